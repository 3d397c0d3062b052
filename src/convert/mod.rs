//! `canopy convert`: inputs → node archive with bounded memory.
//!
//! 1. Import streams every triangle into a spill file (40 bytes each, 56 with normals) while
//!    tracking bounds.
//! 2. If the triangles exceed one chunk's budget, a Morton histogram of their centroids
//!    splits space into chunks that fit, and a second pass distributes them to chunk files.
//! 3. Each chunk is loaded alone, built (PLOC via obvhs), aggregated, cut into pages and
//!    written; only its root node stays in memory.
//! 4. A balanced tree over the chunk roots (in Morton order) forms the top pages.

mod cluster;
mod pages;
mod spill;
mod tree;

pub use cluster::{MatSummary, REFLECT_COS};
pub use tree::MAX_LEAF_TRIS;

use crate::import::{self, SceneDesc, SceneFile, SpillTri, TriangleSink};
use crate::progress;
use anyhow::{bail, Context, Result};
use canopy_format::{encode_page, ArchiveWriter, EncodedPage, Features, PageMeta, SceneInfo, NONE};
use pages::Plan;
use rayon::prelude::*;
use spill::SpillWriter;
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::mpsc::Sender;
use std::sync::{Condvar, Mutex};
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
    pub bvh: BvhQuality,
    pub progress: bool,
}

impl ConvertOptions {
    /// The defaults of `canopy convert` (2 GiB budget, 512-node pages, zstd level 1,
    /// automatic BVH preset), without progress output.
    pub fn new(inputs: Vec<PathBuf>, output: PathBuf) -> ConvertOptions {
        ConvertOptions {
            inputs,
            output,
            mem_budget: 2 << 30,
            scene: None,
            page_nodes: 512,
            zstd_level: 1,
            bvh: BvhQuality::Auto,
            progress: false,
        }
    }
}

/// How hard the hierarchy builder works (obvhs presets).
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum BvhQuality {
    /// `Medium` for inputs up to `AUTO_FAST_ABOVE` triangles, `Fast` beyond.
    Auto,
    Fast,
    Medium,
}

/// Above this many triangles `auto` picks the fast build: reinsertion costs a fifth of
/// conversion time, which matters at scale; small scenes keep the better tree.
const AUTO_FAST_ABOVE: u64 = 8_000_000;

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

impl std::fmt::Display for ConvertReport {
    /// Two lines: what was made, then where the time went.
    fn fmt(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        let per_s = self.input_triangles as f64 / self.seconds_total.max(1e-9);
        writeln!(
            f,
            "{} triangles -> {} nodes in {} pages ({} chunk{}), {:.2} MiB, {:.1} bytes/triangle",
            self.input_triangles,
            self.nodes,
            self.pages,
            self.chunks,
            if self.chunks == 1 { "" } else { "s" },
            self.archive_bytes as f64 / (1 << 20) as f64,
            self.archive_bytes as f64 / self.input_triangles.max(1) as f64
        )?;
        write!(
            f,
            "  {:.2} s (import {:.2}, partition {:.2}, build {:.2}), {:.2} M triangles/s",
            self.seconds_total,
            self.seconds_import,
            self.seconds_partition,
            self.seconds_build,
            per_s / 1e6
        )
    }
}

struct Spill {
    out: SpillWriter,
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
        self.out.write(&t)?;
        self.count += 1;
        if self.count.is_multiple_of(65536) {
            self.bar.set_position(self.count);
        }
        Ok(())
    }
}

/// Refuses an output path that names one of the inputs or the scene file.
fn refuse_overwriting_an_input(opts: &ConvertOptions) -> Result<()> {
    for input in opts.inputs.iter().chain(&opts.scene) {
        if crate::image::same_file(input, &opts.output) {
            bail!(
                "{}: the output would overwrite the input {}",
                opts.output.display(),
                input.display()
            );
        }
    }
    Ok(())
}

