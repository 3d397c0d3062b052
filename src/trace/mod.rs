//! Rays against the paged tree: closest hit and any hit.
//!
//! Triangles are intersected with the watertight test of Woop, Benthin and Wald (JCGT 2013)
//! as pbrt-v4 writes it, so rays through shared edges and vertices never slip between
//! triangles. Box tests scale `t_max` by 1 + 2γ₃ so rounding never culls a box the ray
//! touches (pbrt-v4 `Bounds3::IntersectP`). Spawned rays are offset from the surface by the
//! floating-point error bound of the hit point (pbrt-v4 §6.8), which grows with the point's
//! magnitude instead of being a fixed epsilon.

mod cone;
mod instance;
mod prep;
mod ray;
mod triangle;
mod walk;

use cone::NodeVisitor;
pub use cone::{Cone, ConeHit};
use prep::{Prep, Prep4};
use ray::TriRef;
pub use ray::{gamma, offset_origin, placed_tri, Hit, Ray, MAX_DEPTH, NO_INSTANCE};
use walk::{inside, push_pair, visit_order, Stack, Walk, BINARY};

pub use triangle::Watertight;

use crate::paging::instance::Instance;
use crate::paging::wide::{self, Tri4, Wide};
use crate::paging::{Corners, NodeRef, Page, PageCache, TNode, TriW};
use canopy_format::Node;
use glam::{Vec3A as V, Vec4};
use std::sync::Arc;

/// Page handles a worker thread keeps between rays: looking a page up here costs no shared
/// atomic write, unlike the cache's lock and `Arc` count. Handles are dropped whenever
/// the cache has evicted anything since they were taken (its eviction epoch moved), so
/// evicted pages are freed by the thread's next ray.
struct Held {
    /// Direct-mapped by page number (`id % HELD`).
    slots: Vec<Option<(u32, Arc<Page>)>>,
    epoch: u64,
    lookups: u64,
}

/// Page handles a thread holds at most (a power of two).
const HELD: usize = 256;

impl Held {
    /// Drops every handle if the cache evicted anything since they were taken.
    fn check_epoch(&mut self, cache: &PageCache) {
        let e = cache.epoch();
        if e != self.epoch {
            self.slots.iter_mut().for_each(|h| *h = None);
            self.epoch = e;
        }
    }

    /// Page `id`, loaded if this thread does not hold it.
    #[inline(always)]
    fn get(&mut self, cache: &PageCache, id: u32) -> &Arc<Page> {
        self.lookups += 1;
        let slot = &mut self.slots[id as usize % HELD];
        if !matches!(slot, Some((p, _)) if *p == id) {
            *slot = Some((id, cache.get(id)));
        }
        &slot.as_ref().expect("held page").1
    }
}

/// Traces rays for one worker thread, holding the pages it walks.
pub struct Tracer<'a> {
    pub cache: &'a PageCache,
    held: Held,
    stack: Stack,
    /// The stack of walks inside an instance.
    inner: Stack,
    /// Whether the archive has instances (walks without them skip the instance step).
    instanced: bool,
    pub rays: u64,
}

