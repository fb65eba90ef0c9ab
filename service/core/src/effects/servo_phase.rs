//! Inter-axis phase lag on arcs, direction-dependent and static.
//!
//! Equation: on an arc of commanded centre c with rotation frequency f and unit angular
//! velocity ŵ, with lever r = s − c,
//!
//! δ_i = φ_i(f)·(ŵ × r)_i + ψ_i(f)·(n̂ × r)_i,  i ∈ {y, z},
//!
//! φ_i = b2·f² + b1·f + b0 and ψ_i = c2·f² + c1·f + c0 (each b, c may be a polynomial in
//! position), n̂ = ŵ·sign(ŵ_k) the plane normal with a fixed orientation, k the axis of the
//! largest |ŵ_k| (ties: z before y before x), so n̂ is the same for both senses of rotation.
//! (On a plane whose normal has two components of nearly equal size, n̂ can flip between
//! neighbouring points; scans lie in the machine's planes, where it cannot.)
//! A common term on all axes only turns the circle about c (slides points along the arc) and
//! is not observable, so X is the reference.
//!
//! * Direction-dependent part (φ, `y`/`z`, on unless `direction_dependent: false`): axis i
//!   lags X by a time Δt_i, its error is −Δt_i·v_i = −φ_i·(ŵ × r)_i with φ_i = ωΔt_i — the
//!   phase mismatch of the axis servo loops behind the patented phase-lag correction for
//!   scanning on circles (e.g. Renishaw's "method for calibrating a scanning system"). It
//!   turns a circle into a tilted ellipse whose tilt changes sign between CW and CCW runs.
//! * Static part (ψ, `static_terms`, optional): the same tangential shape with the sign of
//!   the rotation sense removed — an ellipse of fixed orientation in both senses, as a
//!   cross-coupling in phase with position produces (e.g. axis X's inertial load −ω²(x − c_x)
//!   deflecting Y, or cross-talk between the axis drives). Its f⁰ term looks like squareness
//!   on a circle (confounded with `rigid_body` squareness on a single circle).
//!
//! Which applies: a tilt that flips between CW and CCW runs is the direction-dependent one, a
//! tilt that stays is the static one; the lab chooses among the variants (φ only — old
//! documents —, ψ only with `direction_dependent: false`, or both) on held-out runs of both
//! senses. Parameters: φ's (b0..b2 per monomial, y then z) first, then ψ's.

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
    /// Lag of Y behind X: one [b0 (rad), b1 (rad/Hz), b2 (rad/Hz²)] per monomial; absent
    /// (empty) when `direction_dependent` is false.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub y: Vec<[f64; 3]>,
    /// Lag of Z behind X: one [b0, b1, b2] per monomial; absent when `direction_dependent`
    /// is false.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub z: Vec<[f64; 3]>,
    /// Whether the ŵ-signed (direction-dependent) part φ is on (default; old documents).
    #[serde(default = "yes", skip_serializing_if = "is_true")]
    pub direction_dependent: bool,
    /// The static part ψ (same sign for CW and CCW); absent (empty) = none.
    #[serde(default, skip_serializing_if = "StaticTerms::is_empty")]
    pub static_terms: StaticTerms,
}

/// The static (direction-independent) part: ψ_i(f) per monomial.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StaticTerms {
    /// Y: one [c0 (rad), c1 (rad/Hz), c2 (rad/Hz²)] per monomial.
    #[serde(default)]
    pub y: Vec<[f64; 3]>,
    /// Z: one [c0, c1, c2] per monomial.
    #[serde(default)]
    pub z: Vec<[f64; 3]>,
}

impl StaticTerms {
    /// No static part.
    pub fn is_empty(&self) -> bool {
        self.y.is_empty() && self.z.is_empty()
    }
}

fn yes() -> bool {
    true
}

fn is_true(b: &bool) -> bool {
    *b
}

/// Hot-path form.
#[derive(Debug, Clone)]
pub struct Model {
    basis: super::PreparedBasis,
    /// φ; empty when the direction-dependent part is off.
    y: Vec<[f64; 3]>,
    z: Vec<[f64; 3]>,
    /// ψ; empty when there is no static part.
    sy: Vec<[f64; 3]>,
    sz: Vec<[f64; 3]>,
}

