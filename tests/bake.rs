//! `canopy bake` and the bake file: the same light as a bake inside the render, under
//! any memory budget; refused with another archive, truncated or corrupt; bad input gets
//! a clear error and leaves no file.

mod common;
use common::*;
use std::path::{Path, PathBuf};

fn bunny_box(dir: &Path) -> PathBuf {
    let arc = dir.join("b.canopy");
    convert(&scene("bunny_box.glb"), &arc, None);
    arc
}

fn bake(arc: &Path, out: &Path, extra: &[&str]) -> serde_json::Value {
    let stdout = ok(&[
        &["--quiet", "bake", s(arc), "-o", s(out), "--json"][..],
        extra,
    ]
    .concat());
    serde_json::from_str(&stdout).unwrap()
}

const SMALL: [&str; 6] = ["--width", "24", "--height", "24", "--spp", "2"];

/// A render that reads the bake from a file makes the image a render that bakes for
/// itself makes (same seed), and a bake under a budget far below the archive's decoded
/// size writes the same bytes as one without.
#[test]
fn a_baked_file_gives_the_in_process_image_and_a_budget_changes_no_byte() {
    let dir = tempfile::tempdir().unwrap();
    let arc = bunny_box(dir.path());
    let (free, tight) = (dir.path().join("a.radiance"), dir.path().join("b.radiance"));
    let r = bake(&arc, &free, &[]);
    assert!(r["pages"].as_u64().unwrap() > 10 && r["light_samples"].as_u64().unwrap() > 0);
    let r = bake(&arc, &tight, &["--mem-budget", "5MiB", "--threads", "2"]);
    assert!(r["pages_evicted"].as_u64().unwrap() > 0, "{r}");
    assert_eq!(
        std::fs::read(&free).unwrap(),
        std::fs::read(&tight).unwrap()
    );

    let pbgi = [&SMALL[..], &["--integrator", "pbgi"]].concat();
    let (own, _) = render(&arc, &dir.path().join("own.exr"), &pbgi);
    let (read, stats) = render(
        &arc,
        &dir.path().join("read.exr"),
        &[&pbgi[..], &["--bake-in", s(&free)]].concat(),
    );
    assert_eq!(stats["bake_samples"], 0, "the render baked again");
    assert_eq!(rmse(&own, &read), 0.0);
    assert_eq!(own.mean(), read.mean());
}

/// The light rides in the pages: under a budget that evicts, the image is the same.
#[test]
fn baked_light_pages_with_the_nodes_under_a_budget() {
    let dir = tempfile::tempdir().unwrap();
    let arc = bunny_box(dir.path());
    let rad = dir.path().join("a.radiance");
    bake(&arc, &rad, &[]);
    let pbgi = [&SMALL[..], &["--integrator", "pbgi", "--bake-in", s(&rad)]].concat();
    let (free, _) = render(&arc, &dir.path().join("free.exr"), &pbgi);
    let (tight, stats) = render(
        &arc,
        &dir.path().join("tight.exr"),
        &[&pbgi[..], &["--mem-budget", "4MiB", "--threads", "1"]].concat(),
    );
    assert!(stats["pages_evicted"].as_u64().unwrap() > 0, "{stats}");
    assert_eq!(rmse(&free, &tight), 0.0);
}

