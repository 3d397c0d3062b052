//! Textures: import, tiles in the archive, paging under the budget, MIP filtering.

mod common;

use common::textured::{checker_png, plane_gltf, Plane};
use common::*;

/// Writes the grazing checkerboard scene into `dir` and converts it.
fn checker_archive(
    dir: &std::path::Path,
    size: u32,
    checks: u32,
    plane: Plane,
) -> std::path::PathBuf {
    checker_png(&dir.join("checker.png"), size, checks, |_, _| false);
    let gltf = plane_gltf(dir, "plane.gltf", &plane);
    let out = dir.join("plane.canopy");
    convert(&gltf, &out, None);
    out
}

/// For looking at by hand: `CANOPY_TEXSCENE=DIR cargo test --test textures -- --ignored`.
#[test]
#[ignore]
fn write_the_checker_scene() {
    let dir = std::path::PathBuf::from(std::env::var("CANOPY_TEXSCENE").unwrap());
    std::fs::create_dir_all(&dir).unwrap();
    checker_archive(&dir, 1024, 16, Plane::default());
}

/// Renders `archive` at 64×64 with direct light only; returns the image and stats.
fn render64(
    archive: &std::path::Path,
    out: &std::path::Path,
    spp: u32,
    seed: u32,
    extra: &[&str],
) -> (canopy::image::Image, serde_json::Value) {
    let (spp, seed) = (spp.to_string(), seed.to_string());
    let mut args = vec![
        "--spp", &spp, "--seed", &seed, "--width", "64", "--height", "64",
    ];
    args.extend(["--max-depth", "2"]);
    args.extend(extra);
    render(archive, out, &args)
}

/// RMSE over rows `rows` of the red channel.
fn rows_rmse(
    a: &canopy::image::Image,
    b: &canopy::image::Image,
    rows: std::ops::Range<u32>,
) -> f64 {
    let mut sum = 0.0;
    for y in rows.clone() {
        for x in 0..a.width {
            let d = a.pixels[(y * a.width + x) as usize][0] as f64
                - b.pixels[(y * b.width + x) as usize][0] as f64;
            sum += d * d;
        }
    }
    (sum / (rows.len() as f64 * a.width as f64)).sqrt()
}

#[test]
fn mip_filtering_converges_to_point_sampling_and_does_not_alias_at_1_spp() {
    let dir = tempfile::tempdir().unwrap();
    let archive = checker_archive(dir.path(), 1024, 16, Plane::default());
    let point = ["--texture-filter", "point"];
    let (reference, _) = render64(&archive, &dir.path().join("ref.exr"), 4096, 1, &point);
    let (again, _) = render64(&archive, &dir.path().join("ref2.exr"), 4096, 2, &point);
    let noise = rmse(&reference, &again);
    let errs: Vec<f64> = [16, 256, 4096]
        .iter()
        .map(|&spp| {
            let (img, _) = render64(
                &archive,
                &dir.path().join(format!("t{spp}.exr")),
                spp,
                3,
                &[],
            );
            rmse(&img, &reference)
        })
        .collect();
    eprintln!("noise {noise:.2e}, trilinear at 16/256/4096 spp vs 4096 point samples {errs:?}");
    // The filter narrows as 1/√spp, so the images converge to the point-sampled one.
    assert!(
        errs[1] < errs[0] / 2.0 && errs[2] < errs[1] / 2.0,
        "{errs:?}"
    );
    let mean = reference.mean()[0];
    assert!(
        errs[2] < 0.005 * mean,
        "{:.2e} of a mean {mean:.3}",
        errs[2]
    );

    // Where the plane recedes to the horizon the checks are far below a pixel: point
    // samples alias (each sample picks a check), filtered ones agree whatever the seed.
    let horizon = (0..64u32)
        .find(|&y| reference.pixels[(y * 64 + 32) as usize][0] > 0.0)
        .unwrap();
    let far = horizon..horizon + 12;
    let one = |seed, extra: &[&str]| {
        render64(
            &archive,
            &dir.path().join(format!("o{seed}{}.exr", extra.len())),
            1,
            seed,
            extra,
        )
        .0
    };
    let filtered = rows_rmse(&one(5, &[]), &one(6, &[]), far.clone());
    let aliased = rows_rmse(&one(5, &point), &one(6, &point), far.clone());
    eprintln!("1 spp, rows {far:?}: seed-to-seed RMSE {filtered:.4} filtered, {aliased:.4} point");
    assert!(filtered < aliased / 10.0, "{filtered} vs {aliased}");
}

