//! Frames rendered as tiles (`render --crop`) and joined by `canopy assemble`.

mod common;
use canopy::image::Image;
use common::*;
use std::path::{Path, PathBuf};

/// Renders `archive` at 64×48, 4 spp, seed 9, the window `crop` (x0,x1,y0,y1) if any.
fn tile(archive: &Path, out: &Path, crop: Option<&str>, spp: &str) -> PathBuf {
    let mut args = vec![
        "--quiet",
        "render",
        s(archive),
        "-o",
        s(out),
        "--width",
        "64",
        "--height",
        "48",
        "--spp",
        spp,
        "--seed",
        "9",
    ];
    if let Some(c) = crop {
        args.extend(["--crop", c]);
    }
    ok(&args);
    out.to_path_buf()
}

/// Path tracer: tiles of uneven sizes, assembled, are the single-process image bit for
/// bit; each tile's EXR places its data window in the 64×48 display window.
#[test]
fn assembled_tiles_are_the_whole_render_bit_for_bit() {
    let dir = tempfile::tempdir().unwrap();
    let arc = dir.path().join("cbox.canopy");
    convert(&scene("cbox.glb"), &arc, None);
    let whole = tile(&arc, &dir.path().join("whole.exr"), None, "4");
    let crops = ["0,23,0,17", "23,64,0,17", "0,41,17,48", "41,64,17,48"];
    let tiles: Vec<PathBuf> = crops
        .iter()
        .enumerate()
        .map(|(i, c)| tile(&arc, &dir.path().join(format!("t{i}.exr")), Some(c), "4"))
        .collect();
    let (t1, f1) = Image::read_exr_framed(&tiles[1]).unwrap();
    assert_eq!(
        (t1.width, t1.height, f1.origin, f1.display),
        (41, 17, [23, 0], [64, 48])
    );
    let full = dir.path().join("full.exr");
    let mut args = vec!["assemble"];
    args.extend(tiles.iter().rev().map(|t| s(t)));
    args.extend(["-o", s(&full)]);
    ok(&args);
    let (a, b) = (
        Image::read_exr(&full).unwrap(),
        Image::read_exr(&whole).unwrap(),
    );
    assert_eq!((a.width, a.height), (64, 48));
    assert!(
        a.pixels == b.pixels,
        "the assembled frame differs from the whole render"
    );
}

