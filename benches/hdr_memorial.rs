//! HDR merge accuracy and time (Debevec & Malik 1997):
//! `cargo bench --bench hdr_memorial` regenerates `docs/hdr.md`.
//!
//! 1. **Memorial church**: the 16 exposures of Debevec's own series
//!    (`../shared/data/hdr_debevec_memorial/memorial/`, pure-blue borders
//!    masked) are merged with a recovered response and compared with
//!    Debevec's `memorial.hdr` by the RMS of `ln(ours) - ln(ref)` after
//!    removing the mean offset (one per channel: a recovered response fixes
//!    radiance only up to one factor per channel; the one-factor variant is
//!    shown too). `memorial.hdr` is Debevec's result, not ground truth.
//! 2. **3 exposures at 640x480**: the synthetic tabletop through
//!    `SimulateBracket` (stops -2, 0, +2, gamma 2.2): time of the merge and of
//!    the recovery, and the same log error against the exact radiance.
//!
//! OpenCV's `CalibrateDebevec` + `MergeDebevec` run on the same images in the
//! same run through `benches/peers/opencv_hdr.py` (set `DEPTHGRAPH_PEERS=0`
//! to skip; `DEPTHGRAPH_PEER_DIR` keeps the exchanged files).
//!
//! `memorial.hdr` starts with a `VIEW=` line before `#?RADIANCE` and uses CRLF
//! line ends, which the `image` crate's RGBE decoder (0.25) refuses, so this
//! bench reads it with its own small RGBE reader ([`read_rgbe`]).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use depthgraph::evaluation::shared_data_dir;
use depthgraph::graph::prelude::*;
use depthgraph::nodes::camera::hdr::{
    LoadBracketParams, Merged, ResponseCurve, ResponseParams, load_bracket, merge_hdr,
    recover_response,
};
use depthgraph::nodes::sim::sensor::{BracketParams, simulate_bracket};
use depthgraph::nodes::sim::synthetic::{RenderOptions, Scene, render};

/// Median wall time in ms of `repeats` calls, and the last result.
fn median_ms<T>(repeats: usize, mut f: impl FnMut() -> T) -> (Option<T>, f64) {
    let mut times = Vec::new();
    let mut out = None;
    for _ in 0..repeats.max(1) {
        let t = Instant::now();
        out = Some(f());
        times.push(t.elapsed().as_secs_f64() * 1e3);
    }
    times.sort_by(f64::total_cmp);
    (out, times[times.len() / 2])
}

// ------------------------------------------------------------------ RGBE

fn rgbe_to_rgb(p: [u8; 4]) -> [f32; 3] {
    if p[3] == 0 {
        return [0.0; 3];
    }
    // Radiance's convention: (mantissa + 0.5) * 2^(exponent - 136)
    let f = 2f64.powi(p[3] as i32 - 136);
    [0, 1, 2].map(|c| ((p[c] as f64 + 0.5) * f) as f32)
}

/// The byte at `*pos`, advancing it.
fn take(bytes: &[u8], pos: &mut usize) -> Result<u8, String> {
    let b = *bytes.get(*pos).ok_or("truncated pixel data")?;
    *pos += 1;
    Ok(b)
}

fn read_scanline(bytes: &[u8], pos: &mut usize, scan: &mut [[u8; 4]]) -> Result<(), String> {
    let w = scan.len();
    let head = bytes.get(*pos..*pos + 4);
    if let Some(&[2, 2, hi, lo]) = head {
        if (8..32768).contains(&w) && hi & 0x80 == 0 {
            // new run-length encoding: the four channels one after the other
            let sw = ((hi as usize) << 8) | lo as usize;
            if sw != w {
                return Err(format!("scanline width {sw}, expected {w}"));
            }
            *pos += 4;
            for ch in 0..4 {
                let mut x = 0;
                while x < w {
                    let count = take(bytes, pos)? as usize;
                    if count > 128 {
                        let n = count - 128;
                        let v = take(bytes, pos)?;
                        if x + n > w {
                            return Err("run overflows the scanline".into());
                        }
                        for px in &mut scan[x..x + n] {
                            px[ch] = v;
                        }
                        x += n;
                    } else {
                        if count == 0 || x + count > w {
                            return Err("bad literal run".into());
                        }
                        for px in &mut scan[x..x + count] {
                            px[ch] = take(bytes, pos)?;
                        }
                        x += count;
                    }
                }
            }
            return Ok(());
        }
    }
    // flat pixels, with the old encoding's (1, 1, 1, n) repeats
    let mut x = 0;
    let mut shift = 0;
    while x < w {
        let px = [
            take(bytes, pos)?,
            take(bytes, pos)?,
            take(bytes, pos)?,
            take(bytes, pos)?,
        ];
        if px[0] == 1 && px[1] == 1 && px[2] == 1 {
            if x == 0 {
                return Err("repeat before the first pixel".into());
            }
            if shift > 24 {
                return Err("repeat count overflows".into());
            }
            let n = (px[3] as usize) << shift;
            let prev = scan[x - 1];
            let end = (x + n).min(w);
            for p in &mut scan[x..end] {
                *p = prev;
            }
            x = end;
            shift += 8;
        } else {
            scan[x] = px;
            x += 1;
            shift = 0;
        }
    }
    Ok(())
}

