//! `scancorr bench lab-coverage`: are the lab's uncertainties honest? For each machine (seeds
//! 101, 102, … by default: seeds no test uses) the simulator measures the default campaign
//! and a held-out `ring-speeds` run at another position (550, 300, −250 mm), and the lab runs
//! in-process (`scancorr_core::lab`) along up to three paths:
//!
//! - `fit`: `lab fit` of the true effect list with every parameter at its nominal value (zero)
//!   from the nominal model (`calib nominal`, styli qualified): the right structure, nothing
//!   fitted;
//! - `add`: that fitted calibration with one library effect taken out (by the machine's seed,
//!   in the library's order: 101 hides `accel_deflection`, 102 the next, …), then `lab
//!   diagnose` and `lab add` of the ranked-first move, as a user goes by hand;
//! - `discover`: the whole loop from the nominal model.
//!
//! Every fitted parameter is then compared with the simulator's true calibration (the truth
//! only judges): matched by effect kind and parameter name (the same name, hence the same
//! parametrisation: a per-tip probe force is not compared with a machine-wide one); a term
//! the lab's variant has and the truth's variant of the same effect lacks (a cross-term of
//! the acceleration matrix, a higher power) is judged against 0, the truth's value of a term
//! it does not have; an effect whose parameters share no name with the truth's variant is
//! skipped and said. The share with |θ − θ_true| ≤ 2σ (≈ 95 % for an honest Gaussian σ; the
//! issue asks ≥ 90 %), ≤ max(3σ, 5 % of |θ_true|), and the median |θ − θ_true|/σ (0.67 when
//! σ is honest; far below, σ is uselessly wide). Parameters the lab reports as not determined
//! (no σ) are counted apart, never as covered. Effects the truth does not have at all (a
//! machine-wide rigid body, a custom effect) are judged against 0 apart (`absent_effects`):
//! where such an effect stands in for one the truth has, 0 is not its value in the lab's
//! parametrisation, so it is not mixed into the headline share. The parameters the lab says
//! are determined only jointly with others (≥ 99 % of their column follows theirs) are also
//! counted apart (`joint`), with the share the headline would have if they were not
//! determined.
//!
//! Tables (guide straightness knots) are reported apart: artifacts do not determine a guide
//! table's rigid part (a straightness table's offset and slope, a pitch table's mean are a
//! placement or a rotation of the whole volume), so each table's difference from the truth is
//! judged after its least-squares line (straightness) or mean (pitch) is taken out, against
//! each knot's σ; the truth's table is interpolated linearly at the lab's knots (the same
//! guide, the same straightness directions and pitch axis; otherwise skipped and said).

use anyhow::{bail, Context, Result};
use scancorr_core::effects::EffectConfig;
use scancorr_core::lab::analysis::{self, Move, Param};
use scancorr_core::lab::dataset::{self, BagData, BuildOptions};
use scancorr_core::Calibration;
use std::collections::BTreeMap;
use std::path::Path;
use std::time::Instant;

/// The paths the benchmark knows.
pub const PATHS: [&str; 3] = ["fit", "add", "discover"];

/// What to run.
pub struct Options {
    /// Machines (seeds `first_seed` …).
    pub machines: u64,
    /// The first machine seed.
    pub first_seed: u64,
    /// `fit`, `add`, `discover`.
    pub paths: Vec<String>,
    /// Print JSON.
    pub json: bool,
}

/// One judged parameter.
#[derive(Clone)]
struct Judged {
    machine: u64,
    effect: String,
    name: String,
    value: f64,
    sigma: f64,
    truth: f64,
    /// The truth's variant lacks the term: judged against 0.
    zero: bool,
    /// Determined only jointly with other parameters (the lab's note).
    joint: bool,
    /// σ's parts: statistical, scan-clustered, fold spread, penalty shift, model spread.
    parts: [Option<f64>; 5],
}

impl Judged {
    fn z(&self) -> f64 {
        (self.value - self.truth) / self.sigma
    }
    fn in2(&self) -> bool {
        (self.value - self.truth).abs() <= 2.0 * self.sigma
    }
    fn in3(&self) -> bool {
        (self.value - self.truth).abs() <= (3.0 * self.sigma).max(0.05 * self.truth.abs())
    }
}

