//! Lighting estimated from the photo itself, for relighting without a
//! captured environment map: spherical harmonics ([`sh`]), regions of
//! constant albedo ([`regions`]), the light the photo's surfaces bounce
//! ([`bounce`]), the fit ([`estimate`]) and the
//! `EstimateLighting` node ([`node`]).
pub mod bounce;
pub mod estimate;
pub mod node;
pub mod regions;
pub mod sh;
