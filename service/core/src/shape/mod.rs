//! Orthogonal-distance least-squares fits of circles, spheres, lines and planes, as the model
//! lab uses them to evaluate measured artefacts (ring gauges, reference spheres, straight
//! edges, flats), plus a parser for ASCII point files.
//!
//! Every fit minimises the sum of squared *orthogonal* (geometric) distances of the points
//! from the feature, the criterion of ISO 10360-6 and of the NIST algorithm-testing data sets
//! the tests compare against to 1e-10 relative. Units are those of the points (mm).
//!
//! ## Plane and line (closed form)
//!
//! With the centroid p̄ = (1/n)·Σ pᵢ and the centred points wᵢ = pᵢ − p̄ stacked as the rows of
//! W = U·diag(σ₁ ≥ σ₂ ≥ σ₃)·Vᵀ (singular value decomposition):
//!
//! * plane: normal n = v₃ (smallest singular value); signed residual eᵢ = wᵢ·n, and
//!   Σ eᵢ² = σ₃² is the minimum over all planes;
//! * line: direction d = v₁ (largest singular value), through p̄; residual
//!   eᵢ = |wᵢ − (wᵢ·d)·d| ≥ 0, and Σ eᵢ² = σ₂² + σ₃².
//!
//! ## Sphere and circle (iterative)
//!
//! Sphere: minimise S(c, r) = Σ (|qᵢ − c| − r)² over the centre c and radius r, where
//! qᵢ = wᵢ / s are the centred points scaled by their RMS distance s from p̄ (for
//! conditioning; results are transformed back). Circle: the plane is fitted first as above,
//! the points are projected into it, qᵢ = (wᵢ·v₁, wᵢ·v₂) / s, and the same problem is solved
//! in two dimensions; the centre is p̄ + s·(c₁·v₁ + c₂·v₂).
//!
//! The signed residual is eᵢ = |qᵢ − c| − r (positive outside). Its Jacobian row is
//! Jᵢ = [−uᵢᵀ, −1] with uᵢ = (qᵢ − c)/|qᵢ − c| (the −1 is absent when the radius is fixed).
//!
//! 1. **Initialisation** by two algebraic fits, each started from separately, the result with
//!    the smaller S kept:
//!    * Kåsa: linear least squares |qᵢ|² = 2·c·qᵢ + k, r² = k + |c|²;
//!    * Pratt: minimise |Z·A|² subject to Aᵀ·N·A = 1 with rows Zᵢ = [|qᵢ|², qᵢᵀ, 1] and
//!      N the matrix of B = |a|² − 4·A₀·A_last; solved with the SVD Z = U·Σ·Vᵀ,
//!      W = V·Σ·Vᵀ, A = W⁻¹·(eigenvector of W·N⁻¹·W for its second smallest eigenvalue,
//!      the smallest non-negative one: the matrix has the inertia of N⁻¹, one negative);
//!      c = −a/(2A₀), r = √(|a|² − 4A₀A_last)/(2|A₀|).
//! 2. **Levenberg–Marquardt** on the geometric residuals: the step δ minimises
//!    |J·δ + e|² + μσ₁(J)²·|δ|², computed from the SVD of J; μ is lowered ten-fold after every
//!    successful step (to pure Gauss–Newton) and raised ten-fold after a failed one. It stops
//!    when |δ| ≤ 1e-15·(1 + |p|), when the actual and predicted reductions of S are both
//!    below 1e-12·S, or when no step reduces S any more (rounding floor); a run whose radius
//!    or centre exceeds 10⁶ (scaled units) is abandoned as running off to a straight line.
//! 3. **Newton polish** with the exact Hessian H = JᵀJ + Σ eᵢ·(I − uᵢuᵢᵀ)/|qᵢ − c| in the
//!    centre block, which turns the linear convergence of Gauss–Newton on large-residual or
//!    partial-arc data into quadratic convergence. Near the minimum the change of S drowns
//!    in its rounding (S is flat there), so steps below 1e-6·(1 + |p|) are judged by their
//!    size, not by S: they are taken while they shrink, until |δ| ≤ 1e-15·(1 + |p|) or the
//!    rounding floor. Judging by S alone would stop at √ε accuracy (≈1e-10 relative on the
//!    NIST sets); this polish brings it to ≈1e-14.
//!
//! The fixed-radius variants (ring gauges and reference spheres with their certified size)
//! solve the same problem over c only, started from the algebraic centres.
//!
//! ## Conventions and refusals
//!
//! Normals and directions are unit vectors whose largest-magnitude component is positive
//! (the first such component on an exact tie). No result ever holds NaN: non-finite input,
//! too few points and degenerate point sets (all points identical; collinear points for a
//! circle or plane; coplanar points for a sphere; an arc or cap so flat that the fitted radius
//! exceeds 10⁶ times the points' extent) are refused with a [`ShapeError`] saying what is
//! missing and which measurement supplies it.

