use anyhow::{bail, Result};
use canopy::relight::{self, PrepareOptions, RelightOptions, Relighter};
use canopy::units;
use clap::Args;
use std::io::Read;
use std::path::{Path, PathBuf};

/// Relight one view with global illumination: precompute its light transfer once, then
/// render any light set (lamps scaled, lights moved or added) from it.
///
/// `canopy relight ARCHIVE -o VIEW.relight` precomputes; `canopy relight VIEW.relight
/// --lights L.toml -o out.exr` renders a light set (without --lights: the archive's own
/// lights).
#[derive(Args)]
pub struct RelightArgs {
    /// A node archive (to precompute) or a .relight file (to render).
    input: PathBuf,
    /// Output: VIEW.relight when precomputing; .exr or .png (which also writes the .exr)
    /// when rendering.
    #[arg(short, long, required_unless_present = "serve")]
    output: Option<PathBuf>,
    /// Rendering: serve a web page at HOST:PORT (loopback only, e.g. 127.0.0.1:8080) with a
    /// control per light, showing the relit image as the controls move.
    #[arg(long, value_name = "HOST:PORT", conflicts_with = "output")]
    serve: Option<String>,
    /// Rendering: a light set (TOML; see docs/relighting.md) changing the archive's lights.
    #[arg(long, value_name = "FILE")]
    lights: Option<PathBuf>,
    /// Rendering: light and BSDF samples per view sample for each lamp and the environment
    /// (a punctual light takes one light sample, which is exact) [default: 4].
    #[arg(long, value_name = "N")]
    light_samples: Option<u32>,
    /// Precomputing: camera name (default: the first camera, else the default view).
    #[arg(long)]
    camera: Option<String>,
    /// Precomputing: image width (default: the camera's, else 512 high at its aspect).
    #[arg(long)]
    width: Option<u32>,
    /// Precomputing: image height.
    #[arg(long)]
    height: Option<u32>,
    /// Precomputing: view samples per pixel [default: 16].
    #[arg(long)]
    spp: Option<u32>,
    /// Precomputing: transfer paths per view sample [default: 16].
    #[arg(long)]
    paths: Option<u32>,
    /// Precomputing: the compression's accuracy knob, the most coefficients a pixel's
    /// transfer keeps [default: 128].
    #[arg(long)]
    coefficients: Option<u32>,
    /// Precomputing: seed of the sample sequences [default: 0].
    #[arg(long)]
    seed: Option<u32>,
    /// Memory budget, e.g. 1GiB (default: unlimited): precomputing, the archive's pages and the
    /// precompute's tables; rendering, the archive's pages only.
    #[arg(long, value_parser = units::parse_size)]
    mem_budget: Option<u64>,
    /// Worker threads (default: all cores).
    #[arg(long, value_parser = units::parse_threads)]
    threads: Option<usize>,
}

/// Whether `path` starts as a relight file does.
fn is_relight_file(path: &Path) -> bool {
    let mut magic = [0u8; 8];
    std::fs::File::open(path)
        .and_then(|mut f| f.read_exact(&mut magic))
        .is_ok_and(|()| magic == relight::file::MAGIC)
}

pub fn run(a: RelightArgs, progress: bool) -> Result<()> {
    if is_relight_file(&a.input) {
        render(a)
    } else {
        prepare(a, progress)
    }
}

fn prepare(a: RelightArgs, progress: bool) -> Result<()> {
    if let Some(flag) = [
        a.lights.as_ref().map(|_| "--lights"),
        a.light_samples.map(|_| "--light-samples"),
        a.serve.as_ref().map(|_| "--serve"),
    ]
    .into_iter()
    .flatten()
    .next()
    {
        bail!(
            "{flag} applies when rendering a .relight file; {} is an archive to precompute",
            a.input.display()
        );
    }
    let output = a.output.expect("clap requires -o without --serve");
    if output.extension().and_then(|e| e.to_str()) != Some("relight") {
        bail!(
            "{}: a precompute writes a .relight file (`-o VIEW.relight`)",
            output.display()
        );
    }
    let o = PrepareOptions {
        archive: a.input,
        output: output.clone(),
        camera: a.camera,
        width: a.width,
        height: a.height,
        spp: a.spp.unwrap_or(16),
        paths: a.paths.unwrap_or(16),
        coefficients: a.coefficients.unwrap_or(128),
        seed: a.seed.unwrap_or(0),
        mem_budget: a.mem_budget,
        threads: a.threads,
        progress,
    };
    let s = relight::prepare(&o)?;
    println!("{}: {s}", output.display());
    Ok(())
}

fn render(a: RelightArgs) -> Result<()> {
    let given = [
        a.camera.as_ref().map(|_| "--camera"),
        a.width.map(|_| "--width"),
        a.height.map(|_| "--height"),
        a.spp.map(|_| "--spp"),
        a.paths.map(|_| "--paths"),
        a.coefficients.map(|_| "--coefficients"),
        a.seed.map(|_| "--seed"),
    ];
    if let Some(flag) = given.into_iter().flatten().next() {
        bail!(
            "{flag} applies when precomputing; {} is a .relight file, precomputed with its own",
            a.input.display()
        );
    }
    let o = RelightOptions {
        view: a.input.clone(),
        lights: a.lights,
        light_samples: a.light_samples.unwrap_or(4),
        mem_budget: a.mem_budget,
        threads: a.threads,
    };
    let Some(output) = a.output else {
        let addr = a.serve.expect("clap requires --serve without -o");
        let r = Relighter::open(&o, (a.input.with_extension("exr"), None))?;
        return relight::serve::serve(r, &addr, |at| {
            println!("serving http://{at}/ (Ctrl-C ends)");
            std::io::Write::flush(&mut std::io::stdout()).ok();
        });
    };
    let (exr, png) = canopy::render::image_outputs(&output, false, (&a.input, "the view"))?;
    let mut r = Relighter::open(&o, (exr.clone(), png.clone()))?;
    let f = r.image()?;
    f.image.write_exr(&exr)?;
    if let Some(png) = &png {
        f.image.write_png(png, 1.0)?;
    }
    let [t, s, p] = f.seconds;
    println!(
        "{}: {}x{}, relit in {:.3} s (tracing the lights {t:.3} s, summing {s:.3} s, transfer {p:.3} s)",
        output.display(),
        f.image.width,
        f.image.height,
        f.total()
    );
    Ok(())
}
