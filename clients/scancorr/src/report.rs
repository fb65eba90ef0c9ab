//! Self-contained HTML reports (inline SVG, no scripts, no network): polar deviation plots,
//! residual breakdowns with failing bins highlighted, the candidate ranking, the error fall.

use scancorr_core::lab::analysis::{Comparison, Diagnosis};
use scancorr_core::lab::dataset::Dataset;
use scancorr_core::lab::traces::Trace;
use scancorr_core::Calibration;
use serde::Serialize;
use std::fmt::Write;

/// One calibration version in the history.
#[derive(Debug, Clone, Serialize)]
pub struct HistoryRow {
    pub file: String,
    pub version: u64,
    pub parent: Option<u64>,
    pub effects: Vec<String>,
    pub note: String,
    pub rms_um: Option<f64>,
    pub heldout_rms_um: Option<f64>,
    /// What it changed against its parent: `+effect`, `−effect`, `refit`, `start`.
    pub change: String,
    /// The noise floor of the data it was judged on, where known, µm.
    pub noise_floor_um: Option<f64>,
}

fn esc(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

fn page(title: &str, body: &str) -> String {
    format!(
        "<!doctype html><html lang=\"en\"><head><meta charset=\"utf-8\"><title>{t}</title><style>\
body{{font-family:system-ui,sans-serif;margin:2em;max-width:1100px;color:#222}}\
h1{{font-size:1.4em}}h2{{font-size:1.15em;margin-top:2em;border-bottom:1px solid #ccc}}\
figure{{display:inline-block;margin:0.5em;vertical-align:top}}figcaption{{font-size:0.85em;color:#555;max-width:420px}}\
table{{border-collapse:collapse;font-size:0.9em}}td,th{{border:1px solid #ddd;padding:3px 8px;text-align:right}}\
td:first-child,th:first-child{{text-align:left}}.fail{{color:#b00;font-weight:bold}}.muted{{color:#777}}\
</style></head><body><h1>{t}</h1>{body}</body></html>",
        t = esc(title)
    )
}

/// Colours of the traces, by speed (slowest first).
const TRACE_COLOURS: [&str; 6] = [
    "#2266cc", "#2a9d4b", "#e08a00", "#c2185b", "#6a3d9a", "#555555",
];

/// A round scale for polar plots: 1, 2 or 5 × 10ᵏ µm per division, so that `maxdev` fits in
/// four divisions.
fn um_per_div(maxdev: f64) -> f64 {
    let raw = (maxdev / 4.0).max(0.01);
    let e = 10f64.powf(raw.log10().floor());
    [1.0, 2.0, 5.0, 10.0]
        .into_iter()
        .map(|m| m * e)
        .find(|v| *v >= raw * (1.0 - 1e-9))
        .unwrap_or(10.0 * e)
}

fn dir_name(d: i32) -> &'static str {
    if d > 0 {
        "CCW"
    } else {
        "CW"
    }
}

/// Polar plot of one circle feature's traces (one per direction and speed), as a circular
/// test draws them: the certified circle solid, ±4 divisions of `upd` µm dashed, +X to the
/// right and +Y up, each trace de-centred (its own 1θ taken out) with its circularity in the
/// legend. `speeds` fixes the colours (the same speed, the same colour, in every plot).
fn polar(title: &str, role: &str, traces: &[&Trace], upd: f64, speeds: &[i64]) -> String {
    polar_over(title, role, traces, &[], upd, speeds)
}

/// [`polar`] with `under` drawn first, faint, in the same colours: a prediction (`traces`)
/// drawn over the measurement (`under`), each legend line giving both circularities.
fn polar_over(
    title: &str,
    role: &str,
    traces: &[&Trace],
    under: &[&Trace],
    upd: f64,
    speeds: &[i64],
) -> String {
    let (w, r0, div) = (400.0, 100.0, 20.0);
    let c = w / 2.0;
    let speed_key = |t: &Trace| (t.speed_mm_s * 10.0).round() as i64;
    let colour = |t: &Trace| {
        let k = speeds.iter().position(|v| *v == speed_key(t)).unwrap_or(0);
        TRACE_COLOURS[k % TRACE_COLOURS.len()]
    };
    let mut svg = format!(
        "<svg data-plot=\"polar\" data-role=\"{role}\" data-um-per-div=\"{upd}\" xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{w}\" viewBox=\"0 0 {w} {w}\">"
    );
    let _ = write!(svg, "<line x1=\"8\" x2=\"{}\" y1=\"{c}\" y2=\"{c}\" stroke=\"#e4e4e4\"/><line x1=\"{c}\" x2=\"{c}\" y1=\"8\" y2=\"{}\" stroke=\"#e4e4e4\"/>", w - 8.0, w - 8.0);
    for k in -4i32..=4 {
        let rr = r0 + k as f64 * div;
        let (stroke, dash) = if k == 0 {
            ("#444", "")
        } else {
            ("#ccc", "3 3")
        };
        let _ = write!(svg, "<circle cx=\"{c}\" cy=\"{c}\" r=\"{rr}\" fill=\"none\" stroke=\"{stroke}\" stroke-dasharray=\"{dash}\"/>");
    }
    let _ = write!(
        svg,
        "<text x=\"{}\" y=\"{}\" font-size=\"11\">+X</text><text x=\"{}\" y=\"14\" font-size=\"11\">+Y</text>",
        w - 24.0,
        c - 4.0,
        c + 4.0
    );
    let _ = write!(
        svg,
        "<text x=\"6\" y=\"14\" font-size=\"11\">{} µm/div</text><text x=\"6\" y=\"{}\" font-size=\"10\" fill=\"#444\">solid circle: certified Ø</text>",
        fmt_scale(upd),
        w - 6.0
    );
    let layers = under
        .iter()
        .map(|t| (t, true))
        .chain(traces.iter().map(|t| (t, false)));
    for (t, faint) in layers {
        let mut d = String::new();
        for (j, (th, e)) in t.theta_deg.iter().zip(&t.deviation_um).enumerate() {
            let r = (r0 + e / upd * div).clamp(2.0, c - 2.0);
            let th = th.to_radians();
            let _ = write!(
                d,
                "{}{:.1},{:.1} ",
                if j == 0 { "M" } else { "L" },
                c + r * th.cos(),
                c - r * th.sin()
            );
        }
        if t.theta_deg.len() >= 350 {
            d.push('Z');
        }
        let _ = write!(
            svg,
            "<path data-trace=\"{} {} mm/s\" data-layer=\"{}\" data-direction=\"{}\" data-speed-mm-s=\"{}\" data-circularity-um=\"{:.3}\" d=\"{d}\" fill=\"none\" stroke=\"{}\" stroke-width=\"{}\"{}{}/>",
            dir_name(t.direction),
            t.speed_mm_s,
            if faint { "measured" } else { role },
            dir_name(t.direction).to_lowercase(),
            t.speed_mm_s,
            t.circularity_um,
            colour(t),
            if faint { "3" } else { "1.4" },
            if faint { " stroke-opacity=\"0.25\"" } else { "" },
            if t.direction < 0 { " stroke-dasharray=\"6 3\"" } else { "" }
        );
    }
    svg += "</svg>";
    let mut legend = String::from("<ul class=\"traces\">");
    for t in traces {
        let was = under
            .iter()
            .find(|u| u.direction == t.direction && speed_key(u) == speed_key(t))
            .map(|u| format!("measured {:.2} µm → predicted ", u.circularity_um))
            .unwrap_or_default();
        let _ = write!(
            legend,
            "<li><span style=\"color:{}\">{}</span> {} {} mm/s: circularity {was}<b data-circularity-um=\"{:.3}\">{:.2} µm</b></li>",
            colour(t),
            if t.direction < 0 { "╌╌" } else { "━━" },
            dir_name(t.direction),
            t.speed_mm_s,
            t.circularity_um,
            t.circularity_um
        );
    }
    legend += "</ul>";
    let what = if under.is_empty() {
        "deviation from the certified circle per direction and speed"
    } else {
        "predicted deviation (bold) drawn over the measured one (faint), per direction and speed"
    };
    format!(
        "<figure>{svg}<figcaption><b>{}</b>: {what} (1° means, each trace's own centre taken out: the 1θ term is where the circle lies, not its form; circularity = range of the trace){legend}</figcaption></figure>",
        esc(title)
    )
}

