//! Compare, diagnose and add: the lab's questions answered on a [`Dataset`].

use super::dataset::Dataset;
use super::fit::{nuisance_row, ArtifactFit, Normal};
use super::program::FeatureKind;
use super::select::{predicted, Score, Space, Spec};
use super::LabError;
use crate::effects::{Effect, EffectConfig};
use crate::sample::Vec3;
use serde::Serialize;

pub use super::candidates::{candidate, library_candidates, moves, moves_named, variant_key};
pub use super::compare::{compare, Bin, Comparison, Harmonics};
pub use super::select::fit_effects;
pub use super::types::{prepare, Candidate, EffectParams, FitOutcome, Move, Param, Prepared};

/// Columns g_i·r_ik of effect configs for every point (row-major, `k` per point).
fn columns(
    ds: &Dataset,
    art: &ArtifactFit,
    configs: &[EffectConfig],
) -> Result<(Vec<f64>, usize, Vec<crate::effects::Model>), LabError> {
    let mut sensors = ds.sensors.clone();
    let mut models = vec![];
    for c in configs {
        let b = c
            .build(&mut sensors)
            .map_err(|e| LabError::Data(format!("{}: {e}", c.kind())))?;
        models.push(b.model);
    }
    if sensors.names().len() != ds.sensors.names().len() {
        let missing: Vec<&String> = sensors
            .names()
            .iter()
            .filter(|n| ds.sensors.find(n).is_none())
            .collect();
        return Err(LabError::Data(format!(
            "the bags have no readings of temperature sensor(s) {missing:?}: record the temperature stream with those sensors"
        )));
    }
    let k: usize = models.iter().map(|m| m.n_params()).sum();
    let mut cols = vec![0.0; k * ds.points.len()];
    let mut r = vec![Vec3::zeros(); models.iter().map(|m| m.n_params()).max().unwrap_or(0)];
    for (i, p) in ds.points.iter().enumerate() {
        let g = art.grad[i];
        let mut c = 0;
        for m in &models {
            let n = m.n_params();
            m.regressors(&p.ctx, &mut r[..n]);
            for v in &r[..n] {
                cols[i * k + c] = g.dot(v);
                c += 1;
            }
        }
    }
    Ok((cols, k, models))
}

/// A measurement that makes an effect visible — counted only where it acts along the
/// measured direction (a circle fit sees radial errors, a face its normal).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
enum Lever {
    /// Acceleration along the measured direction off arcs (a face approached or left at speed).
    NormalAcceleration,
    /// Circles of another radius at the same speeds: rotation frequency v/2πr and centripetal
    /// acceleration v²/r scale differently.
    Radius,
    Speed,
    Direction,
    Position,
    Temperature,
    Deflection,
    Stylus,
}

fn levers(kind: &str) -> &'static [Lever] {
    use Lever::*;
    match kind {
        "accel_deflection" => &[NormalAcceleration, Radius, Speed, Position],
        // Circles of another diameter separate a gain term in f¹ from the deflection (which
        // follows v²/r, not the rotation frequency; an f² term follows v²/r too): the lever
        // is listed on one side only.
        "servo_gain" => &[Speed],
        "servo_phase" => &[Speed, Direction],
        "stylus_thermal" => &[Temperature, Stylus],
        "scale_thermal" => &[Temperature, Position],
        "probe_force" => &[Deflection],
        "guide_straightness" => &[Position, Stylus],
        "rigid_body" => &[Position, Stylus],
        "probe_lobing" => &[Deflection, Stylus],
        _ => &[],
    }
}

fn lever_text(l: Lever, a: &str, b: &str, covered: bool, positions: &str) -> String {
    let more = if covered { "more " } else { "" };
    let (with, without) = (a, b);
    match l {
        Lever::NormalAcceleration => format!("{more}scans of a face while the machine accelerates along the face's normal, off arcs ({with} responds to acceleration along the measured direction, {without} only on arcs; a straightedge scanned along its length does not show it)"),
        Lever::Radius => format!("{more}circles of another diameter at the same speeds (a smaller ring or a sphere's equator: the rotation frequency v/2πr and the acceleration v²/r scale differently, which separates a term of {without} in f¹ from {with}; a term in f² follows v²/r as {with} does at any diameter, and only the scans of a face accelerated along its normal separate it)"),
        Lever::Speed => format!("scans at {more}other speeds (the effects grow differently with speed)"),
        Lever::Direction => format!("scans in {more}both directions, CW and CCW ({with} changes sign with direction)"),
        Lever::Position => format!("the artifact at {more}other positions in the volume ({with} depends on position; {positions}; `scancorr lab plan` chooses them and predicts each parameter's σ)"),
        Lever::Temperature => format!("a {more}temperature change during the campaign ({with} depends on temperature)"),
        Lever::Deflection => format!("scans at {more}other probe deflections ({with} depends on the deflection)"),
        Lever::Stylus => format!("{more}other styli or head angles ({with} depends on the stylus)"),
    }
}

/// Two candidates this data cannot tell apart.
#[derive(Debug, Clone, Serialize)]
pub struct Confounded {
    /// The two effects.
    pub effects: [String; 2],
    /// How much of each one's fitted correction the other reproduces (R², 0–1).
    pub r2: [f64; 2],
    /// Measurements that would separate them.
    pub separate_by: Vec<String>,
}

pub use super::structure::Structure;

/// One candidate of a diagnosis.
#[derive(Debug, Clone, Serialize)]
pub struct CandidateReport {
    /// What the move does: `add`, `swap` (replaces a model effect) or `drop`.
    pub action: Move,
    /// Effect (with variant) brought in, or the id dropped.
    pub effect: String,
    /// The model effect it replaces or drops.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub replaces: Option<String>,
    /// Fraction of the cross-validated residual it removes (negative: what dropping costs).
    pub explained: f64,
    /// Cross-validated RMS of the model refitted as it is, µm.
    pub cv_rms_before_um: f64,
    /// With the move, every effect refitted, µm.
    pub cv_rms_after_um: f64,
    /// Explains more than noise and pays for its parameters (see [`diagnose`]).
    pub significant: bool,
    /// RMS before, µm (fit data).
    pub rms_before_um: f64,
    /// After, µm (fit data).
    pub rms_after_um: f64,
    /// Held-out RMS before, µm.
    pub heldout_rms_before_um: f64,
    /// Held-out RMS after, µm.
    pub heldout_rms_after_um: f64,
    /// ΔBIC on the fit data.
    pub delta_bic: f64,
    /// Number of parameters.
    pub k: usize,
    /// Fitted parameters of the effect brought in.
    pub params: Vec<Param>,
    /// Parameters the data cannot determine (of every effect refitted).
    pub unidentifiable: Vec<String>,
}

