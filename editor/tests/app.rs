//! Headless test of the whole editor (egui_kittest, no window): a parameter
//! changed through the UI re-runs exactly the nodes downstream of it, and the
//! preview picture changes.

use std::path::PathBuf;
use std::sync::Arc;

use depthgraph_editor::EditorModel;
use depthgraph_editor::app::EditorApp;
use depthgraph_graph::prelude::*;
use egui_kittest::Harness;
use egui_kittest::kittest::Queryable;

mod common;
use common::settle;

fn small_demo() -> EditorApp {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../graphs/demo.ron");
    let reg = Arc::new(depthgraph_nodes::registry().expect("registry"));
    let mut m = EditorModel::load(&path, reg).expect("load demo");
    m.set_param("scene", "width", ParamValue::Int(160))
        .expect("width");
    m.set_param("scene", "height", ParamValue::Int(120))
        .expect("height");
    EditorApp::new(m, path)
}

#[test]
fn ui_tweak_reruns_only_downstream_and_changes_the_preview() {
    let mut app = small_demo();
    app.select("kinect");
    let mut h = Harness::builder()
        .with_size(eframe::egui::vec2(1200.0, 800.0))
        .build_ui_state(|ui, app: &mut EditorApp| app.show(ui), app);
    settle(&mut h);
    let first = h.state().preview_fingerprint();
    let t = h.state().trace().expect("a trace");
    assert_eq!(t.get("scene").map(|r| r.status), Some(Status::Ran));
    assert_eq!(t.get("kinect").map(|r| r.status), Some(Status::Ran));

    // Toggle the Kinect's dropouts through its generated checkbox.
    h.get_by_label("dropouts").click();
    h.run_steps(2);
    settle(&mut h);
    let t = h.state().trace().expect("a trace");
    assert_eq!(
        t.get("scene").map(|r| r.status),
        Some(Status::Cached),
        "upstream of the change is cached"
    );
    assert_eq!(
        t.get("kinect").map(|r| r.status),
        Some(Status::Ran),
        "the changed node re-ran"
    );
    // Nodes that are not upstream of the preview are not run at all.
    for n in ["points", "save_color", "save_points"] {
        assert_ne!(t.get(n).map(|r| r.status), Some(Status::Ran), "{n}");
    }
    let second = h.state().preview_fingerprint();
    assert!(second.is_some() && second != first, "the preview changed");
    assert_eq!(
        h.state().model.param_value("kinect", "dropouts"),
        Ok(ParamValue::Bool(false))
    );
}

#[test]
fn lasso_is_drawn_by_clicking_on_the_preview() {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../graphs/copy_paste.ron");
    let reg = Arc::new(depthgraph_nodes::registry().expect("registry"));
    let mut m = EditorModel::load(&path, reg).expect("load copy_paste");
    m.set_param("lasso", "clicks", ParamValue::Points(Vec::new()))
        .expect("clear clicks");
    let mut app = EditorApp::new(m, path);
    app.select("lasso");
    let mut h = Harness::builder()
        .with_size(eframe::egui::vec2(1200.0, 900.0))
        .build_ui_state(|ui, app: &mut EditorApp| app.show(ui), app);
    settle(&mut h);
    // The checkered sphere of the 320x240 tabletop: centre (217, 166), radius ~38 px.
    let (cx, cy, r) = (217.0f64, 166.0f64, 40.0f64);
    let n = 8;
    for k in 0..=n {
        let frame = h.state().preview_frame().expect("the preview is on screen");
        let a = std::f64::consts::TAU * f64::from(k) / f64::from(n);
        let px = [cx + r * a.cos(), cy + r * a.sin()];
        let pos = frame.to_screen(px);
        // The ninth click (k = n) is taken back with the right button.
        let buttons: &[eframe::egui::PointerButton] = if k < n {
            &[eframe::egui::PointerButton::Primary]
        } else {
            &[
                eframe::egui::PointerButton::Primary,
                eframe::egui::PointerButton::Secondary,
            ]
        };
        for &button in buttons {
            h.hover_at(pos);
            for pressed in [true, false] {
                h.event(eframe::egui::Event::PointerButton {
                    pos,
                    button,
                    pressed,
                    modifiers: eframe::egui::Modifiers::default(),
                });
            }
            h.run_steps(2);
        }
        settle(&mut h);
    }
    let clicks = match h.state().model.param_value("lasso", "clicks") {
        Ok(ParamValue::Points(p)) => p,
        other => panic!("clicks: {other:?}"),
    };
    assert_eq!(
        clicks.len(),
        n as usize,
        "8 clicks kept, the 9th taken back"
    );
    for (k, c) in clicks.iter().enumerate() {
        let a = std::f64::consts::TAU * k as f64 / f64::from(n);
        let want = [cx + r * a.cos(), cy + r * a.sin()];
        assert!(
            (c[0] - want[0]).abs() < 1.0 && (c[1] - want[1]).abs() < 1.0,
            "click {k}: {c:?}, expected {want:?}"
        );
    }
    let Some(Value::Mask(mask)) = h.state().value("lasso.mask") else {
        panic!("the lasso's mask was evaluated");
    };
    assert_eq!(*mask.get(217, 166), 1.0, "the sphere's centre is selected");
    assert_eq!(*mask.get(20, 20), 0.0, "the far corner is not");
    let area: f32 = mask.as_slice().iter().sum();
    let disc = std::f32::consts::PI * 38.0 * 38.0;
    assert!(
        area > 0.7 * disc && area < 1.3 * disc,
        "mask area {area} px against the sphere's {disc:.0}"
    );
}

/// Closing the window with unsaved changes asks first (the edits were
/// lost without a word); "Close without saving" then lets it close, and a
/// document without changes closes at once.
#[test]
fn closing_with_unsaved_changes_asks_first() {
    let mut app = small_demo();
    assert!(app.model.is_modified());
    assert!(app.window_title().ends_with('*'));
    assert!(!app.request_close(), "closed with unsaved changes");
    let mut h = Harness::builder()
        .with_size(eframe::egui::vec2(1200.0, 800.0))
        .build_ui_state(|ui, app: &mut EditorApp| app.show(ui), app);
    h.run_steps(3);
    assert!(!h.state().close_allowed());
    h.get_by_label("Close without saving").click();
    h.run_steps(2);
    assert!(h.state().close_allowed());
    assert!(h.state_mut().request_close());

    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../graphs/demo.ron");
    let reg = Arc::new(depthgraph_nodes::registry().expect("registry"));
    let mut clean = EditorApp::new(EditorModel::load(&path, reg).expect("load"), path);
    assert!(!clean.window_title().ends_with('*'));
    assert!(clean.request_close());
}

/// The lasso's "Clear clicks" works while no picture is shown yet (the
/// first run still computing): the click was dropped before the preview
/// returned early.
#[test]
fn lasso_buttons_work_before_the_picture_arrives() {
    let path = common::graph_path("copy_paste.ron");
    let mut app = EditorApp::new(common::load("copy_paste.ron"), path);
    app.select("lasso");
    let mut h = Harness::builder()
        .with_size(eframe::egui::vec2(1200.0, 800.0))
        .build_ui_state(|ui, app: &mut EditorApp| app.show(ui), app);
    h.step();
    assert!(
        h.state().preview_fingerprint().is_none(),
        "a picture already"
    );
    h.get_by_label("Clear clicks").click();
    h.step();
    assert_eq!(
        h.state().model.param_value("lasso", "clicks"),
        Ok(ParamValue::Points(Vec::new()))
    );
}
