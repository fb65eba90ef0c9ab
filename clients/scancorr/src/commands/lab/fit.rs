//! `scancorr lab fit`: an unchanged model refitted, a new version.

use super::args::LabCmd;
use super::data::{dataset_for, load, um};
use crate::shared::calib::now_rfc3339;
use crate::shared::output::commit_all;
use crate::shared::output::{outputs, put};
use anyhow::Result;
use scancorr_core::lab::analysis::{self};
use scancorr_core::lab::dataset::{self};
use scancorr_core::lab::version;

/// Runs `scancorr lab fit`.
pub(super) fn exec(cmd: LabCmd) -> Result<()> {
    let LabCmd::Fit { data, out, json } = cmd else {
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
    let mut unident = vec![];
    if !new.effects.is_empty() {
        let o = analysis::fit_effects(&ds, &prep, &new.effects)?;
        new.effects = o.configs;
        unident = o.unidentifiable;
    }
    // `new` is the start with its nominal model and effects refitted: its child.
    let mut new = version::next(&new, new.effects.clone(), &now_rfc3339());
    let ds_after = dataset_for(&l, &new)?;
    let after = analysis::prepare(&ds_after)?;
    version::describe(&mut new, "lab fit", ds.noise_floor_um, &p0, &after);
    put(&out_file, new.to_json())?;
    commit_all([out_file])?;
    let s = serde_json::json!({
        "version": new.version,
        "nominal": axes,
        "rms_before_um": p0.rms_fit_um,
        "rms_after_um": after.rms_fit_um,
        "heldout_rms_before_um": p0.rms_held_um,
        "heldout_rms_after_um": after.rms_held_um,
        "unidentifiable": unident,
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
    }
    Ok(())
}
