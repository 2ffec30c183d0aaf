//! The `Node` trait: what a stage declares (ports, parameters) and how it is
//! evaluated.
//!
//! A node's algorithm lives in a plain public function elsewhere
//! (`depthgraph-nodes`); the `Node` impl is a thin adapter that takes typed
//! inputs from [`Inputs`], calls the function and wraps the results.

use std::any::Any;
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

pub use crate::error::NodeError;
use crate::key::{Key, derived_key};
use crate::params::{NodeParams, ParamMap, ParamSpec};
use crate::trace::{DerivedRecord, Status};
use crate::value::{
    ColorImage, Confidence, DepthMap, ExposureStack, Extension, Intrinsics, LabelImage, Mask, Mesh,
    NormalMap, PointCloud, Value, ValueType, VplSet,
};

/// A declared input or output.
#[derive(Debug, Clone, PartialEq)]
pub struct PortSpec {
    /// Port name, unique among the node's inputs (or outputs).
    pub name: &'static str,
    /// Type of the values it carries.
    pub ty: ValueType,
    /// Inputs only: whether the node can run without it.
    pub optional: bool,
    /// One-line description.
    pub doc: &'static str,
}

impl PortSpec {
    /// A required input.
    pub const fn required(name: &'static str, ty: ValueType, doc: &'static str) -> Self {
        Self {
            name,
            ty,
            optional: false,
            doc,
        }
    }
    /// An optional input: the node runs without it.
    pub const fn optional(name: &'static str, ty: ValueType, doc: &'static str) -> Self {
        Self {
            name,
            ty,
            optional: true,
            doc,
        }
    }
    /// Outputs are declared with this (`optional` is meaningless for them).
    pub const fn output(name: &'static str, ty: ValueType, doc: &'static str) -> Self {
        Self::required(name, ty, doc)
    }
}

/// Everything the graph needs to know about a node kind.
#[derive(Debug, Clone)]
pub struct NodeSchema {
    /// Unique name used in pipelines, e.g. `"PullPush"`.
    pub kind: &'static str,
    /// Bumped whenever the output for the same inputs and parameters changes;
    /// part of the cache key.
    pub version: u32,
    /// One-line description (first line) and more.
    pub doc: &'static str,
    /// Declared input ports.
    pub inputs: Vec<PortSpec>,
    /// Declared output ports.
    pub outputs: Vec<PortSpec>,
    /// Declared parameters, in declaration order.
    pub params: Vec<ParamSpec>,
    /// Sinks write files: they run every time they are requested and are never cached.
    pub sink: bool,
}

impl NodeSchema {
    /// Every parameter at its default value.
    pub fn default_params(&self) -> crate::params::ParamMap {
        self.params
            .iter()
            .map(|p| (p.name.to_string(), p.default.clone()))
            .collect()
    }
    /// The input port named `name`.
    pub fn input(&self, name: &str) -> Option<&PortSpec> {
        self.inputs.iter().find(|p| p.name == name)
    }
    /// The output port named `name`.
    pub fn output(&self, name: &str) -> Option<&PortSpec> {
        self.outputs.iter().find(|p| p.name == name)
    }
    /// The parameter named `name`.
    pub fn param(&self, name: &str) -> Option<&ParamSpec> {
        self.params.iter().find(|p| p.name == name)
    }
}

/// Shared flag that asks running nodes to stop.
#[derive(Debug, Clone, Default)]
pub struct CancelToken(Arc<AtomicBool>);

impl CancelToken {
    /// A token that is not cancelled.
    pub fn new() -> Self {
        Self::default()
    }
    /// Asks every holder of a clone to stop; cannot be undone.
    pub fn cancel(&self) {
        self.0.store(true, Ordering::Relaxed);
    }
    /// True once [`cancel`](Self::cancel) was called on any clone.
    pub fn is_cancelled(&self) -> bool {
        self.0.load(Ordering::Relaxed)
    }
}

/// Receives progress reports: `(node name, fraction in [0, 1])`.
pub type ProgressFn = Arc<dyn Fn(&str, f32) + Send + Sync>;

