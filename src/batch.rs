//! `depthgraph batch`: one pipeline over many frames, locally or as a
//! Slurm array job, with a manifest a re-run and a scheduler can read.
//!
//! - Frames come from `{frame}` placeholders ([`crate::graph::frames`]) and
//!   sequence sources (`LoadSequence`); every output path must hold a
//!   placeholder, so no frame overwrites another's files.
//! - Frames run `jobs` at a time on one engine (one thread pool, one memory
//!   cache, the shared disk cache), so memory is bounded by `jobs` frames in
//!   flight. A re-run finds every finished frame's results in the disk cache
//!   and only rewrites its files: the frame is `cached`.
//! - Each finished frame is one line of `manifest.jsonl` ([`FrameRecord`]).
//!   A Slurm array task writes its own part (`parts/part-NNNNN.jsonl`) and
//!   `batch --collect` merges them.
//! - Exit codes ([`BatchSummary::exit_code`]): 0 when every frame is done;
//!   75 when a failure was transient (retrying is worthwhile; permanent
//!   failures then fail again quickly and finished frames are cache hits);
//!   otherwise the lowest permanent failure's code, 65 for bad input data.

use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Instant;

use depthgraph_graph::frames::has_placeholder;
use depthgraph_graph::prelude::*;
use depthgraph_graph::ron_text::RonValue;
use depthgraph_nodes::io::sequence::{LoadSequenceParams, frames as sequence_frames};
use serde::{Deserialize, Serialize};

/// Environment variable of the fault-injection hook used by the Slurm and
/// batch tests: `DEPTHGRAPH_FAULT_TRANSIENT=N` makes frame `N` fail once
/// with a transient failure (exit 75) per output directory, the way a lost
/// device or a full network share would. It changes nothing else.
pub const FAULT_TRANSIENT_VAR: &str = "DEPTHGRAPH_FAULT_TRANSIENT";

/// What became of one frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FrameStatus {
    /// Computed (at least one node ran).
    Ok,
    /// Every result came from the cache; only the files were written.
    Cached,
    /// The frame failed; `error` says why and `exit_code` of what kind.
    Failed,
}

/// One line of `manifest.jsonl`. A line without the fields after `status`
/// (written by another version, or by hand) reads with their defaults: no
/// time, no outputs, no error, exit code 0 (a failure's counts as 1,
/// [`BatchSummary::of`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FrameRecord {
    /// The frame index.
    pub frame: u64,
    /// What became of it.
    pub status: FrameStatus,
    /// Wall time of the frame, milliseconds.
    #[serde(default)]
    pub ms: f64,
    /// The files it wrote.
    #[serde(default)]
    pub outputs: Vec<String>,
    /// Why it failed, printed once.
    #[serde(default)]
    pub error: Option<String>,
    /// The failure's exit code (0 when done): 2 usage, 65 bad input data,
    /// 70 internal, 74 I/O, 75 transient.
    #[serde(default)]
    pub exit_code: u8,
}

impl FrameRecord {
    fn failed(frame: u64, ms: f64, error: String, kind: FailureKind) -> Self {
        Self {
            frame,
            status: FrameStatus::Failed,
            ms,
            outputs: Vec::new(),
            error: Some(error),
            exit_code: kind.exit_code(),
        }
    }
}

/// Counts of a batch and its exit code.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct BatchSummary {
    /// Frames in all.
    pub frames: usize,
    /// Frames computed.
    pub ok: usize,
    /// Frames whose results all came from the cache.
    pub cached: usize,
    /// Failed frames by exit code.
    pub failed: BTreeMap<u8, usize>,
    /// Frames nobody reported (a Slurm task that never wrote its part).
    pub missing: Vec<u64>,
}

impl BatchSummary {
    /// Counts `records` against the `expected` frames.
    pub fn of(records: &[FrameRecord], expected: &[u64]) -> Self {
        let mut s = BatchSummary {
            frames: expected.len(),
            ..Default::default()
        };
        let mut seen = std::collections::BTreeSet::new();
        for r in records {
            seen.insert(r.frame);
            match r.status {
                FrameStatus::Ok => s.ok += 1,
                FrameStatus::Cached => s.cached += 1,
                // (a failure recorded with exit code 0, by hand or by
                // another version, is still a failure: 1)
                FrameStatus::Failed => *s.failed.entry(r.exit_code.max(1)).or_default() += 1,
            }
        }
        s.missing = expected
            .iter()
            .copied()
            .filter(|f| !seen.contains(f))
            .collect();
        s
    }

