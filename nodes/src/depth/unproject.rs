//! Depth to 3D points and back (3d-editing eq. 1).

use std::sync::Arc;

use depthgraph_graph::node_params;
use depthgraph_graph::prelude::*;
use depthgraph_graph::registry::RegistryError;

use crate::kit::checks::{fits_intrinsics, same_size, sane_intrinsics};

/// Unprojects every valid pixel: `X = (u - cx) z / fx`, `Y = (v - cy) z / fy`, `Z = z`
/// (3d-editing eq. 1), with `(u, v)` the pixel centre `(x + 0.5, y + 0.5)`;
/// a point beyond f32's range (a huge depth far from the centre) is left out.
/// Colors are attached when given (same size as the depth).
///
/// ```
/// use depthgraph_graph::value::{Image, Intrinsics};
/// let k = Intrinsics { fx: 1.0, fy: 1.0, cx: 1.0, cy: 0.5, width: 2, height: 1 };
/// let d = Image::from_vec(2, 1, vec![2.0f32, 0.0]).unwrap();
/// let pc = depthgraph_nodes::depth::unproject::unproject(&d, &k, None).unwrap();
/// assert_eq!(pc.positions, vec![[-1.0, 0.0, 2.0]]);
/// ```
pub fn unproject(
    depth: &DepthMap,
    k: &Intrinsics,
    color: Option<&ColorImage>,
) -> Result<PointCloud, NodeError> {
    fits_intrinsics("intrinsics", k, "depth map", depth.dims())?;
    if let Some(c) = color {
        same_size(
            "color",
            "a colour image",
            c.dims(),
            "the depth",
            depth.dims(),
        )?;
    }
    let mut pc = PointCloud::default();
    for y in 0..depth.height() {
        for x in 0..depth.width() {
            let z = *depth.get(x, y);
            if !DepthMap::is_valid(z) {
                continue;
            }
            let p = k.unproject(x as f64 + 0.5, y as f64 + 0.5, z as f64);
            let q = [p.x as f32, p.y as f32, p.z as f32];
            // a huge depth at an image corner can leave f32's range
            // (x = (u - cx) z / fx): no point, as the mesh does
            if !q.iter().all(|c| c.is_finite()) {
                continue;
            }
            pc.positions.push(q);
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
    sane_intrinsics("intrinsics", k)?;
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

depthgraph_graph::ports! {
    /// Inputs of `Unproject`.
    inputs struct UnprojectIn {
        /// metres
        depth: Arc<DepthMap>,
        /// of the depth image
        intrinsics: Intrinsics,
        /// colors for the points, same size as depth
        color: Option<Arc<ColorImage>>,
    }
}

depthgraph_graph::ports! {
    /// Outputs of `Unproject`.
    outputs struct UnprojectOut {
        /// one point per valid pixel (none where it would leave f32's range)
        points: PointCloud,
    }
}

fn unproject_eval(
    _: &EvalCtx,
    i: UnprojectIn,
    _: &UnprojectParams,
) -> Result<Produced<UnprojectOut>, NodeError> {
    let points = unproject(&i.depth, &i.intrinsics, i.color.as_deref())?;
    Ok(UnprojectOut { points }.into())
}

depthgraph_graph::ports! {
    /// Inputs of `Project`.
    inputs struct ProjectIn {
        /// camera-space points
        points: Arc<PointCloud>,
        /// of the target image
        intrinsics: Intrinsics,
    }
}

depthgraph_graph::ports! {
    /// Outputs of `Project`.
    outputs struct ProjectOut {
        /// metres, 0 where no point lands
        depth: DepthMap,
        /// point colors, black where none
        color: ColorImage,
    }
}

fn project_eval(
    ctx: &EvalCtx,
    i: ProjectIn,
    _: &UnprojectParams,
) -> Result<Produced<ProjectOut>, NodeError> {
    crate::kit::checks::output_fits(ctx, "intrinsics", i.intrinsics.width, i.intrinsics.height)?;
    let (depth, color) = project(&i.points, &i.intrinsics)?;
    Ok(ProjectOut { depth, color }.into())
}

node_params! {
    /// Parameters of `ReprojectDepth`: the pose of the depth camera in the
    /// target (color) camera's frame, `p_target = R p_depth + t`.
    pub struct ReprojectParams {
        /// Rotation as X, Y, Z angles in degrees, applied X first (`R = Rz Ry Rx`).
        pub rotation_deg: [f64; 3] = [0.0, 0.0, 0.0], ParamKind::Vec3 { min: -360.0, max: 360.0 };
        /// Position of the depth camera in the target camera's frame, metres
        /// (x right, y down, z forward).
        pub translation_m: [f64; 3] = [0.0, 0.0, 0.0], ParamKind::Vec3 { min: -100.0, max: 100.0 };
        /// Width of the result; 0 = the target's. The target camera is
        /// rescaled to it (e.g. the color camera at the depth camera's
        /// resolution, as NLMeansUpsample expects).
        pub width: usize = 0usize, ParamKind::Int { min: 0, max: 65536 };
        /// Height of the result; 0 = the target's.
        pub height: usize = 0usize, ParamKind::Int { min: 0, max: 65536 };
    }
}

/// Moves a depth map taken by one camera into another camera's image
/// ("realistic depth blur", Sec. 2.1: "we backproject the depth readings
/// into 3D-space and project them onto the image plane of the color
/// camera"): every valid pixel is unprojected with `k_depth` (eq. 1 of the
/// 3-D editing paper), moved by the pose, and projected with `k_target`;
/// the nearest point wins each target pixel (a z-buffer), so occluded
/// readings disappear. Pixels that receive no point are holes (0), as are
/// points behind the target camera. The second output is 1 where a reading
/// landed. Low-resolution readings land sparsely on a finer target: fill the
/// result with the NL-means upsampling / inpainting nodes.
///
/// ```
/// use depthgraph_nodes::depth::unproject::{reproject_depth, ReprojectParams};
/// use depthgraph_graph::value::{DepthMap, Intrinsics};
/// let k = Intrinsics { fx: 20.0, fy: 20.0, cx: 8.0, cy: 8.0, width: 16, height: 16 };
/// let d = DepthMap::filled(16, 16, 2.0);
/// // The depth camera 10 cm right of the target: the wall moves right by f t / z = 1 px.
/// let p = ReprojectParams { translation_m: [0.1, 0.0, 0.0], ..Default::default() };
/// let (out, conf) = reproject_depth(&d, &k, &k, &p).unwrap();
/// assert_eq!(*out.get(0, 8), 0.0); // nothing lands on the left edge
/// assert_eq!(*out.get(15, 8), 2.0);
/// assert_eq!(*conf.get(0, 8), 0.0);
/// ```
pub fn reproject_depth(
    depth: &DepthMap,
    k_depth: &Intrinsics,
    k_target: &Intrinsics,
    p: &ReprojectParams,
) -> Result<(DepthMap, Confidence), NodeError> {
    let (w, h) = depth.dims();
    fits_intrinsics("intrinsics", k_depth, "depth map", (w, h))?;
    sane_intrinsics("target", k_target)?;
    half_size(p)?;
    let [rx, ry, rz] = p.rotation_deg.map(f64::to_radians);
    let rot = glam::DMat3::from_rotation_z(rz)
        * glam::DMat3::from_rotation_y(ry)
        * glam::DMat3::from_rotation_x(rx);
    let t = glam::DVec3::from_array(p.translation_m);
    let k_target = &output_camera(k_target, p);
    let (tw, th) = (k_target.width, k_target.height);
    let mut out = DepthMap::filled(tw, th, 0.0);
    for y in 0..h {
        for x in 0..w {
            let z = *depth.get(x, y);
            if !DepthMap::is_valid(z) {
                continue;
            }
            // pixel centres at integer + 0.5 (the convention of `unproject`);
            // the target pixel is the one whose square holds the projection
            let q = rot * k_depth.unproject(x as f64 + 0.5, y as f64 + 0.5, z as f64) + t;
            let Some(uv) = k_target.project(q) else {
                continue;
            };
            let (u, v) = (uv.x.floor(), uv.y.floor());
            if !(u >= 0.0 && v >= 0.0 && u < tw as f64 && v < th as f64) {
                continue;
            }
            let cell = out.get_mut(u as usize, v as usize);
            let zq = q.z as f32;
            if DepthMap::is_valid(zq) && (*cell == 0.0 || zq < *cell) {
                *cell = zq;
            }
        }
    }
    let conf = out.map(|&z| if DepthMap::is_valid(z) { 1.0 } else { 0.0 });
    Ok((out, conf))
}

/// `width` and `height` are both set or both 0.
fn half_size(p: &ReprojectParams) -> Result<(), NodeError> {
    if (p.width == 0) == (p.height == 0) {
        return Ok(());
    }
    let (set, unset) = if p.width == 0 {
        ("height", "width")
    } else {
        ("width", "height")
    };
    Err(NodeError::param(
        unset,
        format!("is 0 while {set} is set: give both (the result's size) or neither (the target's)"),
    ))
}

/// The camera of [`reproject_depth`]'s result: the target, rescaled when
/// `width` and `height` are set.
pub fn output_camera(k_target: &Intrinsics, p: &ReprojectParams) -> Intrinsics {
    if p.width > 0 && p.height > 0 {
        k_target.scaled_to(p.width, p.height)
    } else {
        *k_target
    }
}

depthgraph_graph::ports! {
    /// Inputs of `ReprojectDepth`.
    inputs struct ReprojectIn {
        /// metres, as the depth camera saw them
        depth: Arc<DepthMap>,
        /// of the depth camera
        intrinsics: Intrinsics,
        /// of the target (color) camera, any size
        target: Intrinsics,
    }
}

depthgraph_graph::ports! {
    /// Outputs of `ReprojectDepth`.
    outputs struct ReprojectOut {
        /// metres in the target frame, 0 where nothing lands
        depth: DepthMap,
        /// 1 where a reading landed, else 0
        confidence: Confidence,
        /// of the result (the target, rescaled)
        intrinsics: Intrinsics,
    }
}

fn reproject_eval(
    ctx: &EvalCtx,
    i: ReprojectIn,
    p: &ReprojectParams,
) -> Result<Produced<ReprojectOut>, NodeError> {
    half_size(p)?;
    let k = output_camera(&i.target, p);
    if p.width > 0 {
        crate::kit::checks::output_fits_param(ctx, "width", k.width, k.height)?;
    } else {
        crate::kit::checks::output_fits(ctx, "target", k.width, k.height)?;
    }
    let (depth, confidence) = reproject_depth(&i.depth, &i.intrinsics, &i.target, p)?;
    Ok(ReprojectOut {
        depth,
        confidence,
        intrinsics: output_camera(&i.target, p),
    }
    .into())
}

/// Registers `Unproject`, `Project` and `ReprojectDepth`.
pub fn register(reg: &mut Registry) -> Result<(), RegistryError> {
    reg.register(PortedNode::new(
        "Unproject",
        1,
        "Depth + intrinsics to a camera-space point cloud (3d-editing eq. 1), with optional colors.",
        unproject_eval,
    ))?;
    reg.register(PortedNode::new(
        "Project",
        1,
        "Point cloud to depth and color images through intrinsics, nearest point wins.",
        project_eval,
    ))?;
    reg.register(PortedNode::new(
        "ReprojectDepth",
        2,
        "Depth from a second camera (its intrinsics, its pose in the target frame) moved into the target \
         camera's image with a z-buffer (realistic-depth-blur Sec. 2.1): occlusions and holes appear, to be \
         filled by NLMeansUpsample / NLMeansInpaint.",
        reproject_eval,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two cameras with the same field of view, the target 4x finer: each
    /// depth pixel lands inside its own footprint on the target (target
    /// pixels 4x..4x+3), on one of the two pixels whose centres are nearest
    /// its own centre, and no point is shifted towards the top-left.
    #[test]
    fn reprojection_uses_pixel_centres_across_scales() {
        let kd = Intrinsics {
            fx: 4.0,
            fy: 4.0,
            cx: 2.0,
            cy: 2.0,
            width: 4,
            height: 4,
        };
        let kt = kd.scaled_to(16, 16);
        let d = DepthMap::filled(4, 4, 2.0);
        let (out, _) = reproject_depth(&d, &kd, &kt, &ReprojectParams::default()).unwrap();
        let landed: Vec<(usize, usize)> = (0..16 * 16)
            .filter(|&i| out.as_slice()[i] > 0.0)
            .map(|i| (i % 16, i / 16))
            .collect();
        assert_eq!(landed.len(), 16);
        for (u, v) in landed {
            let (x, y) = (u / 4, v / 4);
            // the centre of depth pixel x is target coordinate 4x + 2
            for (t, s) in [(u, x), (v, y)] {
                let off = t as f64 + 0.5 - (4 * s) as f64 - 2.0;
                assert!(off.abs() <= 0.5, "target pixel {t} for depth pixel {s}");
            }
        }
        // same scale: a one-pixel shift stays exactly one pixel
        let p = ReprojectParams {
            translation_m: [0.5, 0.0, 0.0],
            ..Default::default()
        };
        let (out, _) = reproject_depth(&d, &kd, &kd, &p).unwrap();
        assert_eq!(*out.get(0, 1), 0.0);
        assert_eq!(*out.get(1, 1), 2.0);
    }

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

    #[test]
    fn reprojection_occludes_and_round_trips() {
        let k = Intrinsics {
            fx: 40.0,
            fy: 40.0,
            cx: 20.0,
            cy: 15.0,
            width: 40,
            height: 30,
        };
        // A near box (1 m) in front of a wall (4 m).
        let d = Image::from_fn(
            40,
            30,
            |x, _| if (15..25).contains(&x) { 1.0f32 } else { 4.0 },
        );
        let p = ReprojectParams {
            translation_m: [0.1, 0.0, 0.0],
            ..Default::default()
        };
        let (out, conf) = reproject_depth(&d, &k, &k, &p).unwrap();
        // The box moves right by f t / z = 4 px, the wall by 1 px: the box
        // covers columns 19..29 in the target (nearest wins over the wall
        // landing there), and a 3-px gap opens left of it where the wall was
        // hidden from the depth camera.
        for x in 19..29 {
            assert_eq!(*out.get(x, 10), 1.0, "x = {x}");
        }
        for x in 16..19 {
            assert_eq!(*out.get(x, 10), 0.0, "x = {x}");
            assert_eq!(*conf.get(x, 10), 0.0);
        }
        assert_eq!(*out.get(15, 10), 4.0);
        assert_eq!(*out.get(29, 10), 4.0);
        // The inverse pose brings the visible points back.
        let back = ReprojectParams {
            translation_m: [-0.1, 0.0, 0.0],
            ..Default::default()
        };
        let (round, _) = reproject_depth(&out, &k, &k, &back).unwrap();
        for x in 15..25 {
            assert_eq!(*round.get(x, 10), 1.0);
        }
        // A 90-degree turn looks away from everything: all holes, no panic.
        let turned = ReprojectParams {
            rotation_deg: [0.0, 180.0, 0.0],
            ..Default::default()
        };
        let (none, _) = reproject_depth(&d, &k, &k, &turned).unwrap();
        assert_eq!(none.hole_count(), none.len());
    }

    #[test]
    fn a_depth_camera_beside_the_color_camera_lands_on_the_truth() {
        use crate::sim::synthetic::{RenderOptions, Scene, render};
        let color_cam = Scene::preset("tabletop", 80, 60).unwrap();
        let truth = render(&color_cam, &RenderOptions::default());
        let mut depth_cam = Scene::preset("tabletop", 80, 60).unwrap();
        let offset = [0.06, -0.02, 0.01];
        depth_cam.move_camera(glam::DVec3::from_array(offset));
        let seen = render(&depth_cam, &RenderOptions::default());
        assert_ne!(seen.depth, truth.depth);
        let p = ReprojectParams {
            translation_m: offset,
            ..Default::default()
        };
        let k = truth.intrinsics;
        // Pixel centres are at +0.5 in the renders; reproject_depth uses
        // integer pixel coordinates on both sides, so the convention cancels.
        let (out, conf) = reproject_depth(&seen.depth, &k, &k, &p).unwrap();
        let (mut good, mut landed) = (0, 0);
        for (i, (&z, &t)) in out
            .as_slice()
            .iter()
            .zip(truth.depth.as_slice())
            .enumerate()
        {
            if conf.as_slice()[i] > 0.0 {
                landed += 1;
                // Splats land on the nearest pixel: the reading must lie
                // within the range of the truth over the pixel's 3x3
                // neighbourhood (1 % slack).
                let (x, y) = ((i % 80) as isize, (i / 80) as isize);
                let (mut lo, mut hi) = (t, t);
                for oy in -1..=1 {
                    for ox in -1..=1 {
                        if let Some(&n) = truth.depth.try_get(x + ox, y + oy) {
                            lo = lo.min(n);
                            hi = hi.max(n);
                        }
                    }
                }
                let near = z >= 0.99 * lo && z <= 1.01 * hi;
                good += near as usize;
            }
        }
        // Most pixels receive a reading; nearly all agree with the truth.
        assert!(landed as f64 > 0.85 * out.len() as f64, "{landed}");
        assert!(good as f64 > 0.995 * landed as f64, "{good} / {landed}");
        // At a quarter of the resolution, with the camera rescaled.
        let quarter = ReprojectParams {
            width: 20,
            height: 15,
            ..p
        };
        let (small, _) = reproject_depth(&seen.depth, &k, &k, &quarter).unwrap();
        assert_eq!(small.dims(), (20, 15));
        assert!(small.hole_count() < 20 * 15 / 4);
    }

    /// Sizes the run cannot hold are refused before anything is allocated;
    /// half a size is named; points beyond f32's range are left out.
    #[test]
    fn impossible_sizes_and_points_are_refused_or_skipped() {
        let tc = crate::test_support::TestCtx::new("n");
        let mut ctx = tc.ctx();
        ctx.max_pixels = 1000;
        let big = Intrinsics {
            fx: 100.0,
            fy: 100.0,
            cx: 32.0,
            cy: 32.0,
            width: 64,
            height: 64,
        };
        let e = project_eval(
            &ctx,
            ProjectIn {
                points: Arc::new(PointCloud::default()),
                intrinsics: big,
            },
            &UnprojectParams::default(),
        )
        .unwrap_err();
        assert!(
            e.to_string().contains("64x64") && e.to_string().contains("1000"),
            "{e}"
        );
        let small = big.scaled_to(8, 8);
        let reproject = |p: &ReprojectParams| {
            reproject_eval(
                &ctx,
                ReprojectIn {
                    depth: Arc::new(DepthMap::filled(8, 8, 1.0)),
                    intrinsics: small,
                    target: small,
                },
                p,
            )
        };
        let wide = ReprojectParams {
            width: 100,
            height: 100,
            ..Default::default()
        };
        let e = reproject(&wide).unwrap_err();
        assert!(e.to_string().contains("100x100"), "{e}");
        assert!(
            matches!(&e, NodeError::Param { param, .. } if param == "width"),
            "{e}"
        );
        let half = ReprojectParams {
            width: 16,
            ..Default::default()
        };
        let e = reproject(&half).unwrap_err();
        assert!(e.to_string().contains("height"), "{e}");
        assert!(reproject(&ReprojectParams::default()).is_ok());
        // 3e38 m at a corner: x = (0.5 - 4) * 3e38 / 1 overflows f32
        let k = Intrinsics {
            fx: 1.0,
            fy: 1.0,
            cx: 4.0,
            cy: 4.0,
            width: 8,
            height: 8,
        };
        let mut d = DepthMap::filled(8, 8, 2.0);
        *d.get_mut(0, 0) = 3e38;
        let pc = unproject(&d, &k, None).unwrap();
        assert_eq!(pc.positions.len(), 63);
        assert!(pc.positions.iter().flatten().all(|c| c.is_finite()));
    }
}
