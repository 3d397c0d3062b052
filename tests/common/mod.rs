#![allow(dead_code)]
//! Helpers shared by the integration tests.

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
