//! Relighting time and accuracy: `cargo bench --bench relight` regenerates
//! `docs/relight.md`.
//!
//! The scene is `graphs/copy_paste_relit.ron` at 640x480 (the sphere pasted
//! behind the red box of the tabletop, lit by the target's sun through the
//! environment map). The graph runs once for the inputs of `Relight`; the
//! bench then calls [`relight`] directly with the VPLs sampled from the
//! graph's environment map.
//!
//! - Time: 256 VPLs x 8000 ISM points (the paper's setting), median of
//!   `DEPTHGRAPH_REPEATS` (default 3) runs, on the threads rayon has.
//! - Error: against a reference run with 1024 VPLs x 32000 points
//!   (`DEPTHGRAPH_RELIGHT_REF_VPLS`, `DEPTHGRAPH_RELIGHT_REF_POINTS`), RMSE of
//!   the linear RGB composite over two pixel sets of the reference: the
//!   **changed** region (the composite differs from the photo by more than
//!   1e-4 in some channel: the object, its shadow and its bounce) and the
//!   **shadow** (target pixels, alpha 0, that the object darkens by more than
//!   1e-4 in luminance). The reference itself is an ISM estimate, not ray-cast
//!   visibility: the errors of its own maps are not measured.

mod common;
use common::{env_usize, median};

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use depthgraph::graph::pipeline::OutputRef;
use depthgraph::graph::prelude::*;
use depthgraph::nodes::relight::{RelightInputs, RelightParams, Relit, relight};
use depthgraph::nodes::relight_scene::{RelightScene, relight_moved};
use depthgraph::nodes::vpl::{Vpl, VplParams, luminance, sample_vpls};

/// The graph's values at 640x480.
struct Scene {
    photo: ColorImage,
    depth: DepthMap,
    normals: NormalMap,
    albedo: ColorImage,
    pasted_color: ColorImage,
    pasted_depth: DepthMap,
    alpha: Mask,
    k: Intrinsics,
    env: ColorImage,
}

fn load_scene(root: &Path, extra: &[&str]) -> Scene {
    let reg = depthgraph::nodes::registry().expect("registry");
    let sets: Vec<String> = [
        "source.width=640",
        "source.height=480",
        "target.width=640",
        "target.height=480",
    ]
    .iter()
    .chain(extra)
    .map(|s| s.to_string())
    .collect();
    let (_, mut p) =
        depthgraph::load_pipeline(&root.join("graphs/copy_paste_relit.ron"), &sets, &reg)
            .expect("graph");
    p.outputs = ["target", "paste", "composite", "env"]
        .iter()
        .map(|n| OutputRef {
            node: p.index_of(n).expect("node"),
            port: None,
        })
        .collect();
    let engine = Engine::new(EngineOptions::default()).expect("engine");
    let r = engine.run(&p, &RunOptions::default()).expect("run");
    let o = &r.outputs;
    let color = |k: &str| match o.get(k) {
        Some(Value::Color(c)) => (**c).clone(),
        other => panic!("{k}: {other:?}"),
    };
    let depth = |k: &str| match o.get(k) {
        Some(Value::Depth(c)) | Some(Value::Mask(c)) => (**c).clone(),
        other => panic!("{k}: {other:?}"),
    };
    Scene {
        photo: color("target.color"),
        depth: depth("target.depth"),
        normals: match o.get("target.normals") {
            Some(Value::Normals(n)) => (**n).clone(),
            other => panic!("normals: {other:?}"),
        },
        albedo: color("target.albedo"),
        pasted_color: color("paste.color"),
        pasted_depth: depth("paste.depth"),
        alpha: depth("composite.alpha"),
        k: match o.get("target.intrinsics") {
            Some(Value::Intrinsics(k)) => *k,
            other => panic!("intrinsics: {other:?}"),
        },
        env: color("env.map"),
    }
}

fn inputs(s: &Scene) -> RelightInputs<'_> {
    RelightInputs {
        photo: &s.photo,
        depth: &s.depth,
        normals: Some(&s.normals),
        albedo: Some(&s.albedo),
        pasted_color: &s.pasted_color,
        pasted_depth: &s.pasted_depth,
        alpha: &s.alpha,
        k: &s.k,
    }
}

