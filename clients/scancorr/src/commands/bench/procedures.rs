//! `scancorr bench procedures`: are the calibration procedures' uncertainties honest? Each
//! procedure runs on `runs` simulated measurements of one machine (run seeds 1…runs), from
//! the nominal model, and every printed parameter is compared with the simulator's truth: the
//! share within 2σ (≈ 95 % for honest σ; the issue asks ≥ 80 %) and within max(3σ, 5 %).
//! Variants on their own programs: `tips-one-angle` (one head angle), `tips-repeat` (the styli's
//! expansion, after `scales`; the styli's lengths judged at the qualification's temperature), `probe-force-quarter|approach|sine`, `dynamics-faces` (the rings
//! with the faces scanned while the carriage oscillates: `calibrate dynamics --bag --bag`),
//! `dynamics-quadratic` (the rings on a machine whose P changes quadratically along X, `sim
//! --with deflection_quadratic`; P2's entries judged as fitted, also where BIC leaves them out),
//! `zero-force-three-forces` (the thin wall at three forces), `zero-force-force-probe` (the
//! thin wall with a force probe, `sim --with force_probe`: each point in the force it reports).
//! `scales` (a ball bar along X, Y and Z read over the room's drift) judges each scale's
//! expansion coefficient (the simulator's truth names `scale_i.alpha_per_k`; the machine's
//! length error g_i has no truth of its own and is not compared).
//! `dynamic-map` has no per-bin truth (a map is a difference of scans): its σ are judged against
//! the runs' scatter about their mean. Runs this executable's `sim` and `calibrate` as child
//! processes, as a user would.

use super::harness::{detrend, exe};
use anyhow::{bail, Context, Result};
use std::collections::BTreeMap;
use std::path::Path;

fn read(p: &Path) -> Result<serde_json::Value> {
    serde_json::from_str(&std::fs::read_to_string(p)?).with_context(|| p.display().to_string())
}

#[derive(Default)]
struct Tally {
    n: usize,
    in2: usize,
    in3: usize,
    per: BTreeMap<String, (usize, usize)>,
    seconds: Vec<f64>,
    /// Comparisons with a non-zero truth, and of them within 2σ (a parameter whose truth is 0
    /// is an easy catch for a wide σ: the share without them is shown beside).
    nonzero: (usize, usize),
}

/// Runs the benchmark.
pub fn run(procedures: &[String], machine: u64, runs: u64, json: bool) -> Result<()> {
    let dir = crate::shared::output::private_dir("scancorr-bench-proc")?;
    let mut all = BTreeMap::new();
    for proc in procedures {
        // (the measurement's program, the procedure, a second measurement's program)
        let (program, calibrate, second) = match proc.as_str() {
            "tips" | "dynamics" | "probe-force" | "scales" => (proc.as_str(), proc.as_str(), None),
            "tips-one-angle" => (proc.as_str(), "tips", None),
            "probe-force-quarter" | "probe-force-approach" | "probe-force-sine" => {
                (proc.as_str(), "probe-force", None)
            }
            "dynamics-faces" => ("dynamics", "dynamics", Some("dynamics-faces")),
            // The rings on a machine whose P changes quadratically along X (`sim --with
            // deflection_quadratic`).
            "dynamics-quadratic" => (proc.as_str(), "dynamics", None),
            "tips-repeat" => {
                let v = tips_repeat(&dir, machine, runs, json)?;
                all.insert(proc.clone(), v);
                continue;
            }
            "zero-force-three-forces" => {
                let v = zero_force(&dir, "thin-wall-forces", &[], machine, runs, json)?;
                all.insert(proc.clone(), v);
                continue;
            }
            "dynamic-map" => {
                let v = dynamic_map(&dir, machine, runs, json)?;
                all.insert(proc.clone(), v);
                continue;
            }
            "zero-force" => {
                let v = zero_force(&dir, "thin-wall", &[], machine, runs, json)?;
                all.insert(proc.clone(), v);
                continue;
            }
            // The thin wall with a force probe (`sim --with force_probe`: a preload, F = F0 +
            // c·|d|), each point extrapolated in the force the probe reports.
            "zero-force-force-probe" => {
                let v = zero_force(
                    &dir,
                    "thin-wall",
                    &["--with", "force_probe"],
                    machine,
                    runs,
                    json,
                )?;
                all.insert(proc.clone(), v);
                continue;
            }
            "straightness" => {
                for method in ["three-probe", "shear-stage"] {
                    let v = straightness(&dir, method, machine, runs, json)?;
                    all.insert(format!("straightness {method}"), v);
                }
                continue;
            }
            "straightness-shear-unequal" | "straightness-three-probe-bow" => {
                let v = straightness(&dir, &proc["straightness-".len()..], machine, runs, json)?;
                all.insert(
                    format!("straightness {}", &proc["straightness-".len()..]),
                    v,
                );
                continue;
            }
            p => bail!("procedure `{p}` ({})", PROCEDURES.join(", ")),
        };
        let mut t = Tally::default();
        for seed in 1..=runs {
            let r = measure_and_calibrate(&dir, program, calibrate, second, machine, seed, &mut t)?;
            let mut truth = read(&dir.join("truth.json"))?;
            if calibrate == "tips" {
                tips_truth_at_qualification(&r, &mut truth);
            }
            judge_params(&r, &truth, &mut t)?;
            if r["quadratic"]["params"].is_object() && r["quadratic"]["decision"] != "selected" {
                // P's ξx² entries as fitted with the term, also when the data left it out.
                judge_params(&r["quadratic"], &truth, &mut t)?;
            }
            if !json {
                eprintln!("{proc}: run {seed}/{runs} done");
            }
        }
        let v = report(proc, &mut t, machine, runs, json)?;
        all.insert(proc.clone(), v);
    }
    std::fs::remove_dir_all(&dir).ok();
    if json {
        outln!("{}", serde_json::to_string_pretty(&all)?)?;
    }
    Ok(())
}

