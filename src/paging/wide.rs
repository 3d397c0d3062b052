//! A page's tree for exact rays, four children to a node with their boxes as SIMD lanes
//! (Embree's BVH4 layout), and its leaves' triangles four to a block, one per lane, both
//! built from the binary tree when the page is decoded. Each node takes the binary
//! children and opens the largest inner one until it has four. A leaf's lane names its
//! first triangle block, and the block its leaf, so a walk reads no binary node. Each
//! wide node names the binary node it descends from, so that a cone, which may stop at
//! any binary node, can go on down the binary tree where the lanes skip a level.

use super::{NodeRef, TNode, TriW};
use glam::Vec4;

/// Four child boxes, per axis, one child per lane, and what each child is.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(16))]
pub struct Wide {
    pub lo: [Vec4; 3],
    pub hi: [Vec4; 3],
    pub child: [u32; 4],
    /// A bit per lane that holds a child: the empty lanes' inverted boxes would pass the
    /// box test (their infinities cancel), so the walk masks them out with this.
    pub used: u32,
    /// The binary node whose descendants the lanes are (`ROOTS`: the page's roots), where
    /// a cone's walk goes on down the binary tree when it might stop at a node the lanes
    /// skip.
    pub node: u32,
    /// The binary nodes between `node` and the lanes (`NO_NODE` where fewer than two;
    /// `MANY` in both where more), whose boxes a cone's walk tests too: the cone might
    /// stop at one whose lanes the ray misses.
    pub skipped: [u32; 2],
}

const _: () = assert!(std::mem::size_of::<Wide>() == 128);

/// `Wide::node` of a page's root: its lanes descend from the page's roots.
pub const ROOTS: u32 = u32::MAX;
/// No node, in `Wide::skipped`.
pub const NO_NODE: u32 = u32::MAX;
/// More skipped nodes than `Wide::skipped` holds.
pub const MANY: u32 = u32::MAX - 1;

/// A child's kind in the top two bits of `Wide::child`, its index below.
pub const KIND: u32 = 3 << 30;
/// Another wide node of the page.
pub const WIDE: u32 = 0;
/// A leaf: its first block of `Page::tri4`.
pub const LEAF: u32 = 1 << 30;
/// With `LEAF`: an instance leaf, its binary node below (triangle blocks never reach this
/// bit).
pub const INSTANCE: u32 = 1 << 29;
/// A child page (its wide root is node 0).
pub const PAGE: u32 = 2 << 30;
/// No child: the lane's box is empty and never hit.
pub const EMPTY: u32 = 3 << 30;

/// Four triangles' vertices, one triangle per lane: `v[vertex][axis]`. Lanes past a
/// leaf's last triangle hold zeros and are masked off by the walk. Every block of a leaf
/// names the leaf, so a walk that reaches a leaf through its block reads no node.
#[derive(Clone, Copy, Debug, Default)]
#[repr(C, align(16))]
pub struct Tri4 {
    pub v: [[Vec4; 3]; 3],
    /// Each lane's material.
    pub material: [u32; 4],
    /// The leaf (a binary node of the page).
    pub leaf: u32,
    /// The leaf's first triangle in the page.
    pub first: u32,
    /// The leaf's triangles (1 to 8): its blocks follow this one up to that count.
    pub count: u32,
}

const _: () = assert!(std::mem::size_of::<Tri4>() == 176);

/// A leaf's `TNode::tri4` when it has no triangles, so no block (no page has this many).
pub const NO_BLOCK: u32 = (1 << 28) - 1;

impl Tri4 {
    /// The block of up to four triangles `quad`, in lane order, of no leaf.
    pub fn new(quad: &[TriW]) -> Tri4 {
        let mut b = Tri4::default();
        for (lane, t) in quad.iter().take(4).enumerate() {
            b.material[lane] = t.material;
            for (v, p) in t.p.iter().enumerate() {
                for (axis, &c) in p.iter().enumerate() {
                    b.v[v][axis][lane] = c;
                }
            }
        }
        b
    }

    /// The triangle in `lane`.
    pub fn tri(&self, lane: usize) -> TriW {
        TriW {
            // Through arrays: indexing a `Vec4` branches on the lane.
            p: self.v.map(|axes| axes.map(|c| c.to_array()[lane])),
            material: self.material[lane],
        }
    }
}

/// `Page::tri4`'s slot of a triangle no leaf holds.
pub const NO_SLOT: u32 = u32::MAX;

