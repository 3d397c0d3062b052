//! Cones: a ray with an opening, and what a cone meets (004 §4.5).

use super::*;

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
pub(super) type NodeVisitor<'v> = dyn FnMut(&Page, u32, f32) + 'v;

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
