#![allow(dead_code)]
use prost::Message;
use scancorr_bag::*;
use scancorr_proto::v1::*;
use std::collections::BTreeMap;
use std::path::PathBuf;

pub fn tmp(name: &str) -> PathBuf {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("scancorr-bag");
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(format!("{name}.mcap"))
}

/// Deterministic pseudo-random numbers (xorshift).
pub struct Rng(pub u64);
impl Rng {
    pub fn next(&mut self) -> u64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        self.0
    }
    pub fn f(&mut self) -> f64 {
        (self.next() >> 11) as f64 / (1u64 << 53) as f64 - 0.5
    }
}

/// An encoded batch of `n` samples of `stream` for `machine`, first sample at `t0` ns.
pub fn batch(
    stream: Stream,
    machine: &str,
    seq0: u64,
    t0: i64,
    n: usize,
    rng: &mut Rng,
) -> Vec<u8> {
    let m = machine.to_string();
    let t = |i: usize| t0 + i as i64 * 1_000_000;
    let seq = |i: usize| seq0 + i as u64;
    match stream {
        Stream::Command => CommandBatch {
            samples: (0..n)
                .map(|i| CommandSample {
                    machine_id: m.clone(),
                    seq: seq(i),
                    t_ns: t(i),
                    x: rng.f(),
                    y: rng.f(),
                    z: rng.f(),
                    segment_id: 3,
                    ..Default::default()
                })
                .collect(),
            // Later fields (e.g. the v1.1 stream tag) keep their defaults.
            ..Default::default()
        }
        .encode_to_vec(),
        Stream::Scale => ScaleBatch {
            samples: (0..n)
                .map(|i| ScaleSample {
                    machine_id: m.clone(),
                    seq: seq(i),
                    t_ns: t(i),
                    x: rng.f(),
                    y: rng.f(),
                    z: rng.f(),
                })
                .collect(),
            // Later fields (e.g. the v1.1 stream tag) keep their defaults.
            ..Default::default()
        }
        .encode_to_vec(),
        Stream::Probe => ProbeBatch {
            samples: (0..n)
                .map(|i| ProbeSample {
                    machine_id: m.clone(),
                    seq: seq(i),
                    t_ns: t(i),
                    u: rng.f(),
                    v: rng.f(),
                    w: rng.f(),
                    tip_id: 1,
                    ..Default::default()
                })
                .collect(),
            // Later fields (e.g. the v1.1 stream tag) keep their defaults.
            ..Default::default()
        }
        .encode_to_vec(),
        Stream::Temperature => TemperatureBatch {
            samples: (0..n)
                .map(|i| TemperatureSample {
                    machine_id: m.clone(),
                    seq: seq(i),
                    t_ns: t(i),
                    sensor: "air".into(),
                    celsius: 20.0 + rng.f(),
                })
                .collect(),
            // Later fields (e.g. the v1.1 stream tag) keep their defaults.
            ..Default::default()
        }
        .encode_to_vec(),
        Stream::Distance => DistanceBatch {
            samples: (0..n)
                .map(|i| DistanceSample {
                    machine_id: m.clone(),
                    seq: seq(i),
                    t_ns: t(i),
                    probe_id: (i % 3) as u32,
                    distance_mm: 0.01 * rng.f(),
                    spacing_mm: [0.0, 40.0, 80.0][i % 3],
                })
                .collect(),
            stream: StreamKind::Distance as i32,
        }
        .encode_to_vec(),
        Stream::Stage => StageBatch {
            samples: (0..n)
                .map(|i| StageSample {
                    machine_id: m.clone(),
                    seq: seq(i),
                    t_ns: t(i),
                    commanded_mm: 0.002 * i as f64,
                    sensor_mm: 0.002 * i as f64 + 1e-5 * rng.f(),
                    probe_id: 2,
                })
                .collect(),
            stream: StreamKind::Stage as i32,
        }
        .encode_to_vec(),
        // Packed (v1.4), as the service and the offline tools write them.
        Stream::Points => scancorr_proto::points::pack(
            &(0..n)
                .map(|i| CorrectedPoint {
                    machine_id: m.clone(),
                    seq: seq(i),
                    t_ns: t(i),
                    surface: Some(Vec3 {
                        x: rng.f(),
                        y: rng.f(),
                        z: rng.f(),
                    }),
                    estimator_valid: true,
                    ..Default::default()
                })
                .collect::<Vec<_>>(),
        )
        .encode_to_vec(),
        Stream::Alarms => EstimatorAlarm {
            machine_id: m,
            seq: seq0,
            t_ns: t0,
            raised: true,
            axis: Axis::X as i32,
            ..Default::default()
        }
        .encode_to_vec(),
    }
}

