//! `canopy render`: an archive to an image under a memory budget.

use crate::camera::Camera;
use crate::image::{check_writable, same_file, Image};
use crate::integrator::cone::{self, light_pass};
use crate::integrator::{path, Counters, NodeSet, Scene};
use crate::light::Lights;
use crate::material::Material;
use crate::paging::{Page, PageCache, CHILD_PAGE, INNER, KIND_MASK};
use crate::progress;
use crate::radiance::RadianceStore;
use crate::sampler::PixelSampler;
use crate::trace::{Cone, Tracer, MAX_DEPTH};
use anyhow::{bail, Context, Result};
use canopy_format::Archive;
use glam::Vec3A as V;
use rayon::prelude::*;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Largest image side accepted.
pub const MAX_SIDE: u32 = 32768;
const TILE: u32 = 16;

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Integrator {
    /// Exact path tracing of the leaf triangles: the ground truth.
    Path,
    /// Cone casts that stop at the level of detail the cone resolves, with diffuse light
    /// stored per node and reused (004 §4.5–4.8).
    Cone,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum LightPass {
    /// When the scene has lights and smooth mirror or glass surfaces.
    Auto,
    On,
    Off,
}

#[derive(Clone, Debug)]
pub struct RenderOptions {
    pub archive: PathBuf,
    pub output: PathBuf,
    pub integrator: Integrator,
    pub spp: u32,
    pub time: Option<Duration>,
    pub mem_budget: Option<u64>,
    pub width: Option<u32>,
    pub height: Option<u32>,
    pub camera: Option<String>,
    pub seed: u32,
    pub threads: Option<usize>,
    pub max_depth: Option<u32>,
    /// x0, x1, y0, y1 in pixels (half-open).
    pub crop: Option<[u32; 4]>,
    pub preview: bool,
    pub exposure: f32,
    pub stats: Option<PathBuf>,
    pub progress: bool,
    /// Cone integrator: multiplier of the cone radius in the LOD rule (0: exact rays).
    pub cone_scale: f32,
    /// Cone integrator: tan α′ of cones after diffuse bounces (004 eq. 4.20's d).
    pub diffuse_tan: f32,
    /// Cone integrator: samples after which a node's stored light counts as converged.
    pub cone_samples: u32,
    /// Cone integrator: the caustic light pass (004 §4.7).
    pub light_pass: LightPass,
    /// Photons per light pass (None: one per pixel).
    pub photons: Option<u32>,
    /// Cone integrator: rays per sample that average the emission seen directly on pixels
    /// straddling an emitter's silhouette (0: the sample's own ray only).
    pub edge_rays: u32,
}

#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct Seconds {
    pub setup: f64,
    pub render: f64,
    /// Of `render`: pulling stored light up the tree between passes (cone integrator).
    pub pull: f64,
    /// Of `render`: light passes (cone integrator, scenes with caustics).
    pub light: f64,
    pub write: f64,
    pub total: f64,
}

#[derive(Clone, Debug, serde::Serialize)]
pub struct RenderStats {
    pub integrator: Integrator,
    pub spp: u32,
    pub width: u32,
    pub height: u32,
    pub crop: Option<[u32; 4]>,
    pub threads: usize,
    pub seconds: Seconds,
    pub peak_rss_bytes: u64,
    pub mem_budget: Option<u64>,
    pub archive_decoded_bytes: u64,
    pub resident_bytes_peak: u64,
    pub pinned_bytes: u64,
    pub film_bytes: u64,
    pub pages_loaded: u64,
    pub pages_evicted: u64,
    pub pages_touched: u64,
    pub cache_hits: u64,
    pub cache_misses: u64,
    pub cache_hit_rate: f64,
    pub bytes_decoded: u64,
    pub unique_nodes_touched: u64,
    pub nodes_per_pixel: f64,
    pub rays: u64,
    pub paths: u64,
    pub rays_per_second: f64,
    pub paths_per_second: f64,
    pub emitters: u64,
    pub punctual_lights: u64,
    /// Which passes ran and why (the scene's features decide).
    pub passes: Vec<String>,
    pub cone_scale: Option<f32>,
    pub stored_nodes: u64,
    pub stored_bytes: u64,
    pub converged_nodes: u64,
    /// Samples of nodes the store had no room for (the budget's quarter was full).
    pub store_refused_samples: u64,
    /// Photons the light passes emitted, and how many left caustic light.
    pub photons: u64,
    pub caustic_deposits: u64,
    /// Pixels at an emitter's silhouette: samples of the pixel or its neighbours both saw
    /// an emitter and missed it (cone integrator: these take `--edge-rays`).
    pub edge_pixels: u64,
    /// Samples whose radiance was NaN or infinite (added as zero); 0 in a correct render.
    pub nonfinite_samples: u64,
    pub image_mean: [f64; 3],
}

