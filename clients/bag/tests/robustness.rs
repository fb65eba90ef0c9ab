mod common;

use common::*;
use scancorr_bag::*;
use scancorr_proto::FILE_DESCRIPTOR_SET;
use std::collections::BTreeMap;
use std::path::Path;

/// Chunk (start, end, messages) of a complete bag, in file order.
fn chunks(bytes: &[u8]) -> Vec<(u64, u64, usize)> {
    let summary = mcap::Summary::read(bytes).unwrap().unwrap();
    let mut v: Vec<_> = summary
        .chunk_indexes
        .iter()
        .map(|c| {
            let n = summary.stream_chunk(bytes, c).unwrap().count();
            (
                c.chunk_start_offset,
                c.chunk_start_offset + c.chunk_length,
                n,
            )
        })
        .collect();
    v.sort();
    v
}

fn header_end(bytes: &[u8]) -> u64 {
    8 + 9 + u64::from_le_bytes(bytes[9..17].try_into().unwrap())
}

/// Opens and fully iterates a bag; must not panic, whatever the bytes.
fn read_anything(path: &Path) -> Result<(BagReader, Vec<Result<BagMessage>>)> {
    let bag = BagReader::open(path)?;
    let msgs = bag.messages()?.collect();
    Ok((bag, msgs))
}

#[test]
fn truncated_bags_read_up_to_the_last_complete_chunk() {
    let path = tmp("trunc_full");
    let header = BagHeader {
        chunk_size: 16 * 1024,
        ..BagHeader::default()
    };
    let written = write_sample_bag(&path, header, 40);
    let bytes = std::fs::read(&path).unwrap();
    let chunks = chunks(&bytes);
    assert!(chunks.len() >= 20, "{} chunks", chunks.len());
    let data_end = chunks.last().unwrap().1;
    let len = bytes.len() as u64;
    let summary_start = mcap::read::footer(&bytes).unwrap().summary_start;

    let mut cuts: Vec<u64> = [0.3, 0.6, 0.9, 0.99]
        .iter()
        .map(|f| (len as f64 * f) as u64)
        .collect();
    for &(start, end, _) in chunks.iter().step_by(5) {
        cuts.extend([start, start + 1, start + 30, end - 1, end, end + 1]);
    }
    cuts.push(header_end(&bytes)); // nothing but the header
    cuts.extend([
        data_end + 5,
        summary_start - 1,
        summary_start,
        summary_start + 5,
        len - 40,
        len - 8,
        len - 1,
    ]); // in the summary / footer
    let cut_path = tmp("trunc_cut");
    for cut in cuts {
        std::fs::write(&cut_path, &bytes[..cut as usize]).unwrap();
        let bag = BagReader::open(&cut_path).unwrap_or_else(|e| panic!("cut at {cut}: {e}"));
        let t = bag
            .truncation()
            .unwrap_or_else(|| panic!("cut at {cut} not reported"));
        assert_eq!(t.file_len, cut);
        assert!(t.readable_len <= cut, "{t:?}");
        let expected: usize = chunks.iter().filter(|c| c.1 <= cut).map(|c| c.2).sum();
        let read: Vec<_> = bag.messages().unwrap().map(|m| m.unwrap()).collect();
        assert_eq!(read.len(), expected, "cut at {cut} ({t:?})");
        assert!(
            written.iter().zip(&read).all(|(w, m)| w.matches(m)),
            "cut at {cut}: not a prefix"
        );
        assert_eq!(bag.message_count(), expected as u64);
        for c in bag.channels() {
            let mine: Vec<_> = written[..expected]
                .iter()
                .filter(|w| w.topic == c.topic)
                .collect();
            assert_eq!(c.message_count, mine.len() as u64);
            assert_eq!(c.sample_count, Some(mine.iter().map(|w| w.samples).sum()));
        }
        // Metadata written before the first chunk survives any cut after it.
        if cut >= chunks[0].0 {
            assert_eq!(bag.artifact().unwrap(), Some(ring()), "cut at {cut}");
        }
        if cut >= data_end {
            assert_eq!(read.len(), written.len());
        }
        if cut >= summary_start {
            assert!(t.reason.contains("data section is complete"), "{t:?}");
        }
    }

    // Cut inside the magic or the header: a clear error, no panic.
    for cut in [0, 1, 7, 8, 9, 16, header_end(&bytes) - 1] {
        std::fs::write(&cut_path, &bytes[..cut as usize]).unwrap();
        let e = BagReader::open(&cut_path).unwrap_err();
        let expected = if cut < 8 {
            "not an MCAP file"
        } else {
            "ends inside the MCAP header"
        };
        assert!(e.to_string().contains(expected), "cut at {cut}: {e}");
    }

    // Every 331st byte: a prefix of the messages, never a panic.
    for cut in (header_end(&bytes)..len).step_by(331) {
        std::fs::write(&cut_path, &bytes[..cut as usize]).unwrap();
        let (bag, msgs) = read_anything(&cut_path).unwrap();
        assert!(bag.truncation().is_some());
        let msgs: Vec<_> = msgs.into_iter().map(|m| m.unwrap()).collect();
        assert!(
            written.iter().zip(&msgs).all(|(w, m)| w.matches(m)),
            "cut at {cut}"
        );
    }
}

