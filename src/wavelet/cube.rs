//! Cube-map geometry: six faces of n×n texels. A face is the square {axis + s·u + t·v :
//! s, t ∈ [−1, 1]}; texel (x, y) covers s ∈ [−1 + 2x/n, −1 + 2(x+1)/n], likewise t with y.
//! The four side faces have v = +z, so the plane z = 0 runs along texel borders when n is
//! even: the upper halves of the side faces and the +z face form the hemicube the
//! micro-buffer uses in a receiver's local frame (z along the normal).

use glam::Vec3;

/// Faces in the order +x, −x, +y, −y, +z, −z: (axis, u, v).
pub const FACES: [(Vec3, Vec3, Vec3); 6] = [
    (Vec3::X, Vec3::Y, Vec3::Z),
    (Vec3::NEG_X, Vec3::NEG_Y, Vec3::Z),
    (Vec3::Y, Vec3::NEG_X, Vec3::Z),
    (Vec3::NEG_Y, Vec3::X, Vec3::Z),
    (Vec3::Z, Vec3::X, Vec3::Y),
    (Vec3::NEG_Z, Vec3::X, Vec3::NEG_Y),
];

/// The face a direction points through and its (s, t) in [−1, 1]².
pub fn face_st(d: Vec3) -> (usize, f32, f32) {
    let a = d.abs();
    let face = if a.x >= a.y && a.x >= a.z {
        if d.x >= 0.0 {
            0
        } else {
            1
        }
    } else if a.y >= a.z {
        if d.y >= 0.0 {
            2
        } else {
            3
        }
    } else if d.z >= 0.0 {
        4
    } else {
        5
    };
    let (axis, u, v) = FACES[face];
    let major = d.dot(axis);
    (face, d.dot(u) / major, d.dot(v) / major)
}

/// Texel index (face·n² + y·n + x) of a direction.
pub fn texel_of(d: Vec3, n: usize) -> usize {
    let (face, s, t) = face_st(d);
    texel_at(face, s, t, n)
}

/// Texel index of the point (s, t) of a face, as [`face_st`] gives it.
pub fn texel_at(face: usize, s: f32, t: f32, n: usize) -> usize {
    let cell = |c: f32| (((c + 1.0) * 0.5 * n as f32) as usize).min(n - 1);
    face * n * n + cell(t) * n + cell(s)
}

/// The four corners of a texel on the unit-distance face, counter-clockwise in (s, t).
pub fn texel_corners(index: usize, n: usize) -> [Vec3; 4] {
    let (face, y, x) = (index / (n * n), (index / n) % n, index % n);
    let (axis, u, v) = FACES[face];
    let c = |i: usize| -1.0 + 2.0 * i as f32 / n as f32;
    let p = |s: f32, t: f32| axis + u * s + v * t;
    [
        p(c(x), c(y)),
        p(c(x + 1), c(y)),
        p(c(x + 1), c(y + 1)),
        p(c(x), c(y + 1)),
    ]
}

/// Unit direction through a texel's centre.
pub fn texel_dir(index: usize, n: usize) -> Vec3 {
    let k = texel_corners(index, n);
    ((k[0] + k[2]) * 0.5).normalize()
}

/// Exact solid angle of a texel: the area element of a cube face integrates to
/// F(s, t) = atan2(s·t, √(s² + t² + 1)), differenced over the texel's corners.
pub fn texel_solid_angle(index: usize, n: usize) -> f32 {
    let (y, x) = ((index / n) % n, index % n);
    let c = |i: usize| -1.0 + 2.0 * i as f64 / n as f64;
    let f = |s: f64, t: f64| (s * t).atan2((s * s + t * t + 1.0).sqrt());
    let (s0, s1, t0, t1) = (c(x), c(x + 1), c(y), c(y + 1));
    (f(s1, t1) - f(s0, t1) - f(s1, t0) + f(s0, t0)) as f32
}

/// ∫ω dω over a texel, exactly: for a spherical polygon, ½ Σ over edges of the edge's
/// angle times the unit normal of its great-circle plane (Lambert's formula for the
/// projected solid angle). Its z component is the texel's cosine integral in a local
/// frame whose z is the normal.
pub fn texel_vector_integral(index: usize, n: usize) -> Vec3 {
    let k = texel_corners(index, n).map(|p| p.as_dvec3().normalize());
    let mut sum = glam::DVec3::ZERO;
    for i in 0..4 {
        let (a, b) = (k[i], k[(i + 1) % 4]);
        sum += a.cross(b).normalize() * a.dot(b).clamp(-1.0, 1.0).acos();
    }
    let v = (sum * 0.5).as_vec3();
    // The winding differs between faces; the integral points into the texel.
    if v.dot(texel_dir(index, n)) < 0.0 {
        -v
    } else {
        v
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    #[test]
    fn texel_solid_angles_sum_to_4pi_and_each_face_to_a_sixth() {
        for n in [1, 2, 8, 32] {
            let per_face: Vec<f64> = (0..6)
                .map(|f| {
                    (0..n * n)
                        .map(|i| texel_solid_angle(f * n * n + i, n) as f64)
                        .sum()
                })
                .collect();
            for s in &per_face {
                assert!((s - 4.0 * PI / 6.0).abs() < 1e-5, "n {n}: face {s}");
            }
            let total: f64 = per_face.iter().sum();
            assert!((total - 4.0 * PI).abs() < 1e-5, "n {n}: {total}");
        }
    }

    #[test]
    fn solid_angle_and_cosine_integral_agree_with_quadrature() {
        let n = 4;
        for index in [0, 5, 21, 2 * 16 + 9, 4 * 16 + 15, 5 * 16 + 6] {
            let k = texel_corners(index, n);
            let (mut omega, mut vec) = (0.0f64, glam::DVec3::ZERO);
            let m = 200;
            for j in 0..m {
                for i in 0..m {
                    let (a, b) = ((i as f64 + 0.5) / m as f64, (j as f64 + 0.5) / m as f64);
                    let p = k[0].as_dvec3()
                        + (k[1] - k[0]).as_dvec3() * a
                        + (k[3] - k[0]).as_dvec3() * b;
                    let area = (k[1] - k[0]).length() as f64 * (k[3] - k[0]).length() as f64
                        / (m * m) as f64;
                    // dω = dA·cosθ/r² = dA/r³ on a face at unit distance.
                    let dw = area / p.length().powi(3);
                    omega += dw;
                    vec += p.normalize() * dw;
                }
            }
            let s = texel_solid_angle(index, n) as f64;
            assert!(
                (s - omega).abs() < 1e-5 * omega.max(1.0),
                "texel {index}: {s} vs {omega}"
            );
            let v = texel_vector_integral(index, n).as_dvec3();
            assert!((v - vec).length() < 1e-5, "texel {index}: {v} vs {vec}");
        }
    }

    #[test]
    fn every_texel_direction_maps_back_to_its_texel() {
        let n = 16;
        for i in 0..6 * n * n {
            assert_eq!(texel_of(texel_dir(i, n), n), i);
        }
    }

    #[test]
    fn the_upper_hemicube_integrates_cosine_to_pi() {
        for n in [2, 4, 16] {
            let (mut omega, mut cos) = (0.0f64, 0.0f64);
            for i in 0..6 * n * n {
                if texel_dir(i, n).z > 0.0 {
                    omega += texel_solid_angle(i, n) as f64;
                    cos += texel_vector_integral(i, n).z as f64;
                }
            }
            assert!((omega - 2.0 * PI).abs() < 1e-5, "n {n}: {omega}");
            assert!((cos - PI).abs() < 1e-5, "n {n}: {cos}");
        }
    }
}
