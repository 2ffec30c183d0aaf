#![no_main]
//! `cargo +nightly fuzz run load_nyu_raw`: see `depthgraph::fuzzing::load_nyu_raw`.
libfuzzer_sys::fuzz_target!(|data: &[u8]| depthgraph::fuzzing::load_nyu_raw(data));
