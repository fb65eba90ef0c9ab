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

fn crc_mismatch(expected: u32, computed: u32) -> String {
    format!("CRC mismatch (expected {expected:#010x}, computed {computed:#010x})")
}

/// The file, read record by record.
struct Source {
    path: PathBuf,
    file: BufReader<File>,
    pos: u64,
    len: u64,
    buf: Vec<u8>,
}

enum Next {
    /// A whole record is in `buf` (opcode, length, body); it ends at `end`.
    Record { op: u8, end: u64 },
    /// `pos` is the limit: no more records.
    End,
    /// The record at `pos` is incomplete: it extends beyond the limit.
    Cut(String),
    /// The record at `pos` claims more bytes than the reader accepts.
    TooLong(String),
}

impl Source {
    fn io(&self, error: std::io::Error) -> BagError {
        BagError::Io {
            path: self.path.clone(),
            error,
        }
    }

    fn read_at(&mut self, offset: u64, n: usize) -> Result<&[u8]> {
        if offset != self.pos {
            self.file
                .seek(SeekFrom::Start(offset))
                .map_err(|e| self.io(e))?;
        }
        self.buf.resize(n, 0);
        let r = self.file.read_exact(&mut self.buf);
        // After a failed read the position is unknown: force a seek next time.
        self.pos = if r.is_ok() {
            offset + n as u64
        } else {
            u64::MAX
        };
        r.map_err(|e| self.io(e))?;
        Ok(&self.buf)
    }

    /// Adds the bytes `start..end` of the file to `crc`.
    fn hash_range(&mut self, start: u64, end: u64, crc: &mut Crc32) -> Result<()> {
        let mut at = start;
        while at < end {
            let n = (end - at).min(HASH_BLOCK);
            crc.update(self.read_at(at, n as usize)?);
            at += n;
        }
        Ok(())
    }

    /// Reads the record at `pos` whose bytes must end by `limit`.
    fn next_record(&mut self, pos: u64, limit: u64) -> Result<Next> {
        if pos >= limit {
            return Ok(Next::End);
        }
        let avail = limit - pos;
        if avail < 9 {
            return Ok(Next::Cut(format!(
                "{avail} stray bytes at offset {pos}, not a whole record"
            )));
        }
        let head = self.read_at(pos, 9)?;
        let op = head[0];
        let len = u64::from_le_bytes(head[1..9].try_into().unwrap_or([0xff; 8]));
        if len > avail - 9 {
            return Ok(Next::Cut(format!(
                "record (opcode {op:#04x}) at offset {pos} needs {len} bytes, only {} remain",
                avail - 9
            )));
        }
        if len > RECORD_LIMIT {
            return Ok(Next::TooLong(format!(
                "record (opcode {op:#04x}) at offset {pos} is {len} bytes long, more than the \
                 {RECORD_LIMIT} the reader accepts"
            )));
        }
        let end = pos + 9 + len;
        self.buf.resize(9 + len as usize, 0);
        let r = self.file.read_exact(&mut self.buf[9..]);
        self.pos = if r.is_ok() { end } else { u64::MAX };
        r.map_err(|e| self.io(e))?;
        Ok(Next::Record { op, end })
    }

    fn body(&self) -> &[u8] {
        &self.buf[9..]
    }
}

/// Why the summary cannot be used.
enum NoSummary {
    /// The file has no (complete) summary: cut short, or written without one.
    Absent(String),
    /// There is a summary, but it is damaged or inconsistent.
    Unusable(String),
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

/// Iterator over a bag's messages, see [`BagReader::messages`].
pub struct Messages<'a> {
    bag: &'a BagReader,
    file: File,
    file_len: u64,
    reader: IndexedReader,
    buf: Vec<u8>,
    done: bool,
}

