//! `lab discover`: the lab's loop, unattended, from any starting calibration to the noise floor.
//!
//! 1. Refit the nominal model (the axes' time constants) from command versus scales, then
//!    every effect the calibration already has (`lab fit`).
//! 2. Diagnose ([`super::analysis::diagnose`]): every addition, swap of variant and drop,
//!    each candidate model refitted as a whole and scored on scans it was not fitted on.
//! 3. Make the best significant move exactly as `lab add` / `lab remove` would
//!    ([`super::analysis::apply`]), correct the bags again with the new version and measure.
//!    A move that brings parameters in and leaves the measured held-out RMS worse than before
//!    is refused and the next significant one tried (a drop may leave it worse by 1 % + 0.02
//!    of the noise floor); with none taken, a drop the held-out data asks for (it gains there
//!    more than the alternate scans lose) is made.
//! 4. When no library move is taken: the structure the diagnosis found (a period, a reversal,
//!    a harmonic of the probing direction) is added as a custom effect named for what it is
//!    ([`super::beyond`]) when it passes the same significance test; then squareness alone;
//!    then, with the residual above 1.5× the floor, pairs of the best candidates fitted
//!    together and the structure left after the best two; before stopping, a guide table's
//!    linear ramp is named squareness (a squareness-only `rigid_body`).
//! 5. Repeat until nothing is significant (or a model would come back that the loop already
//!    had, or the step limit); the reason given names the largest component left unexplained.
//!
//! Each step is a calibration version (parent, note, before/after figures), handed to the
//! caller as it is made, so a user can stop, inspect and go on by hand.

use super::analysis::{self, Candidate, Confounded, Diagnosis, Move, Prepared, Structure};
use super::beyond;
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
    /// What the step found beyond the library, in words (a structure made a custom effect,
    /// squareness taken from a guide table, several effects added at once and why).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub found: Option<String>,
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
    /// Pairs whose corrections look alike (the correlation test of [`Confounded`]) but whose
    /// scores on scans they were not fitted on separate them: not confounded.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub separated: Vec<Separated>,
    /// Structure the library does not explain, left at the end.
    pub unexplained: Vec<Structure>,
    /// Moves that were significant but not taken, and why (the held-out data got worse).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub refused: Vec<String>,
    /// Parameters the data cannot determine in the final model.
    pub unidentifiable: Vec<String>,
    /// Why the loop stopped.
    pub stopped: String,
    /// Where it ended.
    pub r#final: Final,
    /// Candidates the data could not test, and why (last diagnosis).
    pub skipped: Vec<String>,
    /// The steps of the run not kept when the loop was restarted (see [`discover`]); their
    /// versions exist (each was handed to `on_step`), their parent chain leads to step 0.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub abandoned: Vec<Step>,
    /// What the restart did and which run was kept, when the loop was restarted.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub restart: Option<String>,
}

/// Two candidates whose corrections look alike, told apart by their scores.
#[derive(Debug, Clone, Serialize)]
pub struct Separated {
    /// The one taken (or the better scored) first.
    pub effects: [String; 2],
    /// Their cross-validated RMS (scans predicted from the others), µm, in that order.
    pub cv_rms_um: [f64; 2],
    /// Their held-out RMS, µm.
    pub heldout_rms_um: [f64; 2],
}

/// A pair the correlation test names confounded, judged by the candidates' scores as well: when
/// the better one removes, over the worse one, a component that passes the significance test
/// of a move (at least half the noise floor and 1 % of the sum of squares on scans neither was
/// fitted on, the held-out data not worse), the data separates them — the pair is returned as
/// [`Separated`]. `None` keeps it confounded (scores alike, or a candidate not scored).
pub fn separated_by_scores(dg: &Diagnosis, k: &Confounded) -> Option<Separated> {
    let find = |e: &str| {
        dg.candidates
            .iter()
            .find(|c| c.effect == e && c.action == Move::Add)
    };
    let (a, b) = (find(&k.effects[0])?, find(&k.effects[1])?);
    let (good, bad) = if a.cv_rms_after_um <= b.cv_rms_after_um {
        (a, b)
    } else {
        (b, a)
    };
    analysis::significant_gain(
        bad.cv_rms_after_um,
        good.cv_rms_after_um,
        bad.heldout_rms_after_um,
        good.heldout_rms_after_um,
        dg.noise_floor_um,
    )
    .then(|| Separated {
        effects: k.effects.clone(),
        cv_rms_um: [a.cv_rms_after_um, b.cv_rms_after_um],
        heldout_rms_um: [a.heldout_rms_after_um, b.heldout_rms_after_um],
    })
}

