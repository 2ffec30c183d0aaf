//! A real window under Xvfb: the editor opens the demo pipeline, previews
//! the Kinect node and writes a screenshot; the picture must not be blank
//! and must differ from the editor's window with no graph loaded.
//!
//! Needs `xvfb-run` (Debian packages xvfb and xauth, installed by `.ci/run`)
//! and a Vulkan driver (mesa-vulkan-drivers); it fails, saying so, without them.

use std::path::{Path, PathBuf};
use std::process::Command;

fn find_in_path(name: &str) -> Option<PathBuf> {
    std::env::var_os("PATH").and_then(|paths| {
        std::env::split_paths(&paths)
            .map(|d| d.join(name))
            .find(|p| p.is_file())
    })
}

/// Runs the editor under Xvfb with `args` (in the repository root, a
/// 1280x800 window); `XDG_RUNTIME_DIR` under `dir` when the caller has none.
fn run_editor(dir: &Path, args: &[&str]) -> std::process::Output {
    let xvfb = find_in_path("xvfb-run").unwrap_or_else(|| {
        panic!("xvfb-run not found: install the Debian packages xvfb and xauth (see .ci/run)")
    });
    let runtime = dir.join("xdg");
    std::fs::create_dir_all(&runtime).expect("runtime dir");
    let mut cmd = Command::new(xvfb);
    cmd.args(["-a", "-s", "-screen 0 1280x800x24"])
        .arg(env!("CARGO_BIN_EXE_depthgraph-editor"))
        .args(args)
        .args(["--size", "1280x800", "--timeout-s", "240"])
        .current_dir(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join(".."));
    if std::env::var_os("XDG_RUNTIME_DIR").is_none() {
        cmd.env("XDG_RUNTIME_DIR", &runtime);
    }
    cmd.output().expect("xvfb-run starts")
}

/// Runs the editor under Xvfb with `args` and returns the screenshot's RGBA pixels.
fn screenshot(dir: &Path, name: &str, args: &[&str]) -> image::RgbaImage {
    let out = dir.join(name);
    let out_arg = out.to_str().expect("utf-8 temp path");
    let mut all = args.to_vec();
    all.extend(["--screenshot", out_arg]);
    let result = run_editor(dir, &all);
    assert!(
        result.status.success(),
        "editor under Xvfb failed ({}):\n{}\n{}",
        result.status,
        String::from_utf8_lossy(&result.stdout),
        String::from_utf8_lossy(&result.stderr)
    );
    image::open(&out)
        .unwrap_or_else(|e| panic!("screenshot {}: {e}", out.display()))
        .to_rgba8()
}

fn luma(p: &image::Rgba<u8>) -> f64 {
    depthgraph_nodes::kit::color::luminance_f64([p[0], p[1], p[2]].map(f64::from))
}

fn luma_variance(img: &image::RgbaImage) -> f64 {
    let n = f64::from(img.width() * img.height());
    let mean = img.pixels().map(luma).sum::<f64>() / n;
    img.pixels().map(|p| (luma(p) - mean).powi(2)).sum::<f64>() / n
}

fn distinct_colors(img: &image::RgbaImage) -> usize {
    let mut set: Vec<[u8; 3]> = img.pixels().map(|p| [p[0], p[1], p[2]]).collect();
    set.sort_unstable();
    set.dedup();
    set.len()
}

#[test]
fn window_under_xvfb_shows_the_graph_and_the_preview() {
    let dir = tempfile::tempdir().expect("temp dir");
    let graph = screenshot(
        dir.path(),
        "demo.png",
        &["graphs/demo.ron", "--select", "kinect"],
    );
    let empty = screenshot(dir.path(), "empty.png", &[]);
    assert!(
        graph.width() >= 1000 && graph.height() >= 600,
        "window size"
    );
    assert_eq!(graph.dimensions(), empty.dimensions());

    let (vg, ve) = (luma_variance(&graph), luma_variance(&empty));
    assert!(
        vg > 100.0,
        "the graph window is not blank: luma variance {vg:.1}"
    );
    let changed = graph
        .pixels()
        .zip(empty.pixels())
        .filter(|(a, b)| (luma(a) - luma(b)).abs() > 8.0)
        .count();
    let frac = changed as f64 / f64::from(graph.width() * graph.height());
    assert!(
        frac > 0.10,
        "the loaded graph changes the window: {:.1} % of pixels differ",
        frac * 100.0
    );
    // The colour-mapped depth preview brings many colours the bare UI lacks.
    let (cg, ce) = (distinct_colors(&graph), distinct_colors(&empty));
    assert!(
        cg > 4 * ce.max(1) && cg > 1000,
        "preview colours: {cg} with the graph, {ce} without (variance {vg:.0} vs {ve:.0})"
    );
}

/// Runs the editor under Xvfb expecting failure; returns its stderr.
fn failing(dir: &Path, args: &[&str]) -> String {
    let result = run_editor(dir, args);
    assert!(!result.status.success(), "expected a failure for {args:?}");
    String::from_utf8_lossy(&result.stderr).into_owned()
}

#[test]
fn a_drag_in_screenshot_mode_moves_the_pasted_object_or_says_why_not() {
    let dir = tempfile::tempdir().expect("temp dir");
    let out = dir.path().join("out");
    let out = out.to_str().expect("utf-8 temp path");
    let moved = screenshot(
        dir.path(),
        "drag.png",
        &[
            "graphs/copy_paste_relit.ron",
            "--select",
            "composite",
            "--drag",
            "40,-10",
            "--out",
            out,
        ],
    );
    assert!(luma_variance(&moved) > 100.0, "the window is not blank");
    let shot = dir.path().join("x.png");
    let shot = shot.to_str().expect("utf-8 temp path");
    let e = failing(
        dir.path(),
        &[
            "graphs/copy_paste_relit.ron",
            "--select",
            "composite",
            "--drag",
            "40",
            "--screenshot",
            shot,
        ],
    );
    assert!(e.contains("expected DX,DY"), "{e}");
    let e = failing(
        dir.path(),
        &[
            "graphs/copy_paste_relit.ron",
            "--select",
            "source",
            "--drag",
            "40,0",
            "--screenshot",
            shot,
            "--out",
            out,
        ],
    );
    assert!(e.contains("not downstream of a Paste"), "{e}");
}
