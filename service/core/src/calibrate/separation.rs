//! `calibrate straightness`: from the raw streams of an error-separation measurement to the
//! guide's table in a new calibration.
//!
//! 1. **Stations.** Each distance reading takes the carriage position of the last scale
//!    sample at or before it (along the measured axis). A station is a run of readings in
//!    time order while the carriage stands within [`STAND_TOLERANCE_MM`]; a run with fewer
//!    than [`MIN_SAMPLES`] readings of a probe is the carriage passing by, left out and
//!    counted. With a micro-stage, a station's readings are split by the stage's commanded
//!    position and only those taken while its sensor stands within
//!    [`STAND_TOLERANCE_MM`] of that shear's median are kept; the shear is the sensor's mean
//!    (the real spacing), not the command.
//! 2. **Readings.** Each probe's (and shear's) samples at a station are averaged
//!    ([`straightness::average_samples`]: outliers out, standard error widened for
//!    correlated samples, the probe's resolution/√12 as a floor).
//! 3. **Separation** by the chosen method ([`straightness`]): the probes in the order of
//!    their levers along the travel (`spacing_mm` as mounted); the stations are given at
//!    probe A's position (x_ram + lever_A), the results are reported at the carriage
//!    positions the scales read (x_ram), the guide's motion at the method's pitch centre
//!    moved to the ram axis with the separated pitch (X_ram = X_c − θ·lever_c) where there is
//!    one.
//! 4. **The table.** The axis's `guide_straightness` effect gets, at the stations as knots,
//!    the straightness towards the probed axis and (where separated) the pitch about the
//!    third axis, each with its uncertainty; a table the measurement does not see (the other
//!    perpendicular axis, or the pitch of a method without it) is kept, resampled onto the
//!    new knots. What no method sees (the line, a constant pitch) is left out of the table:
//!    it is the axes' alignment (squareness), not their straightness.
//!
//! Source idea: the sequential multi-probe and shear-stage error separation methods
//! ([`straightness`]); stations and averaging as a straightness interferometer's software
//! would do them.

use super::straightness::{
    self, average_samples, ProbeMount, Reading, Separation, ShearOptions, ShearReading,
    StationReading,
};
use super::ProcedureError;
use crate::calib::Calibration;
use crate::effects::{guide_straightness, EffectConfig};
use crate::sample::Axis;
use serde::Serialize;
use std::collections::BTreeMap;

/// The carriage (or the stage) stands while its readings stay within this, mm.
pub const STAND_TOLERANCE_MM: f64 = 1e-3;
/// Fewer readings of a probe than this at a position are the carriage passing by.
pub const MIN_SAMPLES: usize = 10;

/// The separation methods.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Method {
    /// Three probes, sequential, with pitch.
    ThreeProbe,
    /// Two probes, sequential, no pitch.
    TwoProbe,
    /// One probe on a shear micro-stage.
    ShearStage,
}

impl std::str::FromStr for Method {
    type Err = String;
    fn from_str(s: &str) -> Result<Method, String> {
        match s {
            "three-probe" => Ok(Method::ThreeProbe),
            "two-probe" => Ok(Method::TwoProbe),
            "shear-stage" => Ok(Method::ShearStage),
            _ => Err(format!(
                "unknown method `{s}` (known: three-probe, two-probe, shear-stage)"
            )),
        }
    }
}

/// A scale sample: the carriage position, mm.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CarriageSample {
    /// Time, ns.
    pub t_ns: i64,
    /// Scale readings x, y, z, mm.
    pub pos: [f64; 3],
}

/// A distance probe's reading.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DistanceSample {
    /// Time, ns.
    pub t_ns: i64,
    /// Probe id.
    pub probe_id: u32,
    /// Reading, mm.
    pub distance_mm: f64,
    /// Lever along the travel from the ram axis, as mounted, mm.
    pub spacing_mm: f64,
}

/// The micro-stage's position.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StageSample {
    /// Time, ns.
    pub t_ns: i64,
    /// The probe it carries.
    pub probe_id: u32,
    /// Commanded position, mm.
    pub commanded_mm: f64,
    /// Its own sensor's reading, mm.
    pub sensor_mm: f64,
}

