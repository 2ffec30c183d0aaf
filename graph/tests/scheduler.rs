//! Scheduler behaviour with toy nodes that count their evaluations.

use std::sync::Arc;

use depthgraph_graph::node_params;
use depthgraph_graph::prelude::*;

node_params! {
    /// Source params.
    pub struct SourceParams {
        /// Image side.
        pub size: usize = 8usize, ParamKind::Int { min: 1, max: 4096 };
        /// Value offset.
        pub offset: f64 = 0.0, ParamKind::Float { min: -100.0, max: 100.0 };
    }
}
node_params! {
    /// Scale params.
    pub struct ScaleParams {
        /// Factor.
        pub factor: f64 = 1.0, ParamKind::Float { min: -100.0, max: 100.0 };
    }
}
node_params! {
    /// No params.
    pub struct NoParams {}
}

fn source(ctx: &EvalCtx, _: &Inputs, p: &SourceParams) -> Result<Outputs, NodeError> {
    ctx.progress(0.5);
    let img = DepthMap::from_fn(p.size, p.size, |x, y| {
        (x * 31 + y * 7) as f32 * 0.01 + p.offset as f32
    });
    Ok(Outputs::new().with("depth", img))
}
fn scale(_: &EvalCtx, i: &Inputs, p: &ScaleParams) -> Result<Outputs, NodeError> {
    let d = i.depth("depth")?;
    if p.factor == 1.0 {
        return Ok(Outputs::new()
            .with("depth", Value::Depth(d.clone()))
            .passthrough("factor is 1"));
    }
    Ok(Outputs::new().with("depth", d.map_same(|v| v * p.factor as f32)))
}
fn add(_: &EvalCtx, i: &Inputs, _: &NoParams) -> Result<Outputs, NodeError> {
    let a = i.depth("a")?;
    let b = i.depth("b")?;
    if !a.same_dims(b) {
        return Err(NodeError::input("b", "size differs from a"));
    }
    let v: Vec<f32> = a
        .as_slice()
        .iter()
        .zip(b.as_slice())
        .map(|(x, y)| x + y)
        .collect();
    Ok(Outputs::new().with("depth", DepthMap::from_vec(a.width(), a.height(), v)?))
}
fn wait_cancel(ctx: &EvalCtx, i: &Inputs, _: &NoParams) -> Result<Outputs, NodeError> {
    // A long node: checks cancellation between chunks of work.
    for _ in 0..1000 {
        ctx.check_cancelled()?;
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
    Ok(Outputs::new().with("depth", Value::Depth(i.depth("depth")?.clone())))
}

fn registry() -> Registry {
    let d = |n| PortSpec::required(n, ValueType::Depth, "depth");
    let o = || vec![PortSpec::output("depth", ValueType::Depth, "depth")];
    let mut r = Registry::new();
    r.register(TypedNode::new("Source", 1, "source", vec![], o(), source))
        .unwrap();
    r.register(TypedNode::new(
        "Scale",
        1,
        "scale",
        vec![d("depth")],
        o(),
        scale,
    ))
    .unwrap();
    r.register(TypedNode::new(
        "Add",
        1,
        "add",
        vec![d("a"), d("b")],
        o(),
        add,
    ))
    .unwrap();
    r.register(TypedNode::new(
        "Wait",
        1,
        "wait",
        vec![d("depth")],
        o(),
        wait_cancel,
    ))
    .unwrap();
    r
}

const DOC: &str = r#"(
    version: 1,
    nodes: {
        "src": (kind: "Source", params: (size: 16)),
        "left": (kind: "Scale", params: (factor: 2.0), inputs: (depth: "src.depth")),
        "right": (kind: "Scale", params: (factor: 3.0), inputs: (depth: "src.depth")),
        "sum": (kind: "Add", inputs: (a: "left.depth", b: "right.depth")),
        "unused": (kind: "Scale", inputs: (depth: "src.depth")),
    },
    outputs: ["sum.depth"],
)"#;

fn pipeline(sets: &[&str]) -> Pipeline {
    let mut doc = Document::parse(DOC, "doc.ron").unwrap();
    for s in sets {
        doc.apply_set(s).unwrap();
    }
    Pipeline::check(&doc, &registry()).unwrap()
}

fn status(t: &Trace, node: &str) -> Status {
    t.get(node).unwrap().status
}

