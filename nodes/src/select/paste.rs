//! `Paste`: places a selected source object into a target RGB-D image
//! (3d-editing §III.C, last two paragraphs: "the source depth image is
//! scaled to the suggested initial value [...] so as the bounding box of
//! source object doesn't penetrate the target surface. Then a user is able
//! to adjust the scale value [...] Finally the source object is moved to the
//! desired target location").
//!
//! Both cameras sit at the origin of their own frame looking along `+z`; a
//! placement is a uniform scale, a rotation about the object's centroid
//! and a translation (the paper's editor offers scale and translation; its
//! future work asks for "more degrees of freedom").
//!
//! 1. **Object points**: every source pixel with `mask >= mask_threshold` and
//!    a valid depth is unprojected with the source intrinsics (eq. 1) at its
//!    pixel centre. With `largest_surface_only`, only the largest
//!    depth-connected part of the selection is kept (4-neighbours whose
//!    depths differ by at most `max_depth_jump_rel`), which drops the
//!    background pixels a lasso may catch along the object's outline: they
//!    would otherwise float behind the pasted object and inflate its box.
//!    `c` is their centroid, `B0 = [lo, hi]` their axis-aligned bounding box;
//!    with `close_back` (step 5) the box is that of the front and back
//!    points together (the solid's) and `c_s` their centroid.
//! 2. **Placement**: the object becomes `X' = P + s (R (X - c_s) + c_s - c)`:
//!    turned by the rotation `R` of `rotation_deg` ([`rotation`]) about
//!    the solid's centroid `c_s` (step 5; `c` without `close_back`), then
//!    scaled about `c` and moved, with
//!    - `P = c + translation_m` when `target_pixel` is empty, or
//!    - `P = K_t^-1 (u, v, z_t(u, v) + depth_offset_m) + translation_m` for
//!      the one `target_pixel` `(u, v)`: the centroid goes onto that pixel's
//!      ray, `depth_offset_m` from the target surface there (negative: in
//!      front of it);
//!
//!    and `s = s_suggested * scale` (`s_suggested = 1` without `auto_scale`).
//! 3. **Suggested scale** ([`suggest_scale`]): the largest `s` in `(0, 1]`
//!    (1 = the physical size: both images are in metres) for which the box
//!    `B(s) = P + s (B0 - c)` **does not penetrate the target surface**: no
//!    target pixel's surface point (its centre unprojected at its depth)
//!    lies inside `B(s)` ([`box_penetrates`]). Along every pixel ray the box
//!    is then wholly in front of the surface (visible) or wholly behind it
//!    (hidden by a nearer object, which the composite's depth test handles),
//!    never straddling it. Since `c` lies in `B0`, the boxes are nested and
//!    grow with `s`; each surface point enters them at a scale known in
//!    closed form, so the suggested scale is exactly the smallest of those
//!    (capped at 1). The surface is known only at pixel centres; target
//!    holes constrain nothing.
//! 4. **Forward warp without cracks**: the source pixel grid is a mesh (two
//!    triangles per 2x2 cell of object pixels, one where a corner is
//!    missing), cut where a triangle's depths differ by more than
//!    `max_depth_jump_rel` (a depth discontinuity, not a surface). Every
//!    triangle is projected with the target intrinsics and rasterised at
//!    target pixel centres with perspective-correct interpolation; object
//!    pixels in no triangle are splatted as single pixels. Visibility is a
//!    z-buffer: each pixel keeps the nearest fragment (ties: the lower
//!    triangle id), computed with an atomic minimum over `(depth bits, id)`,
//!    so the result is the same for any number of threads. Colors and the
//!    source alpha are interpolated in a second pass.
//! 5. **The closed back** (`close_back`): the selection's unseen back is
//!    its front mirrored about the silhouette plane
//!    ([`crate::relight::closure`]); it is meshed and drawn like the front,
//!    so a rotation that turns the back towards the camera shows a solid,
//!    not a hollow shell. Its colour is unknown: each back fragment takes
//!    the colour (and alpha) of the front pixel whose view ray it shares,
//!    interpolated like the front's (the visible colour mirrored through
//!    the object: exact for objects symmetric about the silhouette plane,
//!    a plausible fill otherwise), and the `back` output marks those
//!    pixels for the user or an inpainting node. Without rotation the
//!    front hides the back entirely and the result is that of the front
//!    alone.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicU64, Ordering};

use std::sync::Arc;

use depthgraph_graph::node_params;
use depthgraph_graph::prelude::*;
use depthgraph_graph::registry::RegistryError;

use crate::kit::checks::{fits_intrinsics, sane_intrinsics};
use crate::kit::grid::neighbours4;
use glam::DVec3;
use rayon::prelude::*;

/// Points nearer than this (metres) to the camera plane are not projected.
const Z_NEAR: f64 = 1e-6;
/// Suggested scales below this mean that no size fits at the placement.
pub const MIN_SUGGESTED_SCALE: f64 = 1e-4;
/// Barycentric tolerance of the rasteriser: pixel centres on a triangle's
/// edge (and within rounding of it) belong to it, so meshes have no cracks.
const EDGE_EPS: f64 = 1e-9;

node_params! {
    /// Parameters of `Paste`.
    pub struct PasteParams {
        /// User scale: multiplies the suggested scale (with auto_scale) or is
        /// the scale (without).
        pub scale: f64 = 1.0, ParamKind::Float { min: 1e-3, max: 1e3 };
        /// Translation of the object's centroid in metres (camera frame: x
        /// right, y down, z forward); added to the target-pixel placement too.
        pub translation_m: [f64; 3] = [0.0, 0.0, 0.0], ParamKind::Vec3 { min: -1e4, max: 1e4 };
        /// Empty, or one (x, y) target pixel: the centroid is placed on its
        /// ray at the target depth there plus depth_offset_m.
        pub target_pixel: Vec<[f64; 2]> = Vec::new(), ParamKind::Points;
        /// With target_pixel: depth of the centroid relative to the target
        /// surface at that pixel, metres (negative = in front of it).
        pub depth_offset_m: f64 = -0.2, ParamKind::Float { min: -1e4, max: 1e4 };
        /// Scale the object to the largest size (at most its physical size)
        /// whose bounding box the target surface does not pass through (3d-editing §III.C).
        pub auto_scale: bool = true, ParamKind::Bool;
        /// Source pixels with mask >= this belong to the object.
        pub mask_threshold: f64 = 0.5, ParamKind::Float { min: 1e-6, max: 1.0 };
        /// Mesh cells whose depths differ by more than this fraction are cut
        /// (a depth discontinuity); also the connectivity of largest_surface_only.
        pub max_depth_jump_rel: f64 = 0.1, ParamKind::Float { min: 1e-6, max: 100.0 };
        /// Keep only the largest depth-connected part of the selection.
        pub largest_surface_only: bool = true, ParamKind::Bool;
        /// Rotation about the object's centroid, degrees: (yaw about the vertical,
        /// pitch about the camera's x axis, roll about its view axis), applied roll, pitch, yaw.
        pub rotation_deg: [f64; 3] = [0.0, 0.0, 0.0], ParamKind::Vec3 { min: -360.0, max: 360.0 };
        /// Close the object's unseen back (its front mirrored about the silhouette plane) so a
        /// rotation can bring it into view; its pixels are marked in `back`.
        pub close_back: bool = true, ParamKind::Bool;
    }
}

/// The rotation of `rotation_deg` (module docs, step 2): `R = R_y(yaw)
/// R_x(pitch) R_z(roll)` in the camera frame (`y` down), so yaw turns the
/// object about the vertical through its centroid.
pub fn rotation(rotation_deg: [f64; 3]) -> glam::DMat3 {
    let [yaw, pitch, roll] = rotation_deg.map(f64::to_radians);
    glam::DMat3::from_rotation_y(yaw)
        * glam::DMat3::from_rotation_x(pitch)
        * glam::DMat3::from_rotation_z(roll)
}