/// The procedures this benchmark runs (`--procedure`).
pub const PROCEDURES: [&str; 18] = [
    "tips",
    "tips-one-angle",
    "tips-repeat",
    "probe-force",
    "probe-force-quarter",
    "probe-force-approach",
    "probe-force-sine",
    "zero-force",
    "zero-force-three-forces",
    "zero-force-force-probe",
    "dynamics",
    "dynamics-faces",
    "dynamics-quadratic",
    "dynamic-map",
    "straightness",
    "straightness-shear-unequal",
    "straightness-three-probe-bow",
    "scales",
];

/// Every printed parameter of `r` with a truth of that name: within 2σ, within max(3σ, 5 %).
fn judge_params(r: &serde_json::Value, truth: &serde_json::Value, t: &mut Tally) -> Result<()> {
    for (name, v) in r["params"].as_object().context("params")? {
        let (Some(v), Some(s), Some(tv)) = (
            v.as_f64(),
            r["uncertainty"][name].as_f64(),
            truth["params"][name].as_f64(),
        ) else {
            continue;
        };
        let d = (v - tv).abs();
        t.n += 1;
        let ok2 = d <= 2.0 * s;
        t.in2 += ok2 as usize;
        t.in3 += (d <= (3.0 * s).max(0.05 * tv.abs())) as usize;
        if tv != 0.0 {
            t.nonzero.0 += 1;
            t.nonzero.1 += ok2 as usize;
        }
        let e = t.per.entry(name.clone()).or_default();
        e.0 += ok2 as usize;
        e.1 += 1;
    }
    Ok(())
}

/// `tips` prints the styli's lengths at the qualification's temperature T_q (the reference of
/// the stylus thermal correction it writes); the simulator's truth states them at 20 °C: the
/// truth's lengths are taken to T_q with each stylus's true coefficient, l·(1 + α·(T_q − 20)).
fn tips_truth_at_qualification(r: &serde_json::Value, truth: &mut serde_json::Value) {
    let Some(t_q) = r["reference_temp_c"].as_f64() else {
        return;
    };
    let p = &truth["params"];
    let at = |tip: &str, field: &str| -> Option<f64> {
        let l = p[format!("{tip}.{field}")].as_f64()?;
        let a = p[format!("{tip}.alpha_per_k")].as_f64()?;
        Some(l * (1.0 + a * (t_q - 20.0)))
    };
    let mut moved = vec![];
    for name in p.as_object().into_iter().flat_map(|o| o.keys()) {
        let Some((tip, field)) = name.split_once('.') else {
            continue;
        };
        let v = match field.strip_prefix("l1_from_") {
            Some(rest) => {
                let reference = rest.trim_end_matches("_mm");
                at(tip, "l1_mm")
                    .zip(at(reference, "l1_mm"))
                    .map(|(a, b)| a - b)
            }
            None if matches!(field, "l1_mm" | "l2_mm" | "l3_mm") => at(tip, field),
            None => None,
        };
        if let Some(v) = v {
            moved.push((name.clone(), v));
        }
    }
    for (name, v) in moved {
        truth["params"][name] = v.into();
    }
}

