use anyhow::Result;
use canopy::render::assemble::assemble;
use clap::Args;
use std::path::PathBuf;

/// Join tiles rendered with `render --crop` into the whole frame.
///
/// Every tile must come from the same archive, settings and seed (their EXR attributes say
/// so) and the tiles must cover the frame exactly once; otherwise nothing is written and
/// the error names the tiles. Frames and tiles up to 65,536 pixels a side and 2^27 pixels
/// in all; every tile's header is checked before any pixel is decoded.
#[derive(Args)]
pub struct AssembleArgs {
    /// Tile images (EXR), in any order.
    #[arg(required = true)]
    tiles: Vec<PathBuf>,
    /// The whole frame (EXR). It appears only once complete.
    #[arg(short, long)]
    output: PathBuf,
    /// Memory for the frame and one tile, e.g. 1GiB (default: unlimited); a frame that
    /// does not fit is refused before any tile is decoded.
    #[arg(long, value_parser = canopy::units::parse_size)]
    mem_budget: Option<u64>,
}

pub fn run(a: AssembleArgs) -> Result<()> {
    let r = assemble(&a.tiles, &a.output, a.mem_budget)?;
    println!("{}: {r}", a.output.display());
    Ok(())
}
