//! `depthgraph batch`: frames from placeholders and sequences, a manifest
//! per frame, re-runs served by the cache, exit codes that tell a permanent
//! failure from a transient one, and the Slurm array script run task by
//! task (the real cluster run is `tests/slurm/run.sh`, started by
//! `.ci/run`).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn bin() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_depthgraph"));
    c.current_dir(root())
        .env("DEPTHGRAPH_BACKEND", "cpu")
        .env_remove("DEPTHGRAPH_FAULT_TRANSIENT");
    c
}

fn code(o: &Output) -> i32 {
    o.status.code().unwrap_or(-1)
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

fn batch(args: &[&str], env: &[(&str, &str)]) -> Output {
    let mut c = bin();
    c.arg("batch").args(args).arg("--quiet");
    for (k, v) in env {
        c.env(k, v);
    }
    c.output().unwrap()
}

/// A small moving-camera pipeline: scene -> Kinect -> fill -> 8-sample
/// refocus -> PNG and EXR per frame.
fn moving(dir: &Path) -> PathBuf {
    let text = r#"(
    version: 1,
    nodes: {
        "scene": (kind: "SyntheticScene", params: (width: 40, height: 30, frame: "{frame}", dolly_m_per_frame: (0.01, 0.0, 0.0))),
        "kinect": (kind: "SimulateKinect", params: (seed: 7),
            inputs: (depth: "scene.depth", color: "scene.color", intrinsics: "scene.intrinsics")),
        "fill": (kind: "DualPullPush",
            inputs: (depth: "kinect.depth", color: "scene.color", intrinsics: "scene.intrinsics")),
        "refocus": (kind: "Refocus", params: (focus_m: 0.95, samples: 8), inputs: (color: "scene.color", depth: "fill.depth")),
        "png": (kind: "SaveColor", params: (path: "f/{frame:03}.png"), inputs: (color: "refocus.color")),
        "exr": (kind: "SaveDepth", params: (path: "f/depth_{frame:03}.exr"), inputs: (depth: "fill.depth")),
    },
    outputs: ["png", "exr"],
)"#;
    let p = dir.join("moving.ron");
    std::fs::write(&p, text).unwrap();
    p
}

#[derive(Debug, serde::Deserialize)]
struct Line {
    frame: u64,
    status: String,
    outputs: Vec<String>,
    error: Option<String>,
    exit_code: u8,
}

fn manifest(path: &Path) -> Vec<Line> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}

