//! Placing the pasted object by hand (3d-editing §III.C: the user "adjusts
//! position and scale by monitoring the result interactively"): the
//! window-free arithmetic of a drag on a preview. Dragging the object moves
//! `Paste.target_pixel` by the pointer's distance in image pixels (the
//! centroid stays on the ray of that pixel, `depth_offset_m` from the target
//! surface, so the object slides along the surface); Ctrl + wheel (a pinch)
//! multiplies `Paste.scale`; dragging the ring around the object turns
//! `Paste.rotation_deg` (yaw with the horizontal motion, pitch with the
//! vertical).

use depthgraph_graph::prelude::Mask;

use crate::model::EditorModel;

/// Degrees of rotation per screen point of a gizmo drag.
pub const DEG_PER_POINT: f64 = 0.5;
/// Smallest and largest `Paste.scale` (its schema's range).
pub const SCALE_RANGE: (f64, f64) = (1e-3, 1e3);

/// The `Paste` node whose placement a drag on `node`'s preview moves:
/// `node` itself when it is a `Paste`, else the nearest one upstream
/// (breadth first over its inputs).
pub fn paste_upstream(model: &EditorModel, node: &str) -> Option<String> {
    model.upstream(node).into_iter().find(|n| {
        model
            .document()
            .node(n)
            .is_some_and(|d| d.kind.value == "Paste")
    })
}

/// Where the pasted object is in target pixels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ObjectView {
    /// Mean of the pixel centres the mask covers (alpha >= 0.5).
    pub centroid: [f64; 2],
    /// Largest distance from the centroid to a covered pixel centre.
    pub radius: f64,
    /// Covered pixels.
    pub pixels: usize,
}

/// The pasted object's footprint in `mask` (`Paste.mask`), or `None` when
/// no pixel has alpha >= 0.5.
pub fn object_view(mask: &Mask) -> Option<ObjectView> {
    let (w, h) = mask.dims();
    let (mut sx, mut sy, mut n) = (0.0f64, 0.0f64, 0usize);
    for y in 0..h {
        for x in 0..w {
            if *mask.get(x, y) >= 0.5 {
                sx += x as f64 + 0.5;
                sy += y as f64 + 0.5;
                n += 1;
            }
        }
    }
    if n == 0 {
        return None;
    }
    // Guard: n >= 1.
    let c = [sx / n as f64, sy / n as f64];
    let mut r2 = 0.0f64;
    for y in 0..h {
        for x in 0..w {
            if *mask.get(x, y) >= 0.5 {
                let (dx, dy) = (x as f64 + 0.5 - c[0], y as f64 + 0.5 - c[1]);
                r2 = r2.max(dx * dx + dy * dy);
            }
        }
    }
    Some(ObjectView {
        centroid: c,
        radius: r2.sqrt(),
        pixels: n,
    })
}

/// True when pixel coordinates `px` fall on the object (alpha >= 0.5).
pub fn on_object(mask: &Mask, px: [f64; 2]) -> bool {
    let (w, h) = mask.dims();
    if !(px[0] >= 0.0 && px[1] >= 0.0) {
        return false;
    }
    let (x, y) = (px[0] as usize, px[1] as usize);
    x < w && y < h && *mask.get(x, y) >= 0.5
}

/// The target pixel after a drag by `delta` image pixels from `start`:
/// kept inside the image (`size`: `[0, n - 0.1]`, as `Paste` refuses a
/// pixel at `n` or beyond), rounded to 0.1 px as the Lasso's clicks.
pub fn dragged_target(start: [f64; 2], delta: [f64; 2], size: [usize; 2]) -> [f64; 2] {
    let clamp = |v: f64, n: usize| {
        let v = if v.is_finite() { v } else { 0.0 };
        let hi = (n as f64 - 0.1).max(0.0);
        ((v.clamp(0.0, hi)) * 10.0).round() / 10.0
    };
    [
        clamp(start[0] + delta[0], size[0]),
        clamp(start[1] + delta[1], size[1]),
    ]
}