/// One polar scale for every trace of a report (µm per division) and the speeds that fix
/// the traces' colours (0.1 mm/s, ascending).
fn scale_and_speeds(all: &[&Trace]) -> (f64, Vec<i64>) {
    let maxdev = all
        .iter()
        .flat_map(|t| t.deviation_um.iter())
        .fold(0.0f64, |a, e| a.max(e.abs()));
    let mut speeds: Vec<i64> = all
        .iter()
        .map(|t| (t.speed_mm_s * 10.0).round() as i64)
        .collect();
    speeds.sort_unstable();
    speeds.dedup();
    (um_per_div(maxdev), speeds)
}

fn fmt_scale(v: f64) -> String {
    if v >= 1.0 {
        format!("{v:.0}")
    } else {
        format!("{v}")
    }
}

/// A value with its standard uncertainty in engineering form: both to the σ's second
/// significant digit, with a common power of ten outside 10⁻³…10⁴ (`(2.31 ± 0.04)e-6`);
/// without σ, four significant digits.
pub fn value_sigma(v: f64, sigma: Option<f64>) -> String {
    if !v.is_finite() {
        return "—".into();
    }
    let big = sigma
        .filter(|s| s.is_finite() && *s > 0.0)
        .map_or(v.abs(), |s| s.max(v.abs()));
    let e = if big > 0.0 {
        big.log10().floor() as i32
    } else {
        0
    };
    let (scale, suffix) = if (-3..4).contains(&e) {
        (1.0, String::new())
    } else {
        (10f64.powi(e), format!("e{e}"))
    };
    match sigma.filter(|s| s.is_finite() && *s > 0.0) {
        Some(s) => {
            let digits = (1 - (s / scale).log10().floor() as i32).clamp(0, 9) as usize;
            let body = format!("{:.digits$} ± {:.digits$}", v / scale, s / scale);
            if suffix.is_empty() {
                body
            } else {
                format!("({body}){suffix}")
            }
        }
        None if v == 0.0 => "0".into(),
        None => {
            let digits = (3 - (v.abs() / scale).log10().floor() as i32).clamp(0, 9) as usize;
            format!("{:.digits$}{suffix}", v / scale)
        }
    }
}

/// The fitted parameters of each effect: name (with unit), value ± standard uncertainty; a
/// parameter the data cannot determine says so in its row (and nowhere else). Effects with
/// many parameters (tables, maps) fold under their name.
fn params_table(heading: &str, groups: &[scancorr_core::lab::analysis::EffectParams]) -> String {
    if groups.iter().all(|g| g.params.is_empty()) {
        return String::new();
    }
    let undetermined: usize = groups
        .iter()
        .map(|g| g.params.iter().filter(|p| p.sigma.is_none()).count())
        .sum();
    let mut s = format!("<h2>{}</h2>", esc(heading));
    if undetermined > 0 {
        let _ = write!(s, "<p class=\"muted\">{undetermined} parameter(s) this data cannot determine are marked <i>not determined</i>: they keep their minimum-norm values and correct nothing this data can check.</p>");
    }
    for g in groups.iter().filter(|g| !g.params.is_empty()) {
        let mut t = String::from("<table data-params=\"1\"><tr><th>parameter (unit)</th><th>value ± standard uncertainty</th></tr>");
        for p in &g.params {
            let _ = write!(
                t,
                "<tr><td>{}</td><td>{}</td></tr>",
                esc(&p.name),
                match p.sigma {
                    Some(_) => value_sigma(p.value, p.sigma),
                    None => format!(
                        "{} <i class=\"muted\">not determined</i>",
                        value_sigma(p.value, None)
                    ),
                }
            );
        }
        t += "</table>";
        if g.params.len() > 12 {
            let _ = write!(
                s,
                "<details><summary><b>{}</b> ({} parameters)</summary>{t}</details>",
                esc(&g.effect),
                g.params.len()
            );
        } else {
            let _ = write!(s, "<p><b>{}</b></p>{t}", esc(&g.effect));
        }
    }
    s
}

/// Each structure's residual against its coordinate with the fitted structure over it.
fn structure_profiles(st: &[scancorr_core::lab::analysis::Structure]) -> String {
    let mut s = String::new();
    for x in st {
        let Some(p) = &x.profile else { continue };
        let what = match (x.period_mm, x.harmonic) {
            (Some(per), _) => format!("fitted period {per} mm along {}", x.axis),
            (_, Some(k)) => format!("fitted {k}θ harmonic of the probing direction"),
            _ => x.kind.clone(),
        };
        let series: Vec<Series> = vec![
            (
                "residual (bin means)".into(),
                "#1f77b4",
                p.x.iter()
                    .copied()
                    .zip(p.measured_um.iter().copied())
                    .collect(),
                false,
            ),
            (
                format!("fitted, ±{:.2} µm", x.amplitude_um),
                "#d62728",
                p.x.iter()
                    .copied()
                    .zip(p.fitted_um.iter().copied())
                    .collect(),
                true,
            ),
        ];
        let _ = write!(
            s,
            "<figure>{}<figcaption>Residual along {} against {} with the {what} ({:.0} % of the residual; each point's residual divided by how much of the error direction it sees, averaged in bins).</figcaption></figure>",
            xy("structure", &series, &p.coordinate, "error, µm"),
            esc(&x.axis),
            esc(&p.coordinate),
            x.explained * 100.0
        );
    }
    s
}

/// The best candidate's predicted traces drawn over the measured ones, one plot per circle,
/// on one scale.
fn prediction_polars(ds: &Dataset, p: &scancorr_core::lab::analysis::Prediction) -> String {
    let verb = match p.action {
        scancorr_core::lab::analysis::Move::Add => "adding",
        scancorr_core::lab::analysis::Move::Swap => "swapping in",
        scancorr_core::lab::analysis::Move::Drop => "dropping",
    };
    let mut s = format!(
        "<h2>What {verb} {} predicts for each circle</h2>",
        esc(&p.effect)
    );
    let all: Vec<&Trace> = p.measured.iter().chain(&p.predicted).collect();
    let (upd, speeds) = scale_and_speeds(&all);
    for (fi, (_, f)) in ds.features.iter().enumerate() {
        let pred: Vec<&Trace> = p.predicted.iter().filter(|t| t.feature == fi).collect();
        let meas: Vec<&Trace> = p.measured.iter().filter(|t| t.feature == fi).collect();
        if pred.is_empty() {
            continue;
        }
        let title = format!(
            "{} {} (Ø{} mm) — {verb} {}",
            f.artifact,
            fi + 1,
            f.certificate_diameter_mm.unwrap_or(f.nominal_diameter_mm),
            p.effect
        );
        s += &polar_over(&title, "predicted", &pred, &meas, upd, &speeds);
    }
    s
}

