//! Simulated camera defects, applicable to any ground truth (a
//! `SyntheticScene` render or a real dataset's ground truth):
//!
//! - [`simulate_kinect`] (`SimulateKinect`): a structured-light sensor like
//!   Kinect v1: projector shadows beside depth edges, dropouts on dark
//!   surfaces and at grazing angles, noise growing with `z^2`, disparity
//!   quantisation and a working range. These are the holes and the noise the
//!   3-D editing paper fills with its pull-push and bilateral filters
//!   (Sec. III).
//! - [`simulate_tof`] (`SimulateToF`): a low-resolution time-of-flight camera
//!   co-located with the color camera, with flying pixels at depth edges,
//!   noise and outliers, as in the depth-blur paper's setup (Sec. 2-3).
//! - [`simulate_bracket`] (`SimulateBracket`): LDR exposure brackets of a
//!   linear HDR radiance image through a camera response curve, the input of
//!   the depth-blur paper's HDR composition.
//!
//! Randomness comes from [`SplitMix64::for_pixel`](crate::kit::rng::SplitMix64::for_pixel), seeded from `(seed, stream, x, y)`,
//! so results are identical whatever the number of threads.

use crate::camera::response::Curve;
use crate::kit::checks::{fits_intrinsics, same_size};
use crate::kit::color::luminance;
use crate::kit::rng::SplitMix64;
use std::sync::Arc;

use depthgraph_graph::node_params;
use depthgraph_graph::prelude::*;
use glam::DVec3;
use rayon::prelude::*;

/// Stream ids keep the random numbers of the simulations independent.
const STREAM_KINECT: u64 = 1;
const STREAM_TOF: u64 = 2;
/// Bracket image `i` uses stream `STREAM_BRACKET + i`.
const STREAM_BRACKET: u64 = 0x1000;

/// Cells per pixel of the projector's z-buffer: footprints are placed to
/// 1/8 pixel, so shadow bands are exact to that.
const ZBUF_SUBCELLS: f64 = 8.0;

/// Speed of light in m/s.
const SPEED_OF_LIGHT: f64 = 299_792_458.0;

fn image<T, K>(w: usize, h: usize, data: Vec<T>) -> Result<Image<T, K>, NodeError> {
    Ok(Image::from_vec(w, h, data)?)
}

// ---------------------------------------------------------------------------
// Structured light (Kinect v1)
// ---------------------------------------------------------------------------

node_params! {
    /// Parameters of the `SimulateKinect` node.
    pub struct KinectParams {
        /// Distance in metres from the camera to the IR projector, along the
        /// camera's +x axis (the stereo baseline; Kinect v1: 7.5 cm). It sets
        /// the width of the shadow bands and the disparity of the
        /// quantisation; 0 disables both.
        pub baseline_m: f64 = 0.075, ParamKind::Float { min: 0.0, max: 1.0 };
        /// Cut holes where the projector cannot see the surface (the band
        /// beside the left side of near objects when the projector is at +x).
        pub shadows: bool = true, ParamKind::Bool;
        /// A pixel is in the projector's shadow when its depth exceeds the
        /// nearest depth the projector sees along its ray by more than this
        /// fraction of that depth.
        pub shadow_tolerance: f64 = 0.01, ParamKind::Float { min: 0.0, max: 1.0 };
        /// Drop measurements on dark surfaces and at grazing angles.
        pub dropouts: bool = true, ParamKind::Bool;
        /// Linear luminance (Rec. 709 weights of `color`) below which a
        /// surface counts as dark.
        pub dark_threshold: f64 = 0.02, ParamKind::Float { min: 0.0, max: 1.0 };
        /// Probability that a dark pixel has no measurement.
        pub dark_dropout_prob: f64 = 0.5, ParamKind::Float { min: 0.0, max: 1.0 };
        /// Angle in degrees between the surface normal (estimated from the
        /// depth) and the viewing ray above which the pattern is too
        /// stretched to decode: no measurement.
        pub grazing_deg: f64 = 85.0, ParamKind::Float { min: 0.0, max: 90.0 };
        /// Depth noise: Gaussian with standard deviation `noise_k * z^2`
        /// (metres, `noise_k` in 1/m); 0 disables it.
        pub noise_k: f64 = 1.5e-3, ParamKind::Float { min: 0.0, max: 1.0 };
        /// Disparity `fx * baseline / z` is rounded to 1/this of a pixel
        /// (Kinect v1: 8); 0 disables the quantisation.
        pub disparity_subpixel: u32 = 8u32, ParamKind::Int { min: 0, max: 4096 };
        /// Measurements nearer than this (metres) are holes.
        pub min_depth_m: f64 = 0.4, ParamKind::Float { min: 0.0, max: 1000.0 };
        /// Measurements farther than this (metres) are holes.
        pub max_depth_m: f64 = 8.0, ParamKind::Float { min: 0.0, max: 1000.0 };
        /// Seed of the noise and the dark dropouts.
        pub seed: u64 = 0u64, ParamKind::Int { min: 0, max: i64::MAX };
    }
}

/// Writes depth `z` into the z-buffer cells whose centres lie in the
/// projector-pixel interval `[start, end)`.
fn splat(zbuf: &mut [f64], start: f64, end: f64, z: f64) {
    let c0 = (start * ZBUF_SUBCELLS - 0.5).ceil().max(0.0);
    let c1 = (end * ZBUF_SUBCELLS - 0.5).ceil().min(zbuf.len() as f64);
    if c1 > c0 {
        for cell in &mut zbuf[c0 as usize..c1 as usize] {
            *cell = cell.min(z);
        }
    }
}

/// The projector's z-buffer along one row (the projector sits at `+x`, so
/// epipolar lines are rows), [`ZBUF_SUBCELLS`] cells per pixel. Pixel `u` at
/// depth `z` covers projector coordinates `[u, u + 1) - fb / z`; where the
/// footprints of two neighbouring valid pixels leave a gap (a surface
/// receding to the right), the gap is filled with the farther of their
/// depths, so no cracks let background pixels through a surface.
fn projector_zbuffer(row: &[f32], fb: f64) -> Vec<f64> {
    let mut zbuf = vec![f64::INFINITY; (row.len() as f64 * ZBUF_SUBCELLS) as usize];
    // Guard: only valid (positive) depths are divided by.
    let shift = |z: f32| fb / z as f64;
    for (u, &z) in row.iter().enumerate() {
        if !DepthMap::is_valid(z) {
            continue;
        }
        let end = u as f64 + 1.0 - shift(z);
        splat(&mut zbuf, u as f64 - shift(z), end, z as f64);
        if let Some(&zn) = row.get(u + 1)
            && DepthMap::is_valid(zn)
        {
            let next_start = u as f64 + 1.0 - shift(zn);
            if next_start > end {
                splat(&mut zbuf, end, next_start, z.max(zn) as f64);
            }
        }
    }
    zbuf
}