impl<'a> Tracer<'a> {
    pub fn new(cache: &'a PageCache) -> Tracer<'a> {
        Tracer {
            cache,
            held: Held {
                slots: vec![None; HELD],
                epoch: cache.epoch(),
                lookups: 0,
            },
            stack: Vec::with_capacity(64),
            inner: Vec::with_capacity(64),
            instanced: cache.archive.header.features & canopy_format::Features::INSTANCES != 0,
            rays: 0,
        }
    }

    /// Page lookups this tracer served from its own handles or the cache.
    pub fn page_lookups(&self) -> u64 {
        self.held.lookups
    }

    /// Walks the paged tree front to back with a cone: `on_tri` gets each triangle the ray
    /// meets (closing `t_max` to its distance), `on_node` each node the cone stops at; with
    /// `any`, the first of either ends the walk.
    ///
    /// Cones walk the four-wide tree, as exact rays do (`walk_exact`). A cone stops at a
    /// binary node it cannot resolve (004 eq. 4.12), and the wide tree skips binary levels,
    /// so where a cone might stop at one of a wide node's lanes, or at a node it skips, the
    /// walk goes on from the binary node the lanes descend from, down the binary tree,
    /// exactly as a binary walk would. Where no lane stops, no
    /// skipped node would have: a skipped node's box holds its lanes' boxes, so the cone
    /// enters it no later, and (its radius growing along the ray) no wider, than it enters
    /// a lane, while the node is no smaller. A cone whose radius does not grow walks the
    /// binary tree throughout. With `INSTANCED`, a cone that does not stop at an instance
    /// leaf walks its prototype as an exact ray (`Walk::enter`): cones stop at an instance
    /// as a whole or not at all.
    #[inline]
    fn walk<const INSTANCED: bool>(
        &mut self,
        ray: &Ray,
        mut on_tri: impl FnMut(TriRef),
        any: bool,
        (cone, on_node): (&Cone, &mut NodeVisitor),
    ) -> bool {
        self.rays += 1;
        let lanes = Prep4::new(ray);
        let prep = &lanes.one;
        let lod = cone.scale > 0.0;
        let grows = cone.r0 >= 0.0 && cone.tan_a >= 0.0;
        // A node holding the far end of a bounded ray (a light) is never an occluder.
        let end = ray.t_max.is_finite().then(|| ray.o + ray.d * ray.t_max);
        let stops = |n: &TNode, t: f32| {
            let side = (V::from(n.hi) - V::from(n.lo)).max_element();
            cone.radius(t) * cone.scale > side
                && !inside(ray.o, n)
                && !end.is_some_and(|e| inside(e, n))
        };
        let mut t_max = ray.t_max;
        let mut stack = std::mem::take(&mut self.stack);
        stack.clear();
        let cache = self.cache;
        let held = &mut self.held;
        let inner = &mut self.inner;
        held.check_epoch(cache);
        let mut page: &Page = held.get(cache, cache.root_page());
        // The entry of `page` to walk next, as `Wide::child` codes it, and its distance.
        let mut next = (!page.wide.is_empty()).then_some((wide::WIDE, 0.0));
        let mut found = false;
        'walk: loop {
            let (r, tn) = match next.take() {
                Some(e) => e,
                None => loop {
                    let Some((pid, r, tn)) = stack.pop() else {
                        break 'walk;
                    };
                    if tn <= t_max {
                        if page.id != pid {
                            page = held.get(cache, pid);
                        }
                        break (r, tn);
                    }
                },
            };
            let index = r & !wide::KIND;
            match r & wide::KIND {
                wide::LEAF if INSTANCED && index & wide::INSTANCE != 0 => {
                    let pid = page.id;
                    let exact = Walk { cache, ray, any };
                    if exact.enter(held, Some(inner), pid, index, &mut t_max, &mut on_tri) {
                        found = true;
                        if any {
                            break 'walk;
                        }
                    }
                    page = held.get(cache, pid);
                }
                wide::LEAF => {
                    if lanes.leaf(page, index, &mut t_max, &mut on_tri, any) {
                        found = true;
                        if any {
                            break 'walk;
                        }
                    }
                }
                wide::PAGE => {
                    page = held.get(cache, index);
                    if page.roots >= 2 && !page.wide.is_empty() {
                        next = Some((wide::WIDE, tn));
                    }
                }
                BINARY => {
                    let Some(node) = page.bvh.get(index as usize) else {
                        continue;
                    };
                    if lod && stops(node, tn) {
                        on_node(page, index, tn);
                        found = true;
                        if any {
                            break 'walk;
                        }
                        t_max = tn;
                        continue;
                    }
                    match node.link() {
                        NodeRef::Leaf { .. } => next = Some((wide::LEAF | node.tri4(), tn)),
                        NodeRef::Inner(l, r) => push_pair(prep, page, [l, r], t_max, &mut stack),
                        NodeRef::ChildPage(child) => next = Some((wide::PAGE | child, tn)),
                        // Without `INSTANCED` skipped, as `lanes.leaf` skips a lane's.
                        NodeRef::Instance(_) => {
                            next = Some((wide::LEAF | wide::INSTANCE | index, tn));
                        }
                    }
                }
                _ => {
                    let Some(w) = page.wide.get(index as usize) else {
                        continue;
                    };
                    let (enter, mask) = lanes.hit(w, t_max);
                    let mask = mask & w.used;
                    let binary = lod
                        && (!grows
                            || lanes.stops(w, enter, cone, end) & mask != 0
                            || w.skipped.iter().any(|&k| match k {
                                wide::NO_NODE => false,
                                wide::MANY => true,
                                k => page.bvh.get(k as usize).is_some_and(|n| {
                                    prep.box_hit(n, t_max).is_some_and(|t| stops(n, t))
                                }),
                            }));
                    if binary {
                        match w.node {
                            wide::ROOTS => {
                                for root in 0..page.roots.min(page.bvh.len() as u32) {
                                    if let Some(t) = prep.box_hit(&page.bvh[root as usize], t_max) {
                                        stack.push((page.id, BINARY | root, t));
                                    }
                                }
                            }
                            k => {
                                if let Some(NodeRef::Inner(l, r)) =
                                    page.bvh.get(k as usize).map(TNode::link)
                                {
                                    push_pair(prep, page, [l, r], t_max, &mut stack);
                                }
                            }
                        }
                        continue;
                    }
                    next = visit_order(w, enter, mask, any, page.id, &mut stack);
                }
            }
        }
        self.stack = stack;
        found
    }

