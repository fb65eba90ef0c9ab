//! The real-time form of the extrapolation to zero force on a scan whose deflection varies as
//! a wave around its circle (`probe-force` variant b): two readings of one place at two
//! forces give the reading at zero force, R0 = R1 − (R2 − R1)·F1/(F2 − F1)
//! ([`zero_force::two_force`]).
//!
//! The readings. The deflection's median crossings cut the scan into its waves; each wave's
//! points above its median deflection are the higher-force reading H_w (mean angle θ_H about
//! the sphere's axis, force F2, radial reading R2), those below it a lower-force reading L_w.
//! H_w and L_w are half a wave apart (12° at 15 waves a turn), not one place: the reading
//! there is y(θ) = s(θ) − k(θ)·F(θ), s the static error map, k(θ) = n̂ᵀ·R·K_t·Rᵀ·n̂ the
//! stylus's bending per unit deflection along the normal at θ. A stylus stiffer one way than
//! the other (machine 47's tip 1: k_v = 2.2·k_u) gives an equator circle k(θ) = k̄ − ½(k_v −
//! k_u)·cos 2θ, and pairing H_w with L_w side by side gives
//!
//! R0 − s = F1·F2·(k(θ_H) − k(θ_L))/(F2 − F1) + (s(θ_L) − s(θ_H))·F2/(F2 − F1),
//!
//! i.e. (k_v − k_u)·sin 2θ·Δθ·F1·F2/(F2 − F1) from the bending alone: on machine 47 run 4,
//! 0.30–0.66 µm, 15 % of the lower reading's 2.2–4.1 µm of bending (measured with every other
//! effect off in the simulator: the same 15 %; neither drift, the carriage's acceleration nor
//! the comparison's reference, which takes the fit's surface through the same arithmetic).
//!
//! So the lower-force reading is taken at H_w's place: R1 = Σ_j ℓ_j(θ_H)·R_{L_j}, F1 = Σ_j
//! ℓ_j(θ_H)·F_{L_j}, the Lagrange interpolation (a cubic) through the [`NODES_EACH_SIDE`]
//! lower-force halves nearest H_w on each side in angle (at ±½ and ±1½ waves on a whole turn:
//! weights −1/16, 9/16, 9/16, −1/16). A smooth k(θ)·F1 and s(θ) pass through it up to its
//! fourth-order term, and each half's mean of k·F differs from k at the half's mean angle
//! times its mean force: together ≈ 0.5 % of the bending on machine 47 (0.013–0.028 µm,
//! against 15 % side by side). A static map with harmonics above half the waves per turn
//! (7 at 15) is not interpolated by the lower halves, which sample it only once a wave.
//!
//! What is reported: each wave's R0 against the fit's zero-force model of the same points put
//! through the same arithmetic (M0; its static map and drift), the fit's own bending put
//! through it too (what the form leaves of a bending that varies with the place: the
//! systematic part, predicted), and what is left beyond that against R0's statistical σ (the
//! points' noise through the weights); and the side-by-side pairing's figures beside them.
//! With no lower halves on both sides (a scan that is not a whole turn) a wave is not paired.

use crate::calibrate::zero_force::{self, Reading, ZeroForce};
use serde::Serialize;

/// Least within-scan spread (5th to 95th percentile) of a scan whose deflection varies, mm.
pub const VARYING_MM: f64 = 0.1;
/// Lower-force halves each side of a higher-force half that its lower reading is
/// interpolated from (2: a cubic).
pub const NODES_EACH_SIDE: usize = 2;

/// One point of a varying scan, as the force fit sees it.
#[derive(Debug, Clone, Copy)]
pub struct Point {
    /// Angle about the sphere's axis, rad.
    pub theta: f64,
    /// Latitude on the sphere, rad.
    pub latitude: f64,
    /// The force (the probe's deflection |d|), mm.
    pub f: f64,
    /// The radial reading without force correction, mm.
    pub y: f64,
    /// The fit's zero-force model of the reading (static map, drift), mm.
    pub model: f64,
    /// The fit's bending in the reading (−n·R·K·d: the reading is short by it), mm.
    pub bending: f64,
    /// Time, ns.
    pub t_ns: i64,
    /// The estimated carriage acceleration along the normal, mm/s².
    pub accel: f64,
}

