use super::*;

#[test]
fn a_table_finds_its_keys_in_order_and_only_them() {
    let t: Table<String, u32> = BTreeMap::from([
        ("sp25".to_string(), 1),
        ("ppt".to_string(), 2),
        ("a".to_string(), 3),
    ])
    .into();
    assert_eq!(t.len(), 3);
    assert_eq!(t.get("ppt"), Some(&2));
    assert_eq!(t["sp25"], 1);
    assert_eq!(t.get("sp2"), None);
    assert_eq!(t.values().copied().collect::<Vec<_>>(), [3, 2, 1]);
    let tips = Calibration::example("m1").build().unwrap().tips;
    let first = tips.values().next().unwrap();
    assert_eq!(tips.get(&first.id).map(|t| t.id), Some(first.id));
    assert!(tips.get(&(first.id + 1000)).is_none());
}
use crate::effects::{accel_deflection, stylus_thermal};

fn doc() -> serde_json::Value {
    let mut c = Calibration::example("m1");
    c.effects.push(EffectConfig::AccelDeflection(
        accel_deflection::Config::zeros(1, false),
    ));
    c.effects
        .push(EffectConfig::StylusThermal(stylus_thermal::Config::zeros(
            false,
        )));
    serde_json::to_value(&c).unwrap()
}

fn err(v: serde_json::Value) -> String {
    match Calibration::from_json(&v.to_string()).and_then(|c| c.build().map(|_| c)) {
        Ok(_) => panic!("accepted {v}"),
        Err(e) => e.to_string(),
    }
}

#[test]
fn example_round_trips_and_builds() {
    let v = doc();
    let c = Calibration::from_json(&v.to_string()).unwrap();
    let m = c.build().unwrap();
    assert_eq!(m.effects.len(), 2);
    assert_eq!(m.sensors.names(), &["stylus".to_string()]);
    assert_eq!(Calibration::from_json(&c.to_json()).unwrap(), c);
    // Fitted parameters survive their JSON form to the last bit.
    let mut c = c;
    for v in [
        9.999999999999999e-6_f64,
        0.1 + 0.2,
        1.0 / 3.0,
        2.2250738585072014e-308,
    ] {
        c.sample_period_s = v.max(1e-9).min(0.5);
        c.metrics.insert("x".into(), v);
        let back = Calibration::from_json(&c.to_json()).unwrap();
        assert_eq!(back.metrics["x"].to_bits(), v.to_bits());
        assert_eq!(back.sample_period_s.to_bits(), c.sample_period_s.to_bits());
    }
}