/// One path's tally over the machines.
#[derive(Default)]
struct Tally {
    scalars: Vec<Judged>,
    /// Table knots (rigid part taken out of the difference).
    knots: Vec<Judged>,
    /// Parameters of effects the truth does not have, against 0.
    absent: Vec<Judged>,
    /// Parameters of matched effects the lab gave no σ.
    not_determined: usize,
    /// Skipped parameters by reason.
    skipped: BTreeMap<String, usize>,
    /// Per machine: (machine, scalars judged, within 2σ).
    per_machine: Vec<(u64, usize, usize)>,
    seconds: Vec<f64>,
    /// Notes (the effect hidden and the move made, per machine; errors).
    notes: Vec<String>,
    /// Machines on which the path failed (the error is in `notes`).
    failed: usize,
}

use super::harness::exe;

/// Runs the benchmark.
pub fn run(o: &Options) -> Result<()> {
    if o.machines == 0 {
        bail!("--machines: at least 1");
    }
    for p in &o.paths {
        if !PATHS.contains(&p.as_str()) {
            bail!("--paths: `{p}` (fit, add, discover)");
        }
    }
    if o.paths.is_empty() {
        bail!("--paths: give at least one of fit, add, discover");
    }
    let want = |p: &str| o.paths.iter().any(|q| q == p);
    let root = crate::shared::output::private_dir("scancorr-bench-lab")?;
    let mut tallies: BTreeMap<&str, Tally> = BTreeMap::new();
    let result = (|| -> Result<()> {
        for i in 0..o.machines {
            let m = o.first_seed.saturating_add(i);
            let dir = root.join(format!("m{m}"));
            std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
            let case = Case::new(&dir, m).with_context(|| format!("machine {m}"))?;
            // `add` starts from the `fit` path's calibration: run it whenever `add` is asked.
            // A lab error on one machine is a finding of the benchmark: said, not fatal.
            let mut fitted = None;
            if want("fit") || want("add") {
                let t0 = Instant::now();
                match case.fit() {
                    Ok((cal, configs, params)) => {
                        let secs = t0.elapsed().as_secs_f64();
                        if want("fit") {
                            let t = tallies.entry("fit").or_default();
                            t.seconds.push(secs);
                            judge(t, m, &configs, &params, &case.truth.effects);
                        }
                        fitted = Some(cal);
                    }
                    Err(e) => {
                        for p in ["fit", "add"].into_iter().filter(|p| want(p)) {
                            let t = tallies.entry(p).or_default();
                            t.notes.push(format!("machine {m}: lab fit failed: {e:#}"));
                            t.failed += 1;
                        }
                    }
                }
            }
            if want("add") {
                let t = tallies.entry("add").or_default();
                // By the machine's seed (101 hides the first), so a machine's case does not
                // depend on where the series starts.
                let n = scancorr_sim::LIBRARY_EFFECTS.len() as u64;
                let hide = scancorr_sim::LIBRARY_EFFECTS[(m.wrapping_add(1) % n) as usize];
                let t0 = Instant::now();
                match fitted.as_ref().map(|start| case.add(start, hide)) {
                    Some(Ok((note, configs, params))) => {
                        t.seconds.push(t0.elapsed().as_secs_f64());
                        t.notes.push(format!("machine {m}: {note}"));
                        judge(t, m, &configs, &params, &case.truth.effects);
                    }
                    Some(Err(e)) => {
                        t.notes.push(format!("machine {m}: {hide} hidden: {e:#}"));
                        t.failed += 1;
                    }
                    None => {}
                }
            }
            if want("discover") {
                let t = tallies.entry("discover").or_default();
                let t0 = Instant::now();
                match case.discover() {
                    Ok((note, configs, params)) => {
                        t.seconds.push(t0.elapsed().as_secs_f64());
                        t.notes.push(format!("machine {m}: {note}"));
                        judge(t, m, &configs, &params, &case.truth.effects);
                    }
                    Err(e) => {
                        t.notes
                            .push(format!("machine {m}: lab discover failed: {e:#}"));
                        t.failed += 1;
                    }
                }
            }
            if !o.json {
                eprintln!("machine {m}: done ({}/{})", i + 1, o.machines);
            }
            std::fs::remove_dir_all(&dir).ok();
        }
        Ok(())
    })();
    std::fs::remove_dir_all(&root).ok();
    result?;
    let mut all = serde_json::Map::new();
    for p in PATHS.iter().rev() {
        if let Some(t) = tallies.get_mut(p) {
            all.insert(p.to_string(), report(p, t, o)?);
        }
    }
    if o.json {
        outln!("{}", serde_json::to_string_pretty(&all)?)?;
    }
    Ok(())
}

