//! The pasted object's surface as a watertight triangle mesh, rasterized
//! exactly into its own orthographic shadow maps (the scene-cached path's
//! object maps, [`crate::relight::scene_cached`]).
//!
//! # Why not splats
//!
//! An imperfect shadow map splats a random subset of points as discs; a
//! lone object's map has no pull-push to close the gaps between them, so
//! the discs must be about twice the ISM radius, and every shadow the
//! object casts comes out wider by that radius (a 16 cm sphere splatted
//! with 2048 points: discs of 1.3 cm, a shadow 8 % too long). The object is
//! small: its own surface, meshed, costs less to rasterize than the
//! overlapping discs (each texel written about twice, the discs about 35
//! times), and its outline is exact to a texel.
//!
//! # The mesh
//!
//! Each depth layer (the visible front, the mirrored back of
//! [`crate::relight::closure`]) is sampled every `stride` pixels inside
//! the object's bounding box:
//!
//! - a **cell** whose four corner samples are valid and on one surface
//!   (depths within `1 + b` [`SAME_SURFACE`] of each other; steeper steps
//!   are depth jumps, never bridged) becomes two
//!   triangles through the corners' unprojected pixel centres: cells share
//!   corners, so their union has no cracks;
//! - a valid pixel whose square the full cells do not cover (the half
//!   pixel band along the outline, cells broken by a depth jump) becomes a
//!   **patch**: the parallelogram of the pixel's footprint on its surface
//!   (`P ± ∂P/∂x/2 ± ∂P/∂y/2`, one-sided differences on the same surface,
//!   fronto-parallel where it has no neighbour, each edge at most
//!   [`MAX_PATCH_EDGE`] pixel sides long), grown by [`PATCH_GROWTH`]
//!   so that patches and cells overlap.
//!
//! The front and the back meet at the silhouette (the back is never in
//! front of the front), so the two layers close the solid.
//!
//! # Rasterization
//!
//! A texel holds the largest `t = p·d` (the point nearest the light) of the
//! triangles covering its centre, interpolated on the triangle's plane:
//! the map's depth is exact at texel centres, off them by the surface's
//! slope times half a texel (what the visibility bias covers).

use depthgraph_graph::prelude::*;
use glam::DVec3;

use crate::relight::ism::{Grid, SAME_SURFACE, ShadowMap, Window, surface_steps};

/// A patch's edge is at most this many pixel sides long (a surface seen
/// at 83° from its normal): a steep step to the neighbour (a sphere's rim,
/// seen edge-on) does not stretch the patch far beyond its pixel. Against
/// the path-traced rooms a cap of 20 sides (`pixel_area`'s) scored the
/// cylinder behind a box 2 dB lower and the others the same; 4 sides left
/// holes in a box's steep faces.
pub const MAX_PATCH_EDGE: f64 = 8.0;

/// Patches are grown by this fraction of their footprint: their edges then
/// overlap the cells' and each other's (no light leaks between them), at
/// the cost of an outline at most 5 % of a pixel too wide.
pub const PATCH_GROWTH: f64 = 1.05;

/// The object's closed surface as triangles (module docs).
#[derive(Debug, Clone, Default)]
pub struct ObjectMesh {
    /// Vertices, camera frame (metres).
    pub verts: Vec<DVec3>,
    /// `verts` in f32 (what the maps transform).
    verts32: Vec<glam::Vec3>,
    /// Triangles, indices into `verts`.
    pub tris: Vec<[u32; 3]>,
    /// The largest distance of a vertex beyond the pixel centres it was
    /// built from (a patch's half diagonal): the mesh lies within this of
    /// the layers' unprojected pixels.
    pub margin: f64,
}

impl ObjectMesh {
    /// The mesh of the `front` depth and, for a closed solid, its `back`
    /// (each `k`'s size, 0 = no surface), sampled every `stride` pixels (at
    /// least 1). `k` must be sane.
    pub fn new(front: &DepthMap, back: Option<&DepthMap>, k: &Intrinsics, stride: usize) -> Self {
        let mut mesh = Self::default();
        mesh.add_layer(front, k, stride.max(1));
        if let Some(b) = back {
            mesh.add_layer(b, k, stride.max(1));
        }
        mesh.verts32 = mesh.verts.iter().map(|v| v.as_vec3()).collect();
        mesh
    }

    /// Whether there is nothing to rasterize.
    pub fn is_empty(&self) -> bool {
        self.tris.is_empty()
    }

