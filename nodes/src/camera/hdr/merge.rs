//! The merge of eq. 6 (Debevec & Malik 1997): per-pixel weighted average of
//! `g(Z) - ln Δt`, with a confidence per pixel, documented fallbacks and an
//! optional white reference.

use depthgraph_graph::prelude::*;
use rayon::prelude::*;

use super::curve::{LEVELS, ResponseCurve, Z_MAX, check_stack, hat_weight, level};

/// Sum of weights that counts as full confidence: one exposure at the
/// middle of the range, `w(127.5)`.
const FULL_WEIGHT: f64 = 127.5;

/// How the exposures of one pixel are weighted in eq. 6.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum MergeWeights {
    /// One weight per pixel and exposure, the mean of the three channels'
    /// weights (hat times resolution, see `Lut`; a missing channel counts 0), used for every channel
    /// whose own value is not clipped (`0 < z < 255`). An exposure is
    /// trusted as a whole: one channel near its toe does not make that
    /// channel's estimate come from a different exposure than its
    /// neighbours', which on real brackets tints dark and bright regions.
    #[default]
    Joint,
    /// Each channel weighted by its own weight (eq. 4's hat times the
    /// resolution factor).
    Channel,
}

/// Parameters of [`merge_hdr_with`].
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct MergeParams {
    /// Weighting of the exposures.
    pub weights: MergeWeights,
    /// A region `[x0, y0, x1)` x `[y0, y1)` (pixels, `[x0, y0, x1, y1]`)
    /// known to be neutral (white or grey): after the merge each channel is
    /// scaled so that the region's mean radiance is the same in all three,
    /// keeping the mean over channels. `None`: the camera's own balance.
    pub white: Option<[usize; 4]>,
}

/// Result of [`merge_hdr`].
#[derive(Debug, Clone, PartialEq)]
pub struct Merged {
    /// Linear radiance `E` per channel (scale: see the module docs).
    pub color: ColorImage,
    /// 1 where some channel had no weighted value (fallback estimate or
    /// missing everywhere), else 0.
    pub fallback: Mask,
    /// Per pixel, `min(1, Σ_j w_j / 127.5)` of its least supported channel:
    /// 1 when the weights add up to at least one exposure at mid level, 0
    /// for a fallback pixel.
    pub confidence: Confidence,
}

/// A real level this close to an 8-bit level reads as that level (what an
/// 8-bit value stored as f32 gives back): its table entries, and clipped
/// at 0 and 255.
const LEVEL_SNAP: f64 = 1e-4;

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

    /// Adds level `z` (present) of an exposure with `ln Δt = lt` and
    /// `g(z) = gz`, weighted by `w` unless the level itself is clipped.
    /// Written without branches on the data (selects instead): clipped and
    /// well-exposed values alternate unpredictably on real brackets. A
    /// value that is not used adds `0 * (gz - lt)`, which leaves the sums
    /// bit for bit as they were (`gz` and `lt` are finite).
    #[inline]
    fn add(&mut self, z: f64, w: f64, gz: f64, lt: f64) {
        // clipped within the tables' snap (`Lut::at`): a float file's
        // 0.99999994 is level 255, weight 0, and must count as saturated
        // (it fell through to "seen nowhere", E = 0)
        let black = z < LEVEL_SNAP;
        let sat = z > Z_MAX - LEVEL_SNAP;
        self.black_lt = if black {
            self.black_lt.max(lt)
        } else {
            self.black_lt
        };
        self.sat_lt = if sat {
            self.sat_lt.min(lt)
        } else {
            self.sat_lt
        };
        let used = if black || sat || w <= 0.0 { 0.0 } else { w };
        self.num += used * (gz - lt);
        self.den += used;
    }

    /// `ln E` and whether the fallback of [`merge_hdr`] was used.
    fn finish(&self, c: usize, curve: &ResponseCurve) -> (f64, bool) {
        if self.den > 0.0 {
            return (self.num / self.den, false); // eq. 6; guard: den > 0
        }
        let last = curve.g[c].len() - 1;
        let sat = self
            .sat_lt
            .is_finite()
            .then(|| curve.g[c][last] - self.sat_lt);
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

/// Per channel and level: the weight of a value and `g`.
///
/// The weight is the hat of eq. 4 times the curve's exposure resolution at
/// that level relative to the mid-range, `min(1, g'_mid / g'(z))`, with
/// `g'` the central difference of `g` and `g'_mid` its median over levels
/// 64..191. Where the response is flat (a film's toe and shoulder, a
/// sensor's black floor, where many exposures give one level), `g'` is
/// large, one level stands for a wide range of `ln E` and the value says
/// little; the hat alone trusts a value at the film base (level 15 of 255)
/// as much as a well-exposed one at 15 above black, which pulls every dark
/// pixel towards the floor of the shorter exposures. This is the
/// `f / f'`-style weighting of Mitsunaga & Nayar (1999) on top of
/// Debevec & Malik's hat. Measured on the memorial series against
/// Debevec's own merge: RMS ln error 0.353 with the hat alone, 0.176 with
/// the resolution factor (OpenCV 0.317); see `docs/hdr.md`. A curve whose
/// mid-range slope is not positive (a constant curve) keeps the hat.
struct Lut<'a> {
    w: [[f64; LEVELS]; 3],
    curve: &'a ResponseCurve,
}

