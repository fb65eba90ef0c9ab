//! `scancorrd` configuration: embedded defaults, or a JSON5 file.

use serde::Deserialize;
use std::path::PathBuf;

/// Service configuration.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Config {
    /// Zenoh mode: `peer` (default), `client` or `router`.
    pub mode: String,
    /// Endpoints to listen on (default `tcp/127.0.0.1:7447`, where the CLI connects by default).
    pub listen: Vec<String>,
    /// Endpoints to connect to (a router, other peers).
    pub connect: Vec<String>,
    /// Key-expression prefix.
    pub prefix: String,
    /// This instance's assignment: machine ids, or patterns with `*` for any run of name
    /// characters (`cell3-*`; `*` alone is every machine). With `allow_any_machine` off the
    /// instance subscribes only to these machines' raw streams and answers only their queries,
    /// so several instances on one router mesh never receive each other's traffic.
    pub machines: Vec<String>,
    /// Serve machines not listed in `machines` (one subscription to every machine's raw
    /// streams: for a single instance).
    pub allow_any_machine: bool,
    /// Folder of the calibration store.
    pub data_dir: PathBuf,
    /// Most machines served at once.
    pub max_machines: usize,
    /// Most samples waiting per stream per machine for their partners in the join (the
    /// calibration's `join.max_pending` applies when it is smaller). Bounds each machine's
    /// memory: a buffer holds at most this many samples (≈ 240 bytes per instant over the
    /// four streams), and what is pushed out is counted as `buffer_overflow`.
    pub max_pending_samples: usize,
    /// A stream that has sent nothing for this long while the scales keep coming is reported
    /// stalled, ms.
    pub stall_after_ms: u64,
    /// Zenoh multicast scouting (off by default: endpoints are explicit).
    pub scouting: bool,
    /// A zenoh configuration file (JSON5) for everything else — TLS certificates, user
    /// authentication — used as the base; mode and endpoints above override it.
    pub zenoh_config: Option<PathBuf>,
    /// Largest message the service accepts from the bus, bytes (zenoh drops larger ones at
    /// reassembly, before they take memory); also the largest calibration document put.
    pub max_message_bytes: usize,
    /// Corrected output waiting to be published per machine, bytes. Publishing never blocks
    /// correction: a machine whose subscribers do not keep up has its newest batches dropped
    /// past this bound, counted as `points_dropped_backpressure` (a `seq` gap for the
    /// subscriber); other machines are not affected.
    pub max_queued_bytes_per_machine: usize,
    /// Take raw batches without the scancorr.v1.1 stream tag (producers older than v1.1).
    /// Off: an untagged batch is refused and counted (`untagged`), because nothing else tells
    /// a command batch published on the scale key from a scale batch.
    pub accept_untagged_batches: bool,
    /// Where the Prometheus metrics endpoint listens (`HOST:PORT`, plain HTTP, `GET
    /// /metrics`); none by default. Keep it on loopback or a management network.
    pub metrics_listen: Option<String>,
    /// Seconds between the log's throughput lines (0: none).
    pub throughput_log_s: u64,
    /// Correcting worker shards (threads), each owning its machines' correctors; 0: one per
    /// core.
    pub workers: usize,
    /// Most CPU time a point may cost with a calibration that is put, µs (measured on a
    /// reference point when it is put): a costlier one is refused, since it could not be
    /// corrected in real time (at 1 kHz, 1 000 µs is a whole core). A stored one is served and
    /// said in the log. 0: no limit.
    pub max_point_cost_us: f64,
    /// A raw message that has waited on its shard longer than this when its turn comes is
    /// shed (counted as `input.shed_late` on the machine's status, said in the log), ms: a
    /// machine whose correction the shard cannot keep up with loses its own stale messages,
    /// and the other machines of the shard keep their share of its time.
    pub shed_after_ms: u64,
    /// Raw messages of one machine waiting on its shard, bytes: more are shed as they arrive
    /// (`input.shed_queue_full`), never waited for (zenoh's callback waiting would stop the
    /// link, and behind a router that link carries every machine).
    pub max_input_bytes_per_machine: usize,
    /// Fail-over between instances serving the same machines (off by default).
    pub failover: Failover,
    /// Publish each point's per-effect breakdown (on by default). Off, the points carry their
    /// surface point, tip centre, normal, flags and calibration version, and no correction
    /// columns (an empty `effects` list, as v1.4 allows): 85 bytes a point on the bus instead
    /// of 85 + 24 per effect, for consumers that use only the corrected points. The
    /// breakdown is still computed (its sum is the correction) and a bag replayed offline
    /// gives it.
    pub publish_breakdown: bool,
}

