//! `canopy convert` in stages (`--work`, `--chunk K`, `--join`: the cluster path of
//! `tools/slurm/canopy-convert.sh`, here as separate processes without Slurm): the archive
//! is byte for byte the one a single process writes, whatever the thread count and the order
//! the chunks are built in, and missing, stale or damaged work files are refused by name.

mod common;
use common::*;
use std::path::Path;

/// Prepares `input` in `work`, builds its chunks last to first, joins; returns the chunk count.
fn staged(input: &[&str], out: &Path, work: &Path, extra: &[&str]) -> usize {
    let mut args = vec!["--quiet", "convert"];
    args.extend(input);
    args.extend(["-o", s(out), "--work", s(work)]);
    args.extend(extra);
    let said = ok(&args);
    assert!(said.contains("prepared"), "{said}");
    let chunks = chunk_count(work);
    for k in (0..chunks).rev() {
        ok(&[
            "--quiet",
            "convert",
            "--work",
            s(work),
            "--chunk",
            &k.to_string(),
        ]);
    }
    ok(&["--quiet", "convert", "--work", s(work), "--join"]);
    chunks
}

/// The chunks a conversion prepared in `work` has (its `chunk-K.tris` files).
fn chunk_count(work: &Path) -> usize {
    std::fs::read_dir(work)
        .unwrap()
        .filter(|e| {
            let name = e.as_ref().unwrap().file_name();
            name.to_string_lossy().ends_with(".tris")
        })
        .count()
}

/// Converts `input` to `out` under `budget` with `threads` threads; returns the report.
fn convert_on(threads: &str, input: &Path, out: &Path, budget: &str) -> serde_json::Value {
    let run = std::process::Command::new(env!("CARGO_BIN_EXE_canopy"))
        .args(["--quiet", "convert", s(input), "-o", s(out)])
        .args(["--mem-budget", budget, "--json"])
        .env("RAYON_NUM_THREADS", threads)
        .output()
        .unwrap();
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    serde_json::from_slice(&run.stdout).unwrap()
}

fn same_bytes(a: &Path, b: &Path, what: &str) {
    let (a, b) = (std::fs::read(a).unwrap(), std::fs::read(b).unwrap());
    assert!(a == b, "{what}: {} and {} bytes differ", a.len(), b.len());
}

#[test]
fn a_staged_conversion_writes_the_single_process_bytes() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let grid: Vec<[f32; 3]> = (0..30)
        .flat_map(|i| (0..30).map(move |j| [5.0 + 1.2 * i as f32, 0.0, 5.0 + 1.2 * j as f32]))
        .collect();
    let instanced = gpu_instanced(d, "carpet.glb", "smallbox", &grid, &vec![[0.01; 3]; 900]);
    let sponza = scene("sponza_textured/sponza_textured.gltf");
    let (showroom, bunny) = (scene("showroom.glb"), scene("bunny.ply"));
    let triangle = d.join("one.obj");
    std::fs::write(&triangle, "v 0 0 0\nv 1 0 0\nv 1 1 0\nf 1 2 3\n").unwrap();
    let cases: [(&str, Vec<&str>, &str); 4] = [
        ("showroom", vec![s(&showroom)], "98MiB"),
        ("textured sponza", vec![s(&sponza)], "128MiB"),
        (
            "instances and a mesh",
            vec![s(&instanced), s(&bunny)],
            "98MiB",
        ),
        (
            "one triangle (a leaf for a root)",
            vec![s(&triangle)],
            "98MiB",
        ),
    ];
    for (what, input, budget) in cases {
        let one = d.join("one.canopy");
        let mut args = vec!["--quiet", "convert"];
        args.extend(&input);
        args.extend(["-o", s(&one), "--mem-budget", budget]);
        ok(&args);
        let work = d.join("work");
        let two = d.join("two.canopy");
        let chunks = staged(&input, &two, &work, &["--mem-budget", budget]);
        assert!(
            chunks > 1 || input == [s(&triangle)],
            "{what}: {chunks} chunk"
        );
        same_bytes(&one, &two, what);
        assert!(!work.exists(), "{what}: the join left its work files");
    }
}

