//! Light from the environment, and the defaults for archives without camera or light.

mod common;
use canopy::image::Image;
use common::*;
use std::path::{Path, PathBuf};

/// A unit cube about the origin (no normals: flat faces) whose material has `albedo`, with
/// neither camera nor light.
fn cube(dir: &Path, albedo: f32) -> PathBuf {
    cube_with(dir, albedo, "")
}

/// `cube` with more of the scene file (`extra` TOML).
fn cube_with(dir: &Path, albedo: f32, extra: &str) -> PathBuf {
    let v = (0..8)
        .map(|i| {
            let c = |b: usize| if i >> b & 1 == 1 { 0.5 } else { -0.5 };
            format!("v {} {} {}\n", c(0), c(1), c(2))
        })
        .collect::<String>();
    // Each face counter-clockwise seen from outside.
    let faces = [
        [1, 3, 7, 5],
        [2, 6, 8, 4],
        [1, 5, 6, 2],
        [3, 4, 8, 7],
        [1, 2, 4, 3],
        [5, 7, 8, 6],
    ]
    .iter()
    .map(|[a, b, c, d]| format!("f {a} {b} {c}\nf {a} {c} {d}\n"))
    .collect::<String>();
    let toml = format!(
        "[[material]]\nname = \"default\"\nbase_color = [{albedo}, {albedo}, {albedo}]\n{extra}"
    );
    obj_scene(
        dir,
        &[("cube.obj", v + &faces), ("scene.toml", toml)],
        "cube.canopy",
    )
}

/// Mean of a channel over the pixels of rows y0..y1 and columns x0..x1, and its standard
/// error from their spread (the block's pixels share one expected value).
fn block_mean(img: &Image, [x0, x1, y0, y1]: [u32; 4]) -> (f64, f64) {
    let v: Vec<f64> = (y0..y1)
        .flat_map(|y| (x0..x1).map(move |x| (x, y)))
        .map(|(x, y)| img.pixels[(y * img.width + x) as usize][0] as f64)
        .collect();
    let n = v.len() as f64;
    let mean = v.iter().sum::<f64>() / n;
    let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0);
    (mean, (var / n).sqrt())
}

/// With nothing but its file name, an archive with no camera and no light renders framed
/// (the default view from +Z, the bounds' sphere filling 45° vertically) under a uniform
/// white environment, each default named on stderr. A cube of albedo 0.5 under radiance 1
/// sends exactly 0.5 (it is convex: each face sees the whole sky over it), the background
/// is exactly 1, and the cube's front face spans the height the framing predicts.
#[test]
fn an_archive_without_camera_or_light_renders_framed_under_a_white_sky() {
    let dir = tempfile::tempdir().unwrap();
    let arc = cube(dir.path(), 0.5);
    let out = dir.path().join("o.exr");
    let run = canopy(&["render", s(&arc), "-o", s(&out), "--spp", "16"]);
    assert!(run.status.success());
    let err = String::from_utf8_lossy(&run.stderr);
    assert!(err.contains("has no camera: the default view"), "{err}");
    assert!(
        err.contains("has no light source: a uniform white environment"),
        "{err}"
    );
    let img = Image::read_exr(&out).unwrap();
    assert_eq!((img.width, img.height), (640, 480));
    assert_eq!(
        img.pixels[0], [1.0; 3],
        "the background is the sky's radiance"
    );
    // The front face at distance d − 0.5 (d = √3/2 / sin 22.5°) spans a half-height of
    // 0.5 / (d − 0.5) over tan 22.5° of the image's.
    let d = 3f64.sqrt() / 2.0 / 22.5f64.to_radians().sin();
    let half = 0.5 / (d - 0.5) / 22.5f64.to_radians().tan() * 240.0;
    let column: Vec<bool> = (0..480)
        .map(|y| img.pixels[y * 640 + 320][0] < 0.75)
        .collect();
    let rows = column.iter().filter(|&&c| c).count() as f64;
    assert!(
        (rows - 2.0 * half).abs() <= 2.0,
        "{rows} rows, framing predicts {}",
        2.0 * half
    );
    let (face, se) = block_mean(&img, [280, 360, 200, 280]);
    assert!((face - 0.5).abs() < 4.0 * se, "front face {face} ± {se}");
}

