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
            for line in failover_lines(&h["failover"]) {
                outln!("{line}")?;
            }
        }
    }
    Ok(())
}

/// `health`'s fail-over block (`failover` on): per machine, whether this instance is active
/// or standing by, since when, its take-overs and split brains.
fn failover_lines(f: &serde_json::Value) -> Vec<String> {
    let Some(machines) = f["machines"].as_object() else {
        return vec![];
    };
    let mut out = vec![format!(
        "  fail-over: active for {} machine(s), standing by for {}{}",
        f["active"],
        f["standby"],
        match f["split_brain_now"].as_u64() {
            Some(n) if n > 0 => format!(", SPLIT BRAIN now for {n} (another instance active too)"),
            _ => String::new(),
        }
    )];
    for (m, v) in machines {
        let since = v["since_unix_ms"]
            .as_u64()
            .map(|ms| scancorr_core::calib::rfc3339_utc((ms / 1000) as i64))
            .unwrap_or_else(|| "?".into());
        let mut line = format!(
            "    {m}: {} since {since} ({} s)",
            v["role"].as_str().unwrap_or("?"),
            v["for_s"]
        );
        if let Some(o) = v["other_active"].as_array().filter(|o| !o.is_empty()) {
            let ids: Vec<&str> = o.iter().filter_map(|x| x.as_str()).collect();
            line += &format!(", active elsewhere: {}", ids.join(", "));
        }
        if let Some(n) = v["standbys"].as_u64().filter(|n| *n > 0) {
            line += &format!(", {n} standby");
        }
        if let Some(n) = v["takeovers"].as_u64().filter(|n| *n > 0) {
            line += &format!(
                ", {n} take-over(s), the last in {} ms",
                v["last_takeover_ms"]
            );
        }
        if let Some(n) = v["split_brains"].as_u64().filter(|n| *n > 0) {
            line += &format!(", {n} split brain(s)");
        }
        out.push(line);
    }
    out
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
    foxglove: (bool, Option<PathBuf>),
    bus: bus::Bus,
) -> Result<()> {
    let bound = bus::Bound {
        seconds,
        idle,
        count,
    };
    use crate::shared::foxglove::{BusSinks, Nominal};
    let (no_foxglove, nominal) = foxglove;
    if no_foxglove && nominal.is_some() {
        anyhow::bail!("--nominal gives the Foxglove channels' deviations: not with --no-foxglove");
    }
    let nominal = nominal
        .map(|b| Nominal::from_bag("--nominal", &b))
        .transpose()?;
    let sinks = (!no_foxglove).then(|| BusSinks::new(&bus.prefix, nominal));
    let n = bus::record(&bus, &keys, &out, bound, sinks)?;
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