/// Horizontal bar chart.
fn bars(
    kind: &str,
    rows: &[(String, f64, bool)],
    unit: &str,
    reference: Option<(f64, &str)>,
) -> String {
    let h = 22.0 * rows.len() as f64 + 30.0;
    let max = rows
        .iter()
        .map(|r| r.1)
        .chain(reference.map(|r| r.0))
        .fold(1e-9f64, f64::max);
    let (x0, wbar) = (230.0, 300.0);
    let mut svg = format!("<svg data-plot=\"{kind}\" xmlns=\"http://www.w3.org/2000/svg\" width=\"620\" height=\"{h}\">");
    for (i, (label, v, hot)) in rows.iter().enumerate() {
        let y = 10.0 + 22.0 * i as f64;
        let _ = write!(
            svg,
            "<text x=\"{}\" y=\"{}\" font-size=\"11\" text-anchor=\"end\">{}</text><rect x=\"{x0}\" y=\"{y}\" width=\"{:.1}\" height=\"16\" fill=\"{}\" data-failing=\"{hot}\"/><text x=\"{:.1}\" y=\"{}\" font-size=\"11\">{v:.3} {unit}</text>",
            x0 - 6.0,
            y + 12.0,
            esc(label),
            (v / max * wbar).max(0.5),
            if *hot { "#cc3333" } else { "#6a8fc8" },
            x0 + (v / max * wbar).max(0.5) + 4.0,
            y + 12.0
        );
    }
    if let Some((r, name)) = reference {
        let x = x0 + r / max * wbar;
        let _ = write!(svg, "<line x1=\"{x:.1}\" x2=\"{x:.1}\" y1=\"4\" y2=\"{}\" stroke=\"#393\" stroke-dasharray=\"4 3\"/><text x=\"{:.1}\" y=\"{}\" font-size=\"10\" fill=\"#393\">{}</text>", h - 14.0, x + 3.0, h - 4.0, esc(name));
    }
    svg + "</svg>"
}

fn breakdown(cmp: &Comparison) -> String {
    let mut s = String::new();
    let mut features: Vec<&str> = cmp.bins.iter().map(|b| b.feature.as_str()).collect();
    features.dedup();
    for f in features {
        let rows: Vec<(String, f64, bool)> = cmp
            .bins
            .iter()
            .filter(|b| b.feature == f)
            .map(|b| (b.bin.clone(), b.rms_um, b.failing))
            .collect();
        let _ = write!(
            s,
            "<figure>{}<figcaption>Residual RMS by {} (red: stands out)</figcaption></figure>",
            bars(
                "residual",
                &rows,
                "µm",
                Some((cmp.noise_floor_um, "noise floor"))
            ),
            esc(f)
        );
    }
    s
}

fn summary(cal: &Calibration, cmp: &Comparison) -> String {
    let mut s = format!(
        "<p>Calibration <b>v{}</b> of machine <b>{}</b> ({} effect(s): {}). {} points.</p><table><tr><th>figure</th><th>µm</th></tr><tr><td>deviation RMS</td><td>{:.3}</td></tr><tr><td>peak-to-valley</td><td>{:.3}</td></tr><tr><td>noise floor</td><td>{:.3}</td></tr></table>",
        cal.version,
        esc(&cal.machine_id),
        cal.effects.len(),
        esc(&cal.effects.iter().map(|e| e.id()).collect::<Vec<_>>().join(", ")),
        cmp.points,
        cmp.rms_um,
        cmp.pv_um,
        cmp.noise_floor_um
    );
    if cmp.failures.is_empty() {
        s += "<h2>Where it fails</h2><p>No bin stands out: every bin is within 1.3 × the RMS or 2 × the noise floor. The plots below still show the data.</p>";
    } else {
        s += "<h2>Where it fails</h2><table><tr><th>feature</th><th>bin</th><th>points</th><th>RMS µm</th><th>mean µm</th><th>the same points as</th></tr>";
        for b in cmp
            .failures
            .iter()
            .filter(|b| b.same_points_as.is_none())
            .take(15)
        {
            let same = cmp.same_points(b);
            let _ = write!(s, "<tr class=\"fail\"><td>{}</td><td>{}</td><td>{}</td><td>{:.3}</td><td>{:.3}</td><td class=\"muted\">{}</td></tr>", esc(&b.feature), esc(&b.bin), b.n, b.rms_um, b.mean_um, esc(&same.join(", ")));
        }
        s += "</table><p class=\"muted\">Bins holding (nearly) the same points — one ring's fast scans seen by speed, acceleration and rotation frequency — are one row: which of those features matters the data of those scans alone cannot say; scans that separate them (another diameter, spin-up and slow-down) can.</p>";
    }
    s
}

/// Polar plots of every circle feature with traces, on one scale for the whole report; with
/// `before`, a before and an after plot per feature.
fn polars(ds: &Dataset, cmp: &Comparison, before: Option<(&Dataset, &Comparison)>) -> String {
    let mut s = String::from("<h2>Deviation of each circle, per direction and speed</h2>");
    let all: Vec<&Trace> = cmp
        .traces
        .iter()
        .chain(before.iter().flat_map(|(_, b)| b.traces.iter()))
        .collect();
    if all.is_empty() {
        s += "<p class=\"muted\">No circle was scanned at a steady speed over a quarter turn or more: nothing to draw.</p>";
        return s;
    }
    let (upd, speeds) = scale_and_speeds(&all);
    for (fi, (_, f)) in ds.features.iter().enumerate() {
        fn of(c: &Comparison, fi: usize) -> Vec<&Trace> {
            c.traces.iter().filter(|t| t.feature == fi).collect()
        }
        let after = of(cmp, fi);
        if after.is_empty() {
            continue;
        }
        let title = format!(
            "{} {} (Ø{} mm)",
            f.artifact,
            fi + 1,
            f.certificate_diameter_mm.unwrap_or(f.nominal_diameter_mm)
        );
        if let Some((_, b)) = before {
            s += &polar(
                &format!("{title} — before"),
                "before",
                &of(b, fi),
                upd,
                &speeds,
            );
            s += &polar(&format!("{title} — after"), "after", &after, upd, &speeds);
        } else {
            s += &polar(&title, "now", &after, upd, &speeds);
        }
    }
    s
}

/// `lab compare --report`.
pub fn compare(
    cal: &Calibration,
    ds: &Dataset,
    cmp: &Comparison,
    before: Option<(&Dataset, &Comparison)>,
) -> String {
    let mut body = summary(cal, cmp);
    if let Some((_, b)) = before {
        body += &format!(
            "<p>Before: deviation RMS {:.3} µm → now {:.3} µm.</p>",
            b.rms_um, cmp.rms_um
        );
    }
    body += &polars(ds, cmp, before);
    body += "<h2>Residual against each feature</h2>";
    body += &breakdown(cmp);
    page("scancorr lab — compare", &body)
}

/// `lab diagnose --report`.
pub fn diagnose(cal: &Calibration, ds: &Dataset, cmp: &Comparison, d: &Diagnosis) -> String {
    let mut body = summary(cal, cmp);
    body += "<h2>Candidate effects, ranked by held-out residual explained</h2>";
    let rows: Vec<(String, f64, bool)> = d
        .candidates
        .iter()
        .take(15)
        .map(|c| (c.effect.clone(), c.explained * 100.0, c.significant))
        .collect();
    body += &format!("<figure>{}<figcaption>Explained fraction of the held-out residual (red: significant)</figcaption></figure>", bars("ranking", &rows, "%", None));
    body += "<table><tr><th>candidate</th><th>explained</th><th>significant</th><th>held-out µm</th><th>fit µm</th><th>ΔBIC</th><th>parameters</th></tr>";
    for c in d.candidates.iter().take(15) {
        let _ = write!(
            body,
            "<tr><td>{}</td><td>{:.1} %</td><td>{}</td><td>{:.3} → {:.3}</td><td>{:.3} → {:.3}</td><td>{:.0}</td><td>{}</td></tr>",
            esc(&c.effect),
            c.explained * 100.0,
            if c.significant { "yes" } else { "no" },
            c.heldout_rms_before_um,
            c.heldout_rms_after_um,
            c.rms_before_um,
            c.rms_after_um,
            c.delta_bic,
            c.k
        );
    }
    body += "</table>";
    for c in &d.confounded {
        let _ = write!(
            body,
            "<p><b>Confounded:</b> {} and {}. To separate them:<ul>",
            esc(&c.effects[0]),
            esc(&c.effects[1])
        );
        for s in &c.separate_by {
            let _ = write!(body, "<li>{}</li>", esc(s));
        }
        body += "</ul></p>";
    }
    for s in &d.unexplained {
        let _ = write!(body, "<p><b>Unexplained structure:</b> {} along {} ({:.3} µm, {:.0} % of the residual). Start a custom effect with <code>{}</code>.</p>", esc(&s.kind), esc(&s.axis), s.amplitude_um, s.explained * 100.0, esc(&s.custom_terms.join(" ")));
    }
    body += &structure_profiles(&d.unexplained);
    if let Some(best) = d.candidates.first() {
        let group = [scancorr_core::lab::analysis::EffectParams {
            effect: best.effect.clone(),
            params: best.params.clone(),
        }];
        body += &params_table(
            &format!("Fitted parameters of the best candidate, {}", best.effect),
            &group,
        );
    }
    if let Some(p) = &d.prediction {
        body += &prediction_polars(ds, p);
    }
    body += &polars(ds, cmp, None);
    body += "<h2>Residual against each feature</h2>";
    body += &breakdown(cmp);
    page("scancorr lab — diagnose", &body)
}

