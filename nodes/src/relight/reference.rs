//! The reference of `Relight`: the same differential composite (the model
//! of [`crate::relight::paired`]: directional VPLs, Lambertian surfaces, one bounce
//! each way with the same clamp and reach) with **exact visibility**, shadow
//! rays cast against the meshes of the target and of the pasted object
//! ([`crate::depth::mesh::depth_to_mesh`], [`crate::relight::raycast`]) instead of imperfect
//! shadow maps. It is slow (a ray per pixel and VPL) and meant for
//! benchmarks and tests: it renders only the pixels it is asked for.
//!
//! A shadow ray leaves a surface point `x` with normal `n` from
//! `x + ε n`, and hits count beyond `t > ε`, with `ε = 1e-3 |x|` (1 mm per
//! metre of distance from the camera: above the meshes' own faceting, below
//! any contact the scenes have).
//!
//! The meshes drop cells across depth jumps of more than 10 % (as
//! [`crate::depth::mesh`] does at discontinuities): a surface seen at a grazing
//! angle at a low resolution, whose neighbouring pixels differ by more,
//! loses its cells here (and casts no shadow), where the shadow maps'
//! splats keep it. Use the reference at resolutions where the surfaces of
//! interest are sampled finer than that.
//!
//! The differential on the target surface is evaluated as
//! `-Σ_k Φ_k max(0, n·ω_k) V^t_k (1 - V^o_k)` (a ray blocked by the object
//! and not by the scene), which is `E^{s+t} - E^t` exactly when
//! `V^{s+t} = V^t ∧ V^o`, true of rays against a union of meshes.

use depthgraph_graph::prelude::*;
use depthgraph_graph::value::Rgb;
use glam::DVec3;
use rayon::prelude::*;

use crate::depth::mesh::{MeshParams, depth_to_mesh};
use crate::relight::fill::scene_fill;
use crate::relight::raycast::Bvh;
use crate::relight::shading::{
    Cone, RelightInputs, RelightParams, Relit, Surf, bounce_sum, capture_ref, centre_and_radius,
    clean_alpha, composite, lit_vpls, nothing_pasted, object_bounce_vpls, object_radiance,
    pixel_areas, received, scene_bounce_vpls, support_vpls, target_albedo, target_surfaces,
};
use crate::relight::vpl::Vpl;

/// Offset of shadow rays, per metre of distance from the camera.
/// (The reference renders the whole image as `Relight`'s
/// `visibility: "raycast"`, [`relight_reference_image`].)
pub const RAY_EPS_REL: f64 = 1e-3;

