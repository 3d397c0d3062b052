//! Gathers shared between the samples of a pixel: each surface of a pixel gathers at its
//! period, its other samples take the mean of its gathers once the render ends.

use super::gather::Strata;
use super::receiver::Pending;
use super::surface::Surface;
use super::PbgiIntegrator;
use crate::sampler::Hash;
use crate::trace::{offset_origin, Ray, Tracer};
use glam::Vec3A as V;
use std::sync::atomic::Ordering::Relaxed;
use std::sync::PoisonError;

/// Irradiance gathers summed at one surface of a pixel.
#[derive(Clone, Copy)]
pub(super) struct Gathered {
    /// The first gather's point and shading normal.
    pub(super) p: V,
    pub(super) n: V,
    pub(super) sum: V,
    /// Gathers summed in `sum`.
    pub(super) gathers: u32,
    /// Samples that landed on it: it gathers at every `period`-th (at its pixel's
    /// phase), and the pixel's first surface also at its first, so a surface's gathers
    /// are in proportion to its share of the pixel's samples. One that has none yet
    /// takes those of the surface whose normal is closest ([`crate::integrator::Integrator::held_back`]).
    pub(super) samples: u32,
    /// Σ path weight × diffuse lobe of the samples that take this surface's irradiance:
    /// they are given the mean of all its gathers once the render ends
    /// ([`crate::integrator::Integrator::held_back`]), not the mean of those made so far, which weighed a
    /// pixel's first gathers most (on room at 8 gathers a pixel, as if it had 4.8).
    pub(super) weight: V,
    /// Its gathers are WPBGI's glossy light, not irradiance.
    pub(super) glossy: bool,
}

impl Gathered {
    /// Whether a receiver at `p` with normal `n` lies on this surface: normals within
    /// 14° and `p` within `footprint` of its tangent plane, the gathers of the same kind.
    pub(super) fn holds(&self, p: V, n: V, footprint: f32, glossy: bool) -> bool {
        self.glossy == glossy
            && self.n.dot(n) >= SAME_NORMAL
            && (p - self.p).dot(self.n).abs() <= footprint
    }
}

/// Most samples of a pixel's surface that share one of WPBGI's glossy gathers.
pub(super) const GLOSSY_PERIOD: u64 = 8;

/// Samples of each pixel whose cached receivers are checked for a surface over them.
pub(super) const PROBED_SAMPLES: u32 = 16;

/// Surfaces a pixel keeps gathers for; samples on others gather without keeping them.
pub(super) const SURFACES_PER_PIXEL: usize = 8;

/// Two hits share gathers only when their shading normals are this close (14°).
pub(super) const SAME_NORMAL: f32 = 0.97;

/// Whether a surface lies over `s` within `reach` along its normal.
pub(super) fn covered_over(tr: &mut Tracer, s: &Surface, reach: f32) -> bool {
    let n = s.frame.n;
    tr.occluded(&Ray {
        o: offset_origin(s.p, s.err, s.ng, n),
        d: n,
        t_max: reach,
    })
}

/// Where a receiver's irradiance comes from.
#[derive(Clone, Copy)]
pub(super) enum Reuse {
    /// The cache's, at the receiver.
    Cached(V),
    /// The mean of (window) pixel's gathers on one of its surfaces, by index: given once
    /// the render ends.
    Pixel(usize, usize),
    /// A gather of its own, this point of its surface's sequence.
    Gather(Strata),
}

/// A receiver's light from its pixel, past the cache: the pixel's gathers on its surface
/// (by pixel and surface index), or a gather of its own.
pub(super) enum InPixel {
    Lend(usize, usize),
    Gather(Strata),
}

impl From<InPixel> for Reuse {
    fn from(r: InPixel) -> Reuse {
        match r {
            InPixel::Lend(pixel, at) => Reuse::Pixel(pixel, at),
            InPixel::Gather(strata) => Reuse::Gather(strata),
        }
    }
}

