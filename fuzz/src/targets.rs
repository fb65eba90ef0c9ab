// The fuzz targets' bodies, one function per target: bytes in, must not panic, hang or abort.
//
// Shared by the cargo-fuzz targets (`fuzz/fuzz_targets/*.rs`, thin wrappers) and by the
// regression test `tests/tests/fuzz_regressions.rs`, which includes this file with
// `#[path]` and runs every file of `fuzz/regressions/<target>/` through the same function.
// So it may only use std, scancorr-core, scancorr-bag and scancorr-proto, and no `crate::`
// paths.

// Wire messages gain fields (v1.1 added the stream tag): samples are built with
// `..Default::default()` even where every field is named today.
#![allow(clippy::needless_update)]

use std::sync::{Arc, OnceLock};

use scancorr_core::calib::{Calibration, Model};
use scancorr_core::expr::Expr;
use scancorr_core::sample::{Sample, StreamId};
use scancorr_core::{wire, Corrector, Output};
use scancorr_proto::v1;

/// The names of the targets, as in `fuzz/Cargo.toml` and `fuzz/regressions/`.
pub const TARGETS: [&str; 4] = ["wire_decode", "calibration", "expr", "bag_reader"];

/// The function of a target by name.
pub fn target(name: &str) -> Option<fn(&[u8])> {
    Some(match name {
        "wire_decode" => wire_decode,
        "calibration" => calibration,
        "expr" => expr,
        "bag_reader" => bag_reader,
        _ => return None,
    })
}

fn example_model() -> Arc<Model> {
    static MODEL: OnceLock<Arc<Model>> = OnceLock::new();
    MODEL
        .get_or_init(|| {
            Arc::new(
                Calibration::example("m1")
                    .build()
                    .expect("the example calibration builds"),
            )
        })
        .clone()
}

/// Pushes samples through a corrector and flushes it, keeping the output small; returns the
/// number of points out.
fn correct(corrector: &mut Corrector, samples: impl IntoIterator<Item = Sample>) -> usize {
    let mut out = Output::default();
    let mut points = 0;
    for s in samples {
        corrector.push(s, &mut out);
        if out.points.len() + out.alarms.len() > 1024 {
            points += out.points.len();
            out.clear();
        }
    }
    corrector.flush(&mut out);
    points + out.points.len()
}

/// `wire_decode`: the protobuf decode path of the four raw streams, then the corrector.
///
/// The input is decoded whole as each of the four streams' batches; it is also read as
/// frames `[stream byte % 4][length u16 LE][payload]` so one input can interleave the streams.
/// Every sample naming the first machine seen is pushed through a corrector of
/// `Calibration::example("m1")`, which is then flushed.
pub fn wire_decode(data: &[u8]) {
    wire_decode_points(data);
}

/// [`wire_decode`], returning the number of corrected points (for checking the seeds).
pub fn wire_decode_points(data: &[u8]) -> usize {
    let mut machine: Option<String> = None;
    let mut samples = Vec::new();
    let mut take = |stream: StreamId, bytes: &[u8]| {
        if let Ok(d) = wire::decode(stream, bytes) {
            for (m, s) in d.samples {
                if *machine.get_or_insert_with(|| m.clone()) == m {
                    samples.push(s);
                }
            }
        }
    };
    for stream in StreamId::ALL {
        take(stream, data);
    }
    let mut rest = data;
    while rest.len() >= 3 {
        let stream = StreamId::ALL[usize::from(rest[0] % 4)];
        let len = usize::from(u16::from_le_bytes([rest[1], rest[2]]));
        let body = &rest[3..];
        let n = len.min(body.len());
        take(stream, &body[..n]);
        rest = &body[n..];
    }
    let mut corrector = Corrector::with_model(example_model());
    correct(&mut corrector, samples)
}

