//! Integrators and the scene state they share.
//!
//! The driver (`render`) knows integrators only through `Integrator`: per pass it calls
//! `begin_pass`, then `sample` for every sample of every pixel (in parallel, by tiles), then
//! `end_pass` — pbrt-v4's `ImageTileIntegrator::Render` → `EvaluatePixelSample` → `Li`.

pub mod cone;
pub mod direct;
pub mod edge;
pub mod path;
pub mod pbgi;
pub mod surface;

pub use direct::{
    bsdf_term, mis_weight, power_heuristic, sample_light, sample_light_weighted, Receiver,
};
pub use surface::{on_side, ShadingPoint};

use crate::camera::Camera;
use crate::light::Lights;
use crate::material::Material;
use crate::paging::{Corners, PageCache};
use crate::sampler::PixelSampler;
use crate::texture::{self, Lookup, Shaded, Textures};
use crate::trace::{Cone, Hit, Ray, Tracer};
use glam::Vec3A as V;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::sync::Arc;
use std::time::Duration;

/// `--integrator`: which estimator renders.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Kind {
    /// Exact path tracing of the leaf triangles: the ground truth.
    Path,
    /// Cone casts that stop at the level of detail the cone resolves, with diffuse light
    /// stored per node and reused (004 §4.5–4.8).
    Cone,
    /// Point-based GI: light of every bounce baked into the nodes, gathered per receiver
    /// into a micro-buffer (003 ch. 2).
    Pbgi,
}

/// An integrator with its own parameters.
#[derive(Clone, Debug)]
pub enum Settings {
    Path,
    Cone(cone::ConeSettings),
    Pbgi(pbgi::PbgiSettings),
}

impl Settings {
    pub fn kind(&self) -> Kind {
        match self {
            Settings::Path => Kind::Path,
            Settings::Cone(_) => Kind::Cone,
            Settings::Pbgi(_) => Kind::Pbgi,
        }
    }

    /// The part of a memory budget the integrator's own state may take (the pages get
    /// the rest): a quarter for the cone integrator's stored light and for PBGI's per-pixel
    /// tables and records. PBGI's baked light (96 bytes a node) rides in the pages, so the
    /// page cache's share holds it.
    pub fn state_share(&self, budget: u64) -> u64 {
        match self {
            Settings::Path => 0,
            Settings::Cone(_) | Settings::Pbgi(_) => budget / 4,
        }
    }

    /// Whether the state's share is lent to the page cache, the state taking it back as it
    /// grows (the cone integrator's stored light, which grows with the nodes paths reach
    /// and often fills a small part of it), rather than kept aside whole (PBGI's tables,
    /// sized before the render).
    pub fn lends_state(&self) -> bool {
        matches!(self, Settings::Cone(_))
    }

    /// `--pixel-split` (1 unless given): the most camera samples a pass takes of a pixel.
    /// PBGI's receiver clusters group a tile's receivers, one per pixel, so they take one.
    pub fn pixel_split(&self, asked: Option<u32>) -> anyhow::Result<u32> {
        match (self, asked) {
            (Settings::Pbgi(p), Some(m)) if m > 1 && p.clusters > 0 => anyhow::bail!(
                "--pixel-split {m}: --receiver-clusters groups one receiver per pixel of a tile, so a pass takes one sample of each pixel (--pixel-split 1)"
            ),
            (_, m) => Ok(m.unwrap_or(1)),
        }
    }

    /// Refuses an archive the integrator cannot render: PBGI's cut and wavelet bounce read
    /// light aggregated up the tree, which holds none for instances (their light depends on
    /// the placement); the cone integrator keys its stored light per instance, in 64 bits.
    /// Returns a note where PBGI's bake leaves instanced meshes to texel rays' paths.
    pub fn check_archive(
        &self,
        archive: &canopy_format::Archive,
    ) -> anyhow::Result<Option<String>> {
        match self {
            Settings::Path => Ok(None),
            Settings::Cone(_) => cone::keys(archive).map(|_| None),
            Settings::Pbgi(p) if !p.rays() => {
                refuse_instances(archive, "--pbgi-gather cut").map(|()| None)
            }
            Settings::Pbgi(p) if p.glossy_bounce != pbgi::wpbgi::GlossyBounce::Rays => {
                refuse_instances(archive, "--pbgi-glossy-bounce wavelet or cache").map(|()| None)
            }
            Settings::Pbgi(_) => Ok(has_instances(archive).then(|| {
                format!(
                    "{}: PBGI's bake holds the archive's unique meshes; what its {} instances place is lit by paths followed on to them, as the path tracer lights it",
                    archive.path().display(),
                    archive.header.instances.count
                )
            })),
        }
    }

