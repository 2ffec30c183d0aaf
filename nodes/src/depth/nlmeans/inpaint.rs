//! Iterative inpainting with confidence propagation (eq. 5).

use std::sync::Arc;

use crate::kit::checks::{param_within, same_size};
use depthgraph_graph::prelude::*;
use rayon::prelude::*;

use super::common::*;
use super::depth_rows::{DepthRows, F32_MAX_PATCH};
use super::inputs::*;
use super::job::PassJob;
use super::params::*;
use super::pass::*;
use super::upsample_pass::{UpsampleJob, cpu_upsample_pass};

// ---------------------------------------------------------------------------
// Inpainting
// ---------------------------------------------------------------------------

/// `runner`'s results for `job`, one per pixel of the grid.
pub(super) fn checked_run(
    runner: &mut dyn PassRunner,
    job: &PassJob,
    progress: &mut dyn FnMut(f32) -> Result<(), NodeError>,
) -> Result<Vec<Option<(f32, f32)>>, NodeError> {
    let out = runner.run(job, progress)?;
    if out.len() != job.w * job.h {
        return Err(NodeError::Internal(format!(
            "an NL-means pass returned {} results for {} pixels",
            out.len(),
            job.w * job.h
        )));
    }
    Ok(out)
}

/// Runs [`PassJob`]s: per pixel, the estimate and confidence of a target
/// (`None` for non-targets and targets without a source), reporting
/// progress in `[0, 1]`. [`CpuPass`] is the CPU's; the GPU backend has its own.
pub trait PassRunner {
    /// One pass.
    fn run(
        &mut self,
        job: &PassJob,
        progress: &mut dyn FnMut(f32) -> Result<(), NodeError>,
    ) -> Result<Vec<Option<(f32, f32)>>, NodeError>;

    /// The first pass of the upsampling (eq. 4), on the CPU unless the
    /// runner has its own.
    fn run_upsample(
        &mut self,
        job: &UpsampleJob,
        progress: &mut dyn FnMut(f32) -> Result<(), NodeError>,
    ) -> Result<Vec<Option<(f32, f32)>>, NodeError> {
        cpu_upsample_pass(job, progress)
    }

    /// The guide of the passes that follow differs from the earlier ones'
    /// (the next scale of a multi-scale upsampling): a runner that keeps
    /// the guide between passes must drop it.
    fn new_guide(&mut self) {}
}

/// The NL-means pass on the CPU (bands of rows in parallel, box sums).
///
/// A runner lives for one call of a stage (one inpainting, one
/// upsampling): it keeps the guide's padded planes from one pass to the
/// next (the iterations of eq. 5 share their guide), dropped by
/// [`PassRunner::new_guide`] and whenever a job's guide, size or padding
/// differs.
#[derive(Default)]
pub struct CpuPass {
    guide: Option<GuideKey>,
}

/// The padded guide a [`CpuPass`] keeps, with what it was built from: the
/// guide slice's address and length, the grid and the padding.
struct GuideKey {
    at: (usize, usize),
    dims: (usize, usize),
    planes: Arc<PaddedGuide>,
}

impl CpuPass {
    /// A runner with nothing kept.
    pub fn new() -> Self {
        Self::default()
    }

    fn guide(&mut self, job: &PassJob, pad: usize) -> Arc<PaddedGuide> {
        let at = (job.guide.as_ptr() as usize, job.guide.len());
        let dims = (job.w, job.h);
        match &self.guide {
            Some(k) if k.at == at && k.dims == dims && k.planes.pad() == pad => k.planes.clone(),
            _ => {
                let planes = Arc::new(PaddedGuide::new(dims, job.guide, pad));
                self.guide = Some(GuideKey {
                    at,
                    dims,
                    planes: planes.clone(),
                });
                planes
            }
        }
    }
}

impl PassRunner for CpuPass {
    fn new_guide(&mut self) {
        self.guide = None;
    }

