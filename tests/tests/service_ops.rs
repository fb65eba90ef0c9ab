//! What an operator sees and relies on, against real processes: the Prometheus endpoint, the
//! systemd readiness and watchdog notifications, the logs (JSON lines on request, no colour
//! off a terminal, a configuration error in one line), the calibration audit trail and
//! rollback, and a service killed with SIGKILL mid-stream that comes back with its history
//! intact and a database that passes `PRAGMA integrity_check`.

mod common;
use common::*;
use serde_json::Value;
use std::io::{Read, Write};
use std::os::unix::net::UnixDatagram;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

fn http_get(port: u16, path: &str) -> String {
    let mut c = std::net::TcpStream::connect(("127.0.0.1", port)).unwrap();
    c.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    write!(c, "GET {path} HTTP/1.1\r\nHost: localhost\r\n\r\n").unwrap();
    let mut s = String::new();
    let _ = c.read_to_string(&mut s);
    s
}

/// The value of one sample line `name{labels} v` of the exposition text.
fn sample(text: &str, series: &str) -> Option<f64> {
    text.lines().find_map(|l| {
        l.strip_prefix(series)?
            .strip_prefix(' ')?
            .trim()
            .parse()
            .ok()
    })
}

/// `calib put` of `v1.json` for m1.
fn put_v1(d: &Path, bus: &str) {
    ok(
        d,
        &[
            "calib",
            "put",
            "--machine",
            "m1",
            "--file",
            "v1.json",
            "--connect",
            bus,
        ],
    );
}

/// `replay --bag r.mcap` at `speed` (`max` or a factor), in the background.
fn replay_in_background(d: &Path, bus: &str, speed: &str, looping: bool) -> std::process::Child {
    let mut args = vec![
        "replay",
        "--bag",
        "r.mcap",
        "--speed",
        speed,
        "--connect",
        bus,
    ];
    if looping {
        args.push("--loop");
    }
    Command::new(scancorr())
        .args(args)
        .current_dir(d)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap()
}

fn status(d: &Path, bus: &str) -> Value {
    serde_json::from_str(&ok(
        d,
        &["status", "--machine", "m1", "--connect", bus, "--json"],
    ))
    .unwrap()
}

