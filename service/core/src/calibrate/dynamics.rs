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
//!   (ξ = 1, x, y, z over 500 mm) and quadratic in X: P = P0 + P1·ξx + P2·ξx² (+ the Y and Z
//!   lines), A the estimated acceleration (`accel_deflection`, position order 2, its ξx²
//!   monomial). The data decide P2: its entries are fitted where the rings' X positions leave
//!   ξx² a spread of ≥ 0.05 after a line in ξx (else "not determined", naming the positions
//!   that would), and kept when the residual's χ² (lag-corrected) drops by more than BIC's
//!   q·ln(n_eff) for its q entries; otherwise the linear fit stands and P2's fitted values
//!   ± σ are reported beside (`quadratic`);
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
//! Rings standing on their edge (`scancorr sim --program dynamics-vertical`: the ring's axis
//! along Y or X, the circle in the XZ or YZ plane, the stylus turned along the axis) obey the
//! same equation with n_i, A_i, the lever and the static pattern's angle θ_i taken in the
//! ring's own plane (the lab fits the circle there): their carriage accelerates along Z and
//! their probe measures along Z, so P's Z row and column (P_zx, P_zy, P_zz, P_xz, P_yz) and the
//! servo phase of Z against X (b0, b1, b2 of `phase_z`; on a YZ ring, of Z against Y) act on
//! them — terms a horizontal ring cannot see; with the rings at several places along X, their
//! change along X as well.
//!
//! Face scans accelerated along and across their normal (`scancorr sim --program
//! dynamics-faces`): the probe held on a face while the carriage oscillates, p(t) = p̄_w +
//! u·A·sin(2πft) (u the face's normal, or one of its tangents when sliding), at ≥ 2 frequencies
//! with one amplitude. Each point i of weave placement w (one place on one face) deviates
//! along the face's normal n by
//!
//! e_i = n·[P(p_i)·A_i] + c_w + d_w·τ_i + k_w·(p_i − p̄_w) + u_s·(u·v_i) + ε_i,
//!
//! * n·P·A the same compliance as on the rings — off arcs, so the servo gain (an arc term)
//!   takes no part: a weave along the normal sees P_nn alone, a sliding weave along t sees P_nt
//!   (P_xz, P_zx, P_yz, P_zy, P_zz, which horizontal rings cannot see);
//! * c_w, d_w·τ the place's static offset and its drift in time; k_w·(p − p̄_w) what changes
//!   with the carriage's displacement but not with the frequency — the probe's bending with its
//!   deflection, the face's tilt, the machine's geometry — shared by the place's frequencies,
//!   so only what grows with f² (the acceleration A = −(2πf)²·(p − p̄_w)) is left to P;
//! * u_s·(u·v) per scan s: what follows the velocity along the oscillation (the scales'
//!   readout delay; the structure's small lag behind the acceleration at f well below its
//!   modes, a few per cent of P·A in quadrature), orthogonal to A over whole periods, fitted
//!   as nuisance.
//!
//! With the weaves, P_xx and P_yy come from the faces and the gain's f² term from what the arcs
//! show beyond them: the two are no longer one column. A term of P in the position (ξ_m,
//! m = x, y, z) is fitted only where the points that carry it spread over ≥ 25 mm along m
//! (ξ's weighted standard deviation ≥ 0.05); otherwise it is named as not determined.
//!
//! The stylus's bending with its deflection (`probe_force`) must be corrected by the start:
//! at speed the deflection takes up the servo's tracking error, which differs per axis (Y lags
//! X by τ_y − τ_x: on an arc a tilted ellipse of the carriage's path, turning with the
//! direction), and an uncorrected stylus under-reports it by its k — a term ∝ f of the same
//! form on a ring as the readouts' delays, about 2π·k̄·(τ_y − τ_x) in b1 of Y, k̄ the mean of
//! the stylus's k along X and Y (its cos 2θ part goes into sin 4θ, not the phase). Fitted beside
//! the phase it is one column with b1 (tried: b1 went from −3.1·10⁻⁴ to +1.6·10⁻⁴ rad/Hz on
//! machine 233, truth −6.3·10⁻⁴); so it is named in `confounded`, with its size per unit k
//! from the refitted time constants, when the start has no `probe_force`.
//!
//! ΔR per scan, as the patent reports it: the deviation after the position's static pattern,
//! e(θ) ≈ a0 + a2·cos 2θ + b2·sin 2θ (θ in the ring's plane from its first axis), gives ΔR along
//! X = a0 + a2 and along Y = a0 − a2, the ellipse's largest and smallest radius change
//! a0 ± √(a2² + b2²) and the direction of the largest; each with its σ (the scan's residual
//! variance after the fit, lag-corrected, through the estimator's weights, widened for the
//! static pattern it is taken against). ΔR/a per position is the σ-weighted line through the
//! origin of ΔR against v²/r over its scans, its σ widened by the scatter (Birge ratio ≥ 1).
//! The static phase φ0 (the phase's f⁰ term, b0 of the constant monomial) is stored in the
//! calibration's `servo_phase` and under the patent's name among its metrics.
//!
//! Spin-up and slow-down points are used: their acceleration and frequency are what the
//! estimator says they are. Weighted least squares over all points, the covariance scaled by
//! the residual variance and by (1 + ρ)/(1 − ρ) for the residuals' lag-1 correlation ρ.
//!
//! Source idea: the surface-shape measuring device's ring-gauge procedure (rings at several
//! positions × speeds × both directions; the deflection matrix P(x) with cross-coupling, the
//! phase b2·f² + b1·f + φ0, the gain in its theoretical form and as a polynomial in f).

