//! Rendering a light set from a precomputed view: direct light at the view samples, light
//! gathered at the transfer's cells, and their product with the transfer.

use super::file::{Coef, RelightFile};
use super::view::Seen;
use super::{cells, header_hash, scene_options};
use crate::integrator::{bsdf_term, sample_light_weighted, Receiver, Scene, ShadingPoint};
use crate::light::{LightSet, Lights};
use crate::material::Material;
use crate::render::Setup;
use crate::sampler::PixelSampler;
use crate::trace::{Cone, Tracer};
use anyhow::{bail, Context, Result};
use glam::Vec3A as V;
use rayon::prelude::*;
use std::path::PathBuf;
use std::time::Instant;

/// Seeds of the light samples' sequences at the gather points and the view samples: fixed,
/// so a light set relit twice gives the same image and a change shows only itself.
const GATHER_SEED: u32 = 0x11E;
const DIRECT_SEED: u32 = 0xD1EC7;

/// What a relight renders with.
#[derive(Clone, Debug)]
pub struct RelightOptions {
    pub view: PathBuf,
    pub lights: Option<PathBuf>,
    /// Light samples per view sample and per gather point.
    pub light_samples: u32,
    pub mem_budget: Option<u64>,
    pub threads: Option<usize>,
}

/// A view ready to relight: its file, scene and view samples' shading points.
pub struct Relighter {
    pub file: RelightFile,
    pub setup: Setup,
    seen: Vec<Seen>,
    light_samples: u32,
    /// Per material, the factor the light set puts on its lamps' emission.
    lamp_scale: Vec<V>,
}

/// One relit image and the time its parts took: light gathered at the transfer's cells,
/// direct light at the view samples, the transfer's product.
pub struct Frame {
    pub image: crate::image::Image,
    pub seconds: [f64; 3],
}

impl Frame {
    pub fn total(&self) -> f64 {
        self.seconds.iter().sum()
    }
}

impl Relighter {
    /// Opens `o.view`, its archive with `o.lights` applied, and traces its view samples.
    pub fn open(o: &RelightOptions, output: (PathBuf, Option<PathBuf>)) -> Result<Relighter> {
        let file = RelightFile::read(&o.view)?;
        if o.light_samples == 0 {
            bail!("--light-samples must be at least 1");
        }
        let h = &file.header;
        let ro = scene_options(
            file.archive.clone(),
            output.0.clone(),
            file.camera(),
            (Some(h.width), Some(h.height)),
            (o.mem_budget, o.threads),
            o.lights.clone(),
        );
        let setup = Setup::open(&ro, output).with_context(|| {
            format!(
                "{}: opening the archive it was precomputed on",
                o.view.display()
            )
        })?;
        if header_hash(&setup.scene.cache.archive) != h.archive_header {
            bail!(
                "{}: {} has changed since the view was precomputed (run `canopy relight` on the archive again)",
                o.view.display(),
                file.archive.display()
            );
        }
        let scene = &setup.scene;
        let seen = setup.pool.install(|| {
            file.views
                .par_chunks(4096)
                .flat_map_iter(|c| {
                    let mut tr = Tracer::new(&scene.cache);
                    c.iter()
                        .map(|v| v.trace(scene, &mut tr))
                        .collect::<Vec<_>>()
                })
                .collect()
        });
        if let Some(err) = scene.error() {
            bail!("{err}");
        }
        let lamp_scale = lamp_scale(&file, scene)?;
        Ok(Relighter {
            file,
            setup,
            seen,
            light_samples: o.light_samples,
            lamp_scale,
        })
    }

    /// Puts `set` in place of the light set the view was opened with: the archive's own
    /// lamps and punctual lights as `set` changes them (the environment stays as opened).
    /// Returns a note when the set leaves no light at all (the image is then black).
    pub fn set_lights(&mut self, set: &LightSet) -> Result<Option<String>> {
        if set.changes_environment() {
            bail!("the environment's strength and rotation are set when the view is opened (--lights)");
        }
        let mut archive = canopy_format::Archive::open(&self.file.archive)?;
        set.apply(&mut archive)?;
        let scene = &mut self.setup.scene;
        let materials: Vec<Material> = archive
            .materials
            .iter()
            .map(Material::from_record)
            .collect();
        let mean: Vec<Material> = (0..materials.len() as u32)
            .map(|i| scene.textures.mean_shade(&materials[i as usize], i))
            .collect();
        let h = &archive.header;
        let radius = 0.5 * (V::from(h.bounds_max) - V::from(h.bounds_min)).length();
        let textures = &scene.textures;
        let lights = Lights::gather(&archive, &mean, |m| textures.emission_textured(m), radius)?;
        let env = std::mem::take(&mut scene.lights).env;
        scene.lights = match env {
            Some(env) => lights.with_environment(env),
            None => lights,
        };
        scene.materials = materials;
        self.lamp_scale = lamp_scale(&self.file, scene)?;
        let dark = scene.lights.is_empty() && scene.lights.env.is_none();
        Ok(dark.then(|| "the light set leaves no light on: the image is black".to_string()))
    }

