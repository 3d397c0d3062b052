//! Rays against the paged tree: closest hit and any hit.
//!
//! Triangles are intersected with the watertight test of Woop, Benthin and Wald (JCGT 2013)
//! as pbrt-v4 writes it, so rays through shared edges and vertices never slip between
//! triangles. Box tests scale `t_max` by 1 + 2γ₃ so rounding never culls a box the ray
//! touches (pbrt-v4 `Bounds3::IntersectP`). Spawned rays are offset from the surface by the
//! floating-point error bound of the hit point (pbrt-v4 §6.8), which grows with the point's
//! magnitude instead of being a fixed epsilon.

mod instance;
mod triangle;

pub use triangle::Watertight;

use crate::paging::instance::Instance;
use crate::paging::wide::{self, Tri4, Wide};
use crate::paging::{NodeRef, Page, PageCache, TNode, TriW};
use canopy_format::Node;
use glam::{Vec3A as V, Vec4};
use std::sync::Arc;

/// Deepest tree the renderer accepts (the traversal stack holds at most depth + 1 entries).
pub const MAX_DEPTH: usize = 250;

/// γ_n = nε/(1−nε) with ε the f32 unit roundoff (pbrt-v4 §6.8.1).
pub const fn gamma(n: i32) -> f32 {
    let e = f32::EPSILON * 0.5;
    (n as f32 * e) / (1.0 - n as f32 * e)
}

#[derive(Clone, Copy, Debug)]
pub struct Ray {
    pub o: V,
    pub d: V,
    pub t_max: f32,
}

/// What a closest-hit query returns: enough to shade without returning to the page.
#[derive(Clone, Copy, Debug)]
pub struct Hit {
    pub t: f32,
    /// Barycentrics of vertices 0, 1, 2.
    pub b: [f32; 3],
    pub tri: TriW,
    pub page: u32,
    /// Global node number of the leaf.
    pub leaf: u64,
    /// Position of the triangle within its leaf (0..MAX_LEAF_TRIS).
    pub slot: u32,
    /// The leaf's mean curvature (004 eq. 4.23), signed about the triangles' winding normal.
    pub curvature: f32,
    /// The instance whose prototype holds the triangle (`NO_INSTANCE`: none); `tri` is in
    /// world space either way.
    pub instance: u32,
    /// That instance's leaf in the scene's tree (global node number), for node statistics.
    pub instance_leaf: u64,
    /// What transforming `tri` to world space adds to the hit point's error bound.
    pub transform_err: V,
    /// Texture coordinates of the triangle's vertices (zero without TEXCOORDS).
    pub uv: [[f32; 2]; 3],
}

/// A prototype's triangle as `inst` places it in the world, bit for bit as a hit on it
/// carries it.
pub fn placed_tri(inst: &Instance, t: &TriW) -> TriW {
    TriW {
        p: instance::to_world(inst, t.p).0,
        ..*t
    }
}

/// `Hit::instance` of a triangle outside every instance.
pub const NO_INSTANCE: u32 = u32::MAX;

/// A triangle a ray met, as the walk finds it: a `Hit` is made only of the nearest.
#[derive(Clone, Copy, Debug)]
struct TriRef {
    page: u32,
    /// The leaf, a node of the page, and its first triangle.
    leaf: u32,
    first: u32,
    /// The triangle in the page, and its place in the page's blocks (block × 4 + lane).
    index: u32,
    block_slot: u32,
    t: f32,
    b: [f32; 3],
    instance: u32,
    /// The instance leaf the walk came through (global node number; 0 outside instances).
    via: u64,
}

impl Hit {
    /// The hit `r` on its page `page`.
    fn new(page: &Page, r: &TriRef) -> Hit {
        let leaf = r.leaf;
        Hit {
            t: r.t,
            b: r.b,
            tri: page.tri4[r.block_slot as usize / 4].tri(r.block_slot as usize % 4),
            page: page.id,
            leaf: page.first_node + leaf as u64,
            slot: r.index - r.first,
            curvature: page
                .nodes
                .get(leaf as usize)
                .map_or(0.0, |n| canopy_format::codec::f16_decode(n.curvature)),
            instance: r.instance,
            instance_leaf: r.via,
            transform_err: V::ZERO,
            uv: page.uvs.get(r.index as usize).copied().unwrap_or_default(),
        }
    }

