//! The library of physical effects. Each effect is its own module whose doc comment states
//! its equation; every effect's correction is linear in its parameters,
//! `correction = Σ θ_i · r_i(context)`, and exposes those regressors `r_i` so the model lab
//! can fit it by least squares.
//!
//! A calibration document lists effects as [`EffectConfig`] (serde, human-editable, with
//! parameters). [`EffectConfig::build`] validates one into a [`BuiltEffect`] ready for the hot
//! path. Parameters go in and out of a config as a flat vector ([`EffectConfig::params`],
//! [`EffectConfig::with_params`]) in the order of [`EffectConfig::param_names`].

pub mod accel_deflection;
pub mod custom;
pub mod feature_map;
pub mod guide_straightness;
pub mod probe_force;
pub mod probe_lobing;
pub mod rigid_body;
pub mod scale_thermal;
pub mod servo_gain;
pub mod servo_phase;
pub mod stylus_thermal;
pub mod thermal_drift;

use crate::sample::{PointContext, Vec3, MAX_SENSORS};
use serde::{Deserialize, Serialize};

/// An effect as written in a calibration document: `{"kind": "...", ...parameters}`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum EffectConfig {
    /// Structure deflection under acceleration, D = P(position)·A.
    AccelDeflection(accel_deflection::Config),
    /// Inter-axis phase lag on arcs.
    ServoPhase(servo_phase::Config),
    /// Per-axis amplitude response on arcs.
    ServoGain(servo_gain::Config),
    /// Stylus growth with temperature.
    StylusThermal(stylus_thermal::Config),
    /// Scale growth with temperature.
    ScaleThermal(scale_thermal::Config),
    /// Stylus bending with probing force.
    ProbeForce(probe_force::Config),
    /// Guide straightness and pitch along an axis.
    GuideStraightness(guide_straightness::Config),
    /// The 21 rigid-body errors of a three-axis machine through its kinematic chain.
    RigidBody(rigid_body::Config),
    /// Direction-dependent probe error (pre-travel variation, lobing).
    ProbeLobing(probe_lobing::Config),
    /// User-defined regressors.
    Custom(custom::Config),
    /// A per-point correction map of one feature's scans at one speed (the dynamic map).
    FeatureMap(feature_map::Config),
    /// Thermal drift from the structure's temperatures through their heat paths' lags.
    ThermalDrift(thermal_drift::Config),
}

/// Names of the built-in kinds, as written in documents.
pub const KINDS: [&str; 12] = [
    "accel_deflection",
    "servo_phase",
    "servo_gain",
    "stylus_thermal",
    "scale_thermal",
    "probe_force",
    "guide_straightness",
    "rigid_body",
    "probe_lobing",
    "custom",
    "feature_map",
    "thermal_drift",
];

/// A validated effect, ready for the hot path.
pub trait Effect: Send + Sync + std::fmt::Debug {
    /// Number of parameters θ.
    fn n_params(&self) -> usize;
    /// Writes the regressors r_i (machine axes) for this context; `out.len() == n_params()`.
    fn regressors(&self, ctx: &PointContext, out: &mut [Vec3]);
    /// The correction Σ θ_i r_i with the effect's parameters, mm.
    fn correction(&self, ctx: &PointContext) -> Vec3;
}

/// A built effect with its name and whether it is dynamic (suspended by alarms).
#[derive(Debug)]
pub struct BuiltEffect {
    /// Effect id (its `id`, or its kind).
    pub id: String,
    /// Dynamic effects depend on the estimated motion and are left out while an estimator
    /// alarm with action `suspend` is raised.
    pub dynamic: bool,
    /// Whether any of its parameters is non-zero (an effect with none cannot contribute, so
    /// it is not reported inactive for contributing nothing).
    pub has_params: bool,
    /// The model.
    pub model: Model,
}

