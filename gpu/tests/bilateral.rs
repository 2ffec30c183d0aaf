//! JointBilateral: device against CPU on lavapipe (or any adapter).

mod common;

use common::*;
use depthgraph_gpu::bilateral::REL_TOL;
use depthgraph_gpu::parity::depth_within;
use depthgraph_graph::prelude::*;
use depthgraph_nodes::depth::bilateral::BilateralParams;
use depthgraph_nodes::kit::rng::SplitMix64;

/// A noisy two-plane scene with holes, NaN, infinities and a hot color.
fn scene(w: usize, h: usize, seed: u64) -> (DepthMap, ColorImage) {
    let mut rng = SplitMix64(seed);
    let depth = DepthMap::from_fn(w, h, |x, _| {
        let base = if x < w / 2 { 1.2 } else { 3.5 };
        (base + 0.01 * rng.gaussian()) as f32
    });
    let mut depth = depth;
    let color = ColorImage::from_fn(w, h, |x, y| {
        if x < w / 2 {
            [0.8, 0.2 + 0.001 * y as f32, 0.1]
        } else {
            [0.05, 0.3, 0.9]
        }
    });
    let mut color = color;
    for (k, v) in [0.0, f32::NAN, f32::INFINITY, -1.0, f32::NEG_INFINITY]
        .iter()
        .enumerate()
    {
        *depth.get_mut(3 + 7 * k, 5 + 3 * k) = *v;
    }
    for k in 0..40 {
        *depth.get_mut((k * 13) % w, (k * 29) % h) = 0.0;
    }
    *color.get_mut(10, 10) = [f32::NAN, 50.0, f32::INFINITY];
    (depth, color)
}

fn inputs(depth: DepthMap, color: ColorImage) -> Inputs {
    let mut i = Inputs::new();
    i.insert("depth", Value::Depth(std::sync::Arc::new(depth)));
    i.insert("color", Value::Color(std::sync::Arc::new(color)));
    i
}

#[test]
fn bilateral_agrees_with_the_cpu_within_its_stated_bound() {
    for (radius, sigma_depth_rel) in [(1usize, 0.02), (5, 0.02), (7, 0.1), (12, 0.5)] {
        let (depth, color) = scene(97, 61, radius as u64);
        let p = BilateralParams {
            radius,
            sigma_depth_rel,
            ..Default::default()
        };
        let (cpu, dev) = both("JointBilateral", &inputs(depth, color), &p.to_values());
        let (a, b) = (depth_of(&cpu, "depth"), depth_of(&dev, "depth"));
        let agreement =
            depth_within(&a, &b, REL_TOL).unwrap_or_else(|e| panic!("r = {radius}: {e}"));
        eprintln!("r = {radius}: max |dz|/z = {:.2e}", agreement.max_rel);
        assert!(dev.transfers.uploads + dev.transfers.resident_hits >= 2);
        assert_eq!(dev.transfers.downloads, 1);
    }
}

#[test]
fn the_bilateral_check_fails_on_a_perturbed_result() {
    let (depth, color) = scene(64, 48, 9);
    let (cpu, dev) = both(
        "JointBilateral",
        &inputs(depth, color),
        &BilateralParams::default().to_values(),
    );
    let (a, b) = (depth_of(&cpu, "depth"), depth_of(&dev, "depth"));
    assert!(depth_within(&a, &b, REL_TOL).is_ok());
    // one pixel off by twice the tolerance
    let mut off = (*b).clone();
    let z = *off.get(20, 20);
    *off.get_mut(20, 20) = z * (1.0 + 2.0 * REL_TOL as f32);
    assert!(depth_within(&a, &off, REL_TOL).is_err());
    // one valid pixel turned into a hole
    let mut holed = (*b).clone();
    *holed.get_mut(30, 30) = 0.0;
    let e = depth_within(&a, &holed, REL_TOL).unwrap_err();
    assert!(e.contains("hole masks differ"), "{e}");
}

#[test]
fn an_all_hole_map_passes_through_on_both_backends() {
    let depth = DepthMap::filled(8, 8, 0.0);
    let color = ColorImage::filled(8, 8, [0.5; 3]);
    let (cpu, dev) = both(
        "JointBilateral",
        &inputs(depth, color),
        &BilateralParams::default().to_values(),
    );
    assert_eq!(cpu.passthrough, dev.passthrough);
    assert!(dev.passthrough.is_some());
    // a color of another size is the same error on both
    let (reg_cpu, reg_dev) = registries();
    let bad = inputs(
        DepthMap::filled(8, 8, 1.0),
        ColorImage::filled(7, 8, [0.5; 3]),
    );
    let p = BilateralParams::default().to_values();
    let e1 = eval_on(&reg_cpu, "JointBilateral", &bad, &p)
        .unwrap_err()
        .to_string();
    let e2 = eval_on(&reg_dev, "JointBilateral", &bad, &p)
        .unwrap_err()
        .to_string();
    assert_eq!(e1, e2);
}
