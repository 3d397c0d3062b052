//! An in-memory binary tree over one chunk of triangles (built with obvhs's PLOC builder),
//! with exact f32 bounds and aggregated cluster attributes per node.

use super::aggregate::{Cluster, MatTable};
use super::morton::{self, MAX_BITS};
use crate::import::SpillTri;
use canopy_format::InstanceRecord;
use glam::Vec3A;
use obvhs::{bvh2::builder::build_bvh2_from_tris, triangle::Triangle, BvhBuildParams};

/// Most triangles a leaf holds: the most a version-1 archive allows (readers refuse more,
/// and the cone integrator keys stored light by a leaf's triangle slot).
pub const MAX_LEAF_TRIS: u32 = canopy_format::validate::MAX_LEAF_TRIANGLES;

/// Coincident triangles beyond this many are built by count, not by PLOC.
const COINCIDENT_GROUP: usize = 64;

/// Splits off groups of more than `COINCIDENT_GROUP` triangles whose centroids fall in one
/// cell of a 2²¹-per-axis grid over the centroids' bounds: the indices of the rest and of
/// each group, all in Morton order.
fn split_coincident(tris: &[SpillTri]) -> (Vec<u32>, Vec<Vec<u32>>) {
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    for t in tris {
        let c = t.centroid();
        for a in 0..3 {
            lo[a] = lo[a].min(c[a]);
            hi[a] = hi[a].max(c[a]);
        }
    }
    let key = |t: &SpillTri| {
        let c = t.centroid();
        let q = [0, 1, 2].map(|a| {
            let e = hi[a] - lo[a];
            let f = if e > 0.0 { (c[a] - lo[a]) / e } else { 0.0 };
            ((f as f64 * (1u64 << MAX_BITS) as f64) as u64).min((1 << MAX_BITS) - 1) as u32
        });
        morton::code(q)
    };
    let mut keyed: Vec<(u64, u32)> = tris
        .iter()
        .enumerate()
        .map(|(i, t)| (key(t), i as u32))
        .collect();
    keyed.sort_unstable();
    let mut plain = Vec::with_capacity(tris.len());
    let mut groups = Vec::new();
    for run in keyed.chunk_by(|a, b| a.0 == b.0) {
        let members = run.iter().map(|&(_, i)| i);
        if run.len() > COINCIDENT_GROUP {
            groups.push(members.collect());
        } else {
            plain.extend(members);
        }
    }
    (plain, groups)
}

#[derive(Clone, Copy, Debug, serde::Serialize, serde::Deserialize)]
pub enum Kind {
    Inner([u32; 2]),
    /// Range in the tree's triangle array.
    Leaf {
        first: u32,
        count: u32,
    },
    /// Children already written as the two roots of a page.
    External {
        page: u32,
    },
    /// A placement of a prototype: record `index` of the tree's `instances`.
    Instance {
        index: u32,
    },
}

#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct BNode {
    pub lo: [f32; 3],
    pub hi: [f32; 3],
    pub kind: Kind,
    pub cluster: Cluster,
    /// Levels below this node (0 for a leaf).
    pub height: u32,
}

pub struct Tree {
    pub nodes: Vec<BNode>,
    /// Triangles in leaf order.
    pub tris: Vec<SpillTri>,
    /// The records of the tree's instance leaves (`Kind::Instance`).
    pub instances: Vec<InstanceRecord>,
    pub root: u32,
}

fn union(a: &BNode, b: &BNode) -> ([f32; 3], [f32; 3]) {
    (
        [0, 1, 2].map(|i| a.lo[i].min(b.lo[i])),
        [0, 1, 2].map(|i| a.hi[i].max(b.hi[i])),
    )
}

impl Tree {
    /// Appends an inner node over two existing nodes, aggregating their attributes.
    pub fn join(&mut self, l: u32, r: u32) -> u32 {
        let (a, b) = (&self.nodes[l as usize], &self.nodes[r as usize]);
        let (lo, hi) = union(a, b);
        let node = BNode {
            lo,
            hi,
            kind: Kind::Inner([l, r]),
            cluster: Cluster::merge(&a.cluster, &b.cluster),
            height: a.height.max(b.height) + 1,
        };
        self.nodes.push(node);
        self.nodes.len() as u32 - 1
    }

    /// A leaf over `tris[first..first+count]`.
    pub fn leaf(&mut self, first: u32, count: u32, mats: &MatTable) -> u32 {
        let ts = &self.tris[first as usize..(first + count) as usize];
        let mut lo = [f32::INFINITY; 3];
        let mut hi = [f32::NEG_INFINITY; 3];
        let mut cluster: Option<Cluster> = None;
        for t in ts {
            for v in &t.p {
                for a in 0..3 {
                    lo[a] = lo[a].min(v[a]);
                    hi[a] = hi[a].max(v[a]);
                }
            }
            let c = Cluster::triangle(&t.p, t.curvature, &mats.of(t));
            cluster = Some(match cluster {
                Some(s) => Cluster::merge(&s, &c),
                None => c,
            });
        }
        self.nodes.push(BNode {
            lo,
            hi,
            kind: Kind::Leaf { first, count },
            cluster: cluster.expect("empty leaf"),
            height: 0,
        });
        self.nodes.len() as u32 - 1
    }

