//! `JointBilateral` on the device: the pilot of the GPU path, a pure gather
//! (`shaders/bilateral.wgsl`).
//!
//! **Agreement with the CPU** (checked by the parity tests on lavapipe):
//! identical hole masks (a pixel is a hole on one backend exactly when it is
//! on the other) and `|z_gpu - z_cpu| <= 1e-5 z` everywhere. The difference
//! comes from the exponential (the GPU's `exp2`, a few ulps, against the
//! CPU's degree-5 polynomial, relative error < 3e-6) and the sums (f32 with
//! compensated summation here, f32 window rows added in f64 there).

use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use depthgraph_graph::ports::Produced;
use depthgraph_graph::prelude::*;
use depthgraph_nodes::depth::bilateral::{
    ALL_HOLES, BilateralIn, BilateralOut, BilateralParams, check_color, check_params,
};

use crate::session::{Session, bytes_of, f32s};
use crate::shaders;

/// The tolerance of the parity check: `|Δz| <= REL_TOL * z`.
pub const REL_TOL: f64 = 1e-5;

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct Params {
    w: u32,
    h: u32,
    r: u32,
    _pad0: u32,
    space_coef: f32,
    color_coef: f32,
    depth_scale: f32,
    _pad1: f32,
}

/// The device evaluation of `JointBilateral` (same contract as
/// [`depthgraph_nodes::depth::bilateral::joint_bilateral`]).
pub fn eval(
    s: &mut Session,
    _: &EvalCtx,
    i: BilateralIn,
    p: &BilateralParams,
) -> Result<Produced<BilateralOut>, NodeError> {
    check_color(&i.depth, &i.color)?;
    if i.depth.hole_count() == i.depth.len() {
        return Ok(Produced::passthrough(
            BilateralOut { depth: i.depth },
            ALL_HOLES,
        ));
    }
    check_params(p)?;
    let (w, h) = i.depth.dims();
    s.check_grid(w, h, 8)?;
    let filter = s.kernel(&shaders::BILATERAL)?;
    let log2e = std::f64::consts::LOG2_E;
    let params = Params {
        w: w as u32,
        h: h as u32,
        r: p.radius as u32,
        _pad0: 0,
        space_coef: (log2e / (2.0 * p.sigma_space_px * p.sigma_space_px)) as f32,
        color_coef: (log2e / (2.0 * p.sigma_color * p.sigma_color)) as f32,
        depth_scale: (log2e / (2.0 * p.sigma_depth_rel * p.sigma_depth_rel)) as f32,
        _pad1: 0.0,
    };
    let (depth, out) = guided_pass(s, &filter, bytemuck::bytes_of(&params), &i.depth, &i.color)?;
    let depth = Arc::new(depth);
    s.keep("depth", out, (4 * w * h) as u64);
    Ok(BilateralOut { depth }.into())
}

/// The two passes JointBilateral and EdgeDetect share: the colour
/// encoded once per pixel ([`shaders::BILATERAL_ENCODE`]), then `main`
/// over (uniform, depth, encoded colour, out), one f32 per pixel. Returns
/// the image read back and its device buffer (for [`Session::keep`]).
pub(crate) fn guided_pass<T>(
    s: &mut Session,
    main: &wgpu::ComputePipeline,
    params: &[u8],
    depth: &Arc<DepthMap>,
    color: &Arc<ColorImage>,
) -> Result<(Image<f32, T>, Arc<crate::context::PooledBuffer>), NodeError> {
    let (w, h) = depth.dims();
    let n = (w * h) as u64;
    let encode = s.kernel(&shaders::BILATERAL_ENCODE)?;
    let uniform = s.uniform(params)?;
    let depth_buf = s.image(depth, bytes_of(depth.as_slice()))?;
    let color_buf = s.image(color, bytes_of(color.as_slice()))?;
    let enc = s.scratch(16 * n)?;
    let out = Arc::new(s.scratch(4 * n)?);
    let bg_enc = s.bind(&encode, &[&uniform, &color_buf, &enc]);
    let bg = s.bind(main, &[&uniform, &depth_buf, &enc, &out]);
    let encoder = s.image_passes(&[(&encode, &bg_enc), (main, &bg)], (w, h));
    let back = s.finish(encoder, &[(&out, 4 * n)])?;
    Ok((Image::from_vec(w, h, f32s(&back[0]))?, out))
}
