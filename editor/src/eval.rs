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
    /// Asked for with [`Evaluator::start_queued`] (a step of a gesture).
    pub queued: bool,
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
    queued: bool,
    /// Where this job's progress callback writes.
    progress: ProgressMap,
}

/// Called by the worker after each finished request and each progress
/// report (e.g. to wake the UI).
type Notify = Arc<Mutex<Option<Box<dyn Fn() + Send>>>>;

fn call(notify: &Notify) {
    if let Ok(n) = notify.lock()
        && let Some(f) = n.as_ref()
    {
        f();
    }
}

/// Runs pipelines on a background thread, newest request first.
pub struct Evaluator {
    notify: Notify,
    jobs: Option<Sender<Job>>,
    results: Receiver<EvalOutcome>,
    /// The cancel tokens of the requests whose outcomes have not come back.
    cancels: Vec<(u64, CancelToken)>,
    generation: u64,
    /// The newest generation whose outcome [`poll`](Self::poll) handed out.
    shown: u64,
    /// The progress of the job the worker runs (or ran last).
    current: Arc<Mutex<ProgressMap>>,
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
        let current: Arc<Mutex<ProgressMap>> = Arc::new(Mutex::new(Arc::default()));
        let worker_current = current.clone();
        let worker =
            std::thread::Builder::new()
                .name("depthgraph-editor-eval".into())
                .spawn(move || {
                    while let Ok(mut job) = job_rx.recv() {
                        // Skip to the newest request.
                        while let Ok(newer) = job_rx.try_recv() {
                            job = newer;
                        }
                        if let Ok(mut c) = worker_current.lock() {
                            *c = job.progress.clone();
                        }
                        // A node that panics ends its request with an internal
                        // error, never the worker (the window would wait forever).
                        let run = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                            engine.run(&job.pipeline, &job.options)
                        }));
                        let (result, cancelled) = match run {
                        Ok(Ok(r)) => (Ok((r.trace, r.outputs)), false),
                        Ok(Err(e)) => {
                            let cancelled = matches!(e, RunError::Cancelled);
                            (Err(e.to_string()), cancelled)
                        }
                        Err(_) => (
                            Err("internal error: the evaluation panicked (a bug: please report it)"
                                .to_string()),
                            false,
                        ),
                    };
                        let outcome = EvalOutcome {
                            generation: job.generation,
                            result,
                            cancelled,
                            queued: job.queued,
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
            cancels: Vec::new(),
            generation: 0,
            shown: 0,
            current,
            out_dir,
            worker: Some(worker),
        })
    }

    /// Starts evaluating `pipeline` (its `outputs` say what is requested),
    /// cancelling the previous run; returns the request number.
    pub fn start(&mut self, pipeline: Pipeline, protected: Vec<PathBuf>) -> u64 {
        self.cancel();
        self.send(pipeline, protected, false)
    }

    /// Like [`start`](Self::start), but the run in flight is left to finish
    /// (its result is still handed out by [`poll`](Self::poll)); a request
    /// that was waiting behind it is replaced by this one.
    pub fn start_queued(&mut self, pipeline: Pipeline, protected: Vec<PathBuf>) -> u64 {
        self.send(pipeline, protected, true)
    }

    fn send(&mut self, pipeline: Pipeline, protected: Vec<PathBuf>, queued: bool) -> u64 {
        let cancel = CancelToken::new();
        self.generation += 1;
        self.cancels.push((self.generation, cancel.clone()));
        let progress: ProgressMap = Arc::new(Mutex::new(BTreeMap::new()));
        let job_progress = progress.clone();
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
                queued,
                progress: job_progress,
            });
        }
        self.generation
    }

    /// Cancels every request whose outcome has not come back, the run in
    /// flight and those waiting behind it (the newest one's outcome then
    /// says it was cancelled); false when there was none.
    pub fn cancel(&mut self) -> bool {
        let any = !self.cancels.is_empty();
        for (_, c) in self.cancels.drain(..) {
            c.cancel();
        }
        any
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

    /// The nodes of the run in flight (or, once it ended, of the last run)
    /// that have started and not finished, with their progress.
    pub fn running(&self) -> BTreeMap<String, NodeProgress> {
        let Ok(current) = self.current.lock().map(|c| c.clone()) else {
            return BTreeMap::new();
        };
        current
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
    /// request's, or a successful older one asked for with
    /// [`start_queued`](Self::start_queued) that finished after the last
    /// shown (a step of a drag, while the next step computes). Other older
    /// outcomes (cancelled runs among them) are dropped.
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
        // Its run is over: its token (and older ones) need no cancelling.
        self.cancels.retain(|(g, _)| *g > o.generation);
        let newest = o.generation == self.generation;
        let step = o.queued && o.result.is_ok();
        if o.generation <= self.shown || !(newest || step) {
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
                Ok(o) => {
                    self.cancels.retain(|(g, _)| *g > o.generation);
                    continue;
                }
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
