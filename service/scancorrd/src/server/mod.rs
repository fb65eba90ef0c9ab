//! The async shell: zenoh in, the pure core, zenoh out. Each machine's state lives on one
//! correcting shard; zenoh's callback sends a served machine's raw messages straight there
//! ([`Routes`]), where each is decoded, pushed through that machine's [`Corrector`] and whatever
//! it completes is handed to that machine's [`Outbox`], which publishes it off the correcting
//! thread; this control task serves the rest (new machines, refusals, queries, the store): a subscriber that stops reading can delay or cost only the points of the machines it
//! subscribes to (dropped newest-first past `max_queued_bytes_per_machine`, counted), never
//! another machine's correction. Nothing on the way in waits: zenoh's callback never blocks
//! (a machine's messages over its share of its shard's queue are shed, counted), and this
//! task never waits on a shard (their snapshots are published; a status query's is awaited by
//! a task of its own; the watchdog is fed by its own task while this loop and every shard
//! turn, see `notify`). A calibration too costly per point to correct in real time is refused
//! at put (`cost`).
//!
//! Everything from outside is checked before it is used: key expressions and machine ids
//! (`scancorr_proto::names`), the stream tag of every raw batch, message and document sizes.
//! What is refused is counted per reason, never per name (a stranger cannot grow the
//! service's memory by inventing names), and logged at most once per [`LOG_EVERY`].
//!
//! This module holds the lifecycle (`run`: declarations, the control loop, the health reply,
//! shutdown) and the machines made served; `routing` routes raw messages (refusals, stalls),
//! `queries` answers the status and calibration queryables (with the audit records), and
//! `exposition` renders the metrics text.

use crate::config::Config;
use crate::input::Input;
use crate::routes::Routes;
use crate::shard::{Core, Handle, Job, Limits, Outbox, Snap};
use crate::store::Store;
use scancorr_core::wire;
use scancorr_proto::Stream;
use serde_json::json;
use std::collections::BTreeMap;
use std::future::Future;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tracing::{error, info, warn};
use zenoh::qos::CongestionControl;

mod exposition;
mod failover;
mod queries;
mod routing;

/// Refusals of one reason are logged at most this often (with the count since the last line).
pub const LOG_EVERY: Duration = Duration::from_secs(10);

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
    /// A name or a request refused (the message says which and why).
    #[error("{0}")]
    Refused(String),
    /// Another instance serves the machine (its liveliness token is on the bus).
    #[error("machine `{0}` is served by another scancorrd instance")]
    ServedElsewhere(String),
}

fn z<E: std::fmt::Display>(e: E) -> ServiceError {
    ServiceError::Zenoh(e.to_string())
}

/// Messages and requests refused before they reached a machine, counted per reason.
#[derive(Debug, Default, Clone, serde::Serialize)]
struct Refused {
    /// Raw samples of a machine this service does not serve.
    not_served: u64,
    /// Raw samples or puts of a new machine beyond `max_machines`.
    over_capacity: u64,
    /// Messages on a key whose machine id or stream is not valid (wildcards included).
    bad_key: u64,
    /// Queries whose key names no valid machine.
    bad_query: u64,
    /// Messages on raw streams the service does not correct (v1.2 `raw/distance` and
    /// `raw/stage`, measurements for calibration procedures) of machines it does not serve
    /// yet (a served machine counts them on its status): skipped, not an error.
    not_corrected: u64,
    /// Raw messages of a machine in this instance's assignment that another instance already
    /// serves (its liveliness token is on the bus): refused, so no point is published twice.
    served_elsewhere: u64,
    /// Raw messages of machines not served yet that arrived while the control task's queue
    /// was full (zenoh's callback never waits for it).
    control_busy: u64,
}

/// How long a machine found served by another instance stays refused before the bus is asked
/// again (when that instance has stopped, its token is gone and this one may take over).
pub const RECHECK_ELSEWHERE: Duration = Duration::from_secs(5);

/// Why a message or request was refused before it reached a machine.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
enum Refusal {
    NotServed,
    OverCapacity,
    BadKey,
    BadQuery,
}

impl Refusal {
    fn name(self) -> &'static str {
        match self {
            Refusal::NotServed => "not_served",
            Refusal::OverCapacity => "over_capacity",
            Refusal::BadKey => "bad_key",
            Refusal::BadQuery => "bad_query",
        }
    }
}

