//! `scancorr-router`: a zenoh router built on zenoh's router mode, loading the same JSON5
//! configuration `zenohd` does (`deploy/router.json5`: TLS with client certificates, access
//! control by certificate common name). The project ships it so that a router for tests and
//! small installs is built from crates with the rest (no `zenohd` install).
//!
//! ```text
//! scancorr-router -c deploy/router.json5 [--listen ENDPOINT]...
//! ```
//! Runs until SIGTERM or Ctrl-C. A configuration error is one line on stderr and exit 2.
//!
//! Every message the access control denies a peer is a WARN line on stderr (`ACL denied …`:
//! the key expression, the peer — its certificate's subject — and the rule), at most 20 per
//! 10 s and each denial of one peer, message and key once a minute; the rest are counted in
//! one line. What it withholds from a peer (egress) is at DEBUG
//! (`RUST_LOG=warn,scancorr_router::acl=debug`).
//!
//! A peer may ask what the access control denied it: the queryable `@scancorr/router/denied`
//! (`?zid=<its zenoh id>`) answers the puts, queries and declarations it tried and was refused
//! in the last 10 minutes, each with its key expression, count and rule — a router's access
//! control drops a denied message without telling its sender, so `scancorr replay` and
//! `sim --live` ask here when their messages are not confirmed, and report a refusal.
//!
//! A TLS handshake that fails (a peer with no certificate, one of another CA, plain TCP on
//! the TLS port, a handshake timeout) is a WARN line `TLS handshake failed: …` with rustls'
//! reason (zenoh-link-tls 1.10.2 says it as an accept error with a hint about the open-file
//! limit, which is dropped), under the same budget of lines.
//!
//! `--log-format json` writes one JSON object per line (values typed); text has colour only
//! on a terminal (never in a file or a pipe, nor with `NO_COLOR` set).

use clap::Parser;
use std::path::PathBuf;

#[derive(Parser)]
#[command(
    name = "scancorr-router",
    version,
    about = "zenoh router (router mode) from a zenohd JSON5 configuration"
)]
struct Args {
    /// zenoh configuration file (JSON5), as `zenohd -c` takes.
    #[arg(short, long)]
    config: PathBuf,
    /// Replace the file's listen endpoints.
    #[arg(long)]
    listen: Vec<String>,
    /// Log lines as `text` (colour only on a terminal) or `json` (one object per line).
    #[arg(long, default_value = "text", value_parser = ["text", "json"])]
    log_format: String,
}

/// zenoh's runtimes unless `ZENOH_RUNTIME` says otherwise: four transmit and four receive
/// workers. A `Block` message for a subscriber that stopped reading (a declaration, a reply)
/// waits up to 5 s for room while holding its link's queue, and the task that pushes it (the
/// receiving task of the link it came from) and that link's transmit task each hold a worker
/// meanwhile: with zenoh's one transmit and two receive workers, every other link would
/// wait too.
const ZENOH_RUNTIME_DEFAULT: &str = "(tx: (worker_threads: 4), rx: (worker_threads: 4))";

fn main() {
    // Read once by zenoh at its first use, so set before any thread or runtime exists.
    if std::env::var_os("ZENOH_RUNTIME").is_none() {
        std::env::set_var("ZENOH_RUNTIME", ZENOH_RUNTIME_DEFAULT);
    }
    let a = Args::parse();
    let rt = match tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
    {
        Ok(rt) => rt,
        Err(e) => {
            eprintln!("scancorr-router: cannot start a runtime: {e}");
            std::process::exit(1);
        }
    };
    if let Err(e) = rt.block_on(run(a)) {
        eprintln!("scancorr-router: {e}");
        std::process::exit(2);
    }
}

