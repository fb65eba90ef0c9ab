//! Structure deflection under acceleration.
//!
//! Equation: D = P(p)·A, where A is the estimated acceleration (mm/s²) and
//! P(p) = Σ_m ξ_m(p)·P_m is a 3×3 compliance matrix (mm per mm/s², full cross-coupling)
//! whose entries are polynomials up to second order in the position p
//! ([`PositionBasis`](super::PositionBasis)). Correction = +D.
//!
//! Source idea: a machine's moving structure behaves as a compliant body — it bends in
//! proportion to the inertial load, and how much depends on where the carriages are
//! (dynamic-error compensation of scanning CMMs, e.g. Renishaw's and Zeiss's patents).

use super::{check_finite, Effect, PositionBasis, MONOMIALS};
use crate::sample::{PointContext, Vec3};
use serde::{Deserialize, Serialize};

/// Document form.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// Optional name (default `accel_deflection`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub id: Option<String>,
    /// Position dependence of P.
    #[serde(default)]
    pub position: PositionBasis,
    /// Only the diagonal of each P_m is a parameter (no cross-coupling).
    #[serde(default)]
    pub diagonal: bool,
    /// P_m, one 3×3 row-major matrix per monomial, mm/(mm/s²).
    pub p: Vec<[[f64; 3]; 3]>,
}

/// Hot-path form.
#[derive(Debug, Clone)]
pub struct Model {
    basis: super::PreparedBasis,
    diagonal: bool,
    p: Vec<nalgebra::Matrix3<f64>>,
    /// The monomials after the constant whose P_m is not all zero (the others add nothing).
    nonzero: Vec<usize>,
}

impl Config {
    /// A zero-parameter model of the given structure.
    pub fn zeros(order: u8, diagonal: bool) -> Config {
        let position = PositionBasis {
            order,
            ..Default::default()
        };
        Config {
            id: None,
            position,
            diagonal,
            p: vec![[[0.0; 3]; 3]; position.len()],
        }
    }

    /// Validates.
    pub fn build(&self) -> Result<Model, String> {
        self.position.validate("position")?;
        if self.p.len() != self.position.len() {
            return Err(format!(
                "p: position order {} needs {} matrices (monomials {}), got {}",
                self.position.order,
                self.position.len(),
                MONOMIALS[..self.position.len()].join(", "),
                self.p.len()
            ));
        }
        for (m, mat) in self.p.iter().enumerate() {
            for (i, row) in mat.iter().enumerate() {
                check_finite(&format!("p[{m}][{i}]"), row)?;
                for (j, v) in row.iter().enumerate() {
                    if self.diagonal && i != j && *v != 0.0 {
                        return Err(format!("p[{m}][{i}][{j}]: must be 0 when diagonal is true"));
                    }
                }
            }
        }
        let p = self
            .p
            .iter()
            .map(|m| nalgebra::Matrix3::from_fn(|i, j| m[i][j]))
            .collect();
        let nonzero = (1..self.p.len())
            .filter(|m| self.p[*m].iter().flatten().any(|v| *v != 0.0))
            .collect();
        Ok(Model {
            basis: self.position.into(),
            diagonal: self.diagonal,
            p,
            nonzero,
        })
    }

    fn index(&self) -> Vec<(usize, usize, usize)> {
        let mut v = vec![];
        for m in 0..self.position.len() {
            for i in 0..3 {
                for j in 0..3 {
                    if !self.diagonal || i == j {
                        v.push((m, i, j));
                    }
                }
            }
        }
        v
    }
    /// Flat parameters.
    pub fn params(&self) -> Vec<f64> {
        self.index()
            .into_iter()
            .map(|(m, i, j)| self.p[m][i][j])
            .collect()
    }
    /// Sets flat parameters.
    pub fn set_params(&mut self, v: &[f64]) {
        for ((m, i, j), x) in self.index().into_iter().zip(v) {
            self.p[m][i][j] = *x;
        }
    }
    /// Parameter names.
    pub fn param_names(&self) -> Vec<String> {
        let ax = ["x", "y", "z"];
        self.index()
            .into_iter()
            .map(|(m, i, j)| {
                format!(
                    "P[{}][{}]{} (mm per mm/s²)",
                    ax[i],
                    ax[j],
                    super::monomial_suffix(m)
                )
            })
            .collect()
    }
}

impl Effect for Model {
    fn n_params(&self) -> usize {
        self.basis.len() * if self.diagonal { 3 } else { 9 }
    }
    fn regressors(&self, ctx: &PointContext, out: &mut [Vec3]) {
        let mut mono = [0.0; 10];
        let n = self.basis.eval(&ctx.scale, &mut mono);
        let a = ctx.est_acc;
        let mut k = 0;
        for &xi in mono.iter().take(n) {
            for i in 0..3 {
                for j in 0..3 {
                    if !self.diagonal || i == j {
                        let mut r = Vec3::zeros();
                        r[i] = xi * a[j];
                        out[k] = r;
                        k += 1;
                    }
                }
            }
        }
    }
    #[inline]
    fn correction(&self, ctx: &PointContext) -> Vec3 {
        let mut mono = [0.0; 10];
        self.basis.eval(&ctx.scale, &mut mono);
        // Σ_m ξ_m·P_m over the monomials with a non-zero P_m (the constant always).
        let mut p = self.p[0];
        for &m in &self.nonzero {
            p += self.p[m] * mono[m];
        }
        p * ctx.est_acc
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::effects::{testutil::assert_linear, EffectConfig};

    #[test]
    fn hand_computed_deflection() {
        // P = diag(1e-6, 2e-6, 0) + x-linear cross term P[y][x] = 5e-7·ξx, ξx = x/500.
        let mut c = Config::zeros(1, false);
        c.p[0] = [[1e-6, 0.0, 0.0], [0.0, 2e-6, 0.0], [0.0, 0.0, 0.0]];
        c.p[1][1][0] = 5e-7;
        let m = c.build().unwrap();
        let mut ctx = PointContext::at_rest(Vec3::new(250.0, 0.0, 0.0));
        ctx.est_acc = Vec3::new(1000.0, -500.0, 0.0);
        // dx = 1e-6·1000 = 1e-3; dy = 2e-6·(−500) + 5e-7·0.5·1000 = −1e-3 + 2.5e-4.
        let d = m.correction(&ctx);
        assert!((d - Vec3::new(1e-3, -7.5e-4, 0.0)).norm() < 1e-15, "{d:?}");
        assert_linear(&m, &EffectConfig::AccelDeflection(c.clone()), &ctx);
        let mut dc = Config::zeros(2, true);
        dc.p[7] = [[1e-6, 0.0, 0.0], [0.0, 3e-7, 0.0], [0.0, 0.0, -2e-7]];
        let dm = dc.build().unwrap();
        ctx.scale = Vec3::new(100.0, -200.0, 50.0);
        ctx.est_acc = Vec3::new(10.0, 20.0, 30.0);
        assert_linear(&dm, &EffectConfig::AccelDeflection(dc), &ctx);
    }

    #[test]
    fn rejects_wrong_shapes() {
        let mut c = Config::zeros(1, true);
        c.p.pop();
        assert!(c.build().unwrap_err().starts_with("p:"));
        let mut c = Config::zeros(0, true);
        c.p[0][0][1] = 1.0;
        assert!(c.build().unwrap_err().contains("p[0][0][1]"));
    }
}
