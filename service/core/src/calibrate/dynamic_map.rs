//! `dynamic-map`: the S1/F1/F2 joint method — a per-point map of a fast scan's error for one
//! feature and speed, measured against slow scans and extrapolated to zero deflection.
//!
//! Measurement (one circle, same path, same direction): S1 a slow scan at deflection d1, F1 a
//! fast scan at d2, F2 a fast scan at d1. Per angle bin j (N bins centred on θ_j = 2πj/N about
//! the slow scan's centre, steady-speed points only) each scan's radial deviation r(θ_j) is the
//! mean of its points' distances from one common centre (the circle fitted to S1) minus S1's
//! radius, positive away from the centre. Then, per bin,
//!
//! * HSZD = F2 − d1·(F1 − F2)/(d2 − d1) — high speed, zero deflection (linear extrapolation);
//! * e1 = F2 − HSZD — the error of the deflection d1 at high speed;
//! * LSZD = S1 − e1 — low speed, zero deflection (the reference surface);
//! * e2 = F2 − LSZD — the dynamic correction of a fast scan at d1 (= F2 − S1 + e1).
//!
//! The map stored (effect `feature_map`, one per feature × tip × direction × speed) is the
//! correction added to a point along the direction away from the centre:
//! a_j = −(HSZD − LSZD) = −(F2 − S1) at zero deflection and b_j = −e1/d1 per mm of deflection,
//! so a fast scan at d1 gets a_j + b_j·d1 = −e2 and one at another deflection d gets
//! −(HSZD − LSZD) − e1·d/d1. It applies to the fast scans' segment ids (a like part measured by
//! the same part program has the same ids), at the fast speed (±5 %), with the same tip, and
//! at the map's place: a point's carriage position c (scales + deflection) must satisfy
//! | |c_xy − c₀| − R₀ | ≤ 1 mm and |c_z − z₀| ≤ 1 mm, c₀, R₀, z₀ S1's carriage path's centre,
//! radius and mean height — a like part stands where the master did; another part program
//! that reuses the segment ids at that speed on another feature gets no map (and the lab
//! says a map applies to none of its scans).
//!
//! Uncertainties: per scan and bin σ = s/√n inflated by the lag-1 correlation of the points
//! in the bin, propagated linearly through the equations above (the scans are independent).
//! To that is added, in quadrature, what the scales' expansion leaves (ISO 1: a scale at T_i
//! reads long by α_i·(T_i − T_ref)·(s_i − o_i)), which no bin's scatter shows: the room warms
//! between and during the scans, so each scan's circle grows (a constant per map), turns into
//! an ellipse (X and Y scales apart) and, within one revolution, drifts (a ramp in time, a
//! sawtooth in the angle: harmonics falling as 1/k) — one pattern over all bins, different
//! each run. Per scan and axis i the radial shift per unit α_i of every point,
//! q_i = (T_i(t) − T_i,S1)·(s_i − o_i)·n_i (T_i(t) the scan's measured scale temperature as a
//! line in time, n the point's radial direction), goes through what the data goes through (its
//! own centre taken out, S1's radius subtracted, binned, then the equations above): G_i per
//! bin. Then σ² += Σ_i (G_i·σ_α,i)², with σ_α,i = α_i/10 of the start's `scale_thermal` when it
//! corrects the scales, else a typical scale's α (11.5 ppm/K: steel) — the coefficient unknown
//! within that. The summary parameters (bin means) take the mean of G, which does not average
//! out over the bins. Without scale sensors in the bags this part is left out (noted).
//!
//! Speed search (with a tolerance): where the bags hold F1 and F2 at several speeds, the speeds
//! are taken in rising order and the slow/fast difference at each — the RMS over the bins of
//! F2 − S1 (= HSZD − LSZD, the dynamic part at zero deflection) — compared with the
//! tolerance: the fastest speed before it first leaves the tolerance needs no map (reported),
//! and maps are stored only for the speeds where it is left. Without a tolerance every speed
//! gets its map.
//!
//! Source idea: Renishaw, "calibrating a coordinate positioning apparatus" — the error of a
//! fast scan of a feature, measured once against slow scans of a like part, corrects later
//! fast scans of like parts.

use super::{Param, ProcedureError};
use crate::calib::Calibration;
use crate::effects::{feature_map, EffectConfig};
use crate::lab::dataset::{Dataset, Phase};
use crate::lab::program::FeatureKind;
use crate::sample::Vec3;
use crate::shape;
use serde::Serialize;
use std::collections::BTreeMap;
use std::f64::consts::TAU;

/// Deflections closer than this are one deflection, mm.
const LEVEL_MM: f64 = 0.04;
/// Least difference of d2 from d1, mm.
const MIN_DEFLECTION_SPREAD_MM: f64 = 0.1;
/// Fewest points of a scan in one bin.
const MIN_BIN_POINTS: usize = 3;
/// Speeds within this fraction are one speed.
const SAME_SPEED: f64 = 0.01;
/// How far a later scan's carriage path may be from the map's place (S1's path radius about
/// its centre, and its height) and still get the map, mm.
pub const PLACE_TOLERANCE_MM: f64 = 1.0;
/// A typical scale's expansion coefficient (steel), 1/K: the uncertainty of a coefficient the
/// start does not correct.
const ALPHA_TYPICAL_PER_K: f64 = 11.5e-6;
/// With the start's `scale_thermal`: the share of its coefficients taken as their uncertainty.
pub(crate) const ALPHA_SHARE: f64 = 0.1;

