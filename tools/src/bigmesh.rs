//! Makes a huge binary PLY from a real mesh: `--copies` (or enough copies for
//! `--triangles`) of the input, each rotated about y, scaled and placed on a jittered grid,
//! streamed to disk with memory for one copy of the input only. With a `.glb` output the
//! same copies are instances (`EXT_mesh_gpu_instancing`) of one stored mesh: a forest of a
//! billion triangles in a file of a few megabytes.
//!
//!     bigmesh ../shared/data/bunny.ply --triangles 50000000 -o big.ply
//!     bigmesh ../shared/data/bunny.ply --triangles 1000000000 -o forest.glb

use anyhow::{bail, Context, Result};
use clap::Parser;
use std::io::{BufWriter, Write};
use std::path::PathBuf;

#[derive(Parser)]
#[command(
    about = "Generate a huge mesh (binary PLY) from copies of a real one, with bounded memory"
)]
struct Args {
    /// Input mesh (PLY).
    input: PathBuf,
    /// Output: a PLY of every copy's triangles, or a .glb of one mesh and an instance per
    /// copy.
    #[arg(short, long)]
    output: PathBuf,
    /// Number of triangles wanted (rounded up to whole copies).
    #[arg(long, conflicts_with = "copies")]
    triangles: Option<u64>,
    /// Number of copies.
    #[arg(long)]
    copies: Option<u64>,
    /// Seed for the placement jitter.
    #[arg(long, default_value_t = 1)]
    seed: u64,
}

use canopy_tools::jitter::SplitMix as Rng;

fn main() -> Result<()> {
    let a = Args::parse();
    let (verts, tris) = canopy::import::ply::read_mesh(&a.input)?;
    if tris.is_empty() {
        bail!("{}: the mesh is empty (no triangles)", a.input.display());
    }
    let copies = match (a.copies, a.triangles) {
        (Some(c), _) => c,
        (None, Some(t)) => t.div_ceil(tris.len() as u64),
        (None, None) => bail!("give --triangles or --copies"),
    }
    .max(1);
    let glb = a
        .output
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("glb"));
    if !glb && (verts.len() as u64).saturating_mul(copies) > u32::MAX as u64 {
        bail!(
            "{} copies need more than 2^32 vertices, which PLY indices here cannot address",
            copies
        );
    }
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    for v in &verts {
        for k in 0..3 {
            lo[k] = lo[k].min(v[k]);
            hi[k] = hi[k].max(v[k]);
        }
    }
    let size = (0..3).map(|k| hi[k] - lo[k]).fold(0.0f32, f32::max);
    let side = (copies as f64).sqrt().ceil() as u64;
    // Placement of every copy: angle, scale, offset on an x/z grid.
    let mut rng = Rng(a.seed);
    let place: Vec<(f32, f32, [f32; 3])> = (0..copies)
        .map(|c| {
            let (gx, gz) = ((c % side) as f32, (c / side) as f32);
            let jitter = [rng.unit() - 0.5, rng.unit() - 0.5];
            (
                rng.unit() * std::f32::consts::TAU,
                0.7 + 0.6 * rng.unit(),
                [
                    (gx + 0.3 * jitter[0]) * size * 1.2,
                    0.0,
                    (gz + 0.3 * jitter[1]) * size * 1.2,
                ],
            )
        })
        .collect();
    if glb {
        let bytes = instanced_glb(&verts, &tris, lo, &place)?;
        std::fs::write(&a.output, bytes)
            .with_context(|| format!("{}: cannot write", a.output.display()))?;
        eprintln!(
            "{}: {} instanced triangles, {} instances of {} triangles",
            a.output.display(),
            tris.len() as u64 * copies,
            copies,
            tris.len()
        );
        return Ok(());
    }
    let f = std::fs::File::create(&a.output)
        .with_context(|| format!("{}: cannot create", a.output.display()))?;
    let mut w = BufWriter::with_capacity(4 << 20, f);
    let nv = verts.len() as u64 * copies;
    let nf = tris.len() as u64 * copies;
    write!(w, "ply\nformat binary_little_endian 1.0\ncomment bigmesh: {copies} copies of {}\nelement vertex {nv}\nproperty float x\nproperty float y\nproperty float z\nelement face {nf}\nproperty list uchar uint vertex_indices\nend_header\n", a.input.display())?;
    for &(angle, scale, off) in &place {
        let (s, c) = angle.sin_cos();
        for v in &verts {
            let p = [v[0] - lo[0], v[1] - lo[1], v[2] - lo[2]].map(|x| x * scale);
            let q = [
                c * p[0] + s * p[2] + off[0],
                p[1],
                -s * p[0] + c * p[2] + off[2],
            ];
            for x in q {
                w.write_all(&x.to_le_bytes())?;
            }
        }
    }
    for copy in 0..copies {
        let base = (copy * verts.len() as u64) as u32;
        for t in &tris {
            w.write_all(&[3u8])?;
            for i in t {
                w.write_all(&(base + i).to_le_bytes())?;
            }
        }
    }
    w.into_inner().map_err(|e| e.into_error())?.sync_all()?;
    eprintln!(
        "{}: {nf} triangles, {nv} vertices ({copies} copies)",
        a.output.display()
    );
    Ok(())
}

