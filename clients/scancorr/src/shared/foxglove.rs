//! What `correct`, `record` and `view` show in Foxglove (`scancorr_bag::foxglove` encodes it):
//! each corrected point with its deviation from the nominal feature of its segment, the
//! program's features as the nominal scene, alarms as log lines. `correct` feeds [`BagSink`]
//! the core's output; `record` feeds it, and `view` feeds [`bus_messages`], the bus's.
//!
//! The deviation is the lab's (`scancorr_core::lab::fit::deviation`) against the feature at its
//! nominal place and size (the certified diameter where the program states one): radial in XY
//! for a bore or boss, along the normal for a face.

use anyhow::{Context, Result};
use prost::Message as _;
use scancorr_bag::foxglove::{self as fx, CloudPoint, NominalFeature, NominalShape};
use scancorr_bag::{BagReader, BagWriter, Stream};
use scancorr_core::lab::fit::{deviation, FeatureFit};
use scancorr_core::lab::program::{FeatureKind, ProgramSpec};
use scancorr_core::Vec3;
use scancorr_proto::v1;
use std::collections::BTreeMap;

/// Metadata record holding the program (JSON in its `json` entry).
pub const PROGRAM_METADATA: &str = "scancorr.program";

/// The nominal features of a program, by segment.
#[derive(Default, Clone)]
pub struct Nominal {
    fits: Vec<FeatureFit>,
    by_segment: BTreeMap<u32, usize>,
    scene: Vec<NominalFeature>,
    /// The `scancorr.program` record it was read from (empty when built from a program).
    record: BTreeMap<String, String>,
}

impl Nominal {
    /// From a program: each feature at its nominal place and size.
    pub fn from_program(p: &ProgramSpec) -> Nominal {
        let mut n = Nominal::default();
        let mut index = BTreeMap::new();
        for f in &p.features {
            let c = Vec3::from(f.nominal_center);
            let d = f.certificate_diameter_mm.unwrap_or(f.nominal_diameter_mm);
            let (fit, shape) = match f.kind {
                FeatureKind::Face => {
                    let nrm = Vec3::from(f.normal)
                        .try_normalize(1e-12)
                        .unwrap_or(Vec3::z());
                    let along = nrm
                        .cross(&Vec3::z())
                        .try_normalize(1e-9)
                        .unwrap_or(Vec3::x());
                    let fit = FeatureFit {
                        center: c,
                        radius: 0.0,
                        fixed_radius: true,
                        plane: [0.0; 3],
                        plane_z: false,
                        kind: f.kind,
                        axes: (nrm, along),
                        n: 0,
                    };
                    let shape = NominalShape::Face {
                        center_mm: f.nominal_center,
                        normal: [nrm.x, nrm.y, nrm.z],
                        size_mm: 40.0,
                    };
                    (fit, shape)
                }
                kind => {
                    let fit = FeatureFit {
                        center: c,
                        radius: d / 2.0,
                        fixed_radius: true,
                        plane: [0.0; 3],
                        plane_z: false,
                        kind,
                        axes: (Vec3::zeros(), Vec3::zeros()),
                        n: 0,
                    };
                    let shape = if f.artifact == "sphere" {
                        NominalShape::Sphere {
                            center_mm: f.nominal_center,
                            radius_mm: d / 2.0,
                        }
                    } else {
                        NominalShape::Circle {
                            center_mm: f.nominal_center,
                            radius_mm: d / 2.0,
                        }
                    };
                    (fit, shape)
                }
            };
            index.insert(f.id, n.fits.len());
            n.fits.push(fit);
            n.scene.push(NominalFeature {
                id: format!("feature/{}", f.id),
                metadata: vec![
                    ("artifact".into(), f.artifact.clone()),
                    ("kind".into(), format!("{:?}", f.kind).to_lowercase()),
                    ("diameter_mm".into(), d.to_string()),
                ],
                shape,
            });
        }
        for s in &p.segments {
            if let Some(i) = s.feature.and_then(|f| index.get(&f)) {
                n.by_segment.insert(s.id, *i);
            }
        }
        n
    }

