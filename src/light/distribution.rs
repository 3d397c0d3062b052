//! Piecewise-constant distributions in one and two dimensions over [0, 1) and [0, 1)²
//! (pbrt-v4 §A.5.1 and §A.5.6, `PiecewiseConstant1D` / `2D`): sampling by inverting the
//! cumulative sum, with the density of what was sampled.

/// A density proportional to non-negative cell weights over [0, 1).
pub struct Piecewise1D {
    /// Cumulative weights, `cdf[0]` = 0 and `cdf[n]` = 1 (uniform where all are zero).
    cdf: Vec<f64>,
    /// Density of each cell (weight / mean weight).
    density: Vec<f32>,
    /// Sum of the weights over the cell count (the integral of the step function).
    integral: f64,
}

impl Piecewise1D {
    pub fn new(weights: &[f32]) -> Piecewise1D {
        let n = weights.len().max(1);
        let w = |i: usize| weights.get(i).map_or(1.0, |&w| w.max(0.0) as f64);
        let mut cdf = Vec::with_capacity(n + 1);
        cdf.push(0.0);
        for i in 0..n {
            cdf.push(cdf[i] + w(i) / n as f64);
        }
        let integral = cdf[n];
        let (cdf, density) = match integral > 0.0 {
            true => (
                cdf.iter().map(|c| c / integral).collect(),
                (0..n).map(|i| (w(i) / integral) as f32).collect(),
            ),
            false => ((0..=n).map(|i| i as f64 / n as f64).collect(), vec![1.0; n]),
        };
        Piecewise1D {
            cdf,
            density,
            integral,
        }
    }

    fn len(&self) -> usize {
        self.density.len()
    }

    /// The integral of the weights as a step function over [0, 1).
    pub fn integral(&self) -> f64 {
        self.integral
    }

    /// A point in [0, 1) from `u`, its cell and its density.
    pub fn sample(&self, u: f32) -> (f32, usize, f32) {
        let u = u as f64;
        // The last cell whose cumulative start is at most u, skipping empty cells.
        let i = (self.cdf.partition_point(|&c| c <= u).max(1) - 1).min(self.len() - 1);
        let (lo, hi) = (self.cdf[i], self.cdf[i + 1]);
        let t = if hi > lo { (u - lo) / (hi - lo) } else { 0.5 };
        let x = ((i as f64 + t) / self.len() as f64).min(1.0 - f64::EPSILON) as f32;
        (x, i, self.density[i])
    }

    /// The density at `x` in [0, 1).
    pub fn density(&self, x: f32) -> f32 {
        let i = ((x * self.len() as f32) as usize).min(self.len() - 1);
        self.density[i]
    }
}

/// A density over [0, 1)² proportional to a grid of cell weights, rows along v.
pub struct Piecewise2D {
    rows: Vec<Piecewise1D>,
    marginal: Piecewise1D,
}

impl Piecewise2D {
    /// `weights` row-major, `width` cells a row.
    pub fn new(weights: &[f32], width: usize) -> Piecewise2D {
        let rows: Vec<Piecewise1D> = weights.chunks(width.max(1)).map(Piecewise1D::new).collect();
        let marginal =
            Piecewise1D::new(&rows.iter().map(|r| r.integral() as f32).collect::<Vec<_>>());
        Piecewise2D { rows, marginal }
    }

    /// A point (u, v) from two uniforms, and its density.
    pub fn sample(&self, u: [f32; 2]) -> ([f32; 2], f32) {
        let (v, row, pv) = self.marginal.sample(u[1]);
        let (x, _, pu) = self.rows[row].sample(u[0]);
        ([x, v], pu * pv)
    }

    /// The density at (u, v).
    pub fn density(&self, [u, v]: [f32; 2]) -> f32 {
        let row = ((v * self.rows.len() as f32) as usize).min(self.rows.len() - 1);
        self.marginal.density(v) * self.rows[row].density(u)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_rng::TestRng as Rng;

    #[test]
    fn a_sample_lands_in_proportion_to_its_cells_weight_with_the_density_it_reports() {
        let d = Piecewise1D::new(&[1.0, 0.0, 3.0, 4.0]);
        assert!((d.integral() - 2.0).abs() < 1e-12);
        let mut rng = Rng::new(3);
        let mut hits = [0u32; 4];
        for _ in 0..40_000 {
            let (x, i, pdf) = d.sample(rng.f32());
            assert_eq!(i, (x * 4.0) as usize);
            assert_eq!(pdf, d.density(x));
            hits[i] += 1;
        }
        assert_eq!(hits[1], 0, "an empty cell is never sampled");
        // 40 000 · 3/8 = 15 000, binomial σ ≈ 97; 4 σ.
        for (i, w) in [1.0, 0.0, 3.0, 4.0].into_iter().enumerate() {
            let expected = 40_000.0 * w / 8.0;
            assert!((hits[i] as f64 - expected).abs() < 400.0, "{hits:?}");
        }
        // All zero: uniform.
        let z = Piecewise1D::new(&[0.0; 5]);
        assert_eq!(z.density(0.3), 1.0);
        assert_eq!(z.sample(0.5).1, 2);
    }

    #[test]
    fn the_two_dimensional_density_integrates_to_one_and_matches_its_samples() {
        let w: Vec<f32> = (0..12).map(|i| ((i * 7) % 5) as f32).collect();
        let d = Piecewise2D::new(&w, 4);
        // The density is constant per cell: its cell-centre sum over the cell area is 1.
        let total: f32 = (0..3)
            .flat_map(|j| (0..4).map(move |i| [(i as f32 + 0.5) / 4.0, (j as f32 + 0.5) / 3.0]))
            .map(|uv| d.density(uv) / 12.0)
            .sum();
        assert!((total - 1.0).abs() < 1e-5, "{total}");
        let mut rng = Rng::new(9);
        for _ in 0..1000 {
            let (uv, pdf) = d.sample([rng.f32(), rng.f32()]);
            assert!(pdf > 0.0);
            assert!((pdf - d.density(uv)).abs() < 1e-4 * pdf, "{uv:?}");
        }
    }
}
