//! Stage 3, chunk trees and pages: each chunk is loaded alone, built (PLOC via obvhs),
//! aggregated, cut into pages and written; only its root node stays in memory. A balanced
//! tree over the chunk roots (in Morton order) forms the top pages.

use super::pages::Plan;
use super::spill;
use super::tree::{BNode, Kind, Tree};
use super::{BvhQuality, ConvertOptions, MatTable, AUTO_FAST_ABOVE};
use crate::import::SpillTri;
use crate::progress;
use anyhow::{bail, Context, Result};
use canopy_format::{
    encode_page, ArchiveWriter, EncodedPage, InstanceRecord, PageMeta, Streams, NONE,
};
use rayon::prelude::*;
use std::collections::BTreeMap;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::mpsc::Sender;
use std::sync::{Condvar, Mutex};

/// Pages of one archive's chunks: which chunk trees, how to build and encode them.
pub struct Chunks<'a> {
    pub files: Vec<spill::Spill>,
    pub mats: &'a MatTable,
    pub triangles: u64,
    pub streams: Streams,
    pub threads: usize,
    /// Draw a progress bar.
    pub show: bool,
}

/// Builds every chunk and the top tree over them and the `extra` nodes (the instances'
/// subtrees, and bare instance leaves naming the records that come with them), appending
/// all pages to `writer`. Returns the root node and the number of its page, which holds the
/// root as node 0.
pub fn build(
    writer: &mut ArchiveWriter,
    c: Chunks,
    extra: (Vec<BNode>, Vec<InstanceRecord>),
    opts: &ConvertOptions,
) -> Result<(BNode, u32)> {
    let bar = progress::bar(c.show, c.triangles, "building");
    let chunk_count = c.files.len();
    let mut assembly = Assembly::new(scene_is_one_chunk(chunk_count, &extra.0), extra.1);
    let job = ChunkJob {
        files: c.files.into_iter().map(|f| Mutex::new(Some(f))).collect(),
        mats: c.mats,
        single: assembly.single,
        fast: fast_build(opts, c.triangles),
        opts,
        streams: c.streams,
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
    // are appended in chunk order, so the archive does not depend on scheduling. Each worker
    // runs its chunk's parallel loops on a pool of its own share of the cores: on the shared
    // pool the workers' loops stole from each other and the build took 10% longer.
    std::thread::scope(|s| -> Result<()> {
        let (tx, rx) = std::sync::mpsc::channel();
        let workers = c.threads.min(chunk_count);
        let inner = (rayon::current_num_threads() / workers).max(1);
        for _ in 0..workers {
            let tx = tx.clone();
            let job = &job;
            let pool = rayon::ThreadPoolBuilder::new().num_threads(inner).build()?;
            s.spawn(move || job.work(tx, pool));
        }
        drop(tx);
        let mut arrived = BTreeMap::new();
        let mut next = 0;
        for (i, out) in rx {
            arrived.insert(i, out?);
            while let Some(out) = arrived.remove(&next) {
                next += 1;
                bar.inc(out.triangles);
                assembly.add(writer, out)?;
            }
        }
        Ok(())
    })?;
    bar.finish_and_clear();
    assembly.finish(writer, extra.0, opts, c.streams)
}

/// Whether the scene is one chunk and nothing else (no instance subtrees): that chunk's tree
/// is paged from its root, which is the scene's; otherwise a top tree joins the roots.
pub fn scene_is_one_chunk(chunks: usize, instance_groups: &[BNode]) -> bool {
    chunks == 1 && instance_groups.is_empty()
}

/// Whether chunk trees get obvhs's fast build (`--bvh`, `auto` by the triangle count).
pub fn fast_build(opts: &ConvertOptions, triangles: u64) -> bool {
    match opts.bvh {
        BvhQuality::Auto => triangles > AUTO_FAST_ABOVE,
        q => q == BvhQuality::Fast,
    }
}

/// The top of the scene taking shape as the chunks' pages arrive in chunk order.
pub struct Assembly {
    /// One chunk and nothing else: its root is the scene's.
    single: bool,
    top: Tree,
    root_page: u32,
    scene_root: Option<BNode>,
}

impl Assembly {
    /// `loose` are the instance records of bare instance leaves among the extra nodes.
    pub fn new(single: bool, loose: Vec<InstanceRecord>) -> Assembly {
        Assembly {
            single,
            top: Tree {
                nodes: Vec::new(),
                tris: Vec::new(),
                instances: loose,
                root: 0,
            },
            root_page: 0,
            scene_root: None,
        }
    }

    /// Appends the next chunk's pages (numbered from the writer's next page) and takes its
    /// root into the top tree.
    pub fn add(&mut self, writer: &mut ArchiveWriter, out: ChunkOut) -> Result<()> {
        let ChunkOut {
            root,
            leaf_tris,
            pages,
            ..
        } = out;
        let first = append_pages(writer, pages)?;
        let Some(root) = root else { return Ok(()) };
        if self.single {
            self.root_page = first;
            self.scene_root = Some(root);
        } else if let Kind::Leaf { count, .. } = root.kind {
            let at = self.top.tris.len() as u32;
            self.top.tris.extend_from_slice(&leaf_tris);
            self.top.nodes.push(BNode {
                kind: Kind::Leaf { first: at, count },
                ..root
            });
        } else {
            self.top.nodes.push(BNode {
                kind: Kind::External { page: first },
                ..root
            });
        }
        Ok(())
    }

    /// Builds and writes the top tree over the chunk roots and `extra`; returns the scene's
    /// root and the number of its page.
    pub fn finish(
        mut self,
        writer: &mut ArchiveWriter,
        extra: Vec<BNode>,
        opts: &ConvertOptions,
        streams: Streams,
    ) -> Result<(BNode, u32)> {
        if !self.single {
            let top = &mut self.top;
            let mut leaves: Vec<u32> = (0..top.nodes.len() as u32).collect();
            if !extra.is_empty() {
                top.nodes.extend(extra);
                leaves = top.morton_order((0..top.nodes.len() as u32).collect());
            }
            if leaves.is_empty() {
                bail!("no triangles in the inputs");
            }
            top.root = top.balanced(&leaves);
            self.root_page = write_pages(writer, top, vec![top.root], opts, streams)?;
            self.scene_root = Some(top.nodes[top.root as usize].clone());
        }
        let Some(scene_root) = self.scene_root else {
            bail!("no triangles in the inputs")
        };
        Ok((scene_root, self.root_page))
    }
}

/// A chunk's pages, compressed and numbered from `base`, ready to append in order.
pub struct EncodedPages {
    pub base: u32,
    pub pages: Vec<(EncodedPage, PageMeta, Externals)>,
}

/// Per cut node of a page: (page holding its children, its local index).
pub type Externals = Vec<(u32, u32)>;

/// A chunk built: its pages and what the top tree takes of it.
pub struct ChunkOut {
    /// The chunk's root (None for an empty chunk).
    pub root: Option<BNode>,
    /// The triangles of a root that is a leaf (such a chunk writes no pages).
    pub leaf_tris: Vec<SpillTri>,
    pub pages: EncodedPages,
    pub triangles: u64,
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
    mats: &'a MatTable,
    single: bool,
    fast: bool,
    opts: &'a ConvertOptions,
    streams: Streams,
    claim: AtomicUsize,
    turn: Mutex<Turn>,
    turn_changed: Condvar,
}

impl ChunkJob<'_> {
    /// Claims chunks in increasing order until none is left, sending each result.
    fn work(&self, tx: Sender<(usize, Result<ChunkOut>)>, pool: rayon::ThreadPool) {
        loop {
            let i = self.claim.fetch_add(1, Ordering::Relaxed);
            if i >= self.files.len() {
                return;
            }
            let out = pool.install(|| self.chunk(i));
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
        let built = ChunkTree::build(tris, self.mats, self.single, self.fast, self.opts);
        let base = {
            let mut turn = self.turn.lock().expect("turn lock");
            while turn.next != i && !turn.failed {
                turn = self.turn_changed.wait(turn).expect("turn lock");
            }
            if turn.failed {
                bail!("stopped: another chunk failed");
            }
            let base = turn.base;
            turn.base += built.page_count();
            turn.next += 1;
            base
        };
        self.turn_changed.notify_all();
        built.encode(base, self.opts, self.streams)
    }
}

/// One chunk's tree and its cut into pages, before page numbers are known.
pub struct ChunkTree {
    triangles: u64,
    /// None for an empty chunk.
    built: Option<(Tree, Plan)>,
    single: bool,
}

impl ChunkTree {
    /// Builds the tree of a chunk's triangles and cuts it into pages: the whole tree when
    /// the chunk is the scene (`single`), else below its root, which joins the top tree.
    pub fn build(
        tris: Vec<SpillTri>,
        mats: &MatTable,
        single: bool,
        fast: bool,
        opts: &ConvertOptions,
    ) -> ChunkTree {
        let triangles = tris.len() as u64;
        let built = (!tris.is_empty()).then(|| {
            let tree = Tree::build(tris, mats, fast);
            let roots = match tree.nodes[tree.root as usize].kind {
                _ if single => vec![tree.root],
                Kind::Inner(children) => children.to_vec(),
                _ => Vec::new(),
            };
            let plan = Plan::new(&tree, roots, opts.page_nodes);
            (tree, plan)
        });
        ChunkTree {
            triangles,
            built,
            single,
        }
    }

    pub fn page_count(&self) -> u32 {
        self.built.as_ref().map_or(0, |(_, p)| p.pages.len() as u32)
    }

    /// The chunk's pages encoded and numbered from `base`.
    pub fn encode(self, base: u32, opts: &ConvertOptions, streams: Streams) -> Result<ChunkOut> {
        let empty = |base| EncodedPages {
            base,
            pages: Vec::new(),
        };
        let count = self.page_count();
        let Some((tree, plan)) = self.built else {
            return Ok(ChunkOut {
                root: None,
                leaf_tris: Vec::new(),
                pages: empty(base),
                triangles: self.triangles,
            });
        };
        let pages = match count {
            0 => empty(base),
            _ => encode_pages(&tree, &plan, base, opts, streams)?,
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
            triangles: self.triangles,
        })
    }
}

/// Encodes and compresses a plan's pages (in parallel), numbering them from `base`.
fn encode_pages(
    tree: &Tree,
    plan: &Plan,
    base: u32,
    opts: &ConvertOptions,
    streams: Streams,
) -> Result<EncodedPages> {
    let pages = (0..plan.pages.len())
        .into_par_iter()
        .map(|i| {
            let (contents, externals) = plan.encode(tree, i, base, streams);
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
            encode_page(&contents, streams, opts.zstd_level).map(|e| (e, meta, externals))
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
pub(super) fn write_pages(
    writer: &mut ArchiveWriter,
    tree: &Tree,
    roots: Vec<u32>,
    opts: &ConvertOptions,
    streams: Streams,
) -> Result<u32> {
    let plan = Plan::new(tree, roots, opts.page_nodes);
    let enc = encode_pages(tree, &plan, writer.page_count(), opts, streams)?;
    append_pages(writer, enc)
}