/// A diagnosis.
#[derive(Debug, Clone, Serialize)]
pub struct Diagnosis {
    /// Residual RMS of the current model on fit data, µm.
    pub rms_um: f64,
    /// Cross-validated RMS of the current model refitted, µm (alternate scans predicted).
    pub cv_rms_um: f64,
    /// On held-out data, µm.
    pub heldout_rms_um: f64,
    /// Noise floor, µm.
    pub noise_floor_um: f64,
    /// Candidates, best first.
    pub candidates: Vec<CandidateReport>,
    /// Pairs the data cannot separate.
    pub confounded: Vec<Confounded>,
    /// Structure no candidate explains (reported when no candidate is significant or the best
    /// leaves clearly more than noise).
    pub unexplained: Vec<Structure>,
    /// Points used (fit, held out).
    pub points: [usize; 2],
    /// Candidates this data cannot test, and why.
    pub skipped: Vec<String>,
    /// What the best candidate predicts for the circles (absent without circles or
    /// candidates).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub prediction: Option<Prediction>,
    /// What the choice of model moves: for each parameter of the model (refitted as it is),
    /// the largest change among the moves this data scores near-equal (see
    /// [`near_equal`]), and the move that makes it. Applied to a fit of this model by
    /// [`widen_by_alternatives`].
    #[serde(skip)]
    pub model_spread: Vec<ModelSpread>,
    /// The residual whose structure `unexplained` reports, while that search is deferred
    /// ([`diagnose_deferred`]); [`fill_unexplained`] runs it.
    #[serde(skip)]
    pub left_residual: Option<Vec<f64>>,
}

/// The largest change of one parameter among the near-equal models (see [`Diagnosis`]).
#[derive(Debug, Clone)]
pub struct ModelSpread {
    /// The effect's id.
    pub effect: String,
    /// The parameter's name.
    pub name: String,
    /// |value in the alternative − value in the model refitted as it is|.
    pub shift: f64,
    /// The move that makes it.
    pub by: String,
}

/// Whether a move's model is near-equal to the model refitted as it is: on the other scans
/// it is better, or worse by less than a significant move would gain (half the noise floor
/// or 1 % of the sum of squares, as [`significant_gain`]): the data cannot say that the model
/// is preferable to it, so what it changes is part of the uncertainty.
pub fn near_equal(base: &Score, s: &Score, noise_um: f64) -> bool {
    if !(s.cv_ss.is_finite() && base.cv_ss.is_finite()) || s.cv_n == 0 {
        return false;
    }
    let n = s.cv_n as f64;
    let noise = noise_um.max(0.01) * 1e-3;
    let band = (0.25 * noise * noise * n).max(0.01 * base.cv_ss);
    s.cv_ss <= base.cv_ss + band
}

/// Widens each parameter's σ of `o` (a fit of the model `model_spread` was computed for) by
/// the largest change among the near-equal models: σ² + change², recorded in
/// `Param::model_spread` and said in its note when it dominates. Parameters without a σ (not
/// determined) stay without one.
pub fn widen_by_alternatives(o: &mut FitOutcome, model_spread: &[ModelSpread]) {
    widen(o, model_spread, |m| {
        format!(
            "the choice of model moves it: `{}`, which the data scores near-equal, changes it by {:.3e}: σ includes that",
            m.by, m.shift
        )
    });
}

/// σ² + change² for each parameter of `o` that `spread` names and that has a σ; the change
/// added in quadrature to `Param::model_spread`, and `say`'s words in the note when the change
/// exceeds the σ before.
fn widen(o: &mut FitOutcome, spread: &[ModelSpread], say: impl Fn(&ModelSpread) -> String) {
    for (c, ps) in o.configs.iter().zip(o.params.iter_mut()) {
        let id = c.id();
        for p in ps.iter_mut() {
            let Some(m) = spread.iter().find(|m| m.effect == id && m.name == p.name) else {
                continue;
            };
            let Some(s) = p.sigma else { continue };
            if !m.shift.is_finite() {
                continue;
            }
            p.model_spread = Some(p.model_spread.map_or(m.shift, |a| a.hypot(m.shift)));
            p.sigma = Some((s * s + m.shift * m.shift).sqrt());
            if m.shift > s {
                let said = say(m);
                p.note = Some(match p.note.take() {
                    Some(n) => format!("{n}; {said}"),
                    None => said,
                });
            }
        }
    }
}

/// The controller's commands without their arcs (centre and radius 0): the corrector then
/// takes each arc from the estimated path itself, its osculating circle
/// ([`crate::estimator::osculating_arc`]).
struct WithoutArcs(std::sync::Arc<dyn super::dataset::Samples>);

impl super::dataset::Samples for WithoutArcs {
    fn replay(&self, f: &mut dyn FnMut(crate::sample::Sample)) -> Result<(), String> {
        self.0.replay(&mut |s| match s {
            crate::sample::Sample::Command(mut c) => {
                c.arc_center = Vec3::zeros();
                c.arc_radius = 0.0;
                f(crate::sample::Sample::Command(c))
            }
            s => f(s),
        })
    }
    fn sensors(&self) -> Vec<String> {
        self.0.sensors()
    }
}