/// Calls `$call` on the model inside a [`Model`], whatever its kind.
macro_rules! each_model {
    ($m:expr, $model:ident => $call:expr) => {
        match $m {
            Model::AccelDeflection($model) => $call,
            Model::ServoPhase($model) => $call,
            Model::ServoGain($model) => $call,
            Model::StylusThermal($model) => $call,
            Model::ScaleThermal($model) => $call,
            Model::ProbeForce($model) => $call,
            Model::GuideStraightness($model) => $call,
            Model::RigidBody($model) => $call,
            Model::ProbeLobing($model) => $call,
            Model::Custom($model) => $call,
            Model::FeatureMap($model) => $call,
            Model::ThermalDrift($model) => $call,
        }
    };
}

/// A built effect model of any kind: one variant per kind of [`EffectConfig`].
///
/// An enum rather than a `Box<dyn Effect>`: the corrector calls every effect for every point,
/// and a `match` on the kind is one jump (no vtable). The match is inlined into the corrector's
/// loop over the effects, but each kind's `correction` is its own function, not inlined into
/// its arm: inlined, the compiler hoisted every kind's per-point work (norms, square roots,
/// divisions) out of the loop, so each point paid it for the kinds its calibration does not
/// have (with one effect, ≈150 instructions per point of ≈3 000); one outlined function for
/// all kinds saved every kind's registers on each call (the per-kind functions save 9–20
/// instructions per effect and point). The larger models are boxed, so that
/// every effect of a calibration does not take the room of the largest kind (a service keeps
/// one model per machine).
#[derive(Debug, Clone)]
pub enum Model {
    /// [`accel_deflection`].
    AccelDeflection(accel_deflection::Model),
    /// [`servo_phase`].
    ServoPhase(servo_phase::Model),
    /// [`servo_gain`].
    ServoGain(servo_gain::Model),
    /// [`stylus_thermal`].
    StylusThermal(stylus_thermal::Model),
    /// [`scale_thermal`].
    ScaleThermal(scale_thermal::Model),
    /// [`probe_force`].
    ProbeForce(probe_force::Model),
    /// [`guide_straightness`].
    GuideStraightness(Box<guide_straightness::Model>),
    /// [`rigid_body`].
    RigidBody(Box<rigid_body::Model>),
    /// [`probe_lobing`].
    ProbeLobing(probe_lobing::Model),
    /// [`custom`].
    Custom(Box<custom::Model>),
    /// [`feature_map`].
    FeatureMap(Box<feature_map::Model>),
    /// [`thermal_drift`].
    ThermalDrift(Box<thermal_drift::Model>),
}

impl Effect for Model {
    fn n_params(&self) -> usize {
        each_model!(self, m => m.n_params())
    }
    fn regressors(&self, ctx: &PointContext, out: &mut [Vec3]) {
        each_model!(self, m => m.regressors(ctx, out))
    }
    /// The kind's correction, each kind's its own function (not inlined): a dispatch in the
    /// caller's loop, and a call that saves only the registers that kind uses. Inlined into
    /// the loop over effects, every kind's per-point square roots and divisions were hoisted
    /// out of it and paid by every point; one function for all kinds saved all of their
    /// registers on every call.
    #[inline]
    fn correction(&self, ctx: &PointContext) -> Vec3 {
        match self {
            Model::AccelDeflection(m) => correction_of(m, ctx),
            Model::ServoPhase(m) => correction_of(m, ctx),
            Model::ServoGain(m) => correction_of(m, ctx),
            Model::StylusThermal(m) => correction_of(m, ctx),
            Model::ScaleThermal(m) => correction_of(m, ctx),
            Model::ProbeForce(m) => correction_of(m, ctx),
            Model::GuideStraightness(m) => correction_of(&**m, ctx),
            Model::RigidBody(m) => correction_of(&**m, ctx),
            Model::ProbeLobing(m) => correction_of(m, ctx),
            Model::Custom(m) => correction_of(&**m, ctx),
            Model::FeatureMap(m) => correction_of(&**m, ctx),
            Model::ThermalDrift(m) => correction_of(&**m, ctx),
        }
    }
}

