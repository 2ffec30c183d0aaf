//! Joint upsampling of low-resolution depth on the color grid (eq. 4).

use crate::kit::checks::fits_intrinsics;
use depthgraph_graph::prelude::*;

use super::common::*;
use super::inpaint::*;
use super::inputs::*;
use super::job::PassJob;
use super::params::*;
use super::pass::*;
use super::prune::*;
use super::upsample_pass::*;

// ---------------------------------------------------------------------------
// Upsampling
// ---------------------------------------------------------------------------

/// For each pixel `a` of an axis of `n_from` pixels, the pixel of the other
/// camera's axis (`n_to` pixels) that the ray through `a`'s centre falls in:
/// `u' = (a + 0.5 - c) / f * f' + c'`, `None` outside.
pub(super) fn axis_map(
    n_from: usize,
    f: f64,
    c: f64,
    f_to: f64,
    c_to: f64,
    n_to: usize,
) -> Vec<usize> {
    (0..n_from)
        .map(|a| {
            // Guard: f > 0 (intrinsics checked sane).
            let u = ((a as f64 + 0.5 - c) / f * f_to + c_to).floor();
            if u.is_finite() && u >= 0.0 && u < n_to as f64 {
                u as usize
            } else {
                NO_SAMPLE
            }
        })
        .collect()
}

/// Joint upsampling of low-resolution depth guided by high-resolution color
/// (eq. 4), for a depth camera co-located with the color camera (depth
/// already transformed into the color camera's frame). The high-resolution
/// camera is `low_k.scaled_to(color size)`; see [`nlmeans_upsample_with`]
/// for other intrinsics.
///
/// 1. With `p.prune`, outliers of the low-resolution depth are pruned
///    ([`prune_outliers`]; the paper prunes before the transformation).
/// 2. Each low-resolution sample `j_low` is placed on the high-resolution
///    pixel `j` its centre's ray falls in; each high-resolution pixel `i`
///    corresponds to the low-resolution pixel `i_low` its ray falls in.
/// 3. `v(i) = sum_j [(1 - alpha) w(i_low, j_low) + alpha w^(u)(i, j)]
///    zeta(j_low) v(j_low) / Z*` over the placed samples `j` of the
///    high-resolution search window (eq. 4 with the confidence factor of
///    eq. 5): `w^(u)` compares high-resolution color patches
///    (`patch_radius`), `w` low-resolution depth patches
///    (`low_patch_radius`) with the discontinuity factor (eq. 3).
/// 4. Pixels left without an estimate are filled by up to `p.iterations`
///    inpainting iterations ([`nlmeans_inpaint`]'s eq. 5 scheme).
///
/// The confidence is the similarity-weighted mean confidence of the samples
/// in the window (low-resolution holes count as 0).
///
/// ```
/// use depthgraph_nodes::depth::nlmeans::{nlmeans_upsample, NLMeansUpsampleParams};
/// use depthgraph_graph::value::{ColorImage, DepthMap, Intrinsics};
/// let low = DepthMap::from_fn(4, 4, |x, _| if x < 2 { 1.0 } else { 2.0 });
/// let k = Intrinsics { fx: 4.0, fy: 4.0, cx: 2.0, cy: 2.0, width: 4, height: 4 };
/// // The color edge is at the depth edge: x = 8 of 16.
/// let color = ColorImage::from_fn(16, 16, |x, _| if x < 8 { [0.1; 3] } else { [0.8; 3] });
/// let (d, c) = nlmeans_upsample(&low, &k, &color, &NLMeansUpsampleParams::default()).unwrap();
/// assert_eq!(d.dims(), (16, 16));
/// assert!((*d.get(7, 5) - 1.0).abs() < 0.01 && (*d.get(8, 5) - 2.0).abs() < 0.01);
/// assert!(*c.get(7, 5) > 0.9);
/// ```
pub fn nlmeans_upsample(
    low_depth: &DepthMap,
    low_k: &Intrinsics,
    guide_color_high: &ColorImage,
    p: &NLMeansUpsampleParams,
) -> Result<(DepthMap, Confidence), NodeError> {
    nlmeans_upsample_with(low_depth, low_k, guide_color_high, None, p, |_| Ok(()))
        .map(|(d, c, _)| (d, c))
}

/// [`nlmeans_upsample`] for a color camera with its own intrinsics
/// `color_k` (same optical centre and orientation as the depth camera;
/// `None`: `low_k` scaled to the color size), calling `on_progress` now and
/// then (cancellation when it returns an error). Also returns the
/// high-resolution intrinsics.
///
/// Errors: `low_k` (port `intrinsics`) or `color_k` (port
/// `color_intrinsics`) not sane or not of their image's size; parameters
/// out of range.
pub fn nlmeans_upsample_with(
    low_depth: &DepthMap,
    low_k: &Intrinsics,
    guide_color_high: &ColorImage,
    color_k: Option<&Intrinsics>,
    p: &NLMeansUpsampleParams,
    on_progress: impl FnMut(f32) -> Result<(), NodeError>,
) -> Result<(DepthMap, Confidence, Intrinsics), NodeError> {
    nlmeans_upsample_on(
        low_depth,
        low_k,
        guide_color_high,
        color_k,
        p,
        on_progress,
        &mut CpuPass,
    )
}

