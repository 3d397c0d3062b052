//! Textured test scenes: a checkerboard PNG written row by row (any size, in bounded memory)
//! and a glTF ground plane that repeats it, seen at a grazing angle under a directional
//! light, so direct light alone makes the image and the texture is all that varies.

use base64::Engine;
use std::path::{Path, PathBuf};

/// A `size`² RGBA PNG of `checks`² squares, dark (sRGB 32) and light (sRGB 224); the
/// alpha channel is 0 in the squares for which `hole(x, y)` holds (by square index).
pub fn checker_png(path: &Path, size: u32, checks: u32, hole: impl Fn(u32, u32) -> bool) {
    let f = std::io::BufWriter::new(std::fs::File::create(path).unwrap());
    let mut enc = png::Encoder::new(f, size, size);
    enc.set_color(png::ColorType::Rgba);
    enc.set_depth(png::BitDepth::Eight);
    enc.set_compression(png::Compression::Fast);
    let mut w = enc.write_header().unwrap().into_stream_writer().unwrap();
    let cell = (size / checks).max(1);
    let mut row = vec![0u8; size as usize * 4];
    for y in 0..size {
        for x in 0..size {
            let (cx, cy) = (x / cell, y / cell);
            let v = if (cx + cy) % 2 == 0 { 224 } else { 32 };
            let a = if hole(cx, cy) { 0 } else { 255 };
            row[x as usize * 4..][..4].copy_from_slice(&[v, v, v, a]);
        }
        std::io::Write::write_all(&mut w, &row).unwrap();
    }
    w.finish().unwrap();
}

/// A `size`² RGBA PNG of one colour.
pub fn solid_png(path: &Path, size: u32, rgba: [u8; 4]) {
    let f = std::io::BufWriter::new(std::fs::File::create(path).unwrap());
    let mut enc = png::Encoder::new(f, size, size);
    enc.set_color(png::ColorType::Rgba);
    enc.set_depth(png::BitDepth::Eight);
    let data: Vec<u8> = (0..size * size).flat_map(|_| rgba).collect();
    enc.write_header().unwrap().write_image_data(&data).unwrap();
}

/// How the plane is seen and textured.
pub struct Plane<'a> {
    /// The image file, relative to the glTF's directory.
    pub image: &'a str,
    /// Texture repeats per scene unit.
    pub repeat: f32,
    /// Camera height above the plane and pitch below the horizon (degrees).
    pub height: f32,
    pub pitch: f32,
    /// glTF alphaMode, or None for opaque.
    pub alpha_mode: Option<&'a str>,
    /// A second, untextured plane this far below (seen through holes), or None.
    pub floor_below: Option<f32>,
    /// Leave out the camera and the light (a scene file gives them).
    pub bare: bool,
    /// A normal texture (image beside the glTF) and its scale, or None.
    pub normal: Option<(&'a str, f32)>,
}

impl Default for Plane<'_> {
    fn default() -> Self {
        Plane {
            image: "checker.png",
            repeat: 0.25,
            height: 1.0,
            pitch: 12.0,
            alpha_mode: None,
            floor_below: None,
            bare: false,
            normal: None,
        }
    }
}

