//! The precompute of a view, streamed so that its memory is bounded by the image, not by
//! the scene: pixels are done a band at a time, their view samples written to the file as
//! they come and their rows' coefficients (cell, weight, a landing in the cell) to three
//! scratch files; the cells the rows read are then numbered (sorted by key), their gather
//! points drawn from the landings in a pass over the scratch files for each range of cells
//! whose points fit in memory, and the rows copied into the file with their cells'
//! numbers. Only per-pixel offsets, the lamps seen, up to eight sky records a pixel and a
//! few numbers per cell stay in memory.

use super::cells::{self, GatherPoint};
use super::file::{self, Coef, Header, Sky, Writer};
use super::{scene_options, transfer, view, PrepareOptions, PrepareStats};
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
/// Most sky records a pixel keeps (the environment met after a smooth bounce or through a
/// surface).
const MAX_SKIES: usize = 8;
/// Largest coefficient stored (half precision's largest finite value).
const F16_MAX: f32 = 65504.0;
/// Pixels precomputed at once.
const BAND: u32 = 4096;
/// Coefficients read from the scratch files at once.
const COPY_BATCH: usize = 1 << 20;
/// Memory for the gather points of a range of cells, without `--mem-budget` (with it, an
/// eighth of the budget).
const POINTS_MEMORY: u64 = 256 << 20;

/// What one pixel's precompute gives: its view samples, compressed transfer row, and the
/// lamps it sees by material.
struct PixelPart {
    views: Vec<view::ViewRay>,
    row: Vec<transfer::Coefficient>,
    emits: Vec<(u32, V)>,
    skies: Vec<Sky>,
}

/// What the pass over the pixels leaves: per pixel its first coefficient and emission
/// record, the emission records, the rows' cell keys, weights and landings in scratch
/// files, and per cell key what it carries over the image.
struct Rows {
    row_first: Vec<u64>,
    emit_first: Vec<u64>,
    emits: Vec<Coef>,
    sky_first: Vec<u64>,
    skies: Vec<Sky>,
    keys: File,
    weights: File,
    landings: File,
    carried: FxHashMap<u64, Carried>,
}

/// What a cell carries over the image: the luminance of its coefficients' weights (as
/// stored, in half precision) and how many coefficients.
#[derive(Clone, Copy, Default)]
struct Carried {
    lum: f32,
    coefs: u32,
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
    let carried: Vec<Carried> = cell_keys.iter().map(|k| rows.carried[k]).collect();
    rows.carried = FxHashMap::default();
    let coefs = *rows
        .row_first
        .last()
        .expect("one offset a pixel and one more");
    let mut numbers = number_cells(&mut rows.keys, &cell_keys, coefs, unnamed(scratch)?)?;
    let memory = o.mem_budget.map_or(POINTS_MEMORY, |b| b / 8);
    let (points, cell_first) = points(
        (&cell_keys, &carried, o.seed),
        (&mut numbers, &mut rows, coefs),
        memory,
        &mut out,
    )?;
    out.section(&cell_first)?;
    out.section(&rows.row_first)?;
    copy_coefficients(&mut numbers, &mut rows.weights, coefs, &mut out)?;
    out.section(&rows.emit_first)?;
    out.section(&rows.emits)?;
    out.section(&rows.sky_first)?;
    out.section(&rows.skies)?;
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
        skies: rows.skies.len() as u64,
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
    let mut key_out = BufWriter::new(unnamed(scratch)?);
    let mut weight_out = BufWriter::new(unnamed(scratch)?);
    let mut landing_out = BufWriter::new(unnamed(scratch)?);
    let (mut row_first, mut emit_first, mut sky_first) = (vec![0u64], vec![0u64], vec![0u64]);
    let (mut emits, mut skies) = (Vec::new(), Vec::new());
    let mut carried: FxHashMap<u64, Carried> = FxHashMap::default();
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
            for (k, v, landing) in &p.row {
                let w = v.to_array().map(|x| f16::from_f32(x.min(F16_MAX)));
                let c = carried.entry(*k).or_default();
                c.lum += half_luminance(w);
                c.coefs += 1;
                key_out.write_all(&k.to_le_bytes())?;
                weight_out.write_all(bytemuck::cast_slice(&w))?;
                landing_out.write_all(bytemuck::bytes_of(landing))?;
            }
            coefs += p.row.len() as u64;
            row_first.push(coefs);
            emits.extend(
                p.emits
                    .iter()
                    .map(|&(index, v)| Coef { index, w: v.into() }),
            );
            emit_first.push(emits.len() as u64);
            skies.extend(p.skies);
            sky_first.push(skies.len() as u64);
        }
        bar.inc((band + BAND).min(pixels) as u64 - band as u64);
    }
    bar.finish_and_clear();
    out.end()?;
    Ok(Rows {
        row_first,
        emit_first,
        emits,
        sky_first,
        skies,
        keys: rewound(key_out)?,
        weights: rewound(weight_out)?,
        landings: rewound(landing_out)?,
        carried,
    })
}

