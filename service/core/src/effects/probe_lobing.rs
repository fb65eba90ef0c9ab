//! Direction-dependent probe error ("lobing"): the pre-travel variation of a probe.
//!
//! Equation: with d the stylus deflection in probe axes (u, v, w), φ = atan2(d_v, d_u) the
//! probing direction in the probe's u-v plane, θ the polar angle from the w axis
//! (sin θ = |d_uv|/|d|, cos θ = d_w/|d|) and n = d_machine/|d_machine| the probing direction in
//! machine axes (the surface normal the corrector uses),
//!
//! δ = n · [ sin θ · Σ_{k=2..K} (a_k cos kφ + b_k sin kφ) + Σ_{j=1..P} c_j cos^j θ ],
//!
//! and δ = 0 when |d_machine| is below `min_deflection_mm` (no contact, no direction). On the
//! probe's equator (scanning in the u-v plane, sin θ = 1) this is the plain Fourier series of
//! the lobing; the sin θ weight fades the in-plane lobes out towards axial probing, where φ is
//! undefined, so the correction stays continuous. The polar terms vanish on the equator.
//! Harmonics 0 and 1 are left out: a constant along the normal is the tip radius and the first
//! harmonic a shift of the tip centre, both set by tip qualification on a reference sphere.
//! Positive a_k, b_k move the corrected point along n (out of the material).
//!
//! Source idea: a kinematic touch-trigger probe (three seats at 120°) triggers after a
//! pre-travel that depends on the probing direction with three-fold symmetry; scanning probes
//! show a similar direction-dependent error from the anisotropic stiffness of their
//! suspension. It appears as the probing form error of ISO 10360-5 (PForm on the test
//! sphere) and as a k-lobed form on a ring gauge.

use super::{check_finite, Effect};
use crate::sample::{PointContext, Vec3};
use serde::{Deserialize, Serialize};

/// Highest harmonic allowed.
pub const MAX_HARMONIC: u8 = 8;
/// Most polar terms.
pub const MAX_POLAR: usize = 4;

/// Document form.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// Optional name.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub id: Option<String>,
    /// Highest harmonic K of φ (2…8); the series runs over k = 2…K.
    pub max_harmonic: u8,
    /// Cosine amplitudes a_2…a_K, mm.
    pub a_mm: Vec<f64>,
    /// Sine amplitudes b_2…b_K, mm.
    pub b_mm: Vec<f64>,
    /// Polar terms c_1…c_P (coefficients of cos^j θ), mm; empty: none (P ≤ 4).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub polar_mm: Vec<f64>,
    /// Below this deflection (machine axes) there is no probing direction and no correction,
    /// mm.
    #[serde(default = "default_min_deflection")]
    pub min_deflection_mm: f64,
}

fn default_min_deflection() -> f64 {
    0.005
}

/// Hot-path form.
#[derive(Debug, Clone)]
pub struct Model {
    a: Vec<f64>,
    b: Vec<f64>,
    polar: Vec<f64>,
    min_defl: f64,
}

impl Config {
    /// Zero-parameter model with harmonics 2…`max_harmonic` and `polar` polar terms.
    pub fn zeros(max_harmonic: u8, polar: usize) -> Config {
        let n = (max_harmonic.max(2) - 1) as usize;
        Config {
            id: None,
            max_harmonic,
            a_mm: vec![0.0; n],
            b_mm: vec![0.0; n],
            polar_mm: vec![0.0; polar],
            min_deflection_mm: default_min_deflection(),
        }
    }
    /// Validates.
    pub fn build(&self) -> Result<Model, String> {
        if !(2..=MAX_HARMONIC).contains(&self.max_harmonic) {
            return Err(format!("max_harmonic: must be 2…{MAX_HARMONIC}"));
        }
        let n = self.max_harmonic as usize - 1;
        for (field, v) in [("a_mm", &self.a_mm), ("b_mm", &self.b_mm)] {
            if v.len() != n {
                return Err(format!(
                    "{field}: needs one value per harmonic 2…{} ({n}), got {}",
                    self.max_harmonic,
                    v.len()
                ));
            }
            check_finite(field, v)?;
        }
        if self.polar_mm.len() > MAX_POLAR {
            return Err(format!(
                "polar_mm: at most {MAX_POLAR} terms, got {}",
                self.polar_mm.len()
            ));
        }
        check_finite("polar_mm", &self.polar_mm)?;
        let m = self.min_deflection_mm;
        if !(m.is_finite() && m > 0.0) {
            return Err("min_deflection_mm: must be a finite number > 0".into());
        }
        Ok(Model {
            a: self.a_mm.clone(),
            b: self.b_mm.clone(),
            polar: self.polar_mm.clone(),
            min_defl: m,
        })
    }
    /// Flat parameters: a_2…a_K, b_2…b_K, c_1…c_P.
    pub fn params(&self) -> Vec<f64> {
        self.a_mm
            .iter()
            .chain(&self.b_mm)
            .chain(&self.polar_mm)
            .copied()
            .collect()
    }
    /// Sets flat parameters.
    pub fn set_params(&mut self, v: &[f64]) {
        let mut it = v.iter().copied();
        for x in self
            .a_mm
            .iter_mut()
            .chain(self.b_mm.iter_mut())
            .chain(self.polar_mm.iter_mut())
        {
            *x = it.next().unwrap();
        }
    }
    /// Parameter names: `a3 (mm)`, `b3 (mm)`, `polar c1 (mm)`.
    pub fn param_names(&self) -> Vec<String> {
        let k = 2..2 + self.a_mm.len();
        k.clone()
            .map(|k| format!("a{k} (mm)"))
            .chain(k.map(|k| format!("b{k} (mm)")))
            .chain((1..=self.polar_mm.len()).map(|j| format!("polar c{j} (mm)")))
            .collect()
    }
}

