//! The scancorr wire contract: protobuf package `scancorr.v1`.
//!
//! Units: mm, s, °C, mm/s², degrees; `t_ns` is the machine controller's clock in ns.
//! The `.proto` source is `proto/scancorr/v1/scancorr.proto`; this crate holds the generated
//! prost types, the key-expression layout and the encoded `FileDescriptorSet` that MCAP bags
//! carry as their schema.
#![forbid(unsafe_code)]

pub mod names;
pub mod points;

/// Generated types of package `scancorr.v1`.
pub mod v1 {
    #![allow(missing_docs)]
    include!(concat!(env!("OUT_DIR"), "/scancorr.v1.rs"));
}

pub use prost;
pub use prost::Message;

/// The encoded `google.protobuf.FileDescriptorSet` of `scancorr/v1/scancorr.proto`
/// (schema data of MCAP channels with schema encoding `protobuf`).
pub const FILE_DESCRIPTOR_SET: &[u8] =
    include_bytes!(concat!(env!("OUT_DIR"), "/scancorr_v1_descriptor.bin"));

/// Protobuf package name; message full names are `scancorr.v1.<Message>`.
pub const PACKAGE: &str = "scancorr.v1";

/// Default key-expression prefix.
pub const DEFAULT_PREFIX: &str = "cmm";

/// The streams of one machine and their key-expression suffixes and message types.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Stream {
    /// `raw/command`: [`v1::CommandBatch`].
    Command,
    /// `raw/scale`: [`v1::ScaleBatch`].
    Scale,
    /// `raw/probe`: [`v1::ProbeBatch`].
    Probe,
    /// `raw/temperature`: [`v1::TemperatureBatch`].
    Temperature,
    /// `raw/distance`: [`v1::DistanceBatch`] (v1.2; not corrected).
    Distance,
    /// `raw/stage`: [`v1::StageBatch`] (v1.2; not corrected).
    Stage,
    /// `corrected/points`: [`v1::CorrectedPointBatch`].
    Points,
    /// `alarms/estimator`: [`v1::EstimatorAlarm`].
    Alarms,
}

impl Stream {
    /// Every raw stream a machine publishes: the four the corrector joins
    /// ([`Stream::CORRECTED`]) and the v1.2 measurement streams ([`Stream::MEASUREMENT`]).
    pub const RAW: [Stream; 6] = [
        Stream::Command,
        Stream::Scale,
        Stream::Probe,
        Stream::Temperature,
        Stream::Distance,
        Stream::Stage,
    ];
    /// The four raw streams the corrector joins into points.
    pub const CORRECTED: [Stream; 4] = [
        Stream::Command,
        Stream::Scale,
        Stream::Probe,
        Stream::Temperature,
    ];
    /// The raw streams of measurements the corrector does not use (v1.2): distance probes and
    /// the micro-stage of a straightness error-separation measurement.
    pub const MEASUREMENT: [Stream; 2] = [Stream::Distance, Stream::Stage];
    /// The two output streams.
    pub const OUTPUT: [Stream; 2] = [Stream::Points, Stream::Alarms];
    /// Every stream, raw then output.
    pub const ALL: [Stream; 8] = [
        Stream::Command,
        Stream::Scale,
        Stream::Probe,
        Stream::Temperature,
        Stream::Distance,
        Stream::Stage,
        Stream::Points,
        Stream::Alarms,
    ];