/// A rate-limited warning per refusal reason.
#[derive(Default)]
struct LogGate {
    last: BTreeMap<Refusal, (Instant, u64)>,
}

impl LogGate {
    /// Whether to log now; with the number of events since the last line logged.
    fn pass(&mut self, reason: Refusal) -> Option<u64> {
        let now = Instant::now();
        match self.last.get_mut(&reason) {
            Some((t, n)) if now.duration_since(*t) < LOG_EVERY => {
                *n += 1;
                None
            }
            Some((t, n)) => {
                let since = *n + 1;
                (*t, *n) = (now, 0);
                Some(since)
            }
            None => {
                self.last.insert(reason, (now, 0));
                Some(1)
            }
        }
    }
}

/// A served machine as the control task sees it; its corrector lives on its shard.
struct Machine {
    /// The shard that corrects it.
    shard: usize,
    /// Its slot on that shard.
    slot: usize,
    /// Why the stored calibration cannot be used (damaged in the store, or no longer valid):
    /// the machine is not corrected until a new calibration is put; the others are served.
    quarantined: Option<String>,
    outbox: Arc<Outbox>,
    /// Its liveliness tokens while this instance is active for it (none while standing by).
    tokens: Vec<zenoh::liveliness::LivelinessToken>,
    /// Fail-over (with `failover.enabled`): active or standby, since when, the others seen.
    fo: Option<failover::Fo>,
    /// The machine's raw key expressions, declared so that zenoh resolves an incoming
    /// message's route once, not by matching every key of every machine per message.
    _raw_keys: Vec<zenoh::key_expr::KeyExpr<'static>>,
    /// Messages on its measurement streams (`raw/distance`, `raw/stage`), skipped.
    not_corrected: u64,
    stalled: [bool; 4],
    /// Calibrations put for this machine since the service started.
    puts: u64,
    /// Its input's counters (shared with its route and its shard).
    input: Arc<Input>,
    /// What its calibration costs per point, measured on a reference point when it was put
    /// or loaded, µs.
    point_cost_us: Option<f64>,
}

struct State {
    cfg: Config,
    session: zenoh::Session,
    store: Store,
    machines: BTreeMap<String, Machine>,
    refused: Refused,
    log: LogGate,
    /// Whether the log said that the measurement streams are not corrected (said once).
    told_not_corrected: bool,
    /// Machines of this instance's assignment that another instance serves, with when the bus
    /// was last asked.
    elsewhere: BTreeMap<String, Instant>,
    /// The correcting workers (job queue, published snapshots, progress), and how many
    /// machines each corrects.
    shards: Vec<Handle>,
    on_shard: Vec<usize>,
    limits: Limits,
    routes: Arc<Routes>,
    /// The point buffers the shards encode into and zenoh gives back.
    pool: Arc<crate::shard::Pool>,
    /// The link to the router (client mode only).
    uplink: Option<crate::uplink::Uplink>,
    /// Fail-over events (liveliness of the other instances) to the control task.
    fo_tx: flume::Sender<failover::Event>,
}

