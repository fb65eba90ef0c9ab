//! The `scancorr.v1.2` measurement streams (distance probes, micro-stage) next to the four
//! corrected streams: `scancorr correct` and the lab correct a bag that holds them exactly as
//! the same bag without them; scancorrd skips them live and counts them as `not_corrected`
//! (one line in its log), a distance batch on another stream's key is a wrong-stream batch,
//! and the points equal the offline ones.

mod common;
use common::*;
use scancorr_bag::{BagHeader, BagReader, BagWriter, Stream};
use scancorr_proto::v1::*;
use scancorr_proto::Message;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

fn distance_batch(machine: &str, seq: u64, t_ns: i64) -> DistanceBatch {
    DistanceBatch {
        samples: (0..3u32)
            .map(|p| DistanceSample {
                machine_id: machine.into(),
                seq: seq + u64::from(p),
                t_ns,
                probe_id: p,
                distance_mm: 0.001 * f64::from(p) + 1e-9 * t_ns as f64,
                spacing_mm: 40.0 * f64::from(p),
            })
            .collect(),
        stream: StreamKind::Distance as i32,
    }
}

fn stage_batch(machine: &str, seq: u64, t_ns: i64) -> StageBatch {
    StageBatch {
        samples: vec![StageSample {
            machine_id: machine.into(),
            seq,
            t_ns,
            commanded_mm: 0.01,
            sensor_mm: 0.0101,
            probe_id: 2,
        }],
        stream: StreamKind::Stage as i32,
    }
}

/// `src` with distance and stage batches of its machine between its messages (metadata
/// copied); returns the number of messages added.
fn with_measurements(src: &Path, dst: &Path) -> u64 {
    let r = BagReader::open(src).unwrap();
    let mut w = BagWriter::create(dst, BagHeader::default()).unwrap();
    for m in r.metadata() {
        w.write_metadata(&m.name, &m.entries).unwrap();
    }
    let (mut added, mut dseq, mut sseq) = (0u64, 0u64, 0u64);
    for (i, m) in r.messages().unwrap().enumerate() {
        let m = m.unwrap();
        w.write(
            m.stream,
            &m.machine,
            r.prefix(),
            m.log_time,
            m.publish_time,
            &m.data,
        )
        .unwrap();
        let t = m.publish_time as i64;
        if i % 20 == 0 {
            w.write_msg(
                &m.machine,
                r.prefix(),
                m.log_time,
                &distance_batch(&m.machine, dseq, t),
            )
            .unwrap();
            dseq += 3;
            added += 1;
        }
        if i % 40 == 0 {
            w.write_msg(
                &m.machine,
                r.prefix(),
                m.log_time,
                &stage_batch(&m.machine, sseq, t),
            )
            .unwrap();
            sseq += 1;
            added += 1;
        }
    }
    w.finish().unwrap();
    added
}

/// Runs `scancorr ARGS` in `dir`, expecting success: (stdout, stderr).
fn ok_with_stderr(dir: &Path, args: &[&str]) -> (String, String) {
    let o = run(dir, args);
    let err = String::from_utf8_lossy(&o.stderr).to_string();
    assert!(o.status.success(), "scancorr {args:?} failed:\n{err}");
    (String::from_utf8(o.stdout).unwrap(), err)
}

