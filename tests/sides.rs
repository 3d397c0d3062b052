//! Which side of a surface reflects: a single-sided material's back is a dark, opaque side
//! (as Mitsuba 3 and pbrt-v4 have it), a double-sided one reflects on both.

mod common;
use canopy::image::Image;
use common::*;
use std::path::{Path, PathBuf};

/// A 2 × 2 quad in the z = 0 plane, wound to face +z (`facing_camera`) or −z, of
/// `material`, seen from a camera at z = 3 looking down −z, with its buffer inline and no
/// light (the default uniform white environment lights it).
fn quad_gltf(dir: &Path, name: &str, facing_camera: bool, material: serde_json::Value) -> PathBuf {
    let corners: [[f32; 3]; 4] = [
        [-1.0, -1.0, 0.0],
        [1.0, -1.0, 0.0],
        [1.0, 1.0, 0.0],
        [-1.0, 1.0, 0.0],
    ];
    let idx: [u32; 6] = match facing_camera {
        true => [0, 1, 2, 0, 2, 3],
        false => [0, 2, 1, 0, 3, 2],
    };
    let used = ["KHR_materials_specular", "KHR_materials_emissive_strength"];
    let mut doc = inline_mesh_gltf(&corners, &idx, material, &used);
    doc["scenes"][0]["nodes"] = serde_json::json!([0, 1]);
    doc["nodes"] = serde_json::json!([{"mesh": 0}, {"camera": 0, "translation": [0.0, 0.0, 3.0]}]);
    doc["cameras"] = serde_json::json!([
        {"type": "perspective", "perspective": {"yfov": 0.3, "aspectRatio": 1.0, "znear": 0.01}}
    ]);
    let path = dir.join(format!("{name}.gltf"));
    std::fs::write(&path, doc.to_string()).unwrap();
    path
}

/// The mean of the image's middle 8 × 8 pixels, all on the quad.
fn middle(img: &Image) -> [f64; 3] {
    let mut sum = [0.0; 3];
    for y in 12..20 {
        for x in 12..20 {
            let p = img.pixels[(y * img.width + x) as usize];
            (0..3).for_each(|c| sum[c] += p[c] as f64 / 64.0);
        }
    }
    sum
}

/// Under the uniform white environment a Lambertian quad of albedo 0.5 seen from its
/// front reflects 0.5. Seen from behind, a single-sided one is dark (0), a double-sided
/// one reflects 0.5 again, and a one-sided emitter shows its dark back (0), in every
/// integrator.
#[test]
fn single_sided_back_faces_are_dark() {
    let dir = tempfile::tempdir().unwrap();
    let grey = |double: bool| {
        serde_json::json!({
            "doubleSided": double,
            "pbrMetallicRoughness": {"baseColorFactor": [0.5, 0.5, 0.5, 1.0], "metallicFactor": 0.0, "roughnessFactor": 1.0},
            "extensions": {"KHR_materials_specular": {"specularFactor": 0.0}}
        })
    };
    let lamp = serde_json::json!({
        "pbrMetallicRoughness": {"baseColorFactor": [0.0, 0.0, 0.0, 1.0], "metallicFactor": 0.0},
        "emissiveFactor": [1.0, 1.0, 1.0],
        "extensions": {"KHR_materials_specular": {"specularFactor": 0.0}, "KHR_materials_emissive_strength": {"emissiveStrength": 2.0}}
    });
    let cases = [
        ("front", true, grey(false), 0.5),
        ("back", false, grey(false), 0.0),
        ("double", false, grey(true), 0.5),
        ("lamp_back", false, lamp, 0.0),
    ];
    for (name, facing, material, want) in cases {
        let gltf = quad_gltf(dir.path(), name, facing, material);
        let arc = dir.path().join(format!("{name}.canopy"));
        convert(&gltf, &arc, None);
        for integrator in ["path", "cone", "pbgi"] {
            let out = dir.path().join(format!("{name}_{integrator}.exr"));
            let seen = middle(&render_sized(&arc, &out, integrator, 16, [32, 32]));
            for c in seen {
                assert!(
                    (c - want).abs() <= 0.02 * want.max(0.5),
                    "{name}, {integrator}: {c} where {want} is expected"
                );
            }
        }
    }
}