async fn run(a: Args) -> Result<(), String> {
    use tracing_subscriber::prelude::*;
    let env =
        tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "warn".into());
    let (tap, tap_filter, tapped, off) = acl_tap();
    let json = a.log_format == "json";
    type Fmt = Box<dyn Layer<tracing_subscriber::Registry> + Send + Sync>;
    let fmt: Fmt = if json {
        Box::new(
            tracing_subscriber::fmt::layer()
                .json()
                .flatten_event(true)
                .with_ansi(false)
                .with_writer(std::io::stderr),
        )
    } else {
        Box::new(
            tracing_subscriber::fmt::layer()
                .with_writer(std::io::stderr)
                .with_ansi(
                    std::io::IsTerminal::is_terminal(&std::io::stderr())
                        && std::env::var_os("NO_COLOR").is_none_or(|v| v.is_empty()),
                ),
        )
    };
    tracing_subscriber::registry()
        .with(fmt.with_filter(tracing_subscriber::filter::FilterExt::and(
            env,
            NotHandshakeHint,
        )))
        .with(tap.with_filter(tap_filter))
        .init();
    let mut cfg =
        zenoh::Config::from_file(&a.config).map_err(|e| format!("{}: {e}", a.config.display()))?;
    let acl = cfg
        .get_json("access_control")
        .ok()
        .and_then(|j| serde_json::from_str::<serde_json::Value>(&j).ok())
        .unwrap_or_default();
    let book = Arc::new(Mutex::new(Book::default()));
    spawn_writer(tapped, off, Acl::from_json(&acl), book.clone());
    cfg.insert_json5("mode", "\"router\"")
        .map_err(|e| format!("mode: {e}"))?;
    if !a.listen.is_empty() {
        let eps = serde_json::to_string(&a.listen).map_err(|e| e.to_string())?;
        cfg.insert_json5("listen/endpoints", &eps)
            .map_err(|e| format!("--listen: {e}"))?;
    }
    // Installed before the session opens: a SIGTERM while it opens (peers may already be
    // routed) stops it cleanly once open, not by the signal's default action.
    let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
        .map_err(|e| e.to_string())?;
    let session = zenoh::open(cfg)
        .await
        .map_err(|e| format!("{}: {e}", a.config.display()))?;
    // What the access control denied a peer, for the peer to ask (`scancorr replay` and
    // `sim --live` do when their messages are not confirmed).
    let _denied = session
        .declare_queryable(DENIED_KEY)
        .callback(move |q| {
            let zid = q.parameters().get("zid").unwrap_or("").to_string();
            let list = book
                .lock()
                .map(|b| b.of(&zid, Instant::now()))
                .unwrap_or_default();
            let _ = zenoh::Wait::wait(q.reply(DENIED_KEY, list.to_string()));
        })
        .await
        .map_err(|e| format!("declaring {DENIED_KEY}: {e}"))?;
    if json {
        eprintln!(
            "{}",
            serde_json::json!({
                "level": "INFO",
                "target": "scancorr_router",
                "message": "routing",
                "version": env!("CARGO_PKG_VERSION"),
                "zid": session.zid().to_string(),
                "config": a.config.display().to_string(),
            })
        );
    } else {
        eprintln!(
            "scancorr-router {}: routing (zid {}) with {}",
            env!("CARGO_PKG_VERSION"),
            session.zid(),
            a.config.display()
        );
    }
    tokio::select! {
        _ = term.recv() => {}
        _ = tokio::signal::ctrl_c() => {}
    }
    session.close().await.map_err(|e| e.to_string())?;
    Ok(())
}

// ---------------------------------------------------------------------------------------------
// Access-control denials in the log.
//
// zenoh 1.10.2's ACL interceptor (zenoh/src/net/routing/interceptor/access_control.rs) says
// what it denies only at TRACE, among as many lines for what it allows (one per routed
// message), without the rule. The router taps that module's events apart from the log's own
// filter: each event site that turns out to report an allowed message is switched off for
// good (tracing's interest cache is rebuilt: no cost per message afterwards); denials go to a
// thread that names the peer (its certificate's subject), the key expression and the rule
// (from the configuration's `access_control`), and writes them at WARN (ingress: what a peer
// tried) or DEBUG (egress: declarations and messages withheld from a peer, routine), at most
// `MAX_LINES` per `WINDOW`, the rest counted in one line.

use std::collections::{HashMap, HashSet};
use std::sync::mpsc::{Receiver, RecvTimeoutError, SyncSender, TrySendError};
use std::sync::{Arc, Mutex, RwLock};
use std::time::{Duration, Instant};
use tracing::callsite::Identifier;
use tracing::{Event, Metadata, Subscriber};
use tracing_subscriber::layer::{Context, Filter, Layer};

/// zenoh's access-control module (the target of its events).
const ACL_TARGET: &str = "zenoh::net::routing::interceptor::access_control";
/// zenoh's TLS link (its listener's accept loop says a failed handshake as an accept error).
const TLS_TARGET: &str = "zenoh_link_tls::unicast";
/// What zenoh-link-tls 1.10.2 appends to every accept error, a failed handshake included.
const ACCEPT_HINT: &str = ". Hint: increase the system open file limit.";

/// A failed TLS handshake in zenoh-link-tls' accept-error line: rustls' reason. An error
/// of the listening socket itself (out of file descriptors) is not one.
fn handshake_failure(target: &str, msg: &str) -> Option<String> {
    if target != TLS_TARGET {
        return None;
    }
    let reason = msg.strip_suffix(ACCEPT_HINT)?;
    if reason.contains("os error 24") || reason.contains("Too many open files") {
        return None;
    }
    Some(reason.to_string())
}

/// The log's filter that drops zenoh-link-tls' accept-error line for a failed handshake (its
/// hint about the open-file limit misleads): the tap writes it as a handshake failure.
struct NotHandshakeHint;

impl<S: Subscriber> Filter<S> for NotHandshakeHint {
    fn enabled(&self, _: &Metadata<'_>, _: &Context<'_, S>) -> bool {
        true
    }
    fn event_enabled(&self, e: &Event<'_>, _: &Context<'_, S>) -> bool {
        if e.metadata().target() != TLS_TARGET {
            return true;
        }
        let mut m = Message(String::new());
        e.record(&mut m);
        handshake_failure(TLS_TARGET, &m.0).is_none()
    }
}
/// At most this many denial lines per [`WINDOW`]...
const MAX_LINES: u32 = 20;
/// ...the rest counted in one line when the window ends.
const WINDOW: Duration = Duration::from_secs(10);
/// The same denial (peer, message, key expression) is written once per this long.
const REPEAT: Duration = Duration::from_secs(60);

