//! The `batch` subcommand: arguments and printing around
//! [`depthgraph::batch`].

use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{Context, Result};
use clap::Args;
use depthgraph::backend::Backend;
use depthgraph::batch::{
    BatchError, BatchSummary, Collected, FrameRecord, FrameRunner, JobFile, ManifestWriter,
    SlurmPlan, check_outputs_per_frame, collect, merge_manifest, part_path, peak_rss_mib,
    sequence_length, slurm_script, task_count, task_frames, write_job, write_manifest,
};
use depthgraph::graph::frames::FrameSelection;
use depthgraph::graph::prelude::*;
use depthgraph::{LoadError, read_document};

#[derive(Args)]
pub struct BatchArgs {
    /// Pipeline file (RON) with {frame} placeholders in its paths (not with --collect).
    #[arg(required_unless_present = "collect")]
    file: Option<PathBuf>,
    /// Frames: START..END (END excluded), START..END:STEP, N, or all (every frame of its
    /// LoadSequence). Default: the pipeline's own `frames: "..."`.
    #[arg(long)]
    frames: Option<String>,
    /// Directory of the outputs, manifest.jsonl, and the Slurm files.
    #[arg(long, default_value = "out")]
    out: PathBuf,
    /// Frames in flight at once (memory grows with it; 0 = one per core).
    #[arg(long, default_value_t = 0)]
    jobs: usize,
    /// Override a parameter: node.param=value (RON syntax; bare words are text).
    #[arg(long = "set", value_name = "NODE.PARAM=VALUE")]
    sets: Vec<String>,
    #[command(flatten)]
    cache: crate::CacheArgs,
    /// In-memory cache budget in MiB: frames rarely share results in memory,
    /// so little is kept there and memory grows with --jobs, not the batch.
    #[arg(long, default_value_t = 64)]
    memory_mb: usize,
    /// Worker threads of the engine all frames share (0 = one per core).
    #[arg(long, default_value_t = 0)]
    threads: usize,
    /// The most pixels one input file may hold.
    #[arg(long, default_value_t = depthgraph::graph::node::DEFAULT_MAX_PIXELS, value_parser = clap::value_parser!(usize))]
    max_pixels: usize,
    /// No progress bar.
    #[arg(long, short)]
    quiet: bool,
    /// Where the device node kinds run (as `run`).
    #[arg(long, value_enum)]
    backend: Option<Backend>,
    /// Submit the batch as a Slurm array job (sbatch) instead of running it here.
    #[arg(long)]
    slurm: bool,
    /// Slurm: at most this many array tasks at once.
    #[arg(long, requires = "slurm")]
    array_max: Option<usize>,
    /// Slurm: frames per array task.
    #[arg(long, default_value_t = 10)]
    frames_per_task: usize,
    /// Slurm: the partition.
    #[arg(long, requires = "slurm")]
    partition: Option<String>,
    /// Slurm: retries of a task that fails transiently (exit 75).
    #[arg(long, default_value_t = 3, requires = "slurm")]
    retries: u32,
    /// Slurm: write and print the script and the job file, submit nothing.
    #[arg(long, requires = "slurm")]
    dry_run: bool,
    /// Slurm: wait for the job to end (squeue, once a second), then collect its manifest.
    #[arg(long, requires = "slurm")]
    wait: bool,
    /// Run array task N's frames and write its part of the manifest (what the Slurm script runs).
    #[arg(long, value_name = "N", requires = "submission")]
    task: Option<usize>,
    /// The submission whose part array task N writes (OUT/parts/ID/).
    #[arg(long, value_name = "ID", requires = "task")]
    submission: Option<String>,
    /// Merge the parts of a Slurm batch in DIR into DIR/manifest.jsonl and report.
    #[arg(long, value_name = "DIR", conflicts_with_all = ["file", "slurm", "task"])]
    collect: Option<PathBuf>,
}

fn fail(e: &BatchError) -> ExitCode {
    eprintln!("error: {e}");
    ExitCode::from(e.exit_code())
}

fn report(summary: &BatchSummary, records: &[FrameRecord]) {
    for r in records.iter().filter(|r| r.error.is_some()) {
        if let Some(e) = &r.error {
            eprintln!("frame {}: {e}", r.frame);
        }
    }
    if !summary.missing.is_empty() {
        eprintln!("frames never reported: {:?}", summary.missing);
    }
    eprintln!("{}", summary.line());
}