/// The selected object in the source camera frame.
#[derive(Debug, Clone, PartialEq)]
pub struct SourceObject {
    /// Per source pixel: whether it is an object point.
    pub member: Vec<bool>,
    /// Number of object points.
    pub count: usize,
    /// Centroid `c` (metres, source camera frame).
    pub centroid: DVec3,
    /// Axis-aligned bounding box `B0` of the object points: its minimum
    /// corner (metres, source camera frame).
    pub lo: DVec3,
    /// Maximum corner of `B0` (metres, source camera frame).
    pub hi: DVec3,
}

/// The pasted layer in target pixels.
#[derive(Debug, Clone, PartialEq)]
pub struct Pasted {
    /// Object color, black where nothing was pasted.
    pub color: ColorImage,
    /// Object depth in metres, 0 where nothing was pasted.
    pub depth: DepthMap,
    /// Object alpha (the source mask, interpolated), 0 where nothing was pasted.
    pub alpha: Mask,
    /// 1 where the pixel shows the object's closed back (step 5), else 0.
    pub back: Mask,
    /// The scale used: suggested x user scale.
    pub scale: f64,
    /// The suggested scale (1 without auto_scale).
    pub suggested_scale: f64,
    /// Where the centroid went, `P` (metres, target camera frame).
    pub anchor: DVec3,
    /// Number of source object points (0: nothing was selected).
    pub object_points: usize,
}

fn check_same(port: &str, a: (usize, usize), depth: (usize, usize)) -> Result<(), NodeError> {
    if a != depth {
        return Err(NodeError::input(
            port,
            format!(
                "is {}x{} but the source depth is {}x{}",
                a.0, a.1, depth.0, depth.1
            ),
        ));
    }
    Ok(())
}

#[inline]
fn depth_ok(z: f32) -> bool {
    DepthMap::is_valid(z)
}

/// Depths `a`, `b` (valid) are on one surface: ratio at most `1 + jump`.
#[inline]
fn connected(a: f64, b: f64, jump: f64) -> bool {
    // guard: both > 0 (valid depths)
    a.max(b) / a.min(b) <= 1.0 + jump
}

/// Step 1 of the module docs: the object points of the selection.
pub fn source_object(
    depth: &DepthMap,
    mask: &Mask,
    k: &Intrinsics,
    mask_threshold: f64,
    max_depth_jump_rel: f64,
    largest_surface_only: bool,
) -> SourceObject {
    let (w, h) = depth.dims();
    let n = w * h;
    let t = mask_threshold as f32;
    let mut member: Vec<bool> = depth
        .as_slice()
        .par_iter()
        .zip(mask.as_slice().par_iter())
        .map(|(&z, &a)| depth_ok(z) && a >= t)
        .collect();
    if largest_surface_only {
        let z = depth.as_slice();
        let mut label = vec![u32::MAX; n];
        let mut best = (0usize, u32::MAX);
        let mut queue = VecDeque::new();
        let mut next = 0u32;
        for seed in 0..n {
            if !member[seed] || label[seed] != u32::MAX {
                continue;
            }
            let mut size = 0usize;
            label[seed] = next;
            queue.push_back(seed);
            while let Some(i) = queue.pop_front() {
                size += 1;
                let zi = z[i] as f64;
                for j in neighbours4(i, w, h) {
                    if member[j]
                        && label[j] == u32::MAX
                        && connected(zi, z[j] as f64, max_depth_jump_rel)
                    {
                        label[j] = next;
                        queue.push_back(j);
                    }
                }
            }
            if size > best.0 {
                best = (size, next);
            }
            next += 1;
        }
        for (m, l) in member.iter_mut().zip(&label) {
            *m = *m && *l == best.1;
        }
    }
    // Centroid and box, summed in f64 per row then over rows.
    let rows: Vec<(usize, DVec3, DVec3, DVec3)> = (0..h)
        .into_par_iter()
        .map(|y| {
            let (mut cnt, mut sum) = (0usize, DVec3::ZERO);
            let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
            for x in 0..w {
                let i = y * w + x;
                if member[i] {
                    let p = k.unproject(x as f64 + 0.5, y as f64 + 0.5, depth.as_slice()[i] as f64);
                    cnt += 1;
                    sum += p;
                    lo = lo.min(p);
                    hi = hi.max(p);
                }
            }
            (cnt, sum, lo, hi)
        })
        .collect();
    let (mut count, mut sum) = (0usize, DVec3::ZERO);
    let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
    for (c, s, l, u) in rows {
        count += c;
        sum += s;
        lo = lo.min(l);
        hi = hi.max(u);
    }
    // guard: count > 0 checked; an empty object has no centroid or box
    let centroid = if count > 0 {
        sum / count as f64
    } else {
        DVec3::ZERO
    };
    if count == 0 {
        lo = DVec3::ZERO;
        hi = DVec3::ZERO;
    }
    SourceObject {
        member,
        count,
        centroid,
        lo,
        hi,
    }
}

/// The target pixels whose unprojected surface point can lie in the box
/// `[lo, hi]`: the bounding rectangle of the projected corners (all pixels
/// when the box reaches `z <= Z_NEAR`), as inclusive `(x0, x1, y0, y1)`, or
/// `None` when it misses the image.
fn box_rect(
    k: &Intrinsics,
    w: usize,
    h: usize,
    lo: DVec3,
    hi: DVec3,
) -> Option<(usize, usize, usize, usize)> {
    if w == 0 || h == 0 || hi.z <= Z_NEAR {
        return None;
    }
    if lo.z <= Z_NEAR {
        return Some((0, w - 1, 0, h - 1));
    }
    let (mut umin, mut umax, mut vmin, mut vmax) = (
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::INFINITY,
        f64::NEG_INFINITY,
    );
    for c in 0..8 {
        let p = DVec3::new(
            if c & 1 == 0 { lo.x } else { hi.x },
            if c & 2 == 0 { lo.y } else { hi.y },
            if c & 4 == 0 { lo.z } else { hi.z },
        );
        let uv = k.project(p)?;
        umin = umin.min(uv.x);
        umax = umax.max(uv.x);
        vmin = vmin.min(uv.y);
        vmax = vmax.max(uv.y);
    }
    // pixels whose centre x + 0.5 lies in [umin, umax] (one pixel of slack for rounding)
    let x0 = (umin - 1.5).ceil().max(0.0);
    let x1 = (umax + 0.5).floor().min((w - 1) as f64);
    let y0 = (vmin - 1.5).ceil().max(0.0);
    let y1 = (vmax + 0.5).floor().min((h - 1) as f64);
    if !(x0 <= x1 && y0 <= y1) {
        return None;
    }
    Some((x0 as usize, x1 as usize, y0 as usize, y1 as usize))
}

/// The target's surface point at pixel `(x, y)` (its centre unprojected at
/// the target depth), `None` at a hole. Callers check `k.is_sane()`.
#[inline]
fn surface_point(target: &DepthMap, k: &Intrinsics, x: usize, y: usize) -> Option<DVec3> {
    let z = *target.get(x, y);
    depth_ok(z).then(|| k.unproject(x as f64 + 0.5, y as f64 + 0.5, z as f64))
}

/// Whether the target surface passes through the box `[lo, hi]` (target
/// camera frame): some target pixel's surface point (its centre unprojected
/// at its depth) lies strictly inside the box. Along that pixel's ray the
/// box then reaches both in front of and behind the surface. A box wholly
/// in front of the surface, or wholly behind a nearer object (hidden, not
/// penetrating), does not penetrate; target holes constrain nothing.
pub fn box_penetrates(target: &DepthMap, k: &Intrinsics, lo: DVec3, hi: DVec3) -> bool {
    let (w, h) = target.dims();
    if !k.is_sane() {
        return false;
    }
    let Some((x0, x1, y0, y1)) = box_rect(k, w, h, lo, hi) else {
        return false;
    };
    (y0..=y1).into_par_iter().any(|y| {
        (x0..=x1).any(|x| {
            surface_point(target, k, x, y).is_some_and(|q| q.cmpgt(lo).all() && q.cmplt(hi).all())
        })
    })
}

