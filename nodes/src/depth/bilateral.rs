//! `JointBilateral`: edge-preserving smoothing of a depth map guided by its
//! color image (3d-editing Sec. III.B, last paragraph: "We apply bilateral
//! filtering to the hole-filled depth image. We use both of color and depth
//! similarity for weight").
//!
//! Every valid pixel `p` becomes the weighted mean of the valid pixels `q` of
//! its `(2r+1) x (2r+1)` window:
//!
//! `D'(p) = sum_q w(p, q) D(q) / sum_q w(p, q)`, with
//! `w(p, q) = G(|p - q|, sigma_space_px) * G(|C'(p) - C'(q)|, sigma_color) * G(D(q) - D(p), sigma_depth_rel * D(p))`
//!
//! where `G(d, s) = exp(-d^2 / (2 s^2))` and `C'` is the gamma-2 encoded
//! color (see [`joint_bilateral`] for why). The depth range scales with the
//! centre's depth, so the filter treats a 1 cm step at 1 m like a 4 cm step at
//! 4 m, which matches the growth of a depth sensor's noise with distance.
//! Holes stay holes: the filter smooths, it does not fill (filling is the
//! pull-push stage's job, Sec. III.B eqs. 2-4).

use std::sync::Arc;

use depthgraph_graph::node_params;
use depthgraph_graph::prelude::*;
use depthgraph_graph::registry::RegistryError;
use depthgraph_graph::value::Rgb;
use rayon::prelude::*;

/// Why the node passes a depth map without a valid pixel through (both backends).
pub const ALL_HOLES: &str = "the depth map has no valid pixel: nothing to smooth";

/// Largest accepted window radius (the `radius` parameter's maximum).
pub const MAX_RADIUS: usize = 32;

/// Weights below `2^-CUTOFF_LOG2` (6e-8) are 0: this bounds the exponent
/// the fast `exp` must handle and makes holes (infinite exponent) drop out.
const CUTOFF_LOG2: f32 = 24.0;

/// Depth stored for holes in the working buffer. It is finite, so a zero
/// weight times it is zero, and at least 1e30 from every valid depth, so the
/// squared difference overflows `f32` to infinity and the weight is 0: holes
/// drop out without a branch in the inner loop.
const HOLE_SENTINEL: f32 = -1.0e30;

/// Bounds of the per-pixel depth coefficient `log2(e) / (2 (sigma_depth_rel z)^2)`:
/// strictly positive (so `coefficient * inf` is `inf`, never NaN) and finite.
const DEPTH_COEF_MIN: f64 = f32::MIN_POSITIVE as f64;
const DEPTH_COEF_MAX: f64 = 1.0e30;

node_params! {
    /// Parameters of the `JointBilateral` node.
    pub struct BilateralParams {
        /// Window radius in pixels: each pixel averages a (2r+1)^2 window
        /// (5 gives the 11x11 window of OpenCV's jointBilateralFilter at d = 11).
        pub radius: usize = 5usize, ParamKind::Int { min: 1, max: MAX_RADIUS as i64 };
        /// Standard deviation of the spatial Gaussian, in pixels.
        pub sigma_space_px: f64 = 3.0, ParamKind::Float { min: 0.1, max: 100.0 };
        /// Standard deviation of the color range Gaussian, on gamma-2 encoded
        /// colors (sqrt of linear RGB clamped to [0, 1]; close to sRGB-encoded
        /// values / 255, so 0.1 is roughly an 8-bit difference of 25, i.e.
        /// OpenCV's sigmaColor / 255).
        pub sigma_color: f64 = 0.1, ParamKind::Float { min: 1e-3, max: 10.0 };
        /// Standard deviation of the depth range Gaussian as a fraction of the
        /// centre pixel's depth (0.02: 2 cm at 1 m, 6 cm at 3 m). Neighbours
        /// much farther than this in depth (across a depth edge) get no weight.
        pub sigma_depth_rel: f64 = 0.02, ParamKind::Float { min: 1e-4, max: 1.0 };
    }
}

/// Checks the parameters a caller of the plain function may have set by hand
/// (the node's are range-checked by the graph already).
pub fn check_params(p: &BilateralParams) -> Result<(), NodeError> {
    if p.radius == 0 || p.radius > MAX_RADIUS {
        return Err(NodeError::param(
            "radius",
            format!("{} is outside [1, {MAX_RADIUS}]", p.radius),
        ));
    }
    for (name, v) in [
        ("sigma_space_px", p.sigma_space_px),
        ("sigma_color", p.sigma_color),
        ("sigma_depth_rel", p.sigma_depth_rel),
    ] {
        if !(v.is_finite() && v > 0.0) {
            return Err(NodeError::param(
                name,
                format!("{v} must be finite and positive"),
            ));
        }
    }
    Ok(())
}

