//! Benchmarks that print their figures (never timed tests).

use crate::synth;
use anyhow::Result;
use scancorr_core::{Calibration, Corrector, Output, Sample};
use std::time::Instant;

/// Throughput of one run of the pure core over `samples` with `cal`'s effects.
struct CoreFigures {
    effects: usize,
    points: usize,
    /// Samples per second, one per repetition, sorted.
    rates: Vec<f64>,
}

impl CoreFigures {
    fn median(&self) -> f64 {
        self.rates[self.rates.len() / 2]
    }
    fn best(&self) -> f64 {
        *self.rates.last().expect("at least one run")
    }
    fn points_per_s(&self, samples: usize) -> f64 {
        self.median() * self.points as f64 / samples as f64
    }
    fn ns_per_point(&self, samples: usize) -> f64 {
        1e9 / self.points_per_s(samples)
    }
    fn json(&self, samples: usize) -> serde_json::Value {
        serde_json::json!({
            "effects": self.effects,
            "points": self.points,
            "samples_per_s": self.median(),
            "samples_per_s_best": self.best(),
            "points_per_s": self.points_per_s(samples),
            "ns_per_point": self.ns_per_point(samples),
        })
    }
}

fn run_core(cal: &Calibration, samples: &[Sample], repeat: usize) -> Result<CoreFigures> {
    let mut rates = vec![];
    let mut produced = 0;
    for _ in 0..repeat.max(1) {
        let mut corr = Corrector::new(cal)?;
        let mut out = Output::default();
        let mut total = 0usize;
        let t0 = Instant::now();
        // Each sample handed over as a decoder would (its copy timed with the core).
        for s in samples {
            corr.push(s.clone(), &mut out);
            total += out.points.len();
            out.clear();
        }
        corr.flush(&mut out);
        total += out.points.len();
        let dt = t0.elapsed().as_secs_f64();
        rates.push(samples.len() as f64 / dt);
        produced = total;
    }
    anyhow::ensure!(
        produced > 0,
        "the benchmark input produced no points: the benchmark would measure nothing"
    );
    rates.sort_by(|a, b| a.total_cmp(b));
    Ok(CoreFigures {
        effects: cal.effects.len(),
        points: produced,
        rates,
    })
}

/// The starting calibration the campaign simulator writes (`bench correct`'s effect set),
/// built in memory: the simulation runs, its samples are thrown away.
fn campaign_calibration() -> Result<Calibration> {
    let options = scancorr_sim::Options {
        program: "campaign".into(),
        ..Default::default()
    };
    Ok(scancorr_sim::run(&options, |_| {})?.start_calibration)
}

/// Target of `bench core` (issue 17), samples per second.
const CORE_TARGET_SAMPLES_PER_S: f64 = 10.0e6;

/// Target of `bench correct` (issue 17; 1 M before it), samples per second.
const CORRECT_TARGET_SAMPLES_PER_S: f64 = 3.0e6;

/// `scancorr bench core`: single-thread throughput of the pure core on a ring scan, with
/// every effect of the library and with the campaign's effects (`bench correct`'s).
pub fn core(points: usize, repeat: usize, json: bool) -> Result<()> {
    let samples = synth::ring_scan(points);
    let n = samples.len();
    let all = run_core(&synth::all_effects_calibration("bench"), &samples, repeat)?;
    let campaign = run_core(&campaign_calibration()?, &samples, repeat)?;
    if json {
        outln!(
            "{}",
            serde_json::json!({
                "bench": "core",
                "samples": n,
                "points": all.points,
                "effects": all.effects,
                "repeat": all.rates.len(),
                "samples_per_s": all.median(),
                "samples_per_s_best": all.best(),
                "points_per_s": all.points_per_s(n),
                "ns_per_point": all.ns_per_point(n),
                "all_effects": all.json(n),
                "campaign_effects": campaign.json(n),
                "target_samples_per_s": CORE_TARGET_SAMPLES_PER_S,
            })
        )?;
    } else {
        outln!(
            "core: {n} samples of a ring scan, {} runs each, one thread (target ≥ {:.0e} samples/s)",
            all.rates.len(),
            CORE_TARGET_SAMPLES_PER_S
        )?;
        for (name, f) in [
            ("every effect", &all),
            ("campaign's effects (bench correct)", &campaign),
        ] {
            outln!("  {name}: {} effects, {} points", f.effects, f.points)?;
            outln!(
                "    samples/s  median {:.3e}  best {:.3e}",
                f.median(),
                f.best()
            )?;
            outln!(
                "    points/s   median {:.3e}  ({:.0} ns per point)",
                f.points_per_s(n),
                f.ns_per_point(n)
            )?;
        }
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
                "target_samples_per_s": CORRECT_TARGET_SAMPLES_PER_S,
            })
        )?;
    } else {
        outln!("correct (campaign bag {:.1} MB → {:.1} MB): {} samples → {} points, {} effects, {} runs", in_bytes as f64 / 1e6, out_bytes as f64 / 1e6, s.samples, s.points, cal.effects.len(), rates.len())?;
        outln!("  samples/s  median {median:.3e}  best {best:.3e}  (target ≥ {CORRECT_TARGET_SAMPLES_PER_S:.0e}; read, decode, correct, encode, write)")?;
    }
    Ok(())
}
