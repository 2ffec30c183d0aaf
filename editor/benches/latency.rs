//! Latency of the editor as a user feels it (issues 8 and 21): the time from
//! an edit to its result's preview picture, through the same background
//! evaluator and picture code the window uses. Three gestures:
//!
//! - **slider**: the demo graph at 640x480, the Kinect node's `noise_k`
//!   slider moved step by step (only the Kinect node re-runs);
//! - **drag**: `copy_paste_relit.ron` at 640x480 with 256 VPLs, the pasted
//!   object dragged left 4 px per step along the back wall
//!   (`Paste.target_pixel`, as a drag on the preview sets it; it stays the
//!   size the graph gives it): Paste, Feather, OcclusionComposite and Relight
//!   re-run, the relighting's scene part stays cached;
//! - **focus**: `refocus.ron` at 640x480 with 64 lens samples, a click on the
//!   picture sets `focus_m` to the depth under the pointer (only Refocus
//!   re-runs).
//!
//!   cargo bench -p depthgraph-editor --bench latency
//!
//! The peer in the same run is the same request with a cold cache (every
//! node runs), which is what an editor without the cache would wait for.
//! `DEPTHGRAPH_LATENCY_PARTS=slider,drag,focus` picks the gestures;
//! `DEPTHGRAPH_BACKEND=gpu` (or `auto`) runs the device kinds on a wgpu
//! adapter (default `cpu`).

use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use depthgraph_editor::focus::{FOCUS_WINDOW_RADIUS, focus_depth};
use depthgraph_editor::placement::dragged_target;
use depthgraph_editor::preview::picture;
use depthgraph_editor::{EditorModel, Evaluator};
use depthgraph_graph::prelude::*;

fn percentile(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let i = ((sorted.len() - 1) as f64 * q).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

/// One request: edit already made, run, wait, build the preview picture of
/// `shown`. Returns the milliseconds, the trace and the values.
fn step(
    ev: &mut Evaluator,
    model: &EditorModel,
    targets: &[String],
    shown: &str,
) -> Result<(f64, Trace, std::collections::BTreeMap<String, Value>), String> {
    let t0 = Instant::now();
    ev.start(
        model
            .pipeline_for(Some(targets))
            .map_err(|e| e.join("\n"))?,
        vec![],
    );
    let outcome = ev
        .wait(Duration::from_secs(600))
        .ok_or("no result within 600 s")?;
    let (trace, values) = outcome.result?;
    let v = values.get(shown).ok_or_else(|| format!("no {shown}"))?;
    let pic = picture(v).ok_or_else(|| format!("{shown} has no picture"))?;
    std::hint::black_box(pic.image.pixels.len());
    Ok((t0.elapsed().as_secs_f64() * 1e3, trace, values))
}

/// Makes edit `i` of a gesture (reading the first warm run's values).
type Edit = dyn FnMut(usize, &mut EditorModel, &Values) -> Result<(), String>;
type Values = std::collections::BTreeMap<String, Value>;

struct Gesture {
    name: &'static str,
    what: &'static str,
    model: EditorModel,
    targets: Vec<String>,
    shown: &'static str,
    /// Nodes that must come from the cache in a warm step.
    cached: &'static [&'static str],
    steps: usize,
    cold_runs: usize,
    /// Makes edit `i` (after a first warm run whose values it may read).
    edit: Box<Edit>,
}

