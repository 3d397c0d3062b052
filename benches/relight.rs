//! One relit frame of a precomputed view: every light's strength changed (their shares of
//! the image kept, scaled: the sum of the shares and the transfer's product), and a point
//! light added where the frame before had it elsewhere: its first frame (a slice of its
//! share traced, then the same) and its complete image (every slice).
//!
//! With `CANOPY_RELIGHT_VIEW=VIEW.relight` it relights that view (e.g. the 1 M-triangle
//! scene of docs/relighting.md); without, the bundled bunny_box at 128², precomputed first.

use canopy::convert::{convert, ConvertOptions};
use canopy::light::LightSet;
use canopy::relight::{prepare, PrepareOptions, RelightOptions, Relighter};
use criterion::{criterion_group, criterion_main, Criterion};
use std::path::{Path, PathBuf};

/// The view benchmarked, and the directory holding it if it was made here.
fn view() -> (PathBuf, Option<tempfile::TempDir>) {
    if let Some(v) = std::env::var_os("CANOPY_RELIGHT_VIEW") {
        return (PathBuf::from(v), None);
    }
    let dir = tempfile::tempdir().unwrap();
    let archive = dir.path().join("bunny_box.canopy");
    let scene = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/bunny_box.glb");
    convert(&ConvertOptions::new(vec![scene], archive.clone())).unwrap();
    let view = dir.path().join("bunny_box.relight");
    prepare(&PrepareOptions {
        archive,
        output: view.clone(),
        camera: None,
        width: Some(128),
        height: Some(128),
        spp: 16,
        paths: 16,
        coefficients: 128,
        seed: 0,
        mem_budget: None,
        threads: None,
        progress: false,
    })
    .unwrap();
    (view, Some(dir))
}

fn set(json: &str) -> LightSet {
    LightSet::from_json(json, "bench").unwrap()
}

fn relight(c: &mut Criterion) {
    let (view, _dir) = view();
    let o = RelightOptions {
        view: view.clone(),
        lights: None,
        light_samples: 4,
        mem_budget: None,
        threads: None,
    };
    let mut r = Relighter::open(&o, (view.with_extension("exr"), None)).unwrap();
    // Every lamp the archive has, by index; the strength alternates so each frame differs.
    let lamps: Vec<usize> = (0..r.setup.scene.materials.len())
        .filter(|&m| r.setup.scene.materials[m].is_emissive())
        .collect();
    let own: Vec<f32> = r
        .setup
        .scene
        .cache
        .archive
        .lights
        .iter()
        .map(|l| l.intensity)
        .collect();
    // Every lamp and every punctual light at `s` times its own strength.
    let strength = |s: f32, added: &str| {
        let e: Vec<String> = lamps
            .iter()
            .map(|m| format!("{{\"material\": {m}, \"strength\": {s}}}"))
            .collect();
        let l: Vec<String> = own
            .iter()
            .enumerate()
            .map(|(k, i)| format!("{{\"light\": {k}, \"intensity\": {}}}", i * s))
            .chain((!added.is_empty()).then(|| added.to_string()))
            .collect();
        format!(
            "{{\"emitter\": [{}], \"light\": [{}]}}",
            e.join(","),
            l.join(",")
        )
    };
    let (lo, hi) = {
        let h = &r.setup.scene.cache.archive.header;
        (h.bounds_min, h.bounds_max)
    };
    // Every share traced whole first: a strength change then traces nothing.
    r.image().unwrap();
    let mut g = c.benchmark_group("relight");
    g.sample_size(10);
    let mut k = 0u32;
    g.bench_function("strength changed", |b| {
        b.iter(|| {
            k += 1;
            r.set_lights(&set(&strength(1.0 + (k % 2) as f32, "")))
                .unwrap();
            r.frame().unwrap()
        })
    });
    // A moved light's first frame traces a slice of its share; `image` traces it whole.
    let moved = |r: &mut Relighter, k: u32| {
        let t = (k % 16) as f32 / 16.0;
        let p: Vec<f32> = (0..3)
            .map(|i| lo[i] + (hi[i] - lo[i]) * (0.2 + 0.6 * t))
            .collect();
        let d = (hi[0] - lo[0]).powi(2);
        let added = format!("{{\"type\": \"point\", \"position\": {p:?}, \"intensity\": {d}}}");
        r.set_lights(&set(&strength(1.0, &added))).unwrap();
    };
    g.bench_function("point light moved, first frame", |b| {
        b.iter(|| {
            k += 1;
            moved(&mut r, k);
            r.frame().unwrap()
        })
    });
    g.bench_function("point light moved, complete", |b| {
        b.iter(|| {
            k += 1;
            moved(&mut r, k);
            r.image().unwrap()
        })
    });
    g.finish();
}

criterion_group!(benches, relight);
criterion_main!(benches);
