//! Reading bags: through the summary when the file is complete, by a linear scan of the
//! complete chunks when it was cut short.
//!
//! Every checksum the file carries is verified: the summary CRC on open (a damaged summary is
//! not used: the data section is scanned instead), the data-section CRC on open (one sequential
//! pass over the file), each chunk's CRC of its uncompressed records whenever the chunk is
//! decoded. A CRC of 0 means "not computed" and is the only way a part passes unverified.
//! Damage is a [`BagError::Damaged`] error, or, with [`ReadOptions::skip_damaged`], a skipped
//! chunk listed by [`BagReader::damaged_chunks`].
use crate::batch::{peek, RawBatch};
use crate::crc::Crc32;
use crate::layout::{self, RecordError};
use crate::{Artifact, BagError, Result, ARTIFACT_METADATA, ENCODING, SAMPLE_COUNTS_METADATA};
use mcap::records::{op, ChunkHeader, ChunkIndex};
use mcap::sans_io::{
    IndexedReadEvent, IndexedReader, IndexedReaderOptions, LinearReadEvent, LinearReader,
    LinearReaderOptions,
};
use mcap::{records::Record, McapError, MAGIC};
use scancorr_proto::{Stream, DEFAULT_PREFIX};
use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::fs::File;
use std::io::{BufReader, Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

mod check;
mod index;
mod messages;
mod source;

use check::*;
use index::*;
pub use messages::Messages;
use source::*;

/// Largest record (or decompressed chunk) the reader accepts; guards allocations against
/// corrupt length fields. scancorr bags use 1 MiB chunks.
const RECORD_LIMIT: u64 = 256 << 20;
/// Most decompressed chunk bytes reading in log-time order may hold at once: chunks whose time
/// ranges overlap are held together. Guards against indexes that make every chunk overlap.
const OVERLAP_LIMIT: u64 = 1 << 30;
/// opcode + length + footer body (summary start, summary offset start, crc) + end magic.
const FOOTER_AND_MAGIC: u64 = 1 + 8 + 20 + 8;
/// The footer bytes the summary CRC covers: opcode, length, summary start, summary offset start.
const FOOTER_CRC_PREFIX: usize = 1 + 8 + 8 + 8;
/// A data-end record: opcode, length, data section CRC.
const DATA_END_LEN: u64 = 1 + 8 + 4;
/// Loose (unchunked) messages are read in runs of at most this many bytes.
const LOOSE_RUN_LIMIT: u64 = 4 << 20;
/// The message reader sees every chunk and loose run as an uncompressed chunk at a made-up
/// offset from here on (beyond any real file offset), `FAKE_STRIDE` apart.
const FAKE_OFFSET_BASE: u64 = 1 << 62;
const FAKE_STRIDE: u64 = 64;
/// Opcode of the filler record that stands in for a skipped chunk (reserved in MCAP, ignored by
/// the message reader).
const FILLER_OPCODE: u8 = 0x00;
/// Bytes read at a time when computing a CRC over a file range.
const HASH_BLOCK: u64 = 1 << 20;

/// How [`BagReader::open_with`] reads a bag. The default fails on any damage.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
#[non_exhaustive]
pub struct ReadOptions {
    /// Skip chunks that fail verification (CRC mismatch, undecodable, inconsistent with the
    /// index), listing them in [`BagReader::damaged_chunks`], instead of failing with
    /// [`BagError::Damaged`]. Damage outside chunks that leaves the messages readable is listed
    /// in [`BagReader::damage_notes`]. Off by default.
    pub skip_damaged: bool,
}

impl ReadOptions {
    /// Sets [`ReadOptions::skip_damaged`].
    pub fn skip_damaged(mut self, skip: bool) -> Self {
        self.skip_damaged = skip;
        self
    }
}

/// A chunk that failed verification and was skipped (only with [`ReadOptions::skip_damaged`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DamagedChunk {
    /// File offset of the chunk record.
    pub offset: u64,
    /// Length of the chunk record, bytes.
    pub length: u64,
    /// Messages lost with it (all channels, scancorr or not), when the file's message index
    /// tells; `None` when unknown.
    pub messages_lost: Option<u64>,
    /// What is wrong, e.g. `CRC mismatch (expected 0x1a2b3c4d, computed 0x5e6f7a8b)`.
    pub reason: String,
}

