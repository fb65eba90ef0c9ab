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
        outln!(
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
        )?;
    } else {
        outln!(
            "core: {n} samples ({produced} points, {} effects), {} runs, one thread",
            cal.effects.len(),
            rates.len()
        )?;
        outln!(
            "  samples/s  median {:.3e}  best {:.3e}  (target ≥ 5e6)",
            median,
            best
        )?;
        outln!(
            "  points/s   median {:.3e}  ({per_point_ns:.0} ns per point)",
            median * produced as f64 / n as f64
        )?;
    }
    Ok(())
}

/// `scancorr bench correct`: the offline corrector end to end on a campaign bag.
pub fn correct(repeat: usize, json: bool) -> Result<()> {
    let dir = std::env::temp_dir().join(format!("scancorr-bench-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let bag = dir.join("campaign.mcap");
    let out = dir.join("corrected.mcap");
    let options = scancorr_sim::Options {
        program: "campaign".into(),
        ..Default::default()
    };
    eprintln!("simulating the campaign into {} …", bag.display());
    crate::simcmd::run(crate::simcmd::SimArgs {
        options,
        out: bag.clone(),
        truth: None,
        calib_out: Some(dir.join("start.json")),
        batch: 100,
        prefix: scancorr_proto::DEFAULT_PREFIX.into(),
        json: false,
    })?;
    let cal = crate::offline::load_calibration(&dir.join("start.json"))?;
    let in_bytes = std::fs::metadata(&bag)?.len();
    let mut rates = vec![];
    let mut last = None;
    for _ in 0..repeat.max(1) {
        let (s, _) = crate::offline::correct(&bag, &cal, Some(&out))?;
        rates.push(s.samples as f64 / s.seconds);
        last = Some(s);
    }
    let s = last.expect("at least one run");
    let out_bytes = std::fs::metadata(&out)?.len();
    std::fs::remove_dir_all(&dir).ok();
    rates.sort_by(|a, b| a.total_cmp(b));
    let median = rates[rates.len() / 2];
    let best = *rates.last().unwrap();
    if json {
        outln!(
            "{}",
            serde_json::json!({
                "bench": "correct",
                "samples": s.samples,
                "points": s.points,
                "effects": cal.effects.len(),
                "input_bytes": in_bytes,
                "output_bytes": out_bytes,
                "repeat": rates.len(),
                "samples_per_s": median,
                "samples_per_s_best": best,
                "target_samples_per_s": 1.0e6,
            })
        )?;
    } else {
        outln!("correct (campaign bag {:.1} MB → {:.1} MB): {} samples → {} points, {} effects, {} runs", in_bytes as f64 / 1e6, out_bytes as f64 / 1e6, s.samples, s.points, cal.effects.len(), rates.len())?;
        outln!("  samples/s  median {median:.3e}  best {best:.3e}  (target ≥ 1e6; read, decode, correct, encode, write)")?;
    }
    Ok(())
}
