//! The shading kit both relighting schemes and the reference share
//! (3d-editing §IV.A): the parameters and inputs of `Relight`, target
//! surfaces and pixel areas, the cone test, the object's radiance and its
//! bounce VPLs, the scene's bounce VPLs, the differential composite of
//! eq. 5 and the target albedo estimate.

use depthgraph_graph::node_params;
use depthgraph_graph::prelude::*;
use depthgraph_graph::value::Rgb;
use glam::DVec3;
use rayon::prelude::*;

use crate::kit::checks::fits_intrinsics;
use crate::kit::color::luminance_clamped;
use crate::relight::ism::pixel_area;
use crate::relight::vpl::Vpl;

node_params! {
    /// Parameters of `Relight`.
    pub struct RelightParams {
        /// Texels per side of each imperfect shadow map.
        pub ism_resolution: usize = 96usize, ParamKind::Int { min: 4, max: 2048 };
        /// Point samples splatted into each shadow map.
        pub ism_points: usize = 8192usize, ParamKind::Int { min: 16, max: 1 << 22 };
        /// Visibility bias in units of max(texel, splat radius), scaled by the slope.
        pub bias_scale: f64 = 1.5, ParamKind::Float { min: 0.0, max: 100.0 };
        /// Floor of the distance of eq. 6, metres.
        pub min_distance_m: f64 = 0.05, ParamKind::Float { min: 1e-6, max: 1e3 };
        /// Object pixels used as bounce VPLs (0 = no bounce).
        pub bounce_vpls: usize = 256usize, ParamKind::Int { min: 0, max: 65536 };
        /// Scene pixels used as secondary VPLs that light the object (one bounce; 0 = none).
        pub scene_vpls: usize = 256usize, ParamKind::Int { min: 0, max: 65536 };
        /// Shadow the bounce VPLs with paraboloid ISMs (off: the bounce is unshadowed).
        pub bounce_shadows: bool = false, ParamKind::Bool;
        /// Scene samples splatted into each bounce VPL's paraboloid map.
        pub bounce_ism_points: usize = 1024usize, ParamKind::Int { min: 16, max: 1 << 20 };
        /// Texels per side of each bounce VPL's paraboloid map.
        pub bounce_ism_resolution: usize = 32usize, ParamKind::Int { min: 4, max: 1024 };
        /// Clamp of the bounce's 1/r², metres (bias: too dark closer than this).
        pub clamp_distance_m: f64 = 0.05, ParamKind::Float { min: 1e-4, max: 10.0 };
        /// The bounce reaches this many object radii from its centre.
        pub bounce_radius_rel: f64 = 3.0, ParamKind::Float { min: 0.0, max: 100.0 };
        /// Below this fraction of the total VPL irradiance the albedo is unknown (taken as 0).
        pub min_shading_rel: f64 = 1e-3, ParamKind::Float { min: 1e-9, max: 1.0 };
        /// Seed of the shadow maps' point subsets.
        pub seed: u64 = 1u64, ParamKind::Int { min: 0, max: 1 << 53 };
        /// Point-sample density of the paired shadow maps: "near_object" (eq. 6) or "uniform" (by area).
        pub importance: Importance = Importance::NearObject, ParamKind::Choice(Importance::NAMES);
        /// "scene_cached": scene maps kept per scene, object maps per run (fast moves);
        /// "paired": scene+object maps with eq. 6 rebuilt every run (the paper's scheme);
        /// "raycast": exact shadow rays through the meshes (the reference; slow).
        pub visibility: Visibility = Visibility::SceneCached, ParamKind::Choice(Visibility::NAMES);
        /// Texels per side of the object's own maps (scene_cached; the maps of dim groups of VPLs, under 1/64 of the power, at half).
        pub object_ism_resolution: usize = 64usize, ParamKind::Int { min: 4, max: 2048 };
        /// Close the object's unseen back (its front mirrored about the silhouette plane) for its shadows.
        pub close_back: bool = true, ParamKind::Bool;
        /// Keep the scene's bounce in the object's shadow: remove only the light the object blocks, direct and bounced.
        pub fill_light: bool = true, ParamKind::Bool;
        /// Where a scene shadow map's occluder lies within its bias of the object (a wall a few centimetres away), march the photo's depth instead (scene_cached).
        pub contact: bool = true, ParamKind::Bool;
        /// The object's capture irradiance is at least this fraction of the VPLs' total: a face the capture map barely lit is not brightened without bound.
        pub min_capture_rel: f64 = 0.02, ParamKind::Float { min: 1e-9, max: 1.0 };
        /// Pixels between the points where the smooth terms are evaluated (scene_cached): the object's irradiance and the bounces every twice this first, every this where those disagree, a pixel between blending the points on its surface when they agree within 5 % (the object's only between all of them), else evaluated itself; the fill light every four times this, then twice, blended whatever its values. 1 = every pixel.
        pub lattice_step: usize = 2usize, ParamKind::Int { min: 1, max: 16 };
        /// Extend the plane the object stands on beyond the photo's frame: it bounces light onto the object.
        pub extend_support: bool = true, ParamKind::Bool;
        /// How far the support plane is extended, in object radii from the object's foot.
        pub support_radius_rel: f64 = 15.0, ParamKind::Float { min: 1.0, max: 1000.0 };
    }
}

