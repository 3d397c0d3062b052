//! PBGI's command-line flags.

use super::{bake, wpbgi};
use crate::integrator::edge::PBGI_EDGE_RAYS;
use std::path::PathBuf;

/// PBGI's parameters (its command-line flags, refused under another integrator).
#[derive(Clone, Debug, clap::Args)]
#[command(next_help_heading = "Point-based GI (--integrator pbgi)")]
pub struct PbgiSettings {
    /// The cut's threshold: a node is splatted whole when its bounding sphere subtends at
    /// most this many of the micro-buffer's smallest texels. Smaller is more exact and
    /// slower; at 0 the cut reaches every leaf, and leaves wider than a texel (or near
    /// the receiver) are rasterized.
    #[arg(long = "pbgi-angle", default_value_t = 1.0, value_parser = crate::units::parse_non_negative)]
    pub angle: f32,
    /// Micro-buffer texels per cube-face side (even; a power of two with
    /// --pbgi-glossy-bounce wavelet): the hemicube has 3·n² texels.
    #[arg(long = "pbgi-resolution", default_value_t = 8, value_parser = parse_resolution)]
    pub resolution: usize,
    /// `--edge-rays` (a flag of both cone and PBGI, set by the command line).
    #[arg(skip = PBGI_EDGE_RAYS)]
    pub edge_rays: u32,
    #[command(flatten)]
    pub bake: bake::BakeSettings,
    /// FPBGI (003 ch. 3): receivers of each 16×16 tile grouped into at most this many
    /// clusters (k-means on position and normal), each sharing one cut and its far splats;
    /// 0 gathers every receiver alone (plain PBGI). The thesis's 100 per 32×32 tile is 25
    /// here.
    #[arg(long = "receiver-clusters", default_value_t = 0)]
    pub clusters: usize,
    /// FPBGI's near/far test: a node is far for a whole cluster when the cluster's radius
    /// is at most this fraction of the distance to the node (r/d ≤ ε; the thesis prints
    /// the inverse, NOTES-002-003 B.2). Smaller shares less and errs less.
    #[arg(long = "cluster-far", default_value_t = 0.01, requires = "clusters", value_parser = crate::units::parse_non_negative)]
    pub far: f32,
    /// Fill the micro-buffer by tracing every texel's ray exactly, its hit reading the
    /// baked light, instead of from the cut (a final gather from the bake). On sponza at
    /// 8² it gathered 3.6× faster and found 0.96 of the indirect light the path tracer
    /// does, where the cut found 0.84 (docs/pbgi.md).
    #[arg(long = "pbgi-rays", conflicts_with_all = ["angle", "clusters", "far", "wavelet", "wavelet_resolution", "wavelet_threshold"])]
    pub rays: bool,
    /// Rays sampled from a receiver's rough specular lobes for its glossy bounce, their
    /// light averaged, each paired with a light sample for its direct light (MIS): the
    /// bounce split, since the micro-buffer is too coarse to gather lobes of α 0.1. On the
    /// showroom at 1,024 spp, RMSE² × time 18% lower with 2 than with 1, 28% with 3 or 4;
    /// at 60 s 2 and 3 are even (docs/pbgi.md). K above 1 is an error on a scene with no
    /// rough metal or rough dielectric [default: 2 where there is one]
    #[arg(long = "pbgi-glossy-rays", value_name = "K", value_parser = clap::value_parser!(u32).range(1..=16))]
    pub glossy_rays: Option<u32>,
    /// How receivers with rough specular lobes (rough metals, glossy coats, rough
    /// dielectrics) take their reflected glossy bounce (a dielectric's transmission keeps
    /// its lobe rays): `rays`, the exact lobe rays above; `wavelet`, WPBGI (000 §3.2-3.3):
    /// the cut into a micro-buffer refined where the BRDF varies (down to 64² a face) and
    /// the product of its Haar coefficients with the BRDF's, tabulated per outgoing
    /// direction (002 §4.2). Under --pbgi-rays each leaf's ray is traced instead of the
    /// cut (their hits read the diffuse bake, as texel rays do, so no glossy maps are
    /// baked). A pixel's surface gathers at every 8th sample (at most --pbgi-reuse), its
    /// samples taking the mean of its gathers. On the showroom it has 7.6x the squared
    /// error of `rays` at 20 s. `cache`: WPBGI's gathers kept as radiance records shared
    /// between pixels (002 §4.3; needs --pbgi-cache), placed where a record covers its 8
    /// neighbouring pixels and refined between passes, each sample taking its own BRDF
    /// product with them; receivers no record covers take the exact lobe rays. On the
    /// showroom 0.91x the squared error of `rays` at 20 s, 3.2-3.6x the path tracer as the
    /// issue's bar words it; on room_glossy 1.03x (docs/pbgi.md). Not with
    /// --receiver-clusters; `wavelet` and `cache` are errors on a scene with no rough
    /// metal or rough dielectric
    #[arg(
        long = "pbgi-glossy-bounce",
        value_name = "HOW",
        default_value = "rays",
        conflicts_with = "clusters"
    )]
    pub glossy_bounce: wpbgi::GlossyBounce,
    /// WPBGI's BRDF tables drop Haar coefficients below this fraction of an entry's L²
    /// norm; the adaptive micro-buffer splits a texel while the table keeps one inside it.
    /// Smaller is more exact and gathers more leaves; at 0 every texel where the BRDF
    /// varies at all is split down to 64² [default: 0.01; only with
    /// --pbgi-glossy-bounce wavelet or cache]
    #[arg(long = "pbgi-brdf-threshold", value_name = "T", value_parser = crate::units::parse_non_negative)]
    pub brdf_threshold: Option<f32>,
    /// WPBGI's light importance F_l (000 §3.2): the BRDF alone refines the adaptive
    /// micro-buffer to 16² a face; past that a leaf splits where the BRDF varies only
    /// while its incident luminance, halved per level past 8², exceeds γ times the
    /// hemisphere's mean, and the new leaves are filled by traversing again the nodes the
    /// split one held (or by their own rays). 0 turns it off: the BRDF refines to 64² at
    /// once. At 20 s, γ = 1 (000's "typically") had 1.40× the squared error of 0 on the
    /// showroom and 1.37× on room_glossy, 0.3 1.07× and 1.35× (docs/pbgi.md)
    /// [default: 0; only with --pbgi-glossy-bounce wavelet or cache]
    #[arg(long = "pbgi-light-importance", value_name = "GAMMA", value_parser = crate::units::parse_non_negative)]
    pub light_gamma: Option<f32>,
    /// Most (light sample, lobe ray) pairs for direct light, and most rays for the glossy
    /// bounce, one glossy receiver takes: each pixel's count grows with the root of the
    /// spread its earlier samples' first two pairs (rays) showed, relative to the image's
    /// noise (`split.rs`), so the edges of highlights take many and the rest K. On the
    /// showroom at 60 s it lowered RMSE² × time by a third (docs/pbgi.md). Under
    /// `--pixel-split` above 1 (PBGI's default) only the bounce's rays split. K turns it off;
    /// above K it needs K of at least 2, and a rough metal or rough dielectric
    /// [default: 32 where there is one]
    #[arg(long = "pbgi-split", value_name = "N", value_parser = clap::value_parser!(u32).range(1..=32))]
    pub split: Option<u32>,
    /// Most samples per gather: each surface of a pixel (normal within 14°, within a
    /// pixel's width of its plane; up to 8 a pixel) gathers at every R-th sample landing
    /// on it (at the pixel's phase), or more often where its first gathers scatter (a
    /// period of √(v̄ c_g / (s² c_s)) samples, v̄ and c_s a sample's variance and cost, s²
    /// and c_g a gather's), and the pixel's first surface also at its first sample;
    /// its samples take the mean irradiance of all its gathers (of the surface whose
    /// normal is closest while it has none, or past 8 surfaces), added once the render
    /// ends so that every gather weighs the same (003 ch. 2 gathers once per
    /// micropolygon, not per pixel sample). 1 gathers at every sample.
    #[arg(long = "pbgi-reuse", value_name = "R", default_value_t = 64, value_parser = clap::value_parser!(u32).range(1..))]
    pub reuse: u32,
    /// The irradiance cache's error bound a (0: off). Before the first pass, gathers are
    /// placed coarse to fine over the pixels where earlier ones leave a pixel's first hit
    /// uncovered; a receiver then reads every gather within
    /// ε = |x − p|/R + √(1 − n·n') < a of it (R: the smaller of the gather's harmonic mean
    /// distance and a light-weighted one, 1 to 4 pixels over a), and gathers alone
    /// (`--pbgi-reuse`) only where none is. Between
    /// passes the records whose next gather lowers the image's error more per ray than
    /// more samples would take one, and gathers at covered pixels (2% of the rays) become
    /// records where they differ from the cache by more than two standard deviations; a
    /// receiver with a surface over it nearer than the records' reach gathers alone.
    /// Smaller is more exact and gathers more.
    #[arg(long = "pbgi-cache", value_name = "A", default_value_t = 0.3, value_parser = parse_cache)]
    pub cache: f32,
    /// Baked light from `canopy bake` (default: bake before the first pass, counted in the
    /// render time, into an unnamed scratch file).
    #[arg(long = "bake-in", value_name = "FILE", conflicts_with_all = ["bake_samples", "patch_size", "bounces"])]
    pub bake_in: Option<PathBuf>,
    /// Refused: the bake file is given with --bake-in.
    #[arg(long, hide = true, value_name = "FILE", value_parser = refused_radiance)]
    pub radiance: Option<PathBuf>,
    /// Refused: every integrator's pixel split is --pixel-split.
    #[arg(long = "pbgi-pixel-split", hide = true, value_name = "M", value_parser = refused_pixel_split)]
    pub pbgi_pixel_split: Option<u32>,
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