impl std::fmt::Display for DamagedChunk {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "damaged chunk at byte offset {} ({} bytes) skipped: {}; ",
            self.offset, self.length, self.reason
        )?;
        match self.messages_lost {
            Some(n) => write!(f, "{n} messages lost"),
            None => write!(f, "an unknown number of messages lost"),
        }
    }
}

/// A channel on a scancorr topic `<prefix>/<machine>/<suffix>`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ChannelInfo {
    /// The key expression.
    pub topic: String,
    /// Machine id from the topic.
    pub machine: String,
    /// Stream from the topic suffix.
    pub stream: Stream,
    /// Messages on the channel (readable ones, for a truncated bag).
    pub message_count: u64,
    /// Samples inside those messages, when known (complete bags written by this crate, and
    /// every truncated bag).
    pub sample_count: Option<u64>,
}

/// A channel whose topic is not `<prefix>/<machine>/<known suffix>`: listed so callers can warn,
/// skipped when iterating.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct UnknownChannel {
    /// The channel topic.
    pub topic: String,
    /// The schema name, if the channel has a schema.
    pub schema_name: Option<String>,
    /// The channel's message encoding.
    pub message_encoding: String,
    /// Messages on the channel.
    pub message_count: u64,
}

/// One metadata record, in file order.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MetadataRecord {
    /// Record name, e.g. `scancorr.run`.
    pub name: String,
    /// Its string map.
    pub entries: BTreeMap<String, String>,
}

/// Why a bag was read by linear scan and how much of it was usable.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Truncation {
    /// File size.
    pub file_len: u64,
    /// End of the last complete record that was read; messages after it are lost.
    pub readable_len: u64,
    /// What the scan found at `readable_len`.
    pub reason: String,
}

/// One recorded message.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BagMessage {
    /// Stream of the channel.
    pub stream: Stream,
    /// Machine id of the channel.
    pub machine: Arc<str>,
    /// Channel topic (key expression).
    pub topic: Arc<str>,
    /// Receive time, ns.
    pub log_time: u64,
    /// Sample time (first sample's `t_ns`), ns.
    pub publish_time: u64,
    /// The encoded batch.
    pub data: Vec<u8>,
}

impl BagMessage {
    /// Decodes the payload as its stream's message type.
    pub fn decode(&self) -> Result<RawBatch> {
        RawBatch::decode_inner(self.stream, &self.data).map_err(|error| BagError::Decode {
            message: self.stream.message_name(),
            context: self.context(),
            error,
        })
    }

    /// Decodes the payload like [`BagMessage::decode`], after checking that a raw batch's
    /// stream tag names this channel's stream (or none): see [`RawBatch::decode_checked`].
    pub fn decode_checked(&self) -> Result<RawBatch> {
        RawBatch::decode_checked(self.stream, &self.data, &self.context())
    }

    fn context(&self) -> String {
        format!(" on {} at log time {}", self.topic, self.log_time)
    }
}

#[derive(Clone)]
struct Route {
    stream: Stream,
    machine: Arc<str>,
    topic: Arc<str>,
}

/// What the message reader reads: a chunk record, or a run of loose message records.
#[derive(Debug, Clone)]
enum Region {
    /// A chunk: its index entry (from the summary or the scan) and, from a scan, its messages.
    Chunk {
        index: ChunkIndex,
        messages: Option<u64>,
    },
    /// Loose records in the data section (`size` bytes from `start`), read as they are.
    Loose {
        start: u64,
        size: u64,
        t_min: u64,
        t_max: u64,
    },
}

impl Region {
    fn offset(&self) -> u64 {
        match self {
            Region::Chunk { index, .. } => index.chunk_start_offset,
            Region::Loose { start, .. } => *start,
        }
    }
    fn times(&self) -> (u64, u64) {
        match self {
            Region::Chunk { index, .. } => (index.message_start_time, index.message_end_time),
            Region::Loose { t_min, t_max, .. } => (*t_min, *t_max),
        }
    }
    /// Bytes of records the message reader gets for it (at least one filler record's worth).
    fn data_size(&self) -> u64 {
        match self {
            Region::Chunk { index, .. } => index.uncompressed_size,
            Region::Loose { size, .. } => *size,
        }
        .max(9)
    }
}