/// Every file under `dir/f`, by name.
fn frame_files(dir: &Path) -> BTreeMap<String, Vec<u8>> {
    let mut out = BTreeMap::new();
    for e in std::fs::read_dir(dir.join("f")).unwrap().flatten() {
        out.insert(
            e.file_name().to_string_lossy().into_owned(),
            std::fs::read(e.path()).unwrap(),
        );
    }
    out
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

#[test]
fn a_batch_writes_every_frame_and_a_rerun_is_served_by_the_cache() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let pipe = moving(d);
    let (out, cache) = (d.join("out"), d.join("cache"));
    let args = [
        s(&pipe),
        "--frames",
        "0..20",
        "--out",
        s(&out),
        "--cache-dir",
        s(&cache),
        "--jobs",
        "2",
    ];
    let o = batch(&args, &[]);
    assert_eq!(code(&o), 0, "{}", stderr(&o));
    assert!(stderr(&o).contains("20 frames: 20 done (20 computed, 0 from cache)"));
    let m = manifest(&out.join("manifest.jsonl"));
    assert_eq!(
        m.iter().map(|l| l.frame).collect::<Vec<_>>(),
        (0..20).collect::<Vec<_>>()
    );
    assert!(
        m.iter()
            .all(|l| l.status == "ok" && l.exit_code == 0 && l.outputs.len() == 2)
    );
    let first = frame_files(&out);
    assert_eq!(first.len(), 40);
    // frames differ: the camera moves
    assert_ne!(first["000.png"], first["019.png"]);

    let o = batch(&args, &[]);
    assert_eq!(code(&o), 0, "{}", stderr(&o));
    assert!(
        stderr(&o).contains("20 done (0 computed, 20 from cache)"),
        "{}",
        stderr(&o)
    );
    assert!(
        manifest(&out.join("manifest.jsonl"))
            .iter()
            .all(|l| l.status == "cached")
    );
    assert_eq!(frame_files(&out), first);

    // one frame with `run --frame` is the batch's frame, byte for byte
    let single = d.join("single");
    let o = bin()
        .args([
            "run",
            s(&pipe),
            "--frame",
            "13",
            "--out",
            s(&single),
            "--no-cache",
            "-q",
        ])
        .output()
        .unwrap();
    assert_eq!(code(&o), 0, "{}", stderr(&o));
    let one = frame_files(&single);
    assert_eq!(one.len(), 2);
    assert_eq!(one["013.png"], first["013.png"]);
    assert_eq!(one["depth_013.exr"], first["depth_013.exr"]);

    // every third frame
    let o = batch(
        &[
            s(&pipe),
            "--frames",
            "0..20:3",
            "--out",
            s(&d.join("third")),
            "--no-cache",
        ],
        &[],
    );
    assert_eq!(code(&o), 0, "{}", stderr(&o));
    let m = manifest(&d.join("third/manifest.jsonl"));
    assert_eq!(
        m.iter().map(|l| l.frame).collect::<Vec<_>>(),
        vec![0, 3, 6, 9, 12, 15, 18]
    );

    // more frames into the same folder: the manifest keeps the first
    // run's records beside the new ones (it was emptied), and the live
    // record of the run is gone once the manifest holds it
    let more = [
        s(&pipe),
        "--frames",
        "18..22",
        "--out",
        s(&out),
        "--cache-dir",
        s(&cache),
    ];
    let o = batch(&more, &[]);
    assert_eq!(code(&o), 0, "{}", stderr(&o));
    let m = manifest(&out.join("manifest.jsonl"));
    assert_eq!(
        m.iter().map(|l| l.frame).collect::<Vec<_>>(),
        (0..22).collect::<Vec<_>>()
    );
    assert_eq!(m[17].status, "cached");
    assert_eq!(
        (m[18].status.as_str(), m[20].status.as_str()),
        ("cached", "ok")
    );
    assert!(!out.join("manifest.jsonl.partial").exists());
}

#[test]
fn a_transient_failure_exits_75_and_the_rerun_completes_it() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let pipe = moving(d);
    let (out, cache) = (d.join("out"), d.join("cache"));
    let args = [
        s(&pipe),
        "--frames",
        "0..6",
        "--out",
        s(&out),
        "--cache-dir",
        s(&cache),
    ];
    let o = batch(&args, &[("DEPTHGRAPH_FAULT_TRANSIENT", "4")]);
    assert_eq!(code(&o), 75, "{}", stderr(&o));
    assert!(
        stderr(&o).contains("1 with exit 75 (transient)"),
        "{}",
        stderr(&o)
    );
    let m = manifest(&out.join("manifest.jsonl"));
    assert_eq!(m.len(), 6);
    assert_eq!(m[4].status, "failed");
    assert_eq!(m[4].exit_code, 75);
    assert!(
        m[4].error
            .as_deref()
            .unwrap()
            .contains("injected transient")
    );
    assert!(m.iter().filter(|l| l.frame != 4).all(|l| l.status == "ok"));
    // the fault strikes once: the retry finishes frame 4, the rest are cache hits
    let o = batch(&args, &[("DEPTHGRAPH_FAULT_TRANSIENT", "4")]);
    assert_eq!(code(&o), 0, "{}", stderr(&o));
    let m = manifest(&out.join("manifest.jsonl"));
    assert_eq!(m[4].status, "ok");
    assert!(
        m.iter()
            .filter(|l| l.frame != 4)
            .all(|l| l.status == "cached")
    );
}

