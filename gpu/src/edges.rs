//! `EdgeDetect` on the device (`shaders/edges.wgsl`): the strength on the
//! device, the binary edges by the CPU's [`binary_edges`] from that
//! strength (the threshold and the thinning are discrete decisions, so they
//! follow the strength the node returns).
//!
//! **Agreement with the CPU** (checked by the parity tests): the strength
//! within [`ABS_TOL`] (the CPU computes in f32 too; the device's division,
//! `sqrt` and fused multiply-adds differ by a few ulps), and the binary
//! edges identical except at pixels the strength leaves ambiguous: within
//! [`ABS_TOL`] of the threshold, or of a neighbour the thinning compares it
//! with.

use bytemuck::{Pod, Zeroable};
use depthgraph_graph::ports::Produced;
use depthgraph_graph::prelude::*;
use depthgraph_nodes::select::edges::{
    DepthTerm, EdgeParams, EdgesIn, EdgesOut, binary_edges, check_dims, check_params,
};

use crate::bilateral::guided_pass;
use crate::session::Session;
use crate::shaders;

/// The parity check's bound on the strength.
pub const ABS_TOL: f64 = 1e-5;

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct Params {
    w: u32,
    h: u32,
    term: u32,
    _pad: u32,
    wc: f32,
    wd: f32,
    inv_cs: f32,
    inv_ds: f32,
    inv_ks: f32,
    kw: f32,
    _pad1: [f32; 2],
}

/// The device evaluation of `EdgeDetect`.
pub fn eval(
    s: &mut Session,
    _: &EvalCtx,
    i: EdgesIn,
    p: &EdgeParams,
) -> Result<Produced<EdgesOut>, NodeError> {
    let term = check_params(p)?;
    check_dims(&i.color, &i.depth)?;
    let (w, h) = i.color.dims();
    if w == 0 || h == 0 {
        return Ok(EdgesOut {
            strength: Image::filled(w, h, 0.0),
            edges: Image::filled(w, h, 0.0),
        }
        .into());
    }
    s.check_grid(w, h, 8)?;
    // The CPU's constants, in its f64-then-f32 order.
    let wsum = p.color_weight + p.depth_weight;
    let params = Params {
        w: w as u32,
        h: h as u32,
        term: u32::from(term == DepthTerm::Gradient),
        _pad: 0,
        wc: (p.color_weight / wsum) as f32,
        wd: (p.depth_weight / wsum) as f32,
        inv_cs: (1.0 / p.color_scale) as f32,
        inv_ds: (1.0 / p.depth_scale_rel) as f32,
        inv_ks: (1.0 / p.crease_scale_rel) as f32,
        kw: p.crease_weight as f32,
        _pad1: [0.0; 2],
    };
    let main = s.kernel(&shaders::EDGES)?;
    let (strength, out): (Confidence, _) =
        guided_pass(s, &main, bytemuck::bytes_of(&params), &i.depth, &i.color)?;
    let edges = binary_edges(&strength, p.threshold as f32, p.thin);
    s.keep("strength", out, (4 * w * h) as u64);
    Ok(EdgesOut { strength, edges }.into())
}
