use super::*;
use scancorr_proto::prost::encoding::encode_varint;

#[test]
fn samples_round_trip_through_the_wire() {
    let samples = vec![
        Sample::Command(CommandSample {
            seq: 1,
            t_ns: 5,
            pos: Vec3::new(1.0, 2.0, 3.0),
            arc_center: Vec3::new(0.5, 0.0, 3.0),
            arc_radius: 2.0,
            segment_id: 7,
        }),
        Sample::Scale(ScaleSample {
            seq: 1,
            t_ns: 5,
            pos: Vec3::new(1.0, 2.0, 3.5),
        }),
        Sample::Probe(ProbeSample {
            seq: 1,
            t_ns: 5,
            deflection: Vec3::new(0.1, -0.2, 0.0),
            tip_id: 2,
            head_a1_deg: 90.0,
            head_a2_deg: 15.0,
            force_n: None,
        }),
        Sample::Temperature(TemperatureSample {
            seq: 1,
            t_ns: 5,
            sensor: "air".into(),
            celsius: 20.25,
        }),
    ];
    let mut b = Batcher::new("m1", 1);
    for s in &samples {
        let stream = b.push(s).unwrap();
        let (bytes, t0, t1) = b.take(stream).unwrap();
        assert_eq!((t0, t1), (5, 5));
        let d = decode(stream, &bytes).unwrap();
        assert_eq!(d.samples, vec![("m1".to_string(), s.clone())]);
    }
    assert!(matches!(
        decode(StreamId::Scale, &[0xff, 0xff, 0xff]),
        Err(WireError::Malformed { .. })
    ));
    assert!(matches!(
        decode(StreamId::Scale, &[]),
        Err(WireError::Empty(_))
    ));
}

#[test]
fn a_batch_on_another_streams_key_is_refused() {
    let cmd = Sample::Command(CommandSample {
        seq: 1,
        t_ns: 5,
        pos: Vec3::new(100.0, 2.0, 3.0),
        arc_center: Vec3::zeros(),
        arc_radius: 0.0,
        segment_id: 0,
    });
    let mut b = Batcher::new("m1", 10).with_layout(Layout::PerSample);
    b.push(&cmd);
    let (bytes, _, _) = b.take(StreamId::Command).unwrap();
    // Without its tag a command batch decodes as a valid scale batch (fields 1–6 agree).
    let untagged = v1::CommandBatch {
        samples: v1::CommandBatch::decode(&bytes[..]).unwrap().samples,
        stream: 0,
        columns: None,
    }
    .encode_to_vec();
    assert_eq!(decode(StreamId::Scale, &untagged).unwrap().samples.len(), 1);
    // With it, the mismatch is detected whatever the policy.
    for tags in [Tags::Require, Tags::AllowUntagged] {
        let e =
            decode_with_tags(StreamId::Scale, &bytes, tags, |_, _| panic!("decoded")).unwrap_err();
        assert_eq!(
            e,
            WireError::WrongStream {
                expected: "scale",
                found: "command".into()
            }
        );
    }
    assert_eq!(
        decode_with_tags(StreamId::Command, &untagged, Tags::Require, |_, _| {}),
        Err(WireError::Untagged("CommandBatch"))
    );
    // Tagging an old batch gives the bytes a v1.1 producer writes.
    assert_eq!(&*tagged(StreamId::Command, &untagged).unwrap(), &bytes[..]);
    assert_eq!(&*tagged(StreamId::Command, &bytes).unwrap(), &bytes[..]);
    assert!(tagged(StreamId::Scale, &bytes).is_err());
    let mut n = 0;
    decode_with_tags(StreamId::Command, &bytes, Tags::Require, |m, s| {
        assert_eq!((m, &s), ("m1", &cmd));
        n += 1;
    })
    .unwrap();
    assert_eq!(n, 1);
    // Packed (v1.3), the same: the columns of fields 1–6 agree too, the tag tells.
    let mut b = Batcher::new("m1", 10);
    b.push(&cmd);
    let (packed, _, _) = b.take(StreamId::Command).unwrap();
    for tags in [Tags::Require, Tags::AllowUntagged] {
        assert_eq!(
            decode_with_tags(StreamId::Scale, &packed, tags, |_, _| panic!("decoded")),
            Err(WireError::WrongStream {
                expected: "scale",
                found: "command".into()
            })
        );
    }
    assert_eq!(
        decode(StreamId::Command, &packed).unwrap().samples,
        vec![("m1".to_string(), cmd)]
    );
}