/// Writes a TUM RGB-D folder of `n` frames with the project's own writers
/// (a batch of the moving scene), timestamps 1 ms apart for depth.
fn tum_folder(d: &Path, n: u64) -> PathBuf {
    let gen_pipe = d.join("gen.ron");
    std::fs::write(
        &gen_pipe,
        r#"(
    version: 1,
    nodes: {
        "scene": (kind: "SyntheticScene", params: (width: 32, height: 24, frame: "{frame}", dolly_m_per_frame: (0.0, 0.0, 0.02))),
        "kinect": (kind: "SimulateKinect", params: (seed: 1),
            inputs: (depth: "scene.depth", color: "scene.color", intrinsics: "scene.intrinsics")),
        "rgb": (kind: "SaveColor", params: (path: "rgb/{frame:04}.png"), inputs: (color: "scene.color")),
        "depth": (kind: "SaveDepth", params: (path: "depth/{frame:04}.png", format: "png16", scale: 5000.0),
            inputs: (depth: "kinect.depth")),
    },
    outputs: ["rgb", "depth"],
)"#,
    )
    .unwrap();
    let tum = d.join("tum");
    let range = format!("0..{n}");
    let o = batch(
        &[
            s(&gen_pipe),
            "--frames",
            &range,
            "--out",
            s(&tum),
            "--no-cache",
        ],
        &[],
    );
    assert_eq!(code(&o), 0, "{}", stderr(&o));
    let mut rgb = String::from("# color images\n# timestamp filename\n");
    let mut depth = String::from("# depth maps\n");
    for f in 0..n {
        let t = 1000.0 + f as f64 / 30.0;
        rgb += &format!("{t:.6} rgb/{f:04}.png\n");
        depth += &format!("{:.6} depth/{f:04}.png\n", t + 0.001);
    }
    std::fs::write(tum.join("rgb.txt"), rgb).unwrap();
    std::fs::write(tum.join("depth.txt"), depth).unwrap();
    tum
}

#[test]
fn a_tum_sequence_runs_all_frames_and_a_corrupt_frame_fails_alone_with_65() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let tum = tum_folder(d, 5);
    let pipe = d.join("tum.ron");
    std::fs::write(
        &pipe,
        format!(
            r#"(
    version: 1,
    nodes: {{
        "seq": (kind: "LoadSequence", params: (source: "{}", frame: "{{frame}}")),
        "smooth": (kind: "JointBilateral", params: (radius: 2), inputs: (depth: "seq.depth", color: "seq.color")),
        "save": (kind: "SaveDepth", params: (path: "f/{{frame:02}}.exr"), inputs: (depth: "smooth.depth")),
    }},
    outputs: ["save"],
)"#,
            tum.display()
        ),
    )
    .unwrap();
    let (out, cache) = (d.join("out"), d.join("cache"));
    let args = [
        s(&pipe),
        "--frames",
        "all",
        "--out",
        s(&out),
        "--cache-dir",
        s(&cache),
    ];
    let o = batch(&args, &[]);
    assert_eq!(code(&o), 0, "{}", stderr(&o));
    let m = manifest(&out.join("manifest.jsonl"));
    assert_eq!(m.len(), 5);
    assert!(m.iter().all(|l| l.status == "ok"));
    let before = frame_files(&out);

    // the depth of frame 3 is damaged on disk: that frame fails as bad input, the others stay done
    std::fs::write(tum.join("depth/0003.png"), b"\x89PNG\r\n\x1a\n truncated").unwrap();
    let o = batch(&args, &[]);
    assert_eq!(code(&o), 65, "{}", stderr(&o));
    assert!(
        stderr(&o).contains("frame 3:") && stderr(&o).contains("0003.png"),
        "{}",
        stderr(&o)
    );
    let m = manifest(&out.join("manifest.jsonl"));
    assert_eq!(m[3].status, "failed");
    assert_eq!(m[3].exit_code, 65);
    assert!(
        m.iter()
            .filter(|l| l.frame != 3)
            .all(|l| l.status == "cached")
    );
    let after = frame_files(&out);
    assert_eq!(
        after, before,
        "frame 3's earlier output is neither removed nor damaged"
    );

    // a frame past the sequence's end fails as bad input naming the length
    let o = batch(
        &[s(&pipe), "--frames", "4..6", "--out", s(&out), "--no-cache"],
        &[],
    );
    assert_eq!(code(&o), 65, "{}", stderr(&o));
    assert!(stderr(&o).contains("holds 5"), "{}", stderr(&o));
}