pub fn cmd_batch(args: &BatchArgs) -> Result<ExitCode> {
    if let Some(dir) = &args.collect {
        return Ok(match collect(dir) {
            Ok(c) => collected(&c, dir),
            Err(e) => fail(&e),
        });
    }
    let Some(file) = &args.file else {
        return Ok(fail(&BatchError::Usage(
            "a pipeline file is required (or --collect DIR)".into(),
        )));
    };
    let doc = match read_document(file, &args.sets) {
        Ok(d) => d,
        Err(LoadError::Check(errs)) => {
            eprintln!("{errs}");
            return Ok(ExitCode::from(2));
        }
        Err(e) => {
            eprintln!("error: {e}");
            return Ok(ExitCode::from(2));
        }
    };
    for n in &doc.notices {
        eprintln!("note: {n}");
    }
    let Some(frames_text) = args.frames.as_ref().or(doc.frames.as_ref()) else {
        return Ok(fail(&BatchError::Usage(format!(
            "--frames is required: {} names no default `frames`",
            file.display()
        ))));
    };
    let selection = match FrameSelection::parse(frames_text) {
        Ok(s) => s,
        Err(e) => return Ok(fail(&BatchError::Usage(e.to_string()))),
    };
    // the pipeline as its first frame would run it: checked once up front,
    // on the CPU kinds (the same kinds, ports and parameters) before any
    // device is probed, then with the backend's
    let first = match selection {
        FrameSelection::Range { start, .. } => start,
        FrameSelection::All => 0,
    };
    let mut reg = depthgraph::nodes::registry().context("building the node registry")?;
    if let Err(e) = doc.for_frame(first).and_then(|d| Pipeline::check(&d, &reg)) {
        return Ok(fail(&BatchError::Check(CheckErrors(e))));
    }
    // A Slurm submission only checks the choice: the tasks take their
    // device where they run (a login node without a GPU submits a GPU job).
    let chosen = match Backend::resolve(args.backend).and_then(|b| {
        if args.slurm {
            Ok(None)
        } else {
            depthgraph::backend::apply(b, &mut reg).map(Some)
        }
    }) {
        Ok(c) => c,
        Err(e) => {
            eprintln!("error: {e}");
            return Ok(ExitCode::from(match e {
                depthgraph::backend::BackendError::BadVariable(_) => 2,
                depthgraph::backend::BackendError::NoDevice(_) => {
                    FailureKind::Unavailable.exit_code()
                }
            }));
        }
    };
    let p = match doc.for_frame(first).and_then(|d| Pipeline::check(&d, &reg)) {
        Ok(p) => p,
        Err(e) => return Ok(fail(&BatchError::Check(CheckErrors(e)))),
    };
    let count = match sequence_length(&p) {
        Some(Ok(n)) => Some(n),
        Some(Err(e)) => return Ok(fail(&BatchError::Usage(format!("the sequence: {e}")))),
        None => None,
    };
    let Some(frames) = selection.frames(count) else {
        return Ok(fail(&BatchError::Usage(
            "--frames all needs a LoadSequence node to say how many frames there are; give a range such as 0..100".into(),
        )));
    };
    if frames.is_empty() {
        return Ok(fail(&BatchError::Usage(
            "the sequence holds no frame".into(),
        )));
    }
    if frames.len() > 1 {
        if doc.frame_params().is_empty() {
            return Ok(fail(&BatchError::Usage(format!(
                "{} takes no frame index (no {{frame}} placeholder): every frame would be the same",
                file.display()
            ))));
        }
        if let Err(e) = check_outputs_per_frame(&doc, &reg) {
            return Ok(fail(&e));
        }
    }
    let jobs = if args.jobs == 0 {
        std::thread::available_parallelism().map_or(1, |n| n.get())
    } else {
        args.jobs
    };
    let cache_dir = args.cache.dir();
    if args.slurm {
        if let (Some(url), false) = (&args.cache.cache_url, args.cache.no_cache)
            && let Err(e) = depthgraph::check_cache_url(url)
        {
            eprintln!("error: {e}");
            return Ok(ExitCode::from(e.kind.exit_code()));
        }
        return slurm(args, file, &doc, &frames, &cache_dir);
    }
    let remote = match args.cache.remote() {
        Ok(r) => r,
        Err(e) => {
            eprintln!("error: {e}");
            return Ok(ExitCode::from(e.kind.exit_code()));
        }
    };
    let engine = Engine::new(EngineOptions {
        memory_budget_bytes: args.memory_mb.saturating_mul(1 << 20),
        disk: args.cache.disk(),
        threads: args.threads,
        remote,
    })?;
    let runner = FrameRunner {
        doc: &doc,
        registry: &reg,
        engine: &engine,
        out_dir: args.out.clone(),
        protected_files: vec![file.clone()],
        max_pixels: Some(args.max_pixels),
    };
    if let Some(task) = args.task {
        // the part's name first: a bad id fails before any frame runs
        let submission = args.submission.as_deref().unwrap_or_default();
        if !depthgraph::batch::valid_submission_id(submission) {
            return Ok(fail(&BatchError::Usage(format!(
                "--submission `{submission}` is not a submission id"
            ))));
        }
        let mine = task_frames(&frames, args.frames_per_task, task);
        // the part holds each frame's record as it finishes (a task killed
        // by its time limit still says what it did), then all in order
        let part = part_path(&args.out, submission, task);
        let live = match ManifestWriter::create(&part) {
            Ok(m) => m,
            Err(e) => return Ok(fail(&e)),
        };
        let records = runner.run_all(mine, jobs, &|r| live.append(r));
        let summary = BatchSummary::of(&records, mine);
        if let Err(e) = write_manifest(&part, &records) {
            return Ok(fail(&e));
        }
        report(&summary, &records);
        return Ok(ExitCode::from(summary.exit_code()));
    }

    // Records go to manifest.jsonl.partial as frames finish; manifest.jsonl
    // takes them at the end, beside the records it holds of other frames
    // (an interrupted run leaves it as it was, and the partial file says
    // what was done).
    let manifest_path = args.out.join("manifest.jsonl");
    let manifest = match ManifestWriter::create(&args.out.join("manifest.jsonl.partial")) {
        Ok(m) => m,
        Err(e) => return Ok(fail(&e)),
    };
    let bar = (!args.quiet && std::io::stderr().is_terminal()).then(|| {
        let b = indicatif::ProgressBar::new(frames.len() as u64);
        let style = indicatif::ProgressStyle::with_template(
            "{bar:30} {pos}/{len} frames, {elapsed} elapsed, ETA {eta} {msg}",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar());
        b.set_style(style);
        b
    });
    eprintln!(
        "batch: {} frames, {jobs} at a time, {} threads (backend: {})",
        frames.len(),
        engine.threads(),
        chosen.as_ref().map_or("cpu", |c| c.used)
    );
    let t = std::time::Instant::now();
    let records = runner.run_all(&frames, jobs, &|r| {
        manifest.append(r);
        if let Some(b) = &bar {
            if r.error.is_some() {
                b.set_message(format!("(frame {} failed)", r.frame));
            }
            b.inc(1);
        }
    });
    if let Some(b) = &bar {
        b.finish_and_clear();
    }
    let wall = t.elapsed().as_secs_f64();
    // the final manifest in frame order
    match merge_manifest(&manifest_path, &records) {
        Ok(Some(aside)) => eprintln!(
            "warning: {} could not be read; it is kept as {}",
            manifest_path.display(),
            aside.display()
        ),
        Ok(None) => {}
        Err(e) => return Ok(fail(&e)),
    }
    let _ = std::fs::remove_file(manifest.path());
    let summary = BatchSummary::of(&records, &frames);
    report(&summary, &records);
    if engine.remote_failed() {
        eprintln!(
            "warning: the --cache-url store failed during the run and was not used after that"
        );
    }
    let rss = peak_rss_mib()
        .map(|m| format!(", peak memory {m:.0} MiB"))
        .unwrap_or_default();
    eprintln!(
        "{wall:.2} s ({:.0} ms per frame{rss}); manifest {}",
        wall * 1e3 / frames.len() as f64,
        manifest_path.display()
    );
    Ok(ExitCode::from(summary.exit_code()))
}

