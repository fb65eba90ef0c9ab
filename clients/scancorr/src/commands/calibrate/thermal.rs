//! `scancorr calibrate thermal-drift`: a drift recording (a table of time, measured
//! displacements, structure temperatures and optionally the spindle speed) in, the drift
//! model per channel out — the loop from the nominal model, where it fails, each group added
//! with its cross-validated and held-out error, every coefficient ± σ. The logic is
//! `scancorr_core::calibrate::thermal_drift`.

use super::args::{helps, PrintArgs};
use crate::report::thermal::{term_name, term_unit};
use crate::shared::output::{outputs, put};
use anyhow::{bail, Context, Result};
use clap::Args as ClapArgs;
use scancorr_bag::import::{self, Columns};
use scancorr_core::calibrate::thermal_drift::{
    self, Channel, Options, Recording, Source, SourceKind, ThermalFit,
};
use scancorr_core::effects::thermal_drift as thermal_drift_effect;
use scancorr_core::effects::EffectConfig;
use scancorr_core::lab::version;
use std::path::PathBuf;

/// Arguments of `calibrate thermal-drift`.
#[derive(ClapArgs, Debug)]
#[command(mut_args(helps("thermal-drift")))]
pub struct Args {
    /// The recording: a table with a header row (comma, semicolon, tab or whitespace
    /// separated), one row per instant.
    #[arg(long, required_unless_present = "bag", conflicts_with = "bag")]
    pub csv: Option<PathBuf>,
    /// The recording as a bag (`scancorr import`): the temperature stream's sensors and the
    /// distance probes as channels (`probe1`, `probe2`, … in mm), one row per reading of the
    /// lowest probe; no heat source (the wire contract has no spindle-speed stream).
    #[arg(long)]
    pub bag: Option<PathBuf>,
    /// The machine in the bag (default: its only one).
    #[arg(long, requires = "bag")]
    pub machine: Option<String>,
    /// The time column.
    #[arg(long, default_value = "time_s")]
    pub time: String,
    /// The time column's unit: s, ms, min or h.
    #[arg(long, default_value = "s")]
    pub time_unit: String,
    /// Measured displacement columns (names, or patterns with `*`: `ch*_um`; from a bag
    /// `probe*`).
    #[arg(long, required = true, num_args = 1..)]
    pub channel: Vec<String>,
    /// The displacement columns' unit: um, mm or m.
    #[arg(long, default_value = "um")]
    pub channel_unit: String,
    /// Temperature columns, °C (names, or patterns with `*`: `t*_c`).
    #[arg(long, required = true, num_args = 1..)]
    pub sensor: Vec<String>,
    /// Heat-source columns (the spindle speed), in their own unit.
    #[arg(long, num_args = 1..)]
    pub heat: Vec<String>,
    /// The first held-out row (0-based data row): rows before it fit, rows from it are only
    /// reported.
    #[arg(long, conflicts_with = "heldout_from_s")]
    pub heldout_from_row: Option<usize>,
    /// The first held-out time (in the time column's unit).
    #[arg(long)]
    pub heldout_from_s: Option<f64>,
    /// Lags of the basis, s.
    #[arg(long, value_delimiter = ',', default_values_t = vec![0.0, 600.0, 2400.0, 9600.0])]
    pub taus: Vec<f64>,
    /// The calibration to add the drift to (its `thermal_drift` effect is replaced); with
    /// `--out` and `--axis`.
    #[arg(long, requires_all = ["out", "axis"])]
    pub calib: Option<PathBuf>,
    /// The new calibration version.
    #[arg(long, requires = "calib")]
    pub out: Option<PathBuf>,
    /// Which machine axis a channel measures, `CHANNEL=x|y|z` (repeat): the channel's compact
    /// model (the temperature terms the corrector holds) goes into the calibration along it.
    #[arg(long, requires = "calib")]
    pub axis: Vec<String>,
    #[command(flatten)]
    pub print: PrintArgs,
}

