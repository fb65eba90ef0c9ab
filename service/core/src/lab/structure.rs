//! Structure left in a residual that no library effect explains, offered as the terms of a
//! `custom` effect.
//!
//! The residual e_i (deviation of point i along its artifact's gradient g_i) is first freed of
//! the artifact placements: with A the placement Jacobian (one block per feature), every
//! column c below and e itself are replaced by their projection P c = c − A (AᵀA)⁺ Aᵀ c, so a
//! structure is only what placements cannot absorb. For projected columns C the fit is
//! t = (CᵀC)⁻¹ Cᵀ e, and the structure explains the fraction tᵀCᵀe / eᵀe of the residual.
//! Three kinds are searched:
//!
//! * `period` along each machine axis a (an encoder's cyclic error):
//!   e_i ≈ g_ia·(s·sin(2π f x_ia) + c·cos(2π f x_ia)), x_ia the scale reading.
//!   A periodogram over frequencies f from 1/min(span/2, 200 mm) to 1/0.5 mm with a step of
//!   1/(4·span) (span = travel covered along the axis, so no peak of width ~1/span falls
//!   between grid points), then the best frequency is refined by golden-section search on the
//!   reduction tᵀCᵀe within ±one step (nonlinear least squares in the period; the linear
//!   amplitudes s, c are eliminated by the inner fit). Custom terms `a:sin(2*pi*a/P)`,
//!   `a:cos(2*pi*a/P)`.
//! * `reversal` of each axis (backlash): e_i ≈ g_ia·b·sign(v_ia) (|v| > 0.01 mm/s).
//!   Custom term `a:sign(va)`.
//! * `probe_direction` (probe lobing, e.g. the 3θ of a kinematic probe): an error along the
//!   surface normal n that depends on the direction the stylus is deflected in,
//!   e_i ≈ (g_i·n_i)·(c·cos kφ_i + s·sin kφ_i), k = 2…8 (k = 1 and 0 are placements),
//!   with n_i = (du, dv, 0)/defl and φ_i = atan2(dv, du), du, dv the deflection in probe
//!   axes: the corrector's normal is the deflection direction (out of the material), so
//!   this is the normal for a head at A1 = A2 = 0 (probe axes = machine axes); with a rotated
//!   head it is the probe-frame direction, which is what a probe's lobing follows, and the
//!   terms below act along the unrotated direction — the fitted columns are computed exactly
//!   as the custom effect evaluates its terms, so what is reported is what the terms fit.
//!   Custom terms `x:du/defl*cos(k*atan2(dv,du))`, `y:dv/defl*cos(…)`, and the same with
//!   sin; one structure is the four terms with coefficients (c, c, s, s).
//!   Scan-angle harmonics (the angle of the point on a circle) are not searched separately:
//!   on circles the scan angle and the probing direction are the same angle (up to π for
//!   bores), so they are found as `probe_direction`.
//!
//! Structures explaining at most 5 % of the residual are dropped, as is one whose fitted
//! component is mostly (R² > 0.5) reproduced by a stronger structure's terms (e.g. a period
//! along x that imitates a lobing harmonic on rings); at most four are kept, strongest first.
//!
//! Source idea: the periodogram of unevenly sampled data as a least-squares fit of a sinusoid
//! per trial frequency (Lomb–Scargle, generalised here to a gradient-weighted regressor and
//! placement nuisance columns), refined by a one-dimensional search of the nonlinear
//! parameter (variable projection, Golub–Pereyra); probe lobing as the harmonics of the
//! probing direction that kinematic touch-trigger and scanning probes show (pre-travel
//! variation, ISO 10360-5 form tests).

use super::dataset::axis_span;
use super::dataset::Dataset;
use super::fit::{golden_max, nuisance_row, ArtifactFit, Normal};
use super::types::Prepared;
use super::LabError;
use crate::sample::Axis;
use nalgebra::{DMatrix, DVector};
use serde::Serialize;
use std::f64::consts::TAU;

/// Structure left in the residual that no candidate explains.
#[derive(Debug, Clone, Serialize)]
pub struct Structure {
    /// What the residual follows: `period` along an axis, `reversal` of an axis,
    /// `probe_direction` (a harmonic of the probing direction, along the normal).
    pub kind: String,
    /// Axis (coordinate and error direction); `normal` for `probe_direction`.
    pub axis: String,
    /// Period, mm (periodic structure).
    pub period_mm: Option<f64>,
    /// Amplitude of the error along the axis (or the normal), µm.
    pub amplitude_um: f64,
    /// Fraction of the residual's sum of squares it explains.
    pub explained: f64,
    /// Terms of a `custom` effect built from it (`AXIS:EXPR`).
    pub custom_terms: Vec<String>,
    /// Harmonic order k of the probing direction (`probe_direction`).
    pub harmonic: Option<u32>,
    /// The residual against the structure's coordinate with the fitted structure over it
    /// (periodic and probing-direction structure; absent for a reversal).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub profile: Option<Profile>,
}

/// The residual seen along a structure's coordinate: each point's residual (placements taken
/// out) divided by how much of the error direction it sees (its gradient along the axis, or
/// along the probing direction; points that see less than half of it are left out), averaged
/// in bins of the coordinate, and the fitted structure at the bins' centres.
#[derive(Debug, Clone, Serialize)]
pub struct Profile {
    /// The coordinate with its unit (`x, mm`; `probing direction φ, °`).
    pub coordinate: String,
    /// Bin centres.
    pub x: Vec<f64>,
    /// Mean residual along the error direction in each bin, µm.
    pub measured_um: Vec<f64>,
    /// The fitted structure there, µm.
    pub fitted_um: Vec<f64>,
    /// Points in each bin.
    pub points: Vec<usize>,
}

/// Least share of the error direction a point must see to enter a [`Profile`].
const PROFILE_MIN_GAIN: f64 = 0.5;
/// Most bins of a profile.
const PROFILE_MAX_BINS: usize = 600;