/// Checks that the guide image has the depth map's size.
pub fn check_color(depth: &DepthMap, color: &ColorImage) -> Result<(), NodeError> {
    if !color.same_dims(depth) {
        return Err(NodeError::input(
            "color",
            format!(
                "is {}x{} but the depth is {}x{}",
                color.width(),
                color.height(),
                depth.width(),
                depth.height()
            ),
        ));
    }
    Ok(())
}

/// The gamma-2 encoding used for the color distance: `sqrt` of the linear
/// value clamped to [0, 1] (HDR highlights all read as 1, NaN as 0), so
/// distances are always finite and at most `sqrt(3)`.
#[inline]
fn encode(v: f32) -> f32 {
    if v > 0.0 { v.min(1.0).sqrt() } else { 0.0 }
}

/// `2^-y` for `0 <= y < CUTOFF_LOG2`: `y = k - u / ln 2` with `k` the
/// nearest integer (found by adding `1.5 * 2^23`, which leaves `k` in the low
/// mantissa bits), `2^(k - y) = exp(u)`, `|u| <= ln 2 / 2`, from its degree-5
/// Taylor polynomial (relative error < 3e-6), and `2^-k` built in the
/// exponent bits. Exactly 1.0 at `y = 0`. Only float arithmetic and bit
/// operations, no branch and no float-to-int cast, so loops over it
/// vectorise.
#[inline(always)]
fn exp2_neg(y: f32) -> f32 {
    const LN2: f32 = std::f32::consts::LN_2;
    const MAGIC: f32 = 12_582_912.0; // 1.5 * 2^23
    let t = y + MAGIC;
    let k = t - MAGIC; // round(y), exact
    let u = (k - y) * LN2;
    let p =
        1.0 + u * (1.0 + u * (1.0 / 2.0 + u * (1.0 / 6.0 + u * (1.0 / 24.0 + u * (1.0 / 120.0)))));
    // 0 <= k <= 24: the biased exponent 127 - k of 2^-k is in [103, 127].
    let k_int = t.to_bits().wrapping_sub(MAGIC.to_bits());
    p * f32::from_bits(127u32.wrapping_sub(k_int) << 23)
}

/// Joint (cross) bilateral filter of `depth` guided by `color`
/// (3d-editing Sec. III.B, last paragraph), see the module docs for the weight.
///
/// - **Color distance**: Euclidean distance between **gamma-2 encoded**
///   colors (`sqrt` of linear RGB clamped to [0, 1]), a cheap perceptual
///   proxy: close to the sRGB curve, roughly uniform in lightness, so one
///   `sigma_color` separates dark and bright surfaces alike, on the scale of
///   an 8-bit camera's values (what the paper's Kinect delivers and OpenCV's
///   filter works on). Distances in linear RGB would make dark regions all
///   look alike and never stop the filter there.
/// - **Holes**: pixels that are not [`DepthMap::is_valid`] (0, NaN, infinite,
///   negative) neither receive nor give weight and come out as `0.0`; valid
///   pixels stay valid (a weighted mean of positive depths is positive).
/// - **Numerics**: the three Gaussians are one exponential of the sum of
///   their exponents (spatial exponents precomputed per window offset),
///   evaluated with a range-reduced polynomial (relative error < 3e-6);
///   weights below `2^-24` are 0. The sums are `sum w` and
///   `sum w (D(q) - D(p))` (so a constant depth comes back bit for bit),
///   accumulated in `f64` over the window rows, each window row's at most 65
///   terms first summed in `f32` (relative error < 4e-6; this keeps the inner
///   loop 4 lanes wide). **Division guard**: the centre pixel is valid and has
///   exponent 0, i.e. weight exactly 1, so the weight sum is at least 1.
/// - **Speed**: for each window offset, one pass over a whole image row
///   updates the accumulators of every pixel of the row (no loop-carried
///   dependency, so it vectorises); rows run in parallel.
/// - **Threads**: each pixel is computed by one thread in a fixed order, so
///   the result is identical for any number of threads.
///
/// Neighbours outside the image are simply absent (no border extension).
///
/// ```
/// use depthgraph_graph::value::Image;
/// use depthgraph_nodes::depth::bilateral::{joint_bilateral, BilateralParams};
/// // A 4x1 strip: two noisy samples near 1 m, a hole, then a far pixel at 3 m.
/// let depth = Image::from_vec(4, 1, vec![1.0f32, 1.02, 0.0, 3.0]).unwrap();
/// let color = Image::filled(4, 1, [0.5f32; 3]);
/// let p = BilateralParams { radius: 3, sigma_depth_rel: 0.05, ..Default::default() };
/// let out = joint_bilateral(&depth, &color, &p).unwrap();
/// let v = out.as_slice();
/// assert!(v[0] > 1.0 && v[0] < 1.01 && v[1] > 1.01 && v[1] < 1.02); // smoothed towards each other
/// assert_eq!(v[2], 0.0); // holes stay holes
/// assert_eq!(v[3], 3.0); // nothing near 3 m to average with: unchanged
/// ```
pub fn joint_bilateral(
    depth: &DepthMap,
    color: &ColorImage,
    p: &BilateralParams,
) -> Result<DepthMap, NodeError> {
    joint_bilateral_with(depth, color, p, |_| Ok(()))
}