depthgraph_graph::param_choice! {
    /// Point-sample density of the paired shadow maps (the `importance` parameter).
    pub enum Importance {
        /// Denser near the pasted object (eq. 6).
        NearObject = "near_object",
        /// By area only.
        Uniform = "uniform",
    }
}

depthgraph_graph::param_choice! {
    /// How visibility is computed (the `visibility` parameter).
    pub enum Visibility {
        /// Scene maps kept per scene, object maps per run (fast moves).
        SceneCached = "scene_cached",
        /// Scene+object maps with eq. 6 rebuilt every run (the paper's scheme).
        Paired = "paired",
        /// Exact shadow rays through the meshes (the reference; slow).
        Raycast = "raycast",
    }
}

/// The inputs of [`relight`](crate::relight::paired::relight), all `k.width x k.height`.
#[derive(Debug, Clone, Copy)]
pub struct RelightInputs<'a> {
    /// The target photo `P`, linear RGB.
    pub photo: &'a ColorImage,
    /// The target's depth in metres (0 = no measurement).
    pub depth: &'a DepthMap,
    /// Target normals; `None` (or zero normals) = estimated from the depth.
    pub normals: Option<&'a NormalMap>,
    /// Target albedo; `None` = estimated as photo / shading.
    pub albedo: Option<&'a ColorImage>,
    /// The pasted object's colour in the target view, linear RGB.
    pub pasted_color: &'a ColorImage,
    /// The pasted object's depth in the target view, metres (0 where the
    /// object is absent).
    pub pasted_depth: &'a DepthMap,
    /// The composite alpha `α` of eq. 5 (after the depth test); clamped to
    /// `[0, 1]`, NaN and pasted-depth holes count as 0.
    pub alpha: &'a Mask,
    /// Intrinsics of the target; every image has their size.
    pub k: &'a Intrinsics,
    /// The VPLs of the map the object was captured under; `None` = the
    /// target's (module docs of [`crate::relight::paired`]).
    pub capture_vpls: Option<&'a [Vpl]>,
}

/// The scene's part of [`RelightInputs`]: what the scene-cached path
/// ([`crate::relight::scene_cached`]) keeps while the object moves.
#[derive(Debug, Clone, Copy)]
pub struct SceneInputs<'a> {
    /// The target photo `P`, linear RGB.
    pub photo: &'a ColorImage,
    /// The target's depth in metres (0 = no measurement).
    pub depth: &'a DepthMap,
    /// Target normals; `None` (or zero normals) = estimated from the depth.
    pub normals: Option<&'a NormalMap>,
    /// Target albedo; `None` = estimated as photo / shading.
    pub albedo: Option<&'a ColorImage>,
    /// Intrinsics of the target; every image has their size.
    pub k: &'a Intrinsics,
}

impl SceneInputs<'_> {
    /// Sane intrinsics, and every image at their size.
    pub(crate) fn check(&self) -> Result<(), NodeError> {
        let k = self.k;
        fits_intrinsics("intrinsics", k, "photo", self.photo.dims())?;
        fits_intrinsics("intrinsics", k, "depth", self.depth.dims())?;
        if let Some(n) = self.normals {
            fits_intrinsics("intrinsics", k, "normals", n.dims())?;
        }
        if let Some(a) = self.albedo {
            fits_intrinsics("intrinsics", k, "albedo", a.dims())?;
        }
        Ok(())
    }
}

impl<'a> RelightInputs<'a> {
    /// The scene's part.
    pub fn scene(&self) -> SceneInputs<'a> {
        SceneInputs {
            photo: self.photo,
            depth: self.depth,
            normals: self.normals,
            albedo: self.albedo,
            k: self.k,
        }
    }

    /// [`SceneInputs::check`], and the object's images at the same size.
    pub(crate) fn check(&self) -> Result<(), NodeError> {
        self.scene().check()?;
        fits_intrinsics(
            "intrinsics",
            self.k,
            "pasted_color",
            self.pasted_color.dims(),
        )?;
        fits_intrinsics(
            "intrinsics",
            self.k,
            "pasted_depth",
            self.pasted_depth.dims(),
        )?;
        fits_intrinsics("intrinsics", self.k, "alpha", self.alpha.dims())
    }

    /// The object's mirrored back ([`crate::relight::closure`]) when
    /// `close_back` is on.
    pub(crate) fn back_depth(&self, p: &RelightParams) -> Option<DepthMap> {
        p.close_back
            .then(|| crate::relight::closure::back_depth(self.pasted_depth, self.k))
    }

    /// The object's closed volume: between its pasted depth and `back`
    /// (the front alone without one), inside the ball `(c, radius)` that
    /// holds its points, widened by 1 % and 1 mm for rounding.
    pub(crate) fn volume<'b>(
        &'b self,
        back: Option<&'b DepthMap>,
        c: DVec3,
        radius: f64,
    ) -> crate::relight::closure::ObjectVolume<'b> {
        crate::relight::closure::ObjectVolume::new(
            self.k,
            self.pasted_depth,
            back.unwrap_or(self.pasted_depth),
            c,
            radius * 1.01 + 1e-3,
        )
    }

    /// The object's surface at pixel `i` (a valid pasted depth): its
    /// unprojected centre, and its normal from the pasted depth, else
    /// facing the camera.
    pub(crate) fn object_surface(&self, i: usize) -> Surf {
        let (k, w) = (self.k, self.k.width);
        let (x, y) = (i % w, i / w);
        let z = *self.pasted_depth.get(x, y) as f64;
        let pos = k.unproject(x as f64 + 0.5, y as f64 + 0.5, z);
        let n = depth_normal(self.pasted_depth, k, x, y).unwrap_or(-pos.normalize());
        Surf { pos, n }
    }
}