/// The raw streams of one measurement, each in time order.
#[derive(Debug, Clone, Default)]
pub struct Raw {
    /// Scales.
    pub carriage: Vec<CarriageSample>,
    /// Distance probes.
    pub distance: Vec<DistanceSample>,
    /// Micro-stage (empty without one).
    pub stage: Vec<StageSample>,
}

/// What the procedure was asked.
#[derive(Debug, Clone)]
pub struct Request<'a> {
    /// Method.
    pub method: Method,
    /// The guide's axis (the carriage's travel).
    pub axis: Axis,
    /// The axis the probes read along (perpendicular to `axis`).
    pub toward: Axis,
    /// The measurement.
    pub raw: &'a Raw,
    /// A reversal measurement (three probes: the straightedge turned over).
    pub reversal: Option<&'a Raw>,
    /// Resolution of a probe reading, mm (the floor of a reading's standard error is
    /// resolution/√12).
    pub probe_resolution_mm: f64,
    /// Three probes without a reversal: the stated bounds that fix the offsets' parabola
    /// (`straightness::ThreeProbeOptions`; default: none, the parabola is reported unseen).
    pub three_probe: straightness::ThreeProbeOptions,
}

/// The procedure's result.
#[derive(Debug, Clone, Serialize)]
pub struct Outcome {
    /// Method.
    pub method: Method,
    /// Axis of the guide and the axis the probes read along.
    pub axis: Axis,
    /// Perpendicular axis of the straightness.
    pub toward: Axis,
    /// The separation, reported at the carriage positions the scales read.
    #[serde(flatten)]
    pub separation: Separation,
    /// Probes used, in lever order: (id, lever mm).
    pub probes: Vec<(u32, f64)>,
    /// Readings averaged into each station reading (median).
    pub samples_per_reading: usize,
    /// Samples left out, by reason.
    pub left_out: BTreeMap<String, u64>,
    /// With lines stepped across the surface: each line's height profile, about the
    /// least-squares plane of all of them (empty for one line).
    pub lines: Vec<LineProfile>,
    /// Flatness (peak-to-valley about the least-squares plane), mm, with lines.
    pub flatness_mm: Option<f64>,
    /// Warnings.
    pub warnings: Vec<String>,
    /// The changed calibration (not yet versioned).
    #[serde(skip)]
    pub calibration: Calibration,
}

/// One stand of the carriage: its position and the distance samples taken there.
struct Stand {
    /// Along the guide, mm.
    x: f64,
    /// Scale readings x, y, z, mm.
    pos: [f64; 3],
    samples: Vec<DistanceSample>,
    t0: i64,
}

/// Splits the distance readings into stands of the carriage (see the module doc).
fn stands(raw: &Raw, axis: usize, left_out: &mut BTreeMap<String, u64>) -> Vec<Stand> {
    let mut out: Vec<Stand> = vec![];
    let mut ci = 0usize;
    for d in &raw.distance {
        while ci + 1 < raw.carriage.len() && raw.carriage[ci + 1].t_ns <= d.t_ns {
            ci += 1;
        }
        let Some(c) = raw.carriage.get(ci).filter(|c| c.t_ns <= d.t_ns) else {
            *left_out
                .entry("before the first scale sample".into())
                .or_default() += 1;
            continue;
        };
        let x = c.pos[axis];
        match out.last_mut() {
            Some(s) if (0..3).all(|i| (c.pos[i] - s.pos[i]).abs() <= STAND_TOLERANCE_MM) => {
                s.samples.push(*d);
            }
            _ => out.push(Stand {
                x,
                pos: c.pos,
                samples: vec![*d],
                t0: d.t_ns,
            }),
        }
    }
    out
}

