//! The thin-walled part (`thin-wall`): a wall clamped at both ends that gives under the
//! probing force (the simulator's `wall` module), scanned along its length by the same line at two probing
//! forces — the passes per-point extrapolation to zero force pairs (`scancorr calibrate
//! zero-force`); `thin-wall-forces` scans it at three.

/// The artifact name of a thin-walled part's face (its physics: the simulator's `wall` module).
pub const WALL_ARTIFACT: &str = "thin-wall";
/// The wall's free length between its clamped ends, mm (centred on the feature's centre).
pub const WALL_LENGTH_MM: f64 = 200.0;

use super::*;

/// The wall: a face of normal −Y, [`WALL_LENGTH_MM`] long along X between its clamps,
/// centred at `position` (or its usual place), with a machined part's µm of form.
fn wall_feature(position: Option<V3>) -> Feature {
    Feature {
        id: 0,
        artifact: WALL_ARTIFACT.into(),
        kind: FeatureKind::Face,
        center: position.unwrap_or(V3::new(450.0, 250.0, -300.0)).into(),
        radius_mm: 0.0,
        nominal_diameter_mm: 0.0,
        certificate_diameter_mm: None,
        normal: [0.0, -1.0, 0.0],
        form: vec![[150.0, 1.0e-3, 0.7], [37.0, 0.3e-3, 2.1]],
    }
}

/// Plans the wall's passes: tip 1 at head angles (0, 0), the line from −90 to +90 mm along
/// the wall at 10 mm/s, once per deflection in `deflections_mm` (the forces ∝ deflection).
pub(super) fn plan(b: &mut Builder, position: Option<V3>, deflections_mm: &[f64]) {
    let f = b.feature(wall_feature(position));
    b.set_tip(1, 0.0, 0.0);
    for d in deflections_mm {
        b.face_line(f, -90.0, 90.0, 10.0, *d);
    }
}
