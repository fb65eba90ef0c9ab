//! The zenoh client of the bus commands (`calib put|get|history`, `status`, `health`,
//! `replay`, `record`, `tail`, `sim --live`, `lab history --machine`): here the session, its
//! configuration and the queries; `replay` (bag → bus, with its delivery ledger), `record`
//! (bus → bag) and `tail` each in their own file.
//!
//! Each opens a zenoh session in client mode, connected to `--connect` (scancorrd, which runs
//! as a peer, or a router), does its job and closes. Client mode matters: a peer forwards
//! what its clients publish to every other client and peer, but not what one peer publishes
//! to another peer (peers are expected to reach each other directly). CLI sessions opened as
//! peers without listening endpoints could not reach each other, so `record` saw nothing of
//! what `sim --live` published through scancorrd. A client also fails at once when nothing
//! listens at the endpoint, where a peer would keep trying in the background.
//!
//! Nothing fails silently: an endpoint with nothing listening, a publisher nobody subscribes
//! to, a recording or a tail that received nothing, a machine the service does not serve —
//! each is an error on stderr and a non-zero exit.

use crate::shared::output::AtomicOutput;
use anyhow::{bail, Context, Result};
use scancorr_bag::{BagHeader, BagReader, BagWriter, Stream};
use scancorr_proto::Message;
use std::path::Path;
use std::time::{Duration, Instant};
use zenoh::qos::CongestionControl;

mod record;
mod replay;
mod tail;

pub use record::record;
pub use replay::replay;
pub use tail::tail;

/// The endpoint when neither `--connect` nor a zenoh configuration names one.
const DEFAULT_ENDPOINT: &str = "tcp/127.0.0.1:7447";

/// Where the bus is.
#[derive(clap::Args, Clone, Debug)]
pub struct Bus {
    /// Zenoh endpoint of scancorrd or a router (PROTOCOL/HOST:PORT; repeatable). Default:
    /// the zenoh configuration's `connect.endpoints`, else tcp/127.0.0.1:7447.
    #[arg(long)]
    pub connect: Vec<String>,
    /// A zenoh configuration file (JSON5), as zenoh's own tools take one: TLS certificates,
    /// endpoints, timeouts (the deployment's `deploy/` files). The CLI always runs as a
    /// client; `--connect` replaces the file's endpoints.
    #[arg(long, value_name = "FILE")]
    pub zenoh_config: Option<std::path::PathBuf>,
    /// Key-expression prefix.
    #[arg(long, default_value = scancorr_proto::DEFAULT_PREFIX)]
    pub prefix: String,
}

/// Zenoh's link protocols.
const PROTOCOLS: [&str; 10] = [
    "tcp",
    "udp",
    "tls",
    "quic",
    "ws",
    "unixsock-stream",
    "unixpipe",
    "serial",
    "vsock",
    "quic_datagram",
];

impl Bus {
    /// Checks `--prefix` and every `--connect` endpoint before anything is done.
    pub fn check(&self) -> Result<()> {
        crate::shared::output::check_prefix(&self.prefix)?;
        for e in &self.connect {
            check_endpoint(e)?;
        }
        self.config().map(|_| ())
    }

    /// The zenoh configuration of a CLI session: the file's (or zenoh's defaults) as a
    /// client, no listening, no multicast scouting, the endpoints of `--connect` (or the
    /// file's, or the default). Errors name the file or the key.
    pub fn config(&self) -> Result<zenoh::Config> {
        let mut cfg = match &self.zenoh_config {
            Some(p) => zenoh::Config::from_file(p).map_err(|e| {
                anyhow::anyhow!(
                    "--zenoh-config {}: {}",
                    p.display(),
                    one_line(&e.to_string())
                )
            })?,
            None => zenoh::Config::default(),
        };
        if let Some(p) = &self.zenoh_config {
            check_tls_files(&cfg, &format!("--zenoh-config {}", p.display()))?;
        }
        let endpoints = self.endpoint_list(&cfg)?;
        for (k, v) in [
            ("mode", "\"client\"".to_string()),
            ("listen/endpoints", "[]".to_string()),
            ("scouting/multicast/enabled", "false".to_string()),
            (
                "connect/endpoints",
                serde_json::to_string(&endpoints).expect("strings"),
            ),
        ] {
            cfg.insert_json5(k, &v)
                .map_err(|e| anyhow::anyhow!("zenoh configuration `{k}`: {e}"))?;
        }
        Ok(cfg)
    }

