//! The scene-cached path of `Relight` (`visibility: "scene_cached"`): what
//! depends only on the target photo and the VPLs is computed once per scene
//! ([`RelightScene`]); moving the pasted object re-does only the object's
//! part ([`relight_moved`]).
//!
//! # Split visibility
//!
//! A shadow map stores, per texel, the occluder nearest to the light, so
//! the map of the scene with the object is the texel-wise maximum of the
//! scene's map and the object's, and (up to hole filling) its visibility
//! is `V^{s+t}_k = V^t_k ∧ V^o_k`. The differential of eq. 5 on the target
//! surface becomes
//!
//! `E^{s+t} - E^t = -Σ_k Φ_k max(0, n·ω_k) V^t_k (1 - V^o_k)`,
//!
//! a sum over the VPLs the object blocks, which are found by the cone test
//! of [`crate::relight::paired`] (a ray towards `ω_k` meets the object only when it
//! passes within its reach). So:
//!
//! - **per scene** ([`RelightScene::new`]): the target's surfaces and pixel
//!   areas, one orthographic ISM per VPL of the scene's own points (uniform
//!   area density: the object's position is not known yet; window = every
//!   scene point, so a receiver outside it is not occluded by the scene),
//!   `E^t` per pixel when the albedo must be estimated, and the VPL
//!   directions grouped into cones for the culling;
//! - **per object position** ([`relight_moved`]): one small map per VPL of
//!   the object alone, over the object's own window (its texels are a
//!   fraction of the object's size, finer than the scene map's): the
//!   object's closed surface meshed and rasterized exactly
//!   ([`crate::relight::object_mesh`]; empty texels stay empty, the outside
//!   of the object unoccluded; the maps of dim groups of VPLs at half the
//!   resolution from the layers pooled over blocks, [`FINE_MAP_SHARE`],
//!   [`COARSE_POOL`]); then the object's shading, the bounces,
//!   and the target pixels whose cone meets a VPL (per tile of pixels,
//!   only the VPLs whose object map holds an occluder the tile may look
//!   up: [`ShadowMap::occupied`]); the smooth terms (the
//!   object's irradiance, its bounce onto the scene, the fill light) on
//!   lattices of pixels ([`crate::relight::lattice`], `lattice_step`).
//!
//! The near-object importance of eq. 6 does not enter this path: the
//! object's shadows come from maps of the object alone, which hold its
//! whole surface by construction. The `"paired"` visibility of [`crate::relight::paired`]
//! keeps the paper's scheme (eq. 6 over scene and object, maps rebuilt on
//! every run).

use std::sync::Arc;

use depthgraph_graph::prelude::*;
use depthgraph_graph::value::Rgb;
use glam::DVec3;
use rayon::prelude::*;

use crate::kit::checks::fits_intrinsics;
use crate::kit::color::luminance_clamped;
use crate::relight::contact::ContactParams;
use crate::relight::direct::{
    DirectLight, DirectPixel, DirectPlan, DirectSum, DirectTile, evaluate as evaluate_direct, slope,
};
use crate::relight::fill::{FillPlan, FillSum, evaluate as evaluate_fill};
use crate::relight::ism::{
    IsmParams, ParaboloidSamples, PointSet, ShadowMap, Window, build_single_in, windows,
};
use crate::relight::lattice::{Agreement, Lattice, Nested};
use crate::relight::object_light::{
    Contact, ObjectLightPlan, ObjectLightSum, evaluate as evaluate_object_light,
};
use crate::relight::object_mesh::{ObjectMesh, pooled};
pub use crate::relight::shading::SceneInputs;
use crate::relight::shading::{
    BOUNCE_SPLAT_SCALE, Cone, PointVplShadows, RelightInputs, RelightParams, Relit, Surf,
    capture_ref, centre_and_radius, clean_alpha, composite, lit_vpls, nothing_pasted,
    object_bounce_vpls, object_radiance, pixel_areas, received, scene_bounce_vpls, support_vpls,
    target_albedo, target_surfaces,
};
use crate::relight::vpl::Vpl;
use depthgraph_graph::bytes::{ByteReader, ByteWriter};

/// VPL directions grouped by the cells of an octahedral grid, each group a
/// cone `(axis, half angle)` holding all its directions: a pixel whose cone
/// towards the object misses a group's cone skips all its VPLs.
#[derive(Debug, Clone)]
struct DirGroups {
    axis: Vec<DVec3>,
    cos_h: Vec<f64>,
    sin_h: Vec<f64>,
    members: Vec<Vec<usize>>,
}

impl DirGroups {
    /// Cells per side of the octahedral grid.
    const CELLS: usize = 8;

    fn new(dirs: &[DVec3]) -> Self {
        let n = Self::CELLS;
        let mut cells: Vec<Vec<usize>> = vec![Vec::new(); n * n];
        for (j, d) in dirs.iter().enumerate() {
            let l1 = d.x.abs() + d.y.abs() + d.z.abs();
            if l1 <= 0.0 {
                continue; // a zero direction lights nothing
            }
            // guard: l1 > 0
            let (x, y) = (d.x / l1, d.y / l1);
            let (x, y) = if d.z < 0.0 {
                ((1.0 - y.abs()) * x.signum(), (1.0 - x.abs()) * y.signum())
            } else {
                (x, y)
            };
            let cell = |t: f64| (((t + 1.0) * 0.5 * n as f64) as usize).min(n - 1);
            cells[cell(y) * n + cell(x)].push(j);
        }
        let mut g = Self {
            axis: Vec::new(),
            cos_h: Vec::new(),
            sin_h: Vec::new(),
            members: Vec::new(),
        };
        for m in cells.into_iter().filter(|m| !m.is_empty()) {
            let axis = m
                .iter()
                .map(|&j| dirs[j])
                .sum::<DVec3>()
                .normalize_or_zero();
            let cos_h = if axis == DVec3::ZERO {
                -1.0
            } else {
                m.iter()
                    .map(|&j| dirs[j].dot(axis).clamp(-1.0, 1.0))
                    .fold(1.0f64, f64::min)
            };
            g.axis.push(axis);
            g.cos_h.push(cos_h);
            g.sin_h.push((1.0 - cos_h * cos_h).max(0.0).sqrt());
            g.members.push(m);
        }
        g
    }

    /// Whether some direction of group `g` may lie in `cone`: the angle
    /// between the axes is at most the sum of the half angles (both below
    /// 90 degrees, else always).
    #[inline]
    fn meets(&self, g: usize, cone: &Cone) -> bool {
        if cone.cos_min <= -1.0 || self.cos_h[g] <= 0.0 {
            return true;
        }
        // cos(θ_c + θ_g) with θ_c, θ_g < 90°: monotone on [0, π]
        let lim = cone.cos_min * self.cos_h[g] - cone.sin * self.sin_h[g];
        cone.u.dot(self.axis[g]) >= lim
    }
}

/// What [`relight_moved`] reuses while only the object changes (module
/// docs). Built by [`RelightScene::new`].
#[derive(Debug, Clone)]
pub struct RelightScene {
    k: Intrinsics,
    vpls: Vec<Vpl>,
    dirs: Vec<DVec3>,
    e_ref: f64,
    target: Vec<Option<Surf>>,
    areas: Vec<f64>,
    maps: Vec<Option<ShadowMap>>,
    /// `E^t` per pixel (VPL-major sums in f64), only without a given albedo.
    e_t: Option<Vec<[f64; 3]>>,
    groups: DirGroups,
    /// Per VPL: `bias_scale * max(texel, splat radius)` of its scene map
    /// (the bias is this times the slope factor, [`slope`]).
    bias_t: Vec<f64>,
    tiles: Vec<Tile>,
    /// The scene's samples, kept for the bounce VPLs' paraboloid maps
    /// (only with `bounce_shadows`).
    pool: Option<PointSet>,
    bias_scale: f64,
    with_albedo: bool,
}

/// A square of [`Tile::SIDE`]² pixels: its valid target pixels and a ball
/// holding their surface points. A ray from any of them passes within
/// `reach` of a point only if the parallel ray from the centre passes
/// within `reach + radius`, so one cone test culls the whole tile.
#[derive(Debug, Clone)]
struct Tile {
    centre: DVec3,
    radius: f64,
    pixels: Vec<usize>,
}

impl RelightScene {
    /// Approximate heap size in bytes (what the engine's cache budget counts).
    pub fn heap_bytes(&self) -> usize {
        use std::mem::size_of;
        let maps: usize = self
            .maps
            .iter()
            .map(|m| size_of::<Option<ShadowMap>>() + m.as_ref().map_or(0, |m| m.t.len() * 4))
            .sum();
        let members: usize = self.groups.members.iter().map(|m| m.len() * 8 + 24).sum();
        let tiles: usize = self.tiles.iter().map(|t| t.pixels.len() * 8 + 56).sum();
        self.vpls.len() * size_of::<Vpl>()
            + self.dirs.len() * 24
            + self.target.len() * size_of::<Option<Surf>>()
            + self.areas.len() * 8
            + maps
            + self.e_t.as_ref().map_or(0, |e| e.len() * 24)
            + self.groups.axis.len() * 40
            + members
            + self.bias_t.len() * 8
            + tiles
            + self.pool.as_ref().map_or(0, PointSet::heap_bytes)
    }
}

impl Tile {
    const SIDE: usize = 8;

    fn all(target: &[Option<Surf>], w: usize, h: usize) -> Vec<Tile> {
        let (tw, th) = (w.div_ceil(Self::SIDE), h.div_ceil(Self::SIDE));
        (0..tw * th)
            .into_par_iter()
            .filter_map(|t| {
                let (x0, y0) = ((t % tw) * Self::SIDE, (t / tw) * Self::SIDE);
                let pixels: Vec<usize> = (y0..(y0 + Self::SIDE).min(h))
                    .flat_map(|y| (x0..(x0 + Self::SIDE).min(w)).map(move |x| y * w + x))
                    .filter(|&i| target[i].is_some())
                    .collect();
                let pts: Vec<DVec3> = pixels
                    .iter()
                    .filter_map(|&i| Some(target[i].as_ref()?.pos))
                    .collect();
                if pts.is_empty() {
                    return None;
                }
                // guard: pts is not empty
                let centre = pts.iter().copied().sum::<DVec3>() / pts.len() as f64;
                let radius = pts
                    .iter()
                    .map(|q| (*q - centre).length())
                    .fold(0.0f64, f64::max);
                Some(Tile {
                    centre,
                    radius,
                    pixels,
                })
            })
            .collect()
    }
}

