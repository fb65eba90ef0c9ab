//! `scancorr bench live`: a bare zenoh relay against scancorrd on loopback, same publisher and
//! subscriber (this process), single-sample messages. The relay (`scancorr bench relay`) and
//! the service each run as their own process, so each path has the same process hops; the
//! cores of this machine are still shared by all three processes.
//!
//! Throughput: every message sent as fast as the path takes it (congestion control Block),
//! until every relayed message or every corrected point has arrived. Latency: at half of the
//! slower path's maximum rate (the same load on both), from publishing an instant's probe sample (the last of its three)
//! to the arrival of that instant's relayed probe sample or corrected point; the service's
//! added latency is its percentile minus the relay's.

use crate::benchfleet::{pct, query, start_scancorrd, Service};
use crate::synth;
use anyhow::{Context, Result};
use scancorr_core::sample::{Sample, StreamId};
use scancorr_core::wire::Batcher;
use scancorr_proto::Message;
use std::collections::HashMap;
use std::process::{Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use zenoh::qos::CongestionControl;

fn z<E: std::fmt::Display>(e: E) -> anyhow::Error {
    anyhow::anyhow!("{e}")
}

async fn session(connect: &[u16], listen: Option<u16>) -> Result<zenoh::Session> {
    let connect: Vec<String> = connect
        .iter()
        .map(|p| format!("tcp/127.0.0.1:{p}"))
        .collect();
    let listen: Vec<String> = listen
        .iter()
        .map(|p| format!("tcp/127.0.0.1:{p}"))
        .collect();
    let cfg = scancorrd::config::zenoh_config("peer", &listen, &connect, false)?;
    zenoh::open(cfg).await.map_err(z)
}

/// `scancorr bench relay`: subscribes to `<prefix>/*/raw/*` and republishes every payload,
/// untouched, on `<key>/out` (one declared publisher per key), until SIGTERM or SIGINT.
pub fn relay(port: u16, prefix: &str) -> Result<()> {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    rt.block_on(async {
        let s = session(&[], Some(port)).await?;
        let sub = s
            .declare_subscriber(format!("{prefix}/*/raw/*"))
            .await
            .map_err(z)?;
        let mut pubs: HashMap<String, zenoh::pubsub::Publisher<'static>> = HashMap::new();
        let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())?;
        let stop = async move {
            tokio::select! { _ = term.recv() => {}, _ = tokio::signal::ctrl_c() => {} }
        };
        tokio::pin!(stop);
        loop {
            tokio::select! {
                biased;
                m = sub.recv_async() => {
                    let Ok(m) = m else { break };
                    let key = m.key_expr().as_str();
                    if !pubs.contains_key(key) {
                        let ke = s.declare_keyexpr(format!("{key}/out")).await.map_err(z)?;
                        let p = s.declare_publisher(ke).congestion_control(CongestionControl::Block).await.map_err(z)?;
                        pubs.insert(key.to_string(), p);
                    }
                    pubs[key].put(m.payload().clone()).await.map_err(z)?;
                }
                _ = &mut stop => break,
            }
        }
        s.close().await.map_err(z)?;
        Ok(())
    })
}

fn start_relay(port: u16, prefix: &str) -> Result<Service> {
    let dir = std::env::temp_dir().join(format!(
        "scancorr-bench-relay-{}-{port}",
        std::process::id()
    ));
    std::fs::create_dir_all(&dir)?;
    let child = Command::new(std::env::current_exe()?)
        .args([
            "bench",
            "relay",
            "--port",
            &port.to_string(),
            "--prefix",
            prefix,
        ])
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(dir.join("relay.log"))?)
        .spawn()
        .context("starting the relay")?;
    Ok(Service { child, dir })
}

fn messages(machine: &str, samples: &[Sample], batch: usize) -> Vec<(StreamId, Vec<u8>, i64)> {
    let mut b = Batcher::new(machine, batch);
    let mut out = vec![];
    for s in samples {
        if let Some(st) = b.push(s) {
            let (bytes, t0, _) = b.take(st).expect("full batch");
            out.push((st, bytes, t0));
        }
    }
    for st in StreamId::ALL {
        if let Some((bytes, t0, _)) = b.take(st) {
            out.push((st, bytes, t0));
        }
    }
    out
}

struct Run {
    samples: u64,
    seconds: f64,
    latencies_us: Vec<f64>,
}

/// What arrives on a path: how many items a message holds, and the time stamp that keys its
/// latency (if it closes an instant).
type Count = fn(&str, &[u8]) -> (u64, Option<i64>);

