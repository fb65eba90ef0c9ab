//! Sine and cosine for the custom effects' expressions, without a call into the C library.
//!
//! Equation: x = n·π/2 + y with n = round(x·2/π) and y (in [−π/4, π/4]) carried as a sum of
//! two doubles y₀ + y₁; then sin x and cos x are ±sin y or ±cos y by n mod 4, and those two are
//! the minimax polynomials of fdlibm's kernels `__kernel_sin` and `__kernel_cos` (errors below
//! one unit in the last place). The reduction is the Cody–Waite one with π/2 split into three
//! parts of 33 bits and their tails, as in fdlibm's `__ieee754_rem_pio2` for medium arguments
//! (|x| < 2²⁰·π/2, about 1.6·10⁶): a second and a third step run only when the first loses
//! too many bits to cancellation, near a multiple of π/2.
//!
//! Larger arguments (and non-finite ones) go to the standard library, which reduces them
//! with the full bits of 2/π. Sine and cosine of one argument come from one reduction, and
//! `sin(x)` is bit for bit `sin_cos(x).0` (likewise the cosine), so a program that shares one
//! reduction between them gives the same values as one that does not.
//!
//! Source: Sun Microsystems' fdlibm (`k_sin.c`, `k_cos.c`, `e_rem_pio2.c`; "Permission to
//! use, copy, modify, and distribute this software is freely granted, provided that this
//! notice is preserved"), in the form musl's `__rem_pio2`, `__sin` and `__cos` give it.
//! Why: the custom effects evaluate a sine and a cosine for every point; the C library's
//! call, with its own tests of the argument, was 3–4 % of `bench core`'s profile (about
//! 8 ns of a custom effect's cost per point; here it is inlined code).

/// Largest |x| reduced here; beyond it the standard library reduces (2²⁰·π/2).
const MEDIUM: f64 = (1u64 << 20) as f64 * std::f64::consts::FRAC_PI_2;

const TO_INT: f64 = 1.5 / f64::EPSILON;
// The constants below are fdlibm's, given (as there) by their bits.
const INV_PIO2: f64 = std::f64::consts::FRAC_2_PI;
/// π/2's first 33 bits, and the rest of π/2 beyond them.
const PIO2_1: f64 = f64::from_bits(0x3ff9_21fb_5440_0000);
const PIO2_1T: f64 = f64::from_bits(0x3dd0_b461_1a62_6331);
/// The next 33 bits, and the rest beyond them.
const PIO2_2: f64 = f64::from_bits(0x3dd0_b461_1a60_0000);
const PIO2_2T: f64 = f64::from_bits(0x3ba3_198a_2e03_7073);
/// The next 33 bits, and the rest.
const PIO2_3: f64 = f64::from_bits(0x3ba3_198a_2e00_0000);
const PIO2_3T: f64 = f64::from_bits(0x397b_839a_2520_49c1);
const PIO4: f64 = std::f64::consts::FRAC_PI_4;

/// The polynomial of sin on [−π/4, π/4] (`__kernel_sin`).
const S1: f64 = f64::from_bits(0xbfc5_5555_5555_5549);
const S2: f64 = f64::from_bits(0x3f81_1111_1110_f8a6);
const S3: f64 = f64::from_bits(0xbf2a_01a0_19c1_61d5);
const S4: f64 = f64::from_bits(0x3ec7_1de3_57b1_fe7d);
const S5: f64 = f64::from_bits(0xbe5a_e5e6_8a2b_9ceb);
const S6: f64 = f64::from_bits(0x3de5_d93a_5acf_d57c);

/// The polynomial of cos on [−π/4, π/4] (`__kernel_cos`).
const C1: f64 = f64::from_bits(0x3fa5_5555_5555_554c);
const C2: f64 = f64::from_bits(0xbf56_c16c_16c1_5177);
const C3: f64 = f64::from_bits(0x3efa_01a0_19cb_1590);
const C4: f64 = f64::from_bits(0xbe92_7e4f_809c_52ad);
const C5: f64 = f64::from_bits(0x3e21_ee9e_bdb4_b1c4);
const C6: f64 = f64::from_bits(0xbda8_fae9_be88_38d4);