impl RelightScene {
    /// The scene's part of `Relight` (module docs) for the VPLs `vpls`,
    /// with `p.ism_resolution`, `p.ism_points`, `p.seed` and `p.bias_scale`.
    pub fn new(inp: &SceneInputs, vpls: &[Vpl], p: &RelightParams) -> Result<Self, NodeError> {
        let k = inp.k;
        inp.check()?;
        let (vpls, dirs, e_ref) = lit_vpls(vpls);
        let target = target_surfaces(inp.depth, inp.normals, k);
        let areas = pixel_areas(inp.depth, k);
        let set = PointSet::new(&[(inp.depth, false)], k, &[], p.min_distance_m);
        let ism = IsmParams {
            resolution: p.ism_resolution,
            points_per_map: p.ism_points,
            bias_scale: p.bias_scale,
            min_distance_m: p.min_distance_m,
            seed: p.seed,
            ..Default::default()
        };
        let m = ism.points_per_map;
        let scene_radius = set.splat_radius(DVec3::ZERO, m);
        let wins = windows(&dirs, &set.positions);
        let maps: Vec<Option<ShadowMap>> = wins
            .par_iter()
            .enumerate()
            .map(|(j, win)| {
                let seed = p.seed.wrapping_mul(0x9E37_79B9).wrapping_add(j as u64);
                build_single_in(win.as_ref()?, &set, &ism, m, 1.0, true, seed)
            })
            .collect();
        let groups = DirGroups::new(&dirs);
        let bias_t = maps
            .iter()
            .map(|m| {
                m.as_ref()
                    .map_or(0.0, |m| p.bias_scale * m.texel_m.max(scene_radius))
            })
            .collect();
        let tiles = Tile::all(&target, k.width, k.height);
        let mut scene = Self {
            k: *k,
            vpls,
            dirs,
            e_ref,
            target,
            areas,
            maps,
            e_t: None,
            groups,
            bias_t,
            tiles,
            pool: None,
            bias_scale: p.bias_scale,
            with_albedo: inp.albedo.is_some(),
        };
        if inp.albedo.is_none() {
            scene.e_t = Some(scene.target_irradiance());
        }
        if p.bounce_shadows {
            scene.pool = Some(set);
        }
        Ok(scene)
    }

    /// The VPLs with energy the scene was built for.
    pub fn vpl_count(&self) -> usize {
        self.vpls.len()
    }

    /// Per VPL: the scene's own shadow map (`None`: it occludes nothing).
    pub fn scene_maps(&self) -> &[Option<ShadowMap>] {
        &self.maps
    }

    /// `E^t = Σ_k Φ_k max(0, n·ω_k) V^t_k` of every target pixel, chunks of
    /// pixels in parallel, VPL-major inside a chunk (one map at a time stays
    /// in cache), each pixel summing its VPLs in order.
    fn target_irradiance(&self) -> Vec<[f64; 3]> {
        const CHUNK: usize = 512;
        self.target
            .par_chunks(CHUNK)
            .flat_map_iter(|chunk| {
                let mut acc = vec![[0.0f64; 3]; chunk.len()];
                for (j, ((v, d), m)) in self.vpls.iter().zip(&self.dirs).zip(&self.maps).enumerate()
                {
                    let power = v.power.map(f64::from);
                    for (s, e) in chunk.iter().zip(acc.iter_mut()) {
                        let Some(s) = s else {
                            continue;
                        };
                        let cos = s.n.dot(*d);
                        if cos <= 0.0 {
                            continue;
                        }
                        if !self.scene_visible(j, m, s, cos) {
                            continue;
                        }
                        for ch in 0..3 {
                            e[ch] += power[ch] * cos;
                        }
                    }
                }
                acc
            })
            .collect()
    }

    /// `V^t_k` at a surface with `cos = n·ω_k > 0`: its map's verdict
    /// with the bias of the scene's splats; visible without a map.
    #[inline]
    fn scene_visible(&self, k: usize, map: &Option<ShadowMap>, s: &Surf, cos: f64) -> bool {
        match map {
            Some(m) => m.visible(s.pos, self.bias_t[k] * slope(cos)),
            None => true,
        }
    }
}

/// The maps of the object alone (module docs): one per group of VPL
/// directions within [`SHARED_MAP_DEG`] of each other.
struct ObjectMaps {
    /// One map per group, built along its first direction.
    maps: Vec<Option<ShadowMap>>,
    /// Per VPL: its group.
    of: Vec<usize>,
    /// Per group: how far the mesh its map was drawn from reaches beyond
    /// the object's pixels, metres ([`ObjectMesh::margin`]).
    margins: Vec<f64>,
    /// The largest of `margins`.
    radius: f64,
    /// Largest texel side of the maps, metres.
    max_texel: f64,
    /// Per group: its map's [`ShadowMap::occupied`] rectangle, once
    /// [`ObjectMaps::with_occupied`] found them (empty before).
    occupied: Vec<Option<[f64; 4]>>,
}

impl ObjectMaps {
    /// The map VPL `j` looks up (`None` for a zero direction).
    #[inline]
    fn get(&self, j: usize) -> Option<&ShadowMap> {
        self.of.get(j).and_then(|&g| self.maps[g].as_ref())
    }

    /// Whether VPL `j`'s map may shadow a point within `r` of `c`: the
    /// ball reaches its [`ShadowMap::occupied`] rectangle (plus half a
    /// texel against rounding). Where it does not, every point of the ball
    /// looks up an empty texel: the VPL reaches it past the object.
    /// Without the rectangles ([`ObjectMaps::with_occupied`]), every VPL
    /// with a map may.
    fn may_shadow(&self, j: usize, c: DVec3, r: f64) -> bool {
        let Some(m) = self.get(j) else {
            return false;
        };
        let Some(rect) = self.of.get(j).and_then(|&g| self.occupied.get(g)) else {
            return true;
        };
        let Some([u0, u1, v0, v1]) = *rect else {
            return false;
        };
        let lc = m.light_coords(c);
        let r = r + 0.5 * m.texel_m;
        lc.x + r >= u0 && lc.x - r <= u1 && lc.y + r >= v0 && lc.y - r <= v1
    }

    /// The maps' [`ShadowMap::occupied`] rectangles found, for
    /// [`ObjectMaps::may_shadow`].
    fn with_occupied(mut self) -> Self {
        self.occupied = self
            .maps
            .par_iter()
            .map(|m| m.as_ref().and_then(ShadowMap::occupied))
            .collect();
        self
    }

    /// The margin of the mesh VPL `j`'s map was drawn from (0 without one).
    #[inline]
    fn margin(&self, j: usize) -> f64 {
        self.of.get(j).map_or(0.0, |&g| self.margins[g])
    }
}

/// VPLs whose directions lie within this angle (degrees) of a group's
/// first share its object map. An environment's sun gives most of the
/// VPLs, all within its disc: a map per VPL there rasterizes the same
/// object a hundred times over. Looking a shadow up along a direction off
/// by `θ` shifts it by `θ` times the receiver's distance from the
/// occluder: 0.9 mm at 20 cm, under the sun's own penumbra (its disc
/// spans about half a degree) and under a texel of the object's maps.
pub const SHARED_MAP_DEG: f64 = 0.25;

/// Groups `dirs` greedily in order (module docs of [`ObjectMaps`]): each
/// direction joins the first group whose first direction lies within
/// [`SHARED_MAP_DEG`], else starts one. Returns the groups' first
/// directions and each direction's group.
fn share_directions(dirs: &[DVec3]) -> (Vec<DVec3>, Vec<usize>) {
    let cos_max = SHARED_MAP_DEG.to_radians().cos();
    let mut firsts: Vec<DVec3> = Vec::new();
    let of = dirs
        .iter()
        .map(|d| {
            let u = d.normalize_or_zero();
            match firsts
                .iter()
                .position(|f| u != DVec3::ZERO && f.dot(u) >= cos_max)
            {
                Some(g) => g,
                None => {
                    firsts.push(u);
                    firsts.len() - 1
                }
            }
        })
        .collect();
    (firsts, of)
}

/// A group of VPL directions whose power is below this share of all the
/// VPLs' gets its object map at half the resolution, from a mesh at the
/// matching stride (`ObjectMeshes`). A map's texel shifts the edge of
/// the shadow it casts by up to half a texel; the error that makes in
/// irradiance is that shift times the group's power, and the errors of
/// many dim groups, in directions spread over the sky, blur into one
/// another. Against the path-traced rooms (`benches/relight_truth.rs`, 64
/// paths per pixel), every map at half resolution scored the overcast
/// rooms within 0.15 dB of full resolution, while halving the sun's maps
/// too cost the sunlit rooms up to 2.2 dB in the influence region; with
/// this split every room scored within 0.3 dB of full resolution, and an
/// object move on `copy_paste_relit.ron` took 58 ms instead of 69.
pub const FINE_MAP_SHARE: f64 = 1.0 / 64.0;

/// The resolution of the maps of the dim groups ([`FINE_MAP_SHARE`]):
/// half the object maps', at least 4.
fn coarse_resolution(res: usize) -> usize {
    (res / 2).max(4)
}

/// The object's closed mesh for the two map resolutions
/// ([`FINE_MAP_SHARE`]): `fine` on the layers' pixels, `coarse` on the
/// layers pooled over [`COARSE_POOL`]² blocks where the object is large
/// enough ([`POOL_MIN_STRIDE`], [`crate::relight::object_mesh::pooled`]),
/// each at the stride of its maps' texels; `coarse` is `None` where it
/// would be the fine one.
struct ObjectMeshes {
    fine: ObjectMesh,
    coarse: Option<ObjectMesh>,
}

/// The coarse maps' mesh is built on the object's layers pooled over
/// blocks of this many pixels a side, where its cells span at least
/// [`POOL_MIN_STRIDE`] pixels. Its maps have half the fine maps'
/// resolution, so a cell of two of their texels spans twice the pixels;
/// but along the outline, where cells break, the mesh falls back to a
/// patch per pixel, and those patches (a band as deep as the stride)
/// were nine tenths of its triangles: 8208 against the fine mesh's 6700
/// for a sphere of 10 000 pixels. Pooled, a patch covers a block: about a
/// third of the triangles, and an outline within half a block.
pub const COARSE_POOL: usize = 2;

