//! Background evaluation: one worker thread owns the cached [`Engine`].
//!
//! Two ways to ask for a run: [`Evaluator::start`] cancels the run in
//! flight (through `RunOptions::cancel`) and is what a typed value or a
//! slider step wants; [`Evaluator::start_queued`] lets the run in flight
//! finish and replaces whatever request was waiting behind it, which is what
//! a drag wants: each finished step is shown while the pointer moves, and no
//! stale position is ever computed (latest wins). Every run reports which
//! nodes are running and how far they are ([`Evaluator::running`]).

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::mpsc::{Receiver, RecvTimeoutError, Sender, channel};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use depthgraph_graph::prelude::*;

/// What one finished request produced.
#[derive(Debug, Clone)]
pub struct EvalOutcome {
    /// The request number [`Evaluator::start`] returned.
    pub generation: u64,
    /// The trace and the requested values, or the run's error.
    pub result: Result<(Trace, BTreeMap<String, Value>), String>,
    /// True when the run was cancelled (the error then says so).
    pub cancelled: bool,
}

/// A node of the run in flight: the fraction it reported (0 when it
/// started) and when it started.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NodeProgress {
    /// Last reported fraction in [0, 1].
    pub fraction: f32,
    /// When the node reported first (its start).
    pub started: Instant,
}

/// Progress of one request's nodes, filled by the worker's progress callback.
type ProgressMap = Arc<Mutex<BTreeMap<String, NodeProgress>>>;

struct Job {
    generation: u64,
    pipeline: Pipeline,
    options: RunOptions,
}

/// Called by the worker after each finished request and each progress
/// report (e.g. to wake the UI).
type Notify = Arc<Mutex<Option<Box<dyn Fn() + Send>>>>;

fn call(notify: &Notify) {
    if let Ok(n) = notify.lock() {
        if let Some(f) = n.as_ref() {
            f();
        }
    }
}

/// Runs pipelines on a background thread, newest request first.
pub struct Evaluator {
    notify: Notify,
    jobs: Option<Sender<Job>>,
    results: Receiver<EvalOutcome>,
    cancel: Option<CancelToken>,
    generation: u64,
    /// The newest generation whose outcome [`poll`](Self::poll) handed out.
    shown: u64,
    progress: ProgressMap,
    out_dir: PathBuf,
    worker: Option<JoinHandle<()>>,
}

impl Evaluator {
    /// An evaluator with an in-memory engine; sinks write under `out_dir`.
    pub fn new(options: EngineOptions, out_dir: PathBuf) -> Result<Self, String> {
        let engine = Arc::new(Engine::new(options).map_err(|e| e.to_string())?);
        let (job_tx, job_rx) = channel::<Job>();
        let (res_tx, res_rx) = channel::<EvalOutcome>();
        let notify: Notify = Arc::new(Mutex::new(None));
        let worker_notify = notify.clone();
        let worker = std::thread::Builder::new()
            .name("depthgraph-editor-eval".into())
            .spawn(move || {
                while let Ok(mut job) = job_rx.recv() {
                    // Skip to the newest request.
                    while let Ok(newer) = job_rx.try_recv() {
                        job = newer;
                    }
                    let run = engine.run(&job.pipeline, &job.options);
                    let cancelled = matches!(run, Err(RunError::Cancelled));
                    let outcome = EvalOutcome {
                        generation: job.generation,
                        result: run.map(|r| (r.trace, r.outputs)).map_err(|e| e.to_string()),
                        cancelled,
                    };
                    if res_tx.send(outcome).is_err() {
                        break;
                    }
                    call(&worker_notify);
                }
            })
            .map_err(|e| format!("cannot start the evaluation thread: {e}"))?;
        Ok(Self {
            notify,
            jobs: Some(job_tx),
            results: res_rx,
            cancel: None,
            generation: 0,
            shown: 0,
            progress: Arc::new(Mutex::new(BTreeMap::new())),
            out_dir,
            worker: Some(worker),
        })
    }

    /// Starts evaluating `pipeline` (its `outputs` say what is requested),
    /// cancelling the previous run; returns the request number.
    pub fn start(&mut self, pipeline: Pipeline, protected: Vec<PathBuf>) -> u64 {
        self.cancel();
        self.send(pipeline, protected)
    }

