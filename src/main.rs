//! `depthgraph`: run, check, explain and sweep RGB-D pipelines.

use std::collections::BTreeMap;
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::{Arc, Mutex};

mod batch_cli;

use anyhow::{Context, Result};
use clap::{Args, Parser, Subcommand};
use depthgraph::backend::{Backend, Chosen};
use depthgraph::graph::prelude::*;
use depthgraph::metrics::Metric;
use depthgraph::sweep::{SweepSpec, plot_svg, run_sweep, to_csv};
use depthgraph::{LoadError, default_cache_dir, load_pipeline, load_pipeline_frame};

/// Exit code when the requested backend cannot be used (no GPU adapter):
/// sysexits EX_UNAVAILABLE. A bad DEPTHGRAPH_BACKEND is a usage error (2).
const EXIT_NO_DEVICE: u8 = FailureKind::Unavailable.exit_code();

/// Writes a line to standard output, returning the error (a closed pipe
/// ends the program quietly, see [`main`]) instead of panicking as
/// `println!` does.
macro_rules! outln {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        writeln!(std::io::stdout().lock(), $($arg)*)?
    }};
}

/// A mistake on the command line found after clap parsed it (exit code 2).
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
struct Usage(String);

const EXIT_CODES_HELP: &str = "Exit codes:
  0   success
  2   usage error or a pipeline that fails its check (also a parameter a node cannot use)
  65  bad input data: a missing, unreadable, corrupt or out-of-range input file
  69  the requested backend (--backend gpu) has no device
  70  internal error (a bug: please report it)
  74  I/O error writing outputs (full or read-only disk, bad output directory)
  75  transient failure (device lost or out of memory, interrupted, cancelled): retrying may succeed";

#[derive(Parser)]
#[command(
    name = "depthgraph",
    version,
    about = "Edit color+depth photographs with typed node graphs",
    after_help = EXIT_CODES_HELP
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run a pipeline and write its outputs.
    Run {
        #[command(flatten)]
        common: RunArgs,
    },
    /// Check a pipeline (syntax, kinds, ports, parameters, types, cycles) without running it.
    Check {
        file: PathBuf,
        /// Override a parameter: node.param=value (RON syntax; bare words are text).
        #[arg(long = "set", value_name = "NODE.PARAM=VALUE")]
        sets: Vec<String>,
    },
    /// List node kinds, or describe one: ports, types, parameters with defaults and ranges.
    Nodes {
        kind: Option<String>,
        /// Print the schema as JSON.
        #[arg(long)]
        json: bool,
    },
    /// Run a pipeline and report, per node, whether it ran, came from the cache, passed through or was not needed.
    Explain {
        #[command(flatten)]
        common: RunArgs,
        /// Print JSON instead of a table.
        #[arg(long)]
        json: bool,
    },
    /// Run a pipeline over many frames ({frame} placeholders, sequences), here or as a
    /// Slurm array job; writes OUT/manifest.jsonl and exits 0, 65 (bad input) or 75 (transient).
    Batch(Box<batch_cli::BatchArgs>),
    /// Error against time over the values of one parameter.
    Sweep {
        #[command(flatten)]
        common: RunArgs,
        /// The parameter and its values: node.param=v1,v2,...
        #[arg(long)]
        param: String,
        /// Reference setting: node.param=value (its output is the reference).
        #[arg(long)]
        reference: Option<String>,
        /// Ground-truth port to compare with instead of a reference run: node.port.
        #[arg(long)]
        truth: Option<String>,
        /// The judged output: node.port.
        #[arg(long)]
        output: String,
        #[arg(long, value_enum, default_value = "rmse")]
        metric: Metric,
        /// Timed repeats per value (median reported).
        #[arg(long, default_value_t = 3)]
        repeats: usize,
        /// CSV file to write (default: <out>/sweep-<node>-<param>.csv).
        #[arg(long)]
        csv: Option<PathBuf>,
        /// SVG plot to write (default: <out>/sweep-<node>-<param>.svg).
        #[arg(long)]
        plot: Option<PathBuf>,
    },
}

