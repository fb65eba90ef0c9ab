//! Compare, diagnose and add: the lab's questions answered on a [`Dataset`].

use super::dataset::Dataset;
use super::fit::{fit_artifacts, nuisance_row, ArtifactFit, Normal};
use super::program::FeatureKind;
use super::select::{predicted, Score, Space, Spec};
use super::LabError;
use crate::effects::{self as fx, Effect, EffectConfig};
use crate::sample::{Axis, Vec3};
use serde::Serialize;

/// The dataset prepared for fitting: artifact fit, masks, baseline figures.
#[derive(Debug, Clone)]
pub struct Prepared {
    /// Artifact fit on all points.
    pub art: ArtifactFit,
    /// Points used for fitting.
    pub fit_mask: Vec<bool>,
    /// Held-out points.
    pub held_mask: Vec<bool>,
    /// Residual RMS on the fit set after refitting placements, µm.
    pub rms_fit_um: f64,
    /// Same on the held-out set (its own placements), µm.
    pub rms_held_um: f64,
    /// Lag-1 autocorrelation of the residuals (for the effective number of points).
    pub rho: f64,
}

fn nuisance_ss(ds: &Dataset, art: &ArtifactFit, y: &[f64], mask: &[bool]) -> (f64, usize) {
    let mut ne = Normal::new(art.n_cols);
    let mut row = vec![];
    for (i, p) in ds.points.iter().enumerate() {
        if mask[i] && art.features[p.feature].is_some() {
            nuisance_row(art, p, &p.surface, &mut row);
            ne.add(&[], &row, y[i]);
        }
    }
    let n = ne.n;
    if n == 0 {
        return (0.0, 0);
    }
    (ne.solve().ss, n)
}

fn rms_um(ss: f64, n: usize) -> f64 {
    if n == 0 {
        0.0
    } else {
        (ss / n as f64).sqrt() * 1e3
    }
}

/// Fits the artifacts and the baseline.
pub fn prepare(ds: &Dataset) -> Result<Prepared, LabError> {
    let surfaces: Vec<Vec3> = ds.points.iter().map(|p| p.surface).collect();
    let all = vec![true; ds.points.len()];
    let art = fit_artifacts(ds, &surfaces, &all);
    if art.features.iter().all(|f| f.is_none()) {
        return Err(LabError::Data(
            "no artifact could be fitted: a circle needs at least 3 points around its circumference, a face 3 points along it".into(),
        ));
    }
    let fit_mask: Vec<bool> = ds
        .points
        .iter()
        .map(|p| !p.held_out && art.features[p.feature].is_some())
        .collect();
    let held_mask: Vec<bool> = ds
        .points
        .iter()
        .map(|p| p.held_out && art.features[p.feature].is_some())
        .collect();
    if fit_mask.iter().filter(|m| **m).count() < 50 {
        return Err(LabError::Data("too few points to fit (fewer than 50 scan points in contact): scan the artifact longer".into()));
    }
    let (ssf, nf) = nuisance_ss(ds, &art, &art.residual, &fit_mask);
    let (ssh, nh) = nuisance_ss(ds, &art, &art.residual, &held_mask);
    let mut num = 0.0;
    let mut den = 0.0;
    for i in 1..ds.points.len() {
        if ds.points[i].segment == ds.points[i - 1].segment
            && ds.points[i].bag == ds.points[i - 1].bag
        {
            num += art.residual[i] * art.residual[i - 1];
            den += art.residual[i] * art.residual[i];
        }
    }
    let rho = if den > 0.0 {
        (num / den).clamp(0.0, 0.99)
    } else {
        0.0
    };
    Ok(Prepared {
        art,
        fit_mask,
        held_mask,
        rms_fit_um: rms_um(ssf, nf),
        rms_held_um: rms_um(ssh, nh),
        rho,
    })
}

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

/// A fitted parameter.
///
/// `sigma` is honest about what moved the value: σ² = max(σ_stat², spread²) + shift², with
/// σ_stat from the penalised normal matrix (scaled by the residual, inflated for correlated
/// residuals), spread half the difference of the two folds' own fits (a second estimate of
/// the statistical part that sees model error), and shift the change the penalties (ridge,
/// smoothness) make against the least-penalised fit of their ladders — a ridge estimator's
/// covariance omits its bias. A parameter the data does not determine has no σ and is
/// listed in `unidentifiable`.
#[derive(Debug, Clone, Serialize)]
pub struct Param {
    /// Name with unit.
    pub name: String,
    /// Value.
    pub value: f64,
    /// Standard uncertainty (see above); absent when not identifiable.
    pub sigma: Option<f64>,
    /// Its statistical part from the normal matrix alone.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sigma_stat: Option<f64>,
    /// |value − least-penalised value| (when a penalty above the ladders' least was used).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub penalty_shift: Option<f64>,
    /// Half the difference of the two folds' fits.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub fold_spread: Option<f64>,
    /// What determines it, when not the data alone: a penalty, only its correlation with
    /// other parameters, or nothing (not determined).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub note: Option<String>,
}

/// The fitted parameters of one effect.
#[derive(Debug, Clone, Serialize)]
pub struct EffectParams {
    /// The effect's id.
    pub effect: String,
    /// Its parameters, in the effect's order.
    pub params: Vec<Param>,
}