#[test]
fn the_slurm_array_script_run_task_by_task_matches_a_local_batch() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let pipe = moving(d);
    let local = d.join("local");
    let o = batch(
        &[
            s(&pipe),
            "--frames",
            "0..20",
            "--out",
            s(&local),
            "--no-cache",
        ],
        &[],
    );
    assert_eq!(code(&o), 0, "{}", stderr(&o));

    let (out, cache) = (d.join("slurm_out"), d.join("shared_cache"));
    // `batch` of the 20 frames into `out` with the shared cache, on Slurm
    let slurm = |extra: &[&str], env: &[(&str, &str)]| {
        let mut a = vec![
            s(&pipe),
            "--frames",
            "0..20",
            "--out",
            s(&out),
            "--cache-dir",
            s(&cache),
            "--slurm",
        ];
        a.extend_from_slice(extra);
        batch(&a, env)
    };
    let o = slurm(
        &[
            "--dry-run",
            "--frames-per-task",
            "6",
            "--array-max",
            "2",
            "--retries",
            "2",
        ],
        &[],
    );
    assert_eq!(code(&o), 0, "{}", stderr(&o));
    let script = String::from_utf8_lossy(&o.stdout).into_owned();
    assert!(script.contains("#SBATCH --array=0-3%2"), "{script}");
    let script_path = out.join("slurm/batch.sbatch");
    assert_eq!(
        std::fs::read_to_string(&script_path).unwrap().trim(),
        script.trim()
    );
    // before any task ran, every frame is missing: worth a retry
    let o = batch(&["--collect", s(&out)], &[]);
    assert_eq!(code(&o), 75, "{}", stderr(&o));
    assert!(stderr(&o).contains("20 never reported"), "{}", stderr(&o));
    // the tasks run the pipeline as submitted: the file edited (here
    // broken) while they wait in the queue changes nothing
    let submitted = std::fs::read(&pipe).unwrap();
    std::fs::write(&pipe, "not a pipeline").unwrap();

    // each array task as Slurm would start it; task 1 (frames 6..12) meets a
    // transient failure at frame 8 and retries within its allocation
    for task in 0..4 {
        let o = Command::new("bash")
            .arg(&script_path)
            .env("SLURM_ARRAY_TASK_ID", task.to_string())
            .env("DEPTHGRAPH_BACKEND", "cpu")
            .env("DEPTHGRAPH_FAULT_TRANSIENT", "8")
            .output()
            .unwrap();
        assert_eq!(code(&o), 0, "task {task}: {}", stderr(&o));
        if task == 1 {
            assert!(stderr(&o).contains("retry 1 of 2"), "{}", stderr(&o));
        }
    }
    let o = batch(&["--collect", s(&out)], &[]);
    assert_eq!(code(&o), 0, "{}", stderr(&o));
    let m = manifest(&out.join("manifest.jsonl"));
    assert_eq!(
        m.iter().map(|l| l.frame).collect::<Vec<_>>(),
        (0..20).collect::<Vec<_>>()
    );
    assert!(m.iter().all(|l| l.exit_code == 0));
    assert_eq!(frame_files(&out), frame_files(&local));
    std::fs::write(&pipe, &submitted).unwrap();

    // A refused submission into the same folder leaves the finished job's
    // file, and what --collect gives, as they were.
    let job_before = std::fs::read(out.join("slurm/job.json")).unwrap();
    let manifest_before = std::fs::read(out.join("manifest.jsonl")).unwrap();
    let path = fake_commands(
        d,
        &[(
            "sbatch",
            "#!/bin/sh\necho 'sbatch: error: invalid partition specified: typo' >&2\nexit 1\n"
                .to_string(),
        )],
    );
    let snapshots = || {
        std::fs::read_dir(out.join("slurm"))
            .unwrap()
            .filter(|e| {
                let name = e.as_ref().unwrap().file_name();
                name.to_string_lossy().starts_with("pipeline-")
            })
            .count()
    };
    let snapshots_before = snapshots();
    let o = slurm(&["--partition", "typo"], &[("PATH", &path)]);
    assert_eq!(code(&o), 2, "{}", stderr(&o));
    assert!(stderr(&o).contains("invalid partition"), "{}", stderr(&o));
    // the refused job's copy of the pipeline is not left behind
    assert_eq!(snapshots(), snapshots_before);
    assert_eq!(
        std::fs::read(out.join("slurm/job.json")).unwrap(),
        job_before
    );
    let o = batch(&["--collect", s(&out)], &[]);
    assert_eq!(code(&o), 0, "{}", stderr(&o));
    assert_eq!(
        std::fs::read(out.join("manifest.jsonl")).unwrap(),
        manifest_before
    );
    // A dry run names a new submission, none of whose tasks has run:
    // --collect says so and leaves the manifest as it was.
    let o = slurm(&["--dry-run"], &[]);
    assert_eq!(code(&o), 0, "{}", stderr(&o));
    let o = batch(&["--collect", s(&out)], &[]);
    assert_eq!(code(&o), 75, "{}", stderr(&o));
    assert!(stderr(&o).contains("nothing collected"), "{}", stderr(&o));
    assert_eq!(
        std::fs::read(out.join("manifest.jsonl")).unwrap(),
        manifest_before
    );
    // A GPU job is submitted from a login node without one: the tasks
    // choose their device where they run.
    let o = slurm(
        &["--dry-run", "--backend", "gpu"],
        &[("DEPTHGRAPH_ADAPTER", "no adapter is called this")],
    );
    assert_eq!(code(&o), 0, "{}", stderr(&o));
    assert!(
        String::from_utf8_lossy(&o.stdout).contains("--backend gpu"),
        "{}",
        String::from_utf8_lossy(&o.stdout)
    );
    // a cache URL the tasks could not open is refused before submitting
    let o = slurm(&["--dry-run", "--cache-url", "nope://x"], &[]);
    assert_eq!(code(&o), 2, "{}", stderr(&o));
    assert!(stderr(&o).contains("nope://x"), "{}", stderr(&o));
}

