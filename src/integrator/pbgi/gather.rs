//! One bounce of indirect light gathered at a receiver: the micro-buffer filled by the cut
//! (`cut`) or by texel rays, and WPBGI's glossy gather where it applies.

use super::super::surface::{hole_number, scattering_hit};
use super::super::Scene;
use super::cut::{Field, Fill};
use super::microbuffer::{Gradients, MicroBuffer};
use super::pixel_reuse::{InPixel, Reuse};
use super::receiver::Pending;
use super::surface::Surface;
use super::{amb, wpbgi, PbgiIntegrator};
use crate::material::{Bsdf, Frame};
use crate::sampler::PixelSampler;
use crate::trace::{offset_origin, Hit, Ray, Tracer};
use glam::{Vec3, Vec3A as V};
use std::cell::RefCell;
use std::sync::atomic::Ordering::Relaxed;

/// Per-thread scratch reused across receivers.
#[derive(Default)]
pub(super) struct Scratch {
    pub(super) mb: MicroBuffer,
    pub(super) amb: amb::Amb,
    /// This receiver's ray per texel above its horizon: texel, world direction (jittered
    /// inside the texel) and the weight of its light ([`Texels::ray`]).
    pub(super) rays: Vec<(u32, V, f32)>,
    /// Per ray: inside some rasterized leaf's cone, and the nearest of their triangles
    /// it met (shaded once the cut is done, so hidden hits cost nothing).
    pub(super) aimed: Vec<bool>,
    pub(super) nearest: Vec<Option<Hit>>,
    pub(super) stack: Vec<(u32, u32)>,
    /// The near leaves this receiver's cut rasterized (page, node).
    pub(super) near: Vec<(u32, u32)>,
    /// The rays inside the cone of the leaf being rasterized.
    pub(super) in_cone: Vec<u32>,
}

thread_local! {
    pub(super) static SCRATCH: RefCell<Scratch> = RefCell::new(Scratch::default());
}

/// A gather's place in a sequence of gathers at one pixel or record: texel k's ray is
/// jittered by point `index` of an Owen-scrambled Sobol sequence of its own (scrambled by
/// `seed` and k), so successive gathers stratify every texel between them, as one
/// pixel's bounces stratify its hemisphere over its samples; independent jitters left
/// room's gathers (9 a pixel, 192 texels each) twice as noisy as 2,048 path-traced bounces.
#[derive(Clone, Copy)]
pub(super) struct Strata {
    pub(super) seed: u64,
    pub(super) index: u32,
}

impl Strata {
    /// Texel k's jitter.
    pub(super) fn jitter(&self, k: u32) -> [f32; 2] {
        let [a, b, ..] = self.sampler(k).get4(0);
        [a, b]
    }

    /// Numbers for shading texel k's hit (a light sample, then a lobe ray), from the same
    /// sequence's next dimensions.
    pub(super) fn shading(&self, k: u32) -> [f32; 6] {
        let sampler = self.sampler(k);
        let [a, b, c, d] = sampler.get4(1);
        let [e, f, ..] = sampler.get4(2);
        [a, b, c, d, e, f]
    }

    /// Texel k's sequence, at this gather's point: the pixel sampler's, with the texel
    /// standing for the pixel (it starts a new sequence past 2¹⁶ points).
    pub(super) fn sampler(&self, k: u32) -> PixelSampler {
        PixelSampler::new((self.seed ^ self.seed >> 32) as u32, k, self.index)
    }
}

impl PbgiIntegrator {
    /// Whether WPBGI gathers this receiver's glossy bounce.
    pub(super) fn gathers_wavelets(&self, s: &Surface) -> bool {
        self.settings.glossy_bounce == wpbgi::GlossyBounce::Wavelet && wpbgi::gathers_wavelets(s)
    }

    /// One bounce of indirect light at the receiver: its diffuse lobe from the
    /// micro-buffer; its rough specular lobes' reflection by WPBGI where
    /// `--pbgi-glossy-bounce wavelet` or `cache` asks (a dielectric's transmission by the
    /// lobe rays that left into it), else from the exact ray sampled from them at
    /// the first hit, which served direct light's MIS too (a lobe
    /// narrower than a micro-buffer texel would be convolved at a few texel centres only:
    /// with `--max-depth` 3 on a rough silver plinth of α 0.04 that overstated its pixels
    /// by 8–11%). `known`: what `reuse` gave for the receiver, when the caller asked it
    /// already.
    pub(super) fn gather(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        q: &Pending,
        field: Option<&Field>,
        known: Option<Reuse>,
    ) -> V {
        let s = &q.s;
        // A rough dielectric's transmission keeps its lobe rays: the cloud holds no light
        // inside it.
        let wavelets = q.cached.is_some() || self.gathers_wavelets(s);
        let transmitted = match wavelets && s.bsdf.trans > 0.0 {
            true => self.lobe_bounce(scene, tr, q, true),
            false => V::ZERO,
        };
        let mut l = transmitted
            + match (q.cached, self.gathers_wavelets(s)) {
                (Some(v), _) => {
                    self.tally.radiance_hits.fetch_add(1, Relaxed);
                    v
                }
                (None, true) => match self.reuse_in_pixel(q, true) {
                    InPixel::Lend(pixel, at) => {
                        self.lend(pixel, at, q.beta);
                        V::ZERO
                    }
                    InPixel::Gather(strata) => {
                        let e = self.gather_wavelet(scene, tr, s, strata);
                        match self.keep(q, e, q.beta, true) {
                            true => V::ZERO,
                            false => e,
                        }
                    }
                },
                (None, false) => self.lobe_bounce(scene, tr, q, false),
            };
        if s.bsdf.diffuse.max_element() > 0.0 {
            // The diffuse lobe is the same for every incident direction: irradiance × it.
            let lobe = s.diffuse_lobe();
            match known.unwrap_or_else(|| self.reuse(tr, q)) {
                Reuse::Cached(e) => {
                    self.tally.cache_hits.fetch_add(1, Relaxed);
                    l += lobe * e;
                }
                Reuse::Pixel(pixel, at) => self.lend(pixel, at, q.beta * lobe),
                Reuse::Gather(strata) => {
                    self.tally.gathers.fetch_add(1, Relaxed);
                    let e = self.gather_irradiance(scene, tr, s, strata, field).0;
                    if !self.keep(q, e, q.beta * lobe, false) {
                        l += lobe * e;
                    }
                }
            }
        }
        l
    }

