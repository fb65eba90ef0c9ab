//! A per-point correction map of one scan of a circular feature at one speed (the dynamic map
//! of `scancorr calibrate dynamic-map`).
//!
//! Equation: for a point of a listed scan segment, with the map's tip and head angles, moving at
//! the map's speed (| |V̂| − v_map | ≤ tolerance, V̂ the estimated velocity; a map without a
//! speed applies at every speed), at the map's place when it has one (the carriage point's
//! distance from the centre within a tolerance of the map's radius, its height of the map's
//! z), with θ = atan2 of (s + d − c) in the XY plane (s the scales, d the deflection in machine
//! axes, c the map's centre in the same carriage coordinates), n̂ = (cos φ·cos θ, cos φ·sin θ,
//! sin φ) pointing away from the centre (φ the latitude of the feature's normal: 0 on a ring,
//! the circle's latitude on a sphere) and hat functions h_j(θ) interpolating linearly
//! (periodically) between N knots θ_j = 2πj/N,
//!
//! δ = n̂ · Σ_j h_j(θ)·(a_j + b_j·|d_probe|),
//!
//! a_j the radial correction at zero deflection, mm, and b_j its change per mm of deflection
//! (empty: none). The signs: δ is *added* to the point (as every effect's correction), along
//! the direction away from the centre whatever the feature (bore or boss): a point measured
//! 1 µm too far from the centre gets a_j + b_j·|d| = −1 µm. Elsewhere (another segment,
//! tip, speed — ramps included) δ = 0.
//!
//! Two kinds are stored: the dynamic map of a fast scan (`calibrate dynamic-map`, at its speed)
//! and the static error map of a feature (`calibrate probe-force`: the zero-force error of each
//! circle on the master sphere, at every speed and its place). Both apply to a fast scan of
//! the feature they share, their corrections added: one correction vector.
//!
//! Source idea: Renishaw's calibration of a coordinate positioning apparatus (the S1/F1/F2
//! method): the error of a fast scan of a feature, measured once against slow scans of the
//! same feature and extrapolated to zero deflection, is stored per point for that feature and
//! speed and applied to later fast scans of like parts measured by the same part program (the
//! same segment ids), combined with the static corrections as one correction vector. Linear in
//! its table values, so `correction == Σ θ r` and the lab can treat it like other tables.

use super::{check_finite, Effect};
use crate::sample::{PointContext, Vec3};
use serde::{Deserialize, Serialize};
use std::f64::consts::TAU;

/// Fewest knots of a map.
pub const MIN_KNOTS: usize = 4;

/// Document form.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// Optional name.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub id: Option<String>,
    /// What was scanned to make the map (artifact, feature, program), for people.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub feature: Option<String>,
    /// Command segment ids the map applies to (the part program's scans of the feature).
    pub segments: Vec<u32>,
    /// Tip (stylus) the map applies to.
    pub tip: u32,
    /// Head angles A1, A2 the map applies to, degrees (within 0.01°).
    #[serde(default)]
    pub head_deg: [f64; 2],
    /// Path speed the map applies to, mm/s (none: every speed — a static map).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub speed_mm_s: Option<f64>,
    /// Largest difference of the estimated path speed from `speed_mm_s`, mm/s (with a speed).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub speed_tolerance_mm_s: Option<f64>,
    /// Centre of the scan's carriage path (scales + deflection), X and Y, mm.
    pub center_mm: [f64; 2],
    /// The place: radius of the scan's carriage path about the centre, mm (none: any).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub radius_mm: Option<f64>,
    /// The place: height (Z) of the scan's carriage path, mm (none: any).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub z_mm: Option<f64>,
    /// How far a point may be from the place (radius and height) and still be of it, mm.
    #[serde(default = "default_place_tolerance")]
    pub place_tolerance_mm: f64,
    /// Latitude of the correction's direction, degrees: 0 horizontal (a ring); a circle on a
    /// sphere at latitude φ is corrected along the sphere's normal.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub latitude_deg: f64,
    /// Radial correction at zero deflection at the knots θ_j = 360°·j/N, mm.
    pub values_mm: Vec<f64>,
    /// Change of the radial correction per mm of deflection at the knots (empty: none).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub per_deflection: Vec<f64>,
    /// The deflection the map was measured at (its values hold exactly there), mm.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub deflection_mm: Option<f64>,
    /// Standard uncertainty of `values_mm + per_deflection·deflection_mm` at the knots, mm,
    /// as the measuring procedure stated it; dropped when the values are refitted.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub values_u_mm: Vec<f64>,
}