    /// The hit of a prototype's triangle moved into world space by its instance: the
    /// vertices transformed (so normals and winding follow, mirrors included), the
    /// curvature scaled by |det|^−⅓ as the converter scales a cluster's.
    fn placed(mut self, placed_by: &Instance) -> Hit {
        let (p, err) = instance::to_world(placed_by, self.tri.p);
        self.tri.p = p;
        self.transform_err = err;
        self.curvature *= placed_by.curvature_scale;
        self
    }

    /// Hit point from the barycentrics (more accurate than o + t·d) and its error bound.
    pub fn point(&self) -> (V, V) {
        let p = self.tri.p.map(V::from);
        let q = p[0] * self.b[0] + p[1] * self.b[1] + p[2] * self.b[2];
        let abs = (p[0] * self.b[0]).abs() + (p[1] * self.b[1]).abs() + (p[2] * self.b[2]).abs();
        (q, abs * gamma(7) + self.transform_err)
    }

    /// Unnormalized geometric normal (e1 × e2, the winding's front side).
    pub fn ng(&self) -> V {
        let p = self.tri.p.map(V::from);
        (p[1] - p[0]).cross(p[2] - p[0])
    }
}

/// Moves `p` off the surface with normal `n` (unit) by its error bound `err`, to the side
/// of `w` (pbrt-v4 `OffsetRayOrigin`), then one ulp further out.
pub fn offset_origin(p: V, err: V, n: V, w: V) -> V {
    let d = n.abs().dot(err);
    let mut off = n * d;
    if w.dot(n) < 0.0 {
        off = -off;
    }
    let po = p + off;
    let step = |v: f32, o: f32| {
        if o > 0.0 {
            v.next_up()
        } else if o < 0.0 {
            v.next_down()
        } else {
            v
        }
    };
    V::new(step(po.x, off.x), step(po.y, off.y), step(po.z, off.z))
}

/// Per-ray constants of the box test.
struct Prep {
    o: V,
    inv: V,
}

impl Prep {
    /// Entry distance if the ray meets the box before `t_max`.
    #[inline]
    fn box_hit(&self, n: &TNode, t_max: f32) -> Option<f32> {
        let t0 = (V::from(n.lo) - self.o) * self.inv;
        let t1 = (V::from(n.hi) - self.o) * self.inv;
        // min/max drop the NaN of 0·∞ (origin on a slab with a zero direction component).
        let near = t0.min(t1);
        let far = t0.max(t1) * (1.0 + 2.0 * gamma(3));
        let enter = near.max_element().max(0.0);
        let exit = far.min_element().min(t_max);
        (enter <= exit).then_some(enter)
    }
}

/// The box test of `Prep::box_hit` on a wide node's four lanes at once, and the
/// watertight triangle test on four triangles at once, each with the same arithmetic per
/// lane as one at a time (no fused multiply-adds, the same order of operations), so a
/// lane's result is the scalar test's bit for bit.
struct Prep4 {
    /// The box test one box at a time, for the binary tree.
    one: Prep,
    o: [Vec4; 3],
    inv: [Vec4; 3],
    /// The ray's axes permuted so that its largest direction component is the third.
    k: [usize; 3],
    /// The shear of the watertight test (pbrt-v4 `Triangle::Intersect`).
    s: [Vec4; 3],
}

/// What the watertight test leaves for its comparison with `t_max`, per lane.
struct Tri4Hits {
    ts: Vec4,
    det: Vec4,
    t: Vec4,
    b: [Vec4; 3],
}

impl Prep4 {
    fn new(r: &Ray) -> Prep4 {
        // The one-triangle test's shear, four lanes wide.
        let w = Watertight::new(r);
        let inv = V::ONE / r.d;
        Prep4 {
            one: Prep { o: r.o, inv },
            o: [0, 1, 2].map(|k| Vec4::splat(r.o[k])),
            inv: [0, 1, 2].map(|k| Vec4::splat(inv[k])),
            k: w.k,
            s: w.s.map(Vec4::splat),
        }
    }