/// Where results are cached: shared by `run`, `explain`, `sweep` and `batch`.
#[derive(Args)]
struct CacheArgs {
    /// Do not read or write the on-disk cache.
    #[arg(long)]
    no_cache: bool,
    /// Where the on-disk cache lives (default: $DEPTHGRAPH_CACHE_DIR, $XDG_CACHE_HOME/depthgraph or ~/.cache/depthgraph).
    #[arg(long)]
    cache_dir: Option<PathBuf>,
    /// On-disk cache budget in MiB; least recently used entries go first.
    #[arg(long, default_value_t = 4096)]
    cache_mb: u64,
    /// A cache many machines share, after the disk cache: s3://bucket/prefix, gs://, az://
    /// or file:///path (credentials from AWS_*, GOOGLE_*, AZURE_* variables).
    #[arg(long, value_name = "URL")]
    cache_url: Option<String>,
}

impl CacheArgs {
    /// The on-disk cache's directory.
    fn dir(&self) -> PathBuf {
        self.cache_dir.clone().unwrap_or_else(default_cache_dir)
    }
    /// The on-disk cache, unless `--no-cache`.
    fn disk(&self) -> Option<DiskCache> {
        (!self.no_cache).then(|| DiskCache::new(self.dir(), self.cache_mb.saturating_mul(1 << 20)))
    }
    /// The shared store of `--cache-url` (checked once), unless `--no-cache`.
    fn remote(
        &self,
    ) -> std::result::Result<
        Option<Arc<dyn depthgraph::graph::cache::BlobStore>>,
        depthgraph::CacheUrlError,
    > {
        match &self.cache_url {
            Some(url) if !self.no_cache => depthgraph::open_cache_url(url).map(Some),
            _ => Ok(None),
        }
    }
}

#[derive(Args)]
struct RunArgs {
    /// Pipeline file (RON).
    file: PathBuf,
    /// Override a parameter: node.param=value (RON syntax; bare words are text).
    #[arg(long = "set", value_name = "NODE.PARAM=VALUE")]
    sets: Vec<String>,
    /// Directory for relative output paths.
    #[arg(long, default_value = "out")]
    out: PathBuf,
    #[command(flatten)]
    cache: CacheArgs,
    /// In-memory cache budget in MiB.
    #[arg(long, default_value_t = 2048)]
    memory_mb: usize,
    /// Worker threads (0 = one per core).
    #[arg(long, default_value_t = 0)]
    threads: usize,
    /// The most pixels one input file may hold; checked on the file's header
    /// before its pixels are decoded.
    #[arg(long, default_value_t = depthgraph::graph::node::DEFAULT_MAX_PIXELS, value_parser = clap::value_parser!(usize))]
    max_pixels: usize,
    /// No progress bars.
    #[arg(long, short)]
    quiet: bool,
    /// Where the device node kinds run: auto (the GPU when a wgpu adapter
    /// exists), cpu, or gpu (fail when there is none). Default: $DEPTHGRAPH_BACKEND, else auto.
    #[arg(long, value_enum)]
    backend: Option<Backend>,
    /// The frame of a pipeline with {frame} placeholders (default 0; `batch` runs many).
    #[arg(long)]
    frame: Option<u64>,
}

fn registry() -> Result<Registry> {
    depthgraph::nodes::registry().context("building the node registry")
}

/// The registry with the device kinds `args.backend` calls for; `Err` with
/// the exit code when the backend cannot be had (the reason printed once).
/// The pipeline is read and checked first, against the CPU kinds (the
/// same kinds, ports and parameters): a missing file, a typo or a bad
/// `--set` fails (exit code 2) before any device is probed. The file is
/// read once: the document returned is the one checked ([`load`] binds it
/// to the chosen kinds), so a pipeline piped on standard input runs, and a
/// file edited meanwhile is not checked in one version and run in another.
fn registry_for(
    args: &RunArgs,
) -> Result<std::result::Result<(Registry, Chosen, Document), ExitCode>> {
    let mut reg = registry()?;
    let doc = match load_pipeline_frame(&args.file, &args.sets, args.frame, &reg) {
        Ok((doc, _)) => doc,
        Err(e) => {
            report_load_error(&e);
            return Ok(Err(ExitCode::from(2)));
        }
    };
    let chosen =
        Backend::resolve(args.backend).and_then(|b| depthgraph::backend::apply(b, &mut reg));
    match chosen {
        Ok(c) => Ok(Ok((reg, c, doc))),
        Err(e) => {
            eprintln!("error: {e}");
            let code = match e {
                depthgraph::backend::BackendError::BadVariable(_) => 2,
                depthgraph::backend::BackendError::NoDevice(_) => EXIT_NO_DEVICE,
            };
            Ok(Err(ExitCode::from(code)))
        }
    }
}

