use super::RenderSettings;
use anyhow::Result;
use canopy::integrator::Kind;
use canopy::sweep::{self, NppRow, SweepOptions};
use canopy::units;
use clap::Args;
use std::path::{Path, PathBuf};

/// Nodes per pixel: render at several resolutions to equal noise and count the nodes used
/// (leaves hit and their ancestors, 004 §5.2), at every power-of-two spp on the way.
/// Writes npp.csv and npp.svg.
#[derive(Args)]
#[command(mut_arg("store_out", |a| a.hide(true)))]
pub struct NppArgs {
    archive: PathBuf,
    #[arg(long, value_delimiter = ',', default_value = "path,cone")]
    pub integrators: Vec<Kind>,
    /// Image heights to render (widths follow the camera's aspect).
    #[arg(long, value_delimiter = ',', default_value = "32,64,128,256,512")]
    resolutions: Vec<u32>,
    /// Noise to render to: the RMS standard error of the pixels' luminance over the image's
    /// mean luminance. Each render doubles its spp until it is reached.
    #[arg(long, default_value_t = 0.05, value_parser = parse_noise)]
    noise: f64,
    /// The most samples per pixel a render takes if the noise target is not reached first.
    #[arg(long, default_value_t = 1024, value_parser = clap::value_parser!(u32).range(1..))]
    spp: u32,
    /// Directory for the CSV, the plot and the images.
    #[arg(short, long, default_value = "npp")]
    output: PathBuf,
    #[command(flatten)]
    pub settings: RenderSettings,
}

/// Speed against error: render each integrator for each time budget, compare with a
/// reference; writes eval.csv, eval.svg (log-log) and eval.md with c = RMSE·√s.
#[derive(Args)]
#[command(mut_arg("store_out", |a| a.hide(true)))]
pub struct EvalArgs {
    archive: PathBuf,
    /// Reference image (a long path-traced render or a Mitsuba 3 render).
    #[arg(long)]
    reference: PathBuf,
    #[arg(long, value_delimiter = ',', default_value = "path,cone")]
    pub integrators: Vec<Kind>,
    /// Time budgets.
    #[arg(long, value_delimiter = ',', value_parser = units::parse_duration, default_value = "5s,15s,60s")]
    times: Vec<std::time::Duration>,
    /// Directory for the CSV, the plot, the table and the images.
    #[arg(short, long, default_value = "eval")]
    output: PathBuf,
    #[command(flatten)]
    pub settings: RenderSettings,
}

/// Renders of `archive` written under `dir`.
fn sweep_options(
    s: &RenderSettings,
    archive: PathBuf,
    dir: &Path,
    spp: u32,
    progress: bool,
) -> SweepOptions {
    SweepOptions {
        out_dir: dir.to_path_buf(),
        base: s.options(Kind::Path, archive, dir.join("x.exr"), spp, progress),
        cone: s.cone(),
        pbgi: s.pbgi(),
    }
}

fn parse_noise(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v > 0.0 && v.is_finite() => Ok(v),
        _ => Err(format!("'{s}' is not a positive number (e.g. 0.05 for 5%)")),
    }
}

pub fn npp(a: NppArgs, progress: bool) -> Result<()> {
    let o = sweep_options(&a.settings, a.archive, &a.output, a.spp, progress);
    println!("{}", NppRow::HEADER);
    for r in sweep::npp(&o, &a.integrators, &a.resolutions, a.noise, a.spp)? {
        println!("{r}");
    }
    println!("wrote {}/npp.csv and npp.svg", a.output.display());
    Ok(())
}

pub fn eval(a: EvalArgs, progress: bool) -> Result<()> {
    let o = sweep_options(&a.settings, a.archive, &a.output, 1, progress);
    let rows = sweep::eval(&o, &a.reference, &a.integrators, &a.times)?;
    for r in &rows {
        println!("{r}");
    }
    for line in sweep::time_to_match(&rows) {
        println!("{line}");
    }
    println!(
        "wrote {}/eval.csv, eval.svg and eval.md",
        a.output.display()
    );
    Ok(())
}
