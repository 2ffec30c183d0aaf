//! Radiance RGBE (`.hdr`, `.pic`): Greg Ward's shared-exponent format, as
//! Debevec's light probes and HDR merges are distributed.
//!
//! Reading:
//!
//! - the header is the lines up to the first empty one, in any order (the
//!   `#?RADIANCE` / `#?RGBE` magic is expected but a file whose header puts
//!   `VIEW=` or comments first is read as well);
//! - `FORMAT=32-bit_rle_rgbe` (the default) or `32-bit_rle_xyze` (CIE XYZ,
//!   turned into linear sRGB primaries, D65, negative components of colours
//!   outside that gamut set to 0);
//! - every `EXPOSURE=e` multiplies into the factor the pixels were scaled
//!   by; the loader divides it out, so values are radiance as captured
//!   (reported by [`Rgbe::exposure`]; a product outside 1e-30..1e30 is an
//!   error, and values beyond f32 saturate at its largest);
//! - the resolution line in any of its eight orientations (`-Y H +X W` is
//!   the usual top-down one; `+Y` is bottom-up, `-X` right-to-left, and
//!   `±X W ±Y H` stores columns);
//! - scan lines flat, in the old run-length encoding (`1 1 1 n` repeats the
//!   previous pixel) or the new one (`2 2 hi lo`, then each channel's runs).
//!
//! A pixel `(r, g, b, e)` is `(c + 0.5) 2^(e - 136)` per channel, 0 when
//! `e = 0` (Ward's `colr_color`). Writing uses the new run-length encoding
//! (flat for widths outside 8..=32767), top-down, and the mantissas
//! `floor(c 256 / 2^k)` of `frexp(max(r, g, b)) = m 2^k`.

use std::path::Path;

use depthgraph_graph::prelude::*;

use super::decode::{Limits, check_dims, decode_err};

/// A decoded Radiance file.
#[derive(Debug, Clone, PartialEq)]
pub struct Rgbe {
    /// Linear RGB, top row first, the exposure divided out.
    pub image: ColorImage,
    /// The product of the header's `EXPOSURE=` values (1 without any).
    pub exposure: f64,
}

/// Linear sRGB (D65) from CIE XYZ.
const XYZ_TO_RGB: [[f64; 3]; 3] = [
    [3.2404542, -1.5371385, -0.4985314],
    [-0.9692660, 1.8760108, 0.0415560],
    [0.0556434, -0.2040259, 1.0572252],
];

/// Whether `bytes` start like a Radiance file.
pub fn looks_like_rgbe(bytes: &[u8]) -> bool {
    bytes.starts_with(b"#?RADIANCE") || bytes.starts_with(b"#?RGBE")
}

/// How the stored scan lines map to the image: the resolution line.
#[derive(Debug, Clone, Copy)]
struct Layout {
    width: usize,
    height: usize,
    /// Scan lines run along x (`±Y H ±X W`), else along y.
    rows: bool,
    /// The first scan line is the top row (`-Y`) / left column (`-X`).
    first_low: bool,
    /// Along a scan line the coordinate increases (`+X` / `+Y`).
    along_up: bool,
    /// Scan lines and their length.
    lines: usize,
    len: usize,
}

fn parse_resolution(line: &str, path: &Path) -> Result<Layout, NodeError> {
    let t: Vec<&str> = line.split_whitespace().collect();
    let bad = || decode_err(path, format!("bad Radiance resolution line `{line}`"));
    if t.len() != 4 {
        return Err(bad());
    }
    let n1: usize = t[1].parse().map_err(|_| bad())?;
    let n2: usize = t[3].parse().map_err(|_| bad())?;
    let (a, b) = (t[0], t[2]);
    let axis = |s: &str| -> Option<(char, bool)> {
        let mut c = s.chars();
        let sign = c.next()?;
        let ax = c.next()?;
        if c.next().is_some() || !matches!(sign, '+' | '-') || !matches!(ax, 'X' | 'Y') {
            return None;
        }
        Some((ax, sign == '+'))
    };
    let ((a_ax, a_up), (b_ax, b_up)) = (axis(a).ok_or_else(bad)?, axis(b).ok_or_else(bad)?);
    if a_ax == b_ax {
        return Err(bad());
    }
    let rows = a_ax == 'Y';
    let (width, height) = if rows { (n2, n1) } else { (n1, n2) };
    // `-Y`: the first line is the top row (image y grows downwards);
    // `-X` first: the first line is the right-most column
    let first_low = if rows { !a_up } else { a_up };
    let along_up = if rows { b_up } else { !b_up };
    Ok(Layout {
        width,
        height,
        rows,
        first_low,
        along_up,
        lines: n1,
        len: n2,
    })
}

