//! The non-standard 2D Haar transform of an n×n face (n a power of two), orthonormal.
//!
//! Each level maps every 2×2 block (a b / c d) of the current scaling coefficients to its
//! scaling coefficient C and three details with 002 eq. 13's matrix, which is symmetric and
//! orthonormal (its own inverse):
//! C = (a+b+c+d)/2, D0 = (a−b+c−d)/2, D1 = (a+b−c−d)/2, D2 = (a−b−c+d)/2.
//! Layout after the transform: index 0 holds the root scaling coefficient; the details of
//! the level whose scaling array is h×h sit at (y, x+h), (y+h, x), (y+h, x+h) for x, y < h
//! (row-major, y·n + x), so a texel's value is found by walking one root-to-leaf path
//! ([`eval`]) without decoding the face (000 §3.1).

use super::Coef;

fn check(len: usize, n: usize) {
    assert!(
        n.is_power_of_two() && len == n * n,
        "Haar face must be n×n with n a power of two"
    );
}

/// Forward transform in place.
pub fn forward<T: Coef>(data: &mut [T], n: usize) {
    check(data.len(), n);
    let mut tmp = vec![T::default(); n * n];
    let mut size = n;
    while size > 1 {
        let h = size / 2;
        for y in 0..h {
            for x in 0..h {
                let a = data[2 * y * n + 2 * x];
                let b = data[2 * y * n + 2 * x + 1];
                let c = data[(2 * y + 1) * n + 2 * x];
                let d = data[(2 * y + 1) * n + 2 * x + 1];
                tmp[y * n + x] = (a + b + c + d) * 0.5;
                tmp[y * n + x + h] = (a - b + c - d) * 0.5;
                tmp[(y + h) * n + x] = (a + b - c - d) * 0.5;
                tmp[(y + h) * n + x + h] = (a - b - c + d) * 0.5;
            }
        }
        for y in 0..size {
            data[y * n..y * n + size].copy_from_slice(&tmp[y * n..y * n + size]);
        }
        size = h;
    }
}

/// Inverse transform in place.
pub fn inverse<T: Coef>(data: &mut [T], n: usize) {
    check(data.len(), n);
    let mut tmp = vec![T::default(); n * n];
    let mut h = 1;
    while h < n {
        for y in 0..h {
            for x in 0..h {
                let [a, b, c, d] = children(
                    data[y * n + x],
                    data[y * n + x + h],
                    data[(y + h) * n + x],
                    data[(y + h) * n + x + h],
                );
                tmp[2 * y * n + 2 * x] = a;
                tmp[2 * y * n + 2 * x + 1] = b;
                tmp[(2 * y + 1) * n + 2 * x] = c;
                tmp[(2 * y + 1) * n + 2 * x + 1] = d;
            }
        }
        let size = 2 * h;
        for y in 0..size {
            data[y * n..y * n + size].copy_from_slice(&tmp[y * n..y * n + size]);
        }
        h = size;
    }
}

/// The four scaling coefficients one level finer: the inverse of 002 eq. 13.
fn children<T: Coef>(c: T, d0: T, d1: T, d2: T) -> [T; 4] {
    [
        (c + d0 + d1 + d2) * 0.5,
        (c - d0 + d1 - d2) * 0.5,
        (c + d0 - d1 - d2) * 0.5,
        (c - d0 - d1 + d2) * 0.5,
    ]
}

/// The value of texel (px, py) from the coefficients `get(index)`: one root-to-leaf walk,
/// three lookups per level.
pub fn eval<T: Coef>(n: usize, px: usize, py: usize, get: impl Fn(usize) -> T) -> T {
    let mut c = get(0);
    let mut h = 1;
    while h < n {
        let shift = (n / h).trailing_zeros();
        let (x, y) = (px >> shift, py >> shift);
        let quad = ((px >> (shift - 1)) & 1) + 2 * ((py >> (shift - 1)) & 1);
        let kids = children(
            c,
            get(y * n + x + h),
            get((y + h) * n + x),
            get((y + h) * n + x + h),
        );
        c = kids[quad];
        h *= 2;
    }
    c
}

