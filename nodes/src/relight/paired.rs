//! `Relight`: adaptive differential rendering of a pasted object into the
//! target photo (3d-editing §IV.A, eq. 5 and 6): the object casts shadows on
//! the scene and sends bounced light, and the photo changes only by the
//! difference the object makes.
//!
//! # What is rendered
//!
//! With the directional VPLs `(ω_k, Φ_k)` of [`crate::relight::vpl`] and the paired
//! imperfect shadow maps of [`crate::relight::ism`] (visibility `V^t_k` without the
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
//! **Units.** A pixel value is radiance (what a camera measures, and what
//! [`crate::sim::pathtrace`] renders); the VPLs carry irradiance
//! (`Φ_k = L ΔΩ` of the map), so `E` is an irradiance and a Lambertian
//! surface of reflectance `r` shows `P = r E / π`. The **albedo** of this
//! module is `ρ = P / E = r / π`, the photo's value per unit irradiance.
//!
//! **Albedo of the target.** `ρ_t` is the `albedo` input when given (in
//! those units: the SyntheticScene's albedo output is, since its shader
//! writes `albedo × irradiance`), else estimated as
//! `P / (E^t + E_ind)` with `E_ind` the scene's own bounce (below, "Shadows
//! with their fill light"); where that is below
//! `min_shading_rel * E_ref` (`E_ref = Σ_k lum(Φ_k)`, the guard of the
//! division) the albedo is unknown and taken as 0: the pixel keeps the
//! photo.
//!
//! **The object's own shading.** The object's pasted colour `P_o` is
//! radiance it sent where it was captured. There it received
//! `E_cap = Σ_k Φ^cap_k max(0, n·ω_k) V^o_k`: the capture map's VPLs (the
//! `capture_vpls` input in the scene-cached and ray-cast schemes; this one
//! takes the target's and refuses the input) with only its own shadows
//! (`V^o`; its capture surroundings are unknown, so nothing bounced onto
//! it there). In the target it receives `E^{s+t} + B_s`: the target's VPLs
//! with the scene's and its own shadows, and the scene's bounce `B_s`
//! (below). It shows `P_o (E^{s+t} + B_s) / max(E_cap, c_floor)`, with
//! `c_floor = min_capture_rel * E_cap,ref`, the capture VPLs' total
//! (the target's `E_ref` without them) (a face the capture map barely lit
//! carries little but noise of its colour, which an unbounded ratio would
//! amplify; with few VPLs some normals get none at all): with the
//! same map on both sides and nothing around it the ratio is 1, and the
//! object gains only what the target adds or blocks (brighter beside a
//! sunlit floor or wall, darker in the scene's shadow). In this (`paired`)
//! scheme `V^o` alone is not at hand: `E_cap` counts a VPL where
//! `V^{s+t}` holds or the scene blocks it (`V^t = 0`, where the object's
//! own visibility is unknown and taken as 1).
//!
//! **Bounce from the scene (one, scene to object).** Up to `scene_vpls`
//! target pixels become secondary point VPLs (drawn with probability
//! `∝ area / distance²` to the object centre, weighted by the inverse
//! pdf). The scene is Lambertian and its radiance is read off the photo,
//! `L = P`, so no albedo or irradiance of the scene is needed; each keeps
//! the fraction `E^{s+t} / E^t` of its direct light (the floor in the
//! object's shadow bounces less). **The support plane** (`extend_support`):
//! the photo shows only part of the floor the object stands on, and a
//! face looking sideways receives much of its bounce from floor outside
//! the frame; that plane (fitted to the up-facing target surfaces around
//! the object, with their mean radiance) is extended to
//! `support_radius_rel` object radii and sampled where the photo does not
//! show it ([`crate::relight::shading`]'s `support_vpls`). They add `B_s`
//! (same clamped formula as below) to the object's irradiance. It is
//! shadowed only with `bounce_shadows` (below).
//!
//! **Bounce (one, object to scene).** Up to `bounce_vpls` object pixels
//! (stratified) become secondary point VPLs: a surface element of area `a_j`
//! with outgoing radiance `L_j` (its shaded colour) gives a receiver
//! `B(x) = Σ_j L_j a_j max(0, n_j·u) max(0, -n·u) / max(r², r_clamp²)` with
//! `u` the unit vector from `x` to the VPL and `r = |x_j - x|`. The
//! **clamp** `r >= clamp_distance_m` bounds every contribution (no fireflies
//! from a VPL touching a surface) at the price of a **bias**: the bounce is
//! too dark within about `clamp_distance_m` of the object. A VPL exactly at a
//! receiver (`r < 1e-9` m) has no direction and contributes 0. Only the
//! object's visible surface bounces (its back's radiance is unknown).
//!
//! **Shadows with their fill light** (`fill_light`). A shadow in a photo
//! is not black: the scene's bounce still reaches it. The differential
//! therefore removes only what the object blocks, direct and bounced:
//! with `E_ind(x)` the scene's bounce at `x` (the same secondary VPLs) and
//! `B_blk(x)` the part of it whose path to `x` crosses the object's closed
//! volume ([`crate::relight::closure::ObjectVolume`]),
//! `I_{s+t} - I_t = ρ_t (E^{s+t} - E^t + B - B_blk)` and `ρ_t` comes from
//! `P / (E^t + E_ind)`: a shadow keeps the photo's share of bounced light
//! instead of losing it in proportion to the direct light.
//!
//! **The unseen back** (`close_back`): the object's shadow maps and its
//! blocking volume use its visible surface closed by a mirrored back
//! ([`crate::relight::closure`]), so a light behind the object (from in
//! front of the camera) casts the shadow of a solid.
//!
//! **Bounce shadows** (`bounce_shadows`, off by default). Each point VPL of
//! either bounce gets a paraboloid ISM of its hemisphere
//! ([`crate::relight::ism::ParaboloidMap`], the ISM paper's maps for VPLs at finite
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
//! and the photo's pixels are kept bit for bit. With nothing pasted (no
//! valid pasted depth; an object the scene hides whole, `α = 0` over its
//! depth, still casts its shadow) or no VPL carrying energy, the node passes
//! the photo through and says why.
//!
//! # Visibility schemes (the `visibility` parameter)
//!
//! - `"scene_cached"` (default, [`crate::relight::scene_cached`]): the scene's maps
//!   (uniform density) and `E^t` are built once per photo and VPL set and
//!   kept in a small memo; each run builds only maps of the object alone
//!   and uses `V^{s+t} = V^t ∧ V^o`. Moving the object costs ~50 ms at
//!   640x480 with 256 VPLs (`docs/relight.md`), and the result is more
//!   accurate than the paired maps at the same budget (the object's maps
//!   have texels a fraction of its size).
//! - `"paired"` (this module's [`relight`]): the paper's scheme above, both
//!   maps rebuilt from eq. 6 samples on every run.
//! - `"raycast"` ([`crate::relight::reference`]): exact shadow rays through
//!   the meshes of the target and the object, the reference of the others.