/// `lab add --report`: before/after.
pub fn add(
    old: &Calibration,
    new: &Calibration,
    fit: &scancorr_core::lab::analysis::FitOutcome,
    dsb: &Dataset,
    cb: &Comparison,
    dsa: &Dataset,
    ca: &Comparison,
) -> String {
    let mut body = format!("<p>{}</p>", esc(&new.note));
    let rows = vec![
        (format!("v{} before", old.version), cb.rms_um, false),
        (format!("v{} after", new.version), ca.rms_um, false),
    ];
    body += &format!(
        "<figure>{}<figcaption>Error fall: deviation RMS</figcaption></figure>",
        bars(
            "error-fall",
            &rows,
            "µm",
            Some((ca.noise_floor_um, "noise floor"))
        )
    );
    body += &polars(dsa, ca, Some((dsb, cb)));
    body += &params_table(
        &format!(
            "Fitted parameters of v{} (every effect refitted)",
            new.version
        ),
        &fit.by_effect(),
    );
    body += "<h2>Residual against each feature (after)</h2>";
    body += &breakdown(ca);
    page("scancorr lab — add", &body)
}

/// `lab history` as text.
pub fn history_text(rows: &[HistoryRow]) -> String {
    let mut s = String::new();
    let max = rows
        .iter()
        .filter_map(|r| r.heldout_rms_um.or(r.rms_um))
        .fold(1e-9f64, f64::max);
    let _ = writeln!(
        s,
        "{:>4} {:>6}  {:>10} {:>10}  {:<40} effects",
        "v", "parent", "RMS µm", "held µm", "error fall (held out)"
    );
    for r in rows {
        let v = r.heldout_rms_um.or(r.rms_um);
        let bar = v
            .map(|v| "█".repeat(((v / max) * 40.0).round() as usize))
            .unwrap_or_default();
        let f = |x: Option<f64>| x.map(|v| format!("{v:.3}")).unwrap_or_else(|| "—".into());
        let _ = writeln!(
            s,
            "{:>4} {:>6}  {:>10} {:>10}  {:<40} {}",
            r.version,
            r.parent
                .map(|p| p.to_string())
                .unwrap_or_else(|| "—".into()),
            f(r.rms_um),
            f(r.heldout_rms_um),
            bar,
            r.effects.join(" + ")
        );
    }
    s
}

/// `lab history --report`.
pub fn history(rows: &[HistoryRow]) -> String {
    let current = rows.iter().map(|r| r.version).max();
    let bars_rows: Vec<(String, f64, bool)> = rows
        .iter()
        .filter_map(|r| {
            r.heldout_rms_um.or(r.rms_um).map(|v| {
                (
                    format!(
                        "v{} {}{}",
                        r.version,
                        r.change,
                        if Some(r.version) == current {
                            " (current)"
                        } else {
                            ""
                        }
                    ),
                    v,
                    false,
                )
            })
        })
        .collect();
    let floor = rows
        .iter()
        .filter_map(|r| r.noise_floor_um)
        .fold(f64::NAN, f64::min);
    let reference = floor.is_finite().then_some((floor, "noise floor"));
    let mut body = if bars_rows.is_empty() {
        "<p class=\"muted\">No version has a recorded residual: give --bag to evaluate each on measurements.</p>".to_string()
    } else {
        format!("<figure>{}<figcaption>Error fall across calibration versions, each labelled by what it changed (held-out RMS where recorded; the dashed line is the noise floor)</figcaption></figure>", bars("error-fall", &bars_rows, "µm", reference))
    };
    body += "<table><tr><th>version</th><th>parent</th><th>changed</th><th>RMS µm</th><th>held-out µm</th><th>effects</th><th>note</th></tr>";
    for r in rows {
        let f = |x: Option<f64>| x.map(|v| format!("{v:.3}")).unwrap_or_else(|| "—".into());
        let _ = write!(body, "<tr><td>{}{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td class=\"muted\">{}</td></tr>", r.version, if Some(r.version) == current { " (current)" } else { "" }, r.parent.map(|p| p.to_string()).unwrap_or_default(), esc(&r.change), f(r.rms_um), f(r.heldout_rms_um), esc(&r.effects.join(" + ")), esc(&r.note));
    }
    body += "</table>";
    page("scancorr lab — history", &body)
}

/// `lab discover --report`: the steps, the error fall against the noise floor, what the
/// campaign could not separate or determine.
pub fn discover(
    start: &Calibration,
    d: &scancorr_core::lab::discover::Discovery,
    circles: Option<((&Dataset, &Comparison), (&Dataset, &Comparison))>,
) -> String {
    let f = &d.r#final;
    let mut rows: Vec<(String, f64, bool)> = vec![(
        format!("start v{} ({} effects)", start.version, start.effects.len()),
        d.start_heldout_rms_um,
        false,
    )];
    for s in &d.steps {
        let what = match &s.replaces {
            Some(r) => format!("{} {} for {r}", s.action, s.effect),
            None => format!("{} {}", s.action, s.effect),
        };
        rows.push((
            format!("{} v{} {}", s.index, s.version, what),
            s.heldout_rms_um,
            false,
        ));
    }
    let mut body = format!(
        "<p>Stopped: {}. Held-out RMS {:.3} → <b>{:.3} µm</b> against a noise floor of {:.3} µm ({:.2}×); cross-validated {:.3} µm. Final model v{}: {}.</p>",
        esc(&d.stopped),
        d.start_heldout_rms_um,
        f.heldout_rms_um,
        f.noise_floor_um,
        f.heldout_rms_um / f.noise_floor_um.max(1e-9),
        f.cv_rms_um,
        f.version,
        esc(&f.effects.join(", "))
    );
    let _ = write!(
        body,
        "<figure>{}<figcaption>Error fall: held-out RMS after each step (dashed: 1.5× the noise floor)</figcaption></figure>",
        bars("error-fall", &rows, "µm", Some((1.5 * f.noise_floor_um, "1.5× noise floor")))
    );
    body += "<table><tr><th>step</th><th>action</th><th>effect</th><th>version</th><th>held-out µm</th><th>cross-validated µm</th><th>fit µm</th><th>confounded with</th></tr>";
    for s in &d.steps {
        let _ = write!(
            body,
            "<tr><td>{}</td><td>{}</td><td>{}{}</td><td>v{}</td><td>{:.3} → {:.3}</td><td>{:.3}</td><td>{:.3}</td><td>{}</td></tr>",
            s.index,
            esc(&s.action),
            esc(&s.effect),
            s.replaces.as_ref().map(|r| format!(" (for {})", esc(r))).unwrap_or_default(),
            s.version,
            s.heldout_rms_before_um,
            s.heldout_rms_um,
            s.cv_rms_um,
            s.rms_um,
            esc(&s.confounded_with.join(", "))
        );
    }
    body += "</table>";
    for c in &d.confounded {
        let _ = write!(
            body,
            "<p><b>Confounded on this campaign:</b> {} and {}. To separate them: {}.</p>",
            esc(&c.effects[0]),
            esc(&c.effects[1]),
            esc(&c.separate_by.join("; "))
        );
    }
    for s in &d.unexplained {
        let _ = write!(body, "<p><b>Left unexplained:</b> {} along {} ({:.3} µm, {:.0} % of the residual): <code>{}</code></p>", esc(&s.kind), esc(&s.axis), s.amplitude_um, s.explained * 100.0, esc(&s.custom_terms.join(" ")));
    }
    body += &structure_profiles(&d.unexplained);
    body += &params_table(
        &format!("Parameters of the final model, v{}", f.version),
        &f.params,
    );
    if let Some(((ds0, c0), (ds1, c1))) = circles {
        body += "<p>Each circle before (the start, red) and after (the final version, blue):</p>";
        body += &polars(ds1, c1, Some((ds0, c0)));
    }
    page("scancorr lab — discover", &body)
}

