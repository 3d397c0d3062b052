//! Edge rays (`--edge-rays`, not in the seeds): at a lamp's silhouette a pixel's noise is
//! mostly the lamp's coverage of the pixel, which any integrator shares with the path
//! tracer. On pixels where earlier samples, of the pixel or its 8 neighbours, both saw an
//! emitter and missed it, the emission seen at the primary hit is averaged over more
//! positions of a denser Owen-scrambled Sobol sequence than the sample's own. Which pixels
//! take them is decided by earlier passes only, so it estimates the same pixel integral;
//! in the first pass, before any sample found a silhouette, every pixel takes them (on the
//! showroom at 20 s, about 490 passes, that one sample of the panel's silhouette seen
//! without them held a quarter of PBGI's squared error there: RMSE 2.59e-3 → 2.48e-3).
//! Where no camera ray can see emission, none are traced (`EdgeRays::new`).
//! The cone and PBGI integrators use it; the path tracer, being the reference, does not.

use super::{Counters, PixelSample, Scene, Target};
use crate::sampler::PixelSampler;
use crate::trace::{Ray, Tracer};
use glam::Vec3A as V;
use std::sync::atomic::{AtomicU32, Ordering::Relaxed};

/// `--edge-rays`' default under cone: 4 or 16 rays did no better than 8 on sponza's cone
/// renders.
pub const DEFAULT_EDGE_RAYS: u32 = 8;

/// `--edge-rays`' default under pbgi, whose samples cost more than the cone's, so that
/// a silhouette's emission is worth more rays per sample: against 8, RMSE at 20 s on the
/// showroom (seeds 1–4) −1.3%, at 60 s sponza −2.3%, bunny_box −0.7%, room +0.4% (three
/// seeds), room_glossy +0.1%.
pub const PBGI_EDGE_RAYS: u32 = 16;

/// The flag, shared by the integrators that take edge rays.
#[derive(Clone, Debug, clap::Args)]
#[command(next_help_heading = "Cone and point-based GI (--integrator cone or pbgi)")]
pub struct EdgeSettings {
    /// Primary rays that average the emission seen on a lamp's silhouette pixels (no
    /// shading); 0 is off [default: 8 under cone, 16 under pbgi]
    #[arg(long, value_parser = clap::value_parser!(u32).range(0..=256))]
    pub edge_rays: Option<u32>,
}

/// Seed offset of the sequences that place a pixel's edge rays.
const EDGE_SEED: u32 = 0x5bd1_e995;

/// The emission an integrator sees at the primary hit of a camera ray.
pub type SeenEmission<'a> = dyn Fn(&mut Tracer, &Ray, &mut Counters) -> V + 'a;

pub struct EdgeRays {
    /// Rays per sample on silhouette pixels (0: off).
    rays: u32,
    /// Whether a camera ray can see emission (else no edge rays, whatever was asked).
    visible: bool,
    seed: u32,
    /// Per pixel of the apron: primary samples that saw emission and that did not.
    seen: Vec<[AtomicU32; 2]>,
    /// The window rendered, and the apron: the window and the pixels around it, inside
    /// the image (x0, x1, y0, y1). A tile's edge mask needs its neighbours' samples.
    window: [u32; 4],
    apron: [u32; 4],
    /// The apron's pixels outside the window (none for a whole frame).
    ring: Vec<[u32; 2]>,
    /// Pixels of the window taking edge rays this pass.
    mask: Vec<bool>,
}

impl EdgeRays {
    /// `env_seen`: the integrator's seen emission counts the environment a camera ray
    /// escapes to. Where no camera ray can see emission (no emissive material, and no
    /// environment it counts) every edge ray would average zeros: none are traced (on a
    /// far-field scene under a sun, the first pass's rays were 46% of a 4-spp cone render's).
    pub fn new(rays: u32, scene: &Scene, target: &Target, env_seen: bool) -> EdgeRays {
        let visible = scene.materials.iter().any(|m| m.is_emissive())
            || (env_seen && scene.lights.env.is_some());
        let rays = if visible { rays } else { 0 };
        let cam = &scene.camera;
        let window = target.window;
        let apron = [
            window[0].saturating_sub(1),
            (window[1] + 1).min(cam.width),
            window[2].saturating_sub(1),
            (window[3] + 1).min(cam.height),
        ];
        let (w, h) = (apron[1] - apron[0], apron[3] - apron[2]);
        let pixels = w as usize * h as usize;
        EdgeRays {
            rays,
            visible,
            seed: target.seed,
            seen: (0..pixels).map(|_| Default::default()).collect(),
            window,
            apron,
            ring: (apron[2]..apron[3])
                .flat_map(|y| (apron[0]..apron[1]).map(move |x| [x, y]))
                .filter(|&[x, y]| {
                    !(window[0]..window[1]).contains(&x) || !(window[2]..window[3]).contains(&y)
                })
                .collect(),
            mask: Vec::new(),
        }
    }

