//! Helpers every family shares, one copy each: the sRGB transfer and
//! luminance ([`color`]), one random number generator ([`rng`]), the depth
//! colormap ([`colormap`]), the shape checks of inputs ([`checks`]), a
//! small dense solver ([`linalg`]), pixel neighbourhoods ([`grid`]) and a
//! vectorisable `exp` of non-positive exponents ([`fast_exp`]) and the
//! check of what vector instructions the CPU runs ([`cpu`]).
//! Nothing here is a node; everything is a plain function.

pub mod checks;
pub mod color;
pub mod colormap;
pub mod cpu;
pub mod fast_exp;
pub mod grid;
pub mod linalg;
pub mod rng;
