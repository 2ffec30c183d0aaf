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
//!   [`EXACT_BELOW`], far above the subnormal range, the target is handed
//!   back ([`Finish::Exact`]) and run again with [`Acc`]'s running maximum.
//!
//! **Precision.** The exponential is [`exp_neg`] (relative error < 1e-12),
//! the sums are f64 as in [`Acc`]; a weight's relative error `δ` moves the
//! estimate by at most `δ (hi - lo)` (the range of the averaged depths), so
//! the results equal [`Acc`]'s to about 1e-12 of the window's depth range
//! (tested against it).

use crate::kit::fast_exp::exp_neg;

use super::pass::*;

/// Weight sums below this are recomputed with the running maximum: the
/// sum's largest term is then above `EXACT_BELOW / (2R+1)^2`, still far
/// from the subnormal range, so every sum kept has full f64 precision.
pub(super) const EXACT_BELOW: f64 = 1e-280;

/// [`Acc`]'s sums for a band, plane by plane, relative to exponent 0.
pub(super) struct DepthSums {
    sim: Vec<f64>,
    sim_conf: Vec<f64>,
    w: Vec<f64>,
    wv: Vec<f64>,
    /// The range of the averaged depths (f32 values, held as f64).
    lo: Vec<f64>,
    hi: Vec<f64>,
}

/// The slices of one row of [`DepthSums`].
struct RowSums<'a> {
    sim: &'a mut [f64],
    sim_conf: &'a mut [f64],
    w: &'a mut [f64],
    wv: &'a mut [f64],
    lo: &'a mut [f64],
    hi: &'a mut [f64],
}

/// One row's inputs, all aligned with its targets.
struct RowIn<'a> {
    dist: &'a [f64],
    zi: &'a [f32],
    ci: &'a [f32],
    zj: &'a [f32],
    cj: &'a [f32],
    /// The largest source depth of each target's window (background side).
    z_max: &'a [f32],
}

impl RowKernel for DepthKernel<'_> {
    type Sums = DepthSums;

    fn sums(&self, len: usize) -> DepthSums {
        DepthSums {
            sim: vec![0.0; len],
            sim_conf: vec![0.0; len],
            w: vec![0.0; len],
            wv: vec![0.0; len],
            lo: vec![f64::INFINITY; len],
            hi: vec![f64::NEG_INFINITY; len],
        }
    }

    #[inline(always)]
    fn add_row(&self, w: usize, row: &RowCands, s: &mut DepthSums) {
        // Runs of consecutive targets: a dense row is one run, the scattered
        // holes of an inpainting pass cost only their own pixels. Each pixel's
        // arithmetic is the same whatever run it is in.
        let n = row.dist.len();
        let mut a = 0;
        while a < n {
            if !row.targets[a] {
                a += 1;
                continue;
            }
            let b = row.targets[a..]
                .iter()
                .position(|t| !*t)
                .map_or(n, |k| a + k);
            self.run(w, row, a..b, s);
            a = b;
        }
    }

    fn finish(&self, s: &DepthSums, k: usize) -> Finish {
        // a NaN sum is handed back too
        if s.w[k].is_nan() || s.w[k] < EXACT_BELOW {
            return Finish::Exact;
        }
        let acc = Acc {
            ms: 0.0,
            sim: s.sim[k],
            sim_conf: s.sim_conf[k],
            mw: 0.0,
            w: s.w[k],
            wv: s.wv[k],
            // exact: the bounds are f32 depths
            lo: s.lo[k] as f32,
            hi: s.hi[k] as f32,
        };
        Finish::Done(acc.finish())
    }
}

