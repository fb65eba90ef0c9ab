//! The correcting workers: each shard is a thread that owns its machines' correctors and
//! takes, in order, the jobs the control task routes to it — a machine's raw messages (decoded,
//! corrected, encoded and handed to the machine's [`Outbox`] here), calibration swaps, status
//! snapshots, the flush at shutdown. A machine lives on one shard for its lifetime, so its
//! samples are corrected in the order they arrived (live equals offline to the bit) and a
//! swap lands between two messages (no sample lost). Nothing on this path takes a lock shared
//! with another shard or with the control task; the outbox's lock is the machine's own,
//! shared only with its publishing thread.

use scancorr_core::calib::Model;
use scancorr_core::sample::StreamId;
use scancorr_core::wire;
use scancorr_core::{Corrector, Output, Stats};
use scancorr_proto::Message;
use serde_json::json;
use std::collections::{HashMap, VecDeque};
use std::sync::{Arc, Mutex};
use std::time::Instant;
use tracing::{info, warn};
use zenoh::Wait;

/// Counters the core does not see (message level).
#[derive(Debug, Default, Clone, serde::Serialize)]
pub(crate) struct Extra {
    pub(crate) malformed: u64,
    pub(crate) empty: u64,
    /// Batches tagged with another stream than their key's (v1.1 tag).
    pub(crate) wrong_stream: u64,
    /// Batches without the v1.1 stream tag (refused unless `accept_untagged_batches`).
    pub(crate) untagged: u64,
    pub(crate) wrong_machine: u64,
    pub(crate) no_calibration: u64,
    pub(crate) messages: u64,
    /// Messages on the machine's raw streams the service does not correct (v1.2
    /// `raw/distance`, `raw/stage`): skipped, not an error, not in `messages`.
    pub(crate) not_corrected: u64,
}

/// A machine's output on its way to the bus: a bounded queue drained by a blocking task, so
/// that a zenoh `put` never holds up the correcting task.
///
/// Points and alarms are published with `CongestionControl::Block`, so a subscriber that is
/// only busy loses nothing. A subscriber that stops reading holds up the drain of the machines
/// it subscribes to (zenoh waits up to 5 s, then closes that link); their outboxes fill, and
/// past `max_queued_bytes_per_machine` the newest batches are dropped and counted. Other
/// machines are not affected: their outboxes drain on their own threads, and zenoh's transmit
/// runtime has several workers (see `main.rs`: one worker would be held by the stalled
/// link's queue lock and stall every link).
pub(crate) struct Outbox {
    pub(crate) points: zenoh::pubsub::Publisher<'static>,
    pub(crate) alarms: zenoh::pubsub::Publisher<'static>,
    pub(crate) machine: String,
    pub(crate) max_bytes: usize,
    pub(crate) state: Mutex<OutState>,
    /// Wakes a draining task that lingers for more output.
    pub(crate) ready: std::sync::Condvar,
}

/// How long a drain task waits for more output before it ends: under steady output the next
/// batch comes sooner, and a waiting thread is cheaper to wake than a new task to start.
const LINGER: std::time::Duration = std::time::Duration::from_micros(500);

#[derive(Default)]
pub(crate) struct OutState {
    queue: VecDeque<Outgoing>,
    bytes: usize,
    draining: bool,
    /// The drain task waits for more (see [`LINGER`]).
    lingering: bool,
    published_points: u64,
    dropped_points: u64,
    dropped_alarms: u64,
    failed: u64,
    /// Raw message arrival → its points published.
    latency: crate::latency::Latency,
}

pub(crate) enum Outgoing {
    /// Encoded points, how many, when the message that completed them arrived.
    Points(Vec<u8>, u64, Option<Instant>),
    Alarm(Vec<u8>),
}

impl Outgoing {
    fn len(&self) -> usize {
        match self {
            Outgoing::Points(b, _, _) | Outgoing::Alarm(b) => b.len(),
        }
    }
}

impl Outbox {
    fn lock(&self) -> std::sync::MutexGuard<'_, OutState> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Queues `o`; drops it (newest first, counted) when the queue is over its bound.
    pub(crate) fn send(self: &Arc<Self>, o: Outgoing) {
        let mut st = self.lock();
        if st.bytes + o.len() > self.max_bytes && !st.queue.is_empty() {
            match o {
                Outgoing::Points(_, n, _) => st.dropped_points += n,
                Outgoing::Alarm(_) => st.dropped_alarms += 1,
            }
            return;
        }
        st.bytes += o.len();
        st.queue.push_back(o);
        if st.lingering {
            self.ready.notify_one();
        } else if !st.draining {
            st.draining = true;
            let me = self.clone();
            tokio::task::spawn_blocking(move || me.drain());
        }
    }

