//! `canopy convert`: inputs → node archive with bounded memory.
//!
//! 1. Import streams every triangle into a spill file (56 bytes each) while tracking bounds.
//! 2. If the triangles exceed one chunk's budget, a Morton histogram of their centroids
//!    splits space into chunks that fit, and a second pass distributes them to chunk files.
//! 3. Each chunk is loaded alone, built (PLOC via obvhs), aggregated, cut into pages and
//!    written; only its root node stays in memory.
//! 4. A balanced tree over the chunk roots (in Morton order) forms the top pages.

mod cluster;
mod pages;
mod tree;

pub use cluster::{MatSummary, REFLECT_COS};
pub use tree::MAX_LEAF_TRIS;

use crate::import::{self, SceneDesc, SceneFile, SpillTri, TriangleSink};
use crate::progress;
use anyhow::{bail, Context, Result};
use canopy_format::{encode_page, ArchiveWriter, Features, PageMeta, SceneInfo, NONE};
use pages::Plan;
use rayon::prelude::*;
use std::fs::File;
use std::io::{BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};
use std::time::Instant;
use tree::{BNode, Kind, Tree};

/// Peak bytes one triangle costs while its chunk is built (spill record, PLOC scratch,
/// tree nodes, encoded pages); measured with `/usr/bin/time -v`, see README.
pub const BUILD_BYTES_PER_TRI: u64 = 400;
/// Memory set aside for everything that is not a chunk (code, buffers, histogram).
const FIXED_BYTES: u64 = 96 << 20;
const MORTON_BITS: u32 = 7;

pub struct ConvertOptions {
    pub inputs: Vec<PathBuf>,
    pub output: PathBuf,
    pub mem_budget: u64,
    pub scene: Option<PathBuf>,
    pub page_nodes: usize,
    pub zstd_level: i32,
    pub progress: bool,
}

#[derive(Debug, Default, serde::Serialize)]
pub struct ConvertReport {
    pub input_triangles: u64,
    pub chunks: u64,
    pub nodes: u64,
    pub pages: u64,
    pub archive_bytes: u64,
    pub seconds_import: f64,
    pub seconds_partition: f64,
    pub seconds_build: f64,
    pub seconds_total: f64,
}

struct Spill {
    out: BufWriter<File>,
    path: PathBuf,
    count: u64,
    lo: [f32; 3],
    hi: [f32; 3],
    materials_used: Vec<bool>,
    bar: indicatif::ProgressBar,
}

impl TriangleSink for Spill {
    fn push(&mut self, t: SpillTri) -> Result<()> {
        for (a, c) in t.centroid().into_iter().enumerate() {
            self.lo[a] = self.lo[a].min(c);
            self.hi[a] = self.hi[a].max(c);
        }
        let m = t.material as usize;
        if m >= self.materials_used.len() {
            self.materials_used.resize(m + 1, false);
        }
        self.materials_used[m] = true;
        self.out
            .write_all(bytemuck::bytes_of(&t))
            .with_context(|| format!("{}: writing spill file", self.path.display()))?;
        self.count += 1;
        if self.count.is_multiple_of(65536) {
            self.bar.set_position(self.count);
        }
        Ok(())
    }
}

/// Streams spill records from a file in blocks.
fn for_each_spilled(path: &Path, mut f: impl FnMut(&[SpillTri]) -> Result<()>) -> Result<()> {
    let mut r = BufReader::with_capacity(
        1 << 20,
        File::open(path).with_context(|| format!("{}: reopening spill", path.display()))?,
    );
    let mut block: Vec<SpillTri> = vec![SpillTri::default(); 16384];
    loop {
        let bytes: &mut [u8] = bytemuck::cast_slice_mut(&mut block);
        let full = bytes.len();
        let mut n = 0;
        while n < full {
            let k = r
                .read(&mut bytes[n..])
                .with_context(|| format!("{}: reading spill", path.display()))?;
            if k == 0 {
                break;
            }
            n += k;
        }
        if n % std::mem::size_of::<SpillTri>() != 0 {
            bail!("{}: spill file has a partial record", path.display());
        }
        let m = n / std::mem::size_of::<SpillTri>();
        if m > 0 {
            f(&block[..m])?;
        }
        if n < full {
            return Ok(());
        }
    }
}

