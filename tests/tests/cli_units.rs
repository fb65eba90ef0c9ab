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
