//! Pull (004 §4.8): every inner node of the resident pages whose light changed (and of
//! their ancestor pages) gets the area-weighted mean of its children's stored light,
//! deepest pages first so page roots are ready for their parents. Evicted pages are
//! skipped, not reloaded: their nodes keep the values of the last pull (the store itself
//! never loses samples). A prototype's pages are pulled per instance that changed them,
//! under that instance's keys, before the scene's tree, whose instance leaves take their
//! prototype root's light as placed by them. There only the nodes above those whose light
//! changed are pulled: an instance far away gets a few samples a pass, and pulling its
//! whole pages cost three quarters of a render of 10,000 instances at `--cone-scale 1`.

use super::{weighted_mean, Keys, Placed, RadianceStore};
use crate::paging::instance::Instance;
use crate::paging::{deepest_first, NodeRef, Page, PageCache, TriW};
use crate::trace::{placed_tri, NO_INSTANCE};
use rayon::prelude::*;
use std::collections::HashMap;

pub fn pull(cache: &PageCache, store: &RadianceStore, keys: Keys) {
    let placed = store.take_placed_dirty();
    let instances: Vec<_> = placed.chunk_by(|a, b| a.0 == b.0).collect();
    instances
        .par_iter()
        .for_each(|changed| pull_placed(cache, store, keys, changed));
    // Each instance's leaf, in the scene's tree, takes its prototype root's new light.
    for changed in &instances {
        if let Some(page) = cache.page_of(changed[0].2 .0) {
            store.mark_dirty(page);
        }
    }
    pull_pages(cache, store, keys, store.take_dirty());
}

/// Pulls, as one instance places them, the nodes above those whose light changed: their
/// ancestors in their own page, and in each page above, the node linking to the page below
/// and its ancestors.
fn pull_placed(
    cache: &PageCache,
    store: &RadianceStore,
    keys: Keys,
    changed: &[(u32, u32, Placed)],
) {
    // The instance, from its leaf (`via`) in the scene's tree; an evicted leaf page is
    // not reloaded, as no page is.
    let via = changed[0].2 .0;
    let leaf = cache.page_of(via).and_then(|p| cache.get_resident(p));
    let Some(by) = leaf.as_ref().and_then(|p| p.instance_of(via)) else {
        return;
    };
    let mut dirty: HashMap<u32, Vec<u32>> = HashMap::new();
    for (_, page, (_, nodes)) in changed {
        let first = cache.entries[*page as usize].first_node;
        let local = nodes.iter().map(|&n| n.saturating_sub(first) as u32);
        dirty.entry(*page).or_default().extend(local);
    }
    let mut below: Vec<u32> = dirty.keys().copied().collect();
    while let Some(p) = below.pop() {
        let e = &cache.entries[p as usize];
        if e.parent_page == canopy_format::NONE {
            continue;
        }
        let nodes = dirty.entry(e.parent_page).or_default();
        if nodes.is_empty() {
            below.push(e.parent_page);
        }
        nodes.push(e.parent_node);
    }
    let pages = dirty.keys().copied().collect();
    for level in deepest_first(&cache.entries, pages) {
        for id in level {
            if let Some(page) = cache.get_resident(id) {
                for i in above(&page, &dirty[&id]) {
                    pull_node(cache, store, keys, &page, Some(by), i);
                }
            }
        }
    }
}

/// The nodes of `page` at or above `nodes` (local indices), deepest first: children come
/// after their parent in a page, so in descending order.
fn above(page: &Page, nodes: &[u32]) -> Vec<usize> {
    let n = page.bvh.len();
    let mut parent = vec![usize::MAX; n];
    for (i, node) in page.bvh.iter().enumerate() {
        if let NodeRef::Inner(l, r) = node.link() {
            for c in [l as usize, r as usize] {
                if c < n {
                    parent[c] = i;
                }
            }
        }
    }
    let mut marked = vec![false; n];
    for &start in nodes {
        let mut i = start as usize;
        while i < n && !marked[i] {
            marked[i] = true;
            i = parent[i];
        }
    }
    (0..n).rev().filter(|&i| marked[i]).collect()
}

/// Pulls `pages` of the scene's tree and their ancestors.
fn pull_pages(cache: &PageCache, store: &RadianceStore, keys: Keys, mut pages: Vec<u32>) {
    // A changed page changes its parent page's cut node: pull the ancestors too.
    let mut seen: std::collections::HashSet<u32> = pages.iter().copied().collect();
    let mut i = 0;
    while i < pages.len() {
        let parent = cache.entries[pages[i] as usize].parent_page;
        if parent != canopy_format::NONE && seen.insert(parent) {
            pages.push(parent);
        }
        i += 1;
    }
    for level in deepest_first(&cache.entries, pages) {
        level.par_iter().for_each(|&id| {
            if let Some(page) = cache.get_resident(id) {
                pull_page(cache, store, keys, &page);
            }
        });
    }
}