/// The white furnace for every integrator: the convex cube of albedo 0.5 under the
/// default sky sends 0.5 at every integrator's defaults (within 4 standard errors and 0.5%).
#[test]
fn every_integrator_lights_a_convex_object_under_a_uniform_sky_exactly() {
    let dir = tempfile::tempdir().unwrap();
    let arc = cube(dir.path(), 0.5);
    for integrator in ["path", "cone", "pbgi"] {
        let out = dir.path().join(format!("{integrator}.exr"));
        let flags = [
            "--integrator",
            integrator,
            "--width",
            "64",
            "--height",
            "48",
            "--spp",
            "64",
        ];
        let (img, stats) = render(&arc, &out, &flags);
        assert!(all_finite(&img));
        // The cone integrator's pixels share stored light, so their spread understates the
        // noise of their mean: 0.5% more is allowed.
        let (face, se) = block_mean(&img, [26, 38, 18, 30]);
        assert!(
            (face - 0.5).abs() < 4.0 * se + 0.0025,
            "{integrator}: front face {face} ± {se}"
        );
        let passes = stats["passes"].to_string();
        assert!(passes.contains("environment: uniform radiance"), "{passes}");
    }
}

/// The map's convention is Mitsuba 3's `envmap`: +Z is u = ½, v = ½, and `--env-rotate`
/// turns the map about +Y (90°: what lay at +Z lies at +X). A camera looking along each
/// axis sees the patch of texels there, exactly (bilinear between equal texels).
#[test]
fn the_environment_map_is_placed_as_mitsuba_places_it() {
    let dir = tempfile::tempdir().unwrap();
    let (w, h) = (16u32, 9u32);
    let mut map = Image::new(w, h);
    for (k, p) in map.pixels.iter_mut().enumerate() {
        let (i, j) = (k as u32 % w, k as u32 / w);
        *p = match (i, j) {
            // u = ½ between columns 7 and 8, v = ½ at row 4: +Z.
            (7..=9, 3..=5) => [7.0, 3.0, 1.0],
            _ => [0.25; 3],
        };
    }
    let env = dir.path().join("sky.exr");
    map.write_exr(&env).unwrap();
    let files = [
        ("speck.obj", "v 0 -5 0\nv 0.01 -5 0\nv 0 -5 0.01\nf 1 2 3\n".to_string()),
        (
            "scene.toml",
            "[[camera]]\nname = \"z\"\nposition = [0.0, 0.0, 0.0]\nlook_at = [0.0, 0.0, 1.0]\nyfov_degrees = 5.0\nwidth = 4\nheight = 4\n\
             [[camera]]\nname = \"x\"\nposition = [0.0, 0.0, 0.0]\nlook_at = [1.0, 0.0, 0.0]\nyfov_degrees = 5.0\nwidth = 4\nheight = 4\n"
                .to_string(),
        ),
    ];
    let arc = obj_scene(dir.path(), &files, "speck.canopy");
    let see = |camera: &str, rotate: &str| {
        let out = dir.path().join(format!("{camera}{rotate}.exr"));
        let flags = [
            "--camera",
            camera,
            "--spp",
            "4",
            "--env",
            s(&env),
            "--env-rotate",
            rotate,
        ];
        render(&arc, &out, &flags).0.pixels[5]
    };
    assert_eq!(see("z", "0"), [7.0, 3.0, 1.0]);
    assert_eq!(see("x", "0"), [0.25; 3]);
    assert_eq!(see("x", "90"), [7.0, 3.0, 1.0]);
    let strong = dir.path().join("strong.exr");
    let flags = [
        "--camera",
        "z",
        "--spp",
        "1",
        "--env",
        s(&env),
        "--env-strength",
        "2",
    ];
    assert_eq!(render(&arc, &strong, &flags).0.pixels[5], [14.0, 6.0, 2.0]);
}

