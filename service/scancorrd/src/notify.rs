//! systemd readiness and watchdog (`Type=notify`, `WatchdogSec=`): datagrams to the socket
//! systemd names in `NOTIFY_SOCKET` (a path, or `@name` in Linux's abstract namespace).
//! Without that variable every call does nothing.
//!
//! `READY=1` once the subscriptions, queryables and stored machines are up; `WATCHDOG=1` at
//! half the interval systemd asks for in `WATCHDOG_USEC`, from the service's main loop (so a
//! loop that stops turning is restarted); `STOPPING=1` when shutting down.

use std::os::unix::net::UnixDatagram;
use std::time::{Duration, Instant};

/// The notification socket and the watchdog's pace.
pub struct Notifier {
    target: Option<(UnixDatagram, String)>,
    watchdog: Option<Duration>,
    last: Option<Instant>,
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
            last: None,
        }
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
    pub fn tick(&mut self) {
        if let Some(every) = self.watchdog {
            if self.last.is_none_or(|t| t.elapsed() >= every) {
                self.send("WATCHDOG=1");
                self.last = Some(Instant::now());
            }
        }
    }
}
