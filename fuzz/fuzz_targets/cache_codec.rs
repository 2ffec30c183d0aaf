#![no_main]
//! `cargo +nightly fuzz run cache_codec`: see `depthgraph::fuzzing::cache_codec`.
libfuzzer_sys::fuzz_target!(|data: &[u8]| depthgraph::fuzzing::cache_codec(data));