/// What the arc's description moves (issue 45, item 2): each parameter of `o` — the fit of
/// `ds`'s model (every effect refitted) on `bags` — against the same model fitted to the same
/// bags with every commanded arc left out, so that the corrector takes the arc (centre,
/// radius, rotation frequency f) from the estimated path instead
/// ([`crate::estimator::osculating_arc`]). The two are the corrector's two descriptions of
/// the same motion; on a steady circle they agree. On the simulator the servo phase's b1
/// fitted under the commanded arcs was 0.6–1.3 % steeper than under the estimated arcs while
/// the rotation frequency came from the estimate's normal acceleration over the commanded
/// radius (0.2 % low: the sampled acceleration's polygon bias and the estimate's smaller
/// circle); with f the estimate's rate about the commanded centre
/// ([`crate::estimator::rotation`]) 0.15–0.6 % is left, and only with `accel_deflection` on:
/// a systematic of the arc's description that no statistic of one fit can show. Its size is a model-form uncertainty
/// (the spread between descriptions the data cannot tell apart, Burnham & Anderson 2002
/// §4.3), given by [`widen_by_arc_source`]. Empty when no point lies on a commanded arc or the
/// model has no effect that uses arcs (`servo_phase`, `servo_gain`, `custom`).
pub fn arc_source_spread(
    bags: &[super::dataset::BagData],
    ds: &Dataset,
    build: &super::dataset::BuildOptions,
    o: &FitOutcome,
) -> Result<Vec<ModelSpread>, LabError> {
    let model = &ds.calibration.effects;
    let uses_arcs = model
        .iter()
        .any(|c| matches!(c.kind(), "servo_phase" | "servo_gain" | "custom"));
    if !uses_arcs || !ds.points.iter().any(|p| p.ctx.arc_radius > 0.0) {
        return Ok(vec![]);
    }
    let stripped: Vec<super::dataset::BagData> = bags
        .iter()
        .map(|b| super::dataset::BagData {
            name: b.name.clone(),
            samples: std::sync::Arc::new(WithoutArcs(b.samples.clone())),
            program: b.program.clone(),
            validation: b.validation,
        })
        .collect();
    let ds2 = super::dataset::build(&stripped, &ds.calibration, build)?;
    let prep2 = prepare(&ds2)?;
    let o2 = fit_effects(&ds2, &prep2, model)?;
    let mut out = vec![];
    for (c, ps) in o.configs.iter().zip(&o.params) {
        let id = c.id();
        let Some(k) = o2.configs.iter().position(|a| a.id() == id) else {
            continue;
        };
        for p in ps.iter().filter(|p| p.sigma.is_some()) {
            let Some(q) = o2.params[k]
                .iter()
                .find(|q| q.name == p.name && q.sigma.is_some())
            else {
                continue;
            };
            let shift = (q.value - p.value).abs();
            if shift.is_finite() {
                out.push(ModelSpread {
                    effect: id.clone(),
                    name: p.name.clone(),
                    shift,
                    by: "each arc taken from the estimated path instead of the commanded arc"
                        .into(),
                });
            }
        }
    }
    Ok(out)
}

/// Widens each parameter's σ of `o` by what the arc's description moves
/// ([`arc_source_spread`]): σ² + change², the change added (in quadrature) to
/// `Param::model_spread` and said in the note when it exceeds the σ before. Parameters
/// without a σ stay without one.
pub fn widen_by_arc_source(o: &mut FitOutcome, spread: &[ModelSpread]) {
    widen(o, spread, |m| {
        format!(
            "the arc's description moves it: with {}, it changes by {:.3e}: σ includes that",
            m.by, m.shift
        )
    });
}

/// The largest change of each parameter of the base fit `base_o` among the near-equal moves
/// of `results`.
///
/// A parameter the near-equal model does not have — its effect dropped or replaced by another
/// kind, or swapped for a variant without that term — is 0 there (the library's convention:
/// an absent term contributes nothing), so its change is its whole value. This is the
/// model-averaged ("unconditional") spread of Burnham & Anderson (2002, §4.3: a parameter is
/// taken as 0 in the models that exclude it); it is largest where the data cannot say
/// whether the term is there at all.
fn model_spreads(
    base_o: &FitOutcome,
    base: &Score,
    results: &[(Candidate, Option<usize>, Spec, Score, FitOutcome, bool)],
    noise_um: f64,
) -> Vec<ModelSpread> {
    let mut out: Vec<ModelSpread> = vec![];
    let mut note = |id: &str, name: &str, shift: f64, by: &str| {
        if !shift.is_finite() {
            return;
        }
        match out.iter_mut().find(|m| m.effect == id && m.name == name) {
            Some(m) if m.shift >= shift => {}
            Some(m) => {
                m.shift = shift;
                m.by = by.to_string();
            }
            None => out.push(ModelSpread {
                effect: id.to_string(),
                name: name.to_string(),
                shift,
                by: by.to_string(),
            }),
        }
    };
    for (c, _, _, score, o, _) in results {
        if !near_equal(base, score, noise_um) {
            continue;
        }
        for (bcfg, bps) in base_o.configs.iter().zip(&base_o.params) {
            let id = bcfg.id();
            // The same effect and variant, else another variant of the same kind (a swap),
            // else none (dropped or replaced by another kind).
            let alt = o
                .configs
                .iter()
                .position(|a| a.id() == id)
                .or_else(|| o.configs.iter().position(|a| a.kind() == bcfg.kind()));
            let same_variant = alt.is_some_and(|a| o.configs[a].id() == id);
            for bp in bps {
                if bp.sigma.is_none() {
                    continue;
                }
                let in_alt = alt.and_then(|a| o.params[a].iter().find(|q| q.name == bp.name));
                let shift = match in_alt {
                    Some(p) if p.sigma.is_some() => (p.value - bp.value).abs(),
                    // Undetermined in the alternative: it says nothing of this value.
                    Some(_) => continue,
                    // The same effect fitted without this parameter (not fitted in the
                    // alternative's space): nothing to compare.
                    None if same_variant => continue,
                    None => bp.value.abs(),
                };
                note(&id, &bp.name, shift, &c.effect);
            }
        }
    }
    out
}

/// The residual a candidate move predicts, beside the measured one: the circles' traces
/// before (the model refitted as it is) and after the move (every effect refitted), both
/// from the same artifact fit, so they share their scale and centre treatment.
#[derive(Debug, Clone, Serialize)]
pub struct Prediction {
    /// The move's effect (with variant) or the id dropped.
    pub effect: String,
    /// The move.
    pub action: Move,
    /// The measured traces.
    pub measured: Vec<super::traces::Trace>,
    /// The traces the move predicts.
    pub predicted: Vec<super::traces::Trace>,
}