    /// Key-expression suffix after `<prefix>/<machine>/`.
    pub fn suffix(self) -> &'static str {
        match self {
            Stream::Command => "raw/command",
            Stream::Scale => "raw/scale",
            Stream::Probe => "raw/probe",
            Stream::Temperature => "raw/temperature",
            Stream::Distance => "raw/distance",
            Stream::Stage => "raw/stage",
            Stream::Points => "corrected/points",
            Stream::Alarms => "alarms/estimator",
        }
    }

    /// Full protobuf message name of the payload.
    pub fn message_name(self) -> &'static str {
        match self {
            Stream::Command => "scancorr.v1.CommandBatch",
            Stream::Scale => "scancorr.v1.ScaleBatch",
            Stream::Probe => "scancorr.v1.ProbeBatch",
            Stream::Temperature => "scancorr.v1.TemperatureBatch",
            Stream::Distance => "scancorr.v1.DistanceBatch",
            Stream::Stage => "scancorr.v1.StageBatch",
            Stream::Points => "scancorr.v1.CorrectedPointBatch",
            Stream::Alarms => "scancorr.v1.EstimatorAlarm",
        }
    }

    /// The stream tag (v1.1) its batches carry; `None` for the output streams, which have none.
    pub fn kind(self) -> Option<v1::StreamKind> {
        Some(match self {
            Stream::Command => v1::StreamKind::Command,
            Stream::Scale => v1::StreamKind::Scale,
            Stream::Probe => v1::StreamKind::Probe,
            Stream::Temperature => v1::StreamKind::Temperature,
            Stream::Distance => v1::StreamKind::Distance,
            Stream::Stage => v1::StreamKind::Stage,
            Stream::Points | Stream::Alarms => return None,
        })
    }

    /// The raw stream a stream tag names; `None` for `STREAM_KIND_UNSPECIFIED` and values this
    /// version does not know.
    pub fn of_kind(tag: i32) -> Option<Stream> {
        Stream::RAW
            .into_iter()
            .find(|s| s.kind().is_some_and(|k| k as i32 == tag))
    }

    /// The key expression of this stream for one machine.
    pub fn key(self, prefix: &str, machine: &str) -> String {
        format!("{prefix}/{machine}/{}", self.suffix())
    }

    /// Parses `<prefix>/<machine>/<suffix>` back into (machine, stream); `None` unless the
    /// machine id follows the [`names`] grammar (so a wildcard is never taken for a machine).
    pub fn parse_key<'a>(prefix: &str, key: &'a str) -> Option<(&'a str, Stream)> {
        let rest = key.strip_prefix(prefix)?.strip_prefix('/')?;
        let (machine, suffix) = rest.split_once('/')?;
        let stream = Stream::ALL.into_iter().find(|s| s.suffix() == suffix)?;
        names::is_valid(machine).then_some((machine, stream))
    }
}

/// The machine of `<prefix>/<machine>/<suffix>` (e.g. suffix `calibration` or `status`):
/// the prefix and the suffix are stripped once each, and the rest must be one valid name.
pub fn machine_of<'a>(prefix: &str, key: &'a str, suffix: &str) -> Option<&'a str> {
    let m = key
        .strip_prefix(prefix)?
        .strip_prefix('/')?
        .strip_suffix(suffix)?
        .strip_suffix('/')?;
    names::is_valid(m).then_some(m)
}

/// Key expression of a machine's calibration queryable for reading: the current document,
/// `?version=N`, `?history`.
pub fn calibration_key(prefix: &str, machine: &str) -> String {
    format!("{prefix}/{machine}/calibration")
}

/// Key expression of a machine's calibration queryable for changing it: a put (the document
/// as the query's payload) or `?rollback=N`. Apart from [`calibration_key`] so that access
/// control can give reading and changing to different roles.
pub fn calibration_write_key(prefix: &str, machine: &str) -> String {
    format!("{prefix}/{machine}/calibration/write")
}

/// The service's refusal of a change asked on the read key (`write` false) or of a read
/// asked on the write key (`write` true).
pub fn calibration_keys_misused(prefix: &str, machine: &str, write: bool) -> String {
    let (read, change) = (
        calibration_key(prefix, machine),
        calibration_write_key(prefix, machine),
    );
    if write {
        format!("{change} takes puts and rollbacks only; read the calibration and its history on {read}")
    } else {
        format!("calibrations are put and rolled back on {change}, not on {read} (the key that reads them)")
    }
}

/// The key of the services' health query, `<prefix>/@scancorrd/health`: every scancorrd on
/// the bus answers it (version, uptime, machines served). The `@` chunk is verbatim in zenoh,
/// so no machine's key (`<prefix>/*/…`) ever matches it.
pub fn health_key(prefix: &str) -> String {
    format!("{prefix}/@scancorrd/health")
}

#[cfg(test)]
mod tests {
    use super::*;
    use prost::Message;

    #[test]
    fn descriptor_set_names_every_stream_message() {
        let fds = prost_types_lite::decode_file_names(FILE_DESCRIPTOR_SET);
        assert!(
            fds.iter().any(|n| n == "scancorr/v1/scancorr.proto"),
            "{fds:?}"
        );
        for s in Stream::RAW.iter().chain(Stream::OUTPUT.iter()) {
            let short = s.message_name().rsplit('.').next().unwrap();
            assert!(
                FILE_DESCRIPTOR_SET
                    .windows(short.len())
                    .any(|w| w == short.as_bytes()),
                "{short} missing from descriptor set"
            );
        }
    }

