//! `dynamics`: the ring-gauge procedure — the machine's dynamic parameters from one ring
//! gauge set up at several positions, scanned at several speeds in both directions.
//!
//! Equations. The nominal model's time constants are refitted first, from command against
//! scales ([`crate::lab::nominal`]). Each point i of ring placement q then deviates along its
//! normal n_i from the ring by
//!
//! e_i = n_i·[P(p_i)·A_i] + n_i·δφ_i + n_i·δg_i + s_q(θ_i) + ε_i,
//!
//! * P(p) = Σ_m ξ_m(p)·P_m, the compliance with cross-coupling, linear in the position
//!   (ξ = 1, x, y, z over 500 mm), A the estimated acceleration (`accel_deflection`);
//! * δφ the servo phase of Y (and Z) against X on arcs, φ = b0 + b1·f + b2·f², each b linear
//!   in the position, changing sign with the direction (`servo_phase`, order 1);
//! * δg the servo gain, δg_i = (α_i,2·f² [+ α_i,1·f])·(s_i − c_i) (`servo_gain`): its
//!   theoretical form (a lag's amplitude response 1 − (2πfτ)²/2) is the f² term alone; the
//!   polynomial in f adds f¹. The better form is chosen on held-out rings: the ring positions
//!   are split in three folds, each predicted by the parameters fitted on the others, its
//!   static pattern refitted. On a steady circle the f² term and the compliance's diagonal
//!   both follow v²/r, at any diameter; only the tangential acceleration of spin-up and
//!   slow-down (which bends the structure, not the servo's amplitude) separates them, and the
//!   procedure reports their correlation;
//! * s_q(θ) the static pattern of placement q: the ring's form and every static error of the
//!   machine where it stands, the same at every speed and in both directions — a Fourier
//!   series in the ring's angle to harmonic 8 with a constant (the radius), plus a drift of
//!   the radius and the centre linear in time (the room warms while the speeds are run),
//!   fitted as nuisance. Only what changes with speed and direction is left to the dynamic
//!   parameters, so the geometry of the machine (not yet calibrated when this procedure
//!   runs) does not leak into them.
//!
//! Spin-up and slow-down points are used: their acceleration and frequency are what the
//! estimator says they are. Weighted least squares over all points, the covariance scaled by
//! the residual variance and by (1 + ρ)/(1 − ρ) for the residuals' lag-1 correlation ρ.
//!
//! Source idea: the surface-shape measuring device's ring-gauge procedure (rings at several
//! positions × speeds × both directions; the deflection matrix P(x) with cross-coupling, the
//! phase b2·f² + b1·f + φ0, the gain in its theoretical form and as a polynomial in f).

use super::{Param, ProcedureError};
use crate::calib::Calibration;
use crate::effects::{accel_deflection, servo_gain, servo_phase, Effect, EffectConfig};
use crate::lab::analysis::Prepared;
use crate::lab::dataset::Dataset;
use crate::lab::fit::Normal;
use crate::lab::nominal::AxisFit;
use crate::lab::program::FeatureKind;
use crate::sample::Vec3;
use serde::Serialize;
use std::collections::BTreeMap;

/// Harmonics of the static pattern per ring placement.
const HARMONICS: usize = 8;
/// A column whose RMS is below this fraction of its effect's strongest is not fitted.
const WEAK_COLUMN: f64 = 1e-3;
/// Least ring positions along X.
const MIN_X_POSITIONS: usize = 5;
const AX: [&str; 3] = ["x", "y", "z"];

/// One scan of a ring: speed, direction, what it shows.
#[derive(Debug, Clone, Serialize)]
pub struct Scan {
    /// Programmed speed, mm/s.
    pub speed_mm_s: f64,
    /// +1 counter-clockwise, −1 clockwise.
    pub direction: i32,
    /// Centripetal acceleration v²/r at programmed speed, mm/s².
    pub accel_mm_s2: f64,
    /// Mean radius change against the placement's static pattern (and its drift), without the
    /// fitted dynamics, µm.
    pub delta_r_um: f64,
    /// The same after the fit, µm.
    pub delta_r_after_um: f64,
}

