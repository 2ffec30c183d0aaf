//! Pixel-grid neighbourhoods.

/// The 4-connected neighbours of pixel `i` of a `w x h` grid (row-major),
/// left, right, up, down, those inside the grid.
pub fn neighbours4(i: usize, w: usize, h: usize) -> impl Iterator<Item = usize> {
    let (x, y) = (i % w.max(1), i / w.max(1));
    [
        (x > 0).then(|| i - 1),
        (x + 1 < w).then(|| i + 1),
        (y > 0).then(|| i - w),
        (y + 1 < h).then(|| i + w),
    ]
    .into_iter()
    .flatten()
}

/// The pixel `v.round()` names on an axis of `n` pixels (`f64::round`:
/// halves away from zero), `None` outside `0..n` or for NaN.
///
/// The same index as `v.round()` tested against `0..n`, without the call
/// to libm's `round` that baseline x86-64 (no SSE4.1) makes for it: on the
/// range kept, `v > -0.5` and `v < n - 0.5`, so `v as i64` truncates
/// exactly (`|v| < 2^52`; guard: a larger `n` takes `f64::round`), and
/// `v - trunc(v)` is exact (both lie within 1 of each other).
#[inline]
pub fn round_to_pixel(v: f64, n: usize) -> Option<usize> {
    let hi = n as f64 - 0.5;
    if !(v > -0.5 && v < hi) {
        return None;
    }
    if hi >= 4.0e15 {
        return Some(v.round() as usize);
    }
    let t = v as i64;
    // v > -0.5: t >= 0, and v - t in (-0.5, 1)
    let up = v - t as f64 >= 0.5;
    Some(t as usize + usize::from(up))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_to_pixel_matches_round_and_a_range_test() {
        let reference = |v: f64, n: usize| {
            let r = v.round();
            (r >= 0.0 && r < n as f64).then_some(r as usize)
        };
        let mut cases = vec![
            -0.5,
            -0.49999999999999994,
            -0.0,
            0.0,
            0.49999999999999994,
            0.5,
            1.5,
            2.5,
            9.499999999999998,
            9.5,
            9.500000000000002,
            10.0,
            -1e300,
            1e300,
            f64::INFINITY,
            f64::NEG_INFINITY,
        ];
        let mut s = 0x1234_5678_9abc_def0u64;
        for _ in 0..20000 {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let u = (s >> 11) as f64 / (1u64 << 53) as f64;
            cases.push(u * 24.0 - 7.0);
            cases.push((u * 24.0 - 7.0).round() + 0.5);
        }
        for n in [1usize, 2, 10, 17] {
            for &v in &cases {
                assert_eq!(round_to_pixel(v, n), reference(v, n), "v {v:e}, n {n}");
            }
        }
        assert_eq!(round_to_pixel(f64::NAN, 10), None);
    }
}
