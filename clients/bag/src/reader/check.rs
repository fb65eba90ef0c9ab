//! The reader's checking: chunks against their index entries and their CRCs (decoding a
//! chunk verifies its records' CRC and lengths), the data section's CRC, how much chunks
//! overlapping in time would hold. Nothing here iterates messages.

use super::*;

pub(super) fn crc_mismatch(expected: u32, computed: u32) -> String {
    format!("CRC mismatch (expected {expected:#010x}, computed {computed:#010x})")
}

/// Fails when, in log-time order, chunks overlapping in time would hold more than
/// `OVERLAP_LIMIT` decompressed bytes at once.
pub(super) fn check_overlap(regions: &[Region]) -> Result<(), String> {
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

/// With a usable summary: checks the data section CRC (one pass over the file). On a mismatch
/// finds the damaged chunks: the first is an error, or, when skipping, all are dropped and
/// counted.
pub(super) fn verify_data_section(src: &mut Source, cat: &mut Catalog) -> Result<()> {
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
pub(super) fn data_section_mismatch(
    src: &Source,
    cat: &mut Catalog,
    mismatch: String,
) -> Result<()> {
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
pub(super) fn lost_messages<R: Read + Seek>(
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

/// Decompresses one chunk record (`record` = opcode, length, body) and verifies the CRC of its
/// uncompressed records (unless it is 0, "not computed"). Returns the header and the records,
/// re-framed (opcode, length, body): exactly the chunk's uncompressed data. `Err` says what is
/// damaged.
pub(super) fn decode_chunk(record: &[u8]) -> Result<(ChunkHeader, Vec<u8>), String> {
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
pub(super) fn check_chunk(record: &[u8], index: &ChunkIndex) -> Result<Vec<u8>, String> {
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