/// The outcome of fitting some effects' parameters jointly with the artifact placements.
#[derive(Debug, Clone, Serialize)]
pub struct FitOutcome {
    /// Fitted configs (parameters = current + fitted change).
    #[serde(skip)]
    pub configs: Vec<EffectConfig>,
    /// Parameters of each config.
    pub params: Vec<Vec<Param>>,
    /// Parameters this data cannot determine (given the minimum-norm value).
    pub unidentifiable: Vec<String>,
    /// Number of fitted parameters.
    pub k: usize,
    /// RMS on the fit set before and after, µm.
    pub rms_before_um: f64,
    /// After.
    pub rms_after_um: f64,
    /// RMS on held-out data before and after (placements refitted there), µm.
    pub heldout_rms_before_um: f64,
    /// After.
    pub heldout_rms_after_um: f64,
    /// Fraction of the held-out residual's sum of squares explained.
    pub explained: f64,
    /// RMS of the residual component removed on held-out data, µm.
    pub explained_component_um: f64,
    /// Cross-validated RMS (alternate scans predicted from the others) before, µm.
    pub cv_rms_before_um: f64,
    /// After.
    pub cv_rms_after_um: f64,
    /// Change of the Bayesian information criterion on the fit set (negative: better).
    pub delta_bic: f64,
    /// Fitted correction per point (for confounding checks), projected on the normal.
    #[serde(skip)]
    pub predicted: Vec<f64>,
}

/// Fits the parameters of `configs` (their current values are the starting point; the
/// change is fitted) jointly with the artifact placements, every effect refitted, tables
/// smoothed as cross-validation chooses. `configs` are the model's effects (already in the
/// data) and possibly new ones with zero parameters.
pub fn fit_effects(
    ds: &Dataset,
    prep: &Prepared,
    configs: &[EffectConfig],
) -> Result<FitOutcome, LabError> {
    let space = Space::build(
        ds,
        prep,
        configs.iter().map(|c| (c.id(), c.clone(), true)).collect(),
    )?;
    let spec = Spec {
        fitted: (0..configs.len()).collect(),
        removed: vec![],
    };
    let base = space.score(&Spec::default());
    let score = space.score(&spec);
    let mut o = space.fit(prep, &spec, &score, &base)?;
    let pairs: Vec<(EffectConfig, Vec<f64>)> = configs
        .iter()
        .zip(&o.configs)
        .map(|(b, a)| (a.clone(), delta(b, a)))
        .collect();
    o.predicted = predicted(ds, prep, &pairs)?;
    Ok(o)
}

impl FitOutcome {
    /// The parameters of each fitted effect, by id.
    pub fn by_effect(&self) -> Vec<EffectParams> {
        self.configs
            .iter()
            .zip(&self.params)
            .map(|(c, p)| EffectParams {
                effect: c.id(),
                params: p.clone(),
            })
            .collect()
    }
}

fn delta(before: &EffectConfig, after: &EffectConfig) -> Vec<f64> {
    after
        .params()
        .iter()
        .zip(before.params())
        .map(|(a, b)| a - b)
        .collect()
}

/// A change to the model: what `lab diagnose` proposes and `lab add` / `lab remove` make.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Move {
    /// Add a library effect (with variant).
    Add,
    /// Replace a model effect (by id) with another variant.
    Swap,
    /// Take a model effect (by id) out.
    Drop,
}

/// A candidate move with the configuration it brings in.
#[derive(Debug, Clone)]
pub struct Candidate {
    /// The move.
    pub action: Move,
    /// The effect brought in (name with variant) or dropped (id).
    pub effect: String,
    /// The model effect replaced or dropped (its id).
    pub replaces: Option<String>,
    /// The configuration brought in (zero parameters); none for a drop.
    pub config: Option<EffectConfig>,
}

/// The candidate effects of the library not in the calibration, with their variants.
pub fn library_candidates(ds: &Dataset) -> Vec<(String, EffectConfig)> {
    moves(ds, &ds.calibration.effects)
        .into_iter()
        .filter(|c| c.action == Move::Add)
        .filter_map(|c| c.config.map(|cfg| (c.effect, cfg)))
        .collect()
}

/// The variant of a config, by its configuration: the kind and the options that change what
/// it models (a guide's axis, the axis its angular term turns about and which tables it has; a
/// rigid body's chain, order, spline or polynomial and its errors; for every other kind its
/// parameters' names, which spell its order, split, per-tip and powers), never its values nor
/// sizes that follow the data's span (a table's knots). Parameter names alone do not say
/// which axis a guide's pitch turns about, so `about=y` and `about=z` looked alike.
pub fn variant_key(c: &EffectConfig) -> String {
    match c {
        EffectConfig::GuideStraightness(g) => {
            let about = g.pitch_about.unwrap_or(match g.axis {
                Axis::X => Axis::Y,
                Axis::Y => Axis::X,
                Axis::Z => Axis::Y,
            });
            let tables: Vec<&str> = g.straightness.keys().map(|a| a.name()).collect();
            format!(
                "guide_straightness:axis={},straightness={},{}",
                g.axis.name(),
                tables.join("+"),
                if g.pitch_rad.is_some() {
                    format!("about={}", about.name())
                } else {
                    "no pitch".into()
                }
            )
        }
        EffectConfig::RigidBody(r) => {
            let errors: Vec<String> = r.errors.keys().map(|e| e.name().to_string()).collect();
            format!(
                "rigid_body:chain={:?},order={},{},errors={}",
                r.chain,
                r.order,
                if r.spline_segments.is_some() {
                    "spline"
                } else {
                    "polynomial"
                },
                errors.join("+")
            )
        }
        _ => format!("{}:{}", c.kind(), c.param_names().join("|")),
    }
}