/// One ring placement.
#[derive(Debug, Clone, Serialize)]
pub struct Position {
    /// Ring centre, mm.
    pub center_mm: [f64; 3],
    /// Its scans.
    pub scans: Vec<Scan>,
}

/// The two forms of the servo gain, scored on held-out ring positions.
#[derive(Debug, Clone, Serialize)]
pub struct GainChoice {
    /// `theoretical` (an f² term, carried by P_xx, P_yy) or `polynomial` (adds f¹).
    pub chosen: String,
    /// Held-out RMS of the theoretical form, µm.
    pub heldout_theoretical_um: f64,
    /// Held-out RMS of the polynomial form, µm.
    pub heldout_polynomial_um: f64,
}

/// What the procedure found.
#[derive(Debug, Clone, Serialize)]
pub struct Outcome {
    /// The new calibration (nominal model and dynamic effects replaced; not yet versioned).
    #[serde(skip)]
    pub calibration: Calibration,
    /// Every determined parameter with its standard uncertainty, by the simulator's names.
    pub params: Vec<Param>,
    /// What this measurement cannot determine, and what would.
    pub undetermined: Vec<String>,
    /// Parameters this measurement barely tells apart, and what separates them.
    pub confounded: Vec<String>,
    /// The gain's form.
    pub gain: GainChoice,
    /// Per ring position: ΔR against speed and acceleration.
    pub positions: Vec<Position>,
    /// Residual RMS after the static patterns, before and after the fit, µm.
    pub residual_before_um: f64,
    /// After.
    pub residual_after_um: f64,
    /// Remarks for the engineer.
    pub notes: Vec<String>,
}

struct Model {
    configs: Vec<EffectConfig>,
    built: Vec<crate::effects::Model>,
    n: usize,
}

impl Model {
    fn new(gain_powers: Vec<u32>, ds: &Dataset) -> Model {
        let configs = vec![
            EffectConfig::AccelDeflection(accel_deflection::Config::zeros(1, false)),
            EffectConfig::ServoPhase(servo_phase::Config::zeros(1)),
            EffectConfig::ServoGain(servo_gain::Config::zeros(0, gain_powers)),
        ];
        let mut sensors = ds.sensors.clone();
        let built: Vec<crate::effects::Model> = configs
            .iter()
            .map(|c| c.build(&mut sensors).expect("zero configs build").model)
            .collect();
        let n = built.iter().map(|b| b.n_params()).sum();
        Model { configs, built, n }
    }
    fn row(&self, ds: &Dataset, prep: &Prepared, i: usize, out: &mut Vec<f64>) {
        out.clear();
        let g = prep.art.grad[i];
        let mut r = vec![Vec3::zeros(); 40];
        for b in &self.built {
            let k = b.n_params();
            b.regressors(&ds.points[i].ctx, &mut r[..k]);
            out.extend(r[..k].iter().map(|v| {
                let x = g.dot(v);
                if x.is_finite() {
                    x
                } else {
                    0.0
                }
            }));
        }
    }
}

/// Columns per placement: the static pattern (constant and 2·HARMONICS Fourier terms) and
/// its slow drift (radius and centre, linear in time).
const PER_PLACEMENT: usize = 2 * HARMONICS + 4;

/// The static-pattern columns of point i (its placement's Fourier series in the angle, and
/// the drift of its radius and centre in time: the room warms while the speeds are run).
fn static_row(
    ds: &Dataset,
    prep: &Prepared,
    col0: &[usize],
    t_mid: &[f64],
    i: usize,
    out: &mut Vec<(usize, f64)>,
) {
    out.clear();
    let p = &ds.points[i];
    let Some(f) = &prep.art.features[p.feature] else {
        return;
    };
    let d = p.surface - f.center;
    let th = d.y.atan2(d.x);
    let c = col0[p.feature];
    out.push((c, 1.0));
    for k in 1..=HARMONICS {
        let a = k as f64 * th;
        out.push((c + 2 * k - 1, a.cos()));
        out.push((c + 2 * k, a.sin()));
    }
    // Time from the placement's middle, in units of 100 s.
    let tau = (p.ctx.t_ns as f64 * 1e-9 - t_mid[p.feature]) / 100.0;
    let c = c + 2 * HARMONICS + 1;
    out.push((c, tau));
    out.push((c + 1, tau * th.cos()));
    out.push((c + 2, tau * th.sin()));
}