fn default_place_tolerance() -> f64 {
    1.0
}

fn is_zero(x: &f64) -> bool {
    *x == 0.0
}

/// Hot-path form.
#[derive(Debug, Clone)]
pub struct Model {
    segments: Vec<u32>,
    tip: u32,
    head: [f64; 2],
    /// Speed and tolerance (tolerance infinite: every speed).
    speed: f64,
    tol: f64,
    center: [f64; 2],
    /// Radius and height of the place (NaN: any) and their tolerance.
    radius: f64,
    z: f64,
    place_tol: f64,
    /// cos φ, sin φ of the latitude.
    cos_lat: f64,
    sin_lat: f64,
    a: Vec<f64>,
    b: Vec<f64>,
}

/// The map's angle of a point: θ of (scales + deflection − centre) in XY, radians in [0, 2π),
/// and the unit direction away from the centre; `None` at the centre.
pub fn angle(ctx: &PointContext, center: [f64; 2]) -> Option<(f64, Vec3)> {
    let p = ctx.scale + ctx.deflection;
    let (x, y) = (p.x - center[0], p.y - center[1]);
    let r = x.hypot(y);
    if !(r > 1e-9) {
        return None;
    }
    Some((y.atan2(x).rem_euclid(TAU), Vec3::new(x / r, y / r, 0.0)))
}

/// The two knots around θ (periodic, `n` knots) and the weight of the first.
#[inline]
pub fn hat(theta: f64, n: usize) -> (usize, usize, f64) {
    let u = theta.rem_euclid(TAU) / TAU * n as f64;
    let j = (u.floor() as usize).min(n - 1);
    let w = 1.0 - (u - j as f64);
    (j, (j + 1) % n, w.clamp(0.0, 1.0))
}

