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
}
