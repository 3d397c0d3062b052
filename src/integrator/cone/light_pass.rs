//! The light distribution pass for caustics (004 §4.7).
//!
//! Photons leave the lights by power (eq. 4.28), follow smooth mirror and glass bounces
//! and leave their power on the first Lambertian surface after at least one of them: the
//! caustic paths L S S* D. Paths starting with a diffuse bounce are the eye pass's, which
//! masks the caustic ones in turn (D S* S L), so each path is counted once. The deposit
//! goes to the hit triangle's light cell as Φ/(π·A'), A' the cell's visible area
//! (§4.7.1); dividing by the global photon count M gives E/π (eq. 4.29–4.30), the quantity
//! the diffuse store holds, and the hit's own albedo multiplies it when shading.
//!
//! Photons are exact rays, so every deposit lands on a leaf triangle: the push of §4.8.2
//! has nothing to move down, and the pull after each pass carries the caustic light up to
//! the nodes wide cones stop at (`light_store::pull`).

use crate::integrator::Scene;
use crate::light_store::{Keys, RadianceStore, GRID};
use crate::material::{cosine_hemisphere, Frame};
use crate::sampler::PixelSampler;
use crate::texture::Lookup;
use crate::trace::{offset_origin, Hit, Ray, Tracer};
use glam::Vec3A as V;
use rayon::prelude::*;
use std::f32::consts::PI;

/// Specular bounces a photon follows at most.
const MAX_BOUNCES: u32 = 16;

/// Sample points per cell for the visible-area estimate.
const VISIBILITY_RAYS: u32 = 16;

/// Photons per work item.
const CHUNK: u32 = 256;

/// What one light pass did.
#[derive(Default, Clone, Copy, Debug)]
pub struct LightPassStats {
    pub rays: u64,
    pub deposits: u64,
}

/// Emits `photons` photons (pass number `pass`) and deposits their caustic light.
pub fn light_pass(
    scene: &Scene,
    store: &RadianceStore,
    keys: Keys,
    photons: u32,
    pass: u32,
    seed: u32,
) -> LightPassStats {
    let chunks: Vec<u32> = (0..photons.div_ceil(CHUNK)).collect();
    let (rays, deposits) = chunks
        .par_iter()
        .map(|&c| {
            let mut tr = Tracer::new(&scene.cache);
            let mut deposits = 0u64;
            for i in c * CHUNK..((c + 1) * CHUNK).min(photons) {
                // Photon i of every pass is sample `pass` of sequence i.
                let s = PixelSampler::new(seed ^ 0x9e37_79b9, i, pass);
                deposits += trace_photon(scene, store, keys, &mut tr, &s) as u64;
            }
            scene.cache.add_lookups(tr.page_lookups());
            (tr.rays, deposits)
        })
        .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
    store.add_photons(photons as u64);
    LightPassStats { rays, deposits }
}

/// Follows one photon; true if it left caustic light somewhere.
fn trace_photon(
    scene: &Scene,
    store: &RadianceStore,
    keys: Keys,
    tr: &mut Tracer,
    s: &PixelSampler,
) -> bool {
    let [u_pick, u0, u1, u2] = s.get4(0);
    let [u3, u4, ..] = s.get4(1);
    let Some(photon) = scene.lights.emit(u_pick, [u0, u1, u2, u3, u4]) else {
        return false;
    };
    let (mut ray, mut flux) = (photon.ray, photon.flux);
    if let Some((m, uv)) = photon.texel {
        flux *= scene
            .textures
            .emission_ratio(&mut Lookup::new(&scene.cache), m, uv);
    }
    for bounce in 0..MAX_BOUNCES {
        let Some(hit) = tr.closest_hit(&ray) else {
            return false;
        };
        let m = &scene
            .material_at(
                hit.tri.material,
                &hit.tri.p,
                &hit.corners,
                hit.b,
                ray.d,
                0.0,
            )
            .m;
        let ng = hit.ng().normalize_or_zero();
        let wo = -ray.d;
        let front = ng.dot(wo) > 0.0;
        if ng == V::ZERO || m.absorbs(front) {
            return false;
        }
        flux *= m.transmittance(front, hit.t * ray.d.length());
        let n = if front { ng } else { -ng };
        if m.is_pure_diffuse() {
            // Direct light (no specular bounce yet) is the eye pass's next-event estimate.
            if bounce > 0 {
                deposit(scene, store, keys, tr, &hit, n, flux);
            }
            return bounce > 0;
        }
        let [u_lobe, ud0, ud1, u_rr] = s.get4(2 + bounce);
        let frame = Frame::new(n);
        let bsdf = m.bsdf(front);
        let Some(bs) = bsdf.sample(frame.to_local(wo), u_lobe, [ud0, ud1]) else {
            return false;
        };
        // Only smooth chains make caustics; a glossy bounce ends the photon (the eye pass
        // samples lights from glossy surfaces itself).
        if !bs.delta {
            return false;
        }
        // Power, unlike radiance, is not scaled by 1/η² through an interface (pbrt-v4
        // §9.5.2, TransportMode::Importance): undo the radiance BSDF's factor.
        let w = if bs.wi.z < 0.0 {
            bs.weight * bsdf.eta * bsdf.eta
        } else {
            bs.weight
        };
        flux *= w;
        // Roulette on the throughput after the fourth bounce.
        if bounce >= 4 {
            let q = w.max_element().min(1.0);
            if u_rr >= q {
                return false;
            }
            flux /= q;
        }
        let (p, err) = hit.point();
        let wi = frame.to_world(bs.wi).normalize();
        ray = Ray {
            o: offset_origin(p, err, ng, wi),
            d: wi,
            t_max: f32::INFINITY,
        };
    }
    false
}

