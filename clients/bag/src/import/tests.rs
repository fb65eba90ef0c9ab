use super::*;
use crate::{BagHeader, BagReader, BagWriter};
use scancorr_proto::v1::{
    CommandBatch, CommandColumns, DistanceBatch, ProbeBatch, ScaleBatch, StageBatch, StreamKind,
    TemperatureBatch,
};

/// Reads `text` with `mapping`; the samples the sink got, or the error.
fn import(text: &str, mapping: &Mapping) -> Result<(Summary, Vec<Sample>), ImportError> {
    let mut got = vec![];
    let s = read(
        text.as_bytes(),
        "t.csv",
        mapping,
        &Options::default(),
        |s| {
            got.push(s);
            Ok(())
        },
    )?;
    Ok((s, got))
}

fn map_json(j: &str) -> Mapping {
    serde_json::from_str(j).unwrap_or_else(|e| panic!("{e}: {j}"))
}

const MIXED: &str = r#"{
  "machine": "m1",
  "time": {"column": "time_ms", "unit": "ms", "offset_ns": 5},
  "command": {"unit": "um", "x": "cx", "y": "cy", "z": 0, "segment_id": "seg"},
  "scale": {"x": "sx", "y": "sy", "z": "sz", "unit": "in"},
  "probe": {"u": "u", "v": "v", "w": "w", "tip_id": 2, "head_a1_deg": 90, "head_a2_deg": "a2"},
  "temperature": {"unit": "K", "sensors": {"air": "T_air", "stylus": "T_st"}}
}"#;

#[test]
fn a_table_at_mixed_rates_becomes_samples() {
    let text = "\
# a controller trace
time_ms;cx;cy;seg;sx;sy;sz;u;v;w;a2;T_st;T_air;note
0;1000;2000;7;1;2;3;0.01;0;0;0;293.15;294.15;start

0.5;1500;2500;7;;;;;;;;;;
1;2000;3000;8;1.5;2.5;3.5;0.02;0.01;0;15;;;
2;;;;;;;;;;;;;just a note
";
    let m = map_json(MIXED);
    let (sum, got) = import(text, &m).unwrap();
    assert_eq!(sum.delimiter, "semicolon");
    assert_eq!(sum.rows, 4);
    assert_eq!(sum.rows_without_samples, 1);
    assert_eq!(sum.samples["command"], 3);
    assert_eq!(sum.samples["scale"], 2);
    assert_eq!(sum.samples["probe"], 2);
    assert_eq!(sum.samples["temperature"], 2);
    // Sensors in column order (T_st before T_air), not the mapping's.
    assert_eq!(sum.sensors, ["stylus", "air"]);
    assert_eq!(sum.unmapped_columns, ["note"]);
    assert_eq!(sum.first_t_ns, Some(5));
    assert_eq!(sum.last_t_ns, Some(1_000_005));
    assert!(sum.warnings.is_empty(), "{:?}", sum.warnings);
    // Row 1: command, scale, probe, then the sensors in column order.
    let streams: Vec<Stream> = got.iter().map(Sample::stream).collect();
    use Stream::*;
    assert_eq!(
        streams,
        [
            Command,
            Scale,
            Probe,
            Temperature,
            Temperature,
            Command,
            Command,
            Scale,
            Probe
        ]
    );
    match &got[0] {
        Sample::Command(c) => {
            assert_eq!(
                (c.seq, c.t_ns, c.x, c.y, c.z, c.segment_id),
                (0, 5, 1.0, 2.0, 0.0, 7)
            );
            assert_eq!(c.machine_id, "m1");
            assert_eq!(c.arc_radius, 0.0);
        }
        s => panic!("{s:?}"),
    }
    match &got[1] {
        Sample::Scale(c) => assert_eq!((c.x, c.y, c.z), (25.4, 50.8, 76.19999999999999)),
        s => panic!("{s:?}"),
    }
    match &got[2] {
        Sample::Probe(p) => assert_eq!(
            (p.u, p.tip_id, p.head_a1_deg, p.head_a2_deg),
            (0.01, 2, 90.0, 0.0)
        ),
        s => panic!("{s:?}"),
    }
    match (&got[3], &got[4]) {
        (Sample::Temperature(a), Sample::Temperature(b)) => {
            assert_eq!((a.sensor.as_str(), a.seq), ("stylus", 0));
            assert_eq!((b.sensor.as_str(), b.seq), ("air", 1));
            assert!((a.celsius - 20.0).abs() < 1e-12 && (b.celsius - 21.0).abs() < 1e-12);
        }
        s => panic!("{s:?}"),
    }
    match &got[5] {
        Sample::Command(c) => assert_eq!((c.seq, c.t_ns, c.x), (1, 500_005, 1.5)),
        s => panic!("{s:?}"),
    }
    match &got[8] {
        Sample::Probe(p) => assert_eq!((p.seq, p.t_ns, p.head_a2_deg), (1, 1_000_005, 15.0)),
        s => panic!("{s:?}"),
    }
}

