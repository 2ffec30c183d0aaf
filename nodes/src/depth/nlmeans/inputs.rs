//! Reading the inputs: depth and confidence sanitised into flat buffers.

use depthgraph_graph::prelude::*;
use rayon::prelude::*;

// ---------------------------------------------------------------------------
// Inputs
// ---------------------------------------------------------------------------

/// Patch-distance feature of one linear color channel: `sqrt(c / (1 + c))`,
/// in `[0, 1)`; NaN and negative values count as 0, `+inf` as 1.
#[inline]
pub(super) fn guide_feature(c: f32) -> f32 {
    if c.is_nan() || c <= 0.0 {
        0.0
    } else if c.is_infinite() {
        1.0
    } else {
        // Guard: 1 + c >= 1.
        (c / (1.0 + c)).sqrt()
    }
}

pub(super) fn guide_features(color: &ColorImage) -> Vec<[f32; 3]> {
    color
        .as_slice()
        .par_iter()
        .map(|c| c.map(guide_feature))
        .collect()
}

/// Depth with holes as 0, and per-pixel confidence: the given confidence
/// (NaN as 0, clamped to `[0, 1]`, 1 when absent) at valid pixels, 0 at holes.
pub(super) fn sanitize(depth: &DepthMap, confidence: Option<&Confidence>) -> (Vec<f32>, Vec<f32>) {
    let z: Vec<f32> = depth
        .as_slice()
        .iter()
        .map(|z| if DepthMap::is_valid(*z) { *z } else { 0.0 })
        .collect();
    let c = z
        .iter()
        .enumerate()
        .map(|(i, z)| {
            if *z > 0.0 {
                let c = confidence.map_or(1.0, |c| c.as_slice()[i]);
                if c.is_nan() { 0.0 } else { c.clamp(0.0, 1.0) }
            } else {
                0.0
            }
        })
        .collect();
    (z, c)
}

pub(super) fn image<T, K>(w: usize, h: usize, data: Vec<T>) -> Result<Image<T, K>, NodeError> {
    Ok(Image::from_vec(w, h, data)?)
}
