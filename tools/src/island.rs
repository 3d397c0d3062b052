//! A production-scale stand-in for instanced scenes like Disney's Moana island: a glb of a
//! few prototypes placed in nested groups, and a scene file with a camera and a sky.
//!
//! Groves stand on a grid over a ground quad. Each grove holds trees, a field of grass tufts
//! and a few scanned rocks (the input PLY); each tree is a trunk and a crown, and a crown is
//! a group of leaf clusters, each cluster hundreds of leaves. The nesting is the file's:
//! grove nodes hold tree nodes, tree nodes a crown node whose `EXT_mesh_gpu_instancing`
//! places the clusters, and one set of placement accessors serves every crown (and every
//! grove's grass and rocks). A reader that expands it places
//! groves × trees × (1 + clusters) + groves × (grass + rocks) instances.
//!
//!     island scenes/bunny.ply -o island.glb     # 39.1 M instances, 1.08e11 triangles
//!
//! Memory holds the glb being written (the placement accessors are shared, so it is small
//! for its instance count).

use anyhow::{bail, Context, Result};
use clap::Parser;
use serde_json::{json, Value};
use std::path::PathBuf;

#[derive(Parser)]
#[command(about = "Generate a nested-instanced island (glb and scene file) from a scanned mesh")]
struct Args {
    /// The rock mesh (PLY), placed a few times per grove.
    input: PathBuf,
    /// Output glb; the scene file (camera, sky) is written beside it with `.toml`.
    #[arg(short, long)]
    output: PathBuf,
    /// Groves per side of the square island (groves²  groves in all).
    #[arg(long, default_value_t = 16)]
    side: u32,
    /// Trees per grove.
    #[arg(long, default_value_t = 400)]
    trees: u32,
    /// Leaf clusters per tree crown.
    #[arg(long, default_value_t = 300)]
    clusters: u32,
    /// Leaves per cluster (two triangles each).
    #[arg(long, default_value_t = 1750)]
    leaves: u32,
    /// Grass tufts per grove.
    #[arg(long, default_value_t = 32_000)]
    grass: u32,
    /// Rocks per grove.
    #[arg(long, default_value_t = 20)]
    rocks: u32,
    /// Seed for every random choice.
    #[arg(long, default_value_t = 1)]
    seed: u64,
}

use canopy_tools::jitter::SplitMix as Rng;

/// A triangle mesh: positions and indices.
#[derive(Default)]
struct Mesh {
    p: Vec<[f32; 3]>,
    i: Vec<[u32; 3]>,
}

impl Mesh {
    fn quad(&mut self, c: [[f32; 3]; 4]) {
        let b = self.p.len() as u32;
        self.p.extend(c);
        self.i.extend([[b, b + 1, b + 2], [b, b + 2, b + 3]]);
    }
}

/// A tapered trunk of `seg` sides, `h` tall, from the origin up.
fn trunk(seg: u32, h: f32, r: f32) -> Mesh {
    let mut m = Mesh::default();
    for k in 0..seg {
        let a = |k: u32| std::f32::consts::TAU * k as f32 / seg as f32;
        let (s0, c0) = a(k).sin_cos();
        let (s1, c1) = a(k + 1).sin_cos();
        m.quad([
            [r * c0, 0.0, r * s0],
            [0.4 * r * c0, h, 0.4 * r * s0],
            [0.4 * r * c1, h, 0.4 * r * s1],
            [r * c1, 0.0, r * s1],
        ]);
    }
    m
}

/// `n` leaves (quads of side `size`) at random in a ball of radius `r`, facing at random.
fn cluster(n: u32, r: f32, size: f32, rng: &mut Rng) -> Mesh {
    let mut m = Mesh::default();
    for _ in 0..n {
        let c = loop {
            let v = [0, 1, 2].map(|_| 2.0 * rng.unit() - 1.0);
            if v.iter().map(|x| x * x).sum::<f32>() <= 1.0 {
                break v.map(|x| x * r);
            }
        };
        let (a, b) = (rng.unit() * std::f32::consts::TAU, rng.unit() * 3.0);
        let u = [a.cos(), 0.3 * b.sin(), a.sin()].map(|x| x * size);
        let v = [-a.sin() * b.cos(), b.cos().abs() + 0.2, a.cos() * b.sin()].map(|x| x * size);
        let at = |s: f32, t: f32| [0, 1, 2].map(|k| c[k] + s * u[k] + t * v[k]);
        m.quad([at(0.0, 0.0), at(1.0, 0.0), at(1.0, 1.0), at(0.0, 1.0)]);
    }
    m
}

/// A tuft of `n` thin blades, `h` tall, within radius `r`.
fn tuft(n: u32, h: f32, r: f32, rng: &mut Rng) -> Mesh {
    let mut m = Mesh::default();
    for _ in 0..n {
        let (a, d) = (rng.unit() * std::f32::consts::TAU, rng.unit() * r);
        let (x, z) = (d * a.cos(), d * a.sin());
        let w = 0.05 * h;
        let lean = [0.3 * h * a.cos(), 0.3 * h * a.sin()];
        m.quad([
            [x - w, 0.0, z],
            [x + w, 0.0, z],
            [x + lean[0] + 0.2 * w, h, z + lean[1]],
            [x + lean[0] - 0.2 * w, h, z + lean[1]],
        ]);
    }
    m
}