/// Two configs are the same variant when their [`variant_key`]s agree.
fn same_variant(a: &EffectConfig, b: &EffectConfig) -> bool {
    a.kind() == b.kind() && variant_key(a) == variant_key(b)
}

fn guide_axis(c: &EffectConfig) -> Option<Axis> {
    match c {
        EffectConfig::GuideStraightness(g) => Some(g.axis),
        _ => None,
    }
}

/// Every move the lab considers from `model`: library effects (all variants) not in it,
/// other variants of those in it, and dropping each.
pub fn moves(ds: &Dataset, model: &[EffectConfig]) -> Vec<Candidate> {
    let mut v = vec![];
    for kind in fx::KINDS {
        if kind == "custom" {
            continue;
        }
        let present: Vec<&EffectConfig> = model.iter().filter(|e| e.kind() == kind).collect();
        for name in variants(kind, ds) {
            let Ok(mut cfg) = candidate(&name, ds) else {
                continue;
            };
            // Guides of different axes are different effects; every other kind is one.
            let same: Vec<&&EffectConfig> = present
                .iter()
                .filter(|e| guide_axis(e) == guide_axis(&cfg))
                .collect();
            match same.first() {
                None => {
                    if !present.is_empty() {
                        if let Some(a) = guide_axis(&cfg) {
                            cfg.set_id(Some(format!("guide_straightness_{}", a.name())));
                        }
                    }
                    if model.iter().any(|e| e.id() == cfg.id()) {
                        continue;
                    }
                    v.push(Candidate {
                        action: Move::Add,
                        effect: name,
                        replaces: None,
                        config: Some(cfg),
                    });
                }
                Some(e) if !same_variant(e, &cfg) => {
                    let id = e.id();
                    cfg.set_id((id != cfg.kind()).then(|| id.clone()));
                    v.push(Candidate {
                        action: Move::Swap,
                        effect: name,
                        replaces: Some(id),
                        config: Some(cfg),
                    });
                }
                Some(_) => {}
            }
        }
    }
    for e in model {
        v.push(Candidate {
            action: Move::Drop,
            effect: e.id(),
            replaces: Some(e.id()),
            config: None,
        });
    }
    v
}

fn tips(ds: &Dataset) -> Vec<u32> {
    let t: std::collections::BTreeSet<u32> = ds.points.iter().map(|p| p.ctx.tip_id).collect();
    t.into_iter().collect()
}

fn variants(kind: &str, ds: &Dataset) -> Vec<String> {
    let several_tips = tips(ds).len() > 1;
    let mut v: Vec<String> = match kind {
        "accel_deflection" => vec![
            "accel_deflection".into(),
            "accel_deflection:full".into(),
            "accel_deflection:full,order=1".into(),
        ],
        "servo_gain" => vec!["servo_gain".into(), "servo_gain:powers=1+2".into()],
        "servo_phase" => vec![
            "servo_phase".into(),
            "servo_phase:static".into(),
            "servo_phase:static,direction".into(),
        ],
        "stylus_thermal" => vec!["stylus_thermal".into(), "stylus_thermal:split".into()],
        "probe_force" => vec!["probe_force".into()],
        "guide_straightness" => Axis::ALL
            .iter()
            .filter(|a| axis_span(ds, **a).1 - axis_span(ds, **a).0 > 100.0)
            .flat_map(|a| {
                Axis::ALL
                    .iter()
                    .filter(|r| *r != a)
                    .map(|r| format!("guide_straightness:axis={},about={}", a.name(), r.name()))
                    .collect::<Vec<_>>()
            })
            .collect(),
        "rigid_body" => vec![
            "rigid_body:order=2".into(),
            "rigid_body:order=3".into(),
            "rigid_body:spline".into(),
        ],
        "probe_lobing" => vec!["probe_lobing".into()],
        k => vec![k.to_string()],
    };
    if several_tips && matches!(kind, "probe_force" | "stylus_thermal") {
        v.push(format!("{kind}:per_tip"));
    }
    v
}

pub(crate) fn axis_span(ds: &Dataset, a: Axis) -> (f64, f64) {
    ds.points.iter().fold((f64::MAX, f64::MIN), |(lo, hi), p| {
        (
            lo.min(p.ctx.scale[a.index()]),
            hi.max(p.ctx.scale[a.index()]),
        )
    })
}

