//! `scancorr calibrate probe-force`: extrapolation to zero force — its text and JSON output.

use super::args::{helps, PrintArgs, VersionArgs};
use super::procedure::{open, outcome_json, points_without, Opened};
use crate::shared::calib::{closing, commit_version, now_rfc3339};
use anyhow::Result;
use scancorr_core::calibrate::probe_force;
use scancorr_core::lab::version;

/// Arguments of `calibrate probe-force`.
#[derive(clap::Args, Debug)]
#[command(mut_args(helps("probe-force")))]
pub struct Args {
    #[command(flatten)]
    io: VersionArgs,
    #[command(flatten)]
    print: PrintArgs,
    /// Only points at each scan's programmed speed (no dwell, spin-up or slow-down): every
    /// deflection is compared at the same kinematic state. For variants whose deflections are
    /// not scanned alike (c: a quarter beside a full turn; d: approaches; b: a wave).
    #[arg(long)]
    steady_only: bool,
    /// Take the structure's compliance under the carriage's acceleration as 0 ± this many µm
    /// per m/s² per axis (unless the start has `accel_deflection`), not fitted, with its effect
    /// added to the coefficients' σ: a wave of the deflection (b) accelerates the carriage in
    /// phase with it, so the scans cannot separate the two and a fitted compliance biases k.
    #[arg(long, value_name = "UM_PER_M_S2")]
    compliance_prior: Option<f64>,
}

/// Runs the procedure.
pub(super) fn exec(a: Args) -> Result<()> {
    let Opened {
        out_file,
        report_file,
        start,
        bags,
    } = open(&a.io.bag, &a.io.calib, &a.io.out, a.print.report.as_deref())?;
    // The force correction and the static maps are what this procedure measures: the points
    // are taken without (the new maps replace the start's of the same tip and segments).
    let ds = points_without(&bags, &start, &["probe_force", "feature_map"], 2)?;
    let mut opts = probe_force::Options {
        steady_only: a.steady_only,
        ..Default::default()
    };
    if let Some(c) = a.compliance_prior {
        if !(c.is_finite() && c > 0.0) {
            anyhow::bail!(
                "--compliance-prior {c}: the prior σ of the compliance must be a positive number \
                 of µm per m/s² (a bridge CMM's: 30)"
            );
        }
        opts.compliance_prior_s2 = Some(c * 1e-6);
    }
    let o = probe_force::run_with(&ds, &start, opts)?;
    let mut new = version::next(&start, o.calibration.effects.clone(), &now_rfc3339());
    new.geometry = o.calibration.geometry.clone();
    new.note = format!(
        "calibrate probe-force: {} settings; residual about each circle's static map {:.3} → \
         {:.3} µm (noise floor {:.3} µm)",
        o.settings.len(),
        o.rms_before_um,
        o.rms_after_um,
        ds.noise_floor_um
    );
    commit_version(
        &mut new,
        vec![
            ("probe_force_rms_before_um", o.rms_before_um),
            ("probe_force_rms_after_um", o.rms_after_um),
            ("noise_floor_um", ds.noise_floor_um),
        ],
        out_file,
        report_file,
        || crate::report::probe_force(&start, &o, ds.noise_floor_um),
    )?;
    if a.print.json {
        let v = outcome_json(&o, &o.params, ds.noise_floor_um, &new, &start, &a.io.out)?;
        outln!("{}", serde_json::to_string_pretty(&v)?)?;
        return Ok(());
    }
    outln!(
        "extrapolation to zero force: {} settings; residual about each circle's static map {:.3} → {:.3} µm (noise floor {:.3} µm)",
        o.settings.len(),
        o.rms_before_um,
        o.rms_after_um,
        ds.noise_floor_um
    )?;
    outln!(
        "consistency of the circles × deflections after the fit: reduced χ² {:.2}{}",
        o.cell_chi2,
        if o.cell_chi2 > 1.0 {
            " (the σ are scaled by it)"
        } else {
            ""
        }
    )?;
    outln!("sphere radius − certified per deflection (before → after the force correction, µm; without a sphere fit: along the probing direction from the zero-force surface):")?;
    for s in &o.settings {
        let lv: Vec<String> = s
            .deflections_mm
            .iter()
            .enumerate()
            .map(|(k, d)| {
                format!(
                    "{d:.2} mm {:+.2}→{:+.2}",
                    s.radius_error_before_um[k], s.radius_error_after_um[k]
                )
            })
            .collect();
        let zero = if s.sphere_fitted {
            format!(
                "at zero force {:+.3} ± {:.3}; static map's form {:.3} µm RMS",
                s.radius_error_at_zero_um[0], s.radius_error_at_zero_um[1], s.static_form_um
            )
        } else {
            "no sphere fit (too little of the sphere)".to_string()
        };
        outln!(
            "  tip {} at ({}, {})°: {}; {zero}; left after the fit {:.3} µm RMS",
            s.tip,
            s.head_deg[0],
            s.head_deg[1],
            lv.join("  "),
            s.fit_rms_um
        )?;
    }
    print_static_maps(&o)?;
    print_real_time(&o)?;
    outln!("parameters (± standard uncertainty):")?;
    for p in &o.params {
        // Each value in the unit its name states (`scancorr_core::units`); the force
        // coefficients (mm/mm) also as µm of bending per mm of deflection.
        if p.name.ends_with("_mm_per_mm") {
            outln!(
                "  {:<32} {:>9.6} ± {:.6} mm/mm ({:.3} ± {:.3} µm per mm of deflection)",
                p.name,
                p.value,
                p.sigma,
                p.value * 1e3,
                p.sigma * 1e3
            )?;
        } else if p.name.ends_with("_mm") {
            outln!(
                "  {:<32} {:>9.5} mm ± {:.3} µm (statistical)",
                p.name,
                p.value,
                p.sigma * 1e3
            )?;
        } else {
            let unit = scancorr_core::units::key_unit(&p.name).unwrap_or("(no unit)");
            outln!("  {:<32} {:>9.6} ± {:.6} {unit}", p.name, p.value, p.sigma)?;
        }
    }
    for u in &o.undetermined {
        outln!("  not determined: {u}")?;
    }
    closing(&o.notes, &a.io.out, &new, &start)
}

