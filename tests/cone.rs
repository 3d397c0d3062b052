//! The cone integrator (004 §4.5–4.8) and the `npp`/`eval` reports.

mod common;
use canopy::paging::PageCache;
use canopy::trace::{Cone, ConeHit, Ray, Tracer};
use canopy_format::Archive;
use common::*;
use glam::Vec3A as V;
use std::sync::Arc;

fn cone(
    arc: &std::path::Path,
    out: &std::path::Path,
    extra: &[&str],
) -> (canopy::film::Image, serde_json::Value) {
    render(arc, out, &[&["--integrator", "cone"], extra].concat())
}

#[test]
fn cone_scale_zero_agrees_with_the_reference() {
    let dir = tempfile::tempdir().unwrap();
    for (name, spp) in [("cbox", "128"), ("bunny_box", "64")] {
        let arc = dir.path().join(format!("{name}.canopy"));
        convert(&scene(&format!("{name}.glb")), &arc, None);
        let (img, stats) = cone(
            &arc,
            &dir.path().join(format!("{name}.exr")),
            &["--cone-scale", "0", "--spp", spp],
        );
        assert_mean_within(&img, &reference(name), 0.01, name);
        assert!(stats["stored_nodes"].as_u64().unwrap() > 0);
        assert!(
            stats["passes"].to_string().contains("light pass: skipped"),
            "{}",
            stats["passes"]
        );
    }
}

#[test]
fn cone_error_falls_with_samples() {
    let dir = tempfile::tempdir().unwrap();
    let arc = dir.path().join("c.canopy");
    convert(&scene("cbox.glb"), &arc, None);
    let r = reference("cbox");
    let e: Vec<f64> = [8, 32]
        .iter()
        .map(|n| {
            rmse(
                &cone(
                    &arc,
                    &dir.path().join(format!("{n}.exr")),
                    &["--spp", &n.to_string()],
                )
                .0,
                &r,
            )
        })
        .collect();
    // Four times the samples: the error should about halve (stored light only helps).
    assert!(e[0] / e[1] > 1.6, "RMSE {e:?}");
}

#[test]
fn default_cones_stay_close_to_the_reference() {
    let dir = tempfile::tempdir().unwrap();
    let arc = dir.path().join("b.canopy");
    convert(&scene("bunny_box.glb"), &arc, None);
    let (img, stats) = cone(&arc, &dir.path().join("b.exr"), &["--spp", "64"]);
    assert!(all_finite(&img));
    assert_mean_within(&img, &reference("bunny_box"), 0.02, "cone scale 1");
    assert_eq!(stats["cone_scale"], 1.0);
}

#[test]
fn counters_saturate_and_paths_stop_there() {
    let dir = tempfile::tempdir().unwrap();
    let arc = dir.path().join("c.canopy");
    convert(&scene("cbox.glb"), &arc, None);
    let (img, stats) = cone(
        &arc,
        &dir.path().join("c.exr"),
        &["--spp", "16", "--cone-samples", "4"],
    );
    assert!(all_finite(&img));
    assert!(stats["converged_nodes"].as_u64().unwrap() > 0, "{stats}");
    // Converged nodes end paths early: fewer rays per path than without a limit.
    let (_, free) = cone(
        &arc,
        &dir.path().join("f.exr"),
        &["--spp", "16", "--cone-samples", "1000000"],
    );
    let per_path =
        |s: &serde_json::Value| s["rays"].as_f64().unwrap() / s["paths"].as_f64().unwrap();
    assert!(
        per_path(&stats) < per_path(&free),
        "{} vs {}",
        per_path(&stats),
        per_path(&free)
    );
    assert_mean_within(&img, &reference("cbox"), 0.05, "4-sample nodes");
}

#[test]
fn cones_from_a_camera_a_million_units_out() {
    let dir = tempfile::tempdir().unwrap();
    let far = dir.path().join("far.glb");
    translated_glb(&scene("cbox.glb"), &far, 1e6);
    let arc = dir.path().join("far.canopy");
    convert(&far, &arc, None);
    let (img, _) = cone(&arc, &dir.path().join("far.exr"), &["--spp", "32"]);
    assert!(all_finite(&img));
    assert_mean_within(&img, &reference("cbox"), 0.02, "cones at 1e6");
}

