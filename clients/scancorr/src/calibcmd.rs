//! `scancorr calibrate …`: the measuring procedures' I/O — reading the bags and the starting
//! calibration, printing every parameter with its uncertainty, writing the new version. The
//! logic is `scancorr_core::calibrate`.

use crate::labcmd::{load_bags, now_rfc3339, outputs, put, SENSORS};
use crate::offline;
use crate::output::commit_all;
use crate::output::AtomicOutput;
use anyhow::{Context, Result};
use clap::Subcommand;
use scancorr_core::calib::Calibration;
use scancorr_core::calibrate::{dynamic_map, dynamics, probe_force, tips, Param};
use scancorr_core::lab::analysis;
use scancorr_core::lab::dataset::BagData;
use scancorr_core::lab::dataset::{self, BuildOptions};
use scancorr_core::lab::version;
use std::path::Path;
use std::path::PathBuf;

#[derive(Subcommand)]
pub enum CalibrateCmd {
    /// Thermal drift from a recording of hours (ISO 230-3): the measured displacement of the
    /// tool or probe against the part with the structure's temperatures (and the spindle
    /// speed), fitted on the first part and judged on a later held-out period; the drift
    /// from the temperatures through their heat paths' lags, each coefficient ± σ.
    ThermalDrift(crate::thermalcmd::Args),
    /// Qualify the styli on a master sphere: the offset of each tip and head angle from the
    /// reference tip gives the stylus lengths, the sphere's apparent size each tip's effective
    /// radius, the drift with temperature each stylus's expansion coefficient.
    Tips {
        /// Bags of the qualification (the master sphere measured by every tip).
        #[arg(long, required = true)]
        bag: Vec<PathBuf>,
        /// The calibration to start from (catalogue styli or an earlier qualification).
        #[arg(long)]
        calib: PathBuf,
        /// The new calibration version.
        #[arg(long)]
        out: PathBuf,
        /// The reference tip (default: the lowest tip id measured at head angles 0, 0).
        #[arg(long)]
        reference_tip: Option<u32>,
        /// Print JSON (`params` and `uncertainty` by the simulator's truth names, `settings`, …).
        #[arg(long)]
        json: bool,
        /// Write an HTML report: each setting against the reference before and after, the
        /// reference's drift in time, every parameter.
        #[arg(long)]
        report: Option<PathBuf>,
    },
    /// Extrapolation to zero probing force: the same circles on the master sphere scanned
    /// at two or more deflections by each tip give that tip's force coefficients (stylus
    /// bending per mm of deflection along each probe axis).
    ProbeForce {
        /// Bags of the measurement (each tip on the sphere at ≥ 2 deflections).
        #[arg(long, required = true)]
        bag: Vec<PathBuf>,
        /// The calibration to start from (its probe_force effect is replaced).
        #[arg(long)]
        calib: PathBuf,
        /// The new calibration version.
        #[arg(long)]
        out: PathBuf,
        /// Print JSON (`params` and `uncertainty` by the simulator's truth names, `settings`, …).
        #[arg(long)]
        json: bool,
        /// Write an HTML report: each setting's radius against deflection before and after,
        /// every parameter.
        #[arg(long)]
        report: Option<PathBuf>,
    },
    /// The S1/F1/F2 joint method: a circle scanned slowly at deflection d1 (S1) and fast at
    /// d2 (F1) and at d1 (F2), in one direction, gives a per-point map of the fast scan's error
    /// (extrapolated to zero deflection against the slow scan) for that feature and speed; the
    /// map corrects later fast scans of like parts by the same part program (same segment ids).
    DynamicMap {
        /// Bags of the measurement (S1, F1 and F2 of one circle).
        #[arg(long, required = true)]
        bag: Vec<PathBuf>,
        /// The calibration to start from (its maps of these scans are replaced).
        #[arg(long)]
        calib: PathBuf,
        /// The new calibration version.
        #[arg(long)]
        out: PathBuf,
        /// Angle bins (the map's knots) around the circle.
        #[arg(long, default_value_t = 72)]
        bins: usize,
        /// Speed search: the slow/fast difference (RMS over the bins of F2 − S1, µm) a speed
        /// may show without a map; speeds are taken rising, maps stored only where it is left.
        #[arg(long)]
        tolerance_um: Option<f64>,
        /// Print JSON (`params` and `uncertainty`, `maps` with every bin's S1, F1, F2, HSZD,
        /// LSZD, e1, e2 and their σ in µm).
        #[arg(long)]
        json: bool,
        /// Write an HTML report: the scans, the extrapolations to zero deflection and e2 per
        /// map.
        #[arg(long)]
        report: Option<PathBuf>,
    },
    /// The ring-gauge procedure: one ring at ≥ 5 positions along X (and along Y and Z), each
    /// at several speeds in both directions, gives the nominal time constants, the deflection
    /// matrix P(x, y, z) with cross-coupling, the servo phase with position-dependent
    /// coefficients and the servo gain in the form held-out rings prefer.
    Dynamics {
        /// Bags of the ring measurement.
        #[arg(long, required = true)]
        bag: Vec<PathBuf>,
        /// The calibration to start from (its dynamic effects are replaced).
        #[arg(long)]
        calib: PathBuf,
        /// The new calibration version.
        #[arg(long)]
        out: PathBuf,
        /// Print JSON (`params` and `uncertainty` by the simulator's truth names, `positions`, …).
        #[arg(long)]
        json: bool,
        /// Write an HTML report: ΔR against acceleration per position before and after, the
        /// fitted compliance along each line of positions, every parameter.
        #[arg(long)]
        report: Option<PathBuf>,
    },
    /// Error separation of a guide's straightness from a straightedge's, without a perfect
    /// reference: distance probes on the carriage stepped along the travel (three probes
    /// with pitch, two probes, or one probe on a shear micro-stage). Writes the axis's
    /// guide_straightness (and pitch) table with its uncertainties.
    Straightness {
        /// three-probe, two-probe or shear-stage.
        #[arg(long)]
        method: String,
        /// Bag of the measurement (scales, distance probes, and the stage).
        #[arg(long)]
        bag: PathBuf,
        /// Bag of the reversal measurement (three probes: the straightedge turned over),
        /// which separates the probes' zero offsets (otherwise a parabola is not seen).
        #[arg(long)]
        reversal: Option<PathBuf>,
        /// The calibration to start from (the axis's guide table is replaced).
        #[arg(long)]
        calib: PathBuf,
        /// The guide's axis (the carriage's travel).
        #[arg(long, default_value = "x")]
        axis: String,
        /// The axis the probes read along (default: y for x, x for y and z).
        #[arg(long)]
        toward: Option<String>,
        /// The new calibration version.
        #[arg(long)]
        out: PathBuf,
        /// Print JSON: per station `stations_mm`, `guide_straightness_mm`,
        /// `part_straightness_mm`, `pitch_rad`, each with `…_u`, and `cannot_see`.
        #[arg(long)]
        json: bool,
        /// Write an HTML report: guide and part profiles with uncertainty bands, the pitch.
        #[arg(long)]
        report: Option<PathBuf>,
    },
    /// A plate's features (holes) measured against nominal: the similarity (offset,
    /// rotation, scale), the anisotropic scale/shear (quadrupole; scale per axis and
    /// squareness), higher-order terms chosen by cross-validation over holes, each ± σ, and
    /// the original plug-plate tool's fit. Reports only.
    Plate(crate::platecmd::PlateArgs),
}

