//! Relighting with global illumination (seed 001, Kontkanen et al. 2006; carried to large
//! scenes over a hierarchy by Hašan, Pellacini and Bala 2006): for one fixed view, the
//! transfer from light arriving at the scene's surfaces to every pixel is precomputed once
//! (`prepare`), all bounces included, over the light cells of the node tree's leaves and
//! compressed along the tree's order; a light set is then rendered (`Relighter::frame`) as
//! direct light at the view samples plus the product of the transfer with direct light
//! gathered at the cells the transfer reads.
//! Light transport is linear in the emitters, so the product is exact up to the transfer's
//! compression and noise: lamps may be scaled and tinted, punctual lights moved, re-aimed
//! or added, the environment made stronger, each without a new precompute.
//!
//! Where light arrives at an interior path vertex it leaves through the diffuse lobe only:
//! lamps' light reflected by glossy surfaces onto others (and caustics) is not carried.

mod cells;
pub mod file;
mod transfer;
mod view;

use crate::camera::Camera;
use crate::integrator::{bsdf_term, sample_light_weighted, Receiver, Scene, ShadingPoint};
use crate::light_store::Keys;
use crate::material::luminance;
use crate::render::{RenderOptions, Setup};
use crate::sampler::{Hash, PixelSampler};
use crate::trace::{Cone, Tracer};
use anyhow::{bail, Context, Result};
use file::{Coef, Header, RelightFile};
use glam::Vec3A as V;
use rayon::prelude::*;
use rustc_hash::FxHashMap;
use std::path::PathBuf;
use std::time::Instant;
use view::Seen;

/// Camera samples per pixel that measure the lamps it sees directly (their edges need more
/// than the view samples).
const EMISSION_SAMPLES: u32 = 64;
/// Largest coefficient stored (half precision's largest finite value).
const F16_MAX: f32 = 65504.0;
/// Seeds of the light samples' sequences at the gather points and the view samples: fixed,
/// so a light set relit twice gives the same image and a change shows only itself.
const GATHER_SEED: u32 = 0x11E;
const DIRECT_SEED: u32 = 0xD1EC7;

/// What one pixel's precompute gives: its view samples, compressed transfer row, and the
/// lamps it sees by material.
struct PixelPart {
    views: Vec<view::ViewRay>,
    row: Vec<(u64, V)>,
    emits: Vec<(u32, V)>,
}

/// What `prepare` precomputes.
#[derive(Clone, Debug)]
pub struct PrepareOptions {
    pub archive: PathBuf,
    pub output: PathBuf,
    pub camera: Option<String>,
    pub width: Option<u32>,
    pub height: Option<u32>,
    /// View samples per pixel.
    pub spp: u32,
    /// Transfer paths per view sample.
    pub paths: u32,
    /// Most coefficients a pixel's transfer row keeps (the compression's accuracy knob).
    pub coefficients: u32,
    pub seed: u32,
    pub mem_budget: Option<u64>,
    pub threads: Option<usize>,
    pub progress: bool,
}

/// How a precompute went.
#[derive(Debug, serde::Serialize)]
pub struct PrepareStats {
    pub seconds: f64,
    pub pixels: u64,
    pub cells: u64,
    pub coefs: u64,
    pub bytes: u64,
}

impl std::fmt::Display for PrepareStats {
    fn fmt(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        write!(
            f,
            "{} pixels, {} light cells, {:.1} coefficients per pixel, {}, {:.2} s",
            self.pixels,
            self.cells,
            self.coefs as f64 / self.pixels.max(1) as f64,
            crate::units::format_size(self.bytes),
            self.seconds
        )
    }
}

