//! Inputs (glTF, PLY, OBJ, MTL) mutated, converted and exercised.

use super::{exercise_archive, poke, Rng};
use crate::glb::{glb_join, glb_split};
use anyhow::Result;
use canopy::convert::{convert, ConvertOptions};
use std::path::Path;

/// A replacement for a glTF JSON value: wrong types, sizes, indices and strides.
fn hostile_json(rng: &mut Rng) -> serde_json::Value {
    use serde_json::json;
    match rng.below(16) {
        0 => json!(0),
        1 => json!(1),
        2 => json!(-1),
        3 => json!(4294967295u64),
        4 => json!(2147483648u64),
        5 => json!(5126), // FLOAT component type
        6 => json!(5125), // UNSIGNED_INT
        7 => json!(5121), // UNSIGNED_BYTE
        8 => json!("VEC3"),
        9 => json!("SCALAR"),
        10 => json!(1e300),
        11 => json!(3),
        12 => json!(4),
        13 => json!(null),
        14 => json!("data:application/octet-stream;base64,AAAA"),
        _ => json!(rng.below(100_000)),
    }
}

/// Replaces one random value (or drops one key) of a JSON document, usually a leaf.
fn mutate_json(v: &mut serde_json::Value, rng: &mut Rng) {
    use serde_json::Value;
    let descend = rng.below(6) != 0;
    match v {
        Value::Object(m) if !m.is_empty() && descend => {
            let keys: Vec<String> = m.keys().cloned().collect();
            let k = rng.pick(&keys).clone();
            if rng.below(12) == 0 {
                m.remove(&k);
            } else if let Some(child) = m.get_mut(&k) {
                mutate_json(child, rng);
            }
        }
        Value::Array(a) if !a.is_empty() && descend => {
            let i = rng.below(a.len());
            mutate_json(&mut a[i], rng);
        }
        _ => *v = hostile_json(rng),
    }
}

/// Tokens that stress a text parser.
const TOKENS: [&str; 12] = [
    "nan",
    "inf",
    "-1",
    "0",
    "4294967296",
    "99999999999999999999",
    "1e39",
    "-0",
    "",
    "/dev/zero",
    "f 1 2",
    "element vertex 4000000000",
];

/// Mutates an input file's bytes: returns the class index and the new bytes.
pub fn mutate_input(name: &str, raw: &[u8], rng: &mut Rng) -> (usize, Vec<u8>) {
    if name.ends_with(".glb") && rng.below(3) != 0 {
        if let Some((mut json, bin)) = glb_split(raw) {
            for _ in 0..1 + rng.below(3) {
                mutate_json(&mut json, rng);
            }
            return (7, glb_join(&json, &bin));
        }
    }
    let mut b = raw.to_vec();
    let text = !name.ends_with(".glb") && !name.ends_with("bin.ply");
    for _ in 0..1 + rng.below(4) {
        if b.is_empty() {
            break;
        }
        let at = rng.below(b.len());
        match rng.below(5) {
            0 => b[at] ^= 1 << rng.below(8),
            1 => b.truncate(at),
            2 if text => {
                let end = b[at..]
                    .iter()
                    .position(|c| c.is_ascii_whitespace())
                    .map_or(b.len(), |e| at + e);
                b.splice(at..end, rng.pick(&TOKENS).bytes());
            }
            3 => {
                let len = rng.below(64).min(b.len() - at);
                let chunk = b[at..at + len].to_vec();
                b.splice(at..at, chunk);
            }
            _ => poke(&mut b[at - at % 4..], rng),
        }
    }
    (8, b)
}