    /// `--connect`, else the configuration file's endpoints, else the default.
    fn endpoint_list(&self, cfg: &zenoh::Config) -> Result<Vec<String>> {
        if !self.connect.is_empty() {
            return Ok(self.connect.clone());
        }
        if self.zenoh_config.is_some() {
            let from_file: Vec<String> = cfg
                .get_json("connect/endpoints")
                .ok()
                .and_then(|j| serde_json::from_str::<serde_json::Value>(&j).ok())
                .map(|v| {
                    // A list, or per-mode lists ({ router: [...], peer: [...], client: [...] }).
                    let list = v.get("client").cloned().unwrap_or(v);
                    list.as_array()
                        .map(|a| {
                            a.iter()
                                .filter_map(|e| e.as_str().map(String::from))
                                .collect()
                        })
                        .unwrap_or_default()
                })
                .unwrap_or_default();
            if !from_file.is_empty() {
                return Ok(from_file);
            }
        }
        Ok(vec![DEFAULT_ENDPOINT.to_string()])
    }

    fn endpoints(&self) -> String {
        match self.config().and_then(|c| {
            let j = c.get_json("connect/endpoints").map_err(z)?;
            let list: Vec<String> = serde_json::from_str(&j)?;
            Ok(list)
        }) {
            Ok(l) => l.join(", "),
            Err(_) => self.connect.join(", "),
        }
    }
}

/// The TLS files a zenoh configuration may name (under `transport/link/tls/`).
const TLS_FILES: [&str; 5] = [
    "root_ca_certificate",
    "connect_certificate",
    "connect_private_key",
    "listen_certificate",
    "listen_private_key",
];

/// Each TLS certificate and key the configuration names must be a readable file: a missing
/// one is named with its key (zenoh itself would only fail to connect).
fn check_tls_files(cfg: &zenoh::Config, source: &str) -> Result<()> {
    for name in TLS_FILES {
        let key = format!("transport/link/tls/{name}");
        let Some(path) = cfg
            .get_json(&key)
            .ok()
            .and_then(|j| serde_json::from_str::<Option<String>>(&j).ok())
            .flatten()
            .filter(|p| !p.is_empty())
        else {
            continue;
        };
        if let Err(e) = std::fs::File::open(&path).and_then(|mut f| {
            use std::io::Read;
            f.read(&mut [0u8; 1]).map(|_| ())
        }) {
            let why = e.to_string();
            let why = why.split(" (os error").next().unwrap_or(&why);
            bail!("{source}: `{key}`: cannot read the TLS certificate or key file {path}: {why}");
        }
    }
    Ok(())
}

/// Endpoints (tcp/, tls/, ws/) at which something accepts a TCP connection within `timeout`.
fn listening(endpoints: &[String], timeout: Duration) -> Vec<String> {
    use std::net::ToSocketAddrs;
    endpoints
        .iter()
        .filter(|e| {
            let Some((proto, addr)) = e.split_once('/') else {
                return false;
            };
            if !matches!(proto, "tcp" | "tls" | "ws") {
                return false;
            }
            let addr = addr.split(['?', '#']).next().unwrap_or(addr);
            addr.to_socket_addrs()
                .ok()
                .and_then(|mut a| a.next())
                .is_some_and(|a| std::net::TcpStream::connect_timeout(&a, timeout).is_ok())
        })
        .cloned()
        .collect()
}

/// An endpoint is `PROTOCOL/ADDRESS` (`tcp/127.0.0.1:7447`), optionally with `?` or `#`
/// parameters.
fn check_endpoint(e: &str) -> Result<()> {
    let shown = scancorr_proto::names::shown(e);
    match e.split_once('/') {
        Some((proto, addr)) if PROTOCOLS.contains(&proto) => {
            if addr.is_empty() || addr.starts_with(['?', '#']) {
                bail!("--connect {shown}: no address after `{proto}/`; use {proto}/HOST:PORT, e.g. tcp/127.0.0.1:7447");
            }
            Ok(())
        }
        Some((proto, _)) => bail!(
            "--connect {shown}: unknown protocol `{}` (zenoh knows {}); use tcp/HOST:PORT, e.g. tcp/127.0.0.1:7447",
            proto.escape_debug(),
            PROTOCOLS.join(", ")
        ),
        None => bail!(
            "--connect {shown}: an endpoint names its protocol; use tcp/HOST:PORT, e.g. tcp/{}",
            if e.contains(':') { e.to_string() } else { "127.0.0.1:7447".into() }
        ),
    }
}