#[test]
fn downstream_change_reruns_only_downstream_in_memory() {
    let engine = Engine::new(EngineOptions::default()).unwrap();
    let first = engine.run(&pipeline(&[]), &RunOptions::default()).unwrap();
    let mut ran = first.trace.evaluated();
    ran.sort();
    assert_eq!(ran, ["left", "right", "src", "sum"]);
    assert_eq!(status(&first.trace, "unused"), Status::NotNeeded);

    // Same pipeline again: the requested node is cached; upstream is not even looked at.
    let again = engine.run(&pipeline(&[]), &RunOptions::default()).unwrap();
    assert_eq!(status(&again.trace, "sum"), Status::Cached);
    assert!(again.trace.evaluated().is_empty());
    assert_eq!(status(&again.trace, "src"), Status::NotNeeded);

    // Change one branch's parameter: that branch and its consumer re-run.
    let changed = engine
        .run(&pipeline(&["left.factor=5"]), &RunOptions::default())
        .unwrap();
    let mut ran = changed.trace.evaluated();
    ran.sort();
    assert_eq!(ran, ["left", "sum"]);
    assert_eq!(status(&changed.trace, "right"), Status::Cached);
    assert_eq!(status(&changed.trace, "src"), Status::Cached);
    let Value::Depth(d) = &changed.outputs["sum.depth"] else {
        panic!()
    };
    let Value::Depth(d0) = &first.outputs["sum.depth"] else {
        panic!()
    };
    // (5 + 3) / (2 + 3) times the first result
    for (a, b) in d.as_slice().iter().zip(d0.as_slice()) {
        assert!((a - b * 8.0 / 5.0).abs() <= 1e-5 * b.abs().max(1.0));
    }
}

#[test]
fn upstream_change_reruns_everything_that_depends_on_it() {
    let engine = Engine::new(EngineOptions::default()).unwrap();
    engine.run(&pipeline(&[]), &RunOptions::default()).unwrap();
    let r = engine
        .run(&pipeline(&["src.offset=1.5"]), &RunOptions::default())
        .unwrap();
    let mut ran = r.trace.evaluated();
    ran.sort();
    assert_eq!(ran, ["left", "right", "src", "sum"]);
}

#[test]
fn disk_cache_survives_a_new_engine() {
    let dir = tempfile::tempdir().unwrap();
    let mk = || {
        Engine::new(EngineOptions {
            disk: Some(DiskCache::new(dir.path(), 1 << 30)),
            ..EngineOptions::default()
        })
        .unwrap()
    };
    let first = mk()
        .run(&pipeline(&["src.size=9"]), &RunOptions::default())
        .unwrap();
    assert_eq!(status(&first.trace, "src"), Status::Ran);
    // A fresh engine (as a second process would be) with a downstream change.
    let second = mk()
        .run(
            &pipeline(&["src.size=9", "right.factor=4"]),
            &RunOptions::default(),
        )
        .unwrap();
    let mut ran = second.trace.evaluated();
    ran.sort();
    assert_eq!(ran, ["right", "sum"]);
    assert_eq!(status(&second.trace, "left"), Status::Cached);
    assert_eq!(status(&second.trace, "src"), Status::Cached);
    assert_eq!(second.outputs.len(), 1);
}

#[test]
fn passthrough_is_recorded_with_reason_and_kept_when_cached() {
    let engine = Engine::new(EngineOptions::default()).unwrap();
    let r = engine
        .run(&pipeline(&["left.factor=1"]), &RunOptions::default())
        .unwrap();
    let rec = r.trace.get("left").unwrap();
    assert_eq!(rec.status, Status::Passthrough);
    assert_eq!(rec.reason.as_deref(), Some("factor is 1"));
    let r2 = engine
        .run(
            &pipeline(&["left.factor=1", "right.factor=7"]),
            &RunOptions::default(),
        )
        .unwrap();
    let rec = r2.trace.get("left").unwrap();
    assert_eq!(rec.status, Status::Cached);
    assert_eq!(rec.reason.as_deref(), Some("factor is 1"));
}

#[test]
fn one_and_two_threads_give_identical_bits() {
    let run = |threads| {
        let e = Engine::new(EngineOptions {
            threads,
            ..EngineOptions::default()
        })
        .unwrap();
        let r = e
            .run(&pipeline(&["src.size=64"]), &RunOptions::default())
            .unwrap();
        let Value::Depth(d) = &r.outputs["sum.depth"] else {
            panic!()
        };
        d.as_slice().iter().map(|v| v.to_bits()).collect::<Vec<_>>()
    };
    assert_eq!(run(1), run(2));
}

