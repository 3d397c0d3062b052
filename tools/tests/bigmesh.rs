//! `bigmesh` writes the same copies as a PLY of every triangle and as a glb of one mesh with
//! an instance per copy: converted, both place the same triangles in the same place, the
//! glb's stored once.

use canopy::convert::{convert, ConvertOptions};
use canopy_format::Archive;
use std::path::Path;

fn bigmesh(out: &Path) {
    let bunny = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/bunny.ply");
    let status = std::process::Command::new(env!("CARGO_BIN_EXE_bigmesh"))
        .args([
            bunny.to_str().unwrap(),
            "--copies",
            "5",
            "--seed",
            "3",
            "-o",
        ])
        .arg(out)
        .status()
        .unwrap();
    assert!(status.success());
}

#[test]
fn instanced_glb_and_ply_hold_the_same_copies() {
    let dir = tempfile::tempdir().unwrap();
    let header = |name: &str, flatten: bool| {
        let input = dir.path().join(name);
        if !input.exists() {
            bigmesh(&input);
        }
        let flat = if flatten { ".flat" } else { "" };
        let out = dir.path().join(format!("{name}{flat}.canopy"));
        let mut o = ConvertOptions::new(vec![input], out.clone());
        o.flatten_instances = flatten;
        convert(&o).unwrap();
        Archive::open(&out).unwrap().header
    };
    let ply = header("copies.ply", false);
    let (glb, flat) = (header("copies.glb", false), header("copies.glb", true));
    assert_eq!(ply.triangles, glb.input_triangles);
    assert_eq!(ply.triangles, 5 * glb.triangles);
    assert_eq!(ply.triangles, flat.triangles);
    assert!(
        std::fs::metadata(dir.path().join("copies.glb"))
            .unwrap()
            .len()
            * 3
            < std::fs::metadata(dir.path().join("copies.ply"))
                .unwrap()
                .len()
    );
    // Flattened, the glb's vertices are the PLY's up to the rounding of the transforms;
    // instanced, the bounds hold them (an instance counts by its prototype's box, turned).
    let extent = (0..3)
        .map(|k| ply.bounds_max[k] - ply.bounds_min[k])
        .fold(0.0, f32::max);
    for k in 0..3 {
        for (a, b) in [
            (ply.bounds_min[k], flat.bounds_min[k]),
            (ply.bounds_max[k], flat.bounds_max[k]),
        ] {
            assert!((a - b).abs() <= 1e-5 * extent, "axis {k}: {a} vs {b}");
        }
        assert!(glb.bounds_min[k] <= flat.bounds_min[k] && glb.bounds_max[k] >= flat.bounds_max[k]);
    }
    // The same triangles in the same places: the moments of the triangles' centroids (to
    // the third order, with the cross terms) agree up to the transforms' rounding; copies
    // swapped, turned or scaled differently would move them.
    let (ma, mb) = (
        moments(&dir.path().join("copies.ply.canopy")),
        moments(&dir.path().join("copies.glb.flat.canopy")),
    );
    for (k, (p, q)) in ma.iter().zip(&mb).enumerate() {
        assert!(
            (p - q).abs() <= 1e-5 * p.abs().max(1.0),
            "moment {k}: {p} vs {q}"
        );
    }
}

/// Moments of the stored triangles' centroids c: Σc, Σc², Σc³ per axis and Σ cx·cy,
/// Σ cy·cz, Σ cz·cx, each over the triangle count.
fn moments(path: &Path) -> [f64; 12] {
    let a = Archive::open(path).unwrap();
    let (mut m, mut n) = ([0f64; 12], 0f64);
    for page in 0..a.page_count() {
        let c = a.read_page(page).unwrap();
        for t in &c.tris {
            let v = t.v.map(|i| c.verts[i as usize]);
            let p = [0, 1, 2].map(|k| (v[0][k] as f64 + v[1][k] as f64 + v[2][k] as f64) / 3.0);
            for k in 0..3 {
                m[k] += p[k];
                m[3 + k] += p[k] * p[k];
                m[6 + k] += p[k] * p[k] * p[k];
                m[9 + k] += p[k] * p[(k + 1) % 3];
            }
            n += 1.0;
        }
    }
    m.map(|x| x / n)
}

/// 4 M bunnies (2.8 × 10¹¹ instanced triangles) convert and render under `--mem-budget
/// 1GiB`, each within the budget plus the film and 64 MiB (`tests/instances.rs` runs 202,500
/// in the default suite). A scale run: `cargo test --release -p canopy-tools --test bigmesh
/// -- --ignored` (about 20 s and 170 MB of files).
#[test]
#[ignore]
fn four_million_instances_within_a_gigabyte() {
    use canopy::render::render;
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("f4m.glb");
    let bunny = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/bunny.ply");
    let status = std::process::Command::new(env!("CARGO_BIN_EXE_bigmesh"))
        .arg(&bunny)
        .args(["--copies", "4000000", "-o"])
        .arg(&input)
        .status()
        .unwrap();
    assert!(status.success());
    let budget = 1u64 << 30;
    let out = dir.path().join("f4m.canopy");
    let mut o = ConvertOptions::new(vec![input], out.clone());
    o.mem_budget = budget;
    let report = convert(&o).unwrap();
    assert_eq!(report.instances, 4_000_000);
    eprintln!(
        "convert: {:.1} s, peak RSS {} MiB",
        report.seconds_total,
        report.peak_rss_bytes >> 20
    );
    assert!(report.peak_rss_bytes <= budget + (64 << 20));
    // The render's own peak: the kernel's high-water mark starts again from here.
    std::fs::write("/proc/self/clear_refs", "5").unwrap();
    let mut r = canopy_tools::fuzz::archive::tiny_render(
        &out,
        dir.path(),
        canopy::integrator::Settings::Path,
    );
    (r.width, r.height, r.spp, r.max_depth, r.mem_budget) =
        (Some(384), Some(256), 4, None, Some(budget));
    let (_, stats) = render(&r).unwrap();
    eprintln!("render: peak RSS {} MiB", stats.peak_rss_bytes >> 20);
    assert!(stats.peak_rss_bytes <= budget + stats.film_bytes + (64 << 20));
}