#[test]
fn the_archive_does_not_depend_on_the_thread_count() {
    let dir = tempfile::tempdir().unwrap();
    let mut outs = Vec::new();
    for threads in ["1", "2", "3"] {
        let out = dir.path().join(format!("t{threads}.canopy"));
        let report = convert_on(threads, &scene("bunny.ply"), &out, "98MiB");
        assert!(report["chunks"].as_u64().unwrap() > 1, "{report}");
        outs.push(out);
    }
    same_bytes(&outs[0], &outs[1], "1 and 2 threads");
    same_bytes(&outs[0], &outs[2], "1 and 3 threads");
}

/// Above 2²⁰ triangles the partition reads and writes the spill in two ranges at once; the
/// chunk files, and so the archive, are what one pass writes, in one process or in stages.
#[test]
fn a_spill_partitioned_in_ranges_gives_the_same_bytes() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let grid = d.join("grid.ply");
    grid_ply(&grid, 750);
    let mut outs = Vec::new();
    for threads in ["1", "2"] {
        let out = d.join(format!("t{threads}.canopy"));
        let report = convert_on(threads, &grid, &out, "256MiB");
        assert_eq!(
            report["input_triangles"].as_u64(),
            Some(1_125_000),
            "{report}"
        );
        assert!(report["chunks"].as_u64().unwrap() > 1, "{report}");
        outs.push(out);
    }
    same_bytes(&outs[0], &outs[1], "1 and 2 threads");
    let staged_out = d.join("staged.canopy");
    staged(
        &[s(&grid)],
        &staged_out,
        &d.join("work"),
        &["--mem-budget", "256MiB"],
    );
    same_bytes(&outs[0], &staged_out, "one process and stages");
    let said = ok(&["inspect", "--verify", s(&outs[0])]);
    let stored = said
        .lines()
        .find_map(|l| l.trim().strip_prefix("stored triangles"))
        .and_then(|r| r.split_whitespace().next())
        .unwrap_or_else(|| panic!("{said}"));
    assert_eq!(stored, "1125000", "every triangle stored once: {said}");
}

#[test]
fn missing_stale_or_damaged_work_files_are_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let work = d.join("work");
    let w = s(&work);
    let bunny = scene("bunny.ply");
    let out = d.join("b.canopy");
    let prepare = || {
        let said = ok(&[
            "--quiet",
            "convert",
            s(&bunny),
            "-o",
            s(&out),
            "--work",
            w,
            "--mem-budget",
            "98MiB",
        ]);
        assert!(said.contains("chunks to build"), "{said}");
    };
    let e = fails(&["convert", "--work", s(&d.join("nothing")), "--join"]);
    assert!(e.contains("no prepared conversion"), "{e}");
    prepare();
    let e = fails(&["convert", "--work", w, "--join"]);
    assert!(
        e.contains("not built yet") && e.contains("--chunk K"),
        "{e}"
    );
    let e = fails(&["convert", "--work", w, "--chunk", "999"]);
    assert!(e.contains("chunk 999 asked for"), "{e}");
    let e = fails(&["convert", "--work", w, "--chunk", "0", "-o", s(&out)]);
    assert!(e.contains("cannot be used with"), "{e}");
    let e = fails(&["convert", "--chunk", "0"]);
    assert!(e.contains("--work"), "{e}");
    let chunks = chunk_count(&work);
    for k in 0..chunks {
        ok(&["--quiet", "convert", "--work", w, "--chunk", &k.to_string()]);
    }
    // A byte of chunk 1's pages changed: its checksum refuses it, and nothing is written.
    let pages = work.join("chunk-1.pages");
    let mut bytes = std::fs::read(&pages).unwrap();
    let last = bytes.len() - 1;
    bytes[last] ^= 1;
    std::fs::write(&pages, &bytes).unwrap();
    let e = fails(&["convert", "--work", w, "--join"]);
    assert!(e.contains("chunk-1.pages") && e.contains("damaged"), "{e}");
    assert!(!out.exists());
    // Pages built before the conversion was prepared again are stale.
    let old = std::fs::read(work.join("chunk-0.pages")).unwrap();
    prepare();
    std::fs::write(work.join("chunk-0.pages"), old).unwrap();
    for k in 1..chunks {
        ok(&["--quiet", "convert", "--work", w, "--chunk", &k.to_string()]);
    }
    let e = fails(&["convert", "--work", w, "--join"]);
    assert!(
        e.contains("chunk-0.pages") && e.contains("another preparation"),
        "{e}"
    );
    assert!(!out.exists());
    // A truncated state file.
    let state = work.join("state");
    let len = std::fs::metadata(&state).unwrap().len();
    std::fs::OpenOptions::new()
        .write(true)
        .open(&state)
        .unwrap()
        .set_len(len / 2)
        .unwrap();
    let e = fails(&["convert", "--work", w, "--chunk", "0"]);
    assert!(e.contains("state"), "{e}");
}