#[test]
fn metrics_audit_trail_and_rollback() {
    let d = scratch("service-ops");
    let (port, mport) = (free_port(), free_port());
    let bus = format!("tcp/127.0.0.1:{port}");
    let svc = Service::start_with(
        &d,
        port,
        &format!("listen: ['tcp/127.0.0.1:{port}'], metrics_listen: '127.0.0.1:{mport}', throughput_log_s: 1,"),
    );
    sim_ring(&d, "v1.json");
    for _ in 0..2 {
        calib_put(&d, "m1", "v1.json", &bus);
    }
    replay_max(&d, "r.mcap", &bus);

    // Rollback: version 1 current again, as version 3 with parent 2.
    let r: Value = serde_json::from_str(&ok(
        &d,
        &[
            "calib",
            "rollback",
            "--machine",
            "m1",
            "--to",
            "1",
            "--connect",
            &bus,
            "--json",
        ],
    ))
    .unwrap();
    assert_eq!(
        (r["version"].as_u64(), r["parent_version"].as_u64()),
        (Some(3), Some(2)),
        "{r}"
    );
    fails(
        &d,
        &[
            "calib",
            "rollback",
            "--machine",
            "m1",
            "--to",
            "3",
            "--connect",
            &bus,
        ],
        &["already current"],
    );
    fails(
        &d,
        &[
            "calib",
            "rollback",
            "--machine",
            "m1",
            "--to",
            "9",
            "--connect",
            &bus,
        ],
        &["no calibration version 9"],
    );
    let h: Value = serde_json::from_str(&ok(
        &d,
        &[
            "calib",
            "history",
            "--machine",
            "m1",
            "--connect",
            &bus,
            "--json",
        ],
    ))
    .unwrap();
    let h = h.as_array().unwrap();
    assert_eq!(h.len(), 3, "{h:?}");
    let actions: Vec<&str> = h
        .iter()
        .map(|v| v["audit"]["action"].as_str().unwrap())
        .collect();
    assert_eq!(actions, ["put", "put", "rollback to v1"]);
    // The requester's claim with its session's zenoh id, the user `uid N` when $USER and
    // $LOGNAME are unset: never a made-up `unknown`.
    let user = std::env::var("USER")
        .or_else(|_| std::env::var("LOGNAME"))
        .ok()
        .filter(|u| !u.is_empty())
        .unwrap_or_else(|| {
            let s = std::fs::read_to_string("/proc/self/status").unwrap();
            let uid = s.lines().find_map(|l| l.strip_prefix("Uid:")).unwrap();
            format!("uid {}", uid.split_whitespace().next().unwrap())
        });
    for v in h {
        let a = &v["audit"];
        let by = a["by"].as_str().unwrap();
        assert!(
            by.starts_with(&format!("{user}@"))
                && by.contains("(claimed), zenoh id ")
                && !by.contains("unknown"),
            "{a}"
        );
        let at = a["at"].as_str().unwrap();
        assert!(
            at.len() == 20 && at.ends_with('Z') && at.starts_with("20"),
            "{at}"
        );
    }
    let text = ok(
        &d,
        &["calib", "history", "--machine", "m1", "--connect", &bus],
    );
    assert!(text.contains("rollback to v1 at "), "{text}");
    let v1: Value = serde_json::from_str(&ok(
        &d,
        &[
            "calib",
            "get",
            "--machine",
            "m1",
            "--version",
            "1",
            "--connect",
            &bus,
        ],
    ))
    .unwrap();
    let v3: Value = serde_json::from_str(&ok(
        &d,
        &["calib", "get", "--machine", "m1", "--connect", &bus],
    ))
    .unwrap();
    assert_eq!(v3["effects"], v1["effects"]);
    assert_eq!(v3["version"], 3);

    // The health query: this service answers, ready, serving one machine.
    let h: Value = serde_json::from_str(&ok(&d, &["health", "--connect", &bus, "--json"])).unwrap();
    let h = h.as_array().unwrap();
    assert_eq!(h.len(), 1, "{h:?}");
    assert_eq!(
        (h[0]["ready"].as_bool(), h[0]["machines"].as_u64()),
        (Some(true), Some(1)),
        "{h:?}"
    );
    assert_eq!(h[0]["version"], env!("CARGO_PKG_VERSION"));
    // A peer has no router to lose.
    assert!(h[0]["router_link"].is_null(), "{h:?}");
    let text = ok(&d, &["health", "--connect", &bus]);
    assert!(
        text.contains("ready") && text.contains("1 machine(s)"),
        "{text}"
    );
    // The metrics endpoint: what the status says, in Prometheus' text format.
    std::thread::sleep(Duration::from_millis(1500));
    let st = status(&d, &bus);
    let m = http_get(mport, "/metrics");
    assert!(
        m.starts_with("HTTP/1.1 200") && m.contains("text/plain; version=0.0.4"),
        "{m}"
    );
    for s in ["command", "scale", "probe", "temperature"] {
        let series = format!("scancorr_samples_in_total{{machine=\"m1\",stream=\"{s}\"}}");
        assert!(
            sample(&m, &series).is_some_and(|v| v > 0.0),
            "{series}: {m}"
        );
    }
    assert_eq!(
        sample(&m, "scancorr_points_out_total{machine=\"m1\"}"),
        st["points_out"].as_f64(),
        "{m}"
    );
    assert_eq!(
        sample(&m, "scancorr_calibration_version{machine=\"m1\"}"),
        Some(3.0)
    );
    assert_eq!(
        sample(&m, "scancorr_calibration_puts_total{machine=\"m1\"}"),
        Some(3.0)
    );
    assert_eq!(sample(&m, "scancorr_machines"), Some(1.0));
    assert!(m.contains("# TYPE scancorr_samples_dropped_total counter"));
    assert!(
        m.contains(
            "scancorr_samples_dropped_total{machine=\"m1\",reason=\"temperature_missing\"} 200"
        ),
        "{m}"
    );
    assert!(
        sample(
            &m,
            "scancorr_samples_missing_total{machine=\"m1\",stream=\"scale\"}"
        ) == Some(0.0)
    );
    assert!(http_get(mport, "/").starts_with("HTTP/1.1 404"));
    // The log: a startup line with the version; a throughput line; no colour off a terminal.
    let log = svc.log();
    assert!(
        log.contains("scancorrd started") && log.contains(env!("CARGO_PKG_VERSION")),
        "{log}"
    );
    assert!(
        log.contains("throughput") && log.contains("samples_per_s"),
        "{log}"
    );
    assert!(!log.contains('\x1b'), "colour codes in a log file");
    svc.stop();
}