/// A map that is not an image, or has a non-finite texel, is refused naming the file; the
/// map's flags need `--env`.
#[test]
fn bad_environment_maps_are_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let arc = cube(dir.path(), 0.5);
    let out = dir.path().join("o.exr");
    let render = ["render", s(&arc), "-o", s(&out), "--spp", "1"];
    let text = dir.path().join("sky.hdr");
    std::fs::write(&text, "not a picture").unwrap();
    let err = fails(&[&render[..], &["--env", s(&text)]].concat());
    assert!(err.contains("sky.hdr") && err.contains("Radiance"), "{err}");
    let mut map = Image::new(4, 2);
    map.pixels[5] = [f32::INFINITY, 0.0, 0.0];
    let inf = dir.path().join("inf.exr");
    map.write_exr(&inf).unwrap();
    let err = fails(&[&render[..], &["--env", s(&inf)]].concat());
    assert!(
        err.contains("inf.exr") && err.contains("texel (1, 1)"),
        "{err}"
    );
    let err = fails(&[&render[..], &["--env-strength", "2"]].concat());
    assert!(err.contains("--env"), "{err}");
    assert!(!out.exists());
}

/// The bundled scenes lit by `scenes/env/sky.hdr` (tools/env_scene.py: gold, steel and clay
/// spheres on a floor; a closed room lit through a window, the sun on its floor) against
/// Mitsuba 3's `envmap` of the same file (`scenes/refs/env_*.exr`): the path tracer within 4
/// standard errors, over the image and per 16×16 block; the cone integrator's mean within
/// 0.5% (1% in the room, below); PBGI, whose bake carries every bounce, within 1%.
#[test]
fn under_an_environment_map_the_integrators_match_mitsuba() {
    let dir = tempfile::tempdir().unwrap();
    let sky = scene("env/sky.hdr");
    for (name, spp) in [("spheres", "512"), ("room", "256")] {
        let arc = dir.path().join(format!("{name}.canopy"));
        ok(&[
            "--quiet",
            "convert",
            s(&scene(&format!("env/{name}.glb"))),
            "-o",
            s(&arc),
        ]);
        let reference = reference(&format!("env_{name}"));
        let run = |out: &str, extra: &[&str]| {
            let flags = [&["--env", s(&sky), "--seed", "4"][..], extra].concat();
            render(&arc, &dir.path().join(format!("{name}_{out}.exr")), &flags).0
        };
        let path = run("path", &["--spp", spp]);
        assert!(all_finite(&path));
        assert_mean_within_noise(&path, &reference, &format!("path tracer, {name}"));
        assert_blocks_within_noise(&path, &reference, &format!("path tracer, {name}"));
        // The cone integrator's stored light is shared between pixels, so its image mean
        // varies from run to run more than its pixels' spread says: in the room at 128 spp
        // two runs gave -0.05% and -0.50% in red. There it is held to 1%.
        let cone = run("cone", &["--integrator", "cone", "--spp", "128"]);
        let tol = if name == "room" { 0.01 } else { 0.005 };
        let what = format!("cone integrator, {name}");
        assert_mean_within(&cone, &reference, tol, &what);
        let pbgi = run("pbgi", &["--integrator", "pbgi", "--spp", "128"]);
        assert_mean_within(&pbgi, &reference, 0.01, &format!("pbgi, {name}"));
    }
}