    /// 0 when every frame is done; 75 when some failure was transient or a
    /// frame is missing (retrying is worthwhile); else the lowest permanent
    /// code (65 for bad input data).
    pub fn exit_code(&self) -> u8 {
        let transient = FailureKind::Transient.exit_code();
        if self.failed.is_empty() && self.missing.is_empty() {
            0
        } else if self.failed.contains_key(&transient) || !self.missing.is_empty() {
            transient
        } else {
            self.failed.keys().next().copied().unwrap_or(transient)
        }
    }

    /// One line: `20 frames: 18 done (5 computed, 13 from cache), 2 failed (65: 1, 75: 1)`.
    pub fn line(&self) -> String {
        let failed: usize = self.failed.values().sum();
        let mut s = format!(
            "{} frames: {} done ({} computed, {} from cache)",
            self.frames,
            self.ok + self.cached,
            self.ok,
            self.cached
        );
        if failed > 0 {
            let by: Vec<String> = self
                .failed
                .iter()
                .map(|(c, n)| format!("{n} with exit {c} ({})", code_name(*c)))
                .collect();
            s += &format!(", {failed} failed: {}", by.join(", "));
        }
        if !self.missing.is_empty() {
            s += &format!(", {} never reported", self.missing.len());
        }
        s
    }
}

/// What an exit code means, for the summary.
pub fn code_name(code: u8) -> &'static str {
    match code {
        2 => "usage or pipeline check",
        65 => "bad input data",
        69 => "no device",
        70 => "internal error",
        74 => "I/O error",
        75 => "transient",
        _ => "other",
    }
}

/// A batch that cannot start (a usage error, exit 2).
#[derive(Debug, thiserror::Error)]
pub enum BatchError {
    /// The pipeline or the frame selection does not make a batch.
    #[error("{0}")]
    Usage(String),
    /// Check errors of the pipeline for its first frame.
    #[error("{0}")]
    Check(CheckErrors),
    /// A manifest or job file that cannot be written or read.
    #[error("{path}: {error}")]
    Io {
        /// The file.
        path: PathBuf,
        /// Why.
        error: std::io::Error,
    },
    /// A manifest or job file that is not what `batch` writes.
    #[error("{path}: line {line}: {message}")]
    Format {
        /// The file.
        path: PathBuf,
        /// Its line, from 1.
        line: usize,
        /// What is wrong.
        message: String,
    },
}

impl BatchError {
    /// The exit code: 2 for usage and check errors, 74 for I/O (75 where
    /// the failure is one a retry may get past: a timeout, an interrupted
    /// call, a busy file system), 65 for a malformed manifest.
    pub fn exit_code(&self) -> u8 {
        use std::io::ErrorKind as K;
        match self {
            BatchError::Usage(_) | BatchError::Check(_) => 2,
            BatchError::Io { error, .. } => match error.kind() {
                K::TimedOut | K::Interrupted | K::WouldBlock | K::ResourceBusy => 75,
                _ => 74,
            },
            BatchError::Format { .. } => 65,
        }
    }
}

/// Refuses a batch of several frames whose outputs would overwrite each
/// other: every output path must hold a `{frame}` placeholder.
pub fn check_outputs_per_frame(doc: &Document, reg: &Registry) -> Result<(), BatchError> {
    let mut shared = Vec::new();
    for n in &doc.nodes {
        let Some(node) = reg.get(&n.kind.value) else {
            continue; // the check names unknown kinds
        };
        for spec in &node.schema().params {
            if spec.kind != ParamKind::OutputPath {
                continue;
            }
            let value = n
                .params
                .iter()
                .find(|(k, _)| k.value == spec.name)
                .map(|(_, v)| match &v.value {
                    RonValue::Str(s) => s.clone(),
                    _ => String::new(),
                })
                .unwrap_or_else(|| match &spec.default {
                    ParamValue::Text(s) => s.clone(),
                    other => other.to_string(),
                });
            if !has_placeholder(&value) {
                shared.push(format!("`{}.{}` = \"{value}\"", n.name.value, spec.name));
            }
        }
    }
    if shared.is_empty() {
        Ok(())
    } else {
        Err(BatchError::Usage(format!(
            "every frame would write the same file: {} (put {{frame}} or {{frame:05}} in the path, e.g. --set node.path=out_{{frame:05}}.png)",
            shared.join(", ")
        )))
    }
}

