#![no_main]
//! `cargo +nightly fuzz run exposure_list`: see `depthgraph::fuzzing::exposure_list`.
libfuzzer_sys::fuzz_target!(|data: &[u8]| depthgraph::fuzzing::exposure_list(data));