/// The named columns of the table at `path`: every cell a finite number, or an error naming
/// each bad cell's line and column.
fn read_table(path: &std::path::Path, wanted: &[String]) -> Result<Columns> {
    let file = path.display().to_string();
    let open = || -> Result<std::io::BufReader<std::fs::File>> {
        Ok(std::io::BufReader::new(
            std::fs::File::open(path).with_context(|| format!("reading {file}"))?,
        ))
    };
    let opts = import::Options::default();
    if wanted.is_empty() {
        let header = import::header(open()?, &file, &opts)?;
        return Ok(Columns {
            header,
            lines: vec![],
            values: vec![],
        });
    }
    Ok(import::read_columns(open()?, &file, wanted, &opts)?)
}

/// The recording from a table: the time, channel, sensor and heat columns the flags name.
fn from_csv(a: &Args, csv: &std::path::Path, time_scale: f64, to_mm: f64) -> Result<Recording> {
    // The header first, to expand the patterns.
    let probe = read_table(csv, &[])?;
    let channels = expand("--channel", &a.channel, &probe.header)?;
    let sensors = expand("--sensor", &a.sensor, &probe.header)?;
    let heat = expand("--heat", &a.heat, &probe.header)?;
    for (flag, names) in [("--sensor", &sensors), ("--heat", &heat)] {
        if let Some(c) = names.iter().find(|n| channels.contains(n) || **n == a.time) {
            bail!("{flag}: column `{c}` is also the time or a channel");
        }
    }
    let mut wanted = vec![a.time.clone()];
    wanted.extend(channels.iter().cloned());
    wanted.extend(sensors.iter().cloned());
    wanted.extend(heat.iter().cloned());
    let t = read_table(csv, &wanted)?;
    let mut cols = t.values.into_iter();
    let t_s: Vec<f64> = cols
        .next()
        .unwrap_or_default()
        .iter()
        .map(|v| v * time_scale)
        .collect();
    let rec = Recording {
        t_s: t_s.clone(),
        channels: channels
            .iter()
            .map(|n| Channel {
                name: n.clone(),
                mm: cols
                    .next()
                    .unwrap_or_default()
                    .iter()
                    .map(|v| v * to_mm)
                    .collect(),
            })
            .collect(),
        sources: sensors
            .iter()
            .map(|n| (n, SourceKind::Temperature))
            .chain(heat.iter().map(|n| (n, SourceKind::HeatSource)))
            .map(|(n, kind)| Source {
                name: n.clone(),
                kind,
                values: cols.next().unwrap_or_default(),
            })
            .collect(),
    };
    Ok(rec)
}