/// One series of an x–y chart: label, colour, points, drawn with a line.
type Series = (String, &'static str, Vec<(f64, f64)>, bool);

/// An x–y chart with axes, ticks at round values, a zero line and a legend.
fn xy(kind: &str, series: &[Series], xlabel: &str, ylabel: &str) -> String {
    let (w, h, l, r, t, b) = (560.0, 320.0, 62.0, 150.0, 14.0, 42.0);
    let pts = series.iter().flat_map(|s| s.2.iter());
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, 0.0f64, 0.0f64);
    for &(x, y) in pts {
        if x.is_finite() && y.is_finite() {
            (x0, x1, y0, y1) = (x0.min(x), x1.max(x), y0.min(y), y1.max(y));
        }
    }
    if x0 > x1 {
        (x0, x1) = (0.0, 1.0);
    }
    if x1 - x0 < 1e-12 {
        x1 = x0 + 1.0;
    }
    if y1 - y0 < 1e-12 {
        y1 = y0 + 1.0;
    }
    let pad = 0.06 * (y1 - y0);
    let (y0, y1) = (y0 - pad, y1 + pad);
    let px = |x: f64| l + (x - x0) / (x1 - x0) * (w - l - r);
    let py = |y: f64| t + (y1 - y) / (y1 - y0) * (h - t - b);
    let mut svg = format!("<svg data-plot=\"{kind}\" xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{h}\" font-size=\"11\">");
    let _ = write!(
        svg,
        "<rect x=\"{l}\" y=\"{t}\" width=\"{}\" height=\"{}\" fill=\"none\" stroke=\"#999\"/>",
        w - l - r,
        h - t - b
    );
    let step = |span: f64| {
        let raw = span / 5.0;
        let m = 10f64.powf(raw.log10().floor());
        [1.0, 2.0, 5.0, 10.0]
            .iter()
            .map(|k| k * m)
            .find(|s| *s >= raw)
            .unwrap_or(m * 10.0)
    };
    let (sx, sy) = (step(x1 - x0), step(y1 - y0));
    let mut v = (x0 / sx).ceil() * sx;
    while v <= x1 + 1e-9 * sx {
        let _ = write!(svg, "<line x1=\"{0:.1}\" x2=\"{0:.1}\" y1=\"{1:.1}\" y2=\"{2:.1}\" stroke=\"#999\"/><text x=\"{0:.1}\" y=\"{3:.1}\" text-anchor=\"middle\">{4}</text>", px(v), h - b, h - b + 4.0, h - b + 16.0, fmt_tick(v, sx));
        v += sx;
    }
    let mut v = (y0 / sy).ceil() * sy;
    while v <= y1 + 1e-9 * sy {
        let _ = write!(svg, "<line x1=\"{0:.1}\" x2=\"{1:.1}\" y1=\"{2:.1}\" y2=\"{2:.1}\" stroke=\"#999\"/><text x=\"{3:.1}\" y=\"{4:.1}\" text-anchor=\"end\">{5}</text>", l - 4.0, l, py(v), l - 6.0, py(v) + 4.0, fmt_tick(v, sy));
        v += sy;
    }
    if y0 < 0.0 && y1 > 0.0 {
        let _ = write!(svg, "<line x1=\"{l}\" x2=\"{0:.1}\" y1=\"{1:.1}\" y2=\"{1:.1}\" stroke=\"#bbb\" stroke-dasharray=\"3 3\"/>", w - r, py(0.0));
    }
    let _ = write!(
        svg,
        "<text x=\"{:.1}\" y=\"{:.1}\" text-anchor=\"middle\">{}</text>",
        l + 0.5 * (w - l - r),
        h - 8.0,
        esc(xlabel)
    );
    let _ = write!(
        svg,
        "<text transform=\"translate(14,{:.1}) rotate(-90)\" text-anchor=\"middle\">{}</text>",
        t + 0.5 * (h - t - b),
        esc(ylabel)
    );
    for (i, (label, colour, p, line)) in series.iter().enumerate() {
        let pts: Vec<String> = p
            .iter()
            .filter(|(x, y)| x.is_finite() && y.is_finite())
            .map(|(x, y)| format!("{:.1},{:.1}", px(*x), py(*y)))
            .collect();
        if *line && pts.len() > 1 {
            let _ = write!(
                svg,
                "<polyline points=\"{}\" fill=\"none\" stroke=\"{colour}\" stroke-width=\"1.2\"/>",
                pts.join(" ")
            );
        }
        for q in &pts {
            let (x, y) = q.split_once(',').unwrap_or(("0", "0"));
            let _ = write!(
                svg,
                "<circle cx=\"{x}\" cy=\"{y}\" r=\"2.5\" fill=\"{colour}\"/>"
            );
        }
        let ly = t + 12.0 + 14.0 * i as f64;
        let _ = write!(svg, "<rect x=\"{:.1}\" y=\"{:.1}\" width=\"10\" height=\"3\" fill=\"{colour}\"/><text x=\"{:.1}\" y=\"{:.1}\">{}</text>", w - r + 8.0, ly - 4.0, w - r + 22.0, ly, esc(label));
    }
    svg + "</svg>"
}

fn fmt_tick(v: f64, step: f64) -> String {
    let d = (-step.log10().floor()).max(0.0) as usize;
    let s = format!("{v:.d$}");
    if s.trim_start_matches('-')
        .chars()
        .all(|c| c == '0' || c == '.')
    {
        "0".into()
    } else {
        s
    }
}

const PALETTE: [&str; 8] = [
    "#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#17becf", "#8c564b", "#e377c2",
];