/// Prints the static error maps, if any.
fn print_static_maps(o: &probe_force::Outcome) -> Result<()> {
    if !o.static_maps.is_empty() {
        outln!("static error maps (zero-force radius − certified around each circle; stored as feature_map effects, apart from the geometry, applied at every speed to scans of that circle; --json: static_maps):")?;
        for m in &o.static_maps {
            let (lo, hi) = m
                .radial_um
                .iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
                    (a.min(*v), b.max(*v))
                });
            let u = m.radial_u_um.iter().cloned().fold(0.0, f64::max);
            outln!(
                "  tip {} latitude {:+.0}°: {:+.3} to {:+.3} µm over {} knots (σ ≤ {:.3} µm)",
                m.tip,
                m.latitude_deg,
                lo,
                hi,
                m.radial_um.len(),
                u
            )?;
        }
    }
    Ok(())
}

/// Prints the real-time form per segment, if any.
fn print_real_time(o: &probe_force::Outcome) -> Result<()> {
    if !o.real_time.is_empty() {
        outln!("real-time form, R0 = R1 − (R2 − R1)·F1/(F2 − F1) per wave of the deflection (the lower-force reading interpolated to the higher one's place), against the fit's zero-force values:")?;
        for rt in &o.real_time {
            outln!(
                "  tip {} segment {} (latitude {:+.0}°, {:.2}–{:.2} mm): {} waves, {} extrapolated, {} at a force below significance, {} alike, {} unpaired; R1 {:.3} µm RMS from the fit's zero force → R0 {:.3} µm RMS: systematic {:.3} µm (the fit's bending, which varies along the circle, through the same arithmetic), {:.3} µm beyond it against a statistical σ of {:.3} µm (halves side by side, half a wave apart: {:.3} µm, {:.3} µm predicted); radial acceleration {:+.1} mm/s² per mm of deflection",
                rt.tip,
                rt.segment,
                rt.latitude_deg,
                rt.deflection_mm[0],
                rt.deflection_mm[1],
                rt.waves,
                rt.extrapolated,
                rt.force_zero,
                rt.alike,
                rt.unpaired,
                rt.before_um,
                rt.rms_um,
                rt.systematic_um,
                rt.unexplained_um,
                rt.sigma_um,
                rt.side_by_side_um,
                rt.side_by_side_systematic_um,
                rt.accel_per_deflection_s2
            )?;
        }
    }
    Ok(())
}