/// `tips-repeat`: the styli's expansion from each head angle visited twice over the room's
/// drift. Per run the scales' expansion first (`calibrate scales` on the `scales` program from
/// the nominal start: otherwise the scales grow with the room as the styli do), then `calibrate
/// tips` on `tips-repeat` from it; every printed parameter against the truth.
fn tips_repeat(dir: &Path, machine: u64, runs: u64, json: bool) -> Result<serde_json::Value> {
    let mut t = Tally::default();
    let ms = machine.to_string();
    for seed in 1..=runs {
        let mut scales = Tally::default();
        measure_and_calibrate(dir, "scales", "scales", None, machine, seed, &mut scales)?;
        std::fs::rename(dir.join("out.json"), dir.join("scales.json"))?;
        let s = (1000 + seed).to_string();
        exe(
            dir,
            &[
                "sim",
                "--program",
                "tips-repeat",
                "--machine-seed",
                &ms,
                "--seed",
                &s,
                "--out",
                "t.mcap",
                "--truth",
                "truth.json",
            ],
        )?;
        let t0 = std::time::Instant::now();
        let r: serde_json::Value = serde_json::from_str(&exe(
            dir,
            &[
                "calibrate",
                "tips",
                "--bag",
                "t.mcap",
                "--calib",
                "scales.json",
                "--out",
                "out.json",
                "--json",
            ],
        )?)?;
        t.seconds.push(t0.elapsed().as_secs_f64());
        let mut truth = read(&dir.join("truth.json"))?;
        tips_truth_at_qualification(&r, &mut truth);
        judge_params(&r, &truth, &mut t)?;
        if !json {
            eprintln!("tips-repeat: run {seed}/{runs} done");
        }
    }
    report("tips-repeat", &mut t, machine, runs, json)
}

/// The tally's figures (printed unless `json`).
fn report(
    proc: &str,
    t: &mut Tally,
    machine: u64,
    runs: u64,
    json: bool,
) -> Result<serde_json::Value> {
    {
        t.seconds.sort_by(f64::total_cmp);
        let worst: Vec<(String, f64)> = {
            let mut v: Vec<(String, f64)> = t
                .per
                .iter()
                .map(|(k, (a, b))| (k.clone(), *a as f64 / *b as f64))
                .collect();
            v.sort_by(|a, b| a.1.total_cmp(&b.1));
            v.into_iter().take(5).collect()
        };
        let frac = |k: usize| if t.n == 0 { 0.0 } else { k as f64 / t.n as f64 };
        let v = serde_json::json!({
            "runs": runs,
            "machine_seed": machine,
            "parameters": t.per.len(),
            "comparisons": t.n,
            "within_2sigma": frac(t.in2),
            "within_3sigma_or_5pct": frac(t.in3),
            "seconds_median": t.seconds.get(t.seconds.len() / 2).copied().unwrap_or(0.0),
            "comparisons_nonzero_truth": t.nonzero.0,
            "within_2sigma_nonzero_truth": (t.nonzero.0 > 0).then(|| t.nonzero.1 as f64 / t.nonzero.0 as f64),
            "worst": worst.iter().map(|(k, f)| serde_json::json!({"name": k, "within_2sigma": f})).collect::<Vec<_>>(),
        });
        if !json {
            let (what, bound) = if proc.starts_with("zero-force") {
                ("series (every zero-force point on the thin wall)", "3σ")
            } else if proc.starts_with("straightness") {
                ("profiles (every station)", "3σ")
            } else if proc == "dynamic-map" {
                ("map series (every bin of each, about the runs' mean)", "3σ")
            } else {
                ("parameters", "max(3σ, 5 %)")
            };
            outln!(
                "{proc}: {} {what} × {runs} runs of machine {machine}: {:.1} % within 2σ, {:.1} % within {bound}; {:.2} s per procedure (median)",
                t.per.len(),
                100.0 * frac(t.in2),
                100.0 * frac(t.in3),
                v["seconds_median"].as_f64().unwrap_or(0.0)
            )?;
            if t.nonzero.0 > 0 && t.nonzero.0 < t.n {
                outln!(
                    "  of them with a non-zero truth ({} of {} comparisons): {:.1} % within 2σ",
                    t.nonzero.0,
                    t.n,
                    100.0 * t.nonzero.1 as f64 / t.nonzero.0 as f64
                )?;
            }
            outln!(
                "  least often within 2σ: {}",
                worst
                    .iter()
                    .map(|(k, f)| format!("{k} {:.0} %", 100.0 * f))
                    .collect::<Vec<_>>()
                    .join(", ")
            )?;
        }
        Ok(v)
    }
}
/// Linear interpolation of (xs, ys) at x (xs increasing, ≥ 2 points).
fn interp(xs: &[f64], ys: &[f64], x: f64) -> f64 {
    let j = xs.partition_point(|a| *a <= x).clamp(1, xs.len() - 1);
    let w = (x - xs[j - 1]) / (xs[j] - xs[j - 1]);
    ys[j - 1] * (1.0 - w) + ys[j] * w
}

