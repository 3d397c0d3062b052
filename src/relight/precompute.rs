//! The precompute of a view, streamed so that its memory is bounded by the image, not by
//! the scene: pixels are done a band at a time, their view samples written to the file as
//! they come and their rows' coefficients to two scratch files; the cells the rows read
//! are then numbered (sorted by key), their gather points written as they are made, and
//! the rows copied into the file with their cells' numbers. Only per-pixel offsets, the
//! lamps seen and one weight per cell stay in memory.

use super::file::{self, Coef, Header, Writer};
use super::{cells, scene_options, transfer, view, PrepareOptions, PrepareStats};
use crate::camera::Camera;
use crate::integrator::Scene;
use crate::light_store::Keys;
use crate::material::luminance;
use crate::render::Setup;
use crate::sampler::{Hash, PixelSampler};
use crate::trace::Tracer;
use anyhow::{bail, Context, Result};
use glam::Vec3A as V;
use half::f16;
use rayon::prelude::*;
use rustc_hash::FxHashMap;
use std::fs::File;
use std::io::{BufReader, BufWriter, Read, Seek, Write};
use std::path::Path;
use std::time::Instant;

/// Camera samples per pixel that measure the lamps it sees directly (their edges need more
/// than the view samples).
const EMISSION_SAMPLES: u32 = 64;
/// Largest coefficient stored (half precision's largest finite value).
const F16_MAX: f32 = 65504.0;
/// Pixels precomputed at once, and cells whose points are made at once.
const BAND: u32 = 4096;
const CELL_BATCH: usize = 1 << 16;
/// Coefficients copied from the scratch files at once.
const COPY_BATCH: usize = 1 << 20;

/// What one pixel's precompute gives: its view samples, compressed transfer row, and the
/// lamps it sees by material.
struct PixelPart {
    views: Vec<view::ViewRay>,
    row: Vec<(u64, V)>,
    emits: Vec<(u32, V)>,
}

/// What the pass over the pixels leaves: per pixel its first coefficient and emission
/// record, the emission records, the rows' cell keys and weights in scratch files, and per
/// cell key the transfer it carries over the image (luminance).
struct Rows {
    row_first: Vec<u64>,
    emit_first: Vec<u64>,
    emits: Vec<Coef>,
    keys: File,
    weights: File,
    carried: FxHashMap<u64, f32>,
}

/// Precomputes the view and transfer of `o.archive` seen from `o.camera`, into `o.output`.
/// Under `--mem-budget` the archive's pages take three quarters of it; the precompute's own
/// tables (per pixel and per cell) the rest.
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
        (o.mem_budget.map(|b| b - b / 4), o.threads),
        None,
    );
    let s = Setup::open(&ro, (o.output.clone(), None))?;
    let archive = &s.scene.cache.archive;
    let keys = Keys::new(&archive.header).with_context(|| {
        format!(
            "{}: its nodes, placed by its {} instances, number more than 64-bit light keys hold",
            o.archive.display(),
            archive.header.instances.count
        )
    })?;
    let path = o
        .archive
        .canonicalize()
        .unwrap_or_else(|_| o.archive.clone());
    let mut out = Writer::create(&o.output, &path)?;
    let scratch = match o.output.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let mut rows = rows(o, &s, &keys, &mut out, scratch)?;
    let mut cell_keys: Vec<u64> = rows.carried.keys().copied().collect();
    cell_keys.par_sort_unstable();
    let carried: Vec<f32> = cell_keys.iter().map(|k| rows.carried[k]).collect();
    rows.carried = FxHashMap::default();
    let (points, cell_first) = points(o, &s, &keys, &cell_keys, &carried, &mut out)?;
    out.section(&cell_first)?;
    out.section(&rows.row_first)?;
    let coefs = *rows
        .row_first
        .last()
        .expect("one offset a pixel and one more");
    copy_coefficients(&mut rows, &cell_keys, coefs, &mut out)?;
    out.section(&rows.emit_first)?;
    out.section(&rows.emits)?;
    let mut camera = [0u8; 64];
    let name = o.camera.as_deref().unwrap_or("").as_bytes();
    camera[..name.len().min(64)].copy_from_slice(&name[..name.len().min(64)]);
    let pixels = s.width as u64 * s.height as u64;
    out.commit(&Header {
        magic: file::MAGIC,
        version: file::VERSION,
        width: s.width,
        height: s.height,
        spp: o.spp,
        paths: o.paths,
        coefficients: o.coefficients,
        seed: o.seed,
        path_len: path.to_string_lossy().len() as u32,
        views: pixels * o.spp as u64,
        cells: cell_keys.len() as u64,
        points,
        coefs,
        emits: rows.emits.len() as u64,
        archive_header: archive.header.header_checksum,
        camera,
    })?;
    Ok(PrepareStats {
        seconds: t0.elapsed().as_secs_f64(),
        pixels,
        cells: cell_keys.len() as u64,
        coefs,
        bytes: std::fs::metadata(&o.output).map_or(0, |m| m.len()),
    })
}

