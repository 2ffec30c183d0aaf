//! Imperfect shadow maps (ISM; 3d-editing §IV.A: "Instant radiosity with
//! imperfect shadow map (ISM) \[8\] is exploited [...] The ISM uses shadow maps
//! based on the approximated point samples of the scene", and eq. 6, the
//! near-object importance of the point samples).
//!
//! Pure functions: the `Relight` node builds the maps it needs.
//!
//! # Point samples with near-object importance (eq. 6)
//!
//! Every valid pixel of the given depth layers (the target, and the pasted
//! object) is a surface element at its unprojected centre with its surface
//! area `a_i` ([`pixel_area`]: the fronto-parallel footprint `z² / (fx fy)`
//! corrected for the slant, so a floor seen at a grazing angle is not
//! under-sampled) and
//! importance `I_i = Σ_j 1 / max(d(p_i, o_j), min_distance_m)` (eq. 6; the
//! floor guards the division at an object centre). Each shadow map draws its
//! own `points_per_map` = M samples with probability `∝ a_i I_i` (stratified
//! over the CDF, its own seed: the "imperfect" part, different VPLs see
//! different subsets). A sample at `p` stands for the area `W / (M I(p))`
//! (`W = Σ a_i I_i`), so it is splatted as a disc of radius
//! `r(p) = sqrt(W / (π M I(p)))`: small and dense near the object, coarse
//! far from it; never below 0.6 x the pixel's longer side on the surface
//! (the samples are pixel centres: a splat smaller than their spacing would
//! leave gaps a shadow leaks through), never above `max_splat_texels`. With no object centre, `I = 1` (uniform area sampling).
//!
//! # Orthographic maps for directional VPLs
//!
//! The environment's VPLs are directional (at infinity, see [`crate::relight::vpl`]),
//! so every shadow ray towards one is parallel: an **orthographic** depth map
//! along the direction `d` is exact for them, where a paraboloid map (the
//! ISM paper's choice for point VPLs at finite positions) would waste
//! resolution on directions that never occur. A map stores, per texel of a
//! plane perpendicular to `d`, the largest `t = p·d` of the samples splatted
//! there (the occluder nearest to the light). Its window is the bounding box
//! of the **receivers** (the points that will be shaded) in that plane: a
//! point projecting outside it cannot shadow any receiver. Texels are square,
//! `texel_m = extent / resolution`.
//!
//! Holes between splats are filled by pull-push ([`crate::depth::pull_push`],
//! bilinear weights) on the stored `t` (shifted to be positive).
//!
//! Two maps are built from the **same** samples, one without the object's
//! points (scene `t`) and one with them (scene `s+t`): where no object point
//! lands they are equal texel for texel, so the differential image
//! `I_{s+t} - I_t` (eq. 5) carries no sampling noise of the target's own shadows.
//!
//! # Visibility
//!
//! A receiver `p` with normal `n` sees the light iff the map has no sample
//! there or `t_map <= p·d + bias`, with a scene-scale-aware bias
//! `bias = bias_scale * max(texel_m, r(p)) * (1 + min(tan θ, 10))`,
//! `cos θ = |n·d|`: a surface's own splats differ from its depth by up to
//! about their radius times the slope.

use depthgraph_graph::node_params;
use depthgraph_graph::prelude::*;
use glam::DVec3;

use crate::depth::pull_push::{PullPushParams, Weights, pull_push};
use crate::kit::rng::SplitMix64;
use depthgraph_graph::bytes::{ByteReader, ByteWriter};

node_params! {
    /// Parameters of the imperfect shadow maps.
    pub struct IsmParams {
        /// Texels per side of each map.
        pub resolution: usize = 96usize, ParamKind::Int { min: 4, max: 2048 };
        /// Point samples splatted into each map (M).
        pub points_per_map: usize = 8192usize, ParamKind::Int { min: 16, max: 1 << 22 };
        /// Largest splat radius in texels (bigger samples leave holes that pull-push fills).
        pub max_splat_texels: f64 = 3.0, ParamKind::Float { min: 0.5, max: 64.0 };
        /// Visibility bias in units of max(texel, splat radius), scaled by the slope.
        pub bias_scale: f64 = 1.5, ParamKind::Float { min: 0.0, max: 100.0 };
        /// Floor of the distance in eq. 6 (metres): guards 1/d at the object centre.
        pub min_distance_m: f64 = 0.05, ParamKind::Float { min: 1e-6, max: 1e3 };
        /// Seed of the per-map point subsets.
        pub seed: u64 = 1u64, ParamKind::Int { min: 0, max: 1 << 53 };
    }
}

/// Eq. 6: `Σ_j 1 / max(d(p, o_j), min_d)`; 1 without centres.
#[inline]
pub fn importance(p: DVec3, centres: &[DVec3], min_d: f64) -> f64 {
    if centres.is_empty() {
        return 1.0;
    }
    // guard: min_d > 0 (parameter range)
    centres
        .iter()
        .map(|o| 1.0 / (p - *o).length().max(min_d))
        .sum()
}

/// Largest ratio of a pixel's surface area to its fronto-parallel area
/// (a surface seen at about 87 degrees from its normal).
pub const MAX_SLANT: f64 = 20.0;

/// Two neighbouring pixels are on one surface when their depths differ by
/// at most this fraction ([`pixel_area`], `surface_steps`, the object's
/// mesh).
pub const SAME_SURFACE: f64 = 0.1;

/// Surface area (m²) of pixel `(x, y)` of a valid depth: `|∂P/∂u × ∂P/∂v|`
/// from the unprojected neighbours on the same surface (depth ratio within
/// 10 %, forward or backward differences), clamped to
/// `[1, MAX_SLANT] * z² / (fx fy)` (the fronto-parallel area, also the
/// fallback without neighbours). Also returns the longer side of the pixel
/// on the surface (m): the spacing of the pixel samples there. `k` must be sane.
pub fn pixel_area(depth: &DepthMap, k: &Intrinsics, x: usize, y: usize) -> (f64, f64) {
    let z = *depth.get(x, y) as f64;
    // guard: k is sane (checked by the caller), fx fy > 0
    let a0 = z * z / (k.fx * k.fy);
    let (_, du, dv) = surface_steps(depth, k, x, y);
    let side = a0.sqrt();
    match (du, dv) {
        (Some(a), Some(b)) => (
            a.cross(b).length().clamp(a0, MAX_SLANT * a0),
            a.length().max(b.length()).min(MAX_SLANT * side),
        ),
        _ => (a0, side),
    }
}