/// Result of [`relight`](crate::relight::paired::relight).
#[derive(Debug, Clone, PartialEq)]
pub struct Relit {
    /// `I_m` (eq. 5).
    pub color: ColorImage,
    /// 1 where rendered, 0 where the photo was kept.
    pub region: Mask,
    /// `I_{s+t} - I_t` on the target surface (0 outside the region).
    pub difference: ColorImage,
}

/// Unit normal of a depth pixel from its neighbours on the same surface,
/// facing the camera; `None` without two neighbours.
///
/// Along each image axis the tangent is the forward or the backward
/// difference, whichever side is flatter (the smaller second difference
/// over two neighbours): on a crease (a box's edge) each pixel takes its
/// own face's tangent instead of one spanning the edge. A side without two
/// neighbours on the surface is used only when the other has none.
pub(crate) fn depth_normal(depth: &DepthMap, k: &Intrinsics, x: usize, y: usize) -> Option<DVec3> {
    let (w, h) = depth.dims();
    let z = *depth.get(x, y) as f64;
    let at = |xx: usize, yy: usize| {
        k.unproject(xx as f64 + 0.5, yy as f64 + 0.5, *depth.get(xx, yy) as f64)
    };
    let same = |xx: usize, yy: usize| {
        let zz = *depth.get(xx, yy) as f64;
        // guard: both > 0 when valid
        DepthMap::is_valid(zz as f32) && zz.max(z) / zz.min(z) <= 1.1
    };
    let p = at(x, y);
    // the tangent along one axis: `step(i)` is the pixel `i` steps away
    // (negative: backwards), `None` off the image or off the surface
    let tangent = |step: &dyn Fn(isize) -> Option<(usize, usize)>| -> Option<DVec3> {
        let on = |i: isize| {
            step(i)
                .filter(|&(xx, yy)| same(xx, yy))
                .map(|(xx, yy)| at(xx, yy))
        };
        let (f1, b1) = (on(1), on(-1));
        match (f1, b1) {
            (Some(f), Some(b)) => {
                // second differences; a side without a second neighbour
                // counts as bent (infinite)
                let bend = |far: Option<DVec3>, near: DVec3| {
                    far.map_or(f64::INFINITY, |q| (q - 2.0 * near + p).length())
                };
                let (bf, bb) = (bend(on(2), f), bend(on(-2), b));
                Some(if bb < bf { p - b } else { f - p })
            }
            (Some(f), None) => Some(f - p),
            (None, Some(b)) => Some(p - b),
            (None, None) => None,
        }
    };
    let du = tangent(&|i| {
        let xx = x as isize + i;
        (xx >= 0 && (xx as usize) < w).then_some((xx as usize, y))
    })?;
    let dv = tangent(&|i| {
        let yy = y as isize + i;
        (yy >= 0 && (yy as usize) < h).then_some((x, yy as usize))
    })?;
    let n = du.cross(dv).normalize_or_zero();
    if n == DVec3::ZERO {
        return None;
    }
    Some(if n.dot(p) > 0.0 { -n } else { n })
}

/// The directions `d` whose ray `x + t d` (`t >= 0`) passes within `reach`
/// of `c`, as a cone `d·u >= cos_min` around the unit `u` towards `c`; every
/// direction (`cos_min = -1`) when `x` is within `reach` of `c`.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Cone {
    pub(crate) u: DVec3,
    pub(crate) cos_min: f64,
    /// `sin` of the cone's half angle (`reach / d`); 1 for every direction.
    pub(crate) sin: f64,
}

impl Cone {
    pub(crate) fn new(x: DVec3, c: DVec3, reach: f64) -> Self {
        let v = c - x;
        let d = v.length();
        if d <= reach {
            return Self {
                u: DVec3::ZERO,
                cos_min: -1.0,
                sin: 1.0,
            };
        }
        // guard: d > reach >= 0. The ray's closest approach to c is
        // d sin θ (θ = angle between d and v, when cos θ > 0), so it passes
        // within reach iff cos θ >= sqrt(1 - (reach / d)²).
        let s = reach / d;
        Self {
            u: v / d,
            cos_min: (1.0 - s * s).max(0.0).sqrt(),
            sin: s,
        }
    }