/// Drops the held-out data asks for: the model without the effect leaves held-out data (at
/// another position or run) better by a component that passes the significance test of an
/// addition (at least half the noise floor and 1 % of the sum of squares), and by more than
/// the cross-validated data loses (in quadrature, per point). Such an effect predicts the
/// campaign's own placements, not the machine elsewhere: its gain on the alternate scans was
/// the placements', and it was let in because it made the held-out data worse by less than
/// a tolerance when larger errors were left (or by a start that had it). Best held-out first; each
/// with the reason in words. Empty without held-out data.
fn refused_by_heldout(
    dg: &Diagnosis,
    held_um: f64,
    noise_um: f64,
) -> Vec<(&analysis::CandidateReport, String)> {
    if !(held_um > 0.0 && held_um.is_finite()) {
        return vec![];
    }
    let mut v: Vec<(&analysis::CandidateReport, String)> = dg
        .candidates
        .iter()
        .filter(|c| c.action == Move::Drop)
        .filter(|c| {
            let (hb, ha) = (held_um, c.heldout_rms_after_um);
            let (cb, ca) = (c.cv_rms_before_um, c.cv_rms_after_um);
            let held_gain2 = hb * hb - ha * ha;
            let cv_cost2 = (ca * ca - cb * cb).max(0.0);
            ha.is_finite()
                && ca.is_finite()
                && analysis::significant_gain(hb, ha, 0.0, 0.0, noise_um)
                && held_gain2 > cv_cost2
        })
        .map(|c| {
            let why = format!(
                "the held-out data refuses {}: without it the held-out RMS goes from {:.3} to {:.3} µm, the cross-validated from {:.3} to {:.3} µm",
                c.effect, held_um, c.heldout_rms_after_um, c.cv_rms_before_um, c.cv_rms_after_um
            );
            (c, why)
        })
        .collect();
    v.sort_by(|a, b| {
        a.0.heldout_rms_after_um
            .total_cmp(&b.0.heldout_rms_after_um)
            .then_with(|| a.0.effect.cmp(&b.0.effect))
    });
    v.truncate(2);
    v
}

/// A custom effect's name in a step: `kind:id` (`custom:cyclic_x_4p000mm`).
fn effect_name(e: &EffectConfig) -> String {
    format!("{}:{}", e.kind(), e.id())
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

/// Significant moves tried in turn per step (each is applied and measured).
const MAX_TRIED: usize = 4;
/// Above this many times the noise floor, a loop with no significant single move tries moves
/// together.
const STALL_FACTOR: f64 = 1.5;
/// Candidates combined in pairs.
const PAIR_OF: usize = 4;

/// A structure in words.
pub fn describe_structure(s: &Structure) -> String {
    match (s.kind.as_str(), s.period_mm, s.harmonic) {
        ("probe_direction", _, Some(k)) => {
            format!("the {k}θ harmonic of the probing direction (probe lobing)")
        }
        (_, Some(p), _) => format!("a period of {p:.4} mm along {}", s.axis),
        ("reversal", _, _) => format!("the sign of the {} velocity (reversal)", s.axis),
        (k, _, _) => format!("{k} along {}", s.axis),
    }
}

/// A model measured: the version, its dataset and figures.
struct Tried {
    next: Calibration,
    ds: dataset::Dataset,
    prep: Prepared,
}

/// The move a step makes.
struct Chosen {
    tried: Tried,
    action: String,
    effect: String,
    replaces: Option<String>,
    cv: f64,
    conf: Vec<Confounded>,
    found: Option<String>,
}

/// How strictly [`Ctx::trial`] holds a move to the held-out data.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Gate {
    /// Parameters brought in: the held-out RMS must not get worse.
    Earn,
    /// Parameters taken out or renamed: worse by at most 1 % + 0.02 of the noise floor.
    Keep,
}

/// What a step works from.
struct Ctx<'a> {
    bags: &'a [BagData],
    o: &'a Options,
    cal: &'a Calibration,
    prep: &'a Prepared,
    index: usize,
}