/// Pixel `(x, y)` of a valid depth unprojected, and its steps to the next
/// pixel along x and along y on the same surface (depth ratio within
/// 10 %): the forward difference, else the backward one, else `None`.
/// `k` must be sane.
pub(crate) fn surface_steps(
    depth: &DepthMap,
    k: &Intrinsics,
    x: usize,
    y: usize,
) -> (DVec3, Option<DVec3>, Option<DVec3>) {
    let z = *depth.get(x, y) as f64;
    let at = |xx: usize, yy: usize| {
        k.unproject(xx as f64 + 0.5, yy as f64 + 0.5, *depth.get(xx, yy) as f64)
    };
    let same = |xx: usize, yy: usize| {
        let zz = *depth.get(xx, yy) as f64;
        // guard: both depths > 0 when valid
        DepthMap::is_valid(zz as f32) && zz.max(z) / zz.min(z) <= 1.0 + SAME_SURFACE
    };
    let (w, h) = depth.dims();
    let p = at(x, y);
    let du = if x + 1 < w && same(x + 1, y) {
        Some(at(x + 1, y) - p)
    } else if x > 0 && same(x - 1, y) {
        Some(p - at(x - 1, y))
    } else {
        None
    };
    let dv = if y + 1 < h && same(x, y + 1) {
        Some(at(x, y + 1) - p)
    } else if y > 0 && same(x, y - 1) {
        Some(p - at(x, y - 1))
    } else {
        None
    };
    (p, du, dv)
}

/// The surface elements of the scene, with their sampling CDF.
#[derive(Debug, Clone)]
pub struct PointSet {
    /// Per element: its unprojected pixel centre (camera frame, metres),
    /// layer by layer in scan order.
    pub positions: Vec<DVec3>,
    /// Whether each element belongs to the pasted object.
    pub object: Vec<bool>,
    cdf: Vec<f64>,
    /// Per element: 0.6 x its longer pixel side (m), the smallest splat
    /// radius that leaves no gap between the pixel samples of a surface.
    pub min_radius: Vec<f64>,
    /// `W = Σ a_i I_i`.
    pub total: f64,
    /// The object centres `o_j` of eq. 6 (camera frame, metres); empty =
    /// uniform importance `I = 1`.
    pub centres: Vec<DVec3>,
    /// Floor of the distance in eq. 6, metres.
    pub min_distance_m: f64,
    /// Per element, packed for the splatting (one cache line per drawn sample).
    elems: Vec<Elem>,
}

/// What splatting needs of one element.
#[derive(Debug, Clone, Copy)]
struct Elem {
    pos: DVec3,
    min_radius: f64,
    /// `1 / sqrt(I(p))` (eq. 6, `I > 0`): the splat radius is
    /// `sqrt(W / (π M)) / sqrt(I)`.
    inv_sqrt_importance: f64,
    object: bool,
}

impl PointSet {
    /// Appends the set to `w` (the disk cache's encoding of a relight scene).
    pub(crate) fn write(&self, w: &mut ByteWriter) {
        w.seq(&self.positions, |w, p| w.vec3(*p));
        w.seq(&self.object, |w, b| w.bool(*b));
        w.seq(&self.cdf, |w, x| w.f64(*x));
        w.seq(&self.min_radius, |w, x| w.f64(*x));
        w.f64(self.total);
        w.seq(&self.centres, |w, p| w.vec3(*p));
        w.f64(self.min_distance_m);
        w.seq(&self.elems, |w, e| {
            w.vec3(e.pos);
            w.f64(e.min_radius);
            w.f64(e.inv_sqrt_importance);
            w.bool(e.object);
        });
    }

    /// Reads what [`PointSet::write`] wrote.
    pub(crate) fn read(r: &mut ByteReader) -> Option<Self> {
        Some(Self {
            positions: r.seq(24, ByteReader::vec3)?,
            object: r.seq(1, ByteReader::bool)?,
            cdf: r.seq(8, ByteReader::f64)?,
            min_radius: r.seq(8, ByteReader::f64)?,
            total: r.f64()?,
            centres: r.seq(24, ByteReader::vec3)?,
            min_distance_m: r.f64()?,
            elems: r.seq(41, |r| {
                Some(Elem {
                    pos: r.vec3()?,
                    min_radius: r.f64()?,
                    inv_sqrt_importance: r.f64()?,
                    object: r.bool()?,
                })
            })?,
        })
    }

    /// Whether the per-element arrays have one entry per element.
    pub(crate) fn consistent(&self) -> bool {
        let n = self.positions.len();
        self.object.len() == n
            && self.cdf.len() == n
            && self.min_radius.len() == n
            && self.elems.len() == n
    }

    /// Approximate heap size in bytes.
    pub fn heap_bytes(&self) -> usize {
        self.positions.len() * 24
            + self.object.len()
            + self.cdf.len() * 8
            + self.min_radius.len() * 8
            + self.centres.len() * 24
            + self.elems.len() * std::mem::size_of::<Elem>()
    }
}

impl PointSet {
    /// Elements of the valid pixels of each `(depth, is_object)` layer seen
    /// by `k` (module docs). Layers must be `k.width x k.height`.
    pub fn new(
        layers: &[(&DepthMap, bool)],
        k: &Intrinsics,
        centres: &[DVec3],
        min_d: f64,
    ) -> Self {
        let mut positions = Vec::new();
        let mut object = Vec::new();
        let mut cdf = Vec::new();
        let mut min_radius = Vec::new();
        let mut elems = Vec::new();
        let mut acc = 0.0f64;
        for (depth, is_obj) in layers {
            let (w, h) = depth.dims();
            for y in 0..h {
                for x in 0..w {
                    let z = *depth.get(x, y);
                    if !DepthMap::is_valid(z) {
                        continue;
                    }
                    let p = k.unproject(x as f64 + 0.5, y as f64 + 0.5, z as f64);
                    let (area, side) = pixel_area(depth, k, x, y);
                    min_radius.push(0.6 * side);
                    let imp = importance(p, centres, min_d);
                    elems.push(Elem {
                        pos: p,
                        min_radius: 0.6 * side,
                        // guard: imp > 0 (sum of positive terms, or 1)
                        inv_sqrt_importance: 1.0 / imp.sqrt(),
                        object: *is_obj,
                    });
                    acc += area * imp;
                    positions.push(p);
                    object.push(*is_obj);
                    cdf.push(acc);
                }
            }
        }
        Self {
            positions,
            object,
            cdf,
            min_radius,
            total: acc,
            centres: centres.to_vec(),
            min_distance_m: min_d,
            elems,
        }
    }

