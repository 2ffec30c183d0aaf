use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use depthgraph_editor::{EditorModel, Evaluator};
use depthgraph_graph::prelude::*;

fn demo_path() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../graphs/demo.ron")
}

fn demo() -> EditorModel {
    let reg = match depthgraph_nodes::registry() {
        Ok(r) => Arc::new(r),
        Err(e) => panic!("registry: {e}"),
    };
    match EditorModel::load(&demo_path(), reg) {
        Ok(m) => m,
        Err(e) => panic!("load demo: {e}"),
    }
}

fn small(m: &mut EditorModel) {
    assert_eq!(m.set_param("scene", "width", ParamValue::Int(48)), Ok(()));
    assert_eq!(m.set_param("scene", "height", ParamValue::Int(32)), Ok(()));
}

#[test]
fn downstream_change_reruns_only_descendants() {
    let mut m = demo();
    small(&mut m);
    let out = std::env::temp_dir().join(format!("depthgraph-editor-test-{}", std::process::id()));
    let mut ev = match Evaluator::new(EngineOptions::default(), out.clone()) {
        Ok(e) => e,
        Err(e) => panic!("{e}"),
    };
    // Request the non-sink leaf: `points` (sinks always run, they write files).
    let targets = vec!["points".to_string()];
    let p = m
        .pipeline_for(Some(&targets))
        .unwrap_or_else(|e| panic!("{e:?}"));
    ev.start(p, vec![]);
    let first = ev
        .wait(Duration::from_secs(120))
        .expect("first run finished");
    let (trace, values) = first.result.expect("first run ok");
    assert_eq!(trace.get("scene").map(|r| r.status), Some(Status::Ran));
    assert!(
        values.keys().any(|k| k.starts_with("points.")),
        "{values:?}"
    );

    // Change a parameter of `kinect` (downstream of `scene`).
    assert_eq!(m.set_param("kinect", "seed", ParamValue::Int(7)), Ok(()));
    let p = m
        .pipeline_for(Some(&targets))
        .unwrap_or_else(|e| panic!("{e:?}"));
    let kinect = p.index_of("kinect").expect("kinect");
    let mut expected: Vec<String> = p
        .downstream_of(kinect)
        .into_iter()
        .map(|i| p.nodes[i].name.clone())
        .filter(|n| n == "kinect" || n == "points")
        .collect();
    expected.sort();
    ev.start(p, vec![]);
    let second = ev
        .wait(Duration::from_secs(120))
        .expect("second run finished");
    let (trace, _) = second.result.expect("second run ok");
    let mut ran: Vec<String> = trace
        .nodes
        .iter()
        .filter(|r| matches!(r.status, Status::Ran | Status::Passthrough))
        .map(|r| r.node.clone())
        .collect();
    ran.sort();
    assert_eq!(ran, expected, "trace:\n{}", trace.table());
    assert_eq!(ran, vec!["kinect".to_string(), "points".to_string()]);
    assert_eq!(trace.get("scene").map(|r| r.status), Some(Status::Cached));
    let _ = std::fs::remove_dir_all(out);
}

#[test]
fn depth_into_color_is_refused_naming_both_types() {
    let mut m = demo();
    let before = m.to_ron();
    // save_color.color is a Color input; scene.depth is a Depth output.
    let err = m
        .try_connect("scene", "depth", "save_color", "color")
        .expect_err("Depth into Color must be refused");
    assert!(err.contains("Depth"), "{err}");
    assert!(err.contains("Color"), "{err}");
    assert_eq!(m.to_ron(), before);
    assert!(!m.can_undo());
    // A compatible wire is accepted.
    assert_eq!(
        m.try_connect("kinect", "depth", "save_depth_gt", "depth"),
        Ok(())
    );
    assert_eq!(
        m.input_source("save_depth_gt", "depth"),
        Some(("kinect".into(), "depth".into()))
    );
}

#[test]
fn bad_params_are_refused_with_names() {
    let mut m = demo();
    let err = m
        .set_param("scene", "width", ParamValue::Int(0))
        .expect_err("out of range");
    assert!(err.contains("scene") && err.contains("width"), "{err}");
    let err = m
        .set_param("scene", "width", ParamValue::Text("big".into()))
        .expect_err("wrong type");
    assert!(err.contains("width"), "{err}");
    let err = m
        .set_param("scene", "nope", ParamValue::Int(1))
        .expect_err("unknown param");
    assert!(err.contains("nope"), "{err}");
    assert!(!m.can_undo());
}