fn sigma_json(ps: &[Param]) -> (serde_json::Value, serde_json::Value) {
    let params: serde_json::Map<String, serde_json::Value> = ps
        .iter()
        .map(|p| (p.name.clone(), p.value.into()))
        .collect();
    let sigma: serde_json::Map<String, serde_json::Value> = ps
        .iter()
        .map(|p| (p.name.clone(), p.sigma.into()))
        .collect();
    (params.into(), sigma.into())
}

/// What every procedure opens: its outputs (checked against its inputs before anything is
/// read), the starting calibration and the bags.
struct Opened {
    out_file: Option<AtomicOutput>,
    report_file: Option<AtomicOutput>,
    start: Calibration,
    bags: Vec<BagData>,
}

fn open(bag: &[PathBuf], calib: &Path, out: &Path, report: Option<&Path>) -> Result<Opened> {
    let mut inputs = vec![("--calib", calib)];
    inputs.extend(bag.iter().map(|b| ("--bag", b.as_path())));
    let [out_file, report_file] = outputs([("--out", Some(out)), ("--report", report)], &inputs)?;
    let start = offline::load_calibration(calib)?;
    crate::output::stage(&format!("reading {} bag(s) …", bag.len()));
    let bags = load_bags(bag, &[], &start.machine_id)?;
    crate::output::stage("bags read; measuring …");
    Ok(Opened {
        out_file,
        report_file,
        start,
        bags,
    })
}