/// The document [`registry_for`] read, checked against `reg` (the chosen
/// backend's kinds); prints its notices, and check errors (one per line)
/// as a failure.
fn load(doc: &Document, reg: &Registry) -> Result<Pipeline, ExitCode> {
    match Pipeline::check(doc, reg) {
        Ok(p) => {
            for n in &doc.notices {
                eprintln!("note: {n}");
            }
            Ok(p)
        }
        Err(e) => {
            report_load_error(&LoadError::Check(CheckErrors(e)));
            Err(ExitCode::from(2))
        }
    }
}

fn report_load_error(e: &LoadError) {
    match e {
        LoadError::Check(errs) => eprintln!("{errs}"),
        other => eprintln!("error: {other}"),
    }
}

fn engine(args: &RunArgs) -> Result<Engine> {
    let remote = args.cache.remote()?;
    Ok(Engine::new(EngineOptions {
        memory_budget_bytes: args.memory_mb.saturating_mul(1 << 20),
        disk: args.cache.disk(),
        threads: args.threads,
        remote,
    })?)
}

fn progress_bar(quiet: bool) -> Option<depthgraph::graph::node::ProgressFn> {
    if quiet || !std::io::stderr().is_terminal() {
        return None;
    }
    let multi = indicatif::MultiProgress::new();
    let bars: Mutex<BTreeMap<String, indicatif::ProgressBar>> = Mutex::new(BTreeMap::new());
    let style = indicatif::ProgressStyle::with_template("{prefix:>16} [{bar:30}] {percent:>3}%")
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
        .progress_chars("=> ");
    Some(Arc::new(move |node: &str, f: f32| {
        let mut bars = bars.lock().unwrap_or_else(|e| e.into_inner());
        let bar = bars.entry(node.to_string()).or_insert_with(|| {
            let b = multi.add(indicatif::ProgressBar::new(1000));
            b.set_style(style.clone());
            b.set_prefix(node.to_string());
            b
        });
        bar.set_position((f * 1000.0) as u64);
        if f >= 1.0 {
            bar.finish_and_clear();
        }
    }))
}

fn run_options(args: &RunArgs) -> RunOptions {
    RunOptions {
        progress: progress_bar(args.quiet),
        out_dir: args.out.clone(),
        protected_files: vec![args.file.clone()],
        max_pixels: Some(args.max_pixels),
        ..RunOptions::default()
    }
}

fn cmd_run(args: &RunArgs) -> Result<ExitCode> {
    let (reg, chosen, doc) = match registry_for(args)? {
        Ok(x) => x,
        Err(code) => return Ok(code),
    };
    let p = match load(&doc, &reg) {
        Ok(x) => x,
        Err(code) => return Ok(code),
    };
    let engine = engine(args)?;
    let t = std::time::Instant::now();
    let result = engine.run(&p, &run_options(args))?;
    let wall = t.elapsed().as_secs_f64() * 1e3;
    // Files always; other values only where the pipeline asked for that port by name.
    let named: Vec<String> = p
        .outputs
        .iter()
        .filter_map(|o| {
            o.port
                .as_ref()
                .map(|port| format!("{}.{}", p.nodes[o.node].name, port))
        })
        .collect();
    for (name, v) in &result.outputs {
        match v {
            Value::File(f) => outln!("wrote {}", f.display()),
            _ if !named.contains(name) => {}
            Value::Scalar(x) => outln!("{name} = {x}"),
            other => outln!("{name}: {} {}", other.value_type(), dims_text(other)),
        }
    }
    let ran = result.trace.evaluated().len();
    let cached = result.trace.with_status(Status::Cached).len();
    eprintln!(
        "{ran} nodes evaluated, {cached} cached, {wall:.0} ms (backend: {})",
        chosen.used
    );
    Ok(ExitCode::SUCCESS)
}

