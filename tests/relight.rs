//! Relighting: a view precomputed once renders light sets as the path tracer does.

mod common;

use canopy::image::Image;
use common::*;
use std::path::Path;

/// `input` converted into `dir` (with a scene file, if any) as NAME.canopy, and its view
/// precomputed as NAME.relight at `size`.
fn precomputed(
    dir: &Path,
    input: &Path,
    scene_file: Option<&Path>,
    name: &str,
    [w, h]: [&str; 2],
) -> (std::path::PathBuf, std::path::PathBuf) {
    let archive = dir.join(format!("{name}.canopy"));
    convert(input, &archive, scene_file);
    let view = dir.join(format!("{name}.relight"));
    let args = [
        "--quiet",
        "relight",
        s(&archive),
        "-o",
        s(&view),
        "--width",
        w,
        "--height",
        h,
    ];
    ok(&args);
    (archive, view)
}

/// The bundled Cornell box converted into `dir`, and its view precomputed at 64×64.
fn prepared(dir: &Path) -> (std::path::PathBuf, std::path::PathBuf) {
    precomputed(dir, &scene("cbox.glb"), None, "cbox", ["64", "64"])
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
        let what = format!("relit, lights {lights:?}");
        assert_relit_like_the_path_tracer(&img, &archive, dir.path(), &extra, &what);
    }
}

/// `img`, relit from `archive`'s view, against the path tracer rendering `archive` with
/// `extra` flags: the 1,024-spp mean's relative standard error is about 0.1% and a relit
/// image's (256 transfer paths a pixel, 16 light samples) about 0.3% at 64×64, so 1.5% is
/// five of the difference's standard errors; and the relit RMSE below the 16-spp path
/// tracer's.
fn assert_relit_like_the_path_tracer(
    img: &Image,
    archive: &Path,
    dir: &Path,
    extra: &[&str],
    what: &str,
) {
    let spp = |n: &'static str, seed: &'static str| [extra, &["--spp", n, "--seed", seed]].concat();
    let (pt, _) = render(archive, &dir.join("pt.exr"), &spp("1024", "0"));
    let (pt16, _) = render(archive, &dir.join("pt16.exr"), &spp("16", "7"));
    assert_mean_within(img, &pt, 0.015, what);
    let (e, e16) = (rmse(img, &pt), rmse(&pt16, &pt));
    assert!(
        e < e16,
        "{what}: relit RMSE {e} is not below the 16-spp path tracer's {e16}"
    );
}

/// An instanced archive relights as the path tracer renders it: the Cornell box's small
/// box placed three times (as it is, mirrored against the other wall, a tenth the size),
/// each copy with light cells of its own and gather points where it stands.
#[test]
fn an_instanced_archive_relights_as_the_path_tracer_renders_it() {
    let dir = tempfile::tempdir().unwrap();
    let places = [[0.0; 3], [556.0, 0.0, 0.0], [180.0, 0.0, 60.0]];
    let scales = [[1.0; 3], [-1.0, 1.0, 1.0], [0.1; 3]];
    let input = gpu_instanced(dir.path(), "boxes.glb", "smallbox", &places, &scales);
    let (archive, view) = precomputed(dir.path(), &input, None, "boxes", ["64", "64"]);
    let img = relit(&view, None, &dir.path().join("relit.exr"));
    let size = ["--width", "64", "--height", "64"];
    assert_relit_like_the_path_tracer(&img, &archive, dir.path(), &size, "relit instances");
}