#[test]
fn a_measurement_batch_on_a_corrected_streams_key_is_the_wrong_stream() {
    // v1.2 samples lay out their fields after `t_ns` differently: prost refuses them as
    // a scale batch, and the error names what they are instead of "malformed".
    let distance = v1::DistanceBatch {
        samples: vec![v1::DistanceSample {
            machine_id: "m1".into(),
            seq: 1,
            t_ns: 5,
            probe_id: 2,
            distance_mm: 0.01,
            spacing_mm: 80.0,
        }],
        stream: v1::StreamKind::Distance as i32,
    }
    .encode_to_vec();
    assert!(v1::ScaleBatch::decode(&distance[..]).is_err());
    for tags in [Tags::Require, Tags::AllowUntagged] {
        assert_eq!(
            decode_with_tags(StreamId::Scale, &distance, tags, |_, _| panic!("decoded")),
            Err(WireError::WrongStream {
                expected: "scale",
                found: "distance".into()
            })
        );
    }
    assert_eq!(
        tagged(StreamId::Probe, &distance).unwrap_err(),
        WireError::WrongStream {
            expected: "probe",
            found: "distance".into()
        }
    );
    let stage = v1::StageBatch {
        samples: vec![v1::StageSample {
            machine_id: "m1".into(),
            t_ns: 5,
            commanded_mm: 0.1,
            sensor_mm: 0.1,
            probe_id: 2,
            ..Default::default()
        }],
        stream: v1::StreamKind::Stage as i32,
    }
    .encode_to_vec();
    assert_eq!(
        decode(StreamId::Temperature, &stage).unwrap_err(),
        WireError::WrongStream {
            expected: "temperature",
            found: "stage".into()
        }
    );
    // Untagged, or not protobuf: malformed, as before.
    let mut untagged = v1::DistanceBatch::decode(&distance[..]).unwrap();
    untagged.stream = 0;
    assert!(matches!(
        decode(StreamId::Scale, &untagged.encode_to_vec()),
        Err(WireError::Malformed { .. })
    ));
    assert!(matches!(
        decode(StreamId::Scale, &[0xff, 0xff, 0xff]),
        Err(WireError::Malformed { .. })
    ));
}

/// Samples of every stream with every field set, some to values varints and zigzag care
/// about (0, negative, large).
fn every_stream(n: u64) -> Vec<Sample> {
    let mut v = vec![];
    for k in 0..n {
        let f = k as f64;
        let t_ns = if k % 7 == 3 {
            -(k as i64)
        } else {
            k as i64 * 1_000_003
        };
        v.push(Sample::Command(CommandSample {
            seq: k,
            t_ns,
            pos: Vec3::new(f, -f * 0.5, 1e300),
            arc_center: Vec3::new(0.0, f * 1e-9, -0.0),
            arc_radius: if k % 2 == 0 { 0.0 } else { 12.5 },
            segment_id: (k * 1000) as u32,
        }));
        v.push(Sample::Scale(ScaleSample {
            seq: u64::MAX - k,
            t_ns: i64::MIN + k as i64,
            pos: Vec3::new(f, 2.0, -3.5),
        }));
        v.push(Sample::Probe(ProbeSample {
            seq: k << 40,
            t_ns,
            deflection: Vec3::new(0.1 * f, 0.0, -0.2),
            tip_id: k as u32 % 3,
            head_a1_deg: 90.0,
            head_a2_deg: -f,
            // A force probe's force (v1.5), 0 N among them (a force, not none).
            force_n: Some(0.1 * f - 0.5),
        }));
        v.push(Sample::Temperature(TemperatureSample {
            seq: k,
            t_ns: i64::MAX - k as i64,
            sensor: ["air", "", "scale_x"][k as usize % 3].into(),
            celsius: 20.0 + f,
        }));
    }
    v
}

