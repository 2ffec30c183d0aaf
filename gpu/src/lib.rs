//! # depthgraph-gpu
//!
//! The wgpu compute backend. Each device node is a second implementation
//! ("wgpu") of a CPU node kind with the **same schema**, so a result's cache
//! key does not depend on the backend that produced it; the discrete
//! decisions (sample counts, active regions, pass-throughs) are the CPU
//! code's own functions, so both backends decide alike.
//!
//! - [`context`]: instance, adapter, device, queue, pipeline cache, buffer
//!   pool, and the device copies of values that device nodes hand each other;
//! - [`session`]: one evaluation's uploads, kernels and downloads, counted;
//! - [`node`]: the [`Node`](depthgraph_graph::node::Node) adapter;
//! - [`backend`]: `--backend auto|cpu|gpu`;
//! - [`parity`]: the agreement checks the tests apply (also usable to
//!   compare two runs of a pipeline);
//! - [`shaders`]: the WGSL sources (`src/shaders/`), one file per kind;
//! - one module per device kind: [`pull_push`] (PullPush, DualPullPush),
//!   [`bilateral`] (JointBilateral), [`nlmeans`] (NLMeansDepth,
//!   NLMeansInpaint, NLMeansUpsample), [`edges`] (EdgeDetect), [`feather`] (Feather),
//!   [`composite`] (OcclusionComposite), [`refocus`] (Refocus), [`relight`]
//!   (Relight: the direct term of a scene-cached move).
//!
//! Numerics on the device are f32; each module states its bound against the
//! CPU's f64 sums and the tolerance its parity test checks.

#![warn(missing_docs)]

pub mod backend;
pub mod bilateral;
pub mod composite;
pub mod context;
pub mod edges;
pub mod feather;
pub mod nlmeans;
pub mod node;
pub mod parity;
pub mod pull_push;
pub mod refocus;
pub mod relight;
pub mod session;
pub mod shaders;

use std::sync::Arc;

use depthgraph_graph::registry::{Registry, RegistryError};

pub use backend::{BackendChoice, BackendRequest, choose};
pub use context::{AdapterRequest, AdapterSummary, GpuContext, GpuError};

/// The node kinds that have a device implementation.
pub const DEVICE_KINDS: &[&str] = &[
    "JointBilateral",
    "Refocus",
    "PullPush",
    "DualPullPush",
    "Feather",
    "EdgeDetect",
    "OcclusionComposite",
    "NLMeansInpaint",
    "NLMeansDepth",
    "NLMeansUpsample",
    "Relight",
];

/// Adds the device implementation of every kind in [`DEVICE_KINDS`] to
/// `reg` (whose CPU kinds must be registered) and prefers them.
pub fn install(reg: &mut Registry, ctx: &Arc<GpuContext>) -> Result<(), RegistryError> {
    node::register_device(reg, ctx, "JointBilateral", bilateral::eval)?;
    node::register_device(reg, ctx, "Refocus", refocus::eval)?;
    node::register_device(reg, ctx, "PullPush", pull_push::eval_plain)?;
    node::register_device(reg, ctx, "DualPullPush", pull_push::eval_dual)?;
    node::register_device(reg, ctx, "Feather", feather::eval)?;
    node::register_device(reg, ctx, "EdgeDetect", edges::eval)?;
    node::register_device(reg, ctx, "OcclusionComposite", composite::eval)?;
    node::register_device(reg, ctx, "NLMeansInpaint", nlmeans::eval_inpaint)?;
    node::register_device(reg, ctx, "NLMeansDepth", nlmeans::eval_depth)?;
    node::register_device(reg, ctx, "NLMeansUpsample", nlmeans::eval_upsample)?;
    node::register_device(reg, ctx, "Relight", relight::eval)?;
    reg.prefer_backends(&["wgpu", "cpu"]);
    Ok(())
}
