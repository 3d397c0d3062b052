#![allow(dead_code)]
//! Helpers shared by the integration tests.

use canopy::image::Image;
use std::path::{Path, PathBuf};
use std::process::Output;

pub fn scene(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("scenes")
        .join(name)
}

pub fn canopy(args: &[&str]) -> Output {
    std::process::Command::new(env!("CARGO_BIN_EXE_canopy"))
        .args(args)
        .output()
        .expect("run canopy")
}

/// Runs canopy and asserts success, returning stdout.
pub fn ok(args: &[&str]) -> String {
    let out = canopy(args);
    assert!(
        out.status.success(),
        "canopy {args:?} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).unwrap()
}

/// Runs canopy, asserts success, and returns stderr (its warnings and notes).
pub fn succeeds_saying(args: &[&str]) -> String {
    let out = canopy(args);
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(out.status.success(), "canopy {args:?} failed: {err}");
    err
}

/// Runs canopy, asserts a clean failure (exit 1 for bad input, 2 for bad arguments; no
/// panic, no signal) and returns stderr.
pub fn fails(args: &[&str]) -> String {
    let out = canopy(args);
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(
        matches!(out.status.code(), Some(1 | 2)),
        "canopy {args:?} should fail cleanly, got {:?}: {err}",
        out.status
    );
    assert!(!err.contains("panicked"), "canopy {args:?} panicked: {err}");
    err
}

pub fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

pub fn convert(input: &Path, out: &Path, scene: Option<&Path>) {
    let mut args = vec!["--quiet", "convert", s(input), "-o", s(out)];
    if let Some(sc) = scene {
        args.extend(["--scene", s(sc)]);
    }
    ok(&args);
}

/// Renders and returns the image and the stats JSON.
pub fn render(archive: &Path, out: &Path, extra: &[&str]) -> (Image, serde_json::Value) {
    let stats = out.with_extension("json");
    let mut args = vec![
        "--quiet",
        "render",
        s(archive),
        "-o",
        s(out),
        "--stats",
        s(&stats),
    ];
    args.extend_from_slice(extra);
    ok(&args);
    let img = Image::read_exr(&out.with_extension("exr")).unwrap();
    let json = serde_json::from_str(&std::fs::read_to_string(&stats).unwrap()).unwrap();
    (img, json)
}

/// `render` with `integrator` at `spp` samples and `width` × `height` pixels: the image.
pub fn render_sized(
    archive: &Path,
    out: &Path,
    integrator: &str,
    spp: u32,
    [width, height]: [u32; 2],
) -> Image {
    let (spp, width, height) = (spp.to_string(), width.to_string(), height.to_string());
    let flags = [
        "--integrator",
        integrator,
        "--spp",
        &spp,
        "--width",
        &width,
        "--height",
        &height,
    ];
    render(archive, out, &flags).0
}

pub fn all_finite(img: &Image) -> bool {
    img.pixels
        .iter()
        .flatten()
        .all(|v| v.is_finite() && *v >= 0.0)
}

pub fn rmse(a: &Image, b: &Image) -> f64 {
    canopy::metrics::error(a, b, canopy::metrics::Metric::Rmse).unwrap()
}

pub fn reference(name: &str) -> Image {
    Image::read_exr(&scene(&format!("refs/{name}.exr"))).unwrap()
}

pub fn assert_mean_within(img: &Image, refimg: &Image, tol: f64, what: &str) {
    let (a, b) = (img.mean(), refimg.mean());
    for c in 0..3 {
        let rel = a[c] / b[c] - 1.0;
        assert!(
            rel.abs() < tol,
            "{what}: channel {c} mean {} vs reference {} ({rel:+.4})",
            a[c],
            b[c]
        );
    }
}

/// Rewrites a glb with every scene node translated by `offset` (cameras included).
pub fn translated_glb(src: &Path, dst: &Path, offset: f64) {
    let data = std::fs::read(src).unwrap();
    let jlen = u32::from_le_bytes(data[12..16].try_into().unwrap()) as usize;
    let mut doc: serde_json::Value = serde_json::from_slice(&data[20..20 + jlen]).unwrap();
    for n in doc["nodes"].as_array_mut().unwrap() {
        if let Some(m) = n.get_mut("matrix") {
            for k in 12..15 {
                m[k] = (m[k].as_f64().unwrap() + offset).into();
            }
        } else {
            n["translation"] = serde_json::json!([offset, offset, offset]);
        }
    }
    let mut json = serde_json::to_vec(&doc).unwrap();
    while !json.len().is_multiple_of(4) {
        json.push(b' ');
    }
    let rest = &data[20 + jlen..];
    let mut out = Vec::new();
    out.extend_from_slice(&data[0..8]);
    out.extend_from_slice(&((12 + 8 + json.len() + rest.len()) as u32).to_le_bytes());
    out.extend_from_slice(&(json.len() as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(&json);
    out.extend_from_slice(rest);
    std::fs::write(dst, out).unwrap();
}

/// A binary PLY heightfield of 2·n² triangles over [0, n]² in x and z, its heights in
/// [0, 0.6]: a large input that is quick to write.
pub fn grid_ply(path: &Path, n: usize) {
    let mut bytes = format!("ply\nformat binary_little_endian 1.0\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nelement face {}\nproperty list uchar uint vertex_indices\nend_header\n", (n + 1) * (n + 1), 2 * n * n).into_bytes();
    for j in 0..=n {
        for i in 0..=n {
            for c in [i as f32, ((i * j) % 7) as f32 * 0.1, j as f32] {
                bytes.extend_from_slice(&c.to_le_bytes());
            }
        }
    }
    for j in 0..n {
        for i in 0..n {
            let a = (j * (n + 1) + i) as u32;
            for t in [
                [a, a + 1, a + n as u32 + 1],
                [a + 1, a + n as u32 + 2, a + n as u32 + 1],
            ] {
                bytes.push(3);
                for k in t {
                    bytes.extend_from_slice(&k.to_le_bytes());
                }
            }
        }
    }
    std::fs::write(path, bytes).unwrap();
}

/// The image mean agrees with the reference's within 4 standard errors of their difference:
/// per channel, the squared RMSE is the sum of both images' per-pixel variances (plus any
/// bias), so RMSE/√pixels bounds the standard error of the difference of the means.
pub fn assert_mean_within_noise(img: &Image, r: &Image, what: &str) {
    let n = img.pixels.len() as f64;
    let (a, b) = (img.mean(), r.mean());
    for c in 0..3 {
        let mse = img
            .pixels
            .iter()
            .zip(&r.pixels)
            .map(|(x, y)| (x[c] as f64 - y[c] as f64).powi(2))
            .sum::<f64>()
            / n;
        let se = (mse / n).sqrt();
        let d = a[c] - b[c];
        assert!(
            d.abs() <= 4.0 * se,
            "{what}: channel {c} mean {} vs reference {}: {d:+.3e} is {:.1} standard errors ({se:.2e})",
            a[c],
            b[c],
            d.abs() / se
        );
    }
}

/// The image's 16×16 blocks (the last row and column may be smaller): each block's corner
/// and its pixels' indices.
pub fn blocks(img: &Image) -> impl Iterator<Item = (u32, u32, Vec<usize>)> + '_ {
    (0..img.height).step_by(16).flat_map(move |by| {
        (0..img.width).step_by(16).map(move |bx| {
            let at = (by..(by + 16).min(img.height))
                .flat_map(|y| {
                    (bx..(bx + 16).min(img.width)).map(move |x| (y * img.width + x) as usize)
                })
                .collect();
            (bx, by, at)
        })
    })
}

/// Per 16×16 block, the block means of `img` and `r` agree within 4 standard errors of
/// their difference (from the pixels' squared differences, as `assert_mean_within_noise`).
pub fn assert_blocks_within_noise(img: &Image, r: &Image, what: &str) {
    assert_blocks_within_noise_and(img, r, 0.0, what)
}

/// `assert_blocks_within_noise` with `rel` of the reference block's mean allowed besides:
/// for converged images whose renderers decode the same texels with slightly different
/// arithmetic.
pub fn assert_blocks_within_noise_and(img: &Image, r: &Image, rel: f64, what: &str) {
    for (bx, by, at) in blocks(img) {
        let n = at.len() as f64;
        for c in 0..3 {
            let d: Vec<f64> = at
                .iter()
                .map(|&i| img.pixels[i][c] as f64 - r.pixels[i][c] as f64)
                .collect();
            let mean = d.iter().sum::<f64>() / n;
            let se = (d.iter().map(|x| x * x).sum::<f64>() / n / n).sqrt();
            let floor = rel * at.iter().map(|&i| r.pixels[i][c] as f64).sum::<f64>() / n;
            assert!(
                mean.abs() <= 4.0 * se + floor,
                "{what}: block ({bx}, {by}) channel {c} differs by {mean:.3e} (standard error {se:.2e})"
            );
        }
    }
}

/// Per 16×16 block and channel, `img`'s mean within `tol` of `r`'s, relative: the image's
/// structure holds, not only its total.
pub fn assert_blocks_within(img: &Image, r: &Image, tol: f64, what: &str) {
    for (bx, by, at) in blocks(img) {
        for c in 0..3 {
            let sum = |im: &Image| at.iter().map(|&i| im.pixels[i][c] as f64).sum::<f64>();
            let rel = sum(img) / sum(r) - 1.0;
            assert!(
                rel.abs() <= tol,
                "{what}: block ({bx}, {by}) channel {c} is {rel:+.4} off"
            );
        }
    }
}

#[path = "../../src/test_rng.rs"]
mod test_rng;
// Not every test binary draws random numbers.
#[allow(unused_imports)]
pub use test_rng::TestRng;

pub mod textured;

/// A glTF document of one mesh node (`positions`, `indices`, its one material
/// `material`), its buffer inline as a data URI, no camera and no light; the caller adds
/// what else it needs.
pub fn inline_mesh_gltf(
    positions: &[[f32; 3]],
    indices: &[u32],
    material: serde_json::Value,
    used: &[&str],
) -> serde_json::Value {
    let mut bin: Vec<u8> = positions
        .iter()
        .flatten()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    let at = bin.len();
    bin.extend(indices.iter().flat_map(|i| i.to_le_bytes()));
    let bound = |f: fn(f32, f32) -> f32, init: f32| {
        [0, 1, 2].map(|a| positions.iter().map(|p| p[a]).fold(init, f))
    };
    use base64::Engine;
    let uri = format!(
        "data:application/octet-stream;base64,{}",
        base64::engine::general_purpose::STANDARD.encode(&bin)
    );
    serde_json::json!({
        "asset": {"version": "2.0"},
        "scene": 0, "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1, "material": 0}]}],
        "materials": [material],
        "extensionsUsed": used,
        "buffers": [{"byteLength": bin.len(), "uri": uri}],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": at},
            {"buffer": 0, "byteOffset": at, "byteLength": bin.len() - at}
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": positions.len(), "type": "VEC3",
             "min": bound(f32::min, f32::INFINITY), "max": bound(f32::max, f32::NEG_INFINITY)},
            {"bufferView": 1, "componentType": 5125, "count": indices.len(), "type": "SCALAR"}
        ]
    })
}