impl Ctx<'_> {
    /// The model `effects` as the next version, measured; refused (Err) when its held-out RMS
    /// is worse than the current model's. A move that brings parameters in (`Gate::Earn`: an
    /// addition, a swap, structure) must not make it worse at all: its gain on the alternate
    /// scans already passed the significance test, and a gain that does not carry to another
    /// position or run is the placements', not the machine's (let in, it stays: a later drop
    /// costs the alternate scans what it gained there). A move that takes parameters out or
    /// renames what the model has (`Gate::Keep`: a drop, squareness from a guide's ramp) may
    /// leave it worse by 1 % + 0.02 of the noise floor: the simpler model at equal figures.
    fn trial(
        &self,
        effects: Vec<EffectConfig>,
        what: &str,
        gate: Gate,
    ) -> Result<Result<Tried, String>, LabError> {
        let mut next = version::next(self.cal, effects, &self.o.created);
        let ds = dataset::build(self.bags, &next, &self.o.build)?;
        let prep = analysis::prepare(&ds)?;
        let noise = ds.noise_floor_um;
        let (b, a) = (self.prep.rms_held_um, prep.rms_held_um);
        let limit = match gate {
            Gate::Earn => b,
            Gate::Keep => 1.01 * b + 0.02 * noise,
        };
        if !a.is_finite() || (b > 0.0 && a > limit) {
            return Ok(Err(format!(
                "{what}: the held-out RMS would go from {b:.3} to {a:.3} µm"
            )));
        }
        version::describe(
            &mut next,
            &format!("lab discover step {}: {what}", self.index),
            noise,
            self.prep,
            &prep,
        );
        Ok(Ok(Tried { next, ds, prep }))
    }

    /// Adds `ce` (with `with`, configs added alongside) when it passes the significance test of
    /// a library move and the held-out data does not get worse.
    #[allow(clippy::too_many_arguments)]
    fn try_custom(
        &self,
        ds: &dataset::Dataset,
        dg: &Diagnosis,
        ce: &beyond::CustomEffect,
        with: &[(String, EffectConfig)],
        seen: &[Vec<String>],
        noise: f64,
        on_progress: &mut dyn FnMut(&str),
        refused: &mut Vec<String>,
    ) -> Result<Option<Chosen>, LabError> {
        let id = ce.config.id();
        if self.cal.effects.iter().any(|e| e.id() == id) {
            return Ok(None);
        }
        let name = effect_name(&ce.config);
        let (effects, cv) = if with.is_empty() {
            let cand = Candidate {
                action: Move::Add,
                effect: name.clone(),
                replaces: None,
                config: Some(ce.config.clone()),
            };
            let applied = match analysis::apply(ds, vec![cand], false) {
                Ok(a) => a,
                Err(e) => {
                    on_progress(&format!(
                        "step {}: {name} cannot be fitted: {e}",
                        self.index
                    ));
                    return Ok(None);
                }
            };
            if !beyond::significant(&applied.outcome, dg.cv_rms_um, self.prep.rms_held_um, noise) {
                return Ok(None);
            }
            (applied.effects, applied.outcome.cv_rms_after_um)
        } else {
            let mut all = self.cal.effects.clone();
            all.extend(with.iter().map(|w| w.1.clone()));
            all.push(ce.config.clone());
            let o = match analysis::fit_effects(ds, self.prep, &all) {
                Ok(o) => o,
                Err(_) => return Ok(None),
            };
            if !beyond::significant(&o, dg.cv_rms_um, self.prep.rms_held_um, noise) {
                return Ok(None);
            }
            (o.configs, o.cv_rms_after_um)
        };
        if seen.contains(&signature(&effects)) {
            return Ok(None);
        }
        let mut effect = name;
        for w in with.iter().rev() {
            effect = format!("{} + {effect}", w.0);
        }
        on_progress(&format!(
            "step {}: adding {effect} — {}",
            self.index, ce.what
        ));
        match self.trial(effects, &format!("add {effect} ({})", ce.what), Gate::Earn)? {
            Err(r) => {
                on_progress(&format!("step {}: not taken — {r}", self.index));
                refused.push(r);
                Ok(None)
            }
            Ok(t) => Ok(Some(Chosen {
                tried: t,
                action: "add".into(),
                effect,
                replaces: None,
                cv,
                conf: vec![],
                found: Some(ce.what.clone()),
            })),
        }
    }

    /// No single move is significant: pairs of the best candidates fitted together, then the
    /// structure left after the best candidates as a custom effect (with them and alone).
    /// Returns the move and the structure left after the best candidates.
    #[allow(clippy::too_many_arguments)]
    fn try_together(
        &self,
        ds: &dataset::Dataset,
        dg: &Diagnosis,
        moves: &[Candidate],
        seen: &[Vec<String>],
        noise: f64,
        on_progress: &mut dyn FnMut(&str),
        refused: &mut Vec<String>,
    ) -> Result<(Option<Chosen>, Vec<Structure>), LabError> {
        // The best additions (of different kinds), with their configs.
        let mut best: Vec<(String, EffectConfig)> = vec![];
        for c in dg
            .candidates
            .iter()
            .filter(|c| c.action == Move::Add && c.explained > 0.0)
        {
            let Some(m) = moves
                .iter()
                .find(|m| m.effect == c.effect && m.action == Move::Add)
            else {
                continue;
            };
            let Some(cfg) = &m.config else { continue };
            if best.iter().any(|b| b.1.kind() == cfg.kind()) {
                continue;
            }
            best.push((c.effect.clone(), cfg.clone()));
            if best.len() == PAIR_OF {
                break;
            }
        }
        on_progress(&format!(
            "step {}: no single move is significant at {:.2}× the noise floor: trying pairs of {}",
            self.index,
            self.prep.rms_held_um / noise.max(1e-9),
            best.iter()
                .map(|b| b.0.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        ));
        let mut pairs: Vec<(FitOutcomeLite, String)> = vec![];
        for i in 0..best.len() {
            for j in i + 1..best.len() {
                let mut all = self.cal.effects.clone();
                all.push(best[i].1.clone());
                all.push(best[j].1.clone());
                let Ok(o) = analysis::fit_effects(ds, self.prep, &all) else {
                    continue;
                };
                let name = format!("{} + {}", best[i].0, best[j].0);
                if beyond::significant(&o, dg.cv_rms_um, self.prep.rms_held_um, noise)
                    && !seen.contains(&signature(&o.configs))
                {
                    pairs.push((
                        FitOutcomeLite {
                            cv: o.cv_rms_after_um,
                            configs: o.configs,
                        },
                        name,
                    ));
                }
            }
        }
        pairs.sort_by(|a, b| a.0.cv.total_cmp(&b.0.cv).then(a.1.cmp(&b.1)));
        for (o, name) in pairs.into_iter().take(2) {
            on_progress(&format!("step {}: adding {name} together", self.index));
            match self.trial(o.configs, &format!("add {name} (together)"), Gate::Earn)? {
                Err(r) => {
                    on_progress(&format!("step {}: not taken — {r}", self.index));
                    refused.push(r);
                }
                Ok(t) => {
                    return Ok((
                        Some(Chosen {
                            tried: t,
                            action: "add".into(),
                            effect: name.clone(),
                            replaces: None,
                            cv: o.cv,
                            conf: vec![],
                            found: Some(format!(
                                "no single move was significant; {name} together are"
                            )),
                        }),
                        vec![],
                    ))
                }
            }
        }
        // The structure left after the best candidates.
        let with: Vec<(String, EffectConfig)> = best.iter().take(2).cloned().collect();
        let mut all = self.cal.effects.clone();
        all.extend(with.iter().map(|w| w.1.clone()));
        let Ok(o) = analysis::fit_effects(ds, self.prep, &all) else {
            return Ok((None, vec![]));
        };
        let resid: Vec<f64> = self
            .prep
            .art
            .residual
            .iter()
            .zip(&o.predicted)
            .map(|(e, d)| e + d)
            .collect();
        let found = super::structure::structure(ds, self.prep, &resid)?;
        for s in found.iter().take(2) {
            let Some(ce) = beyond::custom_effect(s) else {
                continue;
            };
            on_progress(&format!(
                "step {}: left after {}: {}",
                self.index,
                with.iter()
                    .map(|w| w.0.as_str())
                    .collect::<Vec<_>>()
                    .join(" + "),
                ce.what
            ));
            for w in [&[][..], &with[..1.min(with.len())], &with[..]] {
                if let Some(c) =
                    self.try_custom(ds, dg, &ce, w, seen, noise, on_progress, refused)?
                {
                    return Ok((Some(c), found));
                }
            }
        }
        Ok((None, found))
    }

    /// After a guide was added: its tables' ramps moved into a squareness term, kept when the
    /// ramp is more than the noise can make and the model fits as well (see [`beyond`]).
    fn try_squareness(
        &self,
        ds: &dataset::Dataset,
        on_progress: &mut dyn FnMut(&str),
        refused: &mut Vec<String>,
    ) -> Result<Option<(Tried, String)>, LabError> {
        let Some(sq) = beyond::squareness_from_guides(ds, &self.cal.effects) else {
            return Ok(None);
        };
        let noise = ds.noise_floor_um;
        if sq.ramp_um < 0.5 * noise {
            return Ok(None);
        }
        // The ramp matters: without it (and without squareness) the fit gets worse by more
        // than half the noise floor in quadrature.
        let plain: Vec<EffectConfig> = sq
            .effects
            .iter()
            .filter(|e| e.kind() != "rigid_body")
            .cloned()
            .collect();
        let mut bare = self.cal.clone();
        bare.effects = plain;
        let dsb = dataset::build(self.bags, &bare, &self.o.build)?;
        let pb = analysis::prepare(&dsb)?;
        let cost2 = pb.rms_fit_um.powi(2) - self.prep.rms_fit_um.powi(2);
        if !(cost2 > 0.0 && cost2.sqrt() >= 0.5 * noise.max(0.01)) {
            return Ok(None);
        }
        on_progress(&format!(
            "step {}: naming the guide's ramp squareness: {}",
            self.index, sq.what
        ));
        let what = format!("add rigid_body:squareness ({})", sq.what);
        match self.trial(sq.effects, &what, Gate::Keep)? {
            Err(r) => {
                refused.push(r);
                Ok(None)
            }
            Ok(t) => {
                // Without loss: the fit RMS within 1 % (+0.002 µm).
                if t.prep.rms_fit_um > 1.01 * self.prep.rms_fit_um + 0.002 {
                    refused.push(format!(
                        "{what}: the fit RMS would go from {:.3} to {:.3} µm",
                        self.prep.rms_fit_um, t.prep.rms_fit_um
                    ));
                    return Ok(None);
                }
                Ok(Some((t, sq.what)))
            }
        }
    }
}

