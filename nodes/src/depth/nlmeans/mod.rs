//! Non-local means (NL-means) processing of depth guided by a color image:
//! outlier pruning, denoising, joint upsampling and inpainting, after
//! "Realistic depth blur for images with range data", Sec. 2.2 (eq. 1-5).
//!
//! Every estimate is the NL-means weighted average of eq. 1,
//! `v'(i) = sum_j w(i, j) v(j) / Z_i` over a search window `W_i` of
//! `(2 search_radius + 1)^2` pixels, with weights from patch similarity
//! (eq. 2). Here:
//!
//! - **Patch distance.** The squared differences of the color guide (each
//!   linear channel mapped to `sqrt(c / (1 + c))`, bounded in `[0, 1)`, so
//!   HDR highlights do not dominate), divided by `h_color^2`, plus where
//!   depth is known the confidence-weighted squared depth differences
//!   `zeta(p) zeta(q) (v(p) - v(q))^2 / h_depth^2` (eq. 5), averaged over the
//!   `(2 patch_radius + 1)^2` patch. The paper's Gaussian patch kernel `G_a`
//!   is approximated by the average of three nested **box** kernels (radii
//!   0, `ceil(r/2)` and `r`; centre-weighted like a Gaussian) so that, for
//!   each search offset, the distances of all pixels are box sums of one
//!   per-pixel image of squared differences (running sums, i.e. integral
//!   images along rows and columns): cost `O(pixels x search window)`,
//!   independent of the patch size.
//! - **Discontinuity factor xi (eq. 3).** In the paper `xi_ik` weights each
//!   patch pixel by its depth similarity to the patch centre, a kernel that
//!   varies per pixel and so cannot be box-summed. It is applied at the
//!   centres instead: the weight is multiplied by
//!   `xi_ij = exp(-(v(i) - v(j))^2 / h_depth^2)` where both centres have
//!   depth, which serves the same purpose (no averaging across depth edges).
//! - **Confidence (eq. 5).** The weight is multiplied by the confidence
//!   `zeta(j)` of the source pixel, and the output confidence of a pixel is
//!   the similarity-weighted mean confidence of its window,
//!   `sum_j s(i, j) zeta(j) / sum_j s(i, j)` with `s` the weight without the
//!   `zeta(j)` factor: the paper's normalisation `Z_i` divided by its value
//!   for a fully confident window, so it lies in `[0, 1]`, is exactly 1
//!   inside clean data and decays into holes.
//! - **No underflow.** Weights `exp(-distance)` are accumulated relative to
//!   the largest one seen so far (rescaling the sums when a larger one
//!   arrives, as log-sum-exp does), so they never all underflow, however
//!   small `h` is: an estimate exists whenever a source pixel does. The
//!   denoising and inpainting passes get there faster: their sums are kept
//!   relative to exponent 0 (the target itself, always the most similar
//!   candidate) a whole row at a time with a vectorised `exp`, and only the
//!   targets whose every source is near underflow are run again with the
//!   running maximum (`depth_rows`; the results agree to the last place of
//!   f32, tested).
//!
//! Functions:
//! - [`prune_outliers`]: the paper's outlier model, a normal around the
//!   values predicted by the neighbours mixed with a uniform over the depth
//!   range; likely outliers become holes.
//! - [`nlmeans_filter`]: NL-means denoising of the valid pixels.
//! - [`nlmeans_upsample`]: joint upsampling of low-resolution depth guided by
//!   high-resolution color (eq. 4, blend `alpha`).
//! - [`nlmeans_inpaint`]: iterative confidence-propagating inpainting
//!   (eq. 5) with an optional far-depth prior (Sec. 2.3).
//!
//! Sums are accumulated in f64, each pixel's in a fixed order (search
//! offsets in raster order), and the work is split into bands of rows of a
//! fixed size, so results are bit-identical whatever the number of threads.
//! Every estimate is clamped to the range of the values it averages, so it
//! lies within `[min, max]` of the valid inputs and constant depth passes
//! through exactly.

mod common;
mod denoise;
mod depth_rows;
mod inpaint;
mod inputs;
mod job;
mod params;
mod pass;
mod prune;
mod upsample;
mod upsample_pass;

pub use common::{MAX_PATCH_RADIUS, MAX_SEARCH_RADIUS};
pub use denoise::*;
pub use inpaint::*;
use inputs::*;
pub use job::*;
pub use params::*;
pub use prune::*;
pub use upsample::*;
pub use upsample_pass::*;

use crate::kit::checks::same_size;
use depthgraph_graph::prelude::*;
use depthgraph_graph::registry::RegistryError;
use std::sync::Arc;

use common::*;

// ---------------------------------------------------------------------------
// Nodes
// ---------------------------------------------------------------------------

depthgraph_graph::ports! {
    /// Inputs of `NLMeansDepth` and `NLMeansInpaint`.
    inputs struct NLMeansIn {
        /// depth in metres, 0 = hole
        depth: Arc<DepthMap>,
        /// linear color guide of the depth map's size
        color: Arc<ColorImage>,
        /// per-pixel confidence zeta in [0, 1]; default 1 at valid pixels
        confidence: Option<Arc<Confidence>>,
    }
}

depthgraph_graph::ports! {
    /// Outputs of `NLMeansDepth` and `NLMeansInpaint`.
    outputs struct NLMeansOut {
        /// depth in metres, 0 = hole
        depth: Arc<DepthMap>,
        /// confidence of each pixel, 0 at holes
        confidence: Arc<Confidence>,
    }
}

depthgraph_graph::ports! {
    /// Inputs of `NLMeansUpsample`.
    inputs struct UpsampleIn {
        /// low-resolution depth in metres, in the color camera's frame
        depth: Arc<DepthMap>,
        /// intrinsics of the low-resolution depth
        intrinsics: Intrinsics,
        /// high-resolution linear color guide
        color: Arc<ColorImage>,
        /// intrinsics of the color image; default: the depth intrinsics scaled to its size
        color_intrinsics: Option<Intrinsics>,
    }
}

depthgraph_graph::ports! {
    /// Outputs of `NLMeansUpsample`.
    outputs struct UpsampleOut {
        /// depth at the color resolution, 0 = hole
        depth: DepthMap,
        /// confidence of each pixel, 0 at holes
        confidence: Confidence,
        /// intrinsics of the high-resolution depth
        intrinsics: Intrinsics,
    }
}

fn eval_depth(
    ctx: &EvalCtx,
    i: NLMeansIn,
    p: &NLMeansDepthParams,
) -> Result<Produced<NLMeansOut>, NodeError> {
    let conf = i.confidence.as_deref();
    let (d, c) = nlmeans_denoise_with(&i.depth, conf, &i.color, p, |f| {
        ctx.progress(f);
        ctx.check_cancelled()
    })?;
    Ok(NLMeansOut {
        depth: Arc::new(d),
        confidence: Arc::new(c),
    }
    .into())
}

fn eval_upsample(
    ctx: &EvalCtx,
    i: UpsampleIn,
    p: &NLMeansUpsampleParams,
) -> Result<Produced<UpsampleOut>, NodeError> {
    let color_k = i.color_intrinsics.as_ref();
    let (depth, confidence, intrinsics) =
        nlmeans_upsample_with(&i.depth, &i.intrinsics, &i.color, color_k, p, |f| {
            ctx.progress(f);
            ctx.check_cancelled()
        })?;
    Ok(UpsampleOut {
        depth,
        confidence,
        intrinsics,
    }
    .into())
}

