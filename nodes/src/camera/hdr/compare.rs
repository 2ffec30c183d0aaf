//! Comparing radiance maps that are known only up to one factor per channel
//! (what a recovered response gives): the measures the tests and the HDR
//! bench report.

use depthgraph_graph::prelude::*;

/// Mean `|log2(a / b)|` in stops over the pixel-channels where `mask` is set
/// and both values are positive, after removing each channel's median log
/// ratio (the factor a recovered response leaves open). `None` when a
/// channel has no such value or the sizes differ.
pub fn mean_stops_apart(a: &ColorImage, b: &ColorImage, mask: &[bool]) -> Option<f64> {
    if !a.same_dims(b) || mask.len() != a.len() {
        return None;
    }
    let mut sum = 0.0f64;
    let mut n = 0usize;
    for c in 0..3 {
        let mut d: Vec<f64> = a
            .as_slice()
            .iter()
            .zip(b.as_slice())
            .zip(mask)
            .filter(|((p, q), m)| **m && p[c] > 0.0 && q[c] > 0.0)
            .map(|((p, q), _)| (p[c] as f64 / q[c] as f64).log2())
            .collect();
        if d.is_empty() {
            return None;
        }
        let mid = d.len() / 2;
        let med = *d.select_nth_unstable_by(mid, f64::total_cmp).1;
        sum += d.iter().map(|v| (v - med).abs()).sum::<f64>();
        n += d.len();
    }
    // guard: every channel contributed at least one value, so n > 0
    Some(sum / n as f64)
}

/// Pixels some exposure of `stack` sees well: every channel finite and
/// within `[lo, hi]` (values in `[0, 1]`) in at least one exposure.
pub fn seen_well(stack: &ExposureStack, lo: f32, hi: f32) -> Vec<bool> {
    let n = stack.images.first().map_or(0, |i| i.len());
    (0..n)
        .map(|i| {
            stack.images.iter().any(|img| {
                img.as_slice()[i]
                    .iter()
                    .all(|v| v.is_finite() && (lo..=hi).contains(v))
            })
        })
        .collect()
}
