//! `EdgeDetect`: combined color + depth edge strength for selection
//! (3d-editing §III.C: "All the edges in the source image are detected from
//! combined weights of color and depth derivatives. The combined weight of a
//! pixel is a weighted sum of color and depth derivatives", computed on the
//! "hole-filled depth image" of §III).
//!
//! For every pixel `p`:
//!
//! `strength(p) = (w_c * C(p) + w_d * D(p)) / (w_c + w_d)`, in `[0, 1]`,
//!
//! with both terms normalised to `[0, 1]`:
//!
//! - **Color term** `C(p) = min(1, |grad E(p)| / color_scale)`: `E` is the
//!   gamma-2 encoded color (`sqrt` of linear RGB clamped to `[0, 1]`, close to
//!   sRGB / 255, so one scale works in dark and bright regions alike; the
//!   same encoding as [`crate::depth::bilateral`]), `grad` is the 3x3 Sobel
//!   derivative divided by 8 (a per-pixel derivative: a step of height `h`
//!   gives `h / 2` on the two pixels that straddle it), and `|.|` the
//!   Euclidean norm over the three channels and both axes.
//! - **Depth term** `D(p) = min(1, g(p) / depth_scale_rel)` where `g` is a
//!   depth derivative **relative to the pixel's own depth**, so it is
//!   scale-aware: a 1 m to 2 m step scores like a 10 m to 20 m step. Two
//!   choices ([`DepthTerm`]):
//!   - `"occlusion"` (default): `g(p) = max(0, -(w(a) - 2 w(p) + w(b))) / w(p)`,
//!     maximised over the four axes `a - p - b` through `p` (horizontal,
//!     vertical, two diagonals), with `w = 1 / z` the inverse depth. Inverse
//!     depth is affine in pixel coordinates on any plane, so planes (a table
//!     seen at a grazing angle, a slanted wall) score exactly 0, and only
//!     discontinuities and creases remain. The sign keeps only the
//!     **occluding** (nearer) side of a depth step: a pixel of a near object
//!     next to a far background scores `1 - z_near / z_far`, the background
//!     pixel beside it 0. An object's silhouette is thus one pixel wide and
//!     lies on the object's own outermost pixels, which is where the lasso
//!     (§III.C, [`crate::select::lasso`]) should run to select it.
//!
//!     Creases (where an object stands on a table, the edges of a box) have no
//!     depth step, only a kink, which the same second difference measures
//!     with either sign. They enter at a reduced weight:
//!     `D(p) = max(min(1, g(p) / depth_scale_rel), crease_weight * min(1, k(p) / crease_scale_rel))`
//!     with `k(p) = max |w(a) - 2 w(p) + w(b)| / w(p)` over the axes. With
//!     `crease_weight < 1`, the far side of a depth step (which `k` also
//!     marks) stays weaker than its near side. Crease values shrink with the
//!     resolution (a kink spreads over fewer radians per pixel at higher
//!     resolution): `crease_scale_rel = 0.01` suits 320 to 640 pixel widths at
//!     Kinect-like focal lengths.
//!   - `"gradient"`: `g(p) = |Sobel grad z(p)| / 8 / z(p)`, the plain relative
//!     gradient magnitude (symmetric: both sides of a step score, and slanted
//!     planes score `~ 1 / (v - c_y)` per pixel near the horizon).
//!
//! Depth holes (0, NaN, negative; see the value conventions) give no depth
//! term: an axis through a hole is skipped (`"occlusion"`), a hole neighbour
//! takes the centre's depth (`"gradient"`). Connect a hole-filled depth (e.g.
//! `DualPullPush`, §III.B) as the paper does. Neighbours outside the image
//! are replicated (color) or skipped (depth), so the image border itself is
//! never an edge.
//!
//! The binary `edges` output is `strength >= threshold`, optionally thinned
//! by non-maximum suppression to one-pixel-wide lines (for display and as the
//! paper's "detected edges").

