//! One valid calibration never stops the service.
//!
//! A calibration within every documented limit (240 `custom` terms of about 4 kB, each under
//! 64 levels) costs milliseconds of CPU per point. Before, its machine's shard queue filled,
//! zenoh's callback blocked sending to it (every link stalled), the control task waited on
//! the shard's snapshots and stopped sending `WATCHDOG=1` for 37–39 s, other machines lost
//! messages, and `replay` said it had sent what never left.
//!
//! Now: a put of such a calibration is refused (its cost measured on a reference point,
//! against `max_point_cost_us`); and with the limit off, the costly machine sheds its own
//! late messages (counted on its status, said in the log) while the other machine of the same
//! shard loses nothing, the watchdog is fed at its pace, and health is answered.

mod common;
use common::*;
use serde_json::Value;
use std::os::unix::net::UnixDatagram;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

struct Killed(Child);

impl Drop for Killed {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// `calibration` with a `custom` effect of 240 terms of about 4 kB each (every term a sum of
/// chains of sines 58 deep, each of a distinct multiple of the position, so nothing is
/// shared between them).
fn costly(calibration: &str) -> String {
    let mut doc: Value = serde_json::from_str(calibration).unwrap();
    let terms: Vec<Value> = (0..240)
        .map(|t| {
            let mut e = String::new();
            let mut k = 0;
            while e.len() < 3900 {
                if !e.is_empty() {
                    e.push('+');
                }
                // Nested 58 deep (the grammar allows 64 levels).
                e.push_str(&"sin(".repeat(58));
                e.push_str(&format!("x*1.{t:03}{k:03}"));
                e.push_str(&")".repeat(58));
                k += 1;
            }
            let axis = ["x", "y", "z"][t % 3];
            serde_json::json!({"axis": axis, "expr": e})
        })
        .collect();
    doc["effects"]
        .as_array_mut()
        .unwrap()
        .push(serde_json::json!({"kind": "custom", "id": "costly", "terms": terms, "coefficients": vec![1e-12; 240]}));
    let s = doc.to_string();
    assert!(s.len() < 1 << 20, "{} bytes", s.len());
    s
}

fn scancorrd(d: &Path, port: u16, extra: &str, env: &[(&str, String)]) -> Killed {
    std::fs::write(
        d.join("scancorrd.json5"),
        format!("{{ listen: ['tcp/127.0.0.1:{port}'], data_dir: 'data', {extra} }}"),
    )
    .unwrap();
    let mut c = Command::new(common::scancorrd());
    c.args(["--config", "scancorrd.json5"])
        .current_dir(d)
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(d.join("scancorrd.log")).unwrap());
    for (k, v) in env {
        c.env(k, v);
    }
    let child = Killed(c.spawn().unwrap());
    wait_listening(port, || {
        std::fs::read_to_string(d.join("scancorrd.log")).unwrap_or_default()
    });
    child
}

fn status(d: &Path, bus: &str, m: &str) -> Value {
    serde_json::from_str(&ok(
        d,
        &["status", "--machine", m, "--connect", bus, "--json"],
    ))
    .unwrap()
}

#[test]
fn a_calibration_too_costly_for_real_time_is_refused_at_put() {
    let d = scratch("costly-refused");
    let port = free_port();
    let _svc = scancorrd(&d, port, "", &[]);
    let bus = format!("tcp/127.0.0.1:{port}");
    sim_ring(&d, "v1.json");
    let v1 = std::fs::read_to_string(d.join("v1.json")).unwrap();
    std::fs::write(d.join("costly.json"), costly(&v1)).unwrap();
    let err = fails(
        &d,
        &[
            "calib",
            "put",
            "--machine",
            "m1",
            "--file",
            "costly.json",
            "--connect",
            &bus,
        ],
        &["µs of CPU per point", "max_point_cost_us", "real time"],
    );
    eprintln!("{}", err.trim());
    // Nothing was stored; a calibration that keeps real time is taken, its cost on status.
    calib_put(&d, "m1", "v1.json", &bus);
    let s = status(&d, &bus, "m1");
    assert_eq!(s["calibration_version"], 1, "{s}");
    let cost = s["point_cost_us"].as_f64().unwrap();
    assert!(cost > 0.0 && cost < 200.0, "{s}");
}

