//! A bounding volume hierarchy over the lights that chooses one per shading point in
//! proportion to a conservative bound on what it can send there (pbrt-v4 §12.6.3,
//! `BVHLightSampler`): near lights, lights facing the point and lights above its horizon
//! are chosen more often, and a one-sided lamp triangle facing away is never chosen. A
//! light's probability is recomputed by walking from its leaf to the root, as MIS needs
//! when a BSDF sample hits an emitter.

use glam::{Quat, Vec3, Vec3A as V};
use std::f32::consts::PI;

/// What bounds a set of lights' emission (pbrt-v4 `LightBounds`).
#[derive(Clone, Copy, Debug)]
pub struct LightBounds {
    pub lo: V,
    pub hi: V,
    /// Axis of the cone that holds the emitters' normals (or a spot's axis).
    pub w: V,
    /// Cosine of that cone's half-angle θ_o.
    pub cos_o: f32,
    /// Cosine of the angle θ_e beyond θ_o up to which light leaves (π/2 for a lamp).
    pub cos_e: f32,
    /// Power as the chooser weighs it; 0 for an empty set.
    pub phi: f32,
    pub two_sided: bool,
}

const EMPTY: LightBounds = LightBounds {
    lo: V::splat(f32::INFINITY),
    hi: V::splat(f32::NEG_INFINITY),
    w: V::Z,
    cos_o: 1.0,
    cos_e: 1.0,
    phi: 0.0,
    two_sided: false,
};

fn safe_sqrt(x: f32) -> f32 {
    x.max(0.0).sqrt()
}

/// (cos, sin) of θ_a − θ_b, clamped at 0 when θ_a < θ_b.
fn sub_clamped((cos_a, sin_a): (f32, f32), (cos_b, sin_b): (f32, f32)) -> (f32, f32) {
    if cos_a > cos_b {
        (1.0, 0.0)
    } else {
        (cos_a * cos_b + sin_a * sin_b, sin_a * cos_b - cos_a * sin_b)
    }
}

/// Smallest cone holding two cones of directions (pbrt-v4 `Union(DirectionCone, …)`).
fn cone_union((wa, cos_a): (V, f32), (wb, cos_b): (V, f32)) -> (V, f32) {
    let (ta, tb) = (cos_a.clamp(-1.0, 1.0).acos(), cos_b.clamp(-1.0, 1.0).acos());
    let td = wa.angle_between(wb);
    if (td + tb).min(PI) <= ta {
        return (wa, cos_a);
    }
    if (td + ta).min(PI) <= tb {
        return (wb, cos_b);
    }
    let to = 0.5 * (ta + td + tb);
    let axis = wa.cross(wb);
    if to >= PI || axis.length_squared() == 0.0 {
        return (wa, -1.0);
    }
    let rot = Quat::from_axis_angle(Vec3::from(axis.normalize()), to - ta);
    (rot.mul_vec3a(wa).normalize(), to.cos())
}

impl LightBounds {
    pub fn union(self, b: LightBounds) -> LightBounds {
        if self.phi <= 0.0 {
            return b;
        }
        if b.phi <= 0.0 {
            return self;
        }
        let (w, cos_o) = cone_union((self.w, self.cos_o), (b.w, b.cos_o));
        LightBounds {
            lo: self.lo.min(b.lo),
            hi: self.hi.max(b.hi),
            w,
            cos_o,
            cos_e: self.cos_e.min(b.cos_e),
            phi: self.phi + b.phi,
            two_sided: self.two_sided || b.two_sided,
        }
    }

    fn centroid(&self) -> V {
        0.5 * (self.lo + self.hi)
    }

    /// The surface-area-orientation heuristic's cost along `axis` (pbrt-v4
    /// `EvaluateCost`): power × the solid angle of the emission cone × box area, with a
    /// penalty for thin boxes cut across their long side.
    fn cost(&self, extent: V, axis: usize) -> f32 {
        if self.phi <= 0.0 {
            return 0.0;
        }
        let theta_o = self.cos_o.clamp(-1.0, 1.0).acos();
        let theta_e = self.cos_e.clamp(-1.0, 1.0).acos();
        let theta_w = (theta_o + theta_e).min(PI);
        let sin_o = safe_sqrt(1.0 - self.cos_o * self.cos_o);
        let m_omega = 2.0 * PI * (1.0 - self.cos_o)
            + PI / 2.0
                * (2.0 * theta_w * sin_o - (theta_o - 2.0 * theta_w).cos() - 2.0 * theta_o * sin_o
                    + self.cos_o);
        let d = (self.hi - self.lo).max(V::ZERO);
        let area = 2.0 * (d.x * d.y + d.y * d.z + d.z * d.x);
        let kr = extent.max_element() / extent[axis].max(f32::MIN_POSITIVE);
        self.phi * m_omega * kr * area
    }
}

const NONE: u32 = u32::MAX;
const INFINITE: u32 = u32::MAX - 1;
const BUCKETS: usize = 12;
/// Past this depth splits are at the median, which bounds the depth for any input.
const SAH_DEPTH: u32 = 64;
const ONE_MINUS_EPS: f32 = 1.0 - f32::EPSILON / 2.0;

