//! Stylus growth with temperature.
//!
//! Equation: δ = α_s·ΔT·R·l_shank + α_b·ΔT·R·l_bent, with ΔT = T_stylus − T_ref, R the head's
//! machine_from_probe rotation, l_shank = (0, 0, −l1) and l_bent the bent limbs (l2, l3 through
//! β1, β2) in probe axes; with one coefficient (`alpha_bent_per_k` absent) α_b = α_s.
//!
//! Per tip (optional, `alpha_per_tip`): for a point of a listed tip t,
//! δ = ΔT·α_t·R·(l_shank + l_bent), one coefficient for the whole stylus, replacing the per-limb
//! form for that tip; unlisted tips keep the per-limb form. The machine's coefficients have zero
//! regressors for points of a listed tip and a tip's coefficient zero regressors for any other
//! tip, so the effect stays linear in all parameters.
//!
//! Source idea: linear thermal expansion ΔL = α·L·ΔT of every limb of the stylus, so the tip
//! moves along the stylus direction by an amount proportional to its length. The styli of a
//! multi-stylus probe differ in material (steel, carbide, ceramic, carbon fibre) and are
//! qualified one by one; each is taken as one thermally homogeneous body at the sensor's
//! temperature, so its whole offset vector grows by α_t·ΔT.

use super::{probe_force::tip_map, temp, Effect, SensorTable};
use crate::sample::{PointContext, Vec3};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// Document form.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// Optional name.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub id: Option<String>,
    /// Expansion coefficient of the shank l1, 1/K; this and every other coefficient within
    /// ±10⁻³ 1/K.
    pub alpha_shank_per_k: f64,
    /// Expansion coefficient of the bent limbs, 1/K; absent: same as the shank.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub alpha_bent_per_k: Option<f64>,
    /// Temperature at which the stylus lengths were calibrated, °C; −273.15 … 2000 °C.
    #[serde(default = "twenty")]
    pub reference_temp_c: f64,
    /// Temperature sensor.
    #[serde(default = "default_sensor")]
    pub sensor: String,
    /// Expansion coefficient of the whole stylus for individual tips (by tip id), 1/K;
    /// replaces the per-limb coefficients for them.
    #[serde(
        default,
        deserialize_with = "tip_map",
        skip_serializing_if = "BTreeMap::is_empty"
    )]
    pub alpha_per_tip: BTreeMap<u32, f64>,
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
    /// (tip id, α) sorted by tip id; the tip's parameter follows the machine's ones.
    per_tip: Vec<(u32, f64)>,
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
            alpha_per_tip: BTreeMap::new(),
        }
    }
    /// Zero-parameter model with one coefficient of its own for each of `tips`; `split` as in
    /// [`Config::zeros`] for the other tips.
    pub fn zeros_per_tip(tips: &[u32], split: bool) -> Config {
        Config {
            alpha_per_tip: tips.iter().map(|&t| (t, 0.0)).collect(),
            ..Config::zeros(split)
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
            let (lo, hi, unit) = if n == "reference_temp_c" {
                (-273.15, 2000.0, "°C")
            } else {
                (-1e-3, 1e-3, "1/K")
            };
            crate::checks::in_range(n, v, lo, hi, unit)?;
        }
        for (t, a) in &self.alpha_per_tip {
            if !a.is_finite() {
                return Err(format!("alpha_per_tip.{t}: must be a finite number"));
            }
            crate::checks::in_range(&format!("alpha_per_tip.{t}"), *a, -1e-3, 1e-3, "1/K")?;
        }
        let slot = sensors
            .slot(&self.sensor)
            .map_err(|e| format!("sensor: {e}"))?;
        Ok(Model {
            a_s: self.alpha_shank_per_k,
            a_b: self.alpha_bent_per_k,
            t_ref: self.reference_temp_c,
            slot,
            per_tip: self.alpha_per_tip.iter().map(|(&t, &a)| (t, a)).collect(),
        })
    }
    /// Flat parameters: the machine's coefficients, then each listed tip's in tip-id order.
    pub fn params(&self) -> Vec<f64> {
        std::iter::once(self.alpha_shank_per_k)
            .chain(self.alpha_bent_per_k)
            .chain(self.alpha_per_tip.values().copied())
            .collect()
    }
    /// Sets flat parameters.
    pub fn set_params(&mut self, v: &[f64]) {
        self.alpha_shank_per_k = v[0];
        let mut i = 1;
        if let Some(b) = self.alpha_bent_per_k.as_mut() {
            *b = v[1];
            i = 2;
        }
        for (a, x) in self.alpha_per_tip.values_mut().zip(&v[i..]) {
            *a = *x;
        }
    }
    /// Parameter names: `alpha_shank (1/K)`, `alpha_bent (1/K)`, then `tip 2 alpha (1/K)`.
    pub fn param_names(&self) -> Vec<String> {
        let mut v = vec!["alpha_shank (1/K)".to_string()];
        if self.alpha_bent_per_k.is_some() {
            v.push("alpha_bent (1/K)".into());
        }
        v.extend(
            self.alpha_per_tip
                .keys()
                .map(|t| format!("tip {t} alpha (1/K)")),
        );
        v
    }
}

