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
            d.abs() < 4.0 * se,
            "{what}: channel {c} mean {} vs reference {}: {d:+.3e} is {:.1} standard errors ({se:.2e})",
            a[c],
            b[c],
            d.abs() / se
        );
    }
}

#[path = "../../src/test_rng.rs"]
mod test_rng;
// Not every test binary draws random numbers.
#[allow(unused_imports)]
pub use test_rng::TestRng;

pub mod textured;

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
    tiny_glb(dir, name, |json, bin| {
        let mut attributes = serde_json::Map::new();
        for (attr, values) in [("TRANSLATION", translations), ("SCALE", scales)] {
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
            let views = json["bufferViews"].as_array_mut().unwrap();
            views.push(serde_json::json!({"buffer": 0, "byteOffset": offset, "byteLength": values.len() * 12}));
            let view = views.len() - 1;
            let accessors = json["accessors"].as_array_mut().unwrap();
            accessors.push(serde_json::json!({"bufferView": view, "componentType": 5126, "count": values.len(), "type": "VEC3"}));
            attributes.insert(attr.into(), (accessors.len() - 1).into());
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
