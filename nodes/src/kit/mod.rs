//! Helpers every family shares, one copy each: the sRGB transfer and
//! luminance ([`color`]), one random number generator ([`rng`]), the depth
//! colormap ([`colormap`]), and the shape checks of inputs ([`checks`]).
//! Nothing here is a node; everything is a plain function.

pub mod checks;
pub mod color;
pub mod colormap;
pub mod rng;