    #[inline]
    pub(crate) fn contains(&self, d: DVec3) -> bool {
        self.cos_min <= -1.0 || d.dot(self.u) >= self.cos_min
    }
}

/// A surface sample: a point and its normal.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Surf {
    /// Camera space, metres.
    pub pos: DVec3,
    /// Unit normal.
    pub n: DVec3,
}

/// The target's surfaces, per pixel: unprojected centre and unit normal
/// (the given one when finite and non-zero, else from the depth); `None`
/// for a hole or a pixel without a normal.
pub(crate) fn target_surfaces(
    depth: &DepthMap,
    normals: Option<&NormalMap>,
    k: &Intrinsics,
) -> Vec<Option<Surf>> {
    let w = k.width;
    (0..w * k.height)
        .into_par_iter()
        .with_min_len(4096)
        .map(|i| {
            let (x, y) = (i % w, i / w);
            let z = *depth.get(x, y);
            if !DepthMap::is_valid(z) {
                return None;
            }
            let pos = k.unproject(x as f64 + 0.5, y as f64 + 0.5, z as f64);
            let given = normals
                .map(|n| DVec3::from_array(n.get(x, y).map(|c| c as f64)))
                .filter(|n| n.is_finite() && n.length_squared() > 0.5);
            let n = given
                .map(|n| n.normalize())
                .or_else(|| depth_normal(depth, k, x, y))?;
            Some(Surf { pos, n })
        })
        .collect()
}

/// Surface area (m²) of every valid pixel of `depth` ([`pixel_area`]), 0
/// for holes.
pub(crate) fn pixel_areas(depth: &DepthMap, k: &Intrinsics) -> Vec<f64> {
    let w = k.width;
    (0..w * k.height)
        .into_par_iter()
        .with_min_len(4096)
        .map(|i| {
            let (x, y) = (i % w, i / w);
            if DepthMap::is_valid(*depth.get(x, y)) {
                pixel_area(depth, k, x, y).0
            } else {
                0.0
            }
        })
        .collect()
}

/// The alpha of eq. 5: clamped to [0, 1], 0 where it is NaN or the pasted
/// depth is a hole.
pub(crate) fn clean_alpha(alpha: &Mask, pasted_depth: &DepthMap) -> Vec<f32> {
    alpha
        .as_slice()
        .iter()
        .zip(pasted_depth.as_slice())
        .map(|(a, z)| {
            if a.is_nan() || !DepthMap::is_valid(*z) {
                0.0
            } else {
                a.clamp(0.0, 1.0)
            }
        })
        .collect()
}

/// The VPLs with energy, their unit directions and `E_ref = Σ_k lum(Φ_k)`.
pub(crate) fn lit_vpls(vpls: &[Vpl]) -> (Vec<Vpl>, Vec<DVec3>, f64) {
    let vpls: Vec<Vpl> = vpls
        .iter()
        .copied()
        .filter(|v| luminance_clamped(v.power) > 0.0)
        .collect();
    let e_ref: f64 = vpls.iter().map(|v| luminance_clamped(v.power)).sum();
    let dirs = vpls
        .iter()
        .map(|v| DVec3::from_array(v.direction.map(|c| c as f64)).normalize_or_zero())
        .collect();
    (vpls, dirs, e_ref)
}

/// Whether nothing was pasted: no valid pasted depth. An object hidden
/// whole by the scene (alpha 0 everywhere after the depth test) is
/// pasted: it still casts its shadow and blocks light.
pub(crate) fn nothing_pasted(pasted_depth: &DepthMap) -> bool {
    pasted_depth
        .as_slice()
        .iter()
        .all(|z| !DepthMap::is_valid(*z))
}

/// The irradiance scale of the capture side's floor (`min_capture_rel`
/// times it): the capture VPLs' own total when they are given (the floor
/// follows the map the object was captured under, whatever its brightness
/// against the target's), else the target's `e_ref`. Capture VPLs that
/// carry no light are an error naming the port: the object's capture
/// lighting would be nothing, and every face would be brightened to the
/// floor's bound.
pub(crate) fn capture_ref(capture: Option<&[Vpl]>, e_ref: f64) -> Result<f64, NodeError> {
    let Some(cv) = capture else {
        return Ok(e_ref);
    };
    let e_cap: f64 = cv.iter().map(|v| luminance_clamped(v.power)).sum();
    if e_cap > 0.0 && e_cap.is_finite() {
        Ok(e_cap)
    } else {
        Err(NodeError::input(
            "capture_vpls",
            "carry no light (a black map?): the object's capture lighting would be nothing; \
             leave capture_vpls unconnected to take the target's VPLs",
        ))
    }
}

/// Centre (mean) of the object's points and their largest distance from
/// it (at least 1 mm).
pub(crate) fn centre_and_radius(pts: &[DVec3]) -> (DVec3, f64) {
    // guard: max(1) for an empty set (then the centre is 0)
    let c = pts.iter().copied().sum::<DVec3>() / pts.len().max(1) as f64;
    let radius = pts
        .iter()
        .map(|q| (*q - c).length())
        .fold(0.0f64, f64::max)
        .max(1e-3);
    (c, radius)
}