#[test]
fn systemd_readiness_watchdog_and_json_logs() {
    let d = scratch("service-notify");
    let sock_path = d.join("notify.sock");
    let sock = UnixDatagram::bind(&sock_path).unwrap();
    sock.set_read_timeout(Some(Duration::from_secs(20)))
        .unwrap();
    let port = free_port();
    let log = d.join("json.log");
    let mut child = Command::new(scancorrd())
        .args([
            "--listen",
            &format!("tcp/127.0.0.1:{port}"),
            "--data-dir",
            "data",
            "--log-format",
            "json",
        ])
        .env("NOTIFY_SOCKET", &sock_path)
        .env("WATCHDOG_USEC", "600000")
        .current_dir(&d)
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&log).unwrap())
        .spawn()
        .unwrap();
    let mut buf = [0u8; 512];
    let mut seen = vec![];
    let t0 = Instant::now();
    while !(seen.iter().any(|m: &String| m.starts_with("READY=1"))
        && seen.iter().any(|m| m == "WATCHDOG=1"))
    {
        let n = sock.recv(&mut buf).expect("a notification within 20 s");
        seen.push(String::from_utf8_lossy(&buf[..n]).to_string());
        assert!(t0.elapsed() < Duration::from_secs(30), "{seen:?}");
    }
    // The watchdog keeps coming at half the interval (0.3 s).
    let t1 = Instant::now();
    let n = sock.recv(&mut buf).unwrap();
    assert_eq!(&buf[..n], b"WATCHDOG=1");
    assert!(
        t1.elapsed() < Duration::from_millis(900),
        "{:?}",
        t1.elapsed()
    );
    let _ = Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status();
    let t2 = Instant::now();
    loop {
        let n = sock.recv(&mut buf).expect("STOPPING=1");
        if &buf[..n] == b"STOPPING=1" {
            break;
        }
        assert!(t2.elapsed() < Duration::from_secs(20));
    }
    assert!(child.wait().unwrap().success());
    // JSON lines: every line an object; the startup line has the version and configuration.
    let text = std::fs::read_to_string(&log).unwrap();
    let lines: Vec<Value> = text
        .lines()
        .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("not JSON ({e}): {l}")))
        .collect();
    let start = lines
        .iter()
        .find(|v| v["message"] == "scancorrd started")
        .unwrap_or_else(|| panic!("{text}"));
    assert_eq!(start["version"], env!("CARGO_PKG_VERSION"));
    assert_eq!(start["systemd_notify"], true);
    assert!(start["listen"]
        .as_str()
        .unwrap()
        .contains(&port.to_string()));

    // Nothing answers the health query once it stopped: a clear error, non-zero.
    let out = run(
        &d,
        &["health", "--connect", &format!("tcp/127.0.0.1:{port}")],
    );
    assert!(!out.status.success());
    // A configuration error: one line on stderr, exit 2, no backtrace.
    std::fs::write(d.join("bad.json5"), "{ metrics_listen: 'nowhere' }").unwrap();
    let out = Command::new(scancorrd())
        .args(["--config", "bad.json5"])
        .env("RUST_BACKTRACE", "1")
        .current_dir(&d)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert_eq!(err.trim().lines().count(), 1, "{err}");
    assert!(
        err.contains("metrics_listen") && !err.contains("backtrace"),
        "{err}"
    );
}

