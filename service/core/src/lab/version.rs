//! A new calibration version made by the lab: parent, note and the figures measured by
//! correcting the bags again with it (what `lab add`, `lab remove`, `lab fit` and each step of
//! `lab discover` write).

use super::analysis::Prepared;
use crate::calib::Calibration;
use crate::effects::EffectConfig;

/// The child of `parent` with `effects`, stamped `created` (the core has no clock).
pub fn next(parent: &Calibration, effects: Vec<EffectConfig>, created: &str) -> Calibration {
    let mut c = parent.clone();
    c.effects = effects;
    c.parent_version = Some(parent.version);
    c.version = parent.version + 1;
    c.created = created.to_string();
    c
}

/// Sets the note (`what`, then held-out and fit RMS before → after) and the metrics of a new
/// version from the parent's figures (`before`) and its own, measured (`after`).
pub fn describe(
    c: &mut Calibration,
    what: &str,
    noise_floor_um: f64,
    before: &Prepared,
    after: &Prepared,
) {
    c.note = format!(
        "{what}: held-out RMS {:.3} → {:.3} µm (fit {:.3} → {:.3} µm)",
        before.rms_held_um, after.rms_held_um, before.rms_fit_um, after.rms_fit_um
    );
    c.metrics = [
        ("rms_um".to_string(), after.rms_fit_um),
        ("heldout_rms_um".to_string(), after.rms_held_um),
        ("noise_floor_um".to_string(), noise_floor_um),
        ("parent_rms_um".to_string(), before.rms_fit_um),
        ("parent_heldout_rms_um".to_string(), before.rms_held_um),
    ]
    .into();
}
