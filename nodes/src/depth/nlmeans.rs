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
//!   small `h` is: an estimate exists whenever a source pixel does.
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

use std::sync::Arc;

use depthgraph_graph::node_params;
use depthgraph_graph::prelude::*;
use depthgraph_graph::registry::RegistryError;
use rayon::prelude::*;

use crate::kit::checks::{fits_intrinsics, same_size};

/// Rows per band of the parallel passes (fixed, so results do not depend on
/// the number of threads).
const BAND_ROWS: usize = 32;
/// Bands processed between two progress reports / cancellation checks.
const WAVE_BANDS: usize = 8;
/// `exp(-x)` is exactly 0 in f64 for `x >= EXP_CUTOFF`: per-pixel patch
/// distances are capped at `EXP_CUTOFF / (smallest patch kernel weight)`,
/// which changes no weight (a capped pixel alone makes the patch distance
/// at least `EXP_CUTOFF`) and bounds the running sums.
const EXP_CUTOFF: f64 = 746.0;
/// Largest accepted `search_radius`.
pub const MAX_SEARCH_RADIUS: usize = 30;
/// Largest accepted `patch_radius`.
pub const MAX_PATCH_RADIUS: usize = 10;
/// "No sample" in the upsampling's sample map.
const NO_SAMPLE: usize = usize::MAX;

/// An optional confidence map must have the depth map's size.
fn check_confidence(confidence: Option<&Confidence>, depth: &DepthMap) -> Result<(), NodeError> {
    match confidence {
        Some(c) => same_size(
            "confidence",
            "a confidence map",
            c.dims(),
            "the depth map",
            depth.dims(),
        ),
        None => Ok(()),
    }
}

// ---------------------------------------------------------------------------
// Parameters
// ---------------------------------------------------------------------------

node_params! {
    /// Parameters of the `NLMeansDepth` node ([`prune_outliers`] then
    /// [`nlmeans_filter`]).
    pub struct NLMeansDepthParams {
        /// Radius of the search window W_i in pixels (eq. 1): candidates come
        /// from a (2r+1) x (2r+1) window, 5 gives 11x11.
        pub search_radius: usize = 5usize, ParamKind::Int { min: 0, max: 30 };
        /// Radius of the compared patches N in pixels (eq. 2): 2 gives 5x5.
        pub patch_radius: usize = 2usize, ParamKind::Int { min: 0, max: 10 };
        /// Color filtering parameter h (eq. 2), in units of the guide feature
        /// sqrt(c / (1 + c)) of each linear channel (in [0, 1)): the weight
        /// is exp(-mean patch distance), the distance of one pixel being the
        /// sum over channels of squared differences / h_color^2.
        pub h_color: f64 = 0.1, ParamKind::Float { min: 1e-4, max: 100.0 };
        /// Depth filtering parameter in metres: depth patch differences
        /// (eq. 5) and the discontinuity factor xi (eq. 3) enter as
        /// (dz / h_depth)^2.
        pub h_depth: f64 = 0.05, ParamKind::Float { min: 1e-6, max: 1e4 };
        /// Prune outliers (prune_outliers) before filtering; pruned pixels
        /// become holes with confidence 0.
        pub prune: bool = true, ParamKind::Bool;
        /// Radius in pixels of the neighbourhood whose predictions model a
        /// pixel's depth in the outlier test.
        pub outlier_radius: usize = 2usize, ParamKind::Int { min: 1, max: 10 };
        /// Prior probability that a measurement is an outlier (weight of the
        /// uniform component of the mixture).
        pub outlier_prior: f64 = 0.05, ParamKind::Float { min: 1e-6, max: 0.999 };
        /// A pixel whose posterior outlier probability exceeds this becomes a hole.
        pub outlier_threshold: f64 = 0.5, ParamKind::Float { min: 0.0, max: 1.0 };
        /// Constant part of the depth noise standard deviation, metres (the
        /// normal component of the mixture).
        pub noise_sigma_m: f64 = 0.01, ParamKind::Float { min: 1e-6, max: 100.0 };
        /// Part of the depth noise standard deviation proportional to depth.
        pub noise_sigma_rel: f64 = 0.01, ParamKind::Float { min: 0.0, max: 10.0 };
    }
}