    /// Splat radius `r(p)` of a sample at `p` when `m` samples are drawn.
    pub fn splat_radius(&self, p: DVec3, m: usize) -> f64 {
        self.radius_for(importance(p, &self.centres, self.min_distance_m), m)
    }

    /// `r` for a known importance `i` (> 0).
    #[inline]
    fn radius_for(&self, i: f64, m: usize) -> f64 {
        // guard: i > 0 (sum of positive terms or 1)
        self.base_radius(m) / i.sqrt()
    }

    /// `sqrt(W / (π M))`: the splat radius at importance 1.
    #[inline]
    pub fn base_radius(&self, m: usize) -> f64 {
        // guard: m >= 1
        (self.total / (std::f64::consts::PI * m.max(1) as f64)).sqrt()
    }

    /// `m` stratified sample indices drawn with probability `∝ a_i I_i`.
    pub fn draw(&self, m: usize, seed: u64) -> Vec<usize> {
        if self.positions.is_empty() || !self.total.is_finite() || self.total <= 0.0 {
            return Vec::new();
        }
        let mut rng = SplitMix64(seed);
        let cdf = &self.cdf;
        let n = cdf.len();
        // The stratified `t` never decrease (`(i + u) / m` with `u < 1`,
        // monotone rounding), so each search gallops from the previous
        // answer: the same index as `partition_point` over the whole CDF,
        // without its cache misses.
        let mut prev = 0usize;
        (0..m)
            .map(|i| {
                // guard: m >= 1 inside the map
                let t = (i as f64 + rng.next_f64()) / m as f64 * self.total;
                // invariant: every index < lo has c <= t; cdf[hi] > t or hi = n
                let (mut lo, mut hi, mut step) = (prev.min(n), prev.min(n), 1usize);
                while hi < n && cdf[hi] <= t {
                    lo = hi + 1;
                    hi = lo.saturating_add(step).min(n);
                    step = step.saturating_mul(2);
                }
                let j = lo + cdf[lo..hi].partition_point(|&c| c <= t);
                prev = j;
                j.min(n - 1)
            })
            .collect()
    }
}

/// An orthographic depth map along a light direction (module docs).
#[derive(Debug, Clone)]
pub struct ShadowMap {
    /// Unit direction towards the light.
    pub dir: DVec3,
    eu: DVec3,
    ev: DVec3,
    u0: f64,
    v0: f64,
    /// Side of a texel, metres.
    pub texel_m: f64,
    /// `1 / texel_m` (texel lookups multiply instead of divide).
    inv_texel: f64,
    /// Texels per side; `t` holds `res * res` texels, row by row.
    pub res: usize,
    /// Largest `t = p·d` per texel; `-inf` = nothing there.
    pub t: Vec<f32>,
}

/// A [`ShadowMap`]'s frame and window ([`ShadowMap::frame`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MapFrame {
    /// First axis across the light.
    pub eu: DVec3,
    /// Second axis across the light.
    pub ev: DVec3,
    /// Unit direction towards the light (depth axis).
    pub dir: DVec3,
    /// Window origin along `eu`, metres.
    pub u0: f64,
    /// Window origin along `ev`, metres.
    pub v0: f64,
    /// Texels per metre.
    pub inv_texel: f64,
}

fn basis(d: DVec3) -> (DVec3, DVec3) {
    let a = if d.x.abs() < 0.9 { DVec3::X } else { DVec3::Y };
    let eu = d.cross(a).normalize();
    (eu, d.cross(eu))
}

impl ShadowMap {
    /// Appends the map to `w` (the disk cache's encoding of a relight scene).
    pub(crate) fn write(&self, w: &mut ByteWriter) {
        for v in [self.dir, self.eu, self.ev] {
            w.vec3(v);
        }
        for x in [self.u0, self.v0, self.texel_m, self.inv_texel] {
            w.f64(x);
        }
        w.usize(self.res);
        w.f32s(&self.t);
    }

    /// Reads what [`ShadowMap::write`] wrote.
    pub(crate) fn read(r: &mut ByteReader) -> Option<Self> {
        let (dir, eu, ev) = (r.vec3()?, r.vec3()?, r.vec3()?);
        let (u0, v0, texel_m, inv_texel) = (r.f64()?, r.f64()?, r.f64()?, r.f64()?);
        let res = r.usize()?;
        let t = r.f32s()?;
        Some(Self {
            dir,
            eu,
            ev,
            u0,
            v0,
            texel_m,
            inv_texel,
            res,
            t,
        })
    }

    /// Whether the texel array is `res`² (a decoded map is indexed by it)
    /// and the frame finite with a texel of positive size (a NaN coordinate
    /// would pass a device's range tests where `!(u >= 0)` rejects it here).
    pub(crate) fn consistent(&self) -> bool {
        self.res.checked_mul(self.res) == Some(self.t.len())
            && self.dir.is_finite()
            && self.eu.is_finite()
            && self.ev.is_finite()
            && self.u0.is_finite()
            && self.v0.is_finite()
            && self.texel_m.is_finite()
            && self.texel_m > 0.0
            && self.inv_texel.is_finite()
            && self.inv_texel > 0.0
    }

    /// Continuous texel coordinate of `p`.
    #[inline]
    fn texel(&self, p: DVec3) -> (f64, f64) {
        (
            (p.dot(self.eu) - self.u0) * self.inv_texel,
            (p.dot(self.ev) - self.v0) * self.inv_texel,
        )
    }