/// Bins `(x, e/g)` samples over `[lo, hi)` in `nbins` bins and evaluates `fitted` (mm) at each
/// bin with data. Empty bins are left out.
fn profile(
    coordinate: String,
    samples: impl Iterator<Item = (f64, f64, f64)>,
    (lo, hi): (f64, f64),
    nbins: usize,
    fitted: impl Fn(f64) -> f64,
) -> Option<Profile> {
    let nbins = nbins.clamp(8, PROFILE_MAX_BINS);
    let w = (hi - lo) / nbins as f64;
    if !(w > 0.0 && w.is_finite()) {
        return None;
    }
    let mut acc = vec![(0.0, 0usize); nbins];
    for (x, e, g) in samples {
        if g.abs() < PROFILE_MIN_GAIN || !(x.is_finite() && e.is_finite()) || x < lo || x >= hi {
            continue;
        }
        let b = &mut acc[(((x - lo) / w) as usize).min(nbins - 1)];
        b.0 += e / g;
        b.1 += 1;
    }
    let mut p = Profile {
        coordinate,
        x: vec![],
        measured_um: vec![],
        fitted_um: vec![],
        points: vec![],
    };
    for (k, (sum, n)) in acc.into_iter().enumerate() {
        if n > 0 {
            let xc = lo + (k as f64 + 0.5) * w;
            p.x.push(xc);
            p.measured_um.push(sum / n as f64 * 1e3);
            p.fitted_um.push(fitted(xc) * 1e3);
            p.points.push(n);
        }
    }
    (p.x.len() >= 4).then_some(p)
}

/// The profile of a found structure: along its axis for a period (12 bins a period, at most
/// 50 periods from the start of the span), along the probing direction for a harmonic of it.
fn profile_of(ds: &Dataset, nu: &Nuisance, e: &[f64], f: &Found) -> Option<Profile> {
    let coef = f.coef.clone();
    match (f.s.kind.as_str(), f.s.period_mm, f.s.harmonic) {
        ("period", Some(p), _) => {
            let a = Axis::ALL.into_iter().find(|a| a.name() == f.s.axis)?;
            let ai = a.index();
            let (lo, hi) = axis_span(ds, a);
            let hi = hi.min(lo + 50.0 * p);
            let w = TAU / p;
            profile(
                format!("{}, mm", a.name()),
                (0..ds.points.len())
                    .filter(|&i| nu.used(i))
                    .map(|i| (ds.points[i].ctx.scale[ai], e[i], nu.art.grad[i][ai])),
                (lo, hi + 1e-9),
                ((hi - lo) / p * 12.0).ceil() as usize,
                move |x| coef[0] * (w * x).sin() + coef[1] * (w * x).cos(),
            )
        }
        ("probe_direction", _, Some(k)) => {
            let k = k as f64;
            profile(
                "probing direction φ, °".into(),
                (0..ds.points.len())
                    .filter(|&i| nu.used(i))
                    .filter_map(|i| {
                        let (nx, ny, phi) = probing_direction(&ds.points[i].ctx)?;
                        let g = nu.art.grad[i];
                        Some((phi.to_degrees(), e[i], g.x * nx + g.y * ny))
                    }),
                (-180.0, 180.0),
                (k as usize * 12).max(72),
                move |deg| {
                    let phi = deg.to_radians();
                    coef[0] * (k * phi).cos() + coef[1] * (k * phi).sin()
                },
            )
        }
        _ => None,
    }
}

/// Shortest period searched, mm.
const PERIOD_MIN_MM: f64 = 0.5;
/// Longest period searched, mm (also at most half the span).
const PERIOD_MAX_MM: f64 = 200.0;
/// Harmonics of the probing direction searched.
const HARMONICS: std::ops::RangeInclusive<u32> = 2..=8;
/// Smallest fraction of the residual a structure must explain.
const MIN_EXPLAINED: f64 = 0.05;
/// A structure whose component a stronger one reproduces to this R² is the same structure.
const SAME_R2: f64 = 0.5;
/// Most structures reported.
const MAX_STRUCTURES: usize = 4;

/// The placements as nuisance columns: projects them out of residuals and regressors.
struct Nuisance<'a> {
    art: &'a ArtifactFit,
    /// Placement Jacobian row of each point (empty when its feature has no fit).
    rows: Vec<Vec<(usize, f64)>>,
    /// (AᵀA)⁺.
    cov: DMatrix<f64>,
}

impl<'a> Nuisance<'a> {
    fn new(ds: &Dataset, art: &'a ArtifactFit) -> Self {
        let mut ne = Normal::new(art.n_cols);
        let mut rows = vec![vec![]; ds.points.len()];
        for (i, p) in ds.points.iter().enumerate() {
            if art.features[p.feature].is_some() {
                nuisance_row(art, p, &p.surface, &mut rows[i]);
                ne.add(&[], &rows[i], 0.0);
            }
        }
        let cov = ne.solve().cov;
        Nuisance { art, rows, cov }
    }
    /// Point i takes part (its feature was fitted).
    fn used(&self, i: usize) -> bool {
        !self.rows[i].is_empty()
    }
    /// Adds w·(row of point i) to `acc` (accumulates Aᵀc).
    #[inline]
    fn accumulate(&self, i: usize, w: f64, acc: &mut DVector<f64>) {
        for &(c, v) in &self.rows[i] {
            acc[c] += v * w;
        }
    }
    /// uᵀ(AᵀA)⁺v.
    fn quad(&self, u: &DVector<f64>, v: &DVector<f64>) -> f64 {
        if u.is_empty() {
            return 0.0;
        }
        u.dot(&(&self.cov * v))
    }
    /// P c (zero on points not used).
    fn project(&self, c: &[f64]) -> Vec<f64> {
        let mut atc = DVector::zeros(self.art.n_cols);
        for (i, &ci) in c.iter().enumerate() {
            self.accumulate(i, ci, &mut atc);
        }
        let x = &self.cov * atc;
        (0..c.len())
            .map(|i| {
                if self.used(i) {
                    c[i] - self.rows[i].iter().map(|&(k, v)| v * x[k]).sum::<f64>()
                } else {
                    0.0
                }
            })
            .collect()
    }
}

