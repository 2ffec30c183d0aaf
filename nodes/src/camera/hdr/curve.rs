//! Response curves `g = ln f^-1` on 256 levels, the hat weighting of eq. 4
//! and the checks every bracket goes through (Debevec & Malik 1997 §2.1).

use depthgraph_graph::prelude::*;

/// Channel names, for errors.
pub(super) const CHANNEL: [&str; 3] = ["red", "green", "blue"];

/// Number of levels of the response curve (8-bit codes).
pub const LEVELS: usize = 256;
/// Highest level, `Z_max` of eq. 4.
pub(super) const Z_MAX: f64 = 255.0;
/// Level fixed by the constraint `g(Z_MID) = 0`.
pub const Z_MID: usize = 128;
/// Top levels of a curve read from an image that may not all be equal
/// ([`ResponseCurve::from_image`]).
pub const FLAT_TOP: usize = 8;

/// The hat weighting of eq. 4 on a real level `z` in `[0, 255]`:
/// `min(z, 255 - z)`, 0 at (and beyond) both ends and for NaN.
///
/// ```
/// use depthgraph_nodes::camera::hdr::hat_weight;
/// assert_eq!(hat_weight(0.0), 0.0);
/// assert_eq!(hat_weight(255.0), 0.0);
/// assert_eq!(hat_weight(100.0), 100.0);
/// assert_eq!(hat_weight(200.0), 55.0);
/// ```
#[inline]
pub fn hat_weight(z: f64) -> f64 {
    if z > 0.0 && z < Z_MAX {
        z.min(Z_MAX - z)
    } else {
        0.0
    }
}

/// Level of a stored value (`value * 255`, clipped to `[0, 255]`), or `None`
/// for a missing (non-finite) value.
#[inline]
pub(super) fn level(v: f32) -> Option<f64> {
    if v.is_finite() {
        Some((v as f64).clamp(0.0, 1.0) * Z_MAX)
    } else {
        None
    }
}

// ---------------------------------------------------------------------------
// Response curves
// ---------------------------------------------------------------------------

/// A camera response as `g(z) = ln f^-1(z)` (eq. 2) on the 256 levels of each
/// channel: the log exposure `ln(E Δt)` that produces level `z`.
#[derive(Debug, Clone, PartialEq)]
pub struct ResponseCurve {
    /// `g[c][z]` for channel `c` (R, G, B) and level `z` in `0..256`.
    pub g: [[f64; LEVELS]; 3],
}

impl ResponseCurve {
    /// A known gamma camera: the inverse of [`crate::camera::response::response`]
    /// (the curve `SimulateBracket` applies), `g(z) = ln f^-1(z / 255)`, so
    /// `g(255) = 0`. A value 0 only says that the exposure was below half a
    /// level, so `g(0) = ln f^-1(0.5 / 255)` (finite, instead of `ln 0`).
    /// `gamma = 1` is [`ResponseCurve::linear`].
    pub fn gamma(gamma: f64) -> Self {
        let g: [f64; LEVELS] = std::array::from_fn(|z| {
            let v = if z == 0 { 0.5 } else { z as f64 } / Z_MAX;
            let x = crate::camera::response::inverse_response(v as f32, gamma as f32) as f64;
            // guard: the inverse of a positive value is positive; the floor only
            // protects the logarithm against a future change of the curve
            x.max(1e-30).ln()
        });
        Self { g: [g; 3] }
    }

    /// A linear camera: `g(z) = ln(z / 255)`, `g(0) = ln(0.5 / 255)`.
    pub fn linear() -> Self {
        Self::gamma(1.0)
    }

    /// `g` of channel `c` at the real level `z` (clipped to `[0, 255]`),
    /// interpolated linearly between levels.
    #[inline]
    pub fn eval(&self, c: usize, z: f64) -> f64 {
        let z = if z.is_nan() { 0.0 } else { z.clamp(0.0, Z_MAX) };
        let i = (z.floor() as usize).min(LEVELS - 2);
        let f = z - i as f64;
        let g = &self.g[c];
        g[i] + (g[i + 1] - g[i]) * f
    }

