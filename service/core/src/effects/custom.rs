//! User-defined effects.
//!
//! Equation: δ = Σ_t c_t·e_{axis(t)}·g_t(signals), where each term t has an axis and an
//! expression g_t over named signals of the point (see [`SIGNALS`]) and the coefficients c_t
//! are fitted like any built-in effect's parameters.
//!
//! Source idea: sparse-regression model discovery (SINDy) — a candidate term is any function
//! of the measured signals, and a model linear in such terms is fitted by least squares. This
//! is how a user adds an effect the library does not have (an encoder's cyclic error
//! `sin(2*pi*x/4)`, backlash at reversal `sign(vx)`).

use super::{temp, Effect, SensorTable};
use crate::expr::Expr;
use crate::sample::{Axis, PointContext, Vec3};
use serde::{Deserialize, Serialize};

/// Signals an expression may use; temperatures are `T_<sensor>` (e.g. `T_air`).
pub const SIGNALS: [(&str, &str); 29] = [
    ("x", "scale reading x, mm"),
    ("y", "scale reading y, mm"),
    ("z", "scale reading z, mm"),
    ("ex", "estimated position x, mm"),
    ("ey", "estimated position y, mm"),
    ("ez", "estimated position z, mm"),
    ("vx", "estimated velocity x, mm/s"),
    ("vy", "estimated velocity y, mm/s"),
    ("vz", "estimated velocity z, mm/s"),
    ("speed", "estimated speed, mm/s"),
    ("ax", "estimated acceleration x, mm/s²"),
    ("ay", "estimated acceleration y, mm/s²"),
    ("az", "estimated acceleration z, mm/s²"),
    ("acc", "estimated acceleration magnitude, mm/s²"),
    ("f", "rotation frequency on arcs, Hz"),
    (
        "wz",
        "z component of the unit rotation axis (+1 CCW, −1 CW seen from +z)",
    ),
    ("cx", "arc centre x, mm"),
    ("cy", "arc centre y, mm"),
    ("cz", "arc centre z, mm"),
    ("r", "commanded arc radius, mm (0 off arcs)"),
    ("du", "deflection u (probe axes), mm"),
    ("dv", "deflection v (probe axes), mm"),
    ("dw", "deflection w (probe axes), mm"),
    ("defl", "deflection magnitude, mm"),
    ("a1", "head angle A1, degrees"),
    ("a2", "head angle A2, degrees"),
    ("tip", "tip id"),
    ("t", "controller time, s"),
    ("seg", "segment id"),
];

/// One term: a regressor along one axis.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Term {
    /// Machine axis the term acts along.
    pub axis: Axis,
    /// The expression.
    pub expr: String,
}

/// Document form.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// Name of the effect (required: it labels the correction in every point).
    pub id: String,
    /// Depends on the estimated motion (left out while an alarm suspends corrections).
    #[serde(default)]
    pub dynamic: bool,
    /// Terms.
    pub terms: Vec<Term>,
    /// One coefficient per term.
    pub coefficients: Vec<f64>,
}

#[derive(Debug, Clone, Copy)]
enum Sig {
    Builtin(usize),
    Temp(usize),
}

/// Hot-path form.
#[derive(Debug, Clone)]
pub struct Model {
    terms: Vec<(usize, Expr, Vec<Sig>)>,
    coef: Vec<f64>,
}

impl Config {
    /// Validates and compiles the expressions.
    pub fn build(&self, sensors: &mut SensorTable) -> Result<Model, String> {
        if self.id.trim().is_empty() {
            return Err("id: a custom effect needs a name".into());
        }
        if self.terms.is_empty() {
            return Err("terms: at least one term is needed".into());
        }
        if self.coefficients.len() != self.terms.len() {
            return Err(format!(
                "coefficients: one per term ({}), got {}",
                self.terms.len(),
                self.coefficients.len()
            ));
        }
        super::check_finite("coefficients", &self.coefficients)?;
        let mut terms = vec![];
        for (i, t) in self.terms.iter().enumerate() {
            let e = Expr::parse(&t.expr).map_err(|e| format!("terms[{i}].expr: {e}"))?;
            let mut sigs = vec![];
            for v in &e.vars {
                let s = if let Some(k) = SIGNALS.iter().position(|(n, _)| n == v) {
                    Sig::Builtin(k)
                } else if let Some(sensor) = v.strip_prefix("T_") {
                    Sig::Temp(
                        sensors
                            .slot(sensor)
                            .map_err(|e| format!("terms[{i}].expr: {e}"))?,
                    )
                } else {
                    let known: Vec<&str> = SIGNALS.iter().map(|(n, _)| *n).collect();
                    return Err(format!(
                        "terms[{i}].expr: unknown signal '{v}' (known: {}, and T_<sensor>)",
                        known.join(", ")
                    ));
                };
                sigs.push(s);
            }
            terms.push((t.axis.index(), e, sigs));
        }
        Ok(Model {
            terms,
            coef: self.coefficients.clone(),
        })
    }
}

