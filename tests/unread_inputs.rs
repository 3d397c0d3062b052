//! What an input names but does not hold is dropped by name at convert time, and the rest
//! converts: a glTF texture with no image Canopy reads (no `source` and no extension Canopy
//! reads offering one, or a `source` out of range) leaves its material's factors, rendering
//! as the twin without those textures does; an OBJ's missing material library, or a
//! material no library defines, leaves the mesh's default material, rendering as the twin
//! without `mtllib` and `usemtl` does. `inspect` lists what was dropped.

mod common;
use common::*;
use std::path::Path;

/// `arc` renders, not black, pixel for pixel as `twin` converted does (same seed).
fn renders_as_twin(arc: &Path, twin: &Path, dir: &Path, what: &str) {
    let twin_arc = dir.join("twin.canopy");
    convert(twin, &twin_arc, None);
    let flags = [
        "--spp", "4", "--width", "24", "--height", "24", "--seed", "3",
    ];
    let (a, _) = render(arc, &dir.join("a.exr"), &flags);
    let (b, _) = render(&twin_arc, &dir.join("b.exr"), &flags);
    assert!(a.pixels.iter().any(|p| p[0] > 0.0), "a black image");
    assert!(a.pixels == b.pixels, "{what}");
}

#[test]
fn a_texture_without_an_image_is_dropped_by_name_and_its_factor_kept() {
    let dir = tempfile::tempdir().unwrap();
    let quad = [
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [1.0, 1.0, 0.0],
        [0.0, 1.0, 0.0],
    ];
    let material = serde_json::json!({
        "name": "plate",
        "pbrMetallicRoughness": {"baseColorFactor": [0.8, 0.3, 0.1, 1.0], "metallicFactor": 0.0},
    });
    let twin = inline_mesh_gltf(&quad, &[0, 1, 2, 0, 2, 3], material, &[]);
    let mut doc = twin.clone();
    doc["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"] =
        serde_json::json!({"index": 0});
    doc["materials"][0]["normalTexture"] = serde_json::json!({"index": 1});
    doc["textures"] = serde_json::json!([
        {},
        {"source": 7, "extensions": {"MSFT_texture_dds": {"source": 0}}}
    ]);
    doc["extensionsUsed"] = serde_json::json!(["MSFT_texture_dds"]);
    let write = |name: &str, v: &serde_json::Value| {
        let p = dir.path().join(name);
        std::fs::write(&p, v.to_string()).unwrap();
        p
    };
    let (with, without) = (write("with.gltf", &doc), write("twin.gltf", &twin));
    let arc = dir.path().join("with.canopy");
    let said = succeeds_saying(&["convert", s(&with), "-o", s(&arc)]);
    for expect in [
        "material 'plate': its base colour texture (texture 0) is dropped and its factor kept: it has no image",
        "material 'plate': its normal texture (texture 1) is dropped and its factor kept: it names image 7 of 0",
    ] {
        assert!(said.contains(expect), "expected '{expect}' in {said}");
    }
    let listed = ok(&["inspect", s(&arc)]);
    assert!(listed.contains("texture 0) is dropped"), "{listed}");
    renders_as_twin(
        &arc,
        &without,
        dir.path(),
        "the archive renders unlike its twin without the textures",
    );
}

#[test]
fn an_obj_whose_material_library_is_missing_takes_the_default_material_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let body = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3\nusemtl other\nf 1 3 4\n";
    let with = dir.path().join("with.obj");
    std::fs::write(&with, format!("mtllib gone.mtl\nusemtl shell\n{body}")).unwrap();
    let twin = dir.path().join("twin.obj");
    std::fs::write(&twin, body.replace("usemtl other\n", "")).unwrap();
    let arc = dir.path().join("with.canopy");
    let said = succeeds_saying(&["convert", s(&with), "-o", s(&arc)]);
    for expect in [
        "with.obj:1: material library",
        "gone.mtl not found; faces naming its materials take the mesh's default material",
        "with.obj:2: material 'shell' is in no material library read",
        "with.obj:8: material 'other' is in no material library read",
    ] {
        assert!(said.contains(expect), "expected '{expect}' in {said}");
    }
    assert!(ok(&["inspect", s(&arc)]).contains("gone.mtl not found"));
    renders_as_twin(
        &arc,
        &twin,
        dir.path(),
        "the OBJ renders unlike its twin without materials",
    );
}
