//! The plane fit: through the centroid, normal to the direction of least spread (closed form).

use super::*;

/// A fitted plane.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PlaneFit {
    /// A point on the plane: the centroid of the points, mm.
    pub centroid: Vec3,
    /// Unit normal, largest-magnitude component positive.
    pub normal: Vec3,
    /// RMS of `residuals`, mm.
    pub rms: f64,
    /// Signed distance of each point from the plane (positive on the side the normal points
    /// to), mm, in input order.
    pub residuals: Vec<f64>,
}

impl PlaneFit {
    /// Largest absolute residual, mm.
    pub fn max_abs_residual(&self) -> f64 {
        max_abs(&self.residuals)
    }
}

/// Fits a plane by orthogonal-distance least squares: through the centroid, normal to the
/// direction of least spread. Needs 3 points not on one line.
pub fn fit_plane(points: &[Vec3]) -> Result<PlaneFit, ShapeError> {
    let pc = principal(points, ShapeKind::Plane)?;
    if pc.sigma[1] <= DEGENERATE_RATIO * pc.sigma[0] {
        return Err(ShapeError::Collinear {
            kind: ShapeKind::Plane,
        });
    }
    let normal = canonical_sign(pc.axes[2]);
    let residuals: Vec<f64> = pc.centered.iter().map(|w| w.dot(&normal)).collect();
    Ok(PlaneFit {
        centroid: pc.centroid,
        normal,
        rms: rms(&residuals),
        residuals,
    })
}