#[test]
fn killed_writer_leaves_a_readable_bag() {
    let path = tmp("killed");
    let mut w = BagWriter::create(&path, BagHeader::default()).unwrap();
    w.write_artifact(&ring()).unwrap();
    let mut rng = Rng(11);
    let mut n_flushed = 0;
    for i in 0..300 {
        let data = batch(Stream::Scale, "m1", i * 100, i as i64, 100, &mut rng);
        w.write(Stream::Scale, "m1", "cmm", i, i, &data).unwrap();
        if i == 199 {
            w.flush().unwrap();
            n_flushed = 200;
        }
    }
    // The last 100 messages (~600 kB, less than a chunk) are in an open chunk, partly in the
    // file already. Simulate a kill: no finish, no drop.
    std::mem::forget(w);
    let len = std::fs::metadata(&path).unwrap().len();
    let bag = BagReader::open(&path).unwrap();
    let t = bag.truncation().expect("reported as truncated");
    assert!(t.readable_len < len, "{t:?}");
    assert_eq!(read_all(&bag).len(), n_flushed);
    assert_eq!(
        bag.channel("m1", Stream::Scale).unwrap().sample_count,
        Some(20_000)
    );
    assert_eq!(bag.artifact().unwrap(), Some(ring()));
}

#[test]
fn garbage_empty_and_wrong_magic_are_errors() {
    let path = tmp("garbage");
    let cases: Vec<(&str, Vec<u8>, &str)> = vec![
        ("empty", vec![], "empty"),
        ("short", b"\x89MC".to_vec(), "only 3 bytes"),
        ("json", br#"{"not": "a bag"}"#.to_vec(), "wrong magic"),
        (
            "random",
            (0..4096u32)
                .map(|i| (i.wrapping_mul(2654435761) >> 13) as u8)
                .collect(),
            "wrong magic",
        ),
        (
            "magic then garbage",
            [mcap::MAGIC, &[0x42; 100][..]].concat(),
            "not a header",
        ),
        (
            "magic only",
            mcap::MAGIC.to_vec(),
            "ends inside the MCAP header",
        ),
    ];
    for (name, bytes, expected) in cases {
        std::fs::write(&path, &bytes).unwrap();
        let e = BagReader::open(&path).unwrap_err();
        assert!(e.to_string().contains(expected), "{name}: {e}");
        assert!(e.to_string().contains("garbage.mcap"), "{name}: {e}");
    }
    let e = BagReader::open(tmp("does-not-exist")).unwrap_err();
    assert!(matches!(e, BagError::Io { .. }), "{e}");
}

#[test]
fn damaged_bytes_never_panic() {
    let path = tmp("flip_src");
    let header = BagHeader {
        chunk_size: 4096,
        ..BagHeader::default()
    };
    let written = write_sample_bag(&path, header, 1);
    let bytes = std::fs::read(&path).unwrap();
    let flip = tmp("flip");
    let mut rng = Rng(99);
    let (mut ok, mut err) = (0, 0);
    for i in 0..bytes.len() {
        // Every byte of the header, the last chunk and the summary, every 37th elsewhere.
        if i > 200 && i < bytes.len() - 3000 && i % 37 != 0 {
            continue;
        }
        let mut b = bytes.clone();
        b[i] ^= 1 << (rng.next() % 8);
        std::fs::write(&flip, &b).unwrap();
        match read_anything(&flip) {
            Ok((_, msgs)) => {
                ok += 1;
                assert!(msgs.len() <= written.len() + 1);
            }
            Err(_) => err += 1,
        }
    }
    assert!(ok > 0 && err > 0, "ok {ok} err {err}");
}

/// Writes a bag with the plain mcap writer so channels can be anything.
fn write_raw(
    path: &Path,
    options: mcap::WriteOptions,
    channels: &[(&str, &str, &str, &str)],
) -> usize {
    let mut w = options
        .create(std::io::BufWriter::new(
            std::fs::File::create(path).unwrap(),
        ))
        .unwrap();
    let mut ids = Vec::new();
    for &(topic, schema_name, schema_encoding, message_encoding) in channels {
        let schema = w
            .add_schema(schema_name, schema_encoding, FILE_DESCRIPTOR_SET)
            .unwrap();
        ids.push(
            w.add_channel(schema, topic, message_encoding, &BTreeMap::new())
                .unwrap(),
        );
    }
    let mut rng = Rng(5);
    let mut n = 0;
    for i in 0..30u64 {
        for &id in &ids {
            let data = batch(Stream::Scale, "m1", i, i as i64, 3, &mut rng);
            // Log times decrease within each round so ordering is exercised.
            let header = mcap::records::MessageHeader {
                channel_id: id,
                sequence: 0,
                log_time: 1000 + i * 10 - id as u64,
                publish_time: i,
            };
            w.write_to_known_channel(&header, &data).unwrap();
            n += 1;
        }
    }
    w.finish().unwrap();
    n
}

#[test]
fn unknown_topics_are_listed_and_skipped() {
    let path = tmp("unknown_topics");
    let p = "protobuf";
    write_raw(
        &path,
        mcap::WriteOptions::new(),
        &[
            ("cmm/m1/raw/scale", "scancorr.v1.ScaleBatch", p, p),
            ("cmm/m1/raw/other", "scancorr.v1.ScaleBatch", p, p),
            ("/diagnostics", "foo.Bar", p, "json"),
            ("elsewhere/m1/raw/scale", "scancorr.v1.ScaleBatch", p, p),
        ],
    );
    let bag = BagReader::open(&path).unwrap();
    assert_eq!(bag.prefix(), "cmm");
    assert_eq!(bag.channels().len(), 1);
    let topics: Vec<_> = bag
        .unknown_channels()
        .iter()
        .map(|u| u.topic.as_str())
        .collect();
    assert_eq!(
        topics,
        ["cmm/m1/raw/other", "/diagnostics", "elsewhere/m1/raw/scale"]
    );
    assert_eq!(
        bag.unknown_channels()[1].schema_name.as_deref(),
        Some("foo.Bar")
    );
    assert_eq!(bag.unknown_channels()[1].message_count, 30);
    let msgs = read_all(&bag);
    assert_eq!(msgs.len(), 30);
    assert!(msgs.iter().all(|m| &*m.topic == "cmm/m1/raw/scale"));
    assert!(msgs.windows(2).all(|w| w[0].log_time <= w[1].log_time));
    // No sample-count record from a foreign writer: unknown.
    assert_eq!(bag.channels()[0].sample_count, None);
}

#[test]
fn wrong_schema_or_encoding_is_an_error() {
    let path = tmp("wrong_schema");
    let p = "protobuf";
    for (channel, expected) in [
        (
            ("cmm/m1/raw/scale", "scancorr.v1.ProbeBatch", p, p),
            "has schema \"scancorr.v1.ProbeBatch\", expected \"scancorr.v1.ScaleBatch\"",
        ),
        (
            (
                "cmm/m1/raw/scale",
                "scancorr.v1.ScaleBatch",
                "jsonschema",
                p,
            ),
            "schema encoding \"jsonschema\"",
        ),
        (
            ("cmm/m1/raw/scale", "scancorr.v1.ScaleBatch", p, "cdr"),
            "message encoding \"cdr\"",
        ),
    ] {
        write_raw(&path, mcap::WriteOptions::new(), &[channel]);
        let e = BagReader::open(&path).unwrap_err();
        let s = e.to_string();
        assert!(
            s.contains(expected)
                && s.contains("cmm/m1/raw/scale")
                && s.contains("wrong_schema.mcap"),
            "{s}"
        );
    }
}

#[test]
fn unchunked_and_summaryless_bags_are_scanned() {
    let path = tmp("unchunked");
    let p = "protobuf";
    let chans = [
        ("cmm/m1/raw/scale", "scancorr.v1.ScaleBatch", p, p),
        ("cmm/m2/raw/scale", "scancorr.v1.ScaleBatch", p, p),
    ];
    for (name, options) in [
        ("unchunked", mcap::WriteOptions::new().use_chunks(false)),
        (
            "no summary",
            mcap::WriteOptions::new()
                .emit_summary_records(false)
                .emit_summary_offsets(false)
                .chunk_size(Some(500)),
        ),
    ] {
        let n = write_raw(&path, options, &chans);
        let bag = BagReader::open(&path).unwrap();
        assert_eq!(bag.truncation(), None, "{name}");
        assert_eq!(bag.machines(), ["m1", "m2"], "{name}");
        assert_eq!(bag.channels()[0].sample_count, Some(90), "{name}");
        let msgs = read_all(&bag);
        assert_eq!(msgs.len(), n, "{name}");
        assert!(
            msgs.windows(2).all(|w| w[0].log_time <= w[1].log_time),
            "{name}"
        );
    }
}