/// A zero-parameter effect from a candidate name: `kind[:option,option=value…]`.
/// Options: accel_deflection `full`, `order=0|1|2`; servo_gain `powers=1+2`; stylus_thermal
/// `split`, `per_tip`; probe_force `per_tip`; guide_straightness `axis=x|y|z`, `about=x|y|z`
/// (rotation axis of its angular term), `knots=N`; servo_phase `order=0|1`, `static` (the
/// term that keeps its sign with the scan direction), `static,direction` (both); rigid_body
/// `order=1…4`, `spline` (cubic B-spline tables, `step=MM` between knots, default 50),
/// `chain=moving_bridge|fixed_bridge|cantilever|horizontal_arm`; probe_lobing
/// `harmonics=2…8`.
pub fn candidate(name: &str, ds: &Dataset) -> Result<EffectConfig, LabError> {
    let (kind, opts) = name.split_once(':').unwrap_or((name, ""));
    let mut o = std::collections::BTreeMap::new();
    for kv in opts.split(',').filter(|s| !s.is_empty()) {
        let (k, v) = kv.split_once('=').unwrap_or((kv, ""));
        o.insert(k.to_string(), v.to_string());
    }
    let bad = |m: String| LabError::Data(format!("effect `{name}`: {m}"));
    let order = |o: &std::collections::BTreeMap<String, String>| -> Result<u8, LabError> {
        match o.get("order").map(|s| s.as_str()) {
            None => Ok(0),
            Some(s) => s
                .parse::<u8>()
                .ok()
                .filter(|v| *v <= 2)
                .ok_or_else(|| bad("order must be 0, 1 or 2".into())),
        }
    };
    let cfg = match kind {
        "accel_deflection" => EffectConfig::AccelDeflection(fx::accel_deflection::Config::zeros(
            order(&o)?,
            !o.contains_key("full"),
        )),
        "servo_phase" => EffectConfig::ServoPhase(fx::servo_phase::Config::zeros_variant(
            order(&o)?,
            !o.contains_key("static") || o.contains_key("direction"),
            o.contains_key("static"),
        )),
        "servo_gain" => {
            let powers = match o.get("powers") {
                None => vec![2],
                Some(s) => s
                    .split('+')
                    .map(|p| p.parse::<u32>().map_err(|_| bad("powers like 1+2".into())))
                    .collect::<Result<_, _>>()?,
            };
            EffectConfig::ServoGain(fx::servo_gain::Config::zeros(order(&o)?, powers))
        }
        "stylus_thermal" => EffectConfig::StylusThermal(if o.contains_key("per_tip") {
            fx::stylus_thermal::Config::zeros_per_tip(&tips(ds), o.contains_key("split"))
        } else {
            fx::stylus_thermal::Config::zeros(o.contains_key("split"))
        }),
        "scale_thermal" => EffectConfig::ScaleThermal(fx::scale_thermal::Config::zeros()),
        "probe_force" => EffectConfig::ProbeForce(if o.contains_key("per_tip") {
            fx::probe_force::Config::zeros_per_tip(&tips(ds))
        } else {
            fx::probe_force::Config::zeros()
        }),
        "probe_lobing" => {
            let h = match o.get("harmonics") {
                None => 5,
                Some(s) => s
                    .parse::<u8>()
                    .ok()
                    .filter(|h| (2..=8).contains(h))
                    .ok_or_else(|| bad("harmonics must be 2…8".into()))?,
            };
            EffectConfig::ProbeLobing(fx::probe_lobing::Config::zeros(h, 0))
        }
        "rigid_body" => {
            let ord = match o.get("order") {
                None => 2,
                Some(s) => s
                    .parse::<u8>()
                    .ok()
                    .filter(|v| (1..=4).contains(v))
                    .ok_or_else(|| bad("order must be 1…4".into()))?,
            };
            let chain = match o
                .get("chain")
                .map(|s| s.as_str())
                .unwrap_or("moving_bridge")
            {
                "moving_bridge" => fx::rigid_body::Chain::MovingBridge,
                "fixed_bridge" => fx::rigid_body::Chain::FixedBridge,
                "cantilever" => fx::rigid_body::Chain::Cantilever,
                "horizontal_arm" => fx::rigid_body::Chain::HorizontalArm,
                c => {
                    return Err(bad(format!(
                        "chain `{c}` (moving_bridge, fixed_bridge, cantilever, horizontal_arm)"
                    )))
                }
            };
            let ranges = Axis::ALL.map(|a| {
                let (lo, hi) = axis_span(ds, a);
                if hi - lo > 1.0 {
                    [lo.floor(), hi.ceil()]
                } else {
                    [lo.floor() - 1.0, lo.floor() + 1.0]
                }
            });
            if o.contains_key("spline") {
                let step = match o.get("step") {
                    None => 50.0,
                    Some(s) => s
                        .parse::<f64>()
                        .ok()
                        .filter(|v| (5.0..=1000.0).contains(v))
                        .ok_or_else(|| bad("step must be 5…1000 (mm between knots)".into()))?,
                };
                EffectConfig::RigidBody(fx::rigid_body::Config::zeros_spline(chain, ranges, step))
            } else {
                EffectConfig::RigidBody(fx::rigid_body::Config::zeros(chain, ord, ranges))
            }
        }
        "guide_straightness" => {
            let axis = match o.get("axis").map(|s| s.as_str()).unwrap_or("x") {
                "x" => Axis::X,
                "y" => Axis::Y,
                "z" => Axis::Z,
                a => return Err(bad(format!("axis `{a}` (x, y or z)"))),
            };
            let (lo, hi) = axis_span(ds, axis);
            // Not more than 1 mm, or no points at all (the span is then not finite).
            if (hi - lo).partial_cmp(&1.0) != Some(std::cmp::Ordering::Greater) {
                return Err(bad(format!(
                    "the data does not move along {} (scan along the axis' travel)",
                    axis.name()
                )));
            }
            let n = match o.get("knots") {
                Some(s) => s
                    .parse::<usize>()
                    .map_err(|_| bad("knots must be a number".into()))?,
                None => (((hi - lo) / 20.0).round() as usize + 1).clamp(3, 61),
            };
            let mut g = fx::guide_straightness::Config::zeros(axis, lo.floor(), hi.ceil(), n, true);
            if let Some(r) = o.get("about") {
                let r = match r.as_str() {
                    "x" => Axis::X,
                    "y" => Axis::Y,
                    "z" => Axis::Z,
                    r => return Err(bad(format!("about `{r}` (x, y or z)"))),
                };
                if r == axis {
                    return Err(bad(
                        "the angular error turns about an axis other than the moving one".into(),
                    ));
                }
                g.pitch_about = Some(r);
            }
            EffectConfig::GuideStraightness(g)
        }
        "custom" => return Err(bad("a custom effect needs terms (--term AXIS:EXPR)".into())),
        "feature_map" => {
            return Err(LabError::Data(
                "feature_map: a scan's dynamic map is measured, not fitted by the lab: \
                 `scancorr calibrate dynamic-map` (slow and fast scans of the feature at two \
                 deflections, e.g. `scancorr sim --program dynamic-map`)"
                    .into(),
            ))
        }
        "thermal_drift" => {
            return Err(LabError::Data(
                "thermal_drift: its sensors and lags are found from a drift recording (the \
                 displacement of the tool against the part with the structure's temperatures, \
                 over hours), not from artifact scans: `scancorr calibrate thermal-drift`"
                    .into(),
            ))
        }
        k => {
            return Err(LabError::Data(format!(
                "unknown effect `{k}` (known: {})",
                fx::KINDS.join(", ")
            )))
        }
    };
    Ok(cfg)
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

fn lever_text(l: Lever, a: &str, b: &str, covered: bool) -> String {
    let more = if covered { "more " } else { "" };
    let (with, without) = (a, b);
    match l {
        Lever::NormalAcceleration => format!("{more}scans of a face while the machine accelerates along the face's normal, off arcs ({with} responds to acceleration along the measured direction, {without} only on arcs; a straightedge scanned along its length does not show it)"),
        Lever::Radius => format!("{more}circles of another diameter at the same speeds (a smaller ring or a sphere's equator: the rotation frequency v/2πr and the acceleration v²/r scale differently, which separates a term of {without} in f¹ from {with}; a term in f² follows v²/r as {with} does at any diameter, and only the scans of a face accelerated along its normal separate it)"),
        Lever::Speed => format!("scans at {more}other speeds (the effects grow differently with speed)"),
        Lever::Direction => format!("scans in {more}both directions, CW and CCW ({with} changes sign with direction)"),
        Lever::Position => format!("the artifact at {more}other positions in the volume ({with} depends on position)"),
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
    let noise = noise_um.max(0.01) * 1e-3;
    let gain = base.cv_ss - s.cv_ss;
    // Held-out data at another position or run (when given) must not get worse than with the
    // model refitted as it is: an effect that only predicts the alternate scans of the same
    // placements is not kept.
    let held_ok =
        o.heldout_rms_after_um <= 1.01 * base_held_um + 0.02 * noise_um || base_held_um == 0.0;
    match action {
        Move::Add | Move::Swap => {
            gain > 0.0 && (gain / n).sqrt() >= 0.5 * noise && gain >= 0.01 * base.cv_ss && held_ok
        }
        Move::Drop => (gain >= 0.0 || ((-gain) / n).sqrt() < 0.15 * noise) && held_ok,
    }
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

fn separating(a: &str, b: &str, cov: &[Lever]) -> Vec<String> {
    let (ka, kb) = (
        a.split(':').next().unwrap_or(a),
        b.split(':').next().unwrap_or(b),
    );
    let (la, lb) = (levers(ka), levers(kb));
    let mut out = vec![];
    for l in la.iter().filter(|l| !lb.contains(l)) {
        out.push(lever_text(*l, ka, kb, cov.contains(l)));
    }
    for l in lb.iter().filter(|l| !la.contains(l)) {
        out.push(lever_text(*l, kb, ka, cov.contains(l)));
    }
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
        pairs.push((after.clone(), delta(&blk.config, after)));
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
            separating(&first.1.effect, &second.1.effect, &coverage(ds)).join("; ")
        ));
    } else {
        v.push(
            "held-out data is needed to choose: measure the artifact at another position in the volume (another run, e.g. a ring at speeds elsewhere on the table) and pass it with --validate".into(),
        );
    }
    v
}