/// Whether a move should be made: an addition or swap must remove, on scans it was not fitted
/// on, a residual component of at least half the noise floor and at least 1 % of the
/// cross-validated sum of squares, and improve the held-out data (unless that is already at
/// the noise floor); a drop must cost less than 0.15 of the noise floor.
fn significant(
    action: &Move,
    base: &Score,
    s: &Score,
    o: &FitOutcome,
    base_held_um: f64,
    noise_um: f64,
) -> bool {
    let n = s.cv_n.max(1) as f64;
    let rms = |ss: f64| (ss.max(0.0) / n).sqrt() * 1e3;
    match action {
        Move::Add | Move::Swap => significant_gain(
            rms(base.cv_ss),
            rms(s.cv_ss),
            base_held_um,
            o.heldout_rms_after_um,
            noise_um,
        ),
        Move::Drop => {
            let noise = noise_um.max(0.01) * 1e-3;
            let gain = base.cv_ss - s.cv_ss;
            (gain >= 0.0 || ((-gain) / n).sqrt() < 0.15 * noise)
                && held_not_worse(base_held_um, o.heldout_rms_after_um, noise_um)
        }
    }
}

/// The significance test of an addition (a library move, a swap, or a structure made a
/// custom effect): from `base_cv_um` to `after_cv_um` cross-validated RMS (scans predicted
/// from the others, the same points before and after), the move removes a component of at
/// least half the noise floor and at least 1 % of the sum of squares, and held-out data at
/// another position or run (`base_held_um` → `after_held_um`; 0 before when there is none)
/// does not get worse than with the model refitted as it is: an effect that only predicts the
/// alternate scans of the same placements is not kept.
pub fn significant_gain(
    base_cv_um: f64,
    after_cv_um: f64,
    base_held_um: f64,
    after_held_um: f64,
    noise_um: f64,
) -> bool {
    let noise = noise_um.max(0.01);
    let (b, a) = (base_cv_um, after_cv_um);
    if !(a.is_finite() && b.is_finite()) {
        return false;
    }
    let gain2 = b * b - a * a;
    gain2 > 0.0
        && gain2.sqrt() >= 0.5 * noise
        && gain2 >= 0.01 * b * b
        && held_not_worse(base_held_um, after_held_um, noise_um)
}

fn held_not_worse(base_held_um: f64, after_held_um: f64, noise_um: f64) -> bool {
    base_held_um == 0.0
        || (after_held_um.is_finite() && after_held_um <= 1.01 * base_held_um + 0.02 * noise_um)
}

/// The width of a near-tie of [`rank_key`]: keys in one bucket of this width are ranked by
/// the information criterion.
const RANK_TIE: f64 = 0.002;

/// What a scored move is ranked by (see [`rank_order`]).
#[derive(Debug, Clone, PartialEq)]
pub struct RankItem<'a> {
    /// Significant moves come first.
    pub significant: bool,
    /// [`rank_key`]: smaller is better.
    pub key: f64,
    /// Change of the information criterion (the near-ties' tie-breaker).
    pub delta_bic: f64,
    /// Parameters fitted (fewer first).
    pub k: usize,
    /// The move's effect and what it replaces (a stable last key).
    pub name: &'a str,
    /// The model effect replaced or dropped.
    pub replaces: Option<&'a str>,
}

/// The bucket of a rank key: keys within one bucket are a near-tie. Not finite: last.
fn rank_bucket(key: f64) -> i64 {
    if key.is_finite() {
        // `as` saturates: a huge key falls in the last bucket, never wraps.
        (key / RANK_TIE).floor() as i64
    } else {
        i64::MAX
    }
}

/// The ranking of moves, best first: significant first, then the rank key quantised into
/// buckets of [`RANK_TIE`] (a near-tie), then ΔBIC, the number of parameters, the name and
/// the raw key. Each step compares by a total order, and so does the lexicographic whole —
/// unlike "within 0.002 is a tie", which is not transitive (Rust's sort may panic on it).
pub fn rank_order(a: &RankItem, b: &RankItem) -> std::cmp::Ordering {
    b.significant
        .cmp(&a.significant)
        .then(rank_bucket(a.key).cmp(&rank_bucket(b.key)))
        .then(a.delta_bic.total_cmp(&b.delta_bic))
        .then(a.k.cmp(&b.k))
        .then(a.name.cmp(b.name))
        .then(a.replaces.cmp(&b.replaces))
        .then(a.key.total_cmp(&b.key))
}

/// How well a candidate model generalises, smaller is better: the cross-validated mean square
/// relative to the model refitted as it is, times the same ratio on held-out data (another
/// position or run) when there is any — a model must predict both the other scans and the
/// other place. Drops rank by the same key.
fn rank_key(base: &Score, s: &Score, o: &FitOutcome, base_held_um: f64) -> f64 {
    let cv = if base.cv_ss > 0.0 {
        s.cv_ss / base.cv_ss
    } else {
        1.0
    };
    let held = if base_held_um > 0.0 && o.heldout_rms_after_um.is_finite() {
        (o.heldout_rms_after_um / base_held_um).powi(2)
    } else {
        1.0
    };
    cv * held
}

fn r2_explains(
    ds: &Dataset,
    prep: &Prepared,
    target: &[f64],
    by: &EffectConfig,
) -> Result<f64, LabError> {
    let art = &prep.art;
    let (cols, k, _) = columns(ds, art, std::slice::from_ref(by))?;
    let mut ne = Normal::new(k + art.n_cols);
    let mut nn = Normal::new(art.n_cols);
    let mut row = vec![];
    for (i, p) in ds.points.iter().enumerate() {
        if prep.fit_mask[i] {
            nuisance_row(art, p, &p.surface, &mut row);
            ne.add(&cols[i * k..(i + 1) * k], &row, target[i]);
            nn.add(&[], &row, target[i]);
        }
    }
    let (s1, s0) = (ne.solve().ss, nn.solve().ss);
    Ok(if s0 > 0.0 {
        (1.0 - s1 / s0).clamp(0.0, 1.0)
    } else {
        0.0
    })
}

