//! Recovery of the camera response from a bracket (Debevec & Malik 1997,
//! eq. 3-5), with the sampling, smoothness scaling, monotone shaping and
//! end extrapolation that keep it right with two or three exposures.

use depthgraph_graph::prelude::*;
use rayon::prelude::*;

pub(super) use crate::kit::linalg::cholesky_solve;

use super::curve::{CHANNEL, LEVELS, ResponseCurve, Z_MAX, Z_MID, check_stack, hat_weight, level};

/// Most candidate pixels the coverage pass of [`select_samples`] scans (a
/// regular grid over larger images).
const COVER_CANDIDATES: usize = 1 << 16;
/// One channel's solved curve and its support per level.
pub(super) type Solved = ([f64; LEVELS], [u32; LEVELS]);

/// Pixels kept per (exposure, level) by the coverage pass of
/// [`select_samples`].
const COVER_PER_LEVEL: usize = 2;
/// Observations a level needs (over the samples) to count as supported by
/// the data; see [`shape_curve`].
const MIN_SUPPORT: u32 = 2;
/// Levels the end slopes of [`shape_curve`] are measured over.
const END_SPAN: usize = 8;
/// Smallest slope of `g` per level (ln units) the shaping allows: a curve
/// flatter than this would map a 0.1 % change of exposure to a whole level.
const MIN_SLOPE: f64 = 1e-3;
/// Hat weight of a level in the middle of the range, `w(127.5)`: the scale
/// that makes [`ResponseParams::lambda`] dimensionless.
const W_MID: f64 = 127.5;

/// Parameters of [`recover_response`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ResponseParams {
    /// Pixels sampled per channel over the radiance range (`N` of eq. 5;
    /// the paper asks for `N (P - 1) > 255` with `P` exposures), on top of
    /// the coverage pass that takes up to two pixels at every level of
    /// every exposure (see `select_samples`).
    pub samples: usize,
    /// Relative smoothness `λ` (dimensionless): the smoothness term of
    /// eq. 5 weighs `λ` times the data term's mean weight per level, so the
    /// balance stays the same whatever the number of samples and exposures.
    /// See [`recover_response`] for the exact scaling.
    pub lambda: f64,
}

impl Default for ResponseParams {
    fn default() -> Self {
        Self {
            samples: 400,
            lambda: 1e5,
        }
    }
}

