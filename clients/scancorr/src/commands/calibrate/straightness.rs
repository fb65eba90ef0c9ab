//! `scancorr calibrate straightness`: reads the separation measurement (scales, distance
//! probes, micro-stage) from a bag, prints the separated profiles with their uncertainties,
//! and writes the guide's table as a new calibration version. The logic is
//! `scancorr_core::calibrate::separation`.

use super::args::{helps, PrintArgs};
use crate::shared::calib::{self, now_rfc3339};
use crate::shared::output::outputs;
use anyhow::{Context, Result};
use scancorr_bag::measure::read_separation;
use scancorr_bag::{BagReader, Stream};
use scancorr_core::calibrate::separation::{
    self, CarriageSample, DistanceSample, Method, Raw, Request, StageSample,
};
use scancorr_core::calibrate::straightness::ThreeProbeOptions;
use scancorr_core::lab::version;
use scancorr_core::sample::{Axis, Sample, StreamId};
use scancorr_core::wire;
use std::path::{Path, PathBuf};

/// Arguments of `calibrate straightness`.
#[derive(clap::Args, Debug)]
#[command(mut_args(helps("straightness")))]
pub struct Args {
    /// three-probe, two-probe or shear-stage.
    #[arg(long)]
    pub method: String,
    /// Bag of the measurement (scales, distance probes, and the stage).
    #[arg(long)]
    pub bag: PathBuf,
    /// Bag of the reversal measurement (three probes: the straightedge turned over),
    /// which separates the probes' zero offsets (otherwise a parabola is not seen).
    #[arg(long)]
    pub reversal: Option<PathBuf>,
    /// The calibration to start from (the axis's guide table is replaced).
    #[arg(long)]
    pub calib: PathBuf,
    /// The guide's axis (the carriage's travel).
    #[arg(long, default_value = "x")]
    pub axis: String,
    /// The axis the probes read along (default: y for x, x for y and z).
    #[arg(long)]
    pub toward: Option<String>,
    /// The new calibration version.
    #[arg(long)]
    pub out: PathBuf,
    #[command(flatten)]
    pub print: PrintArgs,
    /// Three probes without a reversal: the straightedge's bow (sag about its chord over
    /// the measured span) is at most this, µm (its certificate or grade): the probes'
    /// offsets' parabola is then estimated by least squares, ± σ, instead of unseen.
    #[arg(long)]
    pub straightedge_bow_um: Option<f64>,
    /// With --straightedge-bow-um: each probe's zero offset after zeroing is within ± this,
    /// µm.
    #[arg(long)]
    pub probe_zero_um: Option<f64>,
}

fn axis(flag: &str, s: &str) -> Result<Axis> {
    match s {
        "x" | "X" => Ok(Axis::X),
        "y" | "Y" => Ok(Axis::Y),
        "z" | "Z" => Ok(Axis::Z),
        _ => anyhow::bail!("{flag} {s}: x, y or z"),
    }
}

/// The raw streams of `machine` in `path`, and the probes' resolution the bag states.
fn read(path: &Path, machine: &str) -> Result<(Raw, f64, Vec<String>)> {
    let bag = BagReader::open(path).with_context(|| format!("opening {}", path.display()))?;
    let sep = read_separation(&bag, machine).with_context(|| format!("{}", path.display()))?;
    let mut warnings = sep.warnings();
    let mut raw = Raw {
        distance: sep
            .distance
            .iter()
            .map(|d| DistanceSample {
                t_ns: d.t_ns,
                probe_id: d.probe_id,
                distance_mm: d.distance_mm,
                spacing_mm: d.spacing_mm,
            })
            .collect(),
        stage: sep
            .stage
            .iter()
            .map(|s| StageSample {
                t_ns: s.t_ns,
                probe_id: s.probe_id,
                commanded_mm: s.commanded_mm,
                sensor_mm: s.sensor_mm,
            })
            .collect(),
        ..Raw::default()
    };
    let mut bad = 0u64;
    for msg in bag.messages()? {
        let msg = msg?;
        if &*msg.machine != machine || msg.stream != Stream::Scale {
            continue;
        }
        // Per-sample and packed (v1.3) batches; one tagged as another stream is refused.
        let decoded = wire::decode_with(StreamId::Scale, &msg.data, |m, s| match s {
            Sample::Scale(s) if m == machine && s.pos.iter().all(|v| v.is_finite()) => {
                raw.carriage.push(CarriageSample {
                    t_ns: s.t_ns,
                    pos: [s.pos.x, s.pos.y, s.pos.z],
                })
            }
            _ => bad += 1,
        });
        if decoded.is_err() {
            bad += 1;
        }
    }
    if bad > 0 {
        warnings.push(format!(
            "{}: {bad} scale sample(s) or message(s) left out (another machine, not finite, or \
             not decodable)",
            path.display()
        ));
    }
    raw.carriage.sort_by_key(|c| c.t_ns);
    let resolution = bag
        .metadata_named(scancorr_bag::RUN_METADATA)
        .and_then(|m| m.get("probe_resolution_mm"))
        .and_then(|v| v.parse::<f64>().ok())
        .filter(|v| v.is_finite() && *v >= 0.0)
        .unwrap_or(0.0);
    Ok((raw, resolution, warnings))
}

