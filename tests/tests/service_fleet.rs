//! Several scancorrd instances on one router mesh (a fleet across hosts): each subscribes only
//! to the machines of its assignment, so none receives the others' traffic; an instance whose
//! assignment overlaps refuses a machine another instance already serves (seen by its
//! liveliness token) instead of publishing its points twice; when an instance stops, its
//! machines are unserved, and an instance that has them in its assignment takes them over.

mod common;

use common::*;
use serde_json::Value;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// A child process killed when dropped (a failing assertion leaves nothing running).
struct Killed(Child);

impl Drop for Killed {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// A scancorrd that is a client of the router, with its own store and assignment.
fn instance(d: &Path, bus: &str, name: &str, machines: &str) -> Child {
    std::fs::write(
        d.join(format!("{name}.json5")),
        format!(
            "{{ mode: 'client', listen: [], connect: ['{bus}'], data_dir: 'data-{name}', machines: {machines}, allow_any_machine: false }}"
        ),
    )
    .unwrap();
    Command::new(scancorrd())
        .args(["--config", &format!("{name}.json5")])
        .current_dir(d)
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(d.join(format!("{name}.log"))).unwrap())
        .spawn()
        .unwrap()
}

/// Every instance's health answer, once `n` answer.
fn health(d: &Path, bus: &str, n: usize) -> Vec<Value> {
    let t0 = Instant::now();
    loop {
        let out = run(d, &["health", "--json", "--connect", bus]);
        let v: Vec<Value> = serde_json::from_slice::<Value>(&out.stdout)
            .ok()
            .and_then(|v| v.as_array().cloned())
            .unwrap_or_default();
        if v.len() == n {
            return v;
        }
        assert!(
            t0.elapsed() < Duration::from_secs(20),
            "{} instance(s) answered the health query, not {n}: {}",
            v.len(),
            String::from_utf8_lossy(&out.stderr)
        );
        std::thread::sleep(Duration::from_millis(200));
    }
}

fn of<'a>(h: &'a [Value], first: &str) -> &'a Value {
    h.iter()
        .find(|v| v["assignment"][0] == first)
        .unwrap_or_else(|| panic!("no instance with assignment {first}…: {h:?}"))
}

fn status(d: &Path, bus: &str, m: &str) -> Value {
    serde_json::from_str(&ok(
        d,
        &["status", "--machine", m, "--connect", bus, "--json"],
    ))
    .unwrap()
}

/// The machines the bus lists as served (by their instances' liveliness tokens).
fn listed(d: &Path, bus: &str) -> Vec<String> {
    let v: Value = serde_json::from_str(&ok(d, &["status", "--connect", bus, "--json"])).unwrap();
    serde_json::from_value(v["machines"].clone()).unwrap()
}

fn put(d: &Path, bus: &str, m: &str) {
    let f = format!("{m}.json");
    ok(
        d,
        &[
            "calib",
            "put",
            "--machine",
            m,
            "--file",
            &f,
            "--connect",
            bus,
        ],
    );
}

