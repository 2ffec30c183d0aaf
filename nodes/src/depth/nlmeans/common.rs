//! What every stage shares: band sizes, cut-offs, limits, the confidence check.

use crate::kit::checks::same_size;
use depthgraph_graph::prelude::*;

/// Rows per band of the parallel passes (fixed, so results do not depend on
/// the number of threads).
pub(super) const BAND_ROWS: usize = 32;
/// Columns per tile of the parallel passes (a band of rows is cut into
/// tiles; tiles without a target are skipped).
pub(super) const TILE_COLS: usize = 128;
/// Rows and columns of the smaller tiles a sparse tile is cut into.
pub(super) const SPARSE_ROWS: usize = 8;
pub(super) const SPARSE_COLS: usize = 32;
/// Tiles processed between two progress reports / cancellation checks.
pub(super) const WAVE_TILES: usize = 32;
/// `exp(-x)` is exactly 0 in f64 for `x >= EXP_CUTOFF`: per-pixel patch
/// distances are capped at `EXP_CUTOFF / (smallest patch kernel weight)`,
/// which changes no weight (a capped pixel alone makes the patch distance
/// at least `EXP_CUTOFF`) and bounds the running sums.
pub(super) const EXP_CUTOFF: f64 = 746.0;
/// Largest accepted `search_radius`.
pub const MAX_SEARCH_RADIUS: usize = 30;
/// Largest accepted `patch_radius`.
pub const MAX_PATCH_RADIUS: usize = 10;
/// "No sample" in the upsampling's sample map.
pub(super) const NO_SAMPLE: usize = usize::MAX;

/// An optional confidence map must have the depth map's size.
pub(super) fn check_confidence(
    confidence: Option<&Confidence>,
    depth: &DepthMap,
) -> Result<(), NodeError> {
    match confidence {
        Some(c) => same_size(
            "confidence",
            "a confidence map",
            c.dims(),
            "the depth map",
            depth.dims(),
        ),
        None => Ok(()),
    }
}