/// A face's coefficients after truncation: index and value, sorted by index.
#[derive(Clone, Debug, PartialEq)]
pub struct Sparse<T> {
    pub n: usize,
    pub coefs: Vec<(u32, T)>,
}

impl<T: Coef> Sparse<T> {
    /// Keeps the root scaling coefficient and every coefficient whose magnitude is at least
    /// `threshold` (non-linear approximation, 003 ch. 4). By Parseval the squared L² error
    /// of the face is the sum of the dropped coefficients' squares, so at most
    /// (dropped count)·threshold².
    pub fn truncate(transformed: &[T], n: usize, threshold: f32) -> Self {
        check(transformed.len(), n);
        let t2 = threshold * threshold;
        let coefs = transformed
            .iter()
            .enumerate()
            .filter(|&(i, c)| i == 0 || (c.norm2() > 0.0 && c.norm2() >= t2))
            .map(|(i, &c)| (i as u32, c))
            .collect();
        Sparse { n, coefs }
    }

    pub fn get(&self, index: usize) -> T {
        self.coefs
            .binary_search_by_key(&(index as u32), |&(i, _)| i)
            .map(|k| self.coefs[k].1)
            .unwrap_or_default()
    }

    /// One texel's value.
    pub fn texel(&self, px: usize, py: usize) -> T {
        eval(self.n, px, py, |i| self.get(i))
    }

    /// Every texel (row-major).
    pub fn decode(&self) -> Vec<T> {
        let mut dense = vec![T::default(); self.n * self.n];
        for &(i, c) in &self.coefs {
            dense[i as usize] = c;
        }
        inverse(&mut dense, self.n);
        dense
    }