/// Runs the service until `shutdown` resolves; then flushes every machine and closes the
/// session.
pub async fn run(cfg: Config, shutdown: impl Future<Output = ()>) -> Result<(), ServiceError> {
    cfg.validate()
        .map_err(crate::config::ConfigError::Invalid)?;
    let store = Store::open(&cfg.data_dir)?;
    let session = zenoh::open(cfg.zenoh()?).await.map_err(z)?;
    let prefix = cfg.prefix.clone();
    let metrics = match &cfg.metrics_listen {
        Some(a) => Some(crate::metrics::serve(a).map_err(ServiceError::Refused)?),
        None => None,
    };
    let notify = crate::notify::Notifier::from_env();
    info!(
        version = env!("CARGO_PKG_VERSION"),
        mode = %cfg.mode,
        prefix = %prefix,
        // Typed log values (JSON: strings, numbers, booleans; a list as one string), never a
        // Rust debug form such as `Some(1)`.
        listen = %cfg.listen.join(", "),
        connect = %cfg.connect.join(", "),
        machines = %cfg.machines.join(", "),
        allow_any_machine = cfg.allow_any_machine,
        data_dir = %cfg.data_dir.display(),
        zenoh_config = cfg.zenoh_config.as_ref().map(|p| p.display().to_string()),
        metrics = cfg.metrics_listen.as_deref(),
        subscribes = %cfg.machine_chunks().iter().map(|m| format!("{prefix}/{m}/raw/**")).collect::<Vec<_>>().join(", "),
        systemd_notify = notify.enabled(),
        "scancorrd started"
    );
    // Only this instance's assignment: with several instances on one router mesh, none
    // receives the others' raw traffic or answers for their machines. One queue for all the
    // subscriptions (zenoh's channel, bounded as its default handler is).
    let chunks = cfg.machine_chunks();
    // Each message with the instant it arrived (zenoh's callback), where the latency the
    // service adds starts.
    let (raw_tx, raw) = flume::bounded::<(Instant, zenoh::sample::Sample)>(256);
    let (calib_tx, calib) = flume::bounded(64);
    let (status_tx, status) = flume::bounded(64);
    let mut declared = Declared::default();
    let (fo_tx, fo_rx) = flume::unbounded();
    let routes = Arc::new(Routes::new(&prefix));
    for m in &chunks {
        let tx = raw_tx.clone();
        let routes = routes.clone();
        declared._subscribers.push(
            session
                .declare_subscriber(format!("{prefix}/{m}/raw/**"))
                .callback(move |s| {
                    // Never waits: a full queue sheds (counted), it does not hold up the link.
                    let arrived = Instant::now();
                    if let Some(s) = routes.route(s, arrived) {
                        if let Err(flume::TrySendError::Full((_, s))) = tx.try_send((arrived, s)) {
                            routes.busy(&s);
                        }
                    }
                })
                .await
                .map_err(z)?,
        );
        declared._queryables.push(
            session
                .declare_queryable(format!("{prefix}/{m}/calibration"))
                .with((calib_tx.clone(), calib.clone()))
                .await
                .map_err(z)?,
        );
        declared._queryables.push(
            session
                .declare_queryable(format!("{prefix}/{m}/calibration/write"))
                .with((calib_tx.clone(), calib.clone()))
                .await
                .map_err(z)?,
        );
        declared._queryables.push(
            session
                .declare_queryable(format!("{prefix}/{m}/status"))
                .with((status_tx.clone(), status.clone()))
                .await
                .map_err(z)?,
        );
    }
    drop((raw_tx, calib_tx, status_tx));
    // Liveness and readiness on the bus: every instance answers (`@` keeps the key apart from
    // any machine's).
    let health = session
        .declare_queryable(scancorr_proto::health_key(&prefix))
        .await
        .map_err(z)?;
    let started = Instant::now();
    let workers = cfg.workers();
    let cfg_max_pending = cfg.max_pending_samples;
    let cfg_shed_after_ms = cfg.shed_after_ms;
    let cfg_breakdown = cfg.publish_breakdown;
    let tags = if cfg.accept_untagged_batches {
        wire::Tags::AllowUntagged
    } else {
        wire::Tags::Require
    };
    info!(workers, "correcting on {workers} worker shard(s)");
    let mut st = State {
        cfg,
        session: session.clone(),
        store,
        machines: BTreeMap::new(),
        refused: Refused::default(),
        log: LogGate::default(),
        told_not_corrected: false,
        elsewhere: BTreeMap::new(),
        shards: vec![],
        on_shard: vec![0; workers],
        routes: routes.clone(),
        // Enough buffers for what a shard's lanes have in flight at once.
        pool: crate::shard::Pool::new(16 * workers),
        limits: Limits {
            max_pending_samples: cfg_max_pending,
            tags,
            shed_after: Duration::from_millis(cfg_shed_after_ms),
            breakdown: cfg_breakdown,
        },
        uplink: None,
        fo_tx,
    };
    if st.cfg.mode == "client" {
        let n = session.info().routers_zid().await.count();
        st.uplink = Some(crate::uplink::Uplink::new(n, Instant::now()));
    }
    let mut threads = vec![];
    for k in 0..workers {
        // Unbounded queues: nothing that sends to a shard waits. Each machine's share is
        // bounded where its messages arrive (`max_input_bytes_per_machine`), and a shard that
        // falls behind real time sheds the work of the machine that costs it (see `shard`).
        let (h, thread) = crate::shard::spawn(k, st.limits.clone())
            .map_err(|e| ServiceError::Refused(format!("starting correcting worker {k}: {e}")))?;
        threads.push(thread);
        st.shards.push(h);
    }
    // Machines with a stored calibration are served from the start; one whose stored
    // calibration is damaged is quarantined (named in the log and on its status) while the
    // others start.
    for m in st.store.machines()? {
        if st.cfg.serves(&m) && st.machines.len() < st.cfg.max_machines {
            match st.machine(&m).await {
                Ok(_) | Err(ServiceError::ServedElsewhere(_)) => {}
                Err(e) => return Err(e),
            }
        }
    }
    notify.send(&format!(
        "READY=1\nSTATUS=serving {} machine(s)",
        st.machines.len()
    ));
    // The watchdog is fed from its own task, and only while this loop and every shard turn:
    // neither waits on the other, so a shard that stops (or a loop that does) starves it.
    let control_beat = crate::shard::Beat::new();
    let notify = Arc::new(notify);
    let watchdog = tokio::spawn(crate::notify::watchdog(
        notify.clone(),
        control_beat.clone(),
        st.shards.iter().map(|h| h.beat.clone()).collect(),
    ));
    let mut last_metrics = Instant::now() - Duration::from_secs(10);
    let mut through = Throughput::new(st.totals());
    tokio::pin!(shutdown);
    let mut tick = tokio::time::interval(Duration::from_millis(250));
    loop {
        // Each turn of the loop (each event handled) proves that it turns.
        control_beat.beat();
        tokio::select! {
            biased;
            _ = &mut shutdown => break,
            q = calib.recv_async() => match q {
                Ok(q) => st.on_calibration(q).await,
                Err(e) => { warn!(error = %e, "calibration queryable closed"); break }
            },
            q = status.recv_async() => if let Ok(q) = q { st.on_status(q).await },
            q = health.recv_async() => if let Ok(q) = q {
                // The link as it is now (a query can arrive before the tick sees a return).
                st.watch_uplink().await;
                let quarantined: Vec<&String> = st.machines.iter().filter(|(_, m)| m.quarantined.is_some()).map(|(k, _)| k).collect();
                let mut body = json!({
                    "zid": st.session.zid().to_string(),
                    "version": env!("CARGO_PKG_VERSION"),
                    "ready": true,
                    "uptime_s": started.elapsed().as_secs_f64().round(),
                    "machines": st.machines.len(),
                    "quarantined": quarantined,
                    "workers": st.shards.len(),
                    "assignment": if st.cfg.allow_any_machine { vec!["*".to_string()] } else { st.cfg.machines.clone() },
                    "served_elsewhere": st.elsewhere.keys().collect::<Vec<_>>(),
                    // With fail-over: per machine, active or standby and since when.
                    "failover": st.failover_health(),
                    "refused": st.refused_now(),
                    "router_link": st.uplink.as_ref().map(|u| json!({
                        "routers": u.routers(),
                        "losses": u.losses(),
                        "down_s": (u.down_s(Instant::now()) * 10.0).round() / 10.0,
                    })),
                });
                // The samples taken in, as the shards have them now: each publishes its
                // snapshots when asked, awaited by a task of its own (bounded; a shard that
                // does not answer is counted as last published).
                let shards: Vec<_> = st.shards.iter().map(|h| (h.jobs.clone(), h.board.clone(), h.snaps_asked.clone())).collect();
                tokio::spawn(async move {
                    use std::sync::atomic::Ordering::AcqRel;
                    let mut waits = vec![];
                    for (jobs, _, asked) in &shards {
                        if asked.fetch_add(1, AcqRel) >= MAX_SNAPS_ASKED {
                            asked.fetch_sub(1, AcqRel);
                            continue;
                        }
                        let (tx, rx) = tokio::sync::oneshot::channel();
                        if jobs.send(Job::Publish(tx)).is_ok() {
                            waits.push(rx);
                        }
                    }
                    let _ = tokio::time::timeout(STATUS_WAIT, async {
                        for w in waits {
                            let _ = w.await;
                        }
                    })
                    .await;
                    let boards: Vec<_> = shards.into_iter().map(|(_, b, _)| b).collect();
                    body["samples_in"] = totals(&boards).0.into();
                    // Machines streaming with no calibration in use, and their samples not
                    // corrected.
                    let uncalibrated: BTreeMap<String, u64> = boards
                        .iter()
                        .flat_map(|b| b.all())
                        .filter(|(_, s)| s.core.is_none() && s.extra.no_calibration > 0)
                        .map(|(m, s)| (m, s.extra.no_calibration))
                        .collect();
                    body["uncorrected_samples"] = uncalibrated.values().sum::<u64>().into();
                    body["uncalibrated"] = json!(uncalibrated);
                    let _ = q.reply(q.key_expr().clone(), body.to_string()).await;
                });
            },
            e = fo_rx.recv_async() => if let Ok(e) = e { st.on_failover(e).await },
            s = raw.recv_async() => match s {
                Ok((at, s)) => st.on_raw(s, at).await,
                Err(e) => { warn!(error = %e, "raw subscriber closed"); break }
            },
            _ = tick.tick() => {
                st.check_stalls();
                if st.cfg.failover.enabled {
                    st.check_failover();
                }
                st.watch_uplink().await;
                if let Some(m) = &metrics {
                    if last_metrics.elapsed() >= Duration::from_secs(1) {
                        let text = st.metrics();
                        if let Ok(mut t) = m.lock() {
                            *t = text;
                        }
                        last_metrics = Instant::now();
                    }
                }
                if st.cfg.throughput_log_s > 0 && through.at.elapsed() >= Duration::from_secs(st.cfg.throughput_log_s) {
                    let now = st.totals();
                    let dt = through.at.elapsed().as_secs_f64();
                    info!(
                        machines = st.machines.len(),
                        samples_per_s = ((now.0 - through.last.0) as f64 / dt).round(),
                        points_per_s = ((now.1 - through.last.1) as f64 / dt).round(),
                        dropped = now.2 - through.last.2,
                        "throughput"
                    );
                    through = Throughput::new(now);
                }
            }
        }
    }
    watchdog.abort();
    notify.send("STOPPING=1");
    st.hand_over_at_shutdown();
    st.routes.close();
    info!("shutting down: flushing buffered samples");
    // Every shard finishes what is queued and flushes, at once; bounded, so a shard that does
    // not come back cannot keep the service from stopping.
    let mut waits = vec![];
    for h in &st.shards {
        let (done, wait) = tokio::sync::oneshot::channel();
        if h.jobs.send(Job::Flush(done)).is_ok() {
            waits.push(wait);
        }
    }
    let flushed = tokio::time::timeout(Duration::from_secs(10), async {
        for w in waits {
            let _ = w.await;
        }
    })
    .await;
    if flushed.is_err() {
        warn!("the correcting workers did not flush within 10 s: stopping without them");
    }
    // What was corrected is published before the session closes (bounded: a subscriber that
    // does not read cannot keep the service from stopping).
    let t0 = Instant::now();
    while !st.machines.values().all(|m| m.outbox.idle()) && t0.elapsed() < Duration::from_secs(5) {
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    drop(st);
    if flushed.is_ok() {
        for t in threads {
            let _ = t.join();
        }
    }
    // A peer that stopped reading cannot be told goodbye: closing is bounded, and a close
    // that times out is not a failure of the service.
    match tokio::time::timeout(Duration::from_secs(5), session.close()).await {
        Ok(Ok(())) => {}
        Ok(Err(e)) => warn!(error = %e, "zenoh session did not close cleanly"),
        Err(_) => warn!("zenoh session did not close within 5 s"),
    }
    info!("scancorrd stopped");
    Ok(())
}

/// The throughput line's last totals: (samples in, points out, samples dropped).
struct Throughput {
    at: Instant,
    last: (u64, u64, u64),
}

impl Throughput {
    fn new(last: (u64, u64, u64)) -> Throughput {
        Throughput {
            at: Instant::now(),
            last,
        }
    }
}

impl State {
    /// Looks at the session's routers (client mode): a loss or a return is logged and counted.
    async fn watch_uplink(&mut self) {
        if self.uplink.is_some() {
            let n = self.session.info().routers_zid().await.count();
            let mut lost = false;
            if let Some(u) = &mut self.uplink {
                lost = u.routers() > 0 && n == 0;
                u.observe(n, Instant::now());
            }
            // Fail-over: cut off, this instance steps back (see `failover`).
            if lost && self.cfg.failover.enabled {
                self.lost_bus().await;
            }
        }
    }

    /// Samples in, points out and samples dropped over every machine (their latest published
    /// snapshots: never waits on a shard).
    fn totals(&self) -> (u64, u64, u64) {
        let boards: Vec<_> = self.shards.iter().map(|h| h.board.clone()).collect();
        totals(&boards)
    }

    /// Every machine's latest published snapshot.
    fn snaps(&self) -> BTreeMap<String, Snap> {
        self.shards.iter().flat_map(|h| h.board.all()).collect()
    }

    /// Whether another instance serves `name`: its liveliness token is on the bus. Asked at
    /// most once per [`RECHECK_ELSEWHERE`] per machine; said loudly the first time.
    async fn served_elsewhere(&mut self, name: &str) -> bool {
        if let Some(t) = self.elsewhere.get(name) {
            if t.elapsed() < RECHECK_ELSEWHERE {
                return true;
            }
        }
        let key = format!("{}/{name}/scancorrd", self.cfg.prefix);
        let found = self.token_on_bus(name).await;
        if found {
            if self
                .elsewhere
                .insert(name.to_string(), Instant::now())
                .is_none()
            {
                error!(machine = name, token = %key, "machine already served by another scancorrd instance (its liveliness token is on the bus): this instance refuses it, so no point is published twice; give each instance a disjoint `machines` assignment");
            }
        } else if self.elsewhere.remove(name).is_some() {
            info!(
                machine = name,
                "the other instance no longer serves this machine: taking it over"
            );
        }
        found
    }

    async fn machine(&mut self, name: &str) -> Result<&mut Machine, ServiceError> {
        if !self.machines.contains_key(name) {
            // Every name that reaches here passed the grammar; checked again because it
            // becomes part of key expressions.
            scancorr_proto::names::check_machine(name)
                .map_err(|e| ServiceError::Refused(e.to_string()))?;
            // With fail-over, a machine another instance serves is stood by for.
            let role = if !self.cfg.failover.enabled {
                if self.served_elsewhere(name).await {
                    return Err(ServiceError::ServedElsewhere(name.to_string()));
                }
                failover::Role::Active
            } else if self.token_on_bus(name).await {
                info!(machine = name, "machine served by another instance: standing by for it (hot standby: corrected, not published, until that instance goes)");
                failover::Role::Standby
            } else {
                failover::Role::Active
            };
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
            let alarms = crate::shard::Alarms::new(
                self.session.clone(),
                zenoh::key_expr::KeyExpr::try_from(Stream::Alarms.key(p, name)).map_err(z)?,
            );
            let since_ms = failover::now_ms();
            let tokens = match role {
                failover::Role::Active => self.active_tokens(name, since_ms).await?,
                failover::Role::Standby => vec![],
            };
            let mut raw_keys = Vec::with_capacity(4);
            for st in scancorr_core::sample::StreamId::ALL {
                raw_keys.push(
                    self.session
                        .declare_keyexpr(format!("{p}/{name}/raw/{}", st.name()))
                        .await
                        .map_err(z)?,
                );
            }
            let mut point_cost_us = None;
            let (corrector, quarantined) = match self.store.current(name) {
                Ok(Some(c)) => match c.build() {
                    Ok(m) => {
                        point_cost_us = Some(crate::cost::point_cost_us(&m, crate::cost::AT_START));
                        (
                            Some(crate::shard::corrector(Arc::new(m), &self.limits)),
                            None,
                        )
                    }
                    Err(e) => (
                        None,
                        Some(format!(
                            "stored calibration version {} is not valid: {e}",
                            c.version
                        )),
                    ),
                },
                Ok(None) => {
                    warn!(machine = name, "no calibration for this machine yet: samples are counted, not corrected, until one is put");
                    (None, None)
                }
                Err(e) => (None, Some(e.to_string())),
            };
            if let Some(q) = &quarantined {
                error!(machine = name, reason = %q, "machine quarantined: not corrected until a new calibration is put; the other machines are served");
            }
            // A stored calibration costlier than the limit is served (refusing it would stop
            // correcting the machine), and said: its shard sheds its work if it falls behind.
            if let Some(us) = point_cost_us {
                let limit = self.cfg.max_point_cost_us;
                if limit > 0.0 && us > limit {
                    error!(machine = name, point_cost_us = us.round(), limit_us = limit, "the stored calibration costs more CPU per point than `max_point_cost_us`: it is served, and the machine's messages are shed when its shard falls behind real time");
                }
            }
            info!(
                machine = name,
                version = corrector.as_ref().map(|c| c.settings().version),
                calibrated = corrector.is_some(),
                "serving machine"
            );
            let outbox = Arc::new(Outbox::new(
                points,
                alarms,
                name.to_string(),
                self.cfg.max_queued_bytes_per_machine,
                self.pool.clone(),
                self.cfg.failover.enabled,
            ));
            let fo = if self.cfg.failover.enabled {
                if role == failover::Role::Standby {
                    outbox.hold(self.cfg.failover.max_held_bytes);
                }
                Some(self.watch(name, role, since_ms, outbox.clone()).await?)
            } else {
                None
            };
            let input = Arc::new(Input::new(self.cfg.max_input_bytes_per_machine));
            // The shard with the fewest machines corrects it.
            let shard = (0..self.shards.len())
                .min_by_key(|k| self.on_shard[*k])
                .expect("at least one shard");
            let slot = self.on_shard[shard];
            self.shards[shard]
                .jobs
                .send(Job::Add {
                    slot,
                    name: name.to_string(),
                    core: Box::new(Core::new(corrector, outbox.clone(), input.clone())),
                })
                .map_err(|_| ServiceError::Refused("the correcting workers have stopped".into()))?;
            self.on_shard[shard] += 1;
            // From now on its raw messages go straight to its shard (after the `Add`).
            self.routes
                .add(name, self.shards[shard].jobs.clone(), slot, input.clone());
            self.machines.insert(
                name.to_string(),
                Machine {
                    shard,
                    slot,
                    quarantined,
                    outbox,
                    tokens,
                    fo,
                    _raw_keys: raw_keys,
                    not_corrected: 0,
                    stalled: [false; 4],
                    puts: 0,
                    input,
                    point_cost_us,
                },
            );
        }
        Ok(self.machines.get_mut(name).expect("inserted"))
    }

    /// The refusals, with the messages zenoh's callback shed for want of room at the control
    /// task.
    fn refused_now(&self) -> Refused {
        Refused {
            control_busy: self.routes.busy_count(),
            bad_key: self.refused.bad_key + self.routes.busy_bad_key_count(),
            ..self.refused.clone()
        }
    }

    /// Whether a query about `machine` is for another instance to answer (it serves the
    /// machine): this one stays silent, so the asker gets that instance's answer alone.
    fn answered_elsewhere(&self, machine: &str) -> bool {
        match self.machines.get(machine) {
            // A standby stays silent: the active instance answers (and takes the puts).
            Some(m) => {
                m.fo.as_ref()
                    .is_some_and(|f| f.role == failover::Role::Standby)
            }
            None => self.elsewhere.contains_key(machine),
        }
    }
}

/// Samples in, points out and samples dropped over every machine of `boards`.
fn totals(boards: &[Arc<crate::shard::Board>]) -> (u64, u64, u64) {
    let mut t = (0, 0, 0);
    for b in boards {
        for (_, s) in b.all() {
            if let Some(c) = &s.core {
                t.0 += c.stats.samples();
                t.1 += c.stats.points_out;
                t.2 += c.stats.dropped_total();
            }
        }
    }
    t
}

/// How long a status query waits for its machine's shard to take a snapshot before it is
/// answered with the latest published one.
const STATUS_WAIT: Duration = Duration::from_millis(1000);

/// At most this many snapshots asked of one shard and not taken yet (a shard that does not
/// turn is not sent more).
const MAX_SNAPS_ASKED: usize = 32;

/// The declarations of an instance's assignment, held for its lifetime.
#[derive(Default)]
struct Declared {
    _subscribers: Vec<zenoh::pubsub::Subscriber<()>>,
    _queryables: Vec<zenoh::query::Queryable<flume::Receiver<zenoh::query::Query>>>,
}
