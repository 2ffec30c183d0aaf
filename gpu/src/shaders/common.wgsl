// Helpers every depthgraph kernel shares (prepended to each shader).
//
// WGSL gives no guarantee for NaN and infinities in comparisons, so tests
// for them look at the bits.

// A depth sample is a measurement when it is finite and positive
// (DepthMap::is_valid on the CPU).
// By the bits: positive, non-zero (subnormals included, which a device may
// flush to zero in arithmetic) and finite.
fn is_valid_depth(z: f32) -> bool {
    let b = bitcast<u32>(z);
    return b != 0u && b < 0x7f800000u;
}

// True for NaN.
fn is_nan(v: f32) -> bool {
    let b = bitcast<u32>(v);
    return (b & 0x7f800000u) == 0x7f800000u && (b & 0x007fffffu) != 0u;
}

// True for NaN and both infinities.
fn is_non_finite(v: f32) -> bool {
    return (bitcast<u32>(v) & 0x7f800000u) == 0x7f800000u;
}

// Compensated (Kahan) summation: s.x is the sum, s.y the lost low part.
// Error bound: 2 eps |sum| + O(n eps^2) sum |terms|, independent of n to
// first order, so long f32 sums stay within a few ulps of the f64 ones.
fn kahan_add(s: vec2<f32>, v: f32) -> vec2<f32> {
    let y = v - s.y;
    let t = s.x + y;
    return vec2<f32>(t, (t - s.x) - y);
}