/// One event of zenoh's access control that is not an allowed message.
#[derive(Debug, Clone, PartialEq)]
enum AclEvent {
    /// A message denied: `subject` is the peer's ACL subject (`interface+cert CN+…+zid`) when
    /// the event names it.
    Denied {
        zid: String,
        subject: Option<String>,
        /// zenoh's words, e.g. `Query (ingress)`.
        what: String,
        key: String,
        /// An authorization error (not a plain denial), with its message.
        error: Option<String>,
    },
    /// A peer that matches no subject: every message it sends is denied (default deny).
    NoSubject { zid: String },
}

/// Reads one event's message.
fn parse_acl(msg: &str) -> Option<AclEvent> {
    if let Some(rest) = msg.strip_prefix("Using cached result: ") {
        let (zid, rest) = rest.split_once(" is unauthorized to ")?;
        let (what, key) = rest.rsplit_once(" on ")?;
        let key = key
            .strip_prefix("Some(")
            .and_then(|k| k.strip_suffix(')'))
            .unwrap_or(key);
        return Some(AclEvent::Denied {
            zid: zid.into(),
            subject: None,
            what: what.into(),
            key: key.into(),
            error: None,
        });
    }
    if let Some((zid, _)) = msg.split_once(" did not match any configured ACL subject") {
        return Some(AclEvent::NoSubject { zid: zid.into() });
    }
    let (zid, rest) = msg.split_once(" on ")?;
    let (subject, rest, error) = if let Some((s, r)) = rest.split_once(" is unauthorized to ") {
        (s, r.to_string(), None)
    } else {
        let (s, r) = rest.split_once(" has an authorization error to ")?;
        let (r, e) = r.rsplit_once(": ")?;
        (s, r.to_string(), Some(e.to_string()))
    };
    let (what, key) = rest.rsplit_once(" on ")?;
    Some(AclEvent::Denied {
        zid: zid.into(),
        subject: Some(subject.into()),
        what: what.into(),
        key: key.into(),
        error,
    })
}

/// Whether an event's message reports an allowed message (its site is then switched off).
fn reports_allowed(msg: &str) -> bool {
    msg.contains(" is authorized to ")
}

enum Tapped {
    Event(AclEvent),
    /// A peer's subject, from a permission computed ahead of any message (a cache).
    Peer {
        zid: String,
        subject: String,
    },
    /// An event site that reports no denial (allowed messages, …): switched off.
    Off(Identifier),
    /// A TLS handshake that failed, with rustls' reason.
    Tls(String),
}

/// `ACL (ingress): caching permissions for `K` ...`: zenoh computes every message kind's
/// permission for a key expression ahead of messages (when a resource is declared or first
/// used); the denials it finds then are no message denied. (flow is egress, key)
fn parse_caching(msg: &str) -> Option<(bool, String)> {
    let rest = msg.strip_prefix("ACL (")?;
    let (flow, rest) = rest.split_once("): caching permissions for `")?;
    let (key, _) = rest.split_once('`')?;
    Some((flow == "egress", key.to_string()))
}

thread_local! {
    /// The permissions being computed on this thread, if any: (egress, key expression).
    static CACHING: std::cell::RefCell<Option<(bool, String)>> = const { std::cell::RefCell::new(None) };
}

/// The layer: reads the access-control module's events and hands them to the writer thread.
struct AclTap {
    tx: SyncSender<Tapped>,
}

/// Its filter: the access-control module's event sites, but those that report allowed
/// messages.
struct AclFilter {
    allowed: Arc<RwLock<HashSet<Identifier>>>,
}

impl AclFilter {
    fn wanted(&self, m: &Metadata<'_>) -> bool {
        (m.target() == ACL_TARGET
            || (m.target() == TLS_TARGET && *m.level() <= tracing::Level::WARN))
            && m.is_event()
            && !self
                .allowed
                .read()
                .map(|a| a.contains(&m.callsite()))
                .unwrap_or(false)
    }
}

impl<S: Subscriber> Filter<S> for AclFilter {
    fn enabled(&self, m: &Metadata<'_>, _: &Context<'_, S>) -> bool {
        self.wanted(m)
    }
    fn callsite_enabled(&self, m: &'static Metadata<'static>) -> tracing::subscriber::Interest {
        if self.wanted(m) {
            tracing::subscriber::Interest::sometimes()
        } else {
            tracing::subscriber::Interest::never()
        }
    }
}

struct Message(String);

impl tracing::field::Visit for Message {
    fn record_debug(&mut self, f: &tracing::field::Field, v: &dyn std::fmt::Debug) {
        if f.name() == "message" {
            self.0 = format!("{v:?}");
        }
    }
    fn record_str(&mut self, f: &tracing::field::Field, v: &str) {
        if f.name() == "message" {
            self.0 = v.to_string();
        }
    }
}

