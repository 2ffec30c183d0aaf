//! Bad input and bad days on the command line (issue: nothing breaks):
//! every failure exits with the code of its kind (`depthgraph --help`
//! lists them), a closed standard output ends the program quietly, a
//! header claiming a huge image is refused before anything is allocated,
//! sinks leave no partial file, written files are the same bytes every
//! time, and the disk cache survives truncated entries, a second process
//! on the same store, and a process killed mid-run.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn bin() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_depthgraph"));
    c.current_dir(root())
        .env_remove("DEPTHGRAPH_BACKEND")
        // the device kinds are not what these tests are about
        .env("DEPTHGRAPH_BACKEND", "cpu");
    c
}

fn cli(args: &[&str]) -> std::process::Output {
    bin().args(args).output().unwrap()
}

fn code(o: &std::process::Output) -> i32 {
    o.status.code().unwrap_or(-1)
}

fn stderr(o: &std::process::Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// A pipeline reading `path` with LoadColor and writing it to `out` (a
/// path relative to `--out`, or absolute).
fn copy_pipeline(dir: &Path, input: &Path, out: &str) -> PathBuf {
    let text = format!(
        r#"(
    version: 1,
    nodes: {{
        "load": (kind: "LoadColor", params: (path: "{}")),
        "save": (kind: "SaveColor", params: (path: "{}"), inputs: (color: "load.color")),
    }},
    outputs: ["save"],
)"#,
        input.display(),
        out
    );
    let p = dir.join("copy.ron");
    std::fs::write(&p, text).unwrap();
    p
}

/// A small synthetic pipeline with several sinks (EXR, PNG, PLY).
fn small_demo(dir: &Path) -> PathBuf {
    let text = r#"(
    version: 1,
    nodes: {
        "scene": (kind: "SyntheticScene", params: (preset: "tabletop", width: 96, height: 72)),
        "kinect": (
            kind: "SimulateKinect",
            params: (seed: 3),
            inputs: (depth: "scene.depth", color: "scene.color", intrinsics: "scene.intrinsics"),
        ),
        "fill": (
            kind: "DualPullPush",
            inputs: (depth: "kinect.depth", color: "scene.color", intrinsics: "scene.intrinsics"),
        ),
        "points": (
            kind: "Unproject",
            inputs: (depth: "fill.depth", intrinsics: "scene.intrinsics", color: "scene.color"),
        ),
        "c_exr": (kind: "SaveColor", params: (path: "color.exr"), inputs: (color: "scene.color")),
        "c_png": (kind: "SaveColor", params: (path: "color.png"), inputs: (color: "scene.color")),
        "d_exr": (kind: "SaveDepth", params: (path: "filled.exr"), inputs: (depth: "fill.depth")),
        "d_png": (kind: "SaveDepth", params: (path: "kinect.png"), inputs: (depth: "kinect.depth")),
        "ply": (kind: "SavePointCloud", params: (path: "points.ply"), inputs: (points: "points.points")),
    },
    outputs: ["c_exr", "c_png", "d_exr", "d_png", "ply"],
)"#;
    let p = dir.join("small.ron");
    std::fs::write(&p, text).unwrap();
    p
}

/// Every file under `dir` (relative name to bytes).
fn files(dir: &Path) -> BTreeMap<String, Vec<u8>> {
    let mut out = BTreeMap::new();
    for e in std::fs::read_dir(dir).unwrap().flatten() {
        let p = e.path();
        if p.is_file() {
            out.insert(
                p.file_name().unwrap().to_string_lossy().into_owned(),
                std::fs::read(&p).unwrap(),
            );
        }
    }
    out
}

fn cache_entries(cache: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for d in std::fs::read_dir(cache).into_iter().flatten().flatten() {
        for f in std::fs::read_dir(d.path()).into_iter().flatten().flatten() {
            if f.path().extension().is_some_and(|e| e == "bin") {
                out.push(f.path());
            }
        }
    }
    out
}

fn run_small(pipe: &Path, out: &Path, cache: &Path) -> std::process::Output {
    cli(&[
        "run",
        pipe.to_str().unwrap(),
        "-q",
        "--out",
        out.to_str().unwrap(),
        "--cache-dir",
        cache.to_str().unwrap(),
    ])
}

