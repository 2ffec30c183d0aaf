//! The NL-means pass (eq. 1-3): patch distances, weights, the weighted average, in bands.

use depthgraph_graph::prelude::*;
use rayon::prelude::*;

use super::common::*;
use super::params::*;

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
pub(super) struct Acc {
    /// Largest exponent of all candidates; reference of `sim`, `sim_conf`.
    pub(super) ms: f64,
    /// `sum_j s(i, j)`: similarity weights (without `zeta(j)`).
    pub(super) sim: f64,
    /// `sum_j s(i, j) zeta(j)`.
    pub(super) sim_conf: f64,
    /// Largest exponent of the sources (confidence > 0); reference of `w`, `wv`.
    pub(super) mw: f64,
    /// `Z_i = sum_j w(i, j)`, the weights of eq. 1.
    pub(super) w: f64,
    /// `sum_j w(i, j) v(j)`.
    pub(super) wv: f64,
    /// Range of the values with a positive weight.
    pub(super) lo: f32,
    pub(super) hi: f32,
}

impl Acc {
    pub(super) const EMPTY: Acc = Acc {
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
    pub(super) fn add(&mut self, e: f64, conf: f32, prior: f64, v: f32) {
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
    pub(super) fn finish(&self) -> Option<(f32, f32)> {
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
pub(super) trait PairKernel: Sync {
    /// Adds candidate `j` to the sums of target `i`; `d >= 0` is their mean
    /// patch distance (already divided by the h's).
    fn add(&self, i: usize, j: usize, d: f64, acc: &mut Acc);
}

/// One NL-means pass over a `w` x `h` grid.
pub(super) struct Pass<'a> {
    pub(super) w: usize,
    pub(super) h: usize,
    /// Guide features, `w * h`.
    pub(super) guide: &'a [[f32; 3]],
    /// Depth and confidence for the depth patch term (eq. 5), or none.
    pub(super) depth: Option<(&'a [f32], &'a [f32])>,
    pub(super) core: Core,
}

/// Sums of one band of rows, columns `[xa, xa + bw)`.
pub(super) struct BandOut {
    pub(super) y0: usize,
    pub(super) xa: usize,
    pub(super) bw: usize,
    pub(super) acc: Vec<Acc>,
}

/// Radii of the nested boxes whose average is the patch kernel (see
/// [`PatchKernel`]).
pub(super) fn box_radii(r: usize) -> Vec<usize> {
    let mut radii = vec![0, r.div_ceil(2), r];
    radii.dedup();
    radii
}

/// The patch kernel: the average of the box means over the radii of
/// [`box_radii`], a centre-weighted approximation of the paper's Gaussian
/// `G_a` (for radius 2 the centre pixel weighs 0.38, the 8 pixels around it
/// 0.05 each, the outer 16 pixels 0.013 each) that keeps box sums.
pub(super) struct PatchKernel {
    pub(super) radii: Vec<usize>,
    /// Weight of one pixel of each box: `1 / (boxes * area)`.
    pub(super) coef: Vec<f64>,
    /// Per-pixel distances are capped here: the smallest pixel weight times
    /// the cap is [`EXP_CUTOFF`], so the cap changes no weight.
    pub(super) cap: f64,
}

impl PatchKernel {
    pub(super) fn new(r: usize) -> Self {
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
pub(super) fn band<K: PairKernel>(
    pass: &Pass,
    targets: &[bool],
    kernel: &K,
    y0: usize,
    y1: usize,
) -> BandOut {
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
pub(super) fn run_pass<K: PairKernel>(
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
pub(super) struct DepthKernel<'a> {
    pub(super) z: &'a [f32],
    pub(super) c: &'a [f32],
    pub(super) inv_hd2: f64,
    /// `1 / z_ref` of the far-depth prior `(z_j / z_ref)^2`.
    pub(super) far: Option<f64>,
    /// The background side: `β`, `τ` and the largest source depth in each
    /// pixel's search window (see `PassJob::background`).
    pub(super) background: Option<(f64, f64, &'a [f32])>,
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
        let mut prior = match self.far {
            Some(inv_ref) => {
                let r = zj as f64 * inv_ref;
                r * r
            }
            None => 1.0,
        };
        if let Some((beta, tau, local_max)) = self.background {
            let z_max = local_max[i] as f64;
            if z_max > 0.0 {
                // guard: z_max > 0; the factor lies in (0, 1] and is 1 for the
                // farthest source, so the window's estimate always exists
                // (an underflow to 0 only drops a near candidate)
                let step = (z_max - zj as f64) / z_max;
                prior *= (-beta * (step - tau).max(0.0)).exp();
            }
        }
        acc.add(-(d + xi), cj, prior, zj);
    }
}
