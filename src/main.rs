use anyhow::Result;
use canopy::convert::{convert, BvhQuality, ConvertOptions};
use canopy::metrics::{self, Metric};
use canopy::render::{render, Integrator, LightPass, RenderOptions};
use canopy::sweep::{self, SweepOptions};
use canopy::{image, inspect, progress, units};
use clap::{Args, Parser, Subcommand};
use std::path::PathBuf;

/// Canopy: an out-of-core streaming renderer for scenes bigger than the machine.
#[derive(Parser)]
#[command(version, about, long_about = None)]
struct Cli {
    /// No progress bars (they are also off when stderr is not a terminal).
    #[arg(long, global = true)]
    quiet: bool,
    #[command(subcommand)]
    cmd: Cmd,
}

/// Render settings shared by `render`, `npp` and `eval`.
#[derive(Args, Clone)]
struct Settings {
    /// `path`: exact path tracing of the leaf triangles (the ground truth); `cone`: cone
    /// casts with level of detail and diffuse light stored per node.
    #[arg(long, value_enum, default_value_t = Integrator::Path)]
    integrator: Integrator,
    /// Cone integrator: the cone radius in the LOD rule is multiplied by this; 0 traces
    /// exact rays (with stored-light reuse), larger values stop at coarser nodes.
    #[arg(long, default_value_t = 1.0, value_parser = units::parse_non_negative)]
    cone_scale: f32,
    /// Cone integrator: tan of the half-angle of the cones after a diffuse or glossy bounce
    /// (004 eq. 4.20's d; the thesis used 0.3). Wider cones stop at coarser nodes: fewer
    /// pages and nodes, more bias from clusters standing in for their triangles.
    #[arg(long, default_value_t = canopy::integrator::cone::DIFFUSE_TAN, value_parser = units::parse_non_negative)]
    diffuse_tan: f32,
    /// Cone integrator: samples after which a node's stored light is converged and its
    /// paths stop there (004 §4.6.1 used 65536).
    #[arg(long, default_value_t = 1024, value_parser = clap::value_parser!(u32).range(1..))]
    cone_samples: u32,
    /// Cone integrator: the light pass that carries caustics (light through smooth mirrors
    /// and glass onto diffuse surfaces, 004 §4.7). `auto` runs it when the scene has both
    /// lights and smooth specular surfaces; `off` leaves caustics to the eye paths.
    #[arg(long, value_enum, default_value_t = LightPass::Auto)]
    light_pass: LightPass,
    /// Cone integrator: photons per light pass (one pass before every eye pass; default:
    /// as many as the full image has pixels, whatever --crop says).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    photons: Option<u32>,
    /// Cone integrator: on pixels where earlier samples, of the pixel or its 8 neighbours,
    /// both saw an emitter and missed it (a lamp's silhouette), the emission seen directly
    /// is averaged over this many primary cones per sample instead of the sample's own;
    /// they cost no shading. 0 turns it off.
    #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u32).range(0..=256))]
    edge_rays: u32,
    /// Memory for decoded pages and per-node state, e.g. 256MiB (default: unlimited).
    #[arg(long, value_parser = units::parse_size)]
    mem_budget: Option<u64>,
    /// Camera name (default: the first camera).
    #[arg(long)]
    camera: Option<String>,
    /// Seed of the sample sequences.
    #[arg(long, default_value_t = 0)]
    seed: u32,
    /// Worker threads (default: all cores; at most 16 per core).
    #[arg(long, value_parser = units::parse_threads)]
    threads: Option<usize>,
    /// Longest path in segments (1: only emitters seen directly); default unbounded.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    max_depth: Option<u32>,
}

impl Settings {
    /// Options for `npp` and `eval`: renders of `archive` written under `output`.
    fn sweep(
        self,
        archive: PathBuf,
        output: &std::path::Path,
        spp: u32,
        progress: bool,
    ) -> SweepOptions {
        SweepOptions {
            out_dir: output.to_path_buf(),
            base: self.options(archive, output.join("x.exr"), spp, progress),
        }
    }

