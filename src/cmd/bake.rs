use anyhow::Result;
use canopy::integrator::pbgi::bake::BakeSettings;
use canopy::render::bake::{bake, BakeOptions};
use canopy::units;
use clap::Args;
use std::path::PathBuf;

/// Bake the light every node reflects, every bounce by default, into a bake file for
/// `render --integrator pbgi --bake-in`.
///
/// Leaves take light samples (light tree and shadow rays) on each triangle, then walks
/// from each patch add the further bounces; inner nodes add
/// their children's projected area and power per cube axis. Pages are baked deepest first
/// and written as they finish, so memory stays under --mem-budget. The file names the
/// archive it was baked from and is refused with any other; it appears only once complete.
#[derive(Args)]
pub struct BakeArgs {
    archive: PathBuf,
    /// Output bake file (conventionally SCENE.bake).
    #[arg(short, long)]
    output: PathBuf,
    #[command(flatten)]
    bake: BakeSettings,
    /// Seed of the light samples.
    #[arg(long, default_value_t = 0)]
    seed: u32,
    /// Memory for decoded pages, e.g. 256MiB (default: unlimited).
    #[arg(long, value_parser = units::parse_size)]
    mem_budget: Option<u64>,
    /// Worker threads (default: all cores).
    #[arg(long, value_parser = units::parse_threads)]
    threads: Option<usize>,
    /// Also print the summary as JSON.
    #[arg(long)]
    json: bool,
    /// The render's environment light, which the bake must share.
    #[command(flatten)]
    env: super::EnvArgs,
}

impl BakeArgs {
    pub fn mem_budget(&self) -> Option<u64> {
        self.mem_budget
    }
}

pub fn run(a: BakeArgs, progress: bool) -> Result<()> {
    let r = bake(&BakeOptions {
        archive: a.archive,
        output: a.output.clone(),
        bake: a.bake,
        seed: a.seed,
        mem_budget: a.mem_budget,
        threads: a.threads,
        env: a.env.options(),
        progress,
    })?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&r)?);
    } else {
        println!("{}: {r}", a.output.display());
    }
    Ok(())
}
