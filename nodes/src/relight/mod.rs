//! Relighting by differential rendering with instant radiosity
//! (3d-editing §III.E): the environment map, VPL sampling, imperfect shadow
//! maps, the paired and scene-cached schemes, the ray-cast reference
//! with its BVH, and lighting estimated from the photo ([`lighting`]).
pub mod closure;
pub mod contact;
pub mod direct;
pub mod envmap;
pub mod fill;
pub mod ism;
pub mod lattice;
pub mod lighting;
pub mod node;
pub mod object_light;
pub mod object_mesh;
pub mod paired;
pub mod raycast;
pub mod reference;
pub mod scene_cached;
pub mod shading;
pub mod vpl;

use depthgraph_graph::registry::{Registry, RegistryError};

/// Registers the node kinds of this family.
pub fn register(reg: &mut Registry) -> Result<(), RegistryError> {
    envmap::register(reg)?;
    vpl::register(reg)?;
    node::register(reg)?;
    lighting::node::register(reg)?;
    reg.register_value("RelightScene", scene_cached::decode_scene);
    Ok(())
}
