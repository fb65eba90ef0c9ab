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
    // each group by the fraction explained, largest first; each share as its figures give it.
    let rows = diagnosis_rows(&text);
    assert!(rows.len() >= 3, "{text}");
    for r in &rows {
        if let Some((a, b)) = r.label.split_once(" for ") {
            assert_ne!(a, b, "a swap named by the same name twice:\n{text}");
        }
    }
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
            "--report",
            "add.html",
            "--json",
        ],
    ));
    let (hb, ha) = (
        add["heldout_rms_before_um"].as_f64().unwrap(),
        add["heldout_rms_after_um"].as_f64().unwrap(),
    );
    one_before_figure(&d, &add, from);
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

/// `lab fit` on one ring (machine 4790, no other test's) refits effects one placement cannot
/// determine, and the campaign's second run (`--validate`) gets worse: the refit is refused
/// (exit code 1, nothing written) unless `--accept-worse`, which writes it with a warning; the
/// refit on the data the start was fitted on is written without one. `lab diagnose` on the
/// same campaign: each row's words are its numbers (see [`diagnosis_rows`]). Starts from the
/// nominal model with the simulator's list of effects fitted on run 1 ([`fitted_start`]).
#[test]
fn a_refit_worse_than_its_start_is_refused_and_diagnose_says_what_its_numbers_say() {
    let d = scratch("lab-worse");
    std::thread::scope(|s| {
        for (program, seed, out, extra) in [
            (
                "campaign",
                "1",
                "c.mcap",
                &["--calib-out", "sim.json", "--datasheet-out", "ds.json"][..],
            ),
            ("campaign", "2", "c2.mcap", &[][..]),
            ("ring", "3", "ring.mcap", &[][..]),
        ] {
            let d = &d;
            s.spawn(move || {
                let mut a = vec![
                    "sim",
                    "--program",
                    program,
                    "--machine-seed",
                    "4790",
                    "--seed",
                    seed,
                    "--hide",
                    "servo_phase",
                    "--out",
                    out,
                ];
                a.extend(extra);
                ok(d, &a);
            });
        }
    });
    fitted_start(&d, "sim.json", "ds.json", "c.mcap", "v1.json");
    let v1 = json(&std::fs::read_to_string(d.join("v1.json")).unwrap())["version"]
        .as_u64()
        .unwrap();
    let refit = |out: &str, bag: &str, extra: &[&str]| {
        let mut a = vec![
            "lab",
            "fit",
            "--bag",
            bag,
            "--validate",
            "c2.mcap",
            "--calib",
            "v1.json",
            "--out",
            out,
        ];
        a.extend(extra);
        a.iter().map(|s| s.to_string()).collect::<Vec<_>>()
    };
    let args = refit("v2.json", "ring.mcap", &[]);
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let err = fails(
        &d,
        &args,
        &[
            format!("is worse than v{v1} it starts from").as_str(),
            "on the held-out data (--validate)",
            "nothing written to v2.json",
            "--accept-worse",
        ],
    );
    eprintln!("{err}");
    assert!(!d.join("v2.json").exists(), "a refused refit was written");
    let args = refit("v2.json", "ring.mcap", &["--accept-worse", "--json"]);
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let o = run(&d, &args);
    assert!(o.status.success());
    let j = json(&String::from_utf8_lossy(&o.stdout));
    let (hb, ha) = (
        j["heldout_rms_before_um"].as_f64().unwrap(),
        j["heldout_rms_after_um"].as_f64().unwrap(),
    );
    eprintln!("the refit on one ring: held-out (run 2) {hb:.3} → {ha:.3} µm");
    assert!(
        j["worse_than_start"] == true
            && ha > 1.01 * hb
            && d.join("v2.json").exists()
            && String::from_utf8_lossy(&o.stderr).contains("written anyway (--accept-worse)"),
        "{j:#}"
    );
    let args = refit("v3.json", "c.mcap", &["--json"]);
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let j = json(&ok(&d, &args));
    assert!(j["worse_than_start"] == false, "{j:#}");
    // The diagnosis of the start on this campaign, judged on run 2.
    let text = ok(
        &d,
        &[
            "lab",
            "diagnose",
            "--bag",
            "c.mcap",
            "--validate",
            "c2.mcap",
            "--calib",
            "v1.json",
        ],
    );
    eprintln!("{text}");
    let rows = diagnosis_rows(&text);
    assert!(
        rows.len() >= 3 && rows[0].label.starts_with("servo_phase"),
        "{text}"
    );
    // The finding reproduced: a move that removes much of the cross-validated residual and
    // leaves the held-out data worse, which the row now says.
    assert!(
        rows.iter()
            .any(|r| r.cv_pct > 10.0 && r.held_pct.is_some_and(|h| h < 0.0) && !r.significant),
        "{text}"
    );
}

/// One row of `lab diagnose`'s table, as printed.
struct Row {
    label: String,
    cv_pct: f64,
    held_pct: Option<f64>,
    significant: bool,
    cv: (f64, f64),
    held: (f64, f64),
}

