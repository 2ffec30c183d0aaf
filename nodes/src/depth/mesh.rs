//! `DepthToMesh`: the triangular mesh of a depth map (3d-editing Sec. III.B:
//! "3D point clouds X(p_i) and it's triangular mesh are constructed").
//!
//! Every valid pixel is unprojected through its centre (eq. 1, see
//! [`crate::depth::unproject`]); the pixel grid gives the connectivity: each 2x2 quad
//! of valid pixels becomes two triangles split along its shorter 3-D
//! diagonal, and triangles that straddle a depth discontinuity are dropped, so
//! a near object is not glued to the wall behind it by long "rubber sheet"
//! triangles.

use std::sync::Arc;

use depthgraph_graph::node_params;
use depthgraph_graph::prelude::*;

use crate::kit::checks::{fits_intrinsics, same_size};
use depthgraph_graph::registry::RegistryError;
use glam::DVec3;
use rayon::prelude::*;

node_params! {
    /// Parameters of the `DepthToMesh` node.
    pub struct MeshParams {
        /// Depth discontinuity threshold: a triangle is dropped when the depth
        /// span of its vertices (max z - min z) exceeds this fraction of its
        /// nearest vertex's depth (0.05: 5 cm at 1 m). Larger values keep more
        /// triangles across edges; 0 keeps only triangles of equal depth.
        pub max_edge_rel: f64 = 0.05, ParamKind::Float { min: 0.0, max: 100.0 };
    }
}

/// Checks the sizes of the inputs and the camera.
fn check_inputs(
    depth: &DepthMap,
    k: &Intrinsics,
    color: Option<&ColorImage>,
) -> Result<(), NodeError> {
    let (w, h) = depth.dims();
    fits_intrinsics("intrinsics", k, "depth map", (w, h))?;
    if let Some(c) = color {
        same_size("color", "a colour image", c.dims(), "the depth", (w, h))?;
    }
    if w.saturating_mul(h) > u32::MAX as usize {
        return Err(NodeError::input(
            "depth",
            format!("{w}x{h} has more pixels than 32-bit vertex indices can address"),
        ));
    }
    Ok(())
}

/// A vertex position; holes are `[0, 0, 0]` (`z = 0`).
type P3 = [f32; 3];

#[inline]
fn d3(p: P3) -> DVec3 {
    DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64)
}

/// Bits of a quad's code: split along `b-c` (else `a-d`), first / second
/// triangle of that split kept.
const DIAG_BC: u8 = 1;
const KEEP0: u8 = 2;
const KEEP1: u8 = 4;

/// Corners (bit `1 << corner number`, `a b c d` = `0 1 2 3`) used by the kept
/// triangles of a quad, by code (see [`split`]).
const CORNERS_USED: [u8; 8] = {
    let mut t = [0u8; 8];
    let mut code = 0;
    while code < 8 {
        let (t0, t1) = if code as u8 & DIAG_BC == 0 {
            (0b1101, 0b1011) // a c d, a d b
        } else {
            (0b0111, 0b1110) // a c b, b c d
        };
        if code as u8 & KEEP0 != 0 {
            t[code] |= t0;
        }
        if code as u8 & KEEP1 != 0 {
            t[code] |= t1;
        }
        code += 1;
    }
    t
};

/// Pixel indices `[a, b, c, d]` of the quad whose top-left pixel is `(x, y)`:
///
/// ```text
/// a b
/// c d    (image: x right, y down)
/// ```
#[inline]
fn corners(x: usize, y: usize, w: usize) -> [usize; 4] {
    let a = y * w + x;
    [a, a + 1, a + w, a + w + 1]
}

/// The two triangles of a quad split along `a-d` or `b-c`, as corner numbers
/// (`a b c d` = `0 1 2 3`), counter-clockwise as seen from the camera (see
/// [`depth_to_mesh`]).
#[inline]
fn split(code: u8) -> [[usize; 3]; 2] {
    if code & DIAG_BC == 0 {
        [[0, 2, 3], [0, 3, 1]]
    } else {
        [[0, 2, 1], [1, 2, 3]]
    }
}