impl Messages<'_> {
    fn read_at(&mut self, offset: u64, n: u64) -> Result<()> {
        let io = |error| BagError::Io {
            path: self.bag.path.clone(),
            error,
        };
        // Checked on open; guards against a file that shrank since.
        if n > RECORD_LIMIT + LOOSE_RUN_LIMIT || offset.saturating_add(n) > self.file_len {
            return Err(io(std::io::Error::new(
                std::io::ErrorKind::UnexpectedEof,
                format!("{n} bytes at offset {offset} are beyond the end of the file"),
            )));
        }
        self.buf.resize(n as usize, 0);
        self.file
            .seek(SeekFrom::Start(offset))
            .and_then(|_| self.file.read_exact(&mut self.buf))
            .map_err(io)
    }

    /// The verified records of region `i`, `size` bytes (padded with a filler record).
    fn load(&mut self, i: usize, size: usize) -> Result<Vec<u8>> {
        let bag = self.bag;
        match &bag.regions[i] {
            Region::Loose { start, size: n, .. } => {
                self.read_at(*start, *n)?;
                let mut data = std::mem::take(&mut self.buf);
                pad(&mut data, size);
                Ok(data)
            }
            Region::Chunk { index, messages } => {
                self.read_at(index.chunk_start_offset, index.chunk_length)?;
                match check_chunk(&self.buf, index) {
                    Ok(mut data) => {
                        pad(&mut data, size);
                        Ok(data)
                    }
                    Err(reason) if bag.options.skip_damaged => {
                        let mut damaged = bag
                            .damaged
                            .lock()
                            .unwrap_or_else(std::sync::PoisonError::into_inner);
                        if !damaged.iter().any(|d| d.offset == index.chunk_start_offset) {
                            let lost = messages.or_else(|| {
                                lost_messages(&mut self.file, self.file_len, index)
                                    .map(|m| m.values().sum())
                            });
                            damaged.push(DamagedChunk {
                                offset: index.chunk_start_offset,
                                length: index.chunk_length,
                                messages_lost: lost,
                                reason,
                            });
                        }
                        let mut data = Vec::new();
                        pad(&mut data, size);
                        Ok(data)
                    }
                    Err(reason) => Err(BagError::Damaged {
                        path: bag.path.clone(),
                        what: "chunk",
                        offset: index.chunk_start_offset,
                        reason,
                    }),
                }
            }
        }
    }
}

/// Pads `data` with a filler record (ignored by the message reader) to `size` bytes.
fn pad(data: &mut Vec<u8>, size: usize) {
    if data.len() + 9 <= size {
        let n = size - data.len() - 9;
        data.push(FILLER_OPCODE);
        data.extend_from_slice(&(n as u64).to_le_bytes());
        data.resize(size, 0);
    }
}

impl Iterator for Messages<'_> {
    type Item = Result<BagMessage>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.done {
            return None;
        }
        let bag = self.bag;
        let path = &bag.path;
        loop {
            let event = match self.reader.next_event() {
                None => {
                    self.done = true;
                    return None;
                }
                Some(Err(error)) => {
                    self.done = true;
                    return Some(Err(BagError::Mcap {
                        path: path.clone(),
                        error,
                    }));
                }
                Some(Ok(e)) => e,
            };
            match event {
                IndexedReadEvent::ReadChunkRequest { offset, length } => {
                    let loaded = match bag.fake.get(&offset) {
                        Some(&i) => self.load(i, length),
                        None => Err(BagError::Corrupt {
                            path: path.clone(),
                            reason: format!("no chunk at made-up offset {offset}"),
                        }),
                    };
                    let inserted = loaded.and_then(|data| {
                        self.reader
                            .insert_chunk_record_data(offset, &data)
                            .map_err(|error| BagError::Mcap {
                                path: path.clone(),
                                error,
                            })
                    });
                    if let Err(e) = inserted {
                        self.done = true;
                        return Some(Err(e));
                    }
                }
                IndexedReadEvent::Message { header, data } => {
                    if let Some(r) = bag.routes.get(&header.channel_id) {
                        return Some(Ok(BagMessage {
                            stream: r.stream,
                            machine: r.machine.clone(),
                            topic: r.topic.clone(),
                            log_time: header.log_time,
                            publish_time: header.publish_time,
                            data: data.to_vec(),
                        }));
                    }
                }
            }
        }
    }
}

