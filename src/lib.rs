//! Canopy: an out-of-core streaming renderer. This crate holds the importers, the archive
//! builder, the paged renderer and the command-line front end; `canopy-format` holds the
//! on-disk format.

pub mod camera;
pub mod convert;
pub mod exr_header;
pub mod image;
pub mod import;
pub mod inspect;
pub mod integrator;
pub mod light;
pub mod light_store;
pub mod material;
pub mod metrics;
pub mod moments;
pub mod paging;
pub mod progress;
pub mod relight;
pub mod render;
pub mod sampler;
pub mod sweep;
#[cfg(test)]
mod test_rng;
pub mod texture;
pub mod trace;
pub mod units;
pub mod wavelet;
