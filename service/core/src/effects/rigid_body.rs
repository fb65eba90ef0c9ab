//! The 21 rigid-body errors of a three-axis CMM, composed through its kinematic chain.
//!
//! Equation (first order, small angles): with s the scale readings, l the stylus offset
//! (`tip_offset`, machine axes) and, for each axis i, its translation errors
//! δ_i(s_i) = (δ_xi, δ_yi, δ_zi) (positioning δ_ii, straightness δ_ji) and angular errors
//! ε_i(s_i) = (ε_xi, ε_yi, ε_zi) (roll about its own axis, pitch and yaw about the others),
//!
//! δ = Σ_i σ_i·[ δ_i(s_i) + ε_i(s_i) × λ_i ] + (S_xy·y + S_xz·z, S_yz·z, 0),
//!
//! * λ_i, the Abbe lever of axis i, is the nominal vector from the frame that axis i moves to
//!   the tip: for an axis that carries the probe, the positions of the probe-side axes further
//!   down the chain plus the stylus offset (so the carriages see the ram extension z·e_z, the
//!   ram itself only l); for an axis that moves the part (the table of a fixed bridge), the
//!   whole tip position in the part frame, s + l.
//! * σ_i = +1 for an axis that moves the probe, −1 for one that moves the part: the
//!   parameters are the errors of the moving component itself (the table's own deviation,
//!   machine axes), and the tip moves relative to the part by the opposite amount.
//! * Each error is a polynomial in the normalised position u_i = (s_i − c_i)/h_i (`center_mm`,
//!   `half_range_mm`, clamped to [−1, 1], constant beyond the range):
//!   positioning δ_ii = Σ_{k=1..N} c_k u^k, straightness δ_ji = Σ_{k=2..N} c_k u^k, angular
//!   ε_ji = Σ_{k=1..N} c_k u^k, N = `order` (1…4).
//! * No constant terms: a constant translation is the part's placement; a constant angle times
//!   the lever is a constant per stylus (absorbed by tip qualification) plus terms linear in
//!   the positions that squareness and the part's orientation already carry. Straightness
//!   starts at u²: its linear part is, by the ISO 230-1 definition (deviation from the
//!   reference straight line), squareness or the part's orientation.
//! * Or, for errors with waviness no low-order polynomial follows (`spline_segments`), each
//!   error is a uniform cubic B-spline over the same range, e(u) = Σ_k c_k B_k(u), with
//!   `segments + 3` coefficients per error: a table whose smoothness the fit controls by a
//!   penalty on the second differences of the c_k (a P-spline: Eilers & Marx, "Flexible
//!   smoothing with B-splines and penalties", Statistical Science 11, 1996). The spline has
//!   constant and linear parts; what of them the data cannot tell from the placements and the
//!   squareness stays at zero by the fit's ridge.
//! * Squareness S_xy, S_xz, S_yz (rad) enter proportionally to the scale positions: the tip
//!   moves relative to the part along (S_xy, 1, 0) with y and along (S_xz, S_yz, 1) with z,
//!   whatever the chain (positive S_xy: the angle between +x and +y is π/2 − S_xy).
//!
//! The corrector adds δ to the scale reading, so δ is the tip's actual position relative to
//! the part minus its nominal one.
//!
//! Chains (serial order from the base to the tip; ISO 10360-1 machine types):
//! `moving_bridge` Y (bridge) → X (carriage) → Z (ram), part on the fixed table;
//! `cantilever` the same order (Y arm → X carriage → Z ram), kinematically identical to first
//! order with levers taken from scale zero; `fixed_bridge` X carriage → Z ram with the table
//! moving the part in Y; `horizontal_arm` X column → Z carriage → Y arm. Levers are measured
//! from the scale zero of each axis: the frames of the chain coincide when all scales read
//! zero (another pivot changes the coefficients, not the span of the model).
//!
//! Names (ISO 230-1): EXX positioning of X, EYX straightness of X in Y, AZX rotation of X
//! about Z (ISO 230-1:2012 writes ECX; `ECX`, `EAY`, … are accepted as aliases).
//!
//! Source: ISO 230-1 (geometric accuracy of machines: the six errors of each linear axis and
//! squareness); the rigid-body model of a CMM with its Abbe offsets in Schultschik, Hocken &
//! Pereira, "Coordinate Measuring Machines and Systems" (the 21 parametric errors composed
//! along the kinematic chain).