    /// `p` in the map's frame: `(p·e_u, p·e_v, p·d)`. Maps of the same
    /// direction share the frame ([`ShadowMap::same_frame`]), so one
    /// transform serves both lookups of [`ShadowMap::visible_lc`].
    #[inline]
    pub fn light_coords(&self, p: DVec3) -> DVec3 {
        DVec3::new(p.dot(self.eu), p.dot(self.ev), p.dot(self.dir))
    }

    /// The point at continuous texel coordinates `(u, v)` and `t = 0`.
    pub fn texel_point(&self, u: f64, v: f64) -> DVec3 {
        self.eu * (self.u0 + u * self.texel_m) + self.ev * (self.v0 + v * self.texel_m)
    }

    /// The map's frame: `(e_u, e_v, d)`, the window's origin `(u0, v0)`
    /// and `1 / texel_m` (a texel `(x, y)` holds the points with
    /// `floor((p·e_u - u0) / texel_m) = x`, likewise `y`).
    pub fn frame(&self) -> MapFrame {
        MapFrame {
            eu: self.eu,
            ev: self.ev,
            dir: self.dir,
            u0: self.u0,
            v0: self.v0,
            inv_texel: self.inv_texel,
        }
    }

    /// The rectangle `[u_min, u_max, v_min, v_max]` of light coordinates
    /// ([`ShadowMap::light_coords`]) covered by the texels that hold an
    /// occluder (their outer edges); `None` for an empty map. A point
    /// outside it looks up an empty texel or none: it is visible.
    pub fn occupied(&self) -> Option<[f64; 4]> {
        let res = self.res.max(1);
        let (mut x0, mut x1, mut y0, mut y1) = (usize::MAX, 0, usize::MAX, 0);
        for (k, t) in self.t.iter().enumerate() {
            // a NaN or -inf texel sees everything (`occluder_lc`'s callers)
            if *t == f32::NEG_INFINITY || t.is_nan() {
                continue;
            }
            let (x, y) = (k % res, k / res);
            (x0, x1, y0, y1) = (x0.min(x), x1.max(x), y0.min(y), y1.max(y));
        }
        (x0 != usize::MAX).then(|| {
            let edge = |o: f64, i: usize| o + i as f64 * self.texel_m;
            [
                edge(self.u0, x0),
                edge(self.u0, x1 + 1),
                edge(self.v0, y0),
                edge(self.v0, y1 + 1),
            ]
        })
    }

    /// Whether `other` has the same direction and frame.
    pub fn same_frame(&self, other: &ShadowMap) -> bool {
        self.dir == other.dir && self.eu == other.eu && self.ev == other.ev
    }

    /// [`ShadowMap::visible`] of a point given by [`ShadowMap::light_coords`].
    #[inline]
    pub fn visible_lc(&self, lc: DVec3, bias_m: f64) -> bool {
        let occ = self.occluder_lc(lc) as f64;
        occ.is_nan() || occ <= lc.z + bias_m
    }

    /// The occluder `t` at a point given by [`ShadowMap::light_coords`]
    /// (`-inf` outside the map or on an empty texel: then the point is
    /// visible whatever the bias).
    #[inline]
    pub fn occluder_lc(&self, lc: DVec3) -> f32 {
        let (u, v) = (
            (lc.x - self.u0) * self.inv_texel,
            (lc.y - self.v0) * self.inv_texel,
        );
        if !(u >= 0.0 && v >= 0.0) {
            return f32::NEG_INFINITY;
        }
        let (x, y) = (u as usize, v as usize);
        if x >= self.res || y >= self.res {
            return f32::NEG_INFINITY;
        }
        self.t[y * self.res + x]
    }

    /// Largest occluder `t` at `p`'s texel (`-inf` outside or empty).
    pub fn occluder_t(&self, p: DVec3) -> f32 {
        self.occluder_lc(self.light_coords(p))
    }

    /// Whether `p` sees the light given `bias_m` (module docs).
    #[inline]
    pub fn visible(&self, p: DVec3, bias_m: f64) -> bool {
        let occ = self.occluder_t(p);
        let occ = occ as f64;
        occ.is_nan() || occ <= p.dot(self.dir) + bias_m
    }

    /// The scene-scale-aware bias at `p` with normal `n` (module docs).
    pub fn bias(&self, set: &PointSet, p: DVec3, n: DVec3, m: usize, bias_scale: f64) -> f64 {
        self.bias_with_radius(set.splat_radius(p, m), n, bias_scale)
    }

    /// [`ShadowMap::bias`] with the splat radius `r(p)` already known
    /// (it does not depend on the light: callers compute it once per point).
    #[inline]
    pub fn bias_with_radius(&self, splat_radius: f64, n: DVec3, bias_scale: f64) -> f64 {
        let c = n.dot(self.dir).abs().max(1e-6);
        // guard: c >= 1e-6; tan θ = sqrt(1 - c²) / c capped at 10
        let tan = ((1.0 - c * c).max(0.0).sqrt() / c).min(10.0);
        bias_scale * self.texel_m.max(splat_radius) * (1.0 + tan)
    }

    /// Visibility of `p` in this map and in `other`, which must come from
    /// the same [`build_pair`] (same window): the texel is found once.
    /// Equal to `(self.visible(p, b), other.visible(p, b))`.
    #[inline]
    pub fn visible_pair(&self, other: &ShadowMap, p: DVec3, bias_m: f64) -> (bool, bool) {
        let (u, v) = self.texel(p);
        if !(u >= 0.0 && v >= 0.0) {
            return (true, true);
        }
        let (x, y) = (u as usize, v as usize);
        if x >= self.res || y >= self.res {
            return (true, true);
        }
        let j = y * self.res + x;
        let lim = p.dot(self.dir) + bias_m;
        let vis = |occ: f32| {
            let occ = occ as f64;
            occ.is_nan() || occ <= lim
        };
        let o = other.t.get(j).copied().unwrap_or(f32::NEG_INFINITY);
        (vis(self.t[j]), vis(o))
    }
}

