//! The NL-means pass (eq. 1-3): patch distances, weights, the weighted average, in bands.

use std::ops::{Add, AddAssign, Div, Mul, Sub};
use std::sync::Arc;

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

/// The float type a pass computes its patch distances in: f64 for the
/// per-pair kernels ([`PerPair`], the exact reference), f32 for the depth
/// kernel's vectorised rows (twice the lanes; its bound against the f64
/// pass is in the `depth_rows` module docs).
pub(super) trait Real:
    Copy
    + Send
    + Sync
    + PartialOrd
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + AddAssign
    + 'static
{
    /// 0.
    const ZERO: Self;
    /// An f32 value (exact for both types).
    fn of_f32(v: f32) -> Self;
    /// An f64 value, rounded to the type.
    fn of_f64(v: f64) -> Self;
    /// The smaller of two values.
    fn min(self, o: Self) -> Self;
    /// The larger of two values.
    fn max(self, o: Self) -> Self;
    /// The value as f64 (exact for both types).
    fn to_f64(self) -> f64;
}

/// [`Real`] for a float type: `as` casts between f32, f64 and the type
/// (exact from f32, rounded to f32 from f64), its own `min` and `max`.
macro_rules! real_impl {
    ($t:ty) => {
        impl Real for $t {
            const ZERO: $t = 0.0;
            #[inline(always)]
            fn of_f32(v: f32) -> $t {
                v as $t
            }
            #[inline(always)]
            fn of_f64(v: f64) -> $t {
                v as $t
            }
            #[inline(always)]
            fn min(self, o: $t) -> $t {
                <$t>::min(self, o)
            }
            #[inline(always)]
            fn max(self, o: $t) -> $t {
                <$t>::max(self, o)
            }
            #[inline(always)]
            fn to_f64(self) -> f64 {
                self as f64
            }
        }
    };
}

real_impl!(f64);
real_impl!(f32);

/// What a pass does with a candidate pair.
pub(super) trait PairKernel: Sync {
    /// Adds candidate `j` to the sums of target `i`; `d >= 0` is their mean
    /// patch distance (already divided by the h's).
    fn add(&self, i: usize, j: usize, d: f64, acc: &mut Acc);
    /// Whether any pixel of grid row `y` can be a candidate: `false` lets
    /// the pass skip the rows whose candidates lie there (their
    /// distances and `add` calls), which changes no sum.
    fn row_has_candidates(&self, _y: usize) -> bool {
        true
    }
}

/// The candidates of one band row at one search offset: targets at image
/// columns `x0..x0 + dist.len()` of row `y`, each with the candidate `dx`
/// columns away on row `yj`.
pub(super) struct RowCands<'a, R> {
    pub(super) y: usize,
    pub(super) yj: usize,
    pub(super) x0: usize,
    pub(super) dx: isize,
    /// Mean patch distance of each target and its candidate (divided by the h's).
    pub(super) dist: &'a [R],
    /// Which of the row's pixels are targets (aligned with `dist`).
    pub(super) targets: &'a [bool],
    /// Index of the first target's sums in the band's sums.
    pub(super) at: usize,
}

/// A target's result once every candidate was added.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) enum Finish {
    /// The estimate and confidence, or `None` without a source.
    Done(Option<(f32, f32)>),
    /// The kernel's sums cannot give the estimate to its stated precision
    /// (every source's weight near underflow): run the target again with
    /// the exact per-pair kernel.
    Exact,
}

/// What a pass does with a band row of candidate pairs: [`PerPair`] adapts
/// any [`PairKernel`]; the depth kernel has its own vectorised rows.
pub(super) trait RowKernel: Sync {
    /// The float type of the patch distances the kernel takes.
    type Real: Real;
    /// The sums of a band's targets.
    type Sums: Send;
    /// Empty sums for `len` targets.
    fn sums(&self, len: usize) -> Self::Sums;
    /// Adds one row of candidates (`w` is the grid's width).
    fn add_row(&self, w: usize, row: &RowCands<Self::Real>, sums: &mut Self::Sums);
    /// The result of target `k` of the sums.
    fn finish(&self, sums: &Self::Sums, k: usize) -> Finish;
    /// See [`PairKernel::row_has_candidates`].
    fn row_has_candidates(&self, _y: usize) -> bool {
        true
    }
}