impl<S: Subscriber> Layer<S> for AclTap {
    fn on_event(&self, e: &Event<'_>, _: Context<'_, S>) {
        let mut m = Message(String::new());
        e.record(&mut m);
        if e.metadata().target() == TLS_TARGET {
            // Only the failed handshakes; the link's other warnings are the log's own.
            if let Some(reason) = handshake_failure(TLS_TARGET, &m.0) {
                if let Err(TrySendError::Full(_)) = self.tx.try_send(Tapped::Tls(reason)) {
                    LOST.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                }
            }
            return;
        }
        if let Some(c) = parse_caching(&m.0) {
            CACHING.with(|x| *x.borrow_mut() = Some(c));
            return;
        }
        let tapped = if reports_allowed(&m.0) {
            Tapped::Off(e.metadata().callsite())
        } else {
            match parse_acl(&m.0) {
                Some(AclEvent::Denied {
                    zid,
                    subject: Some(subject),
                    what,
                    key,
                    error: None,
                }) if CACHING.with(|x| {
                    x.borrow().as_ref().is_some_and(|(egress, k)| {
                        *k == key && *egress == what.contains("(egress)")
                    })
                }) =>
                {
                    Tapped::Peer { zid, subject }
                }
                Some(a) => {
                    CACHING.with(|x| *x.borrow_mut() = None);
                    Tapped::Event(a)
                }
                None => Tapped::Off(e.metadata().callsite()),
            }
        };
        // A full queue (a flood the writer has not caught up with) loses lines, not time.
        if let Err(TrySendError::Full(_)) = self.tx.try_send(tapped) {
            LOST.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        }
    }
}

/// Denials not even queued (a flood faster than the writer), counted into the next summary.
static LOST: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);

/// The layer, its filter, the queue the writer thread reads and the sites switched off.
fn acl_tap() -> (
    AclTap,
    AclFilter,
    Receiver<Tapped>,
    Arc<RwLock<HashSet<Identifier>>>,
) {
    let (tx, rx) = std::sync::mpsc::sync_channel(4096);
    let off = Arc::new(RwLock::new(HashSet::new()));
    let filter = AclFilter {
        allowed: off.clone(),
    };
    (AclTap { tx }, filter, rx, off)
}

/// The configuration's access control, to name the rule behind a denial.
#[derive(Default)]
struct Acl {
    default_permission: String,
    rules: Vec<serde_json::Value>,
    subjects: Vec<serde_json::Value>,
    policies: Vec<serde_json::Value>,
}

impl Acl {
    fn from_json(v: &serde_json::Value) -> Acl {
        let list = |k: &str| v[k].as_array().cloned().unwrap_or_default();
        Acl {
            default_permission: v["default_permission"]
                .as_str()
                .unwrap_or("deny")
                .to_string(),
            rules: list("rules"),
            subjects: list("subjects"),
            policies: list("policies"),
        }
    }

    /// The configured subjects a peer's ACL subject matches (zenoh's form:
    /// `Interface(lo)+CertCommonName(operator)+Transport(Tls)+<zid>`): each attribute the
    /// entry lists has one of its values among the parts (in any case).
    fn subjects_of(&self, peer: &str) -> Vec<String> {
        let parts: HashSet<String> = subject_parts(peer)
            .into_iter()
            .map(|(_, v)| v.to_ascii_lowercase())
            .collect();
        let listed = |s: &serde_json::Value, k: &str| match s[k].as_array() {
            None => true,
            Some(vals) => vals.iter().any(|v| {
                v.as_str()
                    .is_some_and(|v| parts.contains(&v.to_ascii_lowercase()))
            }),
        };
        self.subjects
            .iter()
            .filter(|s| {
                [
                    "cert_common_names",
                    "usernames",
                    "interfaces",
                    "link_protocols",
                    "zids",
                ]
                .iter()
                .all(|k| listed(s, k))
            })
            .filter_map(|s| s["id"].as_str().map(str::to_string))
            .collect()
    }

    /// Why `message` (`query`, `put`, …) on `key` in `flow` was denied to the subjects.
    fn rule(&self, subjects: &[String], message: &str, flow: &str, key: &str) -> String {
        if subjects.is_empty() {
            return format!(
                "the peer matches no subject (default_permission: {})",
                self.default_permission
            );
        }
        let rule_ids: Vec<String> = self
            .policies
            .iter()
            .filter(|p| {
                p["subjects"].as_array().is_some_and(|s| {
                    s.iter()
                        .any(|s| s.as_str().is_some_and(|s| subjects.iter().any(|x| x == s)))
                })
            })
            .flat_map(|p| p["rules"].as_array().cloned().unwrap_or_default())
            .filter_map(|r| r.as_str().map(str::to_string))
            .collect();
        let applies = |r: &serde_json::Value| {
            let has = |k: &str, v: &str| {
                r[k].as_array()
                    .is_some_and(|a| a.iter().any(|x| x.as_str() == Some(v)))
            };
            has("messages", message) && has("flows", flow)
        };
        let includes = |r: &serde_json::Value| {
            let Ok(k) = zenoh::key_expr::KeyExpr::try_from(key) else {
                return false;
            };
            r["key_exprs"].as_array().is_some_and(|a| {
                a.iter().any(|x| {
                    x.as_str()
                        .and_then(|x| zenoh::key_expr::KeyExpr::try_from(x).ok())
                        .is_some_and(|x| x.includes(&k))
                })
            })
        };
        let mine: Vec<&serde_json::Value> = self
            .rules
            .iter()
            .filter(|r| {
                r["id"]
                    .as_str()
                    .is_some_and(|id| rule_ids.iter().any(|x| x == id))
            })
            .filter(|r| applies(r))
            .collect();
        if let Some(r) = mine
            .iter()
            .find(|r| r["permission"].as_str() == Some("deny") && includes(r))
        {
            return format!("rule `{}` denies it", r["id"].as_str().unwrap_or("?"));
        }
        let allows: Vec<&str> = mine
            .iter()
            .filter(|r| r["permission"].as_str() == Some("allow"))
            .filter_map(|r| r["id"].as_str())
            .collect();
        format!(
            "no rule of subject {} allows it (default_permission: {}); its rules for {message} {flow}: {}",
            subjects.join(", "),
            self.default_permission,
            if allows.is_empty() {
                "none".to_string()
            } else {
                allows.join(", ")
            }
        )
    }
}