/// The moves `lab add NAME` considers: a variant (`kind:options`) or every variant of a kind,
/// each an addition or, when the model has that effect, a swap.
pub fn moves_named(ds: &Dataset, name: &str) -> Result<Vec<Candidate>, LabError> {
    let model = &ds.calibration.effects;
    let all = moves(ds, model);
    let picked: Vec<Candidate> = all
        .into_iter()
        .filter(|c| c.action != Move::Drop)
        .filter(|c| {
            if name.contains(':') {
                c.effect == name
            } else {
                c.effect.split(':').next() == Some(name)
            }
        })
        .collect();
    if !picked.is_empty() {
        return Ok(picked);
    }
    let cfg = candidate(name, ds)?; // names the problem (unknown effect, bad option)
    if model.iter().any(|e| same_variant(e, &cfg)) {
        return Err(LabError::Data(format!(
            "`{name}` is already in the model in this variant (use `lab fit` to refit it)"
        )));
    }
    Ok(vec![Candidate {
        action: Move::Add,
        effect: name.to_string(),
        replaces: None,
        config: Some(cfg),
    }])
}

/// Diagnoses the residual of the dataset's calibration: tries every library effect not in the
/// model (all variants), every other variant of the effects in it, and dropping each; each
/// candidate model is refitted as a whole and ranked by its cross-validated error (see
/// [`super::select`]), the information criterion breaking near-ties.
pub fn diagnose(ds: &Dataset) -> Result<Diagnosis, LabError> {
    let prep = prepare(ds)?;
    let noise = ds.noise_floor_um;
    let model = ds.calibration.effects.clone();
    let sc = score_moves(ds, &prep, moves(ds, &model))?;
    let mut results = vec![];
    let base_held = sc
        .space
        .fit(&prep, &sc.base_spec, &sc.base, &sc.base)?
        .heldout_rms_after_um;
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
                        separate_by: separating(&bc.effect, &c.effect, &cov),
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
    let unexplained = if left_cv < 1.5 * noise.max(0.01) {
        vec![]
    } else {
        let pred = move_prediction(ds, &prep, &sc.space, &left_spec, &left_o, false)?;
        let resid: Vec<f64> = prep
            .art
            .residual
            .iter()
            .zip(&pred)
            .map(|(e, d)| e + d)
            .collect();
        super::structure::structure(ds, &prep, &resid)?
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
        unexplained,
        points: npts,
        skipped: sc.skipped,
        prediction,
    })
}

