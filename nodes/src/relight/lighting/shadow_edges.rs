//! The light's direction refined by the edges of the cast shadows the
//! photo shows.
//!
//! The fit of [`super::estimate`] reads the photo on a sparse grid (a few
//! thousand samples) and marches its shadow rays in a few geometric steps:
//! a cast shadow's edge is placed to a few pixels, the light's direction to
//! a few degrees, and a relit shadow moves with it (on the furnished
//! path-traced room the found sun lay 4.3° off, and the true map with the
//! sun moved there scored 5 dB less in the influence region). Here the
//! edges decide, on a grid of about 320 pixels across (every pixel of a
//! photo that size):
//!
//! 1. **Labels.** A pixel whose window (same albedo region, half-size
//!    [`EdgeParams::window`]) spans a brightness ratio of at least
//!    [`EdgeParams::min_contrast`] (in 3x3 means within the region, so
//!    noise does not count) is labelled *lit* when its own luminance lies
//!    above the middle of the window's darkest and brightest, *shadowed*
//!    below: across a cast shadow's edge the two sides are the two modes,
//!    and the middle is a blurred edge's 50 % point. (The smoothed value
//!    against a middle in logs moved shallow edges by a pixel across, four
//!    along.)
//! 2. **The band.** Of those, the pixels facing the light (`n·d >=`
//!    [`EdgeParams::min_facing`]: an attached shadow is shading, not an
//!    edge) whose visibility changes somewhere within
//!    [`EdgeParams::radius_deg`] of the fit's direction `d` (its four
//!    neighbours at that angle): the pixels a move of the light can
//!    explain. Brightness steps of texture inside the band cost every
//!    direction alike, unless a shadow edge passes over them.
//! 3. **The search.** The direction minimising the number of band pixels
//!    whose visibility `V(d)` disagrees with their label, by a pattern
//!    search (four neighbours at the step, the step halved when none is
//!    better) within the radius, from [`EdgeParams::step_deg`] down to
//!    [`EdgeParams::min_step_deg`].
//!
//! `V(d)` is a march through the depth map **a grid step at a time**
//! ([`lit_by_pixels`]): the ray's image is a segment, walked in steps of
//! [`March::step_px`] pixels,
//! with the ray's depth at each from the perspective-correct interpolation
//! of `1/z` along it. A point behind a depth pixel by more than a tolerance
//! ([`March::FINE_SLACK`]) and less than the assumed thickness is in
//! shadow; a ray leaving the frame is open (the fit's test, with less
//! slack).

use depthgraph_graph::prelude::*;
use glam::{DVec2, DVec3};
use rayon::prelude::*;

use crate::kit::color::luminance_f64;
use crate::relight::lighting::regions::NO_REGION;
use crate::relight::shading::Surf;

/// Tolerances of `refine_direction`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EdgeParams {
    /// Largest move from the fit's direction, degrees.
    pub radius_deg: f64,
    /// First step of the search, degrees.
    pub step_deg: f64,
    /// The search stops when its step is below this, degrees.
    pub min_step_deg: f64,
    /// Half-size of a label's window, pixels (at 320 pixels across; it
    /// grows with the image).
    pub window: usize,
    /// Smallest ratio of a window's brightest to its darkest luminance for
    /// its pixels to be labelled.
    pub min_contrast: f64,
    /// Smallest `n·d` of a band pixel.
    pub min_facing: f64,
    /// Most labelled pixels tested for the band (a regular subsample
    /// beyond: each test marches five rays).
    pub max_candidates: usize,
    /// Most pixels in the band (a regular subsample beyond).
    pub max_band: usize,
    /// Fewest pixels in the band for a refinement.
    pub min_band: usize,
}

impl Default for EdgeParams {
    fn default() -> Self {
        Self {
            radius_deg: 5.0,
            step_deg: 1.0,
            min_step_deg: 0.06,
            window: 4,
            min_contrast: 1.3,
            min_facing: 0.2,
            max_candidates: 4000,
            max_band: 6000,
            min_band: 30,
        }
    }
}

/// How a shadow ray marches ([`lit_by_pixels`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct March<'a> {
    /// First point, metres along the ray from the offset surface point.
    pub t0: f64,
    /// Last point, metres.
    pub reach: f64,
    /// Thickness behind each depth pixel, metres (row-major; a pixel
    /// without one is no occluder).
    pub thickness: &'a [f32],
    /// The start's offset along the normal and the depth test's tolerance,
    /// metres, plus this fraction of the depth.
    pub slack: (f64, f64),
    /// The march's step in the image, pixels (>= 1).
    pub step_px: f64,
}

