//! A conversion split into stages that separate processes (a cluster's job array) run, the
//! archive byte for byte the one `convert` writes in one process:
//!
//! 1. `prepare`: import, textures, the instances' pages and the partition, as `convert` does
//!    them; the archive so far is suspended in the work directory (`archive.body`), the
//!    chunks' triangles are named files there (`chunk-K.tris`) and everything the later
//!    stages need is in `state`.
//! 2. `chunk K`: builds chunk K's tree and pages, numbered from 0 (`chunk-K.pages`). The
//!    chunks are independent: any order, any node, at once.
//! 3. `join`: resumes the archive, appends each chunk's pages in chunk order, moving the
//!    child-page numbers of the pages that name another page (about a quarter of them) by
//!    the pages before the chunk (`renumber_page`: decompressed, changed, compressed again),
//!    builds the top tree over the chunk roots and writes the tables; then removes the work
//!    files.
//!
//! Every file carries a checksum; a chunk's pages name the state they were built from, so
//! stale or damaged files are refused by name.

use super::chunks::{Assembly, ChunkOut, ChunkTree, EncodedPages};
use super::textures::Coarse;
use super::tree::{BNode, Kind};
use super::{spill, ConvertOptions, ConvertReport, MatTable, Staged};
use crate::import::SpillTri;
use anyhow::{bail, Context, Result};
use bytemuck::Pod;
use canopy_format::atomic::AtomicFile;
use canopy_format::{
    renumber_page, ArchiveWriter, EncodedPage, PageMeta, SceneInfo, Streams, WriterState, NONE,
};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::io::{BufReader, Read};
use std::path::{Path, PathBuf};
use std::time::Instant;

const STATE_MAGIC: &[u8; 8] = b"CNVSTAT1";
const PAGES_MAGIC: &[u8; 8] = b"CNVPAGE1";

/// The suspended archive in a work directory.
pub fn body(work: &Path) -> PathBuf {
    work.join("archive.body")
}

fn state_file(work: &Path) -> PathBuf {
    work.join("state")
}

/// Chunk `k`'s triangles in a work directory.
pub fn chunk_file(work: &Path, k: u32) -> PathBuf {
    work.join(format!("chunk-{k}.tris"))
}

fn pages_file(work: &Path, k: u32) -> PathBuf {
    work.join(format!("chunk-{k}.pages"))
}

/// Everything the chunk and join stages need of the prepared conversion.
#[derive(Serialize, Deserialize)]
struct State {
    output: PathBuf,
    page_nodes: u32,
    zstd_level: i32,
    fast: bool,
    /// One chunk and no instances: the chunk's root is the scene's.
    single: bool,
    /// Bytes of each chunk's triangle file.
    chunk_bytes: Vec<u64>,
    coarse: Vec<Coarse>,
    writer_pages: Vec<u8>,
    writer_tiles: Vec<u8>,
    writer_totals: [u64; 5],
    groups: Vec<BNode>,
    loose: Vec<u8>,
    placed_depth: u32,
    features: u64,
    input_triangles: u64,
    page_nodes_max: u32,
    materials: Vec<u8>,
    cameras: Vec<u8>,
    lights: Vec<u8>,
    textures: Vec<u8>,
    environment: Vec<u8>,
    notes: Vec<u8>,
    report: ConvertReport,
}

/// A chunk's pages as `chunk` wrote them, before their bytes.
#[derive(Serialize, Deserialize)]
struct ChunkHead {
    /// The checksum of the state the chunk was built from.
    state: u64,
    chunk: u32,
    triangles: u64,
    /// Seconds the chunk's build took.
    seconds: f64,
    root: Option<BNode>,
    leaf_tris: Vec<u8>,
    pages: Vec<PageHead>,
}

#[derive(Serialize, Deserialize)]
struct PageHead {
    len: u32,
    raw_len: u32,
    checksum: u64,
    counts: [u32; 4],
    parent: [u32; 2],
    root_count: u16,
    bounds: [[f32; 3]; 2],
    externals: Vec<(u32, u32)>,
    /// Some node names a child page (its number moves at the join).
    names_pages: bool,
}