fn read_all(path: &Path) -> Result<Vec<SpillTri>> {
    let mut out = Vec::new();
    for_each_spilled(path, |b| {
        out.extend_from_slice(b);
        Ok(())
    })?;
    Ok(out)
}

/// 21-bit Morton code of a point in the box (7 bits an axis): the histogram bin.
fn morton(p: [f32; 3], lo: [f32; 3], hi: [f32; 3]) -> u32 {
    let cells = (1u32 << MORTON_BITS) as f32;
    let q = [0, 1, 2].map(|a| {
        let e = hi[a] - lo[a];
        let t = if e > 0.0 { (p[a] - lo[a]) / e } else { 0.0 };
        ((t * cells) as u32).min((1 << MORTON_BITS) - 1)
    });
    let mut code = 0;
    for bit in (0..MORTON_BITS).rev() {
        for v in q {
            code = (code << 1) | ((v >> bit) & 1);
        }
    }
    code
}

/// Consecutive Morton-bin ranges, each holding at most `cap` triangles (unless one bin alone
/// holds more). Returns the chunk index of each bin.
fn chunk_of_bins(hist: &[u64], cap: u64) -> (Vec<u32>, u32) {
    let mut chunk = vec![0u32; hist.len()];
    let (mut cur, mut fill) = (0u32, 0u64);
    for (b, &h) in hist.iter().enumerate() {
        if fill > 0 && fill + h > cap {
            cur += 1;
            fill = 0;
        }
        fill += h;
        chunk[b] = cur;
    }
    (chunk, cur + 1)
}