    /// Walks the paged four-wide tree front to back (exact rays): `on_tri` gets each
    /// triangle the ray meets (closing `t_max` to its distance); with `any`, the first
    /// hit ends the walk.
    #[inline]
    fn walk_exact<const INSTANCED: bool>(
        &mut self,
        ray: &Ray,
        mut on_tri: impl FnMut(TriRef),
        any: bool,
    ) -> bool {
        self.rays += 1;
        let Tracer {
            cache,
            held,
            stack,
            inner,
            ..
        } = self;
        held.check_epoch(cache);
        let walk = Walk { cache, ray, any };
        let inner = INSTANCED.then_some(inner);
        walk.exact::<INSTANCED>(held, stack, inner, cache.root_page(), &mut on_tri)
    }

    /// `walk_exact` in an archive with instances, out of line: with both walks in line,
    /// sponza's any-hit rays (no instances) were 12% slower.
    #[inline(never)]
    fn walk_instanced(&mut self, ray: &Ray, on_tri: impl FnMut(TriRef), any: bool) -> bool {
        self.walk_exact::<true>(ray, on_tri, any)
    }

    /// The `Hit` of a triangle a walk found, in world space.
    fn hit(&mut self, r: &TriRef) -> Hit {
        let hit = Hit::new(self.held.get(self.cache, r.page), r);
        if r.instance == NO_INSTANCE {
            return hit;
        }
        let leaf = self.cache.page_of(r.via);
        match leaf.and_then(|p| self.held.get(self.cache, p).instance_of(r.via)) {
            Some(instance) => hit.placed(instance),
            None => hit,
        }
    }

    /// A handle on page `id` for walks of the tree other than rays' (PBGI's cut).
    pub fn page_handle(&mut self, id: u32) -> Arc<Page> {
        self.held.check_epoch(self.cache);
        Arc::clone(self.held.get(self.cache, id))
    }

    /// Nearest intersection along the ray, if any, before `ray.t_max`.
    pub fn closest_hit(&mut self, ray: &Ray) -> Option<Hit> {
        let mut best: Option<TriRef> = None;
        match self.instanced {
            false => self.walk_exact::<false>(ray, |r| best = Some(r), false),
            true => self.walk_instanced(ray, |r| best = Some(r), false),
        };
        best.map(|r| self.hit(&r))
    }

    /// Whether anything blocks the ray before `ray.t_max`.
    pub fn occluded(&mut self, ray: &Ray) -> bool {
        match self.instanced {
            false => self.walk_exact::<false>(ray, |_| {}, true),
            true => self.walk_instanced(ray, |_| {}, true),
        }
    }

    /// Whether a shadow cone meets anything before `ray.t_max`: like `occluded`, but a node
    /// the cone cannot resolve counts as an occluder (004 §4.6.2 casts light samples as
    /// cones too). `ray.d` must be unit length.
    pub fn cone_occluded(&mut self, ray: &Ray, cone: &Cone) -> bool {
        if cone.scale <= 0.0 {
            return self.occluded(ray);
        }
        let mut ignore = |_: &Page, _, _| {};
        match self.instanced {
            false => self.walk::<false>(ray, |_| {}, true, (cone, &mut ignore)),
            true => self.walk::<true>(ray, |_| {}, true, (cone, &mut ignore)),
        }
    }