fn le(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

/// Writes `dir/name` (a .gltf with an embedded buffer) and returns its path.
pub fn plane_gltf(dir: &Path, name: &str, p: &Plane) -> PathBuf {
    let (s, near, far) = (60.0f32, 4.0f32, -150.0f32);
    let mut pos = vec![-s, 0.0, near, s, 0.0, near, s, 0.0, far, -s, 0.0, far];
    let mut uv: Vec<f32> = pos
        .chunks(3)
        .flat_map(|v| [v[0] * p.repeat, v[2] * p.repeat])
        .collect();
    let mut idx: Vec<u16> = vec![0, 1, 2, 0, 2, 3];
    if let Some(d) = p.floor_below {
        pos.extend([-s, -d, near, s, -d, near, s, -d, far, -s, -d, far]);
        uv.extend([0.0; 8]);
        idx.extend([4, 5, 6, 4, 6, 7]);
    }
    let n = pos.len() / 3;
    let mut bin = le(&pos);
    let uv_at = bin.len();
    bin.extend(le(&uv));
    let idx_at = bin.len();
    bin.extend(idx.iter().flat_map(|i| i.to_le_bytes()));
    let half = |deg: f32| (deg.to_radians() / 2.0).sin_cos();
    let (ps, pc) = half(-p.pitch);
    let (ls, lc) = half(-60.0);
    // Lambertian: no specular layer, as an MTL material without Ks.
    let mut material = serde_json::json!({
        "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}, "metallicFactor": 0.0, "roughnessFactor": 1.0},
        "extensions": {"KHR_materials_specular": {"specularFactor": 0.0}}
    });
    if let Some(mode) = p.alpha_mode {
        material["alphaMode"] = mode.into();
    }
    let mut images = vec![serde_json::json!({"uri": p.image})];
    let mut textures = vec![serde_json::json!({"source": 0, "sampler": 0})];
    if let Some((image, scale)) = p.normal {
        material["normalTexture"] = serde_json::json!({"index": 1, "scale": scale});
        images.push(serde_json::json!({"uri": image}));
        textures.push(serde_json::json!({"source": 1, "sampler": 0}));
    }
    let mut primitives = vec![serde_json::json!({
        "attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "indices": 2, "material": 0
    })];
    let mut views = vec![
        serde_json::json!({"buffer": 0, "byteOffset": 0, "byteLength": uv_at}),
        serde_json::json!({"buffer": 0, "byteOffset": uv_at, "byteLength": idx_at - uv_at}),
        serde_json::json!({"buffer": 0, "byteOffset": idx_at, "byteLength": 12}),
    ];
    let mut accessors = vec![
        serde_json::json!({"bufferView": 0, "componentType": 5126, "count": n, "type": "VEC3",
             "min": [-s, -p.floor_below.unwrap_or(0.0), far], "max": [s, 0.0, near]}),
        serde_json::json!({"bufferView": 1, "componentType": 5126, "count": n, "type": "VEC2"}),
        serde_json::json!({"bufferView": 2, "componentType": 5123, "count": 6, "type": "SCALAR"}),
    ];
    if p.floor_below.is_some() {
        views.push(serde_json::json!({"buffer": 0, "byteOffset": idx_at + 12, "byteLength": 12}));
        accessors.push(serde_json::json!({"bufferView": 3, "componentType": 5123, "count": 6, "type": "SCALAR"}));
        primitives
            .push(serde_json::json!({"attributes": {"POSITION": 0}, "indices": 3, "material": 1}));
    }
    let mut json = serde_json::json!({
        "asset": {"version": "2.0"},
        "extensionsUsed": ["KHR_lights_punctual", "KHR_materials_specular"],
        "extensions": {"KHR_lights_punctual": {"lights": [{"type": "directional", "intensity": 3.0}]}},
        "scene": 0,
        "scenes": [{"nodes": [0, 1, 2]}],
        "nodes": [
            {"mesh": 0},
            {"camera": 0, "translation": [0.0, p.height, 0.0], "rotation": [ps, 0.0, 0.0, pc]},
            {"extensions": {"KHR_lights_punctual": {"light": 0}}, "rotation": [ls, 0.0, 0.0, lc]}
        ],
        "cameras": [{"type": "perspective", "perspective": {"yfov": 0.7, "znear": 0.01, "aspectRatio": 1.0}}],
        "meshes": [{"primitives": primitives}],
        "materials": [material, {"pbrMetallicRoughness": {"baseColorFactor": [0.5, 0.1, 0.1, 1.0], "metallicFactor": 0.0}}],
        "textures": textures,
        "samplers": [{"wrapS": 10497, "wrapT": 10497}],
        "images": images,
        "buffers": [{
            "byteLength": bin.len(),
            "uri": format!("data:application/octet-stream;base64,{}", base64::engine::general_purpose::STANDARD.encode(&bin))
        }],
        "bufferViews": views,
        "accessors": accessors
    });
    if p.bare {
        json["scenes"][0]["nodes"] = serde_json::json!([0]);
    }
    let path = dir.join(name);
    std::fs::write(&path, serde_json::to_vec_pretty(&json).unwrap()).unwrap();
    path
}

/// A `size`² RGBA PNG whose left half (x < size/2) is white and right half black.
pub fn halves_png(path: &Path, size: u32) {
    let f = std::io::BufWriter::new(std::fs::File::create(path).unwrap());
    let mut enc = png::Encoder::new(f, size, size);
    enc.set_color(png::ColorType::Rgba);
    enc.set_depth(png::BitDepth::Eight);
    let data: Vec<u8> = (0..size * size)
        .flat_map(|i| {
            let v = if i % size < size / 2 { 255 } else { 0 };
            [v, v, v, 255]
        })
        .collect();
    enc.write_header().unwrap().write_image_data(&data).unwrap();
}

/// Writes `dir/name`: a white Lambertian floor (4 × 4 at y = 0) under a one-sided lamp
/// facing down at y = 1.5 over x ∈ [x0, x1], z ∈ [−1, 1] (u along x from x0 to x1),
/// radiance 5 times `image`'s texel (sRGB) when given; the camera looks down at the floor
/// from below the lamp's height.
pub fn lamp_gltf(dir: &Path, name: &str, (x0, x1): (f32, f32), image: Option<&str>) -> PathBuf {
    let pos = [
        -2.0, 0.0, 2.0, 2.0, 0.0, 2.0, 2.0, 0.0, -2.0, -2.0, 0.0, -2.0, // floor
        x0, 1.5, -1.0, x1, 1.5, -1.0, x1, 1.5, 1.0, x0, 1.5, 1.0, // lamp
    ];
    let uv = [
        0.0f32, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 1.0, 1.0, 0.0, 1.0,
    ];
    let idx: [u16; 12] = [0, 1, 2, 0, 2, 3, 4, 5, 6, 4, 6, 7];
    let mut bin = le(&pos);
    let uv_at = bin.len();
    bin.extend(le(&uv));
    let idx_at = bin.len();
    bin.extend(idx.iter().flat_map(|i| i.to_le_bytes()));
    let (ps, pc) = (-35f32.to_radians() / 2.0).sin_cos();
    let mut lamp = serde_json::json!({
        "pbrMetallicRoughness": {"baseColorFactor": [0.0, 0.0, 0.0, 1.0], "metallicFactor": 0.0},
        "emissiveFactor": [1.0, 1.0, 1.0],
        "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": 5.0}}
    });
    let mut json = serde_json::json!({
        "asset": {"version": "2.0"},
        "extensionsUsed": ["KHR_materials_specular", "KHR_materials_emissive_strength"],
        "scene": 0,
        "scenes": [{"nodes": [0, 1]}],
        "nodes": [
            {"mesh": 0},
            {"camera": 0, "translation": [0.0, 1.2, 2.5], "rotation": [ps, 0.0, 0.0, pc]}
        ],
        "cameras": [{"type": "perspective", "perspective": {"yfov": 0.8, "znear": 0.01, "aspectRatio": 1.0}}],
        "meshes": [{"primitives": [
            {"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "indices": 2, "material": 0},
            {"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "indices": 3, "material": 1}
        ]}],
        "materials": [
            {"pbrMetallicRoughness": {"baseColorFactor": [0.8, 0.8, 0.8, 1.0], "metallicFactor": 0.0, "roughnessFactor": 1.0},
             "extensions": {"KHR_materials_specular": {"specularFactor": 0.0}}},
            lamp.clone()
        ],
        "buffers": [{
            "byteLength": bin.len(),
            "uri": format!("data:application/octet-stream;base64,{}", base64::engine::general_purpose::STANDARD.encode(&bin))
        }],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": uv_at},
            {"buffer": 0, "byteOffset": uv_at, "byteLength": idx_at - uv_at},
            {"buffer": 0, "byteOffset": idx_at, "byteLength": 12},
            {"buffer": 0, "byteOffset": idx_at + 12, "byteLength": 12}
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 8, "type": "VEC3",
             "min": [-2.0, 0.0, -2.0], "max": [2.0, 1.5, 2.0]},
            {"bufferView": 1, "componentType": 5126, "count": 8, "type": "VEC2"},
            {"bufferView": 2, "componentType": 5123, "count": 6, "type": "SCALAR"},
            {"bufferView": 3, "componentType": 5123, "count": 6, "type": "SCALAR"}
        ]
    });
    if let Some(image) = image {
        lamp["emissiveTexture"] = serde_json::json!({"index": 0});
        json["materials"][1] = lamp;
        json["textures"] = serde_json::json!([{"source": 0, "sampler": 0}]);
        json["samplers"] = serde_json::json!([{"wrapS": 33071, "wrapT": 33071}]);
        json["images"] = serde_json::json!([{"uri": image}]);
    }
    let path = dir.join(name);
    std::fs::write(&path, serde_json::to_vec_pretty(&json).unwrap()).unwrap();
    path
}
