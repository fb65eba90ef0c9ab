//! Nominal transfer-function models and their exact discretisation.
//!
//! Equation: G(s) = N(s)/D(s); the machine's nominal model per axis is G_N = G1(s)·G2(s)
//! (G1 the axis servo, G2 the probe), realised in controllable canonical form
//! ẋ = A x + B u, y = C x + D u and discretised at the sample period T for an input that is
//! linear between samples (first-order hold):
//! x[k+1] = Φ x[k] + Γ1 u[k] + Γ2 (u[k+1] − u[k]), with
//! exp([[A·T, B·T, 0], [0, 0, 1], [0, 0, 0]]) = [[Φ, Γ1, Γ2], [0, 1, 1], [0, 0, 1]].
//!
//! Source idea: a commanded scan path is piecewise smooth and densely sampled, so the
//! triangle-hold discretisation reproduces the continuous response at the sample instants
//! exactly for ramps (and to O(T²) for curves), unlike zero-order hold. Coefficients are
//! validated and kept apart from filter state (as in the `biquad` crate). A state that has
//! decayed below [`crate::flush::BELOW`] is set to zero ([`crate::flush`]).

use nalgebra::DMatrix;
use serde::{Deserialize, Serialize};

/// Highest model order the estimator supports (G1·G2 combined).
pub const MAX_ORDER: usize = 8;

/// A continuous-time transfer function of a calibration document.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum TransferFunction {
    /// G(s) = 1: the axis follows the command exactly.
    Unity,
    /// G(s) = 1/(τ s + 1): a servo with one dominant time constant.
    FirstOrder {
        /// Time constant τ, s; 10 µs … 10 s ([`crate::checks::TAU_S`]).
        tau_s: f64,
    },
    /// G(s) = ωn²/(s² + 2ζωn s + ωn²), ωn = 2π·natural_freq_hz.
    SecondOrder {
        /// Natural frequency, Hz; 0.01 … 10 000 Hz.
        natural_freq_hz: f64,
        /// Damping ratio ζ; 0.001 … 100.
        damping: f64,
    },
    /// G(s) = (num[0] sⁿ + … + num[n]) / (den[0] sᵐ + … + den[m]), highest power first;
    /// proper (n ≤ m) with unit static gain; every pole's magnitude within 10⁻³ … 10⁷ rad/s
    /// ([`POLE_RAD_S`]) and, when n = m, |num[0]/den[0]| ≤ 100.
    Rational {
        /// Numerator coefficients, highest power first.
        num: Vec<f64>,
        /// Denominator coefficients, highest power first.
        den: Vec<f64>,
    },
}

/// A polynomial ratio, highest power first, denominator monic after [`Rational::normalised`].
#[derive(Debug, Clone, PartialEq)]
pub struct Rational {
    /// Numerator, highest power first.
    pub num: Vec<f64>,
    /// Denominator, highest power first.
    pub den: Vec<f64>,
}

/// Why a transfer function was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TransferError {
    /// A coefficient is NaN or infinite, or a parameter is out of range.
    #[error("{0}")]
    Invalid(String),
}