/// What a pair's fit leaves to choose by.
struct FitOutcomeLite {
    cv: f64,
    configs: Vec<EffectConfig>,
}

/// Runs the loop. `on_step` sees every step as soon as its version exists (to write it and
/// show progress); `on_progress` gets a line of what the loop is doing.
///
/// When the loop ends far above the noise floor (more than [`STALL_FACTOR`]×) with a
/// structure left that the library does not have, the effects taken before it may have
/// absorbed part of it and now stand in its way: a table or a polynomial fitted to a cyclic
/// error extrapolates badly once the cyclic error is in, so the structure is refused beside
/// them although it is the largest component left (machine 43 of the simulator: a pitch table
/// about the wrong axis and a second-order rigid body, 14.4× the floor). The loop is then run
/// once more from the refit start with that structure first, and the branch that ends lower on
/// the held-out data is kept; the other's steps are returned as `abandoned`, and `restart`
/// says what was done and why.
pub fn discover(
    bags: &[BagData],
    start: &Calibration,
    o: &Options,
    on_step: &mut dyn FnMut(&Step) -> Result<(), LabError>,
    on_progress: &mut dyn FnMut(&str),
) -> Result<Discovery, LabError> {
    let first = discover_from(bags, Begin::Start(start), o, on_step, on_progress)?
        .map_err(LabError::Data)?;
    let noise = first.r#final.noise_floor_um;
    let ratio = first.r#final.heldout_rms_um / noise.max(1e-9);
    if !(ratio > STALL_FACTOR) {
        return Ok(first);
    }
    let Some((custom, s)) = first.unexplained.iter().take(2).find_map(|s| {
        beyond::custom_effect(s)
            .filter(|c| !first.r#final.effects.contains(&c.config.id()))
            .map(|c| (c, s))
    }) else {
        return Ok(first);
    };
    let why = format!(
        "the loop stalled at {ratio:.2}× the noise floor with {} left ({:.3} µm, {:.0} % of the residual) beside the effects taken before it: restarted from the refit start with it first",
        custom.what,
        s.amplitude_um,
        s.explained * 100.0
    );
    on_progress(&why);
    let next_version = first.steps.iter().map(|s| s.version).max().unwrap_or(0) + 1;
    let branch = Begin::Branch {
        step0: &first.steps[0],
        custom,
        version: next_version,
        why: why.clone(),
    };
    let Some(second) = discover_branch(bags, branch, o, on_step, on_progress)? else {
        return Ok(first);
    };
    let (a, b) = (first.r#final.heldout_rms_um, second.r#final.heldout_rms_um);
    let (mut kept, other, verdict) = if b < a {
        (
            second,
            first,
            format!(
                "{why}; kept: it ends at {b:.3} µm held out where the first run ended at {a:.3} µm"
            ),
        )
    } else {
        (
            first,
            second,
            format!("{why}; not kept: it ends at {b:.3} µm held out, the first run at {a:.3} µm"),
        )
    };
    on_progress(&verdict);
    kept.start_heldout_rms_um = other.start_heldout_rms_um.max(kept.start_heldout_rms_um);
    kept.abandoned = other.steps.into_iter().skip(1).collect();
    kept.restart = Some(verdict);
    Ok(kept)
}

/// Where a run of the loop begins.
enum Begin<'a> {
    /// The user's starting calibration (step 0 refits it).
    Start(&'a Calibration),
    /// A restart: the first run's step 0, with `custom` added first as version `version`.
    Branch {
        step0: &'a Step,
        custom: beyond::CustomEffect,
        version: u64,
        why: String,
    },
}

/// [`discover_from`] for a restart; None when the structure cannot be fitted on the refit
/// start or makes its held-out data worse there (then there is nothing to restart from).
fn discover_branch(
    bags: &[BagData],
    b: Begin<'_>,
    o: &Options,
    on_step: &mut dyn FnMut(&Step) -> Result<(), LabError>,
    on_progress: &mut dyn FnMut(&str),
) -> Result<Option<Discovery>, LabError> {
    match discover_from(bags, b, o, on_step, on_progress)? {
        Ok(d) => Ok(Some(d)),
        Err(why) => {
            on_progress(&format!("no restart: {why}"));
            Ok(None)
        }
    }
}

/// The loop from `begin` (see [`discover`]); the inner Err says why a restart could not begin.
fn discover_from(
    bags: &[BagData],
    begin: Begin<'_>,
    o: &Options,
    on_step: &mut dyn FnMut(&Step) -> Result<(), LabError>,
    on_progress: &mut dyn FnMut(&str),
) -> Result<Result<Discovery, String>, LabError> {
    let um = |x: f64| format!("{x:.3}");
    let (p0, mut cal, mut ds, mut prep, mut steps, mut seen) = match begin {
        Begin::Start(start) => {
            let (p0, cal, ds, prep, s0) = step_zero(bags, start, o, on_progress)?;
            on_step(&s0)?;
            let seen = vec![signature(&cal.effects)];
            (p0, cal, ds, prep, vec![s0], seen)
        }
        Begin::Branch {
            step0,
            custom,
            version,
            why,
        } => {
            let ds0 = dataset::build(bags, &step0.calibration, &o.build)?;
            let p0 = analysis::prepare(&ds0)?;
            let name = effect_name(&custom.config);
            let cand = Candidate {
                action: Move::Add,
                effect: name.clone(),
                replaces: None,
                config: Some(custom.config.clone()),
            };
            let applied = match analysis::apply(&ds0, vec![cand], false) {
                Ok(a) => a,
                Err(e) => return Ok(Err(format!("{name} cannot be fitted: {e}"))),
            };
            let mut cal = version::next(&step0.calibration, applied.effects, &o.created);
            cal.version = version;
            let ds = dataset::build(bags, &cal, &o.build)?;
            let prep = analysis::prepare(&ds)?;
            if !(prep.rms_held_um <= p0.rms_held_um) {
                return Ok(Err(format!(
                    "{name} on the refit start leaves the held-out RMS at {:.3} µm (was {:.3})",
                    prep.rms_held_um, p0.rms_held_um
                )));
            }
            let what = format!("add {name} ({}), restarted", custom.what);
            version::describe(
                &mut cal,
                &format!("lab discover step 1: {what}"),
                ds.noise_floor_um,
                &p0,
                &prep,
            );
            let s1 = Step {
                index: 1,
                action: "add".into(),
                effect: name,
                replaces: None,
                version: cal.version,
                rms_um: prep.rms_fit_um,
                cv_rms_um: applied.outcome.cv_rms_after_um,
                heldout_rms_before_um: p0.rms_held_um,
                heldout_rms_um: prep.rms_held_um,
                confounded_with: vec![],
                found: Some(format!("{}; {why}", custom.what)),
                nominal: vec![],
                calibration: cal.clone(),
            };
            on_step(&s1)?;
            let seen = vec![
                signature(&step0.calibration.effects),
                signature(&cal.effects),
            ];
            (p0, cal, ds, prep, vec![step0.clone(), s1], seen)
        }
    };
    let mut confounded: Vec<Confounded> = vec![];
    let mut separated: Vec<Separated> = vec![];
    let mut refused: Vec<String> = vec![];
    let stopped;
    let last_dg;
    let mut left: Vec<Structure>;
    loop {
        on_progress(&format!(
            "step {}: diagnosing v{} ({} effects, held-out {} µm, noise floor {} µm)",
            steps.len(),
            cal.version,
            cal.effects.len(),
            um(prep.rms_held_um),
            um(ds.noise_floor_um)
        ));
        // The structure search waits until no library move is taken (below).
        let mut dg = analysis::diagnose_deferred(&ds)?;
        if steps.len() > o.max_steps {
            analysis::fill_unexplained(&ds, &mut dg)?;
            left = dg.unexplained.clone();
            stopped = format!("the step limit ({}) was reached", o.max_steps);
            last_dg = dg;
            break;
        }
        let index = steps.len();
        let cx = Ctx {
            bags,
            o,
            cal: &cal,
            prep: &prep,
            index,
        };
        let noise = ds.noise_floor_um;
        let mut chosen: Option<Chosen> = None;
        // 1. The best significant library move that does not bring back a model the loop had
        //    and does not make the held-out data worse.
        let moves = analysis::moves(&ds, &cal.effects);
        let mut any_new = false;
        let significant: Vec<&analysis::CandidateReport> = dg
            .candidates
            .iter()
            .filter(|c| c.significant)
            .take(MAX_TRIED)
            .collect();
        //    Then (no significant move taken) a drop the held-out data asks for.
        let held_drops = refused_by_heldout(&dg, prep.rms_held_um, noise);
        for (c, held) in significant
            .into_iter()
            .map(|c| (c, None))
            .chain(held_drops.into_iter().map(|(c, w)| (c, Some(w))))
        {
            if chosen.is_some() {
                break;
            }
            let Some(cand) = moves
                .iter()
                .find(|m| m.effect == c.effect && m.action == c.action && m.replaces == c.replaces)
            else {
                continue;
            };
            let mut next: Vec<EffectConfig> = cal
                .effects
                .iter()
                .filter(|e| Some(e.id()) != cand.replaces)
                .cloned()
                .collect();
            next.extend(cand.config.clone());
            if seen.contains(&signature(&next)) {
                continue;
            }
            // Squareness named from a guide's ramp is not dropped while a guide table can
            // take the ramp back (the drop would cost nothing and leave it unnamed).
            if cand.action == Move::Drop
                && cand.effect == "squareness"
                && cal.effects.iter().any(|e| e.kind() == "guide_straightness")
            {
                continue;
            }
            any_new = true;
            let verb = match cand.action {
                Move::Add => "adding",
                Move::Swap => "swapping in",
                Move::Drop => "dropping",
            };
            on_progress(&format!(
                "step {index}: {verb} {}{}",
                cand.effect,
                cand.replaces
                    .as_ref()
                    .filter(|_| cand.action == Move::Swap)
                    .map(|r| format!(" for {r}"))
                    .unwrap_or_default()
            ));
            let cand = cand.clone();
            let applied = analysis::apply(&ds, vec![cand.clone()], false)?;
            let action = serde_json::to_value(&cand.action)
                .ok()
                .and_then(|v| v.as_str().map(str::to_string))
                .unwrap_or_default();
            let what = format!(
                "{action} {}{}",
                cand.effect,
                cand.replaces
                    .as_ref()
                    .filter(|_| cand.action == Move::Swap)
                    .map(|r| format!(" (replaces {r})"))
                    .unwrap_or_default()
            );
            let gate = if cand.action == Move::Drop {
                Gate::Keep
            } else {
                Gate::Earn
            };
            match cx.trial(applied.effects, &what, gate)? {
                Err(r) => {
                    on_progress(&format!("step {index}: not taken — {r}"));
                    refused.push(r);
                }
                Ok(t) => {
                    // Confounded by the correlation of their corrections, unless the scores
                    // separate them.
                    let mut conf = vec![];
                    for k in dg.confounded.iter().filter(|k| k.effects[0] == cand.effect) {
                        match separated_by_scores(&dg, k) {
                            Some(sep) => {
                                on_progress(&format!(
                                    "step {index}: {} and {} correct alike, but their scores separate them (cross-validated {:.3} vs {:.3} µm)",
                                    sep.effects[0], sep.effects[1], sep.cv_rms_um[0], sep.cv_rms_um[1]
                                ));
                                separated.push(sep);
                            }
                            None => conf.push(k.clone()),
                        }
                    }
                    chosen = Some(Chosen {
                        tried: t,
                        action,
                        effect: cand.effect.clone(),
                        replaces: cand.replaces.clone().filter(|_| cand.action == Move::Swap),
                        cv: applied.outcome.cv_rms_after_um,
                        conf,
                        found: held,
                    });
                }
            }
        }
        // 2. Structure the library does not have, as a custom effect.
        if chosen.is_none() {
            analysis::fill_unexplained(&ds, &mut dg)?;
        }
        left = dg.unexplained.clone();
        if chosen.is_none() {
            for s in left.iter().take(2) {
                let Some(ce) = beyond::custom_effect(s) else {
                    continue;
                };
                if let Some(c) =
                    cx.try_custom(&ds, &dg, &ce, &[], &seen, noise, on_progress, &mut refused)?
                {
                    chosen = Some(c);
                    break;
                }
            }
        }
        // 3. Squareness on its own (a rigid body's three angles, no axis errors).
        if chosen.is_none() && !cal.effects.iter().any(|e| e.kind() == "rigid_body") {
            if let Some(cfg) = beyond::squareness_config(&ds, [0.0; 3]) {
                let what = "squareness of the axes (rigid_body, squareness only)".to_string();
                let ce = beyond::CustomEffect { config: cfg, what };
                if let Some(c) =
                    cx.try_custom(&ds, &dg, &ce, &[], &seen, noise, on_progress, &mut refused)?
                {
                    chosen = Some(c);
                }
            }
        }
        // 4. Several effects at once: pairs of the best candidates, and the structure left
        //    after them, when the residual is still far above the floor.
        if chosen.is_none() && prep.rms_held_um.max(dg.cv_rms_um) > STALL_FACTOR * noise {
            let (c, after_best) =
                cx.try_together(&ds, &dg, &moves, &seen, noise, on_progress, &mut refused)?;
            chosen = c;
            if chosen.is_none() && !after_best.is_empty() {
                left = after_best;
            }
        }
        // 5. Before stopping: a guide table that carries a ramp carries squareness (with
        //    every other effect in, the ramp is no longer standing in for them): name it.
        if chosen.is_none() {
            if let Some((t, what)) = cx.try_squareness(&ds, on_progress, &mut refused)? {
                chosen = Some(Chosen {
                    cv: dg.cv_rms_um,
                    tried: t,
                    action: "add".into(),
                    effect: "rigid_body:squareness".into(),
                    replaces: None,
                    conf: vec![],
                    found: Some(what),
                });
            }
        }
        let Some(ch) = chosen else {
            let largest = left
                .first()
                .map(|s| {
                    format!(
                        "the largest component left unexplained: {} ({:.3} µm, {:.0} % of the residual)",
                        describe_structure(s),
                        s.amplitude_um,
                        s.explained * 100.0
                    )
                })
                .unwrap_or_else(|| {
                    format!(
                        "what is left ({} µm held out, {:.2}× the noise floor) shows no period, reversal or probing-direction harmonic",
                        um(prep.rms_held_um),
                        prep.rms_held_um / noise.max(1e-9)
                    )
                });
            let why = if !any_new && dg.candidates.iter().any(|c| c.significant) {
                "every significant move leads back to a model already tried"
            } else if dg.candidates.iter().any(|c| c.significant) {
                "every significant move makes the held-out data worse"
            } else if prep.rms_held_um.max(dg.cv_rms_um) > STALL_FACTOR * noise {
                "no candidate is significant, alone, in pairs of the best, or as structure left after them"
            } else {
                "no candidate is significant"
            };
            stopped = format!("{why}; {largest}");
            last_dg = dg;
            break;
        };
        let before = prep.clone();
        let step = Step {
            index,
            action: ch.action,
            effect: ch.effect,
            replaces: ch.replaces,
            version: ch.tried.next.version,
            rms_um: ch.tried.prep.rms_fit_um,
            cv_rms_um: ch.cv,
            heldout_rms_before_um: before.rms_held_um,
            heldout_rms_um: ch.tried.prep.rms_held_um,
            confounded_with: ch.conf.iter().map(|c| c.effects[1].clone()).collect(),
            found: ch.found,
            nominal: vec![],
            calibration: ch.tried.next.clone(),
        };
        on_step(&step)?;
        steps.push(step);
        for c in ch.conf {
            if !confounded.iter().any(|k| k.effects == c.effects) {
                confounded.push(c);
            }
        }
        seen.push(signature(&ch.tried.next.effects));
        cal = ch.tried.next;
        ds = ch.tried.ds;
        prep = ch.tried.prep;
    }
    let mut fin = analysis::fit_effects(&ds, &prep, &cal.effects)?;
    // σ carries what the choice of model moves (the near-equal moves of the last diagnosis).
    analysis::widen_by_alternatives(&mut fin, &last_dg.model_spread);
    // … and what the arc's description moves (the commanded arcs against the estimated path's).
    on_progress(
        "refitting with each arc taken from the estimated path (what the arc's description moves)",
    );
    let arcs = analysis::arc_source_spread(bags, &ds, &o.build, &fin)?;
    analysis::widen_by_arc_source(&mut fin, &arcs);
    let fin_params = fin.by_effect();
    Ok(Ok(Discovery {
        start_heldout_rms_um: p0.rms_held_um,
        start_rms_um: p0.rms_fit_um,
        steps,
        confounded,
        separated,
        unexplained: left,
        refused,
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
        abandoned: vec![],
        restart: None,
    }))
}

/// Step 0: the start corrected as given (`p0`), then its nominal model (the axes' time
/// constants) and its effects refitted, as the first version of the loop.
fn step_zero(
    bags: &[BagData],
    start: &Calibration,
    o: &Options,
    on_progress: &mut dyn FnMut(&str),
) -> Result<(Prepared, Calibration, dataset::Dataset, Prepared, Step), LabError> {
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
    let ds = dataset::build(bags, &cal, &o.build)?;
    let prep = analysis::prepare(&ds)?;
    version::describe(
        &mut cal,
        "lab discover step 0 (refit of the start)",
        ds.noise_floor_um,
        &p0,
        &prep,
    );
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
        found: None,
        nominal: axes,
        calibration: cal.clone(),
    };
    Ok((p0, cal, ds, prep, s0))
}

/// Candidates the lab tries that a default campaign leaves confounded with a model effect: the
/// servo gain in f and f² (against `accel_deflection`) and the rigid body (against a guide).
const PLANNED_CANDIDATES: [&str; 2] = ["servo_gain:powers=1+2", "rigid_body"];

/// What a discovery leaves for a plan to determine: the confounded pairs, and the parameters
/// the data could not determine. Empty: nothing to plan for.
pub fn left_to_plan(d: &Discovery) -> Vec<String> {
    let mut v: Vec<String> = d
        .confounded
        .iter()
        .map(|c| format!("{} against {}", c.effects[0], c.effects[1]))
        .collect();
    if !d.unidentifiable.is_empty() {
        v.push(format!(
            "{} parameter(s) not determined",
            d.unidentifiable.len()
        ));
    }
    v
}

/// The candidates a plan after `d` makes identifiable beside the final model: each effect
/// named confounded with one the loop took, then the candidates a default campaign leaves
/// confounded (see `PLANNED_CANDIDATES`), each kind the model does not have, once.
pub fn plan_candidates(d: &Discovery) -> Vec<String> {
    let mut v: Vec<String> = vec![];
    let kind = |e: &str| e.split(':').next().unwrap_or(e).to_string();
    let names = d
        .confounded
        .iter()
        .map(|c| c.effects[1].clone())
        .chain(PLANNED_CANDIDATES.iter().map(|s| s.to_string()));
    for n in names {
        let k = kind(&n);
        if d.r#final.kinds.contains(&k) || v.iter().any(|x| kind(x) == k) {
            continue;
        }
        v.push(n);
    }
    v
}