/// One run, timed: the paired scheme, or the scene-cached one with its
/// scene built in the run.
fn run(s: &Scene, vpls: &[Vpl], p: &RelightParams) -> (Relit, f64) {
    let inp = inputs(s);
    let t = Instant::now();
    let r = if p.visibility == "paired" {
        relight(&inp, vpls, p)
    } else {
        RelightScene::new(&inp.scene(), vpls, p).and_then(|sc| relight_moved(&sc, &inp, p))
    };
    let r = r.expect("relight").expect("something to relight");
    (r, t.elapsed().as_secs_f64() * 1e3)
}

fn params(points: usize, importance: &str, visibility: &str) -> RelightParams {
    RelightParams {
        ism_points: points,
        importance: importance.to_string(),
        visibility: visibility.to_string(),
        ..Default::default()
    }
}

/// RMSE (linear RGB, f64 sums) over the pixels of `set`; 0 for an empty set.
fn rmse(a: &Relit, b: &Relit, set: &[usize]) -> f64 {
    let mut sum = 0.0f64;
    for &i in set {
        let (x, y) = (a.color.as_slice()[i], b.color.as_slice()[i]);
        for c in 0..3 {
            let d = x[c] as f64 - y[c] as f64;
            sum += d * d;
        }
    }
    // guard: empty set
    (sum / (3 * set.len()).max(1) as f64).sqrt()
}

