//! Light cells as the transfer's gather elements, each on one side of the surface: a cell
//! of a large triangle (`light_store::Keys`, the cells the cone integrator stores light in:
//! a triangle's n×n grid over its barycentrics, n from its size), or a whole leaf where its
//! triangles are smaller than a cell (a scan's fine triangles would otherwise each be a
//! cell, and gathering light costs rays per cell). A cell's light is the mean over its
//! area of the direct light arriving there, gathered at points spread over it.

use crate::light_store::{tri_area, Keys, GRID};
use crate::paging::{NodeRef, Page, PageCache, TriW};
use crate::sampler::Hash;
use crate::trace::{placed_tri, Hit, Tracer, NO_INSTANCE};
use canopy_format::codec::snorm16_decode;
use glam::Vec3A as V;

/// Fewest points a cell gathers light at, and most.
const MIN_POINTS: usize = 4;
const MAX_POINTS: usize = 4096;
/// Gather points per cell on average: besides each cell's least, the rest go to cells by
/// the transfer they carry over the whole image, so the light of a cell many pixels read
/// (whose noise no pixel averages away) is gathered at many points.
const MEAN_POINTS: usize = 8;

/// A point where light is gathered: position and unit normal of the side lit.
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct GatherPoint {
    pub p: [f32; 3],
    pub n: [f32; 3],
}

/// How many points each cell gathers at, given the transfer each carries summed over the
/// image (luminance).
pub fn counts(carried: &[f32]) -> Vec<usize> {
    let total: f64 = carried.iter().map(|&c| c as f64).sum();
    let spare = ((MEAN_POINTS - MIN_POINTS) * carried.len()) as f64;
    carried
        .iter()
        .map(|&c| {
            let share = if total > 0.0 { c as f64 / total } else { 0.0 };
            MIN_POINTS + ((share * spare).ceil() as usize).min(MAX_POINTS - MIN_POINTS)
        })
        .collect()
}

/// Leaves whose triangles' area-weighted mean winding normal is at least this long (1: all
/// face one way) are one cell a side; the triangles of other leaves keep a cell each.
const COHERENT: f32 = 0.9;

/// The cell a hit on its `back` side (or front) lands in: the triangle's cell; or, where
/// the triangle is a single cell and its leaf's triangles face one way, the leaf's side
/// (the key after the leaf's own, the back after that: keys the store leaves unused),
/// taken against the leaf's mean normal whatever the winding of the triangle hit. A
/// prototype's leaf is keyed as the hit's instance places it, so copies in different light
/// keep their own cells.
pub fn key(tr: &mut Tracer, keys: &Keys, hit: &Hit, back: bool) -> u64 {
    let leaf = keys.placed(hit.instance, hit.leaf);
    if keys.grid(&hit.tri) > 1.0 {
        return keys.tri(leaf, hit.slot, back, keys.cell_of(&hit.tri, hit.b));
    }
    let page = tr.page_handle(hit.page);
    match coherent_leaf(&page, hit.leaf) {
        Some((mean, first)) => {
            let flip = page
                .tri(first + hit.slot)
                .is_some_and(|t| opposed(&t, mean));
            keys.node(leaf) + 1 + (back ^ flip) as u64
        }
        None => keys.tri(leaf, hit.slot, back, 0),
    }
}

/// A leaf (global node `leaf` of `page`) whose triangles face one way: its mean winding
/// normal and first triangle.
fn coherent_leaf(page: &Page, leaf: u64) -> Option<(V, u32)> {
    let local = leaf.checked_sub(page.first_node)? as usize;
    let mean = V::from(page.nodes.get(local)?.normal.map(snorm16_decode));
    let Some(NodeRef::Leaf { first, .. }) = page.bvh.get(local).map(|n| n.link()) else {
        return None;
    };
    (mean.length() >= COHERENT).then_some((mean, first))
}

/// Whether `t` is wound against `normal` (its winding normal points away from it).
fn opposed(t: &TriW, normal: V) -> bool {
    let p = t.p.map(V::from);
    (p[1] - p[0]).cross(p[2] - p[0]).dot(normal) < 0.0
}