/// One kind's [`Effect::correction`], never inlined (see [`Model`]'s).
#[inline(never)]
fn correction_of<E: Effect>(m: &E, ctx: &PointContext) -> Vec3 {
    m.correction(ctx)
}

/// Maps temperature sensor names to slots of [`PointContext::temps`]. A slot holds a sensor's
/// reading or, for a [`thermal_drift`] term, the reading through a first-order lag of time
/// constant τ (the corrector keeps the lag's state: [`thermal_drift::Lag`]).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SensorTable {
    names: Vec<String>,
    taus: Vec<f64>,
}

impl SensorTable {
    /// Slot of `name`'s reading, allocating one if new.
    pub fn slot(&mut self, name: &str) -> Result<usize, String> {
        self.lagged_slot(name, 0.0)
    }
    /// Slot of `name`'s reading through a lag of `tau_s` (0: the reading), allocating one if
    /// new.
    pub fn lagged_slot(&mut self, name: &str, tau_s: f64) -> Result<usize, String> {
        if let Some(i) =
            (0..self.names.len()).find(|&i| self.names[i] == name && self.taus[i] == tau_s)
        {
            return Ok(i);
        }
        if self.names.len() == MAX_SENSORS {
            return Err(format!(
                "more than {MAX_SENSORS} temperature sensors (or lagged sensors) referenced"
            ));
        }
        self.names.push(name.to_string());
        self.taus.push(tau_s);
        Ok(self.names.len() - 1)
    }
    /// Slot of `name`'s reading (no lag) if known.
    pub fn find(&self, name: &str) -> Option<usize> {
        (0..self.names.len()).find(|&i| self.names[i] == name && self.taus[i] == 0.0)
    }
    /// Whether any slot reads `name` (directly or through a lag).
    pub fn uses(&self, name: &str) -> bool {
        self.names.iter().any(|n| n == name)
    }
    /// Sensor names by slot (a lagged slot is named by its sensor).
    pub fn names(&self) -> &[String] {
        &self.names
    }
    /// The lag's time constant of a slot, s (0: the reading itself).
    pub fn tau(&self, slot: usize) -> f64 {
        self.taus[slot]
    }
}

/// Reads a temperature slot, or 0 ΔT-neutral `reference` when missing (the corrector drops
/// points whose required sensors are missing, so this only matters for the lab's probes).
#[inline]
pub(crate) fn temp(ctx: &PointContext, slot: usize, reference: f64) -> f64 {
    if ctx.temps_valid & (1 << slot) != 0 {
        ctx.temps[slot]
    } else {
        reference
    }
}