/// The scales' expansion as the σ sees it: each axis's sensor slot, the uncertainty of its
/// coefficient (1/K) and its zero point (mm).
#[derive(Debug, Clone, Copy)]
struct Thermal {
    slots: [Option<usize>; 3],
    sigma_alpha: [f64; 3],
    origin: [f64; 3],
}

impl Thermal {
    fn of(ds: &Dataset, start: &Calibration) -> Thermal {
        let slots = crate::effects::scale_thermal::SENSORS.map(|n| ds.sensors.find(n));
        let corrected = start.effects.iter().find_map(|e| match e {
            EffectConfig::ScaleThermal(c) => Some(c),
            _ => None,
        });
        match corrected {
            Some(c) => Thermal {
                slots,
                sigma_alpha: c.alpha_per_k.map(|a| ALPHA_SHARE * a.abs()),
                origin: c.origin_mm,
            },
            None => Thermal {
                slots,
                sigma_alpha: [ALPHA_TYPICAL_PER_K; 3],
                origin: [0.0; 3],
            },
        }
    }
}

/// One scan's temperature of scale `slot` as a line in time: (t₀ s, T at t₀, slope K/s), from
/// the points that carry a reading (the sensors' noise averaged out).
fn temp_line(ds: &Dataset, idx: &[usize], slot: usize) -> Option<(f64, f64, f64)> {
    let pts: Vec<(f64, f64)> = idx
        .iter()
        .map(|&i| &ds.points[i].ctx)
        .filter(|c| c.temps_valid & (1 << slot) != 0 && c.temps[slot].is_finite())
        .map(|c| (c.t_ns as f64 * 1e-9, c.temps[slot]))
        .collect();
    if pts.len() < 2 {
        return None;
    }
    let n = pts.len() as f64;
    let t0 = pts.iter().map(|p| p.0).sum::<f64>() / n;
    let m = pts.iter().map(|p| p.1).sum::<f64>() / n;
    let stt: f64 = pts.iter().map(|p| (p.0 - t0).powi(2)).sum();
    let sty: f64 = pts.iter().map(|p| (p.0 - t0) * (p.1 - m)).sum();
    Some((t0, m, if stt > 0.0 { sty / stt } else { 0.0 }))
}

/// Per axis, one scan's radial shift per unit α in each bin (its own centre taken out, as its
/// circle fit does), and its constant (S1's is its radius's share). `tref` the reference
/// temperatures; None when a scale has no readings in the scan.
fn thermal_bins(
    ds: &Dataset,
    sc: &ScanPts,
    th_of: &dyn Fn(usize) -> Option<(usize, f64, Vec3)>,
    n: usize,
    thermal: &Thermal,
    tref: [f64; 3],
) -> Option<([Vec<f64>; 3], [f64; 3])> {
    let mut bins: [Vec<f64>; 3] = std::array::from_fn(|_| vec![0.0; n]);
    let mut consts = [0.0; 3];
    for ax in 0..3 {
        let Some(slot) = thermal.slots[ax] else {
            continue;
        };
        let (t0, a, b) = temp_line(ds, &sc.idx, slot)?;
        // Rows (bin, cos θ, sin θ, q).
        let rows: Vec<(usize, f64, f64, f64)> = sc
            .idx
            .iter()
            .filter_map(|&i| {
                let (j, th, nr) = th_of(i)?;
                let c = &ds.points[i].ctx;
                let t = a + b * (c.t_ns as f64 * 1e-9 - t0) - tref[ax];
                Some((
                    j,
                    th.cos(),
                    th.sin(),
                    t * (c.scale[ax] - thermal.origin[ax]) * nr[ax],
                ))
            })
            .collect();
        // Least squares of q on (1, cos θ, sin θ): the circle fit's radius and centre.
        let mut m = nalgebra::Matrix3::<f64>::zeros();
        let mut v = nalgebra::Vector3::<f64>::zeros();
        for r in &rows {
            let x = nalgebra::Vector3::new(1.0, r.1, r.2);
            m += x * x.transpose();
            v += x * r.3;
        }
        let k = m.try_inverse()? * v;
        consts[ax] = k[0];
        let mut cnt = vec![0usize; n];
        for r in &rows {
            bins[ax][r.0] += r.3 - k[1] * r.1 - k[2] * r.2;
            cnt[r.0] += 1;
        }
        for (b, c) in bins[ax].iter_mut().zip(&cnt) {
            *b /= (*c).max(1) as f64;
        }
    }
    Some((bins, consts))
}

/// Options of the procedure.
#[derive(Debug, Clone, Copy)]
pub struct Options {
    /// Angle bins (knots of the map) around the circle.
    pub bins: usize,
    /// A scan is fast when its speed is at least this many times the slow scan's.
    pub min_speed_ratio: f64,
    /// The map applies within this fraction of its speed.
    pub speed_tolerance: f64,
    /// Speed search: the slow/fast difference (RMS of F2 − S1 over the bins, mm) a speed may
    /// show without a map.
    pub tolerance_mm: Option<f64>,
}

impl Default for Options {
    fn default() -> Self {
        Options {
            bins: 72,
            min_speed_ratio: 2.0,
            speed_tolerance: 0.05,
            tolerance_mm: None,
        }
    }
}