/// The number of frames of the pipeline's sequence sources (the shortest
/// when there are several), or `None` when it has none.
pub fn sequence_length(p: &Pipeline) -> Option<Result<u64, String>> {
    let mut len: Option<Result<u64, String>> = None;
    for n in p.nodes.iter().filter(|n| n.kind == "LoadSequence") {
        let this = LoadSequenceParams::from_values(&n.params)
            .map_err(|e| format!("node `{}`: {e}", n.name))
            .and_then(|params| {
                sequence_frames(&params)
                    .map(|f| f.len() as u64)
                    .map_err(|e| format!("node `{}`: {e}", n.name))
            });
        len = Some(match (len, this) {
            (None, t) => t,
            (Some(Err(e)), _) | (_, Err(e)) => Err(e),
            (Some(Ok(a)), Ok(b)) => Ok(a.min(b)),
        });
    }
    len
}

/// Everything a frame run needs besides its index.
pub struct FrameRunner<'a> {
    /// The document with its placeholders.
    pub doc: &'a Document,
    /// The registry (with the chosen backend's kinds).
    pub registry: &'a Registry,
    /// The engine all frames share.
    pub engine: &'a Engine,
    /// Where outputs go.
    pub out_dir: PathBuf,
    /// Files no sink may overwrite (the pipeline file).
    pub protected_files: Vec<PathBuf>,
    /// The pixel budget of one input file.
    pub max_pixels: Option<usize>,
}

impl FrameRunner<'_> {
    /// Runs one frame; never fails as a whole: a failure is the record's,
    /// a panic (a bug) included, recorded as an internal error (70) so the
    /// other frames go on.
    pub fn run(&self, frame: u64) -> FrameRecord {
        let t = Instant::now();
        std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| self.run_inner(frame)))
            .unwrap_or_else(|p| {
                let why = p
                    .downcast_ref::<&str>()
                    .map(|s| s.to_string())
                    .or_else(|| p.downcast_ref::<String>().cloned())
                    .unwrap_or_else(|| "a panic".into());
                FrameRecord::failed(
                    frame,
                    t.elapsed().as_secs_f64() * 1e3,
                    format!("internal error (please report it): {why}"),
                    FailureKind::Internal,
                )
            })
    }

    fn run_inner(&self, frame: u64) -> FrameRecord {
        let t = Instant::now();
        let ms = |t: Instant| t.elapsed().as_secs_f64() * 1e3;
        if let Some(r) = self.injected_fault(frame) {
            return r;
        }
        let checked = self
            .doc
            .for_frame(frame)
            .and_then(|doc| Pipeline::check(&doc, self.registry));
        let p = match checked {
            Ok(p) => p,
            Err(e) => {
                let text = CheckErrors(e).to_string();
                return FrameRecord::failed(frame, ms(t), text, FailureKind::Usage);
            }
        };
        let opts = RunOptions {
            out_dir: self.out_dir.clone(),
            protected_files: self.protected_files.clone(),
            max_pixels: self.max_pixels,
            ..RunOptions::default()
        };
        match self.engine.run(&p, &opts) {
            Ok(result) => {
                let computed = result.trace.nodes.iter().any(|r| {
                    matches!(r.status, Status::Ran | Status::Passthrough)
                        && p.index_of(&r.node)
                            .is_some_and(|i| !p.nodes[i].node.schema().sink)
                });
                let outputs = result
                    .outputs
                    .values()
                    .filter_map(|v| match v {
                        Value::File(f) => Some(f.display().to_string()),
                        _ => None,
                    })
                    .collect();
                FrameRecord {
                    frame,
                    status: if computed {
                        FrameStatus::Ok
                    } else {
                        FrameStatus::Cached
                    },
                    ms: ms(t),
                    outputs,
                    error: None,
                    exit_code: 0,
                }
            }
            Err(e) => FrameRecord::failed(frame, ms(t), e.to_string(), e.kind()),
        }
    }

    /// The test hook of [`FAULT_TRANSIENT_VAR`]: the first attempt at the
    /// named frame in this output directory fails as transient.
    fn injected_fault(&self, frame: u64) -> Option<FrameRecord> {
        let want: u64 = std::env::var(FAULT_TRANSIENT_VAR)
            .ok()?
            .trim()
            .parse()
            .ok()?;
        if want != frame {
            return None;
        }
        let marker = self.out_dir.join(format!(".fault-transient-{frame}"));
        if marker.exists() {
            return None;
        }
        std::fs::create_dir_all(&self.out_dir).ok()?;
        std::fs::write(&marker, b"injected once\n").ok()?;
        Some(FrameRecord::failed(
            frame,
            0.0,
            format!("injected transient failure ({FAULT_TRANSIENT_VAR}={frame})"),
            FailureKind::Transient,
        ))
    }

    /// Runs `frames`, `jobs` at a time; `done` sees each record as it
    /// finishes (in completion order). The result is in frame order.
    pub fn run_all(
        &self,
        frames: &[u64],
        jobs: usize,
        done: &(dyn Fn(&FrameRecord) + Sync),
    ) -> Vec<FrameRecord> {
        let next = AtomicUsize::new(0);
        let records: Mutex<Vec<FrameRecord>> = Mutex::new(Vec::with_capacity(frames.len()));
        std::thread::scope(|s| {
            for _ in 0..jobs.clamp(1, frames.len().max(1)) {
                s.spawn(|| {
                    loop {
                        let i = next.fetch_add(1, Ordering::Relaxed);
                        let Some(&f) = frames.get(i) else { break };
                        let r = self.run(f);
                        done(&r);
                        records.lock().unwrap_or_else(|e| e.into_inner()).push(r);
                    }
                });
            }
        });
        let mut out = records.into_inner().unwrap_or_else(|e| e.into_inner());
        out.sort_by_key(|r| r.frame);
        out
    }
}