/// Rows [`joint_bilateral_with`] filters between two calls of its
/// progress callback (a few milliseconds at 640 px and r = 4).
const BAND_ROWS: usize = 32;

/// [`joint_bilateral`] that calls `on_progress(fraction)` every
/// [`BAND_ROWS`] rows done (every eighth of the rows on a short map), from
/// the worker that finished them, with fractions that rise, and stops with its
/// error when it returns one (cancellation): a large radius on a large map
/// runs for minutes. No barrier between bands: the same bits and the same
/// speed as without a callback.
pub fn joint_bilateral_with(
    depth: &DepthMap,
    color: &ColorImage,
    p: &BilateralParams,
    on_progress: impl Fn(f32) -> Result<(), NodeError> + Sync,
) -> Result<DepthMap, NodeError> {
    check_color(depth, color)?;
    check_params(p)?;
    let (w, h) = depth.dims();
    if w == 0 || h == 0 {
        return Ok(depth.clone());
    }
    let ctx = planes(depth, color, p);
    let mut out = vec![0.0f32; w * h];
    use std::sync::atomic::{AtomicUsize, Ordering};
    // at least about 8 reports (a short, wide strip with a large radius can
    // be cancelled too)
    let band = BAND_ROWS.min(h / 8).max(1);
    let (done, reported) = (AtomicUsize::new(0), AtomicUsize::new(0));
    out.par_chunks_mut(w).enumerate().try_for_each(|(y, row)| {
        ctx.filter_row(y, row);
        let d = done.fetch_add(1, Ordering::Relaxed) + 1;
        // fractions rise: a worker behind one that reported more stays
        // silent
        if (d.is_multiple_of(band) || d == h) && reported.fetch_max(d, Ordering::Relaxed) < d {
            // guard: h > 0 here
            on_progress(d as f32 / h as f32)
        } else {
            Ok(())
        }
    })?;
    Ok(Image::from_vec(w, h, out)?)
}

/// The working planes of [`joint_bilateral`] (inputs checked, not empty).
fn planes(depth: &DepthMap, color: &ColorImage, p: &BilateralParams) -> Planes {
    let (w, h) = depth.dims();
    // Working planes: depth with holes as the sentinel, encoded colors.
    let z: Vec<f32> = depth
        .as_slice()
        .par_iter()
        .map(|&z| {
            if DepthMap::is_valid(z) {
                z
            } else {
                HOLE_SENTINEL
            }
        })
        .collect();
    let plane = |k: usize| -> Vec<f32> {
        color
            .as_slice()
            .par_iter()
            .map(|c: &Rgb| encode(c[k]))
            .collect()
    };
    let log2e = std::f64::consts::LOG2_E;
    Planes {
        w,
        h,
        r: p.radius,
        z,
        c: [plane(0), plane(1), plane(2)],
        space_coef: log2e / (2.0 * p.sigma_space_px * p.sigma_space_px),
        color_coef: (log2e / (2.0 * p.sigma_color * p.sigma_color)) as f32,
        depth_scale: log2e / (2.0 * p.sigma_depth_rel * p.sigma_depth_rel),
    }
}

/// What every row of [`joint_bilateral`] reads; exponents are in base 2
/// (`log2(e)` folded into the coefficients).
struct Planes {
    w: usize,
    h: usize,
    r: usize,
    /// Depth, [`HOLE_SENTINEL`] for holes.
    z: Vec<f32>,
    /// Encoded color channels.
    c: [Vec<f32>; 3],
    space_coef: f64,
    color_coef: f32,
    /// `log2(e) / (2 sigma_depth_rel^2)`, divided by `z^2` per centre pixel.
    depth_scale: f64,
}

