//! High-dynamic-range radiance maps from exposure brackets (seed paper
//! realistic-depth-blur §2.1; P. Debevec, J. Malik, "Recovering High Dynamic
//! Range Radiance Maps from Photographs", SIGGRAPH 1997).
//!
//! # Model (Debevec & Malik §2.1)
//!
//! A pixel value is `Z_ij = f(E_i Δt_j)` (eq. 1): the camera response `f` of
//! the exposure, radiance `E_i` of pixel `i` times exposure time `Δt_j` of
//! image `j`. With `g = ln f^-1`, `g(Z_ij) = ln E_i + ln Δt_j` (eq. 2).
//!
//! - [`recover_response`] estimates `g` on the 256 levels `z = round(value *
//!   255)` of each channel by minimising the weighted objective (eq. 5, the
//!   weighted form of eq. 3)
//!
//!   `O = Σ_i Σ_j {w(Z_ij) [g(Z_ij) - ln E_i - ln Δt_j]}² + λ Σ_{z=1}^{254} [w(z) g''(z)]²`
//!
//!   with the hat weighting `w(z) = min(z, 255 - z)` (eq. 4, `Z_min = 0`,
//!   `Z_max = 255`) and `g''(z) = g(z-1) - 2 g(z) + g(z+1)`, subject to
//!   `g(128) = 0`. Note that `λ` multiplies the squared smoothness sum as
//!   written in eq. 5; the paper's MATLAB `gsolve` and OpenCV's
//!   `CalibrateDebevec` scale the smoothness *rows* by their lambda, so their
//!   `lambda = 10` is this module's `lambda = 100`. The default `λ = 1000`
//!   balances the 400 default samples like OpenCV's default does its 70.
//! - [`merge_hdr`] evaluates eq. 6 per pixel and channel:
//!   `ln E = Σ_j w(Z_j) (g(Z_j) - ln Δt_j) / Σ_j w(Z_j)`.
//!
//! `g` is only determined up to an additive constant per channel (the
//! constraint `g(128) = 0` picks one), so recovered radiance is known up to one
//! unknown factor per channel (a global scale and a white balance, as the
//! paper notes in §2.1). Compare recovered radiance with a reference only
//! after fitting that factor. A *given* curve ([`ResponseCurve::gamma`],
//! [`ResponseCurve::linear`]) is absolute: `g(255) = 0`, so the sensor
//! saturates where `E Δt = 1` (the convention of `SimulateBracket`).
//!
//! # Conventions
//!
//! - Stack images hold values in `[0, 1]` *after* the camera response (not
//!   linearised). Finite values outside `[0, 1]` are clipped; NaN and
//!   infinities mean "missing" (weight 0), e.g. the pure-blue borders of
//!   Debevec's memorial series once [`load_bracket`] masks them.
//! - `z = value * 255` is a real number in the merge (so 16-bit and float
//!   inputs keep their precision; `g` is interpolated linearly between levels)
//!   and is rounded to a level for the recovery.
//! - The weights have no floor: a saturated (`z = 255`) or black (`z = 0`)
//!   value says only that the exposure was out of range, and a floor would
//!   let such values pull the estimate. Pixels with no weight at all take the
//!   documented fallback of [`merge_hdr`] instead.
//! - Sums are accumulated in f64; the output is linear RGB f32.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use depthgraph_graph::node_params;
use depthgraph_graph::prelude::*;
use depthgraph_graph::registry::RegistryError;
use rayon::prelude::*;

/// Number of levels of the response curve (8-bit codes).
pub const LEVELS: usize = 256;
/// Highest level, `Z_max` of eq. 4.
const Z_MAX: f64 = 255.0;
/// Level fixed by the constraint `g(Z_MID) = 0`.
pub const Z_MID: usize = 128;

/// The hat weighting of eq. 4 on a real level `z` in `[0, 255]`:
/// `min(z, 255 - z)`, 0 at (and beyond) both ends and for NaN.
///
/// ```
/// use depthgraph_nodes::camera::hdr::hat_weight;
/// assert_eq!(hat_weight(0.0), 0.0);
/// assert_eq!(hat_weight(255.0), 0.0);
/// assert_eq!(hat_weight(100.0), 100.0);
/// assert_eq!(hat_weight(200.0), 55.0);
/// ```
#[inline]
pub fn hat_weight(z: f64) -> f64 {
    if z > 0.0 && z < Z_MAX {
        z.min(Z_MAX - z)
    } else {
        0.0
    }
}

/// Level of a stored value (`value * 255`, clipped to `[0, 255]`), or `None`
/// for a missing (non-finite) value.
#[inline]
fn level(v: f32) -> Option<f64> {
    if v.is_finite() {
        Some((v as f64).clamp(0.0, 1.0) * Z_MAX)
    } else {
        None
    }
}

// ---------------------------------------------------------------------------
// Response curves
// ---------------------------------------------------------------------------

/// A camera response as `g(z) = ln f^-1(z)` (eq. 2) on the 256 levels of each
/// channel: the log exposure `ln(E Δt)` that produces level `z`.
#[derive(Debug, Clone, PartialEq)]
pub struct ResponseCurve {
    /// `g[c][z]` for channel `c` (R, G, B) and level `z` in `0..256`.
    pub g: [[f64; LEVELS]; 3],
}

impl ResponseCurve {
    /// A known gamma camera: the inverse of [`crate::camera::response::response`]
    /// (the curve `SimulateBracket` applies), `g(z) = ln f^-1(z / 255)`, so
    /// `g(255) = 0`. A value 0 only says that the exposure was below half a
    /// level, so `g(0) = ln f^-1(0.5 / 255)` (finite, instead of `ln 0`).
    /// `gamma = 1` is [`ResponseCurve::linear`].
    pub fn gamma(gamma: f64) -> Self {
        let g: [f64; LEVELS] = std::array::from_fn(|z| {
            let v = if z == 0 { 0.5 } else { z as f64 } / Z_MAX;
            let x = crate::camera::response::inverse_response(v as f32, gamma as f32) as f64;
            // guard: the inverse of a positive value is positive; the floor only
            // protects the logarithm against a future change of the curve
            x.max(1e-30).ln()
        });
        Self { g: [g; 3] }
    }

    /// A linear camera: `g(z) = ln(z / 255)`, `g(0) = ln(0.5 / 255)`.
    pub fn linear() -> Self {
        Self::gamma(1.0)
    }

    /// `g` of channel `c` at the real level `z` (clipped to `[0, 255]`),
    /// interpolated linearly between levels.
    #[inline]
    pub fn eval(&self, c: usize, z: f64) -> f64 {
        let z = if z.is_nan() { 0.0 } else { z.clamp(0.0, Z_MAX) };
        let i = (z.floor() as usize).min(LEVELS - 2);
        let f = z - i as f64;
        let g = &self.g[c];
        g[i] + (g[i + 1] - g[i]) * f
    }

    /// The curve as a 256x1 Color image: pixel `x = z` holds `exp(g(z))` per
    /// channel, the relative exposure `E Δt` that gives level `z` (1 at
    /// `z = 128` for a recovered curve, 1 at `z = 255` for a given one).
    /// Plot it against `z`, save it with `SaveResponse`, or feed it to another
    /// `HdrMerge`'s `curve` input to merge other brackets of the same camera.
    pub fn to_image(&self) -> ColorImage {
        Image::from_fn(LEVELS, 1, |z, _| {
            std::array::from_fn(|c| (self.g[c][z].exp() as f32).min(f32::MAX))
        })
    }

    /// Reads a curve written by [`ResponseCurve::to_image`]; `port` names the
    /// input in errors. Every value must be finite and positive.
    pub fn from_image(img: &ColorImage, port: &str) -> Result<Self, NodeError> {
        if img.dims() != (LEVELS, 1) {
            return Err(NodeError::input(
                port,
                format!(
                    "is {}x{}; expected a 256x1 response curve (exp g(z) per channel, as HdrMerge's `curve` output)",
                    img.width(),
                    img.height()
                ),
            ));
        }
        let mut g = [[0.0; LEVELS]; 3];
        for (z, px) in img.as_slice().iter().enumerate() {
            for (c, v) in px.iter().enumerate() {
                if !(v.is_finite() && *v > 0.0) {
                    return Err(NodeError::input(
                        port,
                        format!("level {z}, channel {c}: {v} is not a positive finite exposure"),
                    ));
                }
                g[c][z] = (*v as f64).ln();
            }
        }
        Ok(Self { g })
    }
}

