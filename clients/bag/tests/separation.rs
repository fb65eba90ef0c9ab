//! The `scancorr.v1.2` measurement streams in bags: distance probes and the micro-stage next to
//! the four corrected streams are read back identical; a bag written before v1.2 still reads;
//! the separation reader's readings, skips and errors; a batch on the other stream's key is
//! told by its tag.
mod common;
use common::*;
use prost::Message;
use scancorr_bag::measure::{read_separation, DistanceReading, MeasureError, StageReading};
use scancorr_bag::*;
use scancorr_proto::v1::*;
use std::path::{Path, PathBuf};

/// A bag recorded by `scancorr sim --program ring --rate 10 --batch 10` before v1.2 (see
/// `fixtures/README.md`).
fn fixture() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/v1_1_ring_m1.mcap")
}

fn distance(machine: &str, seq: u64, t_ns: i64, probe_id: u32, d: f64, at: f64) -> DistanceSample {
    DistanceSample {
        machine_id: machine.into(),
        seq,
        t_ns,
        probe_id,
        distance_mm: d,
        spacing_mm: at,
    }
}

fn distance_batch(samples: Vec<DistanceSample>) -> DistanceBatch {
    DistanceBatch {
        samples,
        stream: StreamKind::Distance as i32,
    }
}

fn stage_batch(samples: Vec<StageSample>) -> StageBatch {
    StageBatch {
        samples,
        stream: StreamKind::Stage as i32,
    }
}

fn stage(machine: &str, seq: u64, t_ns: i64, commanded: f64, sensor: f64) -> StageSample {
    StageSample {
        machine_id: machine.into(),
        seq,
        t_ns,
        commanded_mm: commanded,
        sensor_mm: sensor,
        probe_id: 2,
    }
}