/// The irradiance an object surface receives in the target scene,
/// `E^{s+t} + B_s` ([`object_radiance`]'s numerator).
#[inline]
pub(crate) fn received(est: [f64; 3], bs: [f64; 3]) -> [f64; 3] {
    std::array::from_fn(|ch| est[ch] + bs[ch])
}

/// The object's shaded colour (module docs of [`crate::relight::paired`],
/// "The object's own shading"): its pasted radiance times the ratio of the
/// irradiance it receives in the target scene to the irradiance it
/// received where it was captured,
/// `P_o (E^{s+t} + B_s) / max(E_cap, cap_floor)`: `E^{s+t}` the target's
/// direct light with the scene's and the object's own shadows, `B_s` the
/// scene's bounce, `E_cap` the capture map's direct light with the
/// object's own shadows (its capture surroundings are unknown: nothing
/// bounced there). With the same map on both sides and an empty target
/// the ratio is 1 up to the visibility estimates. `received` is
/// `E^{s+t} + B_s` ([`received`]): the scene-cached path blends that sum
/// on its lattices rather than its two terms apart.
pub(crate) fn object_radiance(pc: Rgb, received: [f64; 3], ecap: [f64; 3], cap_floor: f64) -> Rgb {
    std::array::from_fn(|ch| {
        let cap = ecap[ch].max(cap_floor);
        // guard: cap >= cap_floor > 0
        let ratio = received[ch] / cap;
        (f64::from(pc[ch].max(0.0)) * ratio) as f32
    })
}

/// Up to `count` object pixels (a stratified subset of `obj_idx`) as
/// bounce VPLs `(position, normal, L a)`: each stands for `step` pixels of
/// outgoing radiance `L` (the shaded colour: a pixel value is radiance). `surf(j)` and `radiance(j)` give the
/// surface and the shaded colour of the `j`-th pixel of `obj_idx`; they are
/// asked only of the picked pixels, in parallel.
pub(crate) fn object_bounce_vpls(
    obj_idx: &[usize],
    surf: &(dyn Fn(usize) -> Option<(DVec3, DVec3)> + Sync),
    radiance: &(dyn Fn(usize) -> Rgb + Sync),
    pasted_depth: &DepthMap,
    k: &Intrinsics,
    count: usize,
) -> Vec<(DVec3, DVec3, [f64; 3])> {
    let w = k.width;
    let (picks, step) = bounce_picks(obj_idx.len(), count);
    picks
        .par_iter()
        .filter_map(|&j| {
            let i = obj_idx[j];
            let (pos, nrm) = surf(j)?;
            let (area, _) = pixel_area(pasted_depth, k, i % w, i / w);
            let flux = radiance(j).map(|v| v as f64 * area * step);
            Some((pos, nrm, flux))
        })
        .collect()
}

/// The positions (in a list of `n` object pixels) of the `min(count, n)`
/// stratified bounce VPLs, and how many pixels each stands for.
fn bounce_picks(n: usize, count: usize) -> (Vec<usize>, f64) {
    let m = count.min(n);
    if m == 0 {
        return (Vec::new(), 0.0);
    }
    // guard: m >= 1
    let step = n as f64 / m as f64;
    let picks = (0..m)
        .map(|j| (((j as f64 + 0.5) * step) as usize).min(n - 1))
        .collect();
    (picks, step)
}

/// The shadows of point VPLs `(position, normal, _)` (`bounce_shadows`):
/// one paraboloid map each, built in parallel from the given sample sets;
/// none when off, and then every VPL is seen.
pub(crate) struct PointVplShadows {
    maps: Vec<crate::relight::ism::ParaboloidMap>,
    bias_scale: f64,
}

impl PointVplShadows {
    pub(crate) fn new(
        vpls: &[(DVec3, DVec3, [f64; 3])],
        samples: &[crate::relight::ism::ParaboloidSamples],
        p: &RelightParams,
        seed: u64,
    ) -> Self {
        let maps = if p.bounce_shadows && !samples.is_empty() {
            vpls.par_iter()
                .enumerate()
                .map(|(j, (q, nq, _))| {
                    let s = seed.wrapping_mul(0x2545_F491).wrapping_add(j as u64);
                    crate::relight::ism::ParaboloidMap::build(
                        *q,
                        *nq,
                        samples,
                        p.bounce_ism_resolution,
                        s,
                    )
                })
                .collect()
        } else {
            Vec::new()
        };
        Self {
            maps,
            bias_scale: p.bias_scale,
        }
    }

    /// [`bounce_sum`] at `(x, n)` (its own splat radius `r`) over the
    /// `(index, VPL)` items, each VPL counted where its map sees `x`.
    pub(crate) fn bounce<'a>(
        &self,
        x: DVec3,
        n: DVec3,
        r: f64,
        vpls: impl Iterator<Item = (usize, &'a (DVec3, DVec3, [f64; 3]))>,
        r2_min: f64,
    ) -> [f64; 3] {
        bounce_sum(x, n, vpls, r2_min, |j| {
            self.maps
                .get(j)
                .is_none_or(|m| m.visible(x, n, r, self.bias_scale))
        })
    }
}

