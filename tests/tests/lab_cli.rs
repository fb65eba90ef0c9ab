//! The lab's commands as a user runs them: JSON fields, the error fall across versions, and
//! bad input answered with what is missing — never NaN.

mod common;
use common::*;

fn json(s: &str) -> serde_json::Value {
    assert!(
        !s.contains("NaN") && !s.contains("null,\n  \"rms"),
        "NaN in output: {s}"
    );
    serde_json::from_str(s).unwrap_or_else(|e| panic!("not JSON ({e}): {s}"))
}

#[test]
fn compare_diagnose_add_fit_history() {
    let d = scratch("lab");
    ok(
        &d,
        &[
            "sim",
            "--program",
            "campaign",
            "--hide",
            "servo_phase",
            "--out",
            "c.mcap",
            "--calib-out",
            "sim.json",
            "--datasheet-out",
            "ds.json",
            "--truth",
            "t.json",
        ],
    );
    // The user's start: nominal with the other effects' list, fitted on the campaign.
    fitted_start(&d, "sim.json", "ds.json", "c.mcap", "v1.json");
    let from = json(&std::fs::read_to_string(d.join("v1.json")).unwrap())["version"]
        .as_u64()
        .unwrap();
    let cmp = json(&ok(
        &d,
        &[
            "lab", "compare", "--bag", "c.mcap", "--calib", "v1.json", "--json",
        ],
    ));
    for k in ["rms_um", "pv_um", "noise_floor_um"] {
        assert!(cmp[k].as_f64().unwrap().is_finite(), "{k}");
    }
    let failing = cmp["failures"].as_array().unwrap();
    assert!(
        !failing.is_empty(),
        "servo_phase hidden: some bins must stand out"
    );
    for f in failing {
        assert!(
            f["feature"].is_string() && f["bin"].is_string() && f["rms_um"].as_f64().unwrap() > 0.0
        );
    }
    assert!(cmp["rms_um"].as_f64().unwrap() > 3.0 * cmp["noise_floor_um"].as_f64().unwrap());
    // Every plotted series as CSV: a row per trace and 1° bin, per residual bin, per harmonic
    // (the same numbers as the JSON), and the diagnosis's ranking.
    ok(
        &d,
        &[
            "lab", "compare", "--bag", "c.mcap", "--calib", "v1.json", "--csv", "plots",
        ],
    );
    let traces = std::fs::read_to_string(d.join("plots/traces.csv")).unwrap();
    let rows = traces.lines().count() - 1;
    let want: usize = cmp["traces"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| t["theta_deg"].as_array().unwrap().len())
        .sum();
    assert_eq!(rows, want);
    assert!(traces.starts_with("feature,artifact,diameter_mm,direction,speed_mm_s,circularity_um"));
    let bins = std::fs::read_to_string(d.join("plots/bins.csv")).unwrap();
    assert_eq!(
        bins.lines().count() - 1,
        cmp["bins"].as_array().unwrap().len()
    );
    assert!(
        std::fs::read_to_string(d.join("plots/harmonics.csv"))
            .unwrap()
            .lines()
            .count()
            > 5
    );
    let text = ok(
        &d,
        &[
            "lab", "diagnose", "--bag", "c.mcap", "--calib", "v1.json", "--csv", "plots",
        ],
    );
    // The table: every candidate once, no swap named `X for X`, the significant ones first and
    // each group by the fraction explained, largest first.
    let rows: Vec<(String, f64, bool)> = text
        .lines()
        .filter_map(|l| {
            let t: Vec<&str> = l.split_whitespace().collect();
            let n = t.len();
            let pct = t
                .get(n.checked_sub(5)?)?
                .strip_suffix('%')?
                .parse::<f64>()
                .ok()?;
            let sig = t[n - 4];
            (n >= 6 && (sig == "yes" || sig == "no"))
                .then(|| (t[..n - 5].join(" "), pct, sig == "yes"))
        })
        .collect();
    assert!(rows.len() >= 3, "{text}");
    let mut labels: Vec<&str> = rows.iter().map(|r| r.0.as_str()).collect();
    for l in &labels {
        if let Some((a, b)) = l.split_once(" for ") {
            assert_ne!(a, b, "a swap named by the same name twice:\n{text}");
        }
    }
    for w in rows.windows(2) {
        assert!(
            (w[0].2, w[0].1) >= (w[1].2, w[1].1),
            "rows out of order ({} then {}):\n{text}",
            w[0].0,
            w[1].0
        );
    }
    labels.sort();
    labels.dedup();
    assert_eq!(
        labels.len(),
        rows.len(),
        "a candidate listed twice:\n{text}"
    );
    let notes: Vec<&str> = text.lines().filter(|l| l.contains("not tested:")).collect();
    let mut unique = notes.clone();
    unique.sort();
    unique.dedup();
    assert_eq!(unique.len(), notes.len(), "a note repeated:\n{text}");
    let cand = std::fs::read_to_string(d.join("plots/candidates.csv")).unwrap();
    assert!(
        cand.lines().nth(1).unwrap().contains("servo_phase"),
        "{cand}"
    );
    // The prediction plot's series: the best candidate's traces, measured and predicted.
    let pred = std::fs::read_to_string(d.join("plots/prediction.csv")).unwrap();
    let layers = |l: &str| {
        pred.lines()
            .filter(|r| r.contains(&format!(",{l},")))
            .count()
    };
    assert!(
        layers("measured") >= 360 && layers("measured") == layers("predicted"),
        "prediction.csv: {} measured rows, {} predicted",
        layers("measured"),
        layers("predicted")
    );
    let par = std::fs::read_to_string(d.join("plots/parameters.csv")).unwrap();
    assert!(par.lines().count() > 1 && !par.contains("·1 "), "{par}");
    std::fs::write(d.join("afile"), "x").unwrap();
    fails(
        &d,
        &[
            "lab", "compare", "--bag", "c.mcap", "--calib", "v1.json", "--csv", "afile",
        ],
        &["--csv afile: is a file"],
    );
    // Diagnose with held-out scans of the same bag (no --validate).
    let dg = json(&ok(
        &d,
        &[
            "lab", "diagnose", "--bag", "c.mcap", "--calib", "v1.json", "--json",
        ],
    ));
    let c0 = &dg["candidates"][0];
    assert_eq!(
        c0["effect"].as_str().unwrap().split(':').next(),
        Some("servo_phase"),
        "{dg:#}"
    );
    for k in [
        "explained",
        "rms_before_um",
        "rms_after_um",
        "heldout_rms_after_um",
    ] {
        assert!(c0[k].as_f64().unwrap().is_finite());
    }
    assert!(c0["significant"].as_bool().unwrap() && c0["params"].as_array().unwrap().len() == 6);
    assert!(dg["confounded"].is_array() && dg["unexplained"].is_array());
    // The JSON in the table's order: significant first, then by the fraction explained.
    let order: Vec<(bool, f64)> = dg["candidates"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| {
            (
                c["significant"].as_bool().unwrap(),
                c["explained"].as_f64().unwrap(),
            )
        })
        .collect();
    assert!(order.windows(2).all(|w| w[0] >= w[1]), "{order:?}");
    // Add → the next version, fit → the one after, history shows the fall.
    std::fs::create_dir_all(d.join("cals")).unwrap();
    std::fs::copy(d.join("v1.json"), d.join("cals/v1.json")).unwrap();
    let add = json(&ok(
        &d,
        &[
            "lab",
            "add",
            "servo_phase",
            "--bag",
            "c.mcap",
            "--calib",
            "v1.json",
            "--out",
            "cals/v2.json",
            "--json",
        ],
    ));
    let (hb, ha) = (
        add["heldout_rms_before_um"].as_f64().unwrap(),
        add["heldout_rms_after_um"].as_f64().unwrap(),
    );
    assert!(ha < 0.3 * hb, "{add:#}");
    assert!(add["rms_after_um"].as_f64().unwrap() < add["rms_before_um"].as_f64().unwrap());
    let fit = json(&ok(
        &d,
        &[
            "lab",
            "fit",
            "--bag",
            "c.mcap",
            "--calib",
            "cals/v2.json",
            "--out",
            "cals/v3.json",
            "--json",
        ],
    ));
    assert_eq!(fit["version"], from + 2);
    let nominal = fit["nominal"].as_array().unwrap();
    assert_eq!(nominal.len(), 3);
    for a in nominal {
        assert!(a["rms_after_um"].as_f64().unwrap() <= a["rms_before_um"].as_f64().unwrap());
    }
    assert!(
        fit["heldout_rms_after_um"].as_f64().unwrap() < 1.5 * ha,
        "{fit:#}"
    );
    let hist = json(&ok(
        &d,
        &[
            "lab",
            "history",
            "--calib-dir",
            "cals",
            "--bag",
            "c.mcap",
            "--json",
        ],
    ));
    let rows = hist.as_array().unwrap();
    assert_eq!(
        rows.iter()
            .map(|r| r["version"].as_u64().unwrap())
            .collect::<Vec<_>>(),
        vec![from, from + 1, from + 2]
    );
    assert!(
        rows[1]["heldout_rms_um"].as_f64().unwrap()
            < 0.3 * rows[0]["heldout_rms_um"].as_f64().unwrap()
    );
    let text = ok(&d, &["lab", "history", "--calib-dir", "cals"]);
    assert!(text.contains('█') && text.contains("servo_phase"), "{text}");
}

