//! `depthgraph-editor [FILE]`: opens a pipeline in the graph editor.
//!
//! `--screenshot OUT.png` runs without a person: the window opens, the node
//! given by `--select` is evaluated and previewed, the window is written to
//! OUT.png and closed (the CI test under Xvfb and the README's picture).

use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use clap::Parser;
use depthgraph_editor::EditorModel;
use depthgraph_editor::app::{AutoShot, EditorApp};

#[derive(Parser)]
#[command(
    name = "depthgraph-editor",
    about = "Node-graph editor for depthgraph pipelines"
)]
struct Args {
    /// The pipeline (RON) to open; none opens an empty graph.
    file: Option<PathBuf>,
    /// Write a screenshot of the window to this PNG once the preview is shown, then exit.
    #[arg(long)]
    screenshot: Option<PathBuf>,
    /// The node to select (and preview) at start.
    #[arg(long)]
    select: Option<String>,
    /// Folder the pipeline's sinks write under when previewed (as the CLI's `--out`).
    #[arg(long, default_value = "out")]
    out: PathBuf,
    /// Window size in points, WIDTHxHEIGHT.
    #[arg(long, default_value = "1280x800")]
    size: String,
    /// Screenshot mode: move the pasted object of the selected preview by
    /// DX,DY image pixels (as a drag on it does) before the screenshot.
    #[arg(long, value_name = "DX,DY")]
    drag: Option<String>,
    /// Screenshot mode gives up after this many seconds.
    #[arg(long, default_value_t = 300.0)]
    timeout_s: f64,
    /// Where the device node kinds run: auto (the GPU when a wgpu adapter
    /// exists), cpu, or gpu (fail when there is none). Default:
    /// $DEPTHGRAPH_BACKEND, else auto.
    #[arg(long)]
    backend: Option<String>,
}

/// The registry with the device kinds `--backend` (or `DEPTHGRAPH_BACKEND`)
/// asks for, and a line saying what was chosen.
fn registry(
    backend: Option<&str>,
) -> Result<(depthgraph_graph::registry::Registry, String), String> {
    let mut reg = depthgraph_nodes::registry().map_err(|e| format!("node registry: {e}"))?;
    let name = backend
        .map(str::to_string)
        .or_else(|| std::env::var("DEPTHGRAPH_BACKEND").ok())
        .unwrap_or_else(|| "auto".to_string());
    #[cfg(feature = "gpu")]
    {
        let req = depthgraph_gpu::BackendRequest::parse(&name)
            .ok_or_else(|| format!("--backend `{name}`: expected auto, cpu or gpu"))?;
        let c = depthgraph_gpu::choose(req, &mut reg).map_err(|e| format!("--backend gpu: {e}"))?;
        Ok((reg, format!("backend: {} ({})", c.used, c.reason)))
    }
    #[cfg(not(feature = "gpu"))]
    {
        match name.trim().to_ascii_lowercase().as_str() {
            "auto" | "cpu" => Ok((
                reg,
                "backend: cpu (built without the `gpu` feature)".to_string(),
            )),
            "gpu" => {
                Err("--backend gpu: this editor was built without the `gpu` feature".to_string())
            }
            _ => Err(format!("--backend `{name}`: expected auto, cpu or gpu")),
        }
    }
}

fn parse_drag(s: &str) -> Result<[f64; 2], String> {
    let bad = || format!("--drag `{s}`: expected DX,DY in image pixels, e.g. 40,-10");
    let (x, y) = s.split_once(',').ok_or_else(bad)?;
    let x: f64 = x.trim().parse().map_err(|_| bad())?;
    let y: f64 = y.trim().parse().map_err(|_| bad())?;
    if !(x.is_finite() && y.is_finite()) {
        return Err(bad());
    }
    Ok([x, y])
}

fn parse_size(s: &str) -> Result<[f32; 2], String> {
    let bad = || format!("--size `{s}`: expected WIDTHxHEIGHT, e.g. 1280x800");
    let (w, h) = s.split_once('x').ok_or_else(bad)?;
    let w: f32 = w.trim().parse().map_err(|_| bad())?;
    let h: f32 = h.trim().parse().map_err(|_| bad())?;
    if !(w >= 100.0 && h >= 100.0 && w <= 16384.0 && h <= 16384.0) {
        return Err(format!("--size `{s}`: each side must be 100 to 16384"));
    }
    Ok([w, h])
}

fn main() -> ExitCode {
    let args = Args::parse();
    match run(args) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}

fn run(args: Args) -> Result<(), String> {
    let size = parse_size(&args.size)?;
    let drag = args.drag.as_deref().map(parse_drag).transpose()?;
    if drag.is_some() && (args.screenshot.is_none() || args.select.is_none()) {
        return Err("--drag needs --screenshot and --select (the preview to drag on)".into());
    }
    if !(args.timeout_s.is_finite() && args.timeout_s > 0.0) {
        return Err(format!("--timeout-s {}: must be > 0", args.timeout_s));
    }
    let (registry, chosen) = registry(args.backend.as_deref())?;
    eprintln!("{chosen}");
    let registry = Arc::new(registry);
    let (model, path, new_file) = match &args.file {
        Some(path) => (EditorModel::load(path, registry)?, path.clone(), false),
        None => {
            // A name no file has yet, so Save never overwrites one.
            let path = (0..10_000)
                .map(|n| match n {
                    0 => PathBuf::from("untitled.ron"),
                    n => PathBuf::from(format!("untitled-{n}.ron")),
                })
                .find(|p| !p.exists())
                .ok_or("every name untitled[-N].ron up to N = 9999 is taken")?;
            let name = path.display().to_string();
            (
                EditorModel::from_text("(version: 1, nodes: {})", &name, registry)?,
                path,
                true,
            )
        }
    };
    if let Some(sel) = &args.select
        && model.document().node(sel).is_none()
    {
        return Err(format!(
            "--select `{sel}`: no such node in {}",
            path.display()
        ));
    }
    let mut app = EditorApp::with_out_dir(model, path.clone(), args.out.clone());
    if new_file {
        app = app.with_new_file();
    }
    let outcome = Arc::new(Mutex::new(None));
    if let Some(shot) = &args.screenshot {
        app = app.with_screenshot(AutoShot {
            path: shot.clone(),
            select: args.select.clone(),
            timeout: Duration::from_secs_f64(args.timeout_s),
            outcome: outcome.clone(),
            drag,
        });
    }
    let title = format!("depthgraph editor - {}", path.display());
    let options = eframe::NativeOptions {
        viewport: eframe::egui::ViewportBuilder::default()
            .with_inner_size(size)
            .with_title(title.clone()),
        ..eframe::NativeOptions::default()
    };
    eframe::run_native(&title, options, Box::new(|_cc| Ok(Box::new(app))))
        .map_err(|e| format!("cannot open the window: {e}"))?;
    if args.screenshot.is_some() {
        let result = outcome
            .lock()
            .map_err(|_| "the screenshot state was poisoned".to_string())?
            .take();
        return match result {
            Some(r) => r,
            None => Err("the window closed before the screenshot was taken".into()),
        };
    }
    Ok(())
}