    /// Entry distances of the four boxes, and a bit per lane whose box the ray meets
    /// before `t_max` (empty lanes' bits are meaningless).
    #[inline]
    fn hit(&self, w: &Wide, t_max: f32) -> (Vec4, u32) {
        let grow = Vec4::splat(1.0 + 2.0 * gamma(3));
        let axis = |k: usize| {
            let t0 = (w.lo[k] - self.o[k]) * self.inv[k];
            let t1 = (w.hi[k] - self.o[k]) * self.inv[k];
            (t0.min(t1), t0.max(t1) * grow)
        };
        let ((nx, fx), (ny, fy), (nz, fz)) = (axis(0), axis(1), axis(2));
        let enter = nx.max(ny).max(nz).max(Vec4::ZERO);
        let exit = fx.min(fy).min(fz).min(Vec4::splat(t_max));
        (enter, enter.cmple(exit).bitmask())
    }

    /// The lanes of `w` at whose boxes, entered at `enter`, `cone` would stop: the binary
    /// walk's rule per lane, with the same arithmetic.
    #[inline]
    fn stops(&self, w: &Wide, enter: Vec4, cone: &Cone, end: Option<V>) -> u32 {
        let side = (w.hi[0] - w.lo[0])
            .max(w.hi[1] - w.lo[1])
            .max(w.hi[2] - w.lo[2]);
        let radius = (Vec4::splat(cone.r0) + Vec4::splat(cone.tan_a) * enter).abs();
        let wide = (radius * Vec4::splat(cone.scale)).cmpgt(side).bitmask();
        let inside = |p: [Vec4; 3]| {
            (0..3).fold(15, |m, k| {
                m & p[k].cmpge(w.lo[k]).bitmask() & p[k].cmple(w.hi[k]).bitmask()
            })
        };
        let ends = end.map_or(0, |e| inside([0, 1, 2].map(|k| Vec4::splat(e[k]))));
        wide & !inside(self.o) & !ends
    }

    /// Woop–Benthin–Wald watertight ray–triangle test (pbrt-v4 `Triangle::Intersect`) on
    /// the lanes of `tri` set in `mask`, all but the comparison with `t_max`: the lanes
    /// that pass, and what `leaf` needs to finish.
    #[inline]
    fn tri_hits(&self, tri: &Tri4, mask: u32) -> (u32, Tri4Hits) {
        let [kx, ky, kz] = self.k;
        let [sx, sy, sz] = self.s;
        let [ox, oy, oz] = [self.o[kx], self.o[ky], self.o[kz]];
        let tr = |v: &[Vec4; 3]| {
            let z = v[kz] - oz;
            ([v[kx] - ox + sx * z, v[ky] - oy + sy * z], z)
        };
        let (xy0, z0) = tr(&tri.v[0]);
        let (xy1, z1) = tr(&tri.v[1]);
        let (xy2, z2) = tr(&tri.v[2]);
        let xy = [xy0, xy1, xy2];
        let edge = |a: [Vec4; 2], b: [Vec4; 2]| a[0] * b[1] - a[1] * b[0];
        let mut e = [edge(xy1, xy2), edge(xy2, xy0), edge(xy0, xy1)];
        let zero = |e: Vec4| e.cmpeq(Vec4::ZERO).bitmask();
        let mut exact = (zero(e[0]) | zero(e[1]) | zero(e[2])) & mask;
        while exact != 0 {
            // Exactly on an edge in f32: decide in f64 so neighbours agree.
            let lane = exact.trailing_zeros() as usize;
            exact &= exact - 1;
            for (i, (a, b)) in [(1, 2), (2, 0), (0, 1)].into_iter().enumerate() {
                if e[i][lane] == 0.0 {
                    let (a, b) = (xy[a].map(|c| c[lane] as f64), xy[b].map(|c| c[lane] as f64));
                    e[i][lane] = (a[0] * b[1] - a[1] * b[0]) as f32;
                }
            }
        }
        let [e0, e1, e2] = e;
        let neg = |v: Vec4| v.cmplt(Vec4::ZERO).bitmask();
        let pos = |v: Vec4| v.cmpgt(Vec4::ZERO).bitmask();
        let mut fail = (neg(e0) | neg(e1) | neg(e2)) & (pos(e0) | pos(e1) | pos(e2));
        let det = e0 + e1 + e2;
        fail |= zero(det);
        let z = [z0 * sz, z1 * sz, z2 * sz];
        let ts = e0 * z[0] + e1 * z[1] + e2 * z[2];
        fail |= neg(det) & ts.cmpge(Vec4::ZERO).bitmask();
        fail |= pos(det) & ts.cmple(Vec4::ZERO).bitmask();
        let inv = Vec4::ONE / det;
        let t = ts * inv;
        // pbrt-v4: reject hits closer than the error bound of t (behind the origin).
        let max3 = |a: Vec4, b: Vec4, c: Vec4| a.abs().max(b.abs()).max(c.abs());
        let max_z = max3(z[0], z[1], z[2]);
        let delta_z = Vec4::splat(gamma(3)) * max_z;
        let max_x = max3(xy0[0], xy1[0], xy2[0]);
        let max_y = max3(xy0[1], xy1[1], xy2[1]);
        let delta_x = Vec4::splat(gamma(5)) * (max_x + max_z);
        let delta_y = Vec4::splat(gamma(5)) * (max_y + max_z);
        let delta_e = Vec4::splat(2.0)
            * (Vec4::splat(gamma(2)) * max_x * max_y + delta_y * max_x + delta_x * max_y);
        let max_e = max3(e0, e1, e2);
        let delta_t = Vec4::splat(3.0)
            * (Vec4::splat(gamma(3)) * max_e * max_z + delta_e * max_z + delta_z * max_e)
            * inv.abs();
        fail |= t.cmple(delta_t).bitmask();
        let b = [e0 * inv, e1 * inv, e2 * inv];
        (mask & !fail, Tri4Hits { ts, det, t, b })
    }