impl DepthKernel<'_> {
    /// [`RowKernel::add_row`] for the targets `run` of the row.
    #[inline(always)]
    fn run(&self, w: usize, row: &RowCands, run: std::ops::Range<usize>, s: &mut DepthSums) {
        let n = run.len();
        let i0 = row.y * w + row.x0 + run.start;
        let j0 = ((row.yj * w + row.x0 + run.start) as isize + row.dx) as usize;
        let at = row.at + run.start..row.at + run.end;
        let rin = RowIn {
            dist: &row.dist[run],
            zi: &self.z[i0..i0 + n],
            ci: &self.c[i0..i0 + n],
            zj: &self.z[j0..j0 + n],
            cj: &self.c[j0..j0 + n],
            z_max: match self.background {
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
        };
        match (self.far.is_some(), self.background.is_some()) {
            (false, false) => self.row::<false, false>(&rin, out),
            (true, false) => self.row::<true, false>(&rin, out),
            (false, true) => self.row::<false, true>(&rin, out),
            (true, true) => self.row::<true, true>(&rin, out),
        }
    }

    /// [`DepthKernel::add`] for every target of a row, relative to exponent 0.
    #[inline(always)]
    fn row<const FAR: bool, const BG: bool>(&self, r: &RowIn, s: RowSums) {
        let (beta, tau) = self.background.map_or((0.0, 0.0), |(b, t, _)| (b, t));
        let n = r.dist.len();
        let z_max = if BG { &r.z_max[..n] } else { &[][..] };
        row_sums::<FAR, BG>(
            RowConsts {
                inv_hd2: self.inv_hd2,
                inv_ref: self.far.unwrap_or(0.0),
                beta,
                tau,
            },
            (&r.dist[..n], &r.zi[..n], &r.ci[..n], &r.zj[..n], &r.cj[..n]),
            z_max,
            (&mut s.sim[..n], &mut s.sim_conf[..n]),
            (&mut s.w[..n], &mut s.wv[..n]),
            (&mut s.lo[..n], &mut s.hi[..n]),
        );
    }
}

/// The constants of [`row_sums`].
#[derive(Clone, Copy)]
struct RowConsts {
    inv_hd2: f64,
    /// `1 / z_ref` of the far-depth prior.
    inv_ref: f64,
    /// The background side's `β` and `τ`.
    beta: f64,
    tau: f64,
}

/// Patch distances, then target depth and confidence, then candidate depth
/// and confidence, of one run of targets.
type RowSlices<'a> = (&'a [f64], &'a [f32], &'a [f32], &'a [f32], &'a [f32]);

