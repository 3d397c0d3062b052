//! Fuzzes Canopy in-process: mutated archives (checksums recomputed) and mutated inputs.
//!
//!     cargo run --release -p canopy-tools --bin fuzz -- --seed 1 --time 1h
//!
//! Exit status 0 when no case panicked or hung; 1 with the failing cases listed otherwise;
//! 3 when a case hung (printed with its number and seed).

use anyhow::Result;
use canopy_tools::fuzz::{self, CLASSES};
use clap::Parser;
use std::path::PathBuf;
use std::time::{Duration, Instant};

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
    let t = fuzz::run(a.seed, a.iterations, until, a.hang, dir.path(), |t, i| {
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
        "{total} cases in {:.0} s (seed {}): {} ok, {} clean errors, {} panics, 0 hangs",
        start.elapsed().as_secs_f64(),
        a.seed,
        t.ok,
        t.errors,
        t.failures.len()
    );
    for (c, n) in CLASSES.iter().zip(t.cases) {
        println!("  {n:>8}  {c}");
    }
    for f in &t.failures {
        println!("FAIL {f}");
    }
    if !t.failures.is_empty() {
        std::process::exit(1);
    }
    Ok(())
}
