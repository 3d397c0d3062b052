//! Rendering a light set from a precomputed view: direct light at the view samples, light
//! gathered at the transfer's cells, and their product with the transfer.

use super::file::{Coef, RelightFile};
use super::view::{Bsdfs, Seen, Surface};
use super::{cells, scene_options};
use crate::integrator::direct::escaped_light;
use crate::integrator::{bsdf_term, on_side, sample_light, Receiver, Scene};
use crate::light::{LightSet, Lights, Punctual};
use crate::material::Material;
use crate::render::{gather_lights, Setup};
use crate::sampler::{Hash, PixelSampler};
use crate::trace::{Cone, Tracer};
use anyhow::{bail, Context, Result};
use canopy_format::{LightRecord, MaterialRecord};
use glam::Vec3A as V;
use half::slice::HalfFloatSliceExt;
use rayon::prelude::*;
use rustc_hash::FxHashMap;
use std::ops::Range;
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
    /// Light and BSDF samples per view sample for each lamp and the environment (a gather point
    /// takes one, a punctual light one).
    pub light_samples: u32,
    pub mem_budget: Option<u64>,
    pub threads: Option<usize>,
}

/// A view ready to relight: its file, scene and view samples' shading points, and each
/// light's share of the image (light is linear in the lights: a share computed once is
/// scaled when only a light's strength or colour changes, and traced again only when the
/// light moves or a new one comes).
pub struct Relighter {
    pub file: RelightFile,
    pub setup: Setup,
    seen: Vec<Seen>,
    bsdfs: Vec<crate::material::Bsdf>,
    light_samples: u32,
    /// Per material, the factor the light set puts on its lamps' emission.
    lamp_scale: Vec<V>,
    /// The archive's own material and light records, which a light set changes.
    own: (Vec<MaterialRecord>, Vec<LightRecord>),
    /// The light set's punctual lights.
    punctual: Vec<Punctual>,
    /// The archive's own lamps, by material, and the environment alone: each the lights a
    /// share is traced under.
    lamps: FxHashMap<u32, Lights>,
    env: Option<Lights>,
    /// The light set's environment: a factor on its strength, and the degrees it is turned
    /// from the environment the view was opened with.
    env_strength: f32,
    env_turn: f32,
    /// The degrees the environment in `env` is turned now.
    env_turned: f32,
    /// The scene's bounding sphere (centre, radius), which a light set's lights are made in.
    sphere: (V, f32),
    shares: FxHashMap<Key, Share>,
}

/// What a share of the image is the light of: a material's lamps, a punctual light at unit
/// intensity by its kind, position, direction and cone (bits), or the environment at unit
/// strength turned by some degrees (bits).
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
enum Key {
    Lamps(u32),
    Punctual([u32; 9]),
    Environment(u32),
}

/// A share is traced in slices, one a frame: slice 0 is one gather point of each cell (drawn
/// at random among its points) and one view sample of each pixel, slice `d` ≥ 1 every
/// (`SLICES` − 1)-th of the others (`slice`). A light moved or added shows after one ray a
/// cell and a pixel, and its share is complete `SLICES` frames later.
const SLICES: u32 = 4;

/// The slice of a cell's `j`-th point (counted from its first-drawn) or a pixel's `j`-th
/// view sample.
fn slice(j: u32) -> u32 {
    match j {
        0 => 0,
        j => 1 + (j - 1) % (SLICES - 1),
    }
}

/// One light's share: direct light at each pixel and E/π at each cell, over the slices
/// traced so far.
struct Share {
    /// Per pixel, the direct light its view samples traced so far send, summed.
    direct: Vec<V>,
    /// Per cell, the mean E/π over its points traced so far.
    gathered: Vec<V>,
    /// Per pixel, the environment its transfer met (its sky records; the environment's
    /// share only; empty for the others).
    sky: Vec<V>,
    /// Slices traced.
    done: u32,
}

impl Share {
    /// The weight that makes a pixel's sum the mean over its `spp` view samples traced.
    fn direct_weight(&self, spp: u32) -> f32 {
        1.0 / (0..spp).filter(|&j| slice(j) < self.done).count().max(1) as f32
    }
}

/// A cell's points in slice `d` (`slice`), as places counted from the cell's first-drawn
/// point.
fn slice_points(n: usize, d: u32) -> std::iter::StepBy<Range<usize>> {
    match d {
        0 => (0..n.min(1)).step_by(1),
        d => (d as usize..n).step_by(SLICES as usize - 1),
    }
}

