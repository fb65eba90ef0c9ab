//! Independent check of the `rigid_body` effect against the kinematic chain of a CMM built
//! from exact 4×4 homogeneous transforms.
//!
//! Each axis i at scale reading s_i is the transform H_i = Trans(s_i·d_i + δ_i(u_i))·Rot(ε_i(u_i)),
//! with d_i the (unit) direction of the axis including the squareness errors, δ_i its
//! translation errors and Rot the exact rotation Rz(ε_z)·Ry(ε_y)·Rx(ε_x) (no small-angle
//! linearisation). The tip in the part frame is the product along the chain times the stylus
//! offset l:
//!
//! * moving bridge / cantilever: tip = H_Y·H_X·H_Z·l (bridge on the base, carriage, ram);
//! * fixed bridge: the table carries the part and moves by −y: H_Y = Trans(−y·d_y + δ_Y)·Rot(ε_Y)
//!   relative to the base, tip = H_Y⁻¹·H_X·H_Z·l;
//! * horizontal arm: tip = H_X·H_Z·H_Y·l (column, carriage on it, arm).
//!
//! The deviation actual − nominal (nominal = s + l) is what the corrector adds to the scale
//! reading (`synthesize`: tip = scale + Σ corrections + offset, and the simulator builds its
//! tip as x + e + offset), so the effect's correction must equal it up to second-order terms.
//! The ball plate and the gauge blocks are then "measured" on the erroneous machine (the scale
//! reading at which the real tip sits at the ball centre / block face) and corrected.

#![allow(clippy::needless_range_loop)]

use nalgebra::{Matrix3, Matrix4, Vector3, Vector4};
use scancorr_core::effects::{Effect, EffectConfig, SensorTable};
use scancorr_core::sample::{PointContext, Vec3};

const ORDER: usize = 4;
const LO: [f64; 3] = [0.0, 0.0, -600.0];
const HI: [f64; 3] = [1000.0, 800.0, 0.0];
const AXES: [&str; 3] = ["X", "Y", "Z"];

/// The 21 errors: polynomial coefficients c1…c4 in u = (s − centre)/half range.
#[derive(Clone)]
struct Errors {
    /// trans[i][j]: translation of axis i in direction j, mm (c1 of straightness is 0).
    trans: [[[f64; ORDER]; 3]; 3],
    /// rot[i][j]: rotation of axis i about j, rad.
    rot: [[[f64; ORDER]; 3]; 3],
    /// Squareness xy, xz, yz, rad.
    sq: [f64; 3],
}

fn realistic(scale: f64) -> Errors {
    let mut trans = [[[0.0; ORDER]; 3]; 3];
    let mut rot = [[[0.0; ORDER]; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            for k in 0..ORDER {
                let w = (1.3 * (9 * i + 3 * j + k) as f64 + 0.7).sin() / (1 + k) as f64;
                // Positioning up to ~5 µm, straightness ~2 µm, angles ~6 µrad over the travel.
                trans[i][j][k] = if i == j {
                    5e-3 * w
                } else if k == 0 {
                    0.0
                } else {
                    2e-3 * w
                };
                rot[i][j][k] =
                    6e-6 * (1.1 * (9 * i + 3 * j + k) as f64 + 0.2).cos() / (1 + k) as f64;
            }
        }
    }
    let mut e = Errors {
        trans,
        rot,
        sq: [5e-6, -3e-6, 4e-6],
    };
    e.scale(scale);
    e
}

impl Errors {
    fn scale(&mut self, f: f64) {
        self.trans
            .iter_mut()
            .flatten()
            .flatten()
            .for_each(|c| *c *= f);
        self.rot
            .iter_mut()
            .flatten()
            .flatten()
            .for_each(|c| *c *= f);
        self.sq.iter_mut().for_each(|c| *c *= f);
    }

    /// The calibration document, written by hand from the ISO 230-1 names.
    fn document(&self, chain: &str) -> EffectConfig {
        let mut errors = serde_json::Map::new();
        for i in 0..3 {
            for j in 0..3 {
                let first = if i == j { 0 } else { 1 };
                errors.insert(
                    format!("E{}{}", AXES[j], AXES[i]),
                    serde_json::json!(self.trans[i][j][first..].to_vec()),
                );
                errors.insert(
                    format!("A{}{}", AXES[j], AXES[i]),
                    serde_json::json!(self.rot[i][j].to_vec()),
                );
            }
        }
        let center = [0, 1, 2].map(|i| 0.5 * (LO[i] + HI[i]));
        let half = [0, 1, 2].map(|i| 0.5 * (HI[i] - LO[i]));
        let doc = serde_json::json!({
            "kind": "rigid_body",
            "chain": chain,
            "order": ORDER,
            "center_mm": center,
            "half_range_mm": half,
            "errors": errors,
            "squareness_rad": {"xy": self.sq[0], "xz": self.sq[1], "yz": self.sq[2]},
        });
        serde_json::from_value(doc).unwrap()
    }

