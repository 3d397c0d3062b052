//! Textures: import, tiles in the archive, paging under the budget, MIP filtering.

mod common;

use common::textured::{checker_png, halves_png, lamp_gltf, plane_gltf, solid_png, Plane};
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
    // The filter narrows as 1/√spp, so the images converge to the point-sampled one: at
    // 4096 spp their RMSE is the two renders' noise (`noise`, two point-sampled renders'
    // RMSE) and what is left of the filter's blur (measured 1.29 × `noise`).
    assert!(
        errs[1] < errs[0] / 2.0 && errs[2] < errs[1] / 2.0,
        "{errs:?}"
    );
    assert!(
        errs[2] < 1.5 * noise,
        "{:.2e} against two point-sampled renders' {noise:.2e}",
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
    let five = one(5, &[]);
    let filtered = rows_rmse(&five, &one(6, &[]), far.clone());
    let aliased = rows_rmse(&one(5, &point), &one(6, &point), far.clone());
    eprintln!("1 spp, rows {far:?}: seed-to-seed RMSE {filtered:.4} filtered, {aliased:.4} point");
    assert!(filtered < aliased / 10.0, "{filtered} vs {aliased}");
    // Agreeing is not enough (a constant would): the far rows' filtered light is the
    // checks' true mean there, the point-sampled reference's, within the noise of their
    // difference (its RMS over √pixels bounds the standard error of the means' gap).
    let red_sum = |img: &canopy::image::Image| {
        let row = |y: u32| (0..64).map(move |x| img.pixels[(y * 64 + x) as usize][0] as f64);
        far.clone().flat_map(row).sum::<f64>()
    };
    let n = (far.len() * 64) as f64;
    let gap = (red_sum(&five) - red_sum(&reference)) / n;
    let se = rows_rmse(&five, &reference, far.clone()) / n.sqrt();
    assert!(
        gap.abs() <= 4.0 * se,
        "far rows: filtered mean {gap:+.2e} off the point-sampled one ({se:.1e} standard error)"
    );
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
    big_texture(8192);
}

/// The size: `cargo test --release --test textures -- --ignored sixteen`.
#[test]
#[ignore]
fn a_sixteen_k_texture_converts_in_bounded_memory() {
    big_texture(16384);
}

