//! `--integrator pbgi`: point-based global illumination over the archive's hierarchy
//! (003 ch. 2; Christensen 2008 as cited there).
//!
//! The bake (`bake`) stores in every node the light it reflects diffusely: direct light,
//! and by default every further bounce, carried by walks from each patch (`walk`). At the
//! first non-specular hit x the renderer adds the emission seen, direct light as the path
//! tracer takes it (a light sample, weighed by MIS against the ray sampled from x's rough
//! specular lobes), and the indirect light gathered from the hierarchy, by the texel rays
//! below (`--pbgi-gather rays`, the default) or by a cut:
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
//!   gathers at every `--pbgi-reuse`-th sample landing on it, its other samples
//!   reusing its gathers' mean;
//! - `--pbgi-gather rays`, the default, skips the cut: every texel's ray is traced and
//!   reads the bake;
//! - x's rough specular lobes, mostly narrower than a texel, take exact rays sampled
//!   from them instead (`--pbgi-glossy-rays`; the first with the pixel's own sample
//!   sequence, as the path tracer's next bounce would), their hits shaded as a rasterized
//!   hit is; each ray also serves a light sample's MIS for x's direct light;
//! - or, with `--pbgi-glossy-bounce wavelet`, WPBGI gathers them from the cloud (`wpbgi`:
//!   the adaptive micro-buffer and the wavelet BRDF product, 000 §3.2 and 002 §4.2), and
//!   with `cache` those gathers are kept as radiance records shared between pixels
//!   (`radiance_cache`, 002 §4.3), receivers no record covers taking the exact rays.
//!
//! A pixel whose earlier samples scattered may take more camera samples a pass (the
//! driver's `--pixel-split`, off by default): on the glossy showroom it pays, as half of
//! the noise is the sample's position in the pixel, which nothing at one first hit lowers.
//!
//! Smooth mirrors and glass are followed exactly (one sampled bounce each, with the path
//! tracer's Russian roulette), so a perfectly specular surface degrades to the exact estimator
//! (000 §A.8). The cloud holds every bounce by default, or `--bounces N` (1: direct light
//! reflected once): compare with `--max-depth` 2 + N of the path tracer (camera → x →
//! node → … → light). A gather's ray that meets a surface the bake does not cover (glossy,
//! specular or a back face) follows the light on to the next one it does (`walk::onward`).
//! A smooth lobe layered over rough ones (a smooth clearcoat or mirror over a diffuse base)
//! is followed exactly with the probability of choosing it, the rough lobes estimated at
//! the receiver otherwise (`receiver::lobes`).

mod amb;
pub mod bake;
mod brdf_table;
mod cut;
mod gather;
pub mod glossy;
pub mod irradiance_cache;
mod memory;
pub mod microbuffer;
pub mod patch;
mod pixel_reuse;
mod radiance_cache;
mod receiver;
pub mod receiver_clusters;
mod records;
mod settings;
mod split;
mod stats;
mod surface;
mod walk;
pub mod wpbgi;

use super::edge::EdgeRays;
use super::{Counters, Integrator, Pass, PixelSample, Scene, Stats, Target};
use crate::trace::{Ray, Tracer};
use anyhow::Result;
use gather::*;
use glam::Vec3A as V;
use irradiance_cache::IrradianceCache;
use microbuffer::Texels;
use pixel_reuse::*;
use receiver::*;
pub use settings::PbgiSettings;
use settings::{GLOSSY_RAYS, SPLIT};
use stats::PbgiCounters;
pub use stats::PbgiStats;
use std::sync::atomic::AtomicBool;
use std::sync::Mutex;
use std::time::Instant;

pub struct PbgiIntegrator {
    settings: PbgiSettings,
    /// What the render counted.
    tally: PbgiCounters,
    /// The memory budget's share for this state (per-pixel tables and records), if any.
    state_cap: Option<u64>,
    /// Surfaces a pixel keeps gathers for (`SURFACES_PER_PIXEL`, fewer under a budget).
    surfaces_per_pixel: usize,
    /// Light samples the bake took (0 when read from a file).
    bake_samples: u64,
    texels: Texels,
    seed: u32,
    bake_s: f64,
    /// Per pixel of the window (by its index there): the irradiance gathered there, per
    /// surface.
    gathered: Vec<Mutex<Vec<Gathered>>>,
    /// Edge rays at lamps' silhouettes.
    edge: EdgeRays,
    /// The window rendered (`Target::window`), where the cache's records are placed.
    window: [u32; 4],
    irradiance_cache: Option<IrradianceCache>,
    /// WPBGI's radiance records (`--pbgi-glossy-bounce cache`), and the receivers they gave.
    radiance_cache: Option<radiance_cache::RadianceCache>,
    /// Rays and seconds of the radiance records' gathers.
    radiance_rays: u64,
    radiance_s: f64,
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
    /// The bake holds every bounce: light past surfaces it does not cover is followed
    /// (`walk::onward`).
    onward: bool,
    /// Pairs and bounce rays per glossy receiver, per pixel (`--pbgi-split`).
    split: split::Split,
    /// WPBGI's BRDF tables, and its gathers and their leaves.
    tables: wpbgi::Tables,
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
        PbgiIntegrator {
            settings: settings.clone(),
            tally: PbgiCounters::default(),
            state_cap: target.state_bytes,
            surfaces_per_pixel: SURFACES_PER_PIXEL,
            texels: Texels::new(settings.resolution),
            bake_samples: 0,
            seed,
            bake_s: 0.0,
            gathered: Vec::new(),
            edge: EdgeRays::new(settings.edge_rays, scene, target, true),
            window: target.window,
            irradiance_cache: None,
            radiance_cache: None,
            radiance_rays: 0,
            radiance_s: 0.0,
            crevices: Vec::new(),
            cache_s: 0.0,
            cache_rays: 0,
            refine_rays: 0,
            probe_order: Vec::new(),
            probed: 0,
            probe_rays: 0,
            probe_records: 0,
            glossy_rays,
            onward: false,
            // With more first hits per pixel only the bounce splits (`Split::new`).
            split: split::Split::new(split, glossy_rays, window, target.pixel_split == 1),
            tables: wpbgi::Tables::default(),
        }
    }

    /// Pixels in the window rendered: the size of every per-pixel table, which
    /// `PixelSample::at` indexes.
    fn window_pixels(&self) -> usize {
        let [x0, x1, y0, y1] = self.window;
        ((x1 - x0) * (y1 - y0)) as usize
    }
}

