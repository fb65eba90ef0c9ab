//! The core is pure: no async runtime, no network stack anywhere in its dependency tree.

use std::process::Command;

#[test]
fn core_depends_on_no_tokio_and_no_zenoh() {
    let cargo = env!("CARGO");
    let root = concat!(env!("CARGO_MANIFEST_DIR"), "/..");
    let out = Command::new(cargo)
        .args([
            "tree",
            "-p",
            "scancorr-core",
            "-e",
            "normal,build",
            "--prefix",
            "none",
            "--offline",
        ])
        .current_dir(root)
        .output()
        .expect("cargo tree runs");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let tree = String::from_utf8_lossy(&out.stdout);
    assert!(tree.contains("scancorr-core"), "{tree}");
    assert!(tree.contains("nalgebra"), "the tree is real: {tree}");
    for banned in ["tokio", "zenoh", "async-std", "mio"] {
        assert!(
            !tree
                .lines()
                .any(|l| l.split_whitespace().next() == Some(banned)),
            "scancorr-core depends on {banned}:\n{tree}"
        );
    }
}

#[test]
fn core_forbids_unsafe_code() {
    let lib = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../service/core/src/lib.rs"
    ))
    .unwrap();
    assert!(lib.contains("#![forbid(unsafe_code)]"));
}