use std::sync::Arc;

use depthgraph_graph::node_params;
use depthgraph_graph::prelude::*;
use depthgraph_graph::registry::RegistryError;
use rayon::prelude::*;

depthgraph_graph::param_choice! {
    /// Which depth derivative the depth term uses (the `depth_term`
    /// parameter; see the module docs).
    pub enum DepthTerm {
        /// Occluding-side second difference of inverse depth, relative to depth.
        Occlusion = "occlusion",
        /// Sobel gradient magnitude of depth, relative to depth.
        Gradient = "gradient",
    }
}

node_params! {
    /// Parameters of `EdgeDetect`.
    pub struct EdgeParams {
        /// Weight of the color term in the weighted sum (3d-editing §III.C).
        pub color_weight: f64 = 0.3, ParamKind::Float { min: 0.0, max: 1000.0 };
        /// Weight of the depth term. Above the color weight by default, so an
        /// object's silhouette outscores the texture inside it and behind it.
        pub depth_weight: f64 = 0.7, ParamKind::Float { min: 0.0, max: 1000.0 };
        /// Color gradient magnitude (gamma-2 encoded units per pixel, see the
        /// module docs) that maps to a color term of 1.
        pub color_scale: f64 = 0.1, ParamKind::Float { min: 1e-6, max: 100.0 };
        /// Relative depth derivative that maps to a depth term of 1 (0.05: a
        /// 5 % depth step saturates).
        pub depth_scale_rel: f64 = 0.05, ParamKind::Float { min: 1e-6, max: 100.0 };
        /// Weight of creases (kinks without a depth step) relative to occluding
        /// edges, "occlusion" term only; 0 ignores them.
        pub crease_weight: f64 = 0.5, ParamKind::Float { min: 0.0, max: 1.0 };
        /// Relative second difference of inverse depth that makes a full crease
        /// ("occlusion" term only).
        pub crease_scale_rel: f64 = 0.01, ParamKind::Float { min: 1e-6, max: 100.0 };
        /// "occlusion": occluding-side second difference of inverse depth
        /// (planes score 0, only the nearer side of a step scores);
        /// "gradient": relative Sobel gradient magnitude.
        pub depth_term: DepthTerm = DepthTerm::Occlusion, ParamKind::Choice(DepthTerm::NAMES);
        /// Strength at or above which a pixel is an edge in the binary `edges` output.
        pub threshold: f64 = 0.5, ParamKind::Float { min: 0.0, max: 1.0 };
        /// Thin the binary edges to one pixel by non-maximum suppression.
        pub thin: bool = true, ParamKind::Bool;
    }
}

/// Result of [`detect_edges`].
#[derive(Debug, Clone, PartialEq)]
pub struct Edges {
    /// Combined edge strength in `[0, 1]`.
    pub strength: Confidence,
    /// 1 on (thinned) edge pixels, 0 elsewhere.
    pub edges: Mask,
}

/// Checks the parameters (both backends); returns the depth term.
pub fn check_params(p: &EdgeParams) -> Result<DepthTerm, NodeError> {
    for (name, v) in [
        ("color_weight", p.color_weight),
        ("depth_weight", p.depth_weight),
    ] {
        if !(v.is_finite() && v >= 0.0) {
            return Err(NodeError::param(
                name,
                format!("{v} must be finite and >= 0"),
            ));
        }
    }
    if p.color_weight + p.depth_weight <= 0.0 {
        return Err(NodeError::param(
            "depth_weight",
            "color_weight + depth_weight must be > 0 (both are 0)",
        ));
    }
    if !(p.crease_weight.is_finite() && (0.0..=1.0).contains(&p.crease_weight)) {
        return Err(NodeError::param(
            "crease_weight",
            format!("{} is outside [0, 1]", p.crease_weight),
        ));
    }
    for (name, v) in [
        ("color_scale", p.color_scale),
        ("depth_scale_rel", p.depth_scale_rel),
        ("crease_scale_rel", p.crease_scale_rel),
    ] {
        if !(v.is_finite() && v > 0.0) {
            return Err(NodeError::param(
                name,
                format!("{v} must be finite and > 0"),
            ));
        }
    }
    Ok(p.depth_term)
}

