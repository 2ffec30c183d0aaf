//! What the parity tests share: the device (a missing adapter fails the
//! test, it never skips it), and running one node kind on both backends.

#![allow(dead_code)]

use std::sync::{Arc, OnceLock};

use depthgraph_gpu::{AdapterRequest, GpuContext};
use depthgraph_graph::node::CancelToken;
use depthgraph_graph::prelude::*;

/// The device every test of this binary shares (opening one per test would
/// make lavapipe spend most of the run compiling the same pipelines).
pub fn gpu() -> Arc<GpuContext> {
    static CTX: OnceLock<Arc<GpuContext>> = OnceLock::new();
    CTX.get_or_init(|| {
        GpuContext::new(&AdapterRequest::default()).unwrap_or_else(|e| {
            panic!(
                "the GPU parity tests need a wgpu adapter and found none: {e}. \
                 On Debian: apt install mesa-vulkan-drivers (lavapipe)"
            )
        })
    })
    .clone()
}

/// The CPU-only registry and one with the device kinds preferred.
pub fn registries() -> (Registry, Registry) {
    let cpu = depthgraph_nodes::registry().unwrap();
    let mut dev = depthgraph_nodes::registry().unwrap();
    depthgraph_gpu::install(&mut dev, &gpu()).unwrap();
    (cpu, dev)
}

/// Evaluates `kind` with `inputs` and `params` on `reg`'s preferred backend.
pub fn eval_on(
    reg: &Registry,
    kind: &str,
    inputs: &Inputs,
    params: &ParamMap,
) -> Result<Outputs, NodeError> {
    let node = reg.get(kind).unwrap();
    let cancel = CancelToken::new();
    let dir = std::env::temp_dir();
    let ctx = EvalCtx {
        node: kind,
        cancel: &cancel,
        progress: None,
        out_dir: &dir,
        input_files: &[],
        derivations: None,
        max_pixels: depthgraph_graph::node::DEFAULT_MAX_PIXELS,
    };
    node.eval(&ctx, inputs, params)
}

/// `kind` on the CPU and on the device.
pub fn both(kind: &str, inputs: &Inputs, params: &ParamMap) -> (Outputs, Outputs) {
    let (cpu, dev) = registries();
    assert_eq!(
        dev.get(kind).unwrap().backend(),
        "wgpu",
        "{kind} has no device backend"
    );
    let a = eval_on(&cpu, kind, inputs, params).unwrap();
    let b = eval_on(&dev, kind, inputs, params).unwrap();
    // the device produced it (not a fall-back to the CPU)
    assert_eq!(
        b.origin.as_ref().map(|o| o.backend.as_str()),
        Some("wgpu"),
        "{kind}"
    );
    (a, b)
}

pub fn depth_of(o: &Outputs, port: &str) -> Arc<DepthMap> {
    match o.values.get(port) {
        Some(Value::Depth(d)) => d.clone(),
        other => panic!("{port}: {other:?}"),
    }
}

pub fn color_of(o: &Outputs, port: &str) -> Arc<ColorImage> {
    match o.values.get(port) {
        Some(Value::Color(c)) => c.clone(),
        other => panic!(
            "{port}: not a color image ({:?})",
            other.map(|v| v.value_type())
        ),
    }
}
