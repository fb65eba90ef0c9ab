//! `scancorr bench core` on a calibration of the user's, and what each effect costs: the
//! figures' consistency, never their values (they depend on the host; no timed test).

mod common;
use common::*;
use serde_json::Value;

fn json(s: &str) -> Value {
    serde_json::from_str(s).unwrap_or_else(|e| panic!("not JSON ({e}): {s}"))
}

/// `scancorr bench core --calib FILE --points N --repeat R` and `extra`.
fn core_args<'a>(
    file: &'a str,
    points: &'a str,
    repeat: &'a str,
    extra: &[&'a str],
) -> Vec<&'a str> {
    let mut args = vec![
        "bench", "core", "--calib", file, "--points", points, "--repeat", repeat,
    ];
    args.extend_from_slice(extra);
    args
}

/// The every-effect example of a machine whose travel is far from the benchmarks' default
/// ring, whose only tip is 7 and whose stylus sensor is `probe_head`: the ring must be placed
/// for it.
fn elsewhere(d: &std::path::Path) -> Value {
    let mut cal = json(&ok(
        d,
        &["calib", "example", "--all-effects", "--machine", "m9"],
    ));
    cal["limits"]["travel_mm"] =
        serde_json::json!([[2000.0, 3000.0], [-4000.0, -3000.0], [500.0, 900.0]]);
    cal["geometry"]["tips"][0]["id"] = 7.into();
    for e in cal["effects"].as_array_mut().unwrap() {
        if e["kind"] == "stylus_thermal" {
            e["sensor"] = "probe_head".into();
        }
    }
    cal
}

#[test]
fn bench_core_times_a_users_calibration_and_what_each_effect_costs() {
    let d = scratch("bench-core");
    let cal = elsewhere(&d);
    std::fs::write(d.join("m9.json"), cal.to_string()).unwrap();
    let points = 3000;
    let v = json(&ok(
        &d,
        &core_args("m9.json", "3000", "2", &["--per-effect", "--json"]),
    ));
    assert_eq!(v["calibration"], "m9.json", "{v}");
    // The ring at the centre of the travel (the scales read it 50 mm higher), with the tip
    // and the sensors of this calibration.
    assert_eq!(
        v["ring"]["centre_mm"],
        serde_json::json!([2500.0, -3500.0, 650.0]),
        "{v}"
    );
    assert_eq!(v["ring"]["tip_id"], 7, "{v}");
    assert!(
        v["ring"]["sensors"]
            .as_array()
            .unwrap()
            .contains(&"probe_head".into()),
        "{v}"
    );
    // Corrected where this machine can scan (all but the first 200 ms, which wait for the
    // first temperatures), not dropped as implausible.
    assert!(v["points"].as_u64().unwrap() >= points - 250, "{v}");
    assert!(v["samples_per_s"].as_f64().unwrap() > 0.0, "{v}");
    // Only the calibration asked for: not the every-effect and campaign sets.
    assert!(
        v.get("all_effects").is_none() && v.get("campaign_effects").is_none(),
        "{v}"
    );
    let want: Vec<String> = cal["effects"]
        .as_array()
        .unwrap()
        .iter()
        .map(|e| {
            e["id"]
                .as_str()
                .unwrap_or(e["kind"].as_str().unwrap())
                .to_string()
        })
        .collect();
    assert_eq!(v["effects"], want.len(), "{v}");
    let per = &v["per_effect"];
    assert_eq!(per["rounds"], 2, "{per}");
    let spread = |s: &Value| {
        // Numbers, never null (a NaN would print as null).
        let f = |k: &str| s[k].as_f64().unwrap_or_else(|| panic!("{k} of {s}"));
        let (median, min, max) = (f("median"), f("min"), f("max"));
        assert!(min <= median && median <= max, "{s}");
        (min, max)
    };
    for k in ["every_effect_ns_per_point", "no_effect_ns_per_point"] {
        let (min, _) = spread(&per[k]);
        assert!(min > 0.0, "{k}: {per}");
    }
    assert!(per["shared_ns_per_point"].as_f64().is_some(), "{per}");
    let effects = per["effects"].as_array().unwrap();
    let ids: Vec<&str> = effects.iter().map(|e| e["id"].as_str().unwrap()).collect();
    assert_eq!(ids, want, "{per}");
    for e in effects {
        let (min, max) = spread(&e["ns_per_point"]);
        assert_eq!(e["within_noise"], min <= 0.0 && max >= 0.0, "{e}");
    }

    // The text names every effect.
    let text = ok(&d, &core_args("m9.json", "2000", "1", &["--per-effect"]));
    assert!(text.contains("calibration m9.json: 8 effects"), "{text}");
    assert!(
        text.contains("ring of 25 mm at (2500.0, -3500.0, 650.0) mm, tip 7"),
        "{text}"
    );
    assert!(text.contains("what each effect costs"), "{text}");
    for id in &want {
        assert!(text.contains(id.as_str()), "{id}: {text}");
    }
}

#[test]
fn bench_core_refuses_a_calibration_its_ring_cannot_scan() {
    let d = scratch("bench-core-bad");
    // A travel of 10 mm: no ring of 25 mm fits, every command is implausible.
    let mut cal = elsewhere(&d);
    cal["limits"]["travel_mm"] = serde_json::json!([[0.0, 10.0], [0.0, 10.0], [0.0, 10.0]]);
    std::fs::write(d.join("tiny.json"), cal.to_string()).unwrap();
    fails(
        &d,
        &core_args("tiny.json", "1000", "1", &[]),
        &["tiny.json", "the ring scan gave", "implausible"],
    );
    fails(
        &d,
        &["bench", "core", "--calib", "missing.json"],
        &["reading calibration missing.json"],
    );
}

/// `bench core --hash`: the check that a change to the core's arithmetic keeps its output bit
/// for bit (run it with the binaries before and after). The same pass gives the same hash; the
/// campaign's effects give another output than every effect's.
#[test]
fn bench_core_hashes_its_output() {
    let d = scratch("bench-core-hash");
    let run = || {
        json(&ok(
            &d,
            &["bench", "core", "--points", "2000", "--hash", "--json"],
        ))
    };
    let (a, b) = (run(), run());
    assert_eq!(a, b, "two passes of the same input hash differently");
    let rows = a["hashes"].as_array().unwrap();
    assert_eq!(rows.len(), 2, "{a}");
    for r in rows {
        assert!(r["points"].as_u64().unwrap() > 1000, "{a}");
        assert_eq!(r["hash"].as_str().unwrap().len(), 16, "{a}");
    }
    assert_ne!(rows[0]["hash"], rows[1]["hash"], "{a}");
}