/// The points of `bags` corrected with `cal` less the effects of `kinds` (what the procedure
/// measures), every `stride`-th point; warnings to stderr.
fn points_without(
    bags: &[BagData],
    cal: &Calibration,
    kinds: &[&str],
    stride: usize,
) -> Result<dataset::Dataset> {
    let mut bare = cal.clone();
    bare.effects.retain(|e| !kinds.contains(&e.kind()));
    crate::output::stage("correcting the scans …");
    let ds = dataset::build(bags, &bare, &options(stride))?;
    crate::output::stage(&format!("{} points; fitting …", ds.points.len()));
    for w in &ds.warnings {
        eprintln!("warning: {w}");
    }
    Ok(ds)
}

fn options(stride: usize) -> BuildOptions {
    BuildOptions {
        stride,
        holdout_by_segment: false,
        artifact: None,
        sensors: SENSORS.iter().map(|s| s.to_string()).collect(),
    }
}

/// Stamps `new` with `metrics`, checks it builds, writes it and (when asked) the report, and
/// commits both together.
pub(crate) fn commit_version(
    new: &mut Calibration,
    metrics: Vec<(&str, f64)>,
    out_file: Option<AtomicOutput>,
    report_file: Option<AtomicOutput>,
    report: impl FnOnce() -> String,
) -> Result<()> {
    new.metrics = metrics
        .into_iter()
        .map(|(k, v)| (k.to_string(), v))
        .collect();
    new.build().context("the new calibration")?;
    put(&out_file, new.to_json())?;
    if report_file.is_some() {
        put(&report_file, report())?;
    }
    commit_all([out_file, report_file])
}

/// The closing lines of a procedure's text output: its notes, then where the new version is.
pub(crate) fn closing(
    notes: &[String],
    out: &Path,
    new: &Calibration,
    start: &Calibration,
) -> Result<()> {
    for n in notes {
        outln!("  note: {n}")?;
    }
    outln!(
        "→ {} (version {}, parent {})",
        out.display(),
        new.version,
        start.version
    )
}

/// `--json` of a procedure: its outcome with `params` and `uncertainty` by the truth file's
/// names, and the new version's place.
fn outcome_json(
    o: &impl serde::Serialize,
    ps: &[Param],
    noise_floor_um: f64,
    new: &Calibration,
    start: &Calibration,
    out: &Path,
) -> Result<serde_json::Value> {
    let (params, sigma) = sigma_json(ps);
    let mut v = serde_json::to_value(o)?;
    v["params"] = params;
    v["uncertainty"] = sigma;
    v["noise_floor_um"] = noise_floor_um.into();
    v["version"] = new.version.into();
    v["parent_version"] = start.version.into();
    v["out"] = out.display().to_string().into();
    Ok(v)
}