impl Planes {
    crate::kit::cpu::simd_versions! {
        /// One output row. On x86-64 CPUs with AVX-512 F or AVX2 the row is
        /// computed by the same code compiled with those instructions (AVX2: 8
        /// f32 lanes instead of SSE2's 4; AVX-512: about 30 % faster than AVX2
        /// at r = 4 on the 2-core test machine), the best the CPU has chosen at
        /// run time; each lane does the scalar code's operations in the same
        /// order (no fused multiply-add, no sum across lanes), so every version
        /// gives the same bits (tested).
        fn filter_row(&self, y: usize, out: &mut [f32]);
        avx2: filter_row_avx2, avx512: filter_row_avx512, body: filter_row_body,
    }

    #[inline(always)]
    fn filter_row_body(&self, y: usize, out: &mut [f32]) {
        let (w, r) = (self.w, self.r);
        let row = y * w..(y + 1) * w;
        let zc = &self.z[row.clone()];
        let [rc, gc, bc] = [0, 1, 2].map(|k| &self.c[k][row.clone()]);
        let depth_coef: Vec<f32> = zc
            .iter()
            .map(|&z| {
                let s = self.depth_scale / (z as f64 * z as f64);
                s.clamp(DEPTH_COEF_MIN, DEPTH_COEF_MAX) as f32
            })
            .collect();
        // Window-row sums in f32 (at most 2r + 1 = 65 terms each), added to
        // the f64 sums after every window row.
        let mut sum_w = vec![0.0f64; w];
        let mut sum_wd = vec![0.0f64; w];
        let mut row_w = vec![0.0f32; w];
        let mut row_wd = vec![0.0f32; w];
        let y0 = y.saturating_sub(r);
        let y1 = (y + r).min(self.h - 1);
        for ny in y0..=y1 {
            let nrow = ny * w..(ny + 1) * w;
            let zn = &self.z[nrow.clone()];
            let [rn, gn, bn] = [0, 1, 2].map(|k| &self.c[k][nrow.clone()]);
            let dy = ny.abs_diff(y);
            row_w.fill(0.0);
            row_wd.fill(0.0);
            for dx in -(r as isize)..=r as isize {
                let adx = dx.unsigned_abs();
                if adx >= w {
                    continue;
                }
                let space = ((adx * adx + dy * dy) as f64 * self.space_coef) as f32;
                // Centres x in [xc, xc + len), neighbours x + dx in [xn, xn + len).
                let len = w - adx;
                let (xc, xn) = if dx < 0 { (adx, 0) } else { (0, adx) };
                accumulate_offset(
                    Centre {
                        z: &zc[xc..xc + len],
                        c: [&rc[xc..xc + len], &gc[xc..xc + len], &bc[xc..xc + len]],
                        depth_coef: &depth_coef[xc..xc + len],
                    },
                    Neighbours {
                        z: &zn[xn..xn + len],
                        c: [&rn[xn..xn + len], &gn[xn..xn + len], &bn[xn..xn + len]],
                    },
                    space,
                    self.color_coef,
                    &mut row_w[xc..xc + len],
                    &mut row_wd[xc..xc + len],
                );
            }
            for (s, r) in sum_w.iter_mut().zip(&row_w) {
                *s += *r as f64;
            }
            for (s, r) in sum_wd.iter_mut().zip(&row_wd) {
                *s += *r as f64;
            }
        }
        for (((o, &z), &sw), &swd) in out.iter_mut().zip(zc).zip(&sum_w).zip(&sum_wd) {
            *o = if z == HOLE_SENTINEL {
                0.0
            } else {
                // Guard: sw >= 1, the centre's own weight (exponent 0).
                let v = (z as f64 + swd / sw) as f32;
                if DepthMap::is_valid(v) { v } else { z }
            };
        }
    }
}

/// Centre pixels of one pass of [`accumulate_offset`].
struct Centre<'a> {
    z: &'a [f32],
    c: [&'a [f32]; 3],
    depth_coef: &'a [f32],
}

/// The neighbour of each centre at the pass's offset.
struct Neighbours<'a> {
    z: &'a [f32],
    c: [&'a [f32]; 3],
}

