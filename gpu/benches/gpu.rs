//! CPU against GPU on the same inputs in one run: `cargo bench -p
//! depthgraph-gpu --bench gpu`. Per node (PullPush, DualPullPush, Feather,
//! JointBilateral r = 7, Refocus 640x480 at 256 samples plain, with the
//! background layer and with the per-view lens effects and, with
//! `DEPTHGRAPH_BENCH_FULL=1`, 1600x1200 at 576 samples) and
//! a `Relight` object move at 640x480 with 256 VPLs (the device's direct
//! term, the scene kept) in two path-traced rooms, and
//! per pipeline (`depth_fill.ron`, `refocus.ron`, `copy_paste_relit.ron`,
//! no cache): cold (first
//! evaluation, pipeline compilation included) and warm medians, and the
//! device's upload / kernel / download split. The adapter and driver are
//! named; on a software adapter (lavapipe) the GPU numbers are labelled
//! correctness-only. `DEPTHGRAPH_REPEATS` (default 5) timed repeats;
//! `DEPTHGRAPH_BENCH_ONLY=text` runs only the rows whose name contains it.
//! Refocus also runs with one view per dispatch (a second context), beside
//! the default batches.
//!
//! `gpu/scripts/device-bench.sh` builds this here and runs it on a GPU
//! machine without network.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use depthgraph_gpu::relight::DeviceSums;
use depthgraph_gpu::session::Session;
use depthgraph_gpu::{AdapterRequest, GpuContext};
use depthgraph_graph::node::{CancelToken, Transfers};
use depthgraph_graph::pipeline::OutputRef;
use depthgraph_graph::prelude::*;
use depthgraph_nodes::camera::refocus::RefocusParams;
use depthgraph_nodes::depth::bilateral::BilateralParams;
use depthgraph_nodes::relight::scene_cached::{
    MoveSums, RelightScene, relight_moved, relight_moved_with,
};
use depthgraph_nodes::relight::shading::{RelightInputs, RelightParams};
use depthgraph_nodes::sim::pathtrace::PathTraceParams;
use depthgraph_nodes::sim::relight_truth::{Room, relight_case};
use depthgraph_nodes::sim::synthetic::{RenderOptions, Scene, render};

fn env_usize(name: &str, default: usize) -> usize {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    if v.is_empty() {
        f64::NAN
    } else {
        v[v.len() / 2]
    }
}

struct Row {
    what: String,
    cpu_ms: f64,
    gpu_cold_ms: f64,
    gpu_ms: f64,
    split: Transfers,
}

fn eval(reg: &Registry, kind: &str, inputs: &Inputs, params: &ParamMap) -> (f64, Outputs) {
    let node = reg.get(kind).expect("kind registered");
    let cancel = CancelToken::new();
    let dir = std::env::temp_dir();
    let ctx = EvalCtx {
        node: kind,
        cancel: &cancel,
        progress: None,
        out_dir: &dir,
        input_files: &[],
        derivations: None,
        max_pixels: depthgraph_graph::node::DEFAULT_MAX_PIXELS,
    };
    let t = Instant::now();
    let out = node
        .eval(&ctx, inputs, params)
        .unwrap_or_else(|e| panic!("{kind}: {e}"));
    (t.elapsed().as_secs_f64() * 1e3, out)
}

/// The same inputs as new values (deep copies): nothing is found on the device.
fn fresh_copies(inputs: &Inputs) -> Inputs {
    let mut out = Inputs::new();
    let ports = ["depth", "color", "mask", "intrinsics"];
    for (port, v) in ports.iter().filter_map(|p| inputs.get(p).map(|v| (*p, v))) {
        let v = match v {
            Value::Color(c) => Value::Color(Arc::new((**c).clone())),
            Value::Depth(d) => Value::Depth(Arc::new((**d).clone())),
            Value::Mask(m) => Value::Mask(Arc::new((**m).clone())),
            other => other.clone(),
        };
        out.insert(port, v);
    }
    out
}