/// Stands grouped into lines by their position along `step` (within 0.01 mm), in the order
/// the lines were first measured.
fn split_lines(stands: Vec<Stand>, step: usize) -> Vec<(f64, Vec<Stand>)> {
    let mut lines: Vec<(f64, Vec<Stand>)> = vec![];
    for s in stands {
        let z = s.pos[step];
        match lines
            .iter_mut()
            .find(|l| (l.0 - z).abs() <= 10.0 * STAND_TOLERANCE_MM)
        {
            Some(l) => l.1.push(s),
            None => lines.push((z, vec![s])),
        }
    }
    lines
}

/// One line of a surface stepped across.
#[derive(Debug, Clone, Serialize)]
pub struct LineProfile {
    /// Position along the stepping axis, mm.
    pub step_mm: f64,
    /// Positions along the guide, mm.
    pub positions_mm: Vec<f64>,
    /// Height of the surface (towards the probed axis) about the least-squares plane, mm.
    pub height_mm: Vec<f64>,
    /// Its standard uncertainty, mm.
    pub height_mm_u: Vec<f64>,
}

/// The surface from lines stepped across: the first line's separated part profile, and each
/// other line as the first plus the difference of the reference probe's readings between the
/// lines at each station (X_K, θ_K and the offsets cancel: m_j − m_0 = Y_j − Y_0 at the same
/// carriage position); all about their least-squares plane. (profiles, peak-to-valley)
fn flatness(
    sep: &Separation,
    refs: &[(f64, Vec<(f64, Reading)>)],
    ref_lever: f64,
    step: Axis,
) -> Result<(Vec<LineProfile>, f64), ProcedureError> {
    let part = |x: f64| {
        (
            interpolate(&sep.part_positions_mm, &sep.part_straightness_mm, x),
            interpolate(&sep.part_positions_mm, &sep.part_straightness_mm_u, x),
        )
    };
    let base = &refs[0].1;
    let mut lines = vec![];
    for (z, r) in refs {
        let (mut xs, mut h, mut u) = (vec![], vec![], vec![]);
        for (k, (x, b)) in base.iter().enumerate() {
            let Some((_, v)) = r
                .iter()
                .find(|(xj, _)| (xj - x).abs() <= 10.0 * STAND_TOLERANCE_MM)
            else {
                return Err(ProcedureError::Missing(format!(
                    "line {} (at {} = {z:.3} mm) has no reading at station {k} (x = {x:.3} mm) \
                     that the first line has: every line must repeat the stations",
                    lines.len() + 1,
                    step.name()
                )));
            };
            let pos = x + ref_lever;
            let (y0, u0) = part(pos);
            xs.push(pos);
            h.push(y0 + v.value_mm - b.value_mm);
            u.push((u0 * u0 + v.u_mm * v.u_mm + b.u_mm * b.u_mm).sqrt());
        }
        lines.push(LineProfile {
            step_mm: *z,
            positions_mm: xs,
            height_mm: h,
            height_mm_u: u,
        });
    }
    // The least-squares plane h = a + b·x + c·z over every point.
    let mut ata = nalgebra::Matrix3::<f64>::zeros();
    let mut atb = nalgebra::Vector3::<f64>::zeros();
    for l in &lines {
        for (x, h) in l.positions_mm.iter().zip(&l.height_mm) {
            let row = nalgebra::Vector3::new(1.0, *x, l.step_mm);
            ata += row * row.transpose();
            atb += row * *h;
        }
    }
    let c = ata.try_inverse().map(|i| i * atb).ok_or_else(|| {
        ProcedureError::IllConditioned(
            "the lines do not span a plane: step them across the surface".into(),
        )
    })?;
    let (mut lo, mut hi) = (f64::MAX, f64::MIN);
    for l in lines.iter_mut() {
        for (x, h) in l.positions_mm.iter().zip(l.height_mm.iter_mut()) {
            *h -= c[0] + c[1] * x + c[2] * l.step_mm;
            lo = lo.min(*h);
            hi = hi.max(*h);
        }
    }
    Ok((lines, hi - lo))
}

/// Averages `values`, with the resolution floor on the standard error.
fn reading(values: &[f64], floor: f64) -> Result<(Reading, usize), ProcedureError> {
    let a = average_samples(values)?;
    let mut r = a.reading;
    r.u_mm = r.u_mm.max(floor);
    Ok((r, a.used))
}

