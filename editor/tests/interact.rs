//! Headless tests of editing as the papers' users do (egui_kittest, no
//! window): dragging the pasted object on a preview, clicking a refocused
//! picture to focus, and cancelling a slow run.

use std::time::{Duration, Instant};

use depthgraph_editor::EditorModel;
use depthgraph_editor::app::EditorApp;
use depthgraph_editor::placement::{ObjectView, object_view, on_object};
use depthgraph_editor::preview::ImageFrame;
use depthgraph_graph::prelude::*;
use eframe::egui::{self, Event, Modifiers, PointerButton};
use egui_kittest::Harness;
use egui_kittest::kittest::Queryable;

mod common;
use common::{graph_path, load, settle};

fn harness(app: EditorApp) -> Harness<'static, EditorApp> {
    Harness::builder()
        .with_size(egui::vec2(1400.0, 1400.0))
        .build_ui_state(|ui, app: &mut EditorApp| app.show(ui), app)
}

/// An editor on `m` (read from `graphs/<file>`) with `select` previewed,
/// once its first result is shown.
fn open(m: EditorModel, file: &str, select: &str) -> Harness<'static, EditorApp> {
    let mut app = EditorApp::new(m, graph_path(file));
    app.select(select);
    let mut h = harness(app);
    settle(&mut h);
    h
}

/// A float parameter's current value.
fn float(h: &Harness<'_, EditorApp>, node: &str, param: &str) -> f64 {
    match h.state().model.param_value(node, param) {
        Ok(ParamValue::Float(v)) => v,
        other => panic!("{node}.{param}: {other:?}"),
    }
}

fn button(h: &Harness<'_, EditorApp>, pos: egui::Pos2, pressed: bool) {
    h.event(Event::PointerButton {
        pos,
        button: PointerButton::Primary,
        pressed,
        modifiers: Modifiers::default(),
    });
}

/// A primary-button drag from `from` to `to` in `steps` pointer moves.
fn drag(h: &mut Harness<'_, EditorApp>, from: egui::Pos2, to: egui::Pos2, steps: usize) {
    h.hover_at(from);
    h.run_steps(1);
    button(h, from, true);
    h.run_steps(1);
    for k in 1..=steps {
        h.hover_at(from + (to - from) * (k as f32 / steps as f32));
        h.run_steps(1);
    }
    button(h, to, false);
    h.run_steps(2);
}

/// The pasted object in the preview (`Paste.mask`) and the picture's frame.
fn object_on_screen(h: &Harness<'_, EditorApp>) -> (ObjectView, ImageFrame) {
    let Some(Value::Mask(mask)) = h.state().value("paste.mask") else {
        panic!("the Paste mask is evaluated with a preview downstream of it");
    };
    let view = object_view(mask).expect("the object is in the picture");
    let frame = h.state().preview_frame().expect("the preview is on screen");
    (view, frame)
}

