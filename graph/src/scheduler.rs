//! The cached, demand-driven scheduler.
//!
//! 1. Every node's Merkle [`Key`] is computed before anything runs.
//! 2. Starting from the requested outputs, each node is looked up in the
//!    memory cache, then the disk cache; only on a miss are its inputs
//!    demanded in turn. Nodes upstream of a hit are "not needed".
//! 3. The nodes to run are grouped in dependency levels; the nodes of a level
//!    run in parallel on a rayon pool of the requested size.
//! 4. Each node's status (ran / cached / passthrough / not_needed), reason,
//!    time and bytes go into the [`Trace`] that `explain` prints.
//!
//! Results do not depend on the thread count as long as nodes are
//! deterministic (the contract of [`Node`](crate::node::Node)).

use std::collections::{BTreeMap, HashMap};
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::Instant;

use crate::cache::{BlobStore, DiskCache, MemoryCache, RemoteCache};
use crate::codec::Decoders;
use crate::error::RunError;
use crate::key::{Key, node_key, with_file_contents};
use crate::node::{
    CancelToken, Derivations, EvalCtx, Inputs, NodeError, Outputs, ProgressFn, ValueStore,
    canonical_for_compare, resolve_output,
};
use crate::params::{ParamKind, ParamValue};
use crate::pipeline::Pipeline;
use crate::trace::{DerivedRecord, NodeRecord, Status, Trace};
use crate::value::Value;

/// How an [`Engine`] keeps results and how many threads it uses.
#[derive(Clone)]
pub struct EngineOptions {
    /// In-memory cache budget in bytes.
    pub memory_budget_bytes: usize,
    /// Persistent cache, or `None` to keep results only in memory.
    pub disk: Option<DiskCache>,
    /// Worker threads (0 = rayon's default, one per core).
    pub threads: usize,
    /// A store many workers share (object store), looked up after the
    /// disk cache and written with it; `None` for none.
    pub remote: Option<Arc<dyn BlobStore>>,
}

impl std::fmt::Debug for EngineOptions {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("EngineOptions")
            .field("memory_budget_bytes", &self.memory_budget_bytes)
            .field("disk", &self.disk)
            .field("threads", &self.threads)
            .field("remote", &self.remote.as_ref().map(|r| r.describe()))
            .finish()
    }
}

impl Default for EngineOptions {
    fn default() -> Self {
        Self {
            memory_budget_bytes: 1 << 30,
            disk: None,
            threads: 0,
            remote: None,
        }
    }
}

/// Options of one run.
#[derive(Clone, Default)]
pub struct RunOptions {
    /// Cancels the run when triggered.
    pub cancel: CancelToken,
    /// Receives the nodes' progress reports, if set.
    pub progress: Option<ProgressFn>,
    /// Where relative output paths of sinks go.
    pub out_dir: PathBuf,
    /// Nodes (by index) that must run even when cached (used by `sweep` to time them).
    pub force: Vec<usize>,
    /// Skip cache lookups entirely (results are still stored).
    pub no_cache_lookup: bool,
    /// More files sinks must never overwrite (e.g. the pipeline file itself),
    /// besides those the load nodes read.
    pub protected_files: Vec<PathBuf>,
    /// The pixel budget of one decoded file (`None`:
    /// [`DEFAULT_MAX_PIXELS`](crate::node::DEFAULT_MAX_PIXELS)); not part
    /// of any cache key (a run within the budget computes the same values).
    pub max_pixels: Option<usize>,
}

/// Everything a run produced.
#[derive(Debug, Clone)]
pub struct RunResult {
    /// Requested values by `"node.port"`.
    pub outputs: BTreeMap<String, Value>,
    /// What each node did.
    pub trace: Trace,
}

/// Evaluates pipelines, keeping results between runs.
pub struct Engine {
    memory: Mutex<MemoryCache>,
    disk: Option<DiskCache>,
    remote: Option<RemoteCache>,
    pool: rayon::ThreadPool,
    threads: usize,
}