/// `scale` multiplied by a zoom factor (a wheel notch with Ctrl, a pinch),
/// kept within [`SCALE_RANGE`]; a factor that is not positive and finite
/// leaves the scale as it is.
pub fn zoomed_scale(scale: f64, factor: f64) -> f64 {
    if !(factor.is_finite() && factor > 0.0) {
        return scale;
    }
    (scale * factor).clamp(SCALE_RANGE.0, SCALE_RANGE.1)
}

/// `rotation_deg` (yaw, pitch, roll) after a gizmo drag of `delta` screen
/// points from `start`: yaw follows the horizontal motion, pitch the
/// vertical (dragging up tilts the top away), each wrapped into
/// [-180, 180].
pub fn rotated(start: [f64; 3], delta: [f64; 2]) -> [f64; 3] {
    let wrap = |a: f64| {
        let a = if a.is_finite() { a } else { 0.0 };
        let w = (a + 180.0).rem_euclid(360.0) - 180.0;
        (w * 10.0).round() / 10.0
    };
    [
        wrap(start[0] + delta[0] * DEG_PER_POINT),
        wrap(start[1] - delta[1] * DEG_PER_POINT),
        wrap(start[2]),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn disc_mask(w: usize, h: usize, c: [f64; 2], r: f64) -> Mask {
        let mut v = vec![0.0f32; w * h];
        for y in 0..h {
            for x in 0..w {
                let (dx, dy) = (x as f64 + 0.5 - c[0], y as f64 + 0.5 - c[1]);
                if dx * dx + dy * dy <= r * r {
                    v[y * w + x] = 1.0;
                }
            }
        }
        Mask::from_vec(w, h, v).expect("sizes agree")
    }

    #[test]
    fn the_object_view_is_the_mask_centroid_and_reach() {
        let m = disc_mask(64, 48, [20.0, 30.0], 8.0);
        let v = object_view(&m).expect("a disc");
        assert!((v.centroid[0] - 20.0).abs() < 0.05 && (v.centroid[1] - 30.0).abs() < 0.05);
        assert!(v.radius <= 8.0 && v.radius > 7.0, "{}", v.radius);
        assert!(on_object(&m, [20.0, 30.0]));
        assert!(!on_object(&m, [40.0, 10.0]));
        assert!(!on_object(&m, [-1.0, 10.0]));
        assert!(!on_object(&m, [64.0, 10.0]));
        assert_eq!(object_view(&disc_mask(8, 8, [4.0, 4.0], 0.0)), None);
    }

    #[test]
    fn a_drag_moves_the_target_by_its_distance_inside_the_image() {
        assert_eq!(
            dragged_target([60.5, 150.5], [30.0, -12.0], [320, 240]),
            [90.5, 138.5]
        );
        assert_eq!(
            dragged_target([60.5, 150.5], [-100.0, 200.0], [320, 240]),
            [0.0, 239.9]
        );
        assert_eq!(
            dragged_target([60.5, 150.5], [900.0, 0.0], [320, 240]),
            [319.9, 150.5]
        );
        assert_eq!(
            dragged_target([1.0, 1.0], [f64::NAN, 0.0], [320, 240]),
            [0.0, 1.0]
        );
    }

    #[test]
    fn zoom_and_gizmo_steps_stay_in_range() {
        assert_eq!(zoomed_scale(1.0, 1.1), 1.1);
        assert_eq!(zoomed_scale(900.0, 2.0), 1e3);
        assert_eq!(zoomed_scale(0.5, 0.0), 0.5);
        assert_eq!(zoomed_scale(0.5, f64::NAN), 0.5);
        assert_eq!(rotated([0.0, 0.0, 5.0], [60.0, -20.0]), [30.0, 10.0, 5.0]);
        assert_eq!(rotated([170.0, 0.0, 0.0], [40.0, 0.0]), [-170.0, 0.0, 0.0]);
    }
}
