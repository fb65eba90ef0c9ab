//! Stylus bending with probing force.
//!
//! Equation: δ = R·(k ⊙ d), with d the deflection in probe axes, k = (k_u, k_v, k_w) one
//! dimensionless coefficient per probe direction and R the machine_from_probe rotation; the
//! corrected point is the one extrapolated to zero deflection.
//!
//! Source idea: the probing force grows with deflection and bends the stylus by an amount
//! proportional to it, so points scanned at several deflections lie on a line whose value at
//! zero deflection is the true surface.

use super::{check_finite, Effect};
use crate::sample::{PointContext, Vec3};
use serde::{Deserialize, Serialize};

/// Document form.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// Optional name.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub id: Option<String>,
    /// Coefficient per probe axis (u, v, w), mm of error per mm of deflection.
    pub k: [f64; 3],
}

/// Hot-path form.
#[derive(Debug, Clone)]
pub struct Model {
    k: Vec3,
}

impl Config {
    /// Zero-parameter model.
    pub fn zeros() -> Config {
        Config {
            id: None,
            k: [0.0; 3],
        }
    }
    /// Validates.
    pub fn build(&self) -> Result<Model, String> {
        check_finite("k", &self.k)?;
        Ok(Model { k: self.k.into() })
    }
    /// Flat parameters.
    pub fn params(&self) -> Vec<f64> {
        self.k.to_vec()
    }
    /// Sets flat parameters.
    pub fn set_params(&mut self, v: &[f64]) {
        self.k.copy_from_slice(&v[..3]);
    }
    /// Parameter names.
    pub fn param_names(&self) -> Vec<String> {
        ["u", "v", "w"]
            .iter()
            .map(|a| format!("k_{a} (mm/mm)"))
            .collect()
    }
}

impl Effect for Model {
    fn n_params(&self) -> usize {
        3
    }
    fn regressors(&self, ctx: &PointContext, out: &mut [Vec3]) {
        for i in 0..3 {
            out[i] = ctx.machine_from_probe.column(i) * ctx.deflection_probe[i];
        }
    }
    #[inline]
    fn correction(&self, ctx: &PointContext) -> Vec3 {
        ctx.machine_from_probe * self.k.component_mul(&ctx.deflection_probe)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::effects::{testutil::assert_linear, EffectConfig};
    use crate::stylus::machine_from_probe;

    #[test]
    fn hand_computed_force_correction() {
        let c = Config {
            id: None,
            k: [0.02, 0.03, 0.0],
        };
        let m = c.build().unwrap();
        let mut ctx = PointContext::at_rest(Vec3::zeros());
        ctx.deflection_probe = Vec3::new(0.3, -0.1, 0.0);
        ctx.machine_from_probe = machine_from_probe(90.0, 0.0); // probe u → machine y, v → −x
                                                                // k⊙d = (0.006, −0.003, 0) → machine (0.003, 0.006, 0).
        let d = m.correction(&ctx);
        assert!((d - Vec3::new(0.003, 0.006, 0.0)).norm() < 1e-15, "{d:?}");
        assert_linear(&m, &EffectConfig::ProbeForce(c), &ctx);
    }
}