/// Under a budget too small to hold it, the map is paged: its tiles are read from a
/// temporary file and evicted (the stats count them), and the image is the one rendered
/// with the map held whole, bit for bit. Its bytes are in the stats' resident peak.
#[test]
fn a_map_larger_than_its_share_of_the_budget_is_paged_to_the_same_image() {
    let dir = tempfile::tempdir().unwrap();
    let arc = cube(dir.path(), 0.5);
    let env = dir.path().join("big.exr");
    // 2048 × 1024 texels, 12 MiB as halves: more than a quarter of a 32 MiB budget. Bands
    // of light, so every direction has its own value.
    let mut map = Image::new(2048, 1024);
    for (k, p) in map.pixels.iter_mut().enumerate() {
        let (i, j) = ((k % 2048) as f32, (k / 2048) as f32);
        *p = [
            1.0 + (i * 0.05).sin() * 0.5,
            1.0 + (j * 0.07).cos() * 0.5,
            0.5,
        ];
    }
    map.write_exr(&env).unwrap();
    let args = [
        "--width",
        "32",
        "--height",
        "24",
        "--spp",
        "64",
        "--env",
        s(&env),
    ];
    let (bare, whole) = render(&arc, &dir.path().join("a.exr"), &args);
    let budget = [&args[..], &["--mem-budget", "32MiB"]].concat();
    let (img, paged) = render(&arc, &dir.path().join("b.exr"), &budget);
    assert_eq!(
        img.pixels, bare.pixels,
        "the paged map renders the same image"
    );
    let env_stats = |s: &serde_json::Value, k: &str| s["environment"][k].as_u64().unwrap();
    assert_eq!(env_stats(&whole, "env_tiles_loaded"), 0, "held whole");
    assert!(env_stats(&whole, "env_bytes_peak") >= 2048 * 1024 * 6);
    assert!(
        env_stats(&paged, "env_tiles_evicted") > 0,
        "{}",
        paged["environment"]
    );
    // Its share, a quarter of the budget, and a tile read by each thread while the
    // others are evicted.
    let tile = 64 * 64 * 6 + 64;
    assert!(
        env_stats(&paged, "env_bytes_peak") <= (8 << 20) + 2 * tile,
        "{}",
        paged["environment"]
    );
    assert!(paged["resident_bytes_peak"].as_u64().unwrap() < 32 << 20);
}

/// A render whose every pixel is zero says why, on stderr and in the stats: here the only
/// light is a point light shut inside the cube.
#[test]
fn a_black_image_says_why() {
    let dir = tempfile::tempdir().unwrap();
    let light = "[[light]]\ntype = \"point\"\nposition = [0.0, 0.0, 0.0]\nintensity = 5.0\n";
    let arc = cube_with(dir.path(), 0.5, light);
    let out = dir.path().join("o.exr");
    let stats = dir.path().join("o.json");
    let run = canopy(&[
        "render",
        s(&arc),
        "-o",
        s(&out),
        "--spp",
        "2",
        "--width",
        "8",
        "--height",
        "6",
        "--stats",
        s(&stats),
    ]);
    assert!(run.status.success());
    let err = String::from_utf8_lossy(&run.stderr);
    let why =
        "the image is black: no light from its 0 emitters, 1 punctual lights reached the camera";
    assert!(err.contains(why), "{err}");
    assert!(std::fs::read_to_string(&stats).unwrap().contains(why));
    assert!(Image::read_exr(&out)
        .unwrap()
        .pixels
        .iter()
        .all(|p| *p == [0.0; 3]));
}

