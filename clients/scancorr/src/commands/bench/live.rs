//! `scancorr bench live`: scancorrd against a bare relay (`scancorr bench relay`) that does the
//! same bus work without the correction — the same declarations, the same output traffic (one
//! point message per instant) — on loopback, single-sample messages. Relay, service and the
//! load generator (this process, one session per path) each run as their own process; the
//! cores of this machine are still shared by all three.
//!
//! After a warm-up, rounds alternate (relay first in even rounds, the service in odd ones), so
//! neither path always runs on a cooler or hotter machine. Throughput: every message sent as
//! fast as the path takes it (congestion control Block), until every point has arrived.
//! Latency: paced on the monotonic clock (sleeps of at most 50 µs, no 1-ms timer) at half the
//! relay's median throughput; the
//! latency each path adds is measured inside it, from a message's arrival to the publication
//! of the point it completed (`output.added_latency_us` on its status), not as a difference
//! of two separate percentiles; the end-to-end latency is printed beside it.

use super::harness::{pct, query, session, start_scancorrd, z};
use crate::shared::synth;
use anyhow::Result;
use scancorr_core::sample::{Sample, StreamId};
use scancorr_core::wire::Batcher;
use scancorr_proto::Message;
use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use zenoh::qos::CongestionControl;
use zenoh::Wait;

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
    /// Publication of an instant's probe message → arrival of its point here, µs.
    latencies_us: Vec<f64>,
}

/// Points in a point batch, and the time stamp of the last (which keys its latency).
fn count_points(b: &[u8]) -> (u64, Option<i64>) {
    let batch = scancorr_proto::v1::CorrectedPointBatch::decode(b).unwrap_or_default();
    let last = batch.points.last().map(|p| p.t_ns);
    (
        batch.len() as u64,
        last.or_else(|| {
            batch
                .columns
                .iter()
                .rev()
                .find_map(|c| c.t_ns.last().copied())
        }),
    )
}

/// Waits until `deadline` on this thread, in sleeps of at most 50 µs on the monotonic clock
/// (no spinning: the pacer must not take a core from the paths it measures; tokio's timer,
/// with its 1 ms resolution, is too coarse). Messages due within one sleep go out together,
/// as a controller's would.
fn pace_until(deadline: Instant) {
    loop {
        let now = Instant::now();
        if now >= deadline {
            return;
        }
        std::thread::sleep((deadline - now).min(Duration::from_micros(50)));
    }
}

