//! An in-memory binary tree over one chunk of triangles (built with obvhs's PLOC builder),
//! with exact f32 bounds and aggregated cluster attributes per node.

use super::aggregate::{Cluster, MatTable};
use super::morton::{self, MAX_BITS};
use crate::import::SpillTri;
use canopy_format::InstanceRecord;
use glam::Vec3A;
use obvhs::aabb::Aabb;
use obvhs::bvh2::{leaf_collapser::collapse, reinsertion::ReinsertionOptimizer, Bvh2};
use obvhs::{ploc::PlocBuilder, BvhBuildParams};

/// Most triangles a leaf holds: the most a version-1 archive allows (readers refuse more,
/// and the cone integrator keys stored light by a leaf's triangle slot).
pub const MAX_LEAF_TRIS: u32 = canopy_format::validate::MAX_LEAF_TRIANGLES;

/// Coincident triangles beyond this many are built by count, not by PLOC.
const COINCIDENT_GROUP: usize = 64;

/// Splits off groups of more than `COINCIDENT_GROUP` triangles whose centroids fall in one
/// cell of a 2²¹-per-axis grid over the centroids' bounds: the indices of the rest and of
/// each group. When there is no such group every triangle is in the rest, in input order;
/// otherwise the rest and the groups are in Morton order.
fn split_coincident(tris: &[SpillTri]) -> (Vec<u32>, Vec<Vec<u32>>) {
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    let centroids: Vec<[f32; 3]> = tris
        .iter()
        .map(|t| {
            let c = t.centroid();
            for a in 0..3 {
                lo[a] = lo[a].min(c[a]);
                hi[a] = hi[a].max(c[a]);
            }
            c
        })
        .collect();
    let key = |c: &[f32; 3]| {
        let q = [0, 1, 2].map(|a| {
            let e = hi[a] - lo[a];
            let f = if e > 0.0 { (c[a] - lo[a]) / e } else { 0.0 };
            ((f as f64 * (1u64 << MAX_BITS) as f64) as u64).min((1 << MAX_BITS) - 1) as u32
        });
        morton::code(q)
    };
    let keys: Vec<u64> = centroids.iter().map(key).collect();
    drop(centroids);
    if !may_share_a_cell(&keys) {
        return ((0..tris.len() as u32).collect(), Vec::new());
    }
    let mut keyed: Vec<(u64, u32)> = keys.into_iter().zip(0..).collect();
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

/// Whether more than `COINCIDENT_GROUP` of `keys` may be equal: counts keys by a hash into
/// twice as many saturating counters as keys. Equal keys raise one counter together, so
/// when none passes `COINCIDENT_GROUP` no key is that common; collisions only ever say
/// "may". The sort that finds the groups cost a twentieth of a chunk's build.
fn may_share_a_cell(keys: &[u64]) -> bool {
    let bits = (2 * keys.len()).next_power_of_two().trailing_zeros().max(1);
    let mut counts = vec![0u8; 1 << bits];
    keys.iter().any(|&k| {
        let slot = (k.wrapping_mul(0x9e37_79b9_7f4a_7c15) >> (64 - bits)) as usize;
        counts[slot] = counts[slot].saturating_add(1);
        counts[slot] as usize > COINCIDENT_GROUP
    })
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
        let ploc = (!plain.is_empty()).then(|| Ploc::new(&tris, &plain, fast));
        // Triangles in leaf order, PLOC's leaves first, then each group's; the input is
        // dropped before the nodes are built.
        let leaf_order = ploc
            .iter()
            .flat_map(|h| h.order.iter().map(|&k| plain[k as usize]));
        // Nodes: the hierarchy's, and under 2 per group leaf and group.
        let group_nodes = 2 * groups.iter().map(|g| g.len() / 8 + 2).sum::<usize>();
        let mut tree = Tree {
            nodes: Vec::with_capacity(ploc.as_ref().map_or(0, |h| h.steps.len()) + group_nodes),
            tris: leaf_order
                .chain(groups.iter().flatten().copied())
                .map(|i| tris[i as usize])
                .collect(),
            instances: Vec::new(),
            root: 0,
        };
        drop(tris);
        let mut roots: Vec<u32> = ploc
            .map(|h| tree.replay(&h.steps, mats))
            .into_iter()
            .collect();
        let mut first = plain.len() as u32;
        for group in groups {
            let count = group.len() as u32;
            let leaves: Vec<u32> = (0..count)
                .step_by(MAX_LEAF_TRIS as usize)
                .map(|k| tree.leaf(first + k, MAX_LEAF_TRIS.min(count - k), mats))
                .collect();
            roots.push(tree.balanced(&leaves));
            first += count;
        }
        tree.root = tree.balanced(&roots);
        tree
    }

    /// Builds the nodes of a hierarchy from its post-order steps (`Ploc::steps`) over the
    /// triangles from the first on; returns its root.
    fn replay(&mut self, steps: &[u32], mats: &MatTable) -> u32 {
        let mut next_tri = 0u32;
        let mut built: Vec<u32> = Vec::new();
        for &count in steps {
            let node = match count {
                0 => {
                    let r = built.pop().expect("right child");
                    let l = built.pop().expect("left child");
                    self.join(l, r)
                }
                _ => {
                    next_tri += count;
                    self.leaf(next_tri - count, count, mats)
                }
            };
            built.push(node);
        }
        built[0]
    }
}