use super::Effect;
use crate::sample::{PointContext, Vec3};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// How the three axes are stacked between the part and the probe.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Chain {
    /// Y carries the bridge, X the carriage on it, Z the ram; the part on the fixed table.
    #[default]
    MovingBridge,
    /// The table moves the part in Y; X carriage on the fixed bridge, Z ram.
    FixedBridge,
    /// Y arm, X carriage on the arm, Z ram (same serial order as the moving bridge).
    Cantilever,
    /// X column, Z carriage on the column, Y horizontal arm.
    HorizontalArm,
}

impl Chain {
    /// Axes that carry the probe, from the base to the tip, and the axis that moves the part.
    pub fn layout(self) -> (&'static [usize], Option<usize>) {
        match self {
            Chain::MovingBridge | Chain::Cantilever => (&[1, 0, 2], None),
            Chain::FixedBridge => (&[0, 2], Some(1)),
            Chain::HorizontalArm => (&[0, 2, 1], None),
        }
    }
}

/// One of the 18 per-axis errors: `E<dir><axis>` translation, `A<about><axis>` rotation.
#[allow(missing_docs)]
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "UPPERCASE")]
pub enum Component {
    Exx,
    Eyx,
    Ezx,
    #[serde(alias = "EAX")]
    Axx,
    #[serde(alias = "EBX")]
    Ayx,
    #[serde(alias = "ECX")]
    Azx,
    Exy,
    Eyy,
    Ezy,
    #[serde(alias = "EAY")]
    Axy,
    #[serde(alias = "EBY")]
    Ayy,
    #[serde(alias = "ECY")]
    Azy,
    Exz,
    Eyz,
    Ezz,
    #[serde(alias = "EAZ")]
    Axz,
    #[serde(alias = "EBZ")]
    Ayz,
    #[serde(alias = "ECZ")]
    Azz,
}

impl Component {
    /// All 18 in document order (per axis x, y, z: EX·, EY·, EZ·, AX·, AY·, AZ·).
    pub const ALL: [Component; 18] = [
        Component::Exx,
        Component::Eyx,
        Component::Ezx,
        Component::Axx,
        Component::Ayx,
        Component::Azx,
        Component::Exy,
        Component::Eyy,
        Component::Ezy,
        Component::Axy,
        Component::Ayy,
        Component::Azy,
        Component::Exz,
        Component::Eyz,
        Component::Ezz,
        Component::Axz,
        Component::Ayz,
        Component::Azz,
    ];
    /// (moving axis, rotation?, direction or rotation axis).
    pub fn parts(self) -> (usize, bool, usize) {
        let i = self as usize;
        (i / 6, (i % 6) >= 3, i % 3)
    }
    /// ISO 230-1 style name, e.g. `EYX`.
    pub fn name(self) -> String {
        let (axis, rot, dir) = self.parts();
        let a = ["X", "Y", "Z"];
        format!("{}{}{}", if rot { "A" } else { "E" }, a[dir], a[axis])
    }
    /// Lowest polynomial power: 2 for straightness, 1 otherwise.
    pub fn first_power(self) -> usize {
        let (axis, rot, dir) = self.parts();
        if !rot && dir != axis {
            2
        } else {
            1
        }
    }
    /// Number of coefficients at polynomial order `order`.
    pub fn count(self, order: u8) -> usize {
        (order as usize + 1).saturating_sub(self.first_power())
    }
}

/// Squareness errors, rad.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Squareness {
    /// Between X and Y: δx = S_xy·y.
    #[serde(default)]
    pub xy: f64,
    /// Between X and Z: δx = S_xz·z.
    #[serde(default)]
    pub xz: f64,
    /// Between Y and Z: δy = S_yz·z.
    #[serde(default)]
    pub yz: f64,
}