/// Camera-space point of pixel `(x, y)`, `None` outside or without depth.
fn point_at(depth: &DepthMap, k: &Intrinsics, x: isize, y: isize) -> Option<DVec3> {
    let z = *depth.try_get(x, y)?;
    DepthMap::is_valid(z).then(|| k.unproject(x as f64 + 0.5, y as f64 + 0.5, z as f64))
}

/// Tangent from the neighbour on the side with the smaller depth jump, so a
/// pixel at a depth edge gets the normal of its own surface.
fn tangent(c: DVec3, fwd: Option<DVec3>, back: Option<DVec3>) -> Option<DVec3> {
    match (fwd, back) {
        (Some(f), Some(b)) if (f.z - c.z).abs() <= (c.z - b.z).abs() => Some(f - c),
        (Some(_), Some(b)) => Some(c - b),
        (Some(f), None) => Some(f - c),
        (None, Some(b)) => Some(c - b),
        (None, None) => None,
    }
}

/// Unit normal at pixel `(x, y)` from the cross product of unprojected
/// neighbour differences; `None` for isolated pixels.
fn normal_at(depth: &DepthMap, k: &Intrinsics, x: usize, y: usize) -> Option<(DVec3, DVec3)> {
    let (xi, yi) = (x as isize, y as isize);
    let c = point_at(depth, k, xi, yi)?;
    let tx = tangent(
        c,
        point_at(depth, k, xi + 1, yi),
        point_at(depth, k, xi - 1, yi),
    )?;
    let ty = tangent(
        c,
        point_at(depth, k, xi, yi + 1),
        point_at(depth, k, xi, yi - 1),
    )?;
    // normalize_or_zero guards the division by a vanishing cross product.
    let n = tx.cross(ty).normalize_or_zero();
    (n != DVec3::ZERO).then_some((n, c))
}

/// Simulates a Kinect-v1-like structured-light measurement of the ground
/// truth `depth` (metres, 0 = none) seen with intrinsics `k`; `color`
/// (linear, same size) drives the dark-surface dropouts and may be omitted.
///
/// Per pixel, in order:
/// 1. **Projector shadow.** The projector is the camera moved by
///    `baseline_m` along `+x` with the same intrinsics, so a point at pixel
///    `u` and depth `z` appears in the projector at `u - fx * b / z` on the
///    same row (epipolar lines are rows). Every valid pixel splats its
///    footprint `[u, u + 1) - fx b / z` into a per-row z-buffer of the
///    projector with 1/8-pixel cells, gaps between neighbouring footprints
///    filled with the farther depth; a pixel is a hole when its depth
///    exceeds the z-buffer depth `z_p` at its projector position by more
///    than `shadow_tolerance * z_p`. Near objects thus leave a hole band of
///    `fx b (1/z_near - 1/z_far)` pixels on their **left** (`-x`) side.
///    Points outside the projector's image count as lit.
/// 2. **Dropouts** (`dropouts`): with probability `dark_dropout_prob` where
///    the luminance of `color` is below `dark_threshold`, and always where
///    the angle between the viewing ray and the normal (estimated from the
///    ground truth with edge-aware one-sided differences) exceeds
///    `grazing_deg`.
/// 3. **Noise**: `z += noise_k z^2 N(0, 1)`.
/// 4. **Quantisation**: disparity `d = fx b / z` rounded to
///    `1 / disparity_subpixel` pixel, `z = fx b / d`.
/// 5. **Range**: results outside `[min_depth_m, max_depth_m]` are holes.
///
/// ```
/// use depthgraph_nodes::sim::sensor::{simulate_kinect, KinectParams};
/// use depthgraph_nodes::sim::synthetic::kinect_like_intrinsics;
/// use depthgraph_graph::value::DepthMap;
/// let k = kinect_like_intrinsics(64, 48);
/// let gt = DepthMap::filled(64, 48, 2.0);
/// let p = KinectParams { noise_k: 0.0, ..Default::default() };
/// let d = simulate_kinect(&gt, None, &k, &p).unwrap();
/// // Only quantisation: 2 m is 1.97 px of disparity, rounded to 2 px (1.96875 m).
/// assert_eq!(*d.get(10, 10), 1.96875);
/// ```
pub fn simulate_kinect(
    depth: &DepthMap,
    color: Option<&ColorImage>,
    k: &Intrinsics,
    p: &KinectParams,
) -> Result<DepthMap, NodeError> {
    fits_intrinsics("intrinsics", k, "depth map", depth.dims())?;
    if let Some(c) = color {
        same_size(
            "color",
            "a colour image",
            c.dims(),
            "the depth map",
            depth.dims(),
        )?;
    }
    let (w, h) = depth.dims();
    let mut out = vec![0.0f32; w * h];
    if w == 0 || h == 0 {
        return image(w, h, out);
    }
    let fb = k.fx * p.baseline_m;
    let shadowing = p.shadows && fb > 0.0;
    // cos of the grazing limit: a pixel is grazing when |n . view| < this.
    let cos_limit = p.grazing_deg.to_radians().cos();
    out.par_chunks_mut(w).enumerate().for_each(|(y, row_out)| {
        let row = depth.row(y);
        // (1) The projector's z-buffer along this row (empty when unused).
        let zbuf = if shadowing {
            projector_zbuffer(row, fb)
        } else {
            Vec::new()
        };
        for (u, o) in row_out.iter_mut().enumerate() {
            let z = row[u];
            *o = 0.0;
            if !DepthMap::is_valid(z) {
                continue;
            }
            let z = z as f64;
            if shadowing {
                // Guard: z > 0 (valid).
                let cell = ((u as f64 + 0.5 - fb / z) * ZBUF_SUBCELLS).floor();
                if cell >= 0.0
                    && cell < zbuf.len() as f64
                    && z > zbuf[cell as usize] * (1.0 + p.shadow_tolerance)
                {
                    continue;
                }
            }
            // Fixed draw order per pixel, whatever is used.
            let mut rng = SplitMix64::for_pixel(p.seed, STREAM_KINECT, u as u64, y as u64);
            let u_dark = rng.uniform();
            let g = rng.gaussian();
            if p.dropouts {
                if let Some(c) = color
                    && luminance(*c.get(u, y)) < p.dark_threshold
                    && u_dark < p.dark_dropout_prob
                {
                    continue;
                }
                if let Some((n, pt)) = normal_at(depth, k, u, y) {
                    // Guard: pt.z = z > 0, so |pt| > 0.
                    if n.dot(pt).abs() / pt.length() < cos_limit {
                        continue;
                    }
                }
            }
            let zn = z + p.noise_k * z * z * g;
            if !(zn.is_finite() && zn > 0.0) {
                continue;
            }
            let zq = if p.disparity_subpixel > 0 && fb > 0.0 {
                let s = p.disparity_subpixel as f64;
                // Guard: zn > 0 above; s > 0 here.
                let dq = (fb / zn * s).round() / s;
                if dq <= 0.0 {
                    continue;
                }
                fb / dq
            } else {
                zn
            };
            if zq < p.min_depth_m || zq > p.max_depth_m {
                continue;
            }
            *o = zq as f32;
        }
    });
    image(w, h, out)
}

