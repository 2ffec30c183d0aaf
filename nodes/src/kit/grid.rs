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