/// A `size`² checker (4·size² bytes of texels) converts under a 256 MiB budget with a
/// peak RSS under half its texels, and renders from afar under an eighth of them.
fn big_texture(size: u32) {
    let dir = tempfile::tempdir().unwrap();
    checker_png(&dir.path().join("checker.png"), size, size / 32, |_, _| {
        false
    });
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

/// A PNG holding only a header that claims `w` × `h` RGBA texels (and no image data).
fn png_header_only(path: &std::path::Path, w: u32, h: u32) {
    fn crc32(bytes: &[u8]) -> u32 {
        let mut c = !0u32;
        for &b in bytes {
            c ^= b as u32;
            for _ in 0..8 {
                c = if c & 1 != 0 {
                    0xEDB8_8320 ^ (c >> 1)
                } else {
                    c >> 1
                };
            }
        }
        !c
    }
    let mut ihdr = b"IHDR".to_vec();
    ihdr.extend(w.to_be_bytes());
    ihdr.extend(h.to_be_bytes());
    ihdr.extend([8, 6, 0, 0, 0]);
    let mut out = b"\x89PNG\r\n\x1a\n".to_vec();
    out.extend(13u32.to_be_bytes());
    out.extend(&ihdr);
    out.extend(crc32(&ihdr).to_be_bytes());
    out.extend(0u32.to_be_bytes());
    out.extend(b"IEND");
    out.extend(crc32(b"IEND").to_be_bytes());
    std::fs::write(path, out).unwrap();
}

#[test]
fn bad_textures_are_refused_by_name_and_leave_no_archive() {
    let dir = tempfile::tempdir().unwrap();
    let gltf = plane_gltf(dir.path(), "plane.gltf", &Plane::default());
    let out = dir.path().join("p.canopy");
    let image = dir.path().join("checker.png");
    let refused = |what: &str, expect: &[&str]| {
        let err = fails(&["--quiet", "convert", s(&gltf), "-o", s(&out)]);
        for e in expect {
            assert!(err.contains(e), "{what}: '{e}' not in: {err}");
        }
        assert!(!out.exists(), "{what}: an archive was written");
        let leftovers: Vec<_> = std::fs::read_dir(dir.path())
            .unwrap()
            .flatten()
            .filter(|e| e.file_name().to_string_lossy().contains(".tmp"))
            .collect();
        assert!(leftovers.is_empty(), "{what}: {leftovers:?} left behind");
    };
    refused(
        "missing",
        &["checker.png", "missing", "--missing-textures warn"],
    );

    // With --missing-textures warn the plane keeps its factor (white) and says so.
    let run = canopy(&[
        "--quiet",
        "convert",
        s(&gltf),
        "-o",
        s(&out),
        "--missing-textures",
        "warn",
    ]);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let warning = String::from_utf8_lossy(&run.stderr);
    assert!(
        warning.contains("warning") && warning.contains("checker.png"),
        "{warning}"
    );
    let report = ok(&["inspect", s(&out)]);
    assert!(report.contains("textures            0"), "{report}");
    std::fs::remove_file(&out).unwrap();

    std::fs::write(&image, b"\x89PNG\r\n\x1a\nthis is not a PNG stream").unwrap();
    refused("corrupt PNG", &["checker.png"]);
    checker_png(&image, 64, 4, |_, _| false);
    let mut bytes = std::fs::read(&image).unwrap();
    bytes.truncate(bytes.len() / 2);
    std::fs::write(&image, &bytes).unwrap();
    refused("truncated PNG", &["checker.png"]);
    std::fs::write(
        &image,
        [
            0xFF, 0xD8, 0xFF, 0xE0, 0, 16, b'J', b'F', b'I', b'F', 0, 1, 2, 3,
        ],
    )
    .unwrap();
    refused("corrupt JPEG", &["checker.png"]);
    png_header_only(&image, 0, 16);
    refused("zero-sized", &["checker.png"]);
    png_header_only(&image, 65536, 32768);
    refused("absurd", &["checker.png", "65536×32768"]);
    // A JPEG is decoded whole: a 16384² one (2 GiB decoded) exceeds the default budget's
    // share. Headers only (tables, frame, scan), which is all the size check reads.
    std::fs::write(&image, jpeg_header_only(16384, 16384)).unwrap();
    refused(
        "JPEG too large to decode whole",
        &[
            "checker.png",
            "16384×16384",
            "decoded whole",
            "--mem-budget",
        ],
    );
}

/// A baseline JPEG's markers up to its scan header, declaring `w`×`h`, with no image data.
fn jpeg_header_only(w: u16, h: u16) -> Vec<u8> {
    let mut b = vec![0xFF, 0xD8];
    b.extend([0xFF, 0xDB, 0, 67, 0]);
    b.extend([1u8; 64]);
    b.extend([0xFF, 0xC0, 0, 17, 8]);
    b.extend(h.to_be_bytes());
    b.extend(w.to_be_bytes());
    b.extend([3, 1, 0x11, 0, 2, 0x11, 0, 3, 0x11, 0]);
    for class in [0x00, 0x10] {
        b.extend([0xFF, 0xC4, 0, 20, class, 1]);
        b.extend([0u8; 16]);
    }
    b.extend([0xFF, 0xDA, 0, 12, 3, 1, 0, 2, 0, 3, 0, 0, 63, 0]);
    b.extend([0u8; 16]);
    b.extend([0xFF, 0xD9]);
    b
}

#[test]
fn an_obj_with_map_kd_renders_as_the_same_gltf_plane() {
    let dir = tempfile::tempdir().unwrap();
    // Squares with holes in one corner: an upside-down or mirrored image would move them.
    checker_png(&dir.path().join("checker.png"), 256, 8, |x, y| {
        x < 2 && y < 3
    });
    let plane = Plane {
        repeat: 0.1,
        bare: true,
        ..Plane::default()
    };
    plane_gltf(dir.path(), "plane.gltf", &plane);
    // The same plane as OBJ: `vt` counts v up the image, so it stores 1 − v.
    let (s_, near, far, r) = (60.0f32, 4.0f32, -150.0f32, 0.1f32);
    let corners = [[-s_, near], [s_, near], [s_, far], [-s_, far]];
    let mut obj = String::from("mtllib plane.mtl\nusemtl checker\n");
    for [x, z] in corners {
        obj += &format!("v {x} 0 {z}\nvt {} {}\n", x * r, 1.0 - z * r);
    }
    obj += "f 1/1 2/2 3/3\nf 1/1 3/3 4/4\n";
    std::fs::write(dir.path().join("plane.obj"), obj).unwrap();
    std::fs::write(
        dir.path().join("plane.mtl"),
        "newmtl checker\nKd 1 1 1\nmap_Kd -bm 1 checker.png\n",
    )
    .unwrap();
    let toml = "[[camera]]\nposition = [0.0, 3.0, 0.0]\nlook_at = [0.5, 0.0, -4.0]\nwidth = 64\nheight = 64\nyfov_degrees = 60.0\n\
                [[light]]\ntype = \"directional\"\ndirection = [0.2, -1.0, -0.3]\nintensity = 3.0\n";
    let scene = dir.path().join("s.toml");
    std::fs::write(&scene, toml).unwrap();
    let args = ["--spp", "4", "--max-depth", "2"];
    let mut images = Vec::new();
    for input in ["plane.gltf", "plane.obj"] {
        let out = dir.path().join(format!("{input}.canopy"));
        convert(&dir.path().join(input), &out, Some(&scene));
        images.push(render(&out, &dir.path().join(format!("{input}.exr")), &args).0);
    }
    assert!(images[0].mean()[0] > 0.05);
    let err = rmse(&images[0], &images[1]);
    assert!(err < 1e-5, "OBJ and glTF planes differ: RMSE {err}");
}

#[test]
fn alpha_masks_cut_holes_for_camera_and_shadow_rays() {
    let dir = tempfile::tempdir().unwrap();
    // A quarter of the squares are holes; a red floor lies 0.3 below.
    checker_png(&dir.path().join("checker.png"), 256, 8, |x, y| {
        (x + 2 * y) % 4 == 0
    });
    let mut fractions = Vec::new();
    for (mode, integrator) in [("OPAQUE", "path"), ("MASK", "path"), ("MASK", "cone")] {
        let plane = Plane {
            repeat: 0.5,
            pitch: 50.0,
            height: 2.0,
            alpha_mode: Some(mode),
            floor_below: Some(0.3),
            ..Plane::default()
        };
        let gltf = plane_gltf(dir.path(), &format!("{mode}.gltf"), &plane);
        let out = dir.path().join(format!("{mode}.canopy"));
        if !out.exists() {
            convert(&gltf, &out, None);
        }
        let exr = dir.path().join(format!("{mode}{integrator}.exr"));
        let filter = ["--texture-filter", "point", "--integrator", integrator];
        let (img, _) = render64(&out, &exr, 4, 0, &filter);
        // Lit red floor seen through a hole: red well above green.
        let red = img
            .pixels
            .iter()
            .filter(|p| p[0] > 0.02 && p[0] > 3.0 * p[1])
            .count();
        fractions.push(red as f64 / img.pixels.len() as f64);
    }
    eprintln!("red floor seen on {fractions:.3?} of the pixels (opaque, mask: path, cone)");
    assert_eq!(fractions[0], 0.0, "an opaque plane shows the floor");
    // A quarter of the plane is holes, and the lit part of the floor under each is smaller
    // than the hole (shadow rays pass the same holes): some, but under a quarter.
    assert!((0.02..0.25).contains(&fractions[1]), "{fractions:?}");
    // The cone integrator's cones pass the same holes.
    assert!(
        (fractions[2] - fractions[1]).abs() < 0.2 * fractions[1],
        "{fractions:?}"
    );
}

#[test]
fn a_normal_map_tilts_the_shading_normal_as_gltf_says() {
    // A uniform plane (y up, u along +x, v along +z) under the directional light whose
    // direction to the light is (0, cos 30°, sin 30°). The normal texture tilts the normal by
    // 30° toward +y of the image, which glTF's tangent frame (t = ∂p/∂u, b = n × t) puts
    // toward −z, away from the light: with only direct light each lit pixel is
    // albedo/π · E · (n_s · l), from the texel, the scale and glTF 2.0 §3.9.3 alone.
    let dir = tempfile::tempdir().unwrap();
    checker_png(&dir.path().join("checker.png"), 64, 1, |_, _| false);
    let texel = [128u8, 191, 238, 255];
    solid_png(&dir.path().join("normal.png"), 64, texel);
    let albedo = {
        let c = 224.0 / 255.0f64;
        ((c + 0.055) / 1.055).powf(2.4)
    };
    let l = [0.0, 30f64.to_radians().cos(), 30f64.to_radians().sin()];
    for scale in [1.0f32, 0.5] {
        let [x, y, z] = [0, 1, 2].map(|k| 2.0 * texel[k] as f64 / 255.0 - 1.0);
        let (x, y) = (x * scale as f64, y * scale as f64);
        let len = (x * x + y * y + z * z).sqrt();
        // World: t = +x, b = n × t = −z, n = +y.
        let ns = [x / len, z / len, -y / len];
        let cos = ns[0] * l[0] + ns[1] * l[1] + ns[2] * l[2];
        let expected = albedo / std::f64::consts::PI * 3.0 * cos;
        let plane = Plane {
            pitch: 50.0,
            height: 2.0,
            normal: Some(("normal.png", scale)),
            ..Plane::default()
        };
        let gltf = plane_gltf(dir.path(), "bumped.gltf", &plane);
        let archive = dir.path().join(format!("bumped{scale}.canopy"));
        convert(&gltf, &archive, None);
        for integrator in ["path", "cone"] {
            let exr = dir.path().join(format!("{scale}{integrator}.exr"));
            let (img, _) = render64(&archive, &exr, 2, 1, &["--integrator", integrator]);
            // The bottom rows see only the plane.
            for p in &img.pixels[48 * 64..] {
                assert!(
                    (p[0] as f64 - expected).abs() < 2e-3 * expected,
                    "scale {scale}, {integrator}: {} against {expected}",
                    p[0]
                );
            }
        }
    }
}

#[test]
fn the_normal_mapped_scene_agrees_with_mitsuba() {
    // Ridged normal maps on Lambertian and rough-metal surfaces (scenes/bumps) against
    // Mitsuba 3's `normalmap`: the image means differ by 0.04–0.1% at any spp (how the two
    // interpolate across the ridges' edges), while a bitangent turned round moves them by
    // 12%. Normal maps are read at level 0 whatever the filter, as Mitsuba reads them.
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("bumps.canopy");
    convert(&scene("bumps/bumps.gltf"), &out, None);
    let reference = reference("bumps");
    for integrator in ["path", "cone"] {
        let exr = dir.path().join(format!("{integrator}.exr"));
        let args = ["--spp", "16", "--integrator", integrator];
        let (img, _) = render(&out, &exr, &args);
        assert_mean_within(&img, &reference, 0.005, &format!("bumps, {integrator}"));
    }
}

#[test]
fn a_lamp_emits_its_texels_not_its_mean() {
    // A lamp whose emissive texture is white on its left half and black on its right
    // must light the floor as a lamp of its left half alone, untextured: in light samples,
    // in emission that bounce rays hit, and in the cone integrator's stored light.
    let dir = tempfile::tempdir().unwrap();
    halves_png(&dir.path().join("halves.png"), 64);
    let textured = lamp_gltf(dir.path(), "t.gltf", (-1.0, 1.0), Some("halves.png"));
    let half = lamp_gltf(dir.path(), "h.gltf", (-1.0, 0.0), None);
    let (ta, ha) = (dir.path().join("t.canopy"), dir.path().join("h.canopy"));
    convert(&textured, &ta, None);
    convert(&half, &ha, None);
    // Mean of each quarter of the image's columns.
    let strips = |img: &canopy::image::Image| -> Vec<f64> {
        (0..4)
            .map(|k| {
                let (x0, x1) = (k * img.width / 4, (k + 1) * img.width / 4);
                let mut sum = 0.0;
                for y in 0..img.height {
                    for x in x0..x1 {
                        sum += img.pixels[(y * img.width + x) as usize][0] as f64;
                    }
                }
                sum / ((x1 - x0) * img.height) as f64
            })
            .collect()
    };
    for integrator in ["path", "cone"] {
        let args = [
            "--spp",
            "64",
            "--width",
            "64",
            "--height",
            "64",
            "--integrator",
            integrator,
        ];
        let (a, _) = render(&ta, &dir.path().join(format!("t{integrator}.exr")), &args);
        let (b, _) = render(&ha, &dir.path().join(format!("h{integrator}.exr")), &args);
        assert_mean_within_noise(&a, &b, &format!("textured lamp, {integrator}"));
        let (sa, sb) = (strips(&a), strips(&b));
        assert!(
            sb[0] > 1.5 * sb[3],
            "the half lamp lights the left more: {sb:?}"
        );
        for k in 0..4 {
            assert!(
                (sa[k] / sb[k] - 1.0).abs() < 0.03,
                "{integrator}: strip {k}: {sa:?} against {sb:?}"
            );
        }
    }
}

#[test]
fn cut_outs_keep_their_coverage_when_their_texels_are_smaller_than_a_pixel() {
    // Holes a quarter of the squares, squares far smaller than a pixel: a MIP-filtered
    // alpha (0.75 everywhere) would pass the 0.5 cutoff and close every hole; alpha read at
    // the point keeps a quarter of the plane open, whatever the filter and the integrator.
    let dir = tempfile::tempdir().unwrap();
    checker_png(&dir.path().join("checker.png"), 256, 32, |x, y| {
        (x + 2 * y) % 4 == 0
    });
    let plane = Plane {
        repeat: 4.0,
        pitch: 50.0,
        height: 2.0,
        alpha_mode: Some("MASK"),
        floor_below: Some(0.3),
        ..Plane::default()
    };
    let gltf = plane_gltf(dir.path(), "p.gltf", &plane);
    let out = dir.path().join("p.canopy");
    convert(&gltf, &out, None);
    let mut means = Vec::new();
    for (filter, integrator) in [
        ("point", "path"),
        ("trilinear", "path"),
        ("trilinear", "cone"),
    ] {
        let exr = dir.path().join(format!("{filter}{integrator}.exr"));
        let args = ["--texture-filter", filter, "--integrator", integrator];
        let (img, _) = render64(&out, &exr, 16, 0, &args);
        // Red (the floor seen through holes) over green (the grey plane).
        let m = img.mean();
        means.push(m[0] / m[1]);
    }
    eprintln!("red/green (point, trilinear path, trilinear cone): {means:.4?}");
    assert!(means[0] > 1.05, "the floor shows through: {means:?}");
    for m in &means[1..] {
        assert!((m / means[0] - 1.0).abs() < 0.02, "{means:?}");
    }
}

#[test]
fn a_corrupt_tile_fails_the_render_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let archive = checker_archive(dir.path(), 256, 8, Plane::default());
    let mut bytes = std::fs::read(&archive).unwrap();
    // The tile table (header offset 224: offset, count) gives each tile's frame: flip a
    // byte in every one, so whichever the render reads first is damaged.
    let table = u64::from_le_bytes(bytes[224..232].try_into().unwrap()) as usize;
    let count = u32::from_le_bytes(bytes[232..236].try_into().unwrap()) as usize;
    for t in 0..count {
        let at = table + 32 * t;
        let frame = u64::from_le_bytes(bytes[at..at + 8].try_into().unwrap()) as usize;
        bytes[frame + 3] ^= 0x55;
    }
    std::fs::write(&archive, &bytes).unwrap();
    let out = dir.path().join("r.exr");
    let err = fails(&[
        "render",
        s(&archive),
        "-o",
        s(&out),
        "--spp",
        "1",
        "--width",
        "32",
        "--height",
        "32",
    ]);
    assert!(
        err.contains("texture tile") && err.contains("checksum"),
        "{err}"
    );
    assert!(!out.exists(), "an image was written");
}