#[test]
fn sigkill_mid_stream_keeps_the_history_and_the_database_intact() {
    let d = scratch("service-sigkill");
    let port = free_port();
    let bus = format!("tcp/127.0.0.1:{port}");
    let mut svc = Service::start(&d, port);
    sim_ring(&d, "v1.json");
    put_v1(&d, &bus);
    // The ring replayed in a loop while calibrations are put, and the service killed.
    let mut replay = replay_in_background(&d, &bus, "max", true);
    std::thread::sleep(Duration::from_millis(1500));
    let mut acknowledged = 1;
    for _ in 0..5 {
        let out = run(
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
        if out.status.success() {
            acknowledged += 1;
        }
    }
    // SIGKILL while a put may be in flight.
    let put = Command::new(scancorr())
        .args([
            "calib",
            "put",
            "--machine",
            "m1",
            "--file",
            "v1.json",
            "--connect",
            &bus,
        ])
        .current_dir(&d)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    std::thread::sleep(Duration::from_millis(30));
    svc.kill();
    let _ = replay.kill();
    let _ = replay.wait();
    let mut put = put;
    let _ = put.wait();
    // The database: intact.
    let db = rusqlite::Connection::open(d.join("data").join(scancorrd::store::FILE_NAME)).unwrap();
    let check: String = db
        .query_row("PRAGMA integrity_check", [], |r| r.get(0))
        .unwrap();
    assert_eq!(check, "ok");
    drop(db);
    // Restarted on the same data: the history has every acknowledged version, numbered
    // without a gap, the current one the newest; processing resumes.
    let svc = Service::start(&d, port);
    let h: Value = serde_json::from_str(&ok(
        &d,
        &[
            "calib",
            "history",
            "--machine",
            "m1",
            "--connect",
            &bus,
            "--json",
        ],
    ))
    .unwrap();
    let versions: Vec<u64> = h
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v["version"].as_u64().unwrap())
        .collect();
    assert!(
        versions.len() >= acknowledged,
        "{versions:?} < {acknowledged} acknowledged"
    );
    assert_eq!(versions, (1..=versions.len() as u64).collect::<Vec<_>>());
    let current: Vec<u64> = h
        .as_array()
        .unwrap()
        .iter()
        .filter(|v| v["current"] == true)
        .map(|v| v["version"].as_u64().unwrap())
        .collect();
    assert_eq!(current, vec![*versions.last().unwrap()]);
    assert!(
        h.as_array()
            .unwrap()
            .iter()
            .all(|v| v.get("damaged").is_none()),
        "{h}"
    );
    replay_max(&d, "r.mcap", &bus);
    std::thread::sleep(Duration::from_millis(500));
    let st = status(&d, &bus);
    assert_eq!(st["samples_in"], 51829, "{st}");
    svc.stop();
}