/// The kept triangles of a quad, as corner numbers.
#[inline]
fn kept(code: u8) -> impl Iterator<Item = [usize; 3]> {
    [KEEP0, KEEP1]
        .into_iter()
        .zip(split(code))
        .filter(move |(bit, _)| code & bit != 0)
        .map(|(_, t)| t)
}

/// True when the triangle's depth span is within `rel` times its nearest depth.
#[inline]
fn continuous(z: [f32; 3], rel: f64) -> bool {
    let z = z.map(|z| z as f64);
    let lo = z[0].min(z[1]).min(z[2]);
    let hi = z[0].max(z[1]).max(z[2]);
    hi - lo <= rel * lo
}

/// Which triangles a quad keeps (its code), from its corner positions.
fn quad_code(q: [P3; 4], rel: f64) -> u8 {
    let valid = q.map(|p| p[2] > 0.0);
    let (diag, candidates) = match valid {
        [true, true, true, true] => {
            let [a, b, c, d] = q.map(d3);
            let diag = if a.distance_squared(d) <= b.distance_squared(c) {
                0
            } else {
                DIAG_BC
            };
            (diag, KEEP0 | KEEP1)
        }
        [false, true, true, true] => (DIAG_BC, KEEP1), // b c d
        [true, false, true, true] => (0, KEEP0),       // a c d
        [true, true, false, true] => (0, KEEP1),       // a d b
        [true, true, true, false] => (DIAG_BC, KEEP0), // a c b
        _ => return 0,
    };
    let mut code = diag;
    for (bit, t) in [KEEP0, KEEP1].into_iter().zip(split(diag)) {
        if candidates & bit != 0 && continuous(t.map(|i| q[i][2]), rel) {
            code |= bit;
        }
    }
    code
}

/// Splits `buf` into consecutive slices of the given lengths (which sum to
/// at most its length).
fn split_rows<'a, T>(mut buf: &'a mut [T], lens: &[usize]) -> Vec<&'a mut [T]> {
    let mut out = Vec::with_capacity(lens.len());
    for &n in lens {
        let (head, tail) = std::mem::take(&mut buf).split_at_mut(n);
        out.push(head);
        buf = tail;
    }
    out
}

/// Unit vertex normal from the sum of face cross products at `v`, facing the
/// camera.
fn vertex_normal(sum: DVec3, v: DVec3) -> [f32; 3] {
    let n = sum.normalize_or_zero();
    let n = if n == DVec3::ZERO {
        // No usable area (only through under/overflow at extreme depths):
        // the direction from the vertex to the camera.
        (-v).try_normalize().unwrap_or(DVec3::NEG_Z)
    } else if n.dot(v) > 0.0 {
        -n
    } else {
        n
    };
    n.as_vec3().to_array()
}