#[test]
fn six_raw_streams_round_trip_with_their_values() {
    let path = tmp("separation-six-streams");
    let mut rng = Rng(0x51ab_2c3d_4e5f_6071);
    // Small chunks: many of them, and a file to cut short below.
    let header = BagHeader {
        chunk_size: 16 * 1024,
        ..BagHeader::default()
    };
    let mut w = BagWriter::create(&path, header).unwrap();
    let mut written = Vec::new();
    let mut log = 1_000_000_000u64;
    for r in 0..40usize {
        for (stream, n) in [
            (Stream::Command, 10),
            (Stream::Scale, 100),
            (Stream::Probe, 100),
            (Stream::Temperature, 3),
            (Stream::Distance, 9),
            (Stream::Stage, 4),
        ] {
            let t0 = 5_000_000_000 + (r * 100) as i64 * 1_000_000;
            let data = batch(stream, "m1", (r * n) as u64, t0, n, &mut rng);
            log += 1_000;
            if r % 2 == 1 && Stream::MEASUREMENT.contains(&stream) {
                // Typed writes of the new batches: stream and publish time from the type.
                match RawBatch::decode(stream, &data).unwrap() {
                    RawBatch::Distance(b) => w.write_msg("m1", "cmm", log, &b).unwrap(),
                    RawBatch::Stage(b) => w.write_msg("m1", "cmm", log, &b).unwrap(),
                    other => panic!("{other:?}"),
                }
            } else {
                w.write(stream, "m1", "cmm", log, t0 as u64, &data).unwrap();
            }
            written.push(Written {
                topic: stream.key("cmm", "m1"),
                stream,
                machine: "m1".into(),
                log_time: log,
                publish_time: t0 as u64,
                data,
                samples: n as u64,
            });
        }
    }
    w.finish().unwrap();

    let bag = BagReader::open(&path).unwrap();
    assert!(
        bag.unknown_channels().is_empty(),
        "{:?}",
        bag.unknown_channels()
    );
    let streams: Vec<Stream> = bag.channels().iter().map(|c| c.stream).collect();
    assert_eq!(
        streams,
        Stream::RAW,
        "one channel per raw stream, in stream order"
    );
    for c in bag.channels() {
        assert_eq!(c.topic, c.stream.key("cmm", "m1"));
        let want: u64 = written
            .iter()
            .filter(|w| w.stream == c.stream)
            .map(|w| w.samples)
            .sum();
        assert_eq!(c.sample_count, Some(want), "{}", c.topic);
        assert_eq!(c.message_count, 40, "{}", c.topic);
    }
    let read = read_all(&bag);
    assert_eq!(read.len(), written.len());
    for (m, w) in read.iter().zip(&written) {
        assert!(w.matches(m), "{} at {}", w.topic, w.log_time);
        let b = m.decode_checked().unwrap();
        assert_eq!(b.stream(), m.stream);
        assert_eq!(b.sample_count() as u64, w.samples);
        assert_eq!(b.first_t_ns(), Some(w.publish_time as i64));
        assert_eq!(b.encode_to_vec(), w.data, "values identical: {}", w.topic);
        // The helper writes the older streams untagged (as before v1.1), the new ones tagged.
        let tag = match Stream::MEASUREMENT.contains(&m.stream) {
            true => m.stream.kind().map(|k| k as i32),
            false => Some(0),
        };
        assert_eq!(b.tag(), tag, "{}", w.topic);
        assert_eq!(
            peek(m.stream, &m.data),
            Some(BatchPeek {
                samples: w.samples,
                first_t_ns: Some(w.publish_time as i64)
            })
        );
    }

    // The separation reader: every distance and stage sample, as written, in time order.
    let data = read_separation(&bag, "m1").unwrap();
    let mut want_d: Vec<DistanceReading> = Vec::new();
    let mut want_s: Vec<StageReading> = Vec::new();
    for w in &written {
        match RawBatch::decode(w.stream, &w.data).unwrap() {
            RawBatch::Distance(b) => want_d.extend(b.samples.iter().map(|s| DistanceReading {
                t_ns: s.t_ns,
                seq: s.seq,
                probe_id: s.probe_id,
                distance_mm: s.distance_mm,
                spacing_mm: s.spacing_mm,
            })),
            RawBatch::Stage(b) => want_s.extend(b.samples.iter().map(|s| StageReading {
                t_ns: s.t_ns,
                seq: s.seq,
                probe_id: s.probe_id,
                commanded_mm: s.commanded_mm,
                sensor_mm: s.sensor_mm,
            })),
            _ => {}
        }
    }
    assert_eq!(data.distance.len(), 40 * 9);
    assert_eq!(data.distance, want_d);
    assert_eq!(data.stage, want_s);
    assert_eq!(data.machine, "m1");
    assert_eq!(data.distance_topic, "cmm/m1/raw/distance");
    assert_eq!(data.stage_topic.as_deref(), Some("cmm/m1/raw/stage"));
    assert_eq!(data.probe_ids(), vec![0, 1, 2]);
    assert_eq!(data.readings_of(1).count(), 40 * 3);
    assert!(data.readings_of(1).all(|r| r.spacing_mm == 40.0));
    assert!(data.warnings().is_empty(), "{:?}", data.warnings());

    // Cut short: the scan finds the new channels by their topics too.
    let bytes = std::fs::read(&path).unwrap();
    let cut = tmp("separation-six-streams-cut");
    std::fs::write(&cut, &bytes[..bytes.len() * 6 / 10]).unwrap();
    let bag = BagReader::open(&cut).unwrap();
    assert!(bag.truncation().is_some());
    let d = bag
        .channel("m1", Stream::Distance)
        .expect("distance channel");
    let s = bag.channel("m1", Stream::Stage).expect("stage channel");
    let part = read_separation(&bag, "m1").unwrap();
    assert!(!part.distance.is_empty() && part.distance.len() < want_d.len());
    assert_eq!(d.sample_count, Some(part.distance.len() as u64));
    assert_eq!(s.sample_count, Some(part.stage.len() as u64));
    assert_eq!(part.distance[..], want_d[..part.distance.len()]);
}