/// The coarse mesh is pooled only where its cells (two coarse texels)
/// span at least this many pixels: half a block then moves the outline
/// by at most a quarter of a texel. Against the path-traced rooms,
/// pooling the 320x240 objects (cells of 6 pixels) cost up to 1.1 dB in
/// the influence region (occluded, sun + sky: 31.3 -> 30.2); at 640x480
/// (cells of 11) it scored as well as the unpooled mesh (33.0 against
/// 32.6 and 40.5 against 40.4 dB, 64 paths per pixel).
pub const POOL_MIN_STRIDE: usize = 8;

impl ObjectMeshes {
    /// The meshes of `front` and `back` for an object of centre `c` and
    /// reach `radius` ([`object_stride`]).
    fn new(
        front: &DepthMap,
        back: Option<&DepthMap>,
        k: &Intrinsics,
        c: DVec3,
        radius: f64,
        p: &RelightParams,
    ) -> Self {
        let res = p.object_ism_resolution;
        let fine_stride = object_stride(radius, c.z, k, res);
        let (fine, coarse) = rayon::join(
            || ObjectMesh::new(front, back, k, fine_stride),
            || {
                let stride = object_stride(radius, c.z, k, coarse_resolution(res));
                if stride < POOL_MIN_STRIDE {
                    return (stride != fine_stride)
                        .then(|| ObjectMesh::new(front, back, k, stride));
                }
                let (f, kc) = pooled(front, k, COARSE_POOL);
                let b = back.map(|b| pooled(b, k, COARSE_POOL).0);
                let stride = object_stride(radius, c.z, &kc, coarse_resolution(res));
                Some(ObjectMesh::new(&f, b.as_ref(), &kc, stride))
            },
        );
        Self { fine, coarse }
    }

    fn coarse(&self) -> &ObjectMesh {
        self.coarse.as_ref().unwrap_or(&self.fine)
    }
}

/// The object's maps: its closed mesh ([`crate::relight::object_mesh`])
/// rasterized along every group of directions over its own window, at
/// full resolution for the groups with at least [`FINE_MAP_SHARE`] of the
/// power of `vpls` (in the order of `dirs`), at half for the others.
fn object_maps(
    meshes: &ObjectMeshes,
    dirs: &[DVec3],
    vpls: &[Vpl],
    p: &RelightParams,
) -> ObjectMaps {
    let (firsts, of) = share_directions(dirs);
    let mut power = vec![0.0f64; firsts.len()];
    for (&g, v) in of.iter().zip(vpls) {
        power[g] += luminance_clamped(v.power);
    }
    let total: f64 = power.iter().sum();
    // every map fine when the VPLs carry no power (nothing to weigh by)
    let fine: Vec<bool> = power
        .iter()
        .map(|&pw| total.is_nan() || total <= 0.0 || pw >= FINE_MAP_SHARE * total)
        .collect();
    let windows_of = |want: bool, mesh: &ObjectMesh| {
        let dirs: Vec<DVec3> = firsts
            .iter()
            .zip(&fine)
            .filter(|(_, f)| **f == want)
            .map(|(d, _)| *d)
            .collect();
        windows(&dirs, &mesh.verts).into_iter()
    };
    let (mut wf, mut wc) = (
        windows_of(true, &meshes.fine),
        windows_of(false, meshes.coarse()),
    );
    let res = p.object_ism_resolution;
    // per group: its window, and the mesh and resolution it is drawn at
    let jobs: Vec<(Option<Window>, &ObjectMesh, usize)> = fine
        .iter()
        .map(|&f| {
            if f {
                (wf.next().flatten(), &meshes.fine, res)
            } else {
                (wc.next().flatten(), meshes.coarse(), coarse_resolution(res))
            }
        })
        .collect();
    let maps: Vec<Option<ShadowMap>> = jobs
        .par_iter()
        .map(|(win, mesh, res)| mesh.shadow_map(win.as_ref()?, *res))
        .collect();
    let max_texel = maps
        .iter()
        .flatten()
        .map(|m| m.texel_m)
        .fold(0.0f64, f64::max);
    let margins: Vec<f64> = jobs.iter().map(|(_, mesh, _)| mesh.margin).collect();
    ObjectMaps {
        maps,
        of,
        radius: margins.iter().copied().fold(0.0, f64::max),
        margins,
        max_texel,
        occupied: Vec::new(),
    }
}

/// The lattices' nodes ([`crate::relight::lattice`];
/// `RelightParams::lattice_step`) are blended when they agree within this
/// fraction of the largest ...
const LATTICE_REL: f64 = 0.05;

/// ... plus this fraction of the VPLs' reference irradiance `e_ref`, so
/// that terms near zero blend (the photo is about `ρ e_ref` bright: 1e-3
/// of it is at most a quarter of an 8-bit step, at white).
const LATTICE_ABS_REL: f64 = 1e-3;

/// Pixels per mesh cell of the object (at least 1): about two texels of
/// its maps (a cell's setup costs more than a texel's test; a cell of two
/// texels on a curved surface is still flat to a fraction of a
/// millimetre), whose side is the object's diameter `2 radius` over the
/// resolution's inner texels; a pixel at the object's depth `z` spans
/// `z / fx`.
fn object_stride(radius: f64, z: f64, k: &Intrinsics, res: usize) -> usize {
    // guard: res - 2 >= 1 by the max; fx > 0 for sane intrinsics, z > 0 for
    // a valid centre (else the ratio is not finite and the stride is 1)
    let texel = 2.0 * radius / (res as f64 - 2.0).max(1.0);
    let ratio = 2.0 * texel * k.fx / z + 0.5;
    if ratio.is_finite() && ratio >= 1.0 {
        (ratio as usize).min(16)
    } else {
        1
    }
}

/// Whether the object surface `q` lies on `s`'s surface for the lattices'
/// blend: normals within about 26° (cosine > 0.9), `q` within 1 % of
/// `s`'s depth of its tangent plane and within 10 % of it in all.
fn same_surface(s: &Surf, q: &Surf) -> bool {
    let d = q.pos - s.pos;
    let z = s.pos.z.abs();
    q.n.dot(s.n) > 0.9 && d.dot(s.n).abs() <= 0.01 * z && d.length() <= 0.1 * z
}

/// An object surface's received irradiance `E^{s+t} + B_s` (the
/// target's direct light with both shadows, plus the scene's bounce onto
/// it) and `E_cap`: the numerator and denominator of
/// [`object_radiance`]'s ratio. The lattices blend and test these two,
/// not `E^{s+t}` and `B_s` apart: a bounce that changes by more than the
/// tolerance of itself, but little of all the light the surface receives,
/// is smooth enough to blend (the ratio's error is what the test bounds).
/// At 640x480 this leaves about a third fewer pixels to sum exactly, and
/// the composite's PSNR against every pixel summed falls by at most
/// 1.7 dB, staying above 53 dB (`docs/relight-truth.md`).
type Irradiances = [[f64; 3]; 2];

/// The exact irradiances of a list of surfaces (the lattices' nodes and
/// the pixels no lattice serves).
type ExactIrradiances<'e> = dyn FnMut(&[Surf]) -> Result<Vec<Irradiances>, NodeError> + 'e;

/// [`Irradiances`] as one row of six.
fn flat(v: &Irradiances) -> [f64; 6] {
    std::array::from_fn(|i| v[i / 3][i % 3])
}

/// The object's irradiances ([`Irradiances`]) at its pixels `obj_idx`
/// (sorted, surfaces `surfs`) of a `w x h` image, by `exact` (which takes
/// a list of surfaces and sums VPL-major over them): on the lattices
/// every `2 step`, then every `step` pixels ([`crate::relight::lattice`]),
/// each lattice's nodes that the pixels still open need computed
/// together, the pixels no lattice serves computed exactly.
fn lattice_irradiance(
    obj_idx: &[usize],
    surfs: &[Surf],
    w: usize,
    h: usize,
    step: usize,
    agree: Agreement,
    exact: &mut ExactIrradiances,
) -> Result<Vec<Irradiances>, NodeError> {
    if step <= 1 {
        return exact(surfs);
    }
    // pixel index -> place in `obj_idx` (sorted)
    let place = |i: usize| obj_idx.binary_search(&i).ok();
    let surf_at = |i: usize| place(i).map(|j| &surfs[j]);
    let mut out: Vec<Option<[f64; 6]>> = vec![None; obj_idx.len()];
    // every node computed so far, by place: the coarse lattice's nodes
    // are the fine one's too, and are not computed again
    let mut known: Vec<Option<[f64; 6]>> = vec![None; obj_idx.len()];
    for grid in [
        Lattice::<6>::new(w, h, 2 * step),
        Lattice::<6>::new(w, h, step),
    ] {
        let open: Vec<usize> = (0..obj_idx.len()).filter(|&j| out[j].is_none()).collect();
        // the object's nodes the open pixels blend and no lattice computed
        // yet, each once, in pixel order (the places' order)
        let corners: Vec<[Option<usize>; 4]> = open
            .par_iter()
            .map(|&j| {
                let mut c = [None; 4];
                for (slot, n) in c
                    .iter_mut()
                    .zip(grid.corners(obj_idx[j] % w, obj_idx[j] / w))
                {
                    *slot = place(n).filter(|&q| known[q].is_none());
                }
                c
            })
            .collect();
        let mut need = vec![false; obj_idx.len()];
        for q in corners.iter().flatten().flatten() {
            need[*q] = true;
        }
        let nodes: Vec<usize> = (0..obj_idx.len()).filter(|&q| need[q]).collect();
        let node_surfs: Vec<Surf> = nodes.iter().map(|&q| surfs[q]).collect();
        for (&q, v) in nodes.iter().zip(exact(&node_surfs)?) {
            known[q] = Some(flat(&v));
        }
        let eval = |i: usize| place(i).and_then(|q| known[q]);
        let blended: Vec<Option<[f64; 6]>> = open
            .par_iter()
            .map(|&j| {
                let (i, s) = (obj_idx[j], &surfs[j]);
                let same = |n: usize| surf_at(n).is_some_and(|q| same_surface(s, q));
                grid.at(i % w, i / w, &eval, same, agree)
            })
            .collect();
        for (&j, b) in open.iter().zip(blended) {
            out[j] = b;
        }
    }
    let rest: Vec<usize> = (0..obj_idx.len()).filter(|&j| out[j].is_none()).collect();
    let rest_surfs: Vec<Surf> = rest.iter().map(|&j| surfs[j]).collect();
    for (&j, v) in rest.iter().zip(exact(&rest_surfs)?) {
        out[j] = Some(flat(&v));
    }
    Ok(out
        .into_iter()
        .map(|v| {
            let v = v.unwrap_or([0.0; 6]);
            std::array::from_fn(|t| [v[3 * t], v[3 * t + 1], v[3 * t + 2]])
        })
        .collect())
}