/// Publishes `msgs` on `cmm/<machine>/raw/*` through `s` (connected to one path only) and
/// waits for `expect` points on `cmm/<machine>/corrected/points`. `pace`: one message per
/// interval, from a high-resolution pacer on its own thread (and latency recorded); none: as
/// fast as the path takes them (congestion control Block).
async fn drive(
    s: &zenoh::Session,
    machine: &str,
    msgs: Vec<(StreamId, Vec<u8>, i64)>,
    expect: u64,
    pace: Option<Duration>,
) -> Result<Run> {
    let sent_at = Arc::new(Mutex::new(HashMap::<i64, Instant>::new()));
    let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel::<(u64, Instant, Option<f64>)>();
    let sub = {
        let sent_at = sent_at.clone();
        s.declare_subscriber(scancorr_proto::Stream::Points.key("cmm", machine))
            .callback(move |m| {
                let now = Instant::now();
                let (n, t) = count_points(&m.payload().to_bytes());
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
            .declare_keyexpr(format!("cmm/{machine}/raw/{}", st.name()))
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
    while !publishers[StreamId::Probe as usize]
        .matching_status()
        .await
        .map(|m| m.matching())
        .unwrap_or(false)
    {
        anyhow::ensure!(
            t0.elapsed() < Duration::from_secs(10),
            "no subscriber matched cmm/{machine}/raw/probe"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    tokio::time::sleep(Duration::from_millis(300)).await;
    let n = msgs.len() as u64;
    let start = Instant::now();
    let sender = {
        let sent_at = sent_at.clone();
        tokio::task::spawn_blocking(move || -> Result<()> {
            for (k, (st, bytes, t)) in msgs.into_iter().enumerate() {
                if let Some(p) = pace {
                    pace_until(start + p * k as u32);
                    if st == StreamId::Probe {
                        sent_at.lock().expect("lock").insert(t, Instant::now());
                    }
                }
                publishers[st as usize].put(bytes).wait().map_err(z)?;
            }
            Ok(())
        })
    };
    let (mut got, mut end, mut latencies_us) = (0u64, start, vec![]);
    while got < expect {
        match tokio::time::timeout(Duration::from_secs(10), rx.recv()).await {
            Ok(Some((n, at, l))) => {
                got += n;
                end = at;
                latencies_us.extend(l);
            }
            _ => break,
        }
    }
    sender.await??;
    drop(sub);
    anyhow::ensure!(
        got >= expect,
        "only {got} of {expect} points arrived for {machine}"
    );
    Ok(Run {
        samples: n,
        seconds: (end - start).as_secs_f64(),
        latencies_us,
    })
}

async fn put_calibration(s: &zenoh::Session, machine: &str) -> Result<()> {
    query(
        s,
        scancorr_proto::calibration_write_key("cmm", machine),
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

/// The latency a path says it adds for `machine` (measured inside it), µs: (p50, p99), and
/// the width of its histogram's buckets, % (each percentile is the upper edge of its bucket).
async fn added_latency(s: &zenoh::Session, machine: &str) -> Result<(f64, f64, Option<f64>)> {
    let v: serde_json::Value =
        serde_json::from_str(&query(s, format!("cmm/{machine}/status"), None).await?)?;
    let l = &v["output"]["added_latency_us"];
    match (l["p50"].as_f64(), l["p99"].as_f64()) {
        (Some(a), Some(b)) => Ok((a, b, l["bucket_width_pct"].as_f64())),
        _ => anyhow::bail!("{machine}: no added latency in the status: {v}"),
    }
}

/// Min, median and max (JSON).
fn spread(v: &[f64]) -> serde_json::Value {
    let mut v = v.to_vec();
    v.sort_by(|a, b| a.total_cmp(b));
    serde_json::json!({"min": v[0], "median": v[v.len() / 2], "max": v[v.len() - 1]})
}

fn med(v: &[f64]) -> f64 {
    let mut v = v.to_vec();
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

/// The two paths under test, each reached through its own session.
struct Paths {
    relay: zenoh::Session,
    service: zenoh::Session,
}

impl Paths {
    /// Runs `machine`'s messages through the relay and the service, in the order `relay_first`
    /// says (alternated between rounds): (relay, service).
    #[allow(clippy::too_many_arguments)]
    async fn round(
        &self,
        machine: &str,
        samples: &[Sample],
        expected: u64,
        probes: u64,
        relay_first: bool,
        pace: Option<Duration>,
    ) -> Result<(Run, Run)> {
        let msgs = messages(machine, samples, 1);
        let (a, b) = if relay_first {
            let a = drive(&self.relay, machine, msgs.clone(), probes, pace).await?;
            (
                a,
                drive(&self.service, machine, msgs, expected, pace).await?,
            )
        } else {
            let b = drive(&self.service, machine, msgs.clone(), expected, pace).await?;
            (drive(&self.relay, machine, msgs, probes, pace).await?, b)
        };
        Ok((a, b))
    }
}

/// Runs the benchmark: a warm-up, then `rounds` alternating rounds of throughput (relay first
/// in even rounds, the service first in odd ones), then `rounds` of latency at half the
/// relay's median throughput.
pub fn run(points: usize, rounds: usize, json: bool) -> Result<()> {
    let rounds = rounds.max(1);
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    rt.block_on(async {
        let free = || -> Result<u16> { Ok(std::net::TcpListener::bind("127.0.0.1:0")?.local_addr()?.port()) };
        let (port, relay_port) = (free()?, free()?);
        let dir = crate::shared::output::private_dir("scancorr-bench-live")?;
        let _svc = start_scancorrd(&dir, port, "")?;
        let _relay = super::relay::start(relay_port, "cmm", &super::relay::Options::default())?;
        let paths = Paths {
            relay: session(&[relay_port], None).await?,
            service: session(&[port], None).await?,
        };
        let t0 = Instant::now();
        while query(&paths.service, "cmm/warm-up/status".into(), None).await.is_err() {
            anyhow::ensure!(t0.elapsed() < Duration::from_secs(20), "scancorrd did not answer");
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        let names = |k: &'static str| (0..rounds).map(move |r| format!("{k}{r}"));
        let all: Vec<String> = std::iter::once("warm-up".to_string()).chain(names("t")).chain(names("l")).collect();
        for m in &all {
            put_calibration(&paths.service, m).await?;
        }
        // The calibration reads temperatures: they are part of the input (5 per 100 ms).
        let samples: Vec<Sample> = synth::ring_scan(points);
        let expected = expected_points("x", &samples)?;
        let probes = samples.iter().filter(|s| matches!(s, Sample::Probe(_))).count() as u64;
        let messages_n = samples.len();
        eprintln!("bench live: warm-up, {rounds} throughput rounds and {rounds} latency rounds of {messages_n} single-sample messages per path …");
        // Warm-up: routes, allocators, the service's first machine.
        let warm = &samples[..samples.len() / 4];
        let (w_exp, w_probes) = (expected_points("x", warm)?, warm.iter().filter(|s| matches!(s, Sample::Probe(_))).count() as u64);
        paths.round("warm-up", warm, w_exp, w_probes, true, None).await?;
        let (mut relay_rate, mut svc_rate, mut ratio) = (vec![], vec![], vec![]);
        for (r, m) in names("t").enumerate() {
            let (a, b) = paths.round(&m, &samples, expected, probes, r % 2 == 0, None).await?;
            let (ra, rb) = (a.samples as f64 / a.seconds, b.samples as f64 / b.seconds);
            eprintln!("  round {r}: relay {ra:.0}, service {rb:.0} samples/s, ratio {:.2}", rb / ra);
            relay_rate.push(ra);
            svc_rate.push(rb);
            ratio.push(rb / ra);
        }
        // Latency at half the relay's throughput (the same load on both paths).
        let load = 0.5 * med(&relay_rate);
        let pace = Duration::from_secs_f64(1.0 / load);
        let (mut added, mut relay_added) = ((vec![], vec![]), (vec![], vec![]));
        let (mut e2e, mut relay_e2e) = ((vec![], vec![]), (vec![], vec![]));
        let mut width_pct = None;
        for (r, m) in names("l").enumerate() {
            let (mut a, mut b) = paths.round(&m, &samples, expected, probes, r % 2 == 0, Some(pace)).await?;
            let (s50, s99, w) = added_latency(&paths.service, &m).await?;
            let (r50, r99, _) = added_latency(&paths.relay, &m).await?;
            width_pct = width_pct.or(w);
            eprintln!("  latency round {r}: added p99 service {s99:.0} µs, relay {r99:.0} µs");
            added.0.push(s50);
            added.1.push(s99);
            relay_added.0.push(r50);
            relay_added.1.push(r99);
            e2e.0.push(pct(&mut b.latencies_us, 0.5));
            e2e.1.push(pct(&mut b.latencies_us, 0.99));
            relay_e2e.0.push(pct(&mut a.latencies_us, 0.5));
            relay_e2e.1.push(pct(&mut a.latencies_us, 0.99));
        }
        paths.relay.close().await.map_err(z)?;
        paths.service.close().await.map_err(z)?;
        let batching = if std::env::var_os("SCANCORR_ZENOH_NO_BATCHING").is_some() { "off" } else { "on" };
        if json {
            outln!(
                "{}",
                serde_json::json!({
                    "bench": "live",
                    "rounds": rounds,
                    "messages": messages_n,
                    "zenoh_batching": batching,
                    "relay_samples_per_s": spread(&relay_rate),
                    "service_samples_per_s": spread(&svc_rate),
                    "ratio": spread(&ratio),
                    "latency_load_samples_per_s": load,
                    "service_added_latency_us": {"p50": spread(&added.0), "p99": spread(&added.1)},
                    "relay_added_latency_us": {"p50": spread(&relay_added.0), "p99": spread(&relay_added.1)},
                    "added_latency_bucket_width_pct": width_pct,
                    "service_end_to_end_latency_us": {"p50": spread(&e2e.0), "p99": spread(&e2e.1)},
                    "relay_end_to_end_latency_us": {"p50": spread(&relay_e2e.0), "p99": spread(&relay_e2e.1)},
                    "targets": {"ratio": 0.9, "service_added_p99_us": 1000.0},
                })
            )?;
        } else {
            let f = |v: &[f64], d: usize| { let s = spread(v); format!("{:.d$} ({:.d$}–{:.d$})", s["median"].as_f64().unwrap_or(0.0), s["min"].as_f64().unwrap_or(0.0), s["max"].as_f64().unwrap_or(0.0)) };
            outln!("live, loopback: relay and scancorrd each in their own process, the same declarations and output traffic; {messages_n} single-sample messages per round; zenoh batching {batching}")?;
            outln!("  median (min–max) of {rounds} alternating rounds after a warm-up:")?;
            outln!("  relay      {} samples/s", f(&relay_rate, 0))?;
            outln!("  scancorrd  {} samples/s", f(&svc_rate, 0))?;
            outln!("  ratio      {}   (target ≥ 0.90)", f(&ratio, 2))?;
            outln!("  at half the relay's throughput ({load:.0} samples/s, paced in sleeps of ≤ 50 µs):")?;
            outln!("  added inside (arrival → points published): scancorrd p50 {} µs, p99 {} µs (target ≤ 1000); relay p50 {} µs, p99 {} µs", f(&added.0, 0), f(&added.1, 0), f(&relay_added.0, 0), f(&relay_added.1, 0))?;
            if let Some(w) = width_pct {
                outln!("    (each the upper edge of a histogram bucket {w:.1} % wide: the true value lies between it ÷ {:.3} and it)", 1.0 + w / 100.0)?;
            }
            outln!("  end to end (probe published → point here): scancorrd p50 {} µs, p99 {} µs; relay p50 {} µs, p99 {} µs", f(&e2e.0, 0), f(&e2e.1, 0), f(&relay_e2e.0, 0), f(&relay_e2e.1, 0))?;
        }
        Ok(())
    })
}
