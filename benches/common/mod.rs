//! Timing helpers shared by the benchmarks (each bench uses a subset).
#![allow(dead_code)]

use std::time::Instant;

/// An environment variable parsed as a count, or `default`.
pub fn env_usize(name: &str, default: usize) -> usize {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// Median of `v` (the upper middle for an even count); NaN when empty.
pub fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Runs `f` `repeats` times (at least once); its last result and the median
/// wall time in milliseconds.
pub fn timed<T>(repeats: usize, mut f: impl FnMut() -> T) -> (T, f64) {
    let ms = |t: Instant| t.elapsed().as_secs_f64() * 1e3;
    let t = Instant::now();
    let mut out = f();
    let mut times = vec![ms(t)];
    for _ in 1..repeats.max(1) {
        let t = Instant::now();
        out = f();
        times.push(ms(t));
    }
    (out, median(times))
}

/// Times `a` and `b` alternately, `repeats` times each (at least once), so
/// that both see the same machine: `b`'s last result, the median wall
/// times in milliseconds and the ratio `b / a` of the medians (the figure
/// to report; one noisy stretch of the machine no longer lands on one side
/// only).
pub fn timed_pair<A, B>(
    repeats: usize,
    mut a: impl FnMut() -> A,
    mut b: impl FnMut() -> B,
) -> (B, f64, f64, f64) {
    let ms = |t: Instant| t.elapsed().as_secs_f64() * 1e3;
    let mut pair = || {
        let t = Instant::now();
        std::hint::black_box(a());
        let ta = ms(t);
        let t = Instant::now();
        let out = b();
        (out, ta, ms(t))
    };
    let (mut last, t0a, t0b) = pair();
    let (mut ta, mut tb) = (vec![t0a], vec![t0b]);
    for _ in 1..repeats.max(1) {
        let (out, x, y) = pair();
        last = out;
        ta.push(x);
        tb.push(y);
    }
    let (ma, mb) = (median(ta), median(tb));
    (last, ma, mb, mb / ma)
}

/// Writes a frame for an OpenCV peer script: `DIR/<case>.depth.f32`
/// (little-endian f32, row-major) and `DIR/<case>.color.u8` (sRGB 8-bit RGB).
pub fn write_peer_frame(
    dir: &std::path::Path,
    case: &str,
    depth: &depthgraph::graph::value::DepthMap,
    color: &depthgraph::graph::value::ColorImage,
) -> std::io::Result<()> {
    let z: Vec<u8> = depth
        .as_slice()
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    std::fs::write(dir.join(format!("{case}.depth.f32")), z)?;
    let rgb: Vec<u8> = color
        .as_slice()
        .iter()
        .flat_map(|c| c.map(depthgraph::nodes::kit::color::srgb8))
        .collect();
    std::fs::write(dir.join(format!("{case}.color.u8")), rgb)
}
