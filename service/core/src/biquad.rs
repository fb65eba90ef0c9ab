//! Second-order IIR sections (biquads) for the judgement stage.
//!
//! Equation: y[k] = b0 x[k] + b1 x[k−1] + b2 x[k−2] − a1 y[k−1] − a2 y[k−2] (direct form II
//! transposed). Source idea: the `biquad` crate's split of validated coefficients from filter
//! state, and the bilinear-transform Butterworth design of the Audio-EQ cookbook.
//!
//! A section's state is set to zero once it has decayed below [`crate::flush::BELOW`] (see
//! [`crate::flush`]).

/// The state `(s1, s2)`, or zero when both have decayed ([`crate::flush`]; written so that it
/// compiles to compares and masks, side by side on the channels).
#[inline(always)]
fn flushed(s1: f64, s2: f64) -> (f64, f64) {
    if crate::flush::negligible(&[s1, s2]) {
        (0.0, 0.0)
    } else {
        (s1, s2)
    }
}

/// Validated coefficients of one section (a0 normalised to 1).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Coefficients {
    b0: f64,
    b1: f64,
    b2: f64,
    a1: f64,
    a2: f64,
}

/// State of one section.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct State {
    s1: f64,
    s2: f64,
}

/// States of one section on `C` independent channels, each value in its own array (so the
/// channels run side by side, in SIMD lanes where the machine has them).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Channels<const C: usize> {
    s1: [f64; C],
    s2: [f64; C],
}

impl<const C: usize> Channels<C> {
    /// Every state value of every channel (for the judgement's tests).
    #[cfg(test)]
    pub(crate) fn states(&self) -> impl Iterator<Item = f64> + '_ {
        self.s1.iter().chain(&self.s2).copied()
    }
}

impl Coefficients {
    /// A low-pass section with cutoff `fc` and quality `q` at sampling rate `fs`.
    /// `None` unless 0 < fc < fs/2 and q > 0.
    pub fn lowpass(fs: f64, fc: f64, q: f64) -> Option<Coefficients> {
        if !(fs.is_finite()
            && fc.is_finite()
            && q.is_finite()
            && fc > 0.0
            && fc < fs / 2.0
            && q > 0.0)
        {
            return None;
        }
        let w0 = 2.0 * std::f64::consts::PI * fc / fs;
        let (sin, cos) = w0.sin_cos();
        let alpha = sin / (2.0 * q);
        let a0 = 1.0 + alpha;
        Some(Coefficients {
            b0: (1.0 - cos) / 2.0 / a0,
            b1: (1.0 - cos) / a0,
            b2: (1.0 - cos) / 2.0 / a0,
            a1: -2.0 * cos / a0,
            a2: (1.0 - alpha) / a0,
        })
    }

    /// Butterworth low-pass of even `order` (2, 4, 6, 8) as cascaded sections.
    pub fn butterworth(fs: f64, fc: f64, order: usize) -> Option<Vec<Coefficients>> {
        if order == 0 || order % 2 != 0 || order > 8 {
            return None;
        }
        (0..order / 2)
            .map(|k| {
                let theta = std::f64::consts::PI * (2 * k + 1) as f64 / (2 * order) as f64;
                Coefficients::lowpass(fs, fc, 1.0 / (2.0 * theta.sin()))
            })
            .collect()
    }

    /// The state at rest with constant input `x` (unit DC gain: output `x`).
    pub fn steady(&self, x: f64) -> State {
        // DF2T at rest: y = x; s2 = b2 x − a2 y; s1 = b1 x − a1 y + s2.
        let s2 = self.b2 * x - self.a2 * x;
        State {
            s1: self.b1 * x - self.a1 * x + s2,
            s2,
        }
    }

    /// Filters one sample.
    #[inline]
    pub fn run(&self, st: &mut State, x: f64) -> f64 {
        let y = self.b0 * x + st.s1;
        (st.s1, st.s2) = flushed(self.b1 * x - self.a1 * y + st.s2, self.b2 * x - self.a2 * y);
        y
    }