/// Splats of the bounce maps are this many ISM radii (no pull-push).
pub(crate) const BOUNCE_SPLAT_SCALE: f64 = 2.0;

/// One pixel of eq. 5: `α obj + (1 - α)(P + diff)`, clamped to >= 0; the
/// photo where the result is not finite.
#[inline]
pub(crate) fn composite(pp: Rgb, a: f32, obj: Rgb, diff: [f64; 3]) -> Rgb {
    std::array::from_fn(|ch| {
        let bg = pp[ch] as f64 + diff[ch];
        let v = a as f64 * obj[ch] as f64 + (1.0 - a as f64) * bg;
        if v.is_finite() {
            v.max(0.0) as f32
        } else {
            pp[ch]
        }
    })
}

/// The albedo of a target pixel (module docs): the given one, else
/// `P / E^t` where `E^t >= e_floor`, else 0.
#[inline]
pub(crate) fn target_albedo(given: Option<Rgb>, pp: Rgb, et: [f64; 3], e_floor: f64) -> [f64; 3] {
    std::array::from_fn(|ch| match given {
        Some(a) => a[ch].max(0.0) as f64,
        // guard: divide only when et >= e_floor > 0
        None if et[ch] >= e_floor => pp[ch].max(0.0) as f64 / et[ch],
        None => 0.0,
    })
}

/// Secondary VPLs on the target surfaces (one bounce, scene to object;
/// module docs): `m = p.scene_vpls` pixels drawn, stratified, with probability
/// `∝ a_i / max(d_i, d_min)²` (`d_min = p.clamp_distance_m`, `a_i` the pixel's surface area, `d_i` its
/// distance to the object centre `c`: the bounce falls off as 1/r², so the
/// samples go where it is strong). A pixel value is the radiance the
/// surface sends to the camera, the same in every direction for a
/// Lambertian surface, `L_i = P_i`, so a drawn pixel carries
/// `L_i a_i / (m pdf_i)`. Empty for `m = 0` or no surface.
pub(crate) fn scene_bounce_vpls(
    target: &[Option<Surf>],
    areas: &[f64],
    photo: &ColorImage,
    c: DVec3,
    p: &RelightParams,
) -> Vec<(DVec3, DVec3, [f64; 3])> {
    let (d_min, m, seed) = (p.clamp_distance_m, p.scene_vpls, p.seed);
    if m == 0 {
        return Vec::new();
    }
    let d_min = d_min.max(1e-6);
    // the weights in parallel (a square root and a division a pixel), the
    // running sum in pixel order
    let weights: Vec<f64> = target
        .par_iter()
        .zip(areas.par_iter())
        .map(|(s, &area)| {
            let Some(s) = s else {
                return 0.0;
            };
            let d = (s.pos - c).length().max(d_min);
            // guard: d >= d_min > 0
            let wgt = area / (d * d);
            if wgt.is_finite() && wgt > 0.0 {
                wgt
            } else {
                0.0
            }
        })
        .collect();
    let mut idx = Vec::new();
    let mut cdf = Vec::new();
    let mut acc = 0.0f64;
    for (i, &wgt) in weights.iter().enumerate() {
        if wgt > 0.0 {
            acc += wgt;
            idx.push(i);
            cdf.push(acc);
        }
    }
    if idx.is_empty() || !(acc.is_finite() && acc > 0.0) {
        return Vec::new();
    }
    let mut rng = crate::kit::rng::SplitMix64(seed ^ 0x5EC0_4DA2_B0C3_u64);
    let photo = photo.as_slice();
    (0..m)
        .filter_map(|j| {
            // guard: m >= 1
            let t = (j as f64 + rng.next_f64()) / m as f64 * acc;
            let n = cdf.partition_point(|&q| q <= t).min(idx.len() - 1);
            let i = idx[n];
            let s = target[i].as_ref()?;
            // L a / (m pdf) with pdf = a / (d² acc): the area cancels.
            // guard: m >= 1; d >= d_min > 0 as in the weights
            let d = (s.pos - c).length().max(d_min);
            let scale = d * d * acc / m as f64;
            let flux = photo[i].map(|v| {
                if v.is_finite() {
                    f64::from(v.max(0.0)) * scale
                } else {
                    0.0
                }
            });
            Some((s.pos, s.n, flux))
        })
        .collect()
}

