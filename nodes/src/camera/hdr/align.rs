//! Alignment of handheld brackets by median threshold bitmaps (G. Ward,
//! "Fast, Robust Image Registration for Compositing High Dynamic Range
//! Photographs from Hand-Held Exposures", JGT 8(2), 2003).
//!
//! Thresholding each exposure at its own median gives bitmaps that are
//! nearly the same whatever the exposure (a monotone response keeps the
//! order of pixel values), so they can be compared by XOR. Pixels within
//! `tolerance` levels of the median flip with noise and are excluded. The
//! translation is found coarse to fine on an image pyramid: at each level
//! the 9 shifts around twice the coarser level's answer are scored by the
//! number of differing, non-excluded pixels.

use depthgraph_graph::prelude::*;
use rayon::prelude::*;

/// Parameters of [`align_bracket`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AlignParams {
    /// Largest translation searched, in pixels (per axis, between
    /// neighbouring exposures): the pyramid gets `ceil(log2(max_shift + 1))`
    /// levels below full resolution.
    pub max_shift: usize,
    /// Half-width, in 8-bit levels, of the band around the median whose
    /// pixels are excluded from the comparison (Ward's exclusion bitmap).
    pub tolerance: f64,
}

impl Default for AlignParams {
    fn default() -> Self {
        Self {
            max_shift: 32,
            tolerance: 4.0,
        }
    }
}

/// Result of [`align_bracket`].
#[derive(Debug, Clone, PartialEq)]
pub struct Alignment {
    /// The exposures moved onto the reference; pixels that came from outside
    /// an image are missing (NaN), which the merge ignores.
    pub stack: ExposureStack,
    /// Translation `(dx, dy)` applied to each exposure (in stack order):
    /// aligned `(x, y)` reads the original at `(x - dx, y - dy)`. The
    /// reference (the exposure of median time) has `(0, 0)`.
    pub shifts: Vec<(i64, i64)>,
    /// 1 where every aligned exposure has a value, else 0.
    pub covered: Mask,
}

/// A grey image at one pyramid level, in 8-bit levels; NaN = missing.
struct Grey {
    w: usize,
    h: usize,
    v: Vec<f32>,
}

impl Grey {
    /// Ward's grey `(54 R + 183 G + 19 B) / 256` of values in `[0, 1]`,
    /// in levels; missing when any channel is.
    fn of(img: &ColorImage) -> Self {
        let v = img
            .as_slice()
            .iter()
            .map(|p| {
                if p.iter().all(|c| c.is_finite()) {
                    (54.0 * p[0].clamp(0.0, 1.0)
                        + 183.0 * p[1].clamp(0.0, 1.0)
                        + 19.0 * p[2].clamp(0.0, 1.0))
                        * (255.0 / 256.0)
                } else {
                    f32::NAN
                }
            })
            .collect();
        Self {
            w: img.width(),
            h: img.height(),
            v,
        }
    }

    /// 2x2 box average of the finite values (NaN when none).
    fn half(&self) -> Self {
        let (w, h) = ((self.w / 2).max(1), (self.h / 2).max(1));
        let mut v = vec![f32::NAN; w * h];
        for y in 0..h {
            for x in 0..w {
                let (mut s, mut n) = (0.0f32, 0u32);
                for (sx, sy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                    let (xx, yy) = ((2 * x + sx).min(self.w - 1), (2 * y + sy).min(self.h - 1));
                    let a = self.v[yy * self.w + xx];
                    if a.is_finite() {
                        s += a;
                        n += 1;
                    }
                }
                if n > 0 {
                    v[y * w + x] = s / n as f32; // guard: n > 0
                }
            }
        }
        Self { w, h, v }
    }

    /// The value below which a fraction `q` of the finite pixels lie.
    fn quantile(&self, q: f64) -> Option<f32> {
        let mut finite: Vec<f32> = self.v.iter().copied().filter(|a| a.is_finite()).collect();
        if finite.is_empty() {
            return None;
        }
        let k = ((q * finite.len() as f64) as usize).min(finite.len() - 1);
        let (_, v, _) = finite.select_nth_unstable_by(k, f32::total_cmp);
        Some(*v)
    }

