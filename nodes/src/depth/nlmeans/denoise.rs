//! NL-means depth denoising: pruning, then the pass.

use crate::kit::checks::same_size;
use depthgraph_graph::prelude::*;

use super::common::*;
use super::inpaint::{CpuPass, PassRunner, checked_run};
use super::inputs::*;
use super::job::PassJob;
use super::params::*;
use super::pass::*;
use super::prune::*;

// ---------------------------------------------------------------------------
// Filter
// ---------------------------------------------------------------------------

/// NL-means denoising of depth guided by color (eq. 1-3, 5): each valid
/// pixel becomes the weighted mean of the valid pixels of its search window,
/// with weight
///
/// `w(i, j) = zeta(j) * xi_ij * exp(-(D_color(i, j) + D_depth(i, j)))`
///
/// where `D_color` is the mean over the patch of the squared guide
/// differences / `h_color^2`, `D_depth` the mean of
/// `zeta zeta (v(i+k) - v(j+k))^2 / h_depth^2` over patch pixels where both
/// depths are known (eq. 5), and `xi_ij = exp(-(v(i) - v(j))^2 / h_depth^2)`
/// the discontinuity factor (eq. 3) at the centres (see the module docs).
/// Patch distances use box sums per search offset, so the cost is
/// `O(pixels x search window)`.
///
/// Holes stay holes (use [`nlmeans_inpaint`](crate::depth::nlmeans::nlmeans_inpaint) to fill them). The output
/// confidence is the similarity-weighted mean input confidence of the window
/// (1 inside clean data). Weights are normalised as they are accumulated
/// (module docs), so they never all underflow; a pixel without any source
/// in its window (only possible when its own confidence is 0) keeps its
/// input value with confidence 0. `confidence` defaults to 1 at valid
/// pixels.
///
/// Errors: `color` or `confidence` of another size than `depth`; parameters
/// out of range.
///
/// ```
/// use depthgraph_nodes::depth::nlmeans::{nlmeans_filter, NLMeansDepthParams};
/// use depthgraph_graph::value::{ColorImage, DepthMap};
/// let depth = DepthMap::from_vec(4, 1, vec![2.0, 2.02, 1.98, 0.0]).unwrap();
/// let color = ColorImage::filled(4, 1, [0.5; 3]);
/// let (d, c) = nlmeans_filter(&depth, None, &color, &NLMeansDepthParams::default()).unwrap();
/// let v = *d.get(1, 0);
/// assert!(v > 1.98 && v < 2.02); // pulled towards its neighbours
/// assert_eq!((*d.get(3, 0), *c.get(3, 0)), (0.0, 0.0)); // holes stay holes
/// ```
pub fn nlmeans_filter(
    depth: &DepthMap,
    confidence: Option<&Confidence>,
    guide_color: &ColorImage,
    p: &NLMeansDepthParams,
) -> Result<(DepthMap, Confidence), NodeError> {
    nlmeans_filter_with(depth, confidence, guide_color, p, |_| Ok(()))
}

/// [`nlmeans_filter`] that calls `on_progress(fraction)` now and then and
/// stops with its error when it returns one (cancellation).
pub fn nlmeans_filter_with(
    depth: &DepthMap,
    confidence: Option<&Confidence>,
    guide_color: &ColorImage,
    p: &NLMeansDepthParams,
    on_progress: impl FnMut(f32) -> Result<(), NodeError>,
) -> Result<(DepthMap, Confidence), NodeError> {
    filter_on(
        depth,
        confidence,
        guide_color,
        p,
        on_progress,
        &mut CpuPass::new(),
    )
}

