//! Headless UI test: the side panel's generated widgets edit the model.

use std::path::PathBuf;
use std::sync::Arc;

use depthgraph_editor::EditorModel;
use depthgraph_editor::app::{PanelState, param_panel};
use depthgraph_graph::prelude::*;
use egui_kittest::Harness;
use egui_kittest::kittest::Queryable;

fn load(file: &str) -> EditorModel {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../graphs")
        .join(file);
    let reg = Arc::new(depthgraph_nodes::registry().expect("registry"));
    EditorModel::load(&path, reg).expect("load the graph")
}

fn demo() -> EditorModel {
    load("demo.ron")
}

/// The parameter panel of `node` over `model`, headless.
fn panel(model: EditorModel, node: &'static str) -> Harness<'static, (EditorModel, PanelState)> {
    Harness::new_ui_state(
        move |ui, (model, panel): &mut (EditorModel, PanelState)| {
            param_panel(ui, model, node, panel);
        },
        (model, PanelState::default()),
    )
}

#[test]
fn choice_widget_changes_the_document() {
    let mut harness = panel(demo(), "scene");
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
    let mut harness = panel(demo(), "save_color");
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
    // an output file outside the output folder: absolute (a relative one
    // is joined onto the output folder)
    let want = std::fs::canonicalize("src")
        .expect("src")
        .join("main.rs")
        .display()
        .to_string();
    assert_eq!(
        model.param_value("save_color", "path"),
        Ok(ParamValue::Text(want))
    );
    assert!(panel.browse.is_none(), "the browser closes after a pick");
}

/// A list field shows a value changed elsewhere (a drag on the preview
/// sets `target_pixel`), and focusing it and pressing Enter without typing
/// keeps that value: it wrote back the copy it took when first shown,
/// undoing the drag.
#[test]
fn a_list_field_never_writes_back_a_stale_copy() {
    let mut harness = panel(load("copy_paste.ron"), "paste");
    harness.run();
    let moved = ParamValue::Points(vec![[70.5, 150.5]]);
    harness
        .state_mut()
        .0
        .set_param("paste", "target_pixel", moved.clone())
        .expect("move");
    harness.run();
    assert_eq!(
        harness.get_by_label("target_pixel").value(),
        Some(moved.to_ron())
    );
    harness.get_by_label("target_pixel").focus();
    harness.run();
    harness.key_press(eframe::egui::Key::Enter);
    harness.run();
    assert_eq!(
        harness.state().0.param_value("paste", "target_pixel"),
        Ok(moved)
    );
}

/// A path is applied when its field is left (Enter), not at every
/// keystroke: each keystroke re-ran the preview, and a previewed sink
/// wrote a file under every partial name.
#[test]
fn a_path_is_applied_once_when_its_field_is_left() {
    let mut harness = panel(demo(), "save_color");
    harness.run();
    let before = harness.state().0.param_value("save_color", "path");
    let revision = harness.state().0.revision();
    harness.get_by_label("path").focus();
    harness.run();
    harness.get_by_label("path").type_text("xyz");
    harness.run();
    assert_eq!(harness.state().0.param_value("save_color", "path"), before);
    assert_eq!(harness.state().0.revision(), revision);
    harness.key_press(eframe::egui::Key::Enter);
    harness.run();
    let after = harness.state().0.param_value("save_color", "path");
    match after {
        Ok(ParamValue::Text(t)) => assert!(t.contains("xyz"), "{t}"),
        other => panic!("path not applied: {other:?}"),
    }
    // one edit, one undo step
    assert!(harness.state_mut().0.undo());
    assert_eq!(harness.state().0.param_value("save_color", "path"), before);
    // Escape drops what was typed
    harness.get_by_label("path").focus();
    harness.run();
    harness.get_by_label("path").type_text("abc");
    harness.run();
    harness.key_press(eframe::egui::Key::Escape);
    harness.run();
    assert_eq!(harness.state().0.param_value("save_color", "path"), before);
    assert_eq!(
        harness.get_by_label("path").value(),
        before.clone().ok().map(|v| match v {
            ParamValue::Text(t) => t,
            other => other.to_ron(),
        })
    );
}
