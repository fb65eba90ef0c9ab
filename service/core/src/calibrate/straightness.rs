//! `straightness`: error separation — the straightness (and pitch) of a guide and the
//! straightness of a part (a straightedge) from the same readings, without a perfect
//! reference. The math only, on already-averaged station readings ([`average_samples`] turns
//! a station's raw samples into one).
//!
//! Model. x runs along the travel. At station K the carriage stands at x_K; a probe at
//! x_K + s on the carriage reads its distance to the part,
//!
//! m = Y(x_K + s) − X_K − θ_K·(s − c) + o + ε,
//!
//! Y the part's straightness, X_K the carriage's lateral motion (the guide's straightness)
//! at its pitch centre x_K + c, θ_K its pitch (rad), o the probe's zero offset, ε the noise
//! (standard error u, the reading's). Every method below is linear in the readings.
//!
//! * [`three_probe`] — sequential three-point method with pitch. Probes A, B, C at
//!   s = 0, l, 2l, pitch centre c = l (probe B); the carriage steps by l, so station K's probe
//!   j sees part point K + j (part positions x_0 + i·l, i = 0 … N+1). The second difference
//!   removes the carriage: d_K = m_A − 2m_B + m_C = Y_K − 2Y_{K+1} + Y_{K+2} + δ,
//!   δ = o_A − 2o_B + o_C; so Y_{K+2} = 2Y_{K+1} − Y_K + (d_K − δ) from Y_0 = Y_1 = 0, and then
//!   X_K, θ_K from the station's three readings by weighted least squares,
//!   m_j − Y_{K+j} − ô_j = −X_K − θ_K·(j − 1)·l, ô = (0, −δ/2, 0). The offsets are zero after
//!   zeroing (δ = 0); a δ left in them adds the parabola δ/(2l²)·(x − x_0)² to part and guide
//!   alike and its slope, δ/l²·(x − x_0), to the pitch, which no reading reveals. A
//!   **reversal** (the straightedge turned over about its length over the same stations:
//!   Y → −Y, its carriage motion free) reads
//!   d'_K = −Δ²Y_K + δ, and the least squares over both runs (each station's X, θ
//!   eliminated) is δ̂ = Σ_K (d_K + d'_K)/(v_K + v'_K) / (2·Σ_K 1/(v_K + v'_K)),
//!   Δ²Y_K = [(d_K − δ̂)/v_K − (d'_K − δ̂)/v'_K] / (1/v_K + 1/v'_K), v = u_A² + 4u_B² + u_C².
//!   The unknown start values (Y_0 and the slope, i.e. X_1 and 2Y_1 − Y_2) are the line,
//!   fixed by least squares: the part is reported as its deviation from its least-squares
//!   line, the guide from its own, the pitch about its mean (a tilt of the straightedge and a
//!   slope of the offsets, (o_C − o_A)/(2l), are a constant pitch).
//! * [`two_probe`] — sequential two-point method, no pitch. Probes A, B at s = 0, l:
//!   Y_{K+1} − Y_K = m_B(K) − m_A(K) (cumulative sum from Y_0 = 0), X_K = Y_K − m_A(K), lines
//!   removed. A pitch θ_K (about A) is not separated: it adds −θ_K·l to the part's step, so
//!   the part carries −l·Σ_{k<i} θ_k and the guide the same at its stations.
//! * [`shear_stage`] — one probe on a shear micro-stage whose own sensor gives the true shear
//!   s (the probe spacing) in real time; at each station the stage sets ≥ 2 shears. The
//!   stage travels at a small angle e to the guide's normal, adding e·s to a reading: with
//!   the pitch, a per-station slope φ_K = θ_K − e (pitch centre at s = 0). (a) Shears {0, l}
//!   with the carriage stepping by l: the sequential two-point method above. (b, c) Otherwise
//!   one weighted least squares over all readings: the part on a grid of nodes
//!   x_0 + i·h (h the station step unless given), each reading
//!   m = Σ_n w_n(x_K + s)·Y_n − X_K − φ_K·s, w the linear interpolation between the two
//!   nodes around x_K + s (exactly one node when the position is on the grid: the exact
//!   three-point reconstruction with shears {0, l, 2l} or {−l, 0, l}, nothing smoothed);
//!   φ_K is fitted when every station has ≥ 3 distinct shears. The null space (the line:
//!   Y += a + b·x, X += a + b·x_K, φ += b; without pitch only the constant) is fixed by a
//!   penalty on it alone, M = AᵀWA + λ·VVᵀ, which leaves every reported (line-free) output
//!   the least-squares one; any other pattern the readings cannot determine is refused
//!   (smallest eigenvalue of the scaled normal matrix). The perpendicular error e is a
//!   constant slope: it goes out with the line, exactly (the outputs do not change with e).
//!   One probe has one offset, a constant: no parabola.
//!
//! Uncertainties. With the weights fixed by the readings' standard errors, every output is a
//! linear map of the readings; the map's response to each reading is computed (the same
//! recursion or solve on a unit reading) and σ_i² = Σ_r (∂out_i/∂m_r)²·u_r², scaled by the
//! reduced χ² when the readings are redundant and it exceeds 1. The sequential methods
//! integrate: their σ grow along the travel, as the errors do.
//!
//! Source idea: the sequential three-point straightness method with pitch (Mitsubishi Heavy
//! Industries, Tanaka et al., CIRP Annals 1981), the sequential two-point method, reversal
//! to separate the probes' zero offsets, and single-probe error separation on a shear
//! micro-stage (NUDT): the sheared readings of one probe stand in for a multi-probe head,
//! the stage's sensor giving the spacing.

use super::{Param, ProcedureError};
use nalgebra::DMatrix;
use serde::{Deserialize, Serialize};

/// Stations of a method without a stage sensor must step by the probe spacing within this
/// fraction of it (a step error δ puts the part's slope times δ into the separation).
pub const STEP_TOLERANCE: f64 = 0.01;
/// Shear-stage positions within this fraction of the grid pitch count as one shear (and as
/// "shear = step" for the sequential two-point form).
pub const SHEAR_TOLERANCE: f64 = 1e-3;
/// Shear-stage positions up to this fraction of the grid pitch beyond the first or last node
/// are extrapolated from the end interval (no node of their own).
const END_REACH: f64 = 0.25;
/// Shear readings whose carriage positions differ by less than this belong to one station, mm.
pub const STATION_TOLERANCE_MM: f64 = 1e-3;
/// Least stations of every method: the line (two values) comes out, the guide needs a third.
pub const MIN_STATIONS: usize = 3;
/// A scaled normal-matrix eigenvalue below this fraction of the largest is a pattern the
/// readings do not determine.
const EIGEN_FLOOR: f64 = 1e-13;
/// Largest number of unknowns (grid nodes + stations × (1 or 2)) of the shear stage's dense
/// least squares (its cost grows with the cube).
pub const MAX_UNKNOWNS: usize = 2500;
/// Samples farther than this many robust σ (1.4826·MAD) from the median are rejected.
const OUTLIER_SIGMAS: f64 = 5.0;
/// Least samples for the lag-1 correlation to inflate the standard error.
const MIN_SAMPLES_FOR_CORRELATION: usize = 10;
/// Largest lag-1 correlation used for the inflation.
const MAX_LAG1: f64 = 0.95;

const PROBES: [&str; 3] = ["A", "B", "C"];
const THREE_PROBE: &str = "three-probe sequential (with pitch)";
const TWO_PROBE: &str = "two-probe sequential";

/// One averaged reading: a probe's distance to the part, with its standard error.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Reading {
    /// Mean reading, mm.
    pub value_mm: f64,
    /// Standard error of the mean (1σ), mm; must be > 0.
    pub u_mm: f64,
}

/// The probes' readings at one carriage station (multi-probe methods).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StationReading {
    /// Carriage position x_K (of probe A), mm.
    pub x_mm: f64,
    /// One entry per probe, A first; `None` where the probe gave no reading.
    pub readings: Vec<Option<Reading>>,
}

/// How the probes sit on the carriage: in a row along the travel, equally spaced.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ProbeMount {
    /// Distance l between neighbouring probes, mm; the carriage steps by it.
    pub spacing_mm: f64,
}

/// One reading of the single probe on the shear stage.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ShearReading {
    /// Carriage position x_K, mm (the same for every shear of a station).
    pub x_mm: f64,
    /// Shear s from the stage's own sensor, mm, along the travel (negative: against it).
    pub shear_mm: f64,
    /// Mean reading, mm.
    pub value_mm: f64,
    /// Standard error of the mean, mm; must be > 0.
    pub u_mm: f64,
}

/// Options of [`shear_stage`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct ShearOptions {
    /// Grid pitch h of the part profile, mm; default the median step between stations.
    pub grid_mm: Option<f64>,
}

