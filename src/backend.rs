//! `--backend auto|cpu|gpu` (and `DEPTHGRAPH_BACKEND`): which registry the
//! CLI runs with, and why. Without the `gpu` feature every request runs on
//! the CPU, and `gpu` is refused before anything runs.

use depthgraph_graph::registry::Registry;

/// The backend a user asked for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum Backend {
    /// The GPU when a wgpu adapter exists, else the CPU (and `explain` says why).
    #[default]
    Auto,
    /// The CPU only.
    Cpu,
    /// The GPU; fails before running when no adapter exists.
    Gpu,
}

impl Backend {
    /// The name.
    pub fn name(self) -> &'static str {
        match self {
            Backend::Auto => "auto",
            Backend::Cpu => "cpu",
            Backend::Gpu => "gpu",
        }
    }

    /// `--backend` when given, else `DEPTHGRAPH_BACKEND`, else `auto`.
    pub fn resolve(flag: Option<Backend>) -> Result<Backend, BackendError> {
        if let Some(b) = flag {
            return Ok(b);
        }
        match std::env::var("DEPTHGRAPH_BACKEND") {
            Err(_) => Ok(Backend::Auto),
            Ok(v) => match v.trim().to_ascii_lowercase().as_str() {
                "" | "auto" => Ok(Backend::Auto),
                "cpu" => Ok(Backend::Cpu),
                "gpu" | "wgpu" => Ok(Backend::Gpu),
                _ => Err(BackendError::BadVariable(v)),
            },
        }
    }
}

/// Why the requested backend cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum BackendError {
    /// `DEPTHGRAPH_BACKEND` holds something else than auto, cpu or gpu.
    #[error("DEPTHGRAPH_BACKEND={0:?}: expected auto, cpu or gpu")]
    BadVariable(String),
    /// `gpu` was asked for and no device could be opened.
    #[error("--backend gpu: {0}")]
    NoDevice(String),
}

/// The backend in use and why (what `explain` prints first).
#[derive(Debug, Clone)]
pub struct Chosen {
    /// What was asked for.
    pub requested: Backend,
    /// "wgpu" or "cpu".
    pub used: &'static str,
    /// The adapter, when the GPU is used.
    pub adapter: Option<String>,
    /// Why, in words.
    pub reason: String,
}

/// Installs the device kinds in `reg` as `requested` asks.
#[cfg(feature = "gpu")]
pub fn apply(requested: Backend, reg: &mut Registry) -> Result<Chosen, BackendError> {
    use depthgraph_gpu::BackendRequest;
    let req = match requested {
        Backend::Auto => BackendRequest::Auto,
        Backend::Cpu => BackendRequest::Cpu,
        Backend::Gpu => BackendRequest::Gpu,
    };
    let c = depthgraph_gpu::choose(req, reg).map_err(|e| BackendError::NoDevice(e.to_string()))?;
    Ok(Chosen {
        requested,
        used: c.used,
        adapter: c.ctx.as_ref().map(|ctx| ctx.adapter().label()),
        reason: c.reason,
    })
}

/// Without the `gpu` feature: the CPU, or an error for `gpu`.
#[cfg(not(feature = "gpu"))]
pub fn apply(requested: Backend, reg: &mut Registry) -> Result<Chosen, BackendError> {
    let _ = reg;
    let why = "this depthgraph was built without the `gpu` feature";
    match requested {
        Backend::Gpu => Err(BackendError::NoDevice(why.to_string())),
        _ => Ok(Chosen {
            requested,
            used: "cpu",
            adapter: None,
            reason: format!("{}: {why}", requested.name()),
        }),
    }
}