/// Fills the `-inf` texels of `t` by pull-push (bilinear), in place. A map
/// without any sample stays empty.
fn fill_holes(t: &mut [f32], res: usize) {
    let lo = t
        .iter()
        .copied()
        .filter(|v| v.is_finite())
        .fold(f32::INFINITY, f32::min);
    if !lo.is_finite() {
        return;
    }
    // shift so every sample is >= 1 (pull-push treats <= 0 as a hole)
    let shifted: Vec<f32> = t
        .iter()
        .map(|v| if v.is_finite() { v - lo + 1.0 } else { 0.0 })
        .collect();
    let Ok(img) = Image::from_vec(res, res, shifted) else {
        return;
    };
    if let Ok(f) = pull_push(&img, &PullPushParams::default(), Weights::Bilinear) {
        for (o, v) in t.iter_mut().zip(f.depth.as_slice()) {
            if !o.is_finite() && DepthMap::is_valid(*v) {
                *o = v - 1.0 + lo;
            }
        }
    }
}

/// Builds the two maps of one directional light `dir` (scene `t` without
/// the object's points, scene `s+t` with them) from the same `M` samples,
/// over the window of `receivers` (module docs). `None` without receivers.
pub fn build_pair(
    dir: DVec3,
    receivers: &[DVec3],
    set: &PointSet,
    p: &IsmParams,
    map_seed: u64,
) -> Option<(ShadowMap, ShadowMap)> {
    let win = windows(&[dir], receivers).pop().flatten()?;
    build_pair_in(&win, set, p, map_seed)
}

/// The window of the receivers in the plane of a light direction: the unit
/// direction, its basis and the bounding box `[umin, umax] x [vmin, vmax]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Window {
    /// Unit direction towards the light (the maps built in this window
    /// take it as [`ShadowMap::dir`]).
    pub dir: DVec3,
    eu: DVec3,
    ev: DVec3,
    umin: f64,
    umax: f64,
    vmin: f64,
    vmax: f64,
}

impl Window {
    /// The window grown by `margin` metres on every side.
    pub fn expanded(&self, margin: f64) -> Self {
        Self {
            umin: self.umin - margin,
            umax: self.umax + margin,
            vmin: self.vmin - margin,
            vmax: self.vmax + margin,
            ..*self
        }
    }
}

/// The windows of `receivers` for every direction (`None` for a zero
/// direction or without receivers), in one pass over the receivers
/// (parallel over chunks; min and max in f32, which is exact in any order).
pub fn windows(dirs: &[DVec3], receivers: &[DVec3]) -> Vec<Option<Window>> {
    use rayon::prelude::*;
    let empty: Vec<Option<Window>> = dirs
        .iter()
        .map(|d| {
            let dir = d.normalize_or_zero();
            if dir == DVec3::ZERO || receivers.is_empty() {
                return None;
            }
            let (eu, ev) = basis(dir);
            Some(Window {
                dir,
                eu,
                ev,
                umin: f64::INFINITY,
                umax: f64::NEG_INFINITY,
                vmin: f64::INFINITY,
                vmax: f64::NEG_INFINITY,
            })
        })
        .collect();
    // Bounds in f32 over structure-of-arrays chunks (vectorised): the
    // rounding (~1e-7 relative) is far inside the one-texel margin that
    // `build_pair_in` adds around the window.
    let grow = |mut acc: Vec<Option<Window>>, chunk: &[DVec3]| {
        let xs: Vec<f32> = chunk.iter().map(|r| r.x as f32).collect();
        let ys: Vec<f32> = chunk.iter().map(|r| r.y as f32).collect();
        let zs: Vec<f32> = chunk.iter().map(|r| r.z as f32).collect();
        for w in acc.iter_mut().flatten() {
            let (a, b) = (w.eu.as_vec3(), w.ev.as_vec3());
            let (mut umin, mut umax) = (f32::INFINITY, f32::NEG_INFINITY);
            let (mut vmin, mut vmax) = (f32::INFINITY, f32::NEG_INFINITY);
            for ((x, y), z) in xs.iter().zip(&ys).zip(&zs) {
                let u = x * a.x + y * a.y + z * a.z;
                let v = x * b.x + y * b.y + z * b.z;
                umin = if u < umin { u } else { umin };
                umax = if u > umax { u } else { umax };
                vmin = if v < vmin { v } else { vmin };
                vmax = if v > vmax { v } else { vmax };
            }
            w.umin = w.umin.min(f64::from(umin));
            w.umax = w.umax.max(f64::from(umax));
            w.vmin = w.vmin.min(f64::from(vmin));
            w.vmax = w.vmax.max(f64::from(vmax));
        }
        acc
    };
    let merge = |mut a: Vec<Option<Window>>, b: Vec<Option<Window>>| {
        for (x, y) in a.iter_mut().zip(b) {
            if let (Some(x), Some(y)) = (x.as_mut(), y) {
                x.umin = x.umin.min(y.umin);
                x.umax = x.umax.max(y.umax);
                x.vmin = x.vmin.min(y.vmin);
                x.vmax = x.vmax.max(y.vmax);
            }
        }
        a
    };
    receivers
        .par_chunks(4096)
        .fold(|| empty.clone(), grow)
        .reduce(|| empty.clone(), merge)
}

/// [`build_pair`] over a window from [`windows`].
pub fn build_pair_in(
    win: &Window,
    set: &PointSet,
    p: &IsmParams,
    map_seed: u64,
) -> Option<(ShadowMap, ShadowMap)> {
    let g = Grid::new(win, p.resolution)?;
    let res = g.res;
    let mut t_only = vec![f32::NEG_INFINITY; res * res];
    let mut st = vec![f32::NEG_INFINITY; res * res];
    let m = p.points_per_map;
    g.splat(
        set,
        &set.draw(m, map_seed),
        m,
        1.0,
        p.max_splat_texels,
        |is_obj, span, tq| {
            for t in &mut st[span.clone()] {
                *t = t.max(tq);
            }
            if !is_obj {
                for t in &mut t_only[span] {
                    *t = t.max(tq);
                }
            }
        },
    );
    fill_holes(&mut t_only, res);
    fill_holes(&mut st, res);
    Some((g.map(t_only), g.map(st)))
}

