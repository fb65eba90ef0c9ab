//! What the wire costs per sample and per point, in one process (no bag, no bus):
//!
//!     cargo run --release -p scancorr-tests --example wire_cost
//!
//! Decoding raw batches of a simulated ring (100 samples a batch) in both layouts — one
//! message per sample (v1.0–v1.2) and packed columns (v1.3) — with `wire::decode_machine`, the
//! call the service and `scancorr correct` make; encoding them with `wire::Batcher`; and
//! encoding corrected points with `wire::encode_points` (packed blocks, v1.4) against prost
//! building a message per point (the layout before v1.4). Prints the best of five rounds in ns per sample (per point) and the bytes.

use scancorr_core::sample::{CorrectedPoint, Sample, StreamId, Vec3};
use scancorr_core::wire::{self, Batcher, Layout};
use scancorr_proto::Message;
use std::hint::black_box;
use std::time::Instant;

const BATCH: usize = 100;
const ROUNDS: usize = 5;

/// The best of [`ROUNDS`] timings of `f`, in ns per item.
fn best(items: usize, mut f: impl FnMut()) -> f64 {
    (0..ROUNDS)
        .map(|_| {
            let t = Instant::now();
            f();
            t.elapsed().as_nanos() as f64 / items as f64
        })
        .fold(f64::INFINITY, f64::min)
}

fn encode(samples: &[Sample], layout: Layout) -> Vec<(StreamId, Vec<u8>)> {
    let mut b = Batcher::new("m1", BATCH).with_layout(layout);
    let mut out = vec![];
    for s in samples {
        if let Some(stream) = b.push(s) {
            out.push((stream, b.take(stream).unwrap().0));
        }
    }
    for stream in StreamId::ALL {
        out.extend(b.take(stream).map(|t| (stream, t.0)));
    }
    out
}

fn main() {
    let options = scancorr_sim::Options {
        program: "ring".into(),
        ..Default::default()
    };
    let mut samples = vec![];
    scancorr_sim::run(&options, |s| samples.push(s)).expect("the ring simulates");
    let n = samples.len();
    println!("{n} samples of a simulated ring, batches of {BATCH}");
    for layout in [Layout::PerSample, Layout::Packed] {
        let batches = encode(&samples, layout);
        let bytes: usize = batches.iter().map(|b| b.1.len()).sum();
        let mut out = Vec::with_capacity(BATCH);
        let decode = best(n, || {
            for (stream, b) in &batches {
                out.clear();
                wire::decode_machine(*stream, b, "m1", &mut out).unwrap();
                black_box(&out);
            }
        });
        let encode = best(n, || {
            black_box(encode(&samples, layout));
        });
        println!(
            "{layout:?}: decode {decode:.1} ns/sample, encode {encode:.1} ns/sample, {:.1} bytes/sample",
            bytes as f64 / n as f64
        );
    }

    // Six corrections per point: the library's first six effect kinds.
    let ids: Vec<String> = scancorr_core::effects::KINDS[..6]
        .iter()
        .map(|k| k.to_string())
        .collect();
    let points: Vec<CorrectedPoint> = (0..BATCH as u64)
        .map(|k| {
            let f = k as f64 * 0.37;
            CorrectedPoint {
                seq: 1_000_000 + k,
                t_ns: 5_000_000_000 + k as i64 * 1_000_000,
                sample_seq: 3_000_000 + k,
                surface: Vec3::new(100.0 + f.cos(), 200.0 + f.sin(), -50.5),
                tip_center: Vec3::new(101.0 + f.cos(), 201.0 + f.sin(), -50.5),
                normal: Vec3::new(f.cos(), f.sin(), 0.0),
                corrections: (0..ids.len())
                    .map(|i| Vec3::new(1e-4 * f, -2e-5 * i as f64, 3e-6))
                    .collect(),
                calibration_version: 3,
                estimator_valid: true,
                segment_id: 4,
                tip_id: 1,
            }
        })
        .collect();
    let reps = 2000;
    let mut buf = vec![];
    let direct = best(reps * BATCH, || {
        for _ in 0..reps {
            buf.clear();
            wire::encode_points(&points, "m1", &ids, &mut buf);
            black_box(&buf);
        }
    });
    // The layout before v1.4: a prost message per point, each naming the machine and effects.
    let mut per_point_bytes = 0;
    let prost = best(reps * BATCH, || {
        for _ in 0..reps {
            let batch = scancorr_proto::v1::CorrectedPointBatch {
                points: points.iter().map(|p| wire::point(p, "m1", &ids)).collect(),
                columns: vec![],
            };
            let b = batch.encode_to_vec();
            per_point_bytes = b.len();
            black_box(b);
        }
    });
    println!(
        "points ({} corrections each): wire::encode_points (packed, v1.4) {direct:.1} ns/point \
         and {:.1} bytes/point; a prost message per point (v1.3) {prost:.1} ns/point and \
         {:.1} bytes/point",
        ids.len(),
        buf.len() as f64 / BATCH as f64,
        per_point_bytes as f64 / BATCH as f64
    );
}
