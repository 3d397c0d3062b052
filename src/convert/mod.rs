//! `canopy convert`: inputs → node archive with bounded memory, in stages:
//!
//! 1. `ingest`: every triangle streams into a spill file (`spill`: 40 bytes each, 56 with
//!    normals) while bounds are tracked.
//! 2. `partition`: if the triangles exceed one chunk's budget, a Morton histogram of their
//!    centroids splits space into chunks that fit, written to one spill file each.
//! 3. `chunks`: each chunk is loaded alone and built (`tree`: PLOC via obvhs), its nodes'
//!    attributes aggregated (`cluster`), cut into pages and encoded (`pages`); only its root
//!    stays in memory. A balanced tree over the chunk roots forms the top pages.
//!
//! Meshes placed more than once (`instances`) are built first, each as its own tree through
//! stages 2–3; their instances become leaves of the top tree.

mod aggregate;
mod chunks;
mod ingest;
mod instances;
mod ktx2;
mod morton;
mod pages;
mod partition;
mod record_spill;
mod spill;
pub mod stages;
mod textures;
mod tree;

pub use aggregate::{MatSummary, MatTable, REFLECT_COS};
pub use tree::MAX_LEAF_TRIS;

use crate::import::SceneFile;
use anyhow::{bail, Context, Result};
use canopy_format::{ArchiveWriter, SceneInfo, Streams};
use std::path::{Path, PathBuf};
use std::time::Instant;
use tree::BNode;

/// Peak bytes one triangle costs while its chunk is built (spill record, PLOC scratch,
/// tree nodes, encoded pages); measured with `/usr/bin/time -v`, see README. At 440 (too
/// few once triangles carried texture coordinates) the 50 M mesh peaked at 2012 MiB of its
/// 2 GiB budget; at 464, 250 M triangles in chunks of 4.2 M peaked at 4261 MiB of 4 GiB.
pub const BUILD_BYTES_PER_TRI: u64 = 496;
/// Memory set aside for everything that is not a chunk (code, buffers, histogram).
const FIXED_BYTES: u64 = 96 << 20;

pub struct ConvertOptions {
    pub inputs: Vec<PathBuf>,
    pub output: PathBuf,
    pub mem_budget: u64,
    pub scene: Option<PathBuf>,
    pub page_nodes: usize,
    pub zstd_level: i32,
    pub bvh: BvhQuality,
    /// Store every placement of a mesh as its own triangles (no instances).
    pub flatten_instances: bool,
    /// A texture file that does not exist: an error, or a warning and the factor alone.
    pub missing_textures: MissingTextures,
    pub progress: bool,
}

/// What `convert` does about a texture file that is not there.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum MissingTextures {
    Error,
    /// Warn, and let the materials keep their factors alone.
    Warn,
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
            flatten_instances: false,
            missing_textures: MissingTextures::Error,
            progress: false,
        }
    }
}

/// How hard the hierarchy builder works (obvhs presets).
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum BvhQuality {
    /// Medium for inputs up to 8 M triangles, fast beyond.
    Auto,
    Fast,
    Medium,
}

/// Above this many triangles `auto` picks the fast build: reinsertion costs a fifth of
/// conversion time, which matters at scale; small scenes keep the better tree.
const AUTO_FAST_ABOVE: u64 = 8_000_000;

#[derive(Clone, Debug, Default, serde::Serialize, serde::Deserialize)]
pub struct ConvertReport {
    /// The archive written.
    pub output: PathBuf,
    /// Triangles the inputs place (each instance's counted).
    pub input_triangles: u64,
    /// Meshes stored once, and their placements.
    pub prototypes: u64,
    pub instances: u64,
    pub chunks: u64,
    pub nodes: u64,
    pub pages: u64,
    pub archive_bytes: u64,
    pub textures: u64,
    /// Compressed bytes of the texture tiles.
    pub texture_bytes: u64,
    pub seconds_import: f64,
    pub seconds_partition: f64,
    pub seconds_build: f64,
    pub seconds_total: f64,
    /// Peak resident set of the process when the archive was complete.
    pub peak_rss_bytes: u64,
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
        if self.textures > 0 {
            writeln!(
                f,
                "  {} textures, {:.2} MiB of tiles",
                self.textures,
                self.texture_bytes as f64 / (1 << 20) as f64
            )?;
        }
        if self.instances > 0 {
            writeln!(
                f,
                "  {} meshes stored once, placed {} times",
                self.prototypes, self.instances
            )?;
        }
        write!(
            f,
            "  {:.2} s (import {:.2}, partition {:.2}, build {:.2}), {:.2} M triangles/s, peak RSS {:.1} MiB",
            self.seconds_total,
            self.seconds_import,
            self.seconds_partition,
            self.seconds_build,
            per_s / 1e6,
            self.peak_rss_bytes as f64 / (1 << 20) as f64
        )
    }
}

