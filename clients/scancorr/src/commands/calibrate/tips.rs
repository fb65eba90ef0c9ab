//! `scancorr calibrate tips`: master-sphere qualification — its text and JSON output.

use super::args::{helps, PrintArgs, VersionArgs};
use super::procedure::{open, options, outcome_json, points_without, print_param, Opened};
use crate::shared::calib::{commit_version, now_rfc3339};
use anyhow::Result;
use scancorr_core::calibrate::tips;
use scancorr_core::lab::dataset::{self};
use scancorr_core::lab::version;

/// Arguments of `calibrate tips`.
#[derive(clap::Args, Debug)]
#[command(mut_args(helps("tips")))]
pub struct Args {
    #[command(flatten)]
    io: VersionArgs,
    /// The reference tip (default: the lowest tip id measured at head angles 0, 0).
    #[arg(long)]
    reference_tip: Option<u32>,
    #[command(flatten)]
    print: PrintArgs,
}

/// Runs the procedure.
pub(super) fn exec(a: Args) -> Result<()> {
    let Opened {
        out_file,
        report_file,
        start,
        bags,
    } = open(&a.io.bag, &a.io.calib, &a.io.out, a.print.report.as_deref())?;
    // The stylus thermal correction is what this procedure measures: the points are
    // taken without it.
    let ds = points_without(&bags, &start, &["stylus_thermal"], 1)?;
    let outcome = tips::run(&ds, &start, a.reference_tip)?;
    let mut new = version::next(&start, outcome.calibration.effects.clone(), &now_rfc3339());
    new.geometry = outcome.calibration.geometry.clone();
    // The same bags corrected with the new version: what the qualification leaves.
    let after = tips::run(
        &dataset::build(&bags, &new, &options(1))?,
        &new,
        Some(outcome.reference_tip),
    )
    .ok()
    .filter(|o| !o.reference_alone)
    .map(|o| o.consistency_before_um);
    new.note = if outcome.reference_alone {
        format!(
            "calibrate tips (reference tip {} alone): its effective radius re-qualified",
            outcome.reference_tip
        )
    } else {
        format!(
            "calibrate tips (reference tip {}): tip-to-tip consistency {:.3} µm → {} on the \
             qualification",
            outcome.reference_tip,
            outcome.consistency_before_um,
            after.map_or("—".into(), |a| format!("{a:.3} µm"))
        )
    };
    commit_version(
        &mut new,
        [
            ("tip_consistency_before_um", outcome.consistency_before_um),
            ("tip_fit_residual_um", outcome.residual_rms_um),
        ]
        .into_iter()
        .filter(|_| !outcome.reference_alone)
        .chain([("noise_floor_um", ds.noise_floor_um)])
        .chain(after.map(|a| ("tip_consistency_after_um", a)))
        .collect(),
        out_file,
        report_file,
        || crate::report::tips(&start, &outcome, after, ds.noise_floor_um),
    )?;
    if a.print.json {
        let mut v = outcome_json(
            &outcome,
            &outcome.params,
            ds.noise_floor_um,
            &new,
            &start,
            &a.io.out,
        )?;
        v["consistency_after_um"] = after.into();
        if outcome.reference_alone {
            v["consistency_before_um"] = serde_json::Value::Null;
            v["residual_rms_um"] = serde_json::Value::Null;
        }
        outln!("{}", serde_json::to_string_pretty(&v)?)?;
    } else {
        outln!(
            "qualified {} settings on the master sphere (reference tip {}{})",
            outcome.settings.len(),
            outcome.reference_tip,
            outcome.reference_temp_c.map_or(String::new(), |t| format!(
                ", at {t:.2} °C, range {:.2} K",
                outcome.temp_range_k
            ))
        )?;
        outln!("  setting            offset from the reference (µm)      left (µm)")?;
        for s in &outcome.settings {
            if s.tip == outcome.reference_tip {
                continue;
            }
            outln!(
                        "  tip {} A1 {:>5.1}° A2 {:>5.1}°  ({:>8.3} {:>8.3} {:>8.3})  ({:>6.3} {:>6.3} {:>6.3})",
                        s.tip, s.head_deg[0], s.head_deg[1], s.offset_um[0], s.offset_um[1],
                        s.offset_um[2], s.residual_um[0], s.residual_um[1], s.residual_um[2]
                    )?;
        }
        outln!("parameters (± standard uncertainty):")?;
        for p in &outcome.params {
            outln!("{}", print_param(p))?;
        }
        if !outcome.rotation.is_empty() {
            outln!(
                "  offsets rotated at the sphere's position (µrad, the machine's angular errors there or the head's): {}",
                outcome
                    .rotation
                    .iter()
                    .map(|p| format!("{:.1} ± {:.1}", p.value * 1e6, p.sigma * 1e6))
                    .collect::<Vec<_>>()
                    .join(", ")
            )?;
        }
        for u in &outcome.undetermined {
            outln!("  not determined: {u}")?;
        }
        for n in &outcome.notes {
            outln!("  note: {n}")?;
        }
        if !outcome.reference_alone {
            outln!(
                "tip-to-tip consistency: {:.3} µm with the starting calibration, {} with the new one (noise floor {:.3} µm); fit residual {:.3} µm",
                outcome.consistency_before_um,
                after.map_or("—".into(), |a| format!("{a:.3} µm")),
                ds.noise_floor_um,
                outcome.residual_rms_um
            )?;
        }
        outln!(
            "→ {} (version {}, parent {})",
            a.io.out.display(),
            new.version,
            start.version
        )?;
    }
    Ok(())
}
