//! `--integrator pbgi`: point-based global illumination over the archive's hierarchy
//! (003 ch. 2; Christensen 2008 as cited there).
//!
//! The bake (`bake`) stores in every node the direct light it reflects diffusely. At the
//! first non-specular hit x the renderer adds the emission seen, direct light as the path
//! tracer takes it (a light sample, weighed by MIS against the ray sampled from x's rough
//! specular lobes), and one bounce of indirect light gathered from the hierarchy:
//! - the cut: from the root, a node is splatted whole when x lies outside its bounding
//!   sphere and the sphere's solid angle π r²/d² is at most `--pbgi-angle` times the
//!   smallest micro-buffer texel's; otherwise its children are visited. Nodes wholly below
//!   x's tangent plane are skipped;
//! - a splatted node covers its projected area toward x over d² and sends the light it
//!   reflects that way (`bake::Directional`, read from the page's baked block), plus, for
//!   rough metal and rough dielectric surfaces, the glossy light its cube map holds in that
//!   direction (`glossy`, Haar-coded in the file); seen from behind it is a dark occluder;
//! - leaves too close for their solid angle are rasterized: x casts one ray per texel,
//!   jittered inside it, and each ray meeting a leaf triangle leaves an opaque fragment at
//!   its depth. A front hit on a diffuse surface sends the baked light of the finest patch
//!   under it (`patch`: large triangles are baked as up to 4⁶ patches); other hits take
//!   direct light as x does. A ray aimed at a leaf's sphere that meets
//!   none of its triangles is traced exactly (what it finds could otherwise be missing);
//! - hits are shaded once the cut is done, only the nearest of each texel's ray;
//! - `microbuffer` composites and convolves with x's diffuse lobe (003 eq. 2.1); the
//!   lobe being constant, the gather is kept as irradiance, and each surface of a pixel
//!   gathers at most at every `--pbgi-reuse`-th sample landing on it (more often where
//!   its gathers scatter), its other samples reusing its gathers' mean;
//! - `--pbgi-rays` skips the cut: every texel's ray is traced and reads the bake;
//! - x's rough specular lobes, mostly narrower than a texel, take exact rays sampled
//!   from them instead (`--pbgi-glossy-rays`; the first with the pixel's own sample
//!   sequence, as the path tracer's next bounce would), their hits shaded as a rasterized
//!   hit is; each ray also serves a light sample's MIS for x's direct light;
//! - or, with `--pbgi-glossy-bounce wavelet`, WPBGI gathers them from the cloud (`wpbgi`:
//!   the adaptive micro-buffer and the wavelet BRDF product, 000 §3.2 and 002 §4.2), and
//!   with `cache` those gathers are kept as radiance records shared between pixels
//!   (`radiance_cache`, 002 §4.3), receivers no record covers taking the exact rays.
//!
//! A pixel whose earlier samples scattered takes more camera rays a pass (`pixel_split`,
//! not in the seeds): half of the showroom's noise was the sample's position in the
//! pixel, which nothing at one first hit lowers.
//!
//! Smooth mirrors and glass are followed exactly (one sampled bounce each, up to
//! `SMOOTH_DEPTH`), so a perfectly specular surface degrades to the exact estimator
//! (000 §A.8). The cloud holds `--bounces N` bounces (1: direct light reflected once):
//! compare with `--max-depth` 2 + N of the path tracer (camera → x → node → … → light).
//! A smooth lobe layered over a diffuse one is not sampled (its delta part is lost).

mod amb;
pub mod bake;
mod brdf_table;
pub mod cache;
pub mod cluster;
mod cut;
pub mod glossy;
pub mod microbuffer;
pub mod patch;
mod pixel_split;
mod radiance_cache;
mod records;
mod settings;
mod split;
mod surface;
pub mod wpbgi;

use super::edge::EdgeRays;
use super::surface::{hole_number, scattering_hit, Scatter};
use super::{on_side, Counters, Integrator, Pass, PixelSample, Scene, Stats, Target};
use crate::material::{luminance, Bsdf, Frame};
use crate::moments::Moments;
use crate::sampler::Hash;
use crate::sampler::PixelSampler;
use crate::trace::{offset_origin, Hit, Ray, Tracer};
use anyhow::Result;
use cache::IrradianceCache;
use cut::{Field, Fill};
use glam::{Vec3, Vec3A as V};
use microbuffer::{Gradients, MicroBuffer, Texels};
pub use settings::PbgiSettings;
use std::cell::RefCell;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering::Relaxed};
use std::sync::{Mutex, PoisonError};
use std::time::Instant;
use surface::{hit_light, LobeRay, Surface};

/// Smooth bounces followed before giving up on a path.
const SMOOTH_DEPTH: u32 = 8;

/// What PBGI adds to the render's statistics.
#[derive(Clone, Debug, serde::Serialize)]
pub struct PbgiStats {
    pub pbgi_angle: f32,
    pub pbgi_resolution: usize,
    pub bake_seconds: f64,
    pub bake_samples: u64,
    /// Nodes splatted whole, and texels resolved by exact rays, over the render.
    pub splatted_nodes: u64,
    /// Texels filled by rasterized near leaves (the nearest hit of each texel's ray), and
    /// of them those shaded by a light sample rather than baked light.
    pub near_fragments: u64,
    pub exact_hits: u64,
    /// Pairs for direct light and rays for the glossy bounce that glossy receivers took
    /// beyond `--pbgi-glossy-rays` (`--pbgi-split`).
    pub split_pairs: u64,
    pub split_rays: u64,
    /// Samples pixels took beyond one per pass (`--pbgi-pixel-split`).
    pub further_samples: u64,
    /// Exact rays where a rasterized leaf's cone found none of its triangles.
    pub gap_rays: u64,
    pub receiver_clusters: usize,
    pub clustered_receivers: u64,
    pub pbgi_reuse: u32,
    /// Receivers gathered at, and those that took their pixel's earlier gathers instead.
    pub gathers: u64,
    pub reused_gathers: u64,
    /// Pixels at an emitter's silhouette (these take `--edge-rays`).
    pub edge_pixels: u64,
    /// Texel rays traced exactly under `--pbgi-rays`.
    pub traced_texels: u64,
    /// `--pbgi-cache`, its records, the gathers they average and the receivers that
    /// read them.
    pub pbgi_cache: f32,
    pub cache_records: u64,
    pub cache_gathers: u64,
    pub cache_hits: u64,
    /// Receivers the cache covered but a surface nearer than its records' reach hid.
    pub cache_rejects: u64,
    /// Pixels probed for the cache's error, and the records added where it was found.
    pub cache_probes: u64,
    pub cache_probe_records: u64,
    /// WPBGI's glossy gathers (`--pbgi-glossy-bounce wavelet`), the adaptive micro-buffer's
    /// leaves over them (and the leaves the light importance split), the BRDF tables built
    /// and their kept Haar coefficients.
    pub wavelet_gathers: u64,
    pub amb_leaves: u64,
    pub amb_light_splits: u64,
    pub brdf_tables: usize,
    pub brdf_coefficients: usize,
    /// The radiance cache's records (`--pbgi-glossy-bounce cache`), the gathers they
    /// average and the receivers that read their glossy bounce from them.
    pub radiance_records: u64,
    pub radiance_gathers: u64,
    pub radiance_hits: u64,
}

