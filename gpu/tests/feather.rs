//! Feather: device against CPU.

mod common;

use std::sync::Arc;

use common::*;
use depthgraph_gpu::feather::ABS_TOL;
use depthgraph_graph::prelude::*;
use depthgraph_nodes::select::feather::{FeatherMode, FeatherParams, FeatherPlan, plan};

fn mask_out(o: &Outputs) -> Arc<Mask> {
    match o.values.get("mask") {
        Some(Value::Mask(m)) => m.clone(),
        other => panic!("mask: {other:?}"),
    }
}

/// Bit-identical where the plan leaves pixels alone, within `tol` elsewhere.
fn within(cpu: &Mask, gpu: &Mask, near: &[bool], tol: f64) -> Result<f64, String> {
    if cpu.dims() != gpu.dims() {
        return Err("sizes differ".into());
    }
    let mut worst = 0.0f64;
    for (t, ((a, b), n)) in cpu
        .as_slice()
        .iter()
        .zip(gpu.as_slice())
        .zip(near)
        .enumerate()
    {
        if !n && a.to_bits() != b.to_bits() {
            return Err(format!("untouched pixel {t} differs: {a} vs {b}"));
        }
        let d = (*a as f64 - *b as f64).abs();
        if d.is_nan() || d > tol {
            return Err(format!("pixel {t}: {a} vs {b}, |d| = {d:.2e} > {tol:e}"));
        }
        worst = worst.max(d);
    }
    Ok(worst)
}

/// A disc with a soft edge, a hole, NaN and out-of-range values.
fn disc(w: usize, h: usize) -> Mask {
    let mut m = Mask::from_fn(w, h, |x, y| {
        let (dx, dy) = (x as f32 - w as f32 / 2.0, y as f32 - h as f32 / 2.0);
        let r = (dx * dx + dy * dy).sqrt();
        if r < 0.3 * w as f32 {
            1.0
        } else if r < 0.32 * w as f32 {
            0.5
        } else {
            0.0
        }
    });
    *m.get_mut(w / 2, h / 2) = 0.0;
    *m.get_mut(1, 1) = f32::NAN;
    *m.get_mut(2, 1) = 7.0;
    *m.get_mut(3, 1) = -2.0;
    m
}

fn near_of(m: &Mask, p: &FeatherParams) -> Vec<bool> {
    match plan(m, p).unwrap() {
        FeatherPlan::Unchanged(_) => vec![false; m.len()],
        FeatherPlan::Blur { near, .. } => near,
    }
}

#[test]
fn feather_agrees_with_the_cpu_within_its_stated_bound() {
    for (w, h) in [(120, 90), (33, 200)] {
        let m = disc(w, h);
        for (sigma_px, mode) in [
            (2.0, FeatherMode::Inside),
            (0.7, FeatherMode::Centered),
            (9.0, FeatherMode::Inside),
        ] {
            let p = FeatherParams { sigma_px, mode };
            let mut i = Inputs::new();
            i.insert("mask", Value::Mask(Arc::new(m.clone())));
            let (cpu, dev) = both("Feather", &i, &p.to_values());
            assert_eq!(cpu.passthrough, dev.passthrough);
            let d = within(&mask_out(&cpu), &mask_out(&dev), &near_of(&m, &p), ABS_TOL)
                .unwrap_or_else(|e| panic!("{w}x{h} {p:?}: {e}"));
            eprintln!("{w}x{h} sigma {sigma_px}: max |d| {d:.2e}");
        }
    }
}

#[test]
fn the_feather_check_fails_on_a_perturbed_result() {
    let m = disc(64, 64);
    let p = FeatherParams::default();
    let mut i = Inputs::new();
    i.insert("mask", Value::Mask(Arc::new(m.clone())));
    let (cpu, dev) = both("Feather", &i, &p.to_values());
    let near = near_of(&m, &p);
    let (a, b) = (mask_out(&cpu), mask_out(&dev));
    assert!(within(&a, &b, &near, ABS_TOL).is_ok());
    let t = near.iter().position(|n| *n).unwrap();
    let mut off = (*b).clone();
    off.as_mut_slice()[t] += 3.0 * ABS_TOL as f32;
    assert!(within(&a, &off, &near, ABS_TOL).is_err());
    let u = near.iter().position(|n| !n).unwrap();
    let mut ulp = (*b).clone();
    let v = &mut ulp.as_mut_slice()[u];
    *v = f32::from_bits(v.to_bits() ^ 1);
    assert!(
        within(&a, &ulp, &near, ABS_TOL)
            .unwrap_err()
            .contains("untouched")
    );
}

#[test]
fn nothing_to_feather_passes_through_alike() {
    for (m, sigma) in [(Mask::filled(8, 8, 1.0), 2.0), (disc(16, 16), 0.0)] {
        let mut i = Inputs::new();
        i.insert("mask", Value::Mask(Arc::new(m)));
        let p = FeatherParams {
            sigma_px: sigma,
            ..Default::default()
        };
        let (cpu, dev) = both("Feather", &i, &p.to_values());
        assert!(dev.passthrough.is_some());
        assert_eq!(cpu.passthrough, dev.passthrough);
        assert_eq!(*mask_out(&cpu), *mask_out(&dev));
    }
}
