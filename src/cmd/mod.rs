//! The command line: one module per subcommand, each a function over its parsed arguments;
//! what they print is the `Display` of the library's result types.

mod assemble;
mod bake;
mod compare;
mod convert;
mod inspect;
mod relight;
mod render;
mod sweep;

use anyhow::Result;
use canopy::integrator::cone::ConeSettings;
use canopy::integrator::edge::{EdgeSettings, DEFAULT_EDGE_RAYS, PBGI_EDGE_RAYS};
use canopy::integrator::pbgi::PbgiSettings;
use canopy::integrator::{Kind, Settings};
use canopy::light::sky::SkyOptions;
use canopy::render::{EnvOptions, EnvSource};
use canopy::texture::TextureFilter;
use canopy::units;
use clap::parser::ValueSource;
use clap::{ArgMatches, Args, CommandFactory, FromArgMatches, Parser, Subcommand};
use std::path::PathBuf;

/// Canopy: an out-of-core streaming renderer for scenes bigger than the machine.
#[derive(Parser)]
#[command(version, about, long_about = None)]
pub struct Cli {
    /// No progress bars (they are also off when stderr is not a terminal).
    #[arg(long, global = true)]
    quiet: bool,
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    Convert(convert::ConvertArgs),
    Bake(bake::BakeArgs),
    Render(render::RenderArgs),
    Npp(sweep::NppArgs),
    Eval(sweep::EvalArgs),
    Compare(compare::CompareArgs),
    Inspect(inspect::InspectArgs),
    Assemble(assemble::AssembleArgs),
    Relight(relight::RelightArgs),
}

/// Render settings shared by `render`, `npp` and `eval`.
#[derive(Args, Clone)]
struct RenderSettings {
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
    /// Longest path in segments (1: only emitters seen directly); default unbounded. The
    /// cone integrator neither stores nor reads light under it: stored light stands for
    /// every bounce after its hit.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    max_depth: Option<u32>,
    /// Texture filtering: `trilinear` MIP filtering over each sample's footprint (ray
    /// differentials, or the cone's width), or `point`: the full-resolution texture at the
    /// sample's point (aliases unless many samples are taken; for checking the filter).
    #[arg(long, value_enum, default_value_t = TextureFilter::Trilinear)]
    texture_filter: TextureFilter,
    /// Most camera samples a pass takes of a pixel, more where its earlier samples
    /// scattered (pays on glossy highlights); 1 takes one [default: 1]
    #[arg(long, value_name = "M", value_parser = clap::value_parser!(u32).range(1..=64))]
    pixel_split: Option<u32>,
    #[command(flatten)]
    env: EnvArgs,
    #[command(flatten)]
    cone: ConeSettings,
    #[command(flatten)]
    pbgi: PbgiSettings,
    #[command(flatten)]
    edge: EdgeSettings,
}

