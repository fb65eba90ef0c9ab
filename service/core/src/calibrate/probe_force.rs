//! One concern, kept whole: the `probe-force` procedure, extrapolation to zero probing force
//! (one least squares over all points, [`run`]). Variant (a): the same circles on the master
//! sphere scanned at two or more deflections.
//!
//! Equations. A scanning probe's stylus bends with the probing force, which grows with the
//! deflection d, so the probe reports the tip short of where it is by K_t·d (K_t = diag(k_u,
//! k_v, k_w) per tip t in probe axes): the corrected point of the library's `probe_force`
//! effect is s + R·(K_t·d) (R the head's rotation). On a sphere of centre C and radius ρ, a
//! point p measured without that correction satisfies
//!
//! n·(p + R·(K_t·d) − C(t)) = ρ_c + Σ_h (a_ch·cos hθ + b_ch·sin hθ),   n = (p − C)/|p − C|,
//!
//! per circle c (a setting g — a tip at one head angle — at one latitude, every deflection),
//! θ the angle about the sphere's z axis and C(t) a centre that drifts while the circle's
//! deflections are scanned: the room warms, the stylus grows along itself by α_t·L·ΔT_stylus
//! and the scales read α_s,j·(T_s,j − 20 °C)·s_j less (`stylus_thermal` and `scale_thermal`,
//! their coefficients free, from the bags' `stylus` and `scale_x|y|z` sensors; the scales' a
//! prior on a circle scanned in part, below). Where the bags lack those sensors, or a circle
//! has a scan that does not go round it whole (variant (c)'s quarter), the drift is C_g +
//! Ċ_c·(t − t_c), free per circle. A free drift per circle
//! beside the sensors' columns is not harmless: over a whole turn t is a sawtooth in θ whose
//! harmonics above the static map's (1/h of it at h = 15) are the wave's own (variant b), and
//! the drift took from the sensors' columns what they explain exactly (on machine 241, with
//! only the scales' expansion on, α_z came out 0.8 against 8.6 ppm/K and the tip's k_w 1.1–1.5 %
//! low at 1–2σ; without the free drift α_z 8.51, every k within 0.2σ).
//!
//! Over part of a turn (variant (c)'s quarter beside a full turn) the drift n·Ċ·t has nearly
//! the force's shape (over θ = 0…90°, cos θ, sin θ against cos²θ, sin²θ), so a drift model
//! free per circle, or the sensors' columns, trade against k_v (−2 % to −3 % at −1.7σ to −4σ
//! on machine 241). The measurement separates them: the part-turn scanned at one deflection,
//! then another, then the first again (A-B-A, `sim --program probe-force-quarter`). Such a
//! circle's part-turn scans get their own drift, an offset and a rate, −n·(ΔC_p + Ċ_p·(t −
//! t_p)) with t_p their mean time: the repeat of A around B tells the rate from the force (a
//! drift linear in time moves A's two scans apart, the force does not), and the force
//! coefficients come from the part-turn scans, the full turn carrying the static map round the
//! circle. A single second part-turn at another deflection left k_u 0.3–1.7 % off, its sign
//! following the order of the two (the rate between them is the force's shape again); the
//! part-turn there and back, k_v 50–70 % off (the servo's radial errors change with the
//! direction, and the static map is one for both). A bag whose part-turns do not repeat a
//! deflection gets the free linear drift and a note that the drift and the force are
//! confounded there.
//!
//! What else passes for force over a part-turn, traced on machine 241 (k_u −0.5 to −0.7 % at
//! −5σ, k_v −0.2 % at −3σ to −4σ; with every simulator effect but the force off, unbiased):
//! the machine's geometry (half of it, and the scales' expansion the other half). The carriage
//! sits Δd further in at the larger deflection, so an error field E of the carriage's position
//! (guide straightness, ~0.1 µm per mm of slope) adds n·J·D to each point (J = ∂E/∂x, D the
//! deflection in machine axes): the force's own form. J's diagonal is the force's shape at one
//! head angle and stays in it; over a whole turn the off-diagonal part is orthogonal to the
//! force (sin 2θ against cos 2θ), over a quarter not quite: X's guide straightness towards Y
//! alone (J_yx, 9.7·10⁻⁵ there) left k_u −0.37 % at −3σ, and with J_xy fitted −0.03 %. A
//! circle with A-B-A part-turns fits J_xy, −(n_x·D_y + n_y·D_x)·J_xy (its xz and yz parts have
//! the form of k_w's over a quarter: fitted per circle they took k_w −160 to −250 %, per
//! setting k_w fell to 0–20 % within 2σ).
//!
//! The scales' expansion over a part-turn: the scale j reads α_j·(T_j − 20 °C)·(s_j − o_j)
//! long (ISO 1), and at the larger deflection the carriage sits D further in, so the reading
//! changes by α_j·(T_j − 20 °C)·D_j — J's diagonal again, the force's form. Beside the free
//! drifts the scales' columns see only what the temperatures curve over a circle (mK), as large
//! as a reading's noise (2 mK), so fitted there their coefficients were diluted toward zero
//! (0.1–1.5 ± 0.5–1.3 ppm/K against 8.6–11; errors in variables) and the gradient went into k
//! (−0.3 % at −2.6σ on 241 with only the scales' expansion on); a fit of the columns to each
//! sensor's straight line over ±5 s removed the dilution but left k_u −0.6 % with every
//! simulator effect off on machine 5381. So on a circle with a part-turn scan (a free drift)
//! the scales' term is not fitted: α_j = 0 ± σ_α,j beyond the start's (whose `scale_thermal`
//! the points already carry), its column n_j·(T_j − 20 °C)·(s_j − o_j) a nuisance like the
//! compliance below (σ_α²·(Mc)(Mc)ᵀ added to the covariance), with σ_α,j 10 % of the start's
//! α_j when it corrects the scales (as `dynamic-map` takes it), else 12 ppm/K (as `tips`:
//! glass-ceramic ≈ 0 to steel 11.5, aluminium's 23 at 2σ). A circle scanned whole keeps the
//! columns fitted: there the drift is the sensors' and determines them (variant a).
//!
//! The right-hand side is the **static error map** of that
//! circle: what each point extrapolates to at zero deflection, the same for every
//! deflection, whatever its cause (the sphere's form, the machine's geometry there, a servo
//! ellipse at that speed). Linearised about each setting's own sphere fit, the equation is
//! linear in k_u, k_v, k_w of every tip and in the nuisance (ρ_c, a_ch, b_ch, Ċ_c); one least-
//! squares fit over all settings. Only the change of a point with the deflection determines
//! K (a single deflection is the static map), the latitudes separate k_w (along the stylus)
//! from k_u, k_v, and the angle around each circle separates k_u from k_v (cos² against sin²).
//! The RMS of the fit about the zero-force map is reported per setting.
//!
//! What the start leaves of the dynamics (the nominal start has none) must not pass for force.
//! Two measures ([`Options`]): (1) only points at the programmed speed are used — no dwell,
//! spin-up or slow-down — so every deflection of a circle is compared at the same speed and
//! centripetal acceleration, and what the dynamics do there is the same at each and goes into
//! the static map (the patent's two forces along one path); (2) unless the start carries
//! `accel_deflection`, the structure's compliance under the carriage's acceleration a (the
//! estimated one) is a nuisance beside the force, one per machine axis (the sphere stands at
//! one place): the left-hand side would gain Σ_j C_j·n_j·a_j with C_j = 0 ± σ_C (σ_C = 30 µm
//! per m/s², a bridge CMM's). It is not fitted: the fit is linear, so a term c·C shifts the
//! estimate by M·c·C (M = (AᵀA)⁻¹Aᵀ), and σ_C²·(Mc)(Mc)ᵀ is added to the covariance; the
//! values do not change. On a wave (a = −ω²·d) the force and the compliance are one column up
//! to the scans' small differences: fitting both let those decide C and moved the force
//! coefficients by 0.5 % with every effect off in the simulator; as a nuisance the wave's share
//! σ_k ≈ σ_C·ω² goes into the coefficients' σ.
//!
//! Variant (d) — radial approaches at a few positions, the deflection growing along each —
//! has no sphere to fit: each position's points share one normal n̄ (their mean probing
//! direction) and one static term ρ_p (its distance), with no harmonics and no drift
//! (a position cannot carry a pattern round the sphere, and a drift along n̄ over an approach
//! is the deflection's own ramp): n̄·(p + R·(K_t·d)) = ρ_p.
//!
//! Variant (b) — a circle at a constant deflection and one whose deflection varies
//! sinusoidally around it — enters the same fit (its points carry their own deflections). Such
//! a varying scan also gets the real-time form ([`real_time`]): per wave, the points above
//! the wave's median deflection are a reading (R2, F2) and the lower-force halves around it,
//! interpolated to its place, the other (R1, F1); R0 = R1 − (R2 − R1)·F1/(F2 − F1), compared
//! with what the fit's zero-force model gives for the same points (and the lower-force reading
//! R1 with it: the error removed). The wave accelerates the carriage radially
//! in phase with the deflection (a = −ω²·d for a sinusoid): a compliance C of the structure
//! bends it by C·a, which the force fit cannot tell from a force coefficient −C·ω². The
//! procedure measures that coupling (the estimated radial acceleration against the
//! deflection) and names the bias a typical compliance would cause when the starting
//! calibration does not correct the compliance (`accel_deflection`).
//!
//! Source idea: Renishaw's calibration of a coordinate positioning apparatus — scan the same
//! path at two or more deflections and extrapolate each point to zero deflection; the
//! coefficient is a property of the stylus (one per tip, ISO 10360-5 qualifies stylus by
//! stylus), not of the machine.

