//! Stylus growth with temperature.
//!
//! Equation: δ = α_s·ΔT·R·l_shank + α_b·ΔT·R·l_bent, with ΔT = T_stylus − T_ref, R the head's
//! machine_from_probe rotation, l_shank = (0, 0, −l1) and l_bent the bent limbs (l2, l3 through
//! β1, β2) in probe axes; with one coefficient (`alpha_bent_per_k` absent) α_b = α_s.
//!
//! Source idea: linear thermal expansion ΔL = α·L·ΔT of every limb of the stylus, so the tip
//! moves along the stylus direction by an amount proportional to its length.

use super::{temp, Effect, SensorTable};
use crate::sample::{PointContext, Vec3};
use serde::{Deserialize, Serialize};

/// Document form.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// Optional name.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub id: Option<String>,
    /// Expansion coefficient of the shank l1, 1/K.
    pub alpha_shank_per_k: f64,
    /// Expansion coefficient of the bent limbs, 1/K; absent: same as the shank.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub alpha_bent_per_k: Option<f64>,
    /// Temperature at which the stylus lengths were calibrated, °C.
    #[serde(default = "twenty")]
    pub reference_temp_c: f64,
    /// Temperature sensor.
    #[serde(default = "default_sensor")]
    pub sensor: String,
}

fn twenty() -> f64 {
    20.0
}
fn default_sensor() -> String {
    "stylus".into()
}

/// Hot-path form.
#[derive(Debug, Clone)]
pub struct Model {
    a_s: f64,
    a_b: Option<f64>,
    t_ref: f64,
    slot: usize,
}

impl Config {
    /// Zero-parameter model; `split` gives the bent limbs their own coefficient.
    pub fn zeros(split: bool) -> Config {
        Config {
            id: None,
            alpha_shank_per_k: 0.0,
            alpha_bent_per_k: split.then_some(0.0),
            reference_temp_c: 20.0,
            sensor: default_sensor(),
        }
    }
    /// Validates.
    pub fn build(&self, sensors: &mut SensorTable) -> Result<Model, String> {
        for (n, v) in [
            ("alpha_shank_per_k", self.alpha_shank_per_k),
            ("alpha_bent_per_k", self.alpha_bent_per_k.unwrap_or(0.0)),
            ("reference_temp_c", self.reference_temp_c),
        ] {
            if !v.is_finite() {
                return Err(format!("{n}: must be a finite number"));
            }
        }
        let slot = sensors
            .slot(&self.sensor)
            .map_err(|e| format!("sensor: {e}"))?;
        Ok(Model {
            a_s: self.alpha_shank_per_k,
            a_b: self.alpha_bent_per_k,
            t_ref: self.reference_temp_c,
            slot,
        })
    }
    /// Flat parameters.
    pub fn params(&self) -> Vec<f64> {
        std::iter::once(self.alpha_shank_per_k)
            .chain(self.alpha_bent_per_k)
            .collect()
    }
    /// Sets flat parameters.
    pub fn set_params(&mut self, v: &[f64]) {
        self.alpha_shank_per_k = v[0];
        if let Some(b) = self.alpha_bent_per_k.as_mut() {
            *b = v[1];
        }
    }
    /// Parameter names.
    pub fn param_names(&self) -> Vec<String> {
        let mut v = vec!["alpha_shank (1/K)".to_string()];
        if self.alpha_bent_per_k.is_some() {
            v.push("alpha_bent (1/K)".into());
        }
        v
    }
}

impl Effect for Model {
    fn n_params(&self) -> usize {
        1 + self.a_b.is_some() as usize
    }
    fn regressors(&self, ctx: &PointContext, out: &mut [Vec3]) {
        let dt = temp(ctx, self.slot, self.t_ref) - self.t_ref;
        if self.a_b.is_some() {
            out[0] = ctx.tip_shank * dt;
            out[1] = ctx.tip_bent * dt;
        } else {
            out[0] = ctx.tip_offset() * dt;
        }
    }
    #[inline]
    fn correction(&self, ctx: &PointContext) -> Vec3 {
        let dt = temp(ctx, self.slot, self.t_ref) - self.t_ref;
        (ctx.tip_shank * self.a_s + ctx.tip_bent * self.a_b.unwrap_or(self.a_s)) * dt
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::effects::{testutil::assert_linear, EffectConfig};
    use crate::stylus::{machine_from_probe, TipGeometry};

    #[test]
    fn bent_stylus_grows_with_temperature() {
        // l1 = 50, l2 = 20 bent 90°, head swivelled A1 = 90°: offset (0, 20, −50) machine.
        let tip = TipGeometry {
            id: 1,
            probe: "p".into(),
            l1_mm: 50.0,
            radius_mm: 1.0,
            l2_mm: 20.0,
            beta1_deg: 90.0,
            l3_mm: 0.0,
            beta2_deg: 0.0,
        };
        let r = machine_from_probe(90.0, 0.0);
        let mut sensors = SensorTable::default();
        let c = Config {
            alpha_shank_per_k: 11.5e-6,
            alpha_bent_per_k: Some(23e-6),
            ..Config::zeros(true)
        };
        let m = c.build(&mut sensors).unwrap();
        let mut ctx = PointContext::at_rest(Vec3::zeros());
        ctx.tip_shank = r * tip.shank_probe();
        ctx.tip_bent = r * tip.bent_probe();
        ctx.temps[0] = 23.0;
        ctx.temps_valid = 1;
        // ΔT = 3 K: shank 50·11.5e-6·3 = 1.725e-3 down, bent 20·23e-6·3 = 1.38e-3 along +y.
        let d = m.correction(&ctx);
        assert!(
            (d - Vec3::new(0.0, 1.38e-3, -1.725e-3)).norm() < 1e-15,
            "{d:?}"
        );
        assert_linear(&m, &EffectConfig::StylusThermal(c), &ctx);
        let single = Config {
            alpha_shank_per_k: 1e-5,
            ..Config::zeros(false)
        };
        let ms = single.build(&mut sensors).unwrap();
        assert!((ms.correction(&ctx) - Vec3::new(0.0, 20.0, -50.0) * 3e-5).norm() < 1e-15);
        assert_linear(&ms, &EffectConfig::StylusThermal(single), &ctx);
    }
}
