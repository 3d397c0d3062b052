//! `--integrator cone`: stochastic cone casts with diffuse radiance stored in the nodes
//! (004 §4.5–4.6, §4.8).
//!
//! Each cast is a ray that stops at the first node the cone's radius outgrows (eq. 4.12,
//! scaled by `--cone-scale`; 0 traces exact rays). Primary cones open by one pixel
//! (eq. 4.19) and are jittered in the pixel; after a diffuse bounce tan α = `--diffuse-tan`
//! (eq. 4.20) from the surface; a mirror keeps the cone and resamples the direction
//! uniformly inside it (eq. 4.14–4.16). Light samples are cones of the pixel's opening.
//! Every diffuse hit — a leaf triangle's cell or a whole node — estimates its incident
//! radiance with one light sample and one cosine-sampled bounce, combined by MIS as the
//! path tracer does (eq. 4.27 masks instead; see `walk`). The primary hit keeps its own
//! sample, so visibility and light on screen are exact, and adds it to its cell. A
//! deeper hit answers with its cell's mean (eq. 4.24–4.25) only where a diffuse bounce's
//! footprint at that distance covers the cell (`STORE_TAN`; a node always, the cone
//! stopped there), and only such hits add to it; elsewhere it takes its own sample. A
//! hit whose cell already holds enough samples answers without recursing and adds
//! nothing (`--cone-reuse`, a soft form of §4.6.1's convergence). No pixel shows a cell's
//! mean, so cells cannot show as patches on screen.
//! After each pass the store is pulled up the tree (§4.8) so nodes first met by wide cones
//! start from their children's light. Only cones that stop at nodes read a node's pulled
//! light: at `--cone-scale` 0 the pull runs once, for `--store-out`.
//!
//! Surfaces with specular or transmissive lobes are traced as the path tracer does (no
//! storage); a smooth bounce bends the cone by the surface's curvature (`bent_tan`). Nodes
//! are shaded with the cluster BRDF: a reflect / refract / diffuse choice from the node's
//! Fresnel table and refractiveness (§4.3), a Phong lobe about the heuristic direction
//! (eq. 4.7–4.11), and a Lambertian part with the area-weighted albedo and the Θ heuristic
//! of eq. 4.4 for light samples. When the light pass (`light_pass`, §4.7) runs, diffuse
//! hits add the caustic light it stored, and emission reached from a diffuse hit through
//! smooth bounces only is masked, so caustic paths count once. The emission seen at the
//! primary hit comes back apart from the rest, so the renderer can average it over more of
//! the pixel where the pixel straddles a lamp's silhouette (`seen_emission`).

//!
//! Modules: `walk` (the path), `cluster` (the cluster BRDF), `optics` (cones after smooth
//! bounces), `light_pass` (caustics). The stored light and its pull are `crate::radiance`.

mod cluster;
pub mod light_pass;
mod optics;
mod walk;

pub use cluster::theta_norm;

use super::{Counters, Integrator, PixelSample, Scene, Stats, Target};
use crate::material::Material;
use crate::radiance::{pull, Keys, RadianceStore};
use crate::sampler::PixelSampler;
use crate::trace::{Cone, Hit, Tracer};
use anyhow::Context;
use glam::Vec3A as V;
use std::sync::atomic::{AtomicU32, Ordering::Relaxed};
use std::time::Instant;
use walk::seen_emission;

/// Tan of the footprint a diffuse bounce resolves stored light with: a cell answers a
/// hit at distance t when its side is at most 2·t·STORE_TAN. 0.3 is the thesis's
/// diffuse cone (004 eq. 4.20's d); geometry keeps `--diffuse-tan`'s finer cones.
pub const STORE_TAN: f32 = 0.3;

/// Default tan α after a diffuse bounce (004 eq. 4.20's d; `--diffuse-tan`). Deviation:
/// the thesis chose 0.3 by eye; measured against the path tracer, clusters standing in
/// for their triangles at that width biased the image mean by −0.95% on sponza and +7.1%
/// on 20 M bunnies, against −0.15% and +1.4% at 0.03, which cost sponza no time and the
/// bunnies 18% (README).
pub const DIFFUSE_TAN: f32 = 0.03;

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum LightPass {
    /// When the scene has lights and smooth mirror or glass surfaces.
    Auto,
    On,
    Off,
}