/// A [`PairKernel`] run candidate by candidate with the running sums of [`Acc`].
pub(super) struct PerPair<'a, K>(pub(super) &'a K);

impl<K: PairKernel> RowKernel for PerPair<'_, K> {
    type Real = f64;
    type Sums = Vec<Acc>;

    fn sums(&self, len: usize) -> Vec<Acc> {
        vec![Acc::EMPTY; len]
    }

    fn add_row(&self, w: usize, row: &RowCands<f64>, sums: &mut Vec<Acc>) {
        for (k, (&d, &t)) in row.dist.iter().zip(row.targets).enumerate() {
            if !t {
                continue;
            }
            let x = row.x0 + k;
            let xj = (x as isize + row.dx) as usize;
            self.0
                .add(row.y * w + x, row.yj * w + xj, d, &mut sums[row.at + k]);
        }
    }

    fn finish(&self, sums: &Vec<Acc>, k: usize) -> Finish {
        Finish::Done(sums[k].finish())
    }

    fn row_has_candidates(&self, y: usize) -> bool {
        self.0.row_has_candidates(y)
    }
}

/// One NL-means pass over a `w` x `h` grid.
pub(super) struct Pass<'a> {
    pub(super) w: usize,
    pub(super) h: usize,
    /// Depth and confidence for the depth patch term (eq. 5), or none.
    pub(super) depth: Option<(&'a [f32], &'a [f32])>,
    pub(super) core: Core,
    /// The guide (and depth) planes, padded for every patch and offset.
    pub(super) padded: Padded,
}

impl<'a> Pass<'a> {
    /// A pass over the `w` x `h` grid of `guide` (features, `w * h`).
    pub(super) fn new(
        (w, h): (usize, usize),
        guide: &[[f32; 3]],
        depth: Option<(&'a [f32], &'a [f32])>,
        core: Core,
    ) -> Self {
        let guide = Arc::new(PaddedGuide::new((w, h), guide, core.patch + core.search));
        Self::with_guide((w, h), guide, depth, core)
    }

    /// [`Pass::new`] with the guide's planes already padded (by
    /// `core.patch + core.search`, see [`PaddedGuide::pad`]): passes over
    /// one guide share them.
    pub(super) fn with_guide(
        (w, h): (usize, usize),
        guide: Arc<PaddedGuide>,
        depth: Option<(&'a [f32], &'a [f32])>,
        core: Core,
    ) -> Self {
        Self {
            w,
            h,
            depth,
            core,
            padded: Padded::new((w, h), guide, depth),
        }
    }
}

/// The guide's channels as planes whose rows are extended by `pad` columns
/// on each side with the border pixel's values (see [`Padded`]).
pub(super) struct PaddedGuide {
    pad: usize,
    g: [Vec<f32>; 3],
}

impl PaddedGuide {
    pub(super) fn new((w, h): (usize, usize), guide: &[[f32; 3]], pad: usize) -> Self {
        Self {
            pad,
            g: [0, 1, 2].map(|k| padded_plane((w, h), pad, |i| guide[i][k])),
        }
    }

    /// The columns added on each side.
    pub(super) fn pad(&self) -> usize {
        self.pad
    }
}

/// One plane of `w x h` values `at(i)`, each row extended by `pad` columns
/// on each side with its border value (rows in parallel).
fn padded_plane<F: Fn(usize) -> f32 + Sync>((w, h): (usize, usize), pad: usize, at: F) -> Vec<f32> {
    if w == 0 {
        return Vec::new();
    }
    let stride = w + 2 * pad;
    let mut out = vec![0.0f32; stride * h];
    out.par_chunks_mut(stride).enumerate().for_each(|(y, row)| {
        let (left, rest) = row.split_at_mut(pad);
        let (mid, right) = rest.split_at_mut(w);
        left.fill(at(y * w));
        for (x, o) in mid.iter_mut().enumerate() {
            *o = at(y * w + x);
        }
        right.fill(at(y * w + w - 1));
    });
    out
}