mod delta_r;
mod quadratic;

use super::{Param, ProcedureError};
use crate::calib::Calibration;
use crate::effects::{accel_deflection, servo_gain, servo_phase, Effect, EffectConfig};
use crate::lab::analysis::Prepared;
use crate::lab::dataset::Dataset;
use crate::lab::fit::{FeatureFit, Normal};
use crate::lab::nominal::AxisFit;
use crate::lab::program::FeatureKind;
use crate::sample::Vec3;
use delta_r::{through_origin, ScanSums};
use quadratic::quadratic_test;
pub use quadratic::Quadratic;
use serde::Serialize;
use std::collections::BTreeMap;

/// Harmonics of the static pattern per ring placement.
const HARMONICS: usize = 8;
/// A column whose RMS is below this fraction of its effect's strongest is not fitted.
const WEAK_COLUMN: f64 = 1e-3;
/// Least ring positions along X.
const MIN_X_POSITIONS: usize = 5;
/// A stylus's bending per mm of deflection, typical (a 50 mm steel stylus), for the size of
/// what the uncorrected bending puts into the phase.
const BENDING_TYPICAL: f64 = 0.012;
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
    /// ΔR along X (at θ = 0 and π: the constant and cos 2θ terms of the deviation), without
    /// the fitted dynamics, µm. For a ring standing on its edge: along the plane's first
    /// axis (X in the XZ plane, Y in the YZ plane).
    pub delta_r_x_um: f64,
    /// ΔR along Y (θ = ±π/2), µm; for a ring standing on its edge, along Z.
    pub delta_r_y_um: f64,
    /// σ of ΔR along X, µm: the scan's residual after the fit (lag-corrected) through the
    /// estimator a0 + a2, with the share of the position's static pattern it is taken against.
    pub delta_r_x_sigma_um: f64,
    /// σ of ΔR along Y, µm.
    pub delta_r_y_sigma_um: f64,
    /// The largest radius change over the ring (the ellipse's long axis, a0 + √(a2² + b2²)), µm.
    pub delta_r_max_um: f64,
    /// The smallest (its short axis), µm.
    pub delta_r_min_um: f64,
    /// σ of the largest and the smallest, µm.
    pub delta_r_max_sigma_um: f64,
    /// The long axis's direction from the plane's first axis (X on an upright ring), deg.
    pub delta_r_max_at_deg: f64,
}

/// One ring placement.
#[derive(Debug, Clone, Serialize)]
pub struct Position {
    /// Ring centre, mm.
    pub center_mm: [f64; 3],
    /// The ring's plane: `xy` (upright), `xz` or `yz` (standing on its edge).
    pub plane: String,
    /// Its scans.
    pub scans: Vec<Scan>,
    /// ΔR along X per acceleration v²/r over its scans (a line through the origin), µm per
    /// m/s².
    pub dr_x_per_accel_um_per_m_s2: f64,
    /// σ of ΔR/a along X, µm per m/s².
    pub dr_x_per_accel_sigma_um_per_m_s2: f64,
    /// The same along Y, µm per m/s².
    pub dr_y_per_accel_um_per_m_s2: f64,
    /// σ of ΔR/a along Y, µm per m/s².
    pub dr_y_per_accel_sigma_um_per_m_s2: f64,
}