/// Runs the procedure: `ds` built from the bags with the start calibration after the nominal
/// refit `nominal`, its dynamic effects (`accel_deflection`, `servo_phase`, `servo_gain`) taken
/// out; `prep` its artifact fit.
pub fn run(
    ds: &Dataset,
    prep: &Prepared,
    start: &Calibration,
    nominal: &[AxisFit],
) -> Result<Outcome, ProcedureError> {
    // --- the measurement's design ---
    let rings: Vec<usize> = ds
        .features
        .iter()
        .enumerate()
        .filter(|(i, (_, f))| {
            matches!(f.kind, FeatureKind::Bore | FeatureKind::Boss)
                && f.artifact != "sphere"
                && prep.art.features[*i].is_some()
        })
        .map(|(i, _)| i)
        .collect();
    if rings.is_empty() {
        return Err(ProcedureError::Missing(
            "no ring-gauge scans in the bags (a `ring` bore or boss scanned as circles): \
             `dynamics` needs one ring set up at ≥ 5 positions along X, each scanned at ≥ 2 \
             speeds in both directions, e.g. `scancorr sim --program dynamics`"
                .into(),
        ));
    }
    let mut speeds: BTreeMap<usize, Vec<(i64, i32)>> = BTreeMap::new();
    for p in &ds.points {
        if p.direction != 0 && rings.contains(&p.feature) {
            let key = ((p.speed * 10.0).round() as i64, p.direction);
            let v = speeds.entry(p.feature).or_default();
            if !v.contains(&key) {
                v.push(key);
            }
        }
    }
    let mut notes = vec![];
    let usable: Vec<usize> = rings
        .iter()
        .copied()
        .filter(|f| {
            let n = speeds.get(f).map_or(0, |v| {
                let mut s: Vec<i64> = v.iter().map(|k| k.0).collect();
                s.sort_unstable();
                s.dedup();
                s.len()
            });
            if n < 2 {
                notes.push(format!(
                    "ring at {:?} mm scanned at one speed: left out (its static pattern and \
                     its dynamics cannot be told apart)",
                    ds.features[*f].1.nominal_center
                ));
            }
            n >= 2
        })
        .collect();
    if usable.is_empty() {
        return Err(ProcedureError::IllConditioned(
            "every ring position is scanned at one speed: scan each position at ≥ 2 speeds \
             (the dynamics grow with speed, the static errors at a position do not)"
                .into(),
        ));
    }
    if !usable
        .iter()
        .any(|f| speeds[f].iter().any(|k| k.1 > 0) && speeds[f].iter().any(|k| k.1 < 0))
    {
        return Err(ProcedureError::IllConditioned(
            "every ring is scanned in one direction: add the opposite direction (CW and CCW; \
             the servo phase changes sign with it)"
                .into(),
        ));
    }
    let centers: Vec<Vec3> = usable
        .iter()
        .map(|f| prep.art.features[*f].as_ref().unwrap().center)
        .collect();
    let distinct = |axis: usize| {
        let mut v: Vec<i64> = centers
            .iter()
            .map(|c| (c[axis] / 5.0).round() as i64)
            .collect();
        v.sort_unstable();
        v.dedup();
        v.len()
    };
    let nx = distinct(0);
    if nx < MIN_X_POSITIONS {
        return Err(ProcedureError::IllConditioned(format!(
            "rings at {nx} position(s) along X: add rings at ≥ {MIN_X_POSITIONS} positions \
             along X (the deflection matrix and the phase change along the travel)"
        )));
    }
    let mut undetermined = vec![];
    for (axis, name) in [(1, "Y"), (2, "Z")] {
        if distinct(axis) < 3 {
            undetermined.push(format!(
                "the change along {name} of P and of the phase: the rings stand at fewer \
                 than 3 positions along {name} (add them to determine it)"
            ));
        }
    }

    // --- columns: dynamic parameters (dense), static patterns (sparse) ---
    let mut col0 = vec![usize::MAX; ds.features.len()];
    for (j, f) in usable.iter().enumerate() {
        col0[*f] = j * PER_PLACEMENT;
    }
    let n_static = usable.len() * PER_PLACEMENT;
    let mut t_mid = vec![0.0; ds.features.len()];
    {
        let mut span = vec![(f64::MAX, f64::MIN); ds.features.len()];
        for p in &ds.points {
            let t = p.ctx.t_ns as f64 * 1e-9;
            let s = &mut span[p.feature];
            *s = (s.0.min(t), s.1.max(t));
        }
        for (m, s) in t_mid.iter_mut().zip(&span) {
            *m = 0.5 * (s.0 + s.1);
        }
    }
    let fold_of = |f: usize| usable.iter().position(|u| *u == f).map(|j| j % 3);
    let rows: Vec<usize> = (0..ds.points.len())
        .filter(|&i| col0[ds.points[i].feature] != usize::MAX)
        .collect();
    let models = [Model::new(vec![2], ds), Model::new(vec![1, 2], ds)];
    let mut dense = vec![];
    let mut sparse = vec![];
    // Per model: one normal system per fold.
    let mut ne: Vec<[Normal; 3]> = models
        .iter()
        .map(|m| std::array::from_fn(|_| Normal::new(m.n + n_static)))
        .collect();
    for &i in &rows {
        let f = fold_of(ds.points[i].feature).unwrap();
        static_row(ds, prep, &col0, &t_mid, i, &mut sparse);
        let y = prep.art.residual[i];
        for (m, n) in models.iter().zip(ne.iter_mut()) {
            m.row(ds, prep, i, &mut dense);
            n[f].add(&dense, &sparse, y);
        }
    }
    // Columns far weaker than the strongest of their effect (z acceleration of horizontal
    // rings: numerical noise) are not fitted.
    for (m, n) in models.iter().zip(ne.iter_mut()) {
        let diag: Vec<f64> = (0..m.n)
            .map(|c| n.iter().map(|f| f.m[(c, c)]).sum::<f64>())
            .collect();
        let mut off = 0;
        for b in &m.built {
            let k = b.n_params();
            let top = diag[off..off + k].iter().cloned().fold(0.0, f64::max);
            for c in off..off + k {
                if diag[c] <= WEAK_COLUMN * WEAK_COLUMN * top {
                    for f in n.iter_mut() {
                        f.m.row_mut(c).fill(0.0);
                        f.m.column_mut(c).fill(0.0);
                        f.b[c] = 0.0;
                    }
                }
            }
            off += k;
        }
    }
    let sum = |parts: &[&Normal]| {
        let mut t = Normal::new(parts[0].b.len());
        for p in parts {
            t.m += &p.m;
            t.b += &p.b;
            t.yy += p.yy;
            t.n += p.n;
        }
        t
    };
    // Held-out score: each fold predicted from the other two, its static patterns refitted.
    let heldout = |mi: usize| -> f64 {
        let m = &models[mi];
        let (mut dense, mut sparse) = (vec![], vec![]);
        let mut ss = 0.0;
        let mut n = 0;
        for test in 0..3 {
            let train: Vec<&Normal> = (0..3).filter(|f| *f != test).map(|f| &ne[mi][f]).collect();
            let sol = sum(&train).solve();
            let theta: Vec<f64> = sol.x.iter().take(m.n).copied().collect();
            let mut st = Normal::new(n_static);
            for &i in &rows {
                if fold_of(ds.points[i].feature) != Some(test) {
                    continue;
                }
                m.row(ds, prep, i, &mut dense);
                let y = prep.art.residual[i]
                    + dense.iter().zip(&theta).map(|(a, t)| a * t).sum::<f64>();
                static_row(ds, prep, &col0, &t_mid, i, &mut sparse);
                st.add(&[], &sparse, y);
            }
            if st.n > 0 {
                ss += st.solve().ss;
                n += st.n;
            }
        }
        if n == 0 {
            f64::NAN
        } else {
            (ss / n as f64).sqrt() * 1e3
        }
    };
    let (h0, h1) = (heldout(0), heldout(1));
    if !(h0.is_finite() && h1.is_finite()) {
        return Err(ProcedureError::IllConditioned(
            "too few ring positions to hold any out: add rings at ≥ 5 positions along X".into(),
        ));
    }
    let mi = if h1 < h0 { 1 } else { 0 };
    let gain = GainChoice {
        chosen: if mi == 1 { "polynomial" } else { "theoretical" }.into(),
        heldout_theoretical_um: h0,
        heldout_polynomial_um: h1,
    };
    let m = &models[mi];
    let all = sum(&ne[mi].iter().collect::<Vec<_>>());
    let sol = all.solve();
    let mut st0 = Normal::new(n_static);
    for &i in &rows {
        static_row(ds, prep, &col0, &t_mid, i, &mut sparse);
        st0.add(&[], &sparse, prep.art.residual[i]);
    }
    let ss0 = st0.solve().ss;
    let n = all.n as f64;
    let k = (sol.rank).max(1) as f64;
    let inflate = (1.0 + prep.rho) / (1.0 - prep.rho).max(1e-3);
    let sigma2 = sol.ss / (n - k).max(1.0) * inflate;

    // --- parameters by name ---
    let mut params = vec![];
    for a in nominal {
        params.push(Param {
            name: format!("dynamics.tau_{}_s", a.axis),
            value: a.tau_after_s,
            sigma: a.tau_sigma_s.unwrap_or(f64::NAN),
        });
    }
    params.retain(|p| p.sigma.is_finite());
    for a in nominal.iter().filter(|a| a.tau_sigma_s.is_none()) {
        undetermined.push(format!(
            "the uncertainty of τ_{}: its tracking residual has no curvature at the fit (the \
             axis barely moves)",
            a.axis
        ));
    }
    let mut names = vec![];
    for mono in ["1", "x", "y", "z"] {
        for i in AX {
            for j in AX {
                names.push(format!("dynamics.P_{i}{j}.{mono}"));
            }
        }
    }
    for ax in ["y", "z"] {
        for mono in ["1", "x", "y", "z"] {
            for b in 0..3 {
                names.push(format!("dynamics.phase_{ax}.b{b}.{mono}"));
            }
        }
    }
    for ax in AX {
        if mi == 1 {
            names.push(format!("dynamics.gain_{ax}.f1.1"));
        }
        names.push(format!("dynamics.gain_{ax}.f2.1"));
    }
    debug_assert_eq!(names.len(), m.n);
    let mut theta = vec![0.0; m.n];
    let mut not_seen = vec![];
    for (c, name) in names.iter().enumerate() {
        let seen = all.m[(c, c)] > 0.0 && !sol.unidentifiable.contains(&c);
        if !seen {
            not_seen.push(name.trim_start_matches("dynamics.").to_string());
            continue;
        }
        theta[c] = sol.x[c];
        let s = (sol.cov[(c, c)] * sigma2).sqrt();
        // The fit's convention: the correction adds θ·r, and y + Aθ is minimised.
        params.push(Param {
            name: name.clone(),
            value: sol.x[c],
            sigma: if s.is_finite() { s } else { 0.0 },
        });
    }
    if !not_seen.is_empty() {
        undetermined.push(format!(
            "{} (rings in a horizontal plane neither accelerate along Z nor measure along it: \
             a ring in a vertical plane, or a sphere at several latitudes, determines them)",
            not_seen.join(", ")
        ));
    }
    // The compliance's diagonal and the gain's f² term follow v²/r alike on a steady circle;
    // only the tangential acceleration of spin-up and slow-down tells them apart.
    let mut confounded = vec![];
    let col = |n: &str| names.iter().position(|x| x == n);
    for ax in ["x", "y"] {
        let (Some(a), Some(b)) = (
            col(&format!("dynamics.P_{ax}{ax}.1")),
            col(&format!("dynamics.gain_{ax}.f2.1")),
        ) else {
            continue;
        };
        let r = sol.cov[(a, b)] / (sol.cov[(a, a)] * sol.cov[(b, b)]).sqrt();
        if r.abs() > 0.9 {
            // On a steady circle the two act as P − α/(4π²) (mm per mm/s²).
            let w = 1.0 / (4.0 * std::f64::consts::PI * std::f64::consts::PI);
            let v = sol.x[a] - w * sol.x[b];
            let var =
                (sol.cov[(a, a)] + w * w * sol.cov[(b, b)] - 2.0 * w * sol.cov[(a, b)]) * sigma2;
            confounded.push(format!(
                "P_{ax}{ax}.1 and gain_{ax}.f2.1 (correlation {r:+.3}): on a steady circle both \
                 follow v²/r at any diameter, as P − α/(4π²) = {:.3} ± {:.3} µm per m/s²; only \
                 the rings' spin-up and slow-down tell them apart. Scans of a face while the \
                 machine accelerates along its normal, off arcs, separate them.",
                v * 1e6,
                var.max(0.0).sqrt() * 1e6
            ));
        }
    }

    // --- the calibration ---
    let mut cal = start.clone();
    cal.effects
        .retain(|e| !matches!(e.kind(), "accel_deflection" | "servo_phase" | "servo_gain"));
    let mut off = 0;
    for c in &m.configs {
        let k = c.params().len();
        let fitted = c
            .with_params(&theta[off..off + k])
            .map_err(ProcedureError::Missing)?;
        cal.effects.push(fitted);
        off += k;
    }

    // --- ΔR per scan, before and after: the residual with each placement's static pattern and
    // drift from the joint fit taken out, without and with the fitted dynamics ---
    let mut acc: BTreeMap<(usize, i64, i32), (f64, f64, usize)> = BTreeMap::new();
    for &i in &rows {
        let p = &ds.points[i];
        m.row(ds, prep, i, &mut dense);
        static_row(ds, prep, &col0, &t_mid, i, &mut sparse);
        // x minimises ‖y + A θ + S s‖²: y + S s is the dynamics' signature.
        let stat: f64 = sparse.iter().map(|(c, v)| v * sol.x[m.n + *c]).sum();
        let dynamic: f64 = dense.iter().zip(&theta).map(|(a, t)| a * t).sum();
        let e = acc
            .entry((p.feature, (p.speed * 10.0).round() as i64, p.direction))
            .or_insert((0.0, 0.0, 0));
        e.0 += prep.art.residual[i] + stat;
        e.1 += prep.art.residual[i] + stat + dynamic;
        e.2 += 1;
    }
    let positions = usable
        .iter()
        .map(|&f| {
            let fit = prep.art.features[f].as_ref().unwrap();
            Position {
                center_mm: fit.center.into(),
                scans: acc
                    .range((f, i64::MIN, i32::MIN)..=(f, i64::MAX, i32::MAX))
                    .map(|((_, v, d), (a, b, n))| {
                        let v = *v as f64 / 10.0;
                        Scan {
                            speed_mm_s: v,
                            direction: *d,
                            accel_mm_s2: v * v / fit.radius,
                            delta_r_um: a / *n as f64 * 1e3,
                            delta_r_after_um: b / *n as f64 * 1e3,
                        }
                    })
                    .collect(),
            }
        })
        .collect();
    notes.push(format!(
        "{} ring positions ({} along X), {} points; the static pattern of each position \
         (its form and the machine's geometry there) is fitted to harmonic {HARMONICS} and \
         left out",
        usable.len(),
        nx,
        rows.len()
    ));
    Ok(Outcome {
        calibration: cal,
        params,
        undetermined,
        confounded,
        gain,
        positions,
        residual_before_um: (ss0 / n).sqrt() * 1e3,
        residual_after_um: (sol.ss / n).sqrt() * 1e3,
        notes,
    })
}