/// Checks that the depth has the color's size (both backends).
pub fn check_dims(color: &ColorImage, depth: &DepthMap) -> Result<(), NodeError> {
    if !color.same_dims(depth) {
        return Err(NodeError::input(
            "depth",
            format!(
                "is {}x{} but the color is {}x{}",
                depth.width(),
                depth.height(),
                color.width(),
                color.height()
            ),
        ));
    }
    Ok(())
}

/// Gamma-2 encoding (see the module docs): finite, in `[0, 1]`, NaN -> 0.
#[inline]
fn encode(v: f32) -> f32 {
    if v > 0.0 { v.min(1.0).sqrt() } else { 0.0 }
}

/// Combined color + depth edge strength (3d-editing §III.C), see the module
/// docs for the two terms and their normalisation.
///
/// ```
/// use depthgraph_graph::value::Image;
/// use depthgraph_nodes::select::edges::{detect_edges, EdgeParams};
/// // Near (1 m) on the left, far (2 m) on the right, one flat color.
/// let depth = Image::from_fn(8, 4, |x, _| if x < 4 { 1.0f32 } else { 2.0 });
/// let color = Image::filled(8, 4, [0.5f32; 3]);
/// let e = detect_edges(&color, &depth, &EdgeParams::default()).unwrap();
/// assert!(*e.strength.get(3, 2) > 0.69); // the near side of the step
/// assert!(*e.strength.get(4, 2) < 0.36); // the far side: a crease at half weight
/// assert_eq!(*e.edges.get(3, 1), 1.0);
/// ```
pub fn detect_edges(
    color: &ColorImage,
    depth: &DepthMap,
    p: &EdgeParams,
) -> Result<Edges, NodeError> {
    let term = check_params(p)?;
    check_dims(color, depth)?;
    let (w, h) = color.dims();
    if w == 0 || h == 0 {
        return Ok(Edges {
            strength: Image::filled(w, h, 0.0),
            edges: Image::filled(w, h, 0.0),
        });
    }
    let enc: Vec<[f32; 3]> = color.as_slice().par_iter().map(|c| c.map(encode)).collect();
    // Inverse depth, 0 for holes (occlusion term) / depth, 0 for holes (gradient term).
    let zs: Vec<f32> = depth
        .as_slice()
        .par_iter()
        .map(|&z| if DepthMap::is_valid(z) { z } else { 0.0 })
        .collect();
    let inv: Vec<f32> = zs
        .par_iter()
        .map(|&z| if z > 0.0 { 1.0 / z } else { 0.0 }) // guard: z > 0
        .collect();
    // guard: the sum of weights is > 0 (checked); the scales are > 0 (checked)
    let wsum = p.color_weight + p.depth_weight;
    let (wc, wd) = (
        (p.color_weight / wsum) as f32,
        (p.depth_weight / wsum) as f32,
    );
    let inv_cs = (1.0 / p.color_scale) as f32;
    let inv_ds = (1.0 / p.depth_scale_rel) as f32;
    let inv_ks = (1.0 / p.crease_scale_rel) as f32;
    let kw = p.crease_weight as f32;

    let mut strength = vec![0.0f32; w * h];
    strength.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        let ym = y.saturating_sub(1);
        let yp = (y + 1).min(h - 1);
        for (x, out) in row.iter_mut().enumerate() {
            let xm = x.saturating_sub(1);
            let xp = (x + 1).min(w - 1);
            // Color: Sobel / 8 per channel, replicated borders.
            let e = |xx: usize, yy: usize| &enc[yy * w + xx];
            let (tl, t, tr) = (e(xm, ym), e(x, ym), e(xp, ym));
            let (l, r) = (e(xm, y), e(xp, y));
            let (bl, b, br) = (e(xm, yp), e(x, yp), e(xp, yp));
            let mut g2 = 0.0f32;
            for c in 0..3 {
                let gx = ((tr[c] + 2.0 * r[c] + br[c]) - (tl[c] + 2.0 * l[c] + bl[c])) * 0.125;
                let gy = ((bl[c] + 2.0 * b[c] + br[c]) - (tl[c] + 2.0 * t[c] + tr[c])) * 0.125;
                g2 += gx * gx + gy * gy;
            }
            let cterm = (g2.sqrt() * inv_cs).min(1.0);
            let dterm = match term {
                DepthTerm::Occlusion => {
                    let (g, k) = occlusion_at(&inv, w, h, x, y);
                    (g * inv_ds).min(1.0).max(kw * (k * inv_ks).min(1.0))
                }
                DepthTerm::Gradient => {
                    (gradient_at(&zs, w, x, y, xm, xp, ym, yp) * inv_ds).min(1.0)
                }
            };
            let s = wc * cterm + wd * dterm;
            // NaN cannot arise (all inputs sanitised); clamp for rounding.
            *out = s.clamp(0.0, 1.0);
        }
    });
    let strength = Image::from_vec(w, h, strength)?;
    let edges = binary_edges(&strength, p.threshold as f32, p.thin);
    Ok(Edges { strength, edges })
}

