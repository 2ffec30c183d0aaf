//! The depth kernel (eq. 1-3, 5) a whole band row at a time: the sums of
//! [`Acc`] as planes, one exponential per candidate, loops without a
//! branch so the compiler vectorises them.
//!
//! **Why a fixed reference works.** [`Acc`] keeps its sums relative to the
//! largest exponent seen so far so that weights never all underflow. Here
//! every sum is relative to exponent 0 instead:
//! - the similarity sums `sum_j s(i, j)` always hold the target itself
//!   (search offset 0: patch distance exactly 0, discontinuity term 0),
//!   whose exponent 0 is the largest, so they equal [`Acc`]'s;
//! - the weights `Z_i` of eq. 1 hold the target's own term (its confidence
//!   times its prior, 1 in clean data) wherever the target is a source
//!   itself (denoising). Elsewhere (a hole being inpainted, a target of
//!   tiny confidence) all of them may be tiny: when `Z_i` is below
//!   [`Weight::exact_below`], far above the subnormal range, the target is
//!   handed back ([`Finish::Exact`]) and run again: after the f32 rows in
//!   the f64 rows, after those with [`Acc`]'s running maximum.
//!
//! **Two precisions.** [`DepthRows`] runs in f32 or f64 (`E`): the patch
//! distances of the band (its `Real`), the discontinuity term, the
//! exponential and the priors; the weight sums of eq. 1 (`Z_i` and
//! `sum w v`) are f64 in both, the similarity sums (the confidence) in
//! `E`. The CPU runner takes f32 (eight lanes where f64 has four) for
//! patches up to [`F32_MAX_PATCH`]; when every target is a source itself
//! (denoising) its own term weighs its confidence, so the weights that
//! count never underflow; a hole being inpainted may have every candidate
//! more than 117 units of exponent away, where f32 has nothing left even
//! at the rows' shift ([`Weight::SHIFT`]), and is handed back (1.3k
//! hole fills of 77k holes on a Kinect frame, all iterations together).
//!
//! - f64: the exponential is [`exp_neg`] (relative error < 1e-12); the
//!   results equal [`Acc`]'s to about 1e-12 of the window's depth range.
//! - f32 (only for patch radius `r <= F32_MAX_PATCH = 2`, the default;
//!   wider patches run in f64), against the f64 pass ([`PerPair`] with [`Acc`], the reference
//!   the GPU is checked against too), with `u = 2^-24`: a patch distance
//!   is a sum of at most `(2r+1)^2` non-negative per-pixel terms (each
//!   within `5u`), weighted by the box coefficients, so its relative error
//!   is below `((2r+1)^2 + 8) u`, `33u = 2e-6` at the default `r = 2`; the
//!   exponent `x` of a weight is off by at most that times `|x|`, and only
//!   weights with `|x| <= 117` are not 0 in f32 (the rows weigh a
//!   candidate `exp(x + 30)`, [`Weight::SHIFT`], and `exp(-87)` is f32's
//!   last normal value). With [`exp_f32`]'s `5e-7` a weight's relative
//!   error is `δ <= 33u * 117 + 5e-7 = 2.35e-4` (the background factor,
//!   when on, adds `3 β u`: `9e-6` at the default `β = 50`); in clean data
//!   the weights that count have `|x|` of a few units and `δ` is near
//!   `1e-5`. The weights below `exp(-117)`, 0 in f32, weigh less than
//!   `1e-6` of any sum kept ([`Weight::exact_below`]; smaller sums run
//!   again in f64). Weights off by `δ` move the estimate by at most `δ / (1 - δ)`
//!   of the range of the averaged depths `hi - lo`, and the f64 sums add
//!   nothing of note: **`|Δz| <= 2.5e-4 (hi - lo)`** plus the final rounding to
//!   f32, and the confidence (a ratio of f32 sums of at most `(2R+1)^2`
//!   terms) within `2.5e-4 + 2 (2R+1)^2 u`. Tested against the f64 pass
//!   below, and in `NLMeansDepth`'s results at 640x480 (the depth bench).

use std::marker::PhantomData;

use crate::kit::fast_exp::{exp_f32, exp_neg, exp_neg_f32};

use super::pass::*;

