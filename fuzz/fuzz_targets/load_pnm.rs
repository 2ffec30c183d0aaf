#![no_main]
//! `cargo +nightly fuzz run load_pnm`: see `depthgraph::fuzzing::load_pnm`.
libfuzzer_sys::fuzz_target!(|data: &[u8]| depthgraph::fuzzing::load_pnm(data));
