//! `Relight`: adaptive differential rendering of a pasted object into the
//! target photo (3d-editing §IV.A, eq. 5 and 6): the object casts shadows on
//! the scene and sends bounced light, and the photo changes only by the
//! difference the object makes.
//!
//! # What is rendered
//!
//! With the directional VPLs `(ω_k, Φ_k)` of [`crate::vpl`] and the paired
//! imperfect shadow maps of [`crate::ism`] (visibility `V^t_k` without the
//! object's points, `V^{s+t}_k` with them, built from the **same** samples),
//! Lambertian irradiance at a point `x` with normal `n` is
//! `E^*(x) = Σ_k Φ_k max(0, n·ω_k) V^*_k(x)`, and
//!
//! - `I_t = ρ_t E^t` on the target surface (the scene without the object);
//! - `I_{s+t} = ρ_t (E^{s+t} + B)` on the target surface, where `B` is the
//!   light the object bounces onto it (below), and `ρ_o E^{s+t}` on the
//!   object.
//!
//! The composite is eq. 5 in linear radiance, with `α` the composite alpha
//! (after the depth test) and `P` the photo:
//! `I_m = α I_{s+t} + (1 - α)(P + I_{s+t} - I_t)`, clamped to `>= 0`.
//!
//! **Albedo.** `ρ_t` is the `albedo` input when given, else estimated as
//! `P / E^t` (so `I_t = P` and the scene keeps its look, its shadows scale by
//! `E^{s+t} / E^t`); where `E^t < min_shading_rel * E_ref`
//! (`E_ref = Σ_k lum(Φ_k)`, the guard of the division) the albedo is unknown
//! and taken as 0: the pixel keeps the photo. The object's albedo is its
//! pasted color divided by its **unshadowed** irradiance
//! `Σ_k Φ_k max(0, n·ω_k)` (same guard): the object is assumed photographed
//! under comparable light, and gains the shadows of its new place (the
//! scene bounce, below, enters both).
//!
//! **Bounce from the scene (one, scene to object).** Up to `scene_vpls`
//! target pixels become secondary point VPLs (drawn with probability
//! `∝ area / distance²` to the object centre, weighted by the inverse
//! pdf). The scene is Lambertian and its radiance is read off the photo,
//! `L = P / π`, so no albedo or irradiance of the scene is needed. They add
//! `B_s` (same clamped formula as below) to the object's irradiance, in the
//! albedo estimate as in the shading: `ρ_o = P_o / (E_free + B_s)` and the
//! object shows `ρ_o (E^{s+t} + B_s)`, never brighter than its pasted
//! colour. The bounce fills the object's own shadows with the scene's
//! colours. It is shadowed only with `bounce_shadows` (below).
//!
//! **Bounce (one, object to scene).** Up to `bounce_vpls` object pixels
//! (stratified) become secondary point VPLs: a surface element of area `a_j`
//! with outgoing radiance `L_j = ρ_o E^{s+t}_j / π` gives a receiver
//! `B(x) = Σ_j L_j a_j max(0, n_j·u) max(0, -n·u) / max(r², r_clamp²)` with
//! `u` the unit vector from `x` to the VPL and `r = |x_j - x|`. The
//! **clamp** `r >= clamp_distance_m` bounds every contribution (no fireflies
//! from a VPL touching a surface) at the price of a **bias**: the bounce is
//! too dark within about `clamp_distance_m` of the object. A VPL exactly at a
//! receiver (`r < 1e-9` m) has no direction and contributes 0. The scene's
//! own interreflections that the object blocks are not rendered (the
//! object's shadow of the scene's bounce light).
//!
//! **Bounce shadows** (`bounce_shadows`, off by default). Each point VPL of
//! either bounce gets a paraboloid ISM of its hemisphere
//! ([`crate::ism::ParaboloidMap`], the ISM paper's maps for VPLs at finite
//! positions): `bounce_ism_points` scene samples (plus a quarter as many
//! object samples in the scene-cached scheme) splatted at
//! `bounce_ism_resolution`² texels, and a bounce VPL counts at a receiver
//! only if the map sees it. Off by default: in the scenes measured the
//! bounce is rarely blocked (`docs/relight.md` gives its effect and cost).
//!
//! # Where it renders
//!
//! Only where the object changes the picture. Candidates are found
//! conservatively: pixels where the object is seen (`α > 0`), target points
//! whose ray towards some VPL passes within `2 R` of the object's centre `c`
//! (`R` = the largest distance of an object point from `c`: the doubled
//! radius covers the splats of the shadow maps), and target points within
//! `bounce_radius_rel * R` of `c` (the bounce is cut off beyond). A
//! candidate lit by the VPLs is then kept only if the object changes the
//! visibility of at least one VPL there (`V^{s+t}_k != V^t_k`: only the
//! VPLs of its cone are looked up) or the bounce reaches it; only kept
//! pixels are shaded with all VPLs. Elsewhere `I_{s+t} - I_t` is exactly 0
//! and the photo's pixels are kept bit for bit. With nothing pasted
//! (`α = 0` everywhere) or no VPL carrying energy, the node passes the photo
//! through and says why.
//!
//! # Visibility schemes (the `visibility` parameter)
//!
//! - `"scene_cached"` (default, [`crate::relight_scene`]): the scene's maps
//!   (uniform density) and `E^t` are built once per photo and VPL set and
//!   kept in a small memo; each run builds only maps of the object alone
//!   and uses `V^{s+t} = V^t ∧ V^o`. Moving the object costs ~50 ms at
//!   640x480 with 256 VPLs (`docs/relight.md`), and the result is more
//!   accurate than the paired maps at the same budget (the object's maps
//!   have texels a fraction of its size).
//! - `"paired"` (this module's [`relight`]): the paper's scheme above, both
//!   maps rebuilt from eq. 6 samples on every run.
//! - `"raycast"` ([`crate::relight_reference`]): exact shadow rays through
//!   the meshes of the target and the object, the reference of the others.