/// Glossy light (room_glossy's metal bunnies and silver plinth) rides in the file as Haar
/// coefficients: `inspect` counts them, a render reading the file makes the in-process
/// image, and under a budget that evicts pages the image does not change.
#[test]
fn glossy_coefficients_round_trip_through_the_file_and_the_budget() {
    let dir = tempfile::tempdir().unwrap();
    let arc = dir.path().join("g.canopy");
    convert(&scene("room_glossy.glb"), &arc, None);
    let rad = dir.path().join("g.radiance");
    bake(&arc, &rad, &["--wavelet-resolution", "4"]);
    let info: serde_json::Value = serde_json::from_str(&ok(&[
        "inspect",
        s(&arc),
        "--bake",
        s(&rad),
        "--verify",
        "--json",
    ]))
    .unwrap();
    let r = &info["bake"];
    assert_eq!(r["wavelet_resolution"], 4, "{r}");
    assert!(r["coefficient_bytes"].as_u64().unwrap() > 0, "{r}");

    let pbgi = [
        &SMALL[..],
        &["--integrator", "pbgi", "--pbgi-gather", "cut"],
    ]
    .concat();
    let (own, _) = render(
        &arc,
        &dir.path().join("own.exr"),
        &[&pbgi[..], &["--wavelet-resolution", "4"]].concat(),
    );
    let read = [&pbgi[..], &["--bake-in", s(&rad)]].concat();
    let (free, _) = render(&arc, &dir.path().join("free.exr"), &read);
    assert_eq!(rmse(&own, &free), 0.0);
    let (tight, stats) = render(
        &arc,
        &dir.path().join("tight.exr"),
        &[&read[..], &["--mem-budget", "40MiB", "--threads", "1"]].concat(),
    );
    assert!(stats["pages_evicted"].as_u64().unwrap() > 0, "{stats}");
    assert_eq!(rmse(&free, &tight), 0.0);
}

#[test]
fn a_bake_is_refused_with_another_archive() {
    let dir = tempfile::tempdir().unwrap();
    let arc = bunny_box(dir.path());
    let other = dir.path().join("c.canopy");
    convert(&scene("cbox.glb"), &other, None);
    let rad = dir.path().join("c.radiance");
    bake(&other, &rad, &[]);
    let err = fails(
        &[
            &["render", s(&arc), "-o", s(&dir.path().join("x.exr"))][..],
            &SMALL,
            &["--integrator", "pbgi", "--bake-in", s(&rad)],
        ]
        .concat(),
    );
    assert!(
        err.contains("baked for a different archive") && err.contains(s(&rad)),
        "{err}"
    );
}

/// A bake records the environment it was lit by: read by a render under the same map,
/// strength and rotation it gives that render's image; under another map, another
/// rotation or none, it is refused by name.
#[test]
fn a_bake_is_refused_under_another_environment() {
    let dir = tempfile::tempdir().unwrap();
    let arc = bunny_box(dir.path());
    let sky = scene("env/sky.hdr");
    let rad = dir.path().join("sky.radiance");
    bake(&arc, &rad, &["--env", s(&sky)]);
    let pbgi = [&SMALL[..], &["--integrator", "pbgi", "--env", s(&sky)]].concat();
    let (own, _) = render(&arc, &dir.path().join("own.exr"), &pbgi);
    let with = [&pbgi[..], &["--bake-in", s(&rad)]].concat();
    let (read, _) = render(&arc, &dir.path().join("read.exr"), &with);
    assert_eq!(rmse(&own, &read), 0.0);
    let out = dir.path().join("x.exr");
    let render_args = |extra: &[&'static str]| -> Vec<String> {
        [
            &["render", s(&arc), "-o", s(&out)][..],
            &SMALL,
            &["--integrator", "pbgi", "--bake-in", s(&rad)],
            extra,
        ]
        .concat()
        .into_iter()
        .map(String::from)
        .collect()
    };
    let run = |extra: &[&'static str], more: &[&str]| {
        let mut a = render_args(extra);
        a.extend(more.iter().map(|m| m.to_string()));
        fails(&a.iter().map(String::as_str).collect::<Vec<_>>())
    };
    let turned = run(&["--env-rotate", "90"], &["--env", s(&sky)]);
    assert!(
        turned.contains("baked under another environment") && turned.contains(s(&rad)),
        "{turned}"
    );
    let none = run(&[], &[]);
    assert!(none.contains("baked under another environment"), "{none}");
    let plain = dir.path().join("plain.radiance");
    bake(&arc, &plain, &[]);
    let lit = fails(
        &[
            &["render", s(&arc), "-o", s(&out)][..],
            &SMALL,
            &[
                "--integrator",
                "pbgi",
                "--bake-in",
                s(&plain),
                "--env",
                s(&sky),
            ],
        ]
        .concat(),
    );
    assert!(lit.contains("with no environment light"), "{lit}");
}