impl TransferFunction {
    /// The numerator/denominator polynomials, after checking the parameters.
    pub fn rational(&self) -> Result<Rational, TransferError> {
        let bad = |m: &str| Err(TransferError::Invalid(m.to_string()));
        match self {
            TransferFunction::Unity => Ok(Rational {
                num: vec![1.0],
                den: vec![1.0],
            }),
            TransferFunction::FirstOrder { tau_s } => {
                let [lo, hi] = crate::checks::TAU_S;
                crate::checks::in_range("tau_s", *tau_s, lo, hi, "s")
                    .map_err(TransferError::Invalid)?;
                Ok(Rational {
                    num: vec![1.0],
                    den: vec![*tau_s, 1.0],
                })
            }
            TransferFunction::SecondOrder {
                natural_freq_hz,
                damping,
            } => {
                let [lo, hi] = NATURAL_FREQ_HZ;
                crate::checks::in_range("natural_freq_hz", *natural_freq_hz, lo, hi, "Hz")
                    .map_err(TransferError::Invalid)?;
                let [lo, hi] = DAMPING;
                crate::checks::in_range("damping", *damping, lo, hi, "")
                    .map_err(TransferError::Invalid)?;
                let wn = 2.0 * std::f64::consts::PI * natural_freq_hz;
                Ok(Rational {
                    num: vec![wn * wn],
                    den: vec![1.0, 2.0 * damping * wn, wn * wn],
                })
            }
            TransferFunction::Rational { num, den } => {
                if num.iter().chain(den.iter()).any(|c| !c.is_finite()) {
                    return bad("coefficients must be finite numbers");
                }
                let num = trim(num);
                let den = trim(den);
                if den.is_empty() {
                    return bad("den must have a non-zero coefficient");
                }
                if num.len() > den.len() {
                    return bad("the model must be proper (num degree ≤ den degree)");
                }
                let r = Rational { num, den };
                let dc_den = *r.den.last().unwrap();
                let dc_num = r.num.last().copied().unwrap_or(0.0);
                if dc_den == 0.0 || ((dc_num / dc_den) - 1.0).abs() > 1e-6 {
                    return bad("static gain num(0)/den(0) must be 1 (a position servo follows a constant command)");
                }
                if r.num.len() == r.den.len() {
                    let d = r.num[0] / r.den[0];
                    crate::checks::in_range(
                        "num[0]/den[0] (the gain at high frequency)",
                        d,
                        -MAX_FEEDTHROUGH,
                        MAX_FEEDTHROUGH,
                        "",
                    )
                    .map_err(TransferError::Invalid)?;
                }
                if r.den.len() - 1 <= MAX_ORDER {
                    let [lo, hi] = POLE_RAD_S;
                    for p in poles(&r.den) {
                        crate::checks::in_range("den: a pole's magnitude |p|", p, lo, hi, "rad/s")
                            .map_err(TransferError::Invalid)?;
                    }
                }
                Ok(r)
            }
        }
    }
}

/// Range of `second_order.natural_freq_hz`, Hz.
pub const NATURAL_FREQ_HZ: [f64; 2] = [0.01, 10_000.0];
/// Range of `second_order.damping`.
pub const DAMPING: [f64; 2] = [0.001, 100.0];
/// Range of the magnitude of each pole of a `rational` model, rad/s (time constants from
/// 0.1 µs to 1000 s: wider than `first_order`'s, for the poles a resonance spreads apart).
pub const POLE_RAD_S: [f64; 2] = [1e-3, 1e7];
/// Largest |num[0]/den[0]| of a `rational` model whose numerator has the denominator's
/// degree (its gain at high frequency).
pub const MAX_FEEDTHROUGH: f64 = 100.0;

/// The magnitudes of the roots of `den` (highest power first, leading coefficient non-zero):
/// the eigenvalues of its companion matrix.
fn poles(den: &[f64]) -> Vec<f64> {
    let n = den.len() - 1;
    if n == 0 {
        return vec![];
    }
    let mut c = DMatrix::<f64>::zeros(n, n);
    for i in 0..n - 1 {
        c[(i + 1, i)] = 1.0;
    }
    for i in 0..n {
        c[(0, i)] = -den[i + 1] / den[0];
    }
    c.complex_eigenvalues().iter().map(|z| z.norm()).collect()
}

fn trim(p: &[f64]) -> Vec<f64> {
    let first = p.iter().position(|c| *c != 0.0).unwrap_or(p.len());
    p[first..].to_vec()
}

impl Rational {
    /// Product of two transfer functions.
    pub fn mul(&self, o: &Rational) -> Rational {
        Rational {
            num: polymul(&self.num, &o.num),
            den: polymul(&self.den, &o.den),
        }
    }
    /// Order (denominator degree).
    pub fn order(&self) -> usize {
        self.den.len().saturating_sub(1)
    }
}

fn polymul(a: &[f64], b: &[f64]) -> Vec<f64> {
    if a.is_empty() || b.is_empty() {
        return vec![];
    }
    let mut r = vec![0.0; a.len() + b.len() - 1];
    for (i, x) in a.iter().enumerate() {
        for (j, y) in b.iter().enumerate() {
            r[i + j] += x * y;
        }
    }
    r
}

