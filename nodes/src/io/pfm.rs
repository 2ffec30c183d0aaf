//! PFM (portable float map), as Middlebury stores disparity.

use std::path::Path;

use depthgraph_graph::prelude::*;

use super::decode::{Limits, Samples, check_dims, decode_err, read_file, samples_start};

/// Reads a PFM file (grey `Pf`, or `PF` whose first channel is used);
/// rows are stored bottom-up; a negative scale means little-endian.
pub fn read_pfm(path: &Path) -> Result<Samples, NodeError> {
    decode_pfm(
        &read_file(path, &Limits::default())?,
        path,
        &Limits::default(),
    )
}

/// [`read_pfm`] of a file's bytes (`path` names it in errors). The header
/// is checked against `lim` before the samples are allocated; a scale that
/// is zero or not finite is an error (its sign is the byte order, its
/// magnitude a unit nobody could apply).
pub fn decode_pfm(bytes: &[u8], path: &Path, lim: &Limits) -> Result<Samples, NodeError> {
    // Header: three whitespace-separated tokens after the magic, then one whitespace byte.
    let mut tokens = Vec::new();
    let mut i = 0;
    while tokens.len() < 4 {
        while i < bytes.len() && bytes[i].is_ascii_whitespace() {
            i += 1;
        }
        let start = i;
        while i < bytes.len() && !bytes[i].is_ascii_whitespace() {
            i += 1;
        }
        if start == i || i - start > 32 {
            return Err(decode_err(path, "truncated or malformed PFM header"));
        }
        tokens.push(String::from_utf8_lossy(&bytes[start..i]).to_string());
    }
    i += 1; // the single whitespace after the scale
    let channels = match tokens[0].as_str() {
        "Pf" => 1,
        "PF" => 3,
        m => return Err(decode_err(path, format!("not a PFM file (magic `{m}`)"))),
    };
    let w: usize = tokens[1]
        .parse()
        .map_err(|_| decode_err(path, format!("bad PFM width `{}`", tokens[1])))?;
    let h: usize = tokens[2]
        .parse()
        .map_err(|_| decode_err(path, format!("bad PFM height `{}`", tokens[2])))?;
    let scale: f64 = tokens[3]
        .parse()
        .map_err(|_| decode_err(path, format!("bad PFM scale `{}`", tokens[3])))?;
    if !scale.is_finite() || scale == 0.0 {
        return Err(decode_err(
            path,
            format!(
                "bad PFM scale `{}`: expected a finite non-zero number (its sign is the byte order)",
                tokens[3]
            ),
        ));
    }
    check_dims(path, w, h, lim)?;
    // no overflow: w * h <= lim.max_pixels and channels * 4 <= 12
    let need = w
        .checked_mul(h)
        .and_then(|n| n.checked_mul(channels * 4))
        .ok_or_else(|| decode_err(path, "PFM dimensions overflow"))?;
    let data = bytes.get(samples_start(bytes, i, need)..).unwrap_or(&[]);
    if data.len() < need {
        return Err(decode_err(
            path,
            format!(
                "PFM data holds {} bytes, expected {need} for {w}x{h}x{channels}",
                data.len()
            ),
        ));
    }
    let little = scale < 0.0;
    let mut values = vec![0.0f32; w * h];
    for y in 0..h {
        let src_row = h - 1 - y; // bottom-up
        for x in 0..w {
            let o = ((src_row * w + x) * channels) * 4;
            let b = [data[o], data[o + 1], data[o + 2], data[o + 3]];
            values[y * w + x] = if little {
                f32::from_le_bytes(b)
            } else {
                f32::from_be_bytes(b)
            };
        }
    }
    Ok(Samples {
        width: w,
        height: h,
        values,
    })
}
