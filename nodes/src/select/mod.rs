//! Copy and paste (3d-editing §III.C-D): color+depth edges, the
//! edge-snapping lasso, feathering, placement, and the depth-tested
//! composite.
pub mod composite;
pub mod edges;
pub mod feather;
pub mod lasso;
pub mod paste;

use depthgraph_graph::registry::{Registry, RegistryError};

/// Registers the node kinds of this family.
pub fn register(reg: &mut Registry) -> Result<(), RegistryError> {
    edges::register(reg)?;
    lasso::register(reg)?;
    paste::register(reg)?;
    feather::register(reg)?;
    composite::register(reg)?;
    Ok(())
}