/// What the data covers (for the separating measurements).
fn coverage(ds: &Dataset) -> Vec<Lever> {
    let mut v = vec![];
    if ds
        .points
        .iter()
        .any(|p| p.ctx.arc_radius == 0.0 && p.ctx.est_acc.dot(&p.normal).abs() > 50.0)
    {
        v.push(Lever::NormalAcceleration);
    }
    let radii: std::collections::BTreeSet<i64> = ds
        .features
        .iter()
        .filter(|(_, f)| f.kind != FeatureKind::Face)
        .map(|(_, f)| (f.nominal_diameter_mm * 10.0).round() as i64)
        .collect();
    if radii.len() > 1 {
        v.push(Lever::Radius);
    }
    let speeds: std::collections::BTreeSet<i64> =
        ds.points.iter().map(|p| p.speed.round() as i64).collect();
    if speeds.len() > 2 {
        v.push(Lever::Speed);
    }
    if ds.points.iter().any(|p| p.direction > 0) && ds.points.iter().any(|p| p.direction < 0) {
        v.push(Lever::Direction);
    }
    if ds.features.len() > 1 {
        v.push(Lever::Position);
    }
    if temperature_range(ds) > 0.5 {
        v.push(Lever::Temperature);
    }
    let d: Vec<f64> = ds.points.iter().map(|p| p.ctx.deflection.norm()).collect();
    if d.iter().cloned().fold(f64::MIN, f64::max) - d.iter().cloned().fold(f64::MAX, f64::min) > 0.1
    {
        v.push(Lever::Deflection);
    }
    let tips: std::collections::BTreeSet<(u32, i64)> = ds
        .points
        .iter()
        .map(|p| (p.ctx.tip_id, p.ctx.head_a1_deg.round() as i64))
        .collect();
    if tips.len() > 1 {
        v.push(Lever::Stylus);
    }
    v
}

/// Range of the first temperature sensor over the points, K (0 without readings).
fn temperature_range(ds: &Dataset) -> f64 {
    let t: Vec<f64> = ds
        .points
        .iter()
        .filter(|p| p.ctx.temps_valid & 1 != 0)
        .map(|p| p.ctx.temps[0])
        .collect();
    if t.is_empty() {
        return 0.0;
    }
    t.iter().cloned().fold(f64::MIN, f64::max) - t.iter().cloned().fold(f64::MAX, f64::min)
}

/// The positions a campaign measured, in words: how many distinct artifact centres and the
/// span of the centres along each axis (a rigid body of order k needs k + 1 distinct
/// positions along each axis it depends on, spread over the travel).
fn positions_text(ds: &Dataset) -> String {
    let mut centres: Vec<[f64; 3]> = vec![];
    for (_, f) in &ds.features {
        let c = f.nominal_center;
        if !centres
            .iter()
            .any(|o| (0..3).all(|i| (o[i] - c[i]).abs() < 1.0))
        {
            centres.push(c);
        }
    }
    let span = |i: usize| {
        let lo = centres.iter().map(|c| c[i]).fold(f64::MAX, f64::min);
        let hi = centres.iter().map(|c| c[i]).fold(f64::MIN, f64::max);
        hi - lo
    };
    let axes: Vec<&str> = (0..3)
        .filter(|&i| span(i) < 100.0)
        .map(|i| ["x", "y", "z"][i])
        .collect();
    let unvaried = if axes.is_empty() {
        String::new()
    } else {
        format!(", none apart by 100 mm along {}", axes.join(", "))
    };
    format!(
        "this campaign has {} artifact position(s), their centres spanning {:.0} × {:.0} × {:.0} mm{unvaried}; an effect of order k in position needs k + 1 positions apart along each axis it depends on, spread over the travel",
        centres.len(),
        span(0),
        span(1),
        span(2)
    )
}

/// Measurements that would separate `a` from `b`: the levers one responds to and the other
/// does not. A lever the campaign already has (`cov`) did not separate them: it is named
/// ("more …") only when no lever the campaign lacks would.
fn separating(a: &str, b: &str, cov: &[Lever], ds: &Dataset) -> Vec<String> {
    let (ka, kb) = (
        a.split(':').next().unwrap_or(a),
        b.split(':').next().unwrap_or(b),
    );
    let (la, lb) = (levers(ka), levers(kb));
    let positions = positions_text(ds);
    let mut apart: Vec<(Lever, &str, &str)> = vec![];
    for l in la.iter().filter(|l| !lb.contains(l)) {
        apart.push((*l, ka, kb));
    }
    for l in lb.iter().filter(|l| !la.contains(l)) {
        apart.push((*l, kb, ka));
    }
    let missing = apart.iter().any(|(l, _, _)| !cov.contains(l));
    let mut out: Vec<String> = apart
        .iter()
        .filter(|(l, _, _)| !(missing && cov.contains(l)))
        .map(|(l, x, y)| lever_text(*l, x, y, cov.contains(l), &positions))
        .collect();
    if [ka, kb].contains(&"guide_straightness") {
        // A measurement outside the artifacts' scans determines the guide on its own.
        out.push(
            "the guide measured on its own by error separation (`scancorr calibrate \
             straightness`: distance probes stepped along the travel, no perfect straightedge \
             needed): its straightness and yaw without the artifacts' scans"
                .into(),
        );
    }
    if out.is_empty() {
        out.push(format!("{ka} and {kb} respond to the same measurements; a custom effect that combines them may be the honest model"));
    }
    out
}

/// The candidate model of a move: which blocks are fitted and removed, given the model's
/// blocks `0..n_model` and the move's own block.
fn spec_of(c: &Candidate, model: &[EffectConfig], block: Option<usize>, held: &[usize]) -> Spec {
    let out = c
        .replaces
        .as_ref()
        .and_then(|id| model.iter().position(|e| &e.id() == id));
    let mut fitted: Vec<usize> = (0..model.len())
        .filter(|i| Some(*i) != out && !held.contains(i))
        .collect();
    if let Some(b) = block {
        fitted.push(b);
    }
    Spec {
        fitted,
        removed: out.into_iter().collect(),
    }
}

/// Scored moves on one dataset.
struct Scored {
    space: Space,
    base_spec: Spec,
    base: Score,
    /// (candidate, its block, spec, score)
    moves: Vec<(Candidate, Option<usize>, Spec, Score)>,
    skipped: Vec<String>,
}

