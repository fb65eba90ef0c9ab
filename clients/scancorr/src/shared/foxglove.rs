//! What `correct` and `view` show in Foxglove (`scancorr_bag::foxglove` encodes it): each
//! corrected point with its deviation from the nominal feature of its segment, the program's
//! features as the nominal scene, alarms as log lines.
//!
//! The deviation is the lab's (`scancorr_core::lab::fit::deviation`) against the feature at its
//! nominal place and size (the certified diameter where the program states one): radial in XY
//! for a bore or boss, along the normal for a face.

use anyhow::{Context, Result};
use scancorr_bag::foxglove::{CloudPoint, NominalFeature, NominalShape};
use scancorr_core::lab::fit::{deviation, FeatureFit};
use scancorr_core::lab::program::{FeatureKind, ProgramSpec};
use scancorr_core::Vec3;
use scancorr_proto::v1;
use std::collections::BTreeMap;

/// Metadata record holding the program (JSON in its `json` entry).
pub const PROGRAM_METADATA: &str = "scancorr.program";

/// The nominal features of a program, by segment.
#[derive(Default)]
pub struct Nominal {
    fits: Vec<FeatureFit>,
    by_segment: BTreeMap<u32, usize>,
    scene: Vec<NominalFeature>,
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
        Ok(Some(Nominal::from_program(&p)))
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

/// The Foxglove channels of one machine in a bag being written: the machine frame and the
/// nominal scene with the first batch, then each batch's points and alarms.
pub struct BagSink {
    channels: scancorr_bag::foxglove::BagChannels,
    nominal: Option<Nominal>,
    machine: String,
    started: bool,
    points: Vec<CloudPoint>,
    messages: Vec<scancorr_bag::foxglove::Message>,
}

impl BagSink {
    /// The channels of `machine` under `prefix`, deviations from `nominal` when known.
    pub fn new(prefix: &str, machine: &str, nominal: Option<Nominal>) -> BagSink {
        BagSink {
            channels: scancorr_bag::foxglove::BagChannels::new(prefix, machine),
            nominal,
            machine: machine.into(),
            started: false,
            points: vec![],
            messages: vec![],
        }
    }

    /// Writes one batch of the corrector's output at `log_time` (ns).
    pub fn write(
        &mut self,
        w: &mut scancorr_bag::BagWriter,
        log_time: u64,
        points: &[scancorr_core::CorrectedPoint],
        alarms: &[scancorr_core::Alarm],
    ) -> Result<()> {
        use scancorr_bag::foxglove as fx;
        self.messages.clear();
        if !self.started {
            self.started = true;
            let t0 = points
                .first()
                .map(|p| p.t_ns)
                .or(alarms.first().map(|a| a.t_ns))
                .unwrap_or(0);
            self.messages.push(fx::frame_message(t0, &self.machine));
            if let Some(n) = &self.nominal {
                self.messages
                    .push(fx::nominal_message(&self.machine, t0, n.scene()));
            }
        }
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
        for m in &self.messages {
            self.channels.write(w, log_time, m)?;
        }
        Ok(())
    }
}
