//! Outlier pruning (realistic-depth-blur Sec. 2.2): a normal + uniform mixture per pixel.

use crate::kit::fast_exp::exp_neg;
use depthgraph_graph::prelude::*;
use rayon::prelude::*;

use super::common::*;
use super::inputs::*;
use super::params::*;

// ---------------------------------------------------------------------------
// Outlier pruning
// ---------------------------------------------------------------------------

/// Prunes outliers with the paper's mixture model (Sec. 2.2, after its
/// reference \[12\]): the conditional density of a pixel's depth given its
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
    // The predictions, in the order their terms are summed: each opposite
    // pair's midpoint, then each one-sided extrapolation (offsets of the
    // two neighbours, variance factor).
    let mut preds: Vec<Prediction> = Vec::new();
    for ky in -r..=r {
        for kx in -r..=r {
            if ky > 0 || (ky == 0 && kx > 0) {
                preds.push(Prediction::new((kx, ky), (-kx, -ky), MIDPOINT));
            }
        }
    }
    for ky in -r..=r {
        for kx in -r..=r {
            if (kx, ky) != (0, 0) && 2 * kx.abs() <= r && 2 * ky.abs() <= r {
                preds.push(Prediction::new((kx, ky), (2 * kx, 2 * ky), EXTRAPOLATION));
            }
        }
    }
    let model = Mixture {
        sigma_m: p.sigma_m,
        sigma_rel: p.sigma_rel,
    };
    out_z
        .par_chunks_mut(w)
        .zip(out_c.par_chunks_mut(w))
        .enumerate()
        .for_each(|(y, (row_z, row_c))| {
            let at = y * w;
            if c[at..at + w].iter().all(|c| *c <= 0.0) {
                return;
            }
            let zi: Vec<f64> = z[at..at + w].iter().map(|z| *z as f64).collect();
            let mut num = vec![0.0f64; w];
            let mut den = vec![0.0f64; w];
            for pr in &preds {
                let (Some(ya), Some(yb)) = (shifted(y, pr.a.1, h), shifted(y, pr.b.1, h)) else {
                    continue;
                };
                // columns whose two neighbours are inside the image
                let lo = [0, -pr.a.0, -pr.b.0].into_iter().max().unwrap_or(0);
                let hi = [w as isize, w as isize - pr.a.0, w as isize - pr.b.0]
                    .into_iter()
                    .min()
                    .unwrap_or(0);
                if lo >= hi {
                    continue; // the image is narrower than the offsets
                }
                let (lo, hi) = (lo as usize, hi as usize);
                let n = hi - lo;
                let sa = (ya * w + lo) as isize + pr.a.0;
                let sb = (yb * w + lo) as isize + pr.b.0;
                let (sa, sb) = (sa as usize, sb as usize);
                model.add_row(
                    pr,
                    (&q[sa..sa + n], &q[sb..sb + n]),
                    (&c[sa..sa + n], &c[sb..sb + n]),
                    &zi[lo..hi],
                    (&mut num[lo..hi], &mut den[lo..hi]),
                );
            }
            for x in 0..w {
                let i = at + x;
                if c[i] <= 0.0 || den[x] <= 0.0 {
                    continue; // not a measurement, or no evidence: kept as it is
                }
                let p_valid = num[x] / den[x]; // guard: den > 0
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

/// `y + dy` when it is a row of an image `h` rows high.
fn shifted(y: usize, dy: isize, h: usize) -> Option<usize> {
    let v = y as isize + dy;
    (v >= 0 && v < h as isize).then_some(v as usize)
}

/// One prediction of a pixel's inverse depth from two neighbours at
/// offsets `a` and `b`: the midpoint `(q_a + q_b) / 2` of an opposite pair
/// (variance factor 1.5) or the extrapolation `2 q_a - q_b` (factor 6).
struct Prediction {
    a: (isize, isize),
    b: (isize, isize),
    /// Weights of `q_a` and `q_b`.
    wa: f64,
    wb: f64,
    /// `-1 / (2 k)` and `1 / sqrt(2 pi k)` of the variance factor `k`.
    neg_half_inv_k: f64,
    inv_root: f64,
}

/// The midpoint of an opposite pair: weights of `q_a` and `q_b`, and the
/// variance factor (the pixel's own noise plus half of each neighbour's).
const MIDPOINT: ((f64, f64), f64) = ((0.5, 0.5), 1.5);
/// The one-sided extrapolation `2 q_a - q_b`: weights and variance factor.
const EXTRAPOLATION: ((f64, f64), f64) = ((2.0, -1.0), 6.0);

impl Prediction {
    fn new(a: (isize, isize), b: (isize, isize), ((wa, wb), k): ((f64, f64), f64)) -> Self {
        // Guard: k > 0 (the constants above).
        Self {
            a,
            b,
            wa,
            wb,
            neg_half_inv_k: -0.5 / k,
            inv_root: 1.0 / (std::f64::consts::TAU * k).sqrt(),
        }
    }
}

/// The noise model of the normal component: `sigma = sigma_m + sigma_rel z`.
struct Mixture {
    sigma_m: f64,
    sigma_rel: f64,
}

impl Mixture {
    crate::kit::cpu::simd_versions! {
        /// Adds one prediction's term to the kernel density of a row's pixels:
        /// `num += wgt N(z_i; z_p, k sigma(z_p)^2)`, `den += wgt`, with
        /// `wgt = c_a c_b` and `z_p = 1 / q_p` wherever both neighbours are
        /// measurements and `q_p > 0` (finite). With `q_p = 1 / z_p`,
        /// `(z_i - z_p) / sigma = (z_i q_p - 1) / (sigma_m q_p + sigma_rel)` and
        /// `1 / sigma = q_p / (sigma_m q_p + sigma_rel)`: one division per term
        /// (guard: the divisor is at least `sigma_m q_p > 0` where used; other
        /// lanes divide by a selected 1). No branch: the loop vectorises.
        ///
        /// On x86-64 CPUs with AVX-512 F or AVX2 the loop is compiled again with
        /// those instructions and the best is chosen at run time (the same
        /// arithmetic lane by lane, so the same bits: Rust fuses no multiply
        /// and add on its own; tested).
        fn add_row(
            &self,
            pr: &Prediction,
            q: (&[f64], &[f64]),
            c: (&[f32], &[f32]),
            zi: &[f64],
            sums: (&mut [f64], &mut [f64]),
        );
        avx2: add_row_avx2, avx512: add_row_avx512, body: add_row_body,
    }

    /// The loop of [`Mixture::add_row`].
    #[inline(always)]
    fn add_row_body(
        &self,
        pr: &Prediction,
        (qa, qb): (&[f64], &[f64]),
        (ca, cb): (&[f32], &[f32]),
        zi: &[f64],
        (num, den): (&mut [f64], &mut [f64]),
    ) {
        let n = zi.len();
        let (qa, qb, ca, cb) = (&qa[..n], &qb[..n], &ca[..n], &cb[..n]);
        let (num, den) = (&mut num[..n], &mut den[..n]);
        for x in 0..n {
            let wgt = ca[x] as f64 * cb[x] as f64;
            let qp = pr.wa * qa[x] + pr.wb * qb[x];
            // `&`, not `&&`: no branch (NaN fails `qp > 0`)
            let ok = (wgt > 0.0) & (qp > 0.0) & (qp < f64::INFINITY);
            let qs = if ok { qp } else { 1.0 };
            let inv = 1.0 / (self.sigma_m * qs + self.sigma_rel);
            let t = (zi[x] * qs - 1.0) * inv;
            let pdf = exp_neg(pr.neg_half_inv_k * t * t) * pr.inv_root * qs * inv;
            num[x] += if ok { wgt * pdf } else { 0.0 };
            den[x] += if ok { wgt } else { 0.0 };
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kit::rng::SplitMix64;

    /// The mixture model pixel by pixel, as written in the paper's terms
    /// (a normal density with its square root and libm's exponential): the
    /// reference of the row loops.
    fn reference(z: &[f32], c: &[f32], w: usize, h: usize, p: &PruneParams) -> Vec<Option<f64>> {
        let valid: Vec<f64> = z
            .iter()
            .zip(c)
            .filter(|(_, c)| **c > 0.0)
            .map(|(z, _)| *z as f64)
            .collect();
        let (zmin, zmax) = valid
            .iter()
            .fold((f64::INFINITY, 0.0f64), |(a, b), z| (a.min(*z), b.max(*z)));
        let sigma = |z: f64| p.sigma_m + p.sigma_rel * z;
        let uniform = 1.0 / (zmax - zmin).max(8.0 * sigma(zmax));
        let pi_u = p.prior * uniform;
        let r = p.radius as isize;
        let at = |x: isize, y: isize| -> Option<usize> {
            let inside = x >= 0 && y >= 0 && x < w as isize && y < h as isize;
            let i = (y * w as isize + x) as usize;
            (inside && c[i] > 0.0).then_some(i)
        };
        let q = |i: usize| 1.0 / z[i] as f64;
        (0..w * h)
            .map(|i| {
                if c[i] <= 0.0 {
                    return None;
                }
                let (x, y) = ((i % w) as isize, (i / w) as isize);
                let (mut num, mut den) = (0.0, 0.0);
                let mut add = |qp: f64, k: f64, wgt: f64| {
                    if qp > 0.0 && qp.is_finite() {
                        let zp = 1.0 / qp;
                        let var = k * sigma(zp) * sigma(zp);
                        let d = z[i] as f64 - zp;
                        num +=
                            wgt * (-0.5 * d * d / var).exp() / (std::f64::consts::TAU * var).sqrt();
                        den += wgt;
                    }
                };
                for ky in -r..=r {
                    for kx in -r..=r {
                        if (ky > 0 || (ky == 0 && kx > 0))
                            && let (Some(a), Some(b)) = (at(x + kx, y + ky), at(x - kx, y - ky))
                        {
                            add(0.5 * (q(a) + q(b)), 1.5, c[a] as f64 * c[b] as f64);
                        }
                    }
                }
                for ky in -r..=r {
                    for kx in -r..=r {
                        if (kx, ky) != (0, 0)
                            && 2 * kx.abs() <= r
                            && 2 * ky.abs() <= r
                            && let (Some(a), Some(b)) =
                                (at(x + kx, y + ky), at(x + 2 * kx, y + 2 * ky))
                        {
                            add(2.0 * q(a) - q(b), 6.0, c[a] as f64 * c[b] as f64);
                        }
                    }
                }
                (den > 0.0).then(|| pi_u / (pi_u + (1.0 - p.prior) * num / den))
            })
            .collect()
    }

    #[test]
    fn every_compiled_row_loop_gives_the_same_bits() {
        let n = 203;
        let mut rng = SplitMix64(5);
        let mut v = |lo: f64, hi: f64| lo + (hi - lo) * rng.uniform();
        let qa: Vec<f64> = (0..n).map(|_| v(0.2, 1.0)).collect();
        let qb: Vec<f64> = (0..n).map(|_| v(-0.1, 1.0)).collect();
        let ca: Vec<f32> = (0..n).map(|_| v(-0.5, 1.0).max(0.0) as f32).collect();
        let cb: Vec<f32> = (0..n).map(|_| v(-0.5, 1.0).max(0.0) as f32).collect();
        let zi: Vec<f64> = (0..n).map(|_| v(1.0, 5.0)).collect();
        let model = Mixture {
            sigma_m: 0.002,
            sigma_rel: 0.003,
        };
        let run = |f: &dyn Fn(&mut [f64], &mut [f64])| {
            let (mut num, mut den) = (vec![0.1f64; n], vec![0.2f64; n]);
            f(&mut num, &mut den);
            (num, den)
        };
        let preds = [
            Prediction::new((1, 0), (-1, 0), MIDPOINT),
            Prediction::new((0, 1), (0, 2), EXTRAPOLATION),
        ];
        let plain = run(&|num, den| {
            for pr in &preds {
                model.add_row_body(pr, (&qa, &qb), (&ca, &cb), &zi, (num, den));
            }
        });
        assert!(
            plain
                .0
                .iter()
                .zip(&plain.1)
                .all(|(a, b)| a.is_finite() && b.is_finite())
        );
        let bits = |v: &(Vec<f64>, Vec<f64>)| -> Vec<u64> {
            v.0.iter().chain(&v.1).map(|x| x.to_bits()).collect()
        };
        let dispatched = run(&|num, den| {
            for pr in &preds {
                model.add_row(pr, (&qa, &qb), (&ca, &cb), &zi, (num, den));
            }
        });
        assert_eq!(bits(&dispatched), bits(&plain));
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx2") {
                let v = run(&|num, den| {
                    for pr in &preds {
                        // SAFETY: the CPU has AVX2.
                        unsafe { model.add_row_avx2(pr, (&qa, &qb), (&ca, &cb), &zi, (num, den)) };
                    }
                });
                assert_eq!(bits(&v), bits(&plain));
            }
            if crate::kit::cpu::avx512() {
                let v = run(&|num, den| {
                    for pr in &preds {
                        // SAFETY: the CPU has AVX-512 F and what it implies.
                        unsafe {
                            model.add_row_avx512(pr, (&qa, &qb), (&ca, &cb), &zi, (num, den))
                        };
                    }
                });
                assert_eq!(bits(&v), bits(&plain));
            }
        }
    }

    #[test]
    fn the_row_loops_match_the_per_pixel_model() {
        let (w, h) = (41, 23);
        let mut rng = SplitMix64(17);
        let mut z = vec![0.0f32; w * h];
        let mut c = vec![0.0f32; w * h];
        for i in 0..w * h {
            let (x, y) = ((i % w) as f64, (i / w) as f64);
            if rng.uniform() < 0.15 {
                continue; // a hole
            }
            // a tilted plane, a step, noise and a few spikes
            let base = if x < 20.0 {
                1.0 + 0.01 * x + 0.005 * y
            } else {
                2.5
            };
            let spike = if rng.uniform() < 0.03 { 1.5 } else { 0.0 };
            z[i] = (base + 0.004 * rng.gaussian() + spike) as f32;
            c[i] = (0.3 + 0.7 * rng.uniform()) as f32;
        }
        let depth = DepthMap::from_vec(w, h, z.clone()).unwrap();
        let conf = Confidence::from_vec(w, h, c.clone()).unwrap();
        for radius in [1, 2, 3] {
            let p = PruneParams {
                radius,
                ..PruneParams::default()
            };
            let (dz, dc) = prune_outliers(&depth, Some(&conf), &p).unwrap();
            let want = reference(&z, &c, w, h, &p);
            let (mut pruned, mut worst) = (0, 0.0f64);
            for i in 0..w * h {
                let Some(p_out) = want[i] else {
                    // holes and pixels without evidence are kept as they are
                    assert_eq!((dz.as_slice()[i], dc.as_slice()[i]), (z[i], c[i]));
                    continue;
                };
                if p_out > p.threshold {
                    pruned += 1;
                    assert_eq!(
                        (dz.as_slice()[i], dc.as_slice()[i]),
                        (0.0, 0.0),
                        "pixel {i}"
                    );
                } else {
                    let expect = c[i] as f64 * (1.0 - p_out);
                    worst = worst.max((dc.as_slice()[i] as f64 - expect).abs());
                }
            }
            assert!(pruned > 5, "radius {radius}: {pruned} pruned");
            // the confidences agree to f32 rounding
            assert!(worst <= 1e-7, "radius {radius}: {worst:e}");
        }
    }
}
