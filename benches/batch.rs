//! `depthgraph batch` throughput: N frames of `graphs/sequence_demo.ron`
//! (640x480: Kinect simulation, dual pull-push fill, 64-sample refocus) run
//! locally with `--jobs 1` and `--jobs 2`, against N times one frame's
//! single-thread time divided by the cores, with each run's peak memory;
//! and, when a Slurm cluster answers (`sinfo`), the same frames as an array
//! job.
//!
//!   cargo bench --bench batch                       # N = 100
//!   DEPTHGRAPH_BATCH_FRAMES=20 cargo bench --bench batch
//!
//! Every run is uncached (`--no-cache`), so each frame is computed.

use std::path::Path;
use std::process::Command;
use std::time::Instant;

fn bin() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_depthgraph"));
    c.current_dir(env!("CARGO_MANIFEST_DIR"))
        .env("DEPTHGRAPH_BACKEND", "cpu")
        .env_remove("DEPTHGRAPH_FAULT_TRANSIENT");
    c
}

/// Runs `args`, returning wall seconds and the peak memory the batch
/// reported (MiB), or the failure's text.
fn timed(args: &[&str]) -> Result<(f64, Option<f64>), String> {
    let t = Instant::now();
    let o = bin().args(args).output().map_err(|e| e.to_string())?;
    let wall = t.elapsed().as_secs_f64();
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    if !o.status.success() {
        return Err(err);
    }
    let peak = err
        .split("peak memory ")
        .nth(1)
        .and_then(|r| r.split_whitespace().next())
        .and_then(|m| m.parse().ok());
    Ok((wall, peak))
}

fn main() {
    let n: u64 = std::env::var("DEPTHGRAPH_BATCH_FRAMES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(100);
    let cores = std::thread::available_parallelism().map_or(1, |c| c.get());
    let dir = match tempfile::tempdir() {
        Ok(d) => d,
        Err(e) => {
            eprintln!("batch bench: no temporary directory: {e}");
            std::process::exit(1);
        }
    };
    let d = dir.path();
    let s = |p: &Path| p.to_string_lossy().into_owned();
    let frames = format!("0..{n}");

    // one frame on one thread, the median of three frames
    let mut single = Vec::new();
    for f in [0u64, n / 2, n.saturating_sub(1)] {
        let out = s(&d.join("single"));
        let fr = f.to_string();
        match timed(&[
            "run",
            "graphs/sequence_demo.ron",
            "--frame",
            &fr,
            "--out",
            &out,
            "--no-cache",
            "--threads",
            "1",
            "-q",
        ]) {
            Ok((w, _)) => single.push(w),
            Err(e) => {
                eprintln!("batch bench: one frame failed: {e}");
                std::process::exit(1);
            }
        }
    }
    single.sort_by(f64::total_cmp);
    let t1 = single[1];
    let ideal = n as f64 * t1 / cores as f64;
    println!(
        "one frame, 1 thread: {:.0} ms (median of 3, process start included)",
        t1 * 1e3
    );
    println!("ideal for {n} frames on {cores} cores: {ideal:.1} s\n");
    println!("| run | wall s | vs ideal | per frame ms | peak MiB |");
    println!("|---|---:|---:|---:|---:|");
    let mut local2 = None;
    for jobs in [1usize, 2, 4] {
        let out = s(&d.join(format!("jobs{jobs}")));
        let j = jobs.to_string();
        match timed(&[
            "batch",
            "graphs/sequence_demo.ron",
            "--frames",
            &frames,
            "--out",
            &out,
            "--no-cache",
            "--jobs",
            &j,
            "--quiet",
        ]) {
            Ok((w, peak)) => {
                if jobs == 2 {
                    local2 = Some(w);
                }
                println!(
                    "| local, --jobs {jobs} | {w:.1} | {:.2}x | {:.0} | {} |",
                    w / ideal,
                    w * 1e3 / n as f64,
                    peak.map(|p| format!("{p:.0}"))
                        .unwrap_or_else(|| "?".into())
                );
            }
            Err(e) => println!("| local, --jobs {jobs} | failed: {} | | | |", e.trim()),
        }
    }
    let slurm = Command::new("sinfo").arg("-h").output();
    if !slurm.is_ok_and(|o| o.status.success()) {
        println!("\nno Slurm cluster answers (sinfo): the array job was not measured");
        return;
    }
    for k in [10usize, 25] {
        let out = s(&d.join(format!("slurm{k}")));
        let kk = k.to_string();
        match timed(&[
            "batch",
            "graphs/sequence_demo.ron",
            "--frames",
            &frames,
            "--out",
            &out,
            "--no-cache",
            "--jobs",
            "1",
            "--quiet",
            "--slurm",
            "--frames-per-task",
            &kk,
            "--wait",
        ]) {
            Ok((w, _)) => {
                let span = task_span(Path::new(&out));
                println!(
                    "| Slurm array, {k} frames per task, --jobs 1 per task | {w:.1} | {:.2}x | {:.0} | |{}{}",
                    w / ideal,
                    w * 1e3 / n as f64,
                    local2
                        .map(|l| format!(" local --jobs 2 x {:.2};", w / l))
                        .unwrap_or_default(),
                    span.map(|s| format!(
                        " first task start to last task end {s:.1} s{}",
                        local2
                            .map(|l| format!(" (x {:.2} of local)", s / l))
                            .unwrap_or_default()
                    ))
                    .unwrap_or_default()
                );
            }
            Err(e) => println!("| Slurm array, {k} per task | failed: {} | | | |", e.trim()),
        }
    }
}

/// Seconds from the first array task's start to the last one's end: each
/// part file is written when its task ends, and a task with `--jobs 1`
/// started its frames' summed time before that. This leaves out what
/// Slurm adds before the first task and `sbatch --wait`'s polling after the
/// last.
fn task_span(out: &Path) -> Option<f64> {
    let mut first_start = f64::INFINITY;
    let mut last_end = f64::NEG_INFINITY;
    for sub in std::fs::read_dir(out.join("parts")).ok()?.flatten() {
        for part in std::fs::read_dir(sub.path()).ok()?.flatten() {
            let end = part
                .metadata()
                .ok()?
                .modified()
                .ok()?
                .duration_since(std::time::UNIX_EPOCH)
                .ok()?
                .as_secs_f64();
            let text = std::fs::read_to_string(part.path()).ok()?;
            let busy: f64 = text
                .lines()
                .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
                .filter_map(|v| v["ms"].as_f64())
                .sum::<f64>()
                / 1e3;
            first_start = first_start.min(end - busy);
            last_end = last_end.max(end);
        }
    }
    (last_end > first_start).then_some(last_end - first_start)
}