    /// Irradiance at `s` from the cut, the near rays and the micro-buffer, the distance
    /// it may be carried ([`MicroBuffer::reach_distance`]) and the irradiance gradients
    /// (world space). `strata` places the gather in its pixel's or record's sequence. With
    /// a cluster's `field`, its far splats are taken as they are and the cut starts from
    /// its near nodes instead of the root.
    pub(super) fn gather_irradiance(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        s: &Surface,
        strata: Strata,
        field: Option<&Field>,
    ) -> (V, f32, Gradients) {
        SCRATCH.with_borrow_mut(|sc| {
            let texels = &self.texels;
            sc.mb.clear();
            sc.rays.clear();
            sc.rays.extend(texels.upper.iter().filter_map(|&k| {
                let [a, b] = strata.jitter(k);
                let (local, weight) = texels.ray(k as usize, a, b);
                let w = s.frame.to_world(V::from(local)).normalize();
                (w.dot(s.n) > 0.0).then_some((k, w, weight))
            }));
            self.fill_texels(scene, tr, s, field, sc, strata, Fill::Hemicube);
            let incident = sc.mb.resolve(texels, |_| Vec3::ZERO);
            let e = MicroBuffer::convolve(texels, &incident, |_| Vec3::ONE);
            let g = sc.mb.gradients(texels, &incident);
            let g = g.map(|v| s.frame.to_world(V::from(v)).into());
            (V::from(e), sc.mb.reach_distance(texels, &incident), g)
        })
    }

    /// Irradiance from the cloud at a bake point q of a front face with normal `ng` (the
    /// next bounce of `bake`).
    pub fn irradiance(&self, scene: &Scene, tr: &mut Tracer, q: V, err: V, ng: V, key: u64) -> V {
        let frame = Frame::new(ng);
        // The gather reads only the point, its normals and frame; any BSDF will do.
        let white = Bsdf::lambert(V::ONE);
        let s = Surface {
            p: q,
            err,
            ng,
            n: ng,
            frame,
            bsdf: white,
            wo_l: V::Z,
            emitted: V::ZERO,
            absorbs: false,
            front: true,
            sigma: V::ZERO,
        };
        let strata = Strata {
            seed: key,
            index: 0,
        };
        self.gather_irradiance(scene, tr, &s, strata, None).0
    }

    /// Texel k's ray traced exactly, its hit shaded as a rasterized hit and weighted as the
    /// ray's place in the texel asks ([`Texels::ray`]): every texel under
    /// `--pbgi-gather rays`; otherwise where a rasterized leaf's cone promised geometry its
    /// triangles did not hold (without it the texel would show splats' partial coverage
    /// and the black background through the gaps).
    /// Returns the hit's depth, fragment id, weighted light and whether it was sampled.
    pub(super) fn texel_ray(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        s: &Surface,
        (k, weight): (u32, f32),
        w: V,
        strata: Strata,
    ) -> Option<(f32, u64, Vec3, bool)> {
        let ray = Ray {
            o: offset_origin(s.p, s.err, s.ng, w),
            d: w,
            t_max: f32::INFINITY,
        };
        let mut ray = ray;
        let hit = scattering_hit(scene, tr, &mut ray, hole_number(w), &mut 0)
            .ok()?
            .hit;
        let page = tr.page_handle(hit.page);
        let (sends, sampled) = self.hit_sends(scene, tr, &page, &hit, w, || strata.shading(k));
        let l = Vec3::from(sends * weight);
        Some((hit.t, u64::MAX - k as u64, l, sampled))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A pixel's or record's successive gathers stratify each texel between them: the
    /// first 16 jitters of a texel fall one in each cell of a 4×4 grid and one in each of
    /// 16 columns and 16 rows (Sobol's (0, 2)-sequence property, which Owen scrambling
    /// keeps), and texels are scrambled apart.
    #[test]
    fn successive_gathers_stratify_every_texel() {
        let strata = |index| Strata { seed: 77, index };
        for k in [0u32, 5, 191] {
            let points: Vec<[f32; 2]> = (0..16).map(|i| strata(i).jitter(k)).collect();
            for cells in [[4usize, 4], [16, 1], [1, 16]] {
                let mut seen = vec![0; 16];
                for p in &points {
                    let cx = (p[0] * cells[0] as f32) as usize;
                    let cy = (p[1] * cells[1] as f32) as usize;
                    seen[cy * cells[0] + cx] += 1;
                }
                assert!(
                    seen.iter().all(|&n| n == 1),
                    "texel {k}, {cells:?}: {seen:?}"
                );
            }
        }
        assert_ne!(strata(0).jitter(0), strata(0).jitter(1));
        assert_ne!(Strata { seed: 78, index: 0 }.jitter(0), strata(0).jitter(0));
    }
}