/// Render options for the scene of a relight: the path tracer's, which reads lights as
/// the archive and a light set give them.
fn scene_options(
    archive: PathBuf,
    output: PathBuf,
    camera: Option<String>,
    size: (Option<u32>, Option<u32>),
    budget: (Option<u64>, Option<usize>),
    lights: Option<PathBuf>,
) -> RenderOptions {
    RenderOptions {
        archive,
        output,
        integrator: crate::integrator::Settings::Path,
        spp: 1,
        time: None,
        noise: None,
        mem_budget: budget.0,
        width: size.0,
        height: size.1,
        camera,
        seed: 0,
        threads: budget.1,
        max_depth: None,
        texture_filter: crate::texture::TextureFilter::Trilinear,
        pixel_split: None,
        env: None,
        lights,
        display: None,
        crop: None,
        preview: false,
        exposure: 1.0,
        stats: None,
        node_stats: false,
        progress: false,
    }
}

fn header_hash(archive: &canopy_format::Archive) -> u64 {
    xxhash_rust::xxh3::xxh3_64(bytemuck::bytes_of(&archive.header))
}

/// Precomputes the view and transfer of `o.archive` seen from `o.camera`, into `o.output`.
pub fn prepare(o: &PrepareOptions) -> Result<PrepareStats> {
    let t0 = Instant::now();
    if o.spp == 0 || o.paths == 0 {
        bail!("--spp and --paths must be at least 1");
    }
    if o.coefficients == 0 {
        bail!("--coefficients must be at least 1");
    }
    crate::image::check_writable(&o.output)?;
    let ro = scene_options(
        o.archive.clone(),
        o.output.clone(),
        o.camera.clone(),
        (o.width, o.height),
        (o.mem_budget, o.threads),
        None,
    );
    let s = Setup::open(&ro, (o.output.clone(), None))?;
    let scene = &s.scene;
    let archive = &scene.cache.archive;
    if !archive.instances.is_empty() {
        bail!(
            "{}: relighting reads light per node of the scene's own tree, and the archive places {} instances (convert with instances flattened)",
            o.archive.display(),
            archive.instances.len()
        );
    }
    let keys =
        Keys::new(&archive.header).context("the archive's node numbers do not fit 64-bit keys")?;
    let (w, h) = (s.width, s.height);
    let bar = crate::progress::bar(o.progress, h as u64, "relight precompute (rows)");
    let parts: Vec<PixelPart> = s.pool.install(|| {
        (0..h)
            .into_par_iter()
            .flat_map_iter(|y| {
                let mut tr = Tracer::new(&scene.cache);
                let out: Vec<PixelPart> = (0..w)
                    .map(|x| pixel(scene, &mut tr, &keys, o, (x, y)))
                    .collect();
                bar.inc(1);
                out
            })
            .collect()
    });
    bar.finish_and_clear();
    if let Some(err) = scene.error() {
        bail!("{err}");
    }
    let mut keys_used: Vec<u64> = parts.iter().flat_map(|p| &p.row).map(|e| e.0).collect();
    keys_used.par_sort_unstable();
    keys_used.dedup();
    let index: FxHashMap<u64, u32> = keys_used
        .iter()
        .enumerate()
        .map(|(i, &k)| (k, i as u32))
        .collect();
    let mut carried = vec![0.0f32; keys_used.len()];
    for (k, v) in parts.iter().flat_map(|p| &p.row) {
        carried[index[k] as usize] += luminance(*v);
    }
    let count = cells::counts(&carried);
    let points: Vec<Vec<cells::GatherPoint>> = s.pool.install(|| {
        keys_used
            .par_iter()
            .zip(&count)
            .map(|(&k, &n)| {
                cells::points(&scene.cache, &keys, k, n, &mut Hash::new(k ^ o.seed as u64))
            })
            .collect()
    });
    let file = assemble(o, (w, h), header_hash(archive), &parts, &index, points);
    file.write(&o.output)?;
    Ok(PrepareStats {
        seconds: t0.elapsed().as_secs_f64(),
        pixels: w as u64 * h as u64,
        cells: keys_used.len() as u64,
        coefs: file.coef_cell.len() as u64,
        bytes: std::fs::metadata(&o.output).map_or(0, |m| m.len()),
    })
}