    /// Nearest hit of a cone: a leaf triangle, or the first node whose box the cone's
    /// radius outgrows (004 §4.5.1); `ray.d` must be unit length.
    pub fn cone_hit(&mut self, ray: &Ray, cone: &Cone) -> Option<ConeHit> {
        if cone.scale <= 0.0 {
            return self.closest_hit(ray).map(ConeHit::Tri);
        }
        let mut tri_best: Option<TriRef> = None;
        let mut node_best: Option<ConeHit> = None;
        let mut on_node = |page: &Page, ni: u32, t: f32| {
            node_best = page.nodes.get(ni as usize).map(|record| ConeHit::Node {
                page: page.id,
                node: page.first_node + ni as u64,
                t,
                record: *record,
            })
        };
        let on_tri = |r| tri_best = Some(r);
        match self.instanced {
            false => self.walk::<false>(ray, on_tri, false, (cone, &mut on_node)),
            true => self.walk::<true>(ray, on_tri, false, (cone, &mut on_node)),
        };
        // Both callbacks close t_max, so whichever came last is the nearest.
        match (tri_best, node_best) {
            (Some(r), Some(ConeHit::Node { t, .. })) if r.t <= t => {
                Some(ConeHit::Tri(self.hit(&r)))
            }
            (_, Some(n)) => Some(n),
            (r, None) => r.map(|r| ConeHit::Tri(self.hit(&r))),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_rng::TestRng;

    /// Four-lane results of `tri` (lanes 0..4) closed against `t_max` as `Prep4::leaf`
    /// does, each lane on its own.
    fn lanes(p: &Prep4, tris: &[TriW; 4], t_max: f32) -> [Option<(f32, [f32; 3])>; 4] {
        let (pass, h) = p.tri_hits(&Tri4::new(tris), 15);
        std::array::from_fn(|lane| {
            let (ts, det) = (h.ts[lane], h.det[lane]);
            let far = (det < 0.0 && ts < t_max * det) || (det > 0.0 && ts > t_max * det);
            (pass & 1 << lane != 0 && !far).then(|| (h.t[lane], h.b.map(|b| b[lane])))
        })
    }

    #[test]
    fn four_lanes_match_the_one_triangle_test_bit_for_bit() {
        let mut rng = TestRng::new(15);
        let bits = |h: Option<(f32, [f32; 3])>| h.map(|(t, b)| (t.to_bits(), b.map(f32::to_bits)));
        let mut hits = 0;
        for i in 0..20_000 {
            // Rays through a shared vertex, along shared edges, axis-aligned and scaled far
            // from the origin, against triangles that share those vertices and edges.
            let scale = [1e-3, 1.0, 1e4][i % 3];
            let q = [rng.v(scale), rng.v(scale), rng.v(scale), rng.v(scale)];
            let target = match i % 4 {
                0 => q[0],
                1 => q[0].lerp(q[1], rng.f32()),
                _ => q[0] * 0.3 + q[1] * 0.3 + q[2] * 0.4,
            };
            let o = rng.v(2.0 * scale);
            let mut d = target - o;
            if i % 5 == 0 {
                d = V::new(d.x, 0.0, if i % 2 == 0 { 0.0 } else { d.z });
            }
            if d == V::ZERO {
                continue;
            }
            let ray = Ray {
                o,
                d,
                t_max: f32::INFINITY,
            };
            let p = Prep4::new(&ray);
            let tri = |a: usize, b: usize, c: usize| TriW {
                p: [q[a], q[b], q[c]].map(|v| v.to_array()),
                material: 0,
            };
            let tris = [tri(0, 1, 2), tri(1, 0, 3), tri(0, 2, 3), tri(2, 2, 3)];
            let t_max = [f32::INFINITY, 1.0, 0.5][i % 3];
            let four = lanes(&p, &tris, t_max);
            for (lane, t) in tris.iter().enumerate() {
                let one = Watertight::new(&ray).hit(t, t_max);
                hits += one.is_some() as u32;
                assert_eq!(bits(four[lane]), bits(one), "ray {i}, lane {lane}");
            }
        }
        assert!(
            hits > 5_000,
            "only {hits} hits: the rays miss too often to test much"
        );
    }
}
