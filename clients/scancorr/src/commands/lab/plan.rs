//! `scancorr lab plan`: a campaign planned before it is measured — arguments, printing and
//! files. The design and the prediction are `scancorr_core::lab::plan`; with `--program` and
//! `--bag` the lab's own fit on the measured bags is set beside the prediction.

use crate::shared::bags::{load_bags, SENSORS};
use crate::shared::output::commit_all;
use crate::shared::output::{outputs, put};
use anyhow::{Context, Result};
use clap::Args;
use scancorr_core::lab::analysis;
use scancorr_core::lab::dataset::{self, BuildOptions};
use scancorr_core::lab::plan::{self, Assumptions, Owned, PlanRequest, Prediction, Program};
use std::path::{Path, PathBuf};

/// Candidates planned for by default: the physics the lab cannot tell apart on a default
/// campaign (`accel_deflection` against `servo_gain`, `guide_straightness` against
/// `rigid_body`).
pub const DEFAULT_CANDIDATES: [&str; 2] = ["servo_gain:powers=1+2", "rigid_body"];

/// Arguments of `scancorr lab plan`.
#[derive(Args)]
pub struct PlanArgs {
    /// The calibration to plan for (its effects, as fitted, and its noise floor).
    #[arg(long)]
    calib: PathBuf,
    /// An artifact you own: ring:d=50.0012, sphere:d=25.0004, straightedge:l=400 (repeatable).
    #[arg(long)]
    artifact: Vec<String>,
    /// Machine time available, minutes.
    #[arg(long, default_value_t = 15.0)]
    minutes: f64,
    /// The machine's data sheet, for its travel (otherwise the calibration's limits.travel_mm).
    #[arg(long)]
    datasheet: Option<PathBuf>,
    /// A candidate effect to make identifiable as well as the model's (repeatable; default
    /// servo_gain:powers=1+2 and rigid_body; `none` for the model's effects alone).
    #[arg(long)]
    candidate: Vec<String>,
    /// Noise floor of a point, µm (default: the calibration's `metrics.noise_floor_um`).
    #[arg(long)]
    noise_um: Option<f64>,
    /// Lag-1 correlation of the residuals the lab will see.
    #[arg(long, default_value_t = 0.0)]
    rho: f64,
    /// The lab's `--stride`.
    #[arg(long, default_value_t = 4)]
    stride: usize,
    /// The lab will be given held-out bags (`--validate`): every scan fits.
    #[arg(long)]
    validate_separately: bool,
    /// Room temperature at the start, °C.
    #[arg(long, default_value_t = 20.5)]
    temp_c: f64,
    /// Its rise over the campaign, K (a program record's temperature span takes its place).
    #[arg(long, default_value_t = 1.0)]
    temp_rise_k: f64,
    /// The largest rise of the room's temperature you can produce over the campaign, K (the
    /// air conditioning off, the day's drift): the plan weighs spans up to it for the thermal
    /// effects' σ and writes the span to reach into the record (`temperature.span_k`).
    #[arg(long)]
    temp_span_k: Option<f64>,
    /// With --temp-span-k: the corrections are to hold within ±K of 20 °C (the span is chosen
    /// so each thermal correction's uncertainty there is within a third of the noise floor).
    #[arg(long, default_value_t = 2.0)]
    temp_use_k: f64,
    /// Simulated measurements of the design the lab fits to predict its σ (0: the design's
    /// normal matrix alone, no penalty or fold spread).
    #[arg(long, default_value_t = plan::FIT_REPLICATES)]
    replicates: usize,
    /// Predict an existing program record instead of planning one.
    #[arg(long)]
    program: Option<PathBuf>,
    /// With --program: bags measured with it; the lab fits them and sets its σ beside the
    /// prediction.
    #[arg(long)]
    bag: Vec<PathBuf>,
    /// Write the planned program record here (`scancorr sim --program FILE`).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Print JSON.
    #[arg(long)]
    json: bool,
}

