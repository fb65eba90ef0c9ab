//! `scancorr lab add`: an effect added to the model (built-in, with variant, or custom), fitted, a new version.

use super::args::LabCmd;
use super::data::{dataset_for, load, um};
use super::print::{print_params, print_undetermined};
use crate::report;
use crate::shared::calib::now_rfc3339;
use crate::shared::output::commit_all;
use crate::shared::output::{outputs, put};
use anyhow::{bail, Context, Result};
use scancorr_core::effects::{custom, EffectConfig};
use scancorr_core::lab::analysis;
use scancorr_core::lab::dataset::Dataset;
use scancorr_core::lab::version;
use scancorr_core::sample::Axis;
use scancorr_core::Calibration;

/// Runs `scancorr lab add`.
pub(super) fn exec(cmd: LabCmd) -> Result<()> {
    let LabCmd::Add {
        effect,
        data,
        out,
        refit_all,
        only_new,
        terms,
        name,
        json,
        report,
    } = cmd
    else {
        unreachable!("lab add")
    };
    let [out_file, report_out] = outputs(
        [
            ("--out", Some(out.as_path())),
            ("--report", report.as_deref()),
        ],
        &data.inputs(),
    )?;
    let l = load(&data)?;
    let ds = dataset_for(&l, &l.cal)?;
    let prep = analysis::prepare(&ds)?;
    let cands = candidates(&ds, &l.cal, &effect, &terms, &name)?;
    let _ = refit_all;
    let applied = analysis::apply(&ds, cands, only_new)?;
    let advice = applied.advice.clone();
    let mut o = applied.outcome;
    let vname = match &applied.candidate.replaces {
        Some(r) => format!("{} (replacing {r})", applied.candidate.effect),
        None => applied.candidate.effect.clone(),
    };
    let mut new = version::next(&l.cal, applied.effects, &now_rfc3339());
    // Measure, don't extrapolate: correct again with the new version.
    let ds_after = dataset_for(&l, &new)?;
    let after = analysis::prepare(&ds_after)?;
    // σ carries what the choice of model moves (the moves this data scores near-equal on the
    // new model), as `lab discover`'s does.
    analysis::widen_by_alternatives(&mut o, &analysis::model_spread(&ds_after)?);
    let what = format!(
        "lab add {vname}{}",
        if only_new {
            " (only the new effect fitted)"
        } else {
            ""
        }
    );
    version::describe(&mut new, &what, ds.noise_floor_um, &prep, &after);
    new.build().context("the fitted calibration")?;
    put(&out_file, new.to_json())?;
    // "Before" is the parent as it is, "after" the new version, each on the fit and the
    // held-out data: one definition for the text, the JSON and the report.
    let figures = report::AddFigures {
        fit_um: [prep.rms_fit_um, after.rms_fit_um],
        held_um: [prep.rms_held_um, after.rms_held_um],
        cv_um: [o.cv_rms_before_um, o.cv_rms_after_um],
        validated: !data.validate.is_empty(),
    };
    if report.is_some() {
        let cmp_b = analysis::compare(&ds)?;
        let cmp_a = analysis::compare(&ds_after)?;
        put(
            &report_out,
            report::add(&l.cal, &new, &o, &ds, &cmp_b, &ds_after, &cmp_a, &figures),
        )?;
    }
    // Every output complete: only now do they replace anything.
    commit_all([out_file, report_out])?;
    if let Some(p) = &report {
        eprintln!("report: {}", p.display());
    }
    let summary = serde_json::json!({
        "effect": vname,
        "version": new.version,
        "parent_version": l.cal.version,
        "rms_before_um": prep.rms_fit_um,
        "rms_after_um": after.rms_fit_um,
        "heldout_rms_before_um": prep.rms_held_um,
        "heldout_rms_after_um": after.rms_held_um,
        "noise_floor_um": ds.noise_floor_um,
        "params": o.params.last(),
        "unidentifiable": o.unidentifiable,
        "heldout_improved": after.rms_held_um < prep.rms_held_um,
        "cv_rms_before_um": o.cv_rms_before_um,
        "cv_rms_after_um": o.cv_rms_after_um,
        "figures": figures_json(&figures, l.cal.version, new.version),
        "advice": advice,
        "out": out,
    });
    for a in &advice {
        eprintln!("note: {a}");
    }
    if after.rms_held_um >= prep.rms_held_um && prep.rms_held_um > 0.0 {
        eprintln!(
                    "warning: {vname} does not improve the held-out data ({} → {} µm): `lab diagnose` would not propose it; keep the parent version",
                    um(prep.rms_held_um),
                    um(after.rms_held_um)
                );
    }
    if json {
        outln!("{}", serde_json::to_string_pretty(&summary)?)?;
    } else {
        outln!(
            "added {vname} → {} (version {}, parent {})",
            out.display(),
            new.version,
            l.cal.version
        )?;
        print_figures(&figures, l.cal.version, new.version, ds.noise_floor_um)?;
        print_params(
            o.params.last().map(Vec::as_slice).unwrap_or_default(),
            "    ",
            "every one in --json and --report",
        )?;
        print_undetermined(&o)?;
    }
    Ok(())
}

