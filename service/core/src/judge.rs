//! The judgement stage: is the motion estimate still valid?
//!
//! Equation: a_meas = second difference of the scales (unequal spacing allowed),
//! δa = LP(A_est) − LP(a_meas) per axis with the same low-pass LP on both (so they are
//! compared at equal delay, A_est taken at the middle sample of the difference); an alarm is
//! raised when |δa| > threshold for `min_duration`, and cleared when |δa| < clear_fraction ×
//! threshold for `clear_duration` — one alarm per episode.
//!
//! Source idea: model-based fault detection — a residual between a model's prediction and a
//! measurement, low-passed to the band where the measurement is trustworthy, with hysteresis
//! against chattering.

use crate::biquad::{Channels, Coefficients};
use crate::sample::{Axis, Vec3};

/// A change of alarm state on one axis.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Transition {
    /// Axis.
    pub axis: Axis,
    /// Raised (true) or cleared.
    pub raised: bool,
    /// Filtered estimate, mm/s².
    pub estimated: f64,
    /// Filtered measurement, mm/s².
    pub measured: f64,
}

#[derive(Debug, Clone, Default)]
struct AxisState {
    raised: bool,
    above: u32,
    below: u32,
}

/// Judgement state of one machine.
#[derive(Debug, Clone)]
pub struct Judge {
    sections: Vec<Coefficients>,
    threshold: f64,
    clear_level: f64,
    raise_samples: u32,
    clear_samples: u32,
    /// Last three scale samples (t, s) and the estimated A at the last two.
    hist: [(i64, Vec3); 3],
    a_est: [Vec3; 3],
    n_hist: usize,
    /// The last spacing of the scale samples (ns) and 1/spacing in s⁻¹: a regular stream
    /// needs no division per sample (the reciprocal is the same bits either way).
    recip: (i64, f64),
    axes: [AxisState; 3],
    /// Filter states per section of the six channels: estimated x, y, z, measured x, y, z.
    /// The channels are independent, so each section runs on all six at once.
    states: Vec<Channels<6>>,
    primed: bool,
}

impl Judge {
    /// Bytes of heap this judge holds (its filter sections).
    pub fn heap_bytes(&self) -> usize {
        self.sections.capacity() * std::mem::size_of::<Coefficients>()
            + self.states.capacity() * std::mem::size_of::<Channels<6>>()
    }

    /// A judge with validated filter sections and limits.
    pub fn new(
        sections: Vec<Coefficients>,
        threshold: f64,
        clear_fraction: f64,
        raise_samples: u32,
        clear_samples: u32,
    ) -> Judge {
        Judge {
            sections,
            threshold,
            clear_level: threshold * clear_fraction,
            raise_samples,
            clear_samples,
            hist: [(0, Vec3::zeros()); 3],
            a_est: [Vec3::zeros(); 3],
            n_hist: 0,
            recip: (0, f64::INFINITY),
            axes: Default::default(),
            states: Vec::new(),
            primed: false,
        }
    }

    /// Changes the limits (new calibration) keeping the filter history when the filter is
    /// unchanged.
    pub fn reconfigure(
        &mut self,
        sections: Vec<Coefficients>,
        threshold: f64,
        clear_fraction: f64,
        raise: u32,
        clear: u32,
    ) {
        if sections != self.sections {
            self.sections = sections;
            self.restart();
        }
        self.threshold = threshold;
        self.clear_level = threshold * clear_fraction;
        self.raise_samples = raise;
        self.clear_samples = clear;
    }

    /// Forgets the sample history (after a gap); alarm states are kept until data clear them.
    pub fn restart(&mut self) {
        self.n_hist = 0;
        self.primed = false;
    }

    /// 1 / (`dt_ns` in s), remembered for the last spacing.
    #[inline]
    fn reciprocal(&mut self, dt_ns: i64) -> f64 {
        if dt_ns != self.recip.0 {
            self.recip = (dt_ns, 1.0 / (dt_ns as f64 * 1e-9));
        }
        self.recip.1
    }

