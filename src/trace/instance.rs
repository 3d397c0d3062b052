//! Rays into instances and hits out of them, with the pbrt-v4 error bounds of applying a
//! transform (pbrt-v4 §6.8.4, `Transform` of a `Point3fi` and of a ray).

use super::gamma;
use crate::paging::instance::{Instance, Rows};
use glam::Vec3A as V;

/// `m` applied to point `p`, and the bound γ₃(|m₀ₓx| + |m₀ᵧy| + |m₀₂z| + |t|) per row of
/// its rounding error (pbrt-v4 `Transform::operator()(Point3fi)` for an exact point).
fn point(m: &Rows, p: V) -> (V, V) {
    let row = |r: &[f32; 4]| {
        let v = r[0] * p.x + r[1] * p.y + r[2] * p.z + r[3];
        let e = (r[0] * p.x).abs() + (r[1] * p.y).abs() + (r[2] * p.z).abs() + r[3].abs();
        (v, e * gamma(3))
    };
    let [(x, ex), (y, ey), (z, ez)] = m.each_ref().map(row);
    (V::new(x, y, z), V::new(ex, ey, ez))
}

fn vector(m: &Rows, d: V) -> V {
    let row = |r: &[f32; 4]| r[0] * d.x + r[1] * d.y + r[2] * d.z;
    V::new(row(&m[0]), row(&m[1]), row(&m[2]))
}

/// The ray `o + t·d` in object space, with the same `t` along it, and `dt`: as pbrt-v4
/// does, the origin is moved forward along the ray past the error bound of its
/// transform, so a ray leaving a surface cannot start behind it; the object-space walk
/// gets `t_max − dt` and its hits lie at world `t + dt`.
pub fn ray_to_object(inst: &Instance, o: V, d: V) -> (V, V, f32) {
    let (o, err) = point(&inst.to_object, o);
    let d = vector(&inst.to_object, d);
    let len2 = d.length_squared();
    if len2 <= 0.0 {
        return (o, d, 0.0);
    }
    let dt = d.abs().dot(err) / len2;
    (o + d * dt, d, dt)
}

/// A prototype triangle's vertices in world space, and the largest error bound of the
/// three (what a point interpolated from them adds to its own bound).
pub fn to_world(inst: &Instance, p: [[f32; 3]; 3]) -> ([[f32; 3]; 3], V) {
    let mut worst = V::ZERO;
    let p = p.map(|v| {
        let (w, e) = point(&inst.to_world, V::from(v));
        worst = worst.max(e);
        w.to_array()
    });
    (p, worst)
}
