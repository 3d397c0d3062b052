//! Splitting a pass's sample of a pixel over more camera samples where its earlier
//! samples scattered (`--pixel-split`, not in the seeds; a per-pixel form of adaptive
//! sampling), for every integrator.
//!
//! A pass's sample of a pixel is the mean of m camera samples, the first its own and the
//! others from a sequence of the pixel's own that runs on across passes, with
//! m = ⌈√(κ (v / c) / (v̄ / c̄))⌉ from the pixel's earlier samples: v their variance and c
//! their rays, v̄ and c̄ the image's means of them (splitting's optimum, n ∝ √(v / c)).
//! The count comes only from earlier samples, never from the ones it is spent on; still,
//! the pass's first sample is the next point of the pixel's stratified sequence, placed
//! away from the earlier points that set its weight, so the mean drifts at low sample
//! counts (docs/rendering.md measures it). The split is off by default. More samples at
//! one first hit cannot lower the part of a pixel's variance that is the sample's
//! position in it (a highlight on a curved metal, a lamp's silhouette, a textured edge);
//! more first hits can. docs/rendering.md gives what it gains per integrator.

use crate::material::luminance;
use crate::moments::Moments;
use crate::sampler::PixelSampler;
use glam::Vec3A as V;
use std::sync::{Mutex, PoisonError};

/// κ in m = ⌈√(κ (v / c) / (v̄ / c̄))⌉. Under a cap of 16 camera rays κ 0.25 to 4 gave
/// the same error. With the cap at 64, on the showroom at 20 s (seeds 1–4), κ 4 lowered
/// the mean squared error by 13% against κ 0.5 under 16, side by side, and κ 2, 6 and 8
/// by 8, 14 and 9% (later batches of the same hour). The walls' error is mostly their
/// cache records', which more samples do not lower; the gold bunny's highlights take all
/// the first hits they get.
const GAIN: f64 = 4.0;

/// Samples of a pixel before its spread decides anything: the passes before it take one
/// sample, and weigh as much as the later passes' means. On the showroom at 20 s, seeds
/// 1–4, 2 instead of 4 lowered the mean RMSE from 2.45e-3 to 2.38e-3 (room at 60 s: −0.9%).
const AFTER: u32 = 2;

/// Seed offset of the pixels' own sequences of further samples.
const SEED: u32 = 0x2c1b_3c6d;

/// One pixel's samples so far: their luminances and rays, and the further samples it
/// took (where its own sequence is).
#[derive(Default, Clone, Copy)]
struct Pixel {
    y: Moments,
    rays: u64,
    further: u32,
}

impl Pixel {
    fn variance(&self) -> Option<f64> {
        (self.y.count >= AFTER as u64).then(|| self.y.variance())
    }

    /// Rays per sample (at least one).
    fn cost(&self) -> f64 {
        (self.rays as f64 / self.y.count.max(1) as f64).max(1.0)
    }
}

pub(super) struct PixelSplit {
    /// Most samples one pass takes of a pixel (1: off).
    most: u32,
    seed: u32,
    pixels: Vec<Mutex<Pixel>>,
    /// The mean over pixels of one sample's variance and of its rays, at the pass's
    /// start.
    mean_variance: f64,
    mean_cost: f64,
}

impl PixelSplit {
    /// Up to `most` samples a pass over `pixels` pixels.
    pub(super) fn new(most: u32, seed: u32, pixels: usize) -> PixelSplit {
        let pixels = match most > 1 {
            true => (0..pixels).map(|_| Mutex::default()).collect(),
            false => Vec::new(),
        };
        PixelSplit {
            most,
            seed,
            pixels,
            mean_variance: 0.0,
            mean_cost: 1.0,
        }
    }

    /// Most samples a pass takes of a pixel; 1 where it is off.
    pub(super) fn most(&self) -> u32 {
        match self.pixels.is_empty() {
            true => 1,
            false => self.most,
        }
    }

    fn pixel(&self, at: usize) -> Option<Pixel> {
        let slot = self.pixels.get(at)?;
        Some(*slot.lock().unwrap_or_else(PoisonError::into_inner))
    }

    /// Before a pass: the image's mean variance of one sample so far, which it returns
    /// (None where it is off).
    pub(super) fn begin_pass(&mut self) -> Option<f64> {
        if self.pixels.is_empty() {
            return None;
        }
        let (mut sum, mut cost, mut n) = (0.0, 0.0, 0usize);
        for at in 0..self.pixels.len() {
            let Some(p) = self.pixel(at) else { continue };
            if let Some(v) = p.variance() {
                sum += v;
                cost += p.cost();
                n += 1;
            }
        }
        self.mean_variance = sum / n.max(1) as f64;
        self.mean_cost = cost / n.max(1) as f64;
        Some(self.mean_variance)
    }

    /// Samples this pass takes of the pixel at `at`, from its earlier ones.
    pub(super) fn count(&self, at: usize) -> u32 {
        let Some(p) = self.pixel(at) else {
            return 1;
        };
        let Some(v) = p.variance().filter(|_| self.mean_variance > 0.0) else {
            return 1;
        };
        let m = (GAIN * v / p.cost() / (self.mean_variance / self.mean_cost))
            .sqrt()
            .ceil();
        // NaN (a non-finite spread) takes one.
        (m.min(self.most as f64) as u32).max(1)
    }

