//! `Feather` on the device (`shaders/feather.wgsl`). The plan (cleaned
//! mask, kernel, the pixels near a boundary, pass-through) is the CPU's
//! [`plan`], so both backends decide alike.
//!
//! **Agreement with the CPU** (checked by the parity tests): pixels the
//! plan leaves alone are bit-identical, the others within [`ABS_TOL`]. The
//! taps are the CPU's f64 taps rounded to f32 (relative 6e-8 each, and they
//! sum to 1), the two passes are compensated f32 sums, so each pass is off
//! by a few ulps of a value in [0, 1].

use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use depthgraph_graph::ports::Produced;
use depthgraph_graph::prelude::*;
use depthgraph_nodes::select::feather::{
    FeatherIn, FeatherOut, FeatherParams, FeatherPlan, plan, unchanged_reason,
};

use crate::session::{Session, bytes_of, f32s};
use crate::shaders;

/// The parity check's bound on changed pixels (alpha units).
pub const ABS_TOL: f64 = 1e-6;

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct Params {
    w: u32,
    h: u32,
    r: u32,
    inside: u32,
}

/// The device evaluation of `Feather`.
pub fn eval(
    s: &mut Session,
    _: &EvalCtx,
    i: FeatherIn,
    p: &FeatherParams,
) -> Result<Produced<FeatherOut>, NodeError> {
    let (mask, kernel, near, inside) = match plan(&i.mask, p)? {
        FeatherPlan::Unchanged(m) => {
            return Ok(Produced::passthrough(
                FeatherOut { mask: m },
                unchanged_reason(p),
            ));
        }
        FeatherPlan::Blur {
            mask,
            kernel,
            near,
            inside,
        } => (mask, kernel, near, inside),
    };
    let (w, h) = mask.dims();
    s.check_grid(w, h, 8)?;
    let n = (w * h) as u64;
    let params = Params {
        w: w as u32,
        h: h as u32,
        r: (kernel.len() / 2) as u32,
        inside: u32::from(inside),
    };
    let taps: Vec<f32> = kernel.iter().map(|&t| t as f32).collect();
    let near: Vec<u32> = near.iter().map(|&b| u32::from(b)).collect();
    let horizontal = s.kernel(&shaders::FEATHER_HORIZONTAL)?;
    let vertical = s.kernel(&shaders::FEATHER_VERTICAL)?;
    let uniform = s.uniform(bytemuck::bytes_of(&params))?;
    // the cleaned mask is a new value: uploaded (the input's device copy
    // holds the uncleaned one)
    let mask_buf = s.upload(bytes_of(mask.as_slice()))?;
    let taps_buf = s.upload(bytes_of(&taps))?;
    let near_buf = s.upload(bytes_of(&near))?;
    let horiz = s.scratch(4 * n)?;
    let out = Arc::new(s.scratch(4 * n)?);
    let bg_h = s.bind_at(
        &horizontal,
        &[(0, &uniform), (1, &mask_buf), (2, &taps_buf), (4, &horiz)],
    );
    let bg_v = s.bind(
        &vertical,
        &[&uniform, &mask_buf, &taps_buf, &near_buf, &horiz, &out],
    );
    let encoder = s.image_passes(&[(&horizontal, &bg_h), (&vertical, &bg_v)], (w, h));
    let back = s.finish(encoder, &[(&out, 4 * n)])?;
    let mask: Mask = Image::from_vec(w, h, f32s(&back[0]))?;
    s.keep("mask", out, 4 * n);
    Ok(FeatherOut { mask }.into())
}