/// Peak resident set of this process (VmHWM), 0 where /proc is unavailable.
pub fn peak_rss_bytes() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1)?.parse::<u64>().ok())
        })
        .map_or(0, |kb| kb * 1024)
}

/// Where the EXR and (if asked) the PNG go: `-o x.png` writes x.png and x.exr beside it.
fn outputs(o: &RenderOptions) -> Result<(PathBuf, Option<PathBuf>)> {
    let ext = o
        .output
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase);
    match ext.as_deref() {
        Some("exr") => Ok((
            o.output.clone(),
            o.preview.then(|| o.output.with_extension("png")),
        )),
        Some("png") => Ok((o.output.with_extension("exr"), Some(o.output.clone()))),
        _ => bail!("{}: output must end in .exr or .png", o.output.display()),
    }
}

pub fn render(o: &RenderOptions) -> Result<(Image, RenderStats)> {
    let t0 = Instant::now();
    let (exr_path, png_path) = outputs(o)?;
    for out in std::iter::once(&exr_path).chain(&png_path).chain(&o.stats) {
        if same_file(out, &o.archive) {
            bail!(
                "{}: writing there would overwrite the archive",
                out.display()
            );
        }
        check_writable(out)?;
    }
    if o.spp == 0 && o.time.is_none() {
        bail!("--spp must be at least 1");
    }
    for (flag, v) in [
        ("--cone-scale", o.cone_scale),
        ("--diffuse-tan", o.diffuse_tan),
        ("--exposure", o.exposure),
    ] {
        if !(v.is_finite() && v >= 0.0) {
            bail!("{flag} must be a finite number of at least 0, not {v}");
        }
    }
    if let Some(t) = o
        .threads
        .filter(|&t| t == 0 || t > crate::units::max_threads())
    {
        bail!(
            "--threads {t}: give 1 to {} ({} per core)",
            crate::units::max_threads(),
            crate::units::THREADS_PER_CORE
        );
    }
    let archive = Arc::new(Archive::open(&o.archive)?);
    if archive.header.depth as usize > MAX_DEPTH {
        bail!(
            "{}: tree depth {} exceeds the {} this renderer traverses",
            o.archive.display(),
            archive.header.depth,
            MAX_DEPTH
        );
    }
    let cam_rec = match &o.camera {
        Some(name) => archive
            .cameras
            .iter()
            .find(|c| canopy_format::name_str(&c.name) == *name)
            .with_context(|| {
                let names: Vec<_> = archive
                    .cameras
                    .iter()
                    .map(|c| canopy_format::name_str(&c.name).to_string())
                    .collect();
                format!(
                    "{}: no camera named {name:?} (cameras: {})",
                    o.archive.display(),
                    if names.is_empty() {
                        "none".into()
                    } else {
                        names.join(", ")
                    }
                )
            })?,
        None => archive.cameras.first().with_context(|| {
            format!(
                "{}: the archive has no camera; convert with a glTF camera or --scene",
                o.archive.display()
            )
        })?,
    };
    let (width, height) = resolution(o, cam_rec)?;
    let crop = match o.crop {
        Some([x0, x1, y0, y1]) => {
            if x0 >= x1 || y0 >= y1 || x1 > width || y1 > height {
                bail!(
                    "--crop {x0},{x1},{y0},{y1} is not a non-empty window inside {width}x{height}"
                );
            }
            [x0, x1, y0, y1]
        }
        None => [0, width, 0, height],
    };
    let threads = o.threads.unwrap_or_else(rayon::current_num_threads).max(1);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .context("starting worker threads")?;
    let touched = NodeSet::new(archive.header.nodes);
    // The cone integrator's stored light gets a quarter of the budget; pages the rest.
    let store_share = match (o.mem_budget, o.integrator) {
        (Some(b), Integrator::Cone) => Some(b / 4),
        (Some(_), Integrator::Path) => Some(0),
        (None, _) => None,
    };
    let budget = match o.mem_budget {
        Some(b) => Some(
            b.checked_sub(touched.bytes() + store_share.unwrap_or(0))
                .with_context(|| {
                    format!("--mem-budget {b} cannot even hold the node statistics")
                })?,
        ),
        None => None,
    };
    let cache = PageCache::new(Arc::clone(&archive), budget, threads)?;
    let prefetcher = cache.start_prefetch();
    let materials: Vec<Material> = archive
        .materials
        .iter()
        .map(Material::from_record)
        .collect();
    let (lo, hi) = (
        V::from(archive.header.bounds_min),
        V::from(archive.header.bounds_max),
    );
    let lights = Lights::gather(&archive, &materials, 0.5 * (hi - lo).length())?;
    // The caustic light pass (cone integrator): decided once, and the stats say why.
    let smooth = materials.iter().any(Material::has_delta_lobe);
    let light_pass = o.integrator == Integrator::Cone
        && !lights.is_empty()
        && match o.light_pass {
            LightPass::Off => false,
            LightPass::On => true,
            LightPass::Auto => smooth,
        };
    let mut passes = match o.integrator {
        Integrator::Path => vec!["path: eye paths with next-event estimation and MIS".to_string()],
        Integrator::Cone => vec![
            format!("cone: eye pass, cone scale {}, diffuse cones tan {}, diffuse light stored per node (converged at {} samples)", o.cone_scale, o.diffuse_tan, o.cone_samples),
            "pull after every eye pass".to_string(),
            if light_pass {
                "light pass: photons through smooth mirrors and glass leave caustics on diffuse surfaces (L S S* D); the eye pass masks those paths; pulled after each pass".into()
            } else if o.light_pass == LightPass::Off {
                "light pass: off (--light-pass off); caustics come from the eye pass".into()
            } else if !smooth && o.light_pass == LightPass::Auto {
                "light pass: skipped, no smooth mirror or glass surfaces".into()
            } else {
                "light pass: skipped, no lights".into()
            },
        ],
    };
    if lights.is_empty() {
        passes.push("no light sources: the image is black".into());
    }
    let scene = Scene {
        cache: Arc::clone(&cache),
        materials,
        camera: Camera::new(cam_rec, width, height),
        lights,
        max_depth: o.max_depth,
        touched,
        dirty: (0..archive.pages.len())
            .map(|_| Default::default())
            .collect(),
    };
    let store = RadianceStore::new(o.cone_samples, store_share);
    // Photons light the whole scene whatever the crop: one per pixel of the full image.
    let photons = o.photons.unwrap_or((width * height).max(1));
    let mut deposits = 0u64;
    let mut light_s = 0.0;
    let setup = t0.elapsed().as_secs_f64();

    let t1 = Instant::now();
    let (cw, ch) = (crop[1] - crop[0], crop[3] - crop[2]);
    let tiles: Vec<[u32; 4]> = (0..ch.div_ceil(TILE))
        .flat_map(|ty| (0..cw.div_ceil(TILE)).map(move |tx| [tx, ty, 0, 0]))
        .map(|[tx, ty, ..]| {
            let x0 = crop[0] + tx * TILE;
            let y0 = crop[2] + ty * TILE;
            [x0, (x0 + TILE).min(crop[1]), y0, (y0 + TILE).min(crop[3])]
        })
        .collect();
    let mut sums = vec![[0f64; 3]; (cw * ch) as usize];
    // Per pixel: primary samples that saw emission and that did not.
    let mut seen = vec![[0u32; 2]; (cw * ch) as usize];
    let rays = AtomicU64::new(0);
    let paths = AtomicU64::new(0);
    let nonfinite = AtomicU64::new(0);
    let mut done = 0u32;
    let mut pull_s = 0.0;
    let bar = match o.time {
        Some(t) => progress::bar(o.progress, t.as_secs().max(1), "rendering (s)"),
        None => progress::bar(o.progress, tiles.len() as u64 * o.spp as u64, "rendering"),
    };
    loop {
        // With a time budget, passes of one sample each until the next would overrun it.
        // Passes of one sample when the time decides, and for the cone integrator, whose
        // store is pulled between passes.
        let count = match (o.time, o.integrator) {
            (None, Integrator::Path) => o.spp,
            (None, Integrator::Cone) => 1,
            (Some(_), _) => 1,
        };
        let pass_start = Instant::now();
        store.begin_pass(done + count);
        if light_pass {
            let lp = pool.install(|| light_pass::light_pass(&scene, &store, photons, done, o.seed));
            rays.fetch_add(lp.rays, Relaxed);
            deposits += lp.deposits;
            light_s += pass_start.elapsed().as_secs_f64();
        }
        let edge = if o.integrator == Integrator::Cone && o.edge_rays > 0 {
            edge_mask(&seen, cw)
        } else {
            Vec::new()
        };
        let results: Vec<Vec<([f64; 3], [u32; 2])>> = pool.install(|| {
            tiles
                .par_iter()
                .map(|t| {
                    let mut c = Counters::default();
                    let mut tr = Tracer::new(&scene.cache);
                    let px = Pixels {
                        t: *t,
                        first: done,
                        count,
                        edge: &edge,
                        origin: [crop[0], crop[2]],
                        stride: cw,
                    };
                    let out = render_tile(&scene, &store, &mut tr, px, o, &mut c);
                    rays.fetch_add(tr.rays, Relaxed);
                    paths.fetch_add(c.paths, Relaxed);
                    nonfinite.fetch_add(c.nonfinite, Relaxed);
                    scene.cache.add_lookups(tr.page_lookups);
                    if o.time.is_none() {
                        bar.inc(count as u64);
                    }
                    out
                })
                .collect()
        });
        for (t, px) in tiles.iter().zip(results) {
            let w = t[1] - t[0];
            for (i, (v, n)) in px.into_iter().enumerate() {
                let (x, y) = (t[0] + i as u32 % w - crop[0], t[2] + i as u32 / w - crop[2]);
                let at = (y * cw + x) as usize;
                for k in 0..3 {
                    sums[at][k] += v[k];
                }
                for k in 0..2 {
                    seen[at][k] = seen[at][k].saturating_add(n[k]);
                }
            }
        }
        done += count;
        if let Some(err) = cache.error() {
            bail!("{err}");
        }
        // Pull after passes 1, 2, 4, 8 and then every 8th: a pull walks every resident
        // page, which on a big scene costs more than a small pass.
        if o.integrator == Integrator::Cone && (done.is_power_of_two() || done.is_multiple_of(8)) {
            let t = Instant::now();
            pool.install(|| cone::pull(&scene, &store));
            pull_s += t.elapsed().as_secs_f64();
        }

        match o.time {
            None if done < o.spp => {}
            None => break,
            Some(limit) => {
                bar.set_position(t1.elapsed().as_secs());
                let spent = t1.elapsed();
                if spent + pass_start.elapsed() > limit || done >= u32::MAX - 1 {
                    break;
                }
            }
        }
    }
    bar.finish_and_clear();
    let render_s = t1.elapsed().as_secs_f64();
    let edge_pixels = edge_mask(&seen, cw).iter().filter(|&&e| e).count() as u64;
    if o.integrator == Integrator::Cone {
        passes.push(if o.edge_rays == 0 {
            "edge rays: off (--edge-rays 0)".into()
        } else {
            format!(
                "edge rays: {} per sample average the emission seen on the {edge_pixels} pixels found at an emitter's silhouette",
                o.edge_rays
            )
        });
    }
    cache.stop_prefetch();
    prefetcher.join().ok();

    let mut img = Image::new(cw, ch);
    for (p, s) in img.pixels.iter_mut().zip(&sums) {
        *p = s.map(|v| (v / done as f64) as f32);
    }
    let t2 = Instant::now();
    img.write_exr(&exr_path)?;
    if let Some(p) = &png_path {
        img.write_png(p, o.exposure)?;
    }
    let write_s = t2.elapsed().as_secs_f64();

    let unique = ancestors_closure(&scene)?;
    let cs = cache.stats();
    let (rays, paths) = (rays.load(Relaxed), paths.load(Relaxed));
    let stats = RenderStats {
        integrator: o.integrator,
        spp: done,
        width,
        height,
        crop: o.crop,
        threads,
        seconds: Seconds {
            setup,
            render: render_s,
            pull: pull_s,
            light: light_s,
            write: write_s,
            total: t0.elapsed().as_secs_f64(),
        },
        peak_rss_bytes: peak_rss_bytes(),
        mem_budget: o.mem_budget,
        archive_decoded_bytes: cache.archive_decoded_bytes(),
        resident_bytes_peak: cs.resident_bytes_peak + scene.touched.bytes() + store.bytes(),
        pinned_bytes: cs.pinned_bytes,
        // Sums, emission tallies and the edge mask per pixel, then the image.
        film_bytes: (sums.len() * (24 + 8 + 1) + img.pixels.len() * 12) as u64,
        pages_loaded: cs.pages_loaded,
        pages_evicted: cs.pages_evicted,
        pages_touched: cs.pages_touched,
        cache_hits: cs.hits,
        cache_misses: cs.misses,
        cache_hit_rate: cs.cache_hit_rate,
        bytes_decoded: cs.bytes_decoded,
        unique_nodes_touched: unique,
        nodes_per_pixel: unique as f64 / (cw as f64 * ch as f64),
        rays,
        paths,
        rays_per_second: rays as f64 / render_s.max(1e-9),
        paths_per_second: paths as f64 / render_s.max(1e-9),
        emitters: scene.lights.emitters.len() as u64,
        punctual_lights: scene.lights.punctual.len() as u64,
        passes,
        cone_scale: (o.integrator == Integrator::Cone).then_some(o.cone_scale),
        stored_nodes: store.len() as u64,
        stored_bytes: store.bytes(),
        converged_nodes: store.converged() as u64,
        store_refused_samples: store.refused(),
        photons: store.photons(),
        caustic_deposits: deposits,
        edge_pixels,
        nonfinite_samples: nonfinite.load(Relaxed),
        image_mean: img.mean(),
    };
    if let Some(p) = &o.stats {
        let json = serde_json::to_string_pretty(&stats)?;
        crate::image::write_atomically(p, |tmp| Ok(std::fs::write(tmp, json)?))?;
    }
    Ok((img, stats))
}