/// A discretised single-input single-output model: validated coefficients, no state.
///
/// The coefficients of order n are kept in one allocation of n² + 6n numbers (Φ row-major,
/// then Γ1, Γ2, C, C·A, C·A², x_ss), not in arrays sized for the largest order: a service
/// keeps three per probe type per machine.
#[derive(Debug, Clone, PartialEq)]
pub struct Discrete {
    /// State dimension n (0 for G = 1).
    pub n: usize,
    /// Φ, Γ1, Γ2, C, C·A, C·A², x_ss (see [`Discrete::phi`] and the others).
    coef: Box<[f64]>,
    /// Direct feedthrough D.
    pub d: f64,
    /// C·B (non-zero for relative degree 1).
    pub cb: f64,
    /// C·A·B.
    pub cab: f64,
    /// Samples for a disturbance of the state to decay to 1e-4.
    pub settle_samples: u64,
    /// Sample period, s.
    pub period_s: f64,
    /// 1 / period (the input's slope without a division per step).
    inv_period_s: f64,
    /// 1 / period² (its curvature).
    inv_period2: f64,
}

/// The coefficient vectors of a model of order `n`, in the order they are stored after Φ.
#[derive(Clone, Copy)]
enum Part {
    G1 = 0,
    G2,
    C,
    Ca,
    Ca2,
    Xss,
}

impl Discrete {
    /// Φ, row-major n×n.
    pub fn phi(&self) -> &[f64] {
        &self.coef[..self.n * self.n]
    }
    fn part(&self, p: Part) -> &[f64] {
        let at = self.n * self.n + p as usize * self.n;
        &self.coef[at..at + self.n]
    }
    fn part_mut(&mut self, p: Part) -> &mut [f64] {
        let at = self.n * self.n + p as usize * self.n;
        &mut self.coef[at..at + self.n]
    }
    /// Γ1.
    pub fn g1(&self) -> &[f64] {
        self.part(Part::G1)
    }
    /// Γ2.
    pub fn g2(&self) -> &[f64] {
        self.part(Part::G2)
    }
    /// Output row C.
    pub fn c(&self) -> &[f64] {
        self.part(Part::C)
    }
    /// C·A, for the first derivative of the output.
    pub fn ca(&self) -> &[f64] {
        self.part(Part::Ca)
    }
    /// C·A², for the second derivative.
    pub fn ca2(&self) -> &[f64] {
        self.part(Part::Ca2)
    }
    /// Steady state per unit constant input: x_ss = −A⁻¹B.
    pub fn xss(&self) -> &[f64] {
        self.part(Part::Xss)
    }
}

/// Running state of a [`Discrete`] model.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DiscreteState {
    /// Model state.
    pub x: [f64; MAX_ORDER],
    /// Last input.
    pub u: f64,
    /// Input before the last.
    pub u_prev: f64,
}

/// Output of one step: value and its first two time derivatives.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Derivs {
    /// y.
    pub y: f64,
    /// ẏ.
    pub dy: f64,
    /// ÿ.
    pub ddy: f64,
}

