//! Foxglove channels: corrected points, the artifact's nominal shape, alarms and the machine
//! frame in Foxglove's well-known schemas, so Foxglove (or any tool that knows them) shows a
//! bag, or the live view of `scancorr view`, in 3D.
//!
//! Channels, under `<prefix>/<machine>/foxglove/` (message and schema encoding `protobuf`):
//!
//! | suffix | schema | what |
//! |---|---|---|
//! | `points` | `foxglove.PointCloud` | corrected surface points, one message per run of points of one segment (at most a corrector batch): the fields of [`POINT_FIELDS`] |
//! | `deviation` | `scancorr.foxglove.DeviationSummary` | per `points` message: time, segment, count, min / max / RMS deviation (a plot against time) |
//! | `nominal` | `foxglove.SceneUpdate` | the program's features at their nominal place and size: a circle as a line loop, a sphere, a face as a thin square |
//! | `alarms` | `foxglove.Log` | estimator alarms: raised as `WARNING`, cleared as `INFO` |
//! | `frame` | `foxglove.FrameTransform` | the machine frame (`<machine>`) in `world`, identity: the frame every other channel is in |
//!
//! Positions are in metres (Foxglove's unit; mm ÷ 1000 as one IEEE division, so a reader
//! recovers the bag's millimetres exactly by × 1000 only up to rounding: compare in metres).
//! The deviation is in mm, from the nominal feature of the point's segment (see
//! `scancorr_core::lab::fit::deviation`: radial for a circle, along the normal for a face);
//! points of a segment with no feature have no `deviation_mm` field.
//!
//! Packed field types are Foxglove's `PackedElementField.NumericType` (UINT8 = 1 … FLOAT32 =
//! 7, FLOAT64 = 8), not ROS `PointField`'s (where FLOAT64 is 8 too but UINT32 is 6).
//!
//! The schemas are Foxglove's published `.proto` files, vendored in `clients/bag/foxglove/`
//! (MIT; source and commit in its README) and compiled by `protox` at build time. The
//! `foxglove` crate (the Foxglove SDK) was measured as the alternative: it adds ~20 crates
//! (its own tungstenite 0.30, sha1 0.11, serde_with, …) to a clean build for what a few
//! hundred lines do here.
use crate::{BagWriter, Result};

/// The generated prost types of the vendored schemas.
#[allow(missing_docs, clippy::all, clippy::pedantic)]
pub mod schema {
    /// Foxglove's messages (`foxglove.*`).
    pub mod foxglove {
        include!(concat!(env!("OUT_DIR"), "/foxglove.rs"));
    }
    /// scancorr's own message for the plot of deviation against time.
    pub mod scancorr {
        /// `scancorr.foxglove.*`.
        pub mod foxglove {
            include!(concat!(env!("OUT_DIR"), "/scancorr.foxglove.rs"));
        }
    }
    /// The well-known types the schemas use.
    pub mod google {
        /// `google.protobuf.*`.
        pub mod protobuf {
            include!(concat!(env!("OUT_DIR"), "/google.protobuf.rs"));
        }
    }
}

use prost::Message as _;
use schema::foxglove as fg;
use schema::google::protobuf::Timestamp;

/// The encoded `FileDescriptorSet` of every Foxglove channel's schema (with its imports).
pub const DESCRIPTOR_SET: &[u8] =
    include_bytes!(concat!(env!("OUT_DIR"), "/foxglove_descriptor.bin"));

/// One Foxglove channel of a machine.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Channel {
    /// `foxglove.PointCloud` of corrected points.
    Points,
    /// `scancorr.foxglove.DeviationSummary`, one per points message.
    Deviation,
    /// `foxglove.SceneUpdate` of the nominal features.
    Nominal,
    /// `foxglove.Log` of alarms.
    Alarms,
    /// `foxglove.FrameTransform` of the machine frame.
    Frame,
}

impl Channel {
    /// Every channel.
    pub const ALL: [Channel; 5] = [
        Channel::Points,
        Channel::Deviation,
        Channel::Nominal,
        Channel::Alarms,
        Channel::Frame,
    ];

