//! Simulation with exact ground truth: synthetic scenes and their renderer,
//! and sensors (Kinect, ToF, exposure brackets).
pub mod lighting_truth;
pub mod pathtrace;
pub mod relight_truth;
pub mod sensor;
pub mod synthetic;

use depthgraph_graph::registry::{Registry, RegistryError};

/// Registers the node kinds of this family.
pub fn register(reg: &mut Registry) -> Result<(), RegistryError> {
    synthetic::register(reg)?;
    sensor::register(reg)?;
    Ok(())
}
