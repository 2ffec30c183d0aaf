//! `PullPush` and `DualPullPush` on the device (`shaders/pull_push.wgsl`):
//! the whole pyramid, pull and push, in one submission. The level count is
//! the CPU's [`level_count`] (it depends on the hole mask alone) and the
//! pass-throughs are the CPU's [`nothing_to_fill`], so both backends decide
//! alike.
//!
//! **Agreement with the CPU** (checked by the parity tests): identical hole
//! and filled masks, measured pixels bit-identical, and filled pixels within
//! `|Δz| <= 1e-5 z` ([`REL_TOL`], PullPush) and `|Δz| <= 1e-4 z`
//! ([`DUAL_REL_TOL`], DualPullPush). The device computes in f32 where the
//! CPU uses f64; each filled value is a convex combination of at most four
//! coarse values per level (a few ulps each), over at most 24 levels. The
//! dual weights `1 / (eps + |C_i - C_j|)` amplify the f32 rounding of the
//! pulled colors (about `2^-23 |C|`) by up to `|C| / eps` (eq. 3's weight is
//! most sensitive where two colors nearly agree), so with the default
//! `eps = 1e-3` a weight may be off by ~2e-4 relative and the filled depth
//! by that times the spread of its four coarse depths; measured on the
//! parity scenes and `depth_fill.ron`: at most 4e-6 relative.

use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use depthgraph_graph::ports::Produced;
use depthgraph_graph::prelude::*;
use depthgraph_nodes::depth::pull_push::{
    DualPullPushIn, PullPushIn, PullPushOut, PullPushParams, Weights, check_inputs, check_params,
    level_count, nothing_to_fill, shadow_masks,
};

use crate::session::{Bind, Session, bytes_of, entry, f32s, uniform_blocks};
use crate::shaders;

/// The parity check's bound on PullPush's filled pixels: `|Δz| <= REL_TOL * z`.
pub const REL_TOL: f64 = 1e-5;

/// The bound on DualPullPush's filled pixels (see the module docs).
pub const DUAL_REL_TOL: f64 = 1e-4;

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct Level {
    fw: u32,
    fh: u32,
    f_off: u32,
    cw: u32,
    ch: u32,
    c_off: u32,
    dual: u32,
    /// 1: the push reads `shadow` per hole; 0: every hole takes the
    /// background side (no masks: `shadow` holds one unused word)
    masked: u32,
    epsilon: f32,
    scale_f: f32,
    kfx: f32,
    kfy: f32,
    kcx: f32,
    kcy: f32,
    beta: f32,
    edge: f32,
}

const BINDS: &[Bind] = &[
    Bind::DynamicUniform,
    Bind::Read,
    Bind::Read,
    Bind::ReadWrite,
    Bind::ReadWrite,
    Bind::ReadWrite,
    Bind::ReadWrite,
    Bind::ReadWrite,
    Bind::Read,
];

/// The device evaluation of `PullPush`.
pub fn eval_plain(
    s: &mut Session,
    _: &EvalCtx,
    i: PullPushIn,
    p: &PullPushParams,
) -> Result<Produced<PullPushOut>, NodeError> {
    if let Some(out) = nothing_to_fill(&i.depth) {
        return Ok(out);
    }
    fill(s, &i.depth, None, p)
}

/// The device evaluation of `DualPullPush`.
pub fn eval_dual(
    s: &mut Session,
    _: &EvalCtx,
    i: DualPullPushIn,
    p: &PullPushParams,
) -> Result<Produced<PullPushOut>, NodeError> {
    if let Some(out) = nothing_to_fill(&i.depth) {
        return Ok(out);
    }
    fill(s, &i.depth, Some((&i.color, &i.intrinsics)), p)
}