/// The row loop of [`DepthKernel::row`]. Every slice is its own argument
/// (so the compiler knows they do not overlap) of one length (so it drops
/// the bounds checks), and the body has no branch: the loop vectorises
/// (inlined into the pass's band, with the instructions it was compiled for).
#[inline(always)]
fn row_sums<const FAR: bool, const BG: bool>(
    k: RowConsts,
    (dist, zi, ci, zj, cjs): RowSlices,
    z_max: &[f32],
    (sim, sim_conf): (&mut [f64], &mut [f64]),
    (sw, swv): (&mut [f64], &mut [f64]),
    (lo, hi): (&mut [f64], &mut [f64]),
) {
    let n = dist.len();
    let (zi, ci, zj, cjs) = (&zi[..n], &ci[..n], &zj[..n], &cjs[..n]);
    let (sim, sim_conf, sw, swv) = (
        &mut sim[..n],
        &mut sim_conf[..n],
        &mut sw[..n],
        &mut swv[..n],
    );
    let (lo, hi) = (&mut lo[..n], &mut hi[..n]);
    for i in 0..n {
        // Confidences are in [0, 1] (sanitised): `positive` is exactly 1 for
        // any c > 0 (even subnormal) and 0 for c = 0, without a select the
        // compiler would have to combine across lanes.
        let positive = |c: f64| (c * 1e300).min(1.0);
        let cj = cjs[i] as f64;
        let zjd = zj[i] as f64;
        // Discontinuity factor xi_ij (eq. 3) of a source where the centre has depth.
        let dz = zi[i] as f64 - zjd;
        let xi = dz * dz * k.inv_hd2 * (positive(cj) * positive(ci[i] as f64));
        let e = exp_neg(-(dist[i] + xi));
        sim[i] += e;
        // a hole (confidence 0) counts in the similarity only
        let sc = e * cj;
        sim_conf[i] += sc;
        let mut wgt = sc;
        if FAR {
            let q = zjd * k.inv_ref;
            wgt *= q * q;
        }
        if BG {
            let zm = z_max[i] as f64;
            // guard: z_max > 0 (selected after the division; 0 = no
            // source in the window, factor 1)
            let step = (zm - zjd) / zm;
            let f = exp_neg(-k.beta * (step - k.tau).max(0.0));
            wgt *= if zm > 0.0 { f } else { 1.0 };
        }
        sw[i] += wgt;
        swv[i] += wgt * zjd;
        let pos = wgt > 0.0;
        lo[i] = lo[i].min(if pos { zjd } else { f64::INFINITY });
        hi[i] = hi[i].max(if pos { zjd } else { f64::NEG_INFINITY });
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::depth::nlmeans::inpaint::window_max;
    use crate::depth::nlmeans::params::Core;
    use crate::kit::rng::SplitMix64;

    /// Both kernels over the same pass: (vectorised rows with the exact
    /// fallback, per pair with the running maximum), per pixel.
    type Both = (Vec<Option<(f32, f32)>>, Vec<Option<(f32, f32)>>);

    fn both(
        w: usize,
        h: usize,
        h_color: f64,
        hole_rate: f64,
        far: bool,
        background: bool,
        seed: u64,
    ) -> (Both, Vec<bool>) {
        let (guide, z, c) = scene(w, h, hole_rate, seed);
        let core = Core::new(4, 2, h_color, 0.05).unwrap();
        let pass = Pass::new((w, h), &guide, Some((&z, &c)), core);
        let lm = window_max(&z, &c, w, h, core.search);
        let kernel = DepthKernel {
            z: &z,
            c: &c,
            inv_hd2: core.inv_hd2,
            far: far.then_some(1.0 / 3.1),
            background: background.then_some((50.0, 0.05, lm.as_slice())),
        };
        // denoising targets where there is depth, inpainting elsewhere
        let targets: Vec<bool> = (0..w * h).map(|i| (i / w) % 3 != 1).collect();
        let (mut fast, exact) = collect(&pass, &targets, &kernel);
        let mut redo = vec![false; w * h];
        for i in &exact {
            redo[*i] = true;
        }
        let (slow_exact, _) = collect(&pass, &redo, &PerPair(&kernel));
        for i in exact {
            fast[i] = slow_exact[i];
        }
        let (slow, _) = collect(&pass, &targets, &PerPair(&kernel));
        ((fast, slow), redo)
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
    fn collect<K: RowKernel>(
        pass: &Pass,
        targets: &[bool],
        kernel: &K,
    ) -> (Vec<Option<(f32, f32)>>, Vec<usize>) {
        let mut out = vec![None; pass.w * pass.h];
        let mut exact = Vec::new();
        run_pass(pass, targets, kernel, &mut |_| Ok(()), |i, r| match r {
            Finish::Done(v) => out[i] = v,
            Finish::Exact => exact.push(i),
        })
        .unwrap();
        (out, exact)
    }

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

    #[test]
    fn rows_agree_with_the_running_maximum() {
        for (far, background) in [(false, false), (true, false), (false, true), (true, true)] {
            let ((fast, slow), _) = both(37, 29, 0.1, 0.3, far, background, 5);
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
    fn underflowing_weights_are_run_again_exactly() {
        // h_color 1e-3: colour differences of ~0.3 give exponents near -1e5,
        // so a hole's sources all underflow relative to exponent 0.
        let ((fast, slow), redo) = both(23, 17, 1e-3, 0.5, false, true, 9);
        assert!(redo.iter().any(|r| *r), "no target needed the exact path");
        let (dz, dc) = worst(&fast, &slow);
        assert!(
            dz <= 2.0 * f32::EPSILON && dc <= 2.0 * f32::EPSILON,
            "{dz:e} {dc:e}"
        );
        // every hole with a source in its window got an estimate
        let filled = redo.iter().zip(&fast).filter(|(r, v)| **r && v.is_some());
        assert!(filled.count() > 0);
    }

    #[test]
    fn the_avx2_band_equals_the_plain_band_bit_for_bit() {
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
        let targets = vec![true; w * h];
        let (a, b) = (
            band(&pass, &targets, &kernel, (0, h), (0, w)),
            band_body(&pass, &targets, &kernel, (0, h), (0, w)),
        );
        let (sa, sb) = (a.sums.unwrap(), b.sums.unwrap());
        let bits = |f: Finish| match f {
            Finish::Done(Some((v, c))) => (v.to_bits(), c.to_bits()),
            _ => (0, 0),
        };
        let differ = (0..w * h)
            .filter(|&k| bits(kernel.finish(&sa, k)) != bits(kernel.finish(&sb, k)))
            .count();
        assert_eq!(differ, 0);
        assert!((0..w * h).all(|k| kernel.finish(&sa, k) != Finish::Exact));
    }

    #[test]
    fn a_perturbed_kernel_fails_the_comparison() {
        let ((mut fast, slow), _) = both(19, 13, 0.1, 0.3, false, false, 3);
        let (dz, _) = worst(&fast, &slow);
        assert!(dz <= 2.0 * f32::EPSILON);
        let k = fast.iter().position(|v| v.is_some()).unwrap();
        if let Some((z, _)) = fast[k].as_mut() {
            *z *= 1.0 + 4.0 * f32::EPSILON;
        }
        assert!(worst(&fast, &slow).0 > 2.0 * f32::EPSILON);
    }
}
