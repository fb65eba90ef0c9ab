//! The thermal-drift procedure's report, and the names and units of its terms.

use super::svg::value_sigma;
use super::svg::{esc, page, xy, PALETTE};
use scancorr_core::calibrate::thermal_drift::{self, SourceKind};
use std::fmt::Write;

/// `calibrate thermal-drift --report`: per channel the loop (each group added, its
/// cross-validated and held-out error), the drift against time (measured, the nominal model,
/// the final model; the held-out period shaded by its start line), the residual against time,
/// the measured drift against the source the nominal model's residual follows most, and the
/// largest terms with their σ.
pub fn thermal_drift(
    rec: &scancorr_core::calibrate::thermal_drift::Recording,
    f: &scancorr_core::calibrate::thermal_drift::ThermalFit,
) -> String {
    let n = rec.t_s.len();
    let t0 = rec.t_s[0];
    let hours = |r: usize| (rec.t_s[r] - t0) / 3600.0;
    // At most ~800 points a line: every k-th row.
    let k = n.div_ceil(800).max(1);
    let rows: Vec<usize> = (0..n).step_by(k).collect();
    let mut body = format!(
        "<p>{n} rows over {:.1} h. Fitted on the rows before {:.1} h ({} rows); the {} rows after it are <b>held out</b>: reported, never used to choose or fit. Cross-validation: forward-chaining over blocks of time of the fit rows. Lag basis {:?} s.</p>",
        hours(n - 1),
        hours(f.fit_rows),
        f.fit_rows,
        f.heldout_rows,
        f.taus_s
    );
    for c in &f.confounded {
        let _ = write!(
            body,
            "<p><b>Confounded:</b> {} carries what {} does (r = {:.4}); only {} is fitted.</p>",
            esc(&c.dropped),
            esc(&c.kept),
            c.r,
            esc(&c.kept)
        );
    }
    if !f.undetermined.is_empty() {
        let _ = write!(
            body,
            "<details><summary><b>Cannot determine</b> ({}): the recording does not tell these apart</summary><ul>{}</ul></details>",
            f.undetermined.len(),
            f.undetermined
                .iter()
                .map(|u| format!("<li>{}</li>", esc(u)))
                .collect::<String>()
        );
    }
    body += "<table><tr><th>channel</th><th>nominal, held-out MAE µm</th><th>final, held-out MAE µm</th><th>RMS µm</th><th>max µm</th><th>cross-validated MAE µm</th></tr>";
    for c in &f.channels {
        let _ = write!(
            body,
            "<tr><td>{}</td><td>{:.3}</td><td><b>{:.3}</b></td><td>{:.3}</td><td>{:.2}</td><td>{:.3}</td></tr>",
            esc(&c.channel),
            c.nominal_heldout.mae_um,
            c.heldout.mae_um,
            c.heldout.rms_um,
            c.heldout.max_um,
            c.cv_mae_um
        );
    }
    body += "</table>";
    for c in &f.channels {
        let _ = write!(body, "<h2>{}</h2>", esc(&c.channel));
        if let Some(w) = c.follows.first() {
            let _ = write!(body, "<p>Where the nominal model fails: the drift follows <b>{}</b> through a lag of {} s (r = {:.2}).</p>", esc(&w.source), w.tau_s, w.r);
        }
        body += "<table><tr><th>step</th><th>model</th><th>cross-validated MAE µm</th><th>held-out MAE µm</th></tr>";
        for (i, s) in c.steps.iter().enumerate() {
            let _ = write!(
                body,
                "<tr><td>{i}</td><td>{}{}</td><td>{:.3}</td><td>{:.3}</td></tr>",
                if i == 0 { "" } else { "add " },
                esc(&s.added),
                s.cv_mae_um,
                s.heldout.mae_um
            );
        }
        body += "</table>";
        let nominal = c.measured_um[..f.fit_rows].iter().sum::<f64>() / f.fit_rows as f64;
        let series = |v: &dyn Fn(usize) -> f64| -> Vec<(f64, f64)> {
            rows.iter().map(|&r| (hours(r), v(r))).collect()
        };
        let split = hours(f.fit_rows);
        let (lo, hi) = c
            .measured_um
            .iter()
            .fold((f64::MAX, f64::MIN), |(a, b), v| (a.min(*v), b.max(*v)));
        body += &xy(
            "thermal-drift-time",
            &[
                (
                    "measured".into(),
                    PALETTE[0],
                    series(&|r| c.measured_um[r]),
                    true,
                ),
                ("nominal".into(), "#999", series(&|_| nominal), true),
                (
                    "model".into(),
                    PALETTE[1],
                    series(&|r| c.prediction_um[r]),
                    true,
                ),
                (
                    "held out from".into(),
                    "#000",
                    vec![(split, lo), (split, hi)],
                    true,
                ),
            ],
            "time, h",
            "drift, µm",
        );
        body += &xy(
            "thermal-drift-residual",
            &[
                (
                    "nominal".into(),
                    "#999",
                    series(&|r| c.measured_um[r] - nominal),
                    true,
                ),
                (
                    "model".into(),
                    PALETTE[1],
                    series(&|r| c.measured_um[r] - c.prediction_um[r]),
                    true,
                ),
            ],
            "time, h",
            "measured − model, µm",
        );
        if let Some(w) = c.follows.first() {
            if let Some(s) = rec.sources.iter().find(|s| s.name == w.source) {
                // The source through the lag it is followed at: the drift against it is
                // the line a one-term model would draw.
                let lagged = scancorr_core::effects::thermal_drift::Lag { tau_s: w.tau_s }
                    .run(&rec.t_s, &s.values);
                let pts = |a: usize, b: usize| -> Vec<(f64, f64)> {
                    rows.iter()
                        .filter(|&&r| r >= a && r < b)
                        .map(|&r| (lagged[r], c.measured_um[r]))
                        .collect()
                };
                body += &xy(
                    "thermal-drift-against",
                    &[
                        ("fit rows".into(), PALETTE[0], pts(0, f.fit_rows), false),
                        ("held out".into(), PALETTE[1], pts(f.fit_rows, n), false),
                    ],
                    &format!("{} through a lag of {} s", w.source, w.tau_s),
                    "drift, µm",
                );
            }
        }
        body += "<table><tr><th>term</th><th>k ± σ</th><th>contribution (SD over the fit rows) µm</th></tr>";
        for t in c.terms.iter().take(12) {
            let _ = write!(
                body,
                "<tr><td>{}</td><td>{} {}</td><td>{:.2}</td></tr>",
                esc(&term_name(t)),
                value_sigma(t.k, Some(t.sigma)),
                esc(&term_unit(t)),
                t.contribution_um
            );
        }
        let _ = write!(body, "</table><p>{} terms in all; constant {:.3} µm; ridge λ {:.1e}; residual lag-1 correlation {:.3} (the σ are inflated for it and include the spread over the cross-validation's fits).</p>", c.terms.len(), c.offset_um, c.lambda, c.residual_rho);
    }
    page("scancorr calibrate thermal-drift", &body)
}

/// `t4 (τ 2400 s)`, `spindle_rpm² (τ 600 s)`.
pub fn term_name(t: &thermal_drift::Term) -> String {
    format!(
        "{}{} (τ {:.0} s)",
        t.source,
        if t.power == 2 { "²" } else { "" },
        t.tau_s
    )
}

/// The unit of a term's coefficient.
pub fn term_unit(t: &thermal_drift::Term) -> String {
    match t.kind {
        SourceKind::Temperature => "µm/K".into(),
        SourceKind::HeatSource => format!("µm at {}", t.full_scale),
    }
}
