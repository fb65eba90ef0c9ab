//! The compact model ([`compact`]): at most 8 temperature terms by forward selection, lags
//! refined, their σ; and the `thermal_drift` effect they make ([`effect`]).

use super::*;

/// A model the corrector can hold ([`crate::effects::thermal_drift`]): at most `max_terms`
/// temperature terms (sensor, τ) of the same columns, chosen by forward selection — each step
/// the term whose addition gives the lowest cross-validated error (ridge weight chosen with
/// it), while it lowers that error by `min_gain` — and judged on the same held-out rows.
///
/// Then each chosen lag (τ > 0) is refined off the basis: ln τ by golden-section search
/// within a factor 4 of its basis value, minimising the fit rows' squared residual with the
/// other terms refitted (two passes over the terms). The refined lags are kept only when they
/// also lower the cross-validated error (else the basis lags stay, `refined` false). Their
/// uncertainties are those of the nonlinear least squares: s²(JᵀJ)⁻¹ over (c0, k_j, ln τ_j)
/// with J the prediction's Jacobian over the fit rows, inflated for the residual's lag-1
/// autocorrelation by (1 + ρ)/(1 − ρ); the coefficients' σ add the spread over the
/// cross-validation's fits in quadrature, as the full model's do.
#[derive(Debug, Clone, Serialize)]
pub struct Compact {
    /// The channel.
    pub channel: String,
    /// The constant, µm.
    pub offset_um: f64,
    /// Its terms (temperature, µm/K), in the order they were chosen.
    pub terms: Vec<Term>,
    /// The temperature each term is measured from (the sensor's first reading), °C.
    pub reference_c: Vec<f64>,
    /// Ridge weight.
    pub lambda: f64,
    /// Cross-validated mean absolute error, µm.
    pub cv_mae_um: f64,
    /// Whether the lags were refined off the basis (see [`Compact`]).
    pub refined: bool,
    /// The residual's lag-1 autocorrelation over the fit rows (what inflated the σ).
    pub residual_rho: f64,
    /// Errors over the held-out rows.
    pub heldout: Errors,
}

/// A source's signal as the columns use it (its change since the first row; a heat source
/// normalised and raised to the term's power), to be lagged anew.
pub(super) fn signal(rec: &Recording, t: &Term) -> Option<Vec<f64>> {
    let s = rec.sources.iter().find(|s| s.name == t.source)?;
    Some(match t.kind {
        SourceKind::Temperature => s.values.iter().map(|v| v - s.values[0]).collect(),
        SourceKind::HeatSource => s
            .values
            .iter()
            .map(|v| (v / t.full_scale).powi(t.power as i32))
            .collect(),
    })
}

/// Sum of squared residuals over rows `0..nf` of the ridge fit of the columns.
pub(super) fn sse(cols: &[&Vec<f64>], y: &[f64], nf: usize, lambda: f64) -> f64 {
    match Ridge::fit(cols, y, (0, nf), lambda) {
        Some(m) => (0..nf).map(|r| (y[r] - m.predict(cols, r)).powi(2)).sum(),
        None => f64::INFINITY,
    }
}

/// Golden-section minimum of `f` over [a, b].
pub(super) fn golden(mut a: f64, mut b: f64, iters: usize, mut f: impl FnMut(f64) -> f64) -> f64 {
    let g = (5f64.sqrt() - 1.0) / 2.0;
    let (mut c, mut d) = (b - g * (b - a), a + g * (b - a));
    let (mut fc, mut fd) = (f(c), f(d));
    for _ in 0..iters {
        if fc < fd {
            (b, d, fd) = (d, c, fc);
            c = b - g * (b - a);
            fc = f(c);
        } else {
            (a, c, fc) = (c, d, fd);
            d = a + g * (b - a);
            fd = f(d);
        }
    }
    if fc < fd {
        c
    } else {
        d
    }
}

/// The lag-1 autocorrelation of a residual, clamped to ±0.999.
pub(super) fn lag1(e: &[f64]) -> f64 {
    let n = e.len();
    if n < 3 {
        return 0.0;
    }
    let m = e.iter().sum::<f64>() / n as f64;
    let den: f64 = e.iter().map(|v| (v - m) * (v - m)).sum();
    let num: f64 = (1..n).map(|i| (e[i] - m) * (e[i - 1] - m)).sum();
    if den > 0.0 {
        (num / den).clamp(-0.999, 0.999)
    } else {
        0.0
    }
}