// ---------------------------------------------------------------------------
// Checks shared by recovery and merge
// ---------------------------------------------------------------------------

/// Checks counts, sizes and times of a stack; returns the image size.
fn check_stack(stack: &ExposureStack) -> Result<(usize, usize), NodeError> {
    let n = stack.images.len();
    if n == 0 {
        return Err(NodeError::input("stack", "holds no exposure"));
    }
    if stack.times_s.len() != n {
        return Err(NodeError::input(
            "stack",
            format!(
                "holds {n} images but {} exposure times",
                stack.times_s.len()
            ),
        ));
    }
    let dims = stack.images[0].dims();
    for (j, img) in stack.images.iter().enumerate() {
        if img.dims() != dims {
            return Err(NodeError::input(
                "stack",
                format!(
                    "image {j} is {}x{} but image 0 is {}x{}; every exposure must have the same size",
                    img.width(),
                    img.height(),
                    dims.0,
                    dims.1
                ),
            ));
        }
    }
    for (j, t) in stack.times_s.iter().enumerate() {
        if !(t.is_finite() && *t > 0.0) {
            return Err(NodeError::input(
                "stack",
                format!("exposure time {t} s of image {j} must be finite and positive"),
            ));
        }
    }
    Ok(dims)
}

// ---------------------------------------------------------------------------
// Recovery (eq. 3-5)
// ---------------------------------------------------------------------------

/// Parameters of [`recover_response`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ResponseParams {
    /// Pixels sampled per channel (`N` of eq. 5); the paper asks for
    /// `N (P - 1) > 255` with `P` exposures.
    pub samples: usize,
    /// Smoothness weight `λ` of eq. 5 (multiplies the squared sum; see
    /// `HdrMergeParams::lambda` for the relation to gsolve and OpenCV).
    pub lambda: f64,
}

impl Default for ResponseParams {
    fn default() -> Self {
        Self {
            samples: 400,
            lambda: 1000.0,
        }
    }
}

/// Candidate pixels for the recovery of channel `c`, chosen deterministically
/// so that they span the range of radiances and sit in flat regions.
///
/// 1. Candidates lie on a stratified grid of about `16 * samples` pixels.
/// 2. Each candidate with at least two valid values gets a brightness key,
///    the sum of its levels over the exposures (scaled up when some are
///    missing). For a monotone response this sum grows with radiance, so it
///    orders pixels by `E` without knowing `g`. Pixels black or saturated in
///    every exposure carry no information and are dropped.
/// 3. The key range is cut into `samples` equal bins; each non-empty bin gives
///    the candidate with the fewest missing values and then the smallest
///    local gradient in the middle exposure (Debevec & Malik §2.1 recommend
///    low-variance regions, which are robust to misregistration and blur).
/// 4. When fewer bins are filled than `samples`, further rounds take the
///    second best of every bin, then the third, ... so that large flat
///    regions (many pixels of one radiance, hence the same quantisation
///    error) never dominate the fit.
fn select_samples(stack: &ExposureStack, c: usize, samples: usize) -> Vec<usize> {
    let (w, h) = stack.images[0].dims();
    let n_px = w * h;
    if n_px == 0 || samples == 0 {
        return Vec::new();
    }
    let p = stack.images.len();
    // grid step so that about 16 * samples candidates lie on the grid
    let want = samples.saturating_mul(16).clamp(1, n_px);
    // guard: want >= 1
    let step = ((n_px as f64 / want as f64).sqrt()).max(1.0);
    let gx = ((w as f64 / step).ceil() as usize).max(1);
    let gy = ((h as f64 / step).ceil() as usize).max(1);
    // reference exposure for the flatness test: the median time
    let mut order: Vec<usize> = (0..p).collect();
    order.sort_by(|a, b| stack.times_s[*a].total_cmp(&stack.times_s[*b]));
    let reference = &stack.images[order[p / 2]];
    let at = |x: usize, y: usize| -> f64 { level(reference.get(x, y)[c]).unwrap_or(f64::INFINITY) };
    let full = (Z_MAX as usize * p) as u64;
    // (key, missing, gradient, pixel index)
    let mut cands: Vec<(u64, usize, f64, usize)> = Vec::with_capacity(gx * gy);
    for j in 0..gy {
        let y = (((j as f64 + 0.5) * step) as usize).min(h - 1);
        for i in 0..gx {
            let x = (((i as f64 + 0.5) * step) as usize).min(w - 1);
            let idx = y * w + x;
            let mut sum = 0u64;
            let mut valid = 0usize;
            for img in &stack.images {
                if let Some(z) = level(img.as_slice()[idx][c]) {
                    sum += z.round() as u64;
                    valid += 1;
                }
            }
            if valid < 2 {
                continue;
            }
            // guard: valid >= 2; scale a partial sum to all p exposures
            let key = sum * p as u64 / valid as u64;
            if key == 0 || key >= full {
                continue; // black or saturated everywhere: no information
            }
            let here = at(x, y);
            let gxd = (at((x + 1).min(w - 1), y) - here).abs();
            let gyd = (at(x, (y + 1).min(h - 1)) - here).abs();
            let grad = if (gxd + gyd).is_finite() {
                gxd + gyd
            } else {
                f64::MAX
            };
            cands.push((key, p - valid, grad, idx));
        }
    }
    if cands.is_empty() {
        return Vec::new();
    }
    // bin of each candidate; guard: full + 1 > 0 and key < full, so the bin is < samples
    let bin = |key: u64| {
        (((key as u128 * samples as u128) / (full as u128 + 1)) as usize).min(samples - 1)
    };
    // within a bin: fewest missing values, then flattest, then scan order
    cands.sort_by(|a, b| {
        (bin(a.0), a.1)
            .cmp(&(bin(b.0), b.1))
            .then(a.2.total_cmp(&b.2))
            .then(a.3.cmp(&b.3))
    });
    // rank of each candidate inside its bin
    let mut rank = vec![0usize; cands.len()];
    for k in 1..cands.len() {
        if bin(cands[k].0) == bin(cands[k - 1].0) {
            rank[k] = rank[k - 1] + 1;
        }
    }
    // round robin over the bins: the best of every bin, then the second best, ...
    let mut order: Vec<usize> = (0..cands.len()).collect();
    order.sort_by_key(|k| (rank[*k], bin(cands[*k].0)));
    let mut out: Vec<usize> = order.iter().take(samples).map(|k| cands[*k].3).collect();
    out.sort_unstable();
    out
}

/// Solves `A x = b` in place for a symmetric positive definite `A` (n x n,
/// row-major; only the lower triangle is read) by Cholesky factorisation.
/// `Err(j)` when pivot `j` is not positive.
fn cholesky_solve(a: &mut [f64], n: usize, b: &mut [f64]) -> Result<(), usize> {
    let dot = |x: &[f64], y: &[f64]| x.iter().zip(y).map(|(p, q)| p * q).sum::<f64>();
    for j in 0..n {
        let row_j = j * n;
        let d = a[row_j + j] - dot(&a[row_j..row_j + j], &a[row_j..row_j + j]);
        if !(d > 0.0 && d.is_finite()) {
            return Err(j);
        }
        let d = d.sqrt();
        a[row_j + j] = d;
        for i in (j + 1)..n {
            let row_i = i * n;
            let s = a[row_i + j] - dot(&a[row_i..row_i + j], &a[row_j..row_j + j]);
            a[row_i + j] = s / d; // guard: d > 0 checked above
        }
    }
    // L y = b
    for i in 0..n {
        let s = b[i] - dot(&a[i * n..i * n + i], &b[..i]);
        b[i] = s / a[i * n + i]; // guard: diagonal > 0 after the factorisation
    }
    // L^T x = y
    for i in (0..n).rev() {
        let mut s = b[i];
        for k in (i + 1)..n {
            s -= a[k * n + i] * b[k];
        }
        b[i] = s / a[i * n + i]; // guard: diagonal > 0
    }
    Ok(())
}

