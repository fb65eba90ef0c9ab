//! `calibrate thermal-drift`: the thermal displacement of the tool (or probe) against the
//! part, measured over hours with the structure's temperatures (ISO 230-3's environmental
//! and spindle-heating tests), turned into a model of the drift from the temperatures.
//!
//! Model, per measured channel: d(t) = c0 + Σ_s Σ_τ k_{s,τ}·L_τ[x_s](t), with x_s a source's
//! change since the recording's first row — a temperature ΔT_s (°C) or a heat source's
//! signal (the spindle speed n, as n/n_max and (n/n_max)²: friction grows with n, windage
//! and bearing losses with n²) — and L_τ the first-order lag of
//! [`crate::effects::thermal_drift::Lag`] for every τ of a fixed basis (0, 600, 2400,
//! 9600 s by default: the heat path's response as a mix of exponentials, the distributed-lag
//! form of the heat-transfer models of the machine-tool literature).
//!
//! How it is fitted and judged (never on the rows it reports):
//! * The recording is split in time: the rows before `heldout_from` fit, the rest are held
//!   out and only reported.
//! * The fit rows are cut into `blocks` contiguous blocks of time; the cross-validation is
//!   forward-chaining, as the held-out period is later in time: fit on the blocks before m,
//!   predict the next three, for m from 40 % of the blocks on; the figure is the mean
//!   absolute error over all predicted rows.
//! * Coefficients are a ridge regression on standardised columns (the intercept free), its
//!   weight chosen from a grid by that cross-validation: with tens of lagged columns that are
//!   nearly collinear, the ridge shares a coefficient between them instead of letting two
//!   cancel.
//! * Sensors that carry the same information (|r| ≥ 0.99 between their ΔT over the fit rows)
//!   are named confounded and only the first is fitted; the lags of one source that the
//!   recording cannot tell apart (their columns |r| ≥ 0.995) are named.
//! * The loop of the model lab, on this data: from the nominal model (no thermal effect: a
//!   constant), each candidate group — the temperatures as read, the temperatures through
//!   their lags, the heat source through its lags — is scored by the cross-validation; the
//!   best is added while it lowers the cross-validated error by at least `min_gain`; every
//!   step's held-out error is reported beside it.
//! * Uncertainties: the ridge's covariance from the residual, inflated for the residual's
//!   autocorrelation (a drift's residual is far from white: n_eff = n·(1 − ρ)/(1 + ρ)), and in
//!   quadrature the spread of each coefficient over the cross-validation's fits (what the
//!   split moved).

use super::ProcedureError;
use crate::effects::thermal_drift::Lag;
use nalgebra::{DMatrix, DVector};
use serde::Serialize;

mod compact;
mod ridge;

pub use compact::{compact, effect, Compact};
use ridge::*;

/// What a source is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum SourceKind {
    /// A temperature of the structure, °C.
    Temperature,
    /// A heat source's signal (the spindle speed), in its own unit.
    HeatSource,
}

/// One input signal, a value per row.
#[derive(Debug, Clone)]
pub struct Source {
    /// Its name (a column, a sensor).
    pub name: String,
    /// What it is.
    pub kind: SourceKind,
    /// Its values per row.
    pub values: Vec<f64>,
}

/// One measured displacement, a value per row, mm.
#[derive(Debug, Clone)]
pub struct Channel {
    /// Its name.
    pub name: String,
    /// Displacement per row, mm.
    pub mm: Vec<f64>,
}

/// A drift recording: rows at times `t_s`, every source and channel a value per row.
#[derive(Debug, Clone)]
pub struct Recording {
    /// Time of each row, s, increasing.
    pub t_s: Vec<f64>,
    /// Temperatures and heat sources.
    pub sources: Vec<Source>,
    /// Measured displacements.
    pub channels: Vec<Channel>,
}

/// How the procedure fits.
#[derive(Debug, Clone)]
pub struct Options {
    /// First held-out row: rows before it fit, rows from it are only reported.
    pub heldout_from: usize,
    /// Lags of the basis, s (0: the signal as read).
    pub taus_s: Vec<f64>,
    /// Contiguous blocks of the fit rows for the cross-validation.
    pub blocks: usize,
    /// Ridge weights tried (relative to the rows: the penalty is λ·n·|b|² on standardised
    /// columns).
    pub lambdas: Vec<f64>,
    /// A candidate group is added when it lowers the cross-validated error by this fraction.
    pub min_gain: f64,
    /// |r| at or above which two sensors are confounded.
    pub confounded_r: f64,
}