#[test]
fn dragging_the_pasted_object_moves_its_target_pixel_and_reruns_only_downstream() {
    let mut m = load("copy_paste_relit.ron");
    m.set_param("vpl", "count", ParamValue::Int(16))
        .expect("vpls");
    let start = match m.param_value("paste", "target_pixel") {
        Ok(ParamValue::Points(p)) => p[0],
        other => panic!("target_pixel: {other:?}"),
    };
    let mut h = open(m, "copy_paste_relit.ron", "relight");
    let Some(Value::Mask(mask)) = h.state().value("paste.mask").cloned() else {
        panic!("the Paste mask is evaluated with a preview downstream of it");
    };
    let view = object_view(&mask).expect("the object is in the picture");
    let grab = if on_object(&mask, view.centroid) {
        view.centroid
    } else {
        let (w, h) = mask.dims();
        let i = mask
            .as_slice()
            .iter()
            .position(|a| *a >= 0.5)
            .expect("a pixel");
        [(i % w) as f64 + 0.5, (i / w) as f64 + 0.5].map(|v| v.min((w.max(h)) as f64))
    };
    let frame = h.state().preview_frame().expect("the preview is on screen");
    let delta = [30.0, -10.0];
    let from = frame.to_screen(grab);
    let to = frame.to_screen([grab[0] + delta[0], grab[1] + delta[1]]);
    let undo_before = h.state().model.can_undo();
    drag(&mut h, from, to, 6);
    settle(&mut h);

    let got = match h.state().model.param_value("paste", "target_pixel") {
        Ok(ParamValue::Points(p)) => p[0],
        other => panic!("target_pixel: {other:?}"),
    };
    for a in 0..2 {
        assert!(
            (got[a] - (start[a] + delta[a])).abs() <= 1.0,
            "target pixel {got:?}, expected {start:?} + {delta:?}"
        );
    }
    let t = h.state().trace().expect("a trace");
    for n in ["source", "target", "edges", "lasso", "env", "vpl"] {
        let s = t.get(n).map(|r| r.status);
        assert!(
            matches!(s, Some(Status::Cached | Status::NotNeeded)),
            "{n} is upstream of the placement: cached or not needed, got {s:?}"
        );
    }
    for n in ["paste", "feather", "composite", "relight"] {
        assert_eq!(t.get(n).map(|r| r.status), Some(Status::Ran), "{n} re-ran");
    }
    let relight = t.get("relight").expect("relight's record");
    let scene = relight
        .derived
        .iter()
        .find(|d| d.name == "relight scene")
        .expect("the scene part is a derived value");
    assert_eq!(
        scene.status,
        Status::Cached,
        "the relighting's scene part stays cached"
    );
    let source = t
        .get("paste")
        .and_then(|r| r.derived.iter().find(|d| d.name == "paste source"))
        .expect("the paste's source part is a derived value");
    assert_eq!(
        source.status,
        Status::Cached,
        "the paste's source part stays cached"
    );
    // The whole drag is one undoable edit, and it is over.
    assert!(undo_before, "the VPL count edit is on the undo stack");
    assert!(!h.state().model.in_gesture(), "the drag's gesture ended");
    h.state_mut().model.undo();
    assert_eq!(
        h.state().model.param_value("paste", "target_pixel"),
        Ok(ParamValue::Points(vec![start])),
        "one undo takes the whole drag back"
    );
}

#[test]
fn a_click_on_the_refocus_preview_focuses_on_the_depth_under_the_pointer() {
    let mut m = load("refocus.ron");
    for n in ["scene", "tof_view"] {
        m.set_param(n, "width", ParamValue::Int(320))
            .expect("width");
        m.set_param(n, "height", ParamValue::Int(240))
            .expect("height");
    }
    for n in ["tof", "to_color"] {
        m.set_param(n, "width", ParamValue::Int(80)).expect("width");
        m.set_param(n, "height", ParamValue::Int(60))
            .expect("height");
    }
    m.set_param("refocus", "samples", ParamValue::Int(16))
        .expect("samples");
    let mut h = open(m, "refocus.ron", "refocus");
    let Some(Value::Depth(depth)) = h.state().value("fill.depth").cloned() else {
        panic!("the depth under the refocused picture is evaluated");
    };
    let (w, hh) = depth.dims();
    // A pixel on a flat stretch (its 5x5 window within 0.5 %) well away
    // from the current focus, searched from the centre outwards.
    let flat = |x: usize, y: usize| {
        let mut lo = f32::INFINITY;
        let mut hi = 0.0f32;
        for yy in y - 2..=y + 2 {
            for xx in x - 2..=x + 2 {
                let z = *depth.get(xx, yy);
                lo = lo.min(z);
                hi = hi.max(z);
            }
        }
        lo > 0.0 && hi < lo * 1.005
    };
    let mut pick = None;
    'search: for r in 0..(w.min(hh) / 2 - 3) {
        for (x, y) in [
            (w / 2 + r, hh / 2),
            (w / 2, hh / 2 + r),
            (w / 2 - r, hh / 2 - r / 2),
        ] {
            if flat(x, y) && (f64::from(*depth.get(x, y)) - 0.95).abs() > 0.1 {
                pick = Some((x, y));
                break 'search;
            }
        }
    }
    let (x, y) = pick.expect("a flat stretch of the tabletop");
    let want = f64::from(*depth.get(x, y));
    let frame = h.state().preview_frame().expect("the preview is on screen");
    let pos = frame.to_screen([x as f64 + 0.5, y as f64 + 0.5]);
    h.hover_at(pos);
    h.run_steps(1);
    button(&h, pos, true);
    button(&h, pos, false);
    h.run_steps(2);
    let got = float(&h, "refocus", "focus_m");
    assert!(
        (got - want).abs() <= 0.01 * want,
        "focus {got} m, depth under the pointer {want} m"
    );
    settle(&mut h);
    let t = h.state().trace().expect("a trace");
    assert_eq!(t.get("refocus").map(|r| r.status), Some(Status::Ran));
    assert_eq!(t.get("fill").map(|r| r.status), Some(Status::Cached));
}