/// `depthgraph run PIPE --no-cache --out OUT`.
fn run_no_cache(pipe: &Path, out: &Path) -> std::process::Output {
    cli(&[
        "run",
        pipe.to_str().unwrap(),
        "--no-cache",
        "--out",
        out.to_str().unwrap(),
    ])
}

#[test]
fn a_closed_stdout_ends_the_program_quietly() {
    for args in [
        &["nodes", "--json"][..],
        &["nodes"][..],
        &["nodes", "Refocus"][..],
    ] {
        let mut child = bin()
            .args(args)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        // `| head -0`: the reader is gone before the first line
        drop(child.stdout.take());
        let o = child.wait_with_output().unwrap();
        let err = stderr(&o);
        assert_eq!(code(&o), 0, "{args:?}: {err}");
        assert!(!err.contains("panicked"), "{args:?}: {err}");
        assert!(err.is_empty(), "{args:?} printed: {err}");
    }
}

#[test]
fn exit_codes_name_the_kind_of_failure() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let out = d.join("out");

    // 2: a pipeline that fails its check; an unknown kind asked of `nodes`
    let bad = d.join("bad.ron");
    std::fs::write(
        &bad,
        r#"(version: 1, nodes: {"x": (kind: "NoSuchKind")}, outputs: ["x"])"#,
    )
    .unwrap();
    let o = cli(&["run", bad.to_str().unwrap(), "--out", out.to_str().unwrap()]);
    assert_eq!(code(&o), 2, "{}", stderr(&o));
    let o = cli(&["nodes", "NoSuchKind"]);
    assert_eq!(code(&o), 2, "{}", stderr(&o));
    assert!(stderr(&o).contains("NoSuchKind"));
    // 2: a bad flag (clap)
    let o = cli(&["run", "--no-such-flag"]);
    assert_eq!(code(&o), 2);

    // 65: a missing input file, a corrupt one, a PFM whose scale is NaN
    let missing = d.join("missing.png");
    let p = copy_pipeline(d, &missing, "c.png");
    let o = run_no_cache(&p, &out);
    assert_eq!(code(&o), 65, "{}", stderr(&o));
    assert!(stderr(&o).contains("missing.png"));

    let corrupt = d.join("corrupt.png");
    std::fs::write(&corrupt, b"\x89PNG\r\n\x1a\nthis is not a png at all").unwrap();
    let p = copy_pipeline(d, &corrupt, "c.png");
    let o = run_no_cache(&p, &out);
    assert_eq!(code(&o), 65, "{}", stderr(&o));
    assert!(stderr(&o).contains("corrupt.png"));

    let pfm = d.join("nan.pfm");
    let mut bytes = b"Pf\n2 2\nnan\n".to_vec();
    bytes.extend(std::iter::repeat_n(0u8, 16));
    std::fs::write(&pfm, bytes).unwrap();
    let text = format!(
        r#"(version: 1, nodes: {{"d": (kind: "LoadDepth", params: (path: "{}"))}}, outputs: ["d.depth"])"#,
        pfm.display()
    );
    let p = d.join("pfm.ron");
    std::fs::write(&p, text).unwrap();
    let o = run_no_cache(&p, &out);
    assert_eq!(code(&o), 65, "{}", stderr(&o));
    assert!(stderr(&o).contains("scale"), "{}", stderr(&o));

    // 74: the output directory is a regular file; nothing is written and
    // the input stays as it was
    let good = d.join("good.png");
    image::RgbImage::from_pixel(4, 3, image::Rgb([10, 200, 30]))
        .save(&good)
        .unwrap();
    let before = std::fs::read(&good).unwrap();
    let blocker = d.join("blocker");
    std::fs::write(&blocker, b"a file, not a directory").unwrap();
    let p = copy_pipeline(d, &good, &format!("{}/sub/c.png", blocker.display()));
    let o = run_no_cache(&p, &out);
    assert_eq!(code(&o), 74, "{}", stderr(&o));
    assert_eq!(std::fs::read(&good).unwrap(), before);
    assert_eq!(std::fs::read(&blocker).unwrap(), b"a file, not a directory");

    // 0: the same pipeline with a writable output
    let p = copy_pipeline(d, &good, "c.png");
    let o = run_no_cache(&p, &out);
    assert_eq!(code(&o), 0, "{}", stderr(&o));
    assert!(out.join("c.png").is_file());

    // `--help` documents the codes
    let o = cli(&["--help"]);
    let help = String::from_utf8_lossy(&o.stdout);
    for c in ["65", "74", "75"] {
        assert!(help.contains(c), "--help lacks exit code {c}");
    }
}