/// The direction features of one point: n, sin θ, (cos φ, sin φ), cos θ; None without
/// contact.
#[inline]
fn direction(ctx: &PointContext, min_defl: f64) -> Option<(Vec3, f64, (f64, f64), f64)> {
    let dm = ctx.deflection.norm();
    let d = &ctx.deflection_probe;
    let dn = d.norm();
    if dm.is_nan() || dm < min_defl || dn == 0.0 {
        return None;
    }
    let duv = d.x.hypot(d.y);
    let phi = if duv > 0.0 {
        (d.x / duv, d.y / duv)
    } else {
        (1.0, 0.0)
    };
    Some((ctx.deflection / dm, duv / dn, phi, d.z / dn))
}

impl Effect for Model {
    fn n_params(&self) -> usize {
        2 * self.a.len() + self.polar.len()
    }
    fn regressors(&self, ctx: &PointContext, out: &mut [Vec3]) {
        out.iter_mut().for_each(|r| *r = Vec3::zeros());
        let Some((n, sin_t, (c1, s1), cos_t)) = direction(ctx, self.min_defl) else {
            return;
        };
        let na = self.a.len();
        // cos kφ, sin kφ by rotation: (c_k, s_k) = (c_{k−1}, s_{k−1})·(c1, s1).
        let (mut c, mut s) = (c1, s1);
        for k in 0..na {
            (c, s) = (c * c1 - s * s1, s * c1 + c * s1);
            out[k] = n * (sin_t * c);
            out[na + k] = n * (sin_t * s);
        }
        let mut p = 1.0;
        for j in 0..self.polar.len() {
            p *= cos_t;
            out[2 * na + j] = n * p;
        }
    }
    #[inline]
    fn correction(&self, ctx: &PointContext) -> Vec3 {
        let Some((n, sin_t, (c1, s1), cos_t)) = direction(ctx, self.min_defl) else {
            return Vec3::zeros();
        };
        let (mut c, mut s) = (c1, s1);
        let mut g = 0.0;
        for (a, b) in self.a.iter().zip(&self.b) {
            (c, s) = (c * c1 - s * s1, s * c1 + c * s1);
            g += a * c + b * s;
        }
        g *= sin_t;
        let mut p = 1.0;
        for cj in &self.polar {
            p *= cos_t;
            g += cj * p;
        }
        n * g
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::effects::{testutil::assert_linear, EffectConfig};
    use crate::stylus::machine_from_probe;
    use std::f64::consts::TAU;

    fn probing(dir_machine: Vec3, head_a1_deg: f64) -> PointContext {
        let mut ctx = PointContext::at_rest(Vec3::new(100.0, 200.0, -50.0));
        ctx.machine_from_probe = machine_from_probe(head_a1_deg, 0.0);
        ctx.deflection = dir_machine;
        ctx.deflection_probe = ctx.machine_from_probe.transpose() * dir_machine;
        ctx
    }

    /// Radial correction around a bore at `n` angles; the stylus is pushed towards the
    /// centre, so n = −radial.
    fn ring(m: &Model, a1: f64, n: usize) -> Vec<(f64, f64)> {
        (0..n)
            .map(|i| {
                let t = TAU * i as f64 / n as f64;
                let radial = Vec3::new(t.cos(), t.sin(), 0.0);
                (t, m.correction(&probing(-radial * 0.3, a1)).dot(&radial))
            })
            .collect()
    }

    fn harmonic(r: &[(f64, f64)], k: f64) -> (f64, f64) {
        let n = r.len() as f64;
        let c = r.iter().map(|(t, v)| v * (k * t).cos()).sum::<f64>() * 2.0 / n;
        let s = r.iter().map(|(t, v)| v * (k * t).sin()).sum::<f64>() * 2.0 / n;
        (c, s)
    }

    #[test]
    fn three_lobed_probe_gives_a_three_lobed_ring() {
        let mut c = Config::zeros(6, 0);
        c.a_mm[1] = 0.8e-3; // a3 = 0.8 µm
        let m = c.build().unwrap();
        let r = ring(&m, 0.0, 360);
        // φ = t + π in the probe plane: radial = −a3 cos 3(t + π) = a3 cos 3t.
        let (c3, s3) = harmonic(&r, 3.0);
        assert!((c3 - 0.8e-3).abs() < 1e-12 && s3.abs() < 1e-12, "{c3} {s3}");
        for k in [1.0, 2.0, 4.0, 5.0, 6.0] {
            let (ck, sk) = harmonic(&r, k);
            assert!(ck.hypot(sk) < 1e-12, "harmonic {k}: {ck} {sk}");
        }
        let peak = r.iter().map(|(_, v)| v.abs()).fold(0.0, f64::max);
        assert!((peak - 0.8e-3).abs() < 1e-12);
        // The lobes turn with the head: A1 = 40° shifts the 3θ pattern by 40° (120° of phase).
        let (c3, s3) = harmonic(&ring(&m, 40.0, 360), 3.0);
        assert!((c3.hypot(s3) - 0.8e-3).abs() < 1e-12);
        let phase = s3.atan2(c3).to_degrees();
        assert!((phase - 120.0).abs() < 1e-6, "{phase}");
    }

    #[test]
    fn linear_threshold_and_polar_terms() {
        let mut c = Config::zeros(8, 2);
        let p: Vec<f64> = (0..c.params().len())
            .map(|i| 1e-4 * (1.0 + i as f64).sin())
            .collect();
        c = match EffectConfig::ProbeLobing(c).with_params(&p).unwrap() {
            EffectConfig::ProbeLobing(c) => c,
            _ => unreachable!(),
        };
        let m = c.build().unwrap();
        assert_eq!(m.n_params(), 7 + 7 + 2);
        for (dir, a1) in [
            (Vec3::new(0.2, -0.1, 0.05), 0.0),
            (Vec3::new(-0.02, 0.3, 0.0), 75.0),
            (Vec3::new(0.0, 0.0, 0.3), 0.0),
        ] {
            assert_linear(&m, &EffectConfig::ProbeLobing(c.clone()), &probing(dir, a1));
        }
        // Axial probing: only the polar terms, along n.
        let d = m.correction(&probing(Vec3::new(0.0, 0.0, 0.3), 0.0));
        assert!((d - Vec3::z() * (p[14] + p[15])).norm() < 1e-15, "{d:?}");
        // Below the threshold: nothing (regressors too).
        let ctx = probing(Vec3::new(0.004, 0.0, 0.0), 0.0);
        assert_eq!(m.correction(&ctx), Vec3::zeros());
        assert_linear(&m, &EffectConfig::ProbeLobing(c.clone()), &ctx);
        let names = c.param_names();
        assert_eq!(names[1], "a3 (mm)");
        assert_eq!(names[8], "b3 (mm)");
        assert_eq!(names[14], "polar c1 (mm)");
    }

    #[test]
    fn serde_round_trip_and_validation() {
        let mut c = Config::zeros(4, 1);
        c.a_mm[1] = 1e-3;
        c.id = Some("lobes".into());
        let e = EffectConfig::ProbeLobing(c.clone());
        let s = serde_json::to_string(&e).unwrap();
        assert!(s.contains("\"kind\":\"probe_lobing\""));
        assert_eq!(serde_json::from_str::<EffectConfig>(&s).unwrap(), e);
        assert_eq!(e.id(), "lobes");
        let doc = r#"{"kind":"probe_lobing","max_harmonic":3,"a_mm":[1e-3,0,0],"b_mm":[0,0]}"#;
        let bad = serde_json::from_str::<EffectConfig>(doc).unwrap();
        let mut sensors = crate::effects::SensorTable::default();
        assert!(bad.build(&mut sensors).unwrap_err().starts_with("a_mm:"));
        let err = |f: &dyn Fn(&mut Config)| {
            let mut x = c.clone();
            f(&mut x);
            x.build().unwrap_err()
        };
        assert!(err(&|x| x.max_harmonic = 9).starts_with("max_harmonic:"));
        assert!(err(&|x| x.max_harmonic = 1).starts_with("max_harmonic:"));
        assert!(err(&|x| x.b_mm.push(0.0)).starts_with("b_mm:"));
        assert!(err(&|x| x.b_mm[0] = f64::NAN).starts_with("b_mm[0]:"));
        assert!(err(&|x| x.polar_mm = vec![0.0; 5]).starts_with("polar_mm:"));
        assert!(err(&|x| x.min_deflection_mm = 0.0).starts_with("min_deflection_mm:"));
    }
}