/// An opened bag: channels, metadata and whether it was cut short are read on open; messages
/// are streamed chunk by chunk by [`BagReader::messages`].
pub struct BagReader {
    path: PathBuf,
    options: ReadOptions,
    profile: String,
    library: String,
    prefix: String,
    truncation: Option<Truncation>,
    channels: Vec<ChannelInfo>,
    unknown: Vec<UnknownChannel>,
    metadata: Vec<MetadataRecord>,
    time_range: Option<(u64, u64)>,
    routes: HashMap<u16, Route>,
    /// `regions` as uncompressed chunks at made-up offsets, for the message reader.
    summary: mcap::Summary,
    /// The chunks and loose-message runs to read, in file order.
    regions: Vec<Region>,
    /// Made-up data offset → index in `regions`.
    fake: HashMap<u64, usize>,
    damaged: Mutex<Vec<DamagedChunk>>,
    notes: Vec<String>,
}

impl std::fmt::Debug for BagReader {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("BagReader")
            .field("path", &self.path)
            .field("options", &self.options)
            .field("prefix", &self.prefix)
            .field("truncation", &self.truncation)
            .field("channels", &self.channels)
            .field("unknown", &self.unknown)
            .field("metadata", &self.metadata)
            .field("damaged_chunks", &self.damaged_chunks())
            .field("damage_notes", &self.notes)
            .finish_non_exhaustive()
    }
}

struct SchemaRec {
    name: String,
    encoding: String,
}

struct ChannelRec {
    topic: String,
    schema_id: u16,
    message_encoding: String,
}

/// What open() gathers, from the summary or from a scan.
#[derive(Default)]
struct Catalog {
    skip_damaged: bool,
    profile: String,
    library: String,
    schemas: HashMap<u16, SchemaRec>,
    channels: BTreeMap<u16, ChannelRec>,
    message_counts: BTreeMap<u16, u64>,
    /// From a scan, by channel id.
    sample_counts: BTreeMap<u16, u64>,
    /// From the writer's sample-count record, by topic.
    sample_counts_by_topic: Option<BTreeMap<String, u64>>,
    metadata: Vec<MetadataRecord>,
    regions: Vec<Region>,
    /// From the summary: offset of the data-end record and the data section CRC it holds.
    data_end: Option<(u64, u32)>,
    time_range: Option<(u64, u64)>,
    truncation: Option<Truncation>,
    scanned: bool,
    /// Chunks skipped as damaged (skip mode).
    damaged: Vec<DamagedChunk>,
    /// Channels that lost messages of skipped chunks (their sample counts become unknown);
    /// `lost_unknown` when a skipped chunk's channels are not known.
    lossy: BTreeSet<u16>,
    lost_unknown: bool,
    notes: Vec<String>,
}

impl Catalog {
    fn add_schema(&mut self, id: u16, name: String, encoding: String) {
        if id != 0 {
            self.schemas
                .entry(id)
                .or_insert(SchemaRec { name, encoding });
        }
    }
    fn add_channel(&mut self, c: mcap::records::Channel) {
        self.channels.entry(c.id).or_insert(ChannelRec {
            topic: c.topic,
            schema_id: c.schema_id,
            message_encoding: c.message_encoding,
        });
    }
    fn add_time(&mut self, t: u64) {
        self.time_range = Some(match self.time_range {
            None => (t, t),
            Some((a, b)) => (a.min(t), b.max(t)),
        });
    }
}

/// The stream a topic ends in, whatever its prefix.
fn stream_of_topic(topic: &str) -> Option<Stream> {
    Stream::ALL.into_iter().find(|s| {
        topic
            .strip_suffix(s.suffix())
            .is_some_and(|head| head.ends_with('/'))
    })
}

/// `(prefix, machine)` of a topic `<prefix>/<machine>/<suffix>`.
fn split_topic(topic: &str) -> Option<(&str, &str)> {
    let s = stream_of_topic(topic)?;
    let head = &topic[..topic.len() - s.suffix().len() - 1];
    let (prefix, machine) = head.rsplit_once('/')?;
    (!prefix.is_empty() && !machine.is_empty()).then_some((prefix, machine))
}

fn message_header(data: &[u8]) -> Option<(u16, u64)> {
    let channel = u16::from_le_bytes(data.get(0..2)?.try_into().ok()?);
    let log_time = u64::from_le_bytes(data.get(6..14)?.try_into().ok()?);
    data.get(22..)?;
    Some((channel, log_time))
}

impl BagReader {
    /// Opens a bag: checks the magic and header, then reads the summary, or scans the file
    /// when it has none (cut short, or written without one). Verifies the summary and
    /// data-section CRCs (reading the whole file once); a damaged chunk is a
    /// [`BagError::Damaged`] error, here or from [`BagReader::messages`].
    pub fn open(path: impl AsRef<Path>) -> Result<BagReader> {
        Self::open_with(path, ReadOptions::default())
    }

