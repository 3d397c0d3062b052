//! The node tree as the Haar basis of light over the scene (Hašan et al. 2006 §4; 001
//! §4.2): a gather element is a light cell of a leaf's triangle (`light_store::Keys`, the
//! same cells the cone integrator stores light in), its parent the leaf, then the leaf's
//! ancestors up to one virtual root over the root page's roots. Each element's light is
//! the mean over its area of the light arriving there; a parent's is the area-weighted mean
//! of its children's (the pull), so what a parent holds beyond its children is the Haar
//! scaling coefficient and the differences are the detail coefficients.

use crate::light_store::{tri_area, Keys, GRID};
use crate::paging::{NodeRef, Page, PageCache, TriW};
use crate::sampler::Hash;
use canopy_format::NONE;
use glam::Vec3A as V;
use rustc_hash::FxHashMap;
use std::sync::{Arc, RwLock};

/// The key of the virtual root above the root page's roots.
pub const TOP: u64 = u64::MAX;

/// Parent links of one page's nodes.
struct Links {
    /// Per node, its parent's index in the page (`NONE` for the page's roots).
    parent: Vec<u32>,
}

/// Parent links of the pages read so far, and how keys name nodes and cells.
pub struct Tree<'a> {
    cache: &'a PageCache,
    pub keys: Keys,
    pages: RwLock<FxHashMap<u32, Arc<Links>>>,
}

/// A point where light is gathered: position and unit normal of the side lit.
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct GatherPoint {
    pub p: [f32; 3],
    pub n: [f32; 3],
}

impl<'a> Tree<'a> {
    pub fn new(cache: &'a PageCache, keys: Keys) -> Tree<'a> {
        Tree {
            cache,
            keys,
            pages: RwLock::default(),
        }
    }

    fn links(&self, page: u32) -> Arc<Links> {
        if let Some(l) = self.pages.read().expect("links lock").get(&page) {
            return Arc::clone(l);
        }
        let p = self.cache.get(page);
        let mut parent = vec![NONE; p.bvh.len()];
        for (i, n) in p.bvh.iter().enumerate() {
            if let NodeRef::Inner(l, r) = n.link() {
                for c in [l, r] {
                    if let Some(slot) = parent.get_mut(c as usize) {
                        *slot = i as u32;
                    }
                }
            }
        }
        let links = Arc::new(Links { parent });
        self.pages
            .write()
            .expect("links lock")
            .insert(page, Arc::clone(&links));
        links
    }

    /// The keys of `node`'s ancestors (global number), nearest first, ending with `TOP`.
    pub fn ancestors(&self, node: u64, out: &mut Vec<u64>) {
        let Some(mut page) = self.cache.page_of(node) else {
            out.push(TOP);
            return;
        };
        let mut local = (node - self.cache.entries[page as usize].first_node) as u32;
        loop {
            let links = self.links(page);
            match links.parent.get(local as usize) {
                Some(&up) if up != NONE => local = up,
                _ => {
                    let e = &self.cache.entries[page as usize];
                    if e.parent_page == NONE {
                        break;
                    }
                    (page, local) = (e.parent_page, e.parent_node);
                }
            }
            let first = self.cache.entries[page as usize].first_node;
            out.push(self.keys.node(first + local as u64));
        }
        out.push(TOP);
    }

    /// `k` points spread over what `key` names, with the normal of the side it is lit on:
    /// stratified over a cell; over a node's triangles by area (front sides); none for
    /// `TOP` (its light is the mean of the root page's roots, see `gather_points`).
    pub fn points(&self, key: u64, k: usize, rng: &mut Hash) -> Vec<GatherPoint> {
        if key == TOP {
            return self.roots_points(k, rng);
        }
        let (node, cell) = self.keys.decode(key);
        let Some(page_id) = self.cache.page_of(node) else {
            return Vec::new();
        };
        let page = self.cache.get(page_id);
        let local = (node - page.first_node) as u32;
        match cell {
            Some((slot, back, cell)) => self.cell_points(&page, local, (slot, back, cell), k, rng),
            None => (0..k)
                .filter_map(|_| self.descend(Arc::clone(&page), local, rng))
                .collect(),
        }
    }

    fn roots_points(&self, k: usize, rng: &mut Hash) -> Vec<GatherPoint> {
        let page = self.cache.get(self.cache.root_page());
        let roots: Vec<u32> = (0..page.roots).collect();
        (0..k)
            .filter_map(|_| {
                let r = pick(&roots, |&r| page.nodes[r as usize].area, rng.f32())?;
                self.descend(Arc::clone(&page), *r, rng)
            })
            .collect()
    }

    fn cell_points(
        &self,
        page: &Page,
        leaf: u32,
        (slot, back, cell): (u32, bool, u64),
        k: usize,
        rng: &mut Hash,
    ) -> Vec<GatherPoint> {
        let NodeRef::Leaf { first, count } = page.bvh[leaf as usize].link() else {
            return Vec::new();
        };
        let Some(tri) = (slot < count).then(|| page.tri(first + slot)).flatten() else {
            return Vec::new();
        };
        let n = self.keys.grid(&tri);
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
                point_on(&tri, [1.0 - b1 - b2, b1, b2], back)
            })
            .collect()
    }

    /// A point on node `local` of `page`'s triangles, chosen by area.
    fn descend(&self, mut page: Arc<Page>, mut local: u32, rng: &mut Hash) -> Option<GatherPoint> {
        loop {
            match page.bvh.get(local as usize)?.link() {
                NodeRef::Inner(l, r) => {
                    let a = [l, r].map(|c| page.nodes.get(c as usize).map_or(0.0, |n| n.area));
                    local = *pick(&[l, r], |c| a[(*c == r) as usize], rng.f32())?;
                }
                NodeRef::ChildPage(c) => {
                    page = self.cache.get(c);
                    let a = [0, 1].map(|r| page.nodes.get(r).map_or(0.0, |n| n.area));
                    local = *pick(&[0u32, 1], |r| a[*r as usize], rng.f32())?;
                }
                NodeRef::Leaf { first, count } => {
                    let tris: Vec<TriW> =
                        (first..first + count).filter_map(|t| page.tri(t)).collect();
                    let t = pick(&tris, tri_area, rng.f32())?;
                    let (u, v) = (rng.f32().sqrt(), rng.f32());
                    return Some(point_on(t, [1.0 - u, u * (1.0 - v), u * v], false));
                }
                NodeRef::Instance(_) => return None,
            }
        }
    }
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

/// An item chosen with probability proportional to `weight`, by the uniform `u`.
fn pick<T>(items: &[T], weight: impl Fn(&T) -> f32, u: f32) -> Option<&T> {
    let total: f32 = items.iter().map(&weight).sum();
    if total <= 0.0 || total.is_nan() {
        return items.first();
    }
    let mut x = u * total;
    for it in items {
        x -= weight(it);
        if x < 0.0 {
            return Some(it);
        }
    }
    items.last()
}
