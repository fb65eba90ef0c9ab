//! Every key of the CLI's JSON outputs states its unit by the one table
//! (`scancorr_core::units`): `calib example` (with every effect), `calib nominal`, `lab fit`
//! and `lab diagnose`, the procedures (`calibrate tips`, `probe-force`, `zero-force`,
//! `scales`, `straightness`), `correct`'s summary and `sim`'s; the calibrations they write,
//! their effects' parameter names; and the probe-force text states its coefficients in the unit
//! their name states. Short simulated bags of machine 4747, each made once; every command
//! starts from the user's nominal calibration (`calib nominal` from the simulated data sheet
//! and catalogue); a custom effect's coefficients carry the unit of their expression; the
//! straightness report states the guide's and the part's peak-to-valley about their lines.

mod common;
use common::*;
use scancorr_core::units;
use std::path::Path;

fn walk(what: &str, out: &str, bad: &mut Vec<String>) -> serde_json::Value {
    assert!(!out.contains("NaN"), "{what}: NaN in {out}");
    let v: serde_json::Value =
        serde_json::from_str(out).unwrap_or_else(|e| panic!("{what}: not JSON ({e}): {out}"));
    bad.extend(
        units::check_json(&v)
            .into_iter()
            .map(|b| format!("{what}: {b}")),
    );
    v
}

/// A calibration document: its keys, and every effect's parameter names.
fn calibration(what: &str, dir: &Path, file: &str, bad: &mut Vec<String>) -> usize {
    let text = std::fs::read_to_string(dir.join(file)).unwrap();
    walk(what, &text, bad);
    let cal = scancorr_core::Calibration::from_json(&text).unwrap();
    for e in &cal.effects {
        for n in e.param_names() {
            if let Err(m) = units::check_name(&n) {
                bad.push(format!("{what}: effect {}: {m}", e.kind()));
            }
        }
    }
    cal.effects.len()
}

fn sim(dir: &Path, program: &str, out: &str, extra: &[&str]) -> String {
    let mut a = vec![
        "sim",
        "--program",
        program,
        "--machine-seed",
        "4747",
        "--seed",
        "4747",
        "--out",
        out,
        "--json",
    ];
    a.extend(extra);
    ok(dir, &a)
}