/// A missing, duplicated, overlapping or foreign tile, one with other settings, another
/// seed or another frame size, a gap or a truncated file: a clear error naming the tile,
/// exit status 1, no output.
#[test]
fn bad_tile_sets_are_refused_and_write_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (arc, other) = (d.join("cbox.canopy"), d.join("bunny.canopy"));
    convert(&scene("cbox.glb"), &arc, None);
    convert(&scene("bunny_box.glb"), &other, None);
    let top = tile(&arc, &d.join("top.exr"), Some("0,64,0,24"), "2");
    let bottom = tile(&arc, &d.join("bottom.exr"), Some("0,64,24,48"), "2");
    let wide = tile(&arc, &d.join("wide.exr"), Some("0,64,20,48"), "2");
    let foreign = tile(&other, &d.join("foreign.exr"), Some("0,64,24,48"), "2");
    let more = tile(&arc, &d.join("more.exr"), Some("0,64,24,48"), "3");
    let other_tile = |name: &str, extra: &[&str]| {
        let out = d.join(name);
        let base = ["--quiet", "render", s(&arc), "-o", s(&out), "--spp", "2"];
        ok(&[&base[..], extra].concat());
        out
    };
    let seeded = other_tile(
        "seeded.exr",
        &[
            "--width",
            "64",
            "--height",
            "48",
            "--seed",
            "7",
            "--crop",
            "0,64,24,48",
        ],
    );
    let taller = other_tile(
        "taller.exr",
        &[
            "--width",
            "64",
            "--height",
            "50",
            "--seed",
            "9",
            "--crop",
            "0,64,24,50",
        ],
    );
    let cut = d.join("cut.exr");
    let bytes = std::fs::read(&bottom).unwrap();
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    let (out, nope) = (d.join("out.exr"), d.join("nope.exr"));
    let cases: [(&str, Vec<&Path>, &str); 9] = [
        ("missing", vec![&top, &nope], "nope.exr: no such file"),
        ("duplicated", vec![&top, &top, &bottom], "given twice"),
        ("overlapping", vec![&top, &wide], "overlap at pixel (0, 20)"),
        ("gap", vec![&top], "uncovered, the first at (0, 24)"),
        ("foreign", vec![&top, &foreign], "from another archive"),
        ("other settings", vec![&top, &more], "with other settings"),
        ("another seed", vec![&top, &seeded], "with another seed"),
        (
            "another frame",
            vec![&top, &taller],
            "taller.exr: a 64x50 frame",
        ),
        (
            "truncated",
            vec![&top, &cut],
            "cut.exr: not a readable OpenEXR",
        ),
    ];
    for (what, tiles, expect) in cases {
        let mut args = vec!["assemble"];
        args.extend(tiles.iter().map(|t| s(t)));
        args.extend(["-o", s(&out)]);
        let out_ = canopy(&args);
        let err = String::from_utf8_lossy(&out_.stderr);
        assert_eq!(out_.status.code(), Some(1), "{what}: {err}");
        assert!(err.contains(expect), "{what}: expected '{expect}' in {err}");
        assert!(!out.exists(), "{what}: an output was written");
    }
}

/// The cone integrator's light store: a pre-pass writes it, a render reads it and keeps
/// adding (its own store, written out, holds at least what it read); a store from another
/// archive, another --cone-samples, or truncated is refused by name, exit 1, no image.
#[test]
fn light_stores_carry_over_and_bad_ones_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (arc, other) = (d.join("cbox.canopy"), d.join("bunny.canopy"));
    convert(&scene("cbox.glb"), &arc, None);
    convert(&scene("bunny_box.glb"), &other, None);
    let cone = |archive: &Path, out: &str, samples: &str, extra: &[&str]| {
        let mut args = vec![
            "render",
            s(archive),
            "-o",
            "",
            "--integrator",
            "cone",
            "--width",
            "32",
            "--height",
            "32",
            "--spp",
            "2",
            "--cone-samples",
            samples,
        ];
        let out = d.join(out);
        args[3] = s(&out);
        args.extend(extra);
        (canopy(&args), out)
    };
    let (first, second) = (d.join("first.store"), d.join("second.store"));
    let (run, _) = cone(&arc, "pre.exr", "64", &["--store-out", s(&first)]);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let both = ["--store-in", s(&first), "--store-out", s(&second)];
    let (run, _) = cone(&arc, "next.exr", "64", &both);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    // Every key of the first store is in the second, with at least its count: the second
    // render started from the first's light (FORMAT.md: 64-byte records after the 128-byte
    // header, `key u64` at 0 and `n u32` at 24). Started afresh, some counts would fall.
    let counts = |p: &Path| {
        let b = std::fs::read(p).unwrap();
        let raw = zstd::decode_all(&b[128..]).unwrap();
        raw.chunks_exact(64)
            .map(|r| {
                let key = u64::from_le_bytes(r[..8].try_into().unwrap());
                (key, u32::from_le_bytes(r[24..28].try_into().unwrap()))
            })
            .collect::<std::collections::HashMap<u64, u32>>()
    };
    let (a, b) = (counts(&first), counts(&second));
    assert!(!a.is_empty() && b.len() >= a.len());
    for (key, n) in &a {
        assert!(
            b.get(key).is_some_and(|m| m >= n),
            "key {key}: {n} then {:?}",
            b.get(key)
        );
    }
    let (sa, sb): (u64, u64) = (
        a.values().map(|&n| n as u64).sum(),
        b.values().map(|&n| n as u64).sum(),
    );
    assert!(sb > sa, "the second render added samples: {sa} then {sb}");
    let cut = d.join("cut.store");
    let bytes = std::fs::read(&first).unwrap();
    std::fs::write(&cut, &bytes[..bytes.len() - 9]).unwrap();
    for (what, archive, store, samples, expect) in [
        (
            "another archive",
            &other,
            &first,
            "64",
            "belongs to another archive",
        ),
        ("truncated", &arc, &cut, "64", "truncated or corrupt"),
        (
            "another limit",
            &arc,
            &first,
            "32",
            "stored under --cone-samples 64",
        ),
    ] {
        let (run, out) = cone(archive, "bad.exr", samples, &["--store-in", s(store)]);
        let err = String::from_utf8_lossy(&run.stderr);
        assert_eq!(run.status.code(), Some(1), "{what}: {err}");
        assert!(
            err.contains(expect) && err.contains(s(store)),
            "{what}: {err}"
        );
        assert!(!out.exists(), "{what}: an image was written");
    }
}