#[test]
fn whitespace_columns_and_the_command_line_form() {
    let mut m = Mapping {
        machine: Some("cmm-7".into()),
        time: Some(TimeColumn {
            column: "t".into(),
            unit: TimeUnit::S,
            offset_ns: 0,
        }),
        ..Default::default()
    };
    for (path, col) in [
        ("scale.x", "X"),
        ("scale.y", "Y"),
        ("scale.z", "Z"),
        ("distance.3", "d3"),
        ("temperature.part", "T"),
    ] {
        m.set(path, Source::Column(col.into())).unwrap();
    }
    m.set("distance.3.spacing", Source::Constant(25.0)).unwrap();
    m.set_unit("distance", "um").unwrap();
    m.set_unit("temperature", "C").unwrap();
    let text = "t X Y Z d3 T\n0.001 1 2 3 4.5 20.5\n0.002 1 2 3 5 20.5\n";
    let (sum, got) = import(text, &m).unwrap();
    assert_eq!(sum.delimiter, "whitespace");
    assert_eq!(sum.distance_probes, [3]);
    assert_eq!(sum.samples["distance"], 2);
    match &got[5] {
        Sample::Distance(d) => assert_eq!(
            (d.t_ns, d.probe_id, d.distance_mm, d.spacing_mm, d.seq),
            (2_000_000, 3, 0.005, 0.025, 1)
        ),
        s => panic!("{s:?}"),
    }
    // Specifications that do not parse name what is wrong.
    for (path, needle) in [
        ("scale.w", "no field `w`"),
        ("nothing.x", "no stream `nothing`"),
        ("x", "STREAM.FIELD"),
        ("temperature.bad/name", "sensor name"),
        ("distance.a", "not a probe id"),
        ("distance.9.spacing", "before its spacing"),
        ("distance.3.offset", "no field `offset`"),
    ] {
        let e = m.clone().set(path, Source::Column("c".into())).unwrap_err();
        assert!(e.0.contains(needle), "{path}: {e}");
    }
    let e = m
        .clone()
        .set("temperature.air", Source::Constant(20.0))
        .unwrap_err();
    assert!(e.0.contains("must be a column"), "{e}");
    assert!(m
        .clone()
        .set_unit("scale", "ft")
        .unwrap_err()
        .0
        .contains("mm, um, m or in"));
    assert!(m
        .clone()
        .set_unit("temperature", "F")
        .unwrap_err()
        .0
        .contains("C or K"));
}

