//! Stylus bending with probing force.
//!
//! Equation: δ = R·(k ⊙ d), with d the deflection in probe axes, k = (k_u, k_v, k_w) one
//! dimensionless coefficient per probe direction and R the machine_from_probe rotation; the
//! corrected point is the one extrapolated to zero deflection.
//!
//! Per tip (optional, `per_tip`): δ = R·(k_t ⊙ d) with k_t the coefficients of the point's tip t
//! when t is listed, the machine's k otherwise. Each tip's k_t is a parameter triple of its own;
//! the machine's k regressors are zero for points of a listed tip and a tip's regressors are
//! zero for points of any other tip, so the effect stays linear in all parameters.
//!
//! Source idea: the probing force grows with deflection and bends the stylus by an amount
//! proportional to it, so points scanned at several deflections lie on a line whose value at
//! zero deflection is the true surface. The bending depends on the stylus (length, diameter,
//! material, crank), which is why a multi-stylus probe is qualified stylus by stylus
//! (ISO 10360-5): one k per tip rather than one for the machine.

use super::{check_finite, Effect};
use crate::sample::{PointContext, Vec3};
use serde::{de::Error as _, Deserialize, Deserializer, Serialize};
use std::collections::BTreeMap;

/// Reads a map keyed by tip id. JSON keys are strings, and inside the internally tagged
/// [`super::EffectConfig`] serde cannot turn them into integers itself; a key must be the
/// canonical decimal form of a u32 (no sign, no leading zeros), so no two keys name one tip.
pub(crate) fn tip_map<'de, D, V>(d: D) -> Result<BTreeMap<u32, V>, D::Error>
where
    D: Deserializer<'de>,
    V: Deserialize<'de>,
{
    BTreeMap::<String, V>::deserialize(d)?
        .into_iter()
        .map(|(k, v)| match k.parse::<u32>() {
            Ok(t) if t.to_string() == k => Ok((t, v)),
            _ => Err(D::Error::custom(format!(
                "tip id {k:?}: must be an unsigned integer"
            ))),
        })
        .collect()
}

/// Document form.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// Optional name.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub id: Option<String>,
    /// Coefficient per probe axis (u, v, w), mm of error per mm of deflection; used for every
    /// tip not listed in `per_tip`.
    pub k: [f64; 3],
    /// Coefficients per probe axis for individual tips (by tip id), replacing `k` for them.
    #[serde(
        default,
        deserialize_with = "tip_map",
        skip_serializing_if = "BTreeMap::is_empty"
    )]
    pub per_tip: BTreeMap<u32, [f64; 3]>,
}

/// Hot-path form.
#[derive(Debug, Clone)]
pub struct Model {
    k: Vec3,
    /// (tip id, k) sorted by tip id; the tip's parameters start at 3 + 3·index.
    per_tip: Vec<(u32, Vec3)>,
}

impl Config {
    /// Zero-parameter model.
    pub fn zeros() -> Config {
        Config {
            id: None,
            k: [0.0; 3],
            per_tip: BTreeMap::new(),
        }
    }
    /// Zero-parameter model with its own coefficients for each of `tips`.
    pub fn zeros_per_tip(tips: &[u32]) -> Config {
        Config {
            per_tip: tips.iter().map(|&t| (t, [0.0; 3])).collect(),
            ..Config::zeros()
        }
    }
    /// Validates.
    pub fn build(&self) -> Result<Model, String> {
        check_finite("k", &self.k)?;
        for (t, k) in &self.per_tip {
            check_finite(&format!("per_tip.{t}"), k)?;
        }
        Ok(Model {
            k: self.k.into(),
            per_tip: self.per_tip.iter().map(|(&t, &k)| (t, k.into())).collect(),
        })
    }
    /// Flat parameters: the machine's k, then each listed tip's k in tip-id order.
    pub fn params(&self) -> Vec<f64> {
        let mut v = self.k.to_vec();
        for k in self.per_tip.values() {
            v.extend_from_slice(k);
        }
        v
    }
    /// Sets flat parameters.
    pub fn set_params(&mut self, v: &[f64]) {
        self.k.copy_from_slice(&v[..3]);
        for (j, k) in self.per_tip.values_mut().enumerate() {
            k.copy_from_slice(&v[3 + 3 * j..6 + 3 * j]);
        }
    }
    /// Parameter names: `k_u (mm/mm)` for the machine, `tip 2 k_u (mm/mm)` for tip 2.
    pub fn param_names(&self) -> Vec<String> {
        let axes = ["u", "v", "w"];
        let mut v: Vec<String> = axes.iter().map(|a| format!("k_{a} (mm/mm)")).collect();
        for t in self.per_tip.keys() {
            v.extend(axes.iter().map(|a| format!("tip {t} k_{a} (mm/mm)")));
        }
        v
    }
}