/// sin(y₀ + y₁) for |y₀ + y₁| ≤ π/4 (y₁ the tail of y₀).
#[inline]
fn kernel_sin(x: f64, y: f64) -> f64 {
    let z = x * x;
    let w = z * z;
    let r = S2 + z * (S3 + z * S4) + z * w * (S5 + z * S6);
    let v = z * x;
    x - ((z * (0.5 * y - v * r) - y) - v * S1)
}

/// cos(y₀ + y₁) for |y₀ + y₁| ≤ π/4.
#[inline]
fn kernel_cos(x: f64, y: f64) -> f64 {
    let z = x * x;
    let w = z * z;
    let r = z * (C1 + z * (C2 + z * C3)) + w * w * (C4 + z * (C5 + z * C6));
    let hz = 0.5 * z;
    let w = 1.0 - hz;
    w + (((1.0 - w) - hz) + (z * r - x * y))
}

/// The biased exponent of `x`.
#[inline]
fn exponent(x: f64) -> i64 {
    ((x.to_bits() >> 52) & 0x7ff) as i64
}

/// x = n·π/2 + y₀ + y₁ for finite |x| < [`MEDIUM`]: (n mod 4, y₀, y₁).
#[inline]
fn reduce(x: f64) -> (u32, f64, f64) {
    let mut f = x * INV_PIO2 + TO_INT - TO_INT;
    let mut r = x - f * PIO2_1;
    let mut w = f * PIO2_1T;
    // Round-to-nearest never needs these; kept so that the result holds under any rounding.
    if r - w < -PIO4 {
        f -= 1.0;
        r = x - f * PIO2_1;
        w = f * PIO2_1T;
    } else if r - w > PIO4 {
        f += 1.0;
        r = x - f * PIO2_1;
        w = f * PIO2_1T;
    }
    let mut y0 = r - w;
    let ex = exponent(x);
    if ex - exponent(y0) > 16 {
        // Cancellation near a multiple of π/2: the next bits of π/2.
        let t = r;
        w = f * PIO2_2;
        r = t - w;
        w = f * PIO2_2T - ((t - r) - w);
        y0 = r - w;
        if ex - exponent(y0) > 49 {
            let t = r;
            w = f * PIO2_3;
            r = t - w;
            w = f * PIO2_3T - ((t - r) - w);
            y0 = r - w;
        }
    }
    let y1 = (r - y0) - w;
    // |f| < 2²⁰: exact as an integer; its two low bits are n mod 4 (two's complement).
    ((f as i64 & 3) as u32, y0, y1)
}

/// `reduce(x)` where it applies (|x| < [`MEDIUM`]); `None` beyond, and for NaN, where the
/// standard library answers.
#[inline]
fn reduced(x: f64) -> Option<(u32, f64, f64)> {
    (x.abs() < MEDIUM).then(|| reduce(x))
}

/// (sin x, cos x).
#[inline]
pub fn sin_cos(x: f64) -> (f64, f64) {
    let Some((n, y0, y1)) = reduced(x) else {
        return x.sin_cos();
    };
    let (s, c) = (kernel_sin(y0, y1), kernel_cos(y0, y1));
    match n {
        0 => (s, c),
        1 => (c, -s),
        2 => (-s, -c),
        _ => (-c, s),
    }
}

/// sin x (bit for bit `sin_cos(x).0`).
#[inline]
pub fn sin(x: f64) -> f64 {
    let Some((n, y0, y1)) = reduced(x) else {
        return x.sin();
    };
    match n {
        0 => kernel_sin(y0, y1),
        1 => kernel_cos(y0, y1),
        2 => -kernel_sin(y0, y1),
        _ => -kernel_cos(y0, y1),
    }
}

