//! `scancorr bench fleet`: one scancorrd process serving many machines at 1 kHz each, in real
//! time, on loopback. This process plays every machine controller (pre-encoded batches, paced
//! by sample time; `--links` spreads them over several zenoh connections, each published from
//! its own thread) and one consumer of every machine's points; the service runs as its own
//! process so its memory and CPU time are its own.
//!
//! Figures: points delivered per second against the fleet's rate, `seq` gaps, end-to-end
//! latency (from the moment a batch period ends and the controller publishes it to the
//! moment its corrected points arrive), the service's resident memory per machine and the
//! core's own state per machine (from the status queryable), and CPU time of both processes.

use super::harness::{
    cpu_seconds, memory, pct, query, scancorrd_path, start_scancorrd, start_scancorrd_with,
    task_switches, Service,
};
use crate::shared::synth;
use anyhow::{bail, Context, Result};
use scancorr_core::sample::{Sample, StreamId};
use scancorr_core::wire::Batcher;
use std::fmt::Write;
use std::path::Path;
use std::process::{Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use zenoh::qos::CongestionControl;

/// Fleet benchmark parameters.
#[derive(Debug, Clone)]
pub struct Params {
    /// Machines served at once.
    pub machines: usize,
    /// Simulated seconds each machine scans (at 1 kHz).
    pub seconds: f64,
    /// Controller batch period: each stream's samples of one period go in one message, ms.
    pub batch_ms: u64,
    /// The service's `max_pending_samples` (per stream per machine).
    pub max_pending: usize,
    /// Wall-clock pace as a fraction of real time (1 = real time; 0.25 publishes each period
    /// four times later, so a machine too small to generate the full load can still measure
    /// the state of a full fleet: the samples, batches and per-machine state are the same).
    pub pace: f64,
    /// Route everything through a `scancorr-router` (scancorrd as its client, the
    /// controllers and the consumer too), as a shop floor deploys it.
    pub router: bool,
    /// The service's correcting worker shards (0: one per core).
    pub workers: usize,
    /// Controller links: zenoh sessions (connections) the machines are spread over, each
    /// published from its own thread (at most one per machine).
    pub links: usize,
    /// A bare relay in the service's place (`bench relay --inline`): the bus's own cost per
    /// point (the same keys, input messages and output bytes; no correction, no shards).
    pub relay: bool,
    /// The relay's breakdown entries per point (None: the service's).
    pub relay_effects: Option<usize>,
    /// The service publishes its points without their breakdown (`publish_breakdown: false`).
    pub no_breakdown: bool,
    /// Print JSON.
    pub json: bool,
}

/// Calls `f(seq, t_ns)` for each point of a `CorrectedPointBatch` (or of several joined
/// ones: their bytes one after the other), reading only those two fields of each point in
/// place, from per-point messages or from packed blocks (v1.4: the `seq` and `t_ns` columns).
/// The consumer of 1 000 machines reads about a million points a second: decoding each one
/// would load the bench process, which shares the machine with the service it measures.
/// `None` when the bytes are not a well-formed batch.
fn each_point(mut b: &[u8], mut f: impl FnMut(u64, i64)) -> Option<()> {
    use scancorr_bag::{each_varint, next_field, Value};
    let (mut seqs, mut times) = (vec![], vec![]);
    while !b.is_empty() {
        match next_field(&mut b)? {
            (1, Value::Bytes(mut p)) => {
                let (mut seq, mut t_ns) = (0u64, 0i64);
                while !p.is_empty() {
                    match next_field(&mut p)? {
                        (2, Value::Varint(v)) => seq = v,
                        // int64: two's complement in ten bytes when negative.
                        (3, Value::Varint(v)) => t_ns = v as i64,
                        _ => {}
                    }
                }
                f(seq, t_ns);
            }
            (2, Value::Bytes(mut block)) => {
                // A column may come in several pieces (as protobuf allows): appended in order.
                seqs.clear();
                times.clear();
                while !block.is_empty() {
                    match next_field(&mut block)? {
                        (2, v) => each_varint(v, |x| seqs.push(x))?,
                        (3, v) => each_varint(v, |x| times.push(x))?,
                        _ => {}
                    }
                }
                if seqs.len() != times.len() {
                    return None;
                }
                for (&s, &t) in seqs.iter().zip(&times) {
                    f(s, t as i64);
                }
            }
            _ => {}
        }
    }
    Some(())
}

/// What serves the fleet, as the report names it.
fn served_by(p: &Params) -> String {
    if p.relay {
        let effects = p
            .relay_effects
            .map_or("the service's".to_string(), |n| n.to_string());
        return format!("a bare relay in the service's place (no correction, each message handled as it arrives; {effects} effects per point's breakdown)");
    }
    let workers = if p.workers == 0 {
        "one-per-core".to_string()
    } else {
        p.workers.to_string()
    };
    let router = if p.router {
        " behind a scancorr-router"
    } else {
        ""
    };
    let breakdown = if p.no_breakdown {
        ", points without their breakdown"
    } else {
        ""
    };
    format!("one scancorrd process with {workers} worker(s){router}{breakdown}")
}

fn machine_name(k: usize) -> String {
    format!("f{k:04}")
}

fn start_service(dir: &Path, port: u16, p: &Params) -> Result<Service> {
    let extra = format!(
        "max_machines: {}, max_pending_samples: {}, workers: {}, publish_breakdown: {},",
        p.machines + 16,
        p.max_pending,
        p.workers,
        !p.no_breakdown
    );
    if p.router {
        start_scancorrd_with(
            dir,
            &format!("mode: \"client\", listen: [], connect: [\"tcp/127.0.0.1:{port}\"],"),
            &extra,
        )
    } else {
        start_scancorrd(dir, port, &extra)
    }
}

/// Starts `scancorr-router` (plain TCP on loopback `port`, no access control) with its
/// files in `dir`.
fn start_router(dir: &Path, port: u16) -> Result<Service> {
    std::fs::create_dir_all(dir)?;
    std::fs::write(
        dir.join("router.json5"),
        format!("{{ mode: \"router\", listen: {{ endpoints: [\"tcp/127.0.0.1:{port}\"] }}, scouting: {{ multicast: {{ enabled: false }} }} }}"),
    )?;
    let bin = scancorrd_path()?
        .with_file_name(format!("scancorr-router{}", std::env::consts::EXE_SUFFIX));
    anyhow::ensure!(
        bin.exists(),
        "{} not found: build it with `cargo build --release -p scancorrd`",
        bin.display()
    );
    let child = Command::new(bin)
        .arg("-c")
        .arg(dir.join("router.json5"))
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(dir.join("router.log"))?)
        .spawn()
        .context("starting scancorr-router")?;
    let t0 = Instant::now();
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
        anyhow::ensure!(
            t0.elapsed() < Duration::from_secs(20),
            "scancorr-router did not start"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    Ok(Service {
        child,
        dir: dir.to_path_buf(),
    })
}

/// One batch period of one machine: (stream, payload) messages.
type Period = Vec<(usize, zenoh::bytes::ZBytes)>;

/// Every machine's messages per batch period (the same scan, each machine's own id).
fn encode_fleet(samples: &[Sample], machines: usize, batch_ns: i64) -> Vec<Vec<Period>> {
    let t_min = samples.iter().map(|s| s.t_ns()).min().unwrap_or(0);
    let periods = samples
        .iter()
        .map(|s| ((s.t_ns() - t_min) / batch_ns) as usize)
        .max()
        .map_or(0, |p| p + 1);
    let mut by_period: Vec<Vec<&Sample>> = vec![vec![]; periods];
    for s in samples {
        by_period[((s.t_ns() - t_min) / batch_ns) as usize].push(s);
    }
    by_period
        .iter()
        .map(|ss| {
            (0..machines)
                .map(|m| {
                    let mut b = Batcher::new(&machine_name(m), usize::MAX);
                    for s in ss {
                        b.push(s);
                    }
                    StreamId::ALL
                        .iter()
                        .filter_map(|st| {
                            b.take(*st)
                                .map(|(bytes, _, _)| (*st as usize, bytes.into()))
                        })
                        .collect()
                })
                .collect()
        })
        .collect()
}

/// Runs `f` over `items`, `width` at a time.
async fn in_parallel<T: Send + 'static>(
    session: &zenoh::Session,
    items: Vec<(String, Option<String>)>,
    width: usize,
    what: &str,
    quiet: bool,
    done: impl Fn(String) -> T,
) -> Result<Vec<T>> {
    let mut out = Vec::with_capacity(items.len());
    let n = items.len();
    for (k, chunk) in items.chunks(width).enumerate() {
        let mut set = tokio::task::JoinSet::new();
        for (i, (key, payload)) in chunk.iter().cloned().enumerate() {
            let s = session.clone();
            set.spawn(async move { (i, query(&s, key, payload).await) });
        }
        let mut got: Vec<(usize, String)> = Vec::with_capacity(chunk.len());
        while let Some(r) = set.join_next().await {
            let (i, r) = r?;
            got.push((i, r?));
        }
        got.sort_by_key(|g| g.0);
        out.extend(got.into_iter().map(|(_, s)| done(s)));
        if !quiet && (k + 1) % 10 == 0 {
            eprintln!("  {what}: {} of {n}", ((k + 1) * width).min(n));
        }
    }
    Ok(out)
}