/// On a multi-cluster setup `sbatch --parsable` prints `id;cluster`, and
/// `--wait` asks squeue on that cluster (elsewhere the id is unknown,
/// which read as a job that had ended: it collected at once, mid-job).
/// `scripts` (name, shell text) as executables in `dir/fakebin`, and a
/// PATH that finds them before the system's commands.
fn fake_commands(dir: &Path, scripts: &[(&str, String)]) -> String {
    use std::os::unix::fs::PermissionsExt;
    let fake = dir.join("fakebin");
    std::fs::create_dir_all(&fake).unwrap();
    for (name, text) in scripts {
        let f = fake.join(name);
        std::fs::write(&f, text).unwrap();
        std::fs::set_permissions(&f, std::fs::Permissions::from_mode(0o755)).unwrap();
    }
    format!(
        "{}:{}",
        fake.display(),
        std::env::var("PATH").unwrap_or_default()
    )
}

#[test]
fn a_multi_cluster_job_is_waited_for_on_its_cluster() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let pipe = moving(d);
    let out = d.join("out");
    let log = d.join("squeue.log");
    let path = fake_commands(
        d,
        &[
            ("sbatch", "#!/bin/sh\necho '4242;clusterB'\n".to_string()),
            (
                "squeue",
                format!(
                    "#!/bin/sh\necho \"$@\" >> '{}'\ncase \"$*\" in *'-M clusterB'*) exit 0;; esac\n\
                 echo 'slurm_load_jobs error: Invalid job id specified' >&2\nexit 1\n",
                    log.display()
                ),
            ),
        ],
    );
    let o = batch(
        &[
            s(&pipe),
            "--frames",
            "0..4",
            "--out",
            s(&out),
            "--no-cache",
            "--slurm",
            "--wait",
        ],
        &[("PATH", &path)],
    );
    // the fake job ran nothing: every frame missing, nothing collected
    assert_eq!(code(&o), 75, "{}", stderr(&o));
    assert!(stderr(&o).contains("nothing collected"), "{}", stderr(&o));
    let asked = std::fs::read_to_string(&log).unwrap();
    assert!(
        asked.contains("-M clusterB") && asked.contains("-j 4242"),
        "{asked}"
    );
    let job = std::fs::read_to_string(out.join("slurm/job.json")).unwrap();
    assert!(job.contains("\"4242\""), "{job}");
}

