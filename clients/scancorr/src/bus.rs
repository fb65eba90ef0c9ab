//! The bus commands: `calib put|get|history|status`, `replay`, `record`, `tail`.
//! Each opens a zenoh session (peer mode, connecting to `--connect`), does its job and closes.

use anyhow::{bail, Context, Result};
use scancorr_bag::{BagHeader, BagReader, BagWriter, Stream};
use scancorr_proto::Message;
use std::path::Path;
use std::time::{Duration, Instant};
use zenoh::qos::CongestionControl;

/// Where the bus is.
#[derive(clap::Args, Clone, Debug)]
pub struct Bus {
    /// Zenoh endpoint of scancorrd or a router.
    #[arg(long, default_value = "tcp/127.0.0.1:7447")]
    pub connect: Vec<String>,
    /// Key-expression prefix.
    #[arg(long, default_value = scancorr_proto::DEFAULT_PREFIX)]
    pub prefix: String,
}

fn rt() -> Result<tokio::runtime::Runtime> {
    Ok(tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?)
}

async fn open(bus: &Bus) -> Result<zenoh::Session> {
    let cfg = scancorrd::config::zenoh_config("peer", &[], &bus.connect, false)?;
    zenoh::open(cfg)
        .await
        .map_err(|e| anyhow::anyhow!("opening a zenoh session to {:?}: {e}", bus.connect))
}

/// One query to the calibration/status queryable; returns the reply text.
async fn ask(
    session: &zenoh::Session,
    selector: String,
    payload: Option<Vec<u8>>,
) -> Result<String> {
    let mut last_err = None;
    // The route to the queryable may take a moment after connecting.
    for _ in 0..20 {
        let mut g = session
            .get(selector.as_str())
            .timeout(Duration::from_secs(5));
        if let Some(p) = &payload {
            g = g.payload(p.clone());
        }
        let replies = g.await.map_err(|e| anyhow::anyhow!("{e}"))?;
        if let Ok(r) = replies.recv_async().await {
            return match r.into_result() {
                Ok(s) => Ok(s
                    .payload()
                    .try_to_string()
                    .map(|s| s.to_string())
                    .unwrap_or_default()),
                Err(e) => bail!(
                    "{}",
                    e.payload()
                        .try_to_string()
                        .map(|s| s.to_string())
                        .unwrap_or_else(|_| "error".into())
                ),
            };
        }
        last_err = Some(());
        tokio::time::sleep(Duration::from_millis(250)).await;
    }
    let _ = last_err;
    bail!("no scancorrd answered on `{selector}` (is it running and reachable?)")
}

/// `calib put`.
pub fn calib_put(bus: &Bus, machine: &str, file: &Path) -> Result<String> {
    let text = std::fs::read(file).with_context(|| format!("reading {}", file.display()))?;
    rt()?.block_on(async {
        let s = open(bus).await?;
        let r = ask(
            &s,
            scancorr_proto::calibration_key(&bus.prefix, machine),
            Some(text),
        )
        .await;
        s.close().await.ok();
        r
    })
}

/// `calib get` / `calib history` / `status`.
pub fn query(bus: &Bus, selector: String) -> Result<String> {
    rt()?.block_on(async {
        let s = open(bus).await?;
        let r = ask(&s, selector, None).await;
        s.close().await.ok();
        r
    })
}