    /// The topic's last part.
    pub fn suffix(self) -> &'static str {
        match self {
            Channel::Points => "points",
            Channel::Deviation => "deviation",
            Channel::Nominal => "nominal",
            Channel::Alarms => "alarms",
            Channel::Frame => "frame",
        }
    }

    /// `<prefix>/<machine>/foxglove/<suffix>`.
    pub fn topic(self, prefix: &str, machine: &str) -> String {
        format!("{prefix}/{machine}/foxglove/{}", self.suffix())
    }

    /// The fully-qualified protobuf message name (the schema name).
    pub fn schema_name(self) -> &'static str {
        match self {
            Channel::Points => "foxglove.PointCloud",
            Channel::Deviation => "scancorr.foxglove.DeviationSummary",
            Channel::Nominal => "foxglove.SceneUpdate",
            Channel::Alarms => "foxglove.Log",
            Channel::Frame => "foxglove.FrameTransform",
        }
    }
}

/// One encoded message of a Foxglove channel.
#[derive(Debug, Clone, PartialEq)]
pub struct Message {
    /// Its channel.
    pub channel: Channel,
    /// Its time (the sample time of its first point, the alarm's…), ns.
    pub t_ns: u64,
    /// The protobuf bytes.
    pub data: Vec<u8>,
}

/// A corrected point as the Foxglove channels carry it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CloudPoint {
    /// Point sequence number.
    pub seq: u64,
    /// Sample time, ns.
    pub t_ns: i64,
    /// Corrected surface point, mm.
    pub surface_mm: [f64; 3],
    /// Surface normal (unit).
    pub normal: [f64; 3],
    /// Deviation from the segment's nominal feature, mm; `None` without one.
    pub deviation_mm: Option<f64>,
    /// Calibration version that corrected it.
    pub calibration_version: u64,
    /// Program segment.
    pub segment_id: u32,
    /// Stylus tip.
    pub tip_id: u32,
    /// The estimator was valid (not flagged).
    pub valid: bool,
}

/// Foxglove's `NumericType` numbers (not ROS `PointField`'s).
pub use fg::packed_element_field::NumericType;

/// The packed fields of a `points` message: (name, byte offset, type). `deviation_mm` is
/// left out of a message whose segment has no nominal feature (its bytes are then zero).
pub const POINT_FIELDS: [(&str, u32, NumericType); 12] = [
    ("x", 0, NumericType::Float64),
    ("y", 8, NumericType::Float64),
    ("z", 16, NumericType::Float64),
    ("normal_x", 24, NumericType::Float64),
    ("normal_y", 32, NumericType::Float64),
    ("normal_z", 40, NumericType::Float64),
    ("deviation_mm", 48, NumericType::Float64),
    ("seq", 56, NumericType::Uint32),
    ("calibration_version", 60, NumericType::Uint32),
    ("segment_id", 64, NumericType::Uint32),
    ("tip_id", 68, NumericType::Uint32),
    ("valid", 72, NumericType::Uint8),
];

/// Bytes per point of a `points` message.
pub const POINT_STRIDE: u32 = 80;

fn timestamp(t_ns: i64) -> Timestamp {
    Timestamp {
        seconds: t_ns.div_euclid(1_000_000_000),
        nanos: t_ns.rem_euclid(1_000_000_000) as i32,
    }
}

/// Metres from millimetres.
pub fn metres(mm: f64) -> f64 {
    mm / 1000.0
}

fn identity_pose() -> fg::Pose {
    fg::Pose {
        position: Some(fg::Vector3::default()),
        orientation: Some(fg::Quaternion {
            x: 0.0,
            y: 0.0,
            z: 0.0,
            w: 1.0,
        }),
    }
}

/// One `points` message and its `deviation` summary per run of consecutive points of one
/// segment, appended to `out`.
pub fn points_messages(frame_id: &str, points: &[CloudPoint], out: &mut Vec<Message>) {
    let mut start = 0;
    while start < points.len() {
        let seg = points[start].segment_id;
        let has_dev = points[start].deviation_mm.is_some();
        let end = points[start..]
            .iter()
            .position(|p| p.segment_id != seg || p.deviation_mm.is_some() != has_dev)
            .map_or(points.len(), |n| start + n);
        let run = &points[start..end];
        out.extend(run_messages(frame_id, run, has_dev));
        start = end;
    }
}

