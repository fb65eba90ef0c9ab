//! The real-time form of the extrapolation to zero force: two readings of one place at two
//! probing forces give the reading at zero force.
//!
//! Equation (the line through (F1, R1) and (F2, R2) evaluated at F = 0):
//!
//! R0 = R1 − (R2 − R1)·F1/(F2 − F1),
//!
//! with standard uncertainty from the readings' (first order):
//! ∂R0/∂R1 = F2/(F2 − F1), ∂R0/∂R2 = −F1/(F2 − F1), ∂R0/∂F1 = −(R2 − R1)·F2/(F2 − F1)²,
//! ∂R0/∂F2 = (R2 − R1)·F1/(F2 − F1)².
//!
//! A force below significance (|F| < 3σ_F) is taken as zero: its reading is already the
//! zero-force reading and nothing is extrapolated (extrapolating from a force that is noise
//! only adds the noise of the other reading). Two forces whose difference is below
//! significance cannot be extrapolated from at all: the pair is reported as alike.
//!
//! Source idea: Renishaw's calibration of a coordinate positioning apparatus — the probe
//! takes each point at two forces during the one scan and the controller extrapolates to
//! zero force as it goes, no calibration table needed.

use serde::Serialize;

/// Readings closer to zero than this many standard uncertainties are zero.
pub const SIGNIFICANCE: f64 = 3.0;

/// One reading: a value (a radius, a coordinate) at a probing force (or a deflection, which
/// is proportional to it), each with its standard uncertainty.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Reading {
    /// The value, any length unit.
    pub r: f64,
    /// Its standard uncertainty.
    pub r_sigma: f64,
    /// The force (or deflection).
    pub f: f64,
    /// Its standard uncertainty.
    pub f_sigma: f64,
}

/// The zero-force value of a pair of readings.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum ZeroForce {
    /// Extrapolated along the line through both readings.
    Extrapolated {
        /// R0.
        r0: f64,
        /// Its standard uncertainty.
        sigma: f64,
    },
    /// One reading's force is below significance: that reading is the zero-force one.
    ForceZero {
        /// R0 (the reading at the insignificant force).
        r0: f64,
        /// Its standard uncertainty.
        sigma: f64,
    },
    /// The two forces do not differ significantly: no line to extrapolate along.
    Alike,
}

impl ZeroForce {
    /// R0 and its σ, when there is one.
    pub fn value(&self) -> Option<(f64, f64)> {
        match *self {
            ZeroForce::Extrapolated { r0, sigma } | ZeroForce::ForceZero { r0, sigma } => {
                Some((r0, sigma))
            }
            ZeroForce::Alike => None,
        }
    }
}

fn insignificant(x: f64, sigma: f64) -> bool {
    x.abs() < SIGNIFICANCE * sigma.abs()
}

/// R0 = R1 − (R2 − R1)·F1/(F2 − F1), a force below significance taken as zero.
pub fn two_force(a: Reading, b: Reading) -> ZeroForce {
    if insignificant(a.f, a.f_sigma) {
        return ZeroForce::ForceZero {
            r0: a.r,
            sigma: a.r_sigma,
        };
    }
    if insignificant(b.f, b.f_sigma) {
        return ZeroForce::ForceZero {
            r0: b.r,
            sigma: b.r_sigma,
        };
    }
    let df = b.f - a.f;
    if insignificant(df, a.f_sigma.hypot(b.f_sigma)) || df == 0.0 {
        return ZeroForce::Alike;
    }
    let dr = b.r - a.r;
    let r0 = a.r - dr * a.f / df;
    let g = [
        (b.f / df, a.r_sigma),
        (-a.f / df, b.r_sigma),
        (-dr * b.f / (df * df), a.f_sigma),
        (dr * a.f / (df * df), b.f_sigma),
    ];
    let sigma = g.iter().map(|(d, s)| (d * s).powi(2)).sum::<f64>().sqrt();
    ZeroForce::Extrapolated { r0, sigma }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn reading(r: f64, f: f64) -> Reading {
        Reading {
            r,
            r_sigma: 0.1,
            f,
            f_sigma: 0.01,
        }
    }

    #[test]
    fn a_line_through_two_forces_lands_on_its_zero_force_value() {
        // R = 5 − 2·F: at F = 0.1 and 0.5 the readings are 4.8 and 4.0.
        let z = two_force(reading(4.8, 0.1), reading(4.0, 0.5));
        let (r0, s) = z.value().unwrap();
        assert!(matches!(z, ZeroForce::Extrapolated { .. }));
        assert!((r0 - 5.0).abs() < 1e-12, "{r0}");
        // σ: mostly the nearer reading's, amplified by F2/(F2 − F1) = 1.25, plus F1/(F2 − F1).
        let expect = (1.25f64 * 0.1).hypot(0.25 * 0.1);
        assert!(s > expect && s < expect * 1.1, "{s} vs {expect}");
        // The order of the readings does not matter.
        let (r0b, sb) = two_force(reading(4.0, 0.5), reading(4.8, 0.1))
            .value()
            .unwrap();
        assert!((r0b - r0).abs() < 1e-12 && (sb - s).abs() < 1e-12);
    }

    #[test]
    fn a_force_below_significance_is_zero_and_alike_forces_give_nothing() {
        // 0.02 ± 0.01 is not a force: its reading is the zero-force one.
        let z = two_force(reading(4.96, 0.02), reading(4.0, 0.5));
        assert_eq!(
            z,
            ZeroForce::ForceZero {
                r0: 4.96,
                sigma: 0.1
            }
        );
        // 0.30 and 0.32 ± 0.01 differ by 1.4σ: no line.
        assert_eq!(
            two_force(reading(4.4, 0.30), reading(4.36, 0.32)),
            ZeroForce::Alike
        );
        assert_eq!(ZeroForce::Alike.value(), None);
    }
}