/// A floor of fine triangles wound every other way (as scans and exported sheets come),
/// lit by a point light between it and a ceiling the camera looks up at: the ceiling's
/// indirect light comes off the floor's lit face. The floor's leaves face both ways at
/// once, so their triangles keep a light cell each; taken as one cell a side, half the
/// triangles would gather light on their unlit face (the image 18% dark here).
#[test]
fn a_floor_wound_both_ways_relights_as_the_path_tracer_renders_it() {
    let dir = tempfile::tempdir().unwrap();
    let n = 160;
    let mut floor = String::new();
    for j in 0..=n {
        for i in 0..=n {
            let (x, z) = (
                4.0 * i as f32 / n as f32 - 2.0,
                4.0 * j as f32 / n as f32 - 2.0,
            );
            floor += &format!("v {x} 0 {z}\n");
        }
    }
    for j in 0..n {
        for i in 0..n {
            let v = |a: usize, b: usize| (j + b) * (n + 1) + i + a + 1;
            let (q, r) = ((v(0, 0), v(0, 1), v(1, 1)), (v(0, 0), v(1, 1), v(1, 0)));
            // Every other quad's triangles wound against the floor's upward face.
            let (a, b) = if (i + j) % 2 == 0 {
                (q, r)
            } else {
                ((q.0, q.2, q.1), (r.0, r.2, r.1))
            };
            floor += &format!("f {} {} {}\nf {} {} {}\n", a.0, a.1, a.2, b.0, b.1, b.2);
        }
    }
    let ceiling = "v -2 1 -2\nv 2 1 -2\nv 2 1 2\nv -2 1 2\nf 1 2 3\nf 1 3 4\n".to_string();
    let toml = r#"
[[camera]]
position = [0.0, 0.2, 1.9]
look_at = [0.0, 1.0, 0.0]
width = 48
height = 48
[[material]]
name = "white"
base_color = [0.8, 0.8, 0.8]
[assign]
"floor.obj" = "white"
"ceiling.obj" = "white"
[[light]]
type = "point"
position = [0.0, 0.3, 0.0]
intensity = 1.0
"#;
    let files = [
        ("floor.obj", floor),
        ("ceiling.obj", ceiling),
        ("scene.toml", toml.to_string()),
    ];
    let archive = obj_scene(dir.path(), &files, "floor.canopy");
    let view = dir.path().join("floor.relight");
    ok(&["--quiet", "relight", s(&archive), "-o", s(&view)]);
    let img = relit(&view, None, &dir.path().join("relit.exr"));
    assert_relit_like_the_path_tracer(&img, &archive, dir.path(), &[], "relit floor");
}

/// A lamp facing up 30 cm under the ceiling, the floor the camera sees lit only by the
/// ceiling around the lamp. A gather point there is close to the lamp, where its light
/// sample is weighed against a cosine ray that meets the lamp; were the ray's hit not found
/// among the lamp's triangles, the cells over the lamp would lose much of their light (the
/// image 22% dark). Light reaches the floor only along paths that find the bright ceiling
/// past the lamp's edge, so both images are noisy. The bound is the standard error of the
/// path tracer's image mean at as many paths a pixel as the precompute follows (RMSE over
/// √pixels, 0.46% of the mean), eight of them: the relit mean, whose cells share their
/// light among the pixels reading them, measured within 5.2 of them over four precompute
/// seeds; the relit image must also be the less noisy.
#[test]
fn a_lamp_close_under_the_ceiling_relights_as_the_path_tracer_renders_it() {
    let dir = tempfile::tempdir().unwrap();
    let toml = r#"
[[camera]]
position = [0.0, 0.6, 1.9]
look_at = [0.0, 0.0, 0.0]
width = 48
height = 48
[[material]]
name = "white"
base_color = [0.8, 0.8, 0.8]
[[material]]
name = "lamp"
base_color = [0.0, 0.0, 0.0]
emission = [4.0, 4.0, 4.0]
double_sided = false
[assign]
"floor.obj" = "white"
"ceiling.obj" = "white"
"lamp.obj" = "lamp"
"#;
    let files = [
        (
            "floor.obj",
            obj_quad([[-2., 0., -2.], [-2., 0., 2.], [2., 0., 2.], [2., 0., -2.]]),
        ),
        (
            "ceiling.obj",
            obj_quad([[-2., 1., -2.], [2., 1., -2.], [2., 1., 2.], [-2., 1., 2.]]),
        ),
        (
            "lamp.obj",
            obj_quad([
                [-0.5, 0.7, -0.5],
                [-0.5, 0.7, 0.5],
                [0.5, 0.7, 0.5],
                [0.5, 0.7, -0.5],
            ]),
        ),
        ("scene.toml", toml.to_string()),
    ];
    let archive = obj_scene(dir.path(), &files, "under.canopy");
    let view = dir.path().join("under.relight");
    ok(&["--quiet", "relight", s(&archive), "-o", s(&view)]);
    let img = relit(&view, None, &dir.path().join("relit.exr"));
    let (pt, _) = render(&archive, &dir.path().join("pt.exr"), &["--spp", "1024"]);
    let (pt16, _) = render(
        &archive,
        &dir.path().join("pt16.exr"),
        &["--spp", "16", "--seed", "7"],
    );
    let (pt256, _) = render(
        &archive,
        &dir.path().join("pt256.exr"),
        &["--spp", "256", "--seed", "7"],
    );
    let se = rmse(&pt256, &pt) / (pt.pixels.len() as f64).sqrt();
    let (a, b) = (img.mean()[0], pt.mean()[0]);
    assert!(
        (a - b).abs() <= 8.0 * se,
        "relit mean {a} vs the path tracer's {b}: {:.1} standard errors ({se:.2e})",
        (a - b).abs() / se
    );
    let (e, e16) = (rmse(&img, &pt), rmse(&pt16, &pt));
    assert!(
        e < e16,
        "relit RMSE {e} is not below the 16-spp path tracer's {e16}"
    );
}