impl Default for Options {
    fn default() -> Self {
        Options {
            heldout_from: 0,
            taus_s: vec![0.0, 600.0, 2400.0, 9600.0],
            blocks: 10,
            lambdas: (0..16).map(|i| 10f64.powf(-6.0 + 0.5 * i as f64)).collect(),
            min_gain: 0.05,
            confounded_r: 0.99,
        }
    }
}

/// One column of the model: a source through a lag.
#[derive(Debug, Clone, Serialize)]
pub struct Term {
    /// The source.
    pub source: String,
    /// `temperature` or `heat_source`.
    pub kind: SourceKind,
    /// Power of the source's normalised signal (1, or 2 for a heat source's square).
    pub power: u32,
    /// The lag, s.
    pub tau_s: f64,
    /// The lag's standard uncertainty, s, where the lag was refined (a compact model's terms);
    /// `None` for a lag of the fixed basis.
    pub tau_sigma_s: Option<f64>,
    /// Coefficient: µm per K (temperature) or µm at the source's full scale (heat source,
    /// `full_scale`).
    pub k: f64,
    /// Its standard uncertainty, same unit.
    pub sigma: f64,
    /// The source's value that `k` is per (heat source: its largest over the fit rows).
    pub full_scale: f64,
    /// The term's contribution over the fit rows, standard deviation, µm.
    pub contribution_um: f64,
}

/// The errors of a model over a set of rows, µm.
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct Errors {
    /// Mean absolute error.
    pub mae_um: f64,
    /// Root mean square.
    pub rms_um: f64,
    /// Largest absolute error.
    pub max_um: f64,
}

/// One step of the loop: the group added and the errors after it.
#[derive(Debug, Clone, Serialize)]
pub struct Step {
    /// What the step added (`nominal` for the start).
    pub added: String,
    /// Cross-validated mean absolute error after it, µm.
    pub cv_mae_um: f64,
    /// The ridge weight the cross-validation chose.
    pub lambda: f64,
    /// Errors over the held-out rows after it (reported, never used to choose).
    pub heldout: Errors,
}

/// Where the nominal model fails: how closely its residual follows a source (best lag).
#[derive(Debug, Clone, Serialize)]
pub struct Follows {
    /// The source.
    pub source: String,
    /// The lag at which it follows closest, s.
    pub tau_s: f64,
    /// The correlation of the residual with the lagged source over the fit rows.
    pub r: f64,
}

/// The fitted model of one channel.
#[derive(Debug, Clone, Serialize)]
pub struct ChannelFit {
    /// The channel.
    pub channel: String,
    /// The loop: nominal first, then each group added.
    pub steps: Vec<Step>,
    /// The final model's constant, µm.
    pub offset_um: f64,
    /// Its columns, largest contribution first.
    pub terms: Vec<Term>,
    /// Final ridge weight.
    pub lambda: f64,
    /// Cross-validated mean absolute error of the final model, µm.
    pub cv_mae_um: f64,
    /// Errors over the fit rows.
    pub fit: Errors,
    /// Errors over the held-out rows.
    pub heldout: Errors,
    /// Errors of the nominal model (a constant) over the held-out rows.
    pub nominal_heldout: Errors,
    /// The nominal model's residual against each source, closest first.
    pub follows: Vec<Follows>,
    /// The residual's lag-1 autocorrelation over the fit rows (what inflated the σ).
    pub residual_rho: f64,
    /// The final model's prediction per row, µm.
    pub prediction_um: Vec<f64>,
    /// The measured drift per row, µm.
    pub measured_um: Vec<f64>,
}

/// Two sensors with the same information.
#[derive(Debug, Clone, Serialize)]
pub struct Confounded {
    /// The one fitted.
    pub kept: String,
    /// The one left out.
    pub dropped: String,
    /// Their correlation over the fit rows.
    pub r: f64,
}

/// What the procedure found.
#[derive(Debug, Clone, Serialize)]
pub struct ThermalFit {
    /// Rows fitted (the first ones).
    pub fit_rows: usize,
    /// Rows held out (the rest).
    pub heldout_rows: usize,
    /// The lag basis, s.
    pub taus_s: Vec<f64>,
    /// Sensors left out as confounded with another.
    pub confounded: Vec<Confounded>,
    /// What the recording cannot determine, in words.
    pub undetermined: Vec<String>,
    /// Per channel.
    pub channels: Vec<ChannelFit>,
}

/// A candidate group of columns.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Group {
    Static,
    Lagged,
    Heat,
}

