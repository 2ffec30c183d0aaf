//! Depth maps (3d-editing §III.A-B, realistic-depth-blur §3): unprojection
//! and reprojection, pull-push hole filling, joint bilateral smoothing,
//! NL-means pruning / denoising / upsampling / inpainting, and meshing.
pub mod bilateral;
pub mod mesh;
pub mod nlmeans;
pub mod pull_push;
pub mod unproject;

use depthgraph_graph::registry::{Registry, RegistryError};

/// Registers the node kinds of this family.
pub fn register(reg: &mut Registry) -> Result<(), RegistryError> {
    unproject::register(reg)?;
    bilateral::register(reg)?;
    mesh::register(reg)?;
    pull_push::register(reg)?;
    nlmeans::register(reg)?;
    Ok(())
}