#[test]
fn textured_sponza_agrees_with_mitsuba_in_every_channel() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("s.canopy");
    convert(&scene("sponza_textured/sponza_textured.gltf"), &out, None);
    let report = ok(&["inspect", s(&out)]);
    assert!(report.contains("textures            19 in"), "{report}");
    let (img, st) = render(
        &out,
        &dir.path().join("s.exr"),
        &["--spp", "4", "--seed", "9"],
    );
    assert!(st["texture_tiles_loaded"].as_u64().unwrap() > 100, "{st}");
    assert_mean_within_noise(&img, &reference("sponza_textured"), "textured sponza");
}

#[test]
fn images_without_a_source_are_refused_not_panicked_on() {
    // Found by `fuzz --seed 10`: the gltf crate unwraps an image's view and MIME type.
    let dir = tempfile::tempdir().unwrap();
    let gltf = plane_gltf(dir.path(), "plane.gltf", &Plane::default());
    let json: serde_json::Value = serde_json::from_slice(&std::fs::read(&gltf).unwrap()).unwrap();
    for (image, expect) in [
        (
            serde_json::json!({"bufferView": 0}),
            "image 0: buffer view 0",
        ),
        (
            serde_json::json!({"bufferView": 99, "mimeType": "image/png"}),
            "image 0: buffer view 99",
        ),
        (serde_json::json!({}), "image 0 has neither"),
    ] {
        let mut j = json.clone();
        j["images"][0] = image;
        std::fs::write(&gltf, serde_json::to_vec(&j).unwrap()).unwrap();
        let out = dir.path().join("p.canopy");
        let err = fails(&["--quiet", "convert", s(&gltf), "-o", s(&out)]);
        assert!(err.contains(expect), "{expect}: {err}");
        assert!(!out.exists());
    }
}