/// Fails when, in log-time order, chunks overlapping in time would hold more than
/// `OVERLAP_LIMIT` decompressed bytes at once.
fn check_overlap(regions: &[Region]) -> Result<(), String> {
    // (time, 0 = starts / 1 = ends, bytes): at equal times a chunk starts before one ends.
    let mut events: Vec<(u64, u8, u64)> = Vec::with_capacity(2 * regions.len());
    for r in regions {
        let (a, b) = r.times();
        if a > b {
            return Err(format!(
                "chunk at offset {} has start time {a} after its end time {b}",
                r.offset()
            ));
        }
        events.push((a, 0, r.data_size()));
        events.push((b, 1, r.data_size()));
    }
    events.sort_unstable();
    let mut held = 0u64;
    for (t, kind, size) in events {
        if kind == 0 {
            held = held.saturating_add(size);
            if held > OVERLAP_LIMIT {
                return Err(format!(
                    "chunks overlapping in time at log time {t} hold more than \
                     {OVERLAP_LIMIT} bytes uncompressed; reading them in time order would \
                     need that much memory"
                ));
            }
        } else {
            held = held.saturating_sub(size);
        }
    }
    Ok(())
}

/// Reads the summary section into `cat`. `Err` means it is absent or unusable and the file
/// must be scanned.
fn read_summary(src: &mut Source, header_end: u64, cat: &mut Catalog) -> Result<(), NoSummary> {
    let absent = |s: &str| NoSummary::Absent(s.to_owned());
    let len = src.len;
    if len < header_end + FOOTER_AND_MAGIC {
        return Err(absent("too short for a footer"));
    }
    let footer_start = len - FOOTER_AND_MAGIC;
    let tail = src
        .read_at(footer_start, FOOTER_AND_MAGIC as usize)
        .map_err(|e| NoSummary::Absent(e.to_string()))?
        .to_vec();
    if &tail[29..] != MAGIC {
        return Err(absent("no end magic"));
    }
    if tail[0] != op::FOOTER {
        return Err(absent("no footer record"));
    }
    let summary_start = u64::from_le_bytes([
        tail[9], tail[10], tail[11], tail[12], tail[13], tail[14], tail[15], tail[16],
    ]);
    let summary_crc = u32::from_le_bytes([tail[25], tail[26], tail[27], tail[28]]);
    if summary_start == 0 {
        return Err(absent("no summary section"));
    }
    read_summary_section(
        src,
        header_end,
        summary_start,
        footer_start,
        &tail,
        summary_crc,
        cat,
    )
    .map_err(NoSummary::Unusable)
}

