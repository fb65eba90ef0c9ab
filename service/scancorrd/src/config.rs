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
    /// Machines served; empty means any machine that appears (when `allow_any_machine`).
    pub machines: Vec<String>,
    /// Serve machines not listed in `machines`.
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
        if !["peer", "client", "router"].contains(&c.mode.as_str()) {
            return Err(ConfigError::Parse {
                path: path.into(),
                msg: format!("mode `{}`: peer, client or router", c.mode),
            });
        }
        Ok(c)
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
        apply(base, &self.mode, &self.listen, &self.connect, self.scouting)
    }

    /// Whether `machine` may be served.
    pub fn serves(&self, machine: &str) -> bool {
        self.allow_any_machine || self.machines.iter().any(|m| m == machine)
    }
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
