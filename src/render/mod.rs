//! `canopy render`: an archive to an image under a memory budget. A short driver: passes of
//! samples over tiles, each sample asked of the integrator (`integrator::Integrator`), which
//! it knows only through that trait.

pub mod assemble;
pub mod bake;
mod defaults;
mod display;
mod film;
mod pixel_split;
mod setup;
mod stats;

pub use defaults::{EnvOptions, EnvSource};
pub use setup::{gather_lights, image_outputs, Setup, MAX_SIDE};
pub use stats::{Checkpoint, RenderStats, Seconds};

use crate::progress::peak_rss_bytes;
use crate::texture::TextureFilter;
use display::Display;
use film::{Film, Sums};
use pixel_split::PixelSplit;
use stats::ancestors_closure;

use crate::image::{Frame, Image};
use crate::integrator::{self, Counters, Integrator, Pass, PixelSample, Scene, Target};
use crate::light::Environment;
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
    /// Render passes until this much time is spent, or `spp` samples are taken.
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
    /// Most camera samples a pass takes of a pixel (None: the integrator's default).
    pub pixel_split: Option<u32>,
    /// An environment map lighting the scene from infinitely far away.
    pub env: Option<EnvOptions>,
    /// A light set (`LightSet`) changing the archive's lights.
    pub lights: Option<PathBuf>,
    /// tev's address (HOST:PORT), to stream the image to as it converges.
    pub display: Option<String>,
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
    /// Camera samples beyond one a pixel and pass (`--pixel-split`).
    further: AtomicU64,
}

/// How a render went: samples per pixel, time, work.
struct Run {
    done: u32,
    split: PixelSplit,
    seconds: Seconds,
    tally: Tally,
    growth: Vec<Checkpoint>,
    /// Why the image is black, when it is.
    black: Option<String>,
}