/// A node index with its outputs and time (ms), or the error it raised.
type Finished = (usize, Result<(Outputs, f64, Vec<DerivedRecord>), RunError>);

enum State {
    Unvisited,
    Hit(Arc<Outputs>, f64),
    Run,
}

impl Engine {
    /// An engine with an empty memory cache and its own thread pool; fails
    /// when the threads cannot be started.
    pub fn new(options: EngineOptions) -> Result<Self, RunError> {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(options.threads)
            .thread_name(|i| format!("depthgraph-{i}"))
            .build()
            .map_err(|e| RunError::Threads(e.to_string()))?;
        Ok(Self {
            memory: Mutex::new(MemoryCache::new(options.memory_budget_bytes)),
            disk: options.disk,
            remote: options.remote.map(RemoteCache::new),
            threads: pool.current_num_threads(),
            pool,
        })
    }

    /// Number of worker threads.
    pub fn threads(&self) -> usize {
        self.threads
    }

    /// Whether the shared store (`EngineOptions::remote`) failed a call,
    /// after which this engine stopped using it.
    pub fn remote_failed(&self) -> bool {
        self.remote.as_ref().is_some_and(|r| r.failed())
    }

    /// Drops every in-memory result.
    pub fn clear_memory(&self) {
        self.lock_memory().clear();
    }

    fn lock_memory(&self) -> std::sync::MutexGuard<'_, MemoryCache> {
        // A panic in another thread while holding the lock leaves a valid
        // cache (every mutation completes before unlocking), so recover it.
        self.memory.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Every node's cache key, by node index (a loader's key includes the
    /// contents of the files it reads).
    pub fn keys(pipeline: &Pipeline) -> Vec<Key> {
        let mut keys: Vec<Option<Key>> = vec![None; pipeline.nodes.len()];
        for &i in &pipeline.order {
            // toposort guarantees the sources were keyed first
            let n = &pipeline.nodes[i];
            let files = n.node.input_files(&n.params);
            keys[i] = Some(Self::key_of(
                pipeline,
                i,
                |j| keys[j].unwrap_or(Key::from_bytes([0; 32])),
                &files,
            ));
        }
        keys.into_iter()
            .map(|k| k.unwrap_or(Key::from_bytes([0; 32])))
            .collect()
    }

    /// Node `i`'s key, given its sources' keys (`source(node index)`) and
    /// the `files` it reads (its `input_files`), as they are now.
    fn key_of(
        pipeline: &Pipeline,
        i: usize,
        source: impl Fn(usize) -> Key,
        files: &[std::path::PathBuf],
    ) -> Key {
        let n = &pipeline.nodes[i];
        let schema = n.node.schema();
        let inputs: Vec<(&str, &str, Key)> = n
            .inputs
            .iter()
            .map(|(port, src)| (port.as_str(), src.port.as_str(), source(src.node)))
            .collect();
        let own = node_key(schema.kind, schema.version, &n.params, &inputs);
        with_file_contents(own, files)
    }

    /// Runs what the pipeline's requested outputs need.
    pub fn run(&self, pipeline: &Pipeline, options: &RunOptions) -> Result<RunResult, RunError> {
        self.pool.install(|| self.run_inner(pipeline, options))
    }

    /// Two sinks of this run that would write the same file (the same
    /// output path once resolved against `out_dir`): an error naming both,
    /// before anything runs. Both ran at once and the file held whichever
    /// finished last, different from run to run.
    fn check_distinct_outputs(
        p: &Pipeline,
        state: &[State],
        out_dir: &std::path::Path,
    ) -> Result<(), RunError> {
        let mut seen: BTreeMap<PathBuf, (usize, &str)> = BTreeMap::new();
        for &i in &p.order {
            let n = &p.nodes[i];
            if !matches!(state[i], State::Run) || !n.node.schema().sink {
                continue;
            }
            for spec in &n.node.schema().params {
                if !matches!(spec.kind, ParamKind::OutputPath) {
                    continue;
                }
                let Some(ParamValue::Text(path)) = n.params.get(spec.name) else {
                    continue;
                };
                if path.is_empty() {
                    continue;
                }
                let file = resolve_output(out_dir, path);
                let canon = canonical_for_compare(&file);
                if let Some((j, other)) = seen.get(&canon) {
                    let first = &p.nodes[*j];
                    return Err(RunError::Node {
                        node: n.name.clone(),
                        kind: n.kind.clone(),
                        error: NodeError::param(
                            spec.name,
                            format!(
                                "{} is also written by node `{}` ({}.{}): one would replace the \
                                 other; give each sink its own path",
                                file.display(),
                                first.name,
                                first.name,
                                other
                            ),
                        ),
                    });
                }
                seen.insert(canon, (i, spec.name));
            }
        }
        Ok(())
    }