/// The real-time form (two forces per place, R0 = R1 − (R2 − R1)·F1/(F2 − F1)) on one scan
/// whose deflection varies within it.
#[derive(Debug, Clone, Serialize)]
pub struct RealTime {
    /// Tip.
    pub tip: u32,
    /// Head angles, degrees.
    pub head_deg: [f64; 2],
    /// Command segment of the scan.
    pub segment: u32,
    /// Latitude of the circle on the sphere, degrees.
    pub latitude_deg: f64,
    /// Deflection range scanned (5th, 95th percentile), mm.
    pub deflection_mm: [f64; 2],
    /// Waves of the deflection around the scan (one pair of readings each).
    pub waves: usize,
    /// Waves extrapolated to zero force.
    pub extrapolated: usize,
    /// Waves whose lower force was below significance (taken as zero).
    pub force_zero: usize,
    /// Waves whose two forces did not differ significantly (no zero-force value).
    pub alike: usize,
    /// Waves without lower-force halves on both sides to take the lower reading at the higher
    /// one's place (not paired).
    pub unpaired: usize,
    /// RMS over the waves of the lower-force reading R1 minus the fit's zero-force value of
    /// the same points: the force's error that the real-time form removes, µm.
    pub before_um: f64,
    /// RMS of R0 minus the fit's zero-force value of the same points, µm.
    pub rms_um: f64,
    /// RMS of R0's statistical standard uncertainty (the points' noise), µm.
    pub sigma_um: f64,
    /// RMS of what the form leaves of the fit's own bending (a bending that varies with the
    /// place, through the interpolation and the halves' means): the systematic part
    /// `rms_um` is expected to hold beside `sigma_um`, µm.
    pub systematic_um: f64,
    /// RMS of R0 minus the fit's zero-force value minus that systematic part: what the
    /// bending's variation does not explain, to compare with `sigma_um`, µm.
    pub unexplained_um: f64,
    /// RMS of R0 minus the fit's value with each wave's halves paired side by side (half a
    /// wave apart, not one place), µm.
    pub side_by_side_um: f64,
    /// The systematic part the fit's bending predicts for the side-by-side pairing, µm.
    pub side_by_side_systematic_um: f64,
    /// The carriage's radial acceleration per mm of deflection in this scan (estimated from
    /// the command), mm/s² per mm: a compliance C acts like a force coefficient −C times this.
    pub accel_per_deflection_s2: f64,
}

/// The 5th, 50th and 95th percentiles of the deflections when they vary enough within one scan
/// for the real-time form (a spread ≥ [`VARYING_MM`] over ≥ 40 points).
pub fn varying(defl: &[f64]) -> Option<[f64; 3]> {
    if defl.len() < 40 {
        return None;
    }
    let mut d = defl.to_vec();
    d.sort_by(f64::total_cmp);
    let pct = |q: f64| d[((d.len() - 1) as f64 * q).round() as usize];
    let p = [pct(0.05), pct(0.5), pct(0.95)];
    (p[2] - p[0] >= VARYING_MM).then_some(p)
}

/// One half of a wave: sums of n, angle (unwrapped), F, y, model, bending.
#[derive(Clone, Copy, Default)]
struct Half([f64; 6]);

impl Half {
    fn add(&mut self, th: f64, p: &Point) {
        for (s, v) in self
            .0
            .iter_mut()
            .zip([1.0, th, p.f, p.y, p.model, p.bending])
        {
            *s += v;
        }
    }
    fn mean(&self, k: usize) -> f64 {
        self.0[k] / self.0[0]
    }
}

