#![no_main]
// Thin wrapper: the body is `scancorr_fuzz::calibration` (fuzz/src/targets.rs), which the regression
// test tests/tests/fuzz_regressions.rs also runs on every file of fuzz/regressions/calibration/.
libfuzzer_sys::fuzz_target!(|data: &[u8]| scancorr_fuzz::calibration(data));
