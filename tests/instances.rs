//! Many instances: an archive of 202,500 placements converts and renders within the least
//! memory budget the converter takes, and renders as its flattened twin does.

mod common;
use common::*;

/// Cornell box's small box shrunk a hundredfold and placed 450 × 450 times over the floor
/// (EXT_mesh_gpu_instancing), a twentieth of 4 M instances. Under `--mem-budget 98MiB` (the
/// least the converter takes) its peak RSS stays within the budget: the placements stream
/// through a spill file and the records through pages. Rendered under 98 MiB, it stays
/// within the budget plus the film and 64 MiB, and its image matches the flattened
/// archive's (every copy stored as triangles), pixel for pixel up to the rounding of the
/// transforms.
#[test]
fn many_instances_convert_and_render_within_the_budget() {
    let dir = tempfile::tempdir().unwrap();
    let grid: Vec<[f32; 3]> = (0..450)
        .flat_map(|i| (0..450).map(move |j| [5.0 + 1.2 * i as f32, 0.0, 5.0 + 1.2 * j as f32]))
        .collect();
    let scales = vec![[0.01f32; 3]; grid.len()];
    let input = gpu_instanced(dir.path(), "carpet.glb", "smallbox", &grid, &scales);
    let convert = |out: &str, extra: &[&str]| {
        let arc = dir.path().join(out);
        let args = [
            &["--quiet", "convert", s(&input), "-o", s(&arc), "--json"],
            extra,
        ]
        .concat();
        let report: serde_json::Value = serde_json::from_str(&ok(&args)).unwrap();
        let verify = ok(&["inspect", s(&arc), "--verify"]);
        assert!(verify.contains("verify              ok"), "{verify}");
        (arc, report)
    };
    let (instanced, report) = convert("i.canopy", &["--mem-budget", "98MiB"]);
    assert_eq!(report["instances"], 202_500, "{report}");
    let peak = report["peak_rss_bytes"].as_u64().unwrap();
    eprintln!("convert: peak RSS {} MiB", peak >> 20);
    assert!(peak <= 98 << 20, "convert: peak RSS {} MiB", peak >> 20);
    let (flat, _) = convert("f.canopy", &["--flatten-instances"]);
    let flags = ["--spp", "4", "--width", "64", "--height", "64"];
    let (a, stats) = render(
        &instanced,
        &dir.path().join("i.exr"),
        &[&flags[..], &["--mem-budget", "98MiB"]].concat(),
    );
    let film = stats["film_bytes"].as_u64().unwrap();
    let peak = stats["peak_rss_bytes"].as_u64().unwrap();
    eprintln!(
        "render: peak RSS {} MiB, film {} MiB",
        peak >> 20,
        film >> 20
    );
    assert!(
        peak <= (98 << 20) + film + (64 << 20),
        "render: peak RSS {} MiB",
        peak >> 20
    );
    let (b, _) = render(&flat, &dir.path().join("f.exr"), &flags);
    let differing = a
        .pixels
        .iter()
        .zip(&b.pixels)
        .filter(|(p, q)| (0..3).any(|c| (p[c] - q[c]).abs() > 1e-3 * (1.0 + q[c].abs())))
        .count();
    // A ray grazing a tile's edge may hit one archive's copy and miss the other's.
    assert!(
        differing <= a.pixels.len() / 100,
        "{differing} of {} pixels differ",
        a.pixels.len()
    );
    assert_mean_within(&a, &b, 1e-3, "instanced against flattened");
}
