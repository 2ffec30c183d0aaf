//! The first pass of the joint upsampling (eq. 4) as a job a backend runs:
//! its kernel, its flat-buffer description and the CPU's runner.

use depthgraph_graph::prelude::*;

use super::common::*;
use super::job::PassJob;
use super::params::*;
use super::pass::*;

/// Kernel of eq. 4: candidates are the high-resolution pixels holding a
/// low-resolution sample.
pub(super) struct UpsampleKernel<'a> {
    pub(super) w: usize,
    /// Low-resolution sample at each high-resolution pixel, or `NO_SAMPLE`.
    pub(super) sample_at: &'a [usize],
    /// Low-resolution column / row of each high-resolution column / row.
    pub(super) lo_col: &'a [usize],
    pub(super) lo_row: &'a [usize],
    pub(super) z: &'a [f32],
    pub(super) c: &'a [f32],
    pub(super) lw: usize,
    pub(super) lh: usize,
    pub(super) low_patch: isize,
    pub(super) inv_low_area: f64,
    pub(super) inv_hd2: f64,
    /// `ln(alpha)` and `ln(1 - alpha)` of the blend (`-inf` for 0).
    pub(super) ln_alpha: f64,
    pub(super) ln_one_minus_alpha: f64,
    /// The spatial falloff `1 / (2 sigma^2)`, high-resolution pixels^-2
    /// (0: none).
    pub(super) spatial: f64,
    /// Per high-resolution row, the low-resolution row of the samples
    /// placed on it, or `NO_SAMPLE` (the pass skips candidates on such
    /// rows: at a factor f, f - 1 rows in f).
    pub(super) sample_row: Vec<usize>,
    /// [`Self::low_distance`] of each low-resolution pixel to its
    /// neighbours, computed once (every high-resolution pixel of a
    /// low-resolution one asks for the same pairs: f^2 times each).
    pub(super) table: Option<LowTable>,
}

/// Largest [`LowTable`], entries (96 MiB): beyond it the distances are
/// computed per pair.
const LOW_TABLE_MAX: usize = 12 << 20;

/// The low-resolution distances of every pixel `a` to the pixels `b`
/// within `rx` columns and `ry` rows of it (`NaN` beyond the grid).
pub(super) struct LowTable {
    rx: usize,
    ry: usize,
    /// `2 rx + 1`, and the entries per pixel `(2 rx + 1) (2 ry + 1)`.
    cols: usize,
    side: usize,
    vals: Vec<f64>,
}

