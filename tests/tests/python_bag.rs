//! Bags are readable by an independent consumer: `tests/python/read_bag.py` reads them with the
//! Python `mcap` package and decodes them with `google.protobuf`, building the message classes
//! from the descriptor set each channel carries (none of the project's code). The simulator's
//! bag has the four raw channels with the sample counts it reported, consecutive `seq` and the
//! run and artifact metadata; the corrector's bag has as many points as it reported.
//!
//! The Python environment comes from `scripts/python-env.sh` (a venv under `target/pyenv` with
//! the pinned packages of `tests/python/requirements.txt`). Without Python 3 and pip, or
//! without PyPI on the first run, these tests fail: they do not skip.

mod common;

use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;

const RAW: [(&str, &str); 4] = [
    ("command", "scancorr.v1.CommandBatch"),
    ("scale", "scancorr.v1.ScaleBatch"),
    ("probe", "scancorr.v1.ProbeBatch"),
    ("temperature", "scancorr.v1.TemperatureBatch"),
];

fn workspace() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("tests/ lies in the workspace")
        .to_path_buf()
}

/// `<target>/tmp`, the target directory's scratch space (set by cargo for integration tests).
fn target_tmp() -> PathBuf {
    PathBuf::from(env!("CARGO_TARGET_TMPDIR"))
}

/// The target directory this test was built into.
fn target_dir() -> PathBuf {
    if let Some(t) = target_tmp().parent() {
        return t.to_path_buf();
    }
    match option_env!("CARGO_TARGET_DIR") {
        Some(d) => workspace().join(d),
        None => workspace().join("target"),
    }
}

/// The directory and cargo profile this test binary was built with (`<target>/<dir>/deps/…`;
/// the `dev` profile builds into `debug`).
fn profile() -> (PathBuf, String) {
    let exe = std::env::current_exe().ok();
    if let Some(dir) = exe.as_deref().and_then(Path::parent) {
        if dir.file_name().is_some_and(|n| n == "deps") {
            if let Some(pdir) = dir.parent() {
                let name = pdir.file_name().unwrap().to_string_lossy().into_owned();
                let prof = if name == "debug" { "dev".into() } else { name };
                return (pdir.to_path_buf(), prof);
            }
        }
    }
    if cfg!(debug_assertions) {
        (target_dir().join("debug"), "dev".into())
    } else {
        (target_dir().join("release"), "release".into())
    }
}

fn describe(what: &str, out: &Output) -> String {
    format!(
        "{what}: {}\n--- stdout ---\n{}\n--- stderr ---\n{}",
        out.status,
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    )
}

fn run(what: &str, cmd: &mut Command) -> Output {
    let out = cmd
        .output()
        .unwrap_or_else(|e| panic!("{what}: cannot start {cmd:?}: {e}"));
    assert!(out.status.success(), "{}", describe(what, &out));
    out
}

/// The `scancorr` binary of this profile, built (or brought up to date) first: it belongs to
/// another package, so `cargo test -p scancorr-tests` alone does not build it.
fn scancorr() -> &'static Path {
    static BIN: OnceLock<PathBuf> = OnceLock::new();
    BIN.get_or_init(|| {
        let (dir, prof) = profile();
        let bin = dir.join(format!("scancorr{}", std::env::consts::EXE_SUFFIX));
        // The workspace build (scripts/test.sh) builds it; building one package alone would
        // unify features differently and rebuild much of the dependency tree.
        if !bin.is_file() {
            run(
                "building scancorr-cli",
                Command::new(env!("CARGO"))
                    .args(["build", "--quiet", "-p", "scancorr-cli", "--profile", &prof])
                    .env("CARGO_TARGET_DIR", target_dir())
                    .current_dir(workspace()),
            );
        }
        assert!(
            bin.is_file(),
            "cargo built scancorr-cli but {} is missing",
            bin.display()
        );
        bin
    })
}

