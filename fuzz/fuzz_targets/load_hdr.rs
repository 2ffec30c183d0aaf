#![no_main]
//! `cargo +nightly fuzz run load_hdr`: see `depthgraph::fuzzing::load_hdr`.
libfuzzer_sys::fuzz_target!(|data: &[u8]| depthgraph::fuzzing::load_hdr(data));
