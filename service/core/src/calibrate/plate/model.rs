//! The plate's model terms (similarity, the linear map, monomials to cubic) and their least
//! squares: design, solve, leave-one-out residuals, the parameters propagated from them.

use super::*;

// ---------------------------------------------------------------------------------------
// Model terms

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Term {
    /// Offset x, y; a, b of s·R(θ) = [[a, −b], [b, a]].
    Similarity,
    /// q1, q2: A += [[q1, q2], [q2, −q1]].
    Quadrupole,
    /// Error along `axis` (0: X, 1: Y) ∝ (x/R)^i·(y/R)^j, coefficient in mm.
    Mono { axis: usize, i: u32, j: u32 },
}

pub(super) fn superscript(i: u32) -> &'static str {
    match i {
        2 => "²",
        3 => "³",
        _ => "",
    }
}

pub(super) fn power(v: &str, i: u32) -> String {
    match i {
        0 => String::new(),
        1 => v.to_string(),
        _ => format!("{v}{}", superscript(i)),
    }
}

impl Term {
    pub(super) fn id(self) -> String {
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

    pub(super) fn describe(self) -> String {
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

    pub(super) fn columns(self) -> usize {
        match self {
            Term::Similarity => 4,
            Term::Quadrupole => 2,
            Term::Mono { .. } => 1,
        }
    }

    /// This term's columns' entries for a hole at nominal (x, y): per column, its (X, Y) rows.
    pub(super) fn rows(self, x: f64, y: f64, r: f64, out: &mut Vec<[f64; 2]>) {
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

pub(super) fn monomials() -> Vec<Term> {
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

pub(super) fn model_name(terms: &[Term]) -> String {
    terms.iter().map(|t| t.id()).collect::<Vec<_>>().join(" + ")
}

// ---------------------------------------------------------------------------------------
// Least squares

/// A solved linear least squares over the holes' X and Y rows.
pub(super) struct Solved {
    pub(super) theta: Vec<f64>,
    /// (XᵀX)⁻¹.
    pub(super) inv: DMatrix<f64>,
    /// (XᵀX)⁻¹·RSS/dof.
    pub(super) cov: DMatrix<f64>,
    pub(super) resid: Vec<[f64; 2]>,
    pub(super) dof: usize,
}

/// The design matrix of `terms`: 2n rows (X then Y of each hole), one column per parameter.
pub(super) fn design(terms: &[Term], f: &[Feature], r: f64) -> DMatrix<f64> {
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
pub(super) fn solve(x: &DMatrix<f64>, y: &DVector<f64>) -> Result<Solved, usize> {
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
pub(super) fn loo(x: &DMatrix<f64>, s: &Solved) -> Result<Vec<[f64; 2]>, usize> {
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

pub(super) fn rms_of(e: &[[f64; 2]]) -> f64 {
    if e.is_empty() {
        return 0.0;
    }
    (e.iter().map(|v| v[0] * v[0] + v[1] * v[1]).sum::<f64>() / e.len() as f64).sqrt()
}

/// A fitted model and its left-out errors.
pub(super) struct Fitted {
    pub(super) terms: Vec<Term>,
    pub(super) x: DMatrix<f64>,
    pub(super) s: Solved,
    pub(super) loo: Result<Vec<[f64; 2]>, usize>,
}

pub(super) fn fit(
    terms: &[Term],
    f: &[Feature],
    r: f64,
    y: &DVector<f64>,
) -> Result<Fitted, usize> {
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
pub(super) fn term_of_column(terms: &[Term], col: usize) -> Term {
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
    pub(super) fn residual(&self, f: &[Feature]) -> Residual {
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
    pub(super) fn linear(theta: &[f64], quad: Option<usize>) -> ([f64; 2], [[f64; 2]; 2]) {
        let (ta, tb) = (theta[2], theta[3]);
        let (q1, q2) = quad.map_or((0.0, 0.0), |k| (theta[k], theta[k + 1]));
        (
            [theta[0], theta[1]],
            [[ta + q1, -tb + q2], [tb + q2, ta - q1]],
        )
    }

    pub(super) fn quad_index(&self) -> Option<usize> {
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
pub(super) fn propagate(
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

pub(super) fn param(name: &str, v: (f64, f64)) -> Param {
    Param {
        name: name.into(),
        value: v.0,
        sigma: v.1,
    }
}

/// The left polar decomposition A = s·(I + Q)·R(θ): (θ rad, s, q, φ deg in (−90, 90]).
pub(super) fn polar(a: [[f64; 2]; 2]) -> (f64, f64, f64, f64) {
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
pub(super) fn similarity_values(t: &[f64]) -> Vec<f64> {
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
pub(super) fn affine_values(t: &[f64], quad: usize) -> Vec<f64> {
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
pub(super) fn quad_params(m: &Fitted) -> Option<(Param, Option<Param>)> {
    let k = m.quad_index()?;
    let v = propagate(&m.s.theta, &m.s.cov, |t| affine_values(t, k), &[7]);
    let q = param("quadrupole_ppm", v[6]);
    let ang = (q.value > 2.0 * q.sigma).then(|| param("quadrupole_angle_deg", v[7]));
    Some((q, ang))
}
