//! In-process fuzzing on stable Rust: archives mutated *with their checksums recomputed* so the
//! damage reaches the decoder, and mutated glTF/PLY/OBJ inputs for the importers.
//!
//! Each case runs open, `--verify`, and a tiny render with the path tracer and the cone
//! integrator (archives), or a conversion (inputs). A case passes when it ends in `Ok` or a
//! clean `Err`; a panic on any thread, or a case that outlives the watchdog, is a failure.
//! Side files (light stores, bakes, EXR tiles, scene files) are mutated and read by what
//! reads them under a 64 MiB budget ([`side`]). With the counting allocator installed
//! ([`mem`]), a case whose heap passes its ceiling ends the run, named, as a hang does.

use anyhow::{Context, Result};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

pub mod archive;
pub mod input;
pub mod mem;
pub mod paged;
pub mod side;

pub use archive::*;
pub use input::*;

/// The mutation sequence: the renderer's SplitMix64, seeded apart.
pub struct Rng(canopy::sampler::Hash);
impl Rng {
    pub fn new(seed: u64) -> Rng {
        Rng(canopy::sampler::Hash::new(seed ^ 0x5EED_F022))
    }
    pub fn u64(&mut self) -> u64 {
        self.0.u64()
    }
    pub fn below(&mut self, n: usize) -> usize {
        (self.u64() % n.max(1) as u64) as usize
    }
    fn pick<'a, T>(&mut self, v: &'a [T]) -> &'a T {
        &v[self.below(v.len())]
    }
}

/// The classes of mutation, counted separately in the summary.
pub const CLASSES: [&str; 16] = [
    "archive: random bytes, checksums left stale",
    "archive: truncated or extended",
    "archive: header field, checksums recomputed",
    "archive: page-table field, checksums recomputed",
    "archive: material/camera/light/instance/texture/environment field, checksums recomputed",
    "archive: decoded page bytes (nodes, links, triangles, vertices), recompressed and rechecksummed",
    "archive: page tree rewired (DAG, cycle, shared child), rechecksummed",
    "input: glTF JSON value replaced (accessors, views, buffers, strides, types)",
    "input: PLY/OBJ/MTL/glb bytes or tokens mutated",
    "light store: header field (sizes, version, reserved), checksums recomputed",
    "light store: records edited or body replaced by a zstd bomb, checksums recomputed",
    "bake: header or block-table field, checksums recomputed",
    "bake: block bytes (nodes, pyramids, coefficients) or a zero bomb, checksums recomputed",
    "EXR tile: header window, byte or length, for assemble and compare",
    "scene file: a value replaced (cameras, materials, lights)",
    "environment map: Radiance .hdr header or scanline bytes mutated",
];

/// What a run mutates.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Target {
    Archives,
    Inputs,
    Side,
}

/// A run's settings.
pub struct Config {
    pub seed: u64,
    pub iterations: u64,
    pub until: Option<Instant>,
    /// A case running longer is a hang: the run ends with its description (exit 3).
    pub hang: Duration,
    /// Heap a case may take above what was live when it began (0: no ceiling; it holds
    /// only where the counting allocator of [`mem`] is installed): exit 4 past it.
    pub ceiling: u64,
    /// Cases take these in turn.
    pub targets: Vec<Target>,
    /// Print each case's description to stderr before it runs (to find a case that ends
    /// the process).
    pub trace: bool,
}

#[derive(Default)]
pub struct Tally {
    pub cases: [u64; CLASSES.len()],
    pub ok: u64,
    pub errors: u64,
    pub failures: Vec<String>,
    /// The most heap one case held above its start, per class (0 where not measured).
    pub peak_heap: [u64; CLASSES.len()],
}

/// Values that break naive code: zero, all ones, signs, NaN, infinities, huge and tiny.
const WORDS: [u32; 14] = [
    0,
    1,
    2,
    0xFFFF_FFFF,
    0x7FFF_FFFF,
    0x8000_0000,
    0x7FC0_0000, // NaN
    0x7F80_0000, // +inf
    0xFF80_0000, // -inf
    0xBF80_0000, // -1.0
    0x7F7F_FFFF, // f32::MAX
    0x0000_0001, // denormal
    0x0001_0000,
    0x4000_0000,
];

/// Overwrites an aligned 4-byte word (or a smaller field at its start) with a hostile value.
fn poke(bytes: &mut [u8], rng: &mut Rng) {
    if bytes.len() < 4 {
        return;
    }
    let at = rng.below(bytes.len() / 4) * 4;
    let v = match rng.below(4) {
        0 => rng.u64() as u32,
        1 => (u32::from_le_bytes(bytes[at..at + 4].try_into().expect("4 bytes")))
            .wrapping_add(rng.below(5) as u32)
            .wrapping_sub(2),
        _ => *rng.pick(&WORDS),
    };
    match rng.below(3) {
        0 => bytes[at..at + 2].copy_from_slice(&(v as u16).to_le_bytes()),
        1 => bytes[at] = v as u8,
        _ => bytes[at..at + 4].copy_from_slice(&v.to_le_bytes()),
    }
}

fn poke_record<T: bytemuck::Pod>(records: &mut [T], rng: &mut Rng) {
    if records.is_empty() {
        return;
    }
    let i = rng.below(records.len());
    poke(bytemuck::bytes_of_mut(&mut records[i]), rng);
}

