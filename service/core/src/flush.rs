//! Decayed filter states set to zero before they become subnormal.
//!
//! A recursive filter whose input stays at zero (the judgement's low-pass sections on an axis
//! that does not accelerate, the estimator's discretised model of an axis resting at 0 mm)
//! decays towards zero through the subnormal numbers, and rounding can hold it there for
//! good. On many processors every operation on a subnormal number takes a microcode assist,
//! about a hundred times the time of a normal one: the judgement's sections on the still
//! axis of `bench core`'s ring scan took more than half of its time.
//!
//! So a state whose values all lie below [`BELOW`] in magnitude is set to zero, all of them
//! at once: a value set to zero alone would take its term out of the recursion, and the
//! filter could ring on at the threshold instead of reaching zero. The values set to zero lie
//! hundreds of orders of magnitude below any position (mm) or acceleration (mm/s²) the core
//! handles; any other state is left exactly as it was.

/// Magnitude below which a decayed state is negligible. Far enough above the smallest normal
/// number (2.2e-308) that its products with coefficients down to 1e-50 stay normal.
pub const BELOW: f64 = 1e-250;

/// Whether every value of `v` lies below [`BELOW`] in magnitude (evaluated without a branch
/// per value).
#[inline(always)]
pub fn negligible(v: &[f64]) -> bool {
    v.iter().fold(true, |all, x| all & (x.abs() < BELOW))
}
