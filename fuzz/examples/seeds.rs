//! Writes the seed corpora `fuzz/seeds/<target>/` (small valid inputs the fuzzers start from)
//! and the hand-made regression inputs of `fuzz/regressions/` (the stack overflows of the
//! expression parser, issue finding 2). Deterministic; run it after a wire or format change:
//!
//!     cd fuzz && cargo run --example seeds
//!
//! Kept out of the fuzz targets (an example, not a `[[bin]]`) so the targets depend only on the
//! stable entry points.
#![allow(clippy::needless_update)] // wire messages gain fields: `..Default::default()`

use std::collections::BTreeMap;
use std::path::Path;

use scancorr_bag::{Artifact, ArtifactKind, BagHeader, BagWriter, Compression};
use scancorr_core::effects::*;
use scancorr_core::sample::Axis;
use scancorr_core::Calibration;
use scancorr_proto::v1;
use scancorr_proto::Message;

struct Batches {
    command: v1::CommandBatch,
    scale: v1::ScaleBatch,
    probe: v1::ProbeBatch,
    temperature: v1::TemperatureBatch,
}

/// `n` samples of machine m1 at 1 kHz from `t0_ms` on, scanning a 10 mm circle.
fn batches(t0_ms: u64, n: u64) -> Batches {
    let mut b = Batches {
        command: Default::default(),
        scale: Default::default(),
        probe: Default::default(),
        temperature: Default::default(),
    };
    for i in t0_ms..t0_ms + n {
        let t_ns = i as i64 * 1_000_000;
        let a = i as f64 * 0.05;
        let (x, y) = (100.0 + 10.0 * a.cos(), 200.0 + 10.0 * a.sin());
        b.command.samples.push(v1::CommandSample {
            machine_id: "m1".into(),
            seq: i,
            t_ns,
            x,
            y,
            z: 50.0,
            arc_cx: 100.0,
            arc_cy: 200.0,
            arc_cz: 50.0,
            arc_radius: 10.0,
            segment_id: 1,
            ..Default::default()
        });
        b.scale.samples.push(v1::ScaleSample {
            machine_id: "m1".into(),
            seq: i,
            t_ns,
            x: x - 0.002,
            y: y + 0.001,
            z: 50.0,
            ..Default::default()
        });
        b.probe.samples.push(v1::ProbeSample {
            machine_id: "m1".into(),
            seq: i,
            t_ns,
            u: 0.1 * a.cos(),
            v: 0.1 * a.sin(),
            w: 0.0,
            tip_id: 1,
            ..Default::default()
        });
        if i % 10 == 0 {
            b.temperature.samples.push(v1::TemperatureSample {
                machine_id: "m1".into(),
                seq: i / 10,
                t_ns,
                sensor: "stylus".into(),
                celsius: 20.4,
                ..Default::default()
            });
        }
    }
    b
}

fn frame(out: &mut Vec<u8>, stream: u8, payload: &[u8]) {
    let len = u16::try_from(payload.len()).expect("a seed frame fits in 64 KiB");
    out.push(stream);
    out.extend_from_slice(&len.to_le_bytes());
    out.extend_from_slice(payload);
}

/// A calibration with every effect of the library (small parameters) and custom terms.
fn all_effects() -> Calibration {
    let mut c = Calibration::example("m1");
    let mut ad = accel_deflection::Config::zeros(1, false);
    ad.p[0][0][0] = 2e-6;
    c.effects.push(EffectConfig::AccelDeflection(ad));
    c.effects
        .push(EffectConfig::ServoPhase(servo_phase::Config::zeros(1)));
    c.effects
        .push(EffectConfig::ServoGain(servo_gain::Config::zeros(
            1,
            vec![1, 2],
        )));
    c.effects
        .push(EffectConfig::StylusThermal(stylus_thermal::Config::zeros(
            false,
        )));
    c.effects
        .push(EffectConfig::ScaleThermal(scale_thermal::Config::zeros()));
    c.effects
        .push(EffectConfig::ProbeForce(probe_force::Config::zeros()));
    c.effects.push(EffectConfig::GuideStraightness(
        guide_straightness::Config::zeros(Axis::X, 0.0, 1000.0, 5, false),
    ));
    c.effects.push(EffectConfig::Custom(custom::Config {
        id: "x_cyclic".into(),
        dynamic: true,
        terms: vec![
            custom::Term {
                axis: Axis::X,
                expr: "sin(2*pi*x/4)".into(),
            },
            custom::Term {
                axis: Axis::Y,
                expr: "sign(vy) * (T_air - 20) + max(f, r) ^ 2".into(),
            },
        ],
        coefficients: vec![2e-4, -1e-4],
    }));
    c
}

fn hostile_calibration(expr: String) -> String {
    let mut c = Calibration::example("m1");
    c.effects.push(EffectConfig::Custom(custom::Config {
        id: "hostile".into(),
        dynamic: false,
        terms: vec![custom::Term {
            axis: Axis::X,
            expr,
        }],
        coefficients: vec![0.0],
    }));
    c.to_json()
}