/// Smallest `s >= 0` at which the point `q` is in the box
/// `anchor + s [lo_rel, hi_rel]` (`lo_rel <= 0 <= hi_rel`); infinite when it
/// never is (the box is flat along an axis on which `q` is off the anchor).
#[inline]
fn entry_scale(q: DVec3, anchor: DVec3, lo_rel: DVec3, hi_rel: DVec3) -> f64 {
    let d = q - anchor;
    let mut s = 0.0f64;
    for a in 0..3 {
        let need = if d[a] > 0.0 {
            // guard: divide only by a positive extent
            if hi_rel[a] > 0.0 {
                d[a] / hi_rel[a]
            } else {
                f64::INFINITY
            }
        } else if d[a] < 0.0 {
            if lo_rel[a] < 0.0 {
                d[a] / lo_rel[a]
            } else {
                f64::INFINITY
            }
        } else {
            0.0
        };
        s = s.max(need);
    }
    s
}

/// The suggested scale of 3d-editing §III.C (see the module docs, step 3):
/// the largest `s` in `(0, 1]` such that the box `anchor + s (lo_rel, hi_rel)`
/// (`lo_rel <= 0 <= hi_rel`, the object's box about its centroid) does not
/// [`box_penetrates`] the target surface. Exact: each surface point enters
/// the growing box at a scale computed in closed form, and the answer is the
/// smallest of them (capped at 1; at that scale the nearest surface point
/// touches the box). Fails, naming the placement parameters, when the anchor
/// is not in front of the camera or the surface passes through (or within
/// [`MIN_SUGGESTED_SCALE`] of) the anchor itself.
pub fn suggest_scale(
    target: &DepthMap,
    k: &Intrinsics,
    anchor: DVec3,
    lo_rel: DVec3,
    hi_rel: DVec3,
) -> Result<f64, NodeError> {
    let (w, h) = target.dims();
    let placement_err = |what: String| {
        NodeError::Invalid(format!(
            "auto_scale: {what}; move the object (translation_m, or target_pixel with a negative depth_offset_m) or turn auto_scale off"
        ))
    };
    if anchor.z.is_nan() || anchor.z <= Z_NEAR {
        return Err(placement_err(format!(
            "the centroid would be at z = {:.4} m, not in front of the camera",
            anchor.z
        )));
    }
    sane_intrinsics("target_intrinsics", k)?;
    let Some((x0, x1, y0, y1)) = box_rect(k, w, h, anchor + lo_rel, anchor + hi_rel) else {
        return Ok(1.0);
    };
    let s = (y0..=y1)
        .into_par_iter()
        .map(|y| {
            (x0..=x1)
                .filter_map(|x| surface_point(target, k, x, y))
                .map(|q| entry_scale(q, anchor, lo_rel, hi_rel))
                .fold(f64::INFINITY, f64::min)
        })
        .reduce(|| f64::INFINITY, f64::min)
        .min(1.0);
    if s.is_nan() || s < MIN_SUGGESTED_SCALE {
        return Err(placement_err(format!(
            "the target surface passes within a scale of {MIN_SUGGESTED_SCALE} of the centroid at ({:.3}, {:.3}, {:.3}) m (it is on or inside the surface)",
            anchor.x, anchor.y, anchor.z
        )));
    }
    Ok(s)
}

/// Vertices of the (up to) two triangles of the mesh cell whose top-left
/// source pixel is `i` (see the module docs), before the depth cut.
#[inline]
fn cell_triangles(member: &[bool], w: usize, i: usize) -> [Option<[usize; 3]>; 2] {
    let (a, b, c, d) = (i, i + 1, i + w, i + w + 1);
    match (member[a], member[b], member[c], member[d]) {
        (true, true, true, true) => [Some([a, b, c]), Some([b, d, c])],
        (false, true, true, true) => [None, Some([b, d, c])],
        (true, true, true, false) => [Some([a, b, c]), None],
        (true, false, true, true) => [Some([a, d, c]), None],
        (true, true, false, true) => [Some([a, b, d]), None],
        _ => [None, None],
    }
}

/// Edge function: twice the signed area of `(a, b, p)`.
#[inline]
fn edge(a: [f64; 3], b: [f64; 3], px: f64, py: f64) -> f64 {
    (b[0] - a[0]) * (py - a[1]) - (b[1] - a[1]) * (px - a[0])
}

/// Screen-space barycentrics of `(px, py)` in triangle `t`, `None` when the
/// triangle is degenerate.
#[inline]
fn barycentric(t: &[[f64; 3]; 3], px: f64, py: f64) -> Option<[f64; 3]> {
    let area = edge(t[0], t[1], t[2][0], t[2][1]);
    if area.is_nan() || area.abs() <= 1e-12 {
        return None;
    }
    // guard: |area| > 1e-12
    let l0 = edge(t[1], t[2], px, py) / area;
    let l1 = edge(t[2], t[0], px, py) / area;
    Some([l0, l1, 1.0 - l0 - l1])
}

/// Perspective-correct weights from screen barycentrics `l` and vertex
/// depths `z` (all > 0): `w_i = (l_i / z_i) / sum_j (l_j / z_j)`, and the
/// interpolated depth `1 / sum_j (l_j / z_j)`.
#[inline]
fn perspective(l: [f64; 3], z: [f64; 3]) -> Option<([f64; 3], f64)> {
    // guard: vertex depths >= Z_NEAR > 0
    let q = [l[0] / z[0], l[1] / z[1], l[2] / z[2]];
    let s = q[0] + q[1] + q[2];
    if !(s > 0.0 && s.is_finite()) {
        return None;
    }
    // guard: s > 0
    Some(([q[0] / s, q[1] / s, q[2] / s], 1.0 / s))
}

/// Places the selected object into the target (3d-editing §III.C; see the
/// module docs for every step and definition).
#[allow(clippy::too_many_arguments)]
pub fn paste(
    src_color: &ColorImage,
    src_depth: &DepthMap,
    src_mask: &Mask,
    k_src: &Intrinsics,
    tgt_depth: &DepthMap,
    k_tgt: &Intrinsics,
    p: &PasteParams,
) -> Result<Pasted, NodeError> {
    check_same("source_color", src_color.dims(), src_depth.dims())?;
    let source = paste_source(src_depth, src_mask, k_src, p)?;
    let images = SourceImages {
        color: src_color,
        depth: src_depth,
        mask: src_mask,
        k: k_src,
    };
    paste_placed(&source, &images, tgt_depth, k_tgt, p)
}

/// The source's images, as [`paste_placed`] reads them.
#[derive(Debug, Clone, Copy)]
pub struct SourceImages<'a> {
    /// Linear RGB.
    pub color: &'a ColorImage,
    /// Metres, hole-filled.
    pub depth: &'a DepthMap,
    /// The object's alpha.
    pub mask: &'a Mask,
    /// The source camera.
    pub k: &'a Intrinsics,
}

/// What a paste takes from the source alone (steps 1 and 5 of the module
/// docs): it does not depend on the placement, so `Paste` keeps it as a
/// value the engine caches while the object is moved, turned or scaled.
#[derive(Debug, Clone, PartialEq)]
pub struct PasteSource {
    /// The object points of the selection.
    pub obj: SourceObject,
    /// The closed back's depth per source pixel (`close_back`), 0 off the
    /// object.
    pub back_z: Option<Vec<f32>>,
    /// The solid's centroid `c_s` (step 5; `c` without the back).
    pub pivot: DVec3,
    /// The solid's box: its minimum corner.
    pub solid_lo: DVec3,
    /// The solid's box: its maximum corner.
    pub solid_hi: DVec3,
    /// The source pixels of the object, `(x0, x1, y0, y1)` inclusive;
    /// `None` without object points.
    pub rect: Option<(usize, usize, usize, usize)>,
    /// The source's size.
    pub dims: (usize, usize),
}

impl depthgraph_graph::value::Extension for PasteSource {
    fn type_name(&self) -> &'static str {
        "PasteSource"
    }
    fn bytes(&self) -> usize {
        self.obj.member.len() + self.back_z.as_ref().map_or(0, |b| 4 * b.len())
    }
    fn encode(&self) -> Option<Vec<u8>> {
        None
    }
    fn as_any(&self) -> &dyn std::any::Any {
        self
    }
}