    /// Whether any axis is raised.
    pub fn any_raised(&self) -> bool {
        self.axes.iter().any(|a| a.raised)
    }

    /// Feeds one scale sample and the estimated acceleration at the same time. `judge` is
    /// false while the estimate is known to be settling (no raising then).
    pub fn update(
        &mut self,
        t_ns: i64,
        scale: Vec3,
        a_est: Vec3,
        judge: bool,
        out: &mut impl FnMut(Transition),
    ) {
        // Shifted in registers and stored once (not read back from memory just written).
        let [(t0, s0), (t1, s1)] = [self.hist[1], self.hist[2]];
        let (t2, s2) = (t_ns, scale);
        self.hist = [(t0, s0), (t1, s1), (t2, s2)];
        let a_mid = self.a_est[2];
        self.a_est = [self.a_est[1], a_mid, a_est];
        self.n_hist = (self.n_hist + 1).min(3);
        if self.n_hist < 3 {
            return;
        }
        let (h1, h2) = ((t1 - t0) as f64 * 1e-9, (t2 - t1) as f64 * 1e-9);
        if h1 <= 0.0 || h2 <= 0.0 {
            self.restart();
            return;
        }
        // The divisions by the spacings as multiplications by their reciprocals (those of the
        // last spacing remembered: the same for a regular stream).
        let (r1, r2) = (self.reciprocal(t1 - t0), self.reciprocal(t2 - t1));
        // 2/(h1 + h2) is exactly 1/h when the spacings are equal.
        let k = if t1 - t0 == t2 - t1 {
            r2
        } else {
            2.0 / (h1 + h2)
        };
        let a_meas = ((s2 - s1) * r2 - (s1 - s0) * r1) * k;
        if !self.primed {
            // Both filters of an axis start at rest at the estimate.
            self.states.clear();
            self.states.extend(
                self.sections
                    .iter()
                    .map(|c| c.steady_each([0, 1, 2, 0, 1, 2].map(|i| a_mid[i]))),
            );
            self.primed = true;
        }
        let mut y = [a_mid.x, a_mid.y, a_mid.z, a_meas.x, a_meas.y, a_meas.z];
        for (c, st) in self.sections.iter().zip(self.states.iter_mut()) {
            c.run_each(st, &mut y);
        }
        let mut broken = false;
        for (i, st) in self.axes.iter_mut().enumerate() {
            let (e, m) = (y[i], y[i + 3]);
            let d = (e - m).abs();
            // A difference that is not a number (an overflow in the estimate or the filters)
            // means the estimate cannot be judged: it counts as exceeding, even while settling.
            let nan = !d.is_finite();
            broken |= nan;
            if !st.raised {
                st.above = if (judge && d > self.threshold) || nan {
                    st.above + 1
                } else {
                    0
                };
                if st.above >= self.raise_samples {
                    st.raised = true;
                    st.below = 0;
                    out(Transition {
                        axis: Axis::ALL[i],
                        raised: true,
                        estimated: e,
                        measured: m,
                    });
                }
            } else {
                st.below = if d < self.clear_level {
                    st.below + 1
                } else {
                    0
                };
                if st.below >= self.clear_samples {
                    st.raised = false;
                    st.above = 0;
                    out(Transition {
                        axis: Axis::ALL[i],
                        raised: false,
                        estimated: e,
                        measured: m,
                    });
                }
            }
        }
        if broken {
            // The filters hold a non-finite state: start them again from the next samples, so
            // the alarm can clear once the data are sane again.
            self.primed = false;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn step_disturbance_raises_once_and_clears_once() {
        let fs = 1000.0;
        let sections = Coefficients::butterworth(fs, 40.0, 4).unwrap();
        let mut j = Judge::new(sections, 100.0, 0.5, 4, 50);
        let mut events = vec![];
        // The machine moves at constant acceleration 200 mm/s² along x and the estimate
        // agrees; from sample 500 to 700 the real axis accelerates 600 mm/s² harder (a step
        // disturbance), then agrees again.
        let (mut x, mut v) = (0.0, 0.0);
        let dt = 1.0 / fs;
        for k in 0..2000 {
            let a_true = 200.0 + if (500..700).contains(&k) { 600.0 } else { 0.0 };
            v += a_true * dt;
            x += v * dt;
            j.update(
                (k as i64) * 1_000_000,
                Vec3::new(x, 0.0, 0.0),
                Vec3::new(200.0, 0.0, 0.0),
                true,
                &mut |t| events.push((k, t)),
            );
        }
        assert_eq!(events.len(), 2, "{events:?}");
        let (k_up, up) = events[0];
        let (k_down, down) = events[1];
        assert!(up.raised && up.axis == Axis::X && !down.raised);
        assert!((500..530).contains(&k_up), "raised at {k_up}");
        assert!((700..800).contains(&k_down), "cleared at {k_down}");
        assert!(up.measured - up.estimated > 100.0);
    }

    #[test]
    fn a_non_finite_estimate_raises_and_then_clears() {
        let sections = Coefficients::butterworth(1000.0, 40.0, 4).unwrap();
        let mut j = Judge::new(sections, 100.0, 0.5, 4, 50);
        let mut events = vec![];
        for k in 0..400i64 {
            let a = if (100..110).contains(&k) {
                f64::INFINITY
            } else {
                0.0
            };
            j.update(
                k * 1_000_000,
                Vec3::zeros(),
                Vec3::new(a, 0.0, 0.0),
                false,
                &mut |t| events.push((k, t.raised)),
            );
        }
        assert_eq!(events.len(), 2, "{events:?}");
        assert!(
            events[0].1 && (100..115).contains(&events[0].0),
            "{events:?}"
        );
        assert!(!events[1].1, "{events:?}");
    }

    /// An axis that moves, then stands still: its filters' states reach zero, never a
    /// subnormal number (an operation on one takes a microcode assist, about a hundred times
    /// a normal one's time).
    #[test]
    fn a_still_axis_leaves_no_subnormal_filter_state() {
        let sections = Coefficients::butterworth(1000.0, 40.0, 4).unwrap();
        let mut j = Judge::new(sections, 100.0, 0.5, 4, 50);
        let (mut x, mut v) = (0.0, 0.0);
        for k in 0..20_000i64 {
            // Accelerates for 0.2 s, then stops dead and stays.
            let a = if k < 200 { 500.0 } else { 0.0 };
            v = if k < 200 { v + a * 1e-3 } else { 0.0 };
            x += v * 1e-3;
            j.update(
                k * 1_000_000,
                Vec3::new(x, 0.0, 0.0),
                Vec3::new(a, 0.0, 0.0),
                true,
                &mut |_| (),
            );
            for st in &j.states {
                for s in st.states() {
                    assert!(!s.is_subnormal(), "a subnormal state {s:e} at sample {k}");
                }
            }
        }
        assert!(
            j.states.iter().all(|st| st.states().all(|s| s == 0.0)),
            "{:?}",
            j.states
        );
    }

    #[test]
    fn noise_alone_does_not_raise() {
        let sections = Coefficients::butterworth(1000.0, 40.0, 4).unwrap();
        let mut j = Judge::new(sections, 100.0, 0.5, 4, 50);
        let mut n = 0;
        // Deterministic pseudo-noise of 0.2 µm on a still axis (plus 0.1 µm quantisation).
        let mut s: u64 = 12345;
        for k in 0..20_000 {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let u = ((s >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 2.0 * 0.35e-3;
            let q = (u / 1e-4).round() * 1e-4;
            j.update(
                k * 1_000_000,
                Vec3::new(q, 0.0, 0.0),
                Vec3::zeros(),
                true,
                &mut |_| n += 1,
            );
        }
        assert_eq!(n, 0);
    }
}