/// The recording from a bag: every temperature sensor and distance probe of the machine, one
/// row per reading of the lowest probe (the other probes read at the same instants; each
/// sensor's last reading at or before it; rows before every sensor has read are left out and
/// counted).
fn from_bag(a: &Args, path: &std::path::Path) -> Result<Recording> {
    use scancorr_core::sample::{Sample, StreamId};
    use std::collections::BTreeMap;
    let bag = scancorr_bag::BagReader::open(path)
        .with_context(|| format!("opening {}", path.display()))?;
    let machine = match &a.machine {
        Some(m) => m.clone(),
        None => match bag.machines().as_slice() {
            [m] => m.to_string(),
            ms => bail!(
                "{}: {} machines ({}): name one with --machine",
                path.display(),
                ms.len(),
                ms.join(", ")
            ),
        },
    };
    let sep = scancorr_bag::measure::read_separation(&bag, &machine)
        .with_context(|| format!("{}", path.display()))?;
    for w in sep.warnings() {
        eprintln!("warning: {w}");
    }
    let mut temps: BTreeMap<String, Vec<(i64, f64)>> = BTreeMap::new();
    let mut bad = 0u64;
    for msg in bag.messages()? {
        let msg = msg?;
        if &*msg.machine != machine || msg.stream != scancorr_bag::Stream::Temperature {
            continue;
        }
        let r =
            scancorr_core::wire::decode_with(StreamId::Temperature, &msg.data, |m, s| match s {
                Sample::Temperature(t) if m == machine && t.celsius.is_finite() => {
                    temps.entry(t.sensor).or_default().push((t.t_ns, t.celsius))
                }
                _ => bad += 1,
            });
        if r.is_err() {
            bad += 1;
        }
    }
    if bad > 0 {
        eprintln!(
            "warning: {}: {bad} temperature sample(s) or message(s) left out (another machine, not finite, or not decodable)",
            path.display()
        );
    }
    let mut probes: BTreeMap<u32, Vec<(i64, f64)>> = BTreeMap::new();
    for d in &sep.distance {
        probes
            .entry(d.probe_id)
            .or_default()
            .push((d.t_ns, d.distance_mm));
    }
    let names: Vec<String> = probes.keys().map(|p| format!("probe{p}")).collect();
    let channels = expand("--channel", &a.channel, &names)?;
    let sensor_names: Vec<String> = temps.keys().cloned().collect();
    let sensors = expand("--sensor", &a.sensor, &sensor_names)?;
    if !a.heat.is_empty() {
        bail!("--heat: a bag has no heat-source stream (the wire contract carries no spindle speed); use --csv");
    }
    let (&first, base) = probes.iter().next().context("no distance probe")?;
    let mut skipped = 0usize;
    let mut t_s = vec![];
    let mut ch_vals: Vec<Vec<f64>> = vec![vec![]; channels.len()];
    let mut src_vals: Vec<Vec<f64>> = vec![vec![]; sensors.len()];
    for (i, &(t, _)) in base.iter().enumerate() {
        let held: Option<Vec<f64>> = sensors
            .iter()
            .map(|s| {
                let v = &temps[s];
                let k = v.partition_point(|&(ts, _)| ts <= t);
                (k > 0).then(|| v[k - 1].1)
            })
            .collect();
        let Some(held) = held else {
            skipped += 1;
            continue;
        };
        for (c, name) in channels.iter().enumerate() {
            let id: u32 = name["probe".len()..].parse().unwrap_or(first);
            let v = &probes[&id];
            let k = v.partition_point(|&(ts, _)| ts < t);
            match v.get(k) {
                Some(&(ts, x)) if ts == t => ch_vals[c].push(x),
                _ => bail!(
                    "{}: {name} has no reading at t_ns {t} (probe{first}'s reading {i}): the channels must be read together",
                    path.display()
                ),
            }
        }
        for (k, v) in held.into_iter().enumerate() {
            src_vals[k].push(v);
        }
        t_s.push(t as f64 * 1e-9);
    }
    if skipped > 0 {
        eprintln!(
            "warning: {}: the first {skipped} reading(s) of probe{first} left out: not every sensor had read yet",
            path.display()
        );
    }
    Ok(Recording {
        t_s,
        channels: channels
            .into_iter()
            .zip(ch_vals)
            .map(|(name, mm)| Channel { name, mm })
            .collect(),
        sources: sensors
            .into_iter()
            .zip(src_vals)
            .map(|(name, values)| Source {
                name,
                kind: SourceKind::Temperature,
                values,
            })
            .collect(),
    })
}

/// The header's columns a list of names or `*` patterns names, in the header's order.
fn expand(flag: &str, pats: &[String], header: &[String]) -> Result<Vec<String>> {
    let mut out: Vec<String> = vec![];
    for p in pats {
        let hits: Vec<&String> = header.iter().filter(|h| glob(p, h)).collect();
        if hits.is_empty() {
            bail!(
                "{flag} {p}: no column matches (the header has {})",
                header.join(", ")
            );
        }
        for h in hits {
            if !out.contains(h) {
                out.push(h.clone());
            }
        }
    }
    Ok(out)
}

fn glob(p: &str, s: &str) -> bool {
    match p.split_once('*') {
        None => p == s,
        Some((a, rest)) => {
            s.starts_with(a)
                && (0..=s.len() - a.len())
                    .any(|i| s.is_char_boundary(a.len() + i) && glob(rest, &s[a.len() + i..]))
        }
    }
}