/// Decodes one scan line of `len` pixels starting at `bytes[*pos]`.
fn scanline(
    bytes: &[u8],
    pos: &mut usize,
    len: usize,
    out: &mut [[u8; 4]],
    path: &Path,
) -> Result<(), NodeError> {
    let short = || decode_err(path, "Radiance pixel data ends early");
    let b = bytes.get(*pos..*pos + 4).ok_or_else(short)?;
    // the new run-length encoding
    if (8..=0x7fff).contains(&len) && b[0] == 2 && b[1] == 2 && b[2] & 0x80 == 0 {
        let n = (usize::from(b[2]) << 8) | usize::from(b[3]);
        if n != len {
            return Err(decode_err(
                path,
                format!("Radiance scan line says {n} pixels, the image {len}"),
            ));
        }
        *pos += 4;
        for ch in 0..4 {
            let mut x = 0;
            while x < len {
                let &count = bytes.get(*pos).ok_or_else(short)?;
                *pos += 1;
                if count > 128 {
                    let run = usize::from(count - 128);
                    let &v = bytes.get(*pos).ok_or_else(short)?;
                    *pos += 1;
                    if x + run > len {
                        return Err(decode_err(path, "Radiance run beyond its scan line"));
                    }
                    for p in &mut out[x..x + run] {
                        p[ch] = v;
                    }
                    x += run;
                } else {
                    let run = usize::from(count);
                    if run == 0 || x + run > len {
                        return Err(decode_err(path, "bad Radiance run length"));
                    }
                    let src = bytes.get(*pos..*pos + run).ok_or_else(short)?;
                    for (p, v) in out[x..x + run].iter_mut().zip(src) {
                        p[ch] = *v;
                    }
                    *pos += run;
                    x += run;
                }
            }
        }
        return Ok(());
    }
    // flat pixels, with the old encoding's repeats (1 1 1 n: the previous
    // pixel n << shift more times; consecutive repeats shift by 8)
    let mut x = 0;
    let mut shift = 0u32;
    while x < len {
        let p = bytes.get(*pos..*pos + 4).ok_or_else(short)?;
        *pos += 4;
        if p[0] == 1 && p[1] == 1 && p[2] == 1 {
            if x == 0 || shift > 16 {
                return Err(decode_err(path, "bad Radiance repeat"));
            }
            let run = usize::from(p[3]) << shift;
            if x + run > len {
                return Err(decode_err(path, "Radiance repeat beyond its scan line"));
            }
            let prev = out[x - 1];
            for q in &mut out[x..x + run] {
                *q = prev;
            }
            x += run;
            shift += 8;
        } else {
            out[x] = [p[0], p[1], p[2], p[3]];
            x += 1;
            shift = 0;
        }
    }
    Ok(())
}

/// `(c + 0.5) 2^(e - 136)`, 0 for `e = 0`.
fn rgbe_to_float(p: [u8; 4]) -> [f64; 3] {
    if p[3] == 0 {
        return [0.0; 3];
    }
    let f = 2f64.powi(i32::from(p[3]) - 136);
    [0, 1, 2].map(|i| (f64::from(p[i]) + 0.5) * f)
}