    /// Bounds of the total angle, translation error (over the travel, |u| ≤ 1).
    fn magnitudes(&self) -> (f64, f64) {
        let sum = |v: &[f64]| v.iter().map(|c| c.abs()).sum::<f64>();
        let ang = self.rot.iter().flatten().map(|c| sum(c)).sum::<f64>()
            + self.sq.iter().map(|c| c.abs()).sum::<f64>();
        let tr = self.trans.iter().flatten().map(|c| sum(c)).sum::<f64>();
        (ang, tr)
    }

    fn poly(c: &[f64; ORDER], u: f64) -> f64 {
        (0..ORDER).map(|k| c[k] * u.powi(k as i32 + 1)).sum()
    }

    /// Unit direction of axis i with the squareness errors: Y along (sin Sxy, cos Sxy, 0),
    /// Z along (sin Sxz, sin Syz, √(1 − …)).
    fn direction(&self, i: usize) -> Vector3<f64> {
        let [xy, xz, yz] = self.sq;
        match i {
            0 => Vector3::x(),
            1 => Vector3::new(xy.sin(), xy.cos(), 0.0),
            _ => {
                let (a, b) = (xz.sin(), yz.sin());
                Vector3::new(a, b, (1.0 - a * a - b * b).sqrt())
            }
        }
    }

    /// H_i at scale reading s (the travel along the axis is `travel`·d_i: −s for a table).
    fn transform(&self, i: usize, s: f64, travel: f64) -> Matrix4<f64> {
        let u = (s - 0.5 * (LO[i] + HI[i])) / (0.5 * (HI[i] - LO[i]));
        let t =
            self.direction(i) * travel + Vector3::from_fn(|j, _| Self::poly(&self.trans[i][j], u));
        let [ex, ey, ez] = [0, 1, 2].map(|j| Self::poly(&self.rot[i][j], u));
        let rx = Matrix3::new(
            1.0,
            0.0,
            0.0,
            0.0,
            ex.cos(),
            -ex.sin(),
            0.0,
            ex.sin(),
            ex.cos(),
        );
        let ry = Matrix3::new(
            ey.cos(),
            0.0,
            ey.sin(),
            0.0,
            1.0,
            0.0,
            -ey.sin(),
            0.0,
            ey.cos(),
        );
        let rz = Matrix3::new(
            ez.cos(),
            -ez.sin(),
            0.0,
            ez.sin(),
            ez.cos(),
            0.0,
            0.0,
            0.0,
            1.0,
        );
        let mut h = Matrix4::identity();
        h.fixed_view_mut::<3, 3>(0, 0).copy_from(&(rz * ry * rx));
        h.fixed_view_mut::<3, 1>(0, 3).copy_from(&t);
        h
    }

    /// Actual tip position in the part frame at scale readings s with stylus offset l.
    fn tip(&self, chain: &str, s: &Vec3, l: &Vec3) -> Vec3 {
        let h = |i: usize| self.transform(i, s[i], s[i]);
        let m = match chain {
            "moving_bridge" | "cantilever" => h(1) * h(0) * h(2),
            "fixed_bridge" => {
                let table = self.transform(1, s.y, -s.y);
                table.try_inverse().unwrap() * h(0) * h(2)
            }
            "horizontal_arm" => h(0) * h(2) * h(1),
            c => panic!("chain {c}"),
        };
        let p = m * Vector4::new(l.x, l.y, l.z, 1.0);
        Vec3::new(p.x, p.y, p.z)
    }
}

const CHAINS: [&str; 4] = [
    "moving_bridge",
    "cantilever",
    "fixed_bridge",
    "horizontal_arm",
];

fn ctx(s: Vec3, l: Vec3) -> PointContext {
    let mut c = PointContext::at_rest(s);
    c.tip_shank = Vec3::new(0.0, 0.0, l.z);
    c.tip_bent = Vec3::new(l.x, l.y, 0.0);
    c
}

fn correction(e: &EffectConfig, s: Vec3, l: Vec3) -> Vec3 {
    let b = e.build(&mut SensorTable::default()).unwrap();
    b.model.correction(&ctx(s, l))
}

/// 5×5 balls, 100 mm pitch (a 400 mm plate) in the XY plane at z = −450, stylus offset l.
fn ball_plate() -> Vec<Vec3> {
    let mut v = vec![];
    for a in 0..5 {
        for b in 0..5 {
            v.push(Vec3::new(
                300.0 + 100.0 * a as f64,
                200.0 + 100.0 * b as f64,
                -450.0,
            ));
        }
    }
    v
}

const STYLUS: [f64; 3] = [40.0, -60.0, -120.0];

/// A second-order bound of what the first-order model leaves out: (Σ|ε|)²·L + Σ|ε|·Σ|δ| with
/// L the longest lever, doubled for the cross terms of the product of three rotations.
fn second_order_bound(e: &Errors, l: &Vec3) -> f64 {
    let (ang, tr) = e.magnitudes();
    let lever = Vec3::new(HI[0], HI[1], LO[2]).norm() + l.norm();
    2.0 * (ang * ang * lever + ang * tr)
}

