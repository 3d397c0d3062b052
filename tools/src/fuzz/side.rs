//! The files Canopy reads beside an archive, mutated as an attacker would: light stores and
//! bake files with every checksum recomputed (so the damage reaches the decoder), bodies
//! replaced by zstd frames that inflate far past what they declare, EXR tiles whose
//! headers declare huge or inverted windows, and scene files with values out of range.
//! Each is exercised by what reads it, under a 64 MiB budget.

use super::{poke, Rng};
use crate::glb::{glb_join, glb_split};
use anyhow::{Context, Result};
use canopy::convert::{convert, ConvertOptions};
use canopy::integrator::pbgi::PbgiSettings;
use canopy::integrator::Settings;
use canopy::render::render;
use canopy_format::bake_parts::BakeParts;
use std::io::Write;
use std::path::{Path, PathBuf};

/// The budget every side-file case renders and checks under.
pub const BUDGET: u64 = 64 << 20;

/// Hostile values for 64-bit size fields.
const SIZES: [u64; 10] = [
    0,
    1,
    1 << 26,
    1 << 32,
    (1 << 32) - 1,
    1 << 34,
    1 << 40,
    u64::MAX,
    u64::MAX / 64,
    357_913_760,
];

/// Hostile values for EXR window coordinates.
const COORDS: [i32; 10] = [
    0,
    -1,
    1,
    65_535,
    65_536,
    69_999,
    99_999,
    33_000,
    i32::MAX / 2 - 1,
    i32::MIN / 2 + 2,
];

/// The seed files: an archive of a rough metal floor under an emitter, its light store,
/// its bake (with glossy coefficients), two EXR tiles of one frame, and a scene file.
pub struct Seeds {
    pub dir: PathBuf,
    pub archive: PathBuf,
    pub store: Vec<u8>,
    pub bake: Vec<u8>,
    pub tiles: [Vec<u8>; 2],
    pub ply: Vec<u8>,
    /// The bundled sky (`scenes/env/sky.hdr`), adaptive run-length scanlines.
    pub hdr: Vec<u8>,
}

/// A scene file that exercises every kind of entry: a camera, a material, three lights.
pub const SIDE_SCENE: &str = "[[camera]]\nposition = [0.5, 0.5, 4.0]\nlook_at = [0.5, 0.5, 0.0]\nup = [0.0, 1.0, 0.0]\nyfov_degrees = 45.0\nwidth = 12\nheight = 8\n\n[[material]]\nname = \"default\"\nbase_color = [0.8, 0.7, 0.6]\nmetallic = 0.5\nroughness = 0.4\nior = 1.5\n\n[[light]]\ntype = \"point\"\nposition = [0.5, 0.5, 2.0]\nintensity = 5.0\n\n[[light]]\ntype = \"spot\"\nposition = [0.5, 2.0, 0.5]\ndirection = [0.0, -1.0, 0.0]\ninner_cone_degrees = 10.0\nouter_cone_degrees = 30.0\n\n[[light]]\ntype = \"directional\"\ndirection = [0.3, -1.0, 0.2]\ncolor = [1.0, 0.9, 0.8]\n";

