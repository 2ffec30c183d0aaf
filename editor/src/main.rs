//! `depthgraph-editor FILE`: opens a pipeline in the graph editor.

use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;

use depthgraph_editor::EditorModel;
use depthgraph_editor::app::EditorApp;

fn main() -> ExitCode {
    let Some(path) = std::env::args_os().nth(1).map(PathBuf::from) else {
        eprintln!("usage: depthgraph-editor FILE.ron");
        return ExitCode::from(2);
    };
    let registry = match depthgraph_nodes::registry() {
        Ok(r) => Arc::new(r),
        Err(e) => {
            eprintln!("error: node registry: {e}");
            return ExitCode::FAILURE;
        }
    };
    let model = match EditorModel::load(&path, registry) {
        Ok(m) => m,
        Err(e) => {
            eprintln!("error: {e}");
            return ExitCode::FAILURE;
        }
    };
    let app = EditorApp::new(model, path.clone());
    let title = format!("depthgraph editor - {}", path.display());
    match eframe::run_native(
        &title,
        eframe::NativeOptions::default(),
        Box::new(|_cc| Ok(Box::new(app))),
    ) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}
