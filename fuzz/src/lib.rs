//! Fuzz targets of scancorr (a cargo-fuzz project, its own workspace; see `scripts/fuzz.sh`
//! and `fuzz/README.md`).
//!
//! The target bodies live in `targets.rs`, shared with the regression test
//! `tests/tests/fuzz_regressions.rs`; `examples/seeds.rs` writes the seed corpora.
#![forbid(unsafe_code)]

mod targets;
pub use targets::*;
