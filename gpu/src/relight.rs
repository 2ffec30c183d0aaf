//! `Relight` on the device: the long sums over the VPLs of a scene-cached
//! object move ([`DeviceSums`]):
//!
//! - the direct term (`shaders/relight_direct.wgsl`), the sum over the VPLs
//!   of each pixel's cone of the light the object takes away
//!   ([`depthgraph_nodes::relight::direct`]);
//! - the object's received light (`shaders/relight_object.wgsl`), its
//!   visibility of every VPL through its own maps and the scene's
//!   ([`depthgraph_nodes::relight::object_light`]);
//! - the fill light (`shaders/relight_fill.wgsl`), the scene's own bounce
//!   at the composite's pixels and what of it the object's closed volume
//!   blocks ([`depthgraph_nodes::relight::fill`]), decided on the device
//!   and summed on the host like the object's light.
//!
//! The plans (which tiles, which VPLs in which order, which maps share a
//! frame, the lattices' nodes), the scene's part (cached by the engine),
//! the object's maps, the bounces and the composite stay on the CPU; the
//! shadow maps are uploaded once per move and serve both kernels, the
//! scene's kept on the device with the cached scene and the photo's depth
//! with its value (the next move finds them there);
//! `visibility` `paired` and `raycast` run on the CPU whole (the trace
//! says so).
//!
//! **The object's light agrees with the CPU bit for bit** (checked by the
//! parity tests): the device makes the decisions (two bits per surface and
//! VPL, the contact march included), the host adds the CPU's own f64
//! terms in the CPU's order; a decision whose f32 tests cannot settle it
//! is left to the host for that VPL (the CPU's own decision). So the
//! lattices blend and test the same values on both backends.
//!
//! **The direct term is the CPU's bit for bit too** (checked by the parity
//! tests): the device marks, per pixel, which places of its tile's VPL
//! list the object takes, and the host adds those VPLs' f64 terms `Φ cos`
//! in the list's order, as the CPU does; a pixel with a visibility test
//! whose f32 value lies within its rounding bound of the threshold is
//! recomputed with the CPU's own [`evaluate_pixel`]. ([`DE_TOL`] is 0: the
//! parity check's bound.)

use std::any::Any;
use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use depthgraph_graph::ports::Produced;
use depthgraph_graph::prelude::*;
use depthgraph_nodes::relight::direct::{DirectLight, DirectPlan, DirectSum, evaluate_pixel};
use depthgraph_nodes::relight::fill::{
    FillPlan, FillSeen, FillSum, sums_from_decisions as fill_from_decisions,
};
use depthgraph_nodes::relight::ism::ShadowMap;
use depthgraph_nodes::relight::node::{RelightIn, RelightOut, eval_with};
use depthgraph_nodes::relight::object_light::{
    ObjectLightPlan, ObjectLightSum, Seen, sums_from_decisions,
};
use depthgraph_nodes::relight::scene_cached::{MoveSums, RelightScene};
use depthgraph_nodes::relight::shading::{RelightParams, Surf, Visibility};
use glam::DVec3;
use rayon::prelude::*;

use crate::session::{Session, bytes_of, u32s};
use crate::shaders;

/// The bound of the device's direct term against the CPU's, relative to
/// `Σ_k Φ_k + ΔE` (module docs): none, the sums are the CPU's bits.
pub const DE_TOL: f64 = 0.0;

