//! `lab discover`: the lab's loop, unattended, from any starting calibration to the noise floor.
//!
//! 1. Refit the nominal model (the axes' time constants) from command versus scales, then
//!    every effect the calibration already has (`lab fit`).
//! 2. Diagnose ([`super::analysis::diagnose`]): every addition, swap of variant and drop,
//!    each candidate model refitted as a whole and scored on scans it was not fitted on.
//! 3. Make the best significant move exactly as `lab add` / `lab remove` would
//!    ([`super::analysis::apply`]), correct the bags again with the new version and measure.
//! 4. Repeat until no move is significant (or a model would come back that the loop already
//!    had, or the step limit).
//!
//! Each step is a calibration version (parent, note, before/after figures), handed to the
//! caller as it is made, so a user can stop, inspect and go on by hand.

use super::analysis::{self, Confounded, Move, Structure};
use super::dataset::{self, BagData, BuildOptions};
use super::nominal::{fit_nominal, AxisFit};
use super::version;
use super::LabError;
use crate::calib::Calibration;
use crate::effects::EffectConfig;
use serde::Serialize;

/// Options of the loop.
#[derive(Debug, Clone)]
pub struct Options {
    /// How the bags become a dataset.
    pub build: BuildOptions,
    /// Most moves (additions, swaps, drops) before stopping.
    pub max_steps: usize,
    /// Stamp of the versions written (`created`; the core has no clock).
    pub created: String,
}

/// One step of the loop.
#[derive(Debug, Clone, Serialize)]
pub struct Step {
    /// 0 for the refit of the starting model, then 1, 2, …
    pub index: usize,
    /// `fit` (the refit of the start), `add`, `swap` or `drop`.
    pub action: String,
    /// The effect added or swapped in (name with variant), or dropped.
    pub effect: String,
    /// The model effect replaced or dropped.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub replaces: Option<String>,
    /// The version written.
    pub version: u64,
    /// Residual RMS on the fit scans after the step, µm.
    pub rms_um: f64,
    /// Cross-validated RMS after (scans predicted from the others), µm.
    pub cv_rms_um: f64,
    /// Held-out RMS before and after, µm (measured by correcting again).
    pub heldout_rms_before_um: f64,
    /// After.
    pub heldout_rms_um: f64,
    /// Confounded with the effect added, as the diagnosis found.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub confounded_with: Vec<String>,
    /// The axis refits of step 0.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub nominal: Vec<AxisFit>,
    /// The calibration written at this step.
    #[serde(skip)]
    pub calibration: Calibration,
}

/// Where the loop ended.
#[derive(Debug, Clone, Serialize)]
pub struct Final {
    /// Held-out RMS, µm.
    pub heldout_rms_um: f64,
    /// Residual RMS on the fit scans, µm.
    pub rms_um: f64,
    /// Cross-validated RMS, µm.
    pub cv_rms_um: f64,
    /// Noise floor, µm.
    pub noise_floor_um: f64,
    /// The final model's effects (ids).
    pub effects: Vec<String>,
    /// The final model's effects (kinds).
    pub kinds: Vec<String>,
    /// The final version.
    pub version: u64,
    /// The final model's parameters with their standard uncertainties (every effect refitted
    /// on the final dataset; a parameter the campaign cannot determine has none).
    pub params: Vec<super::analysis::EffectParams>,
}

/// The loop's outcome.
#[derive(Debug, Clone, Serialize)]
pub struct Discovery {
    /// Held-out RMS of the start as given, µm.
    pub start_heldout_rms_um: f64,
    /// Residual RMS of the start as given, µm.
    pub start_rms_um: f64,
    /// The steps.
    pub steps: Vec<Step>,
    /// Pairs the campaign could not separate when one of them was added, with the measurement
    /// that would.
    pub confounded: Vec<Confounded>,
    /// Structure the library does not explain, left at the end.
    pub unexplained: Vec<Structure>,
    /// Parameters the data cannot determine in the final model.
    pub unidentifiable: Vec<String>,
    /// Why the loop stopped.
    pub stopped: String,
    /// Where it ended.
    pub r#final: Final,
    /// Candidates the data could not test, and why (last diagnosis).
    pub skipped: Vec<String>,
}

