//! Outlier pruning (realistic-depth-blur Sec. 2.2): a normal + uniform mixture per pixel.

use depthgraph_graph::prelude::*;
use rayon::prelude::*;

use super::common::*;
use super::inputs::*;
use super::params::*;

// ---------------------------------------------------------------------------
// Outlier pruning
// ---------------------------------------------------------------------------

/// Normal density of a deviation `d` with variance `var > 0`.
#[inline]
pub(super) fn normal_pdf(d: f64, var: f64) -> f64 {
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
