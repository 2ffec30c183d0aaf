#![no_main]
//! `cargo +nightly fuzz run load_exr`: see `depthgraph::fuzzing::load_exr`.
libfuzzer_sys::fuzz_target!(|data: &[u8]| depthgraph::fuzzing::load_exr(data));
