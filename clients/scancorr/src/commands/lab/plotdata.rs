//! `--csv DIR`: every series a lab report plots, as CSV files an engineer can redraw in
//! matplotlib or a spreadsheet — the polar traces (`traces.csv`: one row per trace — a run:
//! feature, tip, head angles, deflection, direction, speed — and 1° bin), the residual per bin of each feature (`bins.csv`), the circles' harmonics
//! (`harmonics.csv`) and, for `diagnose`, the candidate ranking (`candidates.csv`), the best
//! candidate's predicted traces beside the measured ones (`prediction.csv`), the residual
//! along each unexplained structure's coordinate with the fitted structure (`structure.csv`)
//! and the best candidate's parameters (`parameters.csv`). Each file is written under a
//! temporary name and renamed when complete; the folder is created.

use crate::shared::output::AtomicOutput;
use anyhow::{bail, Context, Result};
use scancorr_core::lab::analysis::{Comparison, Diagnosis};
use std::fmt::Write;
use std::path::Path;

fn q(s: &str) -> String {
    crate::shared::output::csv_text(s)
}

/// Prepares `dir` (created when missing; a file there is refused).
pub fn prepare(dir: &Path) -> Result<()> {
    if dir.exists() && !dir.is_dir() {
        bail!("--csv {}: is a file, not a folder", dir.display());
    }
    std::fs::create_dir_all(dir)
        .with_context(|| format!("--csv {}: cannot create it", dir.display()))
}

/// The comparison's series: `traces.csv`, `bins.csv`, `harmonics.csv` (with `prefix`, e.g.
/// `before-`). Returns the files written.
pub fn comparison(dir: &Path, prefix: &str, c: &Comparison) -> Result<Vec<String>> {
    let mut traces = String::from(
        "feature,artifact,diameter_mm,direction,speed_mm_s,circularity_um,radius_um,theta_deg,deviation_um,tip,head_a1_deg,head_a2_deg,deflection_mm\n",
    );
    for t in &c.traces {
        for (th, e) in t.theta_deg.iter().zip(&t.deviation_um) {
            let _ = writeln!(
                traces,
                "{},{},{},{},{},{},{},{},{},{},{},{},{}",
                t.feature + 1,
                q(&t.artifact),
                t.diameter_mm,
                if t.direction > 0 { "ccw" } else { "cw" },
                t.speed_mm_s,
                t.circularity_um,
                t.radius_um,
                th,
                e,
                t.tip,
                t.head_a1_deg,
                t.head_a2_deg,
                t.deflection_mm
            );
        }
    }
    let mut bins = String::from("feature,bin,points,rms_um,mean_um,failing,same_points_as\n");
    for b in &c.bins {
        let _ = writeln!(
            bins,
            "{},{},{},{},{},{},{}",
            q(&b.feature),
            q(&b.bin),
            b.n,
            b.rms_um,
            b.mean_um,
            b.failing,
            q(b.same_points_as.as_deref().unwrap_or(""))
        );
    }
    let mut harm = String::from("feature,artifact,harmonic,amplitude_um\n");
    for h in &c.harmonics {
        for (k, a) in h.amplitude_um.iter().enumerate() {
            let _ = writeln!(harm, "{},{},{},{}", h.feature + 1, q(&h.artifact), k + 1, a);
        }
    }
    write_all(
        dir,
        [
            (format!("{prefix}traces.csv"), traces),
            (format!("{prefix}bins.csv"), bins),
            (format!("{prefix}harmonics.csv"), harm),
        ],
    )
}

/// The candidate ranking of a diagnosis: `candidates.csv`.
pub fn diagnosis(dir: &Path, d: &Diagnosis) -> Result<Vec<String>> {
    let mut s = String::from(
        "action,effect,replaces,significant,explained,cv_rms_before_um,cv_rms_after_um,heldout_rms_before_um,heldout_rms_after_um,delta_bic,parameters\n",
    );
    for c in &d.candidates {
        let _ = writeln!(
            s,
            "{:?},{},{},{},{},{},{},{},{},{},{}",
            c.action,
            q(&c.effect),
            q(c.replaces.as_deref().unwrap_or("")),
            c.significant,
            c.explained,
            c.cv_rms_before_um,
            c.cv_rms_after_um,
            c.heldout_rms_before_um,
            c.heldout_rms_after_um,
            c.delta_bic,
            c.k
        );
    }
    let mut pred = String::from(
        "effect,layer,feature,artifact,direction,speed_mm_s,circularity_um,theta_deg,deviation_um,tip,head_a1_deg,head_a2_deg,deflection_mm\n",
    );
    if let Some(p) = &d.prediction {
        for (layer, ts) in [("measured", &p.measured), ("predicted", &p.predicted)] {
            for t in ts {
                for (th, e) in t.theta_deg.iter().zip(&t.deviation_um) {
                    let _ = writeln!(
                        pred,
                        "{},{layer},{},{},{},{},{},{th},{e},{},{},{},{}",
                        q(&p.effect),
                        t.feature + 1,
                        q(&t.artifact),
                        if t.direction > 0 { "ccw" } else { "cw" },
                        t.speed_mm_s,
                        t.circularity_um,
                        t.tip,
                        t.head_a1_deg,
                        t.head_a2_deg,
                        t.deflection_mm
                    );
                }
            }
        }
    }
    let mut st = String::from(
        "structure,kind,axis,period_mm,harmonic,coordinate,x,points,measured_um,fitted_um\n",
    );
    for (i, x) in d.unexplained.iter().enumerate() {
        let Some(p) = &x.profile else { continue };
        for k in 0..p.x.len() {
            let _ = writeln!(
                st,
                "{},{},{},{},{},{},{},{},{},{}",
                i + 1,
                q(&x.kind),
                q(&x.axis),
                x.period_mm.map(|v| v.to_string()).unwrap_or_default(),
                x.harmonic.map(|v| v.to_string()).unwrap_or_default(),
                q(&p.coordinate),
                p.x[k],
                p.points[k],
                p.measured_um[k],
                p.fitted_um[k]
            );
        }
    }
    let mut par = String::from("effect,parameter,value,sigma\n");
    if let Some(c) = d.candidates.first() {
        for p in &c.params {
            let _ = writeln!(
                par,
                "{},{},{},{}",
                q(&c.effect),
                q(&p.name),
                p.value,
                p.sigma.map(|v| v.to_string()).unwrap_or_default()
            );
        }
    }
    write_all(
        dir,
        [
            ("candidates.csv".to_string(), s),
            ("prediction.csv".to_string(), pred),
            ("structure.csv".to_string(), st),
            ("parameters.csv".to_string(), par),
        ],
    )
}

fn write_all<const N: usize>(dir: &Path, files: [(String, String); N]) -> Result<Vec<String>> {
    let mut outs = vec![];
    for (name, text) in &files {
        let o = AtomicOutput::new("--csv", &dir.join(name))?;
        o.write_all(text)?;
        outs.push(o);
    }
    for o in outs {
        o.commit()?;
    }
    Ok(files.into_iter().map(|(n, _)| n).collect())
}