    /// The next `n` samples of pixel `pixel` (its index in the image) at `at` from its own
    /// sequence: each one's number there and its sampler.
    pub(super) fn further(&self, at: usize, pixel: u32, n: u32) -> Vec<(u32, PixelSampler)> {
        let Some(slot) = self.pixels.get(at).filter(|_| n > 0) else {
            return Vec::new();
        };
        let first = {
            let mut px = slot.lock().unwrap_or_else(PoisonError::into_inner);
            px.further += n;
            px.further - n
        };
        (first..first + n)
            .map(|i| (i, PixelSampler::new(self.seed ^ SEED, pixel, i)))
            .collect()
    }

    /// Records a pass's samples `ls` of the pixel at `at`, which traced `rays` rays.
    pub(super) fn note(&self, at: usize, ls: &[V], rays: u64) {
        let Some(slot) = self.pixels.get(at) else {
            return;
        };
        let mut px = slot.lock().unwrap_or_else(PoisonError::into_inner);
        for y in ls.iter().map(|&l| luminance(l)).filter(|y| y.is_finite()) {
            px.y.add(y);
        }
        px.rays += rays;
    }

    /// The stats' line saying what it did, `further` the samples it added.
    pub(super) fn describe(&self, further: u64) -> String {
        match self.most() {
            1 => "pixel split: off (one camera sample per pixel and pass)".into(),
            m => format!(
                "pixel split: up to {m} camera samples per pixel and pass where its earlier samples scatter ({further} further samples)"
            ),
        }
    }

    /// Bytes held.
    pub(super) fn bytes(&self) -> u64 {
        (self.pixels.len() * size_of::<Mutex<Pixel>>()) as u64
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Notes `n` samples alternating between `lo` and `hi` (variance (hi − lo)²/4 · n/(n−1)),
    /// each of `rays` rays.
    fn feed(split: &PixelSplit, at: usize, n: u32, [lo, hi]: [f32; 2], rays: u64) {
        for i in 0..n {
            split.note(at, &[V::splat(if i % 2 == 0 { lo } else { hi })], rays);
        }
    }

    #[test]
    fn a_pixel_takes_samples_in_proportion_to_the_root_of_its_variance_over_its_cost() {
        let mut split = PixelSplit::new(32, 7, 3);
        // Pixel 0 scatters, pixel 1 is flat, pixel 2 scatters as much at 4× the rays.
        feed(&split, 0, AFTER - 1, [0.0, 2.0], 5);
        feed(&split, 1, AFTER - 1, [1.0, 1.0], 5);
        split.begin_pass();
        assert_eq!(split.count(0), 1, "before its first {AFTER} samples");
        feed(&split, 0, 1001 - (AFTER - 1), [0.0, 2.0], 5);
        feed(&split, 1, 1001 - (AFTER - 1), [1.0, 1.0], 5);
        feed(&split, 2, 1001, [0.0, 2.0], 20);
        let mean_variance = split.begin_pass().unwrap();
        // Pixels 0 and 2 have variance 1.001 (1001 samples), pixel 1 none.
        assert!(
            (mean_variance - 2.002 / 3.0).abs() < 1e-5,
            "{mean_variance}"
        );
        // v̄ / c̄ = (2.002 / 3) / 10, so pixel 0 takes ⌈√(4 · (1.001 / 5) / (0.0667))⌉ =
        // ⌈√12⌉ = 4 and pixel 2, at 4× the cost, ⌈√(4 · (1.001 / 20) / 0.0667)⌉ = ⌈√3⌉ = 2.
        assert_eq!(split.count(0), 4);
        assert_eq!(split.count(1), 1);
        assert_eq!(split.count(2), 2);
        assert_eq!(split.count(9), 1, "outside the window");
        // One pixel of a hundred scatters: ⌈√(4 · 100)⌉ = 20, capped at `most`.
        let mut split = PixelSplit::new(4, 7, 100);
        feed(&split, 0, 100, [0.0, 2.0], 5);
        for at in 1..100 {
            feed(&split, at, 100, [1.0, 1.0], 5);
        }
        split.begin_pass();
        assert_eq!(split.count(0), 4);
    }

    #[test]
    fn further_samples_run_on_through_the_pixels_own_sequence() {
        let split = PixelSplit::new(8, 7, 2);
        let index = |v: Vec<(u32, PixelSampler)>| v.into_iter().map(|f| f.0).collect::<Vec<_>>();
        assert_eq!(index(split.further(0, 40, 3)), [0, 1, 2]);
        assert_eq!(index(split.further(0, 40, 2)), [3, 4]);
        assert_eq!(index(split.further(1, 41, 1)), [0], "each pixel its own");
        assert!(split.further(0, 40, 0).is_empty());
        let [a, b] = [5, 6].map(|i| PixelSampler::new(7 ^ SEED, 40, i).get4(0));
        assert_ne!(a, b);
        assert_ne!(
            PixelSampler::new(7 ^ SEED, 40, 0).get4(0),
            PixelSampler::new(7, 40, 0).get4(0),
            "apart from the pixel's own samples"
        );
    }

    #[test]
    fn one_sample_a_pass_holds_nothing() {
        let mut off = PixelSplit::new(1, 7, 100);
        off.note(0, &[V::ONE], 3);
        assert_eq!(off.begin_pass(), None);
        assert_eq!(off.count(0), 1);
        assert!(off.further(0, 0, 4).is_empty());
        assert_eq!(off.bytes(), 0);
        assert_eq!(off.most(), 1);
    }
}