/// One machine's measurements, its truth and the user's nominal start.
struct Case {
    bags: Vec<BagData>,
    nominal: Calibration,
    truth: Calibration,
    build: BuildOptions,
}

impl Case {
    /// Simulates the campaign (run seed 5) and the held-out ring-speeds run (run seed 6, at
    /// 550, 300, −250 mm) of machine `m`, and makes the nominal start from its data sheet
    /// (`calib nominal --tips-from`: the styli as qualified).
    fn new(dir: &Path, m: u64) -> Result<Case> {
        let ms = m.to_string();
        exe(
            dir,
            &[
                "sim",
                "--program",
                "campaign",
                "--machine-seed",
                &ms,
                "--seed",
                "5",
                "--out",
                "c.mcap",
                "--datasheet-out",
                "datasheet.json",
                "--calib-out",
                "sim.json",
                "--truth",
                "truth.json",
            ],
        )?;
        exe(
            dir,
            &[
                "sim",
                "--program",
                "ring-speeds",
                "--machine-seed",
                &ms,
                "--seed",
                "6",
                "--position",
                "550,300,-250",
                "--out",
                "v.mcap",
            ],
        )?;
        exe(
            dir,
            &[
                "calib",
                "nominal",
                "--datasheet",
                "datasheet.json",
                "--tips-from",
                "sim.json",
                "--out",
                "nominal.json",
            ],
        )?;
        let nominal = crate::shared::calib::load_calibration(&dir.join("nominal.json"))?;
        let t: serde_json::Value = serde_json::from_str(
            &std::fs::read_to_string(dir.join("truth.json")).context("reading truth.json")?,
        )
        .context("truth.json")?;
        let truth = Calibration::from_json(&t["true_calibration"].to_string())
            .context("truth.json: true_calibration")?;
        let bags = crate::shared::bags::load_bags(
            &[dir.join("c.mcap")],
            &[dir.join("v.mcap")],
            &nominal.machine_id,
        )?;
        let build = BuildOptions {
            stride: 4,
            holdout_by_segment: true,
            artifact: None,
            sensors: crate::shared::bags::SENSORS
                .iter()
                .map(|s| s.to_string())
                .collect(),
        };
        Ok(Case {
            bags,
            nominal,
            truth,
            build,
        })
    }

    /// `lab fit` (nominal model, then every effect) of the truth's effect list at zero
    /// parameters: the fitted calibration, and the effects' configs and parameters.
    fn fit(&self) -> Result<(Calibration, Vec<EffectConfig>, Vec<Vec<Param>>)> {
        let mut start = self.nominal.clone();
        start.effects = self
            .truth
            .effects
            .iter()
            .map(|e| e.with_params(&vec![0.0; e.params().len()]))
            .collect::<std::result::Result<_, _>>()
            .map_err(|e| anyhow::anyhow!("zeroing the true effects: {e}"))?;
        let raw: Vec<&dyn dataset::Samples> = self
            .bags
            .iter()
            .filter(|b| !b.validation)
            .map(|b| &*b.samples)
            .collect();
        let (mut new, _) = scancorr_core::lab::nominal::fit_nominal(&raw, &start)?;
        let ds = dataset::build(&self.bags, &new, &self.build)?;
        let prep = analysis::prepare(&ds)?;
        let o = analysis::fit_effects(&ds, &prep, &new.effects)?;
        new.effects = o.configs.clone();
        let cal = scancorr_core::lab::version::next(&new, o.configs.clone(), "bench");
        Ok((cal, o.configs, o.params))
    }