/// The parts of zenoh's ACL subject, `Kind(value)+…+zid`: (kind, value), the zid's kind
/// empty.
fn subject_parts(subject: &str) -> Vec<(&str, &str)> {
    subject
        .split('+')
        .map(|p| match p.split_once('(') {
            Some((k, v)) => (k, v.strip_suffix(')').unwrap_or(v)),
            None => ("", p),
        })
        .collect()
}

/// A peer as the log names it: its certificate's common name and its zid, with the rest of
/// its ACL subject (interface, transport).
fn peer_label(subject: &str, zid: &str) -> String {
    if subject.is_empty() {
        return format!("zid {zid} (subject not yet seen)");
    }
    let parts = subject_parts(subject);
    let cn = parts
        .iter()
        .find(|(k, _)| *k == "CertCommonName")
        .map(|p| p.1);
    let rest: Vec<String> = parts
        .iter()
        .filter(|(k, v)| !k.is_empty() && *k != "CertCommonName" && *v != zid)
        .map(|(k, v)| format!("{} {v}", k.to_ascii_lowercase()))
        .collect();
    match cn {
        Some(cn) => format!("`{cn}` (zid {zid}, {})", rest.join(", ")),
        None => format!("zid {zid} (no certificate, {})", rest.join(", ")),
    }
}

/// zenoh's words for a message type, as the configuration names it.
fn message_kind(what: &str) -> (&'static str, &'static str) {
    let flow = if what.contains("(egress)") {
        "egress"
    } else {
        "ingress"
    };
    let w = what.to_ascii_lowercase();
    let kind = if w.contains("liveliness token") {
        "liveliness_token"
    } else if w.contains("liveliness query") {
        "liveliness_query"
    } else if w.contains("liveliness subscriber") {
        "declare_liveliness_subscriber"
    } else if w.contains("subscriber") {
        "declare_subscriber"
    } else if w.contains("queryable") {
        "declare_queryable"
    } else if w.starts_with("query") {
        "query"
    } else if w.starts_with("reply") {
        "reply"
    } else if w.starts_with("delete") {
        "delete"
    } else if w.starts_with("put") {
        "put"
    } else {
        "message"
    };
    (kind, flow)
}

/// A line to write.
#[derive(Debug, PartialEq)]
enum Line {
    Denied {
        warn: bool,
        message: &'static str,
        flow: &'static str,
        key: String,
        peer: String,
        zid: String,
        rule: String,
        repeats: u64,
    },
    NoSubject {
        zid: String,
        rule: String,
    },
    /// A TLS handshake failed.
    Tls {
        reason: String,
    },
    /// Denials not written in the last window.
    Suppressed {
        count: u64,
        window_s: u64,
    },
}

/// What the writer thread keeps: peers' subjects, the window's count, recent denials.
struct Writer {
    acl: Acl,
    peers: HashMap<String, String>,
    window_start: Instant,
    written: u32,
    suppressed: u64,
    /// (zid, message, flow, key) → (last written, repeats since).
    recent: HashMap<(String, &'static str, &'static str, String), (Instant, u64)>,
}

impl Writer {
    fn new(acl: Acl, now: Instant) -> Writer {
        Writer {
            acl,
            peers: HashMap::new(),
            window_start: now,
            written: 0,
            suppressed: 0,
            recent: HashMap::new(),
        }
    }

    /// Learns a peer's subject.
    fn peer(&mut self, zid: String, subject: String) {
        if self.peers.len() < 4096 || self.peers.contains_key(&zid) {
            self.peers.insert(zid, subject);
        }
    }

    /// The summary of the window that ended, if any was held back.
    fn tick(&mut self, now: Instant) -> Option<Line> {
        if now.duration_since(self.window_start) < WINDOW {
            return None;
        }
        self.window_start = now;
        self.written = 0;
        self.recent
            .retain(|_, (at, _)| now.duration_since(*at) < REPEAT);
        let lost = LOST.swap(0, std::sync::atomic::Ordering::Relaxed);
        let n = std::mem::take(&mut self.suppressed) + lost;
        (n > 0).then_some(Line::Suppressed {
            count: n,
            window_s: WINDOW.as_secs(),
        })
    }