/// The encoded batches of `samples`, one per stream, in `layout`.
fn batches(samples: &[Sample], machine: &str, layout: Layout) -> Vec<(StreamId, Vec<u8>)> {
    let mut b = Batcher::new(machine, usize::MAX).with_layout(layout);
    samples.iter().for_each(|s| {
        b.push(s);
    });
    StreamId::ALL
        .into_iter()
        .filter_map(|s| Some((s, b.take(s)?.0)))
        .collect()
}

/// The bytes prost writes for the batch message `bytes` decode to.
fn prosts_bytes(stream: StreamId, bytes: &[u8]) -> Vec<u8> {
    match stream {
        StreamId::Command => v1::CommandBatch::decode(bytes).unwrap().encode_to_vec(),
        StreamId::Scale => v1::ScaleBatch::decode(bytes).unwrap().encode_to_vec(),
        StreamId::Probe => v1::ProbeBatch::decode(bytes).unwrap().encode_to_vec(),
        StreamId::Temperature => v1::TemperatureBatch::decode(bytes).unwrap().encode_to_vec(),
    }
}

/// A packed batch whose columns field is written twice, the machine id in the first and
/// the columns in the second (one message for prost, which merges them).
fn split_columns(batch: &[u8]) -> Vec<u8> {
    use scancorr_proto::prost::encoding::decode_varint;
    let mut b = batch;
    let mut out = vec![];
    while !b.is_empty() {
        let start = b;
        let key = decode_varint(&mut b).unwrap();
        if key == (3 << 3 | 2) {
            let len = decode_varint(&mut b).unwrap() as usize;
            let (mut cols, rest) = b.split_at(len);
            b = rest;
            let mut machine = vec![];
            let mut others = vec![];
            while !cols.is_empty() {
                let field = cols;
                let k = decode_varint(&mut cols).unwrap();
                let n = decode_varint(&mut cols).unwrap() as usize;
                cols = &cols[n..];
                let whole = &field[..field.len() - cols.len()];
                if k >> 3 == 1 {
                    &mut machine
                } else {
                    &mut others
                }
                .extend_from_slice(whole);
            }
            for part in [machine, others] {
                out.push(3 << 3 | 2);
                encode_varint(part.len() as u64, &mut out);
                out.extend(part);
            }
        } else {
            let _ = decode_varint(&mut b).unwrap();
            out.extend_from_slice(&start[..start.len() - b.len()]);
        }
    }
    out
}