/// The cone integrator's parameters (its command-line flags, which are refused under
/// another integrator).
#[derive(Clone, Debug, clap::Args)]
#[command(next_help_heading = "Cone integrator (--integrator cone)")]
pub struct ConeSettings {
    /// The cone radius in the LOD rule is multiplied by this: 1 is the thesis's level of
    /// detail (cones stop at nodes as wide as themselves, 004 eq. 4.12), larger values
    /// stop at coarser nodes. The default 0 traces exact rays and keeps the stored light's
    /// reuse: at scale 1 nodes shading for their triangles biased the image mean by
    /// +0.33% and tripled the error on `room`, −0.19% on sponza, against at most 0.13%
    /// exact (docs/cone-room.md). Scale 1 touches fewer nodes and pages.
    #[arg(long = "cone-scale", default_value_t = 0.0, value_parser = crate::units::parse_non_negative)]
    pub scale: f32,
    /// Tan of the half-angle of the cones after a diffuse or glossy bounce (004 eq. 4.20's
    /// d; the thesis used 0.3). Wider cones stop at coarser nodes: fewer pages and nodes,
    /// more bias from clusters standing in for their triangles.
    #[arg(long, default_value_t = DIFFUSE_TAN, value_parser = crate::units::parse_non_negative)]
    pub diffuse_tan: f32,
    /// Samples after which a node's stored light is converged: it takes no more, and every
    /// path reading it stops there (004 §4.6.1 used 65536). Default: never. A converged
    /// cell's first samples serve every later read, so one rare bright sample among them
    /// shifts the whole image's mean (docs/cone-room.md); `--cone-reuse` bounds that.
    #[arg(long = "cone-samples", value_parser = clap::value_parser!(u32).range(1..))]
    pub samples: Option<u32>,
    /// How many reads one stored sample serves at most, on average: a hit reading a cell
    /// that holds n samples adds a fresh one with probability min(1, max(A/n, 1/A)), and
    /// otherwise stops there with the cell's mean (first diffuse hits, which keep their
    /// own sample, add to the cell with the same probability). 1 adds at every read.
    #[arg(long, value_name = "A", default_value_t = 8, value_parser = clap::value_parser!(u32).range(1..=1024))]
    pub cone_reuse: u32,
    /// The light pass that carries caustics (light through smooth mirrors and glass onto
    /// diffuse surfaces, 004 §4.7). `auto` runs it when the scene has both lights and
    /// smooth specular surfaces; `off` leaves caustics to the eye paths.
    #[arg(long, value_enum, default_value_t = LightPass::Auto)]
    pub light_pass: LightPass,
    /// Photons per light pass (one pass before every eye pass; default: as many as the
    /// full image has pixels, whatever --crop says).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    pub photons: Option<u32>,
    /// On pixels where earlier samples, of the pixel or its 8 neighbours, both saw an
    /// emitter and missed it (a lamp's silhouette), the emission seen directly is averaged
    /// over this many primary cones per sample instead of the sample's own; they cost no
    /// shading. 0 turns it off.
    #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u32).range(0..=256))]
    pub edge_rays: u32,
    /// Start from the stored light in this file (written by `--store-out` from the same
    /// archive and --cone-samples): tiles of one frame that start from one pre-pass's light
    /// show no seams. The render still adds its own samples.
    #[arg(long, value_name = "LIGHT.store")]
    pub store_in: Option<std::path::PathBuf>,
    /// Write the stored light to this file when the render ends (FORMAT.md, "The light
    /// store file").
    #[arg(long, value_name = "LIGHT.store")]
    pub store_out: Option<std::path::PathBuf>,
}

impl Default for ConeSettings {
    /// The command line's defaults.
    fn default() -> ConeSettings {
        super::flag_defaults()
    }
}

/// What the cone integrator adds to the render's statistics.
#[derive(Clone, Debug, serde::Serialize)]
pub struct ConeStats {
    pub cone_scale: f32,
    pub stored_nodes: u64,
    pub stored_bytes: u64,
    pub converged_nodes: u64,
    /// Hits that read a stored mean, and samples added to the store: their ratio is how
    /// many reads a stored sample serves (at most `--cone-reuse` unless cells converge).
    pub store_reads: u64,
    pub store_adds: u64,
    /// Samples of nodes the store had no room for (the budget's share was full).
    pub store_refused_samples: u64,
    /// Photons the light passes emitted, and how many left caustic light.
    pub photons: u64,
    pub caustic_deposits: u64,
    /// Pixels at an emitter's silhouette: samples of the pixel or its neighbours both saw
    /// an emitter and missed it (these take `--edge-rays`).
    pub edge_pixels: u64,
}