impl Seeds {
    pub fn new(dir: &Path) -> Result<Seeds> {
        let dir = dir.join("side-seeds");
        std::fs::create_dir_all(&dir)?;
        let inputs = super::seed_inputs();
        let glb = &inputs.iter().find(|(n, _)| *n == "s.glb").expect("s.glb").1;
        let glb_path = dir.join("g.glb");
        std::fs::write(&glb_path, rough_metal(glb))?;
        let archive = dir.join("g.canopy");
        let mut o = ConvertOptions::new(vec![glb_path], archive.clone());
        o.page_nodes = 3;
        convert(&o).context("converting the side seed")?;
        let store = dir.join("l.store");
        let mut cone = super::integrators()[1].clone();
        if let Settings::Cone(c) = &mut cone {
            c.store_out = Some(store.clone());
        }
        render(&super::tiny_render(&archive, &dir, cone))?;
        let bake = dir.join("b.radiance");
        canopy::render::bake::bake(&canopy::render::bake::BakeOptions {
            archive: archive.clone(),
            output: bake.clone(),
            bake: canopy::integrator::flag_defaults(),
            seed: 0,
            mem_budget: None,
            threads: Some(1),
            env: None,
            progress: false,
        })?;
        let mut tiles = [Vec::new(), Vec::new()];
        for (k, crop) in [[0, 6, 0, 8], [6, 12, 0, 8]].into_iter().enumerate() {
            let mut o = super::tiny_render(&archive, &dir, Settings::Path);
            o.crop = Some(crop);
            o.output = dir.join(format!("t{k}.exr"));
            render(&o)?;
            tiles[k] = std::fs::read(&o.output)?;
        }
        let ply = inputs.iter().find(|(n, _)| *n == "a.ply").expect("a.ply");
        Ok(Seeds {
            store: std::fs::read(&store)?,
            bake: std::fs::read(&bake)?,
            tiles,
            ply: ply.1.clone(),
            hdr: std::fs::read(
                Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/env/sky.hdr"),
            )?,
            archive,
            dir,
        })
    }
}

/// The glb seed with its floor made rough metal, so a bake stores glossy coefficients.
fn rough_metal(glb: &[u8]) -> Vec<u8> {
    let (mut json, bin) = glb_split(glb).expect("the seed glb splits");
    let floor = &mut json["materials"][1];
    floor["pbrMetallicRoughness"]["metallicFactor"] = 1.0.into();
    floor["pbrMetallicRoughness"]["roughnessFactor"] = 0.4.into();
    floor["extensions"] = serde_json::json!({});
    glb_join(&json, &bin)
}

/// The side-file classes, in `super::CLASSES` order from `FIRST`.
pub const FIRST: usize = 9;

/// A mutated side file.
pub enum Mutation {
    Store(Vec<u8>),
    Bake(Vec<u8>),
    Tile(Vec<u8>),
    Scene(String),
    Map(Vec<u8>),
}

/// Mutates one side file; returns its class (an index of `super::CLASSES`).
pub fn mutate(s: &Seeds, rng: &mut Rng) -> (usize, Mutation) {
    let which = rng.below(7);
    let m = match which {
        0 => Mutation::Store(mutate_store_header(&s.store, rng)),
        1 => Mutation::Store(mutate_store_body(&s.store, rng)),
        2 => Mutation::Bake(mutate_bake_tables(&s.bake, rng)),
        3 => Mutation::Bake(mutate_bake_blocks(&s.bake, rng)),
        4 => Mutation::Tile(mutate_exr(&s.tiles[rng.below(2)], rng)),
        5 => Mutation::Scene(mutate_scene(rng)),
        _ => Mutation::Map(mutate_hdr(&s.hdr, rng)),
    };
    (FIRST + which, m)
}

/// Runs what reads the mutated file, in `dir`.
pub fn exercise(s: &Seeds, dir: &Path, m: &Mutation) -> Result<()> {
    match m {
        Mutation::Store(b) => store_case(s, dir, b),
        Mutation::Bake(b) => bake_case(s, dir, b),
        Mutation::Tile(b) => tile_case(s, dir, b),
        Mutation::Scene(t) => scene_case(s, dir, t),
        Mutation::Map(b) => map_case(s, dir, b),
    }
}

/// Renders the seed archive under the mutated map, within the budget.
fn map_case(s: &Seeds, dir: &Path, bytes: &[u8]) -> Result<()> {
    let path = dir.join("m.hdr");
    std::fs::write(&path, bytes)?;
    let mut o = super::tiny_render(&s.archive, dir, Settings::Path);
    o.mem_budget = Some(BUDGET);
    o.env = Some(canopy::render::EnvOptions {
        source: canopy::render::EnvSource::Map(path),
        strength: 1.0,
        rotate: 0.0,
        uniform_sampling: false,
    });
    render(&o).map(drop)
}

