//! Relighting time and accuracy: `cargo bench --bench relight` regenerates
//! `docs/relight.md`.
//!
//! The scene is `graphs/copy_paste_relit.ron` at 640x480 (the sphere pasted
//! behind the red box of the tabletop, lit by the target's sun through the
//! environment map). The graph runs once for the inputs of `Relight` (and
//! once more with the object moved 15 cm); the bench then calls the
//! relighting functions directly with VPLs sampled from the graph's
//! environment map.
//!
//! - Time: 256 VPLs x 8000 ISM points (the paper's setting), median of
//!   `DEPTHGRAPH_REPEATS` (default 3) runs, on the threads rayon has: the
//!   paired scheme, the scene-cached one from scratch, and the
//!   scene-cached one when only the object moves (scene kept).
//! - Error: against the ray-cast reference ([`relight_reference`]: exact
//!   visibility against the meshes) with `DEPTHGRAPH_RELIGHT_REF_VPLS`
//!   (default 4096) VPLs, on every `DEPTHGRAPH_RELIGHT_REF_STRIDE`-th pixel
//!   (default 3) in x and y. RMSE of the linear RGB composite over two sets
//!   of those pixels: the **changed** ones (the reference differs from the
//!   photo by more than 1e-4 in some channel: the object, its shadow and
//!   its bounce) and the **shadow** (target pixels, alpha 0, that the
//!   object darkens by more than 1e-4 in luminance).
//! - `DEPTHGRAPH_RELIGHT_MOVES=N`: only time N object moves and exit (for
//!   a profiler).

mod common;
use common::{env_usize, median};

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use depthgraph::graph::pipeline::OutputRef;
use depthgraph::graph::prelude::*;
use depthgraph::nodes::kit::color::luminance_clamped;
use depthgraph::nodes::relight::paired::relight;
use depthgraph::nodes::relight::reference::relight_reference;
use depthgraph::nodes::relight::scene_cached::{RelightScene, relight_moved};
use depthgraph::nodes::relight::shading::{
    Importance, RelightInputs, RelightParams, Relit, Visibility,
};
use depthgraph::nodes::relight::vpl::{Vpl, VplParams, sample_vpls};

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
    // The graph is drawn at 320x240: its lasso clicks and paste pixel are
    // doubled for 640x480 (else the lasso would cut a piece of the wall).
    let sets: Vec<String> = [
        "source.width=640",
        "source.height=480",
        "target.width=640",
        "target.height=480",
        "lasso.clicks=[(509.0, 352.4), (474.6, 384.4), (434.2, 410.2), (394.2, 384.0), \
         (359.8, 353.8), (370.6, 309.6), (385.6, 265.2), (432.0, 253.4), (473.0, 272.2), \
         (510.2, 302.6)]",
        "paste.target_pixel=[(121.0, 301.0)]",
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
        Some(Value::Depth(c)) => (**c).clone(),
        other => panic!("{k}: {other:?}"),
    };
    let mask = |k: &str| match o.get(k) {
        Some(Value::Mask(c)) => (**c).clone(),
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
        alpha: mask("composite.alpha"),
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
        capture_vpls: None,
    }
}

/// One run, timed: the paired scheme, or the scene-cached one with its
/// scene built in the run.
fn run(s: &Scene, vpls: &[Vpl], p: &RelightParams) -> (Relit, f64) {
    let inp = inputs(s);
    let t = Instant::now();
    let r = if p.visibility == Visibility::Paired {
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
        importance: Importance::from_name(importance).expect("an importance name"),
        visibility: Visibility::from_name(visibility).expect("a visibility name"),
        ..Default::default()
    }
}

/// The ray-cast reference's composite at the pixels `grid`, and its time (ms).
fn reference_on(
    s: &Scene,
    vpls: &[Vpl],
    p: &RelightParams,
    grid: &[usize],
) -> (Vec<[f32; 3]>, f64) {
    let t = Instant::now();
    let r = relight_reference(&inputs(s), vpls, p, grid)
        .expect("reference")
        .expect("something to relight")
        .into_iter()
        .map(|(c, _)| c)
        .collect();
    (r, t.elapsed().as_secs_f64() * 1e3)
}