/// Seed offset of the sequences that place a pixel's edge rays.
const EDGE_SEED: u32 = 0x5bd1_e995;

pub struct ConeIntegrator {
    settings: ConeSettings,
    store: RadianceStore,
    keys: Keys,
    /// Primary cones open by one pixel (004 eq. 4.19).
    primary: Cone,
    seed: u32,
    /// Whether the light pass runs, and the stats' line saying why.
    light_pass: (bool, String),
    photons: u32,
    deposits: u64,
    /// Per pixel of the apron: primary samples that saw emission and that did not.
    seen: Vec<[AtomicU32; 2]>,
    /// The window rendered, and the apron: the window and the pixels around it, inside
    /// the image (x0, x1, y0, y1). A tile's edge mask needs its neighbours' samples.
    window: [u32; 4],
    apron: [u32; 4],
    /// The apron's pixels outside the window (none for a whole frame).
    ring: Vec<[u32; 2]>,
    /// Pixels taking edge rays this pass.
    edge: Vec<bool>,
    pull_s: f64,
    light_s: f64,
}

impl ConeIntegrator {
    pub fn new(
        settings: &ConeSettings,
        scene: &Scene,
        target: &Target,
    ) -> anyhow::Result<ConeIntegrator> {
        let archive = &scene.cache.archive;
        let cam = &scene.camera;
        let window = target.window;
        let apron = [
            window[0].saturating_sub(1),
            (window[1] + 1).min(cam.width),
            window[2].saturating_sub(1),
            (window[3] + 1).min(cam.height),
        ];
        let (w, h) = (apron[1] - apron[0], apron[3] - apron[2]);
        let keys = keys(archive)?;
        Ok(ConeIntegrator {
            settings: settings.clone(),
            store: RadianceStore::new(
                settings.samples.unwrap_or(u32::MAX),
                target.state_bytes,
                archive.page_count() as usize,
                keys.block(),
            ),
            keys,
            primary: Cone {
                r0: 0.0,
                tan_a: 2.0 * cam.tan_half / cam.height as f32,
                scale: settings.scale,
                spread: settings.diffuse_tan,
            },
            seed: target.seed,
            light_pass: light_pass(settings.light_pass, scene),
            // Photons light the whole scene whatever the crop: one per pixel of the image.
            photons: settings
                .photons
                .unwrap_or(target.pixels.clamp(1, u32::MAX as u64) as u32),
            deposits: 0,
            seen: (0..w as usize * h as usize)
                .map(|_| Default::default())
                .collect(),
            window,
            apron,
            ring: (apron[2]..apron[3])
                .flat_map(|y| (apron[0]..apron[1]).map(move |x| [x, y]))
                .filter(|&[x, y]| {
                    !(window[0]..window[1]).contains(&x) || !(window[2]..window[3]).contains(&y)
                })
                .collect(),
            edge: Vec::new(),
            pull_s: 0.0,
            light_s: 0.0,
        })
    }

    /// Counts whether a primary sample of image pixel (x, y) saw emission.
    fn tally(&self, x: u32, y: u32, v: V) {
        let [x0, x1, y0, _] = self.apron;
        let at = (y.wrapping_sub(y0) * (x1 - x0) + x.wrapping_sub(x0)) as usize;
        if let Some(n) = self.seen.get(at) {
            let n = &n[usize::from(v.max_element() <= 0.0)];
            n.fetch_update(Relaxed, Relaxed, |x| Some(x.saturating_add(1)))
                .ok();
        }
    }

    fn edge_mask(&self) -> Vec<bool> {
        let seen: Vec<[u32; 2]> = self
            .seen
            .iter()
            .map(|s| s.each_ref().map(|n| n.load(Relaxed)))
            .collect();
        let [ax0, ax1, ay0, _] = self.apron;
        let [x0, x1, y0, y1] = self.window;
        let mask = edge_mask(&seen, ax1 - ax0);
        (y0..y1)
            .flat_map(|y| (x0..x1).map(move |x| ((y - ay0) * (ax1 - ax0) + x - ax0) as usize))
            .map(|i| mask[i])
            .collect()
    }

