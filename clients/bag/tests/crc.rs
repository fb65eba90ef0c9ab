//! Damaged bags: every read verifies the checksums, so damage is an error (or, in skip mode, a
//! counted skip) — never silently different messages.
mod common;

use common::*;
use scancorr_bag::*;
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

/// CRC-32 (IEEE), bit by bit: independent of the crate's table-driven one.
fn crc32(data: &[u8]) -> u32 {
    let mut c = !0u32;
    for &b in data {
        c ^= u32::from(b);
        for _ in 0..8 {
            c = if c & 1 != 0 {
                0xEDB8_8320 ^ (c >> 1)
            } else {
                c >> 1
            };
        }
    }
    !c
}

fn u64_at(b: &[u8], at: usize) -> u64 {
    u64::from_le_bytes(b[at..at + 8].try_into().unwrap())
}

/// A chunk of a complete bag: record start and end, and the log times of its messages.
#[derive(Debug, Clone)]
struct Chunk {
    start: u64,
    end: u64,
    /// Offset of the compressed data.
    data: u64,
    compressed_size: u64,
    times: BTreeSet<u64>,
}

fn chunks(bytes: &[u8]) -> Vec<Chunk> {
    let summary = mcap::Summary::read(bytes).unwrap().unwrap();
    let mut v: Vec<_> = summary
        .chunk_indexes
        .iter()
        .map(|c| Chunk {
            start: c.chunk_start_offset,
            end: c.chunk_start_offset + c.chunk_length,
            data: c.compressed_data_offset().unwrap(),
            compressed_size: c.compressed_size,
            times: summary
                .stream_chunk(bytes, c)
                .unwrap()
                .map(|m| m.unwrap().log_time)
                .collect(),
        })
        .collect();
    v.sort_by_key(|c| c.start);
    v
}

/// Offset of the summary section.
fn summary_start(bytes: &[u8]) -> usize {
    mcap::read::footer(bytes).unwrap().summary_start as usize
}

/// Recomputes the data-section CRC (in the data-end record) and the summary CRC (in the
/// footer) after `bytes` were edited: hostile files carry valid checksums.
fn fix_crcs(bytes: &mut [u8]) {
    let s = summary_start(bytes);
    let data_end = s - 13;
    assert_eq!(bytes[data_end], 0x0f, "data-end record");
    let c = crc32(&bytes[..data_end]);
    bytes[s - 4..s].copy_from_slice(&c.to_le_bytes());
    // The summary CRC covers the summary and the footer up to the CRC itself.
    let footer = bytes.len() - 37;
    let c = crc32(&bytes[s..footer + 25]);
    let n = bytes.len();
    bytes[n - 12..n - 8].copy_from_slice(&c.to_le_bytes());
}

/// Offsets of the bodies of the chunk index records in the summary.
fn chunk_index_bodies(bytes: &[u8]) -> Vec<(usize, usize)> {
    let mut pos = summary_start(bytes);
    let footer = bytes.len() - 37;
    let mut out = Vec::new();
    while pos < footer {
        let op = bytes[pos];
        let len = u64_at(bytes, pos + 1) as usize;
        if op == 0x08 {
            out.push((pos + 9, pos + 9 + len));
        }
        pos += 9 + len;
    }
    out
}

#[derive(Debug, Clone, PartialEq, Eq)]
enum Outcome {
    /// `open` failed.
    OpenError(String),
    /// `open` succeeded, iterating failed.
    ReadError(String),
    /// The same messages as the undamaged bag (`reported`: a truncation or damage note says
    /// that something is wrong).
    Same { reported: bool },
    /// Different messages without an error: what must never happen.
    Different(String),
}