/// Scale: a 16 k × 8 k map (768 MiB as halves; a sky, a sun of 5·10⁴ and fine stripes),
/// as OpenEXR and as Radiance `.hdr`, lights the bundled spheres under `--mem-budget 64MiB`
/// with the same image as with no budget, its tiles paged and evicted, its resident peak
/// under the budget. Writes a 0.4 GiB and a 0.5 GiB map in the temporary directory and
/// takes a few minutes: `cargo test --release --test environment -- --ignored`.
#[test]
#[ignore]
fn a_16k_map_renders_under_64_mib_as_it_does_unlimited() {
    let dir = tempfile::tempdir().unwrap();
    let (w, h) = (16384usize, 8192usize);
    let texel = |x: usize, y: usize| {
        let (u, v) = ((x as f32 + 0.5) / w as f32, y as f32 / (h - 1) as f32);
        let sun = (u - 0.3).hypot(v - 0.25) < 0.002;
        let stripe = 1.0 + 0.3 * ((x / 3 + y / 5) % 2) as f32;
        match sun {
            true => [5e4, 4.5e4, 4e4],
            false => [
                0.3 * stripe * (1.0 - v),
                0.5 * stripe * (1.0 - v),
                0.9 * stripe,
            ],
        }
    };
    let exr = dir.path().join("16k.exr");
    write_exr(&exr, w, h, texel);
    let hdr = dir.path().join("16k.hdr");
    write_hdr(&hdr, w, h, texel);
    let arc = dir.path().join("spheres.canopy");
    ok(&[
        "--quiet",
        "convert",
        s(&scene("env/spheres.glb")),
        "-o",
        s(&arc),
    ]);
    for env in [&exr, &hdr] {
        let args = [
            "--width",
            "64",
            "--height",
            "48",
            "--spp",
            "16",
            "--threads",
            "2",
            "--env",
            s(env),
        ];
        let (unlimited, whole) = render(&arc, &dir.path().join("a.exr"), &args);
        let budget = [&args[..], &["--mem-budget", "64MiB"]].concat();
        let (img, paged) = render(&arc, &dir.path().join("b.exr"), &budget);
        assert_eq!(
            img.pixels,
            unlimited.pixels,
            "{}: the same image",
            env.display()
        );
        let evicted = paged["environment"]["env_tiles_evicted"].as_u64().unwrap();
        assert!(evicted > 0, "{}", paged["environment"]);
        let peak = |s: &serde_json::Value| s["resident_bytes_peak"].as_u64().unwrap();
        assert!(peak(&paged) < 64 << 20, "{}", peak(&paged));
        eprintln!(
            "{}: unlimited: resident peak {} B, RSS {} B; 64 MiB: resident peak {} B, RSS {} B, {}",
            env.display(),
            peak(&whole),
            whole["peak_rss_bytes"],
            peak(&paged),
            paged["peak_rss_bytes"],
            paged["environment"]
        );
    }
}

/// A `w` × `h` OpenEXR map of half-float `texel(x, y)`.
fn write_exr(path: &Path, w: usize, h: usize, texel: impl Fn(usize, usize) -> [f32; 3] + Sync) {
    use exr::prelude::*;
    let half = |p: Vec2<usize>| {
        let [r, g, b] = texel(p.x(), p.y()).map(f16::from_f32);
        (r, g, b)
    };
    let layer = Layer::new(
        (w, h),
        LayerAttributes::default(),
        Encoding::FAST_LOSSLESS,
        SpecificChannels::rgb(half),
    );
    exr::image::Image::from_layer(layer)
        .write()
        .to_file(path)
        .unwrap();
}

/// A `w` × `h` Radiance map of `texel(x, y)`, flat RGBE scanlines written as they are
/// computed (the shared exponent of the largest channel, as Radiance's `setcolr` makes it).
fn write_hdr(path: &Path, w: usize, h: usize, texel: impl Fn(usize, usize) -> [f32; 3]) {
    use std::io::Write;
    let mut f = std::io::BufWriter::new(std::fs::File::create(path).unwrap());
    write!(f, "#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y {h} +X {w}\n").unwrap();
    for y in 0..h {
        for x in 0..w {
            let c = texel(x, y);
            let m = c.into_iter().fold(0.0f32, f32::max);
            let rgbe = match m < 1e-32 {
                true => [0; 4],
                false => {
                    let e = m.log2().floor() as i32 + 1;
                    let scale = 256.0 / 2f32.powi(e);
                    let q = c.map(|v| (v * scale).min(255.0) as u8);
                    [q[0], q[1], q[2], (e + 128) as u8]
                }
            };
            f.write_all(&rgbe).unwrap();
        }
    }
    f.flush().unwrap();
}