pub struct PbgiIntegrator {
    settings: PbgiSettings,
    /// Light samples the bake took (0 when read from a file).
    bake_samples: u64,
    texels: Texels,
    seed: u32,
    bake_s: f64,
    splatted: AtomicU64,
    near_fragments: AtomicU64,
    exact_hits: AtomicU64,
    split_pairs: AtomicU64,
    split_rays: AtomicU64,
    gap_rays: AtomicU64,
    /// Receivers gathered through a cluster's field.
    clusters: AtomicU64,
    /// Per pixel of the window (by its index there): the irradiance gathered there, per
    /// surface.
    gathered: Vec<Mutex<Vec<Gathered>>>,
    gathers: AtomicU64,
    reused: AtomicU64,
    traced_texels: AtomicU64,
    /// Edge rays at lamps' silhouettes.
    edge: EdgeRays,
    /// The window rendered (`Target::window`), where the cache's records are placed.
    window: [u32; 4],
    cache: Option<IrradianceCache>,
    /// WPBGI's radiance records (`--pbgi-glossy-bounce cache`), and the receivers they gave.
    radiance: Option<radiance_cache::RadianceCache>,
    radiance_hits: AtomicU64,
    /// Rays and seconds of the radiance records' gathers.
    radiance_rays: u64,
    radiance_s: f64,
    cache_hits: AtomicU64,
    cache_rejects: AtomicU64,
    /// Per pixel: a cached receiver of it had a surface over it (see `probes`).
    crevices: Vec<AtomicBool>,
    cache_s: f64,
    /// Rays of the records' first gathers, and of their refinement since.
    cache_rays: u64,
    refine_rays: u64,
    /// The window's pixels in the order the probes visit them, how many are visited, the
    /// rays the probes traced (each at least a ray per texel) and the records they added
    /// (see `probe_cache`).
    probe_order: Vec<[u32; 2]>,
    probed: usize,
    probe_rays: u64,
    probe_records: u64,
    /// `--pbgi-glossy-rays`, or its default for the scene.
    glossy_rays: u32,
    /// Pairs and bounce rays per glossy receiver, per pixel (`--pbgi-split`).
    split: split::Split,
    /// Camera rays per pixel and pass (`--pbgi-pixel-split`), and the further ones taken.
    pixel_split: pixel_split::PixelSplit,
    further_samples: AtomicU64,
    /// v̄ · c_g / c_s for the pixels' gather periods, at the pass's start (see `period`).
    reuse_target: f32,
    /// WPBGI's BRDF tables, and its gathers and their leaves.
    tables: wpbgi::Tables,
    wavelet_gathers: AtomicU64,
    amb_leaves: AtomicU64,
    light_splits: AtomicU64,
}

/// Irradiance gathers summed at one surface of a pixel.
#[derive(Clone, Copy)]
struct Gathered {
    /// The first gather's point and shading normal.
    p: V,
    n: V,
    sum: V,
    /// The gathers' luminances (their count is the gathers'): their spread sets the
    /// surface's period.
    y: Moments,
    /// Samples that landed on it: it gathers at every `period`-th (at its pixel's
    /// phase), and the pixel's first surface also at its first, so a surface's gathers
    /// are in proportion to its share of the pixel's samples. One that has none yet
    /// takes those of the surface whose normal is closest ([`Integrator::held_back`]).
    samples: u32,
    /// Σ path weight × diffuse lobe of the samples that take this surface's irradiance:
    /// they are given the mean of all its gathers once the render ends
    /// ([`Integrator::held_back`]), not the mean of those made so far, which weighed a
    /// pixel's first gathers most (on room at 8 gathers a pixel, as if it had 4.8).
    weight: V,
    /// Its gathers are WPBGI's glossy light, not irradiance.
    glossy: bool,
}

impl Gathered {
    /// Whether a receiver at `p` with normal `n` lies on this surface: normals within
    /// 14° and `p` within `footprint` of its tangent plane, the gathers of the same kind.
    fn holds(&self, p: V, n: V, footprint: f32, glossy: bool) -> bool {
        self.glossy == glossy
            && self.n.dot(n) >= SAME_NORMAL
            && (p - self.p).dot(self.n).abs() <= footprint
    }

    /// The variance a gather adds to one sample that takes it, in luminance: the
    /// gathers' spread times the samples' mean weight, squared; None before two gathers.
    fn spread(&self) -> Option<f32> {
        if self.y.count < 2 {
            return None;
        }
        let var = self.y.variance() as f32;
        let w = luminance(self.weight) / self.samples.max(1) as f32;
        Some(w * w * var)
    }

    /// How often this surface gathers: every `most`-th sample (`--pbgi-reuse` R) until
    /// its first gather, and until `PILOT_PERIOD` samples have landed on it; then every
    /// `PILOT_PERIOD`-th until its second gather (a surface few samples hit is not worth
    /// two), then at splitting's
    /// optimum: a sample of variance v̄ and cost c_s, a gather of variance s²
    /// (`spread`) and cost c_g shared by P samples, have variance × cost
    /// (v̄ + s² P)(c_s + c_g / P), least at P = √(v̄ c_g / (s² c_s)) (`target` is
    /// v̄ c_g / c_s), taken down to a power of two so that a longer period's samples are
    /// a shorter one's, and at most R.
    fn period(&self, most: u64, target: f32) -> u64 {
        let optimum = match (self.y.count, self.spread()) {
            (0, _) => return most,
            (_, None) if (self.samples as u64) < PILOT_PERIOD => return most,
            (_, None) => return most.min(PILOT_PERIOD),
            (_, Some(s2)) => (target / s2).sqrt(),
        };
        // No v̄ yet (a zero target) or a zero spread (an infinite optimum): R.
        if !(optimum < most as f32 && target > 0.0) {
            return most;
        }
        1 << (optimum.max(1.0) as u64).ilog2()
    }
}

