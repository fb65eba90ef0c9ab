//! The correcting workers: each shard is a thread that owns its machines' correctors and
//! takes, in order per machine, the work routed to it — a machine's raw messages (decoded,
//! corrected, encoded and handed to the machine's [`Outbox`] here), calibration swaps, status
//! snapshots, the flush at shutdown. A machine lives on one shard for its lifetime, so its
//! samples are corrected in the order they arrived (live equals offline to the bit) and a
//! swap lands between two messages (no sample lost).
//!
//! Nothing waits on a shard: its queue is unbounded (each machine's share is bounded where
//! its messages arrive, see [`Input`]); it sorts what arrives into its machines' queues and
//! serves the machines with work by deficit round robin on time, so a machine whose messages
//! take long (a costly model) waits behind the others instead of holding them up, and its own
//! messages that waited longer than `shed_after_ms` are shed, counted and said. It publishes
//! its machines' snapshots ([`Board`]) and beats as it turns ([`Beat`], what feeds the
//! watchdog). Nothing on this path takes a lock shared
//! with another shard or with the control task; the outbox's lock is the machine's own,
//! shared only with its publishing thread.

use crate::input::Input;
use crate::outgoing::{Mark, Outgoing, Span};
use scancorr_core::calib::Model;
use scancorr_core::sample::StreamId;
use scancorr_core::wire;
use scancorr_core::{Corrector, Output, Stats};
use scancorr_proto::Message;
use serde_json::json;
use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};
use tracing::{info, warn};
use zenoh::qos::CongestionControl;
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
    /// Samples that arrived while the machine had no calibration in use (never put, or
    /// quarantined): counted, not corrected (its status also shows them as
    /// `uncorrected_samples`).
    pub(crate) no_calibration: u64,
    pub(crate) messages: u64,
    /// Messages on the machine's raw streams the service does not correct (v1.2
    /// `raw/distance`, `raw/stage`): skipped, not an error, not in `messages`.
    pub(crate) not_corrected: u64,
}

/// A machine's output on its way to the bus: a bounded queue that its shard's publishing
/// [`Lanes`] drain, so that a zenoh `put` never holds up the correcting thread.
///
/// Points and alarms are published with `CongestionControl::Block`, so a subscriber that is
/// only busy loses nothing (behind a router, the router forwards them to each subscriber
/// droppable: `deploy/router.json5`; the one link to the router stays lossless). A subscriber that stops reading holds up the drain of the machines
/// it subscribes to (zenoh waits up to 5 s, then closes that link); their outboxes fill, and
/// past `max_queued_bytes_per_machine` the newest batches are dropped and counted. Other
/// machines are not affected: a lane held up in a `put` for [`STUCK`] while other output
/// waits gets another lane beside it, and zenoh's transmit runtime has several workers (see
/// `main.rs`: one worker would be held by the stalled link's queue lock and stall every link).
pub(crate) struct Outbox {
    points: zenoh::pubsub::Publisher<'static>,
    /// Alarms are rare: put on the session under their key (as a publisher would, with
    /// `Block`), not through a publisher kept per machine; the key is declared on the
    /// machine's first alarm (see [`Alarms`]).
    alarms: Alarms,
    machine: String,
    max_bytes: usize,
    state: Mutex<OutState>,
    /// Where the buffers of its published points go back to.
    pool: Arc<Pool>,
    /// Mirrors `state.hold.holding` (read without the lock).
    holding: std::sync::atomic::AtomicBool,
    /// Not flushed at shutdown (handed over to a standby).
    keep_tail: std::sync::atomic::AtomicBool,
    /// Fail-over on: each publication of points carries its last point's [`Mark`].
    marks: bool,
}

/// Where a machine's alarms are put.
///
/// The key is declared to zenoh on the machine's first alarm and kept: zenoh caches the
/// route of a declared key, but computes the route of an undeclared one on every `put` by
/// matching it against every key it knows — a cost that grows with the fleet. When the
/// machines of a fleet run the same program, their alarms come at the same moment: at 300
/// machines that burst held the publishing lanes for about 0.3 s (perf), at 700 and more for
/// seconds. A machine that never alarms pays nothing for the declaration (about 2 KB).
pub(crate) struct Alarms {
    session: zenoh::Session,
    key: zenoh::key_expr::KeyExpr<'static>,
    declared: std::sync::OnceLock<zenoh::key_expr::KeyExpr<'static>>,
}

impl Alarms {
    pub(crate) fn new(session: zenoh::Session, key: zenoh::key_expr::KeyExpr<'static>) -> Self {
        Alarms {
            session,
            key,
            declared: std::sync::OnceLock::new(),
        }
    }

    /// Puts one alarm (`Block`), under the declared key once it could be declared.
    fn put(&self, b: Vec<u8>) -> zenoh::Result<()> {
        let key = match self.declared.get() {
            Some(k) => k,
            None => match self.session.declare_keyexpr(self.key.clone()).wait() {
                Ok(k) => self.declared.get_or_init(|| k),
                // Not declared: put under the plain key (same key, same subscribers).
                Err(_) => &self.key,
            },
        };
        self.session
            .put(key, b)
            .congestion_control(CongestionControl::Block)
            .express(true)
            .wait()
    }
}

/// Point buffers, reused: a publication's buffer comes back here once zenoh has copied it
/// into its transmit batch (or dropped it), and the next batch of points of any machine is
/// encoded into it. No allocation, growth or fresh pages per batch, and the room of the
/// output in flight is shared by the machines instead of each keeping its own.
pub(crate) struct Pool {
    free: Mutex<Vec<Vec<u8>>>,
    keep: usize,
}

