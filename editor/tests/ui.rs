//! Headless UI test: the side panel's generated widgets edit the model.

use std::path::PathBuf;
use std::sync::Arc;

use depthgraph_editor::EditorModel;
use depthgraph_editor::app::{PanelState, param_panel};
use depthgraph_graph::prelude::*;
use egui_kittest::Harness;
use egui_kittest::kittest::Queryable;

fn demo() -> EditorModel {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../graphs/demo.ron");
    let reg = Arc::new(depthgraph_nodes::registry().expect("registry"));
    EditorModel::load(&path, reg).expect("load demo")
}

#[test]
fn choice_widget_changes_the_document() {
    let state = (demo(), PanelState::default());
    let mut harness = Harness::new_ui_state(
        |ui, (model, panel): &mut (EditorModel, PanelState)| {
            param_panel(ui, model, "scene", panel);
        },
        state,
    );
    harness.run();
    // The widgets come from the schema: one per parameter, found by its name.
    harness.get_by_label("width");
    harness.get_by_label("preset").click();
    harness.run();
    harness.get_by_label("corridor").click();
    harness.run();
    let (model, _) = harness.state();
    assert_eq!(
        model.param_value("scene", "preset"),
        Ok(ParamValue::Text("corridor".into()))
    );
    assert!(model.to_ron().contains("preset: \"corridor\""));
    assert!(model.can_undo());
}

#[test]
fn path_parameter_is_picked_in_the_file_browser() {
    let state = (demo(), PanelState::default());
    let mut harness = Harness::new_ui_state(
        |ui, (model, panel): &mut (EditorModel, PanelState)| {
            param_panel(ui, model, "save_color", panel);
        },
        state,
    );
    harness.run();
    harness.get_by_label("…").click();
    harness.run();
    // Tests run in the editor crate's folder: its `src/` folder and its
    // Cargo.toml are listed; open the folder, then pick a file in it.
    harness.get_by_label("src/").click();
    harness.run();
    harness.get_by_label("main.rs").click();
    harness.run();
    let (model, panel) = harness.state();
    let want = std::path::Path::new(".")
        .join("src")
        .join("main.rs")
        .display()
        .to_string();
    assert_eq!(
        model.param_value("save_color", "path"),
        Ok(ParamValue::Text(want))
    );
    assert!(panel.browse.is_none(), "the browser closes after a pick");
}