/// Appends records to a manifest as they finish, one JSON object per line
/// (a run's live record: a local batch's `manifest.jsonl.partial`, a Slurm
/// task's part), so that a run killed midway still says what it finished.
pub struct ManifestWriter {
    file: Mutex<std::fs::File>,
    path: PathBuf,
}

impl ManifestWriter {
    /// Opens `path` for appending (created if missing): a task retried or
    /// requeued keeps its earlier attempt's records (the last record of a
    /// frame counts), and two runs appending never overwrite each other.
    pub fn create(path: &Path) -> Result<Self, BatchError> {
        let io = |error| BatchError::Io {
            path: path.to_path_buf(),
            error,
        };
        if let Some(d) = path.parent() {
            std::fs::create_dir_all(d).map_err(io)?;
        }
        let mut file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .read(true)
            .open(path)
            .map_err(io)?;
        // a record an earlier writer left cut off (no newline at the end)
        // is cut away, so the next record starts a line of its own
        use std::io::Read;
        let mut held = Vec::new();
        file.read_to_end(&mut held).map_err(io)?;
        if held.last().is_some_and(|b| *b != b'\n') {
            let keep = held.iter().rposition(|b| *b == b'\n').map_or(0, |i| i + 1);
            file.set_len(keep as u64).map_err(io)?;
        }
        Ok(Self {
            file: Mutex::new(file),
            path: path.to_path_buf(),
        })
    }
    /// Appends one record (a failed write is reported at [`write_manifest`]).
    pub fn append(&self, r: &FrameRecord) {
        if let Ok(mut line) = serde_json::to_string(r) {
            line.push('\n');
            let mut f = self.file.lock().unwrap_or_else(|e| e.into_inner());
            // one write of the whole line (with O_APPEND: never interleaved
            // with another writer's); a torn one lacks its newline and is
            // skipped when read
            let _ = f.write_all(line.as_bytes());
            let _ = f.flush();
        }
    }
    /// The file.
    pub fn path(&self) -> &Path {
        &self.path
    }
}

/// Writes `records` (frame order) to `path` atomically.
pub fn write_manifest(path: &Path, records: &[FrameRecord]) -> Result<(), BatchError> {
    let mut text = String::new();
    for r in records {
        let line = serde_json::to_string(r).map_err(|e| BatchError::Io {
            path: path.to_path_buf(),
            error: std::io::Error::other(e),
        })?;
        text.push_str(&line);
        text.push('\n');
    }
    write_text(path, &text)
}

/// Writes `records` into the manifest at `path`, keeping the records it
/// already holds for other frames (an earlier run's frames into the same
/// folder), in frame order, atomically. A manifest there that cannot be
/// read is kept under another name (returned, for the caller to say) and
/// replaced by these records: a finished run's records are never lost to
/// an earlier file's damage.
pub fn merge_manifest(path: &Path, records: &[FrameRecord]) -> Result<Option<PathBuf>, BatchError> {
    let mut moved = None;
    let mut by_frame: BTreeMap<u64, FrameRecord> = BTreeMap::new();
    if path.exists() {
        match read_manifest(path) {
            Ok(old) => by_frame.extend(old.into_iter().map(|r| (r.frame, r))),
            Err(BatchError::Format { .. }) => {
                let aside = free_name(path, "unreadable");
                std::fs::rename(path, &aside).map_err(|error| BatchError::Io {
                    path: path.to_path_buf(),
                    error,
                })?;
                moved = Some(aside);
            }
            Err(e) => return Err(e),
        }
    }
    for r in records {
        by_frame.insert(r.frame, r.clone());
    }
    let all: Vec<FrameRecord> = by_frame.into_values().collect();
    write_manifest(path, &all)?;
    Ok(moved)
}

