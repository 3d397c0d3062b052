use super::RenderSettings;
use anyhow::Result;
use canopy::integrator::Kind;
use canopy::render::{render, RenderOptions};
use canopy::units;
use clap::Args;
use std::path::PathBuf;

/// Render an archive to a linear OpenEXR image (and a PNG preview) under a memory budget.
///
/// Pages are decoded on demand into a cache bounded by --mem-budget; the top pages stay
/// pinned. The path tracer and PBGI give the same image for the same archive, settings and
/// seed whatever the thread count; the cone integrator's stored light depends on the order
/// threads reach it. `-o x.png` writes x.png and x.exr beside it.
#[derive(Args)]
pub struct RenderArgs {
    archive: PathBuf,
    /// `path`: exact path tracing of the leaf triangles (the ground truth); `cone`: cone
    /// casts with level of detail and diffuse light stored per node; `pbgi`: point-based
    /// GI, every bounce baked into the nodes and gathered into a micro-buffer per receiver.
    #[arg(long, value_enum, default_value_t = Kind::Path)]
    pub integrator: Kind,
    /// Output image: .exr, or .png (which also writes the .exr).
    #[arg(short, long)]
    output: PathBuf,
    /// Samples per pixel [default: 64]; with --time, the most (whichever comes first).
    #[arg(long)]
    spp: Option<u32>,
    /// Render until this much time is spent (e.g. 90s, 5m), or --spp samples if given.
    #[arg(long, value_parser = units::parse_duration)]
    time: Option<std::time::Duration>,
    /// Image width (default: the scene's, else 512 high at the camera's aspect).
    #[arg(long)]
    width: Option<u32>,
    /// Image height.
    #[arg(long)]
    height: Option<u32>,
    /// Render only the window X0,X1,Y0,Y1 (pixels, half-open): the EXR's data window is
    /// that tile inside the whole frame's display window, and its attributes name the
    /// archive, settings and seed, so `canopy assemble` can join tiles into the frame.
    #[arg(long, value_parser = parse_crop)]
    crop: Option<[u32; 4]>,
    /// Also write a tone-mapped sRGB PNG beside the EXR.
    #[arg(long)]
    preview: bool,
    /// Scale applied before tone mapping the PNG.
    #[arg(long, default_value_t = 1.0, value_parser = units::parse_non_negative)]
    exposure: f32,
    /// Stream the image as it converges to tev listening at HOST:PORT (e.g.
    /// 127.0.0.1:14158, tev's default).
    #[arg(long, value_name = "HOST:PORT")]
    display_server: Option<String>,
    /// A light set (TOML: lamps scaled, punctual lights moved or added, the environment's
    /// strength) changing the archive's lights; the path tracer only.
    #[arg(long, value_name = "FILE")]
    lights: Option<PathBuf>,
    /// Write render statistics as JSON here.
    #[arg(long)]
    stats: Option<PathBuf>,
    /// Also count the nodes the render used (hit nodes and their ancestors, 004 §5.2) for
    /// the stats' unique_nodes_touched and nodes_per_pixel. It re-reads every page the render
    /// touched: under a tight budget that costs seconds (8 s after a 42-s render of 200 M
    /// triangles at 1 GiB). `canopy npp` always counts.
    #[arg(long)]
    node_stats: bool,
    /// Last: the cone integrator's flags end the help under their own heading.
    #[command(flatten)]
    pub settings: RenderSettings,
}

impl RenderSettings {
    /// Options for a render of `archive` to `output` with integrator `kind`; the rest at
    /// their defaults.
    pub(super) fn options(
        &self,
        kind: Kind,
        archive: PathBuf,
        output: PathBuf,
        spp: u32,
        progress: bool,
    ) -> RenderOptions {
        RenderOptions {
            archive,
            output,
            integrator: self.settings(kind),
            spp,
            time: None,
            noise: None,
            mem_budget: self.mem_budget,
            width: None,
            height: None,
            camera: self.camera.clone(),
            seed: self.seed,
            threads: self.threads,
            max_depth: self.max_depth,
            texture_filter: self.texture_filter,
            pixel_split: self.pixel_split,
            display: None,
            env: self.env.options(),
            lights: None,
            crop: None,
            preview: false,
            exposure: 1.0,
            stats: None,
            node_stats: false,
            progress,
        }
    }
}

pub fn run(a: RenderArgs, progress: bool) -> Result<()> {
    let spp = match (a.spp, a.time) {
        (Some(n), _) => n,
        (None, Some(_)) => u32::MAX - 1,
        (None, None) => 64,
    };
    let opts = RenderOptions {
        time: a.time,
        width: a.width,
        height: a.height,
        crop: a.crop,
        preview: a.preview,
        exposure: a.exposure,
        stats: a.stats,
        node_stats: a.node_stats,
        display: a.display_server,
        lights: a.lights,
        ..a.settings
            .options(a.integrator, a.archive, a.output.clone(), spp, progress)
    };
    let (_, s) = render(&opts)?;
    println!("{}: {s}", a.output.display());
    Ok(())
}

fn parse_crop(s: &str) -> Result<[u32; 4]> {
    let bad = || anyhow::anyhow!("'{s}' is not X0,X1,Y0,Y1 (four whole numbers)");
    let v: Vec<u32> = s
        .split(',')
        .map(|x| x.trim().parse::<u32>())
        .collect::<Result<_, _>>()
        .map_err(|_| bad())?;
    v.try_into().map_err(|_| bad())
}
