//! The `Relight` node: reads its inputs and runs the chosen visibility
//! scheme ([`crate::relight::paired`], [`crate::relight::scene_cached`] or
//! [`crate::relight::reference`]).

use std::sync::Arc;

use depthgraph_graph::prelude::*;
use depthgraph_graph::registry::RegistryError;

use crate::kit::color::luminance_clamped;
use crate::relight::scene_cached::{
    CpuSums, MoveSums, RelightScene, SCENE_PORTS, relight_moved_with, scene_key_params,
};
use crate::relight::vpl::checked_vpls;

use crate::relight::paired::relight;
use crate::relight::shading::{RelightInputs, RelightParams, Visibility};

depthgraph_graph::ports! {
    /// Inputs of `Relight`.
    inputs struct RelightIn {
        /// the target photo P, linear RGB
        photo: Arc<ColorImage>,
        /// target depth, metres
        depth: Arc<DepthMap>,
        /// target normals (else from the depth)
        normals: Option<Arc<NormalMap>>,
        /// target albedo (else photo / shading)
        albedo: Option<Arc<ColorImage>>,
        /// Paste.color
        pasted_color: Arc<ColorImage>,
        /// Paste.depth
        pasted_depth: Arc<DepthMap>,
        /// OcclusionComposite.alpha (after the depth test)
        alpha: Arc<Mask>,
        /// of the target
        intrinsics: Intrinsics,
        /// VplSample.vpls
        vpls: Arc<VplSet>,
        /// VplSample.vpls of the map the object was captured under (else the target's; visibility scene_cached or raycast)
        capture_vpls: Option<Arc<VplSet>>,
    }
}

depthgraph_graph::ports! {
    /// Outputs of `Relight`.
    outputs struct RelightOut {
        /// the composite I_m of eq. 5, linear RGB
        color: Arc<ColorImage>,
        /// 1 where rendered, 0 where the photo was kept
        region: Mask,
        /// I_{s+t} - I_t on the target surface
        difference: ColorImage,
    }
}

/// The most shadow-map texels one run may hold at once: 2^30 f32 depths,
/// 4 GiB. Every VPL's maps are alive together, so the product of the VPL
/// count and a map's texels (each within its own range) could reach a
/// terabyte and abort the process.
pub const MAX_SHADOW_TEXELS: u128 = 1 << 30;

/// Refuses a VPL count (and capture VPLs, whose object maps live beside
/// the scene's) and map resolutions whose shadow maps together exceed
/// [`MAX_SHADOW_TEXELS`], naming the parameters to lower.
pub fn shadow_maps_fit(vpls: usize, capture: usize, p: &RelightParams) -> Result<(), NodeError> {
    let sq = |r: usize| (r as u128) * (r as u128);
    let n = vpls as u128;
    let (maps, what) = match p.visibility {
        // a scene map and an object map per VPL, an object map per capture
        // VPL
        // (paired refuses capture VPLs)
        Visibility::Paired => (2 * n * sq(p.ism_resolution), "ism_resolution"),
        Visibility::SceneCached => (
            n * (sq(p.ism_resolution) + sq(p.object_ism_resolution))
                + capture as u128 * sq(p.object_ism_resolution),
            "ism_resolution and object_ism_resolution",
        ),
        Visibility::Raycast => (0, ""),
    };
    let bounce = if p.bounce_shadows {
        // the scene VPLs, and as many again on the support plane when it is
        // extended (`support_vpls`)
        let scene = p.scene_vpls as u128 * (1 + u128::from(p.extend_support));
        (p.bounce_vpls as u128 + scene) * sq(p.bounce_ism_resolution)
    } else {
        0
    };
    if maps + bounce <= MAX_SHADOW_TEXELS {
        return Ok(());
    }
    let (param, advice) = if bounce > maps {
        (
            "bounce_ism_resolution",
            "lower bounce_ism_resolution, bounce_vpls or scene_vpls, or turn bounce_shadows or extend_support off"
                .to_string(),
        )
    } else {
        (
            "ism_resolution",
            format!("lower {what} or the VPL count (VplSample.count, capture VPLs included)"),
        )
    };
    Err(NodeError::param(
        param,
        format!(
            "the shadow maps of {vpls} VPLs would hold {} M texels at once, more than {} M (4 GiB): {advice}",
            (maps + bounce) >> 20,
            MAX_SHADOW_TEXELS >> 20
        ),
    ))
}

fn eval(ctx: &EvalCtx, i: RelightIn, p: &RelightParams) -> Result<Produced<RelightOut>, NodeError> {
    eval_with(ctx, i, p, &mut CpuSums)
}

