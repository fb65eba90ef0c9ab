//! The plate procedure: the features (holes) of a plate measured against their nominal
//! positions. What the errors hold, model by model, each parameter with its standard
//! uncertainty:
//!
//! * (a) **similarity** nominal → measured: `m = t + s·R(θ)·n` — offset, rotation, one scale;
//! * (b) **+ anisotropic scale / shear**, the whole linear map: `m = t + (I + Q)·s·R(θ)·n`
//!   with `Q = q·[[cos 2φ, sin 2φ], [sin 2φ, −cos 2φ]]` symmetric and traceless (a
//!   "quadrupole" of magnitude q and angle φ: it moves a hole at polar angle α radially by
//!   q·r·cos 2(α − φ) and tangentially by −q·r·sin 2(α − φ)). A CMM engineer reads the same
//!   map as a scale per axis (the images of the nominal X and Y axes stretched by e_x, e_y),
//!   the X axis's rotation, and squareness (the angle between the axes' images less 90°,
//!   positive when they open beyond 90°); both parametrisations are reported;
//! * (c) **what lies beyond**, chosen by cross-validation over holes: leave one hole out
//!   (exact for a linear least squares: the hole's 2×2 block of the hat matrix,
//!   `e₋ᵢ = (I − Hᵢᵢ)⁻¹·rᵢ`), its radial RMS the model's CV figure. The anisotropic term is
//!   the first move (it completes the linear map); then, one at a time, the best of the
//!   second- and third-order polynomial distortions of each axis (X or Y error ∝ x², xy, y²,
//!   x³, x²y, xy², y³ in the nominal coordinates over the plate's radius R, each coefficient
//!   the error at the plate's edge). A move is kept only when it lowers the CV residual
//!   significantly: the per-hole decrease of the squared left-out error has a paired
//!   t ≥ [`Options::t_min`] (3: about 0.1 % one-sided per candidate). Every candidate's CV
//!   figure is reported, and the first move kept is named as the effect the similarity
//!   model lacks.
//!
//! Each fit is an ordinary least squares over both coordinates of every hole (no weights),
//! σ from the residuals: the covariance scaled by the reduced χ² (RSS/(2n − p)); derived
//! quantities (scale, angles, per-axis terms) propagated through their Jacobian. The radial
//! residual of a hole is |m − fit| (the distance, not a projection), the radial RMS
//! √(mean |m − fit|²) over the holes. Nothing undetermined is given a value: a model the
//! holes cannot determine (too few, collinear) is named, never a NaN.
//!
//! [`OriginalTool`] reproduces the fit of the program whose output files plug-plate shops
//! keep (fitPlugPlateMeas, the University of Washington shop's SDSS plug plates), read off
//! its output: the similarity nominal → measured and then its "quadrupole" — a purely radial
//! factor `F·(1 + q·cos 2(α_F − φ))` on the similarity's fitted positions F, α_F their polar
//! angle — each fitted by MINPACK's `lmdif` (forward-difference Levenberg–Marquardt,
//! scipy's `leastsq` defaults) on the **squared** radial errors of the holes (so it
//! minimises Σ r⁴, stopped by lmdif's step-size test before that minimum: near the least
//! squares one for the similarity, at it for the quadrupole). Its `ResidRadErrRMS` is the
//! radial RMS over the small holes, the large ones (measured diameter > 3 mm, SDSS-IV
//! MaNGA holes) apart; their nominal diameter is taken as 3.28 mm for the diameter errors;
//! `QPResidRadErrRMS` is over every hole. All holes enter both fits. Pure logic: no files.

use super::{Param, ProcedureError};
use nalgebra::{DMatrix, DVector};
use serde::Serialize;

/// One feature (hole) of the plate.
#[derive(Debug, Clone, PartialEq)]
pub struct Feature {
    /// Its name (a row number where the file names none).
    pub id: String,
    /// Nominal position, mm.
    pub nominal_mm: [f64; 2],
    /// Measured position, mm.
    pub measured_mm: [f64; 2],
    /// Nominal diameter, mm, where known.
    pub nominal_d_mm: Option<f64>,
    /// Measured diameter, mm, where known.
    pub measured_d_mm: Option<f64>,
}

/// How the procedure chooses.
#[derive(Debug, Clone, Copy)]
pub struct Options {
    /// The paired t a move needs (per-hole decrease of the squared left-out error).
    pub t_min: f64,
    /// Reproduce the original tool's fit as well.
    pub original_tool: bool,
}

impl Default for Options {
    fn default() -> Self {
        Options {
            t_min: 3.0,
            original_tool: true,
        }
    }
}

/// Residuals of a model.
#[derive(Debug, Clone, Serialize)]
pub struct Residual {
    /// √(mean |m − fit|²) over the holes, µm.
    pub rms_radial_um: f64,
    /// RMS of the X residuals, µm.
    pub rms_x_um: f64,
    /// RMS of the Y residuals, µm.
    pub rms_y_um: f64,
    /// Largest radial residual, µm.
    pub max_radial_um: f64,
    /// The radial RMS of the leave-one-hole-out errors, µm (`None`: undetermined, see
    /// `cv_undetermined`).
    pub cv_rms_um: Option<f64>,
    /// Why the CV figure is undetermined.
    pub cv_undetermined: Option<String>,
    /// Parameters of the model.
    pub parameters: usize,
    /// Degrees of freedom left (2·holes − parameters).
    pub dof: usize,
}

/// (a) Offset, rotation and one scale, nominal → measured.
#[derive(Debug, Clone, Serialize)]
pub struct Similarity {
    /// Offset at the nominal origin, µm.
    pub offset_x_um: Param,
    /// Offset at the nominal origin, µm.
    pub offset_y_um: Param,
    /// Rotation, µrad (counter-clockwise positive).
    pub rotation_urad: Param,
    /// The same rotation, degrees.
    pub rotation_deg: Param,
    /// Scale factor.
    pub scale: Param,
    /// Scale − 1, ppm.
    pub scale_ppm: Param,
    /// What it leaves.
    pub residual: Residual,
}

/// (b) The whole linear map, in both parametrisations.
#[derive(Debug, Clone, Serialize)]
pub struct Affine {
    /// Offset at the nominal origin, µm.
    pub offset_x_um: Param,
    /// Offset at the nominal origin, µm.
    pub offset_y_um: Param,
    /// Rotation (of the polar decomposition), µrad.
    pub rotation_urad: Param,
    /// The same, degrees.
    pub rotation_deg: Param,
    /// Mean scale factor.
    pub scale: Param,
    /// Mean scale − 1, ppm.
    pub scale_ppm: Param,
    /// Quadrupole magnitude q, ppm (the original tool's terms).
    pub quadrupole_ppm: Param,
    /// Quadrupole angle φ, degrees in (−90, 90] (`None` when q is not significant: the angle
    /// of nothing).
    pub quadrupole_angle_deg: Option<Param>,
    /// Scale error of the X axis (the image of a nominal X length), ppm (a CMM engineer's
    /// terms).
    pub scale_x_ppm: Param,
    /// Scale error of the Y axis, ppm.
    pub scale_y_ppm: Param,
    /// Squareness: the angle between the axes' images less 90°, µrad (positive: wider).
    pub squareness_urad: Param,
    /// Rotation of the X axis's image, µrad.
    pub x_axis_rotation_urad: Param,
    /// What it leaves.
    pub residual: Residual,
}

/// One candidate move of the selection.
#[derive(Debug, Clone, Serialize)]
pub struct Candidate {
    /// Its id (`quadrupole`, `dx_y3`, …).
    pub term: String,
    /// What it is, in words.
    pub description: String,
    /// CV radial RMS with it, µm.
    pub cv_rms_um: Option<f64>,
    /// Paired t of the per-hole decrease of the squared left-out error.
    pub t: Option<f64>,
    /// It lowers the CV residual significantly.
    pub significant: bool,
    /// Why it cannot be judged.
    pub undetermined: Option<String>,
}

/// One round of the selection: every candidate on the model so far.
#[derive(Debug, Clone, Serialize)]
pub struct Round {
    /// The model so far.
    pub base: String,
    /// Its CV radial RMS, µm.
    pub base_cv_um: f64,
    /// Every candidate tried.
    pub candidates: Vec<Candidate>,
    /// The move kept (the best significant one).
    pub kept: Option<String>,
}

/// (c) The model chosen by cross-validation.
#[derive(Debug, Clone, Serialize)]
pub struct Selection {
    /// The rounds, in order.
    pub rounds: Vec<Round>,
    /// The terms kept beyond the similarity, in order.
    pub kept: Vec<String>,
    /// The chosen model, as a sum of terms.
    pub model: String,
    /// What it leaves.
    pub residual: Residual,
    /// Coefficients of the kept higher-order terms: the error at the plate's edge, µm.
    pub terms: Vec<Param>,
    /// Quadrupole of the chosen model (when kept), ppm.
    pub quadrupole_ppm: Option<Param>,
    /// Its angle, degrees.
    pub quadrupole_angle_deg: Option<Param>,
}