#[test]
fn old_and_packed_batches_decode_to_the_same_samples() {
    let samples = every_stream(50);
    for machine in ["m1", "", "a-much-longer-machine-name"] {
        let old = batches(&samples, machine, Layout::PerSample);
        let packed = batches(&samples, machine, Layout::Packed);
        assert_eq!(old.len(), 4);
        for ((stream, old), (_, packed)) in old.iter().zip(&packed) {
            let want: Vec<(String, Sample)> = samples
                .iter()
                .filter(|s| s.stream() == *stream)
                .map(|s| (machine.to_string(), s.clone()))
                .collect();
            assert_eq!(
                decode(*stream, old).unwrap().samples,
                want,
                "{stream:?} old"
            );
            assert_eq!(decode(*stream, packed).unwrap().samples, want, "{stream:?}");
            // Read by prost rather than straight from the bytes (an unknown field; the
            // columns split in two, which prost merges): the same samples.
            let mut unknown = packed.clone();
            unknown.extend([15 << 3, 1]);
            assert_eq!(
                decode(*stream, &unknown).unwrap().samples,
                want,
                "{stream:?}"
            );
            let split = split_columns(packed);
            assert_ne!(&split, packed);
            assert_eq!(decode(*stream, &split).unwrap().samples, want, "{stream:?}");
            let mut out = vec![];
            let foreign =
                decode_machine_tagged(*stream, packed, "m1", Tags::Require, &mut out).unwrap();
            let ours = if machine == "m1" { want.len() } else { 0 };
            assert_eq!((out.len(), foreign as usize), (ours, want.len() - ours));
            assert_eq!(&prosts_bytes(*stream, packed), packed, "{stream:?}");
            // The v1.1 tag is set: nothing to add for a service that requires it.
            assert_eq!(&*tagged(*stream, packed).unwrap(), &packed[..]);
        }
    }
    let mut b = Batcher::new("m1", 3);
    let full: Vec<_> = samples.iter().take(12).map(|s| b.push(s)).collect();
    assert_eq!(full[..8].iter().flatten().count(), 0);
    assert_eq!(full[8], Some(StreamId::Command));
    let (_, t0, t1) = b.take(StreamId::Command).unwrap();
    assert_eq!((t0, t1), (0, 2_000_006));
    assert!(b.take(StreamId::Command).is_none(), "taken");
    // Batch after batch (the columns emptied and refilled), every sample once, in order.
    let mut b = Batcher::new("m1", 3);
    let mut decoded = vec![];
    for s in &samples[12..] {
        if let Some(stream) = b.push(s) {
            let (bytes, _, _) = b.take(stream).unwrap();
            decode_machine(stream, &bytes, "m1", &mut decoded).unwrap();
        }
    }
    for stream in StreamId::ALL {
        if let Some((bytes, _, _)) = b.take(stream) {
            decode_machine(stream, &bytes, "m1", &mut decoded).unwrap();
        }
    }
    for stream in StreamId::ALL {
        let got: Vec<_> = decoded.iter().filter(|s| s.stream() == stream).collect();
        let want: Vec<_> = samples[12..]
            .iter()
            .filter(|s| s.stream() == stream)
            .collect();
        assert_eq!(got, want, "{stream:?}");
    }
}

#[test]
fn packed_columns_must_agree_in_length() {
    let scale = |columns: v1::ScaleColumns| {
        v1::ScaleBatch {
            stream: v1::StreamKind::Scale as i32,
            columns: Some(columns),
            ..Default::default()
        }
        .encode_to_vec()
    };
    let good = v1::ScaleColumns {
        machine_id: "m1".into(),
        seq: vec![1, 2],
        t_ns: vec![10, 20],
        x: vec![1.0, 2.0],
        y: vec![0.0, 0.0],
        z: vec![3.0, 4.0],
    };
    assert_eq!(
        decode(StreamId::Scale, &scale(good.clone()))
            .unwrap()
            .samples
            .len(),
        2
    );
    let short_y = v1::ScaleColumns {
        y: vec![0.0],
        ..good.clone()
    };
    let e = decode_with(StreamId::Scale, &scale(short_y), |_, _| panic!("decoded"));
    assert_eq!(
        e.unwrap_err().to_string(),
        "malformed ScaleBatch: column `y` holds 1 values for 2 samples (`seq`)"
    );
    let no_seq = v1::ScaleColumns {
        seq: vec![],
        ..good.clone()
    };
    assert!(matches!(
        decode(StreamId::Scale, &scale(no_seq)),
        Err(WireError::Malformed { .. })
    ));
    let temps = v1::TemperatureBatch {
        stream: v1::StreamKind::Temperature as i32,
        columns: Some(v1::TemperatureColumns {
            machine_id: "m1".into(),
            seq: vec![1, 2],
            t_ns: vec![1, 2],
            sensor: vec!["air".into()],
            celsius: vec![20.0, 20.0],
        }),
        ..Default::default()
    };
    assert!(matches!(
        decode(StreamId::Temperature, &temps.encode_to_vec()),
        Err(WireError::Malformed { reason, .. }) if reason.contains("`sensor`")
    ));
    // Columns without samples: an empty batch, as one without messages.
    assert_eq!(
        decode(StreamId::Scale, &scale(v1::ScaleColumns::default())).unwrap_err(),
        WireError::Empty("ScaleBatch")
    );
    // Both forms in one batch.
    let both = v1::ScaleBatch {
        samples: vec![v1::ScaleSample::default()],
        stream: v1::StreamKind::Scale as i32,
        columns: Some(good),
    };
    assert!(matches!(
        decode(StreamId::Scale, &both.encode_to_vec()),
        Err(WireError::Malformed { reason, .. }) if reason.contains("both")
    ));
}