impl Config {
    /// Validates.
    pub fn build(&self) -> Result<Model, String> {
        if self.segments.is_empty() {
            return Err("segments: list the command segment ids the map applies to".into());
        }
        if let Some(f) = &self.feature {
            crate::checks::check_text("feature", f, false)?;
        }
        check_finite("head_deg", &self.head_deg)?;
        let (speed, tol) = match (self.speed_mm_s, self.speed_tolerance_mm_s) {
            (None, None) => (0.0, f64::INFINITY),
            (Some(v), Some(t)) => {
                if !(v.is_finite() && v > 0.0) {
                    return Err("speed_mm_s: must be a finite number > 0".into());
                }
                if !(t.is_finite() && t > 0.0) {
                    return Err("speed_tolerance_mm_s: must be a finite number > 0".into());
                }
                (v, t)
            }
            _ => {
                return Err(
                    "speed_mm_s, speed_tolerance_mm_s: give both (a map at one speed) \
                            or neither (a static map, every speed)"
                        .into(),
                )
            }
        };
        check_finite("center_mm", &self.center_mm)?;
        if let Some(r) = self.radius_mm {
            if !(r.is_finite() && r > 0.0) {
                return Err("radius_mm: must be a finite number > 0".into());
            }
        }
        check_finite("z_mm", &self.z_mm.into_iter().collect::<Vec<_>>())?;
        if !(self.place_tolerance_mm.is_finite() && self.place_tolerance_mm > 0.0) {
            return Err("place_tolerance_mm: must be a finite number > 0".into());
        }
        if !(self.latitude_deg.is_finite() && self.latitude_deg.abs() < 90.0) {
            return Err("latitude_deg: must be a finite number of degrees within ±90".into());
        }
        let n = self.values_mm.len();
        if n < MIN_KNOTS {
            return Err(format!(
                "values_mm: at least {MIN_KNOTS} knots are needed, got {n}"
            ));
        }
        check_finite("values_mm", &self.values_mm)?;
        if !self.per_deflection.is_empty() && self.per_deflection.len() != n {
            return Err(format!(
                "per_deflection: needs one value per knot ({n}) or none, got {}",
                self.per_deflection.len()
            ));
        }
        check_finite("per_deflection", &self.per_deflection)?;
        if let Some(d) = self.deflection_mm {
            if !(d.is_finite() && d >= 0.0) {
                return Err("deflection_mm: must be a finite number ≥ 0".into());
            }
        }
        if !self.values_u_mm.is_empty() {
            if self.values_u_mm.len() != n {
                return Err(format!(
                    "values_u_mm: needs one value per knot ({n}), got {}",
                    self.values_u_mm.len()
                ));
            }
            if self
                .values_u_mm
                .iter()
                .any(|u| !(u.is_finite() && *u >= 0.0))
            {
                return Err("values_u_mm: must be finite and ≥ 0".into());
            }
        }
        Ok(Model {
            segments: self.segments.clone(),
            tip: self.tip,
            head: self.head_deg,
            speed,
            tol,
            center: self.center_mm,
            radius: self.radius_mm.unwrap_or(f64::NAN),
            z: self.z_mm.unwrap_or(f64::NAN),
            place_tol: self.place_tolerance_mm,
            cos_lat: self.latitude_deg.to_radians().cos(),
            sin_lat: self.latitude_deg.to_radians().sin(),
            a: self.values_mm.clone(),
            b: self.per_deflection.clone(),
        })
    }
    /// Whether `self` maps the same scan as `other` and so replaces it: the same tip and head
    /// angles, a segment in common, both static or both at a speed (within either's
    /// tolerance), centres within the place tolerance. A static map and a dynamic map of one
    /// scan are both kept (their corrections add).
    pub fn replaces(&self, other: &Config) -> bool {
        let same_speed = match (
            (self.speed_mm_s, self.speed_tolerance_mm_s),
            (other.speed_mm_s, other.speed_tolerance_mm_s),
        ) {
            ((None, _), (None, _)) => true,
            ((Some(a), ta), (Some(b), tb)) => {
                (a - b).abs() <= ta.unwrap_or(0.0).max(tb.unwrap_or(0.0))
            }
            _ => false,
        };
        let tol = self.place_tolerance_mm.max(other.place_tolerance_mm);
        self.tip == other.tip
            && (0..2).all(|k| (self.head_deg[k] - other.head_deg[k]).abs() <= 0.01)
            && self.segments.iter().any(|s| other.segments.contains(s))
            && same_speed
            && (self.center_mm[0] - other.center_mm[0])
                .hypot(self.center_mm[1] - other.center_mm[1])
                <= tol
    }
    /// Flat parameters: `values_mm`, then `per_deflection`.
    pub fn params(&self) -> Vec<f64> {
        self.values_mm
            .iter()
            .chain(&self.per_deflection)
            .copied()
            .collect()
    }
    /// Sets flat parameters (the stated uncertainties no longer hold and are dropped).
    pub fn set_params(&mut self, v: &[f64]) {
        self.values_u_mm.clear();
        let n = self.values_mm.len();
        self.values_mm.copy_from_slice(&v[..n]);
        self.per_deflection.copy_from_slice(&v[n..]);
    }
    /// Parameter names.
    pub fn param_names(&self) -> Vec<String> {
        let n = self.values_mm.len();
        let deg = |j: usize| 360.0 * j as f64 / n as f64;
        (0..n)
            .map(|j| format!("radial correction at θ={}° (mm)", deg(j)))
            .chain(
                (0..self.per_deflection.len())
                    .map(|j| format!("radial correction per deflection at θ={}° (mm/mm)", deg(j))),
            )
            .collect()
    }
}

impl Model {
    /// Whether the map applies to this point.
    #[inline]
    fn applies(&self, ctx: &PointContext) -> bool {
        ctx.tip_id == self.tip
            && (ctx.head_a1_deg - self.head[0]).abs() <= 0.01
            && (ctx.head_a2_deg - self.head[1]).abs() <= 0.01
            && (ctx.est_vel.norm() - self.speed).abs() <= self.tol
            && self.segments.contains(&ctx.segment_id)
            && self.at_place(ctx)
    }
    /// Whether the point is at the map's place (true when it has none).
    #[inline]
    fn at_place(&self, ctx: &PointContext) -> bool {
        let p = ctx.scale + ctx.deflection;
        let r = (p.x - self.center[0]).hypot(p.y - self.center[1]);
        !((r - self.radius).abs() > self.place_tol || (p.z - self.z).abs() > self.place_tol)
    }
    /// The direction of the correction from the horizontal one away from the centre.
    #[inline]
    fn direction(&self, n_hat: Vec3) -> Vec3 {
        Vec3::new(n_hat.x * self.cos_lat, n_hat.y * self.cos_lat, self.sin_lat)
    }
}