/// The float type of a [`DepthRows`] pass: its patch distances, weights
/// and similarity sums (the weight sums of eq. 1 are f64 in both).
pub(super) trait Weight: Real {
    /// Weight sums below this, for a search window of `candidates` pixels,
    /// are recomputed (in f64 rows, then with the running maximum).
    fn exact_below(candidates: usize) -> f64;
    /// `exp(x)` for `x <= 0`, branch-free.
    fn exp_neg(self) -> Self;
    /// The shift `S` of the rows' reference exponent: a candidate of
    /// exponent `x <= 0` weighs `exp(x + S)` ([`Weight::exp_shifted`]).
    /// Every sum takes the same factor `exp(S)` and only their ratios are
    /// read (eq. 1 and the confidence), so the estimates do not change;
    /// what changes is how far below the best possible candidate (the
    /// target itself, exponent 0) a weight may lie before it underflows.
    const SHIFT: f64;
    /// `exp(x)` for `x <= SHIFT`, branch-free.
    fn exp_shifted(self) -> Self;
}

/// f32's smallest weight: `exp(-87)`, its last normal value; every weight
/// below it is 0 in f32.
const F32_SMALLEST_WEIGHT: f64 = 1.65e-38;

/// The largest share of a weight sum kept from the f32 rows that the
/// weights lost below [`F32_SMALLEST_WEIGHT`] may make up.
const F32_LOST_SHARE: f64 = 1e-6;

impl Weight for f32 {
    /// At most `candidates` weights are lost, each below
    /// [`F32_SMALLEST_WEIGHT`], so a sum kept loses less than
    /// [`F32_LOST_SHARE`] of itself: `candidates * 1.65e-38 / 1e-6`
    /// (`2.0e-30` at the 11x11 window of NLMeansInpaint's default,
    /// `6.1e-29` at the largest, 61x61). (This was a fixed `1e-26`,
    /// which handed back sums the f32 rows held well.)
    fn exact_below(candidates: usize) -> f64 {
        candidates.max(1) as f64 * F32_SMALLEST_WEIGHT / F32_LOST_SHARE
    }
    #[inline(always)]
    fn exp_neg(self) -> f32 {
        exp_neg_f32(self)
    }
    /// 30: a weight underflows at exponent `-117` instead of `-87` (f32
    /// holds `exp(30)` to `exp(-87)`), and the target's own term,
    /// `exp(30) = 1.1e13`, summed over at most 3721 candidates stays far
    /// below f32's largest value. On a Kinect frame (TUM, 77k holes) the
    /// holes handed back over all iterations went from 9.5k to 1.3k (40:
    /// 1.0k, but the bound below would grow past `2.5e-4`).
    const SHIFT: f64 = 30.0;
    #[inline(always)]
    fn exp_shifted(self) -> f32 {
        exp_f32(self)
    }
}

impl Weight for f64 {
    /// `1e-280`: the sum's largest term is then above
    /// `1e-280 / (2R+1)^2`, still far from the subnormal range, so every
    /// sum kept has full f64 precision.
    fn exact_below(_candidates: usize) -> f64 {
        1e-280
    }
    #[inline(always)]
    fn exp_neg(self) -> f64 {
        exp_neg(self)
    }
    /// 0: f64 reaches `exp(-708)`.
    const SHIFT: f64 = 0.0;
    #[inline(always)]
    fn exp_shifted(self) -> f64 {
        exp_neg(self)
    }
}

/// The widest patch radius the f32 rows are used for (module docs: the
/// patch distance's relative error grows as `(2r+1)^2`, and the stated
/// bound is derived at `r = 2`).
pub(super) const F32_MAX_PATCH: usize = 2;

/// The depth kernel's vectorised rows in `E` (f32 or f64; module docs).
pub(super) struct DepthRows<'k, 'a, E> {
    pub(super) kernel: &'k DepthKernel<'a>,
    /// [`Weight::exact_below`] of the pass's search window.
    exact_below: f64,
    _weight: PhantomData<E>,
}