    /// The line for a failed TLS handshake, or none (rate limit).
    fn tls(&mut self, reason: String) -> Option<Line> {
        if self.written >= MAX_LINES {
            self.suppressed += 1;
            return None;
        }
        self.written += 1;
        Some(Line::Tls { reason })
    }

    /// The line for one event, or none (rate limit, a repeat).
    fn take(&mut self, e: AclEvent, now: Instant) -> Option<Line> {
        let line = match e {
            AclEvent::NoSubject { zid } => Line::NoSubject {
                rule: self.acl.rule(&[], "", "", ""),
                zid,
            },
            AclEvent::Denied {
                zid,
                subject,
                what,
                key,
                error,
            } => {
                if let Some(s) = subject {
                    self.peer(zid.clone(), s);
                }
                let (message, flow) = message_kind(&what);
                let k = (zid.clone(), message, flow, key.clone());
                let repeats = match self.recent.get_mut(&k) {
                    Some((at, n)) if now.duration_since(*at) < REPEAT => {
                        *n += 1;
                        return None;
                    }
                    Some((at, n)) => {
                        *at = now;
                        std::mem::take(n)
                    }
                    None => {
                        if self.recent.len() < 65_536 {
                            self.recent.insert(k, (now, 0));
                        }
                        0
                    }
                };
                let peer = self.peers.get(&zid).cloned().unwrap_or_default();
                let subjects = self.acl.subjects_of(&peer);
                let mut rule = self.acl.rule(&subjects, message, flow, &key);
                if let Some(e) = error {
                    rule = format!("authorization error: {e}");
                }
                Line::Denied {
                    warn: flow == "ingress",
                    message,
                    flow,
                    key,
                    peer: peer_label(&peer, &zid),
                    zid,
                    rule,
                    repeats,
                }
            }
        };
        if matches!(line, Line::Denied { warn: false, .. }) {
            // Egress: routine, at DEBUG, outside the warnings' budget.
            return Some(line);
        }
        if self.written >= MAX_LINES {
            self.suppressed += 1;
            return None;
        }
        self.written += 1;
        Some(line)
    }
}

fn write_line(l: Line) {
    match l {
        Line::Denied {
            warn: true,
            message,
            flow,
            key,
            peer,
            zid,
            rule,
            repeats,
        } => tracing::warn!(
            target: "scancorr_router::acl",
            key_expr = %key, peer = %peer, zid = %zid, kind = message, flow, rule = %rule,
            repeats_since_last = repeats,
            "ACL denied {message} ({flow}) on {key} from {peer}: {rule}"
        ),
        Line::Denied {
            message,
            flow,
            key,
            peer,
            zid,
            rule,
            ..
        } => tracing::debug!(
            target: "scancorr_router::acl",
            key_expr = %key, peer = %peer, zid = %zid, kind = message, flow, rule = %rule,
            "ACL withheld {message} ({flow}) on {key} from {peer}: {rule}"
        ),
        Line::NoSubject { zid, rule } => tracing::warn!(
            target: "scancorr_router::acl",
            zid = %zid, rule = %rule,
            "ACL: peer {zid} connected: {rule}, every message it sends is denied"
        ),
        Line::Tls { reason } => tracing::warn!(
            target: "scancorr_router::tls",
            reason = %reason,
            "TLS handshake failed: {reason} (a peer without a certificate of this CA, plain TCP on the TLS port, or a handshake timeout: refused)"
        ),
        Line::Suppressed { count, window_s } => tracing::warn!(
            target: "scancorr_router::acl",
            count, window_s,
            "ACL: {count} more denial(s) in the last {window_s} s not logged (at most {MAX_LINES} lines per {window_s} s; repeats of one denial once per {} s)",
            REPEAT.as_secs()
        ),
    }
}

/// The queryable at which a peer asks what the access control denied it (`?zid=<its zenoh
/// id>`): a JSON list of `{message, flow, key, peer, rule, count, last_s_ago}`, what it tried
/// (ingress) in the last [`BOOK_KEEP`]. The configuration's access control must allow the query
/// (ingress) and its reply (egress) on this key (`deploy/router.json5`: `own-denials`). Any
/// peer allowed to ask may ask about any zenoh id: it learns key expressions and rule names.
const DENIED_KEY: &str = "@scancorr/router/denied";
/// A denial is kept this long for its peer to ask.
const BOOK_KEEP: Duration = Duration::from_secs(600);

/// One kind of denial of one peer: (message, key) with its count.
struct Noted {
    message: &'static str,
    key: String,
    peer: String,
    rule: String,
    count: u64,
    last: Instant,
}

/// The denials of every peer (ingress), for it to ask: at most 4096 peers, 256 kinds each.
#[derive(Default)]
struct Book {
    by_zid: HashMap<String, Vec<Noted>>,
}

