//! Hole filling by pull-push on image pyramids (3d-editing §III.A-B, eq. 2-4).
//!
//! **Pull**: depth and color pyramids are built by averaging 2x2 blocks; a
//! depth sample only counts where it is valid, and each coarse pixel keeps a
//! validity weight `min(1, sum of its children's weights)`.
//!
//! **Push**: from the coarsest level to the finest, every pixel that is a
//! hole at its level takes a weighted mean of the four nearest coarse pixels
//! (already filled). Valid pixels are never changed.
//!
//! - [`Weights::Bilinear`]: the usual bilinear weights (the baseline of the
//!   paper's Fig. 4c).
//! - [`Weights::Dual`]: the paper's dual weights, `W_d * W_c` with
//!   `W_d = 1 / (eps + |X(p_i^r) - X(p_j^{r+1})|)` (eq. 2, distance between
//!   the unprojected 3D points) and `W_c = 1 / (eps + |C(p_i^r) - C(p_j^{r+1})|)`
//!   (eq. 3, linear-RGB distance), combined as in eq. 4. The hole pixel's own
//!   3D point needs a depth: it is unprojected at the bilinear estimate from
//!   the same four coarse pixels (the "interpolated depth pixel" of §III.B).
//!
//! **Background side** (DualPullPush, `background = β > 0`, on by
//! default): holes beside a depth edge are mostly background by
//! construction (a structured-light projector's shadow, a ToF camera's
//! flying pixels at a silhouette), and an average of both sides puts them
//! in mid-air. Every weight of the pull and of the push (eq. 4's `W_d W_c`,
//! and the bilinear estimate the hole pixel is unprojected at) is
//! multiplied by the far factor
//!
//! `W_f = exp(-β max(0, s_j - s_edge))`, `s_j = (z_max - z_j) f / (Δ z_max)`,
//!
//! `z_max` the largest depth among the 2x2 children (pull) or the four
//! coarse neighbours (push), `Δ` their spacing in input pixels and `f` the
//! focal length in pixels: `s_j` is the depth step over the lateral
//! footprint of that spacing, the tangent of the slant a surface would need
//! to make the step. A step steeper than `s_edge` (`edge_slope`, default 4:
//! 76°) is an occlusion edge and the near side loses its weight; surfaces
//! less slanted (a floor, a wall at an angle) are filled exactly as the
//! paper does at every pyramid level. `β = 0` is the paper's filling
//! exactly. `W_f` lies in `(0, 1]` (it may underflow to 0 for a large step,
//! which is harmless: the farthest sample has `W_f = 1`, so no sum
//! vanishes). Plain `PullPush` has no intrinsics to tell an edge from a
//! slanted surface and stays the paper's Fig. 4c baseline.
//!
//! **Which holes are shadows** (`shadow_side`, [`shadow_masks`]). A
//! projector beside the camera casts its shadow on one side of a near
//! surface only: with the projector at `+x` (Kinect v1, the TUM and NYU
//! captures, `SimulateKinect`) the band lies left of the near surface, so
//! along its row a shadow pixel has the far surface as its nearest valid
//! pixel on the left and the near one on the right. The push applies `W_f`
//! only to holes in that configuration (a step steeper than `s_edge` over
//! the gap between the two, [`shadow_side`](PullPushParams::shadow_side)
//! `left`; `right` mirrors it; `both` is every hole, as before); a coarse
//! hole is a shadow when one of its children is. Other holes (dropouts on
//! a surface, a dropout that crosses the near surface's other edge) get
//! eq. 4's weights as the paper has them. The colour decides within a band
//! (`shadow_color_gate = g`): the camera sees the background in a shadow,
//! so a hole pixel whose colour lies nearer the near side's,
//! `|C_i - C_near| < g |C_i - C_far|`, belongs to the near surface and is
//! not a shadow. Nor is a hole wider than the shadow the projector can
//! cast across the step (`shadow_baseline_m = B`, [`shadow_width`]): a
//! projector `B` beside the camera shifts a point at depth `z` by
//! `f B / z` pixels, so its shadow between a near surface at `z_n` and a
//! far one at `z_f` spans `f B (1/z_n - 1/z_f)` pixels; a wider gap (a
//! dropout, a hole across the near surface's edge) gets eq. 4's weights.
//! The pull keeps `W_f` everywhere (it only decides what a coarse pixel
//! straddling an edge holds). Measured on Kinect-like holes and holes
//! punched in a real Kinect frame in `docs/accuracy-depth.md`.
//!
//! Every filled value is a convex combination of coarse values, which are
//! convex combinations of valid input depths, so it lies within their
//! `[min, max]`. Sums are accumulated in f64.

use std::sync::Arc;

use depthgraph_graph::node_params;
use depthgraph_graph::prelude::*;

use crate::kit::checks::{param_within, sane_intrinsics};
use depthgraph_graph::registry::RegistryError;
use rayon::prelude::*;

/// Which push weights to use, with what each needs.
#[derive(Debug, Clone, Copy)]
pub enum Weights<'a> {
    /// Bilinear weights only (plain pull-push).
    Bilinear,
    /// 3D-distance x color-similarity weights (eq. 2-4): the color guide
    /// and the intrinsics of the depth, both of the depth's size.
    Dual {
        /// Linear RGB guide.
        color: &'a ColorImage,
        /// Intrinsics of the depth image.
        k: &'a Intrinsics,
    },
}

depthgraph_graph::param_choice! {
    /// Which holes beside a depth edge `DualPullPush` takes as a projector's shadow
    /// (the `shadow_side` parameter).
    pub enum ShadowSide {
        /// Left of a near surface: a projector right of the camera (+x), as Kinect v1.
        Left = "left",
        /// Right of a near surface: a projector left of the camera.
        Right = "right",
        /// Every hole beside a depth edge, either side (ToF flying pixels; unknown projector).
        Both = "both",
    }
}