fn rt() -> Result<tokio::runtime::Runtime> {
    Ok(tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?)
}

fn z(e: impl std::fmt::Display) -> anyhow::Error {
    anyhow::anyhow!("{e}")
}

async fn open(bus: &Bus) -> Result<zenoh::Session> {
    bus.check()?;
    let cfg = bus.config()?;
    // A client tries each endpoint once and fails when none answers (zenoh's client defaults,
    // made explicit): the CLI never waits in silence for a service that is not there.
    let mut cfg = cfg;
    for (k, v) in [
        ("connect/timeout_ms", "0"),
        ("connect/exit_on_failure", "true"),
    ] {
        cfg.insert_json5(k, v)
            .map_err(|e| anyhow::anyhow!("zenoh configuration `{k}`: {e}"))?;
    }
    let endpoints = cfg
        .get_json("connect/endpoints")
        .ok()
        .and_then(|j| serde_json::from_str::<Vec<String>>(&j).ok())
        .unwrap_or_default();
    let open = zenoh::open(cfg);
    let why = match tokio::time::timeout(Duration::from_secs(8), open).await {
        Ok(Ok(s)) => return Ok(s),
        Ok(Err(e)) => one_line(&e.to_string()),
        Err(_) => "no answer within 8 s".to_string(),
    };
    // Something listening there, yet no session: a refusal (a TLS handshake the router
    // rejected, or no zenoh there), not an absence.
    let at = tokio::task::spawn_blocking(move || listening(&endpoints, Duration::from_millis(500)))
        .await
        .unwrap_or_default();
    if !at.is_empty() {
        bail!(
            "cannot connect to {}: something listens at {} but no zenoh session was established (for tls/: the router refused the TLS handshake — a certificate it does not accept, or none; or no zenoh there) [zenoh: {why}]",
            bus.endpoints(),
            at.join(", ")
        );
    }
    bail!(
        "cannot connect to {}: nothing answers there (is scancorrd or a zenoh router running and listening on it?) [zenoh: {why}]",
        bus.endpoints()
    )
}

/// A zenoh error on one line, without the source location zenoh appends (` at FILE:LINE.`).
fn one_line(s: &str) -> String {
    let s = match s.rfind(" at /") {
        Some(i) if s.trim_end().ends_with('.') => &s[..i],
        _ => s,
    };
    let s = s.split_whitespace().collect::<Vec<_>>().join(" ");
    if s.chars().count() > 300 {
        format!("{}…", s.chars().take(300).collect::<String>())
    } else {
        s
    }
}

/// Who is asking, for the service's audit trail, from this session and its connection:
/// `user@host; zid=<this session's zenoh id>; cn=<the subject's common name of the certificate
/// it connects with>` (the certificate the router's access control admitted, read from the
/// zenoh configuration's `connect_certificate`; no `cn` without TLS). The user is `$USER`,
/// else `$LOGNAME`, else the process's `uid N` — never a made-up name.
pub fn requester(zid: &str, cn: Option<&str>) -> String {
    let user = std::env::var("USER")
        .or_else(|_| std::env::var("LOGNAME"))
        .ok()
        .filter(|u| !u.trim().is_empty())
        .or_else(|| {
            std::fs::read_to_string("/proc/self/status")
                .ok()
                .and_then(|s| {
                    s.lines()
                        .find_map(|l| l.strip_prefix("Uid:"))
                        .and_then(|l| l.split_whitespace().next().map(|u| format!("uid {u}")))
                })
        })
        .unwrap_or_default();
    let host = std::fs::read_to_string("/proc/sys/kernel/hostname")
        .map(|h| h.trim().to_string())
        .unwrap_or_else(|_| "localhost".into());
    let mut r = format!("{user}@{host}; zid={zid}");
    if let Some(cn) = cn {
        r += &format!("; cn={cn}");
    }
    r
}