/// A dynamic parameter in its engineering unit: (value, σ, unit).
fn dynamic_unit(p: &Param) -> (f64, f64, &'static str) {
    let n = p.name.as_str();
    let (k, u) = if n.ends_with("_s") {
        (1e3, "ms")
    } else if n.contains(".P_") {
        (1e6, "µm per m/s²")
    } else if n.contains(".b0.") {
        (1e6, "µrad")
    } else if n.contains(".b1.") {
        (1e6, "µrad/Hz")
    } else if n.contains(".b2.") {
        (1e6, "µrad/Hz²")
    } else if n.contains(".f1.") {
        (1e6, "ppm/Hz")
    } else if n.contains(".f2.") {
        (1e6, "ppm/Hz²")
    } else {
        (1.0, "")
    };
    (p.value * k, p.sigma * k, u)
}

fn run_dynamics(
    bag: Vec<PathBuf>,
    calib: PathBuf,
    out: PathBuf,
    json: bool,
    report: Option<PathBuf>,
) -> Result<()> {
    let Opened {
        out_file,
        report_file,
        start,
        bags,
    } = open(&bag, &calib, &out, report.as_deref())?;
    crate::output::stage("refitting the nominal model's time constants …");
    let raw: Vec<&dyn dataset::Samples> = bags.iter().map(|b| &*b.samples).collect();
    let (refit, axes) = scancorr_core::lab::nominal::fit_nominal(&raw, &start)?;
    // The dynamic effects are what this procedure measures: the points are taken without.
    crate::output::stage("correcting the rings …");
    let ds = points_without(
        &bags,
        &refit,
        &["accel_deflection", "servo_phase", "servo_gain"],
        4,
    )?;
    let prep = analysis::prepare(&ds)?;
    crate::output::stage("fitting …");
    let o = dynamics::run(&ds, &prep, &refit, &axes)?;
    let mut new = version::next(&start, o.calibration.effects.clone(), &now_rfc3339());
    new.nominal = o.calibration.nominal.clone();
    new.note = format!(
        "calibrate dynamics: {} ring positions; residual after the static patterns {:.3} → \
         {:.3} µm (noise floor {:.3} µm); gain form {}",
        o.positions.len(),
        o.residual_before_um,
        o.residual_after_um,
        ds.noise_floor_um,
        o.gain.chosen
    );
    commit_version(
        &mut new,
        vec![
            ("dynamics_residual_before_um", o.residual_before_um),
            ("dynamics_residual_after_um", o.residual_after_um),
            ("noise_floor_um", ds.noise_floor_um),
        ],
        out_file,
        report_file,
        || crate::report::dynamics(&start, &o, ds.noise_floor_um),
    )?;
    if json {
        let mut v = outcome_json(&o, &o.params, ds.noise_floor_um, &new, &start, &out)?;
        v["nominal"] = serde_json::to_value(&axes)?;
        outln!("{}", serde_json::to_string_pretty(&v)?)?;
        return Ok(());
    }
    outln!(
        "ring-gauge procedure: {} positions; residual after each position's static pattern {:.3} → {:.3} µm (noise floor {:.3} µm)",
        o.positions.len(),
        o.residual_before_um,
        o.residual_after_um,
        ds.noise_floor_um
    )?;
    outln!("ΔR per scan against each position's static pattern (before → after, µm):")?;
    for p in &o.positions {
        let scans: Vec<String> = p
            .scans
            .iter()
            .map(|s| {
                format!(
                    "{}{:.0} mm/s ({:.0} mm/s²) {:+.2}→{:+.2}",
                    if s.direction > 0 { "+" } else { "−" },
                    s.speed_mm_s,
                    s.accel_mm_s2,
                    s.delta_r_um,
                    s.delta_r_after_um
                )
            })
            .collect();
        outln!(
            "  ({:>6.1} {:>6.1} {:>7.1})  {}",
            p.center_mm[0],
            p.center_mm[1],
            p.center_mm[2],
            scans.join("  ")
        )?;
    }
    outln!(
        "servo gain: {} form (held-out rings: theoretical {:.3} µm, polynomial in f {:.3} µm)",
        o.gain.chosen,
        o.gain.heldout_theoretical_um,
        o.gain.heldout_polynomial_um
    )?;
    outln!("parameters (± standard uncertainty; P per monomial of the position over 500 mm):")?;
    for p in &o.params {
        let (v, s, u) = dynamic_unit(p);
        outln!("  {:<28} {:>11.4} ± {:.4} {u}", p.name, v, s)?;
    }
    for c in &o.confounded {
        outln!("  confounded: {c}")?;
    }
    for u in &o.undetermined {
        outln!("  not determined: {u}")?;
    }
    closing(&o.notes, &out, &new, &start)
}