    /// The primary samples `first..first + count` of the ring's pixels, tallied as a
    /// full-frame render tallies them (the same sample positions), so a tile's edge mask
    /// at its border is the whole frame's there: without them a tile found other
    /// silhouettes at its border rows, a seam (sponza, 8 tiles, 4 spp: the worst border
    /// row's jump 17× the interior rows' mean).
    fn tally_apron(&self, scene: &Scene, first: u32, count: u32) -> u64 {
        if self.ring.is_empty() {
            return 0;
        }
        let cam = &scene.camera;
        let mut tr = Tracer::new(&scene.cache);
        let mut c = Counters::default();
        for &[x, y] in &self.ring {
            for index in first..first + count {
                let [jx, jy, ..] = PixelSampler::new(self.seed, y * cam.width + x, index).get4(0);
                let r = cam.ray(x as f32 + jx, y as f32 + jy);
                let v = seen_emission(scene, &mut tr, &r, &self.primary, &mut c);
                self.tally(x, y, v);
            }
        }
        tr.rays
    }
}

/// The archive's stored-light keys, or why they do not fit in 64 bits.
pub fn keys(archive: &canopy_format::Archive) -> anyhow::Result<Keys> {
    let h = &archive.header;
    Keys::new(h).with_context(|| {
        format!(
            "{}: {} nodes placed by {} instances are more than the cone integrator's 64-bit stored-light keys can number; convert with --flatten-instances, or render with --integrator path",
            archive.path().display(),
            h.nodes,
            h.instances.count
        )
    })
}

/// The key of the cell `cell` of a hit's triangle, on side `back`, as its instance places it.
fn tri_key(keys: Keys, h: &Hit, back: bool, cell: u64) -> u64 {
    keys.tri(keys.placed(h.instance, h.leaf), h.slot, back, cell)
}

/// Whether the caustic light pass runs: decided once, and the stats say why.
fn light_pass(mode: LightPass, scene: &Scene) -> (bool, String) {
    let smooth = scene.materials.iter().any(Material::has_delta_lobe);
    let lights = !scene.lights.is_empty();
    let on = lights
        && match mode {
            LightPass::Off => false,
            LightPass::On => true,
            LightPass::Auto => smooth,
        };
    let why = if on {
        "light pass: photons through smooth mirrors and glass leave caustics on diffuse surfaces (L S S* D); the eye pass masks those paths"
    } else if mode == LightPass::Off {
        "light pass: off (--light-pass off); caustics come from the eye pass"
    } else if !smooth && mode == LightPass::Auto {
        "light pass: skipped, no smooth mirror or glass surfaces"
    } else {
        "light pass: skipped, no lights"
    };
    (on, why.into())
}

impl Integrator for ConeIntegrator {
    /// One sample per pass: the store is pulled between passes.
    fn pass_samples(&self, _spp: u32) -> u32 {
        1
    }

    fn begin_pass(&mut self, scene: &Scene, first: u32, count: u32) -> anyhow::Result<u64> {
        if let (0, Some(path)) = (first, &self.settings.store_in) {
            crate::radiance::file::load(&self.store, &scene.cache.archive.header, path)?;
        }
        let start = Instant::now();
        self.store.begin_pass(first + count);
        let mut rays = 0;
        if self.light_pass.0 {
            let lp = light_pass::light_pass(
                scene,
                &self.store,
                self.keys,
                self.photons,
                first,
                self.seed,
            );
            rays = lp.rays;
            self.deposits += lp.deposits;
            self.light_s += start.elapsed().as_secs_f64();
        }
        if self.settings.edge_rays > 0 {
            self.edge = self.edge_mask();
            rays += self.tally_apron(scene, first, count);
        }
        Ok(rays)
    }

    fn sample(&self, scene: &Scene, tr: &mut Tracer, px: &PixelSample, c: &mut Counters) -> V {
        let (rest, own) = self.radiance(scene, tr, px.ray, &px.sampler, c);
        self.tally(px.x, px.y, own);
        // At an emitter's silhouette (found by earlier passes) the emission seen is
        // averaged over `edge_rays` positions of a denser stratified sequence: an unbiased
        // estimate of the same pixel integral, each ray a primary cone without shading.
        let k = self.settings.edge_rays;
        if k == 0 || self.edge.get(px.at) != Some(&true) {
            return rest + own;
        }
        let pixel = px.y * scene.camera.width + px.x;
        let sum = (0..k).fold(V::ZERO, |acc, j| {
            let index = px.index.wrapping_mul(k).wrapping_add(j);
            let [ex, ey, ..] = PixelSampler::new(self.seed ^ EDGE_SEED, pixel, index).get4(0);
            let r = scene.camera.ray(px.x as f32 + ex, px.y as f32 + ey);
            acc + seen_emission(scene, tr, &r, &self.primary, c)
        });
        rest + sum / k as f32
    }

