//! Bad input of every kind gets a clear error naming the file and the problem, exit code 1,
//! no panic, and nothing at the output path.

mod common;
use common::*;
use std::path::{Path, PathBuf};

const TRI_PLY_HEADER: &str = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n";

fn convert_fails(input: &Path, expect: &[&str]) {
    let out = input.with_extension("canopy");
    let err = fails(&["convert", s(input), "-o", s(&out)]);
    assert!(
        err.contains(&*input.file_name().unwrap().to_string_lossy()),
        "error does not name the file: {err}"
    );
    for e in expect {
        assert!(err.contains(e), "error lacks '{e}': {err}");
    }
    assert!(!out.exists(), "a failed conversion left {}", out.display());
    let stray: Vec<_> = std::fs::read_dir(input.parent().unwrap())
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().starts_with('.'))
        .collect();
    assert!(stray.is_empty(), "temporary files left: {stray:?}");
}

fn write(dir: &Path, name: &str, bytes: &[u8]) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, bytes).unwrap();
    p
}

#[test]
fn missing_file() {
    let dir = tempfile::tempdir().unwrap();
    convert_fails(&dir.path().join("absent.ply"), &["no such file"]);
}

#[test]
fn unknown_extension() {
    let dir = tempfile::tempdir().unwrap();
    convert_fails(
        &write(dir.path(), "mesh.stl", b"solid"),
        &["unknown input type"],
    );
}

#[test]
fn truncated_ply() {
    let dir = tempfile::tempdir().unwrap();
    let full = std::fs::read(scene("bunny.ply")).unwrap();
    convert_fails(
        &write(dir.path(), "cut.ply", &full[..full.len() / 2]),
        &["truncated"],
    );
}

#[test]
fn nan_and_infinite_vertices() {
    let dir = tempfile::tempdir().unwrap();
    let nan = format!("{TRI_PLY_HEADER}0 0 0\nnan 1 0\n0 1 0\n3 0 1 2\n");
    convert_fails(
        &write(dir.path(), "nan.ply", nan.as_bytes()),
        &["non-finite"],
    );
    let inf = format!("{TRI_PLY_HEADER}0 0 0\n1 1e39 0\n0 1 0\n3 0 1 2\n");
    convert_fails(
        &write(dir.path(), "inf.ply", inf.as_bytes()),
        &["non-finite"],
    );
    convert_fails(
        &write(
            dir.path(),
            "nan.obj",
            b"v 0 0 0\nv 1 0 0\nv 0 inf 0\nf 1 2 3\n",
        ),
        &["non-finite"],
    );
}

#[test]
fn out_of_range_index() {
    let dir = tempfile::tempdir().unwrap();
    let ply = format!("{TRI_PLY_HEADER}0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n");
    convert_fails(
        &write(dir.path(), "idx.ply", ply.as_bytes()),
        &["out of range"],
    );
    convert_fails(
        &write(
            dir.path(),
            "idx.obj",
            b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n",
        ),
        &["out of range"],
    );
}

#[test]
fn empty_mesh() {
    let dir = tempfile::tempdir().unwrap();
    let ply = "ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\nproperty float z\nelement face 0\nproperty list uchar int vertex_indices\nend_header\n";
    convert_fails(&write(dir.path(), "empty.ply", ply.as_bytes()), &["empty"]);
}

#[test]
fn absurd_element_count() {
    let dir = tempfile::tempdir().unwrap();
    let ply = "ply\nformat binary_little_endian 1.0\nelement vertex 999999999999\nproperty float x\nproperty float y\nproperty float z\nend_header\n";
    convert_fails(&write(dir.path(), "huge.ply", ply.as_bytes()), &["claims"]);
}

#[test]
fn corrupt_glb() {
    let dir = tempfile::tempdir().unwrap();
    let mut glb = std::fs::read(scene("cbox.glb")).unwrap();
    for b in &mut glb[20..60] {
        *b = b'#';
    }
    convert_fails(&write(dir.path(), "bad.glb", &glb), &["not a valid glTF"]);
    convert_fails(
        &write(
            dir.path(),
            "short.glb",
            &std::fs::read(scene("cbox.glb")).unwrap()[..100],
        ),
        &["not a valid glTF"],
    );
}

/// A valid archive of the bunny to damage.
fn archive(dir: &Path) -> (PathBuf, Vec<u8>) {
    let p = dir.join("good.canopy");
    ok(&["convert", s(&scene("bunny.ply")), "-o", s(&p)]);
    let bytes = std::fs::read(&p).unwrap();
    (p, bytes)
}