    /// From a bag's metadata records (its `scancorr.program`); `None` without one.
    pub fn from_metadata<'a>(
        records: impl IntoIterator<Item = (&'a str, &'a BTreeMap<String, String>)>,
    ) -> Result<Option<Nominal>> {
        let Some((_, m)) = records
            .into_iter()
            .filter(|(n, _)| *n == PROGRAM_METADATA)
            .last()
        else {
            return Ok(None);
        };
        let Some(json) = m.get("json") else {
            return Ok(None);
        };
        let p: ProgramSpec = serde_json::from_str(json)
            .with_context(|| format!("the {PROGRAM_METADATA} record is not valid"))?;
        let mut n = Nominal::from_program(&p);
        n.record = m.clone();
        Ok(Some(n))
    }

    /// From the `scancorr.program` record of `bag` (the option `flag` names it in errors).
    pub fn from_bag(flag: &str, bag: &std::path::Path) -> Result<Nominal> {
        let r = BagReader::open(bag).with_context(|| format!("{flag} {}", bag.display()))?;
        let records = r.metadata().iter().map(|m| (m.name.as_str(), &m.entries));
        Nominal::from_metadata(records)
            .with_context(|| format!("{flag} {}", bag.display()))?
            .with_context(|| {
                format!(
                    "{flag} {}: the bag has no {PROGRAM_METADATA} record, so no nominal features",
                    bag.display()
                )
            })
    }

    /// The `scancorr.program` record it was read from, if any (a recorded bag keeps it, so
    /// its deviations say what they are from).
    pub fn record(&self) -> Option<&BTreeMap<String, String>> {
        (!self.record.is_empty()).then_some(&self.record)
    }

    /// The features as scene entities.
    pub fn scene(&self) -> &[NominalFeature] {
        &self.scene
    }

    /// Deviation of `surface` (mm) from the nominal feature of `segment`, mm.
    pub fn deviation(&self, segment: u32, surface: Vec3) -> Option<f64> {
        let f = &self.fits[*self.by_segment.get(&segment)?];
        let d = deviation(f, &surface).0;
        d.is_finite().then_some(d)
    }
}

/// A corrected point of the core, for the Foxglove channels.
pub fn cloud_point(p: &scancorr_core::CorrectedPoint, nominal: Option<&Nominal>) -> CloudPoint {
    CloudPoint {
        seq: p.seq,
        t_ns: p.t_ns,
        surface_mm: [p.surface.x, p.surface.y, p.surface.z],
        normal: [p.normal.x, p.normal.y, p.normal.z],
        deviation_mm: nominal.and_then(|n| n.deviation(p.segment_id, p.surface)),
        calibration_version: p.calibration_version,
        segment_id: p.segment_id,
        tip_id: p.tip_id,
        valid: p.estimator_valid,
    }
}

/// A corrected point of the wire, for the Foxglove channels.
pub fn cloud_point_wire(p: &v1::CorrectedPoint, nominal: Option<&Nominal>) -> CloudPoint {
    let v = |x: Option<v1::Vec3>| x.map_or([0.0; 3], |v| [v.x, v.y, v.z]);
    let s = v(p.surface);
    CloudPoint {
        seq: p.seq,
        t_ns: p.t_ns,
        surface_mm: s,
        normal: v(p.normal),
        deviation_mm: nominal.and_then(|n| n.deviation(p.segment_id, Vec3::from(s))),
        calibration_version: p.calibration_version,
        segment_id: p.segment_id,
        tip_id: p.tip_id,
        valid: p.estimator_valid,
    }
}

/// An alarm as a log line: (warning, text).
pub fn alarm_text(a: &v1::EstimatorAlarm) -> (bool, String) {
    let text = format!(
        "{} axis {:?}: estimated {:.1} vs measured {:.1} mm/s² (difference {:.1}, threshold {:.0}), action {:?}, calibration v{}",
        if a.raised { "RAISED" } else { "cleared" },
        a.axis(),
        a.estimated_accel,
        a.measured_accel,
        a.difference,
        a.threshold,
        a.action(),
        a.calibration_version
    );
    (a.raised, text)
}

/// The Foxglove messages of one bus message of `machine` (`stream`, its payload): a corrected
/// point batch or an alarm, appended to `out` (`points` is scratch). False when it is neither or
/// does not decode. What `record` writes and `view` serves.
pub fn bus_messages(
    machine: &str,
    stream: Stream,
    payload: &[u8],
    nominal: Option<&Nominal>,
    points: &mut Vec<CloudPoint>,
    out: &mut Vec<fx::Message>,
) -> bool {
    match stream {
        Stream::Points => {
            let Ok(batch) = v1::CorrectedPointBatch::decode(payload)
                .map_err(|e| e.to_string())
                .and_then(|b| b.into_points().map_err(|e| e.to_string()))
            else {
                return false;
            };
            points.clear();
            points.extend(batch.iter().map(|p| cloud_point_wire(p, nominal)));
            fx::points_messages(machine, points, out);
        }
        Stream::Alarms => {
            let Ok(a) = v1::EstimatorAlarm::decode(payload) else {
                return false;
            };
            let (warn, text) = alarm_text(&a);
            out.push(fx::log_message(a.t_ns, warn, machine, &text));
        }
        _ => return false,
    }
    true
}

/// The Foxglove channels of one machine in a bag being written: the machine frame and the
/// nominal scene with the first batch, then each batch's points and alarms.
pub struct BagSink {
    channels: fx::BagChannels,
    nominal: Option<Nominal>,
    machine: String,
    started: bool,
    points: Vec<CloudPoint>,
    messages: Vec<fx::Message>,
}