impl Book {
    /// Notes a denial (`w` names the peer and the rule, once per kind).
    fn note(
        &mut self,
        w: &Writer,
        zid: &str,
        what: &str,
        key: &str,
        error: Option<&str>,
        now: Instant,
    ) {
        let (message, flow) = message_kind(what);
        if flow != "ingress" {
            return;
        }
        if self.by_zid.len() >= 4096 && !self.by_zid.contains_key(zid) {
            self.by_zid
                .retain(|_, v| v.iter().any(|n| now.duration_since(n.last) < BOOK_KEEP));
            if self.by_zid.len() >= 4096 {
                return;
            }
        }
        let list = self.by_zid.entry(zid.to_string()).or_default();
        if let Some(n) = list
            .iter_mut()
            .find(|n| n.message == message && n.key == key)
        {
            n.count += 1;
            n.last = now;
            return;
        }
        list.retain(|n| now.duration_since(n.last) < BOOK_KEEP);
        if list.len() >= 256 {
            return;
        }
        let peer = w.peers.get(zid).cloned().unwrap_or_default();
        let rule = match error {
            Some(e) => format!("authorization error: {e}"),
            None => w.acl.rule(&w.acl.subjects_of(&peer), message, flow, key),
        };
        list.push(Noted {
            message,
            key: key.to_string(),
            peer: peer_label(&peer, zid),
            rule,
            count: 1,
            last: now,
        });
    }

    /// What `zid` was denied, as the queryable answers.
    fn of(&self, zid: &str, now: Instant) -> serde_json::Value {
        let list: Vec<serde_json::Value> = self
            .by_zid
            .get(zid)
            .map(|v| {
                v.iter()
                    .filter(|n| now.duration_since(n.last) < BOOK_KEEP)
                    .map(|n| {
                        serde_json::json!({
                            "message": n.message, "flow": "ingress", "key": n.key,
                            "peer": n.peer, "rule": n.rule, "count": n.count,
                            "last_s_ago": now.duration_since(n.last).as_secs(),
                        })
                    })
                    .collect()
            })
            .unwrap_or_default();
        serde_json::Value::Array(list)
    }
}

/// The writer thread: denials from the tap, switched-off sites, the window's summary.
fn spawn_writer(
    rx: Receiver<Tapped>,
    allowed: Arc<RwLock<HashSet<Identifier>>>,
    acl: Acl,
    book: Arc<Mutex<Book>>,
) {
    let _ = std::thread::Builder::new()
        .name("acl-log".into())
        .spawn(move || {
            let mut w = Writer::new(acl, Instant::now());
            loop {
                let got = rx.recv_timeout(Duration::from_secs(1));
                if let Some(l) = w.tick(Instant::now()) {
                    write_line(l);
                }
                match got {
                    Ok(Tapped::Event(e)) => {
                        if let AclEvent::Denied {
                            zid,
                            subject,
                            what,
                            key,
                            error,
                        } = &e
                        {
                            if let Some(s) = subject {
                                w.peer(zid.clone(), s.clone());
                            }
                            if let Ok(mut b) = book.lock() {
                                b.note(&w, zid, what, key, error.as_deref(), Instant::now());
                            }
                        }
                        if let Some(l) = w.take(e, Instant::now()) {
                            write_line(l);
                        }
                    }
                    Ok(Tapped::Peer { zid, subject }) => w.peer(zid, subject),
                    Ok(Tapped::Tls(reason)) => {
                        if let Some(l) = w.tls(reason) {
                            write_line(l);
                        }
                    }
                    Ok(Tapped::Off(id)) => {
                        let new = allowed.write().map(|mut a| a.insert(id)).unwrap_or(false);
                        if new {
                            tracing::callsite::rebuild_interest_cache();
                        }
                    }
                    Err(RecvTimeoutError::Timeout) => {}
                    Err(RecvTimeoutError::Disconnected) => break,
                }
            }
        });
}

#[cfg(test)]
mod tests {
    use super::*;

    fn deploy_acl() -> Acl {
        let text = std::fs::read_to_string(
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../deploy/router.json5"),
        )
        .unwrap();
        let v: serde_json::Value = json5::from_str(&text).unwrap();
        Acl::from_json(&v["access_control"])
    }

    #[test]
    fn zenohs_acl_lines_are_read() {
        assert_eq!(
            parse_acl("5f1e on Interface(lo)+CertCommonName(auditor)+Transport(Tls)+5f1e is unauthorized to Query (ingress) on cmm/m1/calibration/write"),
            Some(AclEvent::Denied {
                zid: "5f1e".into(),
                subject: Some("Interface(lo)+CertCommonName(auditor)+Transport(Tls)+5f1e".into()),
                what: "Query (ingress)".into(),
                key: "cmm/m1/calibration/write".into(),
                error: None
            })
        );
        assert_eq!(
            parse_acl(
                "Using cached result: 5f1e is unauthorized to Put (ingress) on cmm/m1/raw/scale"
            ),
            Some(AclEvent::Denied {
                zid: "5f1e".into(),
                subject: None,
                what: "Put (ingress)".into(),
                key: "cmm/m1/raw/scale".into(),
                error: None
            })
        );
        assert!(matches!(
            parse_acl("Using cached result: 5f1e is unauthorized to Undeclare Subscriber (ingress) on Some(cmm/a)"),
            Some(AclEvent::Denied { key, .. }) if key == "cmm/a"
        ));
        assert_eq!(
            parse_acl("77aa did not match any configured ACL subject. Default permission `Deny` will be applied on all messages"),
            Some(AclEvent::NoSubject { zid: "77aa".into() })
        );
        assert!(reports_allowed(
            "Using cached result: 5f1e is authorized to Put (ingress) on cmm/m1/raw/scale"
        ));
        assert!(!reports_allowed(
            "Using cached result: 5f1e is unauthorized to Put (ingress) on cmm/m1/raw/scale"
        ));
        assert_eq!(
            parse_caching("ACL (egress): caching permissions for `cmm/m1/status` ..."),
            Some((true, "cmm/m1/status".into()))
        );
        assert_eq!(parse_acl("Access control is enabled"), None);
    }