/// A punctual light at unit intensity, its key, and the intensity it had.
fn unit(p: &Punctual) -> (Punctual, Key, V) {
    match *p {
        Punctual::Spot {
            pos,
            dir,
            intensity,
            cos_outer,
            cos_inner,
        } => {
            let u = Punctual::Spot {
                pos,
                dir,
                intensity: V::ONE,
                cos_outer,
                cos_inner,
            };
            let b = [
                0.0, pos.x, pos.y, pos.z, dir.x, dir.y, dir.z, cos_outer, cos_inner,
            ];
            (u, Key::Punctual(b.map(f32::to_bits)), intensity)
        }
        Punctual::Directional { dir, irradiance } => {
            let u = Punctual::Directional {
                dir,
                irradiance: V::ONE,
            };
            let b = [1.0, dir.x, dir.y, dir.z, 0.0, 0.0, 0.0, 0.0, 0.0];
            (u, Key::Punctual(b.map(f32::to_bits)), irradiance)
        }
    }
}

/// One relit image and the time its parts took: tracing a slice of the shares not yet
/// complete (light gathered at the cells, direct light at the view samples), summing the
/// shares with their factors, the transfer's product; and whether every share it read was
/// complete.
pub struct Frame {
    pub image: crate::image::Image,
    pub seconds: [f64; 3],
    pub complete: bool,
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
        let mut setup = Setup::open(&ro, output).with_context(|| {
            format!(
                "{}: opening the archive it was precomputed on",
                o.view.display()
            )
        })?;
        if setup.scene.cache.archive.header.header_checksum != h.archive_header {
            bail!(
                "{}: {} has changed since the view was precomputed (run `canopy relight` on the archive again)",
                o.view.display(),
                file.archive.display()
            );
        }
        let scene = &setup.scene;
        let chunks: Vec<(Vec<Seen>, Bsdfs)> = setup.pool.install(|| {
            file.views()
                .par_chunks(4096)
                .map(|c| {
                    let (mut tr, mut bsdfs) = (Tracer::new(&scene.cache), Bsdfs::default());
                    let seen = c.iter().map(|v| v.trace(scene, &mut tr, &mut bsdfs));
                    (seen.collect(), bsdfs)
                })
                .collect()
        });
        let (mut seen, mut bsdfs) = (Vec::with_capacity(file.views().len()), Bsdfs::default());
        for (mut s, b) in chunks {
            bsdfs.merge(&b, &mut s);
            seen.extend(s);
        }
        if let Some(err) = scene.error() {
            bail!("{err}");
        }
        // The archive's own records: the scene's are a light set's when --lights was given.
        let own = match o.lights {
            Some(_) => {
                let a = canopy_format::Archive::open(&file.archive)?;
                (a.materials, a.lights)
            }
            None => {
                let a = &scene.cache.archive;
                (a.materials.clone(), a.lights.clone())
            }
        };
        let lamp_scale = lamp_scale(&file, &own.0, &scene.materials)?;
        let sphere = scene.lights.sphere();
        let lamps = lamps_by_material(scene, &own.0)?;
        let lights = std::mem::take(&mut setup.scene.lights);
        let env = lights
            .env
            .map(|e| Lights::new(Vec::new(), Vec::new(), Some(e), sphere.0, sphere.1));
        Ok(Relighter {
            file,
            setup,
            seen,
            bsdfs: bsdfs.list,
            light_samples: o.light_samples,
            lamp_scale,
            own,
            punctual: lights.punctual,
            lamps,
            env,
            env_strength: 1.0,
            env_turn: 0.0,
            env_turned: 0.0,
            sphere,
            shares: FxHashMap::default(),
        })
    }

    /// Puts `set` in place of the light set the view was opened with: the archive's own
    /// lamps, punctual lights and environment as `set` changes them. Returns a note when
    /// the set leaves no light at all (the image is then black).
    pub fn set_lights(&mut self, set: &LightSet) -> Result<Option<String>> {
        let change = set.environment_change();
        if change.is_some() && self.env.is_none() {
            bail!("[environment] changes the view's environment, and it was opened with none");
        }
        (self.env_strength, self.env_turn) = change.unwrap_or((1.0, 0.0));
        let (mut materials, mut lights) = self.own.clone();
        set.apply_to_lamps(&mut materials, &mut lights)?;
        let scene = &mut self.setup.scene;
        scene.materials = materials.iter().map(Material::from_record).collect();
        self.lamp_scale = lamp_scale(&self.file, &self.own.0, &scene.materials)?;
        self.punctual = lights.iter().filter_map(crate::light::punctual).collect();
        let lamps_on = self
            .lamps
            .keys()
            .any(|&m| self.lamp_scale[m as usize].max_element() > 0.0);
        let env_on = self.env.is_some() && self.env_strength > 0.0;
        let dark = !lamps_on && self.punctual.is_empty() && !env_on;
        Ok(dark.then(|| "the light set leaves no light on: the image is black".to_string()))
    }

    /// Whether the view was opened with an environment (which a light set may change).
    pub fn has_environment(&self) -> bool {
        self.env.is_some()
    }

    /// The archive's own material and light records (before any light set).
    pub fn own_records(&self) -> (&[MaterialRecord], &[LightRecord]) {
        (&self.own.0, &self.own.1)
    }

    /// The shares the current light set reads, with the factor on each.
    fn wanted(&self) -> Vec<(Key, V)> {
        let lamps = self
            .lamps
            .keys()
            .map(|&m| (Key::Lamps(m), self.lamp_scale[m as usize]));
        let punctual = self.punctual.iter().map(|p| {
            let (_, key, scale) = unit(p);
            (key, scale)
        });
        let env = self.env.as_ref().map(|_| {
            let key = Key::Environment(self.env_turn.to_bits());
            (key, V::splat(self.env_strength))
        });
        lamps
            .chain(punctual)
            .chain(env)
            .filter(|(_, s)| s.max_element() > 0.0)
            .collect()
    }

    /// Traces the share of `key` under its lights alone, its slices from those done to
    /// `upto`, in one pass.
    fn trace_slices(&mut self, key: Key, share: &mut Share, upto: u32) {
        let (c, r) = self.sphere;
        let lights = match key {
            Key::Lamps(m) => self.lamps.remove(&m),
            Key::Environment(bits) => self.env.take().map(|mut lights| {
                let turn = f32::from_bits(bits);
                if let Some(e) = lights.env.as_mut() {
                    e.turn(turn - self.env_turned);
                }
                self.env_turned = turn;
                lights
            }),
            Key::Punctual(_) => self
                .punctual
                .iter()
                .map(unit)
                .find(|u| u.1 == key)
                .map(|u| Lights::new(Vec::new(), vec![u.0], None, c, r)),
        }
        .expect("a wanted share's lights exist");
        // A punctual light is one delta: its one light sample is exact.
        let n = match key {
            Key::Punctual(_) => 1,
            _ => self.light_samples,
        };
        let others = std::mem::replace(&mut self.setup.scene.lights, lights);
        let slices = share.done..upto;
        self.setup.pool.install(|| {
            if matches!(key, Key::Environment(_)) && slices.start == 0 {
                share.sky = self.sky();
            }
            self.gather(share, slices.clone());
            self.direct(n, share, slices);
        });
        share.done = upto;
        let lights = std::mem::replace(&mut self.setup.scene.lights, others);
        match key {
            Key::Lamps(m) => {
                self.lamps.insert(m, lights);
            }
            Key::Environment(_) => self.env = Some(lights),
            Key::Punctual(_) => {}
        }
    }

    /// The image under the current light set, complete: every share it reads traced whole.
    pub fn image(&mut self) -> Result<Frame> {
        self.render(SLICES)
    }

    /// The next image under the current light set, as the web page shows it: one more
    /// slice of each share it reads that is not complete.
    pub fn frame(&mut self) -> Result<Frame> {
        self.render(1)
    }

    /// The shares the light set reads, each traced `slices` further (where not complete),
    /// summed with their factors and multiplied by the transfer.
    fn render(&mut self, slices: u32) -> Result<Frame> {
        let t0 = Instant::now();
        let wanted = self.wanted();
        let spp = self.file.header.spp;
        let (cells, pixels) = (
            self.file.cell_first().len() - 1,
            self.file.row_first().len() - 1,
        );
        for &(key, _) in &wanted {
            let mut share = self.shares.remove(&key).unwrap_or_else(|| Share {
                direct: vec![V::ZERO; pixels],
                gathered: vec![V::ZERO; cells],
                sky: Vec::new(),
                done: 0,
            });
            if share.done < SLICES {
                let upto = (share.done + slices).min(SLICES);
                self.trace_slices(key, &mut share, upto);
            }
            self.shares.insert(key, share);
        }
        let complete = wanted.iter().all(|(k, _)| self.shares[k].done == SLICES);
        // Shares no longer read are dropped once they outnumber those read.
        if self.shares.len() > 2 * wanted.len() + 4 {
            self.shares.retain(|k, _| wanted.iter().any(|w| w.0 == *k));
        }
        let t1 = Instant::now();
        let (mut e, mut direct) = (vec![V::ZERO; cells], vec![V::ZERO; pixels]);
        for (key, scale) in &wanted {
            let share = &self.shares[key];
            e.par_iter_mut()
                .zip(&share.gathered)
                .for_each(|(a, b)| *a += *scale * *b);
            let w = *scale * share.direct_weight(spp);
            direct
                .par_iter_mut()
                .zip(&share.direct)
                .for_each(|(a, b)| *a += w * *b);
            direct
                .par_iter_mut()
                .zip(&share.sky)
                .for_each(|(a, b)| *a += *scale * *b);
        }
        let t2 = Instant::now();
        let scene = &self.setup.scene;
        let f = &self.file;
        let (rows, cell_of, weights) = (f.row_first(), f.coef_cell(), f.coef_w());
        let (emit_first, emits) = (f.emit_first(), f.emits());
        let pixels: Vec<[f32; 3]> = self.setup.pool.install(|| {
            (0..rows.len() - 1)
                .into_par_iter()
                .map_init(Vec::new, |w, p| {
                    let own = direct[p];
                    let (a, b) = (rows[p] as usize, rows[p + 1] as usize);
                    // Half to single precision a row at a time (F16C where the CPU has it).
                    let half: &[half::f16] = bytemuck::cast_slice(&weights[a..b]);
                    w.resize(half.len(), 0.0);
                    half.convert_to_f32_slice(w);
                    let gi: V = w
                        .chunks_exact(3)
                        .zip(&cell_of[a..b])
                        .map(|(w, &c)| V::new(w[0], w[1], w[2]) * e[c as usize])
                        .sum();
                    let (a, b) = (emit_first[p] as usize, emit_first[p + 1] as usize);
                    let lamps: V = emits[a..b]
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
            complete,
        })
    }

    /// Per pixel, the environment (the scene's, as the share has turned it) along the
    /// directions of its sky records, times their weights.
    fn sky(&self) -> Vec<V> {
        let scene = &self.setup.scene;
        let (first, skies) = (self.file.sky_first(), self.file.skies());
        (0..first.len() - 1)
            .into_par_iter()
            .map(|p| {
                skies[first[p] as usize..first[p + 1] as usize]
                    .iter()
                    .map(|s| V::from(s.w) * escaped_light(scene, V::from(s.d), None))
                    .sum()
            })
            .collect()
    }

    /// Adds `slices` of each cell's gather points to its mean direct light E/π, one sample
    /// at each (`cells::arriving`; a pixel reads many cells, whose noise it averages).
    fn gather(&self, share: &mut Share, slices: Range<u32>) {
        let (first, points) = (self.file.cell_first(), self.file.points());
        let scene = &self.setup.scene;
        share.gathered.par_iter_mut().enumerate().for_each_init(
            || Tracer::new(&scene.cache),
            |tr, (i, mean)| {
                let pts = &points[first[i] as usize..first[i + 1] as usize];
                let n = pts.len();
                let start =
                    (Hash::new(i as u64 ^ GATHER_SEED as u64).u64() % n.max(1) as u64) as usize;
                let sum: V = slices
                    .clone()
                    .flat_map(|d| slice_points(n, d))
                    .map(|m| {
                        let k = (start + m) % n;
                        let s = PixelSampler::new(GATHER_SEED, i as u32, k as u32);
                        cells::arriving(scene, tr, &pts[k], &s)
                    })
                    .sum();
                let count = |r: Range<u32>| -> usize { r.map(|e| slice_points(n, e).len()).sum() };
                let (before, after) = (count(0..slices.start), count(0..slices.end));
                if after > 0 {
                    *mean = (*mean * before as f32 + sum) / after as f32;
                }
            },
        );
    }

    /// Adds to each pixel the light its view samples of `slices` send to the camera from
    /// `n` light samples: the direct light each reflects (or the environment, for a sample
    /// that left the scene), times the throughput of the smooth bounces before it. Lamps
    /// seen directly are the pixel's emission records.
    fn direct(&self, n: u32, share: &mut Share, slices: Range<u32>) {
        let scene = &self.setup.scene;
        let (views, spp) = (self.file.views(), self.file.header.spp as usize);
        share.direct.par_iter_mut().enumerate().for_each_init(
            || Tracer::new(&scene.cache),
            |tr, (pixel, sum)| {
                let traced = (0..spp).filter(|s| slices.contains(&slice(*s as u32)));
                for s in traced {
                    let i = pixel * spp + s;
                    let l = match &self.seen[i] {
                        Seen::Surface(x) => {
                            let b = &self.bsdfs[x.bsdf as usize];
                            reflected(scene, tr, (x, b), (pixel as u32, s as u32 * n), n)
                        }
                        Seen::Sky => {
                            let d = V::from(views[i].d);
                            crate::integrator::direct::escaped_light(scene, d, None)
                        }
                        Seen::Nothing => V::ZERO,
                    };
                    *sum += V::from(views[i].beta) * l;
                }
            },
        );
    }
}

/// The archive's own lamps (its own emission, `own`), one set of lights per material.
fn lamps_by_material(scene: &Scene, own: &[MaterialRecord]) -> Result<FxHashMap<u32, Lights>> {
    let materials: Vec<Material> = own.iter().map(Material::from_record).collect();
    let all = gather_lights(&scene.cache.archive, &materials, &scene.textures)?;
    Ok(all.by_material().into_iter().collect())
}

/// Per material, the factor on its emission a light set put: `materials`' emission over
/// the archive's own (`own`). Every material a pixel's lamp record names must exist.
fn lamp_scale(
    file: &RelightFile,
    own: &[MaterialRecord],
    materials: &[Material],
) -> Result<Vec<V>> {
    let n = own.len().min(materials.len());
    if let Some(c) = file.emits().iter().find(|c| c.index as usize >= n) {
        bail!(
            "{}: a pixel's lamp names material {} of {n}",
            file.archive.display(),
            c.index
        );
    }
    Ok((0..n)
        .map(|m| {
            let old = V::from(own[m].emission);
            let new = materials[m].emission;
            V::select(old.cmpgt(V::ZERO), new / old, V::ZERO)
        })
        .collect())
}

/// Direct light reflected at `x` toward the camera, from `n` samples of each of two
/// strategies combined by the power heuristic, as the path tracer combines them: a light
/// sample, and a BSDF sample that may meet a lamp or the environment (where the share has
/// either; a BSDF sample of a smooth lobe meets the environment only, a lamp there being a
/// lamp record). Numbers `first..` of the pixel's sequence, so the samples of a pixel's view
/// samples stratify together.
fn reflected(
    scene: &Scene,
    tr: &mut Tracer,
    (x, bsdf): (&Surface, &crate::material::Bsdf),
    (pixel, first): (u32, u32),
    n: u32,
) -> V {
    let (p, err, normal) = (V::from(x.p), V::from(x.err), V::from(x.n));
    let (frame, wo_l) = (x.frame(), V::from(x.wo_l));
    let rec = Receiver::surface(p, err, normal);
    let f = bsdf_term(frame, normal, *bsdf, wo_l);
    let met = scene.lights.has_area();
    let mut sum = V::ZERO;
    for l in 0..n {
        let s = PixelSampler::new(DIRECT_SEED, pixel, first + l);
        let [u0, u1, u2, u3] = s.get4(0);
        sum += sample_light(scene, tr, &rec, &Cone::EXACT, [u0, u1, u2], &f);
        if !met {
            continue;
        }
        let [u4, u5, u6, _] = s.get4(1);
        let Some(bs) = bsdf.sample(wo_l, u3, [u4, u5]) else {
            continue;
        };
        let wi = frame.to_world(bs.wi).normalize();
        if on_side(&frame, normal, wi) && bs.weight.is_finite() {
            let pdf = (!bs.delta).then_some(bs.pdf);
            sum += bs.weight * cells::met_light(scene, tr, (p, err, normal), wi, pdf, u6);
        }
    }
    sum / n as f32
}
