//! In-process fuzzing on stable Rust: archives mutated *with their checksums recomputed* so the
//! damage reaches the decoder, and mutated glTF/PLY/OBJ inputs for the importers.
//!
//! Each case runs open, `--verify`, and a tiny render with the path tracer and the cone
//! integrator (archives), or a conversion (inputs). A case passes when it ends in `Ok` or a
//! clean `Err`; a panic on any thread, or a case that outlives the watchdog, is a failure.
//! Allocation failure aborts the process, which the caller sees as a crash.

use crate::glb::{glb_join, glb_split};
use anyhow::{Context, Result};
use canopy::convert::{convert, ConvertOptions};
use canopy::integrator::cone::ConeSettings;
use canopy::integrator::Settings;
use canopy::render::{render, RenderOptions};
use canopy_format::records::*;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// SplitMix64.
pub struct Rng(u64);
impl Rng {
    pub fn new(seed: u64) -> Rng {
        Rng(seed ^ 0x5EED_F022)
    }
    pub fn u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    pub fn below(&mut self, n: usize) -> usize {
        (self.u64() % n.max(1) as u64) as usize
    }
    fn pick<'a, T>(&mut self, v: &'a [T]) -> &'a T {
        &v[self.below(v.len())]
    }
}

/// The classes of mutation, counted separately in the summary.
pub const CLASSES: [&str; 9] = [
    "archive: random bytes, checksums left stale",
    "archive: truncated or extended",
    "archive: header field, checksums recomputed",
    "archive: page-table field, checksums recomputed",
    "archive: material/camera/light/instance/texture field, checksums recomputed",
    "archive: decoded page bytes (nodes, links, triangles, vertices), recompressed and rechecksummed",
    "archive: page tree rewired (DAG, cycle, shared child), rechecksummed",
    "input: glTF JSON value replaced (accessors, views, buffers, strides, types)",
    "input: PLY/OBJ/MTL/glb bytes or tokens mutated",
];

#[derive(Default)]
pub struct Tally {
    pub cases: [u64; CLASSES.len()],
    pub ok: u64,
    pub errors: u64,
    pub failures: Vec<String>,
}

/// Values that break naive code: zero, all ones, signs, NaN, infinities, huge and tiny.
const WORDS: [u32; 14] = [
    0,
    1,
    2,
    0xFFFF_FFFF,
    0x7FFF_FFFF,
    0x8000_0000,
    0x7FC0_0000, // NaN
    0x7F80_0000, // +inf
    0xFF80_0000, // -inf
    0xBF80_0000, // -1.0
    0x7F7F_FFFF, // f32::MAX
    0x0000_0001, // denormal
    0x0001_0000,
    0x4000_0000,
];

/// An archive taken apart: header, raw (decompressed) pages, tables.
#[derive(Clone)]
pub struct Parts {
    pub header: Header,
    /// Decompressed page bytes (page header, nodes, triangles, vertices, ...).
    pub pages: Vec<Vec<u8>>,
    pub entries: Vec<PageEntry>,
    pub materials: Vec<MaterialRecord>,
    pub cameras: Vec<CameraRecord>,
    pub lights: Vec<LightRecord>,
    pub instances: Vec<InstanceRecord>,
    pub textures: Vec<TextureRecord>,
    /// Decoded texels of each texture tile.
    pub tiles: Vec<Vec<u8>>,
    /// Tile indices in the order their frames lie in the file (the converter writes them
    /// as the pyramid is built, before the pages).
    pub tile_order: Vec<u32>,
}