/// Stage 1: everything up to the chunk builds; its report counts the chunks (`chunks`).
pub fn prepare(opts: &ConvertOptions, work: &Path) -> Result<ConvertReport> {
    let t0 = Instant::now();
    std::fs::create_dir_all(work)
        .with_context(|| format!("{}: cannot create the work directory", work.display()))?;
    remove_work(work, false);
    let s = super::stage(opts, Some(work))?;
    let Staged {
        writer,
        files,
        mats,
        placed,
        info,
        triangles,
        mut report,
    } = s;
    let chunk_bytes = (0..files.len() as u32)
        .map(|k| {
            let f = chunk_file(work, k);
            std::fs::metadata(&f)
                .map(|m| m.len())
                .with_context(|| format!("{}: cannot read its size", f.display()))
        })
        .collect::<Result<Vec<_>>>()?;
    drop(files);
    let w = writer.suspend()?;
    report.seconds_total = t0.elapsed().as_secs_f64();
    let state = State {
        output: opts.output.clone(),
        page_nodes: opts.page_nodes as u32,
        zstd_level: opts.zstd_level,
        fast: super::chunks::fast_build(opts, triangles),
        single: super::chunks::scene_is_one_chunk(chunk_bytes.len(), &placed.groups),
        chunk_bytes,
        coarse: mats.into_coarse(),
        writer_pages: pod_bytes(&w.pages),
        writer_tiles: pod_bytes(&w.tiles),
        writer_totals: [w.nodes, w.tris, w.verts, w.instances, w.len],
        groups: placed.groups,
        loose: pod_bytes(&placed.loose),
        placed_depth: placed.depth,
        features: info.features,
        input_triangles: info.input_triangles,
        page_nodes_max: info.page_nodes_max,
        materials: pod_bytes(&info.materials),
        cameras: pod_bytes(&info.cameras),
        lights: pod_bytes(&info.lights),
        textures: pod_bytes(&info.textures),
        environment: pod_bytes(info.environment.as_slice()),
        notes: pod_bytes(&info.notes),
        report,
    };
    let bytes = postcard::to_stdvec(&state).context("encoding the conversion state")?;
    write_sealed(&state_file(work), STATE_MAGIC, &bytes, &[])?;
    Ok(state.report)
}

/// Stage 2: builds chunk `k` of a prepared conversion; returns its triangle count.
pub fn chunk(work: &Path, k: u32) -> Result<u64> {
    let t0 = Instant::now();
    let (state, sum) = read_state(work)?;
    let Some(&bytes) = state.chunk_bytes.get(k as usize) else {
        bail!(
            "{}: chunk {k} asked for, the conversion has {} (0 to {})",
            work.display(),
            state.chunk_bytes.len(),
            state.chunk_bytes.len().saturating_sub(1)
        );
    };
    let file = chunk_file(work, k);
    let len = std::fs::metadata(&file)
        .with_context(|| format!("{}: cannot read", file.display()))?
        .len();
    if len != bytes {
        bail!("{}: {len} bytes, {bytes} were written", file.display());
    }
    let tris = spill::read_all(&spill::Spill::open(&file)?)?;
    let materials = state.materials.len() / std::mem::size_of::<canopy_format::MaterialRecord>();
    if let Some(t) = tris.iter().find(|t| t.material as usize >= materials) {
        bail!(
            "{}: material {} of {materials}: not this conversion's chunk",
            file.display(),
            t.material
        );
    }
    let opts = state.options();
    let mats = state.mats()?;
    let triangles = tris.len() as u64;
    let built = ChunkTree::build(tris, &mats, state.single, state.fast, &opts);
    let out = built.encode(0, &opts, Streams::of(state.features))?;
    let parents: std::collections::HashSet<u32> =
        out.pages.pages.iter().map(|p| p.1.parent_page).collect();
    let pages: Vec<PageHead> = (out.pages.pages.iter().enumerate())
        .map(|(i, p)| PageHead::of(p, parents.contains(&(i as u32))))
        .collect();
    let head = ChunkHead {
        state: sum,
        chunk: k,
        triangles,
        seconds: t0.elapsed().as_secs_f64(),
        root: out.root,
        leaf_tris: pod_bytes(&out.leaf_tris),
        pages,
    };
    let bytes = postcard::to_stdvec(&head).context("encoding a chunk's pages")?;
    let bodies: Vec<&[u8]> = out.pages.pages.iter().map(|p| &p.0.bytes[..]).collect();
    write_sealed(&pages_file(work, k), PAGES_MAGIC, &bytes, &bodies)?;
    Ok(triangles)
}