fn fill(
    s: &mut Session,
    depth: &Arc<DepthMap>,
    dual: Option<(&Arc<ColorImage>, &Intrinsics)>,
    p: &PullPushParams,
) -> Result<Produced<PullPushOut>, NodeError> {
    let weights = match dual {
        Some((color, k)) => Weights::Dual { color, k },
        None => Weights::Bilinear,
    };
    check_inputs(depth, weights)?;
    check_params(p)?;
    let (w, h) = depth.dims();
    s.check_grid(w, h, 8)?;
    let n_levels = level_count(depth, p) as usize;
    // sizes and offsets of levels 0..=n_levels
    let mut dims = vec![(w, h, 0usize)];
    for _ in 0..n_levels {
        let &(lw, lh, off) = dims.last().unwrap_or(&(w, h, 0));
        dims.push((lw.div_ceil(2), lh.div_ceil(2), off + lw * lh));
    }
    let total = dims
        .last()
        .map(|&(lw, lh, off)| off + lw * lh)
        .unwrap_or(w * h);
    // the holes the background side applies to (the CPU's decision), one
    // word per pixel of every level; without masks every hole is, and the
    // buffer holds one unused word (a binding is never empty)
    let masks = shadow_masks(depth, weights, p, n_levels);
    let masked = u32::from(masks.is_some());
    let shadow_words: Vec<u32> = match masks {
        Some(masks) => masks
            .iter()
            .flat_map(|m| m.iter().map(|b| u32::from(*b)))
            .collect(),
        None => vec![0u32],
    };
    if masked == 1 && shadow_words.len() != total {
        return Err(NodeError::Internal(format!(
            "shadow masks hold {} pixels, the pyramid {total}",
            shadow_words.len()
        )));
    }
    let k = dual.map(|(_, k)| *k);
    let block = |r: usize| {
        let (fw, fh, f_off) = dims[r];
        let (cw, ch, c_off) = dims.get(r + 1).copied().unwrap_or((fw, fh, f_off));
        Level {
            fw: fw as u32,
            fh: fh as u32,
            f_off: f_off as u32,
            cw: cw as u32,
            ch: ch as u32,
            c_off: c_off as u32,
            dual: u32::from(dual.is_some()),
            masked,
            epsilon: p.epsilon as f32,
            scale_f: 0.5f64.powi(r as i32) as f32,
            kfx: k.map_or(1.0, |k| k.fx as f32),
            kfy: k.map_or(1.0, |k| k.fy as f32),
            kcx: k.map_or(0.0, |k| k.cx as f32),
            kcy: k.map_or(0.0, |k| k.cy as f32),
            // the background bias needs the intrinsics: dual weights only
            beta: if dual.is_some() {
                p.background as f32
            } else {
                0.0
            },
            edge: p.edge_slope as f32,
        }
    };
    let blocks: Vec<Level> = (0..=n_levels).map(block).collect();
    let align = s.ctx().limits().min_uniform_buffer_offset_alignment;
    let (bytes, stride) = uniform_blocks(&blocks, align);
    let uniform = s.uniform(&bytes)?;
    let depth_buf = s.image(depth, bytes_of(depth.as_slice()))?;
    let color_buf = match dual {
        Some((c, _)) => s.image(c, bytes_of(c.as_slice()))?,
        None => Arc::new(s.scratch(16)?),
    };
    let shadow_buf = s.upload(bytemuck::cast_slice(&shadow_words))?;
    let lz = s.scratch(4 * total as u64)?;
    let lw = s.scratch(4 * total as u64)?;
    // the color pyramid for the dual weights only (a placeholder otherwise)
    let lc = s.scratch(if dual.is_some() {
        16 * total as u64
    } else {
        16
    })?;
    let n = (w * h) as u64;
    let out_depth = Arc::new(s.scratch(4 * n)?);
    let out_filled = Arc::new(s.scratch(4 * n)?);
    let init = s
        .kernel_in("pull_push.wgsl", BINDS, &shaders::PULL_PUSH_INIT)?
        .0;
    let pull = s
        .kernel_in("pull_push.wgsl", BINDS, &shaders::PULL_PUSH_PULL)?
        .0;
    let push = s
        .kernel_in("pull_push.wgsl", BINDS, &shaders::PULL_PUSH_PUSH)?
        .0;
    let (finish, layout) = s.kernel_in("pull_push.wgsl", BINDS, &shaders::PULL_PUSH_FINISH)?;
    let bg = s
        .ctx()
        .device()
        .create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("pull_push"),
            layout: &layout.0,
            entries: &[
                entry(0, &uniform, Some(std::mem::size_of::<Level>() as u64)),
                entry(1, &depth_buf, None),
                entry(2, &color_buf, None),
                entry(3, &lz, None),
                entry(4, &lw, None),
                entry(5, &lc, None),
                entry(6, &out_depth, None),
                entry(7, &out_filled, None),
                entry(8, &shadow_buf, None),
            ],
        });
    let groups =
        |(lw, lh, _): (usize, usize, usize)| ((lw as u32).div_ceil(8), (lh as u32).div_ceil(8));
    let mut encoder = s.encoder();
    {
        let mut pass = encoder.begin_compute_pass(&Default::default());
        let at = |r: usize| [(r * stride) as u32];
        pass.set_bind_group(0, &bg, &at(0));
        pass.set_pipeline(&init);
        let g = groups(dims[0]);
        pass.dispatch_workgroups(g.0, g.1, 1);
        for r in 0..n_levels {
            pass.set_bind_group(0, &bg, &at(r));
            pass.set_pipeline(&pull);
            let g = groups(dims[r + 1]);
            pass.dispatch_workgroups(g.0, g.1, 1);
        }
        for r in (0..n_levels).rev() {
            pass.set_bind_group(0, &bg, &at(r));
            pass.set_pipeline(&push);
            let g = groups(dims[r]);
            pass.dispatch_workgroups(g.0, g.1, 1);
        }
        pass.set_bind_group(0, &bg, &at(0));
        pass.set_pipeline(&finish);
        let g = groups(dims[0]);
        pass.dispatch_workgroups(g.0, g.1, 1);
    }
    let back = s.finish(encoder, &[(&out_depth, 4 * n), (&out_filled, 4 * n)])?;
    let depth = Arc::new(Image::from_vec(w, h, f32s(&back[0]))?);
    let filled: Mask = Image::from_vec(w, h, f32s(&back[1]))?;
    s.keep("depth", out_depth, 4 * n);
    s.keep("filled", out_filled, 4 * n);
    Ok(PullPushOut { depth, filled }.into())
}