/// `lab diagnose`'s table read back, each row's words held to its numbers: its shares
/// (cross-validated and held-out) are those its RMS pairs give, the rows are in the order the
/// output states (significant first, then by the cross-validated share), each label once, and
/// the count of rows whose held-out data is no better is stated.
fn diagnosis_rows(text: &str) -> Vec<Row> {
    let pair = |s: &str| -> Option<(f64, f64)> {
        let (a, b) = s.split_once('→')?;
        Some((a.parse().ok()?, b.parse().ok()?))
    };
    let rows: Vec<Row> = text
        .lines()
        .filter_map(|l| {
            let t: Vec<&str> = l.split_whitespace().collect();
            let n = t.len();
            if n < 8 || !(t[n - 5] == "yes" || t[n - 5] == "no") {
                return None;
            }
            Some(Row {
                label: t[..n - 7].join(" "),
                cv_pct: t[n - 7].strip_suffix('%')?.parse().ok()?,
                held_pct: t[n - 6].strip_suffix('%').and_then(|p| p.parse().ok()),
                significant: t[n - 5] == "yes",
                cv: pair(t[n - 4])?,
                held: pair(t[n - 3])?,
            })
        })
        .collect();
    assert!(
        text.contains(
            "ranked: the significant first, then by the share of the cross-validated residual"
        ),
        "the order is not stated:\n{text}"
    );
    // 1 − (a/b)², from figures rounded to 0.0005 µm: within what that rounding moves it.
    let share = |(b, a): (f64, f64)| {
        let s = 100.0 * (1.0 - (a / b).powi(2));
        let tol = 100.0 * 0.0005 * (2.0 * a / (b * b) + 2.0 * a * a / (b * b * b)) + 0.06;
        (s, tol)
    };
    for r in &rows {
        let (s, tol) = share(r.cv);
        assert!(
            (s - r.cv_pct).abs() <= tol,
            "{}: says it explains {} % of the cross-validated residual, its figures {:?} give {s:.2} %:\n{text}",
            r.label,
            r.cv_pct,
            r.cv
        );
        match r.held_pct {
            Some(h) => {
                let (s, tol) = share(r.held);
                assert!(
                    (s - h).abs() <= tol,
                    "{}: says {h} % of the held-out data, its figures {:?} give {s:.2} %:\n{text}",
                    r.label,
                    r.held
                );
            }
            None => assert!(r.held.0 == 0.0, "{}: no held-out share:\n{text}", r.label),
        }
    }
    for w in rows.windows(2) {
        assert!(
            (w[0].significant, w[0].cv_pct) >= (w[1].significant, w[1].cv_pct),
            "rows out of order ({} then {}):\n{text}",
            w[0].label,
            w[1].label
        );
    }
    let mut labels: Vec<&str> = rows.iter().map(|r| r.label.as_str()).collect();
    labels.sort();
    labels.dedup();
    assert_eq!(
        labels.len(),
        rows.len(),
        "a candidate listed twice:\n{text}"
    );
    let contradicted = rows
        .iter()
        .filter(|r| r.cv_pct > 0.0 && r.held_pct.is_some_and(|h| h <= 0.0))
        .count();
    let said = text
        .lines()
        .find(|l| l.contains("yet leave the held-out data no better"))
        .map(|l| {
            l.split_whitespace()
                .next()
                .unwrap()
                .parse::<usize>()
                .unwrap()
        })
        .unwrap_or(0);
    assert_eq!(said, contradicted, "{text}");
    rows
}

/// `lab add`'s "before" defined once: its JSON, its report and the new version's note give the
/// parent as it is on the fit and the held-out data, the same figures; the report's other
/// figure (every point, each placement fitted) is labelled as another.
fn one_before_figure(d: &std::path::Path, add: &serde_json::Value, from: u64) {
    let html = std::fs::read_to_string(d.join("add.html")).unwrap();
    let stated = |attr: &str| -> f64 {
        html.split(&format!("{attr}\">"))
            .nth(1)
            .and_then(|s| s.split('<').next())
            .and_then(|s| s.parse().ok())
            .unwrap_or_else(|| panic!("add.html states no {attr}"))
    };
    for (attr, key) in [
        ("data-before-um=\"fit", "rms_before_um"),
        ("data-after-um=\"fit", "rms_after_um"),
        ("data-before-um=\"held", "heldout_rms_before_um"),
        ("data-after-um=\"held", "heldout_rms_after_um"),
    ] {
        let j = add[key].as_f64().unwrap();
        assert!(
            (stated(attr) - j).abs() <= 0.0006,
            "the report's {attr} is {}, the JSON's {key} {j}",
            stated(attr)
        );
    }
    assert!(
        html.contains(&format!("<b>Before</b> is v{from} as it is (not refitted)"))
            && html.contains("data-all-points=\"1\"")
            && add["figures"]["before"] == format!("v{from} as it is (not refitted)"),
        "{:#}",
        add["figures"]
    );
    let note = json(&std::fs::read_to_string(d.join("cals/v2.json")).unwrap())["note"]
        .as_str()
        .unwrap()
        .to_string();
    let want = format!(
        "held-out RMS {:.3} → {:.3} µm (fit {:.3} → {:.3} µm)",
        add["heldout_rms_before_um"].as_f64().unwrap(),
        add["heldout_rms_after_um"].as_f64().unwrap(),
        add["rms_before_um"].as_f64().unwrap(),
        add["rms_after_um"].as_f64().unwrap()
    );
    assert!(note.contains(&want), "the note `{note}` is not `{want}`");
}