/// Grid triangulation of a depth map (3d-editing Sec. III.B, with the
/// unprojection of eq. 1).
///
/// - **Vertices**: one per valid pixel that belongs to a kept triangle, at
///   `k.unproject(x + 0.5, y + 0.5, z)`, in raster order (indices are
///   compact). Pixels that are not [`DepthMap::is_valid`], or whose position
///   does not fit in `f32`, are holes and give no vertex.
/// - **Triangles**: each 2x2 quad `a b / c d` of valid pixels gives two
///   triangles split along the shorter 3-D diagonal (`a-d` on ties); a quad
///   with exactly three valid pixels gives the one triangle they form. A
///   triangle is dropped when `max z - min z > max_edge_rel * min z` over its
///   vertices (a depth discontinuity). Winding: counter-clockwise as seen
///   from the camera. In the camera frame (`x` right, `y` down, `z` forward)
///   the quad `a (x, y)`, `b (x+1, y)`, `c (x, y+1)` gives `a, c, b`: its
///   normal `(c - a) x (b - a)` points to `-z`, towards the camera. Since the
///   vertices project to the pixel centres, every triangle faces the camera.
/// - **Normals**: area-weighted (sum of the faces' edge cross products),
///   unit length, oriented towards the camera (`n . X <= 0`). A vertex whose
///   triangles have no measurable area (only through floating-point
///   under/overflow at absurd depths) gets the unit vector from it to the
///   camera. Computed in `f64` from the `f32` vertex positions.
/// - **Colors**: the pixel's color when `color` is given, else none.
///
/// Rows are processed in parallel; every output element is computed by one
/// thread in a fixed order, so the mesh is identical for any thread count.
///
/// A depth map without valid pixels gives an empty mesh, not an error.
///
/// ```
/// use depthgraph_graph::value::{Image, Intrinsics};
/// use depthgraph_nodes::depth::mesh::{depth_to_mesh, MeshParams};
/// let k = Intrinsics { fx: 2.0, fy: 2.0, cx: 1.0, cy: 1.0, width: 2, height: 2 };
/// let d = Image::from_vec(2, 2, vec![1.0f32; 4]).unwrap();
/// let m = depth_to_mesh(&d, &k, None, &MeshParams::default()).unwrap();
/// assert_eq!(m.positions[0], [-0.25, -0.25, 1.0]);
/// assert_eq!(m.triangles, vec![[0, 2, 3], [0, 3, 1]]);
/// assert!(m.normals.iter().all(|n| (n[2] + 1.0).abs() < 1e-6)); // facing the camera
/// ```
pub fn depth_to_mesh(
    depth: &DepthMap,
    k: &Intrinsics,
    color: Option<&ColorImage>,
    p: &MeshParams,
) -> Result<Mesh, NodeError> {
    check_inputs(depth, k, color)?;
    let rel = p.max_edge_rel;
    if !(rel.is_finite() && rel >= 0.0) {
        return Err(NodeError::param(
            "max_edge_rel",
            format!("{rel} must be finite and non-negative"),
        ));
    }
    let (w, h) = depth.dims();
    if w < 2 || h < 2 {
        return Ok(Mesh::default());
    }

    let mut pos: Vec<P3> = vec![[0.0; 3]; w * h];
    pos.par_chunks_mut(w)
        .zip(depth.as_slice().par_chunks(w))
        .enumerate()
        .for_each(|(y, (out, zs))| {
            for (x, (p, &z)) in out.iter_mut().zip(zs).enumerate() {
                if DepthMap::is_valid(z) {
                    let v = k.unproject(x as f64 + 0.5, y as f64 + 0.5, z as f64);
                    let v = v.as_vec3();
                    if v.is_finite() && v.z > 0.0 {
                        *p = v.to_array();
                    }
                }
            }
        });

    // One code per quad, quad (x, y) at y * (w - 1) + x.
    let qw = w - 1;
    let mut codes = vec![0u8; qw * (h - 1)];
    codes.par_chunks_mut(qw).enumerate().for_each(|(y, row)| {
        for (x, c) in row.iter_mut().enumerate() {
            *c = quad_code(corners(x, y, w).map(|i| pos[i]), rel);
        }
    });

    // The quads around pixel (x, y) as (quad index, the pixel's corner
    // number in it), in a fixed order: up-left, up-right, down-left,
    // down-right; `None` past the borders.
    let around = |x: usize, y: usize| -> [Option<(usize, usize, usize)>; 4] {
        let (up, down) = (y > 0, y + 1 < h);
        let (left, right) = (x > 0, x + 1 < w);
        [
            (up && left).then(|| (x - 1, y - 1, 3)),
            (up && right).then(|| (x, y - 1, 2)),
            (down && left).then(|| (x - 1, y, 1)),
            (down && right).then_some((x, y, 0)),
        ]
    };
    let is_used = |x: usize, y: usize| {
        around(x, y)
            .into_iter()
            .flatten()
            .any(|(qx, qy, corner)| CORNERS_USED[codes[qy * qw + qx] as usize] & (1 << corner) != 0)
    };

    // Vertex counts per row, then the output buffers, filled row by row in
    // parallel (vertex ids are compact and in raster order).
    let counts: Vec<usize> = (0..h)
        .into_par_iter()
        .map(|y| (0..w).filter(|&x| is_used(x, y)).count())
        .collect();
    let n: usize = counts.iter().sum();
    let first: Vec<usize> = counts
        .iter()
        .scan(0, |acc, &c| {
            let f = *acc;
            *acc += c;
            Some(f)
        })
        .collect();
    let color_counts: Vec<usize> = if color.is_some() {
        counts.clone()
    } else {
        vec![0; h]
    };
    let mut mesh = Mesh {
        positions: vec![[0.0; 3]; n],
        normals: vec![[0.0; 3]; n],
        colors: vec![[0.0; 3]; if color.is_some() { n } else { 0 }],
        triangles: Vec::new(),
    };
    let mut ids = vec![0u32; w * h];
    split_rows(&mut mesh.positions, &counts)
        .into_par_iter()
        .zip(split_rows(&mut mesh.normals, &counts))
        .zip(split_rows(&mut mesh.colors, &color_counts))
        .zip(ids.par_chunks_mut(w))
        .enumerate()
        .for_each(|(y, (((ps, ns), cs), id_row))| {
            let mut k = 0;
            for (x, id) in id_row.iter_mut().enumerate() {
                if !is_used(x, y) {
                    continue;
                }
                // Area-weighted normal: the kept triangles' edge cross
                // products (twice their area times their unit normal).
                let mut sum = DVec3::ZERO;
                for (qx, qy, corner) in around(x, y).into_iter().flatten() {
                    let code = codes[qy * qw + qx];
                    if CORNERS_USED[code as usize] & (1 << corner) == 0 {
                        continue;
                    }
                    let q = corners(qx, qy, w).map(|i| d3(pos[i]));
                    for t in kept(code) {
                        if t.contains(&corner) {
                            let [p0, p1, p2] = t.map(|c| q[c]);
                            sum += (p1 - p0).cross(p2 - p0);
                        }
                    }
                }
                // The slices hold exactly the row's used pixels (same
                // predicate as the counts).
                let i = y * w + x;
                if let (Some(p), Some(n)) = (ps.get_mut(k), ns.get_mut(k)) {
                    *p = pos[i];
                    *n = vertex_normal(sum, d3(pos[i]));
                }
                if let (Some(c), Some(slot)) = (color, cs.get_mut(k)) {
                    *slot = c.as_slice()[i];
                }
                // Guard: fewer than u32::MAX pixels (check_inputs).
                *id = (first[y] + k) as u32;
                k += 1;
            }
        });

    let tri_counts: Vec<usize> = codes
        .par_chunks(qw)
        .map(|row| {
            row.iter()
                .map(|c| (c & (KEEP0 | KEEP1)).count_ones() as usize)
                .sum()
        })
        .collect();
    let n_tris = tri_counts.iter().sum();
    mesh.triangles = vec![[0u32; 3]; n_tris];
    split_rows(&mut mesh.triangles, &tri_counts)
        .into_par_iter()
        .zip(codes.par_chunks(qw))
        .enumerate()
        .for_each(|(y, (out, row))| {
            let mut slots = out.iter_mut();
            for (x, &code) in row.iter().enumerate() {
                let q = corners(x, y, w);
                for t in kept(code) {
                    if let Some(slot) = slots.next() {
                        *slot = t.map(|c| ids[q[c]]);
                    }
                }
            }
        });
    Ok(mesh)
}