/// `NLMeansInpaint`'s pass-through of a map without holes (both backends).
pub fn inpaint_passthrough(i: &NLMeansIn) -> Result<Option<Produced<NLMeansOut>>, NodeError> {
    let depth = &i.depth;
    if depth.hole_count() == 0 {
        // Same checks as a real run, so a wrong wiring is not hidden.
        same_size(
            "color",
            "a guide image",
            i.color.dims(),
            "the depth map",
            depth.dims(),
        )?;
        check_confidence(i.confidence.as_deref(), depth)?;
        // the input's confidence as it is when it is one (in [0, 1]),
        // else sanitised as a real run reads it (NaN as 0, clamped)
        let confidence = match &i.confidence {
            Some(c) if c.as_slice().iter().all(|v| (0.0..=1.0).contains(v)) => Arc::clone(c),
            c => Arc::new(image(
                depth.width(),
                depth.height(),
                sanitize(depth, c.as_deref()).1,
            )?),
        };
        let out = NLMeansOut {
            depth: Arc::clone(depth),
            confidence,
        };
        return Ok(Some(Produced::passthrough(out, "no holes to fill")));
    }
    Ok(None)
}

fn eval_inpaint(
    ctx: &EvalCtx,
    i: NLMeansIn,
    p: &NLMeansInpaintParams,
) -> Result<Produced<NLMeansOut>, NodeError> {
    if let Some(out) = inpaint_passthrough(&i)? {
        return Ok(out);
    }
    let depth = &i.depth;
    let (d, c) = nlmeans_inpaint_with(depth, i.confidence.as_deref(), &i.color, p, |f| {
        ctx.progress(f);
        ctx.check_cancelled()
    })?;
    Ok(NLMeansOut {
        depth: Arc::new(d),
        confidence: Arc::new(c),
    }
    .into())
}