/// The separated profiles. Straightness is the deviation from the least-squares line of
/// each profile; the pitch is about its mean.
#[derive(Debug, Clone, Serialize)]
pub struct Separation {
    /// Which method and form produced it.
    pub method: String,
    /// Carriage positions x_K, mm.
    pub stations_mm: Vec<f64>,
    /// Guide straightness X_K at each station (the carriage's lateral motion at its pitch
    /// centre: probe B for three probes, probe A for two, the zero shear for the stage), mm.
    pub guide_straightness_mm: Vec<f64>,
    /// Its standard uncertainty, mm.
    pub guide_straightness_mm_u: Vec<f64>,
    /// Part positions, mm: x_0 + i·l for the probe methods (the stations plus one or two
    /// beyond the last), the grid nodes for the shear stage's least squares.
    pub part_positions_mm: Vec<f64>,
    /// Part straightness at `part_positions_mm`, mm.
    pub part_straightness_mm: Vec<f64>,
    /// Its standard uncertainty, mm.
    pub part_straightness_mm_u: Vec<f64>,
    /// Pitch θ_K about its mean, rad, where the method separates it.
    pub pitch_rad: Option<Vec<f64>>,
    /// Its standard uncertainty, rad.
    pub pitch_rad_u: Option<Vec<f64>>,
    /// What the method cannot see: `line` (a line common to part and guide; its slope is a
    /// constant pitch), `parabola` (a parabola common to part and guide, its slope in the pitch:
    /// the probes' offsets' second difference), `pitch` (not
    /// separated at all), `pitch_constant` (the mean pitch).
    pub cannot_see: Vec<String>,
    /// Reduced χ² of redundant readings (None when they determine the profiles exactly).
    pub chi2_reduced: Option<f64>,
    /// Scalars the method estimated on the way (the offsets' second difference, …).
    pub params: Vec<Param>,
    /// Remarks: conventions, what leaks into the profiles, how to see more.
    pub notes: Vec<String>,
}

/// A station reading averaged from raw samples.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Averaged {
    /// Mean and standard error.
    pub reading: Reading,
    /// Samples averaged.
    pub used: usize,
    /// Samples rejected (non-finite, or outliers farther than 5 robust σ from the median).
    pub rejected: usize,
}

/// Averages raw samples (one value per sample, mm, in time order) into a station reading,
/// robustly: non-finite samples and outliers beyond 5·1.4826·MAD of the median are dropped
/// (no rejection when the MAD is zero), the standard error s/√n is inflated by
/// √((1 + ρ)/(1 − ρ)) for a positive lag-1 correlation ρ (≥ 10 samples, ρ ≤ 0.95). It is
/// zero when all samples are equal: give the probe's resolution/√12 instead, the procedures
/// refuse a zero standard error.
pub fn average_samples(samples: &[f64]) -> Result<Averaged, ProcedureError> {
    let finite: Vec<f64> = samples.iter().copied().filter(|v| v.is_finite()).collect();
    if finite.len() < 2 {
        return Err(ProcedureError::Missing(format!(
            "{} finite samples ({} given): a station reading needs at least 2, its standard \
             error comes from their scatter — record more samples at the station",
            finite.len(),
            samples.len()
        )));
    }
    let med = median(&finite);
    let dev: Vec<f64> = finite.iter().map(|v| (v - med).abs()).collect();
    let robust_sigma = 1.4826 * median(&dev);
    let kept: Vec<f64> = if robust_sigma > 0.0 {
        finite
            .iter()
            .copied()
            .filter(|v| (v - med).abs() <= OUTLIER_SIGMAS * robust_sigma)
            .collect()
    } else {
        finite
    };
    let n = kept.len();
    let mean = kept.iter().sum::<f64>() / n as f64;
    let ss: f64 = kept.iter().map(|v| (v - mean).powi(2)).sum();
    let var = ss / (n - 1) as f64;
    let mut inflation = 1.0;
    if n >= MIN_SAMPLES_FOR_CORRELATION && ss > 0.0 {
        let lag: f64 = kept.windows(2).map(|w| (w[0] - mean) * (w[1] - mean)).sum();
        let rho = (lag / ss).min(MAX_LAG1);
        if rho > 0.0 {
            inflation = (1.0 + rho) / (1.0 - rho);
        }
    }
    Ok(Averaged {
        reading: Reading {
            value_mm: mean,
            u_mm: (var / n as f64 * inflation).sqrt(),
        },
        used: n,
        rejected: samples.len() - n,
    })
}

fn median(v: &[f64]) -> f64 {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    let n = s.len();
    if n % 2 == 1 {
        s[n / 2]
    } else {
        0.5 * (s[n / 2 - 1] + s[n / 2])
    }
}

/// Sequential three-probe separation with pitch (probes A, B, C at 0, l, 2l; pitch about B),
/// optionally with a reversal run (the straightedge turned over about its length, the same
/// stations) that removes the parabola of the probes' offsets.
pub fn three_probe(
    mount: &ProbeMount,
    stations: &[StationReading],
    reversal: Option<&[StationReading]>,
) -> Result<Separation, ProcedureError> {
    let l = spacing(mount)?;
    let main = flatten("measurement", stations, 3, THREE_PROBE)?;
    check_steps("measurement", &main.xs, l)?;
    let n = main.xs.len();
    let rev = match reversal {
        None => None,
        Some(r) => {
            let rv = flatten("reversal", r, 3, THREE_PROBE)?;
            if rv.xs.len() != n {
                return Err(ProcedureError::Missing(format!(
                    "the reversal has {} stations, the measurement {n}: the reversal must \
                     repeat every station of the measurement (the straightedge turned over \
                     about its length, the carriage at the same positions)",
                    rv.xs.len()
                )));
            }
            for (k, (a, b)) in main.xs.iter().zip(&rv.xs).enumerate() {
                if (a - b).abs() > STEP_TOLERANCE * l {
                    return Err(ProcedureError::IllConditioned(format!(
                        "reversal station {k} is at x = {b:.4} mm, the measurement's at \
                         {a:.4} mm: the reversal must repeat the measurement's stations \
                         (within {:.4} mm)",
                        STEP_TOLERANCE * l
                    )));
                }
            }
            Some(rv)
        }
    };
    let model = ThreeProbe::new(n, l, &main.u, rev.as_ref().map(|r| r.u.as_slice()));
    let mut values = main.values.clone();
    let mut u = main.u.clone();
    if let Some(r) = &rev {
        values.extend_from_slice(&r.values);
        u.extend_from_slice(&r.u);
    }
    let lay = Layout {
        part_pos: (0..n + 2).map(|i| main.xs[0] + i as f64 * l).collect(),
        stations: main.xs.clone(),
    };
    let (estimate, delta) = model.solve(&values);
    let mut notes = vec![
        "guide: the carriage's lateral motion at probe B (the pitch centre), listed at the \
         carriage positions x_K (probe A's); part positions x_0 + i·l, i = 0 … N+1"
            .to_string(),
        "pitch about its mean: a constant pitch is a tilt of the straightedge, or a slope \
         (o_C − o_A)/(2l) of the probes' zero offsets"
            .to_string(),
    ];
    let mut params = vec![];
    let (scale, chi2) = match &rev {
        None => {
            let span = (n + 1) as f64;
            notes.push(format!(
                "the probes' zero offsets are taken as zero: a second difference \
                 δ = o_A − 2o_B + o_C left in them adds δ/(2l²)·(x − x_0)² to part and guide \
                 alike, and δ/l²·(x − x_0) to the pitch (0.1 µm of δ is a bow of {:.3} µm \
                 peak-to-valley over this travel) — \
                 add a reversal measurement to separate it",
                0.1 * span * span / 8.0
            ));
            (1.0, None)
        }
        Some(_) => {
            let (chi2, dof, sigma) = model.reversal_fit(&values, delta);
            let red = chi2 / dof as f64;
            let scale = red.max(1.0);
            params.push(Param {
                name: "probe_offsets.second_difference_mm".into(),
                value: delta,
                sigma: sigma * scale.sqrt(),
            });
            notes.push(format!(
                "reversal: the probes' offsets' second difference δ = o_A − 2o_B + o_C = \
                 {:.5} ± {:.5} µm, removed (reduced χ² {red:.2} over {dof} degrees of freedom)",
                delta * 1e3,
                sigma * scale.sqrt() * 1e3
            ));
            (scale, Some(red))
        }
    };
    let mut unit = vec![0.0; values.len()];
    let (est, sig) = propagate(&lay, estimate, &u, scale, |r| {
        unit[r] = 1.0;
        let out = model.solve(&unit).0;
        unit[r] = 0.0;
        out
    });
    let mut cannot = vec!["line", "pitch_constant"];
    if rev.is_none() {
        cannot.push("parabola");
    }
    let method = if rev.is_some() {
        format!("{THREE_PROBE}, with reversal")
    } else {
        THREE_PROBE.to_string()
    };
    output(method, lay, est, sig, &cannot, chi2, params, notes)
}

/// Sequential two-probe separation (probes A, B at 0, l): no pitch.
pub fn two_probe(
    mount: &ProbeMount,
    stations: &[StationReading],
) -> Result<Separation, ProcedureError> {
    let l = spacing(mount)?;
    let main = flatten("measurement", stations, 2, TWO_PROBE)?;
    check_steps("measurement", &main.xs, l)?;
    two_probe_core(l, &main, TWO_PROBE.to_string())
}