impl Discrete {
    /// Realises and discretises `g` at period `period_s`.
    pub fn new(g: &Rational, period_s: f64) -> Result<Discrete, TransferError> {
        if !(period_s.is_finite() && period_s > 0.0) {
            return Err(TransferError::Invalid("sample period must be > 0".into()));
        }
        let lead = g.den[0];
        let den: Vec<f64> = g.den.iter().map(|c| c / lead).collect();
        let n = den.len() - 1;
        if n > MAX_ORDER {
            return Err(TransferError::Invalid(format!(
                "combined model order {n} exceeds the supported {MAX_ORDER}"
            )));
        }
        let mut num = vec![0.0; n + 1 - g.num.len()];
        num.extend(g.num.iter().map(|c| c / lead));
        let b0 = num[0];
        let mut out = Discrete {
            n,
            coef: vec![0.0; n * n + 6 * n].into_boxed_slice(),
            d: b0,
            cb: 0.0,
            cab: 0.0,
            settle_samples: 0,
            period_s,
            inv_period_s: 1.0 / period_s,
            inv_period2: 1.0 / (period_s * period_s),
        };
        if n == 0 {
            return Ok(out);
        }
        // Controllable canonical form.
        let mut a = DMatrix::<f64>::zeros(n, n);
        for i in 0..n - 1 {
            a[(i, i + 1)] = 1.0;
        }
        for j in 0..n {
            a[(n - 1, j)] = -den[n - j];
        }
        let mut b = DMatrix::<f64>::zeros(n, 1);
        b[(n - 1, 0)] = 1.0;
        let mut c = DMatrix::<f64>::zeros(1, n);
        for j in 0..n {
            c[(0, j)] = num[n - j] - den[n - j] * b0;
        }
        // Augmented exponential for first-order hold.
        let mut m = DMatrix::<f64>::zeros(n + 2, n + 2);
        m.view_mut((0, 0), (n, n)).copy_from(&(&a * period_s));
        m.view_mut((0, n), (n, 1)).copy_from(&(&b * period_s));
        m[(n, n + 1)] = 1.0;
        let e = m.exp();
        let ca = &c * &a;
        let ca2 = &ca * &a;
        let xss = a
            .clone()
            .lu()
            .solve(&(-&b))
            .ok_or_else(|| TransferError::Invalid("the model has a pole at s = 0".into()))?;
        for i in 0..n {
            for j in 0..n {
                out.coef[i * n + j] = e[(i, j)];
            }
            out.part_mut(Part::G1)[i] = e[(i, n)];
            out.part_mut(Part::G2)[i] = e[(i, n + 1)];
            out.part_mut(Part::C)[i] = c[(0, i)];
            out.part_mut(Part::Ca)[i] = ca[(0, i)];
            out.part_mut(Part::Ca2)[i] = ca2[(0, i)];
            out.part_mut(Part::Xss)[i] = xss[(i, 0)];
        }
        out.cb = (&c * &b)[(0, 0)];
        out.cab = (&ca * &b)[(0, 0)];
        // Stability and settling from the discrete poles.
        let phi = e.view((0, 0), (n, n)).into_owned();
        let rho = phi
            .complex_eigenvalues()
            .iter()
            .map(|z| z.norm())
            .fold(0.0, f64::max);
        if !(rho < 1.0) {
            return Err(TransferError::Invalid(
                "the model is not stable (a pole in the right half-plane or on the axis)".into(),
            ));
        }
        let dc: f64 = (0..n).map(|i| out.c()[i] * out.xss()[i]).sum::<f64>() + out.d;
        if (dc - 1.0).abs() > 1e-6 {
            return Err(TransferError::Invalid(format!(
                "static gain is {dc}, expected 1"
            )));
        }
        out.settle_samples = ((1e-4f64).ln() / rho.max(1e-300).ln()).ceil().max(1.0) as u64;
        Ok(out)
    }

    /// State at rest under the constant input `u`.
    pub fn steady(&self, u: f64) -> DiscreteState {
        let mut x = [0.0; MAX_ORDER];
        for (xi, s) in x.iter_mut().zip(self.xss()) {
            *xi = s * u;
        }
        DiscreteState { x, u, u_prev: u }
    }

    /// Advances by one period to the input `u_next` and returns the output and its
    /// derivatives at the new instant.
    #[inline]
    pub fn step(&self, s: &mut DiscreteState, u_next: f64) -> Derivs {
        // One instance per order: with the order a constant the loops unroll and the bounds
        // checks vanish (the same operations in the same order as for any order).
        match self.n {
            0 => self.step_n::<0>(s, u_next),
            1 => self.step_n::<1>(s, u_next),
            2 => self.step_n::<2>(s, u_next),
            3 => self.step_n::<3>(s, u_next),
            4 => self.step_n::<4>(s, u_next),
            5 => self.step_n::<5>(s, u_next),
            6 => self.step_n::<6>(s, u_next),
            7 => self.step_n::<7>(s, u_next),
            _ => self.step_n::<MAX_ORDER>(s, u_next),
        }
    }