const CHANNEL: [&str; 3] = ["red", "green", "blue"];

/// Recovers `g` for channel `c` from the sampled pixels `idx` (eq. 5); see
/// [`recover_response`] for the solve.
fn recover_channel(
    stack: &ExposureStack,
    c: usize,
    idx: &[usize],
    lambda: f64,
) -> Result<[f64; LEVELS], NodeError> {
    const N: usize = LEVELS;
    let ln_t: Vec<f64> = stack.times_s.iter().map(|t| t.ln()).collect();
    let mut s = vec![0.0f64; N * N];
    let mut r = vec![0.0f64; N];
    let mut informative = 0usize;
    let mut used = 0usize;
    let mut obs: Vec<(usize, f64, f64)> = Vec::with_capacity(stack.images.len());
    for &i in idx {
        obs.clear();
        for (img, lt) in stack.images.iter().zip(&ln_t) {
            if let Some(z) = level(img.as_slice()[i][c]) {
                let z = z.round();
                let w = hat_weight(z);
                if w > 0.0 {
                    obs.push((z as usize, w * w, *lt));
                }
            }
        }
        let d: f64 = obs.iter().map(|o| o.1).sum();
        if d <= 0.0 {
            continue;
        }
        used += 1;
        if obs.iter().any(|o| o.0 != obs[0].0) {
            informative += 1;
        }
        // r_E = -Σ w² ln Δt
        let r_e: f64 = -obs.iter().map(|o| o.1 * o.2).sum::<f64>();
        for &(za, wa, lta) in &obs {
            s[za * N + za] += wa;
            r[za] += wa * lta;
            // - C D⁻¹ r_E with C[za] = -wa; guard: d > 0 checked above
            r[za] += wa * r_e / d;
            for &(zb, wb, _) in &obs {
                s[za * N + zb] -= wa * wb / d; // guard: d > 0
            }
        }
    }
    if informative == 0 {
        return Err(NodeError::input(
            "stack",
            format!(
                "{} channel: {}; the response cannot be recovered. Use response \"gamma\" or \"linear\", or connect a `curve`",
                CHANNEL[c],
                if used == 0 {
                    "no sampled pixel is well exposed (0 < value < 1) in any exposure".to_string()
                } else {
                    format!(
                        "none of the {used} usable samples changes level between its well-exposed exposures"
                    )
                }
            ),
        ));
    }
    // smoothness (eq. 5): λ [w(z) (g(z-1) - 2 g(z) + g(z+1))]²
    for z in 1..N - 1 {
        let wz = hat_weight(z as f64);
        let k = lambda * wz * wz;
        let a = [(z - 1, 1.0), (z, -2.0), (z + 1, 1.0)];
        for &(p, ap) in &a {
            for &(q, aq) in &a {
                s[p * N + q] += k * ap * aq;
            }
        }
    }
    // constraint g(128) = 0, weighted like an average diagonal entry (any
    // positive weight gives the same solution; this one keeps the scaling even)
    let trace: f64 = (0..N).map(|z| s[z * N + z]).sum();
    // guard: N > 0
    let mean_diag = (trace / N as f64).max(1.0);
    s[Z_MID * N + Z_MID] += mean_diag;
    let eps = 1e-10 * mean_diag;
    for z in 0..N {
        s[z * N + z] += eps;
    }
    cholesky_solve(&mut s, N, &mut r).map_err(|j| {
        NodeError::Invalid(format!(
            "{} channel: the response system is not positive definite (pivot {j}); the exposures do not determine the curve",
            CHANNEL[c]
        ))
    })?;
    if r.iter().any(|v| !v.is_finite()) {
        return Err(NodeError::Invalid(format!(
            "{} channel: the response solve gave non-finite values",
            CHANNEL[c]
        )));
    }
    // impose g(128) = 0 exactly (the solve meets it up to the ε bias)
    let shift = r[Z_MID];
    Ok(std::array::from_fn(|z| r[z] - shift))
}

/// Recovers the response `g` of each channel from a stack (eq. 3-5 of
/// Debevec & Malik), normalised so that `g(128) = 0`. Pixels are sampled per
/// channel, deterministically, spread over the radiance range and preferring
/// flat regions (`p.samples` of them).
///
/// The least-squares problem has unknowns `g(0..255)` and `ln E_i` for the
/// `N` samples. Its normal equations are built directly from the sparse rows
/// (a data row touches one `g(z)` and one `ln E_i`):
///
/// ```text
/// [ G    C ] [ g    ]   [ r_g ]      G = Σ w² e_z e_zᵀ + λ Σ w(z)² s_z s_zᵀ + κ e_128 e_128ᵀ
/// [ Cᵀ   D ] [ ln E ] = [ r_E ]      C[z, i] = -Σ_j w_ij² [Z_ij = z],  D = diag(Σ_j w_ij²)
/// ```
///
/// `D` is diagonal, so `ln E` is eliminated exactly (block LDLᵀ): the Schur
/// complement `S = G - C D⁻¹ Cᵀ` (256 x 256, dense) is factorised by Cholesky
/// in f64, whatever `N` is. Samples with `D_ii = 0` (no weighted value) are
/// left out first; they would make `D` singular and say nothing about `g`.
///
/// Conditioning: adding a constant to `g` and every `ln E_i` leaves the data
/// and smoothness terms unchanged, and the constraint `g(128) = 0` removes
/// exactly that direction. With `λ > 0` the smoothness rows (weights
/// `w(z) > 0` for `z = 1..254`) leave only affine curves `a (z - 128)` free,
/// and `a` is fixed as soon as one sample shows two different weighted levels
/// (checked: otherwise an error). `S` is then positive definite. A Tikhonov
/// term `ε I` with `ε = 1e-10` times the mean diagonal guards the
/// factorisation against rounding; its pull on `g` is of relative size 1e-10.
///
/// Errors: fewer than two exposures, all exposure times equal (the data then
/// say nothing about the curve), mismatched sizes or times, or a channel in
/// which no sampled pixel changes level between well-exposed exposures
/// (e.g. an all-black or all-saturated stack).
///
/// ```
/// use depthgraph_graph::value::ColorImage;
/// use depthgraph_nodes::camera::hdr::{recover_response, ResponseParams};
/// use depthgraph_nodes::sim::sensor::{simulate_bracket, BracketParams};
/// let hdr = ColorImage::from_fn(64, 16, |x, _| [0.01 * 1.1f32.powi(x as i32); 3]);
/// let p = BracketParams { stops: vec![-4.0, -2.0, 0.0, 2.0, 4.0], ..Default::default() };
/// let stack = simulate_bracket(&hdr, &p).unwrap();
/// let g = recover_response(&stack, &ResponseParams::default()).unwrap();
/// assert!(g.g[1][200] > g.g[1][128] && g.g[1][128] > g.g[1][50]);
/// ```
pub fn recover_response(
    stack: &ExposureStack,
    p: &ResponseParams,
) -> Result<ResponseCurve, NodeError> {
    recover_response_with(stack, p, |_| Ok(()))
}

/// [`recover_response`] that calls `on_progress(fraction)` after each channel
/// and stops with its error (cancellation).
pub fn recover_response_with(
    stack: &ExposureStack,
    p: &ResponseParams,
    mut on_progress: impl FnMut(f32) -> Result<(), NodeError>,
) -> Result<ResponseCurve, NodeError> {
    check_stack(stack)?;
    if stack.images.len() < 2 {
        return Err(NodeError::input(
            "stack",
            "holds one exposure; recovering a response needs at least two with different times",
        ));
    }
    let (lo, hi) = stack
        .times_s
        .iter()
        .fold((f64::INFINITY, 0.0f64), |(a, b), t| (a.min(*t), b.max(*t)));
    // guard: times are positive (check_stack), so lo > 0
    if hi / lo < 1.0 + 1e-9 {
        return Err(NodeError::input(
            "stack",
            format!(
                "every exposure has the same time ({lo} s): the response cannot be recovered. \
                 Use response \"gamma\" or \"linear\", or connect a `curve`"
            ),
        ));
    }
    if !(p.lambda.is_finite() && p.lambda > 0.0) {
        return Err(NodeError::param(
            "lambda",
            format!("{} must be finite and positive", p.lambda),
        ));
    }
    if p.samples < 2 {
        return Err(NodeError::param("samples", "needs at least 2"));
    }
    let mut g = [[0.0; LEVELS]; 3];
    for (c, gc) in g.iter_mut().enumerate() {
        let idx = select_samples(stack, c, p.samples);
        *gc = recover_channel(stack, c, &idx, p.lambda)?;
        on_progress((c + 1) as f32 / 3.0)?;
    }
    Ok(ResponseCurve { g })
}