/// Placements: translation, rotation about y (a quaternion) and uniform scale.
struct Placements {
    t: Vec<[f32; 3]>,
    r: Vec<[f32; 4]>,
    s: Vec<f32>,
}

impl Placements {
    /// `n` placements uniform in the box `lo..hi` (y from `lo[1]`), turned at random, scaled
    /// in `scale`.
    fn scatter(n: u32, lo: [f32; 3], hi: [f32; 3], scale: [f32; 2], rng: &mut Rng) -> Self {
        let mut p = Placements {
            t: Vec::new(),
            r: Vec::new(),
            s: Vec::new(),
        };
        for _ in 0..n {
            p.t.push([0, 1, 2].map(|k| lo[k] + rng.unit() * (hi[k] - lo[k])));
            let (s, c) = (rng.unit() * std::f32::consts::PI).sin_cos();
            p.r.push([0.0, s, 0.0, c]);
            p.s.push(scale[0] + rng.unit() * (scale[1] - scale[0]));
        }
        p
    }
}

/// The glb under construction: buffer views and accessors appended to one BIN chunk.
#[derive(Default)]
struct Glb {
    bin: Vec<u8>,
    views: Vec<Value>,
    accessors: Vec<Value>,
}

impl Glb {
    fn accessor(
        &mut self,
        bytes: &[u8],
        count: usize,
        ty: &str,
        ctype: u32,
        extra: Value,
    ) -> usize {
        self.views
            .push(json!({"buffer": 0, "byteOffset": self.bin.len(), "byteLength": bytes.len()}));
        self.bin.extend_from_slice(bytes);
        let mut a = json!({"bufferView": self.views.len() - 1, "componentType": ctype, "count": count, "type": ty});
        if let (Some(a), Value::Object(e)) = (a.as_object_mut(), extra) {
            a.extend(e);
        }
        self.accessors.push(a);
        self.accessors.len() - 1
    }

    fn f32s(&mut self, v: &[f32], count: usize, ty: &str, extra: Value) -> usize {
        self.accessor(bytemuck::cast_slice(v), count, ty, 5126, extra)
    }

    /// A mesh of one primitive with material `mat`.
    fn mesh(&mut self, m: &Mesh, mat: usize) -> Value {
        let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
        for p in &m.p {
            for k in 0..3 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
        }
        let pos = self.f32s(
            m.p.as_flattened(),
            m.p.len(),
            "VEC3",
            json!({"min": lo, "max": hi}),
        );
        let idx = self.accessor(
            bytemuck::cast_slice(&m.i),
            3 * m.i.len(),
            "SCALAR",
            5125,
            json!({}),
        );
        json!({"primitives": [{"attributes": {"POSITION": pos}, "indices": idx, "material": mat}]})
    }

    /// The EXT_mesh_gpu_instancing attributes of `p`.
    fn placements(&mut self, p: &Placements) -> Value {
        let n = p.t.len();
        let scales: Vec<[f32; 3]> = p.s.iter().map(|&s| [s; 3]).collect();
        json!({"EXT_mesh_gpu_instancing": {"attributes": {
            "TRANSLATION": self.f32s(p.t.as_flattened(), n, "VEC3", json!({})),
            "ROTATION": self.f32s(p.r.as_flattened(), n, "VEC4", json!({})),
            "SCALE": self.f32s(scales.as_flattened(), n, "VEC3", json!({})),
        }}})
    }
}

fn main() -> Result<()> {
    let a = Args::parse();
    let (verts, tris) = canopy::import::ply::read_mesh(&a.input)?;
    if tris.is_empty() {
        bail!("{}: the mesh is empty (no triangles)", a.input.display());
    }
    let rock = Mesh { p: verts, i: tris };
    let mut rng = Rng(a.seed);
    let mut glb = Glb::default();
    let meshes = meshes(&a, &rock, &mut glb, &mut rng);
    let nodes = nodes(&a, rock_size(&rock), &mut glb, &mut rng);
    let colour = |c: [f32; 3], rough: f32| json!({"pbrMetallicRoughness": {"baseColorFactor": [c[0], c[1], c[2], 1.0], "metallicFactor": 0.0, "roughnessFactor": rough}, "doubleSided": true});
    let doc = json!({
        "asset": {"version": "2.0", "generator": "canopy island"},
        "extensionsUsed": ["EXT_mesh_gpu_instancing"],
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": nodes,
        "meshes": meshes,
        "materials": [
            colour([0.25, 0.15, 0.08], 0.9),
            colour([0.12, 0.35, 0.08], 0.6),
            colour([0.35, 0.45, 0.12], 0.8),
            colour([0.5, 0.5, 0.48], 0.7),
            colour([0.3, 0.25, 0.18], 1.0),
        ],
        "buffers": [{"byteLength": glb.bin.len()}],
        "bufferViews": glb.views,
        "accessors": glb.accessors,
    });
    let bytes = canopy_tools::glb::glb_join(&doc, &glb.bin);
    std::fs::write(&a.output, bytes)
        .with_context(|| format!("{}: cannot write", a.output.display()))?;
    let scene = write_scene(&a)?;
    let groves = (a.side * a.side) as u64;
    let trees = groves * a.trees as u64;
    let instances = trees * (1 + a.clusters as u64) + groves * (a.grass + a.rocks) as u64;
    let triangles = trees * (32 + a.clusters as u64 * 2 * a.leaves as u64)
        + groves * (a.grass as u64 * 100 + a.rocks as u64 * rock.i.len() as u64)
        + 2;
    eprintln!(
        "{}: {instances} instances placing {triangles} triangles; {} (camera, sky)",
        a.output.display(),
        scene.display()
    );
    Ok(())
}

