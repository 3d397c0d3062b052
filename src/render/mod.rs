//! `canopy render`: an archive to an image under a memory budget. A short driver: passes of
//! samples over tiles, each sample asked of the integrator (`integrator::Integrator`), which
//! it knows only through that trait.

pub mod assemble;
pub mod bake;
mod film;
mod setup;
mod stats;

pub use setup::MAX_SIDE;
pub use stats::{Checkpoint, RenderStats, Seconds};

use crate::progress::peak_rss_bytes;
use crate::texture::TextureFilter;
use film::{Film, Sums};
use setup::Setup;
use stats::ancestors_closure;

use crate::image::{Frame, Image};
use crate::integrator::{self, Counters, Integrator, Pass, PixelSample, Scene, Target};
use crate::progress;
use crate::sampler::PixelSampler;
use crate::trace::Tracer;
use anyhow::{bail, Result};
use rayon::prelude::*;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::time::{Duration, Instant};

#[derive(Clone, Debug)]
pub struct RenderOptions {
    pub archive: PathBuf,
    pub output: PathBuf,
    pub integrator: integrator::Settings,
    pub spp: u32,
    /// Render passes until this much time is spent instead of `spp`.
    pub time: Option<Duration>,
    /// Without `time`: stop at the first power-of-two spp whose relative noise
    /// (`Film::noise`) is at most this, `spp` the most; each power of two is recorded in
    /// the stats' `growth`.
    pub noise: Option<f64>,
    pub mem_budget: Option<u64>,
    pub width: Option<u32>,
    pub height: Option<u32>,
    pub camera: Option<String>,
    pub seed: u32,
    pub threads: Option<usize>,
    pub max_depth: Option<u32>,
    pub texture_filter: TextureFilter,
    /// x0, x1, y0, y1 in pixels (half-open).
    pub crop: Option<[u32; 4]>,
    pub preview: bool,
    pub exposure: f32,
    pub stats: Option<PathBuf>,
    /// Count the nodes the render used (`ancestors_closure`), which re-reads every page
    /// it touched; the noise checkpoints always count.
    pub node_stats: bool,
    pub progress: bool,
}

/// Work counted across threads.
#[derive(Default)]
struct Tally {
    rays: AtomicU64,
    paths: AtomicU64,
    nonfinite: AtomicU64,
}

/// How a render went: samples per pixel, time, work.
struct Run {
    done: u32,
    seconds: Seconds,
    tally: Tally,
    growth: Vec<Checkpoint>,
}