/// The guide's channels (and depth and confidence) as planes whose rows
/// are extended by `pad` columns on each side with the border pixel's
/// values: the patch pixels of every target and candidate of a row are
/// then one contiguous slice (the clamped coordinates of the patches).
pub(super) struct Padded {
    pub(super) pad: usize,
    stride: usize,
    g: Arc<PaddedGuide>,
    z: Vec<f32>,
    c: Vec<f32>,
}

impl Padded {
    fn new((w, h): (usize, usize), g: Arc<PaddedGuide>, depth: Option<(&[f32], &[f32])>) -> Self {
        let pad = g.pad;
        let (z, c) = match depth {
            Some((z, c)) => (
                padded_plane((w, h), pad, |i| z[i]),
                padded_plane((w, h), pad, |i| c[i]),
            ),
            None => (Vec::new(), Vec::new()),
        };
        Self {
            pad,
            stride: w + 2 * pad,
            g,
            z,
            c,
        }
    }

    /// The guide channels of row `y`, padded columns `start..start + len`.
    #[inline]
    pub(super) fn row(&self, y: usize, start: usize, len: usize) -> [&[f32]; 3] {
        let a = y * self.stride + start;
        [0, 1, 2].map(|k| &self.g.g[k][a..a + len])
    }

    /// The depth of row `y`, padded columns `start..start + len` (a pass with depth).
    #[inline]
    pub(super) fn z_row(&self, y: usize, start: usize, len: usize) -> &[f32] {
        let a = y * self.stride + start;
        &self.z[a..a + len]
    }

    /// The confidence of row `y`, padded columns `start..start + len`.
    #[inline]
    pub(super) fn c_row(&self, y: usize, start: usize, len: usize) -> &[f32] {
        let a = y * self.stride + start;
        &self.c[a..a + len]
    }
}

