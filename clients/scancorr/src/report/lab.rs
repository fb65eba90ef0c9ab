//! The model lab's reports: compare, diagnose, add, history, discover.

use super::svg::value_sigma;
use super::svg::{
    bars, colour_keys, esc, page, polar, polar_over, scale_of, xy, PolarScale, Series,
};
use scancorr_core::lab::analysis::{CandidateReport, Comparison, Diagnosis, Move};
use scancorr_core::lab::dataset::Dataset;
use scancorr_core::lab::traces::Trace;
use scancorr_core::Calibration;
use serde::Serialize;
use std::collections::BTreeMap;
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
    let scale = PolarScale {
        upd: scale_of(&all),
        against: None,
    };
    for (fi, (_, f)) in ds.features.iter().enumerate() {
        let pred: Vec<&Trace> = p.predicted.iter().filter(|t| t.feature == fi).collect();
        let meas: Vec<&Trace> = p.measured.iter().filter(|t| t.feature == fi).collect();
        if pred.is_empty() {
            continue;
        }
        let keys = colour_keys(&[&pred[..], &meas[..]].concat());
        let title = format!(
            "{} {} (Ø{} mm) — {verb} {}",
            f.artifact,
            fi + 1,
            f.certificate_diameter_mm.unwrap_or(f.nominal_diameter_mm),
            p.effect
        );
        s += &polar_over(&title, "predicted", &pred, &meas, scale, &keys);
    }
    s
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
        "<p>Calibration <b>v{}</b> of machine <b>{}</b> ({}). {} points.</p><table><tr><th>figure</th><th>µm</th></tr><tr><td>deviation RMS</td><td>{:.3}</td></tr><tr><td>peak-to-valley</td><td>{:.3}</td></tr><tr><td>noise floor</td><td>{:.3}</td></tr></table>",
        cal.version,
        esc(&cal.machine_id),
        match cal.effects.len() {
            0 => "no effects: the nominal model".to_string(),
            n => format!(
                "{n} effect{}: {}",
                if n == 1 { "" } else { "s" },
                esc(&cal.effects.iter().map(|e| e.id()).collect::<Vec<_>>().join(", "))
            ),
        },
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