impl Effect for Model {
    fn n_params(&self) -> usize {
        self.a.len() + self.b.len()
    }
    fn regressors(&self, ctx: &PointContext, out: &mut [Vec3]) {
        out.iter_mut().for_each(|r| *r = Vec3::zeros());
        if !self.applies(ctx) {
            return;
        }
        let Some((th, n_hat)) = angle(ctx, self.center) else {
            return;
        };
        let n_hat = self.direction(n_hat);
        let n = self.a.len();
        let (j, k, w) = hat(th, n);
        out[j] += n_hat * w;
        out[k] += n_hat * (1.0 - w);
        if !self.b.is_empty() {
            let d = ctx.deflection_probe.norm();
            out[n + j] += n_hat * (w * d);
            out[n + k] += n_hat * ((1.0 - w) * d);
        }
    }
    #[inline]
    fn correction(&self, ctx: &PointContext) -> Vec3 {
        if !self.applies(ctx) {
            return Vec3::zeros();
        }
        let Some((th, n_hat)) = angle(ctx, self.center) else {
            return Vec3::zeros();
        };
        let n_hat = self.direction(n_hat);
        let (j, k, w) = hat(th, self.a.len());
        let mut v = w * self.a[j] + (1.0 - w) * self.a[k];
        if !self.b.is_empty() {
            v += (w * self.b[j] + (1.0 - w) * self.b[k]) * ctx.deflection_probe.norm();
        }
        n_hat * v
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::effects::{testutil::assert_linear, EffectConfig};

    fn cfg() -> Config {
        Config {
            id: None,
            feature: Some("ring".into()),
            segments: vec![7, 11],
            tip: 1,
            head_deg: [0.0, 0.0],
            speed_mm_s: Some(80.0),
            speed_tolerance_mm_s: Some(4.0),
            center_mm: [100.0, 50.0],
            radius_mm: None,
            z_mm: None,
            place_tolerance_mm: 1.0,
            latitude_deg: 0.0,
            values_mm: vec![1e-3, 2e-3, 3e-3, 4e-3],
            per_deflection: vec![0.0, 1e-2, 0.0, 0.0],
            deflection_mm: Some(0.3),
            values_u_mm: vec![],
        }
    }

    #[test]
    fn hand_computed_and_linear() {
        let c = cfg();
        let m = c.build().unwrap();
        // 45° from the centre: halfway between knots 0° (1 µm) and 90° (2 µm + 0.01·0.2).
        let mut ctx = PointContext::at_rest(Vec3::new(110.0, 60.0, -200.0));
        ctx.segment_id = 11;
        ctx.est_vel = Vec3::new(0.0, 79.0, 0.0);
        ctx.deflection_probe = Vec3::new(0.2, 0.0, 0.0);
        let d = m.correction(&ctx);
        let v = 0.5 * 1e-3 + 0.5 * (2e-3 + 1e-2 * 0.2);
        let n = Vec3::new(1.0, 1.0, 0.0).normalize();
        assert!((d - n * v).norm() < 1e-15, "{d:?}");
        assert_linear(&m, &EffectConfig::FeatureMap(c.clone()), &ctx);
        // At a knot, past the last one (periodic), and elsewhere.
        ctx.scale = Vec3::new(100.0, 40.0, -200.0); // 270°
        assert!((m.correction(&ctx) - Vec3::new(0.0, -4e-3, 0.0)).norm() < 1e-15);
        assert_linear(&m, &EffectConfig::FeatureMap(c.clone()), &ctx);
        ctx.scale = Vec3::new(110.0, 49.0, -200.0); // just below 360°: towards knot 0
        assert_linear(&m, &EffectConfig::FeatureMap(c.clone()), &ctx);
        let others: [fn(&mut PointContext); 3] = [
            |x: &mut PointContext| x.segment_id = 8,
            |x: &mut PointContext| x.tip_id = 2,
            |x: &mut PointContext| x.est_vel = Vec3::new(0.0, 40.0, 0.0),
        ];
        for f in others {
            let mut o = ctx;
            f(&mut o);
            assert_eq!(m.correction(&o), Vec3::zeros());
            assert_linear(&m, &EffectConfig::FeatureMap(c.clone()), &o);
        }
    }

    #[test]
    fn validation_names_the_field_and_documents_parse() {
        let mut c = cfg();
        c.per_deflection = vec![0.0; 3];
        assert!(c.build().unwrap_err().starts_with("per_deflection"));
        let mut c = cfg();
        c.values_mm = vec![0.0, 1.0, f64::NAN, 0.0];
        assert!(c.build().unwrap_err().starts_with("values_mm[2]"));
        let mut c = cfg();
        c.segments.clear();
        assert!(c.build().unwrap_err().starts_with("segments"));
        let mut c = cfg();
        c.speed_tolerance_mm_s = Some(0.0);
        assert!(c.build().unwrap_err().starts_with("speed_tolerance_mm_s"));
        let mut c = cfg();
        c.speed_tolerance_mm_s = None;
        assert!(c.build().unwrap_err().contains("give both"));
        let mut c = cfg();
        c.latitude_deg = 90.0;
        assert!(c.build().unwrap_err().starts_with("latitude_deg"));
        let mut c = cfg();
        c.radius_mm = Some(-1.0);
        assert!(c.build().unwrap_err().starts_with("radius_mm"));
        // A document of the first form (no place, no latitude) still reads.
        let old = r#"{"kind":"feature_map","segments":[3],"tip":1,"speed_mm_s":80.0,
            "speed_tolerance_mm_s":4.0,"center_mm":[0.0,0.0],"values_mm":[0.0,0.0,0.0,0.0]}"#;
        let EffectConfig::FeatureMap(o) = serde_json::from_str::<EffectConfig>(old).unwrap() else {
            panic!("a feature map")
        };
        assert_eq!(
            (o.radius_mm, o.latitude_deg, o.place_tolerance_mm),
            (None, 0.0, 1.0)
        );
        let j = serde_json::to_string(&EffectConfig::FeatureMap(cfg())).unwrap();
        assert!(j.contains("\"kind\":\"feature_map\""), "{j}");
        let back: EffectConfig = serde_json::from_str(&j).unwrap();
        assert_eq!(back, EffectConfig::FeatureMap(cfg()));
        let typo = j.replace("\"tip\"", "\"tipp\"");
        assert!(serde_json::from_str::<EffectConfig>(&typo).is_err());
    }