/// Writes every texture the materials name and returns their records and coarse levels; with
/// `--missing-textures warn` a texture whose file is absent is dropped (its materials keep
/// their factors) and the remaining ones renumbered.
fn write_textures(
    writer: &mut ArchiveWriter,
    scene: &mut crate::import::SceneDesc,
    opts: &ConvertOptions,
) -> Result<(Vec<canopy_format::TextureRecord>, Vec<textures::Coarse>)> {
    let mut records = Vec::new();
    let mut coarse = Vec::new();
    let mut index = Vec::with_capacity(scene.textures.len());
    let mut notes = Vec::new();
    for (i, src) in scene.textures.iter().enumerate() {
        let missing = src
            .file
            .as_ref()
            .filter(|f| src.bytes.is_none() && !f.exists());
        if let Some(f) = missing {
            if opts.missing_textures == MissingTextures::Warn {
                notes.push(format!(
                    "{}: texture file missing; its materials keep their factors",
                    f.display()
                ));
                index.push(canopy_format::MaterialRecord::NO_TEXTURE);
                continue;
            }
            bail!(
                "{}: texture file missing (--missing-textures warn converts without it)",
                f.display()
            );
        }
        if opts.progress {
            eprintln!("texture {}/{}: {}", i + 1, scene.textures.len(), src.name);
        }
        // Textures are written before the geometry is built: an image decoded whole may
        // use the budget beyond the fixed part.
        let whole_limit = opts.mem_budget.saturating_sub(FIXED_BYTES);
        let (rec, levels) = textures::write_texture(writer, src, opts.zstd_level, whole_limit)
            .with_context(|| format!("texture {}", src.describe()))?;
        index.push(records.len() as u16);
        records.push(rec);
        coarse.push(levels);
    }
    notes.into_iter().for_each(|n| scene.note(n));
    for m in &mut scene.materials {
        for t in &mut m.textures {
            if let Some(&new) = index.get(*t as usize) {
                *t = new;
            }
        }
        // A dropped normal texture takes its scale with it (the reader accepts a scale
        // only with a texture).
        if m.textures[canopy_format::MaterialRecord::NORMAL]
            == canopy_format::MaterialRecord::NO_TEXTURE
        {
            m.normal_scale = 0.0;
        }
    }
    Ok((records, coarse))
}

/// Chunks built at once, whatever the number of cores (each chunk's build is parallel
/// inside): chunk sizes, and so the archive's bytes, do not depend on the machine.
const CHUNKS_AT_ONCE: u64 = 2;

/// Most triangles one chunk may hold: what the budget leaves beside the fixed part and the
/// page table, shared by the chunks built at once (at least 4096 each: `convert` refuses
/// budgets below that with no page table).
fn chunk_cap(budget: u64, triangles: u64, instances: u64) -> u64 {
    let held = FIXED_BYTES + page_table_bytes(triangles, instances);
    (budget.saturating_sub(held) / BUILD_BYTES_PER_TRI / CHUNKS_AT_ONCE).max(4096)
}

/// What the writer's page table may grow to: 96 bytes a page, a page per 256 triangles or
/// 128 instances at the most (pages of 512 nodes held 650 triangles, or 252 instances, in
/// a conversion of 250 M triangles and 39 M instances).
fn page_table_bytes(triangles: u64, instances: u64) -> u64 {
    96 * (triangles / 256 + instances / 128 + 1)
}

/// A conversion up to its chunk builds: the textures and the instances' pages written, the
/// triangles partitioned into chunk files.
struct Staged {
    writer: ArchiveWriter,
    files: Vec<spill::Spill>,
    mats: MatTable,
    placed: instances::Placed,
    /// The scene's tables and features; the root, bounds and depth are filled in last.
    info: SceneInfo,
    /// Triangles stored once (the chunks'), as against those placed.
    triangles: u64,
    report: ConvertReport,
}

pub fn convert(opts: &ConvertOptions) -> Result<ConvertReport> {
    let t0 = Instant::now();
    let mut s = stage(opts, None)?;
    let t = Instant::now();
    let chunks = chunks::Chunks {
        files: std::mem::take(&mut s.files),
        mats: &s.mats,
        triangles: s.triangles,
        streams: Streams::of(s.info.features),
        threads: CHUNKS_AT_ONCE as usize,
        show: opts.progress,
    };
    let extra = (
        std::mem::take(&mut s.placed.groups),
        std::mem::take(&mut s.placed.loose),
    );
    let top = chunks::build(&mut s.writer, chunks, extra, opts)?;
    s.report.seconds_build += t.elapsed().as_secs_f64();
    complete(s.writer, (s.info, s.report), s.placed.depth, top, t0)
}

