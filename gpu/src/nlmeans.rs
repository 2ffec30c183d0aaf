//! `NLMeansInpaint`, `NLMeansDepth` and `NLMeansUpsample` on the device
//! (for NLMeansUpsample: the placement of the samples on the CPU, the first
//! pass of eq. 4 in `shaders/nlmeans_upsample.wgsl`, the inpainting of what
//! it leaves through the same pass as NLMeansInpaint; for NLMeansDepth: the
//! pruning on the CPU, the filter's one pass on the device, targets the
//! valid pixels, a pixel without a source keeping its input with
//! confidence 0, as on the CPU). For the inpainting each iteration's pass runs on the
//! device (`shaders/nlmeans.wgsl`); the iterations, their targets (the
//! reachable holes) and the stopping rule are the CPU's
//! [`nlmeans_inpaint_on`], so both backends fill the same pixels in the
//! same iteration.
//!
//! **Agreement with the CPU** (checked by the parity tests): the same
//! filled pixels (hole masks identical), and filled depths within
//! [`REL_TOL`] relative, confidences within [`REL_TOL`] absolute. The
//! device sums in f32 (the patch distances compensated), the CPU in f64;
//! weights `exp(-d)` carry the distances' rounding (a few ulps of a
//! distance of order 10), so an estimate moves by about 1e-6 of the spread
//! of the depths it averages (measured: at most 8e-7 z, confidences 4e-7; the upsampling's log-domain
//! blend of eq. 4 adds a few ulps: 3.9e-7 z, 3.0e-7). The device keeps the
//! weights of eq. 1 in the log domain (similarity, confidence and prior as
//! one exponent, relative to the largest), so a weight whose f32 factors
//! would underflow still counts where the CPU's f64 product does not
//! underflow: with `background` 400 both fill the same pixels (measured
//! 2.5e-6 z: the exponents reach a few hundred). The sets could differ
//! only where the CPU's f64 product itself underflows (below ~1e-308).

use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use depthgraph_graph::ports::Produced;
use depthgraph_graph::prelude::*;
use depthgraph_nodes::depth::nlmeans::{
    NLMeansDepthParams, NLMeansIn, NLMeansInpaintParams, NLMeansOut, NLMeansUpsampleParams,
    PassJob, PassRunner, UpsampleIn, UpsampleJob, UpsampleOut, inpaint_passthrough,
    nlmeans_denoise_on, nlmeans_inpaint_on, nlmeans_upsample_on,
};

use crate::context::PooledBuffer;
use crate::session::{Session, bytes_of, f32s};
use crate::shaders;

/// Patch-pixel comparisons one pass may ask of the device (beyond it a
/// driver's watchdog may reset the device mid-dispatch): about a second on
/// a current GPU.
const MAX_WORK: f64 = 2e11;

/// The parity check's bound: filled depths `|Δz| <= REL_TOL z`,
/// confidences `|Δc| <= REL_TOL`.
pub const REL_TOL: f64 = 1e-5;

/// The grid and patch kernel of a pass: the first member of both kernels'
/// uniforms (`Patch` in `shaders/nlmeans_acc.wgsl`, field for field).
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct PatchUniform {
    w: u32,
    h: u32,
    search: u32,
    patch: u32,
    r: [u32; 3],
    n_boxes: u32,
    coef: [f32; 3],
    cap: f32,
    inv_hc2: f32,
    inv_hd2: f32,
    pad: [f32; 2],
}

impl PatchUniform {
    /// The fields of `job` (at most three boxes: [`check_job`]).
    fn of(job: &PassJob) -> Self {
        let r = |k: usize| job.radii.get(k).copied().unwrap_or(0) as u32;
        let c = |k: usize| job.coef.get(k).copied().unwrap_or(0.0) as f32;
        Self {
            w: job.w as u32,
            h: job.h as u32,
            search: job.search as u32,
            patch: job.patch as u32,
            r: [r(0), r(1), r(2)],
            n_boxes: job.radii.len() as u32,
            coef: [c(0), c(1), c(2)],
            cap: job.cap.min(f32::MAX as f64) as f32,
            inv_hc2: job.inv_hc2 as f32,
            inv_hd2: job.inv_hd2 as f32,
            pad: [0.0; 2],
        }
    }
}