    fn finish(&mut self, scene: &Scene) -> anyhow::Result<()> {
        if let Some(path) = &self.settings.store_out {
            pull(&scene.cache, &self.store, self.keys);
            crate::radiance::file::save(&self.store, &scene.cache.archive.header, path)?;
        }
        Ok(())
    }

    /// Pull after passes 1, 2, 4, 8 and then every 8th: a pull walks every resident page,
    /// which on a big scene costs more than a small pass. Exact cones (scale 0) meet only
    /// triangles, whose cells are never pulled: no pull (on the 1 G-triangle forest it
    /// took 26 of 28 seconds, each instance's prototype pulled apart).
    fn end_pass(&mut self, scene: &Scene, done: u32) {
        if self.settings.scale > 0.0 && (done.is_power_of_two() || done.is_multiple_of(8)) {
            let t = Instant::now();
            pull(&scene.cache, &self.store, self.keys);
            self.pull_s += t.elapsed().as_secs_f64();
        }
    }

    fn passes(&self) -> Vec<String> {
        let s = &self.settings;
        let edge = if s.edge_rays == 0 {
            "edge rays: off (--edge-rays 0)".into()
        } else {
            format!(
                "edge rays: {} per sample average the emission seen on the {} pixels found at an emitter's silhouette",
                s.edge_rays,
                self.edge_pixels()
            )
        };
        vec![
            format!(
                "cone: eye pass, cone scale {}, diffuse cones tan {}, diffuse light stored per node ({}, each sample serving at most {} reads on average)",
                s.scale,
                s.diffuse_tan,
                s.samples.map_or("never converged".into(), |n| format!("converged at {n} samples")),
                s.cone_reuse
            ),
            if s.scale > 0.0 {
                "pull after eye passes 1, 2, 4, 8 and every 8th".into()
            } else {
                "no pull: exact cones read no node's light".into()
            },
            self.light_pass.1.clone(),
            edge,
        ]
    }

    fn stats(&self) -> Stats {
        let [store_reads, store_adds] = self.store.reuse();
        Stats::Cone(ConeStats {
            cone_scale: self.settings.scale,
            stored_nodes: self.store.len() as u64,
            stored_bytes: self.store.bytes(),
            converged_nodes: self.store.converged() as u64,
            store_reads,
            store_adds,
            store_refused_samples: self.store.refused(),
            photons: self.store.photons(),
            caustic_deposits: self.deposits,
            edge_pixels: self.edge_pixels(),
        })
    }

    /// The store, and per pixel the emission tallies and the edge mask.
    fn state_bytes(&self) -> [u64; 2] {
        [self.store.bytes(), self.seen.len() as u64 * 9]
    }

    fn seconds(&self) -> Vec<(&'static str, f64)> {
        vec![("pull", self.pull_s), ("light", self.light_s)]
    }
}

impl ConeIntegrator {
    fn edge_pixels(&self) -> u64 {
        self.edge_mask().iter().filter(|&&e| e).count() as u64
    }
}

/// Pixels at an emitter's silhouette: among the pixel and its eight neighbours, earlier
/// samples both saw emission and missed it. The neighbours catch a pixel the emitter
/// barely covers before one of its own samples lands on it.
fn edge_mask(seen: &[[u32; 2]], width: u32) -> Vec<bool> {
    let (w, h) = (width as usize, seen.len() / width.max(1) as usize);
    (0..seen.len())
        .map(|i| {
            let (x, y) = (i % w, i / w);
            let mut any = [false; 2];
            for ny in y.saturating_sub(1)..(y + 2).min(h) {
                for nx in x.saturating_sub(1)..(x + 2).min(w) {
                    let n = seen[ny * w + nx];
                    any = [any[0] || n[0] > 0, any[1] || n[1] > 0];
                }
            }
            any[0] && any[1]
        })
        .collect()
}
