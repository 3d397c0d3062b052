//! Textures a glTF names that have no image Canopy reads (no `source` and no extension
//! Canopy reads offering one, or a `source` out of range) are dropped by name at convert
//! time: the material keeps its factors, the archive renders as its twin without those
//! textures does, and `inspect` lists what was dropped.

mod common;
use common::*;

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
    let twin_arc = dir.path().join("twin.canopy");
    convert(&without, &twin_arc, None);
    let flags = [
        "--spp", "4", "--width", "24", "--height", "24", "--seed", "3",
    ];
    let (a, _) = render(&arc, &dir.path().join("a.exr"), &flags);
    let (b, _) = render(&twin_arc, &dir.path().join("b.exr"), &flags);
    assert!(a.pixels.iter().any(|p| p[0] > 0.0), "a black image");
    assert!(
        a.pixels == b.pixels,
        "the archive renders unlike its twin without the textures"
    );
}