/// Where the engine keeps values that nodes derive from their inputs: the
/// memory cache (whose budget counts them) and the disk cache.
pub trait ValueStore: Sync {
    /// The value kept under `key`, unless lookups are off (`--no-cache`).
    fn lookup(&self, key: &Key) -> Option<Value>;
    /// Keeps `value` under `key`.
    fn store(&self, key: Key, value: Value);
}

/// What [`EvalCtx::derived`] needs: the store, the node's identity and the
/// keys of its inputs; it records what it did for the trace.
pub struct Derivations<'a> {
    /// Where the values live.
    pub store: &'a dyn ValueStore,
    /// The node's kind.
    pub kind: &'a str,
    /// The node kind's version.
    pub version: u32,
    /// Key of the value on each connected input port.
    pub input_keys: &'a BTreeMap<String, Key>,
    /// What was derived, for the trace.
    pub records: Mutex<Vec<DerivedRecord>>,
}

/// What a node sees of the run besides its inputs.
pub struct EvalCtx<'a> {
    /// The node's name in the pipeline.
    pub node: &'a str,
    /// Set when the run is cancelled; see [`EvalCtx::check_cancelled`].
    pub cancel: &'a CancelToken,
    /// Where [`EvalCtx::progress()`] reports go; `None` when nobody listens.
    pub progress: Option<&'a ProgressFn>,
    /// Directory that relative output paths are resolved against.
    pub out_dir: &'a std::path::Path,
    /// Files the pipeline reads (sinks refuse to write over them).
    pub input_files: &'a [PathBuf],
    /// The engine's store of derived values; `None` outside an engine (then
    /// [`EvalCtx::derived`] builds every time).
    pub derivations: Option<&'a Derivations<'a>>,
    /// The most pixels a loader may decode from one file, checked against
    /// the file's header before anything is allocated for its pixels
    /// (`--max-pixels`; [`DEFAULT_MAX_PIXELS`] unless the run says otherwise).
    pub max_pixels: usize,
}

/// The default pixel budget of one decoded file: 2^28 pixels (256 MP, 3 GiB
/// as linear RGB f32).
pub const DEFAULT_MAX_PIXELS: usize = 1 << 28;

impl EvalCtx<'_> {
    /// A value derived from some of the node's inputs (`ports`) and its own
    /// key material (`extra`: the parameters it depends on, canonically
    /// encoded), kept by the engine under a Merkle key like any output, so
    /// a later run whose other inputs changed reuses it. This is how a
    /// node keeps per-photo work across edits of the rest (the relighting's
    /// scene part): never in a static. `build` runs on a miss.
    pub fn derived<T: Extension>(
        &self,
        name: &'static str,
        ports: &[&str],
        extra: &[u8],
        build: impl FnOnce() -> Result<T, NodeError>,
    ) -> Result<Arc<T>, NodeError> {
        let Some(d) = self.derivations else {
            return Ok(Arc::new(build()?));
        };
        let inputs: Vec<(&str, Option<Key>)> = ports
            .iter()
            .map(|p| (*p, d.input_keys.get(*p).copied()))
            .collect();
        let key = derived_key(d.kind, d.version, name, extra, &inputs);
        let t = std::time::Instant::now();
        let record = |status, bytes| {
            let rec = DerivedRecord {
                name: name.to_string(),
                status,
                ms: t.elapsed().as_secs_f64() * 1e3,
                bytes,
            };
            d.records
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .push(rec);
        };
        if let Some(Value::Extension(e)) = d.store.lookup(&key) {
            let any: Arc<dyn Any + Send + Sync> = e;
            if let Ok(v) = any.downcast::<T>() {
                record(Status::Cached, v.bytes());
                return Ok(v);
            }
        }
        let v = Arc::new(build()?);
        record(Status::Ran, v.bytes());
        d.store.store(key, Value::Extension(v.clone()));
        Ok(v)
    }

    /// Reports progress; long nodes call this now and then.
    pub fn progress(&self, fraction: f32) {
        if let Some(p) = self.progress {
            p(self.node, fraction.clamp(0.0, 1.0));
        }
    }
    /// `Err(Cancelled)` once the run was cancelled; long loops call this.
    pub fn check_cancelled(&self) -> Result<(), NodeError> {
        if self.cancel.is_cancelled() {
            Err(NodeError::Cancelled)
        } else {
            Ok(())
        }
    }
    /// Resolves an output path against the output directory and refuses
    /// paths the pipeline reads.
    pub fn output_path(&self, path: &str) -> Result<PathBuf, NodeError> {
        let p = resolve_output(self.out_dir, path);
        let canon_target = canonical_for_compare(&p);
        if self
            .input_files
            .iter()
            .any(|i| canonical_for_compare(i) == canon_target)
        {
            return Err(NodeError::WouldOverwriteInput { path: p });
        }
        Ok(p)
    }
}

