//! `canopy bake`: the light every node reflects, into a bake file beside the
//! archive (`format/FORMAT.md`, "The bake file") that `render --integrator pbgi
//! --bake-in` pages in with the nodes.

use super::defaults::{chosen_environment, light_the_scene};
use super::setup::{open_scene, Budget};
use crate::camera::Camera;
use crate::integrator::pbgi::bake::{bake_file, BakeSettings};
use crate::light::Environment;
use crate::progress::peak_rss_bytes;
use anyhow::{Context, Result};
use canopy_format::Archive;
use std::fmt;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

pub struct BakeOptions {
    pub archive: PathBuf,
    pub output: PathBuf,
    pub bake: BakeSettings,
    pub seed: u32,
    pub mem_budget: Option<u64>,
    pub threads: Option<usize>,
    /// The environment map lighting the scene (`render --env`).
    pub env: Option<super::EnvOptions>,
    pub progress: bool,
}

#[derive(Clone, Debug, serde::Serialize)]
pub struct BakeReport {
    pub nodes: u64,
    pub pages: u64,
    pub triangles: u64,
    pub light_samples: u64,
    pub seconds: f64,
    pub file_bytes: u64,
    /// Baked blocks decoded (node records and patch pyramids), what the render pages in.
    pub decoded_bytes: u64,
    pub pages_loaded: u64,
    pub pages_evicted: u64,
    pub peak_rss_bytes: u64,
}

impl fmt::Display for BakeReport {
    fn fmt(&self, f: &mut fmt::Formatter) -> fmt::Result {
        write!(
            f,
            "{} nodes in {} pages baked ({} triangles, {} light samples) in {:.2} s; {:.1} MiB on disk, {:.1} MiB decoded; {} pages loaded, {} evicted; peak RSS {:.1} MiB",
            self.nodes,
            self.pages,
            self.triangles,
            self.light_samples,
            self.seconds,
            self.file_bytes as f64 / 1048576.0,
            self.decoded_bytes as f64 / 1048576.0,
            self.pages_loaded,
            self.pages_evicted,
            self.peak_rss_bytes as f64 / 1048576.0
        )
    }
}

pub fn bake(o: &BakeOptions) -> Result<BakeReport> {
    let t0 = Instant::now();
    super::setup::not_over(&o.output, (&o.archive, "the archive"))?;
    let archive = Arc::new(Archive::open(&o.archive)?);
    let threads = o.threads.unwrap_or_else(rayon::current_num_threads).max(1);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .context("starting worker threads")?;
    // The bake shoots no camera rays; the scene still wants a camera.
    let camera = Camera::new(&bytemuck::Zeroable::zeroed(), 1, 1);
    let (env, note) = chosen_environment(o.env.as_ref(), &archive, o.mem_budget)?;
    if let Some(note) = note {
        eprintln!("note: {note}");
    }
    let aside = env.as_ref().map_or(0, Environment::bytes);
    let mut scene = open_scene(
        Arc::clone(&archive),
        camera,
        o.mem_budget.map(|total| Budget {
            total,
            aside,
            lent: 0,
        }),
        threads,
        None,
    )?;
    let lights = std::mem::take(&mut scene.lights);
    let (lights, note) = light_the_scene(&o.archive, env, lights);
    scene.lights = lights;
    if let Some(note) = note {
        eprintln!("note: {note}");
    }
    let bar = crate::progress::bar(
        o.progress,
        archive.page_count() as u64 * o.bake.bounces.map_or(2, |n| n.min(2)) as u64,
        "baking pages",
    );
    let (samples, decoded_bytes) =
        pool.install(|| bake_file(&scene, &o.bake.params(o.seed), &o.output, &|n| bar.inc(n)))?;
    bar.finish_and_clear();
    let file_bytes = std::fs::metadata(&o.output)
        .with_context(|| format!("{}: cannot read back", o.output.display()))?
        .len();
    Ok(BakeReport {
        nodes: archive.header.nodes,
        pages: archive.page_count() as u64,
        triangles: archive.header.triangles,
        light_samples: samples,
        seconds: t0.elapsed().as_secs_f64(),
        file_bytes,
        decoded_bytes,
        pages_loaded: scene.cache.stats().pages_loaded,
        pages_evicted: scene.cache.stats().pages_evicted,
        peak_rss_bytes: peak_rss_bytes(),
    })
}
