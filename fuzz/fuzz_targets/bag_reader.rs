#![no_main]
// Thin wrapper: the body is `scancorr_fuzz::bag_reader` (fuzz/src/targets.rs), which the regression
// test tests/tests/fuzz_regressions.rs also runs on every file of fuzz/regressions/bag_reader/.
libfuzzer_sys::fuzz_target!(|data: &[u8]| scancorr_fuzz::bag_reader(data));