#[test]
fn save_load_round_trip() {
    let mut m = demo();
    small(&mut m);
    let added = m.add_node("Unproject").expect("add node");
    m.set_position(&added, [12.5, -3.0]);
    let text = m.to_ron();
    let reg = Arc::clone(m.registry());
    let again = EditorModel::from_text(&text, "saved.ron", reg).expect("reload");
    // Same nodes, kinds, params, inputs, outputs and positions.
    assert_eq!(again.to_ron(), text);
    assert_eq!(again.positions(), m.positions());
    let a = m.document();
    let b = again.document();
    assert_eq!(a.nodes.len(), b.nodes.len());
    for (x, y) in a.nodes.iter().zip(&b.nodes) {
        assert_eq!(x.name.value, y.name.value);
        assert_eq!(x.kind.value, y.kind.value);
        let px: Vec<_> = x.params.iter().map(|(k, v)| (&k.value, &v.value)).collect();
        let py: Vec<_> = y.params.iter().map(|(k, v)| (&k.value, &v.value)).collect();
        assert_eq!(px, py);
        let ix: Vec<_> = x.inputs.iter().map(|(k, v)| (&k.value, &v.value)).collect();
        let iy: Vec<_> = y.inputs.iter().map(|(k, v)| (&k.value, &v.value)).collect();
        assert_eq!(ix, iy);
    }
    // Human readable: every node starts on its own line.
    for n in m.node_names() {
        assert!(
            text.lines().any(|l| l.trim() == format!("\"{n}\": (")),
            "node {n} not on its own line:\n{text}"
        );
    }
    assert!(text.contains("layout: {"));
    // The file path round trip too.
    let path =
        std::env::temp_dir().join(format!("depthgraph-editor-rt-{}.ron", std::process::id()));
    m.save(&path).expect("save");
    let loaded = EditorModel::load(&path, Arc::clone(m.registry())).expect("load");
    assert_eq!(loaded.to_ron(), text);
    let _ = std::fs::remove_file(path);
}

#[test]
fn undo_redo_restores() {
    let mut m = demo();
    let original = m.to_ron();
    m.set_param("kinect", "seed", ParamValue::Int(9))
        .expect("set");
    let after_set = m.to_ron();
    m.disconnect("points", "color").expect("disconnect");
    m.remove_node("save_points").expect("remove");
    let after_all = m.to_ron();
    assert!(m.undo());
    assert!(m.undo());
    assert_eq!(m.to_ron(), after_set);
    assert!(m.undo());
    assert_eq!(m.to_ron(), original);
    assert!(!m.undo());
    assert!(m.redo());
    assert_eq!(m.to_ron(), after_set);
    assert!(m.redo() && m.redo());
    assert_eq!(m.to_ron(), after_all);
    assert!(!m.redo());
}

#[test]
fn auto_layout_columns_follow_longest_path() {
    let m = demo();
    let p = m.positions();
    let col = |n: &str| p.get(n).map(|x| x[0]);
    assert_eq!(col("scene"), Some(0.0));
    assert!(col("kinect") > col("scene"));
    assert!(col("points") > col("kinect"));
    assert!(col("save_points") > col("points"));
    assert!(m.check().is_ok());
}

#[test]
fn a_gesture_is_one_undoable_edit() {
    let mut m = demo();
    let before = m.to_ron();
    let undo_depth_before = m.can_undo();
    assert!(!undo_depth_before);
    m.begin_gesture();
    assert!(m.in_gesture());
    for k in 1..=5 {
        m.set_param("kinect", "noise_k", ParamValue::Float(0.001 * f64::from(k)))
            .expect("noise_k");
    }
    m.end_gesture();
    assert!(!m.in_gesture());
    let after = m.to_ron();
    assert_ne!(before, after);
    assert!(m.undo(), "the gesture is undoable");
    assert_eq!(m.to_ron(), before, "one undo takes the whole gesture back");
    assert!(!m.can_undo(), "the five steps made one edit");
    assert!(m.redo());
    assert_eq!(m.to_ron(), after);
    // Outside a gesture every change is its own edit again.
    m.set_param("kinect", "noise_k", ParamValue::Float(0.01))
        .expect("noise_k");
    m.set_param("kinect", "noise_k", ParamValue::Float(0.02))
        .expect("noise_k");
    assert!(m.undo() && m.undo());
    assert_eq!(m.to_ron(), after);
}