/// Positions in `grid` where the reference differs from the photo by more
/// than 1e-4 in some channel.
fn changed_px(reference: &[[f32; 3]], photo: &[[f32; 3]], grid: &[usize]) -> Vec<usize> {
    (0..grid.len())
        .filter(|&g| {
            let (a, b) = (reference[g], photo[grid[g]]);
            (0..3).any(|c| (a[c] - b[c]).abs() > 1e-4)
        })
        .collect()
}

/// RMSE (linear RGB, f64 sums) of `x(g)` against `reference[g]` over the
/// positions `set`; 0 for an empty set.
fn rmse_on(set: &[usize], x: &dyn Fn(usize) -> [f32; 3], reference: &[[f32; 3]]) -> f64 {
    let mut sum = 0.0f64;
    for &g in set {
        let (a, b) = (x(g), reference[g]);
        for c in 0..3 {
            let d = a[c] as f64 - b[c] as f64;
            sum += d * d;
        }
    }
    // guard: empty set
    (sum / (3 * set.len()).max(1) as f64).sqrt()
}

fn main() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let repeats = env_usize("DEPTHGRAPH_REPEATS", 3).max(1);
    let ref_vpls = env_usize("DEPTHGRAPH_RELIGHT_REF_VPLS", 4096);
    let stride = env_usize("DEPTHGRAPH_RELIGHT_REF_STRIDE", 3).max(1);
    let threads = rayon::current_num_threads();
    let scene = load_scene(&root, &[]);
    // the same scene with the object moved 15 cm to the left
    let moved = load_scene(&root, &["paste.translation_m=(-0.15, 0.0, 0.0)"]);
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
    let v256 = vpls(256);
    let cached = params(8000, "near_object", "scene_cached");
    let time_moves = |sc: &RelightScene, n: usize, p: &RelightParams| -> Vec<f64> {
        (0..n)
            .map(|j| {
                let inp = inputs(if j % 2 == 0 { &moved } else { &scene });
                let t = Instant::now();
                let r = relight_moved(sc, &inp, p).expect("relight");
                assert!(r.is_some(), "nothing pasted");
                t.elapsed().as_secs_f64() * 1e3
            })
            .collect()
    };
    if env_usize("DEPTHGRAPH_RELIGHT_MOVES", 0) > 0 {
        let n = env_usize("DEPTHGRAPH_RELIGHT_MOVES", 0);
        let sc = RelightScene::new(&inputs(&scene).scene(), &v256, &cached).expect("scene");
        let t = time_moves(&sc, n, &cached);
        eprintln!("object moved: median {:.1} ms over {n}", median(t));
        return;
    }

    // ---- time at the paper's setting
    let time = |vis: &str| {
        let t: Vec<f64> = (0..repeats)
            .map(|_| run(&scene, &v256, &params(8000, "near_object", vis)).1)
            .collect();
        (median(t.clone()), t)
    };
    let (t_paired, paired_times) = time("paired");
    eprintln!("paired 256 x 8000: {t_paired:.0} ms ({paired_times:?})");
    let (t_first, first_times) = time("scene_cached");
    eprintln!("scene_cached 256 x 8000 from scratch: {t_first:.0} ms ({first_times:?})");
    let t = Instant::now();
    let sc = RelightScene::new(&inputs(&scene).scene(), &v256, &cached).expect("scene");
    let t_scene = t.elapsed().as_secs_f64() * 1e3;
    // the cached scene gives what a fresh one gives, at both places
    for s in [&moved, &scene] {
        let r = relight_moved(&sc, &inputs(s), &cached).expect("relight");
        assert!(
            r == Some(run(s, &v256, &cached).0),
            "a cached scene changed the result"
        );
    }
    let moves = time_moves(&sc, 4 * repeats + 1, &cached);
    let t_move = median(moves.clone());
    let (m_lo, m_hi) = moves
        .iter()
        .fold((f64::INFINITY, 0.0f64), |(a, b), &t| (a.min(t), b.max(t)));
    eprintln!("scene alone {t_scene:.0} ms; object moved: {t_move:.1} ms ({moves:?})");

    // ---- the ray-cast reference on a grid of pixels
    let (w, h) = scene.photo.dims();
    let grid: Vec<usize> = (0..h)
        .step_by(stride)
        .flat_map(|y| (0..w).step_by(stride).map(move |x| y * w + x))
        .collect();
    let (reference, t_ref) = reference_on(&scene, &vpls(ref_vpls), &cached, &grid);
    eprintln!(
        "ray-cast reference, {ref_vpls} VPLs, {} px: {t_ref:.0} ms",
        grid.len()
    );
    let photo = scene.photo.as_slice();
    let alpha = scene.alpha.as_slice();
    let changed = changed_px(&reference, photo, &grid);
    let shadow: Vec<usize> = (0..grid.len())
        .filter(|&g| {
            let i = grid[g];
            alpha[i] <= 0.0 && luminance_clamped(reference[g]) < luminance_clamped(photo[i]) - 1e-4
        })
        .collect();
    let on_object: Vec<usize> = changed
        .iter()
        .copied()
        .filter(|&g| alpha[grid[g]] > 0.0)
        .collect();
    let rmse =
        |r: &Relit, set: &[usize]| rmse_on(set, &|g| r.color.as_slice()[grid[g]], &reference);

    let mut rows: Vec<(String, f64, f64, f64, f64)> = Vec::new();
    let mut row = |label: String, n: usize, p: RelightParams| {
        let (r, t) = run(&scene, &vpls(n), &p);
        let (ec, es, eo) = (rmse(&r, &changed), rmse(&r, &shadow), rmse(&r, &on_object));
        eprintln!("{label}: {t:.0} ms, rmse {ec:.5} / {es:.5} / object {eo:.5}");
        rows.push((label, t, ec, es, eo));
    };
    for vis in ["paired", "scene_cached"] {
        for n in [16, 64, 256, 1024] {
            row(
                format!("{vis}: {n} VPLs x 8000 points"),
                n,
                params(8000, "near_object", vis),
            );
        }
        for m in [1000, 4000, 32000] {
            row(
                format!("{vis}: 256 VPLs x {m} points"),
                256,
                params(m, "near_object", vis),
            );
        }
        for res in [48, 192] {
            row(
                format!("{vis}: 256 x 8000, ISM resolution {res}"),
                256,
                RelightParams {
                    ism_resolution: res,
                    ..params(8000, "near_object", vis)
                },
            );
        }
    }
    row(
        "paired: 256 x 8000, importance uniform".into(),
        256,
        params(8000, "uniform", "paired"),
    );
    for res in [32, 128] {
        row(
            format!("scene_cached: 256 x 8000, object maps {res}²"),
            256,
            RelightParams {
                object_ism_resolution: res,
                ..cached.clone()
            },
        );
    }
    for step in [1, 4] {
        row(
            format!("scene_cached: 256 x 8000, lattice_step {step}"),
            256,
            RelightParams {
                lattice_step: step,
                ..cached.clone()
            },
        );
    }

    // ---- bounce shadows (paraboloid ISMs), against rays that shadow the
    // bounce too
    let shadowed = RelightParams {
        bounce_shadows: true,
        ..cached.clone()
    };
    let (reference_bs, t_ref_bs) = reference_on(&scene, &vpls(ref_vpls), &shadowed, &grid);
    let changed_bs = changed_px(&reference_bs, photo, &grid);
    let rmse_bs = |x: &dyn Fn(usize) -> [f32; 3]| rmse_on(&changed_bs, x, &reference_bs);
    // how much the bounce's shadows change the reference itself
    let ref_gap = rmse_bs(&|g| reference[g]);
    let mut bs_rows: Vec<(String, f64, f64)> = Vec::new();
    for (label, p) in [
        ("scene_cached, bounce unshadowed", cached.clone()),
        ("scene_cached, bounce shadows", shadowed.clone()),
        (
            "paired, bounce shadows",
            RelightParams {
                bounce_shadows: true,
                ..params(8000, "near_object", "paired")
            },
        ),
    ] {
        let (r, t) = run(&scene, &v256, &p);
        let e = rmse_bs(&|g| r.color.as_slice()[grid[g]]);
        eprintln!("{label}: {t:.0} ms, rmse {e:.5}");
        bs_rows.push((label.to_string(), t, e));
    }
    let sc_bs = RelightScene::new(&inputs(&scene).scene(), &v256, &shadowed).expect("scene");
    let t_move_bs = median(time_moves(&sc_bs, 4 * repeats + 1, &shadowed));
    eprintln!("object moved, bounce shadows: {t_move_bs:.1} ms");

    // ---- the doc
    let list = |t: &[f64]| {
        t.iter()
            .map(|t| format!("{t:.0}"))
            .collect::<Vec<_>>()
            .join(", ")
    };
    let mut doc = String::new();
    let _ = writeln!(
        doc,
        "# Relighting: time and accuracy\n\n\
         Generated by `cargo bench --bench relight` (`benches/relight.rs`); do not edit.\n\n\
         The errors here are against the ray-cast reference, which shares the shading model: they \
         measure the shadow maps' visibility. The model itself is measured against a path tracer \
         (influence region and object PSNR beside the naive paste) in \
         [relight-truth.md](relight-truth.md) (`cargo bench --bench relight_truth`).\n\n\
         Scene: `graphs/copy_paste_relit.ron` at 640x480 (the pasted sphere behind the red box, \
         the target's sun in the environment map), the relighting functions called directly with \
         the graph's inputs (given normals and albedo), default parameters unless stated. \
         {threads} rayon threads; times are wall-clock of the relighting alone, on a shared machine.\n"
    );
    let _ = writeln!(
        doc,
        "## Time at the paper's setting (256 VPLs x 8000 ISM points)\n\n\
         | visibility | what runs | median (ms) | runs (ms) |\n|---|---|---:|---|\n\
         | paired (eq. 6, maps rebuilt) | everything | **{t_paired:.0}** | {} |\n\
         | scene_cached | everything (scene built, then the object) | **{t_first:.0}** | {} |\n\
         | scene_cached | the scene alone (once per photo and VPLs) | {t_scene:.0} | |\n\
         | scene_cached | **the object moved**, scene kept | **{t_move:.1}** | {} runs, {m_lo:.1} to {m_hi:.1} |\n",
        list(&paired_times),
        list(&first_times),
        moves.len(),
    );
    let _ = writeln!(
        doc,
        "The object alternates between two places 15 cm apart (`paste.translation_m`); each \
         result equals, bit for bit, that of a scene built for it alone (asserted).\n"
    );
    let _ = writeln!(
        doc,
        "## Error against time\n\n\
         Reference: exact ray-cast visibility against the meshes of the target and the object, \
         {ref_vpls} VPLs, on every {stride}rd pixel in x and y ({} px, {t_ref:.0} ms). RMSE of the \
         linear RGB composite over the reference's **changed** pixels ({} px: differs from the \
         photo by > 1e-4, the object, its shadow and bounce) and its **shadow** ({} px: target \
         pixels darkened by > 1e-4 in luminance), and over the changed pixels on the **object** \
         ({} px).\n\n\
         | setting | time (ms) | RMSE changed | RMSE shadow | RMSE object |\n|---|---:|---:|---:|---:|",
        grid.len(),
        changed.len(),
        shadow.len(),
        on_object.len()
    );
    for (label, t, ec, es, eo) in &rows {
        let _ = writeln!(doc, "| {label} | {t:.0} | {ec:.5} | {es:.5} | {eo:.5} |");
    }
    let _ = writeln!(
        doc,
        "\n## Shadowed bounce (`bounce_shadows`, paraboloid ISMs of the point VPLs)\n\n\
         Reference: the rays above, the bounce rays shadowed too ({t_ref_bs:.0} ms; it differs \
         from the unshadowed reference by RMSE {ref_gap:.5} over its {} changed pixels). \
         256 VPLs x 8000 points; an object move with bounce shadows takes **{t_move_bs:.1} ms** \
         (median, scene cached).\n\n\
         | setting | time (ms) | RMSE changed |\n|---|---:|---:|",
        changed_bs.len()
    );
    for (label, t, e) in &bs_rows {
        let _ = writeln!(doc, "| {label} | {t:.0} | {e:.5} |");
    }
    let path = root.join("docs/relight.md");
    if let Err(e) = std::fs::write(&path, doc) {
        eprintln!("could not write {}: {e}", path.display());
    } else {
        eprintln!("wrote {}", path.display());
    }
}
