//! `NLMeansInpaint` and `NLMeansDepth` on the device (for NLMeansDepth: the
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
//! of the depths it averages (measured: at most 8e-7 z, confidences 4e-7). Where a weight underflows f32 but not
//! f64 (confidences below ~1e-30) the filled sets could differ; the tests'
//! scenes do not reach that.

use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use depthgraph_graph::ports::Produced;
use depthgraph_graph::prelude::*;
use depthgraph_nodes::depth::nlmeans::{
    NLMeansDepthParams, NLMeansIn, NLMeansInpaintParams, NLMeansOut, PassJob, PassRunner,
    inpaint_passthrough, nlmeans_denoise_on, nlmeans_inpaint_on,
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

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct Params {
    w: u32,
    h: u32,
    search: u32,
    patch: u32,
    r0: u32,
    r1: u32,
    r2: u32,
    n_boxes: u32,
    coef0: f32,
    coef1: f32,
    coef2: f32,
    cap: f32,
    inv_hc2: f32,
    inv_hd2: f32,
    inv_ref: f32,
    far: u32,
}

/// The passes on the device; the guide is uploaded once for all of them.
struct DeviceRunner<'s, 'c> {
    s: &'s mut Session<'c>,
    guide: Option<PooledBuffer>,
}

impl PassRunner for DeviceRunner<'_, '_> {
    fn run(
        &mut self,
        job: &PassJob,
        progress: &mut dyn FnMut(f32) -> Result<(), NodeError>,
    ) -> Result<Vec<Option<(f32, f32)>>, NodeError> {
        let s = &mut *self.s;
        let (w, h) = (job.w, job.h);
        s.check_grid(w, h, 8)?;
        let n = w * h;
        if job.radii.is_empty() || job.radii.len() > 3 || job.coef.len() != job.radii.len() {
            return Err(NodeError::Invalid(format!(
                "NL-means patch kernel with {} boxes: the device kernel takes 1 to 3",
                job.radii.len()
            )));
        }
        // What f32 on the device cannot hold as the CPU does: subnormal
        // depths or confidences (a device may flush them to 0, which would
        // change which pixels are sources) and depths beyond 1e18 m (their
        // squares overflow). Such a job, and one too costly for a single
        // dispatch, runs on the CPU (the node falls back as a whole).
        let odd = |v: &f32| *v != 0.0 && (v.abs() < f32::MIN_POSITIVE || v.abs() > 1e18);
        if job.z.iter().any(odd) || job.c.iter().any(odd) {
            return Err(s.too_large(
                "depths or confidences outside the device's f32 range (subnormal, or above 1e18)",
            ));
        }
        let window = (2 * job.search + 1).pow(2) as f64 * (2 * job.patch + 1).pow(2) as f64;
        let targets = job.targets.iter().filter(|t| **t).count() as f64;
        if window * targets > MAX_WORK {
            return Err(s.too_large(&format!(
                "{:.1e} patch-pixel comparisons exceed one dispatch's budget ({MAX_WORK:.0e})",
                window * targets
            )));
        }
        let r = |k: usize| job.radii.get(k).copied().unwrap_or(0) as u32;
        let c = |k: usize| job.coef.get(k).copied().unwrap_or(0.0) as f32;
        let params = Params {
            w: w as u32,
            h: h as u32,
            search: job.search as u32,
            patch: job.patch as u32,
            r0: r(0),
            r1: r(1),
            r2: r(2),
            n_boxes: job.radii.len() as u32,
            coef0: c(0),
            coef1: c(1),
            coef2: c(2),
            cap: job.cap.min(f32::MAX as f64) as f32,
            inv_hc2: job.inv_hc2 as f32,
            inv_hd2: job.inv_hd2 as f32,
            inv_ref: job.far.unwrap_or(0.0) as f32,
            far: u32::from(job.far.is_some()),
        };
        if self.guide.is_none() {
            let g: Vec<[f32; 4]> = job.guide.iter().map(|g| [g[0], g[1], g[2], 0.0]).collect();
            self.guide = Some(s.upload(bytes_of(&g))?);
        }
        let Some(guide) = self.guide.as_ref() else {
            return Err(NodeError::Invalid("no guide on the device".into()));
        };
        let zc: Vec<[f32; 2]> = job.z.iter().zip(job.c).map(|(&z, &c)| [z, c]).collect();
        let targets: Vec<u32> = job.targets.iter().map(|&t| u32::from(t)).collect();
        if job.z.len() != n || job.c.len() != n || job.guide.len() != n || targets.len() != n {
            return Err(NodeError::Invalid(
                "NL-means pass buffers of another size than the grid".into(),
            ));
        }
        let kernel = s.kernel(&shaders::NLMEANS)?;
        let uniform = s.uniform(bytemuck::bytes_of(&params))?;
        let zc_buf = s.upload(bytes_of(&zc))?;
        let t_buf = s.upload(bytes_of(&targets))?;
        let out = s.scratch(16 * n as u64)?;
        let bg = s.bind(&kernel, &[&uniform, guide, &zc_buf, &t_buf, &out]);
        let encoder = s.image_passes(&[(&kernel, &bg)], (w, h));
        let back = s.finish(encoder, &[(&out, 16 * n as u64)])?;
        progress(1.0)?;
        Ok(f32s(&back[0])
            .chunks_exact(4)
            .map(|r| (r[2] > 0.0).then_some((r[0], r[1])))
            .collect())
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