/// Small seed inputs: an OBJ with a material library, ASCII and binary PLYs, a glb with an
/// emitter, glass (with vertex colours), a camera and an extension Canopy does not read (a
/// note), and a scene file giving the meshes a camera and a lamp.
pub fn seed_inputs() -> Vec<(&'static str, Vec<u8>)> {
    let obj = "mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nv 0 0 1\nvn 0 0 1\nusemtl lamp\nf 1//1 2//1 3//1\nusemtl glass\nf 2 4 3\nf 1 3 5\n";
    let mtl = "newmtl lamp\nKd 0.5 0.5 0.5\nKe 4 4 4\nnewmtl glass\nKd 1 1 1\nNi 1.5\nd 0.5\nNs 200\nKs 1 1 1\n";
    let ply = "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\nelement face 2\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n1 1 1\n3 0 1 2\n3 1 3 2\n";
    let mut bply = b"ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\nelement face 2\nproperty list uchar uint vertex_indices\nend_header\n".to_vec();
    for v in [[0f32, 0., 0.], [1., 0., 0.], [0., 1., 0.], [1., 1., 1.]] {
        bply.extend(v.iter().flat_map(|x| x.to_le_bytes()));
    }
    for f in [[0u32, 1, 2], [1, 3, 2]] {
        bply.push(3);
        bply.extend(f.iter().flat_map(|x| x.to_le_bytes()));
    }
    vec![
        ("m.obj", obj.as_bytes().to_vec()),
        ("m.mtl", mtl.as_bytes().to_vec()),
        ("a.ply", ply.as_bytes().to_vec()),
        ("bin.ply", bply),
        ("s.glb", seed_glb(false)),
        ("i.glb", seed_glb(true)),
        // The bundled encodings: Draco and meshopt meshes, WebP and KTX2 textures (each
        // .gltf names its bumps.bin and its image).
        ("d.glb", scene("draco/spheres.glb")),
        ("mo.glb", scene("meshopt/bumps.glb")),
        ("bumps.bin", scene("bumps/bumps.bin")),
        ("ridges.webp", scene("webp/ridges.webp")),
        ("w.gltf", scene("webp/bumps.gltf")),
        ("ridges.ktx2", scene("ktx2/ridges.ktx2")),
        ("k.gltf", scene("ktx2/bumps.gltf")),
    ]
}

/// A bundled scene file's bytes.
fn scene(name: &str) -> Vec<u8> {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../scenes")
        .join(name);
    std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// A glb: two triangles (an emitter over a glass floor), interleaved positions and normals,
/// u16 indices, a camera. `instanced`: also the glass floor as a mesh of its own placed
/// three times (translated, rotated and mirrored, scaled), which `convert` stores once.
fn seed_glb(instanced: bool) -> Vec<u8> {
    let verts: [[f32; 6]; 6] = [
        [-1., 2., -1., 0., -1., 0.],
        [1., 2., -1., 0., -1., 0.],
        [0., 2., 1., 0., -1., 0.],
        [-3., 0., -3., 0., 1., 0.],
        [3., 0., -3., 0., 1., 0.],
        [0., 0., 3., 0., 1., 0.],
    ];
    let mut bin: Vec<u8> = verts
        .iter()
        .flatten()
        .flat_map(|x| x.to_le_bytes())
        .collect();
    for i in [0u16, 2, 1, 3, 5, 4, 0, 0] {
        bin.extend(i.to_le_bytes());
    }
    let mut json = serde_json::json!({
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0, 1]}],
        "nodes": [{"mesh": 0}, {"camera": 0, "translation": [0.0, 1.0, 6.0]}],
        "cameras": [{"type": "perspective", "perspective": {"yfov": 0.8, "znear": 0.01}}],
        "materials": [
            {"emissiveFactor": [1.0, 1.0, 1.0], "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": 5.0}}},
            {"pbrMetallicRoughness": {"roughnessFactor": 0.0, "metallicFactor": 0.0}, "extensions": {
                "KHR_materials_transmission": {"transmissionFactor": 1.0},
                "KHR_materials_clearcoat": {"clearcoatFactor": 0.5, "clearcoatRoughnessFactor": 0.2},
                "KHR_materials_sheen": {"sheenColorFactor": [0.5, 0.4, 0.3], "sheenRoughnessFactor": 0.3}
            }}
        ],
        "extensionsUsed": ["KHR_materials_emissive_strength", "KHR_materials_transmission", "KHR_materials_clearcoat", "KHR_materials_sheen", "KHR_materials_iridescence"],
        "meshes": [{"primitives": [
            {"attributes": {"POSITION": 0, "NORMAL": 1}, "indices": 2, "material": 0},
            {"attributes": {"POSITION": 0, "NORMAL": 1, "COLOR_0": 1}, "indices": 3, "material": 1}
        ]}],
        "buffers": [{"byteLength": bin.len()}],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": 144, "byteStride": 24},
            {"buffer": 0, "byteOffset": 144, "byteLength": 16}
        ],
        "accessors": [
            {"bufferView": 0, "byteOffset": 0, "componentType": 5126, "count": 6, "type": "VEC3", "min": [-3.0, 0.0, -3.0], "max": [3.0, 2.0, 3.0]},
            {"bufferView": 0, "byteOffset": 12, "componentType": 5126, "count": 6, "type": "VEC3"},
            {"bufferView": 1, "byteOffset": 0, "componentType": 5123, "count": 3, "type": "SCALAR"},
            {"bufferView": 1, "byteOffset": 6, "componentType": 5123, "count": 3, "type": "SCALAR"}
        ]
    });
    if !instanced {
        textured(&mut json, &mut bin);
    }
    if instanced {
        json["meshes"].as_array_mut().expect("meshes").push(serde_json::json!(
            {"primitives": [{"attributes": {"POSITION": 0, "NORMAL": 1}, "indices": 3, "material": 1}]}
        ));
        json["nodes"].as_array_mut().expect("nodes").extend([
            serde_json::json!({"mesh": 1, "translation": [0.0, -1.0, -4.0]}),
            serde_json::json!({"mesh": 1, "rotation": [0.0, 0.3826834, 0.0, 0.9238795], "scale": [-1.0, 1.0, 1.0], "translation": [2.0, 0.5, -6.0]}),
            serde_json::json!({"mesh": 1, "scale": [0.5, 2.0, 0.5], "translation": [-2.0, 1.0, -5.0]}),
        ]);
        json["scenes"][0]["nodes"] = serde_json::json!([0, 1, 2, 3, 4]);
    }
    glb_join(&json, &bin)
}

