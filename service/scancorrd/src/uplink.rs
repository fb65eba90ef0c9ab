//! The service's link to its router, in client mode: lost and regained, logged and counted.
//!
//! A client reaches the bus only through a router. While it has none, no raw sample arrives,
//! every point it publishes reaches no one, and its liveliness tokens are gone from the bus
//! (another instance may see its machines unserved). zenoh connects again by itself, and the
//! samples lost meanwhile are counted per stream as missing in seq, but the outage itself
//! would show nowhere. This watch makes it visible: a warning when the last router goes, a
//! line when one is back with how long the outage lasted, and the count on `health` and in
//! the metrics.

use std::time::{Duration, Instant};
use tracing::{info, warn};

/// What the watch has seen of the session's routers.
#[derive(Debug)]
pub(crate) struct Uplink {
    routers: usize,
    losses: u64,
    lost_at: Option<Instant>,
    down: Duration,
}

impl Uplink {
    /// A watch that starts with `routers` routers connected.
    pub(crate) fn new(routers: usize, now: Instant) -> Uplink {
        let mut u = Uplink {
            routers: 1,
            losses: 0,
            lost_at: None,
            down: Duration::ZERO,
        };
        u.observe(routers, now);
        u
    }

    /// Takes the number of routers the session has now; logs a loss or a return.
    pub(crate) fn observe(&mut self, routers: usize, now: Instant) {
        match (self.routers, routers) {
            (1.., 0) => {
                self.losses += 1;
                self.lost_at = Some(now);
                warn!(
                    losses = self.losses,
                    "lost the connection to the router: no raw sample arrives and no point \
                     reaches anyone until zenoh connects again"
                );
            }
            (0, 1..) => {
                let lasted = self.lost_at.take().map_or(Duration::ZERO, |t| now - t);
                self.down += lasted;
                info!(
                    routers,
                    down_s = lasted.as_secs_f64(),
                    "connected to the router again after {:.1} s",
                    lasted.as_secs_f64()
                );
            }
            _ => {}
        }
        self.routers = routers;
    }

    /// Routers connected now.
    pub(crate) fn routers(&self) -> usize {
        self.routers
    }

    /// Times the last router was lost.
    pub(crate) fn losses(&self) -> u64 {
        self.losses
    }

    /// Seconds spent without a router, the outage in course included.
    pub(crate) fn down_s(&self, now: Instant) -> f64 {
        (self.down + self.lost_at.map_or(Duration::ZERO, |t| now - t)).as_secs_f64()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn losses_and_returns_are_counted_and_timed() {
        let t0 = Instant::now();
        let s = Duration::from_secs;
        let mut u = Uplink::new(1, t0);
        assert_eq!((u.routers(), u.losses(), u.down_s(t0)), (1, 0, 0.0));
        u.observe(0, t0 + s(10));
        assert_eq!((u.routers(), u.losses()), (0, 1));
        assert_eq!(u.down_s(t0 + s(13)), 3.0, "an outage in course counts");
        // Still down: not a second loss.
        u.observe(0, t0 + s(11));
        u.observe(2, t0 + s(14));
        assert_eq!((u.routers(), u.losses(), u.down_s(t0 + s(20))), (2, 1, 4.0));
        // One router of two gone: still connected.
        u.observe(1, t0 + s(21));
        assert_eq!(u.losses(), 1);
        u.observe(0, t0 + s(30));
        u.observe(1, t0 + s(31));
        assert_eq!((u.losses(), u.down_s(t0 + s(40))), (2, 5.0));
    }

    #[test]
    fn a_start_without_a_router_is_a_loss() {
        let t0 = Instant::now();
        let mut u = Uplink::new(0, t0);
        assert_eq!((u.routers(), u.losses()), (0, 1));
        u.observe(1, t0 + Duration::from_secs(2));
        assert_eq!(u.down_s(t0 + Duration::from_secs(9)), 2.0);
    }
}