fn read_summary_section(
    src: &mut Source,
    header_end: u64,
    summary_start: u64,
    footer_start: u64,
    footer: &[u8],
    summary_crc: u32,
    cat: &mut Catalog,
) -> Result<(), String> {
    if summary_start < header_end + DATA_END_LEN || summary_start > footer_start {
        return Err(format!("summary start {summary_start} out of range"));
    }
    if summary_crc != 0 {
        let mut crc = Crc32::new();
        src.hash_range(summary_start, footer_start, &mut crc)
            .map_err(|e| e.to_string())?;
        crc.update(&footer[..FOOTER_CRC_PREFIX]);
        let computed = crc.finish();
        if computed != summary_crc {
            return Err(format!("summary {}", crc_mismatch(summary_crc, computed)));
        }
    }
    // The data-end record sits right before the summary; it holds the data section CRC.
    let data_end = summary_start - DATA_END_LEN;
    let rec = src
        .read_at(data_end, DATA_END_LEN as usize)
        .map_err(|e| e.to_string())?;
    if rec[0] != op::DATA_END || rec[1..9] != 4u64.to_le_bytes() {
        return Err("no data-end record before the summary".into());
    }
    let data_crc = u32::from_le_bytes([rec[9], rec[10], rec[11], rec[12]]);
    cat.data_end = Some((data_end, data_crc));
    let mut stats = None;
    let mut metadata_indexes = Vec::new();
    let mut chunk_indexes = Vec::new();
    let mut pos = summary_start;
    loop {
        let (op, end) = match src
            .next_record(pos, footer_start)
            .map_err(|e| e.to_string())?
        {
            Next::End => break,
            Next::Cut(reason) | Next::TooLong(reason) => return Err(reason),
            Next::Record { op, end } => (op, end),
        };
        let keep = matches!(
            op,
            op::SCHEMA | op::CHANNEL | op::STATISTICS | op::CHUNK_INDEX | op::METADATA_INDEX
        );
        if keep {
            let record = layout::parse(op, src.body())
                .map_err(|e| format!("record (opcode {op:#04x}) at offset {pos}: {e}"))?;
            match record {
                Record::Schema { header, .. } => {
                    cat.add_schema(header.id, header.name, header.encoding)
                }
                Record::Channel(c) => cat.add_channel(c),
                Record::Statistics(s) => stats = Some(s),
                Record::ChunkIndex(i) => chunk_indexes.push(i),
                Record::MetadataIndex(i) => metadata_indexes.push(i),
                _ => {}
            }
        }
        pos = end;
    }
    let stats = stats.ok_or("no statistics record")?;
    if chunk_indexes.len() as u64 != u64::from(stats.chunk_count) {
        return Err("chunk index count differs from statistics".into());
    }
    if metadata_indexes.len() as u64 != u64::from(stats.metadata_count) {
        return Err("metadata index count differs from statistics".into());
    }
    if stats.message_count > 0 && stats.chunk_count == 0 {
        return Err("messages outside chunks".into());
    }
    for (id, _) in stats.channel_message_counts.iter().filter(|(_, &n)| n > 0) {
        if !cat.channels.contains_key(id) {
            return Err(format!("summary lacks channel {id}"));
        }
    }
    for c in &chunk_indexes {
        let data = c.compressed_data_offset().map_err(|e| e.to_string())?;
        let fits = c.chunk_start_offset >= header_end
            && c.chunk_start_offset
                .checked_add(c.chunk_length)
                .is_some_and(|e| e <= data_end)
            && data
                .checked_add(c.compressed_size)
                .is_some_and(|e| e <= data_end)
            && c.chunk_length <= RECORD_LIMIT + 9
            && c.uncompressed_size <= RECORD_LIMIT
            && c.compressed_size <= RECORD_LIMIT
            && c.message_start_time <= c.message_end_time;
        if !fits {
            return Err(format!(
                "chunk index at {} out of range",
                c.chunk_start_offset
            ));
        }
    }
    metadata_indexes.sort_by_key(|m| m.offset);
    for m in &metadata_indexes {
        if m.offset < header_end || m.offset.checked_add(m.length).is_none_or(|e| e > data_end) {
            return Err("metadata index out of range".into());
        }
        let end = m.offset + m.length;
        match src.next_record(m.offset, end).map_err(|e| e.to_string())? {
            Next::Record {
                op: op::METADATA, ..
            } => {}
            _ => return Err("metadata index does not point at a metadata record".into()),
        }
        let record = layout::parse(op::METADATA, src.body())
            .map_err(|e| format!("metadata record at offset {}: {e}", m.offset))?;
        match record {
            Record::Metadata(md) => push_metadata(cat, md),
            _ => return Err("metadata record does not parse".into()),
        }
    }
    cat.regions = chunk_indexes
        .into_iter()
        .map(|index| Region::Chunk {
            index,
            messages: None,
        })
        .collect();
    cat.message_counts = stats.channel_message_counts;
    if stats.message_count > 0 {
        cat.time_range = Some((stats.message_start_time, stats.message_end_time));
    }
    Ok(())
}

/// With a usable summary: checks the data section CRC (one pass over the file). On a mismatch
/// finds the damaged chunks: the first is an error, or, when skipping, all are dropped and
/// counted.
fn verify_data_section(src: &mut Source, cat: &mut Catalog) -> Result<()> {
    let Some((data_end, expected)) = cat.data_end else {
        return Ok(());
    };
    if expected == 0 {
        return Ok(());
    }
    let mut crc = Crc32::new();
    src.hash_range(0, data_end, &mut crc)?;
    let computed = crc.finish();
    if computed == expected {
        return Ok(());
    }
    let mismatch = crc_mismatch(expected, computed);
    let mut kept = Vec::new();
    for region in std::mem::take(&mut cat.regions) {
        let Region::Chunk { index, .. } = &region else {
            kept.push(region);
            continue;
        };
        let record = src.read_at(index.chunk_start_offset, index.chunk_length as usize)?;
        let Err(reason) = check_chunk(record, index) else {
            kept.push(region);
            continue;
        };
        if !cat.skip_damaged {
            return Err(BagError::Damaged {
                path: src.path.clone(),
                what: "chunk",
                offset: index.chunk_start_offset,
                reason,
            });
        }
        let lost = lost_messages(&mut src.file, src.len, index);
        src.pos = u64::MAX;
        match &lost {
            Some(by_channel) => {
                for (&channel, &n) in by_channel {
                    if let Some(count) = cat.message_counts.get_mut(&channel) {
                        *count = count.saturating_sub(n);
                    }
                    cat.lossy.insert(channel);
                }
            }
            None => cat.lost_unknown = true,
        }
        cat.damaged.push(DamagedChunk {
            offset: index.chunk_start_offset,
            length: index.chunk_length,
            messages_lost: lost.map(|m| m.values().sum()),
            reason,
        });
    }
    cat.regions = kept;
    data_section_mismatch(src, cat, mismatch)
}