#[test]
fn tiles_page_under_the_budget_without_changing_the_image() {
    let dir = tempfile::tempdir().unwrap();
    // Texels about the size of pixels near the camera: level-0 tiles there, and every
    // coarser level towards the horizon.
    let plane = Plane {
        repeat: 0.1,
        pitch: 35.0,
        ..Plane::default()
    };
    let archive = checker_archive(dir.path(), 1024, 32, plane);
    let common = [
        "--spp",
        "2",
        "--width",
        "480",
        "--height",
        "480",
        "--max-depth",
        "2",
    ];
    let (full, fs) = render(&archive, &dir.path().join("full.exr"), &common);
    let held = fs["resident_bytes_peak"].as_u64().unwrap();
    let tiles = fs["texture_tiles_loaded"].as_u64().unwrap();
    assert!(tiles > 20, "only {tiles} tiles loaded: {fs}");
    assert_eq!(fs["texture_tiles_evicted"], 0);
    let budget = (held / 4).to_string();
    let (part, ps) = render(
        &archive,
        &dir.path().join("part.exr"),
        &[&common[..], &["--mem-budget", &budget]].concat(),
    );
    assert!(full.mean()[0] > 0.05, "the plane is unlit");
    assert_eq!(full.pixels, part.pixels, "the budget changed the image");
    let evicted = ps["texture_tiles_evicted"].as_u64().unwrap();
    assert!(evicted > 0, "no tile evicted under {budget} bytes: {ps}");
    let resident = ps["resident_bytes_peak"].as_u64().unwrap();
    assert!(
        resident <= held / 4,
        "{resident} resident under a budget of {budget}"
    );
}

#[test]
fn a_texture_larger_than_the_budget_converts_in_bounded_memory_and_loads_only_the_levels_in_view() {
    let dir = tempfile::tempdir().unwrap();
    let size = 8192;
    checker_png(&dir.path().join("checker.png"), size, 256, |_, _| false);
    // Seen from high up and far away: the texture is minified, the finest levels unused.
    let plane = Plane {
        repeat: 0.02,
        height: 30.0,
        pitch: 20.0,
        ..Plane::default()
    };
    let gltf = plane_gltf(dir.path(), "plane.gltf", &plane);
    let out = dir.path().join("big.canopy");
    let report: serde_json::Value = serde_json::from_str(&ok(&[
        "--quiet",
        "convert",
        s(&gltf),
        "-o",
        s(&out),
        "--mem-budget",
        "256MiB",
        "--json",
    ]))
    .unwrap();
    let peak = report["peak_rss_bytes"].as_u64().unwrap();
    let texels = (size as u64 * size as u64) * 4;
    eprintln!(
        "converting a {size}² texture ({} MiB of texels) peaked at {} MiB",
        texels >> 20,
        peak >> 20
    );
    assert!(
        peak < texels / 2,
        "convert held {peak} bytes for {texels} bytes of texels"
    );
    let budget = (texels / 8).to_string();
    let (img, st) = render(
        &out,
        &dir.path().join("big.exr"),
        &[
            "--spp",
            "4",
            "--width",
            "96",
            "--height",
            "96",
            "--max-depth",
            "2",
            "--mem-budget",
            &budget,
        ],
    );
    assert!(img.mean()[0] > 0.01);
    let levels: Vec<u64> =
        serde_json::from_value(st["texture_tiles_loaded_per_level"].clone()).unwrap();
    eprintln!("tiles loaded per level: {levels:?}");
    assert!(levels.len() > 8, "{levels:?}");
    assert_eq!(levels[..3], [0, 0, 0], "fine levels loaded: {levels:?}");
}
