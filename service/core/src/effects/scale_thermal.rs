//! Scale growth with temperature.
//!
//! Equation: δ_i = α_i·(T_i − 20 °C)·(s_i − o_i) per axis i, with T_i the temperature of
//! axis i's scale, s_i its reading and o_i its zero point.
//!
//! Source idea: ISO 1 — lengths are defined at 20 °C; a scale at another temperature is
//! longer or shorter by α·L·ΔT, so its reading is off in proportion to the distance from its
//! fixed point.

use super::{temp, Effect, SensorTable};
use crate::checks::in_range;
use crate::sample::{PointContext, Vec3};
use serde::{Deserialize, Serialize};

/// Document form.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// Optional name.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub id: Option<String>,
    /// Expansion coefficient per axis (x, y, z), 1/K; within ±10⁻³ 1/K.
    pub alpha_per_k: [f64; 3],
    /// Reference temperature, °C; −273.15 … 2000 °C.
    #[serde(default = "twenty")]
    pub reference_temp_c: f64,
    /// Sensors of the x, y, z scales.
    #[serde(default = "default_sensors")]
    pub sensors: [String; 3],
    /// Zero point of each scale, mm; within ±10⁶ mm.
    #[serde(default)]
    pub origin_mm: [f64; 3],
}

fn twenty() -> f64 {
    20.0
}
/// The scales' temperature sensors by their usual names (x, y, z): the document's default, and
/// what a procedure reads when the start has no `scale_thermal` to name them.
pub const SENSORS: [&str; 3] = ["scale_x", "scale_y", "scale_z"];

fn default_sensors() -> [String; 3] {
    SENSORS.map(String::from)
}

/// Hot-path form.
#[derive(Debug, Clone)]
pub struct Model {
    alpha: [f64; 3],
    t_ref: f64,
    slots: [usize; 3],
    origin: Vec3,
}

impl Config {
    /// Zero-parameter model.
    pub fn zeros() -> Config {
        Config {
            id: None,
            alpha_per_k: [0.0; 3],
            reference_temp_c: 20.0,
            sensors: default_sensors(),
            origin_mm: [0.0; 3],
        }
    }
    /// Validates.
    pub fn build(&self, sensors: &mut SensorTable) -> Result<Model, String> {
        super::check_finite("alpha_per_k", &self.alpha_per_k)?;
        for (i, a) in self.alpha_per_k.iter().enumerate() {
            in_range(&format!("alpha_per_k[{i}]"), *a, -1e-3, 1e-3, "1/K")?;
        }
        super::check_finite("origin_mm", &self.origin_mm)?;
        for (i, o) in self.origin_mm.iter().enumerate() {
            in_range(&format!("origin_mm[{i}]"), *o, -1e6, 1e6, "mm")?;
        }
        in_range(
            "reference_temp_c",
            self.reference_temp_c,
            -273.15,
            2000.0,
            "°C",
        )?;
        let mut slots = [0; 3];
        for (i, s) in self.sensors.iter().enumerate() {
            slots[i] = sensors.slot(s).map_err(|e| format!("sensors[{i}]: {e}"))?;
        }
        Ok(Model {
            alpha: self.alpha_per_k,
            t_ref: self.reference_temp_c,
            slots,
            origin: self.origin_mm.into(),
        })
    }
    /// Flat parameters.
    pub fn params(&self) -> Vec<f64> {
        self.alpha_per_k.to_vec()
    }
    /// Sets flat parameters.
    pub fn set_params(&mut self, v: &[f64]) {
        self.alpha_per_k.copy_from_slice(&v[..3]);
    }
    /// Parameter names.
    pub fn param_names(&self) -> Vec<String> {
        ["x", "y", "z"]
            .iter()
            .map(|a| format!("alpha_{a} (1/K)"))
            .collect()
    }
}

impl Effect for Model {
    fn n_params(&self) -> usize {
        3
    }
    fn regressors(&self, ctx: &PointContext, out: &mut [Vec3]) {
        for i in 0..3 {
            let dt = temp(ctx, self.slots[i], self.t_ref) - self.t_ref;
            out[i] = Vec3::zeros();
            out[i][i] = dt * (ctx.scale[i] - self.origin[i]);
        }
    }
    #[inline]
    fn correction(&self, ctx: &PointContext) -> Vec3 {
        Vec3::from_fn(|i, _| {
            self.alpha[i]
                * (temp(ctx, self.slots[i], self.t_ref) - self.t_ref)
                * (ctx.scale[i] - self.origin[i])
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::effects::{testutil::assert_linear, EffectConfig};

    #[test]
    fn hand_computed_scale_expansion() {
        let mut sensors = SensorTable::default();
        let c = Config {
            alpha_per_k: [10e-6, 11e-6, 0.0],
            ..Config::zeros()
        };
        let m = c.build(&mut sensors).unwrap();
        let mut ctx = PointContext::at_rest(Vec3::new(400.0, -100.0, 50.0));
        ctx.temps[0] = 22.0;
        ctx.temps[1] = 19.0;
        ctx.temps[2] = 30.0;
        ctx.temps_valid = 0b111;
        // x: 10e-6·2·400 = 8e-3; y: 11e-6·(−1)·(−100) = 1.1e-3; z: α = 0.
        let d = m.correction(&ctx);
        assert!((d - Vec3::new(8e-3, 1.1e-3, 0.0)).norm() < 1e-15, "{d:?}");
        assert_linear(&m, &EffectConfig::ScaleThermal(c), &ctx);
    }
}