/// Every truncation and a flipped byte anywhere (header, blocks, block table) is refused
/// with an error naming the file, when opened or when its page is read.
#[test]
fn a_truncated_or_corrupt_bake_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let arc = bunny_box(dir.path());
    let rad = dir.path().join("a.radiance");
    bake(&arc, &rad, &[]);
    let good = std::fs::read(&rad).unwrap();
    let bad = dir.path().join("bad.radiance");
    let out = dir.path().join("x.exr");
    let try_render = |bytes: &[u8], what: &str| {
        std::fs::write(&bad, bytes).unwrap();
        let err = fails(
            &[
                &["render", s(&arc), "-o", s(&out)][..],
                &["--width", "8", "--height", "8", "--spp", "1"],
                &["--integrator", "pbgi", "--bake-in", s(&bad)],
            ]
            .concat(),
        );
        assert!(err.contains(s(&bad)), "{what}: {err}");
    };
    let n = good.len();
    for len in [0, 7, 8, 100, 128, 129, n / 2, n - 32, n - 1] {
        try_render(&good[..len], &format!("truncated to {len}"));
    }
    let mut longer = good.clone();
    longer.push(0);
    try_render(&longer, "one byte appended");
    for at in [0, 9, 20, 60, 127, 128, 200, n / 2, n - 40, n - 1] {
        let mut b = good.clone();
        b[at] ^= 0x10;
        try_render(&b, &format!("byte {at} flipped"));
    }
    assert!(!out.exists());
}

#[test]
fn bake_refuses_bad_input_and_leaves_no_file() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("o.radiance");
    let missing = dir.path().join("missing.canopy");
    let err = fails(&["bake", s(&missing), "-o", s(&out)]);
    assert!(err.contains(s(&missing)), "{err}");
    let junk = dir.path().join("junk.canopy");
    std::fs::write(&junk, vec![7u8; 4096]).unwrap();
    let err = fails(&["bake", s(&junk), "-o", s(&out)]);
    assert!(err.contains("not a Canopy archive"), "{err}");
    let arc = bunny_box(dir.path());
    let mut bytes = std::fs::read(&arc).unwrap();
    bytes.truncate(bytes.len() / 2);
    let half = dir.path().join("half.canopy");
    std::fs::write(&half, &bytes).unwrap();
    let err = fails(&["bake", s(&half), "-o", s(&out)]);
    assert!(err.contains(s(&half)), "{err}");
    assert!(!out.exists());
    let err = fails(&["bake", s(&arc), "-o", s(&arc)]);
    assert!(err.contains("overwrite the archive"), "{err}");
    let nowhere = dir.path().join("no/such/dir/o.radiance");
    fails(&["bake", s(&arc), "-o", s(&nowhere)]);
    assert!(!nowhere.exists());
    let err = fails(&["bake", s(&arc), "-o", s(&out), "--mem-budget", "1KiB"]);
    assert!(err.contains("--mem-budget"), "{err}");
    assert!(!out.exists());
    assert_eq!(
        std::fs::read_dir(dir.path()).unwrap().count(),
        3,
        "a temporary was left behind"
    );
}

/// The bake file is given to a render with `--bake-in` and to `inspect` with `--bake`; the
/// flag `--radiance` is refused, and the error names the flag to use.
#[test]
fn the_radiance_flag_is_refused_naming_the_bake_flags() {
    let dir = tempfile::tempdir().unwrap();
    let arc = bunny_box(dir.path());
    let rad = dir.path().join("a.bake");
    bake(&arc, &rad, &[]);
    let out = dir.path().join("o.exr");
    let render = ["render", s(&arc), "-o", s(&out), "--integrator", "pbgi"];
    let err = fails(&[&render[..], &["--radiance", s(&rad)]].concat());
    assert!(err.contains("--bake-in FILE"), "{err}");
    assert!(!out.exists());
    let err = fails(&["inspect", s(&arc), "--radiance", s(&rad)]);
    assert!(err.contains("--bake FILE"), "{err}");
    ok(&[&render[..], &SMALL[..], &["--bake-in", s(&rad)]].concat());
    ok(&["inspect", s(&arc), "--bake", s(&rad)]);
}
