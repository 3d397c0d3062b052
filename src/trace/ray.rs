//! Rays and what they hit: the hit record, the triangle a walk found, spawned rays'
//! offsets (pbrt-v4 §6.8).

use super::*;

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
    /// What the triangle's vertices carry for shading (texture coordinates, colours).
    pub corners: Corners,
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
pub(super) struct TriRef {
    pub(super) page: u32,
    /// The leaf, a node of the page, and its first triangle.
    pub(super) leaf: u32,
    pub(super) first: u32,
    /// The triangle in the page, and its place in the page's blocks (block × 4 + lane).
    pub(super) index: u32,
    pub(super) block_slot: u32,
    pub(super) t: f32,
    pub(super) b: [f32; 3],
    pub(super) instance: u32,
    /// The instance leaf the walk came through (global node number; 0 outside instances).
    pub(super) via: u64,
}

impl Hit {
    /// The hit `r` on its page `page`.
    pub(super) fn new(page: &Page, r: &TriRef) -> Hit {
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
            corners: page.corners(r.index),
        }
    }

    /// The hit of a prototype's triangle moved into world space by its instance: the
    /// vertices transformed (so normals and winding follow, mirrors included), the
    /// curvature scaled by |det|^−⅓ as the converter scales a cluster's.
    pub(super) fn placed(mut self, placed_by: &Instance) -> Hit {
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
