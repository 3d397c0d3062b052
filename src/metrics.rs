//! `canopy compare`: error metrics between a test image and a reference, and a
//! false-colour difference image.

use crate::image::{write_png_rgb, Image};
use anyhow::{bail, Result};
use std::path::Path;

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Metric {
    /// Mean squared error over pixels and channels.
    Mse,
    /// Square root of the MSE.
    Rmse,
    /// Mean of (t − r)² / (r² + 0.01), per channel (pbrt's relative MSE guard).
    Relmse,
    /// Mean absolute error.
    Mae,
}

pub fn check_same_size(test: &Image, reference: &Image) -> Result<()> {
    if (test.width, test.height) != (reference.width, reference.height) {
        bail!(
            "image sizes differ: {}x{} against a {}x{} reference",
            test.width,
            test.height,
            reference.width,
            reference.height
        );
    }
    Ok(())
}

/// The metric over all pixels and channels; non-finite test values count as an error of
/// the reference's magnitude plus one, so a NaN cannot hide.
pub fn error(test: &Image, reference: &Image, m: Metric) -> Result<f64> {
    check_same_size(test, reference)?;
    let mut sum = 0f64;
    for (t, r) in test.pixels.iter().zip(&reference.pixels) {
        for c in 0..3 {
            let (t, r) = (t[c] as f64, r[c] as f64);
            let d = if t.is_finite() { t - r } else { r.abs() + 1.0 };
            sum += match m {
                Metric::Mse | Metric::Rmse => d * d,
                Metric::Relmse => d * d / (r * r + 0.01),
                Metric::Mae => d.abs(),
            };
        }
    }
    let mean = sum / (test.pixels.len() * 3).max(1) as f64;
    Ok(if m == Metric::Rmse { mean.sqrt() } else { mean })
}

/// Per-channel image means of both images and their relative difference.
pub fn mean_ratio(test: &Image, reference: &Image) -> [f64; 3] {
    let (a, b) = (test.mean(), reference.mean());
    [0, 1, 2].map(|c| a[c] / b[c] - 1.0)
}

/// A false-colour map of the per-pixel absolute luminance difference: black (none) through
/// blue, green, yellow to red at `scale` (defaults to the 99th percentile).
pub fn write_diff(test: &Image, reference: &Image, path: &Path) -> Result<f64> {
    check_same_size(test, reference)?;
    let diffs: Vec<f32> = test
        .pixels
        .iter()
        .zip(&reference.pixels)
        .map(|(t, r)| {
            let l = |p: &[f32; 3]| crate::material::luminance(glam::Vec3A::from(*p));
            let d = (l(t) - l(r)).abs();
            if d.is_finite() {
                d
            } else {
                f32::INFINITY
            }
        })
        .collect();
    let mut sorted: Vec<f32> = diffs.iter().copied().filter(|d| d.is_finite()).collect();
    sorted.sort_by(f32::total_cmp);
    let scale = sorted
        .get(sorted.len().saturating_sub(1) * 99 / 100)
        .copied()
        .filter(|&s| s > 0.0)
        .unwrap_or(1.0);
    let rgb: Vec<u8> = diffs
        .iter()
        .flat_map(|&d| ramp(if d.is_finite() { d / scale } else { 1.0 }))
        .collect();
    write_png_rgb(path, test.width, test.height, &rgb)?;
    Ok(scale as f64)
}

fn ramp(x: f32) -> [u8; 3] {
    let x = x.clamp(0.0, 1.0);
    let stops = [
        [0.0, 0.0, 0.0],
        [0.0, 0.0, 1.0],
        [0.0, 1.0, 0.0],
        [1.0, 1.0, 0.0],
        [1.0, 0.0, 0.0],
    ];
    let f = x * 4.0;
    let i = (f as usize).min(3);
    let t = f - i as f32;
    [0, 1, 2].map(|c| ((stops[i][c] * (1.0 - t) + stops[i + 1][c] * t) * 255.0 + 0.5) as u8)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn img(v: &[[f32; 3]]) -> Image {
        Image {
            width: v.len() as u32,
            height: 1,
            pixels: v.to_vec(),
        }
    }

    #[test]
    fn metrics_match_hand_computed_values() {
        let r = img(&[[1.0, 1.0, 1.0], [0.0, 0.0, 0.0]]);
        let t = img(&[[1.0, 1.0, 2.0], [0.0, 3.0, 0.0]]);
        // Differences 0,0,1,0,3,0: squares sum 10 over 6 values.
        assert!((error(&t, &r, Metric::Mse).unwrap() - 10.0 / 6.0).abs() < 1e-12);
        assert!((error(&t, &r, Metric::Rmse).unwrap() - (10.0f64 / 6.0).sqrt()).abs() < 1e-12);
        assert!((error(&t, &r, Metric::Mae).unwrap() - 4.0 / 6.0).abs() < 1e-12);
        let rel = (1.0 / 1.01 + 9.0 / 0.01) / 6.0;
        assert!((error(&t, &r, Metric::Relmse).unwrap() - rel).abs() < 1e-9);
        assert_eq!(error(&r, &r, Metric::Mse).unwrap(), 0.0);
    }

    #[test]
    fn nan_counts_as_error_and_sizes_must_match() {
        let r = img(&[[1.0, 1.0, 1.0]]);
        let t = img(&[[f32::NAN, 1.0, 1.0]]);
        assert!(error(&t, &r, Metric::Mse).unwrap() > 0.0);
        assert!(error(&img(&[[0.0; 3], [0.0; 3]]), &r, Metric::Mse).is_err());
    }
}

/// `canopy compare`'s result.
#[derive(Debug, serde::Serialize)]
pub struct Comparison {
    pub metric: Metric,
    pub error: f64,
    pub mean_test: [f64; 3],
    pub mean_reference: [f64; 3],
    pub mean_relative_difference: [f64; 3],
    /// The luminance difference shown as full red in `--diff`, when one was written.
    pub diff_scale: Option<f64>,
}

impl Comparison {
    /// `test` against `reference`, writing the false-colour difference to `diff` if given.
    pub fn new(
        test: &Image,
        reference: &Image,
        metric: Metric,
        diff: Option<&Path>,
    ) -> Result<Comparison> {
        Ok(Comparison {
            metric,
            error: error(test, reference, metric)?,
            mean_test: test.mean(),
            mean_reference: reference.mean(),
            mean_relative_difference: mean_ratio(test, reference),
            diff_scale: diff.map(|p| write_diff(test, reference, p)).transpose()?,
        })
    }
}

impl std::fmt::Display for Comparison {
    fn fmt(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        let r = self.mean_relative_difference;
        writeln!(f, "{:?}: {:.6e}", self.metric, self.error)?;
        write!(
            f,
            "mean: test {:?}, reference {:?}, relative difference {:+.4} {:+.4} {:+.4}",
            self.mean_test, self.mean_reference, r[0], r[1], r[2]
        )
    }
}