    /// `items` sorted by the Morton code of their boxes' centres (2¹⁰ cells an axis over
    /// the centres' bounds), for `balanced`.
    pub fn morton_order(&self, items: Vec<u32>) -> Vec<u32> {
        let centre = |k: u32| {
            let n = &self.nodes[items[k as usize] as usize];
            [0, 1, 2].map(|a| 0.5 * n.lo[a] as f64 + 0.5 * n.hi[a] as f64)
        };
        morton::order(items.len() as u32, 10, centre)
            .into_iter()
            .map(|k| items[k as usize])
            .collect()
    }

    /// A balanced binary tree over `items` (kept in order), built with `join`.
    pub fn balanced(&mut self, items: &[u32]) -> u32 {
        match items {
            [one] => *one,
            _ => {
                let (l, r) = items.split_at(items.len() / 2);
                let (l, r) = (self.balanced(l), self.balanced(r));
                self.join(l, r)
            }
        }
    }

    /// Builds the chunk's hierarchy and aggregates clusters bottom-up. Groups of more than
    /// `COINCIDENT_GROUP` triangles whose centroids share a cell of a 2²¹-per-axis grid
    /// (coincident or nearly so) are split by count into leaves under a balanced subtree:
    /// PLOC pairs equal boxes one pair per sweep, which made such inputs quadratic. The
    /// rest is built with PLOC (obvhs); a balanced tree in Morton order joins the parts.
    /// `fast` picks obvhs's fast preset (no post-collapse reinsertion) over medium.
    pub fn build(tris: Vec<SpillTri>, mats: &MatTable, fast: bool) -> Tree {
        let (plain, groups) = split_coincident(&tris);
        let mut tree = match plain.is_empty() {
            true => Tree {
                nodes: Vec::new(),
                tris: Vec::new(),
                instances: Vec::new(),
                root: 0,
            },
            false => Tree::build_ploc(&tris, &plain, mats, fast),
        };
        let mut roots = if tree.nodes.is_empty() {
            Vec::new()
        } else {
            vec![tree.root]
        };
        for group in groups {
            let first = tree.tris.len() as u32;
            let count = group.len() as u32;
            tree.tris.extend(group.iter().map(|&i| tris[i as usize]));
            let leaves: Vec<u32> = (0..count)
                .step_by(MAX_LEAF_TRIS as usize)
                .map(|k| tree.leaf(first + k, MAX_LEAF_TRIS.min(count - k), mats))
                .collect();
            let root = tree.balanced(&leaves);
            roots.push(root);
        }
        tree.root = tree.balanced(&roots);
        tree
    }

    /// The hierarchy by PLOC of the triangles of `tris` that `subset` names (not empty).
    fn build_ploc(tris: &[SpillTri], subset: &[u32], mats: &MatTable, fast: bool) -> Tree {
        let prims: Vec<Triangle> = subset
            .iter()
            .map(|&i| &tris[i as usize])
            .map(|t| Triangle {
                v0: Vec3A::from(t.p[0]),
                v1: Vec3A::from(t.p[1]),
                v2: Vec3A::from(t.p[2]),
            })
            .collect();
        let mut params = if fast {
            BvhBuildParams::fast_build()
        } else {
            BvhBuildParams::medium_build()
        };
        params.max_prims_per_leaf = MAX_LEAF_TRIS;
        let bvh = build_bvh2_from_tris(&prims, params, &mut Default::default());
        drop(prims);
        let children = |i: usize| {
            let n = &bvh.nodes[i];
            (n.prim_count == 0).then(|| [n.first_index as usize, n.first_index as usize + 1])
        };
        // Pass 1: triangles in depth-first leaf order, so each leaf's range is contiguous.
        let mut order = Vec::with_capacity(subset.len());
        let mut stack = vec![0usize];
        while let Some(i) = stack.pop() {
            match children(i) {
                Some([l, r]) => stack.extend([r, l]),
                None => {
                    let n = &bvh.nodes[i];
                    order.extend_from_slice(
                        &bvh.primitive_indices
                            [n.first_index as usize..(n.first_index + n.prim_count) as usize],
                    );
                }
            }
        }
        let mut tree = Tree {
            nodes: Vec::with_capacity(bvh.nodes.len()),
            tris: order
                .iter()
                .map(|&i| tris[subset[i as usize] as usize])
                .collect(),
            instances: Vec::new(),
            root: 0,
        };
        drop(order);
        // Pass 2: post-order, the same leaf order; inner nodes join the two latest results.
        let mut next_tri = 0u32;
        let mut built: Vec<u32> = Vec::new();
        let mut stack = vec![(0usize, false)];
        while let Some((i, visited)) = stack.pop() {
            match children(i) {
                None => {
                    let count = bvh.nodes[i].prim_count;
                    built.push(tree.leaf(next_tri, count, mats));
                    next_tri += count;
                }
                Some(_) if visited => {
                    let r = built.pop().expect("right child");
                    let l = built.pop().expect("left child");
                    built.push(tree.join(l, r));
                }
                Some([l, r]) => stack.extend([(i, true), (r, false), (l, false)]),
            }
        }
        tree.root = built[0];
        tree
    }
}