impl UpsampleKernel<'_> {
    /// `-ln w(i_low, j_low)`: eq. 2/5 on low-resolution depth patches, with
    /// the discontinuity factor at the centres.
    pub(super) fn low_distance(&self, a: usize, b: usize) -> f64 {
        // Guard: lw > 0 (the upsampling returns before any pass on an
        // empty grid).
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

impl UpsampleKernel<'_> {
    /// The table of [`Self::low_distance`] for the pairs a search window of
    /// `search` high-resolution pixels reaches on the grid (its reach per
    /// axis from the placement itself: the largest distance, in
    /// low-resolution pixels, between a pixel's own low-resolution column
    /// and that of a sample within `search` columns; pairs beyond it, none
    /// with these maps, are computed when asked), `None` when it would
    /// exceed [`LOW_TABLE_MAX`] entries or the depth term is absent.
    fn with_table(mut self, search: usize, h: usize) -> Self {
        use rayon::prelude::*;
        let w = self.w;
        if self.ln_one_minus_alpha == f64::NEG_INFINITY || w == 0 || h == 0 || self.lw == 0 {
            return self;
        }
        // The low-resolution column of the sample on each column (samples
        // sit on a grid: the first row holding one has them all), and row.
        let Some(first) = self
            .sample_at
            .chunks(w)
            .find(|r| r.iter().any(|s| *s != NO_SAMPLE))
        else {
            return self;
        };
        // Guard: lw > 0 (above).
        let col_of: Vec<usize> = first
            .iter()
            .map(|s| {
                if *s == NO_SAMPLE {
                    NO_SAMPLE
                } else {
                    s % self.lw
                }
            })
            .collect();
        let reach = |own: &[usize], of: &[usize]| -> usize {
            let n = own.len();
            (0..n)
                .filter(|&x| own[x] != NO_SAMPLE)
                .flat_map(|x| {
                    let (a, b) = (x.saturating_sub(search), (x + search + 1).min(n));
                    of[a..b]
                        .iter()
                        .filter(|l| **l != NO_SAMPLE)
                        .map(move |l| l.abs_diff(own[x]))
                })
                .max()
                .unwrap_or(0)
        };
        let (rx, ry) = (
            reach(self.lo_col, &col_of),
            reach(self.lo_row, &self.sample_row),
        );
        let cols = 2 * rx + 1;
        let side = cols * (2 * ry + 1);
        let n = self.lw * self.lh;
        if n.saturating_mul(side) > LOW_TABLE_MAX {
            return self;
        }
        let mut vals = vec![f64::NAN; n * side];
        vals.par_chunks_mut(side).enumerate().for_each(|(a, row)| {
            let (ax, ay) = ((a % self.lw) as isize, (a / self.lw) as isize);
            for (k, v) in row.iter_mut().enumerate() {
                let bx = ax + (k % cols) as isize - rx as isize;
                let by = ay + (k / cols) as isize - ry as isize;
                if bx >= 0 && by >= 0 && (bx as usize) < self.lw && (by as usize) < self.lh {
                    *v = self.low_distance(a, by as usize * self.lw + bx as usize);
                }
            }
        });
        self.table = Some(LowTable {
            rx,
            ry,
            cols,
            side,
            vals,
        });
        self
    }

    /// [`Self::low_distance`], from the table where it holds the pair.
    #[inline]
    fn low_distance_of(&self, a: usize, b: usize) -> f64 {
        if let Some(t) = &self.table {
            // Guard: lw > 0 (a table exists only then).
            let (ax, ay) = ((a % self.lw) as isize, (a / self.lw) as isize);
            let (bx, by) = ((b % self.lw) as isize, (b / self.lw) as isize);
            let (dx, dy) = (bx - ax + t.rx as isize, by - ay + t.ry as isize);
            if dx >= 0 && dy >= 0 && dx <= 2 * t.rx as isize && dy <= 2 * t.ry as isize {
                return t.vals[a * t.side + dy as usize * t.cols + dx as usize];
            }
        }
        self.low_distance(a, b)
    }
}

impl PairKernel for UpsampleKernel<'_> {
    fn row_has_candidates(&self, y: usize) -> bool {
        self.sample_row.get(y).is_some_and(|r| *r != NO_SAMPLE)
    }

    #[inline]
    fn add(&self, i: usize, j: usize, d: f64, acc: &mut Acc) {
        let s = self.sample_at[j];
        if s == NO_SAMPLE {
            return;
        }
        // ln((1 - alpha) w + alpha w_u) computed in the log domain, so
        // neither term underflows alone: ln(0) = -inf drops a term.
        let color = self.ln_alpha - d;
        // Guard of `% w`, `/ w` here and below: w > 0 (a pass runs only on
        // a non-empty grid).
        let depth = if self.ln_one_minus_alpha > f64::NEG_INFINITY {
            let (lx, ly) = (self.lo_col[i % self.w], self.lo_row[i / self.w]);
            if lx == NO_SAMPLE || ly == NO_SAMPLE {
                f64::NEG_INFINITY
            } else {
                self.ln_one_minus_alpha - self.low_distance_of(ly * self.lw + lx, s)
            }
        } else {
            f64::NEG_INFINITY
        };
        let mut ln_w = log_add_exp(color, depth);
        if self.spatial > 0.0 {
            // the Gaussian falloff with the distance from i to j
            let (dx, dy) = (
                (i % self.w) as f64 - (j % self.w) as f64,
                (i / self.w) as f64 - (j / self.w) as f64,
            );
            ln_w -= (dx * dx + dy * dy) * self.spatial;
        }
        acc.add(ln_w, self.c[s], 1.0, self.z[s]);
    }
}