/// A data-section CRC mismatch after every chunk was checked: an error when no chunk explains
/// it, a note when skipping.
fn data_section_mismatch(src: &Source, cat: &mut Catalog, mismatch: String) -> Result<()> {
    if cat.damaged.is_empty() {
        let reason = format!(
            "{mismatch} although every chunk verifies: metadata or index records are damaged"
        );
        if !cat.skip_damaged {
            return Err(BagError::Damaged {
                path: src.path.clone(),
                what: "data section",
                offset: 0,
                reason,
            });
        }
        cat.notes.push(format!("data section {reason}"));
    } else {
        cat.notes.push(format!(
            "data section {mismatch}: {} damaged chunk(s) skipped; damage outside the chunks \
             (metadata) cannot be ruled out",
            cat.damaged.len()
        ));
    }
    Ok(())
}

/// Messages of the chunk `index` by channel, from the message index records the index points
/// at; `None` when there are none or they are unreadable.
fn lost_messages<R: Read + Seek>(
    r: &mut R,
    file_len: u64,
    index: &ChunkIndex,
) -> Option<BTreeMap<u16, u64>> {
    if index.message_index_offsets.is_empty() {
        return None;
    }
    let mut out = BTreeMap::new();
    let mut buf = Vec::new();
    for (&channel, &offset) in &index.message_index_offsets {
        let mut head = [0u8; 9];
        r.seek(SeekFrom::Start(offset)).ok()?;
        r.read_exact(&mut head).ok()?;
        let len = u64::from_le_bytes(head[1..9].try_into().ok()?);
        let end = offset.checked_add(9)?.checked_add(len)?;
        if head[0] != op::MESSAGE_INDEX || len > RECORD_LIMIT || end > file_len {
            return None;
        }
        buf.resize(len as usize, 0);
        r.read_exact(&mut buf).ok()?;
        match layout::parse(op::MESSAGE_INDEX, &buf).ok()? {
            Record::MessageIndex(mi) if mi.channel_id == channel => {
                *out.entry(channel).or_default() += mi.records.len() as u64;
            }
            _ => return None,
        }
    }
    Some(out)
}

fn push_metadata(cat: &mut Catalog, md: mcap::records::Metadata) {
    if md.name == SAMPLE_COUNTS_METADATA {
        let counts = md
            .metadata
            .iter()
            .filter_map(|(k, v)| Some((k.clone(), v.parse().ok()?)))
            .collect();
        cat.sample_counts_by_topic = Some(counts);
    } else {
        cat.metadata.push(MetadataRecord {
            name: md.name,
            entries: md.metadata,
        });
    }
}

/// A run of loose (unchunked) message records being collected.
struct LooseRun {
    start: u64,
    end: u64,
    t_min: u64,
    t_max: u64,
}

