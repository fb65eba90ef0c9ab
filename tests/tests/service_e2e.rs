//! End to end across processes over a real zenoh session on loopback: scancorrd, a replayed
//! bag as the machine controller, a recorder as the consumer; live equals offline; a
//! calibration put mid-stream; a restart keeps the history.

mod common;
use common::*;
use std::process::{Command, Stdio};
use std::time::Duration;

#[test]
fn live_equals_offline_calibration_switch_and_restart() {
    let d = scratch("service");
    let port = free_port();
    let bus = ["--connect".to_string(), format!("tcp/127.0.0.1:{port}")];
    let with_bus = |args: &[&str]| -> Vec<String> {
        args.iter()
            .map(|s| s.to_string())
            .chain(bus.iter().cloned())
            .collect()
    };
    let run_bus = |args: &[&str]| {
        ok(
            &d,
            &with_bus(args)
                .iter()
                .map(|s| s.as_str())
                .collect::<Vec<_>>(),
        )
    };
    ok(
        &d,
        &[
            "sim",
            "--program",
            "ring-speeds",
            "--out",
            "r.mcap",
            "--calib-out",
            "v1.json",
        ],
    );

    // --- Live equals offline. ---
    let svc = Service::start(&d, port);
    let put = run_bus(&[
        "calib",
        "put",
        "--machine",
        "m1",
        "--file",
        "v1.json",
        "--json",
    ]);
    assert!(put.contains("\"version\":1"), "{put}");
    let mut rec = Command::new(scancorr())
        .args(with_bus(&[
            "record",
            "--keys",
            "cmm/m1/corrected/**",
            "--out",
            "live.mcap",
            "--idle",
            "3",
            "--seconds",
            "120",
        ]))
        .current_dir(&d)
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    std::thread::sleep(Duration::from_millis(800));
    run_bus(&["replay", "--bag", "r.mcap", "--speed", "max"]);
    std::thread::sleep(Duration::from_millis(500));
    let status: serde_json::Value =
        serde_json::from_str(&run_bus(&["status", "--machine", "m1", "--json"])).unwrap();
    assert_eq!(status["calibration_version"], 1, "{status}");
    svc.stop(); // flushes what is buffered
    assert!(rec.wait().unwrap().success());
    ok(
        &d,
        &[
            "correct", "--bag", "r.mcap", "--calib", "v1.json", "--out", "off.mcap",
        ],
    );
    let live = points(&d.join("live.mcap"));
    let off = points(&d.join("off.mcap"));
    assert!(live.len() > 50_000, "{} live points", live.len());
    assert!(
        live.iter().enumerate().all(|(i, p)| p.seq == i as u64),
        "a seq gap in the live points"
    );
    assert_eq!(live.len(), off.len());
    assert!(live == off, "live points differ from offline points");

    // --- Restart keeps the calibration; a new version mid-stream loses no point. ---
    let svc = Service::start(&d, port);
    let h: serde_json::Value =
        serde_json::from_str(&run_bus(&["calib", "history", "--machine", "m1", "--json"])).unwrap();
    assert_eq!(h.as_array().unwrap().len(), 1, "{h}");
    let mut v2: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("v1.json")).unwrap()).unwrap();
    v2["version"] = 2.into();
    v2["note"] = "second version, put mid-stream".into();
    std::fs::write(d.join("v2.json"), v2.to_string()).unwrap();
    let mut rec = Command::new(scancorr())
        .args(with_bus(&[
            "record",
            "--keys",
            "cmm/m1/corrected/**",
            "--out",
            "live2.mcap",
            "--idle",
            "3",
            "--seconds",
            "120",
        ]))
        .current_dir(&d)
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    std::thread::sleep(Duration::from_millis(800));
    let mut rep = Command::new(scancorr())
        .args(with_bus(&["replay", "--bag", "r.mcap", "--speed", "20"]))
        .current_dir(&d)
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    std::thread::sleep(Duration::from_millis(1500));
    let put = run_bus(&[
        "calib",
        "put",
        "--machine",
        "m1",
        "--file",
        "v2.json",
        "--json",
    ]);
    assert!(put.contains("\"version\":2"), "{put}");
    assert!(rep.wait().unwrap().success());
    std::thread::sleep(Duration::from_millis(500));
    svc.stop();
    assert!(rec.wait().unwrap().success());
    let live2 = points(&d.join("live2.mcap"));
    assert_eq!(live2.len(), off.len(), "every point arrives");
    assert!(
        live2.iter().enumerate().all(|(i, p)| p.seq == i as u64),
        "a seq gap across the calibration switch"
    );
    let switch = live2
        .iter()
        .position(|p| p.calibration_version == 2)
        .expect("version 2 applied mid-stream");
    assert!(
        switch > 1000
            && live2[..switch].iter().all(|p| p.calibration_version == 1)
            && live2[switch..].iter().all(|p| p.calibration_version == 2)
    );
    // Same model content: the points after the switch equal the offline ones.
    assert!(live2[switch..]
        .iter()
        .zip(&off[switch..])
        .all(|(a, b)| a.surface == b.surface));

    // --- A bad document changes nothing; the history survives another restart. ---
    std::fs::write(
        d.join("bad.json"),
        v2.to_string()
            .replace("\"sample_period_s\":0.001", "\"sample_period_s\":-1"),
    )
    .unwrap();
    let svc = Service::start(&d, port);
    let o = Command::new(scancorr())
        .args(with_bus(&[
            "calib",
            "put",
            "--machine",
            "m1",
            "--file",
            "bad.json",
        ]))
        .current_dir(&d)
        .output()
        .unwrap();
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("sample_period_s"));
    let o = Command::new(scancorr())
        .args(with_bus(&[
            "calib",
            "put",
            "--machine",
            "m2",
            "--file",
            "v1.json",
        ]))
        .current_dir(&d)
        .output()
        .unwrap();
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("m2"));
    let h: serde_json::Value =
        serde_json::from_str(&run_bus(&["calib", "history", "--machine", "m1", "--json"])).unwrap();
    let versions: Vec<u64> = h
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v["version"].as_u64().unwrap())
        .collect();
    assert_eq!(versions, vec![1, 2]);
    let cur: serde_json::Value =
        serde_json::from_str(&run_bus(&["calib", "get", "--machine", "m1"])).unwrap();
    assert_eq!(cur["version"], 2);
    // The lab reads the error fall straight from the service's store.
    let hist: serde_json::Value =
        serde_json::from_str(&run_bus(&["lab", "history", "--machine", "m1", "--json"])).unwrap();
    let vs: Vec<u64> = hist
        .as_array()
        .unwrap()
        .iter()
        .map(|r| r["version"].as_u64().unwrap())
        .collect();
    assert_eq!(vs, vec![1, 2], "{hist}");
    svc.stop();
}