impl March<'_> {
    /// The slack of the fine march: 1 mm + 0.1 %. The fit's march allows
    /// 1 cm + 1 %, which shrinks every occluder by that much in depth and
    /// raises every ray's start: a shadow on a floor 2 m away comes out
    /// centimetres short, several pixels at 320 across, what this
    /// refinement means to measure (3 mm + 0.3 % still left the tests'
    /// pole's shadow a pixel short along its edges).
    pub const FINE_SLACK: (f64, f64) = (0.001, 0.001);
}

/// Nearest depth of a point a march still projects (metres): the ray is
/// cut where it would pass behind the camera.
const Z_MIN: f64 = 0.05;

/// `V(d)` by a march [`March::step_px`] pixels at a time (module docs): whether the ray
/// from the surface point `pos` (normal `n`, offset along it by
/// [`March::slack`]) towards the unit direction `d` passes
/// no depth pixel it lies behind.
pub fn lit_by_pixels(
    depth: &DepthMap,
    k: &Intrinsics,
    pos: DVec3,
    n: DVec3,
    d: DVec3,
    m: March,
) -> bool {
    let (w, h) = depth.dims();
    let start = ray_start(pos, n, m.slack);
    let a = start + d * m.t0;
    let mut t1 = m.reach;
    if d.z < 0.0 {
        // guard: -d.z > 0
        t1 = t1.min(m.t0 + (a.z - Z_MIN) / -d.z);
    }
    if t1 <= m.t0 || a.z <= Z_MIN {
        return true;
    }
    let b = start + d * t1;
    let (Some(pa), Some(pb)) = (k.project(a), k.project(b)) else {
        return true;
    };
    let len = (pb - pa).length();
    if !len.is_finite() {
        return true;
    }
    // guard: the step is at least one pixel
    let steps = ((len / m.step_px.max(1.0)).ceil() as usize).clamp(1, 4 * (w + h));
    let (ia, ib) = (1.0 / a.z, 1.0 / b.z); // guard: a.z, b.z >= Z_MIN > 0
    for s in 0..=steps {
        // guard: steps >= 1
        let l = s as f64 / steps as f64;
        // perspective-correct depth along the segment; guard: both inverse
        // depths > 0, so their blend is too
        let qz = 1.0 / ((1.0 - l) * ia + l * ib);
        match hidden_at(depth, m.thickness, pa + (pb - pa) * l, qz, m.slack) {
            None => return true,
            Some(true) => return false,
            Some(false) => {}
        }
    }
    true
}

/// A shadow ray's start: the surface point `pos` lifted along its normal
/// `n` by `slack` (metres, plus a fraction of its depth), clear of its own
/// depth pixel.
pub(crate) fn ray_start(pos: DVec3, n: DVec3, (abs, rel): (f64, f64)) -> DVec3 {
    pos + n * (abs + rel * pos.z)
}

/// The depth map's test of a ray point at depth `qz` seen at image point
/// `u`: `None` outside the frame (the ray leaves it: open), else whether
/// the depth pixel there hides the point (behind it by more than the
/// tolerance `slack`, less than the pixel's `thickness`; no depth hides
/// nothing). The test of both marches, the fit's and [`lit_by_pixels`].
pub(crate) fn hidden_at(
    depth: &DepthMap,
    thickness: &[f32],
    u: DVec2,
    qz: f64,
    (abs, rel): (f64, f64),
) -> Option<bool> {
    let (w, h) = depth.dims();
    if u.x < 0.0 || u.y < 0.0 || u.x >= w as f64 || u.y >= h as f64 {
        return None;
    }
    let (x, y) = (u.x as usize, u.y as usize);
    let z = *depth.get(x, y);
    if !DepthMap::is_valid(z) {
        return Some(false);
    }
    let z = f64::from(z);
    let thick = thickness.get(y * w + x).map_or(0.0, |t| f64::from(*t));
    Some(z < qz - (abs + rel * qz) && qz - z < thick)
}