#[test]
fn every_json_output_states_its_units_by_the_table() {
    let dir = scratch("cli-units");
    let d: &Path = &dir;
    let mut bad = vec![];
    // The bags, in parallel (each a process).
    let sims: Vec<(&str, String)> = std::thread::scope(|s| {
        let jobs: Vec<_> = [
            ("tips", "tips.mcap", &BUYERS_DOCUMENTS[..]),
            ("probe-force", "pf.mcap", &[][..]),
            ("thin-wall", "wall.mcap", &[][..]),
            ("scales", "scales.mcap", &[][..]),
            ("straightness-three-probe", "st.mcap", &[][..]),
            ("ring", "ring.mcap", &[][..]),
        ]
        .into_iter()
        .map(|(p, out, extra)| s.spawn(move || (p, sim(d, p, out, extra))))
        .collect();
        jobs.into_iter().map(|j| j.join().unwrap()).collect()
    });
    for (p, out) in &sims {
        walk(&format!("sim --program {p} --json"), out, &mut bad);
    }

    // Calibration documents.
    let example = ok(d, &["calib", "example"]);
    std::fs::write(d.join("example.json"), &example).unwrap();
    let all = ok(d, &["calib", "example", "--all-effects"]);
    std::fs::write(d.join("all.json"), &all).unwrap();
    assert!(calibration("calib example --all-effects", d, "all.json", &mut bad) >= 8);
    // `--all-effects` promises non-zero example parameters: each effect has some.
    let cal = scancorr_core::Calibration::from_json(&all).unwrap();
    for e in &cal.effects {
        assert!(
            e.params().iter().any(|p| *p != 0.0),
            "calib example --all-effects: {} has only zero parameters",
            e.kind()
        );
    }
    let help = ok(d, &["calib", "example", "--help"]);
    assert!(!help.contains("nominal model only"), "{help}");
    let nominal = ok(
        d,
        &[
            "calib",
            "nominal",
            "--datasheet",
            "datasheet.json",
            "--catalogue",
            "catalogue.json",
            "--out",
            "nominal.json",
            "--json",
        ],
    );
    walk("calib nominal --json", &nominal, &mut bad);
    calibration("calib nominal's document", d, "nominal.json", &mut bad);

    // The procedures (each from the nominal start) and the lab, in parallel.
    let calibrate = |proc: &str, bag: &str, from: &str, to: &str, extra: &[&str]| {
        let mut a = vec![
            "calibrate",
            proc,
            "--bag",
            bag,
            "--calib",
            from,
            "--out",
            to,
            "--json",
        ];
        a.extend(extra);
        ok(d, &a)
    };
    let outs: Vec<(String, String)> = std::thread::scope(|s| {
        let a = s.spawn(|| {
            let pf = calibrate("probe-force", "pf.mcap", "nominal.json", "pf.json", &[]);
            let zf = ok(
                d,
                &[
                    "calibrate",
                    "zero-force",
                    "--bag",
                    "wall.mcap",
                    "--calib",
                    "pf.json",
                    "--json",
                ],
            );
            let text = ok(
                d,
                &[
                    "calibrate",
                    "probe-force",
                    "--bag",
                    "pf.mcap",
                    "--calib",
                    "nominal.json",
                    "--out",
                    "pf-text.json",
                ],
            );
            vec![
                ("calibrate probe-force --json".to_string(), pf),
                ("calibrate zero-force --json".to_string(), zf),
                ("calibrate probe-force (text)".to_string(), text),
            ]
        });
        let b = s.spawn(|| {
            vec![
                (
                    "calibrate tips --json".to_string(),
                    calibrate("tips", "tips.mcap", "nominal.json", "tips.json", &[]),
                ),
                (
                    "calibrate scales --json".to_string(),
                    calibrate("scales", "scales.mcap", "nominal.json", "scales.json", &[]),
                ),
                (
                    "calibrate straightness --json".to_string(),
                    calibrate(
                        "straightness",
                        "st.mcap",
                        "nominal.json",
                        "st.json",
                        &["--method", "three-probe", "--report", "st.html"],
                    ),
                ),
                (
                    "lab fit --json".to_string(),
                    ok(
                        d,
                        &[
                            "lab",
                            "fit",
                            "--bag",
                            "ring.mcap",
                            "--calib",
                            "nominal.json",
                            "--out",
                            "fit.json",
                            "--json",
                        ],
                    ),
                ),
                (
                    "lab add custom --json".to_string(),
                    ok(
                        d,
                        &[
                            "lab",
                            "add",
                            "custom",
                            "--term",
                            "x:vx",
                            "--term",
                            "y:sin(2*pi*y/4)",
                            "--bag",
                            "ring.mcap",
                            "--calib",
                            "nominal.json",
                            "--stride",
                            "16",
                            "--out",
                            "custom.json",
                            "--json",
                        ],
                    ),
                ),
                (
                    "lab diagnose --json".to_string(),
                    ok(
                        d,
                        &[
                            "lab",
                            "diagnose",
                            "--bag",
                            "ring.mcap",
                            "--calib",
                            "nominal.json",
                            "--stride",
                            "16",
                            "--json",
                        ],
                    ),
                ),
                (
                    "correct --json".to_string(),
                    ok(
                        d,
                        &[
                            "correct",
                            "--bag",
                            "ring.mcap",
                            "--calib",
                            "nominal.json",
                            "--out",
                            "corrected.mcap",
                            "--json",
                        ],
                    ),
                ),
            ]
        });
        let mut v = a.join().unwrap();
        v.extend(b.join().unwrap());
        v
    });
    let mut walked = 0;
    for (what, out) in &outs {
        if what.ends_with("(text)") {
            continue;
        }
        let v = walk(what, out, &mut bad);
        walked += 1;
        if what == "calibrate probe-force --json" {
            // The force coefficients state their unit, mm/mm as the effect's `k_u (mm/mm)`.
            let p = v["params"].as_object().unwrap();
            let k: Vec<&String> = p.keys().filter(|k| k.contains("probe_k")).collect();
            assert!(k.len() >= 4, "{v:#}");
            assert!(
                k.iter().all(|k| units::key_unit(k) == Some("mm/mm")),
                "{k:?}"
            );
            for k in &k {
                let x = p[*k].as_f64().unwrap();
                assert!(x > 1e-4 && x < 0.1, "{k} = {x}: not mm/mm");
            }
        }
    }
    assert_eq!(walked, 9);
    // The straightness report states the straightness a metrologist reads: peak-to-valley of
    // the guide and of the part about their least-squares lines, as the profiles give them.
    let st = &outs
        .iter()
        .find(|o| o.0 == "calibrate straightness --json")
        .unwrap()
        .1;
    let st: serde_json::Value = serde_json::from_str(st).unwrap();
    let html = std::fs::read_to_string(d.join("st.html")).unwrap();
    let mut pvs = vec![];
    for (which, x, v) in [
        ("guide", "stations_mm", "guide_straightness_mm"),
        ("part", "part_positions_mm", "part_straightness_mm"),
    ] {
        let arr = |k: &str| -> Vec<f64> {
            st[k]
                .as_array()
                .unwrap_or_else(|| panic!("calibrate straightness --json: no `{k}`"))
                .iter()
                .map(|x| x.as_f64().unwrap())
                .collect()
        };
        let pv = pv_about_line_um(&arr(x), &arr(v));
        let stated: f64 = html
            .split(&format!("data-pv-um=\"{which}\">"))
            .nth(1)
            .and_then(|s| s.split(" µm").next())
            .and_then(|s| s.parse().ok())
            .unwrap_or_else(|| panic!("st.html states no {which} peak-to-valley"));
        eprintln!("straightness of the {which}: {stated} µm peak-to-valley (profile: {pv:.3} µm)");
        assert!(
            pv > 0.1 && (stated - pv).abs() <= 0.006,
            "{which}: the report states {stated} µm, the profile is {pv} µm peak-to-valley"
        );
        // The JSON states the same straightness, over the length its profile spans.
        let j = &st["straightness"][which];
        let (jpv, len) = (j["pv_um"].as_f64(), j["length_mm"].as_f64());
        let xs = arr(x);
        let span = xs.iter().cloned().fold(f64::MIN, f64::max)
            - xs.iter().cloned().fold(f64::MAX, f64::min);
        assert!(
            jpv.is_some_and(|j| (j - pv).abs() <= 1e-3 && (j - stated).abs() <= 0.006)
                && len.is_some_and(|l| (l - span).abs() < 1e-3 && l > 10.0),
            "calibrate straightness --json states {j} for the {which}: the profile is {pv} µm \
             peak-to-valley over {span} mm, the report states {stated} µm"
        );
        pvs.push((which, jpv.unwrap(), span));
    }
    // And so does the text, as the JSON rounds it.
    let text = ok(
        d,
        &[
            "calibrate",
            "straightness",
            "--bag",
            "st.mcap",
            "--calib",
            "nominal.json",
            "--out",
            "st-text.json",
            "--method",
            "three-probe",
        ],
    );
    let line = text
        .lines()
        .find(|l| l.contains("peak-to-valley about the least-squares line"))
        .unwrap_or_else(|| panic!("calibrate straightness states no peak-to-valley:\n{text}"));
    for (which, pv, span) in &pvs {
        let want = format!("{which} {pv:.2} µm over {span:.0} mm");
        assert!(line.contains(&want), "`{want}` not in: {line}");
    }
    // A custom term's coefficient carries the unit of its expression: mm per mm/s for a
    // velocity, mm for a dimensionless sine.
    let custom = scancorr_core::Calibration::from_json(
        &std::fs::read_to_string(d.join("custom.json")).unwrap(),
    )
    .unwrap();
    let names: Vec<String> = custom
        .effects
        .iter()
        .filter(|e| e.kind() == "custom")
        .flat_map(|e| e.param_names())
        .collect();
    assert!(
        names.len() == 2 && names[0].ends_with("(mm per mm/s)") && names[1].ends_with("(mm)"),
        "{names:?}"
    );
    for f in [
        "custom.json",
        "pf.json",
        "tips.json",
        "scales.json",
        "st.json",
        "fit.json",
        "example.json",
    ] {
        calibration(f, d, f, &mut bad);
    }
    // The text states each coefficient in the unit its name states.
    let text = &outs.iter().find(|o| o.0.ends_with("(text)")).unwrap().1;
    let lines: Vec<&str> = text.lines().filter(|l| l.contains("probe_k")).collect();
    assert!(lines.len() >= 4, "{text}");
    for l in &lines {
        let name = l.split_whitespace().next().unwrap();
        let value: f64 = l.split_whitespace().nth(1).unwrap().parse().unwrap();
        assert!(
            units::key_unit(name) == Some("mm/mm") && l.contains(" mm/mm ") && value < 0.1,
            "{l}"
        );
    }
    assert!(
        bad.is_empty(),
        "{} key(s) state no unit:\n{}",
        bad.len(),
        bad.join("\n")
    );
}