    fn drain(&self) {
        let mut st = self.lock();
        loop {
            let Some(o) = st.queue.pop_front() else {
                st.lingering = true;
                st = self
                    .ready
                    .wait_timeout(st, LINGER)
                    .unwrap_or_else(|e| e.into_inner())
                    .0;
                st.lingering = false;
                if st.queue.is_empty() {
                    st.draining = false;
                    return;
                }
                continue;
            };
            st.bytes -= o.len();
            drop(st);
            let (r, n, arrived) = match o {
                Outgoing::Points(b, n, at) => (self.points.put(b).wait(), n, at),
                Outgoing::Alarm(b) => (self.alarms.put(b).wait(), 0, None),
            };
            st = self.lock();
            match r {
                Ok(()) => {
                    st.published_points += n;
                    if let Some(at) = arrived {
                        st.latency.record(at.elapsed());
                    }
                }
                Err(e) => {
                    if st.failed == 0 {
                        warn!(machine = %self.machine, error = %e, "publishing failed");
                    }
                    st.failed += 1;
                }
            }
        }
    }

    pub(crate) fn idle(&self) -> bool {
        let st = self.lock();
        !st.draining && st.queue.is_empty()
    }

    pub(crate) fn figures(&self) -> serde_json::Value {
        let st = self.lock();
        json!({
            "points_published": st.published_points,
            "points_dropped_backpressure": st.dropped_points,
            "alarms_dropped_backpressure": st.dropped_alarms,
            "queued_bytes": st.bytes,
            "publish_failures": st.failed,
            // From a raw message's arrival to the publication of the points it completed, µs.
            "added_latency_us": st.latency.figures(),
        })
    }
}

/// A machine's state on its shard.
pub(crate) struct Core {
    pub(crate) corrector: Option<Corrector>,
    pub(crate) ids: Vec<String>,
    pub(crate) extra: Extra,
    /// Controller time of the newest point produced, ns.
    pub(crate) last_point_t_ns: Option<i64>,
    pub(crate) outbox: Arc<Outbox>,
}

/// What the corrector says about itself, for status and metrics.
#[derive(Debug, Clone)]
pub(crate) struct CoreSnap {
    pub(crate) stats: Stats,
    pub(crate) version: u64,
    pub(crate) pending: [usize; 4],
    pub(crate) watermarks: [Option<i64>; 4],
    pub(crate) inactive: Vec<String>,
    pub(crate) state_bytes: usize,
    pub(crate) max_pending: usize,
}

/// A machine's figures at one moment (taken on its shard, between two messages).
#[derive(Debug, Clone)]
pub(crate) struct Snap {
    /// None: no calibration (never put, or quarantined).
    pub(crate) core: Option<CoreSnap>,
    pub(crate) ids: Vec<String>,
    pub(crate) extra: Extra,
    pub(crate) last_point_t_ns: Option<i64>,
}

/// What the control task sends a shard.
pub(crate) enum Job {
    /// Serve a new machine.
    Add(String, Box<Core>),
    /// One raw message of a machine (its stream from the key), with its arrival.
    Raw {
        machine: String,
        stream: StreamId,
        /// The payload, copied out of zenoh's receive buffer (a queued `Sample` would hold
        /// the whole buffer it arrived in).
        bytes: Vec<u8>,
        arrived: Instant,
    },
    /// A new calibration (the first, or a swap between two messages).
    Model(String, Arc<Model>),
    /// Snapshots of the named machines (all of this shard's when `None`).
    Snap(
        Option<String>,
        tokio::sync::oneshot::Sender<Vec<(String, Snap)>>,
    ),
    /// Flush every machine's buffered samples (shutdown).
    Flush(tokio::sync::oneshot::Sender<()>),
}

/// A shard's settings.
#[derive(Clone)]
pub(crate) struct Limits {
    pub(crate) max_pending_samples: usize,
    pub(crate) tags: wire::Tags,
}

/// A corrector under the service's limits.
pub(crate) fn corrector(model: Arc<Model>, limits: &Limits) -> Corrector {
    let mut c = Corrector::with_model(model);
    c.limit_pending(Some(limits.max_pending_samples));
    c
}