/// A bin of a residual breakdown.
#[derive(Debug, Clone, Serialize)]
pub struct Bin {
    /// Feature binned by.
    pub feature: String,
    /// Bin label.
    pub bin: String,
    /// Points.
    pub n: usize,
    /// Residual RMS, µm.
    pub rms_um: f64,
    /// Mean residual, µm.
    pub mean_um: f64,
    /// Stands out from the rest.
    pub failing: bool,
    /// A worse failing bin of another feature holding (≥ 80 % of the smaller's) points: this
    /// one is those scans seen another way (`feature bin`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub same_points_as: Option<String>,
}

/// |a ∩ b| / min(|a|, |b|) of two sorted index lists (the overlap coefficient).
fn overlap(a: &[u32], b: &[u32]) -> f64 {
    let (mut i, mut j, mut both) = (0, 0, 0usize);
    while i < a.len() && j < b.len() {
        match a[i].cmp(&b[j]) {
            std::cmp::Ordering::Less => i += 1,
            std::cmp::Ordering::Greater => j += 1,
            std::cmp::Ordering::Equal => {
                both += 1;
                i += 1;
                j += 1;
            }
        }
    }
    let small = a.len().min(b.len());
    if small == 0 {
        0.0
    } else {
        both as f64 / small as f64
    }
}

/// Harmonics of a circle feature's residual.
#[derive(Debug, Clone, Serialize)]
pub struct Harmonics {
    /// Feature index.
    pub feature: usize,
    /// Artifact name.
    pub artifact: String,
    /// Amplitudes of 1θ…5θ, µm.
    pub amplitude_um: [f64; 5],
}

/// A comparison of the model with the artifacts.
#[derive(Debug, Clone, Serialize)]
pub struct Comparison {
    /// Residual RMS (all points, shared placements), µm.
    pub rms_um: f64,
    /// Peak-to-valley, µm.
    pub pv_um: f64,
    /// Noise floor, µm.
    pub noise_floor_um: f64,
    /// Bins that stand out, worst first.
    pub failures: Vec<Bin>,
    /// Every bin.
    pub bins: Vec<Bin>,
    /// Harmonics per circle feature.
    pub harmonics: Vec<Harmonics>,
    /// Tracking residual of the nominal model by segment: (bag, segment, µm), worst first.
    pub tracking: Vec<(usize, u32, f64)>,
    /// Points.
    pub points: usize,
    /// One trace per circle feature, direction and speed (see [`super::traces`]).
    pub traces: Vec<super::traces::Trace>,
    /// Residual per point, µm (for plots).
    #[serde(skip)]
    pub residual_um: Vec<f64>,
}

impl Comparison {
    /// The failing bins that hold (nearly) the points of failing bin `b`, seen through another
    /// feature (`feature bin` labels).
    pub fn same_points(&self, b: &Bin) -> Vec<String> {
        let label = format!("{} {}", b.feature, b.bin);
        self.failures
            .iter()
            .filter(|o| o.same_points_as.as_deref() == Some(label.as_str()))
            .map(|o| format!("{} {}", o.feature, o.bin))
            .collect()
    }
}