use std::sync::Arc;

use depthgraph_graph::node_params;
use depthgraph_graph::prelude::*;
use depthgraph_graph::registry::RegistryError;
use depthgraph_graph::value::Rgb;
use glam::DVec3;
use rayon::prelude::*;

use crate::ism::{IsmParams, PointSet, ShadowMap, build_pair_in, pixel_area, windows};
use crate::vpl::{Vpl, from_cloud, luminance};

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
        pub importance: String = "near_object", ParamKind::Choice(IMPORTANCE);
        /// "scene_cached": scene maps kept per scene, object maps per run (fast moves);
        /// "paired": scene+object maps with eq. 6 rebuilt every run (the paper's scheme);
        /// "raycast": exact shadow rays through the meshes (the reference; slow).
        pub visibility: String = "scene_cached", ParamKind::Choice(VISIBILITY);
        /// Texels per side of the object's own maps (scene_cached).
        pub object_ism_resolution: usize = 64usize, ParamKind::Int { min: 4, max: 2048 };
        /// Object samples splatted into each of its maps (scene_cached).
        pub object_ism_points: usize = 2048usize, ParamKind::Int { min: 16, max: 1 << 22 };
    }
}

/// Names of the sampling densities (the `importance` parameter).
pub const IMPORTANCE: &[&str] = &["near_object", "uniform"];

/// Names of the visibility schemes (the `visibility` parameter).
pub const VISIBILITY: &[&str] = &["scene_cached", "paired", "raycast"];

/// The inputs of [`relight`], all `k.width x k.height`.
#[derive(Debug, Clone, Copy)]
pub struct RelightInputs<'a> {
    pub photo: &'a ColorImage,
    pub depth: &'a DepthMap,
    /// Target normals; `None` (or zero normals) = estimated from the depth.
    pub normals: Option<&'a NormalMap>,
    /// Target albedo; `None` = estimated as photo / shading.
    pub albedo: Option<&'a ColorImage>,
    pub pasted_color: &'a ColorImage,
    pub pasted_depth: &'a DepthMap,
    pub alpha: &'a Mask,
    pub k: &'a Intrinsics,
}

/// The scene's part of [`RelightInputs`]: what the scene-cached path
/// ([`crate::relight_scene`]) keeps while the object moves.
#[derive(Debug, Clone, Copy)]
pub struct SceneInputs<'a> {
    pub photo: &'a ColorImage,
    pub depth: &'a DepthMap,
    pub normals: Option<&'a NormalMap>,
    pub albedo: Option<&'a ColorImage>,
    pub k: &'a Intrinsics,
}

