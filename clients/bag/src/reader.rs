//! Reading bags: through the summary when the file is complete, by a linear scan of the
//! complete chunks when it was cut short.
use crate::batch::{peek, RawBatch};
use crate::{Artifact, BagError, Result, ARTIFACT_METADATA, ENCODING, SAMPLE_COUNTS_METADATA};
use mcap::records::{op, ChunkIndex};
use mcap::sans_io::{
    IndexedReadEvent, IndexedReader, IndexedReaderOptions, LinearReadEvent, LinearReader,
    LinearReaderOptions,
};
use mcap::{parse_record, records::Record, MAGIC};
use scancorr_proto::{Stream, DEFAULT_PREFIX};
use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::{BufReader, Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Largest record (or decompressed chunk) the reader accepts; guards allocations against
/// corrupt length fields. scancorr bags use 1 MiB chunks.
const RECORD_LIMIT: u64 = 256 << 20;
/// opcode + length + footer body (summary start, summary offset start, crc) + end magic.
const FOOTER_AND_MAGIC: u64 = 1 + 8 + 20 + 8;
/// Loose (unchunked) messages are read in runs of at most this many bytes.
const LOOSE_RUN_LIMIT: u64 = 4 << 20;
/// Loose-message runs get made-up chunk offsets from here on (beyond any real file offset).
const FAKE_OFFSET_BASE: u64 = 1 << 62;
const ALL_STREAMS: [Stream; 6] = [
    Stream::Command,
    Stream::Scale,
    Stream::Probe,
    Stream::Temperature,
    Stream::Points,
    Stream::Alarms,
];

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
            context: format!(" on {} at log time {}", self.topic, self.log_time),
            error,
        })
    }
}

#[derive(Clone)]
struct Route {
    stream: Stream,
    machine: Arc<str>,
    topic: Arc<str>,
}

/// An opened bag: channels, metadata and whether it was cut short are read on open; messages
/// are streamed chunk by chunk by [`BagReader::messages`].
pub struct BagReader {
    path: PathBuf,
    profile: String,
    library: String,
    prefix: String,
    truncation: Option<Truncation>,
    channels: Vec<ChannelInfo>,
    unknown: Vec<UnknownChannel>,
    metadata: Vec<MetadataRecord>,
    time_range: Option<(u64, u64)>,
    routes: HashMap<u16, Route>,
    summary: mcap::Summary,
    fake_regions: HashMap<u64, u64>,
}

