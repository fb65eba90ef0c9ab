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

/// σ₂/σ₁ (circle, plane) or σ₃/σ₁ (sphere) below which the points count as collinear or
/// coplanar.
const DEGENERATE_RATIO: f64 = 1e-9;
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

/// Parses an ASCII point file: one `x y z` row per point — or `x y` rows (z = 0), as a
/// roundness profile comes — the numbers separated by whitespace and/or commas; the first
/// point row fixes which. Blank lines and `#` comments (to the end of the line) are ignored.
/// The first row may hold only the number of points (an integer), which is then checked
/// against the rows that follow. Errors name the one-based line.
pub fn parse_points(text: &str) -> Result<Vec<Vec3>, ShapeError> {
    let mut points = Vec::new();
    let mut declared: Option<(usize, usize)> = None;
    let mut first = true;
    let mut width: Option<usize> = None;
    for (i, raw) in text.lines().enumerate() {
        let line = i + 1;
        let content = raw.split('#').next().unwrap_or("");
        let tokens: Vec<&str> = content
            .split(|c: char| c.is_whitespace() || c == ',')
            .filter(|t| !t.is_empty())
            .collect();
        if tokens.is_empty() {
            continue;
        }
        if first {
            first = false;
            if tokens.len() == 1 {
                let count = tokens[0].parse::<usize>().map_err(|_| ShapeError::Parse {
                    line,
                    message: format!(
                        "`{}` is neither a point count (a whole number alone on the first \
                         line) nor an `x y z` row",
                        tokens[0]
                    ),
                })?;
                declared = Some((line, count));
                continue;
            }
        }
        let want = *width.get_or_insert(if tokens.len() == 2 { 2 } else { 3 });
        if tokens.len() != want {
            return Err(ShapeError::Parse {
                line,
                message: format!(
                    "expected {want} numbers ({}{}), found {} field(s): `{}`",
                    if want == 2 { "x y" } else { "x y z" },
                    if points.is_empty() {
                        ""
                    } else {
                        ", as the rows before"
                    },
                    tokens.len(),
                    content.trim()
                ),
            });
        }
        let mut xyz = [0.0; 3];
        for (v, t) in xyz.iter_mut().zip(&tokens) {
            let x = t.parse::<f64>().map_err(|_| ShapeError::Parse {
                line,
                message: format!("`{t}` is not a number"),
            })?;
            if !x.is_finite() {
                return Err(ShapeError::Parse {
                    line,
                    message: format!("`{t}` is not a finite number"),
                });
            }
            *v = x;
        }
        points.push(Vec3::new(xyz[0], xyz[1], xyz[2]));
    }
    if let Some((line, count)) = declared {
        if count != points.len() {
            return Err(ShapeError::CountMismatch {
                line,
                declared: count,
                found: points.len(),
            });
        }
    }
    Ok(points)
}

// ---------------------------------------------------------------------------------------------
// Internals.

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

/// Result of a radial (circle or sphere) fit in scaled coordinates.
struct RadialSolution {
    center: Vec<f64>,
    radius: f64,
    residuals: Vec<f64>,
    iterations: usize,
}

/// One run of the iteration from one start.
struct Run {
    params: DVector<f64>,
    cost: f64,
    iterations: usize,
    converged: bool,
}

/// The orthogonal-distance problem Σ (|qᵢ − c| − r)² in `D` dimensions; `fixed` holds the
/// radius when it is not a parameter. Parameters: c (D), then r when free.
struct Radial<'a, const D: usize> {
    q: &'a [[f64; D]],
    fixed: Option<f64>,
}

