//! Benchmarks that print their figures (never timed tests).

use crate::synth;
use anyhow::Result;
use scancorr_core::{Corrector, Output};
use std::time::Instant;

/// `scancorr bench core`: single-thread throughput of the pure core with every effect.
pub fn core(points: usize, repeat: usize, json: bool) -> Result<()> {
    let cal = synth::all_effects_calibration("bench");
    let samples = synth::ring_scan(points);
    let n = samples.len();
    let mut rates = vec![];
    let mut produced = 0;
    for _ in 0..repeat.max(1) {
        let input = samples.clone();
        let mut corr = Corrector::new(&cal)?;
        let mut out = Output::default();
        let mut total = 0usize;
        let t0 = Instant::now();
        for s in input {
            corr.push(s, &mut out);
            total += out.points.len();
            out.clear();
        }
        corr.flush(&mut out);
        total += out.points.len();
        let dt = t0.elapsed().as_secs_f64();
        rates.push(n as f64 / dt);
        produced = total;
    }
    anyhow::ensure!(
        produced > 0,
        "the benchmark input produced no points: the benchmark would measure nothing"
    );
    rates.sort_by(|a, b| a.total_cmp(b));
    let best = *rates.last().unwrap();
    let median = rates[rates.len() / 2];
    let per_point_ns = 1e9 / (median * produced as f64 / n as f64);
    if json {
        println!(
            "{}",
            serde_json::json!({
                "bench": "core",
                "samples": n,
                "points": produced,
                "effects": cal.effects.len(),
                "repeat": rates.len(),
                "samples_per_s": median,
                "samples_per_s_best": best,
                "points_per_s": median * produced as f64 / n as f64,
                "ns_per_point": per_point_ns,
                "target_samples_per_s": 5.0e6,
            })
        );
    } else {
        println!(
            "core: {n} samples ({produced} points, {} effects), {} runs, one thread",
            cal.effects.len(),
            rates.len()
        );
        println!(
            "  samples/s  median {:.3e}  best {:.3e}  (target ≥ 5e6)",
            median, best
        );
        println!(
            "  points/s   median {:.3e}  ({per_point_ns:.0} ns per point)",
            median * produced as f64 / n as f64
        );
    }
    Ok(())
}
