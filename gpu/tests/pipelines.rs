//! Whole pipelines on both backends: `refocus.ron`, `depth_fill.ron` and
//! `copy_paste_relit.ron` from `graphs/`. Every device node's outputs agree
//! with the CPU's within its module's tolerance, every node with no device
//! node upstream gives the same bits, and the trace names the wgpu backend
//! and the adapter for each device node.

mod common;

use std::collections::BTreeSet;
use std::path::PathBuf;

use common::*;
use depthgraph_gpu::parity::{depth_within, display_psnr};
use depthgraph_graph::pipeline::OutputRef;
use depthgraph_graph::prelude::*;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn run_all(file: &str, reg: &Registry) -> (Pipeline, RunResult) {
    let path = root().join("graphs").join(file);
    let text = std::fs::read_to_string(&path).unwrap();
    let doc = Document::parse(&text, file).unwrap();
    let mut p = Pipeline::check(&doc, reg).unwrap();
    p.outputs = (0..p.nodes.len())
        .filter(|&i| !p.nodes[i].node.schema().sink)
        .map(|node| OutputRef { node, port: None })
        .collect();
    let engine = Engine::new(EngineOptions::default()).unwrap();
    let out = std::env::temp_dir().join(format!("depthgraph-gpu-parity-{}", std::process::id()));
    let opts = RunOptions {
        out_dir: out,
        ..RunOptions::default()
    };
    let r = engine
        .run(&p, &opts)
        .unwrap_or_else(|e| panic!("{file}: {e}"));
    (p, r)
}

/// Largest |a - b| over two sample slices (infinite when one is NaN).
fn max_abs(a: &[f32], b: &[f32]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (*x as f64 - *y as f64).abs())
        .fold(
            0.0,
            |m: f64, d| if d.is_nan() { f64::INFINITY } else { m.max(d) },
        )
}

/// Pixels where two masks differ.
fn differing(x: &Mask, y: &Mask) -> usize {
    x.as_slice()
        .iter()
        .zip(y.as_slice())
        .filter(|(a, b)| a != b)
        .count()
}

/// Nodes with a device node at or above them.
fn downstream_of_device(p: &Pipeline) -> BTreeSet<usize> {
    let mut set = BTreeSet::new();
    // nodes are in file order; iterate to a fixed point
    loop {
        let before = set.len();
        for (i, n) in p.nodes.iter().enumerate() {
            let dev = n.node.backend() == "wgpu";
            if dev || n.inputs.values().any(|s| set.contains(&s.node)) {
                set.insert(i);
            }
        }
        if set.len() == before {
            return set;
        }
    }
}