/// `Params` of `shaders/nlmeans.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct Params {
    k: PatchUniform,
    inv_ref: f32,
    far: u32,
    beta: f32,
    tau: f32,
}

/// `Params` of `shaders/nlmeans_upsample.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct UpsampleParams {
    k: PatchUniform,
    lw: u32,
    lh: u32,
    low_patch: u32,
    has_color: u32,
    has_depth: u32,
    inv_low_area: f32,
    ln_alpha: f32,
    ln_one_minus_alpha: f32,
    // the spatial falloff 1 / (2 sigma^2), pixels^-2 (0: none)
    spatial: f32,
    // to a multiple of 16 bytes
    pad: [f32; 3],
}

/// An index of the CPU's (`usize::MAX` for none) as the kernel's `u32`
/// (`u32::MAX` for none); `None` when it does not fit.
fn index_u32(i: usize) -> Option<u32> {
    if i == usize::MAX {
        Some(u32::MAX)
    } else {
        u32::try_from(i).ok().filter(|v| *v != u32::MAX)
    }
}

/// What f32 on the device cannot hold as the CPU does: subnormal depths or
/// confidences (a device may flush them to 0, which would change which
/// pixels are sources) and depths beyond 1e18 m (their squares overflow).
fn outside_f32(v: &f32) -> bool {
    *v != 0.0 && (v.abs() < f32::MIN_POSITIVE || v.abs() > 1e18)
}

/// What every NL-means job must meet on the device: a patch kernel of 1 to
/// 3 boxes; values f32 holds as the CPU does ([`outside_f32`]); at most
/// [`MAX_WORK`] patch-pixel comparisons. A job that fails the last two runs
/// on the CPU (the node falls back as a whole, `explain` says why).
fn check_job(
    s: &mut Session,
    job: &PassJob,
    values: &[&[f32]],
    work: f64,
) -> Result<(), NodeError> {
    if job.radii.is_empty() || job.radii.len() > 3 || job.coef.len() != job.radii.len() {
        return Err(NodeError::Internal(format!(
            "NL-means patch kernel with {} boxes: the device kernel takes 1 to 3",
            job.radii.len()
        )));
    }
    if values.iter().any(|v| v.iter().any(outside_f32)) {
        return Err(s.too_large(
            "depths or confidences outside the device's f32 range (subnormal, or above 1e18)",
        ));
    }
    if work > MAX_WORK {
        return Err(s.too_large(&format!(
            "{work:.1e} patch-pixel comparisons exceed one dispatch's budget ({MAX_WORK:.0e})"
        )));
    }
    Ok(())
}

/// The guide features on the device, uploaded on first use: every pass of a
/// node (the upsampling's and each inpainting iteration's) reads the same.
fn guide_on_device<'g>(
    slot: &'g mut Option<(usize, PooledBuffer)>,
    s: &mut Session,
    guide: &[[f32; 3]],
) -> Result<&'g PooledBuffer, NodeError> {
    // a kept guide of another pixel count is another image's
    if slot.as_ref().is_some_and(|(n, _)| *n != guide.len()) {
        return Err(NodeError::Internal(
            "an NL-means pass met a guide of another size than the one on the device".into(),
        ));
    }
    if slot.is_none() {
        let g: Vec<[f32; 4]> = guide.iter().map(|g| [g[0], g[1], g[2], 0.0]).collect();
        *slot = Some((guide.len(), s.upload(bytes_of(&g))?));
    }
    slot.as_ref()
        .map(|(_, b)| b)
        .ok_or_else(|| NodeError::Internal("no guide on the device".into()))
}

/// One dispatch of an NL-means kernel over the `w x h` grid, bound to
/// `inputs` then its result buffer (`(estimate, confidence, found, 0)` per
/// pixel), read back as the runner's results.
fn one_pass(
    s: &mut Session,
    kernel: &wgpu::ComputePipeline,
    inputs: &[&wgpu::Buffer],
    (w, h): (usize, usize),
) -> Result<Vec<Option<(f32, f32)>>, NodeError> {
    let size = 16 * (w * h) as u64;
    let out = s.scratch(size)?;
    let mut binds = inputs.to_vec();
    binds.push(&out);
    let bg = s.bind(kernel, &binds);
    let encoder = s.image_passes(&[(kernel, &bg)], (w, h));
    let back = s.finish(encoder, &[(&out, size)])?;
    Ok(f32s(&back[0])
        .chunks_exact(4)
        .map(|r| (r[2] > 0.0).then_some((r[0], r[1])))
        .collect())
}

