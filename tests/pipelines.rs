//! Whole pipelines end to end: the shipped demo, the CLI across processes,
//! thread-count independence, and output safety.

use std::path::{Path, PathBuf};
use std::process::Command;

use depthgraph::graph::pipeline::OutputRef;
use depthgraph::graph::prelude::*;

fn graph(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("graphs")
        .join(name)
}

const SMALL: [&str; 2] = ["scene.width=160", "scene.height=120"];

fn cli(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_depthgraph"))
        .args(args)
        .output()
        .unwrap()
}

#[test]
fn demo_writes_every_output_and_they_read_back() {
    let out = tempfile::tempdir().unwrap();
    let cache = tempfile::tempdir().unwrap();
    let demo = graph("demo.ron");
    let mut args = vec![
        "run",
        demo.to_str().unwrap(),
        "--out",
        out.path().to_str().unwrap(),
    ];
    args.extend(["--cache-dir", cache.path().to_str().unwrap(), "--quiet"]);
    for s in &SMALL {
        args.extend(["--set", s]);
    }
    let r = cli(&args);
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    let d = out.path().join("demo");
    let color = depthgraph::nodes::io::load_color(
        &d.join("color.png"),
        depthgraph::nodes::io::ColorSpace::Srgb,
    )
    .unwrap();
    assert_eq!(color.dims(), (160, 120));
    let hdr = depthgraph::nodes::io::load_color(
        &d.join("color.exr"),
        depthgraph::nodes::io::ColorSpace::Linear,
    )
    .unwrap();
    // the 8-bit PNG is the sRGB encoding of the linear EXR (clipped at 1)
    for (a, b) in color.as_slice().iter().zip(hdr.as_slice()) {
        for c in 0..3 {
            assert!((a[c] - b[c].clamp(0.0, 1.0)).abs() < 0.01, "{a:?} vs {b:?}");
        }
    }
    let p = depthgraph::nodes::io::LoadDepthParams::default();
    let truth = depthgraph::nodes::io::load_depth(&d.join("depth_truth.exr"), &p).unwrap();
    let kinect = depthgraph::nodes::io::load_depth(&d.join("depth_kinect.png"), &p).unwrap();
    assert_eq!(truth.dims(), (160, 120));
    assert_eq!(
        truth.hole_count(),
        0,
        "the tabletop scene has no background hole"
    );
    assert!(
        kinect.hole_count() > 0,
        "the simulated Kinect must leave holes"
    );
    // where the Kinect measured, it agrees with the truth to a few percent
    let mut worst = 0.0f32;
    for (k, t) in kinect.as_slice().iter().zip(truth.as_slice()) {
        if *k > 0.0 {
            worst = worst.max((k - t).abs() / t);
        }
    }
    assert!(worst < 0.1, "worst relative error {worst}");
    let ply = std::fs::read(d.join("points.ply")).unwrap();
    let header = String::from_utf8_lossy(&ply[..200]);
    let valid = kinect.len() - kinect.hole_count();
    assert!(
        header.contains(&format!("element vertex {valid}")),
        "{header}"
    );
    assert!(d.join("depth_kinect_preview.png").exists());
}

/// `depthgraph run PIPE --no-cache --quiet --out OUT EXTRA...`.
fn run_uncached(pipe: &Path, out: &Path, extra: &[&str]) -> std::process::Output {
    let mut args = vec![
        "run",
        pipe.to_str().unwrap(),
        "--no-cache",
        "--quiet",
        "--out",
        out.to_str().unwrap(),
    ];
    args.extend(extra);
    cli(&args)
}

/// `depthgraph CMD graphs/demo.ron --quiet --out OUT`, at the small size, then `extra`.
fn demo_cli(cmd: &str, out: &Path, extra: &[&str]) -> std::process::Output {
    let demo = graph("demo.ron");
    let mut args = vec![cmd, demo.to_str().unwrap(), "--quiet"];
    args.extend(["--out", out.to_str().unwrap()]);
    for s in SMALL {
        args.extend(["--set", s]);
    }
    args.extend(extra);
    cli(&args)
}

fn explain(dir: &Path, cache: &Path, sets: &[&str]) -> Vec<serde_json::Value> {
    let mut extra = vec!["--json", "--cache-dir", cache.to_str().unwrap()];
    for s in sets {
        extra.extend(["--set", s]);
    }
    let r = demo_cli("explain", dir, &extra);
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    serde_json::from_slice(&r.stdout).unwrap()
}