/// The composite `I_m` (eq. 5) and the difference `I_{s+t} - I_t` at the
/// pixels `pixels` (indices `y w + x`), with ray-cast visibility (module
/// docs). `Ok(None)` when there is nothing to relight, as for
/// [`crate::relight::paired::relight`]. Out-of-range pixels are an error. Only the
/// VPLs whose ray can pass the object are traced (the cone test of
/// [`crate::relight::paired`], exact here), and pixels the object cannot change are
/// the photo.
pub fn relight_reference(
    inp: &RelightInputs,
    vpls: &[Vpl],
    p: &RelightParams,
    pixels: &[usize],
) -> Result<Option<Vec<(Rgb, Rgb)>>, NodeError> {
    let k = inp.k;
    inp.check()?;
    let (w, h) = (k.width, k.height);
    if let Some(bad) = pixels.iter().find(|&&i| i >= w * h) {
        return Err(NodeError::Invalid(format!(
            "pixel {bad} is outside the {w}x{h} image"
        )));
    }
    let alpha = clean_alpha(inp.alpha, inp.pasted_depth);
    let (vpls, dirs, e_ref) = lit_vpls(vpls);
    let capture = inp.capture_vpls.map(|cv| {
        let (v, d, _) = lit_vpls(cv);
        (v, d)
    });
    // an object hidden whole still casts its shadow (`nothing_pasted`)
    if vpls.is_empty() || !e_ref.is_finite() || nothing_pasted(inp.pasted_depth) {
        return Ok(None);
    }
    let e_floor = p.min_shading_rel * e_ref;
    // the capture side's floor (module docs of `paired`)
    let cap_floor = p.min_capture_rel * capture_ref(inp.capture_vpls, e_ref)?;
    let r2_min = p.clamp_distance_m * p.clamp_distance_m;
    let mp = MeshParams { max_edge_rel: 0.1 };
    let scene_bvh = Bvh::new(&depth_to_mesh(inp.depth, k, None, &mp)?);
    let obj_bvh = Bvh::new(&depth_to_mesh(inp.pasted_depth, k, None, &mp)?);
    // the closed back (`close_back`): its mesh blocks light too
    let back = inp.back_depth(p);
    let back_bvh = match &back {
        Some(b) => Some(Bvh::new(&depth_to_mesh(b, k, None, &mp)?)),
        None => None,
    };
    let target = target_surfaces(inp.depth, inp.normals, k);
    let layers = [Some(inp.pasted_depth), back.as_ref()];
    let obj_pts: Vec<DVec3> = layers
        .iter()
        .flatten()
        .flat_map(|d| {
            (0..w * h)
                .filter(|&i| DepthMap::is_valid(d.as_slice()[i]))
                .map(|i| {
                    let z = d.as_slice()[i] as f64;
                    k.unproject((i % w) as f64 + 0.5, (i / w) as f64 + 0.5, z)
                })
        })
        .collect();
    let (c, radius) = centre_and_radius(&obj_pts);
    let volume = inp.volume(back.as_ref(), c, radius);
    let bounce_reach = p.bounce_radius_rel * radius;
    // a shadow ray from (x, n) towards d
    let ray = |x: DVec3, n: DVec3, d: DVec3| {
        let eps = RAY_EPS_REL * x.length().max(1e-3);
        (x + n * eps, d, eps)
    };
    let free = |bvh: &Bvh, x: DVec3, n: DVec3, d: DVec3| {
        let (o, d, eps) = ray(x, n, d);
        !bvh.occluded(o, d, eps, f64::INFINITY)
    };
    // the object, closed: its front and its back (for the scene's
    // receivers; the object's own surfaces are shadowed by its front
    // alone: near the rim the estimated back may stand in front of them)
    let obj_free = |x: DVec3, n: DVec3, d: DVec3| {
        free(&obj_bvh, x, n, d) && back_bvh.as_ref().is_none_or(|b| free(b, x, n, d))
    };
    // the segment from (x, n) to a point VPL at q on a surface (bounce
    // shadows): stops short of q by the same relative offset
    let sees = |x: DVec3, n: DVec3, q: DVec3| {
        if !p.bounce_shadows {
            return true;
        }
        let v = q - x;
        let len = v.length();
        if len.is_nan() || len <= 0.0 {
            return true;
        }
        // guard: len > 0
        let (o, d, eps) = ray(x, n, v / len);
        let end = len - RAY_EPS_REL * q.length().max(1e-3);
        end <= eps
            || !(scene_bvh.occluded(o, d, eps, end)
                || obj_bvh.occluded(o, d, eps, end)
                || back_bvh
                    .as_ref()
                    .is_some_and(|b| b.occluded(o, d, eps, end)))
    };

    // ---- the object: exact shading where it is needed (the bounce VPLs
    // and the asked pixels)
    let obj_idx: Vec<usize> = (0..w * h).filter(|&i| alpha[i] > 0.0).collect();
    let areas = pixel_areas(inp.depth, k);
    let mut scene_vpls = scene_bounce_vpls(&target, &areas, inp.photo, c, p);
    scene_vpls.extend(support_vpls(&target, inp.photo, k, inp.depth, c, radius, p));
    let fill = p.fill_light && !scene_vpls.is_empty();
    let pasted = inp.pasted_color.as_slice();
    let shade_object = |i: usize| -> Rgb {
        let Surf { pos, n } = inp.object_surface(i);
        let (mut est, mut ecap) = ([0.0f64; 3], [0.0f64; 3]);
        for (v, d) in vpls.iter().zip(&dirs) {
            let cos = n.dot(*d);
            if cos <= 0.0 {
                continue;
            }
            if !free(&obj_bvh, pos, n, *d) {
                continue;
            }
            let vis = free(&scene_bvh, pos, n, *d);
            for ch in 0..3 {
                let e = f64::from(v.power[ch]) * cos;
                ecap[ch] += e;
                if vis {
                    est[ch] += e;
                }
            }
        }
        if let Some(cv) = &capture {
            ecap = [0.0; 3];
            for (v, d) in cv.0.iter().zip(&cv.1) {
                let cos = n.dot(*d);
                if cos > 0.0 && free(&obj_bvh, pos, n, *d) {
                    for (e, pw) in ecap.iter_mut().zip(v.power) {
                        *e += f64::from(pw) * cos;
                    }
                }
            }
        }
        let bs = bounce_sum(pos, n, scene_vpls.iter().enumerate(), r2_min, |j| {
            sees(pos, n, scene_vpls[j].0)
        });
        object_radiance(pasted[i], received(est, bs), ecap, cap_floor)
    };
    let bounce = object_bounce_vpls(
        &obj_idx,
        &|j| {
            let s = inp.object_surface(obj_idx[j]);
            Some((s.pos, s.n))
        },
        &|j| shade_object(obj_idx[j]),
        inp.pasted_depth,
        k,
        p.bounce_vpls,
    );

    // ---- the asked pixels
    let photo = inp.photo.as_slice();
    let out = pixels
        .par_iter()
        .map(|&i| {
            let a = alpha[i];
            let obj = if a > 0.0 { shade_object(i) } else { [0.0; 3] };
            let mut diff = [0.0f64; 3];
            if let Some(s) = &target[i] {
                // The object's triangles lie within `radius` of c (their
                // vertices do): a ray passing farther, even from the
                // offset origin, misses them.
                let eps = RAY_EPS_REL * s.pos.length().max(1e-3);
                let cone = Cone::new(s.pos, c, radius + 2.0 * eps);
                let (mut de, mut hit) = ([0.0f64; 3], false);
                for (v, d) in vpls.iter().zip(&dirs) {
                    let cos = s.n.dot(*d);
                    if cos <= 0.0 || !cone.contains(*d) {
                        continue;
                    }
                    if !obj_free(s.pos, s.n, *d) && free(&scene_bvh, s.pos, s.n, *d) {
                        hit = true;
                        for (e, pw) in de.iter_mut().zip(v.power) {
                            *e += f64::from(pw) * cos;
                        }
                    }
                }
                let near = (!bounce.is_empty() || fill) && (s.pos - c).length() <= bounce_reach;
                if hit || near {
                    let b = if near {
                        bounce_sum(s.pos, s.n, bounce.iter().enumerate(), r2_min, |j| {
                            sees(s.pos, s.n, bounce[j].0)
                        })
                    } else {
                        [0.0; 3]
                    };
                    let (e_ind, blocked) = if fill && near {
                        scene_fill(s.pos, s.n, &scene_vpls, r2_min, &volume)
                    } else {
                        ([0.0; 3], [0.0; 3])
                    };
                    let given = inp.albedo.map(|al| al.as_slice()[i]);
                    let mut et = e_ind;
                    if given.is_none() {
                        for (v, d) in vpls.iter().zip(&dirs) {
                            let cos = s.n.dot(*d);
                            if cos > 0.0 && free(&scene_bvh, s.pos, s.n, *d) {
                                for (e, pw) in et.iter_mut().zip(v.power) {
                                    *e += f64::from(pw) * cos;
                                }
                            }
                        }
                    }
                    let rho = target_albedo(given, photo[i], et, e_floor);
                    diff = std::array::from_fn(|ch| rho[ch] * (b[ch] - de[ch] - blocked[ch]));
                }
            }
            (composite(photo[i], a, obj, diff), diff.map(|v| v as f32))
        })
        .collect();
    Ok(Some(out))
}