/// The probes in lever order, checked: (id, lever).
fn probes(raw: &Raw, want: usize, method: &str) -> Result<Vec<(u32, f64)>, ProcedureError> {
    let mut levers: BTreeMap<u32, f64> = BTreeMap::new();
    for d in &raw.distance {
        let l = levers.entry(d.probe_id).or_insert(d.spacing_mm);
        if (*l - d.spacing_mm).abs() > STAND_TOLERANCE_MM {
            return Err(ProcedureError::IllConditioned(format!(
                "probe {} changes its lever from {:.3} to {:.3} mm during the measurement: \
                 a probe must stay where it is mounted",
                d.probe_id, l, d.spacing_mm
            )));
        }
    }
    let mut v: Vec<(u32, f64)> = levers.into_iter().collect();
    v.sort_by(|a, b| a.1.total_cmp(&b.1));
    if v.len() < want {
        return Err(ProcedureError::Missing(format!(
            "the {method} method needs {want} distance probes; the bag has {} ({}): record \
             the measurement with {want} probes on the mount, e.g. `scancorr sim --program \
             straightness-{}`",
            v.len(),
            v.iter()
                .map(|(id, l)| format!("probe {id} at {l:.1} mm"))
                .collect::<Vec<_>>()
                .join(", "),
            if want == 3 {
                "three-probe"
            } else {
                "two-probe"
            }
        )));
    }
    v.truncate(want);
    Ok(v)
}

/// Station readings of the fixed probes `ps` at one line's stands, at probe A's positions.
fn station_readings(
    line: &[Stand],
    ps: &[(u32, f64)],
    floor: f64,
    left_out: &mut BTreeMap<String, u64>,
    used: &mut Vec<usize>,
) -> Result<Vec<StationReading>, ProcedureError> {
    let mut out = vec![];
    for s in line {
        let per: Vec<Vec<f64>> = ps
            .iter()
            .map(|(id, _)| {
                s.samples
                    .iter()
                    .filter(|d| d.probe_id == *id)
                    .map(|d| d.distance_mm)
                    .collect()
            })
            .collect();
        if per.iter().all(|v| v.len() < MIN_SAMPLES) {
            *left_out
                .entry("read while the carriage moved".into())
                .or_default() += s.samples.len() as u64;
            continue;
        }
        let mut readings = vec![];
        for v in &per {
            if v.len() < MIN_SAMPLES {
                readings.push(None);
            } else {
                let (r, n) = reading(v, floor)?;
                used.push(n);
                readings.push(Some(r));
            }
        }
        out.push(StationReading {
            x_mm: s.x + ps[0].1,
            readings,
        });
    }
    Ok(out)
}