/// Adds the neighbour at one window offset to every centre of a row segment.
/// All slices have the same length.
#[inline(always)]
fn accumulate_offset(
    centre: Centre,
    nb: Neighbours,
    space: f32,
    color_coef: f32,
    sum_w: &mut [f32],
    sum_wd: &mut [f32],
) {
    let n = sum_w.len();
    // Re-slicing to one length lets the compiler drop the bounds checks.
    let (zc, dc) = (&centre.z[..n], &centre.depth_coef[..n]);
    let (rc, gc, bc) = (&centre.c[0][..n], &centre.c[1][..n], &centre.c[2][..n]);
    let zn = &nb.z[..n];
    let (rn, gn, bn) = (&nb.c[0][..n], &nb.c[1][..n], &nb.c[2][..n]);
    let sum_wd = &mut sum_wd[..n];
    for i in 0..n {
        let dz = zn[i] - zc[i];
        let (dr, dg, db) = (rn[i] - rc[i], gn[i] - gc[i], bn[i] - bc[i]);
        // Every term is >= 0 and none is 0 * inf, so e is never NaN; a hole
        // on either side makes dz^2 (hence e) infinite.
        let e = space + color_coef * (dr * dr + dg * dg + db * db) + dc[i] * (dz * dz);
        let inside = e < CUTOFF_LOG2;
        let wgt = exp2_neg(if inside { e } else { 0.0 });
        let wgt = if inside { wgt } else { 0.0 };
        sum_w[i] += wgt;
        sum_wd[i] += wgt * dz;
    }
}

depthgraph_graph::ports! {
    /// Inputs of `JointBilateral`.
    inputs struct BilateralIn {
        /// metres, 0 = no measurement
        depth: Arc<DepthMap>,
        /// linear RGB guide, same size as depth
        color: Arc<ColorImage>,
    }
}

depthgraph_graph::ports! {
    /// Outputs of `JointBilateral`.
    outputs struct BilateralOut {
        /// smoothed metres, holes where the input has holes
        depth: Arc<DepthMap>,
    }
}

fn eval(
    ctx: &EvalCtx,
    i: BilateralIn,
    p: &BilateralParams,
) -> Result<Produced<BilateralOut>, NodeError> {
    if i.depth.hole_count() == i.depth.len() {
        check_color(&i.depth, &i.color)?;
        return Ok(Produced::passthrough(
            BilateralOut {
                depth: DepthMap::canonical_holes(&i.depth),
            },
            ALL_HOLES,
        ));
    }
    let depth = Arc::new(joint_bilateral_with(&i.depth, &i.color, p, |f| {
        ctx.progress(f);
        ctx.check_cancelled()
    })?);
    Ok(BilateralOut { depth }.into())
}