/// Stage 3: the archive from a prepared conversion whose chunks are all built. Its summary
/// adds up the stages' times: what one process would have spent.
pub fn join(work: &Path, show: bool) -> Result<ConvertReport> {
    let t0 = Instant::now();
    let (mut state, sum) = read_state(work)?;
    let missing: Vec<u32> = (0..state.chunk_bytes.len() as u32)
        .filter(|&k| !pages_file(work, k).exists())
        .collect();
    if !missing.is_empty() {
        bail!(
            "{}: chunk{} {} not built yet (`canopy convert --work {} --chunk K`)",
            work.display(),
            if missing.len() == 1 { "" } else { "s" },
            list(&missing),
            work.display()
        );
    }
    let opts = state.options();
    let streams = Streams::of(state.features);
    let writer_state = WriterState {
        pages: records(&state.writer_pages, "page table")?,
        tiles: records(&state.writer_tiles, "tile table")?,
        nodes: state.writer_totals[0],
        tris: state.writer_totals[1],
        verts: state.writer_totals[2],
        instances: state.writer_totals[3],
        len: state.writer_totals[4],
    };
    let mut writer = ArchiveWriter::resume(&state.output, &body(work), writer_state)?;
    let mut assembly = Assembly::new(state.single, records(&state.loose, "instances")?);
    let bar = crate::progress::bar(show, state.chunk_bytes.len() as u64, "joining");
    let mut chunk_seconds = 0.0;
    for k in 0..state.chunk_bytes.len() as u32 {
        let at = writer.page_count();
        let (out, seconds) = read_chunk(work, k, (sum, state.single), at, opts.zstd_level)?;
        chunk_seconds += seconds;
        assembly.add(&mut writer, out)?;
        bar.inc(1);
    }
    bar.finish_and_clear();
    let groups = std::mem::take(&mut state.groups);
    let top = assembly.finish(&mut writer, groups, &opts, streams)?;
    let info = state.info()?;
    let mut report = state.report;
    let prepared_seconds = report.seconds_total;
    report.seconds_build += chunk_seconds + t0.elapsed().as_secs_f64();
    let mut report = super::complete(writer, (info, report), state.placed_depth, top, t0)?;
    report.seconds_total += prepared_seconds + chunk_seconds;
    remove_work(work, true);
    Ok(report)
}

impl State {
    /// What the later stages index by is in range: each texture's coarse levels, the
    /// top nodes' pages and instance records, the options.
    fn check(&self) -> Result<()> {
        let textures: Vec<canopy_format::TextureRecord> = records(&self.textures, "textures")?;
        if textures.len() != self.coarse.len()
            || textures.iter().zip(&self.coarse).any(|(t, c)| !c.fits(t))
        {
            bail!("its textures' coarse levels do not match the textures");
        }
        let pages = self.writer_pages.len() / std::mem::size_of::<canopy_format::PageEntry>();
        let loose = self.loose.len() / std::mem::size_of::<canopy_format::InstanceRecord>();
        let fits = |n: &BNode| match n.kind {
            Kind::External { page } => (page as usize) < pages,
            Kind::Instance { index } => (index as usize) < loose,
            _ => false,
        };
        if !self.groups.iter().all(fits) {
            bail!("an instance group names a page or record it does not have");
        }
        if !(3..=4096).contains(&self.page_nodes) || !(1..=22).contains(&self.zstd_level) {
            bail!("its page size or compression level is out of range");
        }
        Ok(())
    }

    /// The options the later stages use, as prepared.
    fn options(&self) -> ConvertOptions {
        let mut o = ConvertOptions::new(Vec::new(), self.output.clone());
        o.page_nodes = self.page_nodes as usize;
        o.zstd_level = self.zstd_level;
        o
    }

    fn mats(&self) -> Result<MatTable> {
        Ok(MatTable::new(
            &records(&self.materials, "materials")?,
            &records(&self.textures, "textures")?,
            self.coarse.clone(),
        ))
    }

    fn info(&self) -> Result<SceneInfo> {
        Ok(SceneInfo {
            features: self.features,
            input_triangles: self.input_triangles,
            bounds_min: [0.0; 3],
            bounds_max: [0.0; 3],
            root_page: 0,
            depth: 0,
            max_leaf_triangles: super::MAX_LEAF_TRIS,
            page_nodes_max: self.page_nodes_max,
            materials: records(&self.materials, "materials")?,
            cameras: records(&self.cameras, "cameras")?,
            lights: records(&self.lights, "lights")?,
            textures: records(&self.textures, "textures")?,
            environment: records(&self.environment, "environment")?.pop(),
            notes: records(&self.notes, "notes")?,
        })
    }
}