    fn run_inner(&self, p: &Pipeline, opts: &RunOptions) -> Result<RunResult, RunError> {
        let n = p.nodes.len();
        let keys = Self::keys(p);
        let mut state: Vec<State> = (0..n).map(|_| State::Unvisited).collect();

        // Demand: from the requested outputs, stop at cache hits.
        let mut stack: Vec<usize> = p.outputs.iter().map(|o| o.node).collect();
        while let Some(i) = stack.pop() {
            if !matches!(state[i], State::Unvisited) {
                continue;
            }
            let node = &p.nodes[i];
            let cacheable = !node.node.schema().sink && !opts.force.contains(&i);
            let hit = if cacheable && !opts.no_cache_lookup {
                self.lookup(&keys[i], &p.decoders)
            } else {
                None
            };
            match hit {
                Some((out, ms)) => state[i] = State::Hit(out, ms),
                None => {
                    state[i] = State::Run;
                    stack.extend(node.inputs.values().map(|s| s.node));
                }
            }
        }

        // Levels of the nodes to run.
        let mut level = vec![0usize; n];
        let mut max_level = 0;
        for &i in &p.order {
            if matches!(state[i], State::Run) {
                level[i] = p.nodes[i]
                    .inputs
                    .values()
                    .filter(|s| matches!(state[s.node], State::Run))
                    .map(|s| level[s.node] + 1)
                    .max()
                    .unwrap_or(0);
                max_level = max_level.max(level[i]);
            }
        }

        let mut results: Vec<Option<Arc<Outputs>>> = state
            .iter()
            .map(|s| match s {
                State::Hit(o, _) => Some(o.clone()),
                _ => None,
            })
            .collect();
        let mut timings: Vec<f64> = vec![0.0; n];
        let mut derived: Vec<Vec<DerivedRecord>> = vec![Vec::new(); n];
        // Results that may not match their keys: a file the node read
        // changed during the run, or an input came from such a node. They
        // are used, never kept (nor the values derived from them).
        let mut tainted = vec![false; n];
        let mut input_files = p.input_files();
        input_files.extend(opts.protected_files.iter().cloned());
        Self::check_distinct_outputs(p, &state, &opts.out_dir)?;

        // A value no node still to run reads, and that the run does not
        // return, is let go once its readers are done (only its size and
        // what the trace shows are kept): peak memory is the values alive
        // at once, not every value of the run (a 20-node pipeline on a
        // 256-megapixel photo held 60 GiB). The caches keep what their
        // budgets allow.
        let mut readers_left = vec![0usize; n];
        for (j, s) in state.iter().enumerate() {
            if matches!(s, State::Run) {
                for src in p.nodes[j].inputs.values() {
                    readers_left[src.node] += 1;
                }
            }
        }
        let returned: std::collections::HashSet<usize> = p.outputs.iter().map(|o| o.node).collect();
        let mut value_bytes: Vec<Option<usize>> = vec![None; n];
        // cache hits that no node to run reads (and the run does not
        // return) go at once
        for (j, &left) in readers_left.iter().enumerate() {
            if left == 0 && !returned.contains(&j) {
                let_go(j, &mut results, &mut state, &mut value_bytes);
            }
        }
        let position: HashMap<usize, usize> =
            p.order.iter().enumerate().map(|(k, &i)| (i, k)).collect();
        for l in 0..=max_level {
            let batch: Vec<usize> = p
                .order
                .iter()
                .copied()
                .filter(|&i| matches!(state[i], State::Run) && level[i] == l)
                .collect();
            if batch.is_empty() {
                continue;
            }
            for &i in &batch {
                tainted[i] = p.nodes[i].inputs.values().any(|src| tainted[src.node]);
            }
            let done: Mutex<Vec<Finished>> = Mutex::new(Vec::new());
            let results_ref = &results;
            let tainted_ref = &tainted;
            rayon::scope(|s| {
                for &i in &batch {
                    let done = &done;
                    let input_files = &input_files;
                    let keys = &keys;
                    s.spawn(move |_| {
                        let with = NodeRun {
                            input_files,
                            keys,
                            keep_derived: !tainted_ref[i],
                        };
                        let r = self.eval_node(p, i, results_ref, opts, &with);
                        done.lock().unwrap_or_else(|e| e.into_inner()).push((i, r));
                    });
                }
            });
            let mut done = done.into_inner().unwrap_or_else(|e| e.into_inner());
            // Deterministic error reporting: the first failing node in
            // order; the level's other results are kept all the same.
            done.sort_by_key(|(i, _)| position.get(i).copied());
            let mut first_error = None;
            for (i, r) in done {
                let (out, ms, derived_here) = match r {
                    Ok(v) => v,
                    Err(e) => {
                        first_error.get_or_insert(e);
                        continue;
                    }
                };
                derived[i] = derived_here;
                let out = Arc::new(out);
                // A file the node read that changed since the run began
                // (a capture still being written) may have given this
                // result from other contents than the key names: it is
                // used, not kept (the next run keys the new contents),
                // and neither is anything computed from it.
                let n = &p.nodes[i];
                let files = n.node.input_files(&n.params);
                if !files.is_empty() && Self::key_of(p, i, |j| keys[j], &files) != keys[i] {
                    tainted[i] = true;
                }
                if !n.node.schema().sink && !tainted[i] {
                    self.keep(keys[i], &out);
                }
                timings[i] = ms;
                results[i] = Some(out);
            }
            if let Some(e) = first_error {
                return Err(e);
            }
            for &i in &batch {
                for src in p.nodes[i].inputs.values() {
                    let j = src.node;
                    readers_left[j] = readers_left[j].saturating_sub(1);
                    if readers_left[j] == 0 && !returned.contains(&j) {
                        let_go(j, &mut results, &mut state, &mut value_bytes);
                    }
                }
            }
        }

        // Requested values.
        let mut outputs = BTreeMap::new();
        for o in &p.outputs {
            let node = &p.nodes[o.node];
            if let Some(r) = &results[o.node] {
                for (port, v) in &r.values {
                    if o.port.as_deref().is_none_or(|want| want == port) {
                        outputs.insert(format!("{}.{}", node.name, port), v.clone());
                    }
                }
            }
        }

        // Trace in file order.
        let records = (0..n)
            .map(|i| {
                let node = &p.nodes[i];
                let (status, reason, report, ms) = match &state[i] {
                    State::Unvisited => (Status::NotNeeded, None, None, 0.0),
                    State::Hit(o, ms) => {
                        (Status::Cached, o.passthrough.clone(), o.report.clone(), *ms)
                    }
                    State::Run => {
                        let o = results[i].as_ref();
                        let r = o.and_then(|o| o.passthrough.clone());
                        let st = if r.is_some() {
                            Status::Passthrough
                        } else {
                            Status::Ran
                        };
                        (st, r, o.and_then(|o| o.report.clone()), timings[i])
                    }
                };
                let origin = results[i].as_ref().and_then(|o| o.origin.clone());
                let (backend, adapter, backend_note) = match origin {
                    Some(o) => (o.backend, o.adapter, o.note),
                    None => (node.node.backend().to_string(), node.node.adapter(), None),
                };
                let transfers = match &state[i] {
                    State::Run => results[i].as_ref().map(|o| o.transfers).unwrap_or_default(),
                    _ => Default::default(),
                };
                NodeRecord {
                    node: node.name.clone(),
                    kind: node.kind.clone(),
                    status,
                    reason,
                    report,
                    ms,
                    bytes: value_bytes[i]
                        .unwrap_or_else(|| results[i].as_ref().map_or(0, |o| o.bytes())),
                    backend,
                    adapter,
                    backend_note,
                    transfers,
                    key: keys[i].to_hex(),
                    derived: std::mem::take(&mut derived[i]),
                }
            })
            .collect();
        Ok(RunResult {
            outputs,
            trace: Trace {
                nodes: records,
                threads: self.threads,
            },
        })
    }