/// Reads a Radiance file's bytes (`path` names it in errors), its size
/// checked against `lim` before the pixels are allocated.
pub fn decode_rgbe(bytes: &[u8], path: &Path, lim: &Limits) -> Result<Rgbe, NodeError> {
    // the header: lines up to the first empty one
    let mut pos = 0;
    let mut exposure = 1.0f64;
    let mut xyz = false;
    let mut lines = 0;
    loop {
        let end = bytes[pos..]
            .iter()
            .position(|b| *b == b'\n')
            .ok_or_else(|| decode_err(path, "Radiance header without its end (an empty line)"))?;
        let line = String::from_utf8_lossy(&bytes[pos..pos + end]);
        let line = line.trim_end_matches('\r');
        pos += end + 1;
        lines += 1;
        if line.is_empty() {
            break;
        }
        if lines > 4096 {
            return Err(decode_err(path, "Radiance header longer than 4096 lines"));
        }
        if let Some(f) = line.strip_prefix("FORMAT=") {
            match f.trim() {
                "32-bit_rle_rgbe" => xyz = false,
                "32-bit_rle_xyze" => xyz = true,
                other => {
                    return Err(decode_err(
                        path,
                        format!(
                            "Radiance FORMAT={other}: expected 32-bit_rle_rgbe or 32-bit_rle_xyze"
                        ),
                    ));
                }
            }
        } else if let Some(e) = line.strip_prefix("EXPOSURE=") {
            let e: f64 = e
                .trim()
                .parse()
                .map_err(|_| decode_err(path, format!("bad Radiance EXPOSURE `{}`", e.trim())))?;
            if !(e.is_finite() && e > 0.0) {
                return Err(decode_err(
                    path,
                    format!("Radiance EXPOSURE={e}: expected a positive number"),
                ));
            }
            exposure *= e;
        }
    }
    if !(1e-30..=1e30).contains(&exposure) {
        return Err(decode_err(
            path,
            format!("Radiance EXPOSURE product {exposure:e} is outside 1e-30..1e30"),
        ));
    }
    let end = bytes[pos..]
        .iter()
        .position(|b| *b == b'\n')
        .ok_or_else(|| decode_err(path, "Radiance file without a resolution line"))?;
    let res = String::from_utf8_lossy(&bytes[pos..pos + end])
        .trim()
        .to_string();
    pos += end + 1;
    let layout = parse_resolution(&res, path)?;
    check_dims(path, layout.width, layout.height, lim)?;
    let (w, h) = (layout.width, layout.height);
    let mut line = vec![[0u8; 4]; layout.len];
    let mut data = vec![[0.0f32; 3]; w * h];
    // guard: exposure > 0 and finite (checked above)
    let inv_exposure = 1.0 / exposure;
    for l in 0..layout.lines {
        scanline(bytes, &mut pos, layout.len, &mut line, path)?;
        for (k, p) in line.iter().enumerate() {
            let a = if layout.first_low {
                l
            } else {
                layout.lines - 1 - l
            };
            let b = if layout.along_up {
                k
            } else {
                layout.len - 1 - k
            };
            let (x, y) = if layout.rows { (b, a) } else { (a, b) };
            let mut c = rgbe_to_float(*p);
            if xyz {
                let m = XYZ_TO_RGB;
                // colours outside the sRGB gamut lose their negative part
                c = [0, 1, 2].map(|i| (m[i][0] * c[0] + m[i][1] * c[1] + m[i][2] * c[2]).max(0.0));
            }
            // beyond f32 (2^127 mantissas, a tiny exposure) saturates
            data[y * w + x] = c.map(|v| (v * inv_exposure).min(f64::from(f32::MAX)) as f32);
        }
    }
    Ok(Rgbe {
        image: Image::from_vec(w, h, data)?,
        exposure,
    })
}

/// One pixel as RGBE: the mantissas of `frexp(max(r, g, b))`, non-finite
/// and negative values as 0.
fn float_to_rgbe(c: [f32; 3]) -> [u8; 4] {
    let c = c.map(|v| {
        if v.is_finite() && v > 0.0 {
            f64::from(v)
        } else {
            0.0
        }
    });
    let v = c[0].max(c[1]).max(c[2]);
    if v < 1e-38 {
        return [0; 4];
    }
    // v = m 2^k with m in [0.5, 1)
    let k = v.log2().floor() as i32 + 1;
    let k = k.clamp(-128, 127);
    // guard: 2^k > 0
    let scale = 256.0 / 2f64.powi(k);
    let m = c.map(|x| (x * scale).floor().clamp(0.0, 255.0) as u8);
    [m[0], m[1], m[2], (k + 128) as u8]
}