#[test]
fn the_automatic_layout_keeps_wires_shorter_than_file_order_on_every_graph() {
    use depthgraph_editor::layout::{LayoutParams, wire_length};
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../graphs");
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .expect("graphs/")
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "ron"))
        .collect();
    files.sort();
    assert!(files.len() >= 5, "{files:?}");
    let reg = Arc::new(depthgraph_nodes::registry().expect("registry"));
    let (mut total_naive, mut total_good) = (0.0, 0.0);
    for f in &files {
        let m = EditorModel::load(f, reg.clone()).expect("load");
        let names = m.node_names();
        let idx = |n: &str| names.iter().position(|x| x == n);
        let mut edges = Vec::new();
        for d in &m.document().nodes {
            let Some(to) = idx(&d.name.value) else {
                continue;
            };
            let Ok(imp) = m.node_impl(&d.name.value) else {
                continue;
            };
            for p in &imp.schema().inputs {
                if let Some((src, _)) = m.input_source(&d.name.value, p.name)
                    && let Some(from) = idx(&src)
                {
                    edges.push((from, to));
                }
            }
        }
        let heights: Vec<f64> = names
            .iter()
            .map(|n| {
                let imp = m.node_impl(n).expect("kind");
                let s = imp.schema();
                depthgraph_editor::layout::node_height(s.inputs.len().max(s.outputs.len()))
            })
            .collect();
        let as_vec = |l: &std::collections::BTreeMap<String, [f64; 2]>| {
            names.iter().map(|n| l[n]).collect::<Vec<_>>()
        };
        let naive = as_vec(&m.layout_with(Some(&LayoutParams {
            sweeps: 0,
            align: false,
        })));
        let good = as_vec(&m.auto_layout());
        let (ln, lg) = (
            wire_length(&naive, &edges, &heights),
            wire_length(&good, &edges, &heights),
        );
        assert!(
            lg <= ln + 1e-6,
            "{}: wire length {lg} with the layout, {ln} in file order",
            f.display()
        );
        total_naive += ln;
        total_good += lg;
    }
    eprintln!(
        "wire length over all graphs: {total_good:.0} laid out, {total_naive:.0} in file order"
    );
    assert!(
        total_good < 0.9 * total_naive,
        "over all graphs: {total_good} against {total_naive} in file order"
    );
}

#[test]
fn queued_requests_let_the_run_in_flight_finish_and_the_newest_win() {
    let mut m = demo();
    let out = std::env::temp_dir().join(format!("depthgraph-editor-queue-{}", std::process::id()));
    let targets = vec!["kinect".to_string()];
    let run = |queued: bool, m: &mut EditorModel| {
        let mut ev = Evaluator::new(EngineOptions::default(), out.clone()).expect("evaluator");
        let mut gens = Vec::new();
        for seed in 1..=3 {
            m.set_param("kinect", "seed", ParamValue::Int(seed))
                .expect("seed");
            let p = m.pipeline_for(Some(&targets)).expect("pipeline");
            gens.push(if queued {
                ev.start_queued(p, vec![])
            } else {
                ev.start(p, vec![])
            });
        }
        let mut seen = Vec::new();
        let deadline = std::time::Instant::now() + Duration::from_secs(120);
        while ev.pending() {
            if let Some(o) = ev.poll() {
                seen.push((o.generation, o.result.is_ok(), o.cancelled));
            }
            assert!(std::time::Instant::now() < deadline, "no result in 120 s");
            std::thread::sleep(Duration::from_millis(1));
        }
        (gens, seen)
    };
    // Queued (a drag): the run in flight goes to its end and is shown, a
    // waiting one is replaced, the newest is shown last; nothing is cancelled.
    let (gens, seen) = run(true, &mut m);
    assert_eq!(gens, vec![1, 2, 3]);
    assert_eq!(seen.last(), Some(&(3, true, false)), "{seen:?}");
    assert!(seen.iter().all(|s| s.1 && !s.2), "{seen:?}");
    assert!(seen.windows(2).all(|w| w[0].0 < w[1].0), "{seen:?}");
    // Started (a typed value): older runs are cancelled and never shown.
    let (_, seen) = run(false, &mut m);
    assert_eq!(seen, vec![(3, true, false)]);
}