/// `Relight` with the scene's part from `scene` (module docs): the same
/// outputs as [`crate::relight::paired::relight`], up to the visibility scheme.
/// `inp`'s scene part must be the one `scene` was built from (the node
/// guarantees it; a different size or intrinsics is an error).
pub fn relight_moved(
    scene: &RelightScene,
    inp: &RelightInputs,
    p: &RelightParams,
) -> Result<Option<Relit>, NodeError> {
    relight_moved_with(scene, inp, p, &mut CpuSums)
}

/// The evaluators of a move's two long sums over the VPLs: the direct
/// term at the target's pixels ([`crate::relight::direct`]) and the
/// object's received light ([`crate::relight::object_light`]). The CPU's
/// ([`CpuSums`]) or a device's; every discrete choice around them (which
/// pixels, which surfaces, which VPLs, the lattices) is made here.
pub trait MoveSums {
    /// A new move begins (its maps and plans are new): forget what the
    /// last one left (a device's uploaded maps, say).
    fn begin_move(&mut self) {}
    /// The cached scene the next move reads, as the engine keeps it (a
    /// device keeps its maps beside it; the node names it before each move).
    fn scene(&mut self, _scene: &Arc<RelightScene>) {}
    /// One [`DirectSum`] per pixel of the plan, tile after tile.
    fn direct(&mut self, plan: &DirectPlan) -> Result<Vec<DirectSum>, NodeError>;
    /// One [`ObjectLightSum`] per surface of `surfs`, in order.
    fn object_light(
        &mut self,
        plan: &ObjectLightPlan,
        surfs: &[Surf],
    ) -> Result<Vec<ObjectLightSum>, NodeError>;
    /// One [`FillSum`] per surface of `surfs`, in order.
    fn fill(&mut self, plan: &FillPlan, surfs: &[Surf]) -> Result<Vec<FillSum>, NodeError>;
}

/// Both sums on the CPU.
#[derive(Debug, Clone, Copy, Default)]
pub struct CpuSums;

impl MoveSums for CpuSums {
    fn direct(&mut self, plan: &DirectPlan) -> Result<Vec<DirectSum>, NodeError> {
        Ok(evaluate_direct(plan))
    }

    fn object_light(
        &mut self,
        plan: &ObjectLightPlan,
        surfs: &[Surf],
    ) -> Result<Vec<ObjectLightSum>, NodeError> {
        Ok(evaluate_object_light(plan, surfs))
    }

    fn fill(&mut self, plan: &FillPlan, surfs: &[Surf]) -> Result<Vec<FillSum>, NodeError> {
        Ok(evaluate_fill(plan, surfs))
    }
}

