//! The dynamics program's face scans (`dynamics-faces`): three calibrated faces, their normals
//! along −x, −y and +z, each touched by the probe while the carriage oscillates — along the
//! face's normal (the acceleration along the measured direction, off arcs: P_xx, P_yy, P_zz
//! apart from the arcs' f² gain) and along each of the face's two tangents, sliding (the
//! acceleration across the measured direction: P's off-diagonal terms, P_xz, P_zx, P_yz, P_zy
//! among them, which rings in a horizontal plane cannot see).
//!
//! Every weave is run at two frequencies with one amplitude: the acceleration grows with f²,
//! the static errors of the place (the probe's bending with its deflection, the face's tilt,
//! the machine's geometry) do not — `calibrate dynamics` tells the two apart that way.
//! Frequencies 4 and 8 Hz stay far below the structure's modes (≥ 40 Hz), where the probe's
//! displacement follows the acceleration quasi-statically.

use super::*;

/// Normal weaves: amplitude, mm, about the probe deflection, mm (the probe stays in its range).
const NORMAL: (f64, f64) = (0.1, 0.3);
/// Sliding weaves along a tangent: amplitude, mm.
const SLIDE_MM: f64 = 0.4;
/// Weave frequencies, Hz.
const FREQS: [f64; 2] = [4.0, 8.0];
/// Places of the normal weaves along each face, mm (the sliding ones at the middle).
const PLACES: [f64; 3] = [-60.0, 0.0, 60.0];

/// A calibrated face (a few tens of nm of form) of normal `n` at `c`.
fn face(c: V3, n: [f64; 3], seed: f64) -> Feature {
    Feature {
        id: 0,
        artifact: "straightedge".into(),
        kind: FeatureKind::Face,
        center: c.into(),
        radius_mm: 0.0,
        nominal_diameter_mm: 0.0,
        certificate_diameter_mm: None,
        normal: n,
        form: vec![[300.0, 0.03e-3, 0.5 + seed], [170.0, 0.015e-3, 1.1]],
    }
}

/// Plans the face weaves about `position` (or the dynamics program's base).
pub(super) fn plan(b: &mut Builder, position: Option<V3>) {
    let base = position.unwrap_or(V3::new(500.0, 400.0, -280.0));
    b.set_tip(1, 0.0, 0.0);
    let faces = [
        (V3::new(60.0, 0.0, 0.0), [-1.0, 0.0, 0.0]),
        (V3::new(0.0, 60.0, 0.0), [0.0, -1.0, 0.0]),
        (V3::new(0.0, 0.0, -20.0), [0.0, 0.0, 1.0]),
    ];
    for (k, (off, n)) in faces.iter().enumerate() {
        let f = b.feature(face(base + off, *n, k as f64));
        for at in PLACES {
            for freq in FREQS {
                b.face_weave(f, at, NORMAL.0, freq, (6.0 * freq).round(), NORMAL.1);
            }
        }
        // Sliding along the face's two tangents at its middle.
        let nv = V3::from(*n);
        let along = face_along(&nv);
        let across = nv.cross(&along);
        let ft = b.features[f as usize - 1].clone();
        let r_tip = b.stylus(b.tip).radius_mm;
        let off = b.offset(b.tip, b.a1, b.a2);
        let at = ft.c() + nv * (r_tip - NORMAL.1) - off;
        for dir in [along, across] {
            for freq in FREQS {
                let path = Path::Weave {
                    at,
                    dir,
                    amplitude: SLIDE_MM,
                    cycles: (6.0 * freq).round(),
                };
                b.scan(
                    path,
                    TAU * freq * SLIDE_MM,
                    scancorr_core::lab::plan::WEAVE_RAMP_S,
                    f,
                    NORMAL.1,
                );
            }
        }
    }
}