/// One hole's residuals in the original tool's fit, mm.
#[derive(Debug, Clone, Serialize)]
pub struct ToolHole {
    /// The feature's id.
    pub id: String,
    /// Measured − similarity fit, X.
    pub resid_x_mm: f64,
    /// Measured − similarity fit, Y.
    pub resid_y_mm: f64,
    /// Its length.
    pub resid_rad_mm: f64,
    /// Measured − quadrupole fit, X (the similarity's where the quadrupole is not
    /// determined).
    pub qp_resid_x_mm: f64,
    /// Measured − quadrupole fit, Y.
    pub qp_resid_y_mm: f64,
    /// Its length.
    pub qp_resid_rad_mm: f64,
}

/// The original tool's fit (fitPlugPlateMeas), its names and units.
#[derive(Debug, Clone, Serialize)]
pub struct OriginalTool {
    /// FitOffset, mm.
    pub fit_offset_mm: [f64; 2],
    /// FitScale.
    pub fit_scale: f64,
    /// FitRotAngle, degrees.
    pub fit_rot_angle_deg: f64,
    /// QPMagnitude (`None`: its fit failed).
    pub qp_magnitude: Option<f64>,
    /// QPAngle, degrees in [−90, 90].
    pub qp_angle_deg: Option<f64>,
    /// ResidRadErrRMS: the small holes' radial RMS, mm (`None`: no small hole).
    pub resid_rad_err_rms_mm: Option<f64>,
    /// The large (MaNGA) holes' radial RMS, mm.
    pub large_resid_rad_err_rms_mm: Option<f64>,
    /// DiaErrRMS of the small holes, mm.
    pub dia_err_rms_mm: Option<f64>,
    /// DiaErrRMS of the large holes (nominal 3.28 mm), mm.
    pub large_dia_err_rms_mm: Option<f64>,
    /// MaxDiaErr, mm.
    pub max_dia_err_mm: Option<f64>,
    /// QPResidRadErrRMS over every hole, mm.
    pub qp_resid_rad_err_rms_mm: Option<f64>,
    /// Radial RMS over every hole after the similarity, mm.
    pub all_resid_rad_err_rms_mm: f64,
    /// Holes counted large (measured diameter > 3 mm).
    pub large_holes: usize,
    /// lmdif's function evaluations and exit code (similarity, quadrupole).
    pub lmdif: [(usize, i32); 2],
    /// Per hole.
    pub holes: Vec<ToolHole>,
}

/// What the procedure found.
#[derive(Debug, Clone, Serialize)]
pub struct Outcome {
    /// Holes used.
    pub holes: usize,
    /// The plate's radius (largest nominal distance from the origin), mm: the scale of the
    /// higher-order terms.
    pub radius_mm: f64,
    /// (a).
    pub similarity: Similarity,
    /// (b) (`None`: undetermined, see `undetermined`).
    pub affine: Option<Affine>,
    /// (c).
    pub selection: Selection,
    /// The effect the similarity model lacks, named (the first move kept).
    pub missing_effect: Option<String>,
    /// What lies beyond it (the further moves kept), each named.
    pub beyond: Vec<String>,
    /// The original tool's fit.
    pub original_tool: Option<OriginalTool>,
    /// What the holes cannot determine.
    pub undetermined: Vec<String>,
    /// Remarks.
    pub notes: Vec<String>,
}

// ---------------------------------------------------------------------------------------
// Model terms

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Term {
    /// Offset x, y; a, b of s·R(θ) = [[a, −b], [b, a]].
    Similarity,
    /// q1, q2: A += [[q1, q2], [q2, −q1]].
    Quadrupole,
    /// Error along `axis` (0: X, 1: Y) ∝ (x/R)^i·(y/R)^j, coefficient in mm.
    Mono { axis: usize, i: u32, j: u32 },
}

fn superscript(i: u32) -> &'static str {
    match i {
        2 => "²",
        3 => "³",
        _ => "",
    }
}

fn power(v: &str, i: u32) -> String {
    match i {
        0 => String::new(),
        1 => v.to_string(),
        _ => format!("{v}{}", superscript(i)),
    }
}

impl Term {
    fn id(self) -> String {
        match self {
            Term::Similarity => "similarity".into(),
            Term::Quadrupole => "quadrupole".into(),
            Term::Mono { axis, i, j } => format!(
                "d{}_{}{}",
                ["x", "y"][axis],
                match i {
                    0 => String::new(),
                    1 => "x".into(),
                    _ => format!("x{i}"),
                },
                match j {
                    0 => String::new(),
                    1 => "y".into(),
                    _ => format!("y{j}"),
                }
            ),
        }
    }

    fn describe(self) -> String {
        match self {
            Term::Similarity => "offset, rotation and one scale (similarity)".into(),
            Term::Quadrupole => "anisotropic scale/shear (quadrupole)".into(),
            Term::Mono { axis, i, j } => format!(
                "{} error ∝ {}{} ({} order)",
                ["X", "Y"][axis],
                power("x", i),
                power("y", j),
                if i + j == 2 { "2nd" } else { "3rd" }
            ),
        }
    }

    fn columns(self) -> usize {
        match self {
            Term::Similarity => 4,
            Term::Quadrupole => 2,
            Term::Mono { .. } => 1,
        }
    }

    /// This term's columns' entries for a hole at nominal (x, y): per column, its (X, Y) rows.
    fn rows(self, x: f64, y: f64, r: f64, out: &mut Vec<[f64; 2]>) {
        match self {
            Term::Similarity => {
                out.push([1.0, 0.0]);
                out.push([0.0, 1.0]);
                out.push([x, y]);
                out.push([-y, x]);
            }
            Term::Quadrupole => {
                out.push([x, -y]);
                out.push([y, x]);
            }
            Term::Mono { axis, i, j } => {
                let v = (x / r).powi(i as i32) * (y / r).powi(j as i32);
                out.push(if axis == 0 { [v, 0.0] } else { [0.0, v] });
            }
        }
    }
}

fn monomials() -> Vec<Term> {
    let mut v = Vec::new();
    for axis in 0..2 {
        for d in 2..=3u32 {
            for i in (0..=d).rev() {
                v.push(Term::Mono { axis, i, j: d - i });
            }
        }
    }
    v
}

fn model_name(terms: &[Term]) -> String {
    terms.iter().map(|t| t.id()).collect::<Vec<_>>().join(" + ")
}

// ---------------------------------------------------------------------------------------
// Least squares

/// A solved linear least squares over the holes' X and Y rows.
struct Solved {
    theta: Vec<f64>,
    /// (XᵀX)⁻¹.
    inv: DMatrix<f64>,
    /// (XᵀX)⁻¹·RSS/dof.
    cov: DMatrix<f64>,
    resid: Vec<[f64; 2]>,
    dof: usize,
}

/// The design matrix of `terms`: 2n rows (X then Y of each hole), one column per parameter.
fn design(terms: &[Term], f: &[Feature], r: f64) -> DMatrix<f64> {
    let p: usize = terms.iter().map(|t| t.columns()).sum();
    let mut x = DMatrix::zeros(2 * f.len(), p);
    let mut buf = Vec::with_capacity(p);
    for (h, ft) in f.iter().enumerate() {
        buf.clear();
        for t in terms {
            t.rows(ft.nominal_mm[0], ft.nominal_mm[1], r, &mut buf);
        }
        for (c, v) in buf.iter().enumerate() {
            x[(2 * h, c)] = v[0];
            x[(2 * h + 1, c)] = v[1];
        }
    }
    x
}

/// Least squares of `x·θ ≈ y`; `Err(column)` names the column the rows do not determine.
fn solve(x: &DMatrix<f64>, y: &DVector<f64>) -> Result<Solved, usize> {
    let (m, p) = x.shape();
    if m < p {
        return Err(p - 1);
    }
    let d: Vec<f64> = (0..p)
        .map(|j| {
            let n = x.column(j).norm();
            if n > 0.0 {
                n
            } else {
                1.0
            }
        })
        .collect();
    let xs = DMatrix::from_fn(m, p, |i, j| x[(i, j)] / d[j]);
    let svd = xs.svd(true, true);
    let (u, vt) = (svd.u.as_ref().unwrap(), svd.v_t.as_ref().unwrap());
    let s = &svd.singular_values;
    let smax = s.iter().cloned().fold(0.0, f64::max);
    if let Some((k, _)) = s
        .iter()
        .enumerate()
        .filter(|(_, &v)| v.is_nan() || v <= 1e-9 * smax)
        .min_by(|a, b| a.1.total_cmp(b.1))
    {
        // The right singular vector of the null direction: its largest component.
        let row = vt.row(k);
        let j = (0..p)
            .max_by(|&a, &b| row[a].abs().total_cmp(&row[b].abs()))
            .unwrap_or(p - 1);
        return Err(j);
    }
    // θ = D⁻¹·V·Σ⁻¹·Uᵀ·y; (XᵀX)⁻¹ = D⁻¹·V·Σ⁻²·Vᵀ·D⁻¹.
    let uty = u.transpose() * y;
    let mut theta = vec![0.0; p];
    let mut inv = DMatrix::zeros(p, p);
    for k in 0..p {
        let w = uty[k] / s[k];
        for j in 0..p {
            theta[j] += vt[(k, j)] * w / d[j];
        }
        for a in 0..p {
            for b in 0..p {
                inv[(a, b)] += vt[(k, a)] * vt[(k, b)] / (s[k] * s[k] * d[a] * d[b]);
            }
        }
    }
    let fit = x * DVector::from_column_slice(&theta);
    let n = m / 2;
    let resid: Vec<[f64; 2]> = (0..n)
        .map(|h| [y[2 * h] - fit[2 * h], y[2 * h + 1] - fit[2 * h + 1]])
        .collect();
    let rss: f64 = resid.iter().map(|e| e[0] * e[0] + e[1] * e[1]).sum();
    let dof = m - p;
    let cov = if dof > 0 {
        &inv * (rss / dof as f64)
    } else {
        DMatrix::zeros(p, p)
    };
    Ok(Solved {
        theta,
        inv,
        cov,
        resid,
        dof,
    })
}

