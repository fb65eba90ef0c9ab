//! A thin wall that gives under the probing force: the part's own compliance, which no
//! calibration on the master sphere can know.
//!
//! The probe presses on the wall with a force proportional to its deflection d (the probe's
//! springs); the wall, clamped at both ends of its length L like a beam, gives under that
//! point load by
//!
//! w(s) = c(s)·|d|,  c(s) = c_max·(1 − (2s/L)²)³
//!
//! (a clamped–clamped beam's deflection under a point load at a and b = L − a from its ends
//! is ∝ a³b³: stiff near the clamps, softest at mid-span). The surface the tip touches is w
//! deeper along the wall's normal than the unloaded wall, so of the tip's interference δ with
//! the unloaded wall the wall takes w and the stylus and probe the rest:
//! δ = |d|·(1 + k) + w, which with the probe's reading d = D·Rᵀ·n·δ_eff (D = diag(1/(1 + k_i)),
//! the stylus's bending) gives δ_eff = δ/(1 + c·g), g = |D·Rᵀ·n| — exact for this linear model.
//!
//! Source idea: Renishaw's extrapolation to zero force on the part itself (the error of a
//! point is linear in the probing force; a thin-walled part bends differently from the
//! sphere the stylus was calibrated on, so each point is extrapolated on its own).

use crate::machine::V3;
use crate::program::{Feature, FeatureKind};
pub use crate::program::{WALL_ARTIFACT as ARTIFACT, WALL_LENGTH_MM as LENGTH_MM};
use nalgebra::Matrix3;

/// The wall's compliance at mid-span: µm the wall gives per µm of probe deflection.
pub const COMPLIANCE_MAX: f64 = 0.012;

/// The wall's compliance c(s) at the point of `f` nearest `tip` (0 beyond the clamps and for
/// any other feature).
pub fn compliance(f: &Feature, tip: &V3) -> f64 {
    if f.artifact != ARTIFACT || f.kind != FeatureKind::Face {
        return 0.0;
    }
    let n = V3::from(f.normal);
    let along = n.cross(&V3::z()).try_normalize(1e-9).unwrap_or(V3::x());
    let x = 2.0 * (tip - V3::from(f.center)).dot(&along) / LENGTH_MM;
    if x.abs() >= 1.0 {
        0.0
    } else {
        COMPLIANCE_MAX * (1.0 - x * x).powi(3)
    }
}

/// The interference `d_total` with the unloaded surface of `f` less what the wall gives:
/// d_total/(1 + c·g), g = |D·Rᵀ·n| (see the module's equation); `probe_k` the stylus's
/// bending per axis of the probe (already scaled for the stylus).
pub fn yielded(f: &Feature, tip: &V3, d_total: V3, rot: &Matrix3<f64>, probe_k: [f64; 3]) -> V3 {
    let c = compliance(f, tip);
    let len = d_total.norm();
    if c == 0.0 || len == 0.0 {
        return d_total;
    }
    let p = rot.transpose() * (d_total / len);
    let g = V3::new(
        p.x / (1.0 + probe_k[0]),
        p.y / (1.0 + probe_k[1]),
        p.z / (1.0 + probe_k[2]),
    )
    .norm();
    d_total / (1.0 + c * g)
}