fn run_messages(frame_id: &str, run: &[CloudPoint], has_dev: bool) -> [Message; 2] {
    let mut data = vec![0u8; run.len() * POINT_STRIDE as usize];
    let (mut lo, mut hi, mut sq) = (f64::INFINITY, f64::NEG_INFINITY, 0.0);
    for (p, b) in run.iter().zip(data.chunks_exact_mut(POINT_STRIDE as usize)) {
        let f64s = [
            metres(p.surface_mm[0]),
            metres(p.surface_mm[1]),
            metres(p.surface_mm[2]),
            p.normal[0],
            p.normal[1],
            p.normal[2],
            p.deviation_mm.unwrap_or(0.0),
        ];
        for (i, v) in f64s.iter().enumerate() {
            b[i * 8..i * 8 + 8].copy_from_slice(&v.to_le_bytes());
        }
        let u32s = [
            p.seq as u32,
            p.calibration_version.min(u32::MAX as u64) as u32,
            p.segment_id,
            p.tip_id,
        ];
        for (i, v) in u32s.iter().enumerate() {
            b[56 + i * 4..60 + i * 4].copy_from_slice(&v.to_le_bytes());
        }
        b[72] = p.valid as u8;
        if let Some(d) = p.deviation_mm {
            lo = lo.min(d);
            hi = hi.max(d);
            sq += d * d;
        }
    }
    let t_ns = run[0].t_ns;
    let fields = POINT_FIELDS
        .iter()
        .filter(|(name, _, _)| has_dev || *name != "deviation_mm")
        .map(|&(name, offset, ty)| fg::PackedElementField {
            name: name.into(),
            offset,
            r#type: ty as i32,
        })
        .collect();
    let cloud = fg::PointCloud {
        timestamp: Some(timestamp(t_ns)),
        frame_id: frame_id.into(),
        pose: Some(identity_pose()),
        point_stride: POINT_STRIDE,
        fields,
        data: data.into(),
    };
    let summary = schema::scancorr::foxglove::DeviationSummary {
        timestamp: Some(timestamp(t_ns)),
        segment_id: run[0].segment_id,
        points: run.len() as u32,
        first_seq: run[0].seq,
        has_deviation: has_dev,
        min_mm: if has_dev { lo } else { 0.0 },
        max_mm: if has_dev { hi } else { 0.0 },
        rms_mm: if has_dev {
            (sq / run.len() as f64).sqrt()
        } else {
            0.0
        },
    };
    let t = t_ns.max(0) as u64;
    [
        Message {
            channel: Channel::Points,
            t_ns: t,
            data: cloud.encode_to_vec(),
        },
        Message {
            channel: Channel::Deviation,
            t_ns: t,
            data: summary.encode_to_vec(),
        },
    ]
}

/// A nominal feature's shape, machine coordinates in mm.
#[derive(Debug, Clone, PartialEq)]
pub enum NominalShape {
    /// A circle in the XY plane (bore, boss, ring gauge).
    Circle {
        /// Centre, mm.
        center_mm: [f64; 3],
        /// Radius, mm.
        radius_mm: f64,
    },
    /// A sphere.
    Sphere {
        /// Centre, mm.
        center_mm: [f64; 3],
        /// Radius, mm.
        radius_mm: f64,
    },
    /// A plane face, shown as a square of `size_mm`.
    Face {
        /// A point of the face, mm.
        center_mm: [f64; 3],
        /// Unit normal out of the material.
        normal: [f64; 3],
        /// Side of the square shown, mm.
        size_mm: f64,
    },
}

/// A feature of the program with its nominal shape.
#[derive(Debug, Clone, PartialEq)]
pub struct NominalFeature {
    /// Entity id (e.g. `feature/0`).
    pub id: String,
    /// Shown as metadata (artifact, diameter…).
    pub metadata: Vec<(String, String)>,
    /// Its shape.
    pub shape: NominalShape,
}

/// The rotation taking +z to the unit vector `n`.
fn z_to(n: [f64; 3]) -> fg::Quaternion {
    // q = (z × n, 1 + z·n) normalised; opposite vectors turn about x.
    let (x, y, w) = (-n[1], n[0], 1.0 + n[2]);
    let norm = (x * x + y * y + w * w).sqrt();
    if norm < 1e-12 {
        return fg::Quaternion {
            x: 1.0,
            y: 0.0,
            z: 0.0,
            w: 0.0,
        };
    }
    fg::Quaternion {
        x: x / norm,
        y: y / norm,
        z: 0.0,
        w: w / norm,
    }
}