/// A byte of a CR LF-converted stream: itself, or a CR LF pair that stood
/// for 0x0A, 0x0D or 0x0D 0x0A before the conversion.
#[derive(Debug, Clone, Copy)]
enum Tok {
    Byte(u8),
    CrLf,
}

/// Re-decodes one new-RLE scanline (without its 4-byte header) whose bytes
/// went through a CR LF conversion. Every reading of the ambiguous pairs that
/// gives a valid scanline ending exactly at the next scanline header is
/// considered; among them the one whose bytes differ least from the scanline
/// above (each difference capped at 40) wins (dynamic programming over the
/// parser states, i.e. a Viterbi search). Returns the pixels and, per pixel,
/// whether a byte of it came from a pair read as a single byte (0x0A or 0x0D:
/// its value is uncertain).
struct RowRepair<'a> {
    tok: &'a [Tok],
    w: usize,
    above: Option<&'a [[u8; 4]]>,
    memo: std::collections::HashMap<u64, (u32, u8)>,
}

const UNREACHABLE: u32 = u32::MAX;

impl RowRepair<'_> {
    fn key(ti: usize, pend: bool, ch: usize, x: usize, rem: usize, n: usize) -> u64 {
        ti as u64
            | (pend as u64) << 24
            | (ch as u64) << 25
            | (x as u64) << 28
            | (rem as u64) << 44
            | (n as u64) << 52
    }

    /// Readings of the next byte: (value, next token, pending 0x0A, uncertain).
    fn reads(&self, ti: usize, pend: bool) -> Vec<(u8, usize, bool, bool)> {
        if pend {
            return vec![(10, ti, false, false)];
        }
        match self.tok.get(ti) {
            None => vec![],
            Some(Tok::Byte(v)) => vec![(*v, ti + 1, false, false)],
            Some(Tok::CrLf) => vec![
                (10, ti + 1, false, true),
                (13, ti + 1, false, true),
                (13, ti + 1, true, false),
            ],
        }
    }

    fn cost(&self, v: u8, ch: usize, x: usize, n: usize) -> u32 {
        match self.above {
            None => 0,
            Some(a) => a[x..x + n]
                .iter()
                .map(|p| (v as i32 - p[ch] as i32).unsigned_abs().min(40))
                .sum(),
        }
    }

    /// The parser state after reading `v` in state (ch, x, rem, n), and the cost.
    fn step(
        &self,
        v: u8,
        ch: usize,
        x: usize,
        rem: usize,
        n: usize,
    ) -> Option<((usize, usize, usize, usize), u32)> {
        if rem > 0 {
            Some(((ch, x + 1, rem - 1, 0), self.cost(v, ch, x, 1)))
        } else if n > 0 {
            Some(((ch, x + n, 0, 0), self.cost(v, ch, x, n)))
        } else if v > 128 {
            let n = v as usize - 128;
            (x + n <= self.w).then_some(((ch, x, 0, n), 0))
        } else if v > 0 && x + v as usize <= self.w {
            Some(((ch, x, v as usize, 0), 0))
        } else {
            None
        }
    }

    fn best(&mut self, ti: usize, pend: bool, ch: usize, x: usize, rem: usize, n: usize) -> u32 {
        let (mut ch, mut x) = (ch, x);
        if x == self.w && rem == 0 && n == 0 {
            ch += 1;
            x = 0;
        }
        if ch == 4 {
            return if ti == self.tok.len() && !pend {
                0
            } else {
                UNREACHABLE
            };
        }
        let key = Self::key(ti, pend, ch, x, rem, n);
        if let Some(m) = self.memo.get(&key) {
            return m.0;
        }
        let mut best = (UNREACHABLE, 0u8);
        for (i, (v, t1, p1, _)) in self.reads(ti, pend).into_iter().enumerate() {
            let Some(((c2, x2, r2, n2), c)) = self.step(v, ch, x, rem, n) else {
                continue;
            };
            let rest = self.best(t1, p1, c2, x2, r2, n2);
            if rest != UNREACHABLE && rest.saturating_add(c) < best.0 {
                best = (rest.saturating_add(c), i as u8);
            }
        }
        self.memo.insert(key, best);
        best.0
    }

    fn decode(mut self) -> Option<(Vec<[u8; 4]>, Vec<bool>)> {
        if self.best(0, false, 0, 0, 0, 0) == UNREACHABLE {
            return None;
        }
        let w = self.w;
        let mut out = vec![[0u8; 4]; w];
        let mut unsure = vec![false; w];
        let (mut ti, mut pend, mut ch, mut x, mut rem, mut n) = (0, false, 0, 0, 0, 0);
        loop {
            if x == w && rem == 0 && n == 0 {
                ch += 1;
                x = 0;
            }
            if ch == 4 {
                return Some((out, unsure));
            }
            let (_, choice) = *self.memo.get(&Self::key(ti, pend, ch, x, rem, n))?;
            let (v, t1, p1, amb) = *self.reads(ti, pend).get(choice as usize)?;
            let ((c2, x2, r2, n2), _) = self.step(v, ch, x, rem, n)?;
            let span = if rem > 0 {
                x..x + 1
            } else if n > 0 {
                x..x + n
            } else {
                x..x
            };
            for k in span {
                out[k][ch] = v;
                unsure[k] |= amb;
            }
            (ti, pend, ch, x, rem, n) = (t1, p1, c2, x2, r2, n2);
        }
    }
}

