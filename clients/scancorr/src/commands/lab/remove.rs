//! `scancorr lab remove`: an effect taken out of the model, the rest refitted, a new version.

use super::args::LabCmd;
use super::data::{dataset_for, load, um};
use crate::shared::calib::now_rfc3339;
use crate::shared::output::commit_all;
use crate::shared::output::{outputs, put};
use anyhow::{bail, Context, Result};
use scancorr_core::lab::analysis::{self};
use scancorr_core::lab::version;

/// Runs `scancorr lab remove`.
pub(super) fn exec(cmd: LabCmd) -> Result<()> {
    let LabCmd::Remove {
        effect,
        data,
        out,
        json,
    } = cmd
    else {
        unreachable!("lab remove")
    };
    let [out_file] = outputs([("--out", Some(out.as_path()))], &data.inputs())?;
    let l = load(&data)?;
    if !l.cal.effects.iter().any(|e| e.id() == effect) {
        bail!(
            "the model has no effect `{effect}` (it has: {})",
            l.cal
                .effects
                .iter()
                .map(|e| e.id())
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
    let ds = dataset_for(&l, &l.cal)?;
    let prep = analysis::prepare(&ds)?;
    let applied = analysis::apply(
        &ds,
        vec![analysis::Candidate {
            action: analysis::Move::Drop,
            effect: effect.clone(),
            replaces: Some(effect.clone()),
            config: None,
        }],
        false,
    )?;
    let mut new = version::next(&l.cal, applied.effects, &now_rfc3339());
    let ds_after = dataset_for(&l, &new)?;
    let after = analysis::prepare(&ds_after)?;
    version::describe(
        &mut new,
        &format!("lab remove {effect}"),
        ds.noise_floor_um,
        &prep,
        &after,
    );
    new.build().context("the refitted calibration")?;
    put(&out_file, new.to_json())?;
    commit_all([out_file])?;
    let summary = serde_json::json!({
        "removed": effect,
        "version": new.version,
        "parent_version": l.cal.version,
        "rms_before_um": prep.rms_fit_um,
        "rms_after_um": after.rms_fit_um,
        "heldout_rms_before_um": prep.rms_held_um,
        "heldout_rms_after_um": after.rms_held_um,
        "noise_floor_um": ds.noise_floor_um,
        "out": out,
    });
    if json {
        outln!("{}", serde_json::to_string_pretty(&summary)?)?;
    } else {
        outln!(
            "removed {effect} → {} (version {}, parent {})",
            out.display(),
            new.version,
            l.cal.version
        )?;
        outln!(
            "  RMS on fit data   {:>8} → {:>8} µm",
            um(prep.rms_fit_um),
            um(after.rms_fit_um)
        )?;
        outln!(
            "  RMS held out      {:>8} → {:>8} µm   (noise floor {} µm)",
            um(prep.rms_held_um),
            um(after.rms_held_um),
            um(ds.noise_floor_um)
        )?;
    }
    Ok(())
}