fn print_param(p: &Param) -> String {
    let (scale, unit) = if p.name.ends_with("_mm") {
        (1.0, "mm")
    } else if p.name.ends_with("_per_k") {
        (1e6, "ppm/K")
    } else {
        (1.0, "")
    };
    let digits = if unit == "mm" { 5 } else { 3 };
    format!(
        "  {:<20} {:>12.digits$} ± {:.digits$} {unit}",
        p.name,
        p.value * scale,
        p.sigma * scale
    )
}

fn run_probe_force(
    bag: Vec<PathBuf>,
    calib: PathBuf,
    out: PathBuf,
    json: bool,
    report: Option<PathBuf>,
) -> Result<()> {
    let Opened {
        out_file,
        report_file,
        start,
        bags,
    } = open(&bag, &calib, &out, report.as_deref())?;
    // The force correction and the static maps are what this procedure measures: the points
    // are taken without (the new maps replace the start's of the same tip and segments).
    let ds = points_without(&bags, &start, &["probe_force", "feature_map"], 2)?;
    let o = probe_force::run(&ds, &start)?;
    let mut new = version::next(&start, o.calibration.effects.clone(), &now_rfc3339());
    new.geometry = o.calibration.geometry.clone();
    new.note = format!(
        "calibrate probe-force: {} settings; residual about each circle's static map {:.3} → \
         {:.3} µm (noise floor {:.3} µm)",
        o.settings.len(),
        o.rms_before_um,
        o.rms_after_um,
        ds.noise_floor_um
    );
    commit_version(
        &mut new,
        vec![
            ("probe_force_rms_before_um", o.rms_before_um),
            ("probe_force_rms_after_um", o.rms_after_um),
            ("noise_floor_um", ds.noise_floor_um),
        ],
        out_file,
        report_file,
        || crate::report::probe_force(&start, &o, ds.noise_floor_um),
    )?;
    if json {
        let v = outcome_json(&o, &o.params, ds.noise_floor_um, &new, &start, &out)?;
        outln!("{}", serde_json::to_string_pretty(&v)?)?;
        return Ok(());
    }
    outln!(
        "extrapolation to zero force: {} settings; residual about each circle's static map {:.3} → {:.3} µm (noise floor {:.3} µm)",
        o.settings.len(),
        o.rms_before_um,
        o.rms_after_um,
        ds.noise_floor_um
    )?;
    outln!(
        "consistency of the circles × deflections after the fit: reduced χ² {:.2}{}",
        o.cell_chi2,
        if o.cell_chi2 > 1.0 {
            " (the σ are scaled by it)"
        } else {
            ""
        }
    )?;
    outln!("sphere radius − certified per deflection (before → after the force correction, µm; without a sphere fit: along the probing direction from the zero-force surface):")?;
    for s in &o.settings {
        let lv: Vec<String> = s
            .deflections_mm
            .iter()
            .enumerate()
            .map(|(k, d)| {
                format!(
                    "{d:.2} mm {:+.2}→{:+.2}",
                    s.radius_error_before_um[k], s.radius_error_after_um[k]
                )
            })
            .collect();
        let zero = if s.sphere_fitted {
            format!(
                "at zero force {:+.3} ± {:.3}; static map's form {:.3} µm RMS",
                s.radius_error_at_zero_um[0], s.radius_error_at_zero_um[1], s.static_form_um
            )
        } else {
            "no sphere fit (too little of the sphere)".to_string()
        };
        outln!(
            "  tip {} at ({}, {})°: {}; {zero}; left after the fit {:.3} µm RMS",
            s.tip,
            s.head_deg[0],
            s.head_deg[1],
            lv.join("  "),
            s.fit_rms_um
        )?;
    }
    if !o.static_maps.is_empty() {
        outln!("static error maps (zero-force radius − certified around each circle; stored as feature_map effects, apart from the geometry, applied at every speed to scans of that circle; --json: static_maps):")?;
        for m in &o.static_maps {
            let (lo, hi) = m
                .radial_um
                .iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
                    (a.min(*v), b.max(*v))
                });
            let u = m.radial_u_um.iter().cloned().fold(0.0, f64::max);
            outln!(
                "  tip {} latitude {:+.0}°: {:+.3} to {:+.3} µm over {} knots (σ ≤ {:.3} µm)",
                m.tip,
                m.latitude_deg,
                lo,
                hi,
                m.radial_um.len(),
                u
            )?;
        }
    }
    if !o.real_time.is_empty() {
        outln!("real-time form, R0 = R1 − (R2 − R1)·F1/(F2 − F1) per wave of the deflection, against the fit's zero-force values:")?;
        for rt in &o.real_time {
            outln!(
                "  tip {} segment {} (latitude {:+.0}°, {:.2}–{:.2} mm): {} waves, {} extrapolated, {} at a force below significance, {} alike; R1 {:.3} µm RMS from the fit's zero force → R0 {:.3} µm RMS (statistical σ {:.3} µm); radial acceleration {:+.1} mm/s² per mm of deflection",
                rt.tip,
                rt.segment,
                rt.latitude_deg,
                rt.deflection_mm[0],
                rt.deflection_mm[1],
                rt.waves,
                rt.extrapolated,
                rt.force_zero,
                rt.alike,
                rt.before_um,
                rt.rms_um,
                rt.sigma_um,
                rt.accel_per_deflection_s2
            )?;
        }
    }
    outln!("parameters (± standard uncertainty):")?;
    for p in &o.params {
        if p.name.ends_with("_mm") {
            outln!(
                "  {:<28} {:>9.5} mm ± {:.3} µm (statistical)",
                p.name,
                p.value,
                p.sigma * 1e3
            )?;
        } else {
            outln!(
                "  {:<28} {:>9.3} ± {:.3} µm per mm of deflection",
                p.name,
                p.value * 1e3,
                p.sigma * 1e3
            )?;
        }
    }
    for u in &o.undetermined {
        outln!("  not determined: {u}")?;
    }
    closing(&o.notes, &out, &new, &start)
}