impl<const D: usize> Radial<'_, D> {
    fn nparams(&self) -> usize {
        D + usize::from(self.fixed.is_none())
    }

    fn radius(&self, p: &DVector<f64>) -> f64 {
        self.fixed.unwrap_or_else(|| p[D])
    }

    fn distance(&self, i: usize, p: &DVector<f64>) -> f64 {
        let mut d2 = 0.0;
        for j in 0..D {
            let t = self.q[i][j] - p[j];
            d2 += t * t;
        }
        d2.sqrt()
    }

    fn residuals(&self, p: &DVector<f64>) -> Vec<f64> {
        let r = self.radius(p);
        (0..self.q.len()).map(|i| self.distance(i, p) - r).collect()
    }

    fn cost(&self, p: &DVector<f64>) -> f64 {
        let r = self.radius(p);
        (0..self.q.len())
            .map(|i| {
                let e = self.distance(i, p) - r;
                e * e
            })
            .sum()
    }

    /// Residuals and Jacobian at `p`.
    fn linearise(&self, p: &DVector<f64>) -> (DVector<f64>, DMatrix<f64>) {
        let n = self.q.len();
        let k = self.nparams();
        let r = self.radius(p);
        let mut e = DVector::zeros(n);
        let mut jac = DMatrix::zeros(n, k);
        for i in 0..n {
            let d = self.distance(i, p);
            e[i] = d - r;
            if d > 0.0 {
                for j in 0..D {
                    jac[(i, j)] = -(self.q[i][j] - p[j]) / d;
                }
            }
            if k > D {
                jac[(i, D)] = -1.0;
            }
        }
        (e, jac)
    }

    /// Gradient JᵀE and exact Hessian of ½·Σ eᵢ².
    fn gradient_hessian(&self, p: &DVector<f64>) -> Option<(DVector<f64>, DMatrix<f64>)> {
        let (e, jac) = self.linearise(p);
        let g = jac.tr_mul(&e);
        let mut h = jac.tr_mul(&jac);
        for i in 0..self.q.len() {
            let d = self.distance(i, p);
            if d <= 0.0 {
                return None;
            }
            let f = e[i] / d;
            for a in 0..D {
                for b in 0..D {
                    let delta = if a == b { 1.0 } else { 0.0 };
                    h[(a, b)] += f * (delta - jac[(i, a)] * jac[(i, b)]);
                }
            }
        }
        Some((g, h))
    }

    fn small_step(delta: &DVector<f64>, p: &DVector<f64>) -> bool {
        delta.norm() <= STEP_TOL * (1.0 + p.norm())
    }

    /// Levenberg–Marquardt from `p0`, then Newton polish.
    fn run(&self, p0: DVector<f64>) -> Option<Run> {
        let mut p = p0;
        let mut cost = self.cost(&p);
        if !cost.is_finite() {
            return None;
        }
        let mut mu = 1e-4;
        let mut converged = false;
        let mut iterations = 0;
        for _ in 0..MAX_LM_ITERATIONS {
            iterations += 1;
            let (e, jac) = self.linearise(&p);
            let svd = jac.try_svd(true, true, f64::EPSILON, 10_000)?;
            let (u, v_t) = (svd.u.as_ref()?, svd.v_t.as_ref()?);
            let g = u.tr_mul(&e);
            let s = &svd.singular_values;
            let s_max = s.max();
            if s_max.is_nan() || s_max <= 0.0 {
                return None;
            }
            let mut accepted = None;
            loop {
                let lambda = mu * s_max * s_max;
                let mut z = DVector::zeros(s.len());
                for i in 0..s.len() {
                    let den = s[i] * s[i] + lambda;
                    if den > 0.0 {
                        z[i] = -s[i] * g[i] / den;
                    }
                }
                let delta = v_t.tr_mul(&z);
                let trial = &p + &delta;
                let c = self.cost(&trial);
                if c.is_finite() && c < cost {
                    // Reduction of |e|² predicted by the linear model.
                    let predicted: f64 = (0..s.len())
                        .map(|i| -(2.0 * g[i] + s[i] * z[i]) * s[i] * z[i])
                        .sum();
                    accepted = Some((delta, trial, c, predicted));
                    mu = if mu < 1e-12 { 0.0 } else { mu * 0.1 };
                    break;
                }
                if Self::small_step(&delta, &p) {
                    break;
                }
                mu = if mu == 0.0 { 1e-10 } else { mu * 10.0 };
                if mu > 1e20 {
                    break;
                }
            }
            match accepted {
                None => {
                    // No step reduces the cost: at the minimum to rounding.
                    converged = true;
                    break;
                }
                Some((delta, trial, c, predicted)) => {
                    let small = Self::small_step(&delta, &p);
                    // Actual and predicted reductions both negligible: the remaining digits
                    // are the Newton polish's.
                    let flat =
                        cost - c <= REDUCTION_TOL * cost && predicted <= REDUCTION_TOL * cost;
                    p = trial;
                    cost = c;
                    if small || flat {
                        converged = true;
                        break;
                    }
                }
            }
            // Runaway towards an infinite radius (straight or flat points).
            if p.amax() > MAX_RADIUS_RATIO {
                break;
            }
        }
        // Newton polish with the exact Hessian. Near the minimum the change of the cost is
        // below its rounding, so steps are judged by their size instead: accepted while they
        // contract (quadratic convergence), stopped at the rounding floor.
        let mut previous = f64::INFINITY;
        for _ in 0..MAX_NEWTON_ITERATIONS {
            if p.amax() > MAX_RADIUS_RATIO {
                break;
            }
            let Some((g, h)) = self.gradient_hessian(&p) else {
                break;
            };
            let Some(chol) = h.cholesky() else {
                break;
            };
            let delta = -chol.solve(&g);
            let size = delta.norm();
            if !(size.is_finite() && size < previous) {
                break;
            }
            let trial = &p + &delta;
            let c = self.cost(&trial);
            if !c.is_finite() || (c > cost && size > NEWTON_TRUST * (1.0 + p.norm())) {
                break;
            }
            iterations += 1;
            let small = Self::small_step(&delta, &p);
            if size <= NEWTON_TRUST * (1.0 + p.norm()) {
                converged = true;
            }
            p = trial;
            cost = c.min(cost);
            previous = size;
            if small {
                break;
            }
        }
        Some(Run {
            params: p,
            cost,
            iterations,
            converged,
        })
    }
}