mod real_time;

use super::{Param, ProcedureError};
use crate::calib::Calibration;
use crate::effects::{
    feature_map, probe_force, scale_thermal, stylus_thermal, Effect, EffectConfig,
};
use crate::lab::dataset::{Dataset, Phase};
use crate::lab::fit::Normal;
use crate::lab::program::FeatureKind;
use crate::sample::Vec3;
use crate::shape;
pub use real_time::RealTime;
use serde::Serialize;
use std::collections::{BTreeMap, BTreeSet};

/// Points deflected less than this are not used (no probing direction), mm.
const MIN_DEFLECTION_MM: f64 = 0.005;
/// Least spread of the deflections within a setting, mm.
const MIN_DEFLECTION_SPREAD_MM: f64 = 0.1;
/// Deflection levels closer than this are one level, mm.
const LEVEL_MM: f64 = 0.04;
/// A column whose information is below this fraction (squared) of its tip's strongest is not
/// determined by the measurement.
const WEAK_COLUMN: f64 = 0.03;
const AXES: [&str; 3] = ["u", "v", "w"];
/// Points within this latitude (degrees) belong to one circle.
const LATITUDE_DEG: f64 = 4.0;
/// Approaches within this angle about the sphere's axis (degrees) are one position.
const POSITION_DEG: f64 = 10.0;
/// Harmonics of each circle's static pattern.
const HARMONICS: usize = 12;
/// Drift columns per circle: the centre moving linearly in time (mm per 100 s) while its
/// deflections are scanned (only where the sensors do not give the drift), then the part-turn
/// scans' own offset (mm) and rate (mm per 100 s) where they repeat a deflection (A-B-A), and
/// there the geometry's change over the deflection's travel, its xy part (J_xy, mm per mm).
const DRIFT: usize = 10;
/// A scan covering at least this many of a turn's 36 bins of 10° goes round its circle whole.
const WHOLE_TURN_BINS: u32 = 32;
/// A bridge CMM's compliance, for the bias a wave's acceleration would cause: 30 µm per m/s²,
/// in s² (mm per mm/s²).
const TYPICAL_COMPLIANCE_S2: f64 = 30e-6;

/// One setting: a tip at one head angle on the sphere, every deflection.
#[derive(Debug, Clone, Serialize)]
pub struct Setting {
    /// Tip id.
    pub tip: u32,
    /// Head angles A1, A2, degrees.
    pub head_deg: [f64; 2],
    /// Points fitted.
    pub points: usize,
    /// The deflection levels scanned, mm.
    pub deflections_mm: Vec<f64>,
    /// Whether the points cover enough of the sphere to fit it; when not (approaches at a few
    /// positions) the radii below are distances along the probing direction relative to the
    /// zero-force surface, and no radius at zero force is given.
    pub sphere_fitted: bool,
    /// Sphere radius minus the certified radius per deflection level, before (as measured
    /// without any force correction), µm.
    pub radius_error_before_um: Vec<f64>,
    /// The same after the fitted force correction, µm.
    pub radius_error_after_um: Vec<f64>,
    /// Radius at zero deflection minus the certified radius, µm, with its σ.
    pub radius_error_at_zero_um: [f64; 2],
    /// RMS of the static error map's form (harmonics 2 and up of its circles), µm.
    pub static_form_um: f64,
    /// RMS of what is left about the static map after the force correction, µm.
    pub fit_rms_um: f64,
}

/// The outcome of `probe-force`.
#[derive(Debug, Clone, Serialize)]
pub struct Outcome {
    /// The calibration with the fitted force coefficients (unversioned).
    #[serde(skip)]
    pub calibration: Calibration,
    /// Fitted parameters with their σ (`tip2.probe_k_u_mm_per_mm`: mm of error per mm of
    /// deflection, the `probe_force` effect's unit).
    pub params: Vec<Param>,
    /// Every setting measured.
    pub settings: Vec<Setting>,
    /// Residual RMS about each circle's static map with no force correction, µm.
    pub rms_before_um: f64,
    /// Residual RMS after the fit, µm.
    pub rms_after_um: f64,
    /// Reduced χ² of the cells (circle × deflection) after the fit; the σ are scaled by it
    /// when above 1 (what the model leaves beyond noise, the Birge ratio).
    pub cell_chi2: f64,
    /// The static error map of every circle: its zero-force radius around it.
    pub static_maps: Vec<StaticMap>,
    /// The real-time form on each scan whose deflection varies within it (variant b).
    pub real_time: Vec<RealTime>,
    /// What this measurement cannot determine, and why.
    pub undetermined: Vec<String>,
    /// Remarks.
    pub notes: Vec<String>,
}

/// The static error map of one circle on the sphere (a setting at one latitude): what each
/// point extrapolates to at zero deflection, as the radius of the sphere there minus its
/// certified radius, at knots around the circle. It is kept apart from the machine's
/// geometry (which this procedure does not change) and from the force coefficients.
#[derive(Debug, Clone, Serialize)]
pub struct StaticMap {
    /// Tip.
    pub tip: u32,
    /// Head angles, degrees.
    pub head_deg: [f64; 2],
    /// Latitude of the circle on the sphere, degrees.
    pub latitude_deg: f64,
    /// Command segments scanned on it.
    pub segments: Vec<u32>,
    /// Knots: angle about the sphere's axis, degrees.
    pub theta_deg: Vec<f64>,
    /// Radius at zero force minus the certified radius at the knots, µm.
    pub radial_um: Vec<f64>,
    /// Standard uncertainty of each (statistical, the σ of the fit), µm.
    pub radial_u_um: Vec<f64>,
    /// What the new version stores (effect `feature_map`, every speed, at this circle's place,
    /// along the sphere's normal): minus the map, less the tip's own change of radius (which
    /// the new tip radius holds).
    pub stored: feature_map::Config,
}

/// Knots of a static map (every 5°: the map's 12 harmonics, linearly interpolated, within 3 %).
const STATIC_KNOTS: usize = 72;

struct Group {
    tip: u32,
    head: [f64; 2],
    feature: usize,
    idx: Vec<usize>,
}

/// Deflection levels of a set of |d| values: centres of clusters LEVEL_MM apart.
fn levels(mut d: Vec<f64>) -> Vec<f64> {
    d.sort_by(|a, b| a.total_cmp(b));
    let mut out: Vec<(f64, usize)> = vec![];
    for x in d {
        match out.last_mut() {
            Some((m, n)) if x - *m / *n as f64 <= LEVEL_MM => {
                *m += x;
                *n += 1;
            }
            _ => out.push((x, 1)),
        }
    }
    out.into_iter().map(|(m, n)| m / n as f64).collect()
}

fn level_of(levels: &[f64], d: f64) -> usize {
    levels
        .iter()
        .enumerate()
        .min_by(|a, b| (a.1 - d).abs().total_cmp(&(b.1 - d).abs()))
        .map(|(i, _)| i)
        .unwrap_or(0)
}