/// Per row of a grid `w` wide, the low-resolution row (of a grid `lw`
/// wide) of the samples `sample_at` places on it, or `NO_SAMPLE`.
fn sample_rows(sample_at: &[usize], w: usize, lw: usize) -> Vec<usize> {
    sample_at
        .chunks(w.max(1))
        .map(|row| {
            row.iter()
                .find(|s| **s != NO_SAMPLE)
                // Guard: a placed sample exists only where lw > 0.
                .map_or(NO_SAMPLE, |s| s / lw.max(1))
        })
        .collect()
}

/// `ln(exp(a) + exp(b))` without overflow or underflow; `-inf` when both are.
#[inline]
pub(super) fn log_add_exp(a: f64, b: f64) -> f64 {
    let (hi, lo) = if a >= b { (a, b) } else { (b, a) };
    if lo == f64::NEG_INFINITY {
        return hi;
    }
    hi + (lo - hi).exp().ln_1p()
}

/// The first pass of the upsampling (eq. 4) as flat buffers, for a backend
/// that runs it elsewhere (the GPU): the colour side is a [`PassJob`] over
/// the high-resolution grid (every pixel a target; its `z` and `c` are
/// empty), the depth side the low-resolution samples.
#[derive(Debug, Clone, Copy)]
pub struct UpsampleJob<'a> {
    /// Grid, guide features, patch kernel and `h`s of the colour term.
    pub pass: PassJob<'a>,
    /// Low-resolution width and height.
    pub low: (usize, usize),
    /// Low-resolution depth (0 for holes) and confidence.
    pub lz: &'a [f32],
    /// Low-resolution confidence, 0 for holes.
    pub lc: &'a [f32],
    /// Per high-resolution pixel, the low-resolution sample placed on it
    /// (`usize::MAX`: none).
    pub sample_at: &'a [usize],
    /// Per high-resolution column / row, the low-resolution column / row
    /// its ray falls in (`usize::MAX`: outside).
    pub lo_col: &'a [usize],
    /// See `lo_col`.
    pub lo_row: &'a [usize],
    /// Radius of the low-resolution depth patches.
    pub low_patch: usize,
    /// The blend of eq. 4: `alpha` on the colour term, `1 - alpha` on the
    /// depth term.
    pub alpha: f64,
    /// The spatial falloff: each weight times `exp(-|i - j|^2 spatial)`,
    /// `|i - j|` in high-resolution pixels (0: none, eq. 4 as published).
    pub spatial: f64,
}