/// Shear readings of the stage's probe at one line's stands.
fn shear_readings(
    raw: &Raw,
    line: &[Stand],
    floor: f64,
    left_out: &mut BTreeMap<String, u64>,
    used: &mut Vec<usize>,
) -> Result<(Vec<ShearReading>, (u32, f64)), ProcedureError> {
    if raw.stage.is_empty() {
        return Err(ProcedureError::Missing(
            "the bag has no micro-stage stream (raw/stage): the shear-stage method needs the \
             stage's own displacement sensor at every reading; record it, e.g. `scancorr sim \
             --program straightness-shear-stage`"
                .into(),
        ));
    }
    let probe = raw.stage[0].probe_id;
    let lever = raw
        .distance
        .iter()
        .find(|d| d.probe_id == probe)
        .map(|d| d.spacing_mm)
        .ok_or_else(|| {
            ProcedureError::Missing(format!(
                "the stage carries probe {probe}, which gave no distance reading"
            ))
        })?;
    let mut out = vec![];
    for s in line {
        // Each sample with the stage's last state at or before it.
        let mut by_cmd: BTreeMap<i64, (f64, Vec<(f64, f64)>)> = BTreeMap::new();
        let first = raw
            .stage
            .partition_point(|g| g.t_ns < s.t0)
            .saturating_sub(1);
        let mut gi = first;
        for d in s.samples.iter().filter(|d| d.probe_id == probe) {
            while gi + 1 < raw.stage.len() && raw.stage[gi + 1].t_ns <= d.t_ns {
                gi += 1;
            }
            let Some(g) = raw.stage.get(gi).filter(|g| g.t_ns <= d.t_ns) else {
                *left_out
                    .entry("before the first stage sample".into())
                    .or_default() += 1;
                continue;
            };
            let key = (g.commanded_mm / STAND_TOLERANCE_MM).round() as i64;
            let e = by_cmd.entry(key).or_insert((g.commanded_mm, vec![]));
            e.1.push((g.sensor_mm, d.distance_mm));
        }
        for (_, (_, v)) in by_cmd {
            let mut sensors: Vec<f64> = v.iter().map(|p| p.0).collect();
            sensors.sort_by(f64::total_cmp);
            let med = sensors[sensors.len() / 2];
            let keep: Vec<&(f64, f64)> = v
                .iter()
                .filter(|p| (p.0 - med).abs() <= STAND_TOLERANCE_MM)
                .collect();
            *left_out
                .entry("read while the stage moved".into())
                .or_default() += (v.len() - keep.len()) as u64;
            if keep.len() < MIN_SAMPLES {
                *left_out
                    .entry("read while the carriage moved".into())
                    .or_default() += keep.len() as u64;
                continue;
            }
            let shear = keep.iter().map(|p| p.0).sum::<f64>() / keep.len() as f64;
            let vals: Vec<f64> = keep.iter().map(|p| p.1).collect();
            let (r, n) = reading(&vals, floor)?;
            used.push(n);
            out.push(ShearReading {
                x_mm: s.x + lever,
                shear_mm: shear,
                value_mm: r.value_mm,
                u_mm: r.u_mm,
            });
        }
    }
    Ok((out, (probe, lever)))
}