/// The Python interpreter of the project's venv (`scripts/python-env.sh`, last stdout line).
fn python() -> &'static Path {
    static PY: OnceLock<PathBuf> = OnceLock::new();
    PY.get_or_init(|| {
        let script = workspace().join("scripts/python-env.sh");
        let out = Command::new("bash")
            .arg(&script)
            .current_dir(workspace())
            .output()
            .unwrap_or_else(|e| panic!("cannot run bash {}: {e}", script.display()));
        assert!(
            out.status.success(),
            "{}\nthese tests need Python 3 with pip and venv (and PyPI on the first run)",
            describe("scripts/python-env.sh", &out)
        );
        let stdout = String::from_utf8_lossy(&out.stdout);
        let py = PathBuf::from(stdout.lines().last().unwrap_or("").trim());
        assert!(
            py.is_file(),
            "scripts/python-env.sh printed no interpreter path:\n{stdout}"
        );
        py
    })
}

/// Runs `scancorr ARGS` and parses its JSON summary.
fn scancorr_json(args: &[&str]) -> Value {
    let out = run(
        &format!("scancorr {}", args.join(" ")),
        Command::new(scancorr()).args(args),
    );
    serde_json::from_slice(&out.stdout).unwrap_or_else(|e| {
        panic!(
            "scancorr {}: output is not JSON ({e}):\n{}",
            args.join(" "),
            String::from_utf8_lossy(&out.stdout)
        )
    })
}

/// Reads a bag with the independent Python reader; fails on any problem it reports.
fn read_bag(bag: &Path) -> Value {
    let reader = workspace().join("tests/python/read_bag.py");
    let out = run(
        &format!("read_bag.py {}", bag.display()),
        Command::new(python()).arg(&reader).arg(bag),
    );
    serde_json::from_slice(&out.stdout).unwrap_or_else(|e| {
        panic!(
            "read_bag.py: output is not JSON ({e}):\n{}",
            String::from_utf8_lossy(&out.stdout)
        )
    })
}

fn u64_of(v: &Value, what: &str) -> u64 {
    v.as_u64()
        .unwrap_or_else(|| panic!("{what} is not a count: {v}"))
}

/// Checks one channel as the Python reader saw it and returns its sample count.
fn check_channel(read: &Value, topic: &str, schema: &str) -> u64 {
    let t = &read["topics"][topic];
    assert!(
        t.is_object(),
        "no channel {topic}; the reader found {:?}",
        read["topics"]
            .as_object()
            .map(|o| o.keys().collect::<Vec<_>>())
    );
    assert_eq!(t["schema"], schema, "{topic}: {t}");
    assert_eq!(t["schema_encoding"], "protobuf", "{topic}: {t}");
    assert_eq!(t["message_encoding"], "protobuf", "{topic}: {t}");
    assert_eq!(t["machine"], "m1", "{topic}: {t}");
    let samples = u64_of(&t["samples"], &format!("{topic} samples"));
    assert!(
        samples > 0 && u64_of(&t["messages"], topic) > 0,
        "{topic}: {t}"
    );
    // The reader already checked seq is consecutive; the span agrees with the count.
    let (first, last) = (
        u64_of(&t["first_seq"], topic),
        u64_of(&t["last_seq"], topic),
    );
    assert_eq!(
        last - first + 1,
        samples,
        "{topic}: seq span vs samples: {t}"
    );
    assert!(
        t["first_t_ns"].as_i64().unwrap() <= t["last_t_ns"].as_i64().unwrap(),
        "{topic}: {t}"
    );
    samples
}

fn metadata<'a>(read: &'a Value, name: &str) -> &'a [Value] {
    read["metadata"][name]
        .as_array()
        .map(Vec::as_slice)
        .unwrap_or_else(|| {
            panic!(
                "no metadata record {name}; the bag has {:?}",
                read["metadata"]
                    .as_object()
                    .map(|o| o.keys().collect::<Vec<_>>())
            )
        })
}

