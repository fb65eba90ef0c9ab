//! The async shell: zenoh in, the pure core, zenoh out. One task owns every machine's state;
//! each raw message is decoded, pushed through that machine's [`Corrector`] and whatever it
//! completes is published at once.

use crate::config::Config;
use crate::store::Store;
use scancorr_core::wire;
use scancorr_core::{Calibration, Corrector, Output};
use scancorr_proto::{Message, Stream};
use serde_json::json;
use std::collections::BTreeMap;
use std::future::Future;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tracing::{info, warn};
use zenoh::qos::CongestionControl;

/// Why the service stopped.
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    /// Bad configuration.
    #[error(transparent)]
    Config(#[from] crate::config::ConfigError),
    /// The calibration store.
    #[error(transparent)]
    Store(#[from] crate::store::StoreError),
    /// Zenoh.
    #[error("zenoh: {0}")]
    Zenoh(String),
}

fn z<E: std::fmt::Display>(e: E) -> ServiceError {
    ServiceError::Zenoh(e.to_string())
}

/// Counters the core does not see (message level).
#[derive(Debug, Default, Clone, serde::Serialize)]
struct Extra {
    malformed: u64,
    empty: u64,
    wrong_machine: u64,
    no_calibration: u64,
    messages: u64,
}

struct Machine {
    corrector: Option<Corrector>,
    points: zenoh::pubsub::Publisher<'static>,
    alarms: zenoh::pubsub::Publisher<'static>,
    _token: zenoh::liveliness::LivelinessToken,
    /// The machine's raw key expressions, declared so that zenoh resolves an incoming
    /// message's route once, not by matching every key of every machine per message.
    _raw_keys: Vec<zenoh::key_expr::KeyExpr<'static>>,
    ids: Vec<String>,
    extra: Extra,
    last_arrival: [Option<Instant>; 4],
    stalled: [bool; 4],
    last_lag_ms: f64,
}

struct State {
    cfg: Config,
    session: zenoh::Session,
    store: Store,
    machines: BTreeMap<String, Machine>,
    refused: BTreeMap<String, u64>,
    /// What the core completed for the message in hand; published and cleared before the
    /// next message, so one buffer serves every machine.
    out: Output,
}

/// Runs the service until `shutdown` resolves; then flushes every machine and closes the
/// session.
pub async fn run(cfg: Config, shutdown: impl Future<Output = ()>) -> Result<(), ServiceError> {
    let store = Store::open(&cfg.data_dir)?;
    let session = zenoh::open(cfg.zenoh()?).await.map_err(z)?;
    let prefix = cfg.prefix.clone();
    info!(prefix = %prefix, listen = ?cfg.listen, connect = ?cfg.connect, data_dir = %cfg.data_dir.display(), "scancorrd started");
    let raw = session
        .declare_subscriber(format!("{prefix}/*/raw/**"))
        .await
        .map_err(z)?;
    let calib = session
        .declare_queryable(format!("{prefix}/*/calibration"))
        .await
        .map_err(z)?;
    let status = session
        .declare_queryable(format!("{prefix}/*/status"))
        .await
        .map_err(z)?;
    let mut st = State {
        cfg,
        session: session.clone(),
        store,
        machines: BTreeMap::new(),
        refused: BTreeMap::new(),
        out: Output::default(),
    };
    // Machines with a stored calibration are served from the start.
    for m in st.store.machines()? {
        if st.cfg.serves(&m) {
            st.machine(&m).await?;
        }
    }
    tokio::pin!(shutdown);
    let mut tick = tokio::time::interval(Duration::from_millis(250));
    loop {
        tokio::select! {
            biased;
            _ = &mut shutdown => break,
            q = calib.recv_async() => match q {
                Ok(q) => st.on_calibration(q).await,
                Err(e) => { warn!(error = %e, "calibration queryable closed"); break }
            },
            q = status.recv_async() => if let Ok(q) = q { st.on_status(q).await },
            s = raw.recv_async() => match s {
                Ok(s) => st.on_raw(s).await,
                Err(e) => { warn!(error = %e, "raw subscriber closed"); break }
            },
            _ = tick.tick() => st.check_stalls(),
        }
    }
    info!("shutting down: flushing buffered samples");
    let names: Vec<String> = st.machines.keys().cloned().collect();
    for m in names {
        st.flush(&m).await;
    }
    drop(st);
    session.close().await.map_err(z)?;
    info!("scancorrd stopped");
    Ok(())
}

impl State {
    /// A corrector under this service's limits.
    fn corrector(&self, model: Arc<scancorr_core::calib::Model>) -> Corrector {
        let mut c = Corrector::with_model(model);
        c.limit_pending(Some(self.cfg.max_pending_samples));
        c
    }

    async fn machine(&mut self, name: &str) -> Result<&mut Machine, ServiceError> {
        if !self.machines.contains_key(name) {
            let p = &self.cfg.prefix;
            let points = self
                .session
                .declare_publisher(
                    self.session
                        .declare_keyexpr(Stream::Points.key(p, name))
                        .await
                        .map_err(z)?,
                )
                .congestion_control(CongestionControl::Block)
                .await
                .map_err(z)?;
            let alarms = self
                .session
                .declare_publisher(
                    self.session
                        .declare_keyexpr(Stream::Alarms.key(p, name))
                        .await
                        .map_err(z)?,
                )
                .congestion_control(CongestionControl::Block)
                .await
                .map_err(z)?;
            let token = self
                .session
                .liveliness()
                .declare_token(format!("{p}/{name}/scancorrd"))
                .await
                .map_err(z)?;
            let mut raw_keys = Vec::with_capacity(4);
            for st in scancorr_core::sample::StreamId::ALL {
                raw_keys.push(
                    self.session
                        .declare_keyexpr(format!("{p}/{name}/raw/{}", st.name()))
                        .await
                        .map_err(z)?,
                );
            }
            let corrector = match self.store.current(name)? {
                Some(c) => match c.build() {
                    Ok(m) => Some(self.corrector(Arc::new(m))),
                    Err(e) => {
                        warn!(machine = name, error = %e, "stored calibration is not valid; waiting for a new one");
                        None
                    }
                },
                None => {
                    warn!(machine = name, "no calibration for this machine yet: samples are counted, not corrected, until one is put");
                    None
                }
            };
            let ids = corrector
                .as_ref()
                .map(|c| c.effect_ids())
                .unwrap_or_default();
            info!(machine = name, version = ?corrector.as_ref().map(|c| c.calibration().version), "serving machine");
            self.machines.insert(
                name.to_string(),
                Machine {
                    corrector,
                    points,
                    alarms,
                    _token: token,
                    _raw_keys: raw_keys,
                    ids,
                    extra: Extra::default(),
                    last_arrival: [None; 4],
                    stalled: [false; 4],
                    last_lag_ms: 0.0,
                },
            );
        }
        Ok(self.machines.get_mut(name).expect("inserted"))
    }

    async fn on_raw(&mut self, s: zenoh::sample::Sample) {
        let key = s.key_expr().as_str().to_string();
        let Some((machine, stream)) = Stream::parse_key(&self.cfg.prefix, &key) else {
            return;
        };
        let Some(sid) = wire::stream_id(stream) else {
            return;
        };
        let machine = machine.to_string();
        if !self.cfg.serves(&machine)
            || (!self.machines.contains_key(&machine)
                && self.machines.len() >= self.cfg.max_machines)
        {
            let n = self.refused.entry(machine.clone()).or_insert(0);
            if *n == 0 {
                warn!(machine = %machine, "refusing samples of a machine this service does not serve");
            }
            *n += 1;
            return;
        }
        if let Err(e) = self.machine(&machine).await {
            warn!(machine = %machine, error = %e, "cannot serve machine");
            return;
        }
        let (m, out) = (
            self.machines.get_mut(&machine).expect("served"),
            &mut self.out,
        );
        m.extra.messages += 1;
        m.last_arrival[sid as usize] = Some(Instant::now());
        if m.stalled[sid as usize] {
            m.stalled[sid as usize] = false;
            info!(machine = %machine, stream = sid.name(), "stream resumed");
        }
        let bytes = s.payload().to_bytes();
        let mut samples = Vec::new();
        match wire::decode_machine(sid, &bytes, &machine, &mut samples) {
            Ok(f) => m.extra.wrong_machine += f,
            Err(wire::WireError::Empty(_)) => m.extra.empty += 1,
            Err(e) => {
                if m.extra.malformed == 0 {
                    warn!(machine = %machine, stream = sid.name(), error = %e, "malformed message dropped");
                }
                m.extra.malformed += 1;
            }
        }
        let Some(corr) = m.corrector.as_mut() else {
            m.extra.no_calibration += samples.len() as u64;
            return;
        };
        let resets = corr.stats().clock_resets;
        for x in samples {
            corr.push(x, out);
        }
        if corr.stats().clock_resets > resets {
            warn!(machine = %machine, "controller clock reset: the machine's join, estimator and judgement restarted in the new time base");
        }
        if let Some(t) = corr.watermarks()[1] {
            let now_ns = std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map(|d| d.as_nanos() as i64)
                .unwrap_or(0);
            m.last_lag_ms = (now_ns - t) as f64 * 1e-6;
        }
        publish(m, out, &machine).await;
    }

    async fn flush(&mut self, machine: &str) {
        if let Some(m) = self.machines.get_mut(machine) {
            if let Some(c) = m.corrector.as_mut() {
                c.flush(&mut self.out);
                publish(m, &mut self.out, machine).await;
            }
        }
    }

    fn check_stalls(&mut self) {
        let limit = Duration::from_millis(self.cfg.stall_after_ms);
        for (name, m) in self.machines.iter_mut() {
            let Some(scale) = m.last_arrival[1] else {
                continue;
            };
            if scale.elapsed() > limit {
                continue; // nothing is coming at all: the machine is idle, not stalled
            }
            for k in [0usize, 2, 3] {
                let silent = m.last_arrival[k].is_none_or(|t| t.elapsed() > limit);
                if silent && !m.stalled[k] {
                    m.stalled[k] = true;
                    warn!(machine = %name, stream = scancorr_core::sample::StreamId::ALL[k].name(), "stream stalled: no samples while the scales keep coming; no points are produced past it");
                }
            }
        }
    }

    async fn on_status(&mut self, q: zenoh::query::Query) {
        let key = q.key_expr().as_str().to_string();
        let machine = key
            .trim_start_matches(&format!("{}/", self.cfg.prefix))
            .trim_end_matches("/status")
            .to_string();
        let body = match self.machines.get(&machine) {
            None => {
                json!({"machine": machine, "served": false, "refused_samples": self.refused.get(&machine).copied().unwrap_or(0)})
            }
            Some(m) => {
                let (stats, version, pending, wm) = match &m.corrector {
                    Some(c) => (
                        Some(c.stats().clone()),
                        Some(c.calibration().version),
                        c.pending(),
                        c.watermarks(),
                    ),
                    None => (None, None, [0; 4], [None; 4]),
                };
                let stalled: Vec<&str> = (0..4)
                    .filter(|k| m.stalled[*k])
                    .map(|k| scancorr_core::sample::StreamId::ALL[k].name())
                    .collect();
                json!({
                    "machine": machine,
                    "served": true,
                    "calibration_version": version,
                    "samples_in": stats.as_ref().map(|s| s.samples()).unwrap_or(0),
                    "points_out": stats.as_ref().map(|s| s.points_out).unwrap_or(0),
                    "points_flagged": stats.as_ref().map(|s| s.points_invalid).unwrap_or(0),
                    "dropped": stats.as_ref().map(|s| s.dropped_by_name().into_iter().map(|(k, v)| (k.to_string(), v)).collect::<BTreeMap<_, _>>()).unwrap_or_default(),
                    "alarms_raised": stats.as_ref().map(|s| s.alarms_raised).unwrap_or(0),
                    "clock_resets": stats.as_ref().map(|s| s.clock_resets).unwrap_or(0),
                    "messages": m.extra,
                    "pending": {"command": pending[0], "scale": pending[1], "probe": pending[2], "temperature": pending[3]},
                    "watermarks_ns": wm,
                    "stalled": stalled,
                    "stream_lag_ms": m.last_lag_ms,
                    "state_bytes": m.corrector.as_ref().map(|c| c.state_bytes()).unwrap_or(0),
                    "max_pending": m.corrector.as_ref().map(|c| c.max_pending()),
                })
            }
        };
        let _ = q.reply(q.key_expr().clone(), body.to_string()).await;
    }

    async fn on_calibration(&mut self, q: zenoh::query::Query) {
        let key = q.key_expr().as_str().to_string();
        let machine = key
            .trim_start_matches(&format!("{}/", self.cfg.prefix))
            .trim_end_matches("/calibration")
            .to_string();
        let reply = match q.payload() {
            Some(p) => self.put_calibration(&machine, &p.to_bytes()).await,
            None => {
                let params = q.parameters();
                if params.contains_key("history") {
                    self.store
                        .history(&machine)
                        .map(|h| serde_json::to_string(&h).expect("serialisable"))
                        .map_err(|e| e.to_string())
                } else if let Some(v) = params.get("version") {
                    match v.parse::<u64>() {
                        Ok(v) => match self.store.get(&machine, v) {
                            Ok(Some(c)) => Ok(c.to_json()),
                            Ok(None) => Err(format!(
                                "machine `{machine}` has no calibration version {v}"
                            )),
                            Err(e) => Err(e.to_string()),
                        },
                        Err(_) => Err(format!("version `{v}` is not a number")),
                    }
                } else {
                    match self.store.current(&machine) {
                        Ok(Some(c)) => Ok(c.to_json()),
                        Ok(None) => Err(format!("machine `{machine}` has no calibration")),
                        Err(e) => Err(e.to_string()),
                    }
                }
            }
        };
        let _ = match reply {
            Ok(body) => q.reply(q.key_expr().clone(), body).await,
            Err(e) => q.reply_err(e).await,
        };
    }

    async fn put_calibration(&mut self, machine: &str, bytes: &[u8]) -> Result<String, String> {
        let text = std::str::from_utf8(bytes)
            .map_err(|_| "the calibration document is not UTF-8 text".to_string())?;
        let cal = Calibration::from_json(text).map_err(|e| e.to_string())?;
        cal.check_machine(machine).map_err(|e| e.to_string())?;
        cal.build().map_err(|e| e.to_string())?;
        if !self.cfg.serves(machine) {
            return Err(format!("this service does not serve machine `{machine}`"));
        }
        let stored = self.store.put(cal).map_err(|e| e.to_string())?;
        let model = Arc::new(stored.build().map_err(|e| e.to_string())?);
        self.machine(machine).await.map_err(|e| e.to_string())?;
        let fresh = self.corrector(model.clone());
        let m = self.machines.get_mut(machine).expect("served");
        match m.corrector.as_mut() {
            Some(c) => c.set_model(model),
            None => m.corrector = Some(fresh),
        }
        m.ids = m
            .corrector
            .as_ref()
            .map(|c| c.effect_ids())
            .unwrap_or_default();
        info!(machine, version = stored.version, parent = ?stored.parent_version, "calibration applied");
        Ok(json!({"machine": machine, "version": stored.version, "parent_version": stored.parent_version}).to_string())
    }
}

async fn publish(m: &mut Machine, out: &mut Output, machine: &str) {
    if !out.points.is_empty() {
        // Written straight to protobuf (the same bytes prost makes, without a message per point).
        let mut bytes = Vec::with_capacity(out.points.len() * 320);
        wire::encode_points(&out.points, machine, &m.ids, &mut bytes);
        if let Err(e) = m.points.put(bytes).await {
            warn!(machine, error = %e, "publishing points failed");
        }
    }
    for a in &out.alarms {
        if a.raised {
            warn!(
                machine,
                axis = a.axis.name(),
                difference = a.difference,
                threshold = a.threshold,
                "estimator alarm raised"
            );
        } else {
            info!(machine, axis = a.axis.name(), "estimator alarm cleared");
        }
        if let Err(e) = m.alarms.put(wire::alarm(a, machine).encode_to_vec()).await {
            warn!(machine, error = %e, "publishing alarm failed");
        }
    }
    out.clear();
}