fn run_dynamic_map(
    bag: Vec<PathBuf>,
    calib: PathBuf,
    out: PathBuf,
    bins: usize,
    tolerance_um: Option<f64>,
    json: bool,
    report: Option<PathBuf>,
) -> Result<()> {
    let Opened {
        out_file,
        report_file,
        start,
        bags,
    } = open(&bag, &calib, &out, report.as_deref())?;
    // The maps are what this procedure measures: the points are taken without them (every
    // point: a fast scan has a few dozen per bin).
    let ds = points_without(&bags, &start, &["feature_map"], 1)?;
    let o = dynamic_map::run(
        &ds,
        &start,
        &dynamic_map::Options {
            bins,
            tolerance_mm: tolerance_um.map(|t| t * 1e-3),
            ..Default::default()
        },
    )?;
    let mut new = version::next(&start, o.calibration.effects.clone(), &now_rfc3339());
    let e2 = o.maps.iter().map(|m| m.e2_rms_um).fold(0.0, f64::max);
    new.note = format!(
        "calibrate dynamic-map: {} map(s) ({}); e2 up to {e2:.3} µm RMS (noise floor {:.3} µm)",
        o.maps.len(),
        o.maps
            .iter()
            .map(|m| format!("{} at {:.0} mm/s", m.id, m.speed_mm_s))
            .collect::<Vec<_>>()
            .join(", "),
        ds.noise_floor_um
    );
    commit_version(
        &mut new,
        vec![
            ("dynamic_map_e2_rms_um", e2),
            ("noise_floor_um", ds.noise_floor_um),
        ],
        out_file,
        report_file,
        || crate::report::dynamic_map(&start, &o, ds.noise_floor_um),
    )?;
    if json {
        let v = outcome_json(&o, &o.params, ds.noise_floor_um, &new, &start, &out)?;
        outln!("{}", serde_json::to_string_pretty(&v)?)?;
        return Ok(());
    }
    outln!(
        "S1/F1/F2 joint method: {} map(s) (noise floor {:.3} µm)",
        o.maps.len(),
        ds.noise_floor_um
    )?;
    for m in &o.maps {
        outln!("  {} — {}", m.id, m.feature)?;
        for s in &m.scans {
            outln!(
                "    {} segment {:>4}: {:>5.1} mm/s at {:.3} mm, {} points, mean radial {:+.3} µm",
                s.role,
                s.segment,
                s.speed_mm_s,
                s.deflection_mm,
                s.points,
                s.mean_radial_um
            )?;
        }
        outln!(
            "    e2 (fast scan's error at d1) {:.3} µm RMS (σ per bin {:.3} µm RMS); dynamic part at zero deflection {:.3} µm RMS; e1 (deflection at speed) {:.3} µm RMS; {} bins; applies to segments {:?}, tip {}, {:.0} mm/s",
            m.e2_rms_um,
            m.e2_u_rms_um,
            m.dynamic_rms_um,
            m.e1_rms_um,
            m.theta_deg.len(),
            m.segments,
            m.tip,
            m.speed_mm_s
        )?;
    }
    outln!("parameters (± standard uncertainty):")?;
    for p in &o.params {
        outln!(
            "  {:<44} {:>9.3} ± {:.3} µm{}",
            p.name,
            p.value * 1e3,
            p.sigma * 1e3,
            if p.name.ends_with("_per_mm") {
                " per mm of deflection"
            } else {
                ""
            }
        )?;
    }
    for s in &o.speed_search {
        outln!(
            "  speed search, {} (tolerance {:.3} µm): {}; no map needed up to {}",
            s.feature,
            s.tolerance_um,
            s.steps
                .iter()
                .map(|x| format!(
                    "{:.0} mm/s {:.3} ± {:.3} µm{}",
                    x.speed_mm_s,
                    x.difference_um,
                    x.difference_u_um,
                    if x.within { "" } else { " (mapped)" }
                ))
                .collect::<Vec<_>>()
                .join(", "),
            s.fastest_within_mm_s
                .map_or("no speed measured".into(), |v| format!("{v:.0} mm/s"))
        )?;
    }
    for s in &o.skipped {
        outln!("  not mapped: {s}")?;
    }
    closing(&o.notes, &out, &new, &start)
}

