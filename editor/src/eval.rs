//! Background evaluation: one worker thread owns the cached [`Engine`]; a new
//! request cancels the run in flight (through `RunOptions::cancel`).

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::mpsc::{Receiver, RecvTimeoutError, Sender, channel};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::Duration;

use depthgraph_graph::prelude::*;

/// What one finished request produced.
#[derive(Debug, Clone)]
pub struct EvalOutcome {
    /// The request number [`Evaluator::start`] returned.
    pub generation: u64,
    /// The trace and the requested values, or the run's error.
    pub result: Result<(Trace, BTreeMap<String, Value>), String>,
}

struct Job {
    generation: u64,
    pipeline: Pipeline,
    options: RunOptions,
}

/// Called by the worker after each finished request (e.g. to wake the UI).
type Notify = Arc<Mutex<Option<Box<dyn Fn() + Send>>>>;

/// Runs pipelines on a background thread, newest request first.
pub struct Evaluator {
    notify: Notify,
    jobs: Option<Sender<Job>>,
    results: Receiver<EvalOutcome>,
    cancel: Option<CancelToken>,
    generation: u64,
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
                    let result = engine
                        .run(&job.pipeline, &job.options)
                        .map(|r| (r.trace, r.outputs))
                        .map_err(|e| e.to_string());
                    let outcome = EvalOutcome {
                        generation: job.generation,
                        result,
                    };
                    if res_tx.send(outcome).is_err() {
                        break;
                    }
                    if let Ok(n) = worker_notify.lock() {
                        if let Some(f) = n.as_ref() {
                            f();
                        }
                    }
                }
            })
            .map_err(|e| format!("cannot start the evaluation thread: {e}"))?;
        Ok(Self {
            notify,
            jobs: Some(job_tx),
            results: res_rx,
            cancel: None,
            generation: 0,
            out_dir,
            worker: Some(worker),
        })
    }

    /// Starts evaluating `pipeline` (its `outputs` say what is requested),
    /// cancelling the previous run; returns the request number.
    pub fn start(&mut self, pipeline: Pipeline, protected: Vec<PathBuf>) -> u64 {
        if let Some(c) = self.cancel.take() {
            c.cancel();
        }
        let cancel = CancelToken::new();
        self.cancel = Some(cancel.clone());
        self.generation += 1;
        let options = RunOptions {
            cancel,
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

    /// Calls `f` on the worker thread after each finished request, so a
    /// window can repaint at once instead of polling.
    pub fn set_notify(&self, f: impl Fn() + Send + 'static) {
        if let Ok(mut n) = self.notify.lock() {
            *n = Some(Box::new(f));
        }
    }

    /// The newest request number handed out.
    pub fn generation(&self) -> u64 {
        self.generation
    }

    /// A finished outcome of the newest request, if one is ready (older ones are dropped).
    pub fn poll(&mut self) -> Option<EvalOutcome> {
        let mut latest = None;
        while let Ok(o) = self.results.try_recv() {
            if o.generation == self.generation {
                latest = Some(o);
            }
        }
        latest
    }

    /// Waits up to `timeout` for the newest request's outcome.
    pub fn wait(&mut self, timeout: Duration) -> Option<EvalOutcome> {
        let deadline = std::time::Instant::now() + timeout;
        loop {
            let left = deadline.saturating_duration_since(std::time::Instant::now());
            match self.results.recv_timeout(left) {
                Ok(o) if o.generation == self.generation => return Some(o),
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
        if let Some(c) = self.cancel.take() {
            c.cancel();
        }
        self.jobs.take();
        if let Some(w) = self.worker.take() {
            let _ = w.join();
        }
    }
}
