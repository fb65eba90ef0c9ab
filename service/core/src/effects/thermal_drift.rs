//! Thermal drift of the tool (or probe) against the part, driven by the structure's
//! temperatures through their heat paths.
//!
//! Equation: δ = o + Σ_j k_j·(L_τj[T_sj](t) − T_ref,j), with o a constant displacement
//! (mm, per machine axis), k_j a displacement per kelvin (mm/K, per machine axis) and
//! L_τ[T] sensor s's temperature passed through a first-order lag of time constant τ (the
//! heat path between the sensor and the part of the structure that moves):
//! z_k = z_{k−1} + (1 − e^{−Δt/τ})·(T_k − z_{k−1}) at each of the sensor's readings (Δt
//! since its previous one; τ = 0: the reading itself). The lag's state starts at the first
//! reading (the structure taken as in equilibrium with it). The same sensor may appear with
//! several lags (a heat path with two time constants).
//!
//! Source idea: ISO 230-3 (thermal effects of machine tools): the environmental and the
//! internal heat sources' drift measured against structure temperatures, modelled as a
//! linear combination of temperature changes with the lags of the heat paths — the
//! "thermal error model" of the machine-tool literature (e.g. Mayr et al., "Thermal issues in
//! machine tools", CIRP Annals 61/2, 2012, §5: models from temperatures with transfer
//! functions). `scancorr calibrate thermal-drift` finds the sensors, lags and coefficients.
//!
//! The lag is kept by the corrector for each (sensor, τ) the calibration names
//! ([`SensorTable::lagged_slot`], [`Lag`]): it advances with each temperature reading taken
//! for a point, so live and offline correction agree, and the fitting procedure runs the
//! same [`Lag`] over the recorded temperatures.

use super::{temp, Effect, SensorTable};
use crate::checks::in_range;
use crate::sample::{PointContext, Vec3};
use serde::{Deserialize, Serialize};

/// One term: a sensor through its lag, with a coefficient per machine axis.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Term {
    /// Temperature sensor name.
    pub sensor: String,
    /// Time constant of the first-order lag, s (0: no lag); 0 … 10⁶ s.
    #[serde(default)]
    pub tau_s: f64,
    /// Temperature at which this term contributes nothing, °C; −273.15 … 2000 °C.
    #[serde(default = "twenty")]
    pub reference_c: f64,
    /// Displacement per kelvin of the lagged temperature along x, y, z, mm/K.
    #[serde(default)]
    pub k_mm_per_k: [f64; 3],
    /// Standard uncertainty of `tau_s` stated by the procedure that fitted it, s (dropped
    /// when refitted).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tau_s_u: Option<f64>,
}

fn twenty() -> f64 {
    20.0
}

/// Document form.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// Optional name.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub id: Option<String>,
    /// Constant displacement along x, y, z, mm.
    #[serde(default)]
    pub offset_mm: [f64; 3],
    /// The lagged sensors.
    pub terms: Vec<Term>,
}

/// Hot-path form.
#[derive(Debug, Clone)]
pub struct Model {
    offset: Vec3,
    /// (slot, reference, k) per term.
    terms: Vec<(usize, f64, Vec3)>,
}

/// Longest lag of a term, s (11.6 days).
pub const MAX_TAU_S: f64 = 1e6;

/// Most terms of one thermal-drift effect (each takes a slot of the point's temperatures).
pub const MAX_TERMS: usize = 8;

impl Config {
    /// Zero-parameter model on the given (sensor, τ, reference) terms.
    pub fn zeros(terms: &[(String, f64, f64)]) -> Config {
        Config {
            id: None,
            offset_mm: [0.0; 3],
            terms: terms
                .iter()
                .map(|(s, tau, r)| Term {
                    sensor: s.clone(),
                    tau_s: *tau,
                    reference_c: *r,
                    k_mm_per_k: [0.0; 3],
                    tau_s_u: None,
                })
                .collect(),
        }
    }
    /// Validates.
    pub fn build(&self, sensors: &mut SensorTable) -> Result<Model, String> {
        super::check_finite("offset_mm", &self.offset_mm)?;
        if self.terms.is_empty() {
            return Err("terms: at least one sensor is needed".into());
        }
        if self.terms.len() > MAX_TERMS {
            return Err(format!(
                "terms: {} terms, at most {MAX_TERMS}",
                self.terms.len()
            ));
        }
        let mut terms = Vec::with_capacity(self.terms.len());
        for (j, t) in self.terms.iter().enumerate() {
            super::check_finite(&format!("terms[{j}].k_mm_per_k"), &t.k_mm_per_k)?;
            in_range(&format!("terms[{j}].tau_s"), t.tau_s, 0.0, MAX_TAU_S, "s")?;
            in_range(
                &format!("terms[{j}].reference_c"),
                t.reference_c,
                -273.15,
                2000.0,
                "°C",
            )?;
            if self.terms[..j]
                .iter()
                .any(|o| o.sensor == t.sensor && o.tau_s == t.tau_s)
            {
                return Err(format!(
                    "terms[{j}]: sensor `{}` with τ = {} s appears twice",
                    t.sensor, t.tau_s
                ));
            }
            let slot = sensors
                .lagged_slot(&t.sensor, t.tau_s)
                .map_err(|e| format!("terms[{j}].sensor: {e}"))?;
            terms.push((slot, t.reference_c, Vec3::from(t.k_mm_per_k)));
        }
        Ok(Model {
            offset: self.offset_mm.into(),
            terms,
        })
    }
    /// Flat parameters: the offset, then each term's k.
    pub fn params(&self) -> Vec<f64> {
        let mut v = self.offset_mm.to_vec();
        for t in &self.terms {
            v.extend_from_slice(&t.k_mm_per_k);
        }
        v
    }
    /// Sets flat parameters (the order of [`Self::params`]); the τ's stated uncertainties are
    /// dropped (the coefficients they went with changed).
    pub fn set_params(&mut self, v: &[f64]) {
        self.offset_mm.copy_from_slice(&v[..3]);
        for (j, t) in self.terms.iter_mut().enumerate() {
            t.k_mm_per_k.copy_from_slice(&v[3 + 3 * j..6 + 3 * j]);
            t.tau_s_u = None;
        }
    }
    /// Parameter names.
    pub fn param_names(&self) -> Vec<String> {
        let mut v: Vec<String> = ["x", "y", "z"]
            .iter()
            .map(|a| format!("offset_{a} (mm)"))
            .collect();
        for t in &self.terms {
            for a in ["x", "y", "z"] {
                v.push(format!("{}~{}s.k_{a} (mm/K)", t.sensor, t.tau_s));
            }
        }
        v
    }
}

