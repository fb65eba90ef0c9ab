//! The crate's error type.
use std::path::PathBuf;

/// Everything that can go wrong writing or reading a bag. Each variant names the file and what
/// was expected, so a CLI can print it as is. The display text includes the underlying cause.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum BagError {
    /// Opening, reading, writing or syncing the file failed.
    #[error("{}: {error}", path.display())]
    Io {
        /// The bag file.
        path: PathBuf,
        /// The OS error.
        error: std::io::Error,
    },
    /// The file is empty, too short or does not start with the MCAP magic.
    #[error("{}: not an MCAP file: {reason}", path.display())]
    NotMcap {
        /// The file.
        path: PathBuf,
        /// What was found instead.
        reason: String,
    },
    /// The file starts like an MCAP file but its header cannot be read (e.g. cut inside it).
    #[error("{}: corrupt MCAP file: {reason}", path.display())]
    Corrupt {
        /// The bag file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// The bag was altered after it was written: a checksum does not match (chunk CRC, data
    /// section CRC), or a record of a finished file is malformed. Reading with
    /// [`crate::ReadOptions::skip_damaged`] skips damaged chunks and counts them instead.
    #[error("{}: damaged bag: {what} at byte offset {offset}: {reason}", path.display())]
    Damaged {
        /// The bag file.
        path: PathBuf,
        /// What is damaged: `chunk`, `record` or `data section`.
        what: &'static str,
        /// File offset of the damaged record (0 for the data section).
        offset: u64,
        /// What is wrong, e.g. `CRC mismatch (expected 0x1a2b3c4d, computed 0x5e6f7a8b)`.
        reason: String,
    },
    /// A channel on a scancorr topic declares a schema other than the stream's message.
    #[error("{}: channel {topic:?} has schema {found:?}, expected {expected:?}", path.display())]
    WrongSchema {
        /// The bag file.
        path: PathBuf,
        /// The channel topic.
        topic: String,
        /// The fully-qualified message name of the stream.
        expected: &'static str,
        /// The schema name found (`<none>` when the channel has no schema).
        found: String,
    },
    /// A channel on a scancorr topic uses a schema or message encoding other than `protobuf`.
    #[error("{}: channel {topic:?} has {what} encoding {found:?}, expected \"protobuf\"", path.display())]
    WrongEncoding {
        /// The bag file.
        path: PathBuf,
        /// The channel topic.
        topic: String,
        /// `schema` or `message`.
        what: &'static str,
        /// The encoding found.
        found: String,
    },
    /// The MCAP library reported an error (writing, or reading a chunk while iterating).
    #[error("{}: {error}", path.display())]
    Mcap {
        /// The bag file.
        path: PathBuf,
        /// The library error.
        error: mcap::McapError,
    },
    /// A prefix/machine pair does not form a key expression that parses back to itself, or the
    /// bag already records another prefix.
    #[error("invalid key expression (prefix {prefix:?}, machine {machine:?}): {reason}")]
    InvalidKey {
        /// The prefix given.
        prefix: String,
        /// The machine id given.
        machine: String,
        /// Why it was rejected.
        reason: String,
    },
    /// The metadata name is written by the bag writer itself.
    #[error("metadata name {0:?} is reserved for the bag writer")]
    ReservedMetadata(String),
    /// A `scancorr.artifact` metadata entry is missing or malformed.
    #[error("artifact metadata key {key:?}: {reason}")]
    Artifact {
        /// The key.
        key: String,
        /// What is wrong with it.
        reason: String,
    },
    /// A message payload does not decode as its stream's message type.
    #[error("cannot decode {message}{context}: {error}")]
    Decode {
        /// Fully-qualified message name.
        message: &'static str,
        /// Where (` on <topic> at log time <ns>`), empty when unknown.
        context: String,
        /// The prost error.
        error: prost::DecodeError,
    },
    /// A raw batch whose stream tag (v1.1) names another stream than the channel it was
    /// recorded on, e.g. a `DistanceBatch` published on a `raw/stage` key: not decoded as the
    /// wrong message.
    #[error(
        "a {found} batch on the {} stream{context}: its stream tag names another stream than its key",
        expected.suffix()
    )]
    WrongStream {
        /// The channel's stream.
        expected: scancorr_proto::Stream,
        /// The stream the batch's tag names (`distance`, `unknown (9)`).
        found: String,
        /// Where (` on <topic> at log time <ns>`), empty when unknown.
        context: String,
    },
}

/// Shorthand for results of this crate.
pub type Result<T, E = BagError> = std::result::Result<T, E>;

#[cfg(test)]
mod tests {
    #[test]
    fn error_is_send_sync_static() {
        fn check<T: Send + Sync + 'static>() {}
        check::<super::BagError>();
    }
}
