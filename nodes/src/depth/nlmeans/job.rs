//! One NL-means pass as flat buffers: what a backend (the CPU's runner, the
//! GPU's) needs to run eq. 1, 3 and 5 over a grid.

use super::params::*;
use super::pass::*;

/// One NL-means pass of the inpainting, for a backend that runs it
/// elsewhere (the GPU): every input of eq. 1, 3 and 5 as flat buffers.
#[derive(Debug, Clone, Copy)]
pub struct PassJob<'a> {
    /// Grid width.
    pub w: usize,
    /// Grid height.
    pub h: usize,
    /// Guide features per pixel (`sqrt(c / (1 + c))` per channel).
    pub guide: &'a [[f32; 3]],
    /// Depth, 0 for holes.
    pub z: &'a [f32],
    /// Confidence, 0 for holes.
    pub c: &'a [f32],
    /// The pixels to estimate.
    pub targets: &'a [bool],
    /// Every target holds depth (denoising; no hole among them): its own
    /// term, weighed by its confidence, keeps its weights from
    /// underflowing, so a runner may compute them in f32 (see
    /// `depth_rows`); a target of confidence 0 whose weights underflow all
    /// the same is handed back and run in f64. Holes being inpainted
    /// (false) would be handed back too often for f32 to pay.
    pub targets_are_sources: bool,
    /// Search radius (candidates in a `(2R+1)^2` window inside the image).
    pub search: usize,
    /// Patch radius `r` (patch pixels at clamped coordinates).
    pub patch: usize,
    /// Radii of the nested boxes of the patch kernel.
    pub radii: &'a [usize],
    /// Weight of one pixel of each box.
    pub coef: &'a [f64],
    /// Per-pixel distances are capped here.
    pub cap: f64,
    /// `1 / h_color^2`.
    pub inv_hc2: f64,
    /// `1 / h_depth^2`.
    pub inv_hd2: f64,
    /// `1 / z_ref` of the far-depth prior, when on.
    pub far: Option<f64>,
    /// The background side, when on: strength `β` and edge step `τ`; each
    /// weight times `exp(-β max(0, (z_max - z_j) / z_max - τ))` with `z_max`
    /// the largest source depth in the target's search window.
    pub background: Option<(f64, f64)>,
}

impl<'a> PassJob<'a> {
    /// The job of a pass over the `(w, h)` grid.
    pub(super) fn new(
        (w, h): (usize, usize),
        guide: &'a [[f32; 3]],
        (z, c): (&'a [f32], &'a [f32]),
        (targets, targets_are_sources): (&'a [bool], bool),
        core: Core,
        pk: &'a PatchKernel,
        (far, background): (Option<f64>, Option<(f64, f64)>),
    ) -> Self {
        Self {
            w,
            h,
            guide,
            z,
            c,
            targets,
            targets_are_sources,
            search: core.search,
            patch: core.patch,
            radii: &pk.radii,
            coef: &pk.coef,
            cap: pk.cap,
            inv_hc2: core.inv_hc2,
            inv_hd2: core.inv_hd2,
            far,
            background,
        }
    }
}