/// A short scan on a circle for any calibration: commands, scales, probe deflections and
/// every temperature sensor the calibration reads, 200 sample periods (starting once the
/// first temperatures are past the join's delay).
fn scan(corrector: &Corrector, tip_id: u32, cal: &Calibration) -> Vec<Sample> {
    let period_ns = (cal.sample_period_s * 1e9).round().clamp(1.0, 1e9) as i64;
    let delay_ns = (cal.join.temperature_delay_s * 1e9).clamp(0.0, 1e12) as i64;
    let t0 = delay_ns + period_ns;
    let sensors: Vec<String> = corrector.sensor_names().to_vec();
    let mut out = Vec::new();
    for i in 0..200u64 {
        let t_ns = t0 + i as i64 * period_ns;
        let a = i as f64 * 0.05;
        let (x, y, z) = (100.0 + 10.0 * a.cos(), 200.0 + 10.0 * a.sin(), 50.0);
        out.push(wire::command(&v1::CommandSample {
            machine_id: "m1".into(),
            seq: i,
            t_ns,
            x,
            y,
            z,
            arc_cx: 100.0,
            arc_cy: 200.0,
            arc_cz: 50.0,
            arc_radius: 10.0,
            ..Default::default()
        }));
        out.push(wire::scale(&v1::ScaleSample {
            machine_id: "m1".into(),
            seq: i,
            t_ns,
            x: x - 0.001,
            y,
            z,
            ..Default::default()
        }));
        out.push(wire::probe(&v1::ProbeSample {
            machine_id: "m1".into(),
            seq: i,
            t_ns,
            u: 0.1 * a.cos(),
            v: 0.1 * a.sin(),
            w: 0.0,
            tip_id,
            ..Default::default()
        }));
        if i % 50 == 0 {
            for (k, sensor) in sensors.iter().enumerate() {
                out.push(wire::temperature(&v1::TemperatureSample {
                    machine_id: "m1".into(),
                    seq: i * 100 + k as u64,
                    t_ns: t_ns - t0,
                    sensor: sensor.clone(),
                    celsius: 20.5,
                    ..Default::default()
                }));
            }
        }
    }
    out
}

/// `calibration`: a calibration document as the service and `scancorr calib check` take it
/// (JSON → parse → build), then a corrector of the model on a short scan.
pub fn calibration(data: &[u8]) {
    calibration_points(data);
}

/// [`calibration`], returning the number of corrected points (for checking the seeds).
pub fn calibration_points(data: &[u8]) -> usize {
    let Ok(text) = std::str::from_utf8(data) else {
        return 0;
    };
    let Ok(cal) = Calibration::from_json(text) else {
        return 0;
    };
    let _ = cal.to_json();
    let Ok(model) = cal.build() else {
        return 0;
    };
    let tip_id = cal.geometry.tips.first().map_or(1, |t| t.id);
    let mut corrector = Corrector::with_model(Arc::new(model));
    let samples = scan(&corrector, tip_id, &cal);
    correct(&mut corrector, samples)
}

/// `expr`: a custom effect's expression, compiled and evaluated at a few points.
pub fn expr(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let Ok(e) = Expr::parse(text) else {
        return;
    };
    const VALUES: [f64; 8] = [0.0, 1.0, -2.5, 0.5, 1e300, -1e-300, f64::NAN, f64::INFINITY];
    for shift in 0..3 {
        let vars: Vec<f64> = (0..e.vars.len())
            .map(|i| VALUES[(i + shift) % VALUES.len()])
            .collect();
        let _ = e.eval(&vars);
    }
}

fn bag_path() -> std::path::PathBuf {
    // One file per process and thread (the regression test runs targets on several threads).
    let thread = format!("{:?}", std::thread::current().id());
    let thread: String = thread.chars().filter(char::is_ascii_digit).collect();
    std::env::temp_dir().join(format!(
        "scancorr-fuzz-bag-{}-{thread}.mcap",
        std::process::id()
    ))
}

/// `bag_reader`: a bag file opened by `BagReader::open` and read to its end (every message
/// decoded), as `scancorr correct`, the lab and replay read them.
pub fn bag_reader(data: &[u8]) {
    let path = bag_path();
    if std::fs::write(&path, data).is_err() {
        return;
    }
    if let Ok(bag) = scancorr_bag::BagReader::open(&path) {
        let _ = bag.artifact();
        if let Ok(messages) = bag.messages() {
            // Read to the end: the iterator must end by itself after an error.
            for m in messages.flatten() {
                let _ = m.decode();
                let _ = m.decode_checked();
            }
        }
        // The v1.2 measurement reader, for every machine the bag names.
        for machine in bag.machines() {
            let _ = scancorr_bag::measure::read_separation(&bag, machine);
        }
    }
    let _ = std::fs::remove_file(&path);
}