    /// Pushes the quad `(q0, q1, q2, q3)` (in order around it) as two
    /// triangles.
    fn quad(&mut self, q: [u32; 4]) {
        self.tris.push([q[0], q[1], q[2]]);
        self.tris.push([q[0], q[2], q[3]]);
    }

    fn add_layer(&mut self, depth: &DepthMap, k: &Intrinsics, b: usize) {
        let (w, h) = depth.dims();
        let valid = |x: usize, y: usize| DepthMap::is_valid(*depth.get(x, y));
        // the bounding box of the valid pixels
        let (mut x0, mut y0, mut x1, mut y1) = (usize::MAX, usize::MAX, 0usize, 0usize);
        for y in 0..h {
            for x in 0..w {
                if valid(x, y) {
                    x0 = x0.min(x);
                    y0 = y0.min(y);
                    x1 = x1.max(x);
                    y1 = y1.max(y);
                }
            }
        }
        if x0 > x1 {
            return;
        }
        let at = |x: usize, y: usize| {
            k.unproject(x as f64 + 0.5, y as f64 + 0.5, f64::from(*depth.get(x, y)))
        };
        // sample grid: columns x0 + i b (i < gw), rows y0 + j b (j < gh)
        let (gw, gh) = ((x1 - x0) / b + 1, (y1 - y0) / b + 1);
        let mut vid = vec![u32::MAX; gw * gh];
        for j in 0..gh {
            for i in 0..gw {
                let (x, y) = (x0 + i * b, y0 + j * b);
                if valid(x, y) {
                    vid[j * gw + i] = self.verts.len() as u32;
                    self.verts.push(at(x, y));
                }
            }
        }
        // cells (i, j) for i < gw - 1, j < gh - 1: full or not
        let (cw, ch) = (gw.saturating_sub(1), gh.saturating_sub(1));
        let mut full = vec![false; cw * ch];
        for j in 0..ch {
            for i in 0..cw {
                let c = [
                    vid[j * gw + i],
                    vid[j * gw + i + 1],
                    vid[(j + 1) * gw + i],
                    vid[(j + 1) * gw + i + 1],
                ];
                if c.contains(&u32::MAX) {
                    continue;
                }
                let zs = c.map(|v| self.verts[v as usize].z);
                let (lo, hi) = (
                    zs.iter().copied().fold(f64::INFINITY, f64::min),
                    zs.iter().copied().fold(0.0f64, f64::max),
                );
                // guard: valid depths are > 0, so lo > 0
                if hi > lo * (1.0 + SAME_SURFACE * b as f64) {
                    continue;
                }
                full[j * cw + i] = true;
                self.quad([c[0], c[1], c[3], c[2]]);
            }
        }
        // Cell i spans the pixel coordinates [x0 + i b + 1/2, x0 + (i+1) b
        // + 1/2]; pixel x's square [x, x + 1] meets the cells
        // floor((x - x0 - 1/2) / b) ..= floor((x - x0 + 1/2) / b).
        let cells_of = |x: usize, o: usize, n: usize| -> Option<(usize, usize)> {
            let r = x as f64 - o as f64;
            let lo = ((r - 0.5) / b as f64).floor();
            let hi = ((r + 0.5) / b as f64).floor();
            (lo >= 0.0 && (hi as usize) < n).then_some((lo as usize, hi as usize))
        };
        for y in y0..=y1 {
            for x in x0..=x1 {
                if !valid(x, y) {
                    continue;
                }
                let covered = match (cells_of(x, x0, cw), cells_of(y, y0, ch)) {
                    (Some((ia, ib)), Some((ja, jb))) => {
                        (ja..=jb).all(|j| (ia..=ib).all(|i| full[j * cw + i]))
                    }
                    _ => false,
                };
                if covered {
                    continue;
                }
                let p = at(x, y);
                let (hu, hv) = half_edges(depth, k, x, y);
                let v0 = self.verts.len() as u32;
                self.verts
                    .extend([p - hu - hv, p + hu - hv, p + hu + hv, p - hu + hv]);
                self.quad([v0, v0 + 1, v0 + 2, v0 + 3]);
                self.margin = self.margin.max((hu + hv).length().max((hu - hv).length()));
            }
        }
    }

