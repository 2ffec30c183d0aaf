//! Relighting fixtures: a floor and a slab with an exact shadow, as depth
//! maps and as `Relight` inputs, and the check of that shadow.
#![cfg(test)]

use depthgraph_graph::prelude::*;

use crate::relight::shading::{RelightInputs, RelightParams, Relit};
use crate::relight::vpl::Vpl;

/// Floor `y = 0.4` m (rows below the horizon, seen by a Kinect-like
/// camera) and a horizontal slab `x in [-0.2, 0.2]`, `z in [1.6, 2.4]`
/// at `y = 0.2` m, pasted with alpha 1: intrinsics, floor depth, slab
/// depth, slab alpha.
pub(crate) fn floor_and_slab(w: usize, h: usize) -> (Intrinsics, DepthMap, DepthMap, Mask) {
    floor_and_slab_at(w, h, 0.0)
}

/// [`floor_and_slab`] with the slab moved by `dx` metres along x.
pub(crate) fn floor_and_slab_at(
    w: usize,
    h: usize,
    dx_m: f64,
) -> (Intrinsics, DepthMap, DepthMap, Mask) {
    let k = crate::sim::synthetic::kinect_like_intrinsics(w, h);
    let floor = Image::from_fn(w, h, |_, y| {
        let dy = (y as f64 + 0.5 - k.cy) / k.fy;
        if dy > 0.05 { (0.4 / dy) as f32 } else { 0.0 }
    });
    let slab = Image::from_fn(w, h, |x, y| {
        let dx = (x as f64 + 0.5 - k.cx) / k.fx;
        let dy = (y as f64 + 0.5 - k.cy) / k.fy;
        if dy <= 0.0 {
            return 0.0;
        }
        let z = 0.2 / dy;
        if (1.6..=2.4).contains(&z) && (dx * z - dx_m).abs() <= 0.2 {
            z as f32
        } else {
            0.0
        }
    });
    let alpha = slab.map(|z| if *z > 0.0 { 1.0f32 } else { 0.0 });
    (k, floor, slab, alpha)
}

/// The floor and slab of [`floor_and_slab_at`](crate::test_support::relight::floor_and_slab_at)
/// as `Relight` inputs: a grey floor photo (0.5, exactly albedo 0.5
/// under a unit overhead light), a green pasted slab.
pub(crate) struct SlabScene {
    pub k: Intrinsics,
    pub floor: DepthMap,
    pub slab: DepthMap,
    pub alpha: Mask,
    pub photo: ColorImage,
    pub albedo: ColorImage,
    pub pasted_color: ColorImage,
}

impl SlabScene {
    pub(crate) fn new(w: usize, h: usize, dx: f64) -> Self {
        let (k, floor, slab, alpha) = crate::test_support::relight::floor_and_slab_at(w, h, dx);
        let photo = floor.map(|z| if *z > 0.0 { [0.5f32; 3] } else { [0.0; 3] });
        Self {
            k,
            floor,
            slab,
            alpha,
            photo,
            albedo: Image::filled(w, h, [0.5f32; 3]),
            pasted_color: Image::filled(w, h, [0.3f32, 0.6, 0.2]),
        }
    }

    /// The inputs, with the albedo given or to be estimated.
    pub(crate) fn inputs(&self, given_albedo: bool) -> RelightInputs<'_> {
        RelightInputs {
            photo: &self.photo,
            depth: &self.floor,
            normals: None,
            albedo: given_albedo.then_some(&self.albedo),
            pasted_color: &self.pasted_color,
            pasted_depth: &self.slab,
            alpha: &self.alpha,
            k: &self.k,
            capture_vpls: None,
        }
    }
}

pub(crate) fn overhead() -> Vec<Vpl> {
    vec![Vpl {
        direction: [0.0, -1.0, 0.0],
        power: [1.0; 3],
    }]
}