    /// Tests the triangles of the leaf whose first block is `block` four at a time,
    /// passing each hit to `on_tri` in the triangles' order and closing `t_max` to it, as
    /// one triangle at a time would; with `any`, stops at the first. Whether any was met.
    #[inline]
    fn leaf(
        &self,
        page: &Page,
        block: u32,
        t_max: &mut f32,
        on_tri: &mut impl FnMut(TriRef),
        any: bool,
    ) -> bool {
        let Some(head) = page.tri4.get(block as usize) else {
            return false;
        };
        let (leaf, first, count) = (head.leaf, head.first, head.count);
        let mut met = false;
        for j in 0..count.div_ceil(4) {
            let Some(tri) = page.tri4.get((block + j) as usize) else {
                break;
            };
            let (mut pass, h) = self.tri_hits(tri, (1 << (count - 4 * j).min(4)) - 1);
            while pass != 0 {
                let lane = pass.trailing_zeros() as usize;
                pass &= pass - 1;
                let (ts, det) = (h.ts[lane], h.det[lane]);
                if (det < 0.0 && ts < *t_max * det) || (det > 0.0 && ts > *t_max * det) {
                    continue;
                }
                on_tri(TriRef {
                    page: page.id,
                    leaf,
                    first,
                    index: first + 4 * j + lane as u32,
                    block_slot: (block + j) * 4 + lane as u32,
                    t: h.t[lane],
                    b: h.b.map(|b| b[lane]),
                    instance: NO_INSTANCE,
                    via: 0,
                });
                met = true;
                if any {
                    return true;
                }
                *t_max = h.t[lane];
            }
        }
        met
    }
}

/// A cone (frustum) along a ray: radius r(t) = |r0 + tan α · t| (004 eq. 4.17). The LOD
/// rule compares r(t)·`scale` (the user's `--cone-scale`; 0: never stop early, exact rays).
#[derive(Clone, Copy, Debug)]
pub struct Cone {
    pub r0: f32,
    pub tan_a: f32,
    pub scale: f32,
    /// tan α′ of the cones after diffuse and glossy bounces (004 eq. 4.20's d).
    pub spread: f32,
}

impl Cone {
    /// No opening and no level of detail: an exact ray.
    pub const EXACT: Cone = Cone {
        r0: 0.0,
        tan_a: 0.0,
        scale: 0.0,
        spread: 0.0,
    };

    #[inline]
    pub fn radius(&self, t: f32) -> f32 {
        (self.r0 + self.tan_a * t).abs()
    }
}

/// Called with (page, page-local node, entry distance) when a cone stops at a node.
type NodeVisitor<'v> = dyn FnMut(&Page, u32, f32) + 'v;

/// What a cone meets.
#[derive(Clone, Copy, Debug)]
pub enum ConeHit {
    Tri(Hit),
    /// A node accepted as a whole, at its box entry distance; carries the node's record so
    /// shading needs no page lookup.
    Node {
        page: u32,
        /// Global node number.
        node: u64,
        t: f32,
        record: Node,
    },
}

