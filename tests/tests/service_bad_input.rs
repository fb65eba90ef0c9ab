//! scancorrd against bad input, each case checked on the status queryable: nothing panics,
//! every dropped sample is counted by reason, the other machines keep being served.

mod common;
use common::*;
use scancorr_core::sample::*;
use scancorr_core::wire::Batcher;
use scancorr_proto::Message;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

fn scale(seq: u64, t_ns: i64, x: f64) -> Sample {
    Sample::Scale(ScaleSample {
        seq,
        t_ns,
        pos: Vec3::new(x, 0.0, 0.0),
    })
}
fn command(seq: u64, t_ns: i64) -> Sample {
    Sample::Command(CommandSample {
        seq,
        t_ns,
        pos: Vec3::zeros(),
        arc_center: Vec3::zeros(),
        arc_radius: 0.0,
        segment_id: 1,
    })
}

fn encode(machine: &str, samples: &[Sample]) -> (StreamId, Vec<u8>) {
    let mut b = Batcher::new(machine, usize::MAX);
    for s in samples {
        b.push(s);
    }
    let sid = samples[0].stream();
    (sid, b.take(sid).unwrap().0)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_input_is_counted_and_never_stops_the_service() {
    let d = scratch("service-bad");
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    std::fs::write(
        d.join("scancorrd.json5"),
        format!("{{ listen: ['tcp/127.0.0.1:{port}'], data_dir: 'data', machines: ['m1', 'm2'], allow_any_machine: false }}"),
    )
    .unwrap();
    let mut svc = Command::new(scancorrd())
        .args(["--config", "scancorrd.json5"])
        .current_dir(&d)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let t0 = Instant::now();
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
        assert!(t0.elapsed() < Duration::from_secs(20));
        std::thread::sleep(Duration::from_millis(50));
    }
    ok(
        &d,
        &[
            "sim",
            "--program",
            "ring",
            "--machine",
            "m2",
            "--out",
            "m2.mcap",
            "--calib-out",
            "m2.json",
        ],
    );
    let cal = std::fs::read_to_string(d.join("m2.json")).unwrap();
    std::fs::write(
        d.join("m1.json"),
        cal.replace("\"machine_id\": \"m2\"", "\"machine_id\": \"m1\""),
    )
    .unwrap();
    let bus = ["--connect".to_string(), format!("tcp/127.0.0.1:{port}")];
    for m in ["m1", "m2"] {
        let mut a: Vec<String> = ["calib", "put", "--machine", m, "--file"]
            .iter()
            .map(|s| s.to_string())
            .collect();
        a.push(format!("{m}.json"));
        a.extend(bus.iter().cloned());
        ok(&d, &a.iter().map(|s| s.as_str()).collect::<Vec<_>>());
    }
    let s = session(port).await;
    let pubs = |stream: &str, m: &str| format!("cmm/{m}/raw/{stream}");
    let scale_pub = s
        .declare_publisher(pubs("scale", "m1"))
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .await
        .unwrap();
    let cmd_pub = s
        .declare_publisher(pubs("command", "m1"))
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .await
        .unwrap();
    let t0 = Instant::now();
    while !scale_pub.matching_status().await.unwrap().matching() {
        assert!(t0.elapsed() < Duration::from_secs(10));
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    // Malformed protobuf and an empty batch.
    scale_pub.put(vec![0xffu8, 0xff, 0xff, 0x01]).await.unwrap();
    scale_pub
        .put(
            scancorr_proto::v1::ScaleBatch {
                samples: vec![],
                stream: scancorr_proto::v1::StreamKind::Scale as i32,
                columns: None,
            }
            .encode_to_vec(),
        )
        .await
        .unwrap();
    // NaN, duplicates, out of order, a clock jumping backwards.
    let mut v = vec![
        scale(0, 0, 1.0),
        scale(1, 1_000_000, f64::NAN),
        scale(1, 1_000_000, 1.0),
        scale(1, 1_000_000, 1.0),
        scale(2, 500_000, 1.0),
    ];
    v.push(scale(3, 2_000_000, 1.0));
    v.push(scale(4, -5_000_000_000, 1.0)); // clock jumps back 5 s
    scale_pub.put(encode("m1", &v).1).await.unwrap();
    // A batch of 100 000 samples (nothing to join them with: buffered up to the limit, the
    // rest counted as overflow).
    let big: Vec<Sample> = (0..100_000)
        .map(|k| scale(10 + k, 3_000_000 + k as i64 * 1_000_000, 1.0))
        .collect();
    scale_pub.put(encode("m1", &big).1).await.unwrap();
    // The probe goes silent while command and scales keep coming: a stall.
    for k in 0..30u64 {
        let t = 200_000_000_000 + k as i64 * 50_000_000;
        cmd_pub
            .put(encode("m1", &[command(1000 + k, t)]).1)
            .await
            .unwrap();
        scale_pub
            .put(encode("m1", &[scale(200_000 + k, t, 1.0)]).1)
            .await
            .unwrap();
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    // A machine outside the assignment: no subscription of the service matches it, so its
    // traffic never reaches the service (nor costs it anything).
    let other = s.declare_publisher(pubs("scale", "m9")).await.unwrap();
    tokio::time::sleep(Duration::from_millis(300)).await;
    assert!(!other.matching_status().await.unwrap().matching());
    other
        .put(encode("m9", &[scale(0, 0, 1.0)]).1)
        .await
        .unwrap();
    tokio::time::sleep(Duration::from_millis(300)).await;

    let st = status(&s, "m1").await;
    eprintln!("{st:#}");
    assert_eq!(st["messages"]["malformed"], 1, "{st}");
    assert_eq!(st["messages"]["empty"], 1);
    let dropped = &st["dropped"];
    assert_eq!(dropped["non_finite"], 1);
    assert_eq!(dropped["duplicate"], 1);
    assert_eq!(
        dropped["out_of_order"], 2,
        "out of order and the backward clock jump"
    );
    assert!(dropped["buffer_overflow"].as_u64().unwrap() >= 80_000);
    assert_eq!(st["points_out"], 0, "no probe: no point may be invented");
    assert!(
        st["stalled"]
            .as_array()
            .unwrap()
            .iter()
            .any(|x| x == "probe"),
        "{st}"
    );
    // Nor does the service answer for it (another instance may): no reply at all.
    let r = s
        .get("cmm/m9/status")
        .timeout(Duration::from_secs(1))
        .await
        .unwrap();
    assert!(r.recv_async().await.is_err(), "an answer about m9");
    assert_eq!(st["served"], true);
    // The other machine is still served.
    let mut a: Vec<String> = ["replay", "--bag", "m2.mcap", "--speed", "max"]
        .iter()
        .map(|s| s.to_string())
        .collect();
    a.extend(bus.iter().cloned());
    ok(&d, &a.iter().map(|s| s.as_str()).collect::<Vec<_>>());
    // Settled: the count no longer moves.
    let mut m2 = status(&s, "m2").await;
    loop {
        tokio::time::sleep(Duration::from_millis(400)).await;
        let again = status(&s, "m2").await;
        if again["points_out"] == m2["points_out"] {
            break;
        }
        m2 = again;
    }
    let first = m2["points_out"].as_u64().unwrap();
    assert!(first > 10_000, "{m2}");
    assert!(
        m2["pending"]["scale"].as_u64().unwrap() <= m2["max_pending"].as_u64().unwrap(),
        "{m2}"
    );
    // The controller reboots: the same run again, clock and seq from the start. The service
    // sees the clock reset, gives the end of the first run (as `correct` does at the end of a
    // bag) and corrects the second run from a fresh start: nothing counted as out of order.
    ok(&d, &a.iter().map(|s| s.as_str()).collect::<Vec<_>>());
    let offline: serde_json::Value = serde_json::from_str(&ok(
        &d,
        &[
            "correct", "--bag", "m2.mcap", "--calib", "m2.json", "--json",
        ],
    ))
    .unwrap();
    let want = first + offline["points"].as_u64().unwrap();
    // The status queryable may answer before the last messages are through: wait for them.
    let t0 = Instant::now();
    let mut m2 = status(&s, "m2").await;
    while m2["points_out"].as_u64().unwrap() < want && t0.elapsed() < Duration::from_secs(20) {
        tokio::time::sleep(Duration::from_millis(200)).await;
        m2 = status(&s, "m2").await;
    }
    assert_eq!(m2["clock_resets"], 1, "{m2}");
    assert_eq!(m2["points_out"].as_u64().unwrap(), want, "{m2}");
    assert!(m2["dropped"].get("out_of_order").is_none(), "{m2}");
    assert!(m2["dropped"].get("duplicate").is_none(), "{m2}");
    s.close().await.unwrap();
    let _ = Command::new("kill")
        .args(["-TERM", &svc.id().to_string()])
        .status();
    let st = svc.wait().unwrap();
    assert!(st.success(), "{st:?}");
}