impl Integrator for PbgiIntegrator {
    /// The first pass bakes (or reads `--bake-in`) and attaches the light to the pages,
    /// so time budgets count the bake.
    /// One sample per pass when edge rays or the cache are on: a pass's edge mask comes
    /// from the passes before it, and the records are refined between passes.
    fn pass_samples(&self, left: u32, _done: u32) -> u32 {
        // Edge rays and the cache's refinement work between passes.
        match (self.settings.edge_rays, self.settings.cache) {
            (0, 0.0) => left,
            _ => 1,
        }
    }

    fn begin_pass(&mut self, scene: &Scene, pass: &Pass) -> Result<u64> {
        let seen = |tr: &mut Tracer, r: &Ray, c: &mut Counters| seen_emission(scene, tr, r, c);
        let edge_rays = self.edge.begin_pass(scene, pass.first, pass.count, &seen);
        // The pairs' split weighs a pair's spread against one sample's variance, which
        // the film's, of a pass's mean of a pixel's samples, understates where they split.
        let variance = pass.camera_sample_variance.unwrap_or(pass.variance);
        self.split.begin_pass(variance);
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
        self.fit_tables()?;
        if self.settings.reuse > 1 {
            self.gathered = (0..self.window_pixels())
                .map(|_| Mutex::default())
                .collect();
        }
        let t = Instant::now();
        let archive = &scene.cache.archive;
        let file = match &self.settings.bake_in {
            Some(path) => {
                let file = canopy_format::bake::BakeFile::open(path, archive)?;
                bake::check_environment(&file, scene, path)?;
                file
            }
            None => {
                let mut params = self.settings.bake.params(self.seed);
                // Under --max-depth D the cloud holds what paths of D segments reflect
                // past the receiver's gather: D − 2 bounces.
                if params.bounces.is_none() {
                    params.bounces = scene.max_depth.map(|d| d.saturating_sub(2).max(1));
                }
                if self.settings.rays() {
                    // Texel rays, and WPBGI's leaf rays, read only the patches' diffuse
                    // light.
                    params.wavelet = glossy::WaveletMode::Off;
                }
                let (file, samples) = bake::bake_scratch(scene, &params)?;
                self.bake_samples = samples;
                file
            }
        };
        self.onward = file.header.bounces == canopy_format::bake::ALL_BOUNCES;
        scene.cache.attach_bake(file)?;
        self.bake_s = t.elapsed().as_secs_f64();
        let mut cache_rays = 0;
        if self.settings.cache > 0.0 {
            let t = Instant::now();
            let (cache, rays) = self.build_cache(scene, self.settings.cache);
            (self.irradiance_cache, cache_rays) = (Some(cache), rays);
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
            self.radiance_cache = Some(cache);
            cache_rays += rays;
            self.radiance_rays = rays;
            self.radiance_s = t.elapsed().as_secs_f64();
        }
        Ok(self.bake_samples + edge_rays + cache_rays)
    }

    fn sample(&self, scene: &Scene, tr: &mut Tracer, px: &PixelSample, c: &mut Counters) -> V {
        self.sample_pixel(scene, tr, std::slice::from_ref(px), c)[0]
    }

    /// A pixel's pass sample and its further ones: on a silhouette pixel the pass
    /// sample's edge rays' mean stands for every sample's emission.
    fn sample_pixel(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        pxs: &[PixelSample],
        c: &mut Counters,
    ) -> Vec<V> {
        let Some((px, further)) = pxs.split_first() else {
            return Vec::new();
        };
        let (l, pending, own) = self.first_hit_own(scene, tr, px);
        let seen = |tr: &mut Tracer, r: &Ray, c: &mut Counters| seen_emission(scene, tr, r, c);
        let edge = self.edge.emission(scene, tr, px, own, c, &seen);
        let mut out = Vec::with_capacity(pxs.len());
        out.push(self.finish(scene, tr, l + edge, pending, px.share, c));
        let masked = self.edge.masked(px.at);
        for sub in further {
            let (l, pending, own) = self.first_hit_own(scene, tr, sub);
            let own = if masked { edge } else { own };
            out.push(self.finish(scene, tr, l + own, pending, sub.share, c));
        }
        out
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
        self.describe()
    }

    fn stats(&self) -> Stats {
        self.pbgi_stats()
    }

    /// The gathers kept per pixel.
    fn held_back(&self) -> Vec<(usize, V)> {
        self.held_back_gathers()
    }

    fn state_bytes(&self) -> u64 {
        self.state_bytes_now()
    }

    fn seconds(&self) -> Vec<(&'static str, f64)> {
        vec![
            ("bake", self.bake_s),
            ("cache", self.cache_s),
            ("radiance cache", self.radiance_s),
        ]
    }
}