impl PbgiIntegrator {
    /// The irradiance the cache holds at the receiver when nothing is over it within the
    /// records' reach; else a gather of its own when its sample is its pixel's first or
    /// falls at `--pbgi-reuse`'s period (at the pixel's phase); else
    /// its surface's gathers, or, when the pixel keeps no more surfaces, those of the one
    /// whose normal is closest to its own. A later surface's first gather waits for its
    /// phase like the others: gathering at first sight doubled the gathers of a 60-s
    /// render of sponza under the cut, whose gathers cost 1.6 ms each, for surfaces a few
    /// samples hit.
    pub(super) fn reuse(&self, tr: &mut Tracer, q: &Pending) -> Reuse {
        if let Some((e, reach)) = self
            .irradiance_cache
            .as_ref()
            .and_then(|c| c.lookup(q.s.p, q.s.frame.n))
        {
            // A receiver with a surface over it nearer than the records' reach sits in a
            // crevice they did not see (the gap between a ceiling and a lamp hung just
            // below it, which the camera sees into at a grazing angle): it is left to
            // gather for itself.
            if !self.probes(q) || !covered_over(tr, &q.s, reach) {
                return Reuse::Cached(e);
            }
            if let Some(f) = q.at.and_then(|(pixel, _)| self.crevices.get(pixel)) {
                f.store(true, Relaxed);
            }
            self.tally.cache_rejects.fetch_add(1, Relaxed);
        }
        self.reuse_in_pixel(q, false).into()
    }

    /// A gather of the receiver's own, or its pixel's gathers on its surface, as `reuse`
    /// decides past the cache; `glossy`: of WPBGI's glossy light.
    pub(super) fn reuse_in_pixel(&self, q: &Pending, glossy: bool) -> InPixel {
        let Some((pixel, footprint)) = q.at else {
            return InPixel::Gather(Strata {
                seed: q.key,
                index: 0,
            });
        };
        let Some(slot) = self.gathered.get(pixel) else {
            // `--pbgi-reuse 1`: every sample gathers, the pixel's n-th sample its n-th.
            return InPixel::Gather(self.pixel_strata(pixel, 0, q.sample));
        };
        let mut list = slot.lock().unwrap_or_else(PoisonError::into_inner);
        let n = q.s.frame.n;
        match list
            .iter()
            .position(|g| g.holds(q.s.p, n, footprint, glossy))
        {
            Some(i) => {
                let g = &mut list[i];
                // One period whatever the gathers read: set by the spread of a surface's
                // first gathers (splitting's optimum, 1 to R), it sampled more where they
                // had caught a bright tail and left the rest low (caustics with the cache
                // off, 256 spp, seeds 1–3: −1.06%, −1.19%, −1.44% against −0.05%, −0.30%,
                // −0.72% at a fixed 8). WPBGI's glossy gathers keep 8: their light is
                // heavy-tailed (the showroom's floor −0.9% at 64 spp with the spread's
                // period against −0.05%). Irradiance gathers take R: at 60 s on sponza, R 8
                // gave 29 spp and RMSE 1.27e-2, R 64 47 spp and 1.15e-2 (the showroom
                // 5.66e-3 and 5.97e-3).
                let period = match glossy {
                    true => (self.settings.reuse as u64).min(GLOSSY_PERIOD),
                    false => self.settings.reuse as u64,
                };
                let k = g.samples as u64;
                g.samples += 1;
                // Each pixel's later gathers fall at its own phase of the period, so a pass
                // does about 1/period of the pixels' gathers instead of all of them every
                // period-th pass.
                if (k + self.phase(pixel)).is_multiple_of(period) {
                    return InPixel::Gather(self.pixel_strata(pixel, i, g.gathers));
                }
                InPixel::Lend(pixel, i)
            }
            None if list.is_empty() => InPixel::Gather(self.pixel_strata(pixel, 0, 0)),
            None if list.len() < self.surfaces_per_pixel => {
                list.push(Gathered {
                    p: q.s.p,
                    n,
                    sum: V::ZERO,
                    gathers: 0,
                    samples: 1,
                    weight: V::ZERO,
                    glossy,
                });
                let i = list.len() - 1;
                if self.phase(pixel) == 0 {
                    return InPixel::Gather(self.pixel_strata(pixel, i, 0));
                }
                InPixel::Lend(pixel, i)
            }
            None => {
                let closest = (0..list.len())
                    .filter(|&a| list[a].glossy == glossy)
                    .max_by(|&a, &b| list[a].n.dot(n).total_cmp(&list[b].n.dot(n)));
                match closest {
                    Some(i) => InPixel::Lend(pixel, i),
                    None => InPixel::Gather(self.pixel_strata(pixel, list.len(), 0)),
                }
            }
        }
    }