    /// Refuses settings the scene gives nothing to do: more than one ray from glossy
    /// lobes, or splitting them, where no material has rough specular lobes; splitting
    /// with one ray, which shows no spread.
    pub fn check_scene(&self, scene: &Scene) -> anyhow::Result<()> {
        if let Settings::Pbgi(p) = self {
            let glossy = pbgi::glossy::any_glossy(scene);
            let path = scene.cache.archive.path().display();
            if let Some(k) = p.glossy_rays.filter(|&k| k > 1 && !glossy) {
                anyhow::bail!(
                    "--pbgi-glossy-rays {k}: no material of {path} is a rough metal or rough dielectric, so no receiver has a glossy lobe to sample"
                );
            }
            if let Some(n) = p.split.filter(|&n| n > 1 && !glossy) {
                anyhow::bail!(
                    "--pbgi-split {n}: no material of {path} is a rough metal or rough dielectric, so no receiver has a glossy lobe to split"
                );
            }
            if p.rays() {
                let cut_only = if p.angle.is_some() {
                    Some("--pbgi-angle")
                } else if p.clusters > 0 {
                    Some("--receiver-clusters")
                } else {
                    p.bake.wavelet_given()
                };
                if let Some(flag) = cut_only {
                    anyhow::bail!(
                        "{flag} applies to the cut's gather (--pbgi-gather cut); texel rays read only the baked diffuse light"
                    );
                }
            }
            if let (Some(t), pbgi::wpbgi::GlossyBounce::Rays) = (p.brdf_threshold, p.glossy_bounce)
            {
                anyhow::bail!(
                    "--pbgi-brdf-threshold {t} applies to --pbgi-glossy-bounce wavelet or cache, whose BRDF tables it truncates"
                );
            }
            if let (Some(g), pbgi::wpbgi::GlossyBounce::Rays) = (p.light_gamma, p.glossy_bounce) {
                anyhow::bail!(
                    "--pbgi-light-importance {g} applies to --pbgi-glossy-bounce wavelet or cache, whose adaptive micro-buffer it refines"
                );
            }
            let wavelet = p.glossy_bounce != pbgi::wpbgi::GlossyBounce::Rays;
            let how = match p.glossy_bounce {
                pbgi::wpbgi::GlossyBounce::Cache => "cache",
                _ => "wavelet",
            };
            if wavelet && !p.resolution.is_power_of_two() {
                anyhow::bail!(
                    "--pbgi-resolution {}: --pbgi-glossy-bounce {how} splits its micro-buffer's texels in halves down to its BRDF tables' 64², so the resolution must be a power of two (2 to 64)",
                    p.resolution
                );
            }
            if p.glossy_bounce == pbgi::wpbgi::GlossyBounce::Cache && p.cache == 0.0 {
                anyhow::bail!(
                    "--pbgi-glossy-bounce cache keeps its records as the irradiance cache does, which --pbgi-cache 0 turns off"
                );
            }
            if wavelet && !glossy {
                anyhow::bail!(
                    "--pbgi-glossy-bounce {how}: no material of {path} is a rough metal or rough dielectric, so no receiver has a glossy bounce to gather"
                );
            }
            if let (Some(n), Some(1)) = (p.split.filter(|&n| n > 1), p.glossy_rays) {
                anyhow::bail!(
                    "--pbgi-split {n} needs --pbgi-glossy-rays of 2 or more: a receiver's spread is measured between its first two pairs"
                );
            }
        }
        Ok(())
    }

    pub fn build(&self, scene: &Scene, target: &Target) -> anyhow::Result<Box<dyn Integrator>> {
        self.check_scene(scene)?;
        Ok(match self {
            Settings::Path => Box::new(path::PathIntegrator),
            Settings::Cone(c) => Box::new(cone::ConeIntegrator::new(c, scene, target)?),
            Settings::Pbgi(p) => Box::new(pbgi::PbgiIntegrator::new(p, scene, target)),
        })
    }
}

/// An integrator's settings as its command-line flags' defaults give them.
pub fn flag_defaults<T: clap::Args + clap::FromArgMatches>() -> T {
    let cmd = T::augment_args(clap::Command::new("defaults"));
    T::from_arg_matches(&cmd.get_matches_from(["defaults"])).expect("the defaults parse")
}

