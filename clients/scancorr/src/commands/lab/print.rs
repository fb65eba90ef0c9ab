//! The lab's text output: a comparison, a diagnosis (with the structure found and the
//! `lab add custom` command that adds it), a discovery's steps.

use super::args::DataArgs;
use super::data::um;
use anyhow::Result;
use scancorr_core::lab::analysis::{self, Comparison, Diagnosis};
use scancorr_core::Calibration;
use std::path::Path;

/// A diagnosis or discovery as JSON, each unexplained structure's profile abscissa named by
/// its unit as every key of the CLI's JSON states one (`x_mm` along an axis, `x_deg` along the
/// probing direction, from the profile's `coordinate`); an abscissa of another unit keeps `x`,
/// which the units test then names.
pub(super) fn json_with_profile_units(v: &impl serde::Serialize) -> Result<serde_json::Value> {
    fn walk(v: &mut serde_json::Value) {
        match v {
            serde_json::Value::Object(o) => {
                if let Some(serde_json::Value::Object(p)) = o.get_mut("profile") {
                    let unit = p.get("coordinate").and_then(|c| c.as_str()).and_then(|c| {
                        if c.ends_with(", mm") {
                            Some("x_mm")
                        } else if c.ends_with(", °") {
                            Some("x_deg")
                        } else {
                            None
                        }
                    });
                    if let (Some(k), Some(x)) = (unit, p.remove("x")) {
                        p.insert(k.to_string(), x);
                    }
                }
                o.values_mut().for_each(walk);
            }
            serde_json::Value::Array(a) => a.iter_mut().for_each(walk),
            _ => {}
        }
    }
    let mut j = serde_json::to_value(v)?;
    walk(&mut j);
    Ok(j)
}

pub(super) fn print_compare(c: &Comparison, cal: &Calibration) -> Result<()> {
    outln!(
        "calibration v{} ({} effects): {} points",
        cal.version,
        cal.effects.len(),
        c.points
    )?;
    outln!(
        "  deviation RMS {} µm, peak-to-valley {} µm, noise floor {} µm",
        um(c.rms_um),
        um(c.pv_um),
        um(c.noise_floor_um)
    )?;
    if c.failures.is_empty() {
        outln!("  no bin stands out (every bin within 1.3 × the RMS or 2 × the noise floor)")?;
    } else {
        outln!("  where it fails (bins standing out; bins of the same points seen through a correlated feature under the worst):")?;
        for b in c
            .failures
            .iter()
            .filter(|b| b.same_points_as.is_none())
            .take(10)
        {
            outln!(
                "    {:<22} {:<28} RMS {:>7} µm  mean {:>7} µm  ({} points)",
                b.feature,
                b.bin,
                um(b.rms_um),
                um(b.mean_um),
                b.n
            )?;
            let same = c.same_points(b);
            if !same.is_empty() {
                outln!("      the same points as {}", same.join(", "))?;
            }
        }
    }
    let mut features: Vec<usize> = c.traces.iter().map(|t| t.feature).collect();
    features.dedup();
    if !features.is_empty() {
        outln!(
            "  circularity per run (tip, head angles, deflection; direction and speed; each trace about its own centre, 1° means):"
        )?;
    }
    for fi in features {
        let t0 = c.traces.iter().find(|t| t.feature == fi).expect("listed");
        outln!("    {} {} (Ø{} mm):", t0.artifact, fi + 1, t0.diameter_mm)?;
        let mut settings: Vec<String> = vec![];
        for t in c.traces.iter().filter(|t| t.feature == fi) {
            if !settings.contains(&t.setting()) {
                settings.push(t.setting());
            }
        }
        for set in settings {
            let ts: Vec<String> = c
                .traces
                .iter()
                .filter(|t| t.feature == fi && t.setting() == set)
                .map(|t| {
                    format!(
                        "{} {} mm/s {} µm",
                        if t.direction > 0 { "CCW" } else { "CW" },
                        t.speed_mm_s,
                        um(t.circularity_um)
                    )
                })
                .collect();
            outln!("      {set}: {}", ts.join(", "))?;
        }
    }
    for h in &c.harmonics {
        let a: Vec<String> = h
            .amplitude_um
            .iter()
            .enumerate()
            .map(|(k, a)| format!("{}θ {:.3}", k + 1, a))
            .collect();
        outln!(
            "  {} {} harmonics (µm; 1θ is the centre, taken out by the fit): {}",
            h.artifact,
            h.feature + 1,
            a.join("  ")
        )?;
    }
    Ok(())
}