fn status_of<'a>(rows: &'a [serde_json::Value], node: &str) -> &'a str {
    rows.iter()
        .find(|r| r["node"] == node)
        .and_then(|r| r["status"].as_str())
        .unwrap()
}

#[test]
fn second_process_reruns_only_downstream_of_the_change() {
    let out = tempfile::tempdir().unwrap();
    let cache = tempfile::tempdir().unwrap();
    let first = explain(out.path(), cache.path(), &[]);
    for n in ["scene", "kinect", "points", "save_color"] {
        assert_eq!(status_of(&first, n), "ran", "{n}");
    }
    for row in &first {
        for key in ["node", "kind", "status", "reason", "ms", "bytes"] {
            assert!(row.get(key).is_some(), "missing {key} in {row}");
        }
    }
    // A new process: only the Kinect's seed changes.
    let second = explain(out.path(), cache.path(), &["kinect.seed=7"]);
    assert_eq!(status_of(&second, "scene"), "cached");
    assert_eq!(status_of(&second, "kinect"), "ran");
    assert_eq!(status_of(&second, "points"), "ran");
    // Sinks always write; nothing else upstream of the change ran.
    let ran: Vec<&str> = second
        .iter()
        .filter(|r| r["status"] == "ran" && !r["kind"].as_str().unwrap().starts_with("Save"))
        .map(|r| r["node"].as_str().unwrap())
        .collect();
    assert_eq!(ran, ["kinect", "points"]);
    // Same again: everything but the sinks comes from the cache.
    let third = explain(out.path(), cache.path(), &["kinect.seed=7"]);
    assert_eq!(status_of(&third, "kinect"), "cached");
    // the sinks read the scene directly, so it is fetched from the cache, not recomputed
    assert_eq!(status_of(&third, "scene"), "cached");
    assert_eq!(status_of(&third, "points"), "cached");
    // --no-cache computes everything again.
    let r = demo_cli("explain", out.path(), &["--json", "--no-cache"]);
    let rows: Vec<serde_json::Value> = serde_json::from_slice(&r.stdout).unwrap();
    assert_eq!(status_of(&rows, "scene"), "ran");
}

fn in_process(threads: usize) -> Vec<(String, Vec<u32>)> {
    let reg = depthgraph::nodes::registry().unwrap();
    let sets: Vec<String> = SMALL.iter().map(|s| s.to_string()).collect();
    let (_, mut p) = depthgraph::load_pipeline(&graph("demo.ron"), &sets, &reg).unwrap();
    // the values, not the files
    p.outputs = ["scene", "kinect", "points"]
        .iter()
        .map(|n| OutputRef {
            node: p.index_of(n).unwrap(),
            port: None,
        })
        .collect();
    let engine = Engine::new(EngineOptions {
        threads,
        ..EngineOptions::default()
    })
    .unwrap();
    let r = engine.run(&p, &RunOptions::default()).unwrap();
    r.outputs
        .iter()
        .map(|(k, v)| {
            let bits: Vec<u32> = match v {
                Value::Color(_) | Value::Normals(_) | Value::Depth(_) => v
                    .samples()
                    .unwrap()
                    .samples
                    .iter()
                    .map(|x| x.to_bits())
                    .collect(),
                Value::Labels(i) => i.as_slice().to_vec(),
                Value::PointCloud(pc) => pc
                    .positions
                    .iter()
                    .chain(&pc.colors)
                    .flatten()
                    .map(|x| x.to_bits())
                    .collect(),
                Value::Intrinsics(k) => [k.fx, k.fy, k.cx, k.cy]
                    .iter()
                    .map(|x| x.to_bits() as u32)
                    .collect(),
                other => panic!("unexpected {other:?}"),
            };
            (k.clone(), bits)
        })
        .collect()
}

#[test]
fn one_and_two_threads_are_bit_identical_on_the_demo() {
    let one = in_process(1);
    let two = in_process(2);
    assert_eq!(one.len(), two.len());
    assert!(one.len() >= 8);
    for ((ka, a), (kb, b)) in one.iter().zip(&two) {
        assert_eq!(ka, kb);
        assert!(a == b, "{ka} differs between 1 and 2 threads");
    }
}