/// Whether the row named `what` runs: every row, or with
/// `DEPTHGRAPH_BENCH_ONLY` set those whose name contains it.
fn wanted(what: &str) -> bool {
    std::env::var("DEPTHGRAPH_BENCH_ONLY").map_or(true, |only| what.contains(only.as_str()))
}

fn node_row(
    what: &str,
    regs: &(Registry, Registry),
    kind: &str,
    inputs: &Inputs,
    params: &ParamMap,
    repeats: usize,
) -> Option<Row> {
    if !wanted(what) {
        return None;
    }
    let cpu: Vec<f64> = (0..repeats.clamp(1, 3))
        .map(|_| eval(&regs.0, kind, inputs, params).0)
        .collect();
    let (cold, _) = eval(&regs.1, kind, inputs, params);
    let mut warm = Vec::new();
    let mut splits = Vec::new();
    for _ in 0..repeats {
        // New values each time (copied outside the timing), so the inputs
        // are uploaded as for a node that receives new data; pipelines
        // compiled, buffers pooled.
        let fresh = fresh_copies(inputs);
        let (ms, out) = eval(&regs.1, kind, &fresh, params);
        warm.push(ms);
        splits.push(out.transfers);
    }
    let mid = splits.get(splits.len() / 2).copied().unwrap_or_default();
    Some(Row {
        what: what.to_string(),
        cpu_ms: median(cpu),
        gpu_cold_ms: cold,
        gpu_ms: median(warm),
        split: mid,
    })
}

