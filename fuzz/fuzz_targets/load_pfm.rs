#![no_main]
//! `cargo +nightly fuzz run load_pfm`: see `depthgraph::fuzzing::load_pfm`.
libfuzzer_sys::fuzz_target!(|data: &[u8]| depthgraph::fuzzing::load_pfm(data));