    /// Opens a bag like [`BagReader::open`], but skips damaged chunks instead of failing: see
    /// [`BagReader::damaged_chunks`] and [`BagReader::damage_notes`].
    pub fn open_skipping_damaged(path: impl AsRef<Path>) -> Result<BagReader> {
        Self::open_with(path, ReadOptions::default().skip_damaged(true))
    }

    /// Opens a bag with the given options.
    pub fn open_with(path: impl AsRef<Path>, options: ReadOptions) -> Result<BagReader> {
        let path = path.as_ref().to_path_buf();
        let io = |error| BagError::Io {
            path: path.clone(),
            error,
        };
        let file = File::open(&path).map_err(io)?;
        let len = file.metadata().map_err(io)?.len();
        let mut src = Source {
            path: path.clone(),
            file: BufReader::with_capacity(64 * 1024, file),
            pos: 0,
            len,
            buf: Vec::new(),
        };
        let not_mcap = |reason: String| BagError::NotMcap {
            path: path.clone(),
            reason,
        };
        let corrupt = |reason: String| BagError::Corrupt {
            path: path.clone(),
            reason,
        };
        if len == 0 {
            return Err(not_mcap("the file is empty".into()));
        }
        if len < MAGIC.len() as u64 {
            return Err(not_mcap(format!("the file is only {len} bytes long")));
        }
        if src.read_at(0, MAGIC.len())? != MAGIC {
            return Err(not_mcap("wrong magic bytes at the start".into()));
        }
        let mut cat = Catalog {
            skip_damaged: options.skip_damaged,
            ..Catalog::default()
        };
        let header_start = MAGIC.len() as u64;
        if len > header_start {
            let op = src.read_at(header_start, 1)?[0];
            if op != op::HEADER {
                return Err(corrupt(format!(
                    "the first record has opcode {op:#04x}, not a header"
                )));
            }
        }
        let header_end = match src.next_record(header_start, len)? {
            Next::Record {
                op: op::HEADER,
                end,
            } => {
                match layout::parse(op::HEADER, src.body()) {
                    Ok(Record::Header(h)) => {
                        cat.profile = h.profile;
                        cat.library = h.library;
                    }
                    Err(RecordError::Layout(reason)) => {
                        return Err(BagError::Damaged {
                            path: path.clone(),
                            what: "record",
                            offset: header_start,
                            reason,
                        })
                    }
                    _ => return Err(corrupt("the header record does not parse".into())),
                }
                end
            }
            Next::Record { op, .. } => {
                return Err(corrupt(format!(
                    "the first record has opcode {op:#04x}, not a header"
                )))
            }
            Next::TooLong(reason) => return Err(corrupt(reason)),
            Next::End | Next::Cut(_) => {
                return Err(corrupt(format!(
                    "the file ends inside the MCAP header ({len} bytes)"
                )))
            }
        };
        match read_summary(&mut src, header_end, &mut cat) {
            Ok(()) => verify_data_section(&mut src, &mut cat)?,
            Err(why) => {
                cat = Catalog {
                    skip_damaged: cat.skip_damaged,
                    profile: cat.profile,
                    library: cat.library,
                    ..Catalog::default()
                };
                let why = match why {
                    NoSummary::Absent(reason) => reason,
                    NoSummary::Unusable(reason) => {
                        cat.notes.push(format!(
                            "the summary section is unusable ({reason}); the data section was \
                             scanned instead"
                        ));
                        reason
                    }
                };
                scan(&mut src, header_end, &mut cat, &why)?;
            }
        }
        Self::build(path, cat, options)
    }

