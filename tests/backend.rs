//! `--backend` on the command line: `gpu` runs the device kinds on the
//! adapter and `explain --json` names it per node; `gpu` without a matching
//! adapter fails before running (exit code 69); `auto` falls back to the CPU
//! and says why; `--backend gpu` and `cpu` write images that agree.
//! (The GPU parts need the `gpu` feature and a wgpu adapter: lavapipe in CI.)

use std::path::{Path, PathBuf};
use std::process::Command;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn cli(args: &[&str], env: &[(&str, &str)]) -> std::process::Output {
    let mut c = Command::new(env!("CARGO_BIN_EXE_depthgraph"));
    c.current_dir(root())
        .args(args)
        .env_remove("DEPTHGRAPH_BACKEND");
    for (k, v) in env {
        c.env(k, v);
    }
    c.output().unwrap()
}

fn explain_json(
    file: &str,
    out: &Path,
    backend: &str,
    env: &[(&str, &str)],
) -> (Vec<serde_json::Value>, String) {
    let f = root().join("graphs").join(file);
    let r = cli(
        &[
            "explain",
            f.to_str().unwrap(),
            "--json",
            "--no-cache",
            "-q",
            "--backend",
            backend,
            "--out",
            out.to_str().unwrap(),
        ],
        env,
    );
    let stderr = String::from_utf8_lossy(&r.stderr).to_string();
    assert!(r.status.success(), "{stderr}");
    (serde_json::from_slice(&r.stdout).unwrap(), stderr)
}

#[cfg(feature = "gpu")]
#[test]
fn explain_names_the_wgpu_backend_and_adapter_of_each_device_node() {
    let out = tempfile::tempdir().unwrap();
    let cases: [(&str, &[&str]); 2] = [
        ("refocus.ron", &["upsample", "fill", "refocus"]),
        ("depth_fill.ron", &["baseline", "fill", "nlm", "smooth"]),
    ];
    for (file, device) in cases {
        let (rows, stderr) = explain_json(file, out.path(), "gpu", &[]);
        assert!(stderr.contains("backend: wgpu"), "{stderr}");
        for r in &rows {
            let node = r["node"].as_str().unwrap();
            if device.contains(&node) {
                assert_eq!(r["backend"], "wgpu", "{r}");
                assert!(r["adapter"].as_str().is_some_and(|a| !a.is_empty()), "{r}");
                // a pass-through moves nothing; a run reads its result back
                let moved = r["transfers"]["downloads"].as_u64().unwrap();
                assert!(r["status"] == "passthrough" || moved >= 1, "{r}");
            } else {
                // every other node ran on the CPU and says so
                assert_eq!(r["backend"], "cpu", "{r}");
                assert!(r["adapter"].is_null(), "{r}");
            }
        }
    }
}

#[cfg(feature = "gpu")]
#[test]
fn a_cached_result_names_the_backend_that_produced_it() {
    let out = tempfile::tempdir().unwrap();
    let cache = tempfile::tempdir().unwrap();
    let f = root().join("graphs/depth_fill.ron");
    let run = |backend: &str| {
        let r = cli(
            &[
                "explain",
                f.to_str().unwrap(),
                "--json",
                "-q",
                "--backend",
                backend,
                "--cache-dir",
                cache.path().to_str().unwrap(),
                "--out",
                out.path().to_str().unwrap(),
            ],
            &[],
        );
        assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
        let rows: Vec<serde_json::Value> = serde_json::from_slice(&r.stdout).unwrap();
        rows.into_iter().find(|r| r["node"] == "smooth").unwrap()
    };
    let first = run("gpu");
    assert_eq!(
        (first["status"].as_str(), first["backend"].as_str()),
        (Some("ran"), Some("wgpu"))
    );
    // a CPU-only process reads the GPU's result from the disk cache, and says who made it
    let second = run("cpu");
    assert_eq!(second["status"], "cached", "{second}");
    assert_eq!(second["backend"], "wgpu", "{second}");
    assert_eq!(second["adapter"], first["adapter"]);
}