/// True when `data` looks CR LF-converted: every LF follows a CR and every
/// CR precedes an LF.
fn crlf_converted(data: &[u8]) -> bool {
    let lf = data.iter().filter(|b| **b == b'\n').count();
    let cr = data.iter().filter(|b| **b == b'\r').count();
    let pairs = data.windows(2).filter(|p| p == b"\r\n").count();
    lf > 0 && lf == pairs && cr == pairs
}

/// Repairs new-RLE pixel data that went through a CR LF conversion (see
/// [`RowRepair`]); scanlines are found by their headers `2 2 hi lo`.
fn repair_rgbe(data: &[u8], w: usize, h: usize) -> Result<(Vec<[u8; 4]>, Vec<bool>), String> {
    let marker = [2u8, 2, (w >> 8) as u8, (w & 255) as u8];
    let starts: Vec<usize> = data
        .windows(4)
        .enumerate()
        .filter(|(_, win)| *win == marker)
        .map(|(i, _)| i)
        .collect();
    if starts.len() != h || starts.first() != Some(&0) {
        return Err(format!(
            "found {} scanline headers, expected {h}",
            starts.len()
        ));
    }
    let mut pixels = Vec::with_capacity(w * h);
    let mut unsure = Vec::with_capacity(w * h);
    for y in 0..h {
        let end = starts.get(y + 1).copied().unwrap_or(data.len());
        let seg = &data[starts[y] + 4..end];
        let mut tok = Vec::with_capacity(seg.len());
        let mut i = 0;
        while i < seg.len() {
            if seg[i] == b'\r' && seg.get(i + 1) == Some(&b'\n') {
                tok.push(Tok::CrLf);
                i += 2;
            } else {
                tok.push(Tok::Byte(seg[i]));
                i += 1;
            }
        }
        let above = (y > 0).then(|| &pixels[(y - 1) * w..y * w]);
        let (row, amb) = RowRepair {
            tok: &tok,
            w,
            above,
            memo: std::collections::HashMap::new(),
        }
        .decode()
        .ok_or_else(|| format!("row {y} has no consistent reading"))?;
        pixels.extend(row);
        unsure.extend(amb);
    }
    Ok((pixels, unsure))
}

/// Debevec's reference: the radiance, the pixels whose value is uncertain
/// (only after a repair) and a note on how it was read.
struct Reference {
    img: ColorImage,
    unsure: Vec<bool>,
    note: String,
}

