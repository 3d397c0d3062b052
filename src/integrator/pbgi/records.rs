//! Where the caches' records go: placed coarse to fine before the first pass, refined
//! where another gather lowers the image's error most, and, for the irradiance cache,
//! added where a probe finds its interpolation wrong (see `cache` and `radiance_cache` for
//! the records themselves).

use super::irradiance_cache;
use super::irradiance_cache::{IrradianceCache, Record};
use super::microbuffer::Gradients;
use super::radiance_cache::{Light, RadianceCache};
use super::wpbgi::{self, Incident};
use super::{PbgiIntegrator, Pending, Strata};
use crate::integrator::{Pass, Scene};
use crate::material::luminance;
use crate::sampler::Hash;
use crate::trace::Tracer;
use glam::Vec3A as V;
use rayon::prelude::*;
use rustc_hash::FxHashSet;

/// Keeps the radiance records' gathers apart from the irradiance records' at one pixel.
const GLOSSY_SALT: u64 = 0x0061_055E;

/// Gathers a radiance record averages when placed, before the refinement adds more where
/// worth it. With one, the showroom's floor before the plinths was 1.5–2% dark: the
/// refinement stops early at records whose first gathers happened to agree low (their
/// light is heavy-tailed: leaf rays that meet the lit gold bunny); with 8, 0.2–0.8%.
const GLOSSY_GATHERS: u32 = 8;

/// The pixels around one.
const NEIGHBOURS: [(i32, i32); 8] = [
    (-1, -1),
    (0, -1),
    (1, -1),
    (-1, 0),
    (1, 0),
    (-1, 1),
    (0, 1),
    (1, 1),
];

/// The share of the samples' rays the cache's probes may take (`probe_cache`).
const PROBE_SHARE: f64 = 0.02;

/// How many standard deviations a probe's gather must be from the cache to be kept.
const PROBE_SIGMAS: f64 = 2.0;

/// The share of the time left in `--time`'s budget that the refinement, and then the
/// probes, may take before a pass.
const SHARE_OF_TIME_LEFT: f64 = 0.5;

impl PbgiIntegrator {
    /// The irradiance cache's records, placed coarse to fine (`coarse_to_fine`). Returns
    /// the cache and the rays traced.
    pub(super) fn build_cache(&self, scene: &Scene, a: f32) -> (IrradianceCache, u64) {
        let mut cache = IrradianceCache::new(a);
        let rays = self.coarse_to_fine(
            scene,
            &mut cache,
            |tr, cache, at| self.centre_record(scene, tr, cache, at, false),
            |cache, found| cache.extend(found),
            (IrradianceCache::bytes, |_| IrradianceCache::record_cost()),
        );
        (cache, rays)
    }

    /// The radiance cache's records, placed as the irradiance cache's are, at WPBGI's
    /// receivers. Returns the cache and the rays traced.
    pub(super) fn build_radiance_cache(&self, scene: &Scene, a: f32) -> (RadianceCache, u64) {
        let mut cache = RadianceCache::new(a);
        let rays = self.coarse_to_fine(
            scene,
            &mut cache,
            |tr, cache, at| self.centre_radiance_record(scene, tr, cache, at),
            |cache, found| cache.extend(found),
            (RadianceCache::bytes, |(_, light): &(Record, Light)| {
                IrradianceCache::record_cost() + light.bytes()
            }),
        );
        (cache, rays)
    }

