//! Camera intrinsics: presets of common RGB-D cameras and custom values.

use depthgraph_graph::node_params;
use depthgraph_graph::prelude::*;

depthgraph_graph::param_choice! {
    /// A known camera, or custom values (the `preset` parameter).
    pub enum CameraPreset {
        /// Kinect v1 / ROS default.
        KinectV1 = "kinect_v1",
        /// TUM RGB-D freiburg1 colour camera.
        TumFr1 = "tum_fr1",
        /// TUM RGB-D freiburg2 colour camera.
        TumFr2 = "tum_fr2",
        /// TUM RGB-D freiburg3 colour camera.
        TumFr3 = "tum_fr3",
        /// NYU Depth v2 colour camera.
        Nyu = "nyu",
        /// fx, fy, cx, cy as given.
        Custom = "custom",
    }
}

/// Intrinsics of a preset at its native 640x480; `None` for `Custom`.
///
/// Sources: Kinect v1 / ROS default (fx = fy = 525, c = 319.5, 239.5);
/// TUM RGB-D calibrated colour cameras fr1, fr2, fr3 (Sturm et al. 2012);
/// NYU Depth v2 colour camera (Silberman et al. 2012 toolbox).
pub fn preset(preset: CameraPreset) -> Option<Intrinsics> {
    let (fx, fy, cx, cy) = match preset {
        CameraPreset::KinectV1 => (525.0, 525.0, 319.5, 239.5),
        CameraPreset::TumFr1 => (517.3, 516.5, 318.6, 255.3),
        CameraPreset::TumFr2 => (520.9, 521.0, 325.1, 249.7),
        CameraPreset::TumFr3 => (535.4, 539.2, 320.1, 247.6),
        CameraPreset::Nyu => (518.8579, 519.4696, 325.5824, 253.7362),
        CameraPreset::Custom => return None,
    };
    Some(Intrinsics {
        fx,
        fy,
        cx,
        cy,
        width: 640,
        height: 480,
    })
}

node_params! {
    /// Parameters of the `Camera` node.
    pub struct CameraParams {
        /// A known camera, or "custom" to use fx, fy, cx, cy as given.
        pub preset: CameraPreset = CameraPreset::KinectV1, ParamKind::Choice(CameraPreset::NAMES);
        /// Image width in pixels; presets are rescaled to it.
        pub width: usize = 640usize, ParamKind::Int { min: 1, max: 65536 };
        /// Image height in pixels; presets are rescaled to it.
        pub height: usize = 480usize, ParamKind::Int { min: 1, max: 65536 };
        /// Focal length along x in pixels (custom only).
        pub fx: f64 = 525.0, ParamKind::Float { min: 1e-3, max: 1e6 };
        /// Focal length along y in pixels (custom only).
        pub fy: f64 = 525.0, ParamKind::Float { min: 1e-3, max: 1e6 };
        /// Principal point x in pixels (custom only).
        pub cx: f64 = 319.5, ParamKind::Float { min: -1e6, max: 1e6 };
        /// Principal point y in pixels (custom only).
        pub cy: f64 = 239.5, ParamKind::Float { min: -1e6, max: 1e6 };
    }
}

/// The intrinsics the parameters describe.
///
/// ```
/// use depthgraph_nodes::camera::intrinsics::{camera_intrinsics, CameraParams};
/// let k = camera_intrinsics(&CameraParams { width: 320, height: 240, ..Default::default() }).unwrap();
/// assert_eq!(k.fx, 262.5);
/// ```
pub fn camera_intrinsics(p: &CameraParams) -> Result<Intrinsics, NodeError> {
    Ok(match preset(p.preset) {
        Some(k) => k.scaled_to(p.width, p.height),
        None => Intrinsics {
            fx: p.fx,
            fy: p.fy,
            cx: p.cx,
            cy: p.cy,
            width: p.width,
            height: p.height,
        },
    })
}

depthgraph_graph::ports! {
    /// Outputs of `Camera`.
    outputs struct CameraOut {
        /// fx, fy, cx, cy in pixels
        intrinsics: Intrinsics,
    }
}

fn eval(_: &EvalCtx, _: NoInputs, p: &CameraParams) -> Result<Produced<CameraOut>, NodeError> {
    Ok(CameraOut {
        intrinsics: camera_intrinsics(p)?,
    }
    .into())
}

/// Registers `Camera`.
pub fn register(reg: &mut Registry) -> Result<(), depthgraph_graph::registry::RegistryError> {
    reg.register(PortedNode::new(
        "Camera",
        1,
        "Pinhole intrinsics of a known RGB-D camera (Kinect v1, TUM fr1-3, NYU) or custom values.",
        eval,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presets_scale_with_resolution() {
        let k = camera_intrinsics(&CameraParams {
            preset: CameraPreset::TumFr1,
            width: 320,
            height: 240,
            ..Default::default()
        })
        .unwrap();
        assert!((k.fx - 258.65).abs() < 1e-9 && (k.cy - 127.65).abs() < 1e-9);
        for name in CameraPreset::NAMES {
            let p = CameraPreset::from_name(name).unwrap();
            assert_eq!(preset(p).is_some(), p != CameraPreset::Custom, "{name}");
        }
    }
}
