//! Joint upsampling of low-resolution depth on the color grid (eq. 4).

use crate::kit::checks::{fits_intrinsics, param_within};
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
///    (`low_patch_radius`) with the discontinuity factor (eq. 3). Beyond
///    the paper, each weight falls off with the distance from `i` to `j`
///    as `exp(-|i - j|^2 / (2 (spatial_sigma f)^2))` for a factor `f`
///    (0: none, eq. 4 as published), and with it the window is at least
///    `2 f` pixels in radius
///    (`window`): eq. 4's uniform window of 11x11 holds 2 to 3 samples
///    across each axis at x4, where any look-alike patch across an edge
///    counts as much as the pixel's own neighbours.
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
        &mut CpuPass::new(),
    )
}

/// [`nlmeans_upsample_with`] with its passes run by `runner` (the first
/// one through [`PassRunner::run_upsample`], the inpainting's through
/// [`PassRunner::run`]): the placement of the samples, the targets and the
/// stopping rule stay here, so every backend decides alike.
///
/// With a colour image more than `p.max_step_factor` times the depth's
/// size, the upsampling runs in equal steps ([`scale_steps`]): each step is
/// the scheme above from the previous step's result, guided by the colour
/// averaged down to that step's size ([`area_downsample`]); the pruning
/// runs on the input only. The last step's confidence is returned.
pub fn nlmeans_upsample_on(
    low_depth: &DepthMap,
    low_k: &Intrinsics,
    guide_color_high: &ColorImage,
    color_k: Option<&Intrinsics>,
    p: &NLMeansUpsampleParams,
    mut on_progress: impl FnMut(f32) -> Result<(), NodeError>,
    runner: &mut dyn PassRunner,
) -> Result<(DepthMap, Confidence, Intrinsics), NodeError> {
    let (w, h) = guide_color_high.dims();
    param_within("max_step_factor", p.max_step_factor, 0.0, 64.0)?;
    param_within("spatial_sigma", p.spatial_sigma, 0.0, 100.0)?;
    let (lw, lh) = low_depth.dims();
    let steps = if p.max_step_factor > 0.0 {
        scale_steps((lw, lh), (w, h), p.max_step_factor)
    } else {
        vec![(w, h)]
    };
    if steps.len() <= 1 || w == 0 || h == 0 || lw == 0 || lh == 0 {
        return upsample_step(
            (low_depth, None),
            low_k,
            guide_color_high,
            color_k,
            p,
            &mut on_progress,
            runner,
        );
    }
    // The checks of the full-size call first, so a bad input fails before any work.
    Core::new(p.search_radius, p.patch_radius, p.h_color, p.h_depth)?;
    fits_intrinsics("intrinsics", low_k, "depth map", low_depth.dims())?;
    let high_k = match color_k {
        Some(k) => {
            fits_intrinsics("color_intrinsics", k, "color image", (w, h))?;
            *k
        }
        None => low_k.scaled_to(w, h),
    };
    let n = steps.len();
    let mut depth = low_depth.clone();
    let mut k_now = *low_k;
    let mut conf: Option<Confidence> = None;
    for (s, &(sw, sh)) in steps.iter().enumerate() {
        let last = s + 1 == n;
        let small;
        let guide = if last {
            guide_color_high
        } else {
            small = area_downsample(guide_color_high, sw, sh);
            &small
        };
        let step_k = high_k.scaled_to(sw, sh);
        let sp = NLMeansUpsampleParams {
            prune: p.prune && s == 0,
            ..p.clone()
        };
        runner.new_guide();
        // Guard: n >= 2 here.
        let (lo, span) = (s as f32 / n as f32, 1.0 / n as f32);
        let (d, c, _) = upsample_step(
            (&depth, conf.as_ref()),
            &k_now,
            guide,
            Some(&step_k),
            &sp,
            &mut |f| on_progress(lo + span * f),
            runner,
        )?;
        depth = d;
        conf = Some(c);
        k_now = step_k;
    }
    let conf = conf.ok_or_else(|| NodeError::Internal("no upsampling step ran".into()))?;
    Ok((depth, conf, high_k))
}

/// The sizes of the steps of a multi-scale upsampling from `low` to
/// `high` with at most `max_step` per step: for the largest axis ratio `r`,
/// `n = ceil(log(r) / log(max_step))` steps, at most 16 (a few per cent over
/// a power of `max_step` still counts as that power: sizes are rounded),
/// the step `k` of `n` at `high / r_axis^((n - k) / n)` on each axis with
/// its own ratio (rounded, at least 1), the last at `high` exactly.
/// `max_step <= 1` or a ratio up to `max_step` is one step.
pub fn scale_steps(
    low: (usize, usize),
    high: (usize, usize),
    max_step: f64,
) -> Vec<(usize, usize)> {
    let ratio = |h: usize, l: usize| h as f64 / l.max(1) as f64;
    let (rx, ry) = (ratio(high.0, low.0), ratio(high.1, low.1));
    let r = rx.max(ry);
    if !(max_step > 1.0 && r > max_step * 1.025) {
        return vec![high];
    }
    // guard: max_step > 1, so its logarithm is positive
    let n = ((r / 1.025).ln() / max_step.ln()).ceil().clamp(1.0, 16.0) as i32;
    (1..=n)
        .map(|k| {
            let t = (n - k) as f64 / n as f64;
            // each axis by its own ratio (1 where the depth is not smaller)
            let side =
                |v: usize, ra: f64| ((v as f64 / ra.max(1.0).powf(t)).round() as usize).max(1);
            (side(high.0, rx), side(high.1, ry))
        })
        .collect()
}