    fn run(
        &mut self,
        job: &PassJob,
        progress: &mut dyn FnMut(f32) -> Result<(), NodeError>,
    ) -> Result<Vec<Option<(f32, f32)>>, NodeError> {
        let core = Core {
            search: job.search,
            patch: job.patch,
            inv_hc2: job.inv_hc2,
            inv_hd2: job.inv_hd2,
        };
        let guide = self.guide(job, core.patch + core.search);
        let pass = Pass::with_guide((job.w, job.h), guide, Some((job.z, job.c)), core);
        let local_max = job
            .background
            .map(|_| window_max_on(job.z, job.c, (job.w, job.h), job.search, Some(job.targets)));
        let kernel = DepthKernel {
            z: job.z,
            c: job.c,
            inv_hd2: job.inv_hd2,
            far: job.far,
            background: job
                .background
                .zip(local_max.as_deref())
                .map(|((beta, tau), m)| (beta, tau, m)),
        };
        let mut out = vec![None; job.w * job.h];
        // The vectorised rows first; targets they hand back (every weight
        // near underflow) again with the running maximum.
        let mut exact = vec![false; job.w * job.h];
        let mut any_exact = false;
        let sink = |i: usize, r: Finish| match r {
            Finish::Done(v) => out[i] = v,
            Finish::Exact => {
                exact[i] = true;
                any_exact = true;
            }
        };
        // The f32 rows (eight lanes where f64 has four) for patches up to
        // F32_MAX_PATCH (their bound is stated for r <= 2; `depth_rows`),
        // the f64 rows otherwise. A target the f32 rows hand back (every
        // weight below f32's range: 1.3k hole fills of 77k holes on a
        // Kinect frame, all iterations together; in denoising only targets
        // of confidence 0) runs again in the f64 rows, and what those hand
        // back with the running maximum.
        let search = core.search;
        let f64_rows = DepthRows::<f64>::new(&kernel, search);
        if job.patch <= F32_MAX_PATCH {
            run_pass(
                &pass,
                job.targets,
                &DepthRows::<f32>::new(&kernel, search),
                progress,
                sink,
            )?;
            if any_exact {
                let again = std::mem::replace(&mut exact, vec![false; job.w * job.h]);
                any_exact = false;
                run_pass(
                    &pass,
                    &again,
                    &f64_rows,
                    &mut |_| progress(1.0),
                    |i, r| match r {
                        Finish::Done(v) => out[i] = v,
                        Finish::Exact => {
                            exact[i] = true;
                            any_exact = true;
                        }
                    },
                )?;
            }
        } else {
            run_pass(&pass, job.targets, &f64_rows, progress, sink)?;
        }
        if any_exact {
            // progress stays at 1; cancellation is still checked every wave
            run_pass(
                &pass,
                &exact,
                &PerPair(&kernel),
                &mut |_| progress(1.0),
                |i, r| {
                    if let Finish::Done(v) = r {
                        out[i] = v;
                    }
                },
            )?;
        }
        Ok(out)
    }
}

/// [`window_max_on`] on every row (tests).
#[cfg(test)]
pub(super) fn window_max(z: &[f32], c: &[f32], w: usize, h: usize, r: usize) -> Vec<f32> {
    window_max_on(z, c, (w, h), r, None)
}

/// The largest source depth (confidence > 0) in the `(2r+1)^2` window of
/// every pixel, clipped to the image (the candidates of a pass); 0 where
/// the window holds no source. Separable: a row pass ([`window_max_row`]),
/// then a column pass. With `targets`, only the rows holding a target are
/// computed (0 elsewhere): the later iterations of an inpainting have few;
/// `None` computes every row.
pub(super) fn window_max_on(
    z: &[f32],
    c: &[f32],
    (w, h): (usize, usize),
    r: usize,
    targets: Option<&[bool]>,
) -> Vec<f32> {
    if w == 0 || h == 0 {
        return Vec::new();
    }
    let src = |i: usize| {
        if c[i] > 0.0 && z[i].is_finite() {
            z[i]
        } else {
            0.0
        }
    };
    // rows holding a target, and the rows their windows read
    let wanted: Vec<bool> = match targets {
        Some(t) => t.par_chunks(w).map(|row| row.iter().any(|t| *t)).collect(),
        None => vec![true; h],
    };
    let mut read = vec![false; h];
    for (y, _) in wanted.iter().enumerate().filter(|(_, t)| **t) {
        read[y.saturating_sub(r)..(y + r + 1).min(h)].fill(true);
    }
    // rows in parallel, then the columns of every output row in parallel
    let mut rows = vec![0.0f32; w * h];
    rows.par_chunks_mut(w).enumerate().for_each_init(
        || (vec![0.0f32; w], vec![0.0f32; w], vec![0.0f32; w]),
        |(row, pre, suf), (y, out)| {
            if !read[y] {
                return;
            }
            for (x, v) in row.iter_mut().enumerate() {
                *v = src(y * w + x);
            }
            window_max_row(row, r, pre, suf, out);
        },
    );
    let mut out = vec![0.0f32; w * h];
    out.par_chunks_mut(w).enumerate().for_each(|(y, o)| {
        if !wanted[y] {
            return;
        }
        let (a, b) = (y.saturating_sub(r), (y + r + 1).min(h));
        o.copy_from_slice(&rows[a * w..(a + 1) * w]);
        for yy in a + 1..b {
            for (m, v) in o.iter_mut().zip(&rows[yy * w..(yy + 1) * w]) {
                *m = m.max(*v);
            }
        }
    });
    out
}