/// Encodes `img` as a Radiance file (top-down, new run-length encoding).
pub fn encode_rgbe(img: &ColorImage) -> Vec<u8> {
    let (w, h) = img.dims();
    let mut out =
        format!("#?RADIANCE\n# written by depthgraph\nFORMAT=32-bit_rle_rgbe\n\n-Y {h} +X {w}\n")
            .into_bytes();
    let rle = (8..=0x7fff).contains(&w);
    let mut line = vec![[0u8; 4]; w];
    for y in 0..h {
        for (x, p) in line.iter_mut().enumerate() {
            *p = float_to_rgbe(*img.get(x, y));
        }
        if !rle {
            for p in &line {
                out.extend_from_slice(p);
            }
            continue;
        }
        out.extend_from_slice(&[2, 2, (w >> 8) as u8, (w & 0xff) as u8]);
        for ch in 0..4 {
            let v: Vec<u8> = line.iter().map(|p| p[ch]).collect();
            let mut x = 0;
            while x < w {
                // a run of at least 4 equal values is worth its two bytes
                let mut run = 1;
                while x + run < w && run < 127 && v[x + run] == v[x] {
                    run += 1;
                }
                if run >= 4 {
                    out.extend_from_slice(&[128 + run as u8, v[x]]);
                    x += run;
                    continue;
                }
                // literals up to the next run of 4 (at most 128)
                let start = x;
                while x < w && x - start < 128 {
                    let mut r = 1;
                    while x + r < w && r < 4 && v[x + r] == v[x] {
                        r += 1;
                    }
                    if r >= 4 {
                        break;
                    }
                    x += 1;
                }
                out.push((x - start) as u8);
                out.extend_from_slice(&v[start..x]);
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lim() -> Limits {
        Limits::default()
    }

    fn ramp(w: usize, h: usize) -> ColorImage {
        ColorImage::from_fn(w, h, |x, y| {
            let v = 0.01 * (1.0 + x as f32) * (1.0 + 3.0 * y as f32);
            [v, 2.0 * v, if x % 3 == 0 { 0.0 } else { 1000.0 * v }]
        })
    }

    /// Within half a mantissa unit of the largest channel.
    fn close(a: &ColorImage, b: &ColorImage) {
        for (p, q) in a.as_slice().iter().zip(b.as_slice()) {
            let m = p.iter().fold(0.0f32, |m, v| m.max(*v));
            for (x, y) in p.iter().zip(q) {
                assert!((x - y).abs() <= m / 256.0 + 1e-30, "{p:?} vs {q:?}");
            }
        }
    }

    #[test]
    fn round_trip_rle_and_flat() {
        for (w, h) in [(40, 7), (5, 3), (1, 1)] {
            let img = ramp(w, h);
            let bytes = encode_rgbe(&img);
            let back = decode_rgbe(&bytes, Path::new("x.hdr"), &lim()).unwrap();
            assert_eq!(back.image.dims(), (w, h));
            assert_eq!(back.exposure, 1.0);
            close(&img, &back.image);
            // a flat constant image compresses to runs
            let flat = ColorImage::filled(200, 2, [0.5, 0.25, 0.125]);
            assert!(encode_rgbe(&flat).len() < 200 * 2 * 4 / 10);
        }
    }

    #[test]
    fn header_in_any_order_exposure_and_orientations() {
        let img = ramp(9, 4);
        let body = encode_rgbe(&img);
        let split = body.windows(2).position(|w| w == b"\n\n").unwrap() + 2;
        let pixels_at = split + body[split..].iter().position(|b| *b == b'\n').unwrap() + 1;
        // VIEW= and a comment before the magic, EXPOSURE twice
        let mut b = b"VIEW= -vtv -vp 0 0 0\n# made by hand\n#?RADIANCE\nEXPOSURE=2\nFORMAT=32-bit_rle_rgbe\nEXPOSURE=0.25\n\n-Y 4 +X 9\n".to_vec();
        b.extend_from_slice(&body[pixels_at..]);
        let r = decode_rgbe(&b, Path::new("x.hdr"), &lim()).unwrap();
        assert_eq!(r.exposure, 0.5);
        let want = ColorImage::from_fn(9, 4, |x, y| img.get(x, y).map(|v| v * 2.0));
        close(&want, &r.image);
        // bottom-up storage: the same lines under +Y are the image flipped
        let mut up = b"#?RADIANCE\n\n+Y 4 +X 9\n".to_vec();
        up.extend_from_slice(&body[pixels_at..]);
        let r = decode_rgbe(&up, Path::new("x.hdr"), &lim()).unwrap();
        let flipped = ColorImage::from_fn(9, 4, |x, y| *img.get(x, 3 - y));
        close(&flipped, &r.image);
        // columns: `-X 3 +Y 2` stores the right-most column first, each
        // from the bottom up (Radiance's Y points up)
        let col = ramp(3, 2);
        let mut t = b"#?RADIANCE\n\n-X 3 +Y 2\n".to_vec();
        for x in (0..3).rev() {
            for y in (0..2).rev() {
                t.extend_from_slice(&float_to_rgbe(*col.get(x, y)));
            }
        }
        let r = decode_rgbe(&t, Path::new("x.hdr"), &lim()).unwrap();
        assert_eq!(r.image.dims(), (3, 2));
        close(&col, &r.image);
    }

    #[test]
    fn old_run_length_encoding() {
        let px = float_to_rgbe([1.0, 0.5, 0.25]);
        let mut b = b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 1 +X 300\n".to_vec();
        b.extend_from_slice(&px);
        // 1 1 1 43: 43 more; then 1 1 1 1: 1 << 8 = 256 more (300 in all)
        b.extend_from_slice(&[1, 1, 1, 43, 1, 1, 1, 1]);
        let r = decode_rgbe(&b, Path::new("x.hdr"), &lim()).unwrap();
        assert_eq!(r.image.dims(), (300, 1));
        assert!(r.image.as_slice().iter().all(|p| p == r.image.get(0, 0)));
        assert!((r.image.get(299, 0)[0] - 1.0).abs() < 1.0 / 128.0);
    }

    #[test]
    fn bad_files_are_errors_naming_the_file() {
        let good = encode_rgbe(&ramp(12, 3));
        let cases: Vec<(&str, Vec<u8>)> = vec![
            (
                "no_end.hdr",
                b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n".to_vec(),
            ),
            (
                "format.hdr",
                b"#?RADIANCE\nFORMAT=48-bit\n\n-Y 1 +X 1\n\0\0\0\0".to_vec(),
            ),
            (
                "exposure.hdr",
                b"#?RADIANCE\nEXPOSURE=nan\n\n-Y 1 +X 1\n\0\0\0\0".to_vec(),
            ),
            ("res.hdr", b"#?RADIANCE\n\n-Y 1 -Y 1\n\0\0\0\0".to_vec()),
            ("huge.hdr", b"#?RADIANCE\n\n-Y 60000 +X 60000\n".to_vec()),
            ("short.hdr", good[..good.len() - 5].to_vec()),
            (
                "repeat.hdr",
                b"#?RADIANCE\n\n-Y 1 +X 2\n\x01\x01\x01\x05".to_vec(),
            ),
        ];
        for (name, b) in cases {
            let e = decode_rgbe(&b, Path::new(name), &lim()).unwrap_err();
            assert!(e.to_string().contains(name), "{e}");
        }
        let e = decode_rgbe(&good, Path::new("g.hdr"), &Limits { max_pixels: 35 }).unwrap_err();
        assert!(e.to_string().contains("35 pixels"), "{e}");
    }

    #[test]
    fn the_largest_values_stay_finite() {
        // 255.5 2^119 / 0.1 (beyond f32: saturated) and the largest XYZ
        for (head, saturated) in [
            (&b"#?RADIANCE\nEXPOSURE=0.1\n"[..], true),
            (&b"#?RADIANCE\nFORMAT=32-bit_rle_xyze\n"[..], false),
        ] {
            let mut b = head.to_vec();
            b.extend_from_slice(b"\n-Y 1 +X 1\n\xff\xff\xff\xff");
            let r = decode_rgbe(&b, Path::new("x.hdr"), &lim()).unwrap();
            let p = r.image.get(0, 0);
            assert!(p.iter().all(|v| v.is_finite() && *v >= 0.0), "{p:?}");
            assert_eq!(p.contains(&f32::MAX), saturated, "{p:?}");
        }
    }

    #[test]
    fn xyz_files_become_rgb() {
        // D65 white (X, Y, Z) = (0.9505, 1, 1.089) is RGB (1, 1, 1)
        let mut b = b"#?RADIANCE\nFORMAT=32-bit_rle_xyze\n\n-Y 1 +X 1\n".to_vec();
        b.extend_from_slice(&float_to_rgbe([0.9505, 1.0, 1.089]));
        let r = decode_rgbe(&b, Path::new("x.hdr"), &lim()).unwrap();
        for v in r.image.get(0, 0) {
            assert!((v - 1.0).abs() < 0.02, "{:?}", r.image.get(0, 0));
        }
    }

    /// Debevec's own `memorial.hdr` (VIEW= before the magic, new RLE):
    /// read whole, every value finite and non-negative. Needs
    /// `../shared/data`; says so on stderr without it.
    #[test]
    fn debevec_memorial_hdr_reads() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../shared/data/hdr_debevec_memorial/memorial/memorial.hdr");
        let Ok(bytes) = std::fs::read(&path) else {
            eprintln!("{} is missing: memorial.hdr not read", path.display());
            return;
        };
        let r = decode_rgbe(&bytes, &path, &lim()).unwrap();
        assert_eq!(r.image.dims(), (512, 768));
        assert_eq!(r.exposure, 1.0);
        let px = r.image.as_slice();
        assert!(px.iter().flatten().all(|v| v.is_finite() && *v >= 0.0));
        // a church interior lit through its windows: a dynamic range of
        // many stops, not a constant
        let lum: Vec<f32> = px
            .iter()
            .map(|p| p[0] + p[1] + p[2])
            .filter(|l| *l > 0.0)
            .collect();
        let (lo, hi) = lum
            .iter()
            .fold((f32::MAX, 0.0f32), |(a, b), l| (a.min(*l), b.max(*l)));
        assert!(hi / lo > 1000.0, "range {lo}..{hi}");
        // re-encoded and read back: within half a mantissa unit
        let again = decode_rgbe(&encode_rgbe(&r.image), &path, &lim()).unwrap();
        close(&r.image, &again.image);
    }
}
