//! Meshes placed more than once: each prototype is built alone through partition and chunk
//! building (so a prototype larger than a chunk is fine), its root page holding its root as
//! node 0; each placement becomes an instance record and an instance leaf, whose box and
//! cluster are the prototype root's, transformed. The leaves, in Morton order, are built
//! into balanced subtrees of `GROUP` at a time, each written to pages (which carry the
//! records) as it is built, so that memory holds one group's nodes, not a node per instance.

use super::chunks::{self, Chunks};
use super::ingest::{Placement, Prototype, SharedMeshes};
use super::morton;
use super::record_spill::{self, RecordWriter};
use super::spill::{self, Spill, SpillWriter};
use super::tree::{BNode, Kind, Tree};
use super::{partition, ConvertOptions, MatTable};
use crate::progress;
use anyhow::Result;
use canopy_format::validate::check_transform;
use canopy_format::{ArchiveWriter, InstanceRecord, Streams};
use std::collections::HashMap;
use std::path::Path;

/// What every prototype's build shares.
pub struct Build<'a> {
    pub mats: &'a MatTable,
    pub streams: Streams,
    pub threads: usize,
    /// Most triangles in one chunk.
    pub cap: u64,
    pub dir: &'a Path,
    /// Memory for one sorted run of placements.
    pub run_bytes: u64,
}

/// The instances, ready for the top tree.
#[derive(Default)]
pub struct Placed {
    /// Roots of the instances' subtrees (their pages written, with the instance records),
    /// for the top tree; a subtree of one instance is its bare leaf, naming a record of
    /// `loose`.
    pub groups: Vec<BNode>,
    pub loose: Vec<InstanceRecord>,
    /// Instances placed.
    pub count: u64,
    pub prototypes: u64,
    /// Triangles the instances place (a prototype's counted once per instance).
    pub instanced_triangles: u64,
    /// The deepest prototype tree.
    pub depth: u32,
}

/// A placement on its way to the top tree: its Morton code and record.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Keyed {
    code: u64,
    record: InstanceRecord,
}

/// Builds every prototype and places its instances. An instance whose transform is not
/// invertible (a zero scale, which glTF files use to hide a copy) places nothing. The
/// placements stay on disk: one pass finds their centres' bounds, a sort in bounded runs
/// (`record_spill`) puts them in Morton order, and each `GROUP` of them is built and
/// written as it arrives, so memory holds a run and a group whatever their number.
pub fn build(
    writer: &mut ArchiveWriter,
    (spilled, prototypes, mut placements): SharedMeshes,
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
    drop(spilled);
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
    // The prototype root a record's page is, for its box and cluster.
    let root_of: HashMap<u32, &BNode> = roots.iter().flatten().map(|(r, p)| (*p, r)).collect();
    let record = |p: &Placement| -> Option<(InstanceRecord, [[f32; 3]; 2])> {
        let (root, page) = roots.get(p.prototype as usize)?.as_ref()?;
        let record = InstanceRecord {
            to_world: p.to_world,
            prototype_page: *page,
            reserved: [0; 12],
        };
        check_transform(&record).ok()?;
        let (lo, hi) = record.world_box(root.lo, root.hi);
        Some((record, [lo, hi]))
    };
    let centre =
        |[lo, hi]: [[f32; 3]; 2]| [0, 1, 2].map(|a| 0.5 * lo[a] as f64 + 0.5 * hi[a] as f64);
    let mut bounds = [[f64::INFINITY; 3], [f64::NEG_INFINITY; 3]];
    placements.for_each(|p| {
        if let Some((_, b)) = record(&p) {
            let c = centre(b);
            for a in 0..3 {
                bounds[0][a] = bounds[0][a].min(c[a]);
                bounds[1][a] = bounds[1][a].max(c[a]);
            }
            placed.count += 1;
            placed.instanced_triangles += prototypes[p.prototype as usize].count;
        }
        Ok(())
    })?;
    let mut keyed = RecordWriter::create(b.dir)?;
    placements.for_each(|p| match record(&p) {
        Some((record, b)) => keyed.push(&Keyed {
            code: morton::code_in(centre(b), bounds, morton::MAX_BITS),
            record,
        }),
        None => Ok(()),
    })?;
    drop(placements);
    let leaf = |r: &InstanceRecord, index: u32| {
        let root = root_of[&r.prototype_page];
        let (lo, hi) = r.world_box(root.lo, root.hi);
        BNode {
            lo,
            hi,
            kind: Kind::Instance { index },
            cluster: root.cluster.transformed(&r.matrix()),
            height: 0,
        }
    };
    let mut group = Vec::with_capacity(GROUP);
    let mut flush = |group: &mut Vec<InstanceRecord>, placed: &mut Placed| -> Result<()> {
        let leaves = group.iter().zip(0..).map(|(r, i)| leaf(r, i)).collect();
        let (root, bare) = subtree(writer, leaves, std::mem::take(group), b, opts)?;
        let kind = match root.kind {
            Kind::Instance { .. } => Kind::Instance {
                index: placed.loose.len() as u32,
            },
            kind => kind,
        };
        placed.loose.extend(bare);
        placed.groups.push(BNode { kind, ..root });
        Ok(())
    };
    let run = (b.run_bytes / std::mem::size_of::<Keyed>() as u64) as usize;
    let mut keyed = keyed.finish()?;
    record_spill::for_each_sorted(
        &mut keyed,
        |k| k.code,
        run,
        b.dir,
        |k| {
            group.push(k.record);
            match group.len() == GROUP {
                true => flush(&mut group, &mut placed),
                false => Ok(()),
            }
        },
    )?;
    if !group.is_empty() {
        flush(&mut group, &mut placed)?;
    }
    Ok(placed)
}

/// Instances per subtree of the top tree built and written at a time: the nodes in memory
/// stay bounded whatever the instance count.
const GROUP: usize = 1 << 14;

/// A balanced tree over `leaves` (in order), naming `records`, whose pages are written
/// now: its root, standing for them in the top tree (the leaf itself when there is one;
/// then `records` is given back).
fn subtree(
    writer: &mut ArchiveWriter,
    leaves: Vec<BNode>,
    records: Vec<InstanceRecord>,
    b: &Build,
    opts: &ConvertOptions,
) -> Result<(BNode, Vec<InstanceRecord>)> {
    let mut tree = Tree {
        nodes: leaves,
        tris: Vec::new(),
        instances: records,
        root: 0,
    };
    let items: Vec<u32> = (0..tree.nodes.len() as u32).collect();
    tree.root = tree.balanced(&items);
    let root = tree.nodes[tree.root as usize].clone();
    let Kind::Inner(children) = root.kind else {
        return Ok((root, tree.instances));
    };
    let page = chunks::write_pages(writer, &tree, children.to_vec(), opts, b.streams)?;
    let root = BNode {
        kind: Kind::External { page },
        ..root
    };
    Ok((root, Vec::new()))
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
    let files = partition::partition(
        own.finish()?,
        p.count,
        [p.lo, p.hi],
        b.cap,
        b.dir,
        None,
        false,
    )?;
    let c = Chunks {
        files,
        mats: b.mats,
        triangles: p.count,
        streams: b.streams,
        threads: b.threads,
        show: false,
    };
    chunks::build(writer, c, (Vec::new(), Vec::new()), opts)
}