/// Where a sink's output `path` goes: itself when absolute, else under
/// `out_dir`.
pub fn resolve_output(out_dir: &std::path::Path, path: &str) -> PathBuf {
    let p = PathBuf::from(path);
    if p.is_absolute() { p } else { out_dir.join(p) }
}

/// Canonical path for comparisons, also for files that do not exist yet:
/// the longest leading part that exists is canonicalised (links
/// resolved), and the rest is appended with `.` and `..` resolved by
/// name (a part that does not exist is no link, so `new/..` is where
/// `new` is). `out/../photo.png` before `out` exists is therefore
/// `photo.png`, as the write that would create `out` finds it.
pub fn canonical_for_compare(p: &std::path::Path) -> PathBuf {
    canonical_within(p, 40)
}

/// Where `path` leads: itself, or, where it is a symbolic link (a chain of
/// them, at most 40 as the kernel allows), the path the last one names,
/// whether or not that exists. Writers that keep links (the atomic writer
/// of the nodes) and the output checks follow links alike with it. A
/// longer chain (a loop) or an unreadable link is an error.
pub fn follow_links(path: &std::path::Path) -> std::io::Result<PathBuf> {
    let mut at = path.to_path_buf();
    for _ in 0..40 {
        match std::fs::symlink_metadata(&at) {
            Ok(m) if m.file_type().is_symlink() => {
                let to = std::fs::read_link(&at)?;
                at = match at.parent() {
                    Some(dir) if to.is_relative() => dir.join(to),
                    _ => to,
                };
            }
            _ => return Ok(at),
        }
    }
    Err(std::io::Error::other(
        "more than 40 symbolic links in a chain",
    ))
}

/// [`canonical_for_compare`] with at most `budget` more rounds through a
/// `..` (a link `l -> new/../l` resolves to itself: no endless recursion).
fn canonical_within(p: &std::path::Path, budget: u32) -> PathBuf {
    use std::path::Component;
    if let Ok(c) = p.canonicalize() {
        return c;
    }
    // a link to a file not made yet: where the write lands (the atomic
    // writer follows links the same way)
    let p = &follow_links(p).unwrap_or_else(|_| p.to_path_buf());
    if let Ok(c) = p.canonicalize() {
        return c;
    }
    let parts: Vec<Component> = p.components().collect();
    for k in (0..parts.len()).rev() {
        let head: PathBuf = parts[..k].iter().collect();
        let base = if head.as_os_str().is_empty() {
            std::path::Path::new(".")
        } else {
            &head
        };
        if let Ok(mut c) = base.canonicalize() {
            let mut went_up = false;
            for part in &parts[k..] {
                match part {
                    Component::ParentDir => {
                        c.pop();
                        went_up = true;
                    }
                    Component::CurDir => {}
                    other => c.push(other),
                }
            }
            // `new/../link/x`: past the `..` the path may run through
            // folders and links that exist; once more, now without `..`
            return if went_up && budget > 0 {
                canonical_within(&c, budget - 1)
            } else {
                c
            };
        }
    }
    p.to_path_buf()
}

