//! Cone optics: where a cone goes after a smooth bounce (004 §4.5.3–4.5.4).

use crate::material::Frame;
use crate::trace::Cone;
use glam::Vec3A as V;

/// Jitters a direction uniformly inside the cone of half-angle atan(tan α) (eq. 4.14–4.16)
/// and moves the origin so the cone's virtual apex stays put (Fig. 7).
pub fn jitter(o: V, d: V, cone: &Cone, u: [f32; 2]) -> (V, V) {
    if cone.tan_a <= 0.0 {
        return (o, d);
    }
    let cos_a = 1.0 / (1.0 + cone.tan_a * cone.tan_a).sqrt();
    let z = (1.0 - cos_a) * u[0] + cos_a;
    let phi = 2.0 * std::f32::consts::PI * u[1];
    let s = (1.0 - z * z).max(0.0).sqrt();
    let f = Frame::new(d);
    let nd = f
        .to_world(V::new(s * phi.cos(), s * phi.sin(), z))
        .normalize();
    // The apex sits r0 / tan α behind the origin; keep it and start on the old origin plane.
    let apex = o - d * (cone.r0 / cone.tan_a);
    let t = (o - apex).dot(d) / nd.dot(d).max(1e-6);
    (apex + nd * t, nd)
}

/// Opening of a cone after a smooth bounce at distance `t` off a surface of mean
/// curvature `kappa` (signed about the normal on the outgoing side, positive for convex);
/// `cos_o`, `cos_i`: cosines of the outgoing and new directions with that normal; `eta`:
/// relative index across the surface.
///
/// Deviation: eq. 4.21–4.22 scale tan α by (1 ∓ κ·b·cos θ), which mixes a curvature
/// (1/length) into a dimensionless factor, so b would depend on the scene's units. This
/// uses the ray-differential terms the thesis cites instead (Igehy 1999, as in pbrt-v3
/// §10.1.3): the footprint r sees normals turn by κ·r, which adds 2κr·cos θ to a reflected
/// opening and μκr to a refracted one (μ = cos θo/η − cos θi), whose own spread shrinks by
/// η. The new cone starts at the surface with r0 = 0: a frustum starting as wide as the
/// footprint would stop at the mirror's own neighbouring nodes. A focusing surface (negative
/// result) gives an exact ray until the next bounce, which only makes the level finer.
pub fn bent_tan(cone: &Cone, t: f32, kappa: f32, cos_o: f32, cos_i: f32, eta: f32) -> f32 {
    let r = cone.radius(t);
    let tan = if cos_i > 0.0 {
        cone.tan_a + 2.0 * kappa * r * cos_o
    } else {
        let mu = cos_o / eta - cos_i.abs();
        cone.tan_a / eta + mu * kappa * r
    };
    tan.clamp(0.0, cone.spread)
}