#[test]
fn batches_that_cannot_be_right_are_refused_before_running() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let pipe = moving(d);
    let out = d.join("out");
    // outputs without a placeholder would overwrite each other
    let o = batch(
        &[
            s(&pipe),
            "--frames",
            "0..3",
            "--out",
            s(&out),
            "--set",
            "png.path=same.png",
        ],
        &[],
    );
    assert_eq!(code(&o), 2, "{}", stderr(&o));
    assert!(
        stderr(&o).contains("`png.path` = \"same.png\""),
        "{}",
        stderr(&o)
    );
    // a single frame may write a fixed name
    let o = batch(
        &[
            s(&pipe),
            "--frames",
            "2",
            "--out",
            s(&out),
            "--no-cache",
            "--set",
            "png.path=same.png",
        ],
        &[],
    );
    assert_eq!(code(&o), 0, "{}", stderr(&o));
    assert!(out.join("same.png").exists());
    for (frames, says) in [
        ("all", "needs a LoadSequence"),
        ("3..3", "holds no frame"),
        ("0..=4", "END is excluded"),
    ] {
        let o = batch(&[s(&pipe), "--frames", frames, "--out", s(&out)], &[]);
        assert_eq!(code(&o), 2, "{frames}: {}", stderr(&o));
        assert!(stderr(&o).contains(says), "{frames}: {}", stderr(&o));
    }
    // Slurm's options without --slurm would silently run here instead
    let o = batch(
        &[s(&pipe), "--frames", "0..2", "--out", s(&out), "--dry-run"],
        &[],
    );
    assert_eq!(code(&o), 2, "{}", stderr(&o));
    assert!(stderr(&o).contains("--slurm"), "{}", stderr(&o));
    // a line break cannot go into an #SBATCH line (the rest would run as a
    // command): refused, and no script written
    let o = batch(
        &[
            s(&pipe),
            "--frames",
            "0..2",
            "--out",
            s(&out),
            "--slurm",
            "--dry-run",
            "--partition",
            "debug\ntouch pwned",
        ],
        &[],
    );
    assert_eq!(code(&o), 2, "{}", stderr(&o));
    assert!(stderr(&o).contains("line break"), "{}", stderr(&o));
    assert!(!out.join("slurm/batch.sbatch").exists());
    // an array task with a bad submission id fails before any frame runs
    let task_out = d.join("task_out");
    let o = batch(
        &[
            s(&pipe),
            "--frames",
            "0..2",
            "--out",
            s(&task_out),
            "--no-cache",
            "--task",
            "0",
            "--submission",
            "../elsewhere",
        ],
        &[],
    );
    assert_eq!(code(&o), 2, "{}", stderr(&o));
    assert!(stderr(&o).contains("not a submission id"), "{}", stderr(&o));
    assert!(!task_out.join("f").exists(), "a frame ran");
    // a pipeline without a frame index
    let o = batch(
        &[
            "graphs/depth_fill.ron",
            "--frames",
            "0..2",
            "--out",
            s(&out),
        ],
        &[],
    );
    assert_eq!(code(&o), 2, "{}", stderr(&o));
    assert!(stderr(&o).contains("takes no frame index"));
    // a malformed placeholder is located
    let o = batch(
        &[
            s(&pipe),
            "--frames",
            "0..2",
            "--out",
            s(&out),
            "--set",
            "png.path=x_{frame:zz}.png",
        ],
        &[],
    );
    assert_eq!(code(&o), 2, "{}", stderr(&o));
    assert!(stderr(&o).contains("`{frame:zz}`"), "{}", stderr(&o));
}

/// The object-store cache exists with the `s3` feature (on by default).
#[cfg(feature = "s3")]
#[test]
fn two_batches_with_separate_disk_caches_share_an_object_store() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let pipe = moving(d);
    let url = format!("file://{}/store/prefix", d.display());
    let run = |name: &str| {
        batch(
            &[
                s(&pipe),
                "--frames",
                "0..5",
                "--out",
                s(&d.join(name)),
                "--cache-dir",
                s(&d.join(format!("{name}_cache"))),
                "--cache-url",
                &url,
            ],
            &[],
        )
    };
    let o = run("a");
    assert_eq!(code(&o), 0, "{}", stderr(&o));
    assert!(
        manifest(&d.join("a/manifest.jsonl"))
            .iter()
            .all(|l| l.status == "ok")
    );
    // the second process has an empty disk cache: every result comes from the store
    let o = run("b");
    assert_eq!(code(&o), 0, "{}", stderr(&o));
    assert!(
        stderr(&o).contains("5 done (0 computed, 5 from cache)"),
        "{}",
        stderr(&o)
    );
    assert_eq!(frame_files(&d.join("a")), frame_files(&d.join("b")));
    // a bad URL is a usage error, before anything runs
    let o = batch(
        &[
            s(&pipe),
            "--frames",
            "0..2",
            "--out",
            s(&d.join("c")),
            "--cache-url",
            "nope://x",
        ],
        &[],
    );
    assert_eq!(code(&o), 2, "{}", stderr(&o));
    assert!(
        stderr(&o).contains("--cache-url nope://x"),
        "{}",
        stderr(&o)
    );
    assert!(!d.join("c/manifest.jsonl").exists());
}