    /// Fractions of the finite pixels stuck at the dark and at the bright
    /// end: within `tol + 1` levels of the 0.5th and 99.5th percentiles
    /// (a clipped or film-base floor, a saturated ceiling).
    fn stuck_fractions(&self, tol: f32) -> (f64, f64) {
        let (Some(lo), Some(hi)) = (self.quantile(0.005), self.quantile(0.995)) else {
            return (0.0, 0.0);
        };
        let (mut n, mut dark, mut bright) = (0usize, 0usize, 0usize);
        for v in self.v.iter().filter(|v| v.is_finite()) {
            n += 1;
            dark += usize::from(*v <= lo + tol + 1.0);
            bright += usize::from(*v >= hi - tol - 1.0);
        }
        // guard: quantiles exist, so n >= 1
        (dark as f64 / n as f64, bright as f64 / n as f64)
    }

    /// Threshold bitmap (above `threshold`) and exclusion bitmap (finite
    /// and farther than `tol` from it).
    fn bitmaps(&self, threshold: f32, tol: f32) -> Bitmaps {
        Bitmaps {
            w: self.w,
            h: self.h,
            tb: self.v.iter().map(|a| *a > threshold).collect(),
            eb: self
                .v
                .iter()
                .map(|a| a.is_finite() && (a - threshold).abs() > tol)
                .collect(),
        }
    }
}

/// Threshold and exclusion bitmaps of one pyramid level.
struct Bitmaps {
    w: usize,
    h: usize,
    tb: Vec<bool>,
    eb: Vec<bool>,
}

/// A grey image at full resolution (index 0) and `levels` halvings.
fn pyramid(g: Grey, levels: usize) -> Vec<Grey> {
    let mut out = vec![g];
    for _ in 0..levels {
        let next = out[out.len() - 1].half();
        out.push(next);
    }
    out
}

/// The quantile both images of a pair are thresholded at: Ward's median,
/// unless one of them has more than half its pixels stuck at an end
/// (saturated windows, film base); then the middle of the quantiles where
/// neither is stuck, so that both bitmaps still split the scene the same way.
/// `a`, `b`: each image's [`Grey::stuck_fractions`].
fn pair_quantile((da, ba): (f64, f64), (db, bb): (f64, f64)) -> f64 {
    let lo = da.max(db);
    let hi = 1.0 - ba.max(bb);
    if lo < 0.5 && hi > 0.5 {
        0.5
    } else if lo < hi {
        0.5 * (lo + hi)
    } else {
        0.5
    }
}

/// Number of pixels where `a` and `b` shifted by `(dx, dy)` (b's pixel
/// `(x - dx, y - dy)` against a's `(x, y)`) differ, counting only pixels
/// kept by both exclusion bitmaps.
fn cost(a: &Bitmaps, b: &Bitmaps, dx: i64, dy: i64) -> u64 {
    let (w, h) = (a.w as i64, a.h as i64);
    let mut n = 0u64;
    for y in 0..h {
        let by = y - dy;
        if by < 0 || by >= h {
            continue;
        }
        let x0 = dx.max(0);
        let x1 = (w + dx).min(w);
        for x in x0..x1 {
            let (i, j) = ((y * w + x) as usize, (by * w + x - dx) as usize);
            if a.eb[i] && b.eb[j] && a.tb[i] != b.tb[j] {
                n += 1;
            }
        }
    }
    n
}

/// The translation that moves `b` onto `a`, searched coarse to fine over
/// their pyramids (same sizes, full resolution first), both thresholded at
/// the quantile `q`.
fn shift_between(a: &[Grey], b: &[Grey], q: f64, tol: f32) -> (i64, i64) {
    let (mut dx, mut dy) = (0i64, 0i64);
    for (ga, gb) in a.iter().zip(b).rev() {
        dx *= 2;
        dy *= 2;
        let (Some(ta), Some(tb)) = (ga.quantile(q), gb.quantile(q)) else {
            continue; // nothing finite at this level: keep the coarser answer
        };
        let (la, lb) = (&ga.bitmaps(ta, tol), &gb.bitmaps(tb, tol));
        let mut best = (u64::MAX, dx, dy);
        for (ox, oy) in [
            (0, 0),
            (-1, 0),
            (1, 0),
            (0, -1),
            (0, 1),
            (-1, -1),
            (1, -1),
            (-1, 1),
            (1, 1),
        ] {
            let c = cost(la, lb, dx + ox, dy + oy);
            if c < best.0 {
                best = (c, dx + ox, dy + oy);
            }
        }
        (dx, dy) = (best.1, best.2);
    }
    (dx, dy)
}