/// [`relight_moved`] with the long sums from `sums` (the device's, say);
/// everything else on the CPU.
pub fn relight_moved_with(
    scene: &RelightScene,
    inp: &RelightInputs,
    p: &RelightParams,
    sums: &mut dyn MoveSums,
) -> Result<Option<Relit>, NodeError> {
    let k = inp.k;
    if *k != scene.k {
        return Err(NodeError::input(
            "intrinsics",
            "differ from those the cached scene was built with",
        ));
    }
    fits_intrinsics("intrinsics", k, "photo", inp.photo.dims())?;
    fits_intrinsics("intrinsics", k, "pasted_color", inp.pasted_color.dims())?;
    fits_intrinsics("intrinsics", k, "pasted_depth", inp.pasted_depth.dims())?;
    fits_intrinsics("intrinsics", k, "alpha", inp.alpha.dims())?;
    if let Some(a) = inp.albedo {
        fits_intrinsics("intrinsics", k, "albedo", a.dims())?;
    }
    if inp.albedo.is_some() != scene.with_albedo {
        return Err(NodeError::input(
            "albedo",
            "connected differently from when the cached scene was built",
        ));
    }
    sums.begin_move();
    let (w, h) = (k.width, k.height);
    let alpha = clean_alpha(inp.alpha, inp.pasted_depth);
    // an object hidden whole still casts its shadow (`nothing_pasted`)
    if scene.vpls.is_empty() || !scene.e_ref.is_finite() || nothing_pasted(inp.pasted_depth) {
        return Ok(None);
    }
    let e_floor = p.min_shading_rel * scene.e_ref;
    // the capture side's floor (module docs of `paired`)
    let cap_floor = p.min_capture_rel * capture_ref(inp.capture_vpls, scene.e_ref)?;
    let r2_min = p.clamp_distance_m * p.clamp_distance_m;
    // the lattices' tolerance (`crate::relight::lattice`)
    let agree = Agreement {
        rel: LATTICE_REL,
        abs: LATTICE_ABS_REL * scene.e_ref,
        whole: false,
    };

    // ---- the object: its samples (every pasted pixel, hidden ones too:
    // they still cast shadows), its maps, its visible surfaces
    // the closed object (its back mirrored, `close_back`): shadows only
    let back = inp.back_depth(p);
    let mut layers = vec![(inp.pasted_depth, true)];
    if let Some(b) = &back {
        layers.push((b, true));
    }
    // the samples' set (areas, importance, CDF) only for the bounce's
    // paraboloid maps; the centre and reach from the points alone
    let oset = scene
        .pool
        .as_ref()
        .map(|_| PointSet::new(&layers, k, &[], p.min_distance_m));
    let unprojected: Vec<DVec3>;
    let positions: &[DVec3] = match &oset {
        Some(set) => &set.positions,
        None => {
            unprojected = layers
                .iter()
                .flat_map(|(d, _)| {
                    let w = d.width();
                    d.as_slice()
                        .iter()
                        .enumerate()
                        .filter(|(_, z)| DepthMap::is_valid(**z))
                        .map(move |(i, z)| {
                            k.unproject((i % w) as f64 + 0.5, (i / w) as f64 + 0.5, f64::from(*z))
                        })
                })
                .collect();
            &unprojected
        }
    };
    let (c, radius) = centre_and_radius(positions);
    let volume = inp.volume(back.as_ref(), c, radius);
    let meshes = ObjectMeshes::new(inp.pasted_depth, back.as_ref(), k, c, radius, p);
    let om = object_maps(&meshes, &scene.dirs, &scene.vpls, p).with_occupied();
    // A ray meets the object's splats only within this distance of c; the
    // texel adds the lookup's quantisation.
    let reach = radius + om.radius + om.max_texel;
    let bounce_reach = p.bounce_radius_rel * radius;
    let obj_idx: Vec<usize> = (0..w * h).filter(|&i| alpha[i] > 0.0).collect();
    let obj_surfs: Vec<Surf> = obj_idx.par_iter().map(|&i| inp.object_surface(i)).collect();

    // ---- the object's shading: E^{s+t} = Σ Φ cos V^t V^o, and the scene's bounce
    let mut scene_vpls = scene_bounce_vpls(&scene.target, &scene.areas, inp.photo, c, p);
    scene_vpls.extend(support_vpls(
        &scene.target,
        inp.photo,
        k,
        inp.depth,
        c,
        radius,
        p,
    ));
    let pasted = inp.pasted_color.as_slice();
    // per VPL: the object maps' bias constants, for the object's own
    // surfaces (its splats) and for the scene's (none of its splats)
    let bias_oo: Vec<f64> = (0..scene.dirs.len())
        .map(|j| {
            om.get(j)
                .map_or(0.0, |m| scene.bias_scale * m.texel_m.max(om.margin(j)))
        })
        .collect();
    let bias_os: Vec<f64> = (0..scene.dirs.len())
        .map(|j| om.get(j).map_or(0.0, |m| scene.bias_scale * m.texel_m))
        .collect();
    // The scene's secondary VPLs carry the light of the scene **with** the
    // object: each keeps the fraction E^{s+t} / E^t of its direct light
    // (the floor under the object is in its shadow and bounces less).
    let scene_lit: Vec<(DVec3, DVec3, [f64; 3])> = scene_vpls
        .par_iter()
        .map(|&(q, nq, flux)| {
            let (mut et, mut est) = ([0.0f64; 3], [0.0f64; 3]);
            for (j, (v, d)) in scene.vpls.iter().zip(&scene.dirs).enumerate() {
                let cos = nq.dot(*d);
                if cos <= 0.0 {
                    continue;
                }
                let sl = slope(cos);
                let vt = scene.maps[j]
                    .as_ref()
                    .is_none_or(|m| m.visible(q, scene.bias_t[j] * sl));
                if !vt {
                    continue;
                }
                let vo = om.get(j).is_none_or(|m| m.visible(q, bias_os[j] * sl));
                for ch in 0..3 {
                    let e = f64::from(v.power[ch]) * cos;
                    et[ch] += e;
                    if vo {
                        est[ch] += e;
                    }
                }
            }
            let flux = std::array::from_fn(|ch| {
                // guard: divide only when et >= e_floor > 0
                if et[ch] >= e_floor {
                    flux[ch] * (est[ch] / et[ch]).clamp(0.0, 1.0)
                } else {
                    flux[ch]
                }
            });
            (q, nq, flux)
        })
        .collect();
    // The object's received light from the environment's VPLs (the
    // evaluator's: `crate::relight::object_light`): the scene's test is
    // the map's, the contact march deciding where the map's occluder lies
    // within the bias of the surface (`p.contact`).
    // The VPLs as the two sums read them, with the object maps' bias
    // constants `bias_object` per VPL; per VPL with an object map: whether
    // its scene map shares the frame.
    let move_lights = |bias_object: &[f64]| -> Vec<DirectLight> {
        (0..scene.vpls.len())
            .map(|j| DirectLight {
                dir: scene.dirs[j],
                power: scene.vpls[j].power.map(f64::from),
                group: om.of.get(j).copied().unwrap_or(usize::MAX),
                bias_object: bias_object[j],
                bias_scene: scene.bias_t[j],
                shared: match (&scene.maps[j], om.get(j)) {
                    (Some(a), Some(b)) => a.same_frame(b),
                    _ => false,
                },
            })
            .collect()
    };
    let light_plan = ObjectLightPlan {
        lights: move_lights(&bias_oo),
        object_maps: &om.maps,
        scene_maps: &scene.maps,
        contact: p.contact.then_some(Contact {
            depth: inp.depth,
            k,
            params: ContactParams::default(),
        }),
        centre: c,
    };
    // the bounce VPLs' paraboloid maps (bounce_shadows): scene and object
    // samples, each with its own radius
    let m_obj = (p.bounce_ism_points / 4).max(16);
    let (r_scene, r_obj) = match (&scene.pool, &oset) {
        (Some(pool), Some(oset)) => (
            BOUNCE_SPLAT_SCALE * pool.base_radius(p.bounce_ism_points),
            BOUNCE_SPLAT_SCALE * oset.base_radius(m_obj),
        ),
        _ => (0.0, 0.0),
    };
    let bounce_samples: Vec<ParaboloidSamples> = match (&scene.pool, &oset) {
        (Some(pool), Some(oset)) => vec![
            ParaboloidSamples {
                set: pool,
                m: p.bounce_ism_points,
                radius_scale: BOUNCE_SPLAT_SCALE,
            },
            ParaboloidSamples {
                set: oset,
                m: m_obj,
                radius_scale: BOUNCE_SPLAT_SCALE,
            },
        ],
        _ => Vec::new(),
    };
    let scene_shadows = PointVplShadows::new(&scene_vpls, &bounce_samples, p, p.seed ^ 0x5EC0);
    let mut irradiance = |surfs: &[Surf]| -> Result<Vec<Irradiances>, NodeError> {
        let light = sums.object_light(&light_plan, surfs)?;
        if light.len() != surfs.len() {
            return Err(NodeError::Internal(format!(
                "the object light's evaluator gave {} sums for {} surfaces",
                light.len(),
                surfs.len()
            )));
        }
        // the scene's bounce onto the object, per surface
        Ok(light
            .par_iter()
            .zip(surfs)
            .map(|(l, s)| {
                let bs = if scene_vpls.is_empty() {
                    [0.0; 3]
                } else {
                    scene_shadows.bounce(s.pos, s.n, r_obj, scene_lit.iter().enumerate(), r2_min)
                };
                [received(l.est, bs), l.ecap]
            })
            .collect())
    };
    let irr = lattice_irradiance(
        &obj_idx,
        &obj_surfs,
        w,
        h,
        p.lattice_step,
        // the object's irradiance follows its normals (a sphere's rim):
        // interpolated between all its nodes, never extrapolated
        Agreement {
            whole: true,
            ..agree
        },
        &mut irradiance,
    )?;
    // the capture side: the same VPLs, or the capture map's with maps of
    // the object alone in their directions
    let ecap: Vec<[f64; 3]> = match inp.capture_vpls {
        None => irr.iter().map(|v| v[1]).collect(),
        Some(cv) => {
            // `E_cap = Σ_k Φ_k max(0, n·ω_k) V^o_k` of every object surface
            // for the capture map's VPLs: the object light's `E^o` with the
            // object's maps in their directions and no scene
            let (cv, cdirs, _) = lit_vpls(cv);
            let cm = object_maps(&meshes, &cdirs, &cv, p);
            let plan = ObjectLightPlan {
                lights: (0..cv.len())
                    .map(|j| DirectLight {
                        dir: cdirs[j],
                        power: cv[j].power.map(f64::from),
                        group: cm.of.get(j).copied().unwrap_or(usize::MAX),
                        bias_object: cm
                            .get(j)
                            .map_or(0.0, |m| scene.bias_scale * m.texel_m.max(cm.margin(j))),
                        bias_scene: 0.0,
                        shared: false,
                    })
                    .collect(),
                object_maps: &cm.maps,
                scene_maps: &[],
                contact: None,
                centre: c,
            };
            let light = sums.object_light(&plan, &obj_surfs)?;
            if light.len() != obj_surfs.len() {
                return Err(NodeError::Internal(format!(
                    "the object light's evaluator gave {} sums for {} surfaces",
                    light.len(),
                    obj_surfs.len()
                )));
            }
            light.into_iter().map(|l| l.ecap).collect()
        }
    };
    let obj_rad: Vec<Rgb> = obj_idx
        .par_iter()
        .zip(irr.par_iter())
        .zip(ecap.par_iter())
        .map(|((&i, v), &ecap)| object_radiance(pasted[i], v[0], ecap, cap_floor))
        .collect();
    let bounce = object_bounce_vpls(
        &obj_idx,
        &|j| Some((obj_surfs[j].pos, obj_surfs[j].n)),
        &|j| obj_rad[j],
        inp.pasted_depth,
        k,
        p.bounce_vpls,
    );
    let bounce_shadows = PointVplShadows::new(&bounce, &bounce_samples, p, p.seed ^ 0x0B1E);

    // ---- the target's smooth terms and the composite's inputs
    let photo = inp.photo.as_slice();
    let albedo = inp.albedo.map(|a| a.as_slice());
    let fill = p.fill_light && !scene_vpls.is_empty();
    // the smooth terms on lattices (`crate::relight::lattice`): the
    // bounce every 2 and 1 `lattice_step` pixels, the fill every 4 and 2
    let on_surface = |s: &Surf, node: usize| {
        scene.target[node]
            .as_ref()
            .is_some_and(|q| same_surface(s, q))
    };
    // The fill's `blocked` part steps wherever the object's volume starts
    // or stops blocking one of the scene's VPLs: the nodes blend whatever
    // their values (the terms are >= 0: max - min <= max), which smooths
    // those steps, where the former scheme held one value per 4x4 block.
    let fill_agree = Agreement {
        rel: 1.0,
        abs: 0.0,
        whole: false,
    };
    let bounce_grid = Nested::<3>::new(w, h, p.lattice_step);
    let bounce_node = |i: usize| {
        let s = scene.target[i].as_ref()?;
        ((s.pos - c).length() <= bounce_reach)
            .then(|| bounce_shadows.bounce(s.pos, s.n, r_scene, bounce.iter().enumerate(), r2_min))
    };
    let fill_plan = FillPlan {
        vpls: &scene_vpls,
        r2_min,
        volume: &volume,
    };
    // (step 1: every term at every pixel)
    let fill_step = if p.lattice_step <= 1 {
        1
    } else {
        2 * p.lattice_step
    };
    let fill_grid = Nested::<6>::new(w, h, fill_step);
    // Per tile: the VPLs its cone meets and whose object map may shadow it
    // (`ObjectMaps::may_shadow`: the others' lookups find empty texels
    // at every pixel of the tile; the direct term's plan), whether it is
    // within the bounce's reach and the bounce VPLs that face it.
    // Tiles whose cone meets no VPL group, out of the bounce's reach and
    // without object pixels are skipped whole.
    let planned: Vec<(DirectTile, bool, Vec<usize>)> = scene
        .tiles
        .par_iter()
        .filter_map(|tile| {
            let tcone = Cone::new(tile.centre, c, reach + tile.radius);
            let mut vpls: Vec<usize> = (0..scene.groups.axis.len())
                .filter(|&g| scene.groups.meets(g, &tcone))
                .flat_map(|g| scene.groups.members[g].iter().copied())
                .filter(|&j| {
                    tcone.contains(scene.dirs[j]) && om.may_shadow(j, tile.centre, tile.radius)
                })
                .collect();
            // the object maps' groups together (each pixel sums in this order)
            vpls.sort_unstable_by_key(|&j| (om.of[j], j));
            let tile_near = (!bounce.is_empty() || fill)
                && (tile.centre - c).length() - tile.radius <= bounce_reach;
            // the bounce VPLs whose front half-space reaches into the tile
            let tile_bounce: Vec<usize> = if tile_near {
                (0..bounce.len())
                    .filter(|&j| {
                        let (q, nq, _) = &bounce[j];
                        nq.dot(tile.centre - *q) + tile.radius > 0.0
                    })
                    .collect()
            } else {
                Vec::new()
            };
            let any_alpha = tile.pixels.iter().any(|&i| alpha[i] > 0.0);
            if vpls.is_empty() && !tile_near && !any_alpha {
                return None;
            }
            let pixels: Vec<DirectPixel> = tile
                .pixels
                .iter()
                .filter_map(|&i| {
                    let s = scene.target[i].as_ref()?;
                    let cone = Cone::new(s.pos, c, reach);
                    Some(DirectPixel {
                        index: i,
                        pos: s.pos,
                        n: s.n,
                        cone_axis: cone.u,
                        cone_cos_min: cone.cos_min,
                        cone_all: cone.cos_min <= -1.0,
                    })
                })
                .collect();
            Some((DirectTile { pixels, vpls }, tile_near, tile_bounce))
        })
        .collect();
    let mut tiles = Vec::with_capacity(planned.len());
    let mut near_bounce = Vec::with_capacity(planned.len());
    for (t, near, b) in planned {
        tiles.push(t);
        near_bounce.push((near, b));
    }
    let lights = move_lights(&bias_os);
    let plan = DirectPlan {
        tiles,
        lights,
        object_maps: &om.maps,
        scene_maps: &scene.maps,
        centre: c,
    };
    // ---- the target: -Σ Φ cos V^t (1 - V^o) over the VPLs of each
    // pixel's cone (the evaluator's), plus the bounce within its reach
    let direct = sums.direct(&plan)?;
    if direct.len() != plan.pixel_count() {
        return Err(NodeError::Internal(format!(
            "the direct term's evaluator gave {} sums for {} pixels",
            direct.len(),
            plan.pixel_count()
        )));
    }
    let starts = plan.tile_starts();
    // The fill at the pixels the composite rewrites (those the object
    // shades, those within the bounce's reach and the object's own),
    // evaluated in batches by the evaluator: the lattices' nodes, then
    // the pixels they do not serve.
    let fill_pixels: Vec<usize> = if fill {
        let mut v: Vec<usize> = plan
            .tiles
            .iter()
            .zip(&near_bounce)
            .zip(&starts)
            .flat_map(|((tile, (tile_near, _)), &start)| {
                tile.pixels
                    .iter()
                    .zip(&direct[start..])
                    .filter(|(px, sum)| {
                        let near = *tile_near && (px.pos - c).length() <= bounce_reach;
                        sum.hit || near || alpha[px.index] > 0.0
                    })
                    .map(|(px, _)| px.index)
            })
            .collect();
        v.sort_unstable();
        v
    } else {
        Vec::new()
    };
    let fill_values: Vec<Option<FillSum>> = if fill_pixels.is_empty() {
        Vec::new()
    } else {
        let mut many = |list: &[usize]| -> Result<Vec<Option<FillSum>>, NodeError> {
            let surfs: Vec<Surf> = list.iter().filter_map(|&i| scene.target[i]).collect();
            let mut got = sums.fill(&fill_plan, &surfs)?.into_iter();
            if got.len() != surfs.len() {
                return Err(NodeError::Internal(format!(
                    "the fill's evaluator gave {} sums for {} surfaces",
                    got.len(),
                    surfs.len()
                )));
            }
            Ok(list
                .iter()
                .map(|&i| scene.target[i].and_then(|_| got.next()))
                .collect())
        };
        let same = |i: usize, node: usize| scene.target[i].is_some_and(|s| on_surface(&s, node));
        fill_grid.batch(&fill_pixels, &mut many, &same, fill_agree)?
    };
    let diffs: Vec<(usize, [f64; 3], Rgb)> = plan
        .tiles
        .par_iter()
        .zip(near_bounce.par_iter())
        .zip(starts.par_iter())
        .flat_map_iter(|((tile, (tile_near, tile_bounce)), &start)| {
            let mut out = Vec::new();
            for (px, sum) in tile.pixels.iter().zip(&direct[start..]) {
                let (i, de, hit) = (px.index, sum.de, sum.hit);
                let s = Surf {
                    pos: px.pos,
                    n: px.n,
                };
                let near = *tile_near && (s.pos - c).length() <= bounce_reach;
                if !hit && !near && alpha[i] <= 0.0 {
                    continue;
                }
                let (x, y) = (i % w, i / w);
                let same = |node: usize| on_surface(&s, node);
                let b = if near && !bounce.is_empty() {
                    bounce_grid
                        .at(x, y, &bounce_node, same, agree)
                        .unwrap_or_else(|| {
                            let items = tile_bounce.iter().map(|&j| (j, &bounce[j]));
                            bounce_shadows.bounce(s.pos, s.n, r_scene, items, r2_min)
                        })
                } else {
                    [0.0; 3]
                };
                // the scene's own bounce here, and what of it the object blocks
                let f = fill_pixels
                    .binary_search(&i)
                    .ok()
                    .and_then(|k| fill_values.get(k).copied().flatten());
                let (e_ind, blocked) = match f {
                    Some(f) => ([f[0], f[1], f[2]], [f[3], f[4], f[5]]),
                    None => ([0.0; 3], [0.0; 3]),
                };
                let et = match &scene.e_t {
                    Some(e) => std::array::from_fn(|ch| e[i][ch] + e_ind[ch]),
                    None => [0.0; 3],
                };
                let rho = target_albedo(albedo.map(|a| a[i]), photo[i], et, e_floor);
                let d: [f64; 3] =
                    std::array::from_fn(|ch| rho[ch] * (b[ch] - de[ch] - blocked[ch]));
                // the composite here too (in parallel; the scatter below is serial)
                let obj = match obj_idx.binary_search(&i) {
                    Ok(j) => obj_rad[j],
                    Err(_) => [0.0; 3],
                };
                out.push((i, d, composite(photo[i], alpha[i], obj, d)));
            }
            out
        })
        .collect();

    // ---- composite: the photo, rewritten where the object changes it
    let mut color = inp.photo.clone();
    let mut difference: ColorImage = Image::filled(w, h, [0.0f32; 3]);
    let mut region: Mask = Image::filled(w, h, 0.0f32);
    {
        let (cs, ds, rs) = (
            color.as_mut_slice(),
            difference.as_mut_slice(),
            region.as_mut_slice(),
        );
        // Every object pixel with a target surface behind it is in `diffs`
        // (its tile has alpha > 0 and the pixel is kept); the others have
        // no difference.
        for &(i, d, pixel) in &diffs {
            ds[i] = d.map(|v| v as f32);
            rs[i] = 1.0;
            cs[i] = pixel;
        }
        for (&i, obj) in obj_idx.iter().zip(&obj_rad) {
            if scene.target[i].is_none() {
                rs[i] = 1.0;
                cs[i] = composite(photo[i], alpha[i], *obj, [0.0; 3]);
            }
        }
    }
    Ok(Some(Relit {
        color,
        region,
        difference,
    }))
}