/// Scans the data section record by record, keeping every complete chunk (CRC-verified) and
/// computing the data section CRC; stops at the data end record or at the first incomplete
/// record, which it reports as truncation. A damaged record, or an incomplete one in a file
/// that has its footer, is an error — except that when skipping damaged chunks, a damaged
/// chunk is counted and skipped and other damage ends the readable part like a truncation.
fn scan(src: &mut Source, header_end: u64, cat: &mut Catalog, no_summary: &str) -> Result<()> {
    cat.scanned = true;
    let len = src.len;
    let mut crc = Crc32::new();
    src.hash_range(0, header_end, &mut crc)?;
    let mut data_crc = None;
    let mut pos = header_end;
    let mut run: Option<LooseRun> = None;
    // The damaged chunk whose message index records may follow (they count its messages).
    let mut last_damaged: Option<usize> = None;
    let path = src.path.clone();
    let damaged = |what: &'static str, offset: u64, reason: String| BagError::Damaged {
        path: path.clone(),
        what,
        offset,
        reason,
    };
    let stop: Option<String> = loop {
        let (op, end) = match src.next_record(pos, len)? {
            Next::End => {
                break Some(
                    "the file ends without a data-end record (the writer did not finish)".into(),
                );
            }
            Next::Cut(reason) => {
                // A finished file is not cut short: its record framing is damaged.
                if !cat.skip_damaged && has_footer(src, pos)? {
                    return Err(damaged("record", pos, reason));
                }
                break Some(reason);
            }
            Next::TooLong(reason) => {
                if !cat.skip_damaged {
                    return Err(damaged("record", pos, reason));
                }
                break Some(reason);
            }
            Next::Record { op, end } => (op, end),
        };
        if op != op::DATA_END {
            crc.update(&src.buf);
        }
        if op != op::MESSAGE_INDEX {
            last_damaged = None;
        }
        if op == op::CHUNK || op == op::DATA_END || op == op::FOOTER || op == op::HEADER {
            close_run(&mut run, cat);
        }
        let result: Result<(), String> = match op {
            op::CHUNK => match scan_chunk(&src.buf, pos, cat) {
                Ok(()) => Ok(()),
                Err(reason) if cat.skip_damaged => {
                    cat.damaged.push(DamagedChunk {
                        offset: pos,
                        length: end - pos,
                        messages_lost: None,
                        reason,
                    });
                    last_damaged = Some(cat.damaged.len() - 1);
                    Ok(())
                }
                Err(reason) => return Err(damaged("chunk", pos, reason)),
            },
            op::MESSAGE_INDEX => {
                if let Some(i) = last_damaged {
                    if let Ok(Record::MessageIndex(mi)) = layout::parse(op, src.body()) {
                        let d = &mut cat.damaged[i];
                        d.messages_lost =
                            Some(d.messages_lost.unwrap_or(0) + mi.records.len() as u64);
                    }
                }
                Ok(())
            }
            op::MESSAGE => match message_header(src.body()) {
                Some((channel, t)) => {
                    let stream = cat
                        .channels
                        .get(&channel)
                        .and_then(|c| stream_of_topic(&c.topic));
                    let samples = stream
                        .and_then(|s| peek(s, &src.body()[22..]))
                        .map(|p| p.samples);
                    count_message(cat, channel, t, samples);
                    match &mut run {
                        Some(r) if end - r.start <= LOOSE_RUN_LIMIT => {
                            r.end = end;
                            r.t_min = r.t_min.min(t);
                            r.t_max = r.t_max.max(t);
                        }
                        _ => {
                            close_run(&mut run, cat);
                            run = Some(LooseRun {
                                start: pos,
                                end,
                                t_min: t,
                                t_max: t,
                            });
                        }
                    }
                    Ok(())
                }
                None => Err("message record too short".into()),
            },
            op::SCHEMA | op::CHANNEL | op::METADATA | op::DATA_END => {
                match layout::parse(op, src.body()) {
                    Ok(Record::Schema { header, .. }) => {
                        cat.add_schema(header.id, header.name, header.encoding);
                        Ok(())
                    }
                    Ok(Record::Channel(c)) => {
                        cat.add_channel(c);
                        Ok(())
                    }
                    Ok(Record::Metadata(md)) => {
                        push_metadata(cat, md);
                        Ok(())
                    }
                    Ok(Record::DataEnd(d)) => {
                        data_crc = Some(d.data_section_crc);
                        Ok(())
                    }
                    Ok(_) => Ok(()),
                    Err(e) => Err(e.to_string()),
                }
            }
            op::HEADER => Err("a second header record".into()),
            _ => Ok(()),
        };
        if let Err(reason) = result {
            let reason = format!("damaged record (opcode {op:#04x}) at offset {pos}: {reason}");
            if !cat.skip_damaged {
                return Err(damaged("record", pos, reason));
            }
            break Some(reason);
        }
        pos = end;
        if op == op::DATA_END || op == op::FOOTER {
            break None;
        }
    };
    close_run(&mut run, cat);
    if let Some(expected) = data_crc.filter(|&c| c != 0) {
        let computed = crc.finish();
        if computed != expected {
            data_section_mismatch(src, cat, crc_mismatch(expected, computed))?;
        }
    }
    if let Some(reason) = stop {
        cat.truncation = Some(Truncation {
            file_len: len,
            readable_len: pos,
            reason,
        });
    } else if !has_footer(src, pos)? {
        cat.truncation = Some(Truncation {
            file_len: len,
            readable_len: pos,
            reason: format!(
                "the summary or footer is missing or damaged ({no_summary}); the data section \
                 is complete"
            ),
        });
    }
    // Sample counts recorded by the writer describe the whole file; a scan counts itself.
    cat.sample_counts_by_topic = None;
    Ok(())
}