/// [`nlmeans_upsample_with`] with its passes run by `runner` (the first
/// one through [`PassRunner::run_upsample`], the inpainting's through
/// [`PassRunner::run`]): the placement of the samples, the targets and the
/// stopping rule stay here, so every backend decides alike.
pub fn nlmeans_upsample_on(
    low_depth: &DepthMap,
    low_k: &Intrinsics,
    guide_color_high: &ColorImage,
    color_k: Option<&Intrinsics>,
    p: &NLMeansUpsampleParams,
    mut on_progress: impl FnMut(f32) -> Result<(), NodeError>,
    runner: &mut dyn PassRunner,
) -> Result<(DepthMap, Confidence, Intrinsics), NodeError> {
    let core = Core::new(p.search_radius, p.patch_radius, p.h_color, p.h_depth)?;
    if p.low_patch_radius > MAX_PATCH_RADIUS {
        return Err(NodeError::param(
            "low_patch_radius",
            format!("must be at most {MAX_PATCH_RADIUS}"),
        ));
    }
    if !(0.0..=1.0).contains(&p.alpha) {
        return Err(NodeError::param("alpha", "must be in [0, 1]"));
    }
    fits_intrinsics("intrinsics", low_k, "depth map", low_depth.dims())?;
    let (w, h) = guide_color_high.dims();
    let high_k = match color_k {
        Some(k) => {
            fits_intrinsics("color_intrinsics", k, "color image", (w, h))?;
            *k
        }
        None => low_k.scaled_to(w, h),
    };
    let (lw, lh) = low_depth.dims();
    let (lz, lc) = if p.prune {
        let (d, c) = prune_outliers(low_depth, None, &p.prune_params())?;
        (d.into_vec(), c.into_vec())
    } else {
        sanitize(low_depth, None)
    };
    let mut z = vec![0.0f32; w * h];
    let mut c = vec![0.0f32; w * h];
    if w == 0 || h == 0 || lw == 0 || lh == 0 {
        return Ok((image(w, h, z)?, image(w, h, c)?, high_k));
    }
    // Place the samples (a higher confidence wins a shared pixel).
    let to_hi_col = axis_map(lw, low_k.fx, low_k.cx, high_k.fx, high_k.cx, w);
    let to_hi_row = axis_map(lh, low_k.fy, low_k.cy, high_k.fy, high_k.cy, h);
    let mut sample_at = vec![NO_SAMPLE; w * h];
    for (ly, &hy) in to_hi_row.iter().enumerate() {
        for (lx, &hx) in to_hi_col.iter().enumerate() {
            if hx == NO_SAMPLE || hy == NO_SAMPLE {
                continue;
            }
            let (j, s) = (hy * w + hx, ly * lw + lx);
            let old = sample_at[j];
            if old == NO_SAMPLE || lc[s] > lc[old] {
                sample_at[j] = s;
            }
        }
    }
    let lo_col = axis_map(w, high_k.fx, high_k.cx, low_k.fx, low_k.cx, lw);
    let lo_row = axis_map(h, high_k.fy, high_k.cy, low_k.fy, low_k.cy, lh);
    let guide = guide_features(guide_color_high);
    let pk = PatchKernel::new(core.patch);
    let targets = vec![true; w * h];
    let job = UpsampleJob {
        pass: PassJob::new(
            (w, h),
            &guide,
            (&[], &[]),
            &targets,
            core,
            &pk,
            (None, None),
        ),
        low: (lw, lh),
        lz: &lz,
        lc: &lc,
        sample_at: &sample_at,
        lo_col: &lo_col,
        lo_row: &lo_row,
        low_patch: p.low_patch_radius,
        alpha: p.alpha,
    };
    let share = if p.iterations > 0 { 0.5 } else { 1.0 };
    let out = runner.run_upsample(&job, &mut |f| on_progress(f * share))?;
    if out.len() != w * h {
        return Err(NodeError::Internal(format!(
            "the upsampling pass returned {} results for {} pixels",
            out.len(),
            w * h
        )));
    }
    for (i, r) in out.into_iter().enumerate() {
        if let Some((v, conf)) = r {
            z[i] = v;
            c[i] = conf;
        }
    }
    if p.iterations > 0 && c.iter().any(|c| *c <= 0.0) && core.search > 0 {
        inpaint_state(
            &mut z,
            &mut c,
            &guide,
            w,
            h,
            core,
            p.iterations,
            false,
            None,
            &mut |f| on_progress(0.5 + 0.5 * f),
            runner,
        )?;
    }
    Ok((image(w, h, z)?, image(w, h, c)?, high_k))
}