/// Solves the radial problem from the algebraic starts; `scale` converts radii back to mm
/// for error messages.
fn radial_fit<const D: usize>(
    q: &[[f64; D]],
    fixed: Option<f64>,
    kind: ShapeKind,
    scale: f64,
) -> Result<RadialSolution, ShapeError> {
    let problem = Radial { q, fixed };
    let starts: Vec<(Vec<f64>, f64)> = [kasa(q), pratt(q)].into_iter().flatten().collect();
    let mut best: Option<Run> = None;
    let mut iterations = 0;
    for (c, r) in &starts {
        let mut p0 = DVector::from_column_slice(c);
        if fixed.is_none() {
            p0 = p0.push(*r);
        }
        let Some(run) = problem.run(p0) else {
            continue;
        };
        iterations += run.iterations;
        let better = match &best {
            None => true,
            Some(b) => {
                (run.converged && !b.converged)
                    || (run.converged == b.converged && run.cost < b.cost)
            }
        };
        if better {
            best = Some(run);
        }
    }
    let too_flat = |radius: f64| ShapeError::TooFlat {
        kind,
        radius: radius * scale,
        extent: scale,
    };
    let Some(best) = best else {
        // No algebraic start: the points are on a line or plane to within rounding.
        let r = starts.iter().map(|s| s.1).fold(f64::INFINITY, f64::min);
        return Err(too_flat(r));
    };
    let radius = problem.radius(&best.params);
    let center_norm = best.params.rows(0, D).norm();
    if fixed.is_none() && (radius.is_nan() || radius.abs() > MAX_RADIUS_RATIO) {
        return Err(too_flat(radius.abs()));
    }
    if center_norm.is_nan() || center_norm > 1e3 * MAX_RADIUS_RATIO || !best.converged {
        return Err(ShapeError::NoConvergence { kind, iterations });
    }
    // A negative radius is the same circle with all residuals' signs flipped; the cost is
    // symmetric, but report the geometric (positive) one.
    let mut params = best.params.clone();
    if fixed.is_none() && radius < 0.0 {
        params[D] = -radius;
    }
    Ok(RadialSolution {
        center: params.rows(0, D).iter().copied().collect(),
        radius: problem.radius(&params),
        residuals: problem.residuals(&params),
        iterations,
    })
}