fn measure(mut g: Gesture, out: &std::path::Path) -> Result<String, String> {
    let mut cold = Vec::new();
    for _ in 0..g.cold_runs {
        let mut ev = Evaluator::new(EngineOptions::default(), out.to_path_buf())?;
        cold.push(step(&mut ev, &g.model, &g.targets, g.shown)?.0);
    }
    cold.sort_by(f64::total_cmp);
    let mut ev = Evaluator::new(EngineOptions::default(), out.to_path_buf())?;
    let (_, _, values) = step(&mut ev, &g.model, &g.targets, g.shown)?;
    let mut warm = Vec::new();
    let mut last = None;
    for i in 0..g.steps {
        (g.edit)(i, &mut g.model, &values)?;
        let (ms, trace, _) = step(&mut ev, &g.model, &g.targets, g.shown)?;
        for n in g.cached {
            let s = trace.get(n).map(|r| r.status);
            if s != Some(Status::Cached) {
                return Err(format!("{}: {n} should be cached, got {s:?}", g.name));
            }
        }
        warm.push(ms);
        last = Some(trace);
    }
    if let Some(t) = &last {
        let ran: Vec<String> = t
            .nodes
            .iter()
            .filter(|r| r.status == Status::Ran)
            .map(|r| format!("{} {:.1}", r.node, r.ms))
            .collect();
        eprintln!("{}: last step's nodes (ms): {}", g.name, ran.join(", "));
    }
    warm.sort_by(f64::total_cmp);
    let (cm, wm) = (percentile(&cold, 0.5), percentile(&warm, 0.5));
    // Guard: a zero median (impossible in practice) prints inf.
    Ok(format!(
        "| {} | {} | {wm:.1} | {:.1} | {} | {cm:.1} | {:.1} |",
        g.name,
        g.what,
        percentile(&warm, 0.9),
        warm.len(),
        cm / wm.max(1e-9)
    ))
}

fn graph(file: &str, reg: &Arc<Registry>) -> Result<EditorModel, String> {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../graphs")
        .join(file);
    EditorModel::load(&path, reg.clone())
}

/// The registry with the device kinds `DEPTHGRAPH_BACKEND` asks for
/// (`cpu`, the default here so that numbers stay comparable across
/// machines; `gpu` or `auto`), and a line saying what was chosen.
fn registry() -> Result<(Arc<Registry>, String), String> {
    #[allow(unused_mut)]
    let mut reg = depthgraph_nodes::registry().map_err(|e| e.to_string())?;
    let name = std::env::var("DEPTHGRAPH_BACKEND").unwrap_or_else(|_| "cpu".to_string());
    #[cfg(feature = "gpu")]
    {
        let req = depthgraph_gpu::BackendRequest::parse(&name)
            .ok_or_else(|| format!("DEPTHGRAPH_BACKEND `{name}`: expected auto, cpu or gpu"))?;
        let c =
            depthgraph_gpu::choose(req, &mut reg).map_err(|e| format!("backend {name}: {e}"))?;
        Ok((Arc::new(reg), format!("backend {} ({})", c.used, c.reason)))
    }
    #[cfg(not(feature = "gpu"))]
    {
        match name.as_str() {
            "cpu" | "auto" => Ok((Arc::new(reg), "backend cpu (built without `gpu`)".into())),
            _ => Err(format!(
                "DEPTHGRAPH_BACKEND `{name}`: built without the `gpu` feature"
            )),
        }
    }
}

fn slider(reg: &Arc<Registry>) -> Result<Gesture, String> {
    Ok(Gesture {
        name: "slider",
        what: "demo 640x480, Kinect `noise_k`",
        model: graph("demo.ron", reg)?,
        targets: vec!["kinect".into(), "scene".into()],
        shown: "kinect.depth",
        cached: &["scene"],
        steps: 40,
        cold_runs: 5,
        edit: Box::new(|i, m, _| {
            m.set_param(
                "kinect",
                "noise_k",
                ParamValue::Float(0.001 + 0.0001 * i as f64),
            )
        }),
    })
}

