//! Calibration versions as every command reads and writes them: loading a calibration file,
//! the time stamp of a new version, committing a version (and its report) together, and the
//! closing lines a procedure prints.

use crate::shared::output::{commit_all, put, AtomicOutput};
use anyhow::{Context, Result};
use scancorr_core::Calibration;
use std::path::Path;

/// The time stamp of a new version (and of a report): now, RFC 3339 UTC.
pub(crate) use crate::shared::provenance::now_rfc3339;

/// Loads and validates a calibration file.
pub fn load_calibration(path: &Path) -> Result<Calibration> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("reading calibration {}", path.display()))?;
    let cal =
        Calibration::from_json(&text).with_context(|| format!("calibration {}", path.display()))?;
    cal.build()
        .with_context(|| format!("calibration {}", path.display()))?;
    Ok(cal)
}

/// Stamps `new` with `metrics`, checks it builds, writes it and (when asked) the report, and
/// commits both together.
pub(crate) fn commit_version(
    new: &mut Calibration,
    metrics: Vec<(&str, f64)>,
    out_file: Option<AtomicOutput>,
    report_file: Option<AtomicOutput>,
    report: impl FnOnce() -> String,
) -> Result<()> {
    new.metrics = metrics
        .into_iter()
        .map(|(k, v)| (k.to_string(), v))
        .collect();
    new.build().context("the new calibration")?;
    put(&out_file, new.to_json())?;
    if report_file.is_some() {
        put(&report_file, report())?;
    }
    commit_all([out_file, report_file])
}

/// The closing lines of a procedure's text output: its notes, then where the new version is.
pub(crate) fn closing(
    notes: &[String],
    out: &Path,
    new: &Calibration,
    start: &Calibration,
) -> Result<()> {
    for n in notes {
        outln!("  note: {n}")?;
    }
    outln!(
        "→ {} (version {}, parent {})",
        out.display(),
        new.version,
        start.version
    )
}