/// Inputs of one evaluation, by port name.
#[derive(Debug, Default, Clone)]
pub struct Inputs {
    values: BTreeMap<String, Value>,
}

macro_rules! typed_getter {
    ($(($get:ident, $opt:ident, $variant:ident, $t:ty)),* $(,)?) => {$(
        #[doc = concat!("The required `", stringify!($variant), "` input `port`.")]
        pub fn $get(&self, port: &str) -> Result<&Arc<$t>, NodeError> {
            match self.values.get(port) {
                Some(Value::$variant(v)) => Ok(v),
                Some(other) => Err(NodeError::input(port, format!("expected {}, found {}", ValueType::$variant, other.value_type()))),
                None => Err(NodeError::input(port, "not connected")),
            }
        }
        #[doc = concat!("The optional `", stringify!($variant), "` input `port`.")]
        pub fn $opt(&self, port: &str) -> Result<Option<&Arc<$t>>, NodeError> {
            match self.values.get(port) {
                None => Ok(None),
                Some(_) => self.$get(port).map(Some),
            }
        }
    )*};
}

impl Inputs {
    /// No inputs.
    pub fn new() -> Self {
        Self::default()
    }
    /// Sets the value on input `port`, replacing any.
    pub fn insert(&mut self, port: impl Into<String>, v: Value) {
        self.values.insert(port.into(), v);
    }
    /// The value on input `port`, whatever its type.
    pub fn get(&self, port: &str) -> Option<&Value> {
        self.values.get(port)
    }
    typed_getter!(
        (color, color_opt, Color, ColorImage),
        (depth, depth_opt, Depth, DepthMap),
        (mask, mask_opt, Mask, Mask),
        (confidence, confidence_opt, Confidence, Confidence),
        (normals, normals_opt, Normals, NormalMap),
        (labels, labels_opt, Labels, LabelImage),
        (point_cloud, point_cloud_opt, PointCloud, PointCloud),
        (mesh, mesh_opt, Mesh, Mesh),
        (exposures, exposures_opt, ExposureStack, ExposureStack),
        (vpls, vpls_opt, Vpls, VplSet),
    );
    /// The required `Intrinsics` input `port`.
    pub fn intrinsics(&self, port: &str) -> Result<Intrinsics, NodeError> {
        match self.values.get(port) {
            Some(Value::Intrinsics(k)) => Ok(*k),
            Some(other) => Err(NodeError::input(
                port,
                format!("expected Intrinsics, found {}", other.value_type()),
            )),
            None => Err(NodeError::input(port, "not connected")),
        }
    }
    /// The optional `Intrinsics` input `port`.
    pub fn intrinsics_opt(&self, port: &str) -> Result<Option<Intrinsics>, NodeError> {
        match self.values.get(port) {
            None => Ok(None),
            Some(_) => self.intrinsics(port).map(Some),
        }
    }
    /// The required `Scalar` input `port`.
    pub fn scalar(&self, port: &str) -> Result<f64, NodeError> {
        match self.values.get(port) {
            Some(Value::Scalar(x)) => Ok(*x),
            Some(other) => Err(NodeError::input(
                port,
                format!("expected Scalar, found {}", other.value_type()),
            )),
            None => Err(NodeError::input(port, "not connected")),
        }
    }
    /// The required extension input `port`, downcast to `T`.
    pub fn extension<T: Extension>(&self, port: &str) -> Result<&T, NodeError> {
        match self.values.get(port) {
            Some(Value::Extension(e)) => e.as_any().downcast_ref::<T>().ok_or_else(|| {
                NodeError::input(
                    port,
                    format!("expected another kind than {}", e.type_name()),
                )
            }),
            Some(other) => Err(NodeError::input(
                port,
                format!("expected an extension value, found {}", other.value_type()),
            )),
            None => Err(NodeError::input(port, "not connected")),
        }
    }
}

pub use crate::trace::{Origin, Transfers};

