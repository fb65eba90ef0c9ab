//! A slow app behind the router costs no other machine a point.
//!
//! The deployment as shipped: `scancorr-router` with `deploy/router.json5` (mutual TLS, the
//! access control), scancorrd with `deploy/scancorrd.json5` and
//! `deploy/zenoh-client-tls.json5`; only certificate paths, ports and folders replaced. Two
//! controllers stream their machines live; apps (`app-shape-analysis`, the least-privileged
//! role) subscribe to every machine's points: one reads them; the other, a hung app with two
//! sessions, stops in its callback at its first batch and never returns, so its links stop
//! being read.
//!
//! Before, the router forwarded scancorrd's points `Block` to the hung app: its queue full, the
//! router waited on it (5 s per session, then closed that session's link: "Unable to push non
//! droppable network message … Closing transport!") and read nothing from scancorrd's link
//! meanwhile: the healthy app received 8 300 and 8 200 of the 16 793 points of each machine.
//! The router now sends points and alarms to each subscriber droppable (`qos/network` in
//! `deploy/router.json5`): the hung app loses its own points, at its own link, and nothing
//! else does.

mod common;
use common::*;
use serde_json::Value;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};

use std::time::{Duration, Instant};
use zenoh::Wait;

struct Proc(Child, PathBuf);

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

impl Proc {
    fn log(&self) -> String {
        std::fs::read_to_string(&self.1).unwrap_or_default()
    }
}

fn spawn(dir: &Path, bin: &Path, args: &[&str], log: &str) -> Proc {
    let log = dir.join(log);
    let mut c = Command::new(bin);
    // Their own zenoh runtimes, not this process's (see the test's start).
    c.env_remove("ZENOH_RUNTIME");
    let child = c
        .args(args)
        .current_dir(dir)
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&log).unwrap())
        .spawn()
        .unwrap_or_else(|e| panic!("{}: {e}", bin.display()));
    Proc(child, log)
}

/// A deploy file with its certificate folder, router endpoint and data folder replaced.
fn deployed(dir: &Path, name: &str, port: u16, certs: &Path) -> String {
    std::fs::read_to_string(root().join("deploy").join(name))
        .unwrap()
        .replace("/etc/scancorr/tls/", &format!("{}/", certs.display()))
        .replace("tls/0.0.0.0:7447", &format!("tls/127.0.0.1:{port}"))
        .replace("tls/router.example:7447", &format!("tls/127.0.0.1:{port}"))
        .replace(
            "tls/cmm-router.local:7447",
            &format!("tls/127.0.0.1:{port}"),
        )
        .replace("/var/lib/scancorr", &dir.join("data").display().to_string())
        .replace("127.0.0.1:9464", &format!("127.0.0.1:{}", free_port()))
        .replace(
            "/etc/scancorr/zenoh-client-tls.json5",
            &dir.join("zenoh-client-tls.json5").display().to_string(),
        )
}

/// The operator's client file with `role`'s certificate.
fn role(dir: &Path, role: &str, port: u16, certs: &Path) -> PathBuf {
    let text = deployed(dir, "zenoh-operator-tls.json5", port, certs)
        .replace("operator-", &format!("{role}-"));
    let p = dir.join(format!("{role}.json5"));
    std::fs::write(&p, text).unwrap();
    p
}

fn cli(dir: &Path, cfg: &Path, args: &[&str]) -> std::process::Output {
    let mut a: Vec<&str> = args.to_vec();
    a.extend(["--zenoh-config", cfg.to_str().unwrap()]);
    run(dir, &a)
}

