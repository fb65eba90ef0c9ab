//! The Prometheus endpoint (`metrics_listen`): plain HTTP, `GET /metrics` answers the text
//! exposition format (version 0.0.4) with what the main loop last rendered (every second),
//! anything else 404. One small thread; it never touches the service's state, only the text.

use std::io::{Read, Write};
use std::net::TcpListener;
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// The latest rendering, shared with the endpoint's thread.
pub type Text = Arc<Mutex<String>>;

/// Binds `addr` and serves the text from a thread; an address that cannot be bound is an
/// error naming it.
pub fn serve(addr: &str) -> Result<Text, String> {
    let l = TcpListener::bind(addr).map_err(|e| format!("metrics_listen {addr}: {e}"))?;
    let text: Text = Arc::new(Mutex::new(String::new()));
    let t = text.clone();
    std::thread::Builder::new()
        .name("scancorrd-metrics".into())
        .spawn(move || {
            for conn in l.incoming() {
                let Ok(mut c) = conn else { continue };
                let _ = c.set_read_timeout(Some(Duration::from_secs(2)));
                let _ = c.set_write_timeout(Some(Duration::from_secs(2)));
                let mut buf = [0u8; 2048];
                let mut n = 0;
                while n < buf.len() {
                    match c.read(&mut buf[n..]) {
                        Ok(0) | Err(_) => break,
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
                    let body = t.lock().map(|s| s.clone()).unwrap_or_default();
                    format!("HTTP/1.1 200 OK\r\nContent-Type: text/plain; version=0.0.4\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}", body.len())
                } else {
                    "HTTP/1.1 404 Not Found\r\nContent-Length: 21\r\nConnection: close\r\n\r\nonly GET /metrics is\n".to_string()
                };
                let _ = c.write_all(reply.as_bytes());
            }
        })
        .map_err(|e| format!("metrics thread: {e}"))?;
    Ok(text)
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