// ---------------------------------------------------------------------------
// Merge (eq. 6)
// ---------------------------------------------------------------------------

/// Result of [`merge_hdr`].
#[derive(Debug, Clone, PartialEq)]
pub struct Merged {
    /// Linear radiance `E` per channel (scale: see the module docs).
    pub color: ColorImage,
    /// 1 where some channel had no weighted value (fallback estimate or
    /// missing everywhere), else 0.
    pub fallback: Mask,
}

/// `w(z)` and `w(z) g(z)` at the 256 levels.
struct MergeLut {
    w: [f64; LEVELS],
    wg: [[f64; LEVELS]; 3],
}

impl MergeLut {
    fn new(curve: &ResponseCurve) -> Self {
        let w: [f64; LEVELS] = std::array::from_fn(|k| hat_weight(k as f64));
        Self {
            w,
            wg: std::array::from_fn(|c| std::array::from_fn(|k| w[k] * curve.g[c][k])),
        }
    }
}

/// Running sums of eq. 6 for one channel of one pixel.
#[derive(Clone, Copy)]
struct Eq6 {
    num: f64,
    den: f64,
    /// `ln Δt` of the shortest exposure in which the value was saturated.
    sat_lt: f64,
    /// `ln Δt` of the longest exposure in which the value was black.
    black_lt: f64,
}

impl Eq6 {
    const EMPTY: Eq6 = Eq6 {
        num: 0.0,
        den: 0.0,
        sat_lt: f64::INFINITY,
        black_lt: f64::NEG_INFINITY,
    };

    /// Adds the stored value `v` of an exposure with `ln Δt = lt`.
    #[inline]
    fn add(&mut self, v: f32, lt: f64, c: usize, curve: &ResponseCurve, lut: &MergeLut) {
        let Some(z) = level(v) else {
            return;
        };
        // Fast path for values on the 8-bit grid (z within 1e-4 of a level):
        // w and w g from the tables, no interpolation.
        let k = z.round();
        let (w, wg, saturated) = if (z - k).abs() < 1e-4 {
            let k = k as usize;
            (lut.w[k], lut.wg[c][k], k == LEVELS - 1)
        } else {
            let w = hat_weight(z);
            (w, w * curve.eval(c, z), z >= Z_MAX)
        };
        if w > 0.0 {
            self.num += wg - w * lt;
            self.den += w;
        } else if saturated {
            self.sat_lt = self.sat_lt.min(lt);
        } else {
            self.black_lt = self.black_lt.max(lt);
        }
    }

    /// `ln E` and whether the fallback of [`merge_hdr`] was used.
    fn finish(&self, c: usize, curve: &ResponseCurve) -> (f64, bool) {
        if self.den > 0.0 {
            return (self.num / self.den, false); // eq. 6; guard: den > 0
        }
        let sat = self
            .sat_lt
            .is_finite()
            .then(|| curve.g[c][LEVELS - 1] - self.sat_lt);
        let black = self
            .black_lt
            .is_finite()
            .then(|| curve.g[c][0] - self.black_lt);
        let ln_e = match (sat, black) {
            (Some(a), Some(b)) => 0.5 * (a + b),
            (Some(a), None) => a,
            (None, Some(b)) => b,
            (None, None) => f64::NEG_INFINITY, // exp gives E = 0
        };
        (ln_e, true)
    }
}

/// Merges a stack into linear radiance with the response `curve` (eq. 6 of
/// Debevec & Malik), per pixel and channel, accumulating in f64:
/// `ln E = Σ_j w(Z_j) (g(Z_j) - ln Δt_j) / Σ_j w(Z_j)` over the exposures
/// whose value is present (finite), with `g` interpolated at `Z = value * 255`.
///
/// Fallback where `Σ w = 0` (every present value is exactly 0 or 255; such
/// pixels are 1 in [`Merged::fallback`]):
/// - saturated in every present exposure: the shortest of them, assuming
///   saturation, `ln E = g(255) - ln Δt_min` (a lower bound on `E`, the
///   brightest estimate the data allow);
/// - black in every present exposure: the longest, `ln E = g(0) - ln Δt_max`;
/// - both (only with noise or misregistration): the mean of the two logs;
/// - missing in every exposure: `E = 0`.
///
/// Radiance beyond the f32 range is clamped to `f32::MAX`.
///
/// ```
/// use depthgraph_graph::value::ColorImage;
/// use depthgraph_nodes::camera::hdr::{merge_hdr, ResponseCurve};
/// use depthgraph_nodes::sim::sensor::{simulate_bracket, BracketParams};
/// let hdr = ColorImage::filled(4, 4, [0.05, 0.5, 5.0]);
/// let p = BracketParams { noise_sigma: 0.0, stops: vec![-4.0, 0.0, 4.0], ..Default::default() };
/// let stack = simulate_bracket(&hdr, &p).unwrap();
/// let out = merge_hdr(&stack, &ResponseCurve::gamma(2.2)).unwrap();
/// let e = out.color.get(0, 0);
/// assert!((e[2] / 5.0 - 1.0).abs() < 0.02);
/// ```
pub fn merge_hdr(stack: &ExposureStack, curve: &ResponseCurve) -> Result<Merged, NodeError> {
    let (w, h) = check_stack(stack)?;
    let ln_t: Vec<f64> = stack.times_s.iter().map(|t| t.ln()).collect();
    let lut = MergeLut::new(curve);
    let mut color = vec![[0.0f32; 3]; w * h];
    let mut fallback = vec![0.0f32; w * h];
    if w > 0 {
        color
            .par_chunks_mut(w)
            .zip(fallback.par_chunks_mut(w))
            .enumerate()
            .for_each(|(y, (crow, frow))| {
                // One row of sums; each exposure's row is read once, in order.
                let mut sums = vec![[Eq6::EMPTY; 3]; w];
                for (img, &lt) in stack.images.iter().zip(&ln_t) {
                    for (acc, px) in sums.iter_mut().zip(img.row(y)) {
                        for (c, a) in acc.iter_mut().enumerate() {
                            a.add(px[c], lt, c, curve, &lut);
                        }
                    }
                }
                for ((px, fb), acc) in crow.iter_mut().zip(frow.iter_mut()).zip(&sums) {
                    for (c, (out, a)) in px.iter_mut().zip(acc).enumerate() {
                        let (ln_e, used_fallback) = a.finish(c, curve);
                        *out = (ln_e.exp().min(f32::MAX as f64)) as f32;
                        if used_fallback {
                            *fb = 1.0;
                        }
                    }
                }
            });
    }

    Ok(Merged {
        color: Image::from_vec(w, h, color)?,
        fallback: Image::from_vec(w, h, fallback)?,
    })
}

// ---------------------------------------------------------------------------
// Loading brackets
// ---------------------------------------------------------------------------

node_params! {
    /// Parameters of `LoadBracket`.
    pub struct LoadBracketParams {
        /// Text file listing the exposures, one per line: `filename exposure_time_s [more columns
        /// ignored]`; `#` starts a comment; file names are relative to the list's directory
        /// (Debevec's memorial `image_list.txt` reads as is). Leave empty to use `files`.
        pub list: String = "", ParamKind::InputPath;
        /// Comma-separated image files (8/16-bit PNG or TIFF, JPEG; relative to the working
        /// directory like LoadColor's path), used when `list` is empty.
        pub files: String = "", ParamKind::Text;
        /// Exposure time in seconds of each file of `files`, in the same order.
        pub times_s: Vec<f64> = Vec::<f64>::new(), ParamKind::Floats { min: 0.0, max: 1e6 };
        /// Debevec's memorial series marks shifted borders with pure blue (0, 0, 255):
        /// such pixels become missing (NaN, weight 0 in the merge).
        pub mask_pure_blue: bool = false, ParamKind::Bool;
    }
}

