//! Bag files for scancorr: MCAP recordings of the raw and corrected streams of one or more
//! machines, with the measured artifact and run information as metadata.
//!
//! Format (standard MCAP, readable by any MCAP tool, e.g. the Python `mcap` package):
//! - one channel per key expression (topic `<prefix>/<machine>/<suffix>`, e.g.
//!   `cmm/m1/raw/scale`), message encoding `protobuf`, schema encoding `protobuf`, schema name the
//!   fully-qualified message name (`scancorr.v1.ScaleBatch`) and schema data the serialized
//!   `FileDescriptorSet` ([`scancorr_proto::FILE_DESCRIPTOR_SET`]);
//! - each message is one batch (`CommandBatch`, `ScaleBatch`, `ProbeBatch`, `TemperatureBatch`,
//!   the v1.2 `DistanceBatch` and `StageBatch`, `CorrectedPointBatch`, `EstimatorAlarm`) as
//!   prost encodes it; `log_time` is the receive time, `publish_time` the sample time (`t_ns`
//!   of the first sample);
//! - metadata records: `scancorr.artifact` ([`Artifact`]), any others the recorder adds (e.g.
//!   `scancorr.run`), and `scancorr.sample_counts` (topic → samples, written on finish);
//! - zstd-compressed chunks of 1 MiB: a file cut short (recorder killed) reads up to its last
//!   complete chunk, and [`BagReader::truncation`] says so.
//!
//! Reading verifies every checksum the file carries (summary CRC, data-section CRC, each
//! chunk's CRC of its uncompressed records; a CRC of 0 means "not computed"): damage is a
//! [`BagError::Damaged`] error, or with [`ReadOptions::skip_damaged`] a skipped chunk listed by
//! [`BagReader::damaged_chunks`] — never silently altered messages.
//!
//! [`measure`] reads the measurement streams the corrector does not use (v1.2 distance probes
//! and micro-stage) of one machine as plain readings, for calibration procedures.
//!
//! [`foxglove`] encodes corrected points, the nominal features, alarms and the machine frame
//! in Foxglove's schemas, as channels beside scancorr's (`<prefix>/<machine>/foxglove/…`).
//!
//! [`import`] reads a user's recorded table (CSV or whitespace columns) into samples of the
//! raw streams through a column mapping, and writes a bag's raw streams as such a table.
#![forbid(unsafe_code)]
#![warn(missing_docs)]

mod artifact;
mod batch;
mod crc;
mod error;
pub mod foxglove;
pub mod import;
mod layout;
pub mod measure;
mod reader;
mod writer;

pub use artifact::{Artifact, ArtifactKind, ARTIFACT_METADATA};
pub use batch::{
    each_varint, next_field, peek, stream_tag, BatchMessage, BatchPeek, RawBatch, Value,
};
pub use error::{BagError, Result};
pub use reader::{
    BagMessage, BagReader, ChannelInfo, DamagedChunk, Messages, MetadataRecord, ReadOptions,
    Truncation, UnknownChannel,
};
pub use scancorr_proto::Stream;
pub use writer::{BagHeader, BagWriter, Compression, DEFAULT_CHUNK_SIZE, DEFAULT_PROFILE};

/// Schema and message encoding of every scancorr channel.
pub const ENCODING: &str = "protobuf";

/// Suggested metadata record name for run information (program, seed, machine id…).
pub const RUN_METADATA: &str = "scancorr.run";

/// Metadata record the writer adds on finish: topic → number of samples recorded. Reserved.
pub const SAMPLE_COUNTS_METADATA: &str = "scancorr.sample_counts";