impl EffectConfig {
    /// The effect's kind as written in documents.
    pub fn kind(&self) -> &'static str {
        match self {
            EffectConfig::AccelDeflection(_) => "accel_deflection",
            EffectConfig::ServoPhase(_) => "servo_phase",
            EffectConfig::ServoGain(_) => "servo_gain",
            EffectConfig::StylusThermal(_) => "stylus_thermal",
            EffectConfig::ScaleThermal(_) => "scale_thermal",
            EffectConfig::ProbeForce(_) => "probe_force",
            EffectConfig::GuideStraightness(_) => "guide_straightness",
            EffectConfig::RigidBody(_) => "rigid_body",
            EffectConfig::ProbeLobing(_) => "probe_lobing",
            EffectConfig::Custom(_) => "custom",
            EffectConfig::FeatureMap(_) => "feature_map",
            EffectConfig::ThermalDrift(_) => "thermal_drift",
        }
    }

    /// The effect's id: its `id` field or its kind.
    pub fn id(&self) -> String {
        let id = match self {
            EffectConfig::AccelDeflection(c) => c.id.clone(),
            EffectConfig::ServoPhase(c) => c.id.clone(),
            EffectConfig::ServoGain(c) => c.id.clone(),
            EffectConfig::StylusThermal(c) => c.id.clone(),
            EffectConfig::ScaleThermal(c) => c.id.clone(),
            EffectConfig::ProbeForce(c) => c.id.clone(),
            EffectConfig::GuideStraightness(c) => c.id.clone(),
            EffectConfig::RigidBody(c) => c.id.clone(),
            EffectConfig::ProbeLobing(c) => c.id.clone(),
            EffectConfig::Custom(c) => Some(c.id.clone()),
            EffectConfig::FeatureMap(c) => c.id.clone(),
            EffectConfig::ThermalDrift(c) => c.id.clone(),
        };
        id.unwrap_or_else(|| self.kind().to_string())
    }

    /// Sets the effect's id (`None`: named by its kind).
    pub fn set_id(&mut self, id: Option<String>) {
        match self {
            EffectConfig::AccelDeflection(c) => c.id = id,
            EffectConfig::ServoPhase(c) => c.id = id,
            EffectConfig::ServoGain(c) => c.id = id,
            EffectConfig::StylusThermal(c) => c.id = id,
            EffectConfig::ScaleThermal(c) => c.id = id,
            EffectConfig::ProbeForce(c) => c.id = id,
            EffectConfig::GuideStraightness(c) => c.id = id,
            EffectConfig::RigidBody(c) => c.id = id,
            EffectConfig::ProbeLobing(c) => c.id = id,
            EffectConfig::Custom(c) => c.id = id.unwrap_or_else(|| "custom".into()),
            EffectConfig::FeatureMap(c) => c.id = id,
            EffectConfig::ThermalDrift(c) => c.id = id,
        }
    }

    /// Dynamic effects depend on the estimated motion.
    pub fn is_dynamic(&self) -> bool {
        match self {
            EffectConfig::AccelDeflection(_)
            | EffectConfig::ServoPhase(_)
            | EffectConfig::ServoGain(_) => true,
            // Applies at one path speed (the estimated velocity decides).
            EffectConfig::FeatureMap(_) => true,
            EffectConfig::Custom(c) => c.dynamic,
            // Geometry and probe direction: functions of position and deflection only.
            EffectConfig::RigidBody(_) | EffectConfig::ProbeLobing(_) => false,
            _ => false,
        }
    }

    /// Validates and builds the hot-path model. Errors name the offending field, relative to
    /// this effect (the caller prefixes `effects[i]`).
    pub fn build(&self, sensors: &mut SensorTable) -> Result<BuiltEffect, String> {
        let model = match self {
            EffectConfig::AccelDeflection(c) => Model::AccelDeflection(c.build()?),
            EffectConfig::ServoPhase(c) => Model::ServoPhase(c.build()?),
            EffectConfig::ServoGain(c) => Model::ServoGain(c.build()?),
            EffectConfig::StylusThermal(c) => Model::StylusThermal(c.build(sensors)?),
            EffectConfig::ScaleThermal(c) => Model::ScaleThermal(c.build(sensors)?),
            EffectConfig::ProbeForce(c) => Model::ProbeForce(c.build()?),
            EffectConfig::GuideStraightness(c) => Model::GuideStraightness(Box::new(c.build()?)),
            EffectConfig::RigidBody(c) => Model::RigidBody(Box::new(c.build()?)),
            EffectConfig::ProbeLobing(c) => Model::ProbeLobing(c.build()?),
            EffectConfig::Custom(c) => Model::Custom(Box::new(c.build(sensors)?)),
            EffectConfig::FeatureMap(c) => Model::FeatureMap(Box::new(c.build()?)),
            EffectConfig::ThermalDrift(c) => Model::ThermalDrift(Box::new(c.build(sensors)?)),
        };
        Ok(BuiltEffect {
            id: self.id(),
            dynamic: self.is_dynamic(),
            has_params: self.params().iter().any(|p| *p != 0.0),
            model,
        })
    }

    /// The parameters as a flat vector (order of [`Self::param_names`]).
    pub fn params(&self) -> Vec<f64> {
        match self {
            EffectConfig::AccelDeflection(c) => c.params(),
            EffectConfig::ServoPhase(c) => c.params(),
            EffectConfig::ServoGain(c) => c.params(),
            EffectConfig::StylusThermal(c) => c.params(),
            EffectConfig::ScaleThermal(c) => c.params(),
            EffectConfig::ProbeForce(c) => c.params(),
            EffectConfig::GuideStraightness(c) => c.params(),
            EffectConfig::RigidBody(c) => c.params(),
            EffectConfig::ProbeLobing(c) => c.params(),
            EffectConfig::Custom(c) => c.coefficients.clone(),
            EffectConfig::FeatureMap(c) => c.params(),
            EffectConfig::ThermalDrift(c) => c.params(),
        }
    }

    /// Human-readable parameter names with units.
    pub fn param_names(&self) -> Vec<String> {
        match self {
            EffectConfig::AccelDeflection(c) => c.param_names(),
            EffectConfig::ServoPhase(c) => c.param_names(),
            EffectConfig::ServoGain(c) => c.param_names(),
            EffectConfig::StylusThermal(c) => c.param_names(),
            EffectConfig::ScaleThermal(c) => c.param_names(),
            EffectConfig::ProbeForce(c) => c.param_names(),
            EffectConfig::GuideStraightness(c) => c.param_names(),
            EffectConfig::RigidBody(c) => c.param_names(),
            EffectConfig::ProbeLobing(c) => c.param_names(),
            EffectConfig::Custom(c) => c
                .terms
                .iter()
                .map(|t| {
                    format!(
                        "{}·[{}] ({})",
                        t.axis.name(),
                        t.expr,
                        crate::units::coefficient_unit(&t.expr)
                    )
                })
                .collect(),
            EffectConfig::FeatureMap(c) => c.param_names(),
            EffectConfig::ThermalDrift(c) => c.param_names(),
        }
    }

    /// The same structure with new parameter values (`p.len()` must equal the count).
    pub fn with_params(&self, p: &[f64]) -> Result<EffectConfig, String> {
        let n = self.params().len();
        if p.len() != n {
            return Err(format!(
                "{} takes {n} parameters, got {}",
                self.kind(),
                p.len()
            ));
        }
        let mut c = self.clone();
        match &mut c {
            EffectConfig::AccelDeflection(c) => c.set_params(p),
            EffectConfig::ServoPhase(c) => c.set_params(p),
            EffectConfig::ServoGain(c) => c.set_params(p),
            EffectConfig::StylusThermal(c) => c.set_params(p),
            EffectConfig::ScaleThermal(c) => c.set_params(p),
            EffectConfig::ProbeForce(c) => c.set_params(p),
            EffectConfig::GuideStraightness(c) => c.set_params(p),
            EffectConfig::RigidBody(c) => c.set_params(p),
            EffectConfig::ProbeLobing(c) => c.set_params(p),
            EffectConfig::Custom(c) => c.coefficients = p.to_vec(),
            EffectConfig::FeatureMap(c) => c.set_params(p),
            EffectConfig::ThermalDrift(c) => c.set_params(p),
        }
        Ok(c)
    }
}