/// The inputs [`paste_source`] reads (the key of the cached value, with
/// [`source_key_params`]).
pub const SOURCE_PORTS: &[&str] = &["source_depth", "source_mask", "source_intrinsics"];

/// The parameters [`paste_source`] reads, canonically encoded.
pub fn source_key_params(p: &PasteParams) -> Vec<u8> {
    let mut b = Vec::with_capacity(18);
    b.extend(p.mask_threshold.to_le_bytes());
    b.extend(p.max_depth_jump_rel.to_le_bytes());
    b.push(u8::from(p.largest_surface_only));
    b.push(u8::from(p.close_back));
    b
}

/// The source part of a paste ([`PasteSource`]): the inputs' sizes and
/// the parameters it reads checked, the object points, the closed back.
pub fn paste_source(
    src_depth: &DepthMap,
    src_mask: &Mask,
    k_src: &Intrinsics,
    p: &PasteParams,
) -> Result<PasteSource, NodeError> {
    let (sw, sh) = src_depth.dims();
    check_same("source_mask", src_mask.dims(), (sw, sh))?;
    fits_intrinsics("source_intrinsics", k_src, "source image", (sw, sh))?;
    if !(p.max_depth_jump_rel.is_finite() && p.max_depth_jump_rel > 0.0) {
        return Err(NodeError::param(
            "max_depth_jump_rel",
            format!("{} must be finite and > 0", p.max_depth_jump_rel),
        ));
    }
    let n = sw * sh;
    if n.saturating_mul(6) >= u32::MAX as usize {
        return Err(NodeError::input(
            "source_depth",
            format!("{sw}x{sh} is too large to paste (at most about 1.4e9 pixels)"),
        ));
    }
    let obj = source_object(
        src_depth,
        src_mask,
        k_src,
        p.mask_threshold,
        p.max_depth_jump_rel,
        p.largest_surface_only,
    );
    // The closed back (step 5), and the pivot and box of the solid: its
    // front's with the back's points.
    let src_z = src_depth.as_slice();
    let member = &obj.member;
    let back_z: Option<Vec<f32>> = p.close_back.then(|| {
        let front = Image::from_fn(sw, sh, |x, y| {
            if member[y * sw + x] {
                src_z[y * sw + x]
            } else {
                0.0
            }
        });
        crate::relight::closure::back_depth(&front, k_src)
            .as_slice()
            .to_vec()
    });
    let rect = member_rect(member, sw, sh);
    let (pivot, solid_lo, solid_hi) = match (&back_z, rect) {
        (Some(bz), Some((x0, x1, y0, y1))) if obj.count > 0 => {
            let (mut sum, mut lo, mut hi) = (DVec3::ZERO, obj.lo, obj.hi);
            for y in y0..=y1 {
                for x in (x0..=x1).filter(|&x| member[y * sw + x]) {
                    let i = y * sw + x;
                    let (u, v) = (x as f64 + 0.5, y as f64 + 0.5);
                    let f = k_src.unproject(u, v, f64::from(src_z[i]));
                    let b = k_src.unproject(u, v, f64::from(bz[i]));
                    sum += f + b;
                    lo = lo.min(b);
                    hi = hi.max(b);
                }
            }
            // guard: count > 0
            (sum / (2 * obj.count) as f64, lo, hi)
        }
        _ => (obj.centroid, obj.lo, obj.hi),
    };
    Ok(PasteSource {
        obj,
        back_z,
        pivot,
        solid_lo,
        solid_hi,
        rect,
        dims: (sw, sh),
    })
}

/// The smallest rectangle `(x0, x1, y0, y1)` (inclusive) holding every
/// `true` of `member` (`w` x `h`), `None` when there is none.
fn member_rect(member: &[bool], w: usize, h: usize) -> Option<(usize, usize, usize, usize)> {
    let (mut x0, mut x1, mut y0, mut y1) = (usize::MAX, 0, usize::MAX, 0);
    for y in 0..h {
        let row = &member[y * w..(y + 1) * w];
        if let (Some(a), Some(b)) = (row.iter().position(|&m| m), row.iter().rposition(|&m| m)) {
            x0 = x0.min(a);
            x1 = x1.max(b);
            y0 = y0.min(y);
            y1 = y1.max(y);
        }
    }
    (x0 <= x1).then_some((x0, x1, y0, y1))
}