#[test]
fn a_mapping_that_cannot_work_is_refused_before_reading() {
    let base = map_json(MIXED);
    let check = |f: &dyn Fn(&mut Mapping), needle: &str| {
        let mut m = base.clone();
        f(&mut m);
        let e = m.check().unwrap_err();
        assert!(e.0.contains(needle), "{needle}: {e}");
        let e = import("time_ms\n", &m).unwrap_err();
        assert!(matches!(e, ImportError::Mapping(_)), "{e}");
    };
    check(&|m| m.time = None, "no time column");
    check(&|m| m.machine = Some("m/1".into()), "machine id");
    check(
        &|m| {
            m.temperature
                .as_mut()
                .unwrap()
                .sensors
                .insert("*".into(), "T".into());
        },
        "sensor name",
    );
    check(
        &|m| m.scale.as_mut().unwrap().y = None,
        "`scale.y` is not mapped",
    );
    check(
        &|m| m.command.as_mut().unwrap().arc_radius = Some(Source::Column("r".into())),
        "the arc's four fields",
    );
    check(
        &|m| m.probe.as_mut().unwrap().tip_id = Some(Source::Constant(1.5)),
        "not a whole number",
    );
    check(
        &|m| {
            m.scale = Some(ScaleMap {
                x: Some(Source::Constant(1.0)),
                y: Some(Source::Constant(1.0)),
                z: Some(Source::Constant(1.0)),
                ..Default::default()
            })
        },
        "`scale` has no column",
    );
    check(&|m| m.max_gap_s = Some(-1.0), "max_gap_s");
    check(
        &|m| {
            *m = Mapping {
                machine: Some("m1".into()),
                time: m.time.clone(),
                ..Default::default()
            }
        },
        "no stream is mapped",
    );
    // No machine at all.
    let mut m = base.clone();
    m.machine = None;
    assert!(import("time_ms\n", &m)
        .unwrap_err()
        .to_string()
        .contains("no machine id"));
    // Unknown fields in the file are refused (a typo is not ignored).
    let e =
        serde_json::from_str::<Mapping>(r#"{"time": {"column": "t", "unit": "s"}, "scales": {}}"#)
            .unwrap_err();
    assert!(e.to_string().contains("scales"), "{e}");
    let e =
        serde_json::from_str::<Mapping>(r#"{"time": {"column": "t", "unit": "min"}}"#).unwrap_err();
    assert!(e.to_string().contains("min"), "{e}");
}

#[test]
fn the_header_must_fit_the_mapping() {
    let m = map_json(MIXED);
    let e = import("time_ms,cx,cy,cx,seg\n", &m).unwrap_err();
    let s = e.to_string();
    assert!(matches!(e, ImportError::Header { .. }), "{s}");
    assert!(
        s.contains("t.csv:1:4: column \"cx\": a duplicate column name (also column 2)"),
        "{s}"
    );
    assert!(s.contains("no column \"sx\" (mapped as scale.x)"), "{s}");
    assert!(
        s.contains("no column \"T_air\" (mapped as temperature.air)"),
        "{s}"
    );
    assert!(
        s.contains("the header's columns: time_ms, cx, cy, cx, seg"),
        "{s}"
    );
    assert!(matches!(
        import("# nothing\n\n", &m).unwrap_err(),
        ImportError::NoHeader { .. }
    ));
}

/// A small scale-only mapping for the error tests.
fn scale_map(gap: Option<f64>) -> Mapping {
    map_json(&format!(
        r#"{{"machine": "m1", "time": {{"column": "t", "unit": "s"}}, {}
            "scale": {{"x": "x", "y": "y", "z": "z"}},
            "temperature": {{"sensors": {{"air": "T"}}}}}}"#,
        gap.map(|g| format!("\"max_gap_s\": {g},"))
            .unwrap_or_default()
    ))
}