#[test]
fn cancellation_stops_a_long_node() {
    let text = r#"(version: 1, nodes: {
        "src": (kind: "Source"),
        "w": (kind: "Wait", inputs: (depth: "src.depth")),
    }, outputs: ["w.depth"])"#;
    let p = Pipeline::check(&Document::parse(text, "c.ron").unwrap(), &registry()).unwrap();
    let engine = Arc::new(Engine::new(EngineOptions::default()).unwrap());
    let opts = RunOptions::default();
    let cancel = opts.cancel.clone();
    let handle = {
        let engine = engine.clone();
        std::thread::spawn(move || engine.run(&p, &opts))
    };
    std::thread::sleep(std::time::Duration::from_millis(50));
    cancel.cancel();
    let r = handle.join().unwrap();
    assert!(matches!(r, Err(RunError::Cancelled)), "{r:?}");
}

#[test]
fn node_errors_name_the_node() {
    let text = r#"(version: 1, nodes: {
        "a": (kind: "Source", params: (size: 4)),
        "b": (kind: "Source", params: (size: 5)),
        "s": (kind: "Add", inputs: (a: "a.depth", b: "b.depth")),
    }, outputs: ["s"])"#;
    let p = Pipeline::check(&Document::parse(text, "e.ron").unwrap(), &registry()).unwrap();
    let e = Engine::new(EngineOptions::default())
        .unwrap()
        .run(&p, &RunOptions::default())
        .unwrap_err();
    assert_eq!(
        e.to_string(),
        "node `s` (Add): input `b`: size differs from a"
    );
}

#[test]
fn memory_budget_is_respected_across_runs() {
    let engine = Engine::new(EngineOptions {
        memory_budget_bytes: 3000,
        ..EngineOptions::default()
    })
    .unwrap();
    // each 16x16 depth is 1024 bytes; five results would need 5 KiB
    let r = engine.run(&pipeline(&[]), &RunOptions::default()).unwrap();
    assert_eq!(r.trace.get("sum").unwrap().bytes, 1024);
    let again = engine.run(&pipeline(&[]), &RunOptions::default()).unwrap();
    // the most recent result (sum) is still there
    assert_eq!(status(&again.trace, "sum"), Status::Cached);
}

#[test]
fn a_second_backend_is_chosen_at_run_time_with_the_same_cache_key() {
    fn scale_gpu(_: &EvalCtx, i: &Inputs, p: &ScaleParams) -> Result<Outputs, NodeError> {
        // stands in for a GPU implementation: same result, different backend
        Ok(Outputs::new().with("depth", i.depth("depth")?.map_same(|v| v * p.factor as f32)))
    }
    let d = |n| PortSpec::required(n, ValueType::Depth, "depth");
    let o = || vec![PortSpec::output("depth", ValueType::Depth, "depth")];
    let mut reg = registry();
    reg.register_backend(
        TypedNode::new("Scale", 1, "scale", vec![d("depth")], o(), scale_gpu).backend_name("wgpu"),
    )
    .unwrap();
    // a backend whose schema differs is refused: keys would not agree
    let other =
        TypedNode::new("Scale", 2, "scale", vec![d("depth")], o(), scale_gpu).backend_name("wgpu");
    assert!(reg.register_backend(other).is_err());
    let check =
        |reg: &Registry| Pipeline::check(&Document::parse(DOC, "doc.ron").unwrap(), reg).unwrap();
    let cpu = check(&reg);
    reg.prefer_backends(&["wgpu"]);
    let gpu = check(&reg);
    assert_eq!(cpu.nodes[1].node.backend(), "cpu");
    assert_eq!(gpu.nodes[1].node.backend(), "wgpu");
    assert_eq!(Engine::keys(&cpu), Engine::keys(&gpu));
    let engine = Engine::new(EngineOptions::default()).unwrap();
    let a = engine.run(&cpu, &RunOptions::default()).unwrap();
    engine.clear_memory();
    let b = engine.run(&gpu, &RunOptions::default()).unwrap();
    assert_eq!(b.trace.get("left").unwrap().backend, "wgpu");
    assert_eq!(a.outputs, b.outputs);
}

node_params! {
    /// A file reader's params.
    pub struct ReadParams {
        /// The file read.
        pub path: String = "", ParamKind::InputPath;
    }
}