/// Position dependence of a coefficient: a polynomial in ξ = (p − origin)/scale.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PositionBasis {
    /// 0 (constant), 1 (linear: 1, ξx, ξy, ξz) or 2 (adds ξx², ξy², ξz², ξxξy, ξxξz, ξyξz).
    #[serde(default)]
    pub order: u8,
    /// Origin of ξ, mm.
    #[serde(default)]
    pub origin_mm: [f64; 3],
    /// Length that makes ξ dimensionless (about half the travel), mm.
    #[serde(default = "default_scale")]
    pub scale_mm: f64,
}

fn default_scale() -> f64 {
    500.0
}

impl Default for PositionBasis {
    fn default() -> Self {
        PositionBasis {
            order: 0,
            origin_mm: [0.0; 3],
            scale_mm: default_scale(),
        }
    }
}

/// Names of the monomials of order 2, in basis order.
pub const MONOMIALS: [&str; 10] = ["1", "x", "y", "z", "x²", "y²", "z²", "xy", "xz", "yz"];

/// How a parameter's name says which monomial of the position basis it multiplies: nothing
/// for the constant, `· ξx` (ξ = (position − origin) / scale, dimensionless) for the others —
/// so the unit of every coefficient is the unit of the constant term.
pub fn monomial_suffix(m: usize) -> String {
    match m {
        0 => String::new(),
        _ => format!(" · ξ{}", MONOMIALS[m.min(MONOMIALS.len() - 1)]),
    }
}