/// The occluding-side relative second difference of inverse depth `g` at
/// `(x, y)` and its magnitude of either sign `k` (see the module docs); 0 at
/// holes and where no axis has two valid neighbours.
#[inline]
fn occlusion_at(inv: &[f32], w: usize, h: usize, x: usize, y: usize) -> (f32, f32) {
    let wp = inv[y * w + x];
    if wp <= 0.0 {
        return (0.0, 0.0);
    }
    let mut best = 0.0f32;
    let mut kink = 0.0f32;
    for (dx, dy) in [(1isize, 0isize), (0, 1), (1, 1), (1, -1)] {
        let (ax, ay) = (x as isize - dx, y as isize - dy);
        let (bx, by) = (x as isize + dx, y as isize + dy);
        if ax < 0 || ay < 0 || bx < 0 || by < 0 {
            continue;
        }
        let (ax, ay, bx, by) = (ax as usize, ay as usize, bx as usize, by as usize);
        if ax >= w || bx >= w || ay >= h || by >= h {
            continue;
        }
        let (wa, wb) = (inv[ay * w + ax], inv[by * w + bx]);
        if wa <= 0.0 || wb <= 0.0 {
            continue;
        }
        let d = -(wa - 2.0 * wp + wb);
        best = best.max(d);
        kink = kink.max(-d);
    }
    // guard: wp > 0 (checked above)
    (best / wp, kink / wp)
}

/// Relative Sobel gradient magnitude of depth at `(x, y)`; hole neighbours take
/// the centre's depth; 0 at a hole.
#[allow(clippy::too_many_arguments)]
#[inline]
fn gradient_at(
    zs: &[f32],
    w: usize,
    x: usize,
    y: usize,
    xm: usize,
    xp: usize,
    ym: usize,
    yp: usize,
) -> f32 {
    let zc = zs[y * w + x];
    if zc <= 0.0 {
        return 0.0;
    }
    let z = |xx: usize, yy: usize| {
        let v = zs[yy * w + xx];
        if v > 0.0 { v } else { zc }
    };
    let gx = ((z(xp, ym) + 2.0 * z(xp, y) + z(xp, yp)) - (z(xm, ym) + 2.0 * z(xm, y) + z(xm, yp)))
        * 0.125;
    let gy = ((z(xm, yp) + 2.0 * z(x, yp) + z(xp, yp)) - (z(xm, ym) + 2.0 * z(x, ym) + z(xp, ym)))
        * 0.125;
    // guard: zc > 0 (checked above)
    (gx * gx + gy * gy).sqrt() / zc
}