node_params! {
    /// Parameters of `PullPush` and `DualPullPush`.
    pub struct PullPushParams {
        /// The "tiny constant" epsilon of eq. 2 and 3 (metres and linear-RGB units).
        /// It bounds each weight by 1/epsilon; any positive value is stable.
        pub epsilon: f64 = 1e-3, ParamKind::Float { min: 1e-12, max: 10.0 };
        /// Pyramid levels below the input; 0 = auto: as many as the largest hole needs
        /// (until the coarsest level has no hole).
        pub levels: u32 = 0u32, ParamKind::Int { min: 0, max: 24 };
        /// DualPullPush: holes beside a depth edge are filled from the far side (projector
        /// shadows, flying pixels): weights of samples on the near side of a step steeper than
        /// `edge_slope` are multiplied by exp(-background * excess slope). 0 = off (the paper's
        /// eq. 2-4 exactly).
        pub background: f64 = 1.0, ParamKind::Float { min: 0.0, max: 100.0 };
        /// DualPullPush: a depth step counts as an occlusion edge when it exceeds this many times
        /// the lateral footprint of the pixel spacing (the tangent of the slant a surface would
        /// need: 4 = 76 degrees).
        pub edge_slope: f64 = 4.0, ParamKind::Float { min: 0.1, max: 1000.0 };
        /// DualPullPush: which holes the background side applies to: "left" of a near surface
        /// (a projector right of the camera, Kinect v1), "right", or "both" sides.
        pub shadow_side: ShadowSide = ShadowSide::Left, ParamKind::Choice(ShadowSide::NAMES);
        /// DualPullPush: a hole pixel whose colour is nearer the near side's than this share of
        /// its distance to the far side's belongs to the near surface, not to a shadow (0 = the
        /// colour is not asked).
        pub shadow_color_gate: f64 = 0.25, ParamKind::Float { min: 0.0, max: 1.0 };
        /// DualPullPush: the projector's distance from the camera, metres (Kinect v1: 0.075). A
        /// hole wider than the shadow such a projector casts across its depth step (f B (1/z_near
        /// - 1/z_far) pixels, plus 2) is no shadow but a dropout or a hole across the near
        /// surface, and gets the paper's weights (`shadow_side` left or right; "both" takes
        /// every hole beside an edge). 0 = any width may be a shadow.
        pub shadow_baseline_m: f64 = 0.075, ParamKind::Float { min: 0.0, max: 10.0 };
    }
}

/// Result of a fill.
#[derive(Debug, Clone, PartialEq)]
pub struct Filled {
    /// The input depth (metres) with its holes filled; measured pixels are
    /// unchanged and pixels that could not be filled stay 0.
    pub depth: DepthMap,
    /// 1 where the value was filled, 0 where it was measured or stayed a hole.
    pub filled: Mask,
    /// Levels used below the input.
    pub levels: u32,
    /// Holes left (only when `levels` was too small or no pixel was valid).
    pub holes_left: usize,
}

struct Level {
    w: usize,
    h: usize,
    depth: Vec<f64>,
    weight: Vec<f64>,
    color: Vec<[f64; 3]>,
}

/// The background bias of one pyramid step (module docs): strength `β`,
/// edge slope `s_edge` and the sample spacing over the focal length,
/// `Δ / f`.
#[derive(Debug, Clone, Copy)]
struct Far {
    beta: f64,
    edge: f64,
    spacing_over_f: f64,
}

impl Far {
    /// The far factor `W_f` of a sample at depth `z` beside the farthest
    /// at `z_max`; 1 when the bias is off or `z_max <= 0`.
    #[inline]
    fn factor(far: Option<Far>, z: f64, z_max: f64) -> f64 {
        let Some(b) = far else { return 1.0 };
        if z_max.is_nan() || z_max <= 0.0 {
            return 1.0;
        }
        // guard: z_max > 0 and spacing_over_f > 0 (checked intrinsics)
        let s = (z_max - z) / (b.spacing_over_f * z_max);
        let excess = (s - b.edge).max(0.0);
        (-b.beta * excess).exp()
    }
}

fn pull(fine: &Level, far: Option<Far>) -> Level {
    let (w, h) = (fine.w.div_ceil(2), fine.h.div_ceil(2));
    let mut out = Level {
        w,
        h,
        depth: vec![0.0; w * h],
        weight: vec![0.0; w * h],
        color: vec![[0.0; 3]; w * h],
    };
    for y in 0..h {
        for x in 0..w {
            let (mut sw, mut sb, mut sd, mut n) = (0.0, 0.0, 0.0, 0.0);
            let mut sc = [0.0; 3];
            let mut z_max = 0.0f64;
            for dy in 0..2 {
                for dx in 0..2 {
                    let (fx, fy) = (2 * x + dx, 2 * y + dy);
                    if fx < fine.w && fy < fine.h && fine.weight[fy * fine.w + fx] > 0.0 {
                        z_max = z_max.max(fine.depth[fy * fine.w + fx]);
                    }
                }
            }
            for dy in 0..2 {
                for dx in 0..2 {
                    let (fx, fy) = (2 * x + dx, 2 * y + dy);
                    if fx >= fine.w || fy >= fine.h {
                        continue;
                    }
                    let i = fy * fine.w + fx;
                    let wt = fine.weight[i];
                    sw += wt;
                    // the validity weight stays unbiased; the depth average leans far
                    let wb = wt * Far::factor(far, fine.depth[i], z_max);
                    sb += wb;
                    sd += wb * fine.depth[i];
                    for (acc, v) in sc.iter_mut().zip(fine.color[i]) {
                        *acc += v;
                    }
                    n += 1.0;
                }
            }
            let j = y * w + x;
            // guard: sw > 0 checked; n >= 1 (every coarse pixel has at least one child)
            // guard: sb > 0 whenever sw > 0 (the farthest child has W_f = 1,
            // and the weights of valid children are 1)
            if sw > 0.0 && sb > 0.0 {
                out.depth[j] = sd / sb;
                out.weight[j] = sw.min(1.0);
            }
            out.color[j] = sc.map(|v| v / n);
        }
    }
    out
}

/// Checks the parameters both backends take as they are: `background`
/// within `0..=100`, `shadow_color_gate` within `0..=1`,
/// `shadow_baseline_m` within `0..=10` and `edge_slope` within
/// `0.1..=1000`.
pub fn check_params(p: &PullPushParams) -> Result<(), NodeError> {
    param_within("background", p.background, 0.0, 100.0)?;
    param_within("shadow_color_gate", p.shadow_color_gate, 0.0, 1.0)?;
    param_within("shadow_baseline_m", p.shadow_baseline_m, 0.0, 10.0)?;
    param_within("edge_slope", p.edge_slope, 0.1, 1000.0)
}

/// Checks what [`Weights::Dual`] needs: a guide and intrinsics of the
/// depth's size, and sane intrinsics.
pub fn check_inputs(depth: &DepthMap, weights: Weights) -> Result<(), NodeError> {
    let (w, h) = depth.dims();
    if let Weights::Dual { color, k } = weights {
        if !color.same_dims(depth) {
            return Err(NodeError::input(
                "color",
                format!(
                    "is {}x{} but the depth is {w}x{h}",
                    color.width(),
                    color.height()
                ),
            ));
        }
        if (k.width, k.height) != (w, h) {
            return Err(NodeError::input(
                "intrinsics",
                format!("are for {}x{} but the depth is {w}x{h}", k.width, k.height),
            ));
        }
        sane_intrinsics("intrinsics", k)?;
    }
    Ok(())
}

