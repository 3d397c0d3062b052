use anyhow::Result;
use canopy::render::assemble::assemble;
use clap::Args;
use std::path::PathBuf;

/// Join tiles rendered with `render --crop` into the whole frame.
///
/// Every tile must come from the same archive, settings and seed (their EXR attributes say
/// so) and the tiles must cover the frame exactly once; otherwise nothing is written and
/// the error names the tiles.
#[derive(Args)]
pub struct AssembleArgs {
    /// Tile images (EXR), in any order.
    #[arg(required = true)]
    tiles: Vec<PathBuf>,
    /// The whole frame (EXR). It appears only once complete.
    #[arg(short, long)]
    output: PathBuf,
}

pub fn run(a: AssembleArgs) -> Result<()> {
    let r = assemble(&a.tiles, &a.output)?;
    println!("{}: {r}", a.output.display());
    Ok(())
}
