//! ΔR per scan of a ring as the ring-gauge patent reports it — along X and Y, the ellipse's
//! largest and smallest radius change — and ΔR per acceleration per position, each with its σ
//! (the equations are in [`super`]'s doc).

use super::Scan;

/// Per scan: the sums ΔR, its X/Y split, its ellipse and their σ are taken from.
#[derive(Default)]
pub(super) struct ScanSums {
    /// Σe before the fitted dynamics (after the static pattern).
    pub(super) before: f64,
    /// Σe after.
    pub(super) after: f64,
    pub(super) n: usize,
    /// Σe·cos 2θ, Σe·sin 2θ before.
    pub(super) cos2: f64,
    pub(super) sin2: f64,
    /// Σe² after.
    pub(super) after2: f64,
    /// Σcos 2θ, Σcos² 2θ.
    pub(super) c: f64,
    pub(super) cc: f64,
}

impl ScanSums {
    /// The scan: e(θ) ≈ a0 + a2·cos 2θ + b2·sin 2θ + …, ΔR along X a0 + a2, along Y a0 − a2;
    /// each a linear combination of the points, so its variance is the scan's residual
    /// variance s² (× `inflate` for the lag correlation) times the combination's Σw², widened
    /// by (1 + n/N) for the position's static pattern (fitted from its N points) it is
    /// taken against.
    pub(super) fn scan(
        &self,
        v: f64,
        d: i32,
        radius: f64,
        inflate: f64,
        place_points: usize,
    ) -> Scan {
        let n = self.n.max(1) as f64;
        let (a0, a2, b2) = (self.before / n, 2.0 * self.cos2 / n, 2.0 * self.sin2 / n);
        let s2 = self.after2 / n * inflate * (1.0 + n / (place_points.max(self.n) as f64));
        let var = |sign: f64| (s2 * (n + 4.0 * sign * self.c + 4.0 * self.cc) / (n * n)).max(0.0);
        let amp = a2.hypot(b2);
        Scan {
            speed_mm_s: v,
            direction: d,
            accel_mm_s2: v * v / radius,
            delta_r_um: a0 * 1e3,
            delta_r_after_um: self.after / n * 1e3,
            delta_r_x_um: (a0 + a2) * 1e3,
            delta_r_y_um: (a0 - a2) * 1e3,
            delta_r_x_sigma_um: var(1.0).sqrt() * 1e3,
            delta_r_y_sigma_um: var(-1.0).sqrt() * 1e3,
            delta_r_max_um: (a0 + amp) * 1e3,
            delta_r_min_um: (a0 - amp) * 1e3,
            // a0 (s²/n) and the amplitude (≈ 2s²/n) together.
            delta_r_max_sigma_um: (3.0 * s2 / n).sqrt() * 1e3,
            delta_r_max_at_deg: 0.5 * b2.atan2(a2).to_degrees(),
        }
    }
}

/// ΔR per acceleration over a position's scans, a line through the origin weighted by each
/// scan's σ, µm per m/s², and its σ (widened by the scatter about the line when that is larger
/// than the σ say: √(χ²/(k − 1)) ≥ 1).
pub(super) fn through_origin(scans: &[Scan], pick: fn(&Scan) -> (f64, f64)) -> (f64, f64) {
    let (mut sxy, mut sxx) = (0.0, 0.0);
    for s in scans {
        let (y, sig) = pick(s);
        let a = s.accel_mm_s2 * 1e-3;
        let w = 1.0 / (sig * sig).max(1e-12);
        sxy += w * a * y;
        sxx += w * a * a;
    }
    if sxx <= 0.0 {
        return (0.0, 0.0);
    }
    let slope = sxy / sxx;
    let chi2: f64 = scans
        .iter()
        .map(|s| {
            let (y, sig) = pick(s);
            (y - slope * s.accel_mm_s2 * 1e-3).powi(2) / (sig * sig).max(1e-12)
        })
        .sum();
    let birge = if scans.len() > 1 {
        (chi2 / (scans.len() - 1) as f64).max(1.0)
    } else {
        1.0
    };
    (slope, (birge / sxx).sqrt())
}
