//! Every input the fuzzers ever crashed on stays a test: each file of
//! `fuzz/regressions/<target>/` is run through the same function as the cargo-fuzz target
//! (`fuzz/src/targets.rs`, included here), and must neither panic nor abort. The seed corpora
//! `fuzz/seeds/<target>/` are run too (valid inputs: the targets' happy paths still work).
//!
//! Fuzzing itself is `scripts/fuzz.sh` (not part of `cargo test`); it copies what it finds into
//! `fuzz/regressions/`.

#[allow(dead_code)]
#[path = "../../fuzz/src/targets.rs"]
mod targets;

use std::path::{Path, PathBuf};

fn fuzz_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../fuzz")
}

/// The input files of `fuzz/<kind>/<target>/`, sorted (no dot files, no README).
fn inputs(kind: &str, target: &str) -> Vec<PathBuf> {
    let dir = fuzz_dir().join(kind).join(target);
    let mut files: Vec<PathBuf> = match std::fs::read_dir(&dir) {
        Ok(entries) => entries
            .map(|e| e.expect("read the directory").path())
            .filter(|p| p.is_file())
            .filter(|p| {
                let name = p.file_name().and_then(|n| n.to_str()).unwrap_or("");
                !name.starts_with('.') && !name.starts_with("README")
            })
            .collect(),
        Err(_) => vec![],
    };
    files.sort();
    files
}

/// Runs every input of `fuzz/<kind>/<target>/` through the target, each on its own thread
/// (named after the file, so a stack overflow's message names it; 2 MiB of stack, less than
/// the fuzzer's main thread has). Returns how many ran.
fn run_all(kind: &str, target: &str) -> usize {
    let f = targets::target(target).expect("a known target");
    let files = inputs(kind, target);
    let mut failed = vec![];
    for path in &files {
        let data = std::fs::read(path).expect("read the input");
        let name = format!(
            "{kind}/{target}/{}",
            path.file_name().unwrap().to_string_lossy()
        );
        let r = std::thread::Builder::new()
            .name(name.clone())
            .stack_size(2 << 20)
            .spawn(move || f(&data))
            .expect("spawn")
            .join();
        if r.is_err() {
            failed.push(name);
        }
    }
    assert!(failed.is_empty(), "the target panicked on: {failed:?}");
    files.len()
}

#[test]
fn regressions_do_not_crash() {
    let mut total = 0;
    for target in targets::TARGETS {
        total += run_all("regressions", target);
    }
    // The stack overflows of the expression parser (issue finding 2) are there at least.
    assert!(inputs("regressions", "calibration").len() >= 1);
    assert!(inputs("regressions", "expr").len() >= 1);
    eprintln!("{total} regression inputs ran");
}

#[test]
fn seeds_run_and_every_target_has_some() {
    for target in targets::TARGETS {
        let n = run_all("seeds", target);
        assert!(n > 0, "no seeds in fuzz/seeds/{target}");
    }
}

#[test]
fn seeds_reach_the_corrector_and_the_model() {
    // The seeds are valid inputs: the calibrations build and the wire batches decode.
    for path in inputs("seeds", "calibration") {
        let text = std::fs::read_to_string(&path).unwrap();
        let cal = scancorr_core::Calibration::from_json(&text).unwrap();
        assert!(cal.build().is_ok(), "{}", path.display());
    }
    for path in inputs("seeds", "expr") {
        let text = std::fs::read_to_string(&path).unwrap();
        assert!(
            scancorr_core::expr::Expr::parse(&text).is_ok(),
            "{}",
            path.display()
        );
    }
    for path in inputs("seeds", "calibration") {
        let n = targets::calibration_points(&std::fs::read(&path).unwrap());
        assert!(n > 100, "{}: {n} points", path.display());
    }
    let mut decoded = 0;
    for path in inputs("seeds", "wire_decode") {
        let data = std::fs::read(&path).unwrap();
        for stream in scancorr_core::sample::StreamId::ALL {
            if let Ok(d) = scancorr_core::wire::decode(stream, &data) {
                decoded += d.samples.len();
            }
        }
    }
    assert!(decoded > 0);
    // The framed seed interleaves all four streams: the corrector makes points of it.
    let framed = std::fs::read(fuzz_dir().join("seeds/wire_decode/framed.bin")).unwrap();
    let n = targets::wire_decode_points(&framed);
    assert!(n > 50, "{n} points");
    for path in inputs("seeds", "bag_reader") {
        let bag = scancorr_bag::BagReader::open(&path).unwrap();
        assert!(bag.messages().unwrap().count() > 0, "{}", path.display());
    }
}
