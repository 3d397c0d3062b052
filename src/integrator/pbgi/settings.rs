//! PBGI's command-line flags, the bake's among them.

use super::bake::BakeParams;
use super::glossy::WaveletMode;
use super::wpbgi;
use crate::integrator::edge::PBGI_EDGE_RAYS;
use std::path::PathBuf;

/// PBGI's parameters (its command-line flags, refused under another integrator).
#[derive(Clone, Debug, clap::Args)]
#[command(next_help_heading = "Point-based GI (--integrator pbgi)")]
pub struct PbgiSettings {
    /// How a receiver gathers the baked light: `rays` traces one ray per micro-buffer
    /// texel, `cut` splats a cut of the hierarchy (003 ch. 2).
    #[arg(long = "pbgi-gather", value_enum, default_value_t = Gather::Rays)]
    pub gather: Gather,
    #[command(flatten)]
    pub bake: BakeSettings,
    /// Baked light from `canopy bake` (default: baked before the first pass, counted in the
    /// render time).
    #[arg(long = "bake-in", value_name = "FILE", conflicts_with_all = ["bake_samples", "patch_size", "bounces", "quality"])]
    pub bake_in: Option<PathBuf>,
    /// How rough specular lobes take their glossy bounce: exact `rays`, WPBGI's `wavelet`
    /// product (000 §3.2) or its `cache` of radiance records (002 §4.3).
    #[arg(
        long = "pbgi-glossy-bounce",
        value_name = "HOW",
        default_value = "rays",
        conflicts_with = "clusters"
    )]
    pub glossy_bounce: wpbgi::GlossyBounce,
    /// The cut's threshold (with --pbgi-gather cut): a node is splatted whole when it
    /// subtends at most this many texels [default: 1].
    #[arg(long = "pbgi-angle", help_heading = ADVANCED, value_parser = crate::units::parse_non_negative)]
    pub angle: Option<f32>,
    /// Micro-buffer texels per cube-face side, even (a power of two for WPBGI)
    /// [default: 8].
    #[arg(long = "pbgi-resolution", help_heading = ADVANCED, default_value_t = 8, value_parser = parse_resolution, hide_default_value = true)]
    pub resolution: usize,
    /// `--edge-rays` (a flag of both cone and PBGI, set by the command line).
    #[arg(skip = PBGI_EDGE_RAYS)]
    pub edge_rays: u32,
    /// FPBGI (003 ch. 3, with --pbgi-gather cut): receivers of a 16×16 tile grouped into
    /// at most this many clusters sharing one cut; 0 gathers each alone [default: 0].
    #[arg(long = "receiver-clusters", help_heading = ADVANCED, default_value_t = 0, hide_default_value = true)]
    pub clusters: usize,
    /// FPBGI's near/far test: a node is far for a whole cluster when the cluster's radius
    /// is at most this fraction of its distance [default: 0.01].
    #[arg(long = "cluster-far", help_heading = ADVANCED, default_value_t = 0.01, hide_default_value = true, requires = "clusters", value_parser = crate::units::parse_non_negative)]
    pub far: f32,
    /// Rays sampled from a receiver's rough specular lobes for its glossy bounce
    /// [default: 2 where some material is glossy].
    #[arg(long = "pbgi-glossy-rays", help_heading = ADVANCED, value_name = "K", value_parser = clap::value_parser!(u32).range(1..=16))]
    pub glossy_rays: Option<u32>,
    /// WPBGI's BRDF tables drop Haar coefficients below this fraction of an entry's norm
    /// [default: 0.01; with --pbgi-glossy-bounce wavelet or cache].
    #[arg(long = "pbgi-brdf-threshold", help_heading = ADVANCED, value_name = "T", value_parser = crate::units::parse_non_negative)]
    pub brdf_threshold: Option<f32>,
    /// WPBGI's light importance γ (000 §3.2): refine the micro-buffer past 16² only where
    /// incident light exceeds γ times the mean; 0 is off [default: 0; wavelet or cache].
    #[arg(long = "pbgi-light-importance", help_heading = ADVANCED, value_name = "GAMMA", value_parser = crate::units::parse_non_negative)]
    pub light_gamma: Option<f32>,
    /// Most (light sample, lobe ray) pairs a glossy receiver takes where its first two
    /// disagree; 1 is off [default: 32 where some material is glossy].
    #[arg(long = "pbgi-split", help_heading = ADVANCED, value_name = "N", value_parser = clap::value_parser!(u32).range(1..=32))]
    pub split: Option<u32>,
    /// Samples of a pixel's surface that share one gather: it gathers at every R-th; 1
    /// gathers at every sample [default: 64].
    #[arg(long = "pbgi-reuse", help_heading = ADVANCED, value_name = "R", default_value_t = 64, hide_default_value = true, value_parser = clap::value_parser!(u32).range(1..))]
    pub reuse: u32,
    /// The irradiance cache's error bound (gathers shared between nearby pixels); 0 is
    /// off [default: 0.3].
    #[arg(long = "pbgi-cache", help_heading = ADVANCED, value_name = "A", default_value_t = 0.3, hide_default_value = true, value_parser = parse_cache)]
    pub cache: f32,
    /// Refused: the bake file is given with --bake-in.
    #[arg(long, hide = true, value_name = "FILE", value_parser = refused_radiance)]
    pub radiance: Option<PathBuf>,
    /// Refused: every integrator's pixel split is --pixel-split.
    #[arg(long = "pbgi-pixel-split", hide = true, value_name = "M", value_parser = refused_pixel_split)]
    pub pbgi_pixel_split: Option<u32>,
}