impl PageHead {
    /// `names_pages`: some page of the chunk has this one as its parent.
    fn of(
        (page, meta, externals): &(EncodedPage, PageMeta, Vec<(u32, u32)>),
        names_pages: bool,
    ) -> PageHead {
        PageHead {
            len: page.bytes.len() as u32,
            raw_len: page.raw_len,
            checksum: page.checksum,
            counts: [
                page.node_count,
                page.tri_count,
                page.vert_count,
                page.instance_count,
            ],
            parent: [meta.parent_page, meta.parent_node],
            root_count: meta.root_count,
            bounds: [meta.bounds_min, meta.bounds_max],
            externals: externals.clone(),
            names_pages,
        }
    }
}

/// Chunk `k`'s pages, numbered from `base`, and the seconds its build took; `single`: the
/// chunk is the whole scene.
fn read_chunk(
    work: &Path,
    k: u32,
    (state, single): (u64, bool),
    base: u32,
    level: i32,
) -> Result<(ChunkOut, f64)> {
    let path = pages_file(work, k);
    let (head, mut rest) = read_sealed(&path, PAGES_MAGIC)?;
    let head: ChunkHead = postcard::from_bytes(&head)
        .with_context(|| format!("{}: cannot decode its header", path.display()))?;
    if head.state != state || head.chunk != k {
        bail!(
            "{}: built from another preparation of the conversion (build chunk {k} again)",
            path.display()
        );
    }
    let damaged = |what: &str| anyhow::anyhow!("{}: {what}", path.display());
    let moved = |p: u32| match p {
        NONE => Ok(NONE),
        p => p
            .checked_add(base)
            .ok_or_else(|| damaged("a page number overflows")),
    };
    let leaf_tris = records::<SpillTri>(&head.leaf_tris, "triangles")?;
    // A chunk's pages hold what is below its root, or the root too when the chunk is the
    // scene; a leaf root that is not the scene's comes with its triangles instead.
    let paged = !head.pages.is_empty() && leaf_tris.is_empty();
    let fits = match head.root.as_ref().map(|r| r.kind) {
        None => head.pages.is_empty() && leaf_tris.is_empty(),
        Some(Kind::Leaf { .. }) if single => paged,
        Some(Kind::Leaf { count, .. }) => {
            head.pages.is_empty() && leaf_tris.len() == count as usize
        }
        Some(Kind::Inner(_)) => paged,
        Some(_) => false,
    };
    if !fits {
        return Err(damaged("its root does not match its pages"));
    }
    let mut pages = Vec::with_capacity(head.pages.len());
    let mut renumber = Vec::new();
    for (i, h) in head.pages.into_iter().enumerate() {
        let page =
            read_page(&mut rest, &h).with_context(|| format!("{}: page {i}", path.display()))?;
        renumber.push(h.names_pages && base > 0);
        let meta = PageMeta {
            parent_page: moved(h.parent[0])?,
            parent_node: h.parent[1],
            root_count: h.root_count,
            bounds_min: h.bounds[0],
            bounds_max: h.bounds[1],
        };
        let externals = (h.externals.iter())
            .map(|&(p, l)| Ok((moved(p)?, l)))
            .collect::<Result<_>>()?;
        pages.push((page, meta, externals));
    }
    pages
        .par_iter_mut()
        .zip(renumber)
        .enumerate()
        .filter(|(_, (_, r))| *r)
        .try_for_each(|(i, (p, _))| {
            p.0 = renumber_page(&p.0, base, level)
                .with_context(|| format!("{}: page {i}", path.display()))?;
            Ok::<_, anyhow::Error>(())
        })?;
    let out = ChunkOut {
        root: head.root,
        leaf_tris,
        pages: EncodedPages { base, pages },
        triangles: head.triangles,
    };
    Ok((out, head.seconds))
}

fn read_state(work: &Path) -> Result<(State, u64)> {
    let path = state_file(work);
    if !path.exists() {
        bail!(
            "{}: no prepared conversion here (`canopy convert INPUTS -o OUT --work {}` prepares one)",
            work.display(),
            work.display()
        );
    }
    let (bytes, _) = read_sealed(&path, STATE_MAGIC)?;
    let state: State = postcard::from_bytes(&bytes)
        .with_context(|| format!("{}: cannot decode the conversion state", path.display()))?;
    state
        .check()
        .with_context(|| format!("{}: not a state this converter wrote", path.display()))?;
    Ok((state, xxhash_rust::xxh3::xxh3_64(&bytes)))
}