/// A wall one leaf thick (a 2×2 quad at z = 0) in front of a large backdrop at z = −5: a
/// cone of any width from in front must stop at or before the wall, never behind it.
#[test]
fn a_thin_wall_is_never_skipped_by_a_wide_cone() {
    let dir = tempfile::tempdir().unwrap();
    let obj = dir.path().join("w.obj");
    std::fs::write(
        &obj,
        "v -1 -1 0\nv 1 -1 0\nv 1 1 0\nv -1 1 0\nf 1 2 3\nf 1 3 4\n\
         v -50 -50 -5\nv 50 -50 -5\nv 50 50 -5\nv -50 50 -5\nf 5 6 7\nf 5 7 8\n",
    )
    .unwrap();
    let arc = dir.path().join("w.canopy");
    convert(&obj, &arc, None);
    let cache = PageCache::new(Arc::new(Archive::open(&arc).unwrap()), None, 1).unwrap();
    let mut tr = Tracer::new(&cache);
    let mut checked = 0;
    for i in 0..400 {
        let x = (i % 20) as f32 * 0.09 - 0.9;
        let y = (i / 20) as f32 * 0.09 - 0.9;
        let o = V::new(x * 0.5, y * 0.5, 3.0 + (i % 7) as f32);
        let d = (V::new(x, y, 0.0) - o).normalize();
        let t_wall = -o.z / d.z;
        for tan_a in [0.0, 0.01, 0.1, 0.3, 1.0, 10.0] {
            for scale in [0.0, 1.0, 100.0] {
                let c = Cone {
                    r0: 0.0,
                    tan_a,
                    scale,
                };
                let hit = tr.cone_hit(
                    &Ray {
                        o,
                        d,
                        t_max: f32::INFINITY,
                    },
                    &c,
                );
                let t = match hit {
                    Some(ConeHit::Tri(h)) => h.t,
                    Some(ConeHit::Node { t, .. }) => t,
                    None => f32::INFINITY,
                };
                assert!(
                    t <= t_wall * (1.0 + 1e-5),
                    "cone tan {tan_a} scale {scale}: hit at {t}, wall at {t_wall}"
                );
                checked += 1;
            }
        }
    }
    assert_eq!(checked, 400 * 18);
}

#[test]
fn npp_counts_grow_with_resolution_and_stay_within_the_scene() {
    let dir = tempfile::tempdir().unwrap();
    let arc = dir.path().join("b.canopy");
    convert(&scene("bunny_box.glb"), &arc, None);
    let out = dir.path().join("npp");
    ok(&[
        "--quiet",
        "npp",
        s(&arc),
        "--integrator",
        "cone",
        "--resolutions",
        "8,16,32,64",
        "-o",
        s(&out),
    ]);
    let csv = std::fs::read_to_string(out.join("npp.csv")).unwrap();
    let nodes: Vec<u64> = csv
        .lines()
        .skip(1)
        .map(|l| l.split(',').nth(3).unwrap().parse().unwrap())
        .collect();
    assert_eq!(nodes.len(), 4, "{csv}");
    assert!(
        nodes.windows(2).all(|w| w[0] <= w[1]),
        "not growing: {nodes:?}"
    );
    let total = Archive::open(&arc).unwrap().header.nodes;
    assert!(nodes.iter().all(|&n| n > 0 && n <= total));
    let svg = std::fs::read_to_string(out.join("npp.svg")).unwrap();
    assert!(svg.starts_with("<svg") && svg.contains("unique nodes"));
}

#[test]
fn eval_writes_rows_plot_and_table() {
    let dir = tempfile::tempdir().unwrap();
    let arc = dir.path().join("c.canopy");
    convert(&scene("cbox.glb"), &arc, None);
    let out = dir.path().join("eval");
    let text = ok(&[
        "--quiet",
        "eval",
        s(&arc),
        "--reference",
        s(&scene("refs/cbox.exr")),
        "--times",
        "300ms,600ms",
        "-o",
        s(&out),
    ]);
    let csv = std::fs::read_to_string(out.join("eval.csv")).unwrap();
    assert_eq!(csv.lines().count(), 5, "{csv}");
    let md = std::fs::read_to_string(out.join("eval.md")).unwrap();
    assert!(
        md.contains("| Path |") && md.contains("| Cone |") && md.contains("faster"),
        "{md}"
    );
    assert!(text.contains("RMSE"));
    assert!(std::fs::read_to_string(out.join("eval.svg"))
        .unwrap()
        .starts_with("<svg"));
}