/// The subject's common name of the certificate a zenoh configuration connects with
/// (`transport/link/tls/connect_certificate`, PEM), or what keeps it from being read.
pub fn certificate_cn(cfg: &zenoh::Config) -> Option<String> {
    let path = cfg
        .get_json("transport/link/tls/connect_certificate")
        .ok()
        .and_then(|j| serde_json::from_str::<Option<String>>(&j).ok())
        .flatten()?;
    let pem = match std::fs::read(&path) {
        Ok(p) => p,
        Err(e) => return Some(format!("(certificate {path} unreadable: {e})")),
    };
    let cn = x509_parser::pem::parse_x509_pem(&pem)
        .ok()
        .and_then(|(_, p)| {
            let cert = p.parse_x509().ok()?;
            let cn = cert
                .subject()
                .iter_common_name()
                .next()
                .and_then(|c| c.as_str().ok())
                .map(str::to_string);
            cn
        });
    Some(cn.unwrap_or_else(|| format!("(certificate {path}: no common name read)")))
}

/// A query that changes the store (put, rollback), with the requester in its attachment.
pub fn ask_as_user(bus: &Bus, selector: String, payload: Option<Vec<u8>>) -> Result<String> {
    rt()?.block_on(async {
        let s = open(bus).await?;
        let cn = bus.config().ok().as_ref().and_then(certificate_cn);
        let who = requester(&s.zid().to_string(), cn.as_deref());
        let r = ask(&s, selector, payload, Some(who)).await;
        s.close().await.ok();
        r
    })
}

/// No scancorrd answered a query (none is reachable, or none serves the machine asked about).
#[derive(Debug)]
struct NoAnswer(String);

impl std::fmt::Display for NoAnswer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "no scancorrd answered on `{}` (is it running, reachable and serving this prefix?)",
            self.0
        )
    }
}

impl std::error::Error for NoAnswer {}

/// A query that no scancorrd answered although one serves its machine (its liveliness token is
/// seen): refused on its way — a router's access control drops a denied query without telling
/// the asker. The words of the Python package's `Refused` (`clients/python/scancorr/client.py`).
#[derive(Debug)]
struct Refused {
    selector: String,
    machine: String,
    token: String,
}

impl std::fmt::Display for Refused {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "no answer on `{}` although scancorrd serves machine `{}` (its liveliness token `{}` is seen): the query \
             was refused on its way: a router's access control drops a denied query without telling the asker \
             (check its rules for this session's certificate role, deploy/router.json5)",
            self.selector, self.machine, self.token
        )
    }
}

impl std::error::Error for Refused {}

/// The machine a query's selector is about (`<prefix>/<machine>/calibration…`, `…/status`) and
/// its scancorrd's liveliness token key.
fn machine_of(selector: &str) -> Option<(String, String)> {
    let key = selector.split('?').next().unwrap_or(selector);
    let base = key
        .strip_suffix("/calibration/write")
        .or_else(|| key.strip_suffix("/calibration"))
        .or_else(|| key.strip_suffix("/status"))?;
    let (_, machine) = base.rsplit_once('/')?;
    Some((machine.to_string(), format!("{base}/scancorrd")))
}

/// Whether a scancorrd's liveliness token `token` is seen (within `wait`).
async fn token_seen(session: &zenoh::Session, token: &str, wait: Duration) -> bool {
    let Ok(replies) = session.liveliness().get(token).timeout(wait).await else {
        return false;
    };
    let mut seen = false;
    while let Ok(r) = replies.recv_async().await {
        seen |= r.result().is_ok();
    }
    seen
}

/// No answer to `selector`: [`Refused`] when a scancorrd is seen serving its machine, else
/// [`NoAnswer`].
async fn unanswered(session: &zenoh::Session, selector: String) -> anyhow::Error {
    if let Some((machine, token)) = machine_of(&selector) {
        if token_seen(session, &token, Duration::from_secs(1)).await {
            return Refused {
                selector,
                machine,
                token,
            }
            .into();
        }
    }
    NoAnswer(selector).into()
}

/// One query to the calibration/status queryable; returns the reply text.
async fn ask(
    session: &zenoh::Session,
    selector: String,
    payload: Option<Vec<u8>>,
    who: Option<String>,
) -> Result<String> {
    // The route to the queryable may take a moment after connecting.
    let t0 = Instant::now();
    loop {
        let mut g = session
            .get(selector.as_str())
            .timeout(Duration::from_secs(3));
        if let Some(p) = &payload {
            g = g.payload(p.clone());
        }
        if let Some(w) = &who {
            g = g.attachment(w.clone());
        }
        let replies = g.await.map_err(z)?;
        if let Ok(r) = replies.recv_async().await {
            return match r.into_result() {
                Ok(s) => Ok(s
                    .payload()
                    .try_to_string()
                    .map(|s| s.to_string())
                    .unwrap_or_default()),
                Err(e) => bail!(
                    "{}",
                    e.payload()
                        .try_to_string()
                        .map(|s| s.to_string())
                        .unwrap_or_else(|_| "error".into())
                ),
            };
        }
        if t0.elapsed() > Duration::from_secs(6) {
            return Err(unanswered(session, selector).await);
        }
        tokio::time::sleep(Duration::from_millis(250)).await;
    }
}

