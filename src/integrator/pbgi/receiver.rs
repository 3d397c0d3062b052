//! The camera path to the receiver: smooth bounces followed exactly, direct light, the rough
//! lobes' rays and their split, and the receiver left for the gather.

use super::super::direct::escaped_light;
use super::super::surface::{hole_number, scattering_hit, Missed, Scatter};
use super::super::{on_side, roulette, Counters, PixelSample, Scene};
use super::surface::{LobeRay, Surface};
use super::{split, wpbgi, PbgiIntegrator};
use crate::material::{Bsdf, BsdfSample};
use crate::sampler::{Hash, PixelSampler};
use crate::trace::{offset_origin, Ray, Tracer};
use glam::Vec3A as V;
use std::sync::atomic::Ordering::Relaxed;

/// Smooth bounces followed before giving up on a path: a bound against closed mirrors
/// only, as Russian roulette and refraction out end nearly every path long before (a ray
/// grazing a glass sphere reflects inside it a dozen times and more).
pub(super) const SMOOTH_DEPTH: u32 = 1024;

/// The emission seen at a camera ray's first hit, for the edge rays.
pub(super) fn seen_emission(scene: &Scene, tr: &mut Tracer, r: &Ray, c: &mut Counters) -> V {
    let mut ray = *r;
    let hit = match scattering_hit(scene, tr, &mut ray, hole_number(r.d), &mut 0) {
        Ok(hit) => hit,
        Err(Missed::Left) => return c.finite(escaped_light(scene, r.d, None)),
        Err(Missed::Degenerate) => return V::ZERO,
    };
    Surface::at(scene, &hit.hit, r.d).map_or(V::ZERO, |s| c.finite(s.emitted))
}

/// A receiver whose indirect bounce is still to be gathered.
pub(super) struct Pending {
    pub(super) s: Surface,
    /// The rays sampled from x's rough specular lobes for its bounce (`--pbgi-glossy-rays`,
    /// or more by `--pbgi-split`; None where it has none, or where a sample left below the
    /// surface), each with the pixel sequence's numbers for shading its hit.
    pub(super) rays: Vec<(Option<LobeRay>, [f32; 6])>,
    /// Path weight from the camera to x.
    pub(super) beta: V,
    /// Seed of its exact rays.
    pub(super) key: u64,
    /// Its pixel and the pixel's width at x, for sharing gathers; None in the bake.
    pub(super) at: Option<(usize, f32)>,
    /// Its sample number in the pixel.
    pub(super) sample: u32,
    /// Its glossy bounce from the radiance cache's records, where they cover it.
    pub(super) cached: Option<V>,
}

/// Sets a pixel's further samples' exact rays apart (`first_hit_own`).
pub(super) const FURTHER_SALT: u64 = 0x6a09_e667_f3bc_c908;

impl PbgiIntegrator {
    /// Radiance along the camera ray up to the receiver x, the first non-specular hit:
    /// emission seen and direct light; and x with the path weight to it, when one bounce
    /// of indirect light is still to be gathered there. The emission seen at the primary
    /// hit goes through the edge rays.
    pub(super) fn first_hit(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        px: &PixelSample,
        c: &mut Counters,
    ) -> (V, Option<Pending>) {
        let (l, pending, own) = self.first_hit_own(scene, tr, px);
        let seen = |tr: &mut Tracer, r: &Ray, c: &mut Counters| seen_emission(scene, tr, r, c);
        (
            l + self.edge.emission(scene, tr, px, own, c, &seen),
            pending,
        )
    }

