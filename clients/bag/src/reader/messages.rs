//! Iteration: a bag's messages in log-time order, chunk by chunk ([`Messages`]).

use super::*;

/// Iterator over a bag's messages, see [`BagReader::messages`].
pub struct Messages<'a> {
    pub(super) bag: &'a BagReader,
    pub(super) file: File,
    pub(super) file_len: u64,
    pub(super) reader: IndexedReader,
    pub(super) buf: Vec<u8>,
    pub(super) done: bool,
}

impl Messages<'_> {
    pub(super) fn read_at(&mut self, offset: u64, n: u64) -> Result<()> {
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
    pub(super) fn load(&mut self, i: usize, size: usize) -> Result<Vec<u8>> {
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
pub(super) fn pad(data: &mut Vec<u8>, size: usize) {
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