fn absolute(p: &Path) -> Result<PathBuf> {
    std::path::absolute(p)
        .with_context(|| format!("{}: cannot make the path absolute", p.display()))
}

/// Writes the array job's script and job file; submits it unless
/// `--dry-run`; with `--wait`, collects its manifest when it ends.
fn slurm(
    args: &BatchArgs,
    file: &Path,
    doc: &Document,
    frames: &[u64],
    cache_dir: &Path,
) -> Result<ExitCode> {
    let out = absolute(&args.out)?;
    let file = absolute(file)?;
    let submission = depthgraph::batch::new_submission_id();
    // The tasks run a copy of the pipeline as checked now (with --set), so
    // an edit of the file while tasks wait in the queue changes no frame.
    // (written once the script is sure to be; removed if sbatch refuses)
    let snapshot = out.join("slurm").join(format!("pipeline-{submission}.ron"));
    let workdir = std::env::current_dir().context("the working directory")?;
    let exe = std::env::current_exe().context("the path of this program")?;
    let k = args.frames_per_task.max(1);
    let tasks = task_count(frames.len(), k);
    if tasks > 1000 {
        eprintln!(
            "note: {tasks} array tasks; Slurm's default MaxArraySize (1001) refuses more than 1000: raise --frames-per-task if sbatch refuses the job"
        );
    }
    // the frames resolved now (`all` becomes its range), so every task sees the same list
    let spec = match (frames.first(), frames.last()) {
        (Some(&a), Some(&b)) if frames.len() as u64 == b - a + 1 => format!("{a}..{}", b + 1),
        _ => frames_text(frames),
    };
    let mut cmd: Vec<String> = vec![
        exe.display().to_string(),
        "batch".into(),
        snapshot.display().to_string(),
        "--frames".into(),
        spec,
        "--out".into(),
        out.display().to_string(),
        "--frames-per-task".into(),
        k.to_string(),
        "--submission".into(),
        submission.clone(),
        "--jobs".into(),
        args.jobs.to_string(),
        "--threads".into(),
        args.threads.to_string(),
        "--memory-mb".into(),
        args.memory_mb.to_string(),
        "--max-pixels".into(),
        args.max_pixels.to_string(),
        "--quiet".into(),
    ];
    if args.cache.no_cache {
        cmd.push("--no-cache".into());
    } else {
        cmd.push("--cache-dir".into());
        cmd.push(absolute(cache_dir)?.display().to_string());
        cmd.push("--cache-mb".into());
        cmd.push(args.cache.cache_mb.to_string());
    }
    if let Some(u) = &args.cache.cache_url {
        cmd.push("--cache-url".into());
        cmd.push(u.clone());
    }
    if let Some(b) = args.backend {
        cmd.push("--backend".into());
        cmd.push(b.name().to_string());
    }
    // (the --set values are in the snapshot)
    let plan = SlurmPlan {
        frames_per_task: k,
        array_max: args.array_max,
        partition: args.partition.clone(),
        retries: args.retries,
    };
    let name = format!(
        "depthgraph-{}",
        file.file_stem()
            .map(|s| s.to_string_lossy())
            .unwrap_or_default()
    );
    // a line break would end an #SBATCH line (the rest runs as a command,
    // and sbatch ignores every directive after it): refused, not quoted
    let texts = [
        name.clone(),
        workdir.display().to_string(),
        out.display().to_string(),
    ];
    if let Some(bad) = texts
        .iter()
        .chain(&cmd)
        .chain(plan.partition.iter())
        .find(|t| t.contains(['\n', '\r']))
    {
        return Ok(fail(&BatchError::Usage(format!(
            "{bad:?} holds a line break, which an sbatch script cannot carry"
        ))));
    }
    let script = slurm_script(&name, &cmd, &workdir, &out, tasks, &plan);
    let mut job = JobFile {
        submission,
        pipeline: snapshot.display().to_string(),
        frames: frames.to_vec(),
        frames_per_task: k,
        tasks,
        job_id: None,
    };
    let script_path = out.join("slurm").join("batch.sbatch");
    let text = doc.to_ron();
    let written = depthgraph::nodes::io::write_atomic(&snapshot, |tmp| std::fs::write(tmp, &text))
        .and_then(|_| {
            depthgraph::nodes::io::write_atomic(&script_path, |tmp| std::fs::write(tmp, &script))
        });
    if let Err(e) = written {
        eprintln!("error: {e}");
        return Ok(ExitCode::from(e.kind().exit_code()));
    }
    if args.dry_run {
        // (the job file for a submission by hand; a real one is written
        // once sbatch has accepted it, so a refused one leaves the last
        // job's file, and with it what --collect reads, as it was)
        if let Err(e) = write_job(&out, &job) {
            return Ok(fail(&e));
        }
        println!("{script}");
        eprintln!(
            "dry run: {} frames in {tasks} array tasks of {k}; nothing submitted (submit with: sbatch {})",
            frames.len(),
            script_path.display()
        );
        return Ok(ExitCode::SUCCESS);
    }
    let mut sbatch = std::process::Command::new("sbatch");
    sbatch.arg("--parsable").arg(&script_path);
    eprintln!(
        "submitting {} frames as {tasks} array tasks of {k} ({})",
        frames.len(),
        script_path.display()
    );
    let output = match sbatch.output() {
        Ok(o) => o,
        Err(e) => {
            let _ = std::fs::remove_file(&snapshot);
            eprintln!(
                "error: cannot run sbatch ({e}); is this a Slurm login node? (the script is at {})",
                script_path.display()
            );
            return Ok(ExitCode::from(FailureKind::Unavailable.exit_code()));
        }
    };
    let stdout = String::from_utf8_lossy(&output.stdout);
    // `--parsable` prints `id` or, on a multi-cluster setup, `id;cluster`:
    // squeue must be asked on that cluster (elsewhere the id is unknown,
    // which read as a job that ended)
    let first = stdout.lines().next().unwrap_or("");
    let (id, cluster) = first.split_once(';').unwrap_or((first, ""));
    let nonempty = |s: &str| Some(s.trim().to_string()).filter(|s| !s.is_empty());
    let (id, cluster) = (nonempty(id), nonempty(cluster));
    if id.is_none() && !output.status.success() {
        // no task will read it
        let _ = std::fs::remove_file(&snapshot);
        let why = String::from_utf8_lossy(&output.stderr).trim().to_string();
        eprintln!("error: sbatch refused the job: {why}");
        // an unreachable controller is worth a retry; a refused script
        // (a bad partition, an array beyond MaxArraySize) is not
        let transient = ["Unable to contact", "timed out", "Socket", "try again"]
            .iter()
            .any(|m| why.contains(m));
        return Ok(ExitCode::from(if transient {
            FailureKind::Transient.exit_code()
        } else {
            2
        }));
    }
    job.job_id = id.clone();
    if let Err(e) = write_job(&out, &job) {
        return Ok(fail(&e));
    }
    let Some(id) = id else {
        // accepted, but with no id to ask about
        eprintln!(
            "submitted, but sbatch printed no job id{}; when the job ends: depthgraph batch --collect {}",
            if args.wait {
                ", so it cannot be waited for"
            } else {
                ""
            },
            out.display()
        );
        return Ok(ExitCode::from(if args.wait {
            FailureKind::Transient.exit_code()
        } else {
            0
        }));
    };
    if !args.wait {
        println!("{id}");
        eprintln!(
            "submitted job {id}; when it ends: depthgraph batch --collect {}",
            out.display()
        );
        return Ok(ExitCode::SUCCESS);
    }
    if let Err(e) = wait_for_job(&id, cluster.as_deref()) {
        eprintln!("error: {e}");
        return Ok(ExitCode::from(FailureKind::Transient.exit_code()));
    }
    eprintln!("job {id} ended; collecting");
    Ok(match collect(&out) {
        Ok(c) => collected(&c, &out),
        Err(e) => fail(&e),
    })
}

