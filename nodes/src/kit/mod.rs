//! Helpers every family shares, one copy each: the sRGB transfer and
//! luminance, one random number generator, the depth colormap, and the
//! shape checks of inputs.