/// The plane the object stands on, extended beyond the photo's frame
/// (module docs of [`crate::relight::paired`], "The support plane"): up to
/// `p.scene_vpls` point VPLs on the part of the plane the photo does not
/// show, within `p.support_radius_rel` object radii of the object's foot.
///
/// The plane is fitted to the target surfaces within `3 R` of the object's
/// centre `c` that face up (`n·(-y) > 0.8`, the camera held level; at
/// least 32 of them): their mean point and mean normal. Its radiance is
/// their mean photo radiance `P` (the photo has no object, so it is
/// unshadowed; the object's shadow on them is applied like any scene
/// VPL's). Points are drawn in the plane around the foot `f` (`c`
/// projected onto it) with density `∝ 1 / max(d, d_min)²` per area
/// (`log d` uniform in `[ln d_min, ln (k R)]`, the angle uniform), so
/// each carries `L a / (m pdf)` with `a / pdf = 2π d² ln(kR/d_min)`; a
/// drawn point the photo shows (it projects onto a target pixel within 5 %
/// of its depth) carries nothing: the scene VPLs hold it; nor does one
/// behind what the photo shows (a wall hides it from the camera and,
/// the object standing on the camera's side, mostly from the object). Empty when
/// `extend_support` is off, there is no such plane, or it lies above `c`.
pub(crate) fn support_vpls(
    target: &[Option<Surf>],
    photo: &ColorImage,
    k: &Intrinsics,
    depth: &DepthMap,
    c: DVec3,
    radius: f64,
    p: &RelightParams,
) -> Vec<(DVec3, DVec3, [f64; 3])> {
    let m = p.scene_vpls;
    if !p.extend_support || m == 0 || !(radius.is_finite() && radius > 0.0) {
        return Vec::new();
    }
    let up = DVec3::NEG_Y;
    let (mut n_sum, mut q_sum, mut l_sum, mut count) =
        (DVec3::ZERO, DVec3::ZERO, [0.0f64; 3], 0usize);
    // the surfaces to fit found in parallel (rayon's collect keeps the
    // order), summed in pixel order
    let fit: Vec<(&Surf, &Rgb)> = target
        .par_iter()
        .zip(photo.as_slice().par_iter())
        .filter_map(|(s, px)| {
            let s = s.as_ref()?;
            let skip = s.n.dot(up) <= 0.8 || (s.pos - c).length() > 3.0 * radius;
            (!skip && px.iter().all(|v| v.is_finite())).then_some((s, px))
        })
        .collect();
    for (s, px) in fit {
        n_sum += s.n;
        q_sum += s.pos;
        for ch in 0..3 {
            l_sum[ch] += f64::from(px[ch].max(0.0));
        }
        count += 1;
    }
    if count < 32 {
        return Vec::new();
    }
    // guard: count >= 32
    let (n, q) = (n_sum.normalize_or_zero(), q_sum / count as f64);
    let l = l_sum.map(|v| v / count as f64);
    let height = (c - q).dot(n);
    if n == DVec3::ZERO || height <= 0.0 {
        return Vec::new();
    }
    let foot = c - n * height;
    let (e1, e2) = n.any_orthonormal_pair();
    let d_min = p.clamp_distance_m.max(1e-3);
    let d_max = (p.support_radius_rel * radius).max(2.0 * d_min);
    // guard: d_max > d_min > 0
    let log_span = (d_max / d_min).ln();
    let mut rng = crate::kit::rng::SplitMix64(p.seed ^ 0x5u64.wrapping_mul(0x51A7_E5EE_D00D));
    let (w, h) = depth.dims();
    let phi0 = rng.next_f64();
    (0..m)
        .filter_map(|j| {
            // stratified in log d, the angles a golden-ratio sequence
            // (a random start): both well spread; guard: m >= 1
            let u = (j as f64 + rng.next_f64()) / m as f64;
            let d = d_min * (u * log_span).exp();
            let phi = std::f64::consts::TAU * (phi0 + j as f64 * 0.618_033_988_749_894_9).fract();
            let x = foot + (e1 * phi.cos() + e2 * phi.sin()) * d;
            // shown by the photo (the scene VPLs hold it), or behind what
            // the photo shows (a wall between it and the camera, and so,
            // mostly, between it and the object): nothing
            if let Some(uv) = k.project(x)
                && uv.x >= 0.0
                && uv.y >= 0.0
                && (uv.x as usize) < w
                && (uv.y as usize) < h
            {
                let z = *depth.get(uv.x as usize, uv.y as usize);
                if DepthMap::is_valid(z) && f64::from(z) <= 1.05 * x.z {
                    return None;
                }
            }
            // a / pdf = 2π d² ln(d_max / d_min), over m draws
            let scale = std::f64::consts::TAU * d * d * log_span / m as f64;
            Some((x, n, l.map(|v| v * scale)))
        })
        .collect()
}

/// Irradiance bounced onto `(x, n)` by point VPLs `(position, normal,
/// flux-like L a)` with the clamped `1 / max(r², r2_min)` (module docs).
pub fn bounce_at(x: DVec3, n: DVec3, vpls: &[(DVec3, DVec3, [f64; 3])], r2_min: f64) -> [f64; 3] {
    bounce_sum(x, n, vpls.iter().enumerate(), r2_min, |_| true)
}

