//! `scancorr calibrate probe-force` end to end: the simulator's `probe-force` program (each tip
//! on the master sphere, three latitudes, three deflections) on a machine no other test uses,
//! from a nominal calibration (no effects, catalogue styli). The truth file is read only to
//! judge.

mod common;
use common::*;
use std::path::Path;

fn json(s: &str) -> serde_json::Value {
    serde_json::from_str(s).unwrap_or_else(|e| panic!("not JSON ({e}): {s}"))
}

/// Simulates `program` on machine 47 (run `seed`) with every library effect left out of the
/// start, and writes the nominal start `nominal.json` with the catalogue's styli.
fn measure(dir: &Path, program: &str, seed: &str, out: &str) {
    measure_from_nominal(dir, program, "47", seed, out, true);
}

/// Each named coefficient is printed with a positive σ and lies within max(3σ, 5 %) of the
/// truth.
fn judge(label: &str, r: &serde_json::Value, truth: &serde_json::Value, axes: &[&str]) {
    for t in [1, 2] {
        for a in axes {
            let name = format!("tip{t}.probe_k_{a}");
            let v = r["params"][&name]
                .as_f64()
                .unwrap_or_else(|| panic!("{name}: {r:#}"));
            let s = r["uncertainty"][&name].as_f64().unwrap();
            let tv = truth["params"][&name].as_f64().unwrap();
            eprintln!("{label} {name}: {v:.6} ± {s:.6}, truth {tv:.6}");
            assert!(s.is_finite() && s > 0.0, "{name}: σ {s}");
            assert!(
                (v - tv).abs() <= (3.0 * s).max(0.05 * tv.abs()),
                "{name}: {v} ± {s}, truth {tv}"
            );
        }
    }
}

#[test]
fn probe_force_recovers_each_tips_bending_from_the_nominal_model() {
    let dir = scratch("calibrate-probe-force");
    measure(&dir, "probe-force", "4", "pf.mcap");
    let truth = json(&std::fs::read_to_string(dir.join("truth.json")).unwrap());
    let out = ok(
        &dir,
        &[
            "calibrate",
            "probe-force",
            "--bag",
            "pf.mcap",
            "--calib",
            "nominal.json",
            "--out",
            "pf.json",
            "--json",
            "--report",
            "pf.html",
        ],
    );
    assert!(!out.contains("NaN"), "{out}");
    let r = json(&out);
    judge("(a)", &r, &truth, &["u", "v", "w"]);
    for t in [1, 2] {
        // The radius at zero force: the true radius up to the circles' other radial errors.
        let v = r["params"][format!("tip{t}.radius_at_zero_force_mm")]
            .as_f64()
            .unwrap();
        let tv = truth["params"][format!("tip{t}.radius_mm")]
            .as_f64()
            .unwrap();
        assert!((v - tv).abs() < 0.5e-3, "tip {t} radius {v} vs {tv}");
    }
    // One coefficient per stylus: the crank bends more than the reference, as in the truth.
    let ratio = |p: &serde_json::Value| {
        p["tip2.probe_k_u"].as_f64().unwrap() / p["tip1.probe_k_u"].as_f64().unwrap()
    };
    let (fit, true_ratio) = (ratio(&r["params"]), ratio(&truth["params"]));
    assert!(
        true_ratio > 1.25,
        "the machine's crank bends like the reference"
    );
    assert!(
        (fit / true_ratio - 1.0).abs() < 0.03,
        "ratio {fit} vs {true_ratio}"
    );
    // The radius no longer depends on the deflection.
    for s in r["settings"].as_array().unwrap() {
        let b: Vec<f64> = s["radius_error_before_um"]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap())
            .collect();
        let a: Vec<f64> = s["radius_error_after_um"]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap())
            .collect();
        let spread = |v: &[f64]| {
            v.iter().cloned().fold(f64::MIN, f64::max) - v.iter().cloned().fold(f64::MAX, f64::min)
        };
        assert!(spread(&b) > 3.0, "{s}");
        assert!(spread(&a) < 0.3, "{s}");
    }
    assert!(r["rms_after_um"].as_f64().unwrap() < 0.2 * r["rms_before_um"].as_f64().unwrap());
    // The new version: per-tip coefficients, its parent, the note.
    let cal = json(&std::fs::read_to_string(dir.join("pf.json")).unwrap());
    assert_eq!(cal["version"], 2);
    assert_eq!(cal["parent_version"], 1);
    assert!(cal["note"].as_str().unwrap().contains("probe-force"));
    let pf = cal["effects"]
        .as_array()
        .unwrap()
        .iter()
        .find(|e| e["kind"] == "probe_force")
        .expect("a probe_force effect");
    assert_eq!(pf["per_tip"].as_object().unwrap().len(), 2, "{pf}");
    let html = std::fs::read_to_string(dir.join("pf.html")).unwrap();
    assert!(html.contains("radius-before") && html.contains("tip2.probe_k_w"));
}

#[test]
fn probe_force_refuses_a_measurement_that_cannot_determine_it() {
    let dir = scratch("calibrate-probe-force-bad");
    // The qualification scans the sphere at one deflection: the force is the radius there.
    measure(&dir, "tips", "1", "tips.mcap");
    fails(
        &dir,
        &[
            "calibrate",
            "probe-force",
            "--bag",
            "tips.mcap",
            "--calib",
            "nominal.json",
            "--out",
            "x.json",
        ],
        &["one deflection", "≥ 2 deflections"],
    );
    // No sphere at all.
    measure(&dir, "ring", "1", "ring.mcap");
    let err = fails(
        &dir,
        &[
            "calibrate",
            "probe-force",
            "--bag",
            "ring.mcap",
            "--calib",
            "nominal.json",
            "--out",
            "x.json",
        ],
        &["master-sphere", "probe-force"],
    );
    assert!(!err.contains("NaN"), "{err}");
    assert!(!dir.join("x.json").exists());
}

/// `probe-force` on `program` of machine 47 (run `seed`) from the nominal start: the printed
/// JSON and the truth.
fn calibrate(dir: &Path, program: &str, seed: &str) -> (serde_json::Value, serde_json::Value) {
    measure(dir, program, seed, "v.mcap");
    let truth = json(&std::fs::read_to_string(dir.join("truth.json")).unwrap());
    let out = ok(
        dir,
        &[
            "calibrate",
            "probe-force",
            "--bag",
            "v.mcap",
            "--calib",
            "nominal.json",
            "--out",
            &format!("{program}.json"),
            "--json",
        ],
    );
    assert!(!out.contains("NaN"), "{out}");
    (json(&out), truth)
}

/// Variants (c) — a full revolution at one deflection and a quarter at another — and (d) —
/// radial approaches at two positions 90° apart — recover what each determines; (d) names
/// k_w, which it cannot see, instead of printing a number for it.
#[test]
fn probe_force_variants_quarter_and_approach() {
    let dir = scratch("calibrate-probe-force-variants");
    let (r, truth) = calibrate(&dir, "probe-force-quarter", "5");
    judge("(c)", &r, &truth, &["u", "v", "w"]);
    let (r, truth) = calibrate(&dir, "probe-force-approach", "6");
    judge("(d)", &r, &truth, &["u", "v"]);
    for t in [1, 2] {
        let w = format!("tip{t}.probe_k_w");
        assert!(r["params"].get(&w).is_none(), "{w} printed: {r:#}");
        assert!(
            r["undetermined"]
                .as_array()
                .unwrap()
                .iter()
                .any(|u| u.as_str().unwrap().starts_with(&w)),
            "{r:#}"
        );
    }
}
