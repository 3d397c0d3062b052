//! A ray prepared for the walk: its inverse direction for box tests, and four lanes of
//! the watertight triangle test.

use super::*;

/// Per-ray constants of the box test.
pub(super) struct Prep {
    pub(super) o: V,
    pub(super) inv: V,
}

impl Prep {
    /// Entry distance if the ray meets the box before `t_max`.
    #[inline]
    pub(super) fn box_hit(&self, n: &TNode, t_max: f32) -> Option<f32> {
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
pub(super) struct Prep4 {
    /// The box test one box at a time, for the binary tree.
    pub(super) one: Prep,
    pub(super) o: [Vec4; 3],
    pub(super) inv: [Vec4; 3],
    /// The ray's axes permuted so that its largest direction component is the third.
    pub(super) k: [usize; 3],
    /// The shear of the watertight test (pbrt-v4 `Triangle::Intersect`).
    pub(super) s: [Vec4; 3],
}

/// What the watertight test leaves for its comparison with `t_max`, per lane.
pub(super) struct Tri4Hits {
    pub(super) ts: Vec4,
    pub(super) det: Vec4,
    pub(super) t: Vec4,
    pub(super) b: [Vec4; 3],
}

impl Prep4 {
    pub(super) fn new(r: &Ray) -> Prep4 {
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
    pub(super) fn hit(&self, w: &Wide, t_max: f32) -> (Vec4, u32) {
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
    pub(super) fn stops(&self, w: &Wide, enter: Vec4, cone: &Cone, end: Option<V>) -> u32 {
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
    pub(super) fn tri_hits(&self, tri: &Tri4, mask: u32) -> (u32, Tri4Hits) {
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
    pub(super) fn leaf(
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
