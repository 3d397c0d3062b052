use anyhow::{bail, Context, Result};
use canopy::image::{same_file, Image};
use canopy::metrics::{Comparison, Metric};
use clap::Args;
use std::path::{Path, PathBuf};

/// Compare two images: an error metric, the mean ratio, and a false-colour difference.
///
/// OpenEXR images (up to 65,536 pixels a side and 2^27 pixels in all; larger windows are
/// refused from the header, before any pixel is decoded), or 8-bit sRGB PNG images,
/// compared linearised (a note says so).
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

fn is_png(path: &Path) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| e.eq_ignore_ascii_case("png"))
}

/// Bytes an image takes decoded, from its header.
fn decoded_bytes(path: &Path) -> Result<u64> {
    if is_png(path) {
        let (w, h) = image::image_dimensions(path)
            .with_context(|| format!("{}: not a readable PNG image", path.display()))?;
        return Ok(w as u64 * h as u64 * 12);
    }
    Ok(canopy::exr_header::check(path)?.data_bytes())
}

/// An OpenEXR image, or a PNG linearised from sRGB (with a note saying so).
fn read(path: &Path) -> Result<Image> {
    if !is_png(path) {
        return Image::read_exr(path);
    }
    eprintln!(
        "note: {}: an 8-bit sRGB PNG, compared linearised (its tone mapping and clipping stay)",
        path.display()
    );
    Image::read_png_linear(path)
}

pub fn run(a: CompareArgs) -> Result<()> {
    if let Some(d) = a
        .diff
        .iter()
        .find(|d| same_file(d, &a.test) || same_file(d, &a.reference))
    {
        bail!("{}: --diff would overwrite an input image", d.display());
    }
    let sizes = decoded_bytes(&a.test)? + decoded_bytes(&a.reference)?;
    canopy::exr_header::fits_budget(a.mem_budget, sizes, "the two images")?;
    let t = read(&a.test)?;
    let r = read(&a.reference)?;
    let c = Comparison::new(&t, &r, a.metric, a.diff.as_deref())?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&c)?);
    } else {
        println!("{c}");
    }
    Ok(())
}