impl<'a> Lut<'a> {
    fn new(curve: &'a ResponseCurve) -> Self {
        let w = std::array::from_fn(|c| {
            let g = &curve.g[c];
            let slope = |z: usize| {
                let (a, b) = (z.saturating_sub(1), (z + 1).min(LEVELS - 1));
                (g[b] - g[a]) / (b - a) as f64
            };
            let mut mid: Vec<f64> = (64..192).map(slope).collect();
            mid.sort_by(f64::total_cmp);
            let s = mid[mid.len() / 2];
            std::array::from_fn(|z| {
                let h = hat_weight(z as f64);
                let d = slope(z);
                // guard: divides only when d > s > 0
                if s > 0.0 && s.is_finite() && d > s {
                    h * (s / d)
                } else {
                    h
                }
            })
        });
        Self { w, curve }
    }

    /// Weight and `g` of channel `c` at the real level `z` in `[0, 255]`:
    /// the tables at an 8-bit level (within 1e-4, what an 8-bit value
    /// stored as f32 gives back), else interpolated linearly (`g` by
    /// [`ResponseCurve::eval`]).
    #[inline]
    fn at(&self, c: usize, z: f64) -> (f64, f64) {
        let w = &self.w[c];
        // z >= 0: the nearest level by truncation (round() is a libm call
        // on baseline x86-64; this is one instruction and the same value)
        let k = ((z + 0.5) as usize).min(LEVELS - 1);
        if (z - k as f64).abs() < LEVEL_SNAP {
            return (w[k], self.curve.g[c][k]);
        }
        let i = (z as usize).min(LEVELS - 2);
        let f = z - i as f64;
        (w[i] + (w[i + 1] - w[i]) * f, self.curve.eval(c, z))
    }
}

/// [`merge_hdr_with`] with the default parameters (joint weights, no white
/// region).
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
    merge_hdr_with(stack, curve, &MergeParams::default())
}