fn check(file: &str, expect_device: &[&str]) {
    std::env::set_current_dir(root()).unwrap();
    let (cpu_reg, dev_reg) = registries();
    let (_, a) = run_all(file, &cpu_reg);
    let (p, b) = run_all(file, &dev_reg);
    let touched = downstream_of_device(&p);
    let mut device_nodes = Vec::new();
    for (i, n) in p.nodes.iter().enumerate() {
        if n.node.schema().sink {
            continue;
        }
        let rec = b.trace.get(&n.name).unwrap();
        let on_device = n.node.backend() == "wgpu";
        if on_device {
            assert_eq!(rec.backend, "wgpu", "{file} {}", n.name);
            assert!(rec.adapter.as_deref().is_some_and(|s| !s.is_empty()));
            device_nodes.push(n.kind.as_str());
        }
        for (key, va) in a
            .outputs
            .iter()
            .filter(|(k, _)| k.starts_with(&format!("{}.", n.name)))
        {
            let vb = &b.outputs[key];
            match (va, vb, on_device) {
                (Value::Color(x), Value::Color(y), true) if n.kind == "OcclusionComposite" => {
                    let get = |r: &RunResult, port: &str| {
                        r.outputs[&format!("{}.{port}", n.name)].clone()
                    };
                    let (za, zb, aa, ab) = match (
                        get(&a, "depth"),
                        get(&b, "depth"),
                        get(&a, "alpha"),
                        get(&b, "alpha"),
                    ) {
                        (Value::Depth(za), Value::Depth(zb), Value::Mask(aa), Value::Mask(ab)) => {
                            (za, zb, aa, ab)
                        }
                        _ => panic!("{file} {key}: composite outputs"),
                    };
                    // inputs from device nodes upstream differ a little: the
                    // picture, not the bits, is compared then
                    if n.inputs.values().any(|s| touched.contains(&s.node)) {
                        let psnr = display_psnr(x, y).unwrap();
                        eprintln!("{file} {key}: display PSNR {psnr:.1} dB");
                        assert!(psnr >= depthgraph_gpu::refocus::MIN_PSNR_DB);
                    } else {
                        depthgraph_gpu::parity::composite_within(
                            (x, &za, &aa),
                            (y, &zb, &ab),
                            depthgraph_gpu::composite::REL_TOL,
                        )
                        .unwrap_or_else(|e| panic!("{file} {key}: {e}"));
                    }
                }
                (_, _, true) if n.kind == "OcclusionComposite" => {} // with the color
                (Value::Depth(x), Value::Depth(y), true) => {
                    let tol = match n.kind.as_str() {
                        "JointBilateral" => depthgraph_gpu::bilateral::REL_TOL,
                        "PullPush" => depthgraph_gpu::pull_push::REL_TOL,
                        "DualPullPush" => depthgraph_gpu::pull_push::DUAL_REL_TOL,
                        "NLMeansInpaint" | "NLMeansDepth" | "NLMeansUpsample" => {
                            depthgraph_gpu::nlmeans::REL_TOL
                        }
                        other => panic!("{file} {key}: no depth check for {other}"),
                    };
                    // a device node upstream adds its bound to the input's
                    // (DualPullPush's is the largest)
                    let upstream = n.inputs.values().any(|s| touched.contains(&s.node));
                    let tol = if upstream {
                        tol + depthgraph_gpu::pull_push::DUAL_REL_TOL
                    } else {
                        tol
                    };
                    let r = depth_within(x, y, tol).unwrap_or_else(|e| panic!("{file} {key}: {e}"));
                    eprintln!("{file} {key}: max |dz|/z {:.2e}", r.max_rel);
                }
                (Value::Mask(x), Value::Mask(y), true) if n.kind.contains("PullPush") => {
                    assert_eq!(x, y, "{file} {key}: filled masks differ");
                }
                (Value::Mask(x), Value::Mask(y), true) if n.kind == "Feather" => {
                    let worst = max_abs(x.as_slice(), y.as_slice());
                    eprintln!("{file} {key}: max |d| {worst:.2e}");
                    assert!(
                        worst <= depthgraph_gpu::feather::ABS_TOL,
                        "{file} {key}: {worst}"
                    );
                }
                (Value::Mask(x), Value::Mask(y), true) if n.kind == "Relight" => {
                    let differ = differing(x, y);
                    eprintln!("{file} {key}: {differ} region pixels differ");
                    // the region follows the alpha, which the device
                    // composite decides bit for bit
                    assert!(differ * 1000 <= x.len(), "{file} {key}: {differ}");
                }
                // Relight (color, difference): its inputs come from device
                // nodes upstream in every pipeline here: the picture agrees
                (Value::Color(x), Value::Color(y), true)
                    if n.kind == "Refocus" || n.kind == "Relight" =>
                {
                    let psnr = display_psnr(x, y).unwrap();
                    eprintln!("{file} {key}: display PSNR {psnr:.1} dB");
                    assert!(
                        psnr >= depthgraph_gpu::refocus::MIN_PSNR_DB,
                        "{file} {key}: {psnr} dB"
                    );
                }
                (Value::Confidence(x), Value::Confidence(y), true) if n.kind == "EdgeDetect" => {
                    let (ea, eb) = match (
                        &a.outputs[&format!("{}.edges", n.name)],
                        &b.outputs[&format!("{}.edges", n.name)],
                    ) {
                        (Value::Mask(ea), Value::Mask(eb)) => (ea.clone(), eb.clone()),
                        _ => panic!("{file} {key}: no edges"),
                    };
                    let ep =
                        <depthgraph_nodes::select::edges::EdgeParams as NodeParams>::from_values(
                            &n.params,
                        )
                        .unwrap_or_else(|e| panic!("{file} {key}: parameters: {e}"));
                    let (worst, amb) = depthgraph_gpu::parity::edges_within(
                        (x, &ea),
                        (y, &eb),
                        ep.threshold,
                        depthgraph_gpu::edges::strength_tol(&ep),
                    )
                    .unwrap_or_else(|e| panic!("{file} {key}: {e}"));
                    eprintln!(
                        "{file} {key}: max |ds| {worst:.2e}, {amb} ambiguous edge bits differ"
                    );
                }
                (Value::Mask(_), Value::Mask(_), true) if n.kind == "EdgeDetect" => {} // with the strength
                (Value::Confidence(x), Value::Confidence(y), true)
                    if n.kind.starts_with("NLMeans") =>
                {
                    let worst = max_abs(x.as_slice(), y.as_slice());
                    eprintln!("{file} {key}: max |dc| {worst:.2e}");
                    let upstream = n.inputs.values().any(|s| touched.contains(&s.node));
                    let tol = depthgraph_gpu::nlmeans::REL_TOL * if upstream { 100.0 } else { 1.0 };
                    assert!(worst <= tol, "{file} {key}: {worst}");
                }
                // decided on the CPU by both backends: the very same value
                (Value::Intrinsics(x), Value::Intrinsics(y), true) => {
                    assert_eq!(x, y, "{file} {key}: intrinsics differ");
                }
                (_, _, true) => panic!("{file} {key}: no check for {} output", n.kind),
                _ if !touched.contains(&i) => {
                    let (sa, sb) = (va.samples(), vb.samples());
                    if let (Some(sa), Some(sb)) = (sa, sb) {
                        let same = sa
                            .samples
                            .iter()
                            .zip(sb.samples)
                            .all(|(x, y)| x.to_bits() == y.to_bits());
                        assert!(same, "{file} {key}: differs without a device node upstream");
                    }
                }
                (Value::Depth(x), Value::Depth(y), false) if touched.contains(&i) => {
                    // downstream of a device node: the same holes, depths close
                    let r = depth_within(x, y, 1e-3)
                        .unwrap_or_else(|e| panic!("{file} {key} (downstream): {e}"));
                    eprintln!("{file} {key} (downstream): max |dz|/z {:.2e}", r.max_rel);
                }
                (Value::Mask(x), Value::Mask(y), false) if touched.contains(&i) => {
                    let differ = differing(x, y);
                    eprintln!("{file} {key} (downstream): {differ} mask pixels differ");
                }
                (Value::Color(x), Value::Color(y), false) => {
                    // downstream of a device node: the picture still agrees
                    let psnr = display_psnr(x, y).unwrap();
                    eprintln!("{file} {key} (downstream): display PSNR {psnr:.1} dB");
                    assert!(
                        psnr >= depthgraph_gpu::refocus::MIN_PSNR_DB,
                        "{file} {key}: {psnr} dB"
                    );
                }
                _ => {}
            }
        }
    }
    device_nodes.sort_unstable();
    let mut want = expect_device.to_vec();
    want.sort_unstable();
    assert_eq!(device_nodes, want, "{file}: device nodes");
}