/// Sums of one band of rows, columns `[xa, xa + bw)`.
pub(super) struct BandOut<S> {
    pub(super) y0: usize,
    pub(super) xa: usize,
    pub(super) bw: usize,
    pub(super) bh: usize,
    pub(super) sums: Option<S>,
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

crate::kit::cpu::simd_versions! {
    /// Computes the sums of every target pixel of rows `rows = [y0, y1)`, columns
    /// `cols = [x0, x1)`.
    ///
    /// On x86-64 CPUs with AVX-512 F or AVX2 the same code is compiled again
    /// with those instructions (AVX2: 8 f32 or 4 f64 lanes instead of SSE2's
    /// 4 and 2; AVX-512's 32 vector registers keep the f32 rows' constants
    /// in registers, about 10 % faster than AVX2 on the 2-core test machine)
    /// and the best the CPU has is chosen at run time. Each lane computes
    /// what the scalar code computes, in the same order (Rust never fuses a
    /// multiply and an add on its own, and no sum runs across lanes), so
    /// every version gives the same bits (tested against [`band_body`]
    /// called plainly).
    pub(super) fn band<K: RowKernel>(
        pass: &Pass,
        targets: &[bool],
        kernel: &K,
        rows: (usize, usize),
        cols: (usize, usize),
    ) -> BandOut<K::Sums>;
    avx2: band_avx2, avx512: band_avx512, body: band_body,
}

/// The work of [`band`].
#[inline(always)]
pub(super) fn band_body<K: RowKernel>(
    pass: &Pass,
    targets: &[bool],
    kernel: &K,
    (y0, y1): (usize, usize),
    (x0, x1): (usize, usize),
) -> BandOut<K::Sums> {
    let (w, h) = (pass.w, pass.h);
    // The rectangle of the tile's targets: only its rows and columns are
    // computed (a pixel's sums are box sums of its own patch, whatever
    // rectangle it is in).
    let (mut xa, mut xb) = (x1, x0);
    let (mut ya, mut yb) = (y1, y0);
    for y in y0..y1 {
        let row = &targets[y * w + x0..y * w + x1];
        if let Some(first) = row.iter().position(|t| *t) {
            xa = xa.min(x0 + first);
            ya = ya.min(y);
            yb = y + 1;
        }
        if let Some(last) = row.iter().rposition(|t| *t) {
            xb = xb.max(x0 + last + 1);
        }
    }
    let (y0, y1) = (ya, yb);
    if xa >= xb || y0 >= y1 {
        return BandOut {
            y0,
            xa: 0,
            bw: 0,
            bh: 0,
            sums: None,
        };
    }
    let (bw, bh) = (xb - xa, y1 - y0);
    let r = pass.core.patch;
    let n = 2 * r + 1;
    let (ew, eh) = (bw + n - 1, bh + n - 1);
    let pk = PatchKernel::new(r);
    let nb = pk.radii.len();
    let (inv_hc2, inv_hd2) = (
        K::Real::of_f64(pass.core.inv_hc2),
        K::Real::of_f64(pass.core.inv_hd2),
    );
    let cap = K::Real::of_f64(pk.cap);
    let coefs: Vec<K::Real> = pk.coef.iter().map(|c| K::Real::of_f64(*c)).collect();
    let zero = K::Real::ZERO;
    let big_r = pass.core.search as isize;
    let clampi = |v: isize, len: usize| v.clamp(0, len as isize - 1) as usize;
    let pad = &pass.padded;
    // Extended column e of the band is padded column `e0 + e`; its candidate
    // at offset dx is `e0 + e + dx`.
    let e0 = pad.pad + xa - r;
    let mut d = vec![zero; ew];
    // Horizontal box sums of every extended row, per box.
    let mut hs = vec![zero; nb * eh * bw];
    let mut sums = kernel.sums(bw * bh);
    // Patch distances of the current row's targets.
    let mut drow = vec![zero; bw];
    // Each band row's targets, first to last (band columns): at every
    // offset the vertical sums and the kernel run over that span, clipped
    // to the offset's columns (pixels in it that are no targets get sums
    // nobody reads, which costs less than a run per group of scattered
    // holes: each run's setup and its loops' scalar ends); rows without a
    // target are skipped. Each pixel's arithmetic is the same whatever
    // span it is in, so the results are too.
    let spans: Vec<Option<(usize, usize)>> = (0..bh)
        .map(|t| {
            let row = &targets[(y0 + t) * w + xa..(y0 + t) * w + xa + bw];
            let a = row.iter().position(|v| *v)?;
            let b = row.iter().rposition(|v| *v)?;
            Some((a, b + 1))
        })
        .collect();
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
            let eo = (e0 as isize + dx) as usize;
            // Per-pixel distances of the extended rows needed by rows [t0, t1),
            // then horizontal box sums.
            for er in t0..t1 + n - 1 {
                let y = clampi(y0 as isize - r as isize + er as isize, h);
                let yo = clampi(y0 as isize - r as isize + er as isize + dy, h);
                let (ga, gb) = (pad.row(y, e0, ew), pad.row(yo, eo, ew));
                // (the colour term written out in both loops: a closure is
                // not always inlined, and one called per pixel would run
                // without the band's vector instructions)
                if pass.depth.is_some() {
                    let (za, ca) = (pad.z_row(y, e0, ew), pad.c_row(y, e0, ew));
                    let (zb, cb) = (pad.z_row(yo, eo, ew), pad.c_row(yo, eo, ew));
                    for (k, de) in d.iter_mut().enumerate() {
                        let d0 = ga[0][k] - gb[0][k];
                        let d1 = ga[1][k] - gb[1][k];
                        let d2 = ga[2][k] - gb[2][k];
                        let colour = K::Real::of_f32(d0 * d0 + d1 * d1 + d2 * d2) * inv_hc2;
                        // holes have confidence 0 and depth 0: the term is 0
                        let cc = K::Real::of_f32(ca[k] * cb[k]);
                        let dz = K::Real::of_f32(za[k]) - K::Real::of_f32(zb[k]);
                        *de = (colour + cc * dz * dz * inv_hd2).min(cap);
                    }
                } else {
                    for (k, de) in d.iter_mut().enumerate() {
                        let d0 = ga[0][k] - gb[0][k];
                        let d1 = ga[1][k] - gb[1][k];
                        let d2 = ga[2][k] - gb[2][k];
                        let colour = K::Real::of_f32(d0 * d0 + d1 * d1 + d2 * d2) * inv_hc2;
                        *de = colour.min(cap);
                    }
                }
                for (b, &sr) in pk.radii.iter().enumerate() {
                    // Box of radius sr centred on extended column x + r,
                    // summed directly (no running sum, so no drift).
                    let lo = r - sr;
                    let hrow = &mut hs[(b * eh + er) * bw..(b * eh + er + 1) * bw];
                    sum_shifted(hrow, &d[lo..], 2 * sr + 1);
                }
            }
            // Vertical box sums and the kernel over each row's span.
            for (t, span) in spans.iter().enumerate().take(t1).skip(t0) {
                let Some((a, b)) = *span else { continue };
                let (a, b) = (a.max(c0), b.min(c1));
                let y = y0 + t;
                if a >= b || !kernel.row_has_candidates((y as isize + dy) as usize) {
                    continue;
                }
                let dist = &mut drow[a..b];
                patch_distances(dist, &hs, (&pk.radii, &coefs), (eh, bw), (t + r, a));
                let row = RowCands {
                    y,
                    yj: (y as isize + dy) as usize,
                    x0: xa + a,
                    dx,
                    dist,
                    targets: &targets[y * w + xa + a..y * w + xa + b],
                    at: t * bw + a,
                };
                kernel.add_row(w, &row, &mut sums);
            }
        }
    }
    BandOut {
        y0,
        xa,
        bw,
        bh,
        sums: Some(sums),
    }
}