    /// Records found by `find` at every 16th pixel of the window, then at the pixels of
    /// each finer grid, each level's added (`add`) once all of them are found, so that
    /// `find` sees those of the levels before. Returns the rays traced.
    fn coarse_to_fine<C: Sync, T: Send>(
        &self,
        scene: &Scene,
        cache: &mut C,
        find: impl Fn(&mut Tracer, &C, [u32; 2]) -> Option<T> + Sync,
        add: impl Fn(&mut C, Vec<T>),
        (held, cost): (impl Fn(&C) -> u64, impl Fn(&T) -> u64),
    ) -> u64 {
        let [x0, x1, y0, y1] = self.window;
        let mut rays = 0;
        let mut step = 16;
        while step >= 1 {
            let on = |v: u32, s: u32| v.is_multiple_of(s);
            let pixels: Vec<(u32, u32)> = (y0..y1)
                .flat_map(|y| (x0..x1).map(move |x| (x, y)))
                .filter(|&(x, y)| {
                    let (dx, dy) = (x - x0, y - y0);
                    on(dx, step)
                        && on(dy, step)
                        && (step == 16 || !(on(dx, 2 * step) && on(dy, 2 * step)))
                })
                .collect();
            let found: Vec<(Option<T>, u64)> = pixels
                .par_iter()
                .map_init(
                    || Tracer::new(&scene.cache),
                    |tr, &(x, y)| {
                        let before = tr.rays;
                        let rec = find(tr, cache, [x, y]);
                        (rec, tr.rays - before)
                    },
                )
                .collect();
            rays += found.iter().map(|f| f.1).sum::<u64>();
            let mut records: Vec<T> = found.into_iter().filter_map(|f| f.0).collect();
            // Under a budget, placing stops where the state's share is full: the pixels
            // left without a record gather for themselves.
            let fit = self.records_that_fit(held(cache), &records, &cost);
            let full = fit < records.len();
            records.truncate(fit);
            add(cache, records);
            if full {
                break;
            }
            step /= 2;
        }
        rays
    }

    /// A radiance record at pixel (x, y)'s first hit through its centre, where WPBGI
    /// gathers, no record covers it yet, and one at its widest reach would cover the first
    /// hits of all 8 neighbouring pixels. Elsewhere (the gold bunny's curves at a pixel's
    /// scale, a surface's edge) a record would serve little more than its own pixel, and
    /// the exact lobe rays are cheaper than its gathers: on the showroom at 20 s, records
    /// wherever 4 neighbours were covered had 1.10× the squared error. `GLOSSY_GATHERS`
    /// gathers averaged.
    fn centre_radiance_record(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        cache: &RadianceCache,
        [x, y]: [u32; 2],
    ) -> Option<(Record, Light)> {
        let q = self.centre_hit(scene, tr, x, y)?;
        if !wpbgi::gathers_wavelets(&q.s) {
            return None;
        }
        let (p, n) = (q.s.p, q.s.frame.n);
        let wo = q.s.frame.to_world(q.s.wo_l);
        let table = self.table_of(&q.s);
        if cache.lookup(p, n, wo, &table).is_some() {
            return None;
        }
        let footprint = q.at.map_or(0.0, |(_, f)| f);
        let alpha = q.s.glossy().alpha;
        let a = cache.records.a();
        let widest = RadianceCache::record(p, n, wo, V::ZERO, f32::INFINITY, alpha, footprint, a);
        let [x0, x1, y0, y1] = self.window;
        let covered = |tr: &mut Tracer, (dx, dy): (i32, i32)| {
            let (nx, ny) = (x.wrapping_add_signed(dx), y.wrapping_add_signed(dy));
            if !(x0..x1).contains(&nx) || !(y0..y1).contains(&ny) {
                return false;
            }
            self.centre_hit(scene, tr, nx, ny).is_some_and(|o| {
                let owo = o.s.frame.to_world(o.s.wo_l);
                irradiance_cache::weight(&widest, a, o.s.p, o.s.frame.n, owo).is_some()
            })
        };
        if !NEIGHBOURS.iter().all(|&d| covered(tr, d)) {
            return None;
        }
        let mut light = Light::default();
        let mut rec = None;
        for k in 0..GLOSSY_GATHERS {
            let strata = self.radiance_strata([x, y], k);
            let inc = self.gather_incident(scene, tr, &q.s, strata);
            let Some(e) = light.add(&inc) else {
                continue;
            };
            match &mut rec {
                None => {
                    rec = Some(RadianceCache::record(
                        p, n, wo, e, inc.depth, alpha, footprint, a,
                    ))
                }
                Some(r) => r.add(e, &Gradients::default()),
            }
        }
        Some((Record { at: [x, y], ..rec? }, light))
    }

