//! The batch messages a bag carries: a typed enum for decoding, a trait for typed writing and a
//! cheap look into encoded batches (sample count, first sample time) without decoding them.
use crate::BagError;
use prost::Message;
use scancorr_proto::v1::{
    CommandBatch, CorrectedPointBatch, DistanceBatch, EstimatorAlarm, ProbeBatch, ScaleBatch,
    StageBatch, StreamKind, TemperatureBatch,
};
use scancorr_proto::Stream;

/// One decoded bag message: the batch type is fixed by the stream it was recorded on.
///
/// Exists so readers get a single typed value per message instead of matching on the stream
/// and decoding by hand.
#[derive(Debug, Clone, PartialEq)]
pub enum RawBatch {
    /// `raw/command`.
    Command(CommandBatch),
    /// `raw/scale`.
    Scale(ScaleBatch),
    /// `raw/probe`.
    Probe(ProbeBatch),
    /// `raw/temperature`.
    Temperature(TemperatureBatch),
    /// `raw/distance` (v1.2).
    Distance(DistanceBatch),
    /// `raw/stage` (v1.2).
    Stage(StageBatch),
    /// `corrected/points`.
    Points(CorrectedPointBatch),
    /// `alarms/estimator` (one alarm per message).
    Alarm(EstimatorAlarm),
}

impl RawBatch {
    /// Decodes `payload` as the message type of `stream`.
    pub fn decode(stream: Stream, payload: &[u8]) -> Result<Self, BagError> {
        Self::decode_inner(stream, payload).map_err(|error| BagError::Decode {
            message: stream.message_name(),
            context: String::new(),
            error,
        })
    }

    /// Decodes `payload` as the message type of `stream` after checking the stream tag of a
    /// raw batch (v1.1): a batch whose tag names another stream (a `DistanceBatch` recorded on
    /// a `raw/stage` key) is [`BagError::WrongStream`], not decoded as the wrong message. An
    /// untagged batch is taken as `stream`'s: the channel names its type (bags recorded before
    /// v1.1). `context` goes into the errors (e.g. ` on cmm/m1/raw/stage at log time 5`).
    pub fn decode_checked(stream: Stream, payload: &[u8], context: &str) -> Result<Self, BagError> {
        let malformed = |error| BagError::Decode {
            message: stream.message_name(),
            context: context.to_owned(),
            error,
        };
        if let Some(kind) = stream.kind() {
            let tag = match stream_tag(payload) {
                Some(tag) => tag,
                // Bytes the walker does not take (e.g. groups) or that are not protobuf at
                // all: prost reads the tag, or names what is wrong.
                None => Self::decode_inner(stream, payload)
                    .map_err(malformed)?
                    .tag()
                    .unwrap_or_default(),
            };
            if tag != StreamKind::Unspecified as i32 && tag != kind as i32 {
                return Err(BagError::WrongStream {
                    expected: stream,
                    found: tag_name(tag),
                    context: context.to_owned(),
                });
            }
        }
        Self::decode_inner(stream, payload).map_err(malformed)
    }

    pub(crate) fn decode_inner(stream: Stream, b: &[u8]) -> Result<Self, prost::DecodeError> {
        Ok(match stream {
            Stream::Command => RawBatch::Command(CommandBatch::decode(b)?),
            Stream::Scale => RawBatch::Scale(ScaleBatch::decode(b)?),
            Stream::Probe => RawBatch::Probe(ProbeBatch::decode(b)?),
            Stream::Temperature => RawBatch::Temperature(TemperatureBatch::decode(b)?),
            Stream::Distance => RawBatch::Distance(DistanceBatch::decode(b)?),
            Stream::Stage => RawBatch::Stage(StageBatch::decode(b)?),
            Stream::Points => RawBatch::Points(CorrectedPointBatch::decode(b)?),
            Stream::Alarms => RawBatch::Alarm(EstimatorAlarm::decode(b)?),
        })
    }

    /// The stream this batch belongs on.
    pub fn stream(&self) -> Stream {
        match self {
            RawBatch::Command(_) => Stream::Command,
            RawBatch::Scale(_) => Stream::Scale,
            RawBatch::Probe(_) => Stream::Probe,
            RawBatch::Temperature(_) => Stream::Temperature,
            RawBatch::Distance(_) => Stream::Distance,
            RawBatch::Stage(_) => Stream::Stage,
            RawBatch::Points(_) => Stream::Points,
            RawBatch::Alarm(_) => Stream::Alarms,
        }
    }

