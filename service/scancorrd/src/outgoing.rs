//! What a machine's outbox publishes next: a batch of encoded points (with its `seq` range)
//! or an alarm. Shared by the shard's outbox and a hot standby's withheld output.

use std::time::Instant;

pub(crate) enum Outgoing {
    /// Encoded points, how many, when the earliest message that completed them arrived, and
    /// their first and last `seq`.
    Points(Vec<u8>, u64, Option<Instant>, (u64, u64)),
    Alarm(Vec<u8>),
}

impl Outgoing {
    pub(crate) fn len(&self) -> usize {
        match self {
            Outgoing::Points(b, _, _, _) | Outgoing::Alarm(b) => b.len(),
        }
    }
}
