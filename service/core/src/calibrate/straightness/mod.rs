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
//!   slope of the offsets, (o_C − o_A)/(2l), are a constant pitch). Without a reversal,
//!   [`three_probe_with`] estimates δ (β = δ/l, the angle between the probes' zero lines) as
//!   a least-squares start value from a stated bound on the straightedge's bow (and the
//!   zeroing's): the equations are in `three.rs`'s doc.
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
//!   **Two unequal shears** (NUDT's single-probe form: shears {0, s1, s2}, s1 = p·h,
//!   s2 = q·h, q > p ≥ 1, not the equal case p = 1, q = 2, with the carriage stepping by the
//!   grid pitch h). Eliminating X_K and φ_K from a station's three readings leaves one
//!   equation, (q − p)·Y_K − q·Y_{K+p} + p·Y_{K+q} = (q − p)·m_0 − q·m_{s1} + p·m_{s2}, a
//!   recursion of order q: it needs q start values, of which the line is two. The q − 2 others
//!   are the roots of (q − p) − q·r^p + p·r^q other than the double root 1 (p = 2, q = 3:
//!   r = −1/2, a pattern halving from the first station on), which no such station sees. The
//!   exact reconstruction reads them: one station (the first) also at every grid node between
//!   0 and s2, where the stage's readings give Y_0 … Y_q up to the line; every later station
//!   then gives the next node exactly, Y_{K+q} = [q·Y_{K+p} − (q − p)·Y_K + g_K]/p. The least
//!   squares above is this recursion when the readings are on the nodes, and weighs it with
//!   the readings' σ otherwise; without the start station it refuses (the patterns undetermined)
//!   and says which station to add. The start station must be at the end where the roots lie
//!   outside the unit circle (the propagated σ show it: they grow as |r|^K).
//!
//!   **A curved stage path.** The stage's travel off its line by c·s² (sagitta
//!   b = c·(s_max − s_min)²/4 over the shears) adds c·s² to every reading at shear s: the same at
//!   every station, it equals the part and guide both bent by c·x² and the pitch by 2c·x, so
//!   with the pitch separated no reading can show it (`cannot_see: parabola`) — over a travel
//!   L it is b·(L/(s_max − s_min))² peak-to-valley, thousands of times the sagitta. The output
//!   states the profiles' response to 10 nm of sagitta (the same solve on the readings c·s²).
//!   Calibrate the stage's path on an optical flat, or measure the straightedge turned over
//!   (Y → −Y, c·s² stays). Without the pitch (two shears {0, l}) it is a constant per step,
//!   a line: removed.
//!
//!   **Between nodes.** A reading at fraction f of an interval is the part interpolated
//!   linearly; its error is f·(1 − f)·h²/2·Y'' ≤ h²/8·|Y''|. The stage's real shears (its
//!   sensor's, not the commanded ones) are never exactly on the nodes: the output counts these
//!   readings and bounds the error by max f·(1 − f)/2 · max|Δ²Y| of the fitted part.
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
//! the stage's sensor giving the spacing; with two unequal shears the recursion's start values
//! read at one station (the generalised three-point recursion; for lateral-shearing data the
//! exact two-shear reconstruction, Elster & Weingärtner, J. Opt. Soc. Am. A 16, 1999).

use super::{Param, ProcedureError};
use nalgebra::DMatrix;
use serde::{Deserialize, Serialize};

mod shared;
mod shear;
mod three;
mod two;

pub use shear::shear_stage;
pub use three::{three_probe, three_probe_with, ThreeProbeOptions};
pub use two::two_probe;

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

#[cfg(test)]
mod tests;