/// `replay`: bag → bus, paced by sample time (`rate` × real time; None = as fast as possible).
pub fn replay(bus: &Bus, bag: &Path, rate: Option<f64>, looping: bool) -> Result<u64> {
    let reader = BagReader::open(bag).with_context(|| format!("reading bag {}", bag.display()))?;
    rt()?.block_on(async {
        let s = open(bus).await?;
        let mut pubs = std::collections::BTreeMap::new();
        for ch in reader.channels() {
            if Stream::RAW.contains(&ch.stream) {
                let key = ch.stream.key(&bus.prefix, &ch.machine);
                let p = s
                    .declare_publisher(key.clone())
                    .congestion_control(CongestionControl::Block)
                    .await
                    .map_err(|e| anyhow::anyhow!("{e}"))?;
                pubs.insert(ch.topic.clone(), p);
            }
        }
        // Wait until someone listens (the route is set up), at most 10 s.
        let t0 = Instant::now();
        loop {
            let mut all = true;
            for p in pubs.values() {
                all &= p
                    .matching_status()
                    .await
                    .map(|m| m.matching())
                    .unwrap_or(false);
            }
            if all || t0.elapsed() > Duration::from_secs(10) {
                break;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        let mut sent = 0u64;
        loop {
            let start = Instant::now();
            let mut first: Option<u64> = None;
            for m in reader.messages()? {
                let m = m?;
                let Some(p) = pubs.get(&*m.topic) else {
                    continue;
                };
                if let Some(r) = rate {
                    let f = *first.get_or_insert(m.publish_time);
                    let due = Duration::from_secs_f64(
                        (m.publish_time.saturating_sub(f)) as f64 * 1e-9 / r,
                    );
                    if let Some(wait) = due.checked_sub(start.elapsed()) {
                        tokio::time::sleep(wait).await;
                    }
                }
                p.put(m.data).await.map_err(|e| anyhow::anyhow!("{e}"))?;
                sent += 1;
            }
            if !looping {
                break;
            }
        }
        // Let the last messages leave before closing.
        tokio::time::sleep(Duration::from_millis(300)).await;
        s.close().await.ok();
        Ok(sent)
    })
}

/// `record`: bus → bag until `seconds` pass, or `idle` seconds without a message after the
/// first one, or Ctrl-C.
pub fn record(
    bus: &Bus,
    keys: &str,
    out: &Path,
    seconds: Option<f64>,
    idle: Option<f64>,
) -> Result<u64> {
    rt()?.block_on(async {
        let s = open(bus).await?;
        let sub = s.declare_subscriber(keys).await.map_err(|e| anyhow::anyhow!("{e}"))?;
        let mut w = BagWriter::create(out, BagHeader { compression: scancorr_bag::Compression::Lz4, ..BagHeader::default() })?;
        let t0 = Instant::now();
        let mut last = None::<Instant>;
        let mut n = 0u64;
        let mut last_flush = Instant::now();
        eprintln!("recording `{keys}` → {}", out.display());
        loop {
            let wait = Duration::from_millis(200);
            tokio::select! {
                r = sub.recv_async() => {
                    let Ok(sample) = r else { break };
                    let key = sample.key_expr().as_str();
                    let Some((machine, stream)) = Stream::parse_key(&bus.prefix, key) else { continue };
                    let bytes = sample.payload().to_bytes();
                    let now = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_nanos() as u64).unwrap_or(0);
                    let publish = scancorr_bag::peek(stream, &bytes).and_then(|p| p.first_t_ns).map(|t| t.max(0) as u64).unwrap_or(now);
                    w.write(stream, machine, &bus.prefix, now, publish, &bytes)?;
                    n += 1;
                    last = Some(Instant::now());
                    if last_flush.elapsed() > Duration::from_secs(1) {
                        w.flush()?;
                        last_flush = Instant::now();
                    }
                }
                _ = tokio::time::sleep(wait) => {}
                _ = tokio::signal::ctrl_c() => break,
            }
            if seconds.is_some_and(|s| t0.elapsed().as_secs_f64() > s) {
                break;
            }
            if let (Some(i), Some(l)) = (idle, last) {
                if l.elapsed().as_secs_f64() > i {
                    break;
                }
            }
        }
        w.finish()?;
        s.close().await.ok();
        Ok(n)
    })
}

/// `tail`: prints points and alarms as they arrive.
pub fn tail(bus: &Bus, machine: &str, seconds: Option<f64>) -> Result<()> {
    rt()?.block_on(async {
        let s = open(bus).await?;
        let sub = s.declare_subscriber(format!("{}/{machine}/**", bus.prefix)).await.map_err(|e| anyhow::anyhow!("{e}"))?;
        let t0 = Instant::now();
        let mut last_seq: Option<u64> = None;
        loop {
            tokio::select! {
                r = sub.recv_async() => {
                    let Ok(sample) = r else { break };
                    let Some((m, stream)) = Stream::parse_key(&bus.prefix, sample.key_expr().as_str()) else { continue };
                    let bytes = sample.payload().to_bytes();
                    match stream {
                        Stream::Points => {
                            let Ok(b) = scancorr_proto::v1::CorrectedPointBatch::decode(&*bytes) else { continue };
                            for p in &b.points {
                                if let Some(l) = last_seq { if p.seq != l + 1 { println!("!! {m}: missed {} point(s)", p.seq.saturating_sub(l + 1)); } }
                                last_seq = Some(p.seq);
                            }
                            if let Some(p) = b.points.last() {
                                let s = p.surface.clone().unwrap_or_default();
                                println!("{m} #{:<9} t={:.3}s  surface ({:9.4} {:9.4} {:9.4}) mm  v{} {}{}", p.seq, p.t_ns as f64 * 1e-9, s.x, s.y, s.z, p.calibration_version, if p.estimator_valid { "" } else { "FLAGGED " }, if b.points.len() > 1 { format!("(+{} in batch)", b.points.len() - 1) } else { String::new() });
                            }
                        }
                        Stream::Alarms => {
                            if let Ok(a) = scancorr_proto::v1::EstimatorAlarm::decode(&*bytes) {
                                println!("{m} ALARM {} axis {:?} t={:.3}s estimated {:.1} measured {:.1} mm/s² (threshold {:.0})", if a.raised { "RAISED" } else { "cleared" }, a.axis(), a.t_ns as f64 * 1e-9, a.estimated_accel, a.measured_accel, a.threshold);
                            }
                        }
                        _ => {}
                    }
                }
                _ = tokio::time::sleep(Duration::from_millis(200)) => {}
                _ = tokio::signal::ctrl_c() => break,
            }
            if seconds.is_some_and(|s| t0.elapsed().as_secs_f64() > s) {
                break;
            }
        }
        s.close().await.ok();
        Ok(())
    })
}