fn score_moves(ds: &Dataset, prep: &Prepared, cands: Vec<Candidate>) -> Result<Scored, LabError> {
    let model = &ds.calibration.effects;
    let mut blocks: Vec<(String, EffectConfig, bool)> =
        model.iter().map(|e| (e.id(), e.clone(), true)).collect();
    let mut kept = vec![];
    let mut skipped = vec![];
    let t_range = temperature_range(ds);
    // Model effects this data cannot determine (an expansion at one temperature) are kept as
    // they are: neither refitted (they would absorb other effects) nor dropped or swapped.
    let held: Vec<usize> = model
        .iter()
        .enumerate()
        .filter(|(_, e)| matches!(e.kind(), "stylus_thermal" | "scale_thermal") && t_range <= 0.5)
        .map(|(i, _)| i)
        .collect();
    for c in cands {
        if let Some(r) = &c.replaces {
            if let Some(i) = model.iter().position(|e| &e.id() == r) {
                if held.contains(&i) {
                    skipped.push(format!(
                        "{} {r}: kept as it is — the campaign has one temperature (range {t_range:.2} K) and cannot determine it",
                        if c.action == Move::Drop { "dropping" } else { "swapping" }
                    ));
                    continue;
                }
            }
        }
        if let Some(cfg) = &c.config {
            if matches!(cfg.kind(), "stylus_thermal" | "scale_thermal") && t_range <= 0.5 {
                skipped.push(format!(
                    "{}: the campaign has one temperature (range {t_range:.2} K): it cannot determine an expansion — measure across a temperature change of a few kelvin",
                    c.effect
                ));
                continue;
            }
        }
        let block = match &c.config {
            Some(cfg) => {
                let mut sensors = ds.sensors.clone();
                match cfg.build(&mut sensors) {
                    Err(e) => {
                        skipped.push(format!("{}: {e}", c.effect));
                        continue;
                    }
                    Ok(_) if sensors.names().len() != ds.sensors.names().len() => {
                        skipped.push(format!(
                            "{}: the bags have no readings of temperature sensor(s) {:?}: record them",
                            c.effect,
                            &sensors.names()[ds.sensors.names().len()..]
                        ));
                        continue;
                    }
                    Ok(_) => {}
                }
                blocks.push((c.effect.clone(), cfg.clone(), false));
                Some(blocks.len() - 1)
            }
            None => None,
        };
        kept.push((c, block));
    }
    let space = Space::build(ds, prep, blocks)?;
    let base_spec = Spec {
        fitted: (0..model.len()).filter(|i| !held.contains(i)).collect(),
        removed: vec![],
    };
    let base = space.score(&base_spec);
    let moves = kept
        .into_iter()
        .map(|(c, b)| {
            let spec = spec_of(&c, model, b, &held);
            let score = space.score(&spec);
            (c, b, spec, score)
        })
        .collect();
    Ok(Scored {
        space,
        base_spec,
        base,
        moves,
        skipped,
    })
}

/// The model after a move, in the model's order (a swap in place, an addition at the end).
fn model_after(model: &[EffectConfig], spec: &Spec, fitted: &[EffectConfig]) -> Vec<EffectConfig> {
    let mut out: Vec<EffectConfig> = vec![];
    let mut by_block: std::collections::BTreeMap<usize, EffectConfig> = spec
        .fitted
        .iter()
        .zip(fitted)
        .map(|(b, c)| (*b, c.clone()))
        .collect();
    for (i, _) in model.iter().enumerate() {
        if spec.removed.contains(&i) {
            // A swap takes the place of the effect it replaces.
            if let Some((&b, _)) = by_block.iter().find(|(b, _)| **b >= model.len()) {
                out.push(by_block.remove(&b).expect("present"));
            }
        } else if let Some(c) = by_block.remove(&i) {
            out.push(c);
        } else {
            // Held as it is (not determined by this data).
            out.push(model[i].clone());
        }
    }
    out.extend(by_block.into_values());
    out
}

/// The change a fitted move makes to the correction along the normal, per point.
fn move_prediction(
    ds: &Dataset,
    prep: &Prepared,
    space: &Space,
    spec: &Spec,
    o: &FitOutcome,
    only_new: bool,
) -> Result<Vec<f64>, LabError> {
    let mut pairs = vec![];
    for (b, after) in spec.fitted.iter().zip(&o.configs) {
        let blk = &space.blocks[*b];
        if only_new && blk.in_model {
            continue;
        }
        pairs.push((after.clone(), super::select::delta(&blk.config, after)));
    }
    if !only_new {
        for &r in &spec.removed {
            let c = &space.blocks[r].config;
            pairs.push((c.clone(), c.params().iter().map(|v| -v).collect()));
        }
    }
    predicted(ds, prep, &pairs)
}

/// What a move made: the new model (every effect refitted) and the fit.
#[derive(Debug, Clone)]
pub struct Applied {
    /// The candidate applied.
    pub candidate: Candidate,
    /// The model's effects after the move.
    pub effects: Vec<EffectConfig>,
    /// The fit.
    pub outcome: FitOutcome,
    /// When the data alone could not choose the move (a near-tie with another): why, and
    /// what measurement would choose.
    pub advice: Vec<String>,
}

/// Makes the best of `cands` (by cross-validated error) on the dataset's model: adds, swaps or
/// drops it and refits every effect (or, with `only_new`, fits only the new effect). This is
/// what `lab add` / `lab remove` do and each step of `lab discover`.
pub fn apply(ds: &Dataset, cands: Vec<Candidate>, only_new: bool) -> Result<Applied, LabError> {
    let prep = prepare(ds)?;
    let model = &ds.calibration.effects;
    let sc = score_moves(ds, &prep, cands)?;
    let base_held = sc
        .space
        .fit(&prep, &sc.base_spec, &sc.base, &sc.base)?
        .heldout_rms_after_um;
    let mut ranked = vec![];
    for (c, b, spec, score) in sc.moves {
        let o = sc.space.fit(&prep, &spec, &score, &sc.base)?;
        let sig = significant(
            &c.action,
            &sc.base,
            &score,
            &o,
            base_held,
            ds.noise_floor_um,
        );
        let key = rank_key(&sc.base, &score, &o, base_held);
        ranked.push(((sig, key, o.delta_bic), c, b, spec, score));
    }
    // The same order as `diagnose`'s, so `lab add KIND` makes the variant it ranks first.
    ranked.sort_by(|a, b| {
        rank_order(
            &RankItem {
                significant: a.0 .0,
                key: a.0 .1,
                delta_bic: a.0 .2,
                k: a.4.k,
                name: &a.1.effect,
                replaces: a.1.replaces.as_deref(),
            },
            &RankItem {
                significant: b.0 .0,
                key: b.0 .1,
                delta_bic: b.0 .2,
                k: b.4.k,
                name: &b.1.effect,
                replaces: b.1.replaces.as_deref(),
            },
        )
    });
    let advice = choice_advice(ds, &prep, &ranked);
    let Some((_, c, b, spec, score)) = ranked.into_iter().next() else {
        return Err(LabError::Data(match sc.skipped.first() {
            Some(s) => s.clone(),
            None => "nothing to add".into(),
        }));
    };
    let spec = if only_new {
        Spec {
            fitted: b.into_iter().collect(),
            removed: spec.removed,
        }
    } else {
        spec
    };
    let score = if only_new {
        sc.space.score(&spec)
    } else {
        score
    };
    let o = sc.space.fit(&prep, &spec, &score, &sc.base)?;
    let effects = if only_new {
        let mut m: Vec<EffectConfig> = model
            .iter()
            .enumerate()
            .filter(|(i, _)| !spec.removed.contains(i))
            .map(|(_, e)| e.clone())
            .collect();
        m.extend(o.configs.iter().cloned());
        m
    } else {
        model_after(model, &spec, &o.configs)
    };
    Ok(Applied {
        candidate: c,
        effects,
        outcome: o,
        advice,
    })
}