/// The router restarted mid-stream: scancorrd (a client of it) reconnects by itself and goes
/// on correcting; what was lost while the router was down is counted, per stream, as
/// samples missing in seq — and the count is the samples that did not arrive. The outage
/// itself is in the log (lost, back after how long) and on `health`.
#[test]
fn a_router_restart_mid_stream_is_survived_and_the_loss_counted() {
    let d = scratch("router-restart");
    let (port, mport) = (free_port(), free_port());
    let bus = format!("tcp/127.0.0.1:{port}");
    std::fs::write(
        d.join("svc.json5"),
        format!("{{ mode: 'client', listen: [], connect: ['{bus}'], data_dir: 'data', metrics_listen: '127.0.0.1:{mport}' }}"),
    )
    .unwrap();
    let mut router = start_router(&d, port);
    let mut svc = Command::new(scancorrd())
        .args(["--config", "svc.json5"])
        .current_dir(&d)
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(d.join("svc.log")).unwrap())
        .spawn()
        .unwrap();
    sim_ring(&d, "v1.json");
    put_v1(&d, &bus);
    // The ring in real time (17 s); the router killed after 5 s and back 2 s later.
    let mut replay = replay_in_background(&d, &bus, "1", false);
    std::thread::sleep(Duration::from_secs(5));
    let before = status(&d, &bus);
    let _ = router.kill();
    let _ = router.wait();
    std::thread::sleep(Duration::from_secs(2));
    let mut router = start_router(&d, port);
    let out = replay.wait().unwrap();
    assert!(
        out.success(),
        "the replay (a client of the router too) did not survive the restart"
    );
    std::thread::sleep(Duration::from_secs(1));
    let after = status(&d, &bus);
    let n = |v: &Value, k: &str| v[k].as_u64().unwrap();
    let missing: u64 = ["command", "scale", "probe", "temperature"]
        .iter()
        .map(|s| after["samples_missing"][s].as_u64().unwrap())
        .sum();
    eprintln!(
        "router restart: {} samples in before, {} after; {} missing; points {} → {}",
        n(&before, "samples_in"),
        n(&after, "samples_in"),
        missing,
        n(&before, "points_out"),
        n(&after, "points_out")
    );
    // Corrected after the restart, and everything either arrived or is counted missing
    // (the samples of the last partial batch after the restart excepted: none here).
    assert!(
        n(&after, "points_out") > n(&before, "points_out") + 3000,
        "{after}"
    );
    assert!(missing > 1000, "the outage lost nothing? {after}");
    assert_eq!(n(&after, "samples_in") + missing, 51829, "{after}");
    let h: Value = serde_json::from_str(&ok(&d, &["health", "--connect", &bus, "--json"])).unwrap();
    let link = &h[0]["router_link"];
    let log = std::fs::read_to_string(d.join("svc.log")).unwrap();
    assert_eq!(
        (link["routers"].as_u64(), link["losses"].as_u64()),
        (Some(1), Some(1)),
        "{h}\n{log}"
    );
    // Down for the 2 s between kill and restart, and until zenoh connected again.
    let down = link["down_s"].as_f64().unwrap();
    assert!((1.5..20.0).contains(&down), "{h}");
    assert!(
        log.contains("lost the connection to the router")
            && log.contains("connected to the router again after"),
        "{log}"
    );
    let text = ok(&d, &["health", "--connect", &bus]);
    assert!(text.contains("1 router(s), lost 1 time(s)"), "{text}");
    let m = http_get(mport, "/metrics");
    assert!(
        m.contains("\nscancorr_routers_connected 1\n")
            && m.contains("\nscancorr_router_losses_total 1\n"),
        "{m}"
    );
    let _ = svc.kill();
    let _ = svc.wait();
    let _ = router.kill();
    let _ = router.wait();
}

/// The short CI version of the load run: a fleet at 1 kHz per machine through a
/// `scancorr-router` (scancorrd, the controllers on three links and the consumer its clients)
/// loses no point. The full run is `scancorr bench fleet --machines 200 --seconds 300 --router`.
#[test]
fn a_fleet_through_the_router_loses_no_point() {
    let d = scratch("fleet-router");
    let out = ok(
        &d,
        &[
            "bench",
            "fleet",
            "--machines",
            "20",
            "--seconds",
            "5",
            "--router",
            "--links",
            "3",
            "--json",
        ],
    );
    let v: Value = serde_json::from_str(&out).unwrap();
    assert_eq!(v["through_router"], true);
    assert_eq!(v["controller_links"], 3, "{v}");
    // Where the latency goes: the controllers' puts and the service's own share, both
    // measured (each machine's status reports what it added).
    let parts = &v["latency_parts"];
    assert!(
        parts["controller_put_span_ms_max"].as_f64().unwrap() > 0.0,
        "{v}"
    );
    assert!(
        parts["service_added_p99_ms_worst_machine"]
            .as_f64()
            .unwrap()
            > 0.0,
        "{v}"
    );
    assert_eq!(v["received_points"], v["expected_points"], "{v}");
    assert!(v["expected_points"].as_u64().unwrap() >= 90_000, "{v}");
    assert_eq!(v["seq_gaps"], 0, "{v}");
}

