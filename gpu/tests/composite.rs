//! OcclusionComposite: device against CPU.

mod common;

use std::sync::Arc;

use common::*;
use depthgraph_gpu::composite::REL_TOL;
use depthgraph_gpu::parity::composite_within;
use depthgraph_graph::prelude::*;
use depthgraph_nodes::select::composite::CompositeParams;

/// A pasted square partly behind the target, some of it exactly at the
/// tolerance's limit, with soft, NaN, subnormal and out-of-range alphas and
/// holes on both sides.
fn inputs(tol: f64) -> Inputs {
    let (w, h) = (90, 70);
    let td = DepthMap::from_fn(w, h, |x, y| {
        if (x + y) % 23 == 0 {
            0.0
        } else {
            1.5 + 0.01 * x as f32
        }
    });
    let tc = ColorImage::from_fn(w, h, |x, y| {
        [0.1 * (x % 7) as f32, 0.4, 0.02 * (y % 9) as f32]
    });
    let pz = DepthMap::from_fn(w, h, |x, y| {
        let t = *td.get(x, y);
        match (x + 2 * y) % 5 {
            0 => 0.0,
            1 => 1.2,
            // exactly the CPU's limit, and one step either side
            2 => (t as f64 * (1.0 + tol)) as f32,
            3 => f32::from_bits(((t as f64 * (1.0 + tol)) as f32).to_bits() + 1),
            _ => 2.5,
        }
    });
    let pc = ColorImage::from_fn(w, h, |x, _| [0.9, 0.05 * (x % 3) as f32, 3.0]);
    let pa = Mask::from_fn(w, h, |x, y| match (x * 3 + y) % 7 {
        0 => f32::NAN,
        1 => 1e-40, // subnormal
        2 => 1.7,
        3 => -0.5,
        4 => 0.35,
        _ => 1.0,
    });
    let mut i = Inputs::new();
    i.insert("target_color", Value::Color(Arc::new(tc)));
    i.insert("target_depth", Value::Depth(Arc::new(td)));
    i.insert("pasted_color", Value::Color(Arc::new(pc)));
    i.insert("pasted_depth", Value::Depth(Arc::new(pz)));
    i.insert("pasted_alpha", Value::Mask(Arc::new(pa)));
    i
}

fn outs(o: &Outputs) -> (Arc<ColorImage>, Arc<DepthMap>, Arc<Mask>) {
    let a = match o.values.get("alpha") {
        Some(Value::Mask(m)) => m.clone(),
        other => panic!("alpha: {other:?}"),
    };
    (color_of(o, "color"), depth_of(o, "depth"), a)
}

#[test]
fn composite_agrees_with_the_cpu_within_its_stated_bound() {
    for tol in [0.0, 0.05, 1e-7] {
        let p = CompositeParams { tolerance_rel: tol };
        let (cpu, dev) = both("OcclusionComposite", &inputs(tol), &p.to_values());
        let (c1, z1, a1) = outs(&cpu);
        let (c2, z2, a2) = outs(&dev);
        composite_within((&c1, &z1, &a1), (&c2, &z2, &a2), REL_TOL)
            .unwrap_or_else(|e| panic!("tol {tol}: {e}"));
        let hidden = a1.as_slice().iter().filter(|a| **a == 0.0).count();
        let blended = a1
            .as_slice()
            .iter()
            .filter(|a| **a > 0.0 && **a < 1.0)
            .count();
        assert!(
            hidden > 100 && blended > 100,
            "tol {tol}: {hidden} hidden, {blended} blended"
        );
    }
}

#[test]
fn the_composite_check_fails_on_a_perturbed_result() {
    let p = CompositeParams {
        tolerance_rel: 0.05,
    };
    let (cpu, dev) = both("OcclusionComposite", &inputs(0.05), &p.to_values());
    let (c1, z1, a1) = outs(&cpu);
    let (c2, z2, a2) = outs(&dev);
    assert!(composite_within((&c1, &z1, &a1), (&c2, &z2, &a2), REL_TOL).is_ok());
    // one hidden pixel shown instead
    let t = a2.as_slice().iter().position(|a| *a == 0.0).unwrap();
    let mut a3 = (*a2).clone();
    a3.as_mut_slice()[t] = 1.0;
    assert!(composite_within((&c1, &z1, &a1), (&c2, &z2, &a3), REL_TOL).is_err());
    // one blended color off by 10x the bound
    let t = a2
        .as_slice()
        .iter()
        .position(|a| *a > 0.0 && *a < 1.0)
        .unwrap();
    let mut c3 = (*c2).clone();
    c3.as_mut_slice()[t][1] += 10.0 * REL_TOL as f32;
    assert!(composite_within((&c1, &z1, &a1), (&c3, &z2, &a2), REL_TOL).is_err());
}