    /// Number of samples (points; 1 for an alarm) in the batch.
    pub fn sample_count(&self) -> usize {
        match self {
            RawBatch::Command(b) => b.sample_count(),
            RawBatch::Scale(b) => b.sample_count(),
            RawBatch::Probe(b) => b.sample_count(),
            RawBatch::Temperature(b) => b.sample_count(),
            RawBatch::Distance(b) => b.sample_count(),
            RawBatch::Stage(b) => b.sample_count(),
            RawBatch::Points(b) => b.sample_count(),
            RawBatch::Alarm(b) => b.sample_count(),
        }
    }

    /// `t_ns` of the first sample, `None` for an empty batch: the bag's `publish_time`.
    pub fn first_t_ns(&self) -> Option<i64> {
        match self {
            RawBatch::Command(b) => b.first_t_ns(),
            RawBatch::Scale(b) => b.first_t_ns(),
            RawBatch::Probe(b) => b.first_t_ns(),
            RawBatch::Temperature(b) => b.first_t_ns(),
            RawBatch::Distance(b) => b.first_t_ns(),
            RawBatch::Stage(b) => b.first_t_ns(),
            RawBatch::Points(b) => b.first_t_ns(),
            RawBatch::Alarm(b) => b.first_t_ns(),
        }
    }

    /// The stream tag (v1.1) of a raw batch, `STREAM_KIND_UNSPECIFIED` (0) when untagged;
    /// `None` for points and alarms, which carry none.
    pub fn tag(&self) -> Option<i32> {
        match self {
            RawBatch::Command(b) => Some(b.stream),
            RawBatch::Scale(b) => Some(b.stream),
            RawBatch::Probe(b) => Some(b.stream),
            RawBatch::Temperature(b) => Some(b.stream),
            RawBatch::Distance(b) => Some(b.stream),
            RawBatch::Stage(b) => Some(b.stream),
            RawBatch::Points(_) | RawBatch::Alarm(_) => None,
        }
    }

    /// Encodes the batch (protobuf), e.g. to re-record a filtered bag.
    pub fn encode_to_vec(&self) -> Vec<u8> {
        match self {
            RawBatch::Command(b) => b.encode_to_vec(),
            RawBatch::Scale(b) => b.encode_to_vec(),
            RawBatch::Probe(b) => b.encode_to_vec(),
            RawBatch::Temperature(b) => b.encode_to_vec(),
            RawBatch::Distance(b) => b.encode_to_vec(),
            RawBatch::Stage(b) => b.encode_to_vec(),
            RawBatch::Points(b) => b.encode_to_vec(),
            RawBatch::Alarm(b) => b.encode_to_vec(),
        }
    }
}

/// A protobuf message that is recorded as one bag message on a fixed stream.
///
/// Exists so [`crate::BagWriter::write_msg`] can derive the stream and the publish time from
/// the message type and content, which rules out recording a batch on the wrong stream.
pub trait BatchMessage: Message + Sized {
    /// The stream this message type is published on.
    const STREAM: Stream;
    /// Number of samples in the message (1 for an alarm).
    fn sample_count(&self) -> usize;
    /// `t_ns` of the first sample, `None` when there is none.
    fn first_t_ns(&self) -> Option<i64>;
    /// Wraps the message into [`RawBatch`].
    fn into_raw(self) -> RawBatch;
}

macro_rules! batch_message {
    // A batch of the corrected streams: its samples are messages or packed columns (v1.3).
    ($ty:ty, $stream:expr, $variant:ident, packed) => {
        batch_message!(
            $ty,
            $stream,
            $variant,
            |b: &$ty| b.samples.len() + b.columns.as_ref().map_or(0, |c| c.seq.len()),
            |b: &$ty| b.samples.first().map(|s| s.t_ns).or_else(|| b
                .columns
                .as_ref()?
                .t_ns
                .first()
                .copied())
        );
    };
    ($ty:ty, $stream:expr, $field:ident, $variant:ident) => {
        batch_message!(
            $ty,
            $stream,
            $variant,
            |b: &$ty| b.$field.len(),
            |b: &$ty| b.$field.first().map(|s| s.t_ns)
        );
    };
    ($ty:ty, $stream:expr, $variant:ident, $count:expr, $first:expr) => {
        impl BatchMessage for $ty {
            const STREAM: Stream = $stream;
            fn sample_count(&self) -> usize {
                $count(self)
            }
            fn first_t_ns(&self) -> Option<i64> {
                $first(self)
            }
            fn into_raw(self) -> RawBatch {
                RawBatch::$variant(self)
            }
        }
        impl From<$ty> for RawBatch {
            fn from(b: $ty) -> RawBatch {
                RawBatch::$variant(b)
            }
        }
    };
}