/// CRC-32 (PNG's polynomial) of `bytes`.
fn crc32(bytes: &[u8]) -> u32 {
    let mut c = 0xFFFF_FFFFu32;
    for b in bytes {
        c ^= u32::from(*b);
        for _ in 0..8 {
            c = if c & 1 != 0 {
                0xEDB8_8320 ^ (c >> 1)
            } else {
                c >> 1
            };
        }
    }
    !c
}

#[test]
fn a_header_claiming_a_huge_image_is_refused_before_allocation() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let out = d.join("out");
    // a real 4x3 PNG whose IHDR now says 60000x60000 (CRC fixed)
    let small = d.join("small.png");
    image::RgbImage::from_pixel(4, 3, image::Rgb([1, 2, 3]))
        .save(&small)
        .unwrap();
    let mut png = std::fs::read(&small).unwrap();
    // signature (8) + length (4) + "IHDR" (4): width and height follow
    png[16..20].copy_from_slice(&60000u32.to_be_bytes());
    png[20..24].copy_from_slice(&60000u32.to_be_bytes());
    let crc = crc32(&png[12..29]);
    png[29..33].copy_from_slice(&crc.to_be_bytes());
    let huge_png = d.join("huge.png");
    std::fs::write(&huge_png, &png).unwrap();
    let huge_pgm = d.join("huge.pgm");
    std::fs::write(&huge_pgm, b"P5\n60000 60000\n255\n").unwrap();

    for input in [&huge_png, &huge_pgm] {
        let p = copy_pipeline(d, input, "c.png");
        let t = Instant::now();
        let o = run_no_cache(&p, &out);
        let took = t.elapsed();
        let err = stderr(&o);
        assert_eq!(code(&o), 65, "{err}");
        assert!(
            err.contains(&input.file_name().unwrap().to_string_lossy().to_string()),
            "{err}"
        );
        assert!(
            err.contains("60000x60000") && err.contains("limit"),
            "{err}"
        );
        // 3.6 GP would take many seconds and gigabytes to decode
        assert!(took < Duration::from_secs(20), "{took:?}");
    }

    // --max-pixels lowers the budget: the 4x3 image (12 pixels) against 11
    let p = copy_pipeline(d, &small, "c.png");
    let args = [
        "run",
        p.to_str().unwrap(),
        "--no-cache",
        "--out",
        out.to_str().unwrap(),
    ];
    let o = cli(&[&args[..], &["--max-pixels", "11"]].concat());
    assert_eq!(code(&o), 65, "{}", stderr(&o));
    assert!(stderr(&o).contains("11 pixels"), "{}", stderr(&o));
    let o = cli(&[&args[..], &["--max-pixels", "12"]].concat());
    assert_eq!(code(&o), 0, "{}", stderr(&o));
}

#[test]
fn outputs_are_the_same_bytes_every_run_and_for_any_thread_count() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let pipe = small_demo(d);
    let mut runs = Vec::new();
    for (i, threads) in ["1", "2", "2"].iter().enumerate() {
        let out = d.join(format!("out{i}"));
        let o = cli(&[
            "run",
            pipe.to_str().unwrap(),
            "-q",
            "--no-cache",
            "--threads",
            threads,
            "--out",
            out.to_str().unwrap(),
        ]);
        assert_eq!(code(&o), 0, "{}", stderr(&o));
        runs.push(files(&out));
    }
    assert_eq!(runs[0].len(), 5, "{:?}", runs[0].keys());
    for r in &runs[1..] {
        assert_eq!(
            r.keys().collect::<Vec<_>>(),
            runs[0].keys().collect::<Vec<_>>()
        );
        for (name, bytes) in r {
            assert!(bytes == &runs[0][name], "{name} differs between runs");
        }
    }
}