    /// A record gathered at pixel (x, y)'s first hit through its centre, where it has a
    /// diffuse lobe. Placed (`probe` false) where no record covers it yet. A probe gathers
    /// where records with a spread cover it and keeps the gather as a record when it
    /// disagrees with what the cache gives there by more than `PROBE_SIGMAS` standard
    /// deviations of the difference (the records' spread of a gather and of their
    /// means): irradiance that changes faster than the records' gradients say (room's
    /// corner under the ceiling's hot spot, a band narrower than a record) is found so;
    /// the records' refinement lowers their noise, not this.
    fn centre_record(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        cache: &IrradianceCache,
        [x, y]: [u32; 2],
        probe: bool,
    ) -> Option<Record> {
        let q = self.centre_hit(scene, tr, x, y)?;
        let (p, n) = (q.s.p, q.s.frame.n);
        let covered = match probe {
            true => cache.spread(p, n).is_some(),
            false => cache.lookup(p, n).is_some(),
        };
        if q.s.bsdf.diffuse.max_element() <= 0.0 || covered != probe {
            return None;
        }
        let strata = self.record_strata([x, y], 0);
        let found = self.gather_irradiance(scene, tr, &q.s, strata, None);
        if probe && !cache.disagrees(p, n, found.0, PROBE_SIGMAS)? {
            return None;
        }
        Some(new_record(&q, [x, y], found, cache.a()))
    }

    /// The rays the passes' samples have traced: all so far but the cache's (as charged)
    /// and the bake's, left out so that a render reading a baked file makes the same image.
    fn sampled_rays(&self, pass: &Pass) -> u64 {
        let cache = self.cache_rays + self.refine_rays + self.probe_rays + self.radiance_rays;
        pass.rays.saturating_sub(self.bake_samples + cache)
    }

    /// What a gather that traced `rays` is charged, in rays: at least a ray per texel,
    /// since under the cut its splats and rasterized leaves are not rays but cost as much
    /// (sponza with the cut, counted by the rays they traced: 16,852 probes took a
    /// quarter of a 60-s render).
    fn charged(&self, rays: u64) -> u64 {
        rays.max(self.texels.upper.len() as u64)
    }

    /// What a record's gather costs, as its placement's gathers were charged on average.
    fn gather_cost(&self, cache: &IrradianceCache) -> u64 {
        self.charged(self.cache_rays / cache.len().max(1) as u64)
    }

    /// How many of `wanted` gathers the cache may make before a pass: all of them without
    /// a time budget, else those that fit in `SHARE_OF_TIME_LEFT` of the time left at
    /// the wall time its gathers have taken so far. Under the cut on sponza, the first
    /// refinement's second gather of each of 8,371 records overran a 30-s render by 12 s.
    fn affordable(&self, pass: &Pass, cache: &IrradianceCache, wanted: usize) -> usize {
        let gathers = cache.gathers() + self.probed as u64;
        affordable(pass, self.cache_s / gathers.max(1) as f64, wanted)
    }

    /// Probes (`centre_record`) at pixels the cache covers, each pixel once, in a shuffled
    /// order, with at most `PROBE_SHARE` of the samples' rays; the records they find are
    /// added.
    /// Returns the rays traced.
    pub(super) fn probe_cache(&mut self, scene: &Scene, pass: &Pass) -> u64 {
        let Some(cache) = self.irradiance_cache.as_ref() else {
            return 0;
        };
        // The records' spread is known after the second pass's refinement.
        if pass.first < 3 || self.probed >= self.probe_order.len() {
            return 0;
        }
        let allowed = (PROBE_SHARE * self.sampled_rays(pass) as f64) as u64;
        let Some(budget) = allowed.checked_sub(self.probe_rays).filter(|&b| b > 0) else {
            return 0;
        };
        let per_gather = self.gather_cost(cache);
        let wanted = budget.div_ceil(per_gather) as usize;
        let end = self
            .probe_order
            .len()
            .min(self.probed + self.affordable(pass, cache, wanted));
        let found: Vec<(Option<Record>, u64)> = self.probe_order[self.probed..end]
            .par_iter()
            .map_init(
                || Tracer::new(&scene.cache),
                |tr, &at| {
                    let before = tr.rays;
                    let rec = self.centre_record(scene, tr, cache, at, true);
                    (rec, tr.rays - before)
                },
            )
            .collect();
        self.probed = end;
        let rays: u64 = found.iter().map(|f| f.1).sum();
        let cost: u64 = found.iter().map(|f| self.charged(f.1)).sum();
        let mut records: Vec<Record> = found.into_iter().filter_map(|f| f.0).collect();
        // Under a budget the records stop where the state's share is full.
        let fit = self.records_that_fit(0, &records, |_| IrradianceCache::record_cost());
        records.truncate(fit);
        self.probe_records += records.len() as u64;
        if let Some(cache) = self.irradiance_cache.as_mut() {
            cache.reserve_exact(records.len());
            cache.extend(records);
        }
        self.probe_rays += cost;
        rays
    }

