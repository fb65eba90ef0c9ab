//! A served machine's input counters, shared by its route (zenoh's callback admits or sheds
//! each message), its state on its shard (which gives the bytes back and counts what it sheds
//! late) and the control task (status): atomics, no lock, no wait.

use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};

/// A served machine's input on its way to its shard: counted and bounded in zenoh's callback,
/// without a lock or a wait. Shared by the route, the machine's state on its shard (which
/// gives the bytes back and counts what it sheds) and the control task (status).
#[derive(Debug)]
pub(crate) struct Input {
    /// Raw messages of the machine that reached the service (shed ones included).
    pub(crate) arrived: AtomicU64,
    /// Shed as they arrived: the machine's messages waiting on its shard already held
    /// `max_input_bytes_per_machine`.
    pub(crate) shed_queue_full: AtomicU64,
    /// Shed on the shard: they had waited longer than `shed_after_ms` when their turn came
    /// (the shard fell behind real time with this machine's work).
    pub(crate) shed_late: AtomicU64,
    /// Bytes of the machine's messages waiting on its shard.
    pub(crate) queued_bytes: AtomicUsize,
    max_bytes: usize,
}

impl Input {
    pub(crate) fn new(max_bytes: usize) -> Input {
        Input {
            arrived: AtomicU64::new(0),
            shed_queue_full: AtomicU64::new(0),
            shed_late: AtomicU64::new(0),
            queued_bytes: AtomicUsize::new(0),
            max_bytes,
        }
    }

    /// Counts a message of `len` bytes that arrived, and takes it into the machine's queue:
    /// false (shed, counted) when the queue is full. A message alone in the queue is always
    /// taken, whatever its size.
    pub(crate) fn admit(&self, len: usize) -> bool {
        self.arrived.fetch_add(1, Ordering::Relaxed);
        let before = self.queued_bytes.fetch_add(len, Ordering::AcqRel);
        if before > 0 && before + len > self.max_bytes {
            self.queued_bytes.fetch_sub(len, Ordering::AcqRel);
            self.shed_queue_full.fetch_add(1, Ordering::Relaxed);
            return false;
        }
        true
    }

    /// A message of `len` bytes left the queue (corrected or shed).
    pub(crate) fn taken(&self, len: usize) {
        self.queued_bytes.fetch_sub(len, Ordering::AcqRel);
    }

    /// Messages shed, by reason, and the bytes waiting.
    pub(crate) fn figures(&self) -> serde_json::Value {
        let full = self.shed_queue_full.load(Ordering::Relaxed);
        let late = self.shed_late.load(Ordering::Relaxed);
        serde_json::json!({
            "arrived": self.arrived.load(Ordering::Relaxed),
            "shed": full + late,
            "shed_queue_full": full,
            "shed_late": late,
            "queued_bytes": self.queued_bytes.load(Ordering::Relaxed),
        })
    }
}
