//! The real-time form of the extrapolation to zero force: two readings of one place at two
//! probing forces give the reading at zero force.
//!
//! Equation (the line through (F1, R1) and (F2, R2) evaluated at F = 0):
//!
//! R0 = R1 − (R2 − R1)·F1/(F2 − F1),
//!
//! with standard uncertainty from the readings' (first order):
//! ∂R0/∂R1 = F2/(F2 − F1), ∂R0/∂R2 = −F1/(F2 − F1), ∂R0/∂F1 = −(R2 − R1)·F2/(F2 − F1)²,
//! ∂R0/∂F2 = (R2 − R1)·F1/(F2 − F1)².
//!
//! A force below significance (|F| < 3σ_F) is taken as zero: its reading is already the
//! zero-force reading and nothing is extrapolated (extrapolating from a force that is noise
//! only adds the noise of the other reading). Two forces whose difference is below
//! significance cannot be extrapolated from at all: the pair is reported as alike.
//!
//! Source idea: Renishaw's calibration of a coordinate positioning apparatus — the probe
//! takes each point at two forces during the one scan and the controller extrapolates to
//! zero force as it goes, no calibration table needed.
//!
//! ## Per point, on a part ([`per_point`], [`part`])
//!
//! A part scanned by the same path at K ≥ 2 probing forces (passes; the force ∝ the probe's
//! deflection |d|): every point p of the lowest-force pass (normal n, force F1) is paired with
//! each other pass k at the same place — the two points of pass k that bracket p across the
//! surface (their separation in the tangent plane at most [`MAX_GAP`] × that pass's median
//! spacing), interpolated linearly to p's tangent position — giving y_k = (q_k − p)·n at force
//! F_k (y_1 = 0 at F1). A polynomial in the force through them,
//!
//! y(F) = a0 + a1·F (+ a2·F²),
//!
//! evaluated at F = 0 is the point at zero force: p0 = p + a0·n, so R1 − R0 = −a0. With two
//! passes this is R0 = R1 − (R2 − R1)·F1/(F2 − F1) at each point; σ(a0)² = σ²·[(XᵀX)⁻¹]₀₀
//! with σ the point's noise (the two-pass case: σ·√(F1² + F2²)/(F2 − F1)). Each point
//! carries its own line: a thin wall that gives under the force bends differently from the
//! sphere the stylus was calibrated on, and only the part itself shows it. With K ≥ 3 passes
//! the quadratic term (a polynomial in the force) is taken when the data ask for it: the
//! linear fits' residuals over all points, Σ SSR / (N·(K − 2)·σ²) = χ²ᵣ, above both
//! 1 + 5·√(2/(N·(K − 2))) and [`QUADRATIC_CHI2`] (the force error is then not linear in
//! the force at these points); otherwise the least-squares line over all K forces.
//!
//! Source idea: Renishaw's calibration of a coordinate positioning apparatus — the part
//! itself scanned at two forces, each point extrapolated to zero force; where the error is not
//! linear in the force, a look-up table or polynomial in the force.
//!
//! ## The force: a force signal, or the deflection ([`Force`])
//!
//! A deflection-only probe says nothing of its force, and the force is taken as its
//! deflection |d| (a spring without preload: F = c·|d|, so F = 0 at |d| = 0). A force probe,
//! or an active probe in constant-force mode, reports the force itself (wire v1.5, `force_n`,
//! N), and its force is not proportional to the deflection: preloaded springs give
//!
//! F = F0 + c·|d|,
//!
//! and the stylus bends with the force (b = K·F along the probing direction) while the part
//! gives with it. The error of a point is then linear in F, not in |d|: the polynomial above
//! is taken in the reported F, and y(F = 0) is the point at zero force. Taken in |d| instead,
//! the polynomial lands at |d| = 0, where the force is still F0: the result keeps the error
//! at the preload, K·F0 (plus the part's give under F0), on every point. Where every point of
//! a set carries a force, the force is the signal ([`Force::Signal`]); otherwise the
//! deflection ([`Force::Deflection`], also on request, to compare). The forces are reported in
//! their unit: `forces_n` (N) from the signal, `forces_mm` (mm of deflection) from |d|.
//!
//! Source idea: Renishaw's calibration of a coordinate positioning apparatus — the variants
//! with a measured probing force (a force probe, a constant-force probe): the extrapolation
//! to zero force in the measured force.