/// `strength >= threshold`, thinned by non-maximum suppression when `thin`:
/// among the four axes through a pixel, the one whose larger neighbour is the
/// smallest is the direction across the edge; the pixel survives if it beats
/// the first neighbour on that axis strictly and the second at least
/// (the asymmetry keeps exactly one pixel of a two-pixel-wide plateau).
/// Neighbours outside the image are replicated from the border.
pub fn binary_edges(strength: &Confidence, threshold: f32, thin: bool) -> Mask {
    let (w, h) = strength.dims();
    let s = strength.as_slice();
    let mut out = vec![0.0f32; w * h];
    out.par_chunks_mut(w.max(1))
        .enumerate()
        .for_each(|(y, row)| {
            for (x, o) in row.iter_mut().enumerate() {
                let v = s[y * w + x];
                if !(v >= threshold && v > 0.0) {
                    continue;
                }
                if !thin {
                    *o = 1.0;
                    continue;
                }
                let at = |dx: isize, dy: isize| -> f32 {
                    let xx = (x as isize + dx).clamp(0, w as isize - 1) as usize;
                    let yy = (y as isize + dy).clamp(0, h as isize - 1) as usize;
                    s[yy * w + xx]
                };
                let mut best: Option<(f32, f32, f32)> = None;
                for (dx, dy) in [(1isize, 0isize), (0, 1), (1, 1), (1, -1)] {
                    let (a, b) = (at(-dx, -dy), at(dx, dy));
                    let m = a.max(b);
                    if best.is_none_or(|(bm, _, _)| m < bm) {
                        best = Some((m, a, b));
                    }
                }
                if let Some((_, a, b)) = best
                    && v > a
                    && v >= b
                {
                    *o = 1.0;
                }
            }
        });
    // the buffer has w * h elements by construction
    Image::from_vec(w, h, out).unwrap_or_else(|_| Image::filled(w, h, 0.0))
}

depthgraph_graph::ports! {
    /// Inputs of `EdgeDetect`.
    inputs struct EdgesIn {
        /// linear RGB
        color: Arc<ColorImage>,
        /// metres, hole-filled (holes give no depth term)
        depth: Arc<DepthMap>,
    }
}

depthgraph_graph::ports! {
    /// Outputs of `EdgeDetect`.
    outputs struct EdgesOut {
        /// combined edge strength in [0, 1]
        strength: Confidence,
        /// 1 where strength >= threshold (thinned when `thin`)
        edges: Mask,
    }
}

fn eval(_: &EvalCtx, i: EdgesIn, p: &EdgeParams) -> Result<Produced<EdgesOut>, NodeError> {
    let e = detect_edges(&i.color, &i.depth, p)?;
    Ok(EdgesOut {
        strength: e.strength,
        edges: e.edges,
    }
    .into())
}

