//! A hot standby's withheld output (`failover`): a machine served in standby corrects every
//! raw message as the active instance does (same stream, same calibration, same core: the
//! same points), but its outbox holds the points instead of publishing them. What the active
//! instance is seen to publish (each of its publications carries its last point's [`Mark`])
//! is dropped from the front of what is held; what is left — the points the active one has
//! not been seen to publish — is published first when this instance takes the machine over,
//! so that a consumer sees every point once, in order, `seq` without a gap.
//!
//! **Numbering.** Both instances number their points from the stream they received, so their
//! `seq` differ when one missed samples (it stood on the other side of a partition, or lost
//! its router) or started later. A mark names its point on every instance (the scale sample's
//! `sample_seq` and `t_ns`): a held batch that holds a marked point gives the difference
//! (`shift`, the active's `seq` minus this one's), matched after every start of holding and
//! checked again every [`RECHECK`]. Until it is matched nothing is dropped (bounded, below);
//! at a take-over what is published is renumbered by it, and the shard numbers the points it
//! makes from then on alike.
//!
//! Alarms are held in their place between the point batches: one is dropped once the active
//! instance is seen to publish a point that came after it (it publishes in the same order).
//! What is held is bounded (`failover.max_held_bytes`): past it the oldest is dropped and
//! counted (`held_overflow_points`), a gap should the machine be taken over then.
//! At a take-over what is held goes out joined into publications of up to the outbox's join
//! size (not one per message it came from).

use crate::outgoing::{Mark, Outgoing, Span};
use scancorr_proto::v1::CorrectedPoint;
use scancorr_proto::Message;
use serde_json::json;
use std::collections::VecDeque;
use std::time::{Duration, Instant};
use tracing::{info, warn};

/// Once matched, the numbering is checked again this often.
const RECHECK: Duration = Duration::from_secs(2);
/// While not matched, a match is tried at most this often.
const TRY_EVERY: Duration = Duration::from_millis(50);
/// The active instance's newest marks kept for matching.
const MARKS: usize = 64;
/// Held batches decoded per try at most.
const DECODES_PER_TRY: usize = 4;

/// What a standby withholds for one machine (inside its outbox's lock).
#[derive(Default)]
pub(crate) struct Hold {
    /// Withholding (standby); false: the outbox publishes (active, or no fail-over).
    pub(crate) holding: bool,
    held: VecDeque<Outgoing>,
    held_bytes: usize,
    /// The newest point the active instance was seen to publish (its numbering), and when
    /// its last publication was seen.
    seen: Option<Mark>,
    seen_at: Option<Instant>,
    /// Its newest marks (the newest last), for matching the numbering.
    marks: VecDeque<Mark>,
    /// The active instance's `seq` minus this one's for the same point, once matched.
    shift: Option<i64>,
    /// When a match is tried next.
    next_try: Option<Instant>,
    /// Points dropped from the front past `max_bytes`.
    overflow_points: u64,
    /// Points published from what was held, at take-overs.
    released_points: u64,
    /// Matches that found this instance's numbering off the active one's.
    renumbered: u64,
    max_bytes: usize,
}

/// How many points an output holds.
fn count(o: &Outgoing) -> u64 {
    match o {
        Outgoing::Points(_, n, _, _) => *n,
        Outgoing::Alarm(_) => 0,
    }
}

fn span(o: &Outgoing) -> Option<&Span> {
    match o {
        Outgoing::Points(_, _, _, s) => Some(s),
        Outgoing::Alarm(_) => None,
    }
}

fn decode(b: &[u8]) -> Result<Vec<CorrectedPoint>, String> {
    scancorr_proto::v1::CorrectedPointBatch::decode(b)
        .map_err(|e| e.to_string())
        .and_then(|x| x.into_points().map_err(|e| e.to_string()))
}

/// The span of points, in order.
fn span_of(ps: &[CorrectedPoint]) -> Span {
    let (a, b) = (&ps[0], &ps[ps.len() - 1]);
    Span {
        seq: (a.seq, b.seq),
        sample: (a.sample_seq, b.sample_seq),
        last_t_ns: b.t_ns,
    }
}