#[test]
fn a_bag_written_before_v1_2_still_reads() {
    let bytes = std::fs::read(fixture()).unwrap();
    let has = |s: &str| bytes.windows(s.len()).any(|w| w == s.as_bytes());
    assert!(has("scancorr.v1.TemperatureBatch"));
    assert!(
        !has("DistanceBatch"),
        "the fixture must be a bag from before v1.2: its schema does not know the new messages"
    );
    let bag = BagReader::open(fixture()).unwrap();
    assert!(bag.truncation().is_none());
    assert!(bag.unknown_channels().is_empty());
    assert!(
        bag.artifact().unwrap().is_some(),
        "the ring's artifact record"
    );
    let streams: Vec<(&str, Stream)> = bag
        .channels()
        .iter()
        .map(|c| (c.machine.as_str(), c.stream))
        .collect();
    assert_eq!(
        streams,
        Stream::CORRECTED.map(|s| ("m1", s)),
        "the four streams the corrector joins"
    );
    let mut samples = [0u64; 4];
    let mut messages = 0;
    for m in bag.messages().unwrap() {
        let m = m.unwrap();
        let b = m.decode_checked().unwrap();
        assert_eq!(b.tag(), m.stream.kind().map(|k| k as i32), "v1.1 tags");
        let i = Stream::CORRECTED
            .iter()
            .position(|&s| s == m.stream)
            .unwrap();
        samples[i] += b.sample_count() as u64;
        messages += 1;
    }
    assert!(messages > 100, "{messages}");
    for (c, n) in bag.channels().iter().zip(samples) {
        assert!(n > 0, "{}", c.topic);
        assert_eq!(c.sample_count, Some(n), "{}", c.topic);
    }
    // No straightness measurement in it: the reader says what to record.
    let e = read_separation(&bag, "m1").unwrap_err();
    assert!(matches!(e, MeasureError::NoDistanceStream { .. }), "{e:?}");
    let text = e.to_string();
    assert!(
        text.ends_with(
            "v1_1_ring_m1.mcap: the bag has no distance-probe stream (cmm/m1/raw/distance): \
             record the straightness measurement, e.g. scancorr sim --program straightness-three-probe"
        ),
        "{text}"
    );
}

