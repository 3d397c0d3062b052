//! How many (light sample, lobe ray) pairs for direct light and how many rays for the
//! glossy bounce a glossy receiver takes, per pixel, from the spread of the pixel's
//! earlier samples: splitting where the lobes' estimates scatter (a highlight's edge, the
//! panel's reflection), K elsewhere.
//!
//! Splitting's optimum: a sample whose split part has variance v and cost c per split,
//! and the rest variance v_r and cost c_r, has variance × cost (v_r + v / n)(c_r + n c),
//! least at n = √((v / c) / (v_r / c_r)). Here v is the half squared difference of a
//! receiver's first two estimates, v_r the image's mean variance of one sample (a
//! pixel's rest is not measured apart from its direct light), and c_r / c a constant,
//! `GAIN`. v is pooled over the pixel and its eight neighbours: the bounce's light is
//! heavy-tailed where it meets a small bright thing (the floor's reflection of the gold
//! bunny's highlights), and one pixel's few samples seldom see the rare large values that
//! make its variance, where its neighbours' together do. A pixel's counts come only from
//! earlier samples, never from the sample they are spent on, so each estimate stays
//! unbiased.

use crate::material::luminance;
use glam::Vec3A as V;
use std::sync::{Mutex, PoisonError};

/// c_r / c in the optimum's √(κ v / v_r): on the showroom at 60 s, κ 4, 8 and 16 gave
/// c = RMSE·√s of 1.27e-2, 1.23e-2 and 1.28e-2 (docs/pbgi.md).
const GAIN: f32 = 8.0;

/// Samples of a pixel's and its neighbours' glossy receivers, together, before their
/// spread decides anything.
const AFTER: u32 = 4;

/// Σ over a pixel's samples of the half squared difference of two estimates, and their
/// number.
#[derive(Default, Clone, Copy)]
struct Spread {
    sum: f32,
    count: u32,
}

impl Spread {
    fn add(&mut self, o: Spread) {
        self.sum += o.sum;
        self.count += o.count;
    }
}

#[derive(Default, Clone, Copy)]
struct Pixel {
    direct: Spread,
    bounce: Spread,
}

/// Which of a glossy receiver's estimates.
#[derive(Clone, Copy)]
pub(super) enum Part {
    /// Direct light: the mean of its (light sample, lobe ray) pairs.
    Direct,
    /// The glossy bounce: the mean of its lobe rays' light.
    Bounce,
}

/// Per pixel, the spread of its glossy receivers' estimates.
#[derive(Default)]
pub(super) struct Split {
    /// Most pairs or rays one receiver takes (`--pbgi-split`).
    most: u32,
    /// Whether direct light's pairs split too, not only the bounce's rays.
    direct: bool,
    /// The window's width: pixel `at` is at (at mod width, at / width).
    width: usize,
    pixels: Vec<Mutex<Pixel>>,
    /// Per pixel, its spreads and its eight neighbours' summed, at the pass's start.
    pooled: Vec<Pixel>,
    /// The mean over pixels of one sample's luminance variance, at the pass's start.
    mean_variance: f32,
}

/// Pairs for direct light and rays for the bounce one receiver takes.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct Counts {
    pub(super) direct: u32,
    pub(super) bounce: u32,
}

impl Counts {
    /// `k` of each.
    pub(super) fn both(k: u32) -> Counts {
        Counts {
            direct: k,
            bounce: k,
        }
    }
}

impl Split {
    /// Splits up to `most` over a window of `width` × `height` pixels, for receivers that
    /// take `k` of each; none unless `most` exceeds `k` and `k` is 2 or more (two
    /// estimates give a spread).
    /// `direct`: direct light's pairs split as well as the bounce's rays. Where a pixel
    /// takes more first hits (`pixel_split.rs`) they do not: on the showroom at 20 s,
    /// seeds 1 and 2, splitting them too raised the RMSE by 4–7% at every κ tried.
    pub(super) fn new(most: u32, k: u32, [width, height]: [usize; 2], direct: bool) -> Split {
        let pixels = match most > k && k > 1 {
            true => (0..width * height).map(|_| Mutex::default()).collect(),
            false => Vec::new(),
        };
        Split {
            most,
            direct,
            width,
            pixels,
            pooled: Vec::new(),
            mean_variance: 0.0,
        }
    }

    /// Most pairs or rays one receiver takes; 0 where nothing splits.
    pub(super) fn most(&self) -> u32 {
        match self.pixels.is_empty() {
            true => 0,
            false => self.most,
        }
    }

    /// Whether direct light's pairs split, not only the bounce's rays.
    pub(super) fn splits_direct(&self) -> bool {
        self.direct
    }

    /// Before a pass: the image's mean variance of one sample so far; the pixels' spreads
    /// are pooled with their neighbours' for the pass.
    pub(super) fn begin_pass(&mut self, mean_variance: f64) {
        self.mean_variance = mean_variance as f32;
        if self.pixels.is_empty() {
            return;
        }
        let own: Vec<Pixel> = self
            .pixels
            .iter()
            .map(|p| *p.lock().unwrap_or_else(PoisonError::into_inner))
            .collect();
        let (w, h) = (self.width, own.len() / self.width);
        self.pooled = (0..own.len())
            .map(|at| {
                let (x, y) = (at % w, at / w);
                let mut sum = Pixel::default();
                for yy in y.saturating_sub(1)..(y + 2).min(h) {
                    for xx in x.saturating_sub(1)..(x + 2).min(w) {
                        let o = own[yy * w + xx];
                        sum.direct.add(o.direct);
                        sum.bounce.add(o.bounce);
                    }
                }
                sum
            })
            .collect();
    }