/// Document form.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// Optional name.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub id: Option<String>,
    /// Kinematic chain.
    #[serde(default)]
    pub chain: Chain,
    /// Polynomial order N of every error (1…4); with `spline_segments`, the spline's degree
    /// (3: cubic).
    pub order: u8,
    /// Cubic B-spline tables instead of polynomials: segments per axis over centre ± half
    /// range (each error then has segments + 3 coefficients, the spline's control values).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub spline_segments: Option<[u16; 3]>,
    /// Centre of the normalised positions per axis, mm.
    pub center_mm: [f64; 3],
    /// Half range per axis (u = ±1 at centre ± half range), mm.
    pub half_range_mm: [f64; 3],
    /// Coefficients c_first..c_N per modelled error (absent: not modelled), mm or rad.
    #[serde(default)]
    pub errors: BTreeMap<Component, Vec<f64>>,
    /// Squareness errors, rad.
    #[serde(default)]
    pub squareness_rad: Squareness,
}

#[derive(Debug, Clone)]
struct Term {
    axis: usize,
    rot: bool,
    dir: usize,
    first: usize,
    coef: Vec<f64>,
}

/// Segment index and the four nonzero uniform cubic B-spline weights at x (in segment units,
/// clamped to [0, segs]).
#[inline]
fn bspline(x: f64, segs: usize) -> (usize, [f64; 4]) {
    let x = x.clamp(0.0, segs as f64);
    let j = (x.floor() as usize).min(segs - 1);
    let t = x - j as f64;
    let (t2, t3) = (t * t, t * t * t);
    let w = [
        (1.0 - t) * (1.0 - t) * (1.0 - t) / 6.0,
        (3.0 * t3 - 6.0 * t2 + 4.0) / 6.0,
        (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) / 6.0,
        t3 / 6.0,
    ];
    (j, w)
}

/// Hot-path form.
#[derive(Debug, Clone)]
pub struct Model {
    terms: Vec<Term>,
    center: [f64; 3],
    inv_half: [f64; 3],
    probe_side: &'static [usize],
    part_side: Option<usize>,
    squareness: [f64; 3],
    n: usize,
    /// Spline segments per axis (None: polynomials).
    segs: Option<[usize; 3]>,
}