/// What each of `lab add`'s figures is (its JSON's `figures`): the one definition of
/// "before" (the parent as it is) and "after", and the cross-validated pair, another thing.
fn figures_json(f: &report::AddFigures, parent: u64, new: u64) -> serde_json::Value {
    serde_json::json!({
        "before": format!("v{parent} as it is (not refitted)"),
        "after": format!("v{new}"),
        "rms": "on the fit data",
        "heldout_rms": if f.validated {
            "on the --validate bags"
        } else {
            "on the held-out alternate scans of the fit bags (fitted too)"
        },
        "cv_rms": format!(
            "cross-validated (each alternate scan predicted from the others): v{parent}'s model refitted → v{new}'s"
        ),
    })
}

/// `lab add`'s figures in its text, each labelled as [`figures_json`] defines it.
fn print_figures(f: &report::AddFigures, parent: u64, new: u64, noise_um: f64) -> Result<()> {
    outln!("  before: v{parent} as it is (not refitted); after: v{new}")?;
    outln!(
        "  RMS on fit data   {:>8} → {:>8} µm",
        um(f.fit_um[0]),
        um(f.fit_um[1])
    )?;
    outln!(
        "  RMS held out      {:>8} → {:>8} µm   (noise floor {} µm; {})",
        um(f.held_um[0]),
        um(f.held_um[1]),
        um(noise_um),
        if f.validated {
            "the --validate bags"
        } else {
            "no --validate: the alternate scans of the fit bags, fitted too"
        }
    )?;
    outln!(
        "  cross-validated   {:>8} → {:>8} µm   (v{parent}'s model refitted → v{new}'s, each alternate scan predicted from the others)",
        um(f.cv_um[0]),
        um(f.cv_um[1])
    )
}

/// The candidate moves of `lab add`: the custom effect (its `--term`s), one variant, or every
/// variant of a kind (`--name` their id).
fn candidates(
    ds: &Dataset,
    cal: &Calibration,
    effect: &str,
    terms: &[String],
    name: &Option<String>,
) -> Result<Vec<analysis::Candidate>> {
    Ok(if effect == "custom" {
        if terms.is_empty() {
            bail!("a custom effect needs terms: --term 'x:sin(2*pi*x/4)' --term 'x:cos(2*pi*x/4)'");
        }
        let mut ts = vec![];
        for t in terms {
            let (a, e) = t
                .split_once(':')
                .with_context(|| format!("--term {t}: expected AXIS:EXPR"))?;
            let axis = match a.trim() {
                "x" => Axis::X,
                "y" => Axis::Y,
                "z" => Axis::Z,
                o => bail!("--term {t}: axis `{o}` (x, y or z)"),
            };
            ts.push(custom::Term {
                axis,
                expr: e.trim().to_string(),
            });
        }
        let id = name.clone().unwrap_or_else(|| "custom".into());
        if cal.effects.iter().any(|e| e.id() == id) {
            bail!(
                "an effect with id `{id}` is already in the model; give the new one another --name"
            );
        }
        let n = ts.len();
        vec![analysis::Candidate {
            action: analysis::Move::Add,
            effect: id.clone(),
            replaces: None,
            config: Some(EffectConfig::Custom(custom::Config {
                id,
                dynamic: false,
                terms: ts,
                coefficients: vec![0.0; n],
            })),
        }]
    } else {
        let mut c = analysis::moves_named(ds, effect)?;
        if let Some(n) = name {
            scancorr_proto::names::check("--name", n).map_err(|e| anyhow::anyhow!("{e}"))?;
            for m in &mut c {
                if m.action == analysis::Move::Add {
                    if let Some(cfg) = &mut m.config {
                        cfg.set_id(Some(n.clone()));
                    }
                }
            }
        }
        c
    })
}