/// `calibrate dynamics --report`: ΔR against V² and acceleration per position before and
/// after, the fitted diagonal compliance along each line of positions, every parameter.
pub fn dynamics(
    start: &Calibration,
    o: &scancorr_core::calibrate::dynamics::Outcome,
    noise_floor_um: f64,
) -> String {
    let mut body = format!(
        "<p>Start: v{} of {}. {} ring positions; residual after each position's static pattern {:.3} → <b>{:.3} µm</b> (noise floor {:.3} µm). Servo gain: <b>{}</b> form (held-out ring positions: theoretical {:.3} µm, polynomial in f {:.3} µm).</p>",
        start.version,
        esc(&start.machine_id),
        o.positions.len(),
        o.residual_before_um,
        o.residual_after_um,
        noise_floor_um,
        esc(&o.gain.chosen),
        o.gain.heldout_theoretical_um,
        o.gain.heldout_polynomial_um
    );
    // ΔR against acceleration: one series per position (mean of both directions per speed).
    let per_pos = |after: bool| -> Vec<Series> {
        o.positions
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let mut by: std::collections::BTreeMap<i64, (f64, f64, usize)> = Default::default();
                for s in &p.scans {
                    let e = by.entry((s.accel_mm_s2 * 10.0).round() as i64).or_default();
                    e.0 = s.accel_mm_s2;
                    e.1 += if after {
                        s.delta_r_after_um
                    } else {
                        s.delta_r_um
                    };
                    e.2 += 1;
                }
                (
                    format!(
                        "({:.0}, {:.0}, {:.0})",
                        p.center_mm[0], p.center_mm[1], p.center_mm[2]
                    ),
                    PALETTE[i % PALETTE.len()],
                    by.values().map(|(a, d, n)| (*a, d / *n as f64)).collect(),
                    true,
                )
            })
            .collect()
    };
    let _ = write!(
        body,
        "<h2>ΔR against acceleration</h2><figure>{}<figcaption>Before: each position's mean radius change per speed against the centripetal acceleration v²/r (v² on the same axis scaled by 1/r), relative to its static pattern. A straight line through zero is compliance and the gain's f² term; curvature the f¹ term.</figcaption></figure><figure>{}<figcaption>After the fit: what is left per position and speed.</figcaption></figure>",
        xy("delta-r-before", &per_pos(false), "acceleration v²/r (mm/s²)", "ΔR (µm)"),
        xy("delta-r-after", &per_pos(true), "acceleration v²/r (mm/s²)", "ΔR (µm)")
    );
    // The fitted compliance's diagonal and cross terms along each line of positions.
    let val = |n: &str| {
        o.params
            .iter()
            .find(|p| p.name == n)
            .map_or(0.0, |p| p.value)
    };
    let base = o.positions.first().map(|p| p.center_mm).unwrap_or([0.0; 3]);
    let mut figs = String::new();
    for (axis, name) in ["x", "y", "z"].iter().enumerate() {
        let mut along: Vec<f64> = o.positions.iter().map(|p| p.center_mm[axis]).collect();
        along.sort_by(f64::total_cmp);
        along.dedup_by(|a, b| (*a - *b).abs() < 1.0);
        if along.len() < 2 {
            continue;
        }
        let series: Vec<Series> = [
            ("xx", PALETTE[0]),
            ("yy", PALETTE[1]),
            ("xy", PALETTE[2]),
            ("yx", PALETTE[3]),
        ]
        .iter()
        .map(|(ij, c)| {
            let pts = along
                .iter()
                .map(|&q| {
                    let mut pos = base;
                    pos[axis] = q;
                    let xi = pos.map(|v| v / 500.0);
                    let p = val(&format!("dynamics.P_{ij}.1"))
                        + xi[0] * val(&format!("dynamics.P_{ij}.x"))
                        + xi[1] * val(&format!("dynamics.P_{ij}.y"))
                        + xi[2] * val(&format!("dynamics.P_{ij}.z"));
                    (q, p * 1e6)
                })
                .collect();
            (format!("P_{ij}"), *c, pts, true)
        })
        .collect();
        let _ = write!(
            figs,
            "<figure>{}<figcaption>The fitted compliance along {} (the other coordinates at the first position's), µm per m/s². P_xx and P_yy include what of the gain's f² term the spin-up could not separate (see below).</figcaption></figure>",
            xy(&format!("p-along-{name}"), &series, &format!("{} (mm)", name.to_uppercase()), "P (µm per m/s²)"),
            name.to_uppercase()
        );
    }
    let _ = write!(body, "<h2>Coefficients against position</h2>{figs}");
    body += "<h2>Parameters</h2><table><tr><th>parameter</th><th>value</th><th>standard uncertainty</th></tr>";
    for p in &o.params {
        let _ = write!(
            body,
            "<tr><td>{}</td><td>{:.6e}</td><td>{:.2e}</td></tr>",
            esc(&p.name),
            p.value,
            p.sigma
        );
    }
    body += "</table><p class=\"muted\">Units: τ in s; P in mm per mm/s², per monomial 1, x, y, z of the position over 500 mm; phase b0 rad, b1 rad/Hz, b2 rad/Hz²; gain f¹ 1/Hz, f² 1/Hz².</p>";
    for c in &o.confounded {
        let _ = write!(body, "<p><b>Barely separated:</b> {}</p>", esc(c));
    }
    for u in &o.undetermined {
        let _ = write!(body, "<p><b>Not determined:</b> {}</p>", esc(u));
    }
    for n in &o.notes {
        let _ = write!(body, "<p class=\"muted\">{}</p>", esc(n));
    }
    page("scancorr calibrate dynamics", &body)
}

/// `calibrate probe-force --report`: each setting's sphere radius against the deflection
/// before and after the force correction (a line to zero force), every parameter.
pub fn probe_force(
    start: &Calibration,
    o: &scancorr_core::calibrate::probe_force::Outcome,
    noise_floor_um: f64,
) -> String {
    let mut body = format!(
        "<p>Start: v{} of {}. {} settings on the master sphere; residual about each circle's static map {:.3} → <b>{:.3} µm</b> (noise floor {:.3} µm); reduced χ² of the circles × deflections {:.2}.</p>",
        start.version,
        esc(&start.machine_id),
        o.settings.len(),
        o.rms_before_um,
        o.rms_after_um,
        noise_floor_um,
        o.cell_chi2
    );
    let series = |after: bool| -> Vec<Series> {
        o.settings
            .iter()
            .enumerate()
            .map(|(i, s)| {
                let r = if after {
                    &s.radius_error_after_um
                } else {
                    &s.radius_error_before_um
                };
                let mut pts: Vec<(f64, f64)> = vec![(0.0, s.radius_error_at_zero_um[0])];
                pts.extend(s.deflections_mm.iter().zip(r).map(|(d, e)| (*d, *e)));
                (
                    format!(
                        "tip {} A1 {:.0}° A2 {:.0}°",
                        s.tip, s.head_deg[0], s.head_deg[1]
                    ),
                    PALETTE[i % PALETTE.len()],
                    pts,
                    true,
                )
            })
            .collect()
    };
    let _ = write!(
        body,
        "<h2>Radius against deflection</h2><figure>{}<figcaption>Before: the sphere's radius less its certified radius per deflection, measured without a force correction; the first point of each line is the fitted value at zero force. The slope is the stylus bending.</figcaption></figure><figure>{}<figcaption>After the fitted force coefficients: flat. The first point, the fitted zero-force value, can differ from the flat line by a few tenths of a µm: the circles' drift with the measured temperatures shares that much with the radius.</figcaption></figure>",
        xy("radius-before", &series(false), "deflection (mm)", "R − R_cert (µm)"),
        xy("radius-after", &series(true), "deflection (mm)", "R − R_cert (µm)")
    );
    body += "<h2>Parameters</h2><table><tr><th>parameter</th><th>value</th><th>standard uncertainty</th></tr>";
    for p in &o.params {
        let _ = write!(
            body,
            "<tr><td>{}</td><td>{:.4}</td><td>{:.4}</td></tr>",
            esc(&p.name),
            p.value * 1e3,
            p.sigma * 1e3
        );
    }
    body += "</table><p class=\"muted\">probe_k in µm of error per mm of deflection; radius in µm (of the tip radius at zero force).</p>";
    for s in &o.settings {
        let _ = write!(
            body,
            "<p class=\"muted\">tip {} at ({}, {})°: {} points; at zero force R − R_cert = {:+.2} ± {:.2} µm; the static error map's form (harmonics 2 and up, common to every deflection) {:.3} µm RMS; left after the fit {:.3} µm RMS.</p>",
            s.tip, s.head_deg[0], s.head_deg[1], s.points, s.radius_error_at_zero_um[0], s.radius_error_at_zero_um[1], s.static_form_um, s.fit_rms_um
        );
    }
    for u in &o.undetermined {
        let _ = write!(body, "<p><b>Not determined:</b> {}</p>", esc(u));
    }
    for n in &o.notes {
        let _ = write!(body, "<p class=\"muted\">{}</p>", esc(n));
    }
    page("scancorr calibrate probe-force", &body)
}

