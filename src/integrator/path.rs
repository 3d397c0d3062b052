//! `--integrator path`: the exact reference. Unidirectional path tracing over the leaf
//! triangles (no level of detail) with next-event estimation and multiple importance
//! sampling (power heuristic, Veach 1997 §9.2), Russian roulette after the second bounce
//! (pbrt-v4 `PathIntegrator`), unbounded depth unless `--max-depth` caps it.
//!
//! Parameters: `max_depth` (longest path in segments, default unbounded), the sampler's
//! seed. Emitters are one-sided unless their material is double-sided; a single-sided
//! opaque surface hit from behind absorbs.

use super::direct::{emission_weight, escaped_light};
use super::surface::{scattering_hit, Missed, Scatter};
use super::{
    bsdf_term, on_side, roulette, sample_light, Counters, Integrator, PixelSample, Receiver, Scene,
    ShadingPoint, Stats,
};
use crate::sampler::PixelSampler;
use crate::trace::{offset_origin, Cone, Ray, Tracer};
use glam::Vec3A as V;

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
    // Surfaces passed through (alpha holes) on this path.
    let mut passes = 0u32;
    loop {
        // Sample sets: 0 is the pixel position; bounce k uses sets 2k+1 (light choice, light
        // point, lobe) and 2k+2 (direction, roulette).
        let [u_pick, ul0, ul1, u_lobe] = s.get4(2 * depth + 1);
        let [ud0, ud1, u_rr, _] = s.get4(2 * depth + 2);
        // Holes pass unscattered, the depth unchanged.
        let scatter = match scattering_hit(scene, tr, &mut ray, ud0, &mut passes) {
            Ok(s) => s,
            Err(Missed::Left) => {
                let from = (!prev_delta).then_some((prev, prev_pdf));
                l += beta * escaped_light(scene, ray.d, from);
                break;
            }
            Err(Missed::Degenerate) => break,
        };
        let sp = scatter.shading(scene, &ray);
        let length = scatter.length(&ray);
        let Scatter { hit, ng, area, .. } = scatter;
        let wo = -ray.d.normalize();
        beta *= sp.through(length);
        if sp.emitted != V::ZERO {
            if prev_delta {
                l += beta * sp.emitted;
            } else {
                let dist2 = length * length;
                let mis = emission_weight(scene, &hit, (ng, area), wo, prev, prev_pdf, dist2);
                l += beta * sp.emitted * mis;
            }
        }
        if scene.last_segment(depth) || sp.absorbs {
            break;
        }
        let ShadingPoint {
            p,
            err,
            n,
            frame,
            bsdf,
            wo_l,
            ..
        } = sp;

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
        ray = Ray {
            o: offset_origin(p, err, ng, wi),
            d: wi,
            t_max: f32::INFINITY,
        };
        depth += 1;
        if depth > 1 && !roulette(&mut beta, || u_rr) {
            break;
        }
    }
    c.paths += 1;
    c.finite(l)
}