impl Group {
    fn name(self) -> &'static str {
        match self {
            Group::Static => "temperatures as read",
            Group::Lagged => "temperatures through their heat paths' lags",
            Group::Heat => "heat source through its lags",
        }
    }
}

/// A built column.
struct Column {
    term: Term,
    group: Group,
    x: Vec<f64>,
}

/// Fits every channel of the recording.
pub fn fit(rec: &Recording, opt: &Options) -> Result<ThermalFit, ProcedureError> {
    let n = rec.t_s.len();
    check(rec, opt)?;
    let nf = opt.heldout_from;
    let (cols, confounded, undetermined) = columns(rec, opt);
    let blocks = block_bounds(nf, opt.blocks);
    let mut channels = vec![];
    for ch in &rec.channels {
        let y: Vec<f64> = ch.mm.iter().map(|v| v * 1e3).collect();
        channels.push(fit_channel(rec, opt, &cols, &blocks, &ch.name, &y, n));
    }
    Ok(ThermalFit {
        fit_rows: nf,
        heldout_rows: n - nf,
        taus_s: opt.taus_s.clone(),
        confounded,
        undetermined,
        channels,
    })
}

/// The columns every model is made of: each source not confounded with an earlier one
/// through each lag (a heat source as x/x_max and its square), with what the recording
/// cannot tell apart.
fn columns(rec: &Recording, opt: &Options) -> (Vec<Column>, Vec<Confounded>, Vec<String>) {
    let nf = opt.heldout_from;
    // Confounded sensors.
    let mut confounded = vec![];
    let mut kept: Vec<&Source> = vec![];
    for s in &rec.sources {
        if s.kind == SourceKind::Temperature {
            if let Some((k, r)) = kept
                .iter()
                .filter(|k| k.kind == SourceKind::Temperature)
                .map(|k| (k, corr(&k.values[..nf], &s.values[..nf])))
                .find(|(_, r)| r.abs() >= opt.confounded_r)
            {
                confounded.push(Confounded {
                    kept: k.name.clone(),
                    dropped: s.name.clone(),
                    r,
                });
                continue;
            }
        }
        kept.push(s);
    }
    // Columns: each kept source (heat sources as x/x_max and its square) through each lag.
    let mut cols: Vec<Column> = vec![];
    let mut undetermined = vec![];
    for s in &kept {
        let x0 = s.values[0];
        let (signals, full): (Vec<(u32, Vec<f64>)>, f64) = match s.kind {
            SourceKind::Temperature => (vec![(1, s.values.iter().map(|v| v - x0).collect())], 1.0),
            SourceKind::HeatSource => {
                let m = s.values[..nf].iter().fold(0.0f64, |a, v| a.max(v.abs()));
                if m == 0.0 {
                    undetermined.push(format!(
                        "{}: the heat source is zero over the fit rows; nothing about it \
                         can be fitted",
                        s.name
                    ));
                    continue;
                }
                (
                    vec![
                        (1, s.values.iter().map(|v| v / m).collect()),
                        (2, s.values.iter().map(|v| (v / m) * (v / m)).collect()),
                    ],
                    m,
                )
            }
        };
        for (power, x) in signals {
            let mut mine: Vec<(f64, Vec<f64>)> = vec![];
            for &tau in &opt.taus_s {
                let z = Lag { tau_s: tau }.run(&rec.t_s, &x);
                if let Some((t2, _)) = mine
                    .iter()
                    .find(|(_, o)| corr(&o[..nf], &z[..nf]).abs() >= 0.995)
                {
                    undetermined.push(format!(
                        "{}{}: lags of {t2} s and {tau} s cannot be told apart on this \
                         recording (only their sum is determined)",
                        s.name,
                        if power == 2 { "²" } else { "" }
                    ));
                }
                mine.push((tau, z.clone()));
                let group = match (s.kind, tau) {
                    (SourceKind::HeatSource, _) => Group::Heat,
                    (_, t) if t == 0.0 => Group::Static,
                    _ => Group::Lagged,
                };
                cols.push(Column {
                    term: Term {
                        source: s.name.clone(),
                        kind: s.kind,
                        power,
                        tau_s: tau,
                        tau_sigma_s: None,
                        k: 0.0,
                        sigma: 0.0,
                        full_scale: full,
                        contribution_um: 0.0,
                    },
                    group,
                    x: z,
                });
            }
        }
    }
    (cols, confounded, undetermined)
}