/// A glb of the mesh (shifted so `lo` is its origin, as the PLY copies are) and one
/// instance per placement: translation, rotation about y and uniform scale, giving the
/// PLY's vertices (`rotate(scale · (v − lo)) + offset`).
fn instanced_glb(
    verts: &[[f32; 3]],
    tris: &[[u32; 3]],
    lo: [f32; 3],
    place: &[(f32, f32, [f32; 3])],
) -> Result<Vec<u8>> {
    let mut bin: Vec<u8> = Vec::new();
    let mut views = Vec::new();
    let mut view = |bin: &mut Vec<u8>, data: &[u8]| {
        views.push(
            serde_json::json!({"buffer": 0, "byteOffset": bin.len(), "byteLength": data.len()}),
        );
        bin.extend_from_slice(data);
        views.len() - 1
    };
    let local: Vec<[f32; 3]> = verts
        .iter()
        .map(|v| [0, 1, 2].map(|k| v[k] - lo[k]))
        .collect();
    let (mut vmin, mut vmax) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
    for v in &local {
        for k in 0..3 {
            vmin[k] = vmin[k].min(v[k]);
            vmax[k] = vmax[k].max(v[k]);
        }
    }
    let f32s = |v: &mut dyn Iterator<Item = f32>| v.flat_map(f32::to_le_bytes).collect::<Vec<u8>>();
    let pos = view(&mut bin, &f32s(&mut local.iter().flatten().copied()));
    let idx: Vec<u8> = tris
        .iter()
        .flatten()
        .flat_map(|i| i.to_le_bytes())
        .collect();
    let idx = view(&mut bin, &idx);
    let t = view(&mut bin, &f32s(&mut place.iter().flat_map(|p| p.2)));
    let r = view(
        &mut bin,
        &f32s(&mut place.iter().flat_map(|p| {
            let (s, c) = (0.5 * p.0).sin_cos();
            [0.0, s, 0.0, c]
        })),
    );
    let sc = view(&mut bin, &f32s(&mut place.iter().flat_map(|p| [p.1; 3])));
    let n = place.len();
    let json = serde_json::json!({
        "asset": {"version": "2.0", "generator": "canopy bigmesh"},
        "extensionsUsed": ["EXT_mesh_gpu_instancing"],
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "extensions": {"EXT_mesh_gpu_instancing": {"attributes": {"TRANSLATION": 2, "ROTATION": 3, "SCALE": 4}}}}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
        "buffers": [{"byteLength": bin.len()}],
        "bufferViews": views,
        "accessors": [
            {"bufferView": pos, "componentType": 5126, "count": local.len(), "type": "VEC3", "min": vmin, "max": vmax},
            {"bufferView": idx, "componentType": 5125, "count": tris.len() * 3, "type": "SCALAR"},
            {"bufferView": t, "componentType": 5126, "count": n, "type": "VEC3"},
            {"bufferView": r, "componentType": 5126, "count": n, "type": "VEC4"},
            {"bufferView": sc, "componentType": 5126, "count": n, "type": "VEC3"},
        ],
    });
    let out = canopy_tools::glb::glb_join(&json, &bin);
    if out.len() > u32::MAX as usize {
        bail!("{} bytes of mesh and instances do not fit a glb", out.len());
    }
    Ok(out)
}