node_params! {
    /// Parameters of the `NLMeansUpsample` node ([`nlmeans_upsample`]).
    pub struct NLMeansUpsampleParams {
        /// Radius of the search window in high-resolution pixels (eq. 4); it
        /// should be at least the upsampling factor so that every window
        /// holds low-resolution samples (remaining holes are inpainted, see
        /// `iterations`). 5 gives 11x11.
        pub search_radius: usize = 5usize, ParamKind::Int { min: 1, max: 30 };
        /// Radius of the color patches in high-resolution pixels (the weights
        /// w^(u) of eq. 4): 2 gives 5x5.
        pub patch_radius: usize = 2usize, ParamKind::Int { min: 0, max: 10 };
        /// Radius of the depth patches in low-resolution pixels (the weights
        /// w(i_low, j_low) of eq. 4, chosen for the depth resolution): 1
        /// gives 3x3.
        pub low_patch_radius: usize = 1usize, ParamKind::Int { min: 0, max: 10 };
        /// Color filtering parameter (see `NLMeansDepth`), guide feature units.
        pub h_color: f64 = 0.1, ParamKind::Float { min: 1e-4, max: 100.0 };
        /// Depth filtering parameter in metres (see `NLMeansDepth`).
        pub h_depth: f64 = 0.05, ParamKind::Float { min: 1e-6, max: 1e4 };
        /// Linear blend of eq. 4: weight = (1 - alpha) w(i_low, j_low) +
        /// alpha w^(u)(i, j); 0 uses only the low-resolution depth
        /// similarity, 1 only the high-resolution color similarity.
        pub alpha: f64 = 0.9, ParamKind::Float { min: 0.0, max: 1.0 };
        /// Prune outliers (flying pixels, spikes) of the low-resolution depth
        /// first, as the paper does before the transformation.
        pub prune: bool = true, ParamKind::Bool;
        /// Outlier test neighbourhood radius, low-resolution pixels.
        pub outlier_radius: usize = 2usize, ParamKind::Int { min: 1, max: 10 };
        /// Prior probability of an outlier.
        pub outlier_prior: f64 = 0.05, ParamKind::Float { min: 1e-6, max: 0.999 };
        /// Posterior outlier probability above which a sample is dropped.
        pub outlier_threshold: f64 = 0.5, ParamKind::Float { min: 0.0, max: 1.0 };
        /// Constant part of the depth noise standard deviation, metres.
        pub noise_sigma_m: f64 = 0.01, ParamKind::Float { min: 1e-6, max: 100.0 };
        /// Part of the depth noise standard deviation proportional to depth.
        pub noise_sigma_rel: f64 = 0.01, ParamKind::Float { min: 0.0, max: 10.0 };
        /// Inpainting iterations (eq. 5) for high-resolution pixels left
        /// without an estimate (holes of the low-resolution depth, windows
        /// without samples); 0 leaves them as holes.
        pub iterations: usize = 16usize, ParamKind::Int { min: 0, max: 10000 };
    }
}

node_params! {
    /// Parameters of the `NLMeansInpaint` node ([`nlmeans_inpaint`]).
    pub struct NLMeansInpaintParams {
        /// Radius of the search window in pixels; each iteration fills the
        /// holes within this distance of known pixels. 5 gives 11x11.
        pub search_radius: usize = 5usize, ParamKind::Int { min: 1, max: 30 };
        /// Radius of the compared patches in pixels: 2 gives 5x5.
        pub patch_radius: usize = 2usize, ParamKind::Int { min: 0, max: 10 };
        /// Color filtering parameter (see `NLMeansDepth`), guide feature
        /// units. Smaller than for filtering: a hole has no depth of its own,
        /// so the color alone must tell which surface it belongs to.
        pub h_color: f64 = 0.05, ParamKind::Float { min: 1e-4, max: 100.0 };
        /// Depth filtering parameter in metres (see `NLMeansDepth`).
        pub h_depth: f64 = 0.05, ParamKind::Float { min: 1e-6, max: 1e4 };
        /// Maximum number of iterations; stops earlier when no hole is left
        /// or an iteration fills nothing.
        pub iterations: usize = 64usize, ParamKind::Int { min: 0, max: 10000 };
        /// Far-depth prior (Sec. 2.3): multiply each weight by
        /// (z_j / z_max)^2, favouring the background, for disocclusions.
        pub far_prior: bool = false, ParamKind::Bool;
    }
}

/// Parameters of [`prune_outliers`] (the outlier fields of the node
/// parameter structs; see [`NLMeansDepthParams::prune_params`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PruneParams {
    /// Neighbourhood radius in pixels (at least 1).
    pub radius: usize,
    /// Prior probability `pi` of an outlier, in `(0, 1)`.
    pub prior: f64,
    /// Posterior outlier probability above which a pixel becomes a hole.
    pub threshold: f64,
    /// Constant part of the noise standard deviation, metres (positive).
    pub sigma_m: f64,
    /// Part of the noise standard deviation proportional to depth.
    pub sigma_rel: f64,
}

impl Default for PruneParams {
    fn default() -> Self {
        NLMeansDepthParams::default().prune_params()
    }
}

impl NLMeansDepthParams {
    /// The outlier-test fields.
    pub fn prune_params(&self) -> PruneParams {
        PruneParams {
            radius: self.outlier_radius,
            prior: self.outlier_prior,
            threshold: self.outlier_threshold,
            sigma_m: self.noise_sigma_m,
            sigma_rel: self.noise_sigma_rel,
        }
    }
}

impl NLMeansUpsampleParams {
    /// The outlier-test fields.
    pub fn prune_params(&self) -> PruneParams {
        PruneParams {
            radius: self.outlier_radius,
            prior: self.outlier_prior,
            threshold: self.outlier_threshold,
            sigma_m: self.noise_sigma_m,
            sigma_rel: self.noise_sigma_rel,
        }
    }
}

impl PruneParams {
    fn check(&self) -> Result<(), NodeError> {
        if self.radius == 0 || self.radius > MAX_PATCH_RADIUS {
            return Err(NodeError::param(
                "outlier_radius",
                format!("must be in [1, {MAX_PATCH_RADIUS}]"),
            ));
        }
        if !(self.prior > 0.0 && self.prior < 1.0) {
            return Err(NodeError::param("outlier_prior", "must be in (0, 1)"));
        }
        if self.threshold.is_nan() {
            return Err(NodeError::param("outlier_threshold", "must be a number"));
        }
        if !(self.sigma_m.is_finite() && self.sigma_m > 0.0) {
            return Err(NodeError::param(
                "noise_sigma_m",
                "must be finite and positive",
            ));
        }
        if !(self.sigma_rel.is_finite() && self.sigma_rel >= 0.0) {
            return Err(NodeError::param(
                "noise_sigma_rel",
                "must be finite and non-negative",
            ));
        }
        Ok(())
    }
}

