//! Inter-axis phase lag on arcs.
//!
//! Equation: on an arc of commanded centre c with rotation frequency f and unit angular
//! velocity ŵ, axis i lags the reference axis X by the phase φ_i(f) = b2·f² + b1·f + b0
//! (each b may be a polynomial in position); its error is −φ_i·(ŵ × (s − c))_i, so the
//! correction is δ_i = φ_i(f)·(ŵ × (s − c))_i for i ∈ {y, z} (a common lag only slides points
//! along the arc and is not observable, so X is the reference).
//!
//! Source idea: the patented phase-lag correction for scanning on circles (e.g. Renishaw's
//! "method for calibrating a scanning system"): the axes' dynamic responses differ by a
//! frequency-dependent phase that turns a circle into a tilted ellipse.

use super::{check_finite, Effect, PositionBasis, MONOMIALS};
use crate::sample::{PointContext, Vec3};
use serde::{Deserialize, Serialize};

/// Document form.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// Optional name.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub id: Option<String>,
    /// Position dependence of the coefficients.
    #[serde(default)]
    pub position: PositionBasis,
    /// Lag of Y behind X: one [b0 (rad), b1 (rad/Hz), b2 (rad/Hz²)] per monomial.
    pub y: Vec<[f64; 3]>,
    /// Lag of Z behind X: one [b0, b1, b2] per monomial.
    pub z: Vec<[f64; 3]>,
}

/// Hot-path form.
#[derive(Debug, Clone)]
pub struct Model {
    basis: PositionBasis,
    y: Vec<[f64; 3]>,
    z: Vec<[f64; 3]>,
}

impl Config {
    /// Zero-parameter model.
    pub fn zeros(order: u8) -> Config {
        let position = PositionBasis {
            order,
            ..Default::default()
        };
        Config {
            id: None,
            position,
            y: vec![[0.0; 3]; position.len()],
            z: vec![[0.0; 3]; position.len()],
        }
    }
    /// Validates.
    pub fn build(&self) -> Result<Model, String> {
        self.position.validate("position")?;
        for (name, v) in [("y", &self.y), ("z", &self.z)] {
            if v.len() != self.position.len() {
                return Err(format!(
                    "{name}: needs {} coefficient triples, got {}",
                    self.position.len(),
                    v.len()
                ));
            }
            for (m, b) in v.iter().enumerate() {
                check_finite(&format!("{name}[{m}]"), b)?;
            }
        }
        Ok(Model {
            basis: self.position,
            y: self.y.clone(),
            z: self.z.clone(),
        })
    }
    /// Flat parameters: y then z, monomial-major, b0..b2.
    pub fn params(&self) -> Vec<f64> {
        self.y
            .iter()
            .chain(self.z.iter())
            .flat_map(|b| b.iter().copied())
            .collect()
    }
    /// Sets flat parameters.
    pub fn set_params(&mut self, v: &[f64]) {
        let n = self.y.len();
        for (k, x) in v.iter().enumerate() {
            let (arr, idx) = if k < 3 * n {
                (&mut self.y, k)
            } else {
                (&mut self.z, k - 3 * n)
            };
            arr[idx / 3][idx % 3] = *x;
        }
    }
    /// Parameter names.
    pub fn param_names(&self) -> Vec<String> {
        let mut v = vec![];
        for ax in ["y", "z"] {
            for m in MONOMIALS.iter().take(self.position.len()) {
                for (k, unit) in ["rad", "rad/Hz", "rad/Hz²"].iter().enumerate() {
                    v.push(format!("φ_{ax} b{k}·{m} ({unit})"));
                }
            }
        }
        v
    }
}

#[inline]
fn lever(ctx: &PointContext) -> Option<Vec3> {
    if ctx.arc_radius > 0.0 && ctx.rot_axis != Vec3::zeros() {
        Some(ctx.rot_axis.cross(&(ctx.scale - ctx.arc_center)))
    } else {
        None
    }
}

impl Effect for Model {
    fn n_params(&self) -> usize {
        6 * self.basis.len()
    }
    fn regressors(&self, ctx: &PointContext, out: &mut [Vec3]) {
        out.iter_mut().for_each(|r| *r = Vec3::zeros());
        let Some(l) = lever(ctx) else { return };
        let mut mono = [0.0; 10];
        let n = self.basis.eval(&ctx.scale, &mut mono);
        let f = ctx.f_hz;
        let fp = [1.0, f, f * f];
        for (a, axis) in [1usize, 2].iter().enumerate() {
            for (m, xi) in mono.iter().enumerate().take(n) {
                for k in 0..3 {
                    out[a * 3 * n + 3 * m + k][*axis] = xi * fp[k] * l[*axis];
                }
            }
        }
    }
    #[inline]
    fn correction(&self, ctx: &PointContext) -> Vec3 {
        let Some(l) = lever(ctx) else {
            return Vec3::zeros();
        };
        let mut mono = [0.0; 10];
        let n = self.basis.eval(&ctx.scale, &mut mono);
        let f = ctx.f_hz;
        let (mut py, mut pz) = (0.0, 0.0);
        for m in 0..n {
            let (y, z) = (self.y[m], self.z[m]);
            py += mono[m] * (y[0] + f * (y[1] + f * y[2]));
            pz += mono[m] * (z[0] + f * (z[1] + f * z[2]));
        }
        Vec3::new(0.0, py * l.y, pz * l.z)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::effects::{testutil::assert_linear, EffectConfig};

    #[test]
    fn hand_computed_phase_correction() {
        // CCW circle in XY (ŵ = +z), centre (100, 0, 0), probe at angle 0 (x = 125).
        let mut c = Config::zeros(0);
        c.y[0] = [0.0, 1e-3, 2e-4]; // φ_y(f) = 1e-3 f + 2e-4 f²
        let m = c.build().unwrap();
        let mut ctx = PointContext::at_rest(Vec3::new(125.0, 0.0, 0.0));
        ctx.arc_center = Vec3::new(100.0, 0.0, 0.0);
        ctx.arc_radius = 25.0;
        ctx.f_hz = 2.0;
        ctx.rot_axis = Vec3::z();
        // φ = 2e-3 + 8e-4 = 2.8e-3 rad; ŵ × r = z × (25,0,0) = (0,25,0); δy = 0.07 mm.
        let d = m.correction(&ctx);
        assert!((d - Vec3::new(0.0, 0.07, 0.0)).norm() < 1e-15, "{d:?}");
        // Clockwise flips the sign; off the arc nothing.
        ctx.rot_axis = -Vec3::z();
        assert!((m.correction(&ctx) + Vec3::new(0.0, 0.07, 0.0)).norm() < 1e-15);
        assert_linear(&m, &EffectConfig::ServoPhase(c.clone()), &ctx);
        ctx.arc_radius = 0.0;
        assert_eq!(m.correction(&ctx), Vec3::zeros());
        let mut c1 = Config::zeros(1);
        c1.z[2] = [1e-4, 2e-5, 3e-6];
        c1.y[1] = [1e-4, 0.0, 3e-6];
        ctx.arc_radius = 25.0;
        ctx.scale = Vec3::new(110.0, 20.0, 30.0);
        ctx.rot_axis = Vec3::new(0.0, 0.6, 0.8);
        assert_linear(&c1.build().unwrap(), &EffectConfig::ServoPhase(c1), &ctx);
    }
}
