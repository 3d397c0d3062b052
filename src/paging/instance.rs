//! An archive's instances as the tracer uses them: the object-to-world transform and its
//! inverse in f32 (the inverse taken in f64), and the pbrt-v4 error bounds of applying
//! them (pbrt-v4 §6.8.4, `Transform` of a `Point3fi` and of a ray).

use crate::trace::gamma;
use canopy_format::InstanceRecord;
use glam::Vec3A as V;

/// Rows of a 3×4 affine map, column 3 the translation.
type Rows = [[f32; 4]; 3];

#[derive(Clone, Debug)]
pub struct Instance {
    /// The page whose node 0 is the prototype's root.
    pub page: u32,
    to_world: Rows,
    to_object: Rows,
}

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

impl Instance {
    /// The instance of record `r` (its transform checked invertible when the archive was
    /// opened).
    pub fn new(r: &InstanceRecord) -> Instance {
        let m = r.matrix();
        let det = r.det();
        let cof = |r: usize, c: usize| {
            let (r1, r2) = ((r + 1) % 3, (r + 2) % 3);
            let (c1, c2) = ((c + 1) % 3, (c + 2) % 3);
            m[r1][c1] * m[r2][c2] - m[r1][c2] * m[r2][c1]
        };
        // The inverse of the linear part is the transposed cofactor matrix over det.
        let inv: [[f64; 3]; 3] = std::array::from_fn(|i| std::array::from_fn(|j| cof(j, i) / det));
        let to_object = std::array::from_fn(|i| {
            let t = -(0..3).map(|j| inv[i][j] * m[j][3]).sum::<f64>();
            [
                inv[i][0] as f32,
                inv[i][1] as f32,
                inv[i][2] as f32,
                t as f32,
            ]
        });
        Instance {
            page: r.prototype_page,
            to_world: m.map(|row| row.map(|x| x as f32)),
            to_object,
        }
    }

    /// The ray `o + t·d` in object space, with the same `t` along it, and `dt`: as pbrt-v4
    /// does, the origin is moved forward along the ray past the error bound of its
    /// transform, so a ray leaving a surface cannot start behind it; the object-space walk
    /// gets `t_max − dt` and its hits lie at world `t + dt`.
    pub fn ray_to_object(&self, o: V, d: V) -> (V, V, f32) {
        let (o, err) = point(&self.to_object, o);
        let d = vector(&self.to_object, d);
        let len2 = d.length_squared();
        if len2 <= 0.0 {
            return (o, d, 0.0);
        }
        let dt = d.abs().dot(err) / len2;
        (o + d * dt, d, dt)
    }

    /// How the transform scales curvature: |det|^−⅓ (exact for uniform scales).
    pub fn curvature_scale(&self) -> f32 {
        let m = &self.to_world;
        let det = m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
            - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
        det.abs().cbrt().recip()
    }

    /// A prototype triangle's vertices in world space, and the largest error bound of the
    /// three (what a point interpolated from them adds to its own bound).
    pub fn to_world(&self, p: [[f32; 3]; 3]) -> ([[f32; 3]; 3], V) {
        let mut worst = V::ZERO;
        let p = p.map(|v| {
            let (w, e) = point(&self.to_world, V::from(v));
            worst = worst.max(e);
            w.to_array()
        });
        (p, worst)
    }
}