/// `out[x] = max(row[x - r..=x + r])`, the window clipped to the row, for
/// values >= 0, in three comparisons per value whatever `r` (van Herk's
/// and Gil-Werman's blocks of `2r + 1`: a window spans at most two
/// blocks, the suffix maximum of the first and the prefix maximum of the
/// second; one clipped at the row's start begins a block, one clipped at
/// its end ends one). `pre` and `suf` are scratch of the row's length.
fn window_max_row(row: &[f32], r: usize, pre: &mut [f32], suf: &mut [f32], out: &mut [f32]) {
    let w = row.len();
    let k = 2 * r + 1;
    for ((rb, pb), sb) in row.chunks(k).zip(pre.chunks_mut(k)).zip(suf.chunks_mut(k)) {
        let mut m = 0.0f32;
        for (v, p) in rb.iter().zip(pb.iter_mut()) {
            m = m.max(*v);
            *p = m;
        }
        let mut m = 0.0f32;
        for (v, s) in rb.iter().zip(sb.iter_mut()).rev() {
            m = m.max(*v);
            *s = m;
        }
    }
    for (x, o) in out.iter_mut().enumerate() {
        let (a, b) = (x.saturating_sub(r), (x + r).min(w - 1));
        *o = if a / k != b / k {
            suf[a].max(pre[b])
        } else if a % k == 0 {
            pre[b]
        } else {
            suf[a]
        };
    }
}

/// Holes that have a source (confidence > 0) within `r` pixels (Chebyshev),
/// from a summed-area table of the sources.
pub(super) fn reachable_holes(z: &[f32], c: &[f32], w: usize, h: usize, r: usize) -> Vec<bool> {
    let mut sat = vec![0u32; (w + 1) * (h + 1)];
    for y in 0..h {
        let mut row = 0u32;
        for x in 0..w {
            row += (c[y * w + x] > 0.0) as u32;
            sat[(y + 1) * (w + 1) + x + 1] = sat[y * (w + 1) + x + 1] + row;
        }
    }
    (0..w * h)
        .map(|i| {
            if z[i] > 0.0 {
                return false;
            }
            let (x, y) = (i % w, i / w);
            let (x0, y0) = (x.saturating_sub(r), y.saturating_sub(r));
            let (x1, y1) = ((x + r + 1).min(w), (y + r + 1).min(h));
            let s = sat[y1 * (w + 1) + x1] + sat[y0 * (w + 1) + x0]
                - sat[y0 * (w + 1) + x1]
                - sat[y1 * (w + 1) + x0];
            s > 0
        })
        .collect()
}

