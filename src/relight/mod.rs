//! Relighting with global illumination (seed 001, Kontkanen et al. 2006; carried to large
//! scenes over a hierarchy by Hašan, Pellacini and Bala 2006): for one fixed view, the
//! transfer from light arriving at the scene's surfaces to every pixel is precomputed once
//! (`prepare`), all bounces included, over the light cells of the node tree's leaves and
//! compressed along the tree's order; a light set is then rendered (`Relighter::image`, or
//! a slice of each light's rays a frame by `Relighter::frame`) as direct light at the view
//! samples plus the product of the transfer with direct light gathered at the cells the
//! transfer reads.
//! Light transport is linear in the emitters, so the product is exact up to the transfer's
//! compression and noise: lamps may be scaled and tinted, punctual lights moved, re-aimed
//! or added, the environment made stronger or turned, each without a new precompute.
//!
//! Where light arrives at an interior path vertex it leaves through the glossy lobes as if
//! it arrived evenly over the hemisphere (`transfer`): the light reflected is right in
//! total but spread over every direction, so a lamp's highlight thrown onto other
//! surfaces is spread and the image may be off either way. A lamp a path meets after a
//! perfectly smooth bounce or through a surface is a lamp record of the pixel, the
//! environment met so a sky record (their caustics are carried); caustics of punctual
//! lights are not.

mod cells;
pub mod file;
mod precompute;
mod relighter;
pub mod serve;
mod transfer;
mod view;

pub use precompute::prepare;
pub use relighter::{Frame, RelightOptions, Relighter};

use crate::render::RenderOptions;
use std::path::PathBuf;

/// What `prepare` precomputes.
#[derive(Clone, Debug)]
pub struct PrepareOptions {
    pub archive: PathBuf,
    pub output: PathBuf,
    pub camera: Option<String>,
    pub width: Option<u32>,
    pub height: Option<u32>,
    /// View samples per pixel.
    pub spp: u32,
    /// Transfer paths per view sample.
    pub paths: u32,
    /// Most coefficients a pixel's transfer row keeps (the compression's accuracy knob).
    pub coefficients: u32,
    pub seed: u32,
    pub mem_budget: Option<u64>,
    pub threads: Option<usize>,
    pub progress: bool,
}

/// How a precompute went.
#[derive(Debug, serde::Serialize)]
pub struct PrepareStats {
    pub seconds: f64,
    pub pixels: u64,
    pub cells: u64,
    pub coefs: u64,
    pub bytes: u64,
}

impl std::fmt::Display for PrepareStats {
    fn fmt(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        write!(
            f,
            "{} pixels, {} light cells, {:.1} coefficients per pixel, {}, {:.2} s",
            self.pixels,
            self.cells,
            self.coefs as f64 / self.pixels.max(1) as f64,
            crate::units::format_size(self.bytes),
            self.seconds
        )
    }
}

/// Render options for the scene of a relight: the path tracer's, which reads lights as
/// the archive and a light set give them.
fn scene_options(
    archive: PathBuf,
    output: PathBuf,
    camera: Option<String>,
    size: (Option<u32>, Option<u32>),
    budget: (Option<u64>, Option<usize>),
    lights: Option<PathBuf>,
) -> RenderOptions {
    RenderOptions {
        archive,
        output,
        integrator: crate::integrator::Settings::Path,
        spp: 1,
        time: None,
        noise: None,
        mem_budget: budget.0,
        width: size.0,
        height: size.1,
        camera,
        seed: 0,
        threads: budget.1,
        max_depth: None,
        texture_filter: crate::texture::TextureFilter::Trilinear,
        pixel_split: None,
        env: None,
        lights,
        display: None,
        crop: None,
        preview: false,
        exposure: 1.0,
        stats: None,
        node_stats: false,
        progress: false,
    }
}