/// A scratch file in `dir`. It has no name: the kernel reclaims it however the process
/// ends.
fn unnamed(dir: &Path) -> Result<File> {
    tempfile::tempfile_in(dir)
        .with_context(|| format!("{}: cannot create a scratch file", dir.display()))
}

/// A scratch file written, flushed and rewound for reading.
fn rewound(w: BufWriter<File>) -> Result<File> {
    let mut f = w.into_inner().context("writing a scratch file")?;
    f.rewind()?;
    Ok(f)
}

/// The luminance of a weight as stored.
fn half_luminance(w: [f16; 3]) -> f32 {
    luminance(V::from(w.map(f16::to_f32)))
}

/// Each coefficient's cell number (its key's place in the sorted `cell_keys`), from the
/// keys scratch file into `to`, rewound.
fn number_cells(keys: &mut File, cell_keys: &[u64], coefs: u64, to: File) -> Result<File> {
    let mut keys = BufReader::new(keys);
    let mut to = BufWriter::new(to);
    let mut left = coefs as usize;
    let mut buf = vec![0u64; COPY_BATCH];
    while left > 0 {
        let n = left.min(COPY_BATCH);
        keys.read_exact(bytemuck::cast_slice_mut(&mut buf[..n]))
            .context("reading a scratch file back")?;
        for k in &buf[..n] {
            let cell = cell_keys
                .binary_search(k)
                .expect("every row's key is a cell") as u32;
            to.write_all(&cell.to_le_bytes())?;
        }
        left -= n;
    }
    rewound(to)
}

/// The gather points of every cell, in the cells' order, written to `out` a range of cells
/// at a time (as many as `memory` holds points for); returns how many, and each cell's
/// first.
fn points(
    (cell_keys, carried, seed): (&[u64], &[Carried], u32),
    (numbers, rows, coefs): (&mut File, &mut Rows, u64),
    memory: u64,
    out: &mut Writer,
) -> Result<(u64, Vec<u64>)> {
    let count = point_counts(carried);
    let mut cell_first = Vec::with_capacity(cell_keys.len() + 1);
    cell_first.push(0u64);
    let mut start = 0;
    // A cell's points, their list and its sampling state, in bytes.
    let cost = |c: usize| (count[c] * std::mem::size_of::<GatherPoint>() + 40) as u64;
    while start < count.len() {
        let (mut end, mut bytes) = (start + 1, cost(start));
        while end < count.len() && bytes < memory {
            bytes += cost(end);
            end += 1;
        }
        let draw = Draw {
            cells: start..end,
            keys: &cell_keys[start..end],
            carried: &carried[start..end],
            count: &count[start..end],
            seed,
        };
        let files = [&mut *numbers, &mut rows.weights, &mut rows.landings];
        for p in draw.run(files, coefs)? {
            out.put(&p)?;
            cell_first.push(cell_first.last().expect("first offset") + p.len() as u64);
        }
        start = end;
    }
    out.end()?;
    Ok((*cell_first.last().expect("first offset"), cell_first))
}

/// How many points each cell gathers at: `cells::counts` by the transfer each carries,
/// but no more than the landings it has.
fn point_counts(carried: &[Carried]) -> Vec<usize> {
    let lum: Vec<f32> = carried.iter().map(|c| c.lum).collect();
    cells::counts(&lum)
        .into_iter()
        .zip(carried)
        .map(|(n, c)| n.min(c.coefs as usize))
        .collect()
}

/// The gather points of a range of cells, drawn from their landings by systematic sampling
/// on the landings' weights in the order the pixels stored them: a cell's points follow
/// where its transfer lands.
struct Draw<'a> {
    cells: std::ops::Range<usize>,
    keys: &'a [u64],
    carried: &'a [Carried],
    count: &'a [usize],
    seed: u32,
}

/// A cell's systematic sampling so far: its landings' luminance summed, how many landings
/// seen, and the first pick's place (in steps).
#[derive(Clone, Copy)]
struct Picking {
    below: f32,
    seen: u32,
    u: f32,
}