/// Single-probe separation on a shear micro-stage: the sequential two-point form when every
/// station has the shears {0, step}, otherwise the least squares on a grid (pitch separated
/// when every station has ≥ 3 distinct shears).
pub fn shear_stage(
    readings: &[ShearReading],
    options: &ShearOptions,
) -> Result<Separation, ProcedureError> {
    for (i, r) in readings.iter().enumerate() {
        let fields = [r.x_mm, r.shear_mm, r.value_mm, r.u_mm];
        if fields.iter().any(|v| !v.is_finite()) {
            return Err(ProcedureError::Missing(format!(
                "shear reading {i} (x = {} mm, shear = {} mm) is not finite (value {}, u {}): \
                 re-measure it or leave it out",
                r.x_mm, r.shear_mm, r.value_mm, r.u_mm
            )));
        }
        if r.u_mm <= 0.0 {
            return Err(ProcedureError::Missing(format!(
                "shear reading {i} (x = {:.4} mm, shear = {:.4} mm) has standard error {} mm: \
                 it must be positive (at least the probe's resolution/√12)",
                r.x_mm, r.shear_mm, r.u_mm
            )));
        }
    }
    let mut order: Vec<usize> = (0..readings.len()).collect();
    order.sort_by(|&a, &b| {
        (readings[a].x_mm, readings[a].shear_mm)
            .partial_cmp(&(readings[b].x_mm, readings[b].shear_mm))
            .unwrap_or(std::cmp::Ordering::Equal)
    });
    // Stations: runs of carriage positions within STATION_TOLERANCE_MM.
    let mut groups: Vec<Vec<usize>> = vec![];
    for &i in &order {
        match groups.last_mut() {
            Some(g) if (readings[i].x_mm - readings[g[0]].x_mm).abs() <= STATION_TOLERANCE_MM => {
                g.push(i)
            }
            _ => groups.push(vec![i]),
        }
    }
    let ns = groups.len();
    if ns < MIN_STATIONS {
        return Err(ProcedureError::Missing(format!(
            "the shear-stage separation needs at least {MIN_STATIONS} carriage stations (the \
             line of part and guide is removed, the guide needs a third), the readings have \
             {ns}: measure more stations along the travel"
        )));
    }
    let xs: Vec<f64> = groups
        .iter()
        .map(|g| g.iter().map(|&i| readings[i].x_mm).sum::<f64>() / g.len() as f64)
        .collect();
    let steps: Vec<f64> = xs.windows(2).map(|w| w[1] - w[0]).collect();
    let step = median(&steps);
    let h = options.grid_mm.unwrap_or(step);
    if !(h.is_finite() && h > 0.0) {
        return Err(ProcedureError::IllConditioned(format!(
            "the grid pitch must be a positive length, got {h} mm: give `grid_mm` or leave it \
             to the station step"
        )));
    }
    let tol = SHEAR_TOLERANCE * h;
    let mut distinct = vec![];
    for (g, x) in groups.iter().zip(&xs) {
        let mut s: Vec<f64> = g.iter().map(|&i| readings[i].shear_mm).collect();
        s.sort_by(f64::total_cmp);
        s.dedup_by(|a, b| (*a - *b).abs() <= tol);
        if s.len() < 2 {
            return Err(ProcedureError::Missing(format!(
                "station x = {x:.4} mm has readings at a single shear ({:.4} mm): the \
                 single-probe method needs at least two shears per station (three to \
                 separate the pitch)",
                s[0]
            )));
        }
        distinct.push(s.len());
    }
    // (a) The sequential two-point form: shears {0, step}, the carriage stepping by it.
    let two_point = groups.iter().all(|g| g.len() == 2)
        && steps
            .iter()
            .all(|s| (s - step).abs() <= SHEAR_TOLERANCE * step)
        && groups.iter().all(|g| {
            let (a, b) = (readings[g[0]].shear_mm, readings[g[1]].shear_mm);
            a.abs() <= SHEAR_TOLERANCE * step && (b - step).abs() <= SHEAR_TOLERANCE * step
        });
    if two_point {
        let flat = Flat {
            xs: xs.clone(),
            values: groups
                .iter()
                .flat_map(|g| g.iter().map(|&i| readings[i].value_mm))
                .collect(),
            u: groups
                .iter()
                .flat_map(|g| g.iter().map(|&i| readings[i].u_mm))
                .collect(),
        };
        let mut sep = two_probe_core(
            step,
            &flat,
            "shear stage, sequential two-point (shear = step)".to_string(),
        )?;
        sep.notes[0] = "guide: the carriage's lateral motion at the probe's zero shear; part \
                        positions x_0 + i·l, i = 0 … N"
            .to_string();
        sep.notes.push(
            "the stage's perpendicular error e adds e·l to every step of the part: a line, \
             removed"
                .to_string(),
        );
        return Ok(sep);
    }
    let pitch = distinct.iter().all(|&d| d >= 3);
    let rows: Vec<(usize, f64, f64, f64)> = groups
        .iter()
        .enumerate()
        .flat_map(|(k, g)| {
            g.iter().map(move |&i| {
                let r = &readings[i];
                (k, r.shear_mm, r.value_mm, r.u_mm)
            })
        })
        .collect();
    shear_least_squares(&xs, &rows, h, pitch)
}

// ---------------------------------------------------------------------------------------
// Internals.

/// Station readings flattened station-major.
struct Flat {
    xs: Vec<f64>,
    values: Vec<f64>,
    u: Vec<f64>,
}

/// Profiles of a linear estimate before (or after) the unseen line and constant are removed.
#[derive(Clone)]
struct Raw {
    part: Vec<f64>,
    guide: Vec<f64>,
    pitch: Option<Vec<f64>>,
}

/// Where the profiles live.
struct Layout {
    part_pos: Vec<f64>,
    stations: Vec<f64>,
}

fn spacing(mount: &ProbeMount) -> Result<f64, ProcedureError> {
    let l = mount.spacing_mm;
    if !(l.is_finite() && l > 0.0) {
        return Err(ProcedureError::IllConditioned(format!(
            "the probe spacing must be a positive length, got {l} mm: give the distance \
             between neighbouring probes"
        )));
    }
    Ok(l)
}

fn flatten(
    run: &str,
    stations: &[StationReading],
    probes: usize,
    method: &str,
) -> Result<Flat, ProcedureError> {
    if stations.len() < MIN_STATIONS {
        return Err(ProcedureError::Missing(format!(
            "the {method} method needs at least {MIN_STATIONS} stations (the line of part and \
             guide is removed, the guide needs a third), the {run} has {}: measure more \
             stations along the travel",
            stations.len()
        )));
    }
    let mut flat = Flat {
        xs: vec![],
        values: vec![],
        u: vec![],
    };
    for (k, st) in stations.iter().enumerate() {
        if !st.x_mm.is_finite() {
            return Err(ProcedureError::Missing(format!(
                "{run} station {k}: its position is not finite ({}); give the carriage \
                 position",
                st.x_mm
            )));
        }
        if st.readings.len() != probes {
            return Err(ProcedureError::Missing(format!(
                "{run} station {k} (x = {:.4} mm) has {} probe readings; the {method} method \
                 needs {probes} (probes {}) at every station",
                st.x_mm,
                st.readings.len(),
                PROBES[..probes].join(", ")
            )));
        }
        for (j, r) in st.readings.iter().enumerate() {
            let Some(r) = r else {
                return Err(ProcedureError::Missing(format!(
                    "{run} station {k} (x = {:.4} mm): probe {} has no reading; the \
                     sequential method needs every probe at every station — re-measure it",
                    st.x_mm, PROBES[j]
                )));
            };
            if !(r.value_mm.is_finite() && r.u_mm.is_finite()) {
                return Err(ProcedureError::Missing(format!(
                    "{run} station {k} (x = {:.4} mm): probe {}'s reading is not finite \
                     (value {}, u {}) — re-measure it",
                    st.x_mm, PROBES[j], r.value_mm, r.u_mm
                )));
            }
            if r.u_mm <= 0.0 {
                return Err(ProcedureError::Missing(format!(
                    "{run} station {k} (x = {:.4} mm): probe {}'s standard error is {} mm; it \
                     must be positive (at least the probe's resolution/√12)",
                    st.x_mm, PROBES[j], r.u_mm
                )));
            }
            flat.values.push(r.value_mm);
            flat.u.push(r.u_mm);
        }
        flat.xs.push(st.x_mm);
    }
    Ok(flat)
}

fn check_steps(run: &str, xs: &[f64], l: f64) -> Result<(), ProcedureError> {
    for k in 1..xs.len() {
        let step = xs[k] - xs[k - 1];
        if (step - l).abs() > STEP_TOLERANCE * l {
            return Err(ProcedureError::IllConditioned(format!(
                "the {run}'s stations must step by the probe spacing l = {l} mm (within \
                 {:.4} mm): station {k} at x = {:.4} mm is {step:.4} mm after station {} — \
                 without a stage sensor the sequential method needs the carriage to advance \
                 by one probe spacing per station; re-measure at steps of l (stations in \
                 increasing x), or use a shear stage whose sensor gives the true spacing",
                STEP_TOLERANCE * l,
                xs[k],
                k - 1
            )));
        }
    }
    Ok(())
}

/// Least-squares line removed (unweighted, the straightness reference line).
fn detrend(pos: &[f64], y: &mut [f64]) {
    let n = pos.len() as f64;
    if pos.is_empty() {
        return;
    }
    let pm = pos.iter().sum::<f64>() / n;
    let ym = y.iter().sum::<f64>() / n;
    let sxx: f64 = pos.iter().map(|p| (p - pm).powi(2)).sum();
    let sxy: f64 = pos
        .iter()
        .zip(y.iter())
        .map(|(p, v)| (p - pm) * (v - ym))
        .sum();
    let b = if sxx > 0.0 { sxy / sxx } else { 0.0 };
    for (v, p) in y.iter_mut().zip(pos) {
        *v -= ym + b * (p - pm);
    }
}

impl Raw {
    /// Removes what the method cannot see: the part's and the guide's lines, the mean pitch.
    fn finish(mut self, lay: &Layout) -> Raw {
        detrend(&lay.part_pos, &mut self.part);
        detrend(&lay.stations, &mut self.guide);
        if let Some(p) = &mut self.pitch {
            let m = p.iter().sum::<f64>() / p.len().max(1) as f64;
            p.iter_mut().for_each(|v| *v -= m);
        }
        self
    }
}