use depthgraph_graph::prelude::*;
use depthgraph_graph::value::Rgb;
use glam::DVec3;
use rayon::prelude::*;

use crate::relight::ism::{IsmParams, PointSet, ShadowMap, build_pair_in, windows};
use crate::relight::vpl::Vpl;

use crate::relight::fill::scene_fill;
use crate::relight::shading::{
    BOUNCE_SPLAT_SCALE, Cone, Importance, PointVplShadows, RelightInputs, RelightParams, Relit,
    Surf, centre_and_radius, clean_alpha, composite, lit_vpls, object_bounce_vpls, object_radiance,
    pixel_areas, received, scene_bounce_vpls, support_vpls, target_albedo, target_surfaces,
};

/// Irradiance `(E^t, E^{s+t}, E_cap)` per surface (module docs).
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
                    for ((s, r), (et, est, ecap)) in chunk.iter().zip(&radii).zip(acc.iter_mut()) {
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
                        // the capture side: V^o = V^{s+t} where the scene
                        // lets the VPL through, unknown (1) where it does not
                        let vo = vst || !vt;
                        for ch in 0..3 {
                            let e = power[ch] * cos;
                            if vo {
                                ecap[ch] += e;
                            }
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
    let near_object = p.importance == Importance::NearObject;
    let (w, h) = (k.width, k.height);
    let alpha = clean_alpha(inp.alpha, inp.pasted_depth);
    let (vpls, dirs, e_ref) = lit_vpls(vpls);
    // an object hidden whole (alpha 0 after the depth test) still casts
    // its shadow: nothing to do only when nothing was pasted at all
    if vpls.is_empty()
        || !e_ref.is_finite()
        || crate::relight::shading::nothing_pasted(inp.pasted_depth)
    {
        return Ok(None);
    }
    let e_floor = p.min_shading_rel * e_ref;
    // the capture side's floor (module docs of `paired`)
    let cap_floor = p.min_capture_rel * e_ref;

    // ---- surfaces: target and object, per pixel
    let target = target_surfaces(inp.depth, inp.normals, k);
    let object: Vec<Option<Surf>> = (0..w * h)
        .map(|i| (alpha[i] > 0.0).then(|| inp.object_surface(i)))
        .collect();
    // the whole object, hidden parts included (they cast shadows and
    // block fill light as the maps see them): its centre and reach
    let unproject_valid = |d: &DepthMap| -> Vec<DVec3> {
        (0..w * h)
            .filter_map(|i| {
                let z = d.as_slice()[i];
                DepthMap::is_valid(z)
                    .then(|| k.unproject((i % w) as f64 + 0.5, (i / w) as f64 + 0.5, f64::from(z)))
            })
            .collect()
    };
    let mut obj_pts = unproject_valid(inp.pasted_depth);
    // the closed object (its back mirrored, `close_back`): shadows only
    let back = inp.back_depth(p);
    if let Some(b) = &back {
        obj_pts.extend(unproject_valid(b));
    }
    // at least one valid pasted depth (checked above)
    let (c, radius) = centre_and_radius(&obj_pts);
    let volume = inp.volume(back.as_ref(), c, radius);

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
                    // near: the bounce, or the fill light the object blocks
                    ((p.bounce_vpls > 0 || (p.fill_light && p.scene_vpls > 0))
                        && (s.pos - c).length() <= bounce_reach)
                        || {
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
    let mut layers = vec![(inp.depth, false), (inp.pasted_depth, true)];
    if let Some(b) = &back {
        layers.push((b, true));
    }
    let set = PointSet::new(&layers, k, &centres, p.min_distance_m);
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

    // irradiance at surfaces: (without object, with object, capture side)
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
        let mut v = scene_bounce_vpls(&target, &areas, inp.photo, c, p);
        v.extend(support_vpls(&target, inp.photo, k, inp.depth, c, radius, p));
        v
    } else {
        Vec::new()
    };
    let fill = p.fill_light && !scene_vpls.is_empty();
    let bounce_samples = [crate::relight::ism::ParaboloidSamples {
        set: &set,
        m: p.bounce_ism_points,
        radius_scale: BOUNCE_SPLAT_SCALE,
    }];
    let scene_shadows = PointVplShadows::new(&scene_vpls, &bounce_samples, p, p.seed ^ 0x5EC0);
    let obj_rad: Vec<Rgb> = obj_idx
        .par_iter()
        .zip(obj_irr.par_iter())
        .map(|(&i, &(_, est, ecap))| {
            let pc = inp.pasted_color.as_slice()[i];
            let bs = match &object[i] {
                Some(s) if !scene_vpls.is_empty() => {
                    let r = BOUNCE_SPLAT_SCALE * set.splat_radius(s.pos, p.bounce_ism_points);
                    scene_shadows.bounce(s.pos, s.n, r, scene_vpls.iter().enumerate(), r2_min)
                }
                _ => [0.0; 3],
            };
            object_radiance(pc, received(est, bs), ecap, cap_floor)
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
            .is_some_and(|s| (!bounce.is_empty() || fill) && (s.pos - c).length() <= bounce_reach);
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
                // the scene's own bounce here, and what of it the object blocks
                let (e_ind, blocked) = if fill && (s.pos - c).length() <= bounce_reach {
                    scene_fill(s.pos, s.n, &scene_vpls, r2_min, &volume)
                } else {
                    ([0.0; 3], [0.0; 3])
                };
                let given = inp.albedo.map(|a| a.as_slice()[i]);
                let e_all = std::array::from_fn(|ch| et[ch] + e_ind[ch]);
                let rho = target_albedo(given, pp, e_all, e_floor);
                for ch in 0..3 {
                    diff[ch] = rho[ch] * (est[ch] + b[ch] - et[ch] - blocked[ch]);
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
    Ok(Some(Relit {
        color: Image::from_vec(w, h, color)?,
        region: Image::from_vec(
            w,
            h,
            in_region
                .iter()
                .map(|r| if *r { 1.0 } else { 0.0 })
                .collect(),
        )?,
        difference: Image::from_vec(w, h, difference)?,
    }))
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use super::*;
    use crate::relight::ism::pixel_area;
    use crate::relight::node::register;
    use crate::relight::shading::bounce_at;
    use crate::test_support::relight::{floor_and_slab, overhead, slab_shadow_is_analytic};

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
            capture_vpls: None,
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
                let l = photo.as_slice()[i].map(|v| f64::from(v) * a);
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

    /// A slab above a floor under one overhead VPL: the floor under it is
    /// dark (ray-cast reference: the vertical ray from the floor point hits
    /// the slab), every other floor pixel is unchanged, bit for bit where the
    /// node did not render; outside the region the difference is exactly 0.
    #[test]
    fn a_slab_casts_its_analytic_shadow_and_nothing_else_changes() {
        slab_shadow_is_analytic(&|inp, vpls, p| relight(inp, vpls, p).unwrap().unwrap(), 0.0);
    }

    #[test]
    fn nothing_pasted_or_no_light_passes_the_photo_through() {
        let (w, h) = (40, 30);
        let (k, floor, slab, alpha) = floor_and_slab(w, h);
        let photo = ColorImage::from_fn(w, h, |x, y| [x as f32 * 0.01, y as f32 * 0.02, 0.3]);
        let zero = Image::filled(w, h, 0.0f32);
        let mut reg = Registry::new();
        register(&mut reg).unwrap();
        let node = reg.get("Relight").unwrap();
        let test_ctx = crate::test_support::TestCtx::new("relight");
        let ctx = test_ctx.ctx();
        // the node on these inputs, capture VPLs when given, parameters `p`
        let eval = |a: &Mask,
                    pasted: &DepthMap,
                    vpls: &[Vpl],
                    capture: Option<&[Vpl]>,
                    p: &RelightParams| {
            let mut inputs = Inputs::new();
            inputs.insert("photo", Value::from(photo.clone()));
            inputs.insert("depth", Value::from(floor.clone()));
            inputs.insert("pasted_color", Value::from(photo.clone()));
            inputs.insert("pasted_depth", Value::from(pasted.clone()));
            inputs.insert("alpha", Value::Mask(Arc::new(a.clone())));
            inputs.insert("intrinsics", Value::from(k));
            inputs.insert("vpls", Value::from(vpls.to_vec()));
            if let Some(c) = capture {
                inputs.insert("capture_vpls", Value::from(c.to_vec()));
            }
            node.eval(&ctx, &inputs, &p.to_values())
        };
        let run_with = |a: &Mask, pasted: &DepthMap, vpls: &[Vpl]| {
            eval(a, pasted, vpls, None, &RelightParams::default()).unwrap()
        };
        let run = |a: &Mask, vpls: &[Vpl]| run_with(a, &slab, vpls);
        // no pasted depth: nothing pasted
        let out = run_with(&zero, &DepthMap::filled(w, h, 0.0), &overhead());
        assert!(
            out.passthrough
                .as_deref()
                .unwrap()
                .contains("nothing pasted")
        );
        assert_eq!(out.values["color"], Value::from(photo.clone()));
        // (an object hidden whole, alpha 0 over a pasted depth, is pasted:
        // it still casts its shadow)
        assert!(run(&zero, &overhead()).passthrough.is_none());
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
        let none = crate::relight::vpl::sample_vpls(
            &Image::filled(8, 4, [0.0f32; 3]),
            &Default::default(),
        );
        assert!(run(&alpha, &none).passthrough.is_some());
        // and it renders when both are there, finite everywhere
        let out = run(&alpha, &overhead());
        assert!(out.passthrough.is_none());
        match &out.values["color"] {
            Value::Color(c) => assert!(c.as_slice().iter().flatten().all(|v| v.is_finite())),
            other => panic!("{other:?}"),
        }
        // this scheme takes no capture VPLs: refused, not ignored
        let paired = RelightParams {
            visibility: crate::relight::shading::Visibility::Paired,
            ..Default::default()
        };
        let lights = overhead();
        let e = eval(&alpha, &slab, &lights, Some(&lights), &paired).unwrap_err();
        assert!(
            matches!(&e, NodeError::Param { param, .. } if param == "visibility"),
            "{e}"
        );
        // the default scheme takes them
        assert!(
            eval(
                &alpha,
                &slab,
                &lights,
                Some(&lights),
                &RelightParams::default()
            )
            .is_ok()
        );
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
            capture_vpls: None,
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
            crate::test_support::with_threads(threads, || relight(&inp, &vpls, p).unwrap().unwrap())
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
            importance: Importance::Uniform,
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
        // a name that is no importance is refused before any run
        let mut bad = p.to_values();
        bad.insert("importance".into(), ParamValue::Text("nearest".into()));
        assert!(RelightParams::from_values(&bad).is_err());
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