/// Reads a number from a file, as a 1x1 depth map. A file holding 1 is
/// rewritten to 2 just before it is read: a writer that changes the file
/// between the run's keying and the load (a capture still being written).
fn read_number(_: &EvalCtx, _: &Inputs, p: &ReadParams) -> Result<Outputs, NodeError> {
    let io = |e| NodeError::io(&p.path, e);
    if std::fs::read_to_string(&p.path).map_err(io)?.trim() == "1" {
        std::fs::write(&p.path, "2").map_err(io)?;
    }
    let v: f32 = std::fs::read_to_string(&p.path)
        .map_err(io)?
        .trim()
        .parse()
        .map_err(|_| NodeError::param("path", "not a number"))?;
    Ok(Outputs::new().with("depth", DepthMap::filled(1, 1, v)))
}

/// A result from a file that changed during the run is used but not kept:
/// kept, it sat under the key of the contents before the change, and the
/// next run with those contents took it from the cache (2 where the file
/// says 1).
#[test]
fn a_file_changed_during_the_run_leaves_no_cache_entry() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("n.txt");
    let mut reg = Registry::new();
    reg.register(
        TypedNode::new(
            "ReadNumber",
            1,
            "reads a number",
            vec![],
            vec![PortSpec::output("depth", ValueType::Depth, "depth")],
            read_number,
        )
        .reads(|p: &ReadParams| vec![std::path::PathBuf::from(&p.path)]),
    )
    .unwrap();
    reg.register(TypedNode::new(
        "Scale",
        1,
        "scale",
        vec![PortSpec::required("depth", ValueType::Depth, "depth")],
        vec![PortSpec::output("depth", ValueType::Depth, "depth")],
        scale,
    ))
    .unwrap();
    let text = format!(
        "(version: 1, nodes: {{ \"n\": (kind: \"ReadNumber\", params: (path: {:?})), \
         \"s\": (kind: \"Scale\", params: (factor: 10.0), inputs: (depth: \"n.depth\")) }}, \
         outputs: [\"n.depth\", \"s.depth\"])",
        file.display().to_string()
    );
    let p = Pipeline::check(&Document::parse(&text, "doc.ron").unwrap(), &reg).unwrap();
    let engine = Engine::new(EngineOptions {
        disk: Some(DiskCache::new(dir.path().join("cache"), 1 << 30)),
        ..EngineOptions::default()
    })
    .unwrap();
    let value = |r: &RunResult| match r.outputs.get("n.depth") {
        Some(Value::Depth(d)) => *d.get(0, 0),
        _ => f32::NAN,
    };
    std::fs::write(&file, "1").unwrap();
    let first = engine.run(&p, &RunOptions::default()).unwrap();
    assert_eq!(value(&first), 2.0, "the run uses what it read");
    // the file says 1 again: not a cache hit of the 2 read under its key
    std::fs::write(&file, "1").unwrap();
    let second = engine.run(&p, &RunOptions::default()).unwrap();
    assert_eq!(status(&second.trace, "n"), Status::Ran);
    // nor is what was computed from it (its key names the contents 1)
    assert_eq!(status(&second.trace, "s"), Status::Ran);
    // a file that holds still is kept as ever
    std::fs::write(&file, "3").unwrap();
    engine.run(&p, &RunOptions::default()).unwrap();
    let fourth = engine.run(&p, &RunOptions::default()).unwrap();
    assert_eq!(status(&fourth.trace, "n"), Status::Cached);
    assert_eq!(status(&fourth.trace, "s"), Status::Cached);
    assert_eq!(value(&fourth), 3.0);
}

fn panics(_: &EvalCtx, _: &Inputs, _: &NoParams) -> Result<Outputs, NodeError> {
    let v: Vec<f32> = Vec::new();
    Ok(Outputs::new().with("depth", DepthMap::filled(1, 1, v[3])))
}