/// A sequence's index (a list file, a TUM folder's rgb.txt and depth.txt)
/// says which files it reads: no sink writes over it either, though the
/// cache key leaves it out.
#[test]
fn sinks_never_overwrite_a_sequences_index() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let img = Image::from_fn(4, 3, |x, y| [x as f32 / 4.0, y as f32 / 3.0, 0.5]);
    depthgraph::nodes::io::save_color(&img, &d.join("c0.png"), false, 0.0).unwrap();
    let depth = Image::filled(4, 3, 1.5f32);
    depthgraph::nodes::io::save_depth(
        &depth,
        &d.join("d0.png"),
        &depthgraph::nodes::io::SaveDepthParams::default(),
    )
    .unwrap();
    let list = d.join("list.txt");
    std::fs::write(&list, "c0.png d0.png\n").unwrap();
    let before = std::fs::read(&list).unwrap();
    let pipe = d.join("p.ron");
    let text = format!(
        r#"(version: 1, nodes: {{
            "seq": (kind: "LoadSequence", params: (source: "{l}", frame: 0)),
            "save": (kind: "SaveDepth", params: (path: "{l}", format: "png16"), inputs: (depth: "seq.depth")),
        }}, outputs: ["save"])"#,
        l = list.display()
    );
    std::fs::write(&pipe, text).unwrap();
    let r = run_uncached(&pipe, d, &[]);
    let err = String::from_utf8_lossy(&r.stderr);
    assert!(!r.status.success(), "{err}");
    assert!(
        err.contains("refusing to write over a file this pipeline reads"),
        "{err}"
    );
    assert_eq!(std::fs::read(&list).unwrap(), before);
}

/// A sweep's CSV never goes over a file one of its values reads (a swept
/// path), checked before the first value runs.
#[test]
fn sweep_csv_never_goes_over_a_swept_input() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let img = Image::from_fn(4, 3, |x, y| [x as f32 / 4.0, y as f32 / 3.0, 0.5]);
    for f in ["a.png", "b.png"] {
        depthgraph::nodes::io::save_color(&img, &d.join(f), false, 0.0).unwrap();
    }
    let (a, b) = (d.join("a.png"), d.join("b.png"));
    let before = std::fs::read(&b).unwrap();
    let pipe = d.join("p.ron");
    let text = format!(
        r#"(version: 1, nodes: {{ "load": (kind: "LoadColor", params: (path: "{}")) }}, outputs: ["load"])"#,
        a.display()
    );
    std::fs::write(&pipe, text).unwrap();
    let param = format!("load.path={},{}", a.display(), b.display());
    let reference = format!("load.path={}", a.display());
    let r = cli(&[
        "sweep",
        pipe.to_str().unwrap(),
        "--no-cache",
        "--out",
        d.to_str().unwrap(),
        "--param",
        &param,
        "--reference",
        &reference,
        "--output",
        "load.color",
        "--csv",
        b.to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&r.stderr);
    assert_eq!(r.status.code(), Some(2), "{err}");
    assert!(err.contains("refusing to write over"), "{err}");
    assert_eq!(std::fs::read(&b).unwrap(), before);
}

/// A pipeline piped on standard input runs: the file is read once (it
/// was read a second time, found empty, and reported as a syntax error).
#[cfg(target_os = "linux")]
#[test]
fn a_pipeline_on_standard_input_runs() {
    use std::io::Write as _;
    let out = tempfile::tempdir().unwrap();
    let text = r#"(version: 1, nodes: {
        "scene": (kind: "SyntheticScene", params: (width: 16, height: 12)),
        "save": (kind: "SaveDepth", params: (path: "d.exr"), inputs: (depth: "scene.depth")),
    }, outputs: ["save"])"#;
    let mut child = Command::new(env!("CARGO_BIN_EXE_depthgraph"))
        .args([
            "run",
            "/dev/stdin",
            "--no-cache",
            "--quiet",
            "--backend",
            "cpu",
            "--out",
        ])
        .arg(out.path())
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    child
        .stdin
        .take()
        .unwrap()
        .write_all(text.as_bytes())
        .unwrap();
    let r = child.wait_with_output().unwrap();
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    assert!(out.path().join("d.exr").is_file());
}