/// Registers `EdgeDetect`.
pub fn register(reg: &mut Registry) -> Result<(), RegistryError> {
    reg.register(PortedNode::new(
        "EdgeDetect",
        1,
        "Edge strength from a weighted sum of color and relative depth derivatives (3d-editing §III.C).\n\
         strength = (w_c * C + w_d * D) / (w_c + w_d) in [0, 1]; C: gamma-2 color Sobel magnitude / color_scale, \
         D: occluding-side depth discontinuity (or relative gradient) / depth_scale_rel, each clamped to 1.",
        eval,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn flat(w: usize, h: usize) -> ColorImage {
        Image::filled(w, h, [0.4f32, 0.3, 0.2])
    }

    #[test]
    fn occlusion_term_marks_only_the_near_side_and_is_scale_aware() {
        for (near, far) in [(1.0f32, 2.0f32), (10.0, 20.0)] {
            let d = Image::from_fn(16, 8, |x, _| if x < 8 { near } else { far });
            let e = detect_edges(&flat(16, 8), &d, &EdgeParams::default()).unwrap();
            for y in 0..8 {
                for x in 0..16 {
                    let s = *e.strength.get(x, y);
                    if x == 7 {
                        // 1 - near/far = 0.5 >> 0.05: saturated depth term, weight 0.7
                        assert!((s - 0.7).abs() < 1e-6, "({x},{y}) {s}");
                    } else if x == 8 {
                        // the far side only counts as a (concave) crease: half weight
                        assert!((s - 0.35).abs() < 1e-6, "({x},{y}) {s}");
                    } else {
                        assert_eq!(s, 0.0, "({x},{y})");
                    }
                }
            }
            // far on the left: the near side is now column 8
            let d = Image::from_fn(16, 8, |x, _| if x < 8 { far } else { near });
            let e = detect_edges(&flat(16, 8), &d, &EdgeParams::default()).unwrap();
            assert!(*e.strength.get(8, 3) > 0.69 && *e.strength.get(7, 3) < 0.36);
            // without the crease term the far side scores nothing
            let pure = EdgeParams {
                crease_weight: 0.0,
                ..Default::default()
            };
            let e = detect_edges(&flat(16, 8), &d, &pure).unwrap();
            assert_eq!(*e.strength.get(7, 3), 0.0);
        }
    }

    #[test]
    fn planes_have_no_depth_edge_in_occlusion_mode_but_do_in_gradient_mode() {
        // A floor seen at a grazing angle: inverse depth affine in (u, v).
        let d = Image::from_fn(40, 30, |x, y| {
            1.0 / (0.05 + 0.01 * (y as f32 + 0.5) + 0.002 * (x as f32 + 0.5))
        });
        let e = detect_edges(&flat(40, 30), &d, &EdgeParams::default()).unwrap();
        let max = e.strength.as_slice().iter().fold(0.0f32, |a, b| a.max(*b));
        assert!(max < 0.02, "plane scored {max}");
        let g = detect_edges(
            &flat(40, 30),
            &d,
            &EdgeParams {
                depth_term: DepthTerm::Gradient,
                ..Default::default()
            },
        )
        .unwrap();
        let gmax = g.strength.as_slice().iter().fold(0.0f32, |a, b| a.max(*b));
        assert!(gmax > 0.3, "gradient mode scored the slope {gmax}");
    }

    #[test]
    fn creases_score_below_occluding_edges() {
        // A floor (inverse depth rising downwards) meeting a vertical wall
        // (constant depth) at row 10: a concave kink (an object standing on a table).
        let d = Image::from_fn(8, 20, |_, y| {
            if y < 10 {
                2.0f32
            } else {
                1.0 / (0.5 + 0.05 * (y as f32 - 9.0))
            }
        });
        let e = detect_edges(&flat(8, 20), &d, &EdgeParams::default()).unwrap();
        let col: Vec<f32> = (0..20).map(|y| *e.strength.get(4, y)).collect();
        // k = 0.05 / 0.5 = 0.1 >> crease_scale_rel: a full crease, half weight
        assert!((col[9] - 0.35).abs() < 1e-3, "{col:?}");
        for (y, v) in col.iter().enumerate() {
            if y != 9 && y != 10 {
                assert!(*v < 1e-4, "row {y} (f32 rounding only): {col:?}");
            }
        }
        // A ridge towards the camera (convex): only the occluding term, at its
        // own scale: 0.7 * (0.02 / 0.99) / 0.05 at the ridge.
        let ridge = Image::from_fn(8, 20, |_, y| 1.0 / (1.0 - 0.02 * (y as f32 - 9.5).abs()));
        let e = detect_edges(&flat(8, 20), &ridge, &EdgeParams::default()).unwrap();
        let v = *e.strength.get(4, 9);
        assert!((v - 0.7 * (0.02 / 0.99) / 0.05).abs() < 1e-3, "{v}");
        assert!(*e.strength.get(4, 3) < 1e-4);
    }

    #[test]
    fn gradient_mode_marks_both_sides_and_color_edges_thin_to_one_pixel() {
        let d = Image::from_fn(16, 8, |x, _| if x < 8 { 1.0f32 } else { 2.0 });
        let p = EdgeParams {
            depth_term: DepthTerm::Gradient,
            ..Default::default()
        };
        let e = detect_edges(&flat(16, 8), &d, &p).unwrap();
        assert!(*e.strength.get(7, 4) > 0.6 && *e.strength.get(8, 4) > 0.6);
        assert_eq!(*e.strength.get(5, 4), 0.0);
        // color step at constant depth: both columns score, thinning keeps one
        let c = Image::from_fn(16, 8, |x, _| if x < 8 { [0.05f32; 3] } else { [0.8f32; 3] });
        let dd = Image::filled(16, 8, 1.5f32);
        let thick = detect_edges(
            &c,
            &dd,
            &EdgeParams {
                threshold: 0.2,
                thin: false,
                ..Default::default()
            },
        )
        .unwrap();
        let thin = detect_edges(
            &c,
            &dd,
            &EdgeParams {
                threshold: 0.2,
                ..Default::default()
            },
        )
        .unwrap();
        for y in 0..8 {
            assert_eq!(*thick.edges.get(7, y) + *thick.edges.get(8, y), 2.0);
            assert_eq!(*thin.edges.get(7, y) + *thin.edges.get(8, y), 1.0);
        }
        let count = |m: &Mask| m.as_slice().iter().filter(|v| **v > 0.0).count();
        assert_eq!(count(&thick.edges), 16);
        assert_eq!(count(&thin.edges), 8);
    }

    #[test]
    fn hard_inputs_stay_in_range() {
        let d = Image::from_fn(9, 7, |x, y| match (x + y) % 4 {
            0 => 0.0,
            1 => f32::NAN,
            2 => 1e-6,
            _ => 1e6,
        });
        let c = Image::from_fn(9, 7, |x, _| match x % 3 {
            0 => [f32::NAN, f32::INFINITY, -1.0],
            1 => [1e30, 0.0, 0.5],
            _ => [0.2, 0.2, 0.2],
        });
        for term in [DepthTerm::Occlusion, DepthTerm::Gradient] {
            let e = detect_edges(
                &c,
                &d,
                &EdgeParams {
                    depth_term: term,
                    ..Default::default()
                },
            )
            .unwrap();
            for v in e.strength.as_slice() {
                assert!(v.is_finite() && (0.0..=1.0).contains(v), "{v}");
            }
        }
        // 1x1 and empty images
        let e = detect_edges(
            &Image::filled(1, 1, [0.5; 3]),
            &Image::filled(1, 1, 1.0),
            &EdgeParams::default(),
        )
        .unwrap();
        assert_eq!(e.strength.as_slice(), &[0.0]);
        let e = detect_edges(
            &Image::filled(0, 0, [0.5; 3]),
            &Image::filled(0, 0, 1.0),
            &EdgeParams::default(),
        )
        .unwrap();
        assert!(e.strength.is_empty());
    }

    #[test]
    fn bad_parameters_and_sizes_are_named() {
        let c = flat(4, 4);
        let d = Image::filled(4, 4, 1.0f32);
        let e = detect_edges(
            &c,
            &d,
            &EdgeParams {
                color_weight: 0.0,
                depth_weight: 0.0,
                ..Default::default()
            },
        )
        .unwrap_err();
        assert!(e.to_string().contains("depth_weight"), "{e}");
        let e = detect_edges(&c, &Image::filled(3, 4, 1.0f32), &EdgeParams::default()).unwrap_err();
        assert!(
            e.to_string().contains("depth") && e.to_string().contains("3x4"),
            "{e}"
        );
        let mut bad = EdgeParams::default().to_values();
        bad.insert("depth_term".into(), ParamValue::Text("laplace".into()));
        let e = EdgeParams::from_values(&bad).unwrap_err();
        assert!(e.contains("depth_term"), "{e}");
    }
}