/// A surface's gather period between its first and second gathers, once this many
/// samples landed on it, when `--pbgi-reuse` is longer: the two give the spread that sets
/// the period after them.
const PILOT_PERIOD: u64 = 8;

/// Rays from a glossy receiver's lobes for its bounce, unless `--pbgi-glossy-rays` says,
/// where some material has rough specular lobes.
const GLOSSY_RAYS: u32 = 2;

/// Most pairs and bounce rays per glossy receiver, unless `--pbgi-split` says, where
/// some material has rough specular lobes (`Split::new` splits only where K is 2 or more).
const SPLIT: u32 = 32;

/// Most camera rays per pixel and pass, unless `--pbgi-pixel-split` says. With
/// `pixel_split::GAIN` 4, 32 and 64 gave the same showroom error at 20 s (5.13e-6 and
/// 5.20e-6, squared, seeds 1–4); 16 capped the gold bunny's highlights.
const PIXEL_SPLIT: u32 = 32;

/// Samples of each pixel whose cached receivers are checked for a surface over them.
const PROBED_SAMPLES: u32 = 16;

/// Surfaces a pixel keeps gathers for; samples on others gather without keeping them.
const SURFACES_PER_PIXEL: usize = 8;

/// Two hits share gathers only when their shading normals are this close (14°).
const SAME_NORMAL: f32 = 0.97;

/// Per-thread scratch reused across receivers.
#[derive(Default)]
struct Scratch {
    mb: MicroBuffer,
    amb: amb::Amb,
    /// This receiver's ray per texel above its horizon: texel, world direction (jittered
    /// inside the texel) and the weight of its light ([`Texels::ray`]).
    rays: Vec<(u32, V, f32)>,
    /// Per ray: inside some rasterized leaf's cone, and the nearest of their triangles
    /// it met (shaded once the cut is done, so hidden hits cost nothing).
    aimed: Vec<bool>,
    nearest: Vec<Option<Hit>>,
    stack: Vec<(u32, u32)>,
    /// The near leaves this receiver's cut rasterized (page, node).
    near: Vec<(u32, u32)>,
    /// The rays inside the cone of the leaf being rasterized.
    in_cone: Vec<u32>,
}

thread_local! {
    static SCRATCH: RefCell<Scratch> = RefCell::new(Scratch::default());
}

/// The emission seen at a camera ray's first hit, for the edge rays.
fn seen_emission(scene: &Scene, tr: &mut Tracer, r: &Ray, c: &mut Counters) -> V {
    let mut ray = *r;
    let Some(hit) = scattering_hit(scene, tr, &mut ray, hole_number(r.d), &mut 0) else {
        return V::ZERO;
    };
    Surface::at(scene, &hit.hit, r.d).map_or(V::ZERO, |s| c.finite(s.emitted))
}

impl PbgiIntegrator {
    pub fn new(settings: &PbgiSettings, scene: &Scene, target: &Target) -> PbgiIntegrator {
        let seed = target.seed;
        // Where no material has rough specular lobes, no receiver draws extra rays' numbers.
        let glossy = glossy::any_glossy(scene);
        let glossy_rays = match settings.glossy_rays {
            Some(k) => k,
            None if glossy => GLOSSY_RAYS,
            None => 1,
        };
        let split = match settings.split {
            Some(n) => n,
            None if glossy => SPLIT,
            None => 1,
        };
        let [x0, x1, y0, y1] = target.window;
        let window = [(x1 - x0) as usize, (y1 - y0) as usize];
        let pixel_split = match (settings.pixel_split, settings.clusters) {
            (Some(m), _) => m,
            (None, 0) => PIXEL_SPLIT,
            (None, _) => 1,
        };
        PbgiIntegrator {
            settings: settings.clone(),
            texels: Texels::new(settings.resolution),
            bake_samples: 0,
            seed,
            bake_s: 0.0,
            splatted: AtomicU64::new(0),
            near_fragments: AtomicU64::new(0),
            exact_hits: AtomicU64::new(0),
            split_pairs: AtomicU64::new(0),
            split_rays: AtomicU64::new(0),
            gap_rays: AtomicU64::new(0),
            clusters: AtomicU64::new(0),
            gathered: Vec::new(),
            gathers: AtomicU64::new(0),
            reused: AtomicU64::new(0),
            traced_texels: AtomicU64::new(0),
            edge: EdgeRays::new(settings.edge_rays, scene, target),
            window: target.window,
            cache: None,
            radiance: None,
            radiance_hits: AtomicU64::new(0),
            radiance_rays: 0,
            radiance_s: 0.0,
            cache_hits: AtomicU64::new(0),
            cache_rejects: AtomicU64::new(0),
            crevices: Vec::new(),
            cache_s: 0.0,
            cache_rays: 0,
            refine_rays: 0,
            probe_order: Vec::new(),
            probed: 0,
            probe_rays: 0,
            probe_records: 0,
            glossy_rays,
            // With more first hits per pixel only the bounce splits (`Split::new`).
            split: split::Split::new(split, glossy_rays, window, pixel_split == 1),
            pixel_split: pixel_split::PixelSplit::new(pixel_split, seed, window[0] * window[1]),
            further_samples: AtomicU64::new(0),
            reuse_target: 0.0,
            tables: wpbgi::Tables::default(),
            wavelet_gathers: AtomicU64::new(0),
            amb_leaves: AtomicU64::new(0),
            light_splits: AtomicU64::new(0),
        }
    }

    /// Whether WPBGI gathers this receiver's glossy bounce.
    fn gathers_wavelets(&self, s: &Surface) -> bool {
        self.settings.glossy_bounce == wpbgi::GlossyBounce::Wavelet && wpbgi::gathers_wavelets(s)
    }

    /// Pixels in the window rendered: the size of every per-pixel table, which
    /// `PixelSample::at` indexes.
    fn window_pixels(&self) -> usize {
        let [x0, x1, y0, y1] = self.window;
        ((x1 - x0) * (y1 - y0)) as usize
    }