/// One scan the method used.
#[derive(Debug, Clone, Serialize)]
pub struct Scan {
    /// S1, F1 or F2.
    pub role: &'static str,
    /// Command segment id.
    pub segment: u32,
    /// Programmed speed, mm/s.
    pub speed_mm_s: f64,
    /// Mean measured deflection, mm.
    pub deflection_mm: f64,
    /// Steady-speed points used.
    pub points: usize,
    /// Mean radial deviation from S1's circle, µm.
    pub mean_radial_um: f64,
}

/// One map: what was measured per bin, µm, with standard uncertainties.
#[derive(Debug, Clone, Serialize)]
pub struct Map {
    /// Effect id of the map.
    pub id: String,
    /// The feature scanned.
    pub feature: String,
    /// Tip.
    pub tip: u32,
    /// Head angles, degrees.
    pub head_deg: [f64; 2],
    /// +1 CCW, −1 CW.
    pub direction: i32,
    /// The fast speed (the map's), mm/s.
    pub speed_mm_s: f64,
    /// The slow scan's speed, mm/s.
    pub slow_speed_mm_s: f64,
    /// d1 (S1, F2) and d2 (F1), mm.
    pub d1_mm: f64,
    /// d2, mm.
    pub d2_mm: f64,
    /// Segments the map applies to (F2's, F1's).
    pub segments: Vec<u32>,
    /// The three scans.
    pub scans: Vec<Scan>,
    /// Bin centres, degrees.
    pub theta_deg: Vec<f64>,
    /// Radial deviation of S1 per bin, µm.
    pub s1_um: Vec<f64>,
    /// Its σ, µm.
    pub s1_u_um: Vec<f64>,
    /// F1, µm.
    pub f1_um: Vec<f64>,
    /// Its σ, µm.
    pub f1_u_um: Vec<f64>,
    /// F2, µm.
    pub f2_um: Vec<f64>,
    /// Its σ, µm.
    pub f2_u_um: Vec<f64>,
    /// High speed, zero deflection, µm.
    pub hszd_um: Vec<f64>,
    /// Low speed, zero deflection, µm.
    pub lszd_um: Vec<f64>,
    /// e1 = F2 − HSZD, µm.
    pub e1_um: Vec<f64>,
    /// Its σ, µm.
    pub e1_u_um: Vec<f64>,
    /// e2 = F2 − LSZD, µm.
    pub e2_um: Vec<f64>,
    /// Its σ, µm.
    pub e2_u_um: Vec<f64>,
    /// RMS of e2 over the bins, µm.
    pub e2_rms_um: f64,
    /// RMS of e2's σ over the bins, µm.
    pub e2_u_rms_um: f64,
    /// Its part from the points' scatter in the bins alone, µm RMS.
    pub e2_u_noise_rms_um: f64,
    /// Its part from the scales' expansion (one pattern over the bins), µm RMS; 0 without
    /// scale temperatures.
    pub e2_u_scales_rms_um: f64,
    /// RMS of the dynamic part at zero deflection (HSZD − LSZD = F2 − S1), µm.
    pub dynamic_rms_um: f64,
    /// RMS of e1, µm.
    pub e1_rms_um: f64,
    /// RMS of the dynamic part's σ over the bins, µm.
    pub dynamic_u_rms_um: f64,
}

/// One speed of the speed search.
#[derive(Debug, Clone, Serialize)]
pub struct SpeedStep {
    /// Speed, mm/s.
    pub speed_mm_s: f64,
    /// The slow/fast difference: RMS of F2 − S1 over the bins, µm.
    pub difference_um: f64,
    /// RMS of its σ over the bins, µm.
    pub difference_u_um: f64,
    /// Whether it stays within the tolerance.
    pub within: bool,
    /// Whether a map was stored for it.
    pub mapped: bool,
}

/// The speed search of one feature × tip × direction.
#[derive(Debug, Clone, Serialize)]
pub struct SpeedSearch {
    /// The feature scanned.
    pub feature: String,
    /// The tolerance, µm.
    pub tolerance_um: f64,
    /// Every speed with F1 and F2, rising.
    pub steps: Vec<SpeedStep>,
    /// The fastest speed reached before the difference first leaves the tolerance (no map
    /// needed up to it), mm/s; none when the slowest fast speed already leaves it.
    pub fastest_within_mm_s: Option<f64>,
}

/// The outcome of `dynamic-map`.
#[derive(Debug, Clone, Serialize)]
pub struct Outcome {
    /// The calibration with the maps (unversioned).
    #[serde(skip)]
    pub calibration: Calibration,
    /// Summary parameters with their σ (per map: mean radius change and its parts).
    pub params: Vec<Param>,
    /// Every map measured.
    pub maps: Vec<Map>,
    /// Groups of scans that could not make a map, and why.
    pub skipped: Vec<String>,
    /// The speed search per feature, when a tolerance was given.
    pub speed_search: Vec<SpeedSearch>,
    /// Remarks.
    pub notes: Vec<String>,
}

struct ScanPts {
    segment: u32,
    speed: f64,
    defl: f64,
    idx: Vec<usize>,
}

/// One point in a bin: time, angle from the bin's centre (rad), radial deviation, |d| (mm).
type BinPoint = (i64, f64, f64, f64);

/// One scan's bin: the radial deviation at the bin's centre (a straight line in the angle
/// fitted to its points, so the pattern's slope across the bin is neither a bias nor noise),
/// its σ (from the scatter about the line, inflated by the points' lag-1 correlation in
/// time), the points, and their mean deflection.
#[derive(Debug, Clone, Copy)]
struct Bin {
    value: f64,
    sigma: f64,
    n: usize,
    defl: f64,
}

