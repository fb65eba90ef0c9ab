//! One concern: the zenoh client of the bus commands (`calib put|get|history`, `status`,
//! `health`, `replay`, `record`, `tail`, `sim --live`, `lab history --machine`).
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
            return Err(NoAnswer(selector).into());
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

/// How long a publisher waits for a subscriber before giving up.
const MATCH_WAIT: Duration = Duration::from_secs(5);

/// What a replay sent, and what became of it.
#[derive(Debug, Clone, Copy, Default)]
pub struct Replayed {
    /// Messages published.
    pub sent: u64,
    /// Of those, how many did not reach the scancorrd serving their machine (lost on the way:
    /// a link closed, a router down); None when no scancorrd answered to confirm.
    pub not_delivered: Option<u64>,
    /// Of those that arrived, how many the service shed (it could not correct them in real
    /// time; counted on the machine's status as `input.shed`).
    pub shed: u64,
}

impl Replayed {
    /// What became of them, in words (empty when everything arrived and was corrected).
    pub fn said(&self) -> String {
        let mut v = vec![];
        match self.not_delivered {
            Some(0) => {}
            Some(n) => v.push(format!("{n} did not reach scancorrd")),
            None => v.push("their arrival is not confirmed (no scancorrd answered)".into()),
        }
        if self.shed > 0 {
            v.push(format!("{} were shed by scancorrd", self.shed));
        }
        if v.is_empty() {
            String::new()
        } else {
            format!(" ({})", v.join("; "))
        }
    }
}

/// `replay`: bag → bus, paced by sample time (`rate` × real time; None = as fast as possible).
pub fn replay(bus: &Bus, bag: &Path, rate: Option<f64>, looping: bool) -> Result<Replayed> {
    bus.check()?;
    // Read the bag before connecting: a bad bag is reported as such.
    BagReader::open(bag).with_context(|| format!("reading bag {}", bag.display()))?;
    connect(bus)?.replay(bus, bag, rate, looping)
}

