//! The lab's data: corrected scan points with their context, grouped by artifact feature.

use super::program::{FeatureKind, FeatureSpec, ProgramSpec, SegmentKind, SegmentSpec};
use super::LabError;
use crate::calib::{Calibration, Model};
use crate::corrector::{Corrector, DropReason};
use crate::sample::{PointContext, Sample, Vec3};
use std::sync::Arc;

/// Where a point lies in its scan's speed profile.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Phase {
    /// Speeding up.
    SpinUp,
    /// At programmed speed.
    Steady,
    /// Slowing down.
    SlowDown,
}

/// One scan point in the lab.
#[derive(Debug, Clone)]
pub struct LabPoint {
    /// Its context (the signals effects are functions of).
    pub ctx: PointContext,
    /// Corrected surface point (current calibration), mm.
    pub surface: Vec3,
    /// Unit normal out of the material.
    pub normal: Vec3,
    /// Index into [`Dataset::features`].
    pub feature: usize,
    /// Segment id (unique within its bag).
    pub segment: u32,
    /// Index of the bag it came from.
    pub bag: usize,
    /// Programmed speed, mm/s.
    pub speed: f64,
    /// +1 CCW, −1 CW, 0 line.
    pub direction: i32,
    /// Speed profile phase.
    pub phase: Phase,
    /// Held out from fitting (validation data).
    pub held_out: bool,
}

/// A bag's content, as the lab needs it.
#[derive(Debug, Clone)]
pub struct BagData {
    /// A name for messages (the file name).
    pub name: String,
    /// Raw samples of one machine in bag order.
    pub samples: Vec<Sample>,
    /// The program, if the bag has one.
    pub program: Option<ProgramSpec>,
    /// Held out: used only to validate.
    pub validation: bool,
}

/// Scan points of one or more bags corrected with one calibration.
#[derive(Debug, Clone)]
pub struct Dataset {
    /// Points (every `stride`-th contact point of every scan).
    pub points: Vec<LabPoint>,
    /// Features; a feature of bag b is one placement of an artifact.
    pub features: Vec<(usize, FeatureSpec)>,
    /// Temperature sensors by context slot.
    pub sensors: crate::effects::SensorTable,
    /// Noise floor of a point along its normal, estimated from the scans' point-to-point
    /// scatter, µm.
    pub noise_floor_um: f64,
    /// Tracking residual |scale − estimated position| RMS per (bag, segment), µm.
    pub tracking: Vec<(usize, u32, f64)>,
    /// The calibration the points were corrected with.
    pub calibration: Calibration,
    /// What the user should know about the points: samples the corrector dropped (by reason,
    /// with counts), bags without samples, scans not evaluated.
    pub warnings: Vec<String>,
}

/// What a drop reason means for a lab user, and what to do.
fn drop_advice(r: DropReason) -> &'static str {
    match r {
        DropReason::UnknownTip => "the active tip is not in the calibration's geometry: add it to `geometry.tips`",
        DropReason::Duplicate | DropReason::OutOfOrder => {
            "sequence counters or times that do not increase (e.g. one counter shared by several temperature sensors, or bags of two runs mixed)"
        }
        DropReason::TemperatureMissing => "a temperature the calibration needs was never recorded",
        DropReason::TemperatureStale => "a temperature the calibration needs is older than `join.temperature_max_age_s`",
        DropReason::NoCommand | DropReason::CommandGap => "the command stream is missing or has gaps",
        DropReason::NoProbe | DropReason::ProbeGap => "the probe stream is missing or has gaps",
        DropReason::Implausible | DropReason::ImplausibleOutput => "values outside the calibration's `limits`",
        DropReason::NonFinite => "NaN or infinite values",
        DropReason::BufferOverflow => "a stream stalled while the others went on",
        DropReason::UnknownSensor | DropReason::BadName => "temperature sensors with unknown or invalid names",
    }
}

