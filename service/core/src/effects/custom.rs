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
use crate::expr::{Expr, Program};
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

#[derive(Debug, Clone, Copy, PartialEq)]
enum Sig {
    Builtin(usize),
    Temp(usize),
}

/// Hot-path form: the terms' expressions compiled together into one [`Program`] over the
/// distinct signals they read (each read once per point).
#[derive(Debug, Clone)]
pub struct Model {
    signals: Vec<Sig>,
    program: Program,
    /// Axis index of each term.
    axes: Vec<usize>,
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
        let mut signals: Vec<Sig> = vec![];
        let mut terms = vec![];
        for (i, t) in self.terms.iter().enumerate() {
            let e = Expr::parse(&t.expr).map_err(|e| format!("terms[{i}].expr: {e}"))?;
            let mut inputs = vec![];
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
                let k = signals.iter().position(|x| *x == s).unwrap_or_else(|| {
                    signals.push(s);
                    signals.len() - 1
                });
                inputs.push(k);
            }
            terms.push((e, inputs));
        }
        let exprs: Vec<(&Expr, &[usize])> = terms.iter().map(|(e, i)| (e, i.as_slice())).collect();
        Ok(Model {
            program: Program::compile(&exprs, signals.len()),
            signals,
            axes: self.terms.iter().map(|t| t.axis.index()).collect(),
            coef: self.coefficients.clone(),
        })
    }
}

#[inline]
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
    /// Hands each term's value (0 where it is not a finite number) to `out(term, value)`.
    #[inline]
    fn term_values(&self, ctx: &PointContext, mut out: impl FnMut(usize, f64)) {
        let input = |i: usize| match self.signals[i] {
            Sig::Builtin(k) => builtin(ctx, k),
            Sig::Temp(slot) => temp(ctx, slot, 20.0),
        };
        self.program.eval_with(input, |t, x| {
            out(t, if x.is_finite() { x } else { 0.0 });
        });
    }
}

impl Effect for Model {
    fn n_params(&self) -> usize {
        self.axes.len()
    }
    fn regressors(&self, ctx: &PointContext, out: &mut [Vec3]) {
        self.term_values(ctx, |t, x| {
            out[t] = Vec3::zeros();
            out[t][self.axes[t]] = x;
        });
    }
    fn correction(&self, ctx: &PointContext) -> Vec3 {
        let mut d = Vec3::zeros();
        self.term_values(ctx, |t, x| d[self.axes[t]] += self.coef[t] * x);
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