impl Conn {
    /// Publishes a bag's raw streams; fails when nobody subscribes to them. Closes once every
    /// message has arrived at the scancorrd serving its machine (a query that travels behind
    /// them comes back with their count), or says how many did not.
    pub fn replay(
        &self,
        bus: &Bus,
        bag: &Path,
        rate: Option<f64>,
        looping: bool,
    ) -> Result<Replayed> {
        let reader =
            BagReader::open(bag).with_context(|| format!("reading bag {}", bag.display()))?;
        let s = &self.session;
        self.rt.block_on(async {
            let mut pubs = std::collections::BTreeMap::new();
            for ch in reader.channels() {
                if Stream::RAW.contains(&ch.stream) {
                    crate::shared::output::check_machine("the bag's machine", &ch.machine)?;
                    let key = ch.stream.key(&bus.prefix, &ch.machine);
                    let p = s
                        .declare_publisher(key.clone())
                        .congestion_control(CongestionControl::Block)
                        .await
                        .map_err(z)?;
                    pubs.insert(ch.topic.clone(), (key, p, ch.machine.clone()));
                }
            }
            if pubs.is_empty() {
                bail!("{}: no raw streams to publish", bag.display());
            }
            // Wait until someone listens (the route is set up).
            let t0 = Instant::now();
            let matched = loop {
                let mut matched = vec![];
                for (key, p, _) in pubs.values() {
                    if p.matching_status().await.map(|m| m.matching()).unwrap_or(false) {
                        matched.push(key.clone());
                    }
                }
                if matched.len() == pubs.len() || t0.elapsed() > MATCH_WAIT {
                    break matched;
                }
                tokio::time::sleep(Duration::from_millis(50)).await;
            };
            if matched.is_empty() {
                bail!(
                    "nobody subscribes to {} on {} (waited {} s): is scancorrd running there with prefix `{}`?",
                    pubs.values().map(|(k, _, _)| format!("`{k}`")).collect::<Vec<_>>().join(", "),
                    bus.endpoints(),
                    MATCH_WAIT.as_secs(),
                    bus.prefix
                );
            }
            for (key, _, _) in pubs.values() {
                if !matched.contains(key) {
                    eprintln!("warning: nobody subscribes to `{key}`; its messages go nowhere");
                }
            }
            // What the service serving each machine has received of it so far: the replay's
            // messages are counted against it at the end (none: no scancorrd answers for it,
            // and delivery cannot be confirmed).
            let machines: std::collections::BTreeSet<String> =
                pubs.values().map(|(_, _, m)| m.clone()).collect();
            let mut ledgers = std::collections::BTreeMap::new();
            for m in &machines {
                let before = input_of(s, &bus.prefix, m, ASK_FIRST).await;
                let pacing = before.is_some();
                ledgers.insert(m.clone(), Ledger { before, sent: 0, pacing });
            }
            let mut sent = 0u64;
            let mut progress = crate::shared::output::Progress::new();
            let total = reader.message_count();
            loop {
                let start = Instant::now();
                let mut first: Option<u64> = None;
                for m in reader.messages()? {
                    let m = m?;
                    let Some((_, p, machine)) = pubs.get(&*m.topic) else {
                        continue;
                    };
                    if let Some(r) = rate {
                        let f = *first.get_or_insert(m.publish_time);
                        let due = Duration::from_secs_f64(
                            (m.publish_time.saturating_sub(f)) as f64 * 1e-9 / r,
                        );
                        if let Some(wait) = due.checked_sub(start.elapsed()) {
                            tokio::time::sleep(wait).await;
                        }
                    }
                    // Bags recorded before scancorr.v1.1 hold untagged batches; their
                    // channel names the stream, so the tag is added on the way out.
                    let data = match scancorr_core::wire::stream_id(m.stream) {
                        Some(sid) => scancorr_core::wire::tagged(sid, &m.data)
                            .map(|b| b.into_owned())
                            .with_context(|| format!("{}: message on `{}`", bag.display(), m.topic))?,
                        None => m.data.to_vec(),
                    };
                    p.put(data).await.map_err(z)?;
                    sent += 1;
                    let l = ledgers.get_mut(machine).expect("a ledger per machine");
                    l.sent += 1;
                    // As fast as possible: paced by the service, so that what it has not
                    // corrected yet of this machine stays small (it never waits for a
                    // publisher; what it cannot hold, it sheds).
                    if rate.is_none() && l.pacing && l.sent % PACE_EVERY == 0 {
                        l.pacing = pace(s, &bus.prefix, machine).await;
                    }
                    progress.tick(|| format!("replaying {}: {sent} of {total} message(s){}", bag.display(), if looping { " (looping)" } else { "" }));
                }
                if !looping {
                    break;
                }
            }
            progress.finish();
            // Every message has left, and arrived, once the service has counted them: a
            // query travels behind them, in the same queue, over the same links.
            let mut lost = vec![];
            let mut unconfirmed = vec![];
            let mut uncorrected: Vec<String> = vec![];
            let mut replayed = Replayed { sent, not_delivered: Some(0), shed: 0 };
            for (m, l) in &ledgers {
                let Some(before) = &l.before else {
                    unconfirmed.push(m.clone());
                    continue;
                };
                let after = settle(s, &bus.prefix, m, before.arrived + l.sent).await;
                let Some(after) = after else {
                    unconfirmed.push(m.clone());
                    continue;
                };
                let arrived = after.arrived.saturating_sub(before.arrived).min(l.sent);
                if after.calibrated == Some(false) && arrived > 0 {
                    uncorrected.push(m.clone());
                }
                let shed = after.shed.saturating_sub(before.shed).min(arrived);
                replayed.shed += shed;
                if let Some(n) = &mut replayed.not_delivered {
                    *n += l.sent - arrived;
                }
                if shed > 0 {
                    eprintln!(
                        "warning: scancorrd had shed {shed} of the {} message(s) of machine `{m}` when the replay ended: it could not correct them in real time (`input` on its status: `scancorr status --machine {m}`)",
                        l.sent
                    );
                }
                if arrived < l.sent {
                    lost.push(format!("{} of {} for machine `{m}`", l.sent - arrived, l.sent));
                }
            }
            if !unconfirmed.is_empty() {
                replayed.not_delivered = None;
                // Without a service to count them: time for the last messages to leave.
                tokio::time::sleep(Duration::from_millis(300)).await;
                eprintln!(
                    "warning: no scancorrd answered for machine(s) {}: whether their messages arrived is not confirmed",
                    unconfirmed.iter().map(|m| format!("`{m}`")).collect::<Vec<_>>().join(", ")
                );
            }
            if !lost.is_empty() {
                // Said, not failed: a replay that outlived a router restart goes on, and the
                // service counts the samples missing too.
                eprintln!(
                    "warning: messages published did not reach scancorrd ({}): they were lost on the way (a link closed, a router was down)",
                    lost.join(", ")
                );
            }
            // A subscriber that went away (the service stopped) did not get everything.
            let mut still = false;
            for (_, p, _) in pubs.values() {
                still |= p.matching_status().await.map(|m| m.matching()).unwrap_or(false);
            }
            if !still {
                bail!(
                    "the subscribers on {} went away during the replay: some of the {sent} message(s) were not delivered",
                    bus.endpoints()
                );
            }
            if let Some(first) = uncorrected.first() {
                bail!(
                    "scancorrd has no calibration in use for machine(s) {}: it counted what they streamed as uncorrected and published no point (`scancorr status --machine {first}`); put one first: `scancorr calib put --machine {first} --file CALIBRATION.json`",
                    uncorrected.iter().map(|m| format!("`{m}`")).collect::<Vec<_>>().join(", ")
                );
            }
            Ok(replayed)
        })
    }
}