    /// Another gather for record `rec`, at its pixel's first hit again (the `k`-th, so
    /// its rays are new): its irradiance and gradients, or None when that hit is gone.
    fn regather(&self, scene: &Scene, tr: &mut Tracer, rec: &Record) -> Option<(V, Gradients)> {
        let q = self.centre_hit(scene, tr, rec.at[0], rec.at[1])?;
        let strata = self.record_strata(rec.at, rec.y.count as u32);
        let (e, _, g) = self.gather_irradiance(scene, tr, &q.s, strata, None);
        Some((e, g))
    }

    /// The window's pixels that hold no record, shuffled: the order `probe_cache` visits
    /// them in, so that its first probes spread over the whole image.
    pub(super) fn probe_order(&self) -> Vec<[u32; 2]> {
        let [x0, x1, y0, y1] = self.window;
        let held: FxHashSet<[u32; 2]> = self
            .irradiance_cache
            .iter()
            .flat_map(|c| c.records().iter().map(|r| r.at))
            .collect();
        let mut order: Vec<[u32; 2]> = (y0..y1)
            .flat_map(|y| (x0..x1).map(move |x| [x, y]))
            .filter(|at| !held.contains(at))
            .collect();
        let key = |&[x, y]: &[u32; 2]| Hash::new((y as u64) << 32 | x as u64 ^ 0x9B0B).u64();
        order.sort_by_cached_key(key);
        order
    }

    /// The `index`-th gather of the record at pixel `at`.
    fn record_strata(&self, at: [u32; 2], index: u32) -> Strata {
        let pixel = (at[1] as u64) << 32 | at[0] as u64;
        Strata {
            seed: Hash::new(pixel ^ (self.seed as u64) << 48 ^ 0xCAC4E).u64(),
            index,
        }
    }

    /// The records of `cache` worth another gather of `per_gather` rays (see
    /// `refine_cache`), from the second pass on.
    fn worth_refining(&self, pass: &Pass, cache: &IrradianceCache, per_gather: f64) -> Vec<usize> {
        let n = pass.first as f64;
        if pass.first < 2 || cache.is_empty() {
            return Vec::new();
        }
        let pass_rays = (self.sampled_rays(pass) as f64 / n).max(1.0);
        let pixels = self.window_pixels() as f64;
        cache.worth_refining(pass.variance / (n * (n + 1.0)) / pass_rays * per_gather * pixels)
    }