/// A reading of column `col` (3: y, 4: model, 5: bending) from halves with weights.
fn reading(parts: &[(f64, &Half)], col: usize, r_sigma: f64, f_sigma: f64) -> Reading {
    let s2: f64 = parts.iter().map(|(w, h)| w * w / h.0[0]).sum();
    Reading {
        r: parts.iter().map(|(w, h)| w * h.mean(col)).sum(),
        r_sigma: r_sigma * s2.sqrt(),
        f: parts.iter().map(|(w, h)| w * h.mean(2)).sum(),
        f_sigma: f_sigma * s2.sqrt(),
    }
}

/// R0 − M0 and the bending's share of it for one pair, with R0's σ (None: alike forces).
fn pair(lo: &[(f64, &Half)], hi: &Half, r_sigma: f64, f_sigma: f64) -> (ZeroForce, [f64; 4]) {
    let h = [(1.0, hi)];
    let two = |col: usize| {
        zero_force::two_force(
            reading(lo, col, r_sigma, f_sigma),
            reading(&h, col, r_sigma, f_sigma),
        )
    };
    let (z, m, b) = (two(3), two(4), two(5));
    let lower = reading(lo, 3, r_sigma, f_sigma).r - reading(lo, 4, r_sigma, f_sigma).r;
    let v = match (z.value(), m.value(), b.value()) {
        (Some((r0, s0)), Some((m0, _)), Some((b0, _))) => [r0 - m0, b0, s0, lower],
        _ => [f64::NAN; 4],
    };
    (z, v)
}

/// Lagrange weights at `x` of the nodes `xs`.
fn lagrange(xs: &[f64], x: f64) -> Vec<f64> {
    (0..xs.len())
        .map(|j| {
            (0..xs.len())
                .filter(|&m| m != j)
                .map(|m| (x - xs[m]) / (xs[j] - xs[m]))
                .product()
        })
        .collect()
}

fn rms(v: &[f64]) -> f64 {
    (v.iter().map(|x| x * x).sum::<f64>() / v.len().max(1) as f64).sqrt()
}