/// The leaves' triangles of a page as blocks of four, recording each leaf's first block in
/// its node, and each triangle's slot (block × 4 + lane); `None` if the blocks outnumber
/// what a node can record.
pub fn tri4s(bvh: &mut [TNode], tris: &[TriW]) -> Option<(Vec<Tri4>, Vec<u32>)> {
    let mut out = Vec::new();
    let mut slots = vec![NO_SLOT; tris.len()];
    for (leaf, node) in bvh.iter_mut().enumerate() {
        let NodeRef::Leaf { first, count } = node.link() else {
            continue;
        };
        let end = (first + count).min(tris.len() as u32);
        let first = first.min(end);
        if first == end {
            node.set_tri4(NO_BLOCK);
            continue;
        }
        if out.len() >= NO_BLOCK as usize {
            return None;
        }
        node.set_tri4(out.len() as u32);
        for (k, slot) in slots[first as usize..end as usize].iter_mut().enumerate() {
            *slot = (out.len() * 4 + k) as u32;
        }
        out.extend(tris[first as usize..end as usize].chunks(4).map(|q| Tri4 {
            leaf: leaf as u32,
            first,
            count: end - first,
            ..Tri4::new(q)
        }));
    }
    Some((out, slots))
}

impl Wide {
    const NONE: Wide = Wide {
        lo: [Vec4::INFINITY; 3],
        hi: [Vec4::NEG_INFINITY; 3],
        child: [EMPTY; 4],
        used: 0,
        node: ROOTS,
        skipped: [NO_NODE; 2],
    };
}

/// The wide tree of a page whose binary tree is `bvh` with roots 0..`roots`; node 0 is
/// the root (empty when the page has no nodes). A binary child index not above its
/// parent's (impossible in a valid archive) is dropped, so the build always ends.
pub fn build(bvh: &[TNode], roots: u32) -> Vec<Wide> {
    let top: Vec<u32> = (0..roots.min(bvh.len() as u32)).collect();
    if top.is_empty() {
        return Vec::new();
    }
    let mut out = vec![Wide::NONE];
    let mut work = vec![(0usize, ROOTS, top)];
    while let Some((slot, node, mut kids)) = work.pop() {
        let skipped = match open_until_four(bvh, &mut kids)[..] {
            [] => [NO_NODE; 2],
            [a] => [a, NO_NODE],
            [a, b] => [a, b],
            _ => [MANY; 2],
        };
        let mut w = Wide {
            node,
            skipped,
            ..Wide::NONE
        };
        for (lane, &k) in kids.iter().enumerate() {
            let n = &bvh[k as usize];
            for axis in 0..3 {
                w.lo[axis][lane] = n.lo[axis];
                w.hi[axis][lane] = n.hi[axis];
            }
            w.child[lane] = match n.link() {
                NodeRef::Inner(l, r) => {
                    let s = out.len();
                    out.push(Wide::NONE);
                    work.push((s, k, children(bvh, k, l, r)));
                    WIDE | s as u32
                }
                NodeRef::Leaf { .. } => LEAF | n.tri4(),
                NodeRef::ChildPage(p) => PAGE | p,
                NodeRef::Instance(_) => LEAF | INSTANCE | k,
            };
            w.used |= 1 << lane;
        }
        out[slot] = w;
    }
    out
}

/// Inner node k's children l and r that exist and lie after it.
fn children(bvh: &[TNode], k: u32, l: u32, r: u32) -> Vec<u32> {
    [l, r]
        .into_iter()
        .filter(|&c| c > k && (c as usize) < bvh.len())
        .collect()
}

/// Replaces the inner node of largest box surface among `kids` by its children while
/// there are fewer than four; the nodes it replaced.
fn open_until_four(bvh: &[TNode], kids: &mut Vec<u32>) -> Vec<u32> {
    let mut opened = Vec::new();
    while kids.len() < 4 {
        let area = |k: u32| {
            let n = &bvh[k as usize];
            let e = glam::Vec3::from(n.hi) - glam::Vec3::from(n.lo);
            e.x * e.y + e.y * e.z + e.z * e.x
        };
        let best = kids
            .iter()
            .enumerate()
            .filter_map(|(i, &k)| match bvh[k as usize].link() {
                NodeRef::Inner(l, r) => Some((i, k, l, r)),
                _ => None,
            })
            .max_by(|a, b| area(a.1).total_cmp(&area(b.1)));
        let Some((i, k, l, r)) = best else {
            break;
        };
        kids.splice(i..=i, children(bvh, k, l, r));
        opened.push(k);
    }
    opened
}