impl Config {
    /// Zero-parameter model (direction-dependent only, as before).
    pub fn zeros(order: u8) -> Config {
        Config::zeros_variant(order, true, false)
    }
    /// Zero-parameter model of a variant: the direction-dependent part φ and/or the static
    /// part ψ (at least one should be on for the model to build).
    pub fn zeros_variant(order: u8, direction_dependent: bool, with_static: bool) -> Config {
        let position = PositionBasis {
            order,
            ..Default::default()
        };
        let n = position.len();
        let part = |on: bool| if on { vec![[0.0; 3]; n] } else { vec![] };
        Config {
            id: None,
            position,
            y: part(direction_dependent),
            z: part(direction_dependent),
            direction_dependent,
            static_terms: StaticTerms {
                y: part(with_static),
                z: part(with_static),
            },
        }
    }
    /// Validates.
    pub fn build(&self) -> Result<Model, String> {
        self.position.validate("position")?;
        let n = self.position.len();
        let check = |name: &str, v: &[[f64; 3]]| -> Result<(), String> {
            if v.len() != n {
                return Err(format!(
                    "{name}: needs {n} coefficient triples, got {}",
                    v.len()
                ));
            }
            for (m, b) in v.iter().enumerate() {
                check_finite(&format!("{name}[{m}]"), b)?;
            }
            Ok(())
        };
        if self.direction_dependent {
            check("y", &self.y)?;
            check("z", &self.z)?;
        } else {
            for (name, v) in [("y", &self.y), ("z", &self.z)] {
                if !v.is_empty() {
                    return Err(format!(
                        "{name}: must be absent when direction_dependent is false"
                    ));
                }
            }
            if self.static_terms.is_empty() {
                return Err(
                    "static_terms: needed when direction_dependent is false (nothing left)"
                        .to_string(),
                );
            }
        }
        if !self.static_terms.is_empty() {
            check("static_terms.y", &self.static_terms.y)?;
            check("static_terms.z", &self.static_terms.z)?;
        }
        Ok(Model {
            basis: self.position.into(),
            y: self.y.clone(),
            z: self.z.clone(),
            sy: self.static_terms.y.clone(),
            sz: self.static_terms.z.clone(),
        })
    }
    /// Flat parameters: φ (y then z), then ψ (y then z); monomial-major, b0..b2 / c0..c2.
    pub fn params(&self) -> Vec<f64> {
        self.y
            .iter()
            .chain(self.z.iter())
            .chain(self.static_terms.y.iter())
            .chain(self.static_terms.z.iter())
            .flat_map(|b| b.iter().copied())
            .collect()
    }
    /// Sets flat parameters (order of [`Self::params`]).
    pub fn set_params(&mut self, v: &[f64]) {
        let mut it = v.iter();
        for arr in [
            &mut self.y,
            &mut self.z,
            &mut self.static_terms.y,
            &mut self.static_terms.z,
        ] {
            for b in arr.iter_mut().flat_map(|b| b.iter_mut()) {
                match it.next() {
                    Some(x) => *b = *x,
                    None => return,
                }
            }
        }
    }
    /// Parameter names: `φ_y b1 · ξx (rad/Hz)`, …, `static y c0 (rad)`, ….
    pub fn param_names(&self) -> Vec<String> {
        const UNITS: [&str; 3] = ["rad", "rad/Hz", "rad/Hz²"];
        let mut v = vec![];
        for (ax, arr) in [("y", &self.y), ("z", &self.z)] {
            for m in 0..arr.len() {
                for (k, unit) in UNITS.iter().enumerate() {
                    v.push(format!("φ_{ax} b{k}{} ({unit})", super::monomial_suffix(m)));
                }
            }
        }
        for (ax, arr) in [("y", &self.static_terms.y), ("z", &self.static_terms.z)] {
            for m in 0..arr.len() {
                for (k, unit) in UNITS.iter().enumerate() {
                    v.push(format!(
                        "static {ax} c{k}{} ({unit})",
                        super::monomial_suffix(m)
                    ));
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

/// The plane normal with a fixed orientation: ŵ signed so that its largest component (ties:
/// z, then y, then x) is positive — the same for ŵ and −ŵ.
#[inline]
fn fixed_normal(w: &Vec3) -> Vec3 {
    let mut k = 2;
    if w.y.abs() > w[k].abs() {
        k = 1;
    }
    if w.x.abs() > w[k].abs() {
        k = 0;
    }
    if w[k] < 0.0 {
        -w
    } else {
        *w
    }
}

/// The static lever n̂ × (s − c), on arcs only.
#[inline]
fn static_lever(ctx: &PointContext) -> Option<Vec3> {
    if ctx.arc_radius > 0.0 && ctx.rot_axis != Vec3::zeros() {
        Some(fixed_normal(&ctx.rot_axis).cross(&(ctx.scale - ctx.arc_center)))
    } else {
        None
    }
}

/// Σ_m ξ_m·(b_m0 + f·(b_m1 + f·b_m2)) over the monomials `mono`.
#[inline]
fn poly_in_f(mono: &[f64], a: &[[f64; 3]], f: f64) -> f64 {
    let mut p = 0.0;
    for (xi, b) in mono.iter().zip(a) {
        p += xi * (b[0] + f * (b[1] + f * b[2]));
    }
    p
}

impl Effect for Model {
    fn n_params(&self) -> usize {
        3 * (self.y.len() + self.z.len() + self.sy.len() + self.sz.len())
    }
    fn regressors(&self, ctx: &PointContext, out: &mut [Vec3]) {
        out.iter_mut().for_each(|r| *r = Vec3::zeros());
        let (Some(l), Some(ls)) = (lever(ctx), static_lever(ctx)) else {
            return;
        };
        let mut mono = [0.0; 10];
        let n = self.basis.eval(&ctx.scale, &mut mono);
        let f = ctx.f_hz;
        let fp = [1.0, f, f * f];
        // Blocks in parameter order: φ_y, φ_z, ψ_y, ψ_z (absent ones take no columns).
        let mut off = 0;
        for (arr, axis, lv) in [
            (&self.y, 1usize, &l),
            (&self.z, 2, &l),
            (&self.sy, 1, &ls),
            (&self.sz, 2, &ls),
        ] {
            if arr.is_empty() {
                continue;
            }
            for (m, xi) in mono.iter().enumerate().take(n) {
                for k in 0..3 {
                    out[off + 3 * m + k][axis] = xi * fp[k] * lv[axis];
                }
            }
            off += 3 * n;
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
        let mono = &mono[..n];
        let poly = |a: &[[f64; 3]]| poly_in_f(mono, a, f);
        // The direction-dependent part, computed exactly as before the static part existed.
        let dir = if self.y.is_empty() {
            None
        } else {
            Some(Vec3::new(0.0, poly(&self.y) * l.y, poly(&self.z) * l.z))
        };
        if self.sy.is_empty() {
            return dir.unwrap_or_else(Vec3::zeros);
        }
        let ls = fixed_normal(&ctx.rot_axis).cross(&(ctx.scale - ctx.arc_center));
        let st = Vec3::new(0.0, poly(&self.sy) * ls.y, poly(&self.sz) * ls.z);
        match dir {
            Some(d) => d + st,
            None => st,
        }
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

    /// An arc context: centre `c`, rotation axis `w`, point `s`, f = 2 Hz.
    fn arc(s: Vec3, c: Vec3, w: Vec3) -> PointContext {
        let mut ctx = PointContext::at_rest(s);
        ctx.arc_center = c;
        ctx.arc_radius = (s - c).norm();
        ctx.f_hz = 2.0;
        ctx.rot_axis = w;
        ctx
    }

    #[test]
    fn static_term_keeps_its_sign_between_cw_and_ccw() {
        // ψ_y(f) = 1e-3 f + 2e-4 f² = 2.8e-3 rad at 2 Hz, like the hand-computed φ above.
        let mut st = Config::zeros_variant(0, false, true);
        st.static_terms.y[0] = [0.0, 1e-3, 2e-4];
        let ms = st.build().unwrap();
        let mut dd = Config::zeros(0);
        dd.y[0] = [0.0, 1e-3, 2e-4];
        let md = dd.build().unwrap();
        let mut both = Config::zeros_variant(0, true, true);
        both.y[0] = [0.0, 1e-3, 2e-4];
        both.static_terms.y[0] = [0.0, 1e-3, 2e-4];
        let mb = both.build().unwrap();
        let (s, c) = (Vec3::new(125.0, 0.0, 0.0), Vec3::new(100.0, 0.0, 0.0));
        let (ccw, cw) = (arc(s, c, Vec3::z()), arc(s, c, -Vec3::z()));
        let want = Vec3::new(0.0, 0.07, 0.0);
        // Static: n̂ = +z for both senses, n̂ × r = (0, 25, 0), δy = +0.07 mm both times.
        assert!((ms.correction(&ccw) - want).norm() < 1e-15);
        assert_eq!(ms.correction(&ccw), ms.correction(&cw));
        // Direction-dependent: opposite; the two together cancel on CW and add on CCW.
        assert!((md.correction(&ccw) - want).norm() < 1e-15);
        assert_eq!(md.correction(&cw), -md.correction(&ccw));
        assert!((mb.correction(&ccw) - want * 2.0).norm() < 1e-15);
        assert!(mb.correction(&cw).norm() < 1e-15);
        // Tilted plane, position-dependent coefficients, both parts: static equal, φ opposite.
        let mut st1 = Config::zeros_variant(1, false, true);
        st1.static_terms.y[1] = [1e-4, 2e-5, 3e-6];
        st1.static_terms.z[0] = [-2e-4, 1e-5, 0.0];
        st1.static_terms.z[3] = [0.0, 0.0, 4e-6];
        let mut dd1 = Config::zeros(1);
        dd1.y[2] = [1e-4, 0.0, 3e-6];
        dd1.z[0] = [2e-4, -1e-5, 1e-6];
        let mut both1 = dd1.clone();
        both1.static_terms = st1.static_terms.clone();
        let w = Vec3::new(0.0, 0.6, 0.8);
        let (s, c) = (Vec3::new(110.0, 20.0, 30.0), Vec3::new(100.0, 5.0, 40.0));
        let (ccw, cw) = (arc(s, c, w), arc(s, c, -w));
        let (ms1, md1, mb1) = (
            st1.build().unwrap(),
            dd1.build().unwrap(),
            both1.build().unwrap(),
        );
        assert!(ms1.correction(&ccw).norm() > 1e-6);
        assert_eq!(ms1.correction(&ccw), ms1.correction(&cw));
        assert!(md1.correction(&ccw).norm() > 1e-6);
        assert_eq!(md1.correction(&cw), -md1.correction(&ccw));
        for ctx in [&ccw, &cw] {
            let sum = md1.correction(ctx) + ms1.correction(ctx);
            assert!((mb1.correction(ctx) - sum).norm() < 1e-15);
        }
        // Off the arc nothing.
        let mut off = ccw;
        off.arc_radius = 0.0;
        for m in [&ms1, &mb1] {
            assert_eq!(m.correction(&off), Vec3::zeros());
            let mut r = vec![Vec3::new(1.0, 1.0, 1.0); m.n_params()];
            m.regressors(&off, &mut r);
            assert!(r.iter().all(|r| *r == Vec3::zeros()));
        }
    }

    #[test]
    fn both_variants_are_linear() {
        for (dir, stat) in [(false, true), (true, true), (true, false)] {
            for order in [0u8, 1, 2] {
                let mut c = Config::zeros_variant(order, dir, stat);
                let n = c.params().len();
                assert_eq!(
                    n,
                    3 * c.position.len() * (2 * dir as usize + 2 * stat as usize)
                );
                let p: Vec<f64> = (0..n).map(|k| 1e-4 * ((k * 7 % 11) as f64 - 5.0)).collect();
                c = match EffectConfig::ServoPhase(c).with_params(&p).unwrap() {
                    EffectConfig::ServoPhase(c) => c,
                    _ => unreachable!(),
                };
                c.position.origin_mm = [50.0, -20.0, 10.0];
                let m = c.build().unwrap();
                for w in [
                    Vec3::z(),
                    -Vec3::z(),
                    Vec3::new(0.0, 0.6, -0.8),
                    Vec3::new(-0.8, 0.0, 0.6),
                ] {
                    let ctx = arc(Vec3::new(110.0, 20.0, 30.0), Vec3::new(100.0, 5.0, 40.0), w);
                    assert_linear(&m, &EffectConfig::ServoPhase(c.clone()), &ctx);
                }
            }
        }
        let names = Config::zeros_variant(0, true, true).param_names();
        assert_eq!(names[0], "φ_y b0 (rad)");
        assert_eq!(names[6], "static y c0 (rad)");
        assert_eq!(names[11], "static z c2 (rad/Hz²)");
        let names = Config::zeros_variant(1, false, true).param_names();
        assert_eq!(names[4], "static y c1 · ξx (rad/Hz)");
    }

    #[test]
    fn serde_round_trip_of_the_variants() {
        let mut st = Config::zeros_variant(1, false, true);
        st.static_terms.z[2] = [1e-4, -2e-5, 3e-6];
        let mut both = Config::zeros_variant(0, true, true);
        both.y[0] = [1e-4, 2e-5, 0.0];
        both.static_terms.y[0] = [0.0, 0.0, 7e-6];
        both.id = Some("phase_both".into());
        for c in [st.clone(), both, Config::zeros(2)] {
            let e = EffectConfig::ServoPhase(c);
            let s = serde_json::to_string(&e).unwrap();
            let back: EffectConfig = serde_json::from_str(&s).unwrap();
            assert_eq!(back, e, "{s}");
        }
        // The static-only variant writes no φ fields and says it is not direction-dependent.
        let v = serde_json::to_value(EffectConfig::ServoPhase(st)).unwrap();
        assert_eq!(v["direction_dependent"], false);
        assert!(v.get("y").is_none() && v.get("z").is_none(), "{v}");
        assert_eq!(v["static_terms"]["z"][2][0], 1e-4);
        let doc = r#"{"kind": "servo_phase", "direction_dependent": false,
            "static_terms": {"y": [[1e-3, 0.0, 0.0]], "z": [[0.0, 0.0, 0.0]]}}"#;
        let EffectConfig::ServoPhase(c) = serde_json::from_str(doc).unwrap() else {
            panic!()
        };
        assert_eq!(c.params(), vec![1e-3, 0.0, 0.0, 0.0, 0.0, 0.0]);
        assert!(serde_json::from_str::<EffectConfig>(
            r#"{"kind": "servo_phase", "y": [[0,0,0]], "z": [[0,0,0]],
                "static_terms": {"y": [[0,0,0]], "x": [[0,0,0]]}}"#
        )
        .is_err());
    }

    #[test]
    fn old_documents_read_write_and_correct_as_before() {
        let old = r#"{"kind":"servo_phase","position":{"order":1,"origin_mm":[1.0,2.0,3.0],"scale_mm":400.0},"y":[[0.0,0.001,0.0002],[0.00001,0.0,0.0],[0.0,3e-6,0.0],[0.0,0.0,1e-7]],"z":[[0.0002,-0.00001,1e-6],[0.0,0.0,0.0],[0.0,0.0,0.0],[2e-6,0.0,0.0]]}"#;
        let e: EffectConfig = serde_json::from_str(old).unwrap();
        let EffectConfig::ServoPhase(c) = &e else {
            panic!()
        };
        assert!(c.direction_dependent && c.static_terms.is_empty());
        assert_eq!(serde_json::to_string(&e).unwrap(), old);
        assert_eq!(c.params().len(), 24);
        assert_eq!(c.param_names().len(), 24);
        let m = c.build().unwrap();
        assert_eq!(m.n_params(), 24);
        // The correction as the effect computed it before static terms existed, bit for bit.
        let before = |ctx: &PointContext| -> Vec3 {
            let Some(l) = lever(ctx) else {
                return Vec3::zeros();
            };
            let mut mono = [0.0; 10];
            let n = c.position.eval(&ctx.scale, &mut mono);
            let f = ctx.f_hz;
            let (mut py, mut pz) = (0.0, 0.0);
            for (m, xi) in mono.iter().enumerate().take(n) {
                let (y, z) = (c.y[m], c.z[m]);
                py += xi * (y[0] + f * (y[1] + f * y[2]));
                pz += xi * (z[0] + f * (z[1] + f * z[2]));
            }
            Vec3::new(0.0, py * l.y, pz * l.z)
        };
        for w in [Vec3::z(), -Vec3::z(), Vec3::new(0.0, 0.6, 0.8)] {
            for s in [Vec3::new(125.0, 0.0, 0.0), Vec3::new(90.0, -13.0, 7.5)] {
                let ctx = arc(s, Vec3::new(100.0, 0.0, 0.0), w);
                let (a, b) = (m.correction(&ctx), before(&ctx));
                assert_eq!(a.map(f64::to_bits), b.map(f64::to_bits));
            }
        }
    }

    #[test]
    fn validation_names_the_field() {
        let err = |c: &Config| c.build().unwrap_err();
        let mut c = Config::zeros_variant(0, false, true);
        c.y = vec![[0.0; 3]];
        assert!(err(&c).starts_with("y: must be absent"), "{}", err(&c));
        let c = Config::zeros_variant(1, false, false);
        assert!(err(&c).starts_with("static_terms:"), "{}", err(&c));
        let mut c = Config::zeros_variant(1, true, true);
        c.static_terms.y.pop();
        assert_eq!(
            err(&c),
            "static_terms.y: needs 4 coefficient triples, got 3"
        );
        let mut c = Config::zeros_variant(0, true, true);
        c.static_terms.z[0][2] = f64::NAN;
        assert_eq!(err(&c), "static_terms.z[0][2]: must be a finite number");
        let mut c = Config::zeros_variant(0, true, false);
        c.z.clear();
        assert_eq!(err(&c), "z: needs 1 coefficient triples, got 0");
        let e = EffectConfig::ServoPhase(Config::zeros_variant(0, false, true));
        assert!(e.with_params(&[0.0; 12]).is_err());
        assert!(e.with_params(&[0.0; 6]).is_ok());
    }
}