/// The iterations of eq. 5 on `(z, c)` in place (Jacobi: each iteration
/// reads the previous state). Returns the number of iterations run.
#[allow(clippy::too_many_arguments)]
pub(super) fn inpaint_state(
    z: &mut [f32],
    c: &mut [f32],
    guide: &[[f32; 3]],
    w: usize,
    h: usize,
    core: Core,
    iterations: usize,
    far_prior: bool,
    background: Option<(f64, f64)>,
    progress: &mut dyn FnMut(f32) -> Result<(), NodeError>,
    runner: &mut dyn PassRunner,
) -> Result<usize, NodeError> {
    let z_ref = z
        .iter()
        .zip(c.iter())
        .filter(|(_, c)| **c > 0.0)
        .fold(0.0f64, |m, (z, _)| m.max(*z as f64));
    // Guard: only with a positive reference depth.
    let far = (far_prior && z_ref > 0.0).then(|| 1.0 / z_ref);
    let mut done = 0;
    for it in 0..iterations {
        let targets = reachable_holes(z, c, w, h, core.search);
        if !targets.iter().any(|t| *t) {
            break;
        }
        let mut filled = 0usize;
        let pk = PatchKernel::new(core.patch);
        let job = PassJob::new(
            (w, h),
            guide,
            (z, c),
            (&targets, false),
            core,
            &pk,
            (far, background),
        );
        // Guard: iterations >= 1 inside the loop.
        let scale = 1.0 / iterations as f32;
        let mut sub = |f: f32| progress((it as f32 + f) * scale);
        // Jacobi: the pass reads the previous state (the job borrows it),
        // the results go in once it is done.
        let results = checked_run(runner, &job, &mut sub)?;
        for (i, r) in results.into_iter().enumerate() {
            if let (true, Some((v, conf))) = (targets[i], r) {
                z[i] = v;
                c[i] = conf;
                filled += 1;
            }
        }
        done = it + 1;
        if filled == 0 {
            break;
        }
    }
    Ok(done)
}

/// Iterative NL-means inpainting with confidence propagation (eq. 5): each
/// iteration estimates every hole that has known pixels within
/// `search_radius` from them (eq. 1 with the weights of [`nlmeans_filter`](crate::depth::nlmeans::nlmeans_filter),
/// the depth patch term counting only known pixels), and gives it the
/// confidence `sum_j s(i, j) zeta(j) / sum_j s(i, j)` (the normalisation
/// `Z_i` relative to a fully known window), so confidence decays into the
/// hole and later iterations weight the reliable border more. Iterations
/// stop when no hole is left, an iteration fills nothing, or after
/// `iterations`; holes larger than a patch fill from the outside in.
///
/// With `far_prior` each weight is multiplied by `(z_j / z_max)^2`, `z_max`
/// the largest known depth, favouring the background (Sec. 2.3: holes
/// opened by a change of viewpoint belong to the background).
///
/// With `background = β > 0` (the default) each weight of eq. 5 is also
/// multiplied by `exp(-β max(0, (z_w - z_j) / z_w - τ))`, `z_w` the largest
/// known depth in the target's search window and `τ = edge_step`: a source
/// more than `τ` (relative) nearer than the window's farthest lies across
/// an occlusion edge, and a hole beside such an edge (a projector shadow,
/// flying pixels) is background by construction. Sources on one surface
/// (steps below `τ`) keep their weights; the farthest source keeps factor
/// 1, so an estimate exists wherever one did without the bias.
///
/// Valid input pixels are never changed (nor their confidence). Holes that
/// cannot be reached stay 0 with confidence 0 (e.g. an input without any
/// valid pixel). Filled values lie within the range of the valid inputs.
///
/// ```
/// use depthgraph_nodes::depth::nlmeans::{nlmeans_inpaint, NLMeansInpaintParams};
/// use depthgraph_graph::value::{ColorImage, DepthMap};
/// let depth = DepthMap::from_fn(20, 3, |x, _| if x < 4 { 1.0 } else if x < 16 { 0.0 } else { 3.0 });
/// let color = ColorImage::filled(20, 3, [0.5; 3]);
/// let (d, c) = nlmeans_inpaint(&depth, None, &color, &NLMeansInpaintParams::default()).unwrap();
/// assert_eq!(d.hole_count(), 0);
/// assert!(d.as_slice().iter().all(|z| (1.0..=3.0).contains(z)));
/// assert!(*c.get(10, 1) > 0.0 && *c.get(10, 1) < 1.0);
/// assert_eq!(*c.get(0, 0), 1.0);
/// ```
pub fn nlmeans_inpaint(
    depth: &DepthMap,
    confidence: Option<&Confidence>,
    guide_color: &ColorImage,
    p: &NLMeansInpaintParams,
) -> Result<(DepthMap, Confidence), NodeError> {
    nlmeans_inpaint_with(depth, confidence, guide_color, p, |_| Ok(()))
}

