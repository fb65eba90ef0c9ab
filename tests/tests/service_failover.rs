//! Fail-over between two scancorrd instances (`failover.enabled`): a fleet of simulated machines
//! streams through a router; instance A serves them, instance B (same store) stands by for
//! them (corrects, withholds). A is stopped mid-run — SIGKILL (a crash) or SIGTERM (a planned
//! hand-over) — and B takes every machine over: a consumer on the bus receives every point
//! once, in order, `seq` without a gap, each equal to the offline correction of the machine's
//! bag. The take-over time is measured at the consumer (the longest pause of a machine's
//! points around the stop) and read from B's health (from the token's going to take-over).

mod common;

use common::*;
use scancorr_proto::v1::CorrectedPoint;
use serde_json::Value;
use std::collections::BTreeMap;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// Machines in the fleet.
const MACHINES: usize = 10;

/// A child process killed when dropped (a failing assertion leaves nothing running).
struct Killed(Child);

impl Drop for Killed {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn name(k: usize) -> String {
    format!("fo{k:02}")
}

/// A scancorrd client of the router, fail-over on, the store shared (`data`).
fn instance(d: &Path, bus: &str, tag: &str) -> Killed {
    std::fs::write(
        d.join(format!("{tag}.json5")),
        format!(
            "{{ mode: 'client', listen: [], connect: ['{bus}'], data_dir: 'data', machines: ['fo*'], allow_any_machine: false, failover: {{ enabled: true, grace_ms: 100 }} }}"
        ),
    )
    .unwrap();
    Killed(
        Command::new(scancorrd())
            .args(["--config", &format!("{tag}.json5")])
            .current_dir(d)
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(d.join(format!("{tag}.log"))).unwrap())
            .spawn()
            .unwrap(),
    )
}

/// Every instance's health answer.
fn health(d: &Path, bus: &str) -> Vec<Value> {
    let out = run(d, &["health", "--json", "--connect", bus]);
    serde_json::from_slice::<Value>(&out.stdout)
        .ok()
        .and_then(|v| v.as_array().cloned())
        .unwrap_or_default()
}

/// Waits until some instance's health satisfies `f`; returns that answer.
fn wait_health(d: &Path, bus: &str, what: &str, f: impl Fn(&Value) -> bool) -> Value {
    let t0 = Instant::now();
    loop {
        let h = health(d, bus);
        if let Some(v) = h.iter().find(|v| f(v)) {
            return v.clone();
        }
        assert!(
            t0.elapsed() < Duration::from_secs(15),
            "no instance {what}: {h:?}"
        );
        std::thread::sleep(Duration::from_millis(200));
    }
}

/// The points a consumer received per machine, with when each batch arrived.
type Received = Arc<Mutex<BTreeMap<String, Vec<(Instant, Vec<CorrectedPoint>)>>>>;

/// The fleet's bags and offline corrections (the same seeds for every test: the files are
/// made in each test's own folder).
fn fleet(d: &Path) -> BTreeMap<String, Vec<CorrectedPoint>> {
    let mut off = BTreeMap::new();
    for k in 0..MACHINES {
        let m = name(k);
        let seed = (4901 + k).to_string();
        ok(
            d,
            &[
                "sim",
                "--program",
                "ring",
                "--machine",
                &m,
                "--machine-seed",
                &seed,
                "--seed",
                &seed,
                "--out",
                &format!("{m}.mcap"),
                "--calib-out",
                &format!("{m}.json"),
            ],
        );
        ok(
            d,
            &[
                "correct",
                "--bag",
                &format!("{m}.mcap"),
                "--calib",
                &format!("{m}.json"),
                "--out",
                &format!("off-{m}.mcap"),
            ],
        );
        off.insert(m.clone(), points(&d.join(format!("off-{m}.mcap"))));
    }
    off
}