/// Imports every input into `spill`, checking the records each adds (and the scene file's)
/// as the archive reader will, so errors name the file they came from.
fn import_all(
    opts: &ConvertOptions,
    file: &SceneFile,
    scene: &mut SceneDesc,
    spill: &mut Spill,
) -> Result<()> {
    if let Some(p) = &opts.scene {
        scene
            .check_since([0; 3])
            .with_context(|| p.display().to_string())?;
    }
    for input in &opts.inputs {
        let before = scene.counts();
        import::import(input, scene, file, spill)?;
        scene
            .check_since(before)
            .with_context(|| input.display().to_string())?;
    }
    Ok(())
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
    refuse_overwriting_an_input(opts)?;
    let file = match &opts.scene {
        Some(p) => SceneFile::load(p)?,
        None => SceneFile::default(),
    };
    let mut writer = ArchiveWriter::create(&opts.output)?;
    let dir = match opts.output.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let mut scene = SceneDesc {
        cameras: file.cameras(),
        lights: file.lights(),
        ..Default::default()
    };
    let mut spill = Spill {
        out: SpillWriter::create(&dir, 1 << 20)?,
        count: 0,
        lo: [f32::INFINITY; 3],
        hi: [f32::NEG_INFINITY; 3],
        materials_used: Vec::new(),
        bar: progress::counter(opts.progress, "importing", "triangles"),
    };
    import_all(opts, &file, &mut scene, &mut spill)?;
    let Spill {
        out,
        count: total,
        lo: clo,
        hi: chi,
        materials_used,
        bar,
        ..
    } = spill;
    bar.finish_and_clear();
    let spilled = out.finish()?;
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
    let chunk_files: Vec<spill::Spill> = if total <= cap {
        vec![spilled]
    } else {
        let mut hist = vec![0u64; 1 << (3 * MORTON_BITS)];
        spill::for_each(&spilled, |t| {
            hist[morton(t.centroid(), clo, chi) as usize] += 1;
            Ok(())
        })?;
        let (chunk, n) = chunk_of_bins(&hist, cap);
        drop(hist);
        let mut outs = (0..n)
            .map(|_| SpillWriter::create(&dir, 256 << 10))
            .collect::<Result<Vec<_>>>()?;
        let bar = progress::bar(opts.progress, total, "partitioning");
        let mut done = 0u64;
        spill::for_each(&spilled, |t| {
            outs[chunk[morton(t.centroid(), clo, chi) as usize] as usize].write(t)?;
            done += 1;
            if done.is_multiple_of(65536) {
                bar.set_position(done);
            }
            Ok(())
        })?;
        bar.finish_and_clear();
        drop(spilled);
        outs.into_iter()
            .map(SpillWriter::finish)
            .collect::<Result<Vec<_>>>()?
    };
    let chunk_count = chunk_files.len();
    report.chunks = chunk_count as u64;
    report.seconds_partition = t1.elapsed().as_secs_f64();

    // Build chunks.
    let t2 = Instant::now();
    let normals = features & Features::SHADING_NORMALS != 0;
    let bar = progress::bar(opts.progress, total, "building");
    let single = chunk_count == 1;
    let mut top = Tree {
        nodes: Vec::new(),
        tris: Vec::new(),
        root: 0,
    };
    let mut root_page = 0;
    let mut scene_root: Option<BNode> = None;
    let job = ChunkJob {
        files: chunk_files
            .into_iter()
            .map(|f| Mutex::new(Some(f)))
            .collect(),
        mats: &mats,
        single,
        fast: match opts.bvh {
            BvhQuality::Auto => total > AUTO_FAST_ABOVE,
            q => q == BvhQuality::Fast,
        },
        opts,
        normals,
        claim: AtomicUsize::new(0),
        turn: Mutex::new(Turn {
            next: 0,
            base: writer.page_count(),
            failed: false,
        }),
        turn_changed: Condvar::new(),
    };
    // One chunk per worker at a time (the chunk size was divided accordingly). Workers build
    // and compress pages concurrently; page numbers are handed out in chunk order and pages
    // are appended in chunk order, so the archive does not depend on scheduling.
    std::thread::scope(|s| -> Result<()> {
        let (tx, rx) = std::sync::mpsc::channel();
        for _ in 0..threads.min(chunk_count) {
            let tx = tx.clone();
            let job = &job;
            s.spawn(move || job.work(tx));
        }
        drop(tx);
        let mut arrived = BTreeMap::new();
        let mut next = 0;
        for (i, out) in rx {
            arrived.insert(i, out?);
            while let Some(out) = arrived.remove(&next) {
                next += 1;
                let ChunkOut {
                    root,
                    leaf_tris,
                    pages,
                    triangles,
                } = out;
                let first = append_pages(&mut writer, pages)?;
                bar.inc(triangles);
                let Some(root) = root else { continue };
                if single {
                    root_page = first;
                    scene_root = Some(root);
                } else if let Kind::Leaf { count, .. } = root.kind {
                    let at = top.tris.len() as u32;
                    top.tris.extend_from_slice(&leaf_tris);
                    top.nodes.push(BNode {
                        kind: Kind::Leaf { first: at, count },
                        ..root
                    });
                } else {
                    top.nodes.push(BNode {
                        kind: Kind::External { page: first },
                        ..root
                    });
                }
            }
        }
        Ok(())
    })?;
    bar.finish_and_clear();
    if !single {
        let leaves: Vec<u32> = (0..top.nodes.len() as u32).collect();
        top.root = top.balanced(&leaves);
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

/// A chunk's pages, compressed and numbered from `base`, ready to append in order.
struct EncodedPages {
    base: u32,
    pages: Vec<(EncodedPage, PageMeta, Externals)>,
}

/// Per cut node of a page: (page holding its children, its local index).
type Externals = Vec<(u32, u32)>;

struct ChunkOut {
    /// The chunk's root (None for an empty chunk).
    root: Option<BNode>,
    /// The triangles of a root that is a leaf (such a chunk writes no pages).
    leaf_tris: Vec<SpillTri>,
    pages: EncodedPages,
    triangles: u64,
}

/// Next chunk allowed to take page numbers, and the first free number.
struct Turn {
    next: usize,
    base: u32,
    failed: bool,
}

struct ChunkJob<'a> {
    /// Each chunk's spill, taken (and so freed) by the worker that builds it.
    files: Vec<Mutex<Option<spill::Spill>>>,
    mats: &'a [MatSummary],
    single: bool,
    fast: bool,
    opts: &'a ConvertOptions,
    normals: bool,
    claim: AtomicUsize,
    turn: Mutex<Turn>,
    turn_changed: Condvar,
}

impl ChunkJob<'_> {
    /// Claims chunks in increasing order until none is left, sending each result.
    fn work(&self, tx: Sender<(usize, Result<ChunkOut>)>) {
        loop {
            let i = self.claim.fetch_add(1, Ordering::Relaxed);
            if i >= self.files.len() {
                return;
            }
            let out = self.chunk(i);
            let failed = out.is_err();
            // Send before raising the flag, so the first error received is the real one.
            let gone = tx.send((i, out)).is_err();
            if failed {
                self.turn.lock().expect("turn lock").failed = true;
                self.turn_changed.notify_all();
            }
            if failed || gone {
                return;
            }
        }
    }

    fn chunk(&self, i: usize) -> Result<ChunkOut> {
        let spill = self.files[i].lock().expect("chunk lock").take();
        let tris = spill::read_all(&spill.expect("each chunk is claimed once"))?;
        let triangles = tris.len() as u64;
        let tree = (!tris.is_empty()).then(|| Tree::build(tris, self.mats, self.fast));
        let roots = match &tree {
            Some(t) if self.single => vec![t.root],
            Some(t) => match t.nodes[t.root as usize].kind {
                Kind::Inner(children) => children.to_vec(),
                _ => Vec::new(),
            },
            None => Vec::new(),
        };
        let plan = tree
            .as_ref()
            .map(|t| Plan::new(t, roots, self.opts.page_nodes));
        let count = plan.as_ref().map_or(0, |p| p.pages.len() as u32);
        let base = {
            let mut turn = self.turn.lock().expect("turn lock");
            while turn.next != i && !turn.failed {
                turn = self.turn_changed.wait(turn).expect("turn lock");
            }
            if turn.failed {
                bail!("stopped: another chunk failed");
            }
            let base = turn.base;
            turn.base += count;
            turn.next += 1;
            base
        };
        self.turn_changed.notify_all();
        let Some(tree) = tree else {
            return Ok(ChunkOut {
                root: None,
                leaf_tris: Vec::new(),
                pages: EncodedPages {
                    base,
                    pages: Vec::new(),
                },
                triangles,
            });
        };
        let pages = match &plan {
            Some(plan) if count > 0 => encode_pages(&tree, plan, base, self.opts, self.normals)?,
            _ => EncodedPages {
                base,
                pages: Vec::new(),
            },
        };
        let root = tree.nodes[tree.root as usize].clone();
        let leaf_tris = match root.kind {
            Kind::Leaf { first, count } if !self.single => {
                tree.tris[first as usize..(first + count) as usize].to_vec()
            }
            _ => Vec::new(),
        };
        Ok(ChunkOut {
            root: Some(root),
            leaf_tris,
            pages,
            triangles,
        })
    }
}