pub fn render(o: &RenderOptions) -> Result<(Image, RenderStats)> {
    let t0 = Instant::now();
    let s = Setup::new(o)?;
    let (scene, pool) = (&s.scene, &s.pool);
    let prefetcher = scene.cache.start_prefetch();
    let mut film = Film::new(s.window);
    let target = Target {
        seed: o.seed,
        pixels: s.width as u64 * s.height as u64,
        window: s.window,
        state_bytes: s.state_bytes,
    };
    let mut integ = o.integrator.build(scene, &target)?;
    let mut seconds = Seconds {
        setup: t0.elapsed().as_secs_f64(),
        ..Default::default()
    };

    let t1 = Instant::now();
    let tally = Tally::default();
    let bar = match o.time {
        Some(t) => progress::bar(o.progress, t.as_secs().max(1), "rendering (s)"),
        None => progress::bar(
            o.progress,
            film.tiles.len() as u64 * o.spp as u64,
            "rendering",
        ),
    };
    let mut done = 0u32;
    let mut growth = Vec::new();
    loop {
        let count = match (o.time, o.noise) {
            // Passes of one sample when the time decides.
            (Some(_), _) => 1,
            // Passes that end on powers of two, where the noise is measured.
            (None, Some(_)) => integ
                .pass_samples(o.spp - done)
                .min(done.max(1))
                .min(o.spp - done),
            (None, None) => integ.pass_samples(o.spp),
        };
        let so_far = tally.rays.load(Relaxed);
        let pass = Pass {
            first: done,
            count,
            rays: so_far,
            variance: film.sample_variance(done),
            left: o.time.map(|limit| limit.saturating_sub(t1.elapsed())),
        };
        let rays = pool.install(|| integ.begin_pass(scene, &pass))?;
        tally.rays.fetch_add(rays, Relaxed);
        // Timed after begin_pass: a bake there is paid once, not by every pass.
        let pass_start = Instant::now();
        let integ_ref: &dyn Integrator = integ.as_ref();
        let sums: Vec<Vec<Sums>> = pool.install(|| {
            film.tiles
                .par_iter()
                .map(|t| {
                    let out =
                        render_tile(scene, integ_ref, &film, *t, [done, count], o.seed, &tally);
                    if o.time.is_none() {
                        bar.inc(count as u64);
                    }
                    out
                })
                .collect()
        });
        for (i, v) in sums.iter().enumerate() {
            film.add(film.tiles[i], v);
        }
        done += count;
        if let Some(err) = scene.cache.error() {
            bail!("{err}");
        }
        pool.install(|| integ.end_pass(scene, done));
        let spent = t1.elapsed();
        let finished = match (o.time, o.noise) {
            // Stop when the next pass would overrun the budget.
            (Some(limit), _) => {
                bar.set_position(spent.as_secs());
                spent + pass_start.elapsed() > limit || done >= u32::MAX - 1
            }
            (None, Some(target)) if done.is_power_of_two() || done >= o.spp => {
                let c = Checkpoint {
                    spp: done,
                    noise: film.noise(done),
                    unique_nodes: ancestors_closure(scene)?,
                    seconds: spent.as_secs_f64(),
                };
                growth.push(c);
                c.noise <= target || done >= o.spp
            }
            (None, _) => done >= o.spp,
        };
        if finished {
            break;
        }
    }
    bar.finish_and_clear();
    for (at, l) in integ.held_back() {
        film.add_held_back(at, l.into());
    }
    integ.finish(scene)?;
    seconds.render = t1.elapsed().as_secs_f64();
    seconds.parts.extend(integ.seconds());
    drop(prefetcher);

    let img = film.image(done);
    let t2 = Instant::now();
    let frame = Frame {
        display: [s.width, s.height],
        origin: [s.window[0], s.window[2]],
        tags: identity(o, &s),
    };
    img.write_exr_framed(&s.exr, &frame)?;
    if let Some(p) = &s.png {
        img.write_png(p, o.exposure)?;
    }
    seconds.write = t2.elapsed().as_secs_f64();
    seconds.total = t0.elapsed().as_secs_f64();
    let run = Run {
        done,
        seconds,
        tally,
        growth,
    };
    let stats = summarize(o, &s, integ.as_ref(), &film, &img, run)?;
    if let Some(p) = &o.stats {
        let json = serde_json::to_string_pretty(&stats)?;
        crate::image::write_atomically(p, |tmp| Ok(std::fs::write(tmp, json)?))?;
    }
    Ok((img, stats))
}

/// The archive's identity: its header checksum (which covers its tables checksum, size
/// and counts), in hex.
fn archive_checksum(scene: &Scene) -> String {
    format!("{:016x}", scene.cache.archive.header.header_checksum)
}

/// The settings that decide a pixel's value (not threads, budget or exposure), as text:
/// tiles of one frame must agree on it.
fn settings_text(o: &RenderOptions, s: &Setup) -> String {
    format!(
        "{:?} spp={} time={:?} noise={:?} max_depth={:?} textures={:?} camera={:?} size={}x{}",
        o.integrator,
        o.spp,
        o.time,
        o.noise,
        o.max_depth,
        o.texture_filter,
        o.camera,
        s.width,
        s.height
    )
}

/// The EXR attributes naming what made an image (`RenderStats` carries the same).
fn identity(o: &RenderOptions, s: &Setup) -> Vec<(String, String)> {
    vec![
        ("canopy.archive".into(), archive_checksum(&s.scene)),
        ("canopy.seed".into(), o.seed.to_string()),
        ("canopy.settings".into(), settings_text(o, s)),
    ]
}

