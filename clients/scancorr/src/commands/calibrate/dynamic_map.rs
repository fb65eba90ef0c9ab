//! `scancorr calibrate dynamic-map`: the S1/F1/F2 joint method — its text and JSON output.

use super::args::{helps, PrintArgs, VersionArgs};
use super::procedure::{open, outcome_json, points_without, renamed, Opened};
use crate::shared::calib::{closing, commit_version, now_rfc3339};
use anyhow::Result;
use scancorr_core::calibrate::dynamic_map;
use scancorr_core::lab::version;

/// Arguments of `calibrate dynamic-map`.
#[derive(clap::Args, Debug)]
#[command(mut_args(helps("dynamic-map")))]
pub struct Args {
    #[command(flatten)]
    io: VersionArgs,
    /// Angle bins (the map's knots) around the circle.
    #[arg(long, default_value_t = 72)]
    bins: usize,
    /// Speed search: the slow/fast difference (RMS over the bins of F2 − S1, µm) a speed
    /// may show without a map; speeds are taken rising, maps stored only where it is left.
    #[arg(long)]
    tolerance_um: Option<f64>,
    #[command(flatten)]
    print: PrintArgs,
}

/// A map's parameter: its name without its unit (`m1.radius_change`), the unit of its JSON key
/// (`_mm`, or `_mm_per_mm` for the error per mm of deflection, which the core names
/// `…_per_mm`), the text's factor and unit.
fn unit_of(name: &str) -> (&str, &'static str, f64, &'static str) {
    match name.strip_suffix("_per_mm") {
        Some(stem) => (stem, "_mm_per_mm", 1e3, "µm per mm of deflection"),
        None => (name.strip_suffix("_mm").unwrap_or(name), "_mm", 1e3, "µm"),
    }
}

/// Runs the procedure.
pub(super) fn exec(a: Args) -> Result<()> {
    let (out, json, bins, tolerance_um) = (a.io.out, a.print.json, a.bins, a.tolerance_um);
    let Opened {
        out_file,
        report_file,
        start,
        bags,
    } = open(&a.io.bag, &a.io.calib, &out, a.print.report.as_deref())?;
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
        // Each key states its unit (the table of `scancorr_core::units`).
        let named = renamed(&o.params, |n| {
            let (stem, key, _, _) = unit_of(n);
            format!("{stem}{key}")
        });
        let mut v = outcome_json(&o, &named, ds.noise_floor_um, &new, &start, &out)?;
        // A scan's segment is an id: `segment_id`, as the table names ids.
        for m in v["maps"].as_array_mut().into_iter().flatten() {
            for s in m["scans"].as_array_mut().into_iter().flatten() {
                if let Some(id) = s.as_object_mut().and_then(|o| o.remove("segment")) {
                    s["segment_id"] = id;
                }
            }
        }
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
            "    e2 (fast scan's error at d1) {:.3} µm RMS (σ per bin {:.3} µm RMS: the points' scatter {:.3}, the scales' expansion {:.3}); dynamic part at zero deflection {:.3} µm RMS; e1 (deflection at speed) {:.3} µm RMS; {} bins; applies to segments {:?}, tip {}, {:.0} mm/s",
            m.e2_rms_um,
            m.e2_u_rms_um,
            m.e2_u_noise_rms_um,
            m.e2_u_scales_rms_um,
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
        let (stem, _, k, unit) = unit_of(&p.name);
        outln!(
            "  {:<44} {:>9.3} ± {:.3} {unit}",
            stem,
            p.value * k,
            p.sigma * k
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