/// Reads a RADIANCE RGBE file (`-Y h +X w` orientation) as linear RGB. The
/// signature may follow other header lines; CR LF line ends are accepted. A
/// file whose binary data went through a CR LF conversion (the shared
/// `memorial.hdr` did) is repaired by [`repair_rgbe`].
fn read_rgbe(path: &Path) -> Result<Reference, String> {
    let bytes = std::fs::read(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let err = |m: &str| format!("{}: {m}", path.display());
    let mut pos = 0;
    let mut line = || -> Result<String, String> {
        let rest = bytes.get(pos..).unwrap_or(&[]);
        let end = rest
            .iter()
            .position(|b| *b == b'\n')
            .ok_or_else(|| err("header never ends"))?;
        let text = String::from_utf8_lossy(&rest[..end])
            .trim_end_matches('\r')
            .to_string();
        pos += end + 1;
        Ok(text)
    };
    let mut radiance = false;
    loop {
        let l = line()?;
        if l.is_empty() {
            break;
        }
        radiance |= l.starts_with("#?");
        if let Some(f) = l.strip_prefix("FORMAT=") {
            if f.trim() != "32-bit_rle_rgbe" {
                return Err(err(&format!("format {f} is not 32-bit_rle_rgbe")));
            }
        }
    }
    if !radiance {
        return Err(err("no #?RADIANCE signature"));
    }
    let res = line()?;
    let t: Vec<&str> = res.split_whitespace().collect();
    let (h, w) = match t.as_slice() {
        ["-Y", h, "+X", w] => (
            h.parse::<usize>().map_err(|_| err("bad height"))?,
            w.parse::<usize>().map_err(|_| err("bad width"))?,
        ),
        _ => return Err(err(&format!("unsupported orientation `{res}`"))),
    };
    if w == 0 || h == 0 || w > 1 << 15 || h > 1 << 15 {
        return Err(err(&format!("size {w}x{h} out of range")));
    }
    let data = &bytes[pos.min(bytes.len())..];
    let mut plain = Vec::with_capacity(w * h);
    let mut scan = vec![[0u8; 4]; w];
    let mut at = 0;
    let mut failure = None;
    for y in 0..h {
        if let Err(e) = read_scanline(data, &mut at, &mut scan) {
            failure = Some(format!("row {y}: {e}"));
            break;
        }
        plain.extend_from_slice(&scan);
    }
    let (pixels, unsure, note) = match failure {
        None => (plain, vec![false; w * h], String::new()),
        Some(e) if crlf_converted(data) => {
            let (px, unsure) = repair_rgbe(data, w, h)
                .map_err(|r| err(&format!("{e}; the CR LF repair failed too: {r}")))?;
            let n = unsure.iter().filter(|u| **u).count();
            let note = format!(
                "`{}` does not decode as stored ({e}): its binary data went through a CR LF \
                 conversion (every LF byte is preceded by a CR, and no CR stands alone). It was \
                 re-decoded by a dynamic-programming search over the readings of each CR LF pair \
                 (0x0A, 0x0D or both) that keep every scanline valid, preferring the reading \
                 closest to the scanline above; {n} pixels ({:.1} %) hold a byte whose value stays \
                 uncertain (0x0A or 0x0D) and are left out of the comparison.",
                path.display(),
                // guard: w, h >= 1
                100.0 * n as f64 / (w * h) as f64
            );
            (px, unsure, note)
        }
        Some(e) => return Err(err(&e)),
    };
    let img = Image::from_vec(w, h, pixels.into_iter().map(rgbe_to_rgb).collect())
        .map_err(|e| err(&e.to_string()))?;
    Ok(Reference { img, unsure, note })
}

// ------------------------------------------------------------------ metric

/// Log-radiance error after removing the mean offset.
#[derive(Debug, Clone, Copy)]
struct LogError {
    /// RMS of `ln(a) - ln(b) - offset_c`, one offset per channel.
    rms_channel: f64,
    /// RMS with one offset for all channels.
    rms_global: f64,
    /// Fraction of pixel-channels within 10 % after the per-channel offsets.
    within_10: f64,
    /// Least-squares slope of `ln(a)` on `ln(b)` (channels centred and pooled):
    /// 1 when the two agree up to a factor; below 1 when `a` spans a smaller
    /// range of radiance than `b`.
    slope: f64,
    pixels: usize,
}

fn positive(px: &[f32; 3]) -> bool {
    px.iter().all(|v| v.is_finite() && *v > 0.0)
}

fn log_error(a: &ColorImage, b: &ColorImage, mask: &[bool]) -> Option<LogError> {
    if !a.same_dims(b) || mask.len() != a.len() {
        return None;
    }
    let mut sum = [0.0f64; 3];
    let mut sq = [0.0f64; 3];
    let mut n = 0usize;
    let logs: Vec<([f64; 3], [f64; 3])> = a
        .as_slice()
        .iter()
        .zip(b.as_slice())
        .zip(mask)
        .filter(|((p, q), m)| **m && positive(p) && positive(q))
        .map(|((p, q), _)| (p.map(|v| (v as f64).ln()), q.map(|v| (v as f64).ln())))
        .collect();
    let diffs: Vec<[f64; 3]> = logs
        .iter()
        .map(|(la, lb)| [0, 1, 2].map(|c| la[c] - lb[c]))
        .collect();
    for d in &diffs {
        for c in 0..3 {
            sum[c] += d[c];
            sq[c] += d[c] * d[c];
        }
        n += 1;
    }
    if n == 0 {
        return None;
    }
    let nf = n as f64; // guard: n > 0
    let mean = sum.map(|s| s / nf);
    let var_c: f64 = (0..3).map(|c| sq[c] / nf - mean[c] * mean[c]).sum::<f64>() / 3.0;
    let g = mean.iter().sum::<f64>() / 3.0;
    let var_g: f64 = (0..3).map(|c| sq[c] / nf).sum::<f64>() / 3.0 - g * g;
    let tol = 1.1f64.ln();
    let within = diffs
        .iter()
        .flat_map(|d| (0..3).map(move |c| (d[c] - mean[c]).abs() < tol))
        .filter(|ok| *ok)
        .count() as f64
        / (3.0 * nf);
    // slope of ln a on ln b, per-channel means removed
    let mean_a: [f64; 3] = [0, 1, 2].map(|c| logs.iter().map(|l| l.0[c]).sum::<f64>() / nf);
    let mean_b: [f64; 3] = [0, 1, 2].map(|c| logs.iter().map(|l| l.1[c]).sum::<f64>() / nf);
    let (mut sab, mut sbb) = (0.0f64, 0.0f64);
    for (la, lb) in &logs {
        for c in 0..3 {
            sab += (la[c] - mean_a[c]) * (lb[c] - mean_b[c]);
            sbb += (lb[c] - mean_b[c]).powi(2);
        }
    }
    // guard: a constant reference has no slope
    let slope = if sbb > 0.0 { sab / sbb } else { f64::NAN };
    Some(LogError {
        slope,
        rms_channel: var_c.max(0.0).sqrt(),
        rms_global: var_g.max(0.0).sqrt(),
        within_10: within,
        pixels: n,
    })
}

// ------------------------------------------------------------------ peers

fn peer_dir() -> (Option<PathBuf>, Option<tempfile::TempDir>) {
    let kept = std::env::var_os("DEPTHGRAPH_PEER_DIR").map(PathBuf::from);
    let temp = tempfile::tempdir().ok();
    let dir = match (&kept, &temp) {
        (Some(k), _) => std::fs::create_dir_all(k).ok().map(|_| k.clone()),
        (None, Some(t)) => Some(t.path().to_path_buf()),
        _ => None,
    };
    (dir, temp)
}

fn read_rgb_f32(path: &Path, w: usize, h: usize) -> Option<ColorImage> {
    let b = std::fs::read(path).ok()?;
    let v: Vec<f32> = b
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    let px: Vec<[f32; 3]> = v.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
    Image::from_vec(w, h, px).ok()
}

/// Runs the peer script on `case` in `dir`; `Err` says why it did not run.
/// One peer's name, calibration ms, merge ms and output.
type PeerResult = (String, f64, f64, Option<ColorImage>);

/// Runs the OpenCV peers on `case` (inputs already written under `pd`) and
/// reads back their times and outputs; the note names OpenCV's version or
/// why the peers did not run.
fn run_and_read_peers(
    pd: &Path,
    case: &str,
    w: usize,
    h: usize,
) -> (Option<String>, Vec<PeerResult>) {
    let mut out = Vec::new();
    let note = match run_peers(pd, case) {
        Ok(()) => peer_json(pd, case).and_then(|j| {
            for (key, label) in PEER_METHODS {
                out.push((
                    label.to_string(),
                    j["ms"][format!("{key}_calibrate")]
                        .as_f64()
                        .unwrap_or(f64::NAN),
                    j["ms"][format!("{key}_merge")].as_f64().unwrap_or(f64::NAN),
                    read_rgb_f32(&pd.join(format!("{case}.{key}.f32")), w, h),
                ));
            }
            j["opencv"].as_str().map(|v| format!("OpenCV {v}"))
        }),
        Err(e) => Some(format!("OpenCV peers did not run: {e}")),
    };
    (note, out)
}

fn run_peers(dir: &Path, case: &str) -> Result<(), String> {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("benches/peers/opencv_hdr.py");
    match std::process::Command::new("python3")
        .arg(&script)
        .arg(dir)
        .arg(case)
        .status()
    {
        Ok(st) if st.success() => Ok(()),
        Ok(st) => Err(format!("the OpenCV peer failed ({st})")),
        Err(e) => Err(format!("python3 unavailable ({e})")),
    }
}

/// The peer's timings and version for `case`.
fn peer_json(dir: &Path, case: &str) -> Option<serde_json::Value> {
    let text = std::fs::read_to_string(dir.join(format!("{case}.peers.json"))).ok()?;
    serde_json::from_str(&text).ok()
}

/// OpenCV variants the peer runs: key, label.
const PEER_METHODS: [(&str, &str); 2] = [
    (
        "opencv_default",
        "OpenCV CalibrateDebevec (default: 70 samples, lambda 10) + MergeDebevec",
    ),
    (
        "opencv_400",
        "OpenCV CalibrateDebevec (400 samples, lambda 31.6 = sqrt 1000) + MergeDebevec",
    ),
];

/// The part of a peer label before " + MergeDebevec".
fn calibration_of(label: &str) -> &str {
    label.split(" + ").next().unwrap_or(label)
}

struct Row {
    method: String,
    response_ms: f64,
    merge_ms: f64,
    err: Option<LogError>,
    /// The same error over the brightest 80 % of the compared pixels.
    err_bright: Option<LogError>,
}

/// `mask` without its darkest 20 % (by the reference's green channel).
fn brightest_80(reference: &ColorImage, mask: &[bool]) -> Vec<bool> {
    let mut g: Vec<f32> = reference
        .as_slice()
        .iter()
        .zip(mask)
        .filter(|(_, m)| **m)
        .map(|(p, _)| p[1])
        .collect();
    if g.is_empty() {
        return mask.to_vec();
    }
    let k = g.len() / 5;
    let thr = *g.select_nth_unstable_by(k, f32::total_cmp).1;
    reference
        .as_slice()
        .iter()
        .zip(mask)
        .map(|(p, m)| *m && p[1] >= thr)
        .collect()
}

fn table(rows: &[Row], what: &str) -> String {
    let mut s = String::from(
        "| method | response ms | merge ms | total ms | RMS ln error, per-channel factor | RMS ln error, one factor | within 10 % | slope of ln on ln ref | RMS ln error, brightest 80 % | pixels |\n\
         |---|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n",
    );
    for r in rows {
        let (a, b, c, sl, n) = match r.err {
            Some(e) => (
                format!("{:.4}", e.rms_channel),
                format!("{:.4}", e.rms_global),
                format!("{:.1} %", 100.0 * e.within_10),
                format!("{:.3}", e.slope),
                e.pixels.to_string(),
            ),
            None => ("-".into(), "-".into(), "-".into(), "-".into(), "-".into()),
        };
        let _ = writeln!(
            s,
            "| {} | {:.1} | {:.1} | {:.1} | {a} | {b} | {c} | {sl} | {} | {n} |",
            r.method,
            r.response_ms,
            r.merge_ms,
            r.response_ms + r.merge_ms,
            r.err_bright
                .map(|e| format!("{:.4}", e.rms_channel))
                .unwrap_or_else(|| "-".into())
        );
    }
    let _ = writeln!(s, "\nErrors against {what}.");
    s
}

// ------------------------------------------------------------------ cases

fn memorial(data: &Path, peers: Option<&Path>, repeats: usize) -> (String, Option<String>) {
    let dir = data.join("hdr_debevec_memorial").join("memorial");
    let list = dir.join("image_list.txt");
    let mut s =
        String::from("## Memorial church, 16 exposures, 512x768 (Debevec & Malik 1997)\n\n");
    if !list.exists() {
        eprintln!(
            "{} is missing: the memorial comparison is skipped",
            list.display()
        );
        let _ = writeln!(s, "`{}` is missing: no rows.\n", list.display());
        return (s, None);
    }
    let load = |mask: bool| {
        load_bracket(&LoadBracketParams {
            list: list.display().to_string(),
            mask_pure_blue: mask,
            ..Default::default()
        })
    };
    let (stack, load_ms) = median_ms(repeats, || load(true));
    let stack = match stack {
        Some(Ok(st)) => st,
        Some(Err(e)) => {
            eprintln!("memorial: {e}");
            let _ = writeln!(s, "Loading failed: {e}\n");
            return (s, None);
        }
        None => return (s, None),
    };
    let Reference {
        img: reference,
        unsure,
        note: repair_note,
    } = match read_rgbe(&dir.join("memorial.hdr")) {
        Ok(r) => r,
        Err(e) => {
            eprintln!("memorial: {e}");
            let _ = writeln!(s, "Reference unreadable: {e}\n");
            return (s, None);
        }
    };
    let (w, h) = stack.images[0].dims();
    if reference.dims() != (w, h) {
        let _ = writeln!(
            s,
            "Reference is {}x{}, the exposures {w}x{h}: no comparison.\n",
            reference.width(),
            reference.height()
        );
        return (s, None);
    }
    eprintln!(
        "memorial: {} exposures {w}x{h}, loaded in {load_ms:.0} ms",
        stack.images.len()
    );
    let rp = ResponseParams::default();
    let mut outputs: Vec<(String, f64, f64, Option<Merged>)> = Vec::new();
    for (label, st) in [
        (
            format!(
                "depthgraph HdrMerge ({} samples, lambda {}, pure blue masked)",
                rp.samples, rp.lambda
            ),
            Some(stack.clone()),
        ),
        (
            "depthgraph HdrMerge, blue borders not masked".to_string(),
            load(false).ok(),
        ),
    ] {
        let Some(st) = st else { continue };
        let (curve, rec_ms) = median_ms(repeats, || recover_response(&st, &rp));
        let Some(Ok(curve)) = curve else {
            eprintln!("memorial: recovery failed for {label}");
            continue;
        };
        let (merged, merge_ms) = median_ms(repeats, || merge_hdr(&st, &curve));
        outputs.push((label, rec_ms, merge_ms, merged.and_then(Result::ok)));
    }
    // peers on the same files (they have no notion of missing pixels)
    let mut note = None;
    let mut peer_out: Vec<PeerResult> = Vec::new();
    if let Some(pd) = peers {
        let files: Vec<String> = load_list_files(&list)
            .iter()
            .map(|f| f.display().to_string())
            .collect();
        let json = serde_json::json!({ "files": files, "times": stack.times_s }).to_string();
        if std::fs::write(pd.join("memorial.json"), json).is_ok() {
            (note, peer_out) = run_and_read_peers(pd, "memorial", w, h);
        }
    }
    // one pixel set for every method: valid in the reference and every output,
    // and not a fallback pixel of the masked merge
    let mut mask: Vec<bool> = reference
        .as_slice()
        .iter()
        .zip(&unsure)
        .map(|(p, u)| positive(p) && !*u)
        .collect();
    if let Some((_, _, _, Some(m))) = outputs.first() {
        for (k, (px, fb)) in m
            .color
            .as_slice()
            .iter()
            .zip(m.fallback.as_slice())
            .enumerate()
        {
            mask[k] &= positive(px) && *fb == 0.0;
        }
    }
    for img in outputs
        .iter()
        .filter_map(|o| o.3.as_ref().map(|m| &m.color))
        .chain(peer_out.iter().filter_map(|o| o.3.as_ref()))
    {
        for (k, px) in img.as_slice().iter().enumerate() {
            mask[k] &= positive(px);
        }
    }
    let bright = brightest_80(&reference, &mask);
    let row = |method: &str, response_ms: f64, merge_ms: f64, out: Option<&ColorImage>| Row {
        method: method.to_string(),
        response_ms,
        merge_ms,
        err: out.and_then(|o| log_error(o, &reference, &mask)),
        err_bright: out.and_then(|o| log_error(o, &reference, &bright)),
    };
    let mut rows = Vec::new();
    for (label, r, m, out) in &outputs {
        rows.push(row(label, *r, *m, out.as_ref().map(|o| &o.color)));
    }
    for (label, r, m, out) in &peer_out {
        rows.push(row(label, *r, *m, out.as_ref()));
    }
    if !repair_note.is_empty() {
        let _ = writeln!(s, "{repair_note}\n");
    }
    let _ = writeln!(
        s,
        "Loading the 16 PNGs: {load_ms:.0} ms. Pixels compared: valid in `memorial.hdr` and in every \
         output, and not a fallback pixel (saturated or black in every exposure) of the masked merge.\n"
    );
    s.push_str(&table(
        &rows,
        "Debevec's `memorial.hdr` (his own merge of the same scans, not ground truth)",
    ));
    (s, note)
}

/// The image files a list names (for the peer), in order.
fn load_list_files(list: &Path) -> Vec<PathBuf> {
    let text = std::fs::read_to_string(list).unwrap_or_default();
    depthgraph::nodes::camera::hdr::parse_bracket_list(&text, list)
        .map(|v| v.into_iter().map(|e| e.0).collect())
        .unwrap_or_default()
}

fn speed(peers: Option<&Path>, repeats: usize) -> (String, f64, Option<String>) {
    let (w, h) = (640, 480);
    let mut s = String::from(
        "\n## 3 exposures at 640x480 (synthetic tabletop, stops -2, 0, +2, gamma 2.2)\n\n",
    );
    let Some(scene) = Scene::preset("tabletop", w, h) else {
        return (s, f64::NAN, None);
    };
    let truth = render(&scene, &RenderOptions::default()).color;
    let bp = BracketParams {
        stops: vec![-2.0, 0.0, 2.0],
        seed: 1,
        ..Default::default()
    };
    let stack = match simulate_bracket(&truth, &bp) {
        Ok(st) => st,
        Err(e) => {
            let _ = writeln!(s, "Simulation failed: {e}");
            return (s, f64::NAN, None);
        }
    };
    let rp = ResponseParams::default();
    let (curve, rec_ms) = median_ms(repeats, || recover_response(&stack, &rp));
    let Some(Ok(curve)) = curve else {
        let _ = writeln!(s, "Recovery failed.");
        return (s, f64::NAN, None);
    };
    let (merged, merge_ms) = median_ms(repeats, || merge_hdr(&stack, &curve));
    let gamma = ResponseCurve::gamma(bp.gamma);
    let (given, given_ms) = median_ms(repeats, || merge_hdr(&stack, &gamma));
    let mut note = None;
    let mut peer_out = Vec::new();
    if let Some(pd) = peers {
        let mut ok = true;
        for (j, img) in stack.images.iter().enumerate() {
            let bytes: Vec<u8> = img
                .as_slice()
                .iter()
                .flat_map(|p| p.map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8))
                .collect();
            ok &= std::fs::write(pd.join(format!("speed.{j}.u8")), bytes).is_ok();
        }
        let json =
            serde_json::json!({ "width": w, "height": h, "times": stack.times_s }).to_string();
        ok &= std::fs::write(pd.join("speed.json"), json).is_ok();
        if ok {
            (note, peer_out) = run_and_read_peers(pd, "speed", w, h);
        }
    }
    // pixels: lit (truth > 0), valid in every output, and not saturated or
    // black in all three exposures
    let mut mask: Vec<bool> = truth.as_slice().iter().map(positive).collect();
    if let Some(Ok(m)) = &merged {
        for (k, fb) in m.fallback.as_slice().iter().enumerate() {
            mask[k] &= *fb == 0.0;
        }
    }
    let ours =
        [&merged, &given].map(|m| m.as_ref().and_then(|m| m.as_ref().ok()).map(|m| &m.color));
    for img in ours
        .iter()
        .flatten()
        .copied()
        .chain(peer_out.iter().filter_map(|o| o.3.as_ref()))
    {
        for (k, px) in img.as_slice().iter().enumerate() {
            mask[k] &= positive(px);
        }
    }
    let bright = brightest_80(&truth, &mask);
    let row = |method: String, response_ms: f64, merge_ms: f64, out: Option<&ColorImage>| Row {
        method,
        response_ms,
        merge_ms,
        err: out.and_then(|o| log_error(o, &truth, &mask)),
        err_bright: out.and_then(|o| log_error(o, &truth, &bright)),
    };
    let mut rows = vec![
        row(
            format!(
                "depthgraph HdrMerge, recovered ({} samples, lambda {})",
                rp.samples, rp.lambda
            ),
            rec_ms,
            merge_ms,
            ours[0],
        ),
        row(
            "depthgraph HdrMerge, given gamma 2.2 (no recovery)".into(),
            0.0,
            given_ms,
            ours[1],
        ),
    ];
    let mut ratios = Vec::new();
    for (label, r, m, out) in &peer_out {
        if *m > 0.0 {
            ratios.push((label.clone(), merge_ms / m)); // guard: m > 0
        }
        rows.push(row(label.clone(), *r, *m, out.as_ref()));
    }
    s.push_str(&table(&rows, "the exact synthetic radiance"));
    for (label, ratio) in &ratios {
        let _ = writeln!(
            s,
            "\n**Merge time, depthgraph / OpenCV MergeDebevec with the curve of {}: {ratio:.2}** (below 1: depthgraph is faster).",
            calibration_of(label)
        );
    }
    let ratio = ratios.first().map_or(f64::NAN, |r| r.1);
    (s, ratio, note)
}

