//! Benchmarks that print their figures (never timed tests).

use crate::shared::synth;
use anyhow::{bail, Context, Result};
use scancorr_core::calib::Model;
use scancorr_core::{Calibration, Corrector, Output, Sample, Stats};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

/// A hash of everything one pass of the pure core over `samples` with `cal` gives: every
/// point, alarm and context (each value printed in full, so equal hashes mean equal output
/// bit for bit) and the counts.
fn output_hash(cal: &Calibration, samples: &[Sample]) -> Result<(u64, usize)> {
    use std::hash::{Hash, Hasher};
    let mut corr = Corrector::with_model(Arc::new(cal.build()?));
    corr.record_context(true);
    let mut out = Output::default();
    let mut h = std::collections::hash_map::DefaultHasher::new();
    let mut points = 0;
    let mut digest = |out: &mut Output| {
        points += out.points.len();
        for p in &out.points {
            format!("{p:?}").hash(&mut h);
        }
        for a in &out.alarms {
            format!("{a:?}").hash(&mut h);
        }
        for c in &out.contexts {
            format!("{c:?}").hash(&mut h);
        }
        out.clear();
    };
    for s in samples {
        corr.push(s.clone(), &mut out);
        digest(&mut out);
    }
    corr.flush(&mut out);
    digest(&mut out);
    format!("{:?}", corr.stats()).hash(&mut h);
    Ok((h.finish(), points))
}

/// `bench core --hash`: the output's hash with the calibration timed (and the campaign's).
fn print_hashes(
    label: &str,
    cal: &Calibration,
    campaign: bool,
    samples: &[Sample],
    json: bool,
) -> Result<()> {
    let mut rows = vec![(label.to_string(), output_hash(cal, samples)?)];
    if campaign {
        rows.push((
            "campaign effects".to_string(),
            output_hash(&campaign_calibration()?, samples)?,
        ));
    }
    if json {
        let v: Vec<_> = rows
            .iter()
            .map(|(l, (h, n))| {
                serde_json::json!({"calibration": l, "points": n, "hash": format!("{h:016x}")})
            })
            .collect();
        outln!("{}", serde_json::json!({ "bench": "core", "hashes": v }))?;
    } else {
        for (l, (h, n)) in &rows {
            outln!("{l}: {n} points, output hash {h:016x}")?;
        }
    }
    Ok(())
}

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

/// One pass of the pure core over `samples` with `model`: seconds taken, points produced
/// and the corrector's counts.
fn time_core(model: &Arc<Model>, samples: &[Sample]) -> (f64, usize, Stats) {
    let mut corr = Corrector::with_model(model.clone());
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
    (t0.elapsed().as_secs_f64(), total, corr.stats().clone())
}

/// The scale samples of a scan: the points it offers.
fn offered(samples: &[Sample]) -> usize {
    samples
        .iter()
        .filter(|s| matches!(s, Sample::Scale(_)))
        .count()
}

/// Refuses a pass in which most of the `offered` scale samples became no point: it would
/// time the drops.
fn ensure_corrected(points: usize, offered: usize, stats: &Stats) -> Result<()> {
    if 2 * points < offered {
        let drops: Vec<String> = stats
            .dropped_by_name()
            .into_iter()
            .map(|(name, n)| format!("{name} {n}"))
            .collect();
        bail!(
            "the ring scan gave {points} points for {offered} scale samples, so the benchmark would time the drops (dropped: {})",
            if drops.is_empty() { "none".to_string() } else { drops.join(", ") }
        );
    }
    Ok(())
}

fn run_core(cal: &Calibration, samples: &[Sample], repeat: usize) -> Result<CoreFigures> {
    let model = Arc::new(cal.build()?);
    let offered = offered(samples);
    let mut rates = vec![];
    let mut produced = 0;
    for _ in 0..repeat.max(1) {
        let (dt, points, stats) = time_core(&model, samples);
        ensure_corrected(points, offered, &stats)?;
        rates.push(samples.len() as f64 / dt);
        produced = points;
    }
    rates.sort_by(|a, b| a.total_cmp(b));
    Ok(CoreFigures {
        effects: cal.effects.len(),
        points: produced,
        rates,
    })
}

/// Median, least and greatest of some figures (at least one).
#[derive(Debug, Clone, Copy, PartialEq)]
struct Spread {
    median: f64,
    min: f64,
    max: f64,
}