/// A machine's status (asked again for up to 20 s while the service does not answer).
fn status(dir: &Path, op: &Path, machine: &str) -> Value {
    let t0 = Instant::now();
    loop {
        let out = cli(dir, op, &["status", "--machine", machine, "--json"]);
        if out.status.success() {
            return serde_json::from_slice(&out.stdout).unwrap();
        }
        assert!(
            t0.elapsed() < Duration::from_secs(20),
            "status {machine}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        std::thread::sleep(Duration::from_millis(500));
    }
}

/// A client session as the role of `cfg`, with `extra` settings.
fn session(cfg: &Path, extra: &[(&str, &str)]) -> zenoh::Session {
    let mut c = zenoh::Config::from_file(cfg).unwrap();
    c.insert_json5("mode", "\"client\"").unwrap();
    c.insert_json5("scouting/multicast/enabled", "false")
        .unwrap();
    for (k, v) in extra {
        c.insert_json5(k, v).unwrap();
    }
    zenoh::open(c).wait().unwrap()
}

/// Per machine: points received, and the points missing between them (seq gaps).
#[derive(Default, Debug, Clone, Copy)]
struct Got {
    points: u64,
    missing: u64,
    last_seq: Option<u64>,
}

fn note(got: &Mutex<BTreeMap<String, Got>>, payload: &[u8]) {
    use scancorr_proto::Message;
    let b = scancorr_proto::v1::CorrectedPointBatch::decode(payload).unwrap();
    let mut g = got.lock().unwrap();
    for p in b.into_points().unwrap() {
        let e = g.entry(p.machine_id.clone()).or_default();
        e.points += 1;
        if let Some(l) = e.last_seq {
            e.missing += p.seq.saturating_sub(l + 1);
        }
        e.last_seq = Some(p.seq);
    }
}

#[test]
fn a_hung_app_loses_only_its_own_points() {
    // The hung app's sessions live in this process and each holds one of zenoh's receiving
    // workers: enough of them for the healthy app to be served (set before zenoh starts; the
    // service and the router are started without it).
    std::env::set_var("ZENOH_RUNTIME", "(rx: (worker_threads: 8))");
    let d = scratch("deploy-slow-app");
    let certs = make_certs(&d);
    let port = free_port();
    std::fs::write(
        d.join("router.json5"),
        deployed(&d, "router.json5", port, &certs),
    )
    .unwrap();
    let bin = scancorrd().parent().unwrap().to_path_buf();
    let router = spawn(
        &d,
        &bin.join("scancorr-router"),
        &["-c", "router.json5"],
        "router.log",
    );
    wait_listening(port, || format!("router did not start:\n{}", router.log()));
    std::fs::write(
        d.join("zenoh-client-tls.json5"),
        deployed(&d, "zenoh-client-tls.json5", port, &certs),
    )
    .unwrap();
    std::fs::write(
        d.join("scancorrd.json5"),
        deployed(&d, "scancorrd.json5", port, &certs),
    )
    .unwrap();
    let svc = spawn(
        &d,
        &bin.join("scancorrd"),
        &["--config", "scancorrd.json5"],
        "scancorrd.log",
    );
    let op = role(&d, "operator", port, &certs);
    let app = role(&d, "app-shape-analysis", port, &certs);
    let controllers = [
        role(&d, "controller-m1", port, &certs),
        role(&d, "controller-m2", port, &certs),
    ];
    let logs = || format!("scancorrd:\n{}\nrouter:\n{}", svc.log(), router.log());

    sim_ring(&d, "v1.json");
    let v1 = std::fs::read_to_string(d.join("v1.json")).unwrap();
    std::fs::write(
        d.join("v1-m2.json"),
        v1.replace("\"machine_id\": \"m1\"", "\"machine_id\": \"m2\""),
    )
    .unwrap();
    for (m, f) in [("m1", "v1.json"), ("m2", "v1-m2.json")] {
        let out = cli(&d, &op, &["calib", "put", "--machine", m, "--file", f]);
        assert!(
            out.status.success(),
            "calib put {m}: {}\n{}",
            String::from_utf8_lossy(&out.stderr),
            logs()
        );
    }

    // The healthy app reads every machine's points.
    let healthy = session(&app, &[]);
    let got = Arc::new(Mutex::new(BTreeMap::<String, Got>::new()));
    // The longest the healthy app went without a point while they were streamed.
    let arrivals = Arc::new(Mutex::new((None::<Instant>, Duration::ZERO)));
    let (g, a) = (got.clone(), arrivals.clone());
    let _sh = healthy
        .declare_subscriber("cmm/*/corrected/points")
        .callback(move |s| {
            note(&g, &s.payload().to_bytes());
            let mut a = a.lock().unwrap();
            let now = Instant::now();
            if let Some(last) = a.0 {
                a.1 = a.1.max(now - last);
            }
            a.0 = Some(now);
        })
        .wait()
        .unwrap();
    // The hung app, with two sessions subscribed to every machine's points: each callback stops at its
    // first batch until the test ends, and its link's reading task with it (a small socket
    // buffer, so that it stops reading soon). This process's zenoh has receiving workers
    // enough for them and the healthy app (see the start).
    let release = Arc::new(Mutex::new(()));
    let hold = release.lock().unwrap();
    let hung_got = Arc::new(Mutex::new(BTreeMap::<String, Got>::new()));
    let mut hung = vec![];
    for _ in 0..2 {
        let s = session(&app, &[("transport/link/tls/so_rcvbuf", "16384")]);
        let (r, hg) = (release.clone(), hung_got.clone());
        let sub = s
            .declare_subscriber("cmm/*/corrected/points")
            .callback(move |s| {
                note(&hg, &s.payload().to_bytes());
                drop(r.lock());
            })
            .wait()
            .unwrap();
        hung.push((s, sub));
    }
    std::thread::sleep(Duration::from_millis(500));

    // Both controllers stream their machine at twice real time (a ring scan, ~9 s): long
    // enough past the 5 s a `Block` publication waits before its link is closed.
    let t0 = Instant::now();
    let runs: Vec<_> = controllers
        .iter()
        .enumerate()
        .map(|(k, cfg)| {
            let (d, cfg) = (d.to_path_buf(), cfg.clone());
            std::thread::spawn(move || {
                let m = format!("m{}", k + 1);
                cli(
                    &d,
                    &cfg,
                    &[
                        "sim",
                        "--program",
                        "ring",
                        "--live",
                        "--live-rate",
                        "2",
                        "--machine",
                        &m,
                        "--seed",
                        &format!("{}", k + 3),
                    ],
                )
            })
        })
        .collect();
    for (k, r) in runs.into_iter().enumerate() {
        let out = r.join().unwrap();
        assert!(
            out.status.success(),
            "controller m{} streaming: {}\n{}",
            k + 1,
            String::from_utf8_lossy(&out.stderr),
            logs()
        );
    }
    eprintln!("streamed in {:.1} s", t0.elapsed().as_secs_f64());
    let longest_gap = arrivals.lock().unwrap().1;

    // What the service published, once the healthy app has it all (or stops getting more).
    let mut published = BTreeMap::new();
    for m in ["m1", "m2"] {
        let mut s = status(&d, &op, m);
        for _ in 0..40 {
            std::thread::sleep(Duration::from_millis(500));
            let again = status(&d, &op, m);
            let same = again["output"]["points_published"] == s["output"]["points_published"];
            s = again;
            if same && s["output"]["queued_bytes"] == 0 {
                break;
            }
        }
        published.insert(m, s["output"]["points_published"].as_u64().unwrap());
        assert_eq!(s["output"]["points_dropped_backpressure"], 0, "{m}: {s}");
        assert_eq!(s["samples_missing"]["scale"], 0, "{m}: {s}");
    }
    let t1 = Instant::now();
    let mut last = (0, Instant::now());
    loop {
        let g = got.lock().unwrap().clone();
        let have: u64 = g.values().map(|g| g.points).sum();
        let want: u64 = published.values().sum();
        if have >= want {
            break;
        }
        if have != last.0 {
            last = (have, Instant::now());
        }
        if last.1.elapsed() > Duration::from_secs(5) || t1.elapsed() > Duration::from_secs(30) {
            break;
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    let g = got.lock().unwrap().clone();
    let h = hung_got.lock().unwrap().clone();
    let health = cli(&d, &op, &["health", "--json"]);
    let health: Value = serde_json::from_slice(&health.stdout).unwrap_or_default();
    let report = format!(
        "published {published:?}; healthy app {g:?} (longest without a point while streaming: {:.2} s); hung app {h:?}; health {health}\n{}",
        longest_gap.as_secs_f64(),
        logs()
    );
    eprintln!("{}", report.lines().next().unwrap());
    for m in ["m1", "m2"] {
        let got = g.get(m).copied().unwrap_or_default();
        assert!(published[m] > 10_000, "{m}: {report}");
        assert_eq!(
            (got.points, got.missing),
            (published[m], 0),
            "{m}: the healthy app lost points: {report}"
        );
    }
    // Nothing waited for the hung app: the healthy one got points all along (a router
    // waiting on the hung app held every point for 5 s).
    assert!(
        longest_gap < Duration::from_secs(3),
        "the healthy app went {:.1} s without a point: {report}",
        longest_gap.as_secs_f64()
    );
    assert_eq!(
        health[0]["router_link"]["losses"], 0,
        "scancorrd lost its router link: {report}"
    );
    assert!(
        !svc.log().contains("Closing transport"),
        "scancorrd closed a link: {report}"
    );
    // The hung app lost its own points (each session holds its first batch).
    let hung_points: u64 = h.values().map(|g| g.points).sum();
    assert!(
        hung_points < 2 * published.values().sum::<u64>(),
        "{report}"
    );
    drop(hold);
    drop(hung);
}
