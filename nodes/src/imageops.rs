//! Small image operations: exposure, depth visualisation.

use crate::kit::colormap::{colormap_depth, depth_range};
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

fn exposure_eval(_: &EvalCtx, inputs: &Inputs, p: &ExposureParams) -> Result<Outputs, NodeError> {
    let img = inputs.color("color")?;
    if p.stops == 0.0 {
        return Ok(Outputs::new()
            .with("color", Value::Color(img.clone()))
            .passthrough("exposure change is 0 stops"));
    }
    Ok(Outputs::new().with("color", exposure(img, p.stops)))
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

fn preview_eval(
    _: &EvalCtx,
    inputs: &Inputs,
    p: &DepthPreviewParams,
) -> Result<Outputs, NodeError> {
    let d = inputs.depth("depth")?;
    let (lo, hi) = if p.max_m > p.min_m {
        (p.min_m as f32, p.max_m as f32)
    } else {
        depth_range(d, 0.02, 0.98)
    };
    Ok(Outputs::new()
        .with("color", colormap_depth(d, lo, hi))
        .with("min_m", lo as f64)
        .with("max_m", hi as f64))
}

/// Registers `Exposure` and `DepthPreview`.
pub fn register(reg: &mut Registry) -> Result<(), RegistryError> {
    reg.register(TypedNode::new(
        "Exposure",
        1,
        "Scales linear color by 2^stops.",
        vec![PortSpec::required("color", ValueType::Color, "linear RGB")],
        vec![PortSpec::output("color", ValueType::Color, "linear RGB")],
        exposure_eval,
    ))?;
    reg.register(TypedNode::new(
        "DepthPreview",
        1,
        "Colormaps depth for viewing (near blue, far red, holes black).",
        vec![PortSpec::required("depth", ValueType::Depth, "metres")],
        vec![
            PortSpec::output("color", ValueType::Color, "colormapped depth"),
            PortSpec::output("min_m", ValueType::Scalar, "depth of the first color"),
            PortSpec::output("max_m", ValueType::Scalar, "depth of the last color"),
        ],
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