/// Buffers with more room than this are not kept (a batch is at most [`JOIN_UP_TO`] plus
/// one message's points).
const POOL_MAX_ROOM: usize = 2 * JOIN_UP_TO;

impl Pool {
    /// A pool keeping at most `keep` buffers.
    pub(crate) fn new(keep: usize) -> Arc<Pool> {
        Arc::new(Pool {
            free: Mutex::new(Vec::with_capacity(keep)),
            keep,
        })
    }

    /// An empty buffer with room for at least `room` bytes.
    fn get(&self, room: usize) -> Vec<u8> {
        let b = self.free.lock().unwrap_or_else(|e| e.into_inner()).pop();
        let mut b = b.unwrap_or_default();
        b.reserve(room);
        b
    }

    /// Takes a buffer back (kept when there is place for it and it is not too large).
    fn put(&self, mut b: Vec<u8>) {
        if b.capacity() == 0 || b.capacity() > POOL_MAX_ROOM {
            return;
        }
        b.clear();
        let mut free = self.free.lock().unwrap_or_else(|e| e.into_inner());
        if free.len() < self.keep {
            free.push(b);
        }
    }
}

/// A buffer of points on its way through zenoh, back to its pool when zenoh lets go of it.
struct Pooled {
    buf: Vec<u8>,
    pool: Arc<Pool>,
}

impl AsRef<[u8]> for Pooled {
    fn as_ref(&self) -> &[u8] {
        &self.buf
    }
}

impl Drop for Pooled {
    fn drop(&mut self) {
        self.pool.put(std::mem::take(&mut self.buf));
    }
}

/// Point batches queued for one machine are joined into one publication up to this size (the
/// bytes of two `CorrectedPointBatch`es one after the other are the batch of both): a lane
/// that fell behind catches up with fewer, larger messages.
const JOIN_UP_TO: usize = 48 * 1024;

#[derive(Default)]
struct OutState {
    queue: VecDeque<Outgoing>,
    bytes: usize,
    /// Handed to a lane (waiting for one, or being drained).
    queued: bool,
    published_points: u64,
    dropped_points: u64,
    dropped_alarms: u64,
    failed: u64,
    /// Raw message arrival → its points published.
    latency: crate::latency::Latency,
    /// The newest `seq` published.
    last_seq: Option<u64>,
    /// A hot standby's withheld output (`failover`; never holding without it).
    hold: crate::standby::Hold,
}

