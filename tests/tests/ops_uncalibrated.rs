//! Issue 47, the operator's side: a machine that streams with no calibration is a loud state
//! of the service — its samples counted (`uncorrected_samples` on its status, the health reply
//! and the metrics), said in the log once per period (not per sample), and one alarm on the
//! machine's alarm key — and the service's JSON log is typed JSON, one object per line,
//! without an escape byte when it goes to a file. Driven straight on the bus (no CLI).

mod common;
use common::*;
use scancorr_proto::v1;
use scancorr_proto::Message;
use serde_json::Value;
use std::io::{Read, Write};
use std::process::{Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// A tagged batch of `n` scale samples of m1 from `seq0`, 1 ms apart.
fn scales(seq0: u64, n: u64) -> Vec<u8> {
    v1::ScaleBatch {
        samples: (seq0..seq0 + n)
            .map(|k| v1::ScaleSample {
                machine_id: "m1".into(),
                seq: k,
                t_ns: 1_000_000_000 + k as i64 * 1_000_000,
                x: 100.0,
                y: 50.0,
                z: 10.0,
            })
            .collect(),
        stream: v1::StreamKind::Scale as i32,
        columns: None,
    }
    .encode_to_vec()
}

async fn get_json(s: &zenoh::Session, key: &str) -> Value {
    let r = s
        .get(key)
        .timeout(Duration::from_secs(5))
        .await
        .unwrap()
        .recv_async()
        .await
        .unwrap_or_else(|e| panic!("{key}: no reply: {e}"));
    let t = r
        .into_result()
        .unwrap()
        .payload()
        .try_to_string()
        .unwrap()
        .to_string();
    serde_json::from_str(&t).unwrap()
}

fn http_get(port: u16, path: &str) -> String {
    let mut c = std::net::TcpStream::connect(("127.0.0.1", port)).unwrap();
    c.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    write!(c, "GET {path} HTTP/1.1\r\nHost: localhost\r\n\r\n").unwrap();
    let mut s = String::new();
    let _ = c.read_to_string(&mut s);
    s
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn streaming_without_a_calibration_is_counted_shown_logged_once_and_alarmed() {
    let d = scratch("ops-uncalibrated");
    let (port, mport) = (free_port(), free_port());
    std::fs::write(
        d.join("scancorrd.json5"),
        format!("{{ listen: ['tcp/127.0.0.1:{port}'], data_dir: 'data', metrics_listen: '127.0.0.1:{mport}' }}"),
    )
    .unwrap();
    let log = d.join("scancorrd.log");
    let mut child = Command::new(scancorrd())
        .args(["--config", "scancorrd.json5", "--log-format", "json"])
        .env_remove("NO_COLOR")
        .current_dir(&d)
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&log).unwrap())
        .spawn()
        .unwrap();
    wait_listening(port, || std::fs::read_to_string(&log).unwrap_or_default());
    let s = session(port).await;

    // Every alarm of m1.
    let alarms = Arc::new(Mutex::new(Vec::<v1::EstimatorAlarm>::new()));
    let a = alarms.clone();
    let _sub = s
        .declare_subscriber("cmm/m1/alarms/**")
        .callback(move |x| {
            a.lock()
                .unwrap()
                .push(v1::EstimatorAlarm::decode(&*x.payload().to_bytes()).unwrap())
        })
        .await
        .unwrap();
    let scale = s
        .declare_publisher("cmm/m1/raw/scale")
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .await
        .unwrap();
    let t0 = Instant::now();
    while !scale.matching_status().await.unwrap().matching() {
        assert!(
            t0.elapsed() < Duration::from_secs(10),
            "no route to the service"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    // m1 has no calibration: 5 batches of 100 raw samples.
    for b in 0..5 {
        scale.put(scales(b * 100, 100)).await.unwrap();
    }
    let t0 = Instant::now();
    let st = loop {
        let st = status(&s, "m1").await;
        if st["uncorrected_samples"] == 500 || t0.elapsed() > Duration::from_secs(15) {
            break st;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    // The status: counted, not corrected, said.
    assert_eq!(st["uncorrected_samples"], 500, "{st}");
    assert_eq!(st["streaming_uncalibrated"], true, "{st}");
    assert!(st["calibration_version"].is_null(), "{st}");
    assert_eq!(st["points_out"], 0, "{st}");
    // The health reply names the machine and its samples.
    let h = get_json(&s, "cmm/@scancorrd/health").await;
    assert_eq!(h["uncalibrated"]["m1"], 500, "{h}");
    assert_eq!(h["uncorrected_samples"], 500, "{h}");
    // The metrics (published every second).
    let series = "scancorr_uncorrected_samples_total{machine=\"m1\"} 500";
    let t0 = Instant::now();
    let mut m = String::new();
    while !m.contains(series) && t0.elapsed() < Duration::from_secs(5) {
        tokio::time::sleep(Duration::from_millis(250)).await;
        m = http_get(mport, "/metrics");
    }
    assert!(m.contains(series), "{m}");
    // One alarm on the machine's alarm key, raised, with no calibration version nor axis.
    let t0 = Instant::now();
    while alarms.lock().unwrap().is_empty() && t0.elapsed() < Duration::from_secs(5) {
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    // More samples raise no second alarm.
    scale.put(scales(500, 100)).await.unwrap();
    let t0 = Instant::now();
    while status(&s, "m1").await["uncorrected_samples"] != 600 {
        assert!(t0.elapsed() < Duration::from_secs(10));
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    tokio::time::sleep(Duration::from_millis(300)).await;
    {
        let got = alarms.lock().unwrap();
        assert_eq!(got.len(), 1, "{got:?}");
        let a = &got[0];
        assert!(a.raised, "{a:?}");
        assert_eq!(
            (a.machine_id.as_str(), a.calibration_version, a.axis),
            ("m1", 0, v1::Axis::Unspecified as i32),
            "{a:?}"
        );
        assert_eq!(
            a.t_ns,
            1_000_000_000 + 99 * 1_000_000,
            "the newest sample of the first batch"
        );
    }
    drop(_sub);
    drop(scale);
    s.close().await.unwrap();
    let _ = Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status();
    assert!(child.wait().unwrap().success());

    // The log: JSON lines, typed, no escape byte; the state said once (600 samples in well
    // under the 10 s period), its count a JSON number.
    let bytes = std::fs::read(&log).unwrap();
    assert!(!bytes.contains(&0x1b), "an escape byte in a log file");
    let text = String::from_utf8(bytes).unwrap();
    let lines: Vec<Value> = text
        .lines()
        .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("not JSON ({e}): {l}")))
        .collect();
    for l in &lines {
        for (k, v) in l.as_object().unwrap() {
            let debug_form = v
                .as_str()
                .is_some_and(|s| s.starts_with("Some(") || s == "None");
            assert!(!debug_form, "`{k}` logged as Rust's debug form: {l}");
        }
    }
    let said: Vec<&Value> = lines
        .iter()
        .filter(|l| {
            l["message"]
                .as_str()
                .is_some_and(|m| m.starts_with("machine streams with no calibration"))
        })
        .collect();
    assert_eq!(said.len(), 1, "{text}");
    assert!(said[0]["uncorrected_samples"].is_u64(), "{}", said[0]);
    assert_eq!(said[0]["machine"], "m1");
    let serving = lines
        .iter()
        .find(|l| l["message"] == "serving machine")
        .unwrap_or_else(|| panic!("{text}"));
    assert_eq!(serving["calibrated"], false, "{serving}");
    let start = lines
        .iter()
        .find(|l| l["message"] == "scancorrd started")
        .unwrap_or_else(|| panic!("{text}"));
    assert_eq!(start["allow_any_machine"], true, "{start}");
    assert!(
        start["zenoh_config"].is_null(),
        "an absent value is left out: {start}"
    );
    assert_eq!(start["metrics"], format!("127.0.0.1:{mport}"), "{start}");
}

/// `sim --live` and `replay` to a service that has no calibration for the machine do not
/// "succeed": they exit non-zero and say the machine was not corrected and what to do; the
/// bag is kept. With a calibration put, the same replay succeeds.
#[test]
fn publishing_to_an_uncalibrated_machine_fails_loudly() {
    let d = scratch("ops-uncalibrated-cli");
    let port = free_port();
    let _svc = Service::start(&d, port);
    let ep = format!("tcp/127.0.0.1:{port}");
    let needles = ["no calibration in use", "`m1`", "scancorr calib put"];
    let err = fails(
        &d,
        &[
            "sim",
            "--program",
            "ring",
            "--live",
            "--live-rate",
            "max",
            "--out",
            "r.mcap",
            "--calib-out",
            "v1.json",
            "--connect",
            &ep,
        ],
        &needles,
    );
    assert!(d.join("r.mcap").exists(), "the bag is kept: {err}");
    fails(
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
        &needles,
    );
    calib_put(&d, "m1", "v1.json", &ep);
    replay_max(&d, "r.mcap", &ep);
}

/// `tail` of a machine that streams with no calibration says so — the machine is not
/// corrected because scancorrd has no calibration for it, and how to put one — instead of
/// blaming the streams: while it streams (the no-calibration alarm, then the error) and
/// afterwards (from the machine's status, at once and as the error).
#[test]
fn tail_of_an_uncalibrated_machine_names_the_missing_calibration() {
    let d = scratch("ops-uncalibrated-tail");
    let port = free_port();
    let _svc = Service::start(&d, port);
    let ep = format!("tcp/127.0.0.1:{port}");
    ok(
        &d,
        &[
            "sim",
            "--program",
            "ring",
            "--seed",
            "4701",
            "--out",
            "r.mcap",
            "--calib-out",
            "v1.json",
        ],
    );
    let needles = [
        "machine `m1` is not corrected",
        "no calibration in use",
        "scancorr calib put --machine m1",
    ];
    // Tailing while the machine streams.
    let tail = Command::new(scancorr())
        .args([
            "tail",
            "--machine",
            "m1",
            "--seconds",
            "8",
            "--connect",
            &ep,
        ])
        .current_dir(&d)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    std::thread::sleep(Duration::from_millis(1500));
    fails(
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
        &["no calibration in use"],
    );
    let out = tail.wait_with_output().unwrap();
    let (so, se) = (
        String::from_utf8_lossy(&out.stdout).to_string(),
        String::from_utf8_lossy(&out.stderr).to_string(),
    );
    assert_eq!(out.status.code(), Some(1), "{so}\n{se}");
    assert!(
        so.contains("m1 NOT CORRECTED: streaming with no calibration in use"),
        "the no-calibration alarm, said as such:\n{so}"
    );
    assert!(!so.contains("ALARM RAISED"), "{so}");
    assert!(!se.contains("raw streams reaching"), "{se}");
    assert!(se.contains("received no point on `cmm/m1/**`"), "{se}");
    // Tailing afterwards: said at once (a warning) and as the error, with the count.
    let err = fails(
        &d,
        &[
            "tail",
            "--machine",
            "m1",
            "--seconds",
            "1",
            "--connect",
            &ep,
        ],
        &needles,
    );
    assert!(
        err.contains("warning: machine `m1` is not corrected"),
        "{err}"
    );
    assert!(!err.contains("raw streams reaching"), "{err}");
    let samples = ok(
        &d,
        &["status", "--machine", "m1", "--json", "--connect", &ep],
    );
    let st: Value = serde_json::from_str(&samples).unwrap();
    let n = st["uncorrected_samples"].as_u64().unwrap();
    assert!(n > 0, "{st}");
    assert!(
        err.contains(&format!("({n} sample(s) streamed uncorrected")),
        "{err}"
    );
}