const NOMINAL_COLOR: fg::Color = fg::Color {
    r: 0.55,
    g: 0.6,
    b: 0.65,
    a: 0.6,
};

/// The `nominal` message: every feature as a scene entity in `frame_id`.
pub fn nominal_message(frame_id: &str, t_ns: i64, features: &[NominalFeature]) -> Message {
    let entities = features
        .iter()
        .map(|f| {
            let mut e = fg::SceneEntity {
                timestamp: Some(timestamp(t_ns)),
                frame_id: frame_id.into(),
                id: f.id.clone(),
                frame_locked: true,
                metadata: f
                    .metadata
                    .iter()
                    .map(|(k, v)| fg::KeyValuePair {
                        key: k.clone(),
                        value: v.clone(),
                    })
                    .collect(),
                ..Default::default()
            };
            let point = |c: [f64; 3]| fg::Vector3 {
                x: metres(c[0]),
                y: metres(c[1]),
                z: metres(c[2]),
            };
            match &f.shape {
                NominalShape::Circle {
                    center_mm,
                    radius_mm,
                } => {
                    let n = 360;
                    let points = (0..n)
                        .map(|i| {
                            let a = std::f64::consts::TAU * i as f64 / n as f64;
                            fg::Point3 {
                                x: metres(center_mm[0] + radius_mm * a.cos()),
                                y: metres(center_mm[1] + radius_mm * a.sin()),
                                z: metres(center_mm[2]),
                            }
                        })
                        .collect();
                    e.lines.push(fg::LinePrimitive {
                        r#type: fg::line_primitive::Type::LineLoop as i32,
                        pose: Some(identity_pose()),
                        thickness: 2.0,
                        scale_invariant: true,
                        points,
                        color: Some(NOMINAL_COLOR),
                        ..Default::default()
                    });
                }
                NominalShape::Sphere {
                    center_mm,
                    radius_mm,
                } => {
                    let d = metres(2.0 * radius_mm);
                    e.spheres.push(fg::SpherePrimitive {
                        pose: Some(fg::Pose {
                            position: Some(point(*center_mm)),
                            orientation: identity_pose().orientation,
                        }),
                        size: Some(fg::Vector3 { x: d, y: d, z: d }),
                        color: Some(NOMINAL_COLOR),
                    });
                }
                NominalShape::Face {
                    center_mm,
                    normal,
                    size_mm,
                } => {
                    let s = metres(*size_mm);
                    e.cubes.push(fg::CubePrimitive {
                        pose: Some(fg::Pose {
                            position: Some(point(*center_mm)),
                            orientation: Some(z_to(*normal)),
                        }),
                        size: Some(fg::Vector3 {
                            x: s,
                            y: s,
                            z: metres(0.01),
                        }),
                        color: Some(NOMINAL_COLOR),
                    });
                }
            }
            e
        })
        .collect();
    Message {
        channel: Channel::Nominal,
        t_ns: t_ns.max(0) as u64,
        data: fg::SceneUpdate {
            deletions: vec![],
            entities,
        }
        .encode_to_vec(),
    }
}

/// An `alarms` message.
pub fn log_message(t_ns: i64, warning: bool, name: &str, text: &str) -> Message {
    let level = if warning {
        fg::log::Level::Warning
    } else {
        fg::log::Level::Info
    };
    Message {
        channel: Channel::Alarms,
        t_ns: t_ns.max(0) as u64,
        data: fg::Log {
            timestamp: Some(timestamp(t_ns)),
            level: level as i32,
            message: text.into(),
            name: name.into(),
            file: String::new(),
            line: 0,
        }
        .encode_to_vec(),
    }
}

/// The `frame` message: the machine frame `frame_id` in `world`, identity.
pub fn frame_message(t_ns: i64, frame_id: &str) -> Message {
    let pose = identity_pose();
    Message {
        channel: Channel::Frame,
        t_ns: t_ns.max(0) as u64,
        data: fg::FrameTransform {
            timestamp: Some(timestamp(t_ns)),
            parent_frame_id: "world".into(),
            child_frame_id: frame_id.into(),
            translation: pose.position,
            rotation: pose.orientation,
        }
        .encode_to_vec(),
    }
}