    /// The shadow map of the mesh over `win` (grown by [`ObjectMesh::margin`]
    /// by the caller when `win` bounds the pixel centres), `res` texels per
    /// side: per texel the largest `t` of the triangles over its centre,
    /// `-inf` where none is. `None` for an empty window.
    pub fn shadow_map(&self, win: &Window, res: usize) -> Option<ShadowMap> {
        let g = Grid::new(win, res)?;
        let res = g.res;
        // `res + BLOCK - 1` rows of as many texels: a small triangle's
        // block at any texel stays inside the buffer (cropped below)
        let stride = res + BLOCK - 1;
        let mut t = vec![f32::NEG_INFINITY; stride * stride];
        // vertices in texel coordinates (u, v) and t, in f32: coordinates
        // below 2^11 texels and depths of metres keep ~1e-7 relative
        // precision, far below a texel and the visibility bias
        let [fu, fv, fd] = g.frame_f32();
        let lc: Vec<[f32; 3]> = self
            .verts32
            .iter()
            .map(|q| {
                [
                    (q.dot(fu.0) - fu.1) * fu.2,
                    (q.dot(fv.0) - fv.1) * fv.2,
                    q.dot(fd.0),
                ]
            })
            .collect();
        for tri in &self.tris {
            let [a, b, c] = tri.map(|i| lc[i as usize]);
            raster_triangle(a, b, c, res, stride, &mut t);
        }
        let t: Vec<f32> = t
            .chunks_exact(stride)
            .take(res)
            .flat_map(|r| &r[..res])
            .copied()
            .collect();
        Some(g.map(t))
    }
}

/// `depth` (of a camera `k`) pooled over blocks of `f x f` pixels, and
/// the camera of the pooled grid (focal lengths and principal point over
/// `f`, so that pooled pixel `u'` is pixel `f u'`): a block with at least
/// half its pixels valid takes the median of their depths (an upper
/// median, one of them: a block across a depth edge lies on one side, not
/// between), else none. The coarse object maps' mesh is built on it
/// ([`crate::relight::scene_cached`]): a patch then stands for a block,
/// and the outline moves by at most half a block.
pub fn pooled(depth: &DepthMap, k: &Intrinsics, f: usize) -> (DepthMap, Intrinsics) {
    let f = f.max(1);
    let (w, h) = depth.dims();
    let (pw, ph) = (w.div_ceil(f), h.div_ceil(f));
    let mut out = DepthMap::filled(pw, ph, 0.0);
    let mut zs: Vec<f32> = Vec::with_capacity(f * f);
    for by in 0..ph {
        for bx in 0..pw {
            zs.clear();
            let mut n = 0;
            for y in by * f..((by + 1) * f).min(h) {
                for x in bx * f..((bx + 1) * f).min(w) {
                    n += 1;
                    let z = *depth.get(x, y);
                    if DepthMap::is_valid(z) {
                        zs.push(z);
                    }
                }
            }
            if !zs.is_empty() && 2 * zs.len() >= n {
                zs.sort_by(f32::total_cmp);
                *out.get_mut(bx, by) = zs[zs.len() / 2];
            }
        }
    }
    // guard: f >= 1
    let s = f as f64;
    let kp = Intrinsics {
        fx: k.fx / s,
        fy: k.fy / s,
        cx: k.cx / s,
        cy: k.cy / s,
        width: pw,
        height: ph,
    };
    (out, kp)
}

/// The half edges of pixel `(x, y)`'s patch on a valid depth (module
/// docs): `∂P/∂x / 2` and `∂P/∂y / 2` from the neighbours on the same
/// surface (one-sided differences; fronto-parallel without one), each
/// edge at most [`MAX_PATCH_EDGE`] pixel sides long, grown by [`PATCH_GROWTH`].
fn half_edges(depth: &DepthMap, k: &Intrinsics, x: usize, y: usize) -> (DVec3, DVec3) {
    // guard: sane intrinsics have fx > 0; a pixel at depth z spans z / fx
    let side = f64::from(*depth.get(x, y)) / k.fx;
    let (p, du, dv) = surface_steps(depth, k, x, y);
    let z = p.z;
    let du = du.unwrap_or_else(|| k.unproject(x as f64 + 1.5, y as f64 + 0.5, z) - p);
    let dv = dv.unwrap_or_else(|| k.unproject(x as f64 + 0.5, y as f64 + 1.5, z) - p);
    // an edge at most MAX_PATCH_EDGE pixel sides long
    let cap = MAX_PATCH_EDGE * side;
    let clamp = |e: DVec3| {
        let l = e.length();
        // guard: divide only an edge longer than the cap (> 0)
        if l > cap { e * (cap / l) } else { e }
    };
    (
        clamp(du) * (0.5 * PATCH_GROWTH),
        clamp(dv) * (0.5 * PATCH_GROWTH),
    )
}