impl Draw<'_> {
    /// One pass over the `coefs` coefficients' scratch files (cell numbers, weights,
    /// landings; rewound after): the range's points.
    fn run(&self, files: [&mut File; 3], coefs: u64) -> Result<Vec<Vec<GatherPoint>>> {
        let mut points: Vec<Vec<GatherPoint>> =
            self.count.iter().map(|&c| Vec::with_capacity(c)).collect();
        let mut state: Vec<Picking> = self
            .keys
            .iter()
            .map(|&k| Picking {
                below: 0.0,
                seen: 0,
                u: Hash::new(k ^ self.seed as u64).f32(),
            })
            .collect();
        let [numbers, weights, landings] = files;
        let (mut nr, mut wr, mut lr) = (
            BufReader::new(&mut *numbers),
            BufReader::new(&mut *weights),
            BufReader::new(&mut *landings),
        );
        let mut cells = vec![0u32; COPY_BATCH];
        let mut w = vec![[f16::ZERO; 3]; COPY_BATCH];
        let mut l = vec![GatherPoint::default(); COPY_BATCH];
        let mut left = coefs as usize;
        while left > 0 {
            let n = left.min(COPY_BATCH);
            let read = |r: &mut dyn Read, b: &mut [u8]| {
                r.read_exact(b).context("reading a scratch file back")
            };
            read(&mut nr, bytemuck::cast_slice_mut(&mut cells[..n]))?;
            read(&mut wr, bytemuck::cast_slice_mut(&mut w[..n]))?;
            read(&mut lr, bytemuck::cast_slice_mut(&mut l[..n]))?;
            for i in 0..n {
                let c = cells[i] as usize;
                if let Some(j) = c
                    .checked_sub(self.cells.start)
                    .filter(|_| c < self.cells.end)
                {
                    self.pick(
                        j,
                        (half_luminance(w[i]), &l[i]),
                        &mut state[j],
                        &mut points[j],
                    );
                }
            }
            left -= n;
        }
        for f in [numbers, weights, landings] {
            f.rewind()?;
        }
        Ok(points)
    }

    /// Cell `j`'s next landing (its weight's luminance, the point): picked as often as
    /// the cell's picks fall in its weight, every pick left taken at the cell's last.
    fn pick(
        &self,
        j: usize,
        (lum, landing): (f32, &GatherPoint),
        s: &mut Picking,
        points: &mut Vec<GatherPoint>,
    ) {
        let (k, c) = (self.count[j], &self.carried[j]);
        let step = c.lum / k as f32;
        s.below += lum;
        s.seen += 1;
        let last = s.seen == c.coefs;
        while points.len() < k && (last || (s.u + points.len() as f32) * step < s.below) {
            points.push(*landing);
        }
    }
}

/// The rows' coefficients from the scratch files into `out`: their cell numbers, then
/// their weights, each as they are.
fn copy_coefficients(
    numbers: &mut File,
    weights: &mut File,
    coefs: u64,
    out: &mut Writer,
) -> Result<()> {
    for (file, size) in [(numbers, 4), (weights, 6)] {
        let mut r = BufReader::new(file);
        let mut left = coefs as usize * size;
        let mut buf = vec![0u8; COPY_BATCH * size];
        while left > 0 {
            let n = left.min(buf.len());
            r.read_exact(&mut buf[..n])
                .context("reading a scratch file back")?;
            out.put(&buf[..n])?;
            left -= n;
        }
        out.end()?;
    }
    Ok(())
}

/// Pixel (x, y)'s view samples, compressed transfer row, lamps seen (straight, or after
/// perfectly smooth bounces from its surfaces) and the environment met after such bounces.
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
    let mut skies: Vec<Sky> = Vec::new();
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
        let mut smooth = |met| match met {
            transfer::Met::Lamp(material, l) => *lamps.entry(material).or_insert(V::ZERO) += l,
            transfer::Met::Sky(d, w) => skies.push(Sky {
                d: d.into(),
                w: w.into(),
            }),
        };
        for m in 0..o.paths {
            let ps = PixelSampler::new(o.seed ^ 0x5EED, index, s * o.paths + m);
            let to = (&mut row, &mut smooth);
            transfer::follow(scene, tr, &sp, beta, &ps, (keys, weight), to);
        }
    }
    let mut emits: Vec<(u32, V)> = lamps.into_iter().collect();
    emits.sort_unstable_by_key(|e| e.0);
    let mut u = Hash::new(index as u64 ^ (o.seed as u64) << 32);
    PixelPart {
        views,
        row: transfer::compress(&row, o.coefficients, u.f32()),
        emits,
        skies: fewer_skies(skies, MAX_SKIES, u.f32()),
    }
}

/// At most `n` of a pixel's `skies`, by systematic sampling on their weights
/// (`transfer::systematic`, `u` uniform): unbiased, as `transfer::compress` is.
fn fewer_skies(skies: Vec<Sky>, n: usize, u: f32) -> Vec<Sky> {
    if skies.len() <= n {
        return skies;
    }
    let weights: Vec<V> = skies.iter().map(|s| V::from(s.w)).collect();
    transfer::systematic(&weights, n, u)
        .into_iter()
        .map(|(i, w)| Sky {
            d: skies[i].d,
            w: w.into(),
        })
        .collect()
}