use crate::lab::dataset::{Dataset, Phase};
use nalgebra::Vector3;
use serde::Serialize;
use std::collections::BTreeMap;

/// Readings closer to zero than this many standard uncertainties are zero.
pub const SIGNIFICANCE: f64 = 3.0;

/// One reading: a value (a radius, a coordinate) at a probing force (or a deflection, which
/// is proportional to it), each with its standard uncertainty.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Reading {
    /// The value, any length unit.
    pub r: f64,
    /// Its standard uncertainty.
    pub r_sigma: f64,
    /// The force (or deflection).
    pub f: f64,
    /// Its standard uncertainty.
    pub f_sigma: f64,
}

/// The zero-force value of a pair of readings.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum ZeroForce {
    /// Extrapolated along the line through both readings.
    Extrapolated {
        /// R0.
        r0: f64,
        /// Its standard uncertainty.
        sigma: f64,
    },
    /// One reading's force is below significance: that reading is the zero-force one.
    ForceZero {
        /// R0 (the reading at the insignificant force).
        r0: f64,
        /// Its standard uncertainty.
        sigma: f64,
    },
    /// The two forces do not differ significantly: no line to extrapolate along.
    Alike,
}

impl ZeroForce {
    /// R0 and its σ, when there is one.
    pub fn value(&self) -> Option<(f64, f64)> {
        match *self {
            ZeroForce::Extrapolated { r0, sigma } | ZeroForce::ForceZero { r0, sigma } => {
                Some((r0, sigma))
            }
            ZeroForce::Alike => None,
        }
    }
}

fn insignificant(x: f64, sigma: f64) -> bool {
    x.abs() < SIGNIFICANCE * sigma.abs()
}

/// R0 = R1 − (R2 − R1)·F1/(F2 − F1), a force below significance taken as zero.
pub fn two_force(a: Reading, b: Reading) -> ZeroForce {
    if insignificant(a.f, a.f_sigma) {
        return ZeroForce::ForceZero {
            r0: a.r,
            sigma: a.r_sigma,
        };
    }
    if insignificant(b.f, b.f_sigma) {
        return ZeroForce::ForceZero {
            r0: b.r,
            sigma: b.r_sigma,
        };
    }
    let df = b.f - a.f;
    if insignificant(df, a.f_sigma.hypot(b.f_sigma)) || df == 0.0 {
        return ZeroForce::Alike;
    }
    let dr = b.r - a.r;
    let r0 = a.r - dr * a.f / df;
    let g = [
        (b.f / df, a.r_sigma),
        (-a.f / df, b.r_sigma),
        (-dr * b.f / (df * df), a.f_sigma),
        (dr * a.f / (df * df), b.f_sigma),
    ];
    let sigma = g.iter().map(|(d, s)| (d * s).powi(2)).sum::<f64>().sqrt();
    ZeroForce::Extrapolated { r0, sigma }
}

/// A pass's tangent-plane gap, in its median point spacings, beyond which two points no
/// longer bracket a point of the reference pass (a gap in the scan is not interpolated across).
pub const MAX_GAP: f64 = 4.0;

/// The reduced χ² of the linear fits above which (and above its significance) the quadratic
/// term in the force is taken.
pub const QUADRATIC_CHI2: f64 = 1.5;

/// Mean forces of two passes closer than this fraction of the larger cannot be extrapolated
/// from.
pub const ALIKE_FRACTION: f64 = 0.2;

/// One point of a pass: the corrected surface point, its unit normal (out of the material)
/// and the probing force there (the force signal, N, or the probe's deflection |d|, mm: see
/// [`Force`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PassPoint {
    /// Surface point, mm.
    pub p: Vector3<f64>,
    /// Unit normal.
    pub n: Vector3<f64>,
    /// Force, N (a force signal), or deflection, mm.
    pub f: f64,
}

/// What the force of a point is taken from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Force {
    /// The probe's deflection |d|, mm (F ∝ |d|, no preload).
    Deflection,
    /// The force the probe reports, N.
    Signal,
}

