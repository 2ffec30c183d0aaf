//! Lighting estimated from the photo itself, for relighting without a
//! captured environment map: spherical harmonics ([`sh`]), regions of
//! constant albedo ([`regions`]), the light the photo's surfaces bounce
//! ([`bounce`]), the fit ([`estimate`]), its light's direction refined by
//! the cast shadows' edges ([`shadow_edges`]), how thick what the depth
//! shows is ([`thickness`]) and the
//! `EstimateLighting` node ([`node`]).
pub mod bounce;
pub mod estimate;
pub mod node;
pub mod regions;
pub mod sh;
pub mod shadow_edges;
pub mod thickness;