depthgraph_graph::ports! {
    /// Inputs of `DepthToMesh`.
    inputs struct MeshIn {
        /// metres, 0 = no measurement
        depth: Arc<DepthMap>,
        /// of the depth image
        intrinsics: Intrinsics,
        /// vertex colors, same size as depth
        color: Option<Arc<ColorImage>>,
    }
}

depthgraph_graph::ports! {
    /// Outputs of `DepthToMesh`.
    outputs struct MeshOut {
        /// camera-space triangle mesh with normals (and colors when given)
        mesh: Mesh,
    }
}

fn eval(_: &EvalCtx, i: MeshIn, p: &MeshParams) -> Result<Produced<MeshOut>, NodeError> {
    let mesh = depth_to_mesh(&i.depth, &i.intrinsics, i.color.as_deref(), p)?;
    Ok(MeshOut { mesh }.into())
}

/// Registers `DepthToMesh`.
pub fn register(reg: &mut Registry) -> Result<(), RegistryError> {
    reg.register(PortedNode::new(
        "DepthToMesh",
        1,
        "Grid triangulation of a depth map (3d-editing Sec. III.B), dropping triangles across depth edges.\n\
         Vertices are the unprojected pixel centres (eq. 1) with area-weighted normals facing the camera; \
         triangles are counter-clockwise as seen from the camera.",
        eval,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::synthetic::{RenderOptions, Scene, kinect_like_intrinsics, render};
    use proptest::prelude::*;

    fn v3(a: [f32; 3]) -> DVec3 {
        glam::Vec3::from_array(a).as_dvec3()
    }

    /// Geometric normal of triangle `t` (edges in order).
    fn face_normal(m: &Mesh, t: [u32; 3]) -> (DVec3, DVec3) {
        let [a, b, c] = t.map(|i| v3(m.positions[i as usize]));
        ((b - a).cross(c - a), a)
    }

    fn check_structure(m: &Mesh) {
        let n = m.positions.len();
        assert_eq!(m.normals.len(), n);
        let mut used = vec![false; n];
        for t in &m.triangles {
            for &i in t {
                assert!((i as usize) < n, "index {i} out of {n}");
                used[i as usize] = true;
            }
        }
        assert!(used.iter().all(|u| *u), "a vertex belongs to no triangle");
        for (nrm, p) in m.normals.iter().zip(&m.positions) {
            let nv = v3(*nrm);
            assert!(
                nv.is_finite() && (nv.length() - 1.0).abs() < 1e-5,
                "{nrm:?}"
            );
            assert!(nv.dot(v3(*p)) <= 1e-9, "normal {nrm:?} faces away at {p:?}");
        }
    }

    #[test]
    fn fronto_parallel_plane() {
        let (w, h) = (23, 17);
        let k = kinect_like_intrinsics(w, h);
        let d = DepthMap::filled(w, h, 1.5);
        let m = depth_to_mesh(&d, &k, None, &MeshParams::default()).unwrap();
        assert_eq!(m.triangles.len(), 2 * (w - 1) * (h - 1));
        assert_eq!(m.positions.len(), w * h);
        assert!(m.colors.is_empty());
        check_structure(&m);
        for n in &m.normals {
            assert!((v3(*n) - DVec3::NEG_Z).length() < 1e-6, "{n:?}");
        }
        for t in &m.triangles {
            let (n, a) = face_normal(&m, *t);
            assert!(n.z < 0.0 && n.dot(a) < 0.0, "triangle {t:?} is clockwise");
        }
    }

    #[test]
    fn vertices_are_the_unprojected_pixels() {
        let (w, h) = (7, 5);
        let k = Intrinsics {
            fx: 6.0,
            fy: 7.0,
            cx: 3.1,
            cy: 2.4,
            width: w,
            height: h,
        };
        let d = Image::from_fn(w, h, |x, y| 1.0 + 0.01 * x as f32 + 0.02 * y as f32);
        let c = Image::from_fn(w, h, |x, y| [x as f32, y as f32, 0.5]);
        let m = depth_to_mesh(&d, &k, Some(&c), &MeshParams::default()).unwrap();
        assert_eq!(m.positions.len(), w * h);
        for (i, (p, col)) in m.positions.iter().zip(&m.colors).enumerate() {
            let (x, y) = (i % w, i / w);
            let q = k.unproject(x as f64 + 0.5, y as f64 + 0.5, *d.get(x, y) as f64);
            assert_eq!(*p, q.as_vec3().to_array());
            assert_eq!(*col, *c.get(x, y));
        }
        check_structure(&m);
    }

    #[test]
    fn depth_step_drops_exactly_the_triangles_across_it() {
        let (w, h) = (20, 12);
        let k = kinect_like_intrinsics(w, h);
        // Left half at 1 m, right half at 1.5 m: a 50 % jump.
        let d = Image::from_fn(w, h, |x, _| if x < w / 2 { 1.0f32 } else { 1.5 });
        let m = depth_to_mesh(&d, &k, None, &MeshParams::default()).unwrap();
        // One column of quads straddles the step: its 2 (h - 1) triangles go.
        assert_eq!(m.triangles.len(), 2 * (w - 1) * (h - 1) - 2 * (h - 1));
        for t in &m.triangles {
            let z: Vec<f32> = t.iter().map(|&i| m.positions[i as usize][2]).collect();
            assert!(z[0] == z[1] && z[1] == z[2], "triangle {t:?} spans {z:?}");
        }
        // A gentle slope (2 % per pixel) below the threshold keeps everything.
        let d = Image::from_fn(w, h, |x, _| 1.0 + 0.02 * x as f32);
        let m = depth_to_mesh(&d, &k, None, &MeshParams::default()).unwrap();
        assert_eq!(m.triangles.len(), 2 * (w - 1) * (h - 1));
        check_structure(&m);
    }

    #[test]
    fn tabletop_vertices_lie_on_the_analytic_surfaces() {
        let scene = Scene::preset("tabletop", 64, 48).unwrap();
        let out = render(&scene, &RenderOptions::default());
        let k = out.intrinsics;
        let m = depth_to_mesh(&out.depth, &k, Some(&out.color), &MeshParams::default()).unwrap();
        check_structure(&m);
        assert!(
            m.triangles.len() > 64 * 48,
            "{} triangles",
            m.triangles.len()
        );
        let mut plane_vertices = 0;
        for (p, n) in m.positions.iter().zip(&m.normals) {
            let p = v3(*p);
            let uv = k.project(p).unwrap();
            let (x, y) = (uv.x.floor() as usize, uv.y.floor() as usize);
            let id = *out.ids.get(x, y);
            let dist = scene.signed_distance(id, p).unwrap();
            assert!(dist.abs() < 1e-5, "vertex {p} is {dist} m off object {id}");
            // Inside a plane (3x3 pixels of the same planar object), the
            // vertex normal is the plane's.
            let planar = matches!(
                scene.object(id).map(|o| o.primitive),
                Some(crate::sim::synthetic::Primitive::Plane { .. })
            );
            let interior = (x > 0 && y > 0 && x + 1 < k.width && y + 1 < k.height)
                && (0..9).all(|j| *out.ids.get(x + j % 3 - 1, y + j / 3 - 1) == id);
            if planar && interior {
                plane_vertices += 1;
                let truth = v3(*out.normals.get(x, y));
                assert!((v3(*n) - truth).length() < 1e-4, "{n:?} vs {truth}");
            }
        }
        assert!(plane_vertices > 500, "{plane_vertices}");
        for t in &m.triangles {
            let (n, a) = face_normal(&m, *t);
            assert!(n.dot(a) < 0.0, "triangle {t:?} faces away from the camera");
        }
    }

    #[test]
    fn holes_give_no_vertices() {
        let (w, h) = (10, 8);
        let k = kinect_like_intrinsics(w, h);
        // Checkerboard of holes: no quad has three valid pixels.
        let d = Image::from_fn(w, h, |x, y| if (x + y) % 2 == 0 { 1.0f32 } else { 0.0 });
        let m = depth_to_mesh(&d, &k, None, &MeshParams::default()).unwrap();
        assert!(m.positions.is_empty() && m.triangles.is_empty());
        // One hole in a plane: the four quads around it keep one triangle each.
        let bad = [0.0, -2.0, f32::NAN, f32::INFINITY];
        for z in bad {
            let d = Image::from_fn(w, h, |x, y| if (x, y) == (4, 3) { z } else { 1.0 });
            let m = depth_to_mesh(&d, &k, None, &MeshParams::default()).unwrap();
            assert_eq!(m.positions.len(), w * h - 1);
            assert_eq!(m.triangles.len(), 2 * (w - 1) * (h - 1) - 4);
            check_structure(&m);
        }
        // A lone valid pixel has no triangle, hence no vertex.
        let d = Image::from_fn(w, h, |x, y| if (x, y) == (2, 2) { 1.0f32 } else { 0.0 });
        let m = depth_to_mesh(&d, &k, None, &MeshParams::default()).unwrap();
        assert!(m.positions.is_empty());
    }

    #[test]
    fn all_holes_give_an_empty_mesh() {
        let k = kinect_like_intrinsics(6, 4);
        let m = depth_to_mesh(
            &DepthMap::filled(6, 4, 0.0),
            &k,
            None,
            &MeshParams::default(),
        )
        .unwrap();
        assert_eq!(m, Mesh::default());
        for (w, h) in [(1, 1), (1, 5), (5, 1)] {
            let k = kinect_like_intrinsics(w, h);
            let m =
                depth_to_mesh(&DepthMap::filled(w, h, 1.0), &k, None, &Default::default()).unwrap();
            assert_eq!(m, Mesh::default());
        }
    }

    #[test]
    fn mismatched_sizes_name_the_port() {
        let k = kinect_like_intrinsics(16, 12);
        let p = MeshParams::default();
        let e = depth_to_mesh(&DepthMap::filled(8, 6, 1.0), &k, None, &p).unwrap_err();
        let s = e.to_string();
        assert!(
            s.contains("depth") && s.contains("8x6") && s.contains("16x12"),
            "{s}"
        );
        let d = DepthMap::filled(16, 12, 1.0);
        let e = depth_to_mesh(&d, &k, Some(&ColorImage::filled(4, 4, [0.0; 3])), &p).unwrap_err();
        assert!(e.to_string().contains("color") && e.to_string().contains("4x4"));
        let bad_k = Intrinsics { fx: 0.0, ..k };
        let e = depth_to_mesh(&d, &bad_k, None, &p).unwrap_err();
        assert!(e.to_string().contains("intrinsics"), "{e}");
        let e = depth_to_mesh(
            &d,
            &k,
            None,
            &MeshParams {
                max_edge_rel: f64::NAN,
            },
        )
        .unwrap_err();
        assert!(e.to_string().contains("max_edge_rel"), "{e}");
    }

    fn depth_value() -> impl Strategy<Value = f32> {
        prop_oneof![
            3 => 0.2f32..5.0,
            1 => Just(0.0f32),
            1 => prop_oneof![Just(f32::NAN), Just(-1.0f32), Just(f32::INFINITY), Just(1e-30f32), Just(1e30f32)],
        ]
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]
        #[test]
        fn indices_in_range_and_normals_finite(
            w in 1usize..9,
            h in 1usize..9,
            values in prop::collection::vec(depth_value(), 64),
            rel in 0.0f64..2.0,
        ) {
            let d = Image::from_vec(w, h, values[..w * h].to_vec()).unwrap();
            let k = kinect_like_intrinsics(w, h);
            let m = depth_to_mesh(&d, &k, None, &MeshParams { max_edge_rel: rel }).unwrap();
            check_structure(&m);
            for p in &m.positions {
                prop_assert!(p.iter().all(|c| c.is_finite()) && p[2] > 0.0);
            }
            for t in &m.triangles {
                prop_assert!(t[0] != t[1] && t[1] != t[2] && t[0] != t[2]);
            }
        }
    }
}