fn floats(v: &serde_json::Value) -> Result<Vec<f64>> {
    v.as_array()
        .context("an array")?
        .iter()
        .map(|x| x.as_f64().context("a number"))
        .collect()
}

/// `calibrate straightness` by `method` on `runs` separation measurements of the guide of
/// `machine` (run seeds 1…runs: each its own straightedge, offsets and noise): every station's
/// guide, part and pitch against the truth (the line no method sees taken out of the
/// difference; three probes with their reversal). `method` may name a variant:
/// `shear-unequal` (the stage's two unequal shears), `three-probe-bow` (three probes without a
/// reversal, the offsets' parabola from a stated 4 µm bow: the simulator's straightedges sag
/// 2–4 µm over 800 mm).
fn straightness(
    dir: &Path,
    method: &str,
    machine: u64,
    runs: u64,
    json: bool,
) -> Result<serde_json::Value> {
    let ms = machine.to_string();
    // The user's start: nominal (the procedure writes only the guide table).
    sim_nominal(
        dir,
        &[
            "sim",
            "--program",
            "ring",
            "--machine-seed",
            &ms,
            "--out",
            "ring.mcap",
            "--calib-out",
            "start.json",
        ],
    )?;
    let program = format!("straightness-{method}");
    let (program, cal_method, bow) = match method {
        "shear-unequal" => (program, "shear-stage", false),
        "three-probe-bow" => ("straightness-three-probe".to_string(), "three-probe", true),
        m => (program, m, false),
    };
    let mut t = Tally::default();
    for seed in 1..=runs {
        let s = seed.to_string();
        let sim = |out: &str, extra: &[&str]| -> Result<String> {
            let mut a = vec![
                "sim",
                "--program",
                &program,
                "--machine-seed",
                &ms,
                "--seed",
                &s,
                "--out",
                out,
            ];
            a.extend_from_slice(extra);
            exe(dir, &a)
        };
        sim("m.mcap", &["--truth", "truth.json"])?;
        let mut cal = vec![
            "calibrate",
            "straightness",
            "--method",
            cal_method,
            "--bag",
            "m.mcap",
            "--calib",
            "nominal.json",
            "--out",
            "out.json",
            "--json",
        ];
        if bow {
            cal.extend(["--straightedge-bow-um", "4"]);
        } else if cal_method == "three-probe" {
            sim("rev.mcap", &["--reversal"])?;
            cal.extend(["--reversal", "rev.mcap"]);
        }
        let t0 = std::time::Instant::now();
        let r: serde_json::Value = serde_json::from_str(&exe(dir, &cal)?)?;
        t.seconds.push(t0.elapsed().as_secs_f64());
        let truth = read(&dir.join("truth.json"))?;
        let xs = floats(&r["stations_mm"])?;
        let (tx, px, tpx) = (
            floats(&truth["stations_mm"])?,
            floats(&r["part_positions_mm"])?,
            floats(&truth["part_positions_mm"])?,
        );
        let mut judge =
            |name: &str, x: &[f64], v: &[f64], u: &[f64], tx: &[f64], tv: &[f64], line: bool| {
                let d: Vec<f64> = x
                    .iter()
                    .zip(v)
                    .map(|(x, v)| v - interp(tx, tv, *x))
                    .collect();
                let d = if line {
                    detrend(x, &d)
                } else {
                    let m = d.iter().sum::<f64>() / d.len().max(1) as f64;
                    d.iter().map(|v| v - m).collect()
                };
                let e = t.per.entry(name.to_string()).or_default();
                for (d, u) in d.iter().zip(u) {
                    let ok2 = d.abs() <= 2.0 * u;
                    t.n += 1;
                    t.in2 += ok2 as usize;
                    t.in3 += (d.abs() <= 3.0 * u) as usize;
                    e.0 += ok2 as usize;
                    e.1 += 1;
                }
            };
        judge(
            "guide_straightness_mm",
            &xs,
            &floats(&r["guide_straightness_mm"])?,
            &floats(&r["guide_straightness_mm_u"])?,
            &tx,
            &floats(&truth["guide_straightness_mm"])?,
            true,
        );
        judge(
            "part_straightness_mm",
            &px,
            &floats(&r["part_straightness_mm"])?,
            &floats(&r["part_straightness_mm_u"])?,
            &tpx,
            &floats(&truth["part_straightness_mm"])?,
            true,
        );
        if r["pitch_rad"].is_array() {
            judge(
                "pitch_rad",
                &xs,
                &floats(&r["pitch_rad"])?,
                &floats(&r["pitch_rad_u"])?,
                &tx,
                &floats(&truth["pitch_rad"])?,
                false,
            );
        }
        if !json {
            eprintln!("straightness {method}: run {seed}/{runs} done");
        }
    }
    report(
        &format!("straightness {method}"),
        &mut t,
        machine,
        runs,
        json,
    )
}

