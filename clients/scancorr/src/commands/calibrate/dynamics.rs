//! `scancorr calibrate dynamics`: the ring-gauge procedure — the nominal τ, P, the servo phase and
//! gain from rings at several speeds, P's diagonal and Z row and column from faces scanned
//! while the carriage oscillates (`sim --program dynamics-faces`) — its text and JSON output.

use super::args::{helps, PrintArgs, VersionArgs};
use super::procedure::{open, outcome_json, points_without, renamed, sigma_json, Opened};
use crate::shared::calib::{closing, commit_version, now_rfc3339};
use anyhow::Result;
use scancorr_core::calibrate::{dynamics, Param};
use scancorr_core::lab::analysis;
use scancorr_core::lab::dataset::{self};
use scancorr_core::lab::version;

/// Arguments of `calibrate dynamics`.
#[derive(clap::Args, Debug)]
#[command(mut_args(helps("dynamics")))]
pub struct Args {
    #[command(flatten)]
    io: VersionArgs,
    #[command(flatten)]
    print: PrintArgs,
}

/// A dynamic parameter's unit, by what its name holds (`.P_`): the JSON key's suffix (the value
/// as fitted, in that unit, as `scancorr_core::units` reads it), and the engineering unit the
/// text states, with its factor.
struct Unit {
    holds: &'static str,
    key: &'static str,
    factor: f64,
    text: &'static str,
}

/// τ's name ends with its unit already (`dynamics.tau_x_s`); P, the phase and the gain name
/// theirs only in JSON (`dynamics.P_xy.1_mm_per_mm_s2`).
const UNITS: &[Unit] = &[
    unit(".tau_", "_s", 1e3, "ms"),
    unit(".P_", "_mm_per_mm_s2", 1e6, "µm per m/s²"),
    unit(".b0.", "_rad", 1e6, "µrad"),
    unit(".b1.", "_rad_per_hz", 1e6, "µrad/Hz"),
    unit(".b2.", "_rad_per_hz2", 1e6, "µrad/Hz²"),
    unit(".f1.", "_per_hz", 1e6, "ppm/Hz"),
    unit(".f2.", "_per_hz2", 1e6, "ppm/Hz²"),
];

/// A row of [`UNITS`].
const fn unit(holds: &'static str, key: &'static str, factor: f64, text: &'static str) -> Unit {
    Unit {
        holds,
        key,
        factor,
        text,
    }
}

/// A dynamic parameter's name without its unit (`dynamics.P_xy.1`, `dynamics.tau_x`) and its
/// unit.
fn unit_of(name: &str) -> Option<(&str, &'static Unit)> {
    let u = UNITS.iter().find(|u| name.contains(u.holds))?;
    Some((name.strip_suffix(u.key).unwrap_or(name), u))
}

/// The JSON key of a dynamic parameter: its name with its unit (`dynamics.P_xy.1_mm_per_mm_s2`,
/// `dynamics.phase_y.b1.1_rad_per_hz`), as the simulator's truth file names it.
fn json_key(name: &str) -> String {
    match unit_of(name) {
        Some((stem, u)) => format!("{stem}{}", u.key),
        None => name.to_string(),
    }
}