impl<'k, 'a, E: Weight> DepthRows<'k, 'a, E> {
    /// The rows of `kernel` for a pass whose search radius is `search`.
    pub(super) fn new(kernel: &'k DepthKernel<'a>, search: usize) -> Self {
        let side = 2 * search + 1;
        Self {
            kernel,
            exact_below: E::exact_below(side * side),
            _weight: PhantomData,
        }
    }
}

/// [`Acc`]'s sums for a band, plane by plane, relative to exponent 0.
pub(super) struct DepthSums<E> {
    sim: Vec<E>,
    sim_conf: Vec<E>,
    w: Vec<f64>,
    wv: Vec<f64>,
    /// The range of the averaged depths.
    lo: Vec<f32>,
    hi: Vec<f32>,
    /// One row's weights, between the loop in `E` and the f64 sums.
    wgt: Vec<E>,
}

/// The slices of one row of [`DepthSums`].
struct RowSums<'a, E> {
    sim: &'a mut [E],
    sim_conf: &'a mut [E],
    w: &'a mut [f64],
    wv: &'a mut [f64],
    lo: &'a mut [f32],
    hi: &'a mut [f32],
    wgt: &'a mut [E],
}

/// One row's inputs, all aligned with its targets.
struct RowIn<'a, E> {
    dist: &'a [E],
    zi: &'a [f32],
    ci: &'a [f32],
    zj: &'a [f32],
    cj: &'a [f32],
    /// The largest source depth of each target's window (background side).
    z_max: &'a [f32],
}

impl<E: Weight> RowKernel for DepthRows<'_, '_, E> {
    type Real = E;
    type Sums = DepthSums<E>;

    fn sums(&self, len: usize) -> DepthSums<E> {
        DepthSums {
            sim: vec![E::ZERO; len],
            sim_conf: vec![E::ZERO; len],
            w: vec![0.0; len],
            wv: vec![0.0; len],
            lo: vec![f32::INFINITY; len],
            hi: vec![f32::NEG_INFINITY; len],
            wgt: vec![E::ZERO; len],
        }
    }

    #[inline(always)]
    fn add_row(&self, w: usize, row: &RowCands<E>, s: &mut DepthSums<E>) {
        // The whole row: the band hands over its targets' span (`band_body`),
        // whose other pixels get sums nobody reads.
        self.run(w, row, 0..row.dist.len(), s);
    }

    fn finish(&self, s: &DepthSums<E>, k: usize) -> Finish {
        // a NaN sum is handed back too
        if s.w[k].is_nan() || s.w[k] < self.exact_below {
            return Finish::Exact;
        }
        let acc = Acc {
            ms: 0.0,
            sim: s.sim[k].to_f64(),
            sim_conf: s.sim_conf[k].to_f64(),
            mw: 0.0,
            w: s.w[k],
            wv: s.wv[k],
            lo: s.lo[k],
            hi: s.hi[k],
        };
        Finish::Done(acc.finish())
    }
}

impl<E: Weight> DepthRows<'_, '_, E> {
    /// [`RowKernel::add_row`] for the targets `run` of the row.
    #[inline(always)]
    fn run(&self, w: usize, row: &RowCands<E>, run: std::ops::Range<usize>, s: &mut DepthSums<E>) {
        let k = self.kernel;
        let n = run.len();
        let i0 = row.y * w + row.x0 + run.start;
        let j0 = ((row.yj * w + row.x0 + run.start) as isize + row.dx) as usize;
        let at = row.at + run.start..row.at + run.end;
        let rin = RowIn {
            dist: &row.dist[run],
            zi: &k.z[i0..i0 + n],
            ci: &k.c[i0..i0 + n],
            zj: &k.z[j0..j0 + n],
            cj: &k.c[j0..j0 + n],
            z_max: match k.background {
                Some((_, _, m)) => &m[i0..i0 + n],
                None => &[],
            },
        };
        let out = RowSums {
            sim: &mut s.sim[at.clone()],
            sim_conf: &mut s.sim_conf[at.clone()],
            w: &mut s.w[at.clone()],
            wv: &mut s.wv[at.clone()],
            lo: &mut s.lo[at.clone()],
            hi: &mut s.hi[at],
            wgt: &mut s.wgt[..n],
        };
        match (k.far.is_some(), k.background.is_some()) {
            (false, false) => self.row::<false, false>(&rin, out),
            (true, false) => self.row::<true, false>(&rin, out),
            (false, true) => self.row::<false, true>(&rin, out),
            (true, true) => self.row::<true, true>(&rin, out),
        }
    }