    /// Radiance along the camera ray up to the receiver x, the first non-specular hit:
    /// emission seen and direct light; and x with the path weight to it, when one bounce
    /// of indirect light is still to be gathered there. The emission seen at the primary
    /// hit goes through the edge rays.
    fn first_hit(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        px: &PixelSample,
        c: &mut Counters,
    ) -> (V, Option<Pending>) {
        let (l, pending, own) = self.first_hit_own(scene, tr, px, 0);
        let seen = |tr: &mut Tracer, r: &Ray, c: &mut Counters| seen_emission(scene, tr, r, c);
        (
            l + self.edge.emission(scene, tr, px, own, c, &seen),
            pending,
        )
    }

    /// `first_hit` with the emission seen at the primary hit apart (the third value);
    /// `salt` sets a further sample's exact rays apart from its pixel sample's (0 for
    /// the pixel sample's own).
    fn first_hit_own(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        px: &PixelSample,
        salt: u64,
    ) -> (V, Option<Pending>, V) {
        let (mut ray, mut beta, mut l, mut own) = (px.ray, V::ONE, V::ZERO, V::ZERO);
        // Alpha holes pass as the path tracer passes them, with its numbers.
        let mut passes = 0;
        for depth in 0..SMOOTH_DEPTH {
            // The next bounce's set: its first number also decides alpha holes.
            let [ud0, ud1, ..] = px.sampler.get4(2 * depth + 2);
            let Some(Scatter { hit, .. }) = scattering_hit(scene, tr, &mut ray, ud0, &mut passes)
            else {
                break;
            };
            let Some(s) = Surface::at(scene, &hit, ray.d) else {
                break;
            };
            match depth {
                0 => own = s.emitted,
                _ => l += beta * s.emitted,
            }
            if scene.last_segment(depth) || s.absorbs {
                break;
            }
            let [u_pick, ul0, ul1, u_lobe] = px.sampler.get4(2 * depth + 1);
            if s.bsdf.has_smooth_only() {
                let Some(bs) = s.bsdf.sample(s.wo_l, u_lobe, [ud0, ud1]) else {
                    break;
                };
                let wi = s.frame.to_world(bs.wi).normalize();
                if !on_side(&s.frame, s.n, wi) {
                    break;
                }
                beta *= bs.weight;
                ray = Ray {
                    o: offset_origin(s.p, s.err, s.ng, wi),
                    d: wi,
                    t_max: f32::INFINITY,
                };
                continue;
            }
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
                self.split_pairs.fetch_add(more(n), Relaxed);
                self.split_rays.fetch_add(more(bounce), Relaxed);
            }
            direct = sum / n as f32;
            l += beta * direct;
            if scene.last_segment(depth + 1) {
                break;
            }
            // A pixel's width at x, seen from the camera.
            let footprint = (s.p - scene.camera.pos).length() * 2.0 * scene.camera.tan_half
                / scene.camera.height as f32;
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
    fn radiance_lookup(&self, s: &Surface) -> Option<V> {
        let cache = self.radiance.as_ref()?;
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
    fn lobe_bounce(
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

    /// One bounce of indirect light at the receiver: its diffuse lobe from the
    /// micro-buffer; its rough specular lobes' reflection by WPBGI where
    /// `--pbgi-glossy-bounce wavelet` or `cache` asks (a dielectric's transmission by the
    /// lobe rays that left into it), else from the exact ray sampled from them at
    /// the first hit, which served direct light's MIS too (a lobe
    /// narrower than a micro-buffer texel would be convolved at a few texel centres only:
    /// with `--max-depth` 3 on a rough silver plinth of α 0.04 that overstated its pixels
    /// by 8–11%). `known`: what `reuse` gave for the receiver, when the caller asked it
    /// already.
    fn gather(
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
                    self.radiance_hits.fetch_add(1, Relaxed);
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
                    self.cache_hits.fetch_add(1, Relaxed);
                    l += lobe * e;
                }
                Reuse::Pixel(pixel, at) => self.lend(pixel, at, q.beta * lobe),
                Reuse::Gather(strata) => {
                    self.gathers.fetch_add(1, Relaxed);
                    let e = self.gather_irradiance(scene, tr, s, strata, field).0;
                    if !self.keep(q, e, q.beta * lobe, false) {
                        l += lobe * e;
                    }
                }
            }
        }
        l
    }

