#![no_main]
//! `cargo +nightly fuzz run ron_document`: see `depthgraph::fuzzing::ron_document`.
libfuzzer_sys::fuzz_target!(|data: &[u8]| depthgraph::fuzzing::ron_document(data));