#[test]
fn gpu_without_a_matching_adapter_fails_before_running() {
    let out = tempfile::tempdir().unwrap();
    let f = root().join("graphs/refocus.ron");
    let r = cli(
        &[
            "run",
            f.to_str().unwrap(),
            "--no-cache",
            "-q",
            "--backend",
            "gpu",
            "--out",
            out.path().to_str().unwrap(),
        ],
        &[("WGPU_ADAPTER_NAME", "no-such-adapter-xyz")],
    );
    assert_eq!(r.status.code(), Some(69));
    let stderr = String::from_utf8_lossy(&r.stderr);
    assert!(stderr.contains("--backend gpu"), "{stderr}");
    assert_eq!(
        stderr.matches("error:").count(),
        1,
        "printed once: {stderr}"
    );
    assert!(
        std::fs::read_dir(out.path()).unwrap().next().is_none(),
        "nothing written"
    );
    // auto runs on the CPU instead and says why
    let (rows, stderr) = explain_json(
        "depth_fill.ron",
        out.path(),
        "auto",
        &[("WGPU_ADAPTER_NAME", "no-such-adapter-xyz")],
    );
    assert!(stderr.contains("backend: cpu"), "{stderr}");
    #[cfg(feature = "gpu")]
    assert!(stderr.contains("no-such-adapter-xyz"), "{stderr}");
    assert!(rows.iter().all(|r| r["backend"] == "cpu"));
    // a bad DEPTHGRAPH_BACKEND is refused the same way
    let r = cli(
        &["run", f.to_str().unwrap(), "--no-cache", "-q"],
        &[("DEPTHGRAPH_BACKEND", "tpu")],
    );
    assert_eq!(r.status.code(), Some(2), "a usage error");
    assert!(String::from_utf8_lossy(&r.stderr).contains("expected auto, cpu or gpu"));
}

/// A pipeline that cannot run is reported before any device is probed:
/// a missing file or a `--set` naming no node exits with 2 (a usage
/// error) and says so, even where the backend asked for would fail (69).
#[test]
fn a_bad_pipeline_fails_before_the_device_is_probed() {
    let out = tempfile::tempdir().unwrap();
    let o = out.path().to_str().unwrap();
    let demo = root().join("graphs/demo.ron");
    let seq = root().join("graphs/sequence_demo.ron");
    let missing = root().join("graphs/no-such-pipeline.ron");
    let (demo, seq, missing) = (
        demo.to_str().unwrap(),
        seq.to_str().unwrap(),
        missing.to_str().unwrap(),
    );
    let no_gpu = [("WGPU_ADAPTER_NAME", "no-such-adapter-xyz")];
    let cases: [(&[&str], &str); 5] = [
        (&["run", missing], "no-such-pipeline.ron"),
        (&["explain", missing], "no-such-pipeline.ron"),
        (
            &["run", demo, "--set", "nosuch.x=1"],
            "no node named `nosuch`",
        ),
        (
            &["batch", missing, "--frames", "0..2"],
            "no-such-pipeline.ron",
        ),
        (
            &["batch", seq, "--frames", "0..2", "--set", "nosuch.x=1"],
            "no node named `nosuch`",
        ),
    ];
    for (args, says) in cases {
        let mut all: Vec<&str> = args.to_vec();
        all.extend(["--backend", "gpu", "--no-cache", "-q", "--out", o]);
        let r = cli(&all, &no_gpu);
        let stderr = String::from_utf8_lossy(&r.stderr);
        assert_eq!(r.status.code(), Some(2), "{args:?}: {stderr}");
        assert!(stderr.contains(says), "{args:?}: {stderr}");
        assert!(
            !stderr.contains("no-such-adapter-xyz") && !stderr.contains("--backend gpu"),
            "{args:?}: the device was probed: {stderr}"
        );
    }
    assert!(
        std::fs::read_dir(out.path()).unwrap().next().is_none(),
        "nothing written"
    );
}

#[cfg(feature = "gpu")]
#[test]
fn run_on_gpu_and_cpu_write_images_that_agree() {
    let f = root().join("graphs/refocus.ron");
    let mut imgs = Vec::new();
    for backend in ["cpu", "gpu"] {
        let out = tempfile::tempdir().unwrap();
        let r = cli(
            &[
                "run",
                f.to_str().unwrap(),
                "--no-cache",
                "-q",
                "--backend",
                backend,
                "--out",
                out.path().to_str().unwrap(),
            ],
            &[],
        );
        assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
        // the linear EXR, compared as the parity test does (display PSNR)
        let img = image::open(out.path().join("refocus/refocused.exr"))
            .unwrap()
            .to_rgb32f();
        let (w, h) = img.dimensions();
        let px: Vec<[f32; 3]> = img.pixels().map(|p| [p[0], p[1], p[2]]).collect();
        imgs.push((
            depthgraph::graph::value::Image::from_vec(w as usize, h as usize, px).unwrap(),
            out,
        ));
    }
    let psnr = depthgraph::metrics::display_psnr(&imgs[0].0, &imgs[1].0).unwrap();
    assert!(psnr >= 60.0, "display PSNR {psnr:.1} dB");
    // and the check can fail: a faint veil on the GPU image
    let veiled = imgs[1].0.map(|c| [c[0] + 0.004, c[1], c[2]]);
    assert!(depthgraph::metrics::display_psnr(&imgs[0].0, &veiled).unwrap() < 60.0);
}