/// The placement part of a paste (steps 2 to 5 of the module docs) with
/// the source part `source` that [`paste_source`] made of the same
/// images' depth, mask and camera with the same parameters.
pub fn paste_placed(
    source: &PasteSource,
    images: &SourceImages,
    tgt_depth: &DepthMap,
    k_tgt: &Intrinsics,
    p: &PasteParams,
) -> Result<Pasted, NodeError> {
    let SourceImages {
        color: src_color,
        depth: src_depth,
        mask: src_mask,
        k: k_src,
    } = *images;
    let (sw, sh) = src_depth.dims();
    if source.dims != (sw, sh) {
        return Err(NodeError::input(
            "source_depth",
            format!(
                "is {sw}x{sh} but the source part was made of {}x{}",
                source.dims.0, source.dims.1
            ),
        ));
    }
    check_same("source_color", src_color.dims(), (sw, sh))?;
    check_same("source_mask", src_mask.dims(), (sw, sh))?;
    let (tw, th) = tgt_depth.dims();
    fits_intrinsics("target_intrinsics", k_tgt, "target image", (tw, th))?;
    if !(p.scale.is_finite() && p.scale > 0.0) {
        return Err(NodeError::param(
            "scale",
            format!("{} must be finite and > 0", p.scale),
        ));
    }
    if p.translation_m.iter().any(|v| !v.is_finite()) || !p.depth_offset_m.is_finite() {
        return Err(NodeError::param(
            "translation_m",
            "translation and depth offset must be finite",
        ));
    }
    let n = sw * sh;
    if tw.saturating_mul(th) >= u32::MAX as usize {
        return Err(NodeError::input(
            "target_depth",
            format!("{tw}x{th} is too large to paste into (at most about 4.3e9 pixels)"),
        ));
    }
    let obj = &source.obj;
    let empty = |anchor: DVec3| Pasted {
        color: Image::filled(tw, th, [0.0; 3]),
        depth: Image::filled(tw, th, 0.0),
        alpha: Image::filled(tw, th, 0.0),
        back: Image::filled(tw, th, 0.0),
        scale: p.scale,
        suggested_scale: 1.0,
        anchor,
        object_points: 0,
    };
    let src_z = src_depth.as_slice();
    let member = &obj.member;
    let back_z = &source.back_z;
    let (pivot, solid_lo, solid_hi) = (source.pivot, source.solid_lo, source.solid_hi);
    let t = DVec3::from_array(p.translation_m);
    // Placement (step 2).
    let anchor = match p.target_pixel.as_slice() {
        [] => obj.centroid + t,
        [[u, v]] => {
            if !(u.is_finite()
                && v.is_finite()
                && *u >= 0.0
                && *v >= 0.0
                && *u < tw as f64
                && *v < th as f64)
            {
                return Err(NodeError::param(
                    "target_pixel",
                    format!("({u}, {v}) is outside the {tw}x{th} target"),
                ));
            }
            let z = *tgt_depth.get(*u as usize, *v as usize);
            if !depth_ok(z) {
                return Err(NodeError::param(
                    "target_pixel",
                    format!(
                        "the target depth has no measurement at ({}, {}); fill its holes first or pick another pixel",
                        *u as usize, *v as usize
                    ),
                ));
            }
            k_tgt.unproject(*u, *v, z as f64 + p.depth_offset_m) + t
        }
        more => {
            return Err(NodeError::param(
                "target_pixel",
                format!("give one (x, y) pixel or none, found {}", more.len()),
            ));
        }
    };
    let Some((rx0, rx1, ry0, ry1)) = source.rect.filter(|_| obj.count > 0) else {
        return Ok(empty(anchor));
    };
    if p.rotation_deg.iter().any(|v| !v.is_finite()) {
        return Err(NodeError::param("rotation_deg", "angles must be finite"));
    }
    let rot = rotation(p.rotation_deg);
    let c = obj.centroid;
    // the box of the rotated object: that of its rotated box's corners
    let (mut lo_rel, mut hi_rel) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
    for corner in 0..8 {
        let q = DVec3::new(
            if corner & 1 == 0 {
                solid_lo.x
            } else {
                solid_hi.x
            },
            if corner & 2 == 0 {
                solid_lo.y
            } else {
                solid_hi.y
            },
            if corner & 4 == 0 {
                solid_lo.z
            } else {
                solid_hi.z
            },
        );
        let r = rot * (q - pivot) + (pivot - c);
        lo_rel = lo_rel.min(r);
        hi_rel = hi_rel.max(r);
    }
    // Suggested scale (step 3).
    let suggested = if p.auto_scale {
        suggest_scale(tgt_depth, k_tgt, anchor, lo_rel, hi_rel)?
    } else {
        1.0
    };
    let s = suggested * p.scale;

    // Step 4: vertices in the target, then the z-buffer; step 5: the back
    // layer, drawn the same way with ids after the front's.
    let project_layer = |z: &[f32]| -> Vec<[f64; 3]> {
        (0..n)
            .into_par_iter()
            .map(|i| {
                if !member[i] {
                    return [f64::NAN; 3];
                }
                let (x, y) = (i % sw, i / sw);
                let xs = k_src.unproject(x as f64 + 0.5, y as f64 + 0.5, z[i] as f64);
                let xt = anchor + s * (rot * (xs - pivot) + (pivot - c));
                if xt.z <= Z_NEAR {
                    return [f64::NAN; 3];
                }
                match k_tgt.project(xt) {
                    Some(uv) if uv.x.is_finite() && uv.y.is_finite() => [uv.x, uv.y, xt.z],
                    _ => [f64::NAN; 3],
                }
            })
            .collect()
    };
    let verts = project_layer(src_z);
    let back_verts: Option<Vec<[f64; 3]>> = back_z.as_ref().map(|z| project_layer(z));
    let jump = p.max_depth_jump_rel;
    let zbuf: Vec<AtomicU64> = (0..tw * th).map(|_| AtomicU64::new(u64::MAX)).collect();
    let write = |x: usize, y: usize, z: f64, id: u32| {
        let key = ((z as f32).to_bits() as u64) << 32 | id as u64;
        zbuf[y * tw + x].fetch_min(key, Ordering::Relaxed);
    };
    // a layer's triangles get ids base + 2 cell + half, its splats
    // base + 2n + pixel
    let draw_layer = |verts: &[[f64; 3]], base: usize| {
        let usable = |i: usize| !verts[i][2].is_nan();
        // A triangle is drawn when its three vertices project and its
        // source depths are one surface.
        let tri_ok = |tri: &[usize; 3]| -> bool {
            tri.iter().all(|&i| usable(i)) && {
                let z = tri.map(|i| src_z[i] as f64);
                let (zmin, zmax) = (z[0].min(z[1]).min(z[2]), z[0].max(z[1]).max(z[2]));
                // guard: member depths are valid (> 0)
                zmax / zmin <= 1.0 + jump
            }
        };
        // the cells with a corner on the object: top-left corners from
        // one left of and above its rectangle
        if sw >= 2 && sh >= 2 {
            (ry0.saturating_sub(1)..=ry1.min(sh - 2))
                .into_par_iter()
                .for_each(|y| {
                    for x in rx0.saturating_sub(1)..=rx1.min(sw - 2) {
                        let i = y * sw + x;
                        for (half, tri) in cell_triangles(member, sw, i).iter().enumerate() {
                            let Some(tri) = tri else { continue };
                            if !tri_ok(tri) {
                                continue;
                            }
                            let tv = tri.map(|j| verts[j]);
                            raster_triangle(&tv, tw, th, |px, py, z| {
                                write(px, py, z, (base + 2 * i + half) as u32)
                            });
                        }
                    }
                });
        }
        // Object pixels in no drawn triangle: single-pixel splats.
        let splat = |i: usize| {
            if !usable(i) {
                return;
            }
            let (x, y) = (i % sw, i / sw);
            let mut covered = false;
            for (cx, cy) in [
                (x.wrapping_sub(1), y.wrapping_sub(1)),
                (x, y.wrapping_sub(1)),
                (x.wrapping_sub(1), y),
                (x, y),
            ] {
                if cx >= sw - 1 || cy >= sh - 1 || sw < 2 || sh < 2 {
                    continue;
                }
                let ci = cy * sw + cx;
                for tri in cell_triangles(member, sw, ci).iter().flatten() {
                    if tri.contains(&i) && tri_ok(tri) {
                        covered = true;
                    }
                }
            }
            if covered {
                return;
            }
            let v = verts[i];
            if v[0] >= 0.0 && v[1] >= 0.0 && v[0] < tw as f64 && v[1] < th as f64 {
                write(
                    v[0] as usize,
                    v[1] as usize,
                    v[2],
                    (base + 2 * n + i) as u32,
                );
            }
        };
        (ry0..=ry1)
            .into_par_iter()
            .for_each(|y| (rx0..=rx1).for_each(|x| splat(y * sw + x)));
    };
    draw_layer(&verts, 0);
    if let Some(bv) = &back_verts {
        draw_layer(bv, 3 * n);
    }

    // Resolve: interpolate color and alpha of the winning fragment.
    let sc = src_color.as_slice();
    let sa = src_mask.as_slice();
    let alpha_of = |i: usize| {
        let a = sa[i];
        if a.is_nan() {
            0.0
        } else {
            a.clamp(0.0, 1.0) as f64
        }
    };
    // (colour, depth, alpha, back)
    let resolved: Vec<([f32; 3], f32, f32, bool)> = (0..tw * th)
        .into_par_iter()
        .map(|q| {
            let key = zbuf[q].load(Ordering::Relaxed);
            if key == u64::MAX {
                return ([0.0; 3], 0.0, 0.0, false);
            }
            let z = f32::from_bits((key >> 32) as u32);
            let id = (key & 0xffff_ffff) as usize;
            // the back layer's ids follow the front's (step 5); it takes
            // the front's colours at the same source pixels
            let (back, id) = if id >= 3 * n {
                (true, id - 3 * n)
            } else {
                (false, id)
            };
            let layer = if back {
                back_verts.as_deref().unwrap_or(&verts)
            } else {
                &verts
            };
            if id >= 2 * n {
                let i = id - 2 * n;
                return (sc[i], z, alpha_of(i) as f32, back);
            }
            let (cell, half) = (id / 2, id % 2);
            let Some(tri) = cell_triangles(member, sw, cell)[half] else {
                return ([0.0; 3], 0.0, 0.0, false);
            };
            let tv = tri.map(|j| layer[j]);
            let (px, py) = ((q % tw) as f64 + 0.5, (q / tw) as f64 + 0.5);
            let Some(l) = barycentric(&tv, px, py) else {
                return (sc[tri[0]], z, alpha_of(tri[0]) as f32, back);
            };
            let Some((wts, _)) = perspective(l, tv.map(|v| v[2])) else {
                return (sc[tri[0]], z, alpha_of(tri[0]) as f32, back);
            };
            // clamp the tolerance-admitted pixels just outside the edges back in
            let wts = wts.map(|v| v.clamp(0.0, 1.0));
            let ws = wts[0] + wts[1] + wts[2];
            // guard: the weights summed to 1 before clamping, so one was >= 1/3
            // and still is (clamped to at most 1): ws >= 1/3
            let wts = wts.map(|v| v / ws);
            let mut col = [0.0f64; 3];
            let mut a = 0.0f64;
            for (k, &j) in tri.iter().enumerate() {
                for ch in 0..3 {
                    col[ch] += wts[k] * sc[j][ch] as f64;
                }
                a += wts[k] * alpha_of(j);
            }
            (col.map(|v| v as f32), z, a.clamp(0.0, 1.0) as f32, back)
        })
        .collect();
    let mut color = Vec::with_capacity(tw * th);
    let mut depth = Vec::with_capacity(tw * th);
    let mut alpha = Vec::with_capacity(tw * th);
    let mut back = Vec::with_capacity(tw * th);
    for (c, z, a, b) in resolved {
        color.push(c);
        depth.push(z);
        alpha.push(a);
        back.push(if b { 1.0f32 } else { 0.0 });
    }
    Ok(Pasted {
        color: Image::from_vec(tw, th, color)?,
        depth: Image::from_vec(tw, th, depth)?,
        alpha: Image::from_vec(tw, th, alpha)?,
        back: Image::from_vec(tw, th, back)?,
        scale: s,
        suggested_scale: suggested,
        anchor,
        object_points: obj.count,
    })
}