/// Runs the procedure on `start` (see the module doc).
pub fn run(req: &Request, start: &Calibration) -> Result<Outcome, ProcedureError> {
    if req.axis == req.toward {
        return Err(ProcedureError::IllConditioned(format!(
            "--toward {}: the probes must read across the travel, perpendicular to {}",
            req.toward.name(),
            req.axis.name()
        )));
    }
    if req.raw.distance.is_empty() {
        return Err(ProcedureError::Missing(
            "the bag has no distance-probe readings (raw/distance): record the straightness \
             measurement, e.g. `scancorr sim --program straightness-three-probe`"
                .into(),
        ));
    }
    if req.raw.carriage.is_empty() {
        return Err(ProcedureError::Missing(
            "the bag has no scale readings (raw/scale): the stations need the carriage \
             position"
                .into(),
        ));
    }
    let ax = req.axis.index();
    let floor = req.probe_resolution_mm.max(0.0) / 12f64.sqrt();
    let mut left_out = BTreeMap::new();
    let mut used = vec![];
    let mut warnings = vec![];
    let step_axis = Axis::ALL
        .into_iter()
        .find(|a| *a != req.axis && *a != req.toward)
        .expect("three axes");
    let lines = split_lines(stands(req.raw, ax, &mut left_out), step_axis.index());
    if lines.is_empty() {
        return Err(ProcedureError::Missing(
            "no distance reading was taken while the carriage stood: record the probes at \
             each station with the carriage at rest"
                .into(),
        ));
    }
    // Each line's reference readings: (carriage position, reading), one probe (the one at
    // the ram axis, or the stage's at zero shear) — the lines' differences tie them.
    let mut refs: Vec<(f64, Vec<(f64, Reading)>)> = vec![];
    let (sep, ps, centre_lever, ref_lever) = match req.method {
        Method::ThreeProbe | Method::TwoProbe => {
            let (want, name) = if req.method == Method::ThreeProbe {
                (3, "three-probe")
            } else {
                (2, "two-probe")
            };
            let ps = probes(req.raw, want, name)?;
            let l = ps[1].1 - ps[0].1;
            if want == 3 && ((ps[2].1 - ps[1].1) - l).abs() > straightness::STEP_TOLERANCE * l {
                return Err(ProcedureError::IllConditioned(format!(
                    "the probes are not equally spaced (levers {:.3}, {:.3}, {:.3} mm): the \
                     sequential three-probe method needs A, B, C at equal spacing l and the \
                     carriage stepping by l",
                    ps[0].1, ps[1].1, ps[2].1
                )));
            }
            let mount = ProbeMount { spacing_mm: l };
            let r = (0..ps.len())
                .min_by(|a, b| ps[*a].1.abs().total_cmp(&ps[*b].1.abs()))
                .expect("probes");
            let mut first = None;
            for line in &lines {
                let st = station_readings(&line.1, &ps, floor, &mut left_out, &mut used)?;
                refs.push((
                    line.0,
                    st.iter()
                        .filter_map(|s| s.readings[r].map(|v| (s.x_mm - ps[0].1, v)))
                        .collect(),
                ));
                first.get_or_insert(st);
            }
            let st = first.expect("a line");
            if want == 2 && req.reversal.is_some() {
                warnings.push(
                    "--reversal is for the three-probe method (it separates the probes' \
                     offsets' second difference); the two-probe method does not use it"
                        .into(),
                );
            }
            let sep = if want == 3 {
                let rev = match req.reversal {
                    Some(rv) => {
                        let rps = probes(rv, 3, name)?;
                        if rps.iter().map(|p| p.0).ne(ps.iter().map(|p| p.0)) {
                            return Err(ProcedureError::IllConditioned(
                                "the reversal's probes are not the measurement's: the reversal \
                                 must be read by the same three probes"
                                    .into(),
                            ));
                        }
                        let rl = split_lines(stands(rv, ax, &mut left_out), step_axis.index());
                        let Some(first) = rl.first() else {
                            return Err(ProcedureError::Missing(
                                "the reversal has no reading taken while the carriage stood".into(),
                            ));
                        };
                        Some(station_readings(
                            &first.1,
                            &ps,
                            floor,
                            &mut left_out,
                            &mut used,
                        )?)
                    }
                    None => None,
                };
                straightness::three_probe_with(&mount, &st, rev.as_deref(), &req.three_probe)?
            } else {
                straightness::two_probe(&mount, &st)?
            };
            // Pitch centre: probe B (three), probe A (two), as levers from the ram.
            let c = if want == 3 { ps[1].1 } else { ps[0].1 };
            (sep, ps.clone(), c, ps[r].1)
        }
        Method::ShearStage => {
            let mut first = None;
            let mut probe = (0, 0.0);
            for line in &lines {
                let (rd, p) = shear_readings(req.raw, &line.1, floor, &mut left_out, &mut used)?;
                probe = p;
                refs.push((
                    line.0,
                    rd.iter()
                        .filter(|r| r.shear_mm.abs() <= STAND_TOLERANCE_MM)
                        .map(|r| {
                            (
                                r.x_mm - p.1,
                                Reading {
                                    value_mm: r.value_mm,
                                    u_mm: r.u_mm,
                                },
                            )
                        })
                        .collect(),
                ));
                first.get_or_insert(rd);
            }
            let rd = first.expect("a line");
            let sep = straightness::shear_stage(&rd, &ShearOptions::default())?;
            (sep, vec![probe], probe.1, probe.1)
        }
    };
    let (line_profiles, flatness_mm) = if refs.len() > 1 {
        let (p, pv) = flatness(&sep, &refs, ref_lever, step_axis)?;
        (p, Some(pv))
    } else {
        (vec![], None)
    };
    let mut sep = sep;
    if flatness_mm.is_some() {
        sep.cannot_see.push("plane".into());
        sep.cannot_see.push("stepping_axis_straightness".into());
        sep.notes.push(format!(
            "flatness: {} lines stepped along {}, tied by the differences of one probe's \
             readings between lines at each station (the guide's motion cancels in them); the \
             stepping axis's own straightness towards {} between the lines is in those \
             differences and is not seen — correct it with that axis's table; the surface is \
             reported about its least-squares plane",
            refs.len(),
            step_axis.name(),
            req.toward.name()
        ));
    }
    let sep = at_ram(sep, ps[0].1, centre_lever, &mut warnings);
    let cal = with_table(start, req, &sep)?;
    used.sort_unstable();
    let samples_per_reading = used.get(used.len() / 2).copied().unwrap_or(0);
    if left_out.values().any(|n| *n > 0) {
        warnings.push(format!(
            "left out: {}",
            left_out
                .iter()
                .map(|(k, n)| format!("{n} reading(s) {k}"))
                .collect::<Vec<_>>()
                .join(", ")
        ));
    }
    Ok(Outcome {
        method: req.method,
        axis: req.axis,
        toward: req.toward,
        separation: sep,
        probes: ps,
        samples_per_reading,
        left_out,
        lines: line_profiles,
        flatness_mm,
        warnings,
        calibration: cal,
    })
}