/// A structure with what it was fitted from.
struct Found {
    s: Structure,
    /// Projected columns.
    cols: Vec<Vec<f64>>,
    /// Fitted coefficients: the residual's component is Σ coef_j·cols_j.
    coef: Vec<f64>,
}

impl Found {
    fn component(&self) -> Vec<f64> {
        let n = self.cols[0].len();
        (0..n)
            .map(|i| {
                self.cols
                    .iter()
                    .zip(&self.coef)
                    .map(|(c, t)| c[i] * t)
                    .sum()
            })
            .collect()
    }
}

/// Least squares of `e` on (projected) columns: (reduction of the sum of squares, coefficients).
/// None when a column is (nearly) absorbed by the placements or the columns are collinear.
fn fit_cols(cols: &[Vec<f64>], raw_norm2: &[f64], e: &[f64]) -> Option<(f64, Vec<f64>)> {
    let k = cols.len();
    let mut g = DMatrix::<f64>::zeros(k, k);
    let mut b = DVector::<f64>::zeros(k);
    for a in 0..k {
        b[a] = dot(&cols[a], e);
        for c in 0..=a {
            g[(a, c)] = dot(&cols[a], &cols[c]);
            g[(c, a)] = g[(a, c)];
        }
        if g[(a, a)].is_nan() || g[(a, a)] <= 1e-6 * raw_norm2[a] {
            return None;
        }
    }
    let (red, t) = solve_small(g, b)?;
    Some((red, t.iter().copied().collect()))
}