/// `calibrate dynamic-map` on `runs` measurements of one ring on `machine` (run seeds 1…runs:
/// each its own noise and room), from the nominal model: each bin's e2 (and e1) about the mean
/// of the runs, scaled by √(N/(N − 1)), against its stated σ. The simulator holds no per-bin
/// truth of a map (a map is a difference of scans, not a parameter of the machine), so this is
/// the σ's honesty as a repeatability; whether the map is right is judged by the like part
/// (test `calibrate_dynamic_map`).
fn dynamic_map(dir: &Path, machine: u64, runs: u64, json: bool) -> Result<serde_json::Value> {
    if runs < 2 {
        bail!("dynamic-map: at least 2 runs (its σ are judged by the runs' scatter)");
    }
    let mut t = Tally::default();
    // Per series name: each run's values and σ.
    let mut series: BTreeMap<String, Vec<(Vec<f64>, Vec<f64>)>> = BTreeMap::new();
    for seed in 1..=runs {
        let r = measure_and_calibrate(
            dir,
            "dynamic-map",
            "dynamic-map",
            None,
            machine,
            seed,
            &mut t,
        )?;
        for m in r["maps"].as_array().context("maps")? {
            let id = m["id"].as_str().context("map id")?;
            for key in ["e2", "e1"] {
                series.entry(format!("{id}.{key}_um")).or_default().push((
                    floats(&m[format!("{key}_um")])?,
                    floats(&m[format!("{key}_u_um")])?,
                ));
            }
        }
        if !json {
            eprintln!("dynamic-map: run {seed}/{runs} done");
        }
    }
    for (name, rs) in &series {
        let n = rs.len();
        if n < 2 {
            continue;
        }
        let bins = rs[0].0.len();
        let scale = (n as f64 / (n as f64 - 1.0)).sqrt();
        let e = t.per.entry(name.clone()).or_default();
        for j in 0..bins {
            let mean = rs.iter().map(|(v, _)| v[j]).sum::<f64>() / n as f64;
            for (v, u) in rs {
                let d = (v[j] - mean).abs() * scale;
                let ok2 = d <= 2.0 * u[j];
                t.n += 1;
                t.in2 += ok2 as usize;
                t.in3 += (d <= 3.0 * u[j]) as usize;
                e.0 += ok2 as usize;
                e.1 += 1;
            }
        }
    }
    if t.n == 0 {
        bail!("dynamic-map: no map came out of the runs");
    }
    report("dynamic-map", &mut t, machine, runs, json)
}