fn resolution(o: &RenderOptions, cam: &canopy_format::CameraRecord) -> Result<(u32, u32)> {
    let (w, h) = match (o.width, o.height) {
        (Some(w), Some(h)) => (w, h),
        (Some(w), None) if cam.width > 0 => {
            (w, (w as u64 * cam.height as u64 / cam.width as u64) as u32)
        }
        (None, Some(h)) if cam.height > 0 => {
            ((h as u64 * cam.width as u64 / cam.height as u64) as u32, h)
        }
        (None, None) if cam.width > 0 && cam.height > 0 => (cam.width, cam.height),
        (w, h) => {
            let aspect = if cam.aspect > 0.0 { cam.aspect } else { 1.0 };
            match (w, h) {
                (Some(w), _) => (w, (w as f32 / aspect).round() as u32),
                (_, Some(h)) => ((h as f32 * aspect).round() as u32, h),
                _ => ((512.0 * aspect).round() as u32, 512),
            }
        }
    };
    if w == 0 || h == 0 || w > MAX_SIDE || h > MAX_SIDE {
        bail!("resolution {w}x{h} is out of range (each side 1..={MAX_SIDE})");
    }
    Ok((w, h))
}

/// A tile's pixels to render in one pass: samples [first, first + count) of each, and
/// which pixels of the crop (`stride` wide, from `origin`) take edge rays.
struct Pixels<'a> {
    t: [u32; 4],
    first: u32,
    count: u32,
    edge: &'a [bool],
    origin: [u32; 2],
    stride: u32,
}

