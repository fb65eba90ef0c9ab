//! The Prometheus endpoint (`metrics_listen`): plain HTTP, `GET /metrics` answers the text
//! exposition format (version 0.0.4) with what the main loop last rendered (every second),
//! anything else 404. It never touches the service's state, only the text.
//!
//! Connections are served concurrently, each on its own small thread, at most
//! [`MAX_CONNECTIONS`] at once (one more is answered `503` at once and closed). Each has
//! [`REQUEST_DEADLINE`] for its whole request and as long again for its reply, however its
//! bytes are paced: a client that trickles its request (a byte every 1.5 s) loses its own
//! connection and holds up no other.

use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// The latest rendering, shared with the endpoint's thread.
pub type Text = Arc<Mutex<String>>;

/// Most connections served at once.
pub const MAX_CONNECTIONS: usize = 16;

/// Time a connection has for its whole request (the request line and headers); its reply
/// has as long again.
pub const REQUEST_DEADLINE: Duration = Duration::from_secs(2);

/// Largest request head read, bytes.
const MAX_REQUEST: usize = 2048;

/// Binds `addr` and serves the text from a thread; an address that cannot be bound is an
/// error naming it.
pub fn serve(addr: &str) -> Result<Text, String> {
    let l = TcpListener::bind(addr).map_err(|e| format!("metrics_listen {addr}: {e}"))?;
    serve_on(l)
}

/// Serves the text on a bound listener (see the module's description).
pub fn serve_on(l: TcpListener) -> Result<Text, String> {
    let text: Text = Arc::new(Mutex::new(String::new()));
    let t = text.clone();
    let active = Arc::new(AtomicUsize::new(0));
    std::thread::Builder::new()
        .name("scancorrd-metrics".into())
        .spawn(move || {
            for conn in l.incoming() {
                let Ok(mut c) = conn else { continue };
                if active.load(Ordering::Acquire) >= MAX_CONNECTIONS {
                    // Busy: said at once (the reply fits any socket buffer), never waited on.
                    let _ = c.set_write_timeout(Some(Duration::from_millis(100)));
                    let _ = c.write_all(BUSY.as_bytes());
                    continue;
                }
                let slot = Slot::take(&active);
                let t = t.clone();
                // (A thread that cannot be started drops the connection and its slot.)
                let _ = std::thread::Builder::new()
                    .name("scancorrd-metrics-conn".into())
                    .spawn(move || {
                        let _slot = slot;
                        answer(c, &t);
                    });
            }
        })
        .map_err(|e| format!("metrics thread: {e}"))?;
    Ok(text)
}

/// One of the [`MAX_CONNECTIONS`], given back when dropped (even by a panicking thread).
struct Slot(Arc<AtomicUsize>);

impl Slot {
    fn take(active: &Arc<AtomicUsize>) -> Slot {
        active.fetch_add(1, Ordering::AcqRel);
        Slot(active.clone())
    }
}

impl Drop for Slot {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::AcqRel);
    }
}

const BUSY: &str = "HTTP/1.1 503 Service Unavailable\r\nContent-Length: 5\r\nRetry-After: 1\r\nConnection: close\r\n\r\nbusy\n";

/// Reads one request head within [`REQUEST_DEADLINE`] and answers it within as long again.
fn answer(mut c: TcpStream, text: &Text) {
    let deadline = Instant::now() + REQUEST_DEADLINE;
    let mut buf = [0u8; MAX_REQUEST];
    let mut n = 0;
    let mut timed_out = false;
    while n < buf.len() {
        let left = deadline.saturating_duration_since(Instant::now());
        if left.is_zero() || c.set_read_timeout(Some(left)).is_err() {
            timed_out = true;
            break;
        }
        match c.read(&mut buf[n..]) {
            Ok(0) => break,
            Err(e) => {
                use std::io::ErrorKind::{TimedOut, WouldBlock};
                timed_out = matches!(e.kind(), TimedOut | WouldBlock);
                break;
            }
            Ok(k) => {
                n += k;
                if buf[..n].windows(4).any(|w| w == b"\r\n\r\n") {
                    break;
                }
            }
        }
    }
    let req = String::from_utf8_lossy(&buf[..n]);
    let first = req.lines().next().unwrap_or("");
    let reply = if first.starts_with("GET /metrics ") || first == "GET /metrics" {
        let body = text.lock().map(|s| s.clone()).unwrap_or_default();
        format!("HTTP/1.1 200 OK\r\nContent-Type: text/plain; version=0.0.4\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}", body.len())
    } else if timed_out {
        "HTTP/1.1 408 Request Timeout\r\nContent-Length: 17\r\nConnection: close\r\n\r\nrequest too slow\n".to_string()
    } else {
        "HTTP/1.1 404 Not Found\r\nContent-Length: 21\r\nConnection: close\r\n\r\nonly GET /metrics is\n".to_string()
    };
    // The reply within its own deadline, however slowly the client reads.
    let deadline = Instant::now() + REQUEST_DEADLINE;
    let mut rest = reply.as_bytes();
    while !rest.is_empty() {
        let left = deadline.saturating_duration_since(Instant::now());
        if left.is_zero() || c.set_write_timeout(Some(left)).is_err() {
            break;
        }
        match c.write(rest) {
            Ok(0) | Err(_) => break,
            Ok(k) => rest = &rest[k..],
        }
    }
}

