//! Relighting with global illumination (seed 001, Kontkanen et al. 2006; carried to large
//! scenes over a hierarchy by Hašan, Pellacini and Bala 2006): for one fixed view, the
//! transfer from light arriving at the scene's surfaces to every pixel is precomputed once
//! (`prepare`), all bounces included, over the light cells of the node tree's leaves and
//! compressed along the tree's order; a light set is then rendered (`Relighter::frame`) as
//! direct light at the view samples plus the product of the transfer with direct light
//! gathered at the cells the transfer reads.
//! Light transport is linear in the emitters, so the product is exact up to the transfer's
//! compression and noise: lamps may be scaled and tinted, punctual lights moved, re-aimed
//! or added, the environment made stronger or turned, each without a new precompute.
//!
//! Where light arrives at an interior path vertex it leaves through the diffuse lobe only:
//! lamps' light reflected by glossy surfaces onto others (and caustics) is not carried.

mod cells;
pub mod file;
mod relighter;
pub mod serve;
mod transfer;
mod view;

pub use relighter::{Frame, RelightOptions, Relighter};

use crate::camera::Camera;
use crate::integrator::Scene;
use crate::light_store::Keys;
use crate::material::luminance;
use crate::render::{RenderOptions, Setup};
use crate::sampler::{Hash, PixelSampler};
use crate::trace::Tracer;
use anyhow::{bail, Context, Result};
use file::{Coef, Header, RelightFile};
use glam::Vec3A as V;
use rayon::prelude::*;
use rustc_hash::FxHashMap;
use std::path::PathBuf;
use std::time::Instant;

/// Camera samples per pixel that measure the lamps it sees directly (their edges need more
/// than the view samples).
const EMISSION_SAMPLES: u32 = 64;
/// Largest coefficient stored (half precision's largest finite value).
const F16_MAX: f32 = 65504.0;

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
    if archive.header.instances.count > 0 {
        bail!(
            "{}: relighting reads light per node of the scene's own tree, and the archive places {} instances (convert with instances flattened)",
            o.archive.display(),
            archive.header.instances.count
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
    let file = assemble(
        o,
        (w, h),
        archive.header.header_checksum,
        &parts,
        &index,
        points,
    );
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
        let mut lamp = |material, l: V| {
            *lamps.entry(material).or_insert(V::ZERO) += l / samples as f32;
        };
        let (vr, seen) = view::view_sample(scene, tr, ray, &sampler, &mut lamp);
        let Some(sp) = seen else {
            views.extend((s < o.spp).then_some(vr));
            continue;
        };
        let beta = V::from(vr.beta);
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
