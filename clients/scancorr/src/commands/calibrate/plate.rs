//! `scancorr calibrate plate --features FILE [--format plug-plate|csv] [--json]`: a plate's
//! features (holes) measured against their nominal positions — the similarity, the
//! anisotropic scale/shear, what lies beyond by cross-validation, and the original plug-plate
//! tool's fit. Reads the file (`platefile`), prints; the logic is
//! `scancorr_core::calibrate::plate`. Reports only: the rigid-body terms are not written into
//! a calibration.

use super::platefile::{self, Format};
use anyhow::{Context, Result};
use scancorr_core::calibrate::plate::{self, Options, Outcome, Residual};
use scancorr_core::calibrate::Param;
use std::path::PathBuf;

/// Arguments of `calibrate plate`.
#[derive(clap::Args)]
pub struct PlateArgs {
    /// The features: nominal against measured positions (mm).
    #[arg(long)]
    pub features: PathBuf,
    /// `plug-plate` (a CMM's plug-plate file: `Plug Plate:`, `Date:`, then rows of Meas X Y,
    /// Nom X Y, Err X Y, Meas D, Nom D, Round) or `csv` (header
    /// `id,nominal_x,nominal_y,measured_x,measured_y`, optional `nominal_d,measured_d`);
    /// default: told from the file's first line.
    #[arg(long)]
    pub format: Option<String>,
    /// The paired t a move needs to be kept (per-hole decrease of the squared left-out
    /// error).
    #[arg(long, default_value_t = 3.0)]
    pub t_min: f64,
    /// Print JSON: `similarity`, `affine`, `selection` (every round's candidates with their
    /// CV figure), `missing_effect`, `original_tool` (with every hole's residuals), `params`
    /// and `uncertainty` by name.
    #[arg(long)]
    pub json: bool,
}

/// Every parameter by a dotted name, for `params` / `uncertainty`.
fn flat(o: &Outcome) -> Vec<(String, &Param)> {
    let s = &o.similarity;
    let mut v: Vec<(String, &Param)> = [
        &s.offset_x_um,
        &s.offset_y_um,
        &s.rotation_urad,
        &s.rotation_deg,
        &s.scale,
        &s.scale_ppm,
    ]
    .into_iter()
    .map(|p| (format!("similarity.{}", p.name), p))
    .collect();
    if let Some(a) = &o.affine {
        v.extend(
            [
                &a.offset_x_um,
                &a.offset_y_um,
                &a.rotation_urad,
                &a.rotation_deg,
                &a.scale,
                &a.scale_ppm,
                &a.quadrupole_ppm,
                &a.scale_x_ppm,
                &a.scale_y_ppm,
                &a.squareness_urad,
                &a.x_axis_rotation_urad,
            ]
            .into_iter()
            .chain(a.quadrupole_angle_deg.as_ref())
            .map(|p| (format!("affine.{}", p.name), p)),
        );
    }
    v.extend(
        o.selection
            .terms
            .iter()
            .chain(o.selection.quadrupole_ppm.as_ref())
            .chain(o.selection.quadrupole_angle_deg.as_ref())
            .map(|p| (format!("selection.{}", p.name), p)),
    );
    v
}

fn pm(p: &Param, digits: usize) -> String {
    format!("{:>10.digits$} ± {:.digits$}", p.value, p.sigma)
}

fn leaves(r: &Residual) -> String {
    format!(
        "radial RMS {:.2} µm (X {:.2}, Y {:.2}, largest {:.2}), CV RMS {} ({} parameters)",
        r.rms_radial_um,
        r.rms_x_um,
        r.rms_y_um,
        r.max_radial_um,
        r.cv_rms_um.map_or_else(
            || format!(
                "undetermined: {}",
                r.cv_undetermined.as_deref().unwrap_or("—")
            ),
            |v| format!("{v:.2} µm")
        ),
        r.parameters
    )
}

/// The tool's `%w.pf`; where the tool printed `nan` (no such holes), a dash.
fn tool(v: Option<f64>, w: usize, p: usize) -> String {
    v.map_or_else(|| format!("{:>w$}", "—"), |x| format!("{x:w$.p$}"))
}