/// [`nlmeans_inpaint`] that calls `on_progress(fraction)` now and then and
/// stops with its error when it returns one (cancellation).
pub fn nlmeans_inpaint_with(
    depth: &DepthMap,
    confidence: Option<&Confidence>,
    guide_color: &ColorImage,
    p: &NLMeansInpaintParams,
    on_progress: impl FnMut(f32) -> Result<(), NodeError>,
) -> Result<(DepthMap, Confidence), NodeError> {
    nlmeans_inpaint_on(
        depth,
        confidence,
        guide_color,
        p,
        on_progress,
        &mut CpuPass::new(),
    )
}

/// [`nlmeans_inpaint_with`] with its passes run by `runner` (another
/// backend); everything else (the checks, the targets of each iteration,
/// the stopping rule) is this function's.
pub fn nlmeans_inpaint_on(
    depth: &DepthMap,
    confidence: Option<&Confidence>,
    guide_color: &ColorImage,
    p: &NLMeansInpaintParams,
    mut on_progress: impl FnMut(f32) -> Result<(), NodeError>,
    runner: &mut dyn PassRunner,
) -> Result<(DepthMap, Confidence), NodeError> {
    let core = Core::new(p.search_radius, p.patch_radius, p.h_color, p.h_depth)?;
    if core.search == 0 {
        return Err(NodeError::param("search_radius", "must be at least 1"));
    }
    param_within("background", p.background, 0.0, 1000.0)?;
    param_within("edge_step", p.edge_step, 0.001, 1.0)?;
    same_size(
        "color",
        "a guide image",
        guide_color.dims(),
        "the depth map",
        depth.dims(),
    )?;
    check_confidence(confidence, depth)?;
    let (w, h) = depth.dims();
    let (mut z, mut c) = sanitize(depth, confidence);
    let guide = guide_features(guide_color);
    inpaint_state(
        &mut z,
        &mut c,
        &guide,
        w,
        h,
        core,
        p.iterations,
        p.far_prior,
        (p.background > 0.0).then_some((p.background, p.edge_step)),
        &mut on_progress,
        runner,
    )?;
    Ok((image(w, h, z)?, image(w, h, c)?))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The window maximum by its definition: every pixel's clipped
    /// `(2r+1)^2` window, sources only (0 where there is none).
    fn brute(z: &[f32], c: &[f32], (w, h): (usize, usize), r: usize) -> Vec<f32> {
        (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                let mut m = 0.0f32;
                for yy in y.saturating_sub(r)..(y + r + 1).min(h) {
                    for xx in x.saturating_sub(r)..(x + r + 1).min(w) {
                        let j = yy * w + xx;
                        if c[j] > 0.0 && z[j].is_finite() {
                            m = m.max(z[j]);
                        }
                    }
                }
                m
            })
            .collect()
    }

    #[test]
    fn the_window_maximum_is_the_maximum_of_every_clipped_window() {
        let mut s = 17u64;
        let mut next = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (s >> 11) as f64 / (1u64 << 53) as f64
        };
        for (w, h) in [(1, 1), (3, 2), (7, 5), (23, 9), (40, 13)] {
            let z: Vec<f32> = (0..w * h).map(|_| (10.0 * next()) as f32).collect();
            let c: Vec<f32> = (0..w * h)
                .map(|_| if next() < 0.3 { 0.0 } else { 1.0 })
                .collect();
            // rows with a target: every other one
            let targets: Vec<bool> = (0..w * h).map(|i| (i / w) % 2 == 0).collect();
            for r in [0, 1, 2, 5, 11, 30] {
                let want = brute(&z, &c, (w, h), r);
                assert_eq!(window_max(&z, &c, w, h, r), want, "{w}x{h} r {r}");
                let on = window_max_on(&z, &c, (w, h), r, Some(&targets));
                for i in 0..w * h {
                    let expect = if targets[i] { want[i] } else { 0.0 };
                    assert_eq!(on[i], expect, "{w}x{h} r {r} pixel {i}");
                }
            }
        }
    }
}
