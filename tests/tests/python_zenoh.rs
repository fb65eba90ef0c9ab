//! A consumer written by someone else works: `tests/python/subscribe_points.py` subscribes to
//! scancorrd's corrected points and estimator alarms with the Python zenoh client
//! (`eclipse-zenoh`) and decodes them with `google.protobuf`, the message classes built at run
//! time from the descriptor set the bag carries (through `clients/python/scancorr_client`,
//! no Rust code). What it receives live equals what `scancorr correct` computes offline for
//! the same bag and calibration: as many points, `seq` from 0 without a gap, the same first
//! surface point and the same coordinate sums.
//!
//! The Python environment comes from `scripts/python-env.sh` (a venv under `target/pyenv` with
//! the pinned packages of `tests/python/requirements.txt`). Without Python 3 and pip, or
//! without PyPI on the first run, this test fails: it does not skip.

mod common;
use common::*;
use serde_json::Value;
use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::sync::mpsc;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// How long the subscriber may run in all (its `--max-seconds`).
const SUBSCRIBER_MAX_S: u64 = 90;

fn describe(what: &str, out: &Output) -> String {
    format!(
        "{what}: {}\n--- stdout ---\n{}\n--- stderr ---\n{}",
        out.status,
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    )
}

/// The Python interpreter of the project's venv (`scripts/python-env.sh`, last stdout line).
fn python() -> PathBuf {
    let script = root().join("scripts/python-env.sh");
    let out = Command::new("bash")
        .arg(&script)
        .current_dir(root())
        .output()
        .unwrap_or_else(|e| panic!("cannot run bash {}: {e}", script.display()));
    assert!(
        out.status.success(),
        "{}\nthis test needs Python 3 with pip and venv (and PyPI on the first run) to install \
         tests/python/requirements.txt (eclipse-zenoh, protobuf, mcap)",
        describe("scripts/python-env.sh", &out)
    );
    let stdout = String::from_utf8_lossy(&out.stdout);
    let py = PathBuf::from(stdout.lines().last().unwrap_or("").trim());
    assert!(
        py.is_file(),
        "scripts/python-env.sh printed no interpreter path:\n{stdout}"
    );
    py
}

/// The Python subscriber, with its stderr collected by a thread (which also reports `ready`).
struct Subscriber {
    child: Child,
    stderr: Arc<Mutex<String>>,
    stdout: Option<std::thread::JoinHandle<String>>,
}

impl Subscriber {
    fn start(dir: &Path, port: u16, bag: &Path) -> Subscriber {
        let script = root().join("tests/python/subscribe_points.py");
        let mut pythonpath = std::ffi::OsString::from(root().join("clients/python"));
        if let Some(old) = std::env::var_os("PYTHONPATH") {
            pythonpath.push(":");
            pythonpath.push(old);
        }
        let mut child = Command::new(python())
            .arg(&script)
            .args([
                "--connect",
                &format!("tcp/127.0.0.1:{port}"),
                "--machine",
                "m1",
                "--descriptor-bag",
                bag.to_str().unwrap(),
                "--idle",
                "3",
                "--max-seconds",
                &SUBSCRIBER_MAX_S.to_string(),
            ])
            .env("PYTHONPATH", pythonpath)
            .env("PYTHONUNBUFFERED", "1")
            .current_dir(dir)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap_or_else(|e| panic!("cannot start {}: {e}", script.display()));
        let stderr = Arc::new(Mutex::new(String::new()));
        let (ready_tx, ready_rx) = mpsc::channel();
        {
            let err = child.stderr.take().unwrap();
            let stderr = stderr.clone();
            std::thread::spawn(move || {
                for line in BufReader::new(err).lines() {
                    let Ok(line) = line else { break };
                    if line.trim() == "ready" {
                        let _ = ready_tx.send(());
                    }
                    let mut s = stderr.lock().unwrap();
                    s.push_str(&line);
                    s.push('\n');
                }
            });
        }
        let stdout = {
            let mut out = child.stdout.take().unwrap();
            std::thread::spawn(move || {
                let mut s = String::new();
                let _ = out.read_to_string(&mut s);
                s
            })
        };
        let mut sub = Subscriber {
            child,
            stderr,
            stdout: Some(stdout),
        };
        // Wait for "ready" (both subscribers declared); fail early if it died instead.
        let t0 = Instant::now();
        loop {
            if ready_rx.recv_timeout(Duration::from_millis(100)).is_ok() {
                break;
            }
            if let Some(st) = sub.child.try_wait().unwrap() {
                std::thread::sleep(Duration::from_millis(200));
                panic!(
                    "subscribe_points.py exited ({st}) before it was ready:\n{}",
                    sub.stderr.lock().unwrap()
                );
            }
            assert!(
                t0.elapsed() < Duration::from_secs(60),
                "subscribe_points.py not ready after 60 s:\n{}",
                sub.stderr.lock().unwrap()
            );
        }
        sub
    }