/// cbox.glb with its JSON and BIN chunk edited, written to `dir/name`.
pub fn tiny_glb(
    dir: &Path,
    name: &str,
    edit: impl Fn(&mut serde_json::Value, &mut Vec<u8>),
) -> PathBuf {
    let glb = std::fs::read(scene("cbox.glb")).unwrap();
    let jlen = u32::from_le_bytes(glb[12..16].try_into().unwrap()) as usize;
    let mut json: serde_json::Value = serde_json::from_slice(&glb[20..20 + jlen]).unwrap();
    let mut bin = glb[20 + jlen + 8..].to_vec();
    edit(&mut json, &mut bin);
    let mut j = serde_json::to_vec(&json).unwrap();
    while !j.len().is_multiple_of(4) {
        j.push(b' ');
    }
    let mut out = b"glTF".to_vec();
    out.extend(2u32.to_le_bytes());
    out.extend(((12 + 8 + j.len() + 8 + bin.len()) as u32).to_le_bytes());
    out.extend((j.len() as u32).to_le_bytes());
    out.extend(b"JSON");
    out.extend(&j);
    out.extend((bin.len() as u32).to_le_bytes());
    out.extend(b"BIN\0");
    out.extend(&bin);
    let p = dir.join(name);
    std::fs::write(&p, &out).unwrap();
    p
}