impl Spread {
    fn of(v: &[f64]) -> Spread {
        let mut s = v.to_vec();
        s.sort_by(|a, b| a.total_cmp(b));
        Spread {
            median: s[s.len() / 2],
            min: s[0],
            max: s[s.len() - 1],
        }
    }
    /// Whether the rounds disagree on the sign (zero lies in the range).
    fn within_noise(&self) -> bool {
        self.min <= 0.0 && self.max >= 0.0
    }
    fn json(&self) -> serde_json::Value {
        serde_json::json!({"median": self.median, "min": self.min, "max": self.max})
    }
    fn text(&self) -> String {
        format!(
            "{} ({} to {})",
            rounded(self.median),
            rounded(self.min),
            rounded(self.max)
        )
    }
}

/// `v` to the nearest whole number, for print (never "-0").
fn rounded(v: f64) -> String {
    format!("{:.0}", v.round() + 0.0)
}

/// What each effect of a calibration adds to the core's time per point.
///
/// The calibration is timed without any effect and without each effect in turn, and each of
/// those timings sits between two timings of the whole calibration: the variant is measured
/// as a ratio to the mean of its two neighbours, so that a host that speeds up or slows down
/// during the run (a shared host does, by half or more) changes the ratio much less than the times. The
/// ratios are turned back into ns per point at the median time of the whole calibration. An
/// effect's cost is the whole calibration's time less the time without it. Every round times
/// every variant once, starting one variant later than the round before.
struct EffectCosts {
    rounds: usize,
    /// ns per point with every effect (the timings between the variants), and with none.
    every: Spread,
    none: Spread,
    /// Per effect: id, kind, its cost in ns per point.
    effects: Vec<(String, &'static str, Spread)>,
    /// What the effects cost together beyond their own (their list, its sum, the checks of
    /// each correction), ns per point: what the medians of the effects' costs leave of the
    /// medians' difference with every effect and with none. (Per round, a difference of so
    /// many figures would carry the noise of them all.)
    shared: f64,
}

fn effect_costs(cal: &Calibration, samples: &[Sample], rounds: usize) -> Result<EffectCosts> {
    let offered = offered(samples);
    effect_costs_timed(cal, rounds, |model| {
        let (dt, points, stats) = time_core(model, samples);
        ensure_corrected(points, offered, &stats)?;
        Ok(dt * 1e9 / points as f64)
    })
}

/// [`effect_costs`] with `ns_per_point(model)` the core's time per point with `model`.
fn effect_costs_timed(
    cal: &Calibration,
    rounds: usize,
    mut ns_per_point: impl FnMut(&Arc<Model>) -> Result<f64>,
) -> Result<EffectCosts> {
    let rounds = rounds.max(1);
    // Variant 0 is no effect; variant 1 + k is without effect k.
    let mut variants = vec![(
        "no effect".to_string(),
        Calibration {
            effects: vec![],
            ..cal.clone()
        },
    )];
    for (k, e) in cal.effects.iter().enumerate() {
        let mut c = cal.clone();
        c.effects.remove(k);
        variants.push((format!("without effect `{}`", e.id()), c));
    }
    let build = |name: &str, c: &Calibration| {
        c.build()
            .map(Arc::new)
            .with_context(|| format!("the calibration with {name}"))
    };
    let whole = build("every effect", cal)?;
    let models = variants
        .iter()
        .map(|(name, c)| build(name, c))
        .collect::<Result<Vec<_>>>()?;
    let mut time = |model: &Arc<Model>, name: &str| {
        ns_per_point(model).with_context(|| format!("the calibration with {name}"))
    };
    let (mut every, mut ratio) = (vec![], vec![Vec::with_capacity(rounds); models.len()]);
    let mut progress = crate::shared::output::Progress::new();
    for r in 0..rounds {
        let mut before = time(&whole, "every effect")?;
        every.push(before);
        for i in 0..models.len() {
            progress.tick(|| {
                format!(
                    "each effect's cost: round {} of {rounds}, variant {} of {}",
                    r + 1,
                    i + 1,
                    models.len()
                )
            });
            let v = (i + r) % models.len();
            let t = time(&models[v], &variants[v].0)?;
            let after = time(&whole, "every effect")?;
            every.push(after);
            ratio[v].push(t / (0.5 * (before + after)));
            before = after;
        }
    }
    progress.finish();
    let every = Spread::of(&every);
    let at = |q: f64| every.median * q;
    let none = Spread::of(&ratio[0].iter().map(|&q| at(q)).collect::<Vec<_>>());
    let effects: Vec<(String, &'static str, Spread)> = cal
        .effects
        .iter()
        .enumerate()
        .map(|(k, e)| {
            let cost: Vec<f64> = ratio[1 + k].iter().map(|&q| at(1.0 - q)).collect();
            (e.id(), e.kind(), Spread::of(&cost))
        })
        .collect();
    let shared = every.median - none.median - effects.iter().map(|(_, _, c)| c.median).sum::<f64>();
    Ok(EffectCosts {
        rounds,
        every,
        none,
        effects,
        shared,
    })
}

impl EffectCosts {
    fn json(&self) -> serde_json::Value {
        serde_json::json!({
            "rounds": self.rounds,
            "every_effect_ns_per_point": self.every.json(),
            "no_effect_ns_per_point": self.none.json(),
            "shared_ns_per_point": self.shared,
            "effects": self.effects.iter().map(|(id, kind, c)| serde_json::json!({
                "id": id,
                "kind": kind,
                "ns_per_point": c.json(),
                "within_noise": c.within_noise(),
            })).collect::<Vec<_>>(),
        })
    }

    fn print(&self) -> Result<()> {
        if self.effects.is_empty() {
            outln!(
                "  no effect in this calibration: nothing to cost (the core takes {} ns per point)",
                self.every.text()
            )?;
            return Ok(());
        }
        outln!(
            "  what each effect costs, ns per point (every effect less all but it, each timed between two timings of every effect; median (min to max) of {} rounds):",
            self.rounds
        )?;
        let mut order: Vec<&(String, &str, Spread)> = self.effects.iter().collect();
        order.sort_by(|a, b| b.2.median.total_cmp(&a.2.median));
        let width = order
            .iter()
            .map(|(id, kind, _)| id.len() + kind.len() + 3)
            .max()
            .unwrap_or(0);
        for (id, kind, c) in order {
            let name = if id == kind {
                id.clone()
            } else {
                format!("{id} ({kind})")
            };
            let noise = if c.within_noise() {
                "  within noise"
            } else {
                ""
            };
            outln!("    {name:<width$}  {}{noise}", c.text())?;
        }
        outln!(
            "    {:<width$}  {}",
            "shared by the effects",
            rounded(self.shared)
        )?;
        outln!(
            "  every effect {} ns per point, no effect {} (the join, estimator, judgement and point)",
            self.every.text(),
            self.none.text()
        )?;
        Ok(())
    }
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

/// Target of `bench core` (issue 49; 10 M of issue 17 before it), samples per second.
const CORE_TARGET_SAMPLES_PER_S: f64 = 20.0e6;

/// Target of `bench correct` (issue 17; 1 M before it), samples per second.
const CORRECT_TARGET_SAMPLES_PER_S: f64 = 3.0e6;

/// What `scancorr bench core` measures and prints.
pub struct CoreOptions {
    /// Scale samples of the ring scan.
    pub points: usize,
    /// Repetitions (and rounds of `per_effect`).
    pub repeat: usize,
    /// A calibration document to time instead of the every-effect and campaign ones.
    pub calib: Option<PathBuf>,
    /// Also what each effect costs.
    pub per_effect: bool,
    /// A hash of the output instead of timings.
    pub hash: bool,
    pub json: bool,
}

/// `scancorr bench core`: single-thread throughput of the pure core on a ring scan, with
/// every effect of the library and with the campaign's effects (`bench correct`'s), or with
/// a calibration of the user's (on a ring placed where that machine can scan it).
pub fn core(o: &CoreOptions) -> Result<()> {
    let (label, cal, setup) = match &o.calib {
        Some(path) => {
            let cal = crate::shared::calib::load_calibration(path)?;
            let setup = synth::RingSetup::for_calibration(&cal)?;
            (path.display().to_string(), cal, setup)
        }
        None => (
            "every effect".to_string(),
            synth::all_effects_calibration("bench"),
            synth::RingSetup::default(),
        ),
    };
    let samples = synth::ring_scan_with(o.points, &setup);
    let n = samples.len();
    if o.hash {
        return print_hashes(&label, &cal, o.calib.is_none(), &samples, o.json);
    }
    let main = run_core(&cal, &samples, o.repeat).with_context(|| label.clone())?;
    let campaign = match o.calib {
        None => Some(run_core(&campaign_calibration()?, &samples, o.repeat)?),
        Some(_) => None,
    };
    let costs = if o.per_effect {
        Some(effect_costs(&cal, &samples, o.repeat).with_context(|| label.clone())?)
    } else {
        None
    };
    if o.json {
        let mut v = serde_json::json!({
            "bench": "core",
            "calibration": label,
            "ring": {
                "centre_mm": [setup.centre.x, setup.centre.y, setup.centre.z],
                "tip_id": setup.tip_id,
                "sensors": setup.sensors,
            },
            "samples": n,
            "points": main.points,
            "effects": main.effects,
            "repeat": main.rates.len(),
            "samples_per_s": main.median(),
            "samples_per_s_best": main.best(),
            "points_per_s": main.points_per_s(n),
            "ns_per_point": main.ns_per_point(n),
            "target_samples_per_s": CORE_TARGET_SAMPLES_PER_S,
        });
        if let Some(campaign) = &campaign {
            v["all_effects"] = main.json(n);
            v["campaign_effects"] = campaign.json(n);
        }
        if let Some(c) = &costs {
            v["per_effect"] = c.json();
        }
        outln!("{v}")?;
        return Ok(());
    }
    outln!(
        "core: {n} samples of a ring scan, {} runs each, one thread (target ≥ {:.0e} samples/s)",
        main.rates.len(),
        CORE_TARGET_SAMPLES_PER_S
    )?;
    let c = setup.centre;
    outln!(
        "  ring of 25 mm at ({:.1}, {:.1}, {:.1}) mm, tip {}, sensors {}",
        c.x,
        c.y,
        c.z,
        setup.tip_id,
        if setup.sensors.is_empty() {
            "none".to_string()
        } else {
            setup.sensors.join(", ")
        }
    )?;
    let main_name = match o.calib {
        Some(_) => format!("calibration {label}"),
        None => label.clone(),
    };
    let mut sets = vec![(main_name, &main)];
    if let Some(c) = &campaign {
        sets.push(("campaign's effects (bench correct)".to_string(), c));
    }
    for (name, f) in sets {
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
    if let Some(c) = &costs {
        c.print()?;
    }
    Ok(())
}

/// `scancorr bench correct`: the offline corrector end to end on a campaign bag.
pub fn correct(repeat: usize, json: bool) -> Result<()> {
    let dir = crate::shared::output::private_dir("scancorr-bench")?;
    let bag = dir.join("campaign.mcap");
    let out = dir.join("corrected.mcap");
    let options = scancorr_sim::Options {
        program: "campaign".into(),
        ..Default::default()
    };
    eprintln!("simulating the campaign into {} …", bag.display());
    crate::shared::simulate::run(crate::shared::simulate::SimArgs {
        options,
        out: bag.clone(),
        truth: None,
        calib_out: Some(dir.join("start.json")),
        datasheet_out: None,
        catalogue_out: None,
        batch: 100,
        prefix: scancorr_proto::DEFAULT_PREFIX.into(),
        json: false,
    })?;
    let cal = crate::shared::calib::load_calibration(&dir.join("start.json"))?;
    let in_bytes = std::fs::metadata(&bag)?.len();
    let mut rates = vec![];
    let mut last = None;
    for _ in 0..repeat.max(1) {
        let (s, _) = crate::shared::bags::correct(&bag, &cal, Some(&out))?;
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

#[cfg(test)]
mod tests {
    use super::*;
    use scancorr_core::effects::EffectConfig;

    /// The every-effect calibration of a machine whose travel is far from the default ring,
    /// whose tip is 7, and whose stylus sensor is named `probe_head`.
    fn elsewhere() -> Calibration {
        let mut c = synth::all_effects_calibration("m1");
        c.limits.travel_mm = [[2000.0, 3000.0], [-4000.0, -3000.0], [500.0, 900.0]];
        c.geometry.tips[0].id = 7;
        for e in &mut c.effects {
            if let EffectConfig::StylusThermal(s) = e {
                s.sensor = "probe_head".into();
            }
        }
        c
    }

    #[test]
    fn a_ring_placed_for_a_calibration_is_corrected_where_the_default_one_is_not() {
        let cal = elsewhere();
        let model = Arc::new(cal.build().unwrap());
        let setup = synth::RingSetup::for_calibration(&cal).unwrap();
        assert_eq!(setup.tip_id, 7);
        assert!(
            setup.sensors.contains(&"probe_head".to_string()),
            "{setup:?}"
        );
        let scan = synth::ring_scan_with(2000, &setup);
        let (_, points, stats) = time_core(&model, &scan);
        ensure_corrected(points, offered(&scan), &stats).unwrap();
        // All but the first 200 ms, which wait for the first temperatures to be old enough.
        assert!(points >= 1750, "{points} points of 2000: {stats:?}");
        // The benchmarks' own ring lies outside this machine's travel: nearly everything is
        // dropped, and the benchmark says so rather than timing the drops.
        let default = synth::ring_scan(2000);
        let (_, points, stats) = time_core(&model, &default);
        let e = ensure_corrected(points, offered(&default), &stats).unwrap_err();
        assert!(e.to_string().contains("implausible"), "{e}");
        // The default setup is the benchmarks' ring, unchanged.
        assert_eq!(
            synth::ring_scan_with(500, &Default::default()),
            synth::ring_scan(500)
        );
    }

    #[test]
    fn spreads_and_their_noise() {
        let s = Spread::of(&[3.0, -1.0, 2.0, 10.0, 0.5]);
        assert_eq!((s.median, s.min, s.max), (2.0, -1.0, 10.0));
        assert!(s.within_noise());
        assert!(!Spread::of(&[1.0, 4.0]).within_noise());
        assert!(!Spread::of(&[-3.0, -1.0]).within_noise());
        assert_eq!(Spread::of(&[-0.3, 2.4, -12.5]).text(), "0 (-13 to 2)");
    }

    #[test]
    fn costs_are_recovered_from_a_host_that_halves_its_speed_midway() {
        // A core whose time per point is known: 200 ns for the pipeline, 30 shared by the
        // effects when there are any, and 10·(k + 1) for effect k; on a host twice as slow
        // from the middle of the run on.
        let cal = synth::all_effects_calibration("bench");
        let ids: Vec<String> = cal.effects.iter().map(|e| e.id()).collect();
        let own = |id: &str| 10.0 * (1 + ids.iter().position(|i| i == id).unwrap()) as f64;
        let rounds = 5;
        let calls = rounds * (2 * (ids.len() + 1) + 1);
        let mut call = 0;
        let c = effect_costs_timed(&cal, rounds, |m| {
            let slow = if call < calls / 2 { 1.0 } else { 2.0 };
            call += 1;
            let effects: f64 = m.effects.iter().map(|e| own(&e.id)).sum();
            let shared = if m.effects.is_empty() { 0.0 } else { 30.0 };
            Ok(slow * (200.0 + shared + effects))
        })
        .unwrap();
        assert_eq!(call, calls);
        let every = 200.0 + 30.0 + ids.iter().map(|i| own(i)).sum::<f64>();
        // In ns at the median time with every effect (here the slow host's): each figure is
        // the true one scaled by that median's slowness.
        let scale = c.every.median / every;
        assert!(scale == 1.0 || scale == 2.0, "{scale}");
        let close = |got: f64, want: f64| (got - want * scale).abs() < 1e-9 * every;
        for (id, _, s) in &c.effects {
            assert!(close(s.median, own(id)), "{id}: {s:?}");
        }
        assert!(close(c.none.median, 200.0), "{:?}", c.none);
        assert!(close(c.shared, 30.0), "{}", c.shared);
        // The one triple that straddles the change is off; the median is not.
        assert!(c.effects.iter().any(|(_, _, s)| s.min != s.max) || c.none.min != c.none.max);
    }

    #[test]
    fn every_effect_gets_a_cost_and_none_is_nan() {
        let cal = synth::all_effects_calibration("bench");
        let scan = synth::ring_scan(1500);
        let c = effect_costs(&cal, &scan, 2).unwrap();
        assert_eq!(c.rounds, 2);
        let ids: Vec<String> = c.effects.iter().map(|(id, _, _)| id.clone()).collect();
        let want: Vec<String> = cal.effects.iter().map(|e| e.id()).collect();
        assert_eq!(ids, want);
        for s in std::iter::once(&c.every)
            .chain([&c.none])
            .chain(c.effects.iter().map(|(_, _, s)| s))
        {
            assert!(s.min.is_finite() && s.max.is_finite(), "{s:?}");
            assert!(s.min <= s.median && s.median <= s.max, "{s:?}");
        }
        // Times, not differences: positive.
        assert!(c.every.min > 0.0 && c.none.min > 0.0);
    }
}