    fn lookup(&self, key: &Key, decoders: &Decoders) -> Option<(Arc<Outputs>, f64)> {
        let t = Instant::now();
        if let Some(o) = self.lock_memory().get(key) {
            return Some((o, t.elapsed().as_secs_f64() * 1e3));
        }
        if let Some(out) = self.disk.as_ref().and_then(|d| d.get(key, decoders)) {
            let out = Arc::new(out);
            self.lock_memory().put(*key, out.clone());
            return Some((out, t.elapsed().as_secs_f64() * 1e3));
        }
        let out = Arc::new(self.remote.as_ref()?.get(key, decoders)?);
        self.lock_memory().put(*key, out.clone());
        if let Some(disk) = &self.disk {
            let _ = disk.put(key, &out);
        }
        Some((out, t.elapsed().as_secs_f64() * 1e3))
    }

    /// Keeps a result in every cache level. A cache that cannot be written
    /// is not an error of the run.
    fn keep(&self, key: Key, out: &Arc<Outputs>) {
        self.lock_memory().put(key, out.clone());
        if let Some(disk) = &self.disk {
            let _ = disk.put(&key, out);
        }
        if let Some(remote) = &self.remote {
            let _ = remote.put(&key, out);
        }
    }

    fn eval_node(
        &self,
        p: &Pipeline,
        i: usize,
        results: &[Option<Arc<Outputs>>],
        opts: &RunOptions,
        with: &NodeRun,
    ) -> Result<(Outputs, f64, Vec<DerivedRecord>), RunError> {
        let NodeRun {
            input_files,
            keys,
            keep_derived,
        } = *with;
        let node = &p.nodes[i];
        let schema = node.node.schema();
        let fail = |error: NodeError| RunError::Node {
            node: node.name.clone(),
            kind: node.kind.clone(),
            error,
        };
        if opts.cancel.is_cancelled() {
            return Err(RunError::Cancelled);
        }
        let mut inputs = Inputs::new();
        for (port, src) in &node.inputs {
            let v = results[src.node]
                .as_ref()
                .and_then(|o| o.values.get(&src.port))
                .ok_or_else(|| RunError::MissingOutput {
                    node: p.nodes[src.node].name.clone(),
                    kind: p.nodes[src.node].kind.clone(),
                    port: src.port.clone(),
                })?;
            // a Mask feeding a Confidence port (or the reverse) is retagged here
            let v = match schema.input(port) {
                Some(spec) => v.clone().converted_to(spec.ty),
                None => v.clone(),
            };
            inputs.insert(port.clone(), v);
        }
        let input_keys: BTreeMap<String, Key> = node
            .inputs
            .iter()
            .map(|(port, src)| {
                let mut h = blake3::Hasher::new();
                h.update(keys[src.node].as_bytes());
                h.update(src.port.as_bytes());
                (port.clone(), Key::from_bytes(*h.finalize().as_bytes()))
            })
            .collect();
        let store = EngineStore {
            engine: self,
            decoders: &p.decoders,
            lookup: !opts.no_cache_lookup,
            keep: keep_derived,
        };
        let derivations = Derivations {
            store: &store,
            kind: schema.kind,
            version: schema.version,
            input_keys: &input_keys,
            records: Mutex::new(Vec::new()),
        };
        let ctx = EvalCtx {
            node: &node.name,
            cancel: &opts.cancel,
            progress: opts.progress.as_ref(),
            out_dir: &opts.out_dir,
            input_files,
            derivations: Some(&derivations),
            max_pixels: opts.max_pixels.unwrap_or(crate::node::DEFAULT_MAX_PIXELS),
        };
        // A start report (0), so a listener knows which nodes run, also
        // those that never report progress themselves.
        ctx.progress(0.0);
        let t = Instant::now();
        // A panic inside a node (a bug) is that node's internal error, with
        // its name and kind, and the other nodes of the level keep theirs.
        let evaluated = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            node.node.eval(&ctx, &inputs, &node.params)
        }))
        .unwrap_or_else(|payload| {
            let what = payload
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| payload.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "no message".to_string());
            Err(NodeError::Internal(format!("the node panicked: {what}")))
        });
        let out = evaluated.map_err(|e| match e {
            NodeError::Cancelled => RunError::Cancelled,
            e => fail(e),
        })?;
        let ms = t.elapsed().as_secs_f64() * 1e3;
        let mut out = out;
        if out.origin.is_none() {
            out.origin = Some(crate::node::Origin {
                backend: node.node.backend().to_string(),
                adapter: node.node.adapter(),
                note: None,
            });
        }
        for spec in &schema.outputs {
            match out.values.get(spec.name) {
                None => {
                    return Err(RunError::MissingOutput {
                        node: node.name.clone(),
                        kind: node.kind.clone(),
                        port: spec.name.to_string(),
                    });
                }
                Some(v) if !v.value_type().connects_to(spec.ty) => {
                    return Err(RunError::WrongOutputType {
                        node: node.name.clone(),
                        kind: node.kind.clone(),
                        port: spec.name.to_string(),
                        expected: spec.ty,
                        found: v.value_type(),
                    });
                }
                _ => {}
            }
        }
        ctx.progress(1.0);
        let records = derivations
            .records
            .into_inner()
            .unwrap_or_else(|e| e.into_inner());
        Ok((out, ms, records))
    }
}