impl Config {
    /// Zero-parameter model with all 18 errors and the squareness; `ranges` per axis
    /// `[lo, hi]` mm (the travel) set centre and half range.
    pub fn zeros(chain: Chain, order: u8, ranges: [[f64; 2]; 3]) -> Config {
        let errors = Component::ALL
            .iter()
            .filter(|c| c.count(order) > 0)
            .map(|c| (*c, vec![0.0; c.count(order)]))
            .collect();
        Config {
            id: None,
            chain,
            order,
            spline_segments: None,
            center_mm: ranges.map(|r| 0.5 * (r[0] + r[1])),
            half_range_mm: ranges.map(|r| 0.5 * (r[1] - r[0])),
            errors,
            squareness_rad: Squareness::default(),
        }
    }
    /// Zero-parameter model with all 18 errors as cubic B-spline tables, knots about
    /// `step_mm` apart over `ranges`, and the squareness.
    pub fn zeros_spline(chain: Chain, ranges: [[f64; 2]; 3], step_mm: f64) -> Config {
        let segs = ranges.map(|r| ((r[1] - r[0]) / step_mm).ceil().clamp(1.0, 200.0) as u16);
        let errors = Component::ALL
            .iter()
            .map(|c| (*c, vec![0.0; segs[c.parts().0] as usize + 3]))
            .collect();
        Config {
            spline_segments: Some(segs),
            errors,
            ..Config::zeros(chain, 3, ranges)
        }
    }
    /// Coefficients error `c` has in this configuration.
    pub fn count(&self, c: Component) -> usize {
        match self.spline_segments {
            Some(s) => s[c.parts().0] as usize + 3,
            None => c.count(self.order),
        }
    }
    /// Validates.
    pub fn build(&self) -> Result<Model, String> {
        if !(1..=4).contains(&self.order) {
            return Err("order: must be 1, 2, 3 or 4".into());
        }
        if let Some(s) = self.spline_segments {
            if self.order != 3 {
                return Err("order: a spline table is cubic: order must be 3".into());
            }
            if let Some(i) = s.iter().position(|n| !(1..=200).contains(n)) {
                return Err(format!("spline_segments[{i}]: must be 1…200"));
            }
        }
        for (i, c) in self.center_mm.iter().enumerate() {
            if !c.is_finite() {
                return Err(format!("center_mm[{i}]: must be a finite number"));
            }
        }
        for (i, h) in self.half_range_mm.iter().enumerate() {
            if !(h.is_finite() && *h > 0.0) {
                return Err(format!("half_range_mm[{i}]: must be a finite number > 0"));
            }
        }
        let mut terms = vec![];
        for (c, v) in &self.errors {
            let field = format!("errors.{}", c.name());
            let want = self.count(*c);
            if want == 0 || v.len() != want {
                return Err(if self.spline_segments.is_some() {
                    format!(
                        "{field}: {} spline segments need {want} coefficients, got {}",
                        self.spline_segments.unwrap()[c.parts().0],
                        v.len()
                    )
                } else if want == 0 {
                    format!(
                        "{field}: straightness starts at u², order {} has none (remove it)",
                        self.order
                    )
                } else {
                    format!(
                        "{field}: order {} needs {want} coefficients (c{}…c{}), got {}",
                        self.order,
                        c.first_power(),
                        self.order,
                        v.len()
                    )
                });
            }
            super::check_finite(&field, v)?;
            let (axis, rot, dir) = c.parts();
            terms.push(Term {
                axis,
                rot,
                dir,
                first: c.first_power(),
                coef: v.clone(),
            });
        }
        let s = self.squareness_rad;
        for (name, v) in [("xy", s.xy), ("xz", s.xz), ("yz", s.yz)] {
            if !v.is_finite() {
                return Err(format!("squareness_rad.{name}: must be a finite number"));
            }
        }
        let (probe_side, part_side) = self.chain.layout();
        let n = terms.iter().map(|t| t.coef.len()).sum::<usize>() + 3;
        Ok(Model {
            terms,
            center: self.center_mm,
            inv_half: self.half_range_mm.map(|h| 1.0 / h),
            probe_side,
            part_side,
            squareness: [s.xy, s.xz, s.yz],
            n,
            segs: self.spline_segments.map(|s| s.map(|n| n as usize)),
        })
    }
    /// Flat parameters: the errors in component order (c_first…c_N each), then squareness
    /// xy, xz, yz.
    pub fn params(&self) -> Vec<f64> {
        let s = self.squareness_rad;
        self.errors
            .values()
            .flatten()
            .copied()
            .chain([s.xy, s.xz, s.yz])
            .collect()
    }
    /// Sets flat parameters.
    pub fn set_params(&mut self, v: &[f64]) {
        let mut it = v.iter().copied();
        for c in self.errors.values_mut() {
            c.iter_mut().for_each(|x| *x = it.next().unwrap());
        }
        self.squareness_rad = Squareness {
            xy: it.next().unwrap(),
            xz: it.next().unwrap(),
            yz: it.next().unwrap(),
        };
    }
    /// Parameter names, e.g. `EYX c2 (mm)`, `AZX c1 (rad)`, `squareness xy (rad)`; for
    /// spline tables the knot each control value sits at, `EXX at x=350 mm (mm)`.
    pub fn param_names(&self) -> Vec<String> {
        let mut v = vec![];
        for (c, coef) in &self.errors {
            let (axis, rot, _) = c.parts();
            let unit = if rot { "rad" } else { "mm" };
            for k in 0..coef.len() {
                v.push(match self.spline_segments {
                    Some(s) => {
                        let h = self.half_range_mm[axis];
                        let step = 2.0 * h / s[axis] as f64;
                        let at = self.center_mm[axis] - h + (k as f64 - 1.0) * step;
                        format!(
                            "{} at {}={at:.0} mm ({unit})",
                            c.name(),
                            ["x", "y", "z"][axis]
                        )
                    }
                    None => format!("{} c{} ({unit})", c.name(), c.first_power() + k),
                });
            }
        }
        v.extend(["xy", "xz", "yz"].map(|p| format!("squareness {p} (rad)")));
        v
    }
}

