//! Per-axis radial gain on arcs.
//!
//! Equation: on an arc of rotation frequency f about the commanded centre c, the correction
//! of axis i is δ_i = g_i(f)·(s_i − c_i), with g_i(f) = Σ_k α_{i,k}(p)·f^k (powers k from
//! `powers`, each coefficient a polynomial in position). Its physical term is f²: a compliance
//! γ_i between the scale's reading head and the probe (the probe head on its mount, or the
//! reading head on its bracket, whichever dominates that axis) displaces the probe by −γ_i·a_i
//! relative to what the scale reads; on a steady arc a_i = −(2πf)²·(s_i − c_i), so
//! δ_i = γ_i·(2πf)²·(s_i − c_i), i.e. α_{i,2} = 4π²·γ_i — the same displacement as the
//! diagonal of [`accel_deflection`](super::accel_deflection)'s P (α_{i,2} = −4π²·P_ii), seen
//! on arcs only (which is why the ring procedure reports the two as nearly one column). The
//! f¹ term and the position dependence are an empirical polynomial for what arcs show beyond
//! it (a mode's resonance approached, a drive's amplitude loss).
//!
//! Source idea: dynamic-error compensation of scanning CMMs — on a circle each axis sees a
//! sine, and a compliant element between scale and probe makes the fast circle larger or
//! smaller than commanded and elliptic when the axes differ, growing with f²; the correction
//! is applied about the commanded centre (the simulator's machine injects no gain formula: its
//! arc gain is this compliance, `scancorr-sim`'s `mount_compliance_s2`).

use super::{check_finite, Effect, PositionBasis};
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
    /// Powers of f in the polynomial (default [1, 2]).
    #[serde(default = "default_powers")]
    pub powers: Vec<u32>,
    /// α for X: monomial-major, then power (len = monomials × powers), 1/Hz^k.
    pub x: Vec<f64>,
    /// α for Y.
    pub y: Vec<f64>,
    /// α for Z.
    pub z: Vec<f64>,
}

fn default_powers() -> Vec<u32> {
    vec![1, 2]
}

/// Hot-path form.
#[derive(Debug, Clone)]
pub struct Model {
    basis: super::PreparedBasis,
    /// The powers of f (0..=4), indices into [`f_powers`].
    powers: Vec<usize>,
    /// α of the three axes side by side (one vector per monomial and power, monomial-major).
    alpha: Vec<Vec3>,
}

impl Config {
    /// Zero-parameter model.
    pub fn zeros(order: u8, powers: Vec<u32>) -> Config {
        let position = PositionBasis {
            order,
            ..Default::default()
        };
        let n = position.len() * powers.len();
        Config {
            id: None,
            position,
            powers,
            x: vec![0.0; n],
            y: vec![0.0; n],
            z: vec![0.0; n],
        }
    }
    /// Validates.
    pub fn build(&self) -> Result<Model, String> {
        self.position.validate("position")?;
        if self.powers.is_empty() || self.powers.iter().any(|p| *p > 4) {
            return Err("powers: must list powers of f between 0 and 4".into());
        }
        let n = self.position.len() * self.powers.len();
        for (name, v) in [("x", &self.x), ("y", &self.y), ("z", &self.z)] {
            if v.len() != n {
                return Err(format!(
                    "{name}: needs {n} coefficients (monomials × powers), got {}",
                    v.len()
                ));
            }
            check_finite(name, v)?;
        }
        Ok(Model {
            basis: self.position.into(),
            powers: self.powers.iter().map(|p| *p as usize).collect(),
            alpha: (0..n)
                .map(|k| Vec3::new(self.x[k], self.y[k], self.z[k]))
                .collect(),
        })
    }
    /// Flat parameters x, y, z.
    pub fn params(&self) -> Vec<f64> {
        self.x
            .iter()
            .chain(&self.y)
            .chain(&self.z)
            .copied()
            .collect()
    }
    /// Sets flat parameters.
    pub fn set_params(&mut self, v: &[f64]) {
        let n = self.x.len();
        self.x.copy_from_slice(&v[..n]);
        self.y.copy_from_slice(&v[n..2 * n]);
        self.z.copy_from_slice(&v[2 * n..3 * n]);
    }
    /// Parameter names.
    pub fn param_names(&self) -> Vec<String> {
        let mut v = vec![];
        for ax in ["x", "y", "z"] {
            for m in 0..self.position.len() {
                for p in &self.powers {
                    let (pow, unit) = match p {
                        1 => ("".to_string(), "1/Hz".to_string()),
                        p => (superscript(*p), format!("1/Hz{}", superscript(*p))),
                    };
                    v.push(format!(
                        "α_{ax} of f{pow}{} ({unit})",
                        super::monomial_suffix(m)
                    ));
                }
            }
        }
        v
    }
}