/// Registers `JointBilateral`.
pub fn register(reg: &mut Registry) -> Result<(), RegistryError> {
    reg.register(PortedNode::new(
        "JointBilateral",
        1,
        "Edge-preserving depth smoothing guided by color (3d-editing Sec. III.B): spatial x color x depth-range weights.\n\
         Holes stay holes; the depth range scales with the distance (sigma_depth_rel * z).",
        eval,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kit::rng::SplitMix64;

    #[test]
    fn the_vector_rows_equal_the_plain_rows_bit_for_bit() {
        let (w, h) = (53, 17);
        let mut rng = SplitMix64(11);
        let depth = Image::from_fn(w, h, |_, _| {
            if rng.uniform() < 0.2 {
                0.0
            } else {
                (1.0 + 2.0 * rng.uniform()) as f32
            }
        });
        let color = Image::from_fn(w, h, |_, _| [0, 1, 2].map(|_| rng.uniform() as f32));
        let p = BilateralParams {
            radius: 4,
            ..Default::default()
        };
        let ctx = planes(&depth, &color, &p);
        // every compiled version this CPU can run, beside the plain one
        type Row<'a> = Box<dyn Fn(usize, &mut [f32]) + 'a>;
        let mut versions: Vec<(&str, Row)> =
            vec![("dispatch", Box::new(|y, o| ctx.filter_row(y, o)))];
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx2") {
                // SAFETY: the CPU has AVX2.
                versions.push((
                    "avx2",
                    Box::new(|y, o| unsafe { ctx.filter_row_avx2(y, o) }),
                ));
            }
            if crate::kit::cpu::avx512() {
                // SAFETY: the CPU has AVX-512 F (and what it implies).
                versions.push((
                    "avx512",
                    Box::new(|y, o| unsafe { ctx.filter_row_avx512(y, o) }),
                ));
            }
        }
        let (mut a, mut b) = (vec![0.0f32; w], vec![0.0f32; w]);
        for (name, f) in &versions {
            let mut differ = 0;
            for y in 0..h {
                f(y, &mut a);
                ctx.filter_row_body(y, &mut b);
                differ += a
                    .iter()
                    .zip(&b)
                    .filter(|(x, y)| x.to_bits() != y.to_bits())
                    .count();
            }
            assert_eq!(differ, 0, "{name}");
        }
        // the check sees a change in the last place
        b[3] = f32::from_bits(b[3].to_bits() + 1);
        assert!(a.iter().zip(&b).any(|(x, y)| x.to_bits() != y.to_bits()));
        eprintln!("versions compared: {}", versions.len());
    }

    /// Straightforward reference: exact `exp` per neighbour, `f64` throughout.
    fn reference(depth: &DepthMap, color: &ColorImage, p: &BilateralParams) -> DepthMap {
        let (w, h) = depth.dims();
        let r = p.radius as isize;
        Image::from_fn(w, h, |x, y| {
            let zc = *depth.get(x, y);
            if !DepthMap::is_valid(zc) {
                return 0.0;
            }
            let cc = color.get(x, y).map(encode);
            let (mut sw, mut swz) = (0.0f64, 0.0f64);
            for dy in -r..=r {
                for dx in -r..=r {
                    let (nx, ny) = (x as isize + dx, y as isize + dy);
                    let Some(&zn) = depth.try_get(nx, ny) else {
                        continue;
                    };
                    if !DepthMap::is_valid(zn) {
                        continue;
                    }
                    let cn = color.get(nx as usize, ny as usize).map(encode);
                    let dc2: f64 = (0..3).map(|k| ((cn[k] - cc[k]) as f64).powi(2)).sum();
                    let ds2 = (dx * dx + dy * dy) as f64;
                    let sd = p.sigma_depth_rel * zc as f64;
                    let e = ds2 / (2.0 * p.sigma_space_px.powi(2))
                        + dc2 / (2.0 * p.sigma_color.powi(2))
                        + (zn as f64 - zc as f64).powi(2) / (2.0 * sd * sd);
                    let wgt = (-e).exp();
                    sw += wgt;
                    swz += wgt * zn as f64;
                }
            }
            (swz / sw) as f32
        })
    }

    /// Near box (1 m) in front of a far wall (2 m) with Gaussian noise of
    /// `sigma_m`; returns (truth, noisy, box mask).
    fn step_scene(w: usize, h: usize, sigma_m: f64) -> (DepthMap, DepthMap, Image<bool>) {
        let inside = Image::from_fn(w, h, |x, y| {
            x >= w / 3 && x < 2 * w / 3 && y >= h / 4 && y < 3 * h / 4
        });
        let truth = inside.map(|&b| if b { 1.0f32 } else { 2.0 });
        let noisy = Image::from_fn(w, h, |x, y| {
            let mut rng = SplitMix64::for_pixel(7, 0, x as u64, y as u64);
            (*truth.get(x, y) as f64 + sigma_m * rng.gaussian()) as f32
        });
        (truth, noisy, inside)
    }

    fn rmse(a: &DepthMap, b: &DepthMap) -> f64 {
        let s: f64 = a
            .as_slice()
            .iter()
            .zip(b.as_slice())
            .map(|(x, y)| (*x as f64 - *y as f64).powi(2))
            .sum();
        (s / a.len() as f64).sqrt()
    }

    #[test]
    fn constant_depth_is_an_exact_no_op() {
        let d = DepthMap::filled(40, 30, 1.234_567);
        let c = Image::from_fn(40, 30, |x, y| [x as f32 / 40.0, y as f32 / 30.0, 0.3]);
        let out = joint_bilateral(&d, &c, &BilateralParams::default()).unwrap();
        assert_eq!(out, d);
    }

    #[test]
    fn matches_the_exact_reference() {
        let (_, noisy, inside) = step_scene(48, 36, 0.01);
        let c = Image::from_fn(48, 36, |x, y| {
            let t = if *inside.get(x, y) { 0.6 } else { 0.1 };
            [t, 0.2 + 0.01 * x as f32, 0.3 + 0.005 * y as f32]
        });
        let p = BilateralParams::default();
        let fast = joint_bilateral(&noisy, &c, &p).unwrap();
        let slow = reference(&noisy, &c, &p);
        let worst = fast
            .as_slice()
            .iter()
            .zip(slow.as_slice())
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        // Fast exp (< 3e-6) and f32 window-row sums: a few ulp at 2 m.
        assert!(worst < 1e-6, "worst difference {worst} m");
    }

    #[test]
    fn smooths_noise_and_keeps_the_step_sharp() {
        let sigma = 0.01;
        let (w, h) = (96, 72);
        let (truth, noisy, inside) = step_scene(w, h, sigma);
        // Constant color: only the depth range weight can stop the filter.
        let c = ColorImage::filled(w, h, [0.4; 3]);
        let out = joint_bilateral(&noisy, &c, &BilateralParams::default()).unwrap();
        let before = rmse(&noisy, &truth);
        let after = rmse(&out, &truth);
        // Measured: 0.0100 -> 0.0016 m (x6.2).
        assert!(
            before / after > 4.0,
            "rmse {before} -> {after} (x{})",
            before / after
        );
        // Pixels next to the edge stay on their own side: within 2 sigma of
        // their own truth, where blending across would move them by ~0.5 m.
        let mut edge_pixels = 0;
        for y in 0..h {
            for x in 0..w {
                let own = *inside.get(x, y);
                let at_edge =
                    [(1isize, 0isize), (-1, 0), (0, 1), (0, -1)]
                        .iter()
                        .any(|(dx, dy)| {
                            inside
                                .try_get(x as isize + dx, y as isize + dy)
                                .is_some_and(|&o| o != own)
                        });
                if at_edge {
                    edge_pixels += 1;
                    let err = (out.get(x, y) - truth.get(x, y)).abs() as f64;
                    assert!(err < 2.0 * sigma, "({x}, {y}) off by {err}");
                }
            }
        }
        assert!(edge_pixels > 100);
    }

    #[test]
    fn color_edges_stop_the_filter_when_depth_cannot() {
        let (w, h) = (64, 48);
        let (truth, noisy, inside) = step_scene(w, h, 0.01);
        // A depth range this wide (100 % of z) no longer separates 1 m from 2 m...
        let p = BilateralParams {
            sigma_depth_rel: 1.0,
            ..Default::default()
        };
        let grey = ColorImage::filled(w, h, [0.4; 3]);
        let blended = joint_bilateral(&noisy, &grey, &p).unwrap();
        let x = w / 3; // first column of the box
        let y = h / 2;
        assert!(
            (blended.get(x, y) - truth.get(x, y)).abs() > 0.1,
            "grey guide should blend"
        );
        // ...but a red box on a blue wall does.
        let c = inside.map(|&b| if b { [0.8, 0.1, 0.1] } else { [0.1, 0.1, 0.8] });
        let out = joint_bilateral(&noisy, &c, &p).unwrap();
        for (i, (a, t)) in out.as_slice().iter().zip(truth.as_slice()).enumerate() {
            assert!((a - t).abs() < 0.02, "pixel {i}: {a} vs {t}");
        }
    }

    #[test]
    fn holes_stay_holes_and_bad_values_are_holes() {
        let (w, h) = (30, 20);
        let bad = [0.0, -1.0, f32::NAN, f32::INFINITY, f32::NEG_INFINITY];
        let d = Image::from_fn(w, h, |x, y| {
            if (x * 7 + y * 3) % 5 == 0 {
                bad[(x + y) % bad.len()]
            } else {
                1.0 + 0.01 * ((x * y) % 3) as f32
            }
        });
        let c = Image::from_fn(w, h, |x, y| match (x + 2 * y) % 7 {
            0 => [f32::NAN, 0.5, 0.5],
            1 => [f32::INFINITY, -1.0, 0.5],
            _ => [0.2, 0.3, 0.4],
        });
        let out = joint_bilateral(&d, &c, &BilateralParams::default()).unwrap();
        for (a, b) in d.as_slice().iter().zip(out.as_slice()) {
            assert!(b.is_finite());
            if DepthMap::is_valid(*a) {
                assert!(DepthMap::is_valid(*b), "valid pixel lost: {a} -> {b}");
                assert!((0.999..=1.021).contains(b), "{b} outside the input range");
            } else {
                assert_eq!(*b, 0.0, "hole {a} not written as 0");
            }
        }
    }

    #[test]
    fn tiny_images_and_constant_color() {
        let p = BilateralParams::default();
        let one = DepthMap::filled(1, 1, 2.5);
        let c1 = ColorImage::filled(1, 1, [0.3; 3]);
        assert_eq!(joint_bilateral(&one, &c1, &p).unwrap(), one);
        for (w, h) in [(1, 9), (9, 1)] {
            let d = Image::from_fn(w, h, |x, y| 1.0 + 0.01 * ((x + y) % 2) as f32);
            // Two different constant colors: W_c = 1 everywhere, same result,
            // equal to the reference.
            let a = joint_bilateral(&d, &ColorImage::filled(w, h, [0.1; 3]), &p).unwrap();
            let b = joint_bilateral(&d, &ColorImage::filled(w, h, [0.9, 0.2, 0.0]), &p).unwrap();
            assert_eq!(a, b);
            let r = reference(&d, &ColorImage::filled(w, h, [0.1; 3]), &p);
            for (x, y) in a.as_slice().iter().zip(r.as_slice()) {
                assert!((x - y).abs() < 1e-5 && x.is_finite());
            }
        }
        let empty = DepthMap::filled(0, 0, 0.0);
        let out = joint_bilateral(&empty, &ColorImage::filled(0, 0, [0.0; 3]), &p).unwrap();
        assert!(out.is_empty());
    }

    #[test]
    fn same_bits_for_any_thread_count() {
        let (_, noisy, inside) = step_scene(80, 60, 0.02);
        let c = inside.map(|&b| if b { [0.7, 0.2, 0.2] } else { [0.2, 0.2, 0.7] });
        let p = BilateralParams::default();
        let run = |n: usize| {
            crate::test_support::with_threads(n, || joint_bilateral(&noisy, &c, &p).unwrap())
        };
        let one = run(1);
        let three = run(3);
        assert!(
            one.as_slice()
                .iter()
                .zip(three.as_slice())
                .all(|(a, b)| a.to_bits() == b.to_bits())
        );
    }

    /// The banded filter reports rising progress up to 1, gives the same
    /// bits as without a callback, and stops at the callback's error
    /// (cancellation) before the rest of the rows.
    #[test]
    fn progress_rises_and_cancellation_stops_the_filter() {
        let (_, noisy, inside) = step_scene(64, 300, 0.02);
        let c = inside.map(|&b| if b { [0.7, 0.2, 0.2] } else { [0.2, 0.2, 0.7] });
        let p = BilateralParams::default();
        let whole = joint_bilateral(&noisy, &c, &p).unwrap();
        let seen = std::sync::Mutex::new(Vec::new());
        let banded = crate::test_support::with_threads(2, || {
            joint_bilateral_with(&noisy, &c, &p, |f| {
                seen.lock().unwrap().push(f);
                Ok(())
            })
            .unwrap()
        });
        assert_eq!(banded, whole);
        let seen = seen.into_inner().unwrap();
        assert!(seen.len() >= 300 / BAND_ROWS / 2, "{seen:?}");
        assert!(seen.windows(2).all(|w| w[0] < w[1]), "{seen:?}");
        assert_eq!(seen.last(), Some(&1.0));
        let calls = std::sync::atomic::AtomicUsize::new(0);
        let e = crate::test_support::with_threads(2, || {
            joint_bilateral_with(&noisy, &c, &p, |_| {
                let n = calls.fetch_add(1, std::sync::atomic::Ordering::SeqCst) + 1;
                if n >= 2 {
                    Err(NodeError::Cancelled)
                } else {
                    Ok(())
                }
            })
        })
        .unwrap_err();
        assert!(matches!(e, NodeError::Cancelled));
        // stopped early: fewer reports than bands
        assert!(calls.into_inner() < 300 / BAND_ROWS, "kept going");
    }

    #[test]
    fn bad_sizes_and_params_are_named() {
        let d = DepthMap::filled(8, 8, 1.0);
        let e = joint_bilateral(&d, &ColorImage::filled(4, 8, [0.0; 3]), &Default::default())
            .unwrap_err();
        assert!(
            e.to_string().contains("color") && e.to_string().contains("4x8"),
            "{e}"
        );
        let c = ColorImage::filled(8, 8, [0.0; 3]);
        for (p, name) in [
            (
                BilateralParams {
                    radius: 0,
                    ..Default::default()
                },
                "radius",
            ),
            (
                BilateralParams {
                    sigma_color: 0.0,
                    ..Default::default()
                },
                "sigma_color",
            ),
            (
                BilateralParams {
                    sigma_depth_rel: f64::NAN,
                    ..Default::default()
                },
                "sigma_depth_rel",
            ),
        ] {
            let e = joint_bilateral(&d, &c, &p).unwrap_err();
            assert!(e.to_string().contains(name), "{e}");
        }
    }

    #[test]
    fn node_passes_an_all_hole_depth_through() {
        let mut reg = Registry::new();
        register(&mut reg).unwrap();
        let d = std::sync::Arc::new(DepthMap::filled(6, 4, 0.0));
        let mut inputs = Inputs::new();
        inputs.insert("depth", Value::Depth(d.clone()));
        inputs.insert("color", ColorImage::filled(6, 4, [0.5; 3]).into());
        let p = BilateralParams::default();
        let test_ctx = crate::test_support::TestCtx::new("jb");
        let ctx = test_ctx.ctx();
        let node = reg.get("JointBilateral").unwrap();
        let out = node.eval(&ctx, &inputs, &p.to_values()).unwrap();
        assert!(out.passthrough.is_some());
        assert_eq!(out.values["depth"], Value::Depth(d));
    }
}
