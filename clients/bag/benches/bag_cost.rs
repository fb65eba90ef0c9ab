//! What bags cost: the checksum, writing, reading, reading and decoding, in one process.
//!
//!     cargo bench -p scancorr-bag --bench bag_cost
//!
//! 100 000 messages of 100-sample scale batches (one machine) written to a bag, read back
//! (every checksum verified), then read and decoded; and the CRC-32 MCAP uses, over 64 MiB.
//! Prints the median (min–max) of five rounds of each.

// The bag tests' batches and file names, and the crate's own CRC (not part of its API).
#[path = "../tests/common/mod.rs"]
mod common;
// Built here as the crate builds it (its test-only helpers and tests unused).
#[allow(dead_code, unused_imports)]
#[path = "../src/crc.rs"]
mod crc;

use common::{batch, read_all, tmp, Rng};
use scancorr_bag::{BagHeader, BagReader, BagWriter, Stream};
use std::hint::black_box;
use std::time::Instant;

const ROUNDS: usize = 5;
const MESSAGES: usize = 100_000;
const SAMPLES_PER_MESSAGE: usize = 100;

/// Median, min and max of `ROUNDS` rates, each `items` over the seconds one call of `f` took.
fn rates(items: f64, mut f: impl FnMut()) -> (f64, f64, f64) {
    let mut r: Vec<f64> = (0..ROUNDS)
        .map(|_| {
            let t = Instant::now();
            f();
            items / t.elapsed().as_secs_f64()
        })
        .collect();
    r.sort_by(|a, b| a.total_cmp(b));
    (r[ROUNDS / 2], r[0], r[ROUNDS - 1])
}

fn line(what: &str, unit: &str, (median, min, max): (f64, f64, f64)) {
    println!("{what:<28} {median:>8.2} {unit}  ({min:.2}–{max:.2})");
}

fn main() {
    let data: Vec<u8> = (0..64u32 << 20)
        .map(|i| (i.wrapping_mul(2_654_435_761) >> 13) as u8)
        .collect();
    let crc = rates(data.len() as f64 / 1e9, || {
        let mut c = crc::Crc32::new();
        c.update(black_box(&data));
        black_box(c.finish());
    });

    let path = tmp("bag_cost");
    let mut rng = Rng(3);
    let msgs: Vec<Vec<u8>> = (0..200)
        .map(|i| {
            batch(
                Stream::Scale,
                "m1",
                i * SAMPLES_PER_MESSAGE as u64,
                i as i64,
                SAMPLES_PER_MESSAGE,
                &mut rng,
            )
        })
        .collect();
    let samples = (MESSAGES * SAMPLES_PER_MESSAGE) as f64 / 1e6;
    let write = rates(samples, || {
        let mut w = BagWriter::create(&path, BagHeader::default()).expect("create the bag");
        for i in 0..MESSAGES {
            let m = &msgs[i % msgs.len()];
            w.write(Stream::Scale, "m1", "cmm", i as u64, i as u64, m)
                .expect("write a message");
        }
        w.finish().expect("finish the bag");
    });
    let raw_mb = (MESSAGES * msgs[0].len()) as f64 / 1e6;
    let bag_mb = std::fs::metadata(&path).expect("the bag").len() as f64 / 1e6;
    let read = rates(samples, || {
        let bag = BagReader::open(&path).expect("open the bag");
        assert_eq!(read_all(&bag).len(), MESSAGES, "every message read back");
    });
    let decode = rates(samples, || {
        let bag = BagReader::open(&path).expect("open the bag");
        let n: usize = bag
            .messages()
            .expect("the messages")
            .map(|m| {
                m.expect("a message")
                    .decode()
                    .expect("a batch")
                    .sample_count()
            })
            .sum();
        assert_eq!(n, MESSAGES * SAMPLES_PER_MESSAGE, "every sample decoded");
    });
    let _ = std::fs::remove_file(&path);

    println!(
        "bag of {MESSAGES} scale batches of {SAMPLES_PER_MESSAGE} samples: {raw_mb:.1} MB of batches, \
         {bag_mb:.1} MB on disk; median (min–max) of {ROUNDS} rounds"
    );
    line("crc-32 (64 MiB)", "GB/s", crc);
    line("write", "M samples/s", write);
    line("read (checksums verified)", "M samples/s", read);
    line("read + decode", "M samples/s", decode);
}
