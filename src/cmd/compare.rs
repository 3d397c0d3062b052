use anyhow::{bail, Result};
use canopy::image::{same_file, Image};
use canopy::metrics::{Comparison, Metric};
use clap::Args;
use std::path::PathBuf;

/// Compare two images: an error metric, the mean ratio, and a false-colour difference.
///
/// OpenEXR images up to 65,536 pixels a side and 2^27 pixels in all; larger windows are
/// refused from the header, before any pixel is decoded.
#[derive(Args)]
pub struct CompareArgs {
    test: PathBuf,
    reference: PathBuf,
    #[arg(long, value_enum, default_value_t = Metric::Rmse)]
    metric: Metric,
    /// Write a false-colour |luminance difference| PNG (black none, red the 99th percentile).
    #[arg(long)]
    diff: Option<PathBuf>,
    /// Memory for the two images decoded, e.g. 1GiB (default: unlimited); images that do
    /// not fit are refused before they are decoded.
    #[arg(long, value_parser = canopy::units::parse_size)]
    mem_budget: Option<u64>,
    /// Print JSON.
    #[arg(long)]
    json: bool,
}

pub fn run(a: CompareArgs) -> Result<()> {
    if let Some(d) = a
        .diff
        .iter()
        .find(|d| same_file(d, &a.test) || same_file(d, &a.reference))
    {
        bail!("{}: --diff would overwrite an input image", d.display());
    }
    let sizes = canopy::exr_header::check(&a.test)?.data_bytes()
        + canopy::exr_header::check(&a.reference)?.data_bytes();
    canopy::exr_header::fits_budget(a.mem_budget, sizes, "the two images")?;
    let t = Image::read_exr(&a.test)?;
    let r = Image::read_exr(&a.reference)?;
    let c = Comparison::new(&t, &r, a.metric, a.diff.as_deref())?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&c)?);
    } else {
        println!("{c}");
    }
    Ok(())
}