    fn build(path: PathBuf, mut cat: Catalog, options: ReadOptions) -> Result<BagReader> {
        // The prefix: the one most channels use, DEFAULT_PREFIX on a tie, then the smallest.
        let mut votes: BTreeMap<&str, usize> = BTreeMap::new();
        for c in cat.channels.values() {
            if let Some((p, _)) = split_topic(&c.topic) {
                *votes.entry(p).or_default() += 1;
            }
        }
        let best = votes.values().copied().max().unwrap_or(0);
        let prefix = if votes.get(DEFAULT_PREFIX) == Some(&best) || best == 0 {
            DEFAULT_PREFIX.to_owned()
        } else {
            votes
                .iter()
                .find(|(_, &n)| n == best)
                .map_or(DEFAULT_PREFIX, |(p, _)| p)
                .to_owned()
        };
        let sample_counts_by_topic = cat.sample_counts_by_topic.take();
        let mut channels = Vec::new();
        let mut unknown = Vec::new();
        let mut routes = HashMap::new();
        for (&id, c) in &cat.channels {
            let schema = cat.schemas.get(&c.schema_id).filter(|_| c.schema_id != 0);
            let message_count = cat.message_counts.get(&id).copied().unwrap_or(0);
            let Some((machine, stream)) = Stream::parse_key(&prefix, &c.topic) else {
                unknown.push(UnknownChannel {
                    topic: c.topic.clone(),
                    schema_name: schema.map(|s| s.name.clone()),
                    message_encoding: c.message_encoding.clone(),
                    message_count,
                });
                continue;
            };
            match schema {
                Some(s) if s.name == stream.message_name() => {
                    if s.encoding != ENCODING {
                        return Err(BagError::WrongEncoding {
                            path,
                            topic: c.topic.clone(),
                            what: "schema",
                            found: s.encoding.clone(),
                        });
                    }
                }
                other => {
                    return Err(BagError::WrongSchema {
                        path,
                        topic: c.topic.clone(),
                        expected: stream.message_name(),
                        found: other.map_or("<none>".into(), |s| s.name.clone()),
                    })
                }
            }
            if c.message_encoding != ENCODING {
                return Err(BagError::WrongEncoding {
                    path,
                    topic: c.topic.clone(),
                    what: "message",
                    found: c.message_encoding.clone(),
                });
            }
            let sample_count = if cat.scanned {
                Some(cat.sample_counts.get(&id).copied().unwrap_or(0))
            } else {
                sample_counts_by_topic
                    .as_ref()
                    .and_then(|m| m.get(&c.topic).copied())
                    // The writer's counts include the messages of skipped chunks.
                    .filter(|_| !cat.lost_unknown && !cat.lossy.contains(&id))
            };
            routes.insert(
                id,
                Route {
                    stream,
                    machine: Arc::from(machine),
                    topic: Arc::from(c.topic.as_str()),
                },
            );
            channels.push(ChannelInfo {
                topic: c.topic.clone(),
                machine: machine.to_owned(),
                stream,
                message_count,
                sample_count,
            });
        }
        channels.sort_by(|a, b| (&a.machine, a.stream).cmp(&(&b.machine, b.stream)));
        let mut regions = std::mem::take(&mut cat.regions);
        regions.sort_by_key(Region::offset);
        check_overlap(&regions).map_err(|reason| BagError::Corrupt {
            path: path.clone(),
            reason,
        })?;
        // The message reader sees each region as an uncompressed chunk at a made-up offset, in
        // file order (so that equal log times come in file order); `Messages` supplies the
        // verified records.
        let mut chunk_indexes = Vec::with_capacity(regions.len());
        let mut fake = HashMap::with_capacity(regions.len());
        for (i, r) in regions.iter().enumerate() {
            let (t_min, t_max) = r.times();
            let size = r.data_size();
            let index = ChunkIndex {
                message_start_time: t_min,
                message_end_time: t_max,
                chunk_start_offset: FAKE_OFFSET_BASE + i as u64 * FAKE_STRIDE,
                chunk_length: size,
                message_index_offsets: BTreeMap::new(),
                message_index_length: 0,
                compression: String::new(),
                compressed_size: size,
                uncompressed_size: size,
            };
            let data_offset = index
                .compressed_data_offset()
                .map_err(|error| BagError::Mcap {
                    path: path.clone(),
                    error,
                })?;
            fake.insert(data_offset, i);
            chunk_indexes.push(index);
        }
        let summary = mcap::Summary {
            chunk_indexes,
            ..Default::default()
        };
        Ok(BagReader {
            path,
            options,
            profile: cat.profile,
            library: cat.library,
            prefix,
            truncation: cat.truncation,
            channels,
            unknown,
            metadata: cat.metadata,
            time_range: cat.time_range,
            routes,
            summary,
            regions,
            fake,
            damaged: Mutex::new(cat.damaged),
            notes: cat.notes,
        })
    }

    /// The bag file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// MCAP header profile (`scancorr` for bags written by this crate).
    pub fn profile(&self) -> &str {
        &self.profile
    }

    /// MCAP header library string of the writer.
    pub fn library(&self) -> &str {
        &self.library
    }