/// `n` as superscript digits (`2` → `²`).
fn superscript(n: u32) -> String {
    const D: [char; 10] = ['⁰', '¹', '²', '³', '⁴', '⁵', '⁶', '⁷', '⁸', '⁹'];
    n.to_string()
        .chars()
        .map(|c| D[c.to_digit(10).unwrap_or(0) as usize])
        .collect()
}

/// f⁰ … f⁴ by multiplication (no call to a power routine per point).
#[inline]
fn f_powers(f: f64) -> [f64; 5] {
    let f2 = f * f;
    [1.0, f, f2, f2 * f, f2 * f2]
}

impl Model {
    /// g_i = Σ_m ξ_m Σ_k α_{i,m,k} f^k, the three axes at once, for `NP` (= the number of
    /// powers) powers: the same additions in the same order as a loop over them.
    #[inline(always)]
    fn gain<const NP: usize>(&self, mono: &[f64], fp: &[f64; 5]) -> Vec3 {
        let powers: &[usize; NP] = self.powers[..NP]
            .try_into()
            .expect("a built model has NP powers");
        let mut g = Vec3::zeros();
        for (xi, a) in mono.iter().zip(self.alpha.chunks_exact(NP)) {
            let a: &[Vec3; NP] = a.try_into().expect("chunks of NP");
            let mut t = Vec3::zeros();
            for k in 0..NP {
                t += a[k] * fp[powers[k]];
            }
            g += t * *xi;
        }
        g
    }

    /// [`Model::gain`] for any number of powers: the loop over them.
    fn gain_any(&self, mono: &[f64], fp: &[f64; 5]) -> Vec3 {
        let mut g = Vec3::zeros();
        for (xi, a) in mono.iter().zip(self.alpha.chunks_exact(self.powers.len())) {
            let mut t = Vec3::zeros();
            for (a, p) in a.iter().zip(&self.powers) {
                t += a * fp[*p];
            }
            g += t * *xi;
        }
        g
    }
}

