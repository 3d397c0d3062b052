use anyhow::Result;
use canopy::build::{convert, BvhQuality, ConvertOptions};
use canopy::{inspect, progress, units};
use clap::{Parser, Subcommand};
use std::path::PathBuf;

/// Canopy: an out-of-core streaming renderer for scenes bigger than the machine.
#[derive(Parser)]
#[command(version, about, long_about = None)]
struct Cli {
    /// No progress bars (they are also off when stderr is not a terminal).
    #[arg(long, global = true)]
    quiet: bool,
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Convert meshes and scenes (glTF .gltf/.glb, PLY, OBJ) into a node archive.
    ///
    /// Several inputs merge into one scene. Memory stays under --mem-budget however large
    /// the input: triangles are spilled to disk beside the output and built chunk by chunk.
    Convert {
        /// Input files.
        #[arg(required = true)]
        inputs: Vec<PathBuf>,
        /// Output archive (.canopy). It appears only once complete.
        #[arg(short, long)]
        output: PathBuf,
        /// Memory the conversion may use, e.g. 512MiB, 2GiB, 1.5G.
        #[arg(long, default_value = "2GiB", value_parser = units::parse_size)]
        mem_budget: u64,
        /// TOML scene file: camera, materials and lights for meshes that carry none.
        #[arg(long)]
        scene: Option<PathBuf>,
        /// Most nodes in one page (treelet).
        #[arg(long, default_value_t = 512, value_parser = clap::value_parser!(u16).range(3..=4096))]
        page_nodes: u16,
        /// zstd compression level for pages (1 fast .. 19 small).
        #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(i32).range(1..=22))]
        zstd_level: i32,
        /// Hierarchy build effort: `medium` (PLOC with more reinsertion, faster traversal),
        /// `fast` (about a fifth less build time), or `auto`: medium up to 8M triangles.
        #[arg(long, value_enum, default_value_t = BvhQuality::Auto)]
        bvh: BvhQuality,
        /// Also print the summary as JSON.
        #[arg(long)]
        json: bool,
    },
    /// Summarize an archive: counts, sizes, compression, features, pages per path.
    Inspect {
        archive: PathBuf,
        /// Decompress every page and check checksums, links, bounds and counts.
        #[arg(long)]
        verify: bool,
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
    },
}

fn run(cli: Cli) -> Result<()> {
    let show = progress::wanted(cli.quiet);
    match cli.cmd {
        Cmd::Convert {
            inputs,
            output,
            mem_budget,
            scene,
            page_nodes,
            zstd_level,
            bvh,
            json,
        } => {
            let opts = ConvertOptions {
                inputs,
                output: output.clone(),
                mem_budget,
                scene,
                page_nodes: page_nodes as usize,
                zstd_level,
                bvh,
                progress: show,
            };
            let r = convert(&opts)?;
            if json {
                println!("{}", serde_json::to_string_pretty(&r)?);
            } else {
                let per_s = r.input_triangles as f64 / r.seconds_total.max(1e-9);
                println!(
                    "{}: {} triangles -> {} nodes in {} pages ({} chunk{}), {:.2} MiB, {:.1} bytes/triangle",
                    output.display(),
                    r.input_triangles,
                    r.nodes,
                    r.pages,
                    r.chunks,
                    if r.chunks == 1 { "" } else { "s" },
                    r.archive_bytes as f64 / (1 << 20) as f64,
                    r.archive_bytes as f64 / r.input_triangles.max(1) as f64
                );
                println!(
                    "  {:.2} s (import {:.2}, partition {:.2}, build {:.2}), {:.2} M triangles/s",
                    r.seconds_total,
                    r.seconds_import,
                    r.seconds_partition,
                    r.seconds_build,
                    per_s / 1e6
                );
            }
        }
        Cmd::Inspect {
            archive,
            verify,
            json,
        } => {
            let a = canopy_format::Archive::open(&archive)?;
            let mut s = inspect::summarize(&a);
            if verify {
                inspect::verify(&a, &mut s, show)?;
            }
            if json {
                println!("{}", serde_json::to_string_pretty(&s)?);
            } else {
                inspect::print(&s);
            }
        }
    }
    Ok(())
}

fn main() {
    if let Err(e) = run(Cli::parse()) {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}