/// A node that panics (a bug) fails the run with an error naming it, and
/// the nodes that ran beside it keep their results in the cache.
#[test]
fn a_panicking_node_is_named_and_its_siblings_are_kept() {
    let mut reg = registry();
    reg.register(TypedNode::new(
        "Panics",
        1,
        "panics",
        vec![],
        vec![PortSpec::output("depth", ValueType::Depth, "depth")],
        panics,
    ))
    .unwrap();
    let text = r#"(version: 1, nodes: {
        "a": (kind: "Source"),
        "bad": (kind: "Panics"),
        "z": (kind: "Source", params: (offset: 1.0)),
        "sum": (kind: "Add", inputs: (a: "a.depth", b: "bad.depth")),
        "zz": (kind: "Scale", params: (factor: 2.0), inputs: (depth: "z.depth")),
    }, outputs: ["sum.depth", "zz.depth"])"#;
    let p = Pipeline::check(&Document::parse(text, "doc.ron").unwrap(), &reg).unwrap();
    let engine = Engine::new(EngineOptions::default()).unwrap();
    let e = engine.run(&p, &RunOptions::default()).unwrap_err();
    let msg = e.to_string();
    assert!(msg.contains("bad") && msg.contains("Panics"), "{msg}");
    assert!(
        msg.contains("panicked") && msg.contains("index out of bounds"),
        "{msg}"
    );
    // the siblings of the level ran and were kept
    let only_z = r#"(version: 1, nodes: {
        "a": (kind: "Source"),
        "z": (kind: "Source", params: (offset: 1.0)),
    }, outputs: ["a.depth", "z.depth"])"#;
    let q = Pipeline::check(&Document::parse(only_z, "doc.ron").unwrap(), &reg).unwrap();
    let r = engine.run(&q, &RunOptions::default()).unwrap();
    assert_eq!(status(&r.trace, "a"), Status::Cached);
    assert_eq!(status(&r.trace, "z"), Status::Cached);
}

/// What the probe nodes of the next test saw (a test's own record; nodes
/// of the library keep no state).
static SEEN: std::sync::Mutex<Vec<std::sync::Weak<DepthMap>>> = std::sync::Mutex::new(Vec::new());
static LIVE_AT_END: std::sync::atomic::AtomicUsize =
    std::sync::atomic::AtomicUsize::new(usize::MAX);

fn note(_: &EvalCtx, i: &Inputs, _: &NoParams) -> Result<Outputs, NodeError> {
    let d = i.depth("depth")?;
    SEEN.lock().unwrap().push(Arc::downgrade(d));
    Ok(Outputs::new().with("depth", d.map_same(|v| v * 2.0)))
}

fn count_live(_: &EvalCtx, i: &Inputs, _: &NoParams) -> Result<Outputs, NodeError> {
    let live = SEEN
        .lock()
        .unwrap()
        .iter()
        .filter(|w| w.upgrade().is_some())
        .count();
    LIVE_AT_END.store(live, std::sync::atomic::Ordering::SeqCst);
    Ok(Outputs::new().with("depth", Value::Depth(i.depth("depth")?.clone())))
}

/// A value no node still to run reads is let go during the run: when the
/// last node runs, the first node's value (read only by the second) is no
/// longer held (it was, with every other, until the run ended), while the
/// trace still reports its size.
#[test]
fn values_nobody_still_reads_are_let_go_during_the_run() {
    let mut reg = registry();
    let d = |n| PortSpec::required(n, ValueType::Depth, "depth");
    let o = || vec![PortSpec::output("depth", ValueType::Depth, "depth")];
    reg.register(TypedNode::new(
        "Note",
        1,
        "note",
        vec![d("depth")],
        o(),
        note,
    ))
    .unwrap();
    reg.register(TypedNode::new(
        "Live",
        1,
        "live",
        vec![d("depth")],
        o(),
        count_live,
    ))
    .unwrap();
    let text = r#"(version: 1, nodes: {
        "src": (kind: "Source", params: (size: 16)),
        "a": (kind: "Note", inputs: (depth: "src.depth")),
        "b": (kind: "Scale", params: (factor: 3.0), inputs: (depth: "a.depth")),
        "c": (kind: "Live", inputs: (depth: "b.depth")),
    }, outputs: ["c.depth"])"#;
    let p = Pipeline::check(&Document::parse(text, "doc.ron").unwrap(), &reg).unwrap();
    let engine = Engine::new(EngineOptions {
        memory_budget_bytes: 0,
        ..EngineOptions::default()
    })
    .unwrap();
    let r = engine.run(&p, &RunOptions::default()).unwrap();
    assert_eq!(SEEN.lock().unwrap().len(), 1);
    assert_eq!(LIVE_AT_END.load(std::sync::atomic::Ordering::SeqCst), 0);
    assert_eq!(r.trace.get("src").unwrap().bytes, 16 * 16 * 4);
    assert!(matches!(r.outputs.get("c.depth"), Some(Value::Depth(_))));
}
