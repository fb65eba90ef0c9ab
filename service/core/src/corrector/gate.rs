//! The jump gate of the scale and probe streams: samples off the stream's track held until
//! the next ones decide, the spans whose points are flagged.

use super::*;

/// The jump gates' slots: scales, probe.
pub(super) const GATE_SCALE: usize = 0;
pub(super) const GATE_PROBE: usize = 1;

/// The head angles' reading noise the jump gate allows, degrees.
pub(super) const HEAD_NOISE_DEG: f64 = 0.01;

/// Most flagged spans a gate keeps; beyond, the newest two are merged.
pub(super) const MAX_FLAGGED_SPANS: usize = 64;

/// The jump gate of one stream, scales or probe (the module's "Jump gate").
#[derive(Debug, Clone, Default)]
pub(super) struct Gate {
    /// The last two samples taken (t_ns, values), the later second: scales x, y, z; probe
    /// u, v, w, A1, A2.
    pub(super) hist: [Option<(i64, [f64; 5])>; 2],
    /// The probe's tip at the last sample taken.
    pub(super) tip: u32,
    /// The time of the last sample taken (what the join may use up to).
    pub(super) taken_t: Option<i64>,
    /// Samples off the stream's track, held until the next ones decide.
    pub(super) held: Vec<Sample>,
    /// Spans (after, up to] of time whose points are flagged, in time order, disjoint.
    pub(super) flagged: VecDeque<(i64, i64)>,
}

/// What the jump gate compares of a scale or probe sample, and the probe's tip.
#[inline]
pub(super) fn gate_values(s: &Sample) -> ([f64; 5], u32) {
    match s {
        Sample::Scale(s) => ([s.pos.x, s.pos.y, s.pos.z, 0.0, 0.0], 0),
        Sample::Probe(p) => (
            [
                p.deflection.x,
                p.deflection.y,
                p.deflection.z,
                p.head_a1_deg,
                p.head_a2_deg,
            ],
            p.tip_id,
        ),
        _ => ([0.0; 5], 0),
    }
}

/// The turn between two head angles a and b, degrees in [0, 180]: (a − b) mod 360, or 360
/// less it when shorter.
///
/// Bit for bit `(a - b).rem_euclid(360.0)` before the `min`: for |a − b| < 360 the remainder
/// is exact (the difference itself) and the standard library adds 360 to a negative one, so
/// that case (a head that did not turn, or turned less than a turn: every sample of a scan)
/// is computed here without the call to `fmod` the remainder costs.
#[inline]
pub(super) fn head_turn(a: f64, b: f64) -> f64 {
    let d = a - b;
    let x = if d > -360.0 && d < 360.0 {
        if d < 0.0 {
            d + 360.0
        } else {
            d
        }
    } else {
        d.rem_euclid(360.0)
    };
    x.min(360.0 - x)
}

impl Gate {
    /// Whether a sample at `t` with values `v` is on the track of the samples taken.
    #[inline]
    pub(super) fn fits(
        &self,
        probe: bool,
        t: i64,
        v: &[f64; 5],
        tip: u32,
        l: &Limits,
        gap_ns: i64,
    ) -> bool {
        let Some((t1, s1)) = self.hist[1] else {
            return true;
        };
        let h = (t - t1) as f64 * 1e-9;
        let m2 = 2.0 * l.jump_noise_mm;
        let reach = l.max_speed_mm_s * h + m2;
        if probe {
            if tip != self.tip {
                return false;
            }
            // Distance from d to the segment [0, d₁].
            let (d, d1) = (Vec3::new(v[0], v[1], v[2]), Vec3::new(s1[0], s1[1], s1[2]));
            let n1 = d1.norm_squared();
            let back = if n1 > 0.0 {
                (d.dot(&d1) / n1).clamp(0.0, 1.0)
            } else {
                0.0
            };
            let turn = l.max_head_rate_deg_s * h + HEAD_NOISE_DEG;
            return (d - d1 * back).norm() <= reach
                && head_turn(v[3], s1[3]) <= turn
                && head_turn(v[4], s1[4]) <= turn;
        }
        let slope = match self.hist[0] {
            Some((t0, s0)) if t1 - t0 <= gap_ns => {
                let h0 = (t1 - t0) as f64 * 1e-9;
                let bound = 0.5 * l.max_accel_mm_s2 * h * (h + h0) + m2 * (1.0 + h / h0);
                Some((s0, h / h0, bound))
            }
            _ => None,
        };
        (0..3).all(|i| {
            let step = v[i] - s1[i];
            step.abs() <= reach
                && slope.is_none_or(|(s0, r, bound)| (step - (s1[i] - s0[i]) * r).abs() <= bound)
        })
    }

    /// Takes a sample into the track.
    #[inline]
    pub(super) fn record(&mut self, t: i64, v: [f64; 5], tip: u32) {
        self.hist = [self.hist[1], Some((t, v))];
        self.tip = tip;
        self.taken_t = Some(t);
    }

    /// Flags the points in (after, upto].
    pub(super) fn flag(&mut self, after: i64, upto: i64) {
        let full = self.flagged.len() >= MAX_FLAGGED_SPANS;
        match self.flagged.back_mut() {
            Some(b) if b.1 >= after || full => b.1 = b.1.max(upto),
            _ => self.flagged.push_back((after, upto)),
        }
    }

    /// Whether the point at `t` is flagged; forgets the spans before it (points come in time
    /// order).
    #[inline]
    pub(super) fn flags(&mut self, t: i64) -> bool {
        if self.flagged.is_empty() {
            return false;
        }
        while self.flagged.front().is_some_and(|f| f.1 < t) {
            self.flagged.pop_front();
        }
        self.flagged.front().is_some_and(|f| f.0 < t)
    }

    /// Forgets the track (a new time base).
    pub(super) fn reset(&mut self) {
        self.hist = [None, None];
        self.taken_t = None;
        self.held.clear();
        self.flagged.clear();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn head_turn_is_the_euclidean_remainder_bit_for_bit() {
        let reference = |a: f64, b: f64| {
            let x = (a - b).rem_euclid(360.0);
            x.min(360.0 - x)
        };
        let mut values = vec![0.0, -0.0, 360.0, -360.0, 359.999, -359.999, 180.0, -180.0];
        values.extend([
            1e-300,
            -1e-300,
            720.5,
            -720.5,
            1e9,
            -1e9,
            f64::NAN,
            f64::INFINITY,
        ]);
        let mut state = 0x2545_f491_4f6c_dd1du64;
        for _ in 0..2000 {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            let u = (state >> 11) as f64 / (1u64 << 53) as f64;
            values.push((u - 0.5) * 1500.0);
        }
        let mut compared = 0;
        for &a in &values {
            for &b in values.iter().step_by(7) {
                let (got, want) = (head_turn(a, b), reference(a, b));
                assert!(
                    got.to_bits() == want.to_bits() || (got.is_nan() && want.is_nan()),
                    "{a} - {b}: {got} against {want}"
                );
                compared += 1;
            }
        }
        assert!(compared > 500_000, "{compared}");
    }
}