/// Runs `calibrate plate`.
pub fn run(a: PlateArgs) -> Result<()> {
    let format = a.format.as_deref().map(str::parse::<Format>).transpose()?;
    if a.t_min.is_nan() || a.t_min <= 0.0 {
        anyhow::bail!("--t-min {}: a positive number", a.t_min);
    }
    let file = platefile::read(&a.features, format)?;
    let o = plate::run(
        &file.features,
        &Options {
            t_min: a.t_min,
            original_tool: true,
        },
    )
    .with_context(|| format!("{}", a.features.display()))?;
    if a.json {
        let mut v = serde_json::to_value(&o)?;
        let ps = flat(&o);
        v["params"] = ps
            .iter()
            .map(|(k, p)| (k.clone(), p.value.into()))
            .collect::<serde_json::Map<_, _>>()
            .into();
        v["uncertainty"] = ps
            .iter()
            .map(|(k, p)| (k.clone(), p.sigma.into()))
            .collect::<serde_json::Map<_, _>>()
            .into();
        v["file"] = a.features.display().to_string().into();
        v["format"] = file.format.name().into();
        v["plate"] = file.plate.clone().into();
        v["date"] = file.date.clone().into();
        outln!("{}", serde_json::to_string_pretty(&v)?)?;
        return Ok(());
    }
    text(&a, &file, &o)
}