    /// The irradiance the cache holds at the receiver when nothing is over it within the
    /// records' reach; else a gather of its own when its sample is its pixel's first or
    /// falls at its surface's period (at the pixel's phase; [`Gathered::period`]); else
    /// its surface's gathers, or, when the pixel keeps no more surfaces, those of the one
    /// whose normal is closest to its own. A later surface's first gather waits for its
    /// phase like the others: gathering at first sight doubled the gathers of a 60-s
    /// render of sponza under the cut, whose gathers cost 1.6 ms each, for surfaces a few
    /// samples hit. The period falls below `--pbgi-reuse` where a surface's gathers
    /// scatter: the pixels the cache leaves to themselves on the showroom (the plinth's
    /// top under the gold bunny, which sees the bunny's glossy reflection of the panel)
    /// need a gather every few samples, not every 256th. It depends on earlier gathers
    /// only; that they also enter the mean leaves a bias of order 1 / gathers.
    fn reuse(&self, tr: &mut Tracer, q: &Pending) -> Reuse {
        if let Some((e, reach)) = self
            .cache
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
            self.cache_rejects.fetch_add(1, Relaxed);
        }
        self.reuse_in_pixel(q, false).into()
    }

    /// A gather of the receiver's own, or its pixel's gathers on its surface, as `reuse`
    /// decides past the cache; `glossy`: of WPBGI's glossy light.
    fn reuse_in_pixel(&self, q: &Pending, glossy: bool) -> InPixel {
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
                // WPBGI's gathers keep one period: their light is heavy-tailed (rays
                // meeting lamp-lit glossy surfaces), and a period set by the spread of a
                // surface's first gathers sampled more where those had caught a bright
                // tail, leaving the rest low (the showroom's floor −0.9% at 64 spp
                // against −0.05% at a fixed 8).
                let period = match glossy {
                    true => (self.settings.reuse as u64).min(PILOT_PERIOD),
                    false => g.period(self.settings.reuse as u64, self.reuse_target),
                };
                let k = g.samples as u64;
                g.samples += 1;
                // Each pixel's later gathers fall at its own phase of the period, so a pass
                // does about 1/period of the pixels' gathers instead of all of them every
                // period-th pass.
                if (k + self.phase(pixel)).is_multiple_of(period) {
                    return InPixel::Gather(self.pixel_strata(pixel, i, g.y.count as u32));
                }
                InPixel::Lend(pixel, i)
            }
            None if list.is_empty() => InPixel::Gather(self.pixel_strata(pixel, 0, 0)),
            None if list.len() < SURFACES_PER_PIXEL => {
                list.push(Gathered {
                    p: q.s.p,
                    n,
                    sum: V::ZERO,
                    y: Moments::default(),
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
    fn lend(&self, pixel: usize, at: usize, weight: V) {
        self.reused.fetch_add(1, Relaxed);
        if let Some(slot) = self.gathered.get(pixel) {
            let mut list = slot.lock().unwrap_or_else(PoisonError::into_inner);
            if let Some(g) = list.get_mut(at) {
                g.weight += weight;
            }
        }
    }

    /// The `index`-th gather on the `surface`-th surface a pixel keeps gathers for: each
    /// surface's gathers are a sequence of their own.
    fn pixel_strata(&self, pixel: usize, surface: usize, index: u32) -> Strata {
        let key = pixel as u64 ^ (self.seed as u64) << 32 ^ (surface as u64) << 56;
        Strata {
            seed: Hash::new(key ^ 0x5EED).u64(),
            index,
        }
    }

    /// Pixel `pixel`'s phase in `--pbgi-reuse`'s period: its gathers after the first fall
    /// at the samples s with s + phase a multiple of the surface's period
    /// ([`Gathered::period`]).
    fn phase(&self, pixel: usize) -> u64 {
        let r = self.settings.reuse as u64;
        Hash::new(pixel as u64 ^ (self.seed as u64) << 32).u64() % r
    }

    /// Whether a cached receiver is to be checked for a surface over it: in its pixel's
    /// first `PROBED_SAMPLES` samples, and in every later one where such a check found
    /// one. A pixel's samples run one per pass, so the flag is the same whatever the
    /// thread count.
    fn probes(&self, q: &Pending) -> bool {
        let flag = q.at.and_then(|(pixel, _)| self.crevices.get(pixel));
        q.sample < PROBED_SAMPLES || flag.is_some_and(|f| f.load(Relaxed))
    }

    /// The receiver at pixel (x, y)'s first hit through its centre, if there is one.
    fn centre_hit(&self, scene: &Scene, tr: &mut Tracer, x: u32, y: u32) -> Option<Pending> {
        let cam = &scene.camera;
        let [x0, x1, y0, _] = self.window;
        let px = PixelSample {
            x,
            y,
            at: ((y - y0) * (x1 - x0) + x - x0) as usize,
            index: 0,
            sampler: PixelSampler::new(self.seed, y * cam.width + x, 0),
            ray: cam.ray(x as f32 + 0.5, y as f32 + 0.5),
        };
        self.first_hit_own(scene, tr, &px, 0).1
    }

    /// Adds a gather's irradiance `e` to its pixel's surface, with `weight` for the sample
    /// that made it (see [`Gathered::weight`]); false when the pixel keeps no gathers or
    /// none more, and the sample is to take `e` itself.
    fn keep(&self, q: &Pending, e: V, weight: V, glossy: bool) -> bool {
        let Some((pixel, footprint)) = q.at else {
            return false;
        };
        let Some(slot) = self.gathered.get(pixel) else {
            return false;
        };
        let mut list = slot.lock().unwrap_or_else(PoisonError::into_inner);
        let (p, n) = (q.s.p, q.s.frame.n);
        let full = list.len() >= SURFACES_PER_PIXEL;
        match list.iter_mut().find(|g| g.holds(p, n, footprint, glossy)) {
            Some(g) => {
                g.sum += e;
                g.y.add(luminance(e));
                g.weight += weight;
            }
            None if !full => list.push(Gathered {
                p,
                n,
                sum: e,
                y: Moments::of([luminance(e)]),
                samples: 1,
                weight,
                glossy,
            }),
            None => return false,
        }
        true
    }

    /// The rough specular lobes' bounce: the hit of the direction sampled from them,
    /// shaded as a rasterized near hit is (baked light, else direct light).
    fn glossy_bounce(&self, scene: &Scene, tr: &mut Tracer, r: &LobeRay, u: [f32; 6]) -> V {
        let Some(hit) = &r.hit else {
            return V::ZERO;
        };
        self.exact_hits.fetch_add(1, Relaxed);
        let page = tr.page_handle(hit.page);
        r.weight * hit_light(scene, tr, &page, hit, r.w, || u).0
    }

    /// Irradiance at `s` from the cut, the near rays and the micro-buffer, the distance
    /// it may be carried ([`MicroBuffer::reach_distance`]) and the irradiance gradients
    /// (world space). `strata` places the gather in its pixel's or record's sequence. With
    /// a cluster's `field`, its far splats are taken as they are and the cut starts from
    /// its near nodes instead of the root.
    fn gather_irradiance(
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
        let white = Bsdf {
            diffuse: V::ONE,
            f0: V::ZERO,
            f90: V::ZERO,
            alpha: 1.0,
            trans: 0.0,
            tint: V::ONE,
            eta: 1.0,
        };
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
        };
        let strata = Strata {
            seed: key,
            index: 0,
        };
        self.gather_irradiance(scene, tr, &s, strata, None).0
    }

    /// Texel k's ray traced exactly, its hit shaded as a rasterized hit and weighted as the
    /// ray's place in the texel asks ([`Texels::ray`]): every texel under
    /// `--pbgi-rays`; otherwise where a rasterized leaf's cone promised geometry its
    /// triangles did not hold (without it the texel would show splats' partial coverage
    /// and the black background through the gaps).
    /// Returns the hit's depth, fragment id, weighted light and whether it was sampled.
    fn texel_ray(
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
        let hit = scattering_hit(scene, tr, &mut ray, hole_number(w), &mut 0)?.hit;
        let page = tr.page_handle(hit.page);
        let (sends, sampled) = hit_light(scene, tr, &page, &hit, w, || strata.shading(k));
        let l = Vec3::from(sends * weight);
        Some((hit.t, u64::MAX - k as u64, l, sampled))
    }
}

/// Whether a surface lies over `s` within `reach` along its normal.
fn covered_over(tr: &mut Tracer, s: &Surface, reach: f32) -> bool {
    let n = s.frame.n;
    tr.occluded(&Ray {
        o: offset_origin(s.p, s.err, s.ng, n),
        d: n,
        t_max: reach,
    })
}

/// A gather's place in a sequence of gathers at one pixel or record: texel k's ray is
/// jittered by point `index` of an Owen-scrambled Sobol sequence of its own (scrambled by
/// `seed` and k), so successive gathers stratify every texel between them, as one
/// pixel's bounces stratify its hemisphere over its samples; independent jitters left
/// room's gathers (9 a pixel, 192 texels each) twice as noisy as 2,048 path-traced bounces.
#[derive(Clone, Copy)]
struct Strata {
    seed: u64,
    index: u32,
}

impl Strata {
    /// Texel k's jitter.
    fn jitter(&self, k: u32) -> [f32; 2] {
        let [a, b, ..] = self.sampler(k).get4(0);
        [a, b]
    }

    /// Numbers for shading texel k's hit (a light sample, then a lobe ray), from the same
    /// sequence's next dimensions.
    fn shading(&self, k: u32) -> [f32; 6] {
        let sampler = self.sampler(k);
        let [a, b, c, d] = sampler.get4(1);
        let [e, f, ..] = sampler.get4(2);
        [a, b, c, d, e, f]
    }

    /// Texel k's sequence, at this gather's point: the pixel sampler's, with the texel
    /// standing for the pixel (it starts a new sequence past 2¹⁶ points).
    fn sampler(&self, k: u32) -> PixelSampler {
        PixelSampler::new((self.seed ^ self.seed >> 32) as u32, k, self.index)
    }
}

/// Where a receiver's irradiance comes from.
#[derive(Clone, Copy)]
enum Reuse {
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
enum InPixel {
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

/// A receiver whose indirect bounce is still to be gathered.
struct Pending {
    s: Surface,
    /// The rays sampled from x's rough specular lobes for its bounce (`--pbgi-glossy-rays`,
    /// or more by `--pbgi-split`; None where it has none, or where a sample left below the
    /// surface), each with the pixel sequence's numbers for shading its hit.
    rays: Vec<(Option<LobeRay>, [f32; 6])>,
    /// Path weight from the camera to x.
    beta: V,
    /// Seed of its exact rays.
    key: u64,
    /// Its pixel and the pixel's width at x, for sharing gathers; None in the bake.
    at: Option<(usize, f32)>,
    /// Its sample number in the pixel.
    sample: u32,
    /// Its glossy bounce from the radiance cache's records, where they cover it.
    cached: Option<V>,
}

/// Bytes of a per-pixel table, in all and per pixel (none when it is empty: off).
fn per_pixel_bytes<T>(pixels: &[Mutex<T>]) -> [u64; 2] {
    let per_pixel = match pixels.is_empty() {
        true => 0,
        false => size_of::<Mutex<T>>() as u64,
    };
    [per_pixel * pixels.len() as u64, per_pixel]
}

/// Sets a pixel's further samples' exact rays apart (`PbgiIntegrator::sample`).
const FURTHER_SALT: u64 = 0x6a09_e667_f3bc_c908;

impl PbgiIntegrator {
    /// One sample's light, `l` up to its receiver and `pending`'s gather, noted for the
    /// pixel's spread and weighted by its `share` of the pass's samples of the pixel
    /// (its gather's held-back weight too).
    #[allow(clippy::too_many_arguments)]
    fn finish(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        at: usize,
        mut l: V,
        pending: Option<Pending>,
        share: f32,
        rays_before: u64,
        c: &mut Counters,
    ) -> V {
        if let Some(mut q) = pending {
            let beta = q.beta;
            q.beta *= share;
            l += beta * self.gather(scene, tr, &q, None, None);
        }
        c.paths += 1;
        let l = c.finite(l);
        let rays = tr.rays - rays_before;
        self.pixel_split.note(at, luminance(l), rays);
        l * share
    }
}

impl Integrator for PbgiIntegrator {
    /// The first pass bakes (or reads `--radiance`) and attaches the light to the pages,
    /// so time budgets count the bake.
    /// One sample per pass when edge rays or the cache are on: a pass's edge mask comes
    /// from the passes before it, and the records are refined between passes.
    fn pass_samples(&self, spp: u32) -> u32 {
        // Edge rays and the cache's refinement work between passes.
        match (self.settings.edge_rays, self.settings.cache) {
            (0, 0.0) => spp,
            _ => 1,
        }
    }

    fn begin_pass(&mut self, scene: &Scene, pass: &Pass) -> Result<u64> {
        let seen = |tr: &mut Tracer, r: &Ray, c: &mut Counters| seen_emission(scene, tr, r, c);
        let edge_rays = self.edge.begin_pass(scene, pass.first, pass.count, &seen);
        // The pairs' split weighs a pair's spread against one sample's variance, which
        // the film's, of a pass's mean of a pixel's samples, understates where they split.
        let variance = self.pixel_split.begin_pass().unwrap_or(pass.variance);
        self.split.begin_pass(variance);
        self.reuse_target = self.reuse_target(pass, variance);
        if pass.first > 0 {
            let t = Instant::now();
            let refine_rays = self.refine_cache(scene, pass);
            let left = |pass: &Pass| pass.left.map(|l| l.saturating_sub(t.elapsed()));
            let probe_rays = self.probe_cache(
                scene,
                &Pass {
                    left: left(pass),
                    ..*pass
                },
            );
            self.cache_s += t.elapsed().as_secs_f64();
            let r = Instant::now();
            let radiance_rays = self.refine_radiance(
                scene,
                &Pass {
                    left: left(pass),
                    ..*pass
                },
            );
            self.radiance_s += r.elapsed().as_secs_f64();
            return Ok(edge_rays + refine_rays + probe_rays + radiance_rays);
        }
        if self.settings.reuse > 1 {
            self.gathered = (0..self.window_pixels())
                .map(|_| Mutex::default())
                .collect();
        }
        let t = Instant::now();
        let archive = &scene.cache.archive;
        let file = match &self.settings.radiance {
            Some(path) => canopy_format::radiance::RadianceFile::open(path, archive)?,
            None => {
                let mut params = self.settings.bake.params(self.seed);
                if self.settings.rays {
                    // Texel rays, and WPBGI's leaf rays, read only the patches' diffuse
                    // light.
                    params.wavelet = glossy::WaveletMode::Off;
                }
                let (file, samples) = bake::bake_scratch(scene, &params)?;
                self.bake_samples = samples;
                file
            }
        };
        scene.cache.attach_radiance(file)?;
        self.bake_s = t.elapsed().as_secs_f64();
        let mut cache_rays = 0;
        if self.settings.cache > 0.0 {
            let t = Instant::now();
            let (cache, rays) = self.build_cache(scene, self.settings.cache);
            (self.cache, cache_rays) = (Some(cache), rays);
            self.crevices = (0..self.window_pixels())
                .map(|_| AtomicBool::new(false))
                .collect();
            self.cache_rays = rays;
            self.cache_s = t.elapsed().as_secs_f64();
            self.probe_order = self.probe_order();
        }
        if self.settings.glossy_bounce == wpbgi::GlossyBounce::Cache {
            let t = Instant::now();
            let (cache, rays) = self.build_radiance_cache(scene, self.settings.cache);
            self.radiance = Some(cache);
            cache_rays += rays;
            self.radiance_rays = rays;
            self.radiance_s = t.elapsed().as_secs_f64();
        }
        Ok(self.bake_samples + edge_rays + cache_rays)
    }

    /// The mean of the pixel's sample and, where `--pbgi-pixel-split` asks, further
    /// samples of it from its own sequence.
    fn sample(&self, scene: &Scene, tr: &mut Tracer, px: &PixelSample, c: &mut Counters) -> V {
        let m = self.pixel_split.count(px.at);
        let share = 1.0 / m as f32;
        let rays = tr.rays;
        let (l, pending, own) = self.first_hit_own(scene, tr, px, 0);
        let seen = |tr: &mut Tracer, r: &Ray, c: &mut Counters| seen_emission(scene, tr, r, c);
        let edge = self.edge.emission(scene, tr, px, own, c, &seen);
        let mut sum = self.finish(scene, tr, px.at, l + edge, pending, share, rays, c);
        // On a silhouette pixel the edge rays' mean stands for every sample's emission.
        let masked = self.edge.masked(px.at);
        let cam = &scene.camera;
        let further = self
            .pixel_split
            .further(px.at, px.y * cam.width + px.x, m - 1);
        self.further_samples
            .fetch_add(further.len() as u64, Relaxed);
        for (i, sampler) in further {
            let [jx, jy, ..] = sampler.get4(0);
            let sub = PixelSample {
                ray: cam.ray(px.x as f32 + jx, px.y as f32 + jy),
                sampler,
                x: px.x,
                y: px.y,
                at: px.at,
                index: px.index,
            };
            let salt = Hash::new(i as u64 ^ FURTHER_SALT).u64();
            let rays = tr.rays;
            let (l, pending, own) = self.first_hit_own(scene, tr, &sub, salt);
            let own = if masked { edge } else { own };
            sum += self.finish(scene, tr, px.at, l + own, pending, share, rays, c);
        }
        sum
    }

    fn sample_tile(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        pxs: &[PixelSample],
        c: &mut Counters,
    ) -> Vec<V> {
        if self.settings.clusters == 0 {
            return pxs.iter().map(|px| self.sample(scene, tr, px, c)).collect();
        }
        self.sample_clustered(scene, tr, pxs, c)
    }

    fn passes(&self) -> Vec<String> {
        let s = &self.settings;
        vec![
            match &s.radiance {
                Some(path) => format!("bake: read from {} ({:.2} s)", path.display(), self.bake_s),
                None => format!(
                    "bake: {} bounce(s) of light reflected by every node, {} light samples per triangle ({:.2} s)",
                    s.bake.bounces, s.bake.bake_samples, self.bake_s
                ),
            },
            {
                let glossy = match (self.glossy_rays, self.split.most()) {
                    (1, _) => "glossy lobes: one exact ray".to_string(),
                    (k, n) if n > k => format!(
                        "glossy lobes: {k} exact rays, each paired with a light sample for direct light, {} split up to {n} per pixel by the spread of its earlier samples",
                        match self.split.splits_direct() {
                            true => "pairs and bounce rays",
                            false => "bounce rays",
                        }
                    ),
                    (k, _) => format!(
                        "glossy lobes: {k} exact rays, each paired with a light sample for direct light"
                    ),
                };
                let glossy = match s.glossy_bounce {
                    wpbgi::GlossyBounce::Wavelet | wpbgi::GlossyBounce::Cache => {
                        let (tables, coefs) = self.tables.sizes();
                        format!(
                            "{glossy}; the rough lobes' reflection by WPBGI (a dielectric's transmission by its lobe rays): {} gathers into adaptive micro-buffers of {:.0} leaves on average ({:.1} split by the light), the product with {tables} BRDF table(s) of {coefs} Haar coefficients",
                            self.wavelet_gathers.load(Relaxed),
                            self.amb_leaves.load(Relaxed) as f64
                                / self.wavelet_gathers.load(Relaxed).max(1) as f64,
                            self.light_splits.load(Relaxed) as f64
                                / self.wavelet_gathers.load(Relaxed).max(1) as f64
                        )
                    }
                    wpbgi::GlossyBounce::Rays => glossy,
                };
                match s.rays {
                    true => format!(
                        "pbgi: indirect light from a {}² hemicube micro-buffer for diffuse lobes, every texel's ray traced and reading the baked light ({glossy})",
                        s.resolution
                    ),
                    false => format!(
                        "pbgi: indirect light from a cut at {} texels' solid angle into a {}² hemicube micro-buffer for diffuse lobes ({glossy}); near leaves rasterized with baked patch light",
                        s.angle, s.resolution
                    ),
                }
            },
            match self.pixel_split.most() {
                1 => "pixel split: off (one camera ray per pixel and pass)".into(),
                m => format!(
                    "pixel split: up to {m} camera rays per pixel and pass where its earlier samples scatter ({} further samples)",
                    self.further_samples.load(Relaxed)
                ),
            },
            format!(
                "pbgi: each surface of a pixel gathers at every {}-th sample landing on it, the others reusing its gathers' irradiance",
                s.reuse
            ),
            match &self.cache {
                Some(c) => format!(
                    "pbgi: irradiance cache of error bound {}: {} records placed coarse to fine over the pixels ({} of them where one of {} probes disagreed with the cache), averaging {} gathers ({:.2} s), read by the receivers they cover",
                    s.cache, c.len(), self.probe_records, self.probed, c.gathers(), self.cache_s
                ),
                None => "pbgi: no irradiance cache".into(),
            },
            match &self.radiance {
                Some(c) => format!(
                    "pbgi: radiance cache: {} records placed coarse to fine where one would cover its 8 neighbouring pixels, holding {} gathers of {} Haar coefficients each ({:.2} s), the glossy bounce of {} receivers; the others' from exact lobe rays",
                    c.records.len(),
                    c.records.gathers(),
                    c.coefficients(),
                    self.radiance_s,
                    self.radiance_hits.load(Relaxed)
                ),
                None => "pbgi: no radiance cache".into(),
            },
            self.edge.describe(),
        ]
    }

    fn stats(&self) -> Stats {
        let (brdf_tables, brdf_coefficients) = self.tables.sizes();
        Stats::Pbgi(PbgiStats {
            pbgi_angle: self.settings.angle,
            pbgi_resolution: self.settings.resolution,
            bake_seconds: self.bake_s,
            bake_samples: self.bake_samples,
            splatted_nodes: self.splatted.load(Relaxed),
            near_fragments: self.near_fragments.load(Relaxed),
            exact_hits: self.exact_hits.load(Relaxed),
            split_pairs: self.split_pairs.load(Relaxed),
            split_rays: self.split_rays.load(Relaxed),
            further_samples: self.further_samples.load(Relaxed),
            gap_rays: self.gap_rays.load(Relaxed),
            receiver_clusters: self.settings.clusters,
            clustered_receivers: self.clusters.load(Relaxed),
            pbgi_reuse: self.settings.reuse,
            gathers: self.gathers.load(Relaxed),
            traced_texels: self.traced_texels.load(Relaxed),
            reused_gathers: self.reused.load(Relaxed),
            edge_pixels: self.edge.pixels(),
            pbgi_cache: self.settings.cache,
            cache_records: self.cache.as_ref().map_or(0, |c| c.len() as u64),
            cache_gathers: self.cache.as_ref().map_or(0, |c| c.gathers()),
            cache_hits: self.cache_hits.load(Relaxed),
            cache_rejects: self.cache_rejects.load(Relaxed),
            cache_probes: self.probed as u64,
            cache_probe_records: self.probe_records,
            wavelet_gathers: self.wavelet_gathers.load(Relaxed),
            amb_leaves: self.amb_leaves.load(Relaxed),
            amb_light_splits: self.light_splits.load(Relaxed),
            brdf_tables,
            brdf_coefficients,
            radiance_records: self.radiance.as_ref().map_or(0, |c| c.records.len() as u64),
            radiance_gathers: self.radiance.as_ref().map_or(0, |c| c.records.gathers()),
            radiance_hits: self.radiance_hits.load(Relaxed),
        })
    }

    /// The gathers kept per pixel.
    fn held_back(&self) -> Vec<(usize, V)> {
        let pixel = |list: &Vec<Gathered>| {
            let mean = |g: &Gathered| {
                let gathered = list
                    .iter()
                    .filter(|o| o.y.count > 0 && o.glossy == g.glossy);
                let closest = gathered.max_by(|a, b| a.n.dot(g.n).total_cmp(&b.n.dot(g.n)));
                let from = if g.y.count > 0 { Some(g) } else { closest };
                from.map_or(V::ZERO, |o| g.weight * o.sum / o.y.count as f32)
            };
            list.iter().map(mean).sum::<V>()
        };
        let lists = self
            .gathered
            .iter()
            .map(|slot| pixel(&slot.lock().unwrap_or_else(PoisonError::into_inner)));
        lists.enumerate().filter(|(_, l)| *l != V::ZERO).collect()
    }

    fn state_bytes(&self) -> [u64; 2] {
        let kept: usize = self
            .gathered
            .iter()
            .map(|m| m.lock().unwrap_or_else(PoisonError::into_inner).capacity())
            .sum();
        let slots = self.gathered.len() * size_of::<Mutex<Vec<Gathered>>>();
        let cached = self.cache.as_ref().map_or(0, IrradianceCache::bytes)
            + self
                .radiance
                .as_ref()
                .map_or(0, radiance_cache::RadianceCache::bytes);
        let bytes = (slots + kept * size_of::<Gathered>()) as u64 + cached;
        let edge = self.edge.bytes();
        let [split, split_per_pixel] = self.split.bytes();
        let [further, further_per_pixel] = self.pixel_split.bytes();
        [
            bytes + edge + split + further,
            bytes / self.gathered.len().max(1) as u64 + edge + split_per_pixel + further_per_pixel,
        ]
    }

    fn seconds(&self) -> Vec<(&'static str, f64)> {
        vec![
            ("bake", self.bake_s),
            ("cache", self.cache_s),
            ("radiance cache", self.radiance_s),
        ]
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

#[cfg(test)]
mod period_tests {
    use super::*;

    /// A surface with `gathers` of luminance-grey irradiance `values`, hit by `samples`
    /// samples of weight one each.
    fn surface(values: &[f32], samples: u32) -> Gathered {
        Gathered {
            p: V::ZERO,
            n: V::Z,
            sum: values.iter().map(|&v| V::splat(v)).sum(),
            y: Moments::of(values.iter().copied()),
            samples,
            weight: V::splat(samples as f32),
            glossy: false,
        }
    }

    /// The period is R until a surface's first gather and until `PILOT_PERIOD` samples
    /// landed on it, `PILOT_PERIOD` until its second, then √(target / s²) taken down to a
    /// power of two: shorter as the gathers scatter more, R where they agree or no
    /// sample variance is known yet, never above R nor below 1.
    #[test]
    fn a_surfaces_gather_period_shortens_as_its_gathers_scatter() {
        let r = 256;
        assert_eq!(surface(&[], 40).period(r, 1.0), r);
        assert_eq!(surface(&[1.0], 3).period(r, 1.0), r);
        assert_eq!(surface(&[1.0], 9).period(r, 1.0), PILOT_PERIOD);
        assert_eq!(surface(&[1.0], 9).period(4, 1.0), 4);
        assert_eq!(surface(&[1.0, 1.0, 1.0], 40).period(r, 1.0), r);
        assert_eq!(surface(&[1.0, 3.0], 40).period(r, 0.0), r);
        // Spread s² = 2 (values 1 and 3): √(target / 2).
        assert_eq!(surface(&[1.0, 3.0], 40).period(r, 2.0 * 100.0), 8);
        assert_eq!(surface(&[1.0, 3.0], 40).period(r, 2.0 * 0.25), 1);
        assert_eq!(surface(&[1.0, 3.0], 40).period(r, 2.0 * 1e9), r);
        let mut last = r;
        for spread in [0.01f32, 0.1, 1.0, 10.0, 100.0] {
            let g = surface(&[1.0, 1.0 + spread, 1.0 - spread], 40);
            let p = g.period(r, 50.0);
            assert!(
                p.is_power_of_two() && p <= last,
                "{spread}: {p} after {last}"
            );
            last = p;
        }
        assert_eq!(last, 1);
    }
}