/// The wide node `w`'s children whose lanes are set in `mask`, in the order a walk visits
/// them: the first is returned, the rest pushed on `stack` (as children of page `pid`,
/// or as the root of the child page they link to) so that they pop in order.
///
/// A closest-hit walk goes nearest first (equal distances: the higher lane first). An
/// any-hit walk goes first to the boxes the ray enters from outside, then to those it
/// starts inside (entry distance 0), each group from the highest lane down: a ray leaving
/// a surface rarely hits the surface's own neighbourhood, which nearest first would open
/// to the leaves first. On sponza's bounce rays this order was 3.0× faster than the
/// lanes' own order, itself 2.4× faster than nearest first.
#[inline(always)]
fn visit_order(
    w: &Wide,
    enter: Vec4,
    mask: u32,
    any: bool,
    pid: u32,
    stack: &mut Stack,
) -> Option<(u32, f32)> {
    let entry = |c: u32, t: f32| match c & wide::KIND {
        wide::PAGE => (c & !wide::KIND, wide::WIDE, t),
        _ => (pid, c, t),
    };
    if mask & mask.wrapping_sub(1) == 0 {
        let lane = mask.trailing_zeros() as usize;
        return (mask != 0).then(|| (w.child[lane], enter[lane]));
    }
    let t = enter.to_array();
    let mut hits = [(0.0f32, 0u32); 4];
    let mut n = 0;
    let outside = match any {
        true => enter.cmpgt(Vec4::ZERO).bitmask() & mask,
        false => mask,
    };
    for mut group in [outside, mask & !outside] {
        while group != 0 {
            let lane = 31 - group.leading_zeros() as usize;
            group &= !(1 << lane);
            hits[n] = (t[lane], w.child[lane]);
            n += 1;
        }
    }
    if !any {
        for i in 1..n {
            let mut j = i;
            while j > 0 && hits[j].0 < hits[j - 1].0 {
                hits.swap(j, j - 1);
                j -= 1;
            }
        }
    }
    for &(t, c) in hits[1..n].iter().rev() {
        stack.push(entry(c, t));
    }
    Some((hits[0].1, hits[0].0))
}

/// The walk's stack: (page, entry as `Wide::child` codes it, box entry distance).
type Stack = Vec<(u32, u32, f32)>;

/// One exact ray's walk: what stays the same through the world tree and the instances'
/// prototypes.
struct Walk<'w> {
    cache: &'w PageCache,
    ray: &'w Ray,
    any: bool,
}