    /// [`Self::steady`] of each channel.
    pub fn steady_each<const C: usize>(&self, x: [f64; C]) -> Channels<C> {
        let s = x.map(|x| self.steady(x));
        Channels {
            s1: s.map(|s| s.s1),
            s2: s.map(|s| s.s2),
        }
    }

    /// [`Self::run`] on each channel: `x` in, the filtered values out.
    #[inline]
    pub fn run_each<const C: usize>(&self, st: &mut Channels<C>, x: &mut [f64; C]) {
        for ((x, s1), s2) in x.iter_mut().zip(&mut st.s1).zip(&mut st.s2) {
            let y = self.b0 * *x + *s1;
            (*s1, *s2) = flushed(self.b1 * *x - self.a1 * y + *s2, self.b2 * *x - self.a2 * y);
            *x = y;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn butterworth_has_unit_dc_gain_and_attenuates() {
        let c = Coefficients::butterworth(1000.0, 40.0, 4).unwrap();
        let mut st: Vec<State> = c.iter().map(|c| c.steady(0.0)).collect();
        let run = |st: &mut Vec<State>, x: f64| {
            c.iter().zip(st.iter_mut()).fold(x, |v, (c, s)| c.run(s, v))
        };
        let mut y = 0.0;
        for _ in 0..2000 {
            y = run(&mut st, 1.0);
        }
        assert!((y - 1.0).abs() < 1e-9);
        // 200 Hz sine: 4th-order Butterworth at 40 Hz attenuates by (40/200)^4 ≈ 1.6e-3 (bilinear: less).
        let mut peak: f64 = 0.0;
        for k in 0..4000 {
            let v = run(
                &mut st,
                1.0 + (2.0 * std::f64::consts::PI * 200.0 * k as f64 / 1000.0).sin(),
            );
            if k > 2000 {
                peak = peak.max((v - 1.0).abs());
            }
        }
        assert!(peak < 3e-3, "{peak}");
        assert!(Coefficients::butterworth(1000.0, 600.0, 4).is_none());
        assert!(Coefficients::butterworth(1000.0, 40.0, 3).is_none());
        // Steady state starts without transient.
        let s = c[0].steady(5.0);
        let mut s2 = s;
        assert!((c[0].run(&mut s2, 5.0) - 5.0).abs() < 1e-12);
    }

    /// After an impulse the input stays zero: the states decay to exactly zero without ever
    /// being subnormal (unflushed, they reach the subnormals after about 7 400 samples and
    /// rounding holds some there).
    #[test]
    fn a_decaying_section_never_holds_a_subnormal_state() {
        let c = Coefficients::butterworth(1000.0, 40.0, 4).unwrap();
        let mut one: Vec<State> = c.iter().map(|c| c.steady(0.0)).collect();
        let mut each: Vec<Channels<2>> = c.iter().map(|c| c.steady_each([0.0; 2])).collect();
        let mut smallest = f64::INFINITY;
        for k in 0..20_000 {
            let x = if k == 0 { 1.0 } else { 0.0 };
            let mut v = x;
            for (c, s) in c.iter().zip(one.iter_mut()) {
                v = c.run(s, v);
            }
            let mut v2 = [x, -x];
            for (c, s) in c.iter().zip(each.iter_mut()) {
                c.run_each(s, &mut v2);
            }
            assert_eq!(v2, [v, -v], "the channels run as single sections do");
            let states = one
                .iter()
                .flat_map(|s| [s.s1, s.s2])
                .chain(each.iter().flat_map(|s| s.s1.into_iter().chain(s.s2)));
            for st in states {
                assert!(!st.is_subnormal(), "a subnormal state {st:e} at sample {k}");
                if st != 0.0 {
                    smallest = smallest.min(st.abs());
                }
            }
        }
        assert!(smallest < 1e-240, "the states decayed to {smallest:e} only");
        assert!(one.iter().all(|s| s.s1 == 0.0 && s.s2 == 0.0), "{one:?}");
        assert!(each.iter().all(|s| s.s1 == [0.0; 2] && s.s2 == [0.0; 2]));
    }
}