/// `path.<tag>`, or `path.<tag>.N` with the first N that names no file.
fn free_name(path: &Path, tag: &str) -> PathBuf {
    let base = format!("{}.{tag}", path.display());
    let mut at = PathBuf::from(&base);
    let mut n = 1;
    while at.exists() {
        at = PathBuf::from(format!("{base}.{n}"));
        n += 1;
    }
    at
}

fn write_text(path: &Path, text: &str) -> Result<(), BatchError> {
    depthgraph_nodes::io::write_atomic(path, |tmp| std::fs::write(tmp, text))
        .map(|_| ())
        .map_err(|e| BatchError::Io {
            path: path.to_path_buf(),
            // the file system's own error, so its kind sets the exit code
            error: match e {
                depthgraph_graph::error::NodeError::Io { error, .. } => error,
                other => std::io::Error::other(other.to_string()),
            },
        })
}

/// Reads a manifest (or a part of one).
pub fn read_manifest(path: &Path) -> Result<Vec<FrameRecord>, BatchError> {
    let bytes = std::fs::read(path).map_err(|error| BatchError::Io {
        path: path.to_path_buf(),
        error,
    })?;
    // (a record cut mid-character is not valid UTF-8: its line then fails
    // to parse, as any cut record does)
    let text = String::from_utf8_lossy(&bytes);
    let mut out = Vec::new();
    let lines: Vec<&str> = text.lines().collect();
    for (i, line) in lines.iter().enumerate() {
        if line.trim().is_empty() {
            continue;
        }
        // a last line without its newline that does not parse is a record
        // whose write was cut off (a task killed mid-append): not there
        let torn = i + 1 == lines.len() && !text.ends_with('\n');
        let parsed = serde_json::from_str::<FrameRecord>(line);
        if torn && parsed.is_err() {
            break;
        }
        let r: FrameRecord = parsed.map_err(|e| BatchError::Format {
            path: path.to_path_buf(),
            line: i + 1,
            message: e.to_string(),
        })?;
        out.push(r);
    }
    Ok(out)
}

/// The peak resident memory of this process in MiB (Linux), if known.
pub fn peak_rss_mib() -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}

// ------------------------------------------------------------------ Slurm

/// How a batch is split into a Slurm array job.
#[derive(Debug, Clone, PartialEq)]
pub struct SlurmPlan {
    /// Frames per array task.
    pub frames_per_task: usize,
    /// At most this many tasks at once (`--array=...%N`).
    pub array_max: Option<usize>,
    /// The partition, when not the default.
    pub partition: Option<String>,
    /// Retries of a task that exits 75 (transient), within its allocation.
    pub retries: u32,
}

/// The job description `batch --slurm` leaves in `DIR/slurm/job.json`, so
/// `batch --collect DIR` knows which frames to expect and which
/// submission's parts to read.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct JobFile {
    /// This submission's id: its tasks write under `DIR/parts/<submission>/`,
    /// so the parts of an earlier job in the same directory (still running,
    /// or finished) are never merged with this one's.
    pub submission: String,
    /// The pipeline the tasks run: a copy of the submitted file as it was
    /// checked, with its `--set` values (`slurm/pipeline-<submission>.ron`).
    pub pipeline: String,
    /// Every frame of the batch, in order.
    pub frames: Vec<u64>,
    /// Frames per array task.
    pub frames_per_task: usize,
    /// Number of array tasks.
    pub tasks: usize,
    /// Slurm's job id, once submitted.
    pub job_id: Option<String>,
}

/// The frames of array task `task`.
pub fn task_frames(frames: &[u64], frames_per_task: usize, task: usize) -> &[u64] {
    let k = frames_per_task.max(1);
    let start = task.saturating_mul(k).min(frames.len());
    let end = start.saturating_add(k).min(frames.len());
    &frames[start..end]
}

/// The number of array tasks for `n` frames.
pub fn task_count(n: usize, frames_per_task: usize) -> usize {
    n.div_ceil(frames_per_task.max(1))
}

/// The file of array task `task`'s part of the manifest of submission
/// `submission`.
pub fn part_path(out: &Path, submission: &str, task: usize) -> PathBuf {
    out.join("parts")
        .join(submission)
        .join(format!("part-{task:05}.jsonl"))
}