/// The largest extent of the rock mesh.
fn rock_size(rock: &Mesh) -> f32 {
    (0..3)
        .map(|k| {
            let (lo, hi) = rock
                .p
                .iter()
                .fold((f32::MAX, f32::MIN), |(l, h), v| (l.min(v[k]), h.max(v[k])));
            hi - lo
        })
        .fold(0.0, f32::max)
}

/// The prototypes, as glTF meshes 0 to 4: trunk, leaf cluster, grass tuft, rock, ground.
fn meshes(a: &Args, rock: &Mesh, glb: &mut Glb, rng: &mut Rng) -> Vec<Value> {
    let mut ground = Mesh::default();
    let e = a.side as f32;
    ground.quad([[0.0, 0.0, 0.0], [0.0, 0.0, e], [e, 0.0, e], [e, 0.0, 0.0]]);
    vec![
        glb.mesh(&trunk(16, 0.12, 0.01), 0),
        glb.mesh(&cluster(a.leaves, 0.03, 0.006, rng), 1),
        glb.mesh(&tuft(50, 0.015, 0.01, rng), 2),
        glb.mesh(rock, 3),
        glb.mesh(&ground, 4),
    ]
}

/// The node forest: the island's root over the ground and the groves, each grove over its
/// grass, its rocks and its trees, each tree (a trunk) over its crown. One set of
/// placements serves every crown, and one every grove's grass and rocks.
fn nodes(a: &Args, rock_size: f32, glb: &mut Glb, rng: &mut Rng) -> Vec<Value> {
    let crown = Placements::scatter(
        a.clusters,
        [-0.05, 0.08, -0.05],
        [0.05, 0.16, 0.05],
        [0.6, 1.2],
        rng,
    );
    let grass = Placements::scatter(a.grass, [0.0; 3], [1.0, 0.0, 1.0], [0.7, 1.3], rng);
    let scale = [0.05 / rock_size, 0.15 / rock_size];
    let rocks = Placements::scatter(a.rocks, [0.0; 3], [1.0, 0.0, 1.0], scale, rng);
    let crown = glb.placements(&crown);
    let grass = glb.placements(&grass);
    let rocks = glb.placements(&rocks);
    let mut nodes = vec![
        json!({"name": "island", "children": []}),
        json!({"name": "ground", "mesh": 4}),
    ];
    let mut island = vec![1];
    for g in 0..a.side * a.side {
        let grove = nodes.len();
        island.push(grove);
        nodes.push(json!({"name": format!("grove {g}"), "translation": [(g % a.side) as f32, 0.0, (g / a.side) as f32]}));
        let mut children = Vec::new();
        for (name, mesh, ext) in [("grass", 2, &grass), ("rocks", 3, &rocks)] {
            children.push(nodes.len());
            nodes.push(json!({"name": name, "mesh": mesh, "extensions": ext}));
        }
        for _ in 0..a.trees {
            let (s, c) = (rng.unit() * std::f32::consts::PI).sin_cos();
            let scale = [0.8 + 0.4 * rng.unit(); 3];
            children.push(nodes.len());
            nodes.push(json!({
                "mesh": 0,
                "translation": [rng.unit(), 0.0, rng.unit()],
                "rotation": [0.0, s, 0.0, c],
                "scale": scale,
                "children": [nodes.len() + 1],
            }));
            nodes.push(json!({"mesh": 1, "extensions": crown}));
        }
        nodes[grove]["children"] = json!(children);
    }
    nodes[0]["children"] = json!(island);
    nodes
}

/// The scene file beside the output: a raised camera over one corner, looking across the
/// island at 1920 × 800, and a sky.
fn write_scene(a: &Args) -> Result<PathBuf> {
    let e = a.side as f32;
    let scene = a.output.with_extension("toml");
    std::fs::write(
        &scene,
        format!(
            "[[camera]]\nposition = [{}, {}, {}]\nlook_at = [{}, 0.0, {}]\nyfov_degrees = 40.0\nwidth = 1920\nheight = 800\n\n[environment]\nsky = true\nsun_elevation_degrees = 35.0\n",
            -0.15 * e,
            0.35 * e,
            -0.15 * e,
            0.6 * e,
            0.6 * e
        ),
    )
    .with_context(|| format!("{}: cannot write", scene.display()))?;
    Ok(scene)
}