    /// [`Self::step`] of three models (the axes) at once, each on its own state and input:
    /// the same values as three calls. When the three have the same order (the usual case)
    /// the order is matched once and the three steps are one straight run of code.
    pub fn step3(
        models: &[Discrete; 3],
        states: &mut [DiscreteState; 3],
        u_next: [f64; 3],
    ) -> [Derivs; 3] {
        let n = models[0].n;
        if models[1].n != n || models[2].n != n {
            return [0, 1, 2].map(|i| models[i].step(&mut states[i], u_next[i]));
        }
        fn each<const N: usize>(
            m: &[Discrete; 3],
            s: &mut [DiscreteState; 3],
            u: [f64; 3],
        ) -> [Derivs; 3] {
            [0, 1, 2].map(|i| m[i].step_n::<N>(&mut s[i], u[i]))
        }
        match n {
            0 => each::<0>(models, states, u_next),
            1 => each::<1>(models, states, u_next),
            2 => each::<2>(models, states, u_next),
            3 => each::<3>(models, states, u_next),
            4 => each::<4>(models, states, u_next),
            _ => [0, 1, 2].map(|i| models[i].step(&mut states[i], u_next[i])),
        }
    }

    /// [`Self::step`] for a model of order `N` (= `self.n`).
    #[inline(always)]
    fn step_n<const N: usize>(&self, s: &mut DiscreteState, u_next: f64) -> Derivs {
        debug_assert_eq!(self.n, N);
        let du = u_next - s.u;
        // The parts cut at constant offsets from a slice of constant length (its one check in
        // `coef_n`): no check in the cuts, none in the loops.
        let coef = self.coef_n::<N>();
        let (phi, rest) = coef.split_at(N * N);
        let (g1, rest) = rest.split_at(N);
        let g2 = &rest[..N];
        // The new state computed whole from the old, then its N entries stored (the others
        // stay zero).
        let mut x = [0.0; N];
        for (i, xi) in x.iter_mut().enumerate() {
            let mut acc = g1[i] * s.u + g2[i] * du;
            for j in 0..N {
                acc += phi[i * N + j] * s.x[j];
            }
            *xi = acc;
        }
        if crate::flush::negligible(&x) {
            // Decayed to nothing (an axis resting at 0 mm): zero, never subnormal.
            x = [0.0; N];
        }
        s.x[..N].copy_from_slice(&x);
        let slope = du * self.inv_period_s;
        let curv = (u_next - 2.0 * s.u + s.u_prev) * self.inv_period2;
        s.u_prev = s.u;
        s.u = u_next;
        self.output_with::<N>(coef, s, slope, curv)
    }

    /// The coefficients of a model of order `N` (= `self.n`): Φ, Γ1, Γ2, C, C·A, C·A², x_ss.
    /// A slice whose length is a constant, checked here once: the parts cut from it below
    /// need no check of their own (a cut from `self.coef`, whose length is known only at run
    /// time, would be checked each time).
    #[inline(always)]
    fn coef_n<const N: usize>(&self) -> &[f64] {
        &self.coef[..N * N + 6 * N]
    }

    /// Output and derivatives of the current state for input slope and curvature.
    #[inline]
    pub fn output(&self, s: &DiscreteState, slope: f64, curv: f64) -> Derivs {
        match self.n {
            0 => self.output_n::<0>(s, slope, curv),
            1 => self.output_n::<1>(s, slope, curv),
            2 => self.output_n::<2>(s, slope, curv),
            3 => self.output_n::<3>(s, slope, curv),
            4 => self.output_n::<4>(s, slope, curv),
            5 => self.output_n::<5>(s, slope, curv),
            6 => self.output_n::<6>(s, slope, curv),
            7 => self.output_n::<7>(s, slope, curv),
            _ => self.output_n::<MAX_ORDER>(s, slope, curv),
        }
    }

    /// [`Self::output`] for a model of order `N` (= `self.n`).
    #[inline(always)]
    fn output_n<const N: usize>(&self, s: &DiscreteState, slope: f64, curv: f64) -> Derivs {
        self.output_with::<N>(self.coef_n::<N>(), s, slope, curv)
    }