/// Issue 44: `temperature_delay_s = 1e300`, `tau_s = 1e-300`, `sample_period_s = 1e-12`
/// were accepted (and dropped or flagged every point). Every number of the document has a
/// physical range; a value outside is refused naming the field, the value and the range.
#[test]
fn absurd_values_are_refused_naming_field_value_and_range() {
    use serde_json::json;
    let mut base = doc();
    base["effects"].as_array_mut().unwrap().push(json!({
        "kind": "thermal_drift",
        "terms": [{"sensor": "spindle", "tau_s": 600.0, "k_mm_per_k": [0.0, 0.0, 1e-3]}]
    }));
    base["effects"].as_array_mut().unwrap().push(json!({
        "kind": "scale_thermal", "alpha_per_k": [11.5e-6, 11.5e-6, 11.5e-6]
    }));
    base["nominal"]["probes"]["so"] =
        json!({"kind": "second_order", "natural_freq_hz": 200.0, "damping": 0.7});
    base["nominal"]["probes"]["ra"] =
        json!({"kind": "rational", "num": [1.0], "den": [1e-4, 0.02, 1.0]});
    let c = Calibration::from_json(&base.to_string()).unwrap();
    c.build().expect("the base document is valid");
    let cases: &[(&[&str], serde_json::Value, &str, &str, &str)] = &[
        (
            &["join", "temperature_delay_s"],
            json!(1e300),
            "join.temperature_delay_s",
            "1e300",
            "[0, 60] s",
        ),
        (
            &["nominal", "axes", "x", "tau_s"],
            json!(1e-300),
            "nominal.axes.x",
            "1e-300",
            "[1e-5, 10] s",
        ),
        (
            &["nominal", "axes", "y", "tau_s"],
            json!(1e3),
            "nominal.axes.y",
            "1000",
            "[1e-5, 10] s",
        ),
        (
            &["sample_period_s"],
            json!(1e-12),
            "sample_period_s",
            "1e-12",
            "[1e-5, 0.1] s",
        ),
        (
            &["sample_period_s"],
            json!(0.5),
            "sample_period_s",
            "0.5",
            "[1e-5, 0.1] s",
        ),
        (
            &["join", "temperature_max_age_s"],
            json!(0.0),
            "join.temperature_max_age_s",
            "0",
            "[0.01, 86400] s",
        ),
        (
            &["join", "max_gap_periods"],
            json!(1e300),
            "join.max_gap_periods",
            "1e300",
            "[1, 1000] periods",
        ),
        (
            &["join", "clock_reset_s"],
            json!(1e-300),
            "join.clock_reset_s",
            "1e-300",
            "[0.001, 3600] s",
        ),
        (
            &["judgement", "threshold_mm_s2"],
            json!(1e-300),
            "judgement.threshold_mm_s2",
            "1e-300",
            "[1, 1000000] mm/s²",
        ),
        (
            &["judgement", "min_duration_s"],
            json!(1e300),
            "judgement.min_duration_s",
            "1e300",
            "[0, 10] s",
        ),
        (
            &["judgement", "clear_duration_s"],
            json!(-1.0),
            "judgement.clear_duration_s",
            "-1",
            "[0, 10] s",
        ),
        (
            &["judgement", "filter_cutoff_hz"],
            json!(1e-300),
            "judgement.filter_cutoff_hz",
            "1e-300",
            "[0.1, 500] Hz",
        ),
        (
            &["limits", "probe_range_mm"],
            json!(1e-300),
            "limits.probe_range_mm",
            "1e-300",
            "[0.01, 1000] mm",
        ),
        (
            &["limits", "max_correction_mm"],
            json!(1e-9),
            "limits.max_correction_mm",
            "1e-9",
            "[0.001, 1000] mm",
        ),
        (
            &["geometry", "min_contact_deflection_mm"],
            json!(3.0),
            "geometry.min_contact_deflection_mm",
            "3",
            "[0, 1] mm",
        ),
        (
            &["geometry", "tips", "0", "radius_mm"],
            json!(1e300),
            "geometry.tips[0].radius_mm",
            "1e300",
            "[0.005, 100] mm",
        ),
        (
            &["geometry", "tips", "0", "l1_mm"],
            json!(1e7),
            "geometry.tips[0].l1_mm",
            "1e7",
            "[0, 2000] mm",
        ),
        (
            &["geometry", "tips", "0", "beta1_deg"],
            json!(1e300),
            "geometry.tips[0].beta1_deg",
            "1e300",
            "[-360, 360] °",
        ),
        (
            &["nominal", "probes", "so", "natural_freq_hz"],
            json!(1e9),
            "nominal.probes.so",
            "1e9",
            "[0.01, 10000] Hz",
        ),
        (
            &["nominal", "probes", "so", "damping"],
            json!(1e-300),
            "nominal.probes.so",
            "1e-300",
            "[0.001, 100]",
        ),
        (
            &["nominal", "probes", "ra", "den"],
            json!([1e-300, 1.0]),
            "nominal.probes.ra",
            "pole",
            "rad/s",
        ),
        (
            &["effects", "2", "terms", "0", "tau_s"],
            json!(1e300),
            "effects[2].terms[0].tau_s",
            "1e300",
            "[0, 1000000] s",
        ),
        (
            &["effects", "2", "terms", "0", "reference_c"],
            json!(-300.0),
            "effects[2].terms[0].reference_c",
            "-300",
            "°C",
        ),
        (
            &["effects", "3", "alpha_per_k", "1"],
            json!(1.0),
            "effects[3].alpha_per_k[1]",
            "1",
            "1/K",
        ),
        (
            &["effects", "1", "reference_temp_c"],
            json!(1e300),
            "effects[1].reference_temp_c",
            "1e300",
            "°C",
        ),
    ];
    for (path, v, field, value, range) in cases {
        let mut d = base.clone();
        let mut at = &mut d;
        for p in &path[..path.len() - 1] {
            at = match p.parse::<usize>() {
                Ok(i) => &mut at[i],
                Err(_) => &mut at[*p],
            };
        }
        let last = path[path.len() - 1];
        match last.parse::<usize>() {
            Ok(i) => at[i] = v.clone(),
            Err(_) => at[last] = v.clone(),
        }
        let e = err(d);
        assert!(
            e.contains(&format!("`{field}")) && e.contains(value) && e.contains(range),
            "{path:?} = {v}: {e}"
        );
    }
}