/// The NL-means parameters every pass shares, checked.
#[derive(Debug, Clone, Copy)]
struct Core {
    search: usize,
    patch: usize,
    inv_hc2: f64,
    inv_hd2: f64,
}

impl Core {
    fn new(search: usize, patch: usize, h_color: f64, h_depth: f64) -> Result<Self, NodeError> {
        if search > MAX_SEARCH_RADIUS {
            return Err(NodeError::param(
                "search_radius",
                format!("must be at most {MAX_SEARCH_RADIUS}"),
            ));
        }
        if patch > MAX_PATCH_RADIUS {
            return Err(NodeError::param(
                "patch_radius",
                format!("must be at most {MAX_PATCH_RADIUS}"),
            ));
        }
        // Guards of the divisions below: h > 0 and finite.
        if !(h_color.is_finite() && h_color > 0.0) {
            return Err(NodeError::param("h_color", "must be finite and positive"));
        }
        if !(h_depth.is_finite() && h_depth > 0.0) {
            return Err(NodeError::param("h_depth", "must be finite and positive"));
        }
        Ok(Self {
            search,
            patch,
            inv_hc2: 1.0 / (h_color * h_color),
            inv_hd2: 1.0 / (h_depth * h_depth),
        })
    }
}

// ---------------------------------------------------------------------------
// Inputs
// ---------------------------------------------------------------------------

/// Patch-distance feature of one linear color channel: `sqrt(c / (1 + c))`,
/// in `[0, 1)`; NaN and negative values count as 0, `+inf` as 1.
#[inline]
fn guide_feature(c: f32) -> f32 {
    if c.is_nan() || c <= 0.0 {
        0.0
    } else if c.is_infinite() {
        1.0
    } else {
        // Guard: 1 + c >= 1.
        (c / (1.0 + c)).sqrt()
    }
}

fn guide_features(color: &ColorImage) -> Vec<[f32; 3]> {
    color
        .as_slice()
        .par_iter()
        .map(|c| c.map(guide_feature))
        .collect()
}

/// Depth with holes as 0, and per-pixel confidence: the given confidence
/// (NaN as 0, clamped to `[0, 1]`, 1 when absent) at valid pixels, 0 at holes.
fn sanitize(depth: &DepthMap, confidence: Option<&Confidence>) -> (Vec<f32>, Vec<f32>) {
    let z: Vec<f32> = depth
        .as_slice()
        .iter()
        .map(|z| if DepthMap::is_valid(*z) { *z } else { 0.0 })
        .collect();
    let c = z
        .iter()
        .enumerate()
        .map(|(i, z)| {
            if *z > 0.0 {
                let c = confidence.map_or(1.0, |c| c.as_slice()[i]);
                if c.is_nan() { 0.0 } else { c.clamp(0.0, 1.0) }
            } else {
                0.0
            }
        })
        .collect();
    (z, c)
}

fn image<T, K>(w: usize, h: usize, data: Vec<T>) -> Result<Image<T, K>, NodeError> {
    Ok(Image::from_vec(w, h, data)?)
}

// ---------------------------------------------------------------------------
// Outlier pruning
// ---------------------------------------------------------------------------

/// Normal density of a deviation `d` with variance `var > 0`.
#[inline]
fn normal_pdf(d: f64, var: f64) -> f64 {
    // Guard: var > 0 (sigma_m > 0 is checked).
    (-0.5 * d * d / var).exp() / (std::f64::consts::TAU * var).sqrt()
}

