//! The bus commands besides `calib`: `health`, `status`, `replay`, `record`, `tail` — each
//! parses its flags and calls the zenoh client (`shared::bus`), printing what it answers.

use crate::shared::{bus, human};
use anyhow::{Context, Result};
use std::path::PathBuf;

/// `scancorr health`.
pub fn health(json: bool, bus: bus::Bus) -> Result<()> {
    let all = bus::health(&bus)?;
    if json {
        outln!("{}", serde_json::Value::Array(all))?;
    } else {
        for h in &all {
            outln!(
                "scancorrd {} (zid {}): ready, up {} s, {} machine(s){}{}",
                h["version"].as_str().unwrap_or("?"),
                h["zid"].as_str().unwrap_or("?"),
                h["uptime_s"],
                h["machines"],
                match h["quarantined"].as_array() {
                    Some(q) if !q.is_empty() => format!(
                        ", quarantined: {}",
                        q.iter()
                            .filter_map(|v| v.as_str())
                            .collect::<Vec<_>>()
                            .join(", ")
                    ),
                    _ => String::new(),
                },
                human::router_link(&h["router_link"])
            )?;
            if let Some(u) = h["uncalibrated"].as_object().filter(|u| !u.is_empty()) {
                let list: Vec<String> = u
                    .iter()
                    .map(|(m, n)| format!("{m} ({n} samples)"))
                    .collect();
                outln!(
                    "  NOT CORRECTING, streaming without a calibration: {}; put one with `scancorr calib put`",
                    list.join(", ")
                )?;
            }
        }
    }
    Ok(())
}

/// `scancorr status`: one machine, or (without `--machine`) the machines served.
pub fn status(machine: Option<String>, json: bool, bus: bus::Bus) -> Result<()> {
    match machine {
        None => {
            let list = bus::machines(&bus)?;
            if json {
                outln!("{}", serde_json::json!({ "machines": list }))?;
            } else {
                outln!("served: {} machine(s): {}", list.len(), list.join(", "))?;
            }
            Ok(())
        }
        Some(machine) => {
            let reply = bus::status(&bus, &machine)?;
            match serde_json::from_str::<serde_json::Value>(&reply) {
                Ok(v) if !json => outln!("{}", human::status(&v).trim_end())?,
                _ => outln!("{reply}")?,
            }
            Ok(())
        }
    }
}

/// `scancorr replay`.
pub fn replay(bag: PathBuf, speed: String, looping: bool, json: bool, bus: bus::Bus) -> Result<()> {
    let r = if speed == "max" {
        None
    } else {
        let v: f64 = speed
            .parse()
            .with_context(|| format!("--speed {speed}: a number (1.0 real time) or max"))?;
        anyhow::ensure!(v.is_finite() && v > 0.0, "--speed must be > 0");
        Some(v)
    };
    let r = bus::replay(&bus, &bag, r, looping)?;
    if json {
        outln!(
            "{}",
            serde_json::json!({"replayed_messages": r.sent, "not_delivered": r.not_delivered, "shed": r.shed, "bag": bag.display().to_string()})
        )?;
    } else {
        eprintln!(
            "replayed {} message(s) from {}{}",
            r.sent,
            bag.display(),
            r.said()
        );
    }
    Ok(())
}

/// `scancorr record`.
#[allow(clippy::too_many_arguments)]
pub fn record(
    keys: String,
    out: PathBuf,
    seconds: Option<f64>,
    idle: Option<f64>,
    count: Option<u64>,
    json: bool,
    bus: bus::Bus,
) -> Result<()> {
    let bound = bus::Bound {
        seconds,
        idle,
        count,
    };
    let n = bus::record(&bus, &keys, &out, bound)?;
    if json {
        outln!(
            "{}",
            serde_json::json!({"recorded_messages": n, "out": out.display().to_string()})
        )?;
    } else {
        eprintln!("recorded {n} message(s) → {}", out.display());
    }
    Ok(())
}

/// `scancorr tail`.
pub fn tail(
    machine: String,
    seconds: Option<f64>,
    count: Option<u64>,
    json: bool,
    bus: bus::Bus,
) -> Result<()> {
    bus::tail(
        &bus,
        &machine,
        bus::Bound {
            seconds,
            idle: None,
            count,
        },
        json,
    )
}