    /// [`DepthKernel::add`] for every target of a row, relative to exponent 0.
    #[inline(always)]
    fn row<const FAR: bool, const BG: bool>(&self, r: &RowIn<E>, s: RowSums<E>) {
        let k = self.kernel;
        let (beta, tau) = k.background.map_or((0.0, 0.0), |(b, t, _)| (b, t));
        let n = r.dist.len();
        let z_max = if BG { &r.z_max[..n] } else { &[][..] };
        row_sums::<E, FAR, BG>(
            RowConsts {
                inv_hd2: E::of_f64(k.inv_hd2),
                inv_ref: E::of_f64(k.far.unwrap_or(0.0)),
                beta: E::of_f64(beta),
                tau: E::of_f64(tau),
            },
            RowIn {
                dist: &r.dist[..n],
                zi: &r.zi[..n],
                ci: &r.ci[..n],
                zj: &r.zj[..n],
                cj: &r.cj[..n],
                z_max,
            },
            s,
        );
    }
}

/// The constants of [`row_sums`].
#[derive(Clone, Copy)]
struct RowConsts<E> {
    inv_hd2: E,
    /// `1 / z_ref` of the far-depth prior.
    inv_ref: E,
    /// The background side's `β` and `τ`.
    beta: E,
    tau: E,
}

