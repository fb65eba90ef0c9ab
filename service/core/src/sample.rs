//! Samples in, points and alarms out: the core's plain data types.
//!
//! These mirror the wire messages of `scancorr.v1` but carry no machine id and no strings on
//! the hot path (one core instance serves one machine); the shell converts between the two.

use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};

/// A point or vector in machine axes, mm (or mm/s, mm/s² where stated).
pub type Vec3 = Vector3<f64>;

/// A machine axis.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Axis {
    /// X axis.
    X,
    /// Y axis.
    Y,
    /// Z axis.
    Z,
}

impl Axis {
    /// All three axes in index order.
    pub const ALL: [Axis; 3] = [Axis::X, Axis::Y, Axis::Z];
    /// Index 0, 1, 2.
    pub fn index(self) -> usize {
        self as usize
    }
    /// Lower-case name.
    pub fn name(self) -> &'static str {
        ["x", "y", "z"][self as usize]
    }
    /// Unit vector along this axis.
    pub fn unit(self) -> Vec3 {
        let mut v = Vec3::zeros();
        v[self as usize] = 1.0;
        v
    }
}

/// Commanded probe position from the controller's scanning-vector command.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CommandSample {
    /// Per-stream sequence number (duplicate and gap detection).
    pub seq: u64,
    /// Controller time, ns.
    pub t_ns: i64,
    /// Commanded probe position, mm.
    pub pos: Vec3,
    /// Commanded arc centre, mm (meaningful when `arc_radius` > 0).
    pub arc_center: Vec3,
    /// Commanded arc radius Rs, mm; 0 when the segment is not an arc.
    pub arc_radius: f64,
    /// Scan segment id (the lab bins residuals by it).
    pub segment_id: u32,
}

/// Drive-scale readings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScaleSample {
    /// Per-stream sequence number.
    pub seq: u64,
    /// Controller time, ns.
    pub t_ns: i64,
    /// Scale readings, mm.
    pub pos: Vec3,
}

/// Analog probe reading and the probe configuration active at that time.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProbeSample {
    /// Per-stream sequence number.
    pub seq: u64,
    /// Controller time, ns.
    pub t_ns: i64,
    /// Stylus deflection in probe axes (u, v, w), mm.
    pub deflection: Vec3,
    /// Active tip id (selects geometry and the probe model G2).
    pub tip_id: u32,
    /// Head swivel angle A1 about machine Z, degrees.
    pub head_a1_deg: f64,
    /// Head tilt angle A2, degrees.
    pub head_a2_deg: f64,
    /// The probing force the probe reports, N (a force probe or an active probe in
    /// constant-force mode, wire v1.5); `None` without a force signal.
    pub force_n: Option<f64>,
}

/// One temperature reading.
#[derive(Debug, Clone, PartialEq)]
pub struct TemperatureSample {
    /// Per-stream sequence number (one counter for all sensors of the machine).
    pub seq: u64,
    /// Controller time, ns.
    pub t_ns: i64,
    /// Sensor name (`stylus`, `scale_x`, `air`, …).
    pub sensor: String,
    /// Reading, °C.
    pub celsius: f64,
}

/// Any raw input sample.
#[derive(Debug, Clone, PartialEq)]
pub enum Sample {
    /// From `raw/command`.
    Command(CommandSample),
    /// From `raw/scale`.
    Scale(ScaleSample),
    /// From `raw/probe`.
    Probe(ProbeSample),
    /// From `raw/temperature`.
    Temperature(TemperatureSample),
}

impl Sample {
    /// Controller time of the sample.
    pub fn t_ns(&self) -> i64 {
        match self {
            Sample::Command(s) => s.t_ns,
            Sample::Scale(s) => s.t_ns,
            Sample::Probe(s) => s.t_ns,
            Sample::Temperature(s) => s.t_ns,
        }
    }
    /// The sequence number within its stream.
    pub fn seq(&self) -> u64 {
        match self {
            Sample::Command(s) => s.seq,
            Sample::Scale(s) => s.seq,
            Sample::Probe(s) => s.seq,
            Sample::Temperature(s) => s.seq,
        }
    }
    /// Whether every value is finite (and an arc radius is not negative).
    pub fn is_finite(&self) -> bool {
        match self {
            Sample::Command(c) => {
                c.pos
                    .iter()
                    .chain(c.arc_center.iter())
                    .all(|v| v.is_finite())
                    && c.arc_radius.is_finite()
                    && c.arc_radius >= 0.0
            }
            Sample::Scale(c) => c.pos.iter().all(|v| v.is_finite()),
            Sample::Probe(c) => {
                c.deflection.iter().all(|v| v.is_finite())
                    && c.head_a1_deg.is_finite()
                    && c.head_a2_deg.is_finite()
                    && c.force_n.is_none_or(f64::is_finite)
            }
            Sample::Temperature(c) => c.celsius.is_finite(),
        }
    }
    /// Stream index: 0 command, 1 scale, 2 probe, 3 temperature.
    pub fn stream(&self) -> StreamId {
        match self {
            Sample::Command(_) => StreamId::Command,
            Sample::Scale(_) => StreamId::Scale,
            Sample::Probe(_) => StreamId::Probe,
            Sample::Temperature(_) => StreamId::Temperature,
        }
    }
}

/// The four raw streams.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum StreamId {
    /// Commanded path.
    Command,
    /// Drive scales.
    Scale,
    /// Probe deflection.
    Probe,
    /// Temperatures.
    Temperature,
}

impl StreamId {
    /// All four, in index order.
    pub const ALL: [StreamId; 4] = [
        StreamId::Command,
        StreamId::Scale,
        StreamId::Probe,
        StreamId::Temperature,
    ];
    /// Lower-case name.
    pub fn name(self) -> &'static str {
        ["command", "scale", "probe", "temperature"][self as usize]
    }
}