/// Panics seen on any thread since `install_panic_counter`.
static PANICS: AtomicU64 = AtomicU64::new(0);

/// Counts panics on every thread (a rayon worker's or the prefetcher's included) and keeps
/// the first message.
pub fn install_panic_counter() -> Arc<Mutex<Option<String>>> {
    let first = Arc::new(Mutex::new(None));
    let keep = Arc::clone(&first);
    std::panic::set_hook(Box::new(move |info| {
        PANICS.fetch_add(1, Relaxed);
        keep.lock()
            .expect("panic message")
            .get_or_insert_with(|| info.to_string());
    }));
    first
}

/// Runs `c.iterations` cases (or until `c.until`), taking `c.targets` in turn. A case that
/// runs past `c.hang` ends the process with its description (it cannot be interrupted
/// in-process), as one past `c.ceiling` does. Returns the tally; failures list every
/// panicking case.
pub fn run(c: &Config, dir: &Path, mut log: impl FnMut(&Tally, u64)) -> Result<Tally> {
    let first_panic = install_panic_counter();
    let want = |t| c.targets.contains(&t);
    let archives = if want(Target::Archives) {
        seed_archives(dir)?
    } else {
        Vec::new()
    };
    let inputs = seed_inputs();
    let side = match want(Target::Side) {
        true => Some(side::Seeds::new(dir).context("making the side-file seeds")?),
        false => None,
    };
    let mut rng = Rng::new(c.seed);
    let mut tally = Tally::default();
    let current: Arc<Mutex<(String, Instant)>> =
        Arc::new(Mutex::new((String::new(), Instant::now())));
    let watch = Arc::clone(&current);
    let hang = c.hang;
    std::thread::spawn(move || loop {
        std::thread::sleep(Duration::from_millis(500));
        let (what, since) = watch.lock().expect("watchdog").clone();
        if !what.is_empty() && since.elapsed() > hang {
            eprintln!("HANG: case {what} ran past {hang:?}");
            std::process::exit(3);
        }
    });
    let case_dir = dir.join("case");
    let seed = c.seed;
    let mut i = 0u64;
    while i < c.iterations && c.until.is_none_or(|u| Instant::now() < u) {
        std::fs::create_dir_all(&case_dir)?;
        let before = PANICS.load(Relaxed);
        let start = |what: &str| {
            if c.trace {
                eprintln!("case {what}");
            }
            *current.lock().expect("watchdog") = (what.to_string(), Instant::now());
            *mem::CASE.lock().expect("case") = what.to_string();
            mem::begin_case(c.ceiling);
        };
        let (class, what, result) = match c.targets[i as usize % c.targets.len()] {
            Target::Archives => {
                let (parts, raw) = rng.pick(&archives);
                let (class, bytes) = mutate_archive(parts, raw, &mut rng);
                let path = case_dir.join("m.canopy");
                std::fs::write(&path, &bytes)?;
                let what = format!("{i} (seed {seed}): {}", CLASSES[class]);
                start(&what);
                let r = std::panic::catch_unwind(|| exercise_archive(&path, &case_dir));
                (class, what, r.map(|r| r.is_ok()))
            }
            Target::Inputs => {
                let k = rng.below(inputs.len());
                let (name, raw) = &inputs[k];
                let (class, bytes) = mutate_input(name, raw, &mut rng);
                let mut files = inputs.clone();
                files[k].1 = bytes;
                // Mutating a side file (MTL, image, buffer) exercises the file that reads it.
                let main = match *name {
                    "m.mtl" => "m.obj",
                    "ridges.webp" => "w.gltf",
                    "ridges.ktx2" | "bumps.bin" => "k.gltf",
                    n => n,
                };
                let what = format!("{i} (seed {seed}): {} in {name}", CLASSES[class]);
                start(&what);
                let r = std::panic::catch_unwind(|| exercise_input(&case_dir, &files, main));
                (class, what, r.map(|r| r.is_ok()))
            }
            Target::Side => {
                let s = side.as_ref().expect("side seeds");
                let (class, m) = side::mutate(s, &mut rng);
                let what = format!("{i} (seed {seed}): {}", CLASSES[class]);
                start(&what);
                let r = std::panic::catch_unwind(|| side::exercise(s, &case_dir, &m));
                (class, what, r.map(|r| r.is_ok()))
            }
        };
        let heap = mem::end_case();
        current.lock().expect("watchdog").0.clear();
        tally.cases[class] += 1;
        tally.peak_heap[class] = tally.peak_heap[class].max(heap.unwrap_or(0));
        match result {
            Ok(true) => tally.ok += 1,
            Ok(false) => tally.errors += 1,
            Err(_) => {}
        }
        if PANICS.load(Relaxed) != before {
            let msg = first_panic.lock().expect("panic message").take();
            tally
                .failures
                .push(format!("{what}: panic: {}", msg.unwrap_or_default()));
        }
        std::fs::remove_dir_all(&case_dir).ok();
        i += 1;
        log(&tally, i);
    }
    Ok(tally)
}

/// The directory for a run's files.
pub fn work_dir(base: Option<PathBuf>) -> Result<tempfile::TempDir> {
    match base {
        Some(b) => tempfile::tempdir_in(b),
        None => tempfile::tempdir(),
    }
    .context("creating the fuzz directory")
}