/// The passes on the device; the guide is uploaded once for all of them.
struct DeviceRunner<'s, 'c> {
    s: &'s mut Session<'c>,
    /// The guide's pixel count and its buffer.
    guide: Option<(usize, PooledBuffer)>,
}

impl PassRunner for DeviceRunner<'_, '_> {
    fn new_guide(&mut self) {
        self.guide = None;
    }

    fn run(
        &mut self,
        job: &PassJob,
        progress: &mut dyn FnMut(f32) -> Result<(), NodeError>,
    ) -> Result<Vec<Option<(f32, f32)>>, NodeError> {
        let s = &mut *self.s;
        let (w, h) = (job.w, job.h);
        s.check_grid(w, h, 8)?;
        let n = w * h;
        let window = (2 * job.search + 1).pow(2) as f64 * (2 * job.patch + 1).pow(2) as f64;
        let targets = job.targets.iter().filter(|t| **t).count() as f64;
        check_job(s, job, &[job.z, job.c], window * targets)?;
        let params = Params {
            k: PatchUniform::of(job),
            inv_ref: job.far.unwrap_or(0.0) as f32,
            far: u32::from(job.far.is_some()),
            beta: job.background.map_or(0.0, |b| b.0 as f32),
            tau: job.background.map_or(0.0, |b| b.1 as f32),
        };
        let guide = guide_on_device(&mut self.guide, s, job.guide)?;
        let zc: Vec<[f32; 2]> = job.z.iter().zip(job.c).map(|(&z, &c)| [z, c]).collect();
        let targets: Vec<u32> = job.targets.iter().map(|&t| u32::from(t)).collect();
        if job.z.len() != n || job.c.len() != n || job.guide.len() != n || targets.len() != n {
            return Err(NodeError::Internal(
                "NL-means pass buffers of another size than the grid".into(),
            ));
        }
        let kernel = s.kernel(&shaders::NLMEANS)?;
        let uniform = s.uniform(bytemuck::bytes_of(&params))?;
        let zc_buf = s.upload(bytes_of(&zc))?;
        let t_buf = s.upload(bytes_of(&targets))?;
        let out = one_pass(s, &kernel, &[&uniform, guide, &zc_buf, &t_buf], (w, h))?;
        progress(1.0)?;
        Ok(out)
    }

    fn run_upsample(
        &mut self,
        job: &UpsampleJob,
        progress: &mut dyn FnMut(f32) -> Result<(), NodeError>,
    ) -> Result<Vec<Option<(f32, f32)>>, NodeError> {
        let s = &mut *self.s;
        let p = &job.pass;
        let (w, h) = (p.w, p.h);
        let (lw, lh) = job.low;
        s.check_grid(w, h, 8)?;
        let n = w * h;
        if p.guide.len() != n
            || job.sample_at.len() != n
            || job.lo_col.len() != w
            || job.lo_row.len() != h
            || job.lz.len() != lw * lh
            || job.lc.len() != lw * lh
        {
            return Err(NodeError::Internal(
                "NL-means upsampling buffers of another size than the grids".into(),
            ));
        }
        let low_area = (2 * job.low_patch + 1).pow(2) as f64;
        let window =
            (2 * p.search + 1).pow(2) as f64 * ((2 * p.patch + 1).pow(2) as f64 + low_area);
        check_job(s, p, &[job.lz, job.lc], window * n as f64)?;
        let indices = |v: &[usize]| -> Result<Vec<u32>, NodeError> {
            v.iter()
                .map(|&i| index_u32(i))
                .collect::<Option<Vec<u32>>>()
                .ok_or_else(|| NodeError::Internal("a low-resolution index beyond u32".into()))
        };
        let sample_at = indices(job.sample_at)?;
        let axis = indices(&[job.lo_col, job.lo_row].concat())?;
        let n_low = 2 * job.low_patch + 1;
        let params = UpsampleParams {
            k: PatchUniform::of(p),
            lw: lw as u32,
            lh: lh as u32,
            low_patch: job.low_patch as u32,
            has_color: u32::from(job.alpha > 0.0),
            has_depth: u32::from(job.alpha < 1.0),
            // guard: n_low >= 1
            inv_low_area: (1.0 / (n_low * n_low) as f64) as f32,
            // only read where the term exists (alpha > 0, alpha < 1)
            ln_alpha: if job.alpha > 0.0 {
                job.alpha.ln() as f32
            } else {
                0.0
            },
            ln_one_minus_alpha: if job.alpha < 1.0 {
                (1.0 - job.alpha).ln() as f32
            } else {
                0.0
            },
            spatial: job.spatial as f32,
            pad: [0.0; 3],
        };
        // the inpainting that follows uses the same guide
        let guide = guide_on_device(&mut self.guide, s, p.guide)?;
        let low: Vec<[f32; 2]> = job.lz.iter().zip(job.lc).map(|(&z, &c)| [z, c]).collect();
        let kernel = s.kernel(&shaders::NLMEANS_UPSAMPLE)?;
        let uniform = s.uniform(bytemuck::bytes_of(&params))?;
        let low_buf = s.upload(bytes_of(&low))?;
        let at_buf = s.upload(bytes_of(&sample_at))?;
        let axis_buf = s.upload(bytes_of(&axis))?;
        let inputs = [&*uniform, guide, &low_buf, &at_buf, &axis_buf];
        let out = one_pass(s, &kernel, &inputs, (w, h))?;
        progress(1.0)?;
        Ok(out)
    }
}