/// One face scan accelerated in place (a weave).
#[derive(Debug, Clone, Serialize)]
pub struct FaceScan {
    /// Mean carriage position, mm.
    pub center_mm: [f64; 3],
    /// The axis the face's normal lies along (what is measured).
    pub measured_along: String,
    /// The axis the carriage oscillates along.
    pub moved_along: String,
    /// Peak speed, mm/s.
    pub speed_mm_s: f64,
    /// Peak acceleration, mm/s².
    pub peak_accel_mm_s2: f64,
    /// RMS of the deviation along the normal after the place's static terms, without the fitted
    /// dynamics, µm.
    pub dynamic_rms_um: f64,
    /// The same with them, µm.
    pub dynamic_rms_after_um: f64,
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
    /// Face scans accelerated in place, before and after the fit.
    pub faces: Vec<FaceScan>,
    /// P's term quadratic in X: the data's decision.
    pub quadratic: Quadratic,
    /// The static phase φ0 of Y and Z against X (the phase's f⁰ term, `servo_phase` b0 of the
    /// constant monomial), rad ± σ, where determined: stored in the calibration's servo_phase
    /// and, by this name, among its metrics (`dynamics_phi0_y_rad`).
    #[serde(skip)]
    pub phase0: Vec<Param>,
    /// Residual RMS after the static patterns, before and after the fit, µm.
    pub residual_before_um: f64,
    /// After.
    pub residual_after_um: f64,
    /// Remarks for the engineer.
    pub notes: Vec<String>,
}

/// Monomials of P the procedure fits: 1, ξx, ξy, ξz and ξx² — the position basis's first five
/// (order 2; its other quadratic monomials are not fitted).
const P_MONOMIALS: usize = 5;
/// P's columns: nine per monomial.
const P_COLS: usize = 9 * P_MONOMIALS;
/// P2's columns (the ξx² monomial).
const P2_COLS: std::ops::Range<usize> = 36..45;
/// The phase's columns: Y then Z, 4 monomials × (b0, b1, b2) each.
const PHASE_COLS: std::ops::Range<usize> = P_COLS..P_COLS + 24;

struct Model {
    configs: Vec<EffectConfig>,
    built: Vec<crate::effects::Model>,
    /// Per effect, which of its parameters are columns (P: its first five monomials).
    keep: Vec<Vec<usize>>,
    n: usize,
}

impl Model {
    fn new(gain_powers: Vec<u32>, ds: &Dataset) -> Model {
        let configs = vec![
            EffectConfig::AccelDeflection(accel_deflection::Config::zeros(2, false)),
            EffectConfig::ServoPhase(servo_phase::Config::zeros(1)),
            EffectConfig::ServoGain(servo_gain::Config::zeros(0, gain_powers)),
        ];
        let mut sensors = ds.sensors.clone();
        let built: Vec<crate::effects::Model> = configs
            .iter()
            .map(|c| c.build(&mut sensors).expect("zero configs build").model)
            .collect();
        let keep: Vec<Vec<usize>> = built
            .iter()
            .enumerate()
            .map(|(e, b)| (0..if e == 0 { P_COLS } else { b.n_params() }).collect())
            .collect();
        let n = keep.iter().map(|k| k.len()).sum();
        Model {
            configs,
            built,
            keep,
            n,
        }
    }
    fn row(&self, ds: &Dataset, prep: &Prepared, i: usize, out: &mut Vec<f64>) {
        out.clear();
        let g = prep.art.grad[i];
        let mut r = vec![Vec3::zeros(); 100];
        for (b, keep) in self.built.iter().zip(&self.keep) {
            let k = b.n_params();
            b.regressors(&ds.points[i].ctx, &mut r[..k]);
            out.extend(keep.iter().map(|c| {
                let x = g.dot(&r[*c]);
                if x.is_finite() {
                    x
                } else {
                    0.0
                }
            }));
        }
    }
    /// The fitted effects from the columns' values `theta`: P of position order 2 when its ξx²
    /// term is kept, else order 1 (as before the quadratic term).
    fn effects(&self, theta: &[f64], quadratic: bool) -> Result<Vec<EffectConfig>, ProcedureError> {
        let mut out = vec![];
        let mut off = 0;
        for (e, (c, keep)) in self.configs.iter().zip(&self.keep).enumerate() {
            let cols = &theta[off..off + keep.len()];
            off += keep.len();
            let (c, full) = if e == 0 && !quadratic {
                let c = EffectConfig::AccelDeflection(accel_deflection::Config::zeros(1, false));
                let full = cols[..36].to_vec();
                (c, full)
            } else {
                let mut full = vec![0.0; c.params().len()];
                for (t, k) in cols.iter().zip(keep) {
                    full[*k] = *t;
                }
                (c.clone(), full)
            };
            out.push(c.with_params(&full).map_err(ProcedureError::Missing)?);
        }
        Ok(out)
    }
}

/// Columns per placement: the static pattern (constant and 2·HARMONICS Fourier terms) and
/// its slow drift (radius and centre, linear in time).
const PER_PLACEMENT: usize = 2 * HARMONICS + 4;