    /// Adds `weight` to the weight of the pixel's `at`-th surface's gathers: the sample
    /// takes their mean once the render ends.
    pub(super) fn lend(&self, pixel: usize, at: usize, weight: V) {
        self.tally.reused.fetch_add(1, Relaxed);
        if let Some(slot) = self.gathered.get(pixel) {
            let mut list = slot.lock().unwrap_or_else(PoisonError::into_inner);
            if let Some(g) = list.get_mut(at) {
                g.weight += weight;
            }
        }
    }

    /// The `index`-th gather on the `surface`-th surface a pixel keeps gathers for: each
    /// surface's gathers are a sequence of their own.
    pub(super) fn pixel_strata(&self, pixel: usize, surface: usize, index: u32) -> Strata {
        let key = pixel as u64 ^ (self.seed as u64) << 32 ^ (surface as u64) << 56;
        Strata {
            seed: Hash::new(key ^ 0x5EED).u64(),
            index,
        }
    }

    /// Pixel `pixel`'s phase in `--pbgi-reuse`'s period R: its gathers after the first
    /// fall at the samples s with s + phase a multiple of R.
    pub(super) fn phase(&self, pixel: usize) -> u64 {
        let r = self.settings.reuse as u64;
        Hash::new(pixel as u64 ^ (self.seed as u64) << 32).u64() % r
    }

    /// Whether a cached receiver is to be checked for a surface over it: in its pixel's
    /// first `PROBED_SAMPLES` samples, and in every later one where such a check found
    /// one. A pixel's samples run one per pass, so the flag is the same whatever the
    /// thread count.
    pub(super) fn probes(&self, q: &Pending) -> bool {
        let flag = q.at.and_then(|(pixel, _)| self.crevices.get(pixel));
        q.sample < PROBED_SAMPLES || flag.is_some_and(|f| f.load(Relaxed))
    }

    /// Adds a gather's irradiance `e` to its pixel's surface, with `weight` for the sample
    /// that made it (see [`Gathered::weight`]); false when the pixel keeps no gathers or
    /// none more, and the sample is to take `e` itself.
    pub(super) fn keep(&self, q: &Pending, e: V, weight: V, glossy: bool) -> bool {
        let Some((pixel, footprint)) = q.at else {
            return false;
        };
        let Some(slot) = self.gathered.get(pixel) else {
            return false;
        };
        let mut list = slot.lock().unwrap_or_else(PoisonError::into_inner);
        let (p, n) = (q.s.p, q.s.frame.n);
        let full = list.len() >= self.surfaces_per_pixel;
        match list.iter_mut().find(|g| g.holds(p, n, footprint, glossy)) {
            Some(g) => {
                g.sum += e;
                g.gathers += 1;
                g.weight += weight;
            }
            None if !full => list.push(Gathered {
                p,
                n,
                sum: e,
                gathers: 1,
                samples: 1,
                weight,
                glossy,
            }),
            None => return false,
        }
        true
    }

    /// The gathers kept per pixel.
    pub(super) fn held_back_gathers(&self) -> Vec<(usize, V)> {
        let pixel = |list: &Vec<Gathered>| {
            let mean = |g: &Gathered| {
                let gathered = list
                    .iter()
                    .filter(|o| o.gathers > 0 && o.glossy == g.glossy);
                let closest = gathered.max_by(|a, b| a.n.dot(g.n).total_cmp(&b.n.dot(g.n)));
                let from = if g.gathers > 0 { Some(g) } else { closest };
                from.map_or(V::ZERO, |o| g.weight * o.sum / o.gathers as f32)
            };
            list.iter().map(mean).sum::<V>()
        };
        let lists = self
            .gathered
            .iter()
            .map(|slot| pixel(&slot.lock().unwrap_or_else(PoisonError::into_inner)));
        lists.enumerate().filter(|(_, l)| *l != V::ZERO).collect()
    }
}