/// Prunes outliers with the paper's mixture model (Sec. 2.2, after its
/// reference [12]): the conditional density of a pixel's depth given its
/// neighbourhood without itself, `p(v(i) | v(N_i*))`, is a mixture of a
/// normal for valid measurements and a uniform for outliers,
///
/// `p = (1 - pi) * N(v(i); predictions, sigma^2) + pi * U`,
///
/// and a pixel whose posterior outlier probability
/// `pi U / p` exceeds `threshold` becomes a hole (0) with confidence 0.
///
/// - The normal component is a kernel density over the depths the
///   neighbours predict for the pixel. Predictions are made in inverse depth,
///   which is affine in the image for planes, so planes at any slant are
///   predicted exactly: the midpoint of each opposite pair of neighbours
///   (`(1/v(i+k) + 1/v(i-k)) / 2`, variance `1.5 sigma^2` with the pixel's
///   own noise) and the one-sided extrapolation along each direction
///   (`2/v(i+k) - 1/v(i+2k)`, variance `6 sigma^2`), which lets pixels at
///   depth edges be predicted from their own side. Each prediction is
///   weighted by the product of its neighbours' confidences;
///   `sigma = sigma_m + sigma_rel * z` at the predicted depth.
/// - The uniform component spreads over the depth range of the image's
///   valid pixels, at least `8 sigma(z_max)` wide (so constant depth is
///   never an outlier).
/// - A pixel without any prediction (no valid neighbours) cannot be judged
///   and is kept.
///
/// Kept pixels have confidence `zeta(i) (1 - P(outlier))`; values are not
/// changed. Pixels with a valid depth but confidence 0 are passed through.
///
/// ```
/// use depthgraph_nodes::depth::nlmeans::{prune_outliers, PruneParams};
/// use depthgraph_graph::value::DepthMap;
/// let mut depth = DepthMap::from_fn(7, 7, |x, _| 2.0 + 0.01 * x as f32);
/// *depth.get_mut(3, 3) = 5.0; // a spike
/// let (d, c) = prune_outliers(&depth, None, &PruneParams::default()).unwrap();
/// assert_eq!(*d.get(3, 3), 0.0);
/// assert_eq!(*c.get(3, 3), 0.0);
/// assert_eq!(*d.get(1, 1), 2.01); // the plane is kept as it is
/// assert!(*c.get(1, 1) > 0.9);
/// ```
pub fn prune_outliers(
    depth: &DepthMap,
    confidence: Option<&Confidence>,
    p: &PruneParams,
) -> Result<(DepthMap, Confidence), NodeError> {
    p.check()?;
    check_confidence(confidence, depth)?;
    let (w, h) = depth.dims();
    let (z, c) = sanitize(depth, confidence);
    let mut out_z = z.clone();
    let mut out_c = c.clone();
    if w == 0 || h == 0 {
        return Ok((image(w, h, out_z)?, image(w, h, out_c)?));
    }
    // Inverse depths; 0 at holes (never read there: confidence 0).
    let q: Vec<f64> = z
        .iter()
        .map(|z| if *z > 0.0 { 1.0 / *z as f64 } else { 0.0 })
        .collect();
    let (zmin, zmax) = z
        .iter()
        .zip(&c)
        .filter(|(_, c)| **c > 0.0)
        .fold((f64::INFINITY, 0.0f64), |(lo, hi), (z, _)| {
            (lo.min(*z as f64), hi.max(*z as f64))
        });
    if zmax <= 0.0 {
        return Ok((image(w, h, out_z)?, image(w, h, out_c)?));
    }
    let sigma = |z: f64| p.sigma_m + p.sigma_rel * z;
    // Guard: sigma_m > 0 makes the range positive.
    let uniform = 1.0 / (zmax - zmin).max(8.0 * sigma(zmax));
    let pi_u = p.prior * uniform;
    let r = p.radius as isize;
    let mut sym = Vec::new();
    let mut ext = Vec::new();
    for ky in -r..=r {
        for kx in -r..=r {
            if ky > 0 || (ky == 0 && kx > 0) {
                sym.push((kx, ky));
            }
            if (kx, ky) != (0, 0) && 2 * kx.abs() <= r && 2 * ky.abs() <= r {
                ext.push((kx, ky));
            }
        }
    }
    let idx = |x: isize, y: isize| -> Option<usize> {
        if x < 0 || y < 0 || x >= w as isize || y >= h as isize {
            return None;
        }
        let i = y as usize * w + x as usize;
        (c[i] > 0.0).then_some(i)
    };
    out_z
        .par_chunks_mut(w)
        .zip(out_c.par_chunks_mut(w))
        .enumerate()
        .for_each(|(y, (row_z, row_c))| {
            let y = y as isize;
            for x in 0..w {
                let i = y as usize * w + x;
                if c[i] <= 0.0 {
                    continue;
                }
                let xi = x as isize;
                let zi = z[i] as f64;
                let (mut num, mut den) = (0.0f64, 0.0f64);
                let mut add = |qp: f64, var_factor: f64, wgt: f64| {
                    if qp > 0.0 && qp.is_finite() {
                        let zp = 1.0 / qp; // guard: qp > 0
                        let s = sigma(zp);
                        num += wgt * normal_pdf(zi - zp, var_factor * s * s);
                        den += wgt;
                    }
                };
                for &(kx, ky) in &sym {
                    if let (Some(a), Some(b)) = (idx(xi + kx, y + ky), idx(xi - kx, y - ky)) {
                        add(0.5 * (q[a] + q[b]), 1.5, c[a] as f64 * c[b] as f64);
                    }
                }
                for &(kx, ky) in &ext {
                    if let (Some(a), Some(b)) = (idx(xi + kx, y + ky), idx(xi + 2 * kx, y + 2 * ky))
                    {
                        add(2.0 * q[a] - q[b], 6.0, c[a] as f64 * c[b] as f64);
                    }
                }
                if den <= 0.0 {
                    continue; // no evidence: kept as it is
                }
                let p_valid = num / den; // guard: den > 0
                // Guard: pi_u > 0 (prior > 0, uniform > 0).
                let p_out = pi_u / (pi_u + (1.0 - p.prior) * p_valid);
                if p_out > p.threshold {
                    row_z[x] = 0.0;
                    row_c[x] = 0.0;
                } else {
                    row_c[x] = (c[i] as f64 * (1.0 - p_out)) as f32;
                }
            }
        });
    Ok((image(w, h, out_z)?, image(w, h, out_c)?))
}

// ---------------------------------------------------------------------------
// The NL-means pass
// ---------------------------------------------------------------------------

/// Running sums of one target pixel.
///
/// Weights are `exp(e)` for an exponent `e <= 0` (minus the patch distance
/// and the discontinuity term). To keep them from underflowing all together
/// (small `h`, unusual patches) each group of sums is kept relative to the
/// largest exponent seen so far and rescaled when a larger one arrives (the
/// running-maximum trick of log-sum-exp): the ratios of eq. 1 are unchanged
/// and the best candidate always weighs 1, so an estimate exists whenever a
/// source does.
#[derive(Debug, Clone, Copy)]
struct Acc {
    /// Largest exponent of all candidates; reference of `sim`, `sim_conf`.
    ms: f64,
    /// `sum_j s(i, j)`: similarity weights (without `zeta(j)`).
    sim: f64,
    /// `sum_j s(i, j) zeta(j)`.
    sim_conf: f64,
    /// Largest exponent of the sources (confidence > 0); reference of `w`, `wv`.
    mw: f64,
    /// `Z_i = sum_j w(i, j)`, the weights of eq. 1.
    w: f64,
    /// `sum_j w(i, j) v(j)`.
    wv: f64,
    /// Range of the values with a positive weight.
    lo: f32,
    hi: f32,
}