impl Parts {
    pub fn read(path: &Path) -> Result<Parts> {
        let a = canopy_format::Archive::open(path)?;
        let entries = a.entries()?;
        let pages = (0..a.page_count())
            .map(|i| {
                let e = entries[i as usize];
                Ok(zstd::bulk::decompress(
                    a.page_bytes(i)?,
                    e.raw_len as usize,
                )?)
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Parts {
            header: a.header,
            pages,
            entries,
            materials: a.materials.clone(),
            cameras: a.cameras.clone(),
            lights: a.lights.clone(),
            instances: a.instances.clone(),
            textures: a.textures.clone(),
            tiles: (0..a.tile_count())
                .map(|i| Ok(a.read_tile(i)?))
                .collect::<Result<Vec<_>>>()?,
            tile_order: {
                let mut order: Vec<u32> = (0..a.tile_count()).collect();
                order.sort_by_key(|&i| a.tile_entries()[i as usize].offset);
                order
            },
        })
    }

    /// Writes the archive back with every offset, length, alignment and checksum recomputed,
    /// so only the mutation itself is wrong.
    pub fn assemble(&self) -> Vec<u8> {
        let mut out = vec![0u8; 256];
        let align = |out: &mut Vec<u8>| out.resize(out.len().next_multiple_of(ALIGN as usize), 0);
        let mut tiles = vec![<TileEntry as bytemuck::Zeroable>::zeroed(); self.tiles.len()];
        for &i in &self.tile_order {
            let e = canopy_format::encode_tile(&self.tiles[i as usize], 1).expect("zstd");
            align(&mut out);
            tiles[i as usize] = TileEntry {
                offset: out.len() as u64,
                compressed_len: e.bytes.len() as u32,
                raw_len: canopy_format::TILE_BYTES,
                checksum: e.checksum,
                reserved: [0; 8],
            };
            out.extend_from_slice(&e.bytes);
        }
        let mut entries = self.entries.clone();
        for (e, raw) in entries.iter_mut().zip(&self.pages) {
            let z = zstd::bulk::compress(raw, 1).expect("zstd");
            align(&mut out);
            e.offset = out.len() as u64;
            e.compressed_len = z.len() as u32;
            e.checksum = xxhash_rust::xxh3::xxh3_64(&z);
            e.seal();
            out.extend_from_slice(&z);
        }
        align(&mut out);
        align(&mut out);
        let mut h = self.header;
        let table =
            |out: &mut Vec<u8>, bytes: &[u8], count: usize, size: usize, t: &mut TableRef| {
                t.offset = out.len() as u64;
                t.count = count as u32;
                t.record_size = size as u32;
                out.extend_from_slice(bytes);
            };
        let materials = bytemuck::cast_slice(&self.materials);
        table(
            &mut out,
            materials,
            self.materials.len(),
            128,
            &mut h.materials,
        );
        let cameras = bytemuck::cast_slice(&self.cameras);
        table(&mut out, cameras, self.cameras.len(), 128, &mut h.cameras);
        let lights = bytemuck::cast_slice(&self.lights);
        table(&mut out, lights, self.lights.len(), 96, &mut h.lights);
        let instances = bytemuck::cast_slice(&self.instances);
        table(
            &mut out,
            instances,
            self.instances.len(),
            64,
            &mut h.instances,
        );
        let textures = bytemuck::cast_slice(&self.textures);
        table(&mut out, textures, self.textures.len(), 64, &mut h.textures);
        let tile_table = bytemuck::cast_slice(&tiles);
        table(&mut out, tile_table, tiles.len(), 32, &mut h.tiles);
        h.tables_checksum = xxhash_rust::xxh3::xxh3_64(&out[h.materials.offset as usize..]);
        align(&mut out);
        let pages = bytemuck::cast_slice(&entries);
        table(&mut out, pages, entries.len(), 96, &mut h.pages);
        h.file_len = out.len() as u64;
        h.header_checksum = 0;
        h.header_checksum = xxhash_rust::xxh3::xxh3_64(bytemuck::bytes_of(&h));
        out[..256].copy_from_slice(bytemuck::bytes_of(&h));
        out
    }
}

/// Overwrites an aligned 4-byte word (or a smaller field at its start) with a hostile value.
fn poke(bytes: &mut [u8], rng: &mut Rng) {
    if bytes.len() < 4 {
        return;
    }
    let at = rng.below(bytes.len() / 4) * 4;
    let v = match rng.below(4) {
        0 => rng.u64() as u32,
        1 => (u32::from_le_bytes(bytes[at..at + 4].try_into().expect("4 bytes")))
            .wrapping_add(rng.below(5) as u32)
            .wrapping_sub(2),
        _ => *rng.pick(&WORDS),
    };
    match rng.below(3) {
        0 => bytes[at..at + 2].copy_from_slice(&(v as u16).to_le_bytes()),
        1 => bytes[at] = v as u8,
        _ => bytes[at..at + 4].copy_from_slice(&v.to_le_bytes()),
    }
}

fn poke_record<T: bytemuck::Pod>(records: &mut [T], rng: &mut Rng) {
    if records.is_empty() {
        return;
    }
    let i = rng.below(records.len());
    poke(bytemuck::bytes_of_mut(&mut records[i]), rng);
}

/// Mutates an archive; returns the class index.
pub fn mutate_archive(base: &Parts, raw: &[u8], rng: &mut Rng) -> (usize, Vec<u8>) {
    let class = rng.below(7);
    let mut p = base.clone();
    let bytes = match class {
        0 => {
            let mut b = raw.to_vec();
            for _ in 0..1 + rng.below(8) {
                let i = rng.below(b.len());
                b[i] ^= 1 << rng.below(8);
            }
            b
        }
        1 => {
            let mut b = raw.to_vec();
            if rng.below(2) == 0 {
                b.truncate(rng.below(b.len()));
            } else {
                b.extend((0..1 + rng.below(4096)).map(|_| rng.u64() as u8));
            }
            b
        }
        2 => {
            let mut h = bytemuck::bytes_of(&p.header).to_vec();
            // Leave the table refs and checksums to `assemble`: poke the described fields.
            let fields = [
                8usize, 16, 24, 32, 40, 48, 64, 68, 72, 76, 80, 84, 88, 92, 96, 100, 184, 200, 252,
            ];
            let at = *rng.pick(&fields);
            poke(&mut h[at..at + 4], rng);
            p.header = bytemuck::pod_read_unaligned(&h);
            p.assemble()
        }
        3 => {
            poke_record(&mut p.entries, rng);
            p.assemble()
        }
        4 => {
            match rng.below(5) {
                0 => poke_record(&mut p.materials, rng),
                1 => poke_record(&mut p.cameras, rng),
                2 => poke_record(&mut p.lights, rng),
                3 => poke_record(&mut p.textures, rng),
                _ => poke_record(&mut p.instances, rng),
            }
            p.assemble()
        }
        5 => {
            let i = rng.below(p.pages.len());
            let page = &mut p.pages[i];
            for _ in 0..1 + rng.below(3) {
                // Past the 32-byte page header most of the time: nodes, triangles, vertices.
                let skip = if rng.below(8) == 0 { 0 } else { 32 };
                poke(&mut page[skip..], rng);
            }
            p.assemble()
        }
        _ => {
            rewire(&mut p, rng);
            p.assemble()
        }
    };
    (class, bytes)
}

/// Structural lies that pass every checksum: a DAG inside a page, a page linked twice, a
/// parent link made a cycle.
fn rewire(p: &mut Parts, rng: &mut Rng) {
    let i = rng.below(p.pages.len());
    let n = p.entries[i].node_count as usize;
    let node = |k: usize| 32 + k * 128;
    match rng.below(4) {
        0 if n >= 3 => {
            // Node k: inner, children k+1 and k+2 (a DAG when repeated).
            for k in 0..n.saturating_sub(2) {
                let at = node(k);
                p.pages[i][at + 38] = 0;
                p.pages[i][at + 12..at + 16].copy_from_slice(&((k + 1) as u32).to_le_bytes());
                p.pages[i][at + 16..at + 20].copy_from_slice(&((k + 2) as u32).to_le_bytes());
            }
        }
        1 => {
            let j = rng.below(p.entries.len());
            p.entries[i].parent_page = j as u32;
            p.entries[i].level = p.entries[j].level.wrapping_add(rng.below(3) as u16);
        }
        2 if n >= 2 => {
            // Two nodes point at the same child.
            let (a, b) = (rng.below(n), rng.below(n));
            let link = p.pages[i][node(a) + 12..node(a) + 20].to_vec();
            p.pages[i][node(b) + 12..node(b) + 20].copy_from_slice(&link);
            p.pages[i][node(b) + 38] = p.pages[i][node(a) + 38];
        }
        _ => {
            let j = rng.below(p.entries.len());
            p.entries.swap(i, j);
        }
    }
}

/// Options for a tiny render of `archive` into `dir`.
pub fn tiny_render(archive: &Path, dir: &Path, integrator: Settings) -> RenderOptions {
    RenderOptions {
        archive: archive.to_path_buf(),
        output: dir.join("r.exr"),
        integrator,
        spp: 1,
        time: None,
        noise: None,
        mem_budget: None,
        width: Some(12),
        height: Some(8),
        camera: None,
        seed: 0,
        threads: Some(2),
        max_depth: Some(4),
        texture_filter: canopy::texture::TextureFilter::Trilinear,
        crop: None,
        preview: false,
        exposure: 1.0,
        stats: None,
        node_stats: true,
        progress: false,
    }
}

/// Both integrators, the cone one with small settings for tiny renders.
pub fn integrators() -> [Settings; 2] {
    let cone = ConeSettings {
        samples: Some(64),
        photons: Some(64),
        edge_rays: 2,
        ..ConeSettings::default()
    };
    [Settings::Path, Settings::Cone(cone)]
}

/// Open, verify every page, and render with every integrator that takes the archive (PBGI
/// refuses an instanced one). Errors are fine; the caller catches panics.
pub fn exercise_archive(path: &Path, dir: &Path) -> Result<()> {
    let a = canopy_format::Archive::open(path)?;
    let mut s = canopy::inspect::summarize(&a)?;
    let verified = canopy::inspect::verify(&a, &mut s, false);
    // Integrators that refuse the archive are asked once, for their error.
    let usable: Vec<Settings> = integrators()
        .into_iter()
        .filter(|i| i.check_archive(&a).is_ok())
        .collect();
    drop(a);
    for integrator in usable {
        render(&tiny_render(path, dir, integrator))?;
    }
    verified
}

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
/// emitter, glass and a camera, and a scene file giving the meshes a camera and a lamp.
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
    ]
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
            {"pbrMetallicRoughness": {"roughnessFactor": 0.0, "metallicFactor": 0.0}, "extensions": {"KHR_materials_transmission": {"transmissionFactor": 1.0}}}
        ],
        "extensionsUsed": ["KHR_materials_emissive_strength", "KHR_materials_transmission"],
        "meshes": [{"primitives": [
            {"attributes": {"POSITION": 0, "NORMAL": 1}, "indices": 2, "material": 0},
            {"attributes": {"POSITION": 0, "NORMAL": 1}, "indices": 3, "material": 1}
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

/// The archives mutations start from: the seed inputs converted with small pages, so they
/// have several pages and child-page links.
pub fn seed_archives(dir: &Path) -> Result<Vec<(Parts, Vec<u8>)>> {
    let inputs = seed_inputs();
    let mut out = Vec::new();
    for main in ["s.glb", "m.obj", "a.ply", "i.glb"] {
        let d = dir.join(format!("seed-{main}"));
        std::fs::create_dir_all(&d)?;
        for (name, bytes) in &inputs {
            std::fs::write(d.join(name), bytes)?;
        }
        std::fs::write(d.join("scene.toml"), SEED_SCENE)?;
        let path = d.join("x.canopy");
        let mut o = ConvertOptions::new(vec![d.join(main)], path.clone());
        o.page_nodes = 3;
        if !main.ends_with(".glb") {
            o.scene = Some(d.join("scene.toml"));
        }
        convert(&o).with_context(|| format!("converting the seed {main}"))?;
        out.push((Parts::read(&path)?, std::fs::read(&path)?));
    }
    Ok(out)
}

/// Panics seen on any thread since `install_panic_counter`.
static PANICS: AtomicU64 = AtomicU64::new(0);

/// Counts panics on every thread (a rayon worker's or the prefetcher's included) and keeps
/// the first message.
pub fn install_panic_counter() -> Arc<Mutex<Option<String>>> {
    let first = Arc::new(Mutex::new(None));
    let keep = Arc::clone(&first);
    std::panic::set_hook(Box::new(move |info| {
        PANICS.fetch_add(1, Relaxed);
        keep.lock()
            .expect("panic message")
            .get_or_insert_with(|| info.to_string());
    }));
    first
}

/// Runs `iterations` cases (or until `until`), alternating archives and inputs. A case
/// that runs past `hang` aborts the whole process with its description (it cannot be
/// interrupted in-process). Returns the tally; failures list every panicking case.
pub fn run(
    seed: u64,
    iterations: u64,
    until: Option<Instant>,
    hang: Duration,
    dir: &Path,
    mut log: impl FnMut(&Tally, u64),
) -> Result<Tally> {
    let first_panic = install_panic_counter();
    let archives = seed_archives(dir)?;
    let inputs = seed_inputs();
    let mut rng = Rng::new(seed);
    let mut tally = Tally::default();
    let current: Arc<Mutex<(String, Instant)>> =
        Arc::new(Mutex::new((String::new(), Instant::now())));
    let watch = Arc::clone(&current);
    std::thread::spawn(move || loop {
        std::thread::sleep(Duration::from_millis(500));
        let (what, since) = watch.lock().expect("watchdog").clone();
        if !what.is_empty() && since.elapsed() > hang {
            eprintln!("HANG: case {what} ran past {hang:?}");
            std::process::exit(3);
        }
    });
    let case_dir = dir.join("case");
    let mut i = 0u64;
    while i < iterations && until.is_none_or(|u| Instant::now() < u) {
        std::fs::create_dir_all(&case_dir)?;
        let before = PANICS.load(Relaxed);
        let (class, what, result) = if i.is_multiple_of(2) {
            let (parts, raw) = rng.pick(&archives);
            let (class, bytes) = mutate_archive(parts, raw, &mut rng);
            let path = case_dir.join("m.canopy");
            std::fs::write(&path, &bytes)?;
            let what = format!("{i} (seed {seed}): {}", CLASSES[class]);
            *current.lock().expect("watchdog") = (what.clone(), Instant::now());
            let r = std::panic::catch_unwind(|| exercise_archive(&path, &case_dir));
            (class, what, r.map(|r| r.is_ok()))
        } else {
            let k = rng.below(inputs.len());
            let (name, raw) = &inputs[k];
            let (class, bytes) = mutate_input(name, raw, &mut rng);
            let mut files = inputs.clone();
            files[k].1 = bytes;
            // Mutating the MTL exercises the OBJ that reads it.
            let main = match *name {
                "m.mtl" => "m.obj",
                n => n,
            };
            let what = format!("{i} (seed {seed}): {} in {name}", CLASSES[class]);
            *current.lock().expect("watchdog") = (what.clone(), Instant::now());
            let r = std::panic::catch_unwind(|| exercise_input(&case_dir, &files, main));
            (class, what, r.map(|r| r.is_ok()))
        };
        current.lock().expect("watchdog").0.clear();
        tally.cases[class] += 1;
        match result {
            Ok(true) => tally.ok += 1,
            Ok(false) => tally.errors += 1,
            Err(_) => {}
        }
        if PANICS.load(Relaxed) != before {
            let msg = first_panic.lock().expect("panic message").take();
            tally
                .failures
                .push(format!("{what}: panic: {}", msg.unwrap_or_default()));
        }
        std::fs::remove_dir_all(&case_dir).ok();
        i += 1;
        log(&tally, i);
    }
    Ok(tally)
}

/// The directory for a run's files.
pub fn work_dir(base: Option<PathBuf>) -> Result<tempfile::TempDir> {
    match base {
        Some(b) => tempfile::tempdir_in(b),
        None => tempfile::tempdir(),
    }
    .context("creating the fuzz directory")
}