impl Effect for Model {
    fn n_params(&self) -> usize {
        3 * self.alpha.len()
    }
    fn regressors(&self, ctx: &PointContext, out: &mut [Vec3]) {
        out.iter_mut().for_each(|r| *r = Vec3::zeros());
        if ctx.arc_radius <= 0.0 {
            return;
        }
        let mut mono = [0.0; 10];
        let n = self.basis.eval(&ctx.scale, &mut mono);
        let r = ctx.scale - ctx.arc_center;
        let np = self.powers.len();
        let fp = f_powers(ctx.f_hz);
        for i in 0..3 {
            for (m, xi) in mono.iter().enumerate().take(n) {
                for (k, p) in self.powers.iter().enumerate() {
                    out[i * n * np + m * np + k][i] = xi * fp[*p] * r[i];
                }
            }
        }
    }
    #[inline]
    fn correction(&self, ctx: &PointContext) -> Vec3 {
        if ctx.arc_radius <= 0.0 {
            return Vec3::zeros();
        }
        let mut mono = [0.0; 10];
        let n = self.basis.eval(&ctx.scale, &mut mono);
        let fp = f_powers(ctx.f_hz);
        // The number of powers matched once: each monomial's sum is then a straight run of
        // code over an array of fixed length (no loop, no check per power).
        let g = match self.powers.len() {
            1 => self.gain::<1>(&mono[..n], &fp),
            2 => self.gain::<2>(&mono[..n], &fp),
            3 => self.gain::<3>(&mono[..n], &fp),
            4 => self.gain::<4>(&mono[..n], &fp),
            5 => self.gain::<5>(&mono[..n], &fp),
            // More powers than there are (one repeated): the loop over them.
            _ => self.gain_any(&mono[..n], &fp),
        };
        g.component_mul(&(ctx.scale - ctx.arc_center))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::effects::{testutil::assert_linear, EffectConfig};

    #[test]
    fn hand_computed_gain_correction() {
        let mut c = Config::zeros(0, vec![2]);
        c.x = vec![1e-4]; // g_x(f) = 1e-4 f²
        let m = c.build().unwrap();
        let mut ctx = PointContext::at_rest(Vec3::new(124.0, 3.0, 0.0));
        ctx.arc_center = Vec3::new(100.0, 0.0, 0.0);
        ctx.arc_radius = 25.0;
        ctx.f_hz = 3.0;
        // δx = 9e-4 · 24 = 0.0216 mm, about the centre.
        let d = m.correction(&ctx);
        assert!((d - Vec3::new(0.0216, 0.0, 0.0)).norm() < 1e-15, "{d:?}");
        assert_linear(&m, &EffectConfig::ServoGain(c.clone()), &ctx);
        let mut c2 = Config::zeros(1, vec![1, 2]);
        c2.y = vec![1e-3, 2e-4, 1e-5, 0.0, 3e-4, 0.0, 1e-6, 2e-6];
        ctx.scale = Vec3::new(80.0, 20.0, 5.0);
        assert_linear(&c2.build().unwrap(), &EffectConfig::ServoGain(c2), &ctx);
        ctx.arc_radius = 0.0;
        assert_eq!(m.correction(&ctx), Vec3::zeros());
    }

    /// The correction of 1 to 5 powers (each count its own straight code) and of more (a
    /// power repeated: the loop) is the loop's over the powers, bit for bit, at every order.
    #[test]
    fn each_count_of_powers_gives_the_loops_bits() {
        let powers_of = [
            vec![2],
            vec![1, 2],
            vec![0, 2, 4],
            vec![1, 2, 3, 4],
            vec![0, 1, 2, 3, 4],
            vec![1, 2, 2, 3, 0, 4],
        ];
        let mut ctx = PointContext::at_rest(Vec3::new(173.25, -41.5, 12.125));
        ctx.arc_center = Vec3::new(150.0, -20.0, 10.0);
        ctx.arc_radius = 31.0;
        ctx.f_hz = 1.7;
        let mut seed = 0x9e37_79b9_7f4a_7c15u64;
        let mut next = || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            (seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        };
        for powers in powers_of {
            for order in 0..=2 {
                let mut c = Config::zeros(order, powers.clone());
                for v in [&mut c.x, &mut c.y, &mut c.z] {
                    v.iter_mut().for_each(|a| *a = next() * 1e-4);
                }
                let m = c.build().unwrap();
                // The loop over the powers, as the correction was written before.
                let mut mono = [0.0; 10];
                let n = m.basis.eval(&ctx.scale, &mut mono);
                let g = m.gain_any(&mono[..n], &f_powers(ctx.f_hz));
                let want = g.component_mul(&(ctx.scale - ctx.arc_center));
                let got = m.correction(&ctx);
                assert!(want != Vec3::zeros(), "{powers:?} order {order}");
                for i in 0..3 {
                    assert_eq!(
                        got[i].to_bits(),
                        want[i].to_bits(),
                        "{powers:?} order {order} axis {i}: {got:?} against {want:?}"
                    );
                }
            }
        }
    }
}
