//! The Python package (`clients/python`, installed into the tests' venv by
//! `scripts/python-env.sh` with `pip install ./clients/python`) passes its pytest suite:
//! against a live scancorrd fed by `scancorr replay`, the subscriber receives every point
//! with no missed `seq` and the same values as `scancorr correct` offline; calibrations
//! round-trip; `read_bag` reads every channel of a campaign bag; the example app measures the
//! ring within 1 µm; the shape fits match the NIST reference circles and `scancorr shape fit`;
//! the generated protobuf modules are current. Python = CLI (`test_errors.py`): each error the
//! CLI reports and its twin in the package say the same thing — nothing listening, a bad
//! endpoint, an unserved machine, a line fitted as a circle — and `connect()` never returns to
//! nothing: a missing TLS file, a refused TLS handshake, a query a router's access control
//! denies each raise their own `ScancorrError`; a bag's metadata records are all kept.
//!
//! The suite finds the binaries through `SCANCORR_BIN_DIR`. Nothing may be skipped: a skip
//! fails this test.

mod common;
use common::*;
use std::process::Command;

#[test]
fn the_python_package_passes_its_pytest_suite() {
    let env = Command::new("bash")
        .arg(root().join("scripts/python-env.sh"))
        .current_dir(root())
        .output()
        .expect("bash runs");
    assert!(
        env.status.success(),
        "scripts/python-env.sh: {}",
        String::from_utf8_lossy(&env.stderr)
    );
    let py = String::from_utf8_lossy(&env.stdout)
        .lines()
        .last()
        .unwrap_or("")
        .trim()
        .to_string();
    let bins = scancorrd().parent().unwrap().to_path_buf();
    let out = Command::new(&py)
        .args([
            "-m",
            "pytest",
            "-p",
            "no:cacheprovider",
            "-q",
            "-rs",
            "clients/python/tests",
        ])
        .env("SCANCORR_BIN_DIR", &bins)
        .env("PYTHONDONTWRITEBYTECODE", "1")
        .current_dir(root())
        .output()
        .expect("pytest runs");
    let text = format!(
        "{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    eprintln!("{text}");
    assert!(out.status.success(), "pytest failed:\n{text}");
    let summary = text
        .lines()
        .rev()
        .find(|l| l.contains(" passed"))
        .unwrap_or_else(|| panic!("no pytest summary:\n{text}"));
    assert!(
        !summary.contains("skipped")
            && !summary.contains("xfail")
            && !summary.contains("deselected"),
        "nothing may be skipped: {summary}"
    );
    let passed: usize = summary
        .split_whitespace()
        .zip(summary.split_whitespace().skip(1))
        .find(|(_, w)| w.trim_end_matches(',') == "passed")
        .and_then(|(n, _)| n.parse().ok())
        .unwrap_or(0);
    assert!(passed >= 70, "{summary}");
}