/// What a render produces, as the integrators need to know it.
pub struct Target {
    pub seed: u32,
    /// Pixels of the full image.
    pub pixels: u64,
    /// The window rendered in image pixels, x0, x1, y0, y1 (`--crop`, else the image).
    pub window: [u32; 4],
    /// Bytes the integrator's state may take (None: unbounded).
    pub state_bytes: Option<u64>,
    /// Most camera samples one pass takes of a pixel (`--pixel-split`; 1: one).
    pub pixel_split: u32,
}

/// One sample of one pixel, as the driver hands it out.
pub struct PixelSample {
    pub x: u32,
    pub y: u32,
    /// The pixel's index in the window rendered.
    pub at: usize,
    /// Sample number within the pixel.
    pub index: u32,
    pub sampler: PixelSampler,
    /// The camera ray through the sample's position in the pixel.
    pub ray: Ray,
    /// Its weight in the pass's mean of the pixel: 1 over the camera samples the pass
    /// takes of the pixel (`--pixel-split`).
    pub share: f32,
    /// Its number in the pixel's own sequence of further samples, when the pass takes
    /// more than one of the pixel (None: the pass's sample `index`).
    pub further: Option<u32>,
}

/// Statistics an integrator adds to the render's (flattened into its JSON).
#[derive(Clone, Debug, serde::Serialize)]
#[serde(untagged)]
pub enum Stats {
    Path {},
    Cone(cone::ConeStats),
    Pbgi(pbgi::PbgiStats),
}

/// What the driver knows before a pass of samples `first..first + count`.
#[derive(Clone, Copy)]
pub struct Pass {
    pub first: u32,
    pub count: u32,
    /// Rays traced so far.
    pub rays: u64,
    /// The mean over pixels of the variance of one pass's sample of a pixel (the mean of
    /// its camera samples), so far (`Film::sample_variance`).
    pub variance: f64,
    /// Where pixels take several camera samples a pass (`--pixel-split`): the image's mean
    /// variance of one camera sample so far.
    pub camera_sample_variance: Option<f64>,
    /// Camera samples taken so far over the window, further ones counted.
    pub samples: u64,
    /// The time left in `--time`'s budget, if there is one: work between passes that
    /// outgrew it would overrun the budget, since the driver stops only after a pass.
    pub left: Option<Duration>,
}

pub trait Integrator: Send + Sync {
    /// Samples per pixel the next pass takes, `done` taken and `left` more asked for (the
    /// driver takes one per pass under a time limit).
    fn pass_samples(&self, left: u32, _done: u32) -> u32 {
        left
    }
    /// Before a pass; returns the rays it traces.
    fn begin_pass(&mut self, _scene: &Scene, _pass: &Pass) -> anyhow::Result<u64> {
        Ok(0)
    }
    /// Radiance of one pixel sample.
    fn sample(&self, scene: &Scene, tr: &mut Tracer, px: &PixelSample, c: &mut Counters) -> V;
    /// Radiance of one sample in each pixel of a tile, in order (FPBGI shares work
    /// between them).
    fn sample_tile(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        pxs: &[PixelSample],
        c: &mut Counters,
    ) -> Vec<V> {
        pxs.iter().map(|px| self.sample(scene, tr, px, c)).collect()
    }
    /// Radiance of a pass's camera samples of one pixel, in order, each unweighted: its
    /// pass sample and its further ones (`--pixel-split`).
    fn sample_pixel(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        pxs: &[PixelSample],
        c: &mut Counters,
    ) -> Vec<V> {
        pxs.iter().map(|px| self.sample(scene, tr, px, c)).collect()
    }
    /// After a pass, `done` samples per pixel in all.
    fn end_pass(&mut self, _scene: &Scene, _done: u32) {}

    /// Light held back from the samples until the last pass, per window pixel (index as
    /// in `Film::index`), summed over all its samples: PBGI gives the samples that reuse a
    /// pixel's gathers their final mean.
    fn held_back(&self) -> Vec<(usize, V)> {
        Vec::new()
    }
    /// After the last pass, before the image is written (the cone integrator saves its
    /// stored light here).
    fn finish(&mut self, _scene: &Scene) -> anyhow::Result<()> {
        Ok(())
    }
    /// What ran and why, for the stats' `passes`.
    fn passes(&self) -> Vec<String>;
    fn stats(&self) -> Stats;
    /// Bytes of state it holds besides the page cache.
    fn state_bytes(&self) -> u64 {
        0
    }
    /// Parts of the render time it accounts for, by name.
    fn seconds(&self) -> Vec<(&'static str, f64)> {
        Vec::new()
    }
}