/// `--missing-textures warn` with a normal map missing: the archive written is one its own
/// reader accepts (the dropped map takes its scale with it), and it renders.
#[test]
fn a_missing_normal_map_leaves_an_archive_that_reads_and_renders() {
    let dir = tempfile::tempdir().unwrap();
    checker_png(&dir.path().join("checker.png"), 64, 4, |x, y| {
        (x + y) % 2 == 0
    });
    let plane = Plane {
        normal: Some(("ridges.png", 1.0)),
        ..Plane::default()
    };
    let gltf = plane_gltf(dir.path(), "plane.gltf", &plane);
    let out = dir.path().join("p.canopy");
    let args = [
        "--quiet",
        "convert",
        s(&gltf),
        "-o",
        s(&out),
        "--missing-textures",
        "warn",
    ];
    let run = canopy(&args);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    assert!(String::from_utf8_lossy(&run.stderr).contains("ridges.png"));
    let report = ok(&["inspect", s(&out), "--verify"]);
    assert!(report.contains("textures            1"), "{report}");
    let (img, _) = render(
        &out,
        &dir.path().join("p.exr"),
        &["--spp", "2", "--width", "32", "--height", "24"],
    );
    assert!(all_finite(&img) && img.mean()[0] > 0.0);
}

/// EXT_texture_webp and KHR_texture_basisu: `scenes/webp` and `scenes/ktx2`, the bumps
/// scene with its normal map as a lossless WebP or a UASTC KTX2 (which holds this map
/// exactly) and no PNG fallback (`tools/texture_variant.py`), render the PNG scene's image
/// exactly: neither codec loses a texel here.
#[test]
fn webp_and_ktx2_only_textures_render_as_their_png_twin() {
    let dir = tempfile::tempdir().unwrap();
    let flags = ["--spp", "4", "--width", "80", "--height", "60"];
    let images: Vec<_> = ["bumps/bumps.gltf", "webp/bumps.gltf", "ktx2/bumps.gltf"]
        .iter()
        .enumerate()
        .map(|(i, name)| {
            let arc = dir.path().join(format!("{i}.canopy"));
            ok(&["--quiet", "convert", s(&scene(name)), "-o", s(&arc)]);
            render(&arc, &dir.path().join(format!("{i}.exr")), &flags).0
        })
        .collect();
    assert!(
        images[0].pixels == images[1].pixels,
        "the WebP twin's image differs"
    );
    assert!(
        images[0].pixels == images[2].pixels,
        "the KTX2 twin's image differs"
    );
    // The KTX2 file cut after its header: refused, naming the image.
    let broken = dir.path().join("broken");
    std::fs::create_dir(&broken).unwrap();
    for f in ["bumps.gltf", "bumps.bin"] {
        std::fs::copy(scene("ktx2").join(f), broken.join(f)).unwrap();
    }
    let ktx = std::fs::read(scene("ktx2/ridges.ktx2")).unwrap();
    std::fs::write(broken.join("ridges.ktx2"), &ktx[..80]).unwrap();
    let out = dir.path().join("broken.canopy");
    let err = fails(&["convert", s(&broken.join("bumps.gltf")), "-o", s(&out)]);
    assert!(err.contains("ridges.ktx2") && err.contains("KTX2"), "{err}");
    // Level 0 declaring 2^62 decompressed bytes (the transcoder would allocate them).
    let mut huge = ktx.clone();
    huge[96..104].copy_from_slice(&(1u64 << 62).to_le_bytes());
    std::fs::write(broken.join("ridges.ktx2"), &huge).unwrap();
    let err = fails(&["convert", s(&broken.join("bumps.gltf")), "-o", s(&out)]);
    assert!(err.contains("KTX2 level 0 declares"), "{err}");
}