/// The finished estimate and its σ: `response(r)` is the (unfinished) estimate from a unit
/// reading r, the linear map's column.
fn propagate(
    lay: &Layout,
    estimate: Raw,
    u: &[f64],
    scale: f64,
    mut response: impl FnMut(usize) -> Raw,
) -> (Raw, Raw) {
    let est = estimate.finish(lay);
    let mut var = Raw {
        part: vec![0.0; est.part.len()],
        guide: vec![0.0; est.guide.len()],
        pitch: est.pitch.as_ref().map(|p| vec![0.0; p.len()]),
    };
    let acc = |v: &mut [f64], g: &[f64], u2: f64| {
        v.iter_mut().zip(g).for_each(|(a, b)| *a += b * b * u2);
    };
    for (r, ur) in u.iter().enumerate() {
        let g = response(r).finish(lay);
        let u2 = ur * ur * scale;
        acc(&mut var.part, &g.part, u2);
        acc(&mut var.guide, &g.guide, u2);
        if let (Some(v), Some(gp)) = (&mut var.pitch, &g.pitch) {
            acc(v, gp, u2);
        }
    }
    let sqrt = |v: Vec<f64>| v.into_iter().map(f64::sqrt).collect::<Vec<_>>();
    let sig = Raw {
        part: sqrt(var.part),
        guide: sqrt(var.guide),
        pitch: var.pitch.map(sqrt),
    };
    (est, sig)
}

#[allow(clippy::too_many_arguments)]
fn output(
    method: String,
    lay: Layout,
    est: Raw,
    sig: Raw,
    cannot_see: &[&str],
    chi2_reduced: Option<f64>,
    params: Vec<Param>,
    notes: Vec<String>,
) -> Result<Separation, ProcedureError> {
    let finite = est
        .part
        .iter()
        .chain(&est.guide)
        .chain(&sig.part)
        .chain(&sig.guide)
        .chain(est.pitch.iter().flatten())
        .chain(sig.pitch.iter().flatten())
        .all(|v| v.is_finite())
        && params
            .iter()
            .all(|p| p.value.is_finite() && p.sigma.is_finite());
    if !finite {
        return Err(ProcedureError::IllConditioned(format!(
            "the {method} separation gave non-finite values: the readings' standard errors \
             span too many orders of magnitude to be weighted — check their u"
        )));
    }
    Ok(Separation {
        method,
        stations_mm: lay.stations,
        guide_straightness_mm: est.guide,
        guide_straightness_mm_u: sig.guide,
        part_positions_mm: lay.part_pos,
        part_straightness_mm: est.part,
        part_straightness_mm_u: sig.part,
        pitch_rad: est.pitch,
        pitch_rad_u: sig.pitch,
        cannot_see: cannot_see.iter().map(|s| s.to_string()).collect(),
        chi2_reduced,
        params,
        notes,
    })
}

/// The three-probe recursion with its fixed weights.
struct ThreeProbe {
    n: usize,
    l: f64,
    /// Main run's reading weights 1/u², station-major.
    w: Vec<f64>,
    /// Variance of each second difference, main run.
    v: Vec<f64>,
    /// Same, reversal run.
    v_rev: Option<Vec<f64>>,
}

fn second_difference_variances(u: &[f64]) -> Vec<f64> {
    u.chunks(3)
        .map(|c| c[0] * c[0] + 4.0 * c[1] * c[1] + c[2] * c[2])
        .collect()
}

fn second_differences(m: &[f64]) -> Vec<f64> {
    m.chunks(3).map(|c| c[0] - 2.0 * c[1] + c[2]).collect()
}

impl ThreeProbe {
    fn new(n: usize, l: f64, u: &[f64], u_rev: Option<&[f64]>) -> Self {
        ThreeProbe {
            n,
            l,
            w: u.iter().map(|v| 1.0 / (v * v)).collect(),
            v: second_difference_variances(u),
            v_rev: u_rev.map(second_difference_variances),
        }
    }

    /// The offsets' second difference from both runs (0 without a reversal).
    fn delta(&self, d: &[f64], dr: &[f64], vr: &[f64]) -> f64 {
        let (mut num, mut den) = (0.0, 0.0);
        for k in 0..self.n {
            let vv = self.v[k] + vr[k];
            num += (d[k] + dr[k]) / vv;
            den += 1.0 / vv;
        }
        num / (2.0 * den)
    }

    /// χ², degrees of freedom and σ of δ̂ of the reversal's redundancy.
    fn reversal_fit(&self, m: &[f64], delta: f64) -> (f64, usize, f64) {
        let vr = self.v_rev.as_ref().expect("reversal");
        let d = second_differences(&m[..3 * self.n]);
        let dr = second_differences(&m[3 * self.n..]);
        let (mut chi2, mut den) = (0.0, 0.0);
        for k in 0..self.n {
            let vv = self.v[k] + vr[k];
            chi2 += (d[k] + dr[k] - 2.0 * delta).powi(2) / vv;
            den += 1.0 / vv;
        }
        (chi2, self.n - 1, (1.0 / (4.0 * den)).sqrt())
    }

    /// Part (N+2 points), guide and pitch before the line comes out, and δ̂.
    fn solve(&self, m: &[f64]) -> (Raw, f64) {
        let n = self.n;
        let d = second_differences(&m[..3 * n]);
        let (s, delta) = match &self.v_rev {
            None => (d, 0.0),
            Some(vr) => {
                let dr = second_differences(&m[3 * n..]);
                let delta = self.delta(&d, &dr, vr);
                let s = (0..n)
                    .map(|k| {
                        let (a, b) = (1.0 / self.v[k], 1.0 / vr[k]);
                        ((d[k] - delta) * a - (dr[k] - delta) * b) / (a + b)
                    })
                    .collect();
                (s, delta)
            }
        };
        let mut y = vec![0.0; n + 2];
        for k in 0..n {
            y[k + 2] = 2.0 * y[k + 1] - y[k] + s[k];
        }
        let offsets = [0.0, -delta / 2.0, 0.0];
        let mut guide = Vec::with_capacity(n);
        let mut pitch = Vec::with_capacity(n);
        for k in 0..n {
            // m_j − Y_{K+j} − ô_j = −X − θ·(j − 1)·l, weighted least squares in (X, θ).
            let (mut s00, mut s01, mut s11, mut b0, mut b1) = (0.0, 0.0, 0.0, 0.0, 0.0);
            for j in 0..3 {
                let w = self.w[3 * k + j];
                let a = (j as f64 - 1.0) * self.l;
                let r = m[3 * k + j] - y[k + j] - offsets[j];
                s00 += w;
                s01 += w * a;
                s11 += w * a * a;
                b0 -= w * r;
                b1 -= w * a * r;
            }
            let det = s00 * s11 - s01 * s01;
            guide.push((s11 * b0 - s01 * b1) / det);
            pitch.push((s00 * b1 - s01 * b0) / det);
        }
        (
            Raw {
                part: y,
                guide,
                pitch: Some(pitch),
            },
            delta,
        )
    }
}

fn two_probe_raw(m: &[f64], n: usize) -> Raw {
    let mut y = vec![0.0; n + 1];
    let mut x = vec![0.0; n];
    for k in 0..n {
        y[k + 1] = y[k] + m[2 * k + 1] - m[2 * k];
        x[k] = y[k] - m[2 * k];
    }
    Raw {
        part: y,
        guide: x,
        pitch: None,
    }
}

fn two_probe_core(l: f64, main: &Flat, method: String) -> Result<Separation, ProcedureError> {
    let n = main.xs.len();
    let lay = Layout {
        part_pos: (0..=n).map(|i| main.xs[0] + i as f64 * l).collect(),
        stations: main.xs.clone(),
    };
    let estimate = two_probe_raw(&main.values, n);
    let mut unit = vec![0.0; main.values.len()];
    let (est, sig) = propagate(&lay, estimate, &main.u, 1.0, |r| {
        unit[r] = 1.0;
        let out = two_probe_raw(&unit, n);
        unit[r] = 0.0;
        out
    });
    let notes = vec![
        "guide: the carriage's lateral motion at probe A, listed at the carriage positions \
         x_K; part positions x_0 + i·l, i = 0 … N"
            .to_string(),
        "the pitch is not separated: a station's pitch θ_K adds −θ_K·l to the part's step \
         from x_K to x_K + l, so the part profile carries −l·Σ_{k<i} θ_k and the guide the \
         same at its stations — use three probes, or three shears on the stage, to separate \
         it"
        .to_string(),
        "a difference of the probes' zero offsets adds a constant to every step: a line, \
         removed"
            .to_string(),
    ];
    output(
        method,
        lay,
        est,
        sig,
        &["line", "pitch"],
        None,
        vec![],
        notes,
    )
}