/// `calibrate tips --report`: each setting's offset from the reference before and what the
/// qualification leaves, the reference's drift in time, every parameter.
pub fn tips(
    start: &Calibration,
    o: &scancorr_core::calibrate::tips::Outcome,
    consistency_after_um: Option<f64>,
    noise_floor_um: f64,
) -> String {
    let mut body = format!(
        "<p>Start: v{} of {}. Reference tip {}; {} settings on the master sphere{}. Tip-to-tip consistency <b>{:.3} µm</b> with the starting calibration, <b>{}</b> with the qualified one (noise floor {:.3} µm); fit residual {:.3} µm.</p>",
        start.version,
        esc(&start.machine_id),
        o.reference_tip,
        o.settings.len(),
        o.reference_temp_c
            .map_or(String::new(), |t| format!(", at {t:.2} °C (range {:.2} K)", o.temp_range_k)),
        o.consistency_before_um,
        consistency_after_um.map_or("—".into(), |a| format!("{a:.3} µm")),
        noise_floor_um,
        o.residual_rms_um
    );
    let others: Vec<_> = o
        .settings
        .iter()
        .filter(|s| s.tip != o.reference_tip)
        .collect();
    // Before and after on one scale, each setting's pair together.
    let norm = |v: [f64; 3]| (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    let rows: Vec<(String, f64, bool)> = others
        .iter()
        .flat_map(|s| {
            let name = format!(
                "tip {} A1 {:.0}° A2 {:.0}°",
                s.tip, s.head_deg[0], s.head_deg[1]
            );
            [
                (format!("{name} before"), norm(s.offset_um), false),
                (format!("{name} after"), norm(s.residual_um), false),
            ]
        })
        .collect();
    let _ = write!(
        body,
        "<h2>Each setting against the reference</h2><figure>{}<figcaption>|S − S_ref| per setting, µm: before with the starting calibration's styli (catalogue lengths show here), after what the fitted lengths, expansion coefficients and rotation leave; one scale (dashed: 2× the noise floor).</figcaption></figure>",
        bars("tips-offsets", &rows, "µm", Some((2.0 * noise_floor_um, "2× noise floor")))
    );
    // The reference's centre in time: the drift every setting is referred to.
    let refs: Vec<_> = o
        .settings
        .iter()
        .filter(|s| s.tip == o.reference_tip)
        .collect();
    if refs.len() > 1 {
        let c0 = refs[0].center_mm;
        let series: Vec<Series> = ["x", "y", "z"]
            .iter()
            .enumerate()
            .map(|(i, a)| {
                (
                    format!("centre {a}"),
                    PALETTE[i],
                    refs.iter()
                        .map(|s| (s.t_s, (s.center_mm[i] - c0[i]) * 1e3))
                        .collect(),
                    true,
                )
            })
            .collect();
        let _ = write!(
            body,
            "<h2>The reference in time</h2><figure>{}<figcaption>The reference tip's sphere centre against time (µm from its first measurement): the drift (the scales' and the stand's growth as the room warms) that each setting is referred to, interpolated in time.</figcaption></figure>",
            xy("reference-drift", &series, "time (s)", "centre drift (µm)")
        );
    }
    body += "<h2>Settings</h2><table><tr><th>setting</th><th>points</th><th>radius − certified µm</th><th>form µm</th><th>offset µm (x, y, z)</th><th>left µm (x, y, z)</th></tr>";
    for s in &o.settings {
        let _ = write!(
            body,
            "<tr><td>tip {} A1 {:.0}° A2 {:.0}°</td><td>{}</td><td>{:.3}</td><td>{:.3}</td><td>{:.3}, {:.3}, {:.3}</td><td>{:.3}, {:.3}, {:.3}</td></tr>",
            s.tip, s.head_deg[0], s.head_deg[1], s.points, s.radius_error_um, s.rms_um,
            s.offset_um[0], s.offset_um[1], s.offset_um[2],
            s.residual_um[0], s.residual_um[1], s.residual_um[2]
        );
    }
    body += "</table><h2>Parameters</h2><table><tr><th>parameter</th><th>value</th><th>standard uncertainty</th></tr>";
    for p in o.params.iter().chain(&o.rotation) {
        let _ = write!(
            body,
            "<tr><td>{}</td><td>{:.6}</td><td>{:.2e}</td></tr>",
            esc(&p.name),
            p.value,
            p.sigma
        );
    }
    body += "</table><p class=\"muted\">Lengths and radii in mm, expansion coefficients in 1/K, the rotation at the sphere (the last three) in rad.</p>";
    for u in &o.undetermined {
        let _ = write!(body, "<p><b>Not determined:</b> {}</p>", esc(u));
    }
    for n in &o.notes {
        let _ = write!(body, "<p class=\"muted\">{}</p>", esc(n));
    }
    page("scancorr calibrate tips", &body)
}

/// `calibrate straightness --report`: the guide's and the part's straightness with their
/// uncertainty bands (±2σ), the pitch where the method separates it, what it cannot see.
pub fn straightness(
    start: &Calibration,
    o: &scancorr_core::calibrate::separation::Outcome,
    warnings: &[String],
) -> String {
    let s = &o.separation;
    let mut body = format!(
        "<p>Start: v{} of {}. <b>{}</b>: straightness of the {} guide towards {}, {} stations ({:.0}–{:.0} mm), {} readings averaged per probe and station. Straightness is each profile's deviation from its least-squares line; the pitch is about its mean. <b>Cannot see:</b> {}.</p>",
        start.version,
        esc(&start.machine_id),
        esc(&s.method),
        o.axis.name(),
        o.toward.name(),
        s.stations_mm.len(),
        s.stations_mm.first().copied().unwrap_or(0.0),
        s.stations_mm.last().copied().unwrap_or(0.0),
        o.samples_per_reading,
        esc(&s.cannot_see.join(", "))
    );
    let band = |label: &str, colour: &'static str, x: &[f64], v: &[f64], u: &[f64], k: f64| {
        let line = |sign: f64| -> Vec<(f64, f64)> {
            x.iter()
                .zip(v.iter().zip(u))
                .map(|(x, (v, u))| (*x, (v + sign * 2.0 * u) * k))
                .collect()
        };
        vec![
            (
                label.to_string(),
                colour,
                x.iter().zip(v).map(|(x, v)| (*x, v * k)).collect(),
                true,
            ),
            ("+2σ".to_string(), "#bbbbbb", line(1.0), true),
            ("−2σ".to_string(), "#bbbbbb", line(-1.0), true),
        ]
    };
    let _ = write!(
        body,
        "<h2>Guide</h2><figure>{}<figcaption>The carriage's lateral motion towards {} at the carriage positions the scales read, with ±2σ (the sequential methods integrate: the band widens along the travel).</figcaption></figure>",
        xy(
            "guide",
            &band("guide", PALETTE[0], &s.stations_mm, &s.guide_straightness_mm, &s.guide_straightness_mm_u, 1e3),
            &format!("{} (mm)", o.axis.name()),
            "straightness (µm)"
        ),
        o.toward.name()
    );
    let _ = write!(
        body,
        "<h2>Part (straightedge)</h2><figure>{}<figcaption>The straightedge's own form, with ±2σ.</figcaption></figure>",
        xy(
            "part",
            &band("part", PALETTE[1], &s.part_positions_mm, &s.part_straightness_mm, &s.part_straightness_mm_u, 1e3),
            &format!("{} (mm)", o.axis.name()),
            "straightness (µm)"
        )
    );
    match (&s.pitch_rad, &s.pitch_rad_u) {
        (Some(p), Some(u)) => {
            let _ = write!(
                body,
                "<h2>Pitch</h2><figure>{}<figcaption>The carriage's rotation about the third axis, about its mean, with ±2σ.</figcaption></figure>",
                xy(
                    "pitch",
                    &band("pitch", PALETTE[2], &s.stations_mm, p, u, 1e6),
                    &format!("{} (mm)", o.axis.name()),
                    "pitch (µrad)"
                )
            );
        }
        _ => {
            body += "<p><b>Pitch:</b> not separated by this method.</p>";
        }
    }
    if let Some(f) = o.flatness_mm {
        let series: Vec<Series> = o
            .lines
            .iter()
            .enumerate()
            .map(|(i, l)| {
                (
                    format!("{} = {:.0} mm", "line", l.step_mm),
                    PALETTE[i % PALETTE.len()],
                    l.positions_mm
                        .iter()
                        .zip(&l.height_mm)
                        .map(|(x, h)| (*x, h * 1e3))
                        .collect(),
                    true,
                )
            })
            .collect();
        let _ = write!(
            body,
            "<h2>Flatness</h2><p>{} lines stepped across: <b>{:.3} µm</b> peak-to-valley about the least-squares plane.</p><figure>{}<figcaption>Each line's height about the plane of all of them; the lines are tied by one probe's readings at the same carriage position (the guide cancels), so the stepping axis's own straightness between the lines is in them.</figcaption></figure>",
            o.lines.len(),
            f * 1e3,
            xy("flatness", &series, &format!("{} (mm)", o.axis.name()), "height (µm)")
        );
    }
    for p in &s.params {
        let _ = write!(
            body,
            "<p>{}: {:.6} ± {:.6}</p>",
            esc(&p.name),
            p.value,
            p.sigma
        );
    }
    for n in &s.notes {
        let _ = write!(body, "<p class=\"muted\">{}</p>", esc(n));
    }
    for w in warnings {
        let _ = write!(body, "<p><b>Warning:</b> {}</p>", esc(w));
    }
    page("scancorr calibrate straightness", &body)
}

