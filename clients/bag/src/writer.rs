//! Writing bags.
use crate::batch::{peek, BatchMessage};
use crate::{Artifact, BagError, Result, ARTIFACT_METADATA, ENCODING, SAMPLE_COUNTS_METADATA};
use mcap::records::{MessageHeader, Metadata};
use scancorr_proto::{Stream, FILE_DESCRIPTOR_SET};
use std::collections::BTreeMap;
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::sync::{mpsc, Arc, Mutex};

/// Default uncompressed chunk size: a crash loses at most about this much data.
pub const DEFAULT_CHUNK_SIZE: u64 = 1024 * 1024;

/// Default MCAP header profile of scancorr bags.
pub const DEFAULT_PROFILE: &str = "scancorr";

/// Chunk compression of a bag.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Compression {
    /// zstd (default): best ratio, fast enough for well over 1 M samples/s.
    #[default]
    Zstd,
    /// lz4: faster, larger files.
    Lz4,
    /// No compression.
    None,
}

/// How a bag is written: the MCAP header profile plus chunking. Exists so the recorder and
/// tests can pick chunk size/compression; `BagHeader::default()` is what scancorr records.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BagHeader {
    /// MCAP header `profile` (default `scancorr`).
    pub profile: String,
    /// Target uncompressed chunk size in bytes (default 1 MiB). Smaller chunks lose less on a
    /// crash and compress a little worse.
    pub chunk_size: u64,
    /// Chunk compression (default zstd).
    pub compression: Compression,
}

impl Default for BagHeader {
    fn default() -> Self {
        BagHeader {
            profile: DEFAULT_PROFILE.into(),
            chunk_size: DEFAULT_CHUNK_SIZE,
            compression: Compression::Zstd,
        }
    }
}

struct Slot {
    stream: Stream,
    machine: String,
    topic: String,
    id: u16,
    sequence: u32,
    samples: u64,
}

/// Records scancorr streams into an MCAP file: one channel per key expression, registered on
/// first use, chunked and compressed so a file cut short by a crash stays readable up to its
/// last complete chunk.
///
/// Dropping a writer without [`BagWriter::finish`] still finishes the file, ignoring errors.
pub struct BagWriter {
    path: PathBuf,
    mcap: Option<mcap::Writer<BufWriter<File>>>,
    prefix: Option<String>,
    schemas: [u16; Stream::ALL.len()],
    slots: Vec<Slot>,
    last: usize,
    scratch: Vec<u8>,
    writeback: Option<Writeback>,
    /// Channels beside scancorr's streams (e.g. [`crate::foxglove`]'s): id and sequence.
    extra: Vec<(u16, u32)>,
}

/// Payload bytes between two early syncs of a bag's file.
const WRITEBACK_BYTES: u64 = 8 * 1024 * 1024;

/// Has the OS write a large bag out while the rest is still being written: a thread syncs the
/// file's data every [`WRITEBACK_BYTES`] of payload, so the sync of [`BagWriter::finish`] waits
/// for the last part only. An error of these syncs is kept for `finish` to return (the OS
/// reports a write-back error once per open file: the final sync may not see it again).
struct Writeback {
    file: File,
    pending: u64,
    kick: Option<mpsc::SyncSender<()>>,
    thread: Option<std::thread::JoinHandle<()>>,
    error: Arc<Mutex<Option<std::io::Error>>>,
}

impl Writeback {
    fn new(file: &File) -> Option<Writeback> {
        Some(Writeback {
            file: file.try_clone().ok()?,
            pending: 0,
            kick: None,
            thread: None,
            error: Arc::default(),
        })
    }

    /// Counts `n` bytes written; asks for a sync every [`WRITEBACK_BYTES`] (none while one
    /// is still running: the next one covers its bytes too).
    fn wrote(&mut self, n: usize) {
        self.pending += n as u64;
        if self.pending < WRITEBACK_BYTES {
            return;
        }
        self.pending = 0;
        if self.kick.is_none() {
            let (tx, rx) = mpsc::sync_channel::<()>(1);
            let (Ok(file), error) = (self.file.try_clone(), self.error.clone()) else {
                return;
            };
            let thread = std::thread::Builder::new()
                .name("bag-writeback".into())
                .spawn(move || {
                    for () in rx {
                        if let Err(e) = file.sync_data() {
                            if let Ok(mut slot) = error.lock() {
                                slot.get_or_insert(e);
                            }
                            return;
                        }
                    }
                });
            let Ok(thread) = thread else {
                return;
            };
            self.kick = Some(tx);
            self.thread = Some(thread);
        }
        if let Some(k) = &self.kick {
            let _ = k.try_send(());
        }
    }