/// What a raised estimator alarm does to the points.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AlarmAction {
    /// Points keep all corrections and are marked `estimator_valid = false`.
    #[default]
    Flag,
    /// Dynamic corrections are left out while raised (points also marked invalid).
    Suspend,
}

/// A corrected surface point.
#[derive(Debug, Clone, PartialEq)]
pub struct CorrectedPoint {
    /// Consecutive number of produced points (drops do not consume numbers).
    pub seq: u64,
    /// Time of the scale sample, ns.
    pub t_ns: i64,
    /// Seq of the scale sample.
    pub sample_seq: u64,
    /// Corrected contact point on the surface, mm.
    pub surface: Vec3,
    /// Corrected tip centre, mm.
    pub tip_center: Vec3,
    /// Unit surface normal out of the material, or zero when not in contact.
    pub normal: Vec3,
    /// Correction of each effect of the calibration, same order as its `effects` list
    /// (zero for a dynamic effect suspended by an alarm).
    pub corrections: Vec<Vec3>,
    /// Calibration version used.
    pub calibration_version: u64,
    /// False while an estimator alarm is raised or the estimator is settling.
    pub estimator_valid: bool,
    /// Command segment id at this time.
    pub segment_id: u32,
    /// Active tip.
    pub tip_id: u32,
}

/// An estimator-validity alarm being raised or cleared.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Alarm {
    /// Consecutive number of alarms of this corrector.
    pub seq: u64,
    /// Time of the scale sample at which it changed, ns.
    pub t_ns: i64,
    /// Raised (true) or cleared (false).
    pub raised: bool,
    /// Axis.
    pub axis: Axis,
    /// Filtered estimated acceleration, mm/s².
    pub estimated_accel: f64,
    /// Filtered measured acceleration, mm/s².
    pub measured_accel: f64,
    /// estimated − measured, mm/s².
    pub difference: f64,
    /// Threshold in force, mm/s².
    pub threshold: f64,
    /// Action in force.
    pub action: AlarmAction,
    /// Calibration version in force.
    pub calibration_version: u64,
}

/// Everything known about one point when it is corrected: the signals effects are functions
/// of, and the features the lab bins residuals by.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PointContext {
    /// Time, ns.
    pub t_ns: i64,
    /// Scale readings (measured carriage position), mm.
    pub scale: Vec3,
    /// Commanded position interpolated to this time, mm.
    pub command: Vec3,
    /// Estimated position E = G_N·C, mm.
    pub est_pos: Vec3,
    /// Estimated velocity, mm/s.
    pub est_vel: Vec3,
    /// Estimated acceleration, mm/s².
    pub est_acc: Vec3,
    /// Arc centre, mm: the commanded one, or, when the command carries no arc, the centre of
    /// the estimated path's curvature (zero when neither).
    pub arc_center: Vec3,
    /// Arc radius Rs, mm: commanded, or estimated from the path's curvature; 0 off arcs.
    pub arc_radius: f64,
    /// Rotation frequency on arcs, Hz (0 off arcs).
    pub f_hz: f64,
    /// Unit angular-velocity direction on arcs (right-hand rule), zero off arcs or at rest.
    pub rot_axis: Vec3,
    /// Stylus deflection, probe axes, mm.
    pub deflection_probe: Vec3,
    /// Stylus deflection, machine axes, mm.
    pub deflection: Vec3,
    /// The probing force the probe reports, N, interpolated to this time like the
    /// deflection; `None` without a force signal.
    pub force_n: Option<f64>,
    /// Rotation machine_from_probe of the articulating head.
    pub machine_from_probe: Matrix3<f64>,
    /// Nominal shank part of the tip offset (l1), machine axes, mm.
    pub tip_shank: Vec3,
    /// Nominal bent part of the tip offset (l2, l3), machine axes, mm.
    pub tip_bent: Vec3,
    /// Tip radius, mm.
    pub tip_radius: f64,
    /// Active tip.
    pub tip_id: u32,
    /// Head angles, degrees.
    pub head_a1_deg: f64,
    /// Head angles, degrees.
    pub head_a2_deg: f64,
    /// Segment id.
    pub segment_id: u32,
    /// Temperatures by sensor slot (see [`crate::corrector::Corrector::sensor_names`]), °C.
    pub temps: [f64; MAX_SENSORS],
    /// Bit i set when `temps[i]` holds a reading.
    pub temps_valid: u16,
}

/// Most temperature sensors one calibration can refer to.
pub const MAX_SENSORS: usize = 12;

impl PointContext {
    /// Tip offset (shank + bent), machine axes, mm.
    pub fn tip_offset(&self) -> Vec3 {
        self.tip_shank + self.tip_bent
    }
    /// A context at rest at the origin, for tests and examples.
    pub fn at_rest(pos: Vec3) -> Self {
        PointContext {
            t_ns: 0,
            scale: pos,
            command: pos,
            est_pos: pos,
            est_vel: Vec3::zeros(),
            est_acc: Vec3::zeros(),
            arc_center: Vec3::zeros(),
            arc_radius: 0.0,
            f_hz: 0.0,
            rot_axis: Vec3::zeros(),
            deflection_probe: Vec3::zeros(),
            deflection: Vec3::zeros(),
            force_n: None,
            machine_from_probe: Matrix3::identity(),
            tip_shank: Vec3::new(0.0, 0.0, -50.0),
            tip_bent: Vec3::zeros(),
            tip_radius: 1.0,
            tip_id: 1,
            head_a1_deg: 0.0,
            head_a2_deg: 0.0,
            segment_id: 0,
            temps: [20.0; MAX_SENSORS],
            temps_valid: 0,
        }
    }
}