/// A Radiance map with a header line replaced by a hostile one (a resolution, a format, a
/// header without its blank line), or its scanline bytes flipped, poked or cut.
fn mutate_hdr(seed: &[u8], rng: &mut Rng) -> Vec<u8> {
    let body = seed
        .windows(2)
        .position(|w| w == b"\n\n")
        .map_or(0, |k| k + 2);
    let lines = [
        "-Y 99999 +X 99999\n",
        "-Y 0 +X 8\n",
        "+Y 2 +X 4294967297\n",
        "-Y 128 +X 7\n",
        "-X 128 +Y 256\n",
        "FORMAT=32-bit_rle_xyze\n\n-Y 2 +X 2\n",
    ];
    let mut b = seed.to_vec();
    match rng.below(3) {
        0 => {
            let end = b[body..]
                .iter()
                .position(|&c| c == b'\n')
                .map_or(b.len(), |e| body + e + 1);
            b.splice(body..end, rng.pick(&lines).bytes());
        }
        1 => b.truncate(rng.below(b.len())),
        _ => {
            for _ in 0..1 + rng.below(8) {
                let at = body + rng.below(b.len() - body);
                match rng.below(2) {
                    0 => b[at] ^= 1 << rng.below(8),
                    _ => poke(&mut b[at - at % 4..], rng),
                }
            }
        }
    }
    b
}

fn store_case(s: &Seeds, dir: &Path, bytes: &[u8]) -> Result<()> {
    let path = dir.join("m.store");
    std::fs::write(&path, bytes)?;
    let mut cone = super::integrators()[1].clone();
    if let Settings::Cone(c) = &mut cone {
        c.store_in = Some(path);
    }
    let mut o = super::tiny_render(&s.archive, dir, cone);
    o.mem_budget = Some(BUDGET);
    render(&o).map(drop)
}

fn bake_case(s: &Seeds, dir: &Path, bytes: &[u8]) -> Result<()> {
    let path = dir.join("m.radiance");
    std::fs::write(&path, bytes)?;
    let a = canopy_format::Archive::open(&s.archive)?;
    let r = canopy_format::bake::BakeFile::open(&path, &a)?;
    canopy::inspect::bake(&a, &r, true, Some(BUDGET))?;
    let pbgi = PbgiSettings {
        radiance: Some(path),
        ..PbgiSettings::default()
    };
    let mut o = super::tiny_render(&s.archive, dir, Settings::Pbgi(pbgi));
    o.mem_budget = Some(BUDGET);
    render(&o).map(drop)
}

fn tile_case(s: &Seeds, dir: &Path, bytes: &[u8]) -> Result<()> {
    let (a, b) = (dir.join("a.exr"), dir.join("b.exr"));
    std::fs::write(&a, bytes)?;
    std::fs::write(&b, &s.tiles[1])?;
    let joined =
        canopy::render::assemble::assemble(&[a.clone(), b], &dir.join("f.exr"), Some(BUDGET));
    let t = canopy::image::Image::read_exr(&a)?;
    let r = canopy::image::Image::read_exr(&s.dir.join("t0.exr"))?;
    canopy::metrics::Comparison::new(&t, &r, canopy::metrics::Metric::Rmse, None)?;
    joined.map(drop)
}

fn scene_case(s: &Seeds, dir: &Path, scene: &str) -> Result<()> {
    let (ply, toml) = (dir.join("a.ply"), dir.join("scene.toml"));
    std::fs::write(&ply, &s.ply)?;
    std::fs::write(&toml, scene)?;
    let out = dir.join("sc.canopy");
    let mut o = ConvertOptions::new(vec![ply], out.clone());
    o.scene = Some(toml);
    convert(&o)?;
    let mut r = super::tiny_render(&out, dir, Settings::Path);
    r.mem_budget = Some(BUDGET);
    render(&r).map(drop)
}

