//! `Relight` on the device: the direct term of a scene-cached object move
//! (`shaders/relight_direct.wgsl`), the sum over the VPLs of each pixel's
//! cone of the light the object takes away
//! ([`depthgraph_nodes::relight::direct`]). The plan (which tiles, which
//! VPLs in which order, which maps share a frame), the scene's part (cached
//! by the engine), the object's maps, its shading, the bounces and the
//! composite stay on the CPU; `visibility` `paired` and `raycast` run on
//! the CPU whole (the trace says so).
//!
//! **Agreement with the CPU** (checked by the parity tests): every pixel's
//! decisions are the CPU's — each visibility test whose f32 value lies
//! within its rounding bound of the threshold marks the pixel, and the host
//! recomputes marked pixels with the CPU's own
//! [`evaluate_pixel`] —
//! so the pixels the object shades (`hit`) are the same set; the sums are
//! compensated f32 sums of f32 terms `Φ cos`, within
//! `|Δ| <= DE_TOL * (Σ_k Φ_k + ΔE)` of the CPU's f64 sums ([`DE_TOL`]:
//! each term's `cos` carries a few ulps of its f32 normal and direction).

use bytemuck::{Pod, Zeroable};
use depthgraph_graph::ports::Produced;
use depthgraph_graph::prelude::*;
use depthgraph_nodes::relight::direct::{DirectPlan, DirectSum, evaluate_pixel};
use depthgraph_nodes::relight::ism::ShadowMap;
use depthgraph_nodes::relight::node::{RelightIn, RelightOut, eval_with};
use depthgraph_nodes::relight::shading::{RelightParams, Visibility};
use glam::DVec3;

use crate::session::{Session, bytes_of, u32s};
use crate::shaders;

/// The bound of the device's direct term against the CPU's (module docs).
pub const DE_TOL: f64 = 1e-6;

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
    _pad: [u32; 2],
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
    _pad: u32,
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

/// Maps packed for the device: headers and one texel pool.
struct Packed {
    maps: Vec<GpuMap>,
    texels: Vec<f32>,
}

impl Packed {
    /// Appends `m` (relative to `origin`); `None` gives an empty header.
    /// `Err` for a texel the device cannot hold exactly (NaN, +inf or a
    /// finite value at the sentinel's magnitude).
    fn push(&mut self, m: Option<&ShadowMap>, origin: DVec3) -> Result<u32, String> {
        let index = self.maps.len() as u32;
        let Some(m) = m else {
            self.maps.push(GpuMap::zeroed());
            return Ok(index);
        };
        let f = m.frame();
        let offset = u32::try_from(self.texels.len())
            .map_err(|_| "more shadow-map texels than the device indexes".to_string())?;
        for &t in &m.t {
            if t == f32::NEG_INFINITY {
                self.texels.push(EMPTY);
            } else if t.is_finite() && t.abs() < 1e29 {
                self.texels.push(t);
            } else {
                return Err(format!("a shadow-map texel holds {t}"));
            }
        }
        self.maps.push(GpuMap {
            eu: f3(f.eu),
            u0: (f.u0 - origin.dot(f.eu)) as f32,
            ev: f3(f.ev),
            v0: (f.v0 - origin.dot(f.ev)) as f32,
            dir: f3(f.dir),
            z0: origin.dot(f.dir) as f32,
            inv_texel: f.inv_texel as f32,
            res: m.res as u32,
            offset,
            _pad: 0,
        });
        Ok(index)
    }
}

/// The direct term of `plan` on the device (module docs): one sum per
/// pixel of the plan, tile after tile, the marked pixels recomputed here.
pub fn direct(
    s: &mut Session,
    plan: &DirectPlan,
    stats: &mut DirectStats,
) -> Result<Vec<DirectSum>, NodeError> {
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
    // the object maps (one per group), then the scene maps the lists read
    let mut packed = Packed {
        maps: Vec::new(),
        texels: Vec::new(),
    };
    for m in plan.object_maps {
        if let Err(why) = packed.push(m.as_ref(), origin) {
            return Err(s.too_large(&why));
        }
    }
    let mut used = vec![false; plan.lights.len()];
    for &j in &list {
        used[j as usize] = true;
    }
    let mut lights = Vec::with_capacity(plan.lights.len());
    for (j, l) in plan.lights.iter().enumerate() {
        let scene_map = match plan.scene_maps.get(j).and_then(Option::as_ref) {
            Some(m) if used[j] => match packed.push(Some(m), origin) {
                Ok(i) => i,
                Err(why) => return Err(s.too_large(&why)),
            },
            _ => NONE,
        };
        lights.push(GpuLight {
            dir: f3(l.dir),
            bias_object: l.bias_object as f32,
            power: l.power.map(|v| v as f32),
            bias_scene: l.bias_scene as f32,
            // a VPL without an object map is in no list
            group: u32::try_from(l.group).unwrap_or(NONE),
            scene_map,
            shared: u32::from(l.shared),
            _pad: 0,
        });
    }
    let n = pixels.len();
    let kernel = s.kernel(&shaders::RELIGHT_DIRECT)?;
    let params = Params {
        count: n as u32,
        row: gx * WORKGROUP,
        _pad: [0; 2],
    };
    let uniform = s.uniform(bytemuck::bytes_of(&params))?;
    let b_pixels = s.upload(bytes_of(&pixels))?;
    let b_list = s.upload(bytes_of(&list))?;
    let b_lights = s.upload(bytes_of(&lights))?;
    let b_maps = s.upload(bytes_of(&packed.maps))?;
    let b_texels = s.upload(bytes_of(&packed.texels))?;
    let out = s.scratch(16 * n as u64)?;
    let bg = s.bind(
        &kernel,
        &[
            &uniform, &b_pixels, &b_list, &b_lights, &b_maps, &b_texels, &out,
        ],
    );
    let mut encoder = s.encoder();
    {
        let mut pass = encoder.begin_compute_pass(&Default::default());
        pass.set_pipeline(&kernel);
        pass.set_bind_group(0, &bg, &[]);
        pass.dispatch_workgroups(gx, gy, 1);
    }
    let back = s.finish(encoder, &[(&out, 16 * n as u64)])?;
    let words = u32s(&back[0]);
    if words.len() != 4 * n {
        return Err(NodeError::Internal(format!(
            "the device returned {} words for {n} pixels",
            words.len()
        )));
    }
    let starts = plan.tile_starts();
    stats.pixels += n;
    for (w, &(t, k)) in words.chunks_exact(4).zip(&at) {
        let sum = if w[3] & 2 != 0 {
            stats.recomputed += 1;
            evaluate_pixel(plan, &plan.tiles[t], k)
        } else {
            DirectSum {
                de: [0, 1, 2].map(|c| f64::from(f32::from_bits(w[c]))),
                hit: w[3] & 1 != 0,
            }
        };
        sums[starts[t] + k] = sum;
    }
    Ok(sums)
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
    let mut stats = DirectStats::default();
    let mut r = eval_with(ctx, i, p, &mut |plan| direct(s, plan, &mut stats))?;
    if r.passthrough.is_none() {
        let line = format!(
            "direct term on the device: {} pixels, {} recomputed on the host",
            stats.pixels, stats.recomputed
        );
        r.report = Some(match r.report.take() {
            Some(prev) => format!("{prev}; {line}"),
            None => line,
        });
    }
    Ok(r)
}