/// Fail-over between instances (`failover` in the configuration): with it on, an instance
/// whose assignment holds a machine another instance serves does not refuse it but stands by
/// for it (a hot standby: it corrects the machine's raw streams as the active one does,
/// withholds its points, and drops those the active one is seen to publish); when the active
/// instance's liveliness token goes (it stopped, or its router dropped its session after the
/// lease), the standby takes the machine over and publishes the points the active one was
/// not seen to publish, then goes on live. Which instance is active for a machine is decided
/// by zenoh liveliness alone: each active instance declares `<prefix>/<machine>/scancorrd`
/// and `<prefix>/<machine>/scancorrd/active/<since_ms>-<zid>`, each standby
/// `<prefix>/<machine>/scancorrd/standby/<zid>`. Two active at once (a partition healed) is
/// a split brain: both say so (log, health, metrics) and the one active since later steps
/// back to standby. Turn it on in every instance of the set (an active instance with it on
/// hands a machine over at SIGTERM without flushing it, so the standby goes on with the same
/// `seq`). The instances share one calibration store (`data_dir` on one host) or are given
/// the same calibrations: a standby reloads the stored calibration when it takes over.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Failover {
    /// Stand by for machines another instance serves, take them over when it goes.
    pub enabled: bool,
    /// After the active instance's token goes, how long its last points in flight are waited
    /// for before taking over, ms.
    pub grace_ms: u64,
    /// Output a standby holds per machine (what the active one was not seen to publish yet),
    /// bytes; past it the oldest is dropped and counted (`held_overflow_points`).
    pub max_held_bytes: usize,
}

impl Default for Failover {
    fn default() -> Self {
        Failover {
            enabled: false,
            grace_ms: 100,
            max_held_bytes: 8 << 20,
        }
    }
}

impl Default for Config {
    fn default() -> Self {
        Config {
            mode: "peer".into(),
            listen: vec!["tcp/127.0.0.1:7447".into()],
            connect: vec![],
            prefix: scancorr_proto::DEFAULT_PREFIX.into(),
            machines: vec![],
            allow_any_machine: true,
            data_dir: PathBuf::from("scancorr-data"),
            max_machines: 4096,
            max_pending_samples: 2048,
            stall_after_ms: 1000,
            scouting: false,
            zenoh_config: None,
            max_message_bytes: 16 << 20,
            max_queued_bytes_per_machine: 8 << 20,
            accept_untagged_batches: false,
            metrics_listen: None,
            throughput_log_s: 60,
            workers: 0,
            max_point_cost_us: 200.0,
            shed_after_ms: 2000,
            max_input_bytes_per_machine: 4 << 20,
            failover: Failover::default(),
            publish_breakdown: true,
        }
    }
}

/// A configuration that cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// Unreadable file.
    #[error("reading {path}: {source}")]
    Io {
        /// File.
        path: PathBuf,
        /// Cause.
        source: std::io::Error,
    },
    /// Not valid JSON5 or unknown field.
    #[error("{path}: {msg}")]
    Parse {
        /// File.
        path: PathBuf,
        /// What is wrong.
        msg: String,
    },
    /// A value out of range or a name outside the grammar.
    #[error("configuration: {0}")]
    Invalid(String),
    /// A value zenoh refused.
    #[error("zenoh configuration `{key}`: {msg}")]
    Zenoh {
        /// Key.
        key: String,
        /// What zenoh said.
        msg: String,
    },
}