/// Leave-one-hole-out errors: e₋ᵢ = (I − Hᵢᵢ)⁻¹·rᵢ, Hᵢᵢ = Xᵢ·(XᵀX)⁻¹·Xᵢᵀ. `Err(hole)`:
/// that hole alone determines a parameter.
fn loo(x: &DMatrix<f64>, s: &Solved) -> Result<Vec<[f64; 2]>, usize> {
    let p = x.ncols();
    let mut out = Vec::with_capacity(s.resid.len());
    let mut xi = [vec![0.0; p], vec![0.0; p]];
    for (h, r) in s.resid.iter().enumerate() {
        for k in 0..2 {
            for j in 0..p {
                xi[k][j] = x[(2 * h + k, j)];
            }
        }
        let mut hm = [[0.0; 2]; 2];
        for a in 0..2 {
            for b in 0..2 {
                let mut acc = 0.0;
                for (j, xa) in xi[a].iter().enumerate() {
                    let t: f64 = xi[b]
                        .iter()
                        .enumerate()
                        .map(|(k, xb)| s.inv[(j, k)] * xb)
                        .sum();
                    acc += xa * t;
                }
                hm[a][b] = acc;
            }
        }
        let (m00, m01, m10, m11) = (1.0 - hm[0][0], -hm[0][1], -hm[1][0], 1.0 - hm[1][1]);
        let det = m00 * m11 - m01 * m10;
        if det.is_nan() || det <= 1e-9 {
            return Err(h);
        }
        out.push([
            (m11 * r[0] - m01 * r[1]) / det,
            (-m10 * r[0] + m00 * r[1]) / det,
        ]);
    }
    Ok(out)
}

fn rms_of(e: &[[f64; 2]]) -> f64 {
    if e.is_empty() {
        return 0.0;
    }
    (e.iter().map(|v| v[0] * v[0] + v[1] * v[1]).sum::<f64>() / e.len() as f64).sqrt()
}

/// A fitted model and its left-out errors.
struct Fitted {
    terms: Vec<Term>,
    x: DMatrix<f64>,
    s: Solved,
    loo: Result<Vec<[f64; 2]>, usize>,
}

fn fit(terms: &[Term], f: &[Feature], r: f64, y: &DVector<f64>) -> Result<Fitted, usize> {
    let x = design(terms, f, r);
    let s = solve(&x, y)?;
    let loo = loo(&x, &s);
    Ok(Fitted {
        terms: terms.to_vec(),
        x,
        s,
        loo,
    })
}

/// The term a design column belongs to.
fn term_of_column(terms: &[Term], col: usize) -> Term {
    let mut c = 0;
    for t in terms {
        c += t.columns();
        if col < c {
            return *t;
        }
    }
    *terms.last().expect("a model has terms")
}

impl Fitted {
    fn residual(&self, f: &[Feature]) -> Residual {
        let e = &self.s.resid;
        let n = e.len().max(1) as f64;
        let (cv, why) = match &self.loo {
            Ok(l) => (Some(rms_of(l) * 1e3), None),
            Err(h) => (
                None,
                Some(format!(
                    "hole {} alone determines a parameter of {} (too few holes around it)",
                    f[*h].id,
                    model_name(&self.terms)
                )),
            ),
        };
        Residual {
            rms_radial_um: rms_of(e) * 1e3,
            rms_x_um: (e.iter().map(|v| v[0] * v[0]).sum::<f64>() / n).sqrt() * 1e3,
            rms_y_um: (e.iter().map(|v| v[1] * v[1]).sum::<f64>() / n).sqrt() * 1e3,
            max_radial_um: e.iter().map(|v| v[0].hypot(v[1])).fold(0.0, f64::max) * 1e3,
            cv_rms_um: cv,
            cv_undetermined: why,
            parameters: self.x.ncols(),
            dof: self.s.dof,
        }
    }

    /// The linear map's entries A = [[a, b], [c, d]] and offset from θ (similarity first,
    /// then the quadrupole when the model has it).
    fn linear(theta: &[f64], quad: Option<usize>) -> ([f64; 2], [[f64; 2]; 2]) {
        let (ta, tb) = (theta[2], theta[3]);
        let (q1, q2) = quad.map_or((0.0, 0.0), |k| (theta[k], theta[k + 1]));
        (
            [theta[0], theta[1]],
            [[ta + q1, -tb + q2], [tb + q2, ta - q1]],
        )
    }

    fn quad_index(&self) -> Option<usize> {
        let mut c = 0;
        for t in &self.terms {
            if *t == Term::Quadrupole {
                return Some(c);
            }
            c += t.columns();
        }
        None
    }
}

/// Values and σ of `g(θ)` by first-order propagation (central differences, steps a
/// thousandth of each parameter's σ). Entries of `angles` are degrees wrapped modulo 180°.
fn propagate(
    theta: &[f64],
    cov: &DMatrix<f64>,
    g: impl Fn(&[f64]) -> Vec<f64>,
    angles: &[usize],
) -> Vec<(f64, f64)> {
    let v0 = g(theta);
    let p = theta.len();
    let mut jac = vec![vec![0.0; p]; v0.len()];
    let mut t = theta.to_vec();
    for j in 0..p {
        let h = (cov[(j, j)].sqrt() * 1e-3).max(1e-12 * (1.0 + theta[j].abs()));
        t[j] = theta[j] + h;
        let up = g(&t);
        t[j] = theta[j] - h;
        let dn = g(&t);
        t[j] = theta[j];
        for k in 0..v0.len() {
            let mut d = up[k] - dn[k];
            if angles.contains(&k) {
                d = (d + 90.0).rem_euclid(180.0) - 90.0;
            }
            jac[k][j] = d / (2.0 * h);
        }
    }
    v0.iter()
        .enumerate()
        .map(|(k, &v)| {
            let mut var = 0.0;
            for a in 0..p {
                for b in 0..p {
                    var += jac[k][a] * cov[(a, b)] * jac[k][b];
                }
            }
            (v, var.max(0.0).sqrt())
        })
        .collect()
}

fn param(name: &str, v: (f64, f64)) -> Param {
    Param {
        name: name.into(),
        value: v.0,
        sigma: v.1,
    }
}

/// The left polar decomposition A = s·(I + Q)·R(θ): (θ rad, s, q, φ deg in (−90, 90]).
fn polar(a: [[f64; 2]; 2]) -> (f64, f64, f64, f64) {
    let th = (a[1][0] - a[0][1]).atan2(a[0][0] + a[1][1]);
    let s = (a[0][0] + a[1][1]).hypot(a[1][0] - a[0][1]) / 2.0;
    let (c, sn) = (th.cos(), th.sin());
    // S = A·R(−θ).
    let s11 = a[0][0] * c - a[0][1] * sn;
    let s12 = a[0][0] * sn + a[0][1] * c;
    let (qc, qs) = (s11 / s - 1.0, s12 / s);
    let q = qc.hypot(qs);
    let mut phi = qs.atan2(qc).to_degrees() / 2.0;
    if phi <= -90.0 {
        phi += 180.0;
    }
    (th, s, q, phi)
}

/// Similarity quantities: offset µm, rotation µrad and degrees, scale, scale ppm.
fn similarity_values(t: &[f64]) -> Vec<f64> {
    let s = t[2].hypot(t[3]);
    let th = t[3].atan2(t[2]);
    vec![
        t[0] * 1e3,
        t[1] * 1e3,
        th * 1e6,
        th.to_degrees(),
        s,
        (s - 1.0) * 1e6,
    ]
}

/// Affine quantities: offset µm ×2, rotation µrad, degrees, scale, ppm, q ppm, φ deg,
/// e_x ppm, e_y ppm, squareness µrad, X axis rotation µrad.
fn affine_values(t: &[f64], quad: usize) -> Vec<f64> {
    let (off, a) = Fitted::linear(t, Some(quad));
    let (th, s, q, phi) = polar(a);
    let ex = a[0][0].hypot(a[1][0]) - 1.0;
    let ey = a[0][1].hypot(a[1][1]) - 1.0;
    let thx = a[1][0].atan2(a[0][0]);
    let thy = (-a[0][1]).atan2(a[1][1]);
    vec![
        off[0] * 1e3,
        off[1] * 1e3,
        th * 1e6,
        th.to_degrees(),
        s,
        (s - 1.0) * 1e6,
        q * 1e6,
        phi,
        ex * 1e6,
        ey * 1e6,
        (thy - thx) * 1e6,
        thx * 1e6,
    ]
}

