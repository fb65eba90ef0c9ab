mod common;

use common::*;
use prost::Message;
use scancorr_bag::*;
use scancorr_proto::v1::ScaleBatch;
use scancorr_proto::FILE_DESCRIPTOR_SET;
use std::collections::BTreeMap;

#[test]
fn round_trip() {
    let path = tmp("round_trip");
    let written = write_sample_bag(&path, BagHeader::default(), 40);
    let bag = BagReader::open(&path).unwrap();
    assert_eq!(bag.truncation(), None);
    assert_eq!(bag.profile(), "scancorr");
    assert_eq!(bag.prefix(), "cmm");
    assert_eq!(bag.machines(), vec!["m1", "m2"]);
    assert!(bag.unknown_channels().is_empty());
    assert_eq!(bag.channels().len(), 7);
    for c in bag.channels() {
        let mine: Vec<_> = written.iter().filter(|w| w.topic == c.topic).collect();
        assert_eq!(c.topic, c.stream.key("cmm", &c.machine));
        assert_eq!(c.message_count, mine.len() as u64, "{}", c.topic);
        assert_eq!(
            c.sample_count,
            Some(mine.iter().map(|w| w.samples).sum()),
            "{}",
            c.topic
        );
    }
    assert_eq!(
        bag.channel("m1", Stream::Scale).unwrap().sample_count,
        Some(4000)
    );
    assert_eq!(bag.message_count(), written.len() as u64);
    assert_eq!(
        bag.time_range(),
        Some((written[0].log_time, written.last().unwrap().log_time))
    );
    let names: Vec<_> = bag.metadata().iter().map(|m| m.name.as_str()).collect();
    assert_eq!(names, ["scancorr.run", "scancorr.artifact"]);
    assert_eq!(bag.metadata_named(RUN_METADATA), Some(&run_metadata()));
    assert_eq!(bag.artifact().unwrap(), Some(ring()));

    let read = read_all(&bag);
    assert_eq!(read.len(), written.len());
    for (i, (w, m)) in written.iter().zip(&read).enumerate() {
        assert!(w.matches(m), "message {i}: wrote {w:?}\nread {m:?}");
    }
    // Typed decoding.
    let scale = read.iter().find(|m| m.stream == Stream::Scale).unwrap();
    match scale.decode().unwrap() {
        RawBatch::Scale(b) => assert_eq!(b, ScaleBatch::decode(scale.data.as_slice()).unwrap()),
        other => panic!("{other:?}"),
    }
    let alarms: Vec<_> = read.iter().filter(|m| m.stream == Stream::Alarms).collect();
    assert_eq!(alarms.len(), 4);
    assert!(matches!(alarms[0].decode().unwrap(), RawBatch::Alarm(a) if a.raised && a.t_ns == 123));
    // A second pass over the same reader gives the same messages.
    assert_eq!(read_all(&bag), read);
}

#[test]
fn round_trip_lz4_uncompressed_and_tiny_chunks() {
    for (name, compression, chunk_size) in [
        ("lz4", Compression::Lz4, DEFAULT_CHUNK_SIZE),
        ("none", Compression::None, 4096),
        ("tiny", Compression::Zstd, 1),
    ] {
        let path = tmp(&format!("round_trip_{name}"));
        let header = BagHeader {
            profile: "test".into(),
            chunk_size,
            compression,
        };
        let written = write_sample_bag(&path, header, 8);
        let bag = BagReader::open(&path).unwrap();
        assert_eq!(bag.profile(), "test");
        assert_eq!(bag.truncation(), None, "{name}");
        let read = read_all(&bag);
        assert_eq!(read.len(), written.len(), "{name}");
        assert!(
            written.iter().zip(&read).all(|(w, m)| w.matches(m)),
            "{name}"
        );
    }
}

#[test]
fn messages_come_in_log_time_order() {
    let path = tmp("log_time_order");
    let mut rng = Rng(7);
    // Small chunks so that out-of-order log times span chunks.
    let header = BagHeader {
        chunk_size: 2048,
        ..BagHeader::default()
    };
    let mut w = BagWriter::create(&path, header).unwrap();
    let mut written = Vec::new();
    for i in 0..300u64 {
        // Scale arrives in order, probe batches arrive late (log time 50 µs earlier than the
        // scale written before them), some log times repeat.
        let scale_log = 1_000_000 + i * 100;
        let probe_log = if i % 10 == 0 {
            scale_log
        } else {
            scale_log - 50
        };
        for (stream, log) in [(Stream::Scale, scale_log), (Stream::Probe, probe_log)] {
            let data = batch(stream, "m1", i, i as i64, 5, &mut rng);
            w.write(stream, "m1", "cmm", log, i, &data).unwrap();
            written.push((log, stream, data));
        }
    }
    w.finish().unwrap();
    let bag = BagReader::open(&path).unwrap();
    let read = read_all(&bag);
    // Stable sort by log time = expected order.
    written.sort_by_key(|(log, _, _)| *log);
    assert_eq!(read.len(), written.len());
    for ((log, stream, data), m) in written.iter().zip(&read) {
        assert_eq!((m.log_time, m.stream, &m.data), (*log, *stream, data));
    }
}