fn bin_stats(bins: &[Vec<BinPoint>]) -> Vec<Bin> {
    bins.iter()
        .map(|b| {
            let n = b.len();
            if n == 0 {
                return Bin {
                    value: f64::NAN,
                    sigma: f64::NAN,
                    n: 0,
                    defl: f64::NAN,
                };
            }
            let mut v = b.clone();
            v.sort_by_key(|x| x.0);
            let nf = n as f64;
            let mx = v.iter().map(|x| x.1).sum::<f64>() / nf;
            let my = v.iter().map(|x| x.2).sum::<f64>() / nf;
            let sxx: f64 = v.iter().map(|x| (x.1 - mx).powi(2)).sum();
            let sxy: f64 = v.iter().map(|x| (x.1 - mx) * (x.2 - my)).sum();
            let slope = if n >= 3 && sxx > 1e-18 {
                sxy / sxx
            } else {
                0.0
            };
            let value = my - slope * mx;
            let res: Vec<f64> = v.iter().map(|x| x.2 - my - slope * (x.1 - mx)).collect();
            let ss: f64 = res.iter().map(|e| e * e).sum();
            let lag: f64 = res.windows(2).map(|w| w[0] * w[1]).sum();
            let rho = if ss > 0.0 {
                (lag / ss).clamp(0.0, 0.95)
            } else {
                0.0
            };
            let dof = n.saturating_sub(if slope != 0.0 { 2 } else { 1 }).max(1) as f64;
            let var = ss / dof;
            let lever = if sxx > 1e-18 { mx * mx / sxx } else { 0.0 };
            let sigma = (var * (1.0 / nf + lever) * (1.0 + rho) / (1.0 - rho)).sqrt();
            Bin {
                value,
                sigma,
                n,
                defl: v.iter().map(|x| x.3).sum::<f64>() / nf,
            }
        })
        .collect()
}

fn rms(v: &[f64]) -> f64 {
    (v.iter().map(|x| x * x).sum::<f64>() / v.len().max(1) as f64).sqrt()
}

fn missing_what(label: &str, what: &str) -> String {
    format!(
        "{label}: {what}; `dynamic-map` needs S1 (a slow scan at deflection d1), F1 (a fast \
         scan at a second deflection d2, ≥ {MIN_DEFLECTION_SPREAD_MM} mm from d1) and F2 (a fast \
         scan at d1), the same circle in the same direction, e.g. `scancorr sim --program \
         dynamic-map`"
    )
}