fn main() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let repeats = env_usize("DEPTHGRAPH_REPEATS", 3);
    let ref_vpls = env_usize("DEPTHGRAPH_RELIGHT_REF_VPLS", 1024);
    let ref_points = env_usize("DEPTHGRAPH_RELIGHT_REF_POINTS", 32000);
    let threads = rayon::current_num_threads();
    let scene = load_scene(&root, &[]);
    // the same scene with the object moved 15 cm to the right
    let moved = load_scene(&root, &["paste.translation_m=(0.15, 0.0, 0.0)"]);
    assert!(moved.photo == scene.photo && moved.depth == scene.depth);
    assert!(
        moved.pasted_depth != scene.pasted_depth,
        "the object did not move"
    );
    let vpls = |n: usize| {
        sample_vpls(
            &scene.env,
            &VplParams {
                count: n,
                ..Default::default()
            },
        )
    };

    if let Ok(n) = std::env::var("PROFILE_MOVES") {
        let n: usize = n.parse().unwrap();
        let v256 = vpls(256);
        let cached = params(8000, "near_object", "scene_cached");
        let sc = RelightScene::new(&inputs(&scene).scene(), &v256, &cached).expect("scene");
        let t = Instant::now();
        for j in 0..n {
            let inp = inputs(if j % 2 == 0 { &moved } else { &scene });
            let _ = relight_moved(&sc, &inp, &cached);
        }
        eprintln!(
            "{:.1} ms per move",
            t.elapsed().as_secs_f64() * 1e3 / n as f64
        );
        return;
    }
    // ---- time at the paper's setting
    let v256 = vpls(256);
    let mut times = Vec::new();
    for _ in 0..repeats.max(1) {
        times.push(run(&scene, &v256, &params(8000, "near_object", "paired")).1);
    }
    let t_paper = median(times.clone());
    eprintln!("paired 256 x 8000: {t_paper:.0} ms ({times:?})");
    let cached = params(8000, "near_object", "scene_cached");
    let mut first = Vec::new();
    for _ in 0..repeats.max(1) {
        first.push(run(&scene, &v256, &cached).1);
    }
    let t_first = median(first.clone());
    eprintln!("scene_cached 256 x 8000, scene built: {t_first:.0} ms ({first:?})");
    // the scene once, then the object moved back and forth
    let t = Instant::now();
    let sc = RelightScene::new(&inputs(&scene).scene(), &v256, &cached).expect("scene");
    let t_scene = t.elapsed().as_secs_f64() * 1e3;
    let mut moves = Vec::new();
    for j in 0..(2 * repeats.max(1) + 1) {
        let inp = inputs(if j % 2 == 0 { &moved } else { &scene });
        let t = Instant::now();
        let r = relight_moved(&sc, &inp, &cached)
            .expect("relight")
            .expect("pasted");
        moves.push(t.elapsed().as_secs_f64() * 1e3);
        // the cached scene gives what a fresh one gives
        if j < 2 {
            let fresh = run(if j % 2 == 0 { &moved } else { &scene }, &v256, &cached).0;
            assert!(fresh == r, "a cached scene changed the result");
        }
    }
    let t_move = median(moves.clone());
    eprintln!("scene alone {t_scene:.0} ms; object moved: {t_move:.1} ms ({moves:?})");

    // ---- reference
    let (reference, t_ref) = run(
        &scene,
        &vpls(ref_vpls),
        &params(ref_points, "near_object", "paired"),
    );
    eprintln!("reference {ref_vpls} x {ref_points}: {t_ref:.0} ms");
    let photo = scene.photo.as_slice();
    let alpha = scene.alpha.as_slice();
    let changed: Vec<usize> = (0..photo.len())
        .filter(|&i| {
            let (a, b) = (reference.color.as_slice()[i], photo[i]);
            (0..3).any(|c| (a[c] - b[c]).abs() > 1e-4)
        })
        .collect();
    let shadow: Vec<usize> = (0..photo.len())
        .filter(|&i| {
            alpha[i] <= 0.0 && luminance(reference.color.as_slice()[i]) < luminance(photo[i]) - 1e-4
        })
        .collect();

    let mut rows: Vec<(String, f64, f64, f64)> = Vec::new();
    let mut row = |label: String, n: usize, points: usize, imp: &str, vis: &str| {
        let (r, t) = run(&scene, &vpls(n), &params(points, imp, vis));
        let (ec, es) = (
            rmse(&r, &reference, &changed),
            rmse(&r, &reference, &shadow),
        );
        eprintln!("{label}: {t:.0} ms, rmse {ec:.5} / {es:.5}");
        rows.push((label, t, ec, es));
    };
    for vis in ["paired", "scene_cached"] {
        for n in [16, 64, 256, 1024] {
            row(
                format!("{vis}: {n} VPLs x 8000 points"),
                n,
                8000,
                "near_object",
                vis,
            );
        }
        for m in [1000, 4000, 32000] {
            row(
                format!("{vis}: 256 VPLs x {m} points"),
                256,
                m,
                "near_object",
                vis,
            );
        }
    }
    row(
        "paired: 256 x 8000, importance uniform".into(),
        256,
        8000,
        "uniform",
        "paired",
    );

    // ---- the doc
    let mut doc = String::new();
    let _ = writeln!(
        doc,
        "# Relighting: time and accuracy\n\n\
         Generated by `cargo bench --bench relight` (`benches/relight.rs`); do not edit.\n\n\
         Scene: `graphs/copy_paste_relit.ron` at 640x480 (the pasted sphere behind the red box, \
         the target's sun in the environment map), `Relight` called directly with its graph \
         inputs (given normals and albedo), default parameters unless stated. {threads} rayon \
         threads; times are wall-clock of `relight()` alone, on a shared machine.\n"
    );
    let _ = writeln!(
        doc,
        "## Time at the paper's setting\n\n\
         256 VPLs x 8000 ISM points, near-object importance: **{t_paper:.0} ms** \
         (median of {} runs: {}).\n",
        times.len(),
        times
            .iter()
            .map(|t| format!("{t:.0}"))
            .collect::<Vec<_>>()
            .join(", ")
    );
    let _ = writeln!(
        doc,
        "## Error against time\n\n\
         Reference: {ref_vpls} VPLs x {ref_points} points ({t_ref:.0} ms), itself an ISM \
         estimate. RMSE of the linear RGB composite over the reference's **changed** pixels \
         ({} px: differs from the photo by > 1e-4, the object, its shadow and bounce) and its \
         **shadow** ({} px: target pixels darkened by > 1e-4 in luminance).\n\n\
         | setting | time (ms) | RMSE changed | RMSE shadow |\n|---|---:|---:|---:|",
        changed.len(),
        shadow.len()
    );
    for (label, t, ec, es) in &rows {
        let _ = writeln!(doc, "| {label} | {t:.0} | {ec:.5} | {es:.5} |");
    }
    let path = root.join("docs/relight.md");
    if let Err(e) = std::fs::write(&path, doc) {
        eprintln!("could not write {}: {e}", path.display());
    } else {
        eprintln!("wrote {}", path.display());
    }
}