/// A machine's Foxglove channels in a bag, registered on first use.
#[derive(Debug, Clone)]
pub struct BagChannels {
    prefix: String,
    machine: String,
    ids: [Option<u16>; Channel::ALL.len()],
}

impl BagChannels {
    /// The channels of `machine` under `prefix`; none is registered yet.
    pub fn new(prefix: &str, machine: &str) -> BagChannels {
        BagChannels {
            prefix: prefix.into(),
            machine: machine.into(),
            ids: [None; Channel::ALL.len()],
        }
    }

    /// Writes `m` on its channel (registering it first when new) at `log_time_ns`.
    pub fn write(&mut self, w: &mut BagWriter, log_time_ns: u64, m: &Message) -> Result<()> {
        let i = Channel::ALL
            .iter()
            .position(|c| *c == m.channel)
            .unwrap_or(0);
        let id = match self.ids[i] {
            Some(id) => id,
            None => {
                let topic = m.channel.topic(&self.prefix, &self.machine);
                let id = w.add_extra_channel(&topic, m.channel.schema_name(), DESCRIPTOR_SET)?;
                self.ids[i] = Some(id);
                id
            }
        };
        w.write_extra(id, log_time_ns, m.t_ns, &m.data)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn point(seq: u64, segment_id: u32, dev: Option<f64>) -> CloudPoint {
        CloudPoint {
            seq,
            t_ns: 1_000 + seq as i64,
            surface_mm: [seq as f64, -2.5, 100.0],
            normal: [0.0, 1.0, 0.0],
            deviation_mm: dev,
            calibration_version: 3,
            segment_id,
            tip_id: 1,
            valid: seq % 2 == 0,
        }
    }

    #[test]
    fn runs_split_at_segments_and_fields_follow_foxglove_numbering() {
        let pts = [
            point(0, 1, Some(0.001)),
            point(1, 1, Some(-0.002)),
            point(2, 2, None),
        ];
        let mut out = vec![];
        points_messages("m1", &pts, &mut out);
        assert_eq!(out.len(), 4);
        let c = fg::PointCloud::decode(&*out[0].data).unwrap();
        assert_eq!(c.data.len(), 2 * POINT_STRIDE as usize);
        let f: Vec<(String, u32, i32)> = c
            .fields
            .iter()
            .map(|f| (f.name.clone(), f.offset, f.r#type))
            .collect();
        assert_eq!(f[0], ("x".into(), 0, 8), "FLOAT64 is 8");
        assert_eq!(f[7], ("seq".into(), 56, 5), "UINT32 is 5");
        assert_eq!(f[11], ("valid".into(), 72, 1), "UINT8 is 1");
        let b = &c.data[POINT_STRIDE as usize..];
        assert_eq!(
            f64::from_le_bytes(b[0..8].try_into().unwrap()),
            1.0 / 1000.0
        );
        assert_eq!(f64::from_le_bytes(b[48..56].try_into().unwrap()), -0.002);
        assert_eq!(u32::from_le_bytes(b[56..60].try_into().unwrap()), 1);
        let s = schema::scancorr::foxglove::DeviationSummary::decode(&*out[1].data).unwrap();
        assert_eq!((s.points, s.min_mm, s.max_mm), (2, -0.002, 0.001));
        let c2 = fg::PointCloud::decode(&*out[2].data).unwrap();
        assert!(c2.fields.iter().all(|f| f.name != "deviation_mm"));
    }

    #[test]
    fn the_descriptor_set_holds_every_schema() {
        let has = |s: &str| DESCRIPTOR_SET.windows(s.len()).any(|w| w == s.as_bytes());
        for c in Channel::ALL {
            let (package, name) = c.schema_name().rsplit_once('.').unwrap();
            assert!(has(name) && has(package), "{c:?}");
        }
        assert!(has("google/protobuf/timestamp.proto"));
    }

    #[test]
    fn z_turns_onto_the_normal() {
        let q = z_to([0.0, -1.0, 0.0]);
        // Rotating z by q: the z column of the rotation matrix.
        let (x, y, z, w) = (q.x, q.y, q.z, q.w);
        let col = [
            2.0 * (x * z + w * y),
            2.0 * (y * z - w * x),
            1.0 - 2.0 * (x * x + y * y),
        ];
        assert!((col[0]).abs() < 1e-12 && (col[1] + 1.0).abs() < 1e-12 && col[2].abs() < 1e-12);
    }
}