impl Acc {
    const EMPTY: Acc = Acc {
        ms: f64::NEG_INFINITY,
        sim: 0.0,
        sim_conf: 0.0,
        mw: f64::NEG_INFINITY,
        w: 0.0,
        wv: 0.0,
        lo: f32::INFINITY,
        hi: f32::NEG_INFINITY,
    };

    /// Adds a candidate with similarity `exp(e)`, confidence `conf` (0 for
    /// a hole: it only counts in the confidence), extra weight factor
    /// `prior > 0` and value `v`. Candidates with `e = -inf` (or NaN) weigh
    /// nothing and are skipped.
    #[inline]
    fn add(&mut self, e: f64, conf: f32, prior: f64, v: f32) {
        if e.is_nan() || e == f64::NEG_INFINITY {
            return;
        }
        if e > self.ms {
            // exp(-inf) = 0 for the first candidate: the sums are 0 anyway.
            let k = (self.ms - e).exp();
            self.sim *= k;
            self.sim_conf *= k;
            self.ms = e;
        }
        let s = (e - self.ms).exp();
        self.sim += s;
        if conf <= 0.0 {
            return;
        }
        self.sim_conf += s * conf as f64;
        if e > self.mw {
            let k = (self.mw - e).exp();
            self.w *= k;
            self.wv *= k;
            self.mw = e;
        }
        let rel = if self.mw == self.ms {
            s
        } else {
            (e - self.mw).exp()
        };
        let wgt = rel * conf as f64 * prior;
        if wgt > 0.0 {
            self.w += wgt;
            self.wv += wgt * v as f64;
            self.lo = self.lo.min(v);
            self.hi = self.hi.max(v);
        }
    }

    /// The estimate of eq. 1 and its confidence; `None` when no source had
    /// a positive weight (fallback of the callers).
    fn finish(&self) -> Option<(f32, f32)> {
        // Guard of the division: Z_i > 0 and finite.
        if !(self.w > 0.0 && self.w.is_finite()) {
            return None;
        }
        // Clamped to the averaged values: rounding never leaves their range.
        let v = ((self.wv / self.w) as f32).max(self.lo).min(self.hi);
        if !DepthMap::is_valid(v) {
            return None;
        }
        // Guard: sim >= 1 (the largest candidate weighs 1) once a source was added.
        let conf = if self.sim > 0.0 {
            (self.sim_conf / self.sim) as f32
        } else {
            0.0
        };
        // A filled pixel keeps a positive confidence so it is never taken for a hole.
        Some((v, conf.clamp(f32::MIN_POSITIVE, 1.0)))
    }
}

/// What a pass does with a candidate pair.
trait PairKernel: Sync {
    /// Adds candidate `j` to the sums of target `i`; `d >= 0` is their mean
    /// patch distance (already divided by the h's).
    fn add(&self, i: usize, j: usize, d: f64, acc: &mut Acc);
}

/// One NL-means pass over a `w` x `h` grid.
struct Pass<'a> {
    w: usize,
    h: usize,
    /// Guide features, `w * h`.
    guide: &'a [[f32; 3]],
    /// Depth and confidence for the depth patch term (eq. 5), or none.
    depth: Option<(&'a [f32], &'a [f32])>,
    core: Core,
}

/// Sums of one band of rows, columns `[xa, xa + bw)`.
struct BandOut {
    y0: usize,
    xa: usize,
    bw: usize,
    acc: Vec<Acc>,
}

/// Radii of the nested boxes whose average is the patch kernel (see
/// [`PatchKernel`]).
fn box_radii(r: usize) -> Vec<usize> {
    let mut radii = vec![0, r.div_ceil(2), r];
    radii.dedup();
    radii
}

/// The patch kernel: the average of the box means over the radii of
/// [`box_radii`], a centre-weighted approximation of the paper's Gaussian
/// `G_a` (for radius 2 the centre pixel weighs 0.38, the 8 pixels around it
/// 0.05 each, the outer 16 pixels 0.013 each) that keeps box sums.
struct PatchKernel {
    radii: Vec<usize>,
    /// Weight of one pixel of each box: `1 / (boxes * area)`.
    coef: Vec<f64>,
    /// Per-pixel distances are capped here: the smallest pixel weight times
    /// the cap is [`EXP_CUTOFF`], so the cap changes no weight.
    cap: f64,
}

impl PatchKernel {
    fn new(r: usize) -> Self {
        let radii = box_radii(r);
        let nb = radii.len() as f64;
        // Guard: nb >= 1 and every area >= 1.
        let coef: Vec<f64> = radii
            .iter()
            .map(|s| 1.0 / (nb * ((2 * s + 1) * (2 * s + 1)) as f64))
            .collect();
        let w_min = coef.iter().copied().fold(f64::INFINITY, f64::min);
        Self {
            radii,
            coef,
            cap: EXP_CUTOFF / w_min,
        }
    }
}