fn outcome(path: &Path, reference: &[BagMessage]) -> Outcome {
    let bag = match BagReader::open(path) {
        Ok(bag) => bag,
        Err(e) => return Outcome::OpenError(e.to_string()),
    };
    let msgs = match bag.messages().and_then(|m| m.collect::<Result<Vec<_>>>()) {
        Ok(m) => m,
        Err(e) => return Outcome::ReadError(e.to_string()),
    };
    assert!(bag.damaged_chunks().is_empty(), "skips only when asked");
    if msgs.len() != reference.len() {
        return Outcome::Different(format!(
            "{} messages instead of {}",
            msgs.len(),
            reference.len()
        ));
    }
    if let Some(i) = (0..msgs.len()).find(|&i| msgs[i] != reference[i]) {
        return Outcome::Different(format!(
            "message {i} differs: {:?} @ {} ({} bytes) instead of {:?} @ {} ({} bytes)",
            msgs[i].topic,
            msgs[i].log_time,
            msgs[i].data.len(),
            reference[i].topic,
            reference[i].log_time,
            reference[i].data.len()
        ));
    }
    Outcome::Same {
        reported: bag.truncation().is_some() || !bag.damage_notes().is_empty(),
    }
}

/// Writes the sample bag (several chunks, seven channels on two machines).
fn sample(name: &str, compression: Compression) -> (PathBuf, Vec<u8>, Vec<BagMessage>) {
    let path = tmp(name);
    let header = BagHeader {
        chunk_size: 8 * 1024,
        compression,
        ..BagHeader::default()
    };
    let written = write_sample_bag(&path, header, 12);
    let bytes = std::fs::read(&path).unwrap();
    let bag = BagReader::open(&path).unwrap();
    assert_eq!(bag.truncation(), None);
    assert!(bag.damage_notes().is_empty());
    let reference = read_all(&bag);
    assert_eq!(reference.len(), written.len());
    assert!(written.iter().zip(&reference).all(|(w, m)| w.matches(m)));
    (path, bytes, reference)
}

#[derive(Debug, Default)]
struct Tally {
    variants: usize,
    open_errors: usize,
    read_errors: usize,
    same: usize,
    same_reported: usize,
    crc_errors: usize,
}