/// Solves G t = b for a small symmetric positive definite G; (tᵀb, t).
fn solve_small(g: DMatrix<f64>, b: DVector<f64>) -> Option<(f64, DVector<f64>)> {
    let d: Vec<f64> = (0..g.nrows()).map(|i| g[(i, i)].sqrt()).collect();
    if d.iter().any(|x| x.is_nan() || *x <= 0.0) {
        return None;
    }
    // Collinear columns: the scaled Gram matrix must be well conditioned.
    let scaled = DMatrix::from_fn(g.nrows(), g.ncols(), |i, j| g[(i, j)] / (d[i] * d[j]));
    let eig = nalgebra::SymmetricEigen::new(scaled).eigenvalues;
    if eig.iter().cloned().fold(f64::MAX, f64::min) < 1e-6 {
        return None;
    }
    let t = g.cholesky()?.solve(&b);
    let red = t.dot(&b);
    (red.is_finite() && t.iter().all(|x| x.is_finite())).then_some((red, t))
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// Fits raw columns to the projected residual and makes a [`Found`] when it explains enough.
fn found(raw: Vec<Vec<f64>>, nu: &Nuisance, e: &[f64], total: f64, s: Structure) -> Option<Found> {
    let raw_norm2: Vec<f64> = raw.iter().map(|c| dot(c, c)).collect();
    let cols: Vec<Vec<f64>> = raw.iter().map(|c| nu.project(c)).collect();
    let (red, coef) = fit_cols(&cols, &raw_norm2, e)?;
    let explained = red / total;
    if !(explained > MIN_EXPLAINED && explained <= 1.0 + 1e-9) {
        return None;
    }
    let amplitude_um = match coef.len() {
        1 => coef[0].abs(),
        _ => coef[0].hypot(coef[1]),
    } * 1e3;
    if !amplitude_um.is_finite() {
        return None;
    }
    Some(Found {
        s: Structure {
            explained,
            amplitude_um,
            ..s
        },
        cols,
        coef,
    })
}

/// Sums of a two-column (sin, cos) fit, accumulated point by point.
struct SinCos {
    ss: f64,
    sc: f64,
    cc: f64,
    se: f64,
    ce: f64,
    as_: DVector<f64>,
    ac: DVector<f64>,
}

impl SinCos {
    fn new(n_cols: usize) -> Self {
        SinCos {
            ss: 0.0,
            sc: 0.0,
            cc: 0.0,
            se: 0.0,
            ce: 0.0,
            as_: DVector::zeros(n_cols),
            ac: DVector::zeros(n_cols),
        }
    }
    #[inline]
    fn add(&mut self, nu: &Nuisance, i: usize, s: f64, c: f64, e: f64) {
        self.ss += s * s;
        self.sc += s * c;
        self.cc += c * c;
        self.se += s * e;
        self.ce += c * e;
        nu.accumulate(i, s, &mut self.as_);
        nu.accumulate(i, c, &mut self.ac);
    }
    /// Reduction of the sum of squares by the projected columns (0 when degenerate).
    fn reduction(&self, nu: &Nuisance) -> f64 {
        let a11 = self.ss - nu.quad(&self.as_, &self.as_);
        let a12 = self.sc - nu.quad(&self.as_, &self.ac);
        let a22 = self.cc - nu.quad(&self.ac, &self.ac);
        let det = a11 * a22 - a12 * a12;
        if !(a11 > 1e-6 * self.ss && a22 > 1e-6 * self.cc && det > 1e-9 * self.ss * self.cc) {
            return 0.0;
        }
        let (b1, b2) = (self.se, self.ce);
        let red = (a22 * b1 * b1 - 2.0 * a12 * b1 * b2 + a11 * b2 * b2) / det;
        if red.is_finite() {
            red.max(0.0)
        } else {
            0.0
        }
    }
}

/// Points with a fitted feature, and their coordinate and gradient along axis `ai`.
fn axis_points(ds: &Dataset, nu: &Nuisance, ai: usize) -> Vec<(usize, f64, f64)> {
    (0..ds.points.len())
        .filter(|&i| nu.used(i))
        .map(|i| (i, ds.points[i].ctx.scale[ai], nu.art.grad[i][ai]))
        .collect()
}

/// Reduction by a sinusoid of frequency `f` (1/mm) along the axis.
fn period_reduction(pts: &[(usize, f64, f64)], nu: &Nuisance, e: &[f64], f: f64) -> f64 {
    let mut acc = SinCos::new(nu.art.n_cols);
    let w = TAU * f;
    for &(i, x, g) in pts {
        let (s, c) = (w * x).sin_cos();
        acc.add(nu, i, g * s, g * c, e[i]);
    }
    acc.reduction(nu)
}

/// Consecutive points of `pts` whose placement rows are on the same (at most 3) consecutive
/// columns — one feature's: (first, end, first column, columns), and each point's row values
/// padded to 3. `None` when a row is not of that form.
#[allow(clippy::type_complexity)]
fn runs(
    pts: &[(usize, f64, f64)],
    nu: &Nuisance,
) -> Option<(Vec<(usize, usize, usize, usize)>, Vec<[f64; 3]>)> {
    let mut runs: Vec<(usize, usize, usize, usize)> = vec![];
    let mut vals = Vec::with_capacity(pts.len());
    for (q, &(i, _, _)) in pts.iter().enumerate() {
        let row = &nu.rows[i];
        let c0 = row.first().map_or(0, |r| r.0);
        if row.len() > 3 || row.iter().enumerate().any(|(k, r)| r.0 != c0 + k) {
            return None;
        }
        let mut v = [0.0; 3];
        for (k, r) in row.iter().enumerate() {
            v[k] = r.1;
        }
        vals.push(v);
        match runs.last_mut() {
            Some(r) if r.2 == c0 && r.3 == row.len() && r.1 == q => r.1 = q + 1,
            _ => runs.push((q, q + 1, c0, row.len())),
        }
    }
    Some((runs, vals))
}

/// Periodogram on the grid f0 + j·df, j < n: the index of the largest reduction.
fn periodogram(
    pts: &[(usize, f64, f64)],
    nu: &Nuisance,
    e: &[f64],
    f0: f64,
    df: f64,
    n: usize,
) -> usize {
    let mut best = (0.0, 0);
    for (j, red) in reductions(pts, nu, e, (f0, df, n), true)
        .into_iter()
        .enumerate()
    {
        if red > best.0 {
            best = (red, j);
        }
    }
    best.1
}

/// The reduction by a sinusoid at each frequency f0 + j·df, j < n (`fast`: by runs of one
/// feature's points where the rows allow, see [`runs`]; else point by point).
fn reductions(
    pts: &[(usize, f64, f64)],
    nu: &Nuisance,
    e: &[f64],
    (f0, df, n): (f64, f64, usize),
    fast: bool,
) -> Vec<f64> {
    // exp(i 2π f x) by recurrence along the grid, re-anchored now and then against drift.
    let mut z: Vec<(f64, f64)> = vec![(0.0, 0.0); pts.len()];
    let step: Vec<(f64, f64)> = pts
        .iter()
        .map(|&(_, x, _)| {
            let (s, c) = (TAU * df * x).sin_cos();
            (c, s)
        })
        .collect();
    let mut zq = |j: usize, f: f64, q: usize, x: f64| {
        let (c, s) = if j % 256 == 0 {
            let (s, c) = (TAU * f * x).sin_cos();
            (c, s)
        } else {
            let (c0, s0) = z[q];
            let (cd, sd) = step[q];
            (c0 * cd - s0 * sd, s0 * cd + c0 * sd)
        };
        z[q] = (c, s);
        (c, s)
    };
    let mut out = Vec::with_capacity(n);
    let fast = if fast { runs(pts, nu) } else { None };
    let ge: Vec<(f64, f64)> = pts.iter().map(|&(i, _, g)| (g, e[i])).collect();
    for j in 0..n {
        let f = f0 + j as f64 * df;
        let mut acc = SinCos::new(nu.art.n_cols);
        match &fast {
            // One feature's columns accumulated in registers over its run of points (the
            // same sums as `SinCos::add`, point by point, without a store per point).
            Some((runs, vals)) => {
                let (mut ss, mut sc, mut cc, mut se, mut ce) = (0.0, 0.0, 0.0, 0.0, 0.0);
                for &(q0, q1, c0, m) in runs {
                    let (mut a, mut b) = ([0.0f64; 3], [0.0f64; 3]);
                    for q in q0..q1 {
                        let (c, s) = zq(j, f, q, pts[q].1);
                        let (g, eq) = ge[q];
                        let (gs, gc) = (g * s, g * c);
                        ss += gs * gs;
                        sc += gs * gc;
                        cc += gc * gc;
                        se += gs * eq;
                        ce += gc * eq;
                        let v = vals[q];
                        for k in 0..3 {
                            a[k] += v[k] * gs;
                            b[k] += v[k] * gc;
                        }
                    }
                    for k in 0..m {
                        acc.as_[c0 + k] += a[k];
                        acc.ac[c0 + k] += b[k];
                    }
                }
                (acc.ss, acc.sc, acc.cc, acc.se, acc.ce) = (ss, sc, cc, se, ce);
            }
            None => {
                for (q, &(i, x, g)) in pts.iter().enumerate() {
                    let (c, s) = zq(j, f, q, x);
                    acc.add(nu, i, g * s, g * c, e[i]);
                }
            }
        }
        out.push(acc.reduction(nu));
    }
    out
}

/// Best period along axis `a`, refined.
fn period_along(ds: &Dataset, nu: &Nuisance, e: &[f64], total: f64, a: Axis) -> Option<Found> {
    let ai = a.index();
    let pts = axis_points(ds, nu, ai);
    let g_rms = (pts.iter().map(|p| p.2 * p.2).sum::<f64>() / pts.len().max(1) as f64).sqrt();
    if g_rms < 0.1 {
        return None;
    }
    let (lo, hi) = axis_span(ds, a);
    let span = hi - lo;
    let pmax = (span / 2.0).min(PERIOD_MAX_MM);
    if !(span >= 2.0 && pmax > PERIOD_MIN_MM) {
        return None;
    }
    let (fmin, fmax) = (1.0 / pmax, 1.0 / PERIOD_MIN_MM);
    let df = 1.0 / (4.0 * span);
    let n = ((fmax - fmin) / df).ceil() as usize + 1;
    let j = periodogram(&pts, nu, e, fmin, df, n);
    let fj = fmin + j as f64 * df;
    let f = golden_max(
        |f| period_reduction(&pts, nu, e, f),
        (fj - df).max(fmin),
        (fj + df).min(fmax),
    );
    // Reported (and fitted) with the digits the custom term carries.
    let p = (1e5 / f).round() / 1e5;
    let w = TAU / p;
    let nm = a.name();
    let raw = |trig: fn(f64) -> f64| -> Vec<f64> {
        (0..ds.points.len())
            .map(|i| nu.art.grad[i][ai] * trig(w * ds.points[i].ctx.scale[ai]))
            .collect()
    };
    found(
        vec![raw(f64::sin), raw(f64::cos)],
        nu,
        e,
        total,
        Structure {
            kind: "period".into(),
            axis: nm.into(),
            period_mm: Some(p),
            amplitude_um: 0.0,
            explained: 0.0,
            custom_terms: vec![
                format!("{nm}:sin(2*pi*{nm}/{p:.5})"),
                format!("{nm}:cos(2*pi*{nm}/{p:.5})"),
            ],
            harmonic: None,
            profile: None,
        },
    )
}

/// A step with the sign of the velocity along axis `a`.
fn reversal_along(ds: &Dataset, nu: &Nuisance, e: &[f64], total: f64, a: Axis) -> Option<Found> {
    let ai = a.index();
    let col: Vec<f64> = ds
        .points
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let v = p.ctx.est_vel[ai];
            if v.abs() > 0.01 {
                nu.art.grad[i][ai] * v.signum()
            } else {
                0.0
            }
        })
        .collect();
    found(
        vec![col],
        nu,
        e,
        total,
        Structure {
            kind: "reversal".into(),
            axis: a.name().into(),
            period_mm: None,
            amplitude_um: 0.0,
            explained: 0.0,
            custom_terms: vec![format!("{0}:sign(v{0})", a.name())],
            harmonic: None,
            profile: None,
        },
    )
}