/// Quadrupole (ppm, angle) of a fitted model with the quadrupole term, with σ; the angle
/// `None` when q is below 2σ.
fn quad_params(m: &Fitted) -> Option<(Param, Option<Param>)> {
    let k = m.quad_index()?;
    let v = propagate(&m.s.theta, &m.s.cov, |t| affine_values(t, k), &[7]);
    let q = param("quadrupole_ppm", v[6]);
    let ang = (q.value > 2.0 * q.sigma).then(|| param("quadrupole_angle_deg", v[7]));
    Some((q, ang))
}

// ---------------------------------------------------------------------------------------
// The procedure

fn check(features: &[Feature]) -> Result<f64, ProcedureError> {
    for f in features {
        let all = [
            f.nominal_mm[0],
            f.nominal_mm[1],
            f.measured_mm[0],
            f.measured_mm[1],
        ];
        if all.iter().any(|v| !v.is_finite())
            || f.nominal_d_mm.is_some_and(|d| !d.is_finite())
            || f.measured_d_mm.is_some_and(|d| !d.is_finite())
        {
            return Err(ProcedureError::Missing(format!(
                "feature {}: a coordinate or diameter is not a finite number",
                f.id
            )));
        }
    }
    if features.len() < 3 {
        return Err(ProcedureError::Missing(format!(
            "{} feature(s): a plate fit needs at least 3 holes (offset, rotation and scale \
             are 4 parameters, and their σ needs residuals beyond them)",
            features.len()
        )));
    }
    let r = features
        .iter()
        .map(|f| f.nominal_mm[0].hypot(f.nominal_mm[1]))
        .fold(0.0, f64::max);
    if r <= 0.0 {
        return Err(ProcedureError::IllConditioned(
            "every hole is at the nominal origin: rotation and scale are not determined \
             (measure holes away from the centre)"
                .into(),
        ));
    }
    Ok(r)
}

/// Paired t of the per-hole decrease of the squared left-out error, base → new.
fn paired_t(base: &[[f64; 2]], new: &[[f64; 2]]) -> Option<f64> {
    let n = base.len();
    if n < 2 {
        return None;
    }
    let d: Vec<f64> = base
        .iter()
        .zip(new)
        .map(|(a, b)| (a[0] * a[0] + a[1] * a[1]) - (b[0] * b[0] + b[1] * b[1]))
        .collect();
    let mean = d.iter().sum::<f64>() / n as f64;
    let var = d.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
    let se = (var / n as f64).sqrt();
    (se > 0.0).then(|| mean / se)
}

/// Runs the plate procedure.
pub fn run(features: &[Feature], opts: &Options) -> Result<Outcome, ProcedureError> {
    let r = check(features)?;
    let n = features.len();
    let y = DVector::from_iterator(
        2 * n,
        features
            .iter()
            .flat_map(|f| [f.measured_mm[0], f.measured_mm[1]]),
    );
    let mut undetermined = Vec::new();
    let mut notes = Vec::new();

    // (a)
    let sim = fit(&[Term::Similarity], features, r, &y).map_err(|_| {
        ProcedureError::IllConditioned(
            "the holes coincide: rotation and scale are not determined (measure holes apart)"
                .into(),
        )
    })?;
    let v = propagate(&sim.s.theta, &sim.s.cov, similarity_values, &[]);
    let similarity = Similarity {
        offset_x_um: param("offset_x_um", v[0]),
        offset_y_um: param("offset_y_um", v[1]),
        rotation_urad: param("rotation_urad", v[2]),
        rotation_deg: param("rotation_deg", v[3]),
        scale: param("scale", v[4]),
        scale_ppm: param("scale_ppm", v[5]),
        residual: sim.residual(features),
    };

    // (b)
    let aff_terms = [Term::Similarity, Term::Quadrupole];
    let affine = match fit(&aff_terms, features, r, &y) {
        Err(_) => {
            undetermined.push(
                "anisotropic scale/shear (quadrupole; scale per axis and squareness): the holes \
                 are collinear — measure holes off the line"
                    .into(),
            );
            None
        }
        Ok(m) if m.s.dof == 0 => {
            undetermined.push(format!(
                "anisotropic scale/shear: {n} holes leave no residual to give it a σ (measure \
                 at least 4)"
            ));
            None
        }
        Ok(m) => {
            let v = propagate(&m.s.theta, &m.s.cov, |t| affine_values(t, 4), &[7]);
            let q = param("quadrupole_ppm", v[6]);
            let angle = if q.value > 2.0 * q.sigma {
                Some(param("quadrupole_angle_deg", v[7]))
            } else {
                notes.push(format!(
                    "the quadrupole's magnitude ({:.2} ± {:.2} ppm) is below 2σ: its angle is \
                     not determined",
                    q.value, q.sigma
                ));
                None
            };
            Some(Affine {
                offset_x_um: param("offset_x_um", v[0]),
                offset_y_um: param("offset_y_um", v[1]),
                rotation_urad: param("rotation_urad", v[2]),
                rotation_deg: param("rotation_deg", v[3]),
                scale: param("scale", v[4]),
                scale_ppm: param("scale_ppm", v[5]),
                quadrupole_ppm: q,
                quadrupole_angle_deg: angle,
                scale_x_ppm: param("scale_x_ppm", v[8]),
                scale_y_ppm: param("scale_y_ppm", v[9]),
                squareness_urad: param("squareness_urad", v[10]),
                x_axis_rotation_urad: param("x_axis_rotation_urad", v[11]),
                residual: m.residual(features),
            })
        }
    };

    // (c)
    let selection = select(features, r, &y, sim, opts, &mut undetermined);
    let first = selection.rounds.iter().find_map(|rd| {
        let k = rd.kept.as_ref()?;
        let c = rd.candidates.iter().find(|c| &c.term == k)?;
        Some((rd.base_cv_um, c))
    });
    let missing_effect = if selection.kept.is_empty() {
        match similarity.residual.cv_rms_um {
            Some(cv) => notes.push(format!(
                "no move lowers the cross-validated residual significantly: the similarity \
                 model leaves {:.2} µm radial RMS (CV {:.2} µm), what the holes' scatter is",
                similarity.residual.rms_radial_um, cv
            )),
            None => notes.push(
                "the cross-validated residual is undetermined: no move was judged".to_string(),
            ),
        }
        None
    } else {
        first.map(|(base_cv, c)| {
            format!(
                "the similarity model leaves {:.1} µm radial RMS; adding {} removes it: CV RMS \
                 {:.2} → {:.2} µm",
                similarity.residual.rms_radial_um,
                c.description,
                base_cv,
                c.cv_rms_um.unwrap_or(base_cv)
            )
        })
    };
    let mut beyond = Vec::new();
    for rd in selection
        .rounds
        .iter()
        .skip_while(|rd| rd.kept.is_none())
        .skip(1)
    {
        if let Some(k) = &rd.kept {
            if let Some(c) = rd.candidates.iter().find(|c| &c.term == k) {
                beyond.push(format!(
                    "then {}: CV RMS {:.2} → {:.2} µm (t {:.1})",
                    c.description,
                    rd.base_cv_um,
                    c.cv_rms_um.unwrap_or(rd.base_cv_um),
                    c.t.unwrap_or(0.0)
                ));
            }
        }
    }

    let original_tool = if opts.original_tool {
        match original_tool(features) {
            Ok(o) => {
                if o.qp_magnitude.is_none() {
                    notes.push(
                        "the original tool's quadrupole is not determined (its fit failed, or \
                         the holes lie on one line through the centre)"
                            .into(),
                    );
                }
                Some(o)
            }
            Err(why) => {
                notes.push(format!("the original tool's fit: {why}"));
                None
            }
        }
    } else {
        None
    };
    Ok(Outcome {
        holes: n,
        radius_mm: r,
        similarity,
        affine,
        selection,
        missing_effect,
        beyond,
        original_tool,
        undetermined,
        notes,
    })
}