/// A `Relight` object move (scene kept) at 640x480 with 256 VPLs on a
/// path-traced room: the CPU's move against the move with the device's
/// two long sums (the direct term, the object's light), the scene built
/// once for both and named to the device as the node names it (its maps
/// and the photo's depth stay on the device between moves).
fn relight_move_row(ctx: &GpuContext, room: Room, repeats: usize) -> Option<Row> {
    let quick = PathTraceParams {
        samples: 1,
        bounces: 2,
        seed: 1,
    };
    let case = relight_case(room, None, 640, 480, 256, &quick).expect("relight case");
    let what = format!("Relight move 640x480 256 VPLs, {}", case.name);
    if !wanted(&what) {
        return None;
    }
    let vpls = case.vpls(256);
    let depth = Arc::new(case.depth.clone());
    let inp = RelightInputs {
        depth: &depth,
        ..case.inputs()
    };
    let p = RelightParams::default();
    let scene = Arc::new(RelightScene::new(&inp.scene(), &vpls, &p).expect("relight scene"));
    let cpu: Vec<f64> = (0..repeats)
        .map(|_| {
            let t = Instant::now();
            relight_moved(&scene, &inp, &p).expect("relight move");
            t.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    let device = |s: &mut Session| {
        let t = Instant::now();
        let mut sums = DeviceSums::new(s).with_depth(depth.clone());
        sums.scene(&scene);
        relight_moved_with(&scene, &inp, &p, &mut sums).expect("relight move on the device");
        t.elapsed().as_secs_f64() * 1e3
    };
    let cold = device(&mut Session::new(ctx));
    let mut warm = Vec::new();
    let mut split = Transfers::default();
    for _ in 0..repeats {
        let mut s = Session::new(ctx);
        warm.push(device(&mut s));
        split = s.stats;
    }
    Some(Row {
        what,
        cpu_ms: median(cpu),
        gpu_cold_ms: cold,
        gpu_ms: median(warm),
        split,
    })
}

fn pipeline_row(file: &str, regs: &(Registry, Registry), repeats: usize) -> Option<Row> {
    if !wanted(&format!("pipeline {file}")) {
        return None;
    }
    // DEPTHGRAPH_ROOT: the repository on a machine the binary was carried to
    let root = std::env::var_os("DEPTHGRAPH_ROOT")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join(".."));
    std::env::set_current_dir(&root).expect("repository root");
    let text = std::fs::read_to_string(root.join("graphs").join(file)).expect("pipeline file");
    let doc = Document::parse(&text, file).expect("pipeline parses");
    let run = |reg: &Registry| -> (f64, Transfers) {
        let mut p = Pipeline::check(&doc, reg).expect("pipeline checks");
        p.outputs = (0..p.nodes.len())
            .filter(|&i| !p.nodes[i].node.schema().sink)
            .map(|node| OutputRef { node, port: None })
            .collect();
        let engine = Engine::new(EngineOptions::default()).expect("engine");
        let opts = RunOptions {
            out_dir: std::env::temp_dir().join("depthgraph-gpu-bench"),
            ..RunOptions::default()
        };
        let t = Instant::now();
        let r = engine.run(&p, &opts).expect("pipeline runs");
        let ms = t.elapsed().as_secs_f64() * 1e3;
        let mut sum = Transfers::default();
        for n in &r.trace.nodes {
            let t = n.transfers;
            sum.uploads += t.uploads;
            sum.upload_bytes += t.upload_bytes;
            sum.upload_ms += t.upload_ms;
            sum.resident_hits += t.resident_hits;
            sum.downloads += t.downloads;
            sum.download_bytes += t.download_bytes;
            sum.download_ms += t.download_ms;
            sum.kernel_ms += t.kernel_ms;
        }
        (ms, sum)
    };
    let cpu: Vec<f64> = (0..repeats.clamp(1, 3)).map(|_| run(&regs.0).0).collect();
    let (cold, _) = run(&regs.1);
    let warm: Vec<(f64, Transfers)> = (0..repeats.clamp(1, 3)).map(|_| run(&regs.1)).collect();
    let split = warm[warm.len() / 2].1;
    Some(Row {
        what: format!("pipeline {file}"),
        cpu_ms: median(cpu),
        gpu_cold_ms: cold,
        gpu_ms: median(warm.iter().map(|w| w.0).collect()),
        split,
    })
}

fn scene_inputs(w: usize, h: usize) -> (Arc<ColorImage>, Arc<DepthMap>) {
    let (c, d, _) = scene_with_intrinsics(w, h);
    (c, d)
}

fn scene_with_intrinsics(w: usize, h: usize) -> (Arc<ColorImage>, Arc<DepthMap>, Intrinsics) {
    let scene = Scene::preset("tabletop", w, h).expect("preset");
    let r = render(&scene, &RenderOptions::default());
    (Arc::new(r.color), Arc::new(r.depth), r.intrinsics)
}

/// `depth` with Kinect-like holes: 20 % scattered and a 60x40 block.
fn with_holes(depth: &DepthMap) -> DepthMap {
    let mut rng = depthgraph_nodes::kit::rng::SplitMix64(11);
    let (w, h) = depth.dims();
    DepthMap::from_fn(w, h, |x, y| {
        let block = (w / 3..w / 3 + 60).contains(&x) && (h / 2..h / 2 + 40).contains(&y);
        if block || rng.next_f64() < 0.2 {
            0.0
        } else {
            *depth.get(x, y)
        }
    })
}

fn main() {
    if std::env::args().any(|a| a == "--list") {
        return; // cargo's bench discovery
    }
    let repeats = env_usize("DEPTHGRAPH_REPEATS", 5).max(1);
    let ctx = match GpuContext::new(&AdapterRequest::default()) {
        Ok(c) => c,
        Err(e) => {
            eprintln!("gpu bench: {e}");
            std::process::exit(69);
        }
    };
    let a = ctx.adapter().clone();
    let cpu = depthgraph_nodes::registry().expect("registry");
    let mut dev = depthgraph_nodes::registry().expect("registry");
    depthgraph_gpu::install(&mut dev, &ctx).expect("device kinds");
    let regs = (cpu, dev);
    let threads = rayon::current_num_threads();
    println!("# GPU bench\n");
    println!(
        "adapter: {} ({:?} {}), driver: {}, API: {}; CPU: {threads} threads",
        a.name,
        a.device_type,
        if a.is_software() {
            "software"
        } else {
            "hardware"
        },
        a.driver,
        a.api
    );
    if a.is_software() {
        println!(
            "\n**{} is a software rasteriser: its GPU timings are for correctness only.**",
            a.name
        );
    }
    let mut rows = Vec::new();

    let (color, depth, k) = scene_with_intrinsics(640, 480);
    let holed = Arc::new(with_holes(&depth));
    let mut pi = Inputs::new();
    pi.insert("depth", Value::Depth(holed));
    let pp = depthgraph_nodes::depth::pull_push::PullPushParams::default();
    rows.extend(node_row(
        "PullPush 640x480 (20 % holes)",
        &regs,
        "PullPush",
        &pi,
        &pp.to_values(),
        repeats,
    ));
    pi.insert("color", Value::Color(color.clone()));
    pi.insert("intrinsics", Value::Intrinsics(k));
    rows.extend(node_row(
        "DualPullPush 640x480 (20 % holes)",
        &regs,
        "DualPullPush",
        &pi,
        &pp.to_values(),
        repeats,
    ));
    // NL-means inpainting of the same holes (its default 64 iterations stop
    // when nothing is left to fill)
    let mut ni = Inputs::new();
    ni.insert("depth", pi.get("depth").cloned().expect("depth"));
    ni.insert("color", Value::Color(color.clone()));
    let np = depthgraph_nodes::depth::nlmeans::NLMeansInpaintParams::default();
    rows.extend(node_row(
        "NLMeansInpaint 640x480 (20 % holes)",
        &regs,
        "NLMeansInpaint",
        &ni,
        &np.to_values(),
        repeats.min(3),
    ));
    // NL-means upsampling x4: 160x120 depth (every 4th pixel of the scene's)
    // onto the 640x480 colour
    let low = DepthMap::from_fn(160, 120, |x, y| *depth.get(4 * x + 2, 4 * y + 2));
    let mut ui = Inputs::new();
    ui.insert("depth", Value::Depth(Arc::new(low)));
    ui.insert("intrinsics", Value::Intrinsics(k.scaled_to(160, 120)));
    ui.insert("color", Value::Color(color.clone()));
    let up = depthgraph_nodes::depth::nlmeans::NLMeansUpsampleParams::default();
    rows.extend(node_row(
        "NLMeansUpsample 160x120 -> 640x480",
        &regs,
        "NLMeansUpsample",
        &ui,
        &up.to_values(),
        repeats.min(3),
    ));
    let disc = Mask::from_fn(640, 480, |x, y| {
        let (dx, dy) = (x as f32 - 320.0, y as f32 - 240.0);
        if dx * dx + dy * dy < 150.0 * 150.0 {
            1.0
        } else {
            0.0
        }
    });
    let mut fi = Inputs::new();
    fi.insert("mask", Value::Mask(Arc::new(disc)));
    let fp = depthgraph_nodes::select::feather::FeatherParams::default();
    rows.extend(node_row(
        "Feather 640x480 sigma 2",
        &regs,
        "Feather",
        &fi,
        &fp.to_values(),
        repeats,
    ));
    let mut i = Inputs::new();
    i.insert("depth", Value::Depth(depth.clone()));
    i.insert("color", Value::Color(color.clone()));
    let bp = BilateralParams {
        radius: 7,
        ..Default::default()
    };
    rows.extend(node_row(
        "JointBilateral 640x480 r=7",
        &regs,
        "JointBilateral",
        &i,
        &bp.to_values(),
        repeats,
    ));

    let rp = |samples: usize, _w: usize| RefocusParams {
        focal_length_mm: 50.0,
        f_number: 1.4,
        focus_m: 0.95,
        // full frame at any width: the paper's lens
        sensor_width_mm: 36.0,
        samples,
        ..Default::default()
    };
    let mut ri = Inputs::new();
    ri.insert("color", Value::Color(color));
    ri.insert("depth", Value::Depth(depth));
    rows.extend(node_row(
        "Refocus 640x480 256 samples",
        &regs,
        "Refocus",
        &ri,
        &rp(256, 640).to_values(),
        repeats,
    ));
    // the same with one view per dispatch (the path before batching), on a
    // second context opened only when the row runs
    let one_view_row = |what: &str, inputs: &Inputs, params: &ParamMap, repeats: usize| {
        if !wanted(what) {
            return None;
        }
        let ctx = GpuContext::new(&AdapterRequest {
            views_per_dispatch: Some(1),
            ..Default::default()
        })
        .expect("the same adapter again");
        let mut dev = depthgraph_nodes::registry().expect("registry");
        depthgraph_gpu::install(&mut dev, &ctx).expect("device kinds");
        let regs = (depthgraph_nodes::registry().expect("registry"), dev);
        node_row(what, &regs, "Refocus", inputs, params, repeats)
    };
    rows.extend(one_view_row(
        "Refocus 640x480 256 samples, one view per dispatch",
        &ri,
        &rp(256, 640).to_values(),
        repeats,
    ));
    let layered = RefocusParams {
        background_layer: true,
        ..rp(256, 640)
    };
    rows.extend(node_row(
        "Refocus 640x480 256 samples, background layer",
        &regs,
        "Refocus",
        &ri,
        &layered.to_values(),
        repeats,
    ));
    // every per-view lens effect at once (the image-wide ones run on the host)
    let lensed = RefocusParams {
        spherical_aberration_d: 0.5,
        chromatic_longitudinal_d: 0.3,
        barrel_distance_mm: 40.0,
        ..rp(256, 640)
    };
    rows.extend(node_row(
        "Refocus 640x480 256 samples, spherical + longitudinal chromatic + barrel",
        &regs,
        "Refocus",
        &ri,
        &lensed.to_values(),
        repeats,
    ));
    if std::env::var_os("DEPTHGRAPH_BENCH_FULL").is_some() {
        let (c, d) = scene_inputs(1600, 1200);
        let mut bi = Inputs::new();
        bi.insert("color", Value::Color(c));
        bi.insert("depth", Value::Depth(d));
        rows.extend(node_row(
            "Refocus 1600x1200 576 samples",
            &regs,
            "Refocus",
            &bi,
            &rp(576, 1600).to_values(),
            repeats.min(3),
        ));
        rows.extend(one_view_row(
            "Refocus 1600x1200 576 samples, one view per dispatch",
            &bi,
            &rp(576, 1600).to_values(),
            repeats.min(3),
        ));
    }
    for room in [Room::Open, Room::NearWall] {
        rows.extend(relight_move_row(&ctx, room, repeats));
    }
    for f in ["depth_fill.ron", "refocus.ron", "copy_paste_relit.ron"] {
        rows.extend(pipeline_row(f, &regs, repeats));
    }

    println!(
        "\n| case | CPU ms | GPU cold ms | GPU warm ms | CPU/GPU | up (MiB, ms) | kernels ms | down (MiB, ms) | already on device |"
    );
    println!("|---|---:|---:|---:|---:|---:|---:|---:|---:|");
    for r in &rows {
        let mib = |b: usize| b as f64 / (1024.0 * 1024.0);
        println!(
            "| {} | {:.2} | {:.2} | {:.2} | {:.2} | {:.2}, {:.2} | {:.2} | {:.2}, {:.2} | {} |",
            r.what,
            r.cpu_ms,
            r.gpu_cold_ms,
            r.gpu_ms,
            r.cpu_ms / r.gpu_ms,
            mib(r.split.upload_bytes),
            r.split.upload_ms,
            r.split.kernel_ms,
            mib(r.split.download_bytes),
            r.split.download_ms,
            r.split.resident_hits
        );
    }
    println!(
        "\npipeline compilation (all kernels, cold): {:.1} ms",
        ctx.compile_ms()
    );
}
