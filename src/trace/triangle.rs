//! The watertight ray–triangle test of Woop, Benthin and Wald (JCGT 2013) one triangle at
//! a time, as pbrt-v4's `Triangle::Intersect` writes it: the reference the four-lane test
//! of the traversal matches bit for bit, and the test of rays that meet triangles outside
//! a traversal (PBGI's rasterized leaves).

use super::{gamma, Ray};
use crate::paging::TriW;

/// A ray prepared for the test: its origin and the shear that makes it run along +z.
pub struct Watertight {
    o: [f32; 3],
    /// The axes permuted so z is the direction's largest component.
    pub(super) k: [usize; 3],
    /// Shear x, y and scale z.
    pub(super) s: [f32; 3],
}

impl Watertight {
    pub fn new(r: &Ray) -> Watertight {
        let a = r.d.abs();
        let kz = if a.x > a.y {
            if a.x > a.z {
                0
            } else {
                2
            }
        } else if a.y > a.z {
            1
        } else {
            2
        };
        let kx = (kz + 1) % 3;
        let ky = (kx + 1) % 3;
        let d = r.d.to_array();
        Watertight {
            o: r.o.to_array(),
            k: [kx, ky, kz],
            s: [-d[kx] / d[kz], -d[ky] / d[kz], 1.0 / d[kz]],
        }
    }

    /// Distance along the ray (in units of its direction) and barycentrics of its hit on
    /// `tri` before `t_max`, if any.
    pub fn hit(&self, tri: &TriW, t_max: f32) -> Option<(f32, [f32; 3])> {
        let [kx, ky, kz] = self.k;
        let [sx, sy, sz] = self.s;
        let o = self.o;
        let tr = |p: &[f32; 3]| {
            let z = p[kz] - o[kz];
            ((p[kx] - o[kx] + sx * z, p[ky] - o[ky] + sy * z), z)
        };
        let (xy0, z0) = tr(&tri.p[0]);
        let (xy1, z1) = tr(&tri.p[1]);
        let (xy2, z2) = tr(&tri.p[2]);
        let xy = [xy0, xy1, xy2];
        let edge = |a: (f32, f32), b: (f32, f32)| {
            let e = a.0 * b.1 - a.1 * b.0;
            if e == 0.0 {
                // Exactly on an edge in f32: decide in f64 so neighbours agree.
                (a.0 as f64 * b.1 as f64 - a.1 as f64 * b.0 as f64) as f32
            } else {
                e
            }
        };
        let e0 = edge(xy[1], xy[2]);
        let e1 = edge(xy[2], xy[0]);
        let e2 = edge(xy[0], xy[1]);
        if (e0 < 0.0 || e1 < 0.0 || e2 < 0.0) && (e0 > 0.0 || e1 > 0.0 || e2 > 0.0) {
            return None;
        }
        let det = e0 + e1 + e2;
        if det == 0.0 {
            return None;
        }
        let z = [z0 * sz, z1 * sz, z2 * sz];
        let ts = e0 * z[0] + e1 * z[1] + e2 * z[2];
        if det < 0.0 && (ts >= 0.0 || ts < t_max * det) {
            return None;
        }
        if det > 0.0 && (ts <= 0.0 || ts > t_max * det) {
            return None;
        }
        let inv = 1.0 / det;
        let tt = ts * inv;
        // pbrt-v4: reject hits closer than the error bound of t (behind the origin).
        let max_z = z[0].abs().max(z[1].abs()).max(z[2].abs());
        let delta_z = gamma(3) * max_z;
        let max_x = xy[0].0.abs().max(xy[1].0.abs()).max(xy[2].0.abs());
        let max_y = xy[0].1.abs().max(xy[1].1.abs()).max(xy[2].1.abs());
        let delta_x = gamma(5) * (max_x + max_z);
        let delta_y = gamma(5) * (max_y + max_z);
        let delta_e = 2.0 * (gamma(2) * max_x * max_y + delta_y * max_x + delta_x * max_y);
        let max_e = e0.abs().max(e1.abs()).max(e2.abs());
        let delta_t =
            3.0 * (gamma(3) * max_e * max_z + delta_e * max_z + delta_z * max_e) * inv.abs();
        if tt <= delta_t {
            return None;
        }
        Some((tt, [e0 * inv, e1 * inv, e2 * inv]))
    }
}