    /// `first_hit` with the emission seen at the primary hit apart (the third value).
    pub(super) fn first_hit_own(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        px: &PixelSample,
    ) -> (V, Option<Pending>, V) {
        // A further sample's exact rays are set apart from its pass sample's.
        let salt = px
            .further
            .map_or(0, |i| Hash::new(i as u64 ^ FURTHER_SALT).u64());
        let (mut ray, mut beta, mut l, mut own) = (px.ray, V::ONE, V::ZERO, V::ZERO);
        // Alpha holes pass as the path tracer passes them, with its numbers.
        let mut passes = 0;
        for depth in 0..SMOOTH_DEPTH {
            // The next bounce's set: its first number also decides alpha holes.
            let [ud0, ud1, u_rr, _] = px.sampler.get4(2 * depth + 2);
            let (hit, travelled) = match scattering_hit(scene, tr, &mut ray, ud0, &mut passes) {
                Ok(Scatter { hit, travelled, .. }) => (hit, travelled),
                Err(missed) => {
                    // Camera rays and smooth bounces see the environment whole.
                    let sky = match missed {
                        Missed::Left => escaped_light(scene, ray.d, None),
                        Missed::Degenerate => V::ZERO,
                    };
                    match depth {
                        0 => own = sky,
                        _ => l += beta * sky,
                    }
                    break;
                }
            };
            let Some(s) = Surface::at(scene, &hit, ray.d) else {
                break;
            };
            beta *= s.through(travelled + hit.t * ray.d.length());
            match depth {
                0 => own = s.emitted,
                _ => l += beta * s.emitted,
            }
            if scene.last_segment(depth) || s.absorbs {
                break;
            }
            let [u_pick, ul0, ul1, u_lobe] = px.sampler.get4(2 * depth + 1);
            let u_lobe = match lobes(&s.bsdf, s.wo_l, u_lobe, [ud0, ud1]) {
                Lobes::Here { scale, u_lobe } => {
                    beta *= scale;
                    u_lobe
                }
                Lobes::Follow(bs) => {
                    let Some(bs) = bs else {
                        break;
                    };
                    let wi = s.frame.to_world(bs.wi).normalize();
                    if !on_side(&s.frame, s.n, wi) {
                        break;
                    }
                    beta *= bs.weight;
                    // Russian roulette after the second bounce, as the path tracer's.
                    if depth > 0 && !roulette(&mut beta, || u_rr) {
                        break;
                    }
                    ray = Ray {
                        o: offset_origin(s.p, s.err, s.ng, wi),
                        d: wi,
                        t_max: f32::INFINITY,
                    };
                    continue;
                }
            };
            let key = ((px.at as u64) << 20 ^ px.index as u64) ^ (self.seed as u64) << 52 ^ salt;
            // The pixel's own sequence (`ud0`, `ud1`), as the path tracer's next bounce
            // would take it.
            let rough = s.has_rough_lobes();
            let lobe = match rough {
                true => s.lobe_ray(scene, tr, [u_lobe, ud0, ud1]),
                false => None,
            };
            let mut direct = s.direct(scene, tr, [u_pick, ul0, ul1], lobe.as_ref());
            // Each lobe ray is kept with the numbers for shading its hit: the first's from
            // the pixel's next two sets. A receiver without rough lobes has none (and no
            // glossy bounce), so it draws no numbers for one.
            let mut rays = Vec::new();
            if rough {
                let [a, b, c, d] = px.sampler.get4(2 * depth + 3);
                let [e, f, ..] = px.sampler.get4(2 * depth + 4);
                rays.push((lobe, [a, b, c, d, e, f]));
            }
            // A glossy receiver's other lobe rays, each paired with a light sample for
            // direct light: three sets of the pixel's sequence past those of the first.
            // The first `bounce` carry the bounce, the first `direct` direct light.
            let split::Counts { direct: n, bounce } = match rough {
                true => self.split.counts(px.at, self.glossy_rays),
                false => split::Counts::both(1),
            };
            // WPBGI gathers the reflected bounce, or the radiance cache holds it: lobe
            // rays would serve only a rough dielectric's transmission.
            let cached = self.radiance_lookup(&s);
            let reflects = s.bsdf.trans == 0.0;
            let bounce = match (self.gathers_wavelets(&s) || cached.is_some()) && reflects {
                true => 1,
                false => bounce,
            };
            let (mut sum, mut second) = (direct, V::ZERO);
            for k in 1..n.max(bounce) {
                let set = 2 * depth + 5 + 3 * (k - 1);
                let [u0, u1, u2, p0] = px.sampler.get4(set);
                let [a, b, c, d] = px.sampler.get4(set + 1);
                let [e, f, p1, p2] = px.sampler.get4(set + 2);
                let r = s.lobe_ray(scene, tr, [u0, u1, u2]);
                if k < n {
                    let pair = s.direct(scene, tr, [p0, p1, p2], r.as_ref());
                    if k == 1 {
                        second = pair;
                    }
                    sum += pair;
                }
                if k < bounce {
                    rays.push((r, [a, b, c, d, e, f]));
                }
            }
            if n > 1 {
                self.split.note(px.at, split::Part::Direct, direct, second);
            }
            if n.max(bounce) > self.glossy_rays {
                let more = |c: u32| c.saturating_sub(self.glossy_rays) as u64;
                self.tally.split_pairs.fetch_add(more(n), Relaxed);
                self.tally.split_rays.fetch_add(more(bounce), Relaxed);
            }
            direct = sum / n as f32;
            l += beta * direct;
            if scene.last_segment(depth + 1) {
                break;
            }
            // A pixel's width at x, seen from the camera.
            let footprint = scene.camera.footprint(s.p);
            let at = Some((px.at, footprint));
            let sample = px.index;
            let q = Pending {
                s,
                rays,
                beta,
                key,
                at,
                sample,
                cached,
            };
            return (l, Some(q), own);
        }
        (l, None, own)
    }