/// cbox.glb with node `node` instanced by EXT_mesh_gpu_instancing: `translations` as its
/// TRANSLATION accessor and `scales` (if any) as SCALE.
pub fn gpu_instanced(
    dir: &Path,
    name: &str,
    node: &str,
    translations: &[[f32; 3]],
    scales: &[[f32; 3]],
) -> PathBuf {
    gpu_instanced_rotated(dir, name, node, translations, &[], scales)
}

/// `gpu_instanced` with a rotation per instance (unit quaternions x, y, z, w).
pub fn gpu_instanced_rotated(
    dir: &Path,
    name: &str,
    node: &str,
    translations: &[[f32; 3]],
    rotations: &[[f32; 4]],
    scales: &[[f32; 3]],
) -> PathBuf {
    let flat = |v: &[[f32; 3]]| v.iter().map(|a| a.to_vec()).collect::<Vec<_>>();
    let columns = [
        ("TRANSLATION", flat(translations), "VEC3"),
        (
            "ROTATION",
            rotations.iter().map(|a| a.to_vec()).collect(),
            "VEC4",
        ),
        ("SCALE", flat(scales), "VEC3"),
    ];
    tiny_glb(dir, name, |json, bin| {
        let mut attributes = serde_json::Map::new();
        for (attr, values, ty) in &columns {
            if values.is_empty() {
                continue;
            }
            while bin.len() % 4 != 0 {
                bin.push(0);
            }
            let offset = bin.len();
            for v in values.iter().flatten() {
                bin.extend(v.to_le_bytes());
            }
            let bytes = bin.len() - offset;
            let views = json["bufferViews"].as_array_mut().unwrap();
            views.push(serde_json::json!({"buffer": 0, "byteOffset": offset, "byteLength": bytes}));
            let view = views.len() - 1;
            let accessors = json["accessors"].as_array_mut().unwrap();
            accessors.push(serde_json::json!({"bufferView": view, "componentType": 5126, "count": values.len(), "type": ty}));
            attributes.insert(attr.to_string(), (accessors.len() - 1).into());
        }
        json["buffers"][0]["byteLength"] = bin.len().into();
        json["extensionsUsed"] = serde_json::json!(["EXT_mesh_gpu_instancing"]);
        let node = json["nodes"]
            .as_array_mut()
            .unwrap()
            .iter_mut()
            .find(|n| n["name"] == node)
            .unwrap();
        node["extensions"] =
            serde_json::json!({"EXT_mesh_gpu_instancing": {"attributes": attributes}});
    })
}