/// Kåsa's algebraic fit: least squares |q|² = 2·c·q + k; returns (c, r).
fn kasa<const D: usize>(q: &[[f64; D]]) -> Option<(Vec<f64>, f64)> {
    let n = q.len();
    let a = DMatrix::from_fn(n, D + 1, |i, j| if j < D { 2.0 * q[i][j] } else { 1.0 });
    let b = DVector::from_fn(n, |i, _| q[i].iter().map(|x| x * x).sum::<f64>());
    let svd = a.try_svd(true, true, f64::EPSILON, 10_000)?;
    let smax = svd.singular_values.max();
    let x = svd.solve(&b, 1e-12 * smax).ok()?;
    let c: Vec<f64> = x.iter().take(D).copied().collect();
    let r2 = x[D] + c.iter().map(|v| v * v).sum::<f64>();
    (r2 > 0.0 && r2.is_finite() && c.iter().all(|v| v.is_finite())).then(|| (c, r2.sqrt()))
}

/// Pratt's algebraic fit (Chernov's SVD formulation); returns (c, r).
fn pratt<const D: usize>(q: &[[f64; D]]) -> Option<(Vec<f64>, f64)> {
    let n = q.len();
    let m = D + 2;
    let z = DMatrix::from_fn(n, m, |i, j| match j {
        0 => q[i].iter().map(|x| x * x).sum::<f64>(),
        j if j <= D => q[i][j - 1],
        _ => 1.0,
    });
    let svd = z.try_svd(false, true, f64::EPSILON, 10_000)?;
    let v_t = svd.v_t.as_ref()?;
    let s = &svd.singular_values;
    if s.len() < m {
        return None;
    }
    let (imin, smin) = s.argmin();
    let a: DVector<f64> = if smin <= 1e-12 * s.max() {
        // Exact fit: the null vector of Z.
        v_t.row(imin).transpose()
    } else {
        let w = v_t.transpose() * DMatrix::from_diagonal(s) * v_t;
        let mut ninv = DMatrix::zeros(m, m);
        ninv[(0, m - 1)] = -0.5;
        ninv[(m - 1, 0)] = -0.5;
        for j in 1..=D {
            ninv[(j, j)] = 1.0;
        }
        let mat = &w * ninv * &w;
        let sym = (&mat + mat.transpose()) * 0.5;
        let eig = sym.try_symmetric_eigen(f64::EPSILON, 10_000)?;
        // W·N⁻¹·W has the inertia of N⁻¹: exactly one negative eigenvalue. The solution is
        // the eigenvector of the second smallest (the smallest non-negative one in exact
        // arithmetic; rounding may make it slightly negative for exact data).
        let mut order: Vec<usize> = (0..m).collect();
        order.sort_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]));
        let i = order[1];
        let e = eig.eigenvectors.column(i).into_owned();
        w.lu().solve(&e)?
    };
    let a0 = a[0];
    if a0.is_nan() || a0 == 0.0 {
        return None;
    }
    let c: Vec<f64> = (1..=D).map(|j| -a[j] / (2.0 * a0)).collect();
    let disc = (1..=D).map(|j| a[j] * a[j]).sum::<f64>() - 4.0 * a0 * a[m - 1];
    let r = disc.sqrt() / (2.0 * a0.abs());
    (r > 0.0 && r.is_finite() && c.iter().all(|v| v.is_finite())).then_some((c, r))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64, tol: f64) -> bool {
        (a - b).abs() <= tol * (1.0 + b.abs())
    }

    /// A deterministic pseudo-random sequence in [−1, 1).
    fn noise(seed: u64) -> impl FnMut() -> f64 {
        let mut x = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
        move || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            (x >> 11) as f64 / (1u64 << 52) as f64 - 1.0
        }
    }

    fn sphere_points(c: Vec3, r: f64, n: usize, noise_amp: f64) -> Vec<Vec3> {
        let mut rnd = noise(7);
        (0..n)
            .map(|i| {
                // Fibonacci sphere.
                let z = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
                let phi = i as f64 * 2.399_963_229_728_653;
                let rho = (1.0 - z * z).sqrt();
                let dir = Vec3::new(rho * phi.cos(), rho * phi.sin(), z);
                c + dir * (r + noise_amp * rnd())
            })
            .collect()
    }

    #[test]
    fn sphere_exact_and_fixed() {
        let c = Vec3::new(120.5, -40.25, 310.0);
        let pts = sphere_points(c, 12.7, 50, 0.0);
        let f = fit_sphere(&pts).unwrap();
        assert!((f.center - c).norm() < 1e-11, "{:?}", f.center);
        assert!(close(f.radius, 12.7, 1e-13));
        assert!(close(f.diameter, 25.4, 1e-13));
        assert!(f.rms < 1e-11 && f.max_abs_residual() < 1e-11);
        let g = fit_sphere_fixed_radius(&pts, 12.7).unwrap();
        assert!((g.center - c).norm() < 1e-11);
        assert_eq!(g.radius, 12.7);
    }

    #[test]
    fn sphere_cap_with_noise_is_unbiased() {
        // A 60° cap with symmetric noise: the fit stays close to the truth.
        let c = Vec3::new(1.0, 2.0, 3.0);
        let mut rnd = noise(3);
        let pts: Vec<Vec3> = (0..400)
            .map(|i| {
                let z = 1.0 - 0.5 * (i as f64 + 0.5) / 400.0;
                let phi = i as f64 * 2.399_963_229_728_653;
                let rho = (1.0 - z * z).sqrt();
                c + Vec3::new(rho * phi.cos(), rho * phi.sin(), z) * (5.0 + 1e-4 * rnd())
            })
            .collect();
        let f = fit_sphere(&pts).unwrap();
        assert!((f.center - c).norm() < 1e-3, "{:?}", f.center);
        assert!((f.radius - 5.0).abs() < 1e-3);
        assert!(f.rms > 0.0 && f.rms < 1e-4);
        // Residuals are the signed orthogonal distances.
        for (p, e) in pts.iter().zip(&f.residuals) {
            assert!(close((p - f.center).norm() - f.radius, *e, 1e-12));
        }
    }

    #[test]
    fn circle_tilted_exact() {
        let c = Vec3::new(10.0, 20.0, -5.0);
        let n = Vec3::new(1.0, -2.0, 0.5).normalize();
        let a = n.cross(&Vec3::x()).normalize();
        let b = n.cross(&a);
        let pts: Vec<Vec3> = (0..7)
            .map(|i| {
                let t = 0.3 + i as f64 * 0.4;
                c + (a * t.cos() + b * t.sin()) * 25.0
            })
            .collect();
        let f = fit_circle(&pts).unwrap();
        assert!((f.center - c).norm() < 1e-11);
        assert!(close(f.radius, 25.0, 1e-13));
        assert!(f.normal.dot(&n).abs() > 1.0 - 1e-14);
        // Sign convention: largest-magnitude component (−2/…, y) positive.
        assert!(f.normal.y > 0.0);
        assert!(f.plane_rms < 1e-12);
        let g = fit_circle_fixed_radius(&pts, 25.0).unwrap();
        assert!((g.center - c).norm() < 1e-11);
        assert_eq!(g.diameter, 50.0);
    }

    #[test]
    fn circle_three_points_and_signed_residuals() {
        let pts = [
            Vec3::new(1.0, 0.0, 0.0),
            Vec3::new(0.0, 1.0, 0.0),
            Vec3::new(-1.0, 0.0, 0.0),
        ];
        let f = fit_circle(&pts).unwrap();
        assert!(f.center.norm() < 1e-14);
        assert!(close(f.radius, 1.0, 1e-14));
        assert_eq!(f.normal, Vec3::z());
        // Fixed radius larger than the true one, points all round: all fall 0.5 inside.
        let square = [pts[0], pts[1], pts[2], Vec3::new(0.0, -1.0, 0.0)];
        let g = fit_circle_fixed_radius(&square, 1.5).unwrap();
        assert!(g.center.norm() < 1e-14);
        assert!(g.residuals.iter().all(|e| close(*e, -0.5, 1e-14)));
        assert!(close(g.rms, 0.5, 1e-14));
        let h = fit_circle(&square).unwrap();
        assert!(h.residuals.iter().all(|e| e.abs() < 1e-15));
    }

    #[test]
    fn line_fit() {
        let p0 = Vec3::new(1.0, 2.0, 3.0);
        let d = Vec3::new(-0.2, 0.3, -0.9).normalize();
        let off = d.cross(&Vec3::x()).normalize();
        let pts: Vec<Vec3> = (0..11)
            .map(|i| {
                let t = i as f64 - 5.0;
                p0 + d * t + off * if i % 2 == 0 { 0.01 } else { -0.01 }
            })
            .collect();
        let f = fit_line(&pts).unwrap();
        assert!(f.direction.dot(&d).abs() > 1.0 - 1e-6);
        assert!(f.direction.z > 0.0, "largest component positive");
        assert!(close(f.direction.norm(), 1.0, 1e-15));
        assert!(f.residuals.iter().all(|e| *e >= 0.0));
        assert!((f.rms - 0.01).abs() < 1e-4);
        // Two points are enough.
        let two = fit_line(&[Vec3::zeros(), Vec3::new(0.0, 3.0, 4.0)]).unwrap();
        assert!((two.direction - Vec3::new(0.0, 0.6, 0.8)).norm() < 1e-15);
        assert!(two.rms < 1e-15);
    }

    #[test]
    fn plane_fit() {
        let n = Vec3::new(0.1, -0.2, -1.0).normalize();
        let c = Vec3::new(5.0, 6.0, 7.0);
        let a = n.cross(&Vec3::x()).normalize();
        let b = n.cross(&a);
        let pts: Vec<Vec3> = (0..25)
            .map(|i| {
                let (x, y) = ((i % 5) as f64 - 2.0, (i / 5) as f64 - 2.0);
                let h = if (i % 5 + i / 5) % 2 == 0 {
                    0.002
                } else {
                    -0.002
                };
                c + a * x * 10.0 + b * y * 10.0 + n * h
            })
            .collect();
        let f = fit_plane(&pts).unwrap();
        assert!(f.normal.dot(&n).abs() > 1.0 - 1e-9);
        assert!(f.normal.z > 0.0, "largest component positive");
        assert!((f.centroid - c - n * 0.00008).norm() < 1e-3);
        assert!(f.max_abs_residual() <= 0.0021);
        let sum: f64 = f.residuals.iter().sum();
        assert!(
            sum.abs() < 1e-12,
            "signed residuals sum to 0 about the centroid"
        );
    }

    #[test]
    fn too_few_points() {
        let p = [Vec3::zeros(), Vec3::x(), Vec3::y()];
        assert_eq!(
            fit_sphere(&p).unwrap_err(),
            ShapeError::TooFewPoints {
                kind: ShapeKind::Sphere,
                needed: 4,
                got: 3
            }
        );
        let e = fit_circle(&p[..2]).unwrap_err();
        assert!(e.to_string().contains("at least 3 points, got 2"), "{e}");
        assert!(matches!(
            fit_line(&p[..1]),
            Err(ShapeError::TooFewPoints { needed: 2, .. })
        ));
        assert!(matches!(
            fit_plane(&[]),
            Err(ShapeError::TooFewPoints {
                needed: 3,
                got: 0,
                ..
            })
        ));
    }

    #[test]
    fn degenerate_sets() {
        let line: Vec<Vec3> = (0..6)
            .map(|i| Vec3::new(1.0, 2.0, 3.0) * i as f64)
            .collect();
        let e = fit_circle(&line).unwrap_err();
        assert_eq!(
            e,
            ShapeError::Collinear {
                kind: ShapeKind::Circle
            }
        );
        assert!(e
            .to_string()
            .contains("scan more of the circle's circumference"));
        assert!(matches!(
            fit_plane(&line),
            Err(ShapeError::Collinear { .. })
        ));
        let flat: Vec<Vec3> = (0..8)
            .map(|i| Vec3::new((i as f64).cos(), (i as f64).sin(), 4.0))
            .collect();
        let e = fit_sphere(&flat).unwrap_err();
        assert!(matches!(e, ShapeError::Coplanar { .. }));
        assert!(e.to_string().contains("coplanar"));
        let same = vec![Vec3::new(0.1, 0.2, 0.3); 5];
        for e in [
            fit_circle(&same).unwrap_err(),
            fit_sphere(&same).unwrap_err(),
            fit_line(&same).unwrap_err(),
            fit_plane(&same).unwrap_err(),
        ] {
            assert!(
                matches!(e, ShapeError::AllIdentical { count: 5, .. }),
                "{e}"
            );
        }
        // A nearly straight arc: bulge 1e-9 over a length of 2.
        let arc: Vec<Vec3> = (0..5)
            .map(|i| {
                let x = i as f64 * 0.5 - 1.0;
                Vec3::new(x, 1e-9 * (1.0 - x * x), 0.0)
            })
            .collect();
        assert!(matches!(
            fit_circle(&arc),
            Err(ShapeError::TooFlat { .. } | ShapeError::Collinear { .. })
        ));
        assert!(fit_circle_fixed_radius(&pts_unit_circle(), 0.0).is_err());
        assert!(fit_sphere_fixed_radius(&line, f64::NAN).is_err());
    }

    fn pts_unit_circle() -> Vec<Vec3> {
        (0..4)
            .map(|i| {
                let t = i as f64;
                Vec3::new(t.cos(), t.sin(), 0.0)
            })
            .collect()
    }

    #[test]
    fn non_finite_points() {
        let mut p = pts_unit_circle();
        p[2].y = f64::NAN;
        let e = fit_circle(&p).unwrap_err();
        assert_eq!(e, ShapeError::NonFinite { index: 2 });
        assert!(e.to_string().starts_with("point 3 "));
        p[2].y = f64::INFINITY;
        assert!(matches!(
            fit_plane(&p),
            Err(ShapeError::NonFinite { index: 2 })
        ));
        assert!(matches!(fit_line(&p), Err(ShapeError::NonFinite { .. })));
        p.push(Vec3::z());
        assert!(matches!(fit_sphere(&p), Err(ShapeError::NonFinite { .. })));
        let huge: Vec<Vec3> = pts_unit_circle().iter().map(|v| v * 1e300).collect();
        assert_eq!(fit_circle(&huge).unwrap_err(), ShapeError::OutOfRange);
    }

    #[test]
    fn parser() {
        let text = "# ring gauge\n3\n1 2 3\n\n4,5,6  # second\n 7 ,\t8, 9\n";
        let p = parse_points(text).unwrap();
        assert_eq!(
            p,
            vec![
                Vec3::new(1.0, 2.0, 3.0),
                Vec3::new(4.0, 5.0, 6.0),
                Vec3::new(7.0, 8.0, 9.0)
            ]
        );
        // No count line.
        assert_eq!(
            parse_points("1e-3 -2 +3.5\r\n").unwrap(),
            vec![Vec3::new(1e-3, -2.0, 3.5)]
        );
        assert!(parse_points("").unwrap().is_empty());
        assert_eq!(
            parse_points("4\n1 2 3\n4 5 6\n").unwrap_err(),
            ShapeError::CountMismatch {
                line: 1,
                declared: 4,
                found: 2
            }
        );
        let e = parse_points("1 2 3\n4 5\n").unwrap_err();
        assert!(matches!(e, ShapeError::Parse { line: 2, .. }), "{e}");
        assert!(
            e.to_string().starts_with("line 2: expected 3 numbers"),
            "{e}"
        );
        let e = parse_points("1 2 3\n4 x 6\n").unwrap_err();
        assert!(e.to_string().contains("line 2: `x` is not a number"), "{e}");
        let e = parse_points("# c\n\n1 2 nan\n").unwrap_err();
        assert!(matches!(e, ShapeError::Parse { line: 3, .. }), "{e}");
        // A count is accepted only on the first data row.
        assert!(matches!(
            parse_points("1 2 3\n5\n"),
            Err(ShapeError::Parse { line: 2, .. })
        ));
        assert!(matches!(
            parse_points("3.5\n1 2 3\n"),
            Err(ShapeError::Parse { line: 1, .. })
        ));
        assert!(parse_points("1 2 3 4\n").is_err());
        // x y rows: a profile in the XY plane; the first row fixes the width.
        assert_eq!(
            parse_points("# profile\n1, 2\n3 4\n").unwrap(),
            vec![Vec3::new(1.0, 2.0, 0.0), Vec3::new(3.0, 4.0, 0.0)]
        );
        let e = parse_points("1 2\n3 4 5\n").unwrap_err();
        assert!(
            e.to_string()
                .starts_with("line 2: expected 2 numbers (x y, as the rows before)"),
            "{e}"
        );
    }

    #[test]
    fn kinds() {
        assert_eq!("Sphere".parse::<ShapeKind>().unwrap(), ShapeKind::Sphere);
        let e = "cone".parse::<ShapeKind>().unwrap_err();
        assert_eq!(
            e.to_string(),
            "unknown shape kind `cone`: expected one of circle, sphere, line, plane"
        );
    }
}
