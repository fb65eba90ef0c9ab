//! Conversion between the wire contract (`scancorr.v1`) and the core's types.
//!
//! Pure functions: bytes or prost messages in, core samples out, and back. The live service,
//! the bag tools and the simulator all convert here, so a point means the same everywhere.

//!
//! One concern a module: `decode` (raw batches in both layouts into samples),
//! `encode` (points and alarms out), `batch` (raw samples into batches, [`Batcher`]); this
//! module holds what they share: the errors, the v1.1 stream tag and its checks.

use crate::sample::*;
use scancorr_proto::v1;
use scancorr_proto::Message;

mod batch;
mod decode;
mod encode;

pub use batch::*;
pub use decode::*;
pub use encode::*;

/// Why a payload could not be turned into samples.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum WireError {
    /// The bytes are not the expected protobuf message.
    #[error("malformed {message}: {reason}")]
    Malformed {
        /// Expected message.
        message: &'static str,
        /// Decoder's complaint.
        reason: String,
    },
    /// A batch with no samples.
    #[error("empty {0}")]
    Empty(&'static str),
    /// A batch that names another stream than the key it came on (v1.1 stream tag).
    #[error("a {found} batch on the {expected} stream")]
    WrongStream {
        /// The stream of the key.
        expected: &'static str,
        /// The stream the batch names.
        found: String,
    },
    /// A batch without the v1.1 stream tag where one is required.
    #[error(
        "{0} without its stream tag (a producer older than scancorr.v1.1, or another message type)"
    )]
    Untagged(&'static str),
}

/// Whether a raw batch must carry its v1.1 stream tag.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Tags {
    /// A batch without the tag is refused ([`WireError::Untagged`]): the live service, where
    /// nothing but the key says what a payload is.
    Require,
    /// A batch without the tag is taken as the key's stream: bags, whose channel names the
    /// message type, and producers older than v1.1.
    AllowUntagged,
}

/// The v1.1 tag value of a stream.
pub fn stream_kind(stream: StreamId) -> v1::StreamKind {
    match stream {
        StreamId::Command => v1::StreamKind::Command,
        StreamId::Scale => v1::StreamKind::Scale,
        StreamId::Probe => v1::StreamKind::Probe,
        StreamId::Temperature => v1::StreamKind::Temperature,
    }
}

fn check_tag(stream: StreamId, tag: i32, tags: Tags, name: &'static str) -> Result<(), WireError> {
    if tag == stream_kind(stream) as i32 {
        return Ok(());
    }
    if tag == v1::StreamKind::Unspecified as i32 {
        return match tags {
            Tags::AllowUntagged => Ok(()),
            Tags::Require => Err(WireError::Untagged(name)),
        };
    }
    Err(WireError::WrongStream {
        expected: stream.name(),
        found: tag_name(tag),
    })
}

/// A stream tag as a stream name: `distance`, `unknown (9)`.
fn tag_name(tag: i32) -> String {
    v1::StreamKind::try_from(tag)
        .map(|k| {
            k.as_str_name()
                .trim_start_matches("STREAM_KIND_")
                .to_ascii_lowercase()
        })
        .unwrap_or_else(|_| format!("unknown ({tag})"))
}

/// The error of a raw batch of `stream` that prost could not decode: [`WireError::WrongStream`]
/// when the bytes are a well-formed batch of another raw stream that carries that stream's tag
/// (one whose samples lay out their fields differently, e.g. a v1.2 `DistanceBatch` on a scale
/// key), else [`WireError::Malformed`]. Only on this error path are the other types tried.
fn undecodable(
    stream: StreamId,
    bytes: &[u8],
    message: &'static str,
    e: scancorr_proto::prost::DecodeError,
) -> WireError {
    fn tagged_as<M: Message + Default>(
        bytes: &[u8],
        kind: v1::StreamKind,
        tag: fn(&M) -> i32,
    ) -> bool {
        M::decode(bytes).is_ok_and(|m| tag(&m) == kind as i32)
    }
    use v1::StreamKind as K;
    let other = [
        K::Command,
        K::Scale,
        K::Probe,
        K::Temperature,
        K::Distance,
        K::Stage,
    ]
    .into_iter()
    .filter(|&k| k != stream_kind(stream))
    .find(|&k| match k {
        K::Command => tagged_as::<v1::CommandBatch>(bytes, k, |m| m.stream),
        K::Scale => tagged_as::<v1::ScaleBatch>(bytes, k, |m| m.stream),
        K::Probe => tagged_as::<v1::ProbeBatch>(bytes, k, |m| m.stream),
        K::Temperature => tagged_as::<v1::TemperatureBatch>(bytes, k, |m| m.stream),
        K::Distance => tagged_as::<v1::DistanceBatch>(bytes, k, |m| m.stream),
        K::Stage => tagged_as::<v1::StageBatch>(bytes, k, |m| m.stream),
        K::Unspecified => false,
    });
    match other {
        Some(k) => WireError::WrongStream {
            expected: stream.name(),
            found: tag_name(k as i32),
        },
        None => WireError::Malformed {
            message,
            reason: e.to_string(),
        },
    }
}

/// The bytes of a raw batch with its v1.1 stream tag: appended when missing (protobuf merges
/// a field written after the others), refused when it names another stream. For replaying
/// bags recorded before v1.1 into a service that requires the tag.
pub fn tagged(stream: StreamId, bytes: &[u8]) -> Result<std::borrow::Cow<'_, [u8]>, WireError> {
    let tag = match stream {
        StreamId::Command => v1::CommandBatch::decode(bytes).map(|b| b.stream),
        StreamId::Scale => v1::ScaleBatch::decode(bytes).map(|b| b.stream),
        StreamId::Probe => v1::ProbeBatch::decode(bytes).map(|b| b.stream),
        StreamId::Temperature => v1::TemperatureBatch::decode(bytes).map(|b| b.stream),
    }
    .map_err(|e| undecodable(stream, bytes, "raw batch", e))?;
    check_tag(stream, tag, Tags::AllowUntagged, "raw batch")?;
    if tag != 0 {
        return Ok(std::borrow::Cow::Borrowed(bytes));
    }
    let mut v = Vec::with_capacity(bytes.len() + 2);
    v.extend_from_slice(bytes);
    put_u64(2, stream_kind(stream) as u64, &mut v);
    Ok(std::borrow::Cow::Owned(v))
}

/// The core stream of a raw wire stream.
pub fn stream_id(s: scancorr_proto::Stream) -> Option<StreamId> {
    use scancorr_proto::Stream as S;
    match s {
        S::Command => Some(StreamId::Command),
        S::Scale => Some(StreamId::Scale),
        S::Probe => Some(StreamId::Probe),
        S::Temperature => Some(StreamId::Temperature),
        _ => None,
    }
}

#[cfg(test)]
mod tests;