impl Model {
    /// Powers u_i^0…u_i^4 of the clamped normalised positions.
    #[inline]
    fn powers(&self, s: &Vec3) -> [[f64; 5]; 3] {
        let mut p = [[1.0; 5]; 3];
        for (i, pi) in p.iter_mut().enumerate() {
            let u = ((s[i] - self.center[i]) * self.inv_half[i]).clamp(-1.0, 1.0);
            for k in 1..5 {
                pi[k] = pi[k - 1] * u;
            }
        }
        p
    }
    /// Segment and B-spline weights per axis (spline tables only).
    #[inline]
    fn splines(&self, s: &Vec3) -> Option<[(usize, [f64; 4]); 3]> {
        self.segs.map(|segs| {
            [0, 1, 2].map(|i| {
                let u = (s[i] - self.center[i]) * self.inv_half[i];
                bspline((u + 1.0) * 0.5 * segs[i] as f64, segs[i])
            })
        })
    }
    /// Signed Abbe lever λ_i per axis and sign σ_i.
    #[inline]
    fn levers(&self, ctx: &PointContext) -> ([Vec3; 3], [f64; 3]) {
        let l = ctx.tip_offset();
        let mut lever = [Vec3::zeros(); 3];
        let mut sign = [1.0; 3];
        let mut acc = l;
        for &a in self.probe_side.iter().rev() {
            lever[a] = acc;
            acc[a] += ctx.scale[a];
        }
        if let Some(a) = self.part_side {
            lever[a] = ctx.scale + l;
            sign[a] = -1.0;
        }
        (lever, sign)
    }
}

#[inline]
fn unit_cross(dir: usize, v: &Vec3) -> Vec3 {
    let mut e = Vec3::zeros();
    e[dir] = 1.0;
    e.cross(v)
}