/// The force (v1.5): a force probe's samples carry it on both layouts, a deflection-only
/// probe's none (the column empty, the field absent); a batch mixing the two is written one
/// message per sample, nothing lost; a force column of another length is malformed, named.
#[test]
fn the_force_column_holds_a_force_for_every_sample_or_none() {
    let probe = |k: u64, force_n: Option<f64>| {
        Sample::Probe(ProbeSample {
            seq: k,
            t_ns: k as i64 * 1000,
            deflection: Vec3::new(0.3, 0.0, 0.0),
            tip_id: 1,
            head_a1_deg: 0.0,
            head_a2_deg: 0.0,
            force_n,
        })
    };
    let cases: [Vec<Sample>; 3] = [
        (0..4).map(|k| probe(k, None)).collect(),
        (0..4)
            .map(|k| probe(k, Some(0.2 + 0.1 * k as f64)))
            .collect(),
        (0..4)
            .map(|k| probe(k, (k % 2 == 1).then_some(0.25)))
            .collect(),
    ];
    for (i, samples) in cases.iter().enumerate() {
        for layout in [Layout::Packed, Layout::PerSample] {
            let (stream, bytes) = batches(samples, "m1", layout).swap_remove(0);
            assert_eq!(stream, StreamId::Probe);
            let got: Vec<Sample> = decode(stream, &bytes)
                .unwrap()
                .samples
                .into_iter()
                .map(|(_, s)| s)
                .collect();
            assert_eq!(&got, samples, "case {i} {layout:?}");
            let b = v1::ProbeBatch::decode(&bytes[..]).unwrap();
            let column = b.columns.as_ref().map_or(0, |c| c.force_n.len());
            match (i, layout) {
                (0, Layout::Packed) => assert_eq!(column, 0),
                (1, Layout::Packed) => assert_eq!(column, 4),
                // Mixed: one message per sample, whatever the layout asked.
                _ => assert!(b.columns.is_none() && b.samples.len() == 4),
            }
        }
    }
    // A force column of another length: the same error as any column, on both readers.
    let bad = v1::ProbeBatch {
        stream: v1::StreamKind::Probe as i32,
        columns: Some(v1::ProbeColumns {
            machine_id: "m1".into(),
            seq: vec![1, 2],
            t_ns: vec![10, 20],
            u: vec![0.3; 2],
            v: vec![0.0; 2],
            w: vec![0.0; 2],
            tip_id: vec![1; 2],
            head_a1_deg: vec![0.0; 2],
            head_a2_deg: vec![0.0; 2],
            force_n: vec![0.2],
        }),
        ..Default::default()
    }
    .encode_to_vec();
    let want = "malformed ProbeBatch: column `force_n` holds 1 values for 2 samples (`seq`)";
    let e = decode_with(StreamId::Probe, &bad, |_, _| panic!("decoded")).unwrap_err();
    assert_eq!(e.to_string(), want);
    // Through prost (an unknown field appended): the same.
    let mut unknown = bad.clone();
    unknown.extend([15 << 3, 1]);
    let e = decode_with(StreamId::Probe, &unknown, |_, _| panic!("decoded")).unwrap_err();
    assert_eq!(e.to_string(), want);
}

mod garbled {
    use super::*;
    use proptest::prelude::*;

