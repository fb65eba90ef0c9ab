//! The line fit: through the centroid along the principal direction (closed form).

use super::*;

/// A fitted straight line.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LineFit {
    /// A point on the line: the centroid of the points, mm.
    pub centroid: Vec3,
    /// Unit direction, largest-magnitude component positive.
    pub direction: Vec3,
    /// RMS of `residuals`, mm.
    pub rms: f64,
    /// Orthogonal distance of each point from the line (≥ 0), mm, in input order.
    pub residuals: Vec<f64>,
}

impl LineFit {
    /// Largest residual, mm.
    pub fn max_abs_residual(&self) -> f64 {
        max_abs(&self.residuals)
    }
}

/// Fits a straight line by orthogonal-distance least squares: through the centroid along the
/// principal direction. Needs 2 distinct points.
pub fn fit_line(points: &[Vec3]) -> Result<LineFit, ShapeError> {
    let pc = principal(points, ShapeKind::Line)?;
    let direction = canonical_sign(pc.axes[0]);
    let residuals: Vec<f64> = pc
        .centered
        .iter()
        .map(|w| (w - direction * w.dot(&direction)).norm())
        .collect();
    Ok(LineFit {
        centroid: pc.centroid,
        direction,
        rms: rms(&residuals),
        residuals,
    })
}