use crate::sample::Vec3;
use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};
use std::fmt;
use std::str::FromStr;

mod circle;
mod line;
mod plane;
mod points;
mod radial;
mod sphere;

pub use circle::{fit_circle, fit_circle_fixed_radius, CircleFit};
pub use line::{fit_line, LineFit};
pub use plane::{fit_plane, PlaneFit};
pub use points::parse_points;
pub use sphere::{fit_sphere, fit_sphere_fixed_radius, SphereFit};

/// σ₂/σ₁ (circle, plane) or σ₃/σ₁ (sphere) below which the points count as collinear or
/// coplanar.
const DEGENERATE_RATIO: f64 = 1e-9;

/// The least arc, degrees, a circle's points must span about the fitted centre for the
/// circle to be determined (the Python package's `MIN_ARC_DEG`).
pub const MIN_ARC_DEG: f64 = 1.0;
/// Fitted radius over the points' RMS extent above which an arc or cap counts as flat.
const MAX_RADIUS_RATIO: f64 = 1e6;
/// Relative step size at which the iteration has converged.
const STEP_TOL: f64 = 1e-15;
/// Maximum Levenberg–Marquardt iterations per start.
const MAX_LM_ITERATIONS: usize = 500;
/// Relative reduction of the sum of squares (actual and predicted) at which
/// Levenberg–Marquardt hands over to the Newton polish.
const REDUCTION_TOL: f64 = 1e-12;
/// Maximum Newton polish iterations.
const MAX_NEWTON_ITERATIONS: usize = 30;
/// Relative Newton step size below which a step is taken without a cost decrease (the
/// quadratic model is exact there to far below the cost's rounding) and the iteration counts
/// as converged.
const NEWTON_TRUST: f64 = 1e-6;

/// The kinds of geometric feature this module fits.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ShapeKind {
    /// A circle in 3D space (plane, then circle in the plane).
    Circle,
    /// A sphere.
    Sphere,
    /// A straight line.
    Line,
    /// A plane.
    Plane,
}

impl ShapeKind {
    /// All kinds, in the order they are listed to users.
    pub const ALL: [ShapeKind; 4] = [
        ShapeKind::Circle,
        ShapeKind::Sphere,
        ShapeKind::Line,
        ShapeKind::Plane,
    ];

    /// Lower-case name (`circle`, `sphere`, `line`, `plane`).
    pub fn name(self) -> &'static str {
        match self {
            ShapeKind::Circle => "circle",
            ShapeKind::Sphere => "sphere",
            ShapeKind::Line => "line",
            ShapeKind::Plane => "plane",
        }
    }

    /// The minimum number of points a fit of this kind needs: circle 3, sphere 4, line 2,
    /// plane 3.
    pub fn min_points(self) -> usize {
        match self {
            ShapeKind::Circle => 3,
            ShapeKind::Sphere => 4,
            ShapeKind::Line => 2,
            ShapeKind::Plane => 3,
        }
    }

    fn names() -> String {
        ShapeKind::ALL.map(ShapeKind::name).join(", ")
    }

    fn collinear_hint(self) -> &'static str {
        match self {
            ShapeKind::Circle => {
                "scan more of the circle's circumference (at least 3 points not on one line)"
            }
            _ => {
                "the plane is undetermined; probe points spread in two directions over the \
                 surface (at least 3 not on one line)"
            }
        }
    }

    fn flat_hint(self) -> &'static str {
        match self {
            ShapeKind::Sphere => {
                "the points lie on a nearly flat surface, the sphere is undetermined; probe \
                 points over a larger part of the sphere (e.g. around the equator and one at \
                 the pole)"
            }
            _ => {
                "the points lie on a nearly straight line, the circle is undetermined; scan \
                 more of the circle's circumference"
            }
        }
    }
}

impl fmt::Display for ShapeKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for ShapeKind {
    type Err = ShapeError;