#[test]
fn two_instances_share_a_router_with_disjoint_and_overlapping_assignments() {
    let d = scratch("two-instances");
    let port = free_port();
    let bus = format!("tcp/127.0.0.1:{port}");
    let _router = Killed(start_router(&d, port));

    // Three machines, a ring each (different machines: different seeds).
    let mut samples = std::collections::BTreeMap::new();
    for (i, m) in ["m1", "m2", "m3"].iter().enumerate() {
        let out = ok(
            &d,
            &[
                "sim",
                "--program",
                "ring",
                "--machine",
                m,
                "--machine-seed",
                &(i + 1).to_string(),
                "--out",
                &format!("{m}.mcap"),
                "--calib-out",
                &format!("{m}.json"),
                "--json",
            ],
        );
        let v: Value = serde_json::from_str(out.lines().last().unwrap()).unwrap();
        let n: u64 = v["samples"]
            .as_object()
            .expect("samples per stream")
            .values()
            .map(|x| x.as_u64().unwrap())
            .sum();
        samples.insert(m.to_string(), n);
    }
    // A serves m1 and m2; B serves m2 (overlap) and the pattern m3* (disjoint from A).
    let mut a = Killed(instance(&d, &bus, "a", "['m1', 'm2']"));
    health(&d, &bus, 1);
    put(&d, &bus, "m1");
    put(&d, &bus, "m2");
    let _b = Killed(instance(&d, &bus, "b", "['m2', 'm3*']"));
    health(&d, &bus, 2);
    put(&d, &bus, "m3");

    // Count the points published per machine on the bus.
    let rt = tokio::runtime::Runtime::new().unwrap();
    let counts: Vec<Arc<AtomicU64>> = (0..3).map(|_| Arc::new(AtomicU64::new(0))).collect();
    let (session, _subs) = rt.block_on(async {
        let s = session(port).await;
        let mut subs = vec![];
        for (i, m) in ["m1", "m2", "m3"].iter().enumerate() {
            let c = counts[i].clone();
            subs.push(
                s.declare_subscriber(format!("cmm/{m}/corrected/points"))
                    .callback(move |x| {
                        use scancorr_proto::Message;
                        let b = scancorr_proto::v1::CorrectedPointBatch::decode(
                            &*x.payload().to_bytes(),
                        )
                        .unwrap();
                        c.fetch_add(b.len() as u64, Ordering::Relaxed);
                    })
                    .await
                    .unwrap(),
            );
        }
        (s, subs)
    });
    std::thread::sleep(Duration::from_millis(500));
    let replays: Vec<Killed> = ["m1", "m2", "m3"]
        .iter()
        .map(|m| {
            Command::new(scancorr())
                .args([
                    "replay",
                    "--bag",
                    &format!("{m}.mcap"),
                    "--speed",
                    "4",
                    "--connect",
                    &bus,
                ])
                .current_dir(&d)
                .stdout(Stdio::null())
                .stderr(Stdio::null())
                .spawn()
                .unwrap()
        })
        .map(Killed)
        .collect();
    for mut r in replays {
        assert!(r.0.wait().unwrap().success(), "a replay failed");
    }
    // Every machine served once: its points on the bus are those its one instance published.
    let t0 = Instant::now();
    let st: Vec<Value> = loop {
        let st: Vec<Value> = ["m1", "m2", "m3"]
            .iter()
            .map(|m| status(&d, &bus, m))
            .collect();
        let settled = st.iter().zip(&counts).all(|(s, c)| {
            s["output"]["points_published"].as_u64() == Some(c.load(Ordering::Relaxed))
                && s["samples_in"].as_u64() == samples.get(s["machine"].as_str().unwrap()).copied()
        });
        if settled || t0.elapsed() > Duration::from_secs(15) {
            break st;
        }
        std::thread::sleep(Duration::from_millis(300));
    };
    for (s, c) in st.iter().zip(&counts) {
        let m = s["machine"].as_str().unwrap();
        let got = c.load(Ordering::Relaxed);
        eprintln!(
            "{m}: {} samples in of {}, {} points out, {got} points on the bus",
            s["samples_in"], samples[m], s["points_out"]
        );
        assert_eq!(s["samples_in"].as_u64(), Some(samples[m]), "{m}: {s}");
        assert!(got > 10_000, "{m}: {got} points");
        assert_eq!(
            s["output"]["points_published"].as_u64(),
            Some(got),
            "{m}: points on the bus are not those its instance published (twice published?)"
        );
        assert_eq!(s["points_out"].as_u64(), Some(got), "{m}: {s}");
    }
    // Who received what: A only m1's and m2's traffic, B only m3's and (its overlap) m2's,
    // refused as served by A.
    let h = health(&d, &bus, 2);
    let (ha, hb) = (of(&h, "m1"), of(&h, "m2"));
    eprintln!("A: {ha}\nB: {hb}");
    assert_eq!(
        ha["samples_in"].as_u64(),
        Some(samples["m1"] + samples["m2"])
    );
    assert_eq!(hb["samples_in"].as_u64(), Some(samples["m3"]));
    for r in ["not_served", "bad_key", "served_elsewhere", "over_capacity"] {
        assert_eq!(ha["refused"][r], 0, "A refused {r}: {ha}");
    }
    assert_eq!(
        hb["refused"]["not_served"], 0,
        "B received m1's traffic: {hb}"
    );
    assert!(
        hb["refused"]["served_elsewhere"].as_u64().unwrap() > 0,
        "{hb}"
    );
    assert_eq!(hb["served_elsewhere"], serde_json::json!(["m2"]), "{hb}");
    assert_eq!(hb["machines"], 1, "{hb}");
    let log_b = std::fs::read_to_string(d.join("b.log")).unwrap();
    assert!(
        log_b.contains("already served by another scancorrd instance") && log_b.contains("m2"),
        "B did not say loudly that it refuses m2:\n{log_b}"
    );
    assert_eq!(listed(&d, &bus), ["m1", "m2", "m3"]);

    // A stops: its tokens vanish; m1 is unserved (nothing else has it), m2 too until its
    // traffic comes again and B, whose assignment has it, takes it over.
    let _ = Command::new("kill")
        .args(["-TERM", &a.0.id().to_string()])
        .status();
    assert!(a.0.wait().unwrap().success());
    let t0 = Instant::now();
    loop {
        let listed = listed(&d, &bus);
        if listed == ["m3"] {
            break;
        }
        assert!(
            t0.elapsed() < Duration::from_secs(10),
            "after A stopped the bus still lists {listed:?}"
        );
        std::thread::sleep(Duration::from_millis(200));
    }
    fails(
        &d,
        &["status", "--machine", "m1", "--connect", &bus],
        &["machine `m1` is not served"],
    );
    std::thread::sleep(super_recheck());
    replay_max(&d, "m2.mcap", &bus);
    let t0 = Instant::now();
    let m2 = loop {
        let out = run(
            &d,
            &["status", "--machine", "m2", "--connect", &bus, "--json"],
        );
        if out.status.success() {
            break serde_json::from_slice::<Value>(&out.stdout).unwrap();
        }
        assert!(
            t0.elapsed() < Duration::from_secs(15),
            "B did not take m2 over"
        );
        std::thread::sleep(Duration::from_millis(300));
    };
    // B has no calibration for m2 (it is in A's store): served, counted, not corrected.
    assert_eq!(m2["served"], true, "{m2}");
    assert!(m2["calibration_version"].is_null(), "{m2}");
    assert!(
        m2["messages"]["no_calibration"].as_u64().unwrap() > 0,
        "{m2}"
    );
    let log_b = std::fs::read_to_string(d.join("b.log")).unwrap();
    assert!(log_b.contains("taking it over"), "{log_b}");

    rt.block_on(async { session.close().await }).ok();
}

/// A little longer than the service's recheck interval for a machine served elsewhere.
fn super_recheck() -> Duration {
    scancorrd::server::RECHECK_ELSEWHERE + Duration::from_millis(500)
}