/// Gives the floor of `seed_glb` texture coordinates and an 8×8 RGBA PNG (in the BIN
/// chunk) as a masked base-colour texture, so archives from it hold textures and tiles.
fn textured(json: &mut serde_json::Value, bin: &mut Vec<u8>) {
    let uv_at = bin.len();
    for uv in [
        [0f32, 0.],
        [1., 0.],
        [0.5, 1.],
        [0., 0.],
        [3., 0.],
        [1.5, 2.],
    ] {
        bin.extend(uv.iter().flat_map(|x| x.to_le_bytes()));
    }
    let mut png_bytes = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut png_bytes, 8, 8);
        enc.set_color(png::ColorType::Rgba);
        let mut w = enc.write_header().expect("png header");
        let texels: Vec<u8> = (0..64u8)
            .flat_map(|i| [i * 4, 255 - i * 4, 128, if i % 5 == 0 { 0 } else { 255 }])
            .collect();
        w.write_image_data(&texels).expect("png data");
    }
    let png_at = bin.len();
    bin.extend(&png_bytes);
    while !bin.len().is_multiple_of(4) {
        bin.push(0);
    }
    json["buffers"][0]["byteLength"] = bin.len().into();
    let views = json["bufferViews"].as_array_mut().expect("views");
    views.push(serde_json::json!({"buffer": 0, "byteOffset": uv_at, "byteLength": 48}));
    views.push(
        serde_json::json!({"buffer": 0, "byteOffset": png_at, "byteLength": png_bytes.len()}),
    );
    json["accessors"].as_array_mut().expect("accessors").push(
        serde_json::json!({"bufferView": 2, "componentType": 5126, "count": 6, "type": "VEC2"}),
    );
    json["images"] = serde_json::json!([{"bufferView": 3, "mimeType": "image/png"}]);
    json["textures"] = serde_json::json!([{"source": 0}]);
    json["materials"][1]["pbrMetallicRoughness"]["baseColorTexture"] =
        serde_json::json!({"index": 0});
    json["materials"][1]["alphaMode"] = "MASK".into();
    json["materials"][1]["normalTexture"] = serde_json::json!({"index": 0, "scale": 0.7});
    for p in json["meshes"][0]["primitives"]
        .as_array_mut()
        .expect("primitives")
    {
        p["attributes"]["TEXCOORD_0"] = 4.into();
    }
}

/// The scene file that gives OBJ and PLY seeds a camera and a lamp.
pub const SEED_SCENE: &str = "[[camera]]\nname = \"c\"\nposition = [0.5, 0.5, 4.0]\nlook_at = [0.5, 0.5, 0.0]\nyfov_degrees = 45.0\n\n[[light]]\ntype = \"point\"\nposition = [0.5, 0.5, 2.0]\nintensity = 5.0\n";

/// Converts one (possibly mutated) input set.
pub fn exercise_input(dir: &Path, files: &[(&str, Vec<u8>)], main: &str) -> Result<()> {
    for (name, bytes) in files {
        std::fs::write(dir.join(name), bytes)?;
    }
    let scene = dir.join("scene.toml");
    std::fs::write(&scene, SEED_SCENE)?;
    let out = dir.join("in.canopy");
    let mut o = ConvertOptions::new(vec![dir.join(main)], out.clone());
    o.mem_budget = 256 << 20;
    o.page_nodes = 3 + (main.len() % 5);
    if !main.ends_with(".glb") {
        o.scene = Some(scene);
    }
    convert(&o)?;
    let r = exercise_archive(&out, dir);
    std::fs::remove_file(&out).ok();
    r
}
