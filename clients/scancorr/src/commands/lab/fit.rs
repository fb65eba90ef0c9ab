//! `scancorr lab fit`: an unchanged model refitted, a new version.

use super::args::LabCmd;
use super::data::{dataset_for, load, um};
use super::print::{print_params, print_undetermined};
use crate::shared::calib::now_rfc3339;
use crate::shared::output::commit_all;
use crate::shared::output::{outputs, put};
use anyhow::{bail, Result};
use scancorr_core::lab::analysis::{self};
use scancorr_core::lab::dataset::{self};
use scancorr_core::lab::version;

/// Runs `scancorr lab fit`.
pub(super) fn exec(cmd: LabCmd) -> Result<()> {
    let LabCmd::Fit {
        data,
        out,
        json,
        accept_worse,
    } = cmd
    else {
        unreachable!("lab fit")
    };
    let [out_file] = outputs([("--out", Some(out.as_path()))], &data.inputs())?;
    let l = load(&data)?;
    let raw: Vec<&dyn dataset::Samples> = l
        .bags
        .iter()
        .filter(|b| !b.validation)
        .map(|b| &*b.samples)
        .collect();
    let (mut new, axes) = scancorr_core::lab::nominal::fit_nominal(&raw, &l.cal)?;
    let ds0 = dataset_for(&l, &l.cal)?;
    let p0 = analysis::prepare(&ds0)?;
    let ds = dataset_for(&l, &new)?;
    let prep = analysis::prepare(&ds)?;
    // Each effect's parameters ± σ, as `lab add` and `lab discover` report theirs.
    let fitted = if new.effects.is_empty() {
        None
    } else {
        let o = analysis::fit_effects(&ds, &prep, &new.effects)?;
        new.effects = o.configs.clone();
        Some(o)
    };
    // `new` is the start with its nominal model and effects refitted: its child.
    let mut new = version::next(&new, new.effects.clone(), &now_rfc3339());
    let ds_after = dataset_for(&l, &new)?;
    let after = analysis::prepare(&ds_after)?;
    version::describe(&mut new, "lab fit", ds.noise_floor_um, &p0, &after);
    // A refit worse than its start is not written without a word (see --accept-worse).
    let validated = !data.validate.is_empty();
    let noise = ds0.noise_floor_um;
    for w in worse_than_start(&p0, &after, validated, 1.01, 0.02 * noise) {
        eprintln!("warning: the refit is worse than v{} {w}", l.cal.version);
    }
    let worse = worse_than_start(&p0, &after, validated, 1.03, 0.05 * noise);
    if !worse.is_empty() {
        let what = format!(
            "the refit (v{}) is worse than v{} it starts from, {}",
            new.version,
            l.cal.version,
            worse.join(", and ")
        );
        if !accept_worse {
            bail!(
                "lab fit: {what}: nothing written to {}. Keep v{}; pass --accept-worse to write \
                 the refit anyway",
                out.display(),
                l.cal.version
            );
        }
        eprintln!(
            "warning: {what}; written anyway (--accept-worse): keep v{} unless you know why",
            l.cal.version
        );
    }
    put(&out_file, new.to_json())?;
    commit_all([out_file])?;
    let s = serde_json::json!({
        "version": new.version,
        "nominal": axes,
        "rms_before_um": p0.rms_fit_um,
        "rms_after_um": after.rms_fit_um,
        "heldout_rms_before_um": p0.rms_held_um,
        "heldout_rms_after_um": after.rms_held_um,
        "params": fitted.as_ref().map(|o| o.by_effect()).unwrap_or_default(),
        "unidentifiable": fitted.as_ref().map(|o| o.unidentifiable.clone()).unwrap_or_default(),
        "judged_on": if data.validate.is_empty() { "fit data" } else { "fit data and held-out data (--validate)" },
        "worse_than_start": !worse.is_empty(),
    });
    if json {
        outln!("{}", serde_json::to_string_pretty(&s)?)?;
    } else {
        outln!("refit → {} (version {})", out.display(), new.version)?;
        for a in &axes {
            outln!(
                "  axis {}: τ {:.5} → {:.5} s, tracking RMS {:.2} → {:.2} µm",
                a.axis,
                a.tau_before_s,
                a.tau_after_s,
                a.rms_before_um,
                a.rms_after_um
            )?;
        }
        outln!(
            "  RMS fit {} → {} µm, held out {} → {} µm",
            um(p0.rms_fit_um),
            um(after.rms_fit_um),
            um(p0.rms_held_um),
            um(after.rms_held_um)
        )?;
        if let Some(o) = &fitted {
            for e in o.by_effect() {
                outln!("  {}", e.effect)?;
                print_params(&e.params, "    ", "every one in --json")?;
            }
            print_undetermined(o)?;
        }
    }
    Ok(())
}

/// Where the refit `after` is worse than its start `before`: on the fit data, and with
/// `validated` (held-out bags given) on the held-out data — an RMS above `factor` × before +
/// `plus_um`, or not finite. Each as "on the … data A → B µm RMS". `lab fit` warns above
/// 1.01 × + 0.02 × the noise floor (the tolerance the lab's significance test gives the
/// held-out data) and refuses above 1.03 × + 0.05 × the noise floor: a refit of an unchanged
/// model on its own data moves its fit RMS by up to about 2 % (the time constants are refitted
/// by their own criterion, the tracking error), which is warned of, not refused.
fn worse_than_start(
    before: &analysis::Prepared,
    after: &analysis::Prepared,
    validated: bool,
    factor: f64,
    plus_um: f64,
) -> Vec<String> {
    let worse = |b: f64, a: f64| !a.is_finite() || (b.is_finite() && a > factor * b + plus_um);
    let mut w = vec![];
    if worse(before.rms_fit_um, after.rms_fit_um) {
        w.push(format!(
            "on the fit data {} → {} µm RMS",
            um(before.rms_fit_um),
            um(after.rms_fit_um)
        ));
    }
    if validated && before.rms_held_um > 0.0 && worse(before.rms_held_um, after.rms_held_um) {
        w.push(format!(
            "on the held-out data (--validate) {} → {} µm RMS",
            um(before.rms_held_um),
            um(after.rms_held_um)
        ));
    }
    w
}
