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

fn block_bounds(n: usize, k: usize) -> Vec<(usize, usize)> {
    (0..k).map(|i| (i * n / k, (i + 1) * n / k)).collect()
}

/// The forward-chaining folds: (fit rows end, validation rows) per fold.
fn folds(blocks: &[(usize, usize)]) -> Vec<(usize, (usize, usize))> {
    let k = blocks.len();
    let first = (2 * k).div_ceil(5).max(2);
    (first..=k.saturating_sub(3))
        .map(|m| (blocks[m].0, (blocks[m].0, blocks[m + 2].1)))
        .collect()
}

/// A ridge fit on standardised columns: prediction function data.
struct Ridge {
    mean: Vec<f64>,
    sd: Vec<f64>,
    ybar: f64,
    b: DVector<f64>,
    a_inv: DMatrix<f64>,
    ztz: DMatrix<f64>,
}

impl Ridge {
    fn fit(cols: &[&Vec<f64>], y: &[f64], rows: (usize, usize), lambda: f64) -> Option<Ridge> {
        let (r0, r1) = rows;
        let n = (r1 - r0) as f64;
        let p = cols.len();
        let mean: Vec<f64> = cols
            .iter()
            .map(|c| c[r0..r1].iter().sum::<f64>() / n)
            .collect();
        let sd: Vec<f64> = cols
            .iter()
            .zip(&mean)
            .map(|(c, m)| {
                let v = c[r0..r1].iter().map(|x| (x - m) * (x - m)).sum::<f64>() / n;
                v.sqrt()
            })
            .collect();
        let ybar = y[r0..r1].iter().sum::<f64>() / n;
        let mut ztz = DMatrix::<f64>::zeros(p, p);
        let mut zty = DVector::<f64>::zeros(p);
        let mut z = vec![0.0; p];
        for r in r0..r1 {
            for j in 0..p {
                z[j] = if sd[j] > 0.0 {
                    (cols[j][r] - mean[j]) / sd[j]
                } else {
                    0.0
                };
            }
            let yr = y[r] - ybar;
            for i in 0..p {
                zty[i] += z[i] * yr;
                for j in i..p {
                    ztz[(i, j)] += z[i] * z[j];
                }
            }
        }
        for i in 0..p {
            for j in 0..i {
                ztz[(i, j)] = ztz[(j, i)];
            }
        }
        let mut a = ztz.clone();
        for i in 0..p {
            // A column without variation gets a unit penalty: it cannot be determined.
            a[(i, i)] += lambda.max(1e-12) * n + if sd[i] > 0.0 { 0.0 } else { 1.0 };
        }
        let a_inv = a.cholesky()?.inverse();
        let b = &a_inv * zty;
        Some(Ridge {
            mean,
            sd,
            ybar,
            b,
            a_inv,
            ztz,
        })
    }

    fn predict(&self, cols: &[&Vec<f64>], r: usize) -> f64 {
        let mut v = self.ybar;
        for (j, c) in cols.iter().enumerate() {
            if self.sd[j] > 0.0 {
                v += self.b[j] * (c[r] - self.mean[j]) / self.sd[j];
            }
        }
        v
    }

    /// Coefficient j in the column's own unit.
    fn k(&self, j: usize) -> f64 {
        if self.sd[j] > 0.0 {
            self.b[j] / self.sd[j]
        } else {
            0.0
        }
    }
}

/// Cross-validated MAE of the columns at ridge weight λ, and each fold's coefficients.
fn cv(
    cols: &[&Vec<f64>],
    y: &[f64],
    fl: &[(usize, (usize, usize))],
    lambda: f64,
) -> Option<(f64, Vec<Vec<f64>>)> {
    let (mut sum, mut count) = (0.0, 0usize);
    let mut ks = vec![];
    for &(end, (v0, v1)) in fl {
        let (mut s, mut c) = (0.0, 0usize);
        if cols.is_empty() {
            let ybar = y[..end].iter().sum::<f64>() / end as f64;
            for r in v0..v1 {
                s += (y[r] - ybar).abs();
                c += 1;
            }
        } else {
            let m = Ridge::fit(cols, y, (0, end), lambda)?;
            for r in v0..v1 {
                s += (y[r] - m.predict(cols, r)).abs();
                c += 1;
            }
            ks.push((0..cols.len()).map(|j| m.k(j)).collect());
        }
        sum += s;
        count += c;
    }
    Some((sum / count.max(1) as f64, ks))
}

