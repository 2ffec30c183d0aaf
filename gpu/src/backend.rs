//! Choosing the backend: `auto` (the GPU when a hardware adapter exists;
//! a software one such as lavapipe is slower than the CPU nodes), `cpu` or
//! `gpu` (any adapter, or fail before running when there is none), from the
//! command line or `DEPTHGRAPH_BACKEND`.

use std::sync::Arc;

use depthgraph_graph::registry::Registry;

use crate::context::{AdapterRequest, GpuContext, GpuError};

/// The backend a user asked for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum BackendRequest {
    /// The GPU when a hardware adapter exists, else the CPU.
    #[default]
    Auto,
    /// The CPU only.
    Cpu,
    /// The GPU, or an error before anything runs.
    Gpu,
}

impl BackendRequest {
    /// The names the command line and `DEPTHGRAPH_BACKEND` accept.
    pub const NAMES: &[&str] = &["auto", "cpu", "gpu"];

    /// Parses `auto`, `cpu` or `gpu` (case-insensitive).
    pub fn parse(s: &str) -> Option<Self> {
        match s.trim().to_ascii_lowercase().as_str() {
            "auto" => Some(Self::Auto),
            "cpu" => Some(Self::Cpu),
            "gpu" | "wgpu" => Some(Self::Gpu),
            _ => None,
        }
    }

    /// The name.
    pub fn name(self) -> &'static str {
        match self {
            Self::Auto => "auto",
            Self::Cpu => "cpu",
            Self::Gpu => "gpu",
        }
    }
}

/// What was chosen, and why.
#[derive(Debug, Clone)]
pub struct BackendChoice {
    /// What was asked for.
    pub requested: BackendRequest,
    /// The backend the device kinds run on: "wgpu" or "cpu".
    pub used: &'static str,
    /// The device, when the GPU is used.
    pub ctx: Option<Arc<GpuContext>>,
    /// Why, in words (shown by `explain`).
    pub reason: String,
}

impl BackendChoice {
    /// The CPU, for `reason`.
    pub fn cpu(requested: BackendRequest, reason: impl Into<String>) -> Self {
        Self {
            requested,
            used: "cpu",
            ctx: None,
            reason: reason.into(),
        }
    }
}

/// Opens the device `req` calls for and installs the device kinds in `reg`.
/// `Gpu` without an adapter is an error; `Auto` then falls back to the CPU
/// and says why.
pub fn choose(req: BackendRequest, reg: &mut Registry) -> Result<BackendChoice, GpuError> {
    if req == BackendRequest::Cpu {
        return Ok(BackendChoice::cpu(req, "--backend cpu"));
    }
    match GpuContext::new(&AdapterRequest::default()) {
        // A software rasterizer (Mesa's lavapipe/llvmpipe, WARP) is an
        // adapter but not a GPU: the CPU nodes, vectorised and threaded,
        // are faster than the same kernels emulated on the CPU, so `auto`
        // takes the CPU; `gpu` still uses it (the parity tests do).
        Ok(ctx) if req == BackendRequest::Auto && ctx.adapter().is_software() => {
            Ok(BackendChoice::cpu(
                req,
                format!(
                    "auto: the only adapter, {}, is a software one (slower than the CPU nodes); \
                     running on the CPU (--backend gpu uses it)",
                    ctx.adapter().label()
                ),
            ))
        }
        Ok(ctx) => {
            crate::install(reg, &ctx).map_err(|e| ctx.error(e.to_string()))?;
            let reason = format!("{} adapter {}", req.name(), ctx.adapter().label());
            Ok(BackendChoice {
                requested: req,
                used: "wgpu",
                ctx: Some(ctx),
                reason,
            })
        }
        Err(e) if req == BackendRequest::Auto => Ok(BackendChoice::cpu(
            req,
            format!("auto: {e}; running on the CPU"),
        )),
        Err(e) => Err(e),
    }
}