/// `--sky` at its defaults (sun 45° up, turbidity 3) against Mitsuba 3's `sunsky`
/// (`scenes/refs/sky_spheres.exr`, tools/crosscheck.py --sky, 16,384 spp):
/// the path tracer within 4 standard errors over the image and per 16×16 block, the cone
/// integrator's mean within 0.5%.
#[test]
fn under_the_sky_the_integrators_match_mitsuba() {
    let dir = tempfile::tempdir().unwrap();
    let arc = dir.path().join("spheres.canopy");
    ok(&[
        "--quiet",
        "convert",
        s(&scene("env/spheres.glb")),
        "-o",
        s(&arc),
    ]);
    let reference = reference("sky_spheres");
    let run = |out: &str, extra: &[&str]| {
        let flags = [&["--sky", "--seed", "2"][..], extra].concat();
        render(&arc, &dir.path().join(format!("{out}.exr")), &flags).0
    };
    let path = run("path", &["--spp", "512"]);
    assert_mean_within_noise(&path, &reference, "path tracer under the sky");
    assert_blocks_within_noise(&path, &reference, "path tracer under the sky");
    let cone = run("cone", &["--integrator", "cone", "--spp", "128"]);
    assert_mean_within(&cone, &reference, 0.005, "cone integrator under the sky");
}

/// The sun lights as much as it shows: a convex cube of albedo 0.5 facing the sun gains
/// ρ/π · L · Ω · cos θ on its front face, where L is the sun's radiance read off a pixel
/// that sees the sun's disk (its sky taken off) and Ω the solid angle of its 0.5358°
/// aperture. That holds only if the sun's disk, its sampling and its density agree.
#[test]
fn the_sun_lights_as_much_as_it_shows() {
    let dir = tempfile::tempdir().unwrap();
    let arc = cube(dir.path(), 0.5);
    let shot = |name: &str, azimuth: &str, sun: &str| {
        let out = dir.path().join(format!("{name}.exr"));
        let flags = [
            "--sky",
            "--sun-elevation",
            "20",
            "--sun-azimuth",
            azimuth,
            "--sun-strength",
            sun,
            "--spp",
            "16",
        ];
        render(&arc, &out, &flags).0
    };
    // Seen from the default view (from +Z, 45° vertically over 480 rows), the sun 15°
    // toward +X of −Z and 20° up lands on pixel (475, 21), 2.9 pixels inside its rim.
    let at = (21 * 640 + 475) as usize;
    let (seen, sky) = (shot("seen", "15", "1"), shot("sky", "15", "0"));
    let le: Vec<f64> = (0..3)
        .map(|c| seen.pixels[at][c] as f64 - sky.pixels[at][c] as f64)
        .collect();
    assert!(le[0] > 1e3, "the sun's pixel: {le:?}");
    // Behind the camera (azimuth 180°) it lights the front face at cos 20°.
    let (lit, unlit) = (shot("lit", "180", "1"), shot("unlit", "180", "0"));
    let half = (0.5358f64 / 2.0).to_radians();
    let omega = 2.0 * std::f64::consts::PI * (1.0 - half.cos());
    // The front face spans the middle of the image.
    let face = [280, 360, 200, 280];
    for c in 0..3 {
        let channel = |img: &Image| {
            let mut one = img.clone();
            for p in &mut one.pixels {
                p[0] = p[c];
            }
            block_mean(&one, face)
        };
        let ((a, sa), (b, sb)) = (channel(&lit), channel(&unlit));
        let want = 0.5 / std::f64::consts::PI * le[c] * omega * 20f64.to_radians().cos();
        let se = (sa * sa + sb * sb).sqrt();
        assert!(
            (a - b - want).abs() <= 4.0 * se + 1e-4 * want,
            "channel {c}: the sun adds {} where {want} is expected (standard error {se:.2e})",
            a - b
        );
    }
}