    /// One more gather each for the radiance records worth it, as `refine_cache` chooses
    /// them. Returns the rays traced.
    pub(super) fn refine_radiance(&mut self, scene: &Scene, pass: &Pass) -> u64 {
        let Some(cache) = self.radiance_cache.as_ref() else {
            return 0;
        };
        let gathers = cache.records.gathers().max(1);
        let per_gather = self.radiance_rays as f64 / gathers as f64;
        let mut ids = self.worth_refining(pass, &cache.records, per_gather);
        ids.truncate(affordable(
            pass,
            self.radiance_s / gathers as f64,
            ids.len(),
        ));
        if ids.is_empty() {
            return 0;
        }
        let found: Vec<(Option<Incident>, u64)> = ids
            .par_iter()
            .map_init(
                || Tracer::new(&scene.cache),
                |tr, &id| {
                    let before = tr.rays;
                    let rec = &cache.records.records()[id];
                    let inc = self.centre_hit(scene, tr, rec.at[0], rec.at[1]).map(|q| {
                        let strata = self.radiance_strata(rec.at, rec.y.count as u32);
                        self.gather_incident(scene, tr, &q.s, strata)
                    });
                    (inc, tr.rays - before)
                },
            )
            .collect();
        let rays: u64 = found.iter().map(|f| f.1).sum();
        if let Some(cache) = self.radiance_cache.as_mut() {
            for (&id, (inc, _)) in ids.iter().zip(&found) {
                if let Some(inc) = inc {
                    cache.add(id, inc);
                }
            }
        }
        self.radiance_rays += rays;
        rays
    }

    /// The `index`-th gather of the radiance record at pixel `at`.
    fn radiance_strata(&self, at: [u32; 2], index: u32) -> Strata {
        let strata = self.record_strata(at, index);
        Strata {
            seed: strata.seed ^ GLOSSY_SALT,
            ..strata
        }
    }

    /// One more gather each for the records worth it: those whose gather lowers the
    /// image's squared error more per ray than another pass of samples would. A pass of n
    /// samples per pixel lowers it by V/(n(n+1)) (V: one sample's variance, from the film)
    /// for the rays a pass has cost; a gather on a record by its [`Record::gain`] times
    /// its lobe squared, over the pixels, for a gather's rays. So the records' share of
    /// the rays follows how noisy they are against the pixels: on sponza a fixed tenth was
    /// best and a fifth cost 8%; on the showroom, whose records see its steel floor through
    /// light samples, a third was 1.5× better than a tenth.
    pub(super) fn refine_cache(&mut self, scene: &Scene, pass: &Pass) -> u64 {
        let Some(cache) = self.irradiance_cache.as_ref() else {
            return 0;
        };
        let mut ids = self.worth_refining(pass, cache, self.gather_cost(cache) as f64);
        ids.truncate(self.affordable(pass, cache, ids.len()));
        if ids.is_empty() {
            return 0;
        }
        let found: Vec<(Option<(V, Gradients)>, u64)> = ids
            .par_iter()
            .map_init(
                || Tracer::new(&scene.cache),
                |tr, &id| {
                    let before = tr.rays;
                    let e = self.regather(scene, tr, &cache.records()[id]);
                    (e, tr.rays - before)
                },
            )
            .collect();
        let rays: u64 = found.iter().map(|f| f.1).sum();
        let cost: u64 = found.iter().map(|f| self.charged(f.1)).sum();
        if let Some(cache) = self.irradiance_cache.as_mut() {
            for (&id, (e, _)) in ids.iter().zip(&found) {
                if let Some((e, g)) = e {
                    cache.add(id, *e, g);
                }
            }
        }
        self.refine_rays += cost;
        rays
    }
}

/// The record of a gather (irradiance, reach distance, gradients) at receiver `q`, the
/// first hit through pixel `at`'s centre.
fn new_record(q: &Pending, at: [u32; 2], (e, distance, g): (V, f32, Gradients), a: f32) -> Record {
    let footprint = q.at.map_or(0.0, |(_, f)| f);
    let rec = Record::new(q.s.p, q.s.frame.n, e, distance, footprint, a);
    Record {
        at,
        g,
        lobe: luminance(q.s.diffuse_lobe()),
        ..rec
    }
}

/// How many of `wanted` gathers of `per_gather` seconds each fit before a pass: all of
/// them without a time budget, else those that fit in `SHARE_OF_TIME_LEFT` of the time
/// left. Under the cut on sponza, the first refinement's second gather of each of 8,371
/// records overran a 30-s render by 12 s.
fn affordable(pass: &Pass, per_gather: f64, wanted: usize) -> usize {
    let Some(left) = pass.left else {
        return wanted;
    };
    let fits = SHARE_OF_TIME_LEFT * left.as_secs_f64() / per_gather.max(f64::MIN_POSITIVE);
    wanted.min(fits as usize)
}