/// [`relight_reference`] over the whole image, as a [`Relit`]: the region
/// is where the composite differs from the photo or the object is seen.
pub fn relight_reference_image(
    inp: &RelightInputs,
    vpls: &[Vpl],
    p: &RelightParams,
) -> Result<Option<Relit>, NodeError> {
    let (w, h) = (inp.k.width, inp.k.height);
    let all: Vec<usize> = (0..w * h).collect();
    let Some(px) = relight_reference(inp, vpls, p, &all)? else {
        return Ok(None);
    };
    let photo = inp.photo.as_slice();
    // the alpha the render used (none where the pasted depth has a hole)
    let alpha = clean_alpha(inp.alpha, inp.pasted_depth);
    let region: Vec<f32> = px
        .iter()
        .enumerate()
        .map(|(i, (c, _))| {
            let changed = *c != photo[i] || alpha[i] > 0.0;
            if changed { 1.0 } else { 0.0 }
        })
        .collect();
    let (color, difference): (Vec<Rgb>, Vec<Rgb>) = px.into_iter().unzip();
    Ok(Some(Relit {
        color: Image::from_vec(w, h, color)?,
        region: Image::from_vec(w, h, region)?,
        difference: Image::from_vec(w, h, difference)?,
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The slab under an overhead light: the reference darkens exactly the
    /// floor below it (the analytic shadow, to a pixel's footprint) and
    /// keeps every other floor pixel; the ISM render agrees with it on all
    /// pixels away from the shadow's outline.
    #[test]
    fn the_reference_casts_the_analytic_shadow_and_the_isms_match_it() {
        let (w, h) = (160, 120);
        let sc = crate::test_support::relight::SlabScene::new(w, h, 0.0);
        let (k, floor, alpha, photo) = (sc.k, &sc.floor, &sc.alpha, &sc.photo);
        let inp = sc.inputs(true);
        let p = RelightParams {
            ism_points: 20000,
            ism_resolution: 128,
            bounce_vpls: 0,
            scene_vpls: 0,
            ..Default::default()
        };
        let vpls = crate::test_support::relight::overhead();
        let all: Vec<usize> = (0..w * h).collect();
        let r = relight_reference(&inp, &vpls, &p, &all).unwrap().unwrap();
        let ism = crate::relight::paired::relight(&inp, &vpls, &p)
            .unwrap()
            .unwrap();
        let (mut shadowed, mut agree, mut edge) = (0, 0, 0);
        for (i, &(c, _)) in r.iter().enumerate() {
            let z = *floor.get(i % w, i / w);
            if alpha.as_slice()[i] > 0.0 || z <= 0.0 {
                continue;
            }
            let q = k.unproject((i % w) as f64 + 0.5, (i / w) as f64 + 0.5, z as f64);
            let under = q.x.abs() <= 0.2 && (1.6..=2.4).contains(&q.z);
            // The slab's mesh spans its pixel centres: its outline is
            // known to a pixel's footprint on it, z / fx across and
            // z² / (0.2 fy) in depth (seen 0.2 m below the camera).
            let foot_z = |z: f64| z * z / (0.2 * k.fy) + 0.01;
            let near = (q.x.abs() - 0.2).abs() < 2.4 / k.fx + 0.01
                || (q.z - 1.6).abs() < foot_z(1.6)
                || (q.z - 2.4).abs() < foot_z(2.4);
            if near {
                edge += 1;
                continue;
            }
            if under {
                shadowed += 1;
                assert!(c[0] < 1e-6, "shadowed floor at {q}: {c:?}");
            } else {
                assert_eq!(c, photo.as_slice()[i], "lit floor at {q}");
            }
            let far_from_edge = (q.x.abs() - 0.2).abs() >= 0.15
                && (q.z - 1.6).abs() >= 0.15
                && (q.z - 2.4).abs() >= 0.15;
            if far_from_edge {
                assert_eq!(ism.color.as_slice()[i], c, "ISM and rays differ at {q}");
                agree += 1;
            }
        }
        assert!(shadowed > 50 && agree > 4000, "{shadowed} {agree} {edge}");
        // out-of-range pixels are an error
        assert!(relight_reference(&inp, &vpls, &p, &[w * h]).is_err());
        // the whole image: the same pixels, the photo kept outside the region
        let img = relight_reference_image(&inp, &vpls, &p).unwrap().unwrap();
        for (i, (c, d)) in r.iter().enumerate() {
            assert_eq!(img.color.as_slice()[i], *c);
            assert_eq!(img.difference.as_slice()[i], *d);
            if img.region.as_slice()[i] == 0.0 {
                assert_eq!(*c, photo.as_slice()[i]);
            }
        }
        assert!(img.region.as_slice().iter().filter(|v| **v > 0.0).count() > shadowed);
    }

    /// The node renders the reference with `visibility: "raycast"` (the
    /// shadow under the slab), and refuses an unknown scheme.
    #[test]
    fn the_node_offers_the_reference_as_a_visibility() {
        use std::sync::Arc;
        let (w, h) = (160, 120);
        let sc = crate::test_support::relight::SlabScene::new(w, h, 0.0);
        let mut reg = Registry::new();
        crate::relight::node::register(&mut reg).unwrap();
        let node = reg.get("Relight").unwrap();
        let test_ctx = crate::test_support::TestCtx::new("relight");
        let ctx = test_ctx.ctx();
        let mut inputs = Inputs::new();
        inputs.insert("photo", Value::from(sc.photo.clone()));
        inputs.insert("depth", Value::from(sc.floor.clone()));
        inputs.insert("albedo", Value::from(sc.albedo.clone()));
        inputs.insert("pasted_color", Value::from(sc.pasted_color.clone()));
        inputs.insert("pasted_depth", Value::from(sc.slab.clone()));
        inputs.insert("alpha", Value::Mask(Arc::new(sc.alpha.clone())));
        inputs.insert("intrinsics", Value::from(sc.k));
        let vpls = crate::test_support::relight::overhead();
        inputs.insert("vpls", Value::from(vpls.clone()));
        let with = |vis: &str| RelightParams {
            visibility: crate::relight::shading::Visibility::from_name(vis).unwrap(),
            bounce_vpls: 0,
            scene_vpls: 0,
            ..Default::default()
        };
        let out = node
            .eval(&ctx, &inputs, &with("raycast").to_values())
            .unwrap();
        let expect = relight_reference_image(&sc.inputs(true), &vpls, &with("raycast"))
            .unwrap()
            .unwrap();
        assert_eq!(out.values["color"], Value::from(expect.color.clone()));
        // floor pixels (lit in the photo, not the slab) now in its shadow
        let dark = (0..w * h)
            .filter(|&i| {
                sc.photo.as_slice()[i][0] > 0.0
                    && sc.alpha.as_slice()[i] == 0.0
                    && expect.color.as_slice()[i][0] < 1e-6
            })
            .count();
        assert!(dark > 20, "{dark} shadowed pixels");
        // a name that is no scheme is refused by the node
        let mut bad = with("raycast").to_values();
        bad.insert("visibility".into(), ParamValue::Text("exact".into()));
        assert!(node.eval(&ctx, &inputs, &bad).is_err());
    }
}