impl SceneInputs<'_> {
    /// Sane intrinsics, and every image at their size.
    pub(crate) fn check(&self) -> Result<(), NodeError> {
        let k = self.k;
        if !k.is_sane() {
            return Err(NodeError::input(
                "intrinsics",
                "focal lengths must be finite and positive",
            ));
        }
        check("photo", self.photo.dims(), k)?;
        check("depth", self.depth.dims(), k)?;
        if let Some(n) = self.normals {
            check("normals", n.dims(), k)?;
        }
        if let Some(a) = self.albedo {
            check("albedo", a.dims(), k)?;
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
        check("pasted_color", self.pasted_color.dims(), self.k)?;
        check("pasted_depth", self.pasted_depth.dims(), self.k)?;
        check("alpha", self.alpha.dims(), self.k)
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

/// Result of [`relight`].
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
    let du = if x + 1 < w && same(x + 1, y) {
        at(x + 1, y) - p
    } else if x > 0 && same(x - 1, y) {
        p - at(x - 1, y)
    } else {
        return None;
    };
    let dv = if y + 1 < h && same(x, y + 1) {
        at(x, y + 1) - p
    } else if y > 0 && same(x, y - 1) {
        p - at(x, y - 1)
    } else {
        return None;
    };
    let n = du.cross(dv).normalize_or_zero();
    if n == DVec3::ZERO {
        return None;
    }
    Some(if n.dot(p) > 0.0 { -n } else { n })
}

pub(crate) fn check(port: &str, dims: (usize, usize), k: &Intrinsics) -> Result<(), NodeError> {
    if dims != (k.width, k.height) {
        return Err(NodeError::input(
            port,
            format!(
                "is {}x{} but the intrinsics are for {}x{}",
                dims.0, dims.1, k.width, k.height
            ),
        ));
    }
    Ok(())
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

#[derive(Debug, Clone)]
pub(crate) struct Surf {
    pub(crate) pos: DVec3,
    pub(crate) n: DVec3,
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
        .filter(|v| luminance(v.power) > 0.0)
        .collect();
    let e_ref: f64 = vpls.iter().map(|v| luminance(v.power)).sum();
    let dirs = vpls
        .iter()
        .map(|v| DVec3::from_array(v.direction.map(|c| c as f64)).normalize_or_zero())
        .collect();
    (vpls, dirs, e_ref)
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

/// The object's shaded colour (module docs, "Bounce from the scene"):
/// `ρ_o (E^{s+t} + B_s)` with `ρ_o = P_o / max(E_free + B_s, e_floor)`.
pub(crate) fn object_radiance(
    pc: Rgb,
    est: [f64; 3],
    efree: [f64; 3],
    bs: [f64; 3],
    e_floor: f64,
) -> Rgb {
    std::array::from_fn(|ch| {
        // The pasted colour was lit directly and by bounced light alike:
        // ρ_o = P / (E_free + B_s), so the shaded object is
        // P (E^{s+t} + B_s) / (E_free + B_s) <= P (no firefly where the
        // direct light is weak).
        let free = (efree[ch] + bs[ch]).max(e_floor);
        // guard: free >= e_floor > 0
        let rho = (pc[ch].max(0.0) as f64) / free;
        (rho * (est[ch] + bs[ch])) as f32
    })
}

/// Up to `count` object pixels (a stratified subset of `obj_idx`) as
/// bounce VPLs `(position, normal, L a)`: each stands for `step` pixels of
/// outgoing radiance `ρ E / π`. `surf(j)` and `radiance(j)` give the
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
            let flux = radiance(j).map(|v| v as f64 / std::f64::consts::PI * area * step);
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
    maps: Vec<crate::ism::ParaboloidMap>,
    bias_scale: f64,
}

impl PointVplShadows {
    pub(crate) fn new(
        vpls: &[(DVec3, DVec3, [f64; 3])],
        samples: &[crate::ism::ParaboloidSamples],
        p: &RelightParams,
        seed: u64,
    ) -> Self {
        let maps = if p.bounce_shadows && !samples.is_empty() {
            vpls.par_iter()
                .enumerate()
                .map(|(j, (q, nq, _))| {
                    let s = seed.wrapping_mul(0x2545_F491).wrapping_add(j as u64);
                    crate::ism::ParaboloidMap::build(*q, *nq, samples, p.bounce_ism_resolution, s)
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

/// Irradiance `(E^t, E^{s+t}, unshadowed)` per surface.
type Irr = ([f64; 3], [f64; 3], [f64; 3]);

/// What the irradiance of a surface needs.
struct IrrCtx<'a> {
    vpls: &'a [Vpl],
    dirs: &'a [DVec3],
    maps: &'a [Option<(ShadowMap, ShadowMap)>],
    set: &'a PointSet,
    m: usize,
    bias_scale: f64,
}

impl IrrCtx<'_> {
    /// Surfaces per parallel chunk: its accumulators stay in cache while
    /// the VPL loop walks the maps one at a time.
    const CHUNK: usize = 512;

    /// Whether the object changes the visibility of any VPL at each
    /// surface: `V^{s+t}_k != V^t_k` for some `k` with `n·ω_k > 0`. Only
    /// VPLs whose ray from the surface passes within `reach` of the
    /// object's centre `c` are looked up: the object's splats lie inside
    /// that cylinder (module docs), so elsewhere the paired maps agree
    /// texel for texel. A surface stops at its first differing VPL.
    fn changed(&self, surfs: &[&Surf], c: DVec3, reach: f64) -> Vec<bool> {
        surfs
            .par_iter()
            .map(|s| {
                let cone = Cone::new(s.pos, c, reach);
                let r = self.set.splat_radius(s.pos, self.m);
                self.dirs.iter().zip(self.maps).any(|(dir, m)| {
                    if s.n.dot(*dir) <= 0.0 || !cone.contains(*dir) {
                        return false;
                    }
                    match m {
                        Some((mt, mst)) => {
                            let b = mst.bias_with_radius(r, s.n, self.bias_scale);
                            let (vt, vst) = mt.visible_pair(mst, s.pos, b);
                            vt != vst
                        }
                        None => false,
                    }
                })
            })
            .collect()
    }

    /// `Σ_k Φ_k max(0, n·ω_k) V_k` of every surface. Chunks of surfaces
    /// run in parallel, each VPL-major (one pair of maps at a time stays in
    /// cache); every surface still sums its VPLs in their order, so the
    /// result does not depend on the thread count.
    fn irradiance(&self, surfs: &[&Surf]) -> Vec<Irr> {
        surfs
            .par_chunks(Self::CHUNK)
            .flat_map_iter(|chunk| {
                let radii: Vec<f64> = chunk
                    .iter()
                    .map(|s| self.set.splat_radius(s.pos, self.m))
                    .collect();
                let mut acc: Vec<Irr> = vec![([0.0; 3], [0.0; 3], [0.0; 3]); chunk.len()];
                for ((v, d), m) in self.vpls.iter().zip(self.dirs).zip(self.maps) {
                    let power = v.power.map(|c| c as f64);
                    for ((s, r), (et, est, efree)) in chunk.iter().zip(&radii).zip(acc.iter_mut()) {
                        let cos = s.n.dot(*d);
                        if cos <= 0.0 {
                            continue;
                        }
                        let (vt, vst) = match m {
                            Some((mt, mst)) => {
                                let b = mst.bias_with_radius(*r, s.n, self.bias_scale);
                                mt.visible_pair(mst, s.pos, b)
                            }
                            None => (true, true),
                        };
                        for ch in 0..3 {
                            let e = power[ch] * cos;
                            efree[ch] += e;
                            if vt {
                                et[ch] += e;
                            }
                            if vst {
                                est[ch] += e;
                            }
                        }
                    }
                }
                acc
            })
            .collect()
    }
}

/// Differential rendering (module docs). `Ok(None)` when there is nothing
/// to do (nothing pasted, or no VPL with energy): the photo stands.
pub fn relight(
    inp: &RelightInputs,
    vpls: &[Vpl],
    p: &RelightParams,
) -> Result<Option<Relit>, NodeError> {
    let k = inp.k;
    inp.check()?;
    let near_object = match p.importance.as_str() {
        "near_object" => true,
        "uniform" => false,
        other => {
            return Err(NodeError::param(
                "importance",
                format!("\"{other}\" is not one of \"near_object\", \"uniform\""),
            ));
        }
    };
    let (w, h) = (k.width, k.height);
    let alpha = clean_alpha(inp.alpha, inp.pasted_depth);
    let (vpls, dirs, e_ref) = lit_vpls(vpls);
    if vpls.is_empty() || !e_ref.is_finite() || alpha.iter().all(|a| *a <= 0.0) {
        return Ok(None);
    }
    let e_floor = p.min_shading_rel * e_ref;

    // ---- surfaces: target and object, per pixel
    let target = target_surfaces(inp.depth, inp.normals, k);
    let object: Vec<Option<Surf>> = (0..w * h)
        .map(|i| (alpha[i] > 0.0).then(|| inp.object_surface(i)))
        .collect();
    let obj_pts: Vec<DVec3> = object.iter().flatten().map(|s| s.pos).collect();
    // at least one alpha > 0 pixel, which has a valid pasted depth
    let (c, radius) = centre_and_radius(&obj_pts);

    // ---- region
    let reach = 2.0 * radius;
    let bounce_reach = p.bounce_radius_rel * radius;
    let in_region: Vec<bool> = (0..w * h)
        .into_par_iter()
        .map(|i| {
            if alpha[i] > 0.0 {
                return true;
            }
            match &target[i] {
                None => false,
                Some(s) => {
                    (p.bounce_vpls > 0 && (s.pos - c).length() <= bounce_reach) || {
                        let cone = Cone::new(s.pos, c, reach);
                        dirs.iter().any(|d| cone.contains(*d))
                    }
                }
            }
        })
        .collect();
    let mut receivers: Vec<DVec3> = Vec::new();
    for i in 0..w * h {
        if in_region[i] {
            if let Some(s) = &target[i] {
                receivers.push(s.pos);
            }
            if let Some(s) = &object[i] {
                receivers.push(s.pos);
            }
        }
    }

    // ---- shadow maps (eq. 6 importance around the object centre)
    let ism = IsmParams {
        resolution: p.ism_resolution,
        points_per_map: p.ism_points,
        bias_scale: p.bias_scale,
        min_distance_m: p.min_distance_m,
        seed: p.seed,
        ..Default::default()
    };
    let centres = if near_object { vec![c] } else { Vec::new() };
    let set = PointSet::new(
        &[(inp.depth, false), (inp.pasted_depth, true)],
        k,
        &centres,
        p.min_distance_m,
    );
    let wins = windows(&dirs, &receivers);
    let maps: Vec<Option<(ShadowMap, ShadowMap)>> = wins
        .par_iter()
        .enumerate()
        .map(|(j, win)| {
            build_pair_in(
                win.as_ref()?,
                &set,
                &ism,
                p.seed.wrapping_mul(0x9E37_79B9).wrapping_add(j as u64),
            )
        })
        .collect();

    // irradiance at surfaces: (without object, with object, unshadowed)
    let irr_ctx = IrrCtx {
        vpls: &vpls,
        dirs: &dirs,
        maps: &maps,
        set: &set,
        m: ism.points_per_map,
        bias_scale: ism.bias_scale,
    };

    // ---- object shading and bounce VPLs
    let obj_idx: Vec<usize> = (0..w * h)
        .filter(|&i| in_region[i] && object[i].is_some())
        .collect();
    let obj_surfs: Vec<&Surf> = obj_idx.iter().filter_map(|&i| object[i].as_ref()).collect();
    let obj_irr = irr_ctx.irradiance(&obj_surfs);
    let r2_min = p.clamp_distance_m * p.clamp_distance_m;
    // secondary VPLs on the scene: the light the scene bounces onto the object
    let scene_vpls = if p.scene_vpls > 0 {
        let areas = pixel_areas(inp.depth, k);
        scene_bounce_vpls(&target, &areas, inp.photo, c, p)
    } else {
        Vec::new()
    };
    let bounce_samples = [crate::ism::ParaboloidSamples {
        set: &set,
        m: p.bounce_ism_points,
        radius_scale: BOUNCE_SPLAT_SCALE,
    }];
    let scene_shadows = PointVplShadows::new(&scene_vpls, &bounce_samples, p, p.seed ^ 0x5EC0);
    let obj_rad: Vec<Rgb> = obj_idx
        .par_iter()
        .zip(obj_irr.par_iter())
        .map(|(&i, &(_, est, efree))| {
            let pc = inp.pasted_color.as_slice()[i];
            let bs = match &object[i] {
                Some(s) if !scene_vpls.is_empty() => {
                    let r = BOUNCE_SPLAT_SCALE * set.splat_radius(s.pos, p.bounce_ism_points);
                    scene_shadows.bounce(s.pos, s.n, r, scene_vpls.iter().enumerate(), r2_min)
                }
                _ => [0.0; 3],
            };
            object_radiance(pc, est, efree, bs, e_floor)
        })
        .collect();
    // bounce VPLs: stratified subset of object pixels
    let bounce = object_bounce_vpls(
        &obj_idx,
        &|j| object[obj_idx[j]].as_ref().map(|s| (s.pos, s.n)),
        &|j| obj_rad[j],
        inp.pasted_depth,
        k,
        p.bounce_vpls,
    );
    let bounce_shadows = PointVplShadows::new(&bounce, &bounce_samples, p, p.seed ^ 0x0B1E);

    // ---- which target surfaces the object changes: its shadow (some VPL's
    // visibility differs) or the bounce's reach; only these are shaded.
    let cand_idx: Vec<usize> = (0..w * h)
        .filter(|&i| in_region[i] && target[i].is_some())
        .collect();
    let cand_surfs: Vec<&Surf> = cand_idx
        .iter()
        .filter_map(|&i| target[i].as_ref())
        .collect();
    let shadowed = irr_ctx.changed(&cand_surfs, c, reach);
    let mut in_region = in_region;
    for (&i, sh) in cand_idx.iter().zip(&shadowed) {
        let near = target[i]
            .as_ref()
            .is_some_and(|s| !bounce.is_empty() && (s.pos - c).length() <= bounce_reach);
        in_region[i] = alpha[i] > 0.0 || *sh || near;
    }

    // ---- per pixel
    let photo = inp.photo.as_slice();
    // the target surfaces of the region, shaded together (VPL-major)
    let tgt_idx: Vec<usize> = (0..w * h)
        .filter(|&i| in_region[i] && target[i].is_some())
        .collect();
    let tgt_surfs: Vec<&Surf> = tgt_idx.iter().filter_map(|&i| target[i].as_ref()).collect();
    let tgt_irr = irr_ctx.irradiance(&tgt_surfs);
    let px: Vec<(Rgb, Rgb)> = (0..w * h)
        .into_par_iter()
        .map(|i| {
            let pp = photo[i];
            if !in_region[i] {
                return (pp, [0.0; 3]);
            }
            let mut diff = [0.0f64; 3];
            let shaded = tgt_idx
                .binary_search(&i)
                .ok()
                .and_then(|j| Some((target[i].as_ref()?, tgt_irr.get(j)?)));
            if let Some((s, &(et, est, _))) = shaded {
                let mut b = [0.0f64; 3];
                if (s.pos - c).length() <= bounce_reach {
                    let r = BOUNCE_SPLAT_SCALE * set.splat_radius(s.pos, p.bounce_ism_points);
                    b = bounce_shadows.bounce(s.pos, s.n, r, bounce.iter().enumerate(), r2_min);
                }
                let given = inp.albedo.map(|a| a.as_slice()[i]);
                let rho = target_albedo(given, pp, et, e_floor);
                for ch in 0..3 {
                    diff[ch] = rho[ch] * (est[ch] + b[ch] - et[ch]);
                }
            }
            let a = alpha[i];
            let obj = match obj_idx.binary_search(&i) {
                Ok(j) => obj_rad[j],
                Err(_) => [0.0; 3],
            };
            (composite(pp, a, obj, diff), diff.map(|d| d as f32))
        })
        .collect();
    let (color, difference): (Vec<Rgb>, Vec<Rgb>) = px.into_iter().unzip();
    let shape = |e: depthgraph_graph::value::ShapeError| NodeError::Invalid(e.to_string());
    Ok(Some(Relit {
        color: Image::from_vec(w, h, color).map_err(shape)?,
        region: Image::from_vec(
            w,
            h,
            in_region
                .iter()
                .map(|r| if *r { 1.0 } else { 0.0 })
                .collect(),
        )
        .map_err(shape)?,
        difference: Image::from_vec(w, h, difference).map_err(shape)?,
    }))
}

/// Secondary VPLs on the target surfaces (one bounce, scene to object;
/// module docs): `m = p.scene_vpls` pixels drawn, stratified, with probability
/// `∝ a_i / max(d_i, d_min)²` (`d_min = p.clamp_distance_m`, `a_i` the pixel's surface area, `d_i` its
/// distance to the object centre `c`: the bounce falls off as 1/r², so the
/// samples go where it is strong). A Lambertian surface seen in the photo
/// has radiance `L_i = P_i / π` (`P = ρ E` is the pixel value), so a drawn
/// pixel carries `L_i a_i / (m pdf_i)`. Empty for `m = 0` or no surface.
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
    let mut idx = Vec::new();
    let mut cdf = Vec::new();
    let mut acc = 0.0f64;
    for ((i, s), &area) in target.iter().enumerate().zip(areas) {
        let Some(s) = s else {
            continue;
        };
        let d = (s.pos - c).length().max(d_min);
        // guard: d >= d_min > 0
        let wgt = area / (d * d);
        if !(wgt.is_finite() && wgt > 0.0) {
            continue;
        }
        acc += wgt;
        idx.push(i);
        cdf.push(acc);
    }
    if idx.is_empty() || !(acc.is_finite() && acc > 0.0) {
        return Vec::new();
    }
    let mut rng = crate::vpl::SplitMix64(seed ^ 0x5EC0_4DA2_B0C3_u64);
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
            let scale = d * d * acc / (m as f64 * std::f64::consts::PI);
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

fn eval(ctx: &EvalCtx, inputs: &Inputs, p: &RelightParams) -> Result<Outputs, NodeError> {
    let photo = inputs.color("photo")?;
    let k = inputs.intrinsics("intrinsics")?;
    let cloud = inputs.point_cloud("vpls")?;
    let vpls = from_cloud(cloud, "vpls")?;
    let normals = match inputs.get("normals") {
        Some(Value::Normals(n)) => Some(n.clone()),
        Some(other) => {
            return Err(NodeError::input(
                "normals",
                format!("expected Normals, found {}", other.value_type()),
            ));
        }
        None => None,
    };
    let inp = RelightInputs {
        photo,
        depth: inputs.depth("depth")?,
        normals: normals.as_deref(),
        albedo: inputs.color_opt("albedo")?.map(|a| a.as_ref()),
        pasted_color: inputs.color("pasted_color")?,
        pasted_depth: inputs.depth("pasted_depth")?,
        alpha: inputs.mask("alpha")?,
        k: &k,
    };
    ctx.check_cancelled()?;
    let result = match p.visibility.as_str() {
        "paired" => relight(&inp, &vpls, p)?,
        "raycast" => crate::relight_reference::relight_reference_image(&inp, &vpls, p)?,
        "scene_cached" => {
            let key = crate::relight_scene::SceneKey {
                photo: photo.clone(),
                depth: inputs.depth("depth")?.clone(),
                normals: normals.clone(),
                albedo: inputs.color_opt("albedo")?.cloned(),
                vpls: cloud.clone(),
                k,
                params: crate::relight_scene::SceneKey::params_of(p),
            };
            let (scene, _reused) = crate::relight_scene::memo_scene(key, || {
                crate::relight_scene::RelightScene::new(&inp.scene(), &vpls, p)
            })?;
            ctx.check_cancelled()?;
            crate::relight_scene::relight_moved(&scene, &inp, p)?
        }
        other => {
            return Err(NodeError::param(
                "visibility",
                format!("\"{other}\" is not one of {VISIBILITY:?}"),
            ));
        }
    };
    match result {
        Some(r) => Ok(Outputs::new()
            .with("color", r.color)
            .with("region", Value::Mask(Arc::new(r.region)))
            .with("difference", r.difference)),
        None => {
            let (w, h) = photo.dims();
            let reason = if vpls.iter().all(|v| luminance(v.power) <= 0.0) {
                "no VPL carries energy (black environment map): nothing to relight"
            } else {
                "nothing pasted: the alpha is 0 everywhere"
            };
            Ok(Outputs::new()
                .with("color", Value::Color(photo.clone()))
                .with("region", Value::Mask(Arc::new(Image::filled(w, h, 0.0))))
                .with("difference", Image::filled(w, h, [0.0f32; 3]))
                .passthrough(reason))
        }
    }
}

/// Registers `Relight`.
pub fn register(reg: &mut Registry) -> Result<(), RegistryError> {
    reg.register(TypedNode::new(
        "Relight",
        3,
        "Differential rendering of a pasted object (3d-editing §IV.A, eq. 5-6): instant radiosity with the \
         directional VPLs of an environment map, imperfect shadow maps, one bounce each way with clamped \
         1/r² (object to scene; scene to object through secondary VPLs read off the photo).\n\
         Only the pixels the object changes are rendered; elsewhere the photo is kept bit for bit.\n\
         visibility: scene_cached keeps the scene's shadow maps while only the object changes (fast moves); \
         paired rebuilds scene+object maps with near-object importance (eq. 6) every run; raycast traces \
         exact shadow rays through the meshes (the reference, slow).",
        vec![
            PortSpec::required("photo", ValueType::Color, "the target photo P, linear RGB"),
            PortSpec::required("depth", ValueType::Depth, "target depth, metres"),
            PortSpec::optional("normals", ValueType::Normals, "target normals (else from the depth)"),
            PortSpec::optional("albedo", ValueType::Color, "target albedo (else photo / shading)"),
            PortSpec::required("pasted_color", ValueType::Color, "Paste.color"),
            PortSpec::required("pasted_depth", ValueType::Depth, "Paste.depth"),
            PortSpec::required("alpha", ValueType::Mask, "OcclusionComposite.alpha (after the depth test)"),
            PortSpec::required("intrinsics", ValueType::Intrinsics, "of the target"),
            PortSpec::required("vpls", ValueType::PointCloud, "VplSample.vpls"),
        ],
        vec![
            PortSpec::output("color", ValueType::Color, "the composite I_m of eq. 5, linear RGB"),
            PortSpec::output("region", ValueType::Mask, "1 where rendered, 0 where the photo was kept"),
            PortSpec::output("difference", ValueType::Color, "I_{s+t} - I_t on the target surface"),
        ],
        eval,
    ))
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::ism::fixtures::floor_and_slab;

    /// The sampled scene bounce (secondary VPLs drawn ∝ area / d²) matches
    /// the sum over every floor pixel at a point facing the floor, keeps
    /// the floor's colour, and is empty for 0 VPLs.
    #[test]
    fn scene_bounce_is_an_unbiased_estimate_of_the_floor_light() {
        let (w, h) = (160, 120);
        let (k, floor, slab, alpha) = floor_and_slab(w, h);
        let photo: ColorImage = Image::filled(w, h, [0.8, 0.2, 0.1]);
        let inp = RelightInputs {
            photo: &photo,
            depth: &floor,
            normals: None,
            albedo: None,
            pasted_color: &photo,
            pasted_depth: &slab,
            alpha: &alpha,
            k: &k,
        };
        let up = DVec3::new(0.0, -1.0, 0.0);
        let target: Vec<Option<Surf>> = (0..w * h)
            .map(|i| {
                let z = *floor.get(i % w, i / w);
                DepthMap::is_valid(z).then(|| Surf {
                    pos: k.unproject((i % w) as f64 + 0.5, (i / w) as f64 + 0.5, z as f64),
                    n: up,
                })
            })
            .collect();
        // The slab's underside: 0.2 m above the floor, facing it.
        let (x, n) = (DVec3::new(0.0, 0.2, 2.0), DVec3::new(0.0, 1.0, 0.0));
        let clamp = 0.05;
        let all: Vec<(DVec3, DVec3, [f64; 3])> = target
            .iter()
            .enumerate()
            .filter_map(|(i, s)| {
                let s = s.as_ref()?;
                let (a, _) = pixel_area(&floor, &k, i % w, i / w);
                let l = photo.as_slice()[i].map(|v| f64::from(v) * a / std::f64::consts::PI);
                Some((s.pos, s.n, l))
            })
            .collect();
        let exact = bounce_at(x, n, &all, clamp * clamp);
        assert!(exact[0] > 0.1, "the floor lights the underside: {exact:?}");
        let areas = pixel_areas(&floor, &k);
        let draw = |m: usize| RelightParams {
            clamp_distance_m: clamp,
            scene_vpls: m,
            seed: 7,
            ..Default::default()
        };
        let vpls = scene_bounce_vpls(&target, &areas, inp.photo, x, &draw(4096));
        assert_eq!(vpls.len(), 4096);
        let est = bounce_at(x, n, &vpls, clamp * clamp);
        for ch in 0..3 {
            let rel = (est[ch] - exact[ch]).abs() / exact[ch];
            assert!(
                rel < 0.05,
                "channel {ch}: {} vs {} ({rel:.3})",
                est[ch],
                exact[ch]
            );
        }
        // The colour of the floor: ratios kept.
        assert!((est[1] / est[0] - 0.25).abs() < 1e-9);
        assert!(scene_bounce_vpls(&target, &areas, inp.photo, x, &draw(0)).is_empty());
    }

    /// The floor and slab of [`floor_and_slab_at`](crate::ism::fixtures::floor_and_slab_at)
    /// as `Relight` inputs: a grey floor photo (0.5, exactly albedo 0.5
    /// under a unit overhead light), a green pasted slab.
    pub(crate) struct SlabScene {
        pub k: Intrinsics,
        pub floor: DepthMap,
        pub slab: DepthMap,
        pub alpha: Mask,
        pub photo: ColorImage,
        pub albedo: ColorImage,
        pub pasted_color: ColorImage,
    }

    impl SlabScene {
        pub(crate) fn new(w: usize, h: usize, dx: f64) -> Self {
            let (k, floor, slab, alpha) = crate::ism::fixtures::floor_and_slab_at(w, h, dx);
            let photo = floor.map(|z| if *z > 0.0 { [0.5f32; 3] } else { [0.0; 3] });
            Self {
                k,
                floor,
                slab,
                alpha,
                photo,
                albedo: Image::filled(w, h, [0.5f32; 3]),
                pasted_color: Image::filled(w, h, [0.3f32, 0.6, 0.2]),
            }
        }

        /// The inputs, with the albedo given or to be estimated.
        pub(crate) fn inputs(&self, given_albedo: bool) -> RelightInputs<'_> {
            RelightInputs {
                photo: &self.photo,
                depth: &self.floor,
                normals: None,
                albedo: given_albedo.then_some(&self.albedo),
                pasted_color: &self.pasted_color,
                pasted_depth: &self.slab,
                alpha: &self.alpha,
                k: &self.k,
            }
        }
    }

    pub(crate) fn overhead() -> Vec<Vpl> {
        vec![Vpl {
            direction: [0.0, -1.0, 0.0],
            power: [1.0; 3],
        }]
    }

    /// A slab above a floor under one overhead VPL: the floor under it is
    /// dark (ray-cast reference: the vertical ray from the floor point hits
    /// the slab), every other floor pixel is unchanged, bit for bit where the
    /// node did not render; outside the region the difference is exactly 0.
    #[test]
    fn a_slab_casts_its_analytic_shadow_and_nothing_else_changes() {
        slab_shadow_is_analytic(&|inp, vpls, p| relight(inp, vpls, p).unwrap().unwrap(), 0.0);
    }

    /// The check of the test above, for either visibility scheme.
    pub(crate) fn slab_shadow_is_analytic(
        run: &dyn Fn(&RelightInputs, &[Vpl], &RelightParams) -> Relit,
        dx: f64,
    ) {
        let (w, h) = (160, 120);
        let (k, floor, slab, alpha) = crate::ism::fixtures::floor_and_slab_at(w, h, dx);
        let albedo = Image::filled(w, h, [0.5f32; 3]);
        // the photo is exactly albedo x the VPL's irradiance (cos = 1)
        let photo = floor.map(|z| if *z > 0.0 { [0.5f32; 3] } else { [0.0; 3] });
        let pasted_color = Image::filled(w, h, [0.3f32, 0.6, 0.2]);
        let inp = RelightInputs {
            photo: &photo,
            depth: &floor,
            normals: None,
            albedo: Some(&albedo),
            pasted_color: &pasted_color,
            pasted_depth: &slab,
            alpha: &alpha,
            k: &k,
        };
        let p = RelightParams {
            ism_points: 20000,
            ism_resolution: 128,
            bounce_vpls: 0,
            ..Default::default()
        };
        let r = run(&inp, &overhead(), &p);
        let (mut shadowed, mut wrong, mut edge, mut untouched) = (0, 0, 0, 0);
        for y in 0..h {
            for x in 0..w {
                let (i, z) = (y * w + x, *floor.get(x, y));
                let (c, d, reg) = (
                    r.color.as_slice()[i],
                    r.difference.as_slice()[i],
                    r.region.as_slice()[i],
                );
                assert!(c.iter().all(|v| v.is_finite() && *v >= 0.0));
                if alpha.as_slice()[i] >= 1.0 {
                    // the object is never brighter than its pasted colour
                    let pc = pasted_color.as_slice()[i];
                    assert!(
                        (0..3).all(|ch| c[ch] <= pc[ch] * (1.0 + 1e-5)),
                        "{c:?} > {pc:?}"
                    );
                }
                if reg == 0.0 {
                    untouched += 1;
                    assert_eq!(c, photo.as_slice()[i]);
                    assert_eq!(d, [0.0; 3]);
                    continue;
                }
                if alpha.as_slice()[i] > 0.0 || z <= 0.0 {
                    continue;
                }
                let q = k.unproject(x as f64 + 0.5, y as f64 + 0.5, z as f64);
                // ray-cast reference: the vertical ray from q meets y = 0.2 at (q.x, q.z)
                let under = (q.x - dx).abs() <= 0.2 && (1.6..=2.4).contains(&q.z);
                let near = ((q.x - dx).abs() - 0.2).abs() < 0.15
                    || (q.z - 1.6).abs() < 0.15
                    || (q.z - 2.4).abs() < 0.15;
                let dark = c[0] < 0.25;
                if near {
                    edge += 1;
                } else if under != dark {
                    wrong += 1;
                } else if under {
                    shadowed += 1;
                    assert!(c[0] < 1e-6, "fully shadowed floor at {q}: {c:?}");
                } else {
                    assert_eq!(c, photo.as_slice()[i], "lit floor at {q} changed");
                }
            }
        }
        assert!(shadowed > 30, "{shadowed}");
        assert_eq!(
            wrong, 0,
            "{wrong} pixels disagree with the ray-cast shadow ({edge} near its edge)"
        );
        assert!(
            untouched > w * h / 2,
            "the region is not limited: {untouched} untouched"
        );
        // the slab itself: fully lit from above, keeps its pasted color
        let i = (0..w * h).find(|&i| alpha.as_slice()[i] > 0.0).unwrap();
        let c = r.color.as_slice()[i];
        assert!((c[1] - 0.6).abs() < 1e-3, "{c:?}");
    }

    #[test]
    fn nothing_pasted_or_no_light_passes_the_photo_through() {
        let (w, h) = (40, 30);
        let (k, floor, slab, alpha) = floor_and_slab(w, h);
        let photo = Image::from_fn(w, h, |x, y| [x as f32 * 0.01, y as f32 * 0.02, 0.3]);
        let zero = Image::filled(w, h, 0.0f32);
        let mut reg = Registry::new();
        register(&mut reg).unwrap();
        let node = reg.get("Relight").unwrap();
        let test_ctx = crate::test_util::TestCtx::new("relight");
        let ctx = test_ctx.ctx();
        let run = |a: &Mask, vpls: &[Vpl]| {
            let mut inputs = Inputs::new();
            inputs.insert("photo", Value::from(photo.clone()));
            inputs.insert("depth", Value::from(floor.clone()));
            inputs.insert("pasted_color", Value::from(photo.clone()));
            inputs.insert("pasted_depth", Value::from(slab.clone()));
            inputs.insert("alpha", Value::Mask(Arc::new(a.clone())));
            inputs.insert("intrinsics", Value::from(k));
            inputs.insert("vpls", Value::from(crate::vpl::to_cloud(vpls)));
            node.eval(&ctx, &inputs, &RelightParams::default().to_values())
                .unwrap()
        };
        let out = run(&zero, &overhead());
        assert!(
            out.passthrough
                .as_deref()
                .unwrap()
                .contains("nothing pasted")
        );
        assert_eq!(out.values["color"], Value::from(photo.clone()));
        let out = run(&alpha, &[]);
        assert!(out.passthrough.as_deref().unwrap().contains("no VPL"));
        assert_eq!(out.values["color"], Value::from(photo.clone()));
        let black = vec![Vpl {
            direction: [0.0, -1.0, 0.0],
            power: [0.0; 3],
        }];
        let out = run(&alpha, &black);
        assert!(out.passthrough.is_some());
        // from a black environment map, through VplSample
        let none = crate::vpl::sample_vpls(&Image::filled(8, 4, [0.0f32; 3]), &Default::default());
        assert!(run(&alpha, &none).passthrough.is_some());
        // and it renders when both are there, finite everywhere
        let out = run(&alpha, &overhead());
        assert!(out.passthrough.is_none());
        match &out.values["color"] {
            Value::Color(c) => assert!(c.as_slice().iter().flatten().all(|v| v.is_finite())),
            other => panic!("{other:?}"),
        }
    }

    /// The same result, bit for bit, on 1 and 2 threads; and the uniform
    /// density is a valid choice, an unknown one an error.
    #[test]
    fn thread_count_does_not_change_the_result() {
        let (w, h) = (80, 60);
        let (k, floor, slab, alpha) = floor_and_slab(w, h);
        let photo = floor.map(|z| if *z > 0.0 { [0.5f32; 3] } else { [0.0; 3] });
        let pasted_color = Image::filled(w, h, [0.3f32, 0.6, 0.2]);
        let inp = RelightInputs {
            photo: &photo,
            depth: &floor,
            normals: None,
            albedo: None,
            pasted_color: &pasted_color,
            pasted_depth: &slab,
            alpha: &alpha,
            k: &k,
        };
        let vpls: Vec<Vpl> = (0..24)
            .map(|j| {
                let a = j as f32 * 0.7;
                Vpl {
                    direction: [0.5 * a.cos(), -1.0, 0.5 * a.sin()],
                    power: [0.1, 0.2, 0.05 * (j % 3) as f32],
                }
            })
            .collect();
        let p = RelightParams {
            ism_points: 3000,
            ism_resolution: 48,
            bounce_vpls: 32,
            ..Default::default()
        };
        let run = |threads: usize, p: &RelightParams| {
            crate::test_util::with_threads(threads, || relight(&inp, &vpls, p).unwrap().unwrap())
        };
        let one = run(1, &p);
        assert_eq!(one, run(2, &p));
        assert_eq!(one, run(3, &p));
        // with the bounce shadowed by paraboloid maps too
        let shadowed = RelightParams {
            bounce_shadows: true,
            ..p.clone()
        };
        let one = run(1, &shadowed);
        assert_eq!(one, run(3, &shadowed));
        let uni = RelightParams {
            importance: "uniform".into(),
            ..p.clone()
        };
        assert!(
            run(2, &uni)
                .color
                .as_slice()
                .iter()
                .flatten()
                .all(|v| v.is_finite())
        );
        let bad = RelightParams {
            importance: "nearest".into(),
            ..p
        };
        assert!(relight(&inp, &vpls, &bad).is_err());
    }

    /// A bounce VPL at (or touching) the receiver: finite, and no
    /// contribution exceeds its clamp `L a / r_clamp²`.
    #[test]
    fn a_vpl_inside_a_surface_is_finite_and_clamped() {
        let l = [2.0, 1.0, 0.5];
        let n = DVec3::NEG_Y;
        let x = DVec3::new(0.0, 0.4, 2.0);
        let r2_min = 0.05f64 * 0.05;
        let bound = |c: usize| l[c] / r2_min;
        for q in [
            x,
            x + DVec3::new(0.0, -1e-12, 0.0),
            x + DVec3::new(1e-4, -1e-4, 0.0),
            x + DVec3::new(0.0, -0.01, 0.0),
        ] {
            let b = bounce_at(x, n, &[(q, DVec3::Y, l)], r2_min);
            for c in 0..3 {
                assert!(
                    b[c].is_finite() && b[c] >= 0.0 && b[c] <= bound(c) + 1e-9,
                    "{q}: {b:?}"
                );
            }
        }
        assert_eq!(bounce_at(x, n, &[(x, DVec3::Y, l)], r2_min), [0.0; 3]);
        // far away it is the unclamped 1/r² law
        let q = x + DVec3::new(0.0, -1.0, 0.0);
        let b = bounce_at(x, n, &[(q, DVec3::Y, l)], r2_min);
        assert!((b[0] - 2.0).abs() < 1e-12);
    }
}