    /// Waits for the exit; returns its JSON report (fails on a non-zero exit).
    fn finish(mut self) -> Value {
        let t0 = Instant::now();
        let status = loop {
            if let Some(st) = self.child.try_wait().unwrap() {
                break st;
            }
            assert!(
                t0.elapsed() < Duration::from_secs(SUBSCRIBER_MAX_S + 30),
                "subscribe_points.py did not finish:\n{}",
                self.stderr.lock().unwrap()
            );
            std::thread::sleep(Duration::from_millis(50));
        };
        let stdout = self.stdout.take().unwrap().join().unwrap();
        std::thread::sleep(Duration::from_millis(100)); // let the stderr thread catch up
        let stderr = self.stderr.lock().unwrap().clone();
        assert!(
            status.success(),
            "subscribe_points.py: {status}\n--- stdout ---\n{stdout}\n--- stderr ---\n{stderr}"
        );
        serde_json::from_str(stdout.trim()).unwrap_or_else(|e| {
            panic!("subscribe_points.py: output is not JSON ({e}):\n{stdout}\n{stderr}")
        })
    }
}

impl Drop for Subscriber {
    fn drop(&mut self) {
        if self.child.try_wait().ok().flatten().is_none() {
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
    }
}

/// The points of the corrector's bag, in file order.

fn f64s(v: &Value, what: &str) -> Vec<f64> {
    v.as_array()
        .unwrap_or_else(|| panic!("{what} is not an array: {v}"))
        .iter()
        .map(|x| {
            x.as_f64()
                .unwrap_or_else(|| panic!("{what}: not a number: {x}"))
        })
        .collect()
}

fn close(a: f64, b: f64, tol: f64) -> bool {
    (a - b).abs() <= tol * (1.0 + a.abs().max(b.abs()))
}

#[test]
fn a_python_zenoh_subscriber_receives_what_the_offline_corrector_computes() {
    let t_start = Instant::now();
    // First, so that a missing Python environment fails before anything else is started.
    let py = python();
    eprintln!("python: {} ({:.1?})", py.display(), t_start.elapsed());

    let d = scratch("python-zenoh");
    let port = free_port();
    let bus = format!("tcp/127.0.0.1:{port}");
    sim_ring(&d, "v1.json");

    let svc = Service::start(&d, port);
    let put = ok(
        &d,
        &[
            "calib",
            "put",
            "--machine",
            "m1",
            "--file",
            "v1.json",
            "--connect",
            &bus,
            "--json",
        ],
    );
    assert!(put.contains("\"version\":1"), "{put}");

    let sub = Subscriber::start(&d, port, &d.join("r.mcap"));
    std::thread::sleep(Duration::from_millis(1000)); // the subscription's route to scancorrd
    ok(
        &d,
        &[
            "replay",
            "--bag",
            "r.mcap",
            "--speed",
            "max",
            "--connect",
            &bus,
        ],
    );
    std::thread::sleep(Duration::from_millis(500));
    svc.stop(); // flushes what is buffered
    let live = sub.finish();
    eprintln!("subscriber: {live}");

    let off: Value = serde_json::from_str(&ok(
        &d,
        &[
            "correct", "--bag", "r.mcap", "--calib", "v1.json", "--out", "off.mcap", "--json",
        ],
    ))
    .expect("correct --json prints JSON");
    let n = off["points"]
        .as_u64()
        .unwrap_or_else(|| panic!("correct --json has no points count: {off}"));
    assert!(n > 10_000, "{off}");

    assert_eq!(
        live["points"].as_u64(),
        Some(n),
        "points received by the Python subscriber vs computed offline ({off})"
    );
    assert_eq!(live["gaps"], 0, "seq gaps seen by the Python subscriber");
    assert_eq!(live["first_seq"], 0, "{live}");
    assert_eq!(live["last_seq"].as_u64(), Some(n - 1), "{live}");
    assert_eq!(live["decode_errors"], 0, "{live}");
    assert_eq!(
        live["calibration_versions"],
        serde_json::json!([1]),
        "{live}"
    );
    assert_eq!(
        live["alarms"].as_u64(),
        off["alarms"].as_u64(),
        "estimator alarms"
    );

    // The decoded content: the first surface point and the coordinate sums agree.
    let offline = points(&d.join("off.mcap"));
    assert_eq!(offline.len() as u64, n);
    let first = offline[0].surface.clone().expect("a surface point");
    let sample = f64s(&live["sample_surface"], "sample_surface");
    for (got, want) in sample.iter().zip([first.x, first.y, first.z]) {
        assert!(
            close(*got, want, 1e-12),
            "first surface point: Python decoded {sample:?}, offline {first:?}"
        );
    }
    let mut sum = [0.0f64; 3];
    for p in &offline {
        let s = p.surface.clone().unwrap_or_default();
        sum[0] += s.x;
        sum[1] += s.y;
        sum[2] += s.z;
    }
    let got = f64s(&live["surface_sum"], "surface_sum");
    for (g, w) in got.iter().zip(sum) {
        assert!(
            close(*g, w, 1e-9),
            "surface sums: Python {got:?}, offline {sum:?}"
        );
    }
    eprintln!("python_zenoh: {:.1?} in all", t_start.elapsed());
    std::fs::remove_dir_all(&d).ok();
}