#[test]
fn offline_tools_correct_the_four_streams_and_skip_the_measurements() {
    let d = scratch("measurement-offline");
    sim_ring(&d, "v1.json");
    let added = with_measurements(&d.join("r.mcap"), &d.join("rds.mcap"));
    assert!(added > 50, "{added}");
    let bag = BagReader::open(d.join("rds.mcap")).unwrap();
    assert!(bag.channel("m1", Stream::Distance).is_some());
    assert!(bag.channel("m1", Stream::Stage).is_some());
    assert!(bag.unknown_channels().is_empty());
    let sep = scancorr_bag::measure::read_separation(&bag, "m1").unwrap();
    assert!(sep.warnings().is_empty(), "{:?}", sep.warnings());
    assert_eq!(sep.probe_ids(), [0, 1, 2]);

    let correct = |bag: &str, out: &str| {
        let (out, err) = ok_with_stderr(
            &d,
            &[
                "correct", "--bag", bag, "--calib", "v1.json", "--out", out, "--json",
            ],
        );
        let mut v: serde_json::Value = serde_json::from_str(&out).unwrap();
        for timing in ["seconds", "samples_per_s"] {
            v.as_object_mut().unwrap().remove(timing).expect(timing);
        }
        (v, err)
    };
    let (plain, plain_err) = correct("r.mcap", "a.mcap");
    let (with, with_err) = correct("rds.mcap", "b.mcap");
    assert_eq!(plain, with, "the same summary (samples, points, drops)");
    assert_eq!(
        plain_err, with_err,
        "no warning about the measurement channels"
    );
    let (a, b) = (points(&d.join("a.mcap")), points(&d.join("b.mcap")));
    assert!(a.len() > 1000, "{} points", a.len());
    assert!(
        a == b,
        "points differ with the measurement streams in the bag"
    );

    // The lab replays the bag's samples through the same core.
    let lab = |bag: &str| {
        let (out, err) = ok_with_stderr(
            &d,
            &[
                "lab", "compare", "--bag", bag, "--calib", "v1.json", "--json",
            ],
        );
        let v: serde_json::Value = serde_json::from_str(&out).unwrap();
        (v, err.replace(bag, "BAG"))
    };
    let (plain, plain_err) = lab("r.mcap");
    let (with, with_err) = lab("rds.mcap");
    for k in ["rms_um", "pv_um", "noise_floor_um"] {
        assert!(plain[k].is_number(), "{k}: {plain}");
        assert_eq!(plain[k], with[k], "{k}");
    }
    assert_eq!(plain_err, with_err);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_service_skips_the_measurements_and_counts_them() {
    let d = scratch("measurement-live");
    sim_ring(&d, "v1.json");
    let added = with_measurements(&d.join("r.mcap"), &d.join("rds.mcap"));
    let port = free_port();
    let bus = ["--connect".to_string(), format!("tcp/127.0.0.1:{port}")];
    let with_bus = |args: &[&str]| -> Vec<String> {
        args.iter()
            .map(|s| s.to_string())
            .chain(bus.iter().cloned())
            .collect()
    };
    let run_bus = |args: &[&str]| {
        let a = with_bus(args);
        ok(&d, &a.iter().map(|s| s.as_str()).collect::<Vec<_>>())
    };
    let svc = Service::start(&d, port);
    run_bus(&["calib", "put", "--machine", "m1", "--file", "v1.json"]);
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

    // By hand: a distance and a stage batch of m1, a distance batch of a machine nobody
    // serves, and a distance batch published on m1's scale key.
    let s = session(port).await;
    let distance = distance_batch("m1", 0, 1_000).encode_to_vec();
    for (key, bytes) in [
        ("cmm/m1/raw/distance", distance.clone()),
        (
            "cmm/m1/raw/stage",
            stage_batch("m1", 0, 1_000).encode_to_vec(),
        ),
        (
            "cmm/m5/raw/distance",
            distance_batch("m5", 0, 1_000).encode_to_vec(),
        ),
        ("cmm/m1/raw/scale", distance.clone()),
    ] {
        let p = s
            .declare_publisher(key)
            .congestion_control(zenoh::qos::CongestionControl::Block)
            .await
            .unwrap();
        let t0 = Instant::now();
        while !p.matching_status().await.unwrap().matching() {
            assert!(
                t0.elapsed() < Duration::from_secs(10),
                "nobody subscribes to {key}"
            );
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        p.put(bytes).await.unwrap();
    }
    tokio::time::sleep(Duration::from_millis(800)).await;
    // The recorded bag, measurement streams and all, as a controller would publish it.
    run_bus(&["replay", "--bag", "rds.mcap", "--speed", "max"]);
    let want = 2 + added;
    let t0 = Instant::now();
    let mut st = status(&s, "m1").await;
    while st["messages"]["not_corrected"] != want && t0.elapsed() < Duration::from_secs(20) {
        tokio::time::sleep(Duration::from_millis(200)).await;
        st = status(&s, "m1").await;
    }
    assert_eq!(st["messages"]["not_corrected"], want, "{st}");
    assert_eq!(
        st["messages"]["wrong_stream"], 1,
        "the distance batch on the scale key: {st}"
    );
    assert_eq!(st["messages"]["malformed"], 0, "{st}");
    let m5 = status(&s, "m5").await;
    assert_eq!(m5["served"], false, "{m5}");
    assert_eq!(m5["refused"]["not_corrected"], 1, "{m5}");
    assert_eq!(m5["refused"]["bad_key"], 0, "{m5}");
    s.close().await.unwrap();
    let log = svc.log();
    svc.stop();
    assert!(rec.wait().unwrap().success());
    assert_eq!(
        log.matches("raw/distance and raw/stage").count(),
        1,
        "said once:\n{log}"
    );
    assert!(!log.contains("bad_key"), "{log}");

    // Live equals offline with the measurement streams on the bus.
    ok(
        &d,
        &[
            "correct", "--bag", "r.mcap", "--calib", "v1.json", "--out", "off.mcap",
        ],
    );
    let (live, off) = (points(&d.join("live.mcap")), points(&d.join("off.mcap")));
    assert!(off.len() > 1000, "{} points", off.len());
    assert_eq!(live.len(), off.len());
    assert!(live == off, "live points differ from offline points");
}