/// Polar plots of every circle feature with traces; with `before`, a before and an after plot
/// per feature. The "now" plots share one scale; the "before" plots one, and the "after" plots
/// their own (the residual left magnified, the magnification stated), so that what is left
/// after a correction is readable and the plots of one kind compare between features.
fn polars(ds: &Dataset, cmp: &Comparison, before: Option<(&Dataset, &Comparison)>) -> String {
    let mut s = String::from(
        "<h2>Deviation of each circle, one trace per run (tip, head angles, deflection, direction, speed)</h2>",
    );
    let now: Vec<&Trace> = cmp.traces.iter().collect();
    let was: Vec<&Trace> = before.iter().flat_map(|(_, b)| b.traces.iter()).collect();
    if now.is_empty() && was.is_empty() {
        s += "<p class=\"muted\">No circle was scanned at a steady speed over a quarter turn or more: nothing to draw.</p>";
        return s;
    }
    let (upd_after, upd_before) = (scale_of(&now), scale_of(&was));
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
            let bt = of(b, fi);
            let keys = colour_keys(&[&bt[..], &after[..]].concat());
            let bs = PolarScale {
                upd: upd_before,
                against: None,
            };
            s += &polar(&format!("{title} — before"), "before", &bt, bs, &keys);
            let scale = PolarScale {
                upd: upd_after.min(upd_before),
                against: Some(upd_before),
            };
            s += &polar(&format!("{title} — after"), "after", &after, scale, &keys);
        } else {
            let scale = PolarScale {
                upd: upd_after,
                against: None,
            };
            s += &polar(&title, "now", &after, scale, &colour_keys(&after));
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

/// The model's effects by id, each named by its library variant (`accel_deflection:full,order=1`)
/// where one matches it, else by its kind: what a swap replaces, so that a swap of one variant
/// for another never reads `accel_deflection for accel_deflection`.
pub fn model_variants(cal: &Calibration, ds: &Dataset) -> BTreeMap<String, String> {
    use scancorr_core::lab::candidates::{library_candidates, variant_key};
    let library = library_candidates(ds);
    cal.effects
        .iter()
        .map(|e| {
            let key = variant_key(e);
            let name = library
                .iter()
                .find(|(_, c)| c.kind() == e.kind() && variant_key(c) == key)
                .map(|(n, _)| n.clone())
                .unwrap_or_else(|| format!("{} (its own variant)", e.kind()));
            (e.id(), name)
        })
        .collect()
}

/// A candidate's row label: `servo_gain` (added), `accel_deflection for
/// accel_deflection:full,order=1` (swapped: the variant brought in for the model's),
/// `drop probe_force`.
pub fn candidate_label(c: &CandidateReport, model: &BTreeMap<String, String>) -> String {
    match (&c.action, &c.replaces) {
        (Move::Swap, Some(r)) => {
            let was = model.get(r).cloned().unwrap_or_else(|| r.clone());
            format!("{} for {was}", c.effect)
        }
        (Move::Drop, _) => format!("drop {}", c.effect),
        _ => c.effect.clone(),
    }
}

/// The order of a diagnosis's rows ([`tidy_diagnosis`]) and what "explained" means, as every
/// output states it.
pub const DIAGNOSIS_ORDER: &str = "ranked: the significant first, then by the share of the cross-validated residual each removes (CV expl.: every effect refitted, each alternate scan predicted from the others), largest first; held expl: the same share of the held-out data's mean square (negative: worse)";

/// The share of the held-out data's mean square a candidate removes, 1 − (after/before)²
/// (negative: the held-out data gets worse); `None` without held-out data.
pub fn heldout_explained(c: &CandidateReport) -> Option<f64> {
    let (b, a) = (c.heldout_rms_before_um, c.heldout_rms_after_um);
    (b > 0.0 && b.is_finite() && a.is_finite()).then(|| 1.0 - (a / b).powi(2))
}

/// A diagnosis as every output shows it: the significant candidates first, each group by the
/// share of the cross-validated residual explained (largest first, then by label); a
/// candidate whose label repeats an earlier one's is left out (the better of the two is kept),
/// and so is a repeated note of what was not tested.
pub fn tidy_diagnosis(d: &mut Diagnosis, model: &BTreeMap<String, String>) {
    d.candidates.sort_by(|a, b| {
        b.significant
            .cmp(&a.significant)
            .then(b.explained.total_cmp(&a.explained))
            .then_with(|| candidate_label(a, model).cmp(&candidate_label(b, model)))
    });
    let mut seen = std::collections::BTreeSet::new();
    d.candidates
        .retain(|c| seen.insert(candidate_label(c, model)));
    let mut seen = std::collections::BTreeSet::new();
    d.skipped.retain(|s| seen.insert(s.clone()));
}

/// `lab diagnose --report`.
pub fn diagnose(
    cal: &Calibration,
    ds: &Dataset,
    cmp: &Comparison,
    d: &Diagnosis,
    model: &BTreeMap<String, String>,
) -> String {
    let mut body = summary(cal, cmp);
    let _ = write!(
        body,
        "<h2>Candidate effects</h2><p data-order=\"1\">{}.</p>",
        esc(&DIAGNOSIS_ORDER.replacen("ranked", "Ranked", 1))
    );
    let rows: Vec<(String, f64, bool)> = d
        .candidates
        .iter()
        .take(15)
        .map(|c| {
            (
                candidate_label(c, model),
                c.explained * 100.0,
                c.significant,
            )
        })
        .collect();
    body += &format!("<figure>{}<figcaption>Share of the cross-validated residual each candidate removes (red: significant); the table gives the held-out data's share beside it</figcaption></figure>", bars("ranking", &rows, "%", None));
    body += "<table><tr><th>candidate</th><th>CV explained</th><th>held-out explained</th><th>significant</th><th>cross-validated µm</th><th>held-out µm</th><th>fit µm</th><th>ΔBIC</th><th>parameters</th></tr>";
    for c in d.candidates.iter().take(15) {
        let _ = write!(
            body,
            "<tr><td>{}</td><td>{:.1} %</td><td>{}</td><td>{}</td><td>{:.3} → {:.3}</td><td>{:.3} → {:.3}</td><td>{:.3} → {:.3}</td><td>{:.0}</td><td>{}</td></tr>",
            esc(&candidate_label(c, model)),
            c.explained * 100.0,
            heldout_explained(c).map_or("—".to_string(), |h| format!("{:.1} %", h * 100.0)),
            if c.significant { "yes" } else { "no" },
            c.cv_rms_before_um,
            c.cv_rms_after_um,
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

/// The figures of a `lab add`, each defined once and used by its text, JSON and report alike:
/// "before" is the parent version as it is (not refitted), "after" the new version, each
/// measured on the fit data and on the held-out data; the cross-validated pair is another
/// thing — the parent's model refitted and the new model, each alternate scan predicted from
/// the others — and is labelled so.
pub struct AddFigures {
    /// RMS on the fit data, before → after, µm.
    pub fit_um: [f64; 2],
    /// RMS on the held-out data, before → after, µm.
    pub held_um: [f64; 2],
    /// Cross-validated RMS, the parent's model refitted → the new model, µm.
    pub cv_um: [f64; 2],
    /// The held-out data are --validate bags (else the alternate scans of the fit bags).
    pub validated: bool,
}

/// `lab add --report`: before/after.
#[allow(clippy::too_many_arguments)]
pub fn add(
    old: &Calibration,
    new: &Calibration,
    fit: &scancorr_core::lab::analysis::FitOutcome,
    dsb: &Dataset,
    cb: &Comparison,
    dsa: &Dataset,
    ca: &Comparison,
    f: &AddFigures,
) -> String {
    let (vo, vn) = (old.version, new.version);
    let held = if f.validated {
        "held-out data (--validate)"
    } else {
        "held-out data (alternate scans)"
    };
    let mut body = format!(
        "<p>{}</p><p data-figures=\"1\"><b>Before</b> is v{vo} as it is (not refitted); <b>after</b> is v{vn}. Fit data: <b data-before-um=\"fit\">{:.3}</b> → <b data-after-um=\"fit\">{:.3}</b> µm RMS; {held}: <b data-before-um=\"held\">{:.3}</b> → <b data-after-um=\"held\">{:.3}</b> µm RMS. Cross-validated (each alternate scan predicted from the others; v{vo}'s model refitted → v{vn}'s): {:.3} → {:.3} µm RMS. Noise floor {:.3} µm.</p>",
        esc(&new.note),
        f.fit_um[0],
        f.fit_um[1],
        f.held_um[0],
        f.held_um[1],
        f.cv_um[0],
        f.cv_um[1],
        ca.noise_floor_um
    );
    let rows = vec![
        (format!("v{vo} before, fit data"), f.fit_um[0], false),
        (format!("v{vn} after, fit data"), f.fit_um[1], false),
        (format!("v{vo} before, held-out"), f.held_um[0], false),
        (format!("v{vn} after, held-out"), f.held_um[1], false),
    ];
    body += &format!(
        "<figure>{}<figcaption>Error fall: RMS on the fit data and on the {held}, before (v{vo} as it is) and after (v{vn})</figcaption></figure>",
        bars(
            "error-fall",
            &rows,
            "µm",
            Some((ca.noise_floor_um, "noise floor"))
        )
    );
    let _ = write!(
        body,
        "<p data-all-points=\"1\">The plots below show every point, fit and held-out together, each placement's position fitted: deviation RMS over all points v{vo} {:.3} → v{vn} {:.3} µm (another figure than the two above, for that reason).</p>",
        cb.rms_um, ca.rms_um
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
        body += "<p>Each circle before (the start) and after (the final version), the after plots on their own, magnified scale (stated in each):</p>";
        body += &polars(ds1, c1, Some((ds0, c0)));
    }
    page("scancorr lab — discover", &body)
}