/// Computes the sums of every target pixel of rows `[y0, y1)`.
fn band<K: PairKernel>(pass: &Pass, targets: &[bool], kernel: &K, y0: usize, y1: usize) -> BandOut {
    let (w, h) = (pass.w, pass.h);
    let (mut xa, mut xb) = (w, 0);
    for y in y0..y1 {
        let row = &targets[y * w..(y + 1) * w];
        if let Some(first) = row.iter().position(|t| *t) {
            xa = xa.min(first);
        }
        if let Some(last) = row.iter().rposition(|t| *t) {
            xb = xb.max(last + 1);
        }
    }
    if xa >= xb {
        return BandOut {
            y0,
            xa: 0,
            bw: 0,
            acc: Vec::new(),
        };
    }
    let (bw, bh) = (xb - xa, y1 - y0);
    let r = pass.core.patch;
    let n = 2 * r + 1;
    let (ew, eh) = (bw + n - 1, bh + n - 1);
    let pk = PatchKernel::new(r);
    let nb = pk.radii.len();
    let (inv_hc2, inv_hd2) = (pass.core.inv_hc2, pass.core.inv_hd2);
    let big_r = pass.core.search as isize;
    let clampi = |v: isize, len: usize| v.clamp(0, len as isize - 1) as usize;
    let cols: Vec<usize> = (0..ew)
        .map(|e| clampi(xa as isize - r as isize + e as isize, w))
        .collect();
    let mut cols_o = vec![0usize; ew];
    let mut d = vec![0.0f64; ew];
    // Horizontal box sums of every extended row, per box.
    let mut hs = vec![0.0f64; nb * eh * bw];
    // Vertical box sums of the current row, per box.
    let mut vs = vec![0.0f64; nb * bw];
    let mut acc = vec![Acc::EMPTY; bw * bh];
    for dy in -big_r..=big_r {
        // Rows of the band whose candidate row y + dy is inside the image.
        let t0 = (-(y0 as isize) - dy).max(0) as usize;
        let t1 = ((h as isize - y0 as isize - dy).min(bh as isize)).max(0) as usize;
        if t0 >= t1 {
            continue;
        }
        for dx in -big_r..=big_r {
            let c0 = (-(xa as isize) - dx).max(0) as usize;
            let c1 = ((w as isize - xa as isize - dx).min(bw as isize)).max(0) as usize;
            if c0 >= c1 {
                continue;
            }
            for (e, co) in cols_o.iter_mut().enumerate() {
                *co = clampi(xa as isize - r as isize + e as isize + dx, w);
            }
            // Per-pixel distances of the extended rows needed by rows [t0, t1),
            // then horizontal box sums.
            for er in t0..t1 + n - 1 {
                let y = clampi(y0 as isize - r as isize + er as isize, h);
                let yo = clampi(y0 as isize - r as isize + er as isize + dy, h);
                let g = &pass.guide[y * w..(y + 1) * w];
                let go = &pass.guide[yo * w..(yo + 1) * w];
                for ((de, &p), &q) in d.iter_mut().zip(&cols).zip(&cols_o) {
                    let (a, b) = (g[p], go[q]);
                    let (d0, d1, d2) = (a[0] - b[0], a[1] - b[1], a[2] - b[2]);
                    *de = (d0 * d0 + d1 * d1 + d2 * d2) as f64 * inv_hc2;
                }
                if let Some((z, c)) = pass.depth {
                    let (zr, cr) = (&z[y * w..(y + 1) * w], &c[y * w..(y + 1) * w]);
                    let (zo, co) = (&z[yo * w..(yo + 1) * w], &c[yo * w..(yo + 1) * w]);
                    for ((de, &p), &q) in d.iter_mut().zip(&cols).zip(&cols_o) {
                        let cc = cr[p] * co[q];
                        if cc > 0.0 {
                            let dz = zr[p] as f64 - zo[q] as f64;
                            *de += cc as f64 * dz * dz * inv_hd2;
                        }
                    }
                }
                for de in d.iter_mut() {
                    *de = de.min(pk.cap);
                }
                for (b, &sr) in pk.radii.iter().enumerate() {
                    // Box of radius sr centred on extended column x + r.
                    let (lo, len) = (r - sr, 2 * sr + 1);
                    let hrow = &mut hs[(b * eh + er) * bw..(b * eh + er + 1) * bw];
                    let mut s: f64 = d[lo..lo + len].iter().sum();
                    hrow[0] = s;
                    for x in 1..bw {
                        s += d[lo + x + len - 1] - d[lo + x - 1];
                        hrow[x] = s;
                    }
                }
            }
            // Vertical box sums and the kernel.
            for t in t0..t1 {
                for (b, &sr) in pk.radii.iter().enumerate() {
                    let v = &mut vs[b * bw..(b + 1) * bw];
                    let plane = &hs[b * eh * bw..(b + 1) * eh * bw];
                    // Rows t + r - sr ..= t + r + sr of the extended band.
                    let (lo, len) = (t + r - sr, 2 * sr + 1);
                    if t == t0 {
                        v.copy_from_slice(&plane[lo * bw..(lo + 1) * bw]);
                        for k in 1..len {
                            let row = &plane[(lo + k) * bw..(lo + k + 1) * bw];
                            for (vx, hv) in v.iter_mut().zip(row) {
                                *vx += hv;
                            }
                        }
                    } else {
                        let add = &plane[(lo + len - 1) * bw..(lo + len) * bw];
                        let sub = &plane[(lo - 1) * bw..lo * bw];
                        for ((vx, a), s) in v.iter_mut().zip(add).zip(sub) {
                            *vx += a - s;
                        }
                    }
                }
                let y = y0 + t;
                let yj = (y as isize + dy) as usize;
                let trow = &targets[y * w..(y + 1) * w];
                for cidx in c0..c1 {
                    let x = xa + cidx;
                    if !trow[x] {
                        continue;
                    }
                    let xj = (x as isize + dx) as usize;
                    let mut dist = 0.0;
                    for (b, coef) in pk.coef.iter().enumerate() {
                        dist += coef * vs[b * bw + cidx].max(0.0);
                    }
                    kernel.add(y * w + x, yj * w + xj, dist, &mut acc[t * bw + cidx]);
                }
            }
        }
    }
    BandOut { y0, xa, bw, acc }
}

