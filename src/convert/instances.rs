//! Meshes placed more than once: each prototype is built alone through partition and chunk
//! building (so a prototype larger than a chunk is fine), its root page holding its root as
//! node 0; each placement becomes an instance record and an instance leaf, whose box and
//! cluster are the prototype root's, transformed. The leaves, in Morton order, are built
//! into balanced subtrees of `GROUP` at a time, each written to pages as it is built, so
//! that memory holds the records and one group's nodes, not a node per instance.

use super::chunks::{self, Chunks};
use super::ingest::{Prototype, SharedMeshes};
use super::morton;
use super::spill::{self, Spill, SpillWriter};
use super::tree::{BNode, Kind, Tree};
use super::{partition, ConvertOptions, MatTable};
use crate::progress;
use anyhow::Result;
use canopy_format::validate::check_transform;
use canopy_format::{ArchiveWriter, InstanceRecord, Streams};
use std::path::Path;

/// What every prototype's build shares.
pub struct Build<'a> {
    pub mats: &'a MatTable,
    pub streams: Streams,
    pub threads: usize,
    /// Most triangles in one chunk.
    pub cap: u64,
    pub dir: &'a Path,
}

/// The instances, ready for the top tree and the instance table.
#[derive(Default)]
pub struct Placed {
    /// Roots of the instances' subtrees (their pages written), for the top tree.
    pub groups: Vec<BNode>,
    pub records: Vec<InstanceRecord>,
    pub prototypes: u64,
    /// Triangles the instances place (a prototype's counted once per instance).
    pub instanced_triangles: u64,
    /// The deepest prototype tree.
    pub depth: u32,
}

/// Builds every prototype and places its instances. An instance whose transform is not
/// invertible (a zero scale, which glTF files use to hide a copy) places nothing.
pub fn build(
    writer: &mut ArchiveWriter,
    (spilled, prototypes, instances): SharedMeshes,
    b: &Build,
    opts: &ConvertOptions,
) -> Result<Placed> {
    let total = prototypes.iter().map(|p| p.count).sum();
    let bar = progress::bar(opts.progress, total, "building prototypes");
    let mut roots = Vec::with_capacity(prototypes.len());
    for p in &prototypes {
        roots.push(match p.count {
            0 => None,
            _ => Some(prototype(writer, &spilled, p, b, opts)?),
        });
        bar.inc(p.count);
    }
    bar.finish_and_clear();
    let mut placed = Placed {
        prototypes: roots.iter().flatten().count() as u64,
        depth: roots
            .iter()
            .flatten()
            .map(|(r, _)| r.height)
            .max()
            .unwrap_or(0),
        ..Default::default()
    };
    let mut of_record = Vec::new();
    for (proto, to_world) in instances {
        let Some((_, page)) = &roots[proto as usize] else {
            continue;
        };
        let record = InstanceRecord {
            to_world,
            prototype_page: *page,
            reserved: [0; 12],
        };
        if check_transform(&record).is_err() {
            continue;
        }
        placed.records.push(record);
        of_record.push(proto);
        placed.instanced_triangles += prototypes[proto as usize].count;
    }
    let root = |i: u32| {
        let (root, _) = roots[of_record[i as usize] as usize]
            .as_ref()
            .expect("a placed prototype has a root");
        (&placed.records[i as usize], root)
    };
    let world_box = |i: u32| {
        let (record, root) = root(i);
        record.world_box(root.lo, root.hi)
    };
    let leaf = |i: u32| {
        let (record, root) = root(i);
        let (lo, hi) = world_box(i);
        BNode {
            lo,
            hi,
            kind: Kind::Instance { index: i },
            cluster: root.cluster.transformed(&record.matrix()),
            height: 0,
        }
    };
    let centre = |i: u32| {
        let (lo, hi) = world_box(i);
        [0, 1, 2].map(|a| 0.5 * lo[a] as f64 + 0.5 * hi[a] as f64)
    };
    let order = morton::order(placed.records.len() as u32, morton::MAX_BITS, centre);
    for group in order.chunks(GROUP) {
        placed
            .groups
            .push(subtree(writer, group.iter().map(|&i| leaf(i)), b, opts)?);
    }
    Ok(placed)
}

/// Instances per subtree of the top tree built and written at a time: the nodes in memory
/// stay bounded whatever the instance count.
const GROUP: usize = 1 << 14;

/// A balanced tree over `leaves` (in order) whose pages are written now: its root, standing
/// for them in the top tree (the leaf itself when there is one).
fn subtree(
    writer: &mut ArchiveWriter,
    leaves: impl Iterator<Item = BNode>,
    b: &Build,
    opts: &ConvertOptions,
) -> Result<BNode> {
    let mut tree = Tree {
        nodes: leaves.collect(),
        tris: Vec::new(),
        root: 0,
    };
    let items: Vec<u32> = (0..tree.nodes.len() as u32).collect();
    tree.root = tree.balanced(&items);
    let root = tree.nodes[tree.root as usize].clone();
    let Kind::Inner(children) = root.kind else {
        return Ok(root);
    };
    let page = chunks::write_pages(writer, &tree, children.to_vec(), opts, b.streams)?;
    Ok(BNode {
        kind: Kind::External { page },
        ..root
    })
}

/// One prototype's tree: its triangles copied to their own spill, partitioned and built.
fn prototype(
    writer: &mut ArchiveWriter,
    spilled: &Spill,
    p: &Prototype,
    b: &Build,
    opts: &ConvertOptions,
) -> Result<(BNode, u32)> {
    let mut own = SpillWriter::create(b.dir, 256 << 10)?;
    spill::for_each_in(spilled, p.start, p.count, |t| own.write(t))?;
    let files = partition::partition(own.finish()?, p.count, [p.lo, p.hi], b.cap, b.dir, false)?;
    let c = Chunks {
        files,
        mats: b.mats,
        triangles: p.count,
        streams: b.streams,
        threads: b.threads,
        show: false,
    };
    chunks::build(writer, c, Vec::new(), opts)
}
