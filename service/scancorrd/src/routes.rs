//! The raw messages' way in: zenoh's callback sends a message of a machine being served
//! straight to that machine's shard; everything else (a machine not served yet, a refusal, a
//! measurement stream) goes to the control task, which decides. One hop and no task wake-up
//! less per message on the hot path.
//!
//! Order is kept per machine: while any message of a machine waits on the control task's
//! queue, its later messages queue behind it there too, so none overtakes another on the
//! way to the shard. The counts are kept per machine name only while such messages wait
//! (bounded by that queue), so strangers cannot grow them.

use crate::shard::Job;
use scancorr_core::sample::StreamId;
use scancorr_core::wire;
use scancorr_proto::Stream;
use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{RwLock, RwLockReadGuard, RwLockWriteGuard};
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
    /// When the newest message of each stream arrived: ns since `epoch` + 1, 0 for never.
    last_arrival: [AtomicU64; 4],
}

impl Route {
    fn arrived(&self, epoch: Instant, sid: StreamId, at: Instant) {
        let ns = at.saturating_duration_since(epoch).as_nanos() as u64;
        self.last_arrival[sid as usize].fetch_max(ns.saturating_add(1), Ordering::Relaxed);
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
        }
    }

    fn read(&self) -> RwLockReadGuard<'_, Table> {
        self.table.read().unwrap_or_else(|e| e.into_inner())
    }

    fn write(&self) -> RwLockWriteGuard<'_, Table> {
        self.table.write().unwrap_or_else(|e| e.into_inner())
    }

    /// Sends a raw message of a served machine to its shard; returns the message when it is
    /// for the control task.
    pub(crate) fn route(
        &self,
        s: zenoh::sample::Sample,
        arrived: Instant,
    ) -> Option<zenoh::sample::Sample> {
        let Some((machine, stream)) = Stream::parse_key(&self.prefix, s.key_expr().as_str()) else {
            return Some(s);
        };
        let to = {
            let t = self.read();
            t.direct(machine, stream).map(|(r, sid)| {
                r.arrived(self.epoch, sid, arrived);
                (r.shard.clone(), r.slot, sid)
            })
        };
        let to = match to {
            Some(to) => to,
            None => {
                // Decided again under the write lock: the table may have changed.
                let mut t = self.write();
                match t.direct(machine, stream) {
                    Some((r, sid)) => {
                        r.arrived(self.epoch, sid, arrived);
                        (r.shard.clone(), r.slot, sid)
                    }
                    None => {
                        *t.at_control.entry(machine.to_string()).or_default() += 1;
                        return Some(s);
                    }
                }
            }
        };
        let (shard, slot, stream) = to;
        let job = Job::Raw {
            slot,
            stream,
            bytes: s.payload().to_bytes().into_owned(),
            arrived,
        };
        // A closed queue: the service is stopping.
        let _ = shard.send(job);
        None
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
    pub(crate) fn add(&self, machine: &str, shard: flume::Sender<Job>, slot: usize) {
        self.write().routes.insert(
            machine.to_string(),
            Route {
                shard,
                slot,
                last_arrival: Default::default(),
            },
        );
    }

    /// Notes a message that reached the shard through the control task.
    pub(crate) fn arrived(&self, machine: &str, sid: StreamId, at: Instant) {
        if let Some(r) = self.read().routes.get(machine) {
            r.arrived(self.epoch, sid, at);
        }
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