/// Two sinks that would write one file (the same path, or the same file
/// by another spelling) are refused before anything runs, naming both:
/// they ran at once and the file held whichever finished last.
#[test]
fn two_sinks_never_write_the_same_file() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let out = d.join("out");
    for (a, b) in [("d.exr", "d.exr"), ("d.exr", "./sub/../d.exr")] {
        let abs_b = if b.starts_with('.') {
            b.to_string()
        } else {
            out.join(b).display().to_string()
        };
        let pipe = d.join("p.ron");
        let text = format!(
            r#"(version: 1, nodes: {{
                "scene": (kind: "SyntheticScene", params: (width: 16, height: 12)),
                "a": (kind: "SaveDepth", params: (path: "{a}"), inputs: (depth: "scene.depth")),
                "b": (kind: "SaveColor", params: (path: "{abs_b}"), inputs: (color: "scene.color")),
            }}, outputs: ["a", "b"])"#
        );
        std::fs::write(&pipe, text).unwrap();
        std::fs::create_dir_all(out.join("sub")).unwrap();
        let r = run_uncached(&pipe, &out, &[]);
        let err = String::from_utf8_lossy(&r.stderr);
        assert_eq!(r.status.code(), Some(2), "{a} / {b}: {err}");
        assert!(
            err.contains("also written by node")
                && err.contains("node `a`")
                && err.contains("node `b`"),
            "{err}"
        );
        assert!(!out.join("d.exr").exists(), "nothing is written");
    }
}

#[test]
fn sinks_never_overwrite_an_input_file() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("photo.png");
    let img = Image::from_fn(4, 3, |x, y| [x as f32 / 4.0, y as f32 / 3.0, 0.5]);
    depthgraph::nodes::io::save_color(&img, &input, false, 0.0).unwrap();
    let before = std::fs::read(&input).unwrap();
    let pipe = dir.path().join("p.ron");
    let text = format!(
        r#"(version: 1, nodes: {{
            "load": (kind: "LoadColor", params: (path: "{p}")),
            "bright": (kind: "Exposure", params: (stops: 1.0), inputs: (color: "load.color")),
            "save": (kind: "SaveColor", params: (path: "{p}"), inputs: (color: "bright.color")),
        }}, outputs: ["save"])"#,
        p = input.display()
    );
    std::fs::write(&pipe, text).unwrap();
    let r = run_uncached(&pipe, dir.path(), &[]);
    assert!(!r.status.success());
    let err = String::from_utf8_lossy(&r.stderr);
    assert!(
        err.contains("refusing to write over a file this pipeline reads"),
        "{err}"
    );
    assert_eq!(std::fs::read(&input).unwrap(), before);
    // nor over the pipeline file itself (relative path resolved against --out)
    let r = run_uncached(&pipe, dir.path(), &["--set", "save.path=p.ron"]);
    assert!(!r.status.success());
    assert!(
        std::fs::read_to_string(&pipe)
            .unwrap()
            .starts_with("(version: 1")
    );
    // a different target works, and the result is twice as bright
    let r = run_uncached(&pipe, dir.path(), &["--set", "save.path=bright.png"]);
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    let a =
        depthgraph::nodes::io::load_color(&input, depthgraph::nodes::io::ColorSpace::Srgb).unwrap();
    let b = depthgraph::nodes::io::load_color(
        &dir.path().join("bright.png"),
        depthgraph::nodes::io::ColorSpace::Srgb,
    )
    .unwrap();
    let (pa, pb) = (a.get(1, 1), b.get(1, 1));
    assert!(
        (pb[0] - (2.0 * pa[0]).min(1.0)).abs() < 0.01,
        "{pa:?} -> {pb:?}"
    );
}

#[test]
fn nodes_lists_every_kind_with_its_schema() {
    let r = cli(&["nodes", "--json"]);
    assert!(r.status.success());
    let list: Vec<serde_json::Value> = serde_json::from_slice(&r.stdout).unwrap();
    let reg = depthgraph::nodes::registry().unwrap();
    assert_eq!(list.len(), reg.kinds().count());
    let cam = list.iter().find(|n| n["kind"] == "Camera").unwrap();
    let width = cam["params"]
        .as_array()
        .unwrap()
        .iter()
        .find(|p| p["name"] == "width")
        .unwrap();
    assert_eq!(width["default"], "640");
    assert_eq!(width["range"], "[1, 65536]");
    let r = cli(&["nodes", "Camra"]);
    assert!(!r.status.success());
    assert!(String::from_utf8_lossy(&r.stderr).contains("did you mean `Camera`?"));
}