fn sig(x: Option<f64>) -> String {
    match x {
        Some(s) => format!("{s:.3e}"),
        None => "undetermined".into(),
    }
}

/// Runs `scancorr lab plan`.
pub fn exec(a: PlanArgs) -> Result<()> {
    let mut inputs: Vec<(&str, &Path)> = vec![("--calib", a.calib.as_path())];
    if let Some(d) = &a.datasheet {
        inputs.push(("--datasheet", d));
    }
    if let Some(p) = &a.program {
        inputs.push(("--program", p));
    }
    inputs.extend(a.bag.iter().map(|b| ("--bag", b.as_path())));
    let [out] = outputs([("--out", a.out.as_deref())], &inputs)?;
    let cal = crate::shared::calib::load_calibration(&a.calib)?;
    let candidates: Vec<String> = if a.candidate.is_empty() {
        DEFAULT_CANDIDATES.iter().map(|s| s.to_string()).collect()
    } else {
        a.candidate
            .iter()
            .filter(|c| c.as_str() != "none")
            .cloned()
            .collect()
    };
    let noise = match a.noise_um {
        Some(n) => n,
        None => {
            let n = Assumptions::noise_from(&cal, f64::NAN);
            anyhow::ensure!(
                n.is_finite(),
                "--calib {}: no noise floor in its metrics (a version the lab wrote has one): give --noise-um",
                a.calib.display()
            );
            n
        }
    };
    anyhow::ensure!(a.stride >= 1, "--stride: at least 1");
    let assumptions = Assumptions {
        noise_um: noise,
        rho: a.rho,
        stride: a.stride,
        heldout_alternate: !a.validate_separately,
        temp_c: a.temp_c,
        temp_rise_k: a.temp_rise_k,
    };
    if let Some(path) = &a.program {
        anyhow::ensure!(
            a.artifact.is_empty() && a.out.is_none() && a.temp_span_k.is_none(),
            "--program predicts a program record as it is (at its own temperature span, if it names one): --artifact, --out and --temp-span-k are for planning one"
        );
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("--program {}: reading", path.display()))?;
        let program = Program::from_json(&text)
            .map_err(|e| anyhow::anyhow!("--program {}: {e}", path.display()))?;
        let pred = predict(&a, &cal, &program, &candidates, &assumptions)?;
        let measured = if a.bag.is_empty() {
            None
        } else {
            Some(measure(&a, &cal, &candidates)?)
        };
        // The same design at the residual and its correlation the bags showed (the lab's
        // residual after its fit, which carries what the model leaves beside the noise floor:
        // the lab's σ is scaled by it), the assumptions set aside.
        let at_measured = match &measured {
            Some((_, _, noise, rho)) if *noise > 0.0 => Some(predict(
                &a,
                &cal,
                &program,
                &candidates,
                &Assumptions {
                    noise_um: *noise,
                    rho: rho.clamp(0.0, 0.98),
                    ..assumptions.clone()
                },
            )?),
            _ => None,
        };
        return print_prediction(
            &a,
            &program,
            &pred,
            measured.as_ref(),
            None,
            at_measured.as_ref(),
        );
    }
    anyhow::ensure!(
        a.bag.is_empty(),
        "--bag: only with --program (the bags measured with a program record)"
    );
    anyhow::ensure!(
        !a.artifact.is_empty(),
        "--artifact: name the artifacts you own, e.g. --artifact ring:d=50.0012 --artifact sphere:d=25.0004 --artifact straightedge:l=400"
    );
    let owned = a
        .artifact
        .iter()
        .map(|s| Owned::parse(s).map_err(|e| anyhow::anyhow!("--artifact {e}")))
        .collect::<Result<Vec<_>>>()?;
    let req = PlanRequest {
        travel_mm: travel(&a, &cal)?,
        owned,
        minutes: a.minutes,
        candidates,
        assumptions,
    };
    let mut planned = plan::plan(&cal, &req)?;
    // The temperature span to reach, when the user says what span they can produce.
    let thermal = match a.temp_span_k {
        Some(s) => plan::apply_thermal(&cal, &mut planned, &req, s, a.temp_use_k)?,
        None => None,
    };
    if a.replicates > 0 {
        planned.prediction = predict(
            &a,
            &cal,
            &planned.program,
            &req.candidates,
            &req.assumptions,
        )?;
    }
    put(&out, planned.program.to_json())?;
    commit_all([out])?;
    print_prediction(
        &a,
        &planned.program,
        &planned.prediction,
        None,
        Some((&planned, thermal.as_ref())),
        None,
    )
}