/// Lets go of node `j`'s values (see `readers_left` in `Engine::run`):
/// its result, and its cache hit's, become a shell with what the trace
/// shows (pass-through, report, origin, transfers) and its size is noted.
fn let_go(
    j: usize,
    results: &mut [Option<Arc<Outputs>>],
    state: &mut [State],
    value_bytes: &mut [Option<usize>],
) {
    let Some(o) = results[j].take() else {
        return;
    };
    value_bytes[j] = Some(o.bytes());
    let shell = Arc::new(Outputs {
        values: BTreeMap::new(),
        passthrough: o.passthrough.clone(),
        report: o.report.clone(),
        origin: o.origin.clone(),
        transfers: o.transfers,
    });
    if let State::Hit(held, _) = &mut state[j] {
        *held = shell.clone();
    }
    results[j] = Some(shell);
}

/// What one node's evaluation shares with the run: the files the pipeline
/// reads (no output may replace one), every node's key, and whether the
/// values it derives may be kept (see `tainted` in `run`).
#[derive(Clone, Copy)]
struct NodeRun<'a> {
    input_files: &'a [PathBuf],
    keys: &'a [Key],
    keep_derived: bool,
}

/// The engine's caches as the store of derived values: one value under
/// the port name `value`.
struct EngineStore<'a> {
    engine: &'a Engine,
    decoders: &'a Decoders,
    lookup: bool,
    /// False when the node's inputs may not match their keys (see
    /// `tainted` in `run`): its derived values are then not kept.
    keep: bool,
}

impl ValueStore for EngineStore<'_> {
    fn lookup(&self, key: &Key) -> Option<Value> {
        if !self.lookup {
            return None;
        }
        let (out, _) = self.engine.lookup(key, self.decoders)?;
        out.values.get("value").cloned()
    }
    fn store(&self, key: Key, value: Value) {
        if !self.keep {
            return;
        }
        let out = Arc::new(Outputs::new().with("value", value));
        self.engine.keep(key, &out);
    }
}