impl Force {
    /// The unit of the force's values.
    pub fn unit(self) -> &'static str {
        match self {
            Force::Deflection => "mm of deflection",
            Force::Signal => "N",
        }
    }
}

/// One point of the part at zero force.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct ZeroPoint {
    /// The point at zero force, mm.
    pub p0: [f64; 3],
    /// Its unit normal.
    pub normal: [f64; 3],
    /// R1 − R0 along the normal (the force's error at the lowest force), µm.
    pub error_at_f1_um: f64,
    /// σ of R0 from the points' noise, µm.
    pub sigma_um: f64,
}

/// Per-point extrapolation of one set of passes.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PerPoint {
    /// What the force was taken from.
    pub force: Force,
    /// Mean deflection of each pass, lowest first, mm (the force taken as the deflection;
    /// empty with a force signal).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub forces_mm: Vec<f64>,
    /// Mean force of each pass, lowest first, N (from the force signal; empty otherwise).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub forces_n: Vec<f64>,
    /// The polynomial's degree in the force (1: a line; 2: a quadratic).
    pub degree: usize,
    /// Reduced χ² of the linear fits (K ≥ 3 passes; none with two).
    pub chi2_linear: Option<f64>,
    /// Points at zero force (every point of the lowest-force pass that the others bracket).
    #[serde(skip)]
    pub points: Vec<ZeroPoint>,
    /// Points of the lowest-force pass no other pass brackets (its ends, gaps).
    pub unpaired: usize,
}

/// A spatial hash of a pass's points (cells of `h` mm).
struct Grid {
    h: f64,
    cells: BTreeMap<[i64; 3], Vec<usize>>,
}

impl Grid {
    fn new(pts: &[PassPoint], h: f64) -> Grid {
        let mut cells: BTreeMap<[i64; 3], Vec<usize>> = BTreeMap::new();
        for (i, q) in pts.iter().enumerate() {
            cells.entry(Self::key(&q.p, h)).or_default().push(i);
        }
        Grid { h, cells }
    }
    fn key(p: &Vector3<f64>, h: f64) -> [i64; 3] {
        [
            (p.x / h).floor() as i64,
            (p.y / h).floor() as i64,
            (p.z / h).floor() as i64,
        ]
    }
    /// The index of the point nearest `p` in the tangent plane of `n` within one cell.
    fn nearest(&self, pts: &[PassPoint], p: &Vector3<f64>, n: &Vector3<f64>) -> Option<usize> {
        let k = Self::key(p, self.h);
        let mut best: Option<(f64, usize)> = None;
        for dx in -1..=1 {
            for dy in -1..=1 {
                for dz in -1..=1 {
                    let Some(v) = self.cells.get(&[k[0] + dx, k[1] + dy, k[2] + dz]) else {
                        continue;
                    };
                    for &j in v {
                        let d = pts[j].p - p;
                        let t = (d - n * d.dot(n)).norm();
                        if best.is_none_or(|(b, _)| t < b) {
                            best = Some((t, j));
                        }
                    }
                }
            }
        }
        best.map(|(_, j)| j)
    }
}

/// The median distance between consecutive points of a pass.
fn median_spacing(pts: &[PassPoint]) -> f64 {
    let mut d: Vec<f64> = pts.windows(2).map(|w| (w[1].p - w[0].p).norm()).collect();
    if d.is_empty() {
        return 0.0;
    }
    d.sort_by(f64::total_cmp);
    d[d.len() / 2]
}

/// Pass `q` (points in scan order) at the place of `p`: (y = (q − p)·n, F), interpolated
/// between the two points that bracket p in its tangent plane.
fn bracket(q: &[PassPoint], grid: &Grid, gap: f64, p: &PassPoint) -> Option<(f64, f64)> {
    let j = grid.nearest(q, &p.p, &p.n)?;
    let tan = |v: Vector3<f64>| v - p.n * v.dot(&p.n);
    for m in [j.wrapping_sub(1), j + 1] {
        let Some(b) = q.get(m) else { continue };
        let a = &q[j];
        let ab = tan(b.p - a.p);
        let l2 = ab.norm_squared();
        if l2 == 0.0 || l2.sqrt() > gap {
            continue;
        }
        let t = tan(p.p - a.p).dot(&ab) / l2;
        if (-1e-9..=1.0 + 1e-9).contains(&t) {
            let at = a.p + (b.p - a.p) * t;
            return Some(((at - p.p).dot(&p.n), a.f + (b.f - a.f) * t));
        }
    }
    None
}

