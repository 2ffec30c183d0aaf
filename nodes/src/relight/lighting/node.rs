//! The `EstimateLighting` node: reads the photo and its depth and runs
//! [`estimate_lighting`].

use std::sync::Arc;

use depthgraph_graph::prelude::*;
use depthgraph_graph::registry::RegistryError;

use crate::relight::lighting::estimate::{EstimateInputs, EstimateParams, estimate_lighting_with};

depthgraph_graph::ports! {
    /// Inputs of `EstimateLighting`.
    inputs struct EstimateIn {
        /// the photo, linear RGB
        color: Arc<ColorImage>,
        /// its depth, metres
        depth: Arc<DepthMap>,
        /// of the photo
        intrinsics: Intrinsics,
        /// its normals (else from the depth)
        normals: Option<Arc<NormalMap>>,
        /// surfaces to trust (>= 0.5), else all
        mask: Option<Arc<Mask>>,
    }
}

depthgraph_graph::ports! {
    /// Outputs of `EstimateLighting`.
    outputs struct EstimateOut {
        /// equirectangular linear radiance (the EnvironmentMap convention)
        map: ColorImage,
        /// in [0, 1]: shading variation explained, times the variation there was
        confidence: f64,
    }
}

fn eval(
    ctx: &EvalCtx,
    i: EstimateIn,
    p: &EstimateParams,
) -> Result<Produced<EstimateOut>, NodeError> {
    let est = estimate_lighting_with(
        &EstimateInputs {
            color: &i.color,
            depth: &i.depth,
            k: &i.intrinsics,
            normals: i.normals.as_deref(),
            mask: i.mask.as_deref(),
        },
        p,
        &|| ctx.check_cancelled(),
    )?;
    Ok(Produced::reported(
        EstimateOut {
            map: est.map,
            confidence: est.confidence,
        },
        est.report,
    ))
}

/// Registers `EstimateLighting`.
pub fn register(reg: &mut Registry) -> Result<(), RegistryError> {
    reg.register(PortedNode::new(
        "EstimateLighting",
        7,
        "The photo's lighting estimated from its own shading, as an environment map for VplSample and Relight \
         when no capture of the light exists (3d-editing §VI, future work).\n\
         Lambertian surfaces of piecewise-constant albedo; low-frequency light as spherical harmonics of order 2 \
         (Ramamoorthi & Hanrahan 2001) fitted to the ratios of each pixel to its region's mean, plus a dominant \
         directional light (sun, lamp) searched over the sphere with its cast shadows marched through the depth \
         map (a light whose fit leaves the low-frequency part under a tenth of the mean irradiance is not \
         believed: a sky darker than black beside a low \"sun\" is the fit trading one for the other); \
         robust weights for highlights and textures. The light the photo's own surfaces bounce onto each other \
         (a radiosity gather from its pixels), and the sky those surfaces hide, are left out of the map, since \
         Relight bounces and shadows with the same surfaces (bounce = false counts it all as sky). The light's \
         scale assumes a median reflectance \
         (assumed_albedo, grey world). Below the camera's horizon, which no photo shows (its own floor hides \
         it), the map holds a ground of reflectance ground_albedo under the fitted sky (with bounce on): it \
         lights only an object where it was captured. A photo without shading variation gives a uniform ambient sky with \
         confidence 0 and says so. explain shows the light found, the ambient level and the confidence.",
        eval,
    ))
}