/// Damaged copies of bags of each compression, made deterministically: ~200 single-bit flips
/// spread over the file, ~60 overwritten runs of 1–48 bytes, and in every chunk a flip in its
/// CRC field and one in its compressed data. Each must give an error or the same messages.
#[test]
fn damaged_bags_error_or_read_the_same() {
    let mut total = Tally::default();
    for (name, compression) in [
        ("none", Compression::None),
        ("zstd", Compression::Zstd),
        ("lz4", Compression::Lz4),
    ] {
        let (_, bytes, reference) = sample(&format!("crc_src_{name}"), compression);
        let chunks = chunks(&bytes);
        assert!(chunks.len() >= 5, "{name}: {} chunks", chunks.len());
        let channels: BTreeSet<_> = reference.iter().map(|m| m.topic.clone()).collect();
        assert!(channels.len() >= 6, "{name}: {channels:?}");
        let len = bytes.len();
        let mut rng = Rng(0x5eed ^ len as u64);
        // (what, offset, replacement bytes, chunk whose data is hit)
        let mut variants: Vec<(String, usize, Vec<u8>, Option<u64>)> = Vec::new();
        for k in 0..200 {
            let at = (k * len / 200 + (rng.next() as usize) % (len / 200)).min(len - 1);
            let b = bytes[at] ^ (1 << (rng.next() % 8));
            variants.push((format!("flip at {at}"), at, vec![b], None));
        }
        for k in 0..60 {
            let n = 1 + (rng.next() % 48) as usize;
            let at = (k * len / 60 + (rng.next() as usize) % (len / 60)).min(len - n);
            let mut run: Vec<u8> = (0..n).map(|_| rng.next() as u8).collect();
            if run == bytes[at..at + n] {
                run[0] ^= 0xff;
            }
            variants.push((format!("{n} bytes overwritten at {at}"), at, run, None));
        }
        for c in &chunks {
            // The uncompressed CRC field: opcode, length, start time, end time, size.
            let at = c.start as usize + 1 + 8 + 24 + 1;
            variants.push((
                format!("CRC field of chunk {}", c.start),
                at,
                vec![bytes[at] ^ 0x10],
                Some(c.start),
            ));
            let at = (c.data + c.compressed_size / 2) as usize;
            variants.push((
                format!("data of chunk {}", c.start),
                at,
                vec![bytes[at] ^ 0x04],
                Some(c.start),
            ));
        }
        let damaged = tmp(&format!("crc_damaged_{name}"));
        let file_name = damaged.file_name().unwrap().to_str().unwrap().to_owned();
        let mut tally = Tally::default();
        for (what, at, replacement, chunk) in &variants {
            let mut b = bytes.clone();
            b[*at..*at + replacement.len()].copy_from_slice(replacement);
            assert_ne!(b, bytes, "{name}: {what}");
            std::fs::write(&damaged, &b).unwrap();
            tally.variants += 1;
            let error = match outcome(&damaged, &reference) {
                Outcome::Different(how) => {
                    panic!("{name}: {what}: read without an error, but {how}")
                }
                Outcome::Same { reported } => {
                    assert!(chunk.is_none(), "{name}: {what}: damage not detected");
                    tally.same += 1;
                    tally.same_reported += reported as usize;
                    continue;
                }
                Outcome::OpenError(e) => {
                    tally.open_errors += 1;
                    e
                }
                Outcome::ReadError(e) => {
                    tally.read_errors += 1;
                    e
                }
            };
            assert!(error.contains(&file_name), "{name}: {what}: {error}");
            if error.contains("CRC mismatch (expected 0x") {
                tally.crc_errors += 1;
            }
            if let Some(start) = chunk {
                // Damage inside one chunk is pinned on that chunk.
                let expected = format!("damaged bag: chunk at byte offset {start}: ");
                assert!(error.contains(&expected), "{name}: {what}: {error}");
                if compression == Compression::None || what.starts_with("CRC") {
                    assert!(error.contains("CRC mismatch"), "{name}: {what}: {error}");
                }
            }
        }
        println!("{name}: {} bytes, {} chunks: {tally:?}", len, chunks.len());
        assert_eq!(
            tally.variants,
            tally.open_errors + tally.read_errors + tally.same
        );
        assert!(tally.open_errors + tally.read_errors > tally.variants / 2);
        assert!(tally.crc_errors > 0 && tally.same > 0, "{name}: {tally:?}");
        total.variants += tally.variants;
        total.open_errors += tally.open_errors;
        total.read_errors += tally.read_errors;
        total.same += tally.same;
        total.same_reported += tally.same_reported;
        total.crc_errors += tally.crc_errors;
    }
    println!("all: {total:?}");
}

/// The messages of `reference` not logged at `times`.
fn without(reference: &[BagMessage], times: &BTreeSet<u64>) -> Vec<BagMessage> {
    reference
        .iter()
        .filter(|m| !times.contains(&m.log_time))
        .cloned()
        .collect()
}