    /// The image under the scene's lights.
    pub fn frame(&self) -> Result<Frame> {
        let t0 = Instant::now();
        let scene = &self.setup.scene;
        let e = self.setup.pool.install(|| self.gathered());
        let t1 = Instant::now();
        let direct = self.setup.pool.install(|| self.direct());
        let t2 = Instant::now();
        let f = &self.file;
        let spp = f.header.spp as usize;
        let pixels: Vec<[f32; 3]> = self.setup.pool.install(|| {
            (0..f.row_first.len() - 1)
                .into_par_iter()
                .map(|p| {
                    let own: V = direct[p * spp..(p + 1) * spp].iter().sum::<V>() / spp as f32;
                    let (a, b) = (f.row_first[p] as usize, f.row_first[p + 1] as usize);
                    let gi: V = (a..b)
                        .map(|c| {
                            V::from(f.coef_w[c].map(half::f16::to_f32)) * e[f.coef_cell[c] as usize]
                        })
                        .sum();
                    let (a, b) = (f.emit_first[p] as usize, f.emit_first[p + 1] as usize);
                    let lamps: V = f.emits[a..b]
                        .iter()
                        .map(|c: &Coef| V::from(c.w) * self.lamp_scale[c.index as usize])
                        .sum();
                    (own + gi + lamps).into()
                })
                .collect()
        });
        if let Some(err) = scene.error() {
            bail!("{err}");
        }
        Ok(Frame {
            image: crate::image::Image {
                width: f.header.width,
                height: f.header.height,
                pixels,
            },
            seconds: [t1 - t0, t2 - t1, t2.elapsed()].map(|d| d.as_secs_f64()),
        })
    }

    /// Per cell, the mean direct light E/π arriving over its gather points, one light
    /// sample at each (a pixel reads many cells, whose noise it averages).
    fn gathered(&self) -> Vec<V> {
        let f = &self.file;
        let scene = &self.setup.scene;
        (0..f.cell_first.len() - 1)
            .into_par_iter()
            .map_init(
                || Tracer::new(&scene.cache),
                |tr, i| {
                    let pts = &f.points[f.cell_first[i] as usize..f.cell_first[i + 1] as usize];
                    let sum: V = pts
                        .iter()
                        .enumerate()
                        .map(|(k, p)| {
                            let u = PixelSampler::new(GATHER_SEED, i as u32, k as u32).get4(0);
                            arriving(scene, tr, p, [u[0], u[1], u[2]])
                        })
                        .sum();
                    sum / pts.len().max(1) as f32
                },
            )
            .collect()
    }

    /// Per view sample, the light it sends to the camera: the direct light it reflects (or
    /// the environment, for a sample that left the scene), times the throughput of the
    /// smooth bounces before it. Lamps seen directly are the pixel's emission records.
    fn direct(&self) -> Vec<V> {
        let scene = &self.setup.scene;
        let n = self.light_samples;
        (0..self.seen.len())
            .into_par_iter()
            .map_init(
                || Tracer::new(&scene.cache),
                |tr, i| {
                    let beta = V::from(self.file.views[i].beta);
                    let l = match &self.seen[i] {
                        Seen::Surface(sp) => {
                            let spp = self.file.header.spp;
                            let (pixel, s) = (i as u32 / spp, i as u32 % spp);
                            reflected(scene, tr, sp, (pixel, s * n), n)
                        }
                        Seen::Sky => crate::integrator::direct::escaped_light(
                            scene,
                            V::from(self.file.views[i].d),
                            None,
                        ),
                        Seen::Nothing => V::ZERO,
                    };
                    beta * l
                },
            )
            .collect()
    }
}

/// Per material, the factor on its emission the scene's light set put: the scene's
/// emission over the archive's own.
fn lamp_scale(file: &RelightFile, scene: &Scene) -> Result<Vec<V>> {
    let own = canopy_format::Archive::open(&file.archive)?;
    let n = own.materials.len().min(scene.materials.len());
    if let Some(c) = file.emits.iter().find(|c| c.index as usize >= n) {
        bail!(
            "{}: a pixel's lamp names material {} of {n}",
            file.archive.display(),
            c.index
        );
    }
    Ok((0..n)
        .map(|m| {
            let old = V::from(own.materials[m].emission);
            let new = scene.materials[m].emission;
            V::select(old.cmpgt(V::ZERO), new / old, V::ZERO)
        })
        .collect())
}

/// E/π arriving at gather point `p` from one light sample.
fn arriving(scene: &Scene, tr: &mut Tracer, p: &cells::GatherPoint, u: [f32; 3]) -> V {
    let (at, n) = (V::from(p.p), V::from(p.n));
    let rec = Receiver::surface(at, at.abs() * crate::trace::gamma(7), n);
    sample_light_weighted(scene, tr, &rec, &Cone::EXACT, u, |wi, _| {
        V::splat(n.dot(wi).max(0.0) * std::f32::consts::FRAC_1_PI)
    })
}

/// Direct light reflected at `sp` toward the camera: `n` light samples (next-event
/// estimation alone: a light set's lamps are where it puts them), numbers `first..` of
/// the pixel's sequence, so the samples of a pixel's view samples stratify together.
fn reflected(
    scene: &Scene,
    tr: &mut Tracer,
    sp: &ShadingPoint,
    (pixel, first): (u32, u32),
    n: u32,
) -> V {
    if sp.absorbs || sp.bsdf.has_smooth_only() {
        return V::ZERO;
    }
    let rec = Receiver::surface(sp.p, sp.err, sp.ng);
    let f = bsdf_term(sp.frame, sp.n, sp.bsdf, sp.wo_l);
    let mut sum = V::ZERO;
    for l in 0..n {
        let [u0, u1, u2, _] = PixelSampler::new(DIRECT_SEED, pixel, first + l).get4(0);
        sum += sample_light_weighted(scene, tr, &rec, &Cone::EXACT, [u0, u1, u2], |wi, _| f(wi).0);
    }
    sum / n as f32
}