    /// [`Self::output_n`] with the coefficients of [`Self::coef_n`].
    #[inline(always)]
    fn output_with<const N: usize>(
        &self,
        coef: &[f64],
        s: &DiscreteState,
        slope: f64,
        curv: f64,
    ) -> Derivs {
        let (mut y, mut dy, mut ddy) = (self.d * s.u, self.cb * s.u + self.d * slope, 0.0);
        ddy += self.cab * s.u + self.cb * slope + self.d * curv;
        let rest = &coef[N * N + 2 * N..];
        let (c, rest) = rest.split_at(N);
        let (ca, rest) = rest.split_at(N);
        let ca2 = &rest[..N];
        for i in 0..N {
            y += c[i] * s.x[i];
            dy += ca[i] * s.x[i];
            ddy += ca2[i] * s.x[i];
        }
        Derivs { y, dy, ddy }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lag(tau: f64) -> Rational {
        TransferFunction::FirstOrder { tau_s: tau }
            .rational()
            .unwrap()
    }

    fn first(tau: f64, t: f64) -> Discrete {
        Discrete::new(&lag(tau), t).unwrap()
    }

    /// Two first-order lags in series.
    fn second(a: f64, b: f64, t: f64) -> Discrete {
        Discrete::new(&lag(a).mul(&lag(b)), t).unwrap()
    }

    #[test]
    fn three_axes_at_once_are_three_steps_bit_for_bit() {
        let t = 0.001;
        let second = |a: f64, b: f64| second(a, b, t);
        // The same order on every axis (one match), and mixed orders (one call per axis).
        for models in [
            [
                second(0.012, 0.002),
                second(0.015, 0.002),
                second(0.010, 0.003),
            ],
            [first(0.012, t), second(0.015, 0.002), first(0.010, t)],
        ] {
            let mut together = [0, 1, 2].map(|i| models[i].steady(i as f64));
            let mut alone = together;
            for k in 0..200 {
                let u = [0, 1, 2].map(|i| ((k * (i + 3)) as f64 * 0.01).sin() * 10.0);
                let got = Discrete::step3(&models, &mut together, u);
                for i in 0..3 {
                    let want = models[i].step(&mut alone[i], u[i]);
                    for (g, w) in [
                        (got[i].y, want.y),
                        (got[i].dy, want.dy),
                        (got[i].ddy, want.ddy),
                    ] {
                        assert_eq!(g.to_bits(), w.to_bits(), "axis {i}, step {k}");
                    }
                }
            }
        }
    }

    /// An axis that moves and then rests at exactly zero: the model's state decays to zero
    /// and reaches it, never holding a subnormal number (an operation on one takes a
    /// microcode assist, about a hundred times a normal one's time).
    #[test]
    fn a_state_decaying_to_zero_is_never_subnormal() {
        let t = 0.001;
        let second = |a: f64, b: f64| second(a, b, t);
        let models = [second(0.012, 0.002), second(0.015, 0.002), first(0.010, t)];
        let mut states = [0, 1, 2].map(|i| models[i].steady(0.0));
        for k in 0..40_000 {
            let u = if (10..300).contains(&k) { 25.0 } else { 0.0 };
            Discrete::step3(&models, &mut states, [u; 3]);
            for (i, s) in states.iter().enumerate() {
                for x in &s.x[..models[i].n] {
                    assert!(
                        !x.is_subnormal(),
                        "axis {i}: a subnormal state {x:e} at {k}"
                    );
                }
            }
        }
        assert!(
            states.iter().all(|s| s.x.iter().all(|x| *x == 0.0)),
            "{states:?}"
        );
    }

    #[test]
    fn first_order_step_response_is_exact() {
        let (tau, t) = (0.012, 0.001);
        let d = first(tau, t);
        let mut s = d.steady(0.0);
        // A step applied at k = 0 and held: the first-order-hold model sees a ramp over the
        // first period, so compare from k = 1 with the response to that ramp-then-hold input:
        // y(t) = 1 − (τ/T)(1 − e^{−T/τ}) e^{−(t−T)/τ} for t ≥ T.
        let mut y = 0.0;
        for k in 1..=100 {
            y = d.step(&mut s, 1.0).y;
            let tk = k as f64 * t;
            let exact = 1.0 - (tau / t) * (1.0 - (-t / tau).exp()) * (-(tk - t) / tau).exp();
            assert!((y - exact).abs() < 1e-12, "k={k} y={y} exact={exact}");
        }
        assert!((y - 1.0).abs() < 1e-3);
    }

    #[test]
    fn first_order_ramp_response_lags_by_tau() {
        // u(t) = v t from rest: y(t) = v (t − τ + τ e^{−t/τ}) exactly at every sample.
        let (tau, t, v) = (0.01, 0.001, 50.0);
        let d = first(tau, t);
        let mut s = d.steady(0.0);
        for k in 1..=200 {
            let tk = k as f64 * t;
            let o = d.step(&mut s, v * tk);
            let exact = v * (tk - tau + tau * (-tk / tau).exp());
            assert!((o.y - exact).abs() < 1e-10, "k={k}: {} vs {exact}", o.y);
            let exact_dy = v * (1.0 - (-tk / tau).exp());
            assert!(
                (o.dy - exact_dy).abs() < 1e-9 * v.max(1.0),
                "k={k}: {} vs {exact_dy}",
                o.dy
            );
        }
        // After 20 τ the lag is v τ.
        let tk = 200.0 * t;
        let o = d.output(&s, v, 0.0);
        assert!((v * tk - o.y - v * tau).abs() < 1e-6);
    }

    #[test]
    fn second_order_derivatives_match_closed_form() {
        // Step response of an underdamped second-order system and its derivatives.
        let (fnat, zeta, t) = (25.0, 0.5, 0.0005);
        let g = TransferFunction::SecondOrder {
            natural_freq_hz: fnat,
            damping: zeta,
        };
        let d = Discrete::new(&g.rational().unwrap(), t).unwrap();
        let mut s = d.steady(0.0);
        // Use a ramp input (exact under first-order hold): u = t.
        let wn = 2.0 * std::f64::consts::PI * fnat;
        let wd = wn * (1.0 - zeta * zeta).sqrt();
        for k in 1..=400 {
            let tk = k as f64 * t;
            let o = d.step(&mut s, tk);
            // Ramp response: y = t − 2ζ/ωn + e^{−ζωn t}(2ζ/ωn cos ωd t + (2ζ²−1)/ωd sin ωd t)
            let e = (-zeta * wn * tk).exp();
            let y = tk - 2.0 * zeta / wn
                + e * (2.0 * zeta / wn * (wd * tk).cos()
                    + (2.0 * zeta * zeta - 1.0) / wd * (wd * tk).sin());
            // ÿ equals the impulse response h(t) = ωn²/ωd e^{−ζωn t} sin ωd t.
            let h = wn * wn / wd * e * (wd * tk).sin();
            assert!((o.y - y).abs() < 1e-10, "k={k}: {} vs {y}", o.y);
            assert!((o.ddy - h).abs() < 1e-7 * wn, "k={k}: {} vs {h}", o.ddy);
        }
    }

    #[test]
    fn product_and_validation() {
        let g1 = TransferFunction::FirstOrder { tau_s: 0.01 }
            .rational()
            .unwrap();
        let g2 = TransferFunction::FirstOrder { tau_s: 0.002 }
            .rational()
            .unwrap();
        let g = g1.mul(&g2);
        assert_eq!(g.order(), 2);
        let d = Discrete::new(&g, 0.001).unwrap();
        assert_eq!(d.n, 2);
        assert!(
            d.settle_samples > 50 && d.settle_samples < 200,
            "{}",
            d.settle_samples
        );
        for bad in [
            TransferFunction::FirstOrder { tau_s: -1.0 },
            TransferFunction::FirstOrder { tau_s: f64::NAN },
            TransferFunction::Rational {
                num: vec![2.0],
                den: vec![1.0, 1.0],
            },
            TransferFunction::Rational {
                num: vec![1.0, 0.0, 1.0],
                den: vec![1.0, 1.0],
            },
        ] {
            assert!(bad.rational().is_err(), "{bad:?}");
        }
        // Unstable: s² − s + 1 (static gain 1) is refused at discretisation.
        let unstable = TransferFunction::Rational {
            num: vec![1.0],
            den: vec![1.0, -1.0, 1.0],
        };
        assert!(Discrete::new(&unstable.rational().unwrap(), 0.001).is_err());
        let unity = Discrete::new(&TransferFunction::Unity.rational().unwrap(), 0.001).unwrap();
        let mut s = unity.steady(3.0);
        assert_eq!(unity.step(&mut s, 4.0).y, 4.0);
    }
}
