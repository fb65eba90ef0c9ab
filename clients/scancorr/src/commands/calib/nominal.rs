//! `scancorr calib nominal`: a machine's nominal calibration from its data sheet and the
//! probe and stylus catalogue (`scancorr_core::datasheet` makes and validates it; this reads
//! the files, writes the document and says where each value came from).

use crate::shared::output::{self, AtomicOutput};
use anyhow::{Context, Result};
use scancorr_core::datasheet::{self, Catalogue, DataSheet, TauSource};
use scancorr_core::transfer::TransferFunction;
use scancorr_core::Calibration;
use std::path::PathBuf;

/// Arguments of `scancorr calib nominal`.
#[derive(clap::Args)]
pub struct NominalArgs {
    /// The machine's data sheet (JSON: `machine_id`, `sample_period_s`, per axis `tau_s` and
    /// `travel_mm`). Without it every axis starts at 10 ms, to be fitted, and the travel is
    /// not checked.
    #[arg(long)]
    datasheet: Option<PathBuf>,
    /// The probe and stylus catalogue (JSON: `probes` with their `tau_s`, `tips` with `id`,
    /// `probe`, `l1_mm`, `l2_mm`, `beta1_deg`, `radius_mm`, `alpha_per_k`).
    #[arg(
        long,
        required_unless_present = "tips_from",
        conflicts_with = "tips_from"
    )]
    catalogue: Option<PathBuf>,
    /// Instead of a catalogue: the probes and tips of this calibration (styli qualified by
    /// `scancorr calibrate tips`; nothing else of it is taken).
    #[arg(long)]
    tips_from: Option<PathBuf>,
    /// Machine id (default: the data sheet's; needed without one).
    #[arg(long)]
    machine: Option<String>,
    /// The controller's streaming period, s (default: the data sheet's, or 0.001).
    #[arg(long)]
    sample_period_s: Option<f64>,
    /// Output calibration (JSON).
    #[arg(long)]
    out: PathBuf,
    /// Print a JSON summary (`out`, `machine`, `tau_s`, `tau_source`, `tips`) instead of text.
    #[arg(long)]
    json: bool,
}

fn read(flag: &str, p: &std::path::Path) -> Result<String> {
    std::fs::read_to_string(p).with_context(|| format!("{flag} {}", p.display()))
}

/// Runs `scancorr calib nominal`.
pub fn run(a: NominalArgs) -> Result<()> {
    match (&a.machine, &a.datasheet) {
        (Some(m), _) => output::check_machine("--machine", m)?,
        (None, None) => anyhow::bail!("give --machine ID (no --datasheet names the machine)"),
        (None, Some(_)) => {}
    }
    let (styli_flag, styli) = match (&a.catalogue, &a.tips_from) {
        (Some(c), _) => ("--catalogue", c.as_path()),
        (None, Some(t)) => ("--tips-from", t.as_path()),
        (None, None) => anyhow::bail!("give --catalogue FILE (or --tips-from CALIBRATION)"),
    };
    let mut inputs = vec![(styli_flag, styli)];
    if let Some(d) = &a.datasheet {
        inputs.push(("--datasheet", d.as_path()));
    }
    output::refuse_same_file(&[("--out", a.out.as_path())], &inputs)?;
    let sheet = a
        .datasheet
        .as_deref()
        .map(|p| {
            DataSheet::from_json(&read("--datasheet", p)?)
                .with_context(|| format!("{}", p.display()))
        })
        .transpose()?;
    let text = read(styli_flag, styli)?;
    let catalogue = if a.catalogue.is_some() {
        Catalogue::from_json(&text).map_err(anyhow::Error::from)
    } else {
        Calibration::from_json(&text)
            .map_err(anyhow::Error::from)
            .and_then(|c| Ok(Catalogue::from_calibration(&c)?))
    }
    .with_context(|| format!("{}", styli.display()))?;
    let out = AtomicOutput::new("--out", &a.out)?;
    let (cal, source) = datasheet::nominal(
        a.machine.as_deref(),
        sheet.as_ref(),
        &catalogue,
        a.sample_period_s,
        &crate::shared::calib::now_rfc3339(),
    )
    .context("the nominal calibration")?;
    out.write_all(cal.to_json())?;
    out.commit()?;

    let axes = [
        ("x", &cal.nominal.axes.x),
        ("y", &cal.nominal.axes.y),
        ("z", &cal.nominal.axes.z),
    ];
    if a.json {
        outln!(
            "{}",
            serde_json::json!({
                "out": a.out,
                "machine": cal.machine_id,
                "version": cal.version,
                "tau_s": axes.iter().map(|(n, tf)| (n.to_string(), tau(tf))).collect::<std::collections::BTreeMap<_, _>>(),
                "tau_source": source,
                "sample_period_s": cal.sample_period_s,
                "travel_mm": cal.limits.travel_mm,
                "tips": cal.geometry.tips,
            })
        )?;
        return Ok(());
    }
    print_text(&a, &cal, source, styli, sheet.is_some())
}