fn describe_drops(bag: &str, st: &crate::corrector::Stats) -> Option<String> {
    let total = st.samples();
    let dropped = st.dropped_total();
    if dropped == 0 || (dropped as f64) < 1e-3 * total as f64 {
        return None;
    }
    let reasons: Vec<String> = DropReason::ALL
        .iter()
        .filter(|r| st.dropped[**r as usize] > 0)
        .map(|r| format!("{} {} ({})", st.dropped[*r as usize], r.name(), drop_advice(*r)))
        .collect();
    Some(format!(
        "{bag}: the corrector dropped {dropped} of {total} samples: {}",
        reasons.join("; ")
    ))
}

fn scan_phase(seg: &SegmentSpec, t_s: f64, speed_now: f64) -> Phase {
    if speed_now > 0.97 * seg.speed {
        Phase::Steady
    } else if t_s - seg.t0_s < seg.t1_s - t_s {
        Phase::SpinUp
    } else {
        Phase::SlowDown
    }
}

/// Options for building a dataset.
#[derive(Debug, Clone)]
pub struct BuildOptions {
    /// Keep every `stride`-th point of a scan (neighbouring points at 1 kHz are nearly the same).
    pub stride: usize,
    /// Hold out every other scan of each feature in bags not marked as validation when no
    /// validation bag is given.
    pub holdout_by_segment: bool,
    /// Artifact for bags without a program record.
    pub artifact: Option<FeatureSpec>,
    /// Extra temperature sensors to carry in the contexts (so candidate effects can use them).
    pub sensors: Vec<String>,
}

impl Default for BuildOptions {
    fn default() -> Self {
        BuildOptions {
            stride: 4,
            holdout_by_segment: true,
            artifact: None,
            sensors: vec![],
        }
    }
}