/// One part a node's light is the mean of: a triangle of a leaf or a child node.
struct Part {
    /// Stored diffuse light and the samples behind it (the fewest of its cells).
    diffuse: Option<([f32; 3], u32)>,
    caustic: [f32; 3],
    area: f32,
}

/// A leaf's triangle: diffuse, the lit cells' means (of either side) weighted by their
/// samples; caustic, all cells by area, an unlit cell counting as dark, each the sum of
/// what arrived on its two sides.
fn triangle_part(store: &RadianceStore, keys: Keys, leaf: u64, k: u32, t: &TriW) -> Part {
    let sides: Vec<_> = keys
        .cells(t)
        .map(|(cell, area)| {
            let [front, back] = [false, true].map(|b| store.get(keys.tri(leaf, k, b, cell)));
            (front, back, area)
        })
        .collect();
    let lit: Vec<_> = sides
        .iter()
        .flat_map(|(f, b, _)| [f, b])
        .filter_map(|e| e.and_then(|e| e.value()))
        .collect();
    let diffuse = weighted_mean(lit.iter().map(|&(v, c)| (v, c as f32)))
        .zip(lit.iter().map(|&(_, c)| c).min());
    let caustic = weighted_mean(sides.iter().map(|(f, b, area)| {
        let [cf, cb] = [f, b].map(|e| e.map_or([0.0; 3], |e| e.caustic));
        ([0, 1, 2].map(|c| cf[c] + cb[c]), *area)
    }))
    .unwrap_or_default();
    Part {
        diffuse,
        caustic,
        area: super::tri_area(t),
    }
}

/// Pulls the nodes of `page` of the scene's tree, deepest first.
fn pull_page(cache: &PageCache, store: &RadianceStore, keys: Keys, page: &Page) {
    for i in (0..page.bvh.len()).rev() {
        pull_node(cache, store, keys, page, None, i);
    }
}