/// `zero-force`: per run, the sphere's force coefficients (`probe-force` on the quarter
/// variant from the nominal start) and the thin-walled part at two forces (`wall_program` =
/// `thin-wall`; `thin-wall-forces`: at three, the polynomial in the force), the
/// simulator's other machine errors off, `with` switched on in both measurements; every
/// zero-force point against the true unloaded wall (about the points' mean: where the part
/// stands along its normal is free), within 2σ and 3σ of R0's σ.
fn zero_force(
    dir: &Path,
    wall_program: &str,
    with: &[&str],
    machine: u64,
    runs: u64,
    json: bool,
) -> Result<serde_json::Value> {
    use scancorr_core::sample::Vec3;
    const OFF: [&str; 10] = [
        "--effect",
        "accel_deflection=0",
        "--effect",
        "servo_phase=0",
        "--effect",
        "stylus_thermal=0",
        "--effect",
        "scale_thermal=0",
        "--effect",
        "guide_straightness=0",
    ];
    let mut t = Tally::default();
    let ms = machine.to_string();
    for seed in 1..=runs {
        for f in [
            "m.mcap",
            "start.json",
            "datasheet.json",
            "catalogue.json",
            "nominal.json",
            "pf.json",
            "w.mcap",
            "truth.json",
            "zero.xyz",
        ] {
            std::fs::remove_file(dir.join(f)).ok();
        }
        let (s1, s2) = ((2 * seed).to_string(), (2 * seed + 1).to_string());
        let mut a = vec![
            "sim",
            "--program",
            "probe-force-quarter",
            "--machine-seed",
            &ms,
        ];
        a.extend([
            "--seed",
            &s1,
            "--out",
            "m.mcap",
            "--calib-out",
            "start.json",
        ]);
        a.extend(OFF);
        a.extend(with);
        // (The switched-off effects cannot be hidden: the nominal start is the data sheet's.)
        a.extend([
            "--datasheet-out",
            "datasheet.json",
            "--catalogue-out",
            "catalogue.json",
        ]);
        exe(dir, &a)?;
        let nominal = [
            "calib",
            "nominal",
            "--datasheet",
            "datasheet.json",
            "--catalogue",
        ];
        exe(
            dir,
            &[
                &nominal[..],
                &["catalogue.json", "--out", "nominal.json"][..],
            ]
            .concat(),
        )?;
        let pf = [
            "--bag",
            "m.mcap",
            "--calib",
            "nominal.json",
            "--out",
            "pf.json",
        ];
        exe(dir, &[&["calibrate", "probe-force"][..], &pf[..]].concat())?;
        let mut a = vec!["sim", "--program", wall_program, "--machine-seed", &ms];
        a.extend(["--seed", &s2, "--out", "w.mcap", "--truth", "truth.json"]);
        a.extend(OFF);
        a.extend(with);
        exe(dir, &a)?;
        let t0 = std::time::Instant::now();
        let r: serde_json::Value = serde_json::from_str(&exe(
            dir,
            &[
                "calibrate",
                "zero-force",
                "--bag",
                "w.mcap",
                "--calib",
                "pf.json",
                "--points-out",
                "zero.xyz",
                "--json",
            ],
        )?)?;
        t.seconds.push(t0.elapsed().as_secs_f64());
        let sigma = r["sets"][0]["sigma_um"].as_f64().context("sigma_um")?;
        let truth = read(&dir.join("truth.json"))?;
        let wall: scancorr_sim::program::Feature = truth["features"]
            .as_array()
            .context("features")?
            .iter()
            .find(|f| f["artifact"] == scancorr_sim::wall::ARTIFACT)
            .map(|f| serde_json::from_value(f.clone()))
            .context("the wall in the truth")??;
        let n = Vec3::from(wall.normal);
        let along = n.cross(&Vec3::z()).normalize();
        let pts =
            scancorr_core::shape::parse_points(&std::fs::read_to_string(dir.join("zero.xyz"))?)?;
        let h: Vec<f64> = pts
            .iter()
            .map(|p| p - Vec3::from(wall.center))
            .map(|d| (d.dot(&n) - wall.form_at(d.dot(&along))) * 1e3)
            .collect();
        let mean = h.iter().sum::<f64>() / h.len().max(1) as f64;
        let e = t.per.entry("wall points at zero force".into()).or_default();
        for v in &h {
            let d = (v - mean).abs();
            t.n += 1;
            t.in2 += (d <= 2.0 * sigma) as usize;
            t.in3 += (d <= 3.0 * sigma) as usize;
            e.0 += (d <= 2.0 * sigma) as usize;
            e.1 += 1;
        }
        if !json {
            eprintln!("zero-force ({wall_program}): run {seed}/{runs} done");
        }
    }
    let name = if !with.is_empty() {
        format!("zero-force ({wall_program} {})", with.join(" "))
    } else if wall_program == "thin-wall" {
        "zero-force".to_string()
    } else {
        format!("zero-force ({wall_program})")
    };
    report(&name, &mut t, machine, runs, json)
}

