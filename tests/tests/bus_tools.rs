//! The bus tools fail loudly when nothing is there, and `record` records what the simulator
//! publishes in the README's own setup (scancorrd on its defaults, two CLI processes).

mod common;
use common::*;
use std::io::Read;
use std::path::Path;
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

/// Runs `scancorr ARGS` in `dir`, killed after `limit`; returns the output and the time taken
/// (None when it had to be killed).
fn run_timed(dir: &Path, args: &[&str], limit: Duration) -> (Output, Option<Duration>) {
    let t0 = Instant::now();
    let mut child = Command::new(scancorr())
        .args(args)
        .current_dir(dir)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // Drain both pipes on threads so a chatty child never blocks.
    let mut so = child.stdout.take().unwrap();
    let mut se = child.stderr.take().unwrap();
    let to = std::thread::spawn(move || {
        let mut v = vec![];
        so.read_to_end(&mut v).ok();
        v
    });
    let te = std::thread::spawn(move || {
        let mut v = vec![];
        se.read_to_end(&mut v).ok();
        v
    });
    let mut took = None;
    let status = loop {
        if let Some(st) = child.try_wait().unwrap() {
            took = Some(t0.elapsed());
            break st;
        }
        if t0.elapsed() > limit {
            child.kill().ok();
            break child.wait().unwrap();
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    let out = Output {
        status,
        stdout: to.join().unwrap(),
        stderr: te.join().unwrap(),
    };
    (out, took)
}

/// Expects `scancorr ARGS` to exit non-zero (1, no panic) within 10 s with every needle in
/// its stderr.
fn fails_fast(dir: &Path, args: &[&str], needles: &[&str]) -> String {
    let (o, took) = run_timed(dir, args, Duration::from_secs(20));
    let err = String::from_utf8_lossy(&o.stderr).to_string();
    let took = took.unwrap_or_else(|| panic!("scancorr {args:?} still running after 20 s:\n{err}"));
    assert!(
        took < Duration::from_secs(10),
        "scancorr {args:?} took {took:?} to fail:\n{err}"
    );
    assert_eq!(
        o.status.code(),
        Some(1),
        "scancorr {args:?} should fail with exit 1 ({:?}):\n{err}",
        o.status
    );
    assert!(!err.contains("panicked"), "{err}");
    for n in needles {
        assert!(
            err.contains(n),
            "scancorr {args:?}: expected `{n}` in:\n{err}"
        );
    }
    err
}

/// Raw messages in a bag.
fn messages(bag: &Path) -> usize {
    let r = scancorr_bag::BagReader::open(bag).unwrap();
    r.messages()
        .unwrap()
        .filter(|m| scancorr_bag::Stream::RAW.contains(&m.as_ref().unwrap().stream))
        .count()
}

#[test]
fn publishing_to_an_endpoint_with_nothing_listening_fails_fast() {
    let d = scratch("bus-nothing");
    sim_ring(&d, "v1.json");
    let ep = format!("tcp/127.0.0.1:{}", free_port());
    fails_fast(
        &d,
        &["sim", "--program", "ring", "--live", "--connect", &ep],
        &[&ep],
    );
    fails_fast(
        &d,
        &[
            "replay",
            "--bag",
            "r.mcap",
            "--speed",
            "max",
            "--connect",
            &ep,
        ],
        &[&ep],
    );
    fails_fast(
        &d,
        &[
            "tail",
            "--machine",
            "m1",
            "--seconds",
            "3",
            "--connect",
            &ep,
        ],
        &[&ep],
    );
    fails_fast(&d, &["status", "--machine", "m1", "--connect", &ep], &[&ep]);
    // An endpoint without its protocol.
    fails_fast(
        &d,
        &["replay", "--bag", "r.mcap", "--connect", "127.0.0.1:7447"],
        &["use tcp/HOST:PORT"],
    );
}

#[test]
fn record_records_every_raw_message_the_simulator_publishes() {
    let d = scratch("bus-record");
    let port = free_port();
    let ep = format!("tcp/127.0.0.1:{port}");
    // What the simulator publishes: the same program and seed, written offline.
    sim_ring(&d, "v1.json");
    let expected = messages(&d.join("r.mcap"));
    assert!(expected > 500, "{expected}");

    // scancorrd on its defaults (a peer, listening), a recorder and the simulator, each a
    // CLI process connected to it; the machine calibrated (a live run to a machine without
    // one fails: nothing would be corrected).
    let svc = Service::start(&d, port);
    calib_put(&d, "m1", "v1.json", &ep);
    let rec = Command::new(scancorr())
        .args([
            "record",
            "--keys",
            "cmm/m1/raw/**",
            "--out",
            "run.mcap",
            "--idle",
            "3",
            "--seconds",
            "120",
            "--connect",
            &ep,
        ])
        .current_dir(&d)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    std::thread::sleep(Duration::from_millis(1500));
    let (sim, _) = run_timed(
        &d,
        &[
            "sim",
            "--program",
            "ring",
            "--live",
            // Twice real time, as the README runs it. (scancorrd drops forwarded raw
            // messages for a consumer that falls behind — its `qos/network` overwrite — so
            // at `max` a recorder may see gaps, which `record` then reports as an error.)
            "--live-rate",
            "2",
            "--connect",
            &ep,
        ],
        Duration::from_secs(120),
    );
    let sim_err = String::from_utf8_lossy(&sim.stderr).to_string();
    assert!(sim.status.success(), "sim --live failed:\n{sim_err}");
    assert!(
        sim_err.contains(&format!("published {expected} message(s) live")),
        "{sim_err}"
    );
    let t0 = Instant::now();
    let rec = rec.wait_with_output().unwrap();
    let rec_err = String::from_utf8_lossy(&rec.stderr).to_string();
    assert!(t0.elapsed() < Duration::from_secs(60));
    assert!(rec.status.success(), "record failed:\n{rec_err}");
    assert!(
        rec_err.contains(&format!("recorded {expected} message(s)")),
        "{rec_err}"
    );
    assert_eq!(messages(&d.join("run.mcap")), expected, "{rec_err}");
    svc.stop();
}

#[test]
fn the_service_running_but_nothing_there_is_an_error() {
    let d = scratch("bus-empty");
    let port = free_port();
    let ep = format!("tcp/127.0.0.1:{port}");
    sim_ring(&d, "v1.json");
    let svc = Service::start(&d, port);
    // Published where nobody subscribes (the service listens under prefix `cmm`).
    fails_fast(
        &d,
        &[
            "replay",
            "--bag",
            "r.mcap",
            "--prefix",
            "other",
            "--speed",
            "max",
            "--connect",
            &ep,
        ],
        &["nobody subscribes", "other/m1/raw/"],
    );
    // No machine served yet: listing them is an error that says how one is served.
    fails_fast(
        &d,
        &["status", "--connect", &ep],
        &["serves a machine", "calib put"],
    );
    // A machine the service does not serve.
    fails_fast(
        &d,
        &["status", "--machine", "nosuch", "--connect", &ep],
        &["nosuch", "does not serve"],
    );
    // The same through a zenoh configuration file naming the endpoint (as a TLS deployment's
    // would), and a file that is not one: its name and zenoh's reason.
    std::fs::write(
        d.join("client.json5"),
        format!("{{ connect: {{ endpoints: [\"{ep}\"] }} }}"),
    )
    .unwrap();
    fails_fast(
        &d,
        &[
            "status",
            "--machine",
            "nosuch",
            "--zenoh-config",
            "client.json5",
        ],
        &["nosuch", "does not serve"],
    );
    std::fs::write(d.join("broken.json5"), "{ connect: { endpoints: [ }").unwrap();
    fails_fast(
        &d,
        &[
            "status",
            "--machine",
            "m1",
            "--zenoh-config",
            "broken.json5",
        ],
        &["--zenoh-config broken.json5"],
    );
    // Nothing published: tail and record say so, and record writes no file.
    fails_fast(
        &d,
        &[
            "tail",
            "--machine",
            "m1",
            "--seconds",
            "2",
            "--connect",
            &ep,
        ],
        &["received nothing on `cmm/m1/**`"],
    );
    fails_fast(
        &d,
        &[
            "record",
            "--keys",
            "cmm/m1/raw/**",
            "--out",
            "none.mcap",
            "--seconds",
            "2",
            "--connect",
            &ep,
        ],
        &["received nothing on `cmm/m1/raw/**`"],
    );
    assert!(!d.join("none.mcap").exists());
    assert!(std::fs::read_dir(&d)
        .unwrap()
        .flatten()
        .all(|e| !e.file_name().to_string_lossy().contains(".tmp")));
    svc.stop();
}

#[test]
fn names_from_flags_are_checked_before_use() {
    let d = scratch("bus-names");
    let ep = format!("tcp/127.0.0.1:{}", free_port());
    for (args, needle) in [
        (
            vec!["status", "--machine", "*", "--connect", &ep],
            "machine id",
        ),
        (
            vec!["tail", "--machine", "m1/raw", "--connect", &ep],
            "machine id",
        ),
        (
            vec!["calib", "get", "--machine", "**", "--connect", &ep],
            "machine id",
        ),
        (
            vec![
                "sim",
                "--program",
                "ring",
                "--machine",
                "../m1",
                "--out",
                "x.mcap",
            ],
            "machine id",
        ),
        (
            vec![
                "sim",
                "--program",
                "ring",
                "--prefix",
                "cmm/*",
                "--out",
                "x.mcap",
            ],
            "prefix",
        ),
        (
            vec![
                "status",
                "--machine",
                "m1",
                "--prefix",
                "cmm/**",
                "--connect",
                &ep,
            ],
            "prefix",
        ),
        (vec!["calib", "example", "--machine=-rf"], "machine id"),
    ] {
        fails_fast(&d, &args, &[needle]);
    }
    assert!(!d.join("x.mcap").exists());
}

/// The audit's `by` comes from the connection, not from `$USER`: with `$USER` and `$LOGNAME`
/// unset, a put and a rollback are recorded with the session's zenoh id and the process's
/// uid, never `unknown`. (Through a TLS router the certificate's subject is added:
/// router_acl.rs, the lab's rollback, also with `$USER` unset.)
#[test]
fn the_audit_names_the_connection_with_user_unset() {
    let d = scratch("bus-audit-nouser");
    let port = free_port();
    let ep = format!("tcp/127.0.0.1:{port}");
    ok(
        &d,
        &[
            "sim",
            "--program",
            "ring",
            "--seed",
            "4702",
            "--out",
            "r.mcap",
            "--calib-out",
            "v1.json",
        ],
    );
    let svc = Service::start(&d, port);
    let nameless = |args: &[&str]| {
        let mut a: Vec<&str> = args.to_vec();
        a.extend(["--connect", ep.as_str()]);
        let o = Command::new(scancorr())
            .args(&a)
            .env_remove("USER")
            .env_remove("LOGNAME")
            .current_dir(&d)
            .output()
            .unwrap();
        assert!(
            o.status.success(),
            "scancorr {a:?} with $USER unset: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        String::from_utf8(o.stdout).unwrap()
    };
    for _ in 0..2 {
        nameless(&["calib", "put", "--machine", "m1", "--file", "v1.json"]);
    }
    nameless(&["calib", "rollback", "--machine", "m1", "--to", "1"]);
    let h: serde_json::Value = serde_json::from_str(&nameless(&[
        "calib",
        "history",
        "--machine",
        "m1",
        "--json",
    ]))
    .unwrap();
    let by: Vec<&str> = h
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v["audit"]["by"].as_str().unwrap())
        .collect();
    assert_eq!(by.len(), 3, "{h}");
    let uid = std::fs::read_to_string("/proc/self/status")
        .unwrap()
        .lines()
        .find_map(|l| l.strip_prefix("Uid:"))
        .and_then(|l| l.split_whitespace().next().map(String::from))
        .unwrap();
    let mut zids = std::collections::BTreeSet::new();
    for b in &by {
        assert!(!b.contains("unknown") && !b.contains("unnamed"), "{by:#?}");
        assert!(b.starts_with(&format!("uid {uid}@")), "{by:#?}");
        let zid = b
            .split(", zenoh id ")
            .nth(1)
            .unwrap_or_else(|| panic!("no zenoh id: {by:#?}"));
        assert!(
            zid.len() >= 8 && zid.chars().all(|c| c.is_ascii_hexdigit()),
            "{by:#?}"
        );
        zids.insert(zid.to_string());
    }
    assert_eq!(zids.len(), 3, "each command its own session: {by:#?}");
    svc.stop();
}
