//! Fuzzes Canopy in-process: mutated archives (checksums recomputed) and mutated inputs.
//!
//!     cargo run --release -p canopy-tools --bin fuzz -- --seed 1 --time 1h
//!
//! Exit status 0 when no case panicked or hung; 1 with the failing cases listed otherwise;
//! 3 when a case hung, 4 when a case's heap passed its ceiling (each printed with its
//! number and seed).

use anyhow::Result;
use canopy_tools::fuzz::mem::Counting;
use canopy_tools::fuzz::{self, Config, Target, CLASSES};
use clap::Parser;
use std::path::PathBuf;
use std::time::{Duration, Instant};

#[global_allocator]
static HEAP: Counting = Counting;

#[derive(Parser)]
#[command(about = "Fuzz archives (with checksums recomputed) and importers in-process")]
struct Args {
    /// Seed of the mutation sequence.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Cases to run.
    #[arg(long, default_value_t = u64::MAX)]
    iterations: u64,
    /// Stop after this long (e.g. 90s, 1h).
    #[arg(long, value_parser = canopy::units::parse_duration)]
    time: Option<Duration>,
    /// A case running longer than this is a hang.
    #[arg(long, default_value = "60s", value_parser = canopy::units::parse_duration)]
    hang: Duration,
    /// Heap one case may take above what was live when it began; past it the run ends
    /// (exit 4), naming the case.
    #[arg(long, default_value = "512MiB", value_parser = canopy::units::parse_size)]
    mem_ceiling: u64,
    /// What to mutate, taken in turn: archives, inputs (glTF, PLY, OBJ, MTL), side
    /// (light stores, bakes, EXR tiles, scene files).
    #[arg(
        long,
        value_enum,
        value_delimiter = ',',
        default_value = "archives,inputs,side"
    )]
    targets: Vec<Target>,
    /// Print each case's description before it runs.
    #[arg(long)]
    trace: bool,
    /// Where to put the cases' files (default: the system's temporary directory).
    #[arg(long)]
    dir: Option<PathBuf>,
}

fn main() -> Result<()> {
    let a = Args::parse();
    if a.iterations == u64::MAX && a.time.is_none() {
        anyhow::bail!("give --iterations or --time");
    }
    let dir = fuzz::work_dir(a.dir)?;
    let start = Instant::now();
    let until = a.time.map(|t| start + t);
    let mut last = Instant::now();
    let config = Config {
        seed: a.seed,
        iterations: a.iterations,
        until,
        hang: a.hang,
        ceiling: a.mem_ceiling,
        targets: a.targets,
        trace: a.trace,
    };
    let t = fuzz::run(&config, dir.path(), |t, i| {
        if last.elapsed() > Duration::from_secs(30) {
            last = Instant::now();
            eprintln!(
                "{i} cases in {:.0} s: {} ok, {} clean errors, {} failures",
                start.elapsed().as_secs_f64(),
                t.ok,
                t.errors,
                t.failures.len()
            );
        }
    })?;
    let total: u64 = t.cases.iter().sum();
    println!(
        "{total} cases in {:.0} s (seed {}): {} ok, {} clean errors, {} panics, 0 hangs, 0 over the {} ceiling",
        start.elapsed().as_secs_f64(),
        a.seed,
        t.ok,
        t.errors,
        t.failures.len(),
        canopy::units::format_size(a.mem_ceiling)
    );
    println!("     cases  peak heap  class");
    for ((c, n), heap) in CLASSES.iter().zip(t.cases).zip(t.peak_heap) {
        println!("  {n:>8}  {:>5.1} MiB  {c}", heap as f64 / 1048576.0);
    }
    for f in &t.failures {
        println!("FAIL {f}");
    }
    if !t.failures.is_empty() {
        std::process::exit(1);
    }
    Ok(())
}