/// A new submission id: the time in nanoseconds since 1970 and the
/// process, in hex (unique per submitting process and moment).
pub fn new_submission_id() -> String {
    let ns = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos());
    format!("{ns:x}-{:x}", std::process::id())
}

/// Whether `id` is a submission id [`new_submission_id`] could have made
/// (it becomes a folder name).
pub fn valid_submission_id(id: &str) -> bool {
    !id.is_empty() && id.len() <= 64 && id.chars().all(|c| c.is_ascii_hexdigit() || c == '-')
}

/// Quotes `s` for a POSIX shell.
pub fn shell_quote(s: &str) -> String {
    if !s.is_empty()
        && s.chars()
            .all(|c| c.is_ascii_alphanumeric() || "-_./=:,+@%".contains(c))
    {
        s.to_string()
    } else {
        format!("'{}'", s.replace('\'', "'\\''"))
    }
}

/// The sbatch script of an array job: each task runs
/// `task_command + --task $SLURM_ARRAY_TASK_ID`, retried up to
/// `plan.retries` times while it exits 75, and ends with the task's exit
/// code (75 left after the retries lets a cluster with `RequeueExit=75`
/// requeue it).
pub fn slurm_script(
    name: &str,
    task_command: &[String],
    workdir: &Path,
    out: &Path,
    tasks: usize,
    plan: &SlurmPlan,
) -> String {
    let mut s = String::from("#!/bin/bash\n");
    s += &format!("#SBATCH --job-name={}\n", shell_quote(name));
    let throttle = plan
        .array_max
        .map(|n| format!("%{}", n.max(1)))
        .unwrap_or_default();
    s += &format!("#SBATCH --array=0-{}{throttle}\n", tasks.saturating_sub(1));
    s += &format!(
        "#SBATCH --output={}\n",
        shell_quote(
            &out.join("slurm")
                .join("task-%A_%a.log")
                .display()
                .to_string()
        )
    );
    s += &format!(
        "#SBATCH --chdir={}\n",
        shell_quote(&workdir.display().to_string())
    );
    if let Some(p) = &plan.partition {
        s += &format!("#SBATCH --partition={}\n", shell_quote(p));
    }
    s += "#SBATCH --requeue\n";
    s += "# Written by `depthgraph batch --slurm`; each task writes its part of the\n";
    s += "# manifest, and `depthgraph batch --collect DIR` merges them.\n";
    s += "set -u\n";
    let cmd: Vec<String> = task_command.iter().map(|a| shell_quote(a)).collect();
    s += &format!("retries={}\n", plan.retries);
    s += "attempt=0\n";
    s += "while true; do\n";
    s += &format!("  {} --task \"$SLURM_ARRAY_TASK_ID\"\n", cmd.join(" "));
    s += "  rc=$?\n";
    s += "  if [ \"$rc\" -ne 75 ] || [ \"$attempt\" -ge \"$retries\" ]; then exit \"$rc\"; fi\n";
    s += "  attempt=$((attempt + 1))\n";
    s += "  echo \"depthgraph: task $SLURM_ARRAY_TASK_ID failed transiently (exit 75): retry $attempt of $retries\" >&2\n";
    s += "  sleep $((attempt * 2))\n";
    s += "done\n";
    s
}

/// Writes the job file.
pub fn write_job(out: &Path, job: &JobFile) -> Result<PathBuf, BatchError> {
    let path = out.join("slurm").join("job.json");
    let text = serde_json::to_string_pretty(job).map_err(|e| BatchError::Io {
        path: path.clone(),
        error: std::io::Error::other(e),
    })?;
    write_text(&path, &(text + "\n"))?;
    Ok(path)
}

/// Reads the job file of a batch directory.
pub fn read_job(out: &Path) -> Result<JobFile, BatchError> {
    let path = out.join("slurm").join("job.json");
    let text = std::fs::read_to_string(&path).map_err(|error| BatchError::Io {
        path: path.clone(),
        error,
    })?;
    serde_json::from_str(&text).map_err(|e| BatchError::Format {
        path,
        line: e.line(),
        message: e.to_string(),
    })
}

/// What [`collect`] found.
#[derive(Debug)]
pub struct Collected {
    /// The records of the frames the job file expects, one per frame.
    pub records: Vec<FrameRecord>,
    /// Their count against the job's frames.
    pub summary: BatchSummary,
    /// The manifest written; `None` when no task of the submission has
    /// written a part (every frame missing): a manifest already there (an
    /// earlier job's, collected before a refused or dry-run submission
    /// named another) is left as it is.
    pub manifest: Option<PathBuf>,
    /// The submission the job file names.
    pub submission: String,
}