/// `calib put`.
pub fn calib_put(bus: &Bus, machine: &str, file: &Path) -> Result<String> {
    crate::shared::output::check_machine("--machine", machine)?;
    let text = std::fs::read(file).with_context(|| format!("reading {}", file.display()))?;
    ask_as_user(
        bus,
        scancorr_proto::calibration_write_key(&bus.prefix, machine),
        Some(text),
    )
}

/// `calib get` / `calib history` / `status`.
pub fn query(bus: &Bus, selector: String) -> Result<String> {
    rt()?.block_on(async {
        let s = open(bus).await?;
        let r = ask(&s, selector, None, None).await;
        s.close().await.ok();
        r
    })
}

/// `status`: the machine's status document; an error when the service does not serve it.
pub fn status(bus: &Bus, machine: &str) -> Result<String> {
    crate::shared::output::check_machine("--machine", machine)?;
    // Each instance answers only for the machines it serves (its assignment, less those another
    // instance already serves): no answer means no instance serves this one.
    let text = query(bus, format!("{}/{machine}/status", bus.prefix)).map_err(|e| {
        if e.downcast_ref::<NoAnswer>().is_some() {
            anyhow::anyhow!(
                "machine `{machine}` is not served: no scancorrd on {} answers for it (none running, or none has it in its `machines` assignment); `scancorr status` lists the machines served",
                bus.endpoints()
            )
        } else {
            e
        }
    })?;
    let v: serde_json::Value = serde_json::from_str(&text)
        .with_context(|| format!("the status reply is not JSON: {}", one_line(&text)))?;
    if v.get("served").and_then(|s| s.as_bool()) == Some(false) {
        let refused = v
            .get("refused_samples")
            .and_then(|r| r.as_u64())
            .unwrap_or(0);
        bail!(
            "scancorrd at {} does not serve machine `{machine}` (no calibration stored for it and no samples accepted{}); \
             `scancorr calib put --machine {machine} --file CAL.json` starts serving it",
            bus.endpoints(),
            if refused > 0 {
                format!("; {refused} sample(s) refused")
            } else {
                String::new()
            }
        );
    }
    Ok(text)
}

/// `health`: every scancorrd's answer to the health query (an error when none answers).
pub fn health(bus: &Bus) -> Result<Vec<serde_json::Value>> {
    bus.check()?;
    let key = scancorr_proto::health_key(&bus.prefix);
    rt()?.block_on(async {
        let s = open(bus).await?;
        let t0 = Instant::now();
        let mut out = vec![];
        // The route to the queryables may take a moment after connecting.
        while out.is_empty() && t0.elapsed() < Duration::from_secs(6) {
            let replies = s
                .get(key.as_str())
                .consolidation(zenoh::query::ConsolidationMode::None)
                .target(zenoh::query::QueryTarget::All)
                .timeout(Duration::from_secs(2))
                .await
                .map_err(z)?;
            while let Ok(r) = replies.recv_async().await {
                if let Ok(sample) = r.result() {
                    let text = sample.payload().try_to_string().map(|s| s.to_string()).unwrap_or_default();
                    out.push(serde_json::from_str(&text).unwrap_or(serde_json::Value::String(text)));
                }
            }
            if out.is_empty() {
                tokio::time::sleep(Duration::from_millis(250)).await;
            }
        }
        s.close().await.ok();
        if out.is_empty() {
            bail!("no scancorrd answered the health query `{key}` on {} (is one running, reachable and serving prefix `{}`?)", bus.endpoints(), bus.prefix);
        }
        Ok(out)
    })
}

