#![no_main]
//! `cargo +nightly fuzz run set_override`: see `depthgraph::fuzzing::set_override`.
libfuzzer_sys::fuzz_target!(|data: &[u8]| depthgraph::fuzzing::set_override(data));