/// Forward selection by leave-one-hole-out CV, the quadrupole first.
fn select(
    f: &[Feature],
    r: f64,
    y: &DVector<f64>,
    sim: Fitted,
    opts: &Options,
    undetermined: &mut Vec<String>,
) -> Selection {
    let mut cur = sim;
    let mut rounds = Vec::new();
    let mut kept = Vec::new();
    let mut pool: Vec<Term> = monomials();
    let mut first = true;
    // The quadrupole was judged on the current model and not kept.
    let mut quad_judged = false;
    while let Ok(base_loo) = &cur.loo {
        let base_loo = base_loo.clone();
        let base_cv = rms_of(&base_loo) * 1e3;
        let mut cands: Vec<Term> = Vec::new();
        if !cur.terms.contains(&Term::Quadrupole) && !quad_judged {
            cands.push(Term::Quadrupole);
        }
        if !first {
            cands.extend(pool.iter().copied());
        }
        first = false;
        if cands.is_empty() {
            break;
        }
        let mut out = Vec::new();
        let mut best: Option<(f64, Term, Fitted)> = None;
        for c in cands {
            let mut terms = cur.terms.clone();
            terms.push(c);
            let mut cand = Candidate {
                term: c.id(),
                description: c.describe(),
                cv_rms_um: None,
                t: None,
                significant: false,
                undetermined: None,
            };
            match fit(&terms, f, r, y) {
                Err(col) => {
                    let t = term_of_column(&terms, col);
                    cand.undetermined = Some(if t == c {
                        "the holes do not separate it from the model (collinear or too few \
                         holes)"
                            .into()
                    } else {
                        format!("it makes {} undetermined", t.describe())
                    });
                }
                Ok(m) if m.s.dof < 2 => {
                    cand.undetermined = Some("too few holes: no residual left".into());
                }
                Ok(m) => match &m.loo {
                    Err(h) => {
                        cand.undetermined = Some(format!("hole {} alone determines it", f[*h].id));
                    }
                    Ok(l) => {
                        let cv = rms_of(l) * 1e3;
                        let t = paired_t(&base_loo, l);
                        cand.cv_rms_um = Some(cv);
                        cand.t = t;
                        cand.significant = cv < base_cv && t.is_some_and(|t| t >= opts.t_min);
                        if cand.significant && best.as_ref().is_none_or(|b| cv < b.0) {
                            best = Some((cv, c, m));
                        }
                    }
                },
            }
            out.push(cand);
        }
        let kept_now = best.as_ref().map(|b| b.1.id());
        rounds.push(Round {
            base: model_name(&cur.terms),
            base_cv_um: base_cv,
            candidates: out,
            kept: kept_now,
        });
        match best {
            Some((_, t, m)) => {
                kept.push(t.id());
                pool.retain(|p| *p != t);
                cur = m;
                quad_judged = false;
            }
            // The quadrupole not kept: the polynomials next, on the similarity.
            None if rounds.len() == 1 => quad_judged = true,
            None => break,
        }
    }
    if cur.loo.is_err() {
        undetermined.push(
            "the cross-validated residual: a hole alone determines a parameter of the \
             similarity (too few holes)"
                .into(),
        );
    }
    let quad = quad_params(&cur);
    let mut terms = Vec::new();
    let mut c = 0;
    for t in &cur.terms {
        if let Term::Mono { .. } = t {
            terms.push(Param {
                name: format!("{}_um", t.id()),
                value: cur.s.theta[c] * 1e3,
                sigma: cur.s.cov[(c, c)].max(0.0).sqrt() * 1e3,
            });
        }
        c += t.columns();
    }
    Selection {
        rounds,
        kept,
        model: model_name(&cur.terms),
        residual: cur.residual(f),
        terms,
        quadrupole_ppm: quad.as_ref().map(|q| q.0.clone()),
        quadrupole_angle_deg: quad.and_then(|q| q.1),
    }
}

// ---------------------------------------------------------------------------------------
// The original tool

/// Holes whose measured diameter exceeds this are the large (MaNGA) ones, mm.
pub const LARGE_HOLE_MM: f64 = 3.0;
/// The nominal diameter the original tool gives the large holes, mm.
pub const LARGE_NOMINAL_MM: f64 = 3.28;

fn tool_sim(c: &[f64], p: [f64; 2]) -> [f64; 2] {
    // numpy's order: offset + (p·Mᵀ), M = [[c3, −c2], [c2, c3]].
    [
        c[0] + (p[0] * c[3] + p[1] * -c[2]),
        c[1] + (p[0] * c[2] + p[1] * c[3]),
    ]
}

fn tool_quad(c: &[f64], p: [f64; 2]) -> [f64; 2] {
    let r2 = p[0] * p[0] + p[1] * p[1];
    let k = if r2 > 0.0 {
        1.0 + c[0] * 1e-3 * (2.0 * (p[1].atan2(p[0]) - c[1])).cos()
    } else {
        1.0
    };
    [p[0] * k, p[1] * k]
}

fn rms_opt(v: impl Iterator<Item = f64>) -> Option<f64> {
    let (mut s, mut k) = (0.0, 0usize);
    for x in v {
        s += x * x;
        k += 1;
    }
    (k > 0).then(|| (s / k as f64).sqrt())
}

/// The original tool's fit (see the module's documentation).
pub fn original_tool(f: &[Feature]) -> Result<OriginalTool, String> {
    if f.len() < 4 {
        return Err(format!(
            "{} holes: its fit needs at least 4 (lmdif: no fewer functions than parameters)",
            f.len()
        ));
    }
    let meas: Vec<[f64; 2]> = f.iter().map(|h| h.measured_mm).collect();
    let nom: Vec<[f64; 2]> = f.iter().map(|h| h.nominal_mm).collect();
    let mut c = vec![0.0, 0.0, 0.0, 1.0];
    let (info, nfev) = minpack::lmdif(
        |x, fv| {
            for (k, (m, n)) in meas.iter().zip(&nom).enumerate() {
                let p = tool_sim(x, *n);
                fv[k] = (m[0] - p[0]).powi(2) + (m[1] - p[1]).powi(2);
            }
        },
        f.len(),
        &mut c,
        1000,
    );
    if !(1..=4).contains(&info) {
        return Err(format!("its similarity fit failed (lmdif info {info})"));
    }
    let fitp: Vec<[f64; 2]> = nom.iter().map(|n| tool_sim(&c, *n)).collect();
    let mut q = vec![0.01, 0.0];
    let (qinfo, qnfev) = minpack::lmdif(
        |x, fv| {
            for (k, (m, p)) in meas.iter().zip(&fitp).enumerate() {
                let g = tool_quad(x, *p);
                fv[k] = (m[0] - g[0]).powi(2) + (m[1] - g[1]).powi(2);
            }
        },
        f.len(),
        &mut q,
        5000,
    );
    // Its quadrupole is linear in (q·cos 2φ, q·sin 2φ): undetermined where the holes do not
    // separate those two (all at one polar angle modulo 90°), or lie on one line (where no
    // anisotropic term is determined).
    let qcols = DMatrix::from_fn(2 * f.len(), 2, |row, col| {
        let p = nom[row / 2];
        let a = 2.0 * p[1].atan2(p[0]);
        p[row % 2] * if col == 0 { a.cos() } else { a.sin() }
    });
    let zeros = DVector::zeros(2 * f.len());
    let determined = solve(&qcols, &zeros).is_ok()
        && solve(
            &design(&[Term::Similarity, Term::Quadrupole], f, 1.0),
            &zeros,
        )
        .is_ok();
    let qok = (1..=4).contains(&qinfo) && determined;
    if qok {
        // Magnitude positive, angle wrapped into [−π/2, π/2] (the tool's normalisation).
        if q[0] < 0.0 {
            q[0] = -q[0];
            q[1] += std::f64::consts::FRAC_PI_2;
        }
        let mut a = q[1].rem_euclid(2.0 * std::f64::consts::PI);
        if a > std::f64::consts::PI {
            a -= std::f64::consts::PI;
        }
        if a > std::f64::consts::FRAC_PI_2 {
            a -= std::f64::consts::PI;
        }
        q[1] = a;
    }
    let large: Vec<bool> = f
        .iter()
        .map(|h| h.measured_d_mm.is_some_and(|d| d > LARGE_HOLE_MM))
        .collect();
    let mut holes = Vec::with_capacity(f.len());
    for (k, h) in f.iter().enumerate() {
        let e = [meas[k][0] - fitp[k][0], meas[k][1] - fitp[k][1]];
        let g = if qok { tool_quad(&q, fitp[k]) } else { fitp[k] };
        let eq = [meas[k][0] - g[0], meas[k][1] - g[1]];
        holes.push(ToolHole {
            id: h.id.clone(),
            resid_x_mm: e[0],
            resid_y_mm: e[1],
            resid_rad_mm: e[0].hypot(e[1]),
            qp_resid_x_mm: eq[0],
            qp_resid_y_mm: eq[1],
            qp_resid_rad_mm: eq[0].hypot(eq[1]),
        });
    }
    let dia_err = |k: usize| -> Option<f64> {
        let md = f[k].measured_d_mm?;
        let nd = if large[k] {
            LARGE_NOMINAL_MM
        } else {
            f[k].nominal_d_mm?
        };
        Some(md - nd)
    };
    let dia: Vec<Option<f64>> = (0..f.len()).map(dia_err).collect();
    Ok(OriginalTool {
        fit_offset_mm: [c[0], c[1]],
        fit_scale: c[2].hypot(c[3]),
        fit_rot_angle_deg: c[2].atan2(c[3]).to_degrees(),
        qp_magnitude: qok.then(|| q[0] * 1e-3),
        qp_angle_deg: qok.then(|| q[1].to_degrees()),
        resid_rad_err_rms_mm: rms_opt(
            holes
                .iter()
                .zip(&large)
                .filter(|(_, l)| !**l)
                .map(|(h, _)| h.resid_rad_mm),
        ),
        large_resid_rad_err_rms_mm: rms_opt(
            holes
                .iter()
                .zip(&large)
                .filter(|(_, l)| **l)
                .map(|(h, _)| h.resid_rad_mm),
        ),
        dia_err_rms_mm: rms_opt(
            dia.iter()
                .zip(&large)
                .filter(|(_, l)| !**l)
                .filter_map(|(d, _)| *d),
        ),
        large_dia_err_rms_mm: rms_opt(
            dia.iter()
                .zip(&large)
                .filter(|(_, l)| **l)
                .filter_map(|(d, _)| *d),
        ),
        max_dia_err_mm: dia.iter().flatten().copied().reduce(f64::max),
        qp_resid_rad_err_rms_mm: if qok {
            rms_opt(holes.iter().map(|h| h.qp_resid_rad_mm))
        } else {
            None
        },
        all_resid_rad_err_rms_mm: rms_opt(holes.iter().map(|h| h.resid_rad_mm)).unwrap_or(0.0),
        large_holes: large.iter().filter(|l| **l).count(),
        lmdif: [(nfev, info), (qnfev, qinfo)],
        holes,
    })
}