/// The root mean square of `v` (0 when empty).
fn rms(v: &[f64]) -> f64 {
    (v.iter().map(|x| x * x).sum::<f64>() / v.len().max(1) as f64).sqrt()
}

/// Straightness as a metrologist states it (ISO 12780): a profile's peak-to-valley about its
/// least-squares line, µm, over the length the profile spans — the figure the report states
/// (`report::straightness_pv_um`, the same function). `None` with fewer than three points.
struct Pv {
    pv_um: Option<f64>,
    from_mm: f64,
    to_mm: f64,
    /// The profile's standard uncertainty, RMS over its points, µm.
    u_rms_um: f64,
}

impl Pv {
    fn of(x: &[f64], v: &[f64], u: &[f64]) -> Pv {
        let xs = x
            .iter()
            .zip(v)
            .filter(|(x, v)| x.is_finite() && v.is_finite());
        let (from_mm, to_mm) = xs.fold((f64::INFINITY, f64::NEG_INFINITY), |a, (x, _)| {
            (a.0.min(*x), a.1.max(*x))
        });
        let pv_um = crate::report::straightness_pv_um(x, v);
        Pv {
            pv_um,
            from_mm: if pv_um.is_some() { from_mm } else { 0.0 },
            to_mm: if pv_um.is_some() { to_mm } else { 0.0 },
            u_rms_um: rms(u) * 1e3,
        }
    }

    fn json(&self) -> serde_json::Value {
        let r = |v: f64| (v * 1e4).round() / 1e4;
        match self.pv_um {
            Some(p) => serde_json::json!({
                "pv_um": r(p),
                "length_mm": r(self.to_mm - self.from_mm),
                "from_mm": r(self.from_mm),
                "to_mm": r(self.to_mm),
                "profile_u_rms_um": r(self.u_rms_um),
            }),
            None => serde_json::json!({ "note": "too few points for a straightness value" }),
        }
    }

    fn text(&self) -> String {
        match self.pv_um {
            Some(p) => format!(
                "{p:.2} µm over {:.0} mm ({:.0}–{:.0} mm; profile σ {:.3} µm RMS)",
                self.to_mm - self.from_mm,
                self.from_mm,
                self.to_mm,
                self.u_rms_um
            ),
            None => "— (too few points)".into(),
        }
    }
}

/// The guide's and the part's straightness ([`Pv`]).
fn straightness_pv(s: &scancorr_core::calibrate::straightness::Separation) -> (Pv, Pv) {
    (
        Pv::of(
            &s.stations_mm,
            &s.guide_straightness_mm,
            &s.guide_straightness_mm_u,
        ),
        Pv::of(
            &s.part_positions_mm,
            &s.part_straightness_mm,
            &s.part_straightness_mm_u,
        ),
    )
}

/// Prints the separated profiles with their uncertainties, the flatness and the parameters.
fn print_text(o: &separation::Outcome, ax: Axis, toward: Axis) -> Result<()> {
    let s = &o.separation;
    outln!(
        "straightness of the {} guide towards {} by {}: {} stations, {} readings averaged per \
         probe and station",
        ax.name(),
        toward.name(),
        s.method,
        s.stations_mm.len(),
        o.samples_per_reading
    )?;
    outln!(
        "  {:>9}  {:>18}  {:>18}",
        "x (mm)",
        "guide (µm)",
        if s.pitch_rad.is_some() {
            "pitch (µrad)"
        } else {
            ""
        }
    )?;
    for (k, x) in s.stations_mm.iter().enumerate() {
        let pitch = match (&s.pitch_rad, &s.pitch_rad_u) {
            (Some(p), Some(u)) => format!("{:+8.3} ± {:.3}", p[k] * 1e6, u[k] * 1e6),
            _ => String::new(),
        };
        outln!(
            "  {:>9.2}  {:+8.3} ± {:<7.3}  {:>18}",
            x,
            s.guide_straightness_mm[k] * 1e3,
            s.guide_straightness_mm_u[k] * 1e3,
            pitch
        )?;
    }
    outln!("  part (straightedge) straightness, µm:")?;
    for (k, x) in s.part_positions_mm.iter().enumerate() {
        outln!(
            "  {:>9.2}  {:+8.3} ± {:.3}",
            x,
            s.part_straightness_mm[k] * 1e3,
            s.part_straightness_mm_u[k] * 1e3
        )?;
    }
    let (g, p) = straightness_pv(s);
    outln!(
        "  straightness, peak-to-valley about the least-squares line (ISO 12780): guide {}, part {}",
        g.text(),
        p.text()
    )?;
    if let Some(f) = o.flatness_mm {
        outln!(
            "  flatness of the surface over {} lines: {:.3} µm peak-to-valley about its \
             least-squares plane",
            o.lines.len(),
            f * 1e3
        )?;
        for l in &o.lines {
            let rmsu = rms(&l.height_mm_u) * 1e3;
            outln!(
                "    line at {:.2} mm: {:+.3} … {:+.3} µm (σ {:.3} µm RMS)",
                l.step_mm,
                l.height_mm.iter().cloned().fold(f64::MAX, f64::min) * 1e3,
                l.height_mm.iter().cloned().fold(f64::MIN, f64::max) * 1e3,
                rmsu
            )?;
        }
    }
    outln!(
        "  cannot see: {} (straightness is the deviation from each profile's least-squares \
         line; the pitch about its mean)",
        s.cannot_see.join(", ")
    )?;
    for p in &s.params {
        outln!("  {}: {:.6} ± {:.6}", p.name, p.value, p.sigma)?;
    }
    Ok(())
}

