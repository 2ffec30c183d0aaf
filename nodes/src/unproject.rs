//! Depth to 3D points and back (3d-editing eq. 1).

use depthgraph_graph::node_params;
use depthgraph_graph::prelude::*;
use depthgraph_graph::registry::RegistryError;

fn check_dims(what: &str, w: usize, h: usize, k: &Intrinsics) -> Result<(), NodeError> {
    if (w, h) != (k.width, k.height) {
        return Err(NodeError::input(
            what,
            format!(
                "is {w}x{h} but the intrinsics are for {}x{}; give the Camera node the image's size",
                k.width, k.height
            ),
        ));
    }
    if !k.is_sane() {
        return Err(NodeError::input(
            "intrinsics",
            "focal lengths must be finite and positive",
        ));
    }
    Ok(())
}

/// Unprojects every valid pixel: `X = (u - cx) z / fx`, `Y = (v - cy) z / fy`, `Z = z`
/// (3d-editing eq. 1), with `(u, v)` the pixel centre `(x + 0.5, y + 0.5)`.
/// Colors are attached when given (same size as the depth).
///
/// ```
/// use depthgraph_graph::value::{Image, Intrinsics};
/// let k = Intrinsics { fx: 1.0, fy: 1.0, cx: 1.0, cy: 0.5, width: 2, height: 1 };
/// let d = Image::from_vec(2, 1, vec![2.0f32, 0.0]).unwrap();
/// let pc = depthgraph_nodes::unproject::unproject(&d, &k, None).unwrap();
/// assert_eq!(pc.positions, vec![[-1.0, 0.0, 2.0]]);
/// ```
pub fn unproject(
    depth: &DepthMap,
    k: &Intrinsics,
    color: Option<&ColorImage>,
) -> Result<PointCloud, NodeError> {
    check_dims("depth", depth.width(), depth.height(), k)?;
    if let Some(c) = color {
        if !c.same_dims(depth) {
            return Err(NodeError::input(
                "color",
                format!(
                    "is {}x{} but the depth is {}x{}",
                    c.width(),
                    c.height(),
                    depth.width(),
                    depth.height()
                ),
            ));
        }
    }
    let mut pc = PointCloud::default();
    for y in 0..depth.height() {
        for x in 0..depth.width() {
            let z = *depth.get(x, y);
            if !DepthMap::is_valid(z) {
                continue;
            }
            let p = k.unproject(x as f64 + 0.5, y as f64 + 0.5, z as f64);
            pc.positions.push([p.x as f32, p.y as f32, p.z as f32]);
            if let Some(c) = color {
                pc.colors.push(*c.get(x, y));
            }
        }
    }
    Ok(pc)
}

/// Projects points into an image with a z-buffer (nearest point wins, one
/// pixel per point): depth (0 where nothing lands) and color (black there).
pub fn project(points: &PointCloud, k: &Intrinsics) -> Result<(DepthMap, ColorImage), NodeError> {
    if !k.is_sane() {
        return Err(NodeError::input(
            "intrinsics",
            "focal lengths must be finite and positive",
        ));
    }
    let mut depth = Image::filled(k.width, k.height, 0.0f32);
    let mut color = Image::filled(k.width, k.height, [0.0f32; 3]);
    let has_color = points.colors.len() == points.positions.len();
    for (i, p) in points.positions.iter().enumerate() {
        let v = glam::DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64);
        let Some(uv) = k.project(v) else { continue };
        if !(uv.x.is_finite() && uv.y.is_finite()) || uv.x < 0.0 || uv.y < 0.0 {
            continue;
        }
        let (x, y) = (uv.x.floor() as usize, uv.y.floor() as usize);
        if x >= k.width || y >= k.height {
            continue;
        }
        let z = depth.get_mut(x, y);
        if *z == 0.0 || p[2] < *z {
            *z = p[2];
            if has_color {
                *color.get_mut(x, y) = points.colors[i];
            }
        }
    }
    Ok((depth, color))
}