    #[test]
    fn a_denial_names_the_rule_of_the_shipped_configuration() {
        let acl = deploy_acl();
        let peer = "Interface(lo)+CertCommonName(auditor)+Transport(Tls)+5f1e";
        assert_eq!(acl.subjects_of(peer), ["auditors"]);
        assert_eq!(
            peer_label(peer, "5f1e"),
            "`auditor` (zid 5f1e, interface lo, transport Tls)"
        );
        let r = acl.rule(
            &acl.subjects_of(peer),
            "query",
            "ingress",
            "cmm/m1/calibration/write",
        );
        assert_eq!(
            r,
            "no rule of subject auditors allows it (default_permission: deny); its rules for query ingress: ask-status, ask-calibration, own-denials"
        );
        let r = acl.rule(
            &acl.subjects_of("Interface(lo)+CertCommonName(app-shape-analysis)+Transport(Tls)+1"),
            "put",
            "ingress",
            "cmm/m1/raw/scale",
        );
        assert!(
            r.contains("subject apps") && r.ends_with("put ingress: none"),
            "{r}"
        );
        assert!(acl.rule(&[], "", "", "").contains("matches no subject"));
        // An explicit deny rule is named.
        let mut v: serde_json::Value = serde_json::json!({
            "default_permission": "allow",
            "rules": [{"id": "no-raw", "messages": ["put"], "flows": ["ingress"], "permission": "deny", "key_exprs": ["cmm/*/raw/**"]}],
            "subjects": [{"id": "apps", "cert_common_names": ["app"]}],
            "policies": [{"rules": ["no-raw"], "subjects": ["apps"]}]
        });
        let acl = Acl::from_json(&v);
        assert_eq!(
            acl.rule(&["apps".into()], "put", "ingress", "cmm/m1/raw/scale"),
            "rule `no-raw` denies it"
        );
        v["rules"][0]["key_exprs"] = serde_json::json!(["cmm/m2/**"]);
        assert!(Acl::from_json(&v)
            .rule(&["apps".into()], "put", "ingress", "cmm/m1/raw/scale")
            .starts_with("no rule"));
    }

    #[test]
    fn a_flood_of_denials_writes_a_bounded_number_of_lines_and_counts_the_rest() {
        let t0 = Instant::now();
        let mut w = Writer::new(deploy_acl(), t0);
        w.peer(
            "5f1e".into(),
            "Interface(lo)+CertCommonName(app-shape-analysis)+Transport(Tls)+5f1e".into(),
        );
        let denied = |k: usize| AclEvent::Denied {
            zid: "5f1e".into(),
            subject: None,
            what: "Put (ingress)".into(),
            key: format!("cmm/m1/raw/x{k}"),
            error: None,
        };
        let mut lines = vec![];
        for k in 0..10_000 {
            lines.extend(w.take(denied(k), t0 + Duration::from_micros(k as u64)));
        }
        assert_eq!(lines.len(), MAX_LINES as usize);
        match &lines[0] {
            Line::Denied {
                warn: true,
                message: "put",
                flow: "ingress",
                key,
                peer,
                rule,
                ..
            } => {
                assert_eq!(key, "cmm/m1/raw/x0");
                assert!(peer.contains("app-shape-analysis"));
                assert!(rule.contains("subject apps"), "{rule}");
            }
            l => panic!("{l:?}"),
        }
        assert_eq!(w.tick(t0 + Duration::from_secs(1)), None);
        assert_eq!(
            w.tick(t0 + WINDOW),
            Some(Line::Suppressed {
                count: 10_000 - MAX_LINES as u64,
                window_s: WINDOW.as_secs()
            })
        );
        // The same denial again within a minute: counted, not written; after it, written
        // with the number of repeats.
        let t1 = t0 + WINDOW;
        assert_eq!(w.take(denied(0), t1), None);
        let l = w.take(denied(0), t0 + REPEAT + Duration::from_secs(1));
        assert!(matches!(l, Some(Line::Denied { repeats: 1, .. })), "{l:?}");
        // Egress: routine, DEBUG, outside the budget.
        let l = w.take(
            AclEvent::Denied {
                zid: "5f1e".into(),
                subject: None,
                what: "Declare/Undeclare Subscriber (egress)".into(),
                key: "cmm/m1/raw/**".into(),
                error: None,
            },
            t1,
        );
        assert!(matches!(l, Some(Line::Denied { warn: false, .. })), "{l:?}");
    }
}