/// Whether a batch may hold the point of scale sample `sample_seq` (its range, or a range
/// that went back: a sequence restart inside).
fn covers(s: &Span, sample_seq: u64) -> bool {
    s.sample.0 > s.sample.1 || (s.sample.0..=s.sample.1).contains(&sample_seq)
}

impl Hold {
    /// Starts withholding, with at most `max_bytes` held; the numbering is matched anew.
    pub(crate) fn start(&mut self, max_bytes: usize) {
        self.holding = true;
        self.max_bytes = max_bytes;
        self.seen = None;
        self.seen_at = None;
        self.marks.clear();
        self.shift = None;
        self.next_try = None;
    }

    /// Keeps one output (it is not published): then drops what the active one has published,
    /// and the oldest past the bound.
    pub(crate) fn keep(&mut self, o: Outgoing) {
        self.held_bytes += o.len();
        self.held.push_back(o);
        self.try_match();
        self.trim();
        while self.held_bytes > self.max_bytes && self.held.len() > 1 {
            let o = self.pop();
            if span(&o).is_some() {
                if self.overflow_points == 0 {
                    warn!(
                        bytes = self.max_bytes,
                        "standby: more output held than `failover.max_held_bytes` (the active instance is not seen publishing?): the oldest is dropped, a gap should this instance take the machine over now"
                    );
                }
                self.overflow_points += count(&o);
            }
        }
    }

    fn pop(&mut self) -> Outgoing {
        let o = self.held.pop_front().expect("not empty");
        self.held_bytes -= o.len();
        o
    }

    /// The active instance was seen to publish up to the point `m`.
    pub(crate) fn see(&mut self, m: Mark) {
        self.seen_at = Some(Instant::now());
        if self.seen.is_none_or(|s| m.seq > s.seq) {
            self.seen = Some(m);
        }
        self.marks.push_back(m);
        if self.marks.len() > MARKS {
            self.marks.pop_front();
        }
        self.try_match();
        self.trim();
    }

    /// Matches this instance's numbering with the active one's, when due: a held batch
    /// holding a marked point.
    fn try_match(&mut self) {
        let now = Instant::now();
        if self.next_try.is_some_and(|t| now < t) || self.marks.is_empty() {
            return;
        }
        self.next_try = Some(now + TRY_EVERY);
        let mut decodes = 0;
        for m in self.marks.iter().rev() {
            for o in self.held.iter().rev() {
                let Outgoing::Points(b, _, _, s) = o else {
                    continue;
                };
                if !covers(s, m.sample_seq) {
                    continue;
                }
                if decodes == DECODES_PER_TRY {
                    return;
                }
                decodes += 1;
                let Ok(ps) = decode(b) else { continue };
                let Some(p) = ps
                    .iter()
                    .find(|p| p.sample_seq == m.sample_seq && p.t_ns == m.t_ns)
                else {
                    continue;
                };
                let shift = m.seq.wrapping_sub(p.seq) as i64;
                if self.shift != Some(shift) {
                    if shift != 0 {
                        self.renumbered += 1;
                        info!(
                            machine = %p.machine_id,
                            shift,
                            "standby: this instance numbers the machine's points differently from the active instance (it missed samples or started later): taken over, it goes on in the active one's numbering"
                        );
                    }
                    if self.shift.is_some() {
                        warn!(machine = %p.machine_id, was = self.shift, now = shift, "standby: the numbering moved against the active instance's");
                    }
                    self.shift = Some(shift);
                }
                self.next_try = Some(now + RECHECK);
                return;
            }
        }
    }

    /// When the active instance's last publication was seen (none since holding started).
    pub(crate) fn seen_at(&self) -> Option<Instant> {
        self.seen_at
    }

    /// `seq` in the active instance's numbering (as matched).
    fn theirs(&self, seq: u64) -> u64 {
        seq.wrapping_add_signed(self.shift.unwrap_or(0))
    }