#[test]
fn cancel_stops_the_running_node_and_its_status_says_so() {
    let m = load("refocus.ron");
    let mut app = EditorApp::new(m, graph_path("refocus.ron"));
    app.select("refocus");
    let mut h = harness(app);
    let deadline = Instant::now() + Duration::from_secs(120);
    // A node that has run for 50 ms already is a long one (NL-means,
    // refocus): the cancel lands inside it, not between two nodes.
    let long_running = |h: &Harness<'_, EditorApp>| {
        h.state()
            .running_nodes()
            .values()
            .any(|p| p.started.elapsed() >= Duration::from_millis(50))
    };
    while !long_running(&h) {
        h.step();
        assert!(Instant::now() < deadline, "no node ran 50 ms within 120 s");
        std::thread::sleep(Duration::from_millis(5));
    }
    // The node's progress bar and the preview's cancel button are shown.
    h.run_steps(1);
    let running: Vec<String> = h.state().running_nodes().keys().cloned().collect();
    assert!(!running.is_empty());
    h.get_by_label("cancel run").click();
    h.run_steps(1);
    let deadline = Instant::now() + Duration::from_secs(120);
    while h.state().busy() {
        h.step();
        assert!(
            Instant::now() < deadline,
            "the run did not stop within 120 s"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
    h.run_steps(2);
    let cancelled = h.state().cancelled_nodes().clone();
    assert!(
        !cancelled.is_empty(),
        "the nodes that were running are marked"
    );
    let err = h.state().run_error().unwrap_or_default().to_string();
    assert!(err.contains("cancelled"), "the run's status: {err}");
    assert!(
        h.state().value("refocus.color").is_none(),
        "the cancelled run produced no result"
    );
    assert!(
        h.state().trace().is_none(),
        "no node finished a run that was cancelled"
    );
}

#[test]
fn ctrl_wheel_scales_and_the_ring_turns_the_pasted_object_each_one_undo_step() {
    let m = load("copy_paste.ron");
    let scale0 = match m.param_value("paste", "scale") {
        Ok(ParamValue::Float(s)) => s,
        other => panic!("scale: {other:?}"),
    };
    let mut h = open(m, "copy_paste.ron", "composite");
    let (view, frame) = object_on_screen(&h);
    let centre = frame.to_screen(view.centroid);

    // Two wheel notches with Ctrl over the picture: scale x 1.1 x 1.1.
    h.hover_at(centre);
    h.run_steps(1);
    for _ in 0..2 {
        h.event(Event::Zoom(1.1));
        h.run_steps(1);
    }
    let deadline = Instant::now() + Duration::from_secs(30);
    while h.state().model.in_gesture() {
        h.step();
        assert!(Instant::now() < deadline, "the wheel gesture never ended");
        std::thread::sleep(Duration::from_millis(20));
    }
    let scale = float(&h, "paste", "scale");
    let want = scale0 * 1.1f64 * 1.1f64;
    assert!(
        (scale - want).abs() < 1e-6 * want,
        "scale {scale}, expected {want}"
    );
    settle(&mut h);

    // A drag on the ring to the right of the object: yaw follows the
    // horizontal motion at 0.5 degrees per screen point.
    let (view, frame) = object_on_screen(&h);
    let centre = frame.to_screen(view.centroid);
    let ring = view.radius as f32 * frame.scale() + 12.0;
    let from = centre + egui::vec2(ring, 0.0);
    let to = from + egui::vec2(40.0, 0.0);
    drag(&mut h, from, to, 4);
    let rot = match h.state().model.param_value("paste", "rotation_deg") {
        Ok(ParamValue::Vec3(r)) => r,
        other => panic!("rotation_deg: {other:?}"),
    };
    assert!((rot[0] - 20.0).abs() <= 0.5, "yaw {rot:?}, expected 20");
    assert!(rot[1].abs() <= 0.5 && rot[2] == 0.0, "{rot:?}");
    assert!(!h.state().model.in_gesture());
    settle(&mut h);

    // Each gesture is one undo step: turn back, then scale back.
    h.state_mut().model.undo();
    assert_eq!(
        h.state().model.param_value("paste", "rotation_deg"),
        Ok(ParamValue::Vec3([0.0, 0.0, 0.0]))
    );
    h.state_mut().model.undo();
    assert_eq!(
        h.state().model.param_value("paste", "scale"),
        Ok(ParamValue::Float(scale0))
    );
}