/// The machine's travel: the data sheet's, else the calibration's limits (refused when they
/// are the default ±5000 mm).
fn travel(a: &PlanArgs, cal: &scancorr_core::Calibration) -> Result<[[f64; 2]; 3]> {
    Ok(match &a.datasheet {
        Some(p) => {
            let text = std::fs::read_to_string(p)
                .with_context(|| format!("--datasheet {}: reading", p.display()))?;
            let d = scancorr_core::datasheet::DataSheet::from_json(&text)
                .map_err(|e| anyhow::anyhow!("--datasheet {}: {e}", p.display()))?;
            [d.axes.x.travel_mm, d.axes.y.travel_mm, d.axes.z.travel_mm]
        }
        None => {
            let t = cal.limits.travel_mm;
            anyhow::ensure!(
                t.iter().all(|[lo, hi]| hi - lo < 9000.0),
                "--calib {}: limits.travel_mm is the default ±5000 mm, not the machine's: give --datasheet (or make the calibration with `calib nominal --datasheet`)",
                a.calib.display()
            );
            t
        }
    })
}

/// The temperature span in words: the span to reach, why, and the worst thermal parameter's
/// σ and correction uncertainty at each span weighed.
fn print_thermal(t: &plan::ThermalPlan) -> Result<()> {
    outln!(
        "  temperature: let the room's temperature rise by {} K over the campaign (the record's temperature.span_k){}",
        t.span_k,
        if t.meets_target { "" } else { " — short of the target" }
    )?;
    outln!("             why: {}", t.why)?;
    for st in &t.ladder {
        let w = st
            .params
            .iter()
            .max_by(|x, y| {
                x.error_um
                    .unwrap_or(f64::INFINITY)
                    .total_cmp(&y.error_um.unwrap_or(f64::INFINITY))
            })
            .map(|p| match (p.sigma, p.error_um) {
                (Some(s), Some(e)) => format!("{}: {} σ {s:.2e}, {e:.3} µm", p.effect, p.name),
                _ => format!("{}: {} undetermined", p.effect, p.name),
            })
            .unwrap_or_default();
        outln!(
            "    {}{:>5} K: worst at ±{} K about 20 °C: {w}",
            if st.span_k == t.span_k { "→" } else { " " },
            st.span_k,
            t.use_k
        )?;
    }
    Ok(())
}

/// The prediction: the lab's fit on `--replicates` simulated measurements, or the design's
/// normal matrix alone.
fn predict(
    a: &PlanArgs,
    cal: &scancorr_core::Calibration,
    program: &Program,
    candidates: &[String],
    assumptions: &Assumptions,
) -> Result<Prediction> {
    Ok(if a.replicates == 0 {
        plan::predict(cal, program, candidates, assumptions)?
    } else {
        plan::predict_by_fit(cal, program, candidates, assumptions, a.replicates)?
    })
}

/// One parameter as the lab measured it.
#[derive(serde::Serialize)]
struct Measured {
    effect: String,
    name: String,
    value: f64,
    sigma: Option<f64>,
    /// Its parts, as the lab composes σ: the normal matrix's, the scan-clustered (sandwich)
    /// one, half the folds' difference and the penalty's shift.
    #[serde(skip_serializing_if = "Option::is_none")]
    sigma_stat: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    sigma_scan: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    fold_spread: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    penalty_shift: Option<f64>,
    /// What the lab says determines it, when not the data alone.
    #[serde(skip_serializing_if = "Option::is_none")]
    note: Option<String>,
}

