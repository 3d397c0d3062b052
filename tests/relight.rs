//! Relighting: a view precomputed once renders light sets as the path tracer does.

mod common;

use canopy::image::Image;
use common::*;
use std::path::Path;

/// The bundled Cornell box converted into `dir`, and its view precomputed at 64×64.
fn prepared(dir: &Path) -> (std::path::PathBuf, std::path::PathBuf) {
    let archive = dir.join("cbox.canopy");
    convert(&scene("cbox.glb"), &archive, None);
    let view = dir.join("cbox.relight");
    ok(&[
        "--quiet",
        "relight",
        s(&archive),
        "-o",
        s(&view),
        "--width",
        "64",
        "--height",
        "64",
    ]);
    (archive, view)
}

fn relit(view: &Path, lights: Option<&Path>, out: &Path) -> Image {
    let mut args = vec!["relight", s(view), "-o", s(out)];
    if let Some(l) = lights {
        args.extend(["--lights", s(l)]);
    }
    ok(&args);
    Image::read_exr(out).unwrap()
}

/// Light set used here: the lamp dimmed and tinted, a coloured point light added.
const SET: &str = "[[emitter]]\nmaterial = \"light\"\nstrength = 0.5\ncolor = [1.0, 0.6, 0.4]\n\
[[light]]\ntype = \"point\"\nposition = [150.0, 300.0, 200.0]\nintensity = 20000.0\ncolor = [0.5, 0.8, 1.0]\n";

#[test]
fn relit_light_sets_match_the_path_tracer() {
    let dir = tempfile::tempdir().unwrap();
    let (archive, view) = prepared(dir.path());
    let set = dir.path().join("set.toml");
    std::fs::write(&set, SET).unwrap();
    for lights in [None, Some(set.as_path())] {
        let img = relit(&view, lights, &dir.path().join("relit.exr"));
        let mut extra = vec!["--width", "64", "--height", "64"];
        if let Some(l) = lights {
            extra.extend(["--lights", s(l)]);
        }
        let (pt, _) = render(
            &archive,
            &dir.path().join("pt.exr"),
            &[&extra[..], &["--spp", "1024"]].concat(),
        );
        let (pt16, _) = render(
            &archive,
            &dir.path().join("pt16.exr"),
            &[&extra[..], &["--spp", "16", "--seed", "7"]].concat(),
        );
        // The 1024-spp mean's relative standard error is about 0.1% and the relit image's
        // (256 transfer paths a pixel, 16 light samples) about 0.3% at 64×64: 1.5% is five
        // of the difference's standard errors.
        assert_mean_within(&img, &pt, 0.015, &format!("relit, lights {lights:?}"));
        let (e, e16) = (rmse(&img, &pt), rmse(&pt16, &pt));
        assert!(
            e < e16,
            "relit RMSE {e} is not below the 16-spp path tracer's {e16} (lights {lights:?})"
        );
    }
}

#[test]
fn light_is_linear_in_the_lamps() {
    // The same view under a lamp twice as strong is the same samples' image twice over.
    let dir = tempfile::tempdir().unwrap();
    let (_, view) = prepared(dir.path());
    let set = dir.path().join("twice.toml");
    std::fs::write(&set, "[[emitter]]\nmaterial = 4\nstrength = 2\n").unwrap();
    let one = relit(&view, None, &dir.path().join("one.exr"));
    let two = relit(&view, Some(&set), &dir.path().join("two.exr"));
    let lit = one.pixels.iter().filter(|p| p[0] > 0.0).count();
    assert!(lit > one.pixels.len() / 2, "only {lit} pixels lit");
    for (a, b) in one.pixels.iter().zip(&two.pixels) {
        for c in 0..3 {
            assert!(
                (b[c] - 2.0 * a[c]).abs() <= 1e-4 * b[c].abs().max(1e-6),
                "{a:?} → {b:?}"
            );
        }
    }
}

#[test]
fn bad_relight_files_and_flags_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let (archive, view) = prepared(dir.path());
    let out = dir.path().join("x.exr");
    let bytes = std::fs::read(&view).unwrap();
    let bad = dir.path().join("bad.relight");
    std::fs::write(&bad, &bytes[..bytes.len() / 2]).unwrap();
    assert!(fails(&["relight", s(&bad), "-o", s(&out)]).contains("checksum"));
    let mut flipped = bytes.clone();
    flipped[200] ^= 1;
    std::fs::write(&bad, &flipped).unwrap();
    assert!(fails(&["relight", s(&bad), "-o", s(&out)]).contains("not a valid relight file"));
    assert!(fails(&["relight", s(&view), "-o", s(&out), "--paths", "4"])
        .contains("--paths applies when precomputing"));
    assert!(
        fails(&["relight", s(&archive), "-o", s(&view), "--lights", "x.toml"])
            .contains("--lights applies when rendering")
    );
    assert!(fails(&["relight", s(&archive), "-o", s(&out)]).contains("writes a .relight file"));
    let missing = dir.path().join("missing.toml");
    assert!(
        fails(&["relight", s(&view), "-o", s(&out), "--lights", s(&missing)])
            .contains("missing.toml")
    );
    let set = dir.path().join("set.toml");
    std::fs::write(&set, "[[emitter]]\nmaterial = \"lamp\"\n").unwrap();
    assert!(
        fails(&["relight", s(&view), "-o", s(&out), "--lights", s(&set)])
            .contains("no material \"lamp\"")
    );
    // The archive changed since the view was precomputed.
    convert(&scene("bunny_box.glb"), &archive, None);
    assert!(fails(&["relight", s(&view), "-o", s(&out)]).contains("has changed since"));
    assert!(!out.exists(), "a refused relight wrote {}", out.display());
}