/// `color` averaged down to `w` x `h`: each output pixel is the mean of
/// the input pixels whose centre falls in it (linear RGB, so the mean is
/// the light the larger pixel would have gathered). Non-finite samples
/// are left out; a pixel with none is 0.
pub fn area_downsample(color: &ColorImage, w: usize, h: usize) -> ColorImage {
    let (cw, ch) = color.dims();
    let mut sum = vec![[0.0f64; 3]; w * h];
    let mut count = vec![0u32; w * h];
    if cw > 0 && ch > 0 {
        for y in 0..ch {
            // the output pixel the input pixel's centre falls in
            let oy = ((2 * y + 1) * h / (2 * ch)).min(h.saturating_sub(1));
            for x in 0..cw {
                let ox = ((2 * x + 1) * w / (2 * cw)).min(w.saturating_sub(1));
                let c = color.get(x, y);
                if c.iter().all(|v| v.is_finite()) {
                    let o = oy * w + ox;
                    for k in 0..3 {
                        sum[o][k] += c[k] as f64;
                    }
                    count[o] += 1;
                }
            }
        }
    }
    ColorImage::from_fn(w, h, |x, y| {
        let o = y * w + x;
        // Guard: count > 0, else 0.
        if count[o] == 0 {
            [0.0; 3]
        } else {
            sum[o].map(|v| (v / count[o] as f64) as f32)
        }
    })
}

/// Largest spatial falloff `1 / (2 sigma^2)`, pixels^-2: a `spatial_sigma`
/// so small that the falloff would overflow weighs every candidate but the
/// nearest by `exp(-1e6)` = 0 (in f64 and f32 alike), and the products
/// with distances (`dx^2 + dy^2 <= 2 * 30^2`) stay finite in f32.
const MAX_SPATIAL: f64 = 1e6;

/// The search radius of one step's pass and its spatial falloff
/// `1 / (2 sigma^2)` in high-resolution pixels^-2 (0: none), for a step
/// from `low_k` to `high_k`: the factor `f` is the larger ratio of their
/// focal lengths, the radius `max(search_radius, ceil(2 f))` (at most
/// [`MAX_SEARCH_RADIUS`]: 4 to 5 samples across each axis of the window,
/// fewer beyond f = 15), sigma `spatial_sigma * f`, the falloff at most
/// [`MAX_SPATIAL`]. Without the falloff (`spatial_sigma` 0) eq. 4 as
/// published: `search_radius` (a wider uniform window would weigh far
/// samples as much as near ones).
///
/// Errors: `spatial_sigma` outside `0..=100`.
fn window(
    p: &NLMeansUpsampleParams,
    low_k: &Intrinsics,
    high_k: &Intrinsics,
) -> Result<(usize, f64), NodeError> {
    param_within("spatial_sigma", p.spatial_sigma, 0.0, 100.0)?;
    if p.spatial_sigma == 0.0 {
        // eq. 4 as published: a uniform window of `search_radius`
        return Ok((p.search_radius, 0.0));
    }
    // Guard: both intrinsics passed `fits_intrinsics` (focal lengths > 0
    // and finite); a ratio below 1 (a "step" that shrinks) counts as 1, and
    // one that overflows (focal lengths 1e300 apart) as the largest window.
    let f = (high_k.fx / low_k.fx).max(high_k.fy / low_k.fy).max(1.0);
    let widened = (2.0 * f).ceil().min(MAX_SEARCH_RADIUS as f64) as usize;
    let search = p.search_radius.max(widened).min(MAX_SEARCH_RADIUS);
    let sigma = p.spatial_sigma * f;
    // Guard: sigma > 0 (spatial_sigma > 0, f >= 1); a sigma so small that
    // the quotient overflows is capped, one so large that it rounds to 0
    // is no falloff.
    let spatial = (1.0 / (2.0 * sigma * sigma)).min(MAX_SPATIAL);
    Ok((search, spatial))
}

/// One step of [`nlmeans_upsample_on`]: eq. 4 at the full factor.
/// `low` is the depth and, for a later step, the previous step's
/// confidence (so holes an earlier step inpainted keep their lower weight).
fn upsample_step(
    (low_depth, low_conf): (&DepthMap, Option<&Confidence>),
    low_k: &Intrinsics,
    guide_color_high: &ColorImage,
    color_k: Option<&Intrinsics>,
    p: &NLMeansUpsampleParams,
    on_progress: &mut dyn FnMut(f32) -> Result<(), NodeError>,
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
    check_confidence(low_conf, low_depth)?;
    let (lz, lc) = if p.prune {
        let (d, c) = prune_outliers(low_depth, low_conf, &p.prune_params())?;
        (d.into_vec(), c.into_vec())
    } else {
        sanitize(low_depth, low_conf)
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
    let (search, spatial) = window(p, low_k, &high_k)?;
    let job = UpsampleJob {
        pass: PassJob::new(
            (w, h),
            &guide,
            (&[], &[]),
            (&targets, false),
            Core { search, ..core },
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
        spatial,
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