/// Reports what `collect` found in `dir`; the exit code of its summary.
fn collected(c: &Collected, dir: &Path) -> ExitCode {
    report(&c.summary, &c.records);
    match &c.manifest {
        Some(m) => eprintln!("wrote {}", m.display()),
        None => eprintln!(
            "no task of submission {} has written its part yet ({}): nothing collected, {} left as it is",
            c.submission,
            dir.join("parts").join(&c.submission).display(),
            dir.join("manifest.jsonl").display()
        ),
    }
    ExitCode::from(c.summary.exit_code())
}

/// Frames that are not one contiguous range, as a range with a step when
/// they are evenly spaced.
fn frames_text(frames: &[u64]) -> String {
    match frames {
        [a, b, ..] => {
            let step = b - a;
            let last = frames[frames.len() - 1];
            format!("{a}..{}:{step}", last + 1)
        }
        [a] => a.to_string(),
        [] => "0..0".into(),
    }
}

/// Waits until no task of job `id` (on `cluster`, where sbatch named one)
/// is pending or running, asking `squeue` once a second (`sbatch --wait` polls with growing pauses, up to tens of
/// seconds after the job ended). A controller that does not answer for a
/// minute is an error.
fn wait_for_job(id: &str, cluster: Option<&str>) -> std::result::Result<(), String> {
    let mut unanswered = 0u32;
    loop {
        let mut squeue = std::process::Command::new("squeue");
        if let Some(c) = cluster {
            squeue.args(["-M", c]);
        }
        let q = squeue.args(["-h", "-j", id, "-o", "%i"]).output();
        match q {
            Ok(o) if o.status.success() => {
                unanswered = 0;
                if String::from_utf8_lossy(&o.stdout).trim().is_empty() {
                    return Ok(());
                }
            }
            // a job that left the controller's memory is done too
            Ok(o) if String::from_utf8_lossy(&o.stderr).contains("Invalid job id") => {
                return Ok(());
            }
            Ok(o) => {
                unanswered += 1;
                if unanswered >= 60 {
                    return Err(format!(
                        "squeue has not answered about job {id} for a minute: {}",
                        String::from_utf8_lossy(&o.stderr).trim()
                    ));
                }
            }
            Err(e) => return Err(format!("cannot run squeue: {e}")),
        }
        std::thread::sleep(std::time::Duration::from_secs(1));
    }
}