/// The shear stage's least squares: rows are (station, shear, value, u).
fn shear_least_squares(
    xs: &[f64],
    rows: &[(usize, f64, f64, f64)],
    h: f64,
    pitch: bool,
) -> Result<Separation, ProcedureError> {
    let ns = xs.len();
    let x0 = xs[0];
    let pos = |&(k, s, _, _): &(usize, f64, f64, f64)| xs[k] + s;
    let (qmin, qmax) = rows
        .iter()
        .map(pos)
        .fold((f64::MAX, f64::MIN), |a, q| (a.0.min(q), a.1.max(q)));
    // The end nodes: a position up to a quarter pitch beyond them (a shear the stage's own
    // scale error makes a little longer than commanded) is extrapolated from the last
    // interval rather than given a node that only it would touch, by a sliver.
    let lo = ((qmin - x0) / h + END_REACH).floor();
    let hi = ((qmax - x0) / h - END_REACH).ceil();
    let nodes_f = hi - lo + 1.0;
    let unknowns_f = nodes_f + (ns * if pitch { 2 } else { 1 }) as f64;
    if !(3.0..=MAX_UNKNOWNS as f64).contains(&nodes_f) || unknowns_f > MAX_UNKNOWNS as f64 {
        return Err(ProcedureError::IllConditioned(format!(
            "a grid of pitch {h} mm over the probe positions {qmin:.3} … {qmax:.3} mm has \
             {nodes_f} nodes and, with {ns} stations, {unknowns_f} unknowns: the dense least \
             squares takes 3 … {MAX_UNKNOWNS} — give a grid pitch near the shears' spacing, or \
             split the travel into overlapping parts"
        )));
    }
    let ny = nodes_f as usize;
    let nodes: Vec<f64> = (0..ny).map(|i| x0 + (lo + i as f64) * h).collect();
    let n = ny + ns + if pitch { ns } else { 0 };
    // Sparse rows of the design matrix; count readings between nodes.
    let mut between = 0usize;
    let design: Vec<Vec<(usize, f64)>> = rows
        .iter()
        .map(|row| {
            let (k, s, _, _) = *row;
            let t = (pos(row) - nodes[0]) / h;
            let i0 = (t.floor().max(0.0) as usize).min(ny - 2);
            let f = t - i0 as f64;
            let mut e = vec![];
            if f.abs() > 1e-9 && (f - 1.0).abs() > 1e-9 {
                between += 1;
            }
            if (1.0 - f).abs() > 1e-12 {
                e.push((i0, 1.0 - f));
            }
            if f.abs() > 1e-12 {
                e.push((i0 + 1, f));
            }
            e.push((ny + k, -1.0));
            if pitch {
                e.push((ny + ns + k, -s));
            }
            e
        })
        .collect();
    let w: Vec<f64> = rows.iter().map(|r| 1.0 / (r.3 * r.3)).collect();
    let mut nm = DMatrix::<f64>::zeros(n, n);
    let mut atwm = vec![0.0; n];
    for ((e, wr), row) in design.iter().zip(&w).zip(rows) {
        for &(i, ci) in e {
            atwm[i] += wr * ci * row.2;
            for &(j, cj) in e {
                nm[(i, j)] += wr * ci * cj;
            }
        }
    }
    // The null space the model always has (the line), orthonormalised, penalised alone.
    let xc = xs.iter().sum::<f64>() / ns as f64;
    let mut gauge = vec![{
        let mut v = vec![0.0; n];
        v[..ny + ns].iter_mut().for_each(|a| *a = 1.0);
        v
    }];
    if pitch {
        let mut v = vec![0.0; n];
        for (i, p) in nodes.iter().enumerate() {
            v[i] = p - xc;
        }
        for (k, x) in xs.iter().enumerate() {
            v[ny + k] = x - xc;
            v[ny + ns + k] = 1.0;
        }
        gauge.push(v);
    }
    let mut basis: Vec<Vec<f64>> = vec![];
    for mut v in gauge {
        for b in &basis {
            let d: f64 = v.iter().zip(b).map(|(a, c)| a * c).sum();
            v.iter_mut().zip(b).for_each(|(a, c)| *a -= d * c);
        }
        let norm = v.iter().map(|a| a * a).sum::<f64>().sqrt();
        v.iter_mut().for_each(|a| *a /= norm);
        basis.push(v);
    }
    let lambda = nm.trace() / n as f64;
    let mut m = nm;
    for b in &basis {
        for i in 0..n {
            if b[i] == 0.0 {
                continue;
            }
            for j in 0..n {
                m[(i, j)] += lambda * b[i] * b[j];
            }
        }
    }
    let d: Vec<f64> = (0..n).map(|i| m[(i, i)].sqrt().max(1e-300)).collect();
    let scaled = DMatrix::from_fn(n, n, |i, j| m[(i, j)] / (d[i] * d[j]));
    let eig = scaled.symmetric_eigen();
    let top = eig.eigenvalues.iter().fold(0.0_f64, |a, &e| a.max(e));
    let weak: Vec<usize> = (0..n)
        .filter(|&i| eig.eigenvalues[i].is_nan() || eig.eigenvalues[i] <= EIGEN_FLOOR * top)
        .collect();
    if !weak.is_empty() {
        let i = weak
            .iter()
            .copied()
            .min_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]))
            .unwrap_or(weak[0]);
        let z = eig.eigenvectors.column(i);
        let (mut worst, mut at) = (0.0, nodes[0]);
        for (k, p) in nodes.iter().enumerate() {
            let v = (z[k] / d[k]).abs();
            if v > worst {
                worst = v;
                at = *p;
            }
        }
        return Err(ProcedureError::IllConditioned(format!(
            "the shear readings leave {} pattern(s) of the part and guide undetermined (the \
             largest near x = {at:.3} mm): each station's shears ({}) must, with the {:.3} mm \
             step between stations, see every grid node (pitch {h:.3} mm) from more than one \
             station — add a shear per station{}, or step the carriage by less",
            weak.len(),
            shear_list(rows, 0),
            xs[1] - xs[0],
            if pitch {
                ""
            } else {
                " (three or more shears also separate the pitch)"
            }
        )));
    }
    let mut q = eig.eigenvectors.clone();
    for (j, mut col) in q.column_iter_mut().enumerate() {
        col /= eig.eigenvalues[j];
    }
    let sinv = q * eig.eigenvectors.transpose();
    let minv = DMatrix::from_fn(n, n, |i, j| sinv[(i, j)] / (d[i] * d[j]));
    let sol: Vec<f64> = (0..n)
        .map(|i| (0..n).map(|j| minv[(i, j)] * atwm[j]).sum())
        .collect();
    let mut chi2 = 0.0;
    for ((e, wr), row) in design.iter().zip(&w).zip(rows) {
        let fit: f64 = e.iter().map(|&(i, c)| c * sol[i]).sum();
        chi2 += wr * (row.2 - fit).powi(2);
    }
    let rank = n - basis.len();
    let chi2_red = (rows.len() > rank).then(|| chi2 / (rows.len() - rank) as f64);
    let scale = chi2_red.unwrap_or(1.0).max(1.0);
    let split = |v: Vec<f64>| Raw {
        part: v[..ny].to_vec(),
        guide: v[ny..ny + ns].to_vec(),
        pitch: pitch.then(|| v[ny + ns..].to_vec()),
    };
    let lay = Layout {
        part_pos: nodes.clone(),
        stations: xs.to_vec(),
    };
    let u: Vec<f64> = rows.iter().map(|r| r.3).collect();
    let (est, sig) = propagate(&lay, split(sol), &u, scale, |r| {
        let mut col = vec![0.0; n];
        for &(i, c) in &design[r] {
            let f = w[r] * c;
            col.iter_mut()
                .enumerate()
                .for_each(|(a, v)| *v += f * minv[(a, i)]);
        }
        split(col)
    });
    let mut notes = vec![
        "guide: the carriage's lateral motion at the probe's zero shear, listed at the \
         carriage positions x_K"
            .to_string(),
        format!(
            "part on a grid of pitch {h:.4} mm, {:.3} … {:.3} mm; {between} of {} readings \
             fall between nodes and use linear interpolation of the part (error up to \
             h²/8·|Y''|)",
            nodes[0],
            nodes[ny - 1],
            rows.len()
        ),
    ];
    if pitch {
        notes.push(
            "pitch separated about its mean: per station the readings give the slope \
             θ_K − e (e the stage's perpendicular error, a reading error e·s); e and a \
             constant pitch are one constant slope, taken out with the line"
                .to_string(),
        );
    } else {
        notes.push(
            "fewer than three shears at some station: the pitch is not separated; a station's \
             pitch adds −θ_K·s to its reading at shear s, so its variation enters part and \
             guide (a constant pitch and the stage's perpendicular error go out with the \
             line)"
                .to_string(),
        );
    }
    if let Some(c) = chi2_red {
        if c > 1.0 {
            notes.push(format!(
                "reduced χ² {c:.2}: the readings scatter more than their standard errors (or \
                 the part is not linear between nodes); uncertainties scaled by √χ²"
            ));
        }
    }
    let cannot: &[&str] = if pitch {
        &["line", "pitch_constant"]
    } else {
        &["line", "pitch"]
    };
    let method = format!(
        "shear stage, least squares {} ({})",
        if between == 0 {
            "on the grid nodes"
        } else {
            "with interpolation between grid nodes"
        },
        if pitch { "with pitch" } else { "no pitch" }
    );
    output(method, lay, est, sig, cannot, chi2_red, vec![], notes)
}