/// Renders samples `first..first + count` of a tile's pixels; returns their sums.
fn render_tile(
    scene: &Scene,
    integ: &dyn Integrator,
    film: &Film,
    t: [u32; 4],
    [first, count]: [u32; 2],
    seed: u32,
    tally: &Tally,
) -> Vec<Sums> {
    let mut c = Counters::default();
    let mut tr = Tracer::new(&scene.cache);
    let cam = &scene.camera;
    let pixels: Vec<(u32, u32)> = (t[2]..t[3])
        .flat_map(|y| (t[0]..t[1]).map(move |x| (y, x)))
        .collect();
    let mut out: Vec<Sums> = vec![[0.0; 4]; pixels.len()];
    let mut batch = Vec::with_capacity(pixels.len());
    for index in first..first + count {
        batch.clear();
        batch.extend(pixels.iter().map(|&(y, x)| {
            let sampler = PixelSampler::new(seed, y * cam.width + x, index);
            let [jx, jy, ..] = sampler.get4(0);
            PixelSample {
                x,
                y,
                at: film.index(x, y),
                index,
                ray: cam.ray(x as f32 + jx, y as f32 + jy),
                sampler,
            }
        }));
        for (sum, l) in out
            .iter_mut()
            .zip(integ.sample_tile(scene, &mut tr, &batch, &mut c))
        {
            let l = [l.x as f64, l.y as f64, l.z as f64];
            for k in 0..3 {
                sum[k] += l[k];
            }
            sum[3] += film::luminance(l).powi(2);
        }
    }
    tally.rays.fetch_add(tr.rays, Relaxed);
    tally.paths.fetch_add(c.paths, Relaxed);
    tally.nonfinite.fetch_add(c.nonfinite, Relaxed);
    scene.cache.add_lookups(tr.page_lookups());
    out
}

fn summarize(
    o: &RenderOptions,
    s: &Setup,
    integ: &dyn Integrator,
    film: &Film,
    img: &Image,
    run: Run,
) -> Result<RenderStats> {
    let Run {
        done,
        seconds,
        tally,
        growth,
    } = run;
    let scene = &s.scene;
    let unique = match o.node_stats || o.noise.is_some() {
        true => Some(ancestors_closure(scene)?),
        false => None,
    };
    let [state, per_pixel] = integ.state_bytes();
    let mut cache = scene.cache.stats();
    cache.resident_bytes_peak += scene.touched.bytes() + state;
    let (rays, paths) = (tally.rays.load(Relaxed), tally.paths.load(Relaxed));
    let render_s = seconds.render.max(1e-9);
    let mut passes = integ.passes();
    if scene.lights.is_empty() {
        passes.push("no light sources: the image is black".into());
    }
    Ok(RenderStats {
        integrator: o.integrator.kind(),
        archive_checksum: archive_checksum(&s.scene),
        settings: settings_text(o, s),
        seed: o.seed,
        spp: done,
        width: s.width,
        height: s.height,
        crop: o.crop,
        threads: s.threads,
        seconds,
        peak_rss_bytes: peak_rss_bytes(),
        mem_budget: o.mem_budget,
        archive_decoded_bytes: scene.cache.archive_decoded_bytes(),
        cache,
        film_bytes: film.bytes() + per_pixel,
        unique_nodes_touched: unique,
        nodes_per_pixel: unique.map(|u| u as f64 / (film.width() as f64 * film.height() as f64)),
        rays,
        paths,
        rays_per_second: rays as f64 / render_s,
        paths_per_second: paths as f64 / render_s,
        emitters: scene.lights.emitters.len() as u64,
        punctual_lights: scene.lights.punctual.len() as u64,
        passes,
        nonfinite_samples: tally.nonfinite.load(Relaxed),
        details: integ.stats(),
        image_mean: img.mean(),
        growth,
    })
}