/// The model knows whether it holds unsaved changes: an edit makes it
/// modified, undoing back to the file's state or saving clears it, and a
/// node position equal to the stored one at the canvas's f32 precision
/// neither counts nor rewrites the file's number.
#[test]
fn unsaved_changes_are_tracked() {
    let mut m = demo();
    assert!(!m.is_modified());
    m.set_param("kinect", "seed", ParamValue::Int(9))
        .expect("set");
    assert!(m.is_modified());
    assert!(m.undo());
    assert!(!m.is_modified());
    // a value set back to what the file says is no change
    m.set_param("kinect", "seed", ParamValue::Int(9))
        .expect("set");
    let original = demo().param_value("kinect", "seed").expect("seed");
    m.set_param("kinect", "seed", original).expect("set back");
    assert!(!m.is_modified());
    let [x, y] = m.positions()["scene"];
    m.set_position("scene", [x + 10.0, y]);
    assert!(m.is_modified());
    let dir = std::env::temp_dir().join(format!("depthgraph-editor-dirty-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("dir");
    let path = dir.join("p.ron");
    m.save(&path).expect("save");
    assert!(!m.is_modified());
    // a layout number f32 cannot hold: what the canvas hands back for it
    // each frame (its f32) changes neither the model nor the file
    let text = std::fs::read_to_string(&path).expect("read");
    let text = text.replace(
        &format!("\"scene\": ({:?}, {y:?})", x + 10.0),
        &format!("\"scene\": (10.3, {y:?})"),
    );
    assert!(text.contains("(10.3, "), "{text}");
    std::fs::write(&path, &text).expect("write");
    let mut m = EditorModel::load(&path, Arc::clone(m.registry())).expect("load");
    m.set_position("scene", [f64::from(10.3f32), f64::from(y as f32)]);
    assert_eq!(m.positions()["scene"], [10.3, y]);
    assert!(!m.is_modified());
    assert!(m.to_ron().contains("(10.3, "));
    let _ = std::fs::remove_dir_all(dir);
}

/// Save replaces the file whole through a temporary file beside it (none
/// left behind); a first save of a new document never replaces a file
/// that appeared at its name; the file's comments survive a save.
#[test]
fn saving_replaces_whole_files_keeps_comments_and_never_clobbers_new_names() {
    let dir = std::env::temp_dir().join(format!("depthgraph-editor-save-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("dir");
    let source = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../graphs/refocus.ron");
    let reg = Arc::new(depthgraph_nodes::registry().expect("registry"));
    let mut m = EditorModel::load(&source, Arc::clone(&reg)).expect("load");
    let path = dir.join("refocus.ron");
    std::fs::write(
        &path,
        "an older, longer text that must be replaced whole ".repeat(400),
    )
    .expect("old file");
    m.set_param("refocus", "f_number", ParamValue::Float(4.0))
        .expect("set");
    m.save(&path).expect("save");
    let text = std::fs::read_to_string(&path).expect("read");
    assert_eq!(text, m.to_ron());
    let names: Vec<String> = std::fs::read_dir(&dir)
        .expect("list")
        .map(|e| e.expect("entry").file_name().to_string_lossy().into_owned())
        .collect();
    assert_eq!(
        names,
        vec!["refocus.ron".to_string()],
        "temporary files left"
    );
    // every comment line of the original is in the saved file
    let original = std::fs::read_to_string(&source).expect("read source");
    for line in original
        .lines()
        .filter(|l| l.trim_start().starts_with("//"))
    {
        assert!(text.contains(line.trim()), "comment lost: {line}\n{text}");
    }
    let reloaded = EditorModel::load(&path, Arc::clone(&reg)).expect("reload");
    assert_eq!(
        reloaded.param_value("refocus", "f_number"),
        Ok(ParamValue::Float(4.0))
    );
    // a new document's name taken meanwhile: not written
    let taken = dir.join("untitled.ron");
    std::fs::write(&taken, "someone else's").expect("taken");
    let mut fresh =
        EditorModel::from_text("(version: 1, nodes: {})", "untitled.ron", reg).expect("fresh");
    fresh.add_node("SyntheticScene").expect("add");
    assert_eq!(fresh.save_new(&taken), Ok(false));
    assert_eq!(
        std::fs::read_to_string(&taken).expect("read"),
        "someone else's"
    );
    assert!(fresh.is_modified());
    let free = dir.join("untitled-1.ron");
    assert_eq!(fresh.save_new(&free), Ok(true));
    assert!(!fresh.is_modified());
    assert_eq!(
        std::fs::read_to_string(&free).expect("read"),
        fresh.to_ron()
    );
    let _ = std::fs::remove_dir_all(dir);
}