/// What a structure is, in words.
pub(super) fn structure_text(s: &scancorr_core::lab::analysis::Structure) -> String {
    match (s.kind.as_str(), s.period_mm, s.harmonic) {
        ("probe_direction", _, Some(k)) => {
            format!("the {k}θ harmonic of the probing direction (probe lobing)")
        }
        (_, Some(p), _) => format!("a period of {p:.4} mm along {}", s.axis),
        ("reversal", _, _) => format!("the sign of the {} velocity (reversal)", s.axis),
        (k, _, _) => format!("{k} along {}", s.axis),
    }
}

/// A complete `lab add custom` command for a structure: it runs as it is.
pub(super) fn custom_command(s: &scancorr_core::lab::analysis::Structure, d: &DataArgs) -> String {
    let q = |p: &Path| {
        let t = p.display().to_string();
        if t.chars()
            .all(|c| c.is_ascii_alphanumeric() || "._-/+=,".contains(c))
        {
            t
        } else {
            format!("'{}'", t.replace('\'', "'\\''"))
        }
    };
    let name = match (s.kind.as_str(), s.harmonic) {
        ("probe_direction", Some(k)) => format!("probe_direction_{k}"),
        (k, _) => format!("{k}_{}", s.axis),
    };
    let mut c = format!("scancorr lab add custom --name {name}");
    for t in &s.custom_terms {
        c += &format!(" --term '{t}'");
    }
    for b in &d.bag {
        c += &format!(" --bag {}", q(b));
    }
    for b in &d.validate {
        c += &format!(" --validate {}", q(b));
    }
    if let Some(a) = &d.artifact {
        c += &format!(" --artifact {a}");
    }
    if d.stride != 4 {
        c += &format!(" --stride {}", d.stride);
    }
    c += &format!(" --calib {} --out next.json", q(&d.calib));
    c
}

pub(super) fn print_diagnosis(
    d: &Diagnosis,
    data: &DataArgs,
    model: &std::collections::BTreeMap<String, String>,
) -> Result<()> {
    outln!(
        "residual RMS {} µm (cross-validated {} µm, held out {} µm), noise floor {} µm, {} fit / {} held-out points",
        um(d.rms_um),
        um(d.cv_rms_um),
        um(d.heldout_rms_um),
        um(d.noise_floor_um),
        d.points[0],
        d.points[1]
    )?;
    let label = |c: &analysis::CandidateReport| crate::report::candidate_label(c, model);
    let w = d
        .candidates
        .iter()
        .take(12)
        .map(|c| label(c).chars().count())
        .max()
        .unwrap_or(0)
        .max(34);
    outln!("  {}", crate::report::DIAGNOSIS_ORDER)?;
    outln!(
        "  {:<w$} {:>9} {:>9} {:>4} {:>13} {:>13} {:>13} {:>8}",
        "candidate",
        "CV expl.",
        "held expl",
        "sig",
        "CV µm",
        "held-out µm",
        "fit µm",
        "ΔBIC"
    )?;
    let pair = |a: f64, b: f64| format!("{a:.3}→{b:.3}");
    for c in d.candidates.iter().take(12) {
        outln!(
            "  {:<w$} {:>8.1}% {:>9} {:>4} {:>13} {:>13} {:>13} {:>8.0}",
            label(c),
            c.explained * 100.0,
            crate::report::heldout_explained(c)
                .map_or("—".to_string(), |h| format!("{:.1}%", h * 100.0)),
            if c.significant { "yes" } else { "no" },
            pair(c.cv_rms_before_um, c.cv_rms_after_um),
            pair(c.heldout_rms_before_um, c.heldout_rms_after_um),
            pair(c.rms_before_um, c.rms_after_um),
            c.delta_bic
        )?;
    }
    // As printed (one decimal of a per cent): the rows this line counts are those a reader sees.
    let shown = |x: f64| (x * 1000.0).round() / 10.0;
    let contradicted = d
        .candidates
        .iter()
        .take(12)
        .filter(|c| {
            shown(c.explained) > 0.0
                && crate::report::heldout_explained(c).is_some_and(|h| shown(h) <= 0.0)
        })
        .count();
    if contradicted > 0 {
        outln!(
            "  {contradicted} of these remove cross-validated residual yet leave the held-out data no better (held expl ≤ 0): they fit the scans of these placements, not the held-out data"
        )?;
    }
    if !d.candidates.iter().any(|c| c.significant) {
        outln!("  no candidate is significant (none removes half the noise floor from scans it was not fitted on)")?;
    }
    for s in &d.skipped {
        outln!("  not tested: {s}")?;
    }
    for c in &d.confounded {
        outln!("  confounded: {} and {} (each reproduces {:.0} % / {:.0} % of the other) — to separate them:", c.effects[0], c.effects[1], c.r2[0] * 100.0, c.r2[1] * 100.0)?;
        for s in &c.separate_by {
            outln!("    · {s}")?;
        }
    }
    for s in &d.unexplained {
        outln!(
            "  unexplained: {}, amplitude {:.3} µm, {:.0} % of the residual →\n    {}",
            structure_text(s),
            s.amplitude_um,
            s.explained * 100.0,
            custom_command(s, data)
        )?;
    }
    Ok(())
}