/// The distinct shears of one station, for messages.
fn shear_list(rows: &[(usize, f64, f64, f64)], station: usize) -> String {
    let mut s: Vec<f64> = rows
        .iter()
        .filter(|r| r.0 == station)
        .map(|r| r.1)
        .collect();
    s.sort_by(f64::total_cmp);
    s.dedup_by(|a, b| (*a - *b).abs() < 1e-6);
    s.iter()
        .map(|v| format!("{v:.3}"))
        .collect::<Vec<_>>()
        .join(", ")
        + " mm"
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Small deterministic PRNG (SplitMix64) with Gaussian deviates.
    struct Rng(u64);
    impl Rng {
        fn next_u64(&mut self) -> u64 {
            self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            z ^ (z >> 31)
        }
        fn uniform(&mut self) -> f64 {
            ((self.next_u64() >> 11) as f64 + 0.5) / (1u64 << 53) as f64
        }
        fn gauss(&mut self) -> f64 {
            let (a, b) = (self.uniform(), self.uniform());
            (-2.0 * a.ln()).sqrt() * (std::f64::consts::TAU * b).cos()
        }
    }

    const L: f64 = 20.0;
    const X0: f64 = 50.0;
    const N: usize = 30;
    const NOISE: f64 = 5e-6; // 5 nm per averaged reading

    /// The straightedge: a set-up offset and tilt, a 3 µm bow and 1.5 µm of waviness, mm.
    fn part(x: f64) -> f64 {
        let t = (x - 360.0) / 330.0;
        0.4 + 1e-4 * (x - 300.0)
            + 3e-3 * (1.0 - t * t)
            + 1.5e-3 * (std::f64::consts::TAU * x / 350.0 + 0.4).sin()
    }
    /// The guide: a line, a 2.5 µm cubic and 0.8 µm of waviness, mm (at the pitch centre).
    fn guide(x: f64) -> f64 {
        let t = (x - 350.0) / 300.0;
        3e-5 * x + 2.5e-3 * t * t * t + 0.8e-3 * (std::f64::consts::TAU * x / 260.0).sin()
    }
    /// The carriage's pitch: 20 µrad constant plus 4 µrad varying, rad.
    fn pitch(x: f64) -> f64 {
        2e-5 + 4e-6 * (std::f64::consts::TAU * x / 410.0 + 1.0).sin()
    }
    fn flat_pitch(_x: f64) -> f64 {
        2e-5
    }

    fn stations() -> Vec<f64> {
        (0..N).map(|k| X0 + k as f64 * L).collect()
    }

    /// Probe readings from the geometry: probe j at x + j·l, pitch about probe `centre`.
    fn probe_readings(
        probes: usize,
        centre: f64,
        offsets: &[f64],
        sign: f64,
        pitch_of: fn(f64) -> f64,
        noise: f64,
        rng: &mut Rng,
    ) -> Vec<StationReading> {
        stations()
            .into_iter()
            .map(|x| StationReading {
                x_mm: x,
                readings: (0..probes)
                    .map(|j| {
                        let lever = j as f64 * L - centre;
                        let v = sign * part(x + j as f64 * L) - guide(x) - pitch_of(x) * lever
                            + offsets[j]
                            + noise * rng.gauss();
                        Some(Reading {
                            value_mm: v,
                            u_mm: noise.max(1e-7),
                        })
                    })
                    .collect(),
            })
            .collect()
    }

    /// Shear-stage readings: stage error e·s, the sensor reporting the true shear.
    fn shear_readings(
        shears: &[f64],
        jitter: f64,
        e: f64,
        pitch_of: fn(f64) -> f64,
        rng: &mut Rng,
    ) -> Vec<ShearReading> {
        let mut out = vec![];
        for x in stations() {
            for &s0 in shears {
                let s = s0 + jitter * (2.0 * rng.uniform() - 1.0);
                let v =
                    part(x + s) - guide(x) - pitch_of(x) * s + e * s + 0.02 + NOISE * rng.gauss();
                out.push(ShearReading {
                    x_mm: x,
                    shear_mm: s,
                    value_mm: v,
                    u_mm: NOISE,
                });
            }
        }
        out
    }

    fn detrended(pos: &[f64], f: impl Fn(f64) -> f64) -> Vec<f64> {
        let mut y: Vec<f64> = pos.iter().map(|&p| f(p)).collect();
        detrend(pos, &mut y);
        y
    }
    fn centred(pos: &[f64], f: impl Fn(f64) -> f64) -> Vec<f64> {
        let y: Vec<f64> = pos.iter().map(|&p| f(p)).collect();
        let m = y.iter().sum::<f64>() / y.len() as f64;
        y.iter().map(|v| v - m).collect()
    }
    fn rms(v: impl Iterator<Item = f64>) -> f64 {
        let (s, n) = v.fold((0.0, 0usize), |a, x| (a.0 + x * x, a.1 + 1));
        (s / n as f64).sqrt()
    }
    fn diff(a: &[f64], b: &[f64]) -> Vec<f64> {
        a.iter().zip(b).map(|(x, y)| x - y).collect()
    }

    /// RMS error, RMS σ, fraction within 2σ.
    fn judge(est: &[f64], sig: &[f64], truth: &[f64]) -> (f64, f64, f64) {
        let e = diff(est, truth);
        let within = e
            .iter()
            .zip(sig)
            .filter(|(a, s)| a.abs() <= 2.0 * **s)
            .count();
        (
            rms(e.iter().copied()),
            rms(sig.iter().copied()),
            within as f64 / e.len() as f64,
        )
    }

    fn check(label: &str, est: &[f64], sig: &[f64], truth: &[f64]) -> (f64, f64) {
        let (e, s, frac) = judge(est, sig, truth);
        eprintln!("{label}: RMS error {e:.3e}, RMS σ {s:.3e}, within 2σ {frac:.2}");
        assert!(e <= 2.0 * s, "{label}: RMS error {e:e} > 2 × RMS σ {s:e}");
        (e, s)
    }

    fn truths(sep: &Separation, pitch_of: fn(f64) -> f64) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        (
            detrended(&sep.part_positions_mm, part),
            detrended(&sep.stations_mm, guide),
            centred(&sep.stations_mm, pitch_of),
        )
    }

    #[test]
    fn three_probe_recovers_part_guide_and_pitch() {
        let mut rng = Rng(1);
        let st = probe_readings(3, L, &[0.0; 3], 1.0, pitch, NOISE, &mut rng);
        let sep = three_probe(&ProbeMount { spacing_mm: L }, &st, None).unwrap();
        assert_eq!(sep.part_positions_mm.len(), N + 2);
        let (yp, xg, th) = truths(&sep, pitch);
        check(
            "3p part",
            &sep.part_straightness_mm,
            &sep.part_straightness_mm_u,
            &yp,
        );
        check(
            "3p guide",
            &sep.guide_straightness_mm,
            &sep.guide_straightness_mm_u,
            &xg,
        );
        let (p, pu) = (
            sep.pitch_rad.as_ref().unwrap(),
            sep.pitch_rad_u.as_ref().unwrap(),
        );
        check("3p pitch", p, pu, &th);
        assert_eq!(sep.cannot_see, ["line", "pitch_constant", "parabola"]);
        // The sequential method's σ grow along the travel.
        let u = &sep.part_straightness_mm_u;
        let min = u.iter().copied().fold(f64::MAX, f64::min);
        let max = u.iter().copied().fold(0.0, f64::max);
        assert!(max > 2.0 * min, "σ {min:e} … {max:e}");
        let json = serde_json::to_value(&sep).unwrap();
        for k in [
            "stations_mm",
            "guide_straightness_mm",
            "guide_straightness_mm_u",
            "part_straightness_mm",
            "part_straightness_mm_u",
            "pitch_rad",
            "pitch_rad_u",
            "cannot_see",
            "notes",
        ] {
            assert!(json.get(k).is_some(), "{k}");
        }
    }

    #[test]
    fn offsets_give_the_predicted_parabola_unless_reversed() {
        let offsets = [0.8e-3, 1.3e-3, 1.5e-3];
        let delta = offsets[0] - 2.0 * offsets[1] + offsets[2];
        let mount = ProbeMount { spacing_mm: L };
        let mut rng = Rng(2);
        let st = probe_readings(3, L, &offsets, 1.0, pitch, 0.0, &mut rng);
        let sep = three_probe(&mount, &st, None).unwrap();
        let (yp, xg, th) = truths(&sep, pitch);
        let c2 = delta / (2.0 * L * L);
        let bow = |x: f64| c2 * (x - X0).powi(2);
        let want_g: Vec<f64> = xg
            .iter()
            .zip(detrended(&sep.stations_mm, bow))
            .map(|(a, b)| a + b)
            .collect();
        let want_p: Vec<f64> = yp
            .iter()
            .zip(detrended(&sep.part_positions_mm, bow))
            .map(|(a, b)| a + b)
            .collect();
        let eg = rms(diff(&sep.guide_straightness_mm, &want_g).into_iter());
        let ep = rms(diff(&sep.part_straightness_mm, &want_p).into_iter());
        let size = rms(detrended(&sep.stations_mm, bow).into_iter());
        eprintln!("parabola: RMS {size:e} mm, guide off it by {eg:e}, part by {ep:e}");
        assert!(size > 1e-3 && eg < 1e-10 && ep < 1e-10);
        // The pitch carries the parabola's slope 2·c2·(x − x_0) (about its mean).
        let want_t: Vec<f64> = th
            .iter()
            .zip(centred(&sep.stations_mm, |x| 2.0 * c2 * (x - X0)))
            .map(|(a, b)| a + b)
            .collect();
        let ept = rms(diff(sep.pitch_rad.as_ref().unwrap(), &want_t).into_iter());
        assert!(ept < 1e-12, "{ept:e}");
        // With the reversal the parabola is gone and δ measured.
        let rev = probe_readings(3, L, &offsets, -1.0, flat_pitch, 0.0, &mut rng);
        let sep = three_probe(&mount, &st, Some(&rev)).unwrap();
        assert_eq!(sep.cannot_see, ["line", "pitch_constant"]);
        let eg = rms(diff(&sep.guide_straightness_mm, &xg).into_iter());
        let ep = rms(diff(&sep.part_straightness_mm, &yp).into_iter());
        assert!(eg < 1e-10 && ep < 1e-10, "{eg:e} {ep:e}");
        assert!((sep.params[0].value - delta).abs() < 1e-12);
    }

    #[test]
    fn reversal_with_noise_within_bounds() {
        let offsets = [0.8e-3, 1.3e-3, 1.5e-3];
        let mut rng = Rng(3);
        let st = probe_readings(3, L, &offsets, 1.0, pitch, NOISE, &mut rng);
        let rev = probe_readings(3, L, &offsets, -1.0, flat_pitch, NOISE, &mut rng);
        let sep = three_probe(&ProbeMount { spacing_mm: L }, &st, Some(&rev)).unwrap();
        let (yp, xg, th) = truths(&sep, pitch);
        check(
            "3p+rev part",
            &sep.part_straightness_mm,
            &sep.part_straightness_mm_u,
            &yp,
        );
        check(
            "3p+rev guide",
            &sep.guide_straightness_mm,
            &sep.guide_straightness_mm_u,
            &xg,
        );
        check(
            "3p+rev pitch",
            sep.pitch_rad.as_ref().unwrap(),
            sep.pitch_rad_u.as_ref().unwrap(),
            &th,
        );
        let p = &sep.params[0];
        let delta = offsets[0] - 2.0 * offsets[1] + offsets[2];
        assert!((p.value - delta).abs() < 3.0 * p.sigma, "{p:?}");
    }

    #[test]
    fn two_probe_recovers_without_pitch_and_shows_the_pitch_it_cannot_see() {
        let mount = ProbeMount { spacing_mm: L };
        let mut rng = Rng(4);
        let st = probe_readings(2, 0.0, &[0.01, -0.02], 1.0, flat_pitch, NOISE, &mut rng);
        let sep = two_probe(&mount, &st).unwrap();
        assert_eq!(sep.part_positions_mm.len(), N + 1);
        assert_eq!(sep.cannot_see, ["line", "pitch"]);
        assert!(sep.pitch_rad.is_none());
        let (yp, xg, _) = truths(&sep, flat_pitch);
        check(
            "2p part",
            &sep.part_straightness_mm,
            &sep.part_straightness_mm_u,
            &yp,
        );
        check(
            "2p guide",
            &sep.guide_straightness_mm,
            &sep.guide_straightness_mm_u,
            &xg,
        );
        // A varying pitch leaks as −l·Σθ, as the note says.
        let st = probe_readings(2, 0.0, &[0.0; 2], 1.0, pitch, 0.0, &mut rng);
        let sep = two_probe(&mount, &st).unwrap();
        let mut cum = vec![0.0];
        for x in stations() {
            let last = *cum.last().unwrap();
            cum.push(last - L * pitch(x));
        }
        let mut leak = cum.clone();
        detrend(&sep.part_positions_mm, &mut leak);
        let want: Vec<f64> = yp.iter().zip(&leak).map(|(a, b)| a + b).collect();
        assert!(rms(diff(&sep.part_straightness_mm, &want).into_iter()) < 1e-10);
    }

    #[test]
    fn shear_two_point_is_sequential_and_removes_the_stage_error() {
        let mut rng = Rng(5);
        let r0 = shear_readings(&[0.0, L], 0.0, 0.0, flat_pitch, &mut rng);
        let mut rng = Rng(5);
        let r1 = shear_readings(&[0.0, L], 0.0, 5e-4, flat_pitch, &mut rng);
        let a = shear_stage(&r0, &ShearOptions::default()).unwrap();
        let b = shear_stage(&r1, &ShearOptions::default()).unwrap();
        assert!(a.method.contains("two-point"), "{}", a.method);
        let (yp, xg, _) = truths(&a, flat_pitch);
        check(
            "shear 2pt part",
            &b.part_straightness_mm,
            &b.part_straightness_mm_u,
            &yp,
        );
        check(
            "shear 2pt guide",
            &b.guide_straightness_mm,
            &b.guide_straightness_mm_u,
            &xg,
        );
        let d = rms(diff(&a.guide_straightness_mm, &b.guide_straightness_mm).into_iter())
            + rms(diff(&a.part_straightness_mm, &b.part_straightness_mm).into_iter());
        assert!(d < 1e-11, "stage error left {d:e}");
        // Against the step: shears {−l, 0}, the same separation by least squares.
        let mut rng = Rng(5);
        let r2 = shear_readings(&[-L, 0.0], 0.0, 5e-4, flat_pitch, &mut rng);
        let c = shear_stage(&r2, &ShearOptions::default()).unwrap();
        assert!(c.method.contains("no pitch"), "{}", c.method);
        assert_eq!(c.cannot_see, ["line", "pitch"]);
        let (yp, xg, _) = truths(&c, flat_pitch);
        check(
            "shear −l part",
            &c.part_straightness_mm,
            &c.part_straightness_mm_u,
            &yp,
        );
        check(
            "shear −l guide",
            &c.guide_straightness_mm,
            &c.guide_straightness_mm_u,
            &xg,
        );
    }

    #[test]
    fn shear_three_point_exact_recovers_and_removes_the_stage_error() {
        let mut rng = Rng(6);
        let r0 = shear_readings(&[-L, 0.0, L], 0.0, 0.0, pitch, &mut rng);
        let mut rng = Rng(6);
        let r1 = shear_readings(&[-L, 0.0, L], 0.0, 3e-4, pitch, &mut rng);
        let a = shear_stage(&r0, &ShearOptions::default()).unwrap();
        let b = shear_stage(&r1, &ShearOptions::default()).unwrap();
        assert!(b.method.contains("on the grid nodes"), "{}", b.method);
        assert_eq!(b.cannot_see, ["line", "pitch_constant"]);
        assert_eq!(b.part_positions_mm.len(), N + 2);
        assert!((b.part_positions_mm[0] - (X0 - L)).abs() < 1e-9);
        let (yp, xg, th) = truths(&b, pitch);
        check(
            "shear 3pt part",
            &b.part_straightness_mm,
            &b.part_straightness_mm_u,
            &yp,
        );
        check(
            "shear 3pt guide",
            &b.guide_straightness_mm,
            &b.guide_straightness_mm_u,
            &xg,
        );
        check(
            "shear 3pt pitch",
            b.pitch_rad.as_ref().unwrap(),
            b.pitch_rad_u.as_ref().unwrap(),
            &th,
        );
        let d = rms(diff(&a.guide_straightness_mm, &b.guide_straightness_mm).into_iter())
            + rms(diff(&a.part_straightness_mm, &b.part_straightness_mm).into_iter());
        let dp =
            rms(diff(a.pitch_rad.as_ref().unwrap(), b.pitch_rad.as_ref().unwrap()).into_iter());
        eprintln!("stage error 0.3 mrad: profiles change by {d:e} mm, pitch by {dp:e} rad");
        assert!(d < 1e-10 && dp < 1e-12);
    }

    #[test]
    fn shear_scanning_with_interpolation_recovers() {
        let mut rng = Rng(7);
        // Shears not equal to the step, on a half-step grid, one between nodes, and the
        // stage's sensor reporting a few µm of jitter.
        let r = shear_readings(&[0.0, 10.0, 25.0, 30.0, 40.0], 0.004, 2e-4, pitch, &mut rng);
        let sep = shear_stage(
            &r,
            &ShearOptions {
                grid_mm: Some(10.0),
            },
        )
        .unwrap();
        assert!(sep.method.contains("interpolation"), "{}", sep.method);
        let (yp, xg, th) = truths(&sep, pitch);
        check(
            "shear scan part",
            &sep.part_straightness_mm,
            &sep.part_straightness_mm_u,
            &yp,
        );
        check(
            "shear scan guide",
            &sep.guide_straightness_mm,
            &sep.guide_straightness_mm_u,
            &xg,
        );
        check(
            "shear scan pitch",
            sep.pitch_rad.as_ref().unwrap(),
            sep.pitch_rad_u.as_ref().unwrap(),
            &th,
        );
        eprintln!("shear scan χ² {:?}", sep.chi2_reduced);
    }

    #[test]
    fn recursion_equals_least_squares() {
        let mut rng = Rng(8);
        let st = probe_readings(3, L, &[0.0; 3], 1.0, pitch, NOISE, &mut rng);
        let a = three_probe(&ProbeMount { spacing_mm: L }, &st, None).unwrap();
        let shear: Vec<ShearReading> = st
            .iter()
            .flat_map(|s| {
                s.readings.iter().enumerate().map(move |(j, r)| {
                    let r = r.unwrap();
                    ShearReading {
                        x_mm: s.x_mm,
                        shear_mm: j as f64 * L,
                        value_mm: r.value_mm,
                        u_mm: r.u_mm,
                    }
                })
            })
            .collect();
        let b = shear_stage(&shear, &ShearOptions::default()).unwrap();
        let (pa, pb) = (a.pitch_rad.as_ref().unwrap(), b.pitch_rad.as_ref().unwrap());
        assert!(rms(diff(&a.part_straightness_mm, &b.part_straightness_mm).into_iter()) < 1e-10);
        assert!(rms(diff(pa, pb).into_iter()) < 1e-12);
        // The stage's guide is at A (zero shear), the three-probe's at B: X_A = X_B − θ·l.
        let mut moved: Vec<f64> = a
            .guide_straightness_mm
            .iter()
            .zip(pa)
            .map(|(x, t)| x - t * L)
            .collect();
        detrend(&a.stations_mm, &mut moved);
        assert!(rms(diff(&moved, &b.guide_straightness_mm).into_iter()) < 1e-10);
        let su = diff(&a.part_straightness_mm_u, &b.part_straightness_mm_u);
        assert!(rms(su.into_iter()) < 1e-10);
    }

    #[test]
    fn three_methods_agree_on_the_guide() {
        let mut rng = Rng(9);
        let mount = ProbeMount { spacing_mm: L };
        let s3 = three_probe(
            &mount,
            &probe_readings(3, L, &[0.0; 3], 1.0, flat_pitch, NOISE, &mut rng),
            None,
        )
        .unwrap();
        let s2 = two_probe(
            &mount,
            &probe_readings(2, 0.0, &[0.0; 2], 1.0, flat_pitch, NOISE, &mut rng),
        )
        .unwrap();
        let ss = shear_stage(
            &shear_readings(&[-L, 0.0, L], 0.0, 1e-4, flat_pitch, &mut rng),
            &ShearOptions::default(),
        )
        .unwrap();
        for (name, a, b) in [
            ("3p/2p", &s3, &s2),
            ("3p/shear", &s3, &ss),
            ("2p/shear", &s2, &ss),
        ] {
            let z: Vec<f64> = a
                .guide_straightness_mm
                .iter()
                .zip(&b.guide_straightness_mm)
                .zip(
                    a.guide_straightness_mm_u
                        .iter()
                        .zip(&b.guide_straightness_mm_u),
                )
                .map(|((x, y), (u, v))| (x - y) / (u * u + v * v).sqrt())
                .collect();
            let within = z.iter().filter(|v| v.abs() <= 2.0).count() as f64 / z.len() as f64;
            let r = rms(z.iter().copied());
            eprintln!("{name}: RMS normalised difference {r:.2}, within 2σ {within:.2}");
            assert!(r < 2.0 && within >= 0.75, "{name}");
        }
    }

    /// Monte Carlo: the propagated σ is the scatter of the estimates.
    fn monte_carlo(label: &str, runs: usize, f: impl Fn(&mut Rng) -> Separation) {
        let mut z2 = [0.0; 3];
        let (mut inside, mut count) = ([0usize; 3], [0usize; 3]);
        for seed in 0..runs {
            let mut rng = Rng(1000 + seed as u64);
            let sep = f(&mut rng);
            let (yp, xg, th) = truths(&sep, pitch);
            let sets = [
                (&sep.part_straightness_mm, &sep.part_straightness_mm_u, yp),
                (&sep.guide_straightness_mm, &sep.guide_straightness_mm_u, xg),
            ];
            for (i, (e, u, t)) in sets.into_iter().enumerate() {
                for ((a, s), b) in e.iter().zip(u).zip(&t) {
                    let z = (a - b) / s;
                    z2[i] += z * z;
                    inside[i] += (z.abs() <= 2.0) as usize;
                    count[i] += 1;
                }
            }
            if let (Some(p), Some(u)) = (&sep.pitch_rad, &sep.pitch_rad_u) {
                for ((a, s), b) in p.iter().zip(u).zip(&th) {
                    let z = (a - b) / s;
                    z2[2] += z * z;
                    inside[2] += (z.abs() <= 2.0) as usize;
                    count[2] += 1;
                }
            }
        }
        for (i, what) in ["part", "guide", "pitch"].iter().enumerate() {
            if count[i] == 0 {
                continue;
            }
            let r = (z2[i] / count[i] as f64).sqrt();
            let frac = inside[i] as f64 / count[i] as f64;
            eprintln!("{label} {what}: RMS(error/σ) {r:.2}, within 2σ {frac:.3}");
            assert!((0.8..1.25).contains(&r) && frac > 0.9, "{label} {what}");
        }
    }

    #[test]
    fn propagated_sigma_is_the_scatter() {
        let mount = ProbeMount { spacing_mm: L };
        monte_carlo("3p", 40, |rng| {
            three_probe(
                &mount,
                &probe_readings(3, L, &[0.0; 3], 1.0, pitch, NOISE, rng),
                None,
            )
            .unwrap()
        });
        monte_carlo("2p", 40, |rng| {
            two_probe(
                &mount,
                &probe_readings(2, 0.0, &[0.0; 2], 1.0, flat_pitch, NOISE, rng),
            )
            .unwrap()
        });
        monte_carlo("shear", 30, |rng| {
            shear_stage(
                &shear_readings(&[0.0, 10.0, 20.0, 30.0, 40.0], 0.0, 1e-4, pitch, rng),
                &ShearOptions {
                    grid_mm: Some(10.0),
                },
            )
            .unwrap()
        });
    }

    fn err_text(r: Result<Separation, ProcedureError>) -> String {
        match r {
            Ok(_) => panic!("expected an error"),
            Err(e) => e.to_string(),
        }
    }

    #[test]
    fn bad_input_is_refused_with_a_clear_message() {
        let mount = ProbeMount { spacing_mm: L };
        let mut rng = Rng(10);
        let good = probe_readings(3, L, &[0.0; 3], 1.0, pitch, NOISE, &mut rng);
        // Too few stations.
        let e = err_text(three_probe(&mount, &good[..2], None));
        assert!(
            e.contains("at least 3 stations") && e.contains("has 2"),
            "{e}"
        );
        // Unequal spacing.
        let mut bad = good.clone();
        bad[5].x_mm += 1.0;
        let e = err_text(three_probe(&mount, &bad, None));
        assert!(
            e.contains("step by the probe spacing") && e.contains("station 5"),
            "{e}"
        );
        // A probe missing.
        let mut bad = good.clone();
        bad[7].readings[1] = None;
        let e = err_text(three_probe(&mount, &bad, None));
        assert!(
            e.contains("station 7") && e.contains("probe B has no reading"),
            "{e}"
        );
        // Non-finite readings.
        let mut bad = good.clone();
        bad[3].readings[2] = Some(Reading {
            value_mm: f64::NAN,
            u_mm: 1e-5,
        });
        let e = err_text(three_probe(&mount, &bad, None));
        assert!(
            e.contains("station 3") && e.contains("probe C") && e.contains("not finite"),
            "{e}"
        );
        let mut bad = good.clone();
        bad[3].readings[0] = Some(Reading {
            value_mm: 0.1,
            u_mm: 0.0,
        });
        let e = err_text(three_probe(&mount, &bad, None));
        assert!(e.contains("must be positive"), "{e}");
        // Wrong probe count, bad spacing, short reversal.
        let e = err_text(two_probe(&mount, &good));
        assert!(
            e.contains("has 3 probe readings") && e.contains("needs 2"),
            "{e}"
        );
        let e = err_text(three_probe(
            &ProbeMount {
                spacing_mm: f64::NAN,
            },
            &good,
            None,
        ));
        assert!(e.contains("probe spacing"), "{e}");
        let e = err_text(three_probe(&mount, &good, Some(&good[..10])));
        assert!(e.contains("reversal has 10 stations"), "{e}");
        // Shear stage: non-finite, too few stations, one shear, undetermined layout.
        let mut r = shear_readings(&[0.0, L, 2.0 * L], 0.0, 0.0, pitch, &mut rng);
        let keep = r.clone();
        r[4].value_mm = f64::INFINITY;
        let e = err_text(shear_stage(&r, &ShearOptions::default()));
        assert!(
            e.contains("shear reading 4") && e.contains("not finite"),
            "{e}"
        );
        let e = err_text(shear_stage(&keep[..6], &ShearOptions::default()));
        assert!(
            e.contains("at least 3 carriage stations") && e.contains("have 2"),
            "{e}"
        );
        let one: Vec<ShearReading> = keep
            .iter()
            .filter(|r| r.shear_mm != L || r.x_mm != X0 + L)
            .copied()
            .collect();
        let one: Vec<ShearReading> = one
            .into_iter()
            .filter(|r| r.x_mm != X0 + L || r.shear_mm == 0.0)
            .collect();
        let e = err_text(shear_stage(&one, &ShearOptions::default()));
        assert!(
            e.contains("single shear") && e.contains("x = 70.0000"),
            "{e}"
        );
        let r = shear_readings(&[0.0, L, 3.0 * L], 0.0, 0.0, pitch, &mut rng);
        let e = err_text(shear_stage(&r, &ShearOptions::default()));
        assert!(
            e.contains("undetermined") && e.contains("add a shear"),
            "{e}"
        );
        let e = err_text(shear_stage(
            &keep,
            &ShearOptions {
                grid_mm: Some(-1.0),
            },
        ));
        assert!(e.contains("grid pitch"), "{e}");
    }

    #[test]
    fn averaging_is_robust() {
        let mut rng = Rng(11);
        let mut s: Vec<f64> = (0..200).map(|_| 1.0 + 1e-4 * rng.gauss()).collect();
        s[17] = 5.0;
        s[40] = f64::NAN;
        let a = average_samples(&s).unwrap();
        assert_eq!((a.used, a.rejected), (198, 2));
        assert!((a.reading.value_mm - 1.0).abs() < 3.0 * a.reading.u_mm);
        assert!(
            (a.reading.u_mm / (1e-4 / 198f64.sqrt()) - 1.0).abs() < 0.35,
            "{a:?}"
        );
        // A slow drift (correlated samples) inflates the standard error.
        let d: Vec<f64> = (0..200)
            .map(|i| (i as f64 * 0.05).sin() * 1e-4 + 1e-6 * rng.gauss())
            .collect();
        let b = average_samples(&d).unwrap();
        let plain = {
            let m = d.iter().sum::<f64>() / 200.0;
            (d.iter().map(|v| (v - m).powi(2)).sum::<f64>() / 199.0 / 200.0).sqrt()
        };
        assert!(b.reading.u_mm > 3.0 * plain);
        let e = average_samples(&[1.0, f64::NAN]).unwrap_err().to_string();
        assert!(e.contains("at least 2"), "{e}");
    }
}