/// Lanes of the box-sum loops: each output's sum is held in registers of
/// this many values while its terms are added (several independent
/// additions in flight).
const LANES: usize = 16;

/// `out[x] = sum_{k < n} src[x + k]`, each output summed directly (no
/// running sum, so no drift), its terms in the order of `k`.
#[inline(always)]
fn sum_shifted<R: Real>(out: &mut [R], src: &[R], n: usize) {
    let len = out.len();
    let src = &src[..len + n - 1];
    // LANES columns at a time, then 8 and 4 (a narrow band of scattered
    // holes is mostly such a rest), then one by one
    let mut x = sum_shifted_by::<R, LANES>(out, src, n, 0);
    x = sum_shifted_by::<R, 8>(out, src, n, x);
    x = sum_shifted_by::<R, 4>(out, src, n, x);
    sum_shifted_by::<R, 1>(out, src, n, x);
}

/// [`sum_shifted`]'s outputs from `x` on, `L` at a time while `L` remain;
/// returns where it stopped.
#[inline(always)]
fn sum_shifted_by<R: Real, const L: usize>(
    out: &mut [R],
    src: &[R],
    n: usize,
    mut x: usize,
) -> usize {
    let len = out.len();
    while x + L <= len {
        let mut acc = [R::ZERO; L];
        for k in 0..n {
            let s = &src[x + k..x + k + L];
            for l in 0..L {
                acc[l] += s[l];
            }
        }
        out[x..x + L].copy_from_slice(&acc);
        x += L;
    }
    x
}

/// The patch distances of one row of a band's targets, columns
/// `c0..c0 + dist.len()`: `sum_b coef_b (vertical box sum of radius
/// sr_b over the horizontal sums hs_b)`, rows centred on extended row
/// `centre`. Each box sum is summed directly from its rows (no running sum:
/// in f32 one would drift by an ulp of the largest sum per row), in a
/// register, then weighted (the order fixed: boxes, then rows).
#[inline(always)]
fn patch_distances<R: Real>(
    dist: &mut [R],
    hs: &[R],
    (radii, coefs): (&[usize], &[R]),
    (eh, bw): (usize, usize),
    (centre, c0): (usize, usize),
) {
    // as in `sum_shifted`: LANES, 8 and 4 columns at a time, then one by one
    let geom = ((radii, coefs), (eh, bw), (centre, c0));
    let mut x = patch_distances_by::<R, LANES>(dist, hs, geom, 0);
    x = patch_distances_by::<R, 8>(dist, hs, geom, x);
    x = patch_distances_by::<R, 4>(dist, hs, geom, x);
    patch_distances_by::<R, 1>(dist, hs, geom, x);
}

