//! systemd readiness and watchdog (`Type=notify`, `WatchdogSec=`): datagrams to the socket
//! systemd names in `NOTIFY_SOCKET` (a path, or `@name` in Linux's abstract namespace).
//! Without that variable every call does nothing.
//!
//! `READY=1` once the subscriptions, queryables and stored machines are up; `WATCHDOG=1` at
//! half the interval systemd asks for in `WATCHDOG_USEC`, from a task of its own ([`watchdog`])
//! and only while the control loop and every correcting shard prove that they turn (each
//! beats as it goes; neither waits on the other), so a service that stops correcting is
//! restarted; `STOPPING=1` when shutting down.

use crate::shard::Beat;
use std::os::unix::net::UnixDatagram;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tracing::{error, info};

/// The notification socket and the watchdog's pace.
pub struct Notifier {
    target: Option<(UnixDatagram, String)>,
    watchdog: Option<Duration>,
    last: Mutex<Option<Instant>>,
}

impl Notifier {
    /// From `NOTIFY_SOCKET` and `WATCHDOG_USEC` (`WATCHDOG_PID`, when set, must be ours).
    pub fn from_env() -> Notifier {
        let target = std::env::var("NOTIFY_SOCKET")
            .ok()
            .filter(|s| !s.is_empty())
            .and_then(|s| UnixDatagram::unbound().ok().map(|u| (u, s)));
        let ours = std::env::var("WATCHDOG_PID")
            .ok()
            .and_then(|p| p.parse::<u32>().ok())
            .is_none_or(|p| p == std::process::id());
        let watchdog = std::env::var("WATCHDOG_USEC")
            .ok()
            .and_then(|v| v.parse::<u64>().ok())
            .filter(|v| *v > 0 && ours)
            .map(|us| Duration::from_micros(us / 2));
        Notifier {
            target,
            watchdog,
            last: Mutex::new(None),
        }
    }

    /// Half the watchdog interval systemd asks for (the pace of `WATCHDOG=1`), if it does.
    pub fn watchdog_every(&self) -> Option<Duration> {
        self.watchdog
    }

    /// Whether systemd listens.
    pub fn enabled(&self) -> bool {
        self.target.is_some()
    }

    /// Sends `state` (e.g. `READY=1\nSTATUS=…`); errors are not the service's concern.
    pub fn send(&self, state: &str) {
        let Some((sock, path)) = &self.target else {
            return;
        };
        let _ = match path.strip_prefix('@') {
            #[cfg(target_os = "linux")]
            Some(name) => {
                use std::os::linux::net::SocketAddrExt;
                std::os::unix::net::SocketAddr::from_abstract_name(name.as_bytes())
                    .and_then(|a| sock.send_to_addr(state.as_bytes(), &a))
            }
            #[cfg(not(target_os = "linux"))]
            Some(_) => Ok(0),
            None => sock.send_to(state.as_bytes(), path),
        };
    }

    /// `WATCHDOG=1` when half the watchdog interval has passed since the last one.
    pub fn tick(&self) {
        if let Some(every) = self.watchdog {
            let mut last = self.last.lock().unwrap_or_else(|e| e.into_inner());
            if last.is_none_or(|t| t.elapsed() >= every) {
                self.send("WATCHDOG=1");
                *last = Some(Instant::now());
            }
        }
    }
}

/// How long the control loop or a shard may go without a beat before the watchdog is no
/// longer fed (half the interval systemd asks for; without a watchdog, the log still says).
fn stall_limit(n: &Notifier) -> Duration {
    n.watchdog_every()
        .unwrap_or(Duration::from_secs(5))
        .max(Duration::from_millis(500))
}

/// Feeds the watchdog while the control loop (`control`) and every shard (`shards`) beat
/// within [`stall_limit`]; says in the log which one stopped, and when it turns again.
pub(crate) async fn watchdog(n: Arc<Notifier>, control: Arc<Beat>, shards: Vec<Arc<Beat>>) {
    let limit = stall_limit(&n);
    let mut told = false;
    let mut tick = tokio::time::interval(Duration::from_millis(100));
    loop {
        tick.tick().await;
        let mut stuck = vec![];
        if control.age() > limit {
            stuck.push(format!(
                "the control loop ({:.1} s)",
                control.age().as_secs_f64()
            ));
        }
        for (k, b) in shards.iter().enumerate() {
            if b.age() > limit {
                stuck.push(format!("shard {k} ({:.1} s)", b.age().as_secs_f64()));
            }
        }
        if stuck.is_empty() {
            n.tick();
            if told {
                told = false;
                info!(
                    "every correcting shard and the control loop turn again: the watchdog is fed"
                );
            }
        } else if !told {
            told = true;
            error!(
                stuck = %stuck.join(", "),
                "no progress for more than {:.1} s: the systemd watchdog is no longer fed (the service is restarted if it does not recover)",
                limit.as_secs_f64()
            );
        }
    }
}