/// The lab's fit of the model and the candidates on the bags.
fn measure(
    a: &PlanArgs,
    cal: &scancorr_core::Calibration,
    candidates: &[String],
) -> Result<(Vec<Measured>, f64, f64, f64)> {
    let bags = load_bags(&a.bag, &[], &cal.machine_id)?;
    let opts = BuildOptions {
        stride: a.stride,
        holdout_by_segment: !a.validate_separately,
        artifact: None,
        sensors: SENSORS.iter().map(|s| s.to_string()).collect(),
    };
    let ds = dataset::build(&bags, cal, &opts)?;
    let prep = analysis::prepare(&ds)?;
    let configs = plan::configs_for(&ds, candidates)?;
    let cfgs: Vec<_> = configs.iter().map(|(_, c)| c.clone()).collect();
    let o = analysis::fit_effects(&ds, &prep, &cfgs)?;
    let mut v = vec![];
    for ((name, c), ps) in configs.iter().zip(&o.params) {
        let effect = if c.kind() == name || c.id() == *name {
            c.id()
        } else {
            name.clone()
        };
        for p in ps {
            v.push(Measured {
                effect: effect.clone(),
                name: p.name.clone(),
                value: p.value,
                sigma: p.sigma,
                sigma_stat: p.sigma_stat,
                sigma_scan: p.sigma_scan,
                fold_spread: p.fold_spread,
                penalty_shift: p.penalty_shift,
                note: p.note.clone(),
            });
        }
    }
    Ok((
        v,
        ds.noise_floor_um,
        o.rms_after_um.max(ds.noise_floor_um),
        prep.rho,
    ))
}