/// MINPACK's `lmdif` (Moré, Garbow, Hillstrom 1980), as scipy's `leastsq` calls it: forward
/// differences with step √ε·|x|, `diag` from the Jacobian's column norms (mode 1),
/// factor 100, ftol = xtol = 1.49012e-8, gtol = 0. Used only to reproduce the original
/// tool's numbers, which depend on where lmdif stops.
mod minpack {
    const EPSMCH: f64 = f64::EPSILON;
    const DWARF: f64 = f64::MIN_POSITIVE;
    const FTOL: f64 = 1.49012e-8;
    const XTOL: f64 = 1.49012e-8;
    const GTOL: f64 = 0.0;
    const FACTOR: f64 = 100.0;

    fn enorm(v: &[f64]) -> f64 {
        v.iter().map(|x| x * x).sum::<f64>().sqrt()
    }

    /// Minimises Σ fᵢ(x)² over x (m functions); returns (info, function evaluations).
    pub fn lmdif(
        mut fcn: impl FnMut(&[f64], &mut [f64]),
        m: usize,
        x: &mut [f64],
        maxfev: usize,
    ) -> (i32, usize) {
        let n = x.len();
        if n == 0 || m < n {
            return (0, 0);
        }
        let mut fvec = vec![0.0; m];
        let mut fjac = vec![0.0; m * n]; // column-major: (i, j) at i + j·m
        let mut diag = vec![0.0; n];
        let mut qtf = vec![0.0; n];
        let mut ipvt = vec![0usize; n];
        let (mut wa1, mut wa2, mut wa3) = (vec![0.0; n], vec![0.0; n], vec![0.0; n]);
        let mut wa4 = vec![0.0; m];
        fcn(x, &mut fvec);
        let mut nfev = 1;
        let mut fnorm = enorm(&fvec);
        let mut par = 0.0;
        let mut iter = 1;
        let mut delta = 0.0;
        let mut xnorm = 0.0;
        let eps = EPSMCH.sqrt();
        loop {
            // Jacobian by forward differences.
            for j in 0..n {
                let temp = x[j];
                let mut h = eps * temp.abs();
                if h == 0.0 {
                    h = eps;
                }
                x[j] = temp + h;
                fcn(x, &mut wa4);
                x[j] = temp;
                for i in 0..m {
                    fjac[i + j * m] = (wa4[i] - fvec[i]) / h;
                }
            }
            nfev += n;
            qrfac(m, n, &mut fjac, &mut ipvt, &mut wa1, &mut wa2, &mut wa3);
            if iter == 1 {
                for j in 0..n {
                    diag[j] = if wa2[j] == 0.0 { 1.0 } else { wa2[j] };
                    wa3[j] = diag[j] * x[j];
                }
                xnorm = enorm(&wa3[..n]);
                delta = FACTOR * xnorm;
                if delta == 0.0 {
                    delta = FACTOR;
                }
            }
            // Qᵀ·fvec, the first n components into qtf.
            wa4[..m].copy_from_slice(&fvec[..m]);
            for j in 0..n {
                if fjac[j + j * m] != 0.0 {
                    let mut sum = 0.0;
                    for i in j..m {
                        sum += fjac[i + j * m] * wa4[i];
                    }
                    let temp = -sum / fjac[j + j * m];
                    for i in j..m {
                        wa4[i] += fjac[i + j * m] * temp;
                    }
                }
                fjac[j + j * m] = wa1[j];
                qtf[j] = wa4[j];
            }
            // Norm of the scaled gradient.
            let mut gnorm: f64 = 0.0;
            if fnorm != 0.0 {
                for j in 0..n {
                    let l = ipvt[j];
                    if wa2[l] != 0.0 {
                        let mut sum = 0.0;
                        for i in 0..=j {
                            sum += fjac[i + j * m] * (qtf[i] / fnorm);
                        }
                        gnorm = gnorm.max((sum / wa2[l]).abs());
                    }
                }
            }
            if gnorm <= GTOL {
                return (4, nfev);
            }
            for j in 0..n {
                diag[j] = diag[j].max(wa2[j]);
            }
            loop {
                lmpar(
                    n, &mut fjac, m, &ipvt, &diag, &qtf, delta, &mut par, &mut wa1, &mut wa2,
                    &mut wa3, &mut wa4,
                );
                for j in 0..n {
                    wa1[j] = -wa1[j];
                    wa2[j] = x[j] + wa1[j];
                    wa3[j] = diag[j] * wa1[j];
                }
                let pnorm = enorm(&wa3[..n]);
                if iter == 1 {
                    delta = delta.min(pnorm);
                }
                fcn(&wa2, &mut wa4);
                nfev += 1;
                let fnorm1 = enorm(&wa4[..m]);
                let mut actred = -1.0;
                if 0.1 * fnorm1 < fnorm {
                    actred = 1.0 - (fnorm1 / fnorm).powi(2);
                }
                for j in 0..n {
                    wa3[j] = 0.0;
                    let l = ipvt[j];
                    let temp = wa1[l];
                    for i in 0..=j {
                        wa3[i] += fjac[i + j * m] * temp;
                    }
                }
                let temp1 = enorm(&wa3[..n]) / fnorm;
                let temp2 = (par.sqrt() * pnorm) / fnorm;
                let prered = temp1 * temp1 + temp2 * temp2 / 0.5;
                let dirder = -(temp1 * temp1 + temp2 * temp2);
                let ratio = if prered != 0.0 { actred / prered } else { 0.0 };
                if ratio <= 0.25 {
                    let mut temp = if actred >= 0.0 {
                        0.5
                    } else {
                        0.5 * dirder / (dirder + 0.5 * actred)
                    };
                    if 0.1 * fnorm1 >= fnorm || temp < 0.1 {
                        temp = 0.1;
                    }
                    delta = temp * delta.min(pnorm / 0.1);
                    par /= temp;
                } else if par == 0.0 || ratio >= 0.75 {
                    delta = pnorm / 0.5;
                    par *= 0.5;
                }
                if ratio >= 1e-4 {
                    for j in 0..n {
                        x[j] = wa2[j];
                        wa2[j] = diag[j] * x[j];
                    }
                    fvec[..m].copy_from_slice(&wa4[..m]);
                    xnorm = enorm(&wa2[..n]);
                    fnorm = fnorm1;
                    iter += 1;
                }
                let mut info = 0;
                if actred.abs() <= FTOL && prered <= FTOL && 0.5 * ratio <= 1.0 {
                    info = 1;
                }
                if delta <= XTOL * xnorm {
                    info = 2;
                }
                if actred.abs() <= FTOL && prered <= FTOL && 0.5 * ratio <= 1.0 && info == 2 {
                    info = 3;
                }
                if info != 0 {
                    return (info, nfev);
                }
                if nfev >= maxfev {
                    info = 5;
                }
                if actred.abs() <= EPSMCH && prered <= EPSMCH && 0.5 * ratio <= 1.0 {
                    info = 6;
                }
                if delta <= EPSMCH * xnorm {
                    info = 7;
                }
                if gnorm <= EPSMCH {
                    info = 8;
                }
                if info != 0 {
                    return (info, nfev);
                }
                if ratio >= 1e-4 {
                    break;
                }
            }
        }
    }

    /// QR with column pivoting by Householder transformations; R's diagonal into `rdiag`,
    /// the columns' norms into `acnorm`.
    fn qrfac(
        m: usize,
        n: usize,
        a: &mut [f64],
        ipvt: &mut [usize],
        rdiag: &mut [f64],
        acnorm: &mut [f64],
        wa: &mut [f64],
    ) {
        for j in 0..n {
            acnorm[j] = enorm(&a[j * m..j * m + m]);
            rdiag[j] = acnorm[j];
            wa[j] = rdiag[j];
            ipvt[j] = j;
        }
        for j in 0..m.min(n) {
            let mut kmax = j;
            for k in j..n {
                if rdiag[k] > rdiag[kmax] {
                    kmax = k;
                }
            }
            if kmax != j {
                for i in 0..m {
                    a.swap(i + j * m, i + kmax * m);
                }
                rdiag[kmax] = rdiag[j];
                wa[kmax] = wa[j];
                ipvt.swap(j, kmax);
            }
            let mut ajnorm = enorm(&a[j + j * m..j * m + m]);
            if ajnorm != 0.0 {
                if a[j + j * m] < 0.0 {
                    ajnorm = -ajnorm;
                }
                for i in j..m {
                    a[i + j * m] /= ajnorm;
                }
                a[j + j * m] += 1.0;
                for k in j + 1..n {
                    let mut sum = 0.0;
                    for i in j..m {
                        sum += a[i + j * m] * a[i + k * m];
                    }
                    let temp = sum / a[j + j * m];
                    for i in j..m {
                        a[i + k * m] -= temp * a[i + j * m];
                    }
                    if rdiag[k] != 0.0 {
                        let temp = a[j + k * m] / rdiag[k];
                        rdiag[k] *= (1.0 - temp * temp).max(0.0).sqrt();
                        if 0.05 * (rdiag[k] / wa[k]).powi(2) <= EPSMCH {
                            rdiag[k] = enorm(&a[j + 1 + k * m..k * m + m]);
                            wa[k] = rdiag[k];
                        }
                    }
                }
            }
            rdiag[j] = -ajnorm;
        }
    }