    /// Parses a lower- or mixed-case kind name; unknown names give
    /// [`ShapeError::UnknownKind`], whose message lists the kinds.
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        ShapeKind::ALL
            .into_iter()
            .find(|k| k.name().eq_ignore_ascii_case(s.trim()))
            .ok_or_else(|| ShapeError::UnknownKind(s.to_string()))
    }
}

/// Why a fit or a point file was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ShapeError {
    /// Fewer points than the feature has degrees of freedom.
    #[error(
        "a {kind} fit needs at least {needed} points, got {got}: measure at least {} more \
         point(s) on the feature",
        .needed - .got
    )]
    TooFewPoints {
        /// The feature fitted.
        kind: ShapeKind,
        /// Points needed ([`ShapeKind::min_points`]).
        needed: usize,
        /// Points given.
        got: usize,
    },
    /// A coordinate is NaN or infinite.
    #[error(
        "point {} has a non-finite coordinate (NaN or infinity): re-measure or remove it",
        .index + 1
    )]
    NonFinite {
        /// Zero-based index of the first offending point (the message counts from 1).
        index: usize,
    },
    /// All points coincide (to rounding).
    #[error(
        "all {count} points are the same point: the {kind} is undetermined; measure points \
         spread over the feature"
    )]
    AllIdentical {
        /// The feature fitted.
        kind: ShapeKind,
        /// Number of points.
        count: usize,
    },
    /// The points lie on one line (circle, plane).
    #[error("the points are collinear: {}", .kind.collinear_hint())]
    Collinear {
        /// The feature fitted.
        kind: ShapeKind,
    },
    /// The points lie in one plane (sphere).
    #[error(
        "the points are coplanar: the sphere is undetermined; probe points off that plane \
         (e.g. one near the pole)"
    )]
    Coplanar {
        /// The feature fitted.
        kind: ShapeKind,
    },
    /// The best fit has a radius far beyond the extent of the points.
    #[error(
        "best-fit radius {radius:.6e} mm over a point extent of {extent:.6e} mm: {}",
        .kind.flat_hint()
    )]
    TooFlat {
        /// The feature fitted.
        kind: ShapeKind,
        /// The runaway radius, mm.
        radius: f64,
        /// RMS distance of the points from their centroid, mm.
        extent: f64,
    },
    /// The points span so little of the best-fit circle that it is not determined (a
    /// straightedge's scan: its best circle is huge and anywhere along the normal).
    #[error(
        "the points span {span_deg:.3}° of the best-fit circle (radius {radius:.6e} mm over a \
         point extent of {extent:.6e} mm), less than {min_deg}°: {}",
        .kind.flat_hint()
    )]
    ShortArc {
        /// The feature fitted.
        kind: ShapeKind,
        /// The arc the points span about the fitted centre, degrees.
        span_deg: f64,
        /// The fitted radius, mm.
        radius: f64,
        /// RMS distance of the points from their centroid, mm.
        extent: f64,
        /// The least span accepted ([`MIN_ARC_DEG`]).
        min_deg: f64,
    },
    /// Coordinates so large that their squares overflow double precision.
    #[error(
        "the coordinates are too large to fit in double precision (up to about 1e150 mm is \
         supported): check the units of the points"
    )]
    OutOfRange,
    /// A fixed radius that is not a positive finite number.
    #[error("the fixed radius must be a positive finite number of mm, got {radius}")]
    InvalidRadius {
        /// The radius given.
        radius: f64,
    },
    /// The iteration did not converge.
    #[error(
        "the {kind} fit did not converge in {iterations} iterations: the points may not \
         describe a {kind}; check them for outliers"
    )]
    NoConvergence {
        /// The feature fitted.
        kind: ShapeKind,
        /// Iterations spent.
        iterations: usize,
    },
    /// A line of a point file could not be read.
    #[error("line {line}: {message}")]
    Parse {
        /// One-based line number.
        line: usize,
        /// What is wrong with it.
        message: String,
    },
    /// The point count declared on the first line disagrees with the rows.
    #[error(
        "line {line} declares {declared} points but the file holds {found}: the file is \
         truncated or its count is wrong"
    )]
    CountMismatch {
        /// One-based line number of the count.
        line: usize,
        /// Count declared.
        declared: usize,
        /// Rows found.
        found: usize,
    },
    /// An unknown shape kind name.
    #[error("unknown shape kind `{0}`: expected one of {kinds}", kinds = ShapeKind::names())]
    UnknownKind(String),
}

// What the fits share.

fn max_abs(v: &[f64]) -> f64 {
    v.iter().fold(0.0, |m, x| m.max(x.abs()))
}