/// Runs a pass over every target pixel and hands each target's sums to
/// `sink` (row by row, in order), reporting progress in `[0, 1]` after every
/// wave of bands.
fn run_pass<K: PairKernel>(
    pass: &Pass,
    targets: &[bool],
    kernel: &K,
    progress: &mut dyn FnMut(f32) -> Result<(), NodeError>,
    mut sink: impl FnMut(usize, &Acc),
) -> Result<(), NodeError> {
    let (w, h) = (pass.w, pass.h);
    if w == 0 || h == 0 {
        return Ok(());
    }
    let bands: Vec<(usize, usize)> = (0..h)
        .step_by(BAND_ROWS)
        .map(|y0| (y0, (y0 + BAND_ROWS).min(h)))
        .filter(|&(y0, y1)| targets[y0 * w..y1 * w].iter().any(|t| *t))
        .collect();
    let waves = bands.len().div_ceil(WAVE_BANDS).max(1);
    for (k, wave) in bands.chunks(WAVE_BANDS).enumerate() {
        let outs: Vec<BandOut> = wave
            .par_iter()
            .map(|&(y0, y1)| band(pass, targets, kernel, y0, y1))
            .collect();
        for out in &outs {
            if out.bw == 0 {
                continue;
            }
            for (t, row) in out.acc.chunks(out.bw).enumerate() {
                for (c, a) in row.iter().enumerate() {
                    let i = (out.y0 + t) * w + out.xa + c;
                    if targets[i] {
                        sink(i, a);
                    }
                }
            }
        }
        // Guard: waves >= 1.
        progress((k + 1) as f32 / waves as f32)?;
    }
    Ok(())
}

/// Kernel of the filter and the inpainting: sources are the pixels with
/// confidence, weighted by eq. 2/5 with the discontinuity factor (eq. 3)
/// and optionally the far-depth prior.
struct DepthKernel<'a> {
    z: &'a [f32],
    c: &'a [f32],
    inv_hd2: f64,
    /// `1 / z_ref` of the far-depth prior `(z_j / z_ref)^2`.
    far: Option<f64>,
}