/// Merges a stack into linear radiance with the response `curve` (eq. 6 of
/// Debevec & Malik), per pixel and channel, accumulating in f64:
/// `ln E = Σ_j w_j (g(Z_j) - ln Δt_j) / Σ_j w_j` over the exposures whose
/// value is present (finite) and not clipped (`0 < Z < 255`), with `g`
/// interpolated at the real level `Z = value * 255` and `w_j` the hat of
/// eq. 4 times the curve's exposure resolution at that level (see `Lut`),
/// shared by the channels or not as [`MergeParams::weights`] says.
///
/// Fallback where `Σ w = 0` (every present value is exactly 0 or 255; such
/// pixels are 1 in [`Merged::fallback`] and 0 in [`Merged::confidence`]):
/// - saturated in every present exposure: the shortest of them, assuming
///   saturation, `ln E = g(255) - ln Δt_min` (a lower bound on `E`, the
///   brightest estimate the data allow);
/// - black in every present exposure: the longest, `ln E = g(0) - ln Δt_max`
///   (an upper bound);
/// - both (only with noise or misregistration): the mean of the two logs;
/// - missing in every exposure: `E = 0`.
///
/// Radiance beyond the f32 range is clamped to `f32::MAX`. Errors: a bad
/// stack, or a white region that is empty, outside the image or without
/// light in some channel.
pub fn merge_hdr_with(
    stack: &ExposureStack,
    curve: &ResponseCurve,
    p: &MergeParams,
) -> Result<Merged, NodeError> {
    let (w, h) = check_stack(stack)?;
    let ln_t: Vec<f64> = stack.times_s.iter().map(|t| t.ln()).collect();
    let lut = Lut::new(curve);
    let mut color = vec![[0.0f32; 3]; w * h];
    let mut fallback = vec![0.0f32; w * h];
    let mut confidence = vec![0.0f32; w * h];
    if w > 0 {
        color
            .par_chunks_mut(w)
            .zip(fallback.par_chunks_mut(w))
            .zip(confidence.par_chunks_mut(w))
            .enumerate()
            .for_each(|(y, ((crow, frow), qrow))| {
                // Pixel by pixel, the exposures' rows side by side: the sums
                // of a pixel stay in registers.
                let rows: Vec<&[[f32; 3]]> = stack.images.iter().map(|img| img.row(y)).collect();
                for (x, ((px, fb), q)) in crow
                    .iter_mut()
                    .zip(frow.iter_mut())
                    .zip(qrow.iter_mut())
                    .enumerate()
                {
                    let mut acc = [Eq6::EMPTY; 3];
                    for (row, &lt) in rows.iter().zip(&ln_t) {
                        let z = row[x].map(level);
                        let wg: [(f64, f64); 3] =
                            std::array::from_fn(|c| z[c].map_or((0.0, 0.0), |zc| lut.at(c, zc)));
                        let joint = (wg[0].0 + wg[1].0 + wg[2].0) / 3.0;
                        for (c, a) in acc.iter_mut().enumerate() {
                            let Some(zc) = z[c] else { continue };
                            let wc = match p.weights {
                                MergeWeights::Joint => joint,
                                MergeWeights::Channel => wg[c].0,
                            };
                            a.add(zc, wc, wg[c].1, lt);
                        }
                    }
                    let mut conf = 1.0f64;
                    for (c, (out, a)) in px.iter_mut().zip(&acc).enumerate() {
                        let (ln_e, used_fallback) = a.finish(c, curve);
                        *out = (ln_e.exp().min(f32::MAX as f64)) as f32;
                        if used_fallback {
                            *fb = 1.0;
                        }
                        // guard: FULL_WEIGHT > 0
                        conf = conf.min((a.den / FULL_WEIGHT).min(1.0));
                    }
                    *q = conf as f32;
                }
            });
    }
    if let Some(rect) = p.white {
        neutralise(&mut color, w, h, rect)?;
    }
    Ok(Merged {
        color: Image::from_vec(w, h, color)?,
        fallback: Image::from_vec(w, h, fallback)?,
        confidence: Image::from_vec(w, h, confidence)?,
    })
}

/// Scales the channels so that the mean of `rect` (`[x0, y0, x1, y1]`,
/// half-open) is neutral, keeping the mean over channels; sums in f64 over
/// finite values.
fn neutralise(
    color: &mut [[f32; 3]],
    w: usize,
    h: usize,
    rect: [usize; 4],
) -> Result<(), NodeError> {
    let [x0, y0, x1, y1] = rect;
    if !(x0 < x1 && y0 < y1 && x1 <= w && y1 <= h) {
        return Err(NodeError::param(
            "white",
            format!(
                "[{x0}, {y0}, {x1}, {y1}] is not a non-empty region [x0, y0, x1, y1] inside the {w}x{h} image"
            ),
        ));
    }
    let mut sum = [0.0f64; 3];
    let mut n = [0usize; 3];
    for y in y0..y1 {
        for px in &color[y * w + x0..y * w + x1] {
            for c in 0..3 {
                if px[c].is_finite() {
                    sum[c] += px[c] as f64;
                    n[c] += 1;
                }
            }
        }
    }
    // guard: a channel with no finite value or no light cannot be balanced
    let mean: Vec<f64> = (0..3)
        .map(|c| if n[c] > 0 { sum[c] / n[c] as f64 } else { 0.0 })
        .collect();
    if let Some(c) = (0..3).find(|c| !(mean[*c] > 0.0 && mean[*c].is_finite())) {
        return Err(NodeError::param(
            "white",
            format!(
                "the region [{x0}, {y0}, {x1}, {y1}] has no light in channel {c}; pick a lit neutral surface"
            ),
        ));
    }
    let grey = (mean[0] + mean[1] + mean[2]) / 3.0;
    let factor: [f64; 3] = std::array::from_fn(|c| grey / mean[c]); // guard: mean > 0 checked
    for px in color.iter_mut() {
        for c in 0..3 {
            px[c] = ((px[c] as f64 * factor[c]).min(f32::MAX as f64)) as f32;
        }
    }
    Ok(())
}