/// Least squares of y against a polynomial of `degree` in F: the coefficients, the residual
/// sum of squares and [(XᵀX)⁻¹]₀₀ (None when the forces cannot carry the degree).
fn poly_fit(fs: &[f64], ys: &[f64], degree: usize) -> Option<(Vec<f64>, f64, f64)> {
    let n = degree + 1;
    let x = nalgebra::DMatrix::from_fn(fs.len(), n, |i, j| fs[i].powi(j as i32));
    let y = nalgebra::DVector::from_column_slice(ys);
    let xtx = x.transpose() * &x;
    let inv = xtx.try_inverse()?;
    let a = &inv * x.transpose() * &y;
    let r = &y - &x * &a;
    let v00 = inv[(0, 0)];
    (v00.is_finite() && v00 > 0.0).then(|| (a.iter().copied().collect(), r.norm_squared(), v00))
}

/// Per-point extrapolation to zero force of `passes` (each in scan order, K ≥ 2, any order of
/// force; their forces taken from `force`, the values in its unit) with `sigma_mm` the noise
/// of one point (the dataset's floor). Errors name the pass.
pub fn per_point(
    passes: &[Vec<PassPoint>],
    sigma_mm: f64,
    force: Force,
) -> Result<PerPoint, String> {
    if passes.len() < 2 {
        return Err(format!(
            "{} pass(es): per-point zero force needs the same path scanned at ≥ 2 forces",
            passes.len()
        ));
    }
    if !(sigma_mm.is_finite() && sigma_mm > 0.0) {
        return Err(format!("point noise {sigma_mm} mm: must be > 0"));
    }
    let mut order: Vec<(f64, usize)> = vec![];
    for (k, p) in passes.iter().enumerate() {
        if p.len() < 3 {
            return Err(format!("pass {}: {} point(s), need ≥ 3", k + 1, p.len()));
        }
        if let Some(i) = p
            .iter()
            .position(|q| !(q.f.is_finite() && q.p.iter().all(|v| v.is_finite())))
        {
            return Err(format!("pass {}: point {} is not finite", k + 1, i + 1));
        }
        order.push((p.iter().map(|q| q.f).sum::<f64>() / p.len() as f64, k));
    }
    order.sort_by(|a, b| a.0.total_cmp(&b.0));
    for w in order.windows(2) {
        if w[1].0 - w[0].0 < ALIKE_FRACTION * w[1].0 {
            return Err(format!(
                "passes {} and {}: forces {:.3} and {:.3} {} are alike (need ≥ {:.0} % apart)",
                w[0].1 + 1,
                w[1].1 + 1,
                w[0].0,
                w[1].0,
                force.unit(),
                ALIKE_FRACTION * 100.0
            ));
        }
    }
    let reference = &passes[order[0].1];
    let others: Vec<(&[PassPoint], Grid, f64)> = order[1..]
        .iter()
        .map(|&(_, k)| {
            let q = &passes[k][..];
            let gap = MAX_GAP * median_spacing(q).max(1e-6);
            (q, Grid::new(q, gap), gap)
        })
        .collect();
    // Every reference point with every other pass at its place.
    let mut rows: Vec<(usize, Vec<f64>, Vec<f64>)> = vec![];
    let mut unpaired = 0;
    for (i, p) in reference.iter().enumerate() {
        let mut fs = vec![p.f];
        let mut ys = vec![0.0];
        for (q, grid, gap) in &others {
            match bracket(q, grid, *gap, p) {
                Some((y, f)) => {
                    fs.push(f);
                    ys.push(y);
                }
                None => break,
            }
        }
        if fs.len() == passes.len() {
            rows.push((i, fs, ys));
        } else {
            unpaired += 1;
        }
    }
    if rows.is_empty() {
        return Err(format!(
            "no point of the lowest-force pass (pass {}) is met by the other passes: are they the same path?",
            order[0].1 + 1
        ));
    }
    // The degree: a line, or a quadratic where the lines leave significantly more than noise.
    let k = passes.len();
    let mut chi2_linear = None;
    let mut degree = 1;
    if k >= 3 {
        let mut ssr = 0.0;
        for (_, fs, ys) in &rows {
            ssr += poly_fit(fs, ys, 1).map(|(_, r, _)| r).unwrap_or(0.0);
        }
        let dof = (rows.len() * (k - 2)) as f64;
        let chi2 = ssr / (dof * sigma_mm * sigma_mm);
        chi2_linear = Some(chi2);
        if chi2 > QUADRATIC_CHI2 && chi2 > 1.0 + 5.0 * (2.0 / dof).sqrt() {
            degree = 2;
        }
    }
    let mut points = Vec::with_capacity(rows.len());
    for (i, fs, ys) in &rows {
        let p = &reference[*i];
        let Some((a, _, v00)) = poly_fit(fs, ys, degree) else {
            unpaired += 1;
            continue;
        };
        let p0 = p.p + p.n * a[0];
        points.push(ZeroPoint {
            p0: [p0.x, p0.y, p0.z],
            normal: [p.n.x, p.n.y, p.n.z],
            error_at_f1_um: -a[0] * 1e3,
            sigma_um: sigma_mm * v00.sqrt() * 1e3,
        });
    }
    let forces: Vec<f64> = order.iter().map(|o| o.0).collect();
    let (forces_mm, forces_n) = match force {
        Force::Deflection => (forces, vec![]),
        Force::Signal => (vec![], forces),
    };
    Ok(PerPoint {
        force,
        forces_mm,
        forces_n,
        degree,
        chi2_linear,
        points,
        unpaired,
    })
}