depthgraph_graph::ports! {
    /// Inputs of `SimulateKinect`.
    inputs struct KinectIn {
        /// ground-truth depth in metres
        depth: Arc<DepthMap>,
        /// linear color for the dark-surface dropouts
        color: Option<Arc<ColorImage>>,
        /// intrinsics of the depth map
        intrinsics: Intrinsics,
    }
}

depthgraph_graph::ports! {
    /// Outputs of `SimulateKinect`.
    outputs struct KinectOut {
        /// simulated measurement, 0 = no measurement
        depth: DepthMap,
    }
}

fn eval_kinect(
    _: &EvalCtx,
    i: KinectIn,
    p: &KinectParams,
) -> Result<Produced<KinectOut>, NodeError> {
    let depth = simulate_kinect(&i.depth, i.color.as_deref(), &i.intrinsics, p)?;
    Ok(KinectOut { depth }.into())
}

// ---------------------------------------------------------------------------
// Time of flight
// ---------------------------------------------------------------------------

node_params! {
    /// Parameters of the `SimulateToF` node.
    pub struct ToFParams {
        /// Width of the ToF image in pixels.
        pub width: usize = 160usize, ParamKind::Int { min: 1, max: 8192 };
        /// Height of the ToF image in pixels.
        pub height: usize = 120usize, ParamKind::Int { min: 1, max: 8192 };
        /// A footprint whose depth range exceeds this fraction of its mean
        /// depth mixes surfaces: its pixel becomes a flying pixel.
        pub edge_threshold_rel: f64 = 0.05, ParamKind::Float { min: 0.0, max: 100.0 };
        /// Modulation frequency in MHz; sets how surfaces of a mixed
        /// footprint combine (phasor sum) and the unambiguous range c / 2f.
        pub modulation_mhz: f64 = 20.0, ParamKind::Float { min: 0.1, max: 10000.0 };
        /// Constant part of the noise standard deviation, metres.
        pub noise_m: f64 = 0.01, ParamKind::Float { min: 0.0, max: 10.0 };
        /// Part of the noise standard deviation proportional to depth.
        pub noise_rel: f64 = 0.005, ParamKind::Float { min: 0.0, max: 10.0 };
        /// Probability that a pixel is replaced by a uniform random depth in
        /// `[min_depth_m, max_depth_m]`.
        pub outlier_rate: f64 = 0.001, ParamKind::Float { min: 0.0, max: 1.0 };
        /// Measurements nearer than this (metres) are holes.
        pub min_depth_m: f64 = 0.1, ParamKind::Float { min: 0.0, max: 1000.0 };
        /// Measurements farther than this (metres) are holes.
        pub max_depth_m: f64 = 7.0, ParamKind::Float { min: 0.0, max: 1000.0 };
        /// Seed of the noise and the outliers.
        pub seed: u64 = 0u64, ParamKind::Int { min: 0, max: i64::MAX };
    }
}

/// High-resolution pixels `[start, end)` of footprint `i` when `n_hi` pixels
/// are integrated into `n_lo`: those whose centre falls in the low-resolution
/// pixel, or (upsampling) the one under its centre. Requires `n_lo, n_hi > 0`.
fn footprint(i: usize, n_lo: usize, n_hi: usize) -> (usize, usize) {
    // (x + 0.5) * n_lo / n_hi >= i  <=>  x >= (2 i n_hi - n_lo) / (2 n_lo).
    let bound = |i: usize| -> usize {
        let num = 2 * i as i128 * n_hi as i128 - n_lo as i128;
        let den = 2 * n_lo as i128; // > 0: the guard of the divisions below
        let c = if num <= 0 {
            -((-num) / den)
        } else {
            (num + den - 1) / den
        };
        c.clamp(0, n_hi as i128) as usize
    };
    let (start, end) = (bound(i), bound(i + 1));
    if end > start {
        (start, end)
    } else {
        let c = ((2 * i + 1) * n_hi / (2 * n_lo)).min(n_hi - 1);
        (c, c + 1)
    }
}

/// The noiseless ToF value of one footprint: the mean depth, or for a
/// footprint mixing surfaces, the phase of the summed return signals (each
/// weighted by `1/z^2`, the fall-off of the returned light) converted back
/// to depth. `None` when most of the footprint has no depth or the phasors
/// cancel.
fn integrate(zs: &[f64], n_total: usize, p: &ToFParams, range_m: f64) -> Option<f64> {
    if zs.is_empty() || 2 * (n_total - zs.len()) > n_total {
        return None;
    }
    let n = zs.len() as f64;
    let mean = zs.iter().sum::<f64>() / n; // guard: zs non-empty
    let (lo, hi) = zs.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), z| {
        (lo.min(*z), hi.max(*z))
    });
    if hi - lo <= p.edge_threshold_rel * mean {
        return Some(mean);
    }
    // Flying pixel: phase 2 pi (z - lo) / range for each sample.
    let (mut re, mut im, mut wsum) = (0.0f64, 0.0f64, 0.0f64);
    for z in zs {
        let w = 1.0 / (z * z); // guard: z > 0 (valid samples only)
        let phi = std::f64::consts::TAU * (z - lo) / range_m; // guard: range_m > 0
        re += w * phi.cos();
        im += w * phi.sin();
        wsum += w;
    }
    if re.hypot(im) <= 1e-9 * wsum {
        return None;
    }
    Some(lo + im.atan2(re).rem_euclid(std::f64::consts::TAU) * range_m / std::f64::consts::TAU)
}