pub struct Scene {
    pub cache: Arc<PageCache>,
    pub materials: Vec<Material>,
    pub textures: Textures,
    /// The factor on a sample's footprint for texture filtering (`TextureFilter::footprint_scale`).
    pub texture_scale: f32,
    pub lights: Lights,
    pub camera: Camera,
    /// Longest path in segments (1: emitters seen directly); None for unbounded.
    pub max_depth: Option<u32>,
    /// One bit per node of the archive: leaves hit (ancestors are added at the end).
    pub touched: NodeSet,
}

impl Scene {
    /// Counts a hit's leaf, and the instance leaf it came through, as touched.
    pub fn touch(&self, hit: &Hit) {
        self.touched.insert(hit.leaf);
        if hit.instance != crate::trace::NO_INSTANCE {
            self.touched.insert(hit.instance_leaf);
        }
    }

    /// Material `index` as shaded at a triangle point (barycentrics `b`; the vertices'
    /// texture coordinates and colours `c`) met along direction `d` with a footprint
    /// `spread` wide there (see `Textures::shade`), the vertex colour multiplying the base
    /// colour (glTF 2.0 §3.9.2, `COLOR_0`). Untextured, uncoloured materials are returned
    /// as they are.
    #[inline]
    pub fn material_at(
        &self,
        index: u32,
        tri: &[[f32; 3]; 3],
        c: &Corners,
        b: [f32; 3],
        d: V,
        spread: f32,
    ) -> Shaded {
        let m = &self.materials[index as usize];
        let mut shaded = if self.textures.varies(index) {
            let p = tri.map(V::from);
            let fp = self.textures.footprint(index, p, c, b, d, spread);
            self.textures
                .shade(&mut Lookup::new(&self.cache), m, index, &fp, p, c)
        } else {
            Shaded::plain(*m)
        };
        if let Some(rgba) = c.colour_at(b) {
            shaded.m.tint(rgba);
        }
        shaded
    }

    /// The material at a hit, with the path tracer's footprint: a pixel's spread at the
    /// hit's distance from the camera (pbrt-v4's `Approximate_dp_dxy`, used at every bounce).
    pub fn material_at_hit(&self, hit: &Hit, d: V) -> Shaded {
        let spread = match self.textures.varies(hit.tri.material) {
            true => self.texture_scale * self.camera.footprint(hit.point().0),
            false => 0.0,
        };
        self.material_at(hit.tri.material, &hit.tri.p, &hit.corners, hit.b, d, spread)
    }

    /// The material at a cone's triangle hit: the cone's radius there is the footprint. A
    /// primary cone's radius is one pixel's spacing (004 eq. 4.19), the path tracer's
    /// footprint; its diameter, used before, blurred texture edges into a structured bias
    /// against the path tracer's images (+0.02% and edge pairs on textured Sponza).
    pub fn material_at_cone(&self, hit: &Hit, ray: &Ray, cone: &Cone) -> Shaded {
        let spread = self.texture_scale * cone.radius(hit.t);
        let m = hit.tri.material;
        self.material_at(m, &hit.tri.p, &hit.corners, hit.b, ray.d, spread)
    }

    /// The first failure to read the scene's data during a render: a page or texture tile,
    /// or a paged environment tile.
    pub fn error(&self) -> Option<String> {
        self.cache.error().or_else(|| self.lights.error())
    }

    /// A triangle hit's opacity alone (no colour lookups): see `opacity`.
    pub fn opacity_at(&self, hit: &Hit) -> f32 {
        self.opacity(hit.tri.material, &hit.corners, hit.b)
    }

    /// Material `index`'s opacity at barycentrics `b` of a triangle whose vertices carry
    /// `c` (see `Textures::opacity`; the vertex colour's alpha multiplies the material's).
    pub fn opacity(&self, index: u32, c: &Corners, b: [f32; 3]) -> f32 {
        if !self.textures.varies(index) {
            return 1.0;
        }
        let m = &self.materials[index as usize];
        let alpha = c.colour_at(b).map_or(1.0, |rgba| rgba[3]);
        let at = texture::Footprint::point(c, b);
        self.textures
            .opacity(&mut Lookup::new(&self.cache), m, index, &at, alpha)
    }