/// Merges the parts of a Slurm batch into `DIR/manifest.jsonl`: every
/// frame the job file expects, the last part's record of each frame. A
/// frame no part reports is counted as missing; when no part exists at
/// all nothing is written ([`Collected::manifest`]).
pub fn collect(out: &Path) -> Result<Collected, BatchError> {
    let job = read_job(out)?;
    let mut by_frame: BTreeMap<u64, FrameRecord> = BTreeMap::new();
    if !valid_submission_id(&job.submission) {
        return Err(BatchError::Format {
            path: out.join("slurm").join("job.json"),
            line: 1,
            message: format!("`{}` is not a submission id", job.submission),
        });
    }
    let mut parts = 0usize;
    for task in 0..job.tasks {
        let part = part_path(out, &job.submission, task);
        if !part.exists() {
            continue;
        }
        parts += 1;
        for r in read_manifest(&part)? {
            by_frame.insert(r.frame, r);
        }
    }
    let wanted: std::collections::BTreeSet<u64> = job.frames.iter().copied().collect();
    let records: Vec<FrameRecord> = by_frame
        .into_values()
        .filter(|r| wanted.contains(&r.frame))
        .collect();
    let manifest = if parts > 0 {
        let path = out.join("manifest.jsonl");
        if let Some(aside) = merge_manifest(&path, &records)? {
            eprintln!(
                "warning: {} could not be read; it is kept as {}",
                path.display(),
                aside.display()
            );
        }
        Some(path)
    } else {
        None
    };
    let summary = BatchSummary::of(&records, &job.frames);
    Ok(Collected {
        records,
        summary,
        manifest,
        submission: job.submission,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rec(frame: u64, status: FrameStatus, code: u8) -> FrameRecord {
        FrameRecord {
            frame,
            status,
            ms: 1.0,
            outputs: vec![],
            error: None,
            exit_code: code,
        }
    }

    #[test]
    fn an_io_failure_a_retry_may_pass_exits_75() {
        let io = |kind| BatchError::Io {
            path: "m".into(),
            error: std::io::Error::from(kind),
        };
        assert_eq!(io(std::io::ErrorKind::TimedOut).exit_code(), 75);
        assert_eq!(io(std::io::ErrorKind::PermissionDenied).exit_code(), 74);
        // the atomic write keeps the file system's error kind
        let dir = tempfile::tempdir().unwrap();
        let blocked = dir.path().join("file");
        std::fs::write(&blocked, "x").unwrap();
        let e = write_manifest(&blocked.join("sub/manifest.jsonl"), &[]).unwrap_err();
        match &e {
            BatchError::Io { error, .. } => assert_ne!(error.kind(), std::io::ErrorKind::Other),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn exit_codes_say_whether_a_retry_is_worthwhile() {
        let all = [0, 1, 2, 3];
        let ok = [
            rec(0, FrameStatus::Ok, 0),
            rec(1, FrameStatus::Cached, 0),
            rec(2, FrameStatus::Ok, 0),
            rec(3, FrameStatus::Ok, 0),
        ];
        assert_eq!(BatchSummary::of(&ok, &all).exit_code(), 0);
        let mut bad = ok.clone();
        bad[1] = rec(1, FrameStatus::Failed, 65);
        let s = BatchSummary::of(&bad, &all);
        assert_eq!(s.exit_code(), 65);
        assert!(
            s.line().contains("1 with exit 65 (bad input data)"),
            "{}",
            s.line()
        );
        bad[2] = rec(2, FrameStatus::Failed, 75);
        assert_eq!(BatchSummary::of(&bad, &all).exit_code(), 75);
        // a frame nobody reported is worth a retry
        let s = BatchSummary::of(&ok[..3], &all);
        assert_eq!(s.missing, vec![3]);
        assert_eq!(s.exit_code(), 75);
        bad[2] = rec(2, FrameStatus::Failed, 74);
        assert_eq!(BatchSummary::of(&bad, &all).exit_code(), 65);
        // a part line with only the frame and its status reads (another
        // version's), its failure counted as one
        let short: FrameRecord = serde_json::from_str(r#"{"frame":3,"status":"failed"}"#).unwrap();
        assert_eq!(
            short,
            FrameRecord {
                ms: 0.0,
                ..rec(3, FrameStatus::Failed, 0)
            }
        );
        // a failure that says exit 0 does not pass for success
        let mut zero = ok.clone();
        zero[3] = rec(3, FrameStatus::Failed, 0);
        let s = BatchSummary::of(&zero, &all);
        assert_eq!(s.exit_code(), 1, "{}", s.line());
        assert!(s.line().contains("1 failed"), "{}", s.line());
    }

    #[test]
    fn tasks_cover_every_frame_once() {
        let frames: Vec<u64> = (0..23).map(|f| f * 3).collect();
        let k = 5;
        let n = task_count(frames.len(), k);
        assert_eq!(n, 5);
        let joined: Vec<u64> = (0..n)
            .flat_map(|t| task_frames(&frames, k, t).to_vec())
            .collect();
        assert_eq!(joined, frames);
        assert!(task_frames(&frames, k, n).is_empty());
    }

    #[test]
    fn the_script_runs_each_task_and_retries_only_transient_failures() {
        let plan = SlurmPlan {
            frames_per_task: 4,
            array_max: Some(3),
            partition: Some("debug".into()),
            retries: 2,
        };
        let cmd = vec![
            "/bin/depthgraph".to_string(),
            "batch".into(),
            "a b.ron".into(),
        ];
        let s = slurm_script("dg", &cmd, Path::new("/w"), Path::new("/o"), 7, &plan);
        assert!(s.contains("#SBATCH --array=0-6%3\n"), "{s}");
        assert!(s.contains("#SBATCH --partition=debug\n"));
        assert!(s.contains("/bin/depthgraph batch 'a b.ron' --task \"$SLURM_ARRAY_TASK_ID\""));
        assert!(s.contains("retries=2\n") && s.contains("\"$rc\" -ne 75"));
        assert_eq!(shell_quote("it's"), "'it'\\''s'");
        assert_eq!(shell_quote(""), "''");
    }

    #[test]
    fn manifests_round_trip_and_report_their_line() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("m.jsonl");
        let rs = vec![rec(0, FrameStatus::Ok, 0), rec(5, FrameStatus::Failed, 65)];
        write_manifest(&p, &rs).unwrap();
        assert_eq!(read_manifest(&p).unwrap(), rs);
        std::fs::write(&p, "{\"frame\": 1}\n").unwrap();
        let e = read_manifest(&p).unwrap_err();
        assert!(matches!(e, BatchError::Format { line: 1, .. }), "{e}");
        assert_eq!(e.exit_code(), 65);
        // a record cut off mid-write (no newline) is left out; the same
        // damage with its newline is an error
        write_manifest(&p, &rs).unwrap();
        let mut text = std::fs::read_to_string(&p).unwrap();
        text.push_str("{\"frame\": 9, \"sta");
        std::fs::write(&p, &text).unwrap();
        assert_eq!(read_manifest(&p).unwrap(), rs);
        text.push('\n');
        std::fs::write(&p, &text).unwrap();
        assert!(read_manifest(&p).is_err());
        // merging into an unreadable manifest keeps it aside, loses nothing
        let moved = merge_manifest(&p, &rs[..1]).unwrap().unwrap();
        assert_eq!(std::fs::read_to_string(&moved).unwrap(), text);
        assert_eq!(read_manifest(&p).unwrap(), rs[..1].to_vec());
        std::fs::write(&p, "garbage\n").unwrap();
        let again = merge_manifest(&p, &rs).unwrap().unwrap();
        assert_ne!(again, moved);
        assert_eq!(read_manifest(&p).unwrap(), rs);
        // the live writer appends: a second writer adds to the first's,
        // after cutting away a record the first left cut off
        let live = dir.path().join("live.jsonl");
        ManifestWriter::create(&live).unwrap().append(&rs[0]);
        let mut f = std::fs::OpenOptions::new()
            .append(true)
            .open(&live)
            .unwrap();
        f.write_all("{\"frame\": 7, \"st\u{e9}".as_bytes()[..16].as_ref())
            .unwrap();
        drop(f);
        ManifestWriter::create(&live).unwrap().append(&rs[1]);
        assert_eq!(read_manifest(&live).unwrap(), rs);
        // a record cut mid-character at the end is left out
        let cut = dir.path().join("cut.jsonl");
        write_manifest(&cut, &rs).unwrap();
        let mut f = std::fs::OpenOptions::new().append(true).open(&cut).unwrap();
        f.write_all(&"{\"frame\": 7, \"\u{e9}".as_bytes()[..15])
            .unwrap();
        drop(f);
        assert_eq!(read_manifest(&cut).unwrap(), rs);
    }
}