impl Effect for Model {
    fn n_params(&self) -> usize {
        self.n
    }
    fn regressors(&self, ctx: &PointContext, out: &mut [Vec3]) {
        let p = self.powers(&ctx.scale);
        let sp = self.splines(&ctx.scale);
        let (lever, sign) = self.levers(ctx);
        let mut j = 0;
        for t in &self.terms {
            let v = if t.rot {
                unit_cross(t.dir, &lever[t.axis])
            } else {
                let mut e = Vec3::zeros();
                e[t.dir] = 1.0;
                e
            } * sign[t.axis];
            match &sp {
                Some(sp) => {
                    let (seg, w) = sp[t.axis];
                    out[j..j + t.coef.len()].fill(Vec3::zeros());
                    for (m, wm) in w.iter().enumerate() {
                        out[j + seg + m] = v * *wm;
                    }
                }
                None => {
                    for k in 0..t.coef.len() {
                        out[j + k] = v * p[t.axis][t.first + k];
                    }
                }
            }
            j += t.coef.len();
        }
        let s = &ctx.scale;
        out[j] = Vec3::new(s.y, 0.0, 0.0);
        out[j + 1] = Vec3::new(s.z, 0.0, 0.0);
        out[j + 2] = Vec3::new(0.0, s.z, 0.0);
    }
    #[inline]
    fn correction(&self, ctx: &PointContext) -> Vec3 {
        let p = self.powers(&ctx.scale);
        let sp = self.splines(&ctx.scale);
        let (lever, sign) = self.levers(ctx);
        let mut d = Vec3::zeros();
        for t in &self.terms {
            let val = match &sp {
                Some(sp) => {
                    let (seg, w) = sp[t.axis];
                    w.iter()
                        .zip(&t.coef[seg..seg + 4])
                        .map(|(w, c)| w * c)
                        .sum::<f64>()
                }
                None => {
                    let pt = &p[t.axis];
                    t.coef
                        .iter()
                        .enumerate()
                        .map(|(k, c)| c * pt[t.first + k])
                        .sum::<f64>()
                }
            } * sign[t.axis];
            if t.rot {
                d += unit_cross(t.dir, &lever[t.axis]) * val;
            } else {
                d[t.dir] += val;
            }
        }
        let s = &ctx.scale;
        let q = &self.squareness;
        d.x += q[0] * s.y + q[1] * s.z;
        d.y += q[2] * s.z;
        d
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::effects::{testutil::assert_linear, EffectConfig};

    const RANGES: [[f64; 2]; 3] = [[0.0, 1000.0], [0.0, 800.0], [-600.0, 0.0]];

    fn ctx_at(s: Vec3, l: Vec3) -> PointContext {
        let mut c = PointContext::at_rest(s);
        c.tip_shank = Vec3::new(0.0, 0.0, l.z);
        c.tip_bent = Vec3::new(l.x, l.y, 0.0);
        c
    }

    fn filled(chain: Chain, order: u8) -> Config {
        let mut c = Config::zeros(chain, order, RANGES);
        let mut k = 0.0_f64;
        for (comp, v) in c.errors.iter_mut() {
            let scale = if comp.parts().1 { 1e-6 } else { 1e-3 };
            v.iter_mut().for_each(|x| {
                k += 1.0;
                *x = scale * (0.3 + 0.17 * k).sin();
            });
        }
        c.squareness_rad = Squareness {
            xy: 3e-6,
            xz: -2e-6,
            yz: 1e-6,
        };
        c
    }

    #[test]
    fn linear_in_parameters_for_every_chain_and_order() {
        for chain in [
            Chain::MovingBridge,
            Chain::FixedBridge,
            Chain::Cantilever,
            Chain::HorizontalArm,
        ] {
            for order in 1..=4u8 {
                let c = filled(chain, order);
                let m = c.build().unwrap();
                assert_eq!(m.n_params(), 18 * order as usize - 3);
                for s in [
                    Vec3::new(100.0, 700.0, -50.0),
                    Vec3::new(900.0, 30.0, -580.0),
                    Vec3::new(1200.0, -5.0, 10.0), // outside: clamped
                ] {
                    let ctx = ctx_at(s, Vec3::new(15.0, -40.0, -120.0));
                    assert_linear(&m, &EffectConfig::RigidBody(c.clone()), &ctx);
                }
            }
        }
    }

    fn filled_spline(chain: Chain) -> Config {
        let mut c = Config::zeros_spline(chain, RANGES, 130.0);
        let mut k = 0.0_f64;
        for (comp, v) in c.errors.iter_mut() {
            let scale = if comp.parts().1 { 1e-6 } else { 1e-3 };
            v.iter_mut().for_each(|x| {
                k += 1.0;
                *x = scale * (0.7 + 0.31 * k).cos();
            });
        }
        c.squareness_rad.xz = 2e-6;
        c
    }

    #[test]
    fn spline_tables_are_linear_in_their_control_values() {
        for chain in [
            Chain::MovingBridge,
            Chain::FixedBridge,
            Chain::HorizontalArm,
        ] {
            let c = filled_spline(chain);
            // 1000/130 → 8 segments in x, 800/130 → 7 in y, 600/130 → 5 in z.
            assert_eq!(c.spline_segments, Some([8, 7, 5]));
            let m = c.build().unwrap();
            assert_eq!(m.n_params(), 6 * (11 + 10 + 8) + 3);
            for s in [
                Vec3::new(0.0, 0.0, -600.0), // the range's corner: the last segment's end
                Vec3::new(433.0, 517.0, -233.0),
                Vec3::new(1000.0, 800.0, 0.0),
                Vec3::new(-50.0, 900.0, 40.0), // outside: clamped
            ] {
                let ctx = ctx_at(s, Vec3::new(-20.0, 35.0, -110.0));
                assert_linear(&m, &EffectConfig::RigidBody(c.clone()), &ctx);
            }
        }
    }

    #[test]
    fn a_spline_holds_a_straight_line_and_names_its_knots() {
        // A cubic B-spline whose control values lie on a line (each at its knot, the name's
        // position) is that line: positioning error 2 µm per 100 mm.
        let mut c = Config::zeros_spline(Chain::MovingBridge, RANGES, 125.0);
        let names = c.param_names();
        let exx: Vec<f64> = names
            .iter()
            .filter(|n| n.starts_with("EXX at x="))
            .map(|n| {
                n["EXX at x=".len()..]
                    .split(' ')
                    .next()
                    .unwrap()
                    .parse()
                    .unwrap()
            })
            .collect();
        assert_eq!(
            exx,
            [-125.0, 0.0, 125.0, 250.0, 375.0, 500.0, 625.0, 750.0, 875.0, 1000.0, 1125.0]
        );
        // 800 mm in 7 segments: knots 114.3 mm apart.
        assert!(
            names.contains(&"AZY at y=457 mm (rad)".to_string()),
            "{names:?}"
        );
        c.errors
            .insert(Component::Exx, exx.iter().map(|x| 2e-5 * x).collect());
        let m = c.build().unwrap();
        for x in [0.0, 1.0, 333.3, 640.0, 999.0, 1000.0] {
            let d = m.correction(&ctx_at(Vec3::new(x, 100.0, -100.0), Vec3::zeros()));
            assert!(
                (d - Vec3::new(2e-5 * x, 0.0, 0.0)).norm() < 1e-15,
                "{x}: {d:?}"
            );
        }
        // Beyond the range: the end value.
        let d = m.correction(&ctx_at(Vec3::new(1200.0, 0.0, 0.0), Vec3::zeros()));
        assert!((d.x - 2e-2).abs() < 1e-15, "{d:?}");
    }

    #[test]
    fn yaw_of_x_is_an_abbe_error_of_the_y_stylus_offset() {
        // AZX (yaw of the X carriage about z): δ = ε ẑ × (z ẑ + l) = ε·(−l_y, l_x, 0).
        let mut c = Config::zeros(Chain::MovingBridge, 1, RANGES);
        let eps = 5e-6; // c1: ε = 5 µrad at u = 1 (x = 1000)
        c.errors.insert(Component::Azx, vec![eps]);
        let m = c.build().unwrap();
        let s = Vec3::new(1000.0, 300.0, -200.0);
        for ly in [0.0, 50.0, 100.0, 200.0] {
            let d = m.correction(&ctx_at(s, Vec3::new(0.0, ly, -100.0)));
            assert!((d - Vec3::new(-eps * ly, 0.0, 0.0)).norm() < 1e-15, "{d:?}");
        }
        // Z position (ram extension) does not matter for a rotation about z.
        let d1 = m.correction(&ctx_at(Vec3::new(1000.0, 300.0, -500.0), Vec3::y() * 80.0));
        assert!((d1.x + eps * 80.0).abs() < 1e-15);
        // Roll of X (AXX) sees the ram extension: x̂ × (z ẑ + l) with l = 0 → (0, −z, 0)·ε.
        let mut r = Config::zeros(Chain::MovingBridge, 1, RANGES);
        r.errors.insert(Component::Axx, vec![eps]);
        let d = r
            .build()
            .unwrap()
            .correction(&ctx_at(Vec3::new(1000.0, 0.0, -400.0), Vec3::zeros()));
        assert!(
            (d - Vec3::new(0.0, eps * 400.0, 0.0)).norm() < 1e-15,
            "{d:?}"
        );
        // Fixed bridge: the table (Y) moves the part, its yaw sees the whole tip position
        // with the opposite sign: −ε ẑ × (s + l).
        let mut f = Config::zeros(Chain::FixedBridge, 1, RANGES);
        f.errors.insert(Component::Azy, vec![eps]);
        let s = Vec3::new(200.0, 800.0, -100.0);
        let l = Vec3::new(0.0, 30.0, -50.0);
        let d = f.build().unwrap().correction(&ctx_at(s, l));
        let want = -(Vec3::z().cross(&(s + l))) * eps;
        assert!((d - want).norm() < 1e-15, "{d:?} vs {want:?}");
    }

    #[test]
    fn squareness_xy_is_an_x_error_proportional_to_y() {
        let mut c = Config::zeros(Chain::HorizontalArm, 2, RANGES);
        c.squareness_rad.xy = 4e-6;
        let m = c.build().unwrap();
        for y in [0.0, 200.0, 800.0] {
            let d = m.correction(&ctx_at(
                Vec3::new(321.0, y, -77.0),
                Vec3::new(0.0, 0.0, -90.0),
            ));
            assert!((d - Vec3::new(4e-6 * y, 0.0, 0.0)).norm() < 1e-15, "{d:?}");
        }
    }

    #[test]
    fn positioning_polynomial_and_names() {
        let mut c = Config::zeros(Chain::MovingBridge, 3, RANGES);
        c.errors.insert(Component::Exx, vec![1e-3, 2e-3, -1e-3]);
        let m = c.build().unwrap();
        // x = 750 → u = 0.5: 0.5e-3 + 0.5e-3 − 0.125e-3.
        let d = m.correction(&ctx_at(Vec3::new(750.0, 0.0, 0.0), Vec3::zeros()));
        assert!((d - Vec3::new(0.875e-3, 0.0, 0.0)).norm() < 1e-15, "{d:?}");
        let names = c.param_names();
        assert_eq!(names.len(), 18 * 3 - 3);
        assert_eq!(names[0], "EXX c1 (mm)");
        assert!(names.contains(&"EYX c2 (mm)".to_string()));
        assert!(names.contains(&"AZX c1 (rad)".to_string()));
        assert!(!names.contains(&"EYX c1 (mm)".to_string()));
        assert_eq!(names.last().unwrap(), "squareness yz (rad)");
    }

    #[test]
    fn serde_round_trip_and_aliases() {
        let c = EffectConfig::RigidBody(filled(Chain::FixedBridge, 2));
        let s = serde_json::to_string(&c).unwrap();
        assert!(s.contains("\"kind\":\"rigid_body\"") && s.contains("\"fixed_bridge\""));
        assert!(s.contains("\"EYX\""));
        let back: EffectConfig = serde_json::from_str(&s).unwrap();
        // serde_json may round the last bit of a float: same structure, same values.
        assert_eq!(back.with_params(&c.params()).unwrap(), c);
        for (x, y) in back.params().iter().zip(c.params()) {
            assert!((x - y).abs() <= 1e-15 * y.abs(), "{x} vs {y}");
        }
        let doc = r#"{"kind":"rigid_body","order":1,"center_mm":[0,0,0],
            "half_range_mm":[1,1,1],"errors":{"ECX":[1e-6]}}"#;
        let EffectConfig::RigidBody(a) = serde_json::from_str(doc).unwrap() else {
            panic!()
        };
        assert_eq!(a.chain, Chain::MovingBridge);
        assert_eq!(
            a.errors.keys().copied().collect::<Vec<_>>(),
            [Component::Azx]
        );
        assert!(serde_json::from_str::<EffectConfig>(&doc.replace("ECX", "EQX")).is_err());
    }

