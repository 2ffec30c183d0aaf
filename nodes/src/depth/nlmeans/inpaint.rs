//! Iterative inpainting with confidence propagation (eq. 5).

use crate::kit::checks::same_size;
use depthgraph_graph::prelude::*;

use super::common::*;
use super::inputs::*;
use super::params::*;
use super::pass::*;

// ---------------------------------------------------------------------------
// Inpainting
// ---------------------------------------------------------------------------

/// Holes that have a source (confidence > 0) within `r` pixels (Chebyshev),
/// from a summed-area table of the sources.
pub(super) fn reachable_holes(z: &[f32], c: &[f32], w: usize, h: usize, r: usize) -> Vec<bool> {
    let mut sat = vec![0u32; (w + 1) * (h + 1)];
    for y in 0..h {
        let mut row = 0u32;
        for x in 0..w {
            row += (c[y * w + x] > 0.0) as u32;
            sat[(y + 1) * (w + 1) + x + 1] = sat[y * (w + 1) + x + 1] + row;
        }
    }
    (0..w * h)
        .map(|i| {
            if z[i] > 0.0 {
                return false;
            }
            let (x, y) = (i % w, i / w);
            let (x0, y0) = (x.saturating_sub(r), y.saturating_sub(r));
            let (x1, y1) = ((x + r + 1).min(w), (y + r + 1).min(h));
            let s = sat[y1 * (w + 1) + x1] + sat[y0 * (w + 1) + x0]
                - sat[y0 * (w + 1) + x1]
                - sat[y1 * (w + 1) + x0];
            s > 0
        })
        .collect()
}

/// The iterations of eq. 5 on `(z, c)` in place (Jacobi: each iteration
/// reads the previous state). Returns the number of iterations run.
#[allow(clippy::too_many_arguments)]
pub(super) fn inpaint_state(
    z: &mut Vec<f32>,
    c: &mut Vec<f32>,
    guide: &[[f32; 3]],
    w: usize,
    h: usize,
    core: Core,
    iterations: usize,
    far_prior: bool,
    progress: &mut dyn FnMut(f32) -> Result<(), NodeError>,
) -> Result<usize, NodeError> {
    let z_ref = z
        .iter()
        .zip(c.iter())
        .filter(|(_, c)| **c > 0.0)
        .fold(0.0f64, |m, (z, _)| m.max(*z as f64));
    // Guard: only with a positive reference depth.
    let far = (far_prior && z_ref > 0.0).then(|| 1.0 / z_ref);
    let mut done = 0;
    for it in 0..iterations {
        let targets = reachable_holes(z, c, w, h, core.search);
        if !targets.iter().any(|t| *t) {
            break;
        }
        let (mut nz, mut nc) = (z.clone(), c.clone());
        let mut filled = 0usize;
        {
            let pass = Pass {
                w,
                h,
                guide,
                depth: Some((z, c)),
                core,
            };
            let kernel = DepthKernel {
                z,
                c,
                inv_hd2: core.inv_hd2,
                far,
            };
            // Guard: iterations >= 1 inside the loop.
            let scale = 1.0 / iterations as f32;
            let mut sub = |f: f32| progress((it as f32 + f) * scale);
            run_pass(&pass, &targets, &kernel, &mut sub, |i, acc| {
                if let Some((v, conf)) = acc.finish() {
                    nz[i] = v;
                    nc[i] = conf;
                    filled += 1;
                }
            })?;
        }
        *z = nz;
        *c = nc;
        done = it + 1;
        if filled == 0 {
            break;
        }
    }
    Ok(done)
}

/// Iterative NL-means inpainting with confidence propagation (eq. 5): each
/// iteration estimates every hole that has known pixels within
/// `search_radius` from them (eq. 1 with the weights of [`nlmeans_filter`],
/// the depth patch term counting only known pixels), and gives it the
/// confidence `sum_j s(i, j) zeta(j) / sum_j s(i, j)` (the normalisation
/// `Z_i` relative to a fully known window), so confidence decays into the
/// hole and later iterations weight the reliable border more. Iterations
/// stop when no hole is left, an iteration fills nothing, or after
/// `iterations`; holes larger than a patch fill from the outside in.
///
/// With `far_prior` each weight is multiplied by `(z_j / z_max)^2`, `z_max`
/// the largest known depth, favouring the background (Sec. 2.3: holes
/// opened by a change of viewpoint belong to the background).
///
/// Valid input pixels are never changed (nor their confidence). Holes that
/// cannot be reached stay 0 with confidence 0 (e.g. an input without any
/// valid pixel). Filled values lie within the range of the valid inputs.
///
/// ```
/// use depthgraph_nodes::depth::nlmeans::{nlmeans_inpaint, NLMeansInpaintParams};
/// use depthgraph_graph::value::{ColorImage, DepthMap};
/// let depth = DepthMap::from_fn(20, 3, |x, _| if x < 4 { 1.0 } else if x < 16 { 0.0 } else { 3.0 });
/// let color = ColorImage::filled(20, 3, [0.5; 3]);
/// let (d, c) = nlmeans_inpaint(&depth, None, &color, &NLMeansInpaintParams::default()).unwrap();
/// assert_eq!(d.hole_count(), 0);
/// assert!(d.as_slice().iter().all(|z| (1.0..=3.0).contains(z)));
/// assert!(*c.get(10, 1) > 0.0 && *c.get(10, 1) < 1.0);
/// assert_eq!(*c.get(0, 0), 1.0);
/// ```
pub fn nlmeans_inpaint(
    depth: &DepthMap,
    confidence: Option<&Confidence>,
    guide_color: &ColorImage,
    p: &NLMeansInpaintParams,
) -> Result<(DepthMap, Confidence), NodeError> {
    nlmeans_inpaint_with(depth, confidence, guide_color, p, |_| Ok(()))
}

/// [`nlmeans_inpaint`] that calls `on_progress(fraction)` now and then and
/// stops with its error when it returns one (cancellation).
pub fn nlmeans_inpaint_with(
    depth: &DepthMap,
    confidence: Option<&Confidence>,
    guide_color: &ColorImage,
    p: &NLMeansInpaintParams,
    mut on_progress: impl FnMut(f32) -> Result<(), NodeError>,
) -> Result<(DepthMap, Confidence), NodeError> {
    let core = Core::new(p.search_radius, p.patch_radius, p.h_color, p.h_depth)?;
    if core.search == 0 {
        return Err(NodeError::param("search_radius", "must be at least 1"));
    }
    same_size(
        "color",
        "a guide image",
        guide_color.dims(),
        "the depth map",
        depth.dims(),
    )?;
    check_confidence(confidence, depth)?;
    let (w, h) = depth.dims();
    let (mut z, mut c) = sanitize(depth, confidence);
    let guide = guide_features(guide_color);
    inpaint_state(
        &mut z,
        &mut c,
        &guide,
        w,
        h,
        core,
        p.iterations,
        p.far_prior,
        &mut on_progress,
    )?;
    Ok((image(w, h, z)?, image(w, h, c)?))
}