/// Empty texel on the device (the CPU's `-inf`).
const EMPTY: f32 = -1.0e30;
/// No scene map.
const NONE: u32 = u32::MAX;
/// Invocations per workgroup (`relight_direct.wgsl`).
const WORKGROUP: u32 = 64;

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct Params {
    count: u32,
    /// Invocations per row of the 2-D dispatch (a row's workgroups times
    /// [`WORKGROUP`]): pixel `k` is invocation `(k % row, k / row)`.
    row: u32,
    /// Where the pixels' output offsets start in the list buffer (after
    /// the tiles' VPL lists).
    offsets: u32,
    _pad: u32,
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct GpuPixel {
    pos: [f32; 3],
    cos_min: f32,
    n: [f32; 3],
    first: u32,
    axis: [f32; 3],
    last: u32,
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct GpuLight {
    dir: [f32; 3],
    bias_object: f32,
    power: [f32; 3],
    bias_scene: f32,
    group: u32,
    scene_map: u32,
    shared: u32,
    _pad: u32,
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct GpuMap {
    eu: [f32; 3],
    u0: f32,
    ev: [f32; 3],
    v0: f32,
    dir: [f32; 3],
    z0: f32,
    inv_texel: f32,
    res: u32,
    offset: u32,
    /// 0: the object's texels, 1: the scene's.
    pool: u32,
}

fn f3(v: DVec3) -> [f32; 3] {
    [v.x as f32, v.y as f32, v.z as f32]
}

/// What one move's direct term did on the device.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct DirectStats {
    /// Pixels the device evaluated.
    pub pixels: usize,
    /// Of those, recomputed on the host (a test f32 could not settle).
    pub recomputed: usize,
}

/// A depth map's identity while it is borrowed: its address and size.
type DepthId = (usize, (usize, usize));

/// [`DepthId`] of `d`.
fn depth_id(d: &DepthMap) -> DepthId {
    (std::ptr::from_ref(d) as usize, d.dims())
}

/// The header of map `m` relative to `origin`, its texels at `offset` of
/// texel pool `pool` (0: the object's, 1: the scene's); `Err` for a frame
/// the kernels cannot read as the CPU does (a non-finite axis, origin or
/// depth offset, or a texel size that is not a positive finite number: a
/// NaN coordinate would pass the kernels' range tests, which the CPU's
/// `!(u >= 0)` rejects).
fn header(m: &ShadowMap, origin: DVec3, offset: u32, pool: u32) -> Result<GpuMap, String> {
    let f = m.frame();
    let finite = f.eu.is_finite()
        && f.ev.is_finite()
        && f.dir.is_finite()
        && f.u0.is_finite()
        && f.v0.is_finite()
        && (f.inv_texel as f32).is_finite()
        && f.inv_texel > 0.0
        && (origin.dot(f.dir) as f32).is_finite();
    if !finite {
        return Err(
            "a shadow map whose frame the device cannot read (non-finite or a texel of size 0)"
                .into(),
        );
    }
    Ok(GpuMap {
        eu: f3(f.eu),
        u0: (f.u0 - origin.dot(f.eu)) as f32,
        ev: f3(f.ev),
        v0: (f.v0 - origin.dot(f.ev)) as f32,
        dir: f3(f.dir),
        z0: origin.dot(f.dir) as f32,
        inv_texel: f.inv_texel as f32,
        res: m.res as u32,
        offset,
        pool,
    })
}

/// Appends `m`'s texels to `texels`, the CPU's `-inf` as [`EMPTY`]; `Err`
/// for a texel the device cannot hold exactly (NaN, +inf or a finite value
/// at the sentinel's magnitude).
fn push_texels(m: &ShadowMap, texels: &mut Vec<f32>) -> Result<(), String> {
    for &t in &m.t {
        if t == f32::NEG_INFINITY {
            texels.push(EMPTY);
        } else if t.is_finite() && t.abs() < 1e29 {
            texels.push(t);
        } else {
            return Err(format!("a shadow-map texel holds {t}"));
        }
    }
    Ok(())
}

/// Where each map of `maps` starts in a pool holding all of them in order
/// (`None` for a missing map), and the pool's texel count.
fn offsets(maps: &[Option<ShadowMap>]) -> Result<(Vec<Option<u32>>, usize), String> {
    let mut at = 0usize;
    let mut out = Vec::with_capacity(maps.len());
    for m in maps {
        out.push(match m {
            Some(m) => {
                let o = u32::try_from(at)
                    .map_err(|_| "more shadow-map texels than the device indexes".to_string())?;
                at += m.t.len();
                Some(o)
            }
            None => None,
        });
    }
    u32::try_from(at).map_err(|_| "more shadow-map texels than the device indexes".to_string())?;
    Ok((out, at))
}

/// Shadow maps on the device for one move: the headers of the object's
/// maps (one per group) and of the scene's, the object's texels, and the
/// scene's texels (kept on the device with the cached scene when the move
/// names it), with the index of each VPL's scene map.
pub struct MoveMaps {
    maps: crate::context::PooledBuffer,
    texels: crate::context::PooledBuffer,
    scene_texels: Arc<crate::context::PooledBuffer>,
    /// Per VPL: its scene map's index in `maps` ([`NONE`]: none uploaded).
    scene_index: Vec<u32>,
    /// Object maps uploaded (the first headers).
    groups: usize,
    /// The origin the coordinates are relative to.
    origin: DVec3,
    /// The photo's depth for the contact march, once uploaded.
    depth: Option<Arc<crate::context::PooledBuffer>>,
    /// Which depth map `depth` holds ([`depth_id`]): a plan marching
    /// another one uploads its own.
    depth_of: Option<DepthId>,
    /// The map lists uploaded ([`list_key`]).
    key: [usize; 4],
}

/// Which two map lists a plan reads: their addresses and lengths (lists
/// that live through the move: the engine's scene and the move's maps).
fn list_key(object_maps: &[Option<ShadowMap>], scene_maps: &[Option<ShadowMap>]) -> [usize; 4] {
    [
        object_maps.as_ptr() as usize,
        object_maps.len(),
        scene_maps.as_ptr() as usize,
        scene_maps.len(),
    ]
}

/// The scene's maps as the device keeps them: all of them, one after
/// another, under the cached scene's value (`scene`: its identity; `None`
/// uploads the maps `want` picks for this move alone). The texel offset of
/// each map (`None`: not uploaded).
fn scene_pool(
    s: &mut Session,
    scene_maps: &[Option<ShadowMap>],
    scene: Option<&Arc<dyn Any + Send + Sync>>,
    want: impl Fn(usize) -> bool,
) -> Result<(Arc<crate::context::PooledBuffer>, Vec<Option<u32>>), NodeError> {
    if let Some(key) = scene {
        let (at, total) = offsets(scene_maps).map_err(|why| s.too_large(&why))?;
        if let Some(b) = s.ctx().resident(key) {
            s.stats.resident_hits += 1;
            return Ok((b, at));
        }
        let mut texels = Vec::with_capacity(total);
        for m in scene_maps.iter().flatten() {
            push_texels(m, &mut texels).map_err(|why| s.too_large(&why))?;
        }
        let b = Arc::new(s.upload(bytes_of(&texels))?);
        s.ctx()
            .keep_resident(key, b.clone(), (4 * texels.len()) as u64);
        return Ok((b, at));
    }
    let mut texels = Vec::new();
    let mut at = Vec::with_capacity(scene_maps.len());
    for (j, m) in scene_maps.iter().enumerate() {
        at.push(match m {
            Some(m) if want(j) => {
                let o = u32::try_from(texels.len())
                    .map_err(|_| s.too_large("more shadow-map texels than the device indexes"))?;
                push_texels(m, &mut texels).map_err(|why| s.too_large(&why))?;
                Some(o)
            }
            _ => None,
        });
    }
    Ok((Arc::new(s.upload(bytes_of(&texels))?), at))
}

/// Uploads the object's maps and the scene's (the scene's pool from
/// [`scene_pool`]), relative to `origin`.
fn upload_maps(
    s: &mut Session,
    object_maps: &[Option<ShadowMap>],
    scene_maps: &[Option<ShadowMap>],
    origin: DVec3,
    scene: Option<&Arc<dyn Any + Send + Sync>>,
    want: impl Fn(usize) -> bool,
) -> Result<MoveMaps, NodeError> {
    let mut headers = Vec::with_capacity(object_maps.len() + scene_maps.len());
    let mut texels = Vec::new();
    for m in object_maps {
        let Some(m) = m else {
            headers.push(GpuMap::zeroed());
            continue;
        };
        let offset = u32::try_from(texels.len())
            .map_err(|_| s.too_large("more shadow-map texels than the device indexes"))?;
        push_texels(m, &mut texels).map_err(|why| s.too_large(&why))?;
        headers.push(header(m, origin, offset, 0).map_err(|why| s.too_large(&why))?);
    }
    let (scene_texels, at) = scene_pool(s, scene_maps, scene, want)?;
    let mut scene_index = Vec::with_capacity(scene_maps.len());
    for (m, offset) in scene_maps.iter().zip(&at) {
        scene_index.push(match (m, offset) {
            (Some(m), Some(offset)) => {
                headers.push(header(m, origin, *offset, 1).map_err(|why| s.too_large(&why))?);
                (headers.len() - 1) as u32
            }
            _ => NONE,
        });
    }
    Ok(MoveMaps {
        maps: s.upload(bytes_of(&headers))?,
        texels: s.upload(bytes_of(&texels))?,
        scene_texels,
        scene_index,
        groups: object_maps.len(),
        origin,
        depth: None,
        depth_of: None,
        key: list_key(object_maps, scene_maps),
    })
}

/// One dispatch of `kernel` over a `grid` of workgroups with `inputs`
/// bound in order and the output buffer last; the output's words.
fn run_flat(
    s: &mut Session,
    kernel: &wgpu::ComputePipeline,
    inputs: &[&wgpu::Buffer],
    (out, bytes): (&crate::context::PooledBuffer, u64),
    (gx, gy): (u32, u32),
) -> Result<Vec<u32>, NodeError> {
    let mut buffers = inputs.to_vec();
    buffers.push(out);
    let bg = s.bind(kernel, &buffers);
    let mut encoder = s.encoder();
    {
        let mut pass = encoder.begin_compute_pass(&Default::default());
        pass.set_pipeline(kernel);
        pass.set_bind_group(0, &bg, &[]);
        pass.dispatch_workgroups(gx, gy, 1);
    }
    let back = s.finish(encoder, &[(out, bytes)])?;
    Ok(u32s(&back[0]))
}

/// A light as the kernels read it (its object map's bias constant for the
/// kernel's receivers); `groups`: the object maps uploaded.
fn gpu_light(l: &DirectLight, scene_map: u32, groups: usize) -> GpuLight {
    GpuLight {
        dir: f3(l.dir),
        bias_object: l.bias_object as f32,
        power: l.power.map(|v| v as f32),
        bias_scene: l.bias_scene as f32,
        // a VPL without an object map: none (the object shadows nothing)
        group: if l.group < groups {
            l.group as u32
        } else {
            NONE
        },
        scene_map,
        shared: u32::from(l.shared),
        _pad: 0,
    }
}

/// The direct term of `plan` on the device (module docs): one sum per
/// pixel of the plan, tile after tile, the marked pixels recomputed here.
pub fn direct(
    s: &mut Session,
    plan: &DirectPlan,
    stats: &mut DirectStats,
) -> Result<Vec<DirectSum>, NodeError> {
    let mut used = vec![false; plan.lights.len()];
    for tile in &plan.tiles {
        for &j in &tile.vpls {
            if let Some(u) = used.get_mut(j) {
                *u = true;
            }
        }
    }
    let maps = upload_maps(
        s,
        plan.object_maps,
        plan.scene_maps,
        plan.centre,
        None,
        |j| used.get(j).copied().unwrap_or(false),
    )?;
    direct_with(s, plan, &maps, stats)
}

/// [`direct`] with the maps already on the device (`maps` must hold every
/// scene map the plan's tiles read, relative to the plan's centre).
pub fn direct_with(
    s: &mut Session,
    plan: &DirectPlan,
    maps: &MoveMaps,
    stats: &mut DirectStats,
) -> Result<Vec<DirectSum>, NodeError> {
    if maps.origin != plan.centre || maps.groups != plan.object_maps.len() {
        return Err(NodeError::Internal(
            "the device's shadow maps belong to another move".into(),
        ));
    }
    let origin = plan.centre;
    // the pixels of tiles with VPLs, their lists one after another
    let mut pixels = Vec::new();
    let mut list: Vec<u32> = Vec::new();
    let mut at = Vec::new(); // (tile, pixel) of each device pixel
    for (t, tile) in plan.tiles.iter().enumerate() {
        if tile.vpls.is_empty() || tile.pixels.is_empty() {
            continue;
        }
        let first = list.len() as u32;
        list.extend(tile.vpls.iter().map(|&j| j as u32));
        let last = list.len() as u32;
        for (k, px) in tile.pixels.iter().enumerate() {
            pixels.push(GpuPixel {
                pos: f3(px.pos - origin),
                // every direction: a value the cone's cosine never takes
                cos_min: if px.cone_all {
                    -2.0
                } else {
                    px.cone_cos_min as f32
                },
                n: f3(px.n),
                first,
                axis: f3(px.cone_axis),
                last,
            });
            at.push((t, k));
        }
    }
    let mut sums = vec![DirectSum::default(); plan.pixel_count()];
    if pixels.is_empty() {
        return Ok(sums);
    }
    // A 2-D grid of workgroups (rows of at most the device's limit per
    // dimension, 65 535 on most), so a plan may exceed 4.19 M pixels.
    let Some((gx, gy)) = s.ctx().flat_grid(pixels.len(), WORKGROUP) else {
        return Err(s.too_large(&format!(
            "{} pixels of the direct term need more workgroups than the device dispatches",
            pixels.len()
        )));
    };
    let mut read = vec![false; plan.lights.len()];
    for &j in &list {
        if let Some(r) = read.get_mut(j as usize) {
            *r = true;
        }
    }
    let mut lights = Vec::with_capacity(plan.lights.len());
    for (j, l) in plan.lights.iter().enumerate() {
        let scene_map = maps.scene_index.get(j).copied().unwrap_or(NONE);
        // a tile reads VPL j: its scene map must be there
        if scene_map == NONE && read[j] && plan.scene_maps.get(j).is_some_and(Option::is_some) {
            return Err(NodeError::Internal(format!(
                "the scene map of VPL {j} is not on the device"
            )));
        }
        lights.push(gpu_light(l, scene_map, maps.groups));
    }
    let n = pixels.len();
    // per pixel: a bit per place of its tile's list, then a word of flags,
    // at its own offset (a pixel returns its tile's words, not the longest
    // list's); the offsets follow the lists in the list buffer
    let too_many = || format!("{n} pixels of the direct term are more than the device indexes");
    let mut offsets: Vec<(usize, usize)> = Vec::with_capacity(n);
    let mut total = 0usize;
    for &(t, _) in &at {
        let words = plan.tiles[t].vpls.len().div_ceil(32);
        offsets.push((total, words));
        total += words + 1;
    }
    let offsets_at = list.len();
    let (Ok(count), Ok(offsets_u32), true) = (
        u32::try_from(n),
        u32::try_from(offsets_at),
        u32::try_from(total).is_ok() && u32::try_from(offsets_at + n).is_ok(),
    ) else {
        return Err(s.too_large(&too_many()));
    };
    list.extend(offsets.iter().map(|&(o, _)| o as u32));
    let kernel = s.kernel(&shaders::RELIGHT_DIRECT)?;
    let params = Params {
        count,
        row: gx * WORKGROUP,
        offsets: offsets_u32,
        _pad: 0,
    };
    let uniform = s.uniform(bytemuck::bytes_of(&params))?;
    let b_pixels = s.upload(bytes_of(&pixels))?;
    let b_list = s.upload(bytes_of(&list))?;
    let b_lights = s.upload(bytes_of(&lights))?;
    let bytes = 4 * total as u64;
    let out = s.scratch(bytes)?;
    let all = run_flat(
        s,
        &kernel,
        &[
            &uniform,
            &b_pixels,
            &b_list,
            &b_lights,
            &maps.maps,
            &maps.texels,
            &maps.scene_texels,
        ],
        (&out, bytes),
        (gx, gy),
    )?;
    if all.len() != total {
        return Err(NodeError::Internal(format!(
            "the device returned {} words for {n} pixels",
            all.len()
        )));
    }
    let starts = plan.tile_starts();
    stats.pixels += n;
    // the host's sums: the CPU's terms of the VPLs the device marked, in
    // the list's order (in parallel)
    let decided: Vec<(DirectSum, bool)> = offsets
        .par_iter()
        .zip(at.par_iter())
        .map(|(&(o, words), &(t, k))| {
            let w = &all[o..=o + words];
            let tile = &plan.tiles[t];
            if w[words] & 2 != 0 {
                return (evaluate_pixel(plan, tile, k), true);
            }
            let px = &tile.pixels[k];
            let mut sum = DirectSum::default();
            for (b, &j) in tile.vpls.iter().enumerate() {
                if w[b / 32] & (1 << (b % 32)) == 0 {
                    continue;
                }
                let l = &plan.lights[j];
                let cos = px.n.dot(l.dir);
                sum.hit = true;
                for (e, power) in sum.de.iter_mut().zip(l.power) {
                    *e += power * cos;
                }
            }
            (sum, false)
        })
        .collect();
    for ((sum, again), &(t, k)) in decided.into_iter().zip(&at) {
        stats.recomputed += usize::from(again);
        sums[starts[t] + k] = sum;
    }
    Ok(sums)
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct ObjectParams {
    count: u32,
    /// Invocations per row of the 2-D dispatch.
    row: u32,
    lights: u32,
    /// Words of two-bit decisions per surface.
    words: u32,
    contact: u32,
    width: u32,
    height: u32,
    max_steps: u32,
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    thickness: f32,
    _pad: [f32; 3],
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct GpuSurface {
    pos: [f32; 3],
    _p0: f32,
    n: [f32; 3],
    _p1: f32,
    at: [f32; 3],
    _p2: f32,
}

/// The most steps of one contact march on the device (the CPU's default
/// is 8); a plan asking more runs on the CPU.
pub const MAX_MARCH_STEPS: u32 = 4096;

/// What a decisions kernel (the object's light, the fill) did on the
/// device.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct DecisionStats {
    /// Surfaces the device decided.
    pub surfaces: usize,
    /// Decisions of one surface and VPL left to the host (a test f32
    /// could not settle).
    pub asked: usize,
    /// Dispatches of the decision kernel (a call larger than
    /// [`GpuContext::surfaces_per_dispatch`](crate::GpuContext::surfaces_per_dispatch)
    /// takes several).
    pub dispatches: usize,
}

/// What the object's light did on the device.
pub type ObjectLightStats = DecisionStats;

/// Code-2 pairs ([`Seen::Ask`]) among the sixteen of a word.
fn asked_in(w: u32) -> usize {
    let (hi, lo) = ((w >> 1) & 0x5555_5555, w & 0x5555_5555);
    (hi & !lo).count_ones() as usize
}

/// The object's received light at `surfs` on the device (module docs):
/// the device's decisions, the host's f64 sums.
pub fn object_light(
    s: &mut Session,
    plan: &ObjectLightPlan,
    surfs: &[Surf],
    stats: &mut ObjectLightStats,
) -> Result<Vec<ObjectLightSum>, NodeError> {
    let maps = upload_maps(
        s,
        plan.object_maps,
        plan.scene_maps,
        plan.centre,
        None,
        |_| true,
    )?;
    object_light_with(s, plan, surfs, &maps, stats)
}

/// [`object_light`] with the maps already on the device (`maps` must
/// hold every scene map, relative to the plan's centre).
pub fn object_light_with(
    s: &mut Session,
    plan: &ObjectLightPlan,
    surfs: &[Surf],
    maps: &MoveMaps,
    stats: &mut ObjectLightStats,
) -> Result<Vec<ObjectLightSum>, NodeError> {
    by_dispatch(s, plan.lights.len(), surfs, |s, chunk| {
        object_light_chunk(s, plan, chunk, maps, stats)
    })
}

/// `run` over `surfs` in dispatches of at most [`chunk_surfaces`]
/// surfaces (of `vpls` VPLs' decisions), the results in order.
fn by_dispatch<T>(
    s: &mut Session,
    vpls: usize,
    surfs: &[Surf],
    mut run: impl FnMut(&mut Session, &[Surf]) -> Result<Vec<T>, NodeError>,
) -> Result<Vec<T>, NodeError> {
    let per = chunk_surfaces(s, vpls);
    let mut out = Vec::with_capacity(surfs.len());
    for chunk in surfs.chunks(per) {
        out.extend(run(s, chunk)?);
    }
    Ok(out)
}

/// The size of one dispatch of a decisions kernel: `count` surfaces of
/// `lights` VPLs, `words` words of two-bit codes each, on a grid of
/// workgroups.
struct Decisions {
    count: u32,
    lights: u32,
    words: usize,
    grid: (u32, u32),
}

/// [`Decisions`] of `n` surfaces and `nl` VPLs (`nl > 0`), or the device's
/// refusal when it cannot index them (`what` names the VPLs).
fn decisions(s: &mut Session, n: usize, nl: usize, what: &str) -> Result<Decisions, NodeError> {
    let words = nl.div_ceil(16);
    let too_many = || format!("{n} surfaces of {nl} {what} are more than the device indexes");
    let (Ok(count), Ok(lights), true) = (
        u32::try_from(n),
        u32::try_from(nl),
        n.checked_mul(words)
            .is_some_and(|t| u32::try_from(t).is_ok()),
    ) else {
        return Err(s.too_large(&too_many()));
    };
    let Some(grid) = s.ctx().flat_grid(n, WORKGROUP) else {
        return Err(s.too_large(&too_many()));
    };
    Ok(Decisions {
        count,
        lights,
        words,
        grid,
    })
}

/// One dispatch of a decisions kernel with `inputs` bound in order (the
/// output last) and the host's sums of its codes ([`host_sums`]), counted
/// in `stats`.
fn run_decisions<T: Send>(
    s: &mut Session,
    kernel: &wgpu::ComputePipeline,
    inputs: &[&wgpu::Buffer],
    d: &Decisions,
    surfs: &[Surf],
    stats: &mut DecisionStats,
    sum: impl Fn(&[u32], &Surf) -> T + Sync,
) -> Result<Vec<T>, NodeError> {
    let bytes = 4 * (surfs.len() * d.words) as u64;
    let out = s.scratch(bytes)?;
    let all = run_flat(s, kernel, inputs, (&out, bytes), d.grid)?;
    let (sums, asked) = host_sums(&all, d.words, surfs, sum)?;
    stats.surfaces += surfs.len();
    stats.asked += asked;
    stats.dispatches += 1;
    Ok(sums)
}

/// Surfaces per dispatch of a decisions kernel over `vpls` VPLs: their
/// decisions within the largest buffer the device binds, and at most
/// [`GpuContext::surfaces_per_dispatch`](crate::GpuContext::surfaces_per_dispatch)
/// (65 536 unless the request asked fewer: a dispatch's run time stays
/// short, as a driver's watchdog ends long ones).
fn chunk_surfaces(s: &Session, vpls: usize) -> usize {
    // guard: at least one word per surface, so no division by zero
    let bytes = 4 * vpls.div_ceil(16).max(1) as u64;
    usize::try_from(s.ctx().max_buffer() / bytes)
        .unwrap_or(usize::MAX)
        .clamp(1, s.ctx().surfaces_per_dispatch())
}

/// [`object_light_with`] of one dispatch.
fn object_light_chunk(
    s: &mut Session,
    plan: &ObjectLightPlan,
    surfs: &[Surf],
    maps: &MoveMaps,
    stats: &mut ObjectLightStats,
) -> Result<Vec<ObjectLightSum>, NodeError> {
    if maps.origin != plan.centre || maps.groups != plan.object_maps.len() {
        return Err(NodeError::Internal(
            "the device's shadow maps belong to another move".into(),
        ));
    }
    let n = surfs.len();
    let nl = plan.lights.len();
    if n == 0 || nl == 0 {
        return Ok(vec![ObjectLightSum::default(); n]);
    }
    let d = decisions(s, n, nl, "VPLs")?;
    let origin = plan.centre;
    let mut lights = Vec::with_capacity(nl);
    for (j, l) in plan.lights.iter().enumerate() {
        let scene_map = maps.scene_index.get(j).copied().unwrap_or(NONE);
        if scene_map == NONE && plan.scene_maps.get(j).is_some_and(Option::is_some) {
            return Err(NodeError::Internal(format!(
                "the scene map of VPL {j} is not on the device"
            )));
        }
        lights.push(gpu_light(l, scene_map, maps.groups));
    }
    let surfaces: Vec<GpuSurface> = surfs
        .iter()
        .map(|q| GpuSurface {
            pos: f3(q.pos - origin),
            _p0: 0.0,
            n: f3(q.n),
            _p1: 0.0,
            at: f3(q.pos),
            _p2: 0.0,
        })
        .collect();
    // the photo's depth for the contact march (the move's upload, else
    // one here; one word when the march is off)
    let mut upload = None;
    let march = match &plan.contact {
        Some(c) => {
            let (w, h) = c.depth.dims();
            let (Ok(w), Ok(h)) = (u32::try_from(w), u32::try_from(h)) else {
                return Err(s.too_large("a depth map larger than the device indexes"));
            };
            if maps.depth_of != Some(depth_id(c.depth)) {
                upload = Some(s.upload(bytes_of(c.depth.as_slice()))?);
            }
            Some((w, h, c))
        }
        None => {
            upload = Some(s.upload(&[0u8; 4])?);
            None
        }
    };
    let depth: &wgpu::Buffer = match (&upload, &maps.depth) {
        (Some(b), _) => b,
        (None, Some(b)) => b,
        (None, None) => {
            return Err(NodeError::Internal("no depth buffer for the march".into()));
        }
    };
    // a march of more steps than MAX_MARCH_STEPS stays on the CPU (one
    // dispatch must end well within a driver's watchdog)
    let max_steps = match march {
        Some(m) => match u32::try_from(m.2.params.max_steps) {
            Ok(n) if n <= MAX_MARCH_STEPS => n,
            _ => {
                return Err(s.too_large(&format!(
                    "a contact march of {} steps (the device marches at most {MAX_MARCH_STEPS})",
                    m.2.params.max_steps
                )));
            }
        },
        None => 0,
    };
    let kernel = s.kernel(&shaders::RELIGHT_OBJECT)?;
    let params = ObjectParams {
        count: d.count,
        row: d.grid.0 * WORKGROUP,
        lights: d.lights,
        words: d.words as u32,
        contact: u32::from(march.is_some()),
        width: march.map_or(0, |m| m.0),
        height: march.map_or(0, |m| m.1),
        max_steps,
        // the CPU's footprint guard (`contact::occluded`: fx at least 1e-9)
        fx: march.map_or(1.0, |m| m.2.k.fx.max(1e-9) as f32),
        fy: march.map_or(1.0, |m| m.2.k.fy as f32),
        cx: march.map_or(0.0, |m| m.2.k.cx as f32),
        cy: march.map_or(0.0, |m| m.2.k.cy as f32),
        thickness: march.map_or(0.0, |m| m.2.params.thickness_m as f32),
        _pad: [0.0; 3],
    };
    let uniform = s.uniform(bytemuck::bytes_of(&params))?;
    let b_surfaces = s.upload(bytes_of(&surfaces))?;
    let b_lights = s.upload(bytes_of(&lights))?;
    let inputs = [
        &*uniform,
        &b_surfaces,
        &b_lights,
        &maps.maps,
        &maps.texels,
        &maps.scene_texels,
        depth,
    ];
    run_decisions(s, &kernel, &inputs, &d, surfs, stats, |w, q| {
        sums_from_decisions(plan, q, |j| Seen::from_bits(code(w, j)))
    })
}

/// VPL `j`'s two-bit decision in a surface's words.
#[inline]
fn code(w: &[u32], j: usize) -> u32 {
    w[j / 16] >> (2 * (j % 16))
}

/// The host's part of a decisions kernel: `words` words of two-bit
/// decisions per surface of `surfs` in `all`, summed by `sum` (in
/// parallel); the sums and the decisions left to the host (code 2).
fn host_sums<T: Send>(
    all: &[u32],
    words: usize,
    surfs: &[Surf],
    sum: impl Fn(&[u32], &Surf) -> T + Sync,
) -> Result<(Vec<T>, usize), NodeError> {
    if all.len() != words * surfs.len() {
        return Err(NodeError::Internal(format!(
            "the device returned {} words for {} surfaces of {words} words",
            all.len(),
            surfs.len()
        )));
    }
    let out: Vec<(T, usize)> = all
        .par_chunks_exact(words)
        .zip(surfs)
        .map(|(w, q)| (sum(w, q), w.iter().map(|&x| asked_in(x)).sum()))
        .collect();
    let asked = out.iter().map(|(_, a)| a).sum();
    Ok((out.into_iter().map(|(t, _)| t).collect(), asked))
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct FillParams {
    count: u32,
    /// Invocations per row of the 2-D dispatch.
    row: u32,
    vpls: u32,
    /// Words of two-bit decisions per surface.
    words: u32,
    width: u32,
    height: u32,
    _pad: [u32; 2],
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    centre: [f32; 3],
    radius: f32,
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct GpuPoint {
    pos: [f32; 3],
    _p0: f32,
    n: [f32; 3],
    _p1: f32,
}

/// What the fill did on the device.
pub type FillStats = DecisionStats;

/// The object's volume on the device: its front and back depth maps.
pub struct VolumeMaps {
    front: crate::context::PooledBuffer,
    back: crate::context::PooledBuffer,
    /// The depth maps uploaded (their addresses and lengths).
    key: [usize; 4],
}

/// Uploads the front and back depth maps of `plan`'s volume.
fn upload_volume(s: &mut Session, plan: &FillPlan) -> Result<VolumeMaps, NodeError> {
    let (_, front, back, _, _) = plan.volume.parts();
    Ok(VolumeMaps {
        front: s.upload(bytes_of(front.as_slice()))?,
        back: s.upload(bytes_of(back.as_slice()))?,
        key: volume_key(plan),
    })
}

fn volume_key(plan: &FillPlan) -> [usize; 4] {
    let (_, front, back, _, _) = plan.volume.parts();
    [
        front.as_slice().as_ptr() as usize,
        front.as_slice().len(),
        back.as_slice().as_ptr() as usize,
        back.as_slice().len(),
    ]
}

/// The fill at `surfs` on the device (module docs of
/// [`depthgraph_nodes::relight::fill`]): the device's decisions, the
/// host's f64 sums.
pub fn fill(
    s: &mut Session,
    plan: &FillPlan,
    surfs: &[Surf],
    stats: &mut FillStats,
) -> Result<Vec<FillSum>, NodeError> {
    let volume = upload_volume(s, plan)?;
    fill_with(s, plan, surfs, &volume, stats)
}

/// [`fill`] with the volume's maps already on the device.
pub fn fill_with(
    s: &mut Session,
    plan: &FillPlan,
    surfs: &[Surf],
    volume: &VolumeMaps,
    stats: &mut FillStats,
) -> Result<Vec<FillSum>, NodeError> {
    by_dispatch(s, plan.vpls.len(), surfs, |s, chunk| {
        fill_chunk(s, plan, chunk, volume, stats)
    })
}

/// [`fill_with`] of one dispatch.
fn fill_chunk(
    s: &mut Session,
    plan: &FillPlan,
    surfs: &[Surf],
    volume: &VolumeMaps,
    stats: &mut FillStats,
) -> Result<Vec<FillSum>, NodeError> {
    if volume.key != volume_key(plan) {
        return Err(NodeError::Internal(
            "the device's volume maps belong to another move".into(),
        ));
    }
    let n = surfs.len();
    let nv = plan.vpls.len();
    if n == 0 || nv == 0 {
        return Ok(vec![[0.0; 6]; n]);
    }
    let (k, front, _, centre, radius) = plan.volume.parts();
    let (w, h) = front.dims();
    let d = decisions(s, n, nv, "fill VPLs")?;
    let (Ok(w32), Ok(h32)) = (u32::try_from(w), u32::try_from(h)) else {
        return Err(s.too_large("an object volume larger than the device indexes"));
    };
    let point = |pos: DVec3, n: DVec3| GpuPoint {
        pos: f3(pos),
        _p0: 0.0,
        n: f3(n),
        _p1: 0.0,
    };
    // positions relative to the ball's centre (subtracted in f64): the
    // chord's closest approach then needs no f32 difference of metres-away
    // points
    let surfaces: Vec<GpuPoint> = surfs.iter().map(|q| point(q.pos - centre, q.n)).collect();
    let vpls: Vec<GpuPoint> = plan
        .vpls
        .iter()
        .map(|(q, nq, _)| point(*q - centre, *nq))
        .collect();
    let kernel = s.kernel(&shaders::RELIGHT_FILL)?;
    let params = FillParams {
        count: d.count,
        row: d.grid.0 * WORKGROUP,
        vpls: d.lights,
        words: d.words as u32,
        width: w32,
        height: h32,
        _pad: [0; 2],
        fx: k.fx as f32,
        fy: k.fy as f32,
        cx: k.cx as f32,
        cy: k.cy as f32,
        centre: f3(centre),
        radius: radius as f32,
    };
    let uniform = s.uniform(bytemuck::bytes_of(&params))?;
    let b_surfaces = s.upload(bytes_of(&surfaces))?;
    let b_vpls = s.upload(bytes_of(&vpls))?;
    let inputs = [&*uniform, &b_surfaces, &b_vpls, &volume.front, &volume.back];
    run_decisions(s, &kernel, &inputs, &d, surfs, stats, |w, q| {
        fill_from_decisions(plan, q, |j| FillSeen::from_bits(code(w, j)))
    })
}

/// The long sums of a move on the device ([`MoveSums`]), the shadow maps
/// and the object's volume uploaded once for the move (the scene's maps
/// kept on the device with the cached scene, the photo's depth with its
/// value, when named); what each did. One move at a time: what a move
/// uploaded is known by its lists' addresses, so a caller that drives the
/// evaluators itself calls [`MoveSums::begin_move`] between moves, as
/// `relight_moved_with` does.
pub struct DeviceSums<'s, 'a> {
    session: &'s mut Session<'a>,
    maps: Option<MoveMaps>,
    volume: Option<VolumeMaps>,
    scene: Option<Arc<RelightScene>>,
    depth: Option<Arc<DepthMap>>,
    /// The direct term's work.
    pub direct: DirectStats,
    /// The object's light's work.
    pub object: ObjectLightStats,
    /// The fill's work.
    pub fill: FillStats,
}

impl<'s, 'a> DeviceSums<'s, 'a> {
    /// Sums of one move in `session`.
    pub fn new(session: &'s mut Session<'a>) -> Self {
        DeviceSums {
            session,
            maps: None,
            volume: None,
            scene: None,
            depth: None,
            direct: DirectStats::default(),
            object: ObjectLightStats::default(),
            fill: FillStats::default(),
        }
    }

    /// The photo's depth as a value: its upload is kept on the device with
    /// it (the next move finds it there), where the march reads this map.
    pub fn with_depth(mut self, depth: Arc<DepthMap>) -> Self {
        self.depth = Some(depth);
        self
    }

    /// The maps a plan reads: the move's (its object maps and every scene
    /// map), uploaded on first use and kept for the move's other kernel;
    /// the scene's texels found on the device when the named scene's maps
    /// are the plan's. Another plan's lists (the capture map's object maps,
    /// with no scene) are uploaded for that plan alone ([`Self::keep`]).
    fn maps(
        &mut self,
        object_maps: &[Option<ShadowMap>],
        scene_maps: &[Option<ShadowMap>],
        origin: DVec3,
    ) -> Result<MoveMaps, NodeError> {
        let key = list_key(object_maps, scene_maps);
        match self.maps.take() {
            Some(m) if m.origin == origin && m.key == key => Ok(m),
            other => {
                self.maps = other;
                let key: Option<Arc<dyn Any + Send + Sync>> = self
                    .scene
                    .as_ref()
                    .filter(|sc| std::ptr::eq(sc.scene_maps(), scene_maps))
                    .map(|sc| sc.clone() as Arc<dyn Any + Send + Sync>);
                upload_maps(
                    self.session,
                    object_maps,
                    scene_maps,
                    origin,
                    key.as_ref(),
                    |_| true,
                )
            }
        }
    }
}

impl DeviceSums<'_, '_> {
    /// Keeps `maps` for the move's next kernel when they are the move's
    /// own (they carry the scene's maps) and none are kept yet; a plan's
    /// own upload (no scene maps) is dropped.
    fn keep(&mut self, maps: MoveMaps) {
        if self.maps.is_none() && maps.key[3] > 0 {
            self.maps = Some(maps);
        }
    }
}

impl MoveSums for DeviceSums<'_, '_> {
    fn begin_move(&mut self) {
        self.maps = None;
        self.volume = None;
    }

    fn fill(&mut self, plan: &FillPlan, surfs: &[Surf]) -> Result<Vec<FillSum>, NodeError> {
        if surfs.is_empty() || plan.vpls.is_empty() {
            return Ok(vec![[0.0; 6]; surfs.len()]);
        }
        // the volume's maps once per move
        let volume = match self.volume.take() {
            Some(v) if v.key == volume_key(plan) => v,
            _ => upload_volume(self.session, plan)?,
        };
        let r = fill_with(self.session, plan, surfs, &volume, &mut self.fill);
        self.volume = Some(volume);
        r
    }

    fn scene(&mut self, scene: &Arc<RelightScene>) {
        self.scene = Some(scene.clone());
    }

    fn direct(&mut self, plan: &DirectPlan) -> Result<Vec<DirectSum>, NodeError> {
        let maps = self.maps(plan.object_maps, plan.scene_maps, plan.centre)?;
        let r = direct_with(self.session, plan, &maps, &mut self.direct);
        self.keep(maps);
        r
    }

    fn object_light(
        &mut self,
        plan: &ObjectLightPlan,
        surfs: &[Surf],
    ) -> Result<Vec<ObjectLightSum>, NodeError> {
        let mut maps = self.maps(plan.object_maps, plan.scene_maps, plan.centre)?;
        // the photo's depth once per move, or found on the device
        if let Some(c) = &plan.contact
            && maps.depth_of != Some(depth_id(c.depth))
        {
            let bytes = bytes_of(c.depth.as_slice());
            maps.depth = Some(match &self.depth {
                Some(d) if std::ptr::eq(&**d, c.depth) => self.session.image(d, bytes)?,
                _ => Arc::new(self.session.upload(bytes)?),
            });
            maps.depth_of = Some(depth_id(c.depth));
        }
        let r = object_light_with(self.session, plan, surfs, &maps, &mut self.object);
        self.keep(maps);
        r
    }
}

/// The device evaluation of `Relight` (module docs).
pub fn eval(
    s: &mut Session,
    ctx: &EvalCtx,
    i: RelightIn,
    p: &RelightParams,
) -> Result<Produced<RelightOut>, NodeError> {
    if p.visibility != Visibility::SceneCached {
        return Err(s.too_large(&format!(
            "visibility \"{}\" has no device kernel (the device evaluates the scene-cached move)",
            p.visibility.name()
        )));
    }
    let mut sums = DeviceSums::new(s).with_depth(i.depth.clone());
    let mut r = eval_with(ctx, i, p, &mut sums)?;
    if r.passthrough.is_none() {
        let (d, o, f) = (sums.direct, sums.object, sums.fill);
        let line = format!(
            "direct term on the device: {} pixels, {} recomputed on the host; \
             object light on the device: {} surfaces, {} decisions left to the host; \
             fill on the device: {} surfaces, {} decisions left to the host",
            d.pixels, d.recomputed, o.surfaces, o.asked, f.surfaces, f.asked
        );
        r.report = Some(match r.report.take() {
            Some(prev) => format!("{prev}; {line}"),
            None => line,
        });
    }
    Ok(r)
}