/// How [`run_with`] treats what the starting calibration leaves uncorrected. The default
/// (every point, no compliance) is [`run`]'s; variants (b)–(d) want both measures (`calibrate
/// probe-force --steady-only --compliance-prior 30`).
#[derive(Debug, Clone, Copy)]
pub struct Options {
    /// Only points at the scan's programmed speed (no dwell, no spin-up or slow-down): every
    /// deflection is then compared at the same kinematic state, so what the start leaves of
    /// the dynamics is the same at each and goes into the static map.
    pub steady_only: bool,
    /// The σ of each axis's compliance (s²), a nuisance 0 ± σ in the coefficients' σ (not
    /// fitted) when the start has no `accel_deflection`; `None` leaves it out.
    pub compliance_prior_s2: Option<f64>,
    /// Harmonics of each circle's static pattern.
    pub harmonics: usize,
}

impl Default for Options {
    fn default() -> Self {
        Options {
            steady_only: false,
            compliance_prior_s2: None,
            harmonics: HARMONICS,
        }
    }
}

/// Fits the force coefficients: `ds` built from the bags with `start` without its
/// `probe_force` effect (this procedure measures it).
pub fn run(ds: &Dataset, start: &Calibration) -> Result<Outcome, ProcedureError> {
    run_with(ds, start, Options::default())
}

