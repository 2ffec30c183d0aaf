//! The record of a run: what each node did and why (what `explain` prints).

use std::fmt::Write as _;

use serde::Serialize;

/// What happened to a node in a run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Status {
    /// Evaluated.
    Ran,
    /// Taken from the memory or disk cache.
    Cached,
    /// Evaluated, and it passed its input through (see the reason).
    Passthrough,
    /// Not evaluated: no requested output needs it (or a cached result downstream covers it).
    NotNeeded,
}

impl Status {
    /// The status's snake_case name, as serialized.
    pub fn as_str(self) -> &'static str {
        match self {
            Status::Ran => "ran",
            Status::Cached => "cached",
            Status::Passthrough => "passthrough",
            Status::NotNeeded => "not_needed",
        }
    }
}

/// One node's line of the trace.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct NodeRecord {
    /// The node's name in the pipeline.
    pub node: String,
    /// Its kind.
    pub kind: String,
    /// What happened to it.
    pub status: Status,
    /// Why the node passed through (also kept when the result came from the cache).
    pub reason: Option<String>,
    /// What the node found (its report; kept with a cached result too).
    pub report: Option<String>,
    /// Evaluation (or cache fetch) time in milliseconds.
    pub ms: f64,
    /// Bytes of the node's outputs.
    pub bytes: usize,
    /// Backend that produced its outputs ("cpu", "wgpu"); for a cached
    /// result, the backend that produced the cached values.
    pub backend: String,
    /// The device adapter that produced them, for device backends.
    pub adapter: Option<String>,
    /// Why that backend, when it was a fallback from the preferred one.
    pub backend_note: Option<String>,
    /// Host/device traffic of the evaluation (zero when cached).
    pub transfers: Transfers,
    /// Hex cache key.
    pub key: String,
    /// Values the node derived from its inputs and the engine keeps
    /// ([`EvalCtx::derived`](crate::node::EvalCtx::derived)).
    pub derived: Vec<DerivedRecord>,
}

/// One derived value of a node in a run.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DerivedRecord {
    /// The value's name, e.g. `"relight scene"`.
    pub name: String,
    /// `Cached` when taken from the memory or disk cache, else `Ran`.
    pub status: Status,
    /// Time to build or fetch it, milliseconds.
    pub ms: f64,
    /// Its size.
    pub bytes: usize,
}

/// The whole run.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Trace {
    /// One record per node, in pipeline order.
    pub nodes: Vec<NodeRecord>,
    /// Worker threads of the engine.
    pub threads: usize,
}

impl Trace {
    /// The record of the node named `node`.
    pub fn get(&self, node: &str) -> Option<&NodeRecord> {
        self.nodes.iter().find(|r| r.node == node)
    }
    /// Names of the nodes with the given status.
    pub fn with_status(&self, status: Status) -> Vec<&str> {
        self.nodes
            .iter()
            .filter(|r| r.status == status)
            .map(|r| r.node.as_str())
            .collect()
    }
    /// Names of the nodes that were evaluated (ran or passed through).
    pub fn evaluated(&self) -> Vec<&str> {
        self.nodes
            .iter()
            .filter(|r| matches!(r.status, Status::Ran | Status::Passthrough))
            .map(|r| r.node.as_str())
            .collect()
    }
    /// A readable table.
    pub fn table(&self) -> String {
        let w_node = self
            .nodes
            .iter()
            .map(|r| r.node.len())
            .max()
            .unwrap_or(4)
            .max(4);
        let w_kind = self
            .nodes
            .iter()
            .map(|r| r.kind.len())
            .max()
            .unwrap_or(4)
            .max(4);
        let mut s = String::new();
        let _ = writeln!(
            s,
            "{:<w_node$}  {:<w_kind$}  {:<11}  {:<7}  {:>9}  {:>10}  reason",
            "node", "kind", "status", "backend", "ms", "bytes"
        );
        for r in &self.nodes {
            let _ = writeln!(
                s,
                "{:<w_node$}  {:<w_kind$}  {:<11}  {:<7}  {:>9.2}  {:>10}  {}",
                r.node,
                r.kind,
                r.status.as_str(),
                r.backend,
                r.ms,
                human_bytes(r.bytes),
                r.reason.as_deref().unwrap_or("")
            );
            if let Some(n) = &r.report {
                let _ = writeln!(s, "{:<w_node$}  {:<w_kind$}  found: {n}", "", "");
            }
            if let Some(n) = &r.backend_note {
                let _ = writeln!(s, "{:<w_node$}  {:<w_kind$}  backend: {n}", "", "");
            }
            let t = &r.transfers;
            if !t.is_empty() {
                let _ = writeln!(
                    s,
                    "{:<w_node$}  {:<w_kind$}  device: up {} ({}, {:.2} ms), already on device {}, \
                     kernels {:.2} ms, down {} ({}, {:.2} ms)",
                    "",
                    "",
                    t.uploads,
                    human_bytes(t.upload_bytes),
                    t.upload_ms,
                    t.resident_hits,
                    t.kernel_ms,
                    t.downloads,
                    human_bytes(t.download_bytes),
                    t.download_ms
                );
            }
            for d in &r.derived {
                let _ = writeln!(
                    s,
                    "{:<w_node$}  {:<w_kind$}  {:<11}  {:<7}  {:>9.2}  {:>10}  derived: {}",
                    "",
                    "",
                    d.status.as_str(),
                    "",
                    d.ms,
                    human_bytes(d.bytes),
                    d.name
                );
            }
        }
        let total: f64 = self.nodes.iter().map(|r| r.ms).sum();
        let _ = writeln!(
            s,
            "total node time {total:.2} ms on {} threads",
            self.threads
        );
        s
    }
}

/// `1.5 MiB` style.
pub fn human_bytes(b: usize) -> String {
    let b = b as f64;
    if b >= 1024.0 * 1024.0 {
        format!("{:.1} MiB", b / 1024.0 / 1024.0)
    } else if b >= 1024.0 {
        format!("{:.1} KiB", b / 1024.0)
    } else {
        format!("{b} B")
    }
}

/// The backend and device that produced a node's outputs.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
pub struct Origin {
    /// Backend name ("cpu", "wgpu").
    pub backend: String,
    /// The device's adapter (name, driver and API), for device backends.
    pub adapter: Option<String>,
    /// Why this backend and not the preferred one (e.g. a problem too
    /// large for the device), when it was a fallback.
    pub note: Option<String>,
}

/// Host-to-device and device-to-host traffic of one evaluation.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Transfers {
    /// Buffers copied to the device.
    pub uploads: usize,
    /// Bytes copied to the device.
    pub upload_bytes: usize,
    /// Time spent on uploads, milliseconds.
    pub upload_ms: f64,
    /// Inputs that were already on the device (handed over by a device node
    /// upstream), so not uploaded again.
    pub resident_hits: usize,
    /// Buffers copied back to the host.
    pub downloads: usize,
    /// Bytes copied back.
    pub download_bytes: usize,
    /// Time spent on downloads (waiting for the device included), milliseconds.
    pub download_ms: f64,
    /// Time from the kernels' submission to their completion, milliseconds.
    pub kernel_ms: f64,
}

impl Transfers {
    /// True when nothing moved.
    pub fn is_empty(&self) -> bool {
        self.uploads == 0 && self.downloads == 0 && self.resident_hits == 0
    }
}