fn dims_text(v: &Value) -> String {
    v.image_dims()
        .map(|(w, h)| format!("{w}x{h}"))
        .unwrap_or_default()
}

fn cmd_check(file: &Path, sets: &[String]) -> Result<ExitCode> {
    let reg = registry()?;
    match load_pipeline(file, sets, &reg) {
        Ok((doc, p)) => {
            for n in &doc.notices {
                eprintln!("note: {n}");
            }
            outln!(
                "{}: ok ({} nodes, {} requested outputs)",
                file.display(),
                p.nodes.len(),
                p.outputs.len()
            );
            Ok(ExitCode::SUCCESS)
        }
        Err(e) => {
            report_load_error(&e);
            Ok(ExitCode::from(2))
        }
    }
}

fn cmd_nodes(kind: Option<&str>, json: bool) -> Result<ExitCode> {
    let reg = registry()?;
    let kinds: Vec<&str> = match kind {
        Some(k) => {
            if reg.get(k).is_none() {
                let hint = reg
                    .suggest(k)
                    .map(|s| format!(" (did you mean `{s}`?)"))
                    .unwrap_or_default();
                return Err(Usage(format!("unknown node kind `{k}`{hint}")).into());
            }
            vec![k]
        }
        None => reg.kinds().collect(),
    };
    if json {
        let list: Vec<serde_json::Value> = kinds
            .iter()
            .filter_map(|k| reg.get(k))
            .map(|n| schema_json(n.schema()))
            .collect();
        outln!("{}", serde_json::to_string_pretty(&list)?);
        return Ok(ExitCode::SUCCESS);
    }
    if kind.is_none() {
        for k in kinds {
            if let Some(n) = reg.get(k) {
                outln!("{:<18} {}", k, n.schema().doc.lines().next().unwrap_or(""));
            }
        }
        return Ok(ExitCode::SUCCESS);
    }
    for k in kinds {
        let Some(n) = reg.get(k) else { continue };
        let s = n.schema();
        outln!(
            "{} (version {}){}\n  {}\n",
            s.kind,
            s.version,
            if s.sink { ", sink" } else { "" },
            s.doc
        );
        outln!("  inputs:");
        if s.inputs.is_empty() {
            outln!("    (none)");
        }
        for p in &s.inputs {
            outln!(
                "    {:<14} {:<13} {}{}",
                p.name,
                p.ty,
                if p.optional { "(optional) " } else { "" },
                p.doc
            );
        }
        outln!("  outputs:");
        for p in &s.outputs {
            outln!("    {:<14} {:<13} {}", p.name, p.ty, p.doc);
        }
        outln!("  parameters:");
        if s.params.is_empty() {
            outln!("    (none)");
        }
        for p in &s.params {
            let range = p.kind.range_text();
            outln!(
                "    {:<14} {:<12} default {}{}\n        {}",
                p.name,
                p.kind.type_name(),
                p.default,
                if range.is_empty() {
                    String::new()
                } else {
                    format!(", {range}")
                },
                p.doc.replace('\n', "\n        ")
            );
        }
    }
    Ok(ExitCode::SUCCESS)
}

fn schema_json(s: &NodeSchema) -> serde_json::Value {
    let ports = |ps: &[depthgraph::graph::node::PortSpec]| -> Vec<serde_json::Value> {
        ps.iter()
            .map(|p| serde_json::json!({"name": p.name, "type": p.ty.name(), "optional": p.optional, "doc": p.doc}))
            .collect()
    };
    serde_json::json!({
        "kind": s.kind,
        "version": s.version,
        "doc": s.doc,
        "sink": s.sink,
        "inputs": ports(&s.inputs),
        "outputs": ports(&s.outputs),
        "params": s.params.iter().map(|p| serde_json::json!({
            "name": p.name,
            "type": p.kind.type_name(),
            "range": p.kind.range_text(),
            "default": p.default.to_ron(),
            "doc": p.doc,
        })).collect::<Vec<_>>(),
    })
}