    /// A packed varint column's values as this module reads them (`None` when refused)
    /// and as prost's `decode_varint` reads them.
    fn column_as_read(bytes: &[u8]) -> (Option<Vec<u64>>, Option<Vec<u64>>) {
        let ours = varints(bytes).map(|n| {
            let v: Vec<u64> = Varints(bytes).collect();
            assert_eq!(v.len(), n, "{bytes:02x?}: counted {n}, read {}", v.len());
            v
        });
        let mut b = bytes;
        let mut prost = Some(vec![]);
        while !b.is_empty() {
            match scancorr_proto::prost::encoding::decode_varint(&mut b) {
                Ok(v) => prost.as_mut().expect("not refused yet").push(v),
                Err(_) => {
                    prost = None;
                    break;
                }
            }
        }
        (ours, prost)
    }

    /// The edges of a varint, which random bytes seldom reach: ten bytes whose last is 0 or
    /// 1 (read) or more (refused), ten continuation bytes, a value cut short, no bytes;
    /// eight and nine bytes (the longest read from one word, and one more).
    #[test]
    fn varint_edges_read_as_prost_reads_them() {
        let ten = |last: u8| [[0xff; 9].as_slice(), &[last]].concat();
        let cases: Vec<(Vec<u8>, Option<Vec<u64>>)> = vec![
            (ten(1), Some(vec![u64::MAX])),
            ([[0x80; 9].as_slice(), &[1]].concat(), Some(vec![1 << 63])),
            ([[0x80; 9].as_slice(), &[0]].concat(), Some(vec![0])),
            (ten(2), None),
            (ten(0x7f), None),
            (vec![0xff; 10], None),
            (
                [ten(1).as_slice(), &[0x05]].concat(),
                Some(vec![u64::MAX, 5]),
            ),
            (vec![5, 0xff, 0xff], None),
            (vec![0x96, 0x01], Some(vec![150])),
            (
                [[0xff; 7].as_slice(), &[0x7f]].concat(),
                Some(vec![(1 << 56) - 1]),
            ),
            ([[0x80; 8].as_slice(), &[1]].concat(), Some(vec![1 << 56])),
            (
                [[0x81; 7].as_slice(), &[0x40]].concat(),
                Some(vec![
                    (0..7).map(|k| 1u64 << (7 * k)).sum::<u64>() | 0x40 << 49,
                ]),
            ),
            (vec![], Some(vec![])),
        ];
        // Each case alone and after 1–15 one-byte values: its edge then falls anywhere in
        // the words the column is read by (eight bytes), and across two of them.
        for (bytes, want) in cases {
            for before in 0..16 {
                let bytes = [vec![0x05; before], bytes.clone()].concat();
                let want = want.clone().map(|w| [vec![5; before], w].concat());
                let (ours, prost) = column_as_read(&bytes);
                assert_eq!(prost, want, "prost on {bytes:02x?}");
                assert_eq!(ours, want, "{bytes:02x?}");
            }
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]

        /// A packed varint column is counted and read as prost reads it: the same count
        /// and values, and refused exactly when prost refuses one of its values.
        #[test]
        fn varint_columns_read_as_prost_reads_them(
            bytes in prop::collection::vec(
                prop_oneof![0u8..2, 2u8..0x80, 0x80u8..=0xff, Just(0xffu8)], 0..80),
        ) {
            let (ours, prost) = column_as_read(&bytes);
            prop_assert_eq!(ours, prost, "{:02x?}", bytes);
        }

        /// Every strict prefix of a packed batch is refused, and no byte changed anywhere
        /// makes the decoder panic or hand out samples of a batch it then refuses.
        #[test]
        fn cut_or_changed_packed_batches_are_errors(
            n in 1u64..12,
            which in 0usize..4,
            at in any::<prop::sample::Index>(),
            byte in any::<u8>(),
        ) {
            let (stream, bytes) = batches(&every_stream(n), "m1", Layout::Packed)
                .swap_remove(which);
            for cut in 0..bytes.len() {
                let r = decode_with_tags(stream, &bytes[..cut], Tags::Require, |_, _| {});
                prop_assert!(r.is_err(), "prefix of {cut} of {} bytes decoded", bytes.len());
            }
            let mut changed = bytes.clone();
            changed[at.index(bytes.len())] = byte;
            let mut handed = 0;
            match decode_with_tags(stream, &changed, Tags::AllowUntagged, |_, _| handed += 1) {
                Ok(k) => prop_assert_eq!(k, handed),
                Err(_) => prop_assert_eq!(handed, 0),
            }
        }

        /// Columns of any lengths: decoded when they agree, else malformed (or empty).
        #[test]
        fn columns_of_any_lengths(lens in prop::collection::vec(0usize..4, 10)) {
            let col = |k: usize| vec![1.5; lens[k]];
            let c = v1::CommandColumns {
                machine_id: "m1".into(),
                seq: vec![7; lens[0]],
                t_ns: vec![-1; lens[1]],
                x: col(2),
                y: col(3),
                z: col(4),
                arc_cx: col(5),
                arc_cy: col(6),
                arc_cz: col(7),
                arc_radius: col(8),
                segment_id: vec![3; lens[9]],
            };
            let bytes = v1::CommandBatch {
                stream: v1::StreamKind::Command as i32,
                columns: Some(c),
                ..Default::default()
            }
            .encode_to_vec();
            let r = decode(StreamId::Command, &bytes);
            let agree = lens.iter().all(|&l| l == lens[0]);
            match r {
                Ok(d) => prop_assert!(agree && d.samples.len() == lens[0]),
                Err(WireError::Empty(_)) => prop_assert!(agree && lens[0] == 0),
                Err(WireError::Malformed { .. }) => prop_assert!(!agree),
                Err(e) => prop_assert!(false, "{e}"),
            }
        }
    }
}