fn has_footer(src: &mut Source, data_end: u64) -> Result<bool> {
    if src.len < data_end + FOOTER_AND_MAGIC {
        return Ok(false);
    }
    let tail = src.read_at(src.len - FOOTER_AND_MAGIC, FOOTER_AND_MAGIC as usize)?;
    Ok(tail[0] == op::FOOTER && &tail[29..] == MAGIC)
}

fn close_run(run: &mut Option<LooseRun>, cat: &mut Catalog) {
    let Some(r) = run.take() else { return };
    cat.regions.push(Region::Loose {
        start: r.start,
        size: r.end - r.start,
        t_min: r.t_min,
        t_max: r.t_max,
    });
}

fn count_message(cat: &mut Catalog, channel: u16, log_time: u64, samples: Option<u64>) {
    *cat.message_counts.entry(channel).or_default() += 1;
    *cat.sample_counts.entry(channel).or_default() += samples.unwrap_or(0);
    cat.add_time(log_time);
}

/// The records of well-formed record data (as [`decode_chunk`] returns): offset in `data`,
/// opcode and body.
fn records(data: &[u8]) -> impl Iterator<Item = (usize, u8, &[u8])> {
    let mut rest = data;
    let mut at = 0;
    std::iter::from_fn(move || {
        let (&op, tail) = rest.split_first()?;
        let len = u64::from_le_bytes(tail.get(..8)?.try_into().ok()?);
        let body = tail.get(8..)?.get(..usize::try_from(len).ok()?)?;
        rest = &tail[8 + body.len()..];
        let start = at;
        at += 9 + body.len();
        Some((start, op, body))
    })
}

/// Decompresses one chunk record (`record` = opcode, length, body) and verifies the CRC of its
/// uncompressed records (unless it is 0, "not computed"). Returns the header and the records,
/// re-framed (opcode, length, body): exactly the chunk's uncompressed data. `Err` says what is
/// damaged.
fn decode_chunk(record: &[u8]) -> Result<(ChunkHeader, Vec<u8>), String> {
    let body = record.get(9..).ok_or("chunk record too short")?;
    let header = match layout::parse(op::CHUNK, body).map_err(|e| e.to_string())? {
        Record::Chunk { header, .. } => header,
        _ => return Err("not a chunk".into()),
    };
    if header.uncompressed_size > RECORD_LIMIT {
        return Err(format!(
            "chunk claims {} uncompressed bytes, more than the {RECORD_LIMIT} the reader accepts",
            header.uncompressed_size
        ));
    }
    let options = LinearReaderOptions::default()
        .with_skip_start_magic(true)
        .with_skip_end_magic(true)
        .with_prevalidate_chunk_crcs(true)
        .with_record_length_limit(RECORD_LIMIT as usize);
    let mut reader = LinearReader::new_with_options(options);
    let mut input = record;
    let mut out = Vec::with_capacity(header.uncompressed_size as usize);
    while let Some(event) = reader.next_event() {
        let event = event.map_err(|e| match e {
            McapError::BadChunkCrc { saved, calculated } => crc_mismatch(saved, calculated),
            e => e.to_string(),
        })?;
        match event {
            LinearReadEvent::ReadRequest(n) => {
                let k = n.min(input.len());
                reader.insert(k).copy_from_slice(&input[..k]);
                reader.notify_read(k);
                input = &input[k..];
            }
            LinearReadEvent::Record { opcode, data } => {
                if out.len() + 9 + data.len() > header.uncompressed_size as usize {
                    return Err("chunk records exceed its uncompressed size".into());
                }
                out.push(opcode);
                out.extend_from_slice(&(data.len() as u64).to_le_bytes());
                out.extend_from_slice(data);
            }
        }
    }
    if out.len() as u64 != header.uncompressed_size {
        return Err(format!(
            "chunk records fill {} of its {} uncompressed bytes",
            out.len(),
            header.uncompressed_size
        ));
    }
    Ok((header, out))
}