    /// Before a pass of samples `first..first + count`: the mask from earlier passes, and
    /// the ring's samples tallied. Returns the rays traced.
    pub fn begin_pass(
        &mut self,
        scene: &Scene,
        first: u32,
        count: u32,
        seen: &SeenEmission,
    ) -> u64 {
        if self.rays == 0 {
            return 0;
        }
        // Before any sample no silhouette is known: the first pass takes them everywhere.
        self.mask = match first {
            0 => vec![true; self.window_pixels()],
            _ => self.window_mask(),
        };
        self.tally_apron(scene, first, count, seen)
    }

    /// Whether edge rays are traced at all.
    pub fn traced(&self) -> bool {
        self.rays > 0
    }

    /// Counts whether a primary sample of image pixel (x, y) saw emission.
    pub fn tally(&self, x: u32, y: u32, v: V) {
        let [x0, x1, y0, _] = self.apron;
        let at = (y.wrapping_sub(y0) * (x1 - x0) + x.wrapping_sub(x0)) as usize;
        if let Some(n) = self.seen.get(at) {
            let n = &n[usize::from(v.max_element() <= 0.0)];
            n.fetch_update(Relaxed, Relaxed, |x| Some(x.saturating_add(1)))
                .ok();
        }
    }

    /// The emission seen at the sample's primary hit: its own (`own`), tallied, or on a
    /// silhouette pixel the mean of the edge rays' in its place.
    pub fn emission(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        px: &PixelSample,
        own: V,
        c: &mut Counters,
        seen: &SeenEmission,
    ) -> V {
        self.tally(px.x, px.y, own);
        let k = self.rays;
        if !self.masked(px.at) {
            return own;
        }
        let pixel = px.y * scene.camera.width + px.x;
        let sum = (0..k).fold(V::ZERO, |acc, j| {
            let index = px.index.wrapping_mul(k).wrapping_add(j);
            let [ex, ey, ..] = PixelSampler::new(self.seed ^ EDGE_SEED, pixel, index).get4(0);
            let r = scene.camera.ray(px.x as f32 + ex, px.y as f32 + ey);
            acc + seen(tr, &r, c)
        });
        sum / k as f32
    }

    /// Whether the pixel at `at` of the window takes edge rays this pass.
    pub fn masked(&self, at: usize) -> bool {
        self.rays > 0 && self.mask.get(at) == Some(&true)
    }

    /// Pixels of the window at an emitter's silhouette, as the samples so far find them
    /// (counted with edge rays off too).
    pub fn pixels(&self) -> u64 {
        self.window_mask().iter().filter(|&&e| e).count() as u64
    }

    /// The tallies' and the mask's bytes.
    pub fn bytes(&self) -> u64 {
        self.seen.len() as u64 * 9
    }

    /// The stats' line saying what edge rays did.
    pub fn describe(&self) -> String {
        match (self.rays, self.visible) {
            (0, false) => return "edge rays: off (nothing a camera ray can see emits)".into(),
            (0, true) => return "edge rays: off (--edge-rays 0)".into(),
            _ => {}
        }
        format!(
            "edge rays: {} per sample average the emission seen on the {} pixels found at an emitter's silhouette",
            self.rays,
            self.pixels()
        )
    }

    fn window_pixels(&self) -> usize {
        let [x0, x1, y0, y1] = self.window;
        (x1 - x0) as usize * (y1 - y0) as usize
    }

    fn window_mask(&self) -> Vec<bool> {
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
    fn tally_apron(&self, scene: &Scene, first: u32, count: u32, seen: &SeenEmission) -> u64 {
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
                let v = seen(&mut tr, &r, &mut c);
                self.tally(x, y, v);
            }
        }
        tr.rays
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
