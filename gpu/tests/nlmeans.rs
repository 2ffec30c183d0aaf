//! NLMeansInpaint, NLMeansDepth and NLMeansUpsample: device against CPU.

mod common;

use std::sync::Arc;

use common::*;
use depthgraph_gpu::nlmeans::REL_TOL;
use depthgraph_gpu::parity::depth_within;
use depthgraph_graph::prelude::*;
use depthgraph_nodes::depth::nlmeans::{
    NLMeansDepthParams, NLMeansInpaintParams, NLMeansUpsampleParams,
};
use depthgraph_nodes::kit::rng::SplitMix64;

fn conf_of(o: &Outputs) -> Arc<Confidence> {
    match o.values.get("confidence") {
        Some(Value::Confidence(c)) => c.clone(),
        other => panic!("confidence: {other:?}"),
    }
}

/// Largest |Δ| between two confidence maps, or an error on NaN.
fn conf_diff(a: &Confidence, b: &Confidence) -> f64 {
    a.as_slice()
        .iter()
        .zip(b.as_slice())
        .map(|(x, y)| (*x as f64 - *y as f64).abs())
        .fold(
            0.0,
            |m: f64, d| if d.is_nan() { f64::INFINITY } else { m.max(d) },
        )
}

/// A near card on a far wall, textured, with scattered holes and a hole
/// block straddling the card's edge.
fn scene(w: usize, h: usize, seed: u64) -> Inputs {
    let mut rng = SplitMix64(seed);
    let mut d = DepthMap::from_fn(w, h, |x, y| {
        if (w / 4..w / 2).contains(&x) && (h / 4..3 * h / 4).contains(&y) {
            1.0
        } else {
            3.0 + 0.01 * y as f32
        }
    });
    for z in d.as_mut_slice() {
        if rng.next_f64() < 0.15 {
            *z = 0.0;
        }
    }
    for y in h / 3..h / 2 {
        for x in w / 2 - 4..w / 2 + 6 {
            *d.get_mut(x, y) = 0.0;
        }
    }
    let c = ColorImage::from_fn(w, h, |x, y| {
        if (w / 4..w / 2).contains(&x) && (h / 4..3 * h / 4).contains(&y) {
            [0.8, 0.1, 0.1]
        } else {
            [0.1, 0.2 + 0.01 * ((x + y) % 5) as f32, 0.6]
        }
    });
    let mut i = Inputs::new();
    i.insert("depth", Value::Depth(Arc::new(d)));
    i.insert("color", Value::Color(Arc::new(c)));
    i
}

#[test]
fn inpainting_agrees_with_the_cpu_within_its_stated_bound() {
    for (seed, p) in [
        (1, NLMeansInpaintParams::default()),
        (
            2,
            NLMeansInpaintParams {
                far_prior: true,
                ..Default::default()
            },
        ),
        (
            3,
            NLMeansInpaintParams {
                search_radius: 3,
                patch_radius: 1,
                iterations: 3,
                ..Default::default()
            },
        ),
        (
            4,
            NLMeansInpaintParams {
                patch_radius: 0,
                ..Default::default()
            },
        ),
        // a strong background side: the near side's weights are far below
        // f32's range (exp(-400 * 0.6)), and so are the far side's patch
        // similarities across the card's colour edge
        (
            6,
            NLMeansInpaintParams {
                background: 400.0,
                ..Default::default()
            },
        ),
    ] {
        let i = scene(56, 40, seed);
        let (cpu, dev) = both("NLMeansInpaint", &i, &p.to_values());
        let (a, b) = (depth_of(&cpu, "depth"), depth_of(&dev, "depth"));
        let r = depth_within(&a, &b, REL_TOL).unwrap_or_else(|e| panic!("{p:?}: {e}"));
        let dc = conf_diff(&conf_of(&cpu), &conf_of(&dev));
        assert!(dc <= REL_TOL, "{p:?}: confidence differs by {dc}");
        eprintln!(
            "seed {seed}: max |dz|/z {:.2e}, max |dc| {dc:.2e}",
            r.max_rel
        );
    }
}

