//! A short fuzz run in the default suite; the long run's command is in the README.

use canopy_tools::fuzz::mem::Counting;
use canopy_tools::fuzz::{self, Config, Target};
use std::time::Duration;

/// The heap a case may take, as the long run's default; past it the test process ends
/// (exit 4) naming the case.
#[global_allocator]
static HEAP: Counting = Counting;

fn config(seed: u64, iterations: u64, targets: Vec<Target>) -> Config {
    Config {
        seed,
        iterations,
        until: None,
        hang: Duration::from_secs(120),
        ceiling: 512 << 20,
        targets,
        trace: false,
    }
}

#[test]
fn mutated_archives_and_inputs_never_panic_or_hang() {
    let dir = tempfile::tempdir().unwrap();
    let c = config(7, 400, vec![Target::Archives, Target::Inputs]);
    let t = fuzz::run(&c, dir.path(), |_, _| {}).unwrap();
    assert!(t.failures.is_empty(), "{:#?}", t.failures);
    // Every class ran, and mutations did reach past the checks: some were refused, some
    // still rendered.
    assert!(t.cases[..9].iter().all(|&n| n > 0), "{:?}", t.cases);
    assert!(
        t.errors > 40 && t.ok > 40,
        "ok {}, errors {}",
        t.ok,
        t.errors
    );
}

/// Light stores, bakes, EXR tiles and scene files, mutated: no panic, no case past the
/// ceiling, every class run, and some mutations still accepted (they reach the decoder).
#[test]
fn mutated_side_files_never_panic_hang_or_pass_the_ceiling() {
    let dir = tempfile::tempdir().unwrap();
    let t = fuzz::run(&config(11, 180, vec![Target::Side]), dir.path(), |_, _| {}).unwrap();
    assert!(t.failures.is_empty(), "{:#?}", t.failures);
    assert!(t.cases[9..].iter().all(|&n| n > 0), "{:?}", t.cases);
    assert!(
        t.errors > 40 && t.ok > 5,
        "ok {}, errors {}",
        t.ok,
        t.errors
    );
    // The counting allocator measured every class; none came near the ceiling.
    assert!(
        t.peak_heap[9..].iter().all(|&h| h > 0 && h < 512 << 20),
        "{:?}",
        t.peak_heap
    );
}

#[test]
fn unmutated_seeds_convert_verify_and_render() {
    let dir = tempfile::tempdir().unwrap();
    let inputs = fuzz::seed_inputs();
    for main in ["s.glb", "m.obj", "a.ply", "bin.ply", "i.glb"] {
        let d = dir.path().join(main);
        std::fs::create_dir_all(&d).unwrap();
        fuzz::exercise_input(&d, &inputs, main).unwrap_or_else(|e| panic!("{main}: {e:#}"));
    }
    for (parts, raw) in fuzz::seed_archives(dir.path()).unwrap() {
        assert_eq!(parts.assemble(), raw, "reassembly must be byte-exact");
    }
}

/// The side seeds, unmutated, are read without error by everything that reads them: the
/// mutations start from files that work.
#[test]
fn unmutated_side_seeds_are_accepted() {
    use canopy_tools::fuzz::side::{self, Mutation};
    let dir = tempfile::tempdir().unwrap();
    let s = side::Seeds::new(dir.path()).unwrap();
    let h: canopy_format::bake::BakeHeader = bytemuck::pod_read_unaligned(&s.bake[..128]);
    assert!(
        h.wavelet_n > 0 && h.coef_bytes > 0,
        "the seed bake holds glossy light"
    );
    let case = dir.path().join("case");
    for m in [
        Mutation::Store(s.store.clone()),
        Mutation::Bake(s.bake.clone()),
        Mutation::Tile(s.tiles[0].clone()),
        Mutation::Scene(side::SIDE_SCENE.to_string()),
        Mutation::Map(s.hdr.clone()),
    ] {
        std::fs::create_dir_all(&case).unwrap();
        side::exercise(&s, &case, &m).unwrap_or_else(|e| panic!("{e:#}"));
        std::fs::remove_dir_all(&case).unwrap();
    }
}