/// Parses an exposure list (see [`LoadBracketParams::list`]); `list` is the
/// list's own path, for errors and for resolving relative file names.
pub fn parse_bracket_list(text: &str, list: &Path) -> Result<Vec<(PathBuf, f64)>, NodeError> {
    let dir = list
        .parent()
        .filter(|d| !d.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let err = |line: usize, message: String| NodeError::Decode {
        path: list.to_path_buf(),
        message: format!("line {line}: {message}"),
    };
    let mut out = Vec::new();
    for (n, raw) in text.lines().enumerate() {
        let line = raw.split('#').next().unwrap_or("").trim();
        if line.is_empty() {
            continue;
        }
        let mut tokens = line.split_whitespace();
        let (Some(name), Some(time)) = (tokens.next(), tokens.next()) else {
            return Err(err(
                n + 1,
                format!("expected `filename exposure_time_s`, found `{line}`"),
            ));
        };
        let t: f64 = time.parse().map_err(|_| {
            err(
                n + 1,
                format!("exposure time `{time}` of {name} is not a number"),
            )
        })?;
        if !(t.is_finite() && t > 0.0) {
            return Err(err(
                n + 1,
                format!("exposure time {t} s of {name} must be positive"),
            ));
        }
        out.push((dir.join(name), t));
    }
    if out.is_empty() {
        return Err(NodeError::Decode {
            path: list.to_path_buf(),
            message: "lists no exposure (expected lines `filename exposure_time_s`)".into(),
        });
    }
    Ok(out)
}

/// The files and times the parameters name (reads the list file if set).
pub fn bracket_entries(p: &LoadBracketParams) -> Result<Vec<(PathBuf, f64)>, NodeError> {
    let files: Vec<&str> = p
        .files
        .split(',')
        .map(str::trim)
        .filter(|f| !f.is_empty())
        .collect();
    if !p.list.is_empty() {
        if !files.is_empty() || !p.times_s.is_empty() {
            return Err(NodeError::param(
                "list",
                "set either `list` or `files` + `times_s`, not both",
            ));
        }
        let path = Path::new(&p.list);
        let text = std::fs::read_to_string(path).map_err(|e| NodeError::read(path, e))?;
        return parse_bracket_list(&text, path);
    }
    if files.is_empty() {
        return Err(NodeError::param(
            "list",
            "no exposures given: set `list` (a file of `filename exposure_time_s` lines) or `files` and `times_s`",
        ));
    }
    if files.len() != p.times_s.len() {
        return Err(NodeError::param(
            "times_s",
            format!(
                "holds {} times for the {} files of `files`; expected one per file",
                p.times_s.len(),
                files.len()
            ),
        ));
    }
    files
        .iter()
        .zip(&p.times_s)
        .map(|(f, t)| {
            if t.is_finite() && *t > 0.0 {
                Ok((PathBuf::from(f), *t))
            } else {
                Err(NodeError::param(
                    "times_s",
                    format!("exposure time {t} s of {f} must be positive"),
                ))
            }
        })
        .collect()
}

/// Loads an exposure bracket: values are the stored codes scaled to `[0, 1]`
/// (`/255`, `/65535`), **not** sRGB-linearised, since the merge needs the
/// values after the camera response. Every image must have the size of the
/// first; pure-blue pixels become NaN when `mask_pure_blue` is set.
pub fn load_bracket(p: &LoadBracketParams) -> Result<ExposureStack, NodeError> {
    load_bracket_with(p, &crate::io::Limits::default())
}

/// [`load_bracket`] with each image's header checked against `lim` before
/// its pixels are decoded.
pub fn load_bracket_with(
    p: &LoadBracketParams,
    lim: &crate::io::Limits,
) -> Result<ExposureStack, NodeError> {
    let entries = bracket_entries(p)?;
    let loaded: Vec<Result<ColorImage, NodeError>> = entries
        .par_iter()
        .map(|(path, _)| crate::io::load_color_with(path, crate::io::ColorSpace::Linear, lim))
        .collect();
    let mut stack = ExposureStack::default();
    for ((path, t), img) in entries.iter().zip(loaded) {
        let mut img = img?;
        if let Some(first) = stack.images.first() {
            if img.dims() != first.dims() {
                return Err(NodeError::Decode {
                    path: path.clone(),
                    message: format!(
                        "is {}x{} but {} is {}x{}; every exposure must have the same size",
                        img.width(),
                        img.height(),
                        entries[0].0.display(),
                        first.width(),
                        first.height()
                    ),
                });
            }
        }
        if p.mask_pure_blue {
            for px in img.as_mut_slice() {
                if *px == [0.0, 0.0, 1.0] {
                    *px = [f32::NAN; 3];
                }
            }
        }
        stack.images.push(img);
        stack.times_s.push(*t);
    }
    Ok(stack)
}

depthgraph_graph::ports! {
    /// Outputs of `LoadBracket`.
    outputs struct LoadBracketOut {
        /// values in [0, 1] after the camera response; NaN = missing
        exposures: ExposureStack,
    }
}

fn load_bracket_eval(
    ctx: &EvalCtx,
    _: NoInputs,
    p: &LoadBracketParams,
) -> Result<Produced<LoadBracketOut>, NodeError> {
    Ok(LoadBracketOut {
        exposures: load_bracket_with(p, &crate::io::Limits::of(ctx))?,
    }
    .into())
}

fn bracket_files(p: &LoadBracketParams) -> Vec<PathBuf> {
    let mut out = Vec::new();
    if !p.list.is_empty() {
        out.push(PathBuf::from(&p.list));
    }
    // best effort: the images the list names (an unreadable list is reported by eval)
    if let Ok(entries) = bracket_entries(p) {
        out.extend(entries.into_iter().map(|e| e.0));
    }
    out
}

// ---------------------------------------------------------------------------
// Nodes
// ---------------------------------------------------------------------------

depthgraph_graph::param_choice! {
    /// Where the response curve comes from (the `response` parameter).
    pub enum ResponseSource {
        /// Estimated from the stack (eq. 5).
        Recover = "recover",
        /// A known gamma camera (the curve of SimulateBracket).
        Gamma = "gamma",
        /// A linear camera.
        Linear = "linear",
    }
}

node_params! {
    /// Parameters of `HdrMerge`.
    pub struct HdrMergeParams {
        /// "recover": estimate g from the stack (eq. 5); "gamma": a known gamma camera (the curve
        /// of SimulateBracket); "linear": a linear camera. A connected `curve` input overrides it.
        pub response: ResponseSource = ResponseSource::Recover, ParamKind::Choice(ResponseSource::NAMES);
        /// Gamma of the "gamma" response (see SimulateBracket).
        pub gamma: f64 = 2.2, ParamKind::Float { min: 1.0, max: 5.0 };
        /// "recover": pixels sampled per channel (spread over the radiance range, flat regions
        /// preferred); the paper asks for samples * (exposures - 1) > 255.
        pub samples: usize = 400usize, ParamKind::Int { min: 2, max: 100_000 };
        /// "recover": smoothness weight lambda of eq. 5 (multiplies the squared sum, so OpenCV's
        /// and gsolve's lambda l is l^2 here). The data term grows with `samples`: OpenCV's
        /// default (l = 10 at 70 samples) scaled to 400 samples is about 570.
        pub lambda: f64 = 1000.0, ParamKind::Float { min: 1e-6, max: 1e9 };
    }
}

impl HdrMergeParams {
    /// The recovery part of the parameters.
    pub fn response_params(&self) -> ResponseParams {
        ResponseParams {
            samples: self.samples,
            lambda: self.lambda,
        }
    }
}

depthgraph_graph::ports! {
    /// Inputs of `HdrMerge`.
    inputs struct HdrMergeIn {
        /// exposures with their times
        stack: Arc<ExposureStack>,
        /// a 256x1 response curve (another HdrMerge's `curve`); overrides `response`
        curve: Option<Arc<ColorImage>>,
    }
}

depthgraph_graph::ports! {
    /// Outputs of `HdrMerge`.
    outputs struct HdrMergeOut {
        /// linear radiance
        color: ColorImage,
        /// 256x1: exp g(z) per channel, the relative exposure giving level z
        curve: ColorImage,
        /// 1 where a channel was saturated, black or missing in every exposure
        fallback: Mask,
    }
}

fn hdr_merge_eval(
    ctx: &EvalCtx,
    i: HdrMergeIn,
    p: &HdrMergeParams,
) -> Result<Produced<HdrMergeOut>, NodeError> {
    let stack = &i.stack;
    let (w, h) = check_stack(stack)?;
    let curve = match &i.curve {
        Some(img) => ResponseCurve::from_image(img, "curve")?,
        None => match p.response {
            ResponseSource::Gamma => ResponseCurve::gamma(p.gamma),
            ResponseSource::Linear => ResponseCurve::linear(),
            ResponseSource::Recover => {
                if stack.images.len() == 1 {
                    let out = HdrMergeOut {
                        color: stack.images[0].clone(),
                        curve: ResponseCurve::linear().to_image(),
                        fallback: Mask::filled(w, h, 0.0),
                    };
                    return Ok(Produced::passthrough(
                        out,
                        "a single exposure: no response can be recovered from one image, so it is passed \
                         through unchanged (not linearised); set response to \"gamma\" or \"linear\", or \
                         connect a `curve`, to merge it",
                    ));
                }
                recover_response_with(stack, &p.response_params(), |f| {
                    ctx.progress(0.5 * f);
                    ctx.check_cancelled()
                })?
            }
        },
    };
    ctx.check_cancelled()?;
    let merged = merge_hdr(stack, &curve)?;
    ctx.progress(1.0);
    Ok(HdrMergeOut {
        color: merged.color,
        curve: curve.to_image(),
        fallback: merged.fallback,
    }
    .into())
}

node_params! {
    /// Parameters of `SaveResponse`.
    pub struct SaveResponseParams {
        /// Output `.csv` file (columns z, g_r, g_g, g_b with g = ln exposure). Relative paths go
        /// under `--out`.
        pub path: String = "response.csv", ParamKind::OutputPath;
    }
}

/// Writes a response curve as CSV: a header `z,g_r,g_g,g_b`, then one line
/// per level with `g(z) = ln(E Δt)`.
pub fn save_response(curve: &ResponseCurve, path: &Path) -> Result<PathBuf, NodeError> {
    let mut text = String::from("z,g_r,g_g,g_b\n");
    for z in 0..LEVELS {
        let _ = writeln!(
            text,
            "{z},{},{},{}",
            curve.g[0][z], curve.g[1][z], curve.g[2][z]
        );
    }
    crate::io::write_atomic(path, |tmp| std::fs::write(tmp, text.as_bytes()))
}

depthgraph_graph::ports! {
    /// Inputs of `SaveResponse`.
    inputs struct SaveResponseIn {
        /// 256x1 response curve
        curve: Arc<ColorImage>,
    }
}

depthgraph_graph::ports! {
    /// Outputs of `SaveResponse`.
    outputs struct SaveResponseOut {
        /// the file written
        file: PathBuf,
    }
}

fn save_response_eval(
    ctx: &EvalCtx,
    i: SaveResponseIn,
    p: &SaveResponseParams,
) -> Result<Produced<SaveResponseOut>, NodeError> {
    let curve = ResponseCurve::from_image(&i.curve, "curve")?;
    let path = ctx.output_path(&p.path)?;
    Ok(SaveResponseOut {
        file: save_response(&curve, &path)?,
    }
    .into())
}

/// Registers `LoadBracket`, `HdrMerge` and `SaveResponse`.
pub fn register(reg: &mut Registry) -> Result<(), RegistryError> {
    reg.register(
        PortedNode::new(
            "LoadBracket",
            1,
            "Reads an exposure bracket (images + exposure times) without linearising it.\n\
             From a list file (`filename exposure_time_s` per line, as Debevec's memorial image_list.txt) \
             or from files + times_s; optional pure-blue masking.",
            load_bracket_eval,
        )
        .reads(bracket_files),
    )?;
    reg.register(PortedNode::new(
        "HdrMerge",
        1,
        "Merges an exposure bracket into linear radiance (Debevec & Malik 1997, eq. 5-6).\n\
         Recovers the response curve g by least squares with smoothness (or uses a gamma/linear or \
         connected curve), then averages g(Z) - ln dt with hat weights. A recovered curve gives radiance \
         up to one factor per channel.",
        hdr_merge_eval,
    ))?;
    reg.register(
        PortedNode::new(
            "SaveResponse",
            1,
            "Writes a response curve (HdrMerge's `curve`) as CSV: z, g_r, g_g, g_b.",
            save_response_eval,
        )
        .sink(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::response::inverse_response;
    use crate::sim::sensor::{BracketParams, simulate_bracket};
    use crate::sim::synthetic::{RenderOptions, Scene, render};

    /// Radiance 1e-3..1e2: a log ramp (different per channel) above the
    /// tabletop scene's color.
    fn hdr_scene() -> ColorImage {
        let (w, h) = (64, 48);
        let scene = Scene::preset("tabletop", w, 24).unwrap();
        let tab = render(&scene, &RenderOptions::default()).color;
        Image::from_fn(w, h, |x, y| {
            if y < 24 {
                let t = (x as f64 + (y % 8) as f64 / 8.0) / w as f64;
                let e = |off: f64| (10f64.powf(-3.0 + 5.0 * (t * 0.9 + off)) as f32).min(100.0);
                [e(0.1), e(0.05), e(0.0)]
            } else {
                *tab.get(x, y - 24)
            }
        })
    }

    fn bracket(gamma: f64) -> BracketParams {
        BracketParams {
            stops: vec![-6.0, -4.0, -2.0, 0.0, 2.0, 4.0, 6.0],
            gamma,
            ..Default::default()
        }
    }

    /// Mean and 95th percentile of |E / (s E_true) - 1| over pixels whose
    /// true radiance some exposure sees well (0.05 < E t < 0.9 for some t),
    /// with one fitted factor `s` per channel (1 when `fit` is false).
    fn rel_errors(out: &ColorImage, truth: &ColorImage, times: &[f64], fit: bool) -> (f64, f64) {
        let seen = |e: f64| times.iter().any(|t| (0.05..0.9).contains(&(e * t)));
        let mut errs = Vec::new();
        for c in 0..3 {
            let pairs: Vec<(f64, f64)> = out
                .as_slice()
                .iter()
                .zip(truth.as_slice())
                .map(|(o, t)| (o[c] as f64, t[c] as f64))
                .filter(|(_, t)| *t > 0.0 && seen(*t))
                .collect();
            let s = if fit {
                let mean: f64 =
                    pairs.iter().map(|(o, t)| (o / t).ln()).sum::<f64>() / pairs.len() as f64;
                mean.exp()
            } else {
                1.0
            };
            errs.extend(pairs.iter().map(|(o, t)| (o / (s * t) - 1.0).abs()));
        }
        errs.sort_by(f64::total_cmp);
        let mean = errs.iter().sum::<f64>() / errs.len() as f64;
        (mean, errs[errs.len() * 95 / 100])
    }

    #[test]
    fn recovered_curve_matches_the_simulated_gamma_up_to_a_constant() {
        // default noise (0.2% of saturation): the darkest levels are noise, not response
        let stack = simulate_bracket(&hdr_scene(), &bracket(2.2)).unwrap();
        let curve = recover_response(&stack, &ResponseParams::default()).unwrap();
        let truth: Vec<f64> = (0..LEVELS)
            .map(|z| (inverse_response(z as f32 / 255.0, 2.2) as f64).ln())
            .collect();
        let range = 30..246;
        for c in 0..3 {
            assert_eq!(curve.g[c][Z_MID], 0.0);
            let off =
                range.clone().map(|z| curve.g[c][z] - truth[z]).sum::<f64>() / range.len() as f64;
            let worst = range
                .clone()
                .map(|z| (curve.g[c][z] - truth[z] - off).abs())
                .fold(0.0, f64::max);
            assert!(
                worst < 0.06,
                "channel {c}: max |g - g_true - offset| = {worst}"
            );
            for z in 1..LEVELS {
                assert!(curve.g[c][z] > curve.g[c][z - 1], "g must increase at {z}");
            }
        }
    }

    #[test]
    fn merged_radiance_is_within_a_few_percent_and_a_given_gamma_is_closer() {
        let truth = hdr_scene();
        let run = |noise_sigma: f64, curve: Option<ResponseCurve>| {
            let p = BracketParams {
                noise_sigma,
                ..bracket(2.2)
            };
            let stack = simulate_bracket(&truth, &p).unwrap();
            let fit = curve.is_none();
            let curve = curve
                .unwrap_or_else(|| recover_response(&stack, &ResponseParams::default()).unwrap());
            let m = merge_hdr(&stack, &curve).unwrap();
            rel_errors(&m.color, &truth, &stack.times_s, fit)
        };
        let gamma = || Some(ResponseCurve::gamma(2.2));
        // with noise: a few % after one fitted factor per channel; the known
        // curve is absolute (no factor fitted)
        let (mean_r, p95_r) = run(0.0005, None);
        assert!(
            mean_r < 0.02 && p95_r < 0.05,
            "recovered: mean {mean_r}, p95 {p95_r}"
        );
        let (mean_g, p95_g) = run(0.0005, gamma());
        assert!(
            mean_g < 0.02 && p95_g < 0.05,
            "given: mean {mean_g}, p95 {p95_g}"
        );
        // without noise only the curve differs: the known one is closer
        let (clean_r, clean_r95) = run(0.0, None);
        let (clean_g, clean_g95) = run(0.0, gamma());
        assert!(
            clean_g < clean_r && clean_g95 < clean_r95,
            "given {clean_g} vs recovered {clean_r}"
        );
        // a wrong curve is far worse, even after fitting the factor
        let (mean_w, _) = run(0.0005, Some(ResponseCurve::linear()));
        assert!(
            mean_w > 3.0 * mean_r,
            "linear {mean_w} vs recovered {mean_r}"
        );
    }

    #[test]
    fn sixteen_bit_values_merge_closer_than_eight_bit() {
        let truth = hdr_scene();
        let g = ResponseCurve::gamma(2.2);
        let err = |bits: u32| {
            let p = BracketParams {
                noise_sigma: 0.0,
                bits,
                ..bracket(2.2)
            };
            let stack = simulate_bracket(&truth, &p).unwrap();
            let m = merge_hdr(&stack, &g).unwrap();
            rel_errors(&m.color, &truth, &stack.times_s, false)
        };
        let (e8, e16) = (err(8), err(16));
        assert!(e16.0 < 0.5 * e8.0, "16-bit {e16:?} vs 8-bit {e8:?}");
    }

    fn eval_node(
        stack: ExposureStack,
        p: &HdrMergeParams,
        curve: Option<ColorImage>,
    ) -> Result<Outputs, NodeError> {
        let cancel = CancelToken::new();
        let ctx = EvalCtx {
            node: "merge",
            cancel: &cancel,
            progress: None,
            out_dir: Path::new("."),
            input_files: &[],
            derivations: None,
            max_pixels: depthgraph_graph::node::DEFAULT_MAX_PIXELS,
        };
        let mut inputs = Inputs::new();
        inputs.insert("stack", stack.into());
        if let Some(c) = curve {
            inputs.insert("curve", c.into());
        }
        let mut reg = Registry::new();
        register(&mut reg).expect("registers");
        let node = reg.get("HdrMerge").expect("registered");
        node.eval(&ctx, &inputs, &p.to_values())
    }

    #[test]
    fn single_exposure_passes_through_with_a_reason() {
        let stack = simulate_bracket(
            &hdr_scene(),
            &BracketParams {
                stops: vec![0.0],
                ..Default::default()
            },
        )
        .unwrap();
        let out = eval_node(stack.clone(), &HdrMergeParams::default(), None).unwrap();
        assert!(
            out.passthrough
                .as_deref()
                .unwrap_or("")
                .contains("single exposure")
        );
        assert_eq!(
            out.values["color"],
            Value::Color(Arc::new(stack.images[0].clone()))
        );
        // with a given curve one exposure is linearised, not passed through
        let p = HdrMergeParams {
            response: ResponseSource::Gamma,
            ..Default::default()
        };
        let out = eval_node(stack.clone(), &p, None).unwrap();
        assert!(out.passthrough.is_none());
        assert_ne!(
            out.values["color"],
            Value::Color(Arc::new(stack.images[0].clone()))
        );
    }

    #[test]
    fn equal_times_cannot_recover_but_merge_with_a_given_curve() {
        let mut stack = simulate_bracket(&hdr_scene(), &bracket(2.2)).unwrap();
        stack.images.truncate(3);
        stack.times_s = vec![0.5; 3];
        let e = recover_response(&stack, &ResponseParams::default()).unwrap_err();
        assert!(e.to_string().contains("same time"), "{e}");
        let e = eval_node(stack.clone(), &HdrMergeParams::default(), None).unwrap_err();
        assert!(e.to_string().contains("stack"), "{e}");
        // a connected curve (another merge's output) makes it work
        let curve = ResponseCurve::gamma(2.2).to_image();
        let out = eval_node(stack, &HdrMergeParams::default(), Some(curve)).unwrap();
        let Value::Color(c) = &out.values["color"] else {
            panic!("color output")
        };
        assert!(
            c.as_slice()
                .iter()
                .flatten()
                .all(|v| v.is_finite() && *v >= 0.0)
        );
    }

    #[test]
    fn all_saturated_and_all_black_stacks_give_finite_documented_values() {
        let times = vec![0.25, 1.0, 4.0];
        let g = ResponseCurve::gamma(2.2);
        for (v, want) in [
            (1.0f32, 1.0 / 0.25),           // g(255) = 0, shortest time
            (0.0, (g.g[0][0].exp()) / 4.0), // g(0), longest time
        ] {
            let stack = ExposureStack {
                images: vec![Image::filled(5, 4, [v; 3]); 3],
                times_s: times.clone(),
            };
            let m = merge_hdr(&stack, &g).unwrap();
            for px in m.color.as_slice() {
                for e in px {
                    assert!(e.is_finite());
                    assert!((*e as f64 / want - 1.0).abs() < 1e-5, "{e} vs {want}");
                }
            }
            assert!(m.fallback.as_slice().iter().all(|f| *f == 1.0));
            let e = recover_response(&stack, &ResponseParams::default()).unwrap_err();
            assert!(e.to_string().contains("well exposed"), "{e}");
        }
        // the black estimate lies below the first level's, the saturated one above the last
        assert!(g.g[0][0] < g.g[0][1]);
    }

    #[test]
    fn nan_values_are_ignored() {
        let truth = hdr_scene();
        let stack = simulate_bracket(&truth, &bracket(2.2)).unwrap();
        let (w, h) = stack.images[0].dims();
        let mut holes = stack.clone();
        // exposure 3 misses a block; pixel (0, 0) is missing everywhere
        for y in 10..20 {
            for x in 5..30 {
                *holes.images[3].get_mut(x, y) = [f32::NAN; 3];
            }
        }
        for img in &mut holes.images {
            *img.get_mut(0, 0) = [f32::NAN, 0.5, f32::INFINITY];
        }
        let g = ResponseCurve::gamma(2.2);
        let merged = merge_hdr(&holes, &g).unwrap();
        let without3 = ExposureStack {
            images: [&stack.images[..3], &stack.images[4..]].concat(),
            times_s: [&stack.times_s[..3], &stack.times_s[4..]].concat(),
        };
        let ref3 = merge_hdr(&without3, &g).unwrap();
        let full = merge_hdr(&stack, &g).unwrap();
        for y in 0..h {
            for x in 0..w {
                let got = merged.color.get(x, y);
                assert!(got.iter().all(|v| v.is_finite()));
                if (x, y) == (0, 0) {
                    continue;
                }
                let want = if (10..20).contains(&y) && (5..30).contains(&x) {
                    ref3.color.get(x, y)
                } else {
                    full.color.get(x, y)
                };
                assert_eq!(got, want, "({x}, {y})");
            }
        }
        let px = merged.color.get(0, 0);
        assert_eq!((px[0], px[2]), (0.0, 0.0), "missing everywhere is 0");
        assert!(px[1] > 0.0);
        assert_eq!(*merged.fallback.get(0, 0), 1.0);
        // recovery also ignores them and still works
        assert!(recover_response(&holes, &ResponseParams::default()).is_ok());
    }

    #[test]
    fn bad_stacks_are_named_errors() {
        let img = Image::filled(3, 2, [0.5f32; 3]);
        let cases = [
            (ExposureStack::default(), "no exposure"),
            (
                ExposureStack {
                    images: vec![img.clone(), img.clone()],
                    times_s: vec![1.0],
                },
                "2 images but 1",
            ),
            (
                ExposureStack {
                    images: vec![img.clone(), Image::filled(2, 2, [0.5; 3])],
                    times_s: vec![1.0, 2.0],
                },
                "image 1 is 2x2",
            ),
            (
                ExposureStack {
                    images: vec![img.clone(), img.clone()],
                    times_s: vec![1.0, 0.0],
                },
                "positive",
            ),
        ];
        for (stack, want) in cases {
            let e = merge_hdr(&stack, &ResponseCurve::linear()).unwrap_err();
            assert!(
                e.to_string().contains(want) && e.to_string().contains("stack"),
                "{e}"
            );
        }
        let e = ResponseCurve::from_image(&img, "curve").unwrap_err();
        assert!(e.to_string().contains("256x1"), "{e}");
        let mut bad = ResponseCurve::linear().to_image();
        bad.get_mut(3, 0)[1] = -1.0;
        assert!(ResponseCurve::from_image(&bad, "curve").is_err());
    }

    #[test]
    fn curve_image_round_trips_and_csv_has_256_rows() {
        let g = ResponseCurve::gamma(2.2);
        let back = ResponseCurve::from_image(&g.to_image(), "curve").unwrap();
        for c in 0..3 {
            for z in 0..LEVELS {
                assert!((back.g[c][z] - g.g[c][z]).abs() < 1e-6);
            }
        }
        assert_eq!(g.g[0][255], 0.0);
        assert!((g.eval(1, 127.5) - 0.5 * (g.g[1][127] + g.g[1][128])).abs() < 1e-12);
        let dir = tempfile::tempdir().unwrap();
        let path = save_response(&g, &dir.path().join("r.csv")).unwrap();
        let text = std::fs::read_to_string(path).unwrap();
        assert_eq!(text.lines().count(), 257);
        assert!(text.starts_with("z,g_r,g_g,g_b\n0,"));
    }

    #[test]
    fn thread_count_does_not_change_bits() {
        let stack = simulate_bracket(&hdr_scene(), &bracket(2.2)).unwrap();
        let run = |n| {
            crate::test_support::with_threads(n, || {
                let g = recover_response(&stack, &ResponseParams::default()).unwrap();
                merge_hdr(&stack, &g).unwrap()
            })
        };
        assert_eq!(run(1), run(3));
    }

    fn write_png(path: &Path, w: u32, h: u32, px: impl Fn(u32, u32) -> [u8; 3]) {
        image::RgbImage::from_fn(w, h, |x, y| image::Rgb(px(x, y)))
            .save(path)
            .unwrap();
    }

    #[test]
    fn load_bracket_reads_a_list_without_linearising_and_masks_blue() {
        let dir = tempfile::tempdir().unwrap();
        let sub = dir.path().join("set");
        std::fs::create_dir(&sub).unwrap();
        for (i, v) in [40u8, 128, 230].iter().enumerate() {
            write_png(&sub.join(format!("e{i}.png")), 4, 3, |x, _| {
                if x == 3 { [0, 0, 255] } else { [*v, *v, *v] }
            });
        }
        let list = sub.join("list.txt");
        std::fs::write(
            &list,
            "# Filename exposure 1/shutter\ne0.png 0.25 4 8\n\n  e1.png   1  1 # mid\ne2.png 4\n",
        )
        .unwrap();
        let p = LoadBracketParams {
            list: list.display().to_string(),
            mask_pure_blue: true,
            ..Default::default()
        };
        let s = load_bracket(&p).unwrap();
        assert_eq!(s.times_s, vec![0.25, 1.0, 4.0]);
        assert_eq!(s.images[1].get(0, 0)[0], 128.0 / 255.0, "not linearised");
        assert!(s.images[2].get(3, 1).iter().all(|v| v.is_nan()));
        let files = bracket_files(&p);
        assert_eq!(files.len(), 4, "the list and its three images: {files:?}");
        let unmasked = load_bracket(&LoadBracketParams {
            mask_pure_blue: false,
            ..p.clone()
        })
        .unwrap();
        assert_eq!(*unmasked.images[0].get(3, 0), [0.0, 0.0, 1.0]);

        // files + times
        let names: Vec<String> = (0..3)
            .map(|i| sub.join(format!("e{i}.png")).display().to_string())
            .collect();
        let q = LoadBracketParams {
            files: names.join(", "),
            times_s: vec![1.0, 2.0, 4.0],
            ..Default::default()
        };
        assert_eq!(load_bracket(&q).unwrap().images.len(), 3);

        // errors name the file or parameter and what was expected
        let e = load_bracket(&LoadBracketParams {
            times_s: vec![1.0, 2.0],
            ..q.clone()
        })
        .unwrap_err();
        assert!(
            e.to_string().contains("times_s") && e.to_string().contains("2 times for the 3 files"),
            "{e}"
        );
        let e = load_bracket(&LoadBracketParams {
            times_s: vec![1.0, 0.0, 4.0],
            ..q.clone()
        })
        .unwrap_err();
        assert!(
            e.to_string().contains("e1.png") && e.to_string().contains("positive"),
            "{e}"
        );
        write_png(&sub.join("small.png"), 2, 2, |_, _| [1, 2, 3]);
        std::fs::write(&list, "e0.png 1\nsmall.png 2\n").unwrap();
        let e = load_bracket(&p).unwrap_err();
        assert!(
            e.to_string().contains("small.png") && e.to_string().contains("same size"),
            "{e}"
        );
        std::fs::write(&list, "e0.png 1\nmissing.png 2\n").unwrap();
        let e = load_bracket(&p).unwrap_err();
        assert!(e.to_string().contains("missing.png"), "{e}");
        std::fs::write(&list, "e0.png 1\ne1.png fast\n").unwrap();
        let e = load_bracket(&p).unwrap_err();
        assert!(
            e.to_string().contains("line 2") && e.to_string().contains("list.txt"),
            "{e}"
        );
        std::fs::write(&list, "e0.png -1\n").unwrap();
        assert!(
            load_bracket(&p)
                .unwrap_err()
                .to_string()
                .contains("positive")
        );
        std::fs::write(&list, "# nothing\n").unwrap();
        assert!(
            load_bracket(&p)
                .unwrap_err()
                .to_string()
                .contains("no exposure")
        );
        let e = load_bracket(&LoadBracketParams::default()).unwrap_err();
        assert!(e.to_string().contains("list"), "{e}");
        let e = load_bracket(&LoadBracketParams {
            files: "a.png".into(),
            ..p.clone()
        })
        .unwrap_err();
        assert!(e.to_string().contains("not both"), "{e}");
    }

    #[test]
    fn nodes_produce_their_declared_types() {
        let mut reg = Registry::new();
        register(&mut reg).unwrap();
        let stack = simulate_bracket(&hdr_scene(), &bracket(2.2)).unwrap();
        let out = eval_node(stack, &HdrMergeParams::default(), None).unwrap();
        let node = reg.get("HdrMerge").unwrap();
        for port in &node.schema().outputs {
            assert_eq!(out.values[port.name].value_type(), port.ty, "{}", port.name);
        }
        assert_eq!(out.values["curve"].image_dims(), Some((256, 1)));
    }
}