/// When the first two of `ranked` (best first) are different moves that the data scores
/// within a near-tie (the cross-validated error within 1 % and the significance the same),
/// the choice between them is not the data's: say so, and what would decide it — held-out
/// data at another position when there is none, or the separating measurements.
#[allow(clippy::type_complexity)]
fn choice_advice(
    ds: &Dataset,
    prep: &Prepared,
    ranked: &[((bool, f64, f64), Candidate, Option<usize>, Spec, Score)],
) -> Vec<String> {
    let [first, second, ..] = ranked else {
        return vec![];
    };
    let (a, b) = (&first.4, &second.4);
    let near =
        first.0 .0 == second.0 .0 && a.cv_ss > 0.0 && (b.cv_ss - a.cv_ss).abs() <= 0.01 * a.cv_ss;
    if !near {
        return vec![];
    }
    let independent = prep.held_mask.iter().any(|h| *h) && {
        let bags_fit: std::collections::BTreeSet<usize> = ds
            .points
            .iter()
            .zip(&prep.fit_mask)
            .filter(|(_, m)| **m)
            .map(|(p, _)| p.bag)
            .collect();
        !ds.points
            .iter()
            .zip(&prep.held_mask)
            .any(|(p, m)| *m && bags_fit.contains(&p.bag))
    };
    let mut v = vec![format!(
        "`{}` and `{}` predict the other scans equally well (cross-validated {:.3} vs {:.3} µm): this data does not choose between them",
        first.1.effect,
        second.1.effect,
        a.rms_um(),
        b.rms_um()
    )];
    if independent {
        v.push(format!(
            "the held-out bags chose `{}`; to confirm, measure what separates them: {}",
            first.1.effect,
            separating(&first.1.effect, &second.1.effect, &coverage(ds), ds).join("; ")
        ));
    } else {
        v.push(
            "held-out data is needed to choose: measure the artifact at another position in the volume (another run, e.g. a ring at speeds elsewhere on the table) and pass it with --validate".into(),
        );
    }
    v
}

/// Diagnoses the residual of the dataset's calibration: tries every library effect not in the
/// model (all variants), every other variant of the effects in it, and dropping each; each
/// candidate model is refitted as a whole and ranked by its cross-validated error (see
/// [`super::select`]), the information criterion breaking near-ties.
pub fn diagnose(ds: &Dataset) -> Result<Diagnosis, LabError> {
    let mut dg = diagnose_deferred(ds)?;
    fill_unexplained(ds, &mut dg)?;
    Ok(dg)
}