fn print_prediction(
    a: &PlanArgs,
    program: &Program,
    pred: &Prediction,
    measured: Option<&(Vec<Measured>, f64, f64, f64)>,
    planned: Option<(&plan::Planned, Option<&plan::ThermalPlan>)>,
    at_measured: Option<&Prediction>,
) -> Result<()> {
    let (planned, thermal) = match planned {
        Some((p, t)) => (Some(p), t),
        None => (None, None),
    };
    if a.json {
        let mut j = serde_json::json!({
            "program": program,
            "prediction": pred,
        });
        if let Some(p) = planned {
            j["minutes"] = serde_json::json!(p.minutes);
            j["groups"] = serde_json::to_value(&p.groups)?;
            j["left_out"] = serde_json::to_value(&p.left_out)?;
            j["out"] = serde_json::json!(a.out);
            if let Some(t) = thermal {
                j["thermal"] = serde_json::to_value(t)?;
            }
        }
        if let Some((m, noise, residual, rho)) = measured {
            j["measured"] = serde_json::to_value(m)?;
            j["measured_noise_floor_um"] = serde_json::json!(noise);
            j["measured_residual_um"] = serde_json::json!(residual);
            j["measured_rho"] = serde_json::json!(rho);
        }
        if let Some(p) = at_measured {
            j["prediction_at_measured_noise"] = serde_json::to_value(p)?;
        }
        outln!("{}", serde_json::to_string_pretty(&j)?)?;
        return Ok(());
    }
    if let Some(p) = planned {
        outln!(
            "plan: {} scans on {} artifact placements, {:.1} min of machine time{}",
            program.scans.len(),
            program.features.len(),
            p.minutes,
            a.out
                .as_ref()
                .map(|o| format!(" → {}", o.display()))
                .unwrap_or_default()
        )?;
        for g in &p.groups {
            outln!("  {:5.1} min  {}", g.minutes, g.what)?;
            outln!("             why: {}", g.why)?;
        }
        for g in &p.left_out {
            outln!(
                "  left out for time ({:.1} min): {} — {}",
                g.minutes,
                g.what,
                g.why
            )?;
        }
        if let Some(t) = thermal {
            print_thermal(t)?;
        }
    } else {
        outln!(
            "program {}: {} scans on {} artifact placements{}",
            program.name,
            program.scans.len(),
            program.features.len(),
            program
                .temperature
                .as_ref()
                .map(|t| format!(", the temperature rising by {} K", t.span_k))
                .unwrap_or_default()
        )?;
    }
    outln!(
        "predicted {} ({} points fitted, noise {:.3} µm, ρ {:.2}):",
        if pred.replicates > 0 {
            format!(
                "by the lab's fit on {} simulated measurements of the design",
                pred.replicates
            )
        } else {
            "from the design's normal matrix alone".to_string()
        },
        pred.points,
        pred.noise_um,
        pred.rho
    )?;
    let mut last = String::new();
    for (i, p) in pred.params.iter().enumerate() {
        if p.sigma.is_none() {
            continue;
        }
        if p.effect != last {
            outln!("  {}", p.effect)?;
            last.clone_from(&p.effect);
        }
        let rel = match p.sigma {
            Some(s) if p.value != 0.0 => {
                format!("  ({:.1} % of its value)", 100.0 * s / p.value.abs())
            }
            _ => String::new(),
        };
        let ps_m = at_measured
            .and_then(|q| q.params.get(i))
            .and_then(|q| q.sigma);
        let meas = measured
            .and_then(|(m, _, _, _)| m.get(i))
            .map(|m| match (m.sigma, ps_m.or(p.sigma)) {
                (Some(ms), Some(ps)) if ps > 0.0 => {
                    format!(
                        "   measured {:.3e} ± {ms:.3e} ({:.2}× predicted)",
                        m.value,
                        ms / ps
                    )
                }
                (ms, _) => format!("   measured {:.3e} ± {}", m.value, sig(ms)),
            })
            .unwrap_or_default();
        let joint = if p.determined_alone() {
            ""
        } else {
            "  [confounded: σ set by the lab's penalty]"
        };
        outln!(
            "    {:<28} {:>12.4e}  σ {}{rel}{meas}{joint}",
            p.name,
            p.value,
            sig(p.sigma)
        )?;
    }
    if !pred.correlations.is_empty() {
        outln!("  strongest correlations:")?;
        for c in &pred.correlations {
            outln!("    {:+.4}  {}  ~  {}", c.r, c.a, c.b)?;
        }
    }
    if !pred.confounded.is_empty() {
        outln!(
            "  {} parameter(s) confounded with others (over 99.9 % of the column follows theirs): their σ is the lab's penalty's, not a prediction",
            pred.confounded.len()
        )?;
    }
    if !pred.undetermined.is_empty() {
        let shown: Vec<&str> = pred
            .undetermined
            .iter()
            .take(8)
            .map(|s| s.as_str())
            .collect();
        outln!(
            "  {} parameter(s) this design cannot determine, e.g. {}{}",
            pred.undetermined.len(),
            shown.join("; "),
            if pred.undetermined.len() > 8 {
                "; …"
            } else {
                ""
            }
        )?;
        if !pred.beyond_reach.is_empty() {
            outln!(
                "    of which {} beyond reach of any place with these artifacts (data they cannot give: an error of z alone shifts a horizontal ring as a whole; a term a model effect carries)",
                pred.beyond_reach.len()
            )?;
        }
    }
    if let Some((_, noise, residual, rho)) = measured {
        outln!(
            "  measured: noise floor {noise:.3} µm, residual after the lab's fit {residual:.3} µm, its lag-1 correlation {rho:.2}{}",
            if at_measured.is_some() {
                " (the ratios are to the prediction at the residual and its correlation)"
            } else {
                ""
            }
        )?;
    }
    Ok(())
}