#[test]
fn every_registered_default_is_valid_and_round_trips() {
    let reg = depthgraph::nodes::registry().unwrap();
    for kind in reg.kinds() {
        let node = reg.get(kind).unwrap();
        for spec in &node.schema().params {
            assert!(
                spec.kind.validate(&spec.default).is_ok()
                    || matches!(spec.kind, ParamKind::InputPath),
                "{kind}.{}",
                spec.name
            );
            assert!(!spec.doc.is_empty(), "{kind}.{} has no doc", spec.name);
        }
        assert!(!node.schema().doc.is_empty(), "{kind} has no doc");
    }
}

#[test]
fn sweep_writes_csv_and_plot() {
    let out = tempfile::tempdir().unwrap();
    let r = demo_cli(
        "sweep",
        out.path(),
        &[
            "--no-cache",
            "--param",
            "kinect.noise_k=0,0.0015,0.006",
            "--truth",
            "scene.depth",
            "--output",
            "kinect.depth",
            "--metric",
            "rmse",
            "--repeats",
            "1",
        ],
    );
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    let csv = std::fs::read_to_string(out.path().join("sweep-kinect-noise_k.csv")).unwrap();
    let rows: Vec<Vec<&str>> = csv
        .lines()
        .skip(1)
        .map(|l| l.split(',').collect())
        .collect();
    assert_eq!(rows.len(), 3);
    let err: Vec<f64> = rows.iter().map(|r| r[6].parse().unwrap()).collect();
    // more noise, more error
    assert!(err[0] < err[1] && err[1] < err[2], "{err:?}");
    let svg = std::fs::read_to_string(out.path().join("sweep-kinect-noise_k.svg")).unwrap();
    assert!(
        svg.starts_with("<svg") && svg.contains("<circle"),
        "not a plot"
    );
}

/// What a sweep cannot do is refused (exit 2) before anything runs: its
/// CSV or plot over the pipeline file, both on one file, an output port
/// that does not exist, a value out of range late in the list (the rows
/// before it were computed, then thrown away).
#[test]
fn sweep_refuses_before_running() {
    let dir = tempfile::tempdir().unwrap();
    let pipe = dir.path().join("demo.ron");
    std::fs::copy(graph("demo.ron"), &pipe).unwrap();
    let before = std::fs::read(&pipe).unwrap();
    let p = pipe.to_str().unwrap();
    let o = dir.path().join("out");
    let o = o.to_str().unwrap();
    let same = dir.path().join("r.txt");
    let same = same.to_str().unwrap();
    let base = [
        "sweep",
        p,
        "--no-cache",
        "--out",
        o,
        "--truth",
        "scene.depth",
        "--repeats",
        "1",
    ];
    let cases: [(&[&str], &str); 4] = [
        (
            &[
                "--param",
                "kinect.noise_k=0,0.001",
                "--output",
                "kinect.depth",
                "--csv",
                p,
            ],
            "refusing to write over a file this pipeline reads",
        ),
        (
            &[
                "--param",
                "kinect.noise_k=0,0.001",
                "--output",
                "kinect.depth",
                "--csv",
                same,
                "--plot",
                same,
            ],
            "give each its own file",
        ),
        (
            &[
                "--param",
                "kinect.noise_k=0,0.001",
                "--output",
                "kinect.dpth",
            ],
            "kinect.dpth",
        ),
        (
            &[
                "--param",
                "kinect.noise_k=0,0.001,2",
                "--output",
                "kinect.depth",
            ],
            "outside",
        ),
    ];
    for (extra, says) in cases {
        let mut args: Vec<&str> = base.to_vec();
        args.extend(extra);
        let r = cli(&args);
        let err = String::from_utf8_lossy(&r.stderr);
        assert_eq!(r.status.code(), Some(2), "{extra:?}: {err}");
        assert!(err.contains(says), "{extra:?}: {err}");
        // no row ran: the table's header at most
        let stdout = String::from_utf8_lossy(&r.stdout);
        assert!(stdout.lines().count() <= 1, "{extra:?} ran: {stdout}");
    }
    assert_eq!(std::fs::read(&pipe).unwrap(), before);
    assert!(!std::path::Path::new(same).exists());
}