    /// `lab diagnose` on `start` less `hide`, then `lab add` of the ranked-first move (every
    /// effect refitted): what was done, and the model's configs and parameters.
    fn add(
        &self,
        start: &Calibration,
        hide: &str,
    ) -> Result<(String, Vec<EffectConfig>, Vec<Vec<Param>>)> {
        let mut cal = start.clone();
        cal.effects.retain(|e| e.kind() != hide);
        if cal.effects.len() == start.effects.len() {
            bail!("{hide} is not in the fitted calibration");
        }
        let ds = dataset::build(&self.bags, &cal, &self.build)?;
        let d = analysis::diagnose_deferred(&ds)?;
        let first = d
            .candidates
            .first()
            .with_context(|| format!("{hide} hidden: the diagnosis has no candidate"))?;
        let cands = if first.action == Move::Drop {
            vec![analysis::Candidate {
                action: Move::Drop,
                effect: first.effect.clone(),
                replaces: Some(first.effect.clone()),
                config: None,
            }]
        } else {
            analysis::moves_named(&ds, &first.effect)?
        };
        let a = analysis::apply(&ds, cands, false)?;
        // As `lab add` reports it: σ widened by the near-equal moves on the new model.
        let mut next = cal.clone();
        next.effects = a.effects.clone();
        let ds_after = dataset::build(&self.bags, &next, &self.build)?;
        let mut outcome = a.outcome.clone();
        analysis::widen_by_alternatives(&mut outcome, &analysis::model_spread(&ds_after)?);
        let note = format!(
            "{hide} hidden; ranked first: {:?} {}{}; made: {}",
            first.action,
            first.effect,
            if first.significant {
                ""
            } else {
                " (not significant)"
            },
            a.candidate.effect
        );
        Ok((note, outcome.configs, outcome.params))
    }

    /// `lab discover` from the nominal model: its steps, and the final model's configs and
    /// parameters.
    fn discover(&self) -> Result<(String, Vec<EffectConfig>, Vec<Vec<Param>>)> {
        let opts = scancorr_core::lab::discover::Options {
            build: self.build.clone(),
            max_steps: 20,
            created: "bench".into(),
        };
        let d = scancorr_core::lab::discover::discover(
            &self.bags,
            &self.nominal,
            &opts,
            &mut |_| Ok(()),
            &mut |_| {},
        )?;
        let last = &d.steps.last().context("discover made no step")?.calibration;
        let mut configs = vec![];
        let mut params = vec![];
        for ep in &d.r#final.params {
            if let Some(c) = last.effects.iter().find(|c| c.id() == ep.effect) {
                configs.push(c.clone());
                params.push(ep.params.clone());
            }
        }
        let note = format!(
            "{} step(s), final {} (held-out {:.3} µm, floor {:.3} µm)",
            d.steps.len().saturating_sub(1),
            d.r#final.effects.join(", "),
            d.r#final.heldout_rms_um,
            d.r#final.noise_floor_um
        );
        Ok((note, configs, params))
    }
}

/// Compares the fitted `configs` (with their `params`) of machine `m` with the truth's.
fn judge(
    t: &mut Tally,
    m: u64,
    configs: &[EffectConfig],
    params: &[Vec<Param>],
    truth: &[EffectConfig],
) {
    let (n0, k0) = (
        t.scalars.len(),
        t.scalars.iter().filter(|j| j.in2()).count(),
    );
    for (c, ps) in configs.iter().zip(params) {
        let names = c.param_names();
        let same_kind: Vec<&EffectConfig> = truth.iter().filter(|e| e.kind() == c.kind()).collect();
        if let EffectConfig::GuideStraightness(g) = c {
            judge_tables(t, m, g, ps, &same_kind);
            continue;
        }
        // The truth's variant sharing the most parameter names with the lab's.
        let overlap =
            |e: &EffectConfig| e.param_names().iter().filter(|n| names.contains(n)).count();
        let tc = same_kind
            .iter()
            .max_by_key(|e| overlap(e))
            .filter(|e| overlap(e) > 0);
        // A stylus expansion without its own bent-limb term gives the limbs the shank's α (a
        // lumped α, not the shank's alone): only the same variant is comparable.
        let tc = tc.filter(|e| c.kind() != "stylus_thermal" || e.param_names() == names);
        if tc.is_none() && !same_kind.is_empty() {
            *t.skipped
                .entry(format!(
                    "{}: another parametrisation than the truth's (no parameter name in common, or a lumped α)",
                    c.id()
                ))
                .or_default() += ps.len();
            continue;
        }
        let truth_of: BTreeMap<String, f64> = tc
            .map(|e| e.param_names().into_iter().zip(e.params()).collect())
            .unwrap_or_default();
        for p in ps {
            let Some(s) = p
                .sigma
                .filter(|s| *s > 0.0 && s.is_finite() && p.value.is_finite())
            else {
                t.not_determined += 1;
                continue;
            };
            let tv = truth_of.get(&p.name).copied();
            let j = Judged {
                machine: m,
                effect: c.id(),
                name: p.name.clone(),
                value: p.value,
                sigma: s,
                truth: tv.unwrap_or(0.0),
                zero: tv.is_none(),
                joint: p
                    .note
                    .as_deref()
                    .is_some_and(|n| n.contains("determined only jointly")),
                parts: [
                    p.sigma_stat,
                    p.sigma_scan,
                    p.fold_spread,
                    p.penalty_shift,
                    p.model_spread,
                ],
            };
            if tc.is_some() {
                t.scalars.push(j);
            } else {
                t.absent.push(j);
            }
        }
    }
    let (n1, k1) = (
        t.scalars.len(),
        t.scalars.iter().filter(|j| j.in2()).count(),
    );
    t.per_machine.push((m, n1 - n0, k1 - k0));
}