impl std::fmt::Debug for BagReader {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("BagReader")
            .field("path", &self.path)
            .field("prefix", &self.prefix)
            .field("truncation", &self.truncation)
            .field("channels", &self.channels)
            .field("unknown", &self.unknown)
            .field("metadata", &self.metadata)
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
    chunk_indexes: Vec<ChunkIndex>,
    fake_regions: HashMap<u64, u64>,
    time_range: Option<(u64, u64)>,
    truncation: Option<Truncation>,
    scanned: bool,
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
    ALL_STREAMS.into_iter().find(|s| {
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
    /// The record at `pos` is incomplete or implausible.
    Cut(String),
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
            return Ok(Next::Cut(format!(
                "record (opcode {op:#04x}) at offset {pos} is {len} bytes long"
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

impl BagReader {
    /// Opens a bag: checks the magic and header, then reads the summary, or scans the file
    /// when it has none (cut short, or written without one).
    pub fn open(path: impl AsRef<Path>) -> Result<BagReader> {
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
        let mut cat = Catalog::default();
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
                match parse_record(op::HEADER, src.body()) {
                    Ok(Record::Header(h)) => {
                        cat.profile = h.profile;
                        cat.library = h.library;
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
            Next::End | Next::Cut(_) => {
                return Err(corrupt(format!(
                    "the file ends inside the MCAP header ({len} bytes)"
                )))
            }
        };
        if read_summary(&mut src, header_end, &mut cat).is_err() {
            cat = Catalog {
                profile: cat.profile,
                library: cat.library,
                ..Catalog::default()
            };
            scan(&mut src, header_end, &mut cat)?;
        }
        Self::build(path, cat)
    }

    fn build(path: PathBuf, mut cat: Catalog) -> Result<BagReader> {
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
        let summary = mcap::Summary {
            chunk_indexes: std::mem::take(&mut cat.chunk_indexes),
            ..Default::default()
        };
        Ok(BagReader {
            path,
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
            fake_regions: cat.fake_regions,
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

    /// Iterates over the messages of the scancorr channels in log-time order (file order on
    /// equal times), one chunk in memory at a time. After an error the iterator ends.
    pub fn messages(&self) -> Result<Messages<'_>> {
        let io = |error| BagError::Io {
            path: self.path.clone(),
            error,
        };
        let file = File::open(&self.path).map_err(io)?;
        let options = IndexedReaderOptions::new().with_record_length_limit(RECORD_LIMIT as usize);
        let reader = IndexedReader::new_with_options(&self.summary, options).map_err(|error| {
            BagError::Mcap {
                path: self.path.clone(),
                error,
            }
        })?;
        Ok(Messages {
            bag: self,
            file,
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
    reader: IndexedReader,
    buf: Vec<u8>,
    done: bool,
}

impl Iterator for Messages<'_> {
    type Item = Result<BagMessage>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.done {
            return None;
        }
        let path = &self.bag.path;
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
                    let real = self
                        .bag
                        .fake_regions
                        .get(&offset)
                        .copied()
                        .unwrap_or(offset);
                    self.buf.resize(length, 0);
                    let read = self
                        .file
                        .seek(SeekFrom::Start(real))
                        .and_then(|_| self.file.read_exact(&mut self.buf));
                    if let Err(error) = read {
                        self.done = true;
                        return Some(Err(BagError::Io {
                            path: path.clone(),
                            error,
                        }));
                    }
                    if let Err(error) = self.reader.insert_chunk_record_data(offset, &self.buf) {
                        self.done = true;
                        return Some(Err(BagError::Mcap {
                            path: path.clone(),
                            error,
                        }));
                    }
                }
                IndexedReadEvent::Message { header, data } => {
                    if let Some(r) = self.bag.routes.get(&header.channel_id) {
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

/// Reads the summary section into `cat`. `Err(reason)` means it is absent or unusable and the
/// file must be scanned.
fn read_summary(src: &mut Source, header_end: u64, cat: &mut Catalog) -> Result<(), String> {
    let len = src.len;
    if len < header_end + FOOTER_AND_MAGIC {
        return Err("too short for a footer".into());
    }
    let footer_start = len - FOOTER_AND_MAGIC;
    let tail = src
        .read_at(footer_start, FOOTER_AND_MAGIC as usize)
        .map_err(|e| e.to_string())?;
    if &tail[29..] != MAGIC {
        return Err("no end magic".into());
    }
    if tail[0] != op::FOOTER {
        return Err("no footer record".into());
    }
    let summary_start = u64::from_le_bytes(tail[9..17].try_into().map_err(|_| "footer")?);
    if summary_start == 0 {
        return Err("no summary section".into());
    }
    if summary_start < header_end || summary_start > footer_start {
        return Err(format!("summary start {summary_start} out of range"));
    }
    let mut stats = None;
    let mut metadata_indexes = Vec::new();
    let mut pos = summary_start;
    loop {
        let (op, end) = match src
            .next_record(pos, footer_start)
            .map_err(|e| e.to_string())?
        {
            Next::End => break,
            Next::Cut(reason) => return Err(reason),
            Next::Record { op, end } => (op, end),
        };
        let keep = matches!(
            op,
            op::SCHEMA | op::CHANNEL | op::STATISTICS | op::CHUNK_INDEX | op::METADATA_INDEX
        );
        if keep {
            match parse_record(op, src.body()).map_err(|e| e.to_string())? {
                Record::Schema { header, .. } => {
                    cat.add_schema(header.id, header.name, header.encoding)
                }
                Record::Channel(c) => cat.add_channel(c),
                Record::Statistics(s) => stats = Some(s),
                Record::ChunkIndex(i) => cat.chunk_indexes.push(i),
                Record::MetadataIndex(i) => metadata_indexes.push(i),
                _ => {}
            }
        }
        pos = end;
    }
    let stats = stats.ok_or("no statistics record")?;
    if cat.chunk_indexes.len() != stats.chunk_count as usize {
        return Err("chunk index count differs from statistics".into());
    }
    if metadata_indexes.len() != stats.metadata_count as usize {
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
    for c in &cat.chunk_indexes {
        let data = c.compressed_data_offset().map_err(|e| e.to_string())?;
        let fits = c.chunk_start_offset >= header_end
            && c.chunk_start_offset
                .checked_add(c.chunk_length)
                .is_some_and(|e| e <= summary_start)
            && data
                .checked_add(c.compressed_size)
                .is_some_and(|e| e <= summary_start)
            && c.uncompressed_size <= RECORD_LIMIT
            && c.compressed_size <= RECORD_LIMIT;
        if !fits {
            return Err(format!(
                "chunk index at {} out of range",
                c.chunk_start_offset
            ));
        }
    }
    metadata_indexes.sort_by_key(|m| m.offset);
    for m in &metadata_indexes {
        if m.offset < header_end
            || m.offset
                .checked_add(m.length)
                .is_none_or(|e| e > summary_start)
        {
            return Err("metadata index out of range".into());
        }
        let end = m.offset + m.length;
        match src.next_record(m.offset, end).map_err(|e| e.to_string())? {
            Next::Record {
                op: op::METADATA, ..
            } => {}
            _ => return Err("metadata index does not point at a metadata record".into()),
        }
        match parse_record(op::METADATA, src.body()).map_err(|e| e.to_string())? {
            Record::Metadata(md) => push_metadata(cat, md),
            _ => return Err("metadata record does not parse".into()),
        }
    }
    cat.message_counts = stats.channel_message_counts;
    if stats.message_count > 0 {
        cat.time_range = Some((stats.message_start_time, stats.message_end_time));
    }
    Ok(())
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

/// Scans the data section record by record, keeping every complete chunk; stops at the data
/// end record or at the first incomplete or damaged record, which it reports as truncation.
fn scan(src: &mut Source, header_end: u64, cat: &mut Catalog) -> Result<()> {
    cat.scanned = true;
    let len = src.len;
    let mut pos = header_end;
    let mut run: Option<LooseRun> = None;
    let stop: Option<String> = loop {
        let (op, end) = match src.next_record(pos, len)? {
            Next::End => {
                break Some(
                    "the file ends without a data-end record (the writer did not finish)".into(),
                );
            }
            Next::Cut(reason) => break Some(reason),
            Next::Record { op, end } => (op, end),
        };
        if op == op::CHUNK || op == op::DATA_END || op == op::FOOTER || op == op::HEADER {
            close_run(&mut run, cat);
        }
        let result: Result<(), String> = match op {
            op::CHUNK => scan_chunk(&src.buf, pos, cat),
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
            op::SCHEMA | op::CHANNEL | op::METADATA => match parse_record(op, src.body()) {
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
                Ok(_) => Ok(()),
                Err(e) => Err(e.to_string()),
            },
            op::HEADER => Err("a second header record".into()),
            _ => Ok(()),
        };
        if let Err(reason) = result {
            break Some(format!(
                "damaged record (opcode {op:#04x}) at offset {pos}: {reason}"
            ));
        }
        pos = end;
        if op == op::DATA_END || op == op::FOOTER {
            break None;
        }
    };
    close_run(&mut run, cat);
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
            reason: "the summary or footer is missing or damaged; the data section is complete"
                .into(),
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
    let fake_start = FAKE_OFFSET_BASE + ((cat.fake_regions.len() as u64) << 32);
    let size = r.end - r.start;
    let index = ChunkIndex {
        message_start_time: r.t_min,
        message_end_time: r.t_max,
        chunk_start_offset: fake_start,
        chunk_length: size,
        message_index_offsets: BTreeMap::new(),
        message_index_length: 0,
        compression: String::new(),
        compressed_size: size,
        uncompressed_size: size,
    };
    if let Ok(data_offset) = index.compressed_data_offset() {
        cat.fake_regions.insert(data_offset, r.start);
        cat.chunk_indexes.push(index);
    }
}

fn count_message(cat: &mut Catalog, channel: u16, log_time: u64, samples: Option<u64>) {
    *cat.message_counts.entry(channel).or_default() += 1;
    *cat.sample_counts.entry(channel).or_default() += samples.unwrap_or(0);
    cat.add_time(log_time);
}

/// Decompresses and checks one chunk record (`record` = opcode, length, body at file offset
/// `offset`); on success adds its schemas, channels and messages to `cat` and indexes it.
fn scan_chunk(record: &[u8], offset: u64, cat: &mut Catalog) -> Result<(), String> {
    let header = match parse_record(op::CHUNK, &record[9..]).map_err(|e| e.to_string())? {
        Record::Chunk { header, .. } => header,
        _ => return Err("not a chunk".into()),
    };
    if header.uncompressed_size > RECORD_LIMIT {
        return Err(format!(
            "chunk claims {} uncompressed bytes",
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
    let mut schemas = Vec::new();
    let mut channels = Vec::new();
    let mut messages = Vec::new();
    while let Some(event) = reader.next_event() {
        match event.map_err(|e| e.to_string())? {
            LinearReadEvent::ReadRequest(n) => {
                let k = n.min(input.len());
                reader.insert(k).copy_from_slice(&input[..k]);
                reader.notify_read(k);
                input = &input[k..];
            }
            LinearReadEvent::Record { opcode, data } => match opcode {
                op::SCHEMA | op::CHANNEL => {
                    match parse_record(opcode, data).map_err(|e| e.to_string())? {
                        Record::Schema { header, .. } => schemas.push(header),
                        Record::Channel(c) => channels.push(c),
                        _ => {}
                    }
                }
                op::MESSAGE => {
                    let (channel, t) = message_header(data).ok_or("message record too short")?;
                    let topic = match channels
                        .iter()
                        .find(|c: &&mcap::records::Channel| c.id == channel)
                    {
                        Some(c) => Some(c.topic.as_str()),
                        None => cat.channels.get(&channel).map(|c| c.topic.as_str()),
                    };
                    let samples = topic
                        .and_then(stream_of_topic)
                        .and_then(|s| peek(s, &data[22..]));
                    messages.push((channel, t, samples.map(|p| p.samples)));
                }
                _ => {}
            },
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
        cat.chunk_indexes.push(ChunkIndex {
            message_start_time: t_min,
            message_end_time: t_max,
            chunk_start_offset: offset,
            chunk_length: record.len() as u64,
            message_index_offsets: BTreeMap::new(),
            message_index_length: 0,
            compression: header.compression,
            compressed_size: header.compressed_size,
            uncompressed_size: header.uncompressed_size,
        });
    }
    Ok(())
}