/// The environment light's flags, for `render` and `bake` alike.
#[derive(Args, Clone)]
struct EnvArgs {
    /// Light from an equirectangular environment map (.exr or .hdr; +Y up, Mitsuba 3's
    /// `envmap` convention). Without it or --sky, a scene with no light source is lit by a
    /// uniform white environment, with a note saying so.
    #[arg(long, value_name = "FILE", group = "environment")]
    env: Option<PathBuf>,
    /// Light from a clear sky (Hosek–Wilkie, in Mitsuba 3's `sunsky` units) and its sun.
    #[arg(long, group = "environment")]
    sky: bool,
    /// The sun's height above the horizon in degrees, 0 to 90.
    #[arg(long, value_name = "DEG", default_value_t = 45.0, requires = "sky")]
    sun_elevation: f32,
    /// The sun's direction about +Y in degrees, from −Z toward +X (the default 135° lights
    /// the default view from its upper right).
    #[arg(
        long,
        value_name = "DEG",
        default_value_t = 135.0,
        requires = "sky",
        allow_negative_numbers = true
    )]
    sun_azimuth: f32,
    /// Place the sun by where and when instead: latitude in degrees, north positive (with
    /// --longitude and --datetime; north is −Z, east +X).
    #[arg(long, value_name = "DEG", requires_all = ["sky", "longitude", "datetime"], conflicts_with_all = ["sun_elevation", "sun_azimuth"], allow_negative_numbers = true)]
    latitude: Option<f64>,
    /// Longitude in degrees, east positive (with --latitude).
    #[arg(
        long,
        value_name = "DEG",
        requires = "latitude",
        allow_negative_numbers = true
    )]
    longitude: Option<f64>,
    /// Local time with its offset from UTC, RFC 3339: 2026-06-21T15:00:00+02:00 (with --latitude).
    #[arg(long, value_name = "TIME", requires = "latitude", value_parser = units::parse_time)]
    datetime: Option<chrono::DateTime<chrono::FixedOffset>>,
    /// Advanced: the sky's turbidity, 1 (arctic clear) to 10 (humid haze).
    #[arg(long, value_name = "T", default_value_t = 3.0, requires = "sky")]
    turbidity: f32,
    /// Advanced: the ground albedo the sky model assumes, 0 to 1 (the ground itself is not drawn).
    #[arg(long, value_name = "A", default_value_t = 0.3, requires = "sky")]
    ground_albedo: f32,
    /// Advanced: factor on the sun's radiance (0: the sky alone).
    #[arg(long, value_name = "S", default_value_t = 1.0, requires = "sky", value_parser = units::parse_non_negative)]
    sun_strength: f32,
    /// Factor on the environment's radiance (map or sky).
    #[arg(long, value_name = "S", default_value_t = 1.0, requires = "environment", value_parser = units::parse_non_negative)]
    env_strength: f32,
    /// Turns the environment (map or sky) about +Y by this many degrees.
    #[arg(
        long,
        value_name = "DEG",
        default_value_t = 0.0,
        requires = "environment",
        allow_negative_numbers = true
    )]
    env_rotate: f32,
    /// Advanced: sample the environment map's directions uniformly over the sphere instead
    /// of by its light (to measure what importance sampling gains).
    #[arg(long, requires = "env")]
    env_uniform_sampling: bool,
}

impl EnvArgs {
    fn options(&self) -> Option<EnvOptions> {
        let source = match (&self.env, self.sky) {
            (Some(path), _) => EnvSource::Map(path.clone()),
            (None, true) => EnvSource::Sky(SkyOptions {
                elevation: self.sun_elevation,
                azimuth: self.sun_azimuth,
                turbidity: self.turbidity,
                albedo: self.ground_albedo,
                sun_strength: self.sun_strength,
                place: self
                    .latitude
                    .zip(self.longitude)
                    .zip(self.datetime)
                    .map(|((lat, lon), time)| (lat, lon, time)),
            }),
            (None, false) => return None,
        };
        Some(EnvOptions {
            source,
            strength: self.env_strength,
            rotate: self.env_rotate,
            uniform_sampling: self.env_uniform_sampling,
        })
    }
}

impl RenderSettings {
    fn settings(&self, kind: Kind) -> Settings {
        match kind {
            Kind::Path => Settings::Path,
            Kind::Cone => Settings::Cone(self.cone()),
            Kind::Pbgi => Settings::Pbgi(self.pbgi()),
        }
    }

    fn cone(&self) -> ConeSettings {
        ConeSettings {
            edge_rays: self.edge.edge_rays.unwrap_or(DEFAULT_EDGE_RAYS),
            ..self.cone.clone()
        }
    }

    fn pbgi(&self) -> PbgiSettings {
        PbgiSettings {
            edge_rays: self.edge.edge_rays.unwrap_or(PBGI_EDGE_RAYS),
            ..self.pbgi.clone()
        }
    }
}

