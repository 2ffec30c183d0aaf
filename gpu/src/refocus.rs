//! `Refocus` on the device: every aperture view rendered on the device from
//! one upload of the inputs and one download of the result
//! (`shaders/refocus.wgsl`). The plan (pass-through, sample count and
//! points, active tiles, the sources and their z-buffer keys, the
//! background layer) is the CPU's [`plan`], so both backends decide alike;
//! the layer's entries join the warp as sources keyed `w h + k`, placed at
//! their pixel, exactly as on the CPU. The lens effects: spherical
//! aberration moves every source by green's extra shift in the warp; the
//! barrel clips each view's accumulation per pixel; longitudinal chromatic
//! aberration stores each view's fills and then reads red and blue at
//! their offsets (bilinear, edges clamped), as the CPU's split path does.
//! The unmoved pixels' barrel share and the image-wide effects run on the
//! host after the download ([`BlurPlan::finish_image`]).
//!
//! **Views in batches.** One dispatch has a fixed cost (on an H200, 256
//! views of 4 dispatches each took 30 ms of kernels at 640x480 and 2.8x
//! that at 7.5x the pixels), so the views run in batches of up to
//! [`GpuContext::views_per_dispatch`](crate::GpuContext::views_per_dispatch)
//! (16 by default; fewer where the largest buffer cannot hold that many
//! view slots of 40 bytes a pixel): each view of a batch has its own
//! z-buffer and view slot, one dispatch warps, gathers or fills them all,
//! and the accumulation adds the batch's views to each pixel in view
//! order. The sum is therefore the same bits as with one view per
//! dispatch (tested).
//!
//! **Agreement with the CPU** (checked by the parity tests): the display
//! image's PSNR against the CPU's is at least [`MIN_PSNR_DB`], and pixels
//! outside the active tiles are bit-identical (the host applies the CPU's
//! f64 gain to them after the download). The z-buffer is exact (two
//! 32-bit `atomicMin` passes reproduce the CPU's 64-bit key); the
//! differences come from f32 warp positions (a target can round the other
//! way when it lies within ~1e-6 px of a half pixel), f32 fill weights, and
//! the views' average: f32 with compensated summation here (relative error
//! about 2 ulps), f64 there.

use std::sync::Arc;

use rayon::prelude::*;

use bytemuck::{Pod, Zeroable};
use depthgraph_graph::ports::Produced;
use depthgraph_graph::prelude::*;
use depthgraph_nodes::camera::lens::Aperture;
use depthgraph_nodes::camera::refocus::{
    BlurPlan, Plan, RefocusIn, RefocusOut, RefocusParams, RefocusReport, exposed_f32, plan,
    produced, zkey,
};

use crate::session::{Bind, Session, bytes_of, entry, f32s, u32s, uniform_blocks};
use crate::shaders;

/// The parity check's bound on the display PSNR against the CPU.
pub const MIN_PSNR_DB: f64 = 60.0;

/// Views per command buffer, at least (bounds a submission's length on
/// slow devices and lets progress and cancellation be checked between
/// them; whole batches go into one).
const VIEWS_PER_SUBMIT: usize = 32;

