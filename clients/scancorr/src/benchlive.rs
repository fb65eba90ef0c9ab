//! `scancorr bench live`: a bare zenoh relay against scancorrd, same publisher and subscriber,
//! in one process on loopback (this machine's cores are shared by all parts, so the figures
//! are a lower bound of a dedicated deployment).

use crate::synth;
use anyhow::Result;
use scancorr_core::sample::{Sample, StreamId};
use scancorr_core::wire::Batcher;
use scancorr_proto::Message;
use std::time::{Duration, Instant};
use zenoh::qos::CongestionControl;

async fn session(ports: &[u16], listen: Option<u16>) -> Result<zenoh::Session> {
    let connect: Vec<String> = ports.iter().map(|p| format!("tcp/127.0.0.1:{p}")).collect();
    let listen: Vec<String> = listen
        .iter()
        .map(|p| format!("tcp/127.0.0.1:{p}"))
        .collect();
    let cfg = scancorrd::config::zenoh_config("peer", &listen, &connect, false)?;
    zenoh::open(cfg).await.map_err(|e| anyhow::anyhow!("{e}"))
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

/// Publishes `msgs` on `prefix/machine/raw/*` and counts `expect` items arriving on `out_key`
/// (`count` says how many items a message holds); `pace` spaces messages out.
async fn drive(
    pubs: &zenoh::Session,
    subs: &zenoh::Session,
    prefix: &str,
    machine: &str,
    msgs: &[(StreamId, Vec<u8>, i64)],
    out_key: &str,
    expect: u64,
    count: fn(&[u8]) -> (u64, Option<u64>),
    pace: Option<Duration>,
) -> Result<Run> {
    let sub = subs
        .declare_subscriber(out_key)
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let mut publishers = std::collections::BTreeMap::new();
    for s in StreamId::ALL {
        let key = format!("{prefix}/{machine}/raw/{}", s.name());
        let p = pubs
            .declare_publisher(key)
            .congestion_control(CongestionControl::Block)
            .await
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        publishers.insert(s as usize, p);
    }
    let t0 = Instant::now();
    while !publishers[&(StreamId::Scale as usize)]
        .matching_status()
        .await
        .map(|m| m.matching())
        .unwrap_or(false)
    {
        anyhow::ensure!(
            t0.elapsed() < Duration::from_secs(10),
            "no subscriber matched"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    tokio::time::sleep(Duration::from_millis(200)).await;
    let n_samples: u64 = msgs.len() as u64;
    let sent_at = std::sync::Arc::new(std::sync::Mutex::new(std::collections::HashMap::<
        u64,
        Instant,
    >::new()));
    let recv = {
        let sent_at = sent_at.clone();
        tokio::spawn(async move {
            let mut got = 0u64;
            let mut lat = vec![];
            while got < expect {
                match tokio::time::timeout(Duration::from_secs(10), sub.recv_async()).await {
                    Ok(Ok(s)) => {
                        let (n, key) = count(&s.payload().to_bytes());
                        got += n;
                        if let Some(k) = key {
                            if let Some(t) = sent_at.lock().expect("lock").remove(&k) {
                                lat.push(t.elapsed().as_secs_f64() * 1e6);
                            }
                        }
                    }
                    _ => break,
                }
            }
            (got, Instant::now(), lat)
        })
    };
    let start = Instant::now();
    for (k, (s, bytes, t)) in msgs.iter().enumerate() {
        if let Some(p) = pace {
            let due = p * k as u32;
            if let Some(w) = due.checked_sub(start.elapsed()) {
                tokio::time::sleep(w).await;
            }
            if *s == StreamId::Probe {
                sent_at
                    .lock()
                    .expect("lock")
                    .insert(*t as u64, Instant::now());
            }
        }
        publishers[&(*s as usize)]
            .put(bytes.clone())
            .await
            .map_err(|e| anyhow::anyhow!("{e}"))?;
    }
    let (got, end, latencies_us) = recv.await?;
    anyhow::ensure!(got >= expect, "only {got} of {expect} arrived");
    Ok(Run {
        samples: n_samples,
        seconds: (end - start).as_secs_f64(),
        latencies_us,
    })
}

fn pct(v: &mut [f64], p: f64) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    v.sort_by(|a, b| a.total_cmp(b));
    v[((v.len() as f64 - 1.0) * p).round() as usize]
}

/// Runs the benchmark.
pub fn run(points: usize, json: bool) -> Result<()> {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    rt.block_on(async {
        let port = std::net::TcpListener::bind("127.0.0.1:0")?.local_addr()?.port();
        let dir = std::env::temp_dir().join(format!("scancorr-bench-live-{}", std::process::id()));
        let cfg = scancorrd::Config { listen: vec![format!("tcp/127.0.0.1:{port}")], data_dir: dir.join("data"), ..Default::default() };
        let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
        let service = tokio::spawn(scancorrd::run(cfg, async move {
            let _ = stop_rx.await;
        }));
        tokio::time::sleep(Duration::from_millis(300)).await;
        // The relay: a peer of its own, like the service: subscribe → republish the same bytes.
        let relay_port = std::net::TcpListener::bind("127.0.0.1:0")?.local_addr()?.port();
        let relay = session(&[], Some(relay_port)).await?;
        let pubs = session(&[port, relay_port], None).await?;
        let subs = session(&[port, relay_port], None).await?;
        let rsub = relay.declare_subscriber("bench/*/raw/**").await.map_err(|e| anyhow::anyhow!("{e}"))?;
        let rpub = relay.declare_publisher("bench/out").congestion_control(CongestionControl::Block).await.map_err(|e| anyhow::anyhow!("{e}"))?;
        let relay_task = tokio::spawn(async move {
            while let Ok(s) = rsub.recv_async().await {
                let _ = rpub.put(s.payload().clone()).await;
            }
        });
        // Calibration for the bench machine.
        let cal = synth::all_effects_calibration("bench");
        let replies = pubs.get("cmm/bench/calibration").payload(cal.to_json()).timeout(Duration::from_secs(5)).await.map_err(|e| anyhow::anyhow!("{e}"))?;
        replies.recv_async().await.map_err(|e| anyhow::anyhow!("no calibration reply: {e}"))?.into_result().map_err(|e| anyhow::anyhow!("{:?}", e.payload().try_to_string()))?;
        let samples: Vec<Sample> = synth::ring_scan(points).into_iter().filter(|s| !matches!(s, Sample::Temperature(_))).collect();
        // The calibration reads temperatures: give them (one per 100 ms is part of the input).
        let with_temps: Vec<Sample> = synth::ring_scan(points);
        let single = messages("bench", &with_temps, 1);
        let expected_points = {
            let mut c = scancorr_core::Corrector::new(&cal)?;
            let mut o = scancorr_core::Output::default();
            c.push_all(with_temps.iter().cloned(), &mut o);
            o.points.len() as u64
        };
        let count_points: fn(&[u8]) -> (u64, Option<u64>) = |b| {
            let batch = scancorr_proto::v1::CorrectedPointBatch::decode(b).unwrap_or_default();
            (batch.points.len() as u64, batch.points.last().map(|p| p.t_ns as u64))
        };
        let count_msgs: fn(&[u8]) -> (u64, Option<u64>) = |_| (1, None);
        // (a) bare relay, single-sample messages.
        let relay_run = drive(&pubs, &subs, "bench", "bench", &single, "bench/out", single.len() as u64, count_msgs, None).await?;
        // (b) the service, the same messages.
        let svc_run = drive(&pubs, &subs, "cmm", "bench", &single, "cmm/bench/corrected/points", expected_points, count_points, None).await?;
        // (c) the service with 100-sample batches (a fresh machine id: a new corrector).
        let replies = pubs.get("cmm/bench2/calibration").payload(synth::all_effects_calibration("bench2").to_json()).timeout(Duration::from_secs(5)).await.map_err(|e| anyhow::anyhow!("{e}"))?;
        replies.recv_async().await.map_err(|e| anyhow::anyhow!("no calibration reply: {e}"))?;
        let batched = messages("bench2", &with_temps, 100);
        let batch_run = drive(&pubs, &subs, "cmm", "bench2", &batched, "cmm/bench2/corrected/points", expected_points, count_points, None).await?;
        let batch_samples = with_temps.len() as f64;
        // (d) latency at half the service's maximum rate (single-sample messages).
        let replies = pubs.get("cmm/bench3/calibration").payload(synth::all_effects_calibration("bench3").to_json()).timeout(Duration::from_secs(5)).await.map_err(|e| anyhow::anyhow!("{e}"))?;
        replies.recv_async().await.map_err(|e| anyhow::anyhow!("no calibration reply: {e}"))?;
        let lat_n = (with_temps.len()).min(60_000);
        let lat_msgs = messages("bench3", &with_temps[..lat_n], 1);
        let svc_rate = svc_run.samples as f64 / svc_run.seconds;
        let pace = Duration::from_secs_f64(2.0 / svc_rate);
        let lat_expected = {
            let mut c = scancorr_core::Corrector::new(&synth::all_effects_calibration("bench3"))?;
            let mut o = scancorr_core::Output::default();
            c.push_all(with_temps[..lat_n].iter().cloned(), &mut o);
            o.points.len() as u64
        };
        let mut lat = drive(&pubs, &subs, "cmm", "bench3", &lat_msgs, "cmm/bench3/corrected/points", lat_expected, count_points, Some(pace)).await?;
        let _ = samples;
        relay_task.abort();
        let _ = stop_tx.send(());
        let _ = service.await;
        std::fs::remove_dir_all(&dir).ok();
        let relay_rate = relay_run.samples as f64 / relay_run.seconds;
        let (p50, p99) = (pct(&mut lat.latencies_us, 0.5), pct(&mut lat.latencies_us, 0.99));
        let batch_rate = batch_samples / batch_run.seconds;
        if json {
            println!(
                "{}",
                serde_json::json!({
                    "bench": "live",
                    "messages": single.len(),
                    "relay_samples_per_s": relay_rate,
                    "service_samples_per_s": svc_rate,
                    "ratio": svc_rate / relay_rate,
                    "service_batched_samples_per_s": batch_rate,
                    "latency_load_samples_per_s": 0.5 * svc_rate,
                    "latency_points": lat.latencies_us.len(),
                    "p50_latency_us": p50,
                    "p99_latency_us": p99,
                    "targets": {"ratio": 0.7, "service_batched_samples_per_s": 1.0e6, "p99_latency_us": 1000.0},
                })
            );
        } else {
            println!("live (one process, loopback, 2 cores shared by publisher, relay/service and subscriber):");
            println!("  bare relay, single-sample messages   {relay_rate:>12.0} samples/s");
            println!("  scancorrd,  single-sample messages   {svc_rate:>12.0} samples/s   ratio {:.2} (target ≥ 0.70)", svc_rate / relay_rate);
            println!("  scancorrd,  100-sample batches       {batch_rate:>12.0} samples/s   (target ≥ 1e6)");
            println!("  latency at half load ({:.0} samples/s): p50 {p50:.0} µs, p99 {p99:.0} µs   (target p99 ≤ 1000 µs)", 0.5 * svc_rate);
        }
        Ok(())
    })
}
