//! Human text for the service's JSON replies (`status`, `calib put`, `calib history`): the
//! default output of the bus commands; `--json` prints the reply itself.

use serde_json::Value;

fn scalar(v: &Value) -> String {
    match v {
        Value::String(s) => s.clone(),
        Value::Null => "—".into(),
        Value::Number(n) => match n.as_f64() {
            Some(x) if n.is_f64() => {
                if x.abs() >= 1000.0 || x == 0.0 {
                    format!("{x:.0}")
                } else {
                    format!("{x:.3}")
                }
            }
            _ => n.to_string(),
        },
        other => other.to_string(),
    }
}

/// An object as `key: value` lines (nested objects indented, short ones on one line).
pub fn object(v: &Value, indent: usize) -> String {
    let pad = " ".repeat(indent);
    let mut out = String::new();
    match v {
        Value::Object(m) => {
            for (k, x) in m {
                let label = k.replace('_', " ");
                match x {
                    Value::Object(inner) if inner.is_empty() => {
                        out += &format!("{pad}{label}: none\n");
                    }
                    Value::Object(inner)
                        if inner.values().all(|y| !y.is_object() && !y.is_array())
                            && inner.len() <= 6 =>
                    {
                        let parts: Vec<String> = inner
                            .iter()
                            .map(|(a, b)| format!("{} {}", a.replace('_', " "), scalar(b)))
                            .collect();
                        out += &format!("{pad}{label}: {}\n", parts.join(", "));
                    }
                    Value::Object(_) => {
                        out += &format!("{pad}{label}:\n{}", object(x, indent + 2));
                    }
                    Value::Array(a) if a.iter().all(|y| !y.is_object() && !y.is_array()) => {
                        let parts: Vec<String> = a.iter().map(scalar).collect();
                        out += &format!(
                            "{pad}{label}: {}\n",
                            if parts.is_empty() {
                                "none".into()
                            } else {
                                parts.join(", ")
                            }
                        );
                    }
                    Value::Array(a) => {
                        out += &format!("{pad}{label}:\n");
                        for y in a {
                            out += &format!("{pad}  -\n{}", object(y, indent + 4));
                        }
                    }
                    _ => out += &format!("{pad}{label}: {}\n", scalar(x)),
                }
            }
        }
        other => out += &format!("{pad}{}\n", scalar(other)),
    }
    out
}

/// A calibration history (an array of versions) as one line each.
pub fn history(v: &Value) -> String {
    let Some(a) = v.as_array() else {
        return object(v, 0);
    };
    if a.is_empty() {
        return "no versions stored\n".into();
    }
    let mut out = String::new();
    for r in a {
        let get = |k: &str| r.get(k).map(scalar).unwrap_or_else(|| "—".into());
        out += &format!(
            "v{:<4} parent {:<4} {}  {}{}\n",
            get("version"),
            get("parent_version"),
            get("created"),
            get("note"),
            if r.get("current").and_then(|c| c.as_bool()) == Some(true) {
                "  (current)"
            } else {
                ""
            }
        );
        if let Some(a) = r.get("audit") {
            let f = |k: &str| a.get(k).map(scalar).unwrap_or_else(|| "—".into());
            out += &format!("      {} at {} by {}\n", f("action"), f("at"), f("by"));
        }
    }
    out
}

/// The health reply's `router_link` as the end of its line: nothing for a service that is
/// not a router's client, else whether it is connected and the outages it had.
pub fn router_link(v: &Value) -> String {
    let Some(n) = v.get("routers").and_then(Value::as_u64) else {
        return String::new();
    };
    let losses = v.get("losses").and_then(Value::as_u64).unwrap_or(0);
    let state = if n == 0 {
        "NO ROUTER (cut off from the bus)".to_string()
    } else {
        format!("{n} router(s)")
    };
    if losses == 0 {
        format!(", {state}")
    } else {
        format!(
            ", {state}, lost {losses} time(s), {} s without",
            v.get("down_s").map(scalar).unwrap_or_else(|| "—".into())
        )
    }
}