fn check(rec: &Recording, opt: &Options) -> Result<(), ProcedureError> {
    let n = rec.t_s.len();
    let bad = |m: String| Err(ProcedureError::Missing(m));
    if rec.channels.is_empty() {
        return bad("no measured displacement channel".into());
    }
    if !rec
        .sources
        .iter()
        .any(|s| s.kind == SourceKind::Temperature)
    {
        return bad("no temperature sensor".into());
    }
    for s in &rec.sources {
        if s.values.len() != n {
            return bad(format!(
                "source {}: {} values for {n} rows",
                s.name,
                s.values.len()
            ));
        }
        if let Some(i) = s.values.iter().position(|v| !v.is_finite()) {
            return bad(format!("source {}: row {i} is not a finite number", s.name));
        }
    }
    for c in &rec.channels {
        if c.mm.len() != n {
            return bad(format!(
                "channel {}: {} values for {n} rows",
                c.name,
                c.mm.len()
            ));
        }
        if let Some(i) = c.mm.iter().position(|v| !v.is_finite()) {
            return bad(format!(
                "channel {}: row {i} is not a finite number",
                c.name
            ));
        }
    }
    if let Some(i) = (1..n).find(|&i| !(rec.t_s[i] > rec.t_s[i - 1])) {
        return bad(format!("time does not increase at row {i}"));
    }
    if opt.blocks < 5 {
        return Err(ProcedureError::IllConditioned(
            "at least 5 cross-validation blocks are needed".into(),
        ));
    }
    if opt.heldout_from < 20 * opt.blocks || opt.heldout_from >= n {
        return Err(ProcedureError::IllConditioned(format!(
            "the fit part must hold at least {} rows and leave a held-out part: {} of {n} rows \
             fit",
            20 * opt.blocks,
            opt.heldout_from
        )));
    }
    if opt.lambdas.is_empty() || opt.lambdas.iter().any(|l| !(l.is_finite() && *l >= 0.0)) {
        return Err(ProcedureError::IllConditioned(
            "ridge weights must be finite numbers ≥ 0".into(),
        ));
    }
    if opt.taus_s.is_empty() || opt.taus_s.iter().any(|t| !(t.is_finite() && *t >= 0.0)) {
        return Err(ProcedureError::IllConditioned(
            "lags must be finite numbers ≥ 0 s".into(),
        ));
    }
    Ok(())
}