/// Issue 44: free text (the audit's author, a note) took bidirectional overrides and
/// zero-width characters, which make it read otherwise than it is stored.
#[test]
fn hidden_characters_in_free_text_are_refused_naming_the_field() {
    let mut v = doc();
    v["note"] = "fitted by lab\nsecond line\twith a tab".into();
    assert!(Calibration::from_json(&v.to_string())
        .unwrap()
        .build()
        .is_ok());
    for (field, text, code) in [
        ("note", "approved \u{202E}v9 noitarbilac", "U+202E"),
        ("note", "ok\u{200B}", "U+200B"),
        ("note", "bell\u{7}", "U+0007"),
        ("note", "tag\u{E0041}", "U+E0041"),
        ("created", "2026-01-01T00:00:00Z\u{2066}", "U+2066"),
        ("created", "2026\n", "U+000A"),
    ] {
        let mut v = doc();
        v[field] = text.into();
        let e = err(v);
        assert!(
            e.contains(&format!("`{field}`")) && e.contains(code),
            "{field} = {text:?}: {e}"
        );
    }
    let mut v = doc();
    v["metrics"] = serde_json::json!({"rms\u{200D}_um": 1.0});
    let e = err(v);
    assert!(e.contains("`metrics.rms<U+200D>_um`"), "{e}");
    let mut v = doc();
    v["effects"]
        .as_array_mut()
        .unwrap()
        .push(serde_json::json!({
            "kind": "feature_map", "feature": "ring \u{202D}A", "segments": [1], "tip": 1,
            "place_tolerance_mm": 1.0, "latitude_deg": 0.0, "values_mm": [0.0, 0.0, 0.0, 0.0],
            "center_mm": [0.0, 0.0]
        }));
    let e = err(v);
    assert!(
        e.contains("`effects[2].feature`") && e.contains("U+202D"),
        "{e}"
    );
    assert_eq!(escape_text("a\u{202E}b"), "a<U+202E>b");
}

