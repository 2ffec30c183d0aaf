//! The camera after the shot (realistic-depth-blur paper): intrinsics and
//! their presets, the thin lens and its circle of confusion, refocusing with
//! any aperture shape, and HDR merging of exposure brackets.
pub mod frame_border;
pub mod hdr;
pub mod intrinsics;
pub mod lens;
mod lens_effects_tests;
pub mod occlusion;
pub mod refocus;
pub mod response;
pub mod view_filter;

use depthgraph_graph::registry::{Registry, RegistryError};

/// Registers the node kinds of this family.
pub fn register(reg: &mut Registry) -> Result<(), RegistryError> {
    intrinsics::register(reg)?;
    refocus::register(reg)?;
    hdr::register(reg)?;
    Ok(())
}