/// Simulates a low-resolution time-of-flight camera co-located with the
/// camera of `depth` (metres, 0 = none) and `k`. Returns the `width` x
/// `height` depth and its intrinsics `k.scaled_to(width, height)`.
///
/// Each ToF pixel integrates the ground-truth pixels whose centres fall in
/// it (its footprint):
/// - more than half of them invalid: a hole;
/// - depth range within `edge_threshold_rel * mean`: the mean depth;
/// - otherwise a **flying pixel**: the surfaces' return signals (amplitude
///   `1/z^2`, phase `4 pi f z / c`) add as phasors and the phase of the sum
///   is read back as depth, a value between the surfaces, on none of them;
///
/// then Gaussian noise of standard deviation `noise_m + noise_rel * z` is
/// added, with probability `outlier_rate` the value is replaced by a uniform
/// depth in `[min_depth_m, max_depth_m]`, and values outside that range
/// become holes.
///
/// ```
/// use depthgraph_nodes::sim::sensor::{simulate_tof, ToFParams};
/// use depthgraph_nodes::sim::synthetic::kinect_like_intrinsics;
/// use depthgraph_graph::value::DepthMap;
/// let k = kinect_like_intrinsics(64, 48);
/// let gt = DepthMap::filled(64, 48, 2.0);
/// let p = ToFParams { width: 16, height: 12, noise_m: 0.0, noise_rel: 0.0, outlier_rate: 0.0, ..Default::default() };
/// let (d, k_tof) = simulate_tof(&gt, &k, &p).unwrap();
/// assert_eq!(d.dims(), (16, 12));
/// assert_eq!(k_tof.fx, k.fx / 4.0);
/// assert_eq!(*d.get(3, 3), 2.0);
/// ```
pub fn simulate_tof(
    depth: &DepthMap,
    k: &Intrinsics,
    p: &ToFParams,
) -> Result<(DepthMap, Intrinsics), NodeError> {
    fits_intrinsics("intrinsics", k, "depth map", depth.dims())?;
    let (lw, lh) = (p.width, p.height);
    if lw == 0 || lh == 0 {
        return Err(NodeError::param(
            "width",
            "the ToF image needs at least one pixel",
        ));
    }
    if !(p.modulation_mhz.is_finite() && p.modulation_mhz > 0.0) {
        return Err(NodeError::param("modulation_mhz", "must be positive"));
    }
    let k_lo = k.scaled_to(lw, lh);
    let (w, h) = depth.dims();
    let mut out = vec![0.0f32; lw * lh];
    if w == 0 || h == 0 {
        return Ok((image(lw, lh, out)?, k_lo));
    }
    // Unambiguous range c / 2f; positive (checked above).
    let range_m = SPEED_OF_LIGHT / (2.0 * p.modulation_mhz * 1e6);
    let xs: Vec<(usize, usize)> = (0..lw).map(|i| footprint(i, lw, w)).collect();
    out.par_chunks_mut(lw).enumerate().for_each(|(j, row_out)| {
        let (y0, y1) = footprint(j, lh, h);
        let mut zs = Vec::new();
        for (i, o) in row_out.iter_mut().enumerate() {
            let (x0, x1) = xs[i];
            zs.clear();
            for y in y0..y1 {
                zs.extend(
                    depth.row(y)[x0..x1]
                        .iter()
                        .filter(|z| DepthMap::is_valid(**z))
                        .map(|z| *z as f64),
                );
            }
            let mut rng = SplitMix64::for_pixel(p.seed, STREAM_TOF, i as u64, j as u64);
            let g = rng.gaussian();
            let u_outlier = rng.uniform();
            let u_value = rng.uniform();
            *o = 0.0;
            let Some(z) = integrate(&zs, (x1 - x0) * (y1 - y0), p, range_m) else {
                continue;
            };
            let mut z = z + (p.noise_m + p.noise_rel * z) * g;
            if u_outlier < p.outlier_rate {
                z = p.min_depth_m + u_value * (p.max_depth_m - p.min_depth_m).max(0.0);
            }
            if z.is_finite() && z > 0.0 && z >= p.min_depth_m && z <= p.max_depth_m {
                *o = z as f32;
            }
        }
    });
    Ok((image(lw, lh, out)?, k_lo))
}

depthgraph_graph::ports! {
    /// Inputs of `SimulateToF`.
    inputs struct ToFIn {
        /// ground-truth depth in metres
        depth: Arc<DepthMap>,
        /// intrinsics of the depth map
        intrinsics: Intrinsics,
    }
}

depthgraph_graph::ports! {
    /// Outputs of `SimulateToF`.
    outputs struct ToFOut {
        /// low-resolution measurement, 0 = no measurement
        depth: DepthMap,
        /// intrinsics of the low-resolution image
        intrinsics: Intrinsics,
    }
}

fn eval_tof(_: &EvalCtx, i: ToFIn, p: &ToFParams) -> Result<Produced<ToFOut>, NodeError> {
    let (depth, intrinsics) = simulate_tof(&i.depth, &i.intrinsics, p)?;
    Ok(ToFOut { depth, intrinsics }.into())
}

// ---------------------------------------------------------------------------
// Exposure brackets
// ---------------------------------------------------------------------------

node_params! {
    /// Parameters of the `SimulateBracket` node.
    pub struct BracketParams {
        /// Exposure of each image in stops relative to `base_time_s`
        /// (time = base_time_s * 2^stop), in this order.
        pub stops: Vec<f64> = vec![-2.0, 0.0, 2.0], ParamKind::Floats { min: -30.0, max: 30.0 };
        /// Exposure time of stop 0 in seconds; the sensor saturates at
        /// radiance * time = 1.
        pub base_time_s: f64 = 0.5, ParamKind::Float { min: 1e-9, max: 1e4 };
        /// Gamma of the response curve (see `response`); 1 = linear.
        pub gamma: f64 = 2.2, ParamKind::Float { min: 1.0, max: 5.0 };
        /// Standard deviation of Gaussian noise added to the linear exposure
        /// before the response, as a fraction of saturation.
        pub noise_sigma: f64 = 0.002, ParamKind::Float { min: 0.0, max: 1.0 };
        /// Bits per channel of the stored values (8 = 256 levels).
        pub bits: u32 = 8u32, ParamKind::Int { min: 1, max: 16 };
        /// Seed of the noise.
        pub seed: u64 = 0u64, ParamKind::Int { min: 0, max: i64::MAX };
        /// A handheld bracket: the translation of each exposure in whole pixels, as pairs
        /// [dx0, dy0, dx1, dy1, ...] (one pair per stop); exposure j shows the radiance at
        /// (x - dx, y - dy), the border repeated. Empty: a tripod.
        pub shift_px: Vec<f64> = Vec::<f64>::new(), ParamKind::Floats { min: -4096.0, max: 4096.0 };
    }
}