/// One map of every element of `set` drawn (`m` samples, stratified by
/// area x importance) over `win`, splats of `radius_scale x r(p)` (at least
/// the pixel spacing, at most `max_splat_texels`). With `fill`, holes are
/// filled by pull-push, as in [`build_pair_in`]; without, texels no splat
/// covers stay empty (`-inf`): the map of a lone object, whose outside must
/// stay unoccluded (`radius_scale` ~2 closes the gaps between splats
/// instead). `None` for an empty window.
pub fn build_single_in(
    win: &Window,
    set: &PointSet,
    p: &IsmParams,
    m: usize,
    radius_scale: f64,
    fill: bool,
    map_seed: u64,
) -> Option<ShadowMap> {
    let g = Grid::new(win, p.resolution)?;
    let res = g.res;
    let mut t = vec![f32::NEG_INFINITY; res * res];
    g.splat(
        set,
        &set.draw(m, map_seed),
        m,
        radius_scale,
        p.max_splat_texels,
        |_, span, tq| {
            for t in &mut t[span] {
                *t = t.max(tq);
            }
        },
    );
    if fill {
        fill_holes(&mut t, res);
    }
    Some(g.map(t))
}

/// A paraboloid depth map of the hemisphere around a point light (the ISM
/// paper's maps for VPLs at finite positions: the bounce VPLs). A point
/// `p` at distance `d` in direction `w` from the light's centre `q`, with
/// `z = w·n > 0` (the light's normal `n`), lands at
/// `(w·e_1, w·e_2) / (1 + z)` in the unit disc; the map keeps the nearest
/// occluder distance per texel (stored as `-d`, so that the largest value
/// wins as in [`ShadowMap`]). No pull-push: directions without samples
/// (the sky) must stay open; splats twice the ISM radius close the gaps.
#[derive(Debug, Clone)]
pub struct ParaboloidMap {
    /// Position `q` of the light (camera frame, metres).
    pub centre: DVec3,
    e1: DVec3,
    e2: DVec3,
    n: DVec3,
    /// Texels per side (at least 2) of the square map of the unit disc.
    pub res: usize,
    t: Vec<f32>,
}

/// A set of samples splatted into paraboloid maps: the elements drawn and
/// their splat radius scale.
#[derive(Debug, Clone, Copy)]
pub struct ParaboloidSamples<'a> {
    /// The elements the samples are drawn from.
    pub set: &'a PointSet,
    /// Samples drawn per map.
    pub m: usize,
    /// Multiplies the ISM radius `r(p)`.
    pub radius_scale: f64,
}

impl ParaboloidMap {
    /// Texel coordinates, distance and `z` of `p`; `None` behind the light
    /// (`z <= 0`) or at its centre.
    #[inline]
    fn project(&self, p: DVec3) -> Option<(f64, f64, f64, f64)> {
        let v = p - self.centre;
        let d = v.length();
        if d.is_nan() || d <= 1e-9 {
            return None;
        }
        // guard: d > 1e-9
        let w = v / d;
        let z = w.dot(self.n);
        if z <= 0.0 {
            return None;
        }
        // guard: 1 + z > 1
        let s = 0.5 * self.res as f64 / (1.0 + z);
        let h = 0.5 * self.res as f64;
        Some((w.dot(self.e1) * s + h, w.dot(self.e2) * s + h, d, z))
    }

    /// Builds the map of the light at `centre` facing `normal` (unit) from
    /// the given sample sets, each drawn with its own seed.
    pub fn build(
        centre: DVec3,
        normal: DVec3,
        samples: &[ParaboloidSamples],
        res: usize,
        seed: u64,
    ) -> Self {
        let n = normal.normalize_or_zero();
        let (e1, e2) = if n == DVec3::ZERO {
            (DVec3::X, DVec3::Y)
        } else {
            basis(n)
        };
        let res = res.max(2);
        let mut map = Self {
            centre,
            e1,
            e2,
            n,
            res,
            t: vec![f32::NEG_INFINITY; res * res],
        };
        if n == DVec3::ZERO {
            return map;
        }
        let half_res = 0.5 * res as f64;
        for (si, s) in samples.iter().enumerate() {
            let base = s.radius_scale * s.set.base_radius(s.m);
            for i in s.set.draw(s.m, seed.wrapping_add(si as u64 * 0x9E37)) {
                let Some(e) = s.set.elems.get(i) else {
                    continue;
                };
                let Some((u, v, d, z)) = map.project(e.pos) else {
                    continue;
                };
                let r_m = (base * e.inv_sqrt_importance).max(e.min_radius);
                if d <= r_m {
                    continue; // the light's own surface element
                }
                // angular radius r/d, and du/dθ = 1 / (1 + z) in texels
                let r = (r_m / d / (1.0 + z) * half_res).clamp(0.5, 4.0);
                let tq = -d as f32;
                disc_spans(u, v, r, res, |span| {
                    for t in &mut map.t[span] {
                        *t = t.max(tq);
                    }
                });
            }
        }
        map
    }

    /// Whether `p` (normal `n_p`, own splat radius `r_p`) sees the light:
    /// no occluder nearer than its distance minus a bias of
    /// `bias_scale * max(texel, r_p) * (1 + min(tan θ, 10))` (the texel's
    /// side at `p`'s distance, `θ` between `n_p` and the direction to the
    /// light). Points behind the light see it (their cosine there is 0).
    #[inline]
    pub fn visible(&self, p: DVec3, n_p: DVec3, r_p: f64, bias_scale: f64) -> bool {
        let Some((u, v, d, z)) = self.project(p) else {
            return true;
        };
        if !(u >= 0.0 && v >= 0.0) {
            return true;
        }
        let (x, y) = (u as usize, v as usize);
        if x >= self.res || y >= self.res {
            return true;
        }
        let occ = self.t[y * self.res + x];
        if occ == f32::NEG_INFINITY {
            return true;
        }
        // a texel spans (1 + z) 2 / res radians there
        let texel_m = d * (1.0 + z) * 2.0 / self.res as f64;
        // guard: d > 1e-9 (project)
        let c = (n_p.dot(self.centre - p) / d).abs().max(1e-6);
        let tan = ((1.0 - c * c).max(0.0).sqrt() / c).min(10.0);
        let bias = bias_scale * texel_m.max(r_p) * (1.0 + tan);
        -(occ as f64) + bias >= d
    }
}