/// Measures the maps: `ds` built from the bags with `start` without its `feature_map`
/// effects (this procedure measures them), every point (stride 1) preferably.
pub fn run(ds: &Dataset, start: &Calibration, o: &Options) -> Result<Outcome, ProcedureError> {
    if o.bins < feature_map::MIN_KNOTS {
        return Err(ProcedureError::IllConditioned(format!(
            "--bins {}: at least {} bins are needed",
            o.bins,
            feature_map::MIN_KNOTS
        )));
    }
    if o.tolerance_mm.is_some_and(|t| !(t.is_finite() && t > 0.0)) {
        return Err(ProcedureError::IllConditioned(
            "the speed search's tolerance must be a number > 0".into(),
        ));
    }
    if !(o.min_speed_ratio.is_finite() && o.min_speed_ratio > 1.0) {
        return Err(ProcedureError::IllConditioned(
            "the fast/slow speed ratio must be a number > 1".into(),
        ));
    }
    // Steady points of circle scans: (feature, tip, head, direction) → segment → points.
    type Key = (usize, u32, [i64; 2], i32);
    let mut groups: BTreeMap<Key, BTreeMap<u32, Vec<usize>>> = BTreeMap::new();
    for (i, p) in ds.points.iter().enumerate() {
        let f = &ds.features[p.feature].1;
        if !matches!(f.kind, FeatureKind::Bore | FeatureKind::Boss)
            || p.direction == 0
            || p.phase != Phase::Steady
        {
            continue;
        }
        let h = [p.ctx.head_a1_deg, p.ctx.head_a2_deg].map(|a| (a * 1e3).round() as i64);
        groups
            .entry((p.feature, p.ctx.tip_id, h, p.direction))
            .or_default()
            .entry(p.segment)
            .or_default()
            .push(i);
    }
    if groups.is_empty() {
        return Err(ProcedureError::Missing(missing_what(
            "no circle scans (a bore or boss scanned round at steady speed) in the bags",
            "S1, F1 and F2 are all missing",
        )));
    }
    let mut maps = vec![];
    let mut configs = vec![];
    let mut params = vec![];
    let mut skipped: Vec<(bool, String)> = vec![];
    let mut search = vec![];
    let mut complete = 0usize;
    let thermal = Thermal::of(ds, start);
    for ((fi, tip, h, dir), segs) in &groups {
        let f = &ds.features[*fi].1;
        let label = format!(
            "{} {} (feature {}{}), tip {tip}, {}",
            f.artifact,
            match f.kind {
                FeatureKind::Bore => "bore",
                _ => "boss",
            },
            f.id,
            if ds.features.iter().any(|(b, _)| *b != ds.features[*fi].0) {
                format!(" of bag {}", ds.features[*fi].0 + 1)
            } else {
                String::new()
            },
            if *dir > 0 { "CCW" } else { "CW" }
        );
        let scans: Vec<ScanPts> = segs
            .iter()
            .map(|(s, idx)| ScanPts {
                segment: *s,
                speed: ds.points[idx[0]].speed,
                defl: idx
                    .iter()
                    .map(|&i| ds.points[i].ctx.deflection_probe.norm())
                    .sum::<f64>()
                    / idx.len() as f64,
                idx: idx.clone(),
            })
            .collect();
        let v_slow = scans.iter().map(|s| s.speed).fold(f64::MAX, f64::min);
        let s1 = scans
            .iter()
            .find(|s| (s.speed - v_slow).abs() <= SAME_SPEED * v_slow)
            .expect("the slowest scan");
        let fast: Vec<&ScanPts> = scans
            .iter()
            .filter(|s| s.speed >= o.min_speed_ratio * v_slow)
            .collect();
        if fast.is_empty() {
            skipped.push((
                false,
                missing_what(
                    &label,
                    &format!(
                        "S1 is segment {} ({:.0} mm/s at {:.2} mm) but F1 and F2 are missing \
                         (no scan at ≥ {}× that speed)",
                        s1.segment, s1.speed, s1.defl, o.min_speed_ratio
                    ),
                ),
            ));
            continue;
        }
        let mut speeds: Vec<f64> = fast.iter().map(|s| s.speed).collect();
        speeds.sort_by(|a, b| b.total_cmp(a));
        speeds.dedup_by(|a, b| (*a - *b).abs() <= SAME_SPEED * *b);
        let mut found = vec![];
        for v in speeds {
            let at_v: Vec<&&ScanPts> = fast
                .iter()
                .filter(|s| (s.speed - v).abs() <= SAME_SPEED * v)
                .collect();
            let f2 = at_v
                .iter()
                .filter(|s| (s.defl - s1.defl).abs() <= LEVEL_MM)
                .min_by(|a, b| {
                    (a.defl - s1.defl)
                        .abs()
                        .total_cmp(&(b.defl - s1.defl).abs())
                });
            let f1 = at_v
                .iter()
                .filter(|s| (s.defl - s1.defl).abs() > LEVEL_MM)
                .max_by(|a, b| {
                    (a.defl - s1.defl)
                        .abs()
                        .total_cmp(&(b.defl - s1.defl).abs())
                });
            let (f1, f2) = match (f1, f2) {
                (Some(a), Some(b)) => (a, b),
                (None, Some(_)) => {
                    skipped.push((
                        false,
                        missing_what(
                            &label,
                            &format!(
                                "at {v:.0} mm/s F1 is missing (F2 is there, at S1's deflection \
                                 {:.2} mm; no fast scan at another deflection)",
                                s1.defl
                            ),
                        ),
                    ));
                    continue;
                }
                (Some(_), None) => {
                    skipped.push((
                        false,
                        missing_what(
                            &label,
                            &format!(
                                "at {v:.0} mm/s F2 is missing (no fast scan at S1's deflection \
                                 {:.2} mm)",
                                s1.defl
                            ),
                        ),
                    ));
                    continue;
                }
                (None, None) => continue,
            };
            let (d1, d2) = (s1.defl, f1.defl);
            if (d2 - d1).abs() < MIN_DEFLECTION_SPREAD_MM {
                skipped.push((
                    true,
                    format!(
                        "{label}: at {v:.0} mm/s the deflections d1 {d1:.3} mm and d2 {d2:.3} mm \
                         are too close to extrapolate to zero deflection: scan F1 at least \
                         {MIN_DEFLECTION_SPREAD_MM} mm from d1 (e.g. 0.3 and 0.5 mm)"
                    ),
                ));
                continue;
            }
            match one_map(ds, &label, *tip, *h, *dir, [s1, f1, f2], o, &thermal) {
                Ok(x) => found.push(x),
                Err(e) => skipped.push((true, format!("{label}: {e}"))),
            }
        }
        complete += found.len();
        // Rising speeds; with a tolerance, maps only where the difference leaves it.
        found.reverse();
        let mut steps = vec![];
        let mut fastest_within = None;
        let mut left = false;
        for (m, c, mut p) in found {
            let within = o.tolerance_mm.is_some_and(|t| m.dynamic_rms_um <= t * 1e3);
            left |= !within;
            if !left {
                fastest_within = Some(m.speed_mm_s);
            }
            steps.push(SpeedStep {
                speed_mm_s: m.speed_mm_s,
                difference_um: m.dynamic_rms_um,
                difference_u_um: m.dynamic_u_rms_um,
                within,
                mapped: !within,
            });
            if !within {
                maps.push(m);
                configs.push(c);
                params.append(&mut p);
            }
        }
        if let Some(t) = o.tolerance_mm {
            if !steps.is_empty() {
                search.push(SpeedSearch {
                    feature: label.clone(),
                    tolerance_um: t * 1e3,
                    steps,
                    fastest_within_mm_s: fastest_within,
                });
            }
        }
    }
    if complete == 0 {
        let ill = skipped.iter().all(|(ill, _)| *ill);
        let msg = skipped
            .into_iter()
            .map(|(_, m)| m)
            .collect::<Vec<_>>()
            .join("\n");
        return Err(if ill {
            ProcedureError::IllConditioned(msg)
        } else {
            ProcedureError::Missing(msg)
        });
    }
    // The new maps replace the start's maps of the same scans (static maps stay: they add).
    let mut calibration = start.clone();
    calibration.effects.retain(|e| match e {
        EffectConfig::FeatureMap(old) => !configs.iter().any(|n| n.replaces(old)),
        _ => true,
    });
    calibration
        .effects
        .extend(configs.into_iter().map(EffectConfig::FeatureMap));
    let mut notes = vec![
        "the maps hold only what differs between the fast and the slow scans (and the \
         deflection's error at speed): errors common to both stay with the other effects"
            .to_string(),
        "a map applies to later scans with the same segment ids (a like part measured by the \
         same part program, in the same place), the same tip and head angles, at its speed ±5 %"
            .to_string(),
        if o.tolerance_mm.is_some() {
            "speed search: a speed whose slow/fast difference (RMS of F2 − S1) stays within the \
             tolerance needs no map and gets none"
                .to_string()
        } else {
            "each map is for the speed its fast scans were made at (give a tolerance for the \
             speed search)"
                .to_string()
        },
    ];
    notes.push(if thermal.slots.iter().all(|s| s.is_none()) {
        "no scale temperatures in the bags: what the scales' expansion moves between and during \
         the scans is not in the maps' σ"
            .to_string()
    } else if start
        .effects
        .iter()
        .any(|e| matches!(e, EffectConfig::ScaleThermal(_)))
    {
        format!(
            "the scales' expansion is corrected by the start's `scale_thermal`; {:.0} % of its \
             coefficients is in the maps' σ",
            ALPHA_SHARE * 100.0
        )
    } else {
        format!(
            "the start does not correct the scales' expansion: what the room's drift moves \
             between and during the scans (for a typical {:.1} ppm/K, from the measured scale \
             temperatures) is in the maps' σ; `calibrate scales` first removes most of it",
            ALPHA_TYPICAL_PER_K * 1e6
        )
    });
    Ok(Outcome {
        calibration,
        params,
        maps,
        skipped: skipped.into_iter().map(|(_, m)| m).collect(),
        speed_search: search,
        notes,
    })
}