#[test]
fn bad_rows_are_all_found_named_by_line_and_column_and_nothing_is_kept() {
    let text = "\
t,x,y,z,T
0,1,2,3,20
0.1,1,abc,3,
# a comment keeps its line number
0.2,1,2,,
0.3,1,2,3,20
0.25,1,2,3,
0.4,1,2
0.5,1,2,3,21,extra
0.6,1,2,3,1e999
,1,2,3,
0.7,\"1,2,3,
";
    let mut calls = 0;
    let e = read(
        text.as_bytes(),
        "t.csv",
        &scale_map(None),
        &Options::default(),
        |_| {
            calls += 1;
            Ok(())
        },
    )
    .unwrap_err();
    let s = e.to_string();
    let ImportError::Rows {
        bad_rows,
        rows,
        errors,
        more,
        ..
    } = &e
    else {
        panic!("{s}")
    };
    assert_eq!((*bad_rows, *rows, *more), (8, 10, 0), "{s}");
    assert_eq!(errors.len(), 8, "{s}");
    for needle in [
        "t.csv:3:3: column \"y\": \"abc\" is not a number",
        "t.csv:5:4: column \"z\": empty, but 2 other column(s) of scale are filled",
        "t.csv:7:1: column \"t\": time 0.25 (t_ns 250000000) is not after scale's previous sample (line 6, t_ns 300000000)",
        "t.csv:8: 3 cell(s), the header has 5",
        "t.csv:9:6: column \"(beyond the header)\": 6 cell(s), the header has 5",
        "t.csv:10:5: column \"T\": \"1e999\" is not a finite number",
        "t.csv:11:1: column \"t\": no time, but the row has samples",
        "t.csv:12: cell 2 opens a quote that the line does not close",
    ] {
        assert!(s.contains(needle), "expected `{needle}` in:\n{s}");
    }
    assert!(s.starts_with("t.csv: 8 bad row(s) of 10:"), "{s}");
    // The first row's samples went to the sink; none after the first bad row.
    assert_eq!(calls, 2);

    // Errors kept up to max_errors, all counted.
    let e = read(
        text.as_bytes(),
        "t.csv",
        &scale_map(None),
        &Options {
            max_errors: 3,
            ..Default::default()
        },
        |_| Ok(()),
    )
    .unwrap_err();
    match &e {
        ImportError::Rows {
            bad_rows,
            errors,
            more,
            ..
        } => assert_eq!((*bad_rows, errors.len(), *more), (8, 3, 5)),
        e => panic!("{e}"),
    }
    assert!(e.to_string().contains("… and 5 more error(s)"), "{e}");
}

#[test]
fn gaps_and_time_order_are_per_stream() {
    // The scale at 10 Hz, the temperature at 1 Hz in the same table.
    let mut text = String::from("t,x,y,z,T\n");
    for k in 0..=20 {
        let t = k as f64 * 0.1;
        let temp = if k % 10 == 0 { "20" } else { "" };
        text += &format!("{t},1,2,3,{temp}\n");
    }
    // A gap limit the temperature's own rate exceeds: refused, naming the sensor.
    let e = import(&text, &scale_map(Some(0.15)))
        .unwrap_err()
        .to_string();
    assert!(e.contains("a gap of 1 s in temperature.air"), "{e}");
    assert!(e.contains("more than the largest gap 0.15 s"), "{e}");
    assert!(!e.contains("in scale"), "{e}");
    // A stream's own limit wins.
    let mut m = scale_map(Some(0.15));
    m.temperature.as_mut().unwrap().max_gap_s = Some(1.5);
    let (sum, _) = import(&text, &m).unwrap();
    assert_eq!(sum.samples["temperature"], 3);
    assert_eq!(sum.samples["scale"], 21);
    // A scale gap.
    let gap = text
        .replace("0.5,1,2,3,\n", "")
        .replace("0.6000000000000001,1,2,3,\n", "");
    let e = import(&gap, &m).unwrap_err().to_string();
    assert!(e.contains("a gap of 0.3 s in scale"), "{e}");
    // Two sensors at one time are fine; one sensor twice at one time is not.
    let two = map_json(
        r#"{"machine": "m1", "time": {"column": "t", "unit": "ns"},
            "temperature": {"sensors": {"a": "A", "b": "B"}}}"#,
    );
    let (sum, got) = import("t,A,B\n5,20,21\n5,,\n6,20,\n", &two).unwrap();
    assert_eq!(sum.samples["temperature"], 3);
    assert_eq!(got.iter().map(Sample::seq).collect::<Vec<_>>(), [0, 1, 2]);
    let e = import("t,A,B\n5,20,21\n5,20,\n", &two)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("is not after temperature.a's previous sample"),
        "{e}"
    );
    // A sensor of its own may not take the stream back in time.
    let e = import("t,A,B\n5,20,\n4,,21\n", &two)
        .unwrap_err()
        .to_string();
    assert!(e.contains("goes back in the temperature stream"), "{e}");
}