/// The parameters [`RelightScene::new`] reads, canonically encoded: the
/// key material of the scene as a derived value (with the keys of the
/// inputs it reads, [`SCENE_PORTS`]).
pub fn scene_key_params(p: &RelightParams) -> Vec<u8> {
    let mut b = Vec::with_capacity(45);
    b.extend_from_slice(&SCENE_CODEC.to_le_bytes());
    b.extend_from_slice(&(p.ism_resolution as u64).to_le_bytes());
    b.extend_from_slice(&(p.ism_points as u64).to_le_bytes());
    b.extend_from_slice(&p.seed.to_le_bytes());
    b.extend_from_slice(&p.bias_scale.to_bits().to_le_bytes());
    b.extend_from_slice(&p.min_distance_m.to_bits().to_le_bytes());
    b.push(u8::from(p.bounce_shadows));
    b
}

/// The inputs of `Relight` that [`RelightScene::new`] reads.
pub const SCENE_PORTS: &[&str] = &["photo", "depth", "normals", "albedo", "vpls", "intrinsics"];

/// Layout version of an encoded [`RelightScene`]; part of its key, so a
/// changed layout never meets an old file.
const SCENE_CODEC: u32 = 3;

impl RelightScene {
    /// Appends the scene to `w` (after the layout version).
    fn write(&self, w: &mut ByteWriter) {
        let k = &self.k;
        for x in [k.fx, k.fy, k.cx, k.cy] {
            w.f64(x);
        }
        w.usize(k.width);
        w.usize(k.height);
        w.seq(&self.vpls, |w, v| {
            w.f32s(&v.direction);
            w.f32s(&v.power);
        });
        w.seq(&self.dirs, |w, d| w.vec3(*d));
        w.f64(self.e_ref);
        w.seq(&self.target, |w, s| {
            w.opt(s, |w, s| {
                w.vec3(s.pos);
                w.vec3(s.n);
            })
        });
        w.seq(&self.areas, |w, x| w.f64(*x));
        w.seq(&self.maps, |w, m| w.opt(m, |w, m| m.write(w)));
        w.opt(&self.e_t, |w, e| {
            w.seq(e, |w, c| {
                for x in c {
                    w.f64(*x);
                }
            })
        });
        let g = &self.groups;
        w.seq(&g.axis, |w, a| w.vec3(*a));
        w.seq(&g.cos_h, |w, x| w.f64(*x));
        w.seq(&g.sin_h, |w, x| w.f64(*x));
        w.seq(&g.members, |w, m| w.seq(m, |w, j| w.usize(*j)));
        w.seq(&self.bias_t, |w, x| w.f64(*x));
        w.seq(&self.tiles, |w, t| {
            w.vec3(t.centre);
            w.f64(t.radius);
            w.seq(&t.pixels, |w, i| w.usize(*i));
        });
        w.opt(&self.pool, |w, p| p.write(w));
        w.f64(self.bias_scale);
        w.bool(self.with_albedo);
    }

    /// Reads what [`RelightScene::write`] wrote.
    fn read(r: &mut ByteReader) -> Option<Self> {
        let (fx, fy, cx, cy) = (r.f64()?, r.f64()?, r.f64()?, r.f64()?);
        let (width, height) = (r.usize()?, r.usize()?);
        let three = |r: &mut ByteReader| -> Option<[f32; 3]> { r.f32s()?.try_into().ok() };
        Some(Self {
            k: Intrinsics {
                fx,
                fy,
                cx,
                cy,
                width,
                height,
            },
            vpls: r.seq(40, |r| {
                Some(Vpl {
                    direction: three(r)?,
                    power: three(r)?,
                })
            })?,
            dirs: r.seq(24, ByteReader::vec3)?,
            e_ref: r.f64()?,
            target: r.seq(1, |r| {
                r.opt(|r| {
                    Some(Surf {
                        pos: r.vec3()?,
                        n: r.vec3()?,
                    })
                })
            })?,
            areas: r.seq(8, ByteReader::f64)?,
            maps: r.seq(1, |r| r.opt(ShadowMap::read))?,
            e_t: r.opt(|r| r.seq(24, |r| Some([r.f64()?, r.f64()?, r.f64()?])))?,
            groups: DirGroups {
                axis: r.seq(24, ByteReader::vec3)?,
                cos_h: r.seq(8, ByteReader::f64)?,
                sin_h: r.seq(8, ByteReader::f64)?,
                members: r.seq(8, |r| r.seq(8, ByteReader::usize))?,
            },
            bias_t: r.seq(8, ByteReader::f64)?,
            tiles: r.seq(40, |r| {
                Some(Tile {
                    centre: r.vec3()?,
                    radius: r.f64()?,
                    pixels: r.seq(8, ByteReader::usize)?,
                })
            })?,
            pool: r.opt(PointSet::read)?,
            bias_scale: r.f64()?,
            with_albedo: r.bool()?,
        })
    }