/// pbrt-v4's `ReportUnused`: a flag of an integrator that will not run is an error (exit
/// status 2) naming it, not silently ignored.
fn reject_unused(name: &str, sub: &ArgMatches, kinds: &[Kind]) {
    let flags: [(&[Kind], clap::Command); 3] = [
        (
            &[Kind::Cone],
            ConeSettings::augment_args(clap::Command::new("cone")),
        ),
        (
            &[Kind::Pbgi],
            PbgiSettings::augment_args(clap::Command::new("pbgi")),
        ),
        (
            &[Kind::Cone, Kind::Pbgi],
            EdgeSettings::augment_args(clap::Command::new("edge")),
        ),
    ];
    for (applies, cmd) in flags {
        if applies.iter().any(|k| kinds.contains(k)) {
            continue;
        }
        for arg in cmd.get_arguments() {
            if sub.value_source(arg.get_id().as_str()) == Some(ValueSource::CommandLine) {
                let flag = arg.get_long().unwrap_or_else(|| arg.get_id().as_str());
                let chosen: Vec<String> = kinds
                    .iter()
                    .map(|k| format!("{k:?}").to_lowercase())
                    .collect();
                conflict(
                    name,
                    format!(
                        "--{flag} applies to --integrator {}, not {}",
                        applies
                            .iter()
                            .map(|k| format!("{k:?}").to_lowercase())
                            .collect::<Vec<_>>()
                            .join(" or "),
                        chosen.join(", ")
                    ),
                );
            }
        }
    }
}

/// `npp` and `eval` run every integrator of `--integrators`; `--integrator` would be ignored,
/// and `--store-out` overwritten by each run.
fn reject_single_integrator(name: &str, sub: &ArgMatches) {
    // Every cone run of a sweep would write the store over the last one's.
    if sub.value_source("store_out") == Some(ValueSource::CommandLine) {
        conflict(
            name,
            "--store-out applies to canopy render (one render, one store)".into(),
        );
    }
}

/// Exits with status 2 and clap's usage error for subcommand `name`.
fn conflict(name: &str, message: String) -> ! {
    let mut cli = Cli::command();
    let cmd = cli.find_subcommand_mut(name).expect("a known subcommand");
    cmd.set_bin_name(format!("canopy {name}"));
    cmd.error(clap::error::ErrorKind::ArgumentConflict, message)
        .exit()
}

/// Parses the command line (exiting with status 2 on bad arguments) and runs it.
pub fn run() -> Result<()> {
    let matches = Cli::command().get_matches();
    let cli = Cli::from_arg_matches(&matches).unwrap_or_else(|e| e.exit());
    let show = canopy::progress::wanted(cli.quiet);
    let (name, sub) = matches.subcommand().expect("a subcommand is required");
    let budget = match &cli.cmd {
        Cmd::Render(a) => a.settings.mem_budget,
        Cmd::Npp(a) => a.settings.mem_budget,
        Cmd::Eval(a) => a.settings.mem_budget,
        Cmd::Bake(a) => a.mem_budget(),
        Cmd::Relight(_) => None,
        Cmd::Convert(_) | Cmd::Compare(_) | Cmd::Inspect(_) | Cmd::Assemble(_) => None,
    };
    if budget.is_some() {
        canopy::paging::one_arena();
    }
    match cli.cmd {
        Cmd::Convert(a) => convert::run(a, show),
        Cmd::Bake(a) => bake::run(a, show),
        Cmd::Render(a) => {
            reject_unused(name, sub, &[a.integrator]);
            render::run(a, show)
        }
        Cmd::Npp(a) => {
            reject_unused(name, sub, &a.integrators);
            reject_single_integrator(name, sub);
            sweep::npp(a, show)
        }
        Cmd::Eval(a) => {
            reject_unused(name, sub, &a.integrators);
            reject_single_integrator(name, sub);
            sweep::eval(a, show)
        }
        Cmd::Compare(a) => compare::run(a),
        Cmd::Inspect(a) => inspect::run(a, show),
        Cmd::Assemble(a) => assemble::run(a),
        Cmd::Relight(a) => relight::run(a, show),
    }
}