impl Effect for Model {
    fn n_params(&self) -> usize {
        3 + 3 * self.terms.len()
    }
    fn regressors(&self, ctx: &PointContext, out: &mut [Vec3]) {
        for (i, o) in out.iter_mut().take(3).enumerate() {
            *o = Vec3::zeros();
            o[i] = 1.0;
        }
        for (j, &(slot, r, _)) in self.terms.iter().enumerate() {
            let dt = temp(ctx, slot, r) - r;
            for i in 0..3 {
                let o = &mut out[3 + 3 * j + i];
                *o = Vec3::zeros();
                o[i] = dt;
            }
        }
    }
    #[inline]
    fn correction(&self, ctx: &PointContext) -> Vec3 {
        let mut d = self.offset;
        for &(slot, r, k) in &self.terms {
            d += k * (temp(ctx, slot, r) - r);
        }
        d
    }
}

/// A first-order lag of time constant τ, advanced at each reading (the equation above).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Lag {
    /// Time constant, s (0: no lag).
    pub tau_s: f64,
}

impl Lag {
    /// The state after a reading `u` taken `dt_s` after the previous one, from state `z`.
    #[inline]
    pub fn step(self, z: f64, u: f64, dt_s: f64) -> f64 {
        if self.tau_s <= 0.0 {
            return u;
        }
        z + (1.0 - (-dt_s / self.tau_s).exp()) * (u - z)
    }
    /// The lagged series of readings `u` at times `t_s` (the state starts at the first).
    pub fn run(self, t_s: &[f64], u: &[f64]) -> Vec<f64> {
        let mut out = Vec::with_capacity(u.len());
        let mut z = 0.0;
        for (k, (&t, &x)) in t_s.iter().zip(u).enumerate() {
            z = if k == 0 {
                x
            } else {
                self.step(z, x, t - t_s[k - 1])
            };
            out.push(z);
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::effects::{testutil::assert_linear, EffectConfig};

    #[test]
    fn hand_computed_drift_and_lag() {
        let mut sensors = SensorTable::default();
        let mut c = Config::zeros(&[("spindle".into(), 600.0, 25.0), ("bed".into(), 0.0, 20.0)]);
        c.set_params(&[1e-3, 0.0, 0.0, 2e-3, 0.0, -1e-3, 0.0, 5e-4, 0.0]);
        let m = c.build(&mut sensors).unwrap();
        assert_eq!(sensors.names(), &["spindle".to_string(), "bed".to_string()]);
        assert_eq!(sensors.tau(0), 600.0);
        let mut ctx = PointContext::at_rest(Vec3::new(0.0, 0.0, 0.0));
        ctx.temps[0] = 27.0;
        ctx.temps[1] = 22.0;
        ctx.temps_valid = 0b11;
        // x: 1e-3 + 2e-3·2 = 5e-3; y: 5e-4·2 = 1e-3; z: −1e-3·2 = −2e-3.
        let d = m.correction(&ctx);
        assert!((d - Vec3::new(5e-3, 1e-3, -2e-3)).norm() < 1e-15, "{d:?}");
        assert_linear(&m, &EffectConfig::ThermalDrift(c), &ctx);

        // A step of 1 K through τ = 600 s read every 15 s: 1 − e^{−t/τ} at the readings.
        let t: Vec<f64> = (0..200).map(|k| 15.0 * k as f64).collect();
        let u: Vec<f64> = t.iter().map(|&x| if x > 0.0 { 1.0 } else { 0.0 }).collect();
        let z = Lag { tau_s: 600.0 }.run(&t, &u);
        for (k, &zk) in z.iter().enumerate() {
            let want = 1.0 - (-t[k] / 600.0).exp();
            assert!((zk - want).abs() < 1e-12, "{k}: {zk} vs {want}");
        }
    }

    #[test]
    fn refuses_bad_terms() {
        let mut sensors = SensorTable::default();
        let mut c = Config::zeros(&[("a".into(), -1.0, 20.0)]);
        assert!(c
            .build(&mut sensors)
            .unwrap_err()
            .contains("terms[0].tau_s"));
        c.terms[0].tau_s = 10.0;
        c.terms.push(c.terms[0].clone());
        assert!(c.build(&mut sensors).unwrap_err().contains("appears twice"));
        let c = Config::zeros(&[]);
        assert!(c.build(&mut sensors).unwrap_err().contains("at least one"));
    }
}