#[test]
fn an_independent_reader_finds_the_raw_channels_and_the_corrected_points() {
    let tmp = common::scratch("python-bag-ring");
    let (raw, calib, corrected) = (
        tmp.join("r.mcap"),
        tmp.join("start.json"),
        tmp.join("o.mcap"),
    );
    let s = |p: &PathBuf| p.to_str().unwrap().to_owned();

    let sim = scancorr_json(&[
        "sim",
        "--program",
        "ring",
        "--seed",
        "3",
        "--out",
        &s(&raw),
        "--calib-out",
        &s(&calib),
        "--json",
    ]);
    assert_eq!(sim["machine"], "m1", "{sim}");
    let read = read_bag(&raw);
    eprintln!("raw bag: {}", read["topics"]);

    let mut topics: Vec<&String> = read["topics"].as_object().unwrap().keys().collect();
    topics.sort();
    let mut want: Vec<String> = RAW.iter().map(|(s, _)| format!("cmm/m1/raw/{s}")).collect();
    want.sort();
    assert_eq!(
        topics,
        want.iter().collect::<Vec<_>>(),
        "the sim bag holds the raw channels only"
    );
    for (stream, schema) in RAW {
        let n = check_channel(&read, &format!("cmm/m1/raw/{stream}"), schema);
        let reported = u64_of(&sim["samples"][stream], &format!("sim samples.{stream}"));
        assert_eq!(
            n, reported,
            "{stream}: samples in the bag vs reported by scancorr sim"
        );
    }

    let runs = metadata(&read, "scancorr.run");
    let run = runs.last().unwrap();
    assert_eq!(run["program"], "ring", "scancorr.run: {run}");
    assert_eq!(run["seed"], "3", "scancorr.run: {run}");
    assert_eq!(run["machine_id"], "m1", "scancorr.run: {run}");
    assert!(!metadata(&read, "scancorr.program").is_empty());
    let artifacts = metadata(&read, "scancorr.artifact");
    assert!(
        artifacts.iter().any(|a| {
            a["kind"] == "ring"
                && a.as_object().unwrap().iter().any(|(k, v)| {
                    k.starts_with("certificate")
                        && v.as_str()
                            .and_then(|v| v.parse::<f64>().ok())
                            .is_some_and(|c| c > 0.0)
                })
        }),
        "no ring artifact with a certificate: {artifacts:?}"
    );

    let cor = scancorr_json(&[
        "correct",
        "--bag",
        &s(&raw),
        "--calib",
        &s(&calib),
        "--out",
        &s(&corrected),
        "--json",
    ]);
    let read = read_bag(&corrected);
    eprintln!("corrected bag: {}", read["topics"]);
    let points = check_channel(
        &read,
        "cmm/m1/corrected/points",
        "scancorr.v1.CorrectedPointBatch",
    );
    assert_eq!(
        points,
        u64_of(&cor["points"], "correct points"),
        "points in the bag vs reported: {cor}"
    );
    assert!(points > 10_000, "{cor}");
    if let Some(t) = read["topics"].get("cmm/m1/alarms/estimator") {
        assert_eq!(t["schema"], "scancorr.v1.EstimatorAlarm", "{t}");
    }
}

#[test]
fn an_independent_reader_decodes_the_estimator_alarms() {
    let tmp = common::scratch("python-bag-fault");
    let (raw, calib, corrected) = (
        tmp.join("f.mcap"),
        tmp.join("start.json"),
        tmp.join("o.mcap"),
    );
    let s = |p: &PathBuf| p.to_str().unwrap().to_owned();
    scancorr_json(&[
        "sim",
        "--program",
        "ring",
        "--seed",
        "3",
        "--fault",
        "collision",
        "--out",
        &s(&raw),
        "--calib-out",
        &s(&calib),
        "--json",
    ]);
    let cor = scancorr_json(&[
        "correct",
        "--bag",
        &s(&raw),
        "--calib",
        &s(&calib),
        "--out",
        &s(&corrected),
        "--json",
    ]);
    let raised = u64_of(&cor["alarms"], "correct alarms");
    assert!(raised > 0, "a collision raises the estimator alarm: {cor}");
    let read = read_bag(&corrected);
    eprintln!("corrected bag: {}", read["topics"]);
    let points = check_channel(
        &read,
        "cmm/m1/corrected/points",
        "scancorr.v1.CorrectedPointBatch",
    );
    assert_eq!(points, u64_of(&cor["points"], "correct points"), "{cor}");
    // One message per alarm raised or cleared: at least the raisings `correct` counted.
    let alarms = check_channel(
        &read,
        "cmm/m1/alarms/estimator",
        "scancorr.v1.EstimatorAlarm",
    );
    assert!(
        alarms >= raised,
        "{alarms} alarm messages, {raised} raised: {cor}"
    );
}