fn main() {
    // cargo bench passes --bench; accept and ignore harness flags
    let repeats = 5;
    let peers_on = std::env::var("DEPTHGRAPH_PEERS")
        .map(|v| v != "0")
        .unwrap_or(true);
    let (dir, _temp) = peer_dir();
    let peers = if peers_on { dir.as_deref() } else { None };
    let data = shared_data_dir();
    let (mem, note_a) = memorial(&data, peers, repeats);
    let (spd, ratio, note_b) = speed(peers, repeats);
    let peer_note = if !peers_on {
        "OpenCV peers skipped (DEPTHGRAPH_PEERS=0)".to_string()
    } else {
        note_a
            .or(note_b)
            .unwrap_or_else(|| "OpenCV peers did not run".into())
    };
    let mut md = String::from("# HDR merge (Debevec & Malik 1997)\n\n");
    let _ = writeln!(
        md,
        "Regenerate with `cargo bench --bench hdr_memorial` (this file is overwritten). \
         Error: RMS over pixels and channels of `ln(ours) - ln(ref)` minus its mean (per channel, \
         since a recovered response fixes radiance only up to one factor per channel; the \
         one-factor column removes a single offset); the brightest-80 % column leaves out the \
         darkest fifth of the compared pixels (by the reference); slope: least-squares slope of \
         `ln(ours)` on `ln(ref)`, 1 when both span the same range of radiance. OpenCV has no \
         notion of missing pixels and sees the memorial's blue borders as they are. Times: median \
         of {repeats} runs (OpenCV: after one untimed run), release build, \
         same machine and run for every method; response = curve recovery (`recover_response`, \
         `CalibrateDebevec`), merge = eq. 6 (`merge_hdr`, `MergeDebevec`). {peer_note}.\n"
    );
    md.push_str(&mem);
    md.push_str(&spd);
    let out = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("docs/hdr.md");
    match std::fs::write(&out, &md) {
        Ok(()) => eprintln!("wrote {}", out.display()),
        Err(e) => eprintln!("cannot write {}: {e}", out.display()),
    }
    if ratio.is_finite() {
        eprintln!("merge time ratio depthgraph / OpenCV at 640x480 x3: {ratio:.2}");
    }
    println!("{md}");
}
