//! A short fuzz run in the default suite; the long run's command is in the README.

use canopy_tools::fuzz;
use std::time::Duration;

#[test]
fn mutated_archives_and_inputs_never_panic_or_hang() {
    let dir = tempfile::tempdir().unwrap();
    let t = fuzz::run(
        7,
        400,
        None,
        Duration::from_secs(120),
        dir.path(),
        |_, _| {},
    )
    .unwrap();
    assert!(t.failures.is_empty(), "{:#?}", t.failures);
    // Every class ran, and mutations did reach past the checks: some were refused, some
    // still rendered.
    assert!(t.cases.iter().all(|&n| n > 0), "{:?}", t.cases);
    assert!(
        t.errors > 40 && t.ok > 40,
        "ok {}, errors {}",
        t.ok,
        t.errors
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
