//! Binary PNM (`P5` grey, `P6` RGB, 8 or 16 bit), as the NYU toolbox
//! writes its raw frames.

use std::path::Path;

use depthgraph_graph::prelude::*;

use super::decode::{
    Limits, check_dims, decode_err, read_file, samples_start, srgb8_table, srgb16_table,
};
use crate::kit::color::srgb_to_linear;

/// A binary PNM file (`P5` grey or `P6` RGB, 8 or 16 bit).
#[derive(Debug, Clone, PartialEq)]
pub struct Pnm {
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
    /// 1 (P5) or 3 (P6).
    pub channels: usize,
    /// The header's maxval (255 or less: 8-bit samples; above: 16-bit).
    pub maxval: u32,
    /// Samples row-major, channels interleaved.
    pub samples: Vec<u16>,
}

/// Reads a binary PGM/PPM (`P5`/`P6`). 16-bit samples are big-endian as the
/// format says, unless `little_endian_16` (the NYU Depth v2 raw dumps store
/// little-endian samples under a PGM header, see `nyu_raw` in [`LoadDepthParams`](crate::io::LoadDepthParams)).
pub fn read_pnm(path: &Path, little_endian_16: bool) -> Result<Pnm, NodeError> {
    decode_pnm(
        &read_file(path, &Limits::default())?,
        path,
        little_endian_16,
        &Limits::default(),
    )
}

/// [`read_pnm`] of a file's bytes (`path` names it in errors), the header
/// checked against `lim` before the samples are allocated.
pub fn decode_pnm(
    bytes: &[u8],
    path: &Path,
    little_endian_16: bool,
    lim: &Limits,
) -> Result<Pnm, NodeError> {
    // header: magic, width, height, maxval, separated by whitespace and comments
    let mut pos = 0usize;
    let mut tokens: Vec<String> = Vec::new();
    while tokens.len() < 4 {
        while pos < bytes.len() && (bytes[pos].is_ascii_whitespace() || bytes[pos] == b'#') {
            if bytes[pos] == b'#' {
                while pos < bytes.len() && bytes[pos] != b'\n' {
                    pos += 1;
                }
            } else {
                pos += 1;
            }
        }
        let start = pos;
        while pos < bytes.len() && !bytes[pos].is_ascii_whitespace() && bytes[pos] != b'#' {
            pos += 1;
        }
        if start == pos {
            return Err(decode_err(path, "truncated PNM header"));
        }
        tokens.push(String::from_utf8_lossy(&bytes[start..pos]).into_owned());
    }
    // exactly one whitespace byte ends the header
    pos += 1;
    let channels = match tokens[0].as_str() {
        "P5" => 1,
        "P6" => 3,
        other => {
            return Err(decode_err(
                path,
                format!("PNM type {other} is not supported (binary P5 or P6 only)"),
            ));
        }
    };
    let num = |i: usize, what: &str| -> Result<usize, NodeError> {
        tokens[i]
            .parse::<usize>()
            .map_err(|_| decode_err(path, format!("bad PNM {what} \"{}\"", tokens[i])))
    };
    let (w, h, maxval) = (num(1, "width")?, num(2, "height")?, num(3, "maxval")?);
    check_dims(path, w, h, lim)?;
    if maxval == 0 || maxval > 65535 {
        return Err(decode_err(
            path,
            format!("PNM maxval {maxval} is not in 1..=65535"),
        ));
    }
    let bps = if maxval > 255 { 2 } else { 1 };
    let n = w * h * channels;
    let start = samples_start(bytes, pos.min(bytes.len()), n * bps);
    let data = bytes.get(start..).unwrap_or(&[]);
    if data.len() < n * bps {
        return Err(decode_err(
            path,
            format!(
                "PNM data has {} bytes, {}x{} needs {}",
                data.len(),
                w,
                h,
                n * bps
            ),
        ));
    }
    let samples: Vec<u16> = if bps == 1 {
        data[..n].iter().map(|v| *v as u16).collect()
    } else {
        data[..2 * n]
            .chunks_exact(2)
            .map(|c| {
                if little_endian_16 {
                    u16::from_le_bytes([c[0], c[1]])
                } else {
                    u16::from_be_bytes([c[0], c[1]])
                }
            })
            .collect()
    };
    Ok(Pnm {
        width: w,
        height: h,
        channels,
        maxval: maxval as u32,
        samples,
    })
}

pub(super) fn is_pnm(path: &Path) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
        .is_some_and(|e| matches!(e.as_str(), "pgm" | "ppm" | "pnm"))
}

/// A PNM color file as linear RGB (grey is replicated).
pub(super) fn pnm_color(pnm: Pnm, path: &Path, srgb: bool) -> Result<ColorImage, NodeError> {
    // guard: maxval >= 1 (checked in read_pnm)
    let inv = 1.0 / pnm.maxval as f32;
    let t8 = srgb8_table();
    let t16 = srgb16_table();
    let conv = |v: u16| -> f32 {
        let v = v.min(pnm.maxval as u16);
        if !srgb {
            v as f32 * inv
        } else if pnm.maxval == 255 {
            t8[v as usize]
        } else if pnm.maxval == 65535 {
            t16[v as usize]
        } else {
            srgb_to_linear(v as f32 * inv)
        }
    };
    let data: Vec<[f32; 3]> = pnm
        .samples
        .chunks_exact(pnm.channels)
        .map(|c| {
            if pnm.channels == 3 {
                [conv(c[0]), conv(c[1]), conv(c[2])]
            } else {
                let g = conv(c[0]);
                [g, g, g]
            }
        })
        .collect();
    Image::from_vec(pnm.width, pnm.height, data).map_err(|e| decode_err(path, e.to_string()))
}