/// The bundled spheres under `scenes/env/sky.hdr`, the archive's own (a scene file's
/// `[environment]`, its extra lines `extra`), with their view precomputed at 48×36.
fn spheres_view(dir: &Path, name: &str, extra: &str) -> (std::path::PathBuf, std::path::PathBuf) {
    let toml = dir.join(format!("{name}.toml"));
    let sky = scene("env/sky.hdr");
    let text = format!("[environment]\nmap = {:?}\n{extra}", sky.to_str().unwrap());
    std::fs::write(&toml, text).unwrap();
    let spheres = scene("env/spheres.glb");
    precomputed(dir, &spheres, Some(&toml), name, ["48", "36"])
}

/// The environment made stronger and turned by a light set: 1.5 times as strong matches
/// the path tracer under the same set; turned 120° it is the view precomputed with the
/// environment turned 120° from the start (the precompute never saw that rotation); and a
/// strength alone scales the relit image exactly.
#[test]
fn the_environment_turns_and_scales_without_a_new_precompute() {
    let dir = tempfile::tempdir().unwrap();
    let (archive, view) = spheres_view(dir.path(), "sky", "");
    let stronger = dir.path().join("stronger.toml");
    std::fs::write(&stronger, "[environment]\nstrength = 1.5\n").unwrap();
    let img = relit(&view, Some(&stronger), &dir.path().join("stronger.exr"));
    let extra = ["--width", "48", "--height", "36", "--lights", s(&stronger)];
    let (pt, _) = render(
        &archive,
        &dir.path().join("pt.exr"),
        &[&extra[..], &["--spp", "1024"]].concat(),
    );
    assert_mean_within(&img, &pt, 0.015, "relit under the stronger environment");
    let turned = dir.path().join("turned.toml");
    std::fs::write(&turned, "[environment]\nstrength = 1.5\nrotate = 120.0\n").unwrap();
    let img = relit(&view, Some(&turned), &dir.path().join("turned.exr"));
    let (_, view120) = spheres_view(
        dir.path(),
        "sky120",
        "rotate_degrees = 120.0\nstrength = 1.5\n",
    );
    let opened = relit(&view120, None, &dir.path().join("opened.exr"));
    let dimmer = dir.path().join("dimmer.toml");
    std::fs::write(&dimmer, "[environment]\nstrength = 0.5\nrotate = 120.0\n").unwrap();
    let third = relit(&view, Some(&dimmer), &dir.path().join("dimmer.exr"));
    for ((a, b), t) in img.pixels.iter().zip(&opened.pixels).zip(&third.pixels) {
        for c in 0..3 {
            let tol = 1e-4 * a[c].abs().max(1e-6);
            assert!(
                (a[c] - b[c]).abs() <= tol,
                "turned {a:?} against opened turned {b:?}"
            );
            assert!(
                (a[c] - 3.0 * t[c]).abs() <= tol,
                "{a:?} against three times {t:?}"
            );
        }
    }
}

/// `scenes/env/NAME.glb` under the bundled sky, precomputed at its 128 × 96 and relit:
/// its image mean within 1.5% of Mitsuba 3's reference `scenes/refs/env_NAME.exr`, and its
/// RMSE against that reference below the path tracer's at 64 spp.
fn assert_sky_scene_relights_as_mitsuba_renders_it(name: &str) {
    let dir = tempfile::tempdir().unwrap();
    let toml = dir.path().join("sky.toml");
    let sky = scene("env/sky.hdr");
    std::fs::write(
        &toml,
        format!("[environment]\nmap = {:?}\n", sky.to_str().unwrap()),
    )
    .unwrap();
    let input = scene(&format!("env/{name}.glb"));
    let (archive, view) = precomputed(dir.path(), &input, Some(&toml), name, ["128", "96"]);
    let img = relit(&view, None, &dir.path().join("relit.exr"));
    let reference = Image::read_exr(&scene(&format!("refs/env_{name}.exr"))).unwrap();
    assert_mean_within(
        &img,
        &reference,
        0.015,
        &format!("{name} under the sky, relit"),
    );
    let (pt64, _) = render(
        &archive,
        &dir.path().join("pt64.exr"),
        &["--spp", "64", "--seed", "7"],
    );
    let (e, e64) = (rmse(&img, &reference), rmse(&pt64, &reference));
    assert!(
        e < e64,
        "{name}: relit RMSE {e} is not below the 64-spp path tracer's {e64}"
    );
}