/// Checks the chunk record `record` (read where `index` points) against its index entry and
/// decodes it; `Ok` holds its verified uncompressed records.
fn check_chunk(record: &[u8], index: &ChunkIndex) -> Result<Vec<u8>, String> {
    let (op, len) = match record {
        [op, len @ ..] if len.len() >= 8 => (
            *op,
            u64::from_le_bytes(len[..8].try_into().unwrap_or([0xff; 8])),
        ),
        _ => return Err("chunk record too short".into()),
    };
    if op != op::CHUNK {
        return Err(format!(
            "the chunk index points at a record with opcode {op:#04x}, not a chunk"
        ));
    }
    if len.checked_add(9) != Some(index.chunk_length) {
        return Err(format!(
            "chunk record length {len} differs from the {} bytes in its index entry",
            index.chunk_length.saturating_sub(9)
        ));
    }
    let (header, data) = decode_chunk(record)?;
    if header.compression != index.compression
        || header.compressed_size != index.compressed_size
        || header.uncompressed_size != index.uncompressed_size
    {
        return Err("chunk header differs from its index entry".into());
    }
    for (_, op, body) in records(&data) {
        if op == op::MESSAGE {
            let (_, t) = message_header(body).ok_or("message record too short")?;
            if t < index.message_start_time || t > index.message_end_time {
                return Err(format!(
                    "message log time {t} outside the chunk's time range {}..={}",
                    index.message_start_time, index.message_end_time
                ));
            }
        }
    }
    Ok(data)
}

/// Decodes and checks one chunk record (`record` = opcode, length, body at file offset
/// `offset`); on success adds its schemas, channels and messages to `cat` and indexes it.
fn scan_chunk(record: &[u8], offset: u64, cat: &mut Catalog) -> Result<(), String> {
    let (header, data) = decode_chunk(record)?;
    let mut schemas = Vec::new();
    let mut channels: Vec<mcap::records::Channel> = Vec::new();
    let mut messages = Vec::new();
    for (at, opcode, body) in records(&data) {
        match opcode {
            op::SCHEMA | op::CHANNEL => {
                let record = layout::parse(opcode, body)
                    .map_err(|e| format!("at byte {at} of its uncompressed records: {e}"))?;
                match record {
                    Record::Schema { header, .. } => schemas.push(header),
                    Record::Channel(c) => channels.push(c),
                    _ => {}
                }
            }
            op::MESSAGE => {
                let (channel, t) = message_header(body).ok_or("message record too short")?;
                let topic = match channels.iter().find(|c| c.id == channel) {
                    Some(c) => Some(c.topic.as_str()),
                    None => cat.channels.get(&channel).map(|c| c.topic.as_str()),
                };
                let samples = topic
                    .and_then(stream_of_topic)
                    .and_then(|s| peek(s, &body[22..]));
                messages.push((channel, t, samples.map(|p| p.samples)));
            }
            _ => {}
        }
    }
    for s in schemas {
        cat.add_schema(s.id, s.name, s.encoding);
    }
    for c in channels {
        cat.add_channel(c);
    }
    let (mut t_min, mut t_max) = (u64::MAX, 0);
    for &(channel, t, samples) in &messages {
        count_message(cat, channel, t, samples);
        t_min = t_min.min(t);
        t_max = t_max.max(t);
    }
    if !messages.is_empty() {
        cat.regions.push(Region::Chunk {
            index: ChunkIndex {
                message_start_time: t_min,
                message_end_time: t_max,
                chunk_start_offset: offset,
                chunk_length: record.len() as u64,
                message_index_offsets: BTreeMap::new(),
                message_index_length: 0,
                compression: header.compression,
                compressed_size: header.compressed_size,
                uncompressed_size: header.uncompressed_size,
            },
            messages: Some(messages.len() as u64),
        });
    }
    Ok(())
}
