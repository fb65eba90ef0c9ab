//! The raw messages' way in: zenoh's callback sends a message of a machine being served
//! straight to that machine's shard; everything else (a machine not served yet, a refusal, a
//! measurement stream) goes to the control task, which decides. One hop and no task wake-up
//! less per message on the hot path.
//!
//! zenoh's callback never waits here: a shard's queue is unbounded, and each machine's share
//! of it is bounded by its [`Input`] (`max_input_bytes_per_machine`): a machine whose shard
//! does not keep up has its own messages shed (counted on its status), never another's. The
//! callback of a link waiting on a full queue would stop that link, and behind a router one
//! link carries every machine.
//!
//! Order is kept per machine: while any message of a machine waits on the control task's
//! queue, its later messages queue behind it there too, so none overtakes another on the
//! way to the shard. The counts are kept per machine name only while such messages wait
//! (bounded by that queue), so strangers cannot grow them.

use crate::input::Input;
use crate::shard::Job;
use scancorr_core::sample::StreamId;
use scancorr_core::wire;
use scancorr_proto::Stream;
use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, RwLock, RwLockReadGuard, RwLockWriteGuard};
use std::time::{Duration, Instant};

/// The routing table shared by the subscriber's callback and the control task.
///
/// zenoh calls back on one thread per link, so the table is read-locked on the hot path (the
/// callbacks of served machines' messages do not wait for each other) and the arrival times
/// are atomics; a message for the control task (a machine not served yet, refused, or served
/// elsewhere), and the control task's changes, take the write lock.
pub(crate) struct Routes {
    prefix: String,
    /// What the arrival times count from.
    epoch: Instant,
    table: RwLock<Table>,
    /// Messages of machines not served that the control task had no room for.
    busy: AtomicU64,
    /// Messages on a key that names no valid machine and stream that the control task had no
    /// room for: refused as a bad key all the same (the key, not the queue, refuses them).
    busy_bad_key: AtomicU64,
}

#[derive(Default)]
struct Table {
    routes: HashMap<String, Route>,
    /// Messages on the control task's queue, per machine named.
    at_control: HashMap<String, u32>,
    /// The service is stopping: everything goes to the control task (which no longer reads).
    closed: bool,
}

struct Route {
    shard: flume::Sender<Job>,
    /// The machine's slot on its shard.
    slot: usize,
    input: Arc<Input>,
    /// When the newest message of each stream arrived: ns since `epoch` + 1, 0 for never.
    last_arrival: [AtomicU64; 4],
}

impl Route {
    fn arrived(&self, epoch: Instant, sid: StreamId, at: Instant) {
        let ns = at.saturating_duration_since(epoch).as_nanos() as u64;
        self.last_arrival[sid as usize].fetch_max(ns.saturating_add(1), Ordering::Relaxed);
    }

    /// Hands a message to the machine's shard, unless its queue there is full (counted).
    fn send(&self, epoch: Instant, sid: StreamId, s: &zenoh::sample::Sample, at: Instant) {
        self.arrived(epoch, sid, at);
        let bytes = s.payload().to_bytes().into_owned();
        let len = bytes.len();
        if !self.input.admit(len) {
            return;
        }
        let job = Job::Raw {
            slot: self.slot,
            stream: sid,
            bytes,
            arrived: at,
        };
        // Unbounded: never waits. A closed queue: the service is stopping.
        if self.shard.send(job).is_err() {
            self.input.taken(len);
        }
    }

    fn last_arrival(&self, epoch: Instant) -> [Option<Instant>; 4] {
        self.last_arrival
            .each_ref()
            .map(|a| match a.load(Ordering::Relaxed) {
                0 => None,
                ns => Some(epoch + Duration::from_nanos(ns - 1)),
            })
    }
}

impl Table {
    /// The shard and slot of a message of `machine` on `stream` that may go straight to its
    /// shard (served, and none of its messages waiting at the control task).
    fn direct(&self, machine: &str, stream: Stream) -> Option<(&Route, StreamId)> {
        if self.closed || self.at_control.contains_key(machine) {
            return None;
        }
        Some((self.routes.get(machine)?, wire::stream_id(stream)?))
    }
}

impl Routes {
    pub(crate) fn new(prefix: &str) -> Routes {
        Routes {
            prefix: prefix.to_string(),
            epoch: Instant::now(),
            table: RwLock::default(),
            busy: AtomicU64::new(0),
            busy_bad_key: AtomicU64::new(0),
        }
    }