/// Registers `NLMeansDepth`, `NLMeansUpsample` and `NLMeansInpaint`.
pub fn register(reg: &mut Registry) -> Result<(), RegistryError> {
    reg.register(PortedNode::new(
        "NLMeansDepth",
        2,
        "NL-means depth denoising guided by color, with outlier pruning (depth blur Sec. 2.2, eq. 1-3).\n\
         Outliers (spikes, flying pixels) are pruned with a normal + uniform mixture model and become holes; \
         the remaining depth is averaged over pixels with similar color and depth patches. Holes stay holes.",
        eval_depth,
    ))?;
    reg.register(PortedNode::new(
        "NLMeansUpsample",
        4,
        "Joint NL-means upsampling of low-resolution depth guided by high-resolution color (depth blur eq. 4).\n\
         Low-resolution samples are placed on the color grid and averaged with weights blending low-resolution \
         depth similarity and high-resolution color similarity (alpha); remaining holes are inpainted (eq. 5). \
         Weights fall off with distance (spatial_sigma low-resolution pixels) and the window is at least twice \
         the factor. Factors above max_step_factor (4) run in equal steps, each guided by the colour at its size.",
        eval_upsample,
    ))?;
    reg.register(PortedNode::new(
        "NLMeansInpaint",
        3,
        "Iterative NL-means depth inpainting with confidence propagation (depth blur eq. 5).\n\
         Fills holes from the outside in, weighting known pixels by patch similarity and confidence; \
         optional far-depth prior for disocclusions. Valid pixels are unchanged.",
        eval_inpaint,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kit::rng::SplitMix64;
    use crate::sim::sensor::{KinectParams, ToFParams, simulate_kinect, simulate_tof};
    use crate::sim::synthetic::{RenderOptions, RenderOutput, Scene, render};

    fn tabletop(w: usize, h: usize) -> RenderOutput {
        render(
            &Scene::preset("tabletop", w, h).unwrap(),
            &RenderOptions::default(),
        )
    }

    /// Root mean square error of `a` against `truth` over `mask`, and the count.
    fn rmse(a: &DepthMap, truth: &DepthMap, mask: impl Fn(usize) -> bool) -> (f64, usize) {
        let (mut s, mut n) = (0.0f64, 0usize);
        for (i, (x, t)) in a.as_slice().iter().zip(truth.as_slice()).enumerate() {
            if mask(i) {
                let d = *x as f64 - *t as f64;
                s += d * d;
                n += 1;
            }
        }
        ((s / n.max(1) as f64).sqrt(), n)
    }

    /// Baseline: each hole takes the nearest valid pixel along its row
    /// (the left one on ties), or along its column when the row has none.
    fn row_nearest_fill(d: &DepthMap) -> DepthMap {
        let (w, h) = d.dims();
        let near = |vals: &[f32], i: usize| -> Option<f32> {
            (0..vals.len()).find_map(|k| {
                let l = i
                    .checked_sub(k)
                    .map(|j| vals[j])
                    .filter(|z| DepthMap::is_valid(*z));
                let r = vals.get(i + k).copied().filter(|z| DepthMap::is_valid(*z));
                l.or(r)
            })
        };
        DepthMap::from_fn(w, h, |x, y| {
            let z = *d.get(x, y);
            if DepthMap::is_valid(z) {
                return z;
            }
            let col: Vec<f32> = (0..h).map(|yy| *d.get(x, yy)).collect();
            near(d.row(y), x).or_else(|| near(&col, y)).unwrap_or(0.0)
        })
    }

    /// Upsamples `low` to `w` x `h` by the pixel its centre falls in.
    fn nearest_up(low: &DepthMap, w: usize, h: usize) -> DepthMap {
        let (lw, lh) = low.dims();
        DepthMap::from_fn(w, h, |x, y| *low.get(x * lw / w, y * lh / h))
    }

    /// Bilinear upsampling between low-resolution pixel centres (clamped at
    /// the border; the tests' low-resolution maps have no holes).
    fn bilinear_up(low: &DepthMap, w: usize, h: usize) -> DepthMap {
        let (lw, lh) = low.dims();
        DepthMap::from_fn(w, h, |x, y| {
            let u = ((x as f64 + 0.5) * lw as f64 / w as f64 - 0.5).clamp(0.0, (lw - 1) as f64);
            let v = ((y as f64 + 0.5) * lh as f64 / h as f64 - 0.5).clamp(0.0, (lh - 1) as f64);
            let (x0, y0) = (u.floor() as usize, v.floor() as usize);
            let (x1, y1) = ((x0 + 1).min(lw - 1), (y0 + 1).min(lh - 1));
            let (fx, fy) = (u - x0 as f64, v - y0 as f64);
            let g = |x: usize, y: usize| *low.get(x, y) as f64;
            let top = g(x0, y0) * (1.0 - fx) + g(x1, y0) * fx;
            let bottom = g(x0, y1) * (1.0 - fx) + g(x1, y1) * fx;
            (top * (1.0 - fy) + bottom * fy) as f32
        })
    }

    /// Pixels within `r` of a depth discontinuity of `truth` (a 3x3 depth
    /// range above 5% of the depth).
    fn edge_mask(truth: &DepthMap, r: usize) -> Vec<bool> {
        let (w, h) = truth.dims();
        let jump = |x: usize, y: usize| {
            let z = *truth.get(x, y);
            let (mut lo, mut hi) = (z, z);
            for yy in y.saturating_sub(1)..(y + 2).min(h) {
                for xx in x.saturating_sub(1)..(x + 2).min(w) {
                    lo = lo.min(*truth.get(xx, yy));
                    hi = hi.max(*truth.get(xx, yy));
                }
            }
            hi - lo > 0.05 * z
        };
        let jumps: Vec<bool> = (0..w * h).map(|i| jump(i % w, i / w)).collect();
        (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                (y.saturating_sub(r)..(y + r + 1).min(h)).any(|yy| {
                    (x.saturating_sub(r)..(x + r + 1).min(w)).any(|xx| jumps[yy * w + xx])
                })
            })
            .collect()
    }

    /// `truth` with Gaussian noise of standard deviation `sigma_m + rel * z`.
    fn noisy(truth: &DepthMap, sigma_m: f64, rel: f64, seed: u64) -> DepthMap {
        let w = truth.width();
        let mut out = truth.clone();
        for (i, z) in out.as_mut_slice().iter_mut().enumerate() {
            let mut rng = SplitMix64::for_pixel(seed, 77, (i % w) as u64, (i / w) as u64);
            *z = (*z as f64 + (sigma_m + rel * *z as f64) * rng.gaussian()) as f32;
        }
        out
    }

    /// `truth` with a fraction `rate` of pixels replaced by uniform depths in
    /// `[lo, hi]`; returns the map and the spike mask.
    fn spiked(truth: &DepthMap, rate: f64, lo: f64, hi: f64, seed: u64) -> (DepthMap, Vec<bool>) {
        let w = truth.width();
        let mut out = truth.clone();
        let mut mask = vec![false; truth.len()];
        for (i, z) in out.as_mut_slice().iter_mut().enumerate() {
            let mut rng = SplitMix64::for_pixel(seed, 78, (i % w) as u64, (i / w) as u64);
            if rng.uniform() < rate {
                *z = (lo + (hi - lo) * rng.uniform()) as f32;
                mask[i] = true;
            }
        }
        (out, mask)
    }

    fn gray(w: usize, h: usize) -> ColorImage {
        ColorImage::filled(w, h, [0.5; 3])
    }

    fn k_for(w: usize, h: usize) -> Intrinsics {
        crate::sim::synthetic::kinect_like_intrinsics(w, h)
    }

    /// Valid depths' range.
    fn valid_range(d: &DepthMap) -> (f32, f32) {
        d.as_slice()
            .iter()
            .filter(|z| DepthMap::is_valid(**z))
            .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), z| {
                (lo.min(*z), hi.max(*z))
            })
    }

    /// Outputs are finite, holes have confidence 0, confidences lie in
    /// [0, 1] and every depth lies within `[lo, hi]`.
    fn assert_sane(d: &DepthMap, c: &Confidence, lo: f32, hi: f32, what: &str) {
        assert!(d.same_dims(c), "{what}");
        for (z, c) in d.as_slice().iter().zip(c.as_slice()) {
            assert!(z.is_finite() && c.is_finite(), "{what}: {z} {c}");
            assert!((0.0..=1.0).contains(c), "{what}: confidence {c}");
            if *z == 0.0 {
                assert_eq!(*c, 0.0, "{what}: hole with confidence");
            } else {
                assert!(*z >= lo && *z <= hi, "{what}: {z} outside [{lo}, {hi}]");
            }
        }
    }

    #[test]
    fn inpainting_fills_kinect_holes_better_than_a_row_fill() {
        let gt = tabletop(96, 72);
        let kin = simulate_kinect(
            &gt.depth,
            Some(&gt.color),
            &gt.intrinsics,
            &KinectParams::default(),
        )
        .unwrap();
        let holes: Vec<bool> = kin
            .as_slice()
            .iter()
            .map(|z| !DepthMap::is_valid(*z))
            .collect();
        let n_holes = holes.iter().filter(|h| **h).count();
        assert!(n_holes > 50, "{n_holes}");
        let (d, c) =
            nlmeans_inpaint(&kin, None, &gt.color, &NLMeansInpaintParams::default()).unwrap();
        assert_eq!(d.hole_count(), 0);
        for (i, &hole) in holes.iter().enumerate() {
            if hole {
                assert!(c.as_slice()[i] > 0.0);
            } else {
                // Valid input pixels and their confidence are unchanged.
                assert_eq!(d.as_slice()[i].to_bits(), kin.as_slice()[i].to_bits());
                assert_eq!(c.as_slice()[i], 1.0);
            }
        }
        let (nlm, n) = rmse(&d, &gt.depth, |i| holes[i]);
        let (base, _) = rmse(&row_nearest_fill(&kin), &gt.depth, |i| holes[i]);
        let close = (0..d.len())
            .filter(|&i| holes[i] && (d.as_slice()[i] - gt.depth.as_slice()[i]).abs() < 0.15)
            .count() as f64
            / n as f64;
        // Measured: 101 holes, RMSE 0.368 m vs 0.678 m for the row fill, 81%
        // of the holes within 15 cm. The error is dominated by a few pixels
        // taking the wrong surface (1-1.5 m off): a dark object missing
        // entirely and shadow pixels whose color resembles the occluder.
        // 0.45 m allows about 9% of the holes on the wrong surface.
        assert!(nlm < 0.45, "NL-means {nlm} over {n} holes");
        assert!(nlm < 0.7 * base, "NL-means {nlm} vs row fill {base}");
        assert!(close > 0.75, "{close}");
    }

    #[test]
    fn far_prior_favours_the_background() {
        // A 6-pixel hole band between a near (1 m) and a far (3 m) region
        // under a constant color guide: without the prior both sides weigh
        // alike; with it a far source weighs 9 times a near one.
        let depth = DepthMap::from_fn(30, 8, |x, _| match x {
            0..12 => 1.0,
            12..18 => 0.0,
            _ => 3.0,
        });
        let color = gray(30, 8);
        let mean_fill = |far_prior: bool| {
            let p = NLMeansInpaintParams {
                far_prior,
                background: 0.0,
                ..Default::default()
            };
            let (d, _) = nlmeans_inpaint(&depth, None, &color, &p).unwrap();
            assert_eq!(d.hole_count(), 0);
            (0..8)
                .flat_map(|y| (12..18).map(move |x| (x, y)))
                .map(|(x, y)| *d.get(x, y) as f64)
                .sum::<f64>()
                / 48.0
        };
        // Measured: 2.00 without the prior (symmetric), 2.48 with it (the
        // first column is reached by the near side only, as in a real
        // disocclusion one side at a time).
        let (plain, far) = (mean_fill(false), mean_fill(true));
        assert!((plain - 2.0).abs() < 0.05, "{plain}");
        assert!(far > plain + 0.35 && far <= 3.0, "{far} vs {plain}");
    }

    #[test]
    fn the_background_side_fills_from_beyond_an_edge() {
        // The same band, 6 pixels between 1 m and 3 m under a constant guide.
        // With the background side every window that sees both sides takes
        // the far one; only the first column (whose window reaches the near
        // side alone) stays near.
        let depth = DepthMap::from_fn(30, 8, |x, _| match x {
            0..12 => 1.0,
            12..18 => 0.0,
            _ => 3.0,
        });
        let color = gray(30, 8);
        let fill = |background: f64| {
            let p = NLMeansInpaintParams {
                background,
                ..Default::default()
            };
            nlmeans_inpaint(&depth, None, &color, &p).unwrap().0
        };
        let (on, off) = (fill(50.0), fill(0.0));
        for y in 0..8 {
            for x in 13..18 {
                assert!(
                    (on.get(x, y) - 3.0).abs() < 1e-3,
                    "({x}, {y}): {}",
                    on.get(x, y)
                );
            }
            assert!((on.get(12, y) - 1.0).abs() < 1e-3);
        }
        // without it the band splits between the sides
        assert!((off.get(13, 4) - 1.0).abs() < 0.5, "{}", off.get(13, 4));
        // a one-surface hole (a ramp, steps under edge_step) is unchanged
        let ramp = DepthMap::from_fn(30, 8, |x, _| {
            if (12..18).contains(&x) {
                0.0
            } else {
                2.0 + 0.002 * x as f32
            }
        });
        let p = |background| NLMeansInpaintParams {
            background,
            ..Default::default()
        };
        let a = nlmeans_inpaint(&ramp, None, &color, &p(50.0)).unwrap().0;
        let b = nlmeans_inpaint(&ramp, None, &color, &p(0.0)).unwrap().0;
        assert_eq!(a, b);
    }

    #[test]
    fn upsampling_beats_nearest_and_bilinear_at_depth_edges() {
        let gt = tabletop(160, 120);
        let tof = ToFParams {
            width: 40,
            height: 30,
            noise_m: 0.0,
            noise_rel: 0.0,
            outlier_rate: 0.0,
            ..Default::default()
        };
        let (low, k_low) = simulate_tof(&gt.depth, &gt.intrinsics, &tof).unwrap();
        assert_eq!(low.hole_count(), 0);
        let (d, c) =
            nlmeans_upsample(&low, &k_low, &gt.color, &NLMeansUpsampleParams::default()).unwrap();
        assert_eq!(d.dims(), (160, 120));
        assert_eq!(d.hole_count(), 0);
        assert!(c.as_slice().iter().all(|c| *c > 0.0 && *c <= 1.0));
        let edges = edge_mask(&gt.depth, 2);
        let n_edges = edges.iter().filter(|e| **e).count();
        let at_edges = |e: &DepthMap| rmse(e, &gt.depth, |i| edges[i]).0;
        let all = |e: &DepthMap| rmse(e, &gt.depth, |_| true).0;
        let (nn, bl) = (nearest_up(&low, 160, 120), bilinear_up(&low, 160, 120));
        // Measured on 4529 edge pixels: NL-means 0.154 m, bilinear 0.202 m,
        // nearest 0.231 m (whole image 0.076 / 0.099 / 0.113 m). Most of
        // the remaining error comes from the ToF's flying pixels, which lie
        // between the surfaces on lines along the edges.
        assert!(n_edges > 2000, "{n_edges}");
        assert!(
            at_edges(&d) < 0.85 * at_edges(&bl),
            "{} vs bilinear {}",
            at_edges(&d),
            at_edges(&bl)
        );
        assert!(
            at_edges(&d) < 0.75 * at_edges(&nn),
            "{} vs nearest {}",
            at_edges(&d),
            at_edges(&nn)
        );
        assert!(all(&d) < 0.85 * all(&bl), "{} vs {}", all(&d), all(&bl));
    }

    #[test]
    fn scale_steps_are_equal_and_end_at_the_target() {
        assert_eq!(scale_steps((320, 240), (640, 480), 2.0), vec![(640, 480)]);
        assert_eq!(
            scale_steps((160, 120), (640, 480), 2.0),
            vec![(320, 240), (640, 480)]
        );
        assert_eq!(
            scale_steps((80, 60), (640, 480), 2.0),
            vec![(160, 120), (320, 240), (640, 480)]
        );
        assert_eq!(scale_steps((160, 120), (640, 480), 4.0), vec![(640, 480)]);
        // x8 in steps of at most 4: two of sqrt(8)
        assert_eq!(
            scale_steps((80, 60), (640, 480), 4.0),
            vec![(226, 170), (640, 480)]
        );
        // rounded sizes just over a power stay that power
        assert_eq!(scale_steps((173, 139), (1390, 1110), 2.0).len(), 3);
        assert_eq!(scale_steps((64, 64), (64, 64), 2.0), vec![(64, 64)]);
        assert_eq!(scale_steps((10, 10), (80, 80), 0.0), vec![(80, 80)]);
        // each axis by its own ratio: the wide depth's columns are never thinned
        let steps = scale_steps((100, 10), (800, 800), 4.0);
        assert_eq!(steps.len(), 4);
        assert!(steps.iter().all(|s| s.0 >= 100), "{steps:?}");
        assert_eq!(scale_steps((0, 0), (8, 8), 2.0).last(), Some(&(8, 8)));
    }

    #[test]
    fn stepped_upsampling_stays_sane_on_hard_inputs() {
        let mut rng = SplitMix64(77);
        for (lw, lh, factor) in [(1, 1, 9), (1, 7, 6), (5, 1, 8), (6, 4, 5), (9, 7, 16)] {
            // depths over six decades, holes, one NaN, a sub-millimetre step
            let depth = DepthMap::from_fn(lw, lh, |x, y| match (x + 3 * y) % 5 {
                0 => 0.0,
                1 if x + y == 1 => f32::NAN,
                2 => 1e-3,
                3 => 1e3,
                _ => 1.0 + 1e-4 * rng.uniform() as f32,
            });
            let (w, h) = (lw * factor, lh * factor);
            let color = ColorImage::from_fn(w, h, |x, y| {
                [
                    (x % 3) as f32,
                    (y % 2) as f32 * 1e6,
                    if x == y { f32::INFINITY } else { 0.2 },
                ]
            });
            let k = k_for(lw, lh);
            let (lo, hi) = valid_range(&depth);
            let (d, c) =
                nlmeans_upsample(&depth, &k, &color, &NLMeansUpsampleParams::default()).unwrap();
            assert_eq!(d.dims(), (w, h));
            if lo <= hi {
                assert_sane(&d, &c, lo, hi, &format!("{lw}x{lh} x{factor}"));
                assert!(
                    d.hole_count() < d.len(),
                    "{lw}x{lh} x{factor}: nothing upsampled"
                );
            }
        }
    }

    #[test]
    fn area_downsampling_keeps_the_mean() {
        let c = ColorImage::from_fn(9, 6, |x, y| [x as f32, y as f32, 1.0]);
        let d = area_downsample(&c, 3, 2);
        assert_eq!(d.dims(), (3, 2));
        // output (1, 1) averages x in 3..6, y in 3..6
        assert_eq!(*d.get(1, 1), [4.0, 4.0, 1.0]);
        let mean = |img: &ColorImage| {
            img.as_slice().iter().map(|p| p[0] as f64).sum::<f64>() / img.len() as f64
        };
        assert!((mean(&c) - mean(&d)).abs() < 1e-9);
        // non-finite samples are left out
        let mut n = c.clone();
        *n.get_mut(0, 0) = [f32::NAN, 0.0, 0.0];
        assert!(area_downsample(&n, 3, 2).get(0, 0)[0].is_finite());
    }

    #[test]
    fn multiscale_upsampling_wins_at_a_factor_of_eight() {
        let gt = tabletop(320, 240);
        let tof = ToFParams {
            width: 40,
            height: 30,
            noise_m: 0.02,
            noise_rel: 0.01,
            outlier_rate: 0.0,
            ..Default::default()
        };
        let (low, k_low) = simulate_tof(&gt.depth, &gt.intrinsics, &tof).unwrap();
        let run = |max_step_factor: f64, spatial_sigma: f64| {
            let p = NLMeansUpsampleParams {
                max_step_factor,
                spatial_sigma,
                ..Default::default()
            };
            nlmeans_upsample(&low, &k_low, &gt.color, &p).unwrap().0
        };
        let edges = edge_mask(&gt.depth, 2);
        let at_edges = |e: &DepthMap| rmse(e, &gt.depth, |i| edges[i]).0;
        let all = |d: &DepthMap| rmse(d, &gt.depth, |_| true).0;
        // eq. 4 as published (no falloff, a uniform 11x11 window)
        let (one, steps) = (run(0.0, 0.0), run(4.0, 0.0));
        let bl = bilinear_up(&low, 320, 240);
        assert_eq!(steps.hole_count(), 0);
        // Measured: whole image 0.098 (steps) / 0.099 (one step) / 0.106 m
        // (bilinear); at the edges 0.310 / 0.327 / 0.354 m.
        assert!(all(&steps) < all(&one) && all(&steps) < all(&bl));
        assert!(at_edges(&steps) < 0.97 * at_edges(&one));
        // With the falloff (default) the window widens to 16 pixels in one
        // step: measured 0.088 m whole, 0.287 at the edges; in steps 0.099 /
        // 0.311 (the default, ahead of bilinear either way).
        let (one_f, steps_f) = (run(0.0, 2.0), run(4.0, 2.0));
        assert!(all(&one_f) < 0.95 * all(&steps) && at_edges(&one_f) < 0.95 * at_edges(&steps));
        assert!(all(&steps_f) < all(&bl) && at_edges(&steps_f) < at_edges(&bl));
    }

    #[test]
    fn upsampling_uses_the_intrinsics_and_keeps_constant_depth() {
        let low = DepthMap::filled(20, 15, 2.5);
        let k_low = k_for(20, 15);
        let color = ColorImage::from_fn(80, 60, |x, y| {
            [(x % 7) as f32 * 0.1, (y % 5) as f32 * 0.2, 0.3]
        });
        let p = NLMeansUpsampleParams::default();
        let (d, c, k) = nlmeans_upsample_with(&low, &k_low, &color, None, &p, |_| Ok(())).unwrap();
        assert!(d.as_slice().iter().all(|z| *z == 2.5));
        assert!(c.as_slice().iter().all(|c| *c > 0.0));
        assert_eq!(k, k_low.scaled_to(80, 60));
        // A color camera with a longer focal length sees only the centre of
        // the depth image: its left half gets the depth's columns 5..10.
        let low = DepthMap::from_fn(20, 15, |x, _| if x < 10 { 1.0 } else { 2.0 });
        let k_col = Intrinsics {
            fx: 2.0 * k_low.fx * 4.0,
            fy: 2.0 * k_low.fy * 4.0,
            ..k_low.scaled_to(80, 60)
        };
        let (d, _, k) =
            nlmeans_upsample_with(&low, &k_low, &gray(80, 60), Some(&k_col), &p, |_| Ok(()))
                .unwrap();
        assert_eq!(k, k_col);
        assert_eq!(*d.get(10, 30), 1.0);
        assert_eq!(*d.get(70, 30), 2.0);
        // Depth samples of a camera that is not sane, or intrinsics of the
        // wrong size, are refused naming the port.
        let bad = Intrinsics { fx: 0.0, ..k_low };
        for (k, kc, port) in [
            (bad, None, "intrinsics"),
            (k_for(10, 10), None, "intrinsics"),
            (k_low, Some(k_for(40, 30)), "color_intrinsics"),
        ] {
            match nlmeans_upsample_with(&low, &k, &gray(80, 60), kc.as_ref(), &p, |_| Ok(())) {
                Err(NodeError::Input { port: got, .. }) => assert_eq!(got, port),
                other => panic!("expected an input error, got {other:?}"),
            }
        }
    }

    /// With one colour everywhere every colour patch matches, so with
    /// `alpha` 1 each estimate is the mean of the window's samples weighted
    /// by the spatial falloff alone, over a window of radius
    /// `max(search_radius, 2 f)` (`search_radius` without the falloff):
    /// computed here from the placement's rule and compared (x4, so the
    /// window is 8 pixels, not 5).
    #[test]
    fn the_spatial_falloff_weighs_the_samples_of_the_widened_window() {
        let (lw, lh, f) = (12usize, 10usize, 4usize);
        let mut rng = SplitMix64(3);
        let low = DepthMap::from_fn(lw, lh, |_, _| 1.0 + rng.next_f64() as f32);
        let k = k_for(lw, lh);
        let (w, h) = (lw * f, lh * f);
        let hk = k.scaled_to(w, h);
        let cols = axis_map(lw, k.fx, k.cx, hk.fx, hk.cx, w);
        let rows = axis_map(lh, k.fy, k.cy, hk.fy, hk.cy, h);
        for sigma in [0.0, 1.0, 2.0] {
            // widened to 2 f with the falloff; eq. 4's own without
            let r = if sigma > 0.0 { 8isize } else { 5 };
            let p = NLMeansUpsampleParams {
                alpha: 1.0,
                prune: false,
                spatial_sigma: sigma,
                iterations: 0,
                ..Default::default()
            };
            let (d, _) = nlmeans_upsample(&low, &k, &gray(w, h), &p).unwrap();
            for (x, y) in [(20isize, 17isize), (3, 2), (45, 38), (30, 5)] {
                let (mut sw, mut sz) = (0.0f64, 0.0f64);
                for (ly, &hy) in rows.iter().enumerate() {
                    for (lx, &hx) in cols.iter().enumerate() {
                        let (dx, dy) = (hx as isize - x, hy as isize - y);
                        if dx.abs() > r || dy.abs() > r {
                            continue;
                        }
                        let wt = if sigma > 0.0 {
                            let s = sigma * f as f64;
                            (-((dx * dx + dy * dy) as f64) / (2.0 * s * s)).exp()
                        } else {
                            1.0
                        };
                        sw += wt;
                        sz += wt * f64::from(*low.get(lx, ly));
                    }
                }
                let want = sz / sw;
                let got = f64::from(*d.get(x as usize, y as usize));
                assert!(
                    (got - want).abs() <= 1e-6 * want,
                    "sigma {sigma} at ({x}, {y}): {got} against {want}"
                );
            }
        }
        // A falloff too narrow to compute (1 / (2 sigma^2) overflows) is
        // capped: the nearest sample decides, every pixel has a value.
        let p = NLMeansUpsampleParams {
            alpha: 1.0,
            prune: false,
            spatial_sigma: 1e-200,
            iterations: 0,
            ..Default::default()
        };
        let (d, _) = nlmeans_upsample(&low, &k, &gray(w, h), &p).unwrap();
        for (ly, &hy) in rows.iter().enumerate() {
            for (lx, &hx) in cols.iter().enumerate() {
                assert_eq!(*d.get(hx, hy), *low.get(lx, ly), "sample ({lx}, {ly})");
            }
        }
        assert_eq!(d.hole_count(), 0);
        let p = NLMeansUpsampleParams {
            spatial_sigma: -1.0,
            ..Default::default()
        };
        match nlmeans_upsample(&low, &k, &gray(w, h), &p) {
            Err(NodeError::Param { param, .. }) => assert_eq!(param, "spatial_sigma"),
            other => panic!("expected a parameter error, got {other:?}"),
        }
    }

    #[test]
    fn pruning_removes_spikes_and_keeps_the_scene() {
        let gt = tabletop(96, 72);
        let (sp, mask) = spiked(&gt.depth, 0.02, 0.85, 2.8, 3);
        let p = PruneParams::default();
        let (d, c) = prune_outliers(&sp, None, &p).unwrap();
        let w = 96;
        let sigma = |z: f32| p.sigma_m + p.sigma_rel * z as f64;
        // A spike is detectable when it is more than 5 noise sigmas from the
        // truth and from every true depth in its 5x5 neighbourhood (a spike
        // landing on a neighbouring surface looks like an edge pixel).
        let detectable = |i: usize| {
            let (x, y) = (i % w, i / w);
            let s = sp.as_slice()[i];
            (y.saturating_sub(2)..(y + 3).min(72)).all(|yy| {
                (x.saturating_sub(2)..(x + 3).min(w)).all(|xx| {
                    let t = *gt.depth.get(xx, yy);
                    (s - t).abs() as f64 > 5.0 * sigma(t)
                })
            })
        };
        let cand: Vec<usize> = (0..sp.len())
            .filter(|&i| mask[i] && detectable(i))
            .collect();
        let hits = cand.iter().filter(|&&i| d.as_slice()[i] == 0.0).count();
        let recall = hits as f64 / cand.len() as f64;
        let clean = mask.iter().filter(|m| !**m).count();
        let false_pos = (0..sp.len())
            .filter(|&i| !mask[i] && d.as_slice()[i] == 0.0)
            .count();
        // Measured: 137 spikes, 104 detectable, 101 pruned (97%); 4 false
        // positives among 6775 clean pixels (0.06%).
        assert!(cand.len() > 80, "{}", cand.len());
        assert!(recall > 0.9, "recall {recall} ({hits} of {})", cand.len());
        assert!((false_pos as f64) < 0.005 * clean as f64, "{false_pos}");
        for i in 0..sp.len() {
            if d.as_slice()[i] == 0.0 {
                assert_eq!(c.as_slice()[i], 0.0);
            } else {
                assert_eq!(d.as_slice()[i], sp.as_slice()[i]);
                assert!(c.as_slice()[i] > 0.5);
            }
        }
    }

    #[test]
    fn pruning_leaves_a_clean_tilted_plane_untouched() {
        // The plane z = 2 + 0.8 X (about 39 degrees), exact at every pixel.
        let k = k_for(64, 48);
        let depth = DepthMap::from_fn(64, 48, |x, _| {
            let xn = (x as f64 + 0.5 - k.cx) / k.fx;
            (2.0 / (1.0 - 0.8 * xn)) as f32
        });
        for radius in [1, 2, 4] {
            let p = PruneParams {
                radius,
                sigma_m: 0.001,
                sigma_rel: 0.0,
                ..Default::default()
            };
            let (d, c) = prune_outliers(&depth, None, &p).unwrap();
            assert_eq!(d, depth, "radius {radius}");
            assert!(c.as_slice().iter().all(|c| *c > 0.99), "radius {radius}");
        }
    }

    #[test]
    fn denoising_reduces_noise_and_keeps_holes() {
        let gt = tabletop(96, 72);
        let mut n = noisy(&gt.depth, 0.01, 0.005, 1);
        for x in 10..20 {
            *n.get_mut(x, 5) = 0.0;
        }
        let before = rmse(&n, &gt.depth, |i| n.as_slice()[i] > 0.0).0;
        let (d, c) = nlmeans_denoise(&n, None, &gt.color, &NLMeansDepthParams::default()).unwrap();
        let kept = |i: usize| d.as_slice()[i] > 0.0;
        let after = rmse(&d, &gt.depth, kept).0;
        // Measured: 0.0213 m before, 0.0118 m after, 4 pixels pruned.
        assert!(after < 0.65 * before, "{after} vs {before}");
        assert!(d.hole_count() < 10 + 20, "{}", d.hole_count());
        for x in 10..20 {
            assert_eq!((*d.get(x, 5), *c.get(x, 5)), (0.0, 0.0));
        }
        assert!(
            c.as_slice()
                .iter()
                .enumerate()
                .all(|(i, c)| kept(i) == (*c > 0.0))
        );
    }

    #[test]
    fn constant_depth_is_a_fixed_point() {
        let color = ColorImage::from_fn(24, 18, |x, y| [(x * y % 11) as f32 * 0.1, 0.2, 0.7]);
        for z in [0.001f32, 1.7, 1000.0] {
            let depth = DepthMap::filled(24, 18, z);
            let p = NLMeansDepthParams::default();
            assert_eq!(nlmeans_filter(&depth, None, &color, &p).unwrap().0, depth);
            let (d, c) = nlmeans_denoise(&depth, None, &color, &p).unwrap();
            assert_eq!(d, depth);
            // The pruning leaves each pixel 1 - P(outlier), about 0.98.
            assert!(c.as_slice().iter().all(|c| *c > 0.95 && *c < 1.0));
            let ip = NLMeansInpaintParams::default();
            let (d, c) = nlmeans_inpaint(&depth, None, &color, &ip).unwrap();
            assert_eq!(d, depth);
            assert!(c.as_slice().iter().all(|c| *c == 1.0));
            // With holes, the filled values are exactly the constant.
            let mut holed = depth.clone();
            for x in 3..15 {
                *holed.get_mut(x, 9) = 0.0;
            }
            let (d, _) = nlmeans_inpaint(&holed, None, &color, &ip).unwrap();
            assert_eq!(d, depth);
            let low = DepthMap::filled(6, 4, z);
            let (d, _) = nlmeans_upsample(&low, &k_for(6, 4), &color, &Default::default()).unwrap();
            assert_eq!(d, depth);
        }
    }

    #[test]
    fn filter_keeps_depth_edges_under_a_constant_color_guide() {
        let depth = DepthMap::from_fn(20, 10, |x, _| if x < 10 { 1.0 } else { 1.3 });
        let (d, c) =
            nlmeans_filter(&depth, None, &gray(20, 10), &NLMeansDepthParams::default()).unwrap();
        for y in 0..10 {
            for x in 0..20 {
                let want = if x < 10 { 1.0 } else { 1.3 };
                assert!(
                    (d.get(x, y) - want).abs() < 1e-3,
                    "({x}, {y}): {}",
                    d.get(x, y)
                );
            }
        }
        assert!(c.as_slice().iter().all(|c| *c == 1.0));
    }

    #[test]
    fn filter_keeps_pixels_without_sources() {
        // Valid depths of confidence 0 are no sources: with no source in
        // the window the input value is kept, with confidence 0.
        let depth = DepthMap::from_vec(3, 1, vec![1.0, 0.0, 2.0]).unwrap();
        let conf = Confidence::filled(3, 1, 0.0);
        let (d, c) = nlmeans_filter(&depth, Some(&conf), &gray(3, 1), &Default::default()).unwrap();
        assert_eq!((d, c), (depth, conf));
    }

    #[test]
    fn all_holes_stay_holes_with_zero_confidence() {
        let (w, h) = (12, 9);
        let color = gray(w, h);
        for fill in [0.0f32, f32::NAN, -1.0, f32::INFINITY] {
            let depth = DepthMap::filled(w, h, fill);
            let zero_d = DepthMap::filled(w, h, 0.0);
            let zero_c = Confidence::filled(w, h, 0.0);
            let p = NLMeansDepthParams::default();
            assert_eq!(
                prune_outliers(&depth, None, &p.prune_params()).unwrap(),
                (zero_d.clone(), zero_c.clone())
            );
            assert_eq!(
                nlmeans_filter(&depth, None, &color, &p).unwrap(),
                (zero_d.clone(), zero_c.clone())
            );
            assert_eq!(
                nlmeans_denoise(&depth, None, &color, &p).unwrap(),
                (zero_d.clone(), zero_c.clone())
            );
            let ip = NLMeansInpaintParams::default();
            assert_eq!(
                nlmeans_inpaint(&depth, None, &color, &ip).unwrap(),
                (zero_d.clone(), zero_c.clone())
            );
            let low = DepthMap::filled(3, 3, fill);
            let up = nlmeans_upsample(&low, &k_for(3, 3), &color, &Default::default()).unwrap();
            assert_eq!(up, (zero_d, zero_c));
        }
    }

    #[test]
    fn one_valid_pixel_fills_everything_with_its_value() {
        let mut depth = DepthMap::filled(40, 30, 0.0);
        *depth.get_mut(33, 4) = 1.234;
        let color = ColorImage::from_fn(40, 30, |x, y| [x as f32 / 40.0, y as f32 / 30.0, 0.5]);
        let (d, c) =
            nlmeans_inpaint(&depth, None, &color, &NLMeansInpaintParams::default()).unwrap();
        assert!(d.as_slice().iter().all(|z| *z == 1.234));
        assert!(c.as_slice().iter().all(|c| *c > 0.0));
        assert_eq!(*c.get(33, 4), 1.0);
        // Too few iterations leave the far corner a hole, with confidence 0.
        let p = NLMeansInpaintParams {
            iterations: 2,
            ..Default::default()
        };
        let (d, c) = nlmeans_inpaint(&depth, None, &color, &p).unwrap();
        assert!(d.hole_count() > 0 && *d.get(0, 29) == 0.0 && *c.get(0, 29) == 0.0);
        assert_eq!(*d.get(23, 4), 1.234);
        // Upsampling a single valid sample.
        let mut low = DepthMap::filled(10, 8, 0.0);
        *low.get_mut(2, 2) = 0.75;
        let (d, _) = nlmeans_upsample(&low, &k_for(10, 8), &color, &Default::default()).unwrap();
        assert!(d.as_slice().iter().all(|z| *z == 0.75));
    }

    #[test]
    fn tiny_images_work() {
        for (w, h) in [(1, 1), (1, 7), (7, 1), (2, 1), (0, 0), (0, 5)] {
            let color = gray(w, h);
            let depth = DepthMap::from_fn(w, h, |x, y| {
                if (x + y) % 3 == 1 {
                    0.0
                } else {
                    1.0 + 0.1 * (x + y) as f32
                }
            });
            let (lo, hi) = valid_range(&depth);
            let p = NLMeansDepthParams::default();
            let (d, c) = nlmeans_filter(&depth, None, &color, &p).unwrap();
            assert_sane(&d, &c, lo, hi, "filter");
            let (d, c) = nlmeans_denoise(&depth, None, &color, &p).unwrap();
            assert_sane(&d, &c, lo, hi, "denoise");
            let (d, c) = nlmeans_inpaint(&depth, None, &color, &Default::default()).unwrap();
            assert_sane(&d, &c, lo, hi, "inpaint");
            if depth.len() > depth.hole_count() {
                assert_eq!(d.hole_count(), 0, "{w}x{h}");
            }
            let k = Intrinsics {
                fx: 1.0,
                fy: 1.0,
                cx: w as f64 / 2.0,
                cy: h as f64 / 2.0,
                width: w,
                height: h,
            };
            let (d, c) =
                nlmeans_upsample(&depth, &k, &gray(3 * w, 3 * h), &Default::default()).unwrap();
            assert_eq!(d.dims(), (3 * w, 3 * h));
            assert_sane(&d, &c, lo, hi, "upsample");
        }
    }

    #[test]
    fn non_finite_and_negative_depths_are_holes() {
        let gt = tabletop(32, 24);
        let mut bad = gt.depth.clone();
        let mut zeros = gt.depth.clone();
        for (k, v) in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY, -2.0, -0.0]
            .into_iter()
            .enumerate()
        {
            *bad.get_mut(3 + 5 * k, 7) = v;
            *zeros.get_mut(3 + 5 * k, 7) = 0.0;
        }
        let p = NLMeansDepthParams::default();
        assert_eq!(
            nlmeans_denoise(&bad, None, &gt.color, &p).unwrap(),
            nlmeans_denoise(&zeros, None, &gt.color, &p).unwrap()
        );
        let ip = NLMeansInpaintParams::default();
        let (d, c) = nlmeans_inpaint(&bad, None, &gt.color, &ip).unwrap();
        assert_eq!(
            (d.clone(), c),
            nlmeans_inpaint(&zeros, None, &gt.color, &ip).unwrap()
        );
        assert_eq!(d.hole_count(), 0);
        // NaN or out-of-range confidences and colors are tolerated too.
        let conf = Confidence::from_fn(32, 24, |x, _| match x % 4 {
            0 => f32::NAN,
            1 => -1.0,
            2 => 7.0,
            _ => 0.5,
        });
        let color = ColorImage::from_fn(32, 24, |x, _| [f32::NAN, f32::INFINITY, -(x as f32)]);
        let (lo, hi) = valid_range(&zeros);
        let (d, c) = nlmeans_denoise(&bad, Some(&conf), &color, &p).unwrap();
        assert_sane(&d, &c, lo, hi, "denoise");
        let (d, c) = nlmeans_inpaint(&bad, Some(&conf), &color, &ip).unwrap();
        assert_sane(&d, &c, lo, hi, "inpaint");
    }

    #[test]
    fn extreme_depth_ranges_stay_finite_and_in_range() {
        // 1 mm next to 1000 m, with holes in between.
        let depth = DepthMap::from_fn(30, 20, |x, y| match (x + 2 * y) % 7 {
            0 | 1 => 0.0,
            2..5 => 0.001,
            _ => 1000.0,
        });
        let color = ColorImage::from_fn(30, 20, |x, y| [((x + 2 * y) % 7) as f32 * 0.1, 0.5, 0.5]);
        let (lo, hi) = (0.001, 1000.0);
        let p = NLMeansDepthParams::default();
        let (d, c) = nlmeans_filter(&depth, None, &color, &p).unwrap();
        assert_sane(&d, &c, lo, hi, "filter");
        let (d, c) = nlmeans_denoise(&depth, None, &color, &p).unwrap();
        assert_sane(&d, &c, lo, hi, "denoise");
        for far_prior in [false, true] {
            let ip = NLMeansInpaintParams {
                far_prior,
                ..Default::default()
            };
            let (d, c) = nlmeans_inpaint(&depth, None, &color, &ip).unwrap();
            assert_sane(&d, &c, lo, hi, "inpaint");
            assert_eq!(d.hole_count(), 0);
        }
        let (d, c) =
            nlmeans_upsample(&depth, &k_for(30, 20), &gray(90, 60), &Default::default()).unwrap();
        assert_sane(&d, &c, lo, hi, "upsample");
        // The smallest h: weights of all candidates differ by far more than
        // f64's range, and still every hole is filled.
        let ip = NLMeansInpaintParams {
            h_color: 1e-4,
            h_depth: 1e-6,
            ..Default::default()
        };
        let (d, c) = nlmeans_inpaint(&depth, None, &color, &ip).unwrap();
        assert_sane(&d, &c, lo, hi, "inpaint, small h");
        assert_eq!(d.hole_count(), 0);
    }

    #[test]
    fn results_do_not_depend_on_the_thread_count() {
        let gt = tabletop(80, 70);
        let kin = simulate_kinect(
            &gt.depth,
            Some(&gt.color),
            &gt.intrinsics,
            &KinectParams::default(),
        )
        .unwrap();
        let (low, k_low) = simulate_tof(
            &gt.depth,
            &gt.intrinsics,
            &ToFParams {
                width: 20,
                height: 17,
                ..Default::default()
            },
        )
        .unwrap();
        let run = |threads: usize| {
            crate::test_support::with_threads(threads, || {
                (
                    nlmeans_denoise(&kin, None, &gt.color, &Default::default()).unwrap(),
                    nlmeans_inpaint(&kin, None, &gt.color, &Default::default()).unwrap(),
                    nlmeans_upsample(&low, &k_low, &gt.color, &Default::default()).unwrap(),
                )
            })
        };
        let a = run(1);
        let b = run(3);
        fn bits<K>(m: &Image<f32, K>) -> Vec<u32> {
            m.as_slice().iter().map(|v| v.to_bits()).collect()
        }
        for (x, y) in [(&a.0, &b.0), (&a.1, &b.1), (&a.2, &b.2)] {
            assert_eq!(bits(&x.0), bits(&y.0));
            assert_eq!(bits(&x.1), bits(&y.1));
        }
    }

    #[test]
    fn mismatched_inputs_and_bad_parameters_are_errors() {
        let depth = DepthMap::filled(8, 6, 1.0);
        let small = gray(4, 3);
        let p = NLMeansDepthParams::default();
        let port = |r: Result<(DepthMap, Confidence), NodeError>| match r {
            Err(NodeError::Input { port, message }) => {
                assert!(message.contains("8x6"), "{message}");
                port
            }
            other => panic!("expected an input error, got {other:?}"),
        };
        assert_eq!(port(nlmeans_filter(&depth, None, &small, &p)), "color");
        assert_eq!(port(nlmeans_denoise(&depth, None, &small, &p)), "color");
        assert_eq!(
            port(nlmeans_inpaint(&depth, None, &small, &Default::default())),
            "color"
        );
        let conf = Confidence::filled(4, 3, 1.0);
        assert_eq!(
            port(nlmeans_filter(&depth, Some(&conf), &gray(8, 6), &p)),
            "confidence"
        );
        assert_eq!(
            port(prune_outliers(&depth, Some(&conf), &p.prune_params())),
            "confidence"
        );
        let param = |r: Result<(DepthMap, Confidence), NodeError>| match r {
            Err(NodeError::Param { param, .. }) => param,
            other => panic!("expected a parameter error, got {other:?}"),
        };
        let color = gray(8, 6);
        let bad = NLMeansDepthParams {
            h_color: f64::NAN,
            ..Default::default()
        };
        assert_eq!(param(nlmeans_filter(&depth, None, &color, &bad)), "h_color");
        let bad = NLMeansDepthParams {
            search_radius: 1000,
            ..Default::default()
        };
        assert_eq!(
            param(nlmeans_filter(&depth, None, &color, &bad)),
            "search_radius"
        );
        let bad = NLMeansDepthParams {
            noise_sigma_m: 0.0,
            ..Default::default()
        };
        assert_eq!(
            param(nlmeans_denoise(&depth, None, &color, &bad)),
            "noise_sigma_m"
        );
        // a window of one pixel (the input back) and a threshold that
        // prunes every pixel are refused, not run
        let bad = NLMeansDepthParams {
            search_radius: 0,
            ..Default::default()
        };
        assert_eq!(
            param(nlmeans_denoise(&depth, None, &color, &bad)),
            "search_radius"
        );
        let bad = NLMeansDepthParams {
            outlier_threshold: 0.0,
            ..Default::default()
        };
        assert_eq!(
            param(nlmeans_denoise(&depth, None, &color, &bad)),
            "outlier_threshold"
        );
        let bad = NLMeansInpaintParams {
            search_radius: 0,
            ..Default::default()
        };
        assert_eq!(
            param(nlmeans_inpaint(&depth, None, &color, &bad)),
            "search_radius"
        );
        let bad = NLMeansUpsampleParams {
            alpha: 2.0,
            ..Default::default()
        };
        assert_eq!(
            param(nlmeans_upsample(&depth, &k_for(8, 6), &color, &bad)),
            "alpha"
        );
    }

    fn ctx_params(node: &dyn Node) -> ParamMap {
        node.schema()
            .params
            .iter()
            .map(|s| {
                s.kind.validate(&s.default).unwrap();
                (s.name.to_string(), s.default.clone())
            })
            .collect()
    }

    #[test]
    fn nodes_produce_their_declared_outputs() {
        let mut reg = Registry::new();
        register(&mut reg).unwrap();
        let gt = tabletop(32, 24);
        let kin = simulate_kinect(
            &gt.depth,
            Some(&gt.color),
            &gt.intrinsics,
            &KinectParams::default(),
        )
        .unwrap();
        let (low, k_low) = simulate_tof(
            &gt.depth,
            &gt.intrinsics,
            &ToFParams {
                width: 8,
                height: 6,
                ..Default::default()
            },
        )
        .unwrap();
        let cancel = CancelToken::new();
        let reports = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
        let sink = reports.clone();
        let progress: depthgraph_graph::node::ProgressFn =
            Arc::new(move |_, f| sink.lock().unwrap().push(f));
        let ctx = EvalCtx {
            node: "n",
            cancel: &cancel,
            progress: Some(&progress),
            out_dir: std::path::Path::new("."),
            input_files: &[],
            derivations: None,
            max_pixels: depthgraph_graph::node::DEFAULT_MAX_PIXELS,
        };
        for kind in ["NLMeansDepth", "NLMeansUpsample", "NLMeansInpaint"] {
            let node = reg.get(kind).unwrap();
            let mut inputs = Inputs::new();
            inputs.insert("color", gt.color.clone().into());
            if kind == "NLMeansUpsample" {
                inputs.insert("depth", low.clone().into());
                inputs.insert("intrinsics", k_low.into());
                inputs.insert("color_intrinsics", gt.intrinsics.into());
            } else {
                inputs.insert("depth", kin.clone().into());
                inputs.insert(
                    "confidence",
                    Value::Confidence(Arc::new(Confidence::filled(32, 24, 1.0))),
                );
            }
            reports.lock().unwrap().clear();
            let out = node
                .eval(&ctx, &inputs, &ctx_params(node.as_ref()))
                .unwrap();
            assert!(out.passthrough.is_none());
            for port in &node.schema().outputs {
                assert_eq!(
                    out.values[port.name].value_type(),
                    port.ty,
                    "{kind}.{}",
                    port.name
                );
            }
            match &out.values["depth"] {
                Value::Depth(d) => assert_eq!(d.dims(), (32, 24)),
                other => panic!("{other:?}"),
            }
            let r = reports.lock().unwrap().clone();
            assert!(
                !r.is_empty() && r.windows(2).all(|w| w[0] <= w[1]),
                "{kind}: {r:?}"
            );
        }
        // Inpainting without holes passes the input through.
        let node = reg.get("NLMeansInpaint").unwrap();
        let mut inputs = Inputs::new();
        inputs.insert("depth", gt.depth.clone().into());
        inputs.insert("color", gt.color.clone().into());
        let out = node
            .eval(&ctx, &inputs, &ctx_params(node.as_ref()))
            .unwrap();
        assert_eq!(out.passthrough.as_deref(), Some("no holes to fill"));
        assert_eq!(
            out.values["depth"],
            Value::Depth(Arc::new(gt.depth.clone()))
        );
        assert_eq!(
            out.values["confidence"],
            Value::Confidence(Arc::new(Confidence::filled(32, 24, 1.0)))
        );
        // ... but still checks its wiring.
        inputs.insert("color", gray(5, 5).into());
        assert!(matches!(
            node.eval(&ctx, &inputs, &ctx_params(node.as_ref())),
            Err(NodeError::Input { .. })
        ));
        // Cancellation stops a running node.
        cancel.cancel();
        let node = reg.get("NLMeansDepth").unwrap();
        inputs.insert("depth", kin.clone().into());
        inputs.insert("color", gt.color.clone().into());
        assert!(matches!(
            node.eval(&ctx, &inputs, &ctx_params(node.as_ref())),
            Err(NodeError::Cancelled)
        ));
    }

    use proptest::prelude::*;

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        #[test]
        fn outputs_are_finite_and_within_the_input_range(
            w in 1usize..12,
            h in 1usize..10,
            seed in any::<u64>(),
            hole_rate in 0.0f64..0.9,
            log_lo in -3.0f64..2.0,
            log_span in 0.0f64..6.0,
            far_prior in any::<bool>(),
        ) {
            let depth = DepthMap::from_fn(w, h, |x, y| {
                let mut rng = SplitMix64::for_pixel(seed, 1, x as u64, y as u64);
                if rng.uniform() < hole_rate {
                    [0.0, f32::NAN, -1.0][(rng.next_u64() % 3) as usize]
                } else {
                    10f64.powf(log_lo + log_span * rng.uniform()) as f32
                }
            });
            let color = ColorImage::from_fn(w, h, |x, y| {
                let mut rng = SplitMix64::for_pixel(seed, 2, x as u64, y as u64);
                [rng.uniform() as f32, rng.uniform() as f32 * 4.0, 0.5]
            });
            let (lo, hi) = valid_range(&depth);
            let p = NLMeansDepthParams { search_radius: 2, patch_radius: 1, ..Default::default() };
            let (d, c) = nlmeans_denoise(&depth, None, &color, &p).unwrap();
            assert_sane(&d, &c, lo, hi, "denoise");
            let ip = NLMeansInpaintParams { far_prior, search_radius: 2, patch_radius: 1, ..Default::default() };
            let (d, c) = nlmeans_inpaint(&depth, None, &color, &ip).unwrap();
            assert_sane(&d, &c, lo, hi, "inpaint");
            for (a, b) in depth.as_slice().iter().zip(d.as_slice()) {
                if DepthMap::is_valid(*a) {
                    prop_assert_eq!(a.to_bits(), b.to_bits());
                }
            }
            if depth.hole_count() < depth.len() {
                // Windows of 5x5 reach a 12x10 image in 6 iterations.
                prop_assert_eq!(d.hole_count(), 0);
            }
            let k = k_for(w, h);
            let up = NLMeansUpsampleParams { search_radius: 2, ..Default::default() };
            let (d, c) = nlmeans_upsample(&depth, &k, &ColorImage::filled(2 * w, 2 * h, [0.3; 3]), &up).unwrap();
            assert_sane(&d, &c, lo, hi, "upsample");
        }
    }
}
