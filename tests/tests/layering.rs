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

/// The simulator describes its machine with physics of its own: it may use the calibration's
/// document types (to write the true calibration), never the corrector's formulas — no
/// effect's hot path, no corrector, estimator, judgement, synthesis or discretised model.
#[test]
fn the_simulator_never_calls_the_correctors_formulas() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../clients/sim/src");
    let forbidden = [
        ".correction(",
        ".regressors(",
        "Corrector",
        "synthesize",
        "estimator",
        "judge",
        "Discrete",
        "effects::Effect",
        "BuiltEffect",
        ".build(",
        "osculating_arc",
        "machine_from_probe",
    ];
    let mut files = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().and_then(|e| e.to_str()) != Some("rs") {
            continue;
        }
        files += 1;
        let text = std::fs::read_to_string(&path).unwrap();
        for (n, line) in text.lines().enumerate() {
            let code = line.split("//").next().unwrap_or("");
            for f in forbidden {
                assert!(
                    !code.contains(f),
                    "{}:{}: the simulator uses `{f}` of the corrector: {line}",
                    path.display(),
                    n + 1
                );
            }
        }
    }
    assert!(files >= 4, "read {files} simulator sources");
}