/// A UV sphere with outward vertex normals, as OBJ text.
pub fn sphere_obj(c: [f32; 3], r: f32) -> String {
    let (nu, nv) = (32, 16);
    let mut s = String::new();
    let mut normals = Vec::new();
    for j in 0..=nv {
        let th = std::f32::consts::PI * j as f32 / nv as f32;
        for i in 0..nu {
            let ph = 2.0 * std::f32::consts::PI * i as f32 / nu as f32;
            let n = [th.sin() * ph.cos(), th.cos(), th.sin() * ph.sin()];
            s += &format!(
                "v {} {} {}\n",
                c[0] + r * n[0],
                c[1] + r * n[1],
                c[2] + r * n[2]
            );
            normals.push(n);
        }
    }
    for n in normals {
        s += &format!("vn {} {} {}\n", n[0], n[1], n[2]);
    }
    let idx = |i: usize, j: usize| j * nu + i % nu + 1;
    for j in 0..nv {
        for i in 0..nu {
            let (a, b, c, d) = (idx(i, j), idx(i + 1, j), idx(i + 1, j + 1), idx(i, j + 1));
            if j > 0 {
                s += &format!("f {a}//{a} {b}//{b} {c}//{c}\n");
            }
            if j < nv - 1 {
                s += &format!("f {a}//{a} {c}//{c} {d}//{d}\n");
            }
        }
    }
    s
}

/// OBJ text of one quad, its four corners in order as two triangles: its face's normal is
/// (v1 − v0) × (v2 − v0).
pub fn obj_quad(v: [[f32; 3]; 4]) -> String {
    let vs: String = v
        .iter()
        .map(|p| format!("v {} {} {}\n", p[0], p[1], p[2]))
        .collect();
    vs + "f 1 2 3\nf 1 3 4\n"
}

/// Writes `files` into `dir` and converts their OBJ files, in order, with the
/// `scene.toml` among them into the archive `name`.
pub fn obj_scene(
    dir: &std::path::Path,
    files: &[(&str, String)],
    name: &str,
) -> std::path::PathBuf {
    for (f, text) in files {
        std::fs::write(dir.join(f), text).unwrap();
    }
    let p = |f: &str| dir.join(f).to_str().unwrap().to_string();
    let mut args = vec!["--quiet".to_string(), "convert".into()];
    args.extend(
        files
            .iter()
            .filter(|(f, _)| f.ends_with(".obj"))
            .map(|(f, _)| p(f)),
    );
    args.extend(["--scene".into(), p("scene.toml"), "-o".into(), p(name)]);
    ok(&args.iter().map(String::as_str).collect::<Vec<_>>());
    dir.join(name)
}