/// [`run`] with explicit [`Options`].
pub fn run_with(
    ds: &Dataset,
    start: &Calibration,
    opts: Options,
) -> Result<Outcome, ProcedureError> {
    let harmonics = opts.harmonics.max(1);
    // Static-pattern columns per circle: mean radius, cos and sin of each harmonic.
    let per_circle = 1 + 2 * harmonics;
    let spheres: BTreeMap<usize, f64> = ds
        .features
        .iter()
        .enumerate()
        .filter(|(_, (_, f))| f.artifact == "sphere" && f.kind == FeatureKind::Boss)
        .filter_map(|(i, (_, f))| f.certificate_diameter_mm.map(|d| (i, d / 2.0)))
        .collect();
    if spheres.is_empty() {
        return Err(ProcedureError::Missing(
            "no master-sphere scans in the bags (a `sphere` feature with its certified \
             diameter): `probe-force` needs the same circles on the sphere scanned at two or \
             more deflections by each tip, e.g. `scancorr sim --program probe-force`"
                .into(),
        ));
    }
    // Settings: (tip, head angle, sphere).
    let mut by_key: BTreeMap<(u32, [i64; 2], usize), Vec<usize>> = BTreeMap::new();
    for (i, p) in ds.points.iter().enumerate() {
        // (A point without deflection has no probing direction and says nothing of the force.)
        // Only points at the programmed speed (see [`Options::steady_only`]).
        let steady = !opts.steady_only || (p.speed > 0.0 && p.phase == Phase::Steady);
        if spheres.contains_key(&p.feature)
            && p.ctx.deflection_probe.norm() > MIN_DEFLECTION_MM
            && steady
        {
            let h = [p.ctx.head_a1_deg, p.ctx.head_a2_deg].map(|a| (a * 1e3).round() as i64);
            by_key
                .entry((p.ctx.tip_id, h, p.feature))
                .or_default()
                .push(i);
        }
    }
    let groups: Vec<Group> = by_key
        .into_iter()
        .map(|((tip, h, feature), idx)| Group {
            tip,
            head: h.map(|a| a as f64 / 1e3),
            feature,
            idx,
        })
        .collect();
    let mut tips: Vec<u32> = groups.iter().map(|g| g.tip).collect();
    tips.sort_unstable();
    tips.dedup();
    // Deflection levels per setting; one level cannot separate the force from the radius.
    let mut lvls = vec![];
    for g in &groups {
        let d: Vec<f64> = g
            .idx
            .iter()
            .map(|&i| ds.points[i].ctx.deflection_probe.norm())
            .collect();
        let l = levels(d);
        let spread = l.last().unwrap_or(&0.0) - l.first().unwrap_or(&0.0);
        if l.len() < 2 || spread < MIN_DEFLECTION_SPREAD_MM {
            return Err(ProcedureError::IllConditioned(format!(
                "tip {} at head angles ({}, {})° scanned the sphere at {} ({}): the force \
                 cannot be told from the tip's radius; scan the same circles at ≥ 2 \
                 deflections at least {MIN_DEFLECTION_SPREAD_MM} mm apart (e.g. 0.1, 0.3 and \
                 0.5 mm)",
                g.tip,
                g.head[0],
                g.head[1],
                if l.len() < 2 {
                    "one deflection"
                } else {
                    "deflections too close together"
                },
                l.iter()
                    .map(|x| format!("{x:.2} mm"))
                    .collect::<Vec<_>>()
                    .join(", ")
            )));
        }
        lvls.push(l);
    }
    // The effect's own regressors: one (k_u, k_v, k_w) per tip.
    let cfg = probe_force::Config::zeros_per_tip(&tips);
    let model = cfg.build().map_err(ProcedureError::Missing)?;
    let n_force = model.n_params();
    // Nuisance: the styli's and the scales' expansion as the room warms, from the measured
    // temperatures (the tip centre moves along the stylus, the sphere's apparent centre with
    // the scales) — not linear in time over a circle's scans.
    let mut sensors = ds.sensors.clone();
    let built: Vec<(bool, crate::effects::Model)> = [
        EffectConfig::StylusThermal(stylus_thermal::Config::zeros_per_tip(&tips, false)),
        EffectConfig::ScaleThermal(scale_thermal::Config::zeros()),
    ]
    .iter()
    .filter_map(|c| {
        let scale = matches!(c, EffectConfig::ScaleThermal(_));
        c.build(&mut sensors).ok().map(|b| (scale, b.model))
    })
    .collect();
    // The scales' columns (α_x, α_y, α_z) among the thermal ones.
    let mut scale_col = None;
    let mut off = n_force;
    for (scale, m) in &built {
        if *scale {
            scale_col = Some(off);
        }
        off += m.n_params();
    }
    let thermal: Vec<crate::effects::Model> = built.into_iter().map(|(_, m)| m).collect();
    let n_thermal = n_force + thermal.iter().map(|m| m.n_params()).sum::<usize>();
    // Nuisance: the structure's compliance under the carriage's acceleration, one per machine
    // axis (the sphere stands at one place), unless the start corrects it.
    let compliance_corrected = start.effects.iter().any(|e| e.kind() == "accel_deflection");
    let compliance_prior = opts.compliance_prior_s2.filter(|_| !compliance_corrected);
    let n_compliance = if compliance_prior.is_some() { 3 } else { 0 };
    // Nuisance: the scales' expansion on the circles with a part-turn scan, α_j = 0 ± σ_α,j
    // beyond the start's (module doc): three columns after the compliance's.
    let scale_prior_col = scale_col.map(|_| n_thermal + n_compliance);
    let n_dense = n_thermal + n_compliance + if scale_col.is_some() { 3 } else { 0 };
    let tip_col = |t: u32| 3 + 3 * tips.iter().position(|x| *x == t).expect("listed tip");
    // Per setting: its own sphere fit (the point of linearisation).
    // Where the points cover too little of the sphere to fit it (approaches at a few
    // positions), their centroid and zero: each position's static term holds its distance.
    struct Lin {
        center: Vec3,
        radius: f64,
        sphere: bool,
    }
    let mut lin = vec![];
    for g in &groups {
        let pts: Vec<Vec3> = g.idx.iter().map(|&i| ds.points[i].surface).collect();
        let r_cert = spheres[&g.feature];
        // Only scans that go round the sphere (arcs) determine it: a sphere fitted to straight
        // approaches at a few positions can pass the radius check and give bogus normals.
        let arcs = g.idx.iter().any(|&i| ds.points[i].direction != 0);
        lin.push(match shape::fit_sphere(&pts) {
            Ok(f) if arcs && (f.radius - r_cert).abs() < 0.05 * r_cert => Lin {
                center: f.center,
                radius: f.radius,
                sphere: true,
            },
            _ => Lin {
                center: pts.iter().fold(Vec3::zeros(), |a, p| a + p) / pts.len() as f64,
                radius: 0.0,
                sphere: false,
            },
        });
    }
    // Each point's normal (out of the material): from the sphere's centre where the sphere
    // was fitted, else the probing direction (the deflection in machine axes, which the
    // stylus's uneven bending tilts by a few mrad).
    // Without a sphere fit (approaches at a few positions) the points of one position (its
    // latitude within LATITUDE_DEG, its angle about the sphere's axis within POSITION_DEG)
    // share one normal, their mean probing direction: a single point's direction carries the
    // probe's noise (mrad at the smallest deflections), which would make the normal, and every
    // column built from it, change with the deflection.
    let raw_dir = |i: usize| {
        let c = &ds.points[i].ctx;
        (c.machine_from_probe * c.deflection_probe).normalize()
    };
    let position_key = |gi: usize, i: usize| -> (usize, i64, i64) {
        let n = raw_dir(i);
        let lat = n.z.clamp(-1.0, 1.0).asin().to_degrees();
        let th = n.y.atan2(n.x).to_degrees();
        (
            gi,
            (lat / LATITUDE_DEG).round() as i64,
            (th / POSITION_DEG).round() as i64,
        )
    };
    let mut position_dir: BTreeMap<(usize, i64, i64), Vec3> = BTreeMap::new();
    for (gi, g) in groups.iter().enumerate() {
        if !lin[gi].sphere {
            for &i in &g.idx {
                *position_dir
                    .entry(position_key(gi, i))
                    .or_insert_with(Vec3::zeros) += raw_dir(i);
            }
        }
    }
    let dir = |gi: usize, i: usize| -> Vec3 {
        if lin[gi].sphere {
            (ds.points[i].surface - lin[gi].center).normalize()
        } else {
            position_dir[&position_key(gi, i)].normalize()
        }
    };
    // Circles: the points of one setting at one latitude, every deflection. Each circle's
    // static pattern (its mean radius and HARMONICS harmonics of the angle about the sphere's
    // axis) is the static error map at that latitude, common to every deflection. Without a
    // sphere fit each position is its own "circle" with one static term (its distance) and no
    // harmonics or drift: a few positions cannot carry a pattern round the sphere, and a
    // drift along one direction over an approach is the deflection's own ramp.
    let mut circles: BTreeMap<(usize, i64, i64), usize> = BTreeMap::new();
    let mut circle_of = vec![usize::MAX; ds.points.len()];
    for (gi, g) in groups.iter().enumerate() {
        for &i in &g.idx {
            let key = if lin[gi].sphere {
                let lat = dir(gi, i).z.clamp(-1.0, 1.0).asin().to_degrees();
                (gi, (lat / LATITUDE_DEG).round() as i64, 0)
            } else {
                position_key(gi, i)
            };
            let n = circles.len();
            circle_of[i] = *circles.entry(key).or_insert(n);
        }
    }
    let n_circles = circles.len();
    let mut circles_of_group = vec![vec![]; groups.len()];
    let mut position_only = vec![false; n_circles];
    for ((gi, _, _), c) in &circles {
        circles_of_group[*gi].push(*c);
        position_only[*c] = !lin[*gi].sphere;
    }
    // The centre's drift while a circle's scans run: the styli's and the scales' expansion from
    // their sensors (the thermal columns above) when the bags carry those sensors and each of
    // the circle's scans goes round it whole; a free linear drift per circle otherwise (see
    // the module's doc).
    let sensors_drift = std::iter::once("stylus")
        .chain(scale_thermal::SENSORS)
        .all(|n| ds.sensors.find(n).is_some());
    let mut turn_bins: BTreeMap<(usize, u32), u64> = BTreeMap::new();
    for (gi, g) in groups.iter().enumerate() {
        for &i in &g.idx {
            let n = dir(gi, i);
            let b = ((n.y.atan2(n.x).to_degrees().rem_euclid(360.0) / 10.0) as u32).min(35);
            *turn_bins
                .entry((circle_of[i], ds.points[i].segment))
                .or_default() |= 1 << b;
        }
    }
    let mut free_drift = vec![!sensors_drift; n_circles];
    let mut partial_levels: BTreeMap<usize, Vec<usize>> = BTreeMap::new();
    let mut partial_seg: BTreeSet<(usize, u32)> = BTreeSet::new();
    let mut partial_scans: Vec<BTreeSet<u32>> = vec![BTreeSet::new(); n_circles];
    for ((c, seg), bins) in &turn_bins {
        if bins.count_ones() < WHOLE_TURN_BINS {
            free_drift[*c] = true;
            partial_seg.insert((*c, *seg));
        }
    }
    for (gi, g) in groups.iter().enumerate() {
        for &i in &g.idx {
            let c = circle_of[i];
            if partial_seg.contains(&(c, ds.points[i].segment)) {
                let l = level_of(&lvls[gi], ds.points[i].ctx.deflection_probe.norm());
                let v = partial_levels.entry(c).or_default();
                if !v.contains(&l) {
                    v.push(l);
                }
                partial_scans[c].insert(ds.points[i].segment);
            }
        }
    }
    // A circle whose part-turn scans repeat one deflection around another (A-B-A): their
    // drift gets its own offset and rate (see the module's doc).
    let repeated: Vec<bool> = (0..n_circles)
        .map(|c| {
            let levels = partial_levels.get(&c).map_or(&[][..], |v| &v[..]);
            levels.len() >= 2 && partial_scans[c].len() > levels.len()
        })
        .collect();
    // The circles whose drift is free (a part-turn scan): their scales' columns are the prior's.
    let scale_prior: Vec<bool> = (0..n_circles)
        .map(|c| free_drift[c] && !position_only[c])
        .collect();
    let n_cols = n_dense + (DRIFT + per_circle) * n_circles;
    // Each position's mean distance (approaches): its rows are taken about it. Its static
    // term absorbs it either way, but a distance of millimetres in the rows is lost to
    // rounding in the normal equations wherever a column is nearly constant over a position
    // (a temperature that barely changes), leaving the fit's residual at the distance.
    let mut circle_ref = vec![0.0; n_circles];
    {
        let mut n_ref = vec![0usize; n_circles];
        for (gi, g) in groups.iter().enumerate() {
            for &i in &g.idx {
                let c = circle_of[i];
                if position_only[c] {
                    let l = &lin[gi];
                    circle_ref[c] += dir(gi, i).dot(&(ds.points[i].surface - l.center)) - l.radius;
                    n_ref[c] += 1;
                }
            }
        }
        for (r, n) in circle_ref.iter_mut().zip(&n_ref) {
            *r /= (*n).max(1) as f64;
        }
    }
    // Each circle's mean time (its drift is linear about it).
    let mut t_circle = vec![0.0; n_circles];
    let mut n_in = vec![0usize; n_circles];
    for g in &groups {
        for &i in &g.idx {
            t_circle[circle_of[i]] += ds.points[i].ctx.t_ns as f64 * 1e-9;
            n_in[circle_of[i]] += 1;
        }
    }
    for (t, n) in t_circle.iter_mut().zip(&n_in) {
        *t /= (*n).max(1) as f64;
    }
    let mut t_part = vec![0.0; n_circles];
    let mut n_part = vec![0usize; n_circles];
    for g in &groups {
        for &i in &g.idx {
            if partial_seg.contains(&(circle_of[i], ds.points[i].segment)) {
                t_part[circle_of[i]] += ds.points[i].ctx.t_ns as f64 * 1e-9;
                n_part[circle_of[i]] += 1;
            }
        }
    }
    for (t, n) in t_part.iter_mut().zip(&n_part) {
        *t /= (*n).max(1) as f64;
    }
    let mut ne = Normal::new(n_cols);
    let mut dense = vec![0.0; n_dense];
    let mut r = vec![Vec3::zeros(); n_dense];
    // The thermal regressors about their mean over the measurement: they model what changes
    // while it runs, and the static maps hold the circles at the measurement's mean
    // temperature (about the calibration's reference temperature, an expansion coefficient
    // this measurement barely determines would carry its whole uncertainty into every map).
    let mut thermal_mean = vec![Vec3::zeros(); n_dense];
    let mut n_mean = 0usize;
    for g in &groups {
        for &i in &g.idx {
            let mut off = n_force;
            for m in &thermal {
                let k = m.n_params();
                m.regressors(&ds.points[i].ctx, &mut r[off..off + k]);
                off += k;
            }
            for (a, b) in thermal_mean[..n_thermal].iter_mut().zip(&r).skip(n_force) {
                if b.iter().all(|x| x.is_finite()) {
                    *a += b;
                }
            }
            n_mean += 1;
        }
    }
    for a in &mut thermal_mean {
        *a /= n_mean.max(1) as f64;
    }
    let mut sparse = Vec::with_capacity(DRIFT + per_circle);
    let row = |gi: usize,
               i: usize,
               dense: &mut Vec<f64>,
               r: &mut Vec<Vec3>,
               sparse: &mut Vec<(usize, f64)>|
     -> f64 {
        let p = &ds.points[i];
        let l = &lin[gi];
        let n = dir(gi, i);
        model.regressors(&p.ctx, &mut r[..n_force]);
        let mut off = n_force;
        for m in &thermal {
            let k = m.n_params();
            m.regressors(&p.ctx, &mut r[off..off + k]);
            off += k;
        }
        for j in 0..n_compliance {
            let mut a = Vec3::zeros();
            a[j] = p.ctx.est_acc[j];
            r[n_thermal + j] = a;
        }
        for ((d, ri), mi) in dense.iter_mut().zip(r.iter()).zip(&thermal_mean) {
            *d = if ri.iter().all(|x| x.is_finite()) {
                n.dot(&(ri - mi))
            } else {
                0.0
            };
        }
        let ci = circle_of[i];
        if let (Some(sc), Some(sp)) = (scale_col, scale_prior_col) {
            // On a circle with a part-turn scan the scales' columns are their prior's (not
            // fitted); elsewhere they are fitted.
            for j in 0..3 {
                dense[sp + j] = if scale_prior[ci] {
                    std::mem::take(&mut dense[sc + j])
                } else {
                    0.0
                };
            }
        }
        let dt = (p.ctx.t_ns as f64 * 1e-9 - t_circle[ci]) / 100.0;
        let c0 = DRIFT * ci;
        sparse.clear();
        let k0 = DRIFT * n_circles + per_circle * ci;
        sparse.push((k0, -1.0));
        if position_only[ci] {
            return n.dot(&(p.surface - l.center)) - l.radius - circle_ref[ci];
        }
        if free_drift[ci] {
            sparse.extend([(c0, -n.x * dt), (c0 + 1, -n.y * dt), (c0 + 2, -n.z * dt)]);
        }
        if repeated[ci] && partial_seg.contains(&(ci, p.segment)) {
            let dt2 = (p.ctx.t_ns as f64 * 1e-9 - t_part[ci]) / 100.0;
            sparse.extend([(c0 + 3, -n.x), (c0 + 4, -n.y), (c0 + 5, -n.z)]);
            sparse.extend([
                (c0 + 6, -n.x * dt2),
                (c0 + 7, -n.y * dt2),
                (c0 + 8, -n.z * dt2),
            ]);
        }
        if repeated[ci] {
            // The geometry's change over the deflection's travel, its xy part (module doc).
            let dm = p.ctx.machine_from_probe * p.ctx.deflection_probe;
            sparse.push((c0 + 9, -(n.x * dm.y + n.y * dm.x)));
        }
        let th = n.y.atan2(n.x);
        for h in 1..=harmonics {
            let a = h as f64 * th;
            sparse.push((k0 + 2 * h - 1, -a.cos()));
            sparse.push((k0 + 2 * h, -a.sin()));
        }
        n.dot(&(p.surface - l.center)) - l.radius
    };
    // What is left of point i's row with the parameters x (from the row itself: yᵀy − xᵀAᵀy
    // cancels catastrophically when the static terms carry large distances, as approaches'
    // do).
    let residual = |gi: usize,
                    i: usize,
                    x: &[f64],
                    dense: &mut Vec<f64>,
                    r: &mut Vec<Vec3>,
                    sparse: &mut Vec<(usize, f64)>|
     -> f64 {
        let y = row(gi, i, dense, r, sparse);
        y + dense.iter().zip(x).map(|(a, t)| a * t).sum::<f64>()
            + sparse.iter().map(|(c, v)| v * x[n_dense + c]).sum::<f64>()
    };
    let mut n_rows = 0usize;
    for (gi, g) in groups.iter().enumerate() {
        for &i in &g.idx {
            let y = row(gi, i, &mut dense, &mut r, &mut sparse);
            n_rows += 1;
            ne.add(&dense, &sparse, y);
        }
    }
    // Nuisance terms u = 0 ± σ_u, not fitted: the fit is linear, so such a term c·u shifts the
    // estimate by M·c·u (M = (AᵀA)⁻¹Aᵀ) and adds σ_u²·(Mc)(Mc)ᵀ to its covariance; the
    // values do not change. (1) The structure's compliance, one per axis, 0 ± σ_C: a wave of
    // the deflection accelerates the carriage in phase with it, so the force and the
    // compliance are one column up to the scans' small differences, and fitting both let
    // those (nm) decide a compliance of tens of µm per m/s² and move the force coefficients
    // by it (0.5 % on the sine program with every effect off). (The drift of a circle scanned
    // only in part at one deflection, a quarter beside a full turn, takes the force's shape
    // over the part as well; as a nuisance of 1 nm/s it left the quarter's k_v −3σ with the
    // effects on, so it stays fitted there. Without it the scales' columns take the same
    // shape — n_y·ΔT·y over a quarter against sin²θ — and k_v is −3σ to −4σ.)
    let mut nuisance: Vec<(usize, f64)> = vec![];
    if let Some(sc) = compliance_prior {
        nuisance.extend((n_thermal..n_thermal + n_compliance).map(|c| (c, sc)));
    }
    // (2) The scales' expansion on the circles with a part-turn scan (module doc).
    let scale_sigma = scale_alpha_sigma(start);
    if let Some(sp) = scale_prior_col {
        nuisance.extend((0..3).map(|j| (sp + j, scale_sigma[j])));
    }
    // The machine-wide k has no rows (every tip is listed); a tip's axis the measurement
    // barely sees (no deflection along it) is not determined.
    let mut undetermined = vec![];
    let mut weak = vec![false; n_dense];
    for c in 0..3 {
        weak[c] = true;
    }
    for &t in &tips {
        let c0 = tip_col(t);
        let top = (c0..c0 + 3).map(|c| ne.m[(c, c)]).fold(0.0, f64::max);
        for (a, c) in (c0..c0 + 3).enumerate() {
            if !(ne.m[(c, c)] > WEAK_COLUMN * WEAK_COLUMN * top) {
                weak[c] = true;
                undetermined.push(format!(
                    "tip{t}.probe_k_{}_mm_per_mm: the scans barely deflect tip {t} along its probe axis {} \
                     — add circles at higher latitudes (or faces probed along that axis)",
                    AXES[a], AXES[a]
                ));
            }
        }
    }
    for (c, w) in weak.iter().enumerate() {
        if *w {
            ne.m.row_mut(c).fill(0.0);
            ne.m.column_mut(c).fill(0.0);
            ne.b[c] = 0.0;
        }
    }
    // Each nuisance column's Aᵀc (the normal matrix is kept in its lower triangle), then the
    // column out of the fit.
    let is_nuisance = |c: usize| nuisance.iter().any(|(j, _)| *j == c);
    let n_all = ne.b.len();
    let nuisance_g: Vec<(f64, Vec<f64>)> = nuisance
        .iter()
        .map(|&(j, su)| {
            let g = (0..n_all)
                .map(|i| {
                    if is_nuisance(i) || (i < n_dense && weak[i]) {
                        0.0
                    } else {
                        ne.m[(i.max(j), i.min(j))]
                    }
                })
                .collect();
            (su, g)
        })
        .collect();
    for &(c, _) in &nuisance {
        ne.m.row_mut(c).fill(0.0);
        ne.m.column_mut(c).fill(0.0);
        ne.b[c] = 0.0;
    }
    let (sol, pad) = solve_padded(&ne);
    if sol.rank <= pad {
        return Err(ProcedureError::IllConditioned(
            "the normal equations of the force fit could not be solved (no direction of them \
             determined)"
                .into(),
        ));
    }
    // The same without any force correction: what the static maps and drifts alone leave.
    let ss_before = {
        let mut n0 = ne.clone();
        for c in 0..n_force {
            n0.m.row_mut(c).fill(0.0);
            n0.m.column_mut(c).fill(0.0);
            n0.b[c] = 0.0;
        }
        let x0: Vec<f64> = solve_padded(&n0).0.x.iter().copied().collect();
        let mut ss = 0.0;
        for (gi, g) in groups.iter().enumerate() {
            for &i in &g.idx {
                ss += residual(gi, i, &x0, &mut dense, &mut r, &mut sparse).powi(2);
            }
        }
        ss
    };
    let theta: Vec<f64> = sol.x.iter().copied().collect();
    // Residuals in time order per setting: their lag-1 correlation inflates σ (neighbouring
    // points share the sphere's form and the probe's lobing).
    let mut resid: Vec<Vec<f64>> = vec![];
    let mut ss_after = 0.0;
    // Per cell (circle × deflection level): the residual's mean and its 2θ pattern, the
    // shapes the force coefficients take (see the consistency check below).
    let mut cells: BTreeMap<(usize, usize), [f64; 4]> = BTreeMap::new();
    for (gi, g) in groups.iter().enumerate() {
        let mut order = g.idx.clone();
        order.sort_by_key(|&i| ds.points[i].ctx.t_ns);
        let mut rs = vec![];
        for &i in &order {
            let e = residual(gi, i, &theta, &mut dense, &mut r, &mut sparse);
            ss_after += e * e;
            rs.push(e);
            let p = &ds.points[i];
            let n = dir(gi, i);
            let th2 = 2.0 * n.y.atan2(n.x);
            let lv = level_of(&lvls[gi], p.ctx.deflection_probe.norm());
            let c = cells.entry((circle_of[i], lv)).or_default();
            c[0] += e;
            c[1] += e * th2.cos();
            c[2] += e * th2.sin();
            c[3] += 1.0;
        }
        resid.push(rs);
    }
    let (mut num, mut den) = (0.0, 0.0);
    for rs in &resid {
        for w in rs.windows(2) {
            num += w[0] * w[1];
        }
        den += rs.iter().map(|e| e * e).sum::<f64>();
    }
    let rho = if den > 0.0 {
        (num / den).clamp(0.0, 0.95)
    } else {
        0.0
    };
    let inflate = (1.0 + rho) / (1.0 - rho);
    let dof = (n_rows as f64 - (sol.rank - pad) as f64).max(1.0);
    let point_var = ss_after / dof;
    if !(point_var > 0.0 && point_var.is_finite()) {
        return Err(ProcedureError::IllConditioned(
            "the fit leaves no residual to judge its uncertainty by: too few points per \
             circle and deflection; scan the circles fully"
                .into(),
        ));
    }
    // Consistency between the cells: with the model right, each cell's mean and 2θ pattern
    // are noise (variance σ²/n and 2σ²/n, n the cell's effective points). What is left there
    // beyond noise — a drift the temperatures do not follow, an effect that changes with the
    // circle's radius — would bias the coefficients alike, so the σ grow by its reduced χ²
    // (Birge ratio).
    let mut chi2 = 0.0;
    // (An approach's position has no pattern round the sphere: its cells give their means.)
    let mut cell_terms = 0usize;
    for ((ci, _), c) in &cells {
        let n = c[3] / inflate;
        if n < 1.0 {
            continue;
        }
        let m = c[0] / c[3];
        chi2 += m * m / (point_var / n);
        cell_terms += 1;
        if !position_only[*ci] {
            let (a, b) = (2.0 * c[1] / c[3], 2.0 * c[2] / c[3]);
            chi2 += (a * a + b * b) / (2.0 * point_var / n);
            cell_terms += 2;
        }
    }
    let fitted = (0..n_force).filter(|&c| !weak[c]).count();
    let circle_terms: usize = position_only.iter().map(|&p| if p { 1 } else { 3 }).sum();
    let cell_dof = cell_terms.saturating_sub(circle_terms + fitted);
    let chi2_red = if cell_dof > 0 {
        chi2 / cell_dof as f64
    } else {
        1.0
    };
    let birge = chi2_red.max(1.0);
    let sigma2 = point_var * inflate * birge;
    // What each nuisance would shift the estimate by per unit: M·c = (AᵀA)⁻¹·Aᵀc.
    let shifts: Vec<(f64, Vec<f64>)> = nuisance_g
        .iter()
        .map(|(su, g)| {
            let d = (0..n_all)
                .map(|a| {
                    if is_nuisance(a) {
                        return 0.0;
                    }
                    (0..n_all)
                        .filter(|&b| g[b] != 0.0)
                        .map(|b| sol.cov[(a, b)] * g[b])
                        .sum()
                })
                .collect();
            (*su, d)
        })
        .collect();
    let widen = |c: usize| -> f64 {
        shifts
            .iter()
            .map(|(su, d): &(f64, Vec<f64>)| (su * d[c]).powi(2))
            .sum()
    };
    let sig = |c: usize| (sol.cov[(c, c)].max(0.0) * sigma2 + widen(c)).sqrt();

    let mut params = vec![];
    let mut per_tip: BTreeMap<u32, [f64; 3]> = BTreeMap::new();
    let start_k = start.effects.iter().find_map(|e| match e {
        EffectConfig::ProbeForce(c) => Some(c.clone()),
        _ => None,
    });
    for &t in &tips {
        let c0 = tip_col(t);
        let prior = start_k
            .as_ref()
            .map_or([0.0; 3], |c| c.per_tip.get(&t).copied().unwrap_or(c.k));
        let mut k = [0.0; 3];
        for a in 0..3 {
            if weak[c0 + a] {
                k[a] = prior[a];
                continue;
            }
            k[a] = theta[c0 + a];
            params.push(Param {
                name: format!("tip{t}.probe_k_{}_mm_per_mm", AXES[a]),
                value: theta[c0 + a],
                sigma: sig(c0 + a),
            });
        }
        per_tip.insert(t, k);
    }
    // The fitted force's share of a point's row (its force columns come first).
    let force_of = |dense: &[f64]| -> f64 {
        dense[..n_force]
            .iter()
            .zip(&theta)
            .map(|(a, t)| a * t)
            .sum()
    };
    // Settings' radii per deflection level before and after, and at zero force.
    let mut settings = vec![];
    for (gi, g) in groups.iter().enumerate() {
        let l = &lin[gi];
        let r_cert = spheres[&g.feature];
        let nl = lvls[gi].len();
        let (mut before, mut after, mut count) = (vec![0.0; nl], vec![0.0; nl], vec![0usize; nl]);
        for &i in &g.idx {
            let p = &ds.points[i];
            let y = row(gi, i, &mut dense, &mut r, &mut sparse);
            let force = force_of(&dense);
            let k = level_of(&lvls[gi], p.ctx.deflection_probe.norm());
            before[k] += y;
            after[k] += y + force;
            count[k] += 1;
        }
        // The zero-force radius: the circles' mean radii (each circle's weight its points).
        let (mut rsum, mut vsum, mut nsum) = (0.0, 0.0, 0.0);
        for &c in &circles_of_group[gi] {
            let col = n_dense + DRIFT * n_circles + per_circle * c;
            let m = n_in[c] as f64;
            rsum += m * theta[col];
            vsum += m * m * sig(col).powi(2);
            nsum += m;
        }
        let rho0 = l.radius + rsum / nsum.max(1.0);
        // Without a sphere fit the distances are relative to the zero-force surface (where
        // every level lands after the correction).
        let r_ref = if l.sphere {
            r_cert
        } else {
            l.radius + after.iter().sum::<f64>() / count.iter().sum::<usize>().max(1) as f64
        };
        let rho0_sigma = vsum.sqrt() / nsum.max(1.0);
        let stat: f64 = resid[gi].iter().map(|e| e * e).sum::<f64>() / resid[gi].len() as f64;
        let mut form = 0.0;
        for &i in &g.idx {
            let n = dir(gi, i);
            let th = n.y.atan2(n.x);
            let k0 = n_dense + DRIFT * n_circles + per_circle * circle_of[i];
            let f: f64 = (2..=harmonics)
                .map(|h| {
                    let a = h as f64 * th;
                    theta[k0 + 2 * h - 1] * a.cos() + theta[k0 + 2 * h] * a.sin()
                })
                .sum();
            form += f * f;
        }
        let form = (form / g.idx.len() as f64).sqrt();
        settings.push(Setting {
            tip: g.tip,
            head_deg: g.head,
            points: g.idx.len(),
            deflections_mm: lvls[gi].clone(),
            sphere_fitted: l.sphere,
            radius_error_before_um: (0..nl)
                .map(|k| (l.radius + before[k] / count[k].max(1) as f64 - r_ref) * 1e3)
                .collect(),
            radius_error_after_um: (0..nl)
                .map(|k| (l.radius + after[k] / count[k].max(1) as f64 - r_ref) * 1e3)
                .collect(),
            radius_error_at_zero_um: if l.sphere {
                [(rho0 - r_ref) * 1e3, rho0_sigma * 1e3]
            } else {
                [0.0, 0.0]
            },
            static_form_um: form * 1e3,
            fit_rms_um: stat.sqrt() * 1e3,
        });
    }
    // Each tip's radius at zero force: the calibration's radius plus the sphere's zero-force
    // radius error (the corrector puts the surface a tip radius from the tip centre), mean
    // over the tip's settings.
    let mut calibration = start.clone();
    let mut tip_shift: BTreeMap<u32, f64> = BTreeMap::new();
    for &t in &tips {
        let ss: Vec<&Setting> = settings
            .iter()
            .filter(|s| s.tip == t && s.sphere_fitted)
            .collect();
        if ss.is_empty() {
            undetermined.push(format!(
                "tip{t}.radius_at_zero_force_mm: the scans cover too little of the sphere to \
                 fit it — scan circles (variants a–c) for the tip's radius"
            ));
            continue;
        }
        let Some(g) = calibration.geometry.tips.iter_mut().find(|g| g.id == t) else {
            continue;
        };
        let n = ss.len() as f64;
        let e = ss.iter().map(|s| s.radius_error_at_zero_um[0]).sum::<f64>() / n * 1e-3;
        let v = ss
            .iter()
            .map(|s| (s.radius_error_at_zero_um[1] * 1e-3).powi(2))
            .sum::<f64>()
            / (n * n);
        g.radius_mm += e;
        tip_shift.insert(t, e);
        params.push(Param {
            name: format!("tip{t}.radius_at_zero_force_mm"),
            value: g.radius_mm,
            sigma: v.sqrt(),
        });
    }
    // The static map of each circle at its knots: mean radius plus harmonics, with the σ of
    // that linear combination of the circle's columns.
    let mut static_maps = vec![];
    for ((gi, _, _), &c) in &circles {
        let (gi, g) = (*gi, &groups[*gi]);
        if !lin[gi].sphere {
            continue;
        }
        let k0 = n_dense + DRIFT * n_circles + per_circle * c;
        let members: Vec<usize> = g
            .idx
            .iter()
            .copied()
            .filter(|&i| circle_of[i] == c)
            .collect();
        let lat = members
            .iter()
            .map(|&i| dir(gi, i).z.clamp(-1.0, 1.0).asin())
            .sum::<f64>()
            / members.len().max(1) as f64;
        let mut segments: Vec<u32> = members.iter().map(|&i| ds.points[i].segment).collect();
        segments.sort_unstable();
        segments.dedup();
        let (mut th_deg, mut val, mut unc) = (vec![], vec![], vec![]);
        for j in 0..STATIC_KNOTS {
            let th = std::f64::consts::TAU * j as f64 / STATIC_KNOTS as f64;
            let mut w = vec![(k0, 1.0)];
            for h in 1..=harmonics {
                let a = h as f64 * th;
                w.push((k0 + 2 * h - 1, a.cos()));
                w.push((k0 + 2 * h, a.sin()));
            }
            let v: f64 = w.iter().map(|(col, f)| f * theta[*col]).sum();
            let cov = &sol.cov;
            let var: f64 = w
                .iter()
                .flat_map(|(a, fa)| w.iter().map(move |(b, fb)| fa * fb * cov[(*a, *b)]))
                .sum::<f64>()
                * sigma2;
            th_deg.push(th.to_degrees());
            val.push((lin[gi].radius + v - spheres[&g.feature]) * 1e3);
            unc.push(var.max(0.0).sqrt() * 1e3);
        }
        // Its place: the circle's carriage path (scales + deflection, where the corrector
        // takes the map's angle), the same at every deflection.
        let carr: Vec<Vec3> = members
            .iter()
            .map(|&i| ds.points[i].ctx.scale + ds.points[i].ctx.deflection)
            .collect();
        let Ok(path) = shape::fit_circle(&carr) else {
            continue;
        };
        let z = carr.iter().map(|p| p.z).sum::<f64>() / carr.len() as f64;
        let shift = tip_shift.get(&g.tip).copied().unwrap_or(0.0);
        let stored = feature_map::Config {
            id: Some(format!(
                "static_map_tip{}_lat{:.0}_s{}",
                g.tip,
                lat.to_degrees(),
                segments.first().copied().unwrap_or(0)
            )),
            feature: Some(format!(
                "master sphere, tip {} at head ({}, {})°, circle at latitude {:+.1}°: its error \
                 at zero force (calibrate probe-force)",
                g.tip,
                g.head[0],
                g.head[1],
                lat.to_degrees()
            )),
            segments: segments.clone(),
            tip: g.tip,
            head_deg: g.head,
            speed_mm_s: None,
            speed_tolerance_mm_s: None,
            center_mm: [path.center.x, path.center.y],
            radius_mm: Some(path.radius),
            z_mm: Some(z),
            place_tolerance_mm: 1.0,
            latitude_deg: lat.to_degrees(),
            values_mm: val.iter().map(|v| -(v * 1e-3 - shift)).collect(),
            per_deflection: vec![],
            deflection_mm: None,
            values_u_mm: unc.iter().map(|u| u * 1e-3).collect(),
        };
        if stored.build().is_err() {
            continue;
        }
        static_maps.push(StaticMap {
            tip: g.tip,
            head_deg: g.head,
            latitude_deg: lat.to_degrees(),
            segments,
            theta_deg: th_deg,
            radial_um: val,
            radial_u_um: unc,
            stored,
        });
    }
    // The real-time form on the scans whose deflection varies within them (`real_time`).
    let point_sigma = (point_var * inflate).sqrt();
    let mut real_time = vec![];
    for (gi, g) in groups.iter().enumerate() {
        let mut by_seg: BTreeMap<u32, Vec<usize>> = BTreeMap::new();
        for &i in &g.idx {
            by_seg.entry(ds.points[i].segment).or_default().push(i);
        }
        for (seg, idx) in by_seg {
            let defl = |i: usize| ds.points[i].ctx.deflection_probe.norm();
            let d: Vec<f64> = idx.iter().map(|&i| defl(i)).collect();
            let Some(pct) = real_time::varying(&d) else {
                continue;
            };
            let pts: Vec<real_time::Point> = idx
                .iter()
                .map(|&i| {
                    let n = dir(gi, i);
                    let y = row(gi, i, &mut dense, &mut r, &mut sparse);
                    let force = force_of(&dense);
                    let e = residual(gi, i, &theta, &mut dense, &mut r, &mut sparse);
                    real_time::Point {
                        theta: n.y.atan2(n.x),
                        latitude: n.z.clamp(-1.0, 1.0).asin(),
                        f: defl(i),
                        y,
                        model: y + force - e,
                        bending: -force,
                        t_ns: ds.points[i].ctx.t_ns,
                        accel: n.dot(&ds.points[i].ctx.est_acc),
                    }
                })
                .collect();
            real_time.push(real_time::scan(g.tip, g.head, seg, &pts, pct, point_sigma));
        }
    }
    let mut notes = vec![
        "the radii at zero force carry every radial error of these circles that does not \
         change with the deflection (the machine's geometry at the sphere, its dynamics at this \
         speed): their σ is the statistical part only; the force coefficients are free of it"
            .to_string(),
    ];
    let n_free = (0..n_circles)
        .filter(|&c| free_drift[c] && !position_only[c])
        .count();
    let n_repeated = repeated.iter().filter(|&&r| r).count();
    let n_single = (0..n_circles)
        .filter(|&c| !repeated[c] && !partial_scans[c].is_empty() && !position_only[c])
        .count();
    if n_repeated > 0 {
        notes.push(format!(
            "{n_repeated} circle(s) with part-turn scans that repeat one deflection around \
             another (A-B-A): those scans' drift has its own offset and rate, told from the \
             force by the repeat; the force coefficients come from them, the full turn carries \
             the static map round the circle"
        ));
    }
    if n_single > 0 {
        notes.push(format!(
            "confounded: {n_single} circle(s) have part-turn scans that do not repeat a \
             deflection around another: over part of a turn the sphere's drift (the room \
             warming the scales, n·Ċ·t) has nearly the force's shape, so the drift and the \
             coefficient of the axis the part turns towards (k_v over a quarter from X to Y) \
             trade against each other and their σ understates it; scan the part twice at one \
             deflection around a scan at another (e.g. 0.1, 0.5, 0.1 mm: `sim --program \
             probe-force-quarter`), or a whole turn at each deflection"
        ));
    }
    notes.push(if n_free == 0 {
        "the sphere's drift while each circle is scanned is the styli's and the scales' \
         expansion from their sensors (coefficients fitted with the force)"
            .to_string()
    } else if sensors_drift {
        format!(
            "{n_free} circle(s) with a scan that does not go round them whole get a free linear \
             drift beside the sensors' expansion (over part of a turn the sensors' columns and \
             the force are nearly one)"
        )
    } else {
        "the bags carry no stylus and scale temperature sensors: each circle's drift is free \
         and linear in time"
            .to_string()
    });
    if opts.steady_only {
        notes.push(
            "only points at each scan's programmed speed are used (no dwell, spin-up or \
             slow-down): every deflection is compared at the same kinematic state"
                .to_string(),
        );
    }
    // The compliance as a nuisance: the largest shift it could give a force coefficient.
    let compliance_text = compliance_prior.map(|sc| {
        let worst = shifts[..3]
            .iter()
            .flat_map(|(su, d)| (0..n_force).map(move |c| (su * d[c]).abs()))
            .fold(0.0, f64::max);
        format!(
            "the structure's compliance under the carriage's acceleration is taken as 0 ± {:.0} \
             µm per m/s² per axis (a bridge CMM's) and not fitted (the scans cannot tell it from \
             the force): it is in the coefficients' σ, up to {worst:.6} of one",
            sc * 1e6
        )
    });
    // A wave of the deflection accelerates the carriage in phase with it: unless the start
    // corrects the compliance, a typical one biases the coefficients by C·(a per d).
    if let Some(worst) = real_time
        .iter()
        .map(|rt| rt.accel_per_deflection_s2.abs())
        .max_by(|a, b| a.total_cmp(b))
    {
        let bias = TYPICAL_COMPLIANCE_S2 * worst;
        let sigma_k = params
            .iter()
            .filter(|p| p.name.contains(".probe_k_"))
            .map(|p| p.sigma)
            .fold(f64::INFINITY, f64::min);
        if compliance_corrected {
            notes.push(format!(
                "the deflection's waves accelerate the carriage by up to {worst:.1} mm/s² per mm \
                 of deflection; the start's accel_deflection corrects the structure's bending \
                 under it"
            ));
        } else if let Some(text) = &compliance_text {
            notes.push(format!(
                "the deflection's waves accelerate the carriage by up to {worst:.1} mm/s² per mm \
                 of deflection, in phase with the deflection (a compliance of 30 µm per m/s² \
                 would pass for {bias:.5} of force coefficient): {text}"
            ));
        } else if bias > sigma_k {
            notes.push(format!(
                "confounded: the deflection's waves accelerate the carriage by up to \
                 {worst:.1} mm/s² per mm of deflection, in phase with the deflection — a \
                 compliance of 30 µm per m/s² would shift the force coefficients by {bias:.5} \
                 (their σ: {sigma_k:.5}); slow the wave (fewer waves per turn, a slower scan) \
                 or calibrate dynamics first and start from its accel_deflection"
            ));
        } else {
            notes.push(format!(
                "the deflection's waves accelerate the carriage by up to {worst:.2} mm/s² per \
                 mm of deflection: a compliance of 30 µm per m/s² would shift the force \
                 coefficients by {bias:.6}, below their σ ({sigma_k:.5})"
            ));
        }
    }
    if let (Some(text), true) = (&compliance_text, real_time.is_empty()) {
        notes.push(text.clone());
    }
    // The scales' expansion as a nuisance on the part-turn circles: the largest shift it could
    // give a force coefficient.
    let n_scale_prior = scale_prior.iter().filter(|&&p| p).count();
    if let (Some(sp), true) = (scale_prior_col, n_scale_prior > 0) {
        let worst = nuisance
            .iter()
            .zip(&shifts)
            .filter(|((c, _), _)| (sp..sp + 3).contains(c))
            .flat_map(|(_, (su, d))| (0..n_force).map(move |c| (su * d[c]).abs()))
            .fold(0.0, f64::max);
        let source = if start.effects.iter().any(|e| e.kind() == "scale_thermal") {
            "10 % of the start's `scale_thermal` beyond it"
        } else {
            "the start corrects none: glass-ceramic to steel"
        };
        notes.push(format!(
            "{n_scale_prior} circle(s) with a part-turn scan: the scales' expansion there is not \
             fitted (beside their free drift its columns see only the temperatures' curvature) \
             but taken as α = 0 ± ({:.1}, {:.1}, {:.1}) ppm/K ({source}); its change over the \
             deflection's travel, α·(T − 20 °C)·Δd, has the force's form and is in the \
             coefficients' σ, up to {worst:.6} of one",
            scale_sigma[0] * 1e6,
            scale_sigma[1] * 1e6,
            scale_sigma[2] * 1e6
        ));
    }
    if groups.iter().any(|g| g.head != [0.0, 0.0]) {
        notes.push(
            "a tip measured at several head angles gets one coefficient triple in its probe \
             axes; the angles only add views of it"
                .into(),
        );
    }
    let k_machine = start_k.as_ref().map_or_else(
        || per_tip.values().next().copied().unwrap_or([0.0; 3]),
        |c| c.k,
    );
    let effect = EffectConfig::ProbeForce(probe_force::Config {
        id: start_k.as_ref().and_then(|c| c.id.clone()),
        k: k_machine,
        per_tip: start_k
            .map(|c| c.per_tip)
            .unwrap_or_default()
            .into_iter()
            .chain(per_tip)
            .collect(),
    });
    match calibration
        .effects
        .iter_mut()
        .find(|e| e.kind() == "probe_force")
    {
        Some(e) => *e = effect,
        None => calibration.effects.push(effect),
    }
    // The static maps replace the start's static maps of the same scans.
    let maps: Vec<feature_map::Config> = static_maps.iter().map(|m| m.stored.clone()).collect();
    calibration.effects.retain(|e| match e {
        EffectConfig::FeatureMap(old) => !maps.iter().any(|n| n.replaces(old)),
        _ => true,
    });
    calibration
        .effects
        .extend(maps.into_iter().map(EffectConfig::FeatureMap));
    if !static_maps.is_empty() {
        notes.push(
            "each circle's static error map is stored as a `feature_map` (at every speed, at \
             the circle's place, for its segments and tip): a later scan of that circle by the \
             same program is corrected by it, apart from the machine's geometry; a dynamic map \
             of the same scan adds to it"
                .to_string(),
        );
    }
    Ok(Outcome {
        calibration,
        params,
        settings,
        rms_before_um: (ss_before / n_rows.max(1) as f64).sqrt() * 1e3,
        rms_after_um: (ss_after / n_rows.max(1) as f64).sqrt() * 1e3,
        cell_chi2: chi2_red,
        static_maps,
        real_time,
        undetermined,
        notes,
    })
}

