//! The lab's data: corrected scan points with their context, grouped by artifact feature.

use super::program::{FeatureKind, FeatureSpec, ProgramSpec, SegmentKind, SegmentSpec};
use super::LabError;
use crate::calib::{Calibration, Model};
use crate::corrector::{Corrector, DropReason};
use crate::sample::{Axis, PointContext, Sample, Vec3};
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

/// A bag's raw samples of one machine, replayed in bag order each time the lab corrects
/// them (so a long capture need not be held in memory decoded).
pub trait Samples: Send + Sync {
    /// Calls `f` with every sample, in bag order.
    fn replay(&self, f: &mut dyn FnMut(Sample)) -> Result<(), String>;
    /// Names of the temperature sensors that appear.
    fn sensors(&self) -> Vec<String>;
}

impl Samples for Vec<Sample> {
    fn replay(&self, f: &mut dyn FnMut(Sample)) -> Result<(), String> {
        for s in self {
            f(s.clone());
        }
        Ok(())
    }
    fn sensors(&self) -> Vec<String> {
        let mut v: Vec<String> = vec![];
        for s in self {
            if let Sample::Temperature(t) = s {
                if !v.contains(&t.sensor) {
                    v.push(t.sensor.clone());
                }
            }
        }
        v
    }
}

/// A bag's content, as the lab needs it.
#[derive(Clone)]
pub struct BagData {
    /// A name for messages (the file name).
    pub name: String,
    /// Raw samples of one machine in bag order.
    pub samples: Arc<dyn Samples>,
    /// The program, if the bag has one.
    pub program: Option<ProgramSpec>,
    /// Held out: used only to validate.
    pub validation: bool,
}

impl std::fmt::Debug for BagData {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("BagData")
            .field("name", &self.name)
            .field("program", &self.program.as_ref().map(|p| &p.program))
            .field("validation", &self.validation)
            .finish()
    }
}

/// The run of points being collected: consecutive points of one segment.
struct Run {
    seg_id: u32,
    feature: Option<usize>,
    seg: Option<SegmentSpec>,
    held: bool,
    track_ss: f64,
    track_n: usize,
    valid: usize,
}

/// Collects corrected points into lab points as they stream out of the corrector.
struct Runs<'a> {
    bag: usize,
    base: usize,
    program: &'a ProgramSpec,
    features: &'a [(usize, FeatureSpec)],
    stride: usize,
    held_default: bool,
    any_validation: bool,
    holdout_by_segment: bool,
    current: Option<Run>,
    scan_index: std::collections::BTreeMap<usize, usize>,
    /// Index of the next point in the bag (for the noise windows' adjacency).
    index: usize,
    /// The last two valid points of the run: (index, coordinate).
    last_two: [Option<(usize, f64)>; 2],
    unknown_segments: usize,
    points: &'a mut Vec<LabPoint>,
    tracking: &'a mut Vec<(usize, u32, f64)>,
    noise: &'a mut (f64, usize),
}