/// The compact model of channel `channel` (see [`Compact`]).
pub fn compact(
    rec: &Recording,
    opt: &Options,
    channel: usize,
    max_terms: usize,
) -> Result<Compact, ProcedureError> {
    check(rec, opt)?;
    let ch = rec
        .channels
        .get(channel)
        .ok_or_else(|| ProcedureError::Missing(format!("no channel {channel} in the recording")))?;
    let n = rec.t_s.len();
    let nf = opt.heldout_from;
    let (cols, _, _) = columns(rec, opt);
    let y: Vec<f64> = ch.mm.iter().map(|v| v * 1e3).collect();
    let fl = folds(&block_bounds(nf, opt.blocks));
    let candidates: Vec<usize> = (0..cols.len())
        .filter(|&j| cols[j].term.kind == SourceKind::Temperature)
        .collect();
    let mut chosen: Vec<usize> = vec![];
    let (mut cur, mut lambda) = (best_lambda(&[], &y, &fl, &opt.lambdas).0, 0.0);
    while chosen.len() < max_terms {
        let mut best: Option<(usize, f64, f64)> = None;
        for &j in candidates.iter().filter(|j| !chosen.contains(j)) {
            let mut idx = chosen.clone();
            idx.push(j);
            let c: Vec<&Vec<f64>> = idx.iter().map(|&i| &cols[i].x).collect();
            let (e, l, _) = best_lambda(&c, &y, &fl, &opt.lambdas);
            if best.is_none_or(|b| e < b.1) {
                best = Some((j, e, l));
            }
        }
        let Some((j, e, l)) = best else { break };
        if !(e < cur * (1.0 - opt.min_gain)) {
            break;
        }
        chosen.push(j);
        (cur, lambda) = (e, l);
    }
    // The chosen terms and their columns, then their lags refined off the basis.
    let mut tterms: Vec<Term> = chosen.iter().map(|&i| cols[i].term.clone()).collect();
    let mut xs: Vec<Vec<f64>> = chosen.iter().map(|&i| cols[i].x.clone()).collect();
    let signals: Vec<Option<Vec<f64>>> = tterms.iter().map(|t| signal(rec, t)).collect();
    let mut refined = false;
    if tterms.iter().any(|t| t.tau_s > 0.0) {
        let (mut rt, mut rx) = (tterms.clone(), xs.clone());
        for _pass in 0..2 {
            for j in 0..rt.len() {
                let (Some(sig), true) = (&signals[j], rt[j].tau_s > 0.0) else {
                    continue;
                };
                let base = tterms[j].tau_s;
                let u = golden((base / 4.0).ln(), (base * 4.0).ln(), 24, |u| {
                    let mut trial = rx.clone();
                    trial[j] = Lag { tau_s: u.exp() }.run(&rec.t_s, sig);
                    let c: Vec<&Vec<f64>> = trial.iter().collect();
                    sse(&c, &y, nf, lambda)
                });
                rt[j].tau_s = u.exp();
                rx[j] = Lag { tau_s: rt[j].tau_s }.run(&rec.t_s, sig);
            }
        }
        let c: Vec<&Vec<f64>> = rx.iter().collect();
        let (e, l, _) = best_lambda(&c, &y, &fl, &opt.lambdas);
        if e < cur {
            (tterms, xs, cur, lambda, refined) = (rt, rx, e, l, true);
        }
    }
    let c: Vec<&Vec<f64>> = xs.iter().collect();
    let (mut offset_um, mut terms, mut pred) = (
        y[..nf].iter().sum::<f64>() / nf as f64,
        vec![],
        vec![0.0; n],
    );
    pred.iter_mut().for_each(|p| *p = offset_um);
    if !c.is_empty() {
        let m = Ridge::fit(&c, &y, (0, nf), lambda).ok_or_else(|| {
            ProcedureError::IllConditioned(format!("{}: the compact model does not solve", ch.name))
        })?;
        offset_um = m.ybar;
        for (j, t0) in tterms.iter().enumerate() {
            let mut t = t0.clone();
            t.k = m.k(j);
            t.contribution_um = (t.k * m.sd[j]).abs();
            offset_um -= t.k * m.mean[j];
            terms.push(t);
        }
        for (r, p) in pred.iter_mut().enumerate() {
            *p = m.predict(&c, r);
        }
        let (_, _, fold_ks) = best_lambda(&c, &y, &fl, &[lambda]);
        uncertainties(rec, &mut terms, &signals, &xs, &y, &pred, nf, &fold_ks);
    }
    let rho = lag1(&(0..nf).map(|r| y[r] - pred[r]).collect::<Vec<_>>());
    let reference_c = terms
        .iter()
        .map(|t| {
            rec.sources
                .iter()
                .find(|s| s.name == t.source)
                .map_or(0.0, |s| s.values[0])
        })
        .collect();
    Ok(Compact {
        channel: ch.name.clone(),
        offset_um,
        terms,
        reference_c,
        lambda,
        cv_mae_um: cur,
        refined,
        residual_rho: rho,
        heldout: errors(&y, &pred, (nf, n)),
    })
}