/// Mean over a row of `a − b` (channel mean), per row.
fn row_means(a: &Image, b: &Image) -> Vec<f64> {
    (0..a.height as usize)
        .map(|y| {
            let w = a.width as usize;
            (0..w)
                .map(|x| {
                    let (p, q) = (a.pixels[y * w + x], b.pixels[y * w + x]);
                    (0..3).map(|c| (p[c] - q[c]) as f64).sum::<f64>() / 3.0
                })
                .sum::<f64>()
                / w as f64
        })
        .collect()
}

/// Cone integrator, sponza as 8 tiles of 16 rows against the same frame in one process:
/// at the tile borders the rows' mean difference jumps no more than between interior
/// rows (within 2×). A tile that found lamp silhouettes at its border rows from its own
/// pixels only (its edge-ray mask) would show a seam: with seed 6, border jumps 3.6× the
/// interior's.
#[test]
fn cone_tiles_show_no_seam_at_their_borders() {
    let dir = tempfile::tempdir().unwrap();
    let arc = dir.path().join("sponza.canopy");
    convert(&scene("sponza.glb"), &arc, None);
    let render = |out: &Path, crop: Option<String>| {
        let mut args = vec![
            "--quiet",
            "render",
            s(&arc),
            "-o",
            s(out),
            "--integrator",
            "cone",
            "--width",
            "128",
            "--height",
            "128",
            "--spp",
            "4",
            "--seed",
            "6",
        ];
        let crop = crop.unwrap_or_default();
        if !crop.is_empty() {
            args.extend(["--crop", &crop]);
        }
        ok(&args);
        out.to_path_buf()
    };
    let tiles: Vec<PathBuf> = (0..8)
        .map(|i| {
            let out = dir.path().join(format!("t{i}.exr"));
            render(&out, Some(format!("0,128,{},{}", 16 * i, 16 * (i + 1))))
        })
        .collect();
    let full = dir.path().join("full.exr");
    let mut args = vec!["assemble"];
    args.extend(tiles.iter().map(|t| s(t)));
    args.extend(["-o", s(&full)]);
    ok(&args);
    let one = render(&dir.path().join("one.exr"), None);
    let rows = row_means(
        &Image::read_exr(&full).unwrap(),
        &Image::read_exr(&one).unwrap(),
    );
    let jump = |k: usize| (rows[k + 1] - rows[k]).abs();
    let border: Vec<f64> = (1..8).map(|t| jump(16 * t - 1)).collect();
    let interior: Vec<f64> = (0..127).filter(|k| (k + 1) % 16 != 0).map(jump).collect();
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    let (b, i) = (mean(&border), mean(&interior));
    assert!(
        b < 2.0 * i,
        "border row jump {b:.5} vs interior {i:.5}: {border:?}"
    );
}