    /// Whether the parts agree with each other (lengths and indices), so a
    /// decoded scene can be indexed without a panic.
    fn consistent(&self) -> bool {
        let n = self.vpls.len();
        let px = self.k.width.saturating_mul(self.k.height);
        self.dirs.len() == n
            && self.maps.len() == n
            && self.bias_t.len() == n
            && self.target.len() == px
            && self.areas.len() == px
            && self.e_t.as_ref().is_none_or(|e| e.len() == px)
            && self.groups.axis.len() == self.groups.members.len()
            && self.groups.cos_h.len() == self.groups.members.len()
            && self.groups.sin_h.len() == self.groups.members.len()
            && self.groups.members.iter().flatten().all(|&j| j < n)
            && self.tiles.iter().flat_map(|t| &t.pixels).all(|&i| i < px)
            && self.maps.iter().flatten().all(ShadowMap::consistent)
            && self.pool.as_ref().is_none_or(PointSet::consistent)
    }
}

/// Reads back what [`RelightScene`]'s `encode` wrote (the disk cache's
/// decoder, registered with the `Relight` node); `None` for anything
/// malformed or inconsistent.
pub fn decode_scene(bytes: &[u8]) -> Option<Arc<dyn depthgraph_graph::value::Extension>> {
    let (version, rest) = bytes.split_first_chunk::<4>()?;
    if u32::from_le_bytes(*version) != SCENE_CODEC {
        return None;
    }
    let mut r = ByteReader::new(rest);
    let scene = RelightScene::read(&mut r)?;
    (r.is_done() && scene.consistent()).then(|| Arc::new(scene) as _)
}