/// Runs the procedure.
pub fn run(a: Args) -> Result<()> {
    let method: Method = a.method.parse().map_err(anyhow::Error::msg)?;
    let ax = axis("--axis", &a.axis)?;
    let toward = match &a.toward {
        Some(t) => axis("--toward", t)?,
        None => match ax {
            Axis::X => Axis::Y,
            _ => Axis::X,
        },
    };
    let mut inputs = vec![("--calib", a.calib.as_path()), ("--bag", a.bag.as_path())];
    if let Some(r) = &a.reversal {
        inputs.push(("--reversal", r.as_path()));
    }
    let [out_file, report_file] = outputs(
        [
            ("--out", Some(a.out.as_path())),
            ("--report", a.print.report.as_deref()),
        ],
        &inputs,
    )?;
    let start = calib::load_calibration(&a.calib)?;
    let (raw, resolution, mut warnings) = read(&a.bag, &start.machine_id)?;
    let rev = match &a.reversal {
        Some(p) => {
            let (r, _, w) = read(p, &start.machine_id)?;
            warnings.extend(w);
            Some(r)
        }
        None => None,
    };
    let o = separation::run(
        &Request {
            method,
            axis: ax,
            toward,
            raw: &raw,
            reversal: rev.as_ref(),
            probe_resolution_mm: resolution,
            three_probe: ThreeProbeOptions {
                straightedge_bow_mm: a.straightedge_bow_um.map(|v| v * 1e-3),
                probe_zero_mm: a.probe_zero_um.map(|v| v * 1e-3),
            },
        },
        &start,
    )?;
    warnings.extend(o.warnings.iter().cloned());
    let s = &o.separation;
    let mut new = version::next(&start, o.calibration.effects.clone(), &now_rfc3339());
    let (pv_g, pv_p) = straightness_pv(s);
    new.note = format!(
        "calibrate straightness: {}, {} stations along {} ({:.0}–{:.0} mm), straightness \
         towards {}{}; guide {} peak-to-valley, {:.3} µm RMS (± {:.3} µm), part {} \
         peak-to-valley, {:.3} µm RMS; cannot see: {}",
        s.method,
        s.stations_mm.len(),
        ax.name(),
        s.stations_mm.first().copied().unwrap_or(0.0),
        s.stations_mm.last().copied().unwrap_or(0.0),
        toward.name(),
        if s.pitch_rad.is_some() {
            " and pitch"
        } else {
            ""
        },
        pv_g.text(),
        rms(&s.guide_straightness_mm) * 1e3,
        rms(&s.guide_straightness_mm_u) * 1e3,
        pv_p.text(),
        rms(&s.part_straightness_mm) * 1e3,
        s.cannot_see.join(", ")
    );
    crate::shared::calib::commit_version(
        &mut new,
        vec![
            (
                "guide_straightness_rms_um",
                rms(&s.guide_straightness_mm) * 1e3,
            ),
            (
                "guide_straightness_u_rms_um",
                rms(&s.guide_straightness_mm_u) * 1e3,
            ),
            (
                "part_straightness_rms_um",
                rms(&s.part_straightness_mm) * 1e3,
            ),
        ]
        .into_iter()
        .chain(pv_g.pv_um.map(|v| ("guide_straightness_pv_um", v)))
        .chain(pv_p.pv_um.map(|v| ("part_straightness_pv_um", v)))
        .collect(),
        out_file,
        report_file,
        || crate::report::straightness(&start, &o, &warnings),
    )?;
    for w in &warnings {
        eprintln!("warning: {w}");
    }
    if a.print.json {
        let mut v = serde_json::to_value(&o)?;
        v["warnings"] = serde_json::to_value(&warnings)?;
        // The straightness a metrologist states, as the report states it.
        v["straightness"] = serde_json::json!({
            "definition": "peak-to-valley about the least-squares line (ISO 12780)",
            "guide": pv_g.json(),
            "part": pv_p.json(),
        });
        v["version"] = new.version.into();
        v["parent_version"] = start.version.into();
        v["out"] = a.out.display().to_string().into();
        outln!("{}", serde_json::to_string_pretty(&v)?)?;
        return Ok(());
    }
    print_text(&o, ax, toward)?;
    crate::shared::calib::closing(&s.notes, &a.out, &new, &start)
}