/// The real-time form on one varying scan (`pts` its points, `pct` from [`varying`]) with
/// `point_sigma` (mm) the noise of one radial reading.
pub fn scan(
    tip: u32,
    head_deg: [f64; 2],
    segment: u32,
    pts: &[Point],
    pct: [f64; 3],
    point_sigma: f64,
) -> RealTime {
    let [d5, d50, d95] = pct;
    // Points in order around the circle; the waves from the crossings of the median.
    let mut order: Vec<&Point> = pts.iter().collect();
    order.sort_by(|a, b| a.theta.total_cmp(&b.theta));
    // Crossings with hysteresis (a quarter of the wave's amplitude either side of the
    // median): the deflection's noise near the median makes no crossing of its own.
    let band = 0.125 * (d95 - d5);
    let (mut side, mut first) = (0i8, 0i8);
    let mut crossings = 0usize;
    // Where the first upward crossing is: the waves are cut there, so that each holds one
    // rise above the median and one fall below it, side by side.
    let mut rise_at: Option<usize> = None;
    for (k, p) in order.iter().enumerate() {
        let now = if p.f > d50 + band {
            1
        } else if p.f < d50 - band {
            -1
        } else {
            continue;
        };
        if side != 0 && now != side {
            crossings += 1;
            if now == 1 && rise_at.is_none() {
                rise_at = Some(k);
            }
        }
        if first == 0 {
            first = now;
        }
        side = now;
    }
    // Around the circle: the crossing between the last point and the first.
    if first != 0 && side != first {
        crossings += 1;
    }
    let waves = (crossings / 2).max(1);
    // The deflection's noise from its second differences in time (the wave is smooth over
    // three samples): σ² = E[(d₋ − 2d + d₊)²]/6.
    let mut by_t: Vec<&Point> = pts.iter().collect();
    by_t.sort_by_key(|p| p.t_ns);
    let d2: Vec<f64> = by_t
        .windows(3)
        .map(|w| (w[0].f - 2.0 * w[1].f + w[2].f).powi(2))
        .collect();
    let f_sigma = (d2.iter().sum::<f64>() / (6.0 * d2.len().max(1) as f64))
        .sqrt()
        .max(1e-6);
    if let Some(k) = rise_at {
        order.rotate_left(k);
    }
    // Angles unwrapped from the first point on.
    let th0 = order[0].theta;
    let unwrap = |t: f64| {
        if t < th0 {
            t + std::f64::consts::TAU
        } else {
            t
        }
    };
    let span = unwrap(order[order.len() - 1].theta) - th0;
    let whole = span > std::f64::consts::TAU * (1.0 - 0.5 / waves as f64);
    // Each wave's halves: above (index 1) and below (0) its median deflection.
    let per = order.len() as f64 / waves as f64;
    let mut halves: Vec<Option<[Half; 2]>> = vec![];
    for w in 0..waves {
        let lo_i = (w as f64 * per).round() as usize;
        let hi_i = (((w + 1) as f64 * per).round() as usize).min(order.len());
        let bin = &order[lo_i..hi_i];
        let mut bd: Vec<f64> = bin.iter().map(|p| p.f).collect();
        bd.sort_by(f64::total_cmp);
        if bd.len() < 8 {
            halves.push(None);
            continue;
        }
        let med = bd[bd.len() / 2];
        let mut h = [Half::default(); 2];
        for p in bin {
            h[usize::from(p.f > med)].add(unwrap(p.theta), p);
        }
        halves.push((h[0].0[0] >= 3.0 && h[1].0[0] >= 3.0).then_some(h));
    }
    // The lower-force halves by angle (on a whole turn, with their copies a turn either side).
    let mut lows: Vec<(f64, Half)> = vec![];
    for shift in [-1.0, 0.0, 1.0] {
        if shift != 0.0 && !whole {
            continue;
        }
        for h in halves.iter().flatten() {
            let mut l = h[0];
            l.0[1] += shift * std::f64::consts::TAU * l.0[0];
            lows.push((l.mean(1), l));
        }
    }
    lows.sort_by(|a, b| a.0.total_cmp(&b.0));
    let (mut n_ex, mut n_zero, mut n_alike, mut n_unpaired) = (0, 0, 0, 0);
    let (mut rt, mut bend, mut sig, mut left, mut before) =
        (vec![], vec![], vec![], vec![], vec![]);
    let (mut side_rt, mut side_bend) = (vec![], vec![]);
    let wave_angle = span.max(1e-9) / waves as f64;
    for h in halves.iter().flatten() {
        // Side by side: the wave's own two halves.
        let (_, v) = pair(&[(1.0, &h[0])], &h[1], point_sigma, f_sigma);
        if v[0].is_finite() {
            side_rt.push(v[0]);
            side_bend.push(v[1]);
        }
        // At one place: the lower reading interpolated to the higher half's angle.
        let th = h[1].mean(1);
        let split = lows.partition_point(|l| l.0 < th);
        let n = NODES_EACH_SIDE;
        let nodes = (split >= n && split + n <= lows.len())
            .then(|| &lows[split - n..split + n])
            .filter(|v| v[2 * n - 1].0 - v[0].0 < (2 * n) as f64 * wave_angle);
        let Some(nodes) = nodes else {
            n_unpaired += 1;
            continue;
        };
        let xs: Vec<f64> = nodes.iter().map(|l| l.0).collect();
        let parts: Vec<(f64, &Half)> = lagrange(&xs, th)
            .into_iter()
            .zip(nodes.iter().map(|l| &l.1))
            .collect();
        let (z, v) = pair(&parts, &h[1], point_sigma, f_sigma);
        match z {
            ZeroForce::Extrapolated { .. } => n_ex += 1,
            ZeroForce::ForceZero { .. } => n_zero += 1,
            ZeroForce::Alike => n_alike += 1,
        }
        if v[0].is_finite() {
            rt.push(v[0]);
            bend.push(v[1]);
            sig.push(v[2]);
            left.push(v[0] - v[1]);
            before.push(v[3]);
        }
    }
    // The radial acceleration against the deflection (least-squares slope).
    let (mut sd, mut sa, mut sdd, mut sda) = (0.0, 0.0, 0.0, 0.0);
    for p in pts {
        sd += p.f;
        sa += p.accel;
        sdd += p.f * p.f;
        sda += p.f * p.accel;
    }
    let sn = pts.len() as f64;
    let var = sdd / sn - (sd / sn).powi(2);
    let slope = if var > 0.0 {
        (sda / sn - sd / sn * sa / sn) / var
    } else {
        0.0
    };
    let lat = pts.iter().map(|p| p.latitude).sum::<f64>() / sn;
    RealTime {
        tip,
        head_deg,
        segment,
        latitude_deg: lat.to_degrees(),
        deflection_mm: [d5, d95],
        waves,
        extrapolated: n_ex,
        force_zero: n_zero,
        alike: n_alike,
        unpaired: n_unpaired,
        before_um: rms(&before) * 1e3,
        rms_um: rms(&rt) * 1e3,
        sigma_um: rms(&sig) * 1e3,
        systematic_um: rms(&bend) * 1e3,
        unexplained_um: rms(&left) * 1e3,
        side_by_side_um: rms(&side_rt) * 1e3,
        side_by_side_systematic_um: rms(&side_bend) * 1e3,
        accel_per_deflection_s2: slope,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A whole turn at `waves` waves, the reading s(θ) − k(θ)·F(θ) with k = k̄ − δ·cos 2θ.
    fn turn(waves: f64, dk: f64, s: impl Fn(f64) -> f64) -> Vec<Point> {
        let n = 9000;
        (0..n)
            .map(|i| {
                let theta = -std::f64::consts::PI + i as f64 * std::f64::consts::TAU / n as f64;
                let f = 0.3 + 0.2 * (waves * theta).sin();
                let k = 0.016 - dk * (2.0 * theta).cos();
                Point {
                    theta,
                    latitude: 0.0,
                    f,
                    y: s(theta) - k * f,
                    model: s(theta),
                    bending: -k * f,
                    t_ns: i as i64 * 1_000_000,
                    accel: -f,
                }
            })
            .collect()
    }

    #[test]
    fn the_lower_reading_at_the_higher_ones_place_removes_what_side_by_side_leaves() {
        // A stylus twice as stiff one way: side by side the halves read two places of
        // different bending; the interpolated pairing leaves a fraction of a percent, and the
        // fit's own bending through the same arithmetic predicts it exactly (noise-free).
        let pts = turn(15.0, 0.006, |t| 1e-4 * (2.0 * t).cos());
        let pct = varying(&pts.iter().map(|p| p.f).collect::<Vec<_>>()).unwrap();
        let r = scan(1, [0.0; 2], 1, &pts, pct, 1e-4);
        assert_eq!((r.waves, r.extrapolated, r.unpaired), (15, 15, 0), "{r:?}");
        assert!(r.before_um > 2.0, "{r:?}");
        assert!(r.side_by_side_um > 0.1 * r.before_um, "{r:?}");
        assert!(r.rms_um < 0.01 * r.before_um, "{r:?}");
        assert!((r.rms_um - r.systematic_um).abs() < 1e-9, "{r:?}");
        assert!(r.unexplained_um < 1e-9, "{r:?}");
        assert!((r.side_by_side_um - r.side_by_side_systematic_um).abs() < 1e-9);
        // A bending the same all round: nothing left either way.
        let r = scan(1, [0.0; 2], 1, &turn(15.0, 0.0, |_| 0.0), pct, 1e-4);
        assert!(r.rms_um < 1e-6 && r.side_by_side_um < 1e-6, "{r:?}");
    }
}