/// Calls `frag(x, y, z)` for every pixel centre of the `w` x `h` target
/// inside the projected triangle `t` (`[u, v, z]` per vertex; edges
/// inclusive), with the perspective-correct depth there.
fn raster_triangle(t: &[[f64; 3]; 3], w: usize, h: usize, mut frag: impl FnMut(usize, usize, f64)) {
    let (umin, umax) = (
        t[0][0].min(t[1][0]).min(t[2][0]),
        t[0][0].max(t[1][0]).max(t[2][0]),
    );
    let (vmin, vmax) = (
        t[0][1].min(t[1][1]).min(t[2][1]),
        t[0][1].max(t[1][1]).max(t[2][1]),
    );
    // pixel centres x + 0.5 in [umin, umax], clipped to the image
    let x0 = (umin - 0.5 - EDGE_EPS).ceil().max(0.0);
    let x1 = (umax - 0.5 + EDGE_EPS).floor().min(w as f64 - 1.0);
    let y0 = (vmin - 0.5 - EDGE_EPS).ceil().max(0.0);
    let y1 = (vmax - 0.5 + EDGE_EPS).floor().min(h as f64 - 1.0);
    if !(x0 <= x1 && y0 <= y1) {
        return;
    }
    let z = [t[0][2], t[1][2], t[2][2]];
    for py in y0 as usize..=y1 as usize {
        for px in x0 as usize..=x1 as usize {
            let Some(l) = barycentric(t, px as f64 + 0.5, py as f64 + 0.5) else {
                return;
            };
            if l[0] < -EDGE_EPS || l[1] < -EDGE_EPS || l[2] < -EDGE_EPS {
                continue;
            }
            if let Some((_, zz)) = perspective(l.map(|v| v.max(0.0)), z) {
                frag(px, py, zz);
            }
        }
    }
}

depthgraph_graph::ports! {
    /// Inputs of `Paste`.
    inputs struct PasteIn {
        /// linear RGB of the source
        source_color: Arc<ColorImage>,
        /// metres, hole-filled source depth
        source_depth: Arc<DepthMap>,
        /// source object alpha (Lasso.mask)
        source_mask: Arc<Mask>,
        /// of the source images
        source_intrinsics: Intrinsics,
        /// metres, the target's depth
        target_depth: Arc<DepthMap>,
        /// of the target images
        target_intrinsics: Intrinsics,
    }
}

depthgraph_graph::ports! {
    /// Outputs of `Paste`.
    outputs struct PasteOut {
        /// pasted object color in target pixels, black elsewhere
        color: ColorImage,
        /// pasted object depth, 0 elsewhere
        depth: DepthMap,
        /// alpha of the pasted object in target pixels
        mask: Mask,
        /// 1 where a rotation shows the object's closed back (colour mirrored from its front)
        back: Mask,
        /// the scale used: suggested x user scale
        scale: f64,
    }
}

fn eval(ctx: &EvalCtx, i: PasteIn, p: &PasteParams) -> Result<Produced<PasteOut>, NodeError> {
    // The source part is a value the engine keeps under the keys of the
    // inputs it reads: moving, turning or scaling the object reuses it.
    check_same("source_color", i.source_color.dims(), i.source_depth.dims())?;
    let source = ctx.derived("paste source", SOURCE_PORTS, &source_key_params(p), || {
        paste_source(&i.source_depth, &i.source_mask, &i.source_intrinsics, p)
    })?;
    ctx.check_cancelled()?;
    let images = SourceImages {
        color: &i.source_color,
        depth: &i.source_depth,
        mask: &i.source_mask,
        k: &i.source_intrinsics,
    };
    let r = paste_placed(&source, &images, &i.target_depth, &i.target_intrinsics, p)?;
    let empty = r.object_points == 0;
    // every point placed, none in the picture: behind the camera (a depth
    // offset past the surface), beside it, or scaled below one pixel
    let unseen = !empty && r.alpha.as_slice().iter().all(|a| *a <= 0.0);
    let anchor = r.anchor;
    let out = PasteOut {
        color: r.color,
        depth: r.depth,
        mask: r.alpha,
        back: r.back,
        scale: r.scale,
    };
    if empty {
        return Ok(Produced::passthrough(
            out,
            "nothing pasted: the source mask selects no pixel with a valid depth",
        ));
    }
    if unseen {
        return Ok(Produced::passthrough(
            out,
            format!(
                "nothing pasted: the object lands nowhere in the picture (its centre at ({:.3}, {:.3}, \
                 {:.3}) m in the target camera: behind it, beside the view, or under a pixel); \
                 check target_pixel, depth_offset_m, translation_m and scale",
                anchor.x, anchor.y, anchor.z
            ),
        ));
    }
    Ok(out.into())
}