/// The time column's scale to seconds and the displacement columns' to mm.
fn units(a: &Args) -> Result<(f64, f64)> {
    let time_scale = match a.time_unit.as_str() {
        "s" => 1.0,
        "ms" => 1e-3,
        "min" => 60.0,
        "h" => 3600.0,
        u => bail!("--time-unit {u}: s, ms, min or h"),
    };
    let to_mm = match a.channel_unit.as_str() {
        "um" | "µm" => 1e-3,
        "mm" => 1.0,
        "m" => 1e3,
        u => bail!("--channel-unit {u}: um, mm or m"),
    };
    Ok((time_scale, to_mm))
}

/// The compact models the corrector holds, per mapped channel (`--axis`): each with its axis
/// (0, 1, 2 for x, y, z) and its channel's index.
fn compact_models(
    a: &Args,
    rec: &Recording,
    opt: &Options,
    channels: &[String],
    input: &std::path::Path,
) -> Result<Vec<(thermal_drift::Compact, usize, usize)>> {
    let mut compacts = vec![];
    for m in &a.axis {
        let (ch, ax) = m
            .split_once('=')
            .with_context(|| format!("--axis {m}: CHANNEL=x|y|z"))?;
        let axis = match ax {
            "x" | "X" => 0,
            "y" | "Y" => 1,
            "z" | "Z" => 2,
            _ => bail!("--axis {m}: the axis is x, y or z"),
        };
        let i = channels.iter().position(|c| c == ch).with_context(|| {
            format!(
                "--axis {m}: `{ch}` is not one of the channels ({})",
                channels.join(", ")
            )
        })?;
        if compacts.iter().any(|(_, x, _)| *x == axis) {
            bail!("--axis {m}: two channels along {ax}");
        }
        let per = thermal_drift_effect::MAX_TERMS / a.axis.len().max(1);
        let c = thermal_drift::compact(rec, opt, i, per)
            .with_context(|| format!("{}", input.display()))?;
        compacts.push((c, axis, i));
    }
    Ok(compacts)
}

/// Prints each compact model: its terms, its lags and its held-out error against the full
/// model's.
fn print_compacts(
    compacts: &[(thermal_drift::Compact, usize, usize)],
    fit: &ThermalFit,
) -> Result<()> {
    for (c, x, i) in compacts {
        let full = &fit.channels[*i];
        outln!(
            "{} along {} into the calibration: {} temperature terms (the corrector holds at most {}), held-out MAE {:.3} µm (the full model {:.3} µm)",
            c.channel,
            ["x", "y", "z"][*x],
            c.terms.len(),
            thermal_drift_effect::MAX_TERMS,
            c.heldout.mae_um,
            full.heldout.mae_um
        )?;
        for t in &c.terms {
            outln!(
                "    {:<26} k = {:>20}   τ = {}",
                t.source,
                format!("{} µm/K", crate::report::value_sigma(t.k, Some(t.sigma))),
                match t.tau_sigma_s {
                    Some(u) if u.is_finite() =>
                        format!("{} s", crate::report::value_sigma(t.tau_s, Some(u))),
                    Some(_) => format!("{:.0} s (its σ cannot be determined)", t.tau_s),
                    None => format!("{:.0} s", t.tau_s),
                }
            )?;
        }
        outln!(
            "    lags {} (residual lag-1 correlation {:.3}: σ inflated for it)",
            if c.refined {
                "refined off the basis: they lowered the cross-validated error"
            } else {
                "kept at the basis: refining them did not lower the cross-validated error"
            },
            c.residual_rho
        )?;
        if full.terms.iter().any(|t| t.kind == SourceKind::HeatSource) {
            outln!(
                "  note: the heat-source terms are not in the calibration: the wire contract has no spindle-speed stream yet"
            )?;
        }
    }
    Ok(())
}