#[test]
fn the_separation_reader_counts_what_it_skips_and_names_what_is_missing() {
    let path = tmp("separation-skips");
    let mut w = BagWriter::create(&path, BagHeader::default()).unwrap();
    let scale = ScaleBatch {
        samples: vec![ScaleSample {
            machine_id: "m1".into(),
            t_ns: 1,
            ..Default::default()
        }],
        stream: StreamKind::Scale as i32,
        columns: None,
    };
    w.write_msg("m1", "cmm", 1, &scale).unwrap();
    // Written out of time order: the reader sorts by t_ns.
    let late = distance_batch(vec![
        distance("m1", 3, 3_000, 0, 0.003, 0.0),
        distance("m1", 4, 3_000, 1, 0.004, 40.0),
    ]);
    let early = distance_batch(vec![
        distance("m1", 1, 1_000, 0, 0.001, 0.0),
        distance("m2", 2, 1_000, 1, 0.002, 40.0), // another machine's sample
        distance("m1", 2, 2_000, 1, f64::NAN, 40.0),
        distance("m1", 5, 2_000, 2, 0.005, f64::INFINITY),
    ]);
    w.write_msg("m1", "cmm", 10, &late).unwrap();
    w.write_msg("m1", "cmm", 20, &early).unwrap();
    // Untagged (a producer that forgot the tag): its channel names it; taken.
    let mut untagged = distance_batch(vec![distance("m1", 6, 4_000, 2, 0.006, 80.0)]);
    untagged.stream = 0;
    w.write_msg("m1", "cmm", 30, &untagged).unwrap();
    // Not protobuf, on the distance key.
    w.write(Stream::Distance, "m1", "cmm", 40, 0, &[0xff, 0xff, 0xff])
        .unwrap();
    // A distance batch published on the stage key, and a good stage batch.
    let stray = distance_batch(vec![distance("m1", 9, 5_000, 1, 0.009, 40.0)]);
    w.write(
        Stream::Stage,
        "m1",
        "cmm",
        50,
        5_000,
        &stray.encode_to_vec(),
    )
    .unwrap();
    let good = stage_batch(vec![
        stage("m1", 2, 2_500, 0.002, 0.00201),
        stage("m1", 1, 1_500, 0.001, 0.00099),
    ]);
    w.write_msg("m1", "cmm", 60, &good).unwrap();
    // m2 has scales only; m3 a distance stream whose only batch is a stage batch.
    w.write_msg("m2", "cmm", 70, &scale).unwrap();
    let wrong = stage_batch(vec![stage("m3", 1, 1, 0.0, 0.0)]);
    w.write(Stream::Distance, "m3", "cmm", 80, 1, &wrong.encode_to_vec())
        .unwrap();
    w.finish().unwrap();

    let bag = BagReader::open(&path).unwrap();
    let d = read_separation(&bag, "m1").unwrap();
    let t: Vec<(i64, u64)> = d.distance.iter().map(|r| (r.t_ns, r.seq)).collect();
    assert_eq!(t, [(1_000, 1), (3_000, 3), (3_000, 4), (4_000, 6)]);
    assert_eq!(d.distance[0].distance_mm, 0.001);
    assert_eq!(d.distance[3].spacing_mm, 80.0);
    let ts: Vec<i64> = d.stage.iter().map(|r| r.t_ns).collect();
    assert_eq!(ts, [1_500, 2_500]);
    assert_eq!(d.stage[0].sensor_mm, 0.00099);
    assert_eq!(d.stage[0].probe_id, 2);
    let ds = &d.distance_skipped;
    assert_eq!(
        (
            ds.wrong_stream,
            ds.malformed,
            ds.other_machine,
            ds.not_finite
        ),
        (0, 1, 1, 2)
    );
    let ss = &d.stage_skipped;
    assert_eq!((ss.wrong_stream, ss.malformed, ss.total()), (1, 0, 1));
    let warnings = d.warnings();
    assert_eq!(warnings.len(), 2, "{warnings:?}");
    assert!(
        warnings[0].starts_with(
            "cmm/m1/raw/distance: skipped 1 message(s) that do not decode, 1 sample(s) naming \
             another machine, 2 sample(s) with values that are not finite numbers (first: cannot \
             decode scancorr.v1.DistanceBatch on cmm/m1/raw/distance at log time 40"
        ),
        "{warnings:?}"
    );
    assert_eq!(
        warnings[1],
        "cmm/m1/raw/stage: skipped 1 message(s) tagged as another stream (first: a distance \
         batch on the raw/stage stream on cmm/m1/raw/stage at log time 50: its stream tag names \
         another stream than its key)"
    );

    let e = read_separation(&bag, "m2").unwrap_err();
    assert!(matches!(e, MeasureError::NoDistanceStream { .. }), "{e}");
    assert!(
        e.to_string()
            .contains("the bag has no distance-probe stream (cmm/m2/raw/distance)"),
        "{e}"
    );
    let e = read_separation(&bag, "m9").unwrap_err();
    assert!(
        e.to_string()
            .ends_with("no streams of machine `m9` in this bag (it holds: m1, m2, m3)"),
        "{e}"
    );
    let e = read_separation(&bag, "m3").unwrap_err();
    assert_eq!(
        e.to_string(),
        format!(
            "{}: the distance-probe stream cmm/m3/raw/distance holds no readings: skipped 1 \
             message(s) tagged as another stream (first: a stage batch on the raw/distance \
             stream on cmm/m3/raw/distance at log time 80: its stream tag names another stream \
             than its key)",
            path.display()
        )
    );
    // A name from outside is checked before it becomes part of a key expression.
    for bad in ["*", "m1/raw", "", "../m1"] {
        let e = read_separation(&bag, bad).unwrap_err();
        assert!(matches!(e, MeasureError::InvalidMachine(_)), "{bad:?}: {e}");
        assert!(e.to_string().starts_with("machine id "), "{e}");
    }
}