/// A first-order transfer function's time constant, s (NaN for any other form).
fn tau(tf: &TransferFunction) -> f64 {
    match tf {
        TransferFunction::FirstOrder { tau_s } => *tau_s,
        _ => f64::NAN,
    }
}

/// The text output: what was written and where each part came from.
fn print_text(
    a: &NominalArgs,
    cal: &Calibration,
    source: TauSource,
    styli: &std::path::Path,
    sheet_given: bool,
) -> Result<()> {
    let axes = [
        ("x", &cal.nominal.axes.x),
        ("y", &cal.nominal.axes.y),
        ("z", &cal.nominal.axes.z),
    ];
    outln!(
        "{}: machine {}, version 1, the nominal model (no effects)",
        a.out.display(),
        cal.machine_id
    )?;
    let taus = axes
        .iter()
        .map(|(n, tf)| format!("{n} {:.2} ms", tau(tf) * 1e3))
        .collect::<Vec<_>>()
        .join(", ");
    match (source, &a.datasheet) {
        (TauSource::DataSheet, Some(d)) => outln!(
            "  time constants as {} states them: {taus} — `scancorr calibrate dynamics` (a ring \
             gauge) or `scancorr lab discover` refits them",
            d.display()
        )?,
        _ => outln!(
            "  time constants {} ms on every axis, to be fitted (no --datasheet) — `scancorr \
             calibrate dynamics` (a ring gauge) or `scancorr lab discover` refits them (each \
             searches a factor of 4 either side)",
            datasheet::DEFAULT_TAU_S * 1e3
        )?,
    }
    let probes = cal
        .nominal
        .probes
        .iter()
        .map(|(n, tf)| format!("{n} {:.2} ms", tau(tf) * 1e3))
        .collect::<Vec<_>>()
        .join(", ");
    let tips = cal
        .geometry
        .tips
        .iter()
        .map(|t| {
            // To 0.1 µm: what a qualification states.
            let mm = |x: f64| (x * 1e4).round() / 1e4;
            let bent = if t.l2_mm > 0.0 {
                format!(" + {} mm at {}°", mm(t.l2_mm), t.beta1_deg)
            } else {
                String::new()
            };
            format!(
                "{} ({}, {} mm{bent}, ball r {} mm)",
                t.id,
                t.probe,
                mm(t.l1_mm),
                mm(t.radius_mm)
            )
        })
        .collect::<Vec<_>>()
        .join("; ");
    outln!(
        "  probes: {probes}; tips as {} {}: {tips}",
        styli.display(),
        if a.catalogue.is_some() {
            "lists them (`scancorr calibrate tips` qualifies them)"
        } else {
            "has them"
        }
    )?;
    let l = cal.limits.travel_mm;
    if sheet_given {
        outln!(
            "  travel x {}…{}, y {}…{}, z {}…{} mm; sample period {} ms",
            l[0][0],
            l[0][1],
            l[1][0],
            l[1][1],
            l[2][0],
            l[2][1],
            cal.sample_period_s * 1e3
        )?;
    } else {
        outln!(
            "  travel not stated (no --datasheet): the default limits, ±{} mm; sample period {} ms",
            l[0][1],
            cal.sample_period_s * 1e3
        )?;
    }
    Ok(())
}