/// What `importance` reads of a node's bounds, precomputed (the tree walk evaluates it
/// twice per level for every light sample).
#[derive(Clone, Copy)]
struct Bound {
    center: V,
    /// Squared radius of the box's bounding sphere.
    r2: f32,
    w: V,
    cos_o: f32,
    sin_o: f32,
    cos_e: f32,
    phi: f32,
    two_sided: bool,
}

impl Bound {
    fn new(b: &LightBounds) -> Bound {
        Bound {
            center: b.centroid(),
            r2: 0.25 * (b.hi - b.lo).length_squared(),
            w: b.w,
            cos_o: b.cos_o,
            sin_o: safe_sqrt(1.0 - b.cos_o * b.cos_o),
            cos_e: b.cos_e,
            phi: b.phi,
            two_sided: b.two_sided,
        }
    }

    /// Upper bound on what these lights send to `p` on a surface with normal `n` (zero:
    /// any orientation), up to a common factor (pbrt-v4 `LightBounds::Importance`).
    /// Deviation: pbrt clamps d² at half the box's diagonal, which mixes units; this clamps
    /// it at the squared half-diagonal, the distance below which a bound is meaningless.
    #[inline]
    fn importance(&self, p: V, n: V) -> f32 {
        let d = p - self.center;
        let dist2 = d.length_squared();
        let d2 = dist2.max(self.r2).max(f32::MIN_POSITIVE);
        let wi = if dist2 > 0.0 {
            d / dist2.sqrt()
        } else {
            V::ZERO
        };
        let mut cos_w = self.w.dot(wi);
        if self.two_sided {
            cos_w = cos_w.abs();
        }
        let sin_w = safe_sqrt(1.0 - cos_w * cos_w);
        // Directions the box's bounding sphere subtends from p (all of them from inside).
        let b = if dist2 <= self.r2 {
            (-1.0, 0.0)
        } else {
            let sin2 = self.r2 / dist2;
            (safe_sqrt(1.0 - sin2), sin2.sqrt())
        };
        // The smallest angle between an emitter normal and the direction to p.
        let x = sub_clamped((cos_w, sin_w), (self.cos_o, self.sin_o));
        let (cos_p, _) = sub_clamped(x, b);
        if cos_p <= self.cos_e {
            return 0.0;
        }
        let mut importance = self.phi * cos_p / d2;
        if n != V::ZERO {
            let cos_i = wi.dot(n).abs();
            let (cos_pi, _) = sub_clamped((cos_i, safe_sqrt(1.0 - cos_i * cos_i)), b);
            importance *= cos_pi;
        }
        if importance.is_finite() {
            importance.max(0.0)
        } else {
            0.0
        }
    }
}

struct TreeNode {
    b: Bound,
    parent: u32,
    /// A leaf's light, or an inner node's second child (the first is the next node).
    index: u32,
    leaf: bool,
}

pub struct LightTree {
    nodes: Vec<TreeNode>,
    /// Each light's leaf, `INFINITE` for lights chosen apart from the tree, `NONE` for
    /// lights never chosen.
    leaf_of: Vec<u32>,
    /// Lights without a position to bound (directional), chosen uniformly.
    infinite: Vec<u32>,
}

impl LightTree {
    /// `bounded`: (light, bounds) for lights with a position; `infinite`: the others.
    /// Lights are numbered below `count`.
    pub fn new(count: usize, bounded: Vec<(u32, LightBounds)>, infinite: Vec<u32>) -> LightTree {
        let mut tree = LightTree {
            nodes: Vec::new(),
            leaf_of: vec![NONE; count],
            infinite,
        };
        for &i in &tree.infinite {
            tree.leaf_of[i as usize] = INFINITE;
        }
        let mut items: Vec<_> = bounded.into_iter().filter(|(_, b)| b.phi > 0.0).collect();
        if !items.is_empty() {
            tree.build(&mut items, NONE, 0);
        }
        tree
    }

    fn build(&mut self, items: &mut [(u32, LightBounds)], parent: u32, depth: u32) -> u32 {
        let at = self.nodes.len() as u32;
        let b = items.iter().fold(EMPTY, |acc, (_, b)| acc.union(*b));
        if let [(light, _)] = items {
            self.leaf_of[*light as usize] = at;
            self.nodes.push(TreeNode {
                b: Bound::new(&b),
                parent,
                index: *light,
                leaf: true,
            });
            return at;
        }
        self.nodes.push(TreeNode {
            b: Bound::new(&b),
            parent,
            index: NONE,
            leaf: false,
        });
        let mid = split(items, &b, depth);
        let (left, right) = items.split_at_mut(mid);
        self.build(left, at, depth + 1);
        let second = self.build(right, at, depth + 1);
        self.nodes[at as usize].index = second;
        at
    }