/// Runs a procedure.
pub fn run(cmd: CalibrateCmd) -> Result<()> {
    crate::output::started();
    match cmd {
        CalibrateCmd::Plate(a) => crate::platecmd::run(a),
        CalibrateCmd::ThermalDrift(a) => crate::thermalcmd::run(a),
        CalibrateCmd::DynamicMap {
            bag,
            calib,
            out,
            bins,
            tolerance_um,
            json,
            report,
        } => run_dynamic_map(bag, calib, out, bins, tolerance_um, json, report),
        CalibrateCmd::Straightness {
            method,
            bag,
            reversal,
            calib,
            axis,
            toward,
            out,
            json,
            report,
        } => crate::calibsep::run(crate::calibsep::Args {
            method,
            bag,
            reversal,
            calib,
            axis,
            toward,
            out,
            json,
            report,
        }),
        CalibrateCmd::ProbeForce {
            bag,
            calib,
            out,
            json,
            report,
        } => run_probe_force(bag, calib, out, json, report),
        CalibrateCmd::Dynamics {
            bag,
            calib,
            out,
            json,
            report,
        } => run_dynamics(bag, calib, out, json, report),
        CalibrateCmd::Tips {
            bag,
            calib,
            out,
            reference_tip,
            json,
            report,
        } => {
            let Opened {
                out_file,
                report_file,
                start,
                bags,
            } = open(&bag, &calib, &out, report.as_deref())?;
            // The stylus thermal correction is what this procedure measures: the points are
            // taken without it.
            let ds = points_without(&bags, &start, &["stylus_thermal"], 1)?;
            let outcome = tips::run(&ds, &start, reference_tip)?;
            let mut new =
                version::next(&start, outcome.calibration.effects.clone(), &now_rfc3339());
            new.geometry = outcome.calibration.geometry.clone();
            // The same bags corrected with the new version: what the qualification leaves.
            let after = tips::run(
                &dataset::build(&bags, &new, &options(1))?,
                &new,
                Some(outcome.reference_tip),
            )
            .map(|o| o.consistency_before_um)
            .ok();
            new.note = format!(
                "calibrate tips (reference tip {}): tip-to-tip consistency {:.3} µm → {} on the \
                 qualification",
                outcome.reference_tip,
                outcome.consistency_before_um,
                after.map_or("—".into(), |a| format!("{a:.3} µm"))
            );
            commit_version(
                &mut new,
                [
                    ("tip_consistency_before_um", outcome.consistency_before_um),
                    ("tip_fit_residual_um", outcome.residual_rms_um),
                    ("noise_floor_um", ds.noise_floor_um),
                ]
                .into_iter()
                .chain(after.map(|a| ("tip_consistency_after_um", a)))
                .collect(),
                out_file,
                report_file,
                || crate::report::tips(&start, &outcome, after, ds.noise_floor_um),
            )?;
            if json {
                let mut v = outcome_json(
                    &outcome,
                    &outcome.params,
                    ds.noise_floor_um,
                    &new,
                    &start,
                    &out,
                )?;
                v["consistency_after_um"] = after.into();
                outln!("{}", serde_json::to_string_pretty(&v)?)?;
            } else {
                outln!(
                    "qualified {} settings on the master sphere (reference tip {}{})",
                    outcome.settings.len(),
                    outcome.reference_tip,
                    outcome.reference_temp_c.map_or(String::new(), |t| format!(
                        ", at {t:.2} °C, range {:.2} K",
                        outcome.temp_range_k
                    ))
                )?;
                outln!("  setting            offset from the reference (µm)      left (µm)")?;
                for s in &outcome.settings {
                    if s.tip == outcome.reference_tip {
                        continue;
                    }
                    outln!(
                        "  tip {} A1 {:>5.1}° A2 {:>5.1}°  ({:>8.3} {:>8.3} {:>8.3})  ({:>6.3} {:>6.3} {:>6.3})",
                        s.tip, s.head_deg[0], s.head_deg[1], s.offset_um[0], s.offset_um[1],
                        s.offset_um[2], s.residual_um[0], s.residual_um[1], s.residual_um[2]
                    )?;
                }
                outln!("parameters (± standard uncertainty):")?;
                for p in &outcome.params {
                    outln!("{}", print_param(p))?;
                }
                outln!(
                    "  offsets rotated at the sphere's position (µrad, the machine's angular errors there or the head's): {}",
                    outcome
                        .rotation
                        .iter()
                        .map(|p| format!("{:.1} ± {:.1}", p.value * 1e6, p.sigma * 1e6))
                        .collect::<Vec<_>>()
                        .join(", ")
                )?;
                for u in &outcome.undetermined {
                    outln!("  not determined: {u}")?;
                }
                for n in &outcome.notes {
                    outln!("  note: {n}")?;
                }
                outln!(
                    "tip-to-tip consistency: {:.3} µm with the starting calibration, {} with the new one (noise floor {:.3} µm); fit residual {:.3} µm",
                    outcome.consistency_before_um,
                    after.map_or("—".into(), |a| format!("{a:.3} µm")),
                    ds.noise_floor_um,
                    outcome.residual_rms_um
                )?;
                outln!(
                    "→ {} (version {}, parent {})",
                    out.display(),
                    new.version,
                    start.version
                )?;
            }
            Ok(())
        }
    }
}