/// `depthgraph explain FILE --json --quiet --out OUT --cache-dir CACHE`
/// with `--set` for each of `sets` then of `extra`: the rows, after
/// asserting success.
fn explain_graph(
    file: &Path,
    out: &Path,
    cache: &Path,
    sets: &[&str],
    extra: &[&str],
) -> Vec<serde_json::Value> {
    let mut args = vec!["explain", file.to_str().unwrap(), "--json", "--quiet"];
    args.extend(["--out", out.to_str().unwrap()]);
    args.extend(["--cache-dir", cache.to_str().unwrap()]);
    for s in sets.iter().chain(extra) {
        args.extend(["--set", s]);
    }
    let r = cli(&args);
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    serde_json::from_slice(&r.stdout).unwrap()
}

/// Pipeline B (`graphs/refocus.ron`) end to end at a small size: a bracket
/// and a ToF beside the color camera to a refocused image, and the
/// pass-through when the lens blurs nothing.
#[test]
fn refocus_pipeline_runs_and_passes_through_without_blur() {
    let out = tempfile::tempdir().unwrap();
    let cache = tempfile::tempdir().unwrap();
    let file = graph("refocus.ron");
    let run = |extra: &[&str]| -> Vec<serde_json::Value> {
        let sets = [
            "scene.width=160",
            "scene.height=120",
            "tof_view.width=160",
            "tof_view.height=120",
            "tof.width=40",
            "tof.height=30",
            "to_color.width=40",
            "to_color.height=30",
            "refocus.samples=16",
        ];
        explain_graph(&file, out.path(), cache.path(), &sets, extra)
    };
    let rows = run(&[]);
    for n in ["hdr", "to_color", "upsample", "refocus"] {
        assert_eq!(status_of(&rows, n), "ran", "{n}");
    }
    let img = depthgraph::nodes::io::load_color(
        &out.path().join("refocus/refocused.exr"),
        depthgraph::nodes::io::ColorSpace::Linear,
    )
    .unwrap();
    assert_eq!(img.dims(), (160, 120));
    assert!(
        img.as_slice()
            .iter()
            .flatten()
            .all(|v| v.is_finite() && *v >= 0.0)
    );
    // A pinhole-like lens: every circle of confusion is under half a pixel.
    let rows = run(&["refocus.f_number=1000"]);
    assert_eq!(status_of(&rows, "refocus"), "passthrough");
    assert_eq!(status_of(&rows, "hdr"), "cached");
    let reason = rows
        .iter()
        .find(|r| r["node"] == "refocus")
        .and_then(|r| r["reason"].as_str())
        .unwrap();
    assert!(reason.contains("circle of confusion"), "{reason}");
    // Focusing nearer than the focal length is refused with the parameter named.
    let mut args = vec!["run", file.to_str().unwrap(), "--quiet", "--no-cache"];
    args.extend(["--out", out.path().to_str().unwrap()]);
    args.extend([
        "--set",
        "refocus.focus_m=0.01",
        "--set",
        "scene.width=32",
        "--set",
        "scene.height=24",
    ]);
    let r = cli(&args);
    assert!(!r.status.success());
    let err = String::from_utf8_lossy(&r.stderr);
    assert!(err.contains("refocus") && err.contains("focus_m"), "{err}");
}