    fn p_infinite(&self) -> f32 {
        let trees = usize::from(!self.nodes.is_empty());
        self.infinite.len() as f32 / (self.infinite.len() + trees) as f32
    }

    /// Chooses a light for `p` with surface normal `n` (zero: any) from one uniform;
    /// returns the light and its probability, or None if no light can reach `p`.
    pub fn sample(&self, p: V, n: V, u: f32) -> Option<(usize, f32)> {
        let p_inf = self.p_infinite();
        if u < p_inf {
            let k = self.infinite.len();
            let i = ((u / p_inf * k as f32) as usize).min(k - 1);
            return Some((self.infinite[i] as usize, p_inf / k as f32));
        }
        let root = self.nodes.first()?;
        if root.leaf && root.b.importance(p, n) <= 0.0 {
            return None;
        }
        let mut u = ((u - p_inf) / (1.0 - p_inf)).min(ONE_MINUS_EPS);
        let mut pmf = 1.0 - p_inf;
        let mut at = 0usize;
        loop {
            let node = &self.nodes[at];
            if node.leaf {
                return Some((node.index as usize, pmf));
            }
            let (l, r) = (at + 1, node.index as usize);
            let il = self.nodes[l].b.importance(p, n);
            let ir = self.nodes[r].b.importance(p, n);
            let sum = il + ir;
            if sum <= 0.0 {
                return None;
            }
            let pl = il / sum;
            if u < pl {
                u = (u / pl).min(ONE_MINUS_EPS);
                pmf *= pl;
                at = l;
            } else {
                u = ((u - pl) / (1.0 - pl)).min(ONE_MINUS_EPS);
                pmf *= ir / sum;
                at = r;
            }
        }
    }

    /// The probability that `sample` at `p`, `n` returns `light`.
    pub fn pmf(&self, p: V, n: V, light: usize) -> f32 {
        let Some(&leaf) = self.leaf_of.get(light) else {
            return 0.0;
        };
        let p_inf = self.p_infinite();
        match leaf {
            NONE => return 0.0,
            INFINITE => return p_inf / self.infinite.len() as f32,
            _ => {}
        }
        let mut at = leaf as usize;
        if at == 0 {
            let reach = self.nodes[0].b.importance(p, n) > 0.0;
            return if reach { 1.0 - p_inf } else { 0.0 };
        }
        let mut pmf = 1.0 - p_inf;
        while at != 0 {
            let parent = self.nodes[at].parent as usize;
            let sibling = if at == parent + 1 {
                self.nodes[parent].index as usize
            } else {
                parent + 1
            };
            let (a, s) = (
                self.nodes[at].b.importance(p, n),
                self.nodes[sibling].b.importance(p, n),
            );
            if a <= 0.0 {
                return 0.0;
            }
            pmf *= a / (a + s);
            at = parent;
        }
        pmf
    }
}

/// Where to cut `items` (reordered): the lowest-cost of 12 buckets on each axis of the
/// centroids' box, or the median past `SAH_DEPTH` or when no cut separates anything.
fn split(items: &mut [(u32, LightBounds)], b: &LightBounds, depth: u32) -> usize {
    let (clo, chi) = items.iter().fold(
        (V::splat(f32::INFINITY), V::splat(f32::NEG_INFINITY)),
        |(lo, hi), (_, x)| (lo.min(x.centroid()), hi.max(x.centroid())),
    );
    let ext = chi - clo;
    let bucket = |x: &LightBounds, axis: usize| {
        let t = (x.centroid()[axis] - clo[axis]) / ext[axis];
        ((t * BUCKETS as f32) as usize).min(BUCKETS - 1)
    };
    let extent = (b.hi - b.lo).max(V::ZERO);
    let mut best: Option<(f32, usize, usize)> = None;
    for axis in (0..3).filter(|&a| ext[a] > 0.0 && depth < SAH_DEPTH) {
        let mut buckets = [EMPTY; BUCKETS];
        for (_, x) in items.iter() {
            let k = bucket(x, axis);
            buckets[k] = buckets[k].union(*x);
        }
        for cut in 0..BUCKETS - 1 {
            let below = buckets[..=cut].iter().fold(EMPTY, |a, x| a.union(*x));
            let above = buckets[cut + 1..].iter().fold(EMPTY, |a, x| a.union(*x));
            let cost = below.cost(extent, axis) + above.cost(extent, axis);
            if below.phi > 0.0 && above.phi > 0.0 && best.is_none_or(|(c, ..)| cost < c) {
                best = Some((cost, axis, cut));
            }
        }
    }
    if let Some((_, axis, cut)) = best {
        let mut mid = 0;
        for j in 0..items.len() {
            if bucket(&items[j].1, axis) <= cut {
                items.swap(mid, j);
                mid += 1;
            }
        }
        if mid > 0 && mid < items.len() {
            return mid;
        }
    }
    let axis = ext.max_position();
    let mid = items.len() / 2;
    items.select_nth_unstable_by(mid, |a, b| {
        a.1.centroid()[axis].total_cmp(&b.1.centroid()[axis])
    });
    mid
}
