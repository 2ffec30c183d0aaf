//! `OcclusionComposite` on the device (`shaders/composite.wgsl`).
//!
//! **Agreement with the CPU** (checked by the parity tests): the alpha
//! after the depth test is bit-identical everywhere (pixels whose test the
//! device's f32 product cannot decide, and subnormal alphas, are marked and
//! recomputed on the host with the CPU's own [`pixel`]); pixels with alpha
//! 0 or 1 are bit-identical in color and depth; blended pixels are within
//! [`REL_TOL`] (the device may fuse `a p + (1 - a) t`).

use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use depthgraph_graph::ports::Produced;
use depthgraph_graph::prelude::*;
use depthgraph_nodes::select::composite::{
    CompositeIn, CompositeOut, CompositeParams, check_inputs, passthrough, pixel,
};

use crate::session::{Session, bytes_of, f32s};
use crate::shaders;

/// The bound on blended pixels: `|Δ| <= REL_TOL * max(|v|, 1)`.
pub const REL_TOL: f64 = 1e-6;

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct Params {
    w: u32,
    h: u32,
    exact: u32,
    _pad: u32,
    k: f32,
    _pad1: [f32; 3],
}

/// The device evaluation of `OcclusionComposite`.
pub fn eval(
    s: &mut Session,
    _: &EvalCtx,
    i: CompositeIn,
    p: &CompositeParams,
) -> Result<Produced<CompositeOut>, NodeError> {
    if let Some(out) = passthrough(&i)? {
        return Ok(out);
    }
    let (tc, td, pa) = (&i.target_color, &i.target_depth, &i.pasted_alpha);
    check_inputs(tc, td, &i.pasted_color, &i.pasted_depth, pa, p)?;
    let (w, h) = tc.dims();
    s.check_grid(w, h, 8)?;
    let n = w * h;
    let params = Params {
        w: w as u32,
        h: h as u32,
        exact: u32::from(p.tolerance_rel == 0.0),
        _pad: 0,
        k: (1.0 + p.tolerance_rel) as f32,
        _pad1: [0.0; 3],
    };
    let kernel = s.kernel(&shaders::COMPOSITE)?;
    let uniform = s.uniform(bytemuck::bytes_of(&params))?;
    let b_tc = s.image(tc, bytes_of(tc.as_slice()))?;
    let b_td = s.image(td, bytes_of(td.as_slice()))?;
    let b_pc = s.image(&i.pasted_color, bytes_of(i.pasted_color.as_slice()))?;
    let b_pz = s.image(&i.pasted_depth, bytes_of(i.pasted_depth.as_slice()))?;
    let b_pa = s.image(pa, bytes_of(pa.as_slice()))?;
    let out = s.scratch(20 * n as u64)?;
    let bg = s.bind(
        &kernel,
        &[&uniform, &b_tc, &b_td, &b_pc, &b_pz, &b_pa, &out],
    );
    let encoder = s.image_passes(&[(&kernel, &bg)], (w, h));
    let back = s.finish(encoder, &[(&out, 20 * n as u64)])?;
    let all = f32s(&back[0]);
    let (rgb, rest) = all.split_at(3 * n);
    let (depth, alpha) = rest.split_at(n);
    let mut color: Vec<[f32; 3]> = rgb.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
    let mut depth = depth.to_vec();
    let mut alpha = alpha.to_vec();
    // The pixels the device could not decide: the CPU's function.
    for t in 0..n {
        if alpha[t] < 0.0 {
            let (c, z, a) = pixel(
                tc.as_slice()[t],
                td.as_slice()[t],
                i.pasted_color.as_slice()[t],
                i.pasted_depth.as_slice()[t],
                pa.as_slice()[t],
                p.tolerance_rel,
            );
            color[t] = c;
            depth[t] = z;
            alpha[t] = a;
        }
    }
    Ok(CompositeOut {
        color: Arc::new(Image::from_vec(w, h, color)?),
        depth: Arc::new(Image::from_vec(w, h, depth)?),
        alpha: Image::from_vec(w, h, alpha)?,
    }
    .into())
}
