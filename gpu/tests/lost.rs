//! A lost device (a driver reset, a hang, a removed GPU): the nodes run on
//! the CPU from then on, with the reason in the trace, and give the CPU's
//! result (wgpu panics on a wait on a lost device; the node failed, and
//! every later one with it). Its own test binary: it destroys its device.

mod common;

use std::sync::Arc;

use common::{depth_of, eval_on};
use depthgraph_gpu::{AdapterRequest, GpuContext};
use depthgraph_graph::prelude::*;
use depthgraph_nodes::depth::bilateral::BilateralParams;

#[test]
fn a_lost_device_sends_every_node_to_the_cpu() {
    let ctx = GpuContext::new(&AdapterRequest::default()).unwrap_or_else(|e| {
        panic!(
            "this test needs a wgpu adapter and found none: {e} (apt install mesa-vulkan-drivers)"
        )
    });
    let cpu = depthgraph_nodes::registry().unwrap();
    let mut dev = depthgraph_nodes::registry().unwrap();
    depthgraph_gpu::install(&mut dev, &ctx).unwrap();
    let (w, h) = (40, 24);
    let depth = DepthMap::from_fn(w, h, |x, y| 1.0 + 0.01 * ((x * 7 + y * 3) % 11) as f32);
    let color = ColorImage::from_fn(w, h, |x, _| [x as f32 / w as f32, 0.5, 0.2]);
    let mut inputs = Inputs::new();
    inputs.insert("depth", Value::Depth(Arc::new(depth)));
    inputs.insert("color", Value::Color(Arc::new(color)));
    let params = BilateralParams {
        radius: 3,
        ..Default::default()
    }
    .to_values();
    let want = eval_on(&cpu, "JointBilateral", &inputs, &params).unwrap();
    let before = eval_on(&dev, "JointBilateral", &inputs, &params).unwrap();
    assert_eq!(
        before.origin.as_ref().map(|o| o.backend.as_str()),
        Some("wgpu")
    );
    assert!(ctx.lost().is_none());

    ctx.device().destroy();
    for _ in 0..2 {
        let after = eval_on(&dev, "JointBilateral", &inputs, &params)
            .unwrap_or_else(|e| panic!("a node failed on a lost device: {e}"));
        let origin = after.origin.clone().expect("an origin");
        assert_eq!(origin.backend, "cpu");
        let note = origin.note.unwrap_or_default();
        assert!(note.contains("lost"), "{note}");
        assert_eq!(
            depth_of(&after, "depth").as_slice(),
            depth_of(&want, "depth").as_slice()
        );
    }
    assert!(ctx.lost().is_some());
}