/// The texels of a `res x res` map whose centres `(x + 0.5, y + 0.5)` lie
/// in the disc of radius `r` (texels) around `(u, v)`, row by row, as spans
/// of texel indices.
#[inline]
fn disc_spans(u: f64, v: f64, r: f64, res: usize, mut put: impl FnMut(std::ops::Range<usize>)) {
    if u + r < 0.0 || v + r < 0.0 || u - r > res as f64 || v - r > res as f64 {
        return;
    }
    // floor and ceiling clamped at 0 (casts: no libm call without SSE4.1)
    let floor0 = |x: f64| if x > 0.0 { x as usize } else { 0 };
    let ceil0 = |x: f64| {
        if x > 0.0 {
            let i = x as usize;
            if (i as f64) < x { i + 1 } else { i }
        } else {
            0
        }
    };
    let (x0, x1) = (floor0(u - r), ceil0(u + r).min(res));
    let (y0, y1) = (floor0(v - r), ceil0(v + r).min(res));
    for y in y0..y1 {
        let dy = y as f64 + 0.5 - v;
        let rem = r * r - dy * dy;
        if rem < 0.0 {
            continue;
        }
        let half = rem.sqrt();
        let xa = ceil0(u - half - 0.5).max(x0);
        // floor(b) + 1 clamped at 0: 0 for any b < 0
        let b = u + half - 0.5;
        let xb = (if b >= 0.0 { floor0(b) + 1 } else { 0 }).min(x1);
        if xa < xb {
            put(y * res + xa..y * res + xb);
        }
    }
}

/// The texel grid of a map over a window: one texel of margin each side.
pub(crate) struct Grid {
    dir: DVec3,
    eu: DVec3,
    ev: DVec3,
    u0: f64,
    v0: f64,
    texel_m: f64,
    inv_texel: f64,
    pub(crate) res: usize,
}

impl Grid {
    /// The grid of `resolution`² texels over `win`; `None` for an empty window.
    pub(crate) fn new(win: &Window, resolution: usize) -> Option<Self> {
        let Window {
            dir,
            eu,
            ev,
            umin,
            umax,
            vmin,
            vmax,
        } = *win;
        if !(umin <= umax && vmin <= vmax) {
            return None;
        }
        let res = resolution.max(1);
        let extent = (umax - umin).max(vmax - vmin).max(1e-6);
        let texel_m = extent / (res as f64 - 2.0).max(1.0);
        Some(Self {
            dir,
            eu,
            ev,
            u0: umin - texel_m,
            v0: vmin - texel_m,
            texel_m,
            // guard: texel_m = extent / (res - 2) with extent >= 1e-6 > 0
            inv_texel: 1.0 / texel_m,
            res,
        })
    }

    /// The frame in f32: per axis (`u`, `v`, then `t`) the unit vector, the
    /// offset and the scale, so that a coordinate is `(p·e - offset) · scale`
    /// (`t`: offset 0, scale 1).
    pub(crate) fn frame_f32(&self) -> [(glam::Vec3, f32, f32); 3] {
        let inv = self.inv_texel as f32;
        [
            (self.eu.as_vec3(), self.u0 as f32, inv),
            (self.ev.as_vec3(), self.v0 as f32, inv),
            (self.dir.as_vec3(), 0.0, 1.0),
        ]
    }

    /// The map of the texels `t` (`res`², row by row) on this grid.
    pub(crate) fn map(&self, t: Vec<f32>) -> ShadowMap {
        ShadowMap {
            dir: self.dir,
            eu: self.eu,
            ev: self.ev,
            u0: self.u0,
            v0: self.v0,
            texel_m: self.texel_m,
            inv_texel: self.inv_texel,
            res: self.res,
            t,
        }
    }

