//! `EdgeDetect` on the device (`shaders/edges.wgsl`): the strength on the
//! device, the binary edges by the CPU's [`binary_edges`] from that
//! strength (the threshold and the thinning are discrete decisions, so they
//! follow the strength the node returns).
//!
//! **Agreement with the CPU** (checked by the parity tests): the strength
//! within [`strength_tol`] (the CPU computes in f32 too; the device's
//! division, `sqrt` and fused multiply-adds differ by a few ulps), and the
//! binary edges identical except at pixels the strength leaves ambiguous:
//! within that bound of the threshold, or of a neighbour the thinning
//! compares it with.
//!
//! **Why the bound depends on the parameters.** Vulkan lets a device's
//! `1 / z` be off by 2.5 ulp (the CPU rounds it correctly; lavapipe happens
//! to as well, an NVIDIA H200 does not), and the occlusion term is a
//! second difference of those inverse depths divided by the centre's,
//! `d / w_p = 4 - R` with `R = (w_a + 2 w_p + w_b) / w_p`: the inputs'
//! error (3 ulp each), the sums' rounding on either side (1 ulp of `R w_p`
//! each) and the quotient's (3 ulp) add up to at most `8 ε R`, `ε` =
//! `f32::EPSILON`. The term is `min(s |d / w_p|, 1)` with `s` = `1 /
//! depth_scale_rel` (or `1 / crease_scale_rel` for the crease, weighted by
//! `crease_weight`); where it is below 1, `R <= 4 + 1 / s`, so its error is
//! at most `8 ε (4 s + 1)`, and a clamped term moves by no more (the clamp
//! and the `max` of the two terms are 1-Lipschitz). At the defaults (`s` =
//! 20 and 100) that is `1.3e-4` after the depth weight: on an H200 the
//! crease term of a slanted wall differed by `1.2e-5`, over the flat `1e-5`
//! this module stated before. The gradient term and the colour term have
//! no such cancellation (`16 ε` and `8 ε`).

use bytemuck::{Pod, Zeroable};
use depthgraph_graph::ports::Produced;
use depthgraph_graph::prelude::*;
use depthgraph_nodes::select::edges::{
    DepthTerm, EdgeParams, EdgesIn, EdgesOut, binary_edges, check_dims, check_params,
};

use crate::bilateral::guided_pass;
use crate::session::Session;
use crate::shaders;

/// The parity check's least bound on the strength (module docs).
pub const ABS_TOL: f64 = 1e-5;

/// The parity check's bound on the strength for parameters `p` (module
/// docs, "Why the bound depends on the parameters"): at least [`ABS_TOL`].
/// Weights are normalised as the node normalises them; a zero weight sum
/// (refused by the node) gives [`ABS_TOL`].
pub fn strength_tol(p: &EdgeParams) -> f64 {
    let eps = f64::from(f32::EPSILON);
    let wsum = p.color_weight + p.depth_weight;
    if wsum.is_nan() || wsum <= 0.0 {
        return ABS_TOL;
    }
    // guard: wsum > 0 above; the scales are positive (checked by the node)
    let (wc, wd) = (p.color_weight / wsum, p.depth_weight / wsum);
    let depth = match p.depth_term {
        DepthTerm::Occlusion => {
            let (s, k) = (1.0 / p.depth_scale_rel, 1.0 / p.crease_scale_rel);
            8.0 * eps * (4.0 * s + 1.0).max(p.crease_weight * (4.0 * k + 1.0))
        }
        DepthTerm::Gradient => 16.0 * eps,
    };
    let bound = wc * 8.0 * eps + wd * depth + 4.0 * eps;
    if bound.is_finite() {
        bound.max(ABS_TOL)
    } else {
        ABS_TOL
    }
}

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