fn filter_on(
    depth: &DepthMap,
    confidence: Option<&Confidence>,
    guide_color: &ColorImage,
    p: &NLMeansDepthParams,
    mut on_progress: impl FnMut(f32) -> Result<(), NodeError>,
    runner: &mut dyn PassRunner,
) -> Result<(DepthMap, Confidence), NodeError> {
    if p.search_radius == 0 {
        // a window of the pixel alone: the input back, unfiltered
        return Err(NodeError::param(
            "search_radius",
            "must be at least 1 (0 compares each pixel only with itself)",
        ));
    }
    let core = Core::new(p.search_radius, p.patch_radius, p.h_color, p.h_depth)?;
    same_size(
        "color",
        "a guide image",
        guide_color.dims(),
        "the depth map",
        depth.dims(),
    )?;
    check_confidence(confidence, depth)?;
    let (w, h) = depth.dims();
    let (z, c) = sanitize(depth, confidence);
    let guide = guide_features(guide_color);
    let targets: Vec<bool> = z.iter().map(|z| *z > 0.0).collect();
    let mut out_z = z.clone();
    let mut out_c = vec![0.0f32; w * h];
    let pk = PatchKernel::new(core.patch);
    // targets: the pixels with depth, each a source itself (a target of
    // confidence 0 whose weight sum falls below the f32 rows' `exact_below`
    // is run again in f64)
    let job = PassJob::new(
        (w, h),
        &guide,
        (&z, &c),
        (&targets, true),
        core,
        &pk,
        (None, None),
    );
    for (i, r) in checked_run(runner, &job, &mut on_progress)?
        .into_iter()
        .enumerate()
    {
        // Fallback without any source: input value, confidence 0.
        if let (true, Some((v, conf))) = (targets[i], r) {
            out_z[i] = v;
            out_c[i] = conf;
        }
    }
    Ok((image(w, h, out_z)?, image(w, h, out_c)?))
}

/// Denoising as the `NLMeansDepth` node does it: [`prune_outliers`] (when
/// `p.prune`) then [`nlmeans_filter`] with the pruned confidence.
///
/// ```
/// use depthgraph_nodes::depth::nlmeans::{nlmeans_denoise, NLMeansDepthParams};
/// use depthgraph_graph::value::{ColorImage, DepthMap};
/// let mut depth = DepthMap::filled(9, 9, 1.5);
/// *depth.get_mut(4, 4) = 4.0;
/// let color = ColorImage::filled(9, 9, [0.2; 3]);
/// let (d, _) = nlmeans_denoise(&depth, None, &color, &NLMeansDepthParams::default()).unwrap();
/// assert_eq!(*d.get(4, 4), 0.0); // the spike is pruned
/// assert_eq!(*d.get(0, 0), 1.5); // constant depth passes exactly
/// ```
pub fn nlmeans_denoise(
    depth: &DepthMap,
    confidence: Option<&Confidence>,
    guide_color: &ColorImage,
    p: &NLMeansDepthParams,
) -> Result<(DepthMap, Confidence), NodeError> {
    nlmeans_denoise_with(depth, confidence, guide_color, p, |_| Ok(()))
}

/// [`nlmeans_denoise`] with progress reports and cancellation.
pub fn nlmeans_denoise_with(
    depth: &DepthMap,
    confidence: Option<&Confidence>,
    guide_color: &ColorImage,
    p: &NLMeansDepthParams,
    on_progress: impl FnMut(f32) -> Result<(), NodeError>,
) -> Result<(DepthMap, Confidence), NodeError> {
    nlmeans_denoise_on(
        depth,
        confidence,
        guide_color,
        p,
        on_progress,
        &mut CpuPass::new(),
    )
}

/// [`nlmeans_denoise_with`] with its pass run by `runner` (another
/// backend); the checks and the pruning stay this function's.
pub fn nlmeans_denoise_on(
    depth: &DepthMap,
    confidence: Option<&Confidence>,
    guide_color: &ColorImage,
    p: &NLMeansDepthParams,
    on_progress: impl FnMut(f32) -> Result<(), NodeError>,
    runner: &mut dyn PassRunner,
) -> Result<(DepthMap, Confidence), NodeError> {
    if !p.prune {
        return filter_on(depth, confidence, guide_color, p, on_progress, runner);
    }
    // Check the filter's inputs before the pruning's work.
    Core::new(p.search_radius, p.patch_radius, p.h_color, p.h_depth)?;
    same_size(
        "color",
        "a guide image",
        guide_color.dims(),
        "the depth map",
        depth.dims(),
    )?;
    let (d, c) = prune_outliers(depth, confidence, &p.prune_params())?;
    filter_on(&d, Some(&c), guide_color, p, on_progress, runner)
}