/// A machine's status grouped as an operator reads it: the state first (correcting with
/// which version, or loudly not), then stream health, output, calibration and drops; every
/// other field of the reply after them, so nothing is left out.
pub fn status(v: &Value) -> String {
    let Some(m) = v.as_object() else {
        return object(v, 0);
    };
    let get = |k: &str| m.get(k).cloned().unwrap_or(Value::Null);
    let name = m
        .get("machine")
        .and_then(Value::as_str)
        .unwrap_or("machine");
    let uncorrected = get("uncorrected_samples").as_u64().unwrap_or(0);
    let state = match get("calibration_version").as_u64() {
        Some(ver) => format!(
            "{name}: correcting with calibration v{ver}: {} point(s) out, {} flagged",
            scalar(&get("points_out")),
            scalar(&get("points_flagged"))
        ),
        None if uncorrected > 0 => format!(
            "{name}: NOT CORRECTING: streaming without a calibration, {uncorrected} sample(s) \
             uncorrected and no point published; put one with `scancorr calib put`"
        ),
        None => format!("{name}: no calibration in use, nothing streamed yet"),
    };
    let groups: [(&str, &[&str]); 4] = [
        (
            "stream health",
            &[
                "samples_in",
                "samples_missing",
                "seq_gaps",
                "stream_lag_ms",
                "pending",
                "watermarks_ns",
                "clock_resets",
                "seq_resets",
                "queue_wait_ms",
            ],
        ),
        (
            "output",
            &[
                "points_out",
                "points_flagged",
                "alarms_raised",
                "effect_points",
                "uncorrected_samples",
                "streaming_uncalibrated",
            ],
        ),
        (
            "calibration",
            &[
                "calibration_version",
                "inactive_effects",
                "cost_us_per_point",
                "cpu_s",
                "state_bytes",
                "max_pending",
            ],
        ),
        ("drops", &["dropped", "messages"]),
    ];
    let mut out = format!("{state}\n");
    let mut shown: Vec<&str> = vec!["machine"];
    for (title, keys) in groups {
        let part: serde_json::Map<String, Value> = keys
            .iter()
            .filter_map(|k| m.get(*k).map(|x| (k.to_string(), x.clone())))
            .collect();
        shown.extend(keys.iter());
        if !part.is_empty() {
            out += &format!("{title}:\n{}", object(&Value::Object(part), 2));
        }
    }
    let rest: serde_json::Map<String, Value> = m
        .iter()
        .filter(|(k, _)| !shown.contains(&k.as_str()))
        .map(|(k, x)| (k.clone(), x.clone()))
        .collect();
    if !rest.is_empty() {
        out += &format!("other:\n{}", object(&Value::Object(rest), 2));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_router_link_ends_the_health_line() {
        let j = |s: &str| serde_json::from_str::<Value>(s).unwrap();
        assert_eq!(router_link(&Value::Null), "");
        assert_eq!(
            router_link(&j(r#"{"routers":1,"losses":0,"down_s":0.0}"#)),
            ", 1 router(s)"
        );
        assert_eq!(
            router_link(&j(r#"{"routers":0,"losses":2,"down_s":3.5}"#)),
            ", NO ROUTER (cut off from the bus), lost 2 time(s), 3.500 s without"
        );
    }

    #[test]
    fn replies_read_as_lines() {
        let v: Value = serde_json::from_str(
            r#"{"machine":"m1","calibration_version":3,"drops":{"unknown_tip":0,"duplicate":2},"lag_ms":1.5,"sensors":["air","stylus"]}"#,
        )
        .unwrap();
        let t = object(&v, 0);
        assert!(t.contains("calibration version: 3"), "{t}");
        assert!(t.contains("drops: duplicate 2, unknown tip 0"), "{t}");
        assert!(
            t.contains("lag ms: 1.500") && t.contains("sensors: air, stylus"),
            "{t}"
        );
        let h: Value = serde_json::from_str(
            r#"[{"version":1,"parent_version":null,"created":"2026-11-25T10:00:00Z","note":"start"}]"#,
        )
        .unwrap();
        assert!(
            history(&h).starts_with("v1    parent —    2026-11-25T10:00:00Z  start"),
            "{}",
            history(&h)
        );
        assert_eq!(history(&Value::Array(vec![])), "no versions stored\n");
    }
    #[test]
    fn status_reads_state_first_then_groups_and_keeps_every_field() {
        let j = |s: &str| serde_json::from_str::<Value>(s).unwrap();
        let t = status(&j(
            r#"{"machine":"m1","calibration_version":null,"uncorrected_samples":680,"points_out":0,"samples_in":680,"served":true,"dropped":{"duplicate":1}}"#,
        ));
        let first = t.lines().next().unwrap();
        assert!(
            first.starts_with("m1: NOT CORRECTING") && first.contains("680 sample(s)"),
            "{t}"
        );
        for g in [
            "stream health:",
            "output:",
            "calibration:",
            "drops:",
            "other:",
        ] {
            assert!(t.contains(g), "{g} in {t}");
        }
        assert!(t.contains("served: true"), "{t}");
        let ok = status(&j(
            r#"{"machine":"m2","calibration_version":3,"points_out":12,"points_flagged":1}"#,
        ));
        assert!(
            ok.starts_with("m2: correcting with calibration v3: 12 point(s) out, 1 flagged"),
            "{ok}"
        );
    }
}