/// A room lit only by the sky through its window (measured −0.7% to +0.1% over three
/// precompute seeds). The view samples' direct light takes a light sample and a BSDF
/// sample of the sky, combined by MIS; with light samples alone, the sky's light through
/// the window left the relit image noisier than the path tracer's (RMSE 0.030–0.038
/// against 0.029; with both, 0.0135).
#[test]
fn a_room_lit_by_the_sky_through_its_window_relights_as_mitsuba_renders_it() {
    assert_sky_scene_relights_as_mitsuba_renders_it("room");
}

/// A smooth teal glass sphere and a rough amber one under the sky (measured +0.03% +0.27%
/// +0.33%). The sky met through glass by a transfer path is a pixel's sky record, the
/// rough glass's as the smooth one's: a cell gathers light from the side paths land on
/// only, and without the records the amber sphere showed dark and the image was 7.0% dark
/// in red.
#[test]
fn glass_spheres_under_the_sky_relight_as_mitsuba_renders_them() {
    assert_sky_scene_relights_as_mitsuba_renders_it("glass");
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

/// The precompute streams its pixels a band at a time and its rows through scratch files,
/// and draws the cells' gather points a range of cells at a time (under 2 MiB, about four
/// ranges of the Cornell box's 37,000 points): the file is the same whatever the thread
/// count or the budget, and nothing but the file is left beside it.
#[test]
fn a_precompute_is_the_same_file_at_any_thread_count_and_budget() {
    let dir = tempfile::tempdir().unwrap();
    let archive = dir.path().join("cbox.canopy");
    convert(&scene("cbox.glb"), &archive, None);
    let views: Vec<Vec<u8>> = [["1", "unlimited"], ["2", "2MiB"]]
        .iter()
        .map(|[threads, budget]| {
            let view = dir.path().join(format!("{threads}.relight"));
            let mut args = vec!["--quiet", "relight", s(&archive), "-o", s(&view)];
            // 80 × 64 pixels: more than one band of 4,096.
            args.extend(["--width", "80", "--height", "64", "--threads", threads]);
            if *budget != "unlimited" {
                args.extend(["--mem-budget", budget]);
            }
            ok(&args);
            std::fs::read(view).unwrap()
        })
        .collect();
    assert!(views[0] == views[1], "the two precomputes differ");
    let mut left: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    left.sort();
    assert_eq!(left, ["1.relight", "2.relight", "cbox.canopy"]);
}

#[test]
fn bad_relight_files_and_flags_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let (archive, view) = prepared(dir.path());
    let out = dir.path().join("x.exr");
    let bytes = std::fs::read(&view).unwrap();
    let bad = dir.path().join("bad.relight");
    std::fs::write(&bad, &bytes[..bytes.len() / 2]).unwrap();
    assert!(fails(&["relight", s(&bad), "-o", s(&out)]).contains("the header's counts make"));
    let mut flipped = bytes.clone();
    flipped[200] ^= 1;
    std::fs::write(&bad, &flipped).unwrap();
    let e = fails(&["relight", s(&bad), "-o", s(&out)]);
    assert!(e.contains("not a valid relight file") && e.contains("checksum"));
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

/// One HTTP/1.0 exchange with the server at `addr`: (status code, body).
fn http(addr: &str, request: &str) -> (u16, Vec<u8>) {
    let (code, _, body) = exchange(addr, request);
    (code, body)
}

/// One HTTP/1.0 exchange with the server at `addr`: (status code, header lines, body).
fn exchange(addr: &str, request: &str) -> (u16, String, Vec<u8>) {
    use std::io::{Read, Write};
    let mut s = std::net::TcpStream::connect(addr).unwrap();
    // A server that refuses a body early may close before reading all of it.
    s.write_all(request.as_bytes()).ok();
    let mut out = Vec::new();
    s.read_to_end(&mut out).ok();
    let end = out
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .expect("a header")
        + 4;
    let head = String::from_utf8_lossy(&out[..end]).into_owned();
    let code = head.split(' ').nth(1).unwrap().parse().unwrap();
    (code, head, out[end..].to_vec())
}

fn post(addr: &str, body: &str) -> (u16, Vec<u8>) {
    http(addr, &post_request(body))
}

fn post_request(body: &str) -> String {
    format!(
        "POST /render HTTP/1.0\r\nContent-Length: {}\r\n\r\n{body}",
        body.len()
    )
}

/// A light moved or added is traced a slice a frame: the server answers at once with part
/// of its rays and says so, and the fourth request of the same set gives the image the
/// command line renders whole. The first frame's mean is the whole image's, within the
/// noise of a quarter of the samples (a slice left unweighted would be a quarter as bright).
#[test]
fn a_moved_light_refines_to_the_image_rendered_whole() {
    let dir = tempfile::tempdir().unwrap();
    let (_, view) = prepared(dir.path());
    let json = "{\"light\": [{\"type\": \"point\", \"position\": [150.0, 300.0, 200.0], \"intensity\": 20000.0}]}";
    let (_server, addr) = relight_server(&view);
    let rgb = |png: &[u8]| image::load_from_memory(png).unwrap().to_rgb8().into_raw();
    let frames: Vec<(bool, Vec<u8>)> = (0..4)
        .map(|_| {
            let (code, head, png) = exchange(&addr, &post_request(json));
            assert_eq!(code, 200, "{}", String::from_utf8_lossy(&png));
            (head.contains("X-Frame-Complete: 1"), rgb(&png))
        })
        .collect();
    let complete: Vec<bool> = frames.iter().map(|f| f.0).collect();
    assert_eq!(complete, [false, false, false, true]);
    let set = dir.path().join("set.toml");
    let toml =
        "[[light]]\ntype = \"point\"\nposition = [150.0, 300.0, 200.0]\nintensity = 20000.0\n";
    std::fs::write(&set, toml).unwrap();
    let whole = dir.path().join("whole.png");
    ok(&["relight", s(&view), "--lights", s(&set), "-o", s(&whole)]);
    // The same samples, summed in one pass or four: equal up to float rounding.
    let whole = rgb(&std::fs::read(&whole).unwrap());
    let most = whole
        .iter()
        .zip(&frames[3].1)
        .map(|(&a, &b)| a.abs_diff(b))
        .max();
    assert!(
        most <= Some(1),
        "the refined frame differs from the image rendered whole by {most:?} of 255"
    );
    let mean = |p: &[u8]| p.iter().map(|&v| v as f64).sum::<f64>() / p.len() as f64;
    let (first, last) = (mean(&frames[0].1), mean(&frames[3].1));
    assert!(
        (first / last - 1.0).abs() < 0.05,
        "first frame's mean {first}, whole {last}"
    );
}

#[test]
fn the_server_answers_light_sets_and_survives_bad_requests() {
    let dir = tempfile::tempdir().unwrap();
    let (_, view) = prepared(dir.path());
    assert!(fails(&["relight", s(&view), "--serve", "0.0.0.0:0"]).contains("loopback"));
    let (_server, addr) = relight_server(&view);
    let (code, page) = http(&addr, "GET / HTTP/1.0\r\n\r\n");
    assert_eq!(code, 200);
    assert!(String::from_utf8_lossy(&page).contains("/render"));
    let (code, lights) = http(&addr, "GET /lights HTTP/1.0\r\n\r\n");
    assert_eq!(code, 200);
    assert!(String::from_utf8_lossy(&lights).contains("\"light\""));
    let bad = [
        ("garbage", 400),
        ("{\"emitter\": [{\"material\": 99}]}", 400),
        ("{\"light\": [{\"type\": \"point\"}]}", 400),
        ("{\"lamp\": []}", 400),
        ("{\"environment\": {\"strength\": 2}}", 400),
    ];
    for (body, want) in bad {
        let (code, msg) = post(&addr, body);
        assert_eq!(code, want, "{body}: {}", String::from_utf8_lossy(&msg));
        assert!(!msg.is_empty(), "{body}: no reason given");
    }
    assert_eq!(http(&addr, "GET /nothing HTTP/1.0\r\n\r\n").0, 404);
    assert_eq!(http(&addr, "DELETE /render HTTP/1.0\r\n\r\n").0, 405);
    let huge = "x".repeat((1 << 20) + 10);
    assert_eq!(post(&addr, &huge).0, 413);
    // After all that, a good light set still renders: a PNG of the view's size, brighter
    // under a stronger lamp.
    let mean = |png: &[u8]| {
        let img = image::load_from_memory(png).unwrap().to_rgb8();
        assert_eq!(img.dimensions(), (64, 64));
        img.pixels().map(|p| p[0] as f64).sum::<f64>() / 4096.0
    };
    let (code, one) = post(
        &addr,
        "{\"emitter\": [{\"material\": 4, \"strength\": 0.25}]}",
    );
    assert_eq!(code, 200);
    let (_, two) = post(&addr, "{\"emitter\": [{\"material\": 4, \"strength\": 1}]}");
    assert!(
        mean(&two) > 1.3 * mean(&one),
        "{} vs {}",
        mean(&two),
        mean(&one)
    );
}