/// A triangle's bounding box.
fn bounds(t: &SpillTri) -> Aabb {
    let p = t.p.map(Vec3A::from);
    Aabb::new(p[0].min(p[1]).min(p[2]), p[0].max(p[1]).max(p[2]))
}

/// A PLOC hierarchy, as the order of its leaves' triangles and its post-order steps.
struct Ploc {
    /// Positions in `subset` of the triangles, leaf by leaf, depth first.
    order: Vec<u32>,
    /// Per node in post-order: the triangles of a leaf, or 0 for an inner node, which joins
    /// the two latest nodes.
    steps: Vec<u32>,
}

impl Ploc {
    /// The hierarchy of the triangles of `tris` that `subset` names (not empty).
    fn new(tris: &[SpillTri], subset: &[u32], fast: bool) -> Ploc {
        let boxes: Vec<Aabb> = subset.iter().map(|&i| bounds(&tris[i as usize])).collect();
        let (bvh, collapse) = ploc_hierarchy(&boxes, fast);
        drop(boxes);
        Ploc::walk(&bvh, collapse)
    }

    /// The leaf order and steps of `bvh`, with `collapse` applied on the way if given.
    fn walk(bvh: &Bvh2, collapse: Option<Collapse>) -> Ploc {
        let mut ploc = Ploc {
            order: Vec::with_capacity(bvh.primitive_indices.len()),
            steps: Vec::new(),
        };
        let mut stack = vec![(0usize, false)];
        while let Some((i, visited)) = stack.pop() {
            let n = &bvh.nodes[i];
            let first = n.first_index as usize;
            match (n.is_leaf(), visited) {
                (true, _) => {
                    ploc.steps.push(n.prim_count);
                    ploc.order.extend_from_slice(
                        &bvh.primitive_indices[first..first + n.prim_count as usize],
                    );
                }
                (false, false) => stack.extend([(i, true), (first + 1, false), (first, false)]),
                (false, true) => match collapse.and_then(|c| c.merged(bvh, i, &ploc.steps)) {
                    Some(total) => {
                        ploc.steps.truncate(ploc.steps.len() - 2);
                        ploc.steps.push(total);
                    }
                    None => ploc.steps.push(0),
                },
            }
        }
        ploc
    }
}

/// obvhs's binary PLOC hierarchy over `boxes` (its fast or medium preset, `MAX_LEAF_TRIS` a
/// leaf), built as obvhs builds it with the steps spelled out: PLOC, reinsertion, the SAH
/// leaf collapse, reinsertion again. When the second reinsertion does not run (the fast
/// preset) the collapse is returned rather than applied, for the walk to apply: the same
/// leaves without compacting the node array, which took as long as the PLOC itself.
fn ploc_hierarchy(boxes: &[Aabb], fast: bool) -> (Bvh2, Option<Collapse>) {
    let mut params = match fast {
        true => BvhBuildParams::fast_build(),
        false => BvhBuildParams::medium_build(),
    };
    params.max_prims_per_leaf = MAX_LEAF_TRIS;
    let mut bvh = PlocBuilder::with_capacity(boxes.len()).build(
        params.ploc_search_distance,
        boxes,
        (0..boxes.len() as u32).collect(),
        params.sort_precision,
        params.search_depth_threshold,
    );
    let mut reinsertion = ReinsertionOptimizer::default();
    reinsertion.run(&mut bvh, params.reinsertion_batch_ratio, None);
    let (max_prims, traversal) = (params.max_prims_per_leaf, params.collapse_traversal_cost);
    let after =
        params.reinsertion_batch_ratio * params.post_collapse_reinsertion_batch_ratio_multiplier;
    if after > 0.0 {
        collapse(&mut bvh, max_prims, traversal);
        reinsertion.run(&mut bvh, after, None);
        return (bvh, None);
    }
    // obvhs's early exits: small trees and a root leaf are left as they are.
    let collapses = max_prims > 1
        && bvh.nodes.len() as u32 > max_prims * 2 + 1
        && bvh.primitive_indices.len() as u32 > max_prims
        && !bvh.nodes[0].is_leaf();
    let rule = Collapse {
        max_prims,
        traversal,
    };
    (bvh, collapses.then_some(rule))
}

/// obvhs's SAH leaf collapse (`leaf_collapser::collapse`): bottom up, two sibling leaves
/// merge into their parent when they hold at most `max_prims` together and the parent's
/// cost as a leaf, half-area × (count − `traversal`), is no more than theirs.
#[derive(Clone, Copy)]
struct Collapse {
    max_prims: u32,
    traversal: f32,
}