/// One part's passes (a feature scanned by one tip at one head angle at ≥ 2 forces) at zero
/// force.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PartSet {
    /// The bag's index.
    pub bag: usize,
    /// The feature's artifact name.
    pub artifact: String,
    /// Its id in the bag's program.
    pub feature_id: u32,
    /// Tip.
    pub tip: u32,
    /// The passes' segment ids, lowest force first.
    pub segments: Vec<u32>,
    /// The extrapolation.
    #[serde(flatten)]
    pub result: PerPoint,
}

/// Groups the steady scan points of `ds` by bag, feature, tip and head angles, each scan
/// segment a pass (its points in time order, the force of each: the force signal where every
/// point of the group has one, else the deflection |d|), and extrapolates every group with
/// ≥ 2 passes per point to zero force. Groups of one pass are skipped; none with two is an
/// error naming what to scan. With `force` [`Force::Deflection`] the deflection is taken
/// everywhere.
pub fn part(ds: &Dataset, force: Force) -> Result<Vec<PartSet>, String> {
    type Key = (usize, usize, u32, i64, i64);
    // Per pass: its points with the deflection as force, and with the signal where there is one.
    type Pass = (Vec<PassPoint>, Vec<f64>);
    let mut groups: BTreeMap<Key, BTreeMap<u32, Pass>> = BTreeMap::new();
    for p in &ds.points {
        if p.phase != Phase::Steady || p.normal.norm() < 0.5 {
            continue;
        }
        let key = (
            p.bag,
            p.feature,
            p.ctx.tip_id,
            (p.ctx.head_a1_deg * 1e3).round() as i64,
            (p.ctx.head_a2_deg * 1e3).round() as i64,
        );
        let pass = groups.entry(key).or_default().entry(p.segment).or_default();
        pass.0.push(PassPoint {
            p: p.surface,
            n: p.normal,
            f: p.ctx.deflection_probe.norm(),
        });
        if let Some(f) = p.ctx.force_n.filter(|f| f.is_finite()) {
            pass.1.push(f);
        }
    }
    let sigma = ds.noise_floor_um * 1e-3;
    let mut out = vec![];
    for ((bag, feature, tip, _, _), passes) in groups {
        if passes.len() < 2 {
            continue;
        }
        // The signal when every point of the set carries one.
        let signal = force == Force::Signal && passes.values().all(|(p, f)| f.len() == p.len());
        let (segments, pts): (Vec<u32>, Vec<Vec<PassPoint>>) = passes
            .into_iter()
            .map(|(s, (mut p, f))| {
                if signal {
                    p.iter_mut().zip(f).for_each(|(q, f)| q.f = f);
                }
                (s, p)
            })
            .unzip();
        let used = if signal {
            Force::Signal
        } else {
            Force::Deflection
        };
        let result = per_point(&pts, sigma, used).map_err(|e| {
            format!(
                "bag {} feature {} tip {tip} (segments {segments:?}): {e}",
                bag + 1,
                feature + 1
            )
        })?;
        let mean = |k: usize| pts[k].iter().map(|q| q.f).sum::<f64>() / pts[k].len() as f64;
        let mut by_force: Vec<(f64, u32)> =
            (0..pts.len()).map(|k| (mean(k), segments[k])).collect();
        by_force.sort_by(|a, b| a.0.total_cmp(&b.0));
        let f = &ds.features[feature].1;
        out.push(PartSet {
            bag,
            artifact: f.artifact.clone(),
            feature_id: f.id,
            tip,
            segments: by_force.into_iter().map(|(_, s)| s).collect(),
            result,
        });
    }
    if out.is_empty() {
        return Err(
            "no feature scanned by the same path at ≥ 2 probing forces (the same tip and head angles): scan the part once per force"
                .into(),
        );
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn reading(r: f64, f: f64) -> Reading {
        Reading {
            r,
            r_sigma: 0.1,
            f,
            f_sigma: 0.01,
        }
    }

    #[test]
    fn a_line_through_two_forces_lands_on_its_zero_force_value() {
        // R = 5 − 2·F: at F = 0.1 and 0.5 the readings are 4.8 and 4.0.
        let z = two_force(reading(4.8, 0.1), reading(4.0, 0.5));
        let (r0, s) = z.value().unwrap();
        assert!(matches!(z, ZeroForce::Extrapolated { .. }));
        assert!((r0 - 5.0).abs() < 1e-12, "{r0}");
        // σ: mostly the nearer reading's, amplified by F2/(F2 − F1) = 1.25, plus F1/(F2 − F1).
        let expect = (1.25f64 * 0.1).hypot(0.25 * 0.1);
        assert!(s > expect && s < expect * 1.1, "{s} vs {expect}");
        // The order of the readings does not matter.
        let (r0b, sb) = two_force(reading(4.0, 0.5), reading(4.8, 0.1))
            .value()
            .unwrap();
        assert!((r0b - r0).abs() < 1e-12 && (sb - s).abs() < 1e-12);
    }

    #[test]
    fn a_force_below_significance_is_zero_and_alike_forces_give_nothing() {
        // 0.02 ± 0.01 is not a force: its reading is the zero-force one.
        let z = two_force(reading(4.96, 0.02), reading(4.0, 0.5));
        assert_eq!(
            z,
            ZeroForce::ForceZero {
                r0: 4.96,
                sigma: 0.1
            }
        );
        // 0.30 and 0.32 ± 0.01 differ by 1.4σ: no line.
        assert_eq!(
            two_force(reading(4.4, 0.30), reading(4.36, 0.32)),
            ZeroForce::Alike
        );
        assert_eq!(ZeroForce::Alike.value(), None);
    }
    /// Passes along a line y = 0 (normal +y) at forces `fs`: y_k(x) = e(x, F_k) + noise.
    fn passes(fs: &[f64], e: impl Fn(f64, f64) -> f64, noise: f64) -> Vec<Vec<PassPoint>> {
        let mut seed = 7u64;
        let mut rnd = move || {
            // A small LCG: uniform in (−√3, √3)·noise (σ = noise).
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 2.0 * 3f64.sqrt() * noise
        };
        fs.iter()
            .enumerate()
            .map(|(k, &f)| {
                (0..2000)
                    .map(|i| {
                        // Each pass samples the line at its own places.
                        let x = i as f64 * 0.01 + 0.003 * k as f64;
                        PassPoint {
                            p: Vector3::new(x, e(x, f) + rnd(), 0.0),
                            n: Vector3::y(),
                            f,
                        }
                    })
                    .collect()
            })
            .collect()
    }

    #[test]
    fn each_point_gets_its_own_line_to_zero_force() {
        // A wall that gives 20 µm per mm of force at one end and nothing at the other, plus
        // form: every point's line is its own; the two-pass extrapolation lands on the form.
        let form = |x: f64| 1e-3 * (x * 0.7).sin();
        let e = |x: f64, f: f64| form(x) - 0.02 * (x / 20.0) * f;
        let r = per_point(&passes(&[0.5, 0.1], e, 0.0), 1e-4, Force::Deflection).unwrap();
        assert_eq!(r.degree, 1);
        assert!((r.forces_mm[0] - 0.1).abs() < 1e-9 && (r.forces_mm[1] - 0.5).abs() < 1e-9);
        assert!(r.unpaired <= 1, "{}", r.unpaired);
        for z in &r.points {
            let x = z.p0[0];
            // Within the other pass's linear interpolation between its samples 0.01 mm apart:
            // h²/8·|form''| = 6e-9 mm, a quarter of it carried by the extrapolation.
            assert!((z.p0[1] - form(x)).abs() < 1e-8, "{z:?}");
            assert!(
                (z.error_at_f1_um - (-0.02 * x / 20.0 * 0.1) * 1e3).abs() < 1e-5,
                "{z:?}"
            );
            // σ = σ_point·√(F1² + F2²)/(F2 − F1).
            let s = 0.1 * (0.01f64 + 0.25).sqrt() / 0.4;
            assert!((z.sigma_um - s).abs() < 1e-9, "{}", z.sigma_um);
        }
    }

    #[test]
    fn a_quadratic_in_the_force_is_taken_only_where_the_data_ask_for_it() {
        let form = |x: f64| 1e-3 * (x * 0.3).cos();
        // Linear in the force, with noise: three passes keep the line.
        let lin = |x: f64, f: f64| form(x) - 0.01 * f;
        let r = per_point(
            &passes(&[0.1, 0.3, 0.5], lin, 1e-4),
            1e-4,
            Force::Deflection,
        )
        .unwrap();
        assert_eq!(r.degree, 1, "{:?}", r.chi2_linear);
        assert!(r.chi2_linear.unwrap() < 1.3, "{:?}", r.chi2_linear);
        // Stiffening (−0.03·F + 0.04·F²): the quadratic is taken and lands on the form where
        // the best line through the three forces would miss by microns.
        let quad = |x: f64, f: f64| form(x) - 0.03 * f + 0.04 * f * f;
        let r = per_point(
            &passes(&[0.1, 0.3, 0.5], quad, 1e-4),
            1e-4,
            Force::Deflection,
        )
        .unwrap();
        assert_eq!(r.degree, 2, "{:?}", r.chi2_linear);
        let rms = (r
            .points
            .iter()
            .map(|z| (z.p0[1] - form(z.p0[0])).powi(2))
            .sum::<f64>()
            / r.points.len() as f64)
            .sqrt();
        let sigma = r.points[0].sigma_um * 1e-3;
        assert!(rms < 1.3 * sigma, "{rms} vs σ {sigma}");
    }

    #[test]
    fn per_point_refuses_what_it_cannot_extrapolate() {
        let e = |_: f64, f: f64| -0.01 * f;
        let err = per_point(&passes(&[0.3], e, 0.0), 1e-4, Force::Deflection).unwrap_err();
        assert!(err.contains("≥ 2 forces"), "{err}");
        let err = per_point(&passes(&[0.30, 0.32], e, 0.0), 1e-4, Force::Deflection).unwrap_err();
        assert!(err.contains("alike"), "{err}");
        let mut p = passes(&[0.1, 0.5], e, 0.0);
        p[1][5].p.x = f64::NAN;
        let err = per_point(&p, 1e-4, Force::Deflection).unwrap_err();
        assert!(err.contains("pass 2: point 6"), "{err}");
        // Another path: nothing to pair.
        let mut p = passes(&[0.1, 0.5], e, 0.0);
        p[1].iter_mut().for_each(|q| q.p.z += 50.0);
        let err = per_point(&p, 1e-4, Force::Deflection).unwrap_err();
        assert!(err.contains("same path"), "{err}");
    }
}
