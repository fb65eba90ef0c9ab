//! Guide straightness and pitch of one axis along its travel.
//!
//! Equation: with s the reading of the moving axis a and hat functions h_j(s) interpolating
//! linearly between knots s_j (constant beyond the ends),
//! δ = Σ_j h_j(s)·( Σ_{b ⊥ a} e_b·S_{b,j} + ε_j·(e_r × l_tip) ),
//! where S_b are the straightness deviations towards the perpendicular axes b, ε the pitch
//! angle about the rotation axis r (x→y, y→x, z→y unless set) and l_tip the stylus offset
//! (the Abbe lever arm).
//!
//! Source idea: a carriage running on a guide that is not straight moves sideways
//! (straightness) and tilts (pitch); the tilt moves the tip by the angle times its distance
//! from the guide (Abbe), so a longer stylus sees more of it. Tables of these deviations along
//! the travel are what multi-probe or shifted-probe error separation measures.

use super::{check_finite, Effect};
use crate::sample::{Axis, PointContext, Vec3};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// Document form.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// Optional name.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub id: Option<String>,
    /// The moving axis whose guide this is.
    pub axis: Axis,
    /// Knot positions along the axis, strictly increasing, mm.
    pub knots_mm: Vec<f64>,
    /// Straightness deviation towards each listed perpendicular axis at the knots, mm.
    #[serde(default)]
    pub straightness: BTreeMap<Axis, Vec<f64>>,
    /// Pitch angle at the knots, rad (absent: no pitch term).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pitch_rad: Option<Vec<f64>>,
    /// Rotation axis of the pitch (default: y for x, x for y, y for z).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pitch_about: Option<Axis>,
    /// Standard uncertainty of each straightness table at the knots, mm, where a measuring
    /// procedure stated one (`scancorr calibrate straightness`); dropped when the values are
    /// refitted.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub straightness_u: BTreeMap<Axis, Vec<f64>>,
    /// Standard uncertainty of the pitch at the knots, rad (as `straightness_u`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pitch_rad_u: Option<Vec<f64>>,
}

/// Hot-path form.
#[derive(Debug, Clone)]
pub struct Model {
    axis: usize,
    knots: Vec<f64>,
    /// Knots per mm over the table, (n − 1)/(last − first): where evenly spaced knots put a
    /// position, without a search.
    knots_per_mm: f64,
    /// 1 / (k_{j+1} − k_j) per interval (the weight without a division per point).
    inv_width: Vec<f64>,
    straight: Vec<(usize, Vec<f64>)>,
    /// The straightness deviations at each knot as one vector (zero along the axis itself and
    /// towards the axes without a table).
    straight_at: Vec<Vec3>,
    pitch: Option<(Vec3, Vec<f64>)>,
}