/// Every pixel, a band at a time: its view samples into `out` (the views section), its
/// row's coefficients into the scratch files, its lamps and offsets kept.
fn rows(
    o: &PrepareOptions,
    s: &Setup,
    keys: &Keys,
    out: &mut Writer,
    scratch: &Path,
) -> Result<Rows> {
    let scene = &s.scene;
    let pixels = s.width * s.height;
    // Scratch files have no name: the kernel reclaims them however the process ends.
    let unnamed = || {
        tempfile::tempfile_in(scratch)
            .with_context(|| format!("{}: cannot create a scratch file", scratch.display()))
    };
    let (mut key_out, mut weight_out) = (BufWriter::new(unnamed()?), BufWriter::new(unnamed()?));
    let (mut row_first, mut emit_first) = (vec![0u64], vec![0u64]);
    let mut emits = Vec::new();
    let mut carried: FxHashMap<u64, f32> = FxHashMap::default();
    let bar = crate::progress::bar(o.progress, pixels as u64, "relight precompute (rows)");
    for band in (0..pixels).step_by(BAND as usize) {
        let parts: Vec<PixelPart> = s.pool.install(|| {
            (band..(band + BAND).min(pixels))
                .into_par_iter()
                .map_init(
                    || Tracer::new(&scene.cache),
                    |tr, i| pixel(scene, tr, keys, o, (i % s.width, i / s.width)),
                )
                .collect()
        });
        if let Some(err) = scene.error() {
            bail!("{err}");
        }
        let mut coefs = *row_first.last().expect("first offset");
        for p in parts {
            out.put(&p.views)?;
            for (k, v) in &p.row {
                *carried.entry(*k).or_insert(0.0) += luminance(*v);
                key_out.write_all(&k.to_le_bytes())?;
                let w = v.to_array().map(|x| f16::from_f32(x.min(F16_MAX)));
                weight_out.write_all(bytemuck::cast_slice(&w))?;
            }
            coefs += p.row.len() as u64;
            row_first.push(coefs);
            emits.extend(
                p.emits
                    .iter()
                    .map(|&(index, v)| Coef { index, w: v.into() }),
            );
            emit_first.push(emits.len() as u64);
        }
        bar.inc((band + BAND).min(pixels) as u64 - band as u64);
    }
    bar.finish_and_clear();
    out.end()?;
    let rewound = |w: BufWriter<File>| -> Result<File> {
        let mut f = w.into_inner().context("writing a scratch file")?;
        f.rewind()?;
        Ok(f)
    };
    Ok(Rows {
        row_first,
        emit_first,
        emits,
        keys: rewound(key_out)?,
        weights: rewound(weight_out)?,
        carried,
    })
}

/// The gather points of every cell, in the cells' order, written to `out` a batch at a
/// time; returns how many, and each cell's first.
fn points(
    o: &PrepareOptions,
    s: &Setup,
    keys: &Keys,
    cell_keys: &[u64],
    carried: &[f32],
    out: &mut Writer,
) -> Result<(u64, Vec<u64>)> {
    let count = cells::counts(carried);
    let mut cell_first = Vec::with_capacity(cell_keys.len() + 1);
    cell_first.push(0u64);
    let mut total = 0u64;
    for (ks, ns) in cell_keys.chunks(CELL_BATCH).zip(count.chunks(CELL_BATCH)) {
        let batch: Vec<Vec<cells::GatherPoint>> = s.pool.install(|| {
            ks.par_iter()
                .zip(ns)
                .map(|(&k, &n)| {
                    let rng = &mut Hash::new(k ^ o.seed as u64);
                    cells::points(&s.scene.cache, keys, k, n, rng)
                })
                .collect()
        });
        for p in batch {
            out.put(&p)?;
            total += p.len() as u64;
            cell_first.push(total);
        }
    }
    if let Some(err) = s.scene.error() {
        bail!("{err}");
    }
    out.end()?;
    Ok((total, cell_first))
}

/// The rows' coefficients from the scratch files into `out`: each key as its cell's
/// number (its place in the sorted `cell_keys`), then the weights as they are.
fn copy_coefficients(r: &mut Rows, cell_keys: &[u64], coefs: u64, out: &mut Writer) -> Result<()> {
    let mut keys = BufReader::new(&mut r.keys);
    let mut left = coefs as usize;
    let mut buf = vec![0u64; COPY_BATCH];
    while left > 0 {
        let n = left.min(COPY_BATCH);
        keys.read_exact(bytemuck::cast_slice_mut(&mut buf[..n]))
            .context("reading a scratch file back")?;
        let cells: Vec<u32> = buf[..n]
            .iter()
            .map(|k| {
                cell_keys
                    .binary_search(k)
                    .expect("every row's key is a cell") as u32
            })
            .collect();
        out.put(&cells)?;
        left -= n;
    }
    out.end()?;
    let mut weights = BufReader::new(&mut r.weights);
    let mut left = coefs as usize * 6;
    let mut buf = vec![0u8; COPY_BATCH * 6];
    while left > 0 {
        let n = left.min(buf.len());
        weights
            .read_exact(&mut buf[..n])
            .context("reading a scratch file back")?;
        out.put(&buf[..n])?;
        left -= n;
    }
    out.end()
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