    /// Minimal decoding of `FileDescriptorSet.file[].name` without pulling prost-types in.
    mod prost_types_lite {
        #[derive(Clone, PartialEq, prost::Message)]
        struct FileDescriptorProto {
            #[prost(string, optional, tag = "1")]
            name: Option<String>,
        }
        #[derive(Clone, PartialEq, prost::Message)]
        struct FileDescriptorSet {
            #[prost(message, repeated, tag = "1")]
            file: Vec<FileDescriptorProto>,
        }
        pub fn decode_file_names(b: &[u8]) -> Vec<String> {
            use prost::Message;
            FileDescriptorSet::decode(b)
                .unwrap()
                .file
                .into_iter()
                .filter_map(|f| f.name)
                .collect()
        }
    }

    #[test]
    fn batch_roundtrip() {
        let b = v1::ScaleBatch {
            samples: vec![v1::ScaleSample {
                machine_id: "m1".into(),
                seq: 7,
                t_ns: 1_000_000,
                x: 1.5,
                y: -2.0,
                z: 3.25,
            }],
            stream: v1::StreamKind::Scale as i32,
            columns: None,
        };
        let bytes = b.encode_to_vec();
        assert_eq!(v1::ScaleBatch::decode(bytes.as_slice()).unwrap(), b);
    }

    #[test]
    fn stream_lists_and_tags_agree() {
        let raw_output: Vec<Stream> = Stream::RAW.into_iter().chain(Stream::OUTPUT).collect();
        assert_eq!(raw_output, Stream::ALL);
        let split: Vec<Stream> = Stream::CORRECTED
            .into_iter()
            .chain(Stream::MEASUREMENT)
            .collect();
        assert_eq!(split, Stream::RAW);
        for s in Stream::RAW {
            let k = s.kind().expect("raw streams are tagged");
            assert_eq!(Stream::of_kind(k as i32), Some(s));
            // The tag's name is the stream's key suffix: `STREAM_KIND_DISTANCE` ↔ `raw/distance`.
            let name = k.as_str_name().trim_start_matches("STREAM_KIND_");
            assert_eq!(format!("raw/{}", name.to_ascii_lowercase()), s.suffix());
        }
        assert_eq!(v1::StreamKind::Distance as i32, 5);
        assert_eq!(v1::StreamKind::Stage as i32, 6);
        assert_eq!(Stream::Points.kind(), None);
        assert_eq!(Stream::of_kind(0), None);
        assert_eq!(Stream::of_kind(99), None);
        assert_eq!(
            Stream::parse_key("cmm", "cmm/m1/raw/distance"),
            Some(("m1", Stream::Distance))
        );
        assert_eq!(
            Stream::parse_key("cmm", "cmm/m1/raw/stage"),
            Some(("m1", Stream::Stage))
        );
    }

    #[test]
    fn keys_roundtrip() {
        for s in Stream::RAW.iter().chain(Stream::OUTPUT.iter()) {
            let k = s.key("cmm", "m7");
            assert_eq!(Stream::parse_key("cmm", &k), Some(("m7", *s)));
        }
        assert_eq!(Stream::parse_key("cmm", "cmm/m7/raw/other"), None);
        assert_eq!(Stream::parse_key("cmm", "other/m7/raw/scale"), None);
        assert_eq!(calibration_key("cmm", "m1"), "cmm/m1/calibration");
        assert_eq!(
            calibration_write_key("cmm", "m1"),
            "cmm/m1/calibration/write"
        );
        assert_eq!(
            machine_of("cmm", "cmm/m1/calibration/write", "calibration/write"),
            Some("m1")
        );
        assert_eq!(
            machine_of("cmm", "cmm/m1/calibration/write", "calibration"),
            None
        );
        assert_eq!(
            machine_of("cmm", "cmm/cmm/calibration", "calibration"),
            Some("cmm")
        );
        assert_eq!(machine_of("cmm", "cmm/**/calibration", "calibration"), None);
        assert_eq!(
            machine_of("cmm", "cmm/a/b/calibration", "calibration"),
            None
        );
        for wild in ["*", "**", "$*", "m$*x"] {
            assert_eq!(
                Stream::parse_key("cmm", &format!("cmm/{wild}/raw/scale")),
                None
            );
        }
        assert_eq!(
            Stream::parse_key("cmm", "cmm/cmm/raw/scale"),
            Some(("cmm", Stream::Scale))
        );
    }
}