/// Aligns every exposure of `stack` to the one of median time by
/// median-threshold-bitmap translation (Ward 2003), chaining neighbours in
/// time order (each exposure is registered to the next one towards the
/// reference, whose bitmaps resemble it most). Integer translations only;
/// pixels shifted in from outside become missing (NaN).
///
/// Errors: a bad stack (see `HdrMerge`), `max_shift` 0 or above 4096, or a
/// negative or non-finite tolerance.
pub fn align_bracket(stack: &ExposureStack, p: &AlignParams) -> Result<Alignment, NodeError> {
    let (w, h) = super::curve::check_stack(stack)?;
    if !(1..=4096).contains(&p.max_shift) {
        return Err(NodeError::param(
            "max_shift",
            format!("{} is outside 1..=4096 pixels", p.max_shift),
        ));
    }
    if !(p.tolerance.is_finite() && p.tolerance >= 0.0) {
        return Err(NodeError::param(
            "tolerance",
            format!("{} must be finite and non-negative", p.tolerance),
        ));
    }
    let n = stack.images.len();
    // levels below full resolution: 2^levels - 1 >= max_shift, while the
    // coarsest image keeps at least 8 pixels per side
    let mut levels = 0usize;
    while (1usize << levels) - 1 < p.max_shift && (w.min(h) >> (levels + 1)) >= 8 {
        levels += 1;
    }
    let tol = p.tolerance as f32;
    let pyramids: Vec<Vec<Grey>> = stack
        .images
        .par_iter()
        .map(|img| pyramid(Grey::of(img), levels))
        .collect();
    // each image's stuck fractions at full resolution, once
    let stuck: Vec<(f64, f64)> = pyramids
        .par_iter()
        .map(|p| p[0].stuck_fractions(tol))
        .collect();
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by(|a, b| {
        stack.times_s[*a]
            .total_cmp(&stack.times_s[*b])
            .then(a.cmp(b))
    });
    let r = n / 2; // position of the reference in time order
    // shift of each exposure relative to its neighbour towards the reference
    let steps: Vec<(usize, (i64, i64))> = (0..n)
        .into_par_iter()
        .filter(|k| *k != r)
        .map(|k| {
            let toward = if k < r { k + 1 } else { k - 1 };
            let (a, b) = (order[toward], order[k]);
            let q = pair_quantile(stuck[a], stuck[b]);
            let s = shift_between(&pyramids[a], &pyramids[b], q, tol);
            (k, s)
        })
        .collect();
    let mut rel = vec![(0i64, 0i64); n];
    for (k, s) in steps {
        rel[k] = s;
    }
    let mut shifts = vec![(0i64, 0i64); n];
    for k in (0..r).rev() {
        let prev = shifts[order[k + 1]];
        shifts[order[k]] = (prev.0 + rel[k].0, prev.1 + rel[k].1);
    }
    for k in r + 1..n {
        let prev = shifts[order[k - 1]];
        shifts[order[k]] = (prev.0 + rel[k].0, prev.1 + rel[k].1);
    }
    let images: Vec<ColorImage> = stack
        .images
        .par_iter()
        .zip(&shifts)
        .map(|(img, &(dx, dy))| {
            Image::from_fn(w, h, |x, y| {
                let (sx, sy) = (x as i64 - dx, y as i64 - dy);
                if sx >= 0 && sy >= 0 && (sx as usize) < w && (sy as usize) < h {
                    *img.get(sx as usize, sy as usize)
                } else {
                    [f32::NAN; 3]
                }
            })
        })
        .collect();
    let covered = Image::from_fn(w, h, |x, y| {
        let all = images
            .iter()
            .all(|img| img.get(x, y).iter().all(|v| v.is_finite()));
        if all { 1.0 } else { 0.0 }
    });
    Ok(Alignment {
        stack: ExposureStack {
            images,
            times_s: stack.times_s.clone(),
        },
        shifts,
        covered,
    })
}