/// The probing direction of a point as the custom effect sees it: (du/defl, dv/defl) and
/// φ = atan2(dv, du); None without deflection (the terms evaluate to 0 there).
fn probing_direction(ctx: &crate::sample::PointContext) -> Option<(f64, f64, f64)> {
    let d = ctx.deflection_probe;
    let defl = ctx.deflection.norm();
    let (nx, ny) = (d.x / defl, d.y / defl);
    (defl > 0.0 && nx.is_finite() && ny.is_finite()).then(|| (nx, ny, d.y.atan2(d.x)))
}

/// Custom terms of harmonic k of the probing direction: x cos, y cos, x sin, y sin.
fn probe_terms(k: u32) -> Vec<String> {
    let mut t = vec![];
    for f in ["cos", "sin"] {
        t.push(format!("x:du/defl*{f}({k}*atan2(dv,du))"));
        t.push(format!("y:dv/defl*{f}({k}*atan2(dv,du))"));
    }
    t
}

/// Harmonic k of the probing direction, acting along the normal.
fn probe_harmonic(ds: &Dataset, nu: &Nuisance, e: &[f64], total: f64, k: u32) -> Option<Found> {
    let mut cos = vec![0.0; ds.points.len()];
    let mut sin = vec![0.0; ds.points.len()];
    for (i, p) in ds.points.iter().enumerate() {
        if let (true, Some((nx, ny, phi))) = (nu.used(i), probing_direction(&p.ctx)) {
            let g = nu.art.grad[i];
            let gn = g.x * nx + g.y * ny;
            let (s, c) = (k as f64 * phi).sin_cos();
            cos[i] = gn * c;
            sin[i] = gn * s;
        }
    }
    found(
        vec![cos, sin],
        nu,
        e,
        total,
        Structure {
            kind: "probe_direction".into(),
            axis: "normal".into(),
            period_mm: None,
            amplitude_um: 0.0,
            explained: 0.0,
            custom_terms: probe_terms(k),
            harmonic: Some(k),
            profile: None,
        },
    )
}

/// Fraction of `y` that the least-squares fit on `cols` reproduces.
fn r2_on(cols: &[Vec<f64>], y: &[f64]) -> f64 {
    let yy = dot(y, y);
    if yy.is_nan() || yy <= 0.0 {
        return 0.0;
    }
    let norms: Vec<f64> = cols.iter().map(|c| dot(c, c)).collect();
    fit_cols(cols, &norms, y).map_or(0.0, |(red, _)| red / yy)
}

/// Strongest first, without structures a stronger one already reproduces, at most four.
fn select(mut all: Vec<Found>) -> Vec<Found> {
    all.retain(|f| f.s.explained.is_finite() && f.s.amplitude_um.is_finite());
    all.sort_by(|a, b| b.s.explained.total_cmp(&a.s.explained));
    let mut kept: Vec<Found> = vec![];
    for f in all {
        let y = f.component();
        if kept.iter().all(|k| r2_on(&k.cols, &y) <= SAME_R2) {
            kept.push(f);
        }
        if kept.len() == MAX_STRUCTURES {
            break;
        }
    }
    kept
}