#[test]
fn skip_mode_counts_the_damaged_chunk_and_reads_the_others() {
    for (name, compression) in [("none", Compression::None), ("zstd", Compression::Zstd)] {
        let (_, bytes, reference) = sample(&format!("skip_src_{name}"), compression);
        let chunks = chunks(&bytes);
        let victim = chunks[chunks.len() / 2].clone();
        assert!(!victim.times.is_empty());
        let expected = without(&reference, &victim.times);
        assert!(expected.len() < reference.len());
        let mut b = bytes.clone();
        let at = (victim.data + victim.compressed_size / 2) as usize;
        b[at] ^= 0x01;
        let path = tmp(&format!("skip_damaged_{name}"));

        // Complete file (read through the summary), and the same file cut short after its
        // data section (scanned).
        let cut = summary_start(&bytes) + 5;
        for (how, file) in [("complete", &b[..]), ("cut short", &b[..cut])] {
            std::fs::write(&path, file).unwrap();
            let e = BagReader::open(&path).unwrap_err().to_string();
            let at_chunk = format!("damaged bag: chunk at byte offset {}: ", victim.start);
            assert!(e.contains(&at_chunk), "{name} {how}: {e}");
            if compression == Compression::None {
                assert!(e.contains("CRC mismatch (expected 0x"), "{name} {how}: {e}");
            }

            let bag = BagReader::open_skipping_damaged(&path).unwrap();
            assert!(bag.read_options().skip_damaged);
            assert_eq!(read_all(&bag), expected, "{name} {how}");
            let damaged = bag.damaged_chunks();
            assert_eq!(damaged.len(), 1, "{name} {how}: {damaged:?}");
            let d = &damaged[0];
            assert_eq!(d.offset, victim.start, "{name} {how}");
            assert_eq!(d.length, victim.end - victim.start, "{name} {how}");
            assert_eq!(
                d.messages_lost,
                Some(victim.times.len() as u64),
                "{name} {how}"
            );
            if compression == Compression::None {
                assert!(d.reason.starts_with("CRC mismatch"), "{d:?}");
            }
            assert!(d.to_string().contains("messages lost"), "{d}");
            assert_eq!(bag.message_count(), expected.len() as u64, "{name} {how}");
            if how == "complete" {
                assert_eq!(bag.truncation(), None);
                assert!(
                    bag.damage_notes()
                        .iter()
                        .any(|n| n.contains("data section CRC mismatch")),
                    "{:?}",
                    bag.damage_notes()
                );
                // The writer's sample counts included the lost messages: now unknown.
                for m in reference
                    .iter()
                    .filter(|m| victim.times.contains(&m.log_time))
                {
                    let c = bag
                        .channels()
                        .iter()
                        .find(|c| *c.topic == *m.topic)
                        .unwrap();
                    assert_eq!(c.sample_count, None, "{}", c.topic);
                }
            } else {
                assert!(bag.truncation().is_some());
                for c in bag.channels() {
                    let n = expected.iter().filter(|m| *m.topic == c.topic).count();
                    assert_eq!(c.message_count, n as u64, "{}", c.topic);
                }
            }
            // A second pass gives the same, and counts the chunk once.
            assert_eq!(read_all(&bag), expected);
            assert_eq!(bag.damaged_chunks().len(), 1);
        }
    }
}

/// Without a data-section CRC the damage is found while iterating: the messages before it,
/// then an error naming the chunk — or, skipping, all the other messages.
#[test]
fn damage_found_while_iterating() {
    let (_, bytes, reference) = sample("iter_src", Compression::None);
    let chunks = chunks(&bytes);
    let victim = chunks[2].clone();
    let mut b = bytes.clone();
    let s = summary_start(&bytes);
    b[s - 4..s].copy_from_slice(&[0; 4]); // data section CRC: not computed
    let at = (victim.data + victim.compressed_size / 3) as usize;
    b[at] ^= 0x80;
    let path = tmp("iter_damaged");
    std::fs::write(&path, &b).unwrap();

    let bag = BagReader::open(&path).unwrap();
    let mut before = Vec::new();
    let mut error = None;
    for m in bag.messages().unwrap() {
        match m {
            Ok(m) => before.push(m),
            Err(e) => {
                error = Some(e);
                break;
            }
        }
    }
    let e = error.expect("an error").to_string();
    assert!(
        e.contains(&format!(
            "damaged bag: chunk at byte offset {}: CRC mismatch (expected 0x",
            victim.start
        )),
        "{e}"
    );
    assert!(e.contains("iter_damaged.mcap"), "{e}");
    let first_lost = *victim.times.first().unwrap();
    assert!(before.iter().all(|m| m.log_time < first_lost));
    assert_eq!(before[..], reference[..before.len()]);

    let bag = BagReader::open_skipping_damaged(&path).unwrap();
    assert!(bag.damaged_chunks().is_empty(), "found while iterating");
    assert_eq!(read_all(&bag), without(&reference, &victim.times));
    let damaged = bag.damaged_chunks();
    assert_eq!(damaged.len(), 1);
    assert_eq!(damaged[0].offset, victim.start);
    assert_eq!(damaged[0].messages_lost, Some(victim.times.len() as u64));
}