/// What `refine_direction` found.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Refined {
    /// The refined unit direction.
    pub direction: DVec3,
    /// Pixels in the band.
    pub band: usize,
    /// Band pixels whose visibility disagreed with their label at the
    /// fit's direction, and at the refined one.
    pub disagree_before: usize,
    /// At the refined direction.
    pub disagree_after: usize,
}

/// Rotates the unit `d` by `angle` radians towards the unit `t` (`t ⟂ d`).
fn turn(d: DVec3, t: DVec3, angle: f64) -> DVec3 {
    (d * angle.cos() + t * angle.sin()).normalize_or(d)
}

/// Log luminance of every `stride`-th pixel in x and y that lies in a
/// region, the mean of its 3x3 neighbours in the same region (`None`
/// elsewhere or when black), row-major on that grid.
fn smoothed_log_luminance(color: &ColorImage, labels: &[u32], stride: usize) -> Vec<Option<f64>> {
    let (w, h) = color.dims();
    let stride = stride.max(1);
    let (gw, gh) = (w.div_ceil(stride), h.div_ceil(stride));
    (0..gw * gh)
        .into_par_iter()
        .with_min_len(4096)
        .map(|g| {
            let (x, y) = ((g % gw) * stride, (g / gw) * stride);
            let r = labels[y * w + x];
            if r == NO_REGION {
                return None;
            }
            let (mut s, mut n) = (0.0f64, 0.0f64);
            for yy in y.saturating_sub(1)..(y + 2).min(h) {
                for xx in x.saturating_sub(1)..(x + 2).min(w) {
                    if labels[yy * w + xx] == r {
                        s += luminance_f64(color.get(xx, yy).map(f64::from));
                        n += 1.0;
                    }
                }
            }
            // guard: n >= 1 (the pixel itself); a black mean has no log
            let m = s / n.max(1.0);
            (m > 1e-12 && m.is_finite()).then(|| m.ln())
        })
        .collect()
}

