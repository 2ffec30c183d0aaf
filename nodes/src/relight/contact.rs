//! Contact visibility: a short screen-space march against the target's
//! depth, for the distances an imperfect shadow map cannot resolve.
//!
//! A shadow map answers "visible" whenever its occluder lies within the
//! bias of the receiver (the bias hides the splats' own surface, 3d-editing
//! §III.E, eq. 7's neighbourhood). Beside a wall a few centimetres away that
//! band holds the wall itself, and the sky leaks through it onto the pasted
//! object. Where a map's occluder falls in the band, `Relight` asks the
//! photo's depth instead: the ray `x + t d` is sampled at about one pixel's
//! footprint apart for `t` in `(0, t_max]`, and it is blocked where a
//! sample lies behind the surface the photo shows at its pixel by less
//! than a thickness (in front of it, or far behind it, the ray passes:
//! the photo says nothing about what lies behind a surface).
//!
//! The object is not in the target's depth, so the march never meets the
//! object's own surface; it only turns the map's "visible" into "blocked",
//! never the other way.

use depthgraph_graph::prelude::*;
use glam::DVec3;

/// Parameters of [`occluded`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ContactParams {
    /// Samples along the ray, at most.
    pub max_steps: usize,
    /// A sample behind the photo's surface by more than this (metres, plus
    /// the distance marched) is behind a thin object, not inside it.
    pub thickness_m: f64,
}

impl Default for ContactParams {
    fn default() -> Self {
        Self {
            max_steps: 8,
            thickness_m: 0.05,
        }
    }
}

/// Whether the ray from `x` (camera space, metres) along the unit `d` meets
/// the surface of `depth` within `t_max` metres (module docs).
pub fn occluded(
    depth: &DepthMap,
    k: &Intrinsics,
    x: DVec3,
    d: DVec3,
    t_max: f64,
    p: &ContactParams,
) -> bool {
    // guard: fx > 0 for valid intrinsics; a pixel's footprint at x's depth
    let footprint = x.z.abs() / k.fx.max(1e-9);
    if t_max.is_nan() || t_max <= 0.0 || footprint.is_nan() || footprint <= 0.0 {
        return false;
    }
    // about two footprints apart; guard: footprint > 0 (checked above)
    let steps = ((0.5 * t_max / footprint).ceil() as usize).clamp(1, p.max_steps.max(1));
    let (w, h) = depth.dims();
    // the photo's depth at a sample's pixel (`None` off the image or on
    // a hole), and the pixel
    let surface = |s: DVec3| -> Option<(f64, usize, usize)> {
        let uv = k.project(s)?;
        if !(uv.x >= 0.0 && uv.y >= 0.0) {
            return None;
        }
        let (u, v) = (uv.x as usize, uv.y as usize);
        if u >= w || v >= h {
            return None;
        }
        let z = f64::from(*depth.get(u, v));
        DepthMap::is_valid(z as f32).then_some((z, u, v))
    };
    // A pixel's slack: how much the surface's depth changes to its
    // neighbours on it (within 10 %). A sample a few millimetres above a
    // floor seen at a grazing angle lies "behind" the depth at its
    // pixel's centre by up to that much.
    let slack = |z: f64, u: usize, v: usize| -> f64 {
        let mut m = 0.0f64;
        for (du, dv) in [(-1isize, 0isize), (1, 0), (0, -1), (0, 1)] {
            let (uu, vv) = (u as isize + du, v as isize + dv);
            if uu < 0 || vv < 0 || uu as usize >= w || vv as usize >= h {
                continue;
            }
            let zz = f64::from(*depth.get(uu as usize, vv as usize));
            // guard: both > 0 when valid
            if DepthMap::is_valid(zz as f32) && zz.max(z) / zz.min(z) <= 1.1 {
                m = m.max((zz - z).abs());
            }
        }
        m
    };
    // behind the surface at its pixel by more than a footprint and the
    // pixel's slack (the slack only looked up when it matters)
    let behind = |sz: f64, (z, u, v): (f64, usize, usize)| {
        z < sz - footprint && z < sz - footprint - slack(z, u, v)
    };
    // the last sample in front of the photo's surface; the start's is
    // looked up only when the first sample is behind (most marches never
    // need it)
    let start = || surface(x).filter(|q| !behind(x.z, *q));
    let mut in_front = None;
    for i in 1..=steps {
        let t = t_max * i as f64 / steps as f64;
        let s = x + d * t;
        let Some(q) = surface(s) else {
            in_front = None;
            continue;
        };
        let (z, u, v) = q;
        if behind(s.z, q) {
            // inside the surface when close behind it, or when the ray
            // just crossed it: the previous sample in front of the same
            // surface (depths within 10 % per pixel between the two;
            // guard: both > 0)
            let close = s.z - z < p.thickness_m;
            let crossed = || {
                let prev = if i == 1 { start() } else { in_front };
                prev.is_some_and(|(z0, u0, v0)| {
                    let n = u.abs_diff(u0).max(v.abs_diff(v0)).clamp(1, 16);
                    z0.max(z) / z0.min(z) <= 1.1f64.powi(n as i32)
                })
            };
            if close || crossed() {
                return true;
            }
            in_front = None;
        } else {
            in_front = Some(q);
        }
    }
    false
}

#[cfg(test)]
mod tests {
    use super::*;

    fn k() -> Intrinsics {
        Intrinsics {
            fx: 50.0,
            fy: 50.0,
            cx: 32.0,
            cy: 32.0,
            width: 64,
            height: 64,
        }
    }

    /// A wall at `x = -0.5` m seen by the camera at a grazing angle (the
    /// plane's depth where it is to the left), the background far away: a
    /// point 3 cm from the wall is blocked towards the wall and not away
    /// from it, nor towards it when the march is shorter than the gap.
    #[test]
    fn a_wall_beside_the_point_blocks_rays_towards_it_only() {
        let k = k();
        // a plane x = -0.5 facing +x: for pixel u left of the centre the
        // ray (u - cx)/fx * z = -0.5 gives z = -0.5 fx / (u - cx)
        let depth = Image::from_fn(64, 64, |u, _| {
            let a = (u as f64 + 0.5 - k.cx) / k.fx;
            if a < -0.5 / 4.0 {
                (-0.5 / a) as f32
            } else {
                4.0
            }
        });
        let x = DVec3::new(-0.47, 0.0, 1.5);
        let p = ContactParams::default();
        let towards = DVec3::new(-1.0, -1.0, 0.0).normalize();
        let away = DVec3::new(1.0, -1.0, 0.0).normalize();
        assert!(occluded(&depth, &k, x, towards, 0.2, &p));
        assert!(!occluded(&depth, &k, x, away, 0.2, &p));
        assert!(!occluded(&depth, &k, x, towards, 0.02, &p));
    }

    /// Behind a thin surface (farther than the thickness) the ray passes;
    /// holes (depth 0) never block; a zero march is visible.
    #[test]
    fn thin_surfaces_and_holes_do_not_block() {
        let k = k();
        let x = DVec3::new(0.0, 0.0, 2.0);
        let d = DVec3::new(0.0, 0.0, 1.0);
        let p = ContactParams::default();
        let near = Image::filled(64, 64, 1.0f32);
        assert!(!occluded(&near, &k, x, d, 0.3, &p));
        let hole = Image::filled(64, 64, 0.0f32);
        assert!(!occluded(&hole, &k, x, d, 0.3, &p));
        let just = Image::filled(64, 64, 2.05f32);
        assert!(occluded(&just, &k, x, d, 0.3, &p));
        assert!(!occluded(&just, &k, x, d, 0.0, &p));
    }
}
