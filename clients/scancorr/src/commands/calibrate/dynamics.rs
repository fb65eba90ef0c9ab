//! `scancorr calibrate dynamics`: the ring-gauge procedure — the nominal τ, P, the servo phase and
//! gain from rings at several speeds, P's diagonal and Z row and column from faces scanned
//! while the carriage oscillates (`sim --program dynamics-faces`) — its text and JSON output.

use super::procedure::{open, outcome_json, points_without, Opened};
use crate::shared::calib::{closing, commit_version, now_rfc3339};
use anyhow::Result;
use scancorr_core::calibrate::{dynamics, Param};
use scancorr_core::lab::analysis;
use scancorr_core::lab::dataset::{self};
use scancorr_core::lab::version;
use std::path::PathBuf;

/// A dynamic parameter in its engineering unit: (value, σ, unit).
fn dynamic_unit(p: &Param) -> (f64, f64, &'static str) {
    let n = p.name.as_str();
    let (k, u) = if n.ends_with("_s") {
        (1e3, "ms")
    } else if n.contains(".P_") {
        (1e6, "µm per m/s²")
    } else if n.contains(".b0.") {
        (1e6, "µrad")
    } else if n.contains(".b1.") {
        (1e6, "µrad/Hz")
    } else if n.contains(".b2.") {
        (1e6, "µrad/Hz²")
    } else if n.contains(".f1.") {
        (1e6, "ppm/Hz")
    } else if n.contains(".f2.") {
        (1e6, "ppm/Hz²")
    } else {
        (1.0, "")
    };
    (p.value * k, p.sigma * k, u)
}

/// The face scans accelerated in place: what moved, what was measured, before → after.
fn print_faces(faces: &[dynamics::FaceScan]) -> Result<()> {
    if faces.is_empty() {
        return Ok(());
    }
    outln!(
        "face scans accelerated in place (RMS along the normal after each place's static terms, before → after, µm):"
    )?;
    for f in faces {
        outln!(
            "  ({:>6.1} {:>6.1} {:>7.1})  measured along {}, moved along {}: {:.0} mm/s, {:.0} mm/s² peak  {:.3}→{:.3}",
            f.center_mm[0],
            f.center_mm[1],
            f.center_mm[2],
            f.measured_along,
            f.moved_along,
            f.speed_mm_s,
            f.peak_accel_mm_s2,
            f.dynamic_rms_um,
            f.dynamic_rms_after_um
        )?;
    }
    Ok(())
}

/// Runs the procedure.
pub(super) fn exec(
    bag: Vec<PathBuf>,
    calib: PathBuf,
    out: PathBuf,
    json: bool,
    report: Option<PathBuf>,
) -> Result<()> {
    let Opened {
        out_file,
        report_file,
        start,
        bags,
    } = open(&bag, &calib, &out, report.as_deref())?;
    crate::shared::output::stage("refitting the nominal model's time constants …");
    let raw: Vec<&dyn dataset::Samples> = bags.iter().map(|b| &*b.samples).collect();
    let (refit, axes) = scancorr_core::lab::nominal::fit_nominal(&raw, &start)?;
    // The dynamic effects are what this procedure measures: the points are taken without.
    crate::shared::output::stage("correcting the rings …");
    let ds = points_without(
        &bags,
        &refit,
        &["accel_deflection", "servo_phase", "servo_gain"],
        4,
    )?;
    let prep = analysis::prepare(&ds)?;
    crate::shared::output::stage("fitting …");
    let o = dynamics::run(&ds, &prep, &refit, &axes)?;
    let mut new = version::next(&start, o.calibration.effects.clone(), &now_rfc3339());
    new.nominal = o.calibration.nominal.clone();
    new.note = format!(
        "calibrate dynamics: {} ring positions; residual after the static patterns {:.3} → \
         {:.3} µm (noise floor {:.3} µm); gain form {}",
        o.positions.len(),
        o.residual_before_um,
        o.residual_after_um,
        ds.noise_floor_um,
        o.gain.chosen
    );
    commit_version(
        &mut new,
        vec![
            ("dynamics_residual_before_um", o.residual_before_um),
            ("dynamics_residual_after_um", o.residual_after_um),
            ("noise_floor_um", ds.noise_floor_um),
        ],
        out_file,
        report_file,
        || crate::report::dynamics(&start, &o, ds.noise_floor_um),
    )?;
    if json {
        let mut v = outcome_json(&o, &o.params, ds.noise_floor_um, &new, &start, &out)?;
        v["nominal"] = serde_json::to_value(&axes)?;
        outln!("{}", serde_json::to_string_pretty(&v)?)?;
        return Ok(());
    }
    outln!(
        "ring-gauge procedure: {} positions; residual after each position's static pattern {:.3} → {:.3} µm (noise floor {:.3} µm)",
        o.positions.len(),
        o.residual_before_um,
        o.residual_after_um,
        ds.noise_floor_um
    )?;
    outln!("ΔR per scan against each position's static pattern (before → after, µm):")?;
    for p in &o.positions {
        let scans: Vec<String> = p
            .scans
            .iter()
            .map(|s| {
                format!(
                    "{}{:.0} mm/s ({:.0} mm/s²) {:+.2}→{:+.2}",
                    if s.direction > 0 { "+" } else { "−" },
                    s.speed_mm_s,
                    s.accel_mm_s2,
                    s.delta_r_um,
                    s.delta_r_after_um
                )
            })
            .collect();
        outln!(
            "  ({:>6.1} {:>6.1} {:>7.1})  {}  ΔR/a along X {:+.2}, along Y {:+.2} µm per m/s²",
            p.center_mm[0],
            p.center_mm[1],
            p.center_mm[2],
            scans.join("  "),
            p.dr_x_per_accel_um_per_m_s2,
            p.dr_y_per_accel_um_per_m_s2
        )?;
    }
    print_faces(&o.faces)?;
    outln!(
        "servo gain: {} form (held-out rings: theoretical {:.3} µm, polynomial in f {:.3} µm)",
        o.gain.chosen,
        o.gain.heldout_theoretical_um,
        o.gain.heldout_polynomial_um
    )?;
    outln!("parameters (± standard uncertainty; P per monomial of the position over 500 mm):")?;
    for p in &o.params {
        let (v, s, u) = dynamic_unit(p);
        outln!("  {:<28} {:>11.4} ± {:.4} {u}", p.name, v, s)?;
    }
    for c in &o.confounded {
        outln!("  confounded: {c}")?;
    }
    for u in &o.undetermined {
        outln!("  not determined: {u}")?;
    }
    closing(&o.notes, &out, &new, &start)
}