/// The best ridge weight for the columns: (cv MAE, λ, the folds' coefficients).
fn best_lambda(
    cols: &[&Vec<f64>],
    y: &[f64],
    fl: &[(usize, (usize, usize))],
    lambdas: &[f64],
) -> (f64, f64, Vec<Vec<f64>>) {
    let mut best: Option<(f64, f64, Vec<Vec<f64>>)> = None;
    for &l in lambdas {
        if let Some((e, ks)) = cv(cols, y, fl, l) {
            // Ties (within 0.1 %) go to the larger weight: the simpler model.
            if best.as_ref().is_none_or(|b| e < b.0 * 0.999) {
                best = Some((e, l, ks));
            }
        }
    }
    best.unwrap_or((f64::MAX, lambdas[lambdas.len() - 1], vec![]))
}

fn errors(y: &[f64], pred: &[f64], rows: (usize, usize)) -> Errors {
    let (r0, r1) = rows;
    let n = (r1 - r0).max(1) as f64;
    let (mut a, mut s, mut m) = (0.0, 0.0, 0.0f64);
    for r in r0..r1 {
        let e = (y[r] - pred[r]).abs();
        a += e;
        s += e * e;
        m = m.max(e);
    }
    Errors {
        mae_um: a / n,
        rms_um: (s / n).sqrt(),
        max_um: m,
    }
}