#[test]
fn lab_bad_input_says_what_is_missing() {
    let d = scratch("labbad");
    sim_ring(&d, "v1.json");
    // A bag without the program/artifact record.
    copy_bag(&d.join("r.mcap"), &d.join("bare.mcap"), |_| true);
    fails(
        &d,
        &["lab", "compare", "--bag", "bare.mcap", "--calib", "v1.json"],
        &["--artifact ring:d="],
    );
    let c = json(&ok(
        &d,
        &[
            "lab",
            "compare",
            "--bag",
            "bare.mcap",
            "--calib",
            "v1.json",
            "--artifact",
            "ring:d=50.0012",
            "--json",
        ],
    ));
    assert!(c["rms_um"].as_f64().unwrap() < 1.0, "{c:#}");
    fails(
        &d,
        &[
            "lab",
            "compare",
            "--bag",
            "bare.mcap",
            "--calib",
            "v1.json",
            "--artifact",
            "sphere",
        ],
        &["d="],
    );
    fails(
        &d,
        &[
            "lab",
            "compare",
            "--bag",
            "bare.mcap",
            "--calib",
            "v1.json",
            "--artifact",
            "cube:d=3",
        ],
        &["unknown artifact"],
    );
    // An effect the data cannot support.
    fails(
        &d,
        &[
            "lab",
            "add",
            "guide_straightness:axis=z",
            "--bag",
            "r.mcap",
            "--calib",
            "v1.json",
            "--out",
            "x.json",
        ],
        &["along z"],
    );
    fails(
        &d,
        &[
            "lab", "add", "gravity", "--bag", "r.mcap", "--calib", "v1.json", "--out", "x.json",
        ],
        &["unknown effect"],
    );
    fails(
        &d,
        &[
            "lab", "add", "custom", "--bag", "r.mcap", "--calib", "v1.json", "--out", "x.json",
        ],
        &["--term"],
    );
    fails(
        &d,
        &[
            "lab", "add", "custom", "--term", "x:sin(q)", "--bag", "r.mcap", "--calib", "v1.json",
            "--out", "x.json",
        ],
        &["'q'"],
    );
    // Too little data: the first 5 % of the bag holds no scan.
    let bytes = std::fs::read(d.join("r.mcap")).unwrap();
    std::fs::write(d.join("short.mcap"), &bytes[..bytes.len() / 8]).unwrap();
    let e = run(
        &d,
        &[
            "lab",
            "compare",
            "--bag",
            "short.mcap",
            "--calib",
            "v1.json",
        ],
    );
    let err = String::from_utf8_lossy(&e.stderr);
    assert!(
        !e.status.success() && !err.contains("panicked") && !err.contains("NaN"),
        "{err}"
    );
    assert!(err.contains("no streams") || err.contains("scan"), "{err}");
    // Too few points to fit.
    fails(
        &d,
        &[
            "lab", "diagnose", "--bag", "r.mcap", "--calib", "v1.json", "--stride", "5000",
        ],
        &["too few points"],
    );
}