/// Candidate pixels for the recovery of channel `c`: the union of a
/// coverage pass and a range pass (see [`range_samples`]).
///
/// Coverage: for every exposure `j` and every level `z` in `1..=254` that
/// some candidate pixel takes in `j` (candidates: a regular grid of at most
/// [`COVER_CANDIDATES`] pixels, all of them in smaller images), the
/// [`COVER_PER_LEVEL`] candidates with that level
/// that are well exposed (`0 < z < 255`) in the most exposures, then the
/// flattest (smallest local gradient in the median exposure), then the
/// first in scan order. Each exposure thus constrains every level it sees,
/// which with two or three exposures is what ties the ends of the curve to
/// the middle (a flat-region sampling alone leaves dark and bright levels
/// without data, and the smoothness term then extrapolates noise).
pub(super) fn select_samples(
    stack: &ExposureStack,
    grid: &Grid,
    c: usize,
    samples: usize,
) -> Vec<usize> {
    let (w, h) = stack.images[0].dims();
    let n_px = w * h;
    if n_px == 0 || grid.cand.is_empty() {
        return Vec::new();
    }
    let p = stack.images.len();
    let mut order: Vec<usize> = (0..p).collect();
    order.sort_by(|a, b| stack.times_s[*a].total_cmp(&stack.times_s[*b]));
    let reference = &stack.images[order[p / 2]];
    let at = |i: usize| -> f64 { level(reference.as_slice()[i][c]).unwrap_or(f64::INFINITY) };
    let cand = &grid.cand;
    let good: Vec<u8> = (0..cand.len())
        .map(|k| {
            grid.levels
                .iter()
                .filter(|l| l[k][c].is_some_and(|z| z > 0 && z < u8::MAX))
                .count()
                .min(u8::MAX as usize) as u8
        })
        .collect();
    let grad: Vec<f64> = cand
        .iter()
        .map(|&i| {
            let (x, y) = (i % w, i / w);
            let here = at(i);
            let dx = (at(y * w + (x + 1).min(w - 1)) - here).abs();
            let dy = (at((y + 1).min(h - 1) * w + x) - here).abs();
            if (dx + dy).is_finite() {
                dx + dy
            } else {
                f64::MAX
            }
        })
        .collect();
    let mut out: Vec<usize> = Vec::new();
    for lv in &grid.levels {
        // best COVER_PER_LEVEL pixels per level: (good desc, gradient asc, index asc)
        let mut best: Vec<Vec<(u8, f64, usize)>> = vec![Vec::new(); LEVELS];
        for (k, z) in lv.iter().enumerate() {
            let Some(z) = z[c] else { continue };
            let z = z as usize;
            if z == 0 || z >= LEVELS - 1 || good[k] < 2 {
                continue;
            }
            let slot = &mut best[z];
            let entry = (good[k], grad[k], cand[k]);
            if slot.len() == COVER_PER_LEVEL && !b_first(&entry, &slot[COVER_PER_LEVEL - 1]) {
                continue; // not better than the kept ones
            }
            let pos = slot.partition_point(|a| b_first(a, &entry));
            slot.insert(pos, entry);
            slot.truncate(COVER_PER_LEVEL);
        }
        out.extend(best.iter().flatten().map(|a| a.2));
    }
    if samples > 0 {
        out.extend(range_samples(stack, c, samples));
    }
    out.sort_unstable();
    out.dedup();
    out
}

/// The candidate pixels of the coverage pass (a regular grid of at most
/// [`COVER_CANDIDATES`] pixels) with their level in every exposure and
/// channel (`None`: missing), read from the images once for all channels.
pub(super) struct Grid {
    cand: Vec<usize>,
    /// `levels[j][k][c]`: exposure `j`, candidate `k`, channel `c`.
    levels: Vec<Vec<[Option<u8>; 3]>>,
}

impl Grid {
    pub(super) fn new(stack: &ExposureStack) -> Self {
        let (w, h) = stack.images.first().map_or((0, 0), |i| i.dims());
        let n_px = w * h;
        // every `step`-th pixel of every `step`-th row
        let step = ((n_px as f64 / COVER_CANDIDATES as f64).sqrt().ceil() as usize).max(1);
        let cand: Vec<usize> = (0..h)
            .step_by(step)
            .flat_map(|y| (0..w).step_by(step).map(move |x| y * w + x))
            .collect();
        let levels = stack
            .images
            .par_iter()
            .map(|img| {
                let px = img.as_slice();
                cand.iter()
                    // z in [0, 255]: + 0.5 and truncation is round()
                    .map(|&i| px[i].map(|v| level(v).map(|z| (z + 0.5) as u8)))
                    .collect()
            })
            .collect();
        Self { cand, levels }
    }
}

/// Order of the coverage pass: more well-exposed values first, then the
/// smaller gradient, then the smaller index (scan order).
fn b_first(a: &(u8, f64, usize), b: &(u8, f64, usize)) -> bool {
    b.0.cmp(&a.0).then(a.1.total_cmp(&b.1)).then(a.2.cmp(&b.2)) == std::cmp::Ordering::Less
}