/// Runs `f` (one of the CPU's `*_on` functions) with the passes on the
/// device and progress and cancellation through `ctx`.
fn on_device(
    s: &mut Session,
    ctx: &EvalCtx,
    f: impl FnOnce(
        &mut dyn PassRunner,
        &mut dyn FnMut(f32) -> Result<(), NodeError>,
    ) -> Result<(DepthMap, Confidence), NodeError>,
) -> Result<Produced<NLMeansOut>, NodeError> {
    let mut runner = DeviceRunner { s, guide: None };
    let mut progress = |f: f32| {
        ctx.progress(f);
        ctx.check_cancelled()
    };
    let (d, c) = f(&mut runner, &mut progress)?;
    Ok(NLMeansOut {
        depth: Arc::new(d),
        confidence: Arc::new(c),
    }
    .into())
}

/// The device evaluation of `NLMeansInpaint`.
pub fn eval_inpaint(
    s: &mut Session,
    ctx: &EvalCtx,
    i: NLMeansIn,
    p: &NLMeansInpaintParams,
) -> Result<Produced<NLMeansOut>, NodeError> {
    if let Some(out) = inpaint_passthrough(&i)? {
        return Ok(out);
    }
    on_device(s, ctx, |runner, progress| {
        nlmeans_inpaint_on(
            &i.depth,
            i.confidence.as_deref(),
            &i.color,
            p,
            progress,
            runner,
        )
    })
}

/// The device evaluation of `NLMeansUpsample`: the samples placed on the
/// CPU, the first pass and the inpainting's passes on the device.
pub fn eval_upsample(
    s: &mut Session,
    ctx: &EvalCtx,
    i: UpsampleIn,
    p: &NLMeansUpsampleParams,
) -> Result<Produced<UpsampleOut>, NodeError> {
    let mut runner = DeviceRunner { s, guide: None };
    let progress = |f: f32| {
        ctx.progress(f);
        ctx.check_cancelled()
    };
    let color_k = i.color_intrinsics.as_ref();
    let (depth, confidence, intrinsics) = nlmeans_upsample_on(
        &i.depth,
        &i.intrinsics,
        &i.color,
        color_k,
        p,
        progress,
        &mut runner,
    )?;
    Ok(UpsampleOut {
        depth,
        confidence,
        intrinsics,
    }
    .into())
}

/// The device evaluation of `NLMeansDepth`: the pruning on the CPU, the
/// filter's pass on the device.
pub fn eval_depth(
    s: &mut Session,
    ctx: &EvalCtx,
    i: NLMeansIn,
    p: &NLMeansDepthParams,
) -> Result<Produced<NLMeansOut>, NodeError> {
    on_device(s, ctx, |runner, progress| {
        nlmeans_denoise_on(
            &i.depth,
            i.confidence.as_deref(),
            &i.color,
            p,
            progress,
            runner,
        )
    })
}