/// A dynamic parameter in its engineering unit: (name without its unit, value, σ, unit).
fn dynamic_unit(p: &Param) -> (&str, f64, f64, &'static str) {
    match unit_of(&p.name) {
        Some((stem, u)) => (stem, p.value * u.factor, p.sigma * u.factor, u.text),
        None => (p.name.as_str(), p.value, p.sigma, ""),
    }
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

/// ΔR per scan along X and Y (the patent's maxima) with σ, before → after the mean, and ΔR/a
/// per position.
fn print_delta_r(positions: &[dynamics::Position]) -> Result<()> {
    outln!(
        "ΔR per scan against each position's static pattern, along X / along Y ± σ (mean before → after), µm:"
    )?;
    for p in positions {
        let scans: Vec<String> = p
            .scans
            .iter()
            .map(|s| {
                format!(
                    "{}{:.0} mm/s ({:.0} mm/s²) {:+.2}/{:+.2} ±{:.2} ({:+.2}→{:+.2})",
                    if s.direction > 0 { "+" } else { "−" },
                    s.speed_mm_s,
                    s.accel_mm_s2,
                    s.delta_r_x_um,
                    s.delta_r_y_um,
                    s.delta_r_x_sigma_um.max(s.delta_r_y_sigma_um),
                    s.delta_r_um,
                    s.delta_r_after_um
                )
            })
            .collect();
        outln!(
            "  ({:>6.1} {:>6.1} {:>7.1})  {}  ΔR/a along X {:+.2} ± {:.2}, along Y {:+.2} ± {:.2} µm per m/s²",
            p.center_mm[0],
            p.center_mm[1],
            p.center_mm[2],
            scans.join("  "),
            p.dr_x_per_accel_um_per_m_s2,
            p.dr_x_per_accel_sigma_um_per_m_s2,
            p.dr_y_per_accel_um_per_m_s2,
            p.dr_y_per_accel_sigma_um_per_m_s2
        )?;
    }
    Ok(())
}

/// Runs the procedure.
pub(super) fn exec(a: Args) -> Result<()> {
    let (out, json) = (a.io.out, a.print.json);
    let Opened {
        out_file,
        report_file,
        start,
        bags,
    } = open(&a.io.bag, &a.io.calib, &out, a.print.report.as_deref())?;
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
    // The static phase φ0 by the patent's name (it is servo_phase's b0 of the constant term).
    let phi0: Vec<(String, f64)> = o
        .phase0
        .iter()
        .flat_map(|p| {
            let k = p.name.replace('.', "_");
            [
                (format!("{k}_rad"), p.value),
                (format!("{k}_rad_sigma"), p.sigma),
            ]
        })
        .collect();
    let mut metrics = vec![
        ("dynamics_residual_before_um", o.residual_before_um),
        ("dynamics_residual_after_um", o.residual_after_um),
        ("noise_floor_um", ds.noise_floor_um),
    ];
    metrics.extend(phi0.iter().map(|(k, v)| (k.as_str(), *v)));
    commit_version(&mut new, metrics, out_file, report_file, || {
        crate::report::dynamics(&start, &o, ds.noise_floor_um)
    })?;
    if json {
        // Each key states its unit (the table of `scancorr_core::units`).
        let named = renamed(&o.params, json_key);
        let mut v = outcome_json(&o, &named, ds.noise_floor_um, &new, &start, &out)?;
        v["nominal"] = serde_json::to_value(&axes)?;
        let (p2, s2) = sigma_json(&renamed(&o.quadratic.params, json_key));
        v["quadratic"]["params"] = p2;
        v["quadratic"]["uncertainty"] = s2;
        let (p0, s0) = sigma_json(&renamed(&o.phase0, |n| format!("{n}_rad")));
        v["phase0"] = serde_json::json!({ "params": p0, "uncertainty": s0 });
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
    print_delta_r(&o.positions)?;
    print_faces(&o.faces)?;
    outln!(
        "servo gain: {} form (held-out rings: theoretical {:.3} µm, polynomial in f {:.3} µm)",
        o.gain.chosen,
        o.gain.heldout_theoretical_um,
        o.gain.heldout_polynomial_um
    )?;
    outln!("parameters (± standard uncertainty; P per monomial of the position over 500 mm):")?;
    for p in &o.params {
        let (name, v, s, u) = dynamic_unit(p);
        outln!("  {:<28} {:>11.4} ± {:.4} {u}", name, v, s)?;
    }
    for p in &o.phase0 {
        outln!(
            "  static phase {:<15} {:>11.4} ± {:.4} µrad (the phase's f⁰ term, stored as servo_phase b0)",
            p.name.trim_start_matches("dynamics."),
            p.value * 1e6,
            p.sigma * 1e6
        )?;
    }
    outln!(
        "  P quadratic in X: {} — {}",
        o.quadratic.decision,
        o.quadratic.reason
    )?;
    for c in &o.confounded {
        outln!("  confounded: {c}")?;
    }
    for u in &o.undetermined {
        outln!("  not determined: {u}")?;
    }
    closing(&o.notes, &out, &new, &start)
}