/// `--pbgi-gather`: how a receiver's micro-buffer is filled.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Gather {
    /// Every texel's ray traced exactly, its hit reading the baked light.
    Rays,
    /// A cut of the hierarchy splatted, near leaves rasterized (003 ch. 2).
    Cut,
}

/// The cut's threshold unless `--pbgi-angle` says.
const ANGLE: f32 = 1.0;

impl PbgiSettings {
    /// Whether texel rays fill the micro-buffer.
    pub fn rays(&self) -> bool {
        self.gather == Gather::Rays
    }

    /// The cut's threshold.
    pub fn angle(&self) -> f32 {
        self.angle.unwrap_or(ANGLE)
    }
}

fn parse_resolution(s: &str) -> Result<usize, String> {
    match s.parse::<usize>() {
        Ok(n) if (2..=64).contains(&n) && n.is_multiple_of(2) => Ok(n),
        _ => Err(format!("{s:?}: an even number from 2 to 64")),
    }
}

fn refused_radiance(_: &str) -> Result<PathBuf, String> {
    Err("a bake file is read with --bake-in FILE".into())
}

fn refused_pixel_split(_: &str) -> Result<u32, String> {
    Err("the camera samples a pass takes of a pixel are set with --pixel-split M, for every integrator".into())
}

fn parse_cache(s: &str) -> Result<f32, String> {
    match s.parse::<f32>() {
        Ok(a) if (0.0..=2.0).contains(&a) => Ok(a),
        _ => Err(format!("{s:?}: a number from 0 (off) to 2")),
    }
}

impl Default for PbgiSettings {
    /// The command line's defaults.
    fn default() -> PbgiSettings {
        crate::integrator::flag_defaults()
    }
}

/// Rays from a glossy receiver's lobes for its bounce, unless `--pbgi-glossy-rays` says,
/// where some material has rough specular lobes.
pub(super) const GLOSSY_RAYS: u32 = 2;

/// Most pairs and bounce rays per glossy receiver, unless `--pbgi-split` says, where
/// some material has rough specular lobes (`Split::new` splits only where K is 2 or more).
pub(super) const SPLIT: u32 = 32;