    /// The share of light that survives a ray's `length` along unit `d` to `hit`: less than
    /// 1 where the hit is on the back of a material with a volume (`Material::transmittance`).
    pub fn transmittance_to(&self, hit: &Hit, d: V, length: f32) -> V {
        let front = hit.ng().dot(d) < 0.0;
        self.materials[hit.tri.material as usize].transmittance(front, length)
    }

    /// Material `index` with its textures' means (for values over a whole triangle).
    pub fn mean_material(&self, index: u32) -> Material {
        self.textures
            .mean_shade(&self.materials[index as usize], index)
    }

    /// `mean_material` over a triangle whose vertices carry `c`: their mean colour
    /// multiplies the base colour.
    pub fn mean_material_over(&self, index: u32, c: &Corners) -> Material {
        let mut m = self.mean_material(index);
        if let Some(rgba) = c.mean_colour() {
            m.tint(rgba);
        }
        m
    }

    /// Whether a hit at `depth` (segments before it, from 0) is on the last segment
    /// `--max-depth` allows: it keeps the emission it sees and scatters nothing.
    pub fn last_segment(&self, depth: u32) -> bool {
        self.max_depth.is_some_and(|m| depth + 1 >= m)
    }
}

/// Per-thread counters, summed once per tile.
#[derive(Default, Clone, Copy)]
pub struct Counters {
    pub paths: u64,
    /// Samples whose radiance came out NaN or infinite: counted (the stats report them; a
    /// correct render has none) and added as zero so one bad sample cannot spoil a pixel.
    pub nonfinite: u64,
}

impl Counters {
    /// `v`, or zero (counted) when it is not finite.
    pub fn finite(&mut self, v: glam::Vec3A) -> glam::Vec3A {
        if v.is_finite() {
            v
        } else {
            self.nonfinite += 1;
            glam::Vec3A::ZERO
        }
    }
}

/// A concurrent bit set over the archive's global node numbers.
pub struct NodeSet {
    bits: Vec<AtomicU64>,
}

impl NodeSet {
    pub fn new(nodes: u64) -> NodeSet {
        NodeSet {
            bits: (0..nodes.div_ceil(64)).map(|_| AtomicU64::new(0)).collect(),
        }
    }
    pub fn bytes(&self) -> u64 {
        self.bits.len() as u64 * 8
    }
    #[inline]
    pub fn insert(&self, i: u64) {
        let (w, b) = ((i / 64) as usize, 1u64 << (i % 64));
        if let Some(word) = self.bits.get(w) {
            if word.load(Relaxed) & b == 0 {
                word.fetch_or(b, Relaxed);
            }
        }
    }
    pub fn contains(&self, i: u64) -> bool {
        self.bits
            .get((i / 64) as usize)
            .is_some_and(|w| w.load(Relaxed) & (1 << (i % 64)) != 0)
    }
    pub fn count(&self) -> u64 {
        self.bits
            .iter()
            .map(|w| w.load(Relaxed).count_ones() as u64)
            .sum()
    }
}

/// Russian roulette on a path's throughput `beta` (pbrt-v4's `PathIntegrator`): where its
/// largest channel q is below 1 the path goes on with probability q, `beta` divided by q;
/// `u` draws the uniform only then. Returns whether the path goes on.
pub fn roulette(beta: &mut V, u: impl FnOnce() -> f32) -> bool {
    let q = beta.max_element();
    if q < 1.0 {
        if u() >= q {
            return false;
        }
        *beta /= q;
    }
    true
}

/// An error for `what` (which reads light aggregated up the tree) on an archive with
/// instances, naming what does render it.
pub fn refuse_instances(archive: &canopy_format::Archive, what: &str) -> anyhow::Result<()> {
    if has_instances(archive) {
        anyhow::bail!(
            "{}: {what} reads light summed up the tree, which holds none for instanced meshes (their light depends on where each is placed); PBGI's defaults (texel rays, glossy bounce by rays) render it, or convert with --flatten-instances",
            archive.path().display()
        );
    }
    Ok(())
}

/// Whether the archive places prototypes by instances.
pub fn has_instances(archive: &canopy_format::Archive) -> bool {
    archive.header.features & canopy_format::Features::INSTANCES != 0
}
