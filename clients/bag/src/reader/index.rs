//! Where the messages are: the summary section read when it is usable, otherwise the data
//! section scanned record by record up to the last complete chunk.

use super::*;

/// Why the summary cannot be used.
pub(super) enum NoSummary {
    /// The file has no (complete) summary: cut short, or written without one.
    Absent(String),
    /// There is a summary, but it is damaged or inconsistent.
    Unusable(String),
}

/// Reads the summary section into `cat`. `Err` means it is absent or unusable and the file
/// must be scanned.
pub(super) fn read_summary(
    src: &mut Source,
    header_end: u64,
    cat: &mut Catalog,
) -> Result<(), NoSummary> {
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

pub(super) fn read_summary_section(
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

pub(super) fn push_metadata(cat: &mut Catalog, md: mcap::records::Metadata) {
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
pub(super) struct LooseRun {
    pub(super) start: u64,
    pub(super) end: u64,
    pub(super) t_min: u64,
    pub(super) t_max: u64,
}

/// Scans the data section record by record, keeping every complete chunk (CRC-verified) and
/// computing the data section CRC; stops at the data end record or at the first incomplete
/// record, which it reports as truncation. A damaged record, or an incomplete one in a file
/// that has its footer, is an error — except that when skipping damaged chunks, a damaged
/// chunk is counted and skipped and other damage ends the readable part like a truncation.
pub(super) fn scan(
    src: &mut Source,
    header_end: u64,
    cat: &mut Catalog,
    no_summary: &str,
) -> Result<()> {
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

pub(super) fn has_footer(src: &mut Source, data_end: u64) -> Result<bool> {
    if src.len < data_end + FOOTER_AND_MAGIC {
        return Ok(false);
    }
    let tail = src.read_at(src.len - FOOTER_AND_MAGIC, FOOTER_AND_MAGIC as usize)?;
    Ok(tail[0] == op::FOOTER && &tail[29..] == MAGIC)
}

pub(super) fn close_run(run: &mut Option<LooseRun>, cat: &mut Catalog) {
    let Some(r) = run.take() else { return };
    cat.regions.push(Region::Loose {
        start: r.start,
        size: r.end - r.start,
        t_min: r.t_min,
        t_max: r.t_max,
    });
}

pub(super) fn count_message(cat: &mut Catalog, channel: u16, log_time: u64, samples: Option<u64>) {
    *cat.message_counts.entry(channel).or_default() += 1;
    *cat.sample_counts.entry(channel).or_default() += samples.unwrap_or(0);
    cat.add_time(log_time);
}

/// Decodes and checks one chunk record (`record` = opcode, length, body at file offset
/// `offset`); on success adds its schemas, channels and messages to `cat` and indexes it.
pub(super) fn scan_chunk(record: &[u8], offset: u64, cat: &mut Catalog) -> Result<(), String> {
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