/// The next coarser level of a `w x h` mask: a pixel is set when one of
/// its 2x2 children is. Returns the mask and its size.
fn any_child(fine: &[bool], w: usize, h: usize) -> (Vec<bool>, usize, usize) {
    let (cw, ch) = (w.div_ceil(2), h.div_ceil(2));
    let mut next = vec![false; cw * ch];
    for (i, _) in fine.iter().enumerate().filter(|(_, v)| **v) {
        next[(i / w / 2) * cw + (i % w) / 2] = true;
    }
    (next, cw, ch)
}

/// The number of levels below the input that [`pull_push`] builds: the
/// requested count, or (auto) until the coarsest level has no hole. A coarse
/// pixel is valid exactly when one of its children is, so this depends on
/// the hole mask alone (both backends use it).
pub fn level_count(depth: &DepthMap, p: &PullPushParams) -> u32 {
    let (mut w, mut h) = depth.dims();
    let mut valid: Vec<bool> = depth
        .as_slice()
        .iter()
        .map(|z| DepthMap::is_valid(*z))
        .collect();
    let mut used = 0u32;
    loop {
        let has_hole = valid.contains(&false);
        let done = if p.levels == 0 {
            !has_hole || (w == 1 && h == 1)
        } else {
            used >= p.levels || (w == 1 && h == 1)
        };
        if done {
            return used;
        }
        let (next, cw, ch) = any_child(&valid, w, h);
        (valid, w, h, used) = (next, cw, ch, used + 1);
    }
}

/// The holes the background side applies to (module docs), per level:
/// `levels + 1` masks, level `r` of size `ceil(w / 2^r) x ceil(h / 2^r)`,
/// true where a hole is taken as a projector's shadow. `None` when every
/// hole is (`shadow_side` both) or none is (plain weights, `background`
/// 0), and for inputs [`check_inputs`] refuses (the fills refuse them
/// first). A discrete decision both backends take from here.
pub fn shadow_masks(
    depth: &DepthMap,
    weights: Weights,
    p: &PullPushParams,
    levels: usize,
) -> Option<Vec<Vec<bool>>> {
    let Weights::Dual { color, k } = weights else {
        return None;
    };
    if p.background <= 0.0 || p.shadow_side == ShadowSide::Both {
        return None;
    }
    check_inputs(depth, weights).ok()?;
    let (w, h) = depth.dims();
    // guard: sane intrinsics (checked by the callers) have fx, fy > 0
    let f = 0.5 * (k.fx + k.fy);
    let d = depth.as_slice();
    let c = color.as_slice();
    let gate = p.shadow_color_gate;
    let cdist = |a: [f32; 3], b: [f32; 3]| {
        ((a[0] as f64 - b[0] as f64).powi(2)
            + (a[1] as f64 - b[1] as f64).powi(2)
            + (a[2] as f64 - b[2] as f64).powi(2))
        .sqrt()
    };
    let mut first = vec![false; w * h];
    first
        .par_chunks_mut(w.max(1))
        .enumerate()
        .for_each(|(y, m)| {
            let row = &d[y * w..(y + 1) * w];
            // the nearest valid pixel on the left of each hole
            let mut left: Vec<Option<usize>> = vec![None; w];
            let mut last = None;
            for (x, z) in row.iter().enumerate() {
                if DepthMap::is_valid(*z) {
                    last = Some(x);
                } else {
                    left[x] = last;
                }
            }
            let mut right = None;
            for x in (0..w).rev() {
                if DepthMap::is_valid(row[x]) {
                    right = Some(x);
                    continue;
                }
                let (Some(xl), Some(xr)) = (left[x], right) else {
                    continue;
                };
                let (zl, zr) = (row[xl] as f64, row[xr] as f64);
                // the near side: right of a left shadow, left of a right one
                let ((x_near, z_near), (x_far, z_far)) = match p.shadow_side {
                    ShadowSide::Left => ((xr, zr), (xl, zl)),
                    _ => ((xl, zl), (xr, zr)),
                };
                // the slope of the step over the gap (xr > xl; z_far > 0 valid)
                let slope = (z_far - z_near) * f / ((xr - xl) as f64 * z_far);
                if slope <= p.edge_slope {
                    continue;
                }
                if p.shadow_baseline_m > 0.0
                    && (xr - xl - 1) as f64 > shadow_width(k.fx, p.shadow_baseline_m, z_near, z_far)
                {
                    continue; // wider than any shadow of this step
                }
                let ci = c[y * w + x];
                let near = cdist(ci, c[y * w + x_near]);
                let far = cdist(ci, c[y * w + x_far]);
                // not-a-number colours never veto the shadow
                m[x] = !(gate > 0.0 && near < gate * far);
            }
        });
    let mut masks = vec![first];
    let (mut lw, mut lh) = (w, h);
    for _ in 0..levels {
        let (next, cw, ch) = match masks.last() {
            Some(fine) => any_child(fine, lw, lh),
            None => break,
        };
        masks.push(next);
        (lw, lh) = (cw, ch);
    }
    Some(masks)
}

/// The widest hole (pixels along a row) a projector at `baseline` metres
/// beside a camera of focal length `fx` pixels leaves between a near
/// surface at `z_near` and a far one at `z_far` (both > 0, valid depths):
/// the disparity step `fx B (1/z_near - 1/z_far)`, plus
/// [`SHADOW_SLACK_PX`].
pub fn shadow_width(fx: f64, baseline: f64, z_near: f64, z_far: f64) -> f64 {
    // guard: the callers pass valid (positive, finite) depths
    fx * baseline * (1.0 / z_near - 1.0 / z_far) + SHADOW_SLACK_PX
}

/// Pixels a shadow band may exceed its disparity step by: the pixel at
/// either end that straddles an edge and is lost with it (a sensor's
/// dropout at a silhouette, its disparity quantisation).
pub const SHADOW_SLACK_PX: f64 = 2.0;