/// Static columns of a weave placement: constant, drift in time, the carriage's displacement
/// from the placement's mean along x, y and z.
const PER_WEAVE: usize = 5;
/// A scan of a face is a weave when its carriage stays within this span, mm …
const WEAVE_SPAN_MM: f64 = 3.0;
/// … and accelerates beyond this, mm/s².
const WEAVE_MIN_ACC: f64 = 20.0;
/// Weaves of one face within this distance share a placement, mm.
const WEAVE_PLACE_MM: f64 = 5.0;
/// A position term of P or of the phase is fitted only where ξ's weighted standard deviation
/// over the points that carry it reaches this (25 mm).
const MIN_SPREAD: f64 = 0.05;

/// One static placement: a ring position, or one place on a face where weaves were run.
struct Place {
    /// The ring's feature (None: a weave place).
    ring: Option<usize>,
    /// First static column.
    col0: usize,
    /// Middle of its time span, s.
    t_mid: f64,
    /// Mean carriage position of its weaves, mm.
    mean: Vec3,
    /// Held-out fold (0–2 rings; 3: weaves, always fitted).
    fold: usize,
}

/// The static design: placements, each point's placement, and a weave point's velocity column
/// and the axis its carriage oscillates along.
struct Statics {
    places: Vec<Place>,
    place_of: Vec<usize>,
    vcol: Vec<usize>,
    moved: Vec<usize>,
}

/// A scan of a face while the carriage oscillates in place.
struct Weave {
    bag: usize,
    feature: usize,
    points: Vec<usize>,
    mean: Vec3,
    /// Programmed (peak) speed, mm/s.
    speed: f64,
    /// Largest |acceleration| per axis, mm/s².
    peak: Vec3,
}

/// The face scans of `ds` whose carriage oscillates in place (weaves).
fn find_weaves(ds: &Dataset, prep: &Prepared) -> Vec<Weave> {
    let mut by: BTreeMap<(usize, u32), Vec<usize>> = BTreeMap::new();
    for (i, p) in ds.points.iter().enumerate() {
        if ds.features[p.feature].1.kind == FeatureKind::Face
            && prep.art.features[p.feature].is_some()
        {
            by.entry((p.bag, p.segment)).or_default().push(i);
        }
    }
    let mut out = vec![];
    for ((bag, _), points) in by {
        let (mut lo, mut hi) = (Vec3::repeat(f64::MAX), Vec3::repeat(f64::MIN));
        let (mut sum, mut peak) = (Vec3::zeros(), Vec3::zeros());
        for &i in &points {
            let c = &ds.points[i].ctx;
            lo = lo.inf(&c.scale);
            hi = hi.sup(&c.scale);
            sum += c.scale;
            peak = peak.sup(&c.est_acc.abs());
        }
        if points.len() < 20 || (hi - lo).max() > WEAVE_SPAN_MM || peak.max() < WEAVE_MIN_ACC {
            continue;
        }
        let p0 = &ds.points[points[0]];
        out.push(Weave {
            bag,
            feature: p0.feature,
            mean: sum / points.len() as f64,
            speed: p0.speed,
            peak,
            points,
        });
    }
    out
}

/// The static columns of point i: for a ring, its placement's Fourier series in the angle and
/// the drift of its radius and centre in time (the room warms while the speeds are run); for a
/// weave, its place's offset, drift and displacement terms and its scan's velocity term.
fn static_row(ds: &Dataset, prep: &Prepared, st: &Statics, i: usize, out: &mut Vec<(usize, f64)>) {
    out.clear();
    let p = &ds.points[i];
    let pl = &st.places[st.place_of[i]];
    let c = pl.col0;
    // Time from the placement's middle, in units of 100 s.
    let tau = (p.ctx.t_ns as f64 * 1e-9 - pl.t_mid) / 100.0;
    if pl.ring.is_none() {
        let d = p.ctx.scale - pl.mean;
        out.extend([
            (c, 1.0),
            (c + 1, tau),
            (c + 2, d.x),
            (c + 3, d.y),
            (c + 4, d.z),
        ]);
        out.push((st.vcol[i], p.ctx.est_vel[st.moved[i]] / 10.0));
        return;
    }
    let Some(f) = &prep.art.features[p.feature] else {
        return;
    };
    let th = ring_angle(f, &(p.surface - f.center));
    out.push((c, 1.0));
    for k in 1..=HARMONICS {
        let a = k as f64 * th;
        out.push((c + 2 * k - 1, a.cos()));
        out.push((c + 2 * k, a.sin()));
    }
    let c = c + 2 * HARMONICS + 1;
    out.push((c, tau));
    out.push((c + 1, tau * th.cos()));
    out.push((c + 2, tau * th.sin()));
}

/// The angle of `d` (from a ring's centre) in the ring's plane: about Z from X for an upright
/// ring; from e1 towards e2 of [`crate::lab::program::circle_plane`] for one standing on its edge (e1 along X for
/// a ring in the XZ plane, −Y in the YZ plane; e2 along Z).
fn ring_angle(f: &FeatureFit, d: &Vec3) -> f64 {
    if f.axes.0 == Vec3::zeros() {
        return d.y.atan2(d.x);
    }
    let (n, e1) = f.axes;
    d.dot(&e1.cross(&n)).atan2(d.dot(&e1))
}