/// Starts shard `k`: a thread that runs jobs until every sender is gone.
pub(crate) fn spawn(
    k: usize,
    limits: Limits,
    jobs: flume::Receiver<Job>,
) -> std::io::Result<std::thread::JoinHandle<()>> {
    // The outboxes' publishing tasks run on the service's runtime.
    let runtime = tokio::runtime::Handle::current();
    std::thread::Builder::new()
        .name(format!("shard-{k}"))
        .spawn(move || {
            let _runtime = runtime.enter();
            let mut machines: HashMap<String, Core> = HashMap::new();
            let mut out = Output::default();
            let mut samples = Vec::new();
            while let Ok(job) = jobs.recv() {
                match job {
                    Job::Add(name, core) => {
                        machines.insert(name, *core);
                    }
                    Job::Raw {
                        machine,
                        stream,
                        bytes,
                        arrived,
                    } => {
                        if let Some(m) = machines.get_mut(&machine) {
                            on_raw(
                                m,
                                &machine,
                                stream,
                                &bytes,
                                arrived,
                                &limits,
                                &mut samples,
                                &mut out,
                            );
                        }
                    }
                    Job::Model(name, model) => {
                        if let Some(m) = machines.get_mut(&name) {
                            match m.corrector.as_mut() {
                                Some(c) => c.set_model(model),
                                None => m.corrector = Some(corrector(model, &limits)),
                            }
                            m.ids = m
                                .corrector
                                .as_ref()
                                .map(|c| c.effect_ids())
                                .unwrap_or_default();
                        }
                    }
                    Job::Snap(which, reply) => {
                        let v = match which {
                            Some(n) => machines
                                .get(&n)
                                .map(|m| vec![(n, snap(m))])
                                .unwrap_or_default(),
                            None => machines.iter().map(|(n, m)| (n.clone(), snap(m))).collect(),
                        };
                        let _ = reply.send(v);
                    }
                    Job::Flush(done) => {
                        for (name, m) in machines.iter_mut() {
                            if let Some(c) = m.corrector.as_mut() {
                                c.flush(&mut out);
                                if let Some(p) = out.points.last() {
                                    m.last_point_t_ns = Some(p.t_ns);
                                }
                                publish(m, &mut out, name, None);
                            }
                        }
                        let _ = done.send(());
                    }
                }
            }
        })
}

fn snap(m: &Core) -> Snap {
    Snap {
        core: m.corrector.as_ref().map(|c| CoreSnap {
            stats: c.stats().clone(),
            version: c.calibration().version,
            pending: c.pending(),
            watermarks: c.watermarks(),
            inactive: c.inactive_effects(),
            state_bytes: c.state_bytes(),
            max_pending: c.max_pending(),
        }),
        ids: m.ids.clone(),
        extra: m.extra.clone(),
        last_point_t_ns: m.last_point_t_ns,
    }
}

/// One raw message: decoded (counted by what is wrong with it), corrected, published.
#[allow(clippy::too_many_arguments)]
fn on_raw(
    m: &mut Core,
    machine: &str,
    sid: StreamId,
    bytes: &[u8],
    arrived: Instant,
    limits: &Limits,
    samples: &mut Vec<scancorr_core::sample::Sample>,
    out: &mut Output,
) {
    m.extra.messages += 1;
    samples.clear();
    match wire::decode_machine_tagged(sid, bytes, machine, limits.tags, samples) {
        Ok(f) => m.extra.wrong_machine += f,
        Err(wire::WireError::Empty(_)) => m.extra.empty += 1,
        Err(e) => {
            let count = match e {
                wire::WireError::WrongStream { .. } => &mut m.extra.wrong_stream,
                wire::WireError::Untagged(_) => &mut m.extra.untagged,
                _ => &mut m.extra.malformed,
            };
            *count += 1;
            if *count == 1 {
                warn!(machine, stream = sid.name(), error = %e, "message dropped (further ones are counted on the status)");
            }
        }
    }
    let Some(corr) = m.corrector.as_mut() else {
        m.extra.no_calibration += samples.len() as u64;
        return;
    };
    let (resets, seq_resets) = (corr.stats().clock_resets, corr.stats().seq_resets);
    for x in samples.drain(..) {
        corr.push(x, out);
    }
    if corr.stats().clock_resets > resets {
        warn!(machine, "controller clock reset: the machine's join, estimator and judgement restarted in the new time base");
    }
    if corr.stats().seq_resets > seq_resets {
        warn!(machine, stream = sid.name(), "sequence numbers restarted (a counter wrap or restart): the stream's sequence continues from the new numbers");
    }
    if let Some(p) = out.points.last() {
        m.last_point_t_ns = Some(p.t_ns);
    }
    publish(m, out, machine, Some(arrived));
}

/// Hands what the core completed to the machine's outbox (never waits on the bus).
/// `arrived`: when the raw message that completed these points arrived (none for a flush).
fn publish(m: &mut Core, out: &mut Output, machine: &str, arrived: Option<Instant>) {
    if !out.points.is_empty() {
        // Written straight to protobuf (the same bytes prost makes, without a message per point).
        let mut bytes = Vec::with_capacity(out.points.len() * 320);
        wire::encode_points(&out.points, machine, &m.ids, &mut bytes);
        m.outbox
            .send(Outgoing::Points(bytes, out.points.len() as u64, arrived));
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
        m.outbox
            .send(Outgoing::Alarm(wire::alarm(a, machine).encode_to_vec()));
    }
    out.clear();
}