#[test]
fn the_inpainting_check_fails_on_a_perturbed_result() {
    let i = scene(40, 30, 5);
    let p = NLMeansInpaintParams::default();
    let (cpu, dev) = both("NLMeansInpaint", &i, &p.to_values());
    let (a, b) = (depth_of(&cpu, "depth"), depth_of(&dev, "depth"));
    assert!(depth_within(&a, &b, REL_TOL).is_ok());
    let Some(Value::Depth(input)) = i.get("depth") else {
        panic!()
    };
    let t = input.as_slice().iter().position(|z| *z == 0.0).unwrap();
    let mut off = (*b).clone();
    off.as_mut_slice()[t] *= 1.0 + 3.0 * REL_TOL as f32;
    assert!(depth_within(&a, &off, REL_TOL).is_err());
    let mut unfilled = (*b).clone();
    unfilled.as_mut_slice()[t] = 0.0;
    assert!(depth_within(&a, &unfilled, REL_TOL).is_err());
}

/// A noisy map with outliers: the filter, pruned and not, on both backends.
#[test]
fn denoising_agrees_with_the_cpu_within_its_stated_bound() {
    let mut i = scene(50, 38, 7);
    let mut rng = SplitMix64(8);
    let Some(Value::Depth(d)) = i.get("depth").cloned() else {
        panic!()
    };
    let mut noisy = (*d).clone();
    for z in noisy.as_mut_slice() {
        if *z > 0.0 {
            *z *= 1.0 + 0.01 * rng.gaussian() as f32;
        }
        if rng.next_f64() < 0.01 {
            *z *= 2.0; // an outlier for the pruning
        }
    }
    i.insert("depth", Value::Depth(Arc::new(noisy)));
    for p in [
        NLMeansDepthParams::default(),
        NLMeansDepthParams {
            prune: false,
            ..Default::default()
        },
    ] {
        let (cpu, dev) = both("NLMeansDepth", &i, &p.to_values());
        let (a, b) = (depth_of(&cpu, "depth"), depth_of(&dev, "depth"));
        let r = depth_within(&a, &b, REL_TOL).unwrap_or_else(|e| panic!("prune {}: {e}", p.prune));
        let dc = conf_diff(&conf_of(&cpu), &conf_of(&dev));
        assert!(dc <= REL_TOL, "confidence differs by {dc}");
        eprintln!(
            "denoise prune {}: max |dz|/z {:.2e}, |dc| {dc:.2e}",
            p.prune, r.max_rel
        );
        // and the check sees a filtered pixel moved by 3x the bound
        let t = a.as_slice().iter().position(|z| *z > 0.0).unwrap();
        let mut off = (*b).clone();
        off.as_mut_slice()[t] *= 1.0 + 3.0 * REL_TOL as f32;
        assert!(depth_within(&a, &off, REL_TOL).is_err());
    }
}

/// Values f32 on the device cannot hold as the CPU does (a subnormal
/// confidence) send the node to the CPU: the CPU's result, and the origin
/// says why.
#[test]
fn subnormal_confidences_run_on_the_cpu() {
    let mut i = scene(30, 20, 9);
    let Some(Value::Depth(d)) = i.get("depth").cloned() else {
        panic!()
    };
    let conf = Confidence::from_fn(30, 20, |x, y| if (x + y) % 7 == 0 { 1e-40 } else { 0.9 });
    i.insert("confidence", Value::Confidence(Arc::new(conf)));
    i.insert("depth", Value::Depth(d));
    let (cpu_reg, dev_reg) = registries();
    let p = NLMeansInpaintParams::default().to_values();
    let a = eval_on(&cpu_reg, "NLMeansInpaint", &i, &p).unwrap();
    let b = eval_on(&dev_reg, "NLMeansInpaint", &i, &p).unwrap();
    assert_eq!(*depth_of(&a, "depth"), *depth_of(&b, "depth"));
    let origin = b.origin.unwrap();
    assert_eq!(origin.backend, "cpu");
    assert!(origin.note.unwrap().contains("f32 range"));
}