/// Runs the fleet through A (active) and B (standby), stops A mid-run with `stop`, and checks
/// what the consumer received.
fn failover(tag: &str, stop: impl FnOnce(&mut Killed)) {
    // One fleet at a time (the machine has two cores).
    static ONE: Mutex<()> = Mutex::new(());
    let _one = ONE.lock().unwrap_or_else(|e| e.into_inner());
    let d = scratch(tag);
    let off = fleet(&d);
    let port = free_port();
    let bus = format!("tcp/127.0.0.1:{port}");
    let _router = Killed(start_router(&d, port));
    let mut a = instance(&d, &bus, "a");
    wait_health(&d, &bus, "A answers", |_| true);
    for k in 0..MACHINES {
        let m = name(k);
        let f = format!("{m}.json");
        ok(
            &d,
            &[
                "calib",
                "put",
                "--machine",
                &m,
                "--file",
                &f,
                "--connect",
                &bus,
            ],
        );
    }
    let b = instance(&d, &bus, "b");
    let hb = wait_health(&d, &bus, "standing by for every machine", |v| {
        v["failover"]["standby"] == MACHINES
    });
    let b_zid = hb["zid"].as_str().unwrap().to_string();
    let ha = wait_health(&d, &bus, "active for every machine", |v| {
        v["failover"]["active"] == MACHINES
    });
    assert_ne!(ha["zid"], hb["zid"]);

    // The consumer.
    let got: Received = Arc::default();
    let rt = tokio::runtime::Runtime::new().unwrap();
    let (session, _subs) = rt.block_on(async {
        let s = session(port).await;
        let mut subs = vec![];
        for k in 0..MACHINES {
            let m = name(k);
            let got = got.clone();
            subs.push(
                s.declare_subscriber(format!("cmm/{m}/corrected/points"))
                    .callback(move |x| {
                        use scancorr_proto::Message;
                        let b = scancorr_proto::v1::CorrectedPointBatch::decode(
                            &*x.payload().to_bytes(),
                        )
                        .unwrap()
                        .into_points()
                        .unwrap();
                        got.lock()
                            .unwrap()
                            .entry(m.clone())
                            .or_default()
                            .push((Instant::now(), b));
                    })
                    .await
                    .unwrap(),
            );
        }
        (s, subs)
    });
    std::thread::sleep(Duration::from_millis(500));
    let replays: Vec<Killed> = (0..MACHINES)
        .map(|k| {
            Killed(
                Command::new(scancorr())
                    .args([
                        "replay",
                        "--bag",
                        &format!("{}.mcap", name(k)),
                        "--speed",
                        "4",
                        "--connect",
                        &bus,
                    ])
                    .current_dir(&d)
                    .stdout(Stdio::null())
                    .stderr(std::fs::File::create(d.join(format!("replay-{k}.log"))).unwrap())
                    .spawn()
                    .unwrap(),
            )
        })
        .collect();
    std::thread::sleep(Duration::from_millis(2000));
    let stopped = Instant::now();
    stop(&mut a);
    for mut r in replays {
        assert!(r.0.wait().unwrap().success(), "a replay failed");
    }
    // B took every machine over.
    let hb = wait_health(&d, &bus, "B active for every machine", |v| {
        v["zid"] == b_zid.as_str() && v["failover"]["active"] == MACHINES
    });
    let took: Vec<f64> = hb["failover"]["machines"]
        .as_object()
        .unwrap()
        .values()
        .map(|m| m["last_takeover_ms"].as_f64().unwrap())
        .collect();
    // What B published from what it held (the points A was not seen to publish), and that it
    // dropped none of it.
    let (mut released, mut overflow) = (0, 0);
    for k in 0..MACHINES {
        let st = rt.block_on(status(&session, &name(k)));
        assert_eq!(st["failover"]["role"], "active", "{st}");
        let h = &st["output"]["standby"];
        released += h["released_points"].as_u64().unwrap();
        overflow += h["held_overflow_points"].as_u64().unwrap();
    }
    assert_eq!(overflow, 0, "B dropped held points");
    // B stops (no standby left: it flushes, as a single instance does).
    std::thread::sleep(Duration::from_millis(500));
    let _ = Command::new("kill")
        .args(["-TERM", &b.0.id().to_string()])
        .status();
    let mut b = b;
    assert!(b.0.wait().unwrap().success());
    std::thread::sleep(Duration::from_millis(300));
    rt.block_on(async { session.close().await }).ok();

    let got = got.lock().unwrap();
    let mut longest = 0f64;
    for (m, offline) in &off {
        let batches = got.get(m).map(|v| v.as_slice()).unwrap_or_default();
        // The longest pause between two batches after the stop, s.
        let pause = batches
            .windows(2)
            .filter(|w| w[1].0 > stopped)
            .map(|w| (w[1].0 - w[0].0).as_secs_f64())
            .fold(0f64, f64::max);
        longest = longest.max(pause);
        let live: Vec<&CorrectedPoint> = batches.iter().flat_map(|(_, b)| b).collect();
        let bad_seq = live.iter().enumerate().find(|(i, p)| p.seq != *i as u64);
        assert!(
            bad_seq.is_none(),
            "{m}: point {} has seq {} (a gap or a point twice); {} points",
            bad_seq.unwrap().0,
            bad_seq.unwrap().1.seq,
            live.len()
        );
        assert_eq!(live.len(), offline.len(), "{m}: live vs offline points");
        let differ = live.iter().zip(offline).position(|(a, b)| *a != b);
        assert!(
            differ.is_none(),
            "{m}: live point {} differs from offline",
            differ.unwrap()
        );
    }
    let took_max = took.iter().copied().fold(0f64, f64::max);
    eprintln!(
        "{tag}: {MACHINES} machines, every point once, in order, equal to offline; take-over {:.0} ms at most after the token went (B's health), longest pause of a machine's points at the consumer {:.0} ms; {released} held points published by B at take-over",
        took_max,
        longest * 1e3
    );
    assert!(
        longest < 2.0,
        "take-over took {longest:.2} s at the consumer"
    );
    let log_b = std::fs::read_to_string(d.join("b.log")).unwrap();
    assert!(log_b.contains("took the machine over"), "{log_b}");
}

#[test]
fn sigkill_of_the_active_instance_loses_no_point() {
    failover("failover-kill", |a| {
        let _ = a.0.kill();
        let _ = a.0.wait();
    });
}

#[test]
fn sigterm_hands_the_machines_over_without_a_gap() {
    failover("failover-term", |a| {
        let _ = Command::new("kill")
            .args(["-TERM", &a.0.id().to_string()])
            .status();
        assert!(a.0.wait().unwrap().success());
    });
}

#[test]
fn shipped_failover_configs_parse_with_failover_on() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy");
    for f in ["scancorrd-failover-a.json5", "scancorrd-failover-b.json5"] {
        let c = scancorrd::Config::load(&dir.join(f)).unwrap_or_else(|e| panic!("{f}: {e}"));
        assert!(c.failover.enabled, "{f}");
        assert_eq!(c.machines, ["m1", "m2"], "{f}");
    }
}
