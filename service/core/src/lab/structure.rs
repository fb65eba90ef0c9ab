//! Structure left in a residual that no library effect explains: periods along the axes and
//! reversals, offered as the terms of a `custom` effect.

use super::analysis::{axis_span, Prepared};
use serde::Serialize;
use super::dataset::Dataset;
use super::fit::{nuisance_row, Normal};
use super::LabError;
use crate::sample::Axis;

/// Structure left in the residual that no candidate explains.
#[derive(Debug, Clone, Serialize)]
pub struct Structure {
    /// What the residual follows: `period` along an axis, `reversal` of an axis.
    pub kind: String,
    /// Axis (coordinate and error direction).
    pub axis: String,
    /// Period, mm (periodic structure).
    pub period_mm: Option<f64>,
    /// Amplitude of the error along the axis, µm.
    pub amplitude_um: f64,
    /// Fraction of the residual's sum of squares it explains.
    pub explained: f64,
    /// Terms of a `custom` effect built from it (`AXIS:EXPR`).
    pub custom_terms: Vec<String>,
}

/// Periodic and reversal structure of a residual, strongest first.
pub fn structure(
    ds: &Dataset,
    prep: &Prepared,
    residual: &[f64],
) -> Result<Vec<Structure>, LabError> {
    let art = &prep.art;
    // Remove the placements first.
    let mut ne = Normal::new(art.n_cols);
    let mut row = vec![];
    for (i, p) in ds.points.iter().enumerate() {
        if art.features[p.feature].is_some() {
            nuisance_row(art, p, &p.surface, &mut row);
            ne.add(&[], &row, residual[i]);
        }
    }
    let sol = ne.solve();
    let mut e = vec![0.0; ds.points.len()];
    let mut total = 0.0;
    for (i, p) in ds.points.iter().enumerate() {
        if art.features[p.feature].is_some() {
            nuisance_row(art, p, &p.surface, &mut row);
            e[i] = residual[i] + row.iter().map(|(c, v)| v * sol.x[*c]).sum::<f64>();
            total += e[i] * e[i];
        }
    }
    if total <= 0.0 {
        return Ok(vec![]);
    }
    let two = |c1: &dyn Fn(usize) -> f64, c2: &dyn Fn(usize) -> f64| -> (f64, [f64; 2]) {
        let (mut a11, mut a12, mut a22, mut b1, mut b2) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for i in 0..e.len() {
            let (x1, x2) = (c1(i), c2(i));
            a11 += x1 * x1;
            a12 += x1 * x2;
            a22 += x2 * x2;
            b1 += x1 * e[i];
            b2 += x2 * e[i];
        }
        let det = a11 * a22 - a12 * a12;
        if det.abs() < 1e-30 {
            return (0.0, [0.0; 2]);
        }
        let (t1, t2) = ((a22 * b1 - a12 * b2) / det, (a11 * b2 - a12 * b1) / det);
        (t1 * b1 + t2 * b2, [t1, t2])
    };
    let mut found = vec![];
    for a in Axis::ALL {
        let ai = a.index();
        let g_rms = (ds
            .points
            .iter()
            .enumerate()
            .map(|(i, _)| art.grad[i][ai].powi(2))
            .sum::<f64>()
            / e.len() as f64)
            .sqrt();
        if g_rms < 0.1 {
            continue;
        }
        let (lo, hi) = axis_span(ds, a);
        let span = hi - lo;
        if span < 2.0 {
            continue;
        }
        // Periodogram over periods 0.5 mm … span/2.
        let (pmin, pmax) = (0.5f64, (span / 2.0).min(200.0));
        let mut best = (0.0, 0.0, [0.0; 2]);
        let steps = 600;
        let scan = |p: f64, best: &mut (f64, f64, [f64; 2])| {
            let w = std::f64::consts::TAU / p;
            let s = |i: usize| art.grad[i][ai] * (w * ds.points[i].ctx.scale[ai]).sin();
            let c = |i: usize| art.grad[i][ai] * (w * ds.points[i].ctx.scale[ai]).cos();
            let (red, th) = two(&s, &c);
            if red > best.0 {
                *best = (red, p, th);
            }
        };
        if pmax > pmin {
            for k in 0..=steps {
                let p = pmin * (pmax / pmin).powf(k as f64 / steps as f64);
                scan(p, &mut best);
            }
            // Refine around the best period.
            let p0 = best.1;
            for k in -50..=50 {
                let p = p0 * (1.0 + k as f64 * 0.0004);
                scan(p, &mut best);
            }
        }
        if best.0 > 0.0 {
            let p = best.1;
            found.push(Structure {
                kind: "period".into(),
                axis: a.name().into(),
                period_mm: Some(p),
                amplitude_um: best.2[0].hypot(best.2[1]) * 1e3,
                explained: best.0 / total,
                custom_terms: vec![
                    format!("{}:sin(2*pi*{}/{:.4})", a.name(), a.name(), p),
                    format!("{}:cos(2*pi*{}/{:.4})", a.name(), a.name(), p),
                ],
            });
        }
        // Reversal (backlash-like): a step with the sign of the axis velocity.
        let sg = |i: usize| {
            art.grad[i][ai]
                * ds.points[i].ctx.est_vel[ai].signum()
                * (ds.points[i].ctx.est_vel[ai].abs() > 0.01) as i32 as f64
        };
        let zero = |_: usize| 0.0;
        let (red, th) = {
            let mut a11 = 0.0;
            let mut b1 = 0.0;
            for i in 0..e.len() {
                a11 += sg(i) * sg(i);
                b1 += sg(i) * e[i];
            }
            let _ = zero;
            if a11 > 0.0 {
                (b1 * b1 / a11, [b1 / a11, 0.0])
            } else {
                (0.0, [0.0; 2])
            }
        };
        if red > 0.0 {
            found.push(Structure {
                kind: "reversal".into(),
                axis: a.name().into(),
                period_mm: None,
                amplitude_um: th[0].abs() * 1e3,
                explained: red / total,
                custom_terms: vec![format!("{}:sign(v{})", a.name(), a.name())],
            });
        }
    }
    found.sort_by(|a, b| b.explained.total_cmp(&a.explained));
    found.retain(|s| s.explained > 0.05 && s.amplitude_um.is_finite());
    found.truncate(4);
    Ok(found)
}