node_params! {
    /// `Unproject` has no parameters.
    pub struct UnprojectParams {}
}

fn unproject_eval(_: &EvalCtx, inputs: &Inputs, _: &UnprojectParams) -> Result<Outputs, NodeError> {
    let d = inputs.depth("depth")?;
    let k = inputs.intrinsics("intrinsics")?;
    let c = inputs.color_opt("color")?;
    Ok(Outputs::new().with("points", unproject(d, &k, c.map(|c| c.as_ref()))?))
}

fn project_eval(_: &EvalCtx, inputs: &Inputs, _: &UnprojectParams) -> Result<Outputs, NodeError> {
    let pc = inputs.point_cloud("points")?;
    let k = inputs.intrinsics("intrinsics")?;
    let (d, c) = project(pc, &k)?;
    Ok(Outputs::new().with("depth", d).with("color", c))
}

/// Registers `Unproject` and `Project`.
pub fn register(reg: &mut Registry) -> Result<(), RegistryError> {
    reg.register(TypedNode::new(
        "Unproject",
        1,
        "Depth + intrinsics to a camera-space point cloud (3d-editing eq. 1), with optional colors.",
        vec![
            PortSpec::required("depth", ValueType::Depth, "metres"),
            PortSpec::required("intrinsics", ValueType::Intrinsics, "of the depth image"),
            PortSpec::optional("color", ValueType::Color, "colors for the points, same size as depth"),
        ],
        vec![PortSpec::output("points", ValueType::PointCloud, "one point per valid pixel")],
        unproject_eval,
    ))?;
    reg.register(TypedNode::new(
        "Project",
        1,
        "Point cloud to depth and color images through intrinsics, nearest point wins.",
        vec![
            PortSpec::required("points", ValueType::PointCloud, "camera-space points"),
            PortSpec::required("intrinsics", ValueType::Intrinsics, "of the target image"),
        ],
        vec![
            PortSpec::output("depth", ValueType::Depth, "metres, 0 where no point lands"),
            PortSpec::output("color", ValueType::Color, "point colors, black where none"),
        ],
        project_eval,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn project_inverts_unproject() {
        let k = Intrinsics {
            fx: 50.0,
            fy: 55.0,
            cx: 16.0,
            cy: 12.0,
            width: 32,
            height: 24,
        };
        let d = Image::from_fn(32, 24, |x, y| {
            if (x + y) % 7 == 0 {
                0.0
            } else {
                1.0 + 0.01 * x as f32 + 0.02 * y as f32
            }
        });
        let c = Image::from_fn(32, 24, |x, y| [x as f32, y as f32, 0.0]);
        let pc = unproject(&d, &k, Some(&c)).unwrap();
        assert_eq!(pc.positions.len(), d.len() - d.hole_count());
        let (d2, c2) = project(&pc, &k).unwrap();
        assert_eq!(d2, d);
        for (i, (a, b)) in c.as_slice().iter().zip(c2.as_slice()).enumerate() {
            if d.as_slice()[i] > 0.0 {
                assert_eq!(a, b);
            }
        }
    }

    #[test]
    fn mismatched_sizes_are_named() {
        let k = Intrinsics {
            fx: 50.0,
            fy: 50.0,
            cx: 8.0,
            cy: 8.0,
            width: 16,
            height: 16,
        };
        let e = unproject(&Image::filled(8, 8, 1.0f32), &k, None).unwrap_err();
        assert!(
            e.to_string().contains("8x8") && e.to_string().contains("16x16"),
            "{e}"
        );
        let e = unproject(
            &Image::filled(16, 16, 1.0f32),
            &k,
            Some(&Image::filled(4, 4, [0.0; 3])),
        )
        .unwrap_err();
        assert!(e.to_string().contains("color"), "{e}");
    }
}