fn drag(reg: &Arc<Registry>) -> Result<Gesture, String> {
    let mut m = graph("copy_paste_relit.ron", reg)?;
    for n in ["source", "target"] {
        m.set_param(n, "width", ParamValue::Int(640))?;
        m.set_param(n, "height", ParamValue::Int(480))?;
    }
    let double = |p: ParamValue| match p {
        ParamValue::Points(p) => Ok(ParamValue::Points(
            p.iter().map(|q| [q[0] * 2.0, q[1] * 2.0]).collect(),
        )),
        other => Err(format!("expected points, got {other:?}")),
    };
    let clicks = double(m.param_value("lasso", "clicks")?)?;
    m.set_param("lasso", "clicks", clicks)?;
    let tp = double(m.param_value("paste", "target_pixel")?)?;
    let start = match &tp {
        ParamValue::Points(p) => p[0],
        _ => [0.0, 0.0],
    };
    m.set_param("paste", "target_pixel", tp)?;
    m.set_param("vpl", "count", ParamValue::Int(256))?;
    Ok(Gesture {
        name: "drag",
        what: "copy_paste_relit 640x480, 256 VPLs, pasted object dragged left 4 px a step",
        model: m,
        targets: vec!["relight".into(), "paste".into(), "target".into()],
        shown: "relight.color",
        cached: &["source", "target", "lasso", "vpl"],
        steps: 20,
        cold_runs: 3,
        edit: Box::new(move |i, m, _| {
            m.begin_gesture();
            let r = m.set_param(
                "paste",
                "target_pixel",
                ParamValue::Points(vec![dragged_target(
                    start,
                    [-4.0 * (i + 1) as f64, 0.0],
                    [640, 480],
                )]),
            );
            m.end_gesture();
            r
        }),
    })
}

fn focus(reg: &Arc<Registry>) -> Result<Gesture, String> {
    let mut m = graph("refocus.ron", reg)?;
    m.set_param("refocus", "samples", ParamValue::Int(64))?;
    Ok(Gesture {
        name: "focus",
        what: "refocus 640x480, 64 lens samples, click to focus",
        model: m,
        targets: vec!["refocus".into(), "fill".into()],
        shown: "refocus.color",
        cached: &["fill", "hdr"],
        steps: 20,
        cold_runs: 3,
        edit: Box::new(|i, m, values| {
            let Some(Value::Depth(d)) = values.get("fill.depth") else {
                return Err("no fill.depth".into());
            };
            // Clicks along a diagonal of the picture.
            let t = (i as f64 + 0.5) / 20.0;
            let px = [40.0 + 560.0 * t, 60.0 + 360.0 * t];
            let z = focus_depth(d, px, FOCUS_WINDOW_RADIUS).ok_or("a hole under the click")?;
            // Distinct values, so every click is a new request.
            m.set_param("refocus", "focus_m", ParamValue::Float(z + 1e-4 * i as f64))
        }),
    })
}

fn main() -> Result<(), String> {
    let parts = std::env::var("DEPTHGRAPH_LATENCY_PARTS")
        .unwrap_or_else(|_| "slider,drag,focus".to_string());
    let out = std::env::temp_dir().join("depthgraph-latency-bench");
    let (reg, backend) = registry()?;
    println!(
        "Edit -> re-run -> preview picture, ms ({} threads, {} profile, {backend})",
        rayon_threads(),
        if cfg!(debug_assertions) {
            "dev"
        } else {
            "release"
        }
    );
    println!();
    println!(
        "| gesture | setting | cached median | cached p90 | steps | cold median (peer) | cold / cached |"
    );
    println!("|---|---|---:|---:|---:|---:|---:|");
    for part in parts.split(',').map(str::trim) {
        let g = match part {
            "slider" => slider(&reg)?,
            "drag" => drag(&reg)?,
            "focus" => focus(&reg)?,
            "" => continue,
            other => return Err(format!("unknown part `{other}`: slider, drag or focus")),
        };
        println!("{}", measure(g, &out)?);
    }
    Ok(())
}

/// The worker threads rayon's global pool starts with: `RAYON_NUM_THREADS`
/// when set to a positive count, else the available parallelism.
fn rayon_threads() -> usize {
    std::env::var("RAYON_NUM_THREADS")
        .ok()
        .and_then(|v| v.parse::<usize>().ok())
        .filter(|n| *n > 0)
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()))
}
