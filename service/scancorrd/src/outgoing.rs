//! What a machine's outbox publishes next: a batch of encoded points (with its `seq` range)
//! or an alarm. Shared by the shard's outbox and a hot standby's withheld output.

use std::time::Instant;

pub(crate) enum Outgoing {
    /// Encoded points, how many, when the earliest message that completed them arrived, and
    /// which points they are.
    Points(Vec<u8>, u64, Option<Instant>, Span),
    Alarm(Vec<u8>),
}

/// Which points a batch holds: their first and last `seq`, the first and last `sample_seq`,
/// and the last point's `t_ns` (the last point's `(sample_seq, t_ns)` names the same point on
/// every instance, whatever `seq` each gave it).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub(crate) struct Span {
    pub(crate) seq: (u64, u64),
    pub(crate) sample: (u64, u64),
    pub(crate) last_t_ns: i64,
}

impl Span {
    /// The span of `a` followed by `b` (joined into one publication).
    pub(crate) fn then(self, b: Span) -> Span {
        Span {
            seq: (self.seq.0, b.seq.1),
            sample: (self.sample.0, b.sample.1),
            last_t_ns: b.last_t_ns,
        }
    }
}

/// A published point, as a standby sees it on the bus: the active instance's `seq` for the
/// point of scale sample `sample_seq` at `t_ns`. Each publication of points carries its last
/// point's as its attachment (24 bytes, little-endian; see `server::failover`), so a standby
/// need not decode the points.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Mark {
    pub(crate) seq: u64,
    pub(crate) sample_seq: u64,
    pub(crate) t_ns: i64,
}

impl Mark {
    pub(crate) fn last_of(s: &Span) -> Mark {
        Mark {
            seq: s.seq.1,
            sample_seq: s.sample.1,
            t_ns: s.last_t_ns,
        }
    }

    pub(crate) fn to_bytes(self) -> [u8; 24] {
        let mut b = [0u8; 24];
        b[..8].copy_from_slice(&self.seq.to_le_bytes());
        b[8..16].copy_from_slice(&self.sample_seq.to_le_bytes());
        b[16..].copy_from_slice(&self.t_ns.to_le_bytes());
        b
    }

    pub(crate) fn from_bytes(b: &[u8]) -> Option<Mark> {
        let b: &[u8; 24] = b.try_into().ok()?;
        Some(Mark {
            seq: u64::from_le_bytes(b[..8].try_into().ok()?),
            sample_seq: u64::from_le_bytes(b[8..16].try_into().ok()?),
            t_ns: i64::from_le_bytes(b[16..].try_into().ok()?),
        })
    }
}

impl Outgoing {
    pub(crate) fn len(&self) -> usize {
        match self {
            Outgoing::Points(b, _, _, _) | Outgoing::Alarm(b) => b.len(),
        }
    }
}