/// A model's structure, for recognising one the loop already had.
fn signature(effects: &[EffectConfig]) -> Vec<String> {
    let mut v: Vec<String> = effects
        .iter()
        .map(|e| format!("{}|{}", e.kind(), e.param_names().join(",")))
        .collect();
    v.sort();
    v
}

/// Runs the loop. `on_step` sees every step as soon as its version exists (to write it and
/// show progress); `on_progress` gets a line of what the loop is doing.
pub fn discover(
    bags: &[BagData],
    start: &Calibration,
    o: &Options,
    on_step: &mut dyn FnMut(&Step) -> Result<(), LabError>,
    on_progress: &mut dyn FnMut(&str),
) -> Result<Discovery, LabError> {
    let um = |x: f64| format!("{x:.3}");
    // Step 0: the nominal model and the effects the start has.
    on_progress("correcting the bags with the starting calibration");
    let ds0 = dataset::build(bags, start, &o.build)?;
    let p0 = analysis::prepare(&ds0)?;
    on_progress("refitting the nominal model (axis time constants) and the start's effects");
    let raw: Vec<&dyn dataset::Samples> = bags
        .iter()
        .filter(|b| !b.validation)
        .map(|b| &*b.samples)
        .collect();
    let (nominal, axes) = match fit_nominal(&raw, start) {
        Ok(v) => v,
        Err(e) => {
            on_progress(&format!("nominal model kept: {e}"));
            (start.clone(), vec![])
        }
    };
    let mut cal = nominal;
    if !cal.effects.is_empty() {
        let ds = dataset::build(bags, &cal, &o.build)?;
        let prep = analysis::prepare(&ds)?;
        let fit = analysis::fit_effects(&ds, &prep, &cal.effects)?;
        cal.effects = fit.configs;
    }
    let refit = cal;
    let mut cal = version::next(start, refit.effects.clone(), &o.created);
    cal.nominal = refit.nominal.clone();
    let mut ds = dataset::build(bags, &cal, &o.build)?;
    let mut prep = analysis::prepare(&ds)?;
    version::describe(
        &mut cal,
        "lab discover step 0 (refit of the start)",
        ds.noise_floor_um,
        &p0,
        &prep,
    );
    let mut steps = vec![];
    let s0 = Step {
        index: 0,
        action: "fit".into(),
        effect: "nominal model".into(),
        replaces: None,
        version: cal.version,
        rms_um: prep.rms_fit_um,
        cv_rms_um: prep.rms_fit_um,
        heldout_rms_before_um: p0.rms_held_um,
        heldout_rms_um: prep.rms_held_um,
        confounded_with: vec![],
        nominal: axes,
        calibration: cal.clone(),
    };
    on_step(&s0)?;
    steps.push(s0);
    let mut seen = vec![signature(&cal.effects)];
    let mut confounded: Vec<Confounded> = vec![];
    let stopped;
    let last_dg;
    loop {
        on_progress(&format!(
            "step {}: diagnosing v{} ({} effects, held-out {} µm, noise floor {} µm)",
            steps.len(),
            cal.version,
            cal.effects.len(),
            um(prep.rms_held_um),
            um(ds.noise_floor_um)
        ));
        let dg = analysis::diagnose(&ds)?;
        if steps.len() > o.max_steps {
            stopped = format!("the step limit ({}) was reached", o.max_steps);
            last_dg = dg;
            break;
        }
        // The best significant move that does not bring back a model the loop had.
        let moves = analysis::moves(&ds, &cal.effects);
        let pick = dg
            .candidates
            .iter()
            .filter(|c| c.significant)
            .find_map(|c| {
                let cand = moves.iter().find(|m| {
                    m.effect == c.effect && m.action == c.action && m.replaces == c.replaces
                })?;
                let mut next: Vec<EffectConfig> = cal
                    .effects
                    .iter()
                    .filter(|e| Some(e.id()) != cand.replaces)
                    .cloned()
                    .collect();
                next.extend(cand.config.clone());
                (!seen.contains(&signature(&next))).then(|| cand.clone())
            });
        let Some(cand) = pick else {
            stopped = if dg.candidates.iter().any(|c| c.significant) {
                "every significant move leads back to a model already tried".into()
            } else {
                "no candidate is significant".into()
            };
            last_dg = dg;
            break;
        };
        on_progress(&format!(
            "step {}: {} {}{}",
            steps.len(),
            match cand.action {
                Move::Add => "adding",
                Move::Swap => "swapping in",
                Move::Drop => "dropping",
            },
            cand.effect,
            cand.replaces
                .as_ref()
                .filter(|_| cand.action == Move::Swap)
                .map(|r| format!(" for {r}"))
                .unwrap_or_default()
        ));
        let conf: Vec<Confounded> = dg
            .confounded
            .iter()
            .filter(|c| c.effects[0] == cand.effect)
            .cloned()
            .collect();
        let applied = analysis::apply(&ds, vec![cand.clone()], false)?;
        let before = prep.clone();
        let mut next = version::next(&cal, applied.effects, &o.created);
        let ds_next = dataset::build(bags, &next, &o.build)?;
        let prep_next = analysis::prepare(&ds_next)?;
        let action = serde_json::to_value(&cand.action)
            .ok()
            .and_then(|v| v.as_str().map(str::to_string))
            .unwrap_or_default();
        let what = format!(
            "lab discover step {}: {action} {}{}",
            steps.len(),
            cand.effect,
            cand.replaces
                .as_ref()
                .filter(|_| cand.action == Move::Swap)
                .map(|r| format!(" (replaces {r})"))
                .unwrap_or_default()
        );
        version::describe(
            &mut next,
            &what,
            ds_next.noise_floor_um,
            &before,
            &prep_next,
        );
        let step = Step {
            index: steps.len(),
            action,
            effect: cand.effect.clone(),
            replaces: cand.replaces.clone().filter(|_| cand.action == Move::Swap),
            version: next.version,
            rms_um: prep_next.rms_fit_um,
            cv_rms_um: applied.outcome.cv_rms_after_um,
            heldout_rms_before_um: before.rms_held_um,
            heldout_rms_um: prep_next.rms_held_um,
            confounded_with: conf.iter().map(|c| c.effects[1].clone()).collect(),
            nominal: vec![],
            calibration: next.clone(),
        };
        on_step(&step)?;
        steps.push(step);
        for c in conf {
            if !confounded.iter().any(|k| k.effects == c.effects) {
                confounded.push(c);
            }
        }
        seen.push(signature(&next.effects));
        cal = next;
        ds = ds_next;
        prep = prep_next;
    }
    let fin = analysis::fit_effects(&ds, &prep, &cal.effects)?;
    let fin_params = fin.by_effect();
    Ok(Discovery {
        start_heldout_rms_um: p0.rms_held_um,
        start_rms_um: p0.rms_fit_um,
        steps,
        confounded,
        unexplained: last_dg.unexplained.clone(),
        unidentifiable: fin.unidentifiable,
        stopped,
        r#final: Final {
            heldout_rms_um: prep.rms_held_um,
            rms_um: prep.rms_fit_um,
            cv_rms_um: last_dg.cv_rms_um,
            noise_floor_um: ds.noise_floor_um,
            effects: cal.effects.iter().map(|e| e.id()).collect(),
            kinds: cal.effects.iter().map(|e| e.kind().to_string()).collect(),
            version: cal.version,
            params: fin_params,
        },
        skipped: last_dg.skipped,
    })
}