/// How long the first question to the service may take to answer (a machine's status).
const ASK_FIRST: Duration = Duration::from_secs(3);

/// With `--speed max` / `--live-rate max`, the service is asked every this many messages of a
/// machine how much of it waits to be corrected.
const PACE_EVERY: u64 = 32;

/// Publishing waits while more than this of a machine waits in the service, bytes…
const PACE_HIGH: u64 = 1 << 20;

/// … until it is below this.
const PACE_LOW: u64 = 256 << 10;

/// What a service has received of one machine (its status' `input`).
#[derive(Debug, Clone, Copy, PartialEq)]
struct Received {
    arrived: u64,
    shed: u64,
    queued_bytes: u64,
    /// Whether a calibration is in use (None: a service too old to say).
    calibrated: Option<bool>,
}

/// A machine's messages in a replay: what its service had received before, and what was sent.
struct Ledger {
    before: Option<Received>,
    sent: u64,
    /// Paced by the service (it answers).
    pacing: bool,
}

/// What the scancorrd serving `machine` has received of it (`status?input`, answered at once
/// from the counters of its input); zero for a machine it does not serve yet; None when no
/// scancorrd answers within `wait`.
async fn input_of(
    s: &zenoh::Session,
    prefix: &str,
    machine: &str,
    wait: Duration,
) -> Option<Received> {
    let replies = s
        .get(format!("{prefix}/{machine}/status?input"))
        .timeout(wait)
        .await
        .ok()?;
    let mut best: Option<Received> = None;
    while let Ok(r) = replies.recv_async().await {
        let Ok(sample) = r.result() else { continue };
        let Ok(text) = sample.payload().try_to_string() else {
            continue;
        };
        let Ok(v) = serde_json::from_str::<serde_json::Value>(&text) else {
            continue;
        };
        let got = if v["served"] == true {
            let i = &v["input"];
            // A service older than the `input` counters cannot confirm anything.
            let Some(arrived) = i["arrived"].as_u64() else {
                continue;
            };
            Received {
                arrived,
                shed: i["shed"].as_u64().unwrap_or(0),
                queued_bytes: i["queued_bytes"].as_u64().unwrap_or(0),
                calibrated: v["calibrated"].as_bool(),
            }
        } else {
            Received {
                arrived: 0,
                shed: 0,
                queued_bytes: 0,
                calibrated: None,
            }
        };
        if best.is_none_or(|b| got.arrived > b.arrived) {
            best = Some(got);
        }
    }
    best
}

/// Waits while the service holds more than [`PACE_HIGH`] of `machine` not yet corrected;
/// false when it no longer answers (the replay goes on unpaced).
async fn pace(s: &zenoh::Session, prefix: &str, machine: &str) -> bool {
    let t0 = Instant::now();
    let mut high = PACE_HIGH;
    while t0.elapsed() < Duration::from_secs(30) {
        match input_of(s, prefix, machine, Duration::from_secs(2)).await {
            Some(r) if r.queued_bytes > high => {
                high = PACE_LOW;
                tokio::time::sleep(Duration::from_millis(5)).await;
            }
            Some(_) => return true,
            None => return false,
        }
    }
    true
}