fn fit_channel(
    rec: &Recording,
    opt: &Options,
    cols: &[Column],
    blocks: &[(usize, usize)],
    name: &str,
    y: &[f64],
    n: usize,
) -> ChannelFit {
    let nf = opt.heldout_from;
    let fl = folds(blocks);
    let pick = |groups: &[Group]| -> Vec<usize> {
        (0..cols.len())
            .filter(|&j| groups.contains(&cols[j].group))
            .collect()
    };
    let predict_all = |idx: &[usize], lambda: f64| -> Vec<f64> {
        let c: Vec<&Vec<f64>> = idx.iter().map(|&j| &cols[j].x).collect();
        if c.is_empty() {
            let ybar = y[..nf].iter().sum::<f64>() / nf as f64;
            return vec![ybar; n];
        }
        match Ridge::fit(&c, y, (0, nf), lambda) {
            Some(m) => (0..n).map(|r| m.predict(&c, r)).collect(),
            None => vec![f64::NAN; n],
        }
    };
    // The nominal model.
    let (cv0, _, _) = best_lambda(&[], y, &fl, &opt.lambdas);
    let nominal = predict_all(&[], 0.0);
    let nominal_heldout = errors(y, &nominal, (nf, n));
    let mut steps = vec![Step {
        added: "nominal (no thermal effect)".into(),
        cv_mae_um: cv0,
        lambda: 0.0,
        heldout: nominal_heldout,
    }];
    // Where it fails: the residual against each source at its best lag.
    let resid: Vec<f64> = (0..nf).map(|r| y[r] - nominal[r]).collect();
    let mut follows: Vec<Follows> = vec![];
    for c in cols.iter().filter(|c| c.term.power == 1) {
        let r = corr(&resid, &c.x[..nf]);
        match follows.iter_mut().find(|f| f.source == c.term.source) {
            Some(f) if f.r.abs() >= r.abs() => {}
            Some(f) => {
                f.r = r;
                f.tau_s = c.term.tau_s;
            }
            None => follows.push(Follows {
                source: c.term.source.clone(),
                tau_s: c.term.tau_s,
                r,
            }),
        }
    }
    follows.sort_by(|a, b| b.r.abs().total_cmp(&a.r.abs()));
    // The loop.
    let mut chosen: Vec<Group> = vec![];
    let mut cur = (cv0, 0.0, vec![]);
    loop {
        let mut best: Option<(Group, (f64, f64, Vec<Vec<f64>>))> = None;
        for g in [Group::Static, Group::Lagged, Group::Heat] {
            if chosen.contains(&g) || (g == Group::Static && chosen.contains(&Group::Lagged)) {
                continue;
            }
            let mut gs = chosen.clone();
            gs.push(g);
            if g == Group::Lagged {
                gs.retain(|x| *x != Group::Static);
                gs.push(Group::Static);
            }
            let idx = pick(&gs);
            if idx.is_empty() {
                continue;
            }
            let c: Vec<&Vec<f64>> = idx.iter().map(|&j| &cols[j].x).collect();
            let r = best_lambda(&c, y, &fl, &opt.lambdas);
            if best.as_ref().is_none_or(|b| r.0 < b.1 .0) {
                best = Some((g, r));
            }
        }
        let Some((g, r)) = best else { break };
        if !(r.0 < cur.0 * (1.0 - opt.min_gain)) {
            break;
        }
        chosen.push(g);
        if g == Group::Lagged && !chosen.contains(&Group::Static) {
            chosen.push(Group::Static);
        }
        let idx = pick(&chosen);
        let pred = predict_all(&idx, r.1);
        steps.push(Step {
            added: g.name().into(),
            cv_mae_um: r.0,
            lambda: r.1,
            heldout: errors(y, &pred, (nf, n)),
        });
        cur = r;
    }
    // The final model.
    let idx = pick(&chosen);
    let c: Vec<&Vec<f64>> = idx.iter().map(|&j| &cols[j].x).collect();
    let (cv_mae, lambda, fold_ks) = cur;
    let pred = predict_all(&idx, lambda);
    let fit_err = errors(y, &pred, (0, nf));
    let heldout = errors(y, &pred, (nf, n));
    let resid: Vec<f64> = (0..nf).map(|r| y[r] - pred[r]).collect();
    let rho = {
        let m = resid.iter().sum::<f64>() / nf as f64;
        let (mut num, mut den) = (0.0, 0.0);
        for r in 0..nf {
            den += (resid[r] - m) * (resid[r] - m);
            if r > 0 {
                num += (resid[r] - m) * (resid[r - 1] - m);
            }
        }
        if den > 0.0 {
            (num / den).clamp(-0.999, 0.999)
        } else {
            0.0
        }
    };
    let mut terms = vec![];
    let mut offset_um = y[..nf].iter().sum::<f64>() / nf as f64;
    if let Some(m) = (!c.is_empty())
        .then(|| Ridge::fit(&c, y, (0, nf), lambda))
        .flatten()
    {
        let p = c.len();
        // Effective degrees of freedom of the ridge: tr((Z'Z + λnI)⁻¹Z'Z).
        let df = (&m.a_inv * &m.ztz).trace();
        let rss: f64 = resid.iter().map(|e| e * e).sum();
        let s2 = rss / (nf as f64 - df - 1.0).max(1.0);
        let inflate = (1.0 + rho) / (1.0 - rho);
        let cov = &m.a_inv * &m.ztz * &m.a_inv * (s2 * inflate.max(1.0));
        offset_um = m.ybar;
        for j in 0..p {
            let k = m.k(j);
            offset_um -= k * m.mean[j];
            let sd_stat = if m.sd[j] > 0.0 {
                cov[(j, j)].max(0.0).sqrt() / m.sd[j]
            } else {
                0.0
            };
            let spread = {
                let v: Vec<f64> = fold_ks.iter().filter_map(|ks| ks.get(j).copied()).collect();
                if v.len() > 1 {
                    let mv = v.iter().sum::<f64>() / v.len() as f64;
                    (v.iter().map(|x| (x - mv) * (x - mv)).sum::<f64>() / (v.len() - 1) as f64)
                        .sqrt()
                } else {
                    0.0
                }
            };
            let col = &cols[idx[j]];
            let mut t = col.term.clone();
            t.k = k;
            t.sigma = (sd_stat * sd_stat + spread * spread).sqrt();
            t.contribution_um = (k * m.sd[j]).abs();
            terms.push(t);
        }
        terms.sort_by(|a, b| b.contribution_um.total_cmp(&a.contribution_um));
    }
    let _ = rec;
    ChannelFit {
        channel: name.to_string(),
        steps,
        offset_um,
        terms,
        lambda,
        cv_mae_um: cv_mae,
        fit: fit_err,
        heldout,
        nominal_heldout,
        follows,
        residual_rho: rho,
        prediction_um: pred,
        measured_um: y.to_vec(),
    }
}

#[cfg(test)]
mod tests;