/// A triangle whose texel centres span at most this many columns and rows
/// is tested texel by texel over one block of this side (a fixed-width
/// loop the compiler vectorizes): most of the mesh's triangles cover a
/// few texels, and their per-row intervals cost more than the tests.
const BLOCK: usize = 4;

/// Writes `max(t, plane t)` into every texel of the map `t` (`stride >=
/// res + BLOCK - 1` rows of `stride` texels, the first `res` of the first
/// `res` rows the map's) whose centre lies in the triangle `(a, b, c)` (texel
/// coordinates `x, y`, depth `z`), edges included. A degenerate triangle
/// (seen edge-on) covers nothing.
fn raster_triangle(
    a: [f32; 3],
    b: [f32; 3],
    c: [f32; 3],
    res: usize,
    stride: usize,
    t: &mut [f32],
) {
    let (ab, ac) = ([b[0] - a[0], b[1] - a[1]], [c[0] - a[0], c[1] - a[1]]);
    let area = ab[0] * ac[1] - ab[1] * ac[0];
    // NaN coordinates fail the test too
    if area.is_nan() || area.abs() <= 1e-9 {
        return;
    }
    // guard: |area| > 1e-9
    let inv = 1.0 / area;
    // the texel centres i + 1/2 in [min, max]: i from ceil(min - 1/2) to
    // floor(max - 1/2), clamped to the map (casts, not libm's floor/ceil)
    let first = |m: f32| -> usize {
        let m = m - 0.5;
        if m > 0.0 {
            let i = m as usize;
            if (i as f32) < m { i + 1 } else { i }
        } else {
            0
        }
    };
    let last = |m: f32| -> Option<usize> {
        let m = m - 0.5;
        (m >= 0.0).then(|| (m as usize).min(res - 1))
    };
    let xa = first(a[0].min(b[0]).min(c[0]));
    let ya = first(a[1].min(b[1]).min(c[1]));
    let (Some(xb), Some(yb)) = (
        last(a[0].max(b[0]).max(c[0])),
        last(a[1].max(b[1]).max(c[1])),
    ) else {
        return;
    };
    if xa > xb || ya > yb {
        return;
    }
    // Per row, each of the three barycentric weights is linear in x,
    // `β x + α >= eps`: the row's inside is one interval of x, found from
    // the three constraints, and only its texels are visited (a long, thin
    // triangle costs its rows, not its bounding box). A centre on a shared
    // edge is inside both triangles (`eps` covers f32 rounding).
    let eps = -1e-5f32;
    let (bb, bc) = (ac[1] * inv, -ab[1] * inv);
    let ba = -(bb + bc);
    let (dzb, dzc) = (b[2] - a[2], c[2] - a[2]);
    // guard: each reciprocal is taken only of a non-zero β (else 0, unused)
    let recip = |beta: f32| if beta != 0.0 { 1.0 / beta } else { 0.0 };
    if xb - xa < BLOCK && yb - ya < BLOCK {
        // a whole block of rows ya + r and columns xa + i, every texel
        // tested for all three weights >= eps (the rows' test below) and
        // for the bounding box, without a branch on the data
        let (nx, ny) = (xb - xa, yb - ya);
        let px: [f32; BLOCK] = std::array::from_fn(|i| (xa + i) as f32 + 0.5 - a[0]);
        let in_x: [bool; BLOCK] = std::array::from_fn(|i| i <= nx);
        for r in 0..=ny {
            let py = (ya + r) as f32 + 0.5 - a[1];
            let (ab_, ac_) = (-py * ac[0] * inv, ab[0] * py * inv);
            let aa = 1.0 - ab_ - ac_;
            let at = (ya + r) * stride + xa;
            let Some(row) = t
                .get_mut(at..at + BLOCK)
                .and_then(|r| <&mut [f32; BLOCK]>::try_from(r).ok())
            else {
                return;
            };
            let old = *row;
            *row = std::array::from_fn(|i| {
                let (wb, wc) = (bb * px[i] + ab_, bc * px[i] + ac_);
                let wa = ba * px[i] + aa;
                let z = a[2] + wb * dzb + wc * dzc;
                let inside = in_x[i] & (wb >= eps) & (wc >= eps) & (wa >= eps);
                if inside & (z > old[i]) { z } else { old[i] }
            });
        }
        return;
    }
    let betas = [(bb, recip(bb)), (bc, recip(bc)), (ba, recip(ba))];
    for y in ya..=yb {
        let py = y as f32 + 0.5 - a[1];
        let (ab_, ac_) = (-py * ac[0] * inv, ab[0] * py * inv);
        let aa = 1.0 - ab_ - ac_;
        // x (relative to a) in [lo, hi]
        let (mut lo, mut hi) = (f32::NEG_INFINITY, f32::INFINITY);
        let mut empty = false;
        for ((beta, rb), alpha) in betas.into_iter().zip([ab_, ac_, aa]) {
            if beta > 0.0 {
                lo = lo.max((eps - alpha) * rb);
            } else if beta < 0.0 {
                hi = hi.min((eps - alpha) * rb);
            } else if alpha < eps {
                empty = true;
            }
        }
        if empty || lo.is_nan() || hi.is_nan() || lo > hi {
            continue;
        }
        // texel x has its centre at x + 1/2 - a.x relative to a
        let xs = first(lo + a[0]).max(xa);
        let Some(xe) = last(hi + a[0]) else {
            continue;
        };
        let xe = xe.min(xb);
        if xs > xe {
            continue;
        }
        for x in xs..=xe {
            let px = x as f32 + 0.5 - a[0];
            let (wb, wc) = (bb * px + ab_, bc * px + ac_);
            let z = a[2] + wb * dzb + wc * dzc;
            let cell = &mut t[y * stride + x];
            if z > *cell {
                *cell = z;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::relight::ism::windows;

    fn cam(w: usize, h: usize) -> Intrinsics {
        crate::sim::synthetic::kinect_like_intrinsics(w, h)
    }

    /// Texels a map marks occupied.
    fn covered(m: &ShadowMap) -> usize {
        m.t.iter().filter(|t| t.is_finite()).count()
    }

    /// Pooling keeps a block where at least half its pixels are valid, at
    /// one of their depths (the upper median), and its camera puts the
    /// pooled pixel where the block lies: a plane stays the plane.
    #[test]
    fn pooled_blocks_take_a_member_depth_on_the_same_plane() {
        let k = crate::sim::synthetic::kinect_like_intrinsics(9, 7);
        let mut d = DepthMap::filled(9, 7, 0.0);
        // a fronto-parallel plane at 2 m over x < 6, rows 0..6
        for y in 0..6 {
            for x in 0..6 {
                *d.get_mut(x, y) = 2.0;
            }
        }
        // one block with a near pixel among far ones: 2, 2, 2, 1
        *d.get_mut(1, 1) = 1.0;
        // a block with one valid pixel of four is dropped
        *d.get_mut(6, 0) = 3.0;
        let (p, kp) = pooled(&d, &k, 2);
        assert_eq!(p.dims(), (5, 4));
        assert_eq!(*p.get(0, 0), 2.0);
        assert_eq!(*p.get(2, 2), 2.0);
        assert_eq!(*p.get(3, 0), 0.0);
        // the edge blocks: column 4 (one pixel wide) and row 3 (rows 6)
        assert_eq!(*p.get(4, 0), 0.0);
        assert_eq!(*p.get(0, 3), 0.0);
        // pooled pixel (u', v') + 1/2 at depth z is the point at fine
        // pixel 2 (u' + 1/2): the block's centre
        let q = kp.unproject(1.5, 2.5, 2.0);
        let r = k.unproject(3.0, 5.0, 2.0);
        assert!((q - r).length() < 1e-12, "{q} {r}");
        assert!((kp.fx - k.fx / 2.0).abs() < 1e-12 && kp.width == 5 && kp.height == 4);
    }

    /// Looking at a disc (a sphere's front) from the camera's own
    /// direction, the map covers the disc's area to within the outline's
    /// texels, for every stride, and has no hole inside it (no texel
    /// within the disc's inner 90 % is empty).
    #[test]
    fn a_sphere_front_seen_from_the_camera_covers_its_disc_without_holes() {
        let k = cam(320, 240);
        let (c, r) = (DVec3::new(0.05, 0.0, 1.5), 0.16);
        let front = crate::test_support::relight::sphere_depth(&k, c, r, false);
        for stride in [1, 2, 3, 5] {
            let mesh = ObjectMesh::new(&front, None, &k, stride);
            let pts: Vec<DVec3> = mesh.verts.clone();
            let dir = DVec3::new(0.0, 0.0, -1.0);
            let win = windows(&[dir], &pts)[0].unwrap();
            let m = mesh.shadow_map(&win, 128).unwrap();
            let texel = m.texel_m;
            // the disc the camera sees, as the orthographic map sees it:
            // every point of the front within r' of the axis through c
            let mut inner_holes = 0;
            for (i, tv) in m.t.iter().enumerate() {
                let (u, v) = ((i % m.res) as f64 + 0.5, (i / m.res) as f64 + 0.5);
                // the texel centre in the camera frame at the sphere's depth
                let p = m.texel_point(u, v);
                let rho = ((p.x - c.x).powi(2) + (p.y - c.y).powi(2)).sqrt();
                if rho < 0.9 * r * 0.99 && !tv.is_finite() {
                    inner_holes += 1;
                }
            }
            assert_eq!(inner_holes, 0, "stride {stride}");
            // the silhouette radius seen by the perspective camera is a
            // little under r; orthographically along z the disc radius is
            // about r sqrt(1 - (r/d)²)
            let area = covered(&m) as f64 * texel * texel;
            let expect = std::f64::consts::PI * r * r * (1.0 - (r / c.length()).powi(2));
            assert!(
                (area / expect - 1.0).abs() < 0.06,
                "stride {stride}: area {area} vs {expect}"
            );
        }
    }

    /// The occupied rectangle of a map ([`ShadowMap::occupied`]) holds
    /// every texel with an occluder and is tight: every point outside it
    /// looks up an empty texel (or none), and each of its four edges
    /// borders an occupied texel; the shadow of the sphere's front, seen
    /// obliquely, spans 1.4 to 2.2 radii each way.
    #[test]
    fn a_maps_occupied_rectangle_holds_its_occluders_tightly() {
        let k = cam(160, 120);
        let (c, r) = (DVec3::new(0.05, 0.0, 1.5), 0.16);
        let front = crate::test_support::relight::sphere_depth(&k, c, r, false);
        let mesh = ObjectMesh::new(&front, None, &k, 1);
        let dir = DVec3::new(0.3, 0.8, -0.5).normalize();
        let win = windows(&[dir], &mesh.verts)[0].unwrap();
        let m = mesh.shadow_map(&win, 64).unwrap();
        let [u0, u1, v0, v1] = m.occupied().unwrap();
        let step = m.texel_m;
        // the texel a point with light coordinates (u, v) looks up
        let at = |u: f64, v: f64| m.occluder_lc(DVec3::new(u, v, 0.0));
        let (mut outside, mut empty) = (0, 0);
        let (mut edges, mut hit) = ([false; 4], 0);
        for i in -90..=90 {
            for j in -90..=90 {
                let (u, v) = (
                    0.5 * (u0 + u1) + i as f64 * 0.5 * step,
                    0.5 * (v0 + v1) + j as f64 * 0.5 * step,
                );
                let occ = at(u, v);
                if u < u0 || u >= u1 || v < v0 || v >= v1 {
                    outside += 1;
                    empty += usize::from(occ == f32::NEG_INFINITY);
                } else if occ.is_finite() {
                    hit += 1;
                    edges[0] |= u < u0 + step;
                    edges[1] |= u >= u1 - step;
                    edges[2] |= v < v0 + step;
                    edges[3] |= v >= v1 - step;
                }
            }
        }
        assert!(outside > 1000 && hit > 1000, "{outside} {hit}");
        assert_eq!(empty, outside);
        assert_eq!(edges, [true; 4]);
        for side in [u1 - u0, v1 - v0] {
            assert!(side > 1.4 * r && side < 2.2 * r, "{side}");
        }
        // an empty map has no rectangle
        let mut blank = m.clone();
        blank.t.fill(f32::NEG_INFINITY);
        assert_eq!(blank.occupied(), None);
    }

    /// A depth jump inside the object (two slabs at 1.0 and 1.5 m) is not
    /// bridged: seen from the side, nothing lies between the slabs' depths.
    #[test]
    fn a_depth_jump_is_not_bridged() {
        let k = cam(64, 48);
        let d = Image::from_fn(64, 48, |x, y| {
            if (10..54).contains(&x) && (10..38).contains(&y) {
                if x < 32 { 1.0f32 } else { 1.5 }
            } else {
                0.0
            }
        });
        let mesh = ObjectMesh::new(&d, None, &k, 2);
        for tri in &mesh.tris {
            let zs = tri.map(|i| mesh.verts[i as usize].z);
            let (lo, hi) = (zs[0].min(zs[1]).min(zs[2]), zs[0].max(zs[1]).max(zs[2]));
            assert!(hi / lo < 1.1, "a triangle spans {lo} to {hi}");
        }
    }
}