/// Runs the procedure.
pub fn run(a: Args) -> Result<()> {
    let mut inputs = vec![];
    if let Some(c) = &a.csv {
        inputs.push(("--csv", c.as_path()));
    }
    if let Some(b) = &a.bag {
        inputs.push(("--bag", b.as_path()));
    }
    if let Some(c) = &a.calib {
        inputs.push(("--calib", c.as_path()));
    }
    let [out_file, report_file] = outputs(
        [
            ("--out", a.out.as_deref()),
            ("--report", a.print.report.as_deref()),
        ],
        &inputs,
    )?;
    let start = a
        .calib
        .as_deref()
        .map(crate::shared::calib::load_calibration)
        .transpose()?;
    let (time_scale, to_mm) = units(&a)?;
    let (rec, input) = match (&a.csv, &a.bag) {
        (Some(csv), _) => (from_csv(&a, csv, time_scale, to_mm)?, csv),
        (None, Some(bag)) => (from_bag(&a, bag)?, bag),
        (None, None) => bail!("--csv or --bag: the recording"),
    };
    let rows = rec.t_s.len();
    let t_s = rec.t_s.clone();
    let channels: Vec<String> = rec.channels.iter().map(|c| c.name.clone()).collect();
    let heldout_from = match (a.heldout_from_row, a.heldout_from_s) {
        (Some(r), _) => r,
        (None, Some(s)) => t_s.iter().position(|&x| x >= s * time_scale).unwrap_or(rows),
        (None, None) => bail!("say where the held-out period starts: --heldout-from-row N or --heldout-from-s T (nothing is ever reported on the rows it was fitted on)"),
    };
    if heldout_from == 0 || heldout_from >= rows {
        bail!(
            "the held-out period must leave rows to fit and rows to judge: row {heldout_from} of {}",
            rows
        );
    }
    let opt = Options {
        heldout_from,
        taus_s: a.taus.clone(),
        ..Options::default()
    };
    let fit = thermal_drift::fit(&rec, &opt).with_context(|| format!("{}", input.display()))?;
    // The compact models the corrector holds, per mapped channel.
    let compacts = compact_models(&a, &rec, &opt, &channels, input)?;
    let mut new = None;
    if let Some(start) = &start {
        let models: Vec<_> = compacts.iter().map(|(c, x, _)| (c, *x)).collect();
        let cfg = thermal_drift::effect(&models)?;
        let mut effects: Vec<EffectConfig> = start
            .effects
            .iter()
            .filter(|e| e.kind() != "thermal_drift")
            .cloned()
            .collect();
        effects.push(EffectConfig::ThermalDrift(cfg));
        let mut v = version::next(start, effects, &crate::shared::calib::now_rfc3339());
        v.note = format!(
            "calibrate thermal-drift: {} ({} rows, fit on rows before {}); {}",
            input.display(),
            rows,
            heldout_from,
            compacts
                .iter()
                .map(|(c, x, _)| format!(
                    "{} along {}: {} terms, held-out MAE {:.3} µm",
                    c.channel,
                    ["x", "y", "z"][*x],
                    c.terms.len(),
                    c.heldout.mae_um
                ))
                .collect::<Vec<_>>()
                .join("; ")
        );
        let metrics: Vec<(String, f64)> = compacts
            .iter()
            .map(|(c, x, _)| {
                (
                    format!("thermal_drift_{}_heldout_mae_um", ["x", "y", "z"][*x]),
                    c.heldout.mae_um,
                )
            })
            .collect();
        crate::shared::calib::commit_version(
            &mut v,
            metrics.iter().map(|(k, x)| (k.as_str(), *x)).collect(),
            out_file,
            report_file,
            || crate::report::thermal_drift(&rec, &fit),
        )?;
        new = Some(v);
    } else if report_file.is_some() {
        put(&report_file, crate::report::thermal_drift(&rec, &fit))?;
        crate::shared::output::commit_all([report_file])?;
    }
    if a.print.json {
        let mut v = serde_json::to_value(&fit)?;
        // Per-row series are for the report, not the summary.
        if let Some(chs) = v["channels"].as_array_mut() {
            for c in chs {
                if let Some(o) = c.as_object_mut() {
                    o.remove("prediction_um");
                    o.remove("measured_um");
                }
            }
        }
        v["rows"] = rows.into();
        v["compact"] =
            serde_json::to_value(compacts.iter().map(|(c, _, _)| c).collect::<Vec<_>>())?;
        if let (Some(n), Some(o)) = (&new, &a.out) {
            v["version"] = n.version.into();
            v["out"] = o.display().to_string().into();
        }
        outln!("{}", serde_json::to_string_pretty(&v)?)?;
        return Ok(());
    }
    print_text(&rec, &fit)?;
    print_compacts(&compacts, &fit)?;
    if let (Some(n), Some(o), Some(s)) = (&new, &a.out, &start) {
        crate::shared::calib::closing(&[], o, n, s)?;
    }
    Ok(())
}

