//! `scancorr calibrate scales` end to end: the simulator's `scales` program (a ball bar along
//! X, Y and Z, each read four times over the room's drift) on a machine no other test uses,
//! from the nominal calibration (no effects). The truth file is read only to judge.

mod common;
use common::*;

fn json(s: &str) -> serde_json::Value {
    serde_json::from_str(s).unwrap_or_else(|e| panic!("not JSON ({e}): {s}"))
}

#[test]
fn scales_expansion_from_a_ball_bar_at_several_temperatures() {
    let dir = scratch("calibrate-scales");
    measure_from_nominal(&dir, "scales", "79", "1", "s.mcap", true);
    let truth = json(&std::fs::read_to_string(dir.join("truth.json")).unwrap());
    let r = calibrate_json(&dir, "scales", "s.mcap", "nominal.json", "s.json");
    let (p, u) = (&r["params"], &r["uncertainty"]);
    for a in ["x", "y", "z"] {
        let name = format!("scale_{a}.alpha_per_k");
        let (v, s) = (p[&name].as_f64().unwrap(), u[&name].as_f64().unwrap());
        let t = truth["params"][&name].as_f64().unwrap();
        let span = r["bars"]
            .as_array()
            .unwrap()
            .iter()
            .find(|b| b["axis"] == a)
            .unwrap()["temp_span_k"]
            .as_f64()
            .unwrap();
        eprintln!(
            "{name}: {:.3} ± {:.3} ppm/K (truth {:.3}) over {span:.2} K",
            v * 1e6,
            s * 1e6,
            t * 1e6
        );
        // Honest: within 3σ; determined: σ a small share of the coefficient.
        assert!(s.is_finite() && s > 0.0, "{name}: σ {s}");
        assert!((v - t).abs() <= 3.0 * s, "{name}: {v} ± {s}, truth {t}");
        assert!(s < 0.1 * t.abs(), "{name}: σ {s} against {t}");
    }
    // The readings' length errors are explained down to the centres' noise.
    let (before, after) = (
        r["rms_before_um"].as_f64().unwrap(),
        r["rms_after_um"].as_f64().unwrap(),
    );
    eprintln!("length errors {before:.3} → {after:.3} µm RMS");
    assert!(before > 1.0 && after < 0.2 * before, "{before} → {after}");
    // The new version holds the scales' expansion at the fitted coefficients.
    let cal = json(&std::fs::read_to_string(dir.join("s.json")).unwrap());
    assert_eq!(cal["parent_version"], 1);
    let st = cal["effects"]
        .as_array()
        .unwrap()
        .iter()
        .find(|e| e["kind"] == "scale_thermal")
        .expect("a scale_thermal effect");
    let stored = st["alpha_per_k"][0].as_f64().unwrap();
    assert!((stored - p["scale_x.alpha_per_k"].as_f64().unwrap()).abs() < 1e-12);
    // The README quotes this run: held to what it prints.
    let q = readme_figures("(test `calibrate_scales`) from the nominal start:", 6);
    for (i, a) in ["x", "y", "z"].iter().enumerate() {
        let name = format!("scale_{a}.alpha_per_k");
        assert_quoted(&name, q[2 * i], p[&name].as_f64().unwrap() * 1e6, 3);
        assert_quoted(&name, q[2 * i + 1], u[&name].as_f64().unwrap() * 1e6, 3);
    }
    let q = readme_figures("the readings' length errors fall from", 2);
    assert_quoted("the length errors before", q[0], before, 3);
    assert_quoted("the length errors after", q[1], after, 3);
}

#[test]
fn scales_without_a_ball_bar_names_the_missing_measurement() {
    let dir = scratch("calibrate-scales-bad");
    measure_from_nominal(&dir, "tips", "79", "2", "t.mcap", true);
    let err = fails(
        &dir,
        &[
            "calibrate",
            "scales",
            "--bag",
            "t.mcap",
            "--calib",
            "nominal.json",
            "--out",
            "s.json",
        ],
        &["ball-bar", "sim --program scales"],
    );
    assert!(!err.contains("NaN"), "{err}");
    assert!(!dir.join("s.json").exists());
}