/// Fills the holes of `depth` (see the module docs) with the given weights.
///
/// ```
/// use depthgraph_graph::value::{DepthMap, Intrinsics};
/// use depthgraph_nodes::depth::pull_push::{pull_push, PullPushParams, Weights};
/// let depth = DepthMap::from_vec(3, 1, vec![1.0f32, 0.0, 3.0]).unwrap();
/// let out = pull_push(&depth, &PullPushParams::default(), Weights::Bilinear).unwrap();
/// assert!(out.depth.get(1, 0) > &1.0 && out.depth.get(1, 0) < &3.0);
/// assert_eq!(out.holes_left, 0);
/// ```
pub fn pull_push(
    depth: &DepthMap,
    p: &PullPushParams,
    weights: Weights,
) -> Result<Filled, NodeError> {
    check_inputs(depth, weights)?;
    check_params(p)?;
    let (w, h) = depth.dims();
    let eps = p.epsilon;
    // the background bias of a step whose samples lie `spacing` input pixels
    // apart (dual weights only: the intrinsics tell an edge from a slope)
    let far_at = |spacing: f64| match weights {
        Weights::Dual { k, .. } if p.background > 0.0 => Some(Far {
            beta: p.background,
            edge: p.edge_slope,
            // guard: sane intrinsics (checked) have fx, fy > 0
            spacing_over_f: spacing / (0.5 * (k.fx + k.fy)),
        }),
        _ => None,
    };
    let mut levels = vec![Level {
        w,
        h,
        depth: depth
            .as_slice()
            .iter()
            .map(|z| {
                if DepthMap::is_valid(*z) {
                    *z as f64
                } else {
                    0.0
                }
            })
            .collect(),
        weight: depth
            .as_slice()
            .iter()
            .map(|z| if DepthMap::is_valid(*z) { 1.0 } else { 0.0 })
            .collect(),
        color: match weights {
            Weights::Dual { color, .. } => color
                .as_slice()
                .iter()
                .map(|c| c.map(|v| if v.is_finite() { v as f64 } else { 0.0 }))
                .collect(),
            Weights::Bilinear => vec![[0.0; 3]; w * h],
        },
    }];
    // Pull until the coarsest level has no hole (auto) or the requested count.
    loop {
        let last = &levels[levels.len() - 1];
        let has_hole = last.weight.contains(&0.0);
        let used = (levels.len() - 1) as u32;
        let done = if p.levels == 0 {
            !has_hole || (last.w == 1 && last.h == 1)
        } else {
            used >= p.levels || (last.w == 1 && last.h == 1)
        };
        if done {
            break;
        }
        // children of level r lie 2^r input pixels apart
        let next = pull(last, far_at(2f64.powi((levels.len() - 1) as i32)));
        levels.push(next);
    }
    let shadows = shadow_masks(depth, weights, p, levels.len() - 1);
    // Push: coarse to fine, filling only holes.
    for r in (0..levels.len() - 1).rev() {
        let shadow = shadows.as_ref().map(|m| &m[r]);
        let (fine_part, coarse_part) = levels.split_at_mut(r + 1);
        let fine = &mut fine_part[r];
        let coarse = &coarse_part[0];
        // intrinsics at both levels: exactly 2^-r of the input's
        let scale_f = 0.5f64.powi(r as i32);
        let scale_c = scale_f * 0.5;
        // coarse neighbours lie 2^(r+1) input pixels apart
        let far = far_at(2.0 / scale_f);
        let (fw, cw, ch) = (fine.w, coarse.w, coarse.h);
        let fine_color = &fine.color;
        let fine_weight = &fine.weight;
        // Rows in parallel tasks of at least ~16k pixels: a small level (or
        // a small image, e.g. a shadow map filled inside a parallel loop)
        // stays one task instead of paying rayon's split per row.
        let rows_per_task = (16_384 / fw.max(1)).max(1);
        let rows: Vec<(usize, Vec<(usize, f64)>)> = (0..fine.h)
            .into_par_iter()
            .with_min_len(rows_per_task)
            .map(|y| {
                let mut out = Vec::new();
                for x in 0..fw {
                    let i = y * fw + x;
                    if fine_weight[i] > 0.0 {
                        continue;
                    }
                    // the background side only for the holes taken as shadows
                    let far = if shadow.is_some_and(|m| !m[i]) {
                        None
                    } else {
                        far
                    };
                    // coarse coordinates of the fine pixel centre
                    let cxf = (x as f64 + 0.5) * 0.5 - 0.5;
                    let cyf = (y as f64 + 0.5) * 0.5 - 0.5;
                    let x0 = (cxf.floor().max(0.0) as usize).min(cw - 1);
                    let y0 = (cyf.floor().max(0.0) as usize).min(ch - 1);
                    let x1 = (x0 + 1).min(cw - 1);
                    let y1 = (y0 + 1).min(ch - 1);
                    let fx = (cxf - x0 as f64).clamp(0.0, 1.0);
                    let fy = (cyf - y0 as f64).clamp(0.0, 1.0);
                    let nbrs = [
                        (x0, y0, (1.0 - fx) * (1.0 - fy)),
                        (x1, y0, fx * (1.0 - fy)),
                        (x0, y1, (1.0 - fx) * fy),
                        (x1, y1, fx * fy),
                    ];
                    let z_max = nbrs
                        .iter()
                        .map(|&(cx, cy, _)| cy * cw + cx)
                        .filter(|j| coarse.weight[*j] > 0.0)
                        .map(|j| coarse.depth[j])
                        .fold(0.0f64, f64::max);
                    // bilinear estimate over valid coarse neighbours (far-leaning)
                    let (mut bw, mut bd) = (0.0, 0.0);
                    for &(cx, cy, wb) in &nbrs {
                        let j = cy * cw + cx;
                        if coarse.weight[j] > 0.0 {
                            let wb = wb * Far::factor(far, coarse.depth[j], z_max);
                            bw += wb;
                            bd += wb * coarse.depth[j];
                        }
                    }
                    if bw <= 0.0 {
                        // bilinear weights can all vanish on a border; fall back to plain mean
                        let (mut n, mut s) = (0.0, 0.0);
                        for &(cx, cy, _) in &nbrs {
                            let j = cy * cw + cx;
                            if coarse.weight[j] > 0.0 {
                                let f = Far::factor(far, coarse.depth[j], z_max);
                                n += f;
                                s += f * coarse.depth[j];
                            }
                        }
                        if n == 0.0 {
                            continue; // no data here: stays a hole
                        }
                        bw = n;
                        bd = s;
                    }
                    let z_est = bd / bw; // guard: bw > 0 ensured above
                    let value = match weights {
                        Weights::Bilinear => z_est,
                        Weights::Dual { k, .. } => {
                            let u = (x as f64 + 0.5, y as f64 + 0.5);
                            let xi = unproject_at(k, scale_f, u, z_est);
                            let ci = fine_color[i];
                            let (mut sw, mut sd) = (0.0f64, 0.0f64);
                            for &(cx, cy, _) in &nbrs {
                                let j = cy * cw + cx;
                                if coarse.weight[j] <= 0.0 {
                                    continue;
                                }
                                let xj = unproject_at(
                                    k,
                                    scale_c,
                                    (cx as f64 + 0.5, cy as f64 + 0.5),
                                    coarse.depth[j],
                                );
                                let wd = 1.0 / (eps + dist(xi, xj)); // eq. 2; eps > 0
                                let cj = coarse.color[j];
                                let dc = ((ci[0] - cj[0]).powi(2)
                                    + (ci[1] - cj[1]).powi(2)
                                    + (ci[2] - cj[2]).powi(2))
                                .sqrt();
                                let wc = 1.0 / (eps + dc); // eq. 3; eps > 0
                                let wf = Far::factor(far, coarse.depth[j], z_max);
                                sw += wd * wc * wf;
                                sd += wd * wc * wf * coarse.depth[j];
                            }
                            // guard: at least one valid neighbour (bw > 0) and every weight > 0;
                            // weights are at most 1/eps^2 <= 1e24, far from f64 overflow
                            if sw > 0.0 && sw.is_finite() {
                                sd / sw
                            } else {
                                z_est
                            }
                        }
                    };
                    out.push((x, value));
                }
                (y, out)
            })
            .collect();
        for (y, vals) in rows {
            for (x, v) in vals {
                let i = y * fw + x;
                fine.depth[i] = v;
                fine.weight[i] = f64::MIN_POSITIVE; // filled: valid for the next finer level
            }
        }
    }
    let l0 = &levels[0];
    let mut holes_left = 0;
    let mut filled = Image::filled(w, h, 0.0f32);
    let out: Vec<f32> = (0..w * h)
        .map(|i| {
            let z0 = depth.as_slice()[i];
            if DepthMap::is_valid(z0) {
                z0
            } else if l0.weight[i] > 0.0 {
                filled.as_mut_slice()[i] = 1.0;
                l0.depth[i] as f32
            } else {
                holes_left += 1;
                0.0
            }
        })
        .collect();
    Ok(Filled {
        depth: Image::from_vec(w, h, out)?,
        filled,
        levels: (levels.len() - 1) as u32,
        holes_left,
    })
}