/// Moves the stations from probe A's positions to the carriage's (the scales'), and the
/// guide's motion from the pitch centre to the ram axis where the pitch is separated.
fn at_ram(mut s: Separation, lever_a: f64, lever_c: f64, warnings: &mut Vec<String>) -> Separation {
    for x in s.stations_mm.iter_mut() {
        *x -= lever_a;
    }
    if lever_c != 0.0 {
        match &s.pitch_rad {
            Some(p) => {
                for (g, th) in s.guide_straightness_mm.iter_mut().zip(p) {
                    *g -= th * lever_c;
                }
                s.notes.push(format!(
                    "the guide's motion moved from the pitch centre ({lever_c:.3} mm from the \
                     ram axis) to the ram axis with the separated pitch"
                ));
            }
            None => warnings.push(format!(
                "the guide's motion is at the pitch centre, {lever_c:.3} mm from the ram axis, \
                 and this method does not separate the pitch to move it: the table holds the \
                 motion there"
            )),
        }
    }
    s
}

/// The calibration with the axis's guide table from `sep` (see the module doc).
fn with_table(
    start: &Calibration,
    req: &Request,
    sep: &Separation,
) -> Result<Calibration, ProcedureError> {
    let knots = sep.stations_mm.clone();
    let pitch_about = Axis::ALL
        .into_iter()
        .find(|a| *a != req.axis && *a != req.toward)
        .expect("three axes");
    let mut cal = start.clone();
    let old = cal
        .effects
        .iter()
        .position(|e| matches!(e, EffectConfig::GuideStraightness(g) if g.axis == req.axis));
    let mut e = guide_straightness::Config::zeros(req.axis, 0.0, 1.0, 2, false);
    e.knots_mm = knots.clone();
    e.straightness.clear();
    e.straightness
        .insert(req.toward, sep.guide_straightness_mm.clone());
    e.straightness_u
        .insert(req.toward, sep.guide_straightness_mm_u.clone());
    if let (Some(p), Some(u)) = (&sep.pitch_rad, &sep.pitch_rad_u) {
        e.pitch_rad = Some(p.clone());
        e.pitch_rad_u = Some(u.clone());
        e.pitch_about = Some(pitch_about);
    }
    if let Some(i) = old {
        let EffectConfig::GuideStraightness(g) = &cal.effects[i] else {
            unreachable!()
        };
        e.id = g.id.clone();
        let at = |table: &[f64]| -> Vec<f64> {
            knots
                .iter()
                .map(|x| interpolate(&g.knots_mm, table, *x))
                .collect()
        };
        for (b, t) in &g.straightness {
            if *b != req.toward {
                e.straightness.insert(*b, at(t));
            }
        }
        if e.pitch_rad.is_none() {
            if let Some(p) = &g.pitch_rad {
                e.pitch_rad = Some(at(p));
                e.pitch_about = g.pitch_about;
            }
        }
        cal.effects[i] = EffectConfig::GuideStraightness(e);
    } else {
        cal.effects.push(EffectConfig::GuideStraightness(e));
    }
    cal.build().map_err(|err| {
        ProcedureError::IllConditioned(format!("the new guide table does not validate: {err}"))
    })?;
    Ok(cal)
}