#[test]
fn other_mcap_readers_see_standard_protobuf_channels() {
    let path = tmp("standard");
    write_sample_bag(&path, BagHeader::default(), 3);
    let bytes = std::fs::read(&path).unwrap();
    // The strict in-memory reader of the mcap crate (checks magic, CRCs, schema links).
    let summary = mcap::Summary::read(&bytes).unwrap().unwrap();
    for ch in summary.channels.values() {
        let schema = ch.schema.as_ref().unwrap();
        let (_, stream) = Stream::parse_key("cmm", &ch.topic).unwrap();
        assert_eq!(schema.name, stream.message_name());
        assert_eq!(schema.encoding, "protobuf");
        assert_eq!(ch.message_encoding, "protobuf");
        assert_eq!(&*schema.data, FILE_DESCRIPTOR_SET);
    }
    let options = mcap::read::Options::ValidateChunkCrcs;
    let n = mcap::MessageStream::new_with_options(&bytes, options.into())
        .unwrap()
        .collect::<mcap::McapResult<Vec<_>>>()
        .unwrap()
        .len();
    assert_eq!(n as u64, summary.stats.unwrap().message_count);
    let md: Vec<_> = summary
        .metadata_indexes
        .iter()
        .map(|i| mcap::read::metadata(&bytes, i).unwrap().name)
        .collect();
    assert_eq!(
        md,
        [
            "scancorr.run",
            "scancorr.artifact",
            "scancorr.sample_counts"
        ]
    );
}

#[test]
fn writer_rejects_bad_keys_and_reserved_metadata() {
    let path = tmp("bad_keys");
    let mut w = BagWriter::create(&path, BagHeader::default()).unwrap();
    let data = batch(Stream::Scale, "m1", 0, 0, 1, &mut Rng(1));
    for (prefix, machine) in [
        ("cmm", ""),
        ("cmm", "a/b"),
        ("", "m1"),
        ("cmm/", "m1"),
        ("/cmm", "m1"),
    ] {
        let e = w
            .write(Stream::Scale, machine, prefix, 1, 1, &data)
            .unwrap_err();
        assert!(
            matches!(e, BagError::InvalidKey { .. }),
            "{prefix:?} {machine:?}: {e}"
        );
    }
    w.write(Stream::Scale, "m1", "lab/cmm", 1, 1, &data)
        .unwrap();
    let e = w
        .write(Stream::Scale, "m1", "cmm", 2, 2, &data)
        .unwrap_err();
    assert!(e.to_string().contains("one prefix"), "{e}");
    let e = w
        .write_metadata(SAMPLE_COUNTS_METADATA, &BTreeMap::new())
        .unwrap_err();
    assert!(matches!(e, BagError::ReservedMetadata(_)));
    w.finish().unwrap();
    // A prefix with a slash reads back.
    let bag = BagReader::open(&path).unwrap();
    assert_eq!(bag.prefix(), "lab/cmm");
    assert_eq!(bag.machines(), ["m1"]);
    assert_eq!(read_all(&bag).len(), 1);
}

#[test]
fn dropping_the_writer_finishes_the_file() {
    let path = tmp("dropped");
    {
        let mut w = BagWriter::create(&path, BagHeader::default()).unwrap();
        let data = batch(Stream::Scale, "m1", 0, 0, 10, &mut Rng(1));
        w.write(Stream::Scale, "m1", "cmm", 1, 0, &data).unwrap();
    }
    let bag = BagReader::open(&path).unwrap();
    assert_eq!(bag.truncation(), None);
    assert_eq!(bag.channels()[0].sample_count, Some(10));
}

#[test]
fn empty_bag() {
    let path = tmp("empty_bag");
    BagWriter::create(&path, BagHeader::default())
        .unwrap()
        .finish()
        .unwrap();
    let bag = BagReader::open(&path).unwrap();
    assert_eq!(bag.truncation(), None);
    assert!(bag.channels().is_empty());
    assert_eq!(bag.prefix(), "cmm");
    assert_eq!(bag.time_range(), None);
    assert_eq!(bag.artifact().unwrap(), None);
    assert_eq!(read_all(&bag).len(), 0);
}

#[test]
fn a_bag_synced_while_written_reads_back_whole() {
    // Well over the payload between two early syncs of the file (8 MiB): the syncs run while
    // chunks are still being written, and change nothing in the file.
    let path = tmp("writeback");
    let mut rng = Rng(11);
    let header = BagHeader {
        compression: Compression::Lz4,
        ..BagHeader::default()
    };
    let mut w = BagWriter::create(&path, header).unwrap();
    let mut written = Vec::new();
    let mut bytes = 0;
    let mut i = 0u64;
    while bytes < 24 * 1024 * 1024 {
        let data = batch(Stream::Scale, "m1", i * 100, i as i64 * 1000, 100, &mut rng);
        w.write(Stream::Scale, "m1", "cmm", i, i, &data).unwrap();
        bytes += data.len();
        written.push(data);
        i += 1;
    }
    w.finish().unwrap();
    let bag = BagReader::open(&path).unwrap();
    assert_eq!(bag.truncation(), None);
    let read = read_all(&bag);
    assert_eq!(read.len(), written.len());
    for (k, (data, m)) in written.iter().zip(&read).enumerate() {
        assert_eq!((m.log_time, &m.data), (k as u64, data), "message {k}");
    }
    std::fs::remove_file(&path).ok();
}
