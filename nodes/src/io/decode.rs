//! What every reader shares: the size limits checked before decoding, the
//! decode error, and the sRGB-to-linear tables of 8- and 16-bit codes.

use std::fs;
use std::path::Path;
use std::sync::OnceLock;

use depthgraph_graph::prelude::*;

use crate::kit::color::srgb_to_linear;

/// Largest accepted image side in pixels.
pub const MAX_SIDE: usize = 1 << 15;
/// Default largest accepted pixel count (256 MP); a run sets its own with
/// `--max-pixels` ([`Limits`]).
pub const MAX_PIXELS: usize = depthgraph_graph::node::DEFAULT_MAX_PIXELS;

/// What a reader accepts, checked against a file's header before anything
/// is allocated for its pixels.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// The most pixels of one image (width x height; each side is also at
    /// most [`MAX_SIDE`]).
    pub max_pixels: usize,
}

impl Default for Limits {
    fn default() -> Self {
        Self {
            max_pixels: MAX_PIXELS,
        }
    }
}

impl Limits {
    /// The limits of a node's run (`--max-pixels`).
    pub fn of(ctx: &EvalCtx) -> Self {
        Self {
            max_pixels: ctx.max_pixels,
        }
    }
}

/// The bytes of `path`; an error naming the file when it cannot be read.
pub(super) fn read_file(path: &Path) -> Result<Vec<u8>, NodeError> {
    fs::read(path).map_err(|error| NodeError::read(path, error))
}

/// A decoding error of `path`.
pub(super) fn decode_err(path: &Path, message: impl Into<String>) -> NodeError {
    NodeError::Decode {
        path: path.to_path_buf(),
        message: message.into(),
    }
}

/// Refuses an empty or oversized image before anything is allocated for it.
pub(super) fn check_dims(path: &Path, w: usize, h: usize, lim: &Limits) -> Result<(), NodeError> {
    if w == 0 || h == 0 {
        return Err(decode_err(
            path,
            format!("image is {w}x{h}; expected at least 1x1"),
        ));
    }
    if w > MAX_SIDE || h > MAX_SIDE || w.saturating_mul(h) > lim.max_pixels {
        return Err(decode_err(
            path,
            format!(
                "image is {w}x{h}; the limit is {MAX_SIDE} per side and {} pixels (--max-pixels)",
                lim.max_pixels
            ),
        ));
    }
    Ok(())
}

/// sRGB code to linear, for every 8-bit code (computed once: a constant table).
pub(super) fn srgb8_table() -> &'static [f32; 256] {
    static T: OnceLock<[f32; 256]> = OnceLock::new();
    T.get_or_init(|| std::array::from_fn(|i| srgb_to_linear(i as f32 / 255.0)))
}

/// sRGB code to linear, for every 16-bit code (computed once: a constant table).
pub(super) fn srgb16_table() -> &'static [f32] {
    static T: OnceLock<Vec<f32>> = OnceLock::new();
    T.get_or_init(|| {
        (0..65536)
            .map(|i| srgb_to_linear(i as f32 / 65535.0))
            .collect()
    })
}

/// Samples of a single-channel file, row-major, top row first.
#[derive(Debug, Clone, PartialEq)]
pub struct Samples {
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
    /// The `width * height` stored values as read, before any scale or unit
    /// conversion.
    pub values: Vec<f32>,
}