pub fn render(o: &RenderOptions) -> Result<(Image, RenderStats)> {
    let t0 = Instant::now();
    let s = Setup::new(o)?;
    let (scene, pool) = (&s.scene, &s.pool);
    let prefetcher = scene.cache.start_prefetch();
    let mut film = Film::new(s.window);
    let window_pixels = film.width() as usize * film.height() as usize;
    let mut split = PixelSplit::new(s.pixel_split, o.seed, window_pixels);
    let target = Target {
        seed: o.seed,
        pixels: s.width as u64 * s.height as u64,
        window: s.window,
        state_bytes: s.state_bytes,
        pixel_split: s.pixel_split,
    };
    let mut integ = o.integrator.build(scene, &target)?;
    let origin = [s.window[0], s.window[2]];
    let mut display = o
        .display
        .as_deref()
        .map(|a| Display::connect(a, &o.output.display().to_string(), [s.width, s.height]))
        .transpose()?;
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
        let count = pass_count(o, integ.as_ref(), &split, done);
        let so_far = tally.rays.load(Relaxed);
        let pass = Pass {
            first: done,
            count,
            rays: so_far,
            variance: film.sample_variance(done),
            camera_sample_variance: split.begin_pass(),
            samples: done as u64 * window_pixels as u64 + tally.further.load(Relaxed),
            left: o.time.map(|limit| limit.saturating_sub(t1.elapsed())),
        };
        let rays = pool.install(|| integ.begin_pass(scene, &pass))?;
        tally.rays.fetch_add(rays, Relaxed);
        // Timed after begin_pass: a bake there is paid once, not by every pass.
        let pass_start = Instant::now();
        let tiles = Tiles {
            scene,
            integ: integ.as_ref(),
            film: &film,
            split: &split,
            seed: o.seed,
            samples: done..done + count,
            tally: &tally,
        };
        let sums: Vec<Vec<Sums>> = pool.install(|| {
            film.tiles
                .par_iter()
                .map(|t| {
                    let out = tiles.render(*t);
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
        if let Some(d) = &mut display {
            d.update(|| film.image(done), origin, false);
        }
        if let Some(err) = scene.error() {
            bail!("{err}");
        }
        pool.install(|| integ.end_pass(scene, done));
        let spent = t1.elapsed();
        let finished = match (o.time, o.noise) {
            // Stop when the next pass would overrun the budget.
            (Some(limit), _) => {
                bar.set_position(spent.as_secs());
                spent + pass_start.elapsed() > limit || done >= o.spp
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
    if let Some(d) = &mut display {
        d.update(|| img.clone(), origin, true);
    }
    let t2 = Instant::now();
    let black = black_image(scene, &img);
    write_images(o, &s, &img, black.as_deref())?;
    seconds.write = t2.elapsed().as_secs_f64();
    seconds.total = t0.elapsed().as_secs_f64();
    let run = Run {
        done,
        split,
        seconds,
        tally,
        growth,
        black,
    };
    let stats = summarize(o, &s, integ.as_ref(), &film, &img, run)?;
    if let Some(p) = &o.stats {
        let json = serde_json::to_string_pretty(&stats)?;
        crate::image::write_atomically(p, |tmp| Ok(std::fs::write(tmp, json)?))?;
    }
    Ok((img, stats))
}

/// Samples per pixel the next pass takes, `done` taken so far.
fn pass_count(o: &RenderOptions, integ: &dyn Integrator, split: &PixelSplit, done: u32) -> u32 {
    let count = match (o.time, o.noise) {
        // Passes of one sample when the time decides.
        (Some(_), _) => 1,
        // Passes that end on powers of two, where the noise is measured.
        (None, Some(_)) => integ
            .pass_samples(o.spp - done, done)
            .min(done.max(1))
            .min(o.spp - done),
        (None, None) => integ.pass_samples(o.spp - done, done).min(o.spp - done),
    };
    // The pixel split decides a pass's camera samples from the passes before it.
    match split.most() {
        1 => count,
        _ => count.min(1),
    }
}

/// The EXR (a tile of its frame, tagged with what made it) and the PNG if asked; a black
/// image says `black`, why it is.
fn write_images(o: &RenderOptions, s: &Setup, img: &Image, black: Option<&str>) -> Result<()> {
    if let Some(why) = black {
        eprintln!("warning: {}: {why}", s.exr.display());
    }
    let frame = Frame {
        display: [s.width, s.height],
        origin: [s.window[0], s.window[2]],
        tags: identity(o, s),
    };
    img.write_exr_framed(&s.exr, &frame)?;
    if let Some(p) = &s.png {
        img.write_png(p, o.exposure)?;
    }
    Ok(())
}

/// Why an image is black, when it is (every pixel zero).
fn black_image(scene: &Scene, img: &Image) -> Option<String> {
    if img.pixels.iter().any(|p| p.iter().any(|&c| c != 0.0)) {
        return None;
    }
    let lights = &scene.lights;
    Some(match lights.is_empty() {
        true => "the image is black: the scene has no light source".into(),
        false => format!(
            "the image is black: no light from its {} emitters, {} punctual lights{} reached the camera (are they behind walls, facing away, or cut off by --max-depth?)",
            lights.emitters.len(),
            lights.punctual.len(),
            if lights.env.is_some() { " or the environment" } else { "" }
        ),
    })
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
        "{:?} pixel_split={} env={:?} spp={} time={:?} noise={:?} max_depth={:?} textures={:?} camera={:?} size={}x{}",
        o.integrator,
        s.pixel_split,
        o.env,
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

/// What every tile of a pass needs.
struct Tiles<'a> {
    scene: &'a Scene,
    integ: &'a dyn Integrator,
    film: &'a Film,
    split: &'a PixelSplit,
    seed: u32,
    /// The pass's samples of each pixel.
    samples: std::ops::Range<u32>,
    tally: &'a Tally,
}

impl Tiles<'_> {
    /// Renders the pass's samples of a tile's pixels; returns their sums.
    fn render(&self, t: [u32; 4]) -> Vec<Sums> {
        let mut c = Counters::default();
        let mut tr = Tracer::new(&self.scene.cache);
        let pixels: Vec<(u32, u32)> = (t[2]..t[3])
            .flat_map(|y| (t[0]..t[1]).map(move |x| (y, x)))
            .collect();
        let mut out: Vec<Sums> = vec![[0.0; 4]; pixels.len()];
        let mut batch = Vec::with_capacity(pixels.len());
        for index in self.samples.clone() {
            let ls = match self.split.most() {
                1 => {
                    batch.clear();
                    batch.extend(pixels.iter().map(|&(y, x)| self.sample(x, y, index, 1)));
                    self.integ.sample_tile(self.scene, &mut tr, &batch, &mut c)
                }
                _ => pixels
                    .iter()
                    .map(|&(y, x)| self.split_pixel(&mut tr, x, y, index, &mut c))
                    .collect(),
            };
            for (sum, l) in out.iter_mut().zip(ls) {
                let l = [l.x as f64, l.y as f64, l.z as f64];
                for k in 0..3 {
                    sum[k] += l[k];
                }
                sum[3] += film::luminance(l).powi(2);
            }
        }
        self.tally.rays.fetch_add(tr.rays, Relaxed);
        self.tally.paths.fetch_add(c.paths, Relaxed);
        self.tally.nonfinite.fetch_add(c.nonfinite, Relaxed);
        self.scene.cache.add_lookups(tr.page_lookups());
        out
    }

    /// Pixel (x, y)'s pass sample `index`, one of `m` camera samples the pass takes of it.
    fn sample(&self, x: u32, y: u32, index: u32, m: u32) -> PixelSample {
        let pixel = y * self.scene.camera.width + x;
        let sampler = PixelSampler::new(self.seed, pixel, index);
        self.camera_sample([x, y], index, sampler, 1.0 / m as f32, None)
    }

    /// A camera sample of pixel (x, y) through the position `sampler` draws in it.
    fn camera_sample(
        &self,
        [x, y]: [u32; 2],
        index: u32,
        sampler: PixelSampler,
        share: f32,
        further: Option<u32>,
    ) -> PixelSample {
        let [jx, jy, ..] = sampler.get4(0);
        PixelSample {
            x,
            y,
            at: self.film.index(x, y),
            index,
            ray: self.scene.camera.ray(x as f32 + jx, y as f32 + jy),
            sampler,
            share,
            further,
        }
    }

    /// The mean of pixel (x, y)'s pass sample and the further ones its earlier samples'
    /// spread asks for (`PixelSplit::count`), each noted for the pixel's spread.
    fn split_pixel(
        &self,
        tr: &mut Tracer,
        x: u32,
        y: u32,
        index: u32,
        c: &mut Counters,
    ) -> glam::Vec3A {
        let m = self.split.count(self.film.index(x, y));
        let px = self.sample(x, y, index, m);
        let (at, share) = (px.at, px.share);
        let further = self
            .split
            .further(at, y * self.scene.camera.width + x, m - 1);
        let pxs: Vec<PixelSample> = std::iter::once(px)
            .chain(
                further
                    .into_iter()
                    .map(|(i, sampler)| self.camera_sample([x, y], index, sampler, share, Some(i))),
            )
            .collect();
        self.tally.further.fetch_add(pxs.len() as u64 - 1, Relaxed);
        let rays = tr.rays;
        let ls = self.integ.sample_pixel(self.scene, tr, &pxs, c);
        self.split.note(at, &ls, tr.rays - rays);
        ls.iter().fold(glam::Vec3A::ZERO, |sum, &l| sum + l * share)
    }
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
        split,
        seconds,
        tally,
        growth,
        black,
    } = run;
    let scene = &s.scene;
    let unique = match o.node_stats || o.noise.is_some() {
        true => Some(ancestors_closure(scene)?),
        false => None,
    };
    // State taken back from the page cache's budget counts in its resident bytes.
    let state = integ.state_bytes().saturating_sub(scene.cache.charged());
    let mut cache = scene.cache.stats();
    let environment = scene.lights.env.as_ref().map(Environment::stats);
    let env = environment.map_or(0, |e| e.env_bytes_peak);
    cache.resident_bytes_peak += scene.touched.bytes() + state + env;
    let (rays, paths) = (tally.rays.load(Relaxed), tally.paths.load(Relaxed));
    let render_s = seconds.render.max(1e-9);
    let further = tally.further.load(Relaxed);
    let mut passes = s.notes.clone();
    passes.push(split.describe(further));
    passes.extend(integ.passes());
    if let Some(env) = &scene.lights.env {
        passes.push(format!("environment: {}", env.name));
    }
    passes.extend(black);
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
        environment,
        film_bytes: film.bytes() + split.bytes(),
        unique_nodes_touched: unique,
        nodes_per_pixel: unique.map(|u| u as f64 / (film.width() as f64 * film.height() as f64)),
        rays,
        paths,
        further_samples: further,
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