#[test]
fn first_order_model_matches_the_exact_chain_to_second_order() {
    let l = Vec3::from(STYLUS);
    let mut points = ball_plate();
    for k in 0..=10 {
        let f = k as f64 / 10.0;
        points.push(Vec3::new(LO[0] + f * 1000.0, LO[1] + f * 800.0, HI[2] - f * 600.0) + l);
    }
    for chain in CHAINS {
        let mut worst = vec![];
        for scale in [1.0, 0.5, 0.1] {
            let e = realistic(scale);
            let doc = e.document(chain);
            let bound = second_order_bound(&e, &l);
            let (mut max_diff, mut max_dev) = (0.0f64, 0.0f64);
            for p in &points {
                let s = p - l; // scale reading with the tip nominally at p
                let dev = e.tip(chain, &s, &l) - (s + l);
                let c = correction(&doc, s, l);
                max_diff = max_diff.max((dev - c).norm());
                max_dev = max_dev.max(dev.norm());
            }
            assert!(
                max_diff < bound,
                "{chain} ×{scale}: first order off by {max_diff:e} mm > bound {bound:e}"
            );
            // The deviations are µm, the mismatch a thousandth of that or less.
            assert!(
                max_dev > 1e-3 * scale && max_diff < 1e-3 * max_dev,
                "{chain}"
            );
            worst.push(max_diff);
        }
        // Halving every error quarters the mismatch: what is left is second order only (a
        // wrong sign or lever would leave a first-order remainder that halves).
        let ratio = worst[0] / worst[1];
        assert!((3.5..4.5).contains(&ratio), "{chain}: ratio {ratio}");
        let ratio = worst[1] / worst[2];
        assert!((20.0..30.0).contains(&ratio), "{chain}: ratio {ratio}");
        // At the µrad level (×0.1: angles ≤ 1.3 µrad, squareness ≤ 0.5 µrad) over levers up to
        // 1.4 m the first-order model is exact to below a picometre.
        assert!(worst[2] < 1e-9, "{chain}: {:e} mm", worst[2]);
    }
}

/// The scale reading at which the real tip sits at `target` (fixed-point iteration).
fn probe(e: &Errors, chain: &str, target: &Vec3, l: &Vec3) -> Vec3 {
    let mut s = target - l;
    for _ in 0..20 {
        s -= e.tip(chain, &s, l) - target;
    }
    assert!((e.tip(chain, &s, l) - target).norm() < 1e-12);
    s
}

#[test]
fn ball_plate_is_corrected_to_the_second_order_bound() {
    let l = Vec3::from(STYLUS);
    let e = realistic(1.0);
    let bound = second_order_bound(&e, &l);
    for chain in CHAINS {
        let doc = e.document(chain);
        let (mut raw, mut corrected) = (0.0f64, 0.0f64);
        for ball in ball_plate() {
            let s = probe(&e, chain, &ball, &l);
            // Uncorrected machine: measured = s + l; corrected: + the effect's correction.
            let measured = s + l;
            let fixed = measured + correction(&doc, s, l);
            raw = raw.max((measured - ball).norm());
            corrected = corrected.max((fixed - ball).norm());
        }
        assert!(
            raw > 2e-3,
            "{chain}: the errors should show on the plate ({raw:e})"
        );
        // The correction is evaluated at the measured reading, not the nominal one: add the
        // slope of the errors times the error itself (inside the bound's Σ|ε|·Σ|δ| term).
        // Relative to the error it removes, what is left is of the order of the angles
        // (≤ ~1e-5 rad here).
        assert!(
            corrected < bound && corrected < 1e-5 * raw,
            "{chain}: ball plate corrected to {corrected:e} mm (raw {raw:e}), bound {bound:e}"
        );
    }
}

#[test]
fn gauge_blocks_along_the_space_diagonal() {
    let l = Vec3::from(STYLUS);
    let e = realistic(1.0);
    let bound = second_order_bound(&e, &l);
    let start = Vec3::new(100.0, 80.0, -580.0);
    let dir = Vec3::new(800.0, 640.0, 480.0).normalize(); // s stays inside the travel
    for chain in CHAINS {
        let doc = e.document(chain);
        let (mut raw, mut corrected) = (0.0f64, 0.0f64);
        for length in [100.0, 300.0, 500.0, 700.0, 1000.0] {
            let a = start + dir * 50.0;
            let b = a + dir * length;
            let (sa, sb) = (probe(&e, chain, &a, &l), probe(&e, chain, &b, &l));
            let measured = (sb - sa).dot(&dir);
            let fixed = (sb + correction(&doc, sb, l) - sa - correction(&doc, sa, l)).dot(&dir);
            raw = raw.max((measured - length).abs());
            corrected = corrected.max((fixed - length).abs());
        }
        assert!(raw > 1e-3, "{chain}: length errors should show ({raw:e})");
        assert!(
            corrected < 2.0 * bound && corrected < 1e-5 * raw,
            "{chain}: gauge blocks corrected to {corrected:e} mm (raw {raw:e})"
        );
    }
}