fn cmd_explain(args: &RunArgs, json: bool) -> Result<ExitCode> {
    let (reg, chosen, doc) = match registry_for(args)? {
        Ok(x) => x,
        Err(code) => return Ok(code),
    };
    let p = match load(&doc, &reg) {
        Ok(x) => x,
        Err(code) => return Ok(code),
    };
    let engine = engine(args)?;
    let result = engine.run(&p, &run_options(args))?;
    if json {
        let rows: Vec<serde_json::Value> = result
            .trace
            .nodes
            .iter()
            .map(|r| {
                serde_json::json!({
                    "node": r.node, "kind": r.kind, "status": r.status.as_str(),
                    "reason": r.reason, "report": r.report, "ms": r.ms, "bytes": r.bytes, "backend": r.backend,
                    "adapter": r.adapter, "backend_note": r.backend_note, "transfers": r.transfers,
                    "key": r.key,
                    "derived": r.derived.iter().map(|d| serde_json::json!({
                        "name": d.name, "status": d.status.as_str(), "ms": d.ms, "bytes": d.bytes,
                    })).collect::<Vec<_>>(),
                })
            })
            .collect();
        // The rows stay the top-level array; the choice goes to stderr.
        eprintln!("backend: {} ({})", chosen.used, chosen.reason);
        outln!("{}", serde_json::to_string_pretty(&rows)?);
    } else {
        outln!(
            "backend: {} (requested {}: {})",
            chosen.used,
            chosen.requested.name(),
            chosen.reason
        );
        if let Some(a) = &chosen.adapter {
            outln!("adapter: {a}");
        }
        {
            use std::io::Write as _;
            write!(std::io::stdout().lock(), "{}", result.trace.table())?;
        }
    }
    Ok(ExitCode::SUCCESS)
}

