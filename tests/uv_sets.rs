//! Texture coordinates as glTF gives them: each texture slot with its own set and its own
//! KHR_texture_transform, checked against Blender Cycles through its own glTF importer.

mod common;
use common::*;

/// `scenes/uvsets.glb` (an unlit checker on TEXCOORD_1 under a rotated, scaled and offset
/// transform; an emitter whose stripes and cut-out mask read two sets under two transforms;
/// a scaled checker on a slanted quad) against Cycles at 4,096 spp: the path tracer's image
/// mean and every 16×16 block within 4 standard errors (blocks inside a quad converge to
/// the texels' decoded values, where the two renderers' sRGB decodes differ by up to 3e-5
/// relative: 1e-4 of the block is allowed besides). A slot reading the other set or
/// another slot's transform moves its pattern and fails every block it covers.
#[test]
fn texture_sets_and_transforms_agree_with_cycles() {
    let dir = tempfile::tempdir().unwrap();
    let arc = dir.path().join("uvsets.canopy");
    convert(&scene("uvsets.glb"), &arc, None);
    let r = reference("uvsets");
    let (img, _) = render(&arc, &dir.path().join("path.exr"), &["--spp", "256"]);
    assert_mean_within_noise(&img, &r, "texture sets, path tracer");
    assert_blocks_within_noise_and(&img, &r, 1e-4, "texture sets, path tracer");
    let report = ok(&["inspect", s(&arc)]);
    assert!(report.contains("texcoords2"), "{report}");
}

/// A material whose textures read three coordinate sets (the archive stores two a vertex)
/// keeps the two its slots name first (base colour, metallic-roughness, emissive, normal,
/// …): the normal texture, on the third set met, is dropped with its scale, a warning names
/// it, and the archive is one its reader accepts and renders.
#[test]
fn a_texture_on_a_third_coordinate_set_is_dropped_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let mut doc: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(scene("bumps/bumps.gltf")).unwrap()).unwrap();
    doc["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"] =
        serde_json::json!({"index": 0});
    doc["materials"][0]["normalTexture"]["texCoord"] = serde_json::json!(1);
    doc["materials"][0]["emissiveTexture"] = serde_json::json!({"index": 0, "texCoord": 2});
    doc["materials"][0]["emissiveFactor"] = serde_json::json!([1.0, 1.0, 1.0]);
    for set in ["TEXCOORD_1", "TEXCOORD_2"] {
        doc["meshes"][0]["primitives"][0]["attributes"][set] = serde_json::json!(1);
    }
    for f in ["bumps.bin", "ridges.png"] {
        std::fs::copy(scene("bumps").join(f), dir.path().join(f)).unwrap();
    }
    let gltf = dir.path().join("three_sets.gltf");
    std::fs::write(&gltf, doc.to_string()).unwrap();
    let arc = dir.path().join("three_sets.canopy");
    let err = succeeds_saying(&["convert", s(&gltf), "-o", s(&arc)]);
    assert!(
        err.contains("material 'floor': its normal texture reads texture coordinates 1"),
        "{err}"
    );
    ok(&["inspect", s(&arc)]);
    let flags = ["--spp", "1", "--width", "16", "--height", "12"];
    let (img, _) = render(&arc, &dir.path().join("o.exr"), &flags);
    assert!(all_finite(&img));
}