#[test]
fn an_empty_import_is_an_error_and_an_unused_column_a_warning() {
    let m = scale_map(None);
    let e = import("t,x,y,z,T\n0,,,,\n1,,,,\n", &m).unwrap_err();
    assert!(e.to_string().contains("no sample in 2 data row(s)"), "{e}");
    let (sum, _) = import("t,x,y,z,T\n0,1,2,3,\n", &m).unwrap();
    assert_eq!(sum.warnings.len(), 1);
    assert!(
        sum.warnings[0].contains("temperature.air has no sample"),
        "{:?}",
        sum.warnings
    );
}

#[test]
fn a_failing_sink_stops_the_import() {
    let e = read(
        "t,x,y,z,T\n0,1,2,3,\n".as_bytes(),
        "t.csv",
        &scale_map(None),
        &Options::default(),
        |_| Err("disk full".into()),
    )
    .unwrap_err();
    assert!(
        matches!(e, ImportError::Sink(_)) && e.to_string() == "disk full",
        "{e}"
    );
}

/// A bag with every raw stream: packed and per-sample batches, several sensors at one time,
/// values that print with many digits, a negative zero, an arc, two machines.
fn write_bag(path: &std::path::Path) -> Vec<Sample> {
    let mut w = BagWriter::create(path, BagHeader::default()).unwrap();
    let m = "m1".to_string();
    let mut all = vec![];
    let mut cmd = CommandColumns {
        machine_id: m.clone(),
        ..Default::default()
    };
    let mut scale = vec![];
    let mut probe = vec![];
    let mut temp = vec![];
    let mut dist = vec![];
    let mut stage = vec![];
    for k in 0..50u64 {
        let t = 1_000_000 * k as i64 + 123;
        let x = 0.1 + 0.2 * k as f64 + 1e-13;
        cmd.seq.push(k);
        cmd.t_ns.push(t);
        cmd.x.push(x);
        cmd.y.push(-0.0);
        cmd.z.push(-250.0 / 3.0);
        cmd.arc_cx.push(1.0 / 7.0);
        cmd.arc_cy.push(2.0);
        cmd.arc_cz.push(3.0);
        cmd.arc_radius.push(if k < 25 { 12.5 } else { 0.0 });
        cmd.segment_id.push(k as u32 / 10);
        all.push(Sample::Command(CommandSample {
            machine_id: m.clone(),
            seq: k,
            t_ns: t,
            x,
            y: -0.0,
            z: -250.0 / 3.0,
            arc_cx: 1.0 / 7.0,
            arc_cy: 2.0,
            arc_cz: 3.0,
            arc_radius: if k < 25 { 12.5 } else { 0.0 },
            segment_id: k as u32 / 10,
        }));
        let s = ScaleSample {
            machine_id: m.clone(),
            seq: k,
            t_ns: t + 7,
            x: x * 1.000001,
            y: 1e-300,
            z: 5e300,
        };
        scale.push(s.clone());
        all.push(Sample::Scale(s));
        let p = ProbeSample {
            machine_id: m.clone(),
            seq: k,
            t_ns: t,
            u: 0.3 * (k as f64).sin(),
            v: 0.0,
            w: -0.1,
            tip_id: 3,
            head_a1_deg: 90.0,
            head_a2_deg: 7.5,
            force_n: None,
        };
        probe.push(p.clone());
        all.push(Sample::Probe(p));
        if k % 10 == 0 {
            for (i, sensor) in ["stylus", "scale_x", "air"].iter().enumerate() {
                let s = TemperatureSample {
                    machine_id: m.clone(),
                    seq: temp.len() as u64,
                    t_ns: t,
                    sensor: sensor.to_string(),
                    celsius: 20.0 + 0.001 * (k + i as u64) as f64,
                };
                temp.push(s.clone());
                all.push(Sample::Temperature(s));
            }
            for id in [2u32, 1] {
                let d = DistanceSample {
                    machine_id: m.clone(),
                    seq: dist.len() as u64,
                    t_ns: t + 1,
                    probe_id: id,
                    distance_mm: 0.001 * k as f64 - id as f64,
                    spacing_mm: 25.0 * id as f64,
                };
                dist.push(d.clone());
                all.push(Sample::Distance(d));
            }
            let g = StageSample {
                machine_id: m.clone(),
                seq: stage.len() as u64,
                t_ns: t + 2,
                commanded_mm: 20.0,
                sensor_mm: 19.9999,
                probe_id: 2,
            };
            stage.push(g.clone());
            all.push(Sample::Stage(g));
        }
    }
    let tag = |k: StreamKind| k as i32;
    w.write_msg(
        &m,
        "cmm",
        1,
        &CommandBatch {
            samples: vec![],
            stream: tag(StreamKind::Command),
            columns: Some(cmd),
        },
    )
    .unwrap();
    // Per-sample batches, in two halves.
    for half in scale.chunks(25) {
        w.write_msg(
            &m,
            "cmm",
            2,
            &ScaleBatch {
                samples: half.to_vec(),
                stream: tag(StreamKind::Scale),
                columns: None,
            },
        )
        .unwrap();
    }
    w.write_msg(
        &m,
        "cmm",
        3,
        &ProbeBatch {
            samples: probe,
            stream: tag(StreamKind::Probe),
            columns: None,
        },
    )
    .unwrap();
    w.write_msg(
        &m,
        "cmm",
        4,
        &TemperatureBatch {
            samples: temp,
            stream: tag(StreamKind::Temperature),
            columns: None,
        },
    )
    .unwrap();
    w.write_msg(
        &m,
        "cmm",
        5,
        &DistanceBatch {
            samples: dist,
            stream: tag(StreamKind::Distance),
        },
    )
    .unwrap();
    w.write_msg(
        &m,
        "cmm",
        6,
        &StageBatch {
            samples: stage,
            stream: tag(StreamKind::Stage),
        },
    )
    .unwrap();
    // Another machine's stream is not exported with m1.
    w.write_msg(
        "m2",
        "cmm",
        7,
        &ScaleBatch {
            samples: vec![ScaleSample {
                machine_id: "m2".into(),
                seq: 0,
                t_ns: 3,
                x: 1.0,
                y: 2.0,
                z: 3.0,
            }],
            stream: tag(StreamKind::Scale),
            columns: None,
        },
    )
    .unwrap();
    w.finish().unwrap();
    all
}

