//! `scancorr bench relay`: the floor the service is compared with — the same bus work without
//! the correction. It declares what the service declares (a subscriber on
//! `<prefix>/*/raw/**`, each machine's raw keys, a publisher on
//! `<prefix>/<machine>/corrected/points` with congestion control Block) and makes the same
//! output traffic: for each probe message (the stream that closes an instant) one message of
//! its points, in the service's bytes (written by the service's own encoder, v1.4 packed),
//! stamped with the probe samples' times and numbered from 0 per machine as the service
//! numbers them. It answers `<prefix>/<machine>/status` with the latency it adds, measured as
//! the service measures its own (arrival → `put` returned). Runs until SIGTERM or SIGINT.
//!
//! Two ways to take a message: queued by the subscriber's callback to one worker thread with
//! its arrival instant, as the service hands its messages to its shards (`bench live`
//! compares the service with this), or handled inline in the callback (`--inline`: no
//! hand-over and no wake-up of another thread — the least any service on this bus can spend;
//! `bench fleet --relay` uses it).

use super::harness::{session, z, Service};
use crate::shared::synth;
use anyhow::{Context, Result};
use scancorr_core::sample::{CorrectedPoint, StreamId, Vec3};
use scancorr_proto::Stream;
use std::collections::HashMap;
use std::process::{Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::Instant;
use zenoh::qos::CongestionControl;
use zenoh::Wait;

/// How the relay works.
#[derive(Debug, Clone, Default)]
pub struct Options {
    /// Entries of each point's breakdown (None: as many as every effect's calibration has,
    /// as the service's points carry).
    pub effects: Option<usize>,
    /// Handle each message in the subscriber's callback instead of a worker thread.
    pub inline: bool,
}

/// Per machine: points published and the latency added.
type Figures = HashMap<String, (u64, scancorrd::latency::Latency)>;

/// One machine's declarations and numbering.
struct Out {
    _raw: Vec<zenoh::key_expr::KeyExpr<'static>>,
    points: zenoh::pubsub::Publisher<'static>,
    seq: u64,
}

/// What the relay keeps: each machine's declarations, the breakdown's names, the figures,
/// and the buffers each message reuses (the floor it measures is the bus's, not the
/// allocator's: the service too reuses its output's room).
struct Relay {
    session: zenoh::Session,
    prefix: String,
    machines: HashMap<String, Out>,
    effects: Vec<String>,
    figures: Arc<Mutex<Figures>>,
    /// The probe samples' (seq, time) of the message at hand.
    probes: Vec<(u64, i64)>,
    /// Its points: fixed values but for their numbers and times.
    points: Vec<CorrectedPoint>,
}

/// A relayed point before its numbers and time: values of the service's magnitude.
fn template(effects: usize) -> CorrectedPoint {
    CorrectedPoint {
        seq: 0,
        t_ns: 0,
        sample_seq: 0,
        surface: Vec3::repeat(100.123456),
        tip_center: Vec3::repeat(101.123456),
        normal: Vec3::repeat(0.577),
        corrections: vec![Vec3::repeat(1e-4); effects],
        calibration_version: 1,
        estimator_valid: true,
        segment_id: 1,
        tip_id: 1,
    }
}

impl Relay {
    /// Takes one raw message that arrived at `arrived`; a message of a key that is not a
    /// raw stream's, or whose bytes do not decode, is skipped (a relay has no one to tell).
    fn handle(&mut self, arrived: Instant, m: &zenoh::sample::Sample) -> Result<()> {
        let Some((machine, stream)) = Stream::parse_key(&self.prefix, m.key_expr().as_str()) else {
            return Ok(());
        };
        if !self.machines.contains_key(machine) {
            let (s, prefix) = (&self.session, &self.prefix);
            let mut raw = vec![];
            for st in StreamId::ALL {
                let key = format!("{prefix}/{machine}/raw/{}", st.name());
                raw.push(s.declare_keyexpr(key).wait().map_err(z)?);
            }
            let ke = s
                .declare_keyexpr(Stream::Points.key(prefix, machine))
                .wait()
                .map_err(z)?;
            let points = s
                .declare_publisher(ke)
                .congestion_control(CongestionControl::Block)
                .wait()
                .map_err(z)?;
            let out = Out {
                _raw: raw,
                points,
                seq: 0,
            };
            self.machines.insert(machine.to_string(), out);
        }
        if stream != Stream::Probe {
            return Ok(());
        }
        // Packed (v1.3) or per-sample: each probe sample's seq and time.
        let probes = &mut self.probes;
        probes.clear();
        let bytes = m.payload().to_bytes();
        let decoded = scancorr_core::wire::decode_with(StreamId::Probe, &bytes, |_, s| {
            probes.push((s.seq(), s.t_ns()))
        });
        if decoded.is_err() {
            return Ok(());
        }
        let out = self.machines.get_mut(machine).expect("declared above");
        let e = self.effects.len();
        self.points.resize_with(probes.len(), || template(e));
        for (p, &(sample_seq, t_ns)) in self.points.iter_mut().zip(probes.iter()) {
            (p.seq, p.t_ns, p.sample_seq) = (out.seq, t_ns, sample_seq);
            out.seq += 1;
        }
        // The buffer goes to zenoh with the message (as the service's pooled one does).
        let mut bytes = Vec::new();
        scancorr_core::wire::encode_points(&self.points, machine, &self.effects, &mut bytes);
        out.points.put(bytes).wait().map_err(z)?;
        let n = self.points.len() as u64;
        let mut f = self.figures.lock().expect("lock");
        let at = match f.get_mut(machine) {
            Some(at) => at,
            None => f.entry(machine.to_string()).or_default(),
        };
        at.0 += n;
        at.1.record(arrived.elapsed());
        Ok(())
    }
}

/// Runs the relay on loopback `port` until SIGTERM or SIGINT.
pub fn run(port: u16, prefix: &str, o: &Options) -> Result<()> {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    rt.block_on(async {
        let s = session(&[], Some(port)).await?;
        let figures: Arc<Mutex<Figures>> = Arc::default();
        let _status = {
            let figures = figures.clone();
            let prefix = prefix.to_string();
            s.declare_queryable(format!("{prefix}/*/status"))
                .callback(move |q| {
                    let m = scancorr_proto::machine_of(&prefix, q.key_expr().as_str(), "status")
                        .unwrap_or_default()
                        .to_string();
                    let body = match figures.lock().expect("lock").get(&m) {
                        Some((n, l)) => serde_json::json!({"machine": m, "served": true, "output": {"points_published": n, "added_latency_us": l.figures()}}),
                        None => serde_json::json!({"machine": m, "served": false}),
                    };
                    let _ = q.reply(q.key_expr().clone(), body.to_string()).wait();
                })
                .await
                .map_err(z)?
        };
        let mut effects =
            scancorr_core::Corrector::new(&synth::all_effects_calibration("x"))?.effect_ids();
        if let Some(n) = o.effects {
            effects = (0..n)
                .map(|k| effects.get(k).cloned().unwrap_or_else(|| format!("effect_{k}")))
                .collect();
        }
        let mut relay = Relay {
            session: s.clone(),
            prefix: prefix.to_string(),
            machines: HashMap::new(),
            effects,
            figures,
            probes: vec![],
            points: vec![],
        };
        let raw = format!("{prefix}/*/raw/**");
        let (sub, worker) = if o.inline {
            // Called from zenoh's receive threads, one at a time per message; the lock is
            // uncontended but for two messages at once.
            let relay = Mutex::new(relay);
            let sub = s
                .declare_subscriber(raw)
                .callback(move |m| {
                    if let Err(e) = relay.lock().expect("lock").handle(Instant::now(), &m) {
                        eprintln!("relay: {e:#}");
                    }
                })
                .await
                .map_err(z)?;
            (sub, None)
        } else {
            let (tx, rx) = std::sync::mpsc::sync_channel::<(Instant, zenoh::sample::Sample)>(256);
            let sub = s
                .declare_subscriber(raw)
                .callback(move |m| {
                    let _ = tx.send((Instant::now(), m));
                })
                .await
                .map_err(z)?;
            let worker = std::thread::spawn(move || -> Result<()> {
                while let Ok((arrived, m)) = rx.recv() {
                    relay.handle(arrived, &m)?;
                }
                Ok(())
            });
            (sub, Some(worker))
        };
        let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())?;
        tokio::select! { _ = term.recv() => {}, _ = tokio::signal::ctrl_c() => {} }
        drop(sub);
        s.close().await.map_err(z)?;
        if let Some(w) = worker {
            let _ = w.join();
        }
        Ok(())
    })
}

/// Starts the relay (`scancorr bench relay`) as a child process listening on `port`.
pub(crate) fn start(port: u16, prefix: &str, o: &Options) -> Result<Service> {
    let dir = crate::shared::output::private_dir(&format!("scancorr-bench-relay-{port}"))?;
    let mut args = vec![
        "bench".to_string(),
        "relay".into(),
        "--port".into(),
        port.to_string(),
        "--prefix".into(),
        prefix.into(),
    ];
    if let Some(n) = o.effects {
        args.extend(["--effects".into(), n.to_string()]);
    }
    if o.inline {
        args.push("--inline".into());
    }
    let child = Command::new(std::env::current_exe()?)
        .args(&args)
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(dir.join("relay.log"))?)
        .spawn()
        .context("starting the relay")?;
    Ok(Service { child, dir })
}
