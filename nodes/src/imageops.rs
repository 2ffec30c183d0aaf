//! Small image operations: exposure, depth visualisation.

use crate::kit::colormap::{colormap_depth, depth_range};
use std::sync::Arc;

use depthgraph_graph::node_params;
use depthgraph_graph::prelude::*;
use depthgraph_graph::registry::RegistryError;
use rayon::prelude::*;

/// Multiplies linear color by `2^stops`.
pub fn exposure(img: &ColorImage, stops: f64) -> ColorImage {
    let g = 2f64.powf(stops) as f32;
    let mut out = img.clone();
    out.as_mut_slice()
        .par_iter_mut()
        .for_each(|p| *p = p.map(|v| v * g));
    out
}

node_params! {
    /// Parameters of `Exposure`.
    pub struct ExposureParams {
        /// Exposure change in stops (each stop doubles the light).
        pub stops: f64 = 0.0, ParamKind::Float { min: -30.0, max: 30.0 };
    }
}

depthgraph_graph::ports! {
    /// The input and output of `Exposure`.
    inputs struct ExposureIn {
        /// linear RGB
        color: Arc<ColorImage>,
    }
}

depthgraph_graph::ports! {
    /// The output of `Exposure`.
    outputs struct ExposureOut {
        /// linear RGB
        color: Arc<ColorImage>,
    }
}

fn exposure_eval(
    _: &EvalCtx,
    i: ExposureIn,
    p: &ExposureParams,
) -> Result<Produced<ExposureOut>, NodeError> {
    if p.stops == 0.0 {
        return Ok(Produced::passthrough(
            ExposureOut { color: i.color },
            "exposure change is 0 stops",
        ));
    }
    Ok(ExposureOut {
        color: Arc::new(exposure(&i.color, p.stops)),
    }
    .into())
}

node_params! {
    /// Parameters of `DepthPreview`.
    pub struct DepthPreviewParams {
        /// Depth of the first color in metres; with max_m 0, the 2nd percentile.
        pub min_m: f64 = 0.0, ParamKind::Float { min: 0.0, max: 1e6 };
        /// Depth of the last color in metres; 0 = the 98th percentile.
        pub max_m: f64 = 0.0, ParamKind::Float { min: 0.0, max: 1e6 };
    }
}

depthgraph_graph::ports! {
    /// Inputs of `DepthPreview`.
    inputs struct PreviewIn {
        /// metres
        depth: Arc<DepthMap>,
    }
}

depthgraph_graph::ports! {
    /// Outputs of `DepthPreview`.
    outputs struct PreviewOut {
        /// colormapped depth
        color: ColorImage,
        /// depth of the first color
        min_m: f64,
        /// depth of the last color
        max_m: f64,
    }
}

fn preview_eval(
    _: &EvalCtx,
    i: PreviewIn,
    p: &DepthPreviewParams,
) -> Result<Produced<PreviewOut>, NodeError> {
    let (lo, hi) = if p.max_m > p.min_m {
        (p.min_m as f32, p.max_m as f32)
    } else {
        depth_range(&i.depth, 0.02, 0.98)
    };
    Ok(PreviewOut {
        color: colormap_depth(&i.depth, lo, hi),
        min_m: lo as f64,
        max_m: hi as f64,
    }
    .into())
}

/// Registers `Exposure` and `DepthPreview`.
pub fn register(reg: &mut Registry) -> Result<(), RegistryError> {
    reg.register(PortedNode::new(
        "Exposure",
        1,
        "Scales linear color by 2^stops.",
        exposure_eval,
    ))?;
    reg.register(PortedNode::new(
        "DepthPreview",
        1,
        "Colormaps depth for viewing (near blue, far red, holes black).",
        preview_eval,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exposure_doubles_per_stop() {
        let img = Image::filled(2, 2, [0.25f32, 0.5, 1.0]);
        assert_eq!(*exposure(&img, 1.0).get(1, 1), [0.5, 1.0, 2.0]);
    }
}
