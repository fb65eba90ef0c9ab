//! `scancorr calibrate dynamic-map`: the S1/F1/F2 joint method — its text and JSON output.

use super::procedure::{open, outcome_json, points_without, Opened};
use crate::shared::calib::{closing, commit_version, now_rfc3339};
use anyhow::Result;
use scancorr_core::calibrate::dynamic_map;
use scancorr_core::lab::version;
use std::path::PathBuf;

/// Runs the procedure.
pub(super) fn exec(
    bag: Vec<PathBuf>,
    calib: PathBuf,
    out: PathBuf,
    bins: usize,
    tolerance_um: Option<f64>,
    json: bool,
    report: Option<PathBuf>,
) -> Result<()> {
    let Opened {
        out_file,
        report_file,
        start,
        bags,
    } = open(&bag, &calib, &out, report.as_deref())?;
    // The maps are what this procedure measures: the points are taken without them (every
    // point: a fast scan has a few dozen per bin).
    let ds = points_without(&bags, &start, &["feature_map"], 1)?;
    let o = dynamic_map::run(
        &ds,
        &start,
        &dynamic_map::Options {
            bins,
            tolerance_mm: tolerance_um.map(|t| t * 1e-3),
            ..Default::default()
        },
    )?;
    let mut new = version::next(&start, o.calibration.effects.clone(), &now_rfc3339());
    let e2 = o.maps.iter().map(|m| m.e2_rms_um).fold(0.0, f64::max);
    new.note = format!(
        "calibrate dynamic-map: {} map(s) ({}); e2 up to {e2:.3} µm RMS (noise floor {:.3} µm)",
        o.maps.len(),
        o.maps
            .iter()
            .map(|m| format!("{} at {:.0} mm/s", m.id, m.speed_mm_s))
            .collect::<Vec<_>>()
            .join(", "),
        ds.noise_floor_um
    );
    commit_version(
        &mut new,
        vec![
            ("dynamic_map_e2_rms_um", e2),
            ("noise_floor_um", ds.noise_floor_um),
        ],
        out_file,
        report_file,
        || crate::report::dynamic_map(&start, &o, ds.noise_floor_um),
    )?;
    if json {
        let v = outcome_json(&o, &o.params, ds.noise_floor_um, &new, &start, &out)?;
        outln!("{}", serde_json::to_string_pretty(&v)?)?;
        return Ok(());
    }
    outln!(
        "S1/F1/F2 joint method: {} map(s) (noise floor {:.3} µm)",
        o.maps.len(),
        ds.noise_floor_um
    )?;
    for m in &o.maps {
        outln!("  {} — {}", m.id, m.feature)?;
        for s in &m.scans {
            outln!(
                "    {} segment {:>4}: {:>5.1} mm/s at {:.3} mm, {} points, mean radial {:+.3} µm",
                s.role,
                s.segment,
                s.speed_mm_s,
                s.deflection_mm,
                s.points,
                s.mean_radial_um
            )?;
        }
        outln!(
            "    e2 (fast scan's error at d1) {:.3} µm RMS (σ per bin {:.3} µm RMS); dynamic part at zero deflection {:.3} µm RMS; e1 (deflection at speed) {:.3} µm RMS; {} bins; applies to segments {:?}, tip {}, {:.0} mm/s",
            m.e2_rms_um,
            m.e2_u_rms_um,
            m.dynamic_rms_um,
            m.e1_rms_um,
            m.theta_deg.len(),
            m.segments,
            m.tip,
            m.speed_mm_s
        )?;
    }
    outln!("parameters (± standard uncertainty):")?;
    for p in &o.params {
        outln!(
            "  {:<44} {:>9.3} ± {:.3} µm{}",
            p.name,
            p.value * 1e3,
            p.sigma * 1e3,
            if p.name.ends_with("_per_mm") {
                " per mm of deflection"
            } else {
                ""
            }
        )?;
    }
    for s in &o.speed_search {
        outln!(
            "  speed search, {} (tolerance {:.3} µm): {}; no map needed up to {}",
            s.feature,
            s.tolerance_um,
            s.steps
                .iter()
                .map(|x| format!(
                    "{:.0} mm/s {:.3} ± {:.3} µm{}",
                    x.speed_mm_s,
                    x.difference_um,
                    x.difference_u_um,
                    if x.within { "" } else { " (mapped)" }
                ))
                .collect::<Vec<_>>()
                .join(", "),
            s.fastest_within_mm_s
                .map_or("no speed measured".into(), |v| format!("{v:.0} mm/s"))
        )?;
    }
    for s in &o.skipped {
        outln!("  not mapped: {s}")?;
    }
    closing(&o.notes, &out, &new, &start)
}
