//! PullPush and DualPullPush: device against CPU.

mod common;

use std::sync::Arc;

use common::*;
use depthgraph_gpu::parity::depth_within;
use depthgraph_gpu::pull_push::{DUAL_REL_TOL, REL_TOL};
use depthgraph_graph::prelude::*;
use depthgraph_nodes::depth::pull_push::{PullPushParams, ShadowSide};
use depthgraph_nodes::kit::rng::SplitMix64;

/// Two slanted planes with holes: scattered, a large block, a border strip,
/// and the odd values a sensor writes.
fn scene(w: usize, h: usize, seed: u64, hole_rate: f64) -> (DepthMap, ColorImage, Intrinsics) {
    let mut rng = SplitMix64(seed);
    let mut d = DepthMap::from_fn(w, h, |x, y| {
        if x < w / 2 {
            1.0 + 0.01 * y as f32
        } else {
            2.5 + 0.003 * x as f32
        }
    });
    for z in d.as_mut_slice() {
        if rng.next_f64() < hole_rate {
            *z = 0.0;
        }
    }
    for y in h / 3..h / 2 {
        for x in w / 4..w / 2 + 5 {
            *d.get_mut(x, y) = 0.0;
        }
    }
    for y in 0..h {
        *d.get_mut(w - 1, y) = f32::NAN;
    }
    *d.get_mut(2, 2) = f32::INFINITY;
    *d.get_mut(3, 2) = -1.0;
    let c = ColorImage::from_fn(w, h, |x, y| {
        if x < w / 2 {
            [0.7, 0.2, 0.1]
        } else {
            [0.1, 0.3 + 0.002 * y as f32, 0.8]
        }
    });
    let k = Intrinsics {
        fx: w as f64,
        fy: w as f64,
        cx: w as f64 / 2.0,
        cy: h as f64 / 2.0,
        width: w,
        height: h,
    };
    (d, c, k)
}

fn mask_of(o: &Outputs) -> Arc<Mask> {
    match o.values.get("filled") {
        Some(Value::Mask(m)) => m.clone(),
        other => panic!("filled: {other:?}"),
    }
}

fn compare(kind: &str, i: &Inputs, p: &PullPushParams) -> f64 {
    let tol = if kind == "DualPullPush" {
        DUAL_REL_TOL
    } else {
        REL_TOL
    };
    let (cpu, dev) = both(kind, i, &p.to_values());
    assert_eq!(cpu.passthrough, dev.passthrough, "{kind}");
    assert_eq!(
        *mask_of(&cpu),
        *mask_of(&dev),
        "{kind}: filled masks differ"
    );
    let (a, b) = (depth_of(&cpu, "depth"), depth_of(&dev, "depth"));
    let r = depth_within(&a, &b, tol).unwrap_or_else(|e| panic!("{kind} {p:?}: {e}"));
    r.max_rel
}

#[test]
fn pull_push_agrees_with_the_cpu_within_its_stated_bound() {
    for (w, h, seed, rate) in [(101, 67, 1, 0.2), (64, 64, 2, 0.9), (7, 300, 3, 0.5)] {
        let (d, c, k) = scene(w, h, seed, rate);
        for levels in [0u32, 2] {
            let p = PullPushParams {
                levels,
                ..Default::default()
            };
            let mut i = Inputs::new();
            i.insert("depth", Value::Depth(Arc::new(d.clone())));
            let plain = compare("PullPush", &i, &p);
            i.insert("color", Value::Color(Arc::new(c.clone())));
            i.insert("intrinsics", Value::Intrinsics(k));
            // the near half is left of the far one: "right" takes the holes
            // between them as shadows, "left" as dropouts, "both" as either
            let mut dual = 0.0f64;
            for shadow_side in [ShadowSide::Left, ShadowSide::Right, ShadowSide::Both] {
                dual = dual.max(compare(
                    "DualPullPush",
                    &i,
                    &PullPushParams {
                        epsilon: 1e-4,
                        shadow_side,
                        ..p.clone()
                    },
                ));
            }
            // the device follows the side it is given
            let side = |shadow_side| {
                let q = PullPushParams {
                    epsilon: 1e-4,
                    shadow_side,
                    ..p.clone()
                };
                depth_of(&both("DualPullPush", &i, &q.to_values()).1, "depth")
            };
            // (the 7-pixel-wide scene has no row with both sides around a gap)
            if w >= 64 {
                assert_ne!(
                    side(ShadowSide::Left).as_slice(),
                    side(ShadowSide::Right).as_slice(),
                    "{w}x{h}: left and right shadows fill alike"
                );
            }
            eprintln!(
                "{w}x{h} holes {rate} levels {levels}: max |dz|/z plain {plain:.2e}, dual {dual:.2e}"
            );
        }
    }
}

#[test]
fn the_pull_push_check_fails_on_a_perturbed_result() {
    let (d, _, _) = scene(50, 40, 4, 0.3);
    let mut i = Inputs::new();
    i.insert("depth", Value::Depth(Arc::new(d.clone())));
    let (cpu, dev) = both("PullPush", &i, &PullPushParams::default().to_values());
    let (a, b) = (depth_of(&cpu, "depth"), depth_of(&dev, "depth"));
    assert!(depth_within(&a, &b, REL_TOL).is_ok());
    let t = mask_of(&dev)
        .as_slice()
        .iter()
        .position(|&f| f == 1.0)
        .unwrap();
    let mut off = (*b).clone();
    off.as_mut_slice()[t] *= 1.0 + 3.0 * REL_TOL as f32;
    assert!(depth_within(&a, &off, REL_TOL).is_err());
    let mut holed = (*b).clone();
    holed.as_mut_slice()[t] = 0.0;
    assert!(depth_within(&a, &holed, REL_TOL).is_err());
}

#[test]
fn nothing_to_fill_passes_through_alike() {
    for d in [DepthMap::filled(9, 9, 1.0), DepthMap::filled(9, 9, 0.0)] {
        let mut i = Inputs::new();
        i.insert("depth", Value::Depth(Arc::new(d)));
        let (cpu, dev) = both("PullPush", &i, &PullPushParams::default().to_values());
        assert!(dev.passthrough.is_some());
        assert_eq!(cpu.passthrough, dev.passthrough);
    }
}
