//! Helpers shared by the editor's headless UI tests (each test binary uses
//! some of them).
#![allow(dead_code)]

use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use depthgraph_editor::EditorModel;
use depthgraph_editor::app::EditorApp;
use egui_kittest::Harness;

/// The path of `graphs/<file>`.
pub fn graph_path(file: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../graphs")
        .join(file)
}

/// `graphs/<file>` as a model over the full registry.
pub fn load(file: &str) -> EditorModel {
    let reg = Arc::new(depthgraph_nodes::registry().expect("registry"));
    EditorModel::load(&graph_path(file), reg).expect("load the graph")
}

/// Steps the harness until the requested evaluation is back and shown.
pub fn settle(h: &mut Harness<'_, EditorApp>) {
    let deadline = Instant::now() + Duration::from_secs(300);
    loop {
        h.step();
        if !h.state().busy() && h.state().preview_fingerprint().is_some() {
            h.run_steps(2);
            return;
        }
        assert!(
            Instant::now() < deadline,
            "no preview within 300 s: {:?}",
            h.state().run_error()
        );
        std::thread::sleep(Duration::from_millis(10));
    }
}