/// `Relight` with the long sums of a scene-cached move from `sums` (a
/// device's evaluators; the CPU's are [`CpuSums`]).
pub fn eval_with(
    ctx: &EvalCtx,
    i: RelightIn,
    p: &RelightParams,
    sums: &mut dyn MoveSums,
) -> Result<Produced<RelightOut>, NodeError> {
    let vpls = checked_vpls(&i.vpls, "vpls")?;
    let capture = match &i.capture_vpls {
        Some(c) => Some(checked_vpls(c, "capture_vpls")?),
        None => None,
    };
    if capture.is_some() && p.visibility == Visibility::Paired {
        return Err(NodeError::param(
            "visibility",
            "\"paired\" does not take capture_vpls (its capture side is the target's VPLs): \
             use \"scene_cached\" or \"raycast\", or leave capture_vpls unconnected",
        ));
    }
    shadow_maps_fit(vpls.len(), capture.as_ref().map_or(0, |c| c.len()), p)?;
    let inp = RelightInputs {
        photo: &i.photo,
        depth: &i.depth,
        normals: i.normals.as_deref(),
        albedo: i.albedo.as_deref(),
        pasted_color: &i.pasted_color,
        pasted_depth: &i.pasted_depth,
        alpha: &i.alpha,
        k: &i.intrinsics,
        capture_vpls: capture.as_deref(),
    };
    let result = match p.visibility {
        Visibility::Paired => relight(&inp, &vpls, p)?,
        Visibility::Raycast => crate::relight::reference::relight_reference_image(&inp, &vpls, p)?,
        Visibility::SceneCached => {
            // The per-photo part is a value the engine keeps under the keys
            // of the inputs it reads: moving the object reuses it.
            let scene = ctx.derived("relight scene", SCENE_PORTS, &scene_key_params(p), || {
                RelightScene::new(&inp.scene(), &vpls, p)
            })?;
            ctx.check_cancelled()?;
            sums.scene(&scene);
            relight_moved_with(&scene, &inp, p, sums)?
        }
    };
    match result {
        Some(r) => Ok(RelightOut {
            color: Arc::new(r.color),
            region: r.region,
            difference: r.difference,
        }
        .into()),
        None => {
            let (w, h) = i.photo.dims();
            let reason = if vpls.iter().all(|v| luminance_clamped(v.power) <= 0.0) {
                "no VPL carries energy (black environment map): nothing to relight"
            } else {
                "nothing pasted: the pasted depth has no valid pixel"
            };
            let out = RelightOut {
                color: i.photo.clone(),
                region: Mask::filled(w, h, 0.0),
                difference: ColorImage::filled(w, h, [0.0f32; 3]),
            };
            Ok(Produced::passthrough(out, reason))
        }
    }
}

/// Registers `Relight`.
pub fn register(reg: &mut Registry) -> Result<(), RegistryError> {
    reg.register(PortedNode::new(
        "Relight",
        13,
        "Differential rendering of a pasted object (3d-editing §IV.A, eq. 5-6): instant radiosity with the \
         directional VPLs of an environment map, imperfect shadow maps, one bounce each way with clamped \
         1/r² (object to scene; scene to object through secondary VPLs read off the photo, the floor it stands \
         on extended beyond the frame).\n\
         The object is shaded by the ratio of the irradiance it receives here to what it received where it was \
         captured (capture_vpls, else the same map); shadows remove only the light the object blocks, direct and \
         bounced (fill_light); its unseen back is closed for its shadows (close_back); where a shadow map cannot tell (an occluder \
         within its bias: a wall beside the object) the photo's depth is marched (contact); the object's irradiance, its bounce and the fill are evaluated every lattice_step pixels and blended between them on one surface where neighbours agree. Pixels are radiance.\n\
         Only the pixels the object changes are rendered; elsewhere the photo is kept bit for bit.\n\
         visibility: scene_cached keeps the scene's shadow maps while only the object changes (fast moves); \
         paired rebuilds scene+object maps with near-object importance (eq. 6) every run; raycast traces \
         exact shadow rays through the meshes (the reference, slow). Measured against a path tracer in \
         docs/relight-truth.md.",
        eval,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// VPL counts and map sizes whose maps would not fit are refused with
    /// the parameter to lower; the defaults and the paper's 256 VPLs fit.
    #[test]
    fn shadow_maps_beyond_the_budget_are_refused() {
        let p = RelightParams::default();
        assert!(shadow_maps_fit(256, 0, &p).is_ok());
        assert!(shadow_maps_fit(65536, 0, &p).is_ok());
        // capture VPLs' object maps count too
        let fine = RelightParams {
            object_ism_resolution: 2048,
            ..Default::default()
        };
        assert!(shadow_maps_fit(64, 0, &fine).is_ok());
        assert!(shadow_maps_fit(64, 4096, &fine).is_err());
        let big = RelightParams {
            ism_resolution: 1024,
            ..Default::default()
        };
        let e = shadow_maps_fit(4096, 0, &big).unwrap_err().to_string();
        assert!(
            e.contains("ism_resolution") && e.contains("4096 VPLs"),
            "{e}"
        );
        let paired = RelightParams {
            visibility: Visibility::Paired,
            ism_resolution: 2048,
            ..Default::default()
        };
        assert!(shadow_maps_fit(200, 0, &paired).is_err());
        let bounce = RelightParams {
            bounce_shadows: true,
            bounce_vpls: 65536,
            scene_vpls: 65536,
            bounce_ism_resolution: 1024,
            ..Default::default()
        };
        let e = shadow_maps_fit(64, 0, &bounce).unwrap_err().to_string();
        assert!(e.contains("bounce_ism_resolution"), "{e}");
        // the support plane's VPLs count with the scene's
        let support = RelightParams {
            bounce_shadows: true,
            bounce_vpls: 0,
            scene_vpls: 600,
            bounce_ism_resolution: 1024,
            ..Default::default()
        };
        assert!(support.extend_support);
        assert!(shadow_maps_fit(0, 0, &support).is_err());
        let no_support = RelightParams {
            extend_support: false,
            ..support
        };
        assert!(shadow_maps_fit(0, 0, &no_support).is_ok());
        // the reference casts rays: no maps
        let raycast = RelightParams {
            visibility: Visibility::Raycast,
            ism_resolution: 2048,
            ..Default::default()
        };
        assert!(shadow_maps_fit(65536, 0, &raycast).is_ok());
    }
}
