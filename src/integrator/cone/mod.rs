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
//! bounces), `light_pass` (caustics). The stored light and its pull are `crate::light_store`.

pub mod light_pass;
mod node_brdf;
mod optics;
mod walk;

pub use node_brdf::theta_norm;

use super::edge::{EdgeRays, DEFAULT_EDGE_RAYS};
use super::{Counters, Integrator, Pass, PixelSample, Scene, Stats, Target};
use crate::light_store::{pull, Keys, RadianceStore};
use crate::material::Material;
use crate::trace::{Cone, Hit, Ray, Tracer};
use anyhow::Context;
use glam::Vec3A as V;
use std::sync::Arc;
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
    /// `--edge-rays` (a flag of both cone and PBGI, set by the command line).
    #[arg(skip = DEFAULT_EDGE_RAYS)]
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
    /// Edge rays at lamps' silhouettes.
    edge: EdgeRays,
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
        let keys = keys(archive)?;
        let edge = EdgeRays::new(settings.edge_rays, scene, target, false);
        // Under a budget the state's share is lent to the page cache (`Settings::lends_state`):
        // the edge rays' tables take theirs back now, the store its own as it grows.
        let cap = target.state_bytes.map(|share| {
            let tables = scene.cache.charge(edge.bytes());
            share - tables
        });
        let store = RadianceStore::new(
            settings.samples.unwrap_or(u32::MAX),
            cap,
            archive.page_count() as usize,
            keys.block(),
        );
        Ok(ConeIntegrator {
            settings: settings.clone(),
            store: match cap {
                Some(_) => store.charging(Arc::clone(&scene.cache)),
                None => store,
            },
            keys,
            primary: Cone {
                r0: cam.cone().0,
                tan_a: cam.cone().1,
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
            edge,
            pull_s: 0.0,
            light_s: 0.0,
        })
    }
}

/// Whether the store is pulled once `done` samples per pixel are taken: at 1, 2, 4, 8 and
/// every 8th, as stored light fills in.
fn pulls_after(done: u32) -> bool {
    done.is_power_of_two() || done.is_multiple_of(8)
}

/// Samples per pixel from `done` to the next pull.
fn to_next_pull(done: u32) -> u32 {
    (done + 1..)
        .find(|&d| pulls_after(d))
        .map_or(1, |d| d - done)
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
    /// One sample per pass where something happens before every pass: the light pass, the
    /// edge rays' masks from earlier passes. Cones that stop at nodes take the samples up
    /// to the next pull (`pulls_after`) in one pass. Otherwise every sample in one pass, as
    /// the path tracer takes them: under a budget smaller than the frame's pages each pass
    /// over the frame loads them again (a far-field scene at 4 spp under 256 MiB: 234 K
    /// pages loaded against 320 K).
    fn pass_samples(&self, left: u32, done: u32) -> u32 {
        if self.light_pass.0 || self.edge.traced() {
            return 1;
        }
        match self.settings.scale > 0.0 {
            true => to_next_pull(done).min(left),
            false => left,
        }
    }

    fn begin_pass(&mut self, scene: &Scene, pass: &Pass) -> anyhow::Result<u64> {
        let (first, count) = (pass.first, pass.count);
        if let (0, Some(path)) = (first, &self.settings.store_in) {
            crate::light_store::file::load(&self.store, &scene.cache.archive.header, path)?;
        }
        let start = Instant::now();
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
        let primary = self.primary;
        let seen =
            |tr: &mut Tracer, r: &Ray, c: &mut Counters| seen_emission(scene, tr, r, &primary, c);
        rays += self.edge.begin_pass(scene, first, count, &seen);
        Ok(rays)
    }

    fn sample(&self, scene: &Scene, tr: &mut Tracer, px: &PixelSample, c: &mut Counters) -> V {
        let (rest, own) = self.radiance(scene, tr, px.ray, &px.sampler, c);
        // At an emitter's silhouette (found by earlier passes) the emission seen is
        // averaged over `--edge-rays` primary cones of a denser stratified sequence.
        let seen = |tr: &mut Tracer, r: &Ray, c: &mut Counters| {
            seen_emission(scene, tr, r, &self.primary, c)
        };
        rest + self.edge.emission(scene, tr, px, own, c, &seen)
    }

    fn finish(&mut self, scene: &Scene) -> anyhow::Result<()> {
        if let Some(path) = &self.settings.store_out {
            pull(&scene.cache, &self.store, self.keys);
            crate::light_store::file::save(&self.store, &scene.cache.archive.header, path)?;
        }
        Ok(())
    }

    /// Pull after passes 1, 2, 4, 8 and then every 8th: a pull walks every resident page,
    /// which on a big scene costs more than a small pass. Exact cones (scale 0) meet only
    /// triangles, whose cells are never pulled: no pull (on the 1 G-triangle forest it
    /// took 26 of 28 seconds, each instance's prototype pulled apart).
    fn end_pass(&mut self, scene: &Scene, done: u32) {
        if self.settings.scale > 0.0 && pulls_after(done) {
            let t = Instant::now();
            pull(&scene.cache, &self.store, self.keys);
            self.pull_s += t.elapsed().as_secs_f64();
        }
    }

    fn passes(&self) -> Vec<String> {
        let s = &self.settings;
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
            self.edge.describe(),
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
            edge_pixels: self.edge.pixels(),
        })
    }

    /// The store, and the edge rays' per-pixel emission tallies and mask.
    fn state_bytes(&self) -> u64 {
        self.store.bytes() + self.edge.bytes()
    }

    fn seconds(&self) -> Vec<(&'static str, f64)> {
        vec![("pull", self.pull_s), ("light", self.light_s)]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Passes of `to_next_pull` samples end on every pull and only there: 1, 2, 4, 8 and
    /// every 8th.
    #[test]
    fn passes_end_at_every_pull() {
        let mut ends = Vec::new();
        let mut done = 0;
        while done < 40 {
            done += to_next_pull(done);
            ends.push(done);
        }
        assert_eq!(ends, [1, 2, 4, 8, 16, 24, 32, 40]);
        let pulls: Vec<u32> = (1..=40).filter(|&d| pulls_after(d)).collect();
        assert_eq!(ends, pulls);
    }
}