pub(super) fn print_discovery(
    d: &scancorr_core::lab::discover::Discovery,
    dir: &Path,
) -> Result<()> {
    let f = &d.r#final;
    outln!(
        "stopped: {} — held-out RMS {} → {} µm, noise floor {} µm ({:.2}× the floor), cross-validated {} µm",
        d.stopped,
        um(d.start_heldout_rms_um),
        um(f.heldout_rms_um),
        um(f.noise_floor_um),
        f.heldout_rms_um / f.noise_floor_um.max(1e-9),
        um(f.cv_rms_um)
    )?;
    outln!(
        "  final model v{} ({}): {}",
        f.version,
        dir.join("calibration.json").display(),
        f.effects.join(", ")
    )?;
    if let Some(r) = &d.restart {
        outln!("  restart: {r}")?;
        if !d.abandoned.is_empty() {
            outln!(
                "  the other run's steps (versions kept in {}): {}",
                dir.display(),
                d.abandoned
                    .iter()
                    .map(|s| format!("{} {} (v{})", s.action, s.effect, s.version))
                    .collect::<Vec<_>>()
                    .join(", ")
            )?;
        }
    }
    for c in &d.confounded {
        outln!(
            "  confounded on this campaign: {} and {} — to separate them:",
            c.effects[0],
            c.effects[1]
        )?;
        for s in &c.separate_by {
            outln!("    · {s}")?;
        }
    }
    for r in &d.refused {
        outln!("  not taken (held-out data worse): {r}")?;
    }
    if !d.unidentifiable.is_empty() {
        outln!("  {} parameter(s) the campaign cannot determine (kept at their minimum-norm values), e.g. {}", d.unidentifiable.len(), d.unidentifiable.iter().take(3).cloned().collect::<Vec<_>>().join("; "))?;
    }
    for s in &d.unexplained {
        outln!(
            "  left unexplained: {} along {} ({:.3} µm, {:.0} % of the residual)",
            s.kind,
            s.axis,
            s.amplitude_um,
            s.explained * 100.0
        )?;
    }
    Ok(())
}

/// Fitted parameters in the text output, the first 12 (`rest`: where the others are), each
/// value ± σ with what determines it when not the data alone, or "not determined".
pub(super) fn print_params(ps: &[analysis::Param], indent: &str, rest: &str) -> Result<()> {
    for p in ps.iter().take(12) {
        match p.sigma {
            Some(_) => outln!(
                "{indent}{:<44} {}{}",
                p.name,
                crate::report::value_sigma(p.value, p.sigma),
                p.note
                    .as_deref()
                    .map(|n| format!("  ({n})"))
                    .unwrap_or_default()
            )?,
            None => outln!(
                "{indent}{:<44} {} (not determined by this data)",
                p.name,
                crate::report::value_sigma(p.value, None)
            )?,
        }
    }
    if ps.len() > 12 {
        outln!("{indent}… {} more ({rest})", ps.len() - 12)?;
    }
    Ok(())
}

/// How many of a fit's parameters the data did not determine (kept at minimum-norm values).
pub(super) fn print_undetermined(o: &analysis::FitOutcome) -> Result<()> {
    if !o.unidentifiable.is_empty() {
        outln!(
            "  {} parameter(s) not determined by this data (minimum-norm values)",
            o.unidentifiable.len()
        )?;
    }
    Ok(())
}