    #[test]
    fn validation_names_the_field() {
        let ok = Config::zeros(Chain::MovingBridge, 2, RANGES);
        let err = |f: &dyn Fn(&mut Config)| {
            let mut c = ok.clone();
            f(&mut c);
            c.build().unwrap_err()
        };
        assert!(err(&|c| c.order = 5).starts_with("order:"));
        assert!(err(&|c| c.order = 0).starts_with("order:"));
        assert!(err(&|c| c.half_range_mm[1] = 0.0).starts_with("half_range_mm[1]:"));
        assert!(err(&|c| c.center_mm[2] = f64::NAN).starts_with("center_mm[2]:"));
        let e = err(&|c| {
            c.errors.insert(Component::Eyx, vec![0.0, 0.0]);
        });
        assert!(e.starts_with("errors.EYX:"), "{e}");
        let e = err(&|c| {
            c.errors.insert(Component::Azz, vec![f64::INFINITY, 0.0]);
        });
        assert!(e.starts_with("errors.AZZ[0]:"), "{e}");
        assert!(err(&|c| c.squareness_rad.yz = f64::NAN).starts_with("squareness_rad.yz:"));
        let sp = Config::zeros_spline(Chain::MovingBridge, RANGES, 100.0);
        let mut bad = sp.clone();
        bad.order = 2;
        assert!(bad.build().unwrap_err().contains("cubic"));
        let mut bad = sp.clone();
        bad.spline_segments = Some([10, 0, 6]);
        assert!(bad.build().unwrap_err().starts_with("spline_segments[1]:"));
        let mut bad = sp.clone();
        bad.errors.insert(Component::Eyy, vec![0.0; 4]);
        let e = bad.build().unwrap_err();
        assert!(
            e.starts_with("errors.EYY: 8 spline segments need 11"),
            "{e}"
        );
        let mut one = Config::zeros(Chain::MovingBridge, 1, RANGES);
        one.errors.insert(Component::Ezy, vec![]);
        assert!(one.build().is_err());
    }
}