/// The bake's flags, shared by `canopy bake` and `render --integrator pbgi`.
#[derive(Clone, Debug, clap::Args)]
pub struct BakeSettings {
    /// The bake's light samples and patch size together (docs/pbgi.md measures each).
    #[arg(long, value_enum, default_value_t = Quality::Default)]
    pub quality: Quality,
    /// Bounces the baked light carries: 1 is direct light reflected once [default: all,
    /// ended by Russian roulette; under --max-depth D, D − 2].
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=256))]
    pub bounces: Option<u32>,
    /// Light samples per patch in the bake [default: set by --quality].
    #[arg(long = "bake-samples", help_heading = ADVANCED, value_parser = clap::value_parser!(u32).range(1..=65536))]
    pub bake_samples: Option<u32>,
    /// Finest patch side as a fraction of the scene's diagonal; larger triangles are baked
    /// as up to 4^6 patches [default: set by --quality].
    #[arg(long = "patch-size", help_heading = ADVANCED, value_parser = parse_patch_size)]
    pub patch_size: Option<f32>,
    /// Glossy light stored per node as Haar wavelets (000 §3.1), for the cut gather:
    /// `auto` when some material is glossy and the gather is the cut.
    #[arg(long, help_heading = ADVANCED, value_enum, default_value_t = WaveletMode::Auto)]
    pub wavelet: WaveletMode,
    /// Texels per cube-face side of the glossy maps, a power of two up to 32 [default: 8].
    #[arg(long = "wavelet-resolution", help_heading = ADVANCED, value_parser = parse_wavelet_resolution)]
    pub wavelet_resolution: Option<usize>,
    /// Glossy coefficients below this fraction of their page's largest are dropped
    /// [default: 0.01].
    #[arg(long = "wavelet-threshold", help_heading = ADVANCED, value_parser = crate::units::parse_non_negative)]
    pub wavelet_threshold: Option<f32>,
}

/// The help heading of the PBGI and bake settings that rarely matter.
pub const ADVANCED: &str = "Point-based GI, advanced";

/// `--quality`: the bake's samples and patch size, set together.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Quality {
    /// 4 samples a patch, patches of 2% of the scene's diagonal.
    Draft,
    /// 16 samples a patch, patches of 1%.
    Default,
    /// 64 samples a patch, patches of 1%.
    Final,
}

impl Quality {
    /// Light samples per patch and the finest patch's side (docs/pbgi.md measures them).
    fn bake(self) -> (u32, f32) {
        match self {
            Quality::Draft => (4, 0.02),
            Quality::Default => (16, 0.01),
            Quality::Final => (64, 0.01),
        }
    }
}

fn parse_wavelet_resolution(s: &str) -> Result<usize, String> {
    match s.parse::<usize>() {
        Ok(n) if n.is_power_of_two() && n <= 32 => Ok(n),
        _ => Err(format!("{s:?}: a power of two from 1 to 32")),
    }
}

fn parse_patch_size(s: &str) -> Result<f32, String> {
    match s.parse::<f32>() {
        Ok(v) if v > 0.0 && v <= 1.0 => Ok(v),
        _ => Err(format!("{s:?}: a fraction in (0, 1]")),
    }
}

impl BakeSettings {
    pub fn params(&self, seed: u32) -> BakeParams {
        let (samples, patch_size) = self.quality.bake();
        BakeParams {
            samples: self.bake_samples.unwrap_or(samples),
            seed,
            patch_size: self.patch_size.unwrap_or(patch_size),
            bounces: self.bounces,
            wavelet: self.wavelet,
            wavelet_n: self.wavelet_resolution.unwrap_or(8),
            wavelet_threshold: self.wavelet_threshold.unwrap_or(0.01),
        }
    }

    /// Whether a glossy-map setting was given (they apply only where maps are baked).
    pub fn wavelet_given(&self) -> Option<&'static str> {
        if self.wavelet == WaveletMode::On {
            Some("--wavelet on")
        } else if self.wavelet_resolution.is_some() {
            Some("--wavelet-resolution")
        } else if self.wavelet_threshold.is_some() {
            Some("--wavelet-threshold")
        } else {
            None
        }
    }
}