impl depthgraph_graph::value::Extension for RelightScene {
    fn type_name(&self) -> &'static str {
        "RelightScene"
    }
    fn bytes(&self) -> usize {
        self.heap_bytes()
    }
    fn encode(&self) -> Option<Vec<u8>> {
        let mut w = ByteWriter(SCENE_CODEC.to_le_bytes().to_vec());
        self.write(&mut w);
        Some(w.0)
    }
    fn as_any(&self) -> &dyn std::any::Any {
        self
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::relight::paired::relight;
    use crate::test_support::relight::floor_and_slab_at;
    use crate::test_support::relight::{SlabScene, overhead, slab_shadow_is_analytic};

    fn cached(inp: &RelightInputs, vpls: &[Vpl], p: &RelightParams) -> Relit {
        let scene = RelightScene::new(&inp.scene(), vpls, p).unwrap();
        relight_moved(&scene, inp, p).unwrap().unwrap()
    }

    /// The analytic shadow of the slab (the check of the paired scheme's
    /// test), with the scene cached, at two places of the slab.
    #[test]
    fn a_slab_casts_its_analytic_shadow_with_the_scene_cached() {
        slab_shadow_is_analytic(&cached, 0.0);
        slab_shadow_is_analytic(&cached, 0.35);
    }

    /// The object's lattices test the received irradiance `E^{s+t} + B_s`
    /// and `E_cap`, the ratio's two terms: a bounce that swings by all of
    /// itself but by under 5 % of the whole blends on the coarse lattice
    /// (only its 5 x 5 nodes of a 16 x 16 plane are summed, each blend
    /// within 5 % of the value there), while a whole that swings by more
    /// is summed at more pixels.
    #[test]
    fn the_object_lattices_test_the_light_received_in_all() {
        use std::sync::atomic::{AtomicUsize, Ordering};
        let (w, h) = (16, 16);
        let obj_idx: Vec<usize> = (0..w * h).collect();
        let surfs: Vec<Surf> = obj_idx
            .iter()
            .map(|&i| Surf {
                pos: DVec3::new((i % w) as f64 * 0.01, (i / w) as f64 * 0.01, 2.0),
                n: DVec3::NEG_Z,
            })
            .collect();
        let agree = Agreement {
            rel: LATTICE_REL,
            abs: 0.0,
            whole: true,
        };
        // the value at a surface: direct light 1, a bounce of `swing` about
        // its mean that changes by all of itself over a few pixels
        let value = |s: &Surf, swing: f64| -> Irradiances {
            let bs = swing * (1.0 + (s.pos.x * 100.0).sin());
            [[1.0 + bs; 3], [1.0; 3]]
        };
        for (swing, blends) in [(0.02, true), (0.2, false)] {
            let summed = AtomicUsize::new(0);
            let mut exact = |ss: &[Surf]| -> Result<Vec<Irradiances>, NodeError> {
                summed.fetch_add(ss.len(), Ordering::Relaxed);
                Ok(ss.iter().map(|s| value(s, swing)).collect())
            };
            let irr = lattice_irradiance(&obj_idx, &surfs, w, h, 2, agree, &mut exact).unwrap();
            let n = summed.load(Ordering::Relaxed);
            if blends {
                assert_eq!(n, 25, "swing {swing}: {n} surfaces summed");
                for (s, v) in surfs.iter().zip(&irr) {
                    let want = value(s, swing);
                    assert!((v[0][0] - want[0][0]).abs() <= LATTICE_REL * want[0][0]);
                    assert_eq!(v[1], [1.0; 3]);
                }
            } else {
                assert!(n > 25, "swing {swing}: only {n} surfaces summed");
            }
        }
    }

    fn sky(n: usize) -> Vec<Vpl> {
        (0..n)
            .map(|j| {
                let a = j as f32 * 0.7;
                Vpl {
                    direction: [0.5 * a.cos(), -1.0, 0.5 * a.sin()],
                    power: [0.1, 0.2, 0.05 * (j % 3) as f32],
                }
            })
            .collect()
    }

    /// One scene serves the object at two places: each result is the one a
    /// scene built for it alone gives, bit for bit, on any thread count;
    /// and the shadow moves with the object.
    #[test]
    fn a_cached_scene_gives_what_a_fresh_one_gives_wherever_the_object_is() {
        let (w, h) = (80, 60);
        let (k, floor, slab_a, alpha_a) = floor_and_slab_at(w, h, 0.0);
        let (_, _, slab_b, alpha_b) = floor_and_slab_at(w, h, 0.3);
        let photo = floor.map(|z| if *z > 0.0 { [0.5f32; 3] } else { [0.0; 3] });
        let pasted_color = Image::filled(w, h, [0.3f32, 0.6, 0.2]);
        let inp = |slab: &'static DepthMap, alpha: &'static Mask| RelightInputs {
            photo: Box::leak(Box::new(photo.clone())),
            depth: Box::leak(Box::new(floor.clone())),
            normals: None,
            albedo: None,
            pasted_color: Box::leak(Box::new(pasted_color.clone())),
            pasted_depth: slab,
            alpha,
            k: Box::leak(Box::new(k)),
            capture_vpls: None,
        };
        let leak_d = |d: DepthMap| -> &'static DepthMap { Box::leak(Box::new(d)) };
        let leak_m = |m: Mask| -> &'static Mask { Box::leak(Box::new(m)) };
        let (ia, ib) = (
            inp(leak_d(slab_a), leak_m(alpha_a)),
            inp(leak_d(slab_b), leak_m(alpha_b)),
        );
        let vpls = sky(24);
        let p = RelightParams {
            ism_points: 3000,
            ism_resolution: 48,
            bounce_vpls: 32,
            ..Default::default()
        };
        let scene = RelightScene::new(&ia.scene(), &vpls, &p).unwrap();
        let ra = relight_moved(&scene, &ia, &p).unwrap().unwrap();
        let rb = relight_moved(&scene, &ib, &p).unwrap().unwrap();
        assert_eq!(ra, cached(&ia, &vpls, &p));
        assert_eq!(rb, cached(&ib, &vpls, &p));
        assert_ne!(ra.color, rb.color);
        for threads in [1, 3] {
            let again = crate::test_support::with_threads(threads, || {
                let s = RelightScene::new(&ia.scene(), &vpls, &p).unwrap();
                relight_moved(&s, &ib, &p).unwrap().unwrap()
            });
            assert_eq!(again, rb, "{threads} threads");
        }
        // The shadow follows: the darkened floor's mean x moves by the
        // object's 0.3 m (within a pixel's width at 2 m: ~3 cm here).
        let mean_x = |r: &Relit, alpha: &Mask| {
            let (mut sum, mut n) = (0.0, 0.0);
            for i in 0..w * h {
                let dl = r.difference.as_slice()[i];
                let z = *floor.get(i % w, i / w);
                if alpha.as_slice()[i] == 0.0 && z > 0.0 && dl[1] < -1e-3 {
                    let q = k.unproject((i % w) as f64 + 0.5, (i / w) as f64 + 0.5, z as f64);
                    // weighted by how much darker
                    sum += q.x * f64::from(-dl[1]);
                    n += f64::from(-dl[1]);
                }
            }
            assert!(n > 0.0, "no shadow");
            sum / n
        };
        let shift = mean_x(&rb, ib.alpha) - mean_x(&ra, ia.alpha);
        assert!((shift - 0.3).abs() < 0.06, "shadow moved {shift} m");
    }

    /// The lattices (`lattice_step` 2, the default) against every pixel
    /// evaluated (`lattice_step` 1): the same pixels rendered, the photo
    /// kept bit for bit elsewhere, and every rendered value within 2 % of
    /// the largest change the object makes (the blend's 5 % tolerance on
    /// terms that are part of the change), though not equal (the lattice
    /// did blend).
    #[test]
    fn the_lattices_stay_close_to_every_pixel() {
        let (w, h) = (160, 120);
        let sc = SlabScene::new(w, h, 0.0);
        let inp = sc.inputs(false);
        let vpls = sky(64);
        let exact = RelightParams {
            lattice_step: 1,
            ..Default::default()
        };
        let a = cached(&inp, &vpls, &RelightParams::default());
        let b = cached(&inp, &vpls, &exact);
        assert_eq!(a.region, b.region);
        let (mut worst, mut largest) = (0.0f32, 0.0f32);
        for i in 0..w * h {
            let (ca, cb, p) = (
                a.color.as_slice()[i],
                b.color.as_slice()[i],
                inp.photo.as_slice()[i],
            );
            if a.region.as_slice()[i] == 0.0 {
                assert_eq!(ca, p);
                continue;
            }
            for ch in 0..3 {
                worst = worst.max((ca[ch] - cb[ch]).abs());
                largest = largest.max((cb[ch] - p[ch]).abs());
            }
        }
        assert!(worst > 0.0, "the lattice changed nothing");
        assert!(worst <= 0.02 * largest, "{worst} against {largest}");
    }

    /// Both schemes agree with the ray-cast reference where they should
    /// (the changed pixels, up to the shadow's outline), the scene-cached
    /// one at least as closely as the paired one: its object maps are the
    /// object's mesh, not splats that widen the shadow by their radius.
    #[test]
    fn cached_and_paired_schemes_agree_with_the_rays_on_the_slab() {
        let (w, h) = (160, 120);
        let sc = SlabScene::new(w, h, 0.0);
        let inp = sc.inputs(false);
        let vpls = sky(64);
        let p = RelightParams {
            ism_points: 20000,
            ism_resolution: 128,
            ..Default::default()
        };
        let a = cached(&inp, &vpls, &p);
        let b = relight(&inp, &vpls, &p).unwrap().unwrap();
        let r = crate::relight::reference::relight_reference_image(&inp, &vpls, &p)
            .unwrap()
            .unwrap();
        let rmse = |x: &Relit| {
            let (mut sum, mut n) = (0.0f64, 0usize);
            for i in 0..w * h {
                let (c, t) = (x.color.as_slice()[i], r.color.as_slice()[i]);
                if x.region.as_slice()[i] > 0.0 || r.region.as_slice()[i] > 0.0 {
                    sum += (0..3)
                        .map(|ch| f64::from(c[ch] - t[ch]).powi(2))
                        .sum::<f64>();
                    n += 3;
                } else {
                    assert_eq!(c, t);
                }
            }
            assert!(n > 300, "{n} changed values");
            (sum / n as f64).sqrt()
        };
        let (ea, eb) = (rmse(&a), rmse(&b));
        assert!(
            ea < 0.03 && eb < 0.06 && ea < 0.75 * eb,
            "cached {ea}, paired {eb}"
        );
    }

    /// A sphere above a floor, lit from in front of the camera (the light
    /// sees the sphere's unseen back): with the closed back its shadow has
    /// the analytic ellipse's area `π r² / sin e` within 5 % (-3.5 % when
    /// written) at the default resolutions; the open shell casts a visibly
    /// smaller one (-27 %).
    #[test]
    fn the_closed_back_casts_the_spheres_shadow() {
        let (w, h) = (320, 240);
        let k = crate::sim::synthetic::kinect_like_intrinsics(w, h);
        let (c, r, floor_y) = (DVec3::new(0.0, 0.2, 2.0), 0.15, 0.5);
        let floor = Image::from_fn(w, h, |_, y| {
            let dy = (y as f64 + 0.5 - k.cy) / k.fy;
            if dy > 0.05 {
                (floor_y / dy) as f32
            } else {
                0.0
            }
        });
        let sphere = crate::test_support::relight::sphere_depth(&k, c, r, false);
        let alpha = sphere.map(|z| if *z > 0.0 { 1.0f32 } else { 0.0 });
        let photo = floor.map(|z| if *z > 0.0 { [0.5f32; 3] } else { [0.0; 3] });
        let albedo = Image::filled(w, h, [0.5f32; 3]);
        let pasted = Image::filled(w, h, [0.4f32; 3]);
        let elev = 45f64.to_radians();
        // light from in front of the camera (+z), 45° up: the shadow falls
        // towards the camera
        let vpls = vec![Vpl {
            direction: [0.0, -elev.sin() as f32, elev.cos() as f32],
            power: [1.0; 3],
        }];
        let inp = RelightInputs {
            photo: &photo,
            depth: &floor,
            normals: None,
            albedo: Some(&albedo),
            pasted_color: &pasted,
            pasted_depth: &sphere,
            alpha: &alpha,
            k: &k,
            capture_vpls: None,
        };
        let area = |close: bool| {
            let p = RelightParams {
                close_back: close,
                bounce_vpls: 0,
                scene_vpls: 0,
                ..Default::default()
            };
            let rl = cached(&inp, &vpls, &p);
            (0..w * h)
                .filter(|&i| alpha.as_slice()[i] == 0.0 && floor.as_slice()[i] > 0.0)
                .filter(|&i| rl.color.as_slice()[i][0] < 0.25)
                .map(|i| crate::relight::ism::pixel_area(&floor, &k, i % w, i / w).0)
                .sum::<f64>()
        };
        let want = std::f64::consts::PI * r * r / elev.sin();
        let closed = area(true);
        assert!(
            (closed - want).abs() < 0.05 * want,
            "closed: {closed:.5} m² vs {want:.5}"
        );
        let open = area(false);
        assert!(open < 0.95 * want, "open shell: {open:.5} m² vs {want:.5}");
    }

    #[test]
    fn a_scene_used_with_other_inputs_is_an_error() {
        let (w, h) = (40, 30);
        let sc = SlabScene::new(w, h, 0.0);
        let (k, photo) = (sc.k, &sc.photo);
        let inp = sc.inputs(false);
        let p = RelightParams::default();
        let scene = RelightScene::new(&inp.scene(), &overhead(), &p).unwrap();
        let k2 = Intrinsics {
            fx: k.fx * 2.0,
            ..k
        };
        let other = RelightInputs { k: &k2, ..inp };
        assert!(relight_moved(&scene, &other, &p).is_err());
        let with_albedo = RelightInputs {
            albedo: Some(photo),
            ..inp
        };
        assert!(relight_moved(&scene, &with_albedo, &p).is_err());
        let small = Image::filled(20, 15, 0.0f32);
        let bad = RelightInputs {
            alpha: &small,
            ..inp
        };
        assert!(relight_moved(&scene, &bad, &p).is_err());
        // nothing pasted (no pasted depth): nothing to do
        let zero = Image::filled(w, h, 0.0f32);
        let no_depth = DepthMap::filled(w, h, 0.0);
        let none = RelightInputs {
            alpha: &zero,
            pasted_depth: &no_depth,
            ..inp
        };
        assert!(relight_moved(&scene, &none, &p).unwrap().is_none());
    }

    /// The open room of `sim::relight_truth` at 96x72, one path per pixel
    /// (the photo's exact values do not matter to the tests using it).
    fn quick_open_room() -> crate::sim::relight_truth::RelightCase {
        use crate::sim::pathtrace::PathTraceParams;
        use crate::sim::relight_truth::{Room, relight_case};
        let quick = PathTraceParams {
            samples: 1,
            bounces: 1,
            seed: 1,
        };
        relight_case(Room::Open, None, 96, 72, 32, &quick).unwrap()
    }

    /// The capture side follows the capture map's own brightness: capture
    /// VPLs 100 times dimmer make the object 100 times brighter (its
    /// pasted colour was seen under less light), face by face. The floor
    /// was the target's: every face of a dim capture sat on it and the
    /// object's shading was lost. Capture VPLs that carry no light are an
    /// error naming the port.
    #[test]
    fn the_capture_side_follows_the_capture_maps_own_scale() {
        let c = quick_open_room();
        let vpls = c.vpls(64);
        let p = RelightParams::default();
        let base = c.inputs();
        let scene = RelightScene::new(&base.scene(), &vpls, &p).unwrap();
        let run = |cap: &[Vpl]| {
            let mut inp = c.inputs();
            inp.capture_vpls = Some(cap);
            relight_moved(&scene, &inp, &p).map(|r| r.unwrap().color)
        };
        let dim: Vec<Vpl> = vpls
            .iter()
            .map(|v| Vpl {
                power: v.power.map(|x| x * 0.01),
                ..*v
            })
            .collect();
        let (full, dimmed) = (run(&vpls).unwrap(), run(&dim).unwrap());
        let mut checked = 0;
        for (i, a) in c.alpha.as_slice().iter().enumerate() {
            if *a < 1.0 {
                continue;
            }
            let (f, d) = (full.as_slice()[i], dimmed.as_slice()[i]);
            for ch in 0..3 {
                if f[ch] > 1e-4 {
                    let ratio = d[ch] / f[ch];
                    assert!((ratio - 100.0).abs() < 0.05, "pixel {i}: {ratio}");
                    checked += 1;
                }
            }
        }
        assert!(checked > 100, "{checked}");
        let black: Vec<Vpl> = vpls
            .iter()
            .map(|v| Vpl {
                power: [0.0; 3],
                ..*v
            })
            .collect();
        let e = run(&black).unwrap_err().to_string();
        assert!(e.contains("capture_vpls"), "{e}");
    }

    /// An object the scene hides whole (alpha 0 after the depth test, its
    /// pasted depth still there) casts the shadow it casts when a part of
    /// it shows, in both map schemes: the node passed the photo through
    /// ("nothing pasted") and the shadow vanished with the last pixel.
    #[test]
    fn an_object_hidden_whole_still_casts_its_shadow() {
        let c = quick_open_room();
        let vpls = c.vpls(64);
        let p = RelightParams::default();
        let hidden = Mask::filled(96, 72, 0.0);
        let lum = |v: [f32; 3]| v[0] + v[1] + v[2];
        let photo = c.photo.as_slice();
        let check = |vis: &ColorImage, hid: &ColorImage, scheme: &str| {
            let shadow: Vec<usize> = (0..96 * 72)
                .filter(|&i| c.alpha.as_slice()[i] == 0.0)
                .filter(|&i| lum(vis.as_slice()[i]) < 0.8 * lum(photo[i]))
                .collect();
            assert!(
                shadow.len() > 20,
                "{scheme}: {} shadow pixels",
                shadow.len()
            );
            let kept = shadow
                .iter()
                .filter(|&&i| lum(hid.as_slice()[i]) < 0.9 * lum(photo[i]))
                .count();
            assert!(
                kept * 10 >= shadow.len() * 9,
                "{scheme}: {kept} of {}",
                shadow.len()
            );
            assert!(hid.as_slice().iter().flatten().all(|v| v.is_finite()));
        };
        let base = c.inputs();
        let scene = RelightScene::new(&base.scene(), &vpls, &p).unwrap();
        let mut inp = c.inputs();
        let vis = relight_moved(&scene, &inp, &p).unwrap().unwrap().color;
        inp.alpha = &hidden;
        let hid = relight_moved(&scene, &inp, &p).unwrap().unwrap().color;
        check(&vis, &hid, "scene_cached");
        let mut inp = c.inputs();
        let vis = crate::relight::paired::relight(&inp, &vpls, &p)
            .unwrap()
            .unwrap()
            .color;
        inp.alpha = &hidden;
        let hid = crate::relight::paired::relight(&inp, &vpls, &p)
            .unwrap()
            .unwrap()
            .color;
        check(&vis, &hid, "paired");
    }
}