/// [`patch_distances`]'s outputs from `x` on, `L` at a time while `L`
/// remain; returns where it stopped.
#[inline(always)]
#[allow(clippy::type_complexity)]
fn patch_distances_by<R: Real, const L: usize>(
    dist: &mut [R],
    hs: &[R],
    ((radii, coefs), (eh, bw), (centre, c0)): ((&[usize], &[R]), (usize, usize), (usize, usize)),
    mut x: usize,
) -> usize {
    let len = dist.len();
    let at = |b: usize, row: usize, x: usize| (b * eh + row) * bw + c0 + x;
    while x + L <= len {
        let mut tot = [R::ZERO; L];
        for (b, (&sr, &coef)) in radii.iter().zip(coefs).enumerate() {
            let mut acc = [R::ZERO; L];
            for row in centre - sr..=centre + sr {
                let a = at(b, row, x);
                let s = &hs[a..a + L];
                for l in 0..L {
                    acc[l] += s[l];
                }
            }
            for l in 0..L {
                tot[l] += coef * acc[l];
            }
        }
        dist[x..x + L].copy_from_slice(&tot);
        x += L;
    }
    x
}

/// Runs a pass over every target pixel and hands each target's result to
/// `sink` (tile by tile, in a fixed order), reporting progress in `[0, 1]`
/// after every wave of tiles.
pub(super) fn run_pass<K: RowKernel>(
    pass: &Pass,
    targets: &[bool],
    kernel: &K,
    progress: &mut dyn FnMut(f32) -> Result<(), NodeError>,
    mut sink: impl FnMut(usize, Finish),
) -> Result<(), NodeError> {
    let (w, h) = (pass.w, pass.h);
    if w == 0 || h == 0 {
        return Ok(());
    }
    // Tiles of BAND_ROWS x TILE_COLS holding a target: the scattered holes
    // of an inpainting pass cost only the tiles around them, and a tile
    // whose targets cover less than a quarter of it is cut into tiles of
    // SPARSE_ROWS x SPARSE_COLS (a thin hole strip then costs the small
    // tiles along it, not the rectangle around it). A pixel's sums do not
    // depend on its tile (its patch distances are box sums of its own
    // patch, each summed directly), so neither do the results.
    let count = |(y0, y1): (usize, usize), (x0, x1): (usize, usize)| -> usize {
        (y0..y1)
            .map(|y| {
                targets[y * w + x0..y * w + x1]
                    .iter()
                    .filter(|t| **t)
                    .count()
            })
            .sum()
    };
    let mut tiles: Vec<((usize, usize), (usize, usize))> = Vec::new();
    for y0 in (0..h).step_by(BAND_ROWS) {
        let rows = (y0, (y0 + BAND_ROWS).min(h));
        for x0 in (0..w).step_by(TILE_COLS) {
            let cols = (x0, (x0 + TILE_COLS).min(w));
            let n = count(rows, cols);
            if n == 0 {
                continue;
            }
            if 4 * n >= (rows.1 - rows.0) * (cols.1 - cols.0) {
                tiles.push((rows, cols));
                continue;
            }
            for sy in (rows.0..rows.1).step_by(SPARSE_ROWS) {
                let sub_rows = (sy, (sy + SPARSE_ROWS).min(rows.1));
                for sx in (cols.0..cols.1).step_by(SPARSE_COLS) {
                    let sub_cols = (sx, (sx + SPARSE_COLS).min(cols.1));
                    if count(sub_rows, sub_cols) > 0 {
                        tiles.push((sub_rows, sub_cols));
                    }
                }
            }
        }
    }
    let waves = tiles.len().div_ceil(WAVE_TILES).max(1);
    for (k, wave) in tiles.chunks(WAVE_TILES).enumerate() {
        let outs: Vec<BandOut<K::Sums>> = wave
            .par_iter()
            .map(|&(rows, cols)| band(pass, targets, kernel, rows, cols))
            .collect();
        for out in &outs {
            let Some(sums) = &out.sums else { continue };
            for t in 0..out.bh {
                for c in 0..out.bw {
                    let i = (out.y0 + t) * w + out.xa + c;
                    if targets[i] {
                        sink(i, kernel.finish(sums, t * out.bw + c));
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
