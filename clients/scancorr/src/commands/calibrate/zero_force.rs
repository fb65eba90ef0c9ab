//! `scancorr calibrate zero-force`: a part scanned by the same path at two or more probing
//! forces, each point extrapolated to zero force (`scancorr_core::calibrate::zero_force::part`)
//! — the part's own bending (a thin wall gives under the force), which the sphere's force
//! coefficients cannot know. The force is the probe's force signal where it reports one (a
//! force probe, wire v1.5), else its deflection. Writes the zero-force points; reports only
//! (no calibration).

use super::procedure::options;
use crate::shared::bags::load_bags;
use crate::shared::calib::load_calibration;
use crate::shared::output::{commit_all, outputs, put};
use anyhow::{anyhow, Result};
use scancorr_core::calibrate::zero_force;
use scancorr_core::lab::dataset;
use std::fmt::Write as _;
use std::path::PathBuf;

/// `calibrate zero-force` arguments.
#[derive(clap::Args)]
pub struct Args {
    /// Bags of the part (each feature scanned by the same path at ≥ 2 probing forces).
    #[arg(long, required = true)]
    bag: Vec<PathBuf>,
    /// The calibration the points are corrected with (its probe_force effect stays: what it
    /// leaves is the part's own).
    #[arg(long)]
    calib: PathBuf,
    /// Write the zero-force points (`x y z` rows, mm; `#` lines name each set).
    #[arg(long)]
    points_out: Option<PathBuf>,
    /// Print JSON (`sets`: per feature, tip and head angles what the force was taken from,
    /// the passes' forces (`forces_n`, N, or `forces_mm`, mm of deflection), the degree in the
    /// force, R1 − R0 at the lowest force and R0's σ, µm).
    #[arg(long)]
    json: bool,
    /// What the force is taken from: `signal` (the probe's force signal where every point
    /// of a set has one, else the deflection) or `deflection` (always |d|, as for a probe
    /// without preload).
    #[arg(long, value_enum, default_value_t = ForceFrom::Signal)]
    force_from: ForceFrom,
}

/// `--force-from`.
#[derive(Clone, Copy, clap::ValueEnum)]
enum ForceFrom {
    Signal,
    Deflection,
}

/// Summary of values (µm): mean, RMS about the mean, minimum, maximum.
fn stats(v: &[f64]) -> [f64; 4] {
    let n = v.len().max(1) as f64;
    let mean = v.iter().sum::<f64>() / n;
    let rms = (v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n).sqrt();
    let lo = v.iter().cloned().fold(f64::INFINITY, f64::min);
    let hi = v.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
    [mean, rms, lo, hi]
}

/// Runs the extrapolation.
pub fn run(a: Args) -> Result<()> {
    let mut inputs = vec![("--calib", a.calib.as_path())];
    inputs.extend(a.bag.iter().map(|b| ("--bag", b.as_path())));
    let [points_file] = outputs([("--points-out", a.points_out.as_deref())], &inputs)?;
    let cal = load_calibration(&a.calib)?;
    let bags = load_bags(&a.bag, &[], &cal.machine_id)?;
    let ds = dataset::build(&bags, &cal, &options(1))?;
    for w in &ds.warnings {
        eprintln!("warning: {w}");
    }
    let force = match a.force_from {
        ForceFrom::Signal => zero_force::Force::Signal,
        ForceFrom::Deflection => zero_force::Force::Deflection,
    };
    let sets = zero_force::part(&ds, force).map_err(|e| anyhow!("calibrate zero-force: {e}"))?;
    let mut text = String::new();
    let mut json_sets = vec![];
    for s in &sets {
        let r = &s.result;
        let e: Vec<f64> = r.points.iter().map(|p| p.error_at_f1_um).collect();
        let mut sig: Vec<f64> = r.points.iter().map(|p| p.sigma_um).collect();
        sig.sort_by(f64::total_cmp);
        let sigma = sig.get(sig.len() / 2).copied().unwrap_or(0.0);
        let [mean, rms, lo, hi] = stats(&e);
        writeln!(
            text,
            "# bag {} {} feature {} tip {} segments {:?}",
            s.bag + 1,
            s.artifact,
            s.feature_id,
            s.tip,
            s.segments
        )?;
        for p in &r.points {
            writeln!(text, "{:.6} {:.6} {:.6}", p.p0[0], p.p0[1], p.p0[2])?;
        }
        let mut v = serde_json::to_value(s)?;
        v["points"] = r.points.len().into();
        v["error_at_f1_um"] =
            serde_json::json!({"mean": mean, "rms_about_mean": rms, "min": lo, "max": hi});
        v["sigma_um"] = sigma.into();
        json_sets.push(v);
    }
    put(&points_file, &text)?;
    commit_all([points_file])?;
    if a.json {
        let v = serde_json::json!({
            "sets": json_sets,
            "noise_floor_um": ds.noise_floor_um,
            "points_out": a.points_out.as_ref().map(|p| p.display().to_string()),
        });
        outln!("{}", serde_json::to_string_pretty(&v)?)?;
        return Ok(());
    }
    outln!(
        "per-point extrapolation to zero force: {} set(s) of passes (noise floor {:.3} µm)",
        sets.len(),
        ds.noise_floor_um
    )?;
    for (s, v) in sets.iter().zip(&json_sets) {
        let r = &s.result;
        let f: Vec<String> = r
            .forces_mm
            .iter()
            .chain(&r.forces_n)
            .map(|f| format!("{f:.3}"))
            .collect();
        let e = &v["error_at_f1_um"];
        let g = |k: &str| e[k].as_f64().unwrap_or(0.0);
        let chi2 = r
            .chi2_linear
            .map(|c| format!(", reduced χ² of the lines {c:.2}"))
            .unwrap_or_default();
        outln!(
            "  {} feature {} tip {} (bag {}): passes at {} {}; {} points at zero force ({} unpaired), {} in the force{chi2}; R1 − R0 at the lowest force {:+.3} µm mean, {:.3} µm RMS about it ({:+.3} to {:+.3}); σ(R0) {:.3} µm",
            s.artifact,
            s.feature_id,
            s.tip,
            s.bag + 1,
            f.join(", "),
            r.force.unit(),
            r.points.len(),
            r.unpaired,
            if r.degree == 1 { "linear" } else { "quadratic" },
            g("mean"),
            g("rms_about_mean"),
            g("min"),
            g("max"),
            v["sigma_um"].as_f64().unwrap_or(0.0)
        )?;
    }
    if let Some(p) = &a.points_out {
        outln!("→ {} (x y z of each point at zero force)", p.display())?;
    }
    Ok(())
}