fn corr(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len().max(1) as f64;
    let (ma, mb) = (a.iter().sum::<f64>() / n, b.iter().sum::<f64>() / n);
    let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
    for (x, y) in a.iter().zip(b) {
        sab += (x - ma) * (y - mb);
        saa += (x - ma) * (x - ma);
        sbb += (y - mb) * (y - mb);
    }
    if saa > 0.0 && sbb > 0.0 {
        sab / (saa * sbb).sqrt()
    } else {
        0.0
    }
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
fn signal(rec: &Recording, t: &Term) -> Option<Vec<f64>> {
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
fn sse(cols: &[&Vec<f64>], y: &[f64], nf: usize, lambda: f64) -> f64 {
    match Ridge::fit(cols, y, (0, nf), lambda) {
        Some(m) => (0..nf).map(|r| (y[r] - m.predict(cols, r)).powi(2)).sum(),
        None => f64::INFINITY,
    }
}

/// Golden-section minimum of `f` over [a, b].
fn golden(mut a: f64, mut b: f64, iters: usize, mut f: impl FnMut(f64) -> f64) -> f64 {
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
fn lag1(e: &[f64]) -> f64 {
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
fn uncertainties(
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

#[cfg(test)]
mod tests {
    use super::*;

    /// Small deterministic noise (xorshift), uniform in ±a.
    fn noise(n: usize, a: f64, seed: u64) -> Vec<f64> {
        let mut s = seed;
        (0..n)
            .map(|_| {
                s ^= s << 13;
                s ^= s >> 7;
                s ^= s << 17;
                a * (2.0 * (s >> 11) as f64 / (1u64 << 53) as f64 - 1.0)
            })
            .collect()
    }

    /// A machine whose drift follows one sensor through a 2400 s lag and a heat source
    /// through a 1200 s lag; another sensor is a copy of the first (confounded), a third is
    /// unrelated. The procedure finds the lagged groups, names the copy, and predicts a
    /// later period it never saw.
    #[test]
    fn finds_the_lagged_drift_and_predicts_a_later_period() {
        let n = 4000;
        let t: Vec<f64> = (0..n).map(|k| 15.0 * k as f64).collect();
        let rpm: Vec<f64> = t
            .iter()
            .map(|&x| {
                if ((x / 7200.0) as usize) % 2 == 1 {
                    3000.0
                } else {
                    0.0
                }
            })
            .collect();
        let t_a: Vec<f64> = t
            .iter()
            .zip(noise(n, 0.01, 3))
            .map(|(&x, e)| 22.0 + 2.0 * (x / 20000.0).sin() + e)
            .collect();
        let t_b: Vec<f64> = t_a.iter().map(|v| 0.5 * v + 3.0).collect();
        let t_c: Vec<f64> = noise(n, 0.3, 9).iter().map(|e| 21.0 + e).collect();
        let la = Lag { tau_s: 2400.0 }.run(&t, &t_a.iter().map(|v| v - t_a[0]).collect::<Vec<_>>());
        let lr = Lag { tau_s: 1200.0 }.run(&t, &rpm);
        let y: Vec<f64> = (0..n)
            .zip(noise(n, 0.2e-3, 17))
            .map(|(k, e)| 1e-3 * (5.0 * la[k] + 0.004 * lr[k]) + e)
            .collect();
        let rec = Recording {
            t_s: t,
            sources: vec![
                Source {
                    name: "a".into(),
                    kind: SourceKind::Temperature,
                    values: t_a,
                },
                Source {
                    name: "b".into(),
                    kind: SourceKind::Temperature,
                    values: t_b,
                },
                Source {
                    name: "c".into(),
                    kind: SourceKind::Temperature,
                    values: t_c,
                },
                Source {
                    name: "rpm".into(),
                    kind: SourceKind::HeatSource,
                    values: rpm,
                },
            ],
            channels: vec![Channel {
                name: "z".into(),
                mm: y,
            }],
        };
        let opt = Options {
            heldout_from: 3000,
            ..Options::default()
        };
        let f = fit(&rec, &opt).unwrap();
        assert_eq!(f.confounded.len(), 1);
        assert_eq!(
            (
                f.confounded[0].kept.as_str(),
                f.confounded[0].dropped.as_str()
            ),
            ("a", "b")
        );
        let ch = &f.channels[0];
        let added: Vec<&str> = ch.steps.iter().map(|s| s.added.as_str()).collect();
        assert!(added.contains(&Group::Lagged.name()), "{added:?}");
        assert!(added.contains(&Group::Heat.name()), "{added:?}");
        // The drift spans ~ ±12 µm; the model predicts the held-out hours within half a µm
        // (the noise is uniform ±0.2 µm, MAE 0.1 µm; the heat source's 1200 s lag is not in
        // the basis and is made of its neighbours, 600 and 2400 s).
        assert!(ch.nominal_heldout.mae_um > 3.0, "{:?}", ch.nominal_heldout);
        assert!(ch.heldout.mae_um < 0.5, "{:?} {:?}", ch.heldout, ch.steps);
        assert!(ch
            .terms
            .iter()
            .all(|t| t.k.is_finite() && t.sigma.is_finite() && t.sigma >= 0.0));
        // The strongest term is a lagged `a` or the heat source.
        assert!(
            ["a", "rpm"].contains(&ch.terms[0].source.as_str()),
            "{:?}",
            ch.terms[0]
        );
    }

    /// A drift through a lag of 1500 s, between the basis's 600 and 2400 s, with noise: the
    /// compact model refines its lag off the basis to the truth within its stated σ (and the
    /// σ is not vanishing: between 0.1 % and 20 % of τ), and predicts the held-out rows
    /// better than the basis lag did.
    #[test]
    fn the_compact_model_refines_a_lag_off_the_basis_within_its_sigma() {
        let n = 6000;
        let t: Vec<f64> = (0..n).map(|k| 15.0 * k as f64).collect();
        let a: Vec<f64> = t
            .iter()
            .map(|&x| 20.0 + 2.0 * (x / 5000.0).sin() + 1.5 * (x / 1700.0).cos())
            .collect();
        let da: Vec<f64> = a.iter().map(|v| v - a[0]).collect();
        let la = Lag { tau_s: 1500.0 }.run(&t, &da);
        let y: Vec<f64> = (0..n)
            .zip(noise(n, 0.3e-3, 5))
            .map(|(k, e)| 1e-3 * 6.0 * la[k] + e)
            .collect();
        let rec = Recording {
            t_s: t,
            sources: vec![Source {
                name: "a".into(),
                kind: SourceKind::Temperature,
                values: a,
            }],
            channels: vec![Channel {
                name: "z".into(),
                mm: y,
            }],
        };
        let opt = Options {
            heldout_from: 4500,
            ..Options::default()
        };
        let m = compact(&rec, &opt, 0, 2).unwrap();
        assert!(m.refined, "{m:?}");
        let lag = m
            .terms
            .iter()
            .find(|t| t.tau_s > 0.0)
            .expect("a lagged term");
        let u = lag.tau_sigma_s.expect("a refined lag has its σ");
        assert!(
            (lag.tau_s - 1500.0).abs() < 3.0 * u && u > 1.5 && u < 300.0,
            "τ = {} ± {u} s against 1500 s",
            lag.tau_s
        );
        assert!(
            (lag.k - 6.0).abs() < 3.0 * lag.sigma + 0.05,
            "k = {} ± {}",
            lag.k,
            lag.sigma
        );
        assert!(m.heldout.mae_um < 0.2, "{:?}", m.heldout);
        let cfg = effect(&[(&m, 2)]).unwrap();
        assert!(cfg.terms.iter().any(|t| t.tau_s_u == Some(u)));
    }

    #[test]
    fn refuses_a_recording_it_cannot_fit() {
        let rec = Recording {
            t_s: vec![0.0, 1.0, 1.0],
            sources: vec![Source {
                name: "a".into(),
                kind: SourceKind::Temperature,
                values: vec![20.0; 3],
            }],
            channels: vec![Channel {
                name: "x".into(),
                mm: vec![0.0; 3],
            }],
        };
        let e = fit(
            &rec,
            &Options {
                heldout_from: 2,
                ..Options::default()
            },
        )
        .unwrap_err();
        assert!(
            e.to_string().contains("time does not increase at row 2"),
            "{e}"
        );
    }

    /// The effect written from a compact model corrects as the model predicts: its terms
    /// through the corrector's lag over the recorded readings give the model's prediction.
    #[test]
    fn the_effect_applies_what_the_compact_model_predicts() {
        let n = 3000;
        let t: Vec<f64> = (0..n).map(|k| 15.0 * k as f64).collect();
        let a: Vec<f64> = t.iter().map(|&x| 21.0 + 3.0 * (x / 9000.0).sin()).collect();
        let b: Vec<f64> = t.iter().map(|&x| 24.0 + 1.0 * (x / 3000.0).cos()).collect();
        let la = Lag { tau_s: 2400.0 }.run(&t, &a);
        let y: Vec<f64> = (0..n)
            .map(|k| 1e-3 * (4.0 * (la[k] - 21.0) - 2.0 * (b[k] - b[0])))
            .collect();
        let rec = Recording {
            t_s: t.clone(),
            sources: vec![
                Source {
                    name: "a".into(),
                    kind: SourceKind::Temperature,
                    values: a.clone(),
                },
                Source {
                    name: "b".into(),
                    kind: SourceKind::Temperature,
                    values: b.clone(),
                },
            ],
            channels: vec![Channel {
                name: "z".into(),
                mm: y,
            }],
        };
        let opt = Options {
            heldout_from: 2400,
            ..Options::default()
        };
        let m = compact(&rec, &opt, 0, 4).unwrap();
        assert!(m.heldout.mae_um < 0.05, "{m:?}");
        let cfg = effect(&[(&m, 2)]).unwrap();
        assert!(!cfg.terms.is_empty() && cfg.terms.len() <= 4);
        // Evaluate the effect as the corrector would: each term's lagged reading.
        let mut sensors = crate::effects::SensorTable::default();
        let built = cfg.build(&mut sensors).unwrap();
        let lagged: Vec<Vec<f64>> = (0..sensors.names().len())
            .map(|slot| {
                let src = if sensors.names()[slot] == "a" { &a } else { &b };
                Lag {
                    tau_s: sensors.tau(slot),
                }
                .run(&t, src)
            })
            .collect();
        for k in (0..n).step_by(97) {
            let mut ctx = crate::sample::PointContext::at_rest(crate::sample::Vec3::zeros());
            for (slot, v) in lagged.iter().enumerate() {
                ctx.temps[slot] = v[k];
            }
            ctx.temps_valid = (1 << lagged.len()) - 1;
            let d = crate::effects::Effect::correction(&built, &ctx);
            assert!(d.x == 0.0 && d.y == 0.0);
            assert!(
                (d.z - rec.channels[0].mm[k]).abs() < 1e-4,
                "row {k}: {} vs {}",
                d.z,
                rec.channels[0].mm[k]
            );
        }
    }
}
