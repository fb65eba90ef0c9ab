//! `scancorr calibrate scales`: the scales' expansion from a ball bar read at several
//! temperatures — its text and JSON output.

use super::args::{helps, VersionArgs};
use super::procedure::{open, outcome_json, points_without, print_param, Opened};
use crate::shared::calib::{closing, commit_version, now_rfc3339};
use anyhow::Result;
use scancorr_core::calibrate::scales;
use scancorr_core::lab::version;

/// Arguments of `calibrate scales`.
#[derive(clap::Args, Debug)]
#[command(mut_args(helps("scales")))]
pub struct Args {
    #[command(flatten)]
    io: VersionArgs,
    /// Print JSON (`params` and `uncertainty` by the simulator's truth names, `readings`).
    #[arg(long)]
    json: bool,
}

/// Runs the procedure.
pub(super) fn exec(a: Args) -> Result<()> {
    let Opened {
        out_file,
        report_file,
        start,
        bags,
    } = open(&a.io.bag, &a.io.calib, &a.io.out, None)?;
    // The scales' expansion is what this procedure measures: the points are taken without it.
    let ds = points_without(&bags, &start, &["scale_thermal"], 1)?;
    let o = scales::run(&ds, &start)?;
    let mut new = version::next(&start, o.calibration.effects.clone(), &now_rfc3339());
    new.note = format!(
        "calibrate scales ({} bar(s)): length error {:.3} → {:.3} µm RMS over the readings",
        o.bars.len(),
        o.rms_before_um,
        o.rms_after_um
    );
    commit_version(
        &mut new,
        vec![
            ("scale_length_error_before_um", o.rms_before_um),
            ("scale_length_error_after_um", o.rms_after_um),
            ("noise_floor_um", ds.noise_floor_um),
        ],
        out_file,
        report_file,
        String::new,
    )?;
    if a.json {
        let v = outcome_json(&o, &o.params, ds.noise_floor_um, &new, &start, &a.io.out)?;
        outln!("{}", serde_json::to_string_pretty(&v)?)?;
        return Ok(());
    }
    outln!(
        "scales' expansion from {} ball bar(s): length error {:.3} µm RMS with the start's scale \
         correction left out, {:.3} µm after the fit (noise floor {:.3} µm)",
        o.bars.len(),
        o.rms_before_um,
        o.rms_after_um,
        ds.noise_floor_um
    )?;
    for b in &o.bars {
        outln!(
            "  {} bar {:.1} mm: {} readings over {:.2} K of its scale's temperature",
            b.axis,
            b.length_mm,
            b.readings,
            b.temp_span_k
        )?;
    }
    outln!("  reading  scale °C   length − certified (µm)   left (µm)")?;
    for r in &o.readings {
        outln!(
            "  {}        {:>7.3}   {:>+9.3} ± {:.3}           {:>+7.3}",
            r.axis,
            r.temp_c,
            r.error_um,
            r.sigma_um,
            r.residual_um
        )?;
    }
    outln!("parameters (± standard uncertainty):")?;
    for p in &o.params {
        outln!("{}", print_param(p))?;
    }
    for u in &o.undetermined {
        outln!("  not determined: {u}")?;
    }
    closing(&o.notes, &a.io.out, &new, &start)
}