/// [`bounce_at`] over `(index, VPL)` items, each VPL counted only where
/// `visible(index)` (asked only of VPLs that face `x` and that `x` faces).
pub fn bounce_sum<'a>(
    x: DVec3,
    n: DVec3,
    vpls: impl Iterator<Item = (usize, &'a (DVec3, DVec3, [f64; 3]))>,
    r2_min: f64,
    visible: impl Fn(usize) -> bool,
) -> [f64; 3] {
    let mut b = [0.0f64; 3];
    for (j, (q, nq, l)) in vpls {
        let v = *q - x;
        let r2 = v.length_squared();
        if r2 < 1e-18 {
            continue;
        }
        // cos at the receiver and at the VPL times r² (no square root):
        // (n·v)(-nq·v) = r² (n·u)(nq·(-u))
        let (cr, cq) = (n.dot(v), -nq.dot(v));
        if cr <= 0.0 || cq <= 0.0 {
            continue;
        }
        if !visible(j) {
            continue;
        }
        // guard: r2 >= 1e-18 > 0 and r2_min >= 0
        let g = cr * cq / (r2 * r2.max(r2_min));
        for ch in 0..3 {
            b[ch] += l[ch] * g;
        }
    }
    b
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A vertical face 0.16 m above a floor the photo does not show: the
    /// extended support plane gives it `π L F` with the view factor
    /// `F = (1 - h / sqrt(h² + D²)) / 2` of the floor within `D` (`D` the
    /// extension's reach), within 3 %.
    #[test]
    fn the_support_plane_lights_a_face_above_it() {
        let (w, h) = (64, 48);
        let k = crate::sim::synthetic::kinect_like_intrinsics(w, h);
        // a floor patch 0.5 m below the camera, around the object, in view
        let c = DVec3::new(0.0, 0.3, 2.0);
        let target: Vec<Option<Surf>> = (0..w * h)
            .map(|i| {
                let dy = ((i / w) as f64 + 0.5 - k.cy) / k.fy;
                let z = 0.5 / dy.max(1e-9);
                let pos = k.unproject((i % w) as f64 + 0.5, (i / w) as f64 + 0.5, z);
                (dy > 0.0 && (pos - c).length() < 0.6).then_some(Surf {
                    pos,
                    n: DVec3::NEG_Y,
                })
            })
            .collect();
        let photo = ColorImage::filled(w, h, [0.6f32, 0.3, 0.15]);
        // the depth map shows nothing: every drawn point is off the photo
        let depth = DepthMap::filled(w, h, 0.0);
        let p = RelightParams {
            scene_vpls: 4096,
            clamp_distance_m: 0.01,
            ..Default::default()
        };
        let radius = 0.2;
        let vpls = support_vpls(&target, &photo, &k, &depth, c, radius, &p);
        assert!(vpls.len() > 4000, "{}", vpls.len());
        let x = DVec3::new(0.0, 0.34, 2.0);
        let b = bounce_at(x, DVec3::X, &vpls, 1e-6);
        let (hh, dd) = (0.5 - 0.34, p.support_radius_rel * radius);
        let f = 0.5 * (1.0 - hh / (hh * hh + dd * dd).sqrt());
        for (ch, l) in [0.6, 0.3, 0.15].iter().enumerate() {
            let want = std::f64::consts::PI * l * f;
            assert!(
                (b[ch] - want).abs() < 0.03 * want,
                "channel {ch}: {} vs {want}",
                b[ch]
            );
        }
        // off: nothing
        let off = RelightParams {
            extend_support: false,
            ..p.clone()
        };
        assert!(support_vpls(&target, &photo, &k, &depth, c, radius, &off).is_empty());
    }

    /// A box's vertical edge seen from the front (two planes meeting at a
    /// crease, 90° apart): every pixel's estimated normal is its own
    /// face's, within 1°, the two columns beside the crease included (a
    /// one-sided difference across the edge would average the faces).
    #[test]
    fn normals_beside_a_crease_belong_to_their_face() {
        let (w, h) = (48, 32);
        let k = crate::sim::synthetic::kinect_like_intrinsics(w, h);
        // faces through the edge x = 0, z = 1.5: left x + z = 1.5 (normal
        // (-1, 0, -1)/√2 towards the camera), right -x + z = 1.5
        let (nl, nr) = (
            DVec3::new(-1.0, 0.0, -1.0).normalize(),
            DVec3::new(1.0, 0.0, -1.0).normalize(),
        );
        let depth = Image::from_fn(w, h, |x, _| {
            let a = (x as f64 + 0.5 - k.cx) / k.fx;
            // ray (a z, _, z): left face a z + z = 1.5, right -a z + z = 1.5
            (if a < 0.0 {
                1.5 / (1.0 + a)
            } else {
                1.5 / (1.0 - a)
            }) as f32
        });
        let mut checked = 0;
        for y in 0..h {
            for x in 0..w {
                let n = depth_normal(&depth, &k, x, y).unwrap();
                let a = (x as f64 + 0.5 - k.cx) / k.fx;
                let want = if a < 0.0 { nl } else { nr };
                let deg = n.dot(want).clamp(-1.0, 1.0).acos().to_degrees();
                assert!(deg < 1.0, "pixel ({x}, {y}): {n} vs {want}, {deg:.2}°");
                checked += 1;
            }
        }
        assert_eq!(checked, w * h);
    }
}