    /// Like [`start`](Self::start), but the run in flight is left to finish
    /// (its result is still handed out by [`poll`](Self::poll)); a request
    /// that was waiting behind it is replaced by this one.
    pub fn start_queued(&mut self, pipeline: Pipeline, protected: Vec<PathBuf>) -> u64 {
        self.send(pipeline, protected)
    }

    fn send(&mut self, pipeline: Pipeline, protected: Vec<PathBuf>) -> u64 {
        let cancel = CancelToken::new();
        self.cancel = Some(cancel.clone());
        self.generation += 1;
        let progress: ProgressMap = Arc::new(Mutex::new(BTreeMap::new()));
        self.progress = progress.clone();
        let notify = self.notify.clone();
        let report: depthgraph_graph::node::ProgressFn = Arc::new(move |node: &str, f: f32| {
            if let Ok(mut m) = progress.lock() {
                let now = Instant::now();
                m.entry(node.to_string())
                    .and_modify(|p| p.fraction = f)
                    .or_insert(NodeProgress {
                        fraction: f,
                        started: now,
                    });
            }
            call(&notify);
        });
        let options = RunOptions {
            cancel,
            progress: Some(report),
            out_dir: self.out_dir.clone(),
            protected_files: protected,
            ..RunOptions::default()
        };
        if let Some(tx) = &self.jobs {
            // A send error means the worker is gone; `poll` then reports nothing.
            let _ = tx.send(Job {
                generation: self.generation,
                pipeline,
                options,
            });
        }
        self.generation
    }

    /// Cancels the newest request (its outcome then says it was cancelled);
    /// false when nothing was asked for since the last cancel.
    pub fn cancel(&mut self) -> bool {
        match self.cancel.take() {
            Some(c) => {
                c.cancel();
                true
            }
            None => false,
        }
    }

    /// Calls `f` on the worker thread after each finished request and each
    /// progress report, so a window can repaint at once instead of polling.
    pub fn set_notify(&self, f: impl Fn() + Send + 'static) {
        if let Ok(mut n) = self.notify.lock() {
            *n = Some(Box::new(f));
        }
    }

    /// The newest request number handed out.
    pub fn generation(&self) -> u64 {
        self.generation
    }

    /// True while the newest request's outcome has not been handed out.
    pub fn pending(&self) -> bool {
        self.shown < self.generation
    }

    /// The nodes of the newest request that have started and not finished,
    /// with their progress.
    pub fn running(&self) -> BTreeMap<String, NodeProgress> {
        self.progress
            .lock()
            .map(|m| {
                m.iter()
                    .filter(|(_, p)| p.fraction < 1.0)
                    .map(|(k, p)| (k.clone(), *p))
                    .collect()
            })
            .unwrap_or_default()
    }

    /// The newest finished outcome not handed out before: the newest
    /// request's, or a successful older one that finished after the last
    /// shown (a step of a drag, while the next step computes). Errors of
    /// older requests (a cancelled run among them) are dropped.
    pub fn poll(&mut self) -> Option<EvalOutcome> {
        let mut latest = None;
        while let Ok(o) = self.results.try_recv() {
            if let Some(o) = self.accept(o) {
                latest = Some(o);
            }
        }
        latest
    }

    fn accept(&mut self, o: EvalOutcome) -> Option<EvalOutcome> {
        let newest = o.generation == self.generation;
        if o.generation <= self.shown || (!newest && o.result.is_err()) {
            return None;
        }
        self.shown = o.generation;
        Some(o)
    }

    /// Waits up to `timeout` for the newest request's outcome.
    pub fn wait(&mut self, timeout: Duration) -> Option<EvalOutcome> {
        let deadline = Instant::now() + timeout;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.results.recv_timeout(left) {
                Ok(o) if o.generation == self.generation => return self.accept(o),
                Ok(_) => continue,
                Err(RecvTimeoutError::Timeout) | Err(RecvTimeoutError::Disconnected) => {
                    return None;
                }
            }
        }
    }
}

impl Drop for Evaluator {
    fn drop(&mut self) {
        self.cancel();
        self.jobs.take();
        if let Some(w) = self.worker.take() {
            let _ = w.join();
        }
    }
}