/// Simulates `program` on `machine` (run `seed`, every library effect left out of the start,
/// the truth to `truth.json`), writes the nominal start and runs `calibrate proc` on it; its
/// time goes into the tally; returns its `--json`.
/// With `second`, that program is measured too (run seed 1000 + `seed`, to `second.mcap`) and
/// given to the procedure as a second bag (the faces beside the rings).
fn measure_and_calibrate(
    dir: &Path,
    program: &str,
    proc: &str,
    second: Option<&str>,
    machine: u64,
    seed: u64,
    t: &mut Tally,
) -> Result<serde_json::Value> {
    let (ms, s) = (machine.to_string(), seed.to_string());
    let (program, with) = match program {
        "dynamics-quadratic" => ("dynamics", &["--with", "deflection_quadratic"][..]),
        p => (p, &[][..]),
    };
    let mut args = vec![
        "sim",
        "--program",
        program,
        "--machine-seed",
        &ms,
        "--seed",
        &s,
        "--out",
        "m.mcap",
        "--calib-out",
        "start.json",
        "--truth",
        "truth.json",
    ];
    args.extend(with);
    sim_nominal(dir, &args)?;
    let mut cal = vec!["calibrate", proc, "--bag", "m.mcap"];
    let s2 = (1000 + seed).to_string();
    if let Some(p) = second {
        exe(
            dir,
            &[
                "sim",
                "--program",
                p,
                "--machine-seed",
                &ms,
                "--seed",
                &s2,
                "--out",
                "second.mcap",
            ],
        )?;
        cal.extend(["--bag", "second.mcap"]);
    }
    if program.starts_with("probe-force-") {
        // Variants (b)–(d): their deflections are not scanned alike (`calibrate probe-force`).
        cal.extend(["--steady-only", "--compliance-prior", "30"]);
    }
    cal.extend(["--calib", "nominal.json", "--out", "out.json", "--json"]);
    let t0 = std::time::Instant::now();
    let r = serde_json::from_str(&exe(dir, &cal)?)?;
    t.seconds.push(t0.elapsed().as_secs_f64());
    Ok(r)
}

/// Runs `sim_args` with every library effect left out of the start and the machine's data
/// sheet and stylus catalogue beside, then makes the user's nominal start (`nominal.json`: no
/// effects, data-sheet time constants 30 % off, catalogue styli) from them with `scancorr
/// calib nominal`.
fn sim_nominal(dir: &Path, sim_args: &[&str]) -> Result<()> {
    let mut a = sim_args.to_vec();
    for h in scancorr_sim::LIBRARY_EFFECTS {
        a.extend(["--hide", h]);
    }
    a.extend([
        "--datasheet-out",
        "datasheet.json",
        "--catalogue-out",
        "catalogue.json",
    ]);
    exe(dir, &a)?;
    exe(
        dir,
        &[
            "calib",
            "nominal",
            "--datasheet",
            "datasheet.json",
            "--catalogue",
            "catalogue.json",
            "--out",
            "nominal.json",
        ],
    )?;
    Ok(())
}