/// What a test wrote, to compare with what it reads.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Written {
    pub topic: String,
    pub stream: Stream,
    pub machine: String,
    pub log_time: u64,
    pub publish_time: u64,
    pub data: Vec<u8>,
    pub samples: u64,
}

impl Written {
    pub fn matches(&self, m: &scancorr_bag::BagMessage) -> bool {
        *m.topic == self.topic
            && m.stream == self.stream
            && *m.machine == self.machine
            && m.log_time == self.log_time
            && m.publish_time == self.publish_time
            && m.data == self.data
    }
}

pub fn run_metadata() -> BTreeMap<String, String> {
    [
        ("program", "ring_scan"),
        ("seed", "42"),
        ("machine_id", "m1"),
    ]
    .into_iter()
    .map(|(k, v)| (k.to_string(), v.to_string()))
    .collect()
}

pub fn ring() -> Artifact {
    let mut a = Artifact::new(ArtifactKind::Ring);
    a.diameter_mm = Some(50.0);
    a.certificate_mm = Some(50.00031);
    a.center_x_mm = Some(100.0);
    a.center_y_mm = Some(200.0);
    a.center_z_mm = Some(-50.0);
    a.extra.insert("serial".into(), "R-17".into());
    a
}

/// Writes interleaved streams of two machines; returns what was written in log-time order.
pub fn write_sample_bag(path: &std::path::Path, header: BagHeader, rounds: usize) -> Vec<Written> {
    let mut rng = Rng(0x9e3779b97f4a7c15);
    let mut w = BagWriter::create(path, header).unwrap();
    w.write_metadata(RUN_METADATA, &run_metadata()).unwrap();
    w.write_artifact(&ring()).unwrap();
    let mut out = Vec::new();
    let mut log = 1_000_000_000u64;
    for r in 0..rounds {
        for (machine, stream, n) in [
            ("m1", Stream::Command, 10),
            ("m1", Stream::Scale, 100),
            ("m1", Stream::Probe, 100),
            ("m1", Stream::Temperature, 3),
            ("m2", Stream::Scale, 50),
        ] {
            let t0 = 5_000_000_000 + (r * 100) as i64 * 1_000_000;
            let data = batch(stream, machine, (r * n) as u64, t0, n, &mut rng);
            log += 1_000;
            w.write(stream, machine, "cmm", log, t0 as u64, &data)
                .unwrap();
            out.push(Written {
                topic: stream.key("cmm", machine),
                stream,
                machine: machine.into(),
                log_time: log,
                publish_time: t0 as u64,
                data,
                samples: n as u64,
            });
        }
        // Typed writes: corrected points and (sometimes) an alarm.
        let pts = CorrectedPointBatch {
            points: (0..20)
                .map(|i| CorrectedPoint {
                    machine_id: "m1".into(),
                    seq: (r * 20 + i) as u64,
                    t_ns: 7_000 + i as i64,
                    ..Default::default()
                })
                .collect(),
            columns: vec![],
        };
        log += 1_000;
        w.write_msg("m1", "cmm", log, &pts).unwrap();
        out.push(Written {
            topic: "cmm/m1/corrected/points".into(),
            stream: Stream::Points,
            machine: "m1".into(),
            log_time: log,
            publish_time: 7_000,
            data: pts.encode_to_vec(),
            samples: 20,
        });
        if r % 10 == 3 {
            let alarm = EstimatorAlarm {
                machine_id: "m1".into(),
                seq: r as u64,
                t_ns: 123,
                raised: true,
                ..Default::default()
            };
            log += 1_000;
            w.write_msg("m1", "cmm", log, &alarm).unwrap();
            out.push(Written {
                topic: "cmm/m1/alarms/estimator".into(),
                stream: Stream::Alarms,
                machine: "m1".into(),
                log_time: log,
                publish_time: 123,
                data: alarm.encode_to_vec(),
                samples: 1,
            });
        }
    }
    w.finish().unwrap();
    out
}

pub fn read_all(bag: &BagReader) -> Vec<BagMessage> {
    bag.messages().unwrap().collect::<Result<Vec<_>>>().unwrap()
}