/// Peak-to-valley about the least-squares line of a profile (positions mm, values mm), µm.
fn pv_about_line_um(x: &[f64], v: &[f64]) -> f64 {
    let n = x.len() as f64;
    let (mx, mv) = (x.iter().sum::<f64>() / n, v.iter().sum::<f64>() / n);
    let sxx: f64 = x.iter().map(|x| (x - mx).powi(2)).sum();
    let sxv: f64 = x.iter().zip(v).map(|(x, v)| (x - mx) * (v - mv)).sum();
    let b = sxv / sxx;
    let r: Vec<f64> = x
        .iter()
        .zip(v)
        .map(|(x, v)| v - mv - b * (x - mx))
        .collect();
    let (lo, hi) = r.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |a, r| {
        (a.0.min(*r), a.1.max(*r))
    });
    (hi - lo) * 1e3
}
/// `calibrate dynamics --json` and `calibrate dynamic-map --json`, each from the user's nominal
/// start (machines 4751 and 4753, no other test uses them): every key states its unit by the
/// table — P in mm per mm/s² (as fitted: 1 mm per mm/s² is 10⁶ µm per m/s²), the servo phase in
/// rad, rad/Hz, rad/Hz², the gain in 1/Hz, 1/Hz², τ in s, a map's error per mm of deflection
/// in mm/mm — and the simulator's truth file names each parameter alike.
#[test]
fn the_dynamic_procedures_state_their_units_by_the_table() {
    let runs: Vec<(String, serde_json::Value, serde_json::Value)> = std::thread::scope(|s| {
        let jobs: Vec<_> = [("dynamics", "4751", false), ("dynamic-map", "4753", true)]
            .into_iter()
            .map(|(p, machine, catalogue)| {
                s.spawn(move || {
                    let dir = scratch(&format!("cli-units-{p}"));
                    measure_from_nominal(&dir, p, machine, machine, "m.mcap", catalogue);
                    let out = ok(
                        &dir,
                        &[
                            "calibrate",
                            p,
                            "--bag",
                            "m.mcap",
                            "--calib",
                            "nominal.json",
                            "--out",
                            "new.json",
                            "--json",
                        ],
                    );
                    let mut bad = vec![];
                    let v = walk(&format!("calibrate {p} --json"), &out, &mut bad);
                    assert!(bad.is_empty(), "{} key(s):\n{}", bad.len(), bad.join("\n"));
                    let truth: serde_json::Value = serde_json::from_str(
                        &std::fs::read_to_string(dir.join("truth.json")).unwrap(),
                    )
                    .unwrap();
                    (p.to_string(), v, truth)
                })
            })
            .collect();
        jobs.into_iter().map(|j| j.join().unwrap()).collect()
    });
    for (p, v, truth) in &runs {
        let params = v["params"].as_object().unwrap();
        let unit = |k: &str| units::key_unit(k).unwrap_or_else(|| panic!("{p}: `{k}`"));
        if p == "dynamics" {
            let mut seen = std::collections::BTreeMap::new();
            for (k, x) in params {
                let u = unit(k.as_str());
                *seen.entry(u).or_insert(0) += 1;
                // Named as the truth names it, in its unit (a unit apart would be 10³–10⁶ off).
                let t = truth["params"][k]
                    .as_f64()
                    .unwrap_or_else(|| panic!("{k}: no truth under that name"));
                let (x, s) = (x.as_f64().unwrap(), v["uncertainty"][k].as_f64().unwrap());
                assert!(
                    (x - t).abs() <= (5.0 * s).max(0.5 * t.abs()),
                    "{k}: {x} ± {s}, truth {t}"
                );
                if k.contains(".P_") {
                    // s²: a compliance of tens of µm per m/s² is some 1e-5.
                    assert!(u == "mm per mm/s²" && x.abs() < 1e-3, "{k} = {x} ({u})");
                }
            }
            eprintln!("calibrate dynamics --json: parameters by unit {seen:?}");
            assert!(
                seen.get("mm per mm/s²").is_some_and(|n| *n >= 10),
                "{seen:?}"
            );
            assert!(seen.get("s").is_some_and(|n| *n >= 2), "{seen:?}");
            assert!(seen.get("rad/Hz").is_some_and(|n| *n >= 1), "{seen:?}");
        } else {
            let us: Vec<&str> = params.keys().map(|k| unit(k.as_str())).collect();
            assert!(
                us.contains(&"mm/mm") && us.contains(&"mm"),
                "{p}: {params:?}"
            );
        }
    }
}