/// The check of the test above, for either visibility scheme.
pub(crate) fn slab_shadow_is_analytic(
    run: &dyn Fn(&RelightInputs, &[Vpl], &RelightParams) -> Relit,
    dx: f64,
) {
    let (w, h) = (160, 120);
    let (k, floor, slab, alpha) = crate::test_support::relight::floor_and_slab_at(w, h, dx);
    let albedo = Image::filled(w, h, [0.5f32; 3]);
    // the photo is exactly albedo x the VPL's irradiance (cos = 1)
    let photo = floor.map(|z| if *z > 0.0 { [0.5f32; 3] } else { [0.0; 3] });
    let pasted_color = Image::filled(w, h, [0.3f32, 0.6, 0.2]);
    let inp = RelightInputs {
        photo: &photo,
        depth: &floor,
        normals: None,
        albedo: Some(&albedo),
        pasted_color: &pasted_color,
        pasted_depth: &slab,
        alpha: &alpha,
        k: &k,
        capture_vpls: None,
    };
    let p = RelightParams {
        ism_points: 20000,
        ism_resolution: 128,
        bounce_vpls: 0,
        ..Default::default()
    };
    let r = run(&inp, &overhead(), &p);
    let (mut shadowed, mut wrong, mut edge, mut untouched) = (0, 0, 0, 0);
    for y in 0..h {
        for x in 0..w {
            let (i, z) = (y * w + x, *floor.get(x, y));
            let (c, d, reg) = (
                r.color.as_slice()[i],
                r.difference.as_slice()[i],
                r.region.as_slice()[i],
            );
            assert!(c.iter().all(|v| v.is_finite() && *v >= 0.0));
            let inside = x > 0
                && y > 0
                && x + 1 < w
                && y + 1 < h
                && [i - 1, i + 1, i - w, i + w]
                    .iter()
                    .all(|&j| alpha.as_slice()[j] >= 1.0);
            if inside {
                // the slab's top, lit as where it was captured (the same
                // light, nothing bounced onto a face looking up): never
                // brighter than its pasted colour (its rim, whose normals
                // the depth cannot give, may see the floor's bounce)
                let pc = pasted_color.as_slice()[i];
                assert!(
                    (0..3).all(|ch| c[ch] <= pc[ch] * (1.0 + 1e-5)),
                    "{c:?} > {pc:?}"
                );
            }
            if reg == 0.0 {
                untouched += 1;
                assert_eq!(c, photo.as_slice()[i]);
                assert_eq!(d, [0.0; 3]);
                continue;
            }
            if alpha.as_slice()[i] > 0.0 || z <= 0.0 {
                continue;
            }
            let q = k.unproject(x as f64 + 0.5, y as f64 + 0.5, z as f64);
            // ray-cast reference: the vertical ray from q meets y = 0.2 at (q.x, q.z)
            let under = (q.x - dx).abs() <= 0.2 && (1.6..=2.4).contains(&q.z);
            let near = ((q.x - dx).abs() - 0.2).abs() < 0.15
                || (q.z - 1.6).abs() < 0.15
                || (q.z - 2.4).abs() < 0.15;
            let dark = c[0] < 0.25;
            if near {
                edge += 1;
            } else if under != dark {
                wrong += 1;
            } else if under {
                shadowed += 1;
                assert!(c[0] < 1e-6, "fully shadowed floor at {q}: {c:?}");
            } else {
                assert_eq!(c, photo.as_slice()[i], "lit floor at {q} changed");
            }
        }
    }
    assert!(shadowed > 30, "{shadowed}");
    assert_eq!(
        wrong, 0,
        "{wrong} pixels disagree with the ray-cast shadow ({edge} near its edge)"
    );
    assert!(
        untouched > w * h / 2,
        "the region is not limited: {untouched} untouched"
    );
    // the slab itself: fully lit from above, keeps its pasted color
    let Some(i) = (0..w * h).find(|&i| alpha.as_slice()[i] > 0.0) else {
        panic!("the slab has no pasted pixel");
    };
    let c = r.color.as_slice()[i];
    assert!((c[1] - 0.6).abs() < 1e-3, "{c:?}");
}

/// The depth of a sphere `(c, r)` seen by `k` (its near side, or its far
/// side with `far`), 0 off it.
pub(crate) fn sphere_depth(k: &Intrinsics, c: glam::DVec3, r: f64, far: bool) -> DepthMap {
    Image::from_fn(k.width, k.height, |x, y| {
        let v = k.unproject(x as f64 + 0.5, y as f64 + 0.5, 1.0);
        let (a, b, cc) = (v.dot(v), v.dot(c), c.dot(c) - r * r);
        let disc = b * b - a * cc;
        if disc < 0.0 {
            return 0.0;
        }
        // guard: a = |v|² >= 1 (v.z = 1)
        let t = if far {
            b + disc.sqrt()
        } else {
            b - disc.sqrt()
        } / a;
        t as f32
    })
}