#[test]
fn a_distance_batch_on_the_stage_key_is_the_wrong_stream() {
    // Probe 0 at spacing 0 (the mount's reference probe): its fields after `t_ns` are all
    // doubles or absent, so decoding it as a StageBatch by type alone succeeds — and reads the
    // probe's distance as the stage's sensor. The tag stops that.
    let reference = distance_batch(vec![distance("m1", 7, 1_000, 0, 0.125, 0.0)]);
    let bytes = reference.encode_to_vec();
    match RawBatch::decode(Stream::Stage, &bytes).unwrap() {
        RawBatch::Stage(b) => assert_eq!(b.samples[0].sensor_mm, 0.125, "mis-decoded by type"),
        other => panic!("{other:?}"),
    }
    assert_eq!(stream_tag(&bytes), Some(StreamKind::Distance as i32));
    let e = RawBatch::decode_checked(Stream::Stage, &bytes, "").unwrap_err();
    assert!(
        matches!(&e, BagError::WrongStream { expected: Stream::Stage, found, .. } if found == "distance"),
        "{e:?}"
    );
    assert_eq!(
        e.to_string(),
        "a distance batch on the raw/stage stream: its stream tag names another stream than its key"
    );
    // Any probe: the same.
    let other = distance_batch(vec![distance("m1", 8, 2_000, 2, 0.5, 80.0)]);
    assert!(matches!(
        RawBatch::decode_checked(Stream::Stage, &other.encode_to_vec(), ""),
        Err(BagError::WrongStream { .. })
    ));
    // And the other way round, and the older streams on the new keys.
    let st = stage_batch(vec![stage("m1", 1, 1, 0.1, 0.1)]);
    let e = RawBatch::decode_checked(Stream::Distance, &st.encode_to_vec(), "").unwrap_err();
    assert!(
        e.to_string()
            .starts_with("a stage batch on the raw/distance stream"),
        "{e}"
    );
    let scale = ScaleBatch {
        samples: vec![ScaleSample::default()],
        stream: StreamKind::Scale as i32,
        columns: None,
    };
    let e = RawBatch::decode_checked(Stream::Distance, &scale.encode_to_vec(), "").unwrap_err();
    assert!(
        e.to_string()
            .starts_with("a scale batch on the raw/distance stream"),
        "{e}"
    );
    let e = RawBatch::decode_checked(Stream::Scale, &bytes, "").unwrap_err();
    assert!(
        e.to_string()
            .starts_with("a distance batch on the raw/scale stream"),
        "{e}"
    );
    let mut future = other.clone();
    future.stream = 9;
    let e = RawBatch::decode_checked(Stream::Distance, &future.encode_to_vec(), "").unwrap_err();
    assert!(e.to_string().starts_with("a unknown (9) batch"), "{e}");
    // Right key, tagged or untagged: decoded.
    assert_eq!(
        RawBatch::decode_checked(Stream::Distance, &bytes, "").unwrap(),
        RawBatch::Distance(reference.clone())
    );
    let mut untagged = reference.clone();
    untagged.stream = 0;
    assert!(RawBatch::decode_checked(Stream::Distance, &untagged.encode_to_vec(), "").is_ok());
    // Not protobuf: a decode error, not a panic, not a wrong stream.
    assert_eq!(stream_tag(&[0x0a, 0x05, 0x01]), None);
    assert!(matches!(
        RawBatch::decode_checked(Stream::Stage, &[0x0a, 0x05, 0x01], ""),
        Err(BagError::Decode { .. })
    ));

    // Recorded in a bag (as `scancorr record` stores whatever arrives on the stage key).
    let path = tmp("separation-wrong-key");
    let mut w = BagWriter::create(&path, BagHeader::default()).unwrap();
    w.write(Stream::Stage, "m1", "cmm", 5, 1_000, &bytes)
        .unwrap();
    w.finish().unwrap();
    let bag = BagReader::open(&path).unwrap();
    let m = read_all(&bag).remove(0);
    assert_eq!(m.stream, Stream::Stage);
    let e = m.decode_checked().unwrap_err();
    assert_eq!(
        e.to_string(),
        "a distance batch on the raw/stage stream on cmm/m1/raw/stage at log time 5: its stream \
         tag names another stream than its key"
    );
}
