//! Every WGSL kernel compiles on the adapter (naga's validation and the
//! driver's), with its derived layout. A shader that fails shows here by
//! name, before any parity test runs into it.

mod common;

use depthgraph_gpu::shaders::ALL;

#[test]
fn every_kernel_compiles() {
    let ctx = common::gpu();
    let names: std::collections::BTreeSet<&str> = ALL.iter().map(|k| k.name).collect();
    assert_eq!(names.len(), ALL.len(), "kernel names are unique");
    // the explicit-layout kernels need their layout; the others derive one
    let mut failed = Vec::new();
    for k in ALL {
        if k.name.starts_with("refocus.wgsl") || k.name.starts_with("pull_push.wgsl") {
            continue; // compiled in their layouts by the parity tests
        }
        if let Err(e) = ctx.pipeline(k.name, &k.source(), k.entry) {
            failed.push(format!("{}: {e}", k.name));
        }
    }
    assert!(failed.is_empty(), "{}", failed.join("\n"));
    // a broken shader is reported as an error, not a panic
    let bad = ctx.pipeline("broken.wgsl::main", "fn main( {", "main");
    assert!(bad.is_err());
}