impl Config {
    /// Reads a JSON5 file.
    pub fn load(path: &std::path::Path) -> Result<Config, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Io {
            path: path.into(),
            source,
        })?;
        let c: Config = json5::from_str(&text).map_err(|e| ConfigError::Parse {
            path: path.into(),
            msg: e.to_string(),
        })?;
        c.validate().map_err(|msg| ConfigError::Parse {
            path: path.into(),
            msg,
        })?;
        Ok(c)
    }

    /// Checks values and names (the prefix and every machine id follow the
    /// `scancorr_proto::names` grammar, so none becomes a wildcard in a key expression).
    pub fn validate(&self) -> Result<(), String> {
        if !["peer", "client", "router"].contains(&self.mode.as_str()) {
            return Err(format!(
                "mode {}: peer, client or router",
                scancorr_proto::names::shown(&self.mode)
            ));
        }
        scancorr_proto::names::check_prefix(&self.prefix).map_err(|e| format!("prefix: {e}"))?;
        for (i, m) in self.machines.iter().enumerate() {
            check_pattern(m).map_err(|e| format!("machines[{i}]: {e}"))?;
        }
        if self.machines.is_empty() && !self.allow_any_machine {
            return Err(
                "machines is empty and allow_any_machine is false: this instance would serve nothing"
                    .into(),
            );
        }
        if self.max_machines == 0 || self.max_machines > 1_000_000 {
            return Err("max_machines: 1 … 1 000 000".into());
        }
        if !(1024..=(1 << 30)).contains(&self.max_message_bytes) {
            return Err("max_message_bytes: 1 KiB … 1 GiB".into());
        }
        if self.max_queued_bytes_per_machine < 64 * 1024 {
            return Err("max_queued_bytes_per_machine: at least 64 KiB".into());
        }
        if self.workers > 1024 {
            return Err("workers: 0 (one per core) … 1024".into());
        }
        if self.max_pending_samples == 0 {
            return Err("max_pending_samples: at least 1".into());
        }
        if !(self.max_point_cost_us.is_finite() && self.max_point_cost_us >= 0.0) {
            return Err("max_point_cost_us: a number ≥ 0 (0: no limit)".into());
        }
        if !(100..=600_000).contains(&self.shed_after_ms) {
            return Err("shed_after_ms: 100 … 600 000".into());
        }
        if self.max_input_bytes_per_machine < 64 * 1024 {
            return Err("max_input_bytes_per_machine: at least 64 KiB".into());
        }
        if self.failover.grace_ms > 10_000 {
            return Err("failover.grace_ms: 0 … 10 000".into());
        }
        if self.failover.max_held_bytes < 64 * 1024 {
            return Err("failover.max_held_bytes: at least 64 KiB".into());
        }
        if let Some(m) = &self.metrics_listen {
            m.parse::<std::net::SocketAddr>().map_err(|_| {
                format!(
                    "metrics_listen {}: HOST:PORT with a numeric address (e.g. 127.0.0.1:9464)",
                    scancorr_proto::names::shown(m)
                )
            })?;
        }
        Ok(())
    }

    /// The zenoh session configuration.
    pub fn zenoh(&self) -> Result<zenoh::Config, ConfigError> {
        let base = match &self.zenoh_config {
            Some(p) => zenoh::Config::from_file(p).map_err(|e| ConfigError::Zenoh {
                key: p.display().to_string(),
                msg: e.to_string(),
            })?,
            None => zenoh::Config::default(),
        };
        let mut z = apply(base, &self.mode, &self.listen, &self.connect, self.scouting)?;
        let mut set = |k: &str, v: String| {
            z.insert_json5(k, &v).map_err(|e| ConfigError::Zenoh {
                key: k.into(),
                msg: e.to_string(),
            })
        };
        set(
            "transport/link/rx/max_message_size",
            self.max_message_bytes.to_string(),
        )?;
        // Raw streams that this session forwards to other clients (as a peer it routes for
        // them) may be dropped for a consumer that does not keep up (after zenoh's 1 ms), and
        // travel
        // in their own priority lane (`data_low`): a controller's `Block` publication
        // forwarded to a subscriber that stopped reading would otherwise hold the receiving
        // thread — every machine's input — for up to 5 s, and so would a droppable one
        // queued behind the service's own blocked output in the same lane (zenoh locks a
        // link's lane while a `Block` message waits for room). The service's own output keeps
        // `Block` and is queued per machine (outbox), off the receiving and correcting paths.
        set(
            "qos/network",
            format!(
                r#"[{{ id: "scancorrd_forwarded_raw", messages: ["put", "delete"], flows: ["egress"],
                      key_exprs: ["{}/*/raw/**"], overwrite: {{ congestion_control: "drop", priority: "data_low" }} }}]"#,
                self.prefix
            ),
        )?;
        // 16 batches of queue per link in the lanes the service sends in, for bursts.
        set("transport/link/tx/queue/size/data", "16".into())?;
        set("transport/link/tx/queue/size/data_low", "16".into())?;
        // A lost router is tried again at most 1 s apart (zenoh's default backs off to 4 s):
        // every second without one is a second of samples lost. A `zenoh_config` file keeps
        // its own setting (deploy/zenoh-client-tls.json5 has this one).
        if self.zenoh_config.is_none() {
            set(
                "connect/retry",
                "{ period_init_ms: 250, period_max_ms: 1000, period_increase_factor: 2 }".into(),
            )?;
        }
        Ok(z)
    }

    /// The number of correcting worker shards: `workers`, or one per core when 0.
    pub fn workers(&self) -> usize {
        match self.workers {
            0 => std::thread::available_parallelism().map_or(1, |n| n.get()),
            n => n,
        }
    }

    /// Whether `machine` may be served (it is in this instance's assignment).
    pub fn serves(&self, machine: &str) -> bool {
        self.allow_any_machine || self.machines.iter().any(|p| glob(p, machine))
    }

    /// The machine chunks of the key expressions this instance subscribes and answers on:
    /// `*` when it serves any machine, else one per entry of its assignment (a pattern's `*`
    /// becomes zenoh's in-chunk wildcard `$*`).
    pub fn machine_chunks(&self) -> Vec<String> {
        if self.allow_any_machine || self.machines.iter().any(|m| m == "*") {
            return vec!["*".into()];
        }
        let mut v: Vec<String> = self.machines.iter().map(|m| m.replace('*', "$*")).collect();
        v.sort();
        v.dedup();
        v
    }
}