/// A guide table against the truth's table of the same guide and the same variant (the same
/// straightness directions, a pitch about the same axis): the truth interpolated linearly at
/// the lab's knots (knots outside the truth's are skipped), each table's difference with its
/// rigid part out (the least-squares line of a straightness table, the mean of a pitch table:
/// artifacts do not determine them), against each knot's σ.
fn judge_tables(
    t: &mut Tally,
    m: u64,
    g: &scancorr_core::effects::guide_straightness::Config,
    ps: &[Param],
    truth: &[&EffectConfig],
) {
    let same = truth.iter().find_map(|e| match e {
        EffectConfig::GuideStraightness(h)
            if h.axis == g.axis
                && h.straightness.keys().eq(g.straightness.keys())
                && h.pitch_rad.is_some() == g.pitch_rad.is_some()
                && (g.pitch_rad.is_none() || h.pitch_about == g.pitch_about) =>
        {
            Some(h)
        }
        _ => None,
    });
    let Some(h) = same else {
        let why = if truth.is_empty() {
            "guide_straightness: not in the truth".to_string()
        } else {
            format!(
                "{}: another guide or variant than the truth's (axis, directions, pitch axis)",
                EffectConfig::GuideStraightness(g.clone()).id()
            )
        };
        *t.skipped.entry(why).or_default() += ps.len();
        return;
    };
    let mut tables: Vec<(&[f64], &[f64])> = g
        .straightness
        .values()
        .zip(h.straightness.values())
        .map(|(a, b)| (a.as_slice(), b.as_slice()))
        .collect();
    if let (Some(a), Some(b)) = (&g.pitch_rad, &h.pitch_rad) {
        tables.push((a, b));
    }
    let n = g.knots_mm.len();
    let (lo, hi) = (
        h.knots_mm.first().copied().unwrap_or(0.0),
        h.knots_mm.last().copied().unwrap_or(0.0),
    );
    let id = EffectConfig::GuideStraightness(g.clone()).id();
    for (ti, (_, tv)) in tables.iter().enumerate() {
        let pitch = g.pitch_rad.is_some() && ti == g.straightness.len();
        let (mut x, mut d, mut idx, mut tru) = (vec![], vec![], vec![], vec![]);
        for (k, &xk) in g.knots_mm.iter().enumerate() {
            let j = ti * n + k;
            let Some(p) = ps.get(j) else { continue };
            if !(lo..=hi).contains(&xk) || h.knots_mm.len() < 2 || tv.len() != h.knots_mm.len() {
                *t.skipped
                    .entry(format!("{id}: knots outside the truth's table"))
                    .or_default() += 1;
                continue;
            }
            let tr = interp(&h.knots_mm, tv, xk);
            x.push(xk);
            d.push(p.value - tr);
            idx.push(j);
            tru.push(tr);
        }
        let d = if pitch {
            let mean = d.iter().sum::<f64>() / d.len().max(1) as f64;
            d.iter().map(|v| v - mean).collect()
        } else {
            super::harness::detrend(&x, &d)
        };
        for ((&j, dj), tr) in idx.iter().zip(d).zip(tru) {
            match ps[j].sigma {
                Some(s) if s > 0.0 && s.is_finite() && dj.is_finite() => t.knots.push(Judged {
                    machine: m,
                    effect: id.clone(),
                    name: ps[j].name.clone(),
                    value: tr + dj,
                    sigma: s,
                    truth: tr,
                    zero: false,
                    joint: false,
                    parts: [
                        ps[j].sigma_stat,
                        ps[j].sigma_scan,
                        ps[j].fold_spread,
                        ps[j].penalty_shift,
                        ps[j].model_spread,
                    ],
                }),
                _ => t.not_determined += 1,
            }
        }
    }
}