/// `k` points stratified over the cell `key` names, with the normal of its side, in world
/// space (none if the key names no triangle of the archive).
pub fn points(
    cache: &PageCache,
    keys: &Keys,
    key: u64,
    k: usize,
    rng: &mut Hash,
) -> Vec<GatherPoint> {
    let (placed, cell) = keys.decode(key);
    let (instance, leaf) = keys.unplace(placed);
    let inst = match instance {
        NO_INSTANCE => None,
        i => match cache.instance(i) {
            Some(inst) => Some(inst),
            None => return Vec::new(),
        },
    };
    let Some(page) = cache.page_of(leaf).map(|p| cache.get(p)) else {
        return Vec::new();
    };
    let local = (leaf - page.first_node) as usize;
    let Some(NodeRef::Leaf { first, count }) = page.bvh.get(local).map(|n| n.link()) else {
        return Vec::new();
    };
    // Each triangle placed, and whether it is wound against its leaf's mean normal.
    let mean = coherent_leaf(&page, leaf).map_or(V::ZERO, |c| c.0);
    let tris: Vec<(TriW, bool)> = (first..first + count)
        .filter_map(|t| page.tri(t))
        .map(|t| {
            let placed = inst.as_ref().map_or(t, |i| placed_tri(i, &t));
            (placed, opposed(&t, mean))
        })
        .collect();
    match cell {
        Some((slot, back, cell)) => match tris.get(slot as usize) {
            Some((tri, _)) => cell_points(keys, tri, (back, cell), k, rng),
            None => Vec::new(),
        },
        None => leaf_points(&tris, key == keys.node(placed) + 2, k, rng),
    }
}

/// `k` points over a leaf's triangles, each chosen by its area (stratified), on the leaf's
/// `back` side: each triangle's normal turned to its leaf's mean normal (the flag with it)
/// and then to the back if asked, as `key` takes a leaf's sides.
fn leaf_points(tris: &[(TriW, bool)], back: bool, k: usize, rng: &mut Hash) -> Vec<GatherPoint> {
    let total: f32 = tris.iter().map(|t| tri_area(&t.0)).sum();
    if tris.is_empty() || total <= 0.0 {
        return Vec::new();
    }
    (0..k)
        .map(|s| {
            let mut x = (s as f32 + rng.f32()) / k as f32 * total;
            let (t, flip) = tris
                .iter()
                .find(|t| {
                    x -= tri_area(&t.0);
                    x < 0.0
                })
                .unwrap_or(&tris[tris.len() - 1]);
            let (u, v) = (rng.f32().sqrt(), rng.f32());
            point_on(t, [1.0 - u, u * (1.0 - v), u * v], back ^ flip)
        })
        .collect()
}

/// `k` points stratified over cell `cell` of `tri`, on its `back` side or front.
fn cell_points(
    keys: &Keys,
    tri: &TriW,
    (back, cell): (bool, u64),
    k: usize,
    rng: &mut Hash,
) -> Vec<GatherPoint> {
    let n = keys.grid(tri);
    let (i, j) = ((cell / GRID) as f32, (cell % GRID) as f32);
    let side = (k as f32).sqrt().ceil() as usize;
    (0..k)
        .map(|s| {
            // Stratified in the cell's square; a diagonal cell's outer half folds back.
            let x = ((s % side) as f32 + rng.f32()) / side as f32;
            let y = ((s / side % side) as f32 + rng.f32()) / side as f32;
            let (x, y) = if i + j + 1.0 >= n && x + y > 1.0 {
                (1.0 - y, 1.0 - x)
            } else {
                (x, y)
            };
            let (b1, b2) = ((i + x) / n, (j + y) / n);
            point_on(tri, [1.0 - b1 - b2, b1, b2], back)
        })
        .collect()
}

/// The point at barycentrics `b` of `tri`, with its front (or `back`) normal.
fn point_on(tri: &TriW, b: [f32; 3], back: bool) -> GatherPoint {
    let p = tri.p.map(V::from);
    let q = p[0] * b[0] + p[1] * b[1] + p[2] * b[2];
    let n = (p[1] - p[0]).cross(p[2] - p[0]).normalize_or_zero();
    GatherPoint {
        p: q.into(),
        n: if back { -n } else { n }.into(),
    }
}
