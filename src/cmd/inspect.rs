use anyhow::Result;
use canopy::inspect;
use clap::Args;
use std::path::PathBuf;

/// Summarize an archive: counts, sizes, compression, features, pages per path (and a
/// bake file made from it).
#[derive(Args)]
pub struct InspectArgs {
    archive: PathBuf,
    /// Decompress every page and check checksums, links, bounds and counts.
    #[arg(long)]
    verify: bool,
    /// Also check and summarize this bake file (`canopy bake`) against the archive;
    /// with --verify every block is decoded.
    #[arg(long, value_name = "FILE")]
    bake: Option<std::path::PathBuf>,
    /// Refused: the bake file is given with --bake.
    #[arg(long, hide = true, value_name = "FILE", value_parser = refused_radiance)]
    radiance: Option<std::path::PathBuf>,
    /// With --verify --bake: memory for a page and its block per worker, e.g. 256MiB
    /// (default: unlimited); a block that does not fit is an error.
    #[arg(long, value_parser = canopy::units::parse_size, requires = "bake")]
    mem_budget: Option<u64>,
    /// Print JSON instead of text.
    #[arg(long)]
    json: bool,
}

pub fn run(a: InspectArgs, progress: bool) -> Result<()> {
    let archive = canopy_format::Archive::open(&a.archive)?;
    let mut s = inspect::summarize(&archive)?;
    if a.verify {
        inspect::verify(&archive, &mut s, progress)?;
    }
    if let Some(path) = &a.bake {
        let r = canopy_format::bake::BakeFile::open(path, &archive)?;
        s.bake = Some(inspect::bake(&archive, &r, a.verify, a.mem_budget)?);
    }
    if a.json {
        println!("{}", serde_json::to_string_pretty(&s)?);
    } else {
        print!("{s}");
    }
    Ok(())
}

fn refused_radiance(_: &str) -> Result<std::path::PathBuf, String> {
    Err("inspect takes the bake file as --bake FILE".into())
}
