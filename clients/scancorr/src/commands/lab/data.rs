//! What the lab's commands load: the bags and the starting calibration, and the dataset
//! of the bags corrected with a version.

use super::args::DataArgs;
use crate::shared::bags::{load_bags, SENSORS};
use crate::shared::calib;
use anyhow::Result;
use scancorr_core::lab::dataset::{self, BagData, BuildOptions, Dataset};
use scancorr_core::lab::program::parse_artifact;
use scancorr_core::Calibration;

/// The bags, the starting calibration and the options a lab command builds its datasets with.
pub(super) struct Loaded {
    pub(super) bags: Vec<BagData>,
    pub(super) cal: Calibration,
    pub(super) opts: BuildOptions,
}

/// The bags and the calibration of `--bag`, `--validate`, `--calib`.
pub(super) fn load(d: &DataArgs) -> Result<Loaded> {
    load_from(d, calib::load_calibration(&d.calib)?)
}

/// [`load`] with the calibration already read.
pub(super) fn load_from(d: &DataArgs, cal: Calibration) -> Result<Loaded> {
    crate::shared::output::stage(&format!(
        "reading {} bag(s) …",
        d.bag.len() + d.validate.len()
    ));
    let bags = load_bags(&d.bag, &d.validate, &cal.machine_id)?;
    let artifact = d
        .artifact
        .as_deref()
        .map(parse_artifact)
        .transpose()
        .map_err(|e| anyhow::anyhow!("--artifact: {e}"))?;
    let opts = BuildOptions {
        stride: d.stride.max(1),
        holdout_by_segment: true,
        artifact,
        sensors: SENSORS.iter().map(|s| s.to_string()).collect(),
    };
    Ok(Loaded { bags, cal, opts })
}

/// The bags corrected with `cal`: the lab's points (warnings to stderr).
pub(super) fn dataset_for(l: &Loaded, cal: &Calibration) -> Result<Dataset> {
    crate::shared::output::stage(&format!("correcting the scans with v{} …", cal.version));
    let ds = dataset::build(&l.bags, cal, &l.opts)?;
    crate::shared::output::stage(&format!("{} points; analysing …", ds.points.len()));
    for w in &ds.warnings {
        eprintln!("warning: {w}");
    }
    Ok(ds)
}

/// µm to three decimals.
pub(super) fn um(x: f64) -> String {
    format!("{x:.3}")
}