/// All structures found in `residual`, strongest first, with their residual and columns.
#[cfg(test)]
fn search(ds: &Dataset, prep: &Prepared, residual: &[f64]) -> (Vec<f64>, Vec<Found>) {
    let nu = Nuisance::new(ds, &prep.art);
    search_with(ds, &nu, residual)
}

/// [`search`] with the placements' projection made.
fn search_with(ds: &Dataset, nu: &Nuisance, residual: &[f64]) -> (Vec<f64>, Vec<Found>) {
    let (e, all) = candidates_with(ds, nu, residual);
    (e, select(all))
}

/// Every candidate structure explaining more than 5 % of the residual (unsorted), with the
/// residual freed of the placements.
#[cfg(test)]
fn candidates(ds: &Dataset, prep: &Prepared, residual: &[f64]) -> (Vec<f64>, Vec<Found>) {
    let nu = Nuisance::new(ds, &prep.art);
    candidates_with(ds, &nu, residual)
}

/// [`candidates`] with the placements' projection made.
fn candidates_with(ds: &Dataset, nu: &Nuisance, residual: &[f64]) -> (Vec<f64>, Vec<Found>) {
    let r: Vec<f64> = (0..ds.points.len())
        .map(|i| {
            if nu.used(i) && residual[i].is_finite() {
                residual[i]
            } else {
                0.0
            }
        })
        .collect();
    let e = nu.project(&r);
    let total = dot(&e, &e);
    if !(total > 0.0 && total.is_finite()) {
        return (e, vec![]);
    }
    let mut all = vec![];
    for a in Axis::ALL {
        all.extend(period_along(ds, nu, &e, total, a));
        all.extend(reversal_along(ds, nu, &e, total, a));
    }
    for k in HARMONICS {
        all.extend(probe_harmonic(ds, nu, &e, total, k));
    }
    (e, all)
}

