//! Meshes placed more than once: each prototype is built alone through partition and chunk
//! building (so a prototype larger than a chunk is fine), its root page holding its root as
//! node 0; each placement becomes an instance record and an instance leaf for the top tree,
//! whose box and cluster are the prototype root's, transformed.

use super::chunks::{self, Chunks};
use super::ingest::{Prototype, SharedMeshes};
use super::spill::{self, Spill, SpillWriter};
use super::tree::{BNode, Kind};
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
    pub leaves: Vec<BNode>,
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
    for (proto, to_world) in instances {
        let Some((root, page)) = &roots[proto as usize] else {
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
        let (lo, hi) = record.world_box(root.lo, root.hi);
        placed.leaves.push(BNode {
            lo,
            hi,
            kind: Kind::Instance {
                index: placed.records.len() as u32,
            },
            cluster: root.cluster.transformed(&record.matrix()),
            height: 0,
        });
        placed.records.push(record);
        placed.instanced_triangles += prototypes[proto as usize].count;
    }
    Ok(placed)
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