/// Pulls node `i` of `page`, keyed as instance `by` places it (None: the scene's own
/// tree). Placed triangles are moved
/// into the world, as hits carry them, so their light cells are the ones the hits keyed.
fn pull_node(
    cache: &PageCache,
    store: &RadianceStore,
    keys: Keys,
    page: &Page,
    by: Option<&Instance>,
    i: usize,
) {
    let node_part = |node: u64, area: f32| {
        let e = store.get(keys.node(node));
        Part {
            diffuse: e.and_then(|e| e.value()),
            caustic: e.map_or([0.0; 3], |e| e.caustic),
            area,
        }
    };
    let at = |node: u64| keys.placed(by.map_or(NO_INSTANCE, |p| p.number), node);
    let here = at(page.first_node + i as u64);
    let link = page.bvh[i].link();
    let parts: Vec<Part> = match link {
        // The prototype root's light as this instance placed it (prototypes hold no
        // instances: one level).
        NodeRef::Instance(k) => {
            let Some(placed) = page.instances.get(k as usize).filter(|_| by.is_none()) else {
                return;
            };
            let Some(root) = cache.entries.get(placed.page as usize) else {
                return;
            };
            vec![node_part(
                keys.placed(placed.number, root.first_node),
                page.nodes[i].area,
            )]
        }
        // A leaf none of whose cells holds light has nothing to pull.
        NodeRef::Leaf { .. } if !store.lit(keys.node(here)) => return,
        NodeRef::Leaf { first, count } => (0..count)
            .filter_map(|k| {
                let t = page.tri(first + k)?;
                let t = by.map_or(t, |p| placed_tri(p, &t));
                Some(triangle_part(store, keys, here, k, &t))
            })
            .collect(),
        NodeRef::Inner(l, r) => [l, r]
            .map(|c| node_part(at(page.first_node + c as u64), page.nodes[c as usize].area))
            .into(),
        NodeRef::ChildPage(c) => {
            let Some(child) = cache.get_resident(c) else {
                return;
            };
            let (Some(l), Some(r)) = (child.nodes.first(), child.nodes.get(1)) else {
                return;
            };
            vec![
                node_part(at(child.first_node), l.area),
                node_part(at(child.first_node + 1), r.area),
            ]
        }
    };
    // A leaf takes the mean over its lit triangles; an inner node needs both children.
    let lit = parts.iter().filter(|p| p.diffuse.is_some());
    let leaf = matches!(link, NodeRef::Leaf { .. } | NodeRef::Instance(_));
    let complete = leaf || parts.iter().all(|p| p.diffuse.is_some());
    if let (true, Some(samples)) = (
        complete,
        lit.clone().filter_map(|p| p.diffuse.map(|d| d.1)).min(),
    ) {
        let mean = weighted_mean(lit.filter_map(|p| p.diffuse.map(|d| (d.0, p.area))));
        if let Some(v) = mean {
            store.set_pulled(keys.node(here), v, samples);
        }
    }
    if store.photons() > 0 {
        let c = weighted_mean(parts.iter().map(|p| (p.caustic, p.area))).unwrap_or_default();
        if c.iter().any(|&v| v > 0.0) {
            store.set_caustic(keys.node(here), c);
        }
    }
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;
    use crate::paging::TriW;
    use canopy_format::Archive;
    use std::sync::Arc;

    /// Sum of area·value and of area over the triangles under node `i` of page `pg`, walked
    /// from the tree itself (not the order or dirty flags `pull` uses).
    fn subtree(
        cache: &PageCache,
        value: &dyn Fn(&TriW) -> [f64; 3],
        pg: u32,
        i: u32,
    ) -> ([f64; 3], f64) {
        let page = cache.get(pg);
        let add = |x: ([f64; 3], f64), y: ([f64; 3], f64)| {
            ([0, 1, 2].map(|k| x.0[k] + y.0[k]), x.1 + y.1)
        };
        match page.bvh[i as usize].link() {
            NodeRef::Inner(l, r) => add(subtree(cache, value, pg, l), subtree(cache, value, pg, r)),
            NodeRef::ChildPage(c) => add(subtree(cache, value, c, 0), subtree(cache, value, c, 1)),
            NodeRef::Leaf { first, count } => (first..first + count)
                .filter_map(|k| page.tri(k))
                .fold(([0.0; 3], 0.0), |acc, t| {
                    let area = super::super::tri_area(&t) as f64;
                    add(acc, (value(&t).map(|x| x * area), area))
                }),
            NodeRef::Instance(_) => panic!("the test scene has no instances"),
        }
    }

    /// The bunny converted in `dir`, its camera close by.
    pub(in crate::light_store) fn bunny_archive(dir: &std::path::Path) -> Arc<Archive> {
        let toml = dir.join("s.toml");
        std::fs::write(
            &toml,
            "[[camera]]\nposition = [0.0, 0.1, 0.4]\nlook_at = [0.0, 0.1, 0.0]\n",
        )
        .unwrap();
        let arc = dir.join("b.canopy");
        let bunny = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/bunny.ply");
        let mut o = crate::convert::ConvertOptions::new(vec![bunny], arc.clone());
        o.scene = Some(toml);
        crate::convert::convert(&o).unwrap();
        let archive = Arc::new(Archive::open(&arc).unwrap());
        assert!(
            archive.page_count() as usize > 10,
            "{} pages",
            archive.page_count() as usize
        );
        archive
    }

    /// The renderer's pull on the bunny's pages: with every cell of a triangle holding one
    /// diffuse sample and one caustic deposit of that triangle's own value, each node's
    /// pulled light, diffuse and caustic, must be the area-weighted mean of the values of
    /// the triangles below it — the root's times the total area is the scene's energy.
    #[test]
    fn pull_gives_every_node_the_area_weighted_mean_of_its_triangles() {
        let dir = tempfile::tempdir().unwrap();
        let archive = bunny_archive(dir.path());
        let cache = PageCache::new(Arc::clone(&archive), None, 1).unwrap();
        let value = |t: &TriW| {
            let x =
                ((t.p[0][0] + t.p[1][1] * 7.0 + t.p[2][2] * 13.0) * 97.0).rem_euclid(1.0) as f64;
            [x, 1.0 - x, 0.25 + x * x]
        };
        let keys = Keys::new(&archive.header).unwrap();
        let store = RadianceStore::new(1024, None, archive.page_count() as usize, keys.block());
        store.add_photons(1);
        for pg in 0..archive.page_count() {
            let page = cache.get(pg);
            store.mark_dirty(pg);
            for (i, n) in page.bvh.iter().enumerate() {
                let NodeRef::Leaf { first, count } = n.link() else {
                    continue;
                };
                for k in 0..count {
                    let t = &page.tri(first + k).expect("a leaf's triangle");
                    let v = value(t).map(|x| x as f32);
                    for (cell, _) in keys.cells(t) {
                        let key = keys.tri(page.first_node + i as u64, k, false, cell);
                        store.add(key, v, 1.0);
                        store.add_caustic(key, v);
                    }
                }
            }
        }
        pull(&cache, &store, keys);
        let mut checked = 0;
        for pg in 0..archive.page_count() {
            let page = cache.get(pg);
            for i in 0..page.bvh.len() as u32 {
                let (sum, area) = subtree(&cache, &value, pg, i);
                let want = sum.map(|s| s / area);
                let e = store
                    .get(keys.node(page.first_node + i as u64))
                    .unwrap_or_else(|| panic!("page {pg} node {i}: nothing pulled"));
                let (diffuse, _) = e.value().unwrap();
                for (what, got) in [("diffuse", diffuse), ("caustic", e.caustic)] {
                    for k in 0..3 {
                        assert!(
                            (got[k] as f64 - want[k]).abs() < 1e-4 * want[k].abs().max(0.01),
                            "page {pg} node {i}: {what} pulled {got:?}, area-weighted mean {want:?}"
                        );
                    }
                }
                checked += 1;
            }
        }
        assert_eq!(checked as u64, archive.header.nodes);
    }
}