    #[test]
    fn a_static_map_applies_at_every_speed_at_its_place_along_the_spheres_normal() {
        let mut c = cfg();
        c.speed_mm_s = None;
        c.speed_tolerance_mm_s = None;
        c.per_deflection.clear();
        c.radius_mm = Some(10.0);
        c.z_mm = Some(-200.0);
        c.latitude_deg = 30.0;
        let m = c.build().unwrap();
        // At 90° on the place (radius 10, z −200), at any speed: 2 µm along the normal of a
        // sphere's circle at latitude 30° (cos 30° horizontally, sin 30° up).
        let mut ctx = PointContext::at_rest(Vec3::new(100.0, 60.0, -200.0));
        ctx.segment_id = 7;
        for v in [0.5, 80.0, 300.0] {
            ctx.est_vel = Vec3::new(v, 0.0, 0.0);
            let d = m.correction(&ctx);
            let want = Vec3::new(0.0, 30f64.to_radians().cos(), 0.5) * 2e-3;
            assert!((d - want).norm() < 1e-15, "{v} mm/s: {d:?}");
            assert_linear(&m, &EffectConfig::FeatureMap(c.clone()), &ctx);
        }
        // Off its place (another radius, another height): nothing.
        for at in [
            Vec3::new(100.0, 62.0, -200.0),
            Vec3::new(100.0, 60.0, -198.0),
        ] {
            let mut o = ctx;
            o.scale = at;
            assert_eq!(m.correction(&o), Vec3::zeros());
            assert_linear(&m, &EffectConfig::FeatureMap(c.clone()), &o);
        }
    }

    #[test]
    fn a_map_replaces_the_same_scans_map_of_its_kind_only() {
        let dynamic = cfg();
        let mut newer = cfg();
        newer.values_mm = vec![0.0; 4];
        assert!(newer.replaces(&dynamic));
        // The static map of the same scan is kept beside it; so are other segments, tips,
        // speeds and places.
        let mut stat = cfg();
        stat.speed_mm_s = None;
        stat.speed_tolerance_mm_s = None;
        assert!(!stat.replaces(&dynamic) && !dynamic.replaces(&stat));
        let others: [fn(&mut Config); 4] = [
            |c| c.segments = vec![8],
            |c| c.tip = 2,
            |c| c.speed_mm_s = Some(40.0),
            |c| c.center_mm = [300.0, 50.0],
        ];
        for f in others {
            let mut o = cfg();
            f(&mut o);
            assert!(!o.replaces(&dynamic), "{o:?}");
        }
    }
}