fn builtin(ctx: &PointContext, k: usize) -> f64 {
    let v = &ctx.est_vel;
    let a = &ctx.est_acc;
    match k {
        0..=2 => ctx.scale[k],
        3..=5 => ctx.est_pos[k - 3],
        6..=8 => v[k - 6],
        9 => v.norm(),
        10..=12 => a[k - 10],
        13 => a.norm(),
        14 => ctx.f_hz,
        15 => ctx.rot_axis.z,
        16..=18 => ctx.arc_center[k - 16],
        19 => ctx.arc_radius,
        20..=22 => ctx.deflection_probe[k - 20],
        23 => ctx.deflection.norm(),
        24 => ctx.head_a1_deg,
        25 => ctx.head_a2_deg,
        26 => ctx.tip_id as f64,
        27 => ctx.t_ns as f64 * 1e-9,
        _ => ctx.segment_id as f64,
    }
}

impl Model {
    #[inline]
    fn term_value(&self, ctx: &PointContext, t: usize) -> f64 {
        let (_, e, sigs) = &self.terms[t];
        let mut vals = [0.0; 16];
        let mut heap;
        let v: &mut [f64] = if sigs.len() <= 16 {
            &mut vals
        } else {
            heap = vec![0.0; sigs.len()];
            &mut heap
        };
        for (i, s) in sigs.iter().enumerate() {
            v[i] = match *s {
                Sig::Builtin(k) => builtin(ctx, k),
                Sig::Temp(slot) => temp(ctx, slot, 20.0),
            };
        }
        let x = e.eval(v);
        if x.is_finite() {
            x
        } else {
            0.0
        }
    }
}

impl Effect for Model {
    fn n_params(&self) -> usize {
        self.terms.len()
    }
    fn regressors(&self, ctx: &PointContext, out: &mut [Vec3]) {
        for t in 0..self.terms.len() {
            out[t] = Vec3::zeros();
            out[t][self.terms[t].0] = self.term_value(ctx, t);
        }
    }
    fn correction(&self, ctx: &PointContext) -> Vec3 {
        let mut d = Vec3::zeros();
        for t in 0..self.terms.len() {
            d[self.terms[t].0] += self.coef[t] * self.term_value(ctx, t);
        }
        d
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::effects::{testutil::assert_linear, EffectConfig};

    #[test]
    fn cyclic_error_and_backlash() {
        let c = Config {
            id: "x_cyclic".into(),
            dynamic: false,
            terms: vec![
                Term {
                    axis: Axis::X,
                    expr: "sin(2*pi*x/4)".into(),
                },
                Term {
                    axis: Axis::X,
                    expr: "cos(2*pi*x/4)".into(),
                },
                Term {
                    axis: Axis::Y,
                    expr: "sign(vy) * (T_air - 20)".into(),
                },
            ],
            coefficients: vec![1e-3, 2e-3, 5e-4],
        };
        let mut sensors = SensorTable::default();
        let m = c.build(&mut sensors).unwrap();
        assert_eq!(sensors.names(), &["air".to_string()]);
        let mut ctx = PointContext::at_rest(Vec3::new(1.0, 0.0, 0.0));
        ctx.est_vel = Vec3::new(0.0, -5.0, 0.0);
        ctx.temps[0] = 22.0;
        ctx.temps_valid = 1;
        // x = 1: sin(π/2) = 1, cos = 0 → dx = 1e-3; dy = 5e-4·(−1)·2 = −1e-3.
        let d = m.correction(&ctx);
        assert!((d - Vec3::new(1e-3, -1e-3, 0.0)).norm() < 1e-15, "{d:?}");
        assert_linear(&m, &EffectConfig::Custom(c.clone()), &ctx);
        let bad = Config {
            terms: vec![Term {
                axis: Axis::X,
                expr: "sin(q)".into(),
            }],
            coefficients: vec![0.0],
            ..c
        };
        let e = bad.build(&mut sensors).unwrap_err();
        assert!(e.contains("terms[0].expr") && e.contains("'q'"), "{e}");
    }
}
