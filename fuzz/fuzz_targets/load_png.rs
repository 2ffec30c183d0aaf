#![no_main]
//! `cargo +nightly fuzz run load_png`: see `depthgraph::fuzzing::load_png`.
libfuzzer_sys::fuzz_target!(|data: &[u8]| depthgraph::fuzzing::load_png(data));