/// Periodic, reversal and probing-direction structure of a residual, strongest first.
pub fn structure(
    ds: &Dataset,
    prep: &Prepared,
    residual: &[f64],
) -> Result<Vec<Structure>, LabError> {
    let nu = Nuisance::new(ds, &prep.art);
    let (e, found) = search_with(ds, &nu, residual);
    Ok(found
        .into_iter()
        .map(|f| {
            let profile = profile_of(ds, &nu, &e, &f);
            Structure { profile, ..f.s }
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calib::Calibration;
    use crate::effects::{custom, EffectConfig, SensorTable};
    use crate::lab::dataset::{LabPoint, Phase};
    use crate::lab::program::{FeatureKind, FeatureSpec};
    use crate::lab::select::fit_effects;
    use crate::lab::types::prepare;
    use crate::sample::{PointContext, Vec3};

    /// Deterministic noise: xorshift64*, uniform in (−√3, √3)·sigma (unit variance · sigma).
    struct Rng(u64);
    impl Rng {
        fn next(&mut self, sigma: f64) -> f64 {
            self.0 ^= self.0 >> 12;
            self.0 ^= self.0 << 25;
            self.0 ^= self.0 >> 27;
            let u = (self.0.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 11) as f64 / (1u64 << 53) as f64;
            (2.0 * u - 1.0) * 3f64.sqrt() * sigma
        }
    }

    /// A point at nominal surface position `nominal` with unit normal `n` (out of the
    /// material), measured `dev` mm off along n, moving with velocity `vel`.
    fn point(nominal: Vec3, n: Vec3, dev: f64, vel: Vec3, feature: usize, seg: u32) -> LabPoint {
        let mut ctx = PointContext::at_rest(nominal);
        ctx.est_vel = vel;
        // The corrector's normal is the deflection direction.
        ctx.deflection = n * 0.3;
        ctx.deflection_probe = n * 0.3;
        ctx.segment_id = seg;
        LabPoint {
            ctx,
            surface: nominal + n * dev,
            normal: n,
            feature,
            segment: seg,
            bag: 0,
            speed: vel.norm(),
            direction: 0,
            phase: Phase::Steady,
            held_out: false,
        }
    }

    fn dataset(points: Vec<LabPoint>, features: Vec<FeatureSpec>) -> Dataset {
        Dataset {
            points,
            features: features.into_iter().map(|f| (0, f)).collect(),
            sensors: SensorTable::default(),
            noise_floor_um: 0.1,
            tracking: vec![],
            calibration: Calibration::example("m1"),
            warnings: vec![],
        }
    }

    /// A face with normal `n` (horizontal) through `c`, scanned along n × z over 250 mm,
    /// both ways, with an x cyclic error of `period` mm and amplitude `amp` mm, 0.1 µm noise.
    fn face(
        n: Vec3,
        c: Vec3,
        period: f64,
        amp: f64,
        feature: usize,
        rng: &mut Rng,
    ) -> (Vec<LabPoint>, FeatureSpec) {
        let along = n.cross(&Vec3::z());
        let mut pts = vec![];
        for pass in 0..2u32 {
            let sgn = if pass == 0 { 1.0 } else { -1.0 };
            for j in 0..3000 {
                let s = -125.0 + 250.0 * j as f64 / 2999.0 + 0.013 * pass as f64;
                let nominal = c + along * s;
                let dx = amp * (TAU * nominal.x / period + 0.7).sin();
                // An x error seen along the normal: n·(dx, 0, 0).
                let dev = n.x * dx + rng.next(1e-4);
                let seg = 2 * feature as u32 + pass;
                pts.push(point(nominal, n, dev, along * (10.0 * sgn), feature, seg));
            }
        }
        let f = FeatureSpec {
            id: feature as u32 + 1,
            artifact: "straightedge".into(),
            kind: FeatureKind::Face,
            nominal_center: c.into(),
            nominal_diameter_mm: 0.0,
            certificate_diameter_mm: None,
            normal: n.into(),
        };
        (pts, f)
    }

    /// Two faces, normals (0.6, ±0.8, 0), each covering 200 mm of x (on one face alone an x
    /// period is also a y period: x and y are tied along a line).
    fn face_with_cyclic_error(
        period: f64,
        amp: f64,
        rng: &mut Rng,
    ) -> (Vec<LabPoint>, Vec<FeatureSpec>) {
        let (mut pts, f0) = face(
            Vec3::new(0.6, 0.8, 0.0),
            Vec3::new(300.0, 100.0, 0.0),
            period,
            amp,
            0,
            rng,
        );
        let (more, f1) = face(
            Vec3::new(0.6, -0.8, 0.0),
            Vec3::new(310.0, 337.0, 0.0),
            period,
            amp,
            1,
            rng,
        );
        pts.extend(more);
        (pts, vec![f0, f1])
    }

    /// A 50 mm ring gauge at (100, 200), three revolutions, with a lobing error
    /// amp·cos(kφ + φ0) along the normal (φ = the normal's angle), and 0.1 µm noise.
    fn ring_with_lobing(
        k: u32,
        amp: f64,
        feature: usize,
        rng: &mut Rng,
    ) -> (Vec<LabPoint>, FeatureSpec) {
        let c = Vec3::new(100.0, 200.0, 0.0);
        let r = 25.0;
        let mut pts = vec![];
        for j in 0..3000 {
            let th = TAU * 3.0 * j as f64 / 3000.0;
            let u = Vec3::new(th.cos(), th.sin(), 0.0);
            let n = -u; // bore: out of the material is towards the centre
            let phi = n.y.atan2(n.x);
            let dev = amp * (k as f64 * phi + 0.4).cos() + rng.next(1e-4);
            let vel = Vec3::new(-th.sin(), th.cos(), 0.0) * 10.0;
            pts.push(point(c + u * r, n, dev, vel, feature, 10 + j / 1000));
        }
        let f = FeatureSpec {
            id: 2,
            artifact: "ring".into(),
            kind: FeatureKind::Bore,
            nominal_center: c.into(),
            nominal_diameter_mm: 50.0,
            certificate_diameter_mm: Some(50.0),
            normal: [0.0, 0.0, 1.0],
        };
        (pts, f)
    }

    #[test]
    fn structure_period_refined_to_one_percent() {
        let mut rng = Rng(0x9E37_79B9_7F4A_7C15);
        for period in [4.0, 7.3, 0.9] {
            let (pts, f) = face_with_cyclic_error(period, 2e-3, &mut rng);
            let ds = dataset(pts, f);
            let prep = prepare(&ds).unwrap();
            let s = structure(&ds, &prep, &prep.art.residual).unwrap();
            eprintln!("{period}: {s:#?}");
            let p = &s[0];
            assert_eq!(
                (p.kind.as_str(), p.axis.as_str()),
                ("period", "x"),
                "{s:#?}"
            );
            let got = p.period_mm.unwrap();
            eprintln!("{period} mm reported as {got} mm");
            assert!((got - period).abs() < 0.01 * period, "{got} vs {period}");
            assert!((p.amplitude_um - 2.0).abs() < 0.1, "{}", p.amplitude_um);
            assert!(p.explained > 0.95, "{}", p.explained);
            assert!(
                p.custom_terms[0].starts_with("x:sin(2*pi*x/"),
                "{:?}",
                p.custom_terms
            );
            // The period in the term has the reported digits.
            assert!(
                p.custom_terms[0].contains(&format!("{got:.5}")),
                "{:?}",
                p.custom_terms
            );
            // The profile: the residual along x with the fitted period over it, 12 bins a
            // period; the fitted curve swings ±2 µm and the binned residual follows it.
            let pr = p.profile.as_ref().expect("a period has a profile");
            assert_eq!(pr.coordinate, "x, mm");
            let bins_per_period = period / (pr.x[1] - pr.x[0]);
            assert!((bins_per_period - 12.0).abs() < 1.0, "{bins_per_period}");
            let peak = pr.fitted_um.iter().fold(0.0f64, |a, v| a.max(v.abs()));
            assert!((peak - 2.0).abs() < 0.15, "{peak}");
            let n = pr.x.len() as f64;
            let off = (pr
                .measured_um
                .iter()
                .zip(&pr.fitted_um)
                .map(|(m, f)| (m - f).powi(2))
                .sum::<f64>()
                / n)
                .sqrt();
            assert!(
                off < 0.3,
                "the binned residual is {off} µm rms off the fitted period"
            );
        }
    }

    /// The periodogram by runs of one feature's points gives the reductions of the point by
    /// point sums (to rounding), on faces (2 placement columns) and rings (3).
    #[test]
    fn periodogram_by_runs_is_the_point_by_point_one() {
        let mut rng = Rng(77);
        let (mut pts, mut fs) = face_with_cyclic_error(4.0, 2e-3, &mut rng);
        let (ring, mut f2) = ring_with_lobing(3, 1.5e-3, 2, &mut rng);
        f2.id = 3;
        pts.extend(ring);
        fs.push(f2);
        let ds = dataset(pts, fs);
        let prep = prepare(&ds).unwrap();
        let nu = Nuisance::new(&ds, &prep.art);
        let e = nu.project(&prep.art.residual);
        let mut seen = 0;
        for ai in 0..3 {
            let pts = axis_points(&ds, &nu, ai);
            assert!(runs(&pts, &nu).is_some());
            let grid = (1.0 / 200.0, 1.0 / 800.0, 1500);
            let fast = reductions(&pts, &nu, &e, grid, true);
            let slow = reductions(&pts, &nu, &e, grid, false);
            let top = slow.iter().cloned().fold(0.0, f64::max);
            seen += usize::from(top > 0.0);
            for (j, (a, b)) in fast.iter().zip(&slow).enumerate() {
                assert!((a - b).abs() <= 1e-9 * top, "axis {ai}, f[{j}]: {a} vs {b}");
            }
        }
        // x and y (the points are in one plane: z sees nothing).
        assert_eq!(seen, 2);
    }

    #[test]
    fn structure_probe_direction_harmonic_and_its_terms() {
        let mut rng = Rng(12345);
        let (mut pts, f0) = ring_with_lobing(3, 1.5e-3, 0, &mut rng);
        // A second ring elsewhere with the same probe: the same lobing.
        let (more, mut f1) = ring_with_lobing(3, 1.5e-3, 1, &mut rng);
        f1.nominal_center = [400.0, 150.0, 0.0];
        let shift = Vec3::new(300.0, -50.0, 0.0);
        pts.extend(more.into_iter().map(|mut p| {
            p.surface += shift;
            p.ctx.scale += shift;
            p
        }));
        let ds = dataset(pts, vec![f0, f1]);
        let prep = prepare(&ds).unwrap();
        let (e, found) = search(&ds, &prep, &prep.art.residual);
        let s: Vec<&Structure> = found.iter().map(|f| &f.s).collect();
        eprintln!("{s:#?}");
        let best = &found[0];
        assert_eq!(best.s.kind, "probe_direction", "{s:#?}");
        assert_eq!(best.s.axis, "normal");
        assert_eq!(best.s.harmonic, Some(3));
        assert!(
            (best.s.amplitude_um - 1.5).abs() < 0.1,
            "{}",
            best.s.amplitude_um
        );
        assert!(best.s.explained > 0.95, "{}", best.s.explained);
        // Its profile against the probing direction: 3 waves of ±1.5 µm over the turn.
        let st = structure(&ds, &prep, &prep.art.residual).unwrap();
        let pr = st[0].profile.as_ref().expect("a harmonic has a profile");
        assert_eq!(pr.coordinate, "probing direction φ, °");
        let peak = pr.fitted_um.iter().fold(0.0f64, |a, v| a.max(v.abs()));
        assert!((peak - 1.5).abs() < 0.15, "{peak}");
        let crossings = pr
            .fitted_um
            .windows(2)
            .filter(|w| w[0].signum() != w[1].signum())
            .count();
        assert!(
            (5..=7).contains(&crossings),
            "{crossings} sign changes for 3 waves"
        );
        let off = (pr
            .measured_um
            .iter()
            .zip(&pr.fitted_um)
            .map(|(m, f)| (m - f).powi(2))
            .sum::<f64>()
            / pr.x.len() as f64)
            .sqrt();
        assert!(off < 0.3, "{off}");
        // No period offered for what the harmonic explains, though one fits part of it.
        assert!(s.iter().all(|x| x.kind != "period"), "{s:#?}");
        let (_, all) = candidates(&ds, &prep, &prep.art.residual);
        let periods: Vec<&Structure> = all
            .iter()
            .map(|f| &f.s)
            .filter(|x| x.kind == "period")
            .collect();
        eprintln!("periods before selection: {periods:#?}");
        assert!(periods.iter().any(|x| x.explained > 0.5), "{periods:#?}");
        // The custom terms with coefficients (c, c, s, s) reproduce the fitted component.
        let (c, sn) = (best.coef[0], best.coef[1]);
        let cfg = custom::Config {
            id: "lobing".into(),
            dynamic: false,
            terms: best
                .s
                .custom_terms
                .iter()
                .map(|t| {
                    let (a, x) = t.split_once(':').unwrap();
                    custom::Term {
                        axis: serde_json::from_value(serde_json::json!(a)).unwrap(),
                        expr: x.into(),
                    }
                })
                .collect(),
            coefficients: vec![c, c, sn, sn],
        };
        let model = cfg.build(&mut SensorTable::default()).unwrap();
        let comp = best.component();
        let mut d2 = 0.0;
        for (i, p) in ds.points.iter().enumerate() {
            use crate::effects::Effect;
            let pred = prep.art.grad[i].dot(&model.correction(&p.ctx));
            d2 += (pred - comp[i]).powi(2);
        }
        let rms = (d2 / ds.points.len() as f64).sqrt();
        assert!(
            rms < 1e-6,
            "terms differ from the structure by {rms} mm rms"
        );
        // … and the injected deviation is the residual's component along them.
        let left = e
            .iter()
            .zip(&comp)
            .map(|(a, b)| (a - b).powi(2))
            .sum::<f64>();
        assert!((left / ds.points.len() as f64).sqrt() < 2e-4, "{left}");
        // Fitting the custom effect the user pastes removes the residual.
        let cfg0 = custom::Config {
            coefficients: vec![0.0; 4],
            ..cfg
        };
        let o = fit_effects(&ds, &prep, &[EffectConfig::Custom(cfg0)]).unwrap();
        assert!(
            o.rms_after_um < 0.2 * o.rms_before_um,
            "{} → {}",
            o.rms_before_um,
            o.rms_after_um
        );
    }

    #[test]
    fn structure_of_noise_is_empty() {
        let mut rng = Rng(777);
        let (mut pts, f0) = face_with_cyclic_error(4.0, 0.0, &mut rng);
        let (ring, f1) = ring_with_lobing(3, 0.0, 2, &mut rng);
        pts.extend(ring);
        let ds = dataset(pts, vec![f0[0].clone(), f0[1].clone(), f1]);
        let prep = prepare(&ds).unwrap();
        let s = structure(&ds, &prep, &prep.art.residual).unwrap();
        assert!(s.is_empty(), "{s:#?}");
        // Non-finite residuals are ignored, never reported.
        let mut r = prep.art.residual.clone();
        r[5] = f64::NAN;
        let s = structure(&ds, &prep, &r).unwrap();
        assert!(s
            .iter()
            .all(|x| x.explained.is_finite() && x.amplitude_um.is_finite()));
    }
}
