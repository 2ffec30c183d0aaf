//! EdgeDetect: device against CPU.

mod common;

use std::sync::Arc;

use common::*;
use depthgraph_gpu::edges::strength_tol;
use depthgraph_gpu::parity::edges_within;
use depthgraph_graph::prelude::*;
use depthgraph_nodes::select::edges::{DepthTerm, EdgeParams};

fn outs(o: &Outputs) -> (Arc<Confidence>, Arc<Mask>) {
    let s = match o.values.get("strength") {
        Some(Value::Confidence(c)) => c.clone(),
        other => panic!("strength: {other:?}"),
    };
    let e = match o.values.get("edges") {
        Some(Value::Mask(m)) => m.clone(),
        other => panic!("edges: {other:?}"),
    };
    (s, e)
}

/// A box in front of a slanted wall, textured, with holes and broken values.
fn scene(w: usize, h: usize) -> Inputs {
    let mut d = DepthMap::from_fn(w, h, |x, y| {
        if (w / 3..2 * w / 3).contains(&x) && (h / 3..2 * h / 3).contains(&y) {
            1.2
        } else {
            3.0 + 0.01 * x as f32 + 0.004 * y as f32
        }
    });
    *d.get_mut(5, 5) = 0.0;
    *d.get_mut(6, 5) = f32::NAN;
    *d.get_mut(7, 5) = f32::INFINITY;
    let mut c = ColorImage::from_fn(w, h, |x, y| {
        let t = ((x / 4 + y / 6) % 3) as f32 * 0.2;
        [0.2 + t, 0.5, 0.8 - t]
    });
    *c.get_mut(9, 9) = [f32::NAN, 40.0, -1.0];
    let mut i = Inputs::new();
    i.insert("color", Value::Color(Arc::new(c)));
    i.insert("depth", Value::Depth(Arc::new(d)));
    i
}

#[test]
fn edges_agree_with_the_cpu_within_their_stated_bound() {
    let i = scene(97, 71);
    for p in [
        EdgeParams::default(),
        EdgeParams {
            depth_term: DepthTerm::Gradient,
            thin: false,
            threshold: 0.2,
            ..Default::default()
        },
        EdgeParams {
            color_weight: 1.0,
            depth_weight: 0.0,
            threshold: 0.3,
            ..Default::default()
        },
    ] {
        let (cpu, dev) = both("EdgeDetect", &i, &p.to_values());
        let (sa, ea) = outs(&cpu);
        let (sb, eb) = outs(&dev);
        let (worst, ambiguous) =
            edges_within((&sa, &ea), (&sb, &eb), p.threshold, strength_tol(&p))
                .unwrap_or_else(|e| panic!("{p:?}: {e}"));
        eprintln!(
            "{:?}: max |ds| {worst:.2e}, {ambiguous} ambiguous edge bits differ",
            p.depth_term
        );
        assert!(ea.as_slice().iter().any(|v| *v > 0.0), "the case has edges");
    }
}

#[test]
fn the_edges_check_fails_on_a_perturbed_result() {
    let i = scene(64, 48);
    let p = EdgeParams::default();
    let (cpu, dev) = both("EdgeDetect", &i, &p.to_values());
    let (sa, ea) = outs(&cpu);
    let (sb, eb) = outs(&dev);
    let tol = strength_tol(&p);
    assert!(edges_within((&sa, &ea), (&sb, &eb), p.threshold, tol).is_ok());
    let mut off = (*sb).clone();
    off.as_mut_slice()[100] += 3.0 * tol as f32;
    assert!(edges_within((&sa, &ea), (&off, &eb), p.threshold, tol).is_err());
    // an edge bit set where the strength is far below the threshold
    let t = sa
        .as_slice()
        .iter()
        .position(|v| (*v as f64) < p.threshold - 0.2)
        .unwrap();
    let mut flipped = (*eb).clone();
    flipped.as_mut_slice()[t] = 1.0 - flipped.as_slice()[t];
    assert!(edges_within((&sa, &ea), (&sb, &flipped), p.threshold, tol).is_err());
}