/// Simulates LDR exposure brackets of the linear HDR `radiance`: for each
/// stop, with time `t = base_time_s * 2^stop`, each channel is
/// `quantise(response(radiance * t + noise))`: exposure above 1 saturates to
/// exactly 1.0, values are rounded to `2^bits - 1` levels. Negative or NaN
/// radiance counts as 0.
///
/// ```
/// use depthgraph_nodes::sim::sensor::{simulate_bracket, BracketParams};
/// use depthgraph_graph::value::ColorImage;
/// let hdr = ColorImage::filled(4, 4, [0.5, 1.0, 8.0]);
/// let p = BracketParams { noise_sigma: 0.0, ..Default::default() };
/// let stack = simulate_bracket(&hdr, &p).unwrap();
/// assert_eq!(stack.times_s, vec![0.125, 0.5, 2.0]);
/// assert_eq!(stack.images[2].get(0, 0)[2], 1.0); // 8 * 2 s saturates
/// ```
pub fn simulate_bracket(
    radiance: &ColorImage,
    p: &BracketParams,
) -> Result<ExposureStack, NodeError> {
    if p.stops.is_empty() {
        return Err(NodeError::param("stops", "needs at least one exposure"));
    }
    if !(p.base_time_s.is_finite() && p.base_time_s > 0.0) {
        return Err(NodeError::param("base_time_s", "must be positive"));
    }
    let (w, h) = radiance.dims();
    let shifts = bracket_shifts(p)?;
    let levels = ((1u64 << p.bits.clamp(1, 16)) - 1) as f64;
    let curve = Curve::new(p.gamma);
    let mut stack = ExposureStack::default();
    for (i, stop) in p.stops.iter().enumerate() {
        let t = p.base_time_s * stop.exp2();
        if !(t.is_finite() && t > 0.0) {
            return Err(NodeError::param(
                "stops",
                format!("stop {stop} gives no usable exposure time"),
            ));
        }
        let mut data = vec![[0.0f32; 3]; w * h];
        if w > 0 {
            data.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
                for (x, px) in row.iter_mut().enumerate() {
                    let mut rng = SplitMix64::for_pixel(
                        p.seed,
                        STREAM_BRACKET + i as u64,
                        x as u64,
                        y as u64,
                    );
                    let (dx, dy) = shifts[i];
                    let sx = (x as i64 - dx).clamp(0, w as i64 - 1) as usize;
                    let sy = (y as i64 - dy).clamp(0, h as i64 - 1) as usize;
                    for (out, &l) in px.iter_mut().zip(radiance.get(sx, sy)) {
                        let g = rng.gaussian();
                        let r = l as f64;
                        let r = if r.is_nan() || r < 0.0 { 0.0 } else { r };
                        let e = (r * t + p.noise_sigma * g).clamp(0.0, 1.0);
                        let v = curve.apply(e);
                        // Guard: levels >= 1.
                        *out = ((v * levels).round() / levels) as f32;
                    }
                }
            });
        }
        stack.images.push(image(w, h, data)?);
        stack.times_s.push(t);
    }
    Ok(stack)
}

/// The translation of each exposure (`shift_px` as whole-pixel pairs; all
/// zero when empty).
fn bracket_shifts(p: &BracketParams) -> Result<Vec<(i64, i64)>, NodeError> {
    if p.shift_px.is_empty() {
        return Ok(vec![(0, 0); p.stops.len()]);
    }
    if p.shift_px.len() != 2 * p.stops.len() {
        return Err(NodeError::param(
            "shift_px",
            format!(
                "holds {} numbers for {} stops; expected one pair (dx, dy) per stop",
                p.shift_px.len(),
                p.stops.len()
            ),
        ));
    }
    p.shift_px
        .chunks(2)
        .map(|d| {
            let ok = |v: f64| v.is_finite() && v.fract() == 0.0 && v.abs() <= 4096.0;
            if ok(d[0]) && ok(d[1]) {
                Ok((d[0] as i64, d[1] as i64))
            } else {
                Err(NodeError::param(
                    "shift_px",
                    format!(
                        "({}, {}) is not a whole-pixel shift within 4096",
                        d[0], d[1]
                    ),
                ))
            }
        })
        .collect()
}

depthgraph_graph::ports! {
    /// Inputs of `SimulateBracket`.
    inputs struct BracketIn {
        /// linear HDR radiance
        radiance: Arc<ColorImage>,
    }
}

depthgraph_graph::ports! {
    /// Outputs of `SimulateBracket`.
    outputs struct BracketOut {
        /// the exposures and their times
        exposures: ExposureStack,
    }
}

fn eval_bracket(
    _: &EvalCtx,
    i: BracketIn,
    p: &BracketParams,
) -> Result<Produced<BracketOut>, NodeError> {
    Ok(BracketOut {
        exposures: simulate_bracket(&i.radiance, p)?,
    }
    .into())
}