impl Model {
    /// Number of the machine's (per-limb) parameters.
    #[inline]
    fn n_machine(&self) -> usize {
        1 + self.a_b.is_some() as usize
    }
    /// Index of the tip in `per_tip`, if listed.
    #[inline]
    fn tip_index(&self, tip: u32) -> Option<usize> {
        if self.per_tip.is_empty() {
            return None;
        }
        self.per_tip.binary_search_by_key(&tip, |e| e.0).ok()
    }
}

impl Effect for Model {
    fn n_params(&self) -> usize {
        self.n_machine() + self.per_tip.len()
    }
    fn regressors(&self, ctx: &PointContext, out: &mut [Vec3]) {
        let dt = temp(ctx, self.slot, self.t_ref) - self.t_ref;
        let nm = self.n_machine();
        if let Some(j) = self.tip_index(ctx.tip_id) {
            out.iter_mut().for_each(|r| *r = Vec3::zeros());
            out[nm + j] = ctx.tip_offset() * dt;
            return;
        }
        out[nm..].iter_mut().for_each(|r| *r = Vec3::zeros());
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
        if let Some(j) = self.tip_index(ctx.tip_id) {
            return ctx.tip_offset() * self.per_tip[j].1 * dt;
        }
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

    fn ctx_for(tip: u32, sensors: &mut SensorTable) -> PointContext {
        let g = TipGeometry {
            id: tip,
            probe: "p".into(),
            l1_mm: 50.0,
            radius_mm: 1.0,
            l2_mm: 20.0,
            beta1_deg: 90.0,
            l3_mm: 10.0,
            beta2_deg: 45.0,
        };
        let r = machine_from_probe(30.0, -60.0);
        let mut ctx = PointContext::at_rest(Vec3::zeros());
        ctx.tip_shank = r * g.shank_probe();
        ctx.tip_bent = r * g.bent_probe();
        ctx.tip_id = tip;
        let slot = sensors.slot(&default_sensor()).unwrap();
        ctx.temps[slot] = 23.5;
        ctx.temps_valid = 1 << slot;
        ctx
    }

    const ALPHAS: [f64; 4] = [1e-5, 1.1e-5, 1.2e-5, 1.3e-5];

    fn with_tips(split: bool) -> Config {
        let mut c = Config::zeros_per_tip(&[7, 3], split);
        let n = c.params().len();
        // Short decimals, which serde_json reads back exactly (it is built without
        // `float_roundtrip`).
        c.set_params(&ALPHAS[..n]);
        c
    }

    #[test]
    fn per_tip_coefficient_for_the_whole_stylus() {
        let mut sensors = SensorTable::default();
        for split in [false, true] {
            let c = with_tips(split);
            let nm = 1 + split as usize;
            // Tip-id order: tip 3, then tip 7.
            assert_eq!(c.alpha_per_tip[&3], ALPHAS[nm]);
            assert_eq!(c.alpha_per_tip[&7], ALPHAS[nm + 1]);
            let names = c.param_names();
            assert_eq!(names[nm], "tip 3 alpha (1/K)");
            assert_eq!(names[nm + 1], "tip 7 alpha (1/K)");
            let m = c.build(&mut sensors).unwrap();
            assert_eq!(m.n_params(), nm + 2);
            let cfg = EffectConfig::StylusThermal(c.clone());
            for tip in [1, 3, 7] {
                let ctx = ctx_for(tip, &mut sensors);
                let d = m.correction(&ctx);
                let want = match c.alpha_per_tip.get(&tip) {
                    Some(a) => ctx.tip_offset() * *a * 3.5,
                    None => {
                        (ctx.tip_shank * c.alpha_shank_per_k
                            + ctx.tip_bent * c.alpha_bent_per_k.unwrap_or(c.alpha_shank_per_k))
                            * 3.5
                    }
                };
                assert_eq!(d, want, "tip {tip}");
                assert_linear(&m, &cfg, &ctx);
                let mut r = vec![Vec3::new(9.0, 9.0, 9.0); m.n_params()];
                m.regressors(&ctx, &mut r);
                for (i, r) in r.iter().enumerate() {
                    let own = match tip {
                        3 => i == nm,
                        7 => i == nm + 1,
                        _ => i < nm,
                    };
                    assert_eq!(own, r.norm() > 0.0, "tip {tip} parameter {i}");
                }
            }
        }
    }

    #[test]
    fn serde_round_trip_and_old_documents() {
        for c in [
            Config::zeros(true),
            Config {
                alpha_shank_per_k: 1e-5,
                ..Config::zeros(false)
            },
            with_tips(false),
            with_tips(true),
        ] {
            let listed = !c.alpha_per_tip.is_empty();
            let e = EffectConfig::StylusThermal(c);
            let s = serde_json::to_string(&e).unwrap();
            assert_eq!(listed, s.contains("alpha_per_tip"), "{s}");
            let back: EffectConfig = serde_json::from_str(&s).unwrap();
            assert_eq!(back, e);
        }
        // Documents written before per-tip coefficients existed.
        let mut sensors = SensorTable::default();
        for (old, a_s, a_b) in [
            (
                r#"{"kind":"stylus_thermal","alpha_shank_per_k":1.15e-5,"alpha_bent_per_k":2.3e-5}"#,
                1.15e-5,
                2.3e-5,
            ),
            (
                r#"{"kind":"stylus_thermal","alpha_shank_per_k":1.15e-5,"reference_temp_c":20.0,"sensor":"stylus"}"#,
                1.15e-5,
                1.15e-5,
            ),
        ] {
            let EffectConfig::StylusThermal(c) = serde_json::from_str(old).unwrap() else {
                panic!()
            };
            assert!(c.alpha_per_tip.is_empty());
            let m = c.build(&mut sensors).unwrap();
            assert_eq!(m.n_params(), 1 + c.alpha_bent_per_k.is_some() as usize);
            for tip in [0, 1, 3, 7] {
                let ctx = ctx_for(tip, &mut sensors);
                // The formula before per-tip coefficients, bit for bit.
                let want = (ctx.tip_shank * a_s + ctx.tip_bent * a_b) * 3.5;
                assert_eq!(m.correction(&ctx), want);
                let mut r = vec![Vec3::zeros(); m.n_params()];
                m.regressors(&ctx, &mut r);
                if c.alpha_bent_per_k.is_some() {
                    assert_eq!(r, vec![ctx.tip_shank * 3.5, ctx.tip_bent * 3.5]);
                } else {
                    assert_eq!(r, vec![ctx.tip_offset() * 3.5]);
                }
            }
        }
    }

    #[test]
    fn validation_names_the_field() {
        let mut sensors = SensorTable::default();
        let mut c = with_tips(true);
        *c.alpha_per_tip.get_mut(&7).unwrap() = f64::NAN;
        assert_eq!(
            c.build(&mut sensors).unwrap_err(),
            "alpha_per_tip.7: must be a finite number"
        );
        let bad = r#"{"kind":"stylus_thermal","alpha_shank_per_k":0,"alpha_per_tip":{"2":"x"}}"#;
        assert!(serde_json::from_str::<EffectConfig>(bad).is_err());
    }
}