fn inspect_fails(path: &Path, expect: &str) {
    let err = fails(&["inspect", "--verify", s(path)]);
    assert!(
        err.contains(&*path.file_name().unwrap().to_string_lossy()),
        "error does not name the file: {err}"
    );
    assert!(err.contains(expect), "error lacks '{expect}': {err}");
}

#[test]
fn truncated_archive() {
    let dir = tempfile::tempdir().unwrap();
    let (_, bytes) = archive(dir.path());
    for cut in [0, 5, 100, bytes.len() / 2, bytes.len() - 1] {
        let p = write(dir.path(), "cut.canopy", &bytes[..cut]);
        let err = fails(&["inspect", "--verify", s(&p)]);
        assert!(
            err.contains("cut.canopy")
                && (err.contains("truncated") || err.contains("not a Canopy archive")),
            "cut at {cut}: {err}"
        );
    }
}

#[test]
fn flipped_byte_in_a_page() {
    let dir = tempfile::tempdir().unwrap();
    let (good, bytes) = archive(dir.path());
    let a = canopy_format::Archive::open(&good).unwrap();
    let e = a.pages[a.pages.len() / 2];
    let mut bad = bytes.clone();
    bad[e.offset as usize + e.compressed_len as usize / 2] ^= 0x10;
    inspect_fails(&write(dir.path(), "flip.canopy", &bad), "checksum mismatch");
    // A flipped byte in the tables or the header is caught too.
    let mut bad = bytes.clone();
    let last = bad.len() - 10;
    bad[last] ^= 1;
    inspect_fails(&write(dir.path(), "table.canopy", &bad), "checksum");
    let mut bad = bytes;
    bad[40] ^= 1;
    inspect_fails(&write(dir.path(), "header.canopy", &bad), "checksum");
}

#[test]
fn wrong_magic() {
    let dir = tempfile::tempdir().unwrap();
    let (_, mut bytes) = archive(dir.path());
    bytes[0] = b'X';
    inspect_fails(
        &write(dir.path(), "magic.canopy", &bytes),
        "not a Canopy archive",
    );
    inspect_fails(&scene("cbox.glb"), "not a Canopy archive");
}

#[test]
fn newer_format_version() {
    let dir = tempfile::tempdir().unwrap();
    let (_, mut bytes) = archive(dir.path());
    bytes[8..10].copy_from_slice(&(canopy_format::VERSION_MAJOR + 1).to_le_bytes());
    inspect_fails(
        &write(dir.path(), "future.canopy", &bytes),
        "newer than this canopy reads",
    );
}

#[test]
fn missing_archive_and_bad_sizes() {
    let dir = tempfile::tempdir().unwrap();
    inspect_fails(&dir.path().join("nothing.canopy"), "No such file");
    let out = dir.path().join("o.canopy");
    let cbox = scene("cbox.glb");
    let convert =
        |out: &str, budget: &str| fails(&["convert", s(&cbox), "-o", out, "--mem-budget", budget]);
    assert!(convert(s(&out), "12 parsecs").contains("unknown size unit"));
    assert!(convert(s(&out), "1MiB").contains("too small"));
    assert!(convert("/nonexistent-dir/x.canopy", "1GiB").contains("/nonexistent-dir"));
    assert!(!out.exists());
}

/// A conversion killed with SIGKILL halfway leaves nothing at the output path.
#[test]
fn killed_conversion_leaves_no_output() {
    let dir = tempfile::tempdir().unwrap();
    // A 2M-triangle grid, big enough to still be converting when killed.
    let n = 1000usize;
    let input = dir.path().join("grid.ply");
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
    std::fs::write(&input, bytes).unwrap();
    let out = dir.path().join("grid.canopy");
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_canopy"))
        .args(["convert", s(&input), "-o", s(&out), "--quiet"])
        .spawn()
        .unwrap();
    // Wait until the temporary archive exists, then kill.
    let start = std::time::Instant::now();
    loop {
        let tmp = std::fs::read_dir(dir.path())
            .unwrap()
            .filter_map(|e| e.ok())
            .any(|e| e.file_name().to_string_lossy().contains(".tmp-"));
        if tmp || start.elapsed().as_secs() > 60 {
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(5));
    }
    child.kill().unwrap();
    let status = child.wait().unwrap();
    assert!(
        !status.success(),
        "conversion finished before it could be killed"
    );
    assert!(
        !out.exists(),
        "a killed conversion left a file at the output path"
    );
}