/// Corrects the bags with `cal` and collects the scan points.
pub fn build(bags: &[BagData], cal: &Calibration, o: &BuildOptions) -> Result<Dataset, LabError> {
    let mut model: Model = cal.build().map_err(LabError::Calibration)?;
    for s in &o.sensors {
        let present = bags.iter().any(|b| {
            b.samples
                .iter()
                .any(|x| matches!(x, Sample::Temperature(t) if &t.sensor == s))
        });
        if present {
            model.sensors.slot(s).map_err(LabError::Data)?;
        }
    }
    let model = Arc::new(model);
    let mut points = vec![];
    let mut features = vec![];
    let mut tracking = vec![];
    let mut noise_acc = (0.0, 0usize);
    let any_validation = bags.iter().any(|b| b.validation);
    let mut warnings = vec![];
    for (bi, bag) in bags.iter().enumerate() {
        let program = match (&bag.program, &o.artifact) {
            (Some(p), _) => p.clone(),
            (None, Some(a)) => ProgramSpec { program: "unknown".into(), features: vec![a.clone()], segments: vec![] },
            (None, None) => {
                return Err(LabError::Data(format!(
                    "{}: the bag does not say what was measured; name the artifact, e.g. --artifact ring:d=50.0012",
                    bag.name
                )))
            }
        };
        let base = features.len();
        for f in &program.features {
            features.push((bi, f.clone()));
        }
        let mut corr = Corrector::with_model(model.clone());
        corr.record_context(true);
        let mut out = crate::corrector::Output::default();
        corr.push_all(bag.samples.iter().cloned(), &mut out);
        corr.flush(&mut out);
        if bag.samples.is_empty() {
            warnings.push(format!(
                "{}: no samples of machine `{}` (the calibration's machine id): is it the right machine's bag?",
                bag.name, cal.machine_id
            ));
        }
        warnings.extend(describe_drops(&bag.name, corr.stats()));
        let mut unknown_segments = 0usize;
        // Group by segment, keep valid contact points of scans.
        let seg_of = |id: u32| program.segments.iter().find(|s| s.id == id);
        let mut scan_index: std::collections::BTreeMap<u32, usize> = Default::default();
        let mut i = 0;
        while i < out.points.len() {
            let seg_id = out.points[i].segment_id;
            let mut j = i;
            while j < out.points.len() && out.points[j].segment_id == seg_id {
                j += 1;
            }
            let (feature_idx, seg) = match seg_of(seg_id) {
                Some(s) if s.kind == SegmentKind::Scan => match s
                    .feature
                    .and_then(|f| program.features.iter().position(|x| x.id == f))
                {
                    Some(fi) => (Some(base + fi), Some(s.clone())),
                    None => (None, None),
                },
                Some(_) => (None, None),
                // No program segments: every contact point belongs to the one artifact.
                None if program.segments.is_empty() => (Some(base), None),
                None => {
                    unknown_segments += 1;
                    (None, None)
                }
            };
            // Tracking residual of the nominal model on this segment.
            let tr: f64 = out.contexts[i..j]
                .iter()
                .map(|c| (c.scale - c.est_pos).norm_squared())
                .sum::<f64>()
                / (j - i) as f64;
            tracking.push((bi, seg_id, tr.sqrt() * 1e3));
            if let Some(fi) = feature_idx {
                let k = scan_index.entry(fi as u32).or_insert(0);
                let held = if any_validation {
                    bag.validation
                } else {
                    o.holdout_by_segment && *k % 2 == 1
                };
                *k += 1;
                // Noise floor from the point-to-point scatter of the radial/normal coordinate.
                let f = &features[fi].1;
                let coord = |p: &crate::sample::CorrectedPoint| -> f64 {
                    match f.kind {
                        FeatureKind::Face => p.surface.dot(&Vec3::from(f.normal)),
                        _ => (p.surface - Vec3::from(f.nominal_center)).xy().norm(),
                    }
                };
                let ok: Vec<usize> = (i..j)
                    .filter(|&q| {
                        out.points[q].estimator_valid && out.points[q].normal != Vec3::zeros()
                    })
                    .collect();
                for w in ok.windows(3) {
                    if w[2] == w[0] + 2 {
                        let d2 = coord(&out.points[w[0]]) - 2.0 * coord(&out.points[w[1]])
                            + coord(&out.points[w[2]]);
                        noise_acc.0 += d2 * d2 / 6.0;
                        noise_acc.1 += 1;
                    }
                }
                for (n, &q) in ok.iter().enumerate() {
                    if n % o.stride.max(1) != 0 {
                        continue;
                    }
                    let p = &out.points[q];
                    let ctx = out.contexts[q];
                    let t_s = ctx.t_ns as f64 * 1e-9;
                    let (speed, direction, phase) = match &seg {
                        Some(s) => (s.speed, s.direction, scan_phase(s, t_s, ctx.est_vel.norm())),
                        None => (
                            ctx.est_vel.norm(),
                            (ctx.rot_axis.z.signum() as i32) * (ctx.arc_radius > 0.0) as i32,
                            Phase::Steady,
                        ),
                    };
                    points.push(LabPoint {
                        ctx,
                        surface: p.surface,
                        normal: p.normal,
                        feature: fi,
                        segment: seg_id,
                        bag: bi,
                        speed,
                        direction,
                        phase,
                        held_out: held,
                    });
                }
            }
            i = j;
        }
        if unknown_segments > 0 {
            warnings.push(format!(
                "{}: {unknown_segments} segment(s) of points are not in the bag's program record: not evaluated",
                bag.name
            ));
        }
    }
    if points.is_empty() {
        let why = if warnings.is_empty() {
            String::new()
        } else {
            format!(" — {}", warnings.join("; "))
        };
        return Err(LabError::Data(format!(
            "no scan points in contact with a known artifact: scan the artifact (ring gauge, sphere, straightedge) with the probe deflected{why}"
        )));
    }
    let noise = if noise_acc.1 > 0 {
        (noise_acc.0 / noise_acc.1 as f64).sqrt() * 1e3
    } else {
        0.0
    };
    Ok(Dataset {
        points,
        features,
        sensors: model.sensors.clone(),
        noise_floor_um: noise,
        tracking,
        calibration: cal.clone(),
        warnings,
    })
}