#[test]
fn a_truncated_cache_is_recomputed_and_replaced() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let pipe = small_demo(d);
    let cache = d.join("cache");
    let o = run_small(&pipe, &d.join("a"), &cache);
    assert_eq!(code(&o), 0, "{}", stderr(&o));
    let reference = files(&d.join("a"));
    let entries = cache_entries(&cache);
    assert!(entries.len() >= 4, "{entries:?}");
    let originals: Vec<Vec<u8>> = entries.iter().map(|p| std::fs::read(p).unwrap()).collect();
    // every entry cut short, one of them to nothing, one with a flipped byte
    for (i, (p, full)) in entries.iter().zip(&originals).enumerate() {
        let mut bytes = full[..full.len() * i / (entries.len() + 1)].to_vec();
        if i == 1 && full.len() > 40 {
            bytes = full.clone();
            bytes[40] ^= 0xFF;
        }
        std::fs::write(p, bytes).unwrap();
    }
    let o = run_small(&pipe, &d.join("b"), &cache);
    assert_eq!(code(&o), 0, "{}", stderr(&o));
    assert_eq!(files(&d.join("b")), reference);
    // the entries were written anew, whole
    for (p, full) in entries.iter().zip(&originals) {
        assert_eq!(&std::fs::read(p).unwrap(), full, "{}", p.display());
    }
    // and a third run reads them: every node but the five sinks (which
    // always write their file) comes from the cache
    let o = run_small(&pipe, &d.join("c"), &cache);
    assert_eq!(code(&o), 0);
    assert!(
        stderr(&o).starts_with("5 nodes evaluated, 4 cached"),
        "{}",
        stderr(&o)
    );
    assert_eq!(files(&d.join("c")), reference);
}

#[test]
fn two_processes_share_one_cache_directory() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let pipe = small_demo(d);
    let cache = d.join("cache");
    let spawn = |out: &Path| {
        bin()
            .args([
                "run",
                pipe.to_str().unwrap(),
                "-q",
                "--threads",
                "1",
                "--out",
                out.to_str().unwrap(),
                "--cache-dir",
                cache.to_str().unwrap(),
            ])
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap()
    };
    for round in 0..2 {
        let (a, b) = (d.join(format!("a{round}")), d.join(format!("b{round}")));
        let (pa, pb) = (spawn(&a), spawn(&b));
        let (oa, ob) = (
            pa.wait_with_output().unwrap(),
            pb.wait_with_output().unwrap(),
        );
        assert_eq!(code(&oa), 0, "{}", stderr(&oa));
        assert_eq!(code(&ob), 0, "{}", stderr(&ob));
        let fa = files(&a);
        assert_eq!(fa.len(), 5);
        assert_eq!(fa, files(&b));
    }
    // no temporary file is left behind
    for dd in std::fs::read_dir(&cache).unwrap().flatten() {
        for f in std::fs::read_dir(dd.path()).unwrap().flatten() {
            assert!(
                !f.path().to_string_lossy().ends_with(".tmp"),
                "left {}",
                f.path().display()
            );
        }
    }
}

#[test]
fn a_run_killed_mid_way_leaves_a_cache_the_next_run_uses() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let pipe = small_demo(d);
    let reference = {
        let out = d.join("ref");
        let o = run_no_cache(&pipe, &out);
        assert_eq!(code(&o), 0, "{}", stderr(&o));
        files(&out)
    };
    let cache = d.join("cache");
    // kill at several points of the run (SIGKILL: no clean-up of any kind)
    for (i, delay_ms) in [5u64, 40, 150].into_iter().enumerate() {
        let mut child = bin()
            .args([
                "run",
                pipe.to_str().unwrap(),
                "-q",
                "--out",
                d.join(format!("killed{i}")).to_str().unwrap(),
                "--cache-dir",
                cache.to_str().unwrap(),
            ])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        std::thread::sleep(Duration::from_millis(delay_ms));
        let _ = child.kill();
        let _ = child.wait();
        let out = d.join(format!("after{i}"));
        let o = run_small(&pipe, &out, &cache);
        assert_eq!(code(&o), 0, "{}", stderr(&o));
        assert_eq!(files(&out), reference, "after a kill at {delay_ms} ms");
    }
}