/// What an evaluation returns.
#[derive(Debug, Clone, Default)]
pub struct Outputs {
    /// Output values by port name.
    pub values: BTreeMap<String, Value>,
    /// Set when the node passed its input through unchanged, with the reason
    /// (e.g. "no holes to fill"); `explain` shows it.
    pub passthrough: Option<String>,
    /// What the node found, in one line (e.g. the light `EstimateLighting`
    /// estimated); `explain` shows it and the disk cache keeps it.
    pub report: Option<String>,
    /// Which backend and device produced the values; the scheduler fills
    /// it in after evaluation and the disk cache keeps it, so `explain`
    /// names the producer of a cached result too.
    pub origin: Option<Origin>,
    /// Host/device traffic of the evaluation (zero on the CPU and for
    /// results read from the cache).
    pub transfers: Transfers,
}

impl Outputs {
    /// No outputs and no pass-through.
    pub fn new() -> Self {
        Self::default()
    }
    /// Adds an output (builder style).
    pub fn with(mut self, port: &str, v: impl Into<Value>) -> Self {
        self.values.insert(port.to_string(), v.into());
        self
    }
    /// Marks the result as a pass-through with a reason.
    pub fn passthrough(mut self, reason: impl Into<String>) -> Self {
        self.passthrough = Some(reason.into());
        self
    }
    /// Total bytes held by the values.
    pub fn bytes(&self) -> usize {
        self.values.values().map(Value::bytes).sum()
    }
}

/// A node kind. Implementations are stateless; one instance serves every
/// occurrence of the kind in every pipeline.
///
/// Room for a second backend: a GPU implementation of a kind is another
/// `Node` with the **same schema** (kind, version, ports, parameters), so the
/// cache key is identical; the registry chooses between them at run time
/// (see [`Registry::register_backend`](crate::registry::Registry::register_backend)).
pub trait Node: Send + Sync {
    /// The kind's schema: name, version, ports and parameters.
    fn schema(&self) -> &NodeSchema;
    /// Evaluates the node. `params` have been checked against the schema.
    fn eval(&self, ctx: &EvalCtx, inputs: &Inputs, params: &ParamMap)
    -> Result<Outputs, NodeError>;
    /// Input files this node reads with the given parameters (sinks never
    /// overwrite them).
    fn input_files(&self, params: &ParamMap) -> Vec<PathBuf> {
        let _ = params;
        Vec::new()
    }
    /// Files no sink of the pipeline may write over: those the node reads
    /// and those that say what it reads (a sequence's index), which its
    /// cache key leaves out. The files it reads, unless it says more.
    fn guarded_files(&self, params: &ParamMap) -> Vec<PathBuf> {
        self.input_files(params)
    }
    /// Name of the backend ("cpu", "wgpu"), shown by `explain`.
    fn backend(&self) -> &'static str {
        "cpu"
    }
    /// The device this implementation runs on (adapter name, driver and
    /// API), for device backends; `explain` shows it.
    fn adapter(&self) -> Option<String> {
        None
    }
}

/// Helper to build a typed parameter struct from a checked map.
pub fn typed_params<P: NodeParams>(params: &ParamMap) -> Result<P, NodeError> {
    P::from_values(params).map_err(NodeError::Invalid)
}

/// The files a node with the file list `files` reads under `params`
/// (none when it declares none or the parameters do not convert).
pub(crate) fn files_read<P: NodeParams>(
    files: Option<fn(&P) -> Vec<PathBuf>>,
    params: &ParamMap,
) -> Vec<PathBuf> {
    match (files, P::from_values(params)) {
        (Some(f), Ok(p)) => f(&p),
        _ => Vec::new(),
    }
}

/// Evaluation function of a [`TypedNode`].
pub type TypedEval<P> = fn(&EvalCtx, &Inputs, &P) -> Result<Outputs, NodeError>;

/// A node made of a schema and a function taking the typed parameter struct:
/// the usual way to write one (the adapter stays a few lines).
pub struct TypedNode<P: NodeParams> {
    schema: NodeSchema,
    eval: TypedEval<P>,
    files: Option<fn(&P) -> Vec<PathBuf>>,
    backend: &'static str,
}

