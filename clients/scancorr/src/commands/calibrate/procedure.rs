//! What every calibration procedure shares: its inputs and outputs opened together, the
//! points less what it measures, and its parameters as JSON and text.

use crate::shared::bags::{load_bags, SENSORS};
use crate::shared::calib::{self};
use crate::shared::output::outputs;
use crate::shared::output::AtomicOutput;
use anyhow::Result;
use scancorr_core::calib::Calibration;
use scancorr_core::calibrate::Param;
use scancorr_core::lab::dataset::BagData;
use scancorr_core::lab::dataset::{self, BuildOptions};
use std::path::Path;
use std::path::PathBuf;

/// A procedure's parameters and their σ as JSON objects by name.
pub(super) fn sigma_json(ps: &[Param]) -> (serde_json::Value, serde_json::Value) {
    let params: serde_json::Map<String, serde_json::Value> = ps
        .iter()
        .map(|p| (p.name.clone(), p.value.into()))
        .collect();
    let sigma: serde_json::Map<String, serde_json::Value> = ps
        .iter()
        .map(|p| (p.name.clone(), p.sigma.into()))
        .collect();
    (params.into(), sigma.into())
}

/// What every procedure opens: its outputs (checked against its inputs before anything is
/// read), the starting calibration and the bags.
pub(super) struct Opened {
    pub(super) out_file: Option<AtomicOutput>,
    pub(super) report_file: Option<AtomicOutput>,
    pub(super) start: Calibration,
    pub(super) bags: Vec<BagData>,
}

pub(super) fn open(
    bag: &[PathBuf],
    calib: &Path,
    out: &Path,
    report: Option<&Path>,
) -> Result<Opened> {
    let mut inputs = vec![("--calib", calib)];
    inputs.extend(bag.iter().map(|b| ("--bag", b.as_path())));
    let [out_file, report_file] = outputs([("--out", Some(out)), ("--report", report)], &inputs)?;
    let start = calib::load_calibration(calib)?;
    crate::shared::output::stage(&format!("reading {} bag(s) …", bag.len()));
    let bags = load_bags(bag, &[], &start.machine_id)?;
    crate::shared::output::stage("bags read; measuring …");
    Ok(Opened {
        out_file,
        report_file,
        start,
        bags,
    })
}

/// The points of `bags` corrected with `cal` less the effects of `kinds` (what the procedure
/// measures), every `stride`-th point; warnings to stderr.
pub(super) fn points_without(
    bags: &[BagData],
    cal: &Calibration,
    kinds: &[&str],
    stride: usize,
) -> Result<dataset::Dataset> {
    let mut bare = cal.clone();
    bare.effects.retain(|e| !kinds.contains(&e.kind()));
    crate::shared::output::stage("correcting the scans …");
    let ds = dataset::build(bags, &bare, &options(stride))?;
    crate::shared::output::stage(&format!("{} points; fitting …", ds.points.len()));
    for w in &ds.warnings {
        eprintln!("warning: {w}");
    }
    Ok(ds)
}

/// The dataset options of a procedure: every `stride`-th point, no held-out split.
pub(super) fn options(stride: usize) -> BuildOptions {
    BuildOptions {
        stride,
        holdout_by_segment: false,
        artifact: None,
        sensors: SENSORS.iter().map(|s| s.to_string()).collect(),
    }
}

/// `--json` of a procedure: its outcome with `params` and `uncertainty` by the truth file's
/// names, and the new version's place.
pub(super) fn outcome_json(
    o: &impl serde::Serialize,
    ps: &[Param],
    noise_floor_um: f64,
    new: &Calibration,
    start: &Calibration,
    out: &Path,
) -> Result<serde_json::Value> {
    let (params, sigma) = sigma_json(ps);
    let mut v = serde_json::to_value(o)?;
    v["params"] = params;
    v["uncertainty"] = sigma;
    v["noise_floor_um"] = noise_floor_um.into();
    v["version"] = new.version.into();
    v["parent_version"] = start.version.into();
    v["out"] = out.display().to_string().into();
    Ok(v)
}

/// `ps` under the names `key` gives them (a JSON key that states its unit).
pub(super) fn renamed(ps: &[Param], key: impl Fn(&str) -> String) -> Vec<Param> {
    ps.iter()
        .map(|p| Param {
            name: key(&p.name),
            ..p.clone()
        })
        .collect()
}

/// A parameter ± its σ, one line of a procedure's text output.
pub(super) fn print_param(p: &Param) -> String {
    let (scale, unit) = if p.name.ends_with("_mm") {
        (1.0, "mm")
    } else if p.name.ends_with("_per_k") {
        (1e6, "ppm/K")
    } else {
        (1.0, "")
    };
    let digits = if unit == "mm" { 5 } else { 3 };
    format!(
        "  {:<20} {:>12.digits$} ± {:.digits$} {unit}",
        p.name,
        p.value * scale,
        p.sigma * scale
    )
}