/// A state file changed byte by byte with its checksum made to match (so only the decoding
/// and the checks after it stand between it and the stages): every chunk and the join either
/// refuse it with a message or go on; none panics or dies by a signal.
#[test]
fn a_forged_state_is_refused_or_read_never_panicked_on() {
    let dir = tempfile::tempdir().unwrap();
    let work = dir.path().join("work");
    let out = dir.path().join("t.canopy");
    let input = scene("sponza_textured/sponza_textured.gltf");
    let args = [
        "--quiet",
        "convert",
        s(&input),
        "-o",
        s(&out),
        "--work",
        s(&work),
    ];
    ok(&[&args[..], &["--mem-budget", "128MiB"]].concat());
    let chunks = chunk_count(&work);
    let keep: Vec<_> = std::fs::read_dir(&work)
        .unwrap()
        .map(|e| e.unwrap().path())
        .map(|p| (p.clone(), std::fs::read(&p).unwrap()))
        .collect();
    let state = work.join("state");
    let clean = std::fs::read(&state).unwrap();
    let head = 24..clean.len();
    let mut seed = 0x9e37_79b9_7f4a_7c15u64;
    let mut next = || {
        seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        seed >> 33
    };
    let (mut refused, mut written) = (0, 0);
    // Half the changes fall in the first 256 bytes, where the options, the chunk sizes and
    // the tables' lengths are.
    for i in 0..24 {
        for (p, b) in &keep {
            std::fs::write(p, b).unwrap();
        }
        let mut bytes = clean.clone();
        for _ in 0..1 + next() % 3 {
            let span = if i % 2 == 0 { 256 } else { head.len() };
            let at = head.start + (next() as usize % span);
            bytes[at] = next() as u8;
        }
        let sum = xxhash_rust::xxh3::xxh3_64(&bytes[24..]);
        bytes[16..24].copy_from_slice(&sum.to_le_bytes());
        std::fs::write(&state, &bytes).unwrap();
        let stages = (0..chunks).map(|k| vec!["--chunk".to_string(), k.to_string()]);
        for stage in stages.chain([vec!["--join".to_string()]]) {
            let stage: Vec<&str> = stage.iter().map(|a| a.as_str()).collect();
            let run = canopy(&[&["--quiet", "convert", "--work", s(&work)], &stage[..]].concat());
            let err = String::from_utf8_lossy(&run.stderr);
            match run.status.code() {
                Some(0) => written += (stage[0] == "--join") as u32,
                Some(1) => {
                    assert!(err.contains("error:"), "{err}");
                    refused += 1;
                    break;
                }
                code => panic!("{stage:?} on a forged state: exit {code:?}: {err}"),
            }
        }
        std::fs::create_dir_all(&work).unwrap();
    }
    eprintln!("{refused} forged states refused, {written} joined into an archive");
}