/// Encodes and compresses a plan's pages (in parallel), numbering them from `base`.
fn encode_pages(
    tree: &Tree,
    plan: &Plan,
    base: u32,
    opts: &ConvertOptions,
    normals: bool,
) -> Result<EncodedPages> {
    let pages = (0..plan.pages.len())
        .into_par_iter()
        .map(|i| {
            let (contents, externals) = plan.encode(tree, i, base, normals);
            let grid = plan.grid(tree, i);
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
            encode_page(&contents, normals, opts.zstd_level).map(|e| (e, meta, externals))
        })
        .collect::<std::io::Result<_>>()
        .context("compressing pages")?;
    Ok(EncodedPages { base, pages })
}

/// Appends encoded pages; they must be numbered from the writer's next page. Returns that
/// first number.
fn append_pages(writer: &mut ArchiveWriter, enc: EncodedPages) -> Result<u32> {
    debug_assert!(enc.pages.is_empty() || enc.base == writer.page_count());
    for (page, meta, externals) in enc.pages {
        let index = writer.push(&page, meta)?;
        for (child, local) in externals {
            writer.set_parent(child, index, local);
        }
    }
    Ok(enc.base)
}

/// Cuts the subtrees under `roots` into pages, encodes them and appends them. Returns the
/// archive index of the first (top) page.
fn write_pages(
    writer: &mut ArchiveWriter,
    tree: &Tree,
    roots: Vec<u32>,
    opts: &ConvertOptions,
    normals: bool,
) -> Result<u32> {
    let plan = Plan::new(tree, roots, opts.page_nodes);
    let enc = encode_pages(tree, &plan, writer.page_count(), opts, normals)?;
    append_pages(writer, enc)
}