/// The relighting's per-photo part is a value the engine keeps: moving the
/// object reuses it (from memory, and from disk in a new engine), the
/// result equals a run that built everything afresh, `--no-cache` and a
/// change of a parameter it depends on rebuild it, and `explain` shows it.
/// `Paste`'s source part likewise (in memory).
#[test]
fn the_relight_scene_is_an_engine_cached_value() {
    let reg = depthgraph::nodes::registry().unwrap();
    let file = graph("copy_paste_relit.ron");
    let load = |sets: &[&str]| {
        let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
        let (_, mut p) = depthgraph::load_pipeline(&file, &sets, &reg).unwrap();
        let i = p.index_of("relight").unwrap();
        p.outputs = vec![OutputRef {
            node: i,
            port: Some("color".into()),
        }];
        p
    };
    // the status of the one derived value of `node`, named `name`
    let derived_status = |r: &RunResult, node: &str, name: &str| {
        let rec = r.trace.get(node).unwrap();
        assert_eq!(rec.status, Status::Ran, "{rec:?}");
        assert_eq!(rec.derived.len(), 1, "{rec:?}");
        assert_eq!(rec.derived[0].name, name);
        assert!(rec.derived[0].bytes > 0);
        rec.derived[0].status
    };
    let scene_status = |r: &RunResult| derived_status(r, "relight", "relight scene");
    // Paste's source part (the object points and the closed back) is one
    // too, kept in memory
    let paste_source_status = |r: &RunResult| derived_status(r, "paste", "paste source");
    let color = |r: &RunResult| r.outputs["relight.color"].clone();
    let disk = tempfile::tempdir().unwrap();
    let engine = |with_disk: bool| {
        Engine::new(EngineOptions {
            disk: with_disk.then(|| DiskCache::new(disk.path(), 1 << 30)),
            ..EngineOptions::default()
        })
        .unwrap()
    };
    let e = engine(true);
    let run = |e: &Engine, p: &Pipeline, no_cache: bool| {
        e.run(
            p,
            &RunOptions {
                no_cache_lookup: no_cache,
                ..RunOptions::default()
            },
        )
        .unwrap()
    };
    let first = run(&e, &load(&[]), false);
    assert_eq!(scene_status(&first), Status::Ran);
    assert!(first.trace.table().contains("derived: relight scene"));
    // the object moves: Relight runs again, its scene does not
    let moved = load(&["paste.target_pixel=[(80.5, 160.5)]"]);
    let again = run(&e, &moved, false);
    assert_eq!(scene_status(&again), Status::Cached);
    assert_eq!(paste_source_status(&first), Status::Ran);
    assert_eq!(paste_source_status(&again), Status::Cached);
    let fresh = run(&engine(false), &moved, false);
    assert_eq!(scene_status(&fresh), Status::Ran);
    assert_eq!(paste_source_status(&fresh), Status::Ran);
    assert_eq!(color(&again), color(&fresh));
    assert_ne!(color(&again), color(&first), "the object moved");
    // a new engine (a second CLI run) reads it from the disk cache
    let from_disk = run(
        &engine(true),
        &load(&["paste.target_pixel=[(70.5, 155.5)]"]),
        false,
    );
    assert_eq!(scene_status(&from_disk), Status::Cached);
    // --no-cache and a parameter of the scene part rebuild it
    assert_eq!(scene_status(&run(&e, &moved, true)), Status::Ran);
    let other = load(&[
        "paste.target_pixel=[(80.5, 160.5)]",
        "relight.ism_points=2000",
    ]);
    assert_eq!(scene_status(&run(&e, &other, false)), Status::Ran);
    // a parameter of the source part rebuilds it, one of the placement
    // only does not
    let threshold = load(&[
        "paste.target_pixel=[(80.5, 160.5)]",
        "paste.mask_threshold=0.6",
    ]);
    assert_eq!(
        paste_source_status(&run(&e, &threshold, false)),
        Status::Ran
    );
    let turned = load(&[
        "paste.target_pixel=[(80.5, 160.5)]",
        "paste.mask_threshold=0.6",
        "paste.rotation_deg=(20.0, 0.0, 0.0)",
    ]);
    assert_eq!(
        paste_source_status(&run(&e, &turned, false)),
        Status::Cached
    );
}