    /// Drops the whole outputs the active instance has published (once the numbering is
    /// matched: before, nothing is known to be published).
    fn trim(&mut self) {
        let (Some(_), Some(seen)) = (self.shift, self.seen) else {
            return;
        };
        let s = seen.seq;
        loop {
            let drop_front = match self.held.front() {
                Some(Outgoing::Points(_, _, _, sp)) => self.theirs(sp.seq.1) <= s,
                // An alarm: the active one published it once it published a point after it.
                Some(Outgoing::Alarm(_)) => self
                    .held
                    .iter()
                    .any(|o| span(o).is_some_and(|sp| self.theirs(sp.seq.0) <= s)),
                None => false,
            };
            if !drop_front {
                return;
            }
            self.pop();
        }
    }

    /// Stops withholding: what the active instance was not seen to publish, then `queued`
    /// (what the outbox had not yet moved here), in order, in the active instance's
    /// numbering (the batch it published part of cut after its newest point), joined into
    /// publications of up to `join` bytes. Also returns the shift applied.
    pub(crate) fn release(
        &mut self,
        queued: Vec<Outgoing>,
        join: usize,
    ) -> (VecDeque<Outgoing>, i64) {
        self.holding = false;
        for o in queued {
            self.held_bytes += o.len();
            self.held.push_back(o);
        }
        let shift = match self.shift {
            Some(s) => s,
            None => {
                if self.seen.is_some() {
                    warn!("standby: taking over before this instance's numbering was matched with the active one's: taken as the same");
                }
                0
            }
        };
        self.shift = Some(shift);
        self.trim();
        let seen = self.seen.map(|m| m.seq);
        let mut out: VecDeque<Outgoing> = VecDeque::with_capacity(self.held.len());
        let mut first = true;
        for o in std::mem::take(&mut self.held) {
            let o = match o {
                Outgoing::Points(mut b, mut n, at, mut sp) => {
                    let cut = first && seen.is_some_and(|s| self.theirs(sp.seq.0) <= s);
                    if cut || shift != 0 {
                        match decode(&b) {
                            Ok(mut ps) => {
                                for p in &mut ps {
                                    p.seq = p.seq.wrapping_add_signed(shift);
                                }
                                if let Some(s) = seen {
                                    ps.retain(|p| p.seq > s);
                                }
                                if ps.is_empty() {
                                    first = false;
                                    continue;
                                }
                                b = scancorr_proto::points::pack(&ps).encode_to_vec();
                                n = ps.len() as u64;
                                sp = span_of(&ps);
                            }
                            Err(e) => {
                                warn!(error = %e, "standby: a held batch does not decode; published whole")
                            }
                        }
                    }
                    first = false;
                    Outgoing::Points(b, n, at, sp)
                }
                a => a,
            };
            // Joined with the batch before it (two batches one after the other are the batch
            // of both).
            match (out.back_mut(), o) {
                (Some(Outgoing::Points(b, n, at, sp)), Outgoing::Points(more, m, later, next))
                    if b.len() + more.len() <= join =>
                {
                    b.extend_from_slice(&more);
                    *n += m;
                    *sp = sp.then(next);
                    *at = at.or(later);
                }
                (_, o) => out.push_back(o),
            }
        }
        self.held_bytes = 0;
        self.released_points += out.iter().map(count).sum::<u64>();
        self.shift = None;
        (out, shift)
    }

    /// For the machine's status (only when fail-over is on).
    pub(crate) fn figures(&self) -> Option<serde_json::Value> {
        (self.max_bytes > 0).then(|| {
            json!({
                "holding": self.holding,
                "held_bytes": self.held_bytes,
                "held_points": self.held.iter().map(count).sum::<u64>(),
                "active_seen_seq": self.seen.map(|m| m.seq),
                "seq_shift": self.shift,
                "renumbered": self.renumbered,
                "held_overflow_points": self.overflow_points,
                "released_points": self.released_points,
            })
        })
    }
}