/// Checks an entry of `machines`: a machine id, or a pattern of name characters and single
/// `*`s (never two in a row: `**` means several chunks to zenoh).
pub fn check_pattern(p: &str) -> Result<(), String> {
    if p == "*" {
        return Ok(());
    }
    if p.contains("**") {
        return Err(format!(
            "{}: `**` is not a machine pattern (use one `*`)",
            scancorr_proto::names::shown(p)
        ));
    }
    // Each `*` stands for at least one name character here (a name of one letter in place of
    // each `*` must follow the grammar).
    scancorr_proto::names::check_machine(&p.replace('*', "x")).map_err(|e| {
        format!(
            "{} is not a machine id or pattern: {}",
            scancorr_proto::names::shown(p),
            e.reason
        )
    })
}

/// Whether `name` matches `pattern`, where `*` stands for any run of characters.
pub fn glob(pattern: &str, name: &str) -> bool {
    let Some((head, rest)) = pattern.split_once('*') else {
        return pattern == name;
    };
    let Some(mut tail) = name.strip_prefix(head) else {
        return false;
    };
    let mut parts: Vec<&str> = rest.split('*').collect();
    let last = parts.pop().unwrap_or("");
    for part in parts {
        match tail.find(part) {
            Some(i) => tail = &tail[i + part.len()..],
            None => return false,
        }
    }
    tail.len() >= last.len() && tail.ends_with(last)
}