/// A lamp (a sphere of radius 0.5 and radiance 20) before a dark wall, seen by a 32×32
/// camera: its silhouette is where a pixel's samples scatter most.
pub fn lamp_scene(dir: &Path) -> PathBuf {
    let files = [
        ("lamp.obj", sphere_obj([0.0, 0.0, 0.0], 0.5)),
        (
            "wall.obj",
            "v -4 -4 -1\nv 4 -4 -1\nv 4 4 -1\nv -4 4 -1\nf 1 2 3\nf 1 3 4\n".into(),
        ),
        (
            "scene.toml",
            r#"
[[camera]]
position = [0.0, 0.0, 3.0]
look_at = [0.0, 0.0, 0.0]
width = 32
height = 32
[[material]]
name = "wall"
base_color = [0.05, 0.05, 0.05]
[[material]]
name = "lamp"
base_color = [0.0, 0.0, 0.0]
emission = [20.0, 20.0, 20.0]
[assign]
"wall.obj" = "wall"
"lamp.obj" = "lamp"
"#
            .into(),
        ),
    ];
    obj_scene(dir, &files, "l.canopy")
}

/// A bright lamp sphere seen directly against a dark wall: the noise is mostly the lamp's
/// coverage of its silhouette pixels. Edge rays must find those pixels, leave the image's
/// mean where the path tracer puts it (they estimate the same pixel integral), and cut the
/// error at equal samples, under `integrator` (cone or pbgi); in the first
/// pass, before any sample found a silhouette, every pixel takes them.
pub fn edge_rays_case(integrator: &str) {
    let dir = tempfile::tempdir().unwrap();
    let arc = lamp_scene(dir.path());
    let (truth, _) = render(&arc, &dir.path().join("p.exr"), &["--spp", "2048"]);
    let mut err = [0.0; 2];
    for (i, k) in ["0", "8"].iter().enumerate() {
        for seed in ["1", "2", "3"] {
            let (img, stats) = render(
                &arc,
                &dir.path().join(format!("c{k}_{seed}.exr")),
                &[
                    "--integrator",
                    integrator,
                    "--spp",
                    "32",
                    "--edge-rays",
                    k,
                    "--seed",
                    seed,
                    // PBGI's pixel split would also take more samples at the silhouette.
                    "--pixel-split",
                    "1",
                ],
            );
            assert!(all_finite(&img));
            assert_mean_within(
                &img,
                &truth,
                0.01,
                &format!("{integrator}, edge rays {k}, seed {seed}"),
            );
            // The lamp's 14-pixel disc: a band about 3 pixels wide around its outline.
            let edges = stats["edge_pixels"].as_u64().unwrap();
            assert!((40..=300).contains(&edges), "{edges} edge pixels");
            err[i] += rmse(&img, &truth).powi(2);
        }
    }
    assert!(err[1] < 0.5 * err[0], "squared error {err:?}");
    let first: Vec<f64> = ["0", "8"]
        .iter()
        .map(|k| {
            let flags = ["--integrator", integrator, "--spp", "1", "--edge-rays", k];
            let (img, _) = render(&arc, &dir.path().join(format!("f{k}.exr")), &flags);
            rmse(&img, &truth).powi(2)
        })
        .collect();
    assert!(
        first[1] < 0.5 * first[0],
        "first pass, squared error {first:?}"
    );
}

/// Whether `prog` is on the PATH.
pub fn installed(prog: &str) -> bool {
    std::process::Command::new("sh")
        .args(["-c", &format!("command -v {prog}")])
        .output()
        .is_ok_and(|o| o.status.success())
}

/// Says `test` skipped, and why, where a run's log shows it (straight to standard error: the
/// test harness would hold back `eprintln!`), and leaves `marker` for `.ci/run`, which fails
/// a run where the test skipped although what it needs is installed.
pub fn skipped(marker: &Path, test: &str, why: &str) {
    use std::io::Write;
    let line = format!("{test} SKIPPED: {why}\n");
    std::io::stderr().write_all(line.as_bytes()).ok();
    std::fs::write(marker, line).ok();
}

/// A child process killed when the test ends, however it ends.
pub struct Killed(pub std::process::Child);

impl Drop for Killed {
    fn drop(&mut self) {
        self.0.kill().ok();
        self.0.wait().ok();
    }
}

/// `canopy relight VIEW --serve` on a free loopback port: the server (killed when dropped)
/// and the address it printed (`127.0.0.1:PORT`).
pub fn relight_server(view: &Path) -> (Killed, String) {
    use std::io::BufRead;
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_canopy"))
        .args(["relight", s(view), "--serve", "127.0.0.1:0"])
        .stdout(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let mut line = String::new();
    std::io::BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    let server = Killed(child);
    let at = line.split("http://").nth(1).unwrap().split('/').next();
    (server, at.unwrap().to_string())
}