/// Linear interpolation between knots, constant beyond the ends (the table's own rule).
fn interpolate(k: &[f64], v: &[f64], x: f64) -> f64 {
    if x <= k[0] {
        return v[0];
    }
    let last = k.len() - 1;
    if x >= k[last] {
        return v[last];
    }
    let j = k.partition_point(|a| *a <= x) - 1;
    let w = (x - k[j]) / (k[j + 1] - k[j]);
    v[j] * (1.0 - w) + v[j + 1] * w
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A guide, a straightedge and three probes at levers −l, 0, l written directly: the
    /// procedure puts the guide at the ram positions and its table into the calibration.
    #[test]
    fn three_probes_fill_the_guide_table_at_the_carriage_positions() {
        let l = 25.0;
        let guide = |x: f64| 3e-3 * (x / 300.0).sin();
        let pitch = |x: f64| 10e-6 * (x / 200.0).cos();
        let form = |x: f64| 2e-3 * ((x - 500.0) / 400.0).powi(2) + 0.5e-3 * (x / 60.0).sin();
        let mut raw = Raw::default();
        let mut t = 0i64;
        let mut seed = 7u64;
        let mut noise = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 2e-6
        };
        for k in 0..20 {
            let x = 200.0 + k as f64 * l;
            for _ in 0..40 {
                raw.carriage.push(CarriageSample {
                    t_ns: t,
                    pos: [x, 0.0, 0.0],
                });
                for (id, s) in [(1u32, -l), (2, 0.0), (3, l)] {
                    raw.distance.push(DistanceSample {
                        t_ns: t,
                        probe_id: id,
                        distance_mm: form(x + s) - guide(x) - pitch(x) * s + noise(),
                        spacing_mm: s,
                    });
                }
                t += 1_000_000;
            }
        }
        let start = Calibration::example("m1");
        let req = Request {
            method: Method::ThreeProbe,
            axis: Axis::X,
            toward: Axis::Y,
            raw: &raw,
            reversal: None,
            probe_resolution_mm: 1e-6,
            three_probe: Default::default(),
        };
        let o = run(&req, &start).unwrap();
        assert_eq!(o.separation.stations_mm[0], 200.0);
        assert_eq!(o.samples_per_reading, 40);
        // Against the truth, lines removed.
        let detrend = |x: &[f64], y: &[f64]| -> Vec<f64> {
            let n = x.len() as f64;
            let (mx, my) = (x.iter().sum::<f64>() / n, y.iter().sum::<f64>() / n);
            let b = x
                .iter()
                .zip(y)
                .map(|(a, c)| (a - mx) * (c - my))
                .sum::<f64>()
                / x.iter().map(|a| (a - mx).powi(2)).sum::<f64>();
            x.iter()
                .zip(y)
                .map(|(a, c)| c - my - b * (a - mx))
                .collect()
        };
        let xs = &o.separation.stations_mm;
        let truth: Vec<f64> = xs.iter().map(|x| guide(*x)).collect();
        let (a, b) = (
            detrend(xs, &truth),
            detrend(xs, &o.separation.guide_straightness_mm),
        );
        for (k, (p, q)) in a.iter().zip(&b).enumerate() {
            assert!((p - q).abs() < 0.05e-3, "station {k}: {p} vs {q}");
        }
        let g = o
            .calibration
            .effects
            .iter()
            .find_map(|e| match e {
                EffectConfig::GuideStraightness(g) => Some(g),
                _ => None,
            })
            .expect("a guide table");
        assert_eq!(g.knots_mm, *xs);
        assert_eq!(g.pitch_about, Some(Axis::Z));
        assert!(g.straightness_u[&Axis::Y].iter().all(|u| *u > 0.0));
        // The two-probe method on the same readings says what it cannot see.
        let o2 = run(
            &Request {
                method: Method::TwoProbe,
                ..req.clone()
            },
            &start,
        )
        .unwrap();
        assert!(o2.separation.cannot_see.iter().any(|c| c == "pitch"));
        // No stage: the shear-stage method names the missing stream.
        let e = run(
            &Request {
                method: Method::ShearStage,
                ..req
            },
            &start,
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("raw/stage"), "{e}");
    }
}