#[allow(clippy::too_many_arguments)]
fn cmd_sweep(
    args: &RunArgs,
    param: &str,
    reference: Option<String>,
    truth: Option<String>,
    output: String,
    metric: Metric,
    repeats: usize,
    csv: Option<PathBuf>,
    plot: Option<PathBuf>,
) -> Result<ExitCode> {
    let (reg, chosen, doc) = match registry_for(args)? {
        Ok(x) => x,
        Err(code) => return Ok(code),
    };
    eprintln!("backend: {} ({})", chosen.used, chosen.reason);
    let Some((target, values)) = param.split_once('=') else {
        return Err(Usage("--param must be node.param=v1,v2,...".into()).into());
    };
    let values: Vec<String> = depthgraph::sweep::split_values(values)
        .into_iter()
        .filter(|v| !v.is_empty())
        .collect();
    if values.is_empty() {
        return Err(Usage(format!("--param {target}= lists no values")).into());
    }
    let stem = format!("sweep-{}", target.replace('.', "-"));
    let csv = csv.unwrap_or_else(|| args.out.join(format!("{stem}.csv")));
    let plot = plot.unwrap_or_else(|| args.out.join(format!("{stem}.svg")));
    // the sweep writes its CSV and plot itself, not through a sink: the
    // same rule (never over the pipeline or a file it reads, never one
    // over the other), checked before anything runs (the files the
    // pipeline reads at each value, by run_sweep)
    {
        use depthgraph::graph::node::canonical_for_compare as canon;
        for (flag, path) in [("--csv", &csv), ("--plot", &plot)] {
            if canon(&args.file) == canon(path) {
                return Err(Usage(format!(
                    "{flag} {}: refusing to write over a file this pipeline reads",
                    path.display()
                ))
                .into());
            }
        }
        if canon(&csv) == canon(&plot) {
            return Err(Usage(format!(
                "--csv and --plot are both {}: give each its own file",
                csv.display()
            ))
            .into());
        }
    }
    let spec = SweepSpec {
        param: target.to_string(),
        values,
        reference,
        truth,
        output,
        metric,
        repeats,
        writes: vec![csv.clone(), plot.clone()],
    };
    let engine = engine(args)?;
    let mut opts = run_options(args);
    opts.progress = None;
    // the sweep's product is its CSV and plot: its table on stdout is a
    // courtesy, so a closed stdout stops neither
    use std::io::Write as _;
    let _ = writeln!(
        std::io::stdout().lock(),
        "{:>14}  {:>12}  {:>12}  {:>8}",
        "value",
        "ms (median)",
        metric.name(),
        "missing"
    );
    let rows = match run_sweep(&engine, &doc, &reg, &spec, &opts, |r| {
        let e = r
            .error
            .map(|e| format!("{:.6}", e.value))
            .unwrap_or_else(|| r.note.clone().unwrap_or_default());
        let miss = r.error.map(|e| e.missing.to_string()).unwrap_or_default();
        let _ = writeln!(
            std::io::stdout().lock(),
            "{:>14}  {:>12.2}  {:>12}  {:>8}",
            r.value,
            r.ms_median,
            e,
            miss
        );
    }) {
        Ok(r) => r,
        Err(depthgraph::sweep::SweepError::Check(errs)) => {
            eprintln!("{errs}");
            return Ok(ExitCode::from(2));
        }
        Err(e) => return Err(e.into()),
    };
    let text = to_csv(target, metric, &rows);
    depthgraph::nodes::io::write_atomic(&csv, |tmp| std::fs::write(tmp, &text))?;
    let plotted =
        depthgraph::nodes::io::write_atomic(&plot, |tmp| plot_svg(tmp, target, metric, &rows));
    let _ = writeln!(std::io::stdout().lock(), "wrote {}", csv.display());
    match plotted {
        Ok(_) => {
            let _ = writeln!(std::io::stdout().lock(), "wrote {}", plot.display());
        }
        Err(e) => eprintln!("warning: no plot: {e}"),
    }
    Ok(ExitCode::SUCCESS)
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let r = match cli.command {
        Command::Run { common } => cmd_run(&common),
        Command::Check { file, sets } => cmd_check(&file, &sets),
        Command::Nodes { kind, json } => cmd_nodes(kind.as_deref(), json),
        Command::Explain { common, json } => cmd_explain(&common, json),
        Command::Batch(args) => batch_cli::cmd_batch(&args),
        Command::Sweep {
            common,
            param,
            reference,
            truth,
            output,
            metric,
            repeats,
            csv,
            plot,
        } => cmd_sweep(
            &common, &param, reference, truth, output, metric, repeats, csv, plot,
        ),
    };
    match r {
        Ok(code) => code,
        // a closed standard output (`depthgraph nodes | head`): nobody is
        // left to read, which is not a failure
        Err(e) if is_broken_pipe(&e) => ExitCode::SUCCESS,
        Err(e) => {
            use std::io::Write as _;
            let _ = writeln!(std::io::stderr(), "error: {e:#}");
            ExitCode::from(failure_kind(&e).exit_code())
        }
    }
}

/// A write to standard output that failed because its reader is gone
/// (the error `outln!` returns), never an error of a node's own file.
fn is_broken_pipe(e: &anyhow::Error) -> bool {
    e.downcast_ref::<std::io::Error>()
        .is_some_and(|io| io.kind() == std::io::ErrorKind::BrokenPipe)
}

/// The kind of failure of an error the commands returned (`--help` lists
/// the exit codes); anything not classified is an internal error.
fn failure_kind(e: &anyhow::Error) -> FailureKind {
    use depthgraph::sweep::SweepError;
    for c in e.chain() {
        if let Some(r) = c.downcast_ref::<RunError>() {
            return r.kind();
        }
        if let Some(u) = c.downcast_ref::<depthgraph::CacheUrlError>() {
            return u.kind;
        }
        if let Some(n) = c.downcast_ref::<NodeError>() {
            return n.kind();
        }
        if c.downcast_ref::<Usage>().is_some() || c.downcast_ref::<LoadError>().is_some() {
            return FailureKind::Usage;
        }
        if let Some(s) = c.downcast_ref::<SweepError>() {
            return match s {
                SweepError::Run(r) => r.kind(),
                SweepError::NoValue(_) => FailureKind::Internal,
                _ => FailureKind::Usage,
            };
        }
        if let Some(io) = c.downcast_ref::<std::io::Error>() {
            return FailureKind::of_io(io);
        }
    }
    FailureKind::Internal
}
