use anyhow::Result;
use canopy::inspect;
use clap::Args;
use std::path::PathBuf;

/// Summarize an archive: counts, sizes, compression, features, pages per path (and a
/// radiance file baked from it).
#[derive(Args)]
pub struct InspectArgs {
    archive: PathBuf,
    /// Decompress every page and check checksums, links, bounds and counts.
    #[arg(long)]
    verify: bool,
    /// Also check and summarize this radiance file (`canopy bake`) against the archive;
    /// with --verify every block is decoded.
    #[arg(long, value_name = "FILE")]
    radiance: Option<std::path::PathBuf>,
    /// With --verify --radiance: memory for a page and its block per worker, e.g. 256MiB
    /// (default: unlimited); a block that does not fit is an error.
    #[arg(long, value_parser = canopy::units::parse_size, requires = "radiance")]
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
    if let Some(path) = &a.radiance {
        let r = canopy_format::radiance::RadianceFile::open(path, &archive)?;
        s.radiance = Some(inspect::radiance(&archive, &r, a.verify, a.mem_budget)?);
    }
    if a.json {
        println!("{}", serde_json::to_string_pretty(&s)?);
    } else {
        print!("{s}");
    }
    Ok(())
}