#[test]
fn encode_points_writes_prosts_bytes() {
    let ids: Vec<String> = ["accel_deflection", "", "x_cyclic"]
        .map(String::from)
        .to_vec();
    let mut ps = vec![];
    for k in 0..40u64 {
        let f = k as f64;
        let z = |v: f64| if k % 3 == 0 { 0.0 } else { v };
        ps.push(CorrectedPoint {
            seq: k * 1_000_003,
            t_ns: if k % 5 == 0 {
                -(k as i64) * 7_777_777
            } else {
                k as i64 * 1_000_000_000
            },
            sample_seq: k % 4,
            surface: Vec3::new(z(f * 1.5), -f, if k % 2 == 0 { -0.0 } else { 3.25 }),
            tip_center: Vec3::new(f, z(2.0), 1e-300),
            normal: Vec3::zeros(),
            corrections: (0..3)
                .map(|i| Vec3::new(z(i as f64 * 1e-4), 0.0, -1e-6 * (k % 4) as f64))
                .collect(),
            calibration_version: k % 3,
            estimator_valid: k % 2 == 0,
            segment_id: (k % 7) as u32,
            tip_id: (k * 300) as u32,
        });
    }
    // Lengths of one, two and three bytes (an effect id longer than 127 bytes, one longer
    // than 16 KiB), and a calibration with no effect.
    let long_ids = ["x".repeat(200), "y".repeat(17_000), String::new()].to_vec();
    for ids in [&ids, &long_ids, &vec![]] {
        for machine in [
            "m1",
            "",
            "a-machine-with-a-long-name-to-make-lengths-two-bytes",
        ] {
            let per_point: Vec<_> = ps.iter().map(|p| point(p, machine, ids)).collect();
            let want = scancorr_proto::points::pack(&per_point).encode_to_vec();
            let mut got = vec![0xAA];
            encode_points(&ps, machine, ids, &mut got);
            assert_eq!(&got[1..], &want[..], "machine `{machine}`");
            // Read back: the points, each naming the machine and all effects.
            let back = v1::CorrectedPointBatch::decode(&got[1..])
                .unwrap()
                .into_points()
                .unwrap();
            assert_eq!(back, per_point);
        }
    }
}