    /// The Levenberg–Marquardt parameter for the trust region `delta`; the step into `x`.
    #[allow(clippy::too_many_arguments)]
    fn lmpar(
        n: usize,
        r: &mut [f64],
        ldr: usize,
        ipvt: &[usize],
        diag: &[f64],
        qtb: &[f64],
        delta: f64,
        par: &mut f64,
        x: &mut [f64],
        sdiag: &mut [f64],
        wa1: &mut [f64],
        wa2: &mut [f64],
    ) {
        // The Gauss–Newton direction (least squares where R is singular).
        let mut nsing = n;
        for j in 0..n {
            wa1[j] = qtb[j];
            if r[j + j * ldr] == 0.0 && nsing == n {
                nsing = j;
            }
            if nsing < n {
                wa1[j] = 0.0;
            }
        }
        for j in (0..nsing).rev() {
            wa1[j] /= r[j + j * ldr];
            let temp = wa1[j];
            for i in 0..j {
                wa1[i] -= r[i + j * ldr] * temp;
            }
        }
        for j in 0..n {
            x[ipvt[j]] = wa1[j];
        }
        let mut iter = 0;
        for j in 0..n {
            wa2[j] = diag[j] * x[j];
        }
        let mut dxnorm = enorm(&wa2[..n]);
        let mut fp = dxnorm - delta;
        if fp <= 0.1 * delta {
            *par = 0.0;
            return;
        }
        // Lower bound parl.
        let mut parl = 0.0;
        if nsing >= n {
            for j in 0..n {
                let l = ipvt[j];
                wa1[j] = diag[l] * (wa2[l] / dxnorm);
            }
            for j in 0..n {
                let mut sum = 0.0;
                for i in 0..j {
                    sum += r[i + j * ldr] * wa1[i];
                }
                wa1[j] = (wa1[j] - sum) / r[j + j * ldr];
            }
            let temp = enorm(&wa1[..n]);
            parl = ((fp / delta) / temp) / temp;
        }
        // Upper bound paru.
        for j in 0..n {
            let mut sum = 0.0;
            for i in 0..=j {
                sum += r[i + j * ldr] * qtb[i];
            }
            wa1[j] = sum / diag[ipvt[j]];
        }
        let gnorm = enorm(&wa1[..n]);
        let mut paru = gnorm / delta;
        if paru == 0.0 {
            paru = DWARF / delta.min(0.1);
        }
        *par = par.max(parl).min(paru);
        if *par == 0.0 {
            *par = gnorm / dxnorm;
        }
        loop {
            iter += 1;
            if *par == 0.0 {
                *par = DWARF.max(0.001 * paru);
            }
            let temp = par.sqrt();
            for j in 0..n {
                wa1[j] = temp * diag[j];
            }
            qrsolv(n, r, ldr, ipvt, wa1, qtb, x, sdiag, wa2);
            for j in 0..n {
                wa2[j] = diag[j] * x[j];
            }
            dxnorm = enorm(&wa2[..n]);
            let temp = fp;
            fp = dxnorm - delta;
            if fp.abs() <= 0.1 * delta || (parl == 0.0 && fp <= temp && temp < 0.0) || iter == 10 {
                return;
            }
            // Newton's correction.
            for j in 0..n {
                let l = ipvt[j];
                wa1[j] = diag[l] * (wa2[l] / dxnorm);
            }
            for j in 0..n {
                wa1[j] /= sdiag[j];
                let temp = wa1[j];
                for i in j + 1..n {
                    wa1[i] -= r[i + j * ldr] * temp;
                }
            }
            let temp = enorm(&wa1[..n]);
            let parc = ((fp / delta) / temp) / temp;
            if fp > 0.0 {
                parl = parl.max(*par);
            }
            if fp < 0.0 {
                paru = paru.min(*par);
            }
            *par = parl.max(*par + parc);
        }
    }