/// Builds the exposition text: `# HELP`/`# TYPE` once per metric, then its samples.
#[derive(Default)]
pub struct Render {
    out: String,
}

impl Render {
    /// Starts metric `name` (`counter` or `gauge`).
    pub fn metric(&mut self, name: &str, kind: &str, help: &str) {
        use std::fmt::Write;
        let _ = writeln!(self.out, "# HELP {name} {help}\n# TYPE {name} {kind}");
    }
    /// One sample with labels (values are machine ids and fixed words: no escaping needed
    /// beyond quotes, which names cannot hold).
    pub fn sample(&mut self, name: &str, labels: &[(&str, &str)], v: f64) {
        use std::fmt::Write;
        let l: Vec<String> = labels.iter().map(|(k, v)| format!("{k}=\"{v}\"")).collect();
        if l.is_empty() {
            let _ = writeln!(self.out, "{name} {v}");
        } else {
            let _ = writeln!(self.out, "{name}{{{}}} {v}", l.join(","));
        }
    }
    /// The text.
    pub fn finish(self) -> String {
        self.out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn get(port: u16) -> (String, Duration) {
        let t0 = Instant::now();
        let mut c = TcpStream::connect(("127.0.0.1", port)).unwrap();
        c.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
        c.write_all(b"GET /metrics HTTP/1.1\r\nHost: x\r\n\r\n")
            .unwrap();
        let mut s = String::new();
        let _ = c.read_to_string(&mut s);
        (s, t0.elapsed())
    }

    /// Issue 44: one client sending a byte every 1.5 s blinded the endpoint for everyone (each
    /// byte renewed a 2 s read timeout, and connections were served one after another).
    #[test]
    fn a_trickling_client_blinds_no_one_and_loses_its_own_connection() {
        let l = TcpListener::bind("127.0.0.1:0").unwrap();
        let port = l.local_addr().unwrap().port();
        let text = serve_on(l).unwrap();
        *text.lock().unwrap() = "scancorr_up 1\n".into();
        let slow = std::thread::spawn(move || {
            let t0 = Instant::now();
            let mut c = TcpStream::connect(("127.0.0.1", port)).unwrap();
            for b in b"GET /metrics HTTP/1.1\r\n\r\n" {
                if c.write_all(&[*b]).is_err() {
                    break;
                }
                // Closed by the service: a read sees its end (or its 408).
                c.set_read_timeout(Some(Duration::from_millis(1500)))
                    .unwrap();
                let mut s = String::new();
                if c.read_to_string(&mut s).is_ok() {
                    return (s, t0.elapsed());
                }
            }
            (String::new(), t0.elapsed())
        });
        std::thread::sleep(Duration::from_millis(200));
        // Others are answered at once, again and again, while it trickles.
        for _ in 0..3 {
            let (r, took) = get(port);
            assert!(
                r.starts_with("HTTP/1.1 200") && r.ends_with("scancorr_up 1\n"),
                "{r}"
            );
            assert!(took < Duration::from_millis(500), "answered after {took:?}");
            std::thread::sleep(Duration::from_millis(300));
        }
        let (r, took) = slow.join().unwrap();
        assert!(r.starts_with("HTTP/1.1 408"), "{r:?}");
        assert!(
            took >= REQUEST_DEADLINE && took < REQUEST_DEADLINE + Duration::from_secs(2),
            "the trickling client was cut off after {took:?}"
        );
    }

    #[test]
    fn connections_beyond_the_cap_are_told_busy_and_served_again_once_freed() {
        let l = TcpListener::bind("127.0.0.1:0").unwrap();
        let port = l.local_addr().unwrap().port();
        let _text = serve_on(l).unwrap();
        let idle: Vec<TcpStream> = (0..MAX_CONNECTIONS)
            .map(|_| TcpStream::connect(("127.0.0.1", port)).unwrap())
            .collect();
        std::thread::sleep(Duration::from_millis(200));
        let (r, took) = get(port);
        assert!(r.starts_with("HTTP/1.1 503"), "{r}");
        assert!(took < Duration::from_millis(500), "{took:?}");
        // Idle connections are cut at their deadline; then every slot is free again.
        std::thread::sleep(REQUEST_DEADLINE + Duration::from_millis(300));
        let (r, _) = get(port);
        assert!(r.starts_with("HTTP/1.1 200"), "{r}");
        drop(idle);
    }
}