#[allow(clippy::type_complexity)]
fn one_map(
    ds: &Dataset,
    label: &str,
    tip: u32,
    h: [i64; 2],
    dir: i32,
    [s1, f1, f2]: [&ScanPts; 3],
    o: &Options,
    thermal: &Thermal,
) -> Result<(Map, feature_map::Config, Vec<Param>), String> {
    let n = o.bins;
    // The map's centre: S1's carriage path (scales + deflection), where the map's angle is
    // taken.
    let carr: Vec<Vec3> = s1
        .idx
        .iter()
        .map(|&i| ds.points[i].ctx.scale + ds.points[i].ctx.deflection)
        .collect();
    let cc = shape::fit_circle(&carr).map_err(|e| format!("S1's carriage path: {e}"))?;
    let center = [cc.center.x, cc.center.y];
    // Each scan's radial deviation about its own centre from S1's radius: the centre moves
    // between the scans as the room drifts (the scales grow), and where a like part lies is
    // never known, so the map holds no translation.
    let fit = |sc: &ScanPts, role: &str| {
        let surf: Vec<Vec3> = sc.idx.iter().map(|&i| ds.points[i].surface).collect();
        shape::fit_circle(&surf).map_err(|e| format!("{role}'s circle: {e}"))
    };
    let r_s1 = fit(s1, "S1")?.radius;
    let mut stats = vec![];
    // The scales' expansion per unit α, per scan, axis and bin (see the module doc); None
    // when a scan has no scale temperatures.
    let mut therm: Option<Vec<[Vec<f64>; 3]>> = Some(vec![]);
    let mut s1_const = [0.0; 3];
    let tref: [f64; 3] = std::array::from_fn(|ax| {
        thermal.slots[ax]
            .and_then(|sl| temp_line(ds, &s1.idx, sl))
            .map_or(0.0, |l| l.1)
    });
    for (role, sc) in [("S1", s1), ("F1", f1), ("F2", f2)] {
        let c = fit(sc, role)?.center;
        let th_of = |i: usize| {
            let p = &ds.points[i];
            let (th, _) = feature_map::angle(&p.ctx, center)?;
            let u = th / TAU * n as f64;
            let d = (p.surface - c).xy();
            let r = d.norm();
            (r > 0.0).then(|| {
                (
                    (u.round() as usize) % n,
                    th,
                    Vec3::new(d.x / r, d.y / r, 0.0),
                )
            })
        };
        if let Some(t) = therm.as_mut() {
            match thermal_bins(ds, sc, &th_of, n, thermal, tref) {
                Some((mut g, k)) => {
                    if role == "S1" {
                        s1_const = k;
                    }
                    for (ax, b) in g.iter_mut().enumerate() {
                        b.iter_mut().for_each(|x| *x -= s1_const[ax]);
                    }
                    t.push(g);
                }
                None => therm = None,
            }
        }
        let mut bins: Vec<Vec<BinPoint>> = vec![vec![]; n];
        for &i in &sc.idx {
            let p = &ds.points[i];
            let Some((th, _)) = feature_map::angle(&p.ctx, center) else {
                continue;
            };
            let u = th / TAU * n as f64;
            let j = (u.round() as usize) % n;
            let dth = (u - u.round()) * TAU / n as f64;
            let r = (p.surface - c).xy().norm() - r_s1;
            bins[j].push((p.ctx.t_ns, dth, r, p.ctx.deflection_probe.norm()));
        }
        let st = bin_stats(&bins);
        if let Some((j, b)) = st.iter().enumerate().find(|(_, b)| b.n < MIN_BIN_POINTS) {
            return Err(format!(
                "{role} (segment {}) has {} steady-speed points in the bin at θ = {:.1}° (needs \
                 {MIN_BIN_POINTS}): scan the full circle at steady speed, or use fewer bins",
                sc.segment,
                b.n,
                360.0 * j as f64 / n as f64
            ));
        }
        stats.push(st);
    }
    let um = |v: f64| v * 1e3;
    let mut m = Map {
        id: format!("dynamic_map_s{}", f2.segment),
        feature: label.to_string(),
        tip,
        head_deg: h.map(|a| a as f64 / 1e3),
        direction: dir,
        speed_mm_s: f2.speed,
        slow_speed_mm_s: s1.speed,
        d1_mm: s1.defl,
        d2_mm: f1.defl,
        segments: vec![f2.segment, f1.segment],
        scans: vec![],
        theta_deg: (0..n).map(|j| 360.0 * j as f64 / n as f64).collect(),
        s1_um: vec![],
        s1_u_um: vec![],
        f1_um: vec![],
        f1_u_um: vec![],
        f2_um: vec![],
        f2_u_um: vec![],
        hszd_um: vec![],
        lszd_um: vec![],
        e1_um: vec![],
        e1_u_um: vec![],
        e2_um: vec![],
        e2_u_um: vec![],
        e2_rms_um: 0.0,
        e2_u_rms_um: 0.0,
        e2_u_noise_rms_um: 0.0,
        e2_u_scales_rms_um: 0.0,
        dynamic_rms_um: 0.0,
        e1_rms_um: 0.0,
        dynamic_u_rms_um: 0.0,
    };
    // Per bin, with each scan's own measured deflection there (a fast scan runs at a slightly
    // other deflection than its nominal one: the carriage's path shrinks at speed):
    // k = (F1 − F2)/(dF1 − dF2), HSZD = F2 − k·dF2, LSZD = S1 − k·dS1, e1 = k·dF2,
    // e2 = F2 − LSZD. Each is linear in S1, F1, F2: σ by their coefficients.
    let (mut a, mut b, mut u, mut dynamic, mut dyn_u, mut k_u) =
        (vec![], vec![], vec![], vec![], vec![], vec![]);
    let (mut noise_e2, mut therm_e2, mut dyn_total) = (vec![], vec![], vec![]);
    // Per summary parameter (e2, the dynamic part, k): the bins' mean thermal part per axis.
    let mut jsum = [[0.0; 3]; 3];
    for j in 0..n {
        let (bs, b1, b2) = (stats[0][j], stats[1][j], stats[2][j]);
        let dd = b1.defl - b2.defl;
        if dd.abs() < 0.5 * MIN_DEFLECTION_SPREAD_MM {
            return Err(format!(
                "F1 and F2 differ by only {:.3} mm of deflection at θ = {:.1}°: too little to \
                 extrapolate to zero deflection",
                dd,
                360.0 * j as f64 / n as f64
            ));
        }
        let k = (b1.value - b2.value) / dd;
        let hszd = b2.value - k * b2.defl;
        let lszd = bs.value - k * bs.defl;
        let e1 = k * b2.defl;
        let e2 = b2.value - lszd;
        let sig = |c: [f64; 3]| {
            ((c[0] * bs.sigma).powi(2) + (c[1] * b1.sigma).powi(2) + (c[2] * b2.sigma).powi(2))
                .sqrt()
        };
        // The scales' expansion through the same coefficients: per axis, per unit α.
        let tj = |c: [f64; 3]| -> [f64; 3] {
            std::array::from_fn(|ax| {
                therm.as_ref().map_or(0.0, |g| {
                    c[0] * g[0][ax][j] + c[1] * g[1][ax][j] + c[2] * g[2][ax][j]
                })
            })
        };
        let tvar = |t: [f64; 3]| {
            (0..3)
                .map(|ax| (t[ax] * thermal.sigma_alpha[ax]).powi(2))
                .sum::<f64>()
        };
        // Coefficients of (S1, F1, F2).
        let g = (b2.defl - bs.defl) / dd;
        let (e1c, e2c) = (
            [0.0, b2.defl / dd, -b2.defl / dd],
            [-1.0, bs.defl / dd, 1.0 - bs.defl / dd],
        );
        let (dync, kc) = ([-1.0, -g, 1.0 + g], [0.0, 1.0 / dd, -1.0 / dd]);
        let e1_u = sig(e1c).hypot(tvar(tj(e1c)).sqrt());
        let e2_noise = sig(e2c);
        let e2_therm = tvar(tj(e2c)).sqrt();
        let e2_u = e2_noise.hypot(e2_therm);
        noise_e2.push(e2_noise);
        therm_e2.push(um(e2_therm));
        dyn_u.push(sig(dync));
        k_u.push(sig(kc));
        for (sum, c) in jsum.iter_mut().zip([e2c, dync, kc]) {
            for (s, t) in sum.iter_mut().zip(tj(c)) {
                *s += t / n as f64;
            }
        }
        dyn_total.push(sig(dync).hypot(tvar(tj(dync)).sqrt()));
        m.s1_um.push(um(bs.value));
        m.s1_u_um.push(um(bs.sigma));
        m.f1_um.push(um(b1.value));
        m.f1_u_um.push(um(b1.sigma));
        m.f2_um.push(um(b2.value));
        m.f2_u_um.push(um(b2.sigma));
        m.hszd_um.push(um(hszd));
        m.lszd_um.push(um(lszd));
        m.e1_um.push(um(e1));
        m.e1_u_um.push(um(e1_u));
        m.e2_um.push(um(e2));
        m.e2_u_um.push(um(e2_u));
        dynamic.push(hszd - lszd);
        a.push(-(hszd - lszd));
        b.push(-k);
        u.push(e2_u);
    }
    if a.iter().chain(&b).chain(&u).any(|x| !x.is_finite()) {
        return Err("the map is not finite (a scan without points in a bin)".into());
    }
    m.e2_rms_um = rms(&m.e2_um);
    m.e2_u_rms_um = rms(&m.e2_u_um);
    m.dynamic_rms_um = um(rms(&dynamic));
    m.e1_rms_um = rms(&m.e1_um);
    m.dynamic_u_rms_um = um(rms(&dyn_total));
    m.e2_u_noise_rms_um = um(rms(&noise_e2));
    m.e2_u_scales_rms_um = rms(&therm_e2);
    for (k, (role, sc)) in [("S1", s1), ("F1", f1), ("F2", f2)].into_iter().enumerate() {
        m.scans.push(Scan {
            role,
            segment: sc.segment,
            speed_mm_s: sc.speed,
            deflection_mm: sc.defl,
            points: sc.idx.len(),
            mean_radial_um: um(stats[k].iter().map(|s| s.value).sum::<f64>() / n as f64),
        });
    }
    // Summary parameters: the bins' means (radius changes), σ from the bins' σ.
    let nn = n as f64;
    let mean = |v: &[f64]| v.iter().sum::<f64>() / nn;
    // The bins' noise averages out over them; the scales' part (one pattern) only as its mean.
    let mean_sigma = |v: &[f64], k: usize| {
        let t: f64 = (0..3)
            .map(|ax| (jsum[k][ax] * thermal.sigma_alpha[ax]).powi(2))
            .sum();
        (v.iter().map(|x| x * x).sum::<f64>() / (nn * nn) + t).sqrt()
    };
    let e2: Vec<f64> = m.e2_um.iter().map(|x| x * 1e-3).collect();
    let params = vec![
        Param {
            name: format!("{}.radius_change_mm", m.id),
            value: mean(&e2),
            sigma: mean_sigma(&noise_e2, 0),
        },
        Param {
            name: format!("{}.dynamic_radius_change_mm", m.id),
            value: mean(&dynamic),
            sigma: mean_sigma(&dyn_u, 1),
        },
        Param {
            name: format!("{}.deflection_error_per_mm", m.id),
            value: -mean(&b),
            sigma: mean_sigma(&k_u, 2),
        },
    ];
    let cfg =
        feature_map::Config {
            id: Some(m.id.clone()),
            feature: Some(format!(
            "{label}: S1 segment {} ({:.0} mm/s, {:.3} mm), F1 segment {} ({:.0} mm/s, {:.3} mm), \
             F2 segment {} ({:.0} mm/s, {:.3} mm)",
            s1.segment, s1.speed, s1.defl, f1.segment, f1.speed, f1.defl, f2.segment, f2.speed,
            f2.defl
        )),
            segments: m.segments.clone(),
            tip,
            head_deg: m.head_deg,
            speed_mm_s: Some(f2.speed),
            speed_tolerance_mm_s: Some(o.speed_tolerance * f2.speed),
            center_mm: center,
            // The place: S1's carriage path (its radius about the centre and its height). A
            // like part by the same program stands where the master did (its angle is taken
            // about the master's centre) within PLACE_TOLERANCE_MM; another program reusing
            // these segment ids at this speed elsewhere, or on another size, gets no map.
            radius_mm: Some(cc.radius),
            z_mm: Some(carr.iter().map(|p| p.z).sum::<f64>() / carr.len().max(1) as f64),
            place_tolerance_mm: PLACE_TOLERANCE_MM,
            latitude_deg: 0.0,
            values_mm: a,
            per_deflection: b,
            deflection_mm: Some(f2.defl),
            values_u_mm: u,
        };
    cfg.build().map_err(|e| format!("the map: {e}"))?;
    Ok((m, cfg, params))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bin_statistics_follow_the_slope_and_inflate_for_correlation() {
        // A straight line across the bin: its value at the centre, no scatter left.
        let line: Vec<BinPoint> = (0..20)
            .map(|k| {
                let x = (k as f64 - 9.0) * 1e-3;
                (k, x, 0.5 + 3.0 * x, 0.3)
            })
            .collect();
        // The same residuals, alternating (white) or in two runs (correlated).
        let white: Vec<BinPoint> = (0..100)
            .map(|k| (k, 0.0, if k % 2 == 0 { 1.0 } else { -1.0 }, 0.3))
            .collect();
        let slow: Vec<BinPoint> = (0..100)
            .map(|k| (k, 0.0, if k < 50 { 1.0 } else { -1.0 }, 0.3))
            .collect();
        let st = bin_stats(&[line, white, slow, vec![]]);
        assert!(
            (st[0].value - 0.5).abs() < 1e-12 && st[0].sigma < 1e-9,
            "{st:?}"
        );
        assert!(
            (st[1].sigma - (1.0f64 / 99.0).sqrt()).abs() < 1e-12,
            "{st:?}"
        );
        assert!(st[2].sigma > 3.0 * st[1].sigma, "{st:?}");
        assert!((st[2].defl - 0.3).abs() < 1e-12);
        assert_eq!(st[3].n, 0);
    }
}