fn rms(v: &[f64]) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt()
}

fn check_radius(radius: f64) -> Result<(), ShapeError> {
    if radius.is_finite() && radius > 0.0 {
        Ok(())
    } else {
        Err(ShapeError::InvalidRadius { radius })
    }
}

/// Normalises `v` and flips it so that its largest-magnitude component (the first on a tie)
/// is positive.
fn canonical_sign(v: Vec3) -> Vec3 {
    let mut k = 0;
    for i in 1..3 {
        if v[i].abs() > v[k].abs() {
            k = i;
        }
    }
    let v = v.normalize();
    if v[k] < 0.0 {
        -v
    } else {
        v
    }
}

/// Centroid and principal axes of a point set.
struct Principal {
    centroid: Vec3,
    centered: Vec<Vec3>,
    /// Singular values of the centred points, descending.
    sigma: [f64; 3],
    /// Right singular vectors (unit), matching `sigma`.
    axes: [Vec3; 3],
    /// RMS distance of the points from the centroid.
    extent: f64,
}

/// Checks count and finiteness, centres the points and finds their principal axes; refuses
/// coincident points.
fn principal(points: &[Vec3], kind: ShapeKind) -> Result<Principal, ShapeError> {
    let needed = kind.min_points();
    if points.len() < needed {
        return Err(ShapeError::TooFewPoints {
            kind,
            needed,
            got: points.len(),
        });
    }
    if let Some(index) = points.iter().position(|p| !p.iter().all(|x| x.is_finite())) {
        return Err(ShapeError::NonFinite { index });
    }
    let n = points.len();
    let centroid = points.iter().fold(Vec3::zeros(), |a, p| a + p) / n as f64;
    let centered: Vec<Vec3> = points.iter().map(|p| p - centroid).collect();
    let magnitude = points.iter().fold(0.0f64, |m, p| m.max(p.amax()));
    let extent = (centered.iter().map(|w| w.norm_squared()).sum::<f64>() / n as f64).sqrt();
    // Finite coordinates can still overflow when summed or squared.
    if !(extent.is_finite() && centroid.iter().all(|x| x.is_finite())) {
        return Err(ShapeError::OutOfRange);
    }
    if extent == 0.0 || extent <= 1e-13 * magnitude {
        return Err(ShapeError::AllIdentical { kind, count: n });
    }
    // SVD of the centred points scaled by their extent (conditioning, no overflow).
    let w = DMatrix::from_fn(n, 3, |i, j| centered[i][j] / extent);
    let svd = w
        .try_svd(false, true, f64::EPSILON, 100_000)
        .ok_or(ShapeError::NoConvergence {
            kind,
            iterations: 0,
        })?;
    let v_t = svd.v_t.as_ref().ok_or(ShapeError::NoConvergence {
        kind,
        iterations: 0,
    })?;
    let mut order = [0usize, 1, 2];
    let sv = &svd.singular_values;
    let get = |k: usize| if k < sv.len() { sv[k] } else { 0.0 };
    order.sort_by(|&a, &b| get(b).total_cmp(&get(a)));
    let mut sigma = [0.0; 3];
    let mut axes = [Vec3::zeros(); 3];
    for (slot, &k) in order.iter().enumerate() {
        sigma[slot] = get(k) * extent;
        if k < v_t.nrows() {
            axes[slot] = Vec3::new(v_t[(k, 0)], v_t[(k, 1)], v_t[(k, 2)]);
        }
    }
    // With fewer points than dimensions (a line through 2 points) the thin SVD has fewer
    // than 3 right singular vectors: complete the orthonormal basis.
    if v_t.nrows() < 3 {
        complete_basis(&mut axes, v_t.nrows());
    }
    Ok(Principal {
        centroid,
        centered,
        sigma,
        axes,
        extent,
    })
}

/// Fills `axes[have..]` with unit vectors orthogonal to the first `have` axes.
fn complete_basis(axes: &mut [Vec3; 3], have: usize) {
    for k in have..3 {
        // Start from the coordinate axis least aligned with the existing ones.
        let mut best = Vec3::zeros();
        for e in crate::sample::Axis::ALL {
            let mut v = e.unit();
            for a in axes.iter().take(k) {
                v -= a * a.dot(&v);
            }
            if v.norm() > best.norm() {
                best = v;
            }
        }
        axes[k] = best.normalize();
    }
}

#[cfg(test)]
mod tests;