impl Collapse {
    /// The triangles inner node `i` holds if its children merge into it, given the post-order
    /// steps so far: a leaf is one step, so when the right child is a leaf the last two steps
    /// are the children's.
    fn merged(self, bvh: &Bvh2, i: usize, steps: &[u32]) -> Option<u32> {
        let [.., lc, rc] = *steps else {
            return None;
        };
        let total = lc + rc;
        if lc == 0 || rc == 0 || total > self.max_prims {
            return None;
        }
        let first = bvh.nodes[i].first_index as usize;
        let (l, r) = (&bvh.nodes[first], &bvh.nodes[first + 1]);
        let merged = bvh.nodes[i].aabb().half_area() * (total as f32 - self.traversal);
        let apart = l.aabb().half_area() * lc as f32 + r.aabb().half_area() * rc as f32;
        (merged <= apart).then_some(total)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_rng::TestRng;

    /// Triangles in a few clusters of varied sizes (so PLOC's leaves vary in size).
    fn scattered(rng: &mut TestRng, n: usize) -> Vec<SpillTri> {
        (0..n)
            .map(|i| {
                let c = rng.v(10.0) * (1 + i % 3) as f32;
                let s = 0.01 + rng.f32() * 0.5;
                SpillTri {
                    p: [0, 1, 2].map(|_| (c + rng.v(s)).to_array()),
                    ..Default::default()
                }
            })
            .collect()
    }

    /// A bumpy height field of `k`×`k` quads, two triangles each, as scans are.
    fn surface(k: usize) -> Vec<SpillTri> {
        let at = |x: usize, y: usize| {
            let (u, v) = (x as f32 / k as f32, y as f32 / k as f32);
            [u, v, 0.1 * (9.0 * u).sin() * (7.0 * v).cos()]
        };
        let tri = |p| SpillTri {
            p,
            ..Default::default()
        };
        (0..k * k)
            .flat_map(|q| {
                let (x, y) = (q % k, q / k);
                [
                    tri([at(x, y), at(x + 1, y), at(x + 1, y + 1)]),
                    tri([at(x, y), at(x + 1, y + 1), at(x, y + 1)]),
                ]
            })
            .collect()
    }

    /// The collapse recorded in the walk gives the leaves obvhs's own collapse makes: the
    /// same post-order steps and the same triangles in the same order.
    #[test]
    fn the_recorded_collapse_makes_obvhs_leaves() {
        let mut rng = TestRng::new(5);
        let cases = [3, 9, 17, 200, 5000].map(|n| scattered(&mut rng, n));
        let mut eights = 0;
        for tris in cases.into_iter().chain([surface(4), surface(60)]) {
            let n = tris.len();
            let all: Vec<u32> = (0..n as u32).collect();
            let ours = Ploc::new(&tris, &all, true);
            let boxes: Vec<Aabb> = tris.iter().map(bounds).collect();
            let mut params = BvhBuildParams::fast_build();
            params.max_prims_per_leaf = MAX_LEAF_TRIS;
            let bvh = obvhs::bvh2::builder::build_bvh2(&boxes, params, &mut Default::default());
            let theirs = Ploc::walk(&bvh, None);
            assert_eq!(ours.steps, theirs.steps, "{n} triangles: steps");
            assert_eq!(ours.order, theirs.order, "{n} triangles: leaf order");
            assert!(ours.steps.iter().all(|&c| c <= MAX_LEAF_TRIS));
            assert_eq!(ours.steps.iter().sum::<u32>(), n as u32);
            eights += ours.steps.iter().filter(|&&c| c == MAX_LEAF_TRIS).count();
        }
        assert!(eights > 0, "no case made a full leaf");
    }

    /// A cell holding more than `COINCIDENT_GROUP` centroids is always found; a chunk
    /// without one keeps its input order.
    #[test]
    fn coincident_groups_are_always_found() {
        let mut rng = TestRng::new(9);
        let mut tris = scattered(&mut rng, 3000);
        let (plain, groups) = split_coincident(&tris);
        assert!(groups.is_empty());
        assert_eq!(plain, (0..3000).collect::<Vec<u32>>());
        for extra in [COINCIDENT_GROUP + 1, 500] {
            let copy = tris[17];
            let mut with = tris.clone();
            for k in 0..extra {
                with.insert((k * 37) % with.len(), copy);
            }
            let (plain, groups) = split_coincident(&with);
            assert_eq!(groups.len(), 1, "{extra} copies");
            assert_eq!(
                groups[0].len(),
                extra + 1,
                "{extra} copies and the original"
            );
            assert!(groups[0].iter().all(|&i| with[i as usize] == copy));
            assert_eq!(plain.len() + groups[0].len(), with.len());
        }
        tris.truncate(10);
        assert!(split_coincident(&tris).1.is_empty());
    }
}