#[test]
fn refusals_name_the_field() {
    let mut v = doc();
    v["colour"] = "blue".into();
    assert!(err(v).contains("colour"));

    let mut v = doc();
    v["effects"][0]["kind"] = "gravity_waves".into();
    let e = err(v);
    assert!(
        e.contains("effects[0]") && e.contains("gravity_waves"),
        "{e}"
    );

    let mut v = doc();
    v["effects"][0].as_object_mut().unwrap().remove("p");
    let e = err(v);
    assert!(e.contains("effects[0]") && e.contains("`p`"), "{e}");

    let mut v = doc();
    v["effects"][1]["alpha_shank_per_k"] = serde_json::json!("warm");
    assert!(err(v).contains("effects[1]"));

    let mut v = doc();
    v["nominal"]["axes"]["y"]["tau_s"] = serde_json::json!(-1.0);
    let e = err(v);
    assert!(e.contains("nominal.axes.y") && e.contains("tau_s"), "{e}");

    let mut v = doc();
    v["geometry"]["tips"][0]["probe"] = "unknown".into();
    assert!(err(v).contains("geometry.tips[0].probe"));

    let mut v = doc();
    v["judgement"]["filter_cutoff_hz"] = serde_json::json!(900.0);
    assert!(err(v).contains("judgement.filter_cutoff_hz"));

    let mut v = doc();
    v["effects"][0]["p"] = serde_json::json!([[[0, 0, 0], [0, 0, 0], [0, 0, 0]]]);
    let e = err(v);
    assert!(e.contains("effects[0].p"), "{e}");

    // Non-finite numbers cannot be written in JSON; an overflowing literal is refused.
    let text = doc()
        .to_string()
        .replace("\"sample_period_s\":0.001", "\"sample_period_s\":1e999");
    let e = Calibration::from_json(&text).unwrap_err().to_string();
    assert!(e.contains("sample_period_s"), "{e}");
    assert!(Calibration::example("m1").check_machine("m2").is_err());

    // Trailing garbage after a valid document.
    for tail in ["x", "{}", "\"", "]"] {
        let text = format!("{}{tail}", doc());
        let e = Calibration::from_json(&text).unwrap_err().to_string();
        assert!(e.contains("after the end of the document"), "{e}");
    }
    assert!(Calibration::from_json(&format!("{}  \n", doc())).is_ok());

    // A machine id that would be a key-expression wildcard.
    for bad in ["*", "**", "a/b", "m$*"] {
        let mut v = doc();
        v["machine_id"] = bad.into();
        let e = err(v);
        assert!(e.contains("machine_id"), "{e}");
    }

    let mut v = doc();
    v["limits"]["travel_mm"][1] = serde_json::json!([10.0, -10.0]);
    assert!(err(v).contains("limits.travel_mm[1]"));
    let mut v = doc();
    v["join"]["seq_reset_samples"] = serde_json::json!(0);
    assert!(err(v).contains("join.seq_reset_samples"));
    for (field, bad) in [
        ("max_speed_mm_s", serde_json::json!(0.0)),
        ("max_accel_mm_s2", serde_json::json!(-1.0)),
        ("max_head_rate_deg_s", serde_json::json!(1e300)),
        ("jump_noise_mm", serde_json::json!(-0.001)),
        ("jump_confirm_samples", serde_json::json!(0)),
    ] {
        let mut v = doc();
        v["limits"][field] = bad;
        let e = err(v);
        assert!(e.contains(&format!("limits.{field}")), "{e}");
    }
}

#[test]
fn the_jump_gates_limits_default_and_stay_out_of_documents_that_keep_them() {
    // A document written before the gate's limits existed reads with their defaults, and
    // one that keeps the defaults is written as before (older readers refuse unknown
    // fields).
    let v = doc();
    assert!(v["limits"].get("max_speed_mm_s").is_none(), "{v}");
    let c = Calibration::from_json(&v.to_string()).unwrap();
    let l = &c.limits;
    assert_eq!(
        (l.max_speed_mm_s, l.max_accel_mm_s2, l.max_head_rate_deg_s),
        (2000.0, 50_000.0, 360.0)
    );
    assert_eq!((l.jump_noise_mm, l.jump_confirm_samples), (0.005, 4));
    let mut v = doc();
    v["limits"]["max_speed_mm_s"] = serde_json::json!(500.0);
    let c = Calibration::from_json(&v.to_string()).unwrap();
    c.build().unwrap();
    assert_eq!(c.limits.max_speed_mm_s, 500.0);
    let back = serde_json::to_value(&c).unwrap();
    assert_eq!(back["limits"]["max_speed_mm_s"], serde_json::json!(500.0));
    assert!(back["limits"].get("max_accel_mm_s2").is_none());
}