    /// Stops the thread; the first error of its syncs, if any.
    fn stop(&mut self) -> Option<std::io::Error> {
        drop(self.kick.take());
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
        self.error.lock().ok()?.take()
    }
}

/// The stream's index in [`Stream::ALL`] (a match, so a new stream cannot be forgotten).
fn stream_index(s: Stream) -> usize {
    match s {
        Stream::Command => 0,
        Stream::Scale => 1,
        Stream::Probe => 2,
        Stream::Temperature => 3,
        Stream::Distance => 4,
        Stream::Stage => 5,
        Stream::Points => 6,
        Stream::Alarms => 7,
    }
}

impl BagWriter {
    /// Creates (or truncates) the bag at `path` and writes the MCAP header.
    pub fn create(path: impl AsRef<Path>, header: BagHeader) -> Result<BagWriter> {
        let path = path.as_ref().to_path_buf();
        let file = File::create(&path).map_err(|error| BagError::Io {
            path: path.clone(),
            error,
        })?;
        BagWriter::from_file(file, path, header)
    }

    /// Writes the bag into `file`, already open for writing and empty (a temporary file the
    /// caller created exclusively, so nothing is reopened by name); `path` names it in
    /// messages.
    pub fn from_file(file: File, path: impl AsRef<Path>, header: BagHeader) -> Result<BagWriter> {
        let path = path.as_ref().to_path_buf();
        let compression = match header.compression {
            Compression::Zstd => Some(mcap::Compression::Zstd),
            Compression::Lz4 => Some(mcap::Compression::Lz4),
            Compression::None => None,
        };
        let options = mcap::WriteOptions::new()
            .profile(header.profile)
            .library(concat!(
                "scancorr-bag/",
                env!("CARGO_PKG_VERSION"),
                "; ",
                "mcap-rust"
            ))
            .compression(compression)
            .chunk_size(Some(header.chunk_size.max(1)))
            // Compress on the calling thread: zstd worker threads do not pay off for 1 MiB
            // chunks and would compete with the pipeline for the cores.
            .compression_threads(0);
        let writeback = Writeback::new(&file);
        let mcap = options
            .create(BufWriter::with_capacity(256 * 1024, file))
            .map_err(|error| BagError::Mcap {
                path: path.clone(),
                error,
            })?;
        Ok(BagWriter {
            path,
            mcap: Some(mcap),
            prefix: None,
            schemas: [0; Stream::ALL.len()],
            slots: Vec::new(),
            last: 0,
            scratch: Vec::new(),
            writeback,
            extra: Vec::new(),
        })
    }

    /// The file being written.
    pub fn path(&self) -> &Path {
        &self.path
    }

    fn mcap_err(&self, error: mcap::McapError) -> BagError {
        BagError::Mcap {
            path: self.path.clone(),
            error,
        }
    }

    fn writer(&mut self) -> Result<&mut mcap::Writer<BufWriter<File>>> {
        match self.mcap.as_mut() {
            Some(w) => Ok(w),
            None => Err(BagError::Mcap {
                path: self.path.clone(),
                error: mcap::McapError::AttemptedWriteAfterFailure,
            }),
        }
    }