/// Compares the dataset's corrected points with their artifacts.
pub fn compare(ds: &Dataset) -> Result<Comparison, LabError> {
    let prep = prepare(ds)?;
    let art = &prep.art;
    let all: Vec<bool> = ds
        .points
        .iter()
        .map(|p| art.features[p.feature].is_some())
        .collect();
    let (ss, n) = nuisance_ss(ds, art, &art.residual, &all);
    let res_um: Vec<f64> = art.residual.iter().map(|e| e * 1e3).collect();
    let (mn, mx) = res_um
        .iter()
        .zip(&all)
        .filter(|(_, a)| **a)
        .fold((f64::MAX, f64::MIN), |(a, b), (r, _)| {
            (a.min(*r), b.max(*r))
        });
    let rms = rms_um(ss, n);
    let noise = ds.noise_floor_um;
    let mut bins = vec![];
    type Key = Box<dyn Fn(&super::dataset::LabPoint) -> Option<String>>;
    let q = |v: f64, edges: &[f64], unit: &str| -> String {
        let i = edges.partition_point(|e| *e <= v);
        match i {
            0 => format!("< {}{unit}", fmt(edges[0])),
            i if i == edges.len() => format!("≥ {}{unit}", fmt(edges[edges.len() - 1])),
            i => format!("{}–{}{unit}", fmt(edges[i - 1]), fmt(edges[i])),
        }
    };
    /// Three significant digits (no bin edge prints as 0.000 or as its neighbour).
    fn fmt(x: f64) -> String {
        let a = x.abs();
        if a == 0.0 || !a.is_finite() {
            "0".to_string()
        } else if a >= 100.0 {
            format!("{x:.0}")
        } else {
            let d = (2 - a.log10().floor() as i32).clamp(0, 9) as usize;
            format!("{x:.d$}")
        }
    }
    // Bins in value order: "< a", "a–b" by a, "≥ b"; categories alphabetically.
    fn order(label: &str) -> (f64, String) {
        let num = |t: &str| {
            t.split_whitespace()
                .next()
                .and_then(|x| x.parse::<f64>().ok())
        };
        if let Some(r) = label.strip_prefix("< ") {
            (num(r).map(|_| f64::MIN).unwrap_or(0.0), label.to_string())
        } else if let Some(r) = label.strip_prefix("≥ ") {
            (num(r).map(|_| f64::MAX).unwrap_or(0.0), label.to_string())
        } else if let Some(a) = label
            .split_once('–')
            .and_then(|(a, _)| a.parse::<f64>().ok())
        {
            (a, label.to_string())
        } else {
            (0.0, label.to_string())
        }
    }
    let quantiles = |vals: Vec<f64>| -> Vec<f64> {
        let mut v: Vec<f64> = vals.into_iter().filter(|x| x.is_finite()).collect();
        v.sort_by(|a, b| a.total_cmp(b));
        if v.is_empty() {
            return vec![0.0];
        }
        let mut e: Vec<f64> = (1..5)
            .map(|k| v[(v.len() * k / 5).min(v.len() - 1)])
            .collect();
        // Edges that print alike would make a bin that reads `a–a`.
        e.dedup_by(|a, b| fmt(*a) == fmt(*b));
        e
    };
    let edges_speed = quantiles(ds.points.iter().map(|p| p.ctx.est_vel.norm()).collect());
    let edges_acc = quantiles(ds.points.iter().map(|p| p.ctx.est_acc.norm()).collect());
    let edges_f = quantiles(
        ds.points
            .iter()
            .filter(|p| p.ctx.f_hz > 0.0)
            .map(|p| p.ctx.f_hz)
            .collect(),
    );
    let edges_t = quantiles(ds.points.iter().map(|p| p.ctx.t_ns as f64 * 1e-9).collect());
    let edges_temp = quantiles(
        ds.points
            .iter()
            .filter(|p| p.ctx.temps_valid & 1 != 0)
            .map(|p| p.ctx.temps[0])
            .collect(),
    );
    let edges_defl = quantiles(ds.points.iter().map(|p| p.ctx.deflection.norm()).collect());
    let sensor0 = ds.sensors.names().first().cloned().unwrap_or_default();
    let centers: Vec<[f64; 3]> = ds.features.iter().map(|(_, f)| f.nominal_center).collect();
    let names: Vec<String> = ds
        .features
        .iter()
        .map(|(_, f)| f.artifact.clone())
        .collect();
    let keys: Vec<(String, Key)> = vec![
        (
            "speed".into(),
            Box::new(move |p| Some(q(p.ctx.est_vel.norm(), &edges_speed, " mm/s"))),
        ),
        (
            "acceleration".into(),
            Box::new(move |p| Some(q(p.ctx.est_acc.norm(), &edges_acc, " mm/s²"))),
        ),
        (
            "rotation frequency".into(),
            Box::new(move |p| (p.ctx.f_hz > 0.0).then(|| q(p.ctx.f_hz, &edges_f, " Hz"))),
        ),
        (
            "direction".into(),
            Box::new(|p| {
                Some(match p.direction {
                    1 => "CCW".into(),
                    -1 => "CW".into(),
                    _ => "line".into(),
                })
            }),
        ),
        (
            "phase".into(),
            Box::new(|p| Some(format!("{:?}", p.phase).to_lowercase())),
        ),
        (
            "position".into(),
            Box::new(move |p| {
                let c = centers[p.feature];
                Some(format!(
                    "{} {} at ({:.0}, {:.0}, {:.0})",
                    names[p.feature],
                    p.feature + 1,
                    c[0],
                    c[1],
                    c[2]
                ))
            }),
        ),
        (
            format!("temperature ({sensor0})"),
            Box::new(move |p| {
                (p.ctx.temps_valid & 1 != 0).then(|| q(p.ctx.temps[0], &edges_temp, " °C"))
            }),
        ),
        (
            "deflection".into(),
            Box::new(move |p| Some(q(p.ctx.deflection.norm(), &edges_defl, " mm"))),
        ),
        (
            "stylus/head".into(),
            Box::new(|p| {
                Some(format!(
                    "tip {} A1={:.0}° A2={:.0}°",
                    p.ctx.tip_id, p.ctx.head_a1_deg, p.ctx.head_a2_deg
                ))
            }),
        ),
        (
            "time".into(),
            Box::new(move |p| Some(q(p.ctx.t_ns as f64 * 1e-9, &edges_t, " s"))),
        ),
    ];
    // The points of each failing bin, to tell bins that are the same scans seen through
    // correlated features (speed, acceleration, rotation frequency on one ring).
    let mut members: Vec<Vec<u32>> = vec![];
    for (name, key) in &keys {
        type Acc = (usize, f64, f64, Vec<u32>);
        let mut acc: std::collections::BTreeMap<String, Acc> = Default::default();
        for (i, p) in ds.points.iter().enumerate() {
            if !all[i] {
                continue;
            }
            if let Some(k) = key(p) {
                let a = acc.entry(k).or_default();
                a.0 += 1;
                a.1 += res_um[i];
                a.2 += res_um[i] * res_um[i];
                a.3.push(i as u32);
            }
        }
        let mut acc: Vec<(String, Acc)> = acc.into_iter().collect();
        acc.sort_by(|a, b| {
            let (oa, ob) = (order(&a.0), order(&b.0));
            oa.0.total_cmp(&ob.0).then(oa.1.cmp(&ob.1))
        });
        for (k, (cnt, s, s2, idx)) in acc {
            let r = (s2 / cnt as f64).sqrt();
            let failing = cnt >= 30 && r > 1.3 * rms && r > 2.0 * noise;
            bins.push(Bin {
                feature: name.clone(),
                bin: k,
                n: cnt,
                rms_um: r,
                mean_um: s / cnt as f64,
                failing,
                same_points_as: None,
            });
            members.push(if failing { idx } else { vec![] });
        }
    }
    let mut order_fail: Vec<usize> = (0..bins.len()).filter(|&b| bins[b].failing).collect();
    order_fail.sort_by(|a, b| bins[*b].rms_um.total_cmp(&bins[*a].rms_um));
    // Greedy groups: a failing bin that shares ≥ 80 % of the smaller one's points with a
    // worse one of another feature is that one seen another way.
    let mut leaders: Vec<usize> = vec![];
    for &b in &order_fail {
        let lead = leaders.iter().copied().find(|&l| {
            bins[l].feature != bins[b].feature && overlap(&members[l], &members[b]) >= 0.8
        });
        match lead {
            Some(l) => {
                bins[b].same_points_as = Some(format!("{} {}", bins[l].feature, bins[l].bin))
            }
            None => leaders.push(b),
        }
    }
    let failures: Vec<Bin> = order_fail.iter().map(|&b| bins[b].clone()).collect();
    // Harmonics of circle features.
    let mut harmonics = vec![];
    for (fi, f) in art.features.iter().enumerate() {
        let Some(f) = f else { continue };
        if f.kind == FeatureKind::Face {
            continue;
        }
        let mut amp = [0.0; 5];
        let idx: Vec<usize> = (0..ds.points.len())
            .filter(|&i| ds.points[i].feature == fi)
            .collect();
        for (k, a) in amp.iter_mut().enumerate() {
            let kk = (k + 1) as f64;
            let th = |i: usize| {
                (ds.points[i].surface.y - f.center.y).atan2(ds.points[i].surface.x - f.center.x)
                    * kk
            };
            let (mut cc, mut cs, mut ss_, mut bc, mut bs) = (0.0, 0.0, 0.0, 0.0, 0.0);
            for &i in &idx {
                let (s, c) = th(i).sin_cos();
                cc += c * c;
                cs += c * s;
                ss_ += s * s;
                bc += c * res_um[i];
                bs += s * res_um[i];
            }
            let det = cc * ss_ - cs * cs;
            if det > 1e-12 {
                let (x, y) = ((ss_ * bc - cs * bs) / det, (cc * bs - cs * bc) / det);
                *a = x.hypot(y);
            }
        }
        harmonics.push(Harmonics {
            feature: fi,
            artifact: ds.features[fi].1.artifact.clone(),
            amplitude_um: amp,
        });
    }
    let mut tracking = ds.tracking.clone();
    tracking.sort_by(|a, b| b.2.total_cmp(&a.2));
    tracking.truncate(20);
    Ok(Comparison {
        rms_um: rms,
        pv_um: if mx >= mn { mx - mn } else { 0.0 },
        noise_floor_um: noise,
        failures,
        bins,
        harmonics,
        tracking,
        points: n,
        traces: super::traces::traces(ds, &res_um),
        residual_um: res_um,
    })
}