/// [`diagnose`] with the structure search (the costliest part: a periodogram per axis) left
/// for [`fill_unexplained`]: `unexplained` is empty until then. `lab discover` runs it only
/// when no library move is taken (the same search on the same residual, so the same result).
pub fn diagnose_deferred(ds: &Dataset) -> Result<Diagnosis, LabError> {
    let prep = prepare(ds)?;
    let noise = ds.noise_floor_um;
    let model = ds.calibration.effects.clone();
    let sc = score_moves(ds, &prep, moves(ds, &model))?;
    let mut results = vec![];
    let base_o = sc.space.fit(&prep, &sc.base_spec, &sc.base, &sc.base)?;
    let base_held = base_o.heldout_rms_after_um;
    for (c, b, spec, score) in &sc.moves {
        let o = sc.space.fit(&prep, spec, score, &sc.base)?;
        let sig = significant(&c.action, &sc.base, score, &o, base_held, noise);
        results.push((c.clone(), *b, spec.clone(), score.clone(), o, sig));
    }
    results.sort_by(|a, b| {
        let item = |r: &(Candidate, Option<usize>, Spec, Score, FitOutcome, bool)| {
            (
                rank_key(&sc.base, &r.3, &r.4, base_held),
                r.4.delta_bic,
                r.3.k,
                r.5,
            )
        };
        let (ia, ib) = (item(a), item(b));
        rank_order(
            &RankItem {
                significant: ia.3,
                key: ia.0,
                delta_bic: ia.1,
                k: ia.2,
                name: &a.0.effect,
                replaces: a.0.replaces.as_deref(),
            },
            &RankItem {
                significant: ib.3,
                key: ib.0,
                delta_bic: ib.1,
                k: ib.2,
                name: &b.0.effect,
                replaces: b.0.replaces.as_deref(),
            },
        )
    });
    // Confounding: the best addition against additions of other kinds that explain nearly as
    // much, each judged by its own correction.
    let mut confounded = vec![];
    let cov = coverage(ds);
    if let Some((bc, _, bspec, _, bo, true)) = results.first() {
        if bc.action != Move::Drop {
            let best_pred = move_prediction(ds, &prep, &sc.space, bspec, bo, true)?;
            let best_cfg = bc.config.clone().expect("an addition has a config");
            let mut seen = std::collections::BTreeSet::new();
            for (c, _, spec, _, o, _) in results.iter().skip(1) {
                let Some(cfg) = &c.config else { continue };
                if cfg.kind() == best_cfg.kind()
                    || c.action != Move::Add
                    || !seen.insert(cfg.kind())
                    || o.explained < 0.5 * bo.explained
                {
                    continue;
                }
                let pred = move_prediction(ds, &prep, &sc.space, spec, o, true)?;
                let r_ab = r2_explains(ds, &prep, &best_pred, cfg)?;
                let r_ba = r2_explains(ds, &prep, &pred, &best_cfg)?;
                if r_ab > 0.8 && r_ba > 0.8 {
                    confounded.push(Confounded {
                        effects: [bc.effect.clone(), c.effect.clone()],
                        r2: [r_ab, r_ba],
                        separate_by: separating(&bc.effect, &c.effect, &cov, ds),
                    });
                }
            }
        }
    }
    // Structure: in the residual the best move leaves (or the refitted model's).
    let (left_spec, left_o, left_cv) = match results.first() {
        Some((c, _, spec, score, o, true)) if c.action != Move::Drop => {
            (spec.clone(), o.clone(), score.rms_um())
        }
        _ => {
            let o = sc.space.fit(&prep, &sc.base_spec, &sc.base, &sc.base)?;
            (sc.base_spec.clone(), o, sc.base.rms_um())
        }
    };
    let left_residual = if left_cv < 1.5 * noise.max(0.01) {
        None
    } else {
        let pred = move_prediction(ds, &prep, &sc.space, &left_spec, &left_o, false)?;
        let resid: Vec<f64> = prep
            .art
            .residual
            .iter()
            .zip(&pred)
            .map(|(e, d)| e + d)
            .collect();
        Some(resid)
    };
    // The best candidate's predicted residual, drawn over the measured one.
    let prediction = match results.first() {
        Some((c, _, spec, _, o, _)) => {
            let pred = move_prediction(ds, &prep, &sc.space, spec, o, false)?;
            let um = |d: Option<&[f64]>| -> Vec<f64> {
                prep.art
                    .residual
                    .iter()
                    .enumerate()
                    .map(|(i, e)| (e + d.map_or(0.0, |d| d[i])) * 1e3)
                    .collect()
            };
            let measured = super::traces::traces(ds, &um(None));
            (!measured.is_empty()).then(|| Prediction {
                effect: c.effect.clone(),
                action: c.action.clone(),
                measured,
                predicted: super::traces::traces(ds, &um(Some(&pred))),
            })
        }
        None => None,
    };
    let model_spread = model_spreads(&base_o, &sc.base, &results, noise);
    let npts = [
        prep.fit_mask.iter().filter(|m| **m).count(),
        prep.held_mask.iter().filter(|m| **m).count(),
    ];
    Ok(Diagnosis {
        rms_um: prep.rms_fit_um,
        cv_rms_um: sc.base.rms_um(),
        heldout_rms_um: prep.rms_held_um,
        noise_floor_um: noise,
        candidates: results
            .into_iter()
            .map(|(c, b, spec, score, o, sig)| CandidateReport {
                action: c.action,
                significant: sig,
                effect: c.effect,
                replaces: c.replaces,
                explained: if sc.base.cv_ss > 0.0 {
                    (sc.base.cv_ss - score.cv_ss) / sc.base.cv_ss
                } else {
                    0.0
                },
                cv_rms_before_um: sc.base.rms_um(),
                cv_rms_after_um: score.rms_um(),
                rms_before_um: o.rms_before_um,
                rms_after_um: o.rms_after_um,
                heldout_rms_before_um: o.heldout_rms_before_um,
                heldout_rms_after_um: o.heldout_rms_after_um,
                delta_bic: o.delta_bic,
                k: o.k,
                // The parameters of the effect brought in (the others are refitted too).
                params: spec
                    .fitted
                    .iter()
                    .position(|x| Some(*x) == b)
                    .and_then(|i| o.params.get(i).cloned())
                    .unwrap_or_default(),
                unidentifiable: o.unidentifiable,
            })
            .collect(),
        confounded,
        unexplained: vec![],
        left_residual,
        points: npts,
        skipped: sc.skipped,
        prediction,
        model_spread,
    })
}

/// What the choice of model moves on `ds` (its calibration's effects refitted as they are):
/// [`Diagnosis::model_spread`] without the rest of a diagnosis — only the moves this data
/// scores near-equal (see [`near_equal`]) are fitted. For `lab add`, whose σ carries it as
/// `lab discover`'s does ([`widen_by_alternatives`]).
pub fn model_spread(ds: &Dataset) -> Result<Vec<ModelSpread>, LabError> {
    let prep = prepare(ds)?;
    let noise = ds.noise_floor_um;
    let model = ds.calibration.effects.clone();
    let sc = score_moves(ds, &prep, moves(ds, &model))?;
    let base_o = sc.space.fit(&prep, &sc.base_spec, &sc.base, &sc.base)?;
    let mut results = vec![];
    for (c, b, spec, score) in &sc.moves {
        if !near_equal(&sc.base, score, noise) {
            continue;
        }
        let o = sc.space.fit(&prep, spec, score, &sc.base)?;
        results.push((c.clone(), *b, spec.clone(), score.clone(), o, false));
    }
    Ok(model_spreads(&base_o, &sc.base, &results, noise))
}

/// Runs the structure search [`diagnose_deferred`] left (nothing when it was run or when the
/// residual is within 1.5× the noise floor): fills `dg.unexplained`.
pub fn fill_unexplained(ds: &Dataset, dg: &mut Diagnosis) -> Result<(), LabError> {
    if let Some(resid) = dg.left_residual.take() {
        let prep = prepare(ds)?;
        dg.unexplained = super::structure::structure(ds, &prep, &resid)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lab::dataset::Samples;
    use crate::sample::{CommandSample, Sample};

    /// The arc is taken out of every command, and nothing else changes.
    #[test]
    fn without_arcs_keeps_everything_but_the_arc() {
        let pos = Vec3::new(1.0, 2.0, 3.0);
        let bag: Vec<Sample> = vec![Sample::Command(CommandSample {
            seq: 3,
            t_ns: 7,
            pos,
            arc_center: Vec3::new(4.0, 5.0, 6.0),
            arc_radius: 25.0,
            segment_id: 9,
        })];
        let w = WithoutArcs(std::sync::Arc::new(bag));
        let mut seen = vec![];
        w.replay(&mut |s| seen.push(s)).unwrap();
        assert_eq!(seen.len(), 1);
        let Sample::Command(d) = &seen[0] else {
            panic!("not a command")
        };
        assert_eq!(d.arc_radius, 0.0);
        assert_eq!(d.arc_center, Vec3::zeros());
        assert_eq!((d.seq, d.t_ns, d.pos, d.segment_id), (3, 7, pos, 9));
    }
}