#[test]
fn refocus_pipeline_agrees() {
    check(
        "refocus.ron",
        &["NLMeansInpaint", "NLMeansUpsample", "Refocus"],
    );
}

#[test]
fn depth_fill_pipeline_agrees() {
    check(
        "depth_fill.ron",
        &[
            "PullPush",
            "DualPullPush",
            "NLMeansInpaint",
            "JointBilateral",
        ],
    );
}

#[test]
fn copy_paste_relit_pipeline_agrees() {
    check(
        "copy_paste_relit.ron",
        &["EdgeDetect", "Feather", "OcclusionComposite", "Relight"],
    );
}

/// Two device nodes in a row: the second reads the first's output and the
/// shared guide image from the device (no upload), and the result equals
/// the one computed from fresh uploads.
#[test]
fn a_device_chain_uploads_each_value_once() {
    let text = r#"(
        version: 1,
        nodes: {
            "scene": (kind: "SyntheticScene", params: (preset: "tabletop", width: 96, height: 72)),
            "kinect": (kind: "SimulateKinect", params: (seed: 3),
                inputs: (depth: "scene.depth", color: "scene.color", intrinsics: "scene.intrinsics")),
            "fill": (kind: "PullPush", inputs: (depth: "kinect.depth")),
            "a": (kind: "JointBilateral", params: (radius: 3), inputs: (depth: "fill.depth", color: "scene.color")),
            "b": (kind: "JointBilateral", params: (radius: 2), inputs: (depth: "a.depth", color: "scene.color")),
        },
        outputs: ["a", "b", "scene"],
    )"#;
    let (cpu_reg, dev_reg) = registries();
    let doc = Document::parse(text, "chain").unwrap();
    let run = |reg: &Registry| {
        let p = Pipeline::check(&doc, reg).unwrap();
        Engine::new(EngineOptions::default())
            .unwrap()
            .run(&p, &RunOptions::default())
            .unwrap()
    };
    let (a, b) = (run(&cpu_reg), run(&dev_reg));
    let first = b.trace.get("a").unwrap().transfers;
    let second = b.trace.get("b").unwrap().transfers;
    // a: its depth comes from the PullPush on the device, its color is uploaded
    assert_eq!((first.uploads, first.resident_hits), (1, 1), "{first:?}");
    assert_eq!(second.uploads, 0, "{second:?}");
    assert_eq!(second.resident_hits, 2, "{second:?}");
    for key in ["a.depth", "b.depth"] {
        let (Value::Depth(x), Value::Depth(y)) = (&a.outputs[key], &b.outputs[key]) else {
            panic!("{key}");
        };
        // b's input differs by a's rounding: twice the single-node bound
        depth_within(x, y, 2.0 * depthgraph_gpu::bilateral::REL_TOL)
            .unwrap_or_else(|e| panic!("{key}: {e}"));
    }
    // b again from fresh copies of its inputs (new values: uploaded, not
    // found on the device) gives the same bits as through the hand-over
    let copy = |v: &Value| match v {
        Value::Depth(d) => Value::Depth(std::sync::Arc::new((**d).clone())),
        Value::Color(c) => Value::Color(std::sync::Arc::new((**c).clone())),
        _ => panic!("not an image"),
    };
    let mut i = Inputs::new();
    i.insert("depth", copy(&b.outputs["a.depth"]));
    i.insert("color", copy(&b.outputs["scene.color"]));
    let p = depthgraph_nodes::depth::bilateral::BilateralParams {
        radius: 2,
        ..Default::default()
    };
    let fresh = eval_on(&dev_reg, "JointBilateral", &i, &p.to_values()).unwrap();
    assert_eq!(fresh.transfers.uploads, 2);
    let (Value::Depth(x), Value::Depth(y)) = (&fresh.values["depth"], &b.outputs["b.depth"]) else {
        panic!("depth");
    };
    assert!(
        x.as_slice()
            .iter()
            .zip(y.as_slice())
            .all(|(p, q)| p.to_bits() == q.to_bits())
    );
}
