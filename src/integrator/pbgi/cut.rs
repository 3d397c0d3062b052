//! The cut (003 §2): far nodes splatted into the micro-buffer, near leaves rasterized
//! and their nearest hit per texel ray shaded, and FPBGI's clusters sharing far splats
//! (003 §3).

use super::bake::Directional;
use super::microbuffer::MicroBuffer;
use super::surface::Surface;
use super::{receiver_clusters, PbgiIntegrator, Pending, Reuse, Scratch, Strata};
use crate::integrator::surface::{hole_number, passes_through};
use crate::integrator::{Counters, PixelSample, Scene};
use crate::paging::{NodeRef, Page, TNode};
use crate::trace::{offset_origin, Hit, Ray, Tracer, Watertight, NO_INSTANCE};
use glam::{Vec3, Vec3A as V};
use std::f32::consts::PI;
use std::sync::atomic::Ordering::Relaxed;
use std::sync::Arc;

/// A node is near (its children are visited) while x is within this many bounding radii.
const NEAR: f32 = 1.5;

/// Whether every member of a cluster (within `radius` of its active receiver) lies
/// outside NEAR bounding radii r of a node at distance d from that receiver: only then
/// may the cluster share the node's splat, so no member inside the node's box does,
/// whatever `--cluster-far` is (003 §3's test R ≤ ε·d alone allows it when ε is large).
fn all_outside(d: f32, radius: f32, r: f32) -> bool {
    d - radius > NEAR * r
}

/// The bounding sphere of a node's decoded box.
fn node_sphere(node: &TNode) -> (V, f32) {
    let (lo, hi) = (V::from(node.lo), V::from(node.hi));
    ((lo + hi) * 0.5, (hi - lo).length() * 0.5)
}

/// A node splatted whole, as seen from the point its cut was walked for.
#[derive(Clone, Copy, Debug)]
struct Far {
    /// Unit world direction to the node's centre, and the distance.
    w: V,
    d: f32,
    omega: f32,
    id: u64,
    sends: Vec3,
}

/// What a cluster's receivers share: far splats and the near nodes to refine.
#[derive(Default)]
pub(super) struct Field {
    far: Vec<Far>,
    near: Vec<(u32, u32)>,
}

/// Which micro-buffer a cut fills: the uniform hemicube (`sc.mb`, texels indexed as
/// cube texels) or WPBGI's adaptive one (`sc.amb`, by leaf), whose leaf under a node
/// sets the node's solid-angle threshold.
#[derive(Clone, Copy, PartialEq)]
pub(super) enum Fill {
    Hemicube,
    Adaptive,
}

impl Scratch {
    /// No ray aimed at or met yet, and no node to visit.
    fn start_cut(&mut self) {
        self.aimed.clear();
        self.aimed.resize(self.rays.len(), false);
        self.nearest.clear();
        self.nearest.resize(self.rays.len(), None);
        self.stack.clear();
    }

    /// Fills texel (or leaf) k whole with a hit's light.
    fn put(&mut self, target: Fill, k: u32, depth: f32, id: u64, l: Vec3, sampled: bool) {
        match target {
            Fill::Hemicube => self.mb.fill(k as usize, depth, id, l, sampled),
            Fill::Adaptive => self.amb.fill(k, depth, id, l),
        }
    }
}

