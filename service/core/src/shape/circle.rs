//! The circle fit: the least-squares plane, then the orthogonal-distance circle of the points
//! projected into it (free or fixed radius).

use super::radial::radial_fit;
use super::*;

/// A fitted circle in 3D space.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CircleFit {
    /// Centre, mm.
    pub center: Vec3,
    /// Unit normal of the circle's plane, largest-magnitude component positive.
    pub normal: Vec3,
    /// Radius, mm (the given radius for [`fit_circle_fixed_radius`]).
    pub radius: f64,
    /// Diameter = 2·radius, mm.
    pub diameter: f64,
    /// RMS of `residuals`, mm.
    pub rms: f64,
    /// Signed radial residual of each point within the plane (distance of its projection
    /// from the centre minus the radius; positive outside), mm, in input order.
    pub residuals: Vec<f64>,
    /// RMS distance of the points from the fitted plane, mm (0 for planar points; for
    /// non-planar points the 3D distance to the circle is √(residual² + out-of-plane²)).
    pub plane_rms: f64,
    /// Iterations spent (Levenberg–Marquardt and Newton, all starts).
    pub iterations: usize,
}

impl CircleFit {
    /// Largest absolute residual, mm.
    pub fn max_abs_residual(&self) -> f64 {
        max_abs(&self.residuals)
    }
}

/// Fits a circle to 3D points lying (nearly) in a plane: least-squares plane through the
/// centroid, then the orthogonal-distance least-squares circle of the projected points (see
/// the module documentation). Needs 3 points not on one line.
pub fn fit_circle(points: &[Vec3]) -> Result<CircleFit, ShapeError> {
    circle(points, None)
}

/// Fits the centre of a circle of known `radius` (mm) to 3D points lying (nearly) in a plane,
/// e.g. a ring gauge with its certified size. Needs 3 points not on one line.
pub fn fit_circle_fixed_radius(points: &[Vec3], radius: f64) -> Result<CircleFit, ShapeError> {
    check_radius(radius)?;
    circle(points, Some(radius))
}

fn circle(points: &[Vec3], fixed_radius: Option<f64>) -> Result<CircleFit, ShapeError> {
    let kind = ShapeKind::Circle;
    let pc = principal(points, kind)?;
    if pc.sigma[1] <= DEGENERATE_RATIO * pc.sigma[0] {
        return Err(ShapeError::Collinear { kind });
    }
    let (u, v) = (pc.axes[0], pc.axes[1]);
    let normal = canonical_sign(pc.axes[2]);
    let s = pc.extent;
    let q: Vec<[f64; 2]> = pc
        .centered
        .iter()
        .map(|w| [w.dot(&u) / s, w.dot(&v) / s])
        .collect();
    let sol = radial_fit(&q, fixed_radius.map(|r| r / s), kind, s)?;
    if fixed_radius.is_none() {
        let span_deg = arc_span(&q, [sol.center[0], sol.center[1]]).to_degrees();
        if span_deg < MIN_ARC_DEG {
            return Err(ShapeError::ShortArc {
                kind,
                span_deg,
                radius: sol.radius * s,
                extent: s,
                min_deg: MIN_ARC_DEG,
            });
        }
    }
    let center = pc.centroid + (u * sol.center[0] + v * sol.center[1]) * s;
    let radius = fixed_radius.unwrap_or(sol.radius * s);
    let residuals: Vec<f64> = sol.residuals.iter().map(|e| e * s).collect();
    let plane_rms = (pc
        .centered
        .iter()
        .map(|w| w.dot(&normal).powi(2))
        .sum::<f64>()
        / points.len() as f64)
        .sqrt();
    let fit = CircleFit {
        center,
        normal,
        radius,
        diameter: 2.0 * radius,
        rms: rms(&residuals),
        residuals,
        plane_rms,
        iterations: sol.iterations,
    };
    if !(fit.center.iter().all(|x| x.is_finite())
        && fit.radius.is_finite()
        && fit.rms.is_finite()
        && fit.plane_rms.is_finite())
    {
        return Err(ShapeError::NoConvergence {
            kind,
            iterations: sol.iterations,
        });
    }
    Ok(fit)
}

/// The angle (radians) points `q` span about `c`: 2π less the widest gap between neighbouring
/// points' angles.
fn arc_span(q: &[[f64; 2]], c: [f64; 2]) -> f64 {
    let mut th: Vec<f64> = q.iter().map(|p| (p[1] - c[1]).atan2(p[0] - c[0])).collect();
    th.sort_by(f64::total_cmp);
    let Some((&first, &last)) = th.first().zip(th.last()) else {
        return 0.0;
    };
    let widest = th
        .windows(2)
        .map(|w| w[1] - w[0])
        .fold(first + std::f64::consts::TAU - last, f64::max);
    std::f64::consts::TAU - widest
}
