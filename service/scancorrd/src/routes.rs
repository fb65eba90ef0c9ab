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
use std::sync::Mutex;
use std::time::Instant;

/// The routing table shared by the subscriber's callback and the control task.
pub(crate) struct Routes {
    prefix: String,
    table: Mutex<Table>,
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
    /// When the newest message of each stream arrived.
    last_arrival: [Option<Instant>; 4],
}

impl Routes {
    pub(crate) fn new(prefix: &str) -> Routes {
        Routes {
            prefix: prefix.to_string(),
            table: Mutex::default(),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Table> {
        self.table.lock().unwrap_or_else(|e| e.into_inner())
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
        let mut t = self.lock();
        if !t.closed && !t.at_control.contains_key(machine) {
            if let (Some(sid), Some(r)) = (wire::stream_id(stream), t.routes.get_mut(machine)) {
                r.last_arrival[sid as usize] = Some(arrived);
                let (shard, slot) = (r.shard.clone(), r.slot);
                drop(t);
                let job = Job::Raw {
                    slot,
                    stream: sid,
                    bytes: s.payload().to_bytes().into_owned(),
                    arrived,
                };
                // A closed queue: the service is stopping.
                let _ = shard.send(job);
                return None;
            }
        }
        *t.at_control.entry(machine.to_string()).or_default() += 1;
        drop(t);
        Some(s)
    }

    /// The control task is done with a message of `machine` (the one `route` gave it).
    pub(crate) fn done(&self, machine: &str) {
        let mut t = self.lock();
        if let Some(n) = t.at_control.get_mut(machine) {
            *n -= 1;
            if *n == 0 {
                t.at_control.remove(machine);
            }
        }
    }

    /// Routes `machine`'s messages to `shard` from now on (its state is in `slot` there).
    pub(crate) fn add(&self, machine: &str, shard: flume::Sender<Job>, slot: usize) {
        self.lock().routes.insert(
            machine.to_string(),
            Route {
                shard,
                slot,
                last_arrival: [None; 4],
            },
        );
    }

    /// Notes a message that reached the shard through the control task.
    pub(crate) fn arrived(&self, machine: &str, sid: StreamId, at: Instant) {
        if let Some(r) = self.lock().routes.get_mut(machine) {
            r.last_arrival[sid as usize] = Some(at);
        }
    }

    /// When the newest message of each stream of `machine` arrived.
    pub(crate) fn last_arrival(&self, machine: &str) -> [Option<Instant>; 4] {
        self.lock()
            .routes
            .get(machine)
            .map(|r| r.last_arrival)
            .unwrap_or_default()
    }

    /// Every machine's [`Routes::last_arrival`].
    pub(crate) fn last_arrivals(&self) -> HashMap<String, [Option<Instant>; 4]> {
        self.lock()
            .routes
            .iter()
            .map(|(k, r)| (k.clone(), r.last_arrival))
            .collect()
    }

    /// Stops routing to the shards (and lets go of their queues).
    pub(crate) fn close(&self) {
        let mut t = self.lock();
        t.closed = true;
        t.routes.clear();
    }
}