/// The σ of the scales' expansion coefficients beyond what the start corrects, per axis (1/K):
/// 10 % of the start's `scale_thermal` coefficients (as `dynamic-map` takes them), else 12 ppm/K
/// about zero (as `tips` takes them: glass-ceramic to steel, aluminium at 2σ).
fn scale_alpha_sigma(start: &Calibration) -> [f64; 3] {
    start
        .effects
        .iter()
        .find_map(|e| match e {
            EffectConfig::ScaleThermal(c) => Some(
                c.alpha_per_k
                    .map(|a| super::dynamic_map::ALPHA_SHARE * a.abs()),
            ),
            _ => None,
        })
        .unwrap_or([super::tips::SCALE_ALPHA_PRIOR_PER_K; 3])
}

/// Solves `ne` with every column that carries no information (all zero: a position's unused
/// harmonics and drift, a coefficient not determined) set to the identity, and how many. The
/// eigen-decomposition of a matrix with many exactly zero rows can fail outright (every
/// eigenvalue NaN), which left every coefficient 0 ± 0 on some runs of the approaches.
fn solve_padded(ne: &Normal) -> (crate::lab::fit::Solved, usize) {
    let mut n = ne.clone();
    let mut pad = 0;
    for c in 0..n.b.len() {
        if n.m[(c, c)] == 0.0 {
            n.m[(c, c)] = 1.0;
            pad += 1;
        }
    }
    (n.solve(), pad)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn deflection_levels_cluster_and_assign() {
        let l = levels(vec![0.31, 0.1, 0.29, 0.5, 0.11, 0.49, 0.3]);
        assert_eq!(l.len(), 3);
        assert!((l[0] - 0.105).abs() < 1e-9 && (l[2] - 0.495).abs() < 1e-9);
        assert_eq!(level_of(&l, 0.33), 1);
        assert_eq!(levels(vec![0.3, 0.31, 0.29]).len(), 1);
    }
}