/// Registers `Paste`.
pub fn register(reg: &mut Registry) -> Result<(), RegistryError> {
    reg.register(PortedNode::new(
        "Paste",
        2,
        "Places a selected object into a target RGB-D image (3d-editing §III.C): unproject, turn about the \
         solid's centroid (rotation_deg), scale about the centroid, translate (or put on a target pixel's ray), \
         reproject through the target camera as a crack-free z-buffered mesh. With close_back its unseen back \
         (the front mirrored about the silhouette plane) is drawn too and marked in `back`.\nWith auto_scale, \
         the scale is the largest (at most the physical size) whose bounding box no target surface point lies \
         inside, times the user scale.",
        eval,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::synthetic::{RenderOptions, Scene, kinect_like_intrinsics, render};

    fn custom(fx: f64, w: usize, h: usize) -> Intrinsics {
        Intrinsics {
            fx,
            fy: fx,
            cx: w as f64 / 2.0,
            cy: h as f64 / 2.0,
            width: w,
            height: h,
        }
    }

    fn fixed(auto_scale: bool) -> PasteParams {
        PasteParams {
            auto_scale,
            ..Default::default()
        }
    }

    #[test]
    fn identity_placement_reproduces_the_selection() {
        let (w, h) = (40, 30);
        let k = custom(50.0, w, h);
        let depth = Image::from_fn(w, h, |x, _| 1.0 + 0.01 * x as f32);
        let color = Image::from_fn(w, h, |x, y| [x as f32 / 40.0, y as f32 / 30.0, 0.5]);
        // a rectangle plus one isolated pixel (splatted, not meshed)
        let mask = Image::from_fn(w, h, |x, y| {
            if (5..25).contains(&x) && (4..20).contains(&y) || (x, y) == (32, 25) {
                1.0f32
            } else {
                0.0
            }
        });
        let target = Image::filled(w, h, 5.0f32);
        let p = PasteParams {
            largest_surface_only: false,
            ..fixed(false)
        };
        let r = paste(&color, &depth, &mask, &k, &target, &k, &p).unwrap();
        assert_eq!(r.scale, 1.0);
        assert_eq!(r.object_points, 20 * 16 + 1);
        for y in 0..h {
            for x in 0..w {
                let m = *mask.get(x, y);
                assert_eq!(*r.alpha.get(x, y), m, "alpha at ({x},{y})");
                if m > 0.0 {
                    let (a, b) = (r.color.get(x, y), color.get(x, y));
                    for c in 0..3 {
                        assert!((a[c] - b[c]).abs() < 1e-5, "color at ({x},{y})");
                    }
                    assert!((r.depth.get(x, y) - depth.get(x, y)).abs() < 1e-5);
                } else {
                    assert_eq!(*r.depth.get(x, y), 0.0);
                }
            }
        }
    }

    /// A sphere turned by 180° about the vertical (through the solid's
    /// centroid) shows its closed back:
    /// most of its pixels are marked `back`, its outline stays that of the
    /// sphere, and its depth there is the back's; unturned, no pixel is
    /// back; without `close_back` the turned shell shows its inside only
    /// where the front reaches.
    #[test]
    fn a_half_turn_shows_the_closed_back() {
        let (w, h) = (120, 90);
        let k = kinect_like_intrinsics(w, h);
        let (c, r) = (DVec3::new(0.0, 0.0, 1.5), 0.25);
        let depth = crate::test_support::relight::sphere_depth(&k, c, r, false);
        let mask = depth.map(|z| if *z > 0.0 { 1.0f32 } else { 0.0 });
        let color = Image::from_fn(w, h, |x, _| [x as f32 / w as f32, 0.5, 0.2]);
        let target = Image::filled(w, h, 5.0f32);
        let run = |yaw: f64, close: bool| {
            let p = PasteParams {
                rotation_deg: [yaw, 0.0, 0.0],
                close_back: close,
                ..fixed(false)
            };
            paste(&color, &depth, &mask, &k, &target, &k, &p).unwrap()
        };
        let count = |m: &Mask| m.as_slice().iter().filter(|v| **v > 0.0).count();
        let straight = run(0.0, true);
        assert_eq!(count(&straight.back), 0);
        let object = count(&straight.alpha);
        let turned = run(180.0, true);
        let back = count(&turned.back);
        assert!(back as f64 > 0.8 * object as f64, "{back} of {object}");
        let outline = count(&turned.alpha);
        assert!(
            (outline as f64 - object as f64).abs() < 0.1 * object as f64,
            "{outline} vs {object}"
        );
        // the nearest point of the turned sphere is its old back: within
        // a few cm of the sphere's front distance (the back is estimated)
        let i = (h / 2) * w + w / 2;
        let z = f64::from(turned.depth.as_slice()[i]);
        assert!((z - (c.z - r)).abs() < 0.1, "{z}");
        // the open shell, turned, shows nothing of a back
        assert_eq!(count(&run(180.0, false).back), 0);
        let bad = PasteParams {
            rotation_deg: [f64::NAN, 0.0, 0.0],
            ..fixed(false)
        };
        let err = paste(&color, &depth, &mask, &k, &target, &k, &bad).unwrap_err();
        assert!(err.to_string().contains("rotation_deg"), "{err}");
    }

    #[test]
    fn source_and_target_of_different_sizes_and_intrinsics() {
        // A fronto-parallel square at 1 m in a 160x120 Kinect-like source,
        // moved to 2 m in front of a 200x150 target camera with fx = 300.
        let ks = kinect_like_intrinsics(160, 120);
        let kt = custom(300.0, 200, 150);
        let depth = Image::filled(160, 120, 1.0f32);
        let color = Image::from_fn(160, 120, |x, _| [x as f32 / 160.0, 0.2, 0.7]);
        let mask = Image::from_fn(160, 120, |x, y| {
            if (60..100).contains(&x) && (40..80).contains(&y) {
                1.0f32
            } else {
                0.0
            }
        });
        let target = Image::filled(200, 150, 3.0f32);
        let p = PasteParams {
            translation_m: [0.0, 0.0, 1.0],
            ..fixed(false)
        };
        let r = paste(&color, &depth, &mask, &ks, &target, &kt, &p).unwrap();
        // Analytic footprint: pixel centres 60.5..99.5 span 39 / fx_s metres at
        // 1 m, centred on the axis; at 2 m they project to +-(39 / fx_s) * 300 / 2 / 2.
        let half = 39.0 / ks.fx * 300.0 / 2.0 / 2.0;
        let inside = |c: f64, centre: f64| (c - centre).abs() <= half;
        let mut want = 0;
        for y in 0..150 {
            for x in 0..200 {
                let hit = inside(x as f64 + 0.5, 100.0) && inside(y as f64 + 0.5, 75.0);
                want += usize::from(hit);
                let a = *r.alpha.get(x, y);
                assert_eq!(a, if hit { 1.0 } else { 0.0 }, "({x},{y})");
                if hit {
                    assert!((r.depth.get(x, y) - 2.0).abs() < 1e-5);
                    let c = r.color.get(x, y)[0];
                    assert!((60.0 / 160.0..=100.0 / 160.0).contains(&c), "{c}");
                }
            }
        }
        assert_eq!(want, 44 * 44);
    }

    /// Independent check of step 3: marches every target pixel's centre ray
    /// through the box in 0.2 mm steps and reports a ray on which the box has
    /// points both in front of and behind the target surface.
    fn marched_straddle(target: &DepthMap, k: &Intrinsics, lo: DVec3, hi: DVec3) -> bool {
        let (w, h) = target.dims();
        for y in 0..h {
            for x in 0..w {
                let zt = *target.get(x, y) as f64;
                if zt <= lo.z || zt >= hi.z {
                    continue; // the box's depths are all on one side
                }
                let d = DVec3::new(
                    (x as f64 + 0.5 - k.cx) / k.fx,
                    (y as f64 + 0.5 - k.cy) / k.fy,
                    1.0,
                );
                let (mut front, mut behind) = (false, false);
                let mut t = lo.z;
                while t <= hi.z {
                    let q = d * t;
                    if q.cmpge(lo).all() && q.cmple(hi).all() {
                        front |= t < zt - 1e-4;
                        behind |= t > zt + 1e-4;
                    }
                    t += 2e-4;
                }
                if front && behind {
                    return true;
                }
            }
        }
        false
    }

    #[test]
    fn suggested_scale_never_penetrates_the_target_and_is_tight() {
        let src = render(
            &Scene::preset("tabletop", 160, 120).unwrap(),
            &RenderOptions::default(),
        );
        let tgt = render(
            &Scene::preset("tabletop", 200, 150).unwrap(),
            &RenderOptions::default(),
        );
        let mask = src.ids.map(|v| if *v == 4 { 1.0f32 } else { 0.0 }); // the sphere
        // on the back wall's ray at (170, 60), 8 cm in front of it; the
        // box of the visible surface alone (the marching check below
        // knows only the front's box)
        let p = PasteParams {
            target_pixel: vec![[170.0, 60.0]],
            depth_offset_m: -0.08,
            close_back: false,
            ..Default::default()
        };
        let r = paste(
            &src.color,
            &src.depth,
            &mask,
            &src.intrinsics,
            &tgt.depth,
            &tgt.intrinsics,
            &p,
        )
        .unwrap();
        assert!(
            r.suggested_scale > 0.05 && r.suggested_scale < 0.99,
            "{}",
            r.suggested_scale
        );
        assert_eq!(r.scale, r.suggested_scale);
        // nothing stands in front of the wall there: every pasted pixel is in front of the target surface
        let mut pasted = 0;
        for i in 0..r.depth.len() {
            if r.alpha.as_slice()[i] > 0.0 {
                pasted += 1;
                let (zp, zt) = (r.depth.as_slice()[i], tgt.depth.as_slice()[i]);
                assert!(
                    zp <= zt * (1.0 + 1e-6),
                    "pixel {i}: pasted {zp} behind {zt}"
                );
            }
        }
        assert!(pasted > 100, "{pasted} pixels at scale {}", r.scale);
        // the box itself, checked by marching rays
        let obj = source_object(&src.depth, &mask, &src.intrinsics, 0.5, 0.1, true);
        let bx = |s: f64| {
            (
                r.anchor + s * (obj.lo - obj.centroid),
                r.anchor + s * (obj.hi - obj.centroid),
            )
        };
        let (lo, hi) = bx(r.scale);
        assert!(!marched_straddle(&tgt.depth, &tgt.intrinsics, lo, hi));
        assert!(!box_penetrates(&tgt.depth, &tgt.intrinsics, lo, hi));
        let (lo, hi) = bx(r.scale * 1.1);
        assert!(marched_straddle(&tgt.depth, &tgt.intrinsics, lo, hi));
        assert!(box_penetrates(&tgt.depth, &tgt.intrinsics, lo, hi));
        // the user scale multiplies the suggestion
        let r2 = paste(
            &src.color,
            &src.depth,
            &mask,
            &src.intrinsics,
            &tgt.depth,
            &tgt.intrinsics,
            &PasteParams {
                scale: 0.5,
                ..p.clone()
            },
        )
        .unwrap();
        assert_eq!(r2.scale, 0.5 * r.suggested_scale);
        // in open space the physical size fits: suggested scale 1
        let far = Image::filled(200, 150, 50.0f32);
        let r3 = paste(
            &src.color,
            &src.depth,
            &mask,
            &src.intrinsics,
            &far,
            &tgt.intrinsics,
            &PasteParams::default(),
        )
        .unwrap();
        assert_eq!(r3.suggested_scale, 1.0);
    }

    #[test]
    fn alpha_stays_in_range_and_empty_selections_paste_nothing() {
        let k = custom(40.0, 24, 20);
        let depth = Image::from_fn(24, 20, |x, y| if (x + y) % 7 == 0 { 0.0 } else { 1.5f32 });
        let color = Image::filled(24, 20, [0.5f32; 3]);
        let mask = Image::from_fn(24, 20, |x, _| match x % 4 {
            0 => f32::NAN,
            1 => 2.0,
            2 => -1.0,
            _ => 0.7,
        });
        let target = Image::filled(24, 20, 3.0f32);
        let r = paste(&color, &depth, &mask, &k, &target, &k, &fixed(false)).unwrap();
        assert!(r.object_points > 0);
        for a in r.alpha.as_slice() {
            assert!((0.0..=1.0).contains(a), "{a}");
        }
        // empty mask: nothing pasted, and the node says so
        let none = Image::filled(24, 20, 0.0f32);
        let r = paste(
            &color,
            &depth,
            &none,
            &k,
            &target,
            &k,
            &PasteParams::default(),
        )
        .unwrap();
        assert_eq!(r.object_points, 0);
        assert!(r.alpha.as_slice().iter().all(|a| *a == 0.0));
        assert!(r.depth.as_slice().iter().all(|z| *z == 0.0));
        let mut reg = Registry::new();
        register(&mut reg).unwrap();
        let mut inputs = Inputs::new();
        inputs.insert("source_color", Value::from(color.clone()));
        inputs.insert("source_depth", Value::from(depth.clone()));
        inputs.insert("source_mask", Value::Mask(std::sync::Arc::new(none)));
        inputs.insert("source_intrinsics", Value::from(k));
        inputs.insert("target_depth", Value::from(target.clone()));
        inputs.insert("target_intrinsics", Value::from(k));
        let test_ctx = crate::test_support::TestCtx::new("paste");
        let ctx = test_ctx.ctx();
        let out = reg
            .get("Paste")
            .unwrap()
            .eval(&ctx, &inputs, &PasteParams::default().to_values())
            .unwrap();
        assert!(out.passthrough.unwrap().contains("nothing pasted"));
        // an object moved behind the camera (a depth offset past the
        // target's surface, no auto scale): nothing lands in the picture,
        // and the node says so instead of reporting a paste
        let full = Image::filled(24, 20, 1.0f32);
        inputs.insert("source_mask", Value::Mask(std::sync::Arc::new(full)));
        let behind = PasteParams {
            target_pixel: vec![[12.5, 10.5]],
            depth_offset_m: -10.0,
            auto_scale: false,
            ..PasteParams::default()
        };
        let out = reg
            .get("Paste")
            .unwrap()
            .eval(&ctx, &inputs, &behind.to_values())
            .unwrap();
        let why = out.passthrough.unwrap_or_default();
        assert!(why.contains("lands nowhere in the picture"), "{why}");
    }

    #[test]
    fn stray_background_pixels_of_a_selection_are_dropped() {
        // A near square at 1 m whose mask also catches a 1-px ring of wall at 3 m.
        let k = custom(60.0, 40, 40);
        let depth = Image::from_fn(40, 40, |x, y| {
            if (10..30).contains(&x) && (10..30).contains(&y) {
                1.0f32
            } else {
                3.0
            }
        });
        let mask = Image::from_fn(40, 40, |x, y| {
            if (9..31).contains(&x) && (9..31).contains(&y) {
                1.0f32
            } else {
                0.0
            }
        });
        let obj = source_object(&depth, &mask, &k, 0.5, 0.1, true);
        assert_eq!(obj.count, 400);
        assert_eq!(obj.hi.z, 1.0);
        let all = source_object(&depth, &mask, &k, 0.5, 0.1, false);
        assert_eq!(all.count, 22 * 22);
        assert_eq!(all.hi.z, 3.0);
    }

    #[test]
    fn bad_placements_and_sizes_are_named() {
        let k = custom(40.0, 24, 20);
        let depth = Image::filled(24, 20, 1.0f32);
        let color = Image::filled(24, 20, [0.5f32; 3]);
        let mask = Image::from_fn(24, 20, |x, y| {
            if x > 8 && x < 14 && y > 5 && y < 12 {
                1.0f32
            } else {
                0.0
            }
        });
        let target = Image::from_fn(24, 20, |x, _| if x == 3 { 0.0 } else { 2.0f32 });
        let run = |p: PasteParams| {
            paste(&color, &depth, &mask, &k, &target, &k, &p)
                .unwrap_err()
                .to_string()
        };
        let e = run(PasteParams {
            target_pixel: vec![[30.0, 2.0]],
            ..Default::default()
        });
        assert!(e.contains("target_pixel") && e.contains("outside"), "{e}");
        let e = run(PasteParams {
            target_pixel: vec![[1.0, 2.0], [3.0, 4.0]],
            ..Default::default()
        });
        assert!(e.contains("target_pixel") && e.contains("found 2"), "{e}");
        let e = run(PasteParams {
            target_pixel: vec![[3.5, 2.0]],
            ..Default::default()
        });
        assert!(e.contains("no measurement"), "{e}");
        // the centroid on the target surface: no scale fits
        let e = run(PasteParams {
            target_pixel: vec![[12.5, 10.5]],
            depth_offset_m: 0.0,
            ..Default::default()
        });
        assert!(
            e.contains("on or inside the surface") && e.contains("depth_offset_m"),
            "{e}"
        );
        // behind the camera
        let e = run(PasteParams {
            translation_m: [0.0, 0.0, -5.0],
            ..Default::default()
        });
        assert!(e.contains("not in front of the camera"), "{e}");
        // wholly behind the target wall is not penetrating: hidden, full size
        let r = paste(
            &color,
            &depth,
            &mask,
            &k,
            &target,
            &k,
            &PasteParams {
                translation_m: [0.0, 0.0, 1.5],
                ..Default::default()
            },
        )
        .unwrap();
        assert_eq!(r.suggested_scale, 1.0);
        let e = paste(
            &color,
            &Image::filled(10, 10, 1.0f32),
            &mask,
            &k,
            &target,
            &k,
            &PasteParams::default(),
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("source_color"), "{e}");
        let e = paste(
            &color,
            &depth,
            &mask,
            &k,
            &Image::filled(10, 10, 1.0f32),
            &k,
            &PasteParams::default(),
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("target_intrinsics"), "{e}");
    }

    #[test]
    fn thread_count_does_not_change_bits() {
        let src = render(
            &Scene::preset("tabletop", 96, 72).unwrap(),
            &RenderOptions::default(),
        );
        let mask = src
            .ids
            .map(|v| if *v == 3 || *v == 4 { 1.0f32 } else { 0.0 });
        let kt = custom(90.0, 110, 80);
        let target = Image::filled(110, 80, 4.0f32);
        let p = PasteParams {
            translation_m: [0.1, -0.05, 0.3],
            scale: 1.7,
            ..fixed(false)
        };
        let run = |n| {
            crate::test_support::with_threads(n, || {
                paste(
                    &src.color,
                    &src.depth,
                    &mask,
                    &src.intrinsics,
                    &target,
                    &kt,
                    &p,
                )
                .unwrap()
            })
        };
        let (a, b) = (run(1), run(3));
        assert_eq!(a, b);
        assert!(a.alpha.as_slice().iter().filter(|v| **v > 0.0).count() > 200);
    }
}