    /// The curve as a 256x1 Color image: pixel `x = z` holds `exp(g(z))` per
    /// channel, the relative exposure `E Δt` that gives level `z` (1 at
    /// `z = 128` for a recovered curve, 1 at `z = 255` for a given one).
    /// Plot it against `z`, save it with `SaveResponse`, or feed it to another
    /// `HdrMerge`'s `curve` input to merge other brackets of the same camera.
    pub fn to_image(&self) -> ColorImage {
        Image::from_fn(LEVELS, 1, |z, _| {
            std::array::from_fn(|c| (self.g[c][z].exp() as f32).min(f32::MAX))
        })
    }

    /// Reads a curve written by [`ResponseCurve::to_image`]; `port` names the
    /// input in errors. Every value must be finite and positive, and the top
    /// [`FLAT_TOP`] levels must not all be equal (a curve clipped at 1).
    pub fn from_image(img: &ColorImage, port: &str) -> Result<Self, NodeError> {
        if img.dims() != (LEVELS, 1) {
            return Err(NodeError::input(
                port,
                format!(
                    "is {}x{}; expected a 256x1 response curve (exp g(z) per channel, as HdrMerge's `curve` output)",
                    img.width(),
                    img.height()
                ),
            ));
        }
        let mut g = [[0.0; LEVELS]; 3];
        for (z, px) in img.as_slice().iter().enumerate() {
            for (c, v) in px.iter().enumerate() {
                if !(v.is_finite() && *v > 0.0) {
                    return Err(NodeError::input(
                        port,
                        format!("level {z}, channel {c}: {v} is not a positive finite exposure"),
                    ));
                }
                g[c][z] = (*v as f64).ln();
            }
        }
        // A curve's top levels always rise (recovery extends its ends with
        // a positive slope; a gamma rises everywhere). Flat at the top is
        // what a format that clips at 1 leaves (exp g > 1 above level 128):
        // merged with it every highlight would read as one exposure.
        for (c, gc) in g.iter().enumerate() {
            let top = &gc[LEVELS - FLAT_TOP..];
            if top.iter().all(|v| *v == top[0]) {
                return Err(NodeError::input(
                    port,
                    format!(
                        "channel {c}: levels {} to {} all hold {}: the curve was saved in a format that \
                         clips values above 1 (PNG, JPEG, TIFF) and lost its top; save HdrMerge's curve \
                         as EXR or HDR",
                        LEVELS - FLAT_TOP,
                        LEVELS - 1,
                        top[0].exp()
                    ),
                ));
            }
        }
        Ok(Self { g })
    }
}

// ---------------------------------------------------------------------------
// Checks shared by recovery and merge
// ---------------------------------------------------------------------------

/// Checks counts, sizes and times of a stack; returns the image size.
pub(super) fn check_stack(stack: &ExposureStack) -> Result<(usize, usize), NodeError> {
    let n = stack.images.len();
    if n == 0 {
        return Err(NodeError::input("stack", "holds no exposure"));
    }
    if stack.times_s.len() != n {
        return Err(NodeError::input(
            "stack",
            format!(
                "holds {n} images but {} exposure times",
                stack.times_s.len()
            ),
        ));
    }
    let dims = stack.images[0].dims();
    for (j, img) in stack.images.iter().enumerate() {
        if img.dims() != dims {
            return Err(NodeError::input(
                "stack",
                format!(
                    "image {j} is {}x{} but image 0 is {}x{}; every exposure must have the same size",
                    img.width(),
                    img.height(),
                    dims.0,
                    dims.1
                ),
            ));
        }
    }
    for (j, t) in stack.times_s.iter().enumerate() {
        if !(t.is_finite() && *t > 0.0) {
            return Err(NodeError::input(
                "stack",
                format!("exposure time {t} s of image {j} must be finite and positive"),
            ));
        }
    }
    Ok(dims)
}