pub fn convert(opts: &ConvertOptions) -> Result<ConvertReport> {
    let t0 = Instant::now();
    if opts.inputs.is_empty() {
        bail!("no input files");
    }
    if opts.mem_budget < FIXED_BYTES + 4096 * BUILD_BYTES_PER_TRI {
        bail!(
            "--mem-budget {} is too small: converting needs at least {} MiB",
            opts.mem_budget,
            (FIXED_BYTES + 1024 * BUILD_BYTES_PER_TRI) >> 20
        );
    }
    let file = match &opts.scene {
        Some(p) => SceneFile::load(p)?,
        None => SceneFile::default(),
    };
    let mut writer = ArchiveWriter::create(&opts.output)?;
    let dir = match opts.output.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let spill_dir = tempfile::Builder::new()
        .prefix(".canopy-spill-")
        .tempdir_in(&dir)
        .with_context(|| format!("{}: cannot create a spill directory", dir.display()))?;
    let spill_path = spill_dir.path().join("triangles.bin");
    let mut scene = SceneDesc {
        cameras: file.cameras(),
        lights: file.lights(),
        ..Default::default()
    };
    let mut spill = Spill {
        out: BufWriter::with_capacity(
            1 << 20,
            File::create(&spill_path)
                .with_context(|| format!("{}: cannot create", spill_path.display()))?,
        ),
        path: spill_path.clone(),
        count: 0,
        lo: [f32::INFINITY; 3],
        hi: [f32::NEG_INFINITY; 3],
        materials_used: Vec::new(),
        bar: progress::counter(opts.progress, "importing", "triangles"),
    };
    for input in &opts.inputs {
        import::import(input, &mut scene, &file, &mut spill)?;
    }
    let Spill {
        mut out,
        count: total,
        lo: clo,
        hi: chi,
        materials_used,
        bar,
        ..
    } = spill;
    bar.finish_and_clear();
    out.flush()
        .with_context(|| format!("{}: writing spill file", spill_path.display()))?;
    drop(out);
    let mut report = ConvertReport {
        input_triangles: total,
        seconds_import: t0.elapsed().as_secs_f64(),
        ..Default::default()
    };

    let mats: Vec<MatSummary> = scene.materials.iter().map(MatSummary::of).collect();
    let mut features = 0;
    for (m, _) in mats.iter().zip(&materials_used).filter(|(_, &u)| u) {
        if m.flags & canopy_format::NodeFlags::EMISSIVE != 0 {
            features |= Features::EMITTERS;
        }
        if m.flags & canopy_format::NodeFlags::GLOSSY != 0 {
            features |= Features::GLOSSY;
        }
        if m.flags & canopy_format::NodeFlags::TRANSMISSIVE != 0 {
            features |= Features::TRANSMISSIVE;
        }
    }
    if scene.has_normals {
        features |= Features::SHADING_NORMALS;
    }
    if scene.textured {
        features |= Features::TEXTURED_INPUT;
    }
    if !scene.lights.is_empty() {
        features |= Features::PUNCTUAL_LIGHTS;
    }

    // Partition.
    let t1 = Instant::now();
    let threads = rayon::current_num_threads().max(1);
    let cap = (opts.mem_budget - FIXED_BYTES) / BUILD_BYTES_PER_TRI / threads as u64;
    let chunk_files: Vec<PathBuf> = if total <= cap {
        vec![spill_path.clone()]
    } else {
        let mut hist = vec![0u64; 1 << (3 * MORTON_BITS)];
        for_each_spilled(&spill_path, |b| {
            for t in b {
                hist[morton(t.centroid(), clo, chi) as usize] += 1;
            }
            Ok(())
        })?;
        let (chunk, n) = chunk_of_bins(&hist, cap);
        drop(hist);
        let paths: Vec<PathBuf> = (0..n)
            .map(|i| spill_dir.path().join(format!("chunk{i:05}.bin")))
            .collect();
        let mut outs = paths
            .iter()
            .map(|p| {
                File::create(p)
                    .map(|f| BufWriter::with_capacity(256 << 10, f))
                    .with_context(|| format!("{}: cannot create", p.display()))
            })
            .collect::<Result<Vec<_>>>()?;
        let bar = progress::bar(opts.progress, total, "partitioning");
        for_each_spilled(&spill_path, |b| {
            for t in b {
                let c = chunk[morton(t.centroid(), clo, chi) as usize] as usize;
                outs[c]
                    .write_all(bytemuck::bytes_of(t))
                    .context("writing chunk file")?;
            }
            bar.inc(b.len() as u64);
            Ok(())
        })?;
        bar.finish_and_clear();
        for o in outs.iter_mut() {
            o.flush().context("writing chunk file")?;
        }
        std::fs::remove_file(&spill_path).ok();
        paths
    };
    report.chunks = chunk_files.len() as u64;
    report.seconds_partition = t1.elapsed().as_secs_f64();

    // Build chunks.
    let t2 = Instant::now();
    let normals = features & Features::SHADING_NORMALS != 0;
    let bar = progress::bar(opts.progress, total, "building");
    let single = chunk_files.len() == 1;
    let mut top = Tree {
        nodes: Vec::new(),
        tris: Vec::new(),
        root: 0,
    };
    let mut root_page = 0;
    let mut scene_root: Option<BNode> = None;
    // One chunk per worker at a time (the chunk size was divided accordingly); pages are
    // written in chunk order, so the archive does not depend on scheduling.
    for batch in chunk_files.chunks(threads) {
        let trees = batch
            .par_iter()
            .map(|path| {
                let tris = read_all(path)?;
                std::fs::remove_file(path).ok();
                Ok((!tris.is_empty()).then(|| Tree::build(tris, &mats)))
            })
            .collect::<Result<Vec<_>>>()?;
        for tree in trees.into_iter().flatten() {
            let root = &tree.nodes[tree.root as usize];
            if single {
                root_page = write_pages(&mut writer, &tree, vec![tree.root], opts, normals)?;
                scene_root = Some(root.clone());
            } else if let Kind::Inner(children) = root.kind {
                let page = write_pages(&mut writer, &tree, children.to_vec(), opts, normals)?;
                top.nodes.push(BNode {
                    kind: Kind::External { page },
                    ..root.clone()
                });
            } else if let Kind::Leaf { first, count } = root.kind {
                let at = top.tris.len() as u32;
                top.tris
                    .extend_from_slice(&tree.tris[first as usize..(first + count) as usize]);
                top.nodes.push(BNode {
                    kind: Kind::Leaf { first: at, count },
                    ..root.clone()
                });
            }
            bar.inc(tree.tris.len() as u64);
        }
    }
    bar.finish_and_clear();
    if !single {
        let leaves: Vec<u32> = (0..top.nodes.len() as u32).collect();
        top.root = balanced(&mut top, &leaves);
        root_page = write_pages(&mut writer, &top, vec![top.root], opts, normals)?;
        scene_root = Some(top.nodes[top.root as usize].clone());
    }
    let Some(scene_root) = scene_root else {
        bail!("no triangles in the inputs")
    };
    report.seconds_build = t2.elapsed().as_secs_f64();
    let info = SceneInfo {
        features,
        input_triangles: total,
        bounds_min: scene_root.lo,
        bounds_max: scene_root.hi,
        root_page,
        depth: scene_root.height,
        max_leaf_triangles: MAX_LEAF_TRIS,
        page_nodes_max: opts.page_nodes as u32,
        materials: scene.materials,
        cameras: scene.cameras,
        lights: scene.lights,
    };
    report.pages = writer.page_count() as u64;
    report.nodes = writer.node_count();
    writer.finish(&info)?;
    report.archive_bytes = std::fs::metadata(&opts.output)
        .map(|m| m.len())
        .unwrap_or(0);
    report.seconds_total = t0.elapsed().as_secs_f64();
    Ok(report)
}