/// `graphs/copy_paste_estimated_light.ron`: the map is estimated from the
/// target photo; the light found is the target's sun (elevation 35,
/// azimuth 40) within 10°, `explain` (text and JSON) shows the report,
/// and a result read from the disk cache keeps it.
#[test]
fn the_estimated_light_pipeline_finds_the_targets_sun_and_reports_it() {
    let reg = depthgraph::nodes::registry().unwrap();
    let file = graph("copy_paste_estimated_light.ron");
    let (_, mut p) = depthgraph::load_pipeline(&file, &[], &reg).unwrap();
    let i = p.index_of("relight").unwrap();
    let j = p.index_of("env").unwrap();
    p.outputs = vec![
        OutputRef {
            node: i,
            port: Some("color".into()),
        },
        OutputRef {
            node: j,
            port: Some("map".into()),
        },
    ];
    let disk = tempfile::tempdir().unwrap();
    let engine = || {
        Engine::new(EngineOptions {
            disk: Some(DiskCache::new(disk.path(), 1 << 30)),
            ..EngineOptions::default()
        })
        .unwrap()
    };
    let first = engine().run(&p, &RunOptions::default()).unwrap();
    let rec = first.trace.get("env").unwrap();
    assert_eq!(rec.status, Status::Ran);
    let report = rec.report.clone().unwrap();
    // "light at elevation E°, azimuth A°, ..."
    let num = |key: &str| -> f64 {
        let at = report.find(key).unwrap() + key.len();
        report[at..]
            .split('°')
            .next()
            .unwrap()
            .trim()
            .parse()
            .unwrap()
    };
    let (e, a) = (num("elevation"), num("azimuth"));
    let found = depthgraph::nodes::relight::envmap::sun_direction(e, a);
    let truth = depthgraph::nodes::relight::envmap::sun_direction(35.0, 40.0);
    let err = found.dot(truth).clamp(-1.0, 1.0).acos().to_degrees();
    assert!(err < 10.0, "{err:.1}° off: {report}");
    assert!(first.trace.table().contains(&format!("found: {report}")));
    // a second engine reads the map from disk, with its report
    let again = engine().run(&p, &RunOptions::default()).unwrap();
    let rec = again.trace.get("env").unwrap();
    assert_eq!(rec.status, Status::Cached, "{rec:?}");
    assert_eq!(rec.report.as_deref(), Some(report.as_str()));
    // the CLI's JSON carries it
    let cache = tempfile::tempdir().unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_depthgraph"))
        .args([
            "explain",
            file.to_str().unwrap(),
            "--json",
            "--quiet",
            "--backend",
            "cpu",
        ])
        .env("DEPTHGRAPH_CACHE_DIR", cache.path())
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.contains("\"report\"") && text.contains("light at elevation"),
        "{text}"
    );
    // ... and, as the table does, each node's key and derived values (the
    // relight scene the engine keeps)
    let rows: Vec<serde_json::Value> = serde_json::from_slice(&out.stdout).unwrap();
    let relight = rows.iter().find(|r| r["node"] == "relight").unwrap();
    assert!(
        relight["key"].as_str().is_some_and(|k| k.len() >= 32),
        "{relight}"
    );
    assert_eq!(relight["derived"][0]["name"], "relight scene", "{relight}");
    assert_eq!(relight["derived"][0]["status"], "ran", "{relight}");
}

/// `graphs/refocus_lens.ron` at a small size: Refocus with the lens
/// effects is closer to the ray-traced lens with the same effects than
/// Refocus without them, and explain lists the effects that are off.
#[test]
fn refocus_lens_pipeline_matches_its_ray_traced_lens() {
    let out = tempfile::tempdir().unwrap();
    let cache = tempfile::tempdir().unwrap();
    let file = graph("refocus_lens.ron");
    let run = |extra: &[&str]| -> Vec<serde_json::Value> {
        let sets = [
            "scene.width=160",
            "scene.height=120",
            "truth.width=160",
            "truth.height=120",
            "truth.sensor_width_mm=9",
            "refocus.sensor_width_mm=9",
            "truth.lens_samples=128",
            "refocus.samples=128",
        ];
        explain_graph(&file, out.path(), cache.path(), &sets, extra)
    };
    let load = |name: &str| {
        depthgraph::nodes::io::load_color(
            &out.path().join("refocus_lens").join(name),
            depthgraph::nodes::io::ColorSpace::Linear,
        )
        .unwrap()
    };
    let rows = run(&[]);
    let report = rows
        .iter()
        .find(|r| r["node"] == "refocus")
        .and_then(|r| r["report"].as_str())
        .unwrap_or_default()
        .to_string();
    assert!(report.contains("no focus breathing"), "{report}");
    assert!(!report.contains("chromatic"), "{report}");
    let truth = load("truth.exr");
    let with = depthgraph::metrics::display_psnr(&load("refocus.exr"), &truth).unwrap();
    run(&[
        "refocus.spherical_aberration_d=0",
        "refocus.chromatic_longitudinal_d=0",
        "refocus.chromatic_lateral=0",
        "refocus.barrel_distance_mm=0",
        "refocus.natural_vignetting=0",
    ]);
    let without = depthgraph::metrics::display_psnr(&load("refocus.exr"), &truth).unwrap();
    eprintln!("with the effects {with:.1} dB, without {without:.1} dB");
    assert!(with > without + 3.0, "{with} vs {without}");
    // (at this size the preset's emitters are under a pixel in the
    // pinhole input, which costs every setting a few dB: docs/refocus.md)
    assert!(with > 27.0, "{with}");
}