/// `calibrate dynamic-map --report`: per map the three scans' radial deviations, the two
/// extrapolations to zero deflection, and e2 (the fast scan's error the map removes) with its
/// uncertainty band.
pub fn dynamic_map(
    start: &Calibration,
    o: &scancorr_core::calibrate::dynamic_map::Outcome,
    noise_floor_um: f64,
) -> String {
    let mut body = format!(
        "<p>Start: v{} of {}. {} map(s); noise floor {:.3} µm.</p>",
        start.version,
        esc(&start.machine_id),
        o.maps.len(),
        noise_floor_um
    );
    for m in &o.maps {
        let line = |v: &[f64]| -> Vec<(f64, f64)> {
            m.theta_deg.iter().copied().zip(v.iter().copied()).collect()
        };
        let band = |s: f64| -> Vec<(f64, f64)> {
            m.theta_deg
                .iter()
                .zip(m.e2_um.iter().zip(&m.e2_u_um))
                .map(|(t, (e, u))| (*t, e + s * 2.0 * u))
                .collect()
        };
        let scans: Vec<Series> = vec![
            ("S1 (slow, d1)".into(), PALETTE[0], line(&m.s1_um), true),
            ("F1 (fast, d2)".into(), PALETTE[1], line(&m.f1_um), true),
            ("F2 (fast, d1)".into(), PALETTE[2], line(&m.f2_um), true),
        ];
        let zero: Vec<Series> = vec![
            ("LSZD".into(), PALETTE[0], line(&m.lszd_um), true),
            ("HSZD".into(), PALETTE[2], line(&m.hszd_um), true),
        ];
        let e2: Vec<Series> = vec![
            (
                "e2 = F2 − LSZD".into(),
                PALETTE[3 % PALETTE.len()],
                line(&m.e2_um),
                true,
            ),
            ("e2 + 2σ".into(), "#bbb", band(1.0), true),
            ("e2 − 2σ".into(), "#bbb", band(-1.0), true),
        ];
        let _ = write!(
            body,
            "<h2>{}: {:.0} mm/s (slow {:.0} mm/s), d1 {:.3} mm, d2 {:.3} mm, segments {:?}</h2>\
             <figure>{}<figcaption>Before: the radial deviation of each scan from the slow scan's circle, per bin (positive away from the centre).</figcaption></figure>\
             <figure>{}<figcaption>Extrapolated to zero deflection: at low speed (LSZD, the reference) and at high speed (HSZD).</figcaption></figure>\
             <figure>{}<figcaption>After: e2, what the map removes from a fast scan at d1 (RMS {:.3} µm, its σ {:.3} µm RMS); the dynamic part at zero deflection {:.3} µm RMS, the deflection's e1 {:.3} µm RMS.</figcaption></figure>",
            esc(&m.feature),
            m.speed_mm_s,
            m.slow_speed_mm_s,
            m.d1_mm,
            m.d2_mm,
            m.segments,
            xy("dynamic-map-scans", &scans, "θ (°)", "radial deviation (µm)"),
            xy("dynamic-map-zero", &zero, "θ (°)", "radial deviation (µm)"),
            xy("dynamic-map-e2", &e2, "θ (°)", "e2 (µm)"),
            m.e2_rms_um,
            m.e2_u_rms_um,
            m.dynamic_rms_um,
            m.e1_rms_um
        );
    }
    body += "<h2>Parameters</h2><table><tr><th>parameter</th><th>value (µm, µm/mm)</th><th>standard uncertainty</th></tr>";
    for p in &o.params {
        let _ = write!(
            body,
            "<tr><td>{}</td><td>{:.4}</td><td>{:.4}</td></tr>",
            esc(&p.name),
            p.value * 1e3,
            p.sigma * 1e3
        );
    }
    body += "</table>";
    for s in &o.speed_search {
        let _ = write!(
            body,
            "<h2>Speed search: {} (tolerance {:.3} µm)</h2><table><tr><th>speed (mm/s)</th><th>slow/fast difference, RMS of F2 − S1 (µm)</th><th>σ (µm)</th><th>map</th></tr>",
            esc(&s.feature),
            s.tolerance_um
        );
        for x in &s.steps {
            let _ = write!(
                body,
                "<tr><td>{:.0}</td><td>{:.3}</td><td>{:.3}</td><td>{}</td></tr>",
                x.speed_mm_s,
                x.difference_um,
                x.difference_u_um,
                if x.mapped { "stored" } else { "not needed" }
            );
        }
        let _ = write!(
            body,
            "</table><p>No map needed up to {}.</p>",
            s.fastest_within_mm_s.map_or(
                "— (the slowest fast speed already leaves the tolerance)".into(),
                |v| format!("{v:.0} mm/s")
            )
        );
    }
    for s in &o.skipped {
        let _ = write!(body, "<p><b>Not mapped:</b> {}</p>", esc(s));
    }
    for n in &o.notes {
        let _ = write!(body, "<p class=\"muted\">{}</p>", esc(n));
    }
    page("scancorr calibrate dynamic-map", &body)
}

#[cfg(test)]
mod tests {
    use super::value_sigma;

    #[test]
    fn values_carry_their_uncertainty_to_its_second_digit() {
        assert_eq!(value_sigma(2.3127e-6, Some(4.2e-8)), "(2.313 ± 0.042)e-6");
        assert_eq!(value_sigma(0.01234, Some(0.00051)), "0.01234 ± 0.00051");
        assert_eq!(value_sigma(12.34, Some(1.2)), "12.3 ± 1.2");
        assert_eq!(value_sigma(-1.5e-9, None), "-1.500e-9");
        assert_eq!(value_sigma(0.0, None), "0");
        assert_eq!(value_sigma(f64::NAN, Some(1.0)), "—");
        // A value far below its σ keeps σ's exponent.
        assert_eq!(value_sigma(1e-12, Some(3.0e-7)), "(0.0 ± 3.0)e-7");
    }
}

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
                esc(&crate::thermalcmd::term_name(t)),
                value_sigma(t.k, Some(t.sigma)),
                esc(&crate::thermalcmd::term_unit(t)),
                t.contribution_um
            );
        }
        let _ = write!(body, "</table><p>{} terms in all; constant {:.3} µm; ridge λ {:.1e}; residual lag-1 correlation {:.3} (the σ are inflated for it and include the spread over the cross-validation's fits).</p>", c.terms.len(), c.offset_um, c.lambda, c.residual_rho);
    }
    page("scancorr calibrate thermal-drift", &body)
}