/// A balanced binary tree over `items` (kept in order), built with `Tree::join`.
fn balanced(tree: &mut Tree, items: &[u32]) -> u32 {
    match items {
        [one] => *one,
        _ => {
            let (l, r) = items.split_at(items.len() / 2);
            let (l, r) = (balanced(tree, l), balanced(tree, r));
            tree.join(l, r)
        }
    }
}

/// Cuts the subtrees under `roots` into pages, encodes them in parallel and appends them.
/// Returns the archive index of the first (top) page.
fn write_pages(
    writer: &mut ArchiveWriter,
    tree: &Tree,
    roots: Vec<u32>,
    opts: &ConvertOptions,
    normals: bool,
) -> Result<u32> {
    let plan = Plan::new(tree, roots, opts.page_nodes);
    let base = writer.page_count();
    let encoded: Vec<_> = (0..plan.pages.len())
        .into_par_iter()
        .map(|i| {
            let (contents, externals) = plan.encode(tree, i, base, normals);
            let grid = plan.grid(tree, i);
            encode_page(&contents, opts.zstd_level).map(|e| (e, externals, grid))
        })
        .collect::<std::io::Result<_>>()
        .context("compressing pages")?;
    for (i, (page, externals, grid)) in encoded.into_iter().enumerate() {
        let (parent_page, parent_node) = match plan.parent_of(i) {
            Some((p, local)) => (base + p, local),
            None => (NONE, NONE),
        };
        let meta = PageMeta {
            parent_page,
            parent_node,
            root_count: plan.pages[i].roots.len() as u16,
            bounds_min: grid.lo,
            bounds_max: grid.hi,
        };
        let index = writer.push(&page, meta)?;
        for (child, local) in externals {
            writer.set_parent(child, index, local);
        }
    }
    Ok(base)
}