    fn options(self, archive: PathBuf, output: PathBuf, spp: u32, progress: bool) -> RenderOptions {
        RenderOptions {
            archive,
            output,
            integrator: self.integrator,
            spp,
            time: None,
            mem_budget: self.mem_budget,
            width: None,
            height: None,
            camera: self.camera,
            seed: self.seed,
            threads: self.threads,
            max_depth: self.max_depth,
            crop: None,
            preview: false,
            exposure: 1.0,
            stats: None,
            progress,
            cone_scale: self.cone_scale,
            diffuse_tan: self.diffuse_tan,
            cone_samples: self.cone_samples,
            light_pass: self.light_pass,
            photons: self.photons,
            edge_rays: self.edge_rays,
        }
    }
}

#[derive(Subcommand)]
enum Cmd {
    /// Convert meshes and scenes (glTF .gltf/.glb, PLY, OBJ) into a node archive.
    ///
    /// Several inputs merge into one scene. Memory stays under --mem-budget however large
    /// the input: triangles are spilled to disk beside the output and built chunk by chunk.
    Convert {
        /// Input files.
        #[arg(required = true)]
        inputs: Vec<PathBuf>,
        /// Output archive (.canopy). It appears only once complete.
        #[arg(short, long)]
        output: PathBuf,
        /// Memory the conversion may use, e.g. 512MiB, 2GiB, 1.5G.
        #[arg(long, default_value = "2GiB", value_parser = units::parse_size)]
        mem_budget: u64,
        /// TOML scene file: camera, materials and lights for meshes that carry none.
        #[arg(long)]
        scene: Option<PathBuf>,
        /// Most nodes in one page (treelet).
        #[arg(long, default_value_t = 512, value_parser = clap::value_parser!(u16).range(3..=4096))]
        page_nodes: u16,
        /// zstd compression level for pages (1 fast .. 19 small).
        #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(i32).range(1..=22))]
        zstd_level: i32,
        /// Hierarchy build effort: `medium` (PLOC with more reinsertion, faster traversal),
        /// `fast` (about a fifth less build time), or `auto`: medium up to 8M triangles.
        #[arg(long, value_enum, default_value_t = BvhQuality::Auto)]
        bvh: BvhQuality,
        /// Also print the summary as JSON.
        #[arg(long)]
        json: bool,
    },
    /// Render an archive to a linear OpenEXR image (and a PNG preview) under a memory budget.
    ///
    /// Pages are decoded on demand into a cache bounded by --mem-budget; the top pages stay
    /// pinned. The same archive, settings and seed give the same image whatever the thread
    /// count. `-o x.png` writes x.png and x.exr beside it.
    Render {
        archive: PathBuf,
        /// Output image: .exr, or .png (which also writes the .exr).
        #[arg(short, long)]
        output: PathBuf,
        #[command(flatten)]
        settings: Settings,
        /// Samples per pixel.
        #[arg(long, default_value_t = 64)]
        spp: u32,
        /// Render until this much time is spent (e.g. 90s, 5m) instead of a fixed --spp.
        #[arg(long, value_parser = units::parse_duration)]
        time: Option<std::time::Duration>,
        /// Image width (default: the scene's, else 512 high at the camera's aspect).
        #[arg(long)]
        width: Option<u32>,
        /// Image height.
        #[arg(long)]
        height: Option<u32>,
        /// Render only the window X0,X1,Y0,Y1 (pixels, half-open); the image is the window.
        #[arg(long, value_parser = parse_crop)]
        crop: Option<[u32; 4]>,
        /// Also write a tone-mapped sRGB PNG beside the EXR.
        #[arg(long)]
        preview: bool,
        /// Scale applied before tone mapping the PNG.
        #[arg(long, default_value_t = 1.0, value_parser = units::parse_non_negative)]
        exposure: f32,
        /// Write render statistics as JSON here.
        #[arg(long)]
        stats: Option<PathBuf>,
    },
    /// Nodes per pixel: render at several resolutions and count the unique nodes touched
    /// (leaves hit and their ancestors, 004 §5.2). Writes npp.csv and npp.svg.
    Npp {
        archive: PathBuf,
        /// Image heights to render (widths follow the camera's aspect).
        #[arg(long, value_delimiter = ',', default_value = "32,64,128,256,512")]
        resolutions: Vec<u32>,
        /// Samples per pixel at each resolution.
        #[arg(long, default_value_t = 1)]
        spp: u32,
        /// Directory for the CSV, the plot and the images.
        #[arg(short, long, default_value = "npp")]
        output: PathBuf,
        #[command(flatten)]
        settings: Settings,
    },
    /// Speed against error: render each integrator for each time budget, compare with a
    /// reference; writes eval.csv, eval.svg (log-log) and eval.md with c = RMSE·√s.
    Eval {
        archive: PathBuf,
        /// Reference image (a long path-traced render or a Mitsuba 3 render).
        #[arg(long)]
        reference: PathBuf,
        #[arg(long, value_delimiter = ',', default_value = "path,cone")]
        integrators: Vec<Integrator>,
        /// Time budgets.
        #[arg(long, value_delimiter = ',', value_parser = units::parse_duration, default_value = "5s,15s,60s")]
        times: Vec<std::time::Duration>,
        /// Directory for the CSV, the plot, the table and the images.
        #[arg(short, long, default_value = "eval")]
        output: PathBuf,
        #[command(flatten)]
        settings: Settings,
    },
    /// Compare two images: an error metric, the mean ratio, and a false-colour difference.
    Compare {
        test: PathBuf,
        reference: PathBuf,
        #[arg(long, value_enum, default_value_t = Metric::Rmse)]
        metric: Metric,
        /// Write a false-colour |luminance difference| PNG (black none, red the 99th percentile).
        #[arg(long)]
        diff: Option<PathBuf>,
        /// Print JSON.
        #[arg(long)]
        json: bool,
    },
    /// Summarize an archive: counts, sizes, compression, features, pages per path.
    Inspect {
        archive: PathBuf,
        /// Decompress every page and check checksums, links, bounds and counts.
        #[arg(long)]
        verify: bool,
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
    },
}