fn print_text(rec: &Recording, f: &ThermalFit) -> Result<()> {
    let n = rec.t_s.len();
    let dt = (rec.t_s[n - 1] - rec.t_s[0]) / (n - 1).max(1) as f64;
    outln!(
        "thermal drift: {n} rows (every {dt:.3} s, {:.1} h); fit on rows 0–{} ({:.1} h), held out rows {}–{} ({:.1} h, reported only)",
        (rec.t_s[n - 1] - rec.t_s[0]) / 3600.0,
        f.fit_rows - 1,
        (rec.t_s[f.fit_rows - 1] - rec.t_s[0]) / 3600.0,
        f.fit_rows,
        n - 1,
        (rec.t_s[n - 1] - rec.t_s[f.fit_rows]) / 3600.0
    )?;
    outln!(
        "  lag basis {:?} s; cross-validation forward-chaining over blocks of time of the fit rows",
        f.taus_s
    )?;
    for c in &f.confounded {
        outln!(
            "  confounded: {} carries what {} does (r = {:.4}); only {} is fitted",
            c.dropped,
            c.kept,
            c.r,
            c.kept
        )?;
    }
    for u in &f.undetermined {
        outln!("  cannot determine: {u}")?;
    }
    for c in &f.channels {
        outln!("{}:", c.channel)?;
        if let Some(w) = c.follows.first() {
            outln!(
                "  where the nominal model fails: the drift follows {} through a lag of {} s (r = {:.2}){}",
                w.source,
                w.tau_s,
                w.r,
                c.follows
                    .get(1)
                    .map(|x| format!(", then {} ({} s, r = {:.2})", x.source, x.tau_s, x.r))
                    .unwrap_or_default()
            )?;
        }
        for (i, s) in c.steps.iter().enumerate() {
            outln!(
                "  step {i}  {:<46} CV MAE {:>7.3} µm   held-out MAE {:>7.3} µm (RMS {:.3}, max {:.2})",
                if i == 0 { s.added.clone() } else { format!("add {}", s.added) },
                s.cv_mae_um,
                s.heldout.mae_um,
                s.heldout.rms_um,
                s.heldout.max_um
            )?;
        }
        outln!(
            "  final: held-out MAE {:.3} µm (nominal {:.3}), fit MAE {:.3} µm, ridge λ {:.1e}, residual lag-1 correlation {:.3} (σ inflated for it)",
            c.heldout.mae_um,
            c.nominal_heldout.mae_um,
            c.fit.mae_um,
            c.lambda,
            c.residual_rho
        )?;
        for t in c.terms.iter().take(6) {
            outln!(
                "    {:<26} k = {:>22}   contributes {:.2} µm",
                term_name(t),
                format!(
                    "{} {}",
                    crate::report::value_sigma(t.k, Some(t.sigma)),
                    term_unit(t)
                ),
                t.contribution_um
            )?;
        }
        if c.terms.len() > 6 {
            outln!("    … {} more terms (--json)", c.terms.len() - 6)?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::glob;

    #[test]
    fn patterns() {
        assert!(glob("ch*_um", "ch1_um"));
        assert!(glob("t*_c", "t16_c"));
        assert!(!glob("t*_c", "time_s"));
        assert!(glob("*", "x"));
        assert!(glob("a*b*c", "aXbYc"));
        assert!(!glob("a*b*c", "aXbY"));
    }
}