/// `--latitude`, `--longitude` and `--datetime` place the sun, and say where; a sun below
/// the horizon at that time is refused by name, as is a time without its UTC offset.
#[test]
fn the_sun_is_placed_by_where_and_when() {
    let dir = tempfile::tempdir().unwrap();
    let arc = cube(dir.path(), 0.5);
    let out = dir.path().join("o.exr");
    let at = |time: &str| {
        [
            "render",
            s(&arc),
            "-o",
            s(&out),
            "--spp",
            "1",
            "--sky",
            "--latitude",
            "48.85",
            "--longitude",
            "2.35",
            "--datetime",
            time,
        ]
        .map(str::to_string)
    };
    let args = at("2026-12-03T12:30:00+01:00");
    let err = succeeds_saying(&args.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(
        err.contains("the sun stands 18.98° up at azimuth 177.46°"),
        "{err}"
    );
    std::fs::remove_file(&out).unwrap();
    let args = at("2026-12-03T22:30:00+01:00");
    let err = fails(&args.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(err.contains("below the horizon"), "{err}");
    assert!(!out.exists());
    let args = at("2026-12-03T12:30");
    let err = fails(&args.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(err.contains("UTC offset"), "{err}");
}

/// A scene file's `[environment]` travels in the archive: rendered with no flag, the archive
/// is lit as `--sky` (or `--env`) with the same values lights the same geometry converted
/// without it, sample for sample, and a note names it. Flags replace it.
#[test]
fn the_scene_files_environment_travels_in_the_archive() {
    let dir = tempfile::tempdir().unwrap();
    let plain = cube(dir.path(), 0.5);
    let map = scene("env/sky.hdr");
    let cases = [
        (
            "[environment]\nsky = true\nsun_elevation_degrees = 30.0\nturbidity = 4.0\n"
                .to_string(),
            vec!["--sky", "--sun-elevation", "30", "--turbidity", "4"],
        ),
        (
            format!(
                "[environment]\nmap = {:?}\nstrength = 2.0\nrotate_degrees = 40.0\n",
                map.to_str().unwrap()
            ),
            vec![
                "--env",
                s(&map),
                "--env-strength",
                "2",
                "--env-rotate",
                "40",
            ],
        ),
    ];
    for (k, (toml, flags)) in cases.iter().enumerate() {
        let sub = dir.path().join(format!("case{k}"));
        std::fs::create_dir(&sub).unwrap();
        let carried = cube_with(&sub, 0.5, toml);
        let out = |name: &str| sub.join(format!("{name}.exr"));
        let base = ["render", "--spp", "8", "--width", "48", "--height", "32"];
        let say = succeeds_saying(&[&base[..], &[s(&carried), "-o", s(&out("carried"))]].concat());
        assert!(
            err_has(&say, "lit by the environment its scene file gave"),
            "{say}"
        );
        ok(&[&base[..], &[s(&plain), "-o", s(&out("flags"))], &flags[..]].concat());
        let (a, b) = (
            Image::read_exr(&out("carried")).unwrap(),
            Image::read_exr(&out("flags")).unwrap(),
        );
        assert_eq!(a.pixels, b.pixels, "case {k}");
        let say = succeeds_saying(
            &[
                &base[..],
                &[s(&carried), "-o", s(&out("replaced")), "--sky"],
            ]
            .concat(),
        );
        assert!(
            err_has(&say, "is replaced by the one the flags give"),
            "{say}"
        );
    }
    for (toml, what) in [
        (
            "[environment]\nsky = true\nmap = \"sky.hdr\"\n",
            "either map",
        ),
        ("[environment]\nmap = \"missing.hdr\"\n", "missing.hdr"),
        (
            "[environment]\nsky = true\nsun_elevation_degrees = 120.0\n",
            "sun",
        ),
    ] {
        let sub = tempfile::tempdir().unwrap();
        let v = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n";
        std::fs::write(sub.path().join("t.obj"), v).unwrap();
        std::fs::write(sub.path().join("scene.toml"), toml).unwrap();
        let err = fails(&[
            "convert",
            s(&sub.path().join("t.obj")),
            "--scene",
            s(&sub.path().join("scene.toml")),
            "-o",
            s(&sub.path().join("t.canopy")),
        ]);
        assert!(err.contains(what), "{err}");
    }
}

fn err_has(stderr: &str, what: &str) -> bool {
    stderr
        .lines()
        .any(|l| l.starts_with("note:") && l.contains(what))
}