/// Linear interpolation of (xs, ys) at x (xs increasing, ≥ 2 points).
fn interp(xs: &[f64], ys: &[f64], x: f64) -> f64 {
    let j = xs.partition_point(|a| *a <= x).clamp(1, xs.len() - 1);
    let w = (x - xs[j - 1]) / (xs[j] - xs[j - 1]);
    ys[j - 1] * (1.0 - w) + ys[j] * w
}

fn median(mut v: Vec<f64>) -> Option<f64> {
    v.sort_by(f64::total_cmp);
    (!v.is_empty()).then(|| {
        let n = v.len();
        if n % 2 == 1 {
            v[n / 2]
        } else {
            0.5 * (v[n / 2 - 1] + v[n / 2])
        }
    })
}

/// The path's figures (printed unless `--json`).
fn report(path: &str, t: &mut Tally, o: &Options) -> Result<serde_json::Value> {
    let frac = |v: &[Judged], f: fn(&Judged) -> bool| {
        (!v.is_empty()).then(|| v.iter().filter(|j| f(j)).count() as f64 / v.len() as f64)
    };
    let per_machine: Vec<f64> = t
        .per_machine
        .iter()
        .filter(|(_, n, _)| *n > 0)
        .map(|(_, n, k)| *k as f64 / *n as f64)
        .collect();
    let mut worst = t.scalars.clone();
    worst.sort_by(|a, b| b.z().abs().total_cmp(&a.z().abs()));
    worst.truncate(5);
    let in2 = frac(&t.scalars, Judged::in2);
    let in3 = frac(&t.scalars, Judged::in3);
    let k2 = frac(&t.knots, Judged::in2);
    let med = median(per_machine.clone());
    // ≈ 0.67 for an honest Gaussian σ; above: σ too small, below: too large.
    let z_med = median(t.scalars.iter().map(|j| j.z().abs()).collect());
    let secs = median(t.seconds.clone());
    let zero: Vec<Judged> = t.scalars.iter().filter(|j| j.zero).cloned().collect();
    let joint: Vec<Judged> = t.scalars.iter().filter(|j| j.joint).cloned().collect();
    let not_joint: Vec<Judged> = t.scalars.iter().filter(|j| !j.joint).cloned().collect();
    let absent_in2 = frac(&t.absent, Judged::in2);
    let all: Vec<Judged> = t.scalars.iter().chain(&t.absent).cloned().collect();
    let judged_json = |j: &Judged| {
        serde_json::json!({
            "machine_seed": j.machine, "effect": j.effect, "name": j.name,
            "value": j.value, "sigma": j.sigma, "truth": j.truth, "z": j.z(),
            "against_zero": j.zero, "joint": j.joint,
            "sigma_stat": j.parts[0], "sigma_scan": j.parts[1], "fold_spread": j.parts[2],
            "penalty_shift": j.parts[3], "model_spread": j.parts[4],
        })
    };
    let v = serde_json::json!({
        "machines": o.machines,
        "first_machine_seed": o.first_seed,
        "parameters": t.scalars.len(),
        "within_2sigma": in2,
        "within_3sigma_or_5pct": in3,
        "within_2sigma_median_over_machines": med,
        "within_2sigma_per_machine": t.per_machine.iter().map(|(m, n, k)| serde_json::json!({"machine_seed": m, "parameters": n, "within_2sigma": k})).collect::<Vec<_>>(),
        "median_abs_z": z_med,
        "terms_against_zero": zero.len(),
        "terms_against_zero_within_2sigma": frac(&zero, Judged::in2),
        "joint": joint.len(),
        "joint_within_2sigma": frac(&joint, Judged::in2),
        "within_2sigma_if_joint_not_determined": frac(&not_joint, Judged::in2),
        "absent_effects": t.absent.len(),
        "absent_effects_within_2sigma": absent_in2,
        "absent_effects_median_abs_z": median(t.absent.iter().map(|j| j.z().abs()).collect()),
        "all_within_2sigma": frac(&all, Judged::in2),
        "all_within_3sigma_or_5pct": frac(&all, Judged::in3),
        "all_median_abs_z": median(all.iter().map(|j| j.z().abs()).collect()),
        "judged": t.scalars.iter().chain(&t.absent).map(judged_json).collect::<Vec<_>>(),
        "not_determined": t.not_determined,
        "machines_failed": t.failed,
        "skipped": t.skipped,
        "table_knots": t.knots.len(),
        "table_knots_within_2sigma": k2,
        "table_knots_within_3sigma_or_5pct": frac(&t.knots, Judged::in3),
        "table_knots_median_abs_z": median(t.knots.iter().map(|j| j.z().abs()).collect()),
        "table_knots_judged": t.knots.iter().map(judged_json).collect::<Vec<_>>(),
        "seconds_median": secs,
        "worst": worst.iter().map(|j| serde_json::json!({
            "machine_seed": j.machine, "effect": j.effect, "name": j.name,
            "value": j.value, "sigma": j.sigma, "truth": j.truth, "z": j.z(),
        })).collect::<Vec<_>>(),
        "notes": t.notes,
    });
    if !o.json {
        let pct = |f: Option<f64>| f.map_or("—".to_string(), |f| format!("{:.1} %", 100.0 * f));
        outln!(
            "{path}: {} parameters judged over {} machine(s) (seeds {}…{}): {} within 2σ (median over machines {}), {} within max(3σ, 5 %), median |z| {} (0.67 when σ is honest); {} not determined (no σ); {} s per machine (median)",
            t.scalars.len(),
            o.machines,
            o.first_seed,
            o.first_seed.saturating_add(o.machines - 1),
            pct(in2),
            pct(med),
            pct(in3),
            z_med.map_or("—".to_string(), |z| format!("{z:.2}")),
            t.not_determined,
            secs.map_or("—".to_string(), |s| format!("{s:.1}")),
        )?;
        outln!(
            "  of which {} terms the truth's variant lacks (against 0): {} within 2σ; {} determined only jointly with others: {} within 2σ ({} within 2σ if they were counted as not determined)",
            zero.len(),
            pct(frac(&zero, Judged::in2)),
            joint.len(),
            pct(frac(&joint, Judged::in2)),
            pct(frac(&not_joint, Judged::in2)),
        )?;
        outln!(
            "  effects the truth does not have, against 0: {} parameters, {} within 2σ, median |z| {}; everything together: {} within 2σ, {} within max(3σ, 5 %)",
            t.absent.len(),
            pct(absent_in2),
            median(t.absent.iter().map(|j| j.z().abs()).collect())
                .map_or("—".to_string(), |z| format!("{z:.2}")),
            pct(frac(&all, Judged::in2)),
            pct(frac(&all, Judged::in3)),
        )?;
        if t.failed > 0 {
            outln!("  failed on {} machine(s) (below)", t.failed)?;
        }
        outln!(
            "  guide tables (rigid line out of the difference): {} knots, {} within 2σ",
            t.knots.len(),
            pct(k2)
        )?;
        for (why, n) in &t.skipped {
            outln!("  skipped {n}: {why}")?;
        }
        if !worst.is_empty() {
            outln!("  worst:")?;
        }
        for j in &worst {
            outln!(
                "    machine {} {}: {} = {} (truth {}), z {:+.1}",
                j.machine,
                j.effect,
                j.name,
                crate::report::value_sigma(j.value, Some(j.sigma)),
                crate::report::value_sigma(j.truth, None),
                j.z()
            )?;
        }
        for n in &t.notes {
            outln!("  {n}")?;
        }
    }
    Ok(v)
}

/// The path list from `--paths` (comma-separated or repeated).
pub fn paths(v: &[String]) -> Vec<String> {
    v.iter()
        .flat_map(|s| s.split(','))
        .map(|s| s.trim().to_string())
        .filter(|s| !s.is_empty())
        .collect()
}