/// A store's header fields set to hostile values (sizes, the version, reserved bytes),
/// every checksum recomputed.
fn mutate_store_header(seed: &[u8], rng: &mut Rng) -> Vec<u8> {
    let mut b = seed.to_vec();
    match rng.below(3) {
        0 => {
            let at = [40usize, 48, 64][rng.below(3)];
            b[at..at + 8].copy_from_slice(&SIZES[rng.below(SIZES.len())].to_le_bytes());
        }
        1 => {
            let at = 8 + 4 * rng.below(30);
            poke(&mut b[at..at + 4], rng);
        }
        _ => {
            let entries = u64::from_le_bytes(b[40..48].try_into().expect("8"));
            let d = rng.below(5) as u64;
            b[40..48].copy_from_slice(&entries.wrapping_add(d).wrapping_sub(2).to_le_bytes());
        }
    }
    canopy::light_store::file::reseal(&mut b);
    if rng.below(4) == 0 {
        // Sizes lie while the body's checksum stays what it was.
        b[64..72].copy_from_slice(&SIZES[rng.below(SIZES.len())].to_le_bytes());
    }
    b
}

/// A store's records edited (keys past the archive, values NaN, order), or its body
/// replaced by a frame inflating far past what the header declares; checksums recomputed.
fn mutate_store_body(seed: &[u8], rng: &mut Rng) -> Vec<u8> {
    let mut records = zstd::decode_all(&seed[128..]).expect("the seed store inflates");
    let mut h = canopy::light_store::file::header_of(seed).expect("a header");
    let body = match rng.below(3) {
        0 if records.len() >= 64 => {
            let r = 64 * rng.below(records.len() / 64);
            match rng.below(3) {
                0 => {
                    records[r..r + 8].copy_from_slice(&SIZES[rng.below(SIZES.len())].to_le_bytes())
                }
                _ => poke(&mut records[r..r + 64], rng),
            }
            zstd::encode_all(&records[..], 1).expect("zstd")
        }
        1 => {
            h.entries = [1u64 << 25, 1 << 20, records.len() as u64 / 64 + 1][rng.below(3)];
            bomb(rng.below(256 << 20) + 64, rng.below(2) == 0)
        }
        _ => bomb(records.len() + 64 * rng.below(1 << 20), rng.below(2) == 0),
    };
    let mut b = seed[..128].to_vec();
    canopy::light_store::file::set_header(&mut b, &h);
    b.extend(body);
    canopy::light_store::file::reseal(&mut b);
    b
}

/// One zstd frame of `len` zero bytes, its content size in the frame header or not.
fn bomb(len: usize, pledged: bool) -> Vec<u8> {
    let mut e = zstd::stream::write::Encoder::new(Vec::new(), 1).expect("zstd");
    if pledged {
        e.set_pledged_src_size(Some(len as u64)).expect("zstd");
    }
    let zeros = vec![0u8; 1 << 20];
    let mut left = len;
    while left > 0 {
        let n = left.min(zeros.len());
        e.write_all(&zeros[..n]).expect("zstd");
        left -= n;
    }
    e.finish().expect("zstd")
}

