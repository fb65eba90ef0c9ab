//! The iterative orthogonal-distance solver circles and spheres share (in D dimensions):
//! Kåsa and Pratt starts, Levenberg–Marquardt, Newton polish.

use super::*;

/// Result of a radial (circle or sphere) fit in scaled coordinates.
pub(super) struct RadialSolution {
    pub(super) center: Vec<f64>,
    pub(super) radius: f64,
    pub(super) residuals: Vec<f64>,
    pub(super) iterations: usize,
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
pub(super) fn radial_fit<const D: usize>(
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