/// The artifacts the bags' program records show the user owns: each ring and sphere at its
/// certified diameter (or nominal, without a certificate), and a straightedge at least as long
/// as the longest line scanned along it (speed × duration of its segments, rounded up to
/// 10 mm; 400 mm when its segments say nothing).
pub fn owned_in(bags: &[BagData]) -> Vec<super::plan::Owned> {
    use super::plan::{Artifact, Owned};
    let mut v: Vec<Owned> = vec![];
    for p in bags.iter().filter_map(|b| b.program.as_ref()) {
        for f in &p.features {
            let size = f.certificate_diameter_mm.unwrap_or(f.nominal_diameter_mm);
            let (artifact, size_mm) = match f.artifact.as_str() {
                "ring" => (Artifact::Ring, size),
                "sphere" => (Artifact::Sphere, size),
                "straightedge" => {
                    let l = p
                        .segments
                        .iter()
                        .filter(|s| {
                            s.feature == Some(f.id)
                                && s.kind == super::program::SegmentKind::Scan
                                && s.direction == 0
                        })
                        .map(|s| s.speed.abs() * (s.t1_s - s.t0_s))
                        .filter(|l| l.is_finite())
                        .fold(0.0, f64::max);
                    let l = if l >= 50.0 {
                        (l / 10.0).ceil() * 10.0
                    } else {
                        400.0
                    };
                    (Artifact::Straightedge, l.min(3000.0))
                }
                _ => continue,
            };
            if !(size_mm.is_finite() && size_mm > 0.0) {
                continue;
            }
            match v.iter_mut().find(|o| {
                o.artifact == artifact
                    && (artifact == Artifact::Straightedge || (o.size_mm - size_mm).abs() < 1e-6)
            }) {
                Some(o) => o.size_mm = o.size_mm.max(size_mm),
                None => v.push(Owned { artifact, size_mm }),
            }
        }
    }
    v
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lab::plan::Artifact;
    use crate::lab::program::{FeatureKind, FeatureSpec, ProgramSpec, SegmentKind, SegmentSpec};
    use std::sync::Arc;

    fn feature(id: u32, artifact: &str, d: f64, cert: Option<f64>) -> FeatureSpec {
        FeatureSpec {
            id,
            artifact: artifact.into(),
            kind: if d > 0.0 {
                FeatureKind::Bore
            } else {
                FeatureKind::Face
            },
            nominal_center: [0.0; 3],
            nominal_diameter_mm: d,
            certificate_diameter_mm: cert,
            normal: [0.0, -1.0, 0.0],
        }
    }

    fn line(id: u32, feature: u32, speed: f64, secs: f64) -> SegmentSpec {
        SegmentSpec {
            id,
            kind: SegmentKind::Scan,
            feature: Some(feature),
            speed,
            direction: 0,
            tip: 1,
            a1_deg: 0.0,
            a2_deg: 0.0,
            deflection_mm: 0.3,
            t0_s: 10.0,
            t1_s: 10.0 + secs,
        }
    }

    /// The artifacts a plan may use are those the bags measured: each ring size once, the
    /// sphere, and the straightedge at least as long as its longest line (rounded up).
    #[test]
    fn owned_from_the_bags_program_records() {
        let program = ProgramSpec {
            program: "campaign".into(),
            features: vec![
                feature(1, "ring", 50.0, Some(50.0012)),
                feature(2, "ring", 50.0, Some(50.0012)),
                feature(3, "sphere", 25.0, Some(25.0004)),
                feature(4, "straightedge", 0.0, None),
                feature(5, "part", 30.0, None),
            ],
            segments: vec![line(1, 4, 50.0, 15.2), line(2, 4, 50.0, 3.0)],
        };
        let bag = BagData {
            name: "c.mcap".into(),
            samples: Arc::new(Vec::<crate::sample::Sample>::new()),
            program: Some(program),
            validation: false,
        };
        let owned = owned_in(&[bag]);
        assert_eq!(owned.len(), 3, "{owned:?}");
        assert_eq!(
            (owned[0].artifact, owned[0].size_mm),
            (Artifact::Ring, 50.0012)
        );
        assert_eq!(
            (owned[1].artifact, owned[1].size_mm),
            (Artifact::Sphere, 25.0004)
        );
        // 50 mm/s × 15.2 s = 760 mm.
        assert_eq!(
            (owned[2].artifact, owned[2].size_mm),
            (Artifact::Straightedge, 760.0)
        );
        // No program record: nothing known owned.
        let bare = BagData {
            name: "r.mcap".into(),
            samples: Arc::new(Vec::<crate::sample::Sample>::new()),
            program: None,
            validation: false,
        };
        assert!(owned_in(&[bare]).is_empty());
    }
}
