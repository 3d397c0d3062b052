//! `bigmesh` writes the same copies as a PLY of every triangle and as a glb of one mesh with
//! an instance per copy: converted, both give the same triangles in the same place.

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
    let header = |name: &str| {
        let input = dir.path().join(name);
        bigmesh(&input);
        let out = input.with_extension("canopy");
        convert(&ConvertOptions::new(vec![input], out.clone())).unwrap();
        Archive::open(&out).unwrap().header
    };
    let (ply, glb) = (header("copies.ply"), header("copies.glb"));
    assert_eq!(ply.triangles, glb.triangles);
    assert!(
        std::fs::metadata(dir.path().join("copies.glb"))
            .unwrap()
            .len()
            * 3
            < std::fs::metadata(dir.path().join("copies.ply"))
                .unwrap()
                .len()
    );
    let extent = (0..3)
        .map(|k| ply.bounds_max[k] - ply.bounds_min[k])
        .fold(0.0, f32::max);
    for k in 0..3 {
        for (a, b) in [
            (ply.bounds_min[k], glb.bounds_min[k]),
            (ply.bounds_max[k], glb.bounds_max[k]),
        ] {
            assert!((a - b).abs() <= 1e-5 * extent, "axis {k}: {a} vs {b}");
        }
    }
}
