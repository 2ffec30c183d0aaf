//! Slider-to-result latency of the editor (issue 8): the demo graph at
//! 640x480, the Kinect node selected, its `noise_k` slider moved step by
//! step. Each step times what the window waits for: the edit, the cached
//! re-run on the background evaluator (only the Kinect node re-runs), and
//! the conversion of its depth map into the preview picture.
//!
//!   cargo bench -p depthgraph-editor --bench latency
//!
//! The peer in the same run is the same request with a cold cache (every
//! node runs), which is what an editor without the cache would wait for.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

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

fn main() -> Result<(), String> {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../graphs/demo.ron");
    let reg = Arc::new(depthgraph_nodes::registry().map_err(|e| e.to_string())?);
    let mut model = EditorModel::load(&path, reg)?;
    let targets = vec!["kinect".to_string(), "scene".to_string()];
    let out = std::env::temp_dir().join("depthgraph-latency-bench");
    let timeout = Duration::from_secs(120);

    let step = |ev: &mut Evaluator, model: &EditorModel| -> Result<(f64, Trace), String> {
        let t0 = Instant::now();
        ev.start(
            model
                .pipeline_for(Some(&targets))
                .map_err(|e| e.join("\n"))?,
            vec![],
        );
        let outcome = ev.wait(timeout).ok_or("no result within 120 s")?;
        let (trace, values) = outcome.result?;
        let depth = values.get("kinect.depth").ok_or("no kinect.depth")?;
        let pic = picture(depth).ok_or("depth has no picture")?;
        std::hint::black_box(pic.image.pixels.len());
        Ok((t0.elapsed().as_secs_f64() * 1e3, trace))
    };

    // Cold: a fresh engine, every node runs (the peer).
    let mut cold = Vec::new();
    for _ in 0..5 {
        let mut ev = Evaluator::new(EngineOptions::default(), out.clone())?;
        cold.push(step(&mut ev, &model)?.0);
    }
    cold.sort_by(f64::total_cmp);

    // Warm: one engine, the slider moves.
    let mut ev = Evaluator::new(EngineOptions::default(), out)?;
    step(&mut ev, &model)?;
    let mut warm = Vec::new();
    for i in 0..40 {
        let noise = 0.001 + 0.0001 * f64::from(i);
        model.set_param("kinect", "noise_k", ParamValue::Float(noise))?;
        let (ms, trace) = step(&mut ev, &model)?;
        let scene = trace.get("scene").map(|r| r.status);
        if scene != Some(Status::Cached) {
            return Err(format!(
                "the scene should be cached after a Kinect edit, got {scene:?}"
            ));
        }
        warm.push(ms);
    }
    warm.sort_by(f64::total_cmp);
    let (cm, wm) = (percentile(&cold, 0.5), percentile(&warm, 0.5));
    println!("demo graph 640x480, Kinect noise_k slider, edit -> re-run -> preview picture");
    println!(
        "  cached (editor): median {wm:.1} ms, p90 {:.1} ms, max {:.1} ms over {} steps",
        percentile(&warm, 0.9),
        warm.last().copied().unwrap_or(f64::NAN),
        warm.len()
    );
    println!(
        "  cold (peer, every node runs): median {cm:.1} ms over {} runs",
        cold.len()
    );
    // Guard: a zero median (impossible in practice) prints inf.
    println!("  ratio cold / cached: {:.1}", cm / wm.max(1e-9));
    Ok(())
}