/// One ring, scanned once for fitting at one temperature, from the nominal model with a
/// data-sheet stylus expansion: cross-validation still works (blocks along the scan), nothing
/// is ever NaN, and the expansion the data cannot determine is kept as it is, with the reason,
/// instead of being dropped or swapped.
#[test]
fn one_ring_at_one_temperature_keeps_what_it_cannot_determine() {
    let d = scratch("lab-one-ring");
    ok(
        &d,
        &[
            "sim",
            "--program",
            "ring",
            "--out",
            "r.mcap",
            "--calib-out",
            "s.json",
        ],
    );
    // What a user has: the nominal model, and the stylus expansion from the data sheet
    // (steel, 11.5 ppm/K), no fitted parameter.
    let mut cal = json(&std::fs::read_to_string(d.join("s.json")).unwrap());
    cal["effects"] = serde_json::json!([{
        "kind": "stylus_thermal",
        "alpha_shank_per_k": 11.5e-6,
        "alpha_bent_per_k": 11.5e-6,
        "reference_temp_c": 20.0,
        "sensor": "stylus"
    }]);
    std::fs::write(d.join("nominal.json"), cal.to_string()).unwrap();
    let dg = json(&ok(
        &d,
        &[
            "lab",
            "diagnose",
            "--bag",
            "r.mcap",
            "--calib",
            "nominal.json",
            "--json",
        ],
    ));
    let cv = dg["cv_rms_um"].as_f64().unwrap();
    let noise = dg["noise_floor_um"].as_f64().unwrap();
    assert!(cv.is_finite() && cv > 0.5 * noise, "{dg:#}");
    for c in dg["candidates"].as_array().unwrap() {
        assert!(c["explained"].as_f64().unwrap().is_finite(), "{c:#}");
        if c["action"] == "drop" || c["action"] == "swap" {
            let r = c["replaces"].as_str().unwrap();
            assert!(
                !r.contains("thermal"),
                "{r} offered though the data cannot determine it: {c:#}"
            );
        }
    }
    let skipped: Vec<&str> = dg["skipped"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s.as_str().unwrap())
        .collect();
    assert!(
        skipped
            .iter()
            .any(|s| s.contains("stylus_thermal") && s.contains("one temperature")),
        "{skipped:?}"
    );
}

/// A calibration without the tip the bag scanned with: the lab says why it has no points —
/// the drops by reason, with their count and what to do — instead of "no scan points".
#[test]
fn a_lab_without_points_says_why() {
    let d = scratch("lab-why-no-points");
    ok(
        &d,
        &[
            "sim",
            "--program",
            "ring",
            "--out",
            "r.mcap",
            "--calib-out",
            "s.json",
        ],
    );
    let mut cal = json(&std::fs::read_to_string(d.join("s.json")).unwrap());
    // The nominal model (no effects) with the wrong tip.
    cal["effects"] = serde_json::json!([]);
    cal["geometry"]["tips"][0]["id"] = serde_json::json!(7);
    std::fs::write(d.join("wrong_tip.json"), cal.to_string()).unwrap();
    let err = fails(
        &d,
        &[
            "lab",
            "compare",
            "--bag",
            "r.mcap",
            "--calib",
            "wrong_tip.json",
        ],
        &["no scan points", "unknown_tip", "geometry.tips"],
    );
    // The count is there: "dropped N of M samples: N unknown_tip".
    assert!(
        err.split_whitespace()
            .any(|w| w.parse::<u64>().is_ok_and(|n| n > 1000)),
        "{err}"
    );
}