/// Leaves a photon's power on the hit cell, as Φ / (π · visible area).
fn deposit(
    scene: &Scene,
    store: &RadianceStore,
    keys: Keys,
    tr: &mut Tracer,
    hit: &Hit,
    n: V,
    flux: V,
) {
    let cell = keys.cell_of(&hit.tri, hit.b);
    let key = super::tri_key(keys, hit, n.dot(hit.ng()) < 0.0, cell);
    let visible = match store.get(key).map(|e| e.visible) {
        Some(v) if v > 0.0 => v,
        _ => {
            let v = visible_fraction(scene, tr, hit, n, cell, keys.grid(&hit.tri));
            store.set_visible(key, v);
            v
        }
    };
    let area = keys
        .cells(&hit.tri)
        .find(|&(c, _)| c == cell)
        .map_or(0.0, |(_, a)| a)
        * visible;
    if area > 0.0 {
        store.add_caustic(key, (flux / (PI * area)).to_array());
        store.mark_dirty_in(hit.instance, hit.page, hit.instance_leaf, hit.leaf);
        scene.touch(hit);
    }
}

/// Visible fraction of a cell (004 §4.7.1): a point is hidden when a ray leaving it over
/// the side the photon came from first meets the back of a one-sided surface, i.e. the
/// point lies inside a closed object (a floor under a box standing on it). The thesis
/// needed this for overlapping surfels; with exact triangles only such buried parts
/// remain. Never below one sample's worth, since a photon did reach the cell.
fn visible_fraction(scene: &Scene, tr: &mut Tracer, hit: &Hit, n: V, cell: u64, side: f32) -> f32 {
    let p = hit.tri.p.map(V::from);
    let (ci, cj) = ((cell / GRID) as f32, (cell % GRID) as f32);
    let frame = Frame::new(n);
    let k = (VISIBILITY_RAYS as f32).sqrt() as u32;
    let (mut seen, mut cast) = (0u32, 0u32);
    for a in 0..k {
        for b in 0..k {
            let (fa, fb) = ((a as f32 + 0.5) / k as f32, (b as f32 + 0.5) / k as f32);
            let (b1, b2) = ((ci + fa) / side, (cj + fb) / side);
            if b1 + b2 > 1.0 {
                continue;
            }
            let q = p[0] * (1.0 - b1 - b2) + p[1] * b1 + p[2] * b2;
            let err = p[0].abs().max(p[1].abs()).max(p[2].abs()) * crate::trace::gamma(7);
            let d = frame.to_world(cosine_hemisphere([fb, fa])).normalize();
            let ray = Ray {
                o: offset_origin(q, err, n, d),
                d,
                t_max: f32::INFINITY,
            };
            cast += 1;
            let buried = tr.closest_hit(&ray).is_some_and(|h| {
                let m = &scene.materials[h.tri.material as usize];
                h.ng().dot(d) > 0.0 && !m.double_sided
            });
            if !buried {
                seen += 1;
            }
        }
    }
    if cast == 0 {
        return 1.0;
    }
    (seen as f32 / cast as f32).max(1.0 / cast as f32)
}