/// A CRC of 0 means "not computed": such a chunk is read unverified, without a false alarm.
#[test]
fn zero_crcs_are_not_checked() {
    let (_, bytes, reference) = sample("zero_src", Compression::Zstd);
    let mut b = bytes.clone();
    for c in chunks(&bytes) {
        let at = c.start as usize + 1 + 8 + 24;
        b[at..at + 4].copy_from_slice(&[0; 4]);
    }
    let s = summary_start(&bytes);
    b[s - 4..s].copy_from_slice(&[0; 4]);
    let path = tmp("zero_crcs");
    std::fs::write(&path, &b).unwrap();
    let bag = BagReader::open(&path).unwrap();
    assert_eq!(read_all(&bag), reference);
    assert!(bag.damage_notes().is_empty());
}

/// Hostile lengths and sizes, with valid checksums: clear errors, no panic, no huge allocation.
#[test]
fn hostile_sizes_are_refused() {
    let (_, bytes, reference) = sample("hostile_src", Compression::Zstd);
    let chunks = chunks(&bytes);
    let first = chunks[0].start as usize;
    let path = tmp("hostile");
    let open_and_read = |b: &[u8]| -> Result<Vec<BagMessage>> {
        std::fs::write(&path, b).unwrap();
        let bag = BagReader::open(&path)?;
        let msgs = bag.messages()?.collect::<Result<Vec<_>>>()?;
        Ok(msgs)
    };
    let huge = 100u64 << 30;

    // A record length of 2^63 (the file has its footer: damage, not truncation).
    let mut b = bytes.clone();
    b[first + 1..first + 9].copy_from_slice(&(1u64 << 63).to_le_bytes());
    fix_crcs(&mut b);
    let e = open_and_read(&b).unwrap_err().to_string();
    assert!(e.contains("record length") || e.contains("bytes"), "{e}");
    // The same with the summary gone (scanned; the file is no longer finished: truncation).
    let cut = summary_start(&bytes) + 5;
    std::fs::write(&path, &b[..cut]).unwrap();
    let bag = BagReader::open(&path).unwrap();
    let t = bag.truncation().unwrap();
    assert_eq!(t.readable_len, first as u64, "{t:?}");
    assert!(
        t.reason.contains("needs 9223372036854775808 bytes"),
        "{t:?}"
    );
    assert!(read_all(&bag).is_empty());

    // A chunk claiming 100 GB uncompressed, in its header only.
    let size_at = first + 1 + 8 + 16;
    let mut b = bytes.clone();
    b[size_at..size_at + 8].copy_from_slice(&huge.to_le_bytes());
    fix_crcs(&mut b);
    let e = open_and_read(&b).unwrap_err().to_string();
    assert!(e.contains("damaged bag: chunk at byte offset"), "{e}");
    // ... and in its index entry too: the summary is refused, the scan refuses the chunk.
    for (_, end) in chunk_index_bodies(&b) {
        b[end - 8..end].copy_from_slice(&huge.to_le_bytes());
    }
    fix_crcs(&mut b);
    let e = open_and_read(&b).unwrap_err().to_string();
    assert!(
        e.contains("chunk claims 107374182400 uncompressed bytes, more than the"),
        "{e}"
    );

    // Chunk indexes that make every chunk overlap every other, each claiming the largest
    // accepted size: reading in time order would hold them all at once.
    let mut b = bytes.clone();
    for (body, end) in chunk_index_bodies(&b) {
        b[body..body + 8].copy_from_slice(&0u64.to_le_bytes());
        b[body + 8..body + 16].copy_from_slice(&u64::MAX.to_le_bytes());
        b[end - 8..end].copy_from_slice(&(256u64 << 20).to_le_bytes());
    }
    fix_crcs(&mut b);
    let e = open_and_read(&b).unwrap_err().to_string();
    assert!(e.contains("chunks overlapping in time"), "{e}");

    // Overlapping time ranges within the limits are fine: the same messages.
    let mut b = bytes.clone();
    for (body, _) in chunk_index_bodies(&b) {
        b[body..body + 8].copy_from_slice(&0u64.to_le_bytes());
        b[body + 8..body + 16].copy_from_slice(&u64::MAX.to_le_bytes());
    }
    fix_crcs(&mut b);
    assert_eq!(open_and_read(&b).unwrap(), reference);
}