    fn read(&self) -> RwLockReadGuard<'_, Table> {
        self.table.read().unwrap_or_else(|e| e.into_inner())
    }

    fn write(&self) -> RwLockWriteGuard<'_, Table> {
        self.table.write().unwrap_or_else(|e| e.into_inner())
    }

    /// Sends a raw message of a served machine to its shard (or sheds it, counted, when its
    /// queue there is full); returns the message when it is for the control task. Never
    /// waits.
    pub(crate) fn route(
        &self,
        s: zenoh::sample::Sample,
        arrived: Instant,
    ) -> Option<zenoh::sample::Sample> {
        let Some((machine, stream)) = Stream::parse_key(&self.prefix, s.key_expr().as_str()) else {
            return Some(s);
        };
        {
            let t = self.read();
            if let Some((r, sid)) = t.direct(machine, stream) {
                r.send(self.epoch, sid, &s, arrived);
                return None;
            }
        }
        // Decided again under the write lock: the table may have changed.
        let mut t = self.write();
        match t.direct(machine, stream) {
            Some((r, sid)) => r.send(self.epoch, sid, &s, arrived),
            None => {
                *t.at_control.entry(machine.to_string()).or_default() += 1;
                return Some(s);
            }
        }
        None
    }

    /// A message [`Routes::route`] gave the control task, for which its queue had no room:
    /// shed (counted on the machine's status when it is served, as a bad key when its key
    /// names no valid machine and stream — as the control task would have — else as
    /// `control_busy`).
    pub(crate) fn busy(&self, s: &zenoh::sample::Sample) {
        let Some((m, _)) = Stream::parse_key(&self.prefix, s.key_expr().as_str()) else {
            self.busy_bad_key.fetch_add(1, Ordering::Relaxed);
            return;
        };
        self.done(m);
        if let Some(r) = self.read().routes.get(m) {
            r.input.arrived.fetch_add(1, Ordering::Relaxed);
            r.input.shed_queue_full.fetch_add(1, Ordering::Relaxed);
            return;
        }
        self.busy.fetch_add(1, Ordering::Relaxed);
    }

    /// Messages on a bad key that the control task had no room for.
    pub(crate) fn busy_bad_key_count(&self) -> u64 {
        self.busy_bad_key.load(Ordering::Relaxed)
    }

    /// Messages of machines not served that the control task had no room for.
    pub(crate) fn busy_count(&self) -> u64 {
        self.busy.load(Ordering::Relaxed)
    }

    /// Sends a raw message of a served machine (one the control task took) to its shard, or
    /// sheds it, counted, when its queue there is full. False when the machine has no route.
    pub(crate) fn deliver(
        &self,
        machine: &str,
        sid: StreamId,
        s: &zenoh::sample::Sample,
        arrived: Instant,
    ) -> bool {
        match self.read().routes.get(machine) {
            Some(r) => {
                r.send(self.epoch, sid, s, arrived);
                true
            }
            None => false,
        }
    }

    /// The control task is done with a message of `machine` (the one `route` gave it).
    pub(crate) fn done(&self, machine: &str) {
        let mut t = self.write();
        if let Some(n) = t.at_control.get_mut(machine) {
            *n -= 1;
            if *n == 0 {
                t.at_control.remove(machine);
            }
        }
    }

    /// Routes `machine`'s messages to `shard` from now on (its state is in `slot` there).
    pub(crate) fn add(
        &self,
        machine: &str,
        shard: flume::Sender<Job>,
        slot: usize,
        input: Arc<Input>,
    ) {
        self.write().routes.insert(
            machine.to_string(),
            Route {
                shard,
                slot,
                input,
                last_arrival: Default::default(),
            },
        );
    }

    /// When the newest message of each stream of `machine` arrived.
    pub(crate) fn last_arrival(&self, machine: &str) -> [Option<Instant>; 4] {
        self.read()
            .routes
            .get(machine)
            .map(|r| r.last_arrival(self.epoch))
            .unwrap_or_default()
    }

    /// Every machine's [`Routes::last_arrival`].
    pub(crate) fn last_arrivals(&self) -> HashMap<String, [Option<Instant>; 4]> {
        self.read()
            .routes
            .iter()
            .map(|(k, r)| (k.clone(), r.last_arrival(self.epoch)))
            .collect()
    }

    /// Stops routing to the shards (and lets go of their queues).
    pub(crate) fn close(&self) {
        let mut t = self.write();
        t.closed = true;
        t.routes.clear();
    }
}