impl Walk<'_> {
    /// Walks the four-wide tree under page `start`'s roots with `self.ray`, front to back,
    /// going on to the first child to visit without a trip through `stack`. With
    /// `INSTANCED`, an instance leaf is walked with `inner` as its stack; without (inside a
    /// prototype, where the converter writes no instance, or in an archive without
    /// instances) it is skipped. Kept apart from the cone's walk:
    /// with the cone's binary steps in, even unused, the trace bench's exact rays were
    /// 5–16% slower.
    #[inline(always)]
    fn exact<const INSTANCED: bool>(
        &self,
        held: &mut Held,
        stack: &mut Stack,
        mut inner: Option<&mut Stack>,
        start: u32,
        on_tri: &mut impl FnMut(TriRef),
    ) -> bool {
        let (cache, any) = (self.cache, self.any);
        let lanes = Prep4::new(self.ray);
        let mut t_max = self.ray.t_max;
        stack.clear();
        let mut page: &Page = held.get(cache, start);
        // The child of `page` to walk next, as `Wide::child` codes it.
        let mut next = (!page.wide.is_empty()).then_some(wide::WIDE);
        let mut found = false;
        'walk: loop {
            let r = match next.take() {
                Some(r) => r,
                None => loop {
                    let Some((pid, r, tn)) = stack.pop() else {
                        break 'walk;
                    };
                    if tn <= t_max {
                        if page.id != pid {
                            page = held.get(cache, pid);
                        }
                        break r;
                    }
                },
            };
            let index = r & !wide::KIND;
            match r & wide::KIND {
                wide::LEAF if INSTANCED && index & wide::INSTANCE != 0 => {
                    let pid = page.id;
                    if self.enter(held, inner.as_deref_mut(), pid, index, &mut t_max, on_tri) {
                        found = true;
                        if any {
                            break 'walk;
                        }
                    }
                    page = held.get(cache, pid);
                }
                wide::LEAF => {
                    if lanes.leaf(page, index, &mut t_max, on_tri, any) {
                        found = true;
                        if any {
                            break 'walk;
                        }
                    }
                }
                wide::PAGE => {
                    page = held.get(cache, index);
                    if page.roots >= 2 && !page.wide.is_empty() {
                        next = Some(wide::WIDE);
                    }
                }
                _ => {
                    let Some(w) = page.wide.get(index as usize) else {
                        continue;
                    };
                    let (enter, mask) = lanes.hit(w, t_max);
                    next =
                        visit_order(w, enter, mask & w.used, any, page.id, stack).map(|(c, _)| c);
                }
            }
        }
        found
    }

    /// The walk of `exact` into the instance leaf `index` of page `pid`, out of its loop.
    #[inline(never)]
    fn enter(
        &self,
        held: &mut Held,
        inner: Option<&mut Stack>,
        pid: u32,
        index: u32,
        t_max: &mut f32,
        on_tri: &mut dyn FnMut(TriRef),
    ) -> bool {
        let Some(inner) = inner else {
            return false;
        };
        match instance_at(held.get(self.cache, pid), index) {
            Some(inst) => self.instance(held, inner, inst, t_max, on_tri),
            None => false,
        }
    }

    /// Walks the prototype of instance `inst` (reached through the leaf `via`) with the
    /// ray moved into its object space (`Instance::ray_to_object`): hits go to `on_tri` at
    /// their world distance, tagged with the instance, and close `t_max`.
    #[inline(never)]
    fn instance(
        &self,
        held: &mut Held,
        stack: &mut Stack,
        (inst, via): (u32, u64),
        t_max: &mut f32,
        on_tri: &mut dyn FnMut(TriRef),
    ) -> bool {
        let Some(placed) = self.cache.instances.get(inst as usize) else {
            return false;
        };
        let (o, d, dt) = instance::ray_to_object(placed, self.ray.o, self.ray.d);
        let local = Ray {
            o,
            d,
            t_max: *t_max - dt,
        };
        let walk = Walk {
            cache: self.cache,
            ray: &local,
            any: self.any,
        };
        let mut nearest = None;
        let mut tagged = |mut r: TriRef| {
            r.t += dt;
            r.instance = inst;
            r.via = via;
            nearest = Some(r.t);
            on_tri(r)
        };
        let found = walk.exact::<false>(held, stack, None, placed.page, &mut tagged);
        if let Some(t) = nearest {
            *t_max = t_max.min(t);
        }
        found
    }
}

/// The instance of binary node `node` of `page` and the node's global number, if it is an
/// instance leaf.
#[inline]
fn instance_at(page: &Page, node: u32) -> Option<(u32, u64)> {
    match page.bvh.get((node & !wide::INSTANCE) as usize)?.link() {
        NodeRef::Instance(i) => Some((i, page.first_node + (node & !wide::INSTANCE) as u64)),
        _ => None,
    }
}

/// A stack entry whose kind is `EMPTY` (which no lane pushes) is a binary node of its page.
const BINARY: u32 = wide::EMPTY;

/// Pushes the binary nodes `kids` of `page` that the ray meets before `t_max`, the nearer
/// last (popped first).
#[inline]
fn push_pair(prep: &Prep, page: &Page, [l, r]: [u32; 2], t_max: f32, stack: &mut Stack) {
    let (Some(ln), Some(rn)) = (page.bvh.get(l as usize), page.bvh.get(r as usize)) else {
        return;
    };
    let id = page.id;
    match (prep.box_hit(ln, t_max), prep.box_hit(rn, t_max)) {
        (Some(a), Some(b)) => {
            let (near, far) = if a <= b {
                ((l, a), (r, b))
            } else {
                ((r, b), (l, a))
            };
            stack.push((id, BINARY | far.0, far.1));
            stack.push((id, BINARY | near.0, near.1));
        }
        (Some(a), None) => stack.push((id, BINARY | l, a)),
        (None, Some(b)) => stack.push((id, BINARY | r, b)),
        (None, None) => {}
    }
}

fn inside(p: V, n: &TNode) -> bool {
    p.cmpge(V::from(n.lo)).all() && p.cmple(V::from(n.hi)).all()
}

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
            instanced: !cache.instances.is_empty(),
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
        match self.cache.instances.get(r.instance as usize) {
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