impl Runs<'_> {
    fn finish(&mut self) {
        if let Some(r) = self.current.take() {
            if r.track_n > 0 {
                self.tracking.push((
                    self.bag,
                    r.seg_id,
                    (r.track_ss / r.track_n as f64).sqrt() * 1e3,
                ));
            }
        }
        self.last_two = [None, None];
    }

    fn start(&mut self, seg_id: u32) {
        let program = self.program;
        let (feature, seg) = match program.segments.iter().find(|s| s.id == seg_id) {
            Some(s) if s.kind == SegmentKind::Scan => match s
                .feature
                .and_then(|f| program.features.iter().position(|x| x.id == f))
            {
                Some(fi) => (Some(self.base + fi), Some(s.clone())),
                None => (None, None),
            },
            Some(_) => (None, None),
            // No program segments: every contact point belongs to the one artifact.
            None if program.segments.is_empty() => (Some(self.base), None),
            None => {
                self.unknown_segments += 1;
                (None, None)
            }
        };
        let held = match feature {
            Some(fi) => {
                let k = self.scan_index.entry(fi).or_insert(0);
                let h = if self.any_validation {
                    self.held_default
                } else {
                    self.holdout_by_segment && *k % 2 == 1
                };
                *k += 1;
                h
            }
            None => false,
        };
        self.current = Some(Run {
            seg_id,
            feature,
            seg,
            held,
            track_ss: 0.0,
            track_n: 0,
            valid: 0,
        });
    }

    fn take(&mut self, out: &crate::corrector::Output) {
        for (p, ctx) in out.points.iter().zip(&out.contexts) {
            let index = self.index;
            self.index += 1;
            if self
                .current
                .as_ref()
                .is_none_or(|r| r.seg_id != p.segment_id)
            {
                self.finish();
                self.start(p.segment_id);
            }
            let r = self.current.as_mut().expect("a run was started");
            // Tracking residual of the nominal model on this segment.
            r.track_ss += (ctx.scale - ctx.est_pos).norm_squared();
            r.track_n += 1;
            let Some(fi) = r.feature else { continue };
            if !(p.estimator_valid && p.normal != Vec3::zeros()) {
                continue;
            }
            // Noise floor from the point-to-point scatter of the radial/normal coordinate:
            // second differences of three consecutive valid points.
            let f = &self.features[fi].1;
            let coord = match f.kind {
                FeatureKind::Face => p.surface.dot(&Vec3::from(f.normal)),
                _ => match super::program::circle_plane(f.normal) {
                    // A ring standing on its edge: the radius in its own plane.
                    Some((n, _, _)) => {
                        let d = p.surface - Vec3::from(f.nominal_center);
                        (d - n * d.dot(&n)).norm()
                    }
                    None => (p.surface - Vec3::from(f.nominal_center)).xy().norm(),
                },
            };
            if let [Some((i0, c0)), Some((_, c1))] = self.last_two {
                if index == i0 + 2 {
                    let d2 = c0 - 2.0 * c1 + coord;
                    self.noise.0 += d2 * d2 / 6.0;
                    self.noise.1 += 1;
                }
            }
            self.last_two = [self.last_two[1], Some((index, coord))];
            let n = r.valid;
            r.valid += 1;
            if n % self.stride != 0 {
                continue;
            }
            let t_s = ctx.t_ns as f64 * 1e-9;
            let (speed, direction, phase) = match &r.seg {
                Some(s) => (s.speed, s.direction, scan_phase(s, t_s, ctx.est_vel.norm())),
                None => (
                    ctx.est_vel.norm(),
                    (ctx.rot_axis.z.signum() as i32) * (ctx.arc_radius > 0.0) as i32,
                    Phase::Steady,
                ),
            };
            self.points.push(LabPoint {
                ctx: *ctx,
                surface: p.surface,
                normal: p.normal,
                feature: fi,
                segment: p.segment_id,
                bag: self.bag,
                speed,
                direction,
                phase,
                held_out: r.held,
            });
        }
    }
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
            "sequence counters or times that do not increase within a stream (e.g. a counter per temperature sensor instead of one for the stream, or bags of two runs mixed)"
        }
        DropReason::TemperatureMissing => "a temperature the calibration needs was never recorded",
        DropReason::TemperatureStale => "a temperature the calibration needs is older than `join.temperature_max_age_s`",
        DropReason::NoCommand | DropReason::CommandGap => "the command stream is missing or has gaps",
        DropReason::NoProbe | DropReason::ProbeGap => "the probe stream is missing or has gaps",
        DropReason::Implausible | DropReason::ImplausibleOutput => "values outside the calibration's `limits`",
        DropReason::ImplausibleJump => "scale or probe samples that left their stream's track and came back, faster than `limits.max_speed_mm_s`, `max_accel_mm_s2` or `max_head_rate_deg_s` allow (a damaged stream, or limits below the machine's)",
        DropReason::NonFinite => "NaN or infinite values",
        DropReason::BufferOverflow => "a stream stalled while the others went on",
        DropReason::UnknownSensor | DropReason::BadName => "temperature sensors with unknown or invalid names",
    }
}