/// Refines the light's direction `d` by the cast shadows' edges (module
/// docs); `surfaces` and `labels` per pixel (the fit's albedo regions),
/// `min_up` the sine of the lowest elevation the direction may take.
/// `None` when the band is too small or no direction agrees better.
#[allow(clippy::too_many_arguments)]
pub(crate) fn refine_direction(
    color: &ColorImage,
    depth: &DepthMap,
    k: &Intrinsics,
    surfaces: &[Option<Surf>],
    labels: &[u32],
    d: DVec3,
    min_up: f64,
    march: March,
    p: &EdgeParams,
) -> Option<Refined> {
    let (w, h) = color.dims();
    if w == 0 || h == 0 || surfaces.len() != w * h || labels.len() != w * h {
        return None;
    }
    // pixels labelled on a grid of `stride` (about 320 across), windows
    // scaled with the image and read on the same grid
    let stride = (w / 320).max(1);
    let logl = smoothed_log_luminance(color, labels, stride);
    let (gw, gh) = (w.div_ceil(stride), h.div_ceil(stride));
    let win = p.window;
    let log_contrast = p.min_contrast.max(1.0).ln();
    let labelled: Vec<(usize, bool)> = (0..gh)
        .into_par_iter()
        .flat_map_iter(|gy| {
            let logl = &logl;
            (0..gw).filter_map(move |gx| {
                let i = gy * stride * w + gx * stride;
                let v = logl[gy * gw + gx]?;
                let s = surfaces[i].as_ref()?;
                if s.n.dot(d) < p.min_facing {
                    return None;
                }
                let r = labels[i];
                let (mut lo, mut hi) = (v, v);
                for yy in gy.saturating_sub(win)..(gy + win + 1).min(gh) {
                    for xx in gx.saturating_sub(win)..(gx + win + 1).min(gw) {
                        if labels[yy * stride * w + xx * stride] == r
                            && let Some(u) = logl[yy * gw + xx]
                        {
                            lo = lo.min(u);
                            hi = hi.max(u);
                        }
                    }
                }
                // the pixel's own luminance against the middle of the
                // window's (in linear units: a blurred edge's 50 % point)
                let own = luminance_f64(color.as_slice()[i].map(f64::from));
                (hi - lo >= log_contrast).then_some((i, own > 0.5 * (lo.exp() + hi.exp())))
            })
        })
        .collect();
    // the band: labelled pixels whose visibility changes within the radius
    let radius = p.radius_deg.to_radians();
    let (t1, t2) = d.any_orthonormal_pair();
    let probes = [
        turn(d, t1, radius),
        turn(d, -t1, radius),
        turn(d, t2, radius),
        turn(d, -t2, radius),
    ];
    let take = |v: &[(usize, bool)], most: usize| -> Vec<(usize, bool)> {
        if v.len() <= most {
            return v.to_vec();
        }
        // guard: most >= 1 below
        let every = v.len().div_ceil(most.max(1));
        v.iter().step_by(every).copied().collect()
    };
    let v_with = |i: usize, dir: DVec3, m: March| -> bool {
        surfaces[i]
            .as_ref()
            .is_none_or(|s| s.n.dot(dir) > 0.0 && lit_by_pixels(depth, k, s.pos, s.n, dir, m))
    };
    let v_of = |i: usize, dir: DVec3| v_with(i, dir, march);
    // the band's test marches in steps twice as long (it only asks whether
    // the visibility changes somewhere within the radius)
    let coarse = March {
        step_px: 2.0 * march.step_px.max(1.0),
        ..march
    };
    let band: Vec<(usize, bool)> = take(&labelled, p.max_candidates)
        .into_par_iter()
        .filter(|&(i, _)| {
            let first = v_with(i, probes[0], coarse);
            probes[1..].iter().any(|&q| v_with(i, q, coarse) != first)
                || v_with(i, d, coarse) != first
        })
        .collect();
    let band = take(&band, p.max_band);
    if band.len() < p.min_band.max(1) {
        return None;
    }
    let cost = |dir: DVec3| -> usize {
        band.par_iter()
            .with_min_len(64)
            .filter(|&&(i, lit)| v_of(i, dir) != lit)
            .count()
    };
    let before = cost(d);
    let (mut cur, mut best) = (d, before);
    let cos_radius = radius.cos();
    let mut step = p.step_deg.max(1e-3).to_radians();
    let min_step = p.min_step_deg.max(1e-4).to_radians();
    while step >= min_step && best > 0 {
        let (u1, u2) = cur.any_orthonormal_pair();
        let next = [u1, -u1, u2, -u2]
            .into_iter()
            .map(|t| turn(cur, t, step))
            .filter(|q| q.dot(d) >= cos_radius && -q.y >= min_up)
            .map(|q| (q, cost(q)))
            .min_by_key(|&(_, c)| c);
        match next {
            Some((q, c)) if c < best => {
                cur = q;
                best = c;
            }
            _ => step *= 0.5,
        }
    }
    (best < before).then_some(Refined {
        direction: cur,
        band: band.len(),
        disagree_before: before,
        disagree_after: best,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::relight::lighting::thickness::occluder_thickness;

    /// A pole on the floor: 6 cm square, 70 cm high, 2 m away.
    const BOX_LO: DVec3 = DVec3::new(-0.03, -0.2, 2.0);
    const BOX_HI: DVec3 = DVec3::new(0.03, 0.5, 2.06);

    /// A floor plane at y = 0.5 (camera y down) seen from the camera, with
    /// the pole [`BOX_LO`]-[`BOX_HI`] standing on it: depth and surfaces.
    fn floor_with_pole(w: usize, h: usize) -> (DepthMap, Intrinsics, Vec<Option<Surf>>) {
        let k = crate::test_support::square_camera(w, h);
        let mut depth: DepthMap = Image::filled(w, h, 0.0f32);
        let mut surfaces = vec![None; w * h];
        for y in 0..h {
            for x in 0..w {
                let ray = k.unproject(x as f64 + 0.5, y as f64 + 0.5, 1.0);
                // the pole (slabs), else the floor
                let (lo, hi) = (BOX_LO, BOX_HI);
                let (mut t_in, mut t_out, mut axis) = (0.0f64, f64::INFINITY, 2);
                for a in 0..3 {
                    if ray[a].abs() < 1e-12 {
                        if lo[a] > 0.0 || hi[a] < 0.0 {
                            t_out = -1.0;
                        }
                        continue;
                    }
                    let (ta, tb) = (lo[a] / ray[a], hi[a] / ray[a]);
                    let (near, far) = (ta.min(tb), ta.max(tb));
                    if near > t_in {
                        t_in = near;
                        axis = a;
                    }
                    t_out = t_out.min(far);
                }
                let (pos, n) = if t_in <= t_out && t_out > 0.0 {
                    let mut n = DVec3::ZERO;
                    n[axis] = -ray[axis].signum();
                    (ray * t_in, n)
                } else if ray.y > 0.0 {
                    (ray * (0.5 / ray.y), DVec3::NEG_Y)
                } else {
                    continue;
                };
                *depth.get_mut(x, y) = pos.z as f32;
                surfaces[y * w + x] = Some(Surf { pos, n });
            }
        }
        (depth, k, surfaces)
    }

    /// The march of the tests, through `thick` (the estimate of
    /// [`occluder_thickness`]: the pole is as deep as it is wide).
    fn march(thick: &[f32]) -> March<'_> {
        March {
            t0: 0.02,
            reach: 3.0,
            thickness: thick,
            slack: March::FINE_SLACK,
            step_px: 1.0,
        }
    }

    #[test]
    fn a_march_by_pixels_finds_the_pole_between_the_floor_and_the_light() {
        let (depth, k, _) = floor_with_pole(160, 120);
        let thick = occluder_thickness(&depth, &k, 0.4);
        // a floor point 10 cm in front of the pole, the light behind it
        // (away from the camera, up)
        let pos = DVec3::new(0.0, 0.5, 1.9);
        let n = DVec3::NEG_Y;
        let behind = DVec3::new(0.0, -1.0, 1.0).normalize();
        assert!(!lit_by_pixels(&depth, &k, pos, n, behind, march(&thick)));
        // the light from the camera's side: open
        let front = DVec3::new(0.0, -1.0, -1.0).normalize();
        assert!(lit_by_pixels(&depth, &k, pos, n, front, march(&thick)));
        // beside the pole: open
        let aside = DVec3::new(1.0, -1.0, 0.0).normalize();
        assert!(lit_by_pixels(&depth, &k, pos, n, aside, march(&thick)));
    }

    /// The floor of [`floor_with_pole`] lit by a sun `sun` (and a sky a
    /// tenth of it), in the pole's shadow where the exact ray meets it.
    fn render(
        w: usize,
        h: usize,
        sun: DVec3,
    ) -> (ColorImage, DepthMap, Intrinsics, Vec<Option<Surf>>) {
        let (depth, k, surfaces) = floor_with_pole(w, h);
        let color = ColorImage::from_fn(w, h, |x, y| {
            let Some(s) = &surfaces[y * w + x] else {
                return [0.0; 3];
            };
            let cos = s.n.dot(sun).max(0.0);
            // exact shadow of the pole on the floor: the ray to the sun meets
            // its volume
            let mut shadowed = false;
            if s.n == DVec3::NEG_Y {
                for i in 1..4000 {
                    let q = s.pos + sun * (i as f64 * 0.001);
                    if q.cmpge(BOX_LO).all() && q.cmple(BOX_HI).all() {
                        shadowed = true;
                        break;
                    }
                }
            }
            let e = 0.1 + if shadowed { 0.0 } else { cos };
            [(0.5 * e) as f32; 3]
        });
        (color, depth, k, surfaces)
    }

    #[test]
    fn the_refined_direction_lands_on_the_shadow_that_was_rendered() {
        let (w, h) = (320, 240);
        let sun = DVec3::new(0.7, -0.6, -0.2).normalize();
        let (color, depth, k, surfaces) = render(w, h, sun);
        let thick = occluder_thickness(&depth, &k, 0.4);
        // one region: the floor and the pole alike (one albedo)
        let labels: Vec<u32> = surfaces
            .iter()
            .map(|s| if s.is_some() { 0 } else { NO_REGION })
            .collect();
        let (t1, _) = sun.any_orthonormal_pair();
        let start = turn(sun, t1, 3f64.to_radians());
        let refine = |photo: &ColorImage| {
            refine_direction(
                photo,
                &depth,
                &k,
                &surfaces,
                &labels,
                start,
                0.0,
                march(&thick),
                &EdgeParams::default(),
            )
        };
        let r = refine(&color).expect("a refinement");
        let err = r.direction.dot(sun).clamp(-1.0, 1.0).acos().to_degrees();
        assert!(err < 0.3, "{err}° off (from 3°), {r:?}");
        assert!(r.disagree_after < r.disagree_before);
        // no shadow in the photo: nothing to refine
        let flat = ColorImage::from_fn(w, h, |_, _| [0.3; 3]);
        assert!(refine(&flat).is_none());
    }
}
