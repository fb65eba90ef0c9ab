//! Helpers for tests that drive the `scancorr` binary as a separate process.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// The workspace root.
pub fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .unwrap()
        .to_path_buf()
}

/// The `scancorr` binary of the profile these tests were built with (built if missing).
pub fn scancorr() -> PathBuf {
    let target = std::env::var_os("CARGO_TARGET_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| root().join("target"));
    let profile = if cfg!(debug_assertions) {
        "debug"
    } else {
        "release"
    };
    let bin = target.join(profile).join("scancorr");
    if !bin.exists() {
        let mut c = Command::new(env!("CARGO"));
        c.args(["build", "-p", "scancorr-cli", "--bin", "scancorr"])
            .current_dir(root());
        if profile == "release" {
            c.arg("--release");
        }
        assert!(
            c.status().expect("cargo runs").success(),
            "building scancorr failed"
        );
    }
    bin
}

/// A fresh scratch directory.
pub fn scratch(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("scancorr-test-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Runs `scancorr ARGS` in `dir`.
pub fn run(dir: &Path, args: &[&str]) -> Output {
    Command::new(scancorr())
        .args(args)
        .current_dir(dir)
        .output()
        .expect("scancorr runs")
}

/// Runs and expects success; returns stdout.
pub fn ok(dir: &Path, args: &[&str]) -> String {
    let o = run(dir, args);
    assert!(
        o.status.success(),
        "scancorr {args:?} failed:\n{}\n{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    String::from_utf8(o.stdout).unwrap()
}

/// Runs and expects failure with a message containing every needle; no panic.
pub fn fails(dir: &Path, args: &[&str], needles: &[&str]) -> String {
    let o = run(dir, args);
    let err = String::from_utf8_lossy(&o.stderr).to_string();
    assert!(!o.status.success(), "scancorr {args:?} should fail");
    assert_eq!(
        o.status.code(),
        Some(1),
        "scancorr {args:?} exited by {:?}:\n{err}",
        o.status
    );
    assert!(
        !err.contains("panicked"),
        "scancorr {args:?} panicked:\n{err}"
    );
    for n in needles {
        assert!(
            err.contains(n),
            "scancorr {args:?}: expected `{n}` in:\n{err}"
        );
    }
    err
}