/// The compact model's σ (see [`Compact`]): Gauss–Newton over (c0, k_j, ln τ_j for τ_j > 0)
/// at the fitted values, inflated for the residual's autocorrelation; each k's σ adds the
/// spread over the cross-validation's fits.
#[allow(clippy::too_many_arguments)]
pub(super) fn uncertainties(
    rec: &Recording,
    terms: &mut [Term],
    signals: &[Option<Vec<f64>>],
    xs: &[Vec<f64>],
    y: &[f64],
    pred: &[f64],
    nf: usize,
    fold_ks: &[Vec<f64>],
) {
    let m = terms.len();
    let lagged: Vec<usize> = (0..m)
        .filter(|&j| terms[j].tau_s > 0.0 && signals[j].is_some())
        .collect();
    let p = 1 + m + lagged.len();
    // ∂x_j/∂ln τ_j by central differences.
    let h: f64 = 1e-3;
    let dx: Vec<Vec<f64>> = lagged
        .iter()
        .map(|&j| {
            let sig = signals[j].as_ref().expect("filtered");
            let up = Lag {
                tau_s: terms[j].tau_s * h.exp(),
            }
            .run(&rec.t_s, sig);
            let dn = Lag {
                tau_s: terms[j].tau_s * (-h).exp(),
            }
            .run(&rec.t_s, sig);
            up.iter()
                .zip(&dn)
                .map(|(a, b)| (a - b) / (2.0 * h))
                .collect()
        })
        .collect();
    let mut jtj = DMatrix::<f64>::zeros(p, p);
    let mut row = vec![0.0; p];
    for r in 0..nf {
        row[0] = 1.0;
        for j in 0..m {
            row[1 + j] = xs[j][r];
        }
        for (q, &j) in lagged.iter().enumerate() {
            row[1 + m + q] = terms[j].k * dx[q][r];
        }
        for a in 0..p {
            for b in a..p {
                jtj[(a, b)] += row[a] * row[b];
            }
        }
    }
    for a in 0..p {
        for b in 0..a {
            jtj[(a, b)] = jtj[(b, a)];
        }
    }
    let e: Vec<f64> = (0..nf).map(|r| y[r] - pred[r]).collect();
    let rho = lag1(&e);
    let s2 = e.iter().map(|v| v * v).sum::<f64>() / (nf as f64 - p as f64).max(1.0);
    let inflate = ((1.0 + rho) / (1.0 - rho)).max(1.0);
    // A singular JᵀJ (a lag that does not act) leaves that σ undetermined: infinite.
    let cov = jtj.clone().pseudo_inverse(1e-12 * jtj.norm()).ok();
    for j in 0..m {
        let stat = cov.as_ref().map_or(f64::INFINITY, |c| {
            (c[(1 + j, 1 + j)].max(0.0) * s2 * inflate).sqrt()
        });
        let v: Vec<f64> = fold_ks.iter().filter_map(|ks| ks.get(j).copied()).collect();
        let spread = if v.len() > 1 {
            let mv = v.iter().sum::<f64>() / v.len() as f64;
            (v.iter().map(|x| (x - mv) * (x - mv)).sum::<f64>() / (v.len() - 1) as f64).sqrt()
        } else {
            0.0
        };
        terms[j].sigma = (stat * stat + spread * spread).sqrt();
    }
    for (q, &j) in lagged.iter().enumerate() {
        let su = cov.as_ref().map_or(f64::INFINITY, |c| {
            (c[(1 + m + q, 1 + m + q)].max(0.0) * s2 * inflate).sqrt()
        });
        terms[j].tau_sigma_s = Some(terms[j].tau_s * su);
    }
}

/// The `thermal_drift` effect of compact models, each along its machine axis (0, 1, 2 for x,
/// y, z): the union of their terms, each term's k along the axes whose model has it.
pub fn effect(
    models: &[(&Compact, usize)],
) -> Result<crate::effects::thermal_drift::Config, ProcedureError> {
    use crate::effects::thermal_drift::{Config, Term as EffectTerm, MAX_TERMS};
    let mut c = Config {
        id: None,
        offset_mm: [0.0; 3],
        terms: vec![],
    };
    for (m, axis) in models {
        if *axis > 2 {
            return Err(ProcedureError::Missing(format!("axis {axis}: 0, 1 or 2")));
        }
        c.offset_mm[*axis] = m.offset_um * 1e-3;
        for (t, &r) in m.terms.iter().zip(&m.reference_c) {
            let i = match c
                .terms
                .iter()
                .position(|e| e.sensor == t.source && e.tau_s == t.tau_s)
            {
                Some(i) => i,
                None => {
                    c.terms.push(EffectTerm {
                        sensor: t.source.clone(),
                        tau_s: t.tau_s,
                        reference_c: r,
                        k_mm_per_k: [0.0; 3],
                        tau_s_u: t.tau_sigma_s.filter(|v| v.is_finite()),
                    });
                    c.terms.len() - 1
                }
            };
            c.terms[i].k_mm_per_k[*axis] = t.k * 1e-3;
        }
    }
    if c.terms.len() > MAX_TERMS {
        return Err(ProcedureError::IllConditioned(format!(
            "the models need {} lagged sensors; an effect holds at most {MAX_TERMS}: fewer terms \
             per channel",
            c.terms.len()
        )));
    }
    Ok(c)
}
