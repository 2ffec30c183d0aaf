//! The depth colormap: near to far through seven sRGB stops (dark blue to
//! dark red), lightness growing up to yellow so near and far are told apart
//! also in grey print; the one map the DepthPreview node and the editor use.

use depthgraph_graph::prelude::*;

use crate::kit::color::srgb_to_linear;

/// Colors of the depth colormap (near to far), sRGB-encoded: dark blue, blue,
/// cyan, green, yellow, orange, dark red. Perceptually ordered in lightness
/// up to yellow, so near and far are told apart also in grey print.
const STOPS_SRGB: [[f32; 3]; 7] = [
    [0.19, 0.07, 0.45],
    [0.15, 0.35, 0.85],
    [0.10, 0.70, 0.85],
    [0.30, 0.85, 0.35],
    [0.95, 0.85, 0.15],
    [0.95, 0.45, 0.10],
    [0.60, 0.05, 0.05],
];

/// Linear RGB color for `t` in [0, 1] (clamped; NaN maps to 0).
pub fn colormap(t: f32) -> [f32; 3] {
    let t = if t.is_nan() { 0.0 } else { t.clamp(0.0, 1.0) };
    let x = t * (STOPS_SRGB.len() - 1) as f32;
    let i = (x.floor() as usize).min(STOPS_SRGB.len() - 2);
    let f = x - i as f32;
    let (a, b) = (STOPS_SRGB[i], STOPS_SRGB[i + 1]);
    std::array::from_fn(|c| srgb_to_linear(a[c] + (b[c] - a[c]) * f))
}

/// Depth as colors between `min_m` (first color) and `max_m` (last); holes are black.
///
/// ```
/// use depthgraph_graph::value::Image;
/// let d = Image::from_vec(2, 1, vec![1.0f32, 0.0]).unwrap();
/// let c = depthgraph_nodes::kit::colormap::colormap_depth(&d, 0.5, 2.0);
/// assert_eq!(*c.get(1, 0), [0.0, 0.0, 0.0]);
/// ```
pub fn colormap_depth(depth: &DepthMap, min_m: f32, max_m: f32) -> ColorImage {
    // guard: a zero or negative span maps everything to the first color
    let span = if max_m > min_m {
        max_m - min_m
    } else {
        f32::INFINITY
    };
    depth.map(|z| {
        if DepthMap::is_valid(*z) {
            colormap((z - min_m) / span)
        } else {
            [0.0; 3]
        }
    })
}

/// The `lo` and `hi` quantiles (in [0, 1]) of the valid depths; `(0, 1)` when none is valid.
pub fn depth_range(depth: &DepthMap, lo: f64, hi: f64) -> (f32, f32) {
    let mut v: Vec<f32> = depth
        .as_slice()
        .iter()
        .copied()
        .filter(|z| DepthMap::is_valid(*z))
        .collect();
    if v.is_empty() {
        return (0.0, 1.0);
    }
    let n = v.len();
    let idx = |q: f64| ((q.clamp(0.0, 1.0) * (n - 1) as f64).round() as usize).min(n - 1);
    let (i, j) = (idx(lo), idx(hi));
    let a = *v.select_nth_unstable_by(i, f32::total_cmp).1;
    let b = *v.select_nth_unstable_by(j, f32::total_cmp).1;
    (a, b)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn colormap_is_monotone_in_lightness_up_to_yellow() {
        let lum = crate::kit::color::luminance;
        let mut prev = -1.0;
        for i in 0..=40 {
            let l = lum(colormap(i as f32 / 60.0)); // up to t = 2/3 (yellow)
            assert!(l > prev, "lightness must grow at step {i}");
            prev = l;
        }
    }

    #[test]
    fn quantiles_ignore_holes() {
        let d = Image::from_vec(5, 1, vec![0.0, 3.0, f32::NAN, 1.0, 2.0]).unwrap();
        assert_eq!(depth_range(&d, 0.0, 1.0), (1.0, 3.0));
        assert_eq!(
            depth_range(&Image::filled(2, 2, 0.0f32), 0.0, 1.0),
            (0.0, 1.0)
        );
    }
}