impl Config {
    /// Zero-parameter model along `axis` with `n` knots over `[lo, hi]`, straightness towards
    /// the two perpendicular axes and (optionally) pitch.
    pub fn zeros(axis: Axis, lo: f64, hi: f64, n: usize, pitch: bool) -> Config {
        let n = n.max(2);
        let knots_mm = (0..n)
            .map(|j| lo + (hi - lo) * j as f64 / (n - 1) as f64)
            .collect();
        let straightness = Axis::ALL
            .iter()
            .filter(|b| **b != axis)
            .map(|b| (*b, vec![0.0; n]))
            .collect();
        Config {
            id: None,
            axis,
            knots_mm,
            straightness,
            pitch_rad: pitch.then(|| vec![0.0; n]),
            pitch_about: None,
            straightness_u: BTreeMap::new(),
            pitch_rad_u: None,
        }
    }
    fn pitch_axis(&self) -> Axis {
        self.pitch_about.unwrap_or(match self.axis {
            Axis::X => Axis::Y,
            Axis::Y => Axis::X,
            Axis::Z => Axis::Y,
        })
    }
    /// Validates.
    pub fn build(&self) -> Result<Model, String> {
        let n = self.knots_mm.len();
        if n < 2 {
            return Err("knots_mm: at least two knots are needed".into());
        }
        check_finite("knots_mm", &self.knots_mm)?;
        if self.knots_mm.windows(2).any(|w| w[1] <= w[0]) {
            return Err("knots_mm: must be strictly increasing".into());
        }
        let mut straight = vec![];
        for (b, v) in &self.straightness {
            if *b == self.axis {
                return Err(format!(
                    "straightness.{}: must be perpendicular to the axis {}",
                    b.name(),
                    self.axis.name()
                ));
            }
            if v.len() != n {
                return Err(format!(
                    "straightness.{}: needs one value per knot ({n}), got {}",
                    b.name(),
                    v.len()
                ));
            }
            check_finite(&format!("straightness.{}", b.name()), v)?;
            straight.push((b.index(), v.clone()));
        }
        let pitch = match &self.pitch_rad {
            None => None,
            Some(v) => {
                if v.len() != n {
                    return Err(format!(
                        "pitch_rad: needs one value per knot ({n}), got {}",
                        v.len()
                    ));
                }
                check_finite("pitch_rad", v)?;
                Some((self.pitch_axis().unit(), v.clone()))
            }
        };
        for (b, u) in &self.straightness_u {
            let field = format!("straightness_u.{}", b.name());
            if !self.straightness.contains_key(b) {
                return Err(format!(
                    "{field}: no straightness table towards {}",
                    b.name()
                ));
            }
            check_uncertainty(&field, u, n)?;
        }
        if let Some(u) = &self.pitch_rad_u {
            if self.pitch_rad.is_none() {
                return Err("pitch_rad_u: no pitch_rad table".into());
            }
            check_uncertainty("pitch_rad_u", u, n)?;
        }
        if straight.is_empty() && pitch.is_none() {
            return Err(
                "straightness: give straightness towards a perpendicular axis or pitch_rad".into(),
            );
        }
        let straight_at = (0..n)
            .map(|j| {
                let mut s = Vec3::zeros();
                for (b, v) in &straight {
                    s[*b] = v[j];
                }
                s
            })
            .collect();
        Ok(Model {
            axis: self.axis.index(),
            knots: self.knots_mm.clone(),
            knots_per_mm: (n - 1) as f64 / (self.knots_mm[n - 1] - self.knots_mm[0]),
            inv_width: self
                .knots_mm
                .windows(2)
                .map(|w| 1.0 / (w[1] - w[0]))
                .collect(),
            straight,
            straight_at,
            pitch,
        })
    }
    /// Flat parameters: straightness tables in axis order, then pitch.
    pub fn params(&self) -> Vec<f64> {
        self.straightness
            .values()
            .flatten()
            .chain(self.pitch_rad.iter().flatten())
            .copied()
            .collect()
    }
    /// Sets flat parameters (the stated uncertainties no longer hold and are dropped).
    pub fn set_params(&mut self, v: &[f64]) {
        self.straightness_u.clear();
        self.pitch_rad_u = None;
        let mut it = v.iter();
        for t in self.straightness.values_mut() {
            t.iter_mut().for_each(|x| *x = *it.next().unwrap());
        }
        if let Some(p) = self.pitch_rad.as_mut() {
            p.iter_mut().for_each(|x| *x = *it.next().unwrap());
        }
    }
    /// Parameter names.
    pub fn param_names(&self) -> Vec<String> {
        let mut v = vec![];
        let a = self.axis.name();
        for b in self.straightness.keys() {
            v.extend(
                self.knots_mm
                    .iter()
                    .map(|k| format!("straightness {a}→{} at {a}={k} (mm)", b.name())),
            );
        }
        if self.pitch_rad.is_some() {
            v.extend(
                self.knots_mm
                    .iter()
                    .map(|k| format!("pitch at {a}={k} (rad)")),
            );
        }
        v
    }
}

fn check_uncertainty(field: &str, u: &[f64], n: usize) -> Result<(), String> {
    if u.len() != n {
        return Err(format!(
            "{field}: needs one value per knot ({n}), got {}",
            u.len()
        ));
    }
    if u.iter().any(|x| !(x.is_finite() && *x >= 0.0)) {
        return Err(format!("{field}: must be finite and ≥ 0"));
    }
    Ok(())
}

impl Model {
    /// The two knots around `s` and their weights (constant beyond the ends).
    #[inline]
    fn hat(&self, s: f64) -> (usize, f64) {
        let k = &self.knots;
        if s <= k[0] {
            return (0, 1.0);
        }
        let last = k.len() - 1;
        if s >= k[last] {
            return (last - 1, 0.0);
        }
        // The interval evenly spaced knots put s in (the usual table); searched for when it
        // is not that one (uneven knots, or rounding just across a knot).
        let guess = (((s - k[0]) * self.knots_per_mm) as usize).min(last - 1);
        let j = if k[guess] <= s && s < k[guess + 1] {
            guess
        } else {
            k.partition_point(|x| *x <= s) - 1
        };
        (j, (k[j + 1] - s) * self.inv_width[j])
    }
}