#[inline]
fn unproject_at(k: &Intrinsics, scale: f64, (u, v): (f64, f64), z: f64) -> [f64; 3] {
    // intrinsics of a level: fx * scale, cx * scale (pixel centres scale exactly by halving)
    [
        (u - k.cx * scale) * z / (k.fx * scale),
        (v - k.cy * scale) * z / (k.fy * scale),
        z,
    ]
}

#[inline]
fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

depthgraph_graph::ports! {
    /// Inputs of `PullPush`.
    inputs struct PullPushIn {
        /// metres, 0 = hole
        depth: Arc<DepthMap>,
    }
}

depthgraph_graph::ports! {
    /// Inputs of `DualPullPush`.
    inputs struct DualPullPushIn {
        /// metres, 0 = hole
        depth: Arc<DepthMap>,
        /// guide, same size as the depth
        color: Arc<ColorImage>,
        /// of the depth image
        intrinsics: Intrinsics,
    }
}

depthgraph_graph::ports! {
    /// Outputs of `PullPush` and `DualPullPush`.
    outputs struct PullPushOut {
        /// holes filled; measured pixels unchanged
        depth: Arc<DepthMap>,
        /// 1 where a value was filled
        filled: Mask,
    }
}

/// The pass-through of a map with nothing to fill, or nothing to fill from
/// (both backends use it).
pub fn nothing_to_fill(depth: &Arc<DepthMap>) -> Option<Produced<PullPushOut>> {
    let holes = depth.hole_count();
    let reason = if holes == 0 {
        "no holes to fill"
    } else if holes == depth.len() {
        "no valid depth to fill from"
    } else {
        return None;
    };
    let out = PullPushOut {
        depth: DepthMap::canonical_holes(depth),
        filled: Mask::filled(depth.width(), depth.height(), 0.0),
    };
    Some(Produced::passthrough(out, reason))
}

fn filled(r: Filled) -> Produced<PullPushOut> {
    PullPushOut {
        depth: Arc::new(r.depth),
        filled: r.filled,
    }
    .into()
}

fn eval_plain(
    _: &EvalCtx,
    i: PullPushIn,
    p: &PullPushParams,
) -> Result<Produced<PullPushOut>, NodeError> {
    if let Some(out) = nothing_to_fill(&i.depth) {
        return Ok(out);
    }
    Ok(filled(pull_push(&i.depth, p, Weights::Bilinear)?))
}

fn eval_dual(
    _: &EvalCtx,
    i: DualPullPushIn,
    p: &PullPushParams,
) -> Result<Produced<PullPushOut>, NodeError> {
    if let Some(out) = nothing_to_fill(&i.depth) {
        return Ok(out);
    }
    let w = Weights::Dual {
        color: &i.color,
        k: &i.intrinsics,
    };
    Ok(filled(pull_push(&i.depth, p, w)?))
}