/// Views per batch: the context's `views_per_dispatch`, no more than there
/// are views, and no more than the largest buffer holds the view slots of
/// (`view` is the larger of the two slot arrays: 32 bytes a pixel); at
/// least 1 (one slot that does not fit fails the allocation, and the node
/// runs on the CPU as before).
fn batch_size(per_dispatch: usize, views: usize, n: usize, max_buffer: u64) -> usize {
    // guard: n >= 1 for a blur plan; max(1) keeps the division defined
    let fit = max_buffer / (32 * n.max(1) as u64);
    per_dispatch
        .min(views)
        .min(usize::try_from(fit).unwrap_or(usize::MAX))
        .max(1)
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct Globals {
    w: u32,
    h: u32,
    n_src: u32,
    row: u32,
    scale: f32,
    gain: f32,
    fill_h: f32,
    far_prior: u32,
    barrel: u32,
    per_px: f32,
    radius2: f32,
    slots: u32,
}

/// The views of one batch, `k0 .. k0 + count` (a dynamic uniform block).
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct Batch {
    k0: u32,
    count: u32,
    _pad: [u32; 2],
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct ViewParams {
    dx: f32,
    dy: f32,
    sx: f32,
    sy: f32,
    gx: f32,
    gy: f32,
    bx: f32,
    by: f32,
    erx: f32,
    ery: f32,
    ebx: f32,
    eby: f32,
    k: u32,
    _pad: [u32; 3],
}

const BINDS: &[Bind] = &[
    Bind::Uniform,
    Bind::DynamicUniform,
    Bind::Read,
    Bind::Read,
    Bind::Read,
    Bind::ReadWrite,
    Bind::ReadWrite,
    Bind::ReadWrite,
    Bind::ReadWrite,
    Bind::ReadWrite,
    Bind::Read,
    Bind::Read,
];

/// A 1-D dispatch of `n` invocations (workgroups of 256) folded into 2-D
/// when it exceeds the per-dimension limit: (groups x, groups y, row).
fn fold(n: usize, max_dim: u32) -> (u32, u32, u32) {
    let groups = (n as u64).div_ceil(256).max(1);
    let gx = groups.min(max_dim as u64).max(1);
    let gy = groups.div_ceil(gx);
    (gx as u32, gy as u32, (gx * 256) as u32)
}

/// The device evaluation of `Refocus` (same contract as the CPU node).
pub fn eval(
    s: &mut Session,
    ctx: &EvalCtx,
    i: RefocusIn,
    p: &RefocusParams,
) -> Result<Produced<RefocusOut>, NodeError> {
    let aperture =
        Aperture::from_params(p.aperture, p.blades, p.rotation_deg, i.aperture.as_deref())?;
    let (color, report) = match plan(&i.color, &i.depth, &aperture, p)? {
        Plan::Sharp(out, report) => (out, report),
        Plan::Blur(b) => render(s, ctx, &i.color, &b, &aperture, p)?,
    };
    Ok(produced(RefocusOut { color }, p, &report))
}

/// Renders `plan`'s views on the device.
pub fn render(
    s: &mut Session,
    ctx: &EvalCtx,
    color: &Arc<ColorImage>,
    plan: &BlurPlan,
    aperture: &Aperture,
    p: &RefocusParams,
) -> Result<(ColorImage, RefocusReport), NodeError> {
    let (w, h) = (plan.w, plan.h);
    let n = w * h;
    let views = plan.points.len();
    let limits = s.ctx().limits();
    let max_dim = limits.max_compute_workgroups_per_dimension;
    let slots = batch_size(s.ctx().views_per_dispatch(), views, n, s.ctx().max_buffer());
    let n_src = plan.sources.len() + plan.layer.len();
    // Every kernel indexes with one row length: a fold that needs a second
    // dimension has the full row (256 max_dim), and the others then run
    // with one row of groups, so the largest row serves all (a smaller last
    // batch folds to a row no longer than a full one's).
    let row = [n, n * slots, n_src * slots]
        .into_iter()
        .map(|m| fold(m, max_dim).2)
        .max()
        .unwrap_or(256);
    let (px_x, px_y, _) = fold(n, max_dim);
    let globals = Globals {
        w: w as u32,
        h: h as u32,
        n_src: n_src as u32,
        row,
        // Guard: views >= 1 in a blur plan.
        scale: (plan.gain / views.max(1) as f64) as f32,
        gain: plan.gain as f32,
        fill_h: p.fill_h as f32,
        far_prior: u32::from(p.far_prior),
        barrel: u32::from(plan.barrel.is_some()),
        per_px: plan.barrel.map_or(0.0, |b| b.per_px as f32),
        radius2: plan.barrel.map_or(0.0, |b| b.radius2 as f32),
        slots: slots as u32,
    };
    // Per-view parameters (a storage array the batch indexes).
    let blocks: Vec<ViewParams> = plan
        .points
        .iter()
        .enumerate()
        .map(|(k, pt)| {
            let dir = plan.shift(*pt);
            let step = BlurPlan::fill_step(dir);
            let g = plan.green_shift(*pt);
            // the barrel's test at pixel centre (x, y) is |b + per_px (x, y)|²
            // <= radius²: the view's part in f64 here
            let b = plan.barrel.map_or([0.0; 2], |b| {
                [
                    pt[0] * b.along - b.per_px * b.centre[0],
                    pt[1] * b.along - b.per_px * b.centre[1],
                ]
            });
            // red's and blue's read offsets (longitudinal chromatic
            // aberration): their focus offset's difference from green's
            let e = plan.channel_offsets(*pt);
            let (er, eb) = (e[0].map(|v| v as f32), e[2].map(|v| v as f32));
            ViewParams {
                erx: er[0],
                ery: er[1],
                ebx: eb[0],
                eby: eb[1],
                dx: dir[0] as f32,
                dy: dir[1] as f32,
                sx: step[0] as f32,
                sy: step[1] as f32,
                gx: g[0] as f32,
                gy: g[1] as f32,
                bx: b[0] as f32,
                by: b[1] as f32,
                k: k as u32,
                _pad: [0; 3],
            }
        })
        .collect();
    // The batches, one dynamic uniform block each.
    let batches: Vec<Batch> = (0..views)
        .step_by(slots)
        .map(|k0| Batch {
            k0: k0 as u32,
            count: (views - k0).min(slots) as u32,
            _pad: [0; 2],
        })
        .collect();
    let (batch_bytes, stride) =
        uniform_blocks(&batches, limits.min_uniform_buffer_offset_alignment);
    // (key index, depth bits, m, pixel): the image's sources, then the
    // background layer's entries (key index n + k, at their pixel), as
    // the CPU's warp lists them
    let layer = &plan.layer;
    let src: Vec<[u32; 4]> = plan
        .sources
        .iter()
        .map(|&(i, key)| {
            let m = (plan.inv_u - plan.src_inv_z[i as usize]) as f32;
            [i, (key >> 32) as u32, m.to_bits(), i]
        })
        .chain(layer.pixels.iter().enumerate().map(|(k, &i)| {
            let v = layer.inv_z[k];
            let m = (plan.inv_u - v) as f32;
            let key = zkey(v, n + k);
            [(n + k) as u32, (key >> 32) as u32, m.to_bits(), i]
        }))
        .collect();
    // the layer's colour and inverse depth (one unused entry when empty:
    // a binding is never empty)
    let layer_px: Vec<[f32; 4]> = if layer.is_empty() {
        vec![[0.0; 4]]
    } else {
        layer
            .color
            .iter()
            .zip(&layer.inv_z)
            .map(|(c, &v)| [c[0], c[1], c[2], v as f32])
            .collect()
    };
    let pix: Vec<[f32; 2]> = plan
        .src_inv_z
        .iter()
        .zip(&plan.active)
        .map(|(&v, &a)| [v as f32, if a { 1.0 } else { 0.0 }])
        .collect();

    let g_buf = s.uniform(bytemuck::bytes_of(&globals))?;
    let b_buf = s.uniform(&batch_bytes)?;
    let v_buf = s.upload(bytes_of(&blocks))?;
    let src_buf = s.upload(bytes_of(&src))?;
    // the extended frame's (sanitised) colour when frame_border extended
    // it: uploaded, not kept (no other node holds it); else the input,
    // found resident when a device node made it
    let color_buf = match plan.frame {
        Some(_) => Arc::new(s.upload(bytes_of(&plan.src_color))?),
        None => s.image(color, bytes_of(color.as_slice()))?,
    };
    let pix_buf = s.upload(bytes_of(&pix))?;
    let layer_buf = s.upload(bytes_of(&layer_px))?;
    let zbuf = s.scratch(8 * (n * slots) as u64)?;
    let view = s.scratch(32 * (n * slots) as u64)?;
    let acc = s.scratch(32 * n as u64)?;
    let holes = s.upload(&vec![0u8; 4 * views.max(1)])?;
    let out = Arc::new(s.scratch(12 * n as u64)?);

    // every kernel of refocus.wgsl, one layout
    let mut kernel = |k| s.kernel_in("refocus.wgsl", BINDS, k).map(|(p, _)| p);
    let clear = kernel(&shaders::REFOCUS_CLEAR)?;
    let warp_depth = kernel(&shaders::REFOCUS_WARP_DEPTH)?;
    let warp_index = kernel(&shaders::REFOCUS_WARP_INDEX)?;
    let gather = kernel(&shaders::REFOCUS_GATHER)?;
    let fill = kernel(&shaders::REFOCUS_FILL)?;
    // each view's channels read apart (longitudinal chromatic aberration):
    // the fills stored, then the channels gathered from their offsets
    let split = plan.effects.channels_split();
    let fill_store = kernel(&shaders::REFOCUS_FILL_STORE)?;
    let accumulate_split = kernel(&shaders::REFOCUS_ACCUMULATE_SPLIT)?;
    let (finish, layout) = s.kernel_in("refocus.wgsl", BINDS, &shaders::REFOCUS_FINISH)?;
    let bg = s
        .ctx()
        .device()
        .create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("refocus"),
            layout: &layout.0,
            entries: &[
                entry(0, &g_buf, None),
                entry(1, &b_buf, Some(std::mem::size_of::<Batch>() as u64)),
                entry(2, &src_buf, None),
                entry(3, &color_buf, None),
                entry(4, &pix_buf, None),
                entry(5, &zbuf, None),
                entry(6, &view, None),
                entry(7, &acc, None),
                entry(8, &holes, None),
                entry(9, &out, None),
                entry(10, &layer_buf, None),
                entry(11, &v_buf, None),
            ],
        });

    let mut next = 0;
    let mut done = 0;
    let mut first = true;
    while next < batches.len() || first {
        // whole batches, at least VIEWS_PER_SUBMIT views (or the rest)
        let mut last = next;
        let mut in_submit = 0;
        while last < batches.len() && in_submit < VIEWS_PER_SUBMIT {
            in_submit += batches[last].count as usize;
            last += 1;
        }
        // the views rendered once this submission is done (batches run in
        // view order from view 0)
        let k1 = done + in_submit;
        let mut encoder = s.encoder();
        {
            let mut pass = encoder.begin_compute_pass(&Default::default());
            if first {
                pass.set_pipeline(&clear);
                pass.set_bind_group(0, &bg, &[0]);
                pass.dispatch_workgroups(px_x, px_y, 1);
            }
            for (b, batch) in batches.iter().enumerate().take(last).skip(next) {
                let count = batch.count as usize;
                let off = [(b * stride) as u32];
                pass.set_bind_group(0, &bg, &off);
                let (src_x, src_y, _) = fold(n_src * count, max_dim);
                let (all_x, all_y, _) = fold(n * count, max_dim);
                if n_src > 0 {
                    pass.set_pipeline(&warp_depth);
                    pass.dispatch_workgroups(src_x, src_y, 1);
                    pass.set_pipeline(&warp_index);
                    pass.dispatch_workgroups(src_x, src_y, 1);
                }
                pass.set_pipeline(&gather);
                pass.dispatch_workgroups(all_x, all_y, 1);
                if split {
                    pass.set_pipeline(&fill_store);
                    pass.dispatch_workgroups(all_x, all_y, 1);
                    pass.set_pipeline(&accumulate_split);
                } else {
                    pass.set_pipeline(&fill);
                }
                pass.dispatch_workgroups(px_x, px_y, 1);
            }
            if k1 == views {
                pass.set_bind_group(0, &bg, &[0]);
                pass.set_pipeline(&finish);
                pass.dispatch_workgroups(px_x, px_y, 1);
            }
        }
        first = false;
        if k1 == views {
            let back = s.finish(
                encoder,
                &[(&out, 12 * n as u64), (&holes, 4 * views as u64)],
            )?;
            let rgb = f32s(&back[0]);
            let holes_total: usize = u32s(&back[1]).iter().map(|&c| c as usize).sum();
            let mut data: Vec<[f32; 3]> = rgb
                .par_chunks_exact(3)
                .map(|c| [c[0], c[1], c[2]])
                .collect();
            // Inactive pixels are the input times the gain, which the CPU
            // rounds once from f64: take its formula here so they are
            // bit-identical whatever the gain (a fractional stop's f32
            // product can be an ulp off). Pixels in parallel.
            let changed = data
                .par_iter_mut()
                .zip(plan.active.par_iter())
                .zip(plan.src_color.par_iter())
                .map(|((px, &a), src)| {
                    if a {
                        return false;
                    }
                    let exact = src.map(|v| exposed_f32(v as f64 * plan.gain));
                    let differs = exact.map(f32::to_bits) != px.map(f32::to_bits);
                    *px = exact;
                    differs
                })
                .reduce(|| false, |a, b| a | b);
            let img = Image::from_vec(w, h, data)?;
            // The gaps spherical aberration opens between the views, the
            // barrel's share of the unmoved pixels and the image-wide lens
            // effects (magnification per channel, breathing, natural
            // vignetting) on the host, as the CPU does.
            let changed = changed || plan.finishes();
            let img = plan.finish_image(img, aperture, p)?;
            // The device copy is the value only if nothing was corrected.
            if !changed {
                s.keep("color", out.clone(), 12 * n as u64);
            }
            return Ok((img, plan.report(holes_total)));
        }
        s.submit(encoder)?;
        // Guard: views >= 1 here.
        ctx.progress(k1 as f32 / views as f32);
        ctx.check_cancelled()?;
        next = last;
        done = k1;
    }
    Err(s.fail(s.ctx().error("refocus: no views rendered")))
}

