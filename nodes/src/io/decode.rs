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

/// Bytes a file may hold per pixel of the budget: four channels of f32
/// (an uncompressed RGBA EXR; PFM holds 12), compressed formats less.
const MAX_FILE_BYTES_PER_PIXEL: u64 = 16;

/// Bytes a file may hold beyond its pixels (headers, metadata, extra
/// channels of a small image).
const FILE_SLACK_BYTES: u64 = 64 << 20;

/// The bytes of `path`; an error naming the file when it cannot be read,
/// is not a regular file (a directory, a FIFO, `/dev/zero`: read whole
/// they never end), or holds more than an image within `lim` can
/// (`MAX_FILE_BYTES_PER_PIXEL` per pixel and `FILE_SLACK_BYTES`), checked
/// before it is read.
pub(super) fn read_file(path: &Path, lim: &Limits) -> Result<Vec<u8>, NodeError> {
    // (looked at before it is opened: opening a FIFO waits for a writer)
    let meta = fs::metadata(path).map_err(|error| NodeError::read(path, error))?;
    if !meta.is_file() {
        return Err(decode_err(path, "not a regular file"));
    }
    let file = fs::File::open(path).map_err(|error| NodeError::read(path, error))?;
    let cap = (lim.max_pixels as u64)
        .saturating_mul(MAX_FILE_BYTES_PER_PIXEL)
        .saturating_add(FILE_SLACK_BYTES);
    if meta.len() > cap {
        return Err(decode_err(
            path,
            format!(
                "{} bytes, more than an image within the pixel budget ({} pixels) holds ({cap} bytes)",
                meta.len(),
                lim.max_pixels
            ),
        ));
    }
    let mut bytes = Vec::with_capacity(meta.len() as usize);
    // (a file that grows meanwhile stops at the cap too)
    std::io::Read::read_to_end(&mut std::io::Read::take(file, cap), &mut bytes)
        .map_err(|error| NodeError::read(path, error))?;
    Ok(bytes)
}

/// Where the samples of a binary PNM/PFM start: `pos`, just after the one
/// whitespace byte the formats put after the header, unless that byte was
/// a `\r` of a `\r\n` line end (a file written on Windows) and the bytes
/// left are the `need` samples plus that `\n`: then one further.
pub(super) fn samples_start(bytes: &[u8], pos: usize, need: usize) -> usize {
    let crlf = pos >= 1
        && bytes.get(pos - 1) == Some(&b'\r')
        && bytes.get(pos) == Some(&b'\n')
        && bytes.len().checked_sub(pos) == need.checked_add(1);
    if crlf { pos + 1 } else { pos }
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
