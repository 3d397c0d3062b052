//! `--integrator path`: the exact reference. Unidirectional path tracing over the leaf
//! triangles (no level of detail) with next-event estimation and multiple importance
//! sampling (power heuristic, Veach 1997 §9.2), Russian roulette after the second bounce
//! (pbrt-v4 `PathIntegrator`), unbounded depth unless `--max-depth` caps it.
//!
//! Parameters: `max_depth` (longest path in segments, default unbounded), the sampler's
//! seed. Emitters are one-sided unless their material is double-sided; a single-sided
//! opaque surface hit from behind absorbs.

use super::{
    bsdf_term, on_side, sample_light, shading_frame, Counters, Integrator, PixelSample, Receiver,
    Scene, Stats,
};
use crate::sampler::PixelSampler;
use crate::trace::{offset_origin, Cone, Ray, Tracer};
use glam::Vec3A as V;

/// Veach's power heuristic (β = 2) for two sampling strategies' pdfs.
pub fn power_heuristic(a: f32, b: f32) -> f32 {
    let (a2, b2) = (a * a, b * b);
    if a2 + b2 > 0.0 {
        a2 / (a2 + b2)
    } else {
        0.0
    }
}

/// Most alpha holes one path segment or shadow ray passes through.
pub const MAX_PASSES: u32 = 64;

/// Stochastic opacity: whether a ray goes on through a surface of `opacity` (a hole under
/// an alpha mask; with probability 1 − alpha under blend), from the sample number `u` moved
/// along a golden-ratio sequence for the `passes` already made on this segment.
pub fn passes_through(opacity: f32, u: f32, passes: u32) -> bool {
    opacity < 1.0 && (u + passes as f32 * 0.618_034).fract() >= opacity
}

pub struct PathIntegrator;

impl Integrator for PathIntegrator {
    fn sample(&self, scene: &Scene, tr: &mut Tracer, px: &PixelSample, c: &mut Counters) -> V {
        radiance(scene, tr, px.ray, &px.sampler, c)
    }

    fn passes(&self) -> Vec<String> {
        vec!["path: eye paths with next-event estimation and MIS".into()]
    }

    fn stats(&self) -> Stats {
        Stats::Path {}
    }
}

/// Radiance arriving along `ray`.
pub fn radiance(
    scene: &Scene,
    tr: &mut Tracer,
    mut ray: Ray,
    s: &PixelSampler,
    c: &mut Counters,
) -> V {
    let mut l = V::ZERO;
    let mut beta = V::ONE;
    let mut prev_pdf = 0.0f32;
    let mut prev_delta = true;
    // The last scattering point and its normal, where its light sample was chosen.
    let mut prev = (V::ZERO, V::ZERO);
    let mut depth = 0u32;
    // Surfaces passed through (alpha holes) on this path, and the distance since `prev`.
    let mut passes = 0u32;
    let mut travelled = 0.0f32;
    loop {
        // Sample sets: 0 is the pixel position; bounce k uses sets 2k+1 (light choice, light
        // point, lobe) and 2k+2 (direction, roulette).
        let [u_pick, ul0, ul1, u_lobe] = s.get4(2 * depth + 1);
        let [ud0, ud1, u_rr, _] = s.get4(2 * depth + 2);
        let Some(hit) = tr.closest_hit(&ray) else {
            break;
        };
        scene.touch(&hit);
        let ng_raw = hit.ng();
        let area = 0.5 * ng_raw.length();
        if area.is_nan() || area <= 0.0 {
            break;
        }
        let ng = ng_raw / (2.0 * area);
        if passes < MAX_PASSES && passes_through(scene.opacity_at(&hit), ud0, passes) {
            // Unscattered, its depth unchanged.
            passes += 1;
            travelled += hit.t * ray.d.length();
            let (p, err) = hit.point();
            ray.o = offset_origin(p, err, ng, ray.d);
            continue;
        }
        let shaded = scene.material_at_hit(&hit, ray.d);
        let m = &shaded.m;
        let wo = -ray.d.normalize();
        let front = ng.dot(wo) > 0.0;
        let le = m.emitted(front);
        if le != V::ZERO {
            if prev_delta {
                l += beta * le;
            } else {
                let dist2 = (travelled + hit.t * ray.d.length()).powi(2);
                let light_pdf = scene.lights.pdf_li(
                    prev,
                    scene.lights.emitter_at(hit.leaf, hit.slot),
                    dist2,
                    ng.dot(wo).abs(),
                    area,
                );
                l += beta * le * power_heuristic(prev_pdf, light_pdf);
            }
        }
        if scene.last_segment(depth) || m.absorbs(front) {
            break;
        }
        let (p, err) = hit.point();
        let n = if front { ng } else { -ng };
        let frame = shading_frame(&hit, ng, front, shaded.bump);
        let bsdf = m.bsdf(front);
        let wo_l = frame.to_local(wo);

        // Next-event estimation.
        if !bsdf.has_smooth_only() {
            l += beta
                * sample_light(
                    scene,
                    tr,
                    &Receiver::surface(p, err, ng),
                    &Cone::EXACT,
                    [u_pick, ul0, ul1],
                    bsdf_term(frame, n, bsdf, wo_l),
                );
        }

        // Continue the path by sampling the BSDF.
        let Some(bs) = bsdf.sample(wo_l, u_lobe, [ud0, ud1]) else {
            break;
        };
        let wi = frame.to_world(bs.wi).normalize();
        if !on_side(&frame, n, wi) {
            break;
        }
        beta *= bs.weight;
        if !beta.is_finite() || beta.max_element() <= 0.0 {
            break;
        }
        prev_pdf = bs.pdf;
        prev_delta = bs.delta;
        prev = (p, ng);
        travelled = 0.0;
        ray = Ray {
            o: offset_origin(p, err, ng, wi),
            d: wi,
            t_max: f32::INFINITY,
        };
        depth += 1;
        let q = beta.max_element();
        if depth > 1 && q < 1.0 {
            if u_rr >= q {
                break;
            }
            beta /= q;
        }
    }
    c.paths += 1;
    c.finite(l)
}