/// Pixel (x, y)'s view samples, compressed transfer row and lamps seen.
fn pixel(
    scene: &Scene,
    tr: &mut Tracer,
    keys: &Keys,
    o: &PrepareOptions,
    (x, y): (u32, u32),
) -> PixelPart {
    let cam: &Camera = &scene.camera;
    let weight = 1.0 / (o.spp * o.paths) as f32;
    let index = y * cam.width + x;
    let mut row = transfer::Row::default();
    let mut views = Vec::new();
    let mut lamps: FxHashMap<u32, V> = FxHashMap::default();
    let samples = o.spp.max(EMISSION_SAMPLES);
    for s in 0..samples {
        let sampler = PixelSampler::new(o.seed, index, s);
        let [jx, jy, ..] = sampler.get4(0);
        let ray = cam.ray(x as f32 + jx, y as f32 + jy);
        let (vr, seen) = view::view_sample(scene, tr, ray, &sampler);
        let Some((sp, material)) = seen else {
            views.extend((s < o.spp).then_some(vr));
            continue;
        };
        let beta = V::from(vr.beta);
        if sp.emitted.max_element() > 0.0 {
            *lamps.entry(material).or_insert(V::ZERO) += beta * sp.emitted / samples as f32;
        }
        if s >= o.spp {
            continue;
        }
        views.push(vr);
        for m in 0..o.paths {
            let ps = PixelSampler::new(o.seed ^ 0x5EED, index, s * o.paths + m);
            transfer::follow(scene, tr, &sp, beta, &ps, (keys, weight), &mut row);
        }
    }
    let mut emits: Vec<(u32, V)> = lamps.into_iter().collect();
    emits.sort_unstable_by_key(|e| e.0);
    PixelPart {
        views,
        row: transfer::compress(
            &row,
            o.coefficients,
            Hash::new(index as u64 ^ (o.seed as u64) << 32).f32(),
        ),
        emits,
    }
}

/// The file's sections from the precompute's parts.
fn assemble(
    o: &PrepareOptions,
    (w, h): (u32, u32),
    archive_header: u64,
    parts: &[PixelPart],
    index: &FxHashMap<u64, u32>,
    points: Vec<Vec<cells::GatherPoint>>,
) -> RelightFile {
    let archive = o
        .archive
        .canonicalize()
        .unwrap_or_else(|_| o.archive.clone());
    let mut cell_first = vec![0u64];
    for p in &points {
        cell_first.push(cell_first.last().copied().unwrap_or(0) + p.len() as u64);
    }
    let (mut row_first, mut coef_cell, mut coef_w) = (vec![0u64], Vec::new(), Vec::new());
    let (mut emit_first, mut emits) = (vec![0u64], Vec::new());
    let mut views = Vec::new();
    for p in parts {
        views.extend_from_slice(&p.views);
        coef_cell.extend(p.row.iter().map(|(k, _)| index[k]));
        coef_w.extend(
            p.row
                .iter()
                .map(|(_, v)| v.to_array().map(|x| half::f16::from_f32(x.min(F16_MAX)))),
        );
        row_first.push(coef_cell.len() as u64);
        emits.extend(
            p.emits
                .iter()
                .map(|&(index, v)| Coef { index, w: v.into() }),
        );
        emit_first.push(emits.len() as u64);
    }
    let mut camera = [0u8; 64];
    let name = o.camera.as_deref().unwrap_or("").as_bytes();
    camera[..name.len().min(64)].copy_from_slice(&name[..name.len().min(64)]);
    let points: Vec<cells::GatherPoint> = points.concat();
    RelightFile {
        header: Header {
            magic: file::MAGIC,
            version: file::VERSION,
            width: w,
            height: h,
            spp: o.spp,
            paths: o.paths,
            coefficients: o.coefficients,
            seed: o.seed,
            path_len: archive.to_string_lossy().len() as u32,
            views: views.len() as u64,
            cells: index.len() as u64,
            points: points.len() as u64,
            coefs: coef_cell.len() as u64,
            emits: emits.len() as u64,
            archive_header,
            camera,
        },
        archive,
        views,
        cell_first,
        points,
        row_first,
        coef_cell,
        coef_w,
        emit_first,
        emits,
    }
}

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