    /// Splats the elements `idx` of `set` (drawn `m` at a time) as discs of
    /// radius `scale x r(p)` (floored at the pixel spacing, in texels
    /// clamped to `[0.5, rmax]`): `put(is_object, texels, t)` gets each
    /// disc row by row, as a span of texel indices.
    fn splat(
        &self,
        set: &PointSet,
        idx: &[usize],
        m: usize,
        scale: f64,
        rmax: f64,
        mut put: impl FnMut(bool, std::ops::Range<usize>, f32),
    ) {
        let (res, dir) = (self.res, self.dir);
        let base = scale * set.base_radius(m);
        for &i in idx {
            let Some(e) = set.elems.get(i) else {
                continue;
            };
            let q = e.pos;
            let (u, v) = (
                (q.dot(self.eu) - self.u0) * self.inv_texel,
                (q.dot(self.ev) - self.v0) * self.inv_texel,
            );
            let r = ((base * e.inv_sqrt_importance).max(e.min_radius) * self.inv_texel)
                .min(rmax)
                .max(0.5);
            let tq = q.dot(dir) as f32;
            disc_spans(u, v, r, res, |span| put(e.object, span, tq));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cam(w: usize, h: usize) -> Intrinsics {
        crate::sim::synthetic::kinect_like_intrinsics(w, h)
    }

    /// A decoded map whose frame is not finite (or whose texel has no
    /// size) is inconsistent: the cache rebuilds the scene instead.
    #[test]
    fn a_decoded_map_with_a_bad_frame_is_inconsistent() {
        let good = ShadowMap {
            dir: DVec3::Z,
            eu: DVec3::X,
            ev: DVec3::Y,
            u0: -1.0,
            v0: -1.0,
            texel_m: 0.5,
            inv_texel: 2.0,
            res: 2,
            t: vec![f32::NEG_INFINITY, 1.0, 2.0, 3.0],
        };
        let mut w = depthgraph_graph::bytes::ByteWriter::default();
        good.write(&mut w);
        let bytes = w.0;
        let read = |b: &[u8]| {
            ShadowMap::read(&mut depthgraph_graph::bytes::ByteReader::new(b))
                .expect("a whole map")
                .consistent()
        };
        assert!(read(&bytes));
        // u0 (after three vectors), then inv_texel, made NaN or 0
        for (at, bad) in [
            (72, f64::NAN),
            (96, f64::NAN),
            (96, 0.0),
            (88, f64::INFINITY),
        ] {
            let mut b = bytes.clone();
            b[at..at + 8].copy_from_slice(&bad.to_le_bytes());
            assert!(!read(&b), "byte {at} = {bad}");
        }
    }

    /// A floor (y = 0.4 m, seen from above at an angle: depth rows) and a
    /// 0.4 m x 0.8 m slab 0.2 m above it: under an overhead light the slab's points
    /// shadow exactly the floor points below it in the `s+t` map, nothing in
    /// the `t` map.
    #[test]
    fn a_slab_shadows_the_floor_below_it_only_with_the_object() {
        let (w, h) = (160, 120);
        let k = cam(w, h);
        let (_, floor, slab, _) = crate::test_support::relight::floor_and_slab(w, h);
        assert!(slab.hole_count() < w * h);
        let centre = DVec3::new(0.0, 0.2, 2.0);
        let set = PointSet::new(&[(&floor, false), (&slab, true)], &k, &[centre], 0.05);
        let recv: Vec<(DVec3, f32)> = (0..h)
            .flat_map(|y| (0..w).map(move |x| (x, y)))
            .filter(|&(x, y)| DepthMap::is_valid(*floor.get(x, y)))
            .map(|(x, y)| {
                (
                    k.unproject(x as f64 + 0.5, y as f64 + 0.5, *floor.get(x, y) as f64),
                    0.0,
                )
            })
            .collect();
        let pts: Vec<DVec3> = recv.iter().map(|r| r.0).collect();
        let p = IsmParams {
            points_per_map: 20000,
            resolution: 128,
            ..Default::default()
        };
        let up = DVec3::NEG_Y;
        let (mt, mst) = build_pair(up, &pts, &set, &p, 9).unwrap();
        let (mut wrong, mut shadowed) = (0, 0);
        for q in &pts {
            let bias = mst.bias(&set, *q, up, p.points_per_map, p.bias_scale);
            assert!(mt.visible(*q, bias), "t map shadows the floor at {q}");
            let under = q.x.abs() <= 0.2 && (1.6..=2.4).contains(&q.z);
            // the slab's samples are pixel rows ~0.15 m apart in z: their
            // (round) splats blur its outline by about that much, ~2 texels
            let near_edge = (q.x.abs() - 0.2).abs() < 0.15
                || (q.z - 1.6).abs() < 0.15
                || (q.z - 2.4).abs() < 0.15;
            let vis = mst.visible(*q, bias);
            if under && !vis {
                shadowed += 1;
            }
            if !near_edge && vis == under {
                wrong += 1;
            }
        }
        let n_under = pts
            .iter()
            .filter(|q| q.x.abs() <= 0.2 && (1.6..=2.4).contains(&q.z))
            .count();
        assert!(
            shadowed > 50,
            "{shadowed} of {n_under}, wrong {wrong}, texel {}",
            mst.texel_m
        );
        assert_eq!(wrong, 0);
    }

    /// A wall 2 m from the camera, a point light 1 m from it facing it:
    /// points behind the wall are in its shadow, points before it, on it,
    /// beside it or behind the light are not.
    #[test]
    fn a_paraboloid_map_sees_the_wall_between_a_point_light_and_a_receiver() {
        let (w, h) = (80, 60);
        let k = cam(w, h);
        let wall = Image::filled(w, h, 2.0f32);
        let set = PointSet::new(&[(&wall, false)], &k, &[], 0.05);
        let light = DVec3::new(0.0, 0.0, 1.0);
        let samples = [ParaboloidSamples {
            set: &set,
            m: 4000,
            radius_scale: 2.0,
        }];
        let map = ParaboloidMap::build(light, DVec3::Z, &samples, 32, 5);
        let r = 2.0 * set.base_radius(4000);
        let n = DVec3::NEG_Z;
        // behind the wall, within its extent seen from the light
        for q in [
            DVec3::new(0.0, 0.0, 3.0),
            DVec3::new(0.3, -0.2, 2.5),
            DVec3::new(-0.5, 0.3, 2.6),
        ] {
            assert!(!map.visible(q, n, r, 1.5), "{q} is behind the wall");
        }
        // before it, on it, beside it (beyond its edge), behind the light
        let half_w = 2.0 * (w as f64 / 2.0) / k.fx;
        for q in [
            DVec3::new(0.0, 0.0, 1.5),
            DVec3::new(0.2, 0.1, 1.9),
            k.unproject(40.5, 30.5, 2.0),
            k.unproject(10.5, 50.5, 2.0),
            DVec3::new(half_w * 3.0, 0.0, 2.2),
            DVec3::new(0.0, 0.0, 0.5),
        ] {
            assert!(map.visible(q, n, r, 1.5), "{q} sees the light");
        }
        // a light without a direction sees everything
        let none = ParaboloidMap::build(light, DVec3::ZERO, &samples, 32, 5);
        assert!(none.visible(DVec3::new(0.0, 0.0, 3.0), n, r, 1.5));
    }

    #[test]
    fn importance_prefers_points_near_the_object() {
        let k = cam(40, 30);
        let d = Image::filled(40, 30, 2.0f32);
        let c = k.unproject(5.5, 5.5, 2.0);
        let set = PointSet::new(&[(&d, false)], &k, &[c], 0.01);
        let idx = set.draw(4000, 1);
        let near = idx
            .iter()
            .filter(|&&i| (set.positions[i] - c).length() < 0.3)
            .count();
        // the disc of radius 0.3 m covers well under 10 % of the 2.3 m x 1.7 m wall
        assert!(near > 1200, "{near}");
        assert!(set.splat_radius(c, 4000) < set.splat_radius(k.unproject(39.5, 29.5, 2.0), 4000));
        // no centres: uniform importance, finite radii; empty sets draw nothing
        let flat = PointSet::new(&[(&d, false)], &k, &[], 0.01);
        assert!(flat.splat_radius(c, 10).is_finite());
        let none = PointSet::new(
            &[(&Image::filled(4, 3, 0.0f32), false)],
            &cam(4, 3),
            &[c],
            0.01,
        );
        assert!(none.draw(10, 1).is_empty());
    }
}