/// Registers `SimulateKinect`, `SimulateToF` and `SimulateBracket`.
pub fn register(reg: &mut Registry) -> Result<(), depthgraph_graph::registry::RegistryError> {
    reg.register(PortedNode::new(
        "SimulateKinect",
        1,
        "Structured-light (Kinect v1) defects on a ground-truth depth map.\n\
         Projector shadows beside depth edges, dropouts on dark surfaces and at grazing angles, \
         noise growing with z^2, disparity quantisation and a working range; holes are 0.",
        eval_kinect,
    ))?;
    reg.register(PortedNode::new(
        "SimulateToF",
        1,
        "Low-resolution time-of-flight camera with flying pixels, noise and outliers.\n\
         Integrates footprints of the ground-truth depth; footprints mixing surfaces give phasor-mixed \
         flying pixels.",
        eval_tof,
    ))?;
    reg.register(PortedNode::new(
        "SimulateBracket",
        1,
        "LDR exposure brackets of a linear HDR image through a camera response curve.\n\
         Exposure times base_time_s * 2^stop, clipping at saturation, noise and quantisation.",
        eval_bracket,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::synthetic::{RenderOptions, Scene, kinect_like_intrinsics, render};

    fn quiet_kinect() -> KinectParams {
        KinectParams {
            dropouts: false,
            noise_k: 0.0,
            disparity_subpixel: 0,
            ..Default::default()
        }
    }

    fn holes(d: &DepthMap, x: usize, y: usize) -> bool {
        !DepthMap::is_valid(*d.get(x, y))
    }

    /// A wall at 2 m with a box at 1 m covering `x in [40, 60), y in [16, 48)`.
    fn box_in_front_of_wall() -> (DepthMap, Intrinsics) {
        let k = Intrinsics {
            fx: 80.0,
            fy: 80.0,
            cx: 48.0,
            cy: 32.0,
            width: 96,
            height: 64,
        };
        let d = DepthMap::from_fn(96, 64, |x, y| {
            if (40..60).contains(&x) && (16..48).contains(&y) {
                1.0
            } else {
                2.0
            }
        });
        (d, k)
    }

    #[test]
    fn projector_shadow_band_lies_left_of_the_near_object() {
        // Projector at +x: a far point at pixel u is hidden when a near point
        // maps to the same projector column, u - fb/z_far = u' - fb/z_near, so
        // u = u' - fb (1/z_near - 1/z_far) < u': the band is on the left, of
        // width 80 * 0.15 * (1 - 1/2) = 6 px, i.e. x in [34, 40).
        let (gt, k) = box_in_front_of_wall();
        let p = KinectParams {
            baseline_m: 0.15,
            ..quiet_kinect()
        };
        let d = simulate_kinect(&gt, None, &k, &p).unwrap();
        for y in 0..64 {
            for x in 0..96 {
                let expected_hole = (16..48).contains(&y) && (34..40).contains(&x);
                assert_eq!(holes(&d, x, y), expected_hole, "pixel ({x}, {y})");
                if !expected_hole {
                    assert_eq!(d.get(x, y), gt.get(x, y));
                }
            }
        }
        // Without shadows there are no holes at all.
        let no_shadow = KinectParams {
            shadows: false,
            ..p
        };
        assert_eq!(
            simulate_kinect(&gt, None, &k, &no_shadow)
                .unwrap()
                .hole_count(),
            0
        );
    }

    #[test]
    fn shadows_on_the_synthetic_tabletop_appear_left_of_objects() {
        let scene = Scene::preset("tabletop", 160, 120).unwrap();
        let gt = render(&scene, &RenderOptions::default());
        let d = simulate_kinect(&gt.depth, None, &gt.intrinsics, &quiet_kinect()).unwrap();
        assert!(d.hole_count() > 20, "{}", d.hole_count());
        // Every hole has a nearer surface within the band width to its right
        // (max band: fx b / z_near = 131.25 * 0.075 / 0.85 ~ 11.6 px).
        for y in 0..120 {
            for x in 0..160 {
                if holes(&d, x, y) {
                    let z = *gt.depth.get(x, y);
                    let nearer = (x + 1..(x + 13).min(160))
                        .any(|x2| *gt.depth.get(x2, y) as f64 * 1.01 < z as f64 + 1e-6);
                    assert!(
                        nearer,
                        "hole at ({x}, {y}) without an occluder to its right"
                    );
                }
            }
        }
    }

    #[test]
    fn flat_plane_has_no_holes_without_dropouts_and_noise_follows_k_z2() {
        let k = kinect_like_intrinsics(64, 48);
        let gt = DepthMap::filled(64, 48, 2.0);
        let p = KinectParams {
            disparity_subpixel: 0,
            ..Default::default()
        };
        let d = simulate_kinect(&gt, None, &k, &p).unwrap();
        assert_eq!(d.hole_count(), 0);
        let n = d.len() as f64;
        let mean = d.as_slice().iter().map(|z| *z as f64).sum::<f64>() / n;
        let var = d
            .as_slice()
            .iter()
            .map(|z| (*z as f64 - mean).powi(2))
            .sum::<f64>()
            / (n - 1.0);
        let expected = 1.5e-3 * 2.0 * 2.0;
        assert!(
            (var.sqrt() / expected - 1.0).abs() < 0.2,
            "std {} vs {expected}",
            var.sqrt()
        );
        assert!(
            (mean - 2.0).abs() < 3.0 * expected / n.sqrt() * 2.0,
            "mean {mean}"
        );
    }

    #[test]
    fn quantised_depths_lie_on_the_disparity_lattice() {
        let k = kinect_like_intrinsics(64, 48);
        let gt = DepthMap::filled(64, 48, 3.0);
        let d = simulate_kinect(&gt, None, &k, &KinectParams::default()).unwrap();
        let fb = k.fx * 0.075;
        let mut distinct: Vec<u32> = Vec::new();
        for z in d.as_slice().iter().filter(|z| **z > 0.0) {
            let q = fb / *z as f64 * 8.0;
            assert!(
                (q - q.round()).abs() < 1e-3,
                "disparity {q} / 8 is off the lattice"
            );
            distinct.push(q.round() as u32);
        }
        distinct.sort_unstable();
        distinct.dedup();
        // Noise of 13.5 mm at 3 m against steps of ~0.29 m: few levels.
        assert!(!distinct.is_empty() && distinct.len() <= 4, "{distinct:?}");
    }

    #[test]
    fn dark_surfaces_drop_out_with_the_given_probability() {
        let k = kinect_like_intrinsics(64, 48);
        let gt = DepthMap::filled(64, 48, 2.0);
        let color = ColorImage::from_fn(64, 48, |x, _| if x < 32 { [0.005; 3] } else { [0.5; 3] });
        let p = KinectParams {
            dark_dropout_prob: 0.5,
            ..quiet_kinect()
        };
        let p = KinectParams {
            dropouts: true,
            ..p
        };
        let d = simulate_kinect(&gt, Some(&color), &k, &p).unwrap();
        let left = (0..48)
            .flat_map(|y| (0..32).map(move |x| (x, y)))
            .filter(|(x, y)| holes(&d, *x, *y))
            .count();
        let right = (0..48)
            .flat_map(|y| (32..64).map(move |x| (x, y)))
            .filter(|(x, y)| holes(&d, *x, *y))
            .count();
        let frac = left as f64 / (32.0 * 48.0);
        assert!((0.4..0.6).contains(&frac), "{frac}");
        assert_eq!(right, 0);
        let always = KinectParams {
            dark_dropout_prob: 1.0,
            ..p
        };
        assert_eq!(
            simulate_kinect(&gt, Some(&color), &k, &always)
                .unwrap()
                .hole_count(),
            32 * 48
        );
    }

    #[test]
    fn grazing_surfaces_drop_out_beyond_the_threshold_angle() {
        // A plane through (0, 0, 2) turned 80 degrees about y: the angle to
        // the viewing ray varies from ~55 to ~87 degrees across the image.
        let k = kinect_like_intrinsics(64, 48);
        let a = 80f64.to_radians();
        let n = DVec3::new(a.sin(), 0.0, -a.cos());
        let p0 = DVec3::new(0.0, 0.0, 2.0);
        let ray = |x: usize, y: usize| {
            DVec3::new(
                (x as f64 + 0.5 - k.cx) / k.fx,
                (y as f64 + 0.5 - k.cy) / k.fy,
                1.0,
            )
        };
        let gt = DepthMap::from_fn(64, 48, |x, y| {
            let t = n.dot(p0) / n.dot(ray(x, y));
            if t > 0.5 && t < 7.0 { t as f32 } else { 0.0 }
        });
        let p = KinectParams {
            dropouts: true,
            shadows: false,
            grazing_deg: 75.0,
            ..quiet_kinect()
        };
        let d = simulate_kinect(&gt, None, &k, &p).unwrap();
        let (mut dropped, mut kept) = (0, 0);
        for y in 0..48 {
            for x in 0..64 {
                if !DepthMap::is_valid(*gt.get(x, y)) {
                    continue;
                }
                let r = ray(x, y);
                let angle = (n.dot(r).abs() / r.length()).acos().to_degrees();
                if angle > 76.0 {
                    assert!(holes(&d, x, y), "({x}, {y}) at {angle} deg kept");
                    dropped += 1;
                } else if angle < 74.0 {
                    assert!(!holes(&d, x, y), "({x}, {y}) at {angle} deg dropped");
                    kept += 1;
                }
            }
        }
        assert!(dropped > 100 && kept > 100, "{dropped} {kept}");
        // A fronto-parallel step edge is not grazing (edge-aware normals).
        let (gt, k) = box_in_front_of_wall();
        let p = KinectParams {
            shadows: false,
            ..p
        };
        assert_eq!(simulate_kinect(&gt, None, &k, &p).unwrap().hole_count(), 0);
    }

    #[test]
    fn working_range_cuts_near_and_far() {
        let k = kinect_like_intrinsics(16, 12);
        for (z, expect_holes) in [(0.3f32, 16 * 12), (9.0, 16 * 12), (2.0, 0)] {
            let d =
                simulate_kinect(&DepthMap::filled(16, 12, z), None, &k, &quiet_kinect()).unwrap();
            assert_eq!(d.hole_count(), expect_holes, "z = {z}");
        }
    }

    #[test]
    fn kinect_is_deterministic_per_seed_and_thread_count() {
        let scene = Scene::preset("tabletop", 64, 48).unwrap();
        let gt = render(&scene, &RenderOptions::default());
        let p = KinectParams::default();
        let run = |seed: u64, threads: usize| {
            let p = KinectParams { seed, ..p.clone() };
            crate::test_support::with_threads(threads, || {
                simulate_kinect(&gt.depth, Some(&gt.color), &gt.intrinsics, &p).unwrap()
            })
        };
        let a = run(7, 1);
        assert_eq!(a, run(7, 3));
        assert_ne!(a, run(8, 2));
        assert!(a.as_slice().iter().all(|z| z.is_finite() && *z >= 0.0));
        // Valid measurements stay close to the truth (quantisation steps at
        // 2.8 m and 64 px are ~0.25 m).
        for (m, t) in a.as_slice().iter().zip(gt.depth.as_slice()) {
            if *m > 0.0 {
                assert!((m - t).abs() < 0.2 * t, "{m} vs {t}");
            }
        }
    }

    #[test]
    fn kinect_rejects_mismatched_inputs() {
        let k = kinect_like_intrinsics(16, 12);
        let gt = DepthMap::filled(16, 12, 2.0);
        let small = ColorImage::filled(8, 6, [0.5; 3]);
        let p = KinectParams::default();
        assert!(matches!(
            simulate_kinect(&gt, Some(&small), &k, &p),
            Err(NodeError::Input { .. })
        ));
        let other = kinect_like_intrinsics(32, 24);
        assert!(matches!(
            simulate_kinect(&gt, None, &other, &p),
            Err(NodeError::Input { .. })
        ));
        let empty = Intrinsics {
            width: 0,
            height: 0,
            ..k
        };
        let d = simulate_kinect(&DepthMap::filled(0, 0, 0.0), None, &empty, &p).unwrap();
        assert!(d.is_empty());
    }

    fn quiet_tof() -> ToFParams {
        ToFParams {
            noise_m: 0.0,
            noise_rel: 0.0,
            outlier_rate: 0.0,
            ..Default::default()
        }
    }

    /// 640x480 ground truth: 1 m left of column 322, 3 m from it on.
    fn step_edge() -> (DepthMap, Intrinsics) {
        let d = DepthMap::from_fn(640, 480, |x, _| if x < 322 { 1.0 } else { 3.0 });
        (d, kinect_like_intrinsics(640, 480))
    }

    #[test]
    fn tof_has_the_requested_size_and_scaled_intrinsics() {
        let (gt, k) = step_edge();
        let (d, kl) = simulate_tof(&gt, &k, &ToFParams::default()).unwrap();
        assert_eq!(d.dims(), (160, 120));
        assert_eq!((kl.width, kl.height), (160, 120));
        assert!((kl.fx - 131.25).abs() < 1e-12 && (kl.cx - 80.0).abs() < 1e-12);
        assert!(d.as_slice().iter().all(|z| z.is_finite()));
        // Footprints partition the high-resolution image.
        for (lo, hi) in [(160, 640), (7, 50), (50, 7), (3, 3)] {
            let mut next = 0;
            for i in 0..lo {
                let (s, e) = footprint(i, lo, hi);
                assert!(e > s && e <= hi);
                if lo <= hi {
                    assert_eq!(s, next, "{lo} {hi}");
                    next = e;
                }
            }
            if lo <= hi {
                assert_eq!(next, hi);
            }
        }
    }

    #[test]
    fn tof_makes_flying_pixels_at_depth_edges_only() {
        let (gt, k) = step_edge();
        let (d, _) = simulate_tof(&gt, &k, &quiet_tof()).unwrap();
        for y in 0..120 {
            for x in 0..160 {
                let z = *d.get(x, y);
                if x == 80 {
                    // Footprint 320..324 holds two pixels of each surface.
                    assert!(z > 1.05 && z < 2.95, "({x}, {y}): {z} is on a surface");
                } else {
                    assert_eq!(z, if x < 80 { 1.0 } else { 3.0 }, "({x}, {y})");
                }
            }
        }
        // The 1/z^2 weighting pulls the mix towards the near surface.
        assert!(*d.get(80, 0) < 2.0);
    }

    #[test]
    fn tof_noise_on_flat_regions_stays_within_three_sigma() {
        let k = kinect_like_intrinsics(640, 480);
        let gt = DepthMap::filled(640, 480, 2.5);
        let p = ToFParams {
            outlier_rate: 0.0,
            ..Default::default()
        };
        let (d, _) = simulate_tof(&gt, &k, &p).unwrap();
        let sigma = p.noise_m + p.noise_rel * 2.5;
        let errs: Vec<f64> = d.as_slice().iter().map(|z| *z as f64 - 2.5).collect();
        let within =
            errs.iter().filter(|e| e.abs() <= 3.0 * sigma).count() as f64 / errs.len() as f64;
        assert!(within >= 0.99, "{within}");
        assert!(errs.iter().all(|e| e.abs() <= 5.0 * sigma));
        let std = (errs.iter().map(|e| e * e).sum::<f64>() / errs.len() as f64).sqrt();
        assert!((std / sigma - 1.0).abs() < 0.1, "std {std} vs {sigma}");
    }

    #[test]
    fn tof_outliers_and_holes() {
        let k = kinect_like_intrinsics(640, 480);
        // Left quarter without depth; one invalid pixel in footprint (100, 50).
        let mut gt = DepthMap::from_fn(640, 480, |x, _| if x < 160 { 0.0 } else { 2.0 });
        *gt.get_mut(401, 202) = 0.0;
        let (d, _) = simulate_tof(&gt, &k, &quiet_tof()).unwrap();
        for y in 0..120 {
            for x in 0..160 {
                assert_eq!(*d.get(x, y), if x < 40 { 0.0 } else { 2.0 }, "({x}, {y})");
            }
        }
        let p = ToFParams {
            outlier_rate: 0.1,
            ..quiet_tof()
        };
        let (d, _) = simulate_tof(&gt, &k, &p).unwrap();
        let valid: Vec<f32> = (0..120)
            .flat_map(|y| (40..160).map(move |x| (x, y)))
            .map(|(x, y)| *d.get(x, y))
            .collect();
        let off =
            valid.iter().filter(|z| (**z - 2.0).abs() > 0.05).count() as f64 / valid.len() as f64;
        // 10% outliers, of which ~1.4% land within 5 cm of the truth.
        assert!((0.08..0.12).contains(&off), "{off}");
        assert!(valid.iter().all(|z| *z == 0.0 || (0.1..=7.0).contains(z)));
    }

    #[test]
    fn tof_is_deterministic_per_seed() {
        let (gt, k) = step_edge();
        let p = ToFParams::default();
        let a = simulate_tof(&gt, &k, &p).unwrap();
        assert_eq!(a, simulate_tof(&gt, &k, &p).unwrap());
        let b = simulate_tof(&gt, &k, &ToFParams { seed: 1, ..p }).unwrap();
        assert_ne!(a.0, b.0);
    }

    /// Radiances from deep shadow to far above saturation.
    fn hdr_ramp() -> ColorImage {
        ColorImage::from_fn(64, 48, |x, y| {
            let r = 0.01 * 1.12f32.powi((x + 64 * y) as i32 % 60);
            [r, r * 0.5, r * 2.0]
        })
    }

    #[test]
    fn brackets_are_monotone_clip_to_one_and_invert_on_mid_tones() {
        let hdr = hdr_ramp();
        let p = BracketParams {
            noise_sigma: 0.0,
            ..Default::default()
        };
        let stack = simulate_bracket(&hdr, &p).unwrap();
        assert_eq!(stack.times_s, vec![0.125, 0.5, 2.0]);
        let q = 1.0 / 255.0;
        let curve = Curve::new(p.gamma);
        let mut mid = 0;
        for (img, t) in stack.images.iter().zip(&stack.times_s) {
            for (v, l) in img.as_slice().iter().zip(hdr.as_slice()) {
                for c in 0..3 {
                    let x = l[c] as f64 * t;
                    let v = v[c];
                    assert!(
                        ((v as f64 / q) - (v as f64 / q).round()).abs() < 1e-3,
                        "not quantised"
                    );
                    if x >= 1.0 {
                        assert_eq!(v, 1.0, "saturation must clip to exactly 1");
                    }
                    if (0.1..=0.9).contains(&v) {
                        mid += 1;
                        // The true exposure lies in the inverse image of the
                        // quantisation bin.
                        let lo = curve.invert(v as f64 - q / 2.0) - 1e-6;
                        let hi = curve.invert(v as f64 + q / 2.0) + 1e-6;
                        assert!(lo <= x && x <= hi, "{x} not in [{lo}, {hi}]");
                    }
                }
            }
        }
        assert!(mid > 1000, "{mid}");
        // Longer exposures never give darker pixels, and some are brighter.
        let mut brighter = 0;
        for w in stack.images.windows(2) {
            for (a, b) in w[0].as_slice().iter().zip(w[1].as_slice()) {
                for c in 0..3 {
                    assert!(b[c] >= a[c]);
                    brighter += (b[c] > a[c]) as usize;
                }
            }
        }
        assert!(brighter > 1000);
    }

    #[test]
    fn bracket_noise_is_seeded_and_bounded() {
        let hdr = hdr_ramp();
        let p = BracketParams::default();
        let a = simulate_bracket(&hdr, &p).unwrap();
        assert_eq!(a, simulate_bracket(&hdr, &p).unwrap());
        let b = simulate_bracket(
            &hdr,
            &BracketParams {
                seed: 3,
                ..p.clone()
            },
        )
        .unwrap();
        assert_ne!(a, b);
        assert!(a.images.iter().all(|i| {
            i.as_slice()
                .iter()
                .flatten()
                .all(|v| (0.0..=1.0).contains(v))
        }));
        let p16 = BracketParams {
            bits: 16,
            stops: vec![1.0],
            ..p.clone()
        };
        let s = simulate_bracket(&hdr, &p16).unwrap();
        assert_eq!(s.images.len(), 1);
        assert!(matches!(
            simulate_bracket(&hdr, &BracketParams { stops: vec![], ..p }),
            Err(NodeError::Param { .. })
        ));
    }

    #[test]
    fn nodes_produce_their_declared_types() {
        let mut reg = Registry::new();
        register(&mut reg).unwrap();
        let scene = Scene::preset("tabletop", 32, 24).unwrap();
        let gt = render(&scene, &RenderOptions::default());
        let mut inputs = Inputs::new();
        inputs.insert("depth", gt.depth.clone().into());
        inputs.insert("color", gt.color.clone().into());
        inputs.insert("intrinsics", gt.intrinsics.into());
        inputs.insert("radiance", gt.color.clone().into());
        let test_ctx = crate::test_support::TestCtx::new("n");
        let ctx = test_ctx.ctx();
        for kind in ["SimulateKinect", "SimulateToF", "SimulateBracket"] {
            let node = reg.get(kind).unwrap();
            let params = node.schema().default_params();
            for spec in &node.schema().params {
                spec.kind.validate(&spec.default).unwrap();
            }
            let out = node.eval(&ctx, &inputs, &params).unwrap();
            for port in &node.schema().outputs {
                assert_eq!(
                    out.values[port.name].value_type(),
                    port.ty,
                    "{kind}.{}",
                    port.name
                );
            }
        }
    }
}
