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
    let (extra, loose) = extra;
    let single = chunk_count == 1 && extra.is_empty();
    let mut top = Tree {
        nodes: Vec::new(),
        tris: Vec::new(),
        instances: loose,
        root: 0,
    };
    let mut root_page = 0;
    let mut scene_root: Option<BNode> = None;
    let job = ChunkJob {
        files: c.files.into_iter().map(|f| Mutex::new(Some(f))).collect(),
        mats: c.mats,
        single,
        fast: match opts.bvh {
            BvhQuality::Auto => c.triangles > AUTO_FAST_ABOVE,
            q => q == BvhQuality::Fast,
        },
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
    // are appended in chunk order, so the archive does not depend on scheduling.
    std::thread::scope(|s| -> Result<()> {
        let (tx, rx) = std::sync::mpsc::channel();
        for _ in 0..c.threads.min(chunk_count) {
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
                let first = append_pages(writer, pages)?;
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
        let mut leaves: Vec<u32> = (0..top.nodes.len() as u32).collect();
        if !extra.is_empty() {
            top.nodes.extend(extra);
            leaves = top.morton_order((0..top.nodes.len() as u32).collect());
        }
        if leaves.is_empty() {
            bail!("no triangles in the inputs");
        }
        top.root = top.balanced(&leaves);
        root_page = write_pages(writer, &top, vec![top.root], opts, c.streams)?;
        scene_root = Some(top.nodes[top.root as usize].clone());
    }
    let Some(scene_root) = scene_root else {
        bail!("no triangles in the inputs")
    };
    Ok((scene_root, root_page))
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
            Some(plan) if count > 0 => encode_pages(&tree, plan, base, self.opts, self.streams)?,
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