/// The plane of a ring: `xy`, `xz`, `yz` (or `tilted`).
fn ring_plane(f: &FeatureFit) -> &'static str {
    let n = f.axes.0.abs();
    if f.axes.0 == Vec3::zeros() || n.z > 0.999 {
        "xy"
    } else if n.y > 0.999 {
        "xz"
    } else if n.x > 0.999 {
        "yz"
    } else {
        "tilted"
    }
}

/// What a position term's column `c` must be told apart from: the constant column (P: 9 per
/// monomial; the phase of Y and Z after it: 3 per monomial), and for P's ξx² term also its ξx
/// term. Empty for a constant or the gain.
fn partners(c: usize) -> Vec<usize> {
    if P2_COLS.contains(&c) {
        vec![c % 9, c % 9 + 9]
    } else if c < P_COLS {
        if c >= 9 {
            vec![c % 9]
        } else {
            vec![]
        }
    } else if PHASE_COLS.contains(&c) {
        let k = c - P_COLS;
        if k % 12 >= 3 {
            vec![P_COLS + (k / 12) * 12 + k % 3]
        } else {
            vec![]
        }
    } else {
        vec![]
    }
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
    let weaves = find_weaves(ds, prep);
    let mut places: Vec<Place> = usable
        .iter()
        .enumerate()
        .map(|(j, f)| Place {
            ring: Some(*f),
            col0: j * PER_PLACEMENT,
            t_mid: 0.0,
            mean: Vec3::zeros(),
            fold: j % 3,
        })
        .collect();
    let mut place_of = vec![usize::MAX; ds.points.len()];
    for (i, p) in ds.points.iter().enumerate() {
        if let Some(j) = usable.iter().position(|u| *u == p.feature) {
            place_of[i] = j;
        }
    }
    let mut n_static = usable.len() * PER_PLACEMENT;
    // Weaves of one face in one bag within WEAVE_PLACE_MM share a place: (bag, feature, place).
    let mut keys: Vec<(usize, usize, usize)> = vec![];
    let mut weave_place = vec![];
    for w in &weaves {
        let found = keys.iter().find(|(b, f, q)| {
            *b == w.bag && *f == w.feature && (places[*q].mean - w.mean).norm() < WEAVE_PLACE_MM
        });
        let j = match found {
            Some(k) => k.2,
            None => {
                places.push(Place {
                    ring: None,
                    col0: n_static,
                    t_mid: 0.0,
                    mean: w.mean,
                    fold: 3,
                });
                n_static += PER_WEAVE;
                keys.push((w.bag, w.feature, places.len() - 1));
                places.len() - 1
            }
        };
        weave_place.push(j);
    }
    let mut vcol = vec![usize::MAX; ds.points.len()];
    let mut moved = vec![0; ds.points.len()];
    for (w, j) in weaves.iter().zip(&weave_place) {
        for &i in &w.points {
            place_of[i] = *j;
            vcol[i] = n_static;
            moved[i] = w.peak.iamax();
        }
        n_static += 1;
    }
    {
        let mut span = vec![(f64::MAX, f64::MIN); places.len()];
        for (p, j) in ds.points.iter().zip(&place_of) {
            if *j != usize::MAX {
                let t = p.ctx.t_ns as f64 * 1e-9;
                let s = &mut span[*j];
                *s = (s.0.min(t), s.1.max(t));
            }
        }
        for (q, s) in places.iter_mut().zip(&span) {
            q.t_mid = 0.5 * (s.0 + s.1);
        }
    }
    let st = Statics {
        places,
        place_of,
        vcol,
        moved,
    };
    let fold_of = |i: usize| st.places[st.place_of[i]].fold;
    let rows: Vec<usize> = (0..ds.points.len())
        .filter(|&i| st.place_of[i] != usize::MAX)
        .collect();
    let models = [Model::new(vec![2], ds), Model::new(vec![1, 2], ds)];
    let mut dense = vec![];
    let mut sparse = vec![];
    // Per model: one normal system per fold of ring positions, and one of the weaves (in
    // every fit, never held out).
    let mut ne: Vec<[Normal; 4]> = models
        .iter()
        .map(|m| std::array::from_fn(|_| Normal::new(m.n + n_static)))
        .collect();
    for &i in &rows {
        let f = fold_of(i);
        static_row(ds, prep, &st, i, &mut sparse);
        let y = prep.art.residual[i];
        for (m, n) in models.iter().zip(ne.iter_mut()) {
            m.row(ds, prep, i, &mut dense);
            n[f].add(&dense, &sparse, y);
        }
    }
    // Columns far weaker than the strongest of their effect (z acceleration of horizontal
    // rings: numerical noise) are not fitted, nor a position term whose points stand at one
    // place along its axis.
    let mut narrow = vec![];
    for (mi, (m, n)) in models.iter().zip(ne.iter_mut()).enumerate() {
        let total =
            |n: &[Normal; 4], a: usize, b: usize| n.iter().map(|f| f.m[(a, b)]).sum::<f64>();
        let diag: Vec<f64> = (0..m.n).map(|c| total(n, c, c)).collect();
        let mut drop = vec![];
        let mut off = 0;
        for keep in &m.keep {
            let k = keep.len();
            let top = diag[off..off + k].iter().cloned().fold(0.0, f64::max);
            for c in off..off + k {
                if diag[c] <= WEAK_COLUMN * WEAK_COLUMN * top {
                    drop.push(c);
                }
            }
            off += k;
        }
        for c in 0..m.n {
            let ps = partners(c);
            if ps.is_empty()
                || diag[c] <= 0.0
                || drop.contains(&c)
                || ps.iter().any(|p| drop.contains(p) || diag[*p] <= 0.0)
            {
                continue;
            }
            // ξ's weighted variance left after the partners (the constant; for ξx² also ξx):
            // the Schur complement of the column against them, per the constant's weight.
            let c0 = ps[0];
            let var = if ps.len() == 1 {
                let cross = total(n, c, c0);
                (diag[c] - cross * cross / diag[c0]) / diag[c0]
            } else {
                let c1 = ps[1];
                let (a, b, d) = (diag[c0], total(n, c1, c0), diag[c1]);
                let det = a * d - b * b;
                let (u, v) = (total(n, c, c0), total(n, c, c1));
                if det <= 0.0 {
                    0.0
                } else {
                    (diag[c] - (d * u * u - 2.0 * b * u * v + a * v * v) / det) / diag[c0]
                }
            };
            if var < MIN_SPREAD * MIN_SPREAD {
                drop.push(c);
                if mi == 0 {
                    narrow.push(c);
                }
            }
        }
        for c in drop {
            for f in n.iter_mut() {
                f.m.row_mut(c).fill(0.0);
                f.m.column_mut(c).fill(0.0);
                f.b[c] = 0.0;
            }
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
    // Held-out score: each fold of ring positions predicted from the others and the weaves,
    // its static patterns refitted.
    let heldout = |mi: usize| -> f64 {
        let m = &models[mi];
        let (mut dense, mut sparse) = (vec![], vec![]);
        let mut ss = 0.0;
        let mut n = 0;
        for test in 0..3 {
            let train: Vec<&Normal> = (0..4).filter(|f| *f != test).map(|f| &ne[mi][f]).collect();
            // The gain's form is chosen on the linear P (as before its ξx² term; BIC decides
            // that term afterwards on the chosen form).
            let mut t = sum(&train);
            for c in P2_COLS {
                t.m.row_mut(c).fill(0.0);
                t.m.column_mut(c).fill(0.0);
                t.b[c] = 0.0;
            }
            let sol = t.solve();
            let theta: Vec<f64> = sol.x.iter().take(m.n).copied().collect();
            let mut stn = Normal::new(n_static);
            for &i in &rows {
                if fold_of(i) != test {
                    continue;
                }
                m.row(ds, prep, i, &mut dense);
                let y = prep.art.residual[i]
                    + dense.iter().zip(&theta).map(|(a, t)| a * t).sum::<f64>();
                static_row(ds, prep, &st, i, &mut sparse);
                stn.add(&[], &sparse, y);
            }
            if stn.n > 0 {
                ss += stn.solve().ss;
                n += stn.n;
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
        static_row(ds, prep, &st, i, &mut sparse);
        st0.add(&[], &sparse, prep.art.residual[i]);
    }
    let ss0 = st0.solve().ss;
    let n = all.n as f64;
    let inflate = (1.0 + prep.rho) / (1.0 - prep.rho).max(1e-3);
    // P's term quadratic in X: the data decide (BIC on the lag-corrected χ²); without it the
    // fit is the linear one, as before.
    let (sol, quadratic) = quadratic_test(&all, sol, inflate, &narrow);
    let k = (sol.rank).max(1) as f64;
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
    for mono in ["1", "x", "y", "z", "x2"] {
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
    let mut one_place = vec![];
    for (c, name) in names.iter().enumerate() {
        if P2_COLS.contains(&c) && quadratic.decision != "selected" {
            // Reported in `quadratic` (its own fit, its test, or why it is not determined).
            continue;
        }
        let seen = all.m[(c, c)] > 0.0 && !sol.unidentifiable.contains(&c);
        if !seen {
            let short = name.trim_start_matches("dynamics.").to_string();
            if narrow.contains(&c) {
                one_place.push(short);
            } else {
                not_seen.push(short);
            }
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
             rings in a vertical plane (a ring standing on its edge, in the XZ and YZ planes) \
             determine them, `scancorr sim --program dynamics-vertical`; P's Z row and column also come from faces \
             scanned while the carriage oscillates along and across their normals, `scancorr \
             sim --program dynamics-faces`)",
            not_seen.join(", ")
        ));
    }
    if !one_place.is_empty() {
        undetermined.push(format!(
            "{} (the change along the position of entries seen only at one place: the points \
             that carry them spread over less than {:.0} mm along that axis — repeat those \
             scans at other places to determine it)",
            one_place.join(", "),
            MIN_SPREAD * 500.0
        ));
    }
    // The compliance's diagonal and the gain's f² term follow v²/r alike on a steady circle;
    // only the tangential acceleration of spin-up and slow-down tells them apart.
    let mut confounded = vec![];
    let col = |n: &str| names.iter().position(|x| x == n);
    for ax in AX {
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
                 machine accelerates along its normal, off arcs, separate them (`scancorr sim \
                 --program dynamics-faces`).",
                v * 1e6,
                var.max(0.0).sqrt() * 1e6
            ));
        }
    }

    // Without the stylus's bending corrected, the deflection takes up the servo's tracking
    // error (Y lags X by τ_y − τ_x: on an arc a tilted ellipse of the carriage's path that
    // turns with the direction) and the stylus under-reports it by its k: a term ∝ f with the
    // phase's signature, the same form as the readouts' delays on a ring (see the module doc).
    let bending_corrected = start
        .effects
        .iter()
        .any(|e| matches!(e, EffectConfig::ProbeForce(_)));
    let tau = |a: &str| nominal.iter().find(|f| f.axis == a).map(|f| f.tau_after_s);
    for ax in ["y", "z"] {
        let (Some(c), Some(ta), Some(tx)) =
            (col(&format!("dynamics.phase_{ax}.b1.1")), tau(ax), tau("x"))
        else {
            continue;
        };
        if bending_corrected || theta[c] == 0.0 {
            continue;
        }
        let per_k = std::f64::consts::TAU * (ta - tx);
        confounded.push(format!(
            "phase_{ax}.b1.1 and the stylus's bending (the start corrects no bending): at speed \
             the deflection takes up the servo's tracking error — {ax} lags X by τ_{ax} − τ_x = \
             {:.2} ms, a tilted ellipse of the carriage's path that turns with the direction — \
             and a stylus bending by k per mm of deflection under-reports it: about \
             {per_k:+.2e}·k̄ rad/Hz in b1, k̄ the mean of its k in the ring's plane \
             ({:+.1e} rad/Hz at k̄ = {BENDING_TYPICAL}), beside the readouts' delays, on a \
             ring the same form. Run `calibrate probe-force` first: with \
             the bending corrected b1 is the readouts' (the simulator's machine 233: \
             −3.1·10⁻⁴ rad/Hz without, −6.36·10⁻⁴ with no bending against −6.32·10⁻⁴).",
            (ta - tx) * 1e3,
            per_k * BENDING_TYPICAL
        ));
    }

    // --- the calibration ---
    let mut cal = start.clone();
    cal.effects
        .retain(|e| !matches!(e.kind(), "accel_deflection" | "servo_phase" | "servo_gain"));
    cal.effects
        .extend(m.effects(&theta, quadratic.decision == "selected")?);
    let mut quadratic = quadratic;
    quadratic.params = quadratic
        .cols
        .iter()
        .map(|(c, v, s)| Param {
            name: names[*c].clone(),
            value: *v,
            sigma: *s,
        })
        .collect();
    if quadratic.decision != "selected" {
        notes.push(quadratic.say());
    }
    // The static phase φ0 (the phase's f⁰ term, `servo_phase` b0 of the constant monomial):
    // stored in the calibration's servo_phase (y[0][0], z[0][0]) and, by the patent's name,
    // among its metrics.
    let mut phase0 = vec![];
    for ax in ["y", "z"] {
        let name = format!("dynamics.phase_{ax}.b0.1");
        if let Some(p) = params.iter().find(|p| p.name == name) {
            phase0.push(Param {
                name: format!("dynamics.phi0_{ax}"),
                value: p.value,
                sigma: p.sigma,
            });
        }
    }

    // --- ΔR per scan, before and after: the residual with each placement's static pattern and
    // drift from the joint fit taken out, without and with the fitted dynamics ---
    // Per scan: Σe before, Σe after, count, Σe·cos 2θ and Σe·sin 2θ before (the X/Y split of ΔR
    // and the ellipse's axes), Σe² after, Σcos 2θ, Σcos² 2θ (their σ).
    let mut acc: BTreeMap<(usize, i64, i32), ScanSums> = BTreeMap::new();
    let mut per_place = vec![0usize; usable.len()];
    let mut weave_of = vec![usize::MAX; ds.points.len()];
    for (k, w) in weaves.iter().enumerate() {
        for &i in &w.points {
            weave_of[i] = k;
        }
    }
    let mut wacc = vec![(0.0, 0.0, 0usize); weaves.len()];
    for &i in &rows {
        let p = &ds.points[i];
        m.row(ds, prep, i, &mut dense);
        static_row(ds, prep, &st, i, &mut sparse);
        // x minimises ‖y + A θ + S s‖²: y + S s is the dynamics' signature.
        let stat: f64 = sparse.iter().map(|(c, v)| v * sol.x[m.n + *c]).sum();
        let dynamic: f64 = dense.iter().zip(&theta).map(|(a, t)| a * t).sum();
        if weave_of[i] != usize::MAX {
            let e = &mut wacc[weave_of[i]];
            e.0 += (prep.art.residual[i] + stat).powi(2);
            e.1 += (prep.art.residual[i] + stat + dynamic).powi(2);
            e.2 += 1;
            continue;
        }
        let th = prep.art.features[p.feature]
            .as_ref()
            .map_or(0.0, |f| ring_angle(f, &(p.surface - f.center)));
        let e = acc
            .entry((p.feature, (p.speed * 10.0).round() as i64, p.direction))
            .or_default();
        let (before, after) = (
            prep.art.residual[i] + stat,
            prep.art.residual[i] + stat + dynamic,
        );
        let (c2, s2) = ((2.0 * th).cos(), (2.0 * th).sin());
        e.before += before;
        e.after += after;
        e.n += 1;
        e.cos2 += before * c2;
        e.sin2 += before * s2;
        e.after2 += after * after;
        e.c += c2;
        e.cc += c2 * c2;
        if let Some(j) = usable.iter().position(|u| *u == p.feature) {
            per_place[j] += 1;
        }
    }
    let positions: Vec<Position> = usable
        .iter()
        .enumerate()
        .map(|(j, &f)| {
            let fit = prep.art.features[f].as_ref().unwrap();
            let scans: Vec<Scan> = acc
                .range((f, i64::MIN, i32::MIN)..=(f, i64::MAX, i32::MAX))
                .map(|((_, v, d), e)| {
                    e.scan(*v as f64 / 10.0, *d, fit.radius, inflate, per_place[j])
                })
                .collect();
            let (dr_x, dr_x_sigma) =
                through_origin(&scans, |s| (s.delta_r_x_um, s.delta_r_x_sigma_um));
            let (dr_y, dr_y_sigma) =
                through_origin(&scans, |s| (s.delta_r_y_um, s.delta_r_y_sigma_um));
            Position {
                center_mm: fit.center.into(),
                plane: ring_plane(fit).into(),
                dr_x_per_accel_um_per_m_s2: dr_x,
                dr_x_per_accel_sigma_um_per_m_s2: dr_x_sigma,
                dr_y_per_accel_um_per_m_s2: dr_y,
                dr_y_per_accel_sigma_um_per_m_s2: dr_y_sigma,
                scans,
            }
        })
        .collect();
    let faces: Vec<FaceScan> = weaves
        .iter()
        .zip(&wacc)
        .map(|(w, (a, b, n))| {
            let g = prep.art.grad[w.points[0]];
            let axis = |v: &Vec3| AX[v.iamax()].to_string();
            FaceScan {
                center_mm: w.mean.into(),
                measured_along: axis(&g.abs()),
                moved_along: axis(&w.peak),
                speed_mm_s: w.speed,
                peak_accel_mm_s2: w.peak.max(),
                dynamic_rms_um: (a / (*n).max(1) as f64).sqrt() * 1e3,
                dynamic_rms_after_um: (b / (*n).max(1) as f64).sqrt() * 1e3,
            }
        })
        .collect();
    if !weaves.is_empty() {
        notes.push(format!(
            "{} face scans accelerated in place at {} places: P's entries along their normals \
             come from them off arcs, apart from the arcs' gain",
            weaves.len(),
            st.places.iter().filter(|q| q.ring.is_none()).count()
        ));
    }
    let on_edge = positions.iter().filter(|p| p.plane != "xy").count();
    if on_edge > 0 {
        notes.push(format!(
            "{on_edge} ring positions standing on their edge (XZ and YZ planes): P's Z row and \
             column and the phase of Z against X come from them"
        ));
    }
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
        faces,
        quadratic,
        phase0,
        residual_before_um: (ss0 / n).sqrt() * 1e3,
        residual_after_um: (sol.ss / n).sqrt() * 1e3,
        notes,
    })
}