/// The row loops of [`DepthRows::row`]. Every slice is reborrowed at one
/// length (so the compiler drops the bounds checks), and the bodies have
/// no branch: the loops vectorise (inlined into the pass's band, with the
/// instructions it was compiled for). The first loop runs in `E` only (in
/// f32: eight lanes), the second adds the weights to the f64 sums.
#[inline(always)]
fn row_sums<E: Weight, const FAR: bool, const BG: bool>(
    k: RowConsts<E>,
    r: RowIn<E>,
    s: RowSums<E>,
) {
    let n = r.dist.len();
    let (dist, zi, ci, zj, cjs) = (&r.dist[..n], &r.zi[..n], &r.ci[..n], &r.zj[..n], &r.cj[..n]);
    let z_max = if BG { &r.z_max[..n] } else { &[][..] };
    let (sim, sim_conf, sw, swv) = (
        &mut s.sim[..n],
        &mut s.sim_conf[..n],
        &mut s.w[..n],
        &mut s.wv[..n],
    );
    let (lo, hi, wbuf) = (&mut s.lo[..n], &mut s.hi[..n], &mut s.wgt[..n]);
    let (zero, one) = (E::ZERO, E::of_f32(1.0));
    let shift = E::of_f64(E::SHIFT);
    for i in 0..n {
        let cj = E::of_f32(cjs[i]);
        let zjv = E::of_f32(zj[i]);
        // Discontinuity factor xi_ij (eq. 3) of a source where the centre
        // has depth (a select, not a product: 0 * inf would be NaN).
        let dz = E::of_f32(zi[i]) - zjv;
        let xi = if (cjs[i] > 0.0) & (ci[i] > 0.0) {
            dz * dz * k.inv_hd2
        } else {
            zero
        };
        let e = (shift - (dist[i] + xi)).exp_shifted();
        sim[i] += e;
        // a hole (confidence 0) counts in the similarity only
        let sc = e * cj;
        sim_conf[i] += sc;
        let mut wgt = sc;
        if FAR {
            let q = zjv * k.inv_ref;
            wgt = wgt * q * q;
        }
        if BG {
            let zm = E::of_f32(z_max[i]);
            // guard: z_max > 0 (selected after the division; 0 = no
            // source in the window, factor 1)
            let step = (zm - zjv) / zm;
            let f = (zero - k.beta * (step - k.tau).max(zero)).exp_neg();
            wgt = wgt * if z_max[i] > 0.0 { f } else { one };
        }
        wbuf[i] = wgt;
        let pos = wgt > zero;
        lo[i] = lo[i].min(if pos { zj[i] } else { f32::INFINITY });
        hi[i] = hi[i].max(if pos { zj[i] } else { f32::NEG_INFINITY });
    }
    // The weight sums of eq. 1 in f64.
    for i in 0..n {
        let wd = wbuf[i].to_f64();
        sw[i] += wd;
        swv[i] += wd * zj[i] as f64;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::depth::nlmeans::inpaint::window_max;
    use crate::depth::nlmeans::params::Core;
    use crate::kit::rng::SplitMix64;

    /// The stated bound of the f32 rows against the f64 pass (module docs):
    /// the estimate within this fraction of the averaged depths' range.
    const F32_BOUND: f64 = 2.5e-4;

    /// Results per pixel: estimate and confidence, `None` without a source.
    type Results = Vec<Option<(f32, f32)>>;

    /// A test pass: its scene, kernel settings and targets.
    struct Case {
        w: usize,
        h: usize,
        h_color: f64,
        hole_rate: f64,
        far: bool,
        background: bool,
        seed: u64,
        /// Targets: every pixel with depth and every third row's holes
        /// (false: only the pixels with depth, as in denoising).
        holes: bool,
    }

    /// The rows in `E` (with the exact fallback for what they hand back)
    /// and the per-pair pass with the running maximum, per pixel, plus the
    /// targets handed back and each pixel's window depth range.
    fn both<E: Weight>(k: &Case) -> (Results, Results, Vec<bool>, Vec<f32>) {
        let (w, h) = (k.w, k.h);
        let (guide, z, c) = scene(w, h, k.hole_rate, k.seed);
        let core = Core::new(4, 2, k.h_color, 0.05).unwrap();
        let pass = Pass::new((w, h), &guide, Some((&z, &c)), core);
        let lm = window_max(&z, &c, w, h, core.search);
        let kernel = DepthKernel {
            z: &z,
            c: &c,
            inv_hd2: core.inv_hd2,
            far: k.far.then_some(1.0 / 3.1),
            background: k.background.then_some((50.0, 0.05, lm.as_slice())),
        };
        let targets: Vec<bool> = (0..w * h)
            .map(|i| c[i] > 0.0 || (k.holes && (i / w) % 3 != 1))
            .collect();
        let (mut fast, exact) =
            collect(&pass, &targets, &DepthRows::<E>::new(&kernel, core.search));
        let mut redo = vec![false; w * h];
        for i in &exact {
            redo[*i] = true;
        }
        let (slow_exact, _) = collect(&pass, &redo, &PerPair(&kernel));
        for i in exact {
            fast[i] = slow_exact[i];
        }
        let (slow, _) = collect(&pass, &targets, &PerPair(&kernel));
        let range = window_range(&z, &c, w, h, core.search);
        (fast, slow, redo, range)
    }

    /// The depth range (max - min) of the sources in each pixel's window:
    /// at least the range `hi - lo` of the values a pass averages there.
    fn window_range(z: &[f32], c: &[f32], w: usize, h: usize, r: usize) -> Vec<f32> {
        (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                let (mut lo, mut hi) = (f32::INFINITY, 0.0f32);
                for yy in y.saturating_sub(r)..(y + r + 1).min(h) {
                    for xx in x.saturating_sub(r)..(x + r + 1).min(w) {
                        let j = yy * w + xx;
                        if c[j] > 0.0 {
                            lo = lo.min(z[j]);
                            hi = hi.max(z[j]);
                        }
                    }
                }
                if hi >= lo { hi - lo } else { 0.0 }
            })
            .collect()
    }

    /// A random guide over two noisy surfaces (1 m and 3 m) with holes at
    /// `hole_rate`: guide, depth, confidence.
    fn scene(w: usize, h: usize, hole_rate: f64, seed: u64) -> (Vec<[f32; 3]>, Vec<f32>, Vec<f32>) {
        let mut rng = SplitMix64(seed);
        let guide: Vec<[f32; 3]> = (0..w * h)
            .map(|_| [0, 1, 2].map(|_| rng.uniform() as f32 * 0.9))
            .collect();
        let mut z = vec![0.0f32; w * h];
        let mut c = vec![0.0f32; w * h];
        for i in 0..w * h {
            if rng.uniform() >= hole_rate {
                let base = if (i % w) < w / 2 { 1.0 } else { 3.0 };
                z[i] = (base + 0.02 * rng.gaussian()) as f32;
                c[i] = (0.2 + 0.8 * rng.uniform()) as f32;
            }
        }
        (guide, z, c)
    }

    /// A pass's results per pixel and the targets it handed back.
    fn collect<K: RowKernel>(pass: &Pass, targets: &[bool], kernel: &K) -> (Results, Vec<usize>) {
        let mut out = vec![None; pass.w * pass.h];
        let mut exact = Vec::new();
        run_pass(pass, targets, kernel, &mut |_| Ok(()), |i, r| match r {
            Finish::Done(v) => out[i] = v,
            Finish::Exact => exact.push(i),
        })
        .unwrap();
        (out, exact)
    }

    /// Worst relative differences (depth, confidence); infinite when one
    /// side has an estimate and the other not.
    fn worst(fast: &[Option<(f32, f32)>], slow: &[Option<(f32, f32)>]) -> (f32, f32) {
        let (mut dz, mut dc) = (0.0f32, 0.0f32);
        for (a, b) in fast.iter().zip(slow) {
            match (a, b) {
                (Some((za, ca)), Some((zb, cb))) => {
                    dz = dz.max((za - zb).abs() / zb);
                    dc = dc.max((ca - cb).abs());
                }
                (None, None) => {}
                _ => return (f32::INFINITY, f32::INFINITY),
            }
        }
        (dz, dc)
    }

    /// The f32 rows' differences over their stated bounds (module docs),
    /// worst over the pixels: depth `F32_BOUND (window range)` plus two
    /// f32 ulps, confidence `F32_BOUND + 2 (2R+1)^2 u`. At most 1 within
    /// the bounds; infinite when one side has an estimate and the other not.
    fn over_f32_bound(
        fast: &[Option<(f32, f32)>],
        slow: &[Option<(f32, f32)>],
        range: &[f32],
    ) -> f64 {
        let conf_bound = F32_BOUND + 2.0 * 81.0 * f32::EPSILON as f64 / 2.0;
        let mut worst = 0.0f64;
        for ((a, b), r) in fast.iter().zip(slow).zip(range) {
            match (a, b) {
                (Some((za, ca)), Some((zb, cb))) => {
                    let allowed = F32_BOUND * *r as f64 + 2.0 * (*zb as f64) * f32::EPSILON as f64;
                    worst = worst.max((za - zb).abs() as f64 / allowed);
                    worst = worst.max((ca - cb).abs() as f64 / conf_bound);
                }
                (None, None) => {}
                _ => return f64::INFINITY,
            }
        }
        worst
    }

    fn case(far: bool, background: bool, holes: bool) -> Case {
        Case {
            w: 37,
            h: 29,
            h_color: 0.1,
            hole_rate: 0.3,
            far,
            background,
            seed: 5,
            holes,
        }
    }

    const SETTINGS: [(bool, bool); 4] =
        [(false, false), (true, false), (false, true), (true, true)];

    #[test]
    fn f64_rows_agree_with_the_running_maximum() {
        for (far, background) in SETTINGS {
            let (fast, slow, _, _) = both::<f64>(&case(far, background, true));
            let (dz, dc) = worst(&fast, &slow);
            // f32 results: a last-place difference at most
            assert!(
                dz <= 2.0 * f32::EPSILON,
                "far {far} bg {background}: {dz:e}"
            );
            assert!(
                dc <= 2.0 * f32::EPSILON,
                "far {far} bg {background}: {dc:e}"
            );
            assert!(fast.iter().filter(|v| v.is_some()).count() > 500);
        }
    }

    #[test]
    fn f32_rows_stay_within_their_stated_bound() {
        for holes in [false, true] {
            for (far, background) in SETTINGS {
                let (fast, slow, _, range) = both::<f32>(&case(far, background, holes));
                let over = over_f32_bound(&fast, &slow, &range);
                assert!(
                    over <= 1.0,
                    "holes {holes} far {far} bg {background}: {over}"
                );
                assert!(fast.iter().filter(|v| v.is_some()).count() > 500);
            }
        }
    }

    /// Half of the pixels holes, in a random guide: at small `h_color`
    /// every source of some holes lies far below exponent 0.
    fn deep_case(h_color: f64) -> Case {
        Case {
            w: 23,
            h: 17,
            h_color,
            hole_rate: 0.5,
            far: false,
            background: true,
            seed: 9,
            holes: true,
        }
    }

    #[test]
    fn underflowing_weights_are_run_again_exactly() {
        // f64 rows: h_color 1e-3 gives colour differences of ~0.3
        // exponents near -1e5, so a hole's sources all underflow relative
        // to exponent 0; f32 rows underflow below -117 (-87 and their
        // shift of 30), at h_color 0.02.
        for (h_color, f32_rows) in [(1e-3, false), (0.02, true)] {
            let k = deep_case(h_color);
            let (fast, slow, redo, range) = if f32_rows {
                both::<f32>(&k)
            } else {
                both::<f64>(&k)
            };
            assert!(redo.iter().any(|r| *r), "no target needed the exact path");
            if f32_rows {
                assert!(over_f32_bound(&fast, &slow, &range) <= 1.0);
            } else {
                let (dz, dc) = worst(&fast, &slow);
                assert!(
                    dz <= 2.0 * f32::EPSILON && dc <= 2.0 * f32::EPSILON,
                    "{dz:e} {dc:e}"
                );
            }
            // every hole with a source in its window got an estimate
            let filled = redo.iter().zip(&fast).filter(|(r, v)| **r && v.is_some());
            assert!(filled.count() > 0);
        }
    }

    /// Every version of the band the CPU runs (the dispatched one, AVX2
    /// and AVX-512 F where present) against the plain one over the same
    /// pass, in `E`: the number of pixels whose results differ in any bit,
    /// summed over the versions.
    fn vector_differences<E: Weight>() -> usize {
        let (w, h) = (45, 21);
        let (guide, z, c) = scene(w, h, 0.15, 21);
        let core = Core::new(4, 2, 0.1, 0.05).unwrap();
        let pass = Pass::new((w, h), &guide, Some((&z, &c)), core);
        let lm = window_max(&z, &c, w, h, core.search);
        let kernel = DepthKernel {
            z: &z,
            c: &c,
            inv_hd2: core.inv_hd2,
            far: Some(0.5),
            background: Some((50.0, 0.05, lm.as_slice())),
        };
        let rows = DepthRows::<E>::new(&kernel, core.search);
        let targets = vec![true; w * h];
        let whole = ((0, h), (0, w));
        let plain = band_body(&pass, &targets, &rows, whole.0, whole.1);
        let mut versions = vec![band(&pass, &targets, &rows, whole.0, whole.1)];
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx2") {
                // SAFETY: the CPU has AVX2.
                versions.push(unsafe { band_avx2(&pass, &targets, &rows, whole.0, whole.1) });
            }
            if crate::kit::cpu::avx512() {
                // SAFETY: the CPU has AVX-512 F (and what it implies).
                versions.push(unsafe { band_avx512(&pass, &targets, &rows, whole.0, whole.1) });
            }
        }
        let sb = plain.sums.unwrap();
        let bits = |f: Finish| match f {
            Finish::Done(Some((v, c))) => (v.to_bits(), c.to_bits()),
            _ => (0, 0),
        };
        versions
            .into_iter()
            .map(|a| {
                let sa = a.sums.unwrap();
                // (holes whose f32 weights all underflow are handed back,
                // alike in every version; the rest is compared bit for bit)
                let done = (0..w * h)
                    .filter(|&k| rows.finish(&sa, k) != Finish::Exact)
                    .count();
                assert!(done * 4 > w * h * 3, "{done} of {}", w * h);
                (0..w * h)
                    .filter(|&k| bits(rows.finish(&sa, k)) != bits(rows.finish(&sb, k)))
                    .count()
            })
            .sum()
    }

    /// A colour parameter at which some holes of [`deep_case`] have no source above exponent -87 but all have
    /// one above -117.
    const HC_DEEP: f64 = 0.08;

    /// [`deep_case`] at colour parameter `h_color`, in the f32 rows: the targets with a
    /// source handed back and the worst difference over the stated bound.
    fn f32_hand_backs(h_color: f64) -> (usize, f64) {
        let (fast, slow, redo, range) = both::<f32>(&deep_case(h_color));
        // (a hole without any source in its window is handed back too)
        let with_source = redo.iter().zip(&slow).filter(|(r, v)| **r && v.is_some());
        (with_source.count(), over_f32_bound(&fast, &slow, &range))
    }

    #[test]
    fn the_shift_keeps_weights_between_exp_minus_87_and_minus_117() {
        // At HC_DEEP some holes have no source above exponent -87: rows
        // without the shift (SHIFT = 0) hand back 11 of them (124 and 56
        // at h_color 0.05 and 0.06, against 57 and 13 with it); with the
        // shift every one is estimated in f32, within the stated bound.
        assert_eq!(f32::SHIFT, 30.0);
        let (handed_back, over) = f32_hand_backs(HC_DEEP);
        assert_eq!(handed_back, 0);
        assert!(over <= 1.0, "{over}");
    }

    #[test]
    fn the_vector_band_equals_the_plain_band_bit_for_bit() {
        assert_eq!(vector_differences::<f32>(), 0);
        assert_eq!(vector_differences::<f64>(), 0);
    }

    #[test]
    fn sparse_targets_give_the_results_of_one_whole_tile() {
        // thin vertical strips and a few dots: run_pass cuts its tiles
        // small there; one band over the whole image must give the same bits
        let (w, h) = (150, 40);
        let (guide, z, c) = scene(w, h, 0.2, 33);
        let core = Core::new(4, 2, 0.1, 0.05).unwrap();
        let pass = Pass::new((w, h), &guide, Some((&z, &c)), core);
        let kernel = DepthKernel {
            z: &z,
            c: &c,
            inv_hd2: core.inv_hd2,
            far: None,
            background: None,
        };
        let rows = DepthRows::<f64>::new(&kernel, core.search);
        let targets: Vec<bool> = (0..w * h)
            .map(|i| (i % w) % 37 < 2 || i % 211 == 0)
            .collect();
        let (tiled, exact) = collect(&pass, &targets, &rows);
        assert!(exact.is_empty());
        let whole = band(&pass, &targets, &rows, (0, h), (0, w));
        let sums = whole.sums.unwrap();
        let mut compared = 0;
        for t in 0..whole.bh {
            for k in 0..whole.bw {
                let i = (whole.y0 + t) * w + whole.xa + k;
                if targets[i] {
                    let Finish::Done(v) = rows.finish(&sums, t * whole.bw + k) else {
                        panic!("pixel {i} handed back");
                    };
                    let bits = |r: Option<(f32, f32)>| r.map(|(a, b)| (a.to_bits(), b.to_bits()));
                    assert_eq!(bits(v), bits(tiled[i]), "pixel {i}");
                    compared += 1;
                }
            }
        }
        assert_eq!(compared, targets.iter().filter(|t| **t).count());
    }

    #[test]
    fn a_perturbed_kernel_fails_the_comparisons() {
        let k = Case {
            w: 19,
            h: 13,
            seed: 3,
            ..case(false, false, true)
        };
        let (mut fast, slow, _, _) = both::<f64>(&k);
        assert!(worst(&fast, &slow).0 <= 2.0 * f32::EPSILON);
        let i = fast.iter().position(|v| v.is_some()).unwrap();
        if let Some((z, _)) = fast[i].as_mut() {
            *z *= 1.0 + 4.0 * f32::EPSILON;
        }
        assert!(worst(&fast, &slow).0 > 2.0 * f32::EPSILON);
        // the f32 bound: a pixel moved by twice its allowance fails it
        let (mut fast, slow, _, range) = both::<f32>(&k);
        assert!(over_f32_bound(&fast, &slow, &range) <= 1.0);
        let i = (0..fast.len())
            .find(|i| fast[*i].is_some() && range[*i] > 0.1)
            .unwrap();
        if let Some((z, _)) = fast[i].as_mut() {
            *z += 2.0 * (F32_BOUND * range[i] as f64) as f32 + 4.0 * *z * f32::EPSILON;
        }
        assert!(over_f32_bound(&fast, &slow, &range) > 1.0);
    }
}