#[test]
fn a_costly_model_sheds_its_own_machine_and_no_other() {
    let d = scratch("costly-runs");
    let port = free_port();
    let bus = format!("tcp/127.0.0.1:{port}");
    // systemd's side of the notification socket, with a 2 s watchdog (fed every second).
    let sock_path = d.join("notify.sock");
    let sock = UnixDatagram::bind(&sock_path).unwrap();
    sock.set_read_timeout(Some(Duration::from_millis(100)))
        .unwrap();
    let pings = Arc::new(Mutex::new(Vec::<Instant>::new()));
    let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let (p, st) = (pings.clone(), stop.clone());
    let listener = std::thread::spawn(move || {
        let mut buf = [0u8; 512];
        while !st.load(std::sync::atomic::Ordering::Relaxed) {
            if let Ok(n) = sock.recv(&mut buf) {
                if String::from_utf8_lossy(&buf[..n]).contains("WATCHDOG=1") {
                    p.lock().unwrap().push(Instant::now());
                }
            }
        }
    });
    // One shard for both machines (the worst case: the costly one shares it), the put-time
    // limit off so that the costly model runs.
    let svc = scancorrd(
        &d,
        port,
        "workers: 1, max_point_cost_us: 0",
        &[
            ("NOTIFY_SOCKET", sock_path.display().to_string()),
            ("WATCHDOG_USEC", "2000000".into()),
        ],
    );
    let log = || std::fs::read_to_string(d.join("scancorrd.log")).unwrap_or_default();
    sim_ring(&d, "v1.json");
    let v1 = std::fs::read_to_string(d.join("v1.json")).unwrap();
    std::fs::write(
        d.join("v1-m2.json"),
        v1.replace("\"machine_id\": \"m1\"", "\"machine_id\": \"m2\""),
    )
    .unwrap();
    std::fs::write(d.join("costly.json"), costly(&v1)).unwrap();
    for (m, f) in [("m1", "costly.json"), ("m2", "v1-m2.json")] {
        ok(
            &d,
            &[
                "calib",
                "put",
                "--machine",
                m,
                "--file",
                f,
                "--connect",
                &bus,
            ],
        );
    }
    let cost = status(&d, &bus, "m1")["point_cost_us"].as_f64().unwrap();
    eprintln!("the costly model: {cost:.0} µs per point on the reference point");
    assert!(
        cost > 1000.0,
        "{cost} µs: not costly enough to test anything"
    );

    // m2's points, as a subscriber gets them.
    let rt = tokio::runtime::Runtime::new().unwrap();
    let session = rt.block_on(common::session(port));
    let got = Arc::new(Mutex::new((0u64, 0u64, None::<u64>)));
    let g = got.clone();
    let _sub = rt
        .block_on(async {
            session
                .declare_subscriber("cmm/m2/corrected/points")
                .callback(move |s| {
                    use scancorr_proto::Message;
                    let b =
                        scancorr_proto::v1::CorrectedPointBatch::decode(&*s.payload().to_bytes())
                            .unwrap();
                    let mut g = g.lock().unwrap();
                    for p in b.into_points().unwrap() {
                        g.0 += 1;
                        if let Some(l) = g.2 {
                            g.1 += p.seq.saturating_sub(l + 1);
                        }
                        g.2 = Some(p.seq);
                    }
                })
                .await
        })
        .unwrap();
    std::thread::sleep(Duration::from_millis(300));

    // Both machines stream a ring scan at twice real time (about 9 s), on their own links.
    let t0 = Instant::now();
    let runs: Vec<_> = [("m1", "3"), ("m2", "4")]
        .into_iter()
        .map(|(m, seed)| {
            let (d, bus) = (d.to_path_buf(), bus.clone());
            std::thread::spawn(move || {
                run(
                    &d,
                    &[
                        "sim",
                        "--program",
                        "ring",
                        "--live",
                        "--live-rate",
                        "2",
                        "--machine",
                        m,
                        "--seed",
                        seed,
                        "--out",
                        &format!("{m}.mcap"),
                        "--connect",
                        &bus,
                    ],
                )
            })
        })
        .collect();
    // Health is answered meanwhile, at once.
    std::thread::sleep(Duration::from_secs(4));
    let h0 = Instant::now();
    let h = run(&d, &["health", "--json", "--connect", &bus]);
    let health_s = h0.elapsed().as_secs_f64();
    assert!(
        h.status.success(),
        "health during the run: {}",
        String::from_utf8_lossy(&h.stderr)
    );
    let outs: Vec<_> = runs.into_iter().map(|r| r.join().unwrap()).collect();
    let streamed = t0.elapsed();
    for (k, o) in outs.iter().enumerate() {
        assert!(
            o.status.success(),
            "m{}: {}\n{}",
            k + 1,
            String::from_utf8_lossy(&o.stderr),
            log()
        );
    }
    let m1_said = String::from_utf8_lossy(&outs[0].stderr).to_string();
    let m2_said = String::from_utf8_lossy(&outs[1].stderr).to_string();

    // What the other machine should have: every point `scancorr correct` makes of its bag.
    let offline: Value = serde_json::from_str(&ok(
        &d,
        &[
            "correct",
            "--bag",
            "m2.mcap",
            "--calib",
            "v1-m2.json",
            "--json",
        ],
    ))
    .unwrap();
    let want = offline["points"].as_u64().unwrap();
    let t1 = Instant::now();
    let (mut s1, mut s2);
    loop {
        s2 = status(&d, &bus, "m2");
        s1 = status(&d, &bus, "m1");
        let done = s2["points_out"].as_u64() == Some(want)
            && s2["output"]["points_published"].as_u64() == Some(want)
            && got.lock().unwrap().0 >= want;
        if done || t1.elapsed() > Duration::from_secs(20) {
            break;
        }
        std::thread::sleep(Duration::from_millis(300));
    }
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    listener.join().unwrap();
    let pings = pings.lock().unwrap().clone();
    let gaps: Vec<f64> = pings
        .windows(2)
        .map(|w| (w[1] - w[0]).as_secs_f64())
        .collect();
    let longest = gaps.iter().cloned().fold(0.0, f64::max);
    let (n, missing, _) = *got.lock().unwrap();
    let report = format!(
        "streamed in {:.1} s; m2: {n} of {want} points received, {missing} missing; health answered in {health_s:.2} s; {} watchdog pings, longest gap {longest:.2} s\nm1: {s1}\nm2: {s2}\nm1's replay: {m1_said}\nm2's replay: {m2_said}",
        streamed.as_secs_f64(),
        pings.len()
    );
    eprintln!("{}", report.lines().next().unwrap());
    eprintln!(
        "m1 input {}; cost {} µs per point live",
        s1["input"], s1["cost_us_per_point"]
    );

    // The other machine lost nothing.
    assert_eq!((n, missing), (want, 0), "{report}");
    assert_eq!(s2["points_out"], want, "{report}");
    assert_eq!(s2["input"]["shed"], 0, "{report}");
    for st in ["command", "scale", "probe", "temperature"] {
        assert_eq!(s2["samples_missing"][st], 0, "{st}: {report}");
    }
    assert!(!m2_said.contains("warning"), "{report}");
    // The costly machine shed its own late messages: counted, said by the service and by the
    // replay (all of them arrived).
    assert!(s1["input"]["shed"].as_u64().unwrap() > 0, "{report}");
    assert!(
        s1["input"]["arrived"].as_u64().unwrap() > 0 && m1_said.contains("shed"),
        "{report}"
    );
    assert!(log().contains("fell behind real time"), "{report}");
    // The watchdog was fed at its pace (every second of a 2 s interval) throughout.
    assert!(
        pings.len() as f64 >= streamed.as_secs_f64() * 0.7,
        "{report}"
    );
    assert!(longest < 2.0, "{report}");
    assert!(health_s < 3.0, "{report}");
    drop(svc);
}
