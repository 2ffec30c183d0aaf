//! Setting focus after the shot by clicking on the picture (depth-blur
//! paper, Sec. 2: the user chooses focus and aperture after the shot): the
//! depth under the pointer as the median of a small window with holes
//! skipped, and the circle of confusion a pixel gets under the node's lens
//! (`C |1/z - 1/u|`, [`ThinLens::coc_scale`]).

use depthgraph_graph::prelude::{DepthMap, NodeParams, ParamMap};
use depthgraph_nodes::camera::lens::{ThinLens, inv_depth};
use depthgraph_nodes::camera::refocus::RefocusParams;

use crate::model::EditorModel;

/// Half-width of the focus window (5x5 pixels).
pub const FOCUS_WINDOW_RADIUS: usize = 2;

/// The node kinds whose preview sets focus on a click.
pub const FOCUS_KINDS: [&str; 2] = ["Refocus", "ReverseMappedDof"];

/// The median of the valid depths (finite, > 0) in the `(2r+1)²` window
/// around pixel coordinates `px`; `None` when the point is outside the map
/// or every sample there is a hole. An even count takes the mean of the
/// two middle samples.
pub fn focus_depth(depth: &DepthMap, px: [f64; 2], radius: usize) -> Option<f64> {
    let (w, h) = depth.dims();
    if !(px[0] >= 0.0 && px[1] >= 0.0) || w == 0 || h == 0 {
        return None;
    }
    let (cx, cy) = (px[0] as usize, px[1] as usize);
    if cx >= w || cy >= h {
        return None;
    }
    let mut z: Vec<f64> = Vec::with_capacity((2 * radius + 1).pow(2));
    for y in cy.saturating_sub(radius)..=(cy + radius).min(h - 1) {
        for x in cx.saturating_sub(radius)..=(cx + radius).min(w - 1) {
            let v = *depth.get(x, y);
            if DepthMap::is_valid(v) {
                z.push(f64::from(v));
            }
        }
    }
    if z.is_empty() {
        return None;
    }
    z.sort_by(f64::total_cmp);
    let n = z.len();
    Some(if n % 2 == 1 {
        z[n / 2]
    } else {
        0.5 * (z[n / 2 - 1] + z[n / 2])
    })
}

/// The lens of a `Refocus` / `ReverseMappedDof` node as its parameters now
/// stand in the document.
pub fn node_lens(model: &EditorModel, node: &str) -> Result<ThinLens, String> {
    let mut values = ParamMap::new();
    for spec in RefocusParams::specs() {
        values.insert(spec.name.to_string(), model.param_value(node, spec.name)?);
    }
    let p = RefocusParams::from_values(&values).map_err(|e| format!("node `{node}`: {e}"))?;
    Ok(p.lens())
}

/// Circle-of-confusion diameter in pixels of depth `z` in an image
/// `width_px` wide under `lens`; `None` for a lens that does not validate.
/// A hole counts as infinitely far, as in the node.
pub fn coc_px(lens: &ThinLens, width_px: usize, z: f32) -> Option<f64> {
    lens.validate().ok()?;
    Some(lens.coc_scale(width_px) * (inv_depth(z) - lens.inv_focus()).abs())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_focus_depth_is_the_window_median_without_holes() {
        // 5x5 window around (2, 2): depth 1 + x/10, one hole, one far outlier.
        let mut z: Vec<f32> = (0..36).map(|i| 1.0 + (i % 6) as f32 / 10.0).collect();
        z[2 * 6 + 2] = 0.0;
        z[6 + 1] = 50.0;
        let d = DepthMap::from_vec(6, 6, z).expect("6x6");
        let got = focus_depth(&d, [2.5, 2.5], 2).expect("samples");
        assert!((got - 1.2).abs() < 1e-6, "{got}");
        assert_eq!(focus_depth(&d, [6.0, 1.0], 2), None);
        assert_eq!(focus_depth(&d, [f64::NAN, 1.0], 2), None);
        let holes = DepthMap::from_vec(2, 1, vec![0.0, f32::NAN]).expect("2x1");
        assert_eq!(focus_depth(&holes, [0.5, 0.5], 2), None);
    }

    #[test]
    fn the_circle_of_confusion_is_zero_in_focus_and_grows_off_it() {
        let lens = ThinLens {
            focal_length_mm: 50.0,
            f_number: 2.0,
            focus_m: 2.0,
            sensor_width_mm: 36.0,
        };
        assert!(coc_px(&lens, 640, 2.0).expect("valid") < 1e-9);
        let near = coc_px(&lens, 640, 1.0).expect("valid");
        // C = f_px * A * u / (u - f) = 888.9 * 0.025 * 2 / 1.95; |1/1 - 1/2| = 0.5
        let want = 50.0 * 640.0 / 36.0 * 0.025 * (2.0 / 1.95) * 0.5;
        assert!((near - want).abs() < 1e-9 * want, "{near} vs {want}");
        let bad = ThinLens {
            focus_m: 0.01,
            ..lens
        };
        assert_eq!(coc_px(&bad, 640, 1.0), None);
    }
}
