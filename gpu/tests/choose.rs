//! `auto` takes a hardware adapter and leaves a software one (lavapipe,
//! llvmpipe: kernels emulated on the CPU, slower than the CPU nodes) for
//! the CPU, saying why; `gpu` takes either.

use depthgraph_gpu::{AdapterRequest, BackendRequest, GpuContext, choose};

#[test]
fn auto_leaves_a_software_adapter_to_the_cpu_and_gpu_takes_it() {
    let ctx = GpuContext::new(&AdapterRequest::default()).unwrap_or_else(|e| {
        panic!(
            "this test needs a wgpu adapter and found none: {e} (apt install mesa-vulkan-drivers)"
        )
    });
    let software = ctx.adapter().is_software();
    drop(ctx);
    let mut reg = depthgraph_nodes::registry().unwrap();
    let auto = choose(BackendRequest::Auto, &mut reg).unwrap();
    if software {
        assert_eq!(auto.used, "cpu", "{}", auto.reason);
        assert!(auto.reason.contains("software"), "{}", auto.reason);
        assert_eq!(reg.get("Refocus").map(|n| n.backend()), Some("cpu"));
    } else {
        assert_eq!(auto.used, "wgpu", "{}", auto.reason);
    }
    let mut reg = depthgraph_nodes::registry().unwrap();
    let gpu = choose(BackendRequest::Gpu, &mut reg).unwrap();
    assert_eq!(gpu.used, "wgpu", "{}", gpu.reason);
    assert_eq!(reg.get("Refocus").map(|n| n.backend()), Some("wgpu"));
}