impl BagSink {
    /// The channels of `machine` under `prefix`, deviations from `nominal` when known.
    pub fn new(prefix: &str, machine: &str, nominal: Option<Nominal>) -> BagSink {
        BagSink {
            channels: fx::BagChannels::new(prefix, machine),
            nominal,
            machine: machine.into(),
            started: false,
            points: vec![],
            messages: vec![],
        }
    }

    /// The frame and the nominal scene, once, at `t0` (ns).
    fn start(&mut self, t0: i64) {
        if !self.started {
            self.started = true;
            self.messages.push(fx::frame_message(t0, &self.machine));
            if let Some(n) = &self.nominal {
                self.messages
                    .push(fx::nominal_message(&self.machine, t0, n.scene()));
            }
        }
    }

    fn flush(&mut self, w: &mut BagWriter, log_time: u64) -> Result<()> {
        for m in &self.messages {
            self.channels.write(w, log_time, m)?;
        }
        self.messages.clear();
        Ok(())
    }

    /// Writes one batch of the corrector's output at `log_time` (ns).
    pub fn write(
        &mut self,
        w: &mut BagWriter,
        log_time: u64,
        points: &[scancorr_core::CorrectedPoint],
        alarms: &[scancorr_core::Alarm],
    ) -> Result<()> {
        self.messages.clear();
        let t0 = points
            .first()
            .map(|p| p.t_ns)
            .or(alarms.first().map(|a| a.t_ns))
            .unwrap_or(0);
        self.start(t0);
        self.points.clear();
        let nominal = self.nominal.as_ref();
        self.points
            .extend(points.iter().map(|p| cloud_point(p, nominal)));
        fx::points_messages(&self.machine, &self.points, &mut self.messages);
        for a in alarms {
            let (warn, text) = alarm_text(&scancorr_core::wire::alarm(a, &self.machine));
            self.messages
                .push(fx::log_message(a.t_ns, warn, &self.machine, &text));
        }
        self.flush(w, log_time)
    }

    /// Writes the Foxglove messages of one bus message (see [`bus_messages`]) at `log_time`
    /// (ns); false when it is neither points nor an alarm, or does not decode.
    pub fn write_bus(
        &mut self,
        w: &mut BagWriter,
        log_time: u64,
        stream: Stream,
        payload: &[u8],
    ) -> Result<bool> {
        self.messages.clear();
        let nominal = self.nominal.as_ref();
        let (points, out) = (&mut self.points, &mut self.messages);
        if !bus_messages(&self.machine, stream, payload, nominal, points, out) {
            return Ok(false);
        }
        if !self.started {
            // The frame and the scene first, at the time of the first message.
            let body = std::mem::take(&mut self.messages);
            self.start(body.first().map_or(0, |m| m.t_ns as i64));
            self.messages.extend(body);
        }
        self.flush(w, log_time)?;
        Ok(true)
    }
}

/// The Foxglove channels of every machine of a bag recorded from the bus (`scancorr record`):
/// a [`BagSink`] per machine, as its first points or alarm arrive.
pub struct BusSinks {
    prefix: String,
    nominal: Option<Nominal>,
    sinks: BTreeMap<String, BagSink>,
}

impl BusSinks {
    /// The channels of the machines under `prefix`, deviations from `nominal` when given.
    pub fn new(prefix: &str, nominal: Option<Nominal>) -> BusSinks {
        BusSinks {
            prefix: prefix.into(),
            nominal,
            sinks: BTreeMap::new(),
        }
    }

    /// Writes `nominal`'s program record (when read from a bag), so the recorded bag says
    /// what its deviations are from.
    pub fn write_program(&self, w: &mut BagWriter) -> Result<()> {
        if let Some(r) = self.nominal.as_ref().and_then(Nominal::record) {
            w.write_metadata(PROGRAM_METADATA, r)?;
        }
        Ok(())
    }

    /// Writes the Foxglove messages of one bus message of `machine` at `log_time` (ns); false
    /// when it is neither points nor an alarm, or does not decode.
    pub fn write(
        &mut self,
        w: &mut BagWriter,
        log_time: u64,
        machine: &str,
        stream: Stream,
        payload: &[u8],
    ) -> Result<bool> {
        if !matches!(stream, Stream::Points | Stream::Alarms) {
            return Ok(false);
        }
        if !self.sinks.contains_key(machine) {
            let s = BagSink::new(&self.prefix, machine, self.nominal.clone());
            self.sinks.insert(machine.to_string(), s);
        }
        match self.sinks.get_mut(machine) {
            Some(s) => s.write_bus(w, log_time, stream, payload),
            None => Ok(false),
        }
    }
}