#[test]
fn simulator_publishes_live_and_the_service_corrects() {
    let d = scratch("service-live");
    let port = free_port();
    let ep = format!("tcp/127.0.0.1:{port}");
    sim_ring(&d, "v1.json");
    let svc = Service::start(&d, port);
    // Text by default, the service's reply with --json.
    let put = calib_put(&d, "m1", "v1.json", &ep);
    assert!(
        put.starts_with("m1: stored and made current") && !put.contains('{'),
        "{put}"
    );
    let hist = ok(
        &d,
        &["calib", "history", "--machine", "m1", "--connect", &ep],
    );
    assert!(hist.starts_with("v1 ") && !hist.contains('{'), "{hist}");
    ok(
        &d,
        &[
            "sim",
            "--program",
            "ring",
            "--live",
            "--live-rate",
            "max",
            "--connect",
            &ep,
        ],
    );
    std::thread::sleep(Duration::from_millis(500));
    let st: serde_json::Value = serde_json::from_str(&ok(
        &d,
        &["status", "--machine", "m1", "--connect", &ep, "--json"],
    ))
    .unwrap();
    let off: serde_json::Value = serde_json::from_str(&ok(
        &d,
        &["correct", "--bag", "r.mcap", "--calib", "v1.json", "--json"],
    ))
    .unwrap();
    // Everything but the last few points still waiting for their next samples.
    let (live, offline) = (
        st["points_out"].as_u64().unwrap(),
        off["points"].as_u64().unwrap(),
    );
    assert!(
        live + 5 >= offline && live <= offline,
        "{live} live vs {offline} offline: {st}"
    );
    assert_eq!(st["messages"]["malformed"], 0);
    // The lag in the controller's clock (not wall clock minus a clock that starts at 0).
    let lag = st["stream_lag_ms"].as_f64().expect("stream_lag_ms");
    assert!((0.0..1000.0).contains(&lag), "{st}");
    assert!(
        st["last_sample_age_ms"].as_f64().unwrap() < 60_000.0,
        "{st}"
    );
    // Without a machine: the machines served.
    let list: serde_json::Value =
        serde_json::from_str(&ok(&d, &["status", "--connect", &ep, "--json"])).unwrap();
    assert_eq!(list["machines"], serde_json::json!(["m1"]), "{list}");
    let text = ok(&d, &["status", "--machine", "m1", "--connect", &ep]);
    assert!(
        text.contains(&format!("points out: {live}")) && !text.contains('{'),
        "{text}"
    );
    svc.stop();
}

/// A machine whose probe collides mid-scan: the estimator alarms the service publishes live
/// are the offline corrector's, in order and to the bit (the alarms' keys are declared on a
/// machine's first alarm — see scancorrd's `Alarms` — so the first and later alarms take
/// different paths through zenoh; both must arrive).
#[test]
fn live_alarms_equal_offline_alarms() {
    let d = scratch("service-alarms");
    let port = free_port();
    let ep = format!("tcp/127.0.0.1:{port}");
    // A command line of words, run in `d` (on the bus when `bus`).
    let run = |line: &str, bus: bool| {
        let mut args: Vec<&str> = line.split(' ').collect();
        if bus {
            args.extend(["--connect", ep.as_str()]);
        }
        ok(&d, &args)
    };
    // A user's nominal calibration (`scancorr calib nominal` from the data sheet and the
    // catalogue: no effects, data-sheet time constants), never the simulator's own parameters.
    run(
        &format!(
            "sim --program ring --fault collision --out r.mcap {}",
            BUYERS_DOCUMENTS.join(" ")
        ),
        false,
    );
    nominal_start(&d, "nominal.json", true);
    run(
        "correct --bag r.mcap --calib nominal.json --out off.mcap",
        false,
    );
    let off = alarms(&d.join("off.mcap"));
    assert!(
        off.len() >= 2,
        "the collision should raise and clear an alarm offline: {off:?}"
    );
    let svc = Service::start(&d, port);
    run("calib put --machine m1 --file nominal.json", true);
    let count = off.len().to_string();
    let mut rec = Command::new(scancorr())
        .args(["record", "--keys", "cmm/m1/alarms/**", "--out", "live.mcap"])
        .args(["--count", &count, "--seconds", "60", "--connect", &ep])
        .current_dir(&d)
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    std::thread::sleep(Duration::from_millis(800));
    run("replay --bag r.mcap --speed max", true);
    assert!(rec.wait().unwrap().success());
    svc.stop();
    let live = alarms(&d.join("live.mcap"));
    assert_eq!(live, off, "live alarms differ from offline alarms");
}