fn count_relayed(key: &str, b: &[u8]) -> (u64, Option<i64>) {
    let mut t = None;
    if key.ends_with("/probe/out") {
        // Packed (v1.3) or per-sample: the time of the batch's last sample.
        let _ = scancorr_core::wire::decode_with(StreamId::Probe, b, |_, s| t = Some(s.t_ns()));
    }
    (1, t)
}

fn count_points(_: &str, b: &[u8]) -> (u64, Option<i64>) {
    let batch = scancorr_proto::v1::CorrectedPointBatch::decode(b).unwrap_or_default();
    (
        batch.points.len() as u64,
        batch.points.last().map(|p| p.t_ns),
    )
}

/// Publishes `msgs` on `prefix/machine/raw/*` and counts `expect` items arriving on `out_key`;
/// `pace` spaces messages out (and turns latency recording on).
#[allow(clippy::too_many_arguments)]
async fn drive(
    s: &zenoh::Session,
    prefix: &str,
    machine: &str,
    msgs: &[(StreamId, Vec<u8>, i64)],
    out_key: &str,
    expect: u64,
    count: Count,
    pace: Option<Duration>,
) -> Result<Run> {
    let sent_at = Arc::new(Mutex::new(HashMap::<i64, Instant>::new()));
    let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel::<(u64, Instant, Option<f64>)>();
    let sub = {
        let sent_at = sent_at.clone();
        s.declare_subscriber(out_key)
            .callback(move |m| {
                let now = Instant::now();
                let (n, t) = count(m.key_expr().as_str(), &m.payload().to_bytes());
                let lat = t
                    .and_then(|t| sent_at.lock().expect("lock").remove(&t))
                    .map(|at| (now - at).as_secs_f64() * 1e6);
                let _ = tx.send((n, now, lat));
            })
            .await
            .map_err(z)?
    };
    let mut publishers = Vec::new();
    for st in StreamId::ALL {
        let ke = s
            .declare_keyexpr(format!("{prefix}/{machine}/raw/{}", st.name()))
            .await
            .map_err(z)?;
        publishers.push(
            s.declare_publisher(ke)
                .congestion_control(CongestionControl::Block)
                .await
                .map_err(z)?,
        );
    }
    let t0 = Instant::now();
    while !publishers[StreamId::Scale as usize]
        .matching_status()
        .await
        .map(|m| m.matching())
        .unwrap_or(false)
    {
        anyhow::ensure!(
            t0.elapsed() < Duration::from_secs(10),
            "no subscriber matched {prefix}/{machine}/raw/scale"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    tokio::time::sleep(Duration::from_millis(300)).await;
    let start = Instant::now();
    let sender = async {
        for (k, (st, bytes, t)) in msgs.iter().enumerate() {
            if let Some(p) = pace {
                let due = p * k as u32;
                if let Some(w) = due.checked_sub(start.elapsed()) {
                    tokio::time::sleep(w).await;
                }
                if *st == StreamId::Probe {
                    sent_at.lock().expect("lock").insert(*t, Instant::now());
                }
            }
            publishers[*st as usize]
                .put(bytes.clone())
                .await
                .map_err(z)?;
        }
        anyhow::Ok(())
    };
    let receiver = async {
        let (mut got, mut end, mut lat) = (0u64, start, vec![]);
        while got < expect {
            match tokio::time::timeout(Duration::from_secs(10), rx.recv()).await {
                Ok(Some((n, at, l))) => {
                    got += n;
                    end = at;
                    lat.extend(l);
                }
                _ => break,
            }
        }
        (got, end, lat)
    };
    let (sent, (got, end, latencies_us)) = tokio::join!(sender, receiver);
    sent?;
    drop(sub);
    anyhow::ensure!(got >= expect, "only {got} of {expect} arrived on {out_key}");
    Ok(Run {
        samples: msgs.len() as u64,
        seconds: (end - start).as_secs_f64(),
        latencies_us,
    })
}

async fn put_calibration(s: &zenoh::Session, machine: &str) -> Result<()> {
    query(
        s,
        format!("cmm/{machine}/calibration"),
        Some(synth::all_effects_calibration(machine).to_json()),
    )
    .await
    .map(|_| ())
}

fn expected_points(machine: &str, samples: &[Sample]) -> Result<u64> {
    let mut c = scancorr_core::Corrector::new(&synth::all_effects_calibration(machine))?;
    let mut o = scancorr_core::Output::default();
    c.push_all(samples.iter().cloned(), &mut o);
    Ok(o.points.len() as u64)
}

/// Runs the benchmark.
pub fn run(points: usize, json: bool) -> Result<()> {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    rt.block_on(async {
        let free = || -> Result<u16> { Ok(std::net::TcpListener::bind("127.0.0.1:0")?.local_addr()?.port()) };
        let (port, relay_port) = (free()?, free()?);
        let dir = std::env::temp_dir().join(format!("scancorr-bench-live-{}", std::process::id()));
        let _svc = start_scancorrd(&dir, port, "")?;
        let _relay = start_relay(relay_port, "bench")?;
        let s = session(&[port, relay_port], None).await?;
        let t0 = Instant::now();
        while query(&s, "cmm/bench/status".into(), None).await.is_err() {
            anyhow::ensure!(t0.elapsed() < Duration::from_secs(20), "scancorrd did not answer");
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        for m in ["bench", "bench2", "bench3"] {
            put_calibration(&s, m).await?;
        }
        // The calibration reads temperatures: they are part of the input (5 per 100 ms).
        let samples: Vec<Sample> = synth::ring_scan(points);
        let single = messages("bench", &samples, 1);
        let expected = expected_points("bench", &samples)?;
        // (a) bare relay, single-sample messages.
        let relay_run = drive(&s, "bench", "bench", &single, "bench/*/raw/*/out", single.len() as u64, count_relayed, None).await?;
        // (b) the service, the same messages.
        let svc_run = drive(&s, "cmm", "bench", &single, "cmm/bench/corrected/points", expected, count_points, None).await?;
        // (c) the service with 100-sample batches (a fresh machine: a new corrector).
        let batched = messages("bench2", &samples, 100);
        let batch_run = drive(&s, "cmm", "bench2", &batched, "cmm/bench2/corrected/points", expected, count_points, None).await?;
        // (d) latency at half the maximum load — half the slower path's maximum rate, so both
        // paths carry the same load and neither is saturated — single-sample messages.
        let lat_n = samples.len().min(60_000);
        let svc_rate = svc_run.samples as f64 / svc_run.seconds;
        let relay_rate = relay_run.samples as f64 / relay_run.seconds;
        let load = 0.5 * svc_rate.min(relay_rate);
        let pace = Duration::from_secs_f64(1.0 / load);
        let lat_msgs = messages("bench3", &samples[..lat_n], 1);
        let mut relay_lat = drive(&s, "bench", "bench3", &lat_msgs, "bench/*/raw/*/out", lat_msgs.len() as u64, count_relayed, Some(pace)).await?;
        let lat_expected = expected_points("bench3", &samples[..lat_n])?;
        let mut lat = drive(&s, "cmm", "bench3", &lat_msgs, "cmm/bench3/corrected/points", lat_expected, count_points, Some(pace)).await?;
        s.close().await.map_err(z)?;
        let (p50, p99) = (pct(&mut lat.latencies_us, 0.5), pct(&mut lat.latencies_us, 0.99));
        let (r50, r99) = (pct(&mut relay_lat.latencies_us, 0.5), pct(&mut relay_lat.latencies_us, 0.99));
        let batch_rate = samples.len() as f64 / batch_run.seconds;
        let batching = if std::env::var_os("SCANCORR_ZENOH_NO_BATCHING").is_some() { "off" } else { "on" };
        if json {
            outln!(
                "{}",
                serde_json::json!({
                    "bench": "live",
                    "messages": single.len(),
                    "zenoh_batching": batching,
                    "relay_samples_per_s": relay_rate,
                    "service_samples_per_s": svc_rate,
                    "ratio": svc_rate / relay_rate,
                    "service_batched_samples_per_s": batch_rate,
                    "latency_load_samples_per_s": load,
                    "latency_points": lat.latencies_us.len(),
                    "p50_latency_us": p50,
                    "p99_latency_us": p99,
                    "relay_p50_latency_us": r50,
                    "relay_p99_latency_us": r99,
                    "p99_added_latency_us": p99 - r99,
                    "targets": {"ratio": 0.7, "service_batched_samples_per_s": 1.0e6, "p99_added_latency_us": 1000.0},
                })
            )?;
        } else {
            outln!("live (loopback; relay and scancorrd each in their own process, publisher and subscriber in this one; zenoh batching {batching}):")?;
            outln!("  bare relay, single-sample messages   {relay_rate:>12.0} samples/s")?;
            outln!("  scancorrd,  single-sample messages   {svc_rate:>12.0} samples/s   ratio {:.2} (target ≥ 0.70)", svc_rate / relay_rate)?;
            outln!("  scancorrd,  100-sample batches       {batch_rate:>12.0} samples/s   (target ≥ 1e6)")?;
            outln!("  latency at half load ({load:.0} samples/s, half the slower path's maximum):")?;
            outln!("    relay      p50 {r50:>7.0} µs   p99 {r99:>7.0} µs")?;
            outln!("    scancorrd  p50 {p50:>7.0} µs   p99 {p99:>7.0} µs   added p99 {:.0} µs (target ≤ 1000 µs)", p99 - r99)?;
        }
        Ok(())
    })
}
