//! Calibration procedures: measurements of known artifacts turned into the parameters of a
//! calibration, each with its standard uncertainty.
//!
//! A procedure reads the corrected points of its measurement (a [`Dataset`] the caller built
//! from the bags with the starting calibration), fits what the measurement determines, names
//! what it cannot, and returns the changed calibration (not yet versioned: the caller stamps
//! it with [`crate::lab::version::next`]). Pure logic: no files, no clock.
//!
//! * [`tips`] — qualification of the styli on a master sphere.
//! * [`scales`] — the scales' expansion coefficients from a ball bar read at several
//!   temperatures.
//! * [`probe_force`] — extrapolation to zero force: a force coefficient per tip and axis.
//! * [`dynamic_map`] — the S1/F1/F2 joint method: a per-point map of a fast scan's error for
//!   one feature and speed (slow and fast scans, extrapolated to zero deflection).
//! * [`dynamics`] — the ring-gauge procedure: time constants, deflection matrix, phase, gain.
//! * [`straightness`] — error separation of a guide's straightness (and pitch) from a
//!   straightedge's: three probes, two probes, or one probe on a shear stage.
//! * [`thermal_drift`] — a drift recording (displacement and structure temperatures over
//!   hours): the drift from the temperatures and heat sources through their lags, judged on a
//!   later held-out period.
//! * [`separation`] — `calibrate straightness`: the raw streams into stations, the
//!   separation, the guide's table with its uncertainties in the calibration.
//! * [`plate`] — a plate's features measured against nominal: similarity, anisotropic
//!   scale/shear (quadrupole; scale per axis and squareness), higher-order terms chosen by
//!   leave-one-hole-out cross-validation, the original plug-plate tool's fit reproduced.
//!
//! [`Dataset`]: crate::lab::dataset::Dataset

pub mod dynamic_map;
pub mod dynamics;
pub mod plate;
pub mod probe_force;
pub mod scales;
pub mod separation;
pub mod straightness;
pub mod thermal_drift;
pub mod tips;
pub mod zero_force;

use serde::Serialize;

/// One fitted parameter.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Param {
    /// Name, as the simulator's truth file names it (`tip2.l1_mm`).
    pub name: String,
    /// Value, in the unit its name ends with.
    pub value: f64,
    /// Standard uncertainty (1σ), same unit.
    pub sigma: f64,
}

/// Why a procedure cannot answer.
#[derive(Debug, Clone, thiserror::Error)]
pub enum ProcedureError {
    /// The bags lack the measurement; the message names it.
    #[error("{0}")]
    Missing(String),
    /// The measurement cannot separate the parameters; the message says what to add.
    #[error("{0}")]
    IllConditioned(String),
}

/// Solves the weighted least-squares problem `a·θ ≈ b` (rows weighted by `w`): θ, its
/// covariance scaled by the reduced χ² when that exceeds 1 (so the σ are honest when the
/// model does not describe the data to its stated noise), and the weighted residual RMS.
/// `None` when the normal matrix is singular (a parameter the rows do not determine).
pub(crate) fn weighted_lsq(
    a: &[Vec<f64>],
    b: &[f64],
    w: &[f64],
) -> Option<(Vec<f64>, nalgebra::DMatrix<f64>, f64)> {
    let n = a.first()?.len();
    let m = a.len();
    if m < n {
        return None;
    }
    let mut ata = nalgebra::DMatrix::<f64>::zeros(n, n);
    let mut atb = nalgebra::DVector::<f64>::zeros(n);
    for (row, (&y, &wi)) in a.iter().zip(b.iter().zip(w)) {
        for i in 0..n {
            atb[i] += wi * row[i] * y;
            for j in 0..n {
                ata[(i, j)] += wi * row[i] * row[j];
            }
        }
    }
    // Condition check on the scaled matrix (columns of very different units).
    let d: Vec<f64> = (0..n).map(|i| ata[(i, i)].sqrt().max(1e-300)).collect();
    let scaled = nalgebra::DMatrix::from_fn(n, n, |i, j| ata[(i, j)] / (d[i] * d[j]));
    let eig = scaled.clone().symmetric_eigen();
    let (lo, hi) = eig
        .eigenvalues
        .iter()
        .fold((f64::MAX, 0.0_f64), |acc, &e| (acc.0.min(e), acc.1.max(e)));
    if !(lo > 1e-10 * hi) {
        return None;
    }
    let inv_s = scaled.try_inverse()?;
    let inv = nalgebra::DMatrix::from_fn(n, n, |i, j| inv_s[(i, j)] / (d[i] * d[j]));
    let theta = &inv * atb;
    let mut chi2 = 0.0;
    for (row, (&y, &wi)) in a.iter().zip(b.iter().zip(w)) {
        let r = y - row
            .iter()
            .zip(theta.iter())
            .map(|(x, t)| x * t)
            .sum::<f64>();
        chi2 += wi * r * r;
    }
    let dof = (m - n).max(1) as f64;
    let scale = (chi2 / dof).max(1.0);
    Some((
        theta.iter().copied().collect(),
        inv * scale,
        (chi2 / m as f64).sqrt(),
    ))
}