    /// The counts for a receiver of pixel `at` that takes `k` of each at least, from the
    /// spreads pooled at the pass's start.
    pub(super) fn counts(&self, at: usize, k: u32) -> Counts {
        let Some(px) = self.pooled.get(at) else {
            return Counts::both(k);
        };
        let n = |s: Spread| {
            if s.count < AFTER || self.mean_variance <= 0.0 {
                return k;
            }
            let v = s.sum / s.count as f32;
            let n = (GAIN * v / self.mean_variance).sqrt().ceil();
            // NaN (a non-finite spread) takes k.
            (n.min(self.most as f32) as u32).max(k)
        };
        Counts {
            direct: match self.direct {
                true => n(px.direct),
                false => k,
            },
            bounce: n(px.bounce),
        }
    }

    /// Records a receiver of pixel `at`: `a` and `b`, its first two estimates of `part`.
    pub(super) fn note(&self, at: usize, part: Part, a: V, b: V) {
        let Some(slot) = self.pixels.get(at) else {
            return;
        };
        let d = luminance(a) - luminance(b);
        if !d.is_finite() {
            return;
        }
        let mut px = slot.lock().unwrap_or_else(PoisonError::into_inner);
        let s = match part {
            Part::Direct => &mut px.direct,
            Part::Bounce => &mut px.bounce,
        };
        s.sum += 0.5 * d * d;
        s.count += 1;
    }

    /// Bytes held from the first pass on: the pixels' spreads and their pooled copy.
    pub(super) fn bytes(&self) -> u64 {
        (self.pixels.len() * (size_of::<Mutex<Pixel>>() + size_of::<Pixel>())) as u64
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_pixel_splits_in_proportion_to_the_root_of_its_spread_and_only_after_its_first_samples() {
        // A row of four pixels: 0 and 3 are not neighbours.
        let mut split = Split::new(32, 2, [4, 1], true);
        let k = 2;
        // Pixel 0: estimates 0 and 1 apart in luminance (spread 0.5); pixel 3 agrees.
        for i in 0..AFTER {
            split.begin_pass(0.01);
            assert_eq!(split.counts(0, k).direct, k, "after {i} samples");
            split.note(0, Part::Direct, V::ZERO, V::ONE);
            split.note(3, Part::Direct, V::ONE, V::ONE);
            split.note(3, Part::Bounce, V::ONE, V::ONE);
        }
        assert_eq!(split.counts(0, k).direct, k, "until the next pass starts");
        split.begin_pass(0.01);
        let c = split.counts(0, k);
        // √(8 · 0.5 / 0.01) = 20.
        assert_eq!(c.direct, 20);
        assert_eq!(c.bounce, k, "the bounce has no samples of its own");
        assert_eq!(split.counts(3, k), Counts::both(k));
        split.begin_pass(0.0001);
        assert_eq!(split.counts(0, k).direct, 32, "capped at --pbgi-split");
        assert_eq!(split.counts(7, k).direct, k, "outside the window");
        assert!(split.bytes() > 0);
        for mut off in [
            Split::new(2, 2, [2, 1], true),
            Split::new(32, 1, [2, 1], true),
        ] {
            off.begin_pass(0.01);
            assert_eq!(off.counts(0, 2), Counts::both(2));
            assert_eq!(off.bytes(), 0);
        }
    }

    #[test]
    fn a_pixel_takes_its_neighbours_spread_and_not_a_farther_pixels() {
        // A 5 × 5 window whose centre's bounce once scattered (spread 0.5 in one of 9
        // notes); every other pixel agrees at each of its samples.
        let mut split = Split::new(32, 2, [5, 5], false);
        let centre = 12;
        for at in 0..25 {
            for i in 0..9 {
                let b = if at == centre && i == 0 {
                    V::ONE
                } else {
                    V::ZERO
                };
                split.note(at, Part::Bounce, V::ZERO, b);
            }
        }
        split.begin_pass(0.01);
        // A neighbour of the centre (pixel 6, up and left) pools 81 notes with one spread
        // of 0.5: √(8 · (0.5 / 81) / 0.01) = 2.2, so 3. So does the centre itself.
        for at in [6, 7, 11, 13, centre, 18] {
            assert_eq!(split.counts(at, 2).bounce, 3, "pixel {at}");
        }
        // Two pixels away from it, none of the spread reaches.
        for at in [0, 2, 10, 14, 24] {
            assert_eq!(split.counts(at, 2).bounce, 2, "pixel {at}");
        }
    }

    #[test]
    fn without_direct_splitting_only_the_bounce_splits() {
        let mut split = Split::new(32, 2, [1, 1], false);
        for _ in 0..AFTER {
            split.note(0, Part::Direct, V::ZERO, V::ONE);
            split.note(0, Part::Bounce, V::ZERO, V::ONE);
        }
        split.begin_pass(0.01);
        let c = split.counts(0, 2);
        assert_eq!(c.direct, 2, "direct light keeps K pairs");
        assert_eq!(c.bounce, 20, "√(8 · 0.5 / 0.01)");
    }
}