    /// The glossy bounce the radiance cache's records give the receiver, if they cover it.
    pub(super) fn radiance_lookup(&self, s: &Surface) -> Option<V> {
        let cache = self.radiance_cache.as_ref()?;
        if !wpbgi::gathers_wavelets(s) {
            return None;
        }
        let wo = s.frame.to_world(s.wo_l);
        cache.lookup(s.p, s.frame.n, wo, &self.table_of(s))
    }

    /// The glossy bounce from the exact rays sampled from the receiver's lobes: their mean,
    /// the spread of the first two noted for the split.
    /// With `transmitted_only`, the rays that left into the surface alone count (WPBGI
    /// gathers the reflection).
    pub(super) fn lobe_bounce(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        q: &Pending,
        transmitted_only: bool,
    ) -> V {
        let (mut glossy, mut first) = (V::ZERO, [V::ZERO; 2]);
        for (k, (r, u)) in q.rays.iter().enumerate() {
            let counts = |r: &&LobeRay| !transmitted_only || r.w.dot(q.s.frame.n) < 0.0;
            let b = r
                .as_ref()
                .filter(counts)
                .map_or(V::ZERO, |r| self.glossy_bounce(scene, tr, r, *u));
            if let Some(f) = first.get_mut(k) {
                *f = b;
            }
            glossy += b;
        }
        if let (true, Some((at, _))) = (q.rays.len() > 1, q.at) {
            self.split.note(at, split::Part::Bounce, first[0], first[1]);
        }
        glossy / q.rays.len().max(1) as f32
    }

    /// The rough specular lobes' bounce: the hit of the direction sampled from them,
    /// shaded as a rasterized near hit is (baked light, else direct light).
    pub(super) fn glossy_bounce(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        r: &LobeRay,
        u: [f32; 6],
    ) -> V {
        let Some(hit) = &r.hit else {
            return V::ZERO;
        };
        self.tally.exact_hits.fetch_add(1, Relaxed);
        let page = tr.page_handle(hit.page);
        r.weight * self.hit_sends(scene, tr, &page, hit, r.w, || u).0
    }

    /// The receiver at pixel (x, y)'s first hit through its centre, if there is one.
    pub(super) fn centre_hit(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        x: u32,
        y: u32,
    ) -> Option<Pending> {
        let cam = &scene.camera;
        let [x0, x1, y0, _] = self.window;
        let px = PixelSample {
            x,
            y,
            at: ((y - y0) * (x1 - x0) + x - x0) as usize,
            index: 0,
            sampler: PixelSampler::new(self.seed, y * cam.width + x, 0),
            ray: cam.ray(x as f32 + 0.5, y as f32 + 0.5),
            share: 1.0,
            further: None,
        };
        self.first_hit_own(scene, tr, &px).1
    }

    /// One sample's light, `l` up to its receiver and `pending`'s gather; its gather's
    /// held-back part weighs its `share` of the pass's samples of the pixel.
    pub(super) fn finish(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        mut l: V,
        pending: Option<Pending>,
        share: f32,
        c: &mut Counters,
    ) -> V {
        if let Some(mut q) = pending {
            let beta = q.beta;
            q.beta *= share;
            l += beta * self.gather(scene, tr, &q, None, None);
        }
        c.paths += 1;
        c.finite(l)
    }
}

/// How a receiver's lobes are taken.
enum Lobes {
    /// Follow a smooth lobe's sampled bounce (None: the sample failed).
    Follow(Option<BsdfSample>),
    /// Estimate the rough lobes here, scaled by `scale`, with `u_lobe` for their choice.
    Here { scale: f32, u_lobe: f32 },
}

/// A smooth-only BSDF's bounce is followed. With a smooth lobe over rough ones (a smooth
/// coat or mirror over a diffuse base), the smooth lobe is followed with the probability
/// p that `Bsdf::sample` chooses it, and otherwise the rough lobes are estimated at the
/// receiver, scaled by 1/(1 − p): together unbiased, where dropping the smooth lobe
/// would lose its light.
fn lobes(b: &Bsdf, wo: V, u_lobe: f32, u: [f32; 2]) -> Lobes {
    if b.has_smooth_only() {
        return Lobes::Follow(b.sample(wo, u_lobe, u));
    }
    let p = b.delta_share(wo);
    if p <= 0.0 {
        return Lobes::Here { scale: 1.0, u_lobe };
    }
    match u_lobe < p {
        true => Lobes::Follow(b.sample_delta(wo, u_lobe / p, u)),
        false => Lobes::Here {
            scale: 1.0 / (1.0 - p),
            u_lobe: (u_lobe - p) / (1.0 - p),
        },
    }
}