batch_message!(CommandBatch, Stream::Command, Command, packed);
batch_message!(ScaleBatch, Stream::Scale, Scale, packed);
batch_message!(ProbeBatch, Stream::Probe, Probe, packed);
batch_message!(TemperatureBatch, Stream::Temperature, Temperature, packed);
batch_message!(DistanceBatch, Stream::Distance, samples, Distance);
batch_message!(StageBatch, Stream::Stage, samples, Stage);
// Points as messages or as packed blocks (v1.4).
batch_message!(
    CorrectedPointBatch,
    Stream::Points,
    Points,
    |b: &CorrectedPointBatch| b.len(),
    |b: &CorrectedPointBatch| b
        .points
        .first()
        .map(|p| p.t_ns)
        .or_else(|| b.columns.iter().find_map(|c| c.t_ns.first().copied()))
);

impl BatchMessage for EstimatorAlarm {
    const STREAM: Stream = Stream::Alarms;
    fn sample_count(&self) -> usize {
        1
    }
    fn first_t_ns(&self) -> Option<i64> {
        Some(self.t_ns)
    }
    fn into_raw(self) -> RawBatch {
        RawBatch::Alarm(self)
    }
}

impl From<EstimatorAlarm> for RawBatch {
    fn from(a: EstimatorAlarm) -> RawBatch {
        RawBatch::Alarm(a)
    }
}

/// What [`peek`] finds in an encoded batch.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BatchPeek {
    /// Number of samples (points; 1 for an alarm).
    pub samples: u64,
    /// `t_ns` of the first sample, `None` for an empty batch.
    pub first_t_ns: Option<i64>,
}

/// Counts the samples of an encoded batch and finds its first `t_ns` by walking the protobuf
/// wire format, without decoding (no allocation).
///
/// Exists because recorders hold raw bytes from the bus: they need the publish time (first
/// sample time) and the writer keeps per-channel sample counts. Returns `None` for bytes that
/// are not well-formed protobuf.
pub fn peek(stream: Stream, payload: &[u8]) -> Option<BatchPeek> {
    // Field numbers: the repeated samples/points field is 1 in every batch; `t_ns` is 3 in
    // every sample, point and alarm. A packed raw batch (v1.3) holds its samples in field 3
    // as columns, a packed point batch (v1.4) its points in blocks of columns in field 2
    // (`seq` 2, `t_ns` 3 in both).
    const REPEATED: u32 = 1;
    const COLUMNS: u32 = 3;
    const POINT_COLUMNS: u32 = 2;
    const T_NS: u32 = 3;
    if stream == Stream::Alarms {
        return Some(BatchPeek {
            samples: 1,
            first_t_ns: Some(varint_field(payload, T_NS)?),
        });
    }
    let packed = Stream::CORRECTED.contains(&stream);
    let mut samples = 0u64;
    let mut first = None;
    let mut rest = payload;
    while !rest.is_empty() {
        match next_field(&mut rest)? {
            (REPEATED, Value::Bytes(sample)) => {
                if samples == 0 {
                    first = Some(varint_field(sample, T_NS)?);
                }
                samples += 1;
            }
            (f, Value::Bytes(columns))
                if (packed && f == COLUMNS) || (stream == Stream::Points && f == POINT_COLUMNS) =>
            {
                let (n, t) = peek_columns(columns)?;
                if samples == 0 {
                    first = t;
                }
                samples += n;
            }
            _ => {}
        }
    }
    Some(BatchPeek {
        samples,
        first_t_ns: first,
    })
}