    /// The key-expression prefix of the bag's channels (`cmm` when there are none).
    pub fn prefix(&self) -> &str {
        &self.prefix
    }

    /// `Some` when the file was cut short (no summary/footer, e.g. the recorder was killed):
    /// what is readable is everything up to the last complete chunk. Callers should warn.
    pub fn truncation(&self) -> Option<&Truncation> {
        self.truncation.as_ref()
    }

    /// The scancorr channels, sorted by machine then stream.
    pub fn channels(&self) -> &[ChannelInfo] {
        &self.channels
    }

    /// Channels on other topics; [`BagReader::messages`] skips them.
    pub fn unknown_channels(&self) -> &[UnknownChannel] {
        &self.unknown
    }

    /// The channel of one stream of one machine.
    pub fn channel(&self, machine: &str, stream: Stream) -> Option<&ChannelInfo> {
        self.channels
            .iter()
            .find(|c| c.machine == machine && c.stream == stream)
    }

    /// The machines with at least one channel, sorted.
    pub fn machines(&self) -> Vec<&str> {
        let mut m: Vec<&str> = self.channels.iter().map(|c| c.machine.as_str()).collect();
        m.dedup();
        m
    }

    /// Messages on scancorr channels (what [`BagReader::messages`] yields).
    pub fn message_count(&self) -> u64 {
        self.channels.iter().map(|c| c.message_count).sum()
    }

    /// First and last log time of all messages, ns; `None` for an empty bag.
    pub fn time_range(&self) -> Option<(u64, u64)> {
        self.time_range
    }

    /// Metadata records in file order (the artifact included; the writer's internal
    /// `scancorr.sample_counts` excluded).
    pub fn metadata(&self) -> &[MetadataRecord] {
        &self.metadata
    }

    /// The entries of the last metadata record called `name`.
    pub fn metadata_named(&self, name: &str) -> Option<&BTreeMap<String, String>> {
        self.metadata
            .iter()
            .rev()
            .find(|m| m.name == name)
            .map(|m| &m.entries)
    }

    /// The measured artifact (`scancorr.artifact`), if recorded.
    pub fn artifact(&self) -> Result<Option<Artifact>> {
        self.metadata_named(ARTIFACT_METADATA)
            .map(Artifact::from_metadata)
            .transpose()
    }

    /// How the bag was opened.
    pub fn read_options(&self) -> ReadOptions {
        self.options
    }

    /// Chunks skipped because they failed verification, in the order they were found (only
    /// with [`ReadOptions::skip_damaged`]; without it damage is an error). Found on open, or
    /// while iterating [`BagReader::messages`] — check again after iterating. Callers should
    /// warn; channel message counts exclude the lost messages when the file's message index
    /// tells how many there were.
    pub fn damaged_chunks(&self) -> Vec<DamagedChunk> {
        self.damaged
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .clone()
    }

    /// Damage that did not cost messages: a summary section that failed its CRC or checks (the
    /// data section was scanned and verified instead), or, with
    /// [`ReadOptions::skip_damaged`], a data-section CRC mismatch (metadata or index records
    /// may be damaged). Callers should warn.
    pub fn damage_notes(&self) -> &[String] {
        &self.notes
    }

    /// Iterates over the messages of the scancorr channels in log-time order (file order on
    /// equal times), one chunk in memory at a time. Each chunk's CRC is verified as it is
    /// decoded: a damaged chunk is a [`BagError::Damaged`] item (or, with
    /// [`ReadOptions::skip_damaged`], skipped and listed by [`BagReader::damaged_chunks`]).
    /// After an error the iterator ends.
    pub fn messages(&self) -> Result<Messages<'_>> {
        let io = |error| BagError::Io {
            path: self.path.clone(),
            error,
        };
        let file = File::open(&self.path).map_err(io)?;
        let file_len = file.metadata().map_err(io)?.len();
        // Loose runs may exceed the record limit by the one record that starts them.
        let limit = (RECORD_LIMIT + LOOSE_RUN_LIMIT) as usize;
        let options = IndexedReaderOptions::new().with_record_length_limit(limit);
        let reader = IndexedReader::new_with_options(&self.summary, options).map_err(|error| {
            BagError::Mcap {
                path: self.path.clone(),
                error,
            }
        })?;
        Ok(Messages {
            bag: self,
            file,
            file_len,
            reader,
            buf: Vec::new(),
            done: false,
        })
    }
}
