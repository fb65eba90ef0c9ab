//! A hot standby's withheld output (`failover`): a machine served in standby corrects every
//! raw message as the active instance does (same stream, same calibration, same core: the
//! same points with the same `seq`), but its outbox holds the points instead of publishing
//! them. What the active instance is seen to publish (the newest `seq` on the machine's points
//! key) is dropped from the front of what is held; what is left — the points the active one
//! has not been seen to publish — is published first when this instance takes the machine
//! over, so that a consumer sees every point once, in order, `seq` without a gap.
//!
//! Alarms are held in their place between the point batches: one is dropped once the active
//! instance is seen to publish a point that came after it (it publishes in the same order).
//! What is held is bounded (`failover.max_held_bytes`): past it the oldest is dropped and
//! counted (`held_overflow_points`), a gap should the machine be taken over then.

use crate::outgoing::Outgoing;
use scancorr_proto::Message;
use serde_json::json;
use std::collections::VecDeque;
use tracing::warn;

/// What a standby withholds for one machine (inside its outbox's lock).
#[derive(Default)]
pub(crate) struct Hold {
    /// Withholding (standby); false: the outbox publishes (active, or no fail-over).
    pub(crate) holding: bool,
    held: VecDeque<Outgoing>,
    held_bytes: usize,
    /// The newest `seq` the active instance was seen to publish.
    seen: Option<u64>,
    /// Points dropped from the front past `max_bytes`.
    overflow_points: u64,
    /// Points published from what was held, at take-overs.
    released_points: u64,
    max_bytes: usize,
}

fn seqs(o: &Outgoing) -> Option<(u64, u64)> {
    match o {
        Outgoing::Points(_, _, _, s) => Some(*s),
        Outgoing::Alarm(_) => None,
    }
}

impl Hold {
    /// Starts withholding, with at most `max_bytes` held; `published`: the newest `seq` this
    /// instance published itself (when it steps back, the other has those).
    pub(crate) fn start(&mut self, max_bytes: usize, published: Option<u64>) {
        self.holding = true;
        self.max_bytes = max_bytes;
        self.see(published);
    }

    /// Keeps one output (it is not published): then drops what the active one has published,
    /// and the oldest past the bound.
    pub(crate) fn keep(&mut self, o: Outgoing) {
        self.held_bytes += o.len();
        self.held.push_back(o);
        self.trim();
        while self.held_bytes > self.max_bytes && self.held.len() > 1 {
            let o = self.pop();
            if let Some((a, b)) = seqs(&o) {
                if self.overflow_points == 0 {
                    warn!(
                        bytes = self.max_bytes,
                        "standby: more output held than `failover.max_held_bytes` (the active instance is not seen publishing?): the oldest is dropped, a gap should this instance take the machine over now"
                    );
                }
                self.overflow_points += b - a + 1;
            }
        }
    }

    fn pop(&mut self) -> Outgoing {
        let o = self.held.pop_front().expect("not empty");
        self.held_bytes -= o.len();
        o
    }

    /// The active instance was seen to publish up to `seq`.
    pub(crate) fn see(&mut self, seq: Option<u64>) {
        if let Some(s) = seq {
            self.seen = Some(self.seen.map_or(s, |x| x.max(s)));
            self.trim();
        }
    }

    /// Drops the whole outputs the active instance has published.
    fn trim(&mut self) {
        let Some(s) = self.seen else { return };
        loop {
            let drop_front = match self.held.front() {
                Some(Outgoing::Points(_, _, _, (_, last))) => *last <= s,
                // An alarm: the active one published it once it published a point after it.
                Some(Outgoing::Alarm(_)) => self
                    .held
                    .iter()
                    .any(|o| seqs(o).is_some_and(|(first, _)| first <= s)),
                None => false,
            };
            if !drop_front {
                return;
            }
            self.pop();
        }
    }

    /// Stops withholding: what the active instance was not seen to publish, in order (the
    /// batch it published part of cut after its newest `seq`).
    pub(crate) fn release(&mut self) -> VecDeque<Outgoing> {
        self.holding = false;
        self.trim();
        if let (Some(s), Some(Outgoing::Points(b, n, at, (first, last)))) =
            (self.seen, self.held.front_mut())
        {
            if *first <= s && s < *last {
                match scancorr_proto::v1::CorrectedPointBatch::decode(&b[..])
                    .map_err(|e| e.to_string())
                    .and_then(|x| x.into_points().map_err(|e| e.to_string()))
                {
                    Ok(mut ps) => {
                        ps.retain(|p| p.seq > s);
                        *b = scancorr_proto::points::pack(&ps).encode_to_vec();
                        *n = ps.len() as u64;
                        *first = s + 1;
                        let _ = at;
                    }
                    Err(e) => {
                        warn!(error = %e, "standby: a held batch does not decode; published whole")
                    }
                }
            }
        }
        self.held_bytes = 0;
        let out = std::mem::take(&mut self.held);
        self.released_points += out
            .iter()
            .filter_map(seqs)
            .map(|(a, b)| b - a + 1)
            .sum::<u64>();
        out
    }

    /// For the machine's status (only when fail-over is on).
    pub(crate) fn figures(&self) -> Option<serde_json::Value> {
        (self.max_bytes > 0).then(|| {
            json!({
                "holding": self.holding,
                "held_bytes": self.held_bytes,
                "held_points": self.held.iter().filter_map(seqs).map(|(a, b)| b - a + 1).sum::<u64>(),
                "active_seen_seq": self.seen,
                "held_overflow_points": self.overflow_points,
                "released_points": self.released_points,
            })
        })
    }
}