fn describe_drops(bag: &str, st: &crate::corrector::Stats) -> Option<String> {
    let total = st.samples();
    let dropped = st.dropped_total();
    // A few hundred at the start (the first temperature is yet to come) are expected.
    if dropped == 0 || (dropped as f64) < 1e-2 * total as f64 {
        return None;
    }
    let reasons: Vec<String> = DropReason::ALL
        .iter()
        .filter(|r| st.dropped[**r as usize] > 0)
        .map(|r| {
            format!(
                "{} {} ({})",
                st.dropped[*r as usize],
                r.name(),
                drop_advice(*r)
            )
        })
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
        let present = bags
            .iter()
            .any(|b| b.samples.sensors().iter().any(|n| n == s));
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
    // Per bag: (produced points, effects inactive in it).
    let mut inactive_in: Vec<(bool, Vec<String>)> = vec![];
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
        let mut run = Runs {
            bag: bi,
            base,
            program: &program,
            features: &features,
            stride: o.stride.max(1),
            held_default: bag.validation,
            any_validation,
            holdout_by_segment: o.holdout_by_segment,
            current: None,
            scan_index: Default::default(),
            index: 0,
            last_two: [None, None],
            unknown_segments: 0,
            points: &mut points,
            tracking: &mut tracking,
            noise: &mut noise_acc,
        };
        // Streamed: the corrected points are collected as they come, so memory follows the
        // points kept (every `stride`-th contact point), not the length of the bag.
        let mut n_samples = 0u64;
        bag.samples
            .replay(&mut |x| {
                n_samples += 1;
                corr.push(x, &mut out);
                if out.points.len() >= 4096 {
                    run.take(&out);
                    out.clear();
                }
            })
            .map_err(|e| LabError::Data(format!("{}: {e}", bag.name)))?;
        corr.flush(&mut out);
        run.take(&out);
        run.finish();
        let unknown_segments = run.unknown_segments;
        if n_samples == 0 {
            warnings.push(format!(
                "{}: no samples of machine `{}` (the calibration's machine id): is it the right machine's bag?",
                bag.name, cal.machine_id
            ));
        }
        warnings.extend(describe_drops(&bag.name, corr.stats()));
        let inactive = corr.inactive_effects();
        inactive_in.push((corr.stats().points_out > 0, inactive));
        if unknown_segments > 0 {
            warnings.push(format!(
                "{}: {unknown_segments} segment(s) of points are not in the bag's program record: not evaluated",
                bag.name
            ));
        }
    }
    // An effect with parameters that contributed to no point of any bag: inactive for lack
    // of its signal (no arcs or curvature, no deflection, positions outside its table …).
    let with_points: Vec<&Vec<String>> = inactive_in
        .iter()
        .filter(|(p, _)| *p)
        .map(|(_, v)| v)
        .collect();
    // A feature map applies only to its own part program's scans: one that none of these
    // scans is is expected, and said once.
    let maps = cal.feature_map_ids();
    if let Some(first) = with_points.first() {
        let mut idle_maps = 0;
        for e in first.iter() {
            if with_points.iter().all(|v| v.contains(e)) {
                if maps.contains(e) {
                    idle_maps += 1;
                    continue;
                }
                warnings.push(format!(
                    "effect `{e}` contributed to no point of these bags: inactive for lack of its signal, so the lab cannot judge it here"
                ));
            }
        }
        if idle_maps > 0 {
            warnings.push(format!(
                "{idle_maps} feature map(s) of the calibration apply to none of these scans (a map applies only to its own part program's scans: segment ids, tip, place, speed)"
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

/// The span (min, max) of the scale readings along axis `a` over the dataset's points, mm.
pub(crate) fn axis_span(ds: &Dataset, a: Axis) -> (f64, f64) {
    ds.points.iter().fold((f64::MAX, f64::MIN), |(lo, hi), p| {
        (
            lo.min(p.ctx.scale[a.index()]),
            hi.max(p.ctx.scale[a.index()]),
        )
    })
}
