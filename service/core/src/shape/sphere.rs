//! The sphere fit: orthogonal-distance least squares over centre and radius (or centre only).

use super::radial::radial_fit;
use super::*;

/// A fitted sphere.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SphereFit {
    /// Centre, mm.
    pub center: Vec3,
    /// Radius, mm (the given radius for [`fit_sphere_fixed_radius`]).
    pub radius: f64,
    /// Diameter = 2·radius, mm.
    pub diameter: f64,
    /// RMS of `residuals`, mm.
    pub rms: f64,
    /// Signed residual of each point (distance from the centre minus the radius; positive
    /// outside), mm, in input order.
    pub residuals: Vec<f64>,
    /// Iterations spent (Levenberg–Marquardt and Newton, all starts).
    pub iterations: usize,
}

impl SphereFit {
    /// Largest absolute residual, mm.
    pub fn max_abs_residual(&self) -> f64 {
        max_abs(&self.residuals)
    }
}

/// Fits a sphere by orthogonal-distance least squares (see the module documentation). Needs
/// 4 points not in one plane.
pub fn fit_sphere(points: &[Vec3]) -> Result<SphereFit, ShapeError> {
    sphere(points, None)
}

/// Fits the centre of a sphere of known `radius` (mm), e.g. a reference sphere with its
/// certified size. Needs 4 points not in one plane.
pub fn fit_sphere_fixed_radius(points: &[Vec3], radius: f64) -> Result<SphereFit, ShapeError> {
    check_radius(radius)?;
    sphere(points, Some(radius))
}

fn sphere(points: &[Vec3], fixed_radius: Option<f64>) -> Result<SphereFit, ShapeError> {
    let kind = ShapeKind::Sphere;
    let pc = principal(points, kind)?;
    if pc.sigma[1] <= DEGENERATE_RATIO * pc.sigma[0] {
        // Collinear points are coplanar too; the sphere needs points off any plane.
        return Err(ShapeError::Coplanar { kind });
    }
    if pc.sigma[2] <= DEGENERATE_RATIO * pc.sigma[0] {
        return Err(ShapeError::Coplanar { kind });
    }
    let s = pc.extent;
    let q: Vec<[f64; 3]> = pc
        .centered
        .iter()
        .map(|w| [w[0] / s, w[1] / s, w[2] / s])
        .collect();
    let sol = radial_fit(&q, fixed_radius.map(|r| r / s), kind, s)?;
    let center = pc.centroid + Vec3::new(sol.center[0], sol.center[1], sol.center[2]) * s;
    let radius = fixed_radius.unwrap_or(sol.radius * s);
    let residuals: Vec<f64> = sol.residuals.iter().map(|e| e * s).collect();
    let fit = SphereFit {
        center,
        radius,
        diameter: 2.0 * radius,
        rms: rms(&residuals),
        residuals,
        iterations: sol.iterations,
    };
    if !(fit.center.iter().all(|x| x.is_finite()) && fit.radius.is_finite() && fit.rms.is_finite())
    {
        return Err(ShapeError::NoConvergence {
            kind,
            iterations: sol.iterations,
        });
    }
    Ok(fit)
}