/// `status` without a machine: the machines served on the bus (each scancorrd declares a
/// liveliness token `<prefix>/<machine>/scancorrd` per machine it serves); an error when none.
pub fn machines(bus: &Bus) -> Result<Vec<String>> {
    bus.check()?;
    let key = format!("{}/*/scancorrd", bus.prefix);
    let mut list: Vec<String> = rt()?.block_on(async {
        let s = open(bus).await?;
        let replies = s
            .liveliness()
            .get(key.as_str())
            .timeout(Duration::from_secs(3))
            .await
            .map_err(z)?;
        let mut v = vec![];
        while let Ok(r) = replies.recv_async().await {
            if let Ok(sample) = r.result() {
                if let Some(m) = sample
                    .key_expr()
                    .as_str()
                    .strip_prefix(&format!("{}/", bus.prefix))
                    .and_then(|r| r.strip_suffix("/scancorrd"))
                {
                    // A token with a wildcard (any peer may declare `cmm/*/scancorrd`) names
                    // no machine.
                    if scancorr_proto::names::check_machine(m).is_ok() {
                        v.push(m.to_string());
                    }
                }
            }
        }
        s.close().await.ok();
        Ok::<_, anyhow::Error>(v)
    })?;
    list.sort();
    list.dedup();
    if list.is_empty() {
        bail!(
            "no scancorrd at {} serves a machine under prefix `{}` (a service serves a machine once a calibration is put for it: `scancorr calib put --machine M --file CAL.json`)",
            bus.endpoints(),
            bus.prefix
        );
    }
    Ok(list)
}

/// The JSON documents answering `selector` within `wait` (answers that are errors, not text or
/// not JSON are passed over); None when the query cannot be sent.
async fn json_answers(
    s: &zenoh::Session,
    selector: String,
    wait: Duration,
) -> Option<Vec<serde_json::Value>> {
    let replies = s.get(selector).timeout(wait).await.ok()?;
    let mut docs = vec![];
    while let Ok(r) = replies.recv_async().await {
        let Ok(sample) = r.result() else { continue };
        let Ok(text) = sample.payload().try_to_string() else {
            continue;
        };
        if let Ok(v) = serde_json::from_str(&text) {
            docs.push(v);
        }
    }
    Some(docs)
}

/// An open session to the bus, with its runtime: connect first (failing at once when nothing
/// is there), then do the work.
pub struct Conn {
    rt: tokio::runtime::Runtime,
    session: zenoh::Session,
}

/// Connects to the bus.
pub fn connect(bus: &Bus) -> Result<Conn> {
    let rt = rt()?;
    let session = rt.block_on(open(bus))?;
    Ok(Conn { rt, session })
}

impl Drop for Conn {
    fn drop(&mut self) {
        let s = self.session.clone();
        self.rt.block_on(async move {
            let _ = tokio::time::timeout(Duration::from_secs(2), s.close()).await;
        });
    }
}

/// How `record` and `tail` stop.
#[derive(Clone, Copy, Debug, Default)]
pub struct Bound {
    /// After this many seconds.
    pub seconds: Option<f64>,
    /// After this many seconds without a message, once one arrived.
    pub idle: Option<f64>,
    /// After this many messages.
    pub count: Option<u64>,
}

impl Bound {
    fn check(&self) -> Result<()> {
        for (flag, v) in [("--seconds", self.seconds), ("--idle", self.idle)] {
            if let Some(v) = v {
                if !(v.is_finite() && v > 0.0) {
                    bail!("{flag} must be a number > 0");
                }
            }
        }
        if self.count == Some(0) {
            bail!("--count must be > 0");
        }
        Ok(())
    }

    fn done(&self, t0: Instant, last: Option<Instant>, n: u64) -> bool {
        self.seconds.is_some_and(|s| t0.elapsed().as_secs_f64() > s)
            || self.count.is_some_and(|c| n >= c)
            || matches!((self.idle, last), (Some(i), Some(l)) if l.elapsed().as_secs_f64() > i)
    }

    fn waited(&self, t0: Instant) -> String {
        format!("in {:.1} s", t0.elapsed().as_secs_f64())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn endpoints_name_their_protocol() {
        assert!(check_endpoint("tcp/127.0.0.1:7447").is_ok());
        assert!(check_endpoint("tls/host.example:7447").is_ok());
        let e = check_endpoint("127.0.0.1:7447").unwrap_err().to_string();
        assert!(e.contains("use tcp/HOST:PORT"), "{e}");
        assert!(check_endpoint("tcp/").is_err());
        assert!(check_endpoint("http/x:1").is_err());
    }
}