    /// Index of the channel slot of (stream, machine) under `prefix`, registering it if new.
    fn slot(&mut self, stream: Stream, machine: &str, prefix: &str) -> Result<usize> {
        if let Some(s) = self.slots.get(self.last) {
            if s.stream == stream && s.machine == machine && self.prefix.as_deref() == Some(prefix)
            {
                return Ok(self.last);
            }
        }
        if let Some(p) = &self.prefix {
            if p != prefix {
                return Err(BagError::InvalidKey {
                    prefix: prefix.into(),
                    machine: machine.into(),
                    reason: format!("this bag records prefix {p:?}; a bag holds one prefix"),
                });
            }
        }
        if let Some(i) = self
            .slots
            .iter()
            .position(|s| s.stream == stream && s.machine == machine)
        {
            self.last = i;
            return Ok(i);
        }
        let invalid = |reason: &str| BagError::InvalidKey {
            prefix: prefix.into(),
            machine: machine.into(),
            reason: reason.into(),
        };
        if prefix.is_empty() || prefix.starts_with('/') || prefix.ends_with('/') {
            return Err(invalid(
                "the prefix must be non-empty and not start or end with '/'",
            ));
        }
        if machine.is_empty() || machine.contains('/') {
            return Err(invalid(
                "the machine id must be non-empty and contain no '/'",
            ));
        }
        let topic = stream.key(prefix, machine);
        if Stream::parse_key(prefix, &topic) != Some((machine, stream)) {
            return Err(invalid("the key expression does not parse back"));
        }
        let si = stream_index(stream);
        if self.schemas[si] == 0 {
            let id =
                self.writer()?
                    .add_schema(stream.message_name(), ENCODING, FILE_DESCRIPTOR_SET);
            self.schemas[si] = id.map_err(|e| self.mcap_err(e))?;
        }
        let schema_id = self.schemas[si];
        let id = self
            .writer()?
            .add_channel(schema_id, &topic, ENCODING, &BTreeMap::new());
        let id = id.map_err(|e| self.mcap_err(e))?;
        self.prefix.get_or_insert_with(|| prefix.to_owned());
        self.slots.push(Slot {
            stream,
            machine: machine.into(),
            topic,
            id,
            sequence: 0,
            samples: 0,
        });
        self.last = self.slots.len() - 1;
        Ok(self.last)
    }

    /// Records one already-encoded message (the bytes as received from the bus) of `stream`
    /// of `machine` on topic `<prefix>/<machine>/<suffix>`.
    ///
    /// `log_time_ns` is the receive time, `publish_time_ns` the sample time (`t_ns` of the
    /// first sample, see [`crate::peek`]). The payload is not validated, only walked to count
    /// its samples.
    pub fn write(
        &mut self,
        stream: Stream,
        machine: &str,
        prefix: &str,
        log_time_ns: u64,
        publish_time_ns: u64,
        payload: &[u8],
    ) -> Result<()> {
        let i = self.slot(stream, machine, prefix)?;
        let slot = &mut self.slots[i];
        slot.sequence = slot.sequence.wrapping_add(1);
        slot.samples += peek(stream, payload).map_or(0, |p| p.samples);
        let header = MessageHeader {
            channel_id: slot.id,
            sequence: slot.sequence,
            log_time: log_time_ns,
            publish_time: publish_time_ns,
        };
        let r = self.writer()?.write_to_known_channel(&header, payload);
        r.map_err(|e| self.mcap_err(e))?;
        if let Some(wb) = &mut self.writeback {
            wb.wrote(payload.len());
        }
        Ok(())
    }

    /// Registers a protobuf channel that is not one of scancorr's streams (e.g. the
    /// [`crate::foxglove`] channels): `schema_data` is the encoded `FileDescriptorSet` holding
    /// `schema_name`. Its messages are written with [`BagWriter::write_extra`]; readers list
    /// it among the unknown channels and skip it.
    pub fn add_extra_channel(
        &mut self,
        topic: &str,
        schema_name: &str,
        schema_data: &[u8],
    ) -> Result<u16> {
        let schema = self
            .writer()?
            .add_schema(schema_name, ENCODING, schema_data);
        let schema = schema.map_err(|e| self.mcap_err(e))?;
        let id = self
            .writer()?
            .add_channel(schema, topic, ENCODING, &BTreeMap::new());
        let id = id.map_err(|e| self.mcap_err(e))?;
        self.extra.push((id, 0));
        Ok(id)
    }