/// Range pass of [`select_samples`]: pixels chosen deterministically so that
/// they span the range of radiances and sit in flat regions.
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
fn range_samples(stack: &ExposureStack, c: usize, samples: usize) -> Vec<usize> {
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

/// Recovers `g` for channel `c` from the sampled pixels `idx` (eq. 5); see
/// [`recover_response`] for the solve.
fn recover_channel(
    stack: &ExposureStack,
    c: usize,
    idx: &[usize],
    lambda: f64,
) -> Result<Solved, NodeError> {
    const N: usize = LEVELS;
    let ln_t: Vec<f64> = stack.times_s.iter().map(|t| t.ln()).collect();
    let mut s = vec![0.0f64; N * N];
    let mut r = vec![0.0f64; N];
    let mut informative = 0usize;
    let mut used = 0usize;
    let mut data_total = 0.0f64;
    let mut support = [0u32; LEVELS];
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
        if obs.len() >= 2 {
            // a lone observation only fixes its own ln E_i (its Schur rows vanish)
            for o in &obs {
                support[o.0] += 1;
            }
            data_total += d;
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
    // smoothness (eq. 5), scaled: κ [w(z) (g(z-1) - 2 g(z) + g(z+1))]² with
    // κ = λ s(P) D / (254 w_mid²), D = Σ w² over the data rows, so that λ = 1
    // gives the smoothness rows (at mid weight) the data term's mean weight
    // per level, and s(P) = exposure_scale(P)
    let kappa =
        lambda * exposure_scale(stack.images.len()) * data_total / ((N - 2) as f64 * W_MID * W_MID);
    // the data term's mean diagonal, before the smoothness rows: the
    // Tikhonov guard below is sized by it, not by λ (sized by the whole
    // diagonal it grew with λ and, at λ = 1e9, halved the curve's slope)
    // guard: N > 0
    let data_diag = ((0..N).map(|z| s[z * N + z]).sum::<f64>() / N as f64).max(1.0);
    for z in 1..N - 1 {
        let wz = hat_weight(z as f64);
        let k = kappa * wz * wz;
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
    let eps = 1e-10 * data_diag;
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
    Ok((std::array::from_fn(|z| r[z] - shift), support))
}

/// How much the smoothness matters with `p` exposures: `min(1, (2 / (p -
/// 1))^4)`, 1 for two or three exposures. Data from exposures whose times
/// form one ratio `k` pin `g` only up to a wiggle periodic in `ln z` with
/// the period of `k` (every sample constrains `g(z') - g(z) = ln k` and
/// nothing between), and only the smoothness term removes it; each further
/// exposure adds pairs at other ratios (`k^2`, `k^3`, ...) that break the
/// period, so the curve needs less smoothing and follows a real camera's toe
/// and shoulder more closely (measured on the memorial series: the 16-image
/// curve against Debevec's own merge improves from 0.388 to 0.352 RMS ln
/// error going from λ = 1e5 to 10, while 3-image curves need 1e4..1e5).
fn exposure_scale(p: usize) -> f64 {
    // guard: p >= 2 (checked before any recovery), so p - 1 >= 1
    (2.0 / (p.max(2) - 1) as f64).powi(4).min(1.0)
}

/// Pool-adjacent-violators: the non-decreasing sequence closest to `y` in
/// the weighted least-squares sense (weights `w > 0`), in place.
fn isotonic(y: &mut [f64], w: &[f64]) {
    // blocks of (mean, weight, length)
    let mut blocks: Vec<(f64, f64, usize)> = Vec::with_capacity(y.len());
    for (v, wt) in y.iter().zip(w) {
        blocks.push((*v, *wt, 1));
        while blocks.len() > 1 {
            let (m2, w2, l2) = blocks[blocks.len() - 1];
            let (m1, w1, l1) = blocks[blocks.len() - 2];
            if m1 <= m2 {
                break;
            }
            blocks.truncate(blocks.len() - 2);
            // guard: weights are positive, so w1 + w2 > 0
            blocks.push(((m1 * w1 + m2 * w2) / (w1 + w2), w1 + w2, l1 + l2));
        }
    }
    let mut k = 0;
    for (m, _, l) in blocks {
        for v in &mut y[k..k + l] {
            *v = m;
        }
        k += l;
    }
}

/// Makes a solved curve sound where the data end: non-decreasing over the
/// supported levels (those with at least [`MIN_SUPPORT`] observations),
/// fitted by weighted isotonic regression (weights: the support), and
/// extended beyond them by straight lines with the slope of the last
/// [`END_SPAN`] supported levels (at least [`MIN_SLOPE`]). Levels no sample
/// reached would otherwise hold whatever the smoothness term extrapolated
/// from noisy end data. Curves with fewer than three supported levels are
/// left as solved.
fn shape_curve(g: &mut [f64; LEVELS], support: &[u32; LEVELS]) {
    let Some(lo) = support.iter().position(|s| *s >= MIN_SUPPORT) else {
        return;
    };
    let Some(hi) = support.iter().rposition(|s| *s >= MIN_SUPPORT) else {
        return;
    };
    if hi < lo + 2 {
        return;
    }
    let w: Vec<f64> = support[lo..=hi].iter().map(|s| *s as f64 + 1e-3).collect();
    isotonic(&mut g[lo..=hi], &w);
    let span = END_SPAN.min(hi - lo);
    // guard: span >= 2
    let s_lo = ((g[lo + span] - g[lo]) / span as f64).max(MIN_SLOPE);
    let s_hi = ((g[hi] - g[hi - span]) / span as f64).max(MIN_SLOPE);
    for z in 0..lo {
        g[z] = g[lo] - s_lo * (lo - z) as f64;
    }
    for z in hi + 1..LEVELS {
        g[z] = g[hi] + s_hi * (z - hi) as f64;
    }
}

/// Ties the channels of a recovered curve: each curve is known only up to
/// its own additive constant, and fixing each at one level (`g(128) = 0`)
/// lets the noise of that one level tint the whole image. The constants
/// are instead chosen so that the channels agree, in the hat-weighted
/// least-squares sense, over every level the data support in all three
/// channels (all of `1..=254` when none is), with the mean over channels of
/// `g(128)` at 0. A camera whose channels share one response then maps a
/// neutral surface (equal levels) to neutral radiance at every level, up
/// to the recovery's noise, not only at level 128.
fn tie_channels(g: &mut [[f64; LEVELS]; 3], support: &[[u32; LEVELS]; 3]) {
    let all = |z: usize| support.iter().all(|s| s[z] >= MIN_SUPPORT);
    let any_common = (1..LEVELS - 1).any(all);
    let mut offset = [0.0f64; 3];
    let mut wsum = 0.0f64;
    for z in 1..LEVELS - 1 {
        if any_common && !all(z) {
            continue;
        }
        let w = hat_weight(z as f64);
        let mean = (g[0][z] + g[1][z] + g[2][z]) / 3.0;
        for (o, gc) in offset.iter_mut().zip(g.iter()) {
            *o += w * (gc[z] - mean);
        }
        wsum += w;
    }
    // guard: levels 1..=254 have w >= 1, so wsum > 0 whenever one is used
    if wsum > 0.0 {
        for o in &mut offset {
            *o /= wsum;
        }
    }
    let mid = (0..3).map(|c| g[c][Z_MID] - offset[c]).sum::<f64>() / 3.0;
    for c in 0..3 {
        let shift = offset[c] + mid;
        for v in g[c].iter_mut() {
            *v -= shift;
        }
    }
}

/// Recovers the response `g` of each channel from a stack (eq. 3-5 of
/// Debevec & Malik). Pixels are sampled per channel, deterministically:
/// every level of every exposure, plus `p.samples` spread over the radiance
/// range in flat regions (`select_samples`). Each channel's solution is
/// then shaped (`shape_curve`: non-decreasing, straight ends where no
/// data reached) and the channels are tied (`tie_channels`: one offset
/// each, mean `g(128)` over channels 0).
///
/// The least-squares problem has unknowns `g(0..255)` and `ln E_i` for the
/// `N` samples. Its normal equations are built directly from the sparse rows
/// (a data row touches one `g(z)` and one `ln E_i`):
///
/// ```text
/// [ G    C ] [ g    ]   [ r_g ]      G = Σ w² e_z e_zᵀ + κ Σ w(z)² s_z s_zᵀ + μ e_128 e_128ᵀ
/// [ Cᵀ   D ] [ ln E ] = [ r_E ]      C[z, i] = -Σ_j w_ij² [Z_ij = z],  D = diag(Σ_j w_ij²)
/// ```
///
/// with the smoothness scale `κ = λ Σ_ij w_ij² / (254 · 127.5²)`: `λ` is
/// relative to the data term's mean weight per level, so the same `λ` gives
/// the same balance for 2 exposures or 16, 300 samples or 5000 (eq. 5's
/// absolute `λ` grows with both). `D` is diagonal, so `ln E` is eliminated
/// exactly (block LDLᵀ): the Schur complement `S = G - C D⁻¹ Cᵀ` (256 x 256,
/// dense) is factorised by Cholesky in f64, whatever `N` is. Samples with
/// `D_ii = 0` (no weighted value) are left out first; they would make `D`
/// singular and say nothing about `g`.
///
/// Conditioning: adding a constant to `g` and every `ln E_i` leaves the data
/// and smoothness terms unchanged, and the constraint `g(128) = 0` removes
/// exactly that direction. With `λ > 0` the smoothness rows (weights
/// `w(z) > 0` for `z = 1..254`) leave only affine curves `a (z - 128)` free,
/// and `a` is fixed as soon as one sample shows two different weighted levels
/// (checked: otherwise an error). `S` is then positive definite. A Tikhonov
/// term `ε I` with `ε = 1e-10` times the data term's mean diagonal guards
/// the factorisation against rounding; its pull on `g` is of relative size
/// 1e-10 against the data at any `λ`.
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
    on_progress: impl FnMut(f32) -> Result<(), NodeError>,
) -> Result<ResponseCurve, NodeError> {
    check_recovery_input(stack)?;
    if !(p.lambda.is_finite() && p.lambda > 0.0) {
        return Err(NodeError::param(
            "lambda",
            format!("{} must be finite and positive", p.lambda),
        ));
    }
    solve_channels(
        stack,
        |grid, c| {
            let idx = select_samples(stack, grid, c, p.samples);
            recover_channel(stack, c, &idx, p.lambda)
        },
        on_progress,
    )
}

/// The part every recovery shares: the candidate [`Grid`], one `fit` per
/// channel (independent, so solved in parallel; each gives its curve and
/// its support per level), each curve shaped ([`shape_curve`]) and the
/// channels tied ([`tie_channels`]). `on_progress` hears of each channel in
/// order; the first channel's error wins.
pub(super) fn solve_channels(
    stack: &ExposureStack,
    fit: impl Fn(&Grid, usize) -> Result<Solved, NodeError> + Sync,
    mut on_progress: impl FnMut(f32) -> Result<(), NodeError>,
) -> Result<ResponseCurve, NodeError> {
    let grid = Grid::new(stack);
    let solved: Vec<Result<Solved, NodeError>> = (0..3)
        .into_par_iter()
        .map(|c| {
            let (mut gc, sc) = fit(&grid, c)?;
            shape_curve(&mut gc, &sc);
            Ok((gc, sc))
        })
        .collect();
    let mut g = [[0.0; LEVELS]; 3];
    let mut support = [[0u32; LEVELS]; 3];
    for (c, r) in solved.into_iter().enumerate() {
        let (gc, sc) = r?;
        g[c] = gc;
        support[c] = sc;
        on_progress((c + 1) as f32 / 3.0)?;
    }
    tie_channels(&mut g, &support);
    Ok(ResponseCurve { g })
}

/// Checks that a stack can determine a response: a valid stack of at least
/// two exposures whose times differ.
pub(super) fn check_recovery_input(stack: &ExposureStack) -> Result<(), NodeError> {
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
    Ok(())
}