impl PairKernel for DepthKernel<'_> {
    #[inline]
    fn add(&self, i: usize, j: usize, d: f64, acc: &mut Acc) {
        let cj = self.c[j];
        if cj <= 0.0 {
            acc.add(-d, 0.0, 1.0, 0.0);
            return;
        }
        let zj = self.z[j];
        // Discontinuity factor xi_ij (eq. 3) where the centre has depth.
        let xi = if self.c[i] > 0.0 {
            let dz = self.z[i] as f64 - zj as f64;
            dz * dz * self.inv_hd2
        } else {
            0.0
        };
        let prior = match self.far {
            Some(inv_ref) => {
                let r = zj as f64 * inv_ref;
                r * r
            }
            None => 1.0,
        };
        acc.add(-(d + xi), cj, prior, zj);
    }
}

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
/// Holes stay holes (use [`nlmeans_inpaint`] to fill them). The output
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
    mut on_progress: impl FnMut(f32) -> Result<(), NodeError>,
) -> Result<(DepthMap, Confidence), NodeError> {
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
    let pass = Pass {
        w,
        h,
        guide: &guide,
        depth: Some((&z, &c)),
        core,
    };
    let kernel = DepthKernel {
        z: &z,
        c: &c,
        inv_hd2: core.inv_hd2,
        far: None,
    };
    run_pass(&pass, &targets, &kernel, &mut on_progress, |i, acc| {
        // Fallback without any source: input value, confidence 0.
        if let Some((v, conf)) = acc.finish() {
            out_z[i] = v;
            out_c[i] = conf;
        }
    })?;
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
    if !p.prune {
        return nlmeans_filter_with(depth, confidence, guide_color, p, on_progress);
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
    nlmeans_filter_with(&d, Some(&c), guide_color, p, on_progress)
}

// ---------------------------------------------------------------------------
// Inpainting
// ---------------------------------------------------------------------------

/// Holes that have a source (confidence > 0) within `r` pixels (Chebyshev),
/// from a summed-area table of the sources.
fn reachable_holes(z: &[f32], c: &[f32], w: usize, h: usize, r: usize) -> Vec<bool> {
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
fn inpaint_state(
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

// ---------------------------------------------------------------------------
// Upsampling
// ---------------------------------------------------------------------------

/// For each pixel `a` of an axis of `n_from` pixels, the pixel of the other
/// camera's axis (`n_to` pixels) that the ray through `a`'s centre falls in:
/// `u' = (a + 0.5 - c) / f * f' + c'`, `None` outside.
fn axis_map(n_from: usize, f: f64, c: f64, f_to: f64, c_to: f64, n_to: usize) -> Vec<usize> {
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

/// Kernel of eq. 4: candidates are the high-resolution pixels holding a
/// low-resolution sample.
struct UpsampleKernel<'a> {
    w: usize,
    /// Low-resolution sample at each high-resolution pixel, or `NO_SAMPLE`.
    sample_at: &'a [usize],
    /// Low-resolution column / row of each high-resolution column / row.
    lo_col: &'a [usize],
    lo_row: &'a [usize],
    z: &'a [f32],
    c: &'a [f32],
    lw: usize,
    lh: usize,
    low_patch: isize,
    inv_low_area: f64,
    inv_hd2: f64,
    /// `ln(alpha)` and `ln(1 - alpha)` of the blend (`-inf` for 0).
    ln_alpha: f64,
    ln_one_minus_alpha: f64,
}

impl UpsampleKernel<'_> {
    /// `-ln w(i_low, j_low)`: eq. 2/5 on low-resolution depth patches, with
    /// the discontinuity factor at the centres.
    fn low_distance(&self, a: usize, b: usize) -> f64 {
        let (ax, ay) = ((a % self.lw) as isize, (a / self.lw) as isize);
        let (bx, by) = ((b % self.lw) as isize, (b / self.lw) as isize);
        let cl = |v: isize, n: usize| v.clamp(0, n as isize - 1) as usize;
        let r = self.low_patch;
        let mut s = 0.0f64;
        for ky in -r..=r {
            let ra = cl(ay + ky, self.lh) * self.lw;
            let rb = cl(by + ky, self.lh) * self.lw;
            for kx in -r..=r {
                let pa = ra + cl(ax + kx, self.lw);
                let pb = rb + cl(bx + kx, self.lw);
                let cc = self.c[pa] * self.c[pb];
                if cc > 0.0 {
                    let dz = self.z[pa] as f64 - self.z[pb] as f64;
                    s += cc as f64 * dz * dz;
                }
            }
        }
        let mut dist = s * self.inv_low_area * self.inv_hd2;
        if self.c[a] > 0.0 && self.c[b] > 0.0 {
            let dz = self.z[a] as f64 - self.z[b] as f64;
            dist += dz * dz * self.inv_hd2;
        }
        dist
    }
}

impl PairKernel for UpsampleKernel<'_> {
    #[inline]
    fn add(&self, i: usize, j: usize, d: f64, acc: &mut Acc) {
        let s = self.sample_at[j];
        if s == NO_SAMPLE {
            return;
        }
        // ln((1 - alpha) w + alpha w_u) computed in the log domain, so
        // neither term underflows alone: ln(0) = -inf drops a term.
        let color = self.ln_alpha - d;
        let depth = if self.ln_one_minus_alpha > f64::NEG_INFINITY {
            let (lx, ly) = (self.lo_col[i % self.w], self.lo_row[i / self.w]);
            if lx == NO_SAMPLE || ly == NO_SAMPLE {
                f64::NEG_INFINITY
            } else {
                self.ln_one_minus_alpha - self.low_distance(ly * self.lw + lx, s)
            }
        } else {
            f64::NEG_INFINITY
        };
        acc.add(log_add_exp(color, depth), self.c[s], 1.0, self.z[s]);
    }
}

/// `ln(exp(a) + exp(b))` without overflow or underflow; `-inf` when both are.
#[inline]
fn log_add_exp(a: f64, b: f64) -> f64 {
    let (hi, lo) = if a >= b { (a, b) } else { (b, a) };
    if lo == f64::NEG_INFINITY {
        return hi;
    }
    hi + (lo - hi).exp().ln_1p()
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
    mut on_progress: impl FnMut(f32) -> Result<(), NodeError>,
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
    let n_low = 2 * p.low_patch_radius + 1;
    let kernel = UpsampleKernel {
        w,
        sample_at: &sample_at,
        lo_col: &lo_col,
        lo_row: &lo_row,
        z: &lz,
        c: &lc,
        lw,
        lh,
        low_patch: p.low_patch_radius as isize,
        // Guard: n_low >= 1.
        inv_low_area: 1.0 / (n_low * n_low) as f64,
        inv_hd2: core.inv_hd2,
        ln_alpha: p.alpha.ln(),
        ln_one_minus_alpha: (1.0 - p.alpha).ln(),
    };
    let pass = Pass {
        w,
        h,
        guide: &guide,
        depth: None,
        core,
    };
    let targets = vec![true; w * h];
    let share = if p.iterations > 0 { 0.5 } else { 1.0 };
    run_pass(
        &pass,
        &targets,
        &kernel,
        &mut |f| on_progress(f * share),
        |i, acc| {
            if let Some((v, conf)) = acc.finish() {
                z[i] = v;
                c[i] = conf;
            }
        },
    )?;
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
            &mut |f| on_progress(0.5 + 0.5 * f),
        )?;
    }
    Ok((image(w, h, z)?, image(w, h, c)?, high_k))
}

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

fn eval_inpaint(
    ctx: &EvalCtx,
    i: NLMeansIn,
    p: &NLMeansInpaintParams,
) -> Result<Produced<NLMeansOut>, NodeError> {
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
        let confidence = match &i.confidence {
            Some(c) => Arc::clone(c),
            None => Arc::new(image(
                depth.width(),
                depth.height(),
                sanitize(depth, None).1,
            )?),
        };
        let out = NLMeansOut {
            depth: Arc::clone(depth),
            confidence,
        };
        return Ok(Produced::passthrough(out, "no holes to fill"));
    }
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
        1,
        "NL-means depth denoising guided by color, with outlier pruning (depth blur Sec. 2.2, eq. 1-3).\n\
         Outliers (spikes, flying pixels) are pruned with a normal + uniform mixture model and become holes; \
         the remaining depth is averaged over pixels with similar color and depth patches. Holes stay holes.",
        eval_depth,
    ))?;
    reg.register(PortedNode::new(
        "NLMeansUpsample",
        1,
        "Joint NL-means upsampling of low-resolution depth guided by high-resolution color (depth blur eq. 4).\n\
         Low-resolution samples are placed on the color grid and averaged with weights blending low-resolution \
         depth similarity and high-resolution color similarity (alpha); remaining holes are inpainted (eq. 5).",
        eval_upsample,
    ))?;
    reg.register(PortedNode::new(
        "NLMeansInpaint",
        1,
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