/// One controller link: publishes its machines' messages of each period once the period has
/// ended (`start` + (k + 1) periods of `wall_ns`). Per period: how late it began, and how long
/// its puts took, ms.
fn controller(
    fleet: &[Vec<Period>],
    group: &[(usize, Vec<zenoh::pubsub::Publisher<'static>>)],
    start: Instant,
    wall_ns: i64,
) -> Result<Vec<(f64, f64)>> {
    use zenoh::Wait;
    let mut out = Vec::with_capacity(fleet.len());
    for (k, period) in fleet.iter().enumerate() {
        let due = start + Duration::from_nanos(((k as i64 + 1) * wall_ns) as u64);
        let now = Instant::now();
        let lag_ms = if now < due {
            std::thread::sleep(due - now);
            0.0
        } else {
            (now - due).as_secs_f64() * 1e3
        };
        let t_put = Instant::now();
        for (m, publishers) in group {
            for (st, bytes) in &period[*m] {
                // A `ZBytes` clone shares the bytes.
                publishers[*st]
                    .put(bytes.clone())
                    .wait()
                    .map_err(|e| anyhow::anyhow!("{e}"))?;
            }
        }
        out.push((lag_ms, t_put.elapsed().as_secs_f64() * 1e3));
    }
    Ok(out)
}

#[derive(Default)]
struct Received {
    points: u64,
    /// The bytes of the point messages those points came in.
    bytes: u64,
    gaps: u64,
    /// Point messages that are not a well-formed batch (none expected).
    malformed: u64,
    next_seq: Vec<u64>,
    latencies_ms: Vec<f64>,
    last_arrival: Option<Instant>,
}

/// `scancorr bench fleet`: one measurement, printed as text or JSON.
pub fn run(p: Params) -> Result<()> {
    let p = checked(p)?;
    let m = measure(&p)?;
    if p.json {
        outln!("{}", m.json)
    } else {
        out!("{}", m.text)
    }
}

/// One fleet measurement: the figures as JSON and as the lines `bench fleet` prints.
struct Measured {
    json: serde_json::Value,
    text: String,
}

/// `p` with its values checked, and no more links than machines.
fn checked(p: Params) -> Result<Params> {
    anyhow::ensure!(p.machines >= 1, "--machines must be at least 1");
    anyhow::ensure!(p.links >= 1, "--links must be at least 1");
    // No more links than machines.
    let p = Params {
        links: p.links.min(p.machines),
        ..p
    };
    anyhow::ensure!(p.batch_ms >= 1, "--batch-ms must be at least 1");
    anyhow::ensure!(
        p.seconds > 0.0 && p.seconds.is_finite(),
        "--seconds must be > 0"
    );
    anyhow::ensure!(p.pace > 0.0 && p.pace <= 1.0, "--pace must be in (0, 1]");
    Ok(p)
}

/// Runs the fleet once (`p` [`checked`]); shows progress on stderr unless `p.json`.
fn measure(p: &Params) -> Result<Measured> {
    let quiet = p.json;
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    rt.block_on(async {
        let dir = crate::shared::output::private_dir("scancorr-bench-fleet")?;
        let port = std::net::TcpListener::bind("127.0.0.1:0")?.local_addr()?.port();
        let _router = if p.router {
            Some(start_router(&crate::shared::output::private_dir("scancorr-bench-router")?, port)?)
        } else {
            None
        };
        let mut svc = if p.relay {
            std::fs::remove_dir_all(&dir).ok();
            let o = super::relay::Options { effects: p.relay_effects, inline: true };
            super::relay::start(port, "cmm", &o)?
        } else {
            start_service(&dir, port, p)?
        };
        let pid = svc.child.id();
        let cfg = scancorrd::config::zenoh_config("peer", &[], &[format!("tcp/127.0.0.1:{port}")], false)?;
        let session = zenoh::open(cfg.clone()).await.map_err(|e| anyhow::anyhow!("{e}"))?;
        // Wait for the service.
        let t0 = Instant::now();
        while query(&session, "cmm/probe-service/status".into(), None).await.is_err() {
            if let Ok(Some(st)) = svc.child.try_wait() {
                bail!("{} exited ({st}); log: {}", if p.relay { "the relay" } else { "scancorrd" }, svc.dir.join(if p.relay { "relay.log" } else { "scancorrd.log" }).display());
            }
            anyhow::ensure!(t0.elapsed() < Duration::from_secs(20), "scancorrd did not answer");
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        let (rss_idle, _) = memory(pid).context("reading the service's memory")?;

        // The scan and what the core makes of it (every machine gets the same scan).
        let n_points = (p.seconds * 1000.0).round() as usize;
        let samples = synth::ring_scan(n_points);
        let cal0 = synth::all_effects_calibration(&machine_name(0));
        // The relay makes a point of every probe sample; the service, of each scale sample it
        // can join.
        let expected_per_machine = if p.relay {
            samples.iter().filter(|s| s.stream() == StreamId::Probe).count() as u64
        } else {
            let mut c = scancorr_core::Corrector::new(&cal0)?;
            let mut o = scancorr_core::Output::default();
            c.push_all(samples.iter().cloned(), &mut o);
            o.points.len() as u64
        };
        if !quiet {
            eprintln!("fleet: {} machines × {} samples ({:.0} s at 1 kHz), {} ms batches", p.machines, samples.len(), p.seconds, p.batch_ms);
            eprintln!("  encoding every machine's batches …");
        }
        let batch_ns = p.batch_ms as i64 * 1_000_000;
        // Wall-clock length of a period.
        let wall_ns = (batch_ns as f64 / p.pace).round() as i64;
        let t_min = samples.iter().map(|s| s.t_ns()).min().unwrap_or(0);
        let fleet = encode_fleet(&samples, p.machines, batch_ns);
        let encoded_bytes: usize = fleet.iter().flatten().flatten().map(|(_, b)| b.len()).sum();

        // One calibration per machine: the service creates each machine's state on the put.
        let t_cal = Instant::now();
        let puts: Vec<(String, Option<String>)> = (0..p.machines)
            .filter(|_| !p.relay)
            .map(|m| (scancorr_proto::calibration_write_key("cmm", &machine_name(m)), Some(synth::all_effects_calibration(&machine_name(m)).to_json())))
            .collect();
        in_parallel(&session, puts, 32, "calibrations put", quiet, |_| ()).await?;
        let cal_s = t_cal.elapsed().as_secs_f64();
        tokio::time::sleep(Duration::from_millis(300)).await;
        let (rss_served, _) = memory(pid).context("reading the service's memory")?;

        // The consumer: every machine's points, seq checked, latency against the schedule.
        let rec = Arc::new(Mutex::new(Received { next_seq: vec![0; p.machines], ..Default::default() }));
        let start_cell: Arc<Mutex<Option<Instant>>> = Arc::new(Mutex::new(None));
        let sub = {
            let rec = rec.clone();
            let start_cell = start_cell.clone();
            session
                .declare_subscriber("cmm/*/corrected/points")
                .callback(move |s| {
                    let now = Instant::now();
                    let key = s.key_expr().as_str();
                    let Some(m) = key.split('/').nth(1).and_then(|n| n.strip_prefix('f')).and_then(|n| n.parse::<usize>().ok()) else { return };
                    let bytes = s.payload().to_bytes();
                    let start = *start_cell.lock().expect("lock");
                    let mut r = rec.lock().expect("lock");
                    if m >= r.next_seq.len() {
                        return;
                    }
                    let (mut next, mut gaps, mut n, mut last_t) = (r.next_seq[m], 0, 0u64, None);
                    let well_formed = each_point(&bytes, |seq, t_ns| {
                        gaps += u64::from(seq != next);
                        next = seq + 1;
                        n += 1;
                        last_t = Some(t_ns);
                    });
                    if well_formed.is_none() {
                        r.malformed += 1;
                        return;
                    }
                    let Some(last_t) = last_t else { return };
                    r.next_seq[m] = next;
                    r.gaps += gaps;
                    r.points += n;
                    r.bytes += bytes.len() as u64;
                    if let Some(start) = start {
                        let period = (last_t - t_min) / batch_ns;
                        let due = start + Duration::from_nanos(((period + 1) * wall_ns) as u64);
                        r.latencies_ms.push(now.saturating_duration_since(due).as_secs_f64() * 1e3);
                    }
                    r.last_arrival = Some(now);
                })
                .await
                .map_err(|e| anyhow::anyhow!("{e}"))?
        };
        // Each machine's point key declared here too, so that zenoh resolves an arriving
        // batch's route once, not by matching every key of every machine per message (that
        // took a tenth of the machine's CPU at 500 machines).
        let mut point_keys = Vec::with_capacity(p.machines);
        for m in 0..p.machines {
            point_keys.push(
                session
                    .declare_keyexpr(format!("cmm/{}/corrected/points", machine_name(m)))
                    .await
                    .map_err(|e| anyhow::anyhow!("{e}"))?,
            );
        }
        // The controllers' sessions: link 0 is this session (the consumer's too), the others
        // their own connections to the service. Machine `m` is on link `m % links`.
        let mut links = vec![session.clone()];
        for _ in 1..p.links {
            links.push(zenoh::open(cfg.clone()).await.map_err(|e| anyhow::anyhow!("{e}"))?);
        }
        let mut groups: Vec<Vec<(usize, Vec<zenoh::pubsub::Publisher<'static>>)>> = (0..p.links).map(|_| vec![]).collect();
        for m in 0..p.machines {
            let link = &links[m % p.links];
            let mut row = Vec::with_capacity(4);
            for st in StreamId::ALL {
                // A declared key expression travels as a number and its route is cached.
                let ke = link
                    .declare_keyexpr(format!("cmm/{}/raw/{}", machine_name(m), st.name()))
                    .await
                    .map_err(|e| anyhow::anyhow!("{e}"))?;
                row.push(
                    link.declare_publisher(ke)
                        .congestion_control(CongestionControl::Block)
                        .await
                        .map_err(|e| anyhow::anyhow!("{e}"))?,
                );
            }
            groups[m % p.links].push((m, row));
        }
        tokio::time::sleep(Duration::from_millis(500)).await;

        // The controllers: one thread per link, each publishing its machines' batches of a
        // period when the period has ended, paced on its own.
        let self_cpu0 = cpu_seconds("self").unwrap_or(0.0);
        let svc_cpu0 = cpu_seconds(&pid.to_string()).unwrap_or(0.0);
        let switches0 = task_switches(pid).unwrap_or((0, 0));
        let fleet = Arc::new(fleet);
        let n_periods = fleet.len();
        let start = Instant::now();
        *start_cell.lock().expect("lock") = Some(start);
        let controllers: Vec<_> = groups
            .into_iter()
            .map(|group| {
                let fleet = fleet.clone();
                std::thread::spawn(move || controller(&fleet, &group, start, wall_ns))
            })
            .collect();
        let mut rss_steady = 0u64;
        let period_wall = Duration::from_nanos(wall_ns as u64);
        let mut shown = 0;
        while !controllers.iter().all(|c| c.is_finished()) {
            tokio::time::sleep(Duration::from_millis(20)).await;
            let k = (start.elapsed().as_nanos() / period_wall.as_nanos()) as usize;
            if rss_steady == 0 && k >= n_periods * 4 / 5 {
                rss_steady = memory(pid).map(|m| m.0).unwrap_or(0);
            }
            if !quiet && k >= shown + (n_periods / 10).max(1) && k < n_periods {
                shown = k;
                let got = rec.lock().expect("lock").points;
                eprintln!("  {:>3.0} %  points received {got}", 100.0 * k as f64 / n_periods as f64);
            }
        }
        // Per period: late when any link was; the put span and lag of the slowest link.
        let mut late = vec![false; n_periods];
        let mut put_spans_ms = vec![0f64; n_periods];
        let mut worst_publish_lag_ms = 0f64;
        for c in controllers {
            let r = c.join().map_err(|_| anyhow::anyhow!("a controller thread panicked"))??;
            for (k, (lag_ms, span_ms)) in r.into_iter().enumerate() {
                late[k] |= lag_ms > 0.0;
                worst_publish_lag_ms = worst_publish_lag_ms.max(lag_ms);
                put_spans_ms[k] = put_spans_ms[k].max(span_ms);
            }
        }
        let late_periods = late.iter().filter(|l| **l).count() as u64;
        if rss_steady == 0 {
            rss_steady = memory(pid).map(|m| m.0).unwrap_or(0);
        }
        let publish_s = start.elapsed().as_secs_f64();
        let expected = expected_per_machine * p.machines as u64;
        let t_wait = Instant::now();
        while rec.lock().expect("lock").points < expected && t_wait.elapsed() < Duration::from_secs(30) {
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        let svc_cpu = cpu_seconds(&pid.to_string()).unwrap_or(0.0) - svc_cpu0;
        // Threads that ended meanwhile take their counts with them: a floor.
        let switches = task_switches(pid).map_or((0, 0), |(v, i)| (v.saturating_sub(switches0.0), i.saturating_sub(switches0.1)));
        let self_cpu = cpu_seconds("self").unwrap_or(0.0) - self_cpu0;
        let (rss_end, rss_peak) = memory(pid).unwrap_or((0, 0));
        drop(sub);
        drop(point_keys);

        // The service's own account of each machine.
        let keys: Vec<(String, Option<String>)> = (0..p.machines).map(|m| (format!("cmm/{}/status", machine_name(m)), None)).collect();
        let statuses: Vec<serde_json::Value> = in_parallel(&session, keys, 50, "status read", quiet, |s| serde_json::from_str(&s).unwrap_or_default()).await?;
        let state: Vec<f64> = statuses.iter().filter_map(|s| s["state_bytes"].as_f64()).collect();
        // The latency the service itself adds (message arrival → its points published), each
        // machine's p99, µs: what of the end-to-end latency is the service's.
        let mut added_p99_us: Vec<f64> = statuses
            .iter()
            .filter_map(|s| s["output"]["added_latency_us"]["p99"].as_f64())
            .collect();
        let mut drops = std::collections::BTreeMap::<String, u64>::new();
        for s in &statuses {
            if let Some(d) = s["dropped"].as_object() {
                for (k, v) in d {
                    *drops.entry(k.clone()).or_default() += v.as_u64().unwrap_or(0);
                }
            }
        }
        session.close().await.map_err(|e| anyhow::anyhow!("{e}"))?;
        drop(svc);

        let r = rec.lock().expect("lock");
        let mut lat = r.latencies_ms.clone();
        let (p50, p99, pmax) = (pct(&mut lat, 0.5), pct(&mut lat, 0.99), pct(&mut lat, 1.0));
        let (put_span_p50, put_span_max) = (pct(&mut put_spans_ms, 0.5), pct(&mut put_spans_ms, 1.0));
        let (added_p99_median_ms, added_p99_max_ms) = (pct(&mut added_p99_us, 0.5) / 1e3, pct(&mut added_p99_us, 1.0) / 1e3);
        let span_s = r.last_arrival.map_or(publish_s, |t| (t - start).as_secs_f64());
        let samples_per_s = (samples.len() * p.machines) as f64 / p.seconds * p.pace;
        let points_expected_per_s = (expected_per_machine * p.machines as u64) as f64 / p.seconds * p.pace;
        // Service CPU per delivered point, and what the full fleet at real time would need.
        let us_per_point = svc_cpu / (r.points.max(1) as f64) * 1e6;
        let cores_for_target = us_per_point * 1e-6 * 1000.0 * 1000.0;
        let points_per_s = r.points as f64 / span_s.max(1e-9);
        let per_machine_rss = (rss_steady.max(rss_idle) - rss_idle) as f64 / p.machines as f64;
        let per_machine_served = (rss_served.max(rss_idle) - rss_idle) as f64 / p.machines as f64;
        // No figure (the relay has no core state): 0, not the empty sum's −0.
        let state_mean = if state.is_empty() { 0.0 } else { state.iter().sum::<f64>() / state.len() as f64 };
        let state_max = state.iter().cloned().fold(0.0, f64::max);
        let kept_up = r.points == expected && r.gaps == 0 && r.malformed == 0 && late_periods == 0 && p99 < 2.0 * p.batch_ms as f64 / p.pace;
        // Where the end-to-end latency goes (its own object: `json!` nests only so deep).
        let latency_parts = serde_json::json!({
            "controller_put_span_ms_p50": put_span_p50,
            "controller_put_span_ms_max": put_span_max,
            "service_added_p99_ms_median_machine": added_p99_median_ms,
            "service_added_p99_ms_worst_machine": added_p99_max_ms,
        });
        let mut out = serde_json::json!({
            "bench": "fleet",
            "machines": p.machines,
            "through_router": p.router,
            "bare_relay": p.relay,
            "relay_effects": p.relay_effects,
            "publish_breakdown": !p.relay && !p.no_breakdown,
            "workers": p.workers,
            "rate_hz_per_machine": 1000,
            "seconds": p.seconds,
            "batch_ms": p.batch_ms,
            "pace": p.pace,
            "max_pending_samples": p.max_pending,
            "offered_samples_per_s": samples_per_s,
            "expected_points": expected,
            "received_points": r.points,
            "point_bytes_per_point": r.bytes as f64 / r.points.max(1) as f64,
            "seq_gaps": r.gaps,
            "malformed_point_messages": r.malformed,
            "dropped": drops,
            "points_per_s": points_per_s,
            "publish_seconds": publish_s,
            "late_periods": late_periods,
            "worst_publish_lag_ms": worst_publish_lag_ms,
            "p50_latency_ms": p50,
            "p99_latency_ms": p99,
            "max_latency_ms": pmax,
            "kept_up": kept_up,
            "calibration_puts_s": cal_s,
            "encoded_input_bytes": encoded_bytes,
            "service_rss_idle_bytes": rss_idle,
            "service_rss_served_bytes": rss_served,
            "service_rss_steady_bytes": rss_steady,
            "service_rss_end_bytes": rss_end,
            "service_rss_peak_bytes": rss_peak,
            "rss_per_machine_bytes": per_machine_rss,
            "rss_per_machine_before_data_bytes": per_machine_served,
            "core_state_bytes_mean": state_mean,
            "core_state_bytes_max": state_max,
            "service_cpu_cores": svc_cpu / span_s.max(1e-9),
            "service_cpu_us_per_point": us_per_point,
            "service_cores_for_1000_machines_at_1khz": cores_for_target,
            "bench_process_cpu_cores": self_cpu / span_s.max(1e-9),
            "service_task_switches_per_s": (switches.0 + switches.1) as f64 / span_s.max(1e-9),
            "service_voluntary_switches_per_s": switches.0 as f64 / span_s.max(1e-9),
            "service_involuntary_switches_per_s": switches.1 as f64 / span_s.max(1e-9),
            "targets": {"machines": 1000, "state_bytes_per_machine": 65536},
        });
        out["latency_parts"] = latency_parts;
        out["controller_links"] = p.links.into();
        let mut text = String::new();
        {
            let kib = |b: f64| b / 1024.0;
            writeln!(text, "fleet: {} machines × 1 kHz, {} ms batches, {:.0} s at {:.0} % of real time, {} (loopback; this process plays the controllers, on {} link(s), and the consumer on the same cores)", p.machines, p.batch_ms, p.seconds, 100.0 * p.pace, served_by(p), p.links)?;
            writeln!(text, "  offered                {samples_per_s:>12.0} samples/s  ({points_expected_per_s:.0} points/s expected)")?;
            writeln!(text, "  delivered              {points_per_s:>12.0} points/s   {} of {expected} points, {} seq gaps, {} malformed messages, dropped {:?}; {:.0} bytes per point on the bus", r.points, r.gaps, r.malformed, drops, r.bytes as f64 / r.points.max(1) as f64)?;
            writeln!(text, "  latency (period end → points)  p50 {p50:.1} ms, p99 {p99:.1} ms, max {pmax:.1} ms; publisher late in {late_periods} of {n_periods} periods (worst {worst_publish_lag_ms:.1} ms)")?;
            writeln!(text, "  of which               controllers' puts of a period take {put_span_p50:.1} ms (median; max {put_span_max:.1} ms); the service adds p99 {added_p99_median_ms:.1} ms (median machine; worst {added_p99_max_ms:.1} ms) from arrival to publication")?;
            writeln!(text, "  kept up                {}", if kept_up { "yes" } else { "NO" })?;
            writeln!(text, "  service memory         idle {:.1} MiB, served {:.1} MiB, steady {:.1} MiB, peak {:.1} MiB", rss_idle as f64 / 1048576.0, rss_served as f64 / 1048576.0, rss_steady as f64 / 1048576.0, rss_peak as f64 / 1048576.0)?;
            writeln!(text, "  per machine            {:.1} KiB resident ({:.1} KiB before data); core state {:.1} KiB mean, {:.1} KiB max   (target ≤ 64 KiB)", kib(per_machine_rss), kib(per_machine_served), kib(state_mean), kib(state_max))?;
            writeln!(text, "  CPU                    service {:.2} cores, controllers + consumer {:.2} cores; service {us_per_point:.2} µs per point → {cores_for_target:.2} cores for 1000 machines at 1 kHz", svc_cpu / span_s.max(1e-9), self_cpu / span_s.max(1e-9))?;
            let per_s = |n: u64| n as f64 / span_s.max(1e-9);
            writeln!(text, "  task switches          service {:.0}/s ({:.0}/s waiting, {:.0}/s preempted; threads still running)", per_s(switches.0 + switches.1), per_s(switches.0), per_s(switches.1))?;
        }
        Ok(Measured { json: out, text })
    })
}

/// The sizes `bench fleet --largest` probes, and how often each.
#[derive(Debug, Clone, Copy)]
pub struct Search {
    /// The smallest fleet probed.
    pub from: usize,
    /// The largest fleet probed.
    pub to: usize,
    /// The fleet sizes probed are `from + k·step` (and `to`).
    pub step: usize,
    /// Runs per size: a size keeps up when every one of its runs kept real time.
    pub runs: usize,
}

/// What a search over fleet sizes found.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Bounds {
    /// Not even the smallest size kept up.
    None { failed: usize },
    /// The largest size kept up.
    All { kept_up: usize },
    /// `kept_up` did, `failed` (the next size probed above it) did not; no size between
    /// them was probed.
    Between { kept_up: usize, failed: usize },
}

impl Bounds {
    fn kept_up(self) -> Option<usize> {
        match self {
            Bounds::None { .. } => None,
            Bounds::All { kept_up } | Bounds::Between { kept_up, .. } => Some(kept_up),
        }
    }
    fn failed(self) -> Option<usize> {
        match self {
            Bounds::All { .. } => None,
            Bounds::None { failed } | Bounds::Between { failed, .. } => Some(failed),
        }
    }
}

/// Bisects the sizes `from, from + step, …, to` for the largest that keeps up, supposing
/// that when a fleet does not keep up no larger one does (more machines load the same cores
/// more): `from` first, then `to`, then halving the gap. Each size is probed once; about
/// log₂((to − from)/step) + 2 probes. On a noisy host the sizes near the limit keep up in
/// some runs and not in others: the bound lands somewhere in that band, and more runs per
/// size move it to the band's lower edge.
fn bisect(s: &Search, mut keeps_up: impl FnMut(usize) -> Result<bool>) -> Result<Bounds> {
    let last = (s.to - s.from).div_ceil(s.step);
    // Saturating: a `--step` beyond the range makes the grid `from` and `to` alone.
    let size = |k: usize| s.from.saturating_add(k.saturating_mul(s.step)).min(s.to);
    if !keeps_up(size(0))? {
        return Ok(Bounds::None { failed: size(0) });
    }
    if last == 0 || keeps_up(size(last))? {
        return Ok(Bounds::All {
            kept_up: size(last),
        });
    }
    let (mut lo, mut hi) = (0, last);
    while hi - lo > 1 {
        let mid = lo + (hi - lo) / 2;
        if keeps_up(size(mid))? {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    Ok(Bounds::Between {
        kept_up: size(lo),
        failed: size(hi),
    })
}

/// One size probed by the search: its runs' figures.
struct Probe {
    machines: usize,
    /// Each run's figures (`bench fleet --json`), in order; the runs stop at the first that
    /// did not keep up.
    runs: Vec<serde_json::Value>,
}

impl Probe {
    fn kept_up(&self) -> usize {
        self.runs.iter().filter(|r| r["kept_up"] == true).count()
    }
    /// The median over the runs of a figure.
    fn median(&self, key: &str) -> f64 {
        let mut v: Vec<f64> = self.runs.iter().filter_map(|r| r[key].as_f64()).collect();
        pct(&mut v, 0.5)
    }
}

/// `scancorr bench fleet --largest`: the largest fleet that keeps real time with `p.workers`
/// worker shards, by bisection over `search`'s sizes; each size is run up to `search.runs`
/// times and keeps up only when every run did. Prints each probe and the bounds found.
pub fn largest(p: Params, search: Search) -> Result<()> {
    anyhow::ensure!(search.from >= 1, "--from must be at least 1");
    anyhow::ensure!(
        search.to >= search.from,
        "--machines ({}) must be at least --from ({})",
        search.to,
        search.from
    );
    anyhow::ensure!(search.step >= 1, "--step must be at least 1");
    anyhow::ensure!(search.runs >= 1, "--runs must be at least 1");
    let json = p.json;
    let mut probes: Vec<Probe> = vec![];
    let bounds = bisect(&search, |machines| {
        let q = checked(Params {
            machines,
            json: true,
            ..p.clone()
        })?;
        let mut probe = Probe {
            machines,
            runs: vec![],
        };
        for run in 1..=search.runs {
            eprintln!("  {machines} machines, run {run} of {} …", search.runs);
            let m = measure(&q).with_context(|| {
                format!(
                    "measuring {machines} machines (run {run} of {})",
                    search.runs
                )
            })?;
            let kept_up = m.json["kept_up"] == true;
            probe.runs.push(m.json);
            if !kept_up {
                break;
            }
        }
        let ok = probe.kept_up() == search.runs;
        eprintln!(
            "  {machines} machines: kept up in {} of {} run(s){}, {:.2} µs of service CPU per point",
            probe.kept_up(),
            probe.runs.len(),
            if ok { "" } else { ": does not keep up" },
            probe.median("service_cpu_us_per_point"),
        );
        probes.push(probe);
        Ok(ok)
    })?;
    let workers = if p.workers == 0 {
        "one per core".to_string()
    } else {
        p.workers.to_string()
    };
    if json {
        let rows: Vec<serde_json::Value> = probes
            .iter()
            .map(|r| {
                serde_json::json!({
                    "machines": r.machines,
                    "runs": r.runs.len(),
                    "kept_up_runs": r.kept_up(),
                    "service_cpu_us_per_point_median": r.median("service_cpu_us_per_point"),
                    "rss_per_machine_bytes_median": r.median("rss_per_machine_bytes"),
                    "p99_latency_ms_median": r.median("p99_latency_ms"),
                    "late_periods_median": r.median("late_periods"),
                    "each_run": r.runs,
                })
            })
            .collect();
        outln!(
            "{}",
            serde_json::json!({
                "bench": "fleet-largest",
                "workers": p.workers,
                "from": search.from,
                "to": search.to,
                "step": search.step,
                "runs_per_size": search.runs,
                "largest_kept_up": bounds.kept_up(),
                "smallest_failed": bounds.failed(),
                "probes": rows,
            })
        )?;
        return Ok(());
    }
    outln!(
        "fleet sizes that keep real time with {workers} worker(s): {} to {} machines in steps of {}, each size run up to {} time(s) (kept up: every run did)",
        search.from,
        search.to,
        search.step,
        search.runs
    )?;
    outln!("  machines  kept up  µs per point  KiB per machine  p99 latency ms  late periods   (medians over the size's runs)")?;
    let mut sorted: Vec<&Probe> = probes.iter().collect();
    sorted.sort_by_key(|r| r.machines);
    for r in sorted {
        outln!(
            "  {:>8}  {:>3} of {}  {:>12.2}  {:>15.1}  {:>14.0}  {:>12.0}",
            r.machines,
            r.kept_up(),
            r.runs.len(),
            r.median("service_cpu_us_per_point"),
            r.median("rss_per_machine_bytes") / 1024.0,
            r.median("p99_latency_ms"),
            r.median("late_periods"),
        )?;
    }
    match bounds {
        Bounds::Between { kept_up, failed } => outln!("  largest that kept up: {kept_up} machines; {failed} did not (no size between them was run)"),
        Bounds::All { kept_up } => outln!("  largest that kept up: {kept_up} machines, the largest probed: raise --machines to look further"),
        Bounds::None { failed } => outln!("  none kept up: not even {failed} machines; lower --from"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use prost::Message;

    /// Against every threshold a fleet could have: the bisection finds the largest size on
    /// the grid that keeps up and the next one, probing each size at most once and about
    /// log₂ of the sizes, never outside the range; `to` off the grid is probed as itself.
    #[test]
    fn bisection_finds_the_largest_size_that_keeps_up() {
        for (from, to, step) in [
            (100, 1000, 50),
            (100, 1030, 50),
            (1, 7, 1),
            (300, 300, 50),
            (10, 40, 100),
            (10, 40, usize::MAX),
        ] {
            let search = Search {
                from,
                to,
                step,
                runs: 1,
            };
            let mut grid: Vec<usize> = (from..=to).step_by(step).collect();
            if grid.last() != Some(&to) {
                grid.push(to);
            }
            for threshold in from.saturating_sub(2)..=to + 2 {
                let mut probed = vec![];
                let found = bisect(&search, |n| {
                    probed.push(n);
                    Ok(n <= threshold)
                })
                .unwrap();
                let want_ok = grid.iter().copied().filter(|&n| n <= threshold).max();
                let want_fail = grid.iter().copied().find(|&n| n > threshold);
                let want = match (want_ok, want_fail) {
                    (None, Some(failed)) => Bounds::None { failed },
                    (Some(kept_up), None) => Bounds::All { kept_up },
                    (Some(kept_up), Some(failed)) => Bounds::Between { kept_up, failed },
                    (None, None) => unreachable!("the grid is not empty"),
                };
                let case =
                    format!("{from}..{to} step {step}, threshold {threshold}: probed {probed:?}");
                assert_eq!(found, want, "{case}");
                assert!(probed.iter().all(|n| grid.contains(n)), "{case}");
                let mut once = probed.clone();
                once.sort();
                once.dedup();
                assert_eq!(once.len(), probed.len(), "a size probed twice: {case}");
                let bound = (grid.len() as f64).log2().ceil() as usize + 2;
                assert!(
                    probed.len() <= bound,
                    "{} probes, more than {bound}: {case}",
                    probed.len()
                );
            }
        }
    }

    /// A measurement that fails ends the search with its error; nothing is probed after it.
    #[test]
    fn a_failed_measurement_ends_the_search() {
        let search = Search {
            from: 100,
            to: 1000,
            step: 50,
            runs: 2,
        };
        let mut probed = vec![];
        let e = bisect(&search, |n| {
            probed.push(n);
            if n == 1000 {
                anyhow::bail!("scancorrd exited");
            }
            Ok(true)
        })
        .unwrap_err();
        assert!(format!("{e:#}").contains("scancorrd exited"), "{e:#}");
        assert_eq!(probed, vec![100, 1000]);
    }

    /// The consumer's reading of point batches agrees with prost's decoding, for one batch,
    /// two joined ones, negative times; and refuses cut bytes.
    #[test]
    fn each_point_reads_seq_and_time_as_prost_does() {
        let samples = synth::ring_scan(2000);
        let cal = synth::all_effects_calibration("f0001");
        let mut c = scancorr_core::Corrector::new(&cal).unwrap();
        let mut o = scancorr_core::Output::default();
        c.push_all(samples, &mut o);
        let ids = c.effect_ids();
        let mut points = o.points.clone();
        assert!(points.len() > 300, "{}", points.len());
        points[7].t_ns = -1_234_567;
        let (a, b) = points.split_at(points.len() / 2);
        let mut bytes = vec![];
        scancorr_core::wire::encode_points(a, "f0001", &ids, &mut bytes);
        let one = bytes.len();
        scancorr_core::wire::encode_points(b, "f0001", &ids, &mut bytes);
        for buf in [&bytes[..one], &bytes[..]] {
            let want: Vec<(u64, i64)> = scancorr_proto::v1::CorrectedPointBatch::decode(buf)
                .unwrap()
                .into_points()
                .unwrap()
                .iter()
                .map(|p| (p.seq, p.t_ns))
                .collect();
            let mut got = vec![];
            assert!(each_point(buf, |s, t| got.push((s, t))).is_some());
            assert_eq!(got, want);
        }
        assert!(each_point(&bytes[..one - 1], |_, _| ()).is_none());
        assert!(each_point(&[0x0a, 0xff], |_, _| ()).is_none());
    }
}