impl PositionBasis {
    /// Number of monomials.
    pub fn len(&self) -> usize {
        [1, 4, 10][self.order.min(2) as usize]
    }
    /// Never empty (the constant is always there).
    pub fn is_empty(&self) -> bool {
        false
    }
    /// Checks order, origin and scale.
    pub fn validate(&self, field: &str) -> Result<(), String> {
        if self.order > 2 {
            return Err(format!("{field}.order: must be 0, 1 or 2"));
        }
        if !self.origin_mm.iter().all(|v| v.is_finite()) {
            return Err(format!("{field}.origin_mm: must be finite numbers"));
        }
        if !(self.scale_mm.is_finite() && self.scale_mm > 0.0) {
            return Err(format!("{field}.scale_mm: must be a finite number > 0"));
        }
        Ok(())
    }
    /// Monomial values at `p`; returns how many were written.
    #[inline]
    pub fn eval(&self, p: &Vec3, out: &mut [f64; 10]) -> usize {
        PreparedBasis::from(*self).eval(p, out)
    }
}

/// A [`PositionBasis`] ready for the hot path: the reciprocal of its scale computed once
/// (the values are [`PositionBasis::eval`]'s, bit for bit).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct PreparedBasis {
    order: u8,
    origin: Vec3,
    inv_scale: f64,
}

impl From<PositionBasis> for PreparedBasis {
    fn from(b: PositionBasis) -> Self {
        PreparedBasis {
            order: b.order,
            origin: b.origin_mm.into(),
            inv_scale: 1.0 / b.scale_mm,
        }
    }
}

impl PreparedBasis {
    /// Number of monomials.
    #[inline]
    pub fn len(&self) -> usize {
        [1, 4, 10][self.order.min(2) as usize]
    }
    /// Monomial values at `p`; returns how many were written.
    #[inline]
    pub fn eval(&self, p: &Vec3, out: &mut [f64; 10]) -> usize {
        out[0] = 1.0;
        if self.order == 0 {
            return 1;
        }
        let k = self.inv_scale;
        let (x, y, z) = (
            (p.x - self.origin.x) * k,
            (p.y - self.origin.y) * k,
            (p.z - self.origin.z) * k,
        );
        out[1] = x;
        out[2] = y;
        out[3] = z;
        if self.order == 1 {
            return 4;
        }
        out[4] = x * x;
        out[5] = y * y;
        out[6] = z * z;
        out[7] = x * y;
        out[8] = x * z;
        out[9] = y * z;
        10
    }
}

/// Checks that every value is finite; names the field.
pub(crate) fn check_finite(field: &str, v: &[f64]) -> Result<(), String> {
    match v.iter().position(|x| !x.is_finite()) {
        Some(i) => Err(format!("{field}[{i}]: must be a finite number")),
        None => Ok(()),
    }
}

#[cfg(test)]
pub(crate) mod testutil {
    use super::*;

    /// Asserts that correction == Σ θ r for a context.
    pub fn assert_linear(e: &dyn Effect, cfg: &EffectConfig, ctx: &PointContext) {
        let p = cfg.params();
        assert_eq!(p.len(), e.n_params());
        assert_eq!(cfg.param_names().len(), p.len());
        let mut r = vec![Vec3::zeros(); p.len()];
        e.regressors(ctx, &mut r);
        let sum: Vec3 = r.iter().zip(p.iter()).map(|(r, t)| r * *t).sum();
        let c = e.correction(ctx);
        assert!(
            (sum - c).norm() <= 1e-12 * (1.0 + c.norm()),
            "{sum:?} vs {c:?}"
        );
        // Round trip of the parameters.
        let c2 = cfg.with_params(&p).unwrap();
        assert_eq!(&c2, cfg);
    }
}
