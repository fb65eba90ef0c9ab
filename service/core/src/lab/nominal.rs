//! Refitting the nominal model's axis time constants from command versus scales.
//!
//! Equation: for each axis with a first-order G1(s) = 1/(τs + 1), τ minimises
//! Σ_k (s_k − E_k(τ))² over samples while the axis moves, with E = G1·G2·C discretised as in
//! the estimator (G2, the probe's, is kept). Golden-section search on log τ.

use super::dataset::Samples;
use super::fit::golden_max;
use super::LabError;
use crate::calib::Calibration;
use crate::sample::{Sample, Vec3};
use crate::transfer::{Discrete, TransferFunction};
use serde::Serialize;

/// The refit of one axis.
#[derive(Debug, Clone, Serialize)]
pub struct AxisFit {
    /// Axis name.
    pub axis: String,
    /// τ before and after, s.
    pub tau_before_s: f64,
    /// After.
    pub tau_after_s: f64,
    /// Tracking residual RMS before and after, µm.
    pub rms_before_um: f64,
    /// After.
    pub rms_after_um: f64,
    /// Standard uncertainty of τ after, s: from the curvature of the tracking residual at its
    /// minimum, with the number of points reduced for the residual's correlation.
    pub tau_sigma_s: Option<f64>,
}

/// Command and scale pairs (scale time, commanded position interpolated, scale position).
fn pairs(samples: &dyn Samples) -> Result<Vec<(Vec3, Vec3, bool)>, LabError> {
    let mut cmd: Vec<(i64, Vec3)> = vec![];
    let mut sc: Vec<(i64, Vec3)> = vec![];
    samples
        .replay(&mut |s| match s {
            Sample::Command(c) => cmd.push((c.t_ns, c.pos)),
            Sample::Scale(c) => sc.push((c.t_ns, c.pos)),
            _ => {}
        })
        .map_err(LabError::Data)?;
    cmd.sort_by_key(|c| c.0);
    sc.sort_by_key(|c| c.0);
    let mut out = vec![];
    let mut j = 0;
    for (t, s) in sc {
        while j + 1 < cmd.len() && cmd[j + 1].0 <= t {
            j += 1;
        }
        if j + 1 >= cmd.len() || cmd[j].0 > t {
            continue;
        }
        let (t0, c0) = cmd[j];
        let c = if t0 == t {
            c0
        } else {
            let (t1, c1) = cmd[j + 1];
            c0 + (c1 - c0) * ((t - t0) as f64 / (t1 - t0) as f64)
        };
        out.push((c, s, t0 == t));
    }
    Ok(out)
}

/// Tracking residual while the axis moves: (RMS µm, points, lag-1 autocorrelation).
fn residual_stats(
    samples: &[(Vec3, Vec3, bool)],
    axis: usize,
    tf: &TransferFunction,
    g2: &TransferFunction,
    period: f64,
) -> Option<(f64, usize, f64)> {
    let g = tf.rational().ok()?.mul(&g2.rational().ok()?);
    let d = Discrete::new(&g, period).ok()?;
    let first = samples.first()?;
    let mut st = d.steady(first.0[axis]);
    let (mut ss, mut lag1, mut n) = (0.0, 0.0, 0usize);
    let mut prev = first.0[axis];
    let mut last: Option<f64> = None;
    for (c, s, _) in samples.iter().skip(1) {
        let e = d.step(&mut st, c[axis]);
        // Only while the axis moves: at rest every model agrees.
        if (c[axis] - prev).abs() > 1e-6 {
            let r = s[axis] - e.y;
            ss += r * r;
            if let Some(l) = last {
                lag1 += r * l;
            }
            last = Some(r);
            n += 1;
        } else {
            last = None;
        }
        prev = c[axis];
    }
    (n > 100).then(|| {
        (
            (ss / n as f64).sqrt() * 1e3,
            n,
            (lag1 / ss).clamp(0.0, 0.999),
        )
    })
}

fn residual(
    samples: &[(Vec3, Vec3, bool)],
    axis: usize,
    tf: &TransferFunction,
    g2: &TransferFunction,
    period: f64,
) -> Option<f64> {
    residual_stats(samples, axis, tf, g2, period).map(|r| r.0)
}

/// Refits τ of every first-order axis model from the command and scale streams.
pub fn fit_nominal(
    bags: &[&dyn Samples],
    cal: &Calibration,
) -> Result<(Calibration, Vec<AxisFit>), LabError> {
    let mut all = vec![];
    for b in bags {
        all.extend(pairs(*b)?);
    }
    if all.len() < 1000 {
        return Err(LabError::Data(
            "too few command/scale pairs to fit the nominal model: record moves of the machine"
                .into(),
        ));
    }
    let g2 = cal
        .geometry
        .tips
        .first()
        .and_then(|t| cal.nominal.probes.get(&t.probe))
        .cloned()
        .unwrap_or(TransferFunction::Unity);
    let mut out = cal.clone();
    let mut report = vec![];
    for (i, name) in ["x", "y", "z"].iter().enumerate() {
        let tf = match i {
            0 => &cal.nominal.axes.x,
            1 => &cal.nominal.axes.y,
            _ => &cal.nominal.axes.z,
        };
        let TransferFunction::FirstOrder { tau_s } = tf else {
            continue;
        };
        let f = |tau: f64| {
            residual(
                &all,
                i,
                &TransferFunction::FirstOrder { tau_s: tau },
                &g2,
                cal.sample_period_s,
            )
        };
        let Some(before) = f(*tau_s) else { continue };
        // Golden-section search on ln τ within [τ/4, 4τ].
        let tau = golden_max(
            |x| -f(x.exp()).unwrap_or(f64::MAX),
            (tau_s / 4.0).ln(),
            (tau_s * 4.0).ln(),
        )
        .exp();
        let after = f(tau).unwrap_or(before);
        let (tau, after) = if after < before {
            (tau, after)
        } else {
            (*tau_s, before)
        };
        // σ from the curvature of rms²(τ) = rms₀² + c·(τ − τ₀)², each point weighing
        // (1 − ρ)/(1 + ρ) of an independent one.
        let tau_sigma_s = (|| {
            let h = 0.02 * tau;
            let (r0, n, rho) = residual_stats(
                &all,
                i,
                &TransferFunction::FirstOrder { tau_s: tau },
                &g2,
                cal.sample_period_s,
            )?;
            let (rp, rm) = (f(tau + h)?, f(tau - h)?);
            let c = (rp * rp + rm * rm - 2.0 * r0 * r0) / (2.0 * h * h);
            let n_eff = (n as f64 * (1.0 - rho) / (1.0 + rho)).max(1.0);
            let s = (r0 * r0 / n_eff / c).sqrt();
            (c > 0.0 && s.is_finite()).then_some(s)
        })();
        let new = TransferFunction::FirstOrder { tau_s: tau };
        match i {
            0 => out.nominal.axes.x = new,
            1 => out.nominal.axes.y = new,
            _ => out.nominal.axes.z = new,
        }
        report.push(AxisFit {
            axis: name.to_string(),
            tau_before_s: *tau_s,
            tau_after_s: tau,
            rms_before_um: before,
            rms_after_um: after,
            tau_sigma_s,
        });
    }
    Ok((out, report))
}
