//! The `Relight` node: reads its inputs and runs the chosen visibility
//! scheme ([`crate::relight::paired`], [`crate::relight::scene_cached`] or
//! [`crate::relight::reference`]).

use depthgraph_graph::prelude::*;
use depthgraph_graph::registry::RegistryError;

use crate::kit::color::luminance_clamped;
use crate::relight::scene_cached::{RelightScene, SCENE_PORTS, relight_moved, scene_key_params};
use crate::relight::vpl::checked_vpls;

use crate::relight::paired::relight;
use crate::relight::shading::{RelightInputs, RelightParams, Visibility};

fn eval(ctx: &EvalCtx, inputs: &Inputs, p: &RelightParams) -> Result<Outputs, NodeError> {
    let photo = inputs.color("photo")?;
    let k = inputs.intrinsics("intrinsics")?;
    let vpls = checked_vpls(inputs.vpls("vpls")?, "vpls")?;
    let normals = inputs.normals_opt("normals")?;
    let inp = RelightInputs {
        photo,
        depth: inputs.depth("depth")?,
        normals: normals.map(|n| n.as_ref()),
        albedo: inputs.color_opt("albedo")?.map(|a| a.as_ref()),
        pasted_color: inputs.color("pasted_color")?,
        pasted_depth: inputs.depth("pasted_depth")?,
        alpha: inputs.mask("alpha")?,
        k: &k,
    };
    ctx.check_cancelled()?;
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
            relight_moved(&scene, &inp, p)?
        }
    };
    match result {
        Some(r) => Ok(Outputs::new()
            .with("color", r.color)
            .with("region", r.region)
            .with("difference", r.difference)),
        None => {
            let (w, h) = photo.dims();
            let reason = if vpls.iter().all(|v| luminance_clamped(v.power) <= 0.0) {
                "no VPL carries energy (black environment map): nothing to relight"
            } else {
                "nothing pasted: the alpha is 0 everywhere"
            };
            Ok(Outputs::new()
                .with("color", Value::Color(photo.clone()))
                .with("region", Mask::filled(w, h, 0.0))
                .with("difference", ColorImage::filled(w, h, [0.0f32; 3]))
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
            PortSpec::required("vpls", ValueType::Vpls, "VplSample.vpls"),
        ],
        vec![
            PortSpec::output("color", ValueType::Color, "the composite I_m of eq. 5, linear RGB"),
            PortSpec::output("region", ValueType::Mask, "1 where rendered, 0 where the photo was kept"),
            PortSpec::output("difference", ValueType::Color, "I_{s+t} - I_t on the target surface"),
        ],
        eval,
    ))
}