    /// Σ over coefficients of a·b: the inner product of the two faces (Parseval), the
    /// product 002 eq. 6 takes between a BRDF and a radiance face.
    pub fn dot(&self, other: &Sparse<f32>) -> T {
        let (mut i, mut j) = (0, 0);
        let mut sum = T::default();
        while i < self.coefs.len() && j < other.coefs.len() {
            let (a, b) = (self.coefs[i], other.coefs[j]);
            match a.0.cmp(&b.0) {
                std::cmp::Ordering::Less => i += 1,
                std::cmp::Ordering::Greater => j += 1,
                std::cmp::Ordering::Equal => {
                    sum = sum + a.1 * b.1;
                    i += 1;
                    j += 1;
                }
            }
        }
        sum
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;
    use proptest::prelude::*;

    fn face(n: usize) -> impl Strategy<Value = Vec<f32>> {
        proptest::collection::vec(-100.0f32..100.0, n * n)
    }

    fn sizes() -> impl Strategy<Value = usize> {
        (0u32..6).prop_map(|k| 1 << k)
    }

    proptest! {
        #[test]
        fn forward_then_inverse_reconstructs(data in sizes().prop_flat_map(face)) {
            let n = (data.len() as f64).sqrt() as usize;
            let mut t = data.clone();
            forward(&mut t, n);
            inverse(&mut t, n);
            for (a, b) in data.iter().zip(&t) {
                prop_assert!((a - b).abs() <= 1e-4 * (1.0 + a.abs()), "{a} vs {b}");
            }
        }

        #[test]
        fn parseval_holds_for_inner_products(
            (a, b) in sizes().prop_flat_map(|n| (face(n), face(n)))
        ) {
            let n = (a.len() as f64).sqrt() as usize;
            let space: f64 = a.iter().zip(&b).map(|(x, y)| (x * y) as f64).sum();
            let (mut ta, mut tb) = (a.clone(), b.clone());
            forward(&mut ta, n);
            forward(&mut tb, n);
            let coef: f64 = ta.iter().zip(&tb).map(|(x, y)| (x * y) as f64).sum();
            let scale: f64 = a.iter().chain(&b).map(|x| (x * x) as f64).sum();
            prop_assert!((space - coef).abs() <= 1e-5 * scale.max(1.0), "{space} vs {coef}");
        }

        #[test]
        fn point_query_equals_full_decode(data in sizes().prop_flat_map(face), t in 0.0f32..30.0) {
            let n = (data.len() as f64).sqrt() as usize;
            let mut c = data.clone();
            forward(&mut c, n);
            let sparse = Sparse::truncate(&c, n, t);
            let dense = sparse.decode();
            for y in 0..n {
                for x in 0..n {
                    let q = sparse.texel(x, y);
                    prop_assert!((q - dense[y * n + x]).abs() <= 1e-3, "({x},{y}) {q} vs {}", dense[y * n + x]);
                }
            }
        }

        #[test]
        fn truncation_error_is_the_dropped_energy_and_within_the_bound(
            data in (2u32..6).prop_map(|k| 1usize << k).prop_flat_map(face),
            t in 0.0f32..40.0,
        ) {
            let n = (data.len() as f64).sqrt() as usize;
            let mut c = data.clone();
            forward(&mut c, n);
            let sparse = Sparse::truncate(&c, n, t);
            let dropped = c.len() - sparse.coefs.len();
            let dropped_energy: f64 = c.iter().enumerate()
                .filter(|(i, _)| sparse.coefs.binary_search_by_key(&(*i as u32), |&(k, _)| k).is_err())
                .map(|(_, x)| (x * x) as f64).sum();
            let err: f64 = sparse.decode().iter().zip(&data).map(|(a, b)| ((a - b) * (a - b)) as f64).sum();
            let energy: f64 = data.iter().map(|x| (x * x) as f64).sum();
            prop_assert!((err - dropped_energy).abs() <= 1e-5 * energy.max(1.0), "{err} vs {dropped_energy}");
            prop_assert!(err <= dropped as f64 * (t as f64).powi(2) + 1e-5 * energy.max(1.0));
        }
    }

    #[test]
    fn basis_functions_are_orthonormal() {
        let n = 8;
        let basis: Vec<Vec<f32>> = (0..n * n)
            .map(|k| {
                let mut e = vec![0.0; n * n];
                e[k] = 1.0;
                inverse(&mut e, n);
                e
            })
            .collect();
        for (i, a) in basis.iter().enumerate() {
            for (j, b) in basis.iter().enumerate() {
                let d: f32 = a.iter().zip(b).map(|(x, y)| x * y).sum();
                let want = if i == j { 1.0 } else { 0.0 };
                assert!((d - want).abs() < 1e-6, "<ψ{i}, ψ{j}> = {d}");
            }
        }
    }

    #[test]
    fn the_root_coefficient_is_n_times_the_mean_and_rgb_matches_per_channel() {
        let n = 4;
        let rgb: Vec<Vec3> = (0..16)
            .map(|i| Vec3::new(i as f32, (i * i) as f32, 1.0))
            .collect();
        let mut t = rgb.clone();
        forward(&mut t, n);
        let mean = rgb.iter().copied().sum::<Vec3>() / 16.0;
        assert!((t[0] - mean * n as f32).length() < 1e-4);
        let mut g: Vec<f32> = rgb.iter().map(|c| c.y).collect();
        forward(&mut g, n);
        for (a, b) in t.iter().zip(&g) {
            assert!((a.y - b).abs() < 1e-4);
        }
    }

    #[test]
    fn sparse_dot_equals_the_dense_texel_product() {
        let n = 8;
        let a: Vec<f32> = (0..64).map(|i| ((i * 7) % 11) as f32).collect();
        let b: Vec<f32> = (0..64).map(|i| ((i * 5) % 13) as f32 - 6.0).collect();
        let dense: f32 = a.iter().zip(&b).map(|(x, y)| x * y).sum();
        let (mut ta, mut tb) = (a.clone(), b.clone());
        forward(&mut ta, n);
        forward(&mut tb, n);
        let d = Sparse::truncate(&ta, n, 0.0).dot(&Sparse::truncate(&tb, n, 0.0));
        assert!(
            (d - dense).abs() < 1e-2 * dense.abs().max(1.0),
            "{d} vs {dense}"
        );
    }
}