impl Effect for Model {
    fn n_params(&self) -> usize {
        let n = self.knots.len();
        n * (self.straight.len() + self.pitch.is_some() as usize)
    }
    fn regressors(&self, ctx: &PointContext, out: &mut [Vec3]) {
        out.iter_mut().for_each(|r| *r = Vec3::zeros());
        let n = self.knots.len();
        let (j, w) = self.hat(ctx.scale[self.axis]);
        for (t, (b, _)) in self.straight.iter().enumerate() {
            out[t * n + j][*b] = w;
            out[t * n + j + 1][*b] = 1.0 - w;
        }
        if let Some((r, _)) = &self.pitch {
            let arm = r.cross(&ctx.tip_offset());
            let base = self.straight.len() * n;
            out[base + j] = arm * w;
            out[base + j + 1] = arm * (1.0 - w);
        }
    }
    #[inline]
    fn correction(&self, ctx: &PointContext) -> Vec3 {
        let (j, w) = self.hat(ctx.scale[self.axis]);
        let s = &self.straight_at;
        // Σ_b e_b·(w·S_b,j + (1 − w)·S_b,j+1), all perpendicular axes at once.
        let mut d = Vec3::zeros() + (s[j] * w + s[j + 1] * (1.0 - w));
        if let Some((r, v)) = &self.pitch {
            d += r.cross(&ctx.tip_offset()) * (w * v[j] + (1.0 - w) * v[j + 1]);
        }
        d
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::effects::{testutil::assert_linear, EffectConfig};

    #[test]
    fn hand_computed_straightness_and_abbe() {
        let mut c = Config::zeros(Axis::X, 0.0, 400.0, 5, true); // knots 0,100,…,400
        c.straightness
            .insert(Axis::Y, vec![0.0, 1e-3, 2e-3, 0.0, 0.0]);
        c.straightness.remove(&Axis::Z);
        c.pitch_rad = Some(vec![0.0, 0.0, 1e-5, 3e-5, 0.0]);
        let m = c.build().unwrap();
        let mut ctx = PointContext::at_rest(Vec3::new(250.0, 0.0, 0.0));
        // x = 250: halfway between knots 200 and 300. Straightness y: (2e-3 + 0)/2 = 1e-3.
        // Pitch (about y) 2e-5 rad with the tip 50 mm below: ŷ × (0,0,−50) = (−50, 0, 0).
        let d = m.correction(&ctx);
        assert!((d - Vec3::new(-1e-3, 1e-3, 0.0)).norm() < 1e-15, "{d:?}");
        assert_linear(&m, &EffectConfig::GuideStraightness(c.clone()), &ctx);
        ctx.scale.x = -10.0; // beyond the first knot: value of the first knot
        assert_eq!(m.correction(&ctx), Vec3::zeros());
        ctx.scale.x = 400.0;
        assert_linear(&m, &EffectConfig::GuideStraightness(c), &ctx);
        let bad = Config {
            knots_mm: vec![0.0, 0.0],
            ..Config::zeros(Axis::Y, 0.0, 1.0, 2, false)
        };
        assert!(bad.build().unwrap_err().contains("increasing"));
    }

    #[test]
    fn interpolates_between_the_right_knots_even_or_uneven() {
        // Straightness towards z equal to the knot position (mm → µm): linear interpolation
        // then gives back s·1e-3 anywhere inside the table, whichever interval holds s.
        for knots in [
            vec![0.0, 100.0, 200.0, 300.0, 400.0],
            vec![-50.0, 0.0, 10.0, 300.0, 310.0, 900.0],
        ] {
            let n = knots.len();
            let mut c = Config::zeros(Axis::Y, 0.0, 1.0, n, false);
            c.knots_mm = knots.clone();
            c.straightness.remove(&Axis::X);
            c.straightness
                .insert(Axis::Z, knots.iter().map(|k| k * 1e-3).collect());
            let m = c.build().unwrap();
            let (lo, hi) = (knots[0], knots[n - 1]);
            let mut at: Vec<f64> = knots.clone();
            at.extend((0..=97).map(|i| lo + (hi - lo) * i as f64 / 97.0));
            for s in at {
                let ctx = PointContext::at_rest(Vec3::new(0.0, s, 0.0));
                let d = m.correction(&ctx);
                assert!((d.z - s * 1e-3).abs() < 1e-15, "s = {s}: {d:?}");
                assert_eq!((d.x, d.y), (0.0, 0.0));
                let (j, w) = m.hat(s);
                assert!(knots[j] <= s && s <= knots[j + 1] && (0.0..=1.0).contains(&w));
            }
        }
    }
}