fn bag(path: &Path, compression: Compression, streams: usize, artifact: bool) -> Vec<u8> {
    let header = BagHeader {
        compression,
        chunk_size: 4096,
        ..BagHeader::default()
    };
    let mut w = BagWriter::create(path, header).expect("create the seed bag");
    if artifact {
        w.write_artifact(&Artifact::new(ArtifactKind::Ring))
            .expect("artifact");
    }
    for k in 0..3 {
        let b = batches(k * 5, 5);
        let log = 1_000_000_000 + k * 5_000_000;
        w.write_msg("m1", "cmm", log, &b.command).expect("write");
        if streams > 1 {
            w.write_msg("m1", "cmm", log, &b.scale).expect("write");
        }
        if streams > 2 {
            w.write_msg("m1", "cmm", log, &b.probe).expect("write");
            w.write_msg("m1", "cmm", log, &b.temperature)
                .expect("write");
        }
    }
    w.finish().expect("finish the seed bag");
    std::fs::read(path).expect("read the seed bag")
}

fn main() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut files: Vec<(String, Vec<u8>)> = vec![];
    let mut put =
        |dir: &str, name: &str, data: Vec<u8>| files.push((format!("{dir}/{name}"), data));

    // wire_decode: one batch of each stream, and all four as frames.
    let b = batches(0, 12);
    put(
        "seeds/wire_decode",
        "command.bin",
        b.command.encode_to_vec(),
    );
    put("seeds/wire_decode", "scale.bin", b.scale.encode_to_vec());
    put("seeds/wire_decode", "probe.bin", b.probe.encode_to_vec());
    put(
        "seeds/wire_decode",
        "temperature.bin",
        b.temperature.encode_to_vec(),
    );
    let mut framed = vec![];
    for k in 0..4 {
        let b = batches(k * 25, 25);
        frame(&mut framed, 3, &b.temperature.encode_to_vec());
        frame(&mut framed, 0, &b.command.encode_to_vec());
        frame(&mut framed, 2, &b.probe.encode_to_vec());
        frame(&mut framed, 1, &b.scale.encode_to_vec());
    }
    put("seeds/wire_decode", "framed.bin", framed);

    // calibration: the example and one with every effect.
    put(
        "seeds/calibration",
        "example.json",
        Calibration::example("m1").to_json().into_bytes(),
    );
    let all = all_effects();
    all.build()
        .expect("the all-effects seed calibration builds");
    put(
        "seeds/calibration",
        "all_effects.json",
        all.to_json().into_bytes(),
    );

    // expr: the grammar's corners.
    for (i, e) in [
        "sin(2*pi*x/4)",
        "sign(vx) * (T_air - 20)",
        "2 ^ 3 ^ -2 - -1.5e-3 * max(ax, min(ay, az))",
        "atan2(y, x) + sqrt(abs(du*du + dv*dv)) / (1 + exp(-t))",
        "floor(ex) + ceil(ey) + ln(1 + speed) + log10(1 + acc) - pow(defl, 0.5)",
        "((x)) * +(-(y)) / (tan(a1) + acos(cos(a2)) + asin(0.5) + atan(e))",
    ]
    .iter()
    .enumerate()
    {
        put("seeds/expr", &format!("{i}.txt"), e.as_bytes().to_vec());
    }

    let tmp = std::env::temp_dir().join(format!("scancorr-seed-{}.mcap", std::process::id()));
    // bag_reader: small bags (each holds the schemas' descriptor set, ~6 KB a copy), one
    // uncompressed, one zstd with an artifact, one cut short (no summary: the reader scans).
    let one = bag(&tmp, Compression::None, 1, false);
    put(
        "seeds/bag_reader",
        "cut_short.mcap",
        one[..one.len() * 3 / 5].to_vec(),
    );
    put("seeds/bag_reader", "one_channel.mcap", one);
    put(
        "seeds/bag_reader",
        "two_channels_zstd.mcap",
        bag(&tmp, Compression::Zstd, 2, true),
    );
    let _ = std::fs::remove_file(&tmp);

    // Regressions found by hand: the parser's recursion overflowed the stack (SIGABRT).
    let minus = "-".repeat(100_000) + "x";
    put(
        "regressions/calibration",
        "stack-overflow-100000-unary-minus.json",
        hostile_calibration(minus.clone()).into_bytes(),
    );
    put(
        "regressions/expr",
        "stack-overflow-100000-unary-minus.txt",
        minus.into_bytes(),
    );
    put(
        "regressions/expr",
        "stack-overflow-10000-power-chain.txt",
        ("2^".repeat(10_000) + "2").into_bytes(),
    );

    let mut sizes = BTreeMap::new();
    for (name, data) in files {
        let path = root.join(&name);
        std::fs::create_dir_all(path.parent().expect("a parent")).expect("mkdir");
        std::fs::write(&path, &data).expect("write");
        let top = name.split('/').next().unwrap_or("").to_string();
        *sizes.entry(top).or_insert(0usize) += data.len();
        println!("{:>8}  {name}", data.len());
    }
    for (dir, n) in sizes {
        println!("{n:>8}  total in {dir}/");
    }
}