/// A zenoh configuration from mode and endpoints (shared with the CLI).
pub fn zenoh_config(
    mode: &str,
    listen: &[String],
    connect: &[String],
    scouting: bool,
) -> Result<zenoh::Config, ConfigError> {
    apply(zenoh::Config::default(), mode, listen, connect, scouting)
}

fn apply(
    mut z: zenoh::Config,
    mode: &str,
    listen: &[String],
    connect: &[String],
    scouting: bool,
) -> Result<zenoh::Config, ConfigError> {
    let set = |z: &mut zenoh::Config, k: &str, v: String| {
        z.insert_json5(k, &v).map_err(|e| ConfigError::Zenoh {
            key: k.into(),
            msg: e.to_string(),
        })
    };
    set(&mut z, "mode", format!("\"{mode}\""))?;
    if std::env::var_os("SCANCORR_ZENOH_NO_BATCHING").is_some() {
        // Low latency at the cost of throughput: no adaptive batching on the links.
        set(
            &mut z,
            "transport/link/tx/queue/batching/enabled",
            "false".into(),
        )?;
    }
    set(
        &mut z,
        "listen/endpoints",
        serde_json::to_string(listen).expect("strings"),
    )?;
    set(
        &mut z,
        "connect/endpoints",
        serde_json::to_string(connect).expect("strings"),
    )?;
    set(&mut z, "scouting/multicast/enabled", scouting.to_string())?;
    Ok(z)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_lost_router_is_tried_again_within_a_second_unless_a_file_says_otherwise() {
        let max_ms = |z: zenoh::Config| {
            let r: serde_json::Value =
                serde_json::from_str(&z.get_json("connect/retry").unwrap()).unwrap();
            r["period_max_ms"].as_u64()
        };
        assert_eq!(max_ms(Config::default().zenoh().unwrap()), Some(1000));
        let f = std::env::temp_dir().join(format!("scancorrd-retry-{}.json5", std::process::id()));
        std::fs::write(&f, "{ connect: { retry: { period_max_ms: 8000 } } }").unwrap();
        let z = Config {
            zenoh_config: Some(f.clone()),
            ..Config::default()
        }
        .zenoh()
        .unwrap();
        std::fs::remove_file(&f).ok();
        assert_eq!(max_ms(z), Some(8000));
    }

    #[test]
    fn patterns_match_names_and_become_key_chunks() {
        assert!(glob("m1", "m1") && !glob("m1", "m12"));
        assert!(glob("cell3-*", "cell3-m7") && glob("cell3-*", "cell3-"));
        assert!(!glob("cell3-*", "cell4-m7"));
        assert!(glob("*-left", "m1-left") && !glob("*-left", "m1-right"));
        assert!(glob("a*b*c", "a1b2c") && glob("a*b*c", "abc") && !glob("a*b*c", "ab2"));
        assert!(glob("*", "anything"));
        for bad in ["**", "m**", "", "m 1", "m/1", "$*", "*/x"] {
            assert!(check_pattern(bad).is_err(), "{bad} accepted");
        }
        for good in ["m1", "cell3-*", "*", "*-x", "a*b*c"] {
            assert!(check_pattern(good).is_ok(), "{good} refused");
        }
        let c = Config {
            machines: vec!["m2".into(), "cell3-*".into(), "m1".into()],
            allow_any_machine: false,
            ..Config::default()
        };
        assert_eq!(c.machine_chunks(), ["cell3-$*", "m1", "m2"]);
        assert!(c.serves("cell3-x") && c.serves("m1") && !c.serves("m3"));
        assert_eq!(Config::default().machine_chunks(), ["*"]);
        let none = Config {
            allow_any_machine: false,
            ..Config::default()
        };
        assert!(none.validate().unwrap_err().contains("serve nothing"));
    }
}