fn run(cli: Cli) -> Result<()> {
    let show = progress::wanted(cli.quiet);
    match cli.cmd {
        Cmd::Convert {
            inputs,
            output,
            mem_budget,
            scene,
            page_nodes,
            zstd_level,
            bvh,
            json,
        } => {
            let opts = ConvertOptions {
                inputs,
                output: output.clone(),
                mem_budget,
                scene,
                page_nodes: page_nodes as usize,
                zstd_level,
                bvh,
                progress: show,
            };
            let r = convert(&opts)?;
            if json {
                println!("{}", serde_json::to_string_pretty(&r)?);
            } else {
                let per_s = r.input_triangles as f64 / r.seconds_total.max(1e-9);
                println!(
                    "{}: {} triangles -> {} nodes in {} pages ({} chunk{}), {:.2} MiB, {:.1} bytes/triangle",
                    output.display(),
                    r.input_triangles,
                    r.nodes,
                    r.pages,
                    r.chunks,
                    if r.chunks == 1 { "" } else { "s" },
                    r.archive_bytes as f64 / (1 << 20) as f64,
                    r.archive_bytes as f64 / r.input_triangles.max(1) as f64
                );
                println!(
                    "  {:.2} s (import {:.2}, partition {:.2}, build {:.2}), {:.2} M triangles/s",
                    r.seconds_total,
                    r.seconds_import,
                    r.seconds_partition,
                    r.seconds_build,
                    per_s / 1e6
                );
            }
        }
        Cmd::Render {
            archive,
            output,
            settings,
            spp,
            time,
            width,
            height,
            crop,
            preview,
            exposure,
            stats,
        } => {
            let opts = RenderOptions {
                time,
                width,
                height,
                crop,
                preview,
                exposure,
                stats,
                ..settings.options(archive, output.clone(), spp, show)
            };
            let (_, s) = render(&opts)?;
            println!(
                "{}: {}x{}, {} spp, {:.2} s ({:.2} M rays/s, {:.3} M paths/s), peak RSS {:.1} MiB, {} pages loaded, {} evicted, hit rate {:.4}",
                output.display(),
                s.width,
                s.height,
                s.spp,
                s.seconds.render,
                s.rays_per_second / 1e6,
                s.paths_per_second / 1e6,
                s.peak_rss_bytes as f64 / 1048576.0,
                s.pages_loaded,
                s.pages_evicted,
                s.cache_hit_rate
            );
        }
        Cmd::Npp {
            archive,
            resolutions,
            spp,
            output,
            settings,
        } => {
            let o = settings.sweep(archive, &output, spp, show);
            println!("pixels      unique nodes  nodes/pixel  pages  resident MiB  seconds");
            for r in sweep::npp(&o, &resolutions)? {
                println!(
                    "{:>10}  {:>12}  {:>11.2}  {:>5}  {:>12.1}  {:>7.2}",
                    r.pixels,
                    r.unique_nodes,
                    r.nodes_per_pixel,
                    r.pages_touched,
                    r.resident_bytes_peak as f64 / 1048576.0,
                    r.seconds
                );
            }
            println!("wrote {}/npp.csv and npp.svg", output.display());
        }
        Cmd::Eval {
            archive,
            reference,
            integrators,
            times,
            output,
            settings,
        } => {
            let o = settings.sweep(archive, &output, 1, show);
            let rows = sweep::eval(&o, &reference, &integrators, &times)?;
            for r in &rows {
                println!(
                    "{:?} {:>6.1}s: {} spp, RMSE {:.4e}, c {:.4e}",
                    r.integrator, r.seconds, r.spp, r.rmse, r.c
                );
            }
            if let Some(line) = sweep::time_to_match(&rows) {
                println!("{line}");
            }
            println!("wrote {}/eval.csv, eval.svg and eval.md", output.display());
        }
        Cmd::Compare {
            test,
            reference,
            metric,
            diff,
            json,
        } => {
            if let Some(d) = diff
                .iter()
                .find(|d| image::same_file(d, &test) || image::same_file(d, &reference))
            {
                anyhow::bail!("{}: --diff would overwrite an input image", d.display());
            }
            let t = image::Image::read_exr(&test)?;
            let r = image::Image::read_exr(&reference)?;
            let e = metrics::error(&t, &r, metric)?;
            let ratio = metrics::mean_ratio(&t, &r);
            let scale = match &diff {
                Some(p) => Some(metrics::write_diff(&t, &r, p)?),
                None => None,
            };
            if json {
                let v = serde_json::json!({
                    "metric": metric, "error": e, "mean_test": t.mean(), "mean_reference": r.mean(),
                    "mean_relative_difference": ratio, "diff_scale": scale,
                });
                println!("{}", serde_json::to_string_pretty(&v)?);
            } else {
                println!("{metric:?}: {e:.6e}");
                println!(
                    "mean: test {:?}, reference {:?}, relative difference {:+.4} {:+.4} {:+.4}",
                    t.mean(),
                    r.mean(),
                    ratio[0],
                    ratio[1],
                    ratio[2]
                );
            }
        }
        Cmd::Inspect {
            archive,
            verify,
            json,
        } => {
            let a = canopy_format::Archive::open(&archive)?;
            let mut s = inspect::summarize(&a);
            if verify {
                inspect::verify(&a, &mut s, show)?;
            }
            if json {
                println!("{}", serde_json::to_string_pretty(&s)?);
            } else {
                inspect::print(&s);
            }
        }
    }
    Ok(())
}

fn parse_crop(s: &str) -> Result<[u32; 4]> {
    let v: Vec<u32> = s
        .split(',')
        .map(|x| x.trim().parse::<u32>())
        .collect::<Result<_, _>>()
        .map_err(|_| anyhow::anyhow!("'{s}' is not X0,X1,Y0,Y1 (four whole numbers)"))?;
    match v[..] {
        [a, b, c, d] => Ok([a, b, c, d]),
        _ => anyhow::bail!("'{s}' is not X0,X1,Y0,Y1 (four whole numbers)"),
    }
}

fn main() {
    // Die quietly on a closed pipe (`canopy inspect x | head`) as Unix tools do, instead of
    // Rust's default of ignoring SIGPIPE and panicking in println!.
    #[cfg(unix)]
    // SAFETY: restoring the default disposition of SIGPIPE before any thread starts.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
    if let Err(e) = run(Cli::parse()) {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}