/// Registers `PullPush` and `DualPullPush`.
pub fn register(reg: &mut Registry) -> Result<(), RegistryError> {
    reg.register(PortedNode::new(
        "PullPush",
        1,
        "Fills depth holes by pull-push with bilinear weights (the baseline of 3d-editing Fig. 4c).",
        eval_plain,
    ))?;
    reg.register(PortedNode::new(
        "DualPullPush",
        4,
        "Fills depth holes by pull-push with 3D-distance x color-similarity weights (3d-editing eq. 2-4).",
        eval_dual,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn level_count_is_the_number_of_levels_pull_push_builds() {
        let mut rng = crate::kit::rng::SplitMix64(5);
        for (w, h, holes, levels) in [
            (37, 23, 0.3, 0),
            (64, 64, 0.97, 0),
            (9, 1, 0.5, 0),
            (40, 30, 0.5, 2),
            (40, 30, 0.0, 3),
        ] {
            let d = DepthMap::from_fn(w, h, |_, _| if rng.next_f64() < holes { 0.0 } else { 1.5 });
            let p = PullPushParams {
                levels,
                ..Default::default()
            };
            let r = pull_push(&d, &p, Weights::Bilinear).unwrap();
            assert_eq!(
                level_count(&d, &p),
                r.levels,
                "{w}x{h} holes {holes} levels {levels}"
            );
        }
    }

    use crate::test_support::square_camera as k;

    fn both(depth: &DepthMap, color: &ColorImage, p: &PullPushParams) -> [Filled; 2] {
        let kk = k(depth.width(), depth.height());
        [
            pull_push(depth, p, Weights::Bilinear).unwrap(),
            pull_push(depth, p, Weights::Dual { color, k: &kk }).unwrap(),
        ]
    }

    #[test]
    fn valid_pixels_unchanged_and_every_hole_filled() {
        let d = Image::from_fn(37, 23, |x, y| {
            if (8..20).contains(&x) && (5..15).contains(&y) {
                0.0
            } else {
                1.0 + 0.01 * x as f32 + 0.02 * y as f32
            }
        });
        let c = Image::from_fn(37, 23, |x, _| [x as f32 / 37.0, 0.5, 0.2]);
        for r in both(&d, &c, &PullPushParams::default()) {
            assert_eq!(r.holes_left, 0);
            for (a, b) in d.as_slice().iter().zip(r.depth.as_slice()) {
                if *a > 0.0 {
                    assert_eq!(a, b);
                }
            }
            assert_eq!(
                r.filled.as_slice().iter().filter(|v| **v == 1.0).count(),
                12 * 10
            );
            // a hole in a plane is filled close to the plane
            let want = 1.0 + 0.01 * 14.0 + 0.02 * 10.0;
            assert!(
                (r.depth.get(14, 10) - want).abs() < 0.05,
                "{}",
                r.depth.get(14, 10)
            );
        }
    }

    #[test]
    fn dual_weights_keep_a_depth_edge_that_bilinear_blurs() {
        // Left half near (1 m, dark), right half far (3 m, bright); a hole band across the edge.
        let (w, h) = (64, 32);
        let near = |x: usize| x < 32;
        let gt = DepthMap::from_fn(w, h, |x, _| if near(x) { 1.0f32 } else { 3.0 });
        let c = Image::from_fn(w, h, |x, _| {
            if near(x) {
                [0.1f32, 0.1, 0.1]
            } else {
                [0.9, 0.8, 0.7]
            }
        });
        let d = Image::from_fn(w, h, |x, y| {
            if (24..40).contains(&x) && (8..24).contains(&y) {
                0.0
            } else {
                *gt.get(x, y)
            }
        });
        // the paper's weights (a hole across the edge that is not a shadow)
        let paper = PullPushParams {
            background: 0.0,
            ..Default::default()
        };
        let [plain, dual] = both(&d, &c, &paper);
        let err = |r: &Filled| {
            let mut s = 0.0f64;
            let mut n = 0;
            for i in 0..w * h {
                if d.as_slice()[i] == 0.0 {
                    s += ((r.depth.as_slice()[i] - gt.as_slice()[i]) as f64).powi(2);
                    n += 1;
                }
            }
            (s / n as f64).sqrt()
        };
        let (ep, ed) = (err(&plain), err(&dual));
        assert!(ed < 0.5 * ep, "dual {ed} vs plain {ep}");
        assert!(ed < 0.25, "dual rmse {ed}");
    }

    /// RMSE inside the holes of `d` against `gt`.
    fn hole_rmse(d: &DepthMap, gt: &DepthMap, r: &Filled) -> f64 {
        let (mut s, mut n) = (0.0f64, 0usize);
        for ((a, g), z) in d
            .as_slice()
            .iter()
            .zip(gt.as_slice())
            .zip(r.depth.as_slice())
        {
            if *a == 0.0 {
                s += ((z - g) as f64).powi(2);
                n += 1;
            }
        }
        (s / n.max(1) as f64).sqrt()
    }

    #[test]
    fn a_projector_shadow_is_filled_from_the_background() {
        // A box at 1.2 m before a wall at 3 m; a structured-light projector to
        // the right of the camera leaves a shadow band on the wall left of the
        // box (background by construction), and a dropout hole inside the box.
        let (w, h) = (96, 64);
        let in_box = |x: usize, y: usize| (40..72).contains(&x) && (16..48).contains(&y);
        let gt = DepthMap::from_fn(w, h, |x, y| if in_box(x, y) { 1.2f32 } else { 3.0 });
        // a white box on a white wall: the colour guide cannot tell them apart
        let c = ColorImage::filled(w, h, [0.8, 0.8, 0.8]);
        let shadow = |x: usize, y: usize| (30..40).contains(&x) && (16..48).contains(&y);
        let dropout = |x: usize, y: usize| (52..60).contains(&x) && (28..36).contains(&y);
        let d = Image::from_fn(w, h, |x, y| {
            if shadow(x, y) || dropout(x, y) {
                0.0
            } else {
                *gt.get(x, y)
            }
        });
        // a 640-pixel Kinect's field of view (f = 525 px) cropped to 96x64
        let kk = Intrinsics {
            fx: 525.0,
            fy: 525.0,
            ..k(w, h)
        };
        let fill = |background: f64| {
            let p = PullPushParams {
                background,
                ..Default::default()
            };
            pull_push(&d, &p, Weights::Dual { color: &c, k: &kk }).unwrap()
        };
        let (on, off) = (fill(1.0), fill(0.0));
        let (e_on, e_off) = (hole_rmse(&d, &gt, &on), hole_rmse(&d, &gt, &off));
        assert!(e_on < 0.25 * e_off, "background on {e_on} vs off {e_off}");
        assert!(e_on < 0.1, "{e_on} m");
        // the dropout inside the box stays on the box
        assert!(
            (on.depth.get(56, 32) - 1.2).abs() < 0.01,
            "{}",
            on.depth.get(56, 32)
        );
        // plain PullPush has no intrinsics and ignores the bias
        let p = PullPushParams::default();
        let q = PullPushParams {
            background: 0.0,
            ..p.clone()
        };
        assert_eq!(
            pull_push(&d, &p, Weights::Bilinear).unwrap(),
            pull_push(&d, &q, Weights::Bilinear).unwrap()
        );
    }

    /// A red box at 1.2 m before a white wall at 3 m, seen by a Kinect-like
    /// camera; `hole(x)` says which columns of the box's rows are lost.
    /// Returns the fill's mean absolute error over the lost box pixels and
    /// over the lost wall pixels.
    fn box_fill_errors(hole: impl Fn(usize) -> bool, p: &PullPushParams) -> (f64, f64) {
        let (w, h) = (96, 64);
        let in_box = |x: usize, y: usize| (40..72).contains(&x) && (16..48).contains(&y);
        let gt = DepthMap::from_fn(w, h, |x, y| if in_box(x, y) { 1.2f32 } else { 3.0 });
        let c = ColorImage::from_fn(w, h, |x, y| {
            if in_box(x, y) {
                [0.6, 0.05, 0.05]
            } else {
                [0.8, 0.8, 0.8]
            }
        });
        let lost = |x: usize, y: usize| hole(x) && (16..48).contains(&y);
        let d = Image::from_fn(w, h, |x, y| if lost(x, y) { 0.0 } else { *gt.get(x, y) });
        let kk = Intrinsics {
            fx: 525.0,
            fy: 525.0,
            ..k(w, h)
        };
        let out = pull_push(&d, p, Weights::Dual { color: &c, k: &kk }).unwrap();
        let (mut e, mut n) = ([0.0f64; 2], [0usize; 2]);
        for y in 0..h {
            for x in (0..w).filter(|x| lost(*x, y)) {
                let side = usize::from(!in_box(x, y));
                e[side] += (*out.depth.get(x, y) as f64 - *gt.get(x, y) as f64).abs();
                n[side] += 1;
            }
        }
        (e[0] / n[0].max(1) as f64, e[1] / n[1].max(1) as f64)
    }

    #[test]
    fn a_hole_right_of_a_near_surface_is_no_left_shadow() {
        // a dropout across the box's right edge: 6 box columns, 8 wall columns
        let hole = |x: usize| (66..80).contains(&x);
        let left = PullPushParams::default();
        let both = PullPushParams {
            shadow_side: ShadowSide::Both,
            ..Default::default()
        };
        let (box_left, _) = box_fill_errors(hole, &left);
        let (box_both, _) = box_fill_errors(hole, &both);
        // taken as a shadow (both), the box's pixels get the wall; as a
        // dropout (left), the colour keeps them on the box
        assert!(box_left < 0.1, "box part {box_left} m");
        assert!(box_both > 0.5, "box part with both sides {box_both} m");
    }

    #[test]
    fn the_colour_keeps_the_near_surface_out_of_a_shadow_band() {
        // a band left of the box that also takes its first 6 columns: the
        // shadow part (white, the wall) is filled from the far side, the
        // red part belongs to the box
        let hole = |x: usize| (30..46).contains(&x);
        let gated = PullPushParams::default();
        let blind = PullPushParams {
            shadow_color_gate: 0.0,
            ..Default::default()
        };
        let (box_gated, wall_gated) = box_fill_errors(hole, &gated);
        let (box_blind, wall_blind) = box_fill_errors(hole, &blind);
        assert!(
            wall_gated < 0.1 && wall_blind < 0.1,
            "{wall_gated} {wall_blind}"
        );
        assert!(
            box_gated < 0.1,
            "box part with the colour gate {box_gated} m"
        );
        assert!(box_blind > 0.5, "box part without it {box_blind} m");
    }

    #[test]
    fn a_gap_wider_than_the_projectors_shadow_is_no_shadow() {
        // far 3 m, a gap of `gap` pixels, near 2.5 m: a projector 7.5 cm
        // beside a 500-pixel camera shifts the two by 12.5 and 15 pixels,
        // a shadow of 2.5 pixels (+2 of slack: 4.5)
        let marked = |gap: usize, baseline: f64| {
            let w = 4 + gap + 4;
            let d = DepthMap::from_fn(w, 1, |x, _| match x {
                _ if x < 4 => 3.0f32,
                _ if x < 4 + gap => 0.0,
                _ => 2.5,
            });
            let c = ColorImage::filled(w, 1, [0.5; 3]);
            let kk = Intrinsics {
                fx: 500.0,
                fy: 500.0,
                ..k(w, 1)
            };
            let p = PullPushParams {
                shadow_baseline_m: baseline,
                ..Default::default()
            };
            let m = shadow_masks(&d, Weights::Dual { color: &c, k: &kk }, &p, 0).unwrap();
            (4..4 + gap).filter(|x| m[0][*x]).count()
        };
        assert!((shadow_width(500.0, 0.075, 2.5, 3.0) - 4.5).abs() < 1e-12);
        assert_eq!(marked(4, 0.075), 4);
        assert_eq!(marked(5, 0.075), 0);
        assert_eq!(marked(8, 0.075), 0);
        // a wider baseline casts a wider shadow; 0 lets any width be one
        assert_eq!(marked(8, 0.2), 8);
        assert_eq!(marked(8, 0.0), 8);
        let bad = PullPushParams {
            shadow_baseline_m: -1.0,
            ..Default::default()
        };
        let err = check_params(&bad).unwrap_err().to_string();
        assert!(err.contains("shadow_baseline_m"), "{err}");
    }

    #[test]
    fn shadow_masks_mark_only_the_left_band_and_pull_down() {
        let (w, h) = (16, 2);
        // far 3 m, a gap at 4..8, near 1 m at 8..12, a gap at 12..14, far again
        let z = |x: usize| match x {
            4..8 | 12..14 => 0.0,
            8..12 => 1.0f32,
            _ => 3.0,
        };
        let d = DepthMap::from_fn(w, h, |x, _| z(x));
        let c = ColorImage::filled(w, h, [0.5, 0.5, 0.5]);
        let kk = Intrinsics {
            fx: 500.0,
            fy: 500.0,
            ..k(w, h)
        };
        let wts = Weights::Dual { color: &c, k: &kk };
        let p = PullPushParams::default();
        let m = shadow_masks(&d, wts, &p, 2).unwrap();
        let row: Vec<bool> = (0..w).map(|x| m[0][x]).collect();
        let expect: Vec<bool> = (0..w).map(|x| (4..8).contains(&x)).collect();
        assert_eq!(row, expect);
        // level 1: the pairs 2, 3 hold band pixels
        assert_eq!(m[1].len(), 8);
        assert_eq!(
            (0..8).map(|x| m[1][x]).collect::<Vec<_>>(),
            vec![false, false, true, true, false, false, false, false]
        );
        assert_eq!(m[2].len(), 4);
        // the mirror marks the other gap; both and plain weights need no mask
        let r = PullPushParams {
            shadow_side: ShadowSide::Right,
            ..Default::default()
        };
        let mr = shadow_masks(&d, wts, &r, 0).unwrap();
        assert_eq!(
            (0..w).filter(|x| mr[0][*x]).collect::<Vec<_>>(),
            vec![12, 13]
        );
        let b = PullPushParams {
            shadow_side: ShadowSide::Both,
            ..Default::default()
        };
        assert!(shadow_masks(&d, wts, &b, 2).is_none());
        assert!(shadow_masks(&d, Weights::Bilinear, &p, 2).is_none());
    }

    #[test]
    fn bounded_by_valid_range_for_a_1000x_jump_and_tiny_epsilon() {
        let d = Image::from_fn(16, 16, |x, y| {
            if (x + y) % 3 == 0 {
                0.0
            } else if x < 8 {
                0.001
            } else {
                1000.0
            }
        });
        let c = Image::filled(16, 16, [0.3f32; 3]); // constant color: every W_c = 1/eps
        for eps in [1e-12, 1e-3, 10.0] {
            for r in both(
                &d,
                &c,
                &PullPushParams {
                    epsilon: eps,
                    levels: 0,
                    ..Default::default()
                },
            ) {
                for v in r.depth.as_slice() {
                    assert!(
                        v.is_finite() && *v >= 0.001 && *v <= 1000.0,
                        "{v} (eps {eps})"
                    );
                }
            }
        }
    }

    #[test]
    fn hard_inputs() {
        let c1 = Image::filled(1, 1, [0.0f32; 3]);
        // 1x1 valid, 1x1 hole
        for z in [2.0f32, 0.0] {
            let d = Image::filled(1, 1, z);
            for r in both(&d, &c1, &PullPushParams::default()) {
                assert_eq!(*r.depth.get(0, 0), z);
            }
        }
        // 1xN with one valid pixel: everything becomes that value
        let d = Image::from_fn(9, 1, |x, _| if x == 6 { 4.5 } else { 0.0 });
        let c = Image::filled(9, 1, [0.2f32; 3]);
        for r in both(&d, &c, &PullPushParams::default()) {
            assert!(
                r.depth.as_slice().iter().all(|v| *v == 4.5),
                "{:?}",
                r.depth.as_slice()
            );
        }
        // NaN, inf, negative depths are holes; NaN colors are tolerated
        let d = Image::from_vec(4, 1, vec![f32::NAN, 1.0, f32::INFINITY, -2.0]).unwrap();
        let c = Image::from_vec(4, 1, vec![[f32::NAN; 3], [0.1; 3], [0.2; 3], [0.3; 3]]).unwrap();
        for r in both(&d, &c, &PullPushParams::default()) {
            assert!(r.depth.as_slice().iter().all(|v| *v == 1.0));
        }
        // all holes: nothing to fill from
        let d = Image::filled(5, 4, 0.0f32);
        let c = Image::filled(5, 4, [0.0f32; 3]);
        for r in both(&d, &c, &PullPushParams::default()) {
            assert_eq!(r.holes_left, 20);
        }
    }

    #[test]
    fn too_few_levels_leave_large_holes_and_say_so() {
        let d = Image::from_fn(32, 32, |x, _| if x < 2 { 1.0 } else { 0.0 });
        let r = pull_push(
            &d,
            &PullPushParams {
                levels: 1,
                ..Default::default()
            },
            Weights::Bilinear,
        )
        .unwrap();
        assert!(r.holes_left > 0);
        assert_eq!(r.levels, 1);
        let auto = pull_push(&d, &PullPushParams::default(), Weights::Bilinear).unwrap();
        assert_eq!(auto.holes_left, 0);
    }

    #[test]
    fn mismatched_inputs_are_named() {
        let d = Image::filled(4, 4, 1.0f32);
        let e = pull_push(
            &d,
            &PullPushParams::default(),
            Weights::Dual {
                color: &Image::filled(2, 2, [0.0; 3]),
                k: &k(4, 4),
            },
        )
        .unwrap_err();
        assert!(e.to_string().contains("color"), "{e}");
        let e = pull_push(
            &d,
            &PullPushParams::default(),
            Weights::Dual {
                color: &Image::filled(4, 4, [0.0; 3]),
                k: &k(8, 8),
            },
        )
        .unwrap_err();
        assert!(e.to_string().contains("intrinsics"), "{e}");
    }

    #[test]
    fn thread_count_does_not_change_bits() {
        let d = Image::from_fn(50, 40, |x, y| {
            if (x * 7 + y * 3) % 5 == 0 {
                0.0
            } else {
                1.0 + ((x * y) % 13) as f32 * 0.1
            }
        });
        let c = Image::from_fn(50, 40, |x, y| {
            [(x % 7) as f32 / 7.0, (y % 5) as f32 / 5.0, 0.5]
        });
        let run = |n| {
            crate::test_support::with_threads(n, || {
                pull_push(
                    &d,
                    &PullPushParams::default(),
                    Weights::Dual {
                        color: &c,
                        k: &k(50, 40),
                    },
                )
                .unwrap()
                .depth
            })
        };
        assert_eq!(run(1), run(3));
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]
        #[test]
        fn fills_are_finite_bounded_and_keep_measurements(
            w in 1usize..24, h in 1usize..24,
            seed in any::<u64>(),
            hole_rate in 0.0f64..1.0,
            eps in prop_oneof![Just(1e-12), Just(1e-3), Just(1.0)],
        ) {
            let mut s = seed;
            let mut next = || { s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407); (s >> 11) as f64 / (1u64 << 53) as f64 };
            let d = Image::from_fn(w, h, |_, _| if next() < hole_rate { 0.0 } else { (0.01 + 100.0 * next()) as f32 });
            let c = Image::from_fn(w, h, |_, _| [next() as f32, next() as f32, next() as f32]);
            let valid: Vec<f32> = d.as_slice().iter().copied().filter(|z| *z > 0.0).collect();
            let (lo, hi) = valid.iter().fold((f32::INFINITY, 0.0f32), |(a, b), v| (a.min(*v), b.max(*v)));
            let sides = [(0.0, ShadowSide::Left, 0.25, 0.075), (1.0, ShadowSide::Left, 0.25, 0.075), (100.0, ShadowSide::Left, 1.0, 0.0), (1.0, ShadowSide::Right, 0.0, 10.0), (100.0, ShadowSide::Both, 0.25, 0.075)];
            for r in sides.iter().flat_map(|(b, side, gate, base)| both(&d, &c, &PullPushParams { epsilon: eps, levels: 0, background: *b, edge_slope: 0.5, shadow_side: *side, shadow_color_gate: *gate, shadow_baseline_m: *base })) {
                for (a, b) in d.as_slice().iter().zip(r.depth.as_slice()) {
                    prop_assert!(b.is_finite());
                    if *a > 0.0 { prop_assert_eq!(a, b); }
                    else if !valid.is_empty() { prop_assert!(*b >= lo && *b <= hi, "{} outside [{}, {}]", b, lo, hi); }
                }
                if !valid.is_empty() { prop_assert_eq!(r.holes_left, 0); }
            }
        }
    }
}