/// Writes `magic`, the length and xxh3 of `head`, `head`, then `bodies` back to back, to an
/// unnamed file named `path` once complete (`AtomicFile`: a killed stage leaves nothing).
fn write_sealed(path: &Path, magic: &[u8; 8], head: &[u8], bodies: &[&[u8]]) -> Result<()> {
    let mut out = AtomicFile::create(path, 0)?;
    out.write_all(magic)?;
    out.write_all(&(head.len() as u64).to_le_bytes())?;
    out.write_all(&xxhash_rust::xxh3::xxh3_64(head).to_le_bytes())?;
    out.write_all(head)?;
    for b in bodies {
        out.write_all(b)?;
    }
    out.commit(&[])?;
    Ok(())
}

/// A page's bytes as `h` describes them, checked against its checksum.
fn read_page(from: &mut impl Read, h: &PageHead) -> Result<EncodedPage> {
    let mut bytes = vec![0; h.len as usize];
    from.read_exact(&mut bytes).context("ends early")?;
    if xxhash_rust::xxh3::xxh3_64(&bytes) != h.checksum {
        bail!("damaged (checksum)");
    }
    let [node_count, tri_count, vert_count, instance_count] = h.counts;
    Ok(EncodedPage {
        bytes,
        raw_len: h.raw_len,
        checksum: h.checksum,
        node_count,
        tri_count,
        vert_count,
        instance_count,
    })
}

/// The checked head of a file `write_sealed` wrote, and a reader of what follows it.
fn read_sealed(path: &Path, magic: &[u8; 8]) -> Result<(Vec<u8>, BufReader<std::fs::File>)> {
    let file =
        std::fs::File::open(path).with_context(|| format!("{}: cannot open", path.display()))?;
    let size = file.metadata().map(|m| m.len()).unwrap_or(0);
    let mut r = BufReader::with_capacity(1 << 20, file);
    let mut fixed = [0u8; 24];
    r.read_exact(&mut fixed)
        .with_context(|| format!("{}: shorter than its header", path.display()))?;
    if &fixed[..8] != magic {
        bail!("{}: not a file of a staged conversion", path.display());
    }
    let len = u64::from_le_bytes(fixed[8..16].try_into().expect("8 bytes"));
    let sum = u64::from_le_bytes(fixed[16..24].try_into().expect("8 bytes"));
    if len > size.saturating_sub(24) {
        bail!(
            "{}: its header says {len} bytes, the file is shorter",
            path.display()
        );
    }
    let mut head = vec![0; len as usize];
    r.read_exact(&mut head)
        .with_context(|| format!("{}: ends early", path.display()))?;
    if xxhash_rust::xxh3::xxh3_64(&head) != sum {
        bail!("{}: damaged (checksum)", path.display());
    }
    Ok((head, r))
}

fn pod_bytes<T: Pod>(v: &[T]) -> Vec<u8> {
    bytemuck::cast_slice(v).to_vec()
}

fn records<T: Pod>(bytes: &[u8], what: &str) -> Result<Vec<T>> {
    let size = std::mem::size_of::<T>();
    if !bytes.len().is_multiple_of(size) {
        bail!(
            "the conversion state's {what}: {} bytes, not whole records",
            bytes.len()
        );
    }
    Ok(bytemuck::pod_collect_to_vec(bytes))
}

/// "0, 3 and 7"
fn list(ks: &[u32]) -> String {
    let s: Vec<String> = ks.iter().map(u32::to_string).collect();
    match s.split_last() {
        Some((last, rest)) if !rest.is_empty() => format!("{} and {last}", rest.join(", ")),
        _ => s.join(""),
    }
}

/// Removes what the stages wrote in `work` (an earlier preparation's files too), and with
/// `dir` the directory itself if nothing else is left in it.
fn remove_work(work: &Path, dir: bool) {
    let ours = |name: &str| {
        let chunk = name
            .strip_prefix("chunk-")
            .and_then(|r| r.strip_suffix(".tris").or_else(|| r.strip_suffix(".pages")))
            .is_some_and(|k| k.parse::<u32>().is_ok());
        chunk || name == "state" || name == "archive.body"
    };
    if let Ok(entries) = std::fs::read_dir(work) {
        for e in entries.flatten() {
            if e.file_name().to_str().is_some_and(ours) {
                let _ = std::fs::remove_file(e.path());
            }
        }
    }
    if dir {
        let _ = std::fs::remove_dir(work);
    }
}