impl Model {
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
        3 + 3 * self.per_tip.len()
    }
    fn regressors(&self, ctx: &PointContext, out: &mut [Vec3]) {
        let base = match self.tip_index(ctx.tip_id) {
            Some(j) => {
                out.iter_mut().for_each(|r| *r = Vec3::zeros());
                3 + 3 * j
            }
            None => {
                out[3..].iter_mut().for_each(|r| *r = Vec3::zeros());
                0
            }
        };
        for i in 0..3 {
            out[base + i] = ctx.machine_from_probe.column(i) * ctx.deflection_probe[i];
        }
    }
    #[inline]
    fn correction(&self, ctx: &PointContext) -> Vec3 {
        let k = match self.tip_index(ctx.tip_id) {
            Some(j) => &self.per_tip[j].1,
            None => &self.k,
        };
        ctx.machine_from_probe * k.component_mul(&ctx.deflection_probe)
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
            k: [0.02, 0.03, 0.0],
            ..Config::zeros()
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

    fn ctx_for(tip: u32) -> PointContext {
        let mut ctx = PointContext::at_rest(Vec3::new(10.0, 20.0, 30.0));
        ctx.deflection_probe = Vec3::new(0.3, -0.1, 0.2);
        ctx.machine_from_probe = machine_from_probe(37.0, -25.0);
        ctx.tip_id = tip;
        ctx
    }

    fn two_tips() -> Config {
        let mut c = Config::zeros_per_tip(&[5, 2]);
        c.set_params(&[0.01, 0.02, 0.03, 0.04, 0.05, 0.06, 0.07, 0.08, 0.09]);
        c
    }

    #[test]
    fn per_tip_coefficients_replace_the_machine_ones() {
        let c = two_tips();
        // Tip-id order: tip 2 first, then tip 5.
        assert_eq!(c.per_tip[&2], [0.04, 0.05, 0.06]);
        assert_eq!(c.per_tip[&5], [0.07, 0.08, 0.09]);
        let names = c.param_names();
        assert_eq!(names.len(), 9);
        assert_eq!(names[0], "k_u (mm/mm)");
        assert_eq!(names[3], "tip 2 k_u (mm/mm)");
        assert_eq!(names[8], "tip 5 k_w (mm/mm)");
        let m = c.build().unwrap();
        let cfg = EffectConfig::ProbeForce(c.clone());
        for (tip, k) in [
            (1, [0.01, 0.02, 0.03]),
            (2, [0.04, 0.05, 0.06]),
            (5, [0.07, 0.08, 0.09]),
        ] {
            let ctx = ctx_for(tip);
            let want = ctx.machine_from_probe * Vec3::from(k).component_mul(&ctx.deflection_probe);
            assert_eq!(m.correction(&ctx), want, "tip {tip}");
            assert_linear(&m, &cfg, &ctx);
            // Regressors of the other parameter groups are zero.
            let mut r = vec![Vec3::new(9.0, 9.0, 9.0); m.n_params()];
            m.regressors(&ctx, &mut r);
            let own = match tip {
                2 => 1,
                5 => 2,
                _ => 0,
            };
            for (g, chunk) in r.chunks(3).enumerate() {
                assert_eq!(g == own, chunk.iter().any(|v| v.norm() > 0.0), "tip {tip}");
            }
        }
    }

    #[test]
    fn serde_round_trip_and_old_documents() {
        for c in [
            Config {
                k: [0.01, 0.02, 0.03],
                ..Config::zeros()
            },
            two_tips(),
        ] {
            let e = EffectConfig::ProbeForce(c);
            let s = serde_json::to_string(&e).unwrap();
            assert_eq!(e.params().len() > 3, s.contains("per_tip"), "{s}");
            let back: EffectConfig = serde_json::from_str(&s).unwrap();
            assert_eq!(back, e);
        }
        // A document written before per-tip coefficients existed.
        let old = r#"{"kind":"probe_force","k":[0.01,0.02,0.03]}"#;
        let EffectConfig::ProbeForce(c) = serde_json::from_str(old).unwrap() else {
            panic!()
        };
        assert!(c.per_tip.is_empty());
        assert_eq!(c.params(), vec![0.01, 0.02, 0.03]);
        let m = c.build().unwrap();
        assert_eq!(m.n_params(), 3);
        for tip in [0, 1, 2, 7] {
            let ctx = ctx_for(tip);
            // The formula before per-tip coefficients, bit for bit.
            let k = Vec3::new(0.01, 0.02, 0.03);
            let want = ctx.machine_from_probe * k.component_mul(&ctx.deflection_probe);
            assert_eq!(m.correction(&ctx), want);
            let mut r = vec![Vec3::zeros(); 3];
            m.regressors(&ctx, &mut r);
            for (i, r) in r.iter().enumerate() {
                assert_eq!(
                    *r,
                    ctx.machine_from_probe.column(i) * ctx.deflection_probe[i]
                );
            }
        }
    }

    #[test]
    fn validation_names_the_field() {
        let mut c = two_tips();
        c.per_tip.get_mut(&2).unwrap()[1] = f64::NAN;
        assert_eq!(
            c.build().unwrap_err(),
            "per_tip.2[1]: must be a finite number"
        );
        let mut c = Config::zeros();
        c.k[2] = f64::INFINITY;
        assert_eq!(c.build().unwrap_err(), "k[2]: must be a finite number");
        let bad = r#"{"kind":"probe_force","k":[0,0,0],"per_tip":{"x":[0,0,0]}}"#;
        assert!(serde_json::from_str::<EffectConfig>(bad).is_err());
        for key in ["-1", "+2", "02", "4294967296"] {
            let bad =
                format!(r#"{{"kind":"probe_force","k":[0,0,0],"per_tip":{{"{key}":[0,0,0]}}}}"#);
            let e = serde_json::from_str::<EffectConfig>(&bad)
                .unwrap_err()
                .to_string();
            assert!(e.contains("must be an unsigned integer"), "{e}");
        }
    }
}