/// Imports the inputs, writes the textures and the instances' pages, and partitions the
/// triangles into chunks. With `work`, the archive so far is written there (to be
/// suspended) and the chunk files are named in it, for the cluster stages.
fn stage(opts: &ConvertOptions, work: Option<&Path>) -> Result<Staged> {
    let t0 = Instant::now();
    if opts.inputs.is_empty() {
        bail!("no input files");
    }
    let least = FIXED_BYTES + 4096 * BUILD_BYTES_PER_TRI;
    if opts.mem_budget < least {
        bail!(
            "--mem-budget {} is too small: converting needs at least {}",
            crate::units::format_size(opts.mem_budget),
            crate::units::format_size(crate::units::whole_mib(least))
        );
    }
    let file = match &opts.scene {
        Some(p) => SceneFile::load(p)?,
        None => SceneFile::default(),
    };
    let environment = file.environment().with_context(|| {
        format!(
            "{}",
            opts.scene
                .as_deref()
                .unwrap_or(std::path::Path::new(""))
                .display()
        )
    })?;
    let dir = match (work, opts.output.parent()) {
        (Some(w), _) => w.to_path_buf(),
        (None, Some(d)) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let mut writer = match work {
        Some(w) => ArchiveWriter::create(&stages::body(w))?,
        None => ArchiveWriter::create(&opts.output)?,
    };
    let mut imported = ingest::import_inputs(opts, &file, &dir)?;
    let total = imported.count;
    let mut report = ConvertReport {
        input_triangles: total,
        seconds_import: t0.elapsed().as_secs_f64(),
        ..Default::default()
    };
    let (textures, coarse) = write_textures(&mut writer, &mut imported.scene, opts)?;
    report.textures = textures.len() as u64;
    report.texture_bytes = writer.tile_bytes();
    let mats = MatTable::new(&imported.scene.materials, &textures, coarse);
    let features = imported.features(&mats.summaries);

    let placements = imported.shared.as_ref().map_or(0, |s| s.2.len());
    let cap = chunk_cap(opts.mem_budget, total, placements);
    let streams = Streams::of(features);
    let t2 = Instant::now();
    let placed = match imported.shared {
        Some(shared) => {
            let b = instances::Build {
                mats: &mats,
                streams,
                threads: CHUNKS_AT_ONCE as usize,
                cap,
                dir: &dir,
                run_bytes: (opts.mem_budget - FIXED_BYTES) / 4,
            };
            instances::build(&mut writer, shared, &b, opts)?
        }
        None => instances::Placed::default(),
    };
    report.input_triangles += placed.instanced_triangles;
    report.prototypes = placed.prototypes;
    report.instances = placed.count;
    report.seconds_build = t2.elapsed().as_secs_f64();

    let t1 = Instant::now();
    let bounds = [imported.lo, imported.hi];
    let files = partition::partition(
        imported.spill,
        total,
        bounds,
        cap,
        &dir,
        work,
        opts.progress,
    )?;
    report.chunks = files.len() as u64;
    report.seconds_partition = t1.elapsed().as_secs_f64();
    let scene = imported.scene;
    let notes = scene.note_records();
    let info = SceneInfo {
        features,
        input_triangles: report.input_triangles,
        bounds_min: [0.0; 3],
        bounds_max: [0.0; 3],
        root_page: 0,
        depth: 0,
        max_leaf_triangles: MAX_LEAF_TRIS,
        page_nodes_max: opts.page_nodes as u32,
        materials: scene.materials,
        cameras: scene.cameras,
        lights: scene.lights,
        textures,
        environment,
        notes,
    };
    Ok(Staged {
        writer,
        files,
        mats,
        placed,
        info,
        triangles: total,
        report,
    })
}

/// Writes the tables and header of a conversion whose pages are all written; `top` is the
/// scene's root and the number of its page, `prototype_depth` the deepest prototype tree.
fn complete(
    writer: ArchiveWriter,
    (mut info, mut report): (SceneInfo, ConvertReport),
    prototype_depth: u32,
    top: (BNode, u32),
    t0: Instant,
) -> Result<ConvertReport> {
    let (root, root_page) = top;
    info.bounds_min = root.lo;
    info.bounds_max = root.hi;
    info.root_page = root_page;
    info.depth = root.height.max(prototype_depth);
    report.pages = writer.page_count() as u64;
    report.nodes = writer.node_count();
    report.output = writer.path().to_path_buf();
    writer.finish(&info)?;
    report.archive_bytes = std::fs::metadata(&report.output)
        .map(|m| m.len())
        .unwrap_or(0);
    report.seconds_total = t0.elapsed().as_secs_f64();
    report.peak_rss_bytes = crate::progress::peak_rss_bytes();
    Ok(report)
}