/// cos x (bit for bit `sin_cos(x).1`).
#[inline]
pub fn cos(x: f64) -> f64 {
    let Some((n, y0, y1)) = reduced(x) else {
        return x.cos();
    };
    match n {
        0 => kernel_cos(y0, y1),
        1 => -kernel_sin(y0, y1),
        2 => -kernel_cos(y0, y1),
        _ => kernel_sin(y0, y1),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Distance in units of the last place between two finite doubles of the same sign (or
    /// either zero): the count of doubles between them.
    fn ulps(a: f64, b: f64) -> u64 {
        if a == b {
            return 0;
        }
        let key = |x: f64| {
            let i = x.to_bits() as i64;
            if i < 0 {
                i64::MIN - i
            } else {
                i
            }
        };
        key(a).abs_diff(key(b))
    }

    /// A deterministic spread of arguments: every scale from 1e-9 to the medium limit, both
    /// signs, plus the neighbours of multiples of π/2 (where the reduction cancels).
    fn arguments() -> Vec<f64> {
        let mut xs = vec![0.0, -0.0, 1e-300, -1e-300, 1e-20, PIO4, -PIO4];
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        for _ in 0..200_000 {
            let u = (next() >> 11) as f64 / (1u64 << 53) as f64;
            let e = -9.0 + u * (MEDIUM.log10() + 9.0);
            let sign = if next() & 1 == 0 { 1.0 } else { -1.0 };
            xs.push(sign * 10f64.powf(e));
        }
        for k in 1..2000i64 {
            let m = (k * k * 7919) as f64 * std::f64::consts::FRAC_PI_2;
            if m < MEDIUM {
                let mut x = m;
                for _ in 0..3 {
                    xs.push(x);
                    xs.push(-x);
                    x = f64::from_bits(x.to_bits() + 1);
                }
            }
        }
        xs
    }

    #[test]
    fn within_one_ulp_of_the_standard_library() {
        // Both are within one unit of the true value: they differ by at most one unit (the
        // two roundings of a value close to halfway), and the test finds such ties.
        let mut worst = 0;
        for x in arguments() {
            let (s, c) = sin_cos(x);
            for (got, want) in [(s, x.sin()), (c, x.cos())] {
                let d = ulps(got, want);
                let tiny = want.abs() < 1e-250;
                assert!(
                    d <= 1 || tiny,
                    "x = {x:e}: {got:e} against {want:e} ({d} ulps)"
                );
                worst = worst.max(d);
            }
        }
        assert!(
            worst >= 1,
            "no difference at all: the test may not be comparing"
        );
    }

    #[test]
    fn sine_and_cosine_alone_are_the_bits_of_sin_cos() {
        for x in arguments() {
            let (s, c) = sin_cos(x);
            assert_eq!(sin(x).to_bits(), s.to_bits(), "sin({x:e})");
            assert_eq!(cos(x).to_bits(), c.to_bits(), "cos({x:e})");
        }
    }

    #[test]
    fn beyond_the_medium_range_and_non_finite_are_the_standard_librarys() {
        for x in [MEDIUM, -MEDIUM, 1e7, -3e15, 1e300, f64::MAX] {
            assert_eq!(sin_cos(x).0.to_bits(), x.sin().to_bits(), "{x:e}");
            assert_eq!(sin_cos(x).1.to_bits(), x.cos().to_bits(), "{x:e}");
        }
        for x in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
            let (s, c) = sin_cos(x);
            assert!(s.is_nan() && c.is_nan() && sin(x).is_nan() && cos(x).is_nan());
        }
        assert_eq!(sin(0.0).to_bits(), 0.0f64.to_bits());
        assert_eq!(sin(-0.0).to_bits(), (-0.0f64).to_bits());
        assert_eq!(cos(0.0), 1.0);
    }

    #[test]
    fn exact_at_the_quadrants_the_standard_library_is_exact_at() {
        use std::f64::consts::{FRAC_PI_2, PI};
        assert_eq!(sin(FRAC_PI_2), 1.0);
        assert_eq!(cos(PI), -1.0);
        assert_eq!(sin(-FRAC_PI_2), -1.0);
        assert_eq!(sin(3.0 * FRAC_PI_2), -1.0);
    }
}