impl<P: NodeParams> TypedNode<P> {
    /// `doc`'s first line is the summary `depthgraph nodes` prints.
    pub fn new(
        kind: &'static str,
        version: u32,
        doc: &'static str,
        inputs: Vec<PortSpec>,
        outputs: Vec<PortSpec>,
        eval: TypedEval<P>,
    ) -> Self {
        Self {
            schema: NodeSchema {
                kind,
                version,
                doc,
                inputs,
                outputs,
                params: P::specs(),
                sink: false,
            },
            eval,
            files: None,
            backend: "cpu",
        }
    }
    /// Marks the node as a sink (writes files, never cached).
    pub fn sink(mut self) -> Self {
        self.schema.sink = true;
        self
    }
    /// Declares which files the node reads.
    pub fn reads(mut self, files: fn(&P) -> Vec<PathBuf>) -> Self {
        self.files = Some(files);
        self
    }
    /// Names the backend (default "cpu").
    pub fn backend_name(mut self, name: &'static str) -> Self {
        self.backend = name;
        self
    }
}

impl<P: NodeParams> Node for TypedNode<P> {
    fn schema(&self) -> &NodeSchema {
        &self.schema
    }
    fn eval(
        &self,
        ctx: &EvalCtx,
        inputs: &Inputs,
        params: &ParamMap,
    ) -> Result<Outputs, NodeError> {
        let p: P = typed_params(params)?;
        ctx.check_cancelled()?;
        (self.eval)(ctx, inputs, &p)
    }
    fn input_files(&self, params: &ParamMap) -> Vec<PathBuf> {
        files_read(self.files, params)
    }
    fn backend(&self) -> &'static str {
        self.backend
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paths_through_folders_not_made_yet_compare_where_the_write_lands() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().canonicalize().unwrap();
        let photo = root.join("photo.png");
        std::fs::write(&photo, b"x").unwrap();
        let out = root.join("out"); // not created
        for written in ["../photo.png", "new/../../photo.png", "./.././photo.png"] {
            let p = resolve_output(&out, written);
            assert_eq!(canonical_for_compare(&p), photo, "{written}");
        }
        // a file that does not exist, under folders that do not either
        let p = resolve_output(&out, "a/b/../c.exr");
        assert_eq!(canonical_for_compare(&p), root.join("out/a/c.exr"));
        // the node refuses to write over the input
        let cancel = CancelToken::new();
        let inputs = [photo.clone()];
        let ctx = EvalCtx {
            node: "save",
            cancel: &cancel,
            progress: None,
            out_dir: &out,
            input_files: &inputs,
            derivations: None,
            max_pixels: DEFAULT_MAX_PIXELS,
        };
        let e = ctx.output_path("../photo.png").unwrap_err();
        assert!(matches!(e, NodeError::WouldOverwriteInput { .. }), "{e}");
        assert!(ctx.output_path("../other.png").is_ok());
        #[cfg(unix)]
        {
            use std::os::unix::fs::symlink;
            // a link to a file not made yet compares as its target
            symlink("made.png", root.join("dangling.png")).unwrap();
            assert_eq!(
                canonical_for_compare(&root.join("dangling.png")),
                root.join("made.png")
            );
            // a link whose target runs through a folder not made yet
            symlink("new/../photo.png", root.join("via_new.png")).unwrap();
            assert_eq!(canonical_for_compare(&root.join("via_new.png")), photo);
            // past `..`, an existing link to a folder is followed
            std::fs::create_dir(root.join("real")).unwrap();
            symlink(root.join("real"), root.join("linkdir")).unwrap();
            assert_eq!(
                canonical_for_compare(&root.join("new/../linkdir/x.png")),
                root.join("real/x.png")
            );
            // a link that leads back to itself through a folder not made
            // yet ends (it recursed until the stack overflowed)
            symlink("new/../selfish.png", root.join("selfish.png")).unwrap();
            assert_eq!(
                canonical_for_compare(&root.join("selfish.png")),
                root.join("selfish.png")
            );
        }
    }
}