    /// Records one message on a channel of [`BagWriter::add_extra_channel`].
    pub fn write_extra(
        &mut self,
        channel: u16,
        log_time_ns: u64,
        publish_time_ns: u64,
        payload: &[u8],
    ) -> Result<()> {
        let Some(slot) = self.extra.iter_mut().find(|(id, _)| *id == channel) else {
            return Err(BagError::InvalidKey {
                prefix: String::new(),
                machine: String::new(),
                reason: format!("channel {channel} was not added by add_extra_channel"),
            });
        };
        slot.1 = slot.1.wrapping_add(1);
        let header = MessageHeader {
            channel_id: channel,
            sequence: slot.1,
            log_time: log_time_ns,
            publish_time: publish_time_ns,
        };
        let r = self.writer()?.write_to_known_channel(&header, payload);
        r.map_err(|e| self.mcap_err(e))?;
        if let Some(wb) = &mut self.writeback {
            wb.wrote(payload.len());
        }
        Ok(())
    }

    /// Encodes and records a typed batch on its stream; the publish time is the `t_ns` of its
    /// first sample (negative clamps to 0; an empty batch uses `log_time_ns`).
    pub fn write_msg<M: BatchMessage>(
        &mut self,
        machine: &str,
        prefix: &str,
        log_time_ns: u64,
        msg: &M,
    ) -> Result<()> {
        let publish = msg.first_t_ns().map_or(log_time_ns, |t| t.max(0) as u64);
        let mut buf = std::mem::take(&mut self.scratch);
        buf.clear();
        // Encoding into a Vec cannot fail (it grows as needed).
        let _ = msg.encode(&mut buf);
        let r = self.write(M::STREAM, machine, prefix, log_time_ns, publish, &buf);
        self.scratch = buf;
        r
    }

    /// Writes a metadata record (e.g. `scancorr.run` with program, seed, machine id). Names may
    /// repeat; `scancorr.sample_counts` is reserved.
    pub fn write_metadata(&mut self, name: &str, entries: &BTreeMap<String, String>) -> Result<()> {
        if name == SAMPLE_COUNTS_METADATA {
            return Err(BagError::ReservedMetadata(name.into()));
        }
        self.write_metadata_unchecked(name, entries.clone())
    }

    fn write_metadata_unchecked(
        &mut self,
        name: &str,
        metadata: BTreeMap<String, String>,
    ) -> Result<()> {
        let r = self.writer()?.write_metadata(&Metadata {
            name: name.into(),
            metadata,
        });
        r.map_err(|e| self.mcap_err(e))
    }

    /// Writes the measured artifact as the `scancorr.artifact` metadata record.
    pub fn write_artifact(&mut self, artifact: &Artifact) -> Result<()> {
        self.write_metadata_unchecked(ARTIFACT_METADATA, artifact.to_metadata())
    }

    /// Closes the current chunk and hands everything written so far to the OS, so a crash
    /// after this point loses nothing before it. Call it e.g. once per second while recording.
    pub fn flush(&mut self) -> Result<()> {
        let r = self.writer()?.flush();
        r.map_err(|e| self.mcap_err(e))
    }

    /// Writes the per-channel sample counts, the summary (index, statistics) and the footer,
    /// then syncs the file to disk.
    pub fn finish(mut self) -> Result<()> {
        self.finish_inner()
    }

    fn finish_inner(&mut self) -> Result<()> {
        if self.mcap.is_none() {
            return Ok(());
        }
        if !self.slots.is_empty() {
            let counts = self
                .slots
                .iter()
                .map(|s| (s.topic.clone(), s.samples.to_string()))
                .collect();
            self.write_metadata_unchecked(SAMPLE_COUNTS_METADATA, counts)?;
        }
        let Some(mut w) = self.mcap.take() else {
            return Ok(());
        };
        let finished = w.finish().map_err(|e| self.mcap_err(e));
        let early = self.writeback.take().and_then(|mut wb| wb.stop());
        finished?;
        let file = w.into_inner().into_inner().map_err(|e| BagError::Io {
            path: self.path.clone(),
            error: e.into_error(),
        })?;
        if let Some(error) = early {
            return Err(BagError::Io {
                path: self.path.clone(),
                error,
            });
        }
        file.sync_all().map_err(|error| BagError::Io {
            path: self.path.clone(),
            error,
        })
    }
}

impl Drop for BagWriter {
    fn drop(&mut self) {
        let _ = self.finish_inner();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stream_index_follows_the_list_of_all_streams() {
        for (i, s) in Stream::ALL.into_iter().enumerate() {
            assert_eq!(stream_index(s), i, "{s:?}");
        }
    }
}