/// A bake's header or block-table fields set to hostile values, checksums recomputed.
fn mutate_bake_tables(seed: &[u8], rng: &mut Rng) -> Vec<u8> {
    let mut b = BakeParts::read(seed).expect("the seed bake");
    match rng.below(3) {
        0 => {
            let mut h = bytemuck::bytes_of(&b.header).to_vec();
            // Past the magic; offsets, lengths and checksums are recomputed by `write`.
            let fields = [8usize, 12, 32, 40, 44, 48, 52, 56, 60, 88, 104, 108, 112];
            let at = fields[rng.below(fields.len())];
            match at {
                104 => h[at..at + 4]
                    .copy_from_slice(&[1u32, 2, 4, 32, 64, 128][rng.below(6)].to_le_bytes()),
                _ => poke(&mut h[at..at + 4], rng),
            }
            b.header = bytemuck::pod_read_unaligned(&h);
        }
        _ => {
            let i = rng.below(b.entries.len());
            let e = &mut b.entries[i];
            match rng.below(3) {
                0 => e.patch_count = SIZES[rng.below(SIZES.len())] as u32,
                1 => e.raw_len = SIZES[rng.below(SIZES.len())] as u32,
                _ => {
                    e.node_count = e
                        .node_count
                        .wrapping_add(rng.below(3) as u32)
                        .wrapping_sub(1)
                }
            }
        }
    }
    b.write()
}

/// A bake's decompressed blocks edited (node records, pyramids, coefficient records and
/// kinds), or a block replaced by zeros declaring a huge patch list; checksums recomputed.
fn mutate_bake_blocks(seed: &[u8], rng: &mut Rng) -> Vec<u8> {
    let mut b = BakeParts::read(seed).expect("the seed bake");
    let i = rng.below(b.blocks.len());
    if rng.below(4) == 0 {
        let patches = [357_913_760u64, 1 << 20, 1 << 24][rng.below(3)];
        let len = (b.entries[i].raw_len as u64 + 12 * patches).min(u32::MAX as u64);
        b.entries[i].patch_count = patches as u32;
        b.entries[i].raw_len = len as u32;
        b.blocks[i] = vec![0; len.min(64 << 20) as usize];
    } else {
        for _ in 0..1 + rng.below(3) {
            if b.blocks[i].len() >= 4 {
                poke(&mut b.blocks[i], rng);
            }
        }
    }
    b.write()
}

/// An EXR tile with a window coordinate of its first header set to a hostile value, a
/// byte flipped, or the file cut short.
fn mutate_exr(seed: &[u8], rng: &mut Rng) -> Vec<u8> {
    let mut b = seed.to_vec();
    let windows = box_offsets(&b);
    match rng.below(4) {
        0 | 1 if !windows.is_empty() => {
            let at = windows[rng.below(windows.len())] + 4 * rng.below(4);
            b[at..at + 4].copy_from_slice(&COORDS[rng.below(COORDS.len())].to_le_bytes());
        }
        2 => {
            let at = rng.below(b.len().min(512));
            b[at] ^= 1 << rng.below(8);
        }
        _ => b.truncate(rng.below(b.len())),
    }
    b
}

/// Where the values of the first header's box attributes lie.
fn box_offsets(b: &[u8]) -> Vec<usize> {
    let mut out = Vec::new();
    for name in [&b"dataWindow\0box2i\0"[..], b"displayWindow\0box2i\0"] {
        if let Some(at) = b.windows(name.len()).position(|w| w == name) {
            out.push(at + name.len() + 4);
        }
    }
    out
}

/// Values that a scene file's fields must refuse or survive.
const SCENE_VALUES: [&str; 14] = [
    "0.0",
    "-1.0",
    "nan",
    "inf",
    "1e39",
    "[0.0, 0.0, 0.0]",
    "[nan, 0.0, 1.0]",
    "[0.5, 0.5, 4.0]",
    "\"spot\"",
    "4294967295",
    "-0.0",
    "[1.0, 1.0]",
    "180.0",
    "0",
];

/// The side scene with one to three values replaced.
fn mutate_scene(rng: &mut Rng) -> String {
    let mut lines: Vec<String> = SIDE_SCENE.lines().map(str::to_string).collect();
    for _ in 0..1 + rng.below(3) {
        let i = rng.below(lines.len());
        if let Some(eq) = lines[i].find(" = ") {
            let key = lines[i][..eq].to_string();
            lines[i] = format!("{key} = {}", SCENE_VALUES[rng.below(SCENE_VALUES.len())]);
        }
    }
    lines.join("\n")
}