/// `bench fleet --relay`, the bus's own cost under the service's: a bare relay serves the
/// same fleet in the service's place with the service's output bytes (its own encoder, as
/// many breakdown entries), numbered as the service numbers points, so every point arrives
/// in order; `--relay-effects 0` drops the breakdown (24 bytes an entry less per point). And
/// the service with `publish_breakdown: false` (`--no-breakdown`) publishes every point in
/// the bytes of a point without its breakdown.
#[test]
fn the_bare_relay_moves_the_services_bytes_and_the_breakdown_can_stay_home() {
    let d = scratch("fleet-relay");
    let run = |extra: &[&str]| -> Value {
        let mut args = vec![
            "bench",
            "fleet",
            "--machines",
            "10",
            "--seconds",
            "2",
            "--json",
        ];
        args.extend(extra);
        serde_json::from_str(&ok(&d, &args)).unwrap()
    };
    let service = run(&[]);
    let without = run(&["--no-breakdown"]);
    let relay = run(&["--relay"]);
    let bare = run(&["--relay", "--relay-effects", "0"]);
    for v in [&service, &without, &relay, &bare] {
        assert_eq!(v["received_points"], v["expected_points"], "{v}");
        assert!(v["expected_points"].as_u64().unwrap() >= 15_000, "{v}");
        assert_eq!(v["seq_gaps"], 0, "{v}");
        assert_eq!(v["malformed_point_messages"], 0, "{v}");
    }
    assert_eq!(service["bare_relay"], false, "{service}");
    assert_eq!(relay["bare_relay"], true, "{relay}");
    assert_eq!(service["publish_breakdown"], true, "{service}");
    assert_eq!(without["publish_breakdown"], false, "{without}");
    let per_point = |v: &Value| v["point_bytes_per_point"].as_f64().unwrap();
    let (s, w) = (per_point(&service), per_point(&without));
    let (r, b) = (per_point(&relay), per_point(&bare));
    // The same columns; only the varints' lengths (seq, times, versions) may differ.
    for (x, y, what) in [(r, s, "relay, service"), (b, w, "without breakdown")] {
        assert!(
            (x - y).abs() < 0.02 * y,
            "{what}: {x} against {y} bytes per point"
        );
    }
    // Eight effects' corrections, three doubles each (192 bytes), and their names, once per
    // message of a batch's 100 points (a few bytes per point).
    for (x, y) in [(r, b), (s, w)] {
        assert!(
            (x - y - 8.0 * 24.0).abs() < 4.0,
            "{x} - {y} bytes per point"
        );
    }
}

/// The short CI version of `bench fleet --largest`: a search over two small fleet sizes runs
/// a fleet measurement per probe in one process, and what it reports holds together: the
/// bounds are the probes' verdicts, a size kept up only when each of its runs did, and every
/// run delivered every point. (Whether a size keeps real time depends on the host; the
/// figures are not asserted.)
#[test]
fn the_largest_fleet_search_reports_bounds_its_probes_support() {
    let d = scratch("fleet-largest");
    let out = ok(
        &d,
        &[
            "bench",
            "fleet",
            "--largest",
            "--workers",
            "1",
            "--from",
            "4",
            "--machines",
            "8",
            "--step",
            "4",
            "--runs",
            "1",
            "--seconds",
            "2",
            "--json",
        ],
    );
    let v: Value = serde_json::from_str(&out).unwrap();
    assert_eq!(v["bench"], "fleet-largest", "{v}");
    let probes = v["probes"].as_array().unwrap();
    let verdict = |n: u64| {
        let p = probes
            .iter()
            .find(|p| p["machines"] == n)
            .unwrap_or_else(|| panic!("no probe of {n} machines: {v}"));
        p["kept_up_runs"] == p["runs"] && p["runs"] == 1
    };
    match (v["largest_kept_up"].as_u64(), v["smallest_failed"].as_u64()) {
        // 4 kept up, then 8 did too (both probed) or did not.
        (Some(4), Some(8)) => assert!(verdict(4) && !verdict(8), "{v}"),
        (Some(8), None) => assert!(verdict(4) && verdict(8), "{v}"),
        // 4 did not: the search stops there.
        (None, Some(4)) => assert!(!verdict(4) && probes.len() == 1, "{v}"),
        other => panic!("bounds {other:?} outside the sizes 4 and 8: {v}"),
    }
    for p in probes {
        let runs = p["each_run"].as_array().unwrap();
        assert_eq!(runs.len() as u64, p["runs"].as_u64().unwrap(), "{p}");
        for r in runs {
            assert_eq!(r["machines"], p["machines"], "{r}");
            assert_eq!(r["workers"], 1, "{r}");
            assert!(r["expected_points"].as_u64().unwrap() > 0, "{r}");
            assert_eq!(r["received_points"], r["expected_points"], "{r}");
            assert_eq!(r["seq_gaps"], 0, "{r}");
        }
        let kept = runs.iter().filter(|r| r["kept_up"] == true).count() as u64;
        assert_eq!(p["kept_up_runs"].as_u64().unwrap(), kept, "{p}");
    }
}