impl PbgiIntegrator {
    /// Fills the micro-buffer `target`: under `--pbgi-gather rays` (the default) every
    /// texel's (or leaf's) ray in `sc.rays` traced exactly, else from the cut.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn fill_texels(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        s: &Surface,
        field: Option<&Field>,
        sc: &mut Scratch,
        strata: Strata,
        target: Fill,
    ) {
        if !self.settings.rays() {
            return self.fill_from_cut(scene, tr, s, field, sc, strata, target);
        }
        self.trace_texels(scene, tr, s, sc, strata, target);
    }

    /// Every ray in `sc.rays` traced exactly, its hit reading the bake.
    fn trace_texels(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        s: &Surface,
        sc: &mut Scratch,
        strata: Strata,
        target: Fill,
    ) {
        for j in 0..sc.rays.len() {
            let (k, w, weight) = sc.rays[j];
            if let Some((t, id, l, sampled)) = self.texel_ray(scene, tr, s, (k, weight), w, strata)
            {
                sc.put(target, k, t, id, l, sampled);
            }
        }
        self.tally
            .traced_texels
            .fetch_add(sc.rays.len() as u64, Relaxed);
    }

    /// Fills the adaptive micro-buffer's new leaves, whose rays are in `sc.rays`, after a
    /// split (000 §3.2): traced, or from the cut: the `nodes` its split leaves recorded
    /// traversed again (splatted onto the new leaves or refined), and the near leaves
    /// rasterized so far tested against the new rays.
    pub(super) fn refill_leaves(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        s: &Surface,
        sc: &mut Scratch,
        strata: Strata,
        nodes: &[u64],
    ) {
        if self.settings.rays() {
            return self.trace_texels(scene, tr, s, sc, strata, Fill::Adaptive);
        }
        sc.start_cut();
        sc.stack
            .extend(nodes.iter().map(|&n| ((n >> 32) as u32, n as u32)));
        let rasterized = sc.near.len();
        self.cut(scene, tr, s, sc, Fill::Adaptive);
        for j in 0..rasterized {
            let (pid, i) = sc.near[j];
            let page = tr.page_handle(pid);
            if let Some(NodeRef::Leaf { first, count }) = page.bvh.get(i as usize).map(TNode::link)
            {
                let leaf = page.first_node + i as u64;
                self.raster_leaf(scene, s, &page, leaf, first..first + count, sc);
            }
        }
        self.shade_nearest(scene, tr, s, sc, strata, Fill::Adaptive);
    }

    /// Fills the micro-buffer from the cut: far nodes splatted, near leaves rasterized and
    /// their nearest hit per texel ray shaded, exact rays where a leaf's cone found nothing.
    #[allow(clippy::too_many_arguments)]
    fn fill_from_cut(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        s: &Surface,
        field: Option<&Field>,
        sc: &mut Scratch,
        strata: Strata,
        target: Fill,
    ) {
        sc.start_cut();
        sc.near.clear();
        match field {
            Some(f) => {
                for far in &f.far {
                    self.splat(s, far, &mut sc.mb);
                }
                sc.stack.extend_from_slice(&f.near);
            }
            None => {
                let root = tr.page_handle(scene.cache.root_page());
                sc.stack
                    .extend((0..root.roots.min(root.bvh.len() as u32)).map(|r| (root.id, r)));
            }
        }
        self.cut(scene, tr, s, sc, target);
        self.shade_nearest(scene, tr, s, sc, strata, target);
    }

    /// Shades each ray's nearest rasterized hit, or traces it exactly where a leaf's cone
    /// held it but no triangle met it.
    fn shade_nearest(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        s: &Surface,
        sc: &mut Scratch,
        strata: Strata,
        target: Fill,
    ) {
        let (mut gaps, mut fragments, mut exact) = (0, 0, 0);
        let mut page: Option<Arc<Page>> = None;
        for j in 0..sc.rays.len() {
            let (k, w, weight) = sc.rays[j];
            match sc.nearest[j] {
                Some(hit) => {
                    let p = match page.take() {
                        Some(p) if p.id == hit.page => p,
                        _ => tr.page_handle(hit.page),
                    };
                    let (sends, sampled) =
                        self.hit_sends(scene, tr, &p, &hit, w, || strata.shading(k));
                    let id = (1 << 62) | (hit.leaf << 3) | hit.slot as u64;
                    let l = Vec3::from(sends * weight);
                    sc.put(target, k, hit.t, id, l, sampled);
                    page = Some(p);
                    fragments += 1;
                    exact += sampled as u64;
                }
                None if sc.aimed[j] => {
                    gaps += 1;
                    if let Some((t, id, l, sampled)) =
                        self.texel_ray(scene, tr, s, (k, weight), w, strata)
                    {
                        sc.put(target, k, t, id, l, sampled);
                    }
                }
                None => {}
            }
        }
        self.tally.gap_rays.fetch_add(gaps, Relaxed);
        self.tally.near_fragments.fetch_add(fragments, Relaxed);
        self.tally.exact_hits.fetch_add(exact, Relaxed);
    }

    /// Walks the hierarchy from the nodes on `sc.stack`: far nodes are splatted, near
    /// leaves rasterized.
    fn cut(&self, scene: &Scene, tr: &mut Tracer, s: &Surface, sc: &mut Scratch, target: Fill) {
        let Some(&(first, _)) = sc.stack.last() else {
            return;
        };
        let mut page = tr.page_handle(first);
        let mut splatted = 0;
        while let Some((pid, i)) = sc.stack.pop() {
            if page.id != pid {
                page = tr.page_handle(pid);
            }
            let Some(node) = page.bvh.get(i as usize) else {
                continue;
            };
            let (c, r) = node_sphere(node);
            let v = c - s.p;
            if v.dot(s.n) < -r {
                continue;
            }
            let texel = match target {
                Fill::Hemicube => self.texels.min_solid_angle,
                // A centre below the horizon is dropped by the splat, as the hemicube's is.
                Fill::Adaptive => sc
                    .amb
                    .solid_angle_toward(s.frame.to_local(v).normalize().into())
                    .unwrap_or(self.texels.min_solid_angle),
            };
            if let Some(far) = self.far(&page, i, c, r, s.p, texel) {
                splatted += 1;
                scene.touched.insert(far.id);
                match target {
                    Fill::Hemicube => self.splat(s, &far, &mut sc.mb),
                    Fill::Adaptive => {
                        let dir = Vec3::from(s.frame.to_local(far.w));
                        let node = (pid as u64) << 32 | i as u64;
                        sc.amb
                            .splat(dir, far.d, far.omega, (far.id, node), far.sends);
                    }
                }
                continue;
            }
            match node.link() {
                NodeRef::Leaf { first, count } => {
                    let leaf = page.first_node + i as u64;
                    self.raster_leaf(scene, s, &page, leaf, first..first + count, sc);
                    // Only the adaptive micro-buffer splits leaves and tests them again.
                    if target == Fill::Adaptive {
                        sc.near.push((pid, i));
                    }
                }
                NodeRef::Inner(l, rr) => sc.stack.extend([(pid, l), (pid, rr)]),
                NodeRef::ChildPage(cp) => sc.stack.extend([(cp, 0), (cp, 1)]),
                // The cut is refused on instanced archives (`Settings::check_archive`).
                NodeRef::Instance(_) => {}
            }
        }
        self.tally.splatted.fetch_add(splatted, Relaxed);
    }

    /// Node i of `page` (bounding sphere c, r) as one splat seen from p, when its sphere
    /// subtends at most `--pbgi-angle` texels of solid angle `texel` (the hemicube's
    /// smallest, or the adaptive leaf under it) and p lies outside NEAR radii.
    fn far(&self, page: &Page, i: u32, c: V, r: f32, p: V, texel: f32) -> Option<Far> {
        let omega_max = self.settings.angle() * texel;
        let node = page.bvh.get(i as usize)?;
        // A leaf within one texel is splatted even when the cut asks for more.
        let limit = if matches!(node.link(), NodeRef::Leaf { .. }) {
            omega_max.max(texel)
        } else {
            omega_max
        };
        let v = c - p;
        let d = v.length();
        if !(d > NEAR * r && PI * r * r <= limit * d * d) {
            return None;
        }
        let shown = page
            .baked
            .nodes
            .get(i as usize)
            .copied()
            .unwrap_or_default();
        // Seen from behind, a node still hides what lies beyond it.
        let (front, mut power) = shown.toward(-v / d);
        if let Some(g) = page.glossy.get(i as usize, Vec3::from(-v / d)) {
            // Haar truncation can ring below zero; no direction sends negative light.
            let w = crate::paging::coefs::weight(&shown);
            power += V::from(g * w).max(V::ZERO);
        }
        let back = shown.toward(v / d).0;
        let area = front.max(back);
        let sends = if area > 0.0 { power / area } else { V::ZERO };
        Some(Far {
            w: v / d,
            d,
            omega: area / (d * d),
            id: page.first_node + i as u64,
            sends: Vec3::from(sends),
        })
    }

    fn splat(&self, s: &Surface, f: &Far, mb: &mut MicroBuffer) {
        let dir = Vec3::from(s.frame.to_local(f.w));
        mb.splat(&self.texels, dir, f.d, f.omega, f.id, f.sends);
    }

    /// A cluster's shared part of the cut (003 §3), walked for its active receiver x_C:
    /// a node is far for the whole cluster when its radius R ≤ ε·d (d from x_C to the
    /// node's centre: sharing the splat errs by about R/d in direction); far nodes are
    /// splatted from x_C when small enough, else visited further; near nodes are left for
    /// each receiver to refine.
    /// A node is dropped only when it lies below every member's tangent plane, so a
    /// cluster of one makes exactly PBGI's cut.
    fn field(&self, scene: &Scene, tr: &mut Tracer, members: &[&Surface], xc: &Surface) -> Field {
        let radius = members
            .iter()
            .map(|m| (m.p - xc.p).length())
            .fold(0.0, f32::max);
        let mut field = Field::default();
        let mut stack: Vec<(u32, u32)> = Vec::new();
        let mut page = tr.page_handle(scene.cache.root_page());
        stack.extend((0..page.roots.min(page.bvh.len() as u32)).map(|r| (page.id, r)));
        while let Some((pid, i)) = stack.pop() {
            if page.id != pid {
                page = tr.page_handle(pid);
            }
            let Some(node) = page.bvh.get(i as usize) else {
                continue;
            };
            let (c, r) = node_sphere(node);
            if members.iter().all(|m| (c - m.p).dot(m.n) < -r) {
                continue;
            }
            let d = (c - xc.p).length();
            if radius > self.settings.far * d {
                field.near.push((pid, i));
                continue;
            }
            if let Some(far) = self
                .far(&page, i, c, r, xc.p, self.texels.min_solid_angle)
                .filter(|_| all_outside(d, radius, r))
            {
                scene.touched.insert(far.id);
                field.far.push(far);
                continue;
            }
            match node.link() {
                NodeRef::Leaf { .. } => field.near.push((pid, i)),
                NodeRef::Inner(l, rr) => stack.extend([(pid, l), (pid, rr)]),
                NodeRef::ChildPage(cp) => stack.extend([(cp, 0), (cp, 1)]),
                NodeRef::Instance(_) => {}
            }
        }
        self.tally
            .splatted
            .fetch_add(field.far.len() as u64, Relaxed);
        field
    }

    /// FPBGI over one batch: receivers clustered, one field per cluster, each receiver's
    /// gather starting from its cluster's field.
    pub(super) fn sample_clustered(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        pxs: &[PixelSample],
        c: &mut Counters,
    ) -> Vec<V> {
        let firsts: Vec<(V, Option<Pending>)> = pxs
            .iter()
            .map(|px| self.first_hit(scene, tr, px, c))
            .collect();
        let mut out: Vec<V> = firsts.iter().map(|f| f.0).collect();
        let mut at = Vec::new();
        for (i, q) in firsts.iter().enumerate() {
            let Some(q) = &q.1 else {
                continue;
            };
            match self.reuse(tr, q) {
                Reuse::Gather(strata) => at.push((i, strata)),
                r => out[i] += q.beta * self.gather(scene, tr, q, None, Some(r)),
            }
        }
        let pending: Vec<&Pending> = at
            .iter()
            .filter_map(|&(i, _)| firsts[i].1.as_ref())
            .collect();
        let p: Vec<V> = pending.iter().map(|q| q.s.p).collect();
        let n: Vec<V> = pending.iter().map(|q| q.s.n).collect();
        for cl in receiver_clusters::kmeans(&p, &n, self.settings.clusters) {
            let members: Vec<&Surface> = cl.members.iter().map(|&m| &pending[m].s).collect();
            let field = self.field(scene, tr, &members, &pending[cl.active].s);
            for &m in &cl.members {
                let (q, (i, strata)) = (pending[m], at[m]);
                let gathered = self.gather(scene, tr, q, Some(&field), Some(Reuse::Gather(strata)));
                out[i] += q.beta * gathered;
            }
        }
        self.tally.clusters.fetch_add(p.len() as u64, Relaxed);
        out.into_iter()
            .map(|l| {
                c.paths += 1;
                c.finite(l)
            })
            .collect()
    }

    /// A leaf too near or too wide to splat, rasterized: each of x's texel rays that
    /// meets one of its triangles keeps the nearest hit, an opaque fragment once shaded
    /// (`hit_light`).
    fn raster_leaf(
        &self,
        scene: &Scene,
        s: &Surface,
        page: &Page,
        leaf: u64,
        tris: std::ops::Range<u32>,
        sc: &mut Scratch,
    ) {
        let Some(node) = page.bvh.get((leaf - page.first_node) as usize) else {
            return;
        };
        let (c, r) = node_sphere(node);
        let v = c - s.p;
        let d = v.length();
        // Rays outside the cone around the leaf's sphere miss it.
        let cos_cone = if d > r {
            (1.0 - (r / d).powi(2)).sqrt()
        } else {
            -1.0
        };
        let axis = v / d.max(f32::MIN_POSITIVE);
        sc.in_cone.clear();
        for (j, &(_, w, _)) in sc.rays.iter().enumerate() {
            if w.dot(axis) >= cos_cone {
                sc.in_cone.push(j as u32);
            }
        }
        if sc.in_cone.is_empty() {
            return;
        }
        // Rays leave from just above x, as exact rays do, so x's neighbours on its own
        // surface (coplanar up to rounding) do not block its horizon.
        let o = offset_origin(s.p, s.err, s.ng, s.n);
        let alpha = scene.textures.has_alpha();
        let mut met = false;
        for t in tris.clone() {
            let Some(tri) = page.tri(t) else {
                continue;
            };
            let p = tri.p.map(V::from);
            let ng = (p[1] - p[0]).cross(p[2] - p[0]);
            // A triangle in x's own plane is seen edge-on: it neither sends nor hides.
            if ng.dot(s.p - p[0]).abs() <= 1e-6 * ng.length() * (r + d) {
                continue;
            }
            let slot = t - tris.start;
            for &j in &sc.in_cone {
                sc.aimed[j as usize] = true;
            }
            for &j in &sc.in_cone {
                let j = j as usize;
                let w = sc.rays[j].1;
                let ray = Ray {
                    o,
                    d: w,
                    t_max: f32::INFINITY,
                };
                let Some((depth, b)) = Watertight::new(&ray).hit(&tri, f32::INFINITY) else {
                    continue;
                };
                met = true;
                if sc.nearest[j].is_some_and(|h| h.t <= depth) {
                    continue;
                }
                let hit = Hit {
                    t: depth,
                    b,
                    tri,
                    page: page.id,
                    leaf,
                    slot,
                    curvature: 0.0,
                    instance: NO_INSTANCE,
                    instance_leaf: 0,
                    transform_err: V::ZERO,
                    corners: page.corners(t),
                };
                // An alpha hole hides nothing: the ray goes on to what lies behind it.
                if alpha && passes_through(scene.opacity_at(&hit), hole_number(w), 0) {
                    continue;
                }
                sc.nearest[j] = Some(hit);
            }
        }
        if met {
            scene.touched.insert(leaf);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_rng::TestRng;

    /// A cluster with a member inside a node's box never shares that node's splat.
    #[test]
    fn a_receiver_inside_a_nodes_box_keeps_the_node_near() {
        let mut rng = TestRng::new(11);
        let mut v = || V::new(rng.f32(), rng.f32(), rng.f32());
        for _ in 0..2000 {
            let (lo, size) = (v() * 4.0 - 2.0, v() + V::splat(0.01));
            let (c, r) = ((lo + lo + size) * 0.5, size.length() * 0.5);
            let inside = lo + size * v();
            let xc = v() * 20.0 - 10.0;
            let radius = (inside - xc).length() * (1.0 + v().x);
            assert!(!all_outside((c - xc).length(), radius, r));
        }
    }
}