/// Seed offset of the sequences that place a pixel's edge rays.
const EDGE_SEED: u32 = 0x5bd1_e995;

/// Pixels at an emitter's silhouette: among the pixel and its eight neighbours, earlier
/// samples both saw emission and missed it. The neighbours catch a pixel the emitter
/// barely covers before one of its own samples lands on it.
fn edge_mask(seen: &[[u32; 2]], width: u32) -> Vec<bool> {
    let (w, h) = (width as usize, seen.len() / width.max(1) as usize);
    (0..seen.len())
        .map(|i| {
            let (x, y) = (i % w, i / w);
            let mut any = [false; 2];
            for ny in y.saturating_sub(1)..(y + 2).min(h) {
                for nx in x.saturating_sub(1)..(x + 2).min(w) {
                    let n = seen[ny * w + nx];
                    any = [any[0] || n[0] > 0, any[1] || n[1] > 0];
                }
            }
            any[0] && any[1]
        })
        .collect()
}

/// Renders a tile's samples; returns per pixel the sums and the primary samples that saw
/// emission and that did not.
fn render_tile(
    scene: &Scene,
    store: &RadianceStore,
    tr: &mut Tracer,
    px: Pixels,
    o: &RenderOptions,
    c: &mut Counters,
) -> Vec<([f64; 3], [u32; 2])> {
    let t = px.t;
    // Primary cones open by one pixel (004 eq. 4.19).
    let cone = Cone {
        r0: 0.0,
        tan_a: 2.0 * scene.camera.tan_half / scene.camera.height as f32,
        scale: o.cone_scale,
        spread: o.diffuse_tan,
    };
    let mut out = Vec::with_capacity(((t[1] - t[0]) * (t[3] - t[2])) as usize);
    for (y, x) in (t[2]..t[3]).flat_map(|y| (t[0]..t[1]).map(move |x| (y, x))) {
        let pixel = y * scene.camera.width + x;
        let at = (y - px.origin[1]) * px.stride + x - px.origin[0];
        let mut seen = [0u32; 2];
        let mut sum = [0f64; 3];
        for s in px.first..px.first + px.count {
            let smp = PixelSampler::new(o.seed, pixel, s);
            let [jx, jy, ..] = smp.get4(0);
            let ray = scene.camera.ray(x as f32 + jx, y as f32 + jy);
            let l = match o.integrator {
                Integrator::Path => path::radiance(scene, tr, ray, &smp, c),
                Integrator::Cone => {
                    let (rest, own) = cone::radiance(scene, store, tr, ray, cone, &smp, c);
                    // At an emitter's silhouette (found by earlier passes) the emission
                    // seen is averaged over `edge_rays` positions of a denser stratified
                    // sequence: an unbiased estimate of the same pixel integral, each ray
                    // a primary cone without shading.
                    let k = if px.edge.get(at as usize) == Some(&true) {
                        o.edge_rays
                    } else {
                        0
                    };
                    let mut tally = |v: V| {
                        let n = &mut seen[usize::from(v.max_element() <= 0.0)];
                        *n = n.saturating_add(1);
                    };
                    tally(own);
                    let le = if k == 0 {
                        own
                    } else {
                        (0..k).fold(V::ZERO, |acc, j| {
                            let e = PixelSampler::new(
                                o.seed ^ EDGE_SEED,
                                pixel,
                                s.wrapping_mul(k).wrapping_add(j),
                            );
                            let [ex, ey, ..] = e.get4(0);
                            let r = scene.camera.ray(x as f32 + ex, y as f32 + ey);
                            let v = cone::seen_emission(scene, tr, &r, &cone, c);
                            tally(v);
                            acc + v
                        }) / k as f32
                    };
                    rest + le
                }
            };
            for k in 0..3 {
                sum[k] += l[k] as f64;
            }
        }
        out.push((sum, seen));
    }
    out
}

/// Nodes touched = leaves hit plus all their ancestors (004 §5.2). Walks the pages that
/// were loaded, deepest first, marking a node when a child is marked.
fn ancestors_closure(scene: &Scene) -> Result<u64> {
    let archive = &scene.cache.archive;
    let mut pages: Vec<u32> = (0..archive.pages.len() as u32)
        .filter(|&i| scene.cache.was_touched(i))
        .collect();
    pages.sort_by_key(|&i| std::cmp::Reverse(archive.pages[i as usize].level));
    for id in pages {
        let page = Page::decode(archive, id)?;
        let first = page.first_node;
        for (i, n) in page.bvh.iter().enumerate().rev() {
            let a = (n.a & !KIND_MASK) as u64;
            let marked = match n.a & KIND_MASK {
                INNER => {
                    scene.touched.contains(first + a) || scene.touched.contains(first + n.b as u64)
                }
                CHILD_PAGE => {
                    let f = archive.pages[a as usize].first_node;
                    scene.touched.contains(f) || scene.touched.contains(f + 1)
                }
                _ => false,
            };
            if marked {
                scene.touched.insert(first + i as u64);
            }
        }
    }
    Ok(scene.touched.count())
}
