//! # scancorr-core — the pure correction core
//!
//! Samples in, corrected points and alarms out. This crate is the one place the physics of
//! scanning-CMM correction lives; the live service (`scancorrd`), the offline bag corrector and
//! the model lab all call it, so they agree to the bit.
//!
//! It is synchronous and deterministic: no async runtime, no network, no files, no clocks.
//! The pipeline, in the order a sample travels through it:
//!
//! 1. [`corrector`] — the stream join: command, scale, probe and temperature samples aligned
//!    by `t_ns` with bounded buffering and per-stream watermarks, one output point per scale
//!    sample, every dropped sample counted by [`DropReason`].
//! 2. [`estimator`] — the motion estimator: E = G_N·C with G_N = G1·G2 ([`transfer`]),
//!    acceleration A = Ë of the estimate, rotation frequency f = |r × V|/(2π|r|²), r = E − c
//!    (the estimate's rate about the commanded centre).
//! 3. [`effects`] — one module per physical effect, each a correction vector that is linear in
//!    its parameters, exposing its regressors so the lab can fit it.
//! 4. [`synthesis`](corrector) — surface point = scales + Σ corrections + deflection + tip
//!    offset − tip radius·normal.
//! 5. [`judge`] — estimator validity: filtered estimated vs measured acceleration, alarms
//!    with hysteresis, action `flag` or `suspend`.
#![forbid(unsafe_code)]
#![warn(missing_docs)]

pub mod biquad;
pub mod calib;
pub mod calibrate;
pub mod checks;
pub mod corrector;
pub mod datasheet;
pub mod dim;
pub mod effects;
pub mod estimator;
pub mod expr;
pub mod flush;
pub mod judge;
pub mod lab;
pub mod sample;
pub mod shape;
pub mod stylus;
pub mod transfer;
pub mod trig;
pub mod units;
pub mod wire;

pub use calib::{CalibError, Calibration};
pub use corrector::{Corrector, DropReason, Output, Stats, MAX_KEPT_SENSORS};
pub use sample::{
    Alarm, AlarmAction, Axis, CommandSample, CorrectedPoint, PointContext, ProbeSample, Sample,
    ScaleSample, TemperatureSample, Vec3,
};