/// Low-resolution depth (every `factor`-th pixel of the scene's, holes
/// kept) with its intrinsics, and the scene's colour as the guide.
fn upsample_inputs(w: usize, h: usize, factor: usize, seed: u64) -> Inputs {
    let full = scene(w, h, seed);
    let (Some(Value::Depth(d)), Some(Value::Color(c))) = (full.get("depth"), full.get("color"))
    else {
        panic!("scene without depth or colour")
    };
    let (lw, lh) = (w / factor, h / factor);
    let low = DepthMap::from_fn(lw, lh, |x, y| {
        *d.get(x * factor + factor / 2, y * factor + factor / 2)
    });
    let f = 1.2 * lw as f64;
    let k = Intrinsics {
        fx: f,
        fy: f,
        cx: lw as f64 / 2.0,
        cy: lh as f64 / 2.0,
        width: lw,
        height: lh,
    };
    let mut i = Inputs::new();
    i.insert("depth", Value::Depth(Arc::new(low)));
    i.insert("intrinsics", Value::Intrinsics(k));
    i.insert("color", Value::Color(c.clone()));
    i
}

#[test]
fn upsampling_agrees_with_the_cpu_within_its_stated_bound() {
    for (seed, factor, p) in [
        (11, 4, NLMeansUpsampleParams::default()),
        (
            12,
            2,
            NLMeansUpsampleParams {
                alpha: 0.0,
                prune: false,
                ..Default::default()
            },
        ),
        (
            13,
            4,
            NLMeansUpsampleParams {
                alpha: 1.0,
                iterations: 0,
                ..Default::default()
            },
        ),
        (
            14,
            3,
            NLMeansUpsampleParams {
                alpha: 0.3,
                low_patch_radius: 2,
                patch_radius: 1,
                ..Default::default()
            },
        ),
        // eq. 4 as published: no spatial falloff, the uniform 11x11 window
        (
            15,
            4,
            NLMeansUpsampleParams {
                spatial_sigma: 0.0,
                ..Default::default()
            },
        ),
        // a falloff too narrow to compute: capped alike on both backends
        (
            17,
            4,
            NLMeansUpsampleParams {
                spatial_sigma: 1e-30,
                ..Default::default()
            },
        ),
    ] {
        let i = upsample_inputs(60, 48, factor, seed);
        let (cpu, dev) = both("NLMeansUpsample", &i, &p.to_values());
        check_upsample(seed, factor, &p, &cpu, &dev);
    }
    // x8 runs in two steps of sqrt(8): the device drops its guide between them
    let p = NLMeansUpsampleParams::default();
    let i = upsample_inputs(96, 72, 8, 16);
    let (cpu, dev) = both("NLMeansUpsample", &i, &p.to_values());
    check_upsample(16, 8, &p, &cpu, &dev);
}

fn check_upsample(
    seed: u64,
    factor: usize,
    p: &NLMeansUpsampleParams,
    cpu: &Outputs,
    dev: &Outputs,
) {
    assert_eq!(
        dev.origin.as_ref().map(|o| o.backend.as_str()),
        Some("wgpu")
    );
    let (a, b) = (depth_of(cpu, "depth"), depth_of(dev, "depth"));
    let r = depth_within(&a, &b, REL_TOL).unwrap_or_else(|e| panic!("{p:?}: {e}"));
    let dc = conf_diff(&conf_of(cpu), &conf_of(dev));
    assert!(dc <= REL_TOL, "{p:?}: confidence differs by {dc}");
    assert!(a.hole_count() < a.len(), "nothing upsampled");
    eprintln!(
        "upsample seed {seed} x{factor}: max |dz|/z {:.2e}, max |dc| {dc:.2e}",
        r.max_rel
    );
}

#[test]
fn the_upsampling_check_fails_on_a_perturbed_result() {
    let i = upsample_inputs(48, 36, 4, 15);
    let p = NLMeansUpsampleParams::default();
    let (cpu, dev) = both("NLMeansUpsample", &i, &p.to_values());
    let (a, b) = (depth_of(&cpu, "depth"), depth_of(&dev, "depth"));
    assert!(depth_within(&a, &b, REL_TOL).is_ok());
    let t = a.as_slice().iter().position(|z| *z > 0.0).unwrap();
    let mut off = (*b).clone();
    off.as_mut_slice()[t] *= 1.0 + 3.0 * REL_TOL as f32;
    assert!(depth_within(&a, &off, REL_TOL).is_err());
    let mut hole = (*b).clone();
    hole.as_mut_slice()[t] = 0.0;
    assert!(depth_within(&a, &hole, REL_TOL).is_err());
}