fn text(a: &PlateArgs, file: &platefile::PlateFile, o: &Outcome) -> Result<()> {
    outln!(
        "{}{}{} ({}): {} holes, radius {:.1} mm",
        file.plate
            .as_deref()
            .map_or(String::new(), |p| format!("plate {p}")),
        file.date
            .as_deref()
            .map_or(String::new(), |d| format!(", measured {d}")),
        if file.plate.is_some() || file.date.is_some() {
            format!(" — {}", a.features.display())
        } else {
            a.features.display().to_string()
        },
        file.format.name(),
        o.holes,
        o.radius_mm
    )?;
    let s = &o.similarity;
    outln!("(a) similarity nominal → measured (offset, rotation, one scale), ± 1σ:")?;
    outln!("  offset X      {} µm", pm(&s.offset_x_um, 2))?;
    outln!("  offset Y      {} µm", pm(&s.offset_y_um, 2))?;
    outln!(
        "  rotation      {} µrad  ({:.6} ± {:.6}°, {:.2} ± {:.2}″)",
        pm(&s.rotation_urad, 2),
        s.rotation_deg.value,
        s.rotation_deg.sigma,
        s.rotation_urad.value * 0.206_264_806,
        s.rotation_urad.sigma * 0.206_264_806
    )?;
    outln!(
        "  scale         {} ppm   (factor {:.8})",
        pm(&s.scale_ppm, 2),
        s.scale.value
    )?;
    outln!("  leaves: {}", leaves(&s.residual))?;
    match &o.affine {
        Some(af) => {
            outln!("(b) + anisotropic scale/shear, m = t + (I + Q)·s·R(θ)·n:")?;
            outln!(
                "  quadrupole    {} ppm   at {}",
                pm(&af.quadrupole_ppm, 2),
                af.quadrupole_angle_deg.as_ref().map_or(
                    "an undetermined angle (q below 2σ)".into(),
                    |p| format!("{:.2} ± {:.2}°", p.value, p.sigma)
                )
            )?;
            outln!(
                "  as a CMM's:   scale X {} ppm, scale Y {} ppm,",
                pm(&af.scale_x_ppm, 2).trim(),
                pm(&af.scale_y_ppm, 2).trim()
            )?;
            outln!(
                "                squareness {} µrad ({:.2} ± {:.2}″; > 0: the axes wider than 90°), X axis rotation {} µrad",
                pm(&af.squareness_urad, 2).trim(),
                af.squareness_urad.value * 0.206_264_806,
                af.squareness_urad.sigma * 0.206_264_806,
                pm(&af.x_axis_rotation_urad, 2).trim()
            )?;
            outln!(
                "  with offset X {} µm, Y {} µm, rotation {} µrad, mean scale {} ppm",
                pm(&af.offset_x_um, 2).trim(),
                pm(&af.offset_y_um, 2).trim(),
                pm(&af.rotation_urad, 2).trim(),
                pm(&af.scale_ppm, 2).trim()
            )?;
            outln!("  leaves: {}", leaves(&af.residual))?;
        }
        None => outln!("(b) + anisotropic scale/shear: not determined (below)")?,
    }
    let sel = &o.selection;
    outln!(
        "(c) beyond, by leave-one-hole-out cross-validation (a move kept when the per-hole decrease of the squared left-out error has t ≥ {}):",
        a.t_min
    )?;
    for rd in &sel.rounds {
        outln!("  on {} (CV {:.2} µm):", rd.base, rd.base_cv_um)?;
        let mut cs: Vec<_> = rd.candidates.iter().collect();
        cs.sort_by(|x, y| {
            x.cv_rms_um
                .unwrap_or(f64::MAX)
                .total_cmp(&y.cv_rms_um.unwrap_or(f64::MAX))
        });
        for c in cs {
            let kept = rd.kept.as_deref() == Some(c.term.as_str());
            match (c.cv_rms_um, &c.undetermined) {
                (Some(cv), _) => outln!(
                    "    {:<40} CV {:>6.2} µm  t {:>5}{}",
                    c.description,
                    cv,
                    c.t.map_or("—".into(), |t| format!("{t:.1}")),
                    if kept { "  kept" } else { "" }
                )?,
                (None, why) => outln!(
                    "    {:<40} undetermined: {}",
                    c.description,
                    why.as_deref().unwrap_or("—")
                )?,
            }
        }
    }
    outln!("  chosen: {} — {}", sel.model, leaves(&sel.residual))?;
    if let Some(q) = &sel.quadrupole_ppm {
        outln!(
            "    quadrupole {} ppm{}",
            pm(q, 2).trim(),
            sel.quadrupole_angle_deg
                .as_ref()
                .map_or(String::new(), |p| format!(
                    " at {:.2} ± {:.2}°",
                    p.value, p.sigma
                ))
        )?;
    }
    for t in &sel.terms {
        outln!(
            "    {:<12} {} µm at the plate's edge (R {:.1} mm)",
            t.name.trim_end_matches("_um"),
            pm(t, 2),
            o.radius_mm
        )?;
    }
    match &o.missing_effect {
        Some(m) => outln!("missing effect: {m}")?,
        None => outln!("missing effect: none found")?,
    }
    for b in &o.beyond {
        outln!("  {b}")?;
    }
    if let Some(t) = &o.original_tool {
        outln!(
            "original tool's fit (fitPlugPlateMeas: lmdif on the squared radial errors; large holes = measured D > {} mm, {} of them):",
            plate::LARGE_HOLE_MM,
            t.large_holes
        )?;
        outln!(
            "  FitOffset {:8.3} {:8.3}  FitScale {:8.6}  FitRotAngle {:8.3}",
            t.fit_offset_mm[0],
            t.fit_offset_mm[1],
            t.fit_scale,
            t.fit_rot_angle_deg
        )?;
        outln!(
            "  QPMagnitude {}  QPAngle {}",
            tool(t.qp_magnitude, 10, 8),
            tool(t.qp_angle_deg, 8, 2)
        )?;
        outln!(
            "  ResidRadErrRMS (MANGA) {} ({})  DiaErrRMS (MANGA) {} ({})  MaxDiaErr {}  QPResidRadErrRMS {}",
            tool(t.resid_rad_err_rms_mm, 10, 4),
            tool(t.large_resid_rad_err_rms_mm, 10, 4),
            tool(t.dia_err_rms_mm, 8, 4),
            tool(t.large_dia_err_rms_mm, 8, 4),
            tool(t.max_dia_err_mm, 8, 3),
            tool(t.qp_resid_rad_err_rms_mm, 8, 4)
        )?;
    }
    for u in &o.undetermined {
        outln!("  not determined: {u}")?;
    }
    for n in &o.notes {
        outln!("  note: {n}")?;
    }
    outln!("  note: reported only — the rigid-body terms are not written into a calibration")?;
    Ok(())
}