/// [`UpsampleJob`] on the CPU: the pass of [`nlmeans_upsample_with`](crate::depth::nlmeans::nlmeans_upsample_with).
pub fn cpu_upsample_pass(
    job: &UpsampleJob,
    progress: &mut dyn FnMut(f32) -> Result<(), NodeError>,
) -> Result<Vec<Option<(f32, f32)>>, NodeError> {
    let (p, (lw, lh)) = (&job.pass, job.low);
    let core = Core {
        search: p.search,
        patch: p.patch,
        inv_hc2: p.inv_hc2,
        inv_hd2: p.inv_hd2,
    };
    let n_low = 2 * job.low_patch + 1;
    let kernel = UpsampleKernel {
        w: p.w,
        sample_at: job.sample_at,
        lo_col: job.lo_col,
        lo_row: job.lo_row,
        z: job.lz,
        c: job.lc,
        lw,
        lh,
        low_patch: job.low_patch as isize,
        // Guard: n_low >= 1.
        inv_low_area: 1.0 / (n_low * n_low) as f64,
        inv_hd2: p.inv_hd2,
        ln_alpha: job.alpha.ln(),
        ln_one_minus_alpha: (1.0 - job.alpha).ln(),
        spatial: job.spatial,
        sample_row: sample_rows(job.sample_at, p.w, lw),
        table: None,
    }
    .with_table(p.search, p.h);
    let pass = Pass::new((p.w, p.h), p.guide, None, core);
    let mut out = vec![None; p.w * p.h];
    run_pass(&pass, p.targets, &PerPair(&kernel), progress, |i, r| {
        if let Finish::Done(v) = r {
            out[i] = v;
        }
    })?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kit::rng::SplitMix64;

    /// The table holds the bits `low_distance` computes, for every pair in
    /// its reach (pairs beyond it are computed when asked), and its reach is
    /// the placement's: 2 low-resolution pixels for a window of 8 at x4
    /// (a sample 8 columns away is 2 low-resolution columns away).
    #[test]
    fn the_table_of_low_distances_holds_the_same_bits() {
        use super::super::upsample::axis_map;
        let (lw, lh, f) = (9usize, 7usize, 4usize);
        let (w, h) = (lw * f, lh * f);
        let k = crate::sim::synthetic::kinect_like_intrinsics(lw, lh);
        let hk = k.scaled_to(w, h);
        let to_hi_col = axis_map(lw, k.fx, k.cx, hk.fx, hk.cx, w);
        let to_hi_row = axis_map(lh, k.fy, k.cy, hk.fy, hk.cy, h);
        let mut sample_at = vec![NO_SAMPLE; w * h];
        for (ly, &hy) in to_hi_row.iter().enumerate() {
            for (lx, &hx) in to_hi_col.iter().enumerate() {
                sample_at[hy * w + hx] = ly * lw + lx;
            }
        }
        let lo_col = axis_map(w, hk.fx, hk.cx, k.fx, k.cx, lw);
        let lo_row = axis_map(h, hk.fy, hk.cy, k.fy, k.cy, lh);
        let mut rng = SplitMix64(11);
        let z: Vec<f32> = (0..lw * lh).map(|_| 1.0 + rng.next_f64() as f32).collect();
        // some holes (confidence 0) among partly confident samples
        let c: Vec<f32> = (0..lw * lh)
            .map(|i| {
                if i % 5 == 0 {
                    0.0
                } else {
                    0.5 + 0.5 * rng.next_f64() as f32
                }
            })
            .collect();
        let kernel = UpsampleKernel {
            w,
            sample_at: &sample_at,
            lo_col: &lo_col,
            lo_row: &lo_row,
            z: &z,
            c: &c,
            lw,
            lh,
            low_patch: 1,
            inv_low_area: 1.0 / 9.0,
            inv_hd2: 400.0,
            ln_alpha: 0.9f64.ln(),
            ln_one_minus_alpha: 0.1f64.ln(),
            spatial: 0.0,
            sample_row: sample_rows(&sample_at, w, lw),
            table: None,
        }
        .with_table(8, h);
        let t = kernel.table.as_ref().map(|t| (t.rx, t.ry));
        assert_eq!(t, Some((2, 2)));
        for a in 0..lw * lh {
            for b in 0..lw * lh {
                let (want, got) = (kernel.low_distance(a, b), kernel.low_distance_of(a, b));
                assert_eq!(want.to_bits(), got.to_bits(), "pair ({a}, {b})");
            }
        }
        // every pair a window of 8 asks for is in the table
        for (x, &own) in lo_col.iter().enumerate() {
            for xj in x.saturating_sub(8)..(x + 9).min(w) {
                if let Some(s) = (0..h)
                    .map(|y| sample_at[y * w + xj])
                    .find(|s| *s != NO_SAMPLE)
                {
                    assert!((s % lw).abs_diff(own) <= 2, "column {x} to {xj}");
                }
            }
        }
    }
}