fn tmp(name: &str) -> std::path::PathBuf {
    let d = std::env::temp_dir().join(format!("scancorr-bag-import-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d.join(name)
}

#[test]
fn a_bag_exported_wide_reads_back_to_the_same_samples() {
    let path = tmp("wide.mcap");
    let mut want = write_bag(&path);
    let bag = BagReader::open(&path).unwrap();
    let mut csv = vec![];
    let ex = export_wide(&bag, "m1", &mut csv).unwrap();
    let text = String::from_utf8(csv).unwrap();
    assert_eq!(ex.sensors, ["stylus", "scale_x", "air"]);
    assert_eq!(ex.distance_probes, [2, 1]);
    assert_eq!(ex.samples["command"], 50);
    assert_eq!(ex.samples["temperature"], 15);
    assert_eq!(ex.foreign_samples, 0);
    assert_eq!(ex.bad_batches, 0);
    // Command/probe at t, scale at t+7, distance t+1, stage t+2 (every tenth).
    assert_eq!(ex.rows, 50 * 2 + 5 * 2);
    let head = text.lines().next().unwrap();
    assert!(
        head.starts_with("t_ns,command_x_mm,command_y_mm,command_z_mm,command_arc_cx_mm"),
        "{head}"
    );
    assert!(head.contains(",temperature_stylus_C,temperature_scale_x_C,temperature_air_C,distance_2_mm,distance_2_spacing_mm,distance_1_mm,"), "{head}");
    assert!(text.contains(",-0,"), "negative zero kept");

    // The mapping survives its JSON form.
    let json = serde_json::to_string_pretty(&ex.mapping).unwrap();
    let mapping: Mapping = serde_json::from_str(&json).unwrap();
    assert_eq!(mapping, ex.mapping);
    let (sum, mut got) = import(&text, &mapping).unwrap();
    assert_eq!(sum.rows, ex.rows);
    assert_eq!(sum.delimiter, "comma");
    assert!(sum.unmapped_columns.is_empty());
    // Per stream, the same samples, bit for bit (seq included: the bag's start at 0).
    let key = |s: &Sample| (stream_index(s.stream()), s.seq());
    want.sort_by_key(key);
    got.sort_by_key(key);
    assert_eq!(got.len(), want.len());
    for (g, w) in got.iter().zip(&want) {
        assert_eq!(format!("{g:?}"), format!("{w:?}"));
        assert_eq!(g, w);
    }
    if let (Sample::Command(g), Sample::Command(w)) = (&got[0], &want[0]) {
        assert_eq!(g.y.to_bits(), w.y.to_bits(), "-0.0 stays -0.0");
    }
    std::fs::remove_file(&path).ok();
}

#[test]
fn a_bag_a_table_cannot_hold_is_refused() {
    let path = tmp("backwards.mcap");
    let mut w = BagWriter::create(&path, BagHeader::default()).unwrap();
    let s = |seq, t_ns, x: f64| ScaleSample {
        machine_id: "m1".into(),
        seq,
        t_ns,
        x,
        y: 0.0,
        z: 0.0,
    };
    w.write_msg(
        "m1",
        "cmm",
        1,
        &ScaleBatch {
            samples: vec![s(0, 10, 1.0), s(1, 5, 1.0)],
            stream: StreamKind::Scale as i32,
            columns: None,
        },
    )
    .unwrap();
    w.finish().unwrap();
    let bag = BagReader::open(&path).unwrap();
    let e = export_wide(&bag, "m1", &mut Vec::new())
        .unwrap_err()
        .to_string();
    assert!(e.contains("cmm/m1/raw/scale sample seq 1 (t_ns 5): not after the previous sample (seq 0, t_ns 10)"), "{e}");
    assert!(matches!(
        export_wide(&bag, "m9", &mut Vec::new()),
        Err(WideError::Empty(_))
    ));

    let mut w = BagWriter::create(&path, BagHeader::default()).unwrap();
    w.write_msg(
        "m1",
        "cmm",
        1,
        &ScaleBatch {
            samples: vec![s(0, 10, f64::NAN)],
            stream: StreamKind::Scale as i32,
            columns: None,
        },
    )
    .unwrap();
    w.finish().unwrap();
    let bag = BagReader::open(&path).unwrap();
    let e = export_wide(&bag, "m1", &mut Vec::new())
        .unwrap_err()
        .to_string();
    assert!(e.contains("x is NaN, not a finite number"), "{e}");
    std::fs::remove_file(&path).ok();
}