/// What the service has received of `machine` once it has `expect` messages, or once the count
/// stops growing (a query behind the replay's messages came back and the next ones say the
/// same); None when it stops answering.
async fn settle(s: &zenoh::Session, prefix: &str, machine: &str, expect: u64) -> Option<Received> {
    let t0 = Instant::now();
    let mut last: Option<Received> = None;
    let mut same = 0;
    loop {
        let r = input_of(s, prefix, machine, Duration::from_secs(5)).await?;
        if r.arrived >= expect || t0.elapsed() > Duration::from_secs(20) {
            return Some(r);
        }
        if last.is_some_and(|l| l.arrived == r.arrived) {
            same += 1;
            if same >= 5 {
                return Some(r);
            }
        } else {
            same = 0;
        }
        last = Some(r);
        tokio::time::sleep(Duration::from_millis(100)).await;
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

/// Samples missing between recorded ones: per (machine, stream), a `seq` more than one past
/// the last one seen. (A `seq` going back is a controller restart or a looped replay, not a
/// loss; samples before the first one recorded are not counted.)
#[derive(Default)]
struct Gaps {
    last: std::collections::BTreeMap<(String, Stream), u64>,
    missing: std::collections::BTreeMap<(String, Stream), u64>,
}

impl Gaps {
    fn see(&mut self, machine: &str, stream: Stream, seq: u64) {
        let key = (machine.to_string(), stream);
        if let Some(l) = self.last.get(&key) {
            if seq > l + 1 {
                *self.missing.entry(key.clone()).or_default() += seq - l - 1;
            }
        }
        self.last.insert(key, seq);
    }

    /// Notes the seqs in one message's payload.
    fn message(&mut self, stream: Stream, bytes: &[u8]) {
        if let Some(sid) = scancorr_core::wire::stream_id(stream) {
            if let Ok(d) = scancorr_core::wire::decode(sid, bytes) {
                for (m, s) in &d.samples {
                    self.see(m, stream, s.seq());
                }
            }
        } else if stream == Stream::Points {
            let b = scancorr_proto::v1::CorrectedPointBatch::decode(bytes);
            if let Ok(points) = b.map(|b| b.into_points()) {
                for p in points.iter().flatten() {
                    self.see(&p.machine_id, stream, p.seq);
                }
            }
        } else {
            // The v1.2 measurement streams (distance probes, micro-stage).
            match scancorr_bag::RawBatch::decode(stream, bytes) {
                Ok(scancorr_bag::RawBatch::Distance(b)) => b
                    .samples
                    .iter()
                    .for_each(|s| self.see(&s.machine_id, stream, s.seq)),
                Ok(scancorr_bag::RawBatch::Stage(b)) => b
                    .samples
                    .iter()
                    .for_each(|s| self.see(&s.machine_id, stream, s.seq)),
                _ => {}
            }
        }
    }

    fn total(&self) -> u64 {
        self.missing.values().sum()
    }

    fn describe(&self, prefix: &str) -> String {
        self.missing
            .iter()
            .map(|((m, st), n)| format!("{n} in {}", st.key(prefix, m)))
            .collect::<Vec<_>>()
            .join(", ")
    }
}

/// `record`: bus → bag until the bound, or Ctrl-C. An error, and no file, when nothing of the
/// scancorr streams arrived; an error (with the bag kept) when samples are missing between
/// recorded ones — the bus dropped them for this recorder. With `foxglove`, the corrected
/// points and alarms recorded are also written as Foxglove channels (`shared::foxglove`, as
/// `correct` writes them).
pub fn record(
    bus: &Bus,
    keys: &str,
    out: &Path,
    bound: Bound,
    mut foxglove: Option<crate::shared::foxglove::BusSinks>,
) -> Result<u64> {
    bus.check()?;
    bound.check()?;
    zenoh::key_expr::KeyExpr::try_from(keys).map_err(|e| {
        anyhow::anyhow!(
            "--keys {}: not a key expression: {}",
            scancorr_proto::names::shown(keys),
            one_line(&e.to_string())
        )
    })?;
    let file = AtomicOutput::new("--out", out)?;
    let conn = connect(bus)?;
    let (n, gaps) = conn.rt.block_on(async {
        let s = &conn.session;
        let sub = s.declare_subscriber(keys).await.map_err(z)?;
        let mut w = BagWriter::from_file(file.file()?, file.path(), BagHeader { compression: scancorr_bag::Compression::Lz4, ..BagHeader::default() })
            .with_context(|| format!("creating {}", out.display()))?;
        if let Some(f) = &foxglove {
            f.write_program(&mut w)?;
        }
        let t0 = Instant::now();
        let mut last = None::<Instant>;
        let (mut n, mut other) = (0u64, 0u64);
        let mut gaps = Gaps::default();
        let mut last_flush = Instant::now();
        eprintln!("recording `{keys}` from {} → {}", bus.endpoints(), out.display());
        let mut progress = crate::shared::output::Progress::new();
        let ctrl_c = tokio::signal::ctrl_c();
        tokio::pin!(ctrl_c);
        loop {
            tokio::select! {
                r = sub.recv_async() => {
                    let Ok(sample) = r else { break };
                    let key = sample.key_expr().as_str();
                    let Some((machine, stream)) = Stream::parse_key(&bus.prefix, key) else { other += 1; continue };
                    let bytes = sample.payload().to_bytes();
                    let now = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_nanos() as u64).unwrap_or(0);
                    let publish = scancorr_bag::peek(stream, &bytes).and_then(|p| p.first_t_ns).map(|t| t.max(0) as u64).unwrap_or(now);
                    w.write(stream, machine, &bus.prefix, now, publish, &bytes)?;
                    if let Some(f) = &mut foxglove {
                        f.write(&mut w, now, machine, stream, &bytes)?;
                    }
                    gaps.message(stream, &bytes);
                    n += 1;
                    last = Some(Instant::now());
                    progress.tick(|| format!("recording: {n} message(s) in {:.1} s", t0.elapsed().as_secs_f64()));
                    if last_flush.elapsed() > Duration::from_secs(1) {
                        w.flush()?;
                        last_flush = Instant::now();
                    }
                }
                _ = tokio::time::sleep(Duration::from_millis(200)) => {}
                _ = &mut ctrl_c => break,
            }
            if bound.done(t0, last, n) {
                break;
            }
        }
        progress.finish();
        if n == 0 {
            if other > 0 {
                bail!("received nothing on `{keys}` that is a scancorr stream under prefix `{}` ({other} other message(s)) {}; nothing written", bus.prefix, bound.waited(t0));
            }
            bail!("received nothing on `{keys}` from {} {} (is anything publishing there?); nothing written", bus.endpoints(), bound.waited(t0));
        }
        w.finish().with_context(|| format!("finishing {}", out.display()))?;
        Ok::<_, anyhow::Error>((n, gaps))
    })?;
    file.commit()?;
    if gaps.total() > 0 {
        bail!(
            "recorded {n} message(s) → {}, but {} sample(s) are missing between them (seq gaps: {}): the bus dropped them on the way to this recorder (a publisher faster than real time?)",
            out.display(),
            gaps.total(),
            gaps.describe(&bus.prefix)
        );
    }
    Ok(n)
}

/// `tail`: prints points and alarms as they arrive, until the bound or Ctrl-C; an error when
/// nothing arrived.
pub fn tail(bus: &Bus, machine: &str, bound: Bound, json: bool) -> Result<()> {
    crate::shared::output::check_machine("--machine", machine)?;
    bus.check()?;
    bound.check()?;
    let conn = connect(bus)?;
    let key = format!("{}/{machine}/**", bus.prefix);
    conn.rt.block_on(async {
        let s = &conn.session;
        let sub = s.declare_subscriber(key.as_str()).await.map_err(z)?;
        let t0 = Instant::now();
        let mut last_seq: Option<u64> = None;
        let mut last = None::<Instant>;
        let (mut n, mut bad) = (0u64, 0u64);
        let ctrl_c = tokio::signal::ctrl_c();
        tokio::pin!(ctrl_c);
        loop {
            tokio::select! {
                r = sub.recv_async() => {
                    let Ok(sample) = r else { break };
                    let Some((m, stream)) = Stream::parse_key(&bus.prefix, sample.key_expr().as_str()) else { continue };
                    let bytes = sample.payload().to_bytes();
                    match stream {
                        Stream::Points => {
                            // A payload that is no point batch is shown, counted, and skipped.
                            let points = match scancorr_proto::v1::CorrectedPointBatch::decode(&*bytes).map_err(|e| e.to_string()).and_then(|b| b.into_points().map_err(|e| e.to_string())) {
                                Ok(p) => p,
                                Err(e) => {
                                    bad += 1;
                                    if json { outln!("{}", serde_json::json!({"machine": m, "bad_point_batch": e, "bad_so_far": bad}))?; } else { outln!("!! {m}: a point batch that does not read ({bad} so far): {e}")?; }
                                    continue;
                                }
                            };
                            n += 1;
                            last = Some(Instant::now());
                            for p in &points {
                                if let Some(l) = last_seq { if p.seq != l + 1 {
                                    let missed = p.seq.saturating_sub(l + 1);
                                    if json { outln!("{}", serde_json::json!({"machine": m, "missed_points": missed, "before_seq": p.seq}))?; } else { outln!("!! {m}: missed {missed} point(s)")?; }
                                } }
                                last_seq = Some(p.seq);
                                if json {
                                    let v = |x: Option<scancorr_proto::v1::Vec3>| x.map(|v| [v.x, v.y, v.z]).unwrap_or_default();
                                    outln!("{}", serde_json::json!({"machine": m, "seq": p.seq, "t_ns": p.t_ns, "segment_id": p.segment_id, "tip_id": p.tip_id, "calibration_version": p.calibration_version, "estimator_valid": p.estimator_valid, "surface_mm": v(p.surface), "tip_center_mm": v(p.tip_center), "normal": v(p.normal)}))?;
                                }
                            }
                            if let (Some(p), false) = (points.last(), json) {
                                let s = p.surface.unwrap_or_default();
                                outln!("{m} #{:<9} t={:.3}s  surface ({:9.4} {:9.4} {:9.4}) mm  v{} {}{}", p.seq, p.t_ns as f64 * 1e-9, s.x, s.y, s.z, p.calibration_version, if p.estimator_valid { "" } else { "FLAGGED " }, if points.len() > 1 { format!("(+{} in batch)", points.len() - 1) } else { String::new() })?;
                            }
                        }
                        Stream::Alarms => {
                            if let Ok(a) = scancorr_proto::v1::EstimatorAlarm::decode(&*bytes) {
                                n += 1;
                                last = Some(Instant::now());
                                if json {
                                    outln!("{}", serde_json::json!({"machine": m, "alarm": if a.raised { "raised" } else { "cleared" }, "axis": format!("{:?}", a.axis()), "t_ns": a.t_ns, "estimated_accel_mm_s2": a.estimated_accel, "measured_accel_mm_s2": a.measured_accel, "threshold_mm_s2": a.threshold}))?;
                                } else {
                                    outln!("{m} ALARM {} axis {:?} t={:.3}s estimated {:.1} measured {:.1} mm/s² (threshold {:.0})", if a.raised { "RAISED" } else { "cleared" }, a.axis(), a.t_ns as f64 * 1e-9, a.estimated_accel, a.measured_accel, a.threshold)?;
                                }
                            }
                        }
                        _ => {}
                    }
                }
                _ = tokio::time::sleep(Duration::from_millis(200)) => {}
                _ = &mut ctrl_c => break,
            }
            if bound.done(t0, last, n) {
                break;
            }
        }
        if n == 0 {
            bail!(
                "received nothing on `{key}` from {} {} (are machine `{machine}`'s raw streams reaching scancorrd?)",
                bus.endpoints(),
                bound.waited(t0)
            );
        }
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gaps_count_missing_samples_not_restarts() {
        let mut g = Gaps::default();
        for seq in [5, 6, 7, 10, 11, 0, 1, 3] {
            g.see("m1", Stream::Scale, seq);
        }
        g.see("m2", Stream::Scale, 100);
        g.see("m1", Stream::Probe, 4);
        assert_eq!(g.total(), 3);
        assert_eq!(g.describe("cmm"), "3 in cmm/m1/raw/scale");
    }

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