#[cfg(test)]
mod tests {
    use super::{batch_size, fold};

    #[test]
    fn a_batch_is_what_the_context_asks_within_the_views_and_the_largest_buffer() {
        let n = 640 * 480;
        let slot = 32 * n as u64;
        assert_eq!(batch_size(16, 256, n, 1 << 40), 16);
        assert_eq!(batch_size(16, 7, n, 1 << 40), 7);
        assert_eq!(batch_size(16, 256, n, 5 * slot + slot / 2), 5);
        // one slot that does not fit: 1 (the allocation then says why)
        assert_eq!(batch_size(16, 256, n, slot / 2), 1);
        assert_eq!(batch_size(1, 256, n, 1 << 40), 1);
        assert_eq!(batch_size(0, 0, 0, 0), 1);
    }

    #[test]
    fn a_long_dispatch_folds_into_two_dimensions_covering_every_item() {
        for (n, max_dim) in [
            (1usize, 65535u32),
            (256, 65535),
            (257, 65535),
            (256 * 70_000, 65535),
            (1000, 2),
        ] {
            let (gx, gy, row) = fold(n, max_dim);
            assert!(gx <= max_dim && gy <= max_dim, "{n}");
            assert_eq!(row, gx * 256);
            // every item has an invocation, and not a whole row too many
            let total = gx as usize * gy as usize * 256;
            assert!(
                total >= n && total < n + row as usize + 256,
                "{n}: {gx} x {gy}"
            );
        }
    }
}