impl Outbox {
    pub(crate) fn new(
        points: zenoh::pubsub::Publisher<'static>,
        alarms: Alarms,
        machine: String,
        max_bytes: usize,
        pool: Arc<Pool>,
        marks: bool,
    ) -> Outbox {
        Outbox {
            marks,
            points,
            alarms,
            machine,
            max_bytes,
            state: Mutex::default(),
            pool,
            holding: Default::default(),
            keep_tail: Default::default(),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, OutState> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Queues `o`; drops it (newest first, counted) when the queue is over its bound. True
    /// when the outbox must be handed to a lane (it was not waiting for one or being drained).
    fn send(&self, o: Outgoing) -> bool {
        let mut st = self.lock();
        if st.bytes + o.len() > self.max_bytes && !st.queue.is_empty() {
            match o {
                Outgoing::Points(b, n, _, _) => {
                    st.dropped_points += n;
                    drop(st);
                    self.pool.put(b);
                }
                Outgoing::Alarm(_) => st.dropped_alarms += 1,
            }
            return false;
        }
        st.bytes += o.len();
        match (st.queue.back_mut(), o) {
            (Some(Outgoing::Points(b, n, at, span)), Outgoing::Points(more, m, later, next))
                if b.len() + more.len() <= JOIN_UP_TO =>
            {
                b.extend_from_slice(&more);
                *n += m;
                *span = span.then(next);
                *at = at.or(later);
                let queued = !std::mem::replace(&mut st.queued, true);
                drop(st);
                self.pool.put(more);
                return queued;
            }
            (_, o) => st.queue.push_back(o),
        }
        !std::mem::replace(&mut st.queued, true)
    }

    /// Publishes what is queued, until the queue is empty or, once [`JOIN_UP_TO`] bytes are
    /// out, other outboxes wait for the lane (`lanes`): true then, the lane hands it back to
    /// the end of the line. A standby's backlog published at a take-over thus goes out a
    /// share per machine in turn, not one machine's whole backlog before the next one's first
    /// point. `progress` counts each step.
    fn drain(&self, lanes: &Lanes) -> bool {
        let progress = &lanes.progress;
        let mut sent = 0usize;
        let mut st = self.lock();
        while let Some(o) = st.queue.pop_front() {
            if sent >= JOIN_UP_TO && lanes.others_wait() {
                st.queue.push_front(o);
                return true;
            }
            st.bytes -= o.len();
            if st.hold.holding {
                // A standby: kept, not published (see `standby`).
                st.hold.keep(o);
                continue;
            }
            drop(st);
            let (r, n, arrived, last) = match o {
                Outgoing::Points(b, n, at, span) => {
                    sent += b.len();
                    // Zero-copy: zenoh reads the buffer, and hands it back to the pool when
                    // it is done with it.
                    let b = bytes::Bytes::from_owner(Pooled {
                        buf: b,
                        pool: self.pool.clone(),
                    });
                    // With fail-over, the last point's mark rides along as the attachment:
                    // a standby that receives the publication knows which points it holds
                    // without decoding them (see `standby`).
                    let put = self.points.put(b);
                    let put = if self.marks {
                        put.attachment(Mark::last_of(&span).to_bytes().to_vec())
                    } else {
                        put
                    };
                    (put.wait(), n, at, Some(span.seq.1))
                }
                Outgoing::Alarm(b) => (self.alarms.put(b), 0, None, None),
            };
            progress.fetch_add(1, Ordering::Relaxed);
            st = self.lock();
            match r {
                Ok(()) => {
                    st.published_points += n;
                    st.last_seq = last.or(st.last_seq);
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
        st.queued = false;
        false
    }

    /// Withholds its output from now on (a hot standby): at most `max_bytes` held.
    pub(crate) fn hold(&self, max_bytes: usize) {
        let mut st = self.lock();
        st.hold.start(max_bytes);
        self.holding.store(true, Ordering::Relaxed);
    }

    /// Withholding (a hot standby).
    pub(crate) fn holding(&self) -> bool {
        self.holding.load(Ordering::Relaxed)
    }

    /// The active instance was seen to publish points up to this one.
    pub(crate) fn seen(&self, m: Mark) {
        self.lock().hold.see(m);
    }

    /// When the active instance's last publication was seen (while holding).
    pub(crate) fn last_seen(&self) -> Option<Instant> {
        self.lock().hold.seen_at()
    }

    /// Publishes from now on, what is held and not seen published first, in the active
    /// instance's numbering (what is queued too). Returns whether the outbox must be handed
    /// to a lane, and by how much the points' `seq` were shifted (the shard shifts the
    /// points it makes from now on alike).
    pub(crate) fn release(&self) -> (bool, i64) {
        let mut st = self.lock();
        let queued: Vec<Outgoing> = st.queue.drain(..).collect();
        let (held, shift) = st.hold.release(queued, JOIN_UP_TO);
        self.holding.store(false, Ordering::Relaxed);
        st.bytes = held.iter().map(Outgoing::len).sum();
        st.queue = held;
        let hand = !st.queue.is_empty() && !std::mem::replace(&mut st.queued, true);
        (hand, shift)
    }

    /// At shutdown, hand the machine over as it is (its buffered samples not flushed: a
    /// standby corrects them as more samples come, with the same `seq`).
    pub(crate) fn keep_tail(&self) {
        self.keep_tail.store(true, Ordering::Relaxed);
    }

    pub(crate) fn idle(&self) -> bool {
        let st = self.lock();
        !st.queued && st.queue.is_empty()
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
            "last_seq": st.last_seq,
            "standby": st.hold.figures(),
        })
    }
}

/// How long the lanes of a shard may go without a step (an outbox taken, a `put` returned)
/// while output waits and none is free, before another lane is started: a lane held up by a
/// subscriber that stopped reading delays the shard's other machines by at most about this.
const STUCK: Duration = Duration::from_millis(50);

/// A lane idle this long ends, unless it is its shard's last.
const LANE_IDLE_END: Duration = Duration::from_secs(2);

/// At most this many lanes per shard (as many subscribers stalled at once, each holding one).
const MAX_LANES: usize = 64;

/// The publishing threads of one shard: they take outboxes with output, in the order they
/// were handed over, and drain them. One lane publishes for many machines, woken at most once
/// per batch of jobs of its shard (not once per message); a lane that a stalled subscriber
/// holds up in a `put` gets a new lane beside it (see [`STUCK`]).
pub(crate) struct Lanes {
    shard: usize,
    state: Mutex<LaneState>,
    work: Condvar,
    /// Steps taken by the lanes (an outbox taken, a `put` returned).
    progress: AtomicU64,
}

struct LaneState {
    ready: VecDeque<Arc<Outbox>>,
    lanes: usize,
    idle: usize,
    /// The progress last seen, and since when.
    seen: (u64, Instant),
    /// The shard has stopped: the lanes end once nothing is left.
    closed: bool,
}

impl Lanes {
    pub(crate) fn new(shard: usize) -> Arc<Lanes> {
        Arc::new(Lanes {
            shard,
            state: Mutex::new(LaneState {
                ready: VecDeque::new(),
                lanes: 0,
                idle: 0,
                seen: (0, Instant::now()),
                closed: false,
            }),
            work: Condvar::new(),
            progress: AtomicU64::new(0),
        })
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, LaneState> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Hands outboxes with output to the lanes.
    fn hand(self: &Arc<Self>, ready: impl IntoIterator<Item = Arc<Outbox>>) {
        let mut st = self.lock();
        st.ready.extend(ready);
        self.check_locked(&mut st);
    }

    /// Wakes a lane for waiting output, or starts one when there is none, or when every lane
    /// has been held up for [`STUCK`].
    fn check(self: &Arc<Self>) {
        let mut st = self.lock();
        self.check_locked(&mut st);
    }

    fn check_locked(self: &Arc<Self>, st: &mut LaneState) {
        if st.ready.is_empty() {
            return;
        }
        if st.idle > 0 {
            // As many lanes as there is output for (a lane woken for one outbox can be held
            // up by it while the next waits).
            if st.ready.len() > 1 {
                self.work.notify_all();
            } else {
                self.work.notify_one();
            }
            return;
        }
        let now = Instant::now();
        let p = self.progress.load(Ordering::Relaxed);
        if p != st.seen.0 {
            st.seen = (p, now);
        }
        let stuck = now.duration_since(st.seen.1) >= STUCK;
        if st.lanes == 0 || (stuck && st.lanes < MAX_LANES) {
            if st.lanes > 0 {
                warn!(shard = self.shard, lanes = st.lanes + 1, "publishing held up (a subscriber that does not read?): another publishing lane started");
            }
            st.seen = (p, now);
            let me = self.clone();
            match std::thread::Builder::new()
                .name(format!("publish-{}", self.shard))
                .spawn(move || me.run())
            {
                Ok(_) => st.lanes += 1,
                Err(e) => warn!(shard = self.shard, error = %e, "cannot start a publishing lane"),
            }
        }
    }

    /// Other outboxes wait for a lane.
    fn others_wait(&self) -> bool {
        !self.lock().ready.is_empty()
    }

    /// Ends the lanes once they have published what was handed to them.
    fn close(&self) {
        self.lock().closed = true;
        self.work.notify_all();
    }

    fn run(&self) {
        let mut st = self.lock();
        loop {
            if let Some(o) = st.ready.pop_front() {
                drop(st);
                self.progress.fetch_add(1, Ordering::Relaxed);
                let more = o.drain(self);
                st = self.lock();
                if more {
                    st.ready.push_back(o);
                }
                continue;
            }
            if st.closed {
                return;
            }
            st.idle += 1;
            let (guard, wait) = self
                .work
                .wait_timeout(st, LANE_IDLE_END)
                .unwrap_or_else(|e| e.into_inner());
            st = guard;
            st.idle -= 1;
            if wait.timed_out() && st.ready.is_empty() && st.lanes > 1 {
                st.lanes -= 1;
                return;
            }
        }
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
    /// Points encoded during the current batch of jobs, not yet handed to the outbox.
    pub(crate) pending: Pending,
    /// Its input's counters, shared with its route and the control task.
    pub(crate) input: Arc<Input>,
    /// Its work waiting on the shard, in arrival order.
    pub(crate) work: VecDeque<Work>,
    /// Its share of the shard's time (deficit round robin): ns it may still take this round;
    /// negative after a message that took longer.
    pub(crate) deficit: i64,
    /// In the shard's round.
    pub(crate) active: bool,
    /// What its correction costs: CPU time spent, points, and a running mean per point.
    pub(crate) busy_ns: u64,
    pub(crate) cost_ns_per_point: f64,
    /// How long the newest message it corrected waited on the shard, ms.
    pub(crate) wait_ms: f64,
    /// When the log last said that it is shed.
    pub(crate) told_shed: Option<Instant>,
    /// Streaming with no calibration in use: when it was last said, and its alarm.
    pub(crate) uncalibrated: Uncalibrated,
    /// Changed since its snapshot was last published.
    pub(crate) dirty: bool,
    /// Added to its points' `seq`: the numbering of the instance it took the machine over
    /// from, when this one's differs (it missed samples, or started later; see `standby`).
    pub(crate) seq_shift: i64,
}

impl Core {
    /// A machine's state before any message.
    pub(crate) fn new(
        corrector: Option<Corrector>,
        outbox: Arc<Outbox>,
        input: Arc<Input>,
    ) -> Core {
        let ids = corrector
            .as_ref()
            .map(|c| c.effect_ids())
            .unwrap_or_default();
        Core {
            corrector,
            ids,
            extra: Extra::default(),
            last_point_t_ns: None,
            outbox,
            pending: Pending::default(),
            input,
            work: VecDeque::new(),
            deficit: 0,
            active: false,
            busy_ns: 0,
            cost_ns_per_point: 0.0,
            wait_ms: 0.0,
            told_shed: None,
            uncalibrated: Uncalibrated::default(),
            dirty: true,
            seq_shift: 0,
        }
    }
}

/// A machine that streams while it has no calibration in use (never put, or quarantined) is
/// a loud state: its samples are counted (`uncorrected_samples` on its status, the health
/// reply and the metrics), the log says so at most once per [`UNCALIBRATED_LOG_EVERY`], and
/// one alarm is raised on its alarm key (cleared when a calibration is put): an
/// `EstimatorAlarm` with `calibration_version` 0 and no axis, which no estimator alarm has
/// (every estimator alarm names its axis and the version it was judged with).
#[derive(Debug, Default)]
pub(crate) struct Uncalibrated {
    /// When the log last said so, and the samples since.
    told: Option<Instant>,
    since_told: u64,
    /// Its alarm is raised.
    alarm_raised: bool,
    /// Controller time of the newest sample it had no calibration for, ns.
    newest_t_ns: Option<i64>,
}

/// The log says that a machine streams with no calibration at most this often.
pub(crate) const UNCALIBRATED_LOG_EVERY: Duration = Duration::from_secs(10);

/// The alarm of a machine streaming with no calibration (see [`Uncalibrated`]), raised or
/// cleared at controller time `t_ns`.
pub(crate) fn no_calibration_alarm(machine: &str, raised: bool, t_ns: i64) -> Vec<u8> {
    scancorr_proto::v1::EstimatorAlarm {
        machine_id: machine.to_string(),
        seq: 0,
        t_ns,
        raised,
        axis: scancorr_proto::v1::Axis::Unspecified as i32,
        action: scancorr_proto::v1::AlarmAction::Unspecified as i32,
        calibration_version: 0,
        ..Default::default()
    }
    .encode_to_vec()
}

/// `n` samples of `machine` arrived with no calibration in use (the newest at `t_ns`):
/// said at most once per [`UNCALIBRATED_LOG_EVERY`], and the machine's alarm raised once.
fn uncalibrated(
    m: &mut Core,
    machine: &str,
    n: u64,
    t_ns: Option<i64>,
    ready: &mut Vec<Arc<Outbox>>,
) {
    let u = &mut m.uncalibrated;
    u.since_told += n;
    if u.told.is_none_or(|t| t.elapsed() >= UNCALIBRATED_LOG_EVERY) {
        warn!(
            machine,
            uncorrected_samples = m.extra.no_calibration,
            since_last = u.since_told,
            "machine streams with no calibration in use: its samples are counted (`uncorrected_samples` on its status), not corrected, and no point is published until one is put (`scancorr calib put`); said at most once per {} s",
            UNCALIBRATED_LOG_EVERY.as_secs()
        );
        u.told = Some(Instant::now());
        u.since_told = 0;
    }
    if !u.alarm_raised {
        u.alarm_raised = true;
        warn!(
            machine,
            "no-calibration alarm raised on the machine's alarm key"
        );
        if m.outbox.send(Outgoing::Alarm(no_calibration_alarm(
            machine,
            true,
            t_ns.unwrap_or(0),
        ))) {
            ready.push(m.outbox.clone());
        }
    }
}

/// A machine's points of one batch of jobs: published as one message.
#[derive(Default)]
pub(crate) struct Pending {
    bytes: Vec<u8>,
    points: u64,
    /// When the earliest raw message that completed them arrived.
    arrived: Option<Instant>,
    /// The size of the machine's last batch: the room the next one is given at once.
    last_len: usize,
    /// Which points.
    span: Span,
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
    /// CPU time its correction took, s.
    pub(crate) busy_s: f64,
    /// What a point costs it now (a running mean), µs.
    pub(crate) cost_us_per_point: f64,
    /// How long the newest message corrected waited on the shard, ms.
    pub(crate) wait_ms: f64,
}

/// What the control task (and zenoh's callback) send a shard.
pub(crate) enum Job {
    /// Serve a new machine, in slot `slot` of the shard: machines are added in order and
    /// never removed, so the control task, which counts each shard's machines, names the
    /// slot the shard gives it.
    Add {
        slot: usize,
        name: String,
        core: Box<Core>,
    },
    /// One raw message of the machine in `slot` (its stream from the key), with its arrival.
    Raw {
        slot: usize,
        stream: StreamId,
        /// The payload, copied out of zenoh's receive buffer (a queued `Sample` would hold
        /// the whole buffer it arrived in).
        bytes: Vec<u8>,
        arrived: Instant,
    },
    /// A new calibration (the first, or a swap between two messages).
    Model(String, Arc<Model>),
    /// A snapshot of the named machine, after the messages routed before this job.
    Snap(String, tokio::sync::oneshot::Sender<Snap>),
    /// Flush every machine's buffered samples (shutdown), once its queued messages are done.
    Flush(tokio::sync::oneshot::Sender<()>),
    /// Publish the snapshots of the machines that changed now (health's totals).
    Publish(tokio::sync::oneshot::Sender<()>),
    /// The machine in this slot takes over (a standby becoming active): its outbox publishes
    /// what it held and what follows.
    Release(usize),
}

/// A machine's work waiting on its shard, in order.
pub(crate) enum Work {
    Raw {
        stream: StreamId,
        bytes: Vec<u8>,
        arrived: Instant,
    },
    Model(Arc<Model>),
    Snap(tokio::sync::oneshot::Sender<Snap>),
}

/// A shard's settings.
#[derive(Clone)]
pub(crate) struct Limits {
    pub(crate) max_pending_samples: usize,
    pub(crate) tags: wire::Tags,
    /// A message that waited longer than this on its shard is shed when its turn comes.
    pub(crate) shed_after: Duration,
    /// Points are published with their per-effect breakdown (`publish_breakdown`).
    pub(crate) breakdown: bool,
}

/// A corrector under the service's limits.
pub(crate) fn corrector(model: Arc<Model>, limits: &Limits) -> Corrector {
    let mut c = Corrector::with_model(model);
    c.limit_pending(Some(limits.max_pending_samples));
    c
}

/// At most this many jobs are run before the points they completed are handed to the
/// outboxes (sooner when the queue runs empty): under load a machine's messages of one burst
/// become one publication, and one wake-up of a lane serves many machines.
const BATCH_JOBS: usize = 64;

/// Each machine with work gets this much of its shard's time per round (deficit round robin):
/// a machine whose messages take long (a costly model) waits its turn behind the others
/// instead of holding them up, and its own messages age and are shed when the shard cannot
/// keep up with it.
const QUANTUM_NS: i64 = 2_000_000;

/// How often a shard publishes the snapshots of the machines that changed.
const PUBLISH_EVERY: Duration = Duration::from_millis(200);

/// A shard's latest snapshots, by slot: what status, health and metrics read, so the
/// control task never waits on a shard.
#[derive(Default)]
pub(crate) struct Board {
    snaps: Mutex<Vec<Option<(String, Snap)>>>,
}

impl Board {
    /// Every machine's latest snapshot.
    pub(crate) fn all(&self) -> Vec<(String, Snap)> {
        let s = self.snaps.lock().unwrap_or_else(|e| e.into_inner());
        s.iter().flatten().cloned().collect()
    }

    /// The latest snapshot of the machine in `slot`.
    pub(crate) fn get(&self, slot: usize) -> Option<Snap> {
        let s = self.snaps.lock().unwrap_or_else(|e| e.into_inner());
        s.get(slot).and_then(|x| x.as_ref()).map(|(_, s)| s.clone())
    }
}

/// Proof of progress: when a loop last turned (ms since `epoch`).
pub(crate) struct Beat {
    epoch: Instant,
    ms: AtomicU64,
}

impl Beat {
    pub(crate) fn new() -> Arc<Beat> {
        Arc::new(Beat {
            epoch: Instant::now(),
            ms: AtomicU64::new(0),
        })
    }

    pub(crate) fn beat(&self) {
        let ms = self.epoch.elapsed().as_millis() as u64;
        self.ms.fetch_max(ms, Ordering::Relaxed);
    }

    /// How long since the last beat.
    pub(crate) fn age(&self) -> Duration {
        let ms = self.epoch.elapsed().as_millis() as u64;
        Duration::from_millis(ms.saturating_sub(self.ms.load(Ordering::Relaxed)))
    }
}

/// What the control task keeps of a running shard.
pub(crate) struct Handle {
    pub(crate) jobs: flume::Sender<Job>,
    pub(crate) board: Arc<Board>,
    pub(crate) beat: Arc<Beat>,
    /// Snapshots asked of the shard and not taken yet.
    pub(crate) snaps_asked: Arc<AtomicUsize>,
}

/// Starts shard `k`: a thread that runs jobs until every sender is gone. Its job queue is
/// unbounded (nothing that sends to it ever waits); each machine's share is bounded where its
/// messages arrive (see [`Input`]).
pub(crate) fn spawn(
    k: usize,
    limits: Limits,
) -> std::io::Result<(Handle, std::thread::JoinHandle<()>)> {
    let (tx, jobs) = flume::unbounded();
    let board = Arc::new(Board::default());
    let beat = Beat::new();
    let snaps_asked = Arc::new(AtomicUsize::new(0));
    let handle = Handle {
        jobs: tx,
        board: board.clone(),
        beat: beat.clone(),
        snaps_asked: snaps_asked.clone(),
    };
    let thread = std::thread::Builder::new()
        .name(format!("shard-{k}"))
        .spawn(move || {
            let mut shard = Shard {
                k,
                machines: Vec::new(),
                index: HashMap::new(),
                active: VecDeque::new(),
                touched: Vec::new(),
                ready: Vec::new(),
                lanes: Lanes::new(k),
                out: Output::default(),
                limits,
                flush: None,
                board,
                published: Instant::now(),
                snaps_asked,
            };
            loop {
                beat.beat();
                if shard.active.is_empty() {
                    if let Some(done) = shard.flush.take() {
                        shard.flush_all();
                        let _ = done.send(());
                    }
                    // Nothing queued: wait for a job.
                    match jobs.recv_timeout(STUCK) {
                        Ok(job) => shard.take(job),
                        Err(flume::RecvTimeoutError::Timeout) => {
                            shard.lanes.check();
                            shard.publish(false);
                            continue;
                        }
                        Err(flume::RecvTimeoutError::Disconnected) => break,
                    }
                }
                // Everything that waits, to its machine's queue (a few ns each), then a round
                // of the machines with work.
                for job in jobs.try_iter() {
                    shard.take(job);
                }
                shard.round(&beat);
                shard.hand_over();
                shard.publish(false);
            }
            shard.publish(true);
            shard.lanes.close();
        })?;
    Ok((handle, thread))
}

/// A shard's machines, what it has for its lanes, and scratch space.
struct Shard {
    k: usize,
    machines: Vec<(String, Core)>,
    index: HashMap<String, usize>,
    /// Machines with work, in round order.
    active: VecDeque<usize>,
    /// Machines with pending points.
    touched: Vec<usize>,
    /// Outboxes to hand to the lanes.
    ready: Vec<Arc<Outbox>>,
    lanes: Arc<Lanes>,
    out: Output,
    limits: Limits,
    /// A flush asked for: done once every queued message is.
    flush: Option<tokio::sync::oneshot::Sender<()>>,
    board: Arc<Board>,
    published: Instant,
    snaps_asked: Arc<AtomicUsize>,
}

impl Shard {
    /// Sorts a job to its machine's queue (or runs it, when it is not a machine's).
    fn take(&mut self, job: Job) {
        let (k, w) = match job {
            Job::Add { slot, name, core } => {
                debug_assert_eq!(slot, self.machines.len(), "slots are given in order");
                self.index.insert(name.clone(), self.machines.len());
                self.machines.push((name, *core));
                return;
            }
            Job::Raw {
                slot,
                stream,
                bytes,
                arrived,
            } => {
                if slot >= self.machines.len() {
                    return;
                }
                (
                    slot,
                    Work::Raw {
                        stream,
                        bytes,
                        arrived,
                    },
                )
            }
            Job::Model(name, model) => match self.index.get(&name) {
                Some(&k) => (k, Work::Model(model)),
                None => return,
            },
            Job::Snap(name, reply) => match self.index.get(&name) {
                Some(&k) => (k, Work::Snap(reply)),
                None => {
                    // Dropping the reply tells the asker there is none.
                    self.snaps_asked.fetch_sub(1, Ordering::AcqRel);
                    return;
                }
            },
            Job::Flush(done) => {
                self.flush = Some(done);
                return;
            }
            Job::Publish(done) => {
                self.snaps_asked.fetch_sub(1, Ordering::AcqRel);
                self.publish(true);
                let _ = done.send(());
                return;
            }
            Job::Release(slot) => {
                if let Some((_, m)) = self.machines.get_mut(slot) {
                    // Its points made so far are renumbered with what it held.
                    to_outbox(m, &mut self.ready);
                    let (hand, shift) = m.outbox.release();
                    m.seq_shift = m.seq_shift.wrapping_add(shift);
                    if hand {
                        self.ready.push(m.outbox.clone());
                    }
                    self.hand_over();
                }
                return;
            }
        };
        let m = &mut self.machines[k].1;
        m.work.push_back(w);
        if !m.active {
            m.active = true;
            self.active.push_back(k);
        }
    }

    /// One round of the machines with work (deficit round robin on time), at most
    /// [`BATCH_JOBS`] messages: each gets [`QUANTUM_NS`] of the shard's time, and one whose
    /// message took longer waits until the others had as much.
    fn round(&mut self, beat: &Beat) {
        let mut done = 0;
        let mut turns = self.active.len();
        while done < BATCH_JOBS && turns > 0 {
            turns -= 1;
            let Some(k) = self.active.pop_front() else {
                break;
            };
            let (machine, m) = &mut self.machines[k];
            m.deficit = (m.deficit + QUANTUM_NS).min(QUANTUM_NS);
            while m.deficit > 0 && done < BATCH_JOBS {
                let Some(w) = m.work.pop_front() else {
                    break;
                };
                m.dirty = true;
                match w {
                    Work::Raw {
                        stream,
                        bytes,
                        arrived,
                    } => {
                        m.input.taken(bytes.len());
                        let waited = arrived.elapsed();
                        if waited > self.limits.shed_after {
                            shed_late(self.k, machine, m, waited, self.limits.shed_after);
                            continue;
                        }
                        done += 1;
                        let t0 = Instant::now();
                        let before = m.pending.points;
                        on_raw(
                            m,
                            machine,
                            stream,
                            &bytes,
                            arrived,
                            &self.limits,
                            &mut self.out,
                            &mut self.ready,
                        );
                        let ns = t0.elapsed().as_nanos() as u64;
                        m.deficit -= ns as i64;
                        m.busy_ns += ns;
                        m.wait_ms = waited.as_secs_f64() * 1e3;
                        let points = m.pending.points.saturating_sub(before);
                        if points > 0 {
                            let per = ns as f64 / points as f64;
                            m.cost_ns_per_point = if m.cost_ns_per_point == 0.0 {
                                per
                            } else {
                                0.9 * m.cost_ns_per_point + 0.1 * per
                            };
                        }
                        if m.pending.points > 0 && !self.touched.contains(&k) {
                            self.touched.push(k);
                        }
                        beat.beat();
                    }
                    Work::Model(model) => {
                        if std::mem::take(&mut m.uncalibrated.alarm_raised) {
                            // Corrected from the next message on: the alarm is cleared.
                            info!(machine = %machine, "calibration in use: the no-calibration alarm is cleared");
                            let t = m.uncalibrated.newest_t_ns.unwrap_or(0);
                            if m.outbox
                                .send(Outgoing::Alarm(no_calibration_alarm(machine, false, t)))
                            {
                                self.ready.push(m.outbox.clone());
                            }
                        }
                        m.uncalibrated.told = None;
                        match m.corrector.as_mut() {
                            Some(c) => c.set_model(model),
                            None => m.corrector = Some(corrector(model, &self.limits)),
                        }
                        m.ids = m
                            .corrector
                            .as_ref()
                            .map(|c| c.effect_ids())
                            .unwrap_or_default();
                        // A new model's cost is its own.
                        m.cost_ns_per_point = 0.0;
                    }
                    Work::Snap(reply) => {
                        self.snaps_asked.fetch_sub(1, Ordering::AcqRel);
                        let _ = reply.send(snap(m));
                    }
                }
            }
            if m.work.is_empty() {
                // Idle: its debt is forgotten (it is owed only while it competes).
                m.active = false;
                m.deficit = 0;
            } else {
                self.active.push_back(k);
            }
        }
    }

    /// Flushes every machine's buffered samples and hands their points over.
    fn flush_all(&mut self) {
        for (k, (name, m)) in self.machines.iter_mut().enumerate() {
            if m.outbox.keep_tail.load(Ordering::Relaxed) {
                continue;
            }
            if let Some(c) = m.corrector.as_mut() {
                c.flush(&mut self.out);
                if let Some(p) = self.out.points.last() {
                    m.last_point_t_ns = Some(p.t_ns);
                }
                let breakdown = self.limits.breakdown;
                publish(m, &mut self.out, name, None, breakdown, &mut self.ready);
                m.dirty = true;
                if m.pending.points > 0 && !self.touched.contains(&k) {
                    self.touched.push(k);
                }
            }
        }
        // Handed over before the control task is told, so that it waits for them.
        self.hand_over();
        self.publish(true);
    }

    /// Publishes the snapshots of the machines that changed, at most every
    /// [`PUBLISH_EVERY`] (or now, when `now`).
    fn publish(&mut self, now: bool) {
        if !now && self.published.elapsed() < PUBLISH_EVERY {
            return;
        }
        self.published = Instant::now();
        let fresh: Vec<(usize, String, Snap)> = self
            .machines
            .iter_mut()
            .enumerate()
            .filter(|(_, (_, m))| m.dirty)
            .map(|(k, (name, m))| {
                m.dirty = false;
                (k, name.clone(), snap(m))
            })
            .collect();
        if fresh.is_empty() {
            return;
        }
        let mut b = self.board.snaps.lock().unwrap_or_else(|e| e.into_inner());
        if b.len() < self.machines.len() {
            b.resize(self.machines.len(), None);
        }
        for (k, name, s) in fresh {
            b[k] = Some((name, s));
        }
    }

    /// Hands every machine's pending points to its outbox, and the outboxes to the lanes.
    fn hand_over(&mut self) {
        for k in self.touched.drain(..) {
            let m = &mut self.machines[k].1;
            to_outbox(m, &mut self.ready);
        }
        // Even with nothing new: what waits is looked at again (a lane may be held up).
        self.lanes.hand(self.ready.drain(..));
    }
}

/// A message of `machine` that waited too long on its shard: shed, counted, and said in the
/// log (at most once per 10 s per machine).
fn shed_late(shard: usize, machine: &str, m: &mut Core, waited: Duration, limit: Duration) {
    let n = m.input.shed_late.fetch_add(1, Ordering::Relaxed) + 1;
    if m.told_shed
        .is_none_or(|t| t.elapsed() >= Duration::from_secs(10))
    {
        m.told_shed = Some(Instant::now());
        warn!(
            machine,
            shard,
            waited_ms = (waited.as_secs_f64() * 1e3).round(),
            shed_late = n,
            cost_us_per_point = (m.cost_ns_per_point * 1e-3).round(),
            "the machine's shard fell behind real time with its work: its messages that waited longer than {:.1} s are shed (counted as `input.shed_late` on its status); the other machines are not affected",
            limit.as_secs_f64()
        );
    }
}

fn snap(m: &Core) -> Snap {
    Snap {
        core: m.corrector.as_ref().map(|c| CoreSnap {
            stats: c.stats().clone(),
            version: c.settings().version,
            pending: c.pending(),
            watermarks: c.watermarks(),
            inactive: c.inactive_effects(),
            state_bytes: c.state_bytes(),
            max_pending: c.max_pending(),
        }),
        ids: m.ids.clone(),
        extra: m.extra.clone(),
        last_point_t_ns: m.last_point_t_ns,
        busy_s: m.busy_ns as f64 * 1e-9,
        cost_us_per_point: m.cost_ns_per_point * 1e-3,
        wait_ms: m.wait_ms,
    }
}

/// One raw message: decoded (counted by what is wrong with it), corrected, its points
/// pending for the outbox.
#[allow(clippy::too_many_arguments)]
fn on_raw(
    m: &mut Core,
    machine: &str,
    sid: StreamId,
    bytes: &[u8],
    arrived: Instant,
    limits: &Limits,
    out: &mut Output,
    ready: &mut Vec<Arc<Outbox>>,
) {
    m.extra.messages += 1;
    // Decoded straight into the corrector (nothing is handed over unless the whole batch
    // decodes); without a calibration, only counted.
    let mut uncorrected = 0u64;
    let mut newest_t_ns = None;
    let mut corr = m.corrector.as_mut();
    let (resets, seq_resets) = corr
        .as_ref()
        .map_or((0, 0), |c| (c.stats().clock_resets, c.stats().seq_resets));
    let decoded =
        wire::decode_machine_each(sid, bytes, machine, limits.tags, |x| match corr.as_mut() {
            Some(c) => c.push(x, out),
            None => {
                uncorrected += 1;
                newest_t_ns = Some(newest_t_ns.unwrap_or(i64::MIN).max(x.t_ns()));
            }
        });
    match decoded {
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
        m.extra.no_calibration += uncorrected;
        if uncorrected > 0 {
            m.uncalibrated.newest_t_ns = newest_t_ns.or(m.uncalibrated.newest_t_ns);
            uncalibrated(m, machine, uncorrected, newest_t_ns, ready);
        }
        return;
    };
    // What waits for the other streams keeps its room; the room of a batch gone through is
    // given back, not kept per machine until its next batch.
    corr.trim();
    if corr.stats().clock_resets > resets {
        warn!(machine, "controller clock reset: the machine's join, estimator and judgement restarted in the new time base");
    }
    if corr.stats().seq_resets > seq_resets {
        warn!(machine, stream = sid.name(), "sequence numbers restarted (a counter wrap or restart): the stream's sequence continues from the new numbers");
    }
    if let Some(p) = out.points.last() {
        m.last_point_t_ns = Some(p.t_ns);
    }
    publish(m, out, machine, Some(arrived), limits.breakdown, ready);
}

/// Encodes what the core completed into the machine's pending points (alarms go to the
/// outbox at once, after the points before them); never waits on the bus. `arrived`: when
/// the raw message that completed these points arrived (none for a flush). `breakdown`: with
/// each point's per-effect corrections (`publish_breakdown`). Outboxes that need a lane are
/// added to `ready`.
fn publish(
    m: &mut Core,
    out: &mut Output,
    machine: &str,
    arrived: Option<Instant>,
    breakdown: bool,
    ready: &mut Vec<Arc<Outbox>>,
) {
    // Without the breakdown the block names no effect, and so carries no correction column.
    let ids: &[String] = if breakdown { &m.ids } else { &[] };
    if !out.points.is_empty() {
        // Written straight to protobuf as a packed block (v1.4; the same bytes prost makes).
        if m.pending.bytes.capacity() == 0 {
            // As much room as the machine's last batch took (a machine's batches are alike),
            // at least about what a packed point takes: 100 bytes and 24 per correction.
            let last = m.pending.last_len;
            let room = (out.points.len() * (100 + 24 * ids.len())).max(last + last / 8);
            m.pending.bytes = m.outbox.pool.get(room);
        }
        if m.seq_shift != 0 {
            // Taken over in the numbering of the instance active before (see `standby`).
            for x in &mut out.points {
                x.seq = x.seq.wrapping_add_signed(m.seq_shift);
            }
        }
        let p = &mut m.pending;
        wire::encode_points(&out.points, machine, ids, &mut p.bytes);
        let (first, last) = (&out.points[0], &out.points[out.points.len() - 1]);
        if p.points == 0 {
            p.span.seq.0 = first.seq;
            p.span.sample.0 = first.sample_seq;
        }
        p.span.seq.1 = last.seq;
        p.span.sample.1 = last.sample_seq;
        p.span.last_t_ns = last.t_ns;
        p.points += out.points.len() as u64;
        p.arrived = p.arrived.or(arrived);
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
        to_outbox(m, ready);
        if m.outbox
            .send(Outgoing::Alarm(wire::alarm(a, machine).encode_to_vec()))
        {
            ready.push(m.outbox.clone());
        }
    }
    out.clear();
}

/// Moves a machine's pending points to its outbox.
fn to_outbox(m: &mut Core, ready: &mut Vec<Arc<Outbox>>) {
    if m.pending.points == 0 {
        return;
    }
    let last_len = m.pending.bytes.len();
    let p = std::mem::replace(
        &mut m.pending,
        Pending {
            last_len,
            ..Default::default()
        },
    );
    if m.outbox
        .send(Outgoing::Points(p.bytes, p.points, p.arrived, p.span))
    {
        ready.push(m.outbox.clone());
    }
}
