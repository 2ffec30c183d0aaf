//! Lighting estimated from the photo itself, for relighting without a
//! captured environment map: spherical harmonics ([`sh`]), regions of
//! constant albedo ([`regions`]), the fit ([`estimate`]) and the
//! `EstimateLighting` node ([`node`]).
pub mod estimate;
pub mod node;
pub mod regions;
pub mod sh;
