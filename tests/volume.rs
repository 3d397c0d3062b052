//! KHR_materials_volume: light inside a transmissive mesh is attenuated as Beer and Lambert
//! say, in every integrator.

mod common;
use canopy::image::Image;
use common::*;
use std::path::{Path, PathBuf};

/// A unit cube (flat faces, wound outward) of index-matched glass (ior 1: no refraction, no
/// reflection) whose inside takes `colour` after `distance`, as a glTF with its buffer
/// inline, no camera and no light.
fn cube_of_glass(dir: &Path, colour: [f32; 3], distance: f32) -> PathBuf {
    let corners: Vec<[f32; 3]> = (0..8)
        .map(|i| [i & 1, i >> 1 & 1, i >> 2 & 1].map(|c| c as f32 - 0.5))
        .collect();
    let idx: [u32; 36] = [
        0, 2, 1, 1, 2, 3, 4, 5, 6, 5, 7, 6, 0, 1, 4, 1, 5, 4, 2, 6, 3, 3, 6, 7, 0, 4, 2, 2, 4, 6,
        1, 3, 5, 3, 7, 5,
    ];
    let material = serde_json::json!({
        "pbrMetallicRoughness": {"metallicFactor": 0.0, "roughnessFactor": 0.0},
        "extensions": {
            "KHR_materials_transmission": {"transmissionFactor": 1.0},
            "KHR_materials_ior": {"ior": 1.0},
            "KHR_materials_volume": {"thicknessFactor": 1.0, "attenuationColor": colour, "attenuationDistance": distance}
        }
    });
    let used = [
        "KHR_materials_transmission",
        "KHR_materials_ior",
        "KHR_materials_volume",
    ];
    let doc = inline_mesh_gltf(&corners, &idx, material, &used);
    let path = dir.join("cube.gltf");
    std::fs::write(&path, doc.to_string()).unwrap();
    path
}

/// The middle pixel of a 33×33 image.
fn middle(img: &Image) -> [f32; 3] {
    let p = img.pixels[(16 * img.width + 16) as usize];
    [p[0], p[1], p[2]]
}

/// Seen straight through a unit cube of index-matched glass under the default uniform
/// white environment, the light that crossed it is exp(−σ·1) of white: the attenuation
/// colour itself when its distance is the cube's side, its square at half the side. A
/// thin wall (thickness 0) attenuates nothing.
#[test]
fn light_through_a_volume_falls_as_beer_lambert_says() {
    let dir = tempfile::tempdir().unwrap();
    let colour = [0.5f32, 0.25, 0.125];
    let shoot = |name: &str, gltf: &Path, integrator: &str| {
        let arc = dir.path().join(format!("{name}.canopy"));
        convert(gltf, &arc, None);
        let flags = [
            "--integrator",
            integrator,
            "--spp",
            "4",
            "--width",
            "33",
            "--height",
            "33",
        ];
        middle(&render(&arc, &dir.path().join(format!("{name}.exr")), &flags).0)
    };
    for (distance, power) in [(1.0f32, 1), (0.5, 2)] {
        let gltf = cube_of_glass(dir.path(), colour, distance);
        for integrator in ["path", "cone", "pbgi"] {
            let seen = shoot(&format!("{integrator}{power}"), &gltf, integrator);
            for c in 0..3 {
                let want = colour[c].powi(power);
                assert!(
                    (seen[c] - want).abs() <= 0.01 * want,
                    "{integrator}, distance {distance}: channel {c} is {} where exp(−σ) is {want}",
                    seen[c]
                );
            }
        }
    }
    let thin = dir.path().join("thin");
    std::fs::create_dir_all(&thin).unwrap();
    let gltf = cube_of_glass(&thin, colour, 1.0);
    let mut doc: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&gltf).unwrap()).unwrap();
    doc["materials"][0]["extensions"]["KHR_materials_volume"]["thicknessFactor"] = 0.0.into();
    std::fs::write(&gltf, doc.to_string()).unwrap();
    let seen = shoot("thin", &gltf, "path");
    assert!(
        seen.iter().all(|&v| (v - 1.0).abs() < 0.01),
        "a thin wall: {seen:?}"
    );
}

/// `scenes/env/glass.glb` (tools/env_scene.py: a smooth teal and a rough amber glass
/// sphere whose insides absorb, on a floor) under `scenes/env/sky.hdr`, against Mitsuba
/// 3's dielectrics with a `homogeneous` absorbing interior (`scenes/refs/env_glass.exr`,
/// tools/crosscheck.py, `volpath`): the path tracer within 4 standard errors over the image
/// and per 16×16 block; the cone integrator and PBGI, at their defaults, within 0.5% in the
/// mean.
#[test]
fn absorbing_glass_matches_mitsuba() {
    let dir = tempfile::tempdir().unwrap();
    let arc = dir.path().join("glass.canopy");
    convert(&scene("env/glass.glb"), &arc, None);
    let sky = scene("env/sky.hdr");
    let run = |integrator: &str, spp: &str| {
        let flags = [
            "--env",
            s(&sky),
            "--integrator",
            integrator,
            "--spp",
            spp,
            "--seed",
            "4",
        ];
        render(&arc, &dir.path().join(format!("{integrator}.exr")), &flags).0
    };
    let reference = reference("env_glass");
    let path = run("path", "256");
    assert_mean_within_noise(&path, &reference, "path tracer, absorbing glass");
    assert_blocks_within_noise(&path, &reference, "path tracer, absorbing glass");
    let cone = run("cone", "64");
    assert_mean_within(&cone, &reference, 0.005, "cone integrator, absorbing glass");
    let pbgi = run("pbgi", "16");
    assert_mean_within(&pbgi, &reference, 0.005, "PBGI, absorbing glass");
}