    /// Solves R·z ≈ Qᵀb with the diagonal D added (Givens rotations): (R; D)·x ≈ (Qᵀb; 0).
    #[allow(clippy::too_many_arguments)]
    fn qrsolv(
        n: usize,
        r: &mut [f64],
        ldr: usize,
        ipvt: &[usize],
        diag: &[f64],
        qtb: &[f64],
        x: &mut [f64],
        sdiag: &mut [f64],
        wa: &mut [f64],
    ) {
        for j in 0..n {
            for i in j..n {
                r[i + j * ldr] = r[j + i * ldr];
            }
            x[j] = r[j + j * ldr];
            wa[j] = qtb[j];
        }
        for j in 0..n {
            let l = ipvt[j];
            if diag[l] != 0.0 {
                for s in sdiag.iter_mut().take(n).skip(j) {
                    *s = 0.0;
                }
                sdiag[j] = diag[l];
                let mut qtbpj = 0.0;
                for k in j..n {
                    if sdiag[k] == 0.0 {
                        continue;
                    }
                    let (sin, cos);
                    if r[k + k * ldr].abs() < sdiag[k].abs() {
                        let cotan = r[k + k * ldr] / sdiag[k];
                        sin = 0.5 / (0.25 + 0.25 * cotan * cotan).sqrt();
                        cos = sin * cotan;
                    } else {
                        let tan = sdiag[k] / r[k + k * ldr];
                        cos = 0.5 / (0.25 + 0.25 * tan * tan).sqrt();
                        sin = cos * tan;
                    }
                    r[k + k * ldr] = cos * r[k + k * ldr] + sin * sdiag[k];
                    let temp = cos * wa[k] + sin * qtbpj;
                    qtbpj = -sin * wa[k] + cos * qtbpj;
                    wa[k] = temp;
                    for i in k + 1..n {
                        let temp = cos * r[i + k * ldr] + sin * sdiag[i];
                        sdiag[i] = -sin * r[i + k * ldr] + cos * sdiag[i];
                        r[i + k * ldr] = temp;
                    }
                }
            }
            sdiag[j] = r[j + j * ldr];
            r[j + j * ldr] = x[j];
        }
        let mut nsing = n;
        for j in 0..n {
            if sdiag[j] == 0.0 && nsing == n {
                nsing = j;
            }
            if nsing < n {
                wa[j] = 0.0;
            }
        }
        for j in (0..nsing).rev() {
            let mut sum = 0.0;
            for i in j + 1..nsing {
                sum += r[i + j * ldr] * wa[i];
            }
            wa[j] = (wa[j] - sum) / sdiag[j];
        }
        for j in 0..n {
            x[ipvt[j]] = wa[j];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// splitmix64 → uniform and normal deviates (a fixed seed: the tests are repeatable).
    struct Rng(u64);

    impl Rng {
        fn uniform(&mut self) -> f64 {
            self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            z ^= z >> 31;
            (z >> 11) as f64 / (1u64 << 53) as f64
        }
        fn normal(&mut self) -> f64 {
            let u = self.uniform().max(1e-300);
            let v = self.uniform();
            (-2.0 * u.ln()).sqrt() * (2.0 * std::f64::consts::PI * v).cos()
        }
    }

    /// The truth of a synthetic plate.
    #[derive(Clone, Copy)]
    struct Truth {
        offset_um: [f64; 2],
        rotation_urad: f64,
        scale_ppm: f64,
        q_ppm: f64,
        phi_deg: f64,
        /// X error ∝ (y/R)³ at the edge, µm.
        dx_y3_um: f64,
        noise_um: f64,
    }

    const R: f64 = 300.0;

    fn plate(t: Truth, n: usize, seed: u64) -> Vec<Feature> {
        let mut rng = Rng(seed);
        let th = t.rotation_urad * 1e-6;
        let s = 1.0 + t.scale_ppm * 1e-6;
        let (q, p2) = (t.q_ppm * 1e-6, 2.0 * t.phi_deg.to_radians());
        let qm = [[q * p2.cos(), q * p2.sin()], [q * p2.sin(), -q * p2.cos()]];
        (0..n)
            .map(|k| {
                let (r, a) = (
                    R * rng.uniform().sqrt(),
                    2.0 * std::f64::consts::PI * rng.uniform(),
                );
                let (x, y) = (r * a.cos(), r * a.sin());
                // s·R(θ)·n, then (I + Q).
                let rx = s * (th.cos() * x - th.sin() * y);
                let ry = s * (th.sin() * x + th.cos() * y);
                let mx = rx + qm[0][0] * rx + qm[0][1] * ry;
                let my = ry + qm[1][0] * rx + qm[1][1] * ry;
                let cubic = t.dx_y3_um * 1e-3 * (y / R).powi(3);
                Feature {
                    id: format!("{}", k + 1),
                    nominal_mm: [x, y],
                    measured_mm: [
                        mx + t.offset_um[0] * 1e-3 + cubic + t.noise_um * 1e-3 * rng.normal(),
                        my + t.offset_um[1] * 1e-3 + t.noise_um * 1e-3 * rng.normal(),
                    ],
                    nominal_d_mm: Some(2.167),
                    measured_d_mm: Some(2.170),
                }
            })
            .collect()
    }

    fn within(p: &Param, truth: f64, k: f64) {
        assert!(
            p.sigma > 0.0 && p.sigma.is_finite(),
            "{}: σ {} not positive",
            p.name,
            p.sigma
        );
        assert!(
            (p.value - truth).abs() <= k * p.sigma,
            "{}: {} ± {} vs truth {truth}",
            p.name,
            p.value,
            p.sigma
        );
    }

    const BASE: Truth = Truth {
        offset_um: [40.0, -25.0],
        rotation_urad: 150.0,
        scale_ppm: 12.0,
        q_ppm: 0.0,
        phi_deg: 0.0,
        dx_y3_um: 0.0,
        noise_um: 2.0,
    };

    #[test]
    fn plate_similarity_and_shear_recovered_within_sigma() {
        let t = Truth {
            q_ppm: 20.0,
            phi_deg: 30.0,
            ..BASE
        };
        let f = plate(t, 200, 7);
        let o = run(&f, &Options::default()).unwrap();
        let a = o.affine.as_ref().expect("determined");
        within(&a.offset_x_um, t.offset_um[0], 4.0);
        within(&a.offset_y_um, t.offset_um[1], 4.0);
        within(&a.rotation_urad, t.rotation_urad, 4.0);
        within(&a.scale_ppm, t.scale_ppm, 4.0);
        within(&a.quadrupole_ppm, t.q_ppm, 4.0);
        within(
            a.quadrupole_angle_deg.as_ref().expect("q significant"),
            t.phi_deg,
            4.0,
        );
        // The CMM engineer's terms of the same map: e_x − e_y = 2q·cos 2φ, squareness
        // −2q·sin 2φ (to first order), mean scale the similarity's.
        let p2 = 2.0 * t.phi_deg.to_radians();
        within(&a.scale_x_ppm, t.scale_ppm + t.q_ppm * p2.cos(), 4.0);
        within(&a.scale_y_ppm, t.scale_ppm - t.q_ppm * p2.cos(), 4.0);
        within(&a.squareness_urad, -2.0 * t.q_ppm * p2.sin(), 4.0);
        // σ honest: the residual is the noise (2 µm per coordinate: 2.83 radial).
        assert!((a.residual.rms_radial_um - 2.0 * 2f64.sqrt()).abs() < 0.3);
        // The similarity misses it, and the procedure names it.
        assert!(o.similarity.residual.rms_radial_um > 1.5 * a.residual.rms_radial_um);
        assert_eq!(
            o.selection.kept.first().map(String::as_str),
            Some("quadrupole")
        );
        let m = o.missing_effect.as_deref().unwrap();
        assert!(m.contains("anisotropic scale/shear (quadrupole)"), "{m}");
        assert!(!serde_json::to_string(&o).unwrap().contains("NaN"));
    }

    #[test]
    fn plate_similarity_recovered_and_nothing_named_without_shear() {
        let f = plate(BASE, 150, 11);
        let o = run(&f, &Options::default()).unwrap();
        let s = &o.similarity;
        within(&s.offset_x_um, BASE.offset_um[0], 4.0);
        within(&s.offset_y_um, BASE.offset_um[1], 4.0);
        within(&s.rotation_urad, BASE.rotation_urad, 4.0);
        within(&s.scale_ppm, BASE.scale_ppm, 4.0);
        within(
            &s.rotation_deg,
            (BASE.rotation_urad * 1e-6).to_degrees(),
            4.0,
        );
        within(&s.scale, 1.0 + BASE.scale_ppm * 1e-6, 4.0);
        within(&o.affine.as_ref().unwrap().quadrupole_ppm, 0.0, 4.0);
        assert!(o.missing_effect.is_none(), "{:?}", o.missing_effect);
        assert!(o.selection.kept.is_empty());
        // Every candidate was judged, with its CV figure.
        let round2 = &o.selection.rounds[1];
        assert_eq!(round2.candidates.len(), 14);
        assert!(round2.candidates.iter().all(|c| c.cv_rms_um.is_some()));
    }

    #[test]
    fn plate_cubic_distortion_found_beyond_the_linear_map() {
        let t = Truth {
            q_ppm: 15.0,
            phi_deg: -50.0,
            dx_y3_um: 12.0,
            noise_um: 1.0,
            ..BASE
        };
        let f = plate(t, 300, 3);
        let o = run(&f, &Options::default()).unwrap();
        assert_eq!(o.selection.kept[0], "quadrupole");
        assert!(
            o.selection.kept.iter().any(|k| k == "dx_y3"),
            "{:?}",
            o.selection.kept
        );
        let c = o
            .selection
            .terms
            .iter()
            .find(|p| p.name == "dx_y3_um")
            .unwrap();
        within(c, t.dx_y3_um, 4.0);
        within(o.selection.quadrupole_ppm.as_ref().unwrap(), t.q_ppm, 4.0);
        assert!(!o.beyond.is_empty());
        assert!(o.selection.residual.cv_rms_um.unwrap() < 1.7);
    }

    #[test]
    fn plate_collinear_holes_leave_the_shear_undetermined_without_nan() {
        let f: Vec<Feature> = (0..12)
            .map(|k| {
                let u = -200.0 + 40.0 * k as f64;
                Feature {
                    id: format!("h{k}"),
                    nominal_mm: [u, 0.5 * u],
                    measured_mm: [u + 0.01 + 1e-4 * (k as f64).sin(), 0.5 * u - 0.02],
                    nominal_d_mm: None,
                    measured_d_mm: None,
                }
            })
            .collect();
        let o = run(&f, &Options::default()).unwrap();
        assert!(o.affine.is_none());
        assert!(
            o.undetermined.iter().any(|u| u.contains("collinear")),
            "{:?}",
            o.undetermined
        );
        let q = &o.selection.rounds[0].candidates[0];
        assert!(q.undetermined.is_some() && q.cv_rms_um.is_none());
        assert!(o.original_tool.as_ref().unwrap().qp_magnitude.is_none());
        let js = serde_json::to_string(&o).unwrap();
        assert!(!js.contains("NaN") && !js.contains("inf"), "{js}");
    }

    #[test]
    fn plate_too_few_holes_is_named() {
        let f = plate(BASE, 2, 1);
        let e = run(&f, &Options::default()).unwrap_err().to_string();
        assert!(e.contains("at least 3 holes"), "{e}");
    }

    /// The port of lmdif against scipy.optimize.leastsq (scipy 1.17) on a synthetic plate:
    /// the same coefficients and the same number of function evaluations.
    #[test]
    fn plate_original_tool_fit_matches_scipy_leastsq() {
        let n = 40;
        let f: Vec<Feature> = (0..n)
            .map(|k| {
                let kf = k as f64;
                let (r, a) = (250.0 * ((kf + 1.0) / n as f64).sqrt(), 2.4 * kf);
                let (x, y) = (r * a.cos(), r * a.sin());
                let qf = 1.0 + 2e-5 * (2.0 * (a - 25f64.to_radians())).cos();
                let (th, s) = (3e-4f64, 1.0 + 1e-5);
                Feature {
                    id: format!("{k}"),
                    nominal_mm: [x, y],
                    measured_mm: [
                        0.05 + s * (th.cos() * x - th.sin() * y) * qf + 0.004 * (7.3 * kf).sin(),
                        -0.03 + s * (th.sin() * x + th.cos() * y) * qf + 0.004 * (5.1 * kf).cos(),
                    ],
                    nominal_d_mm: None,
                    measured_d_mm: None,
                }
            })
            .collect();
        let o = original_tool(&f).unwrap();
        let c = [
            0.05019614720893729,
            -0.029709894346109617,
            0.00030063133891997497,
            1.0000092364059185,
        ];
        // Not bit for bit: the path of lmdif's finite differences on Σ r⁴ is sensitive to
        // the last bits of every function value (numpy's dot, its trigonometry), so the
        // stopping point agrees to ~1e-8 mm and the quadrupole to ~1e-4 of itself.
        assert!((o.fit_offset_mm[0] - c[0]).abs() < 1e-7, "{o:?}");
        assert!((o.fit_offset_mm[1] - c[1]).abs() < 1e-7, "{o:?}");
        assert!((o.fit_scale - c[2].hypot(c[3])).abs() < 1e-9);
        assert!((o.fit_rot_angle_deg - c[2].atan2(c[3]).to_degrees()).abs() < 1e-6);
        assert_eq!(o.lmdif[0].1, 2, "stopped by the step-size test, as scipy's");
        let q = [0.01851502901483146, 0.3749059927358013];
        assert!((o.qp_magnitude.unwrap() / (q[0] * 1e-3) - 1.0).abs() < 1e-3);
        assert!((o.qp_angle_deg.unwrap() - q[1].to_degrees()).abs() < 0.01);
        assert_eq!(o.lmdif[1].1, 1, "stopped by the reduction test, as scipy's");
        // And it is the tool's stopping point, not the least-squares optimum.
        let l2 = run(
            &f,
            &Options {
                original_tool: false,
                ..Options::default()
            },
        )
        .unwrap();
        let d = (l2.similarity.offset_x_um.value * 1e-3 - c[0]).abs();
        assert!(d > 1e-6, "least squares {d} mm from scipy's stopping point");
    }
}
