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
        let out = input.with_extension(if flatten { "flat.canopy" } else { "canopy" });
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
}