/// The length of the `seq` column and the first `t_ns` of a packed batch's columns (v1.3) or
/// of a packed point block (v1.4),
/// whether the columns are packed or, as protobuf allows, written one value per field.
fn peek_columns(mut columns: &[u8]) -> Option<(u64, Option<i64>)> {
    const SEQ: u32 = 2;
    const T_NS: u32 = 3;
    let (mut n, mut first) = (0u64, None);
    while !columns.is_empty() {
        match next_field(&mut columns)? {
            (SEQ, v) => each_varint(v, |_| n += 1)?,
            (T_NS, Value::Varint(t)) => {
                first.get_or_insert(t as i64);
            }
            (T_NS, Value::Bytes(mut packed)) if !packed.is_empty() => {
                let t = varint(&mut packed)?;
                first.get_or_insert(t as i64);
            }
            _ => {}
        }
    }
    Some((n, first))
}

/// The stream tag (field 2, v1.1) of an encoded raw batch, 0 when absent, found by walking the
/// wire format without decoding the samples; `None` for bytes that are not well-formed
/// protobuf.
///
/// Exists so a batch on another stream's key is told by its tag before its samples are
/// decoded as the wrong message (which may fail, or worse, succeed).
pub fn stream_tag(payload: &[u8]) -> Option<i32> {
    const STREAM: u32 = 2;
    // An enum is an int32 on the wire: a varint whose low 32 bits are the value.
    varint_field(payload, STREAM).map(|v| v as i32)
}

/// `stream` shown as a stream name: `distance` for `STREAM_KIND_DISTANCE`, `unknown (9)`.
pub(crate) fn tag_name(tag: i32) -> String {
    StreamKind::try_from(tag)
        .map(|k| {
            k.as_str_name()
                .trim_start_matches("STREAM_KIND_")
                .to_ascii_lowercase()
        })
        .unwrap_or_else(|_| format!("unknown ({tag})"))
}

/// The value of varint field `number` (last occurrence wins, 0 when absent, as in proto3).
fn varint_field(mut msg: &[u8], number: u32) -> Option<i64> {
    let mut t = 0i64;
    while !msg.is_empty() {
        if let (f, Value::Varint(v)) = next_field(&mut msg)? {
            if f == number {
                t = v as i64;
            }
        }
    }
    Some(t)
}

/// A protobuf field's value, as [`next_field`] reads it.
pub enum Value<'a> {
    /// Wire type 0.
    Varint(u64),
    /// Wire type 2: the bytes of a string, bytes, packed column or nested message.
    Bytes(&'a [u8]),
    /// Wire types 1 and 5 (fixed 64 and 32 bits), skipped.
    Fixed,
}

/// Reads one field of a protobuf message in place (its number and value) and advances `b`
/// past it; `None` when the bytes are not well-formed or the field number is 0. For readers
/// that need a field or two of a large message without decoding it.
pub fn next_field<'a>(b: &mut &'a [u8]) -> Option<(u32, Value<'a>)> {
    let key = varint(b)?;
    let field = u32::try_from(key >> 3).ok()?;
    let value = match key & 7 {
        0 => Value::Varint(varint(b)?),
        1 => {
            *b = b.get(8..)?;
            Value::Fixed
        }
        2 => {
            let len = usize::try_from(varint(b)?).ok()?;
            let (v, rest) = (b.get(..len)?, b.get(len..)?);
            *b = rest;
            Value::Bytes(v)
        }
        5 => {
            *b = b.get(4..)?;
            Value::Fixed
        }
        _ => return None,
    };
    (field != 0).then_some((field, value))
}

/// Calls `f` with each value of one occurrence of a varint column (`repeated uint64`, …), in
/// either form protobuf allows: packed (the field's bytes hold the values) or one value per
/// field. `None` when the bytes are not well-formed or the field is a fixed-width one.
pub fn each_varint(v: Value<'_>, mut f: impl FnMut(u64)) -> Option<()> {
    match v {
        Value::Varint(x) => f(x),
        Value::Bytes(mut b) => {
            while !b.is_empty() {
                f(varint(&mut b)?);
            }
        }
        Value::Fixed => return None,
    }
    Some(())
}

