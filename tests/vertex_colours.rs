//! Vertex colours: glTF `COLOR_0`, PLY `red green blue (alpha)` and OBJ `v x y z r g b`
//! multiply the base colour in every integrator.

mod common;
use canopy::image::Image;
use common::*;
use std::path::Path;

/// IEC 61966-2-1's decoding, written out here rather than taken from the code under test.
fn srgb_decode(v: f64) -> f64 {
    if v <= 0.04045 {
        v / 12.92
    } else {
        ((v + 0.055) / 1.055).powf(2.4)
    }
}

/// A unit quad facing +z as PLY with an 8-bit colour per vertex.
fn quad_ply(path: &Path, colours: &[[u8; 3]; 4]) {
    let mut text = String::from(
        "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n\
         property float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n\
         element face 1\nproperty list uchar int vertex_indices\nend_header\n",
    );
    for (i, [r, g, b]) in colours.iter().enumerate() {
        let (x, y) = ((i == 1 || i == 2) as u8, (i >= 2) as u8);
        text += &format!("{x} {y} 0 {r} {g} {b}\n");
    }
    text += "4 0 1 2 3\n";
    std::fs::write(path, text).unwrap();
}

/// The same quad as OBJ, its colours as `v` lines' r g b in [0, 1].
fn quad_obj(path: &Path, colours: &[[u8; 3]; 4]) {
    let mut text = String::new();
    for (i, [r, g, b]) in colours.iter().enumerate() {
        let (x, y) = ((i == 1 || i == 2) as u8, (i >= 2) as u8);
        let c = |v: u8| v as f64 / 255.0;
        text += &format!("v {x} {y} 0 {} {} {}\n", c(*r), c(*g), c(*b));
    }
    text += "f 1 2 3 4\n";
    std::fs::write(path, text).unwrap();
}

/// Per channel, the ratio of two images' means.
fn ratio(a: &Image, b: &Image) -> [f64; 3] {
    let (ma, mb) = (a.mean(), b.mean());
    [0, 1, 2].map(|c| ma[c] / mb[c])
}

/// A PLY's and an OBJ's 8-bit colours are sRGB-encoded base colours: a quad coloured
/// (200, 100, 30) at every vertex renders as the same quad whose material's base colour is
/// that colour decoded, and a quad whose corners differ renders the same from PLY and OBJ.
#[test]
fn ply_and_obj_colours_are_srgb_encoded_base_colours() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let c = [200u8, 100, 30];
    let flat = [c; 4];
    quad_ply(&d.join("flat.ply"), &flat);
    quad_obj(&d.join("flat.obj"), &flat);
    quad_ply(&d.join("plain.ply"), &[[255; 3]; 4]);
    let base = c.map(|v| srgb_decode(v as f64 / 255.0));
    let toml = d.join("plain.toml");
    std::fs::write(
        &toml,
        format!(
            "[[material]]\nname = \"default\"\nbase_color = [{}, {}, {}]\n",
            base[0], base[1], base[2]
        ),
    )
    .unwrap();
    let shoot = |name: &str, input: &str, scene: Option<&Path>| {
        let arc = d.join(format!("{name}.canopy"));
        convert(&d.join(input), &arc, scene);
        let flags = ["--spp", "4", "--width", "64", "--height", "64"];
        render(&arc, &d.join(format!("{name}.exr")), &flags).0
    };
    let plain = shoot("plain", "plain.ply", Some(&toml));
    for (name, input) in [("ply", "flat.ply"), ("obj", "flat.obj")] {
        let r = ratio(&shoot(name, input, None), &plain);
        assert!(
            r.iter().all(|x| (x - 1.0).abs() < 2e-3),
            "{name}: colour over material {r:?}"
        );
    }
    let corners = [[255, 0, 0], [0, 255, 0], [0, 0, 255], [128, 128, 128]];
    quad_ply(&d.join("corners.ply"), &corners);
    quad_obj(&d.join("corners.obj"), &corners);
    let (ply, obj) = (
        shoot("corners_ply", "corners.ply", None),
        shoot("corners_obj", "corners.obj", None),
    );
    assert!(rmse(&ply, &obj) < 1e-3 * ply.mean().iter().sum::<f64>());
    let r = ratio(&ply, &plain);
    assert!(
        r.iter().all(|&x| x > 0.2),
        "every channel shows on the corners' quad: {r:?}"
    );
}

/// `scenes/colours.glb` (tools/colour_scene.py: a room whose floor, back wall and two
/// bunnies take their colour from COLOR_0 as bytes, shorts and floats, RGB and RGBA)
/// against Mitsuba 3's `mesh_attribute` of the same colours (`scenes/refs/colours.exr`,
/// tools/crosscheck.py): the path tracer within 4 standard errors over the image and per
/// 16×16 block; the cone integrator and PBGI, at their defaults, within 0.5% in the mean.
#[test]
fn vertex_colours_match_mitsuba() {
    let dir = tempfile::tempdir().unwrap();
    let arc = dir.path().join("colours.canopy");
    convert(&scene("colours.glb"), &arc, None);
    let reference = reference("colours");
    let run = |name: &str, flags: &[&str]| {
        let flags = [&["--seed", "3"][..], flags].concat();
        render(&arc, &dir.path().join(format!("{name}.exr")), &flags).0
    };
    let path = run("path", &["--integrator", "path", "--spp", "256"]);
    assert_mean_within_noise(&path, &reference, "path tracer, vertex colours");
    assert_blocks_within_noise(&path, &reference, "path tracer, vertex colours");
    let cone = run("cone", &["--integrator", "cone", "--spp", "128"]);
    assert_mean_within(&cone, &reference, 0.005, "cone integrator, vertex colours");
    assert_blocks_within(&cone, &reference, 0.05, "cone integrator, vertex colours");
    let pbgi = run("pbgi", &["--integrator", "pbgi", "--spp", "16"]);
    assert_mean_within(&pbgi, &reference, 0.005, "PBGI, vertex colours");
    assert_blocks_within(&pbgi, &reference, 0.05, "PBGI, vertex colours");
}