fn varint(b: &mut &[u8]) -> Option<u64> {
    let mut v = 0u64;
    for i in 0..10 {
        let (&byte, rest) = b.split_first()?;
        *b = rest;
        v |= u64::from(byte & 0x7f) << (7 * i);
        if byte < 0x80 {
            return Some(v);
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;
    use scancorr_proto::v1::{CorrectedPoint, Correction, ScaleColumns, ScaleSample};

    #[test]
    fn peek_matches_decoding() {
        let b = ScaleBatch {
            samples: (0..5)
                .map(|i| ScaleSample {
                    machine_id: "m1".into(),
                    seq: i,
                    t_ns: -7 + i as i64,
                    ..Default::default()
                })
                .collect(),
            ..Default::default()
        };
        let p = peek(Stream::Scale, &b.encode_to_vec()).unwrap();
        assert_eq!(
            p,
            BatchPeek {
                samples: 5,
                first_t_ns: Some(-7)
            }
        );
        assert_eq!(
            peek(Stream::Scale, &[]),
            Some(BatchPeek {
                samples: 0,
                first_t_ns: None
            })
        );
        let points = vec![
            CorrectedPoint {
                t_ns: 42,
                ..Default::default()
            },
            // Other effects than the first point's: packed, a second block.
            CorrectedPoint {
                corrections: vec![Correction {
                    effect: "a".into(),
                    ..Default::default()
                }],
                ..Default::default()
            },
        ];
        let pts = CorrectedPointBatch {
            points: points.clone(),
            columns: vec![],
        };
        let packed = scancorr_proto::points::pack(&points);
        assert_eq!(packed.columns.len(), 2);
        for b in [&pts, &packed] {
            assert_eq!(
                peek(Stream::Points, &b.encode_to_vec()),
                Some(BatchPeek {
                    samples: 2,
                    first_t_ns: Some(42)
                })
            );
            assert_eq!((b.sample_count(), b.first_t_ns()), (2, Some(42)));
        }
        let alarm = EstimatorAlarm {
            t_ns: 9,
            raised: true,
            ..Default::default()
        };
        assert_eq!(
            peek(Stream::Alarms, &alarm.encode_to_vec()),
            Some(BatchPeek {
                samples: 1,
                first_t_ns: Some(9)
            })
        );
        assert_eq!(
            peek(Stream::Scale, &[0x0a, 0x05, 0x01]),
            None,
            "length past the end"
        );
        assert_eq!(peek(Stream::Scale, &[0xff; 11]), None, "overlong varint");
        let raw = RawBatch::from(b.clone());
        assert_eq!(raw.stream(), Stream::Scale);
        assert_eq!(raw.sample_count(), 5);
        assert_eq!(raw.first_t_ns(), Some(-7));
        assert_eq!(
            RawBatch::decode(Stream::Scale, &raw.encode_to_vec()).unwrap(),
            raw
        );
        assert!(matches!(
            RawBatch::decode(Stream::Scale, &[0x0a, 0x05]),
            Err(BagError::Decode { .. })
        ));
    }

    #[test]
    fn peek_reads_packed_batches() {
        let b = ScaleBatch {
            stream: StreamKind::Scale as i32,
            columns: Some(ScaleColumns {
                machine_id: "m1".into(),
                seq: vec![300, 301, 302],
                t_ns: vec![-5, 1 << 40, 7],
                x: vec![1.0; 3],
                y: vec![0.0; 3],
                z: vec![2.0; 3],
            }),
            ..Default::default()
        };
        let want = BatchPeek {
            samples: 3,
            first_t_ns: Some(-5),
        };
        assert_eq!(peek(Stream::Scale, &b.encode_to_vec()), Some(want));
        assert_eq!((b.sample_count(), b.first_t_ns()), (3, Some(-5)));
        // Columns written one value per field (protobuf readers must take that too): seq 5,
        // seq 6, t_ns 7.
        let unpacked = [0x1a, 6, 0x10, 5, 0x10, 6, 0x18, 7];
        assert_eq!(
            peek(Stream::Command, &unpacked),
            Some(BatchPeek {
                samples: 2,
                first_t_ns: Some(7)
            })
        );
        // A packed seq column cut inside a varint is not well-formed.
        assert_eq!(peek(Stream::Scale, &[0x1a, 3, 0x12, 1, 0x80]), None);
        // Field 3 of a measurement batch is not columns.
        assert_eq!(peek(Stream::Distance, &unpacked).unwrap().samples, 0);
    }
}
