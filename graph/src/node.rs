//! The `Node` trait: what a stage declares (ports, parameters) and how it is
//! evaluated.
//!
//! A node's algorithm lives in a plain public function elsewhere
//! (`depthgraph-nodes`); the `Node` impl is a thin adapter that takes typed
//! inputs from [`Inputs`], calls the function and wraps the results.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use crate::params::{NodeParams, ParamMap, ParamSpec};
use crate::value::{
    ColorImage, Confidence, DepthMap, ExposureStack, Intrinsics, LabelImage, Mask, Mesh, NormalMap,
    PointCloud, Value, ValueType,
};

/// A declared input or output.
#[derive(Debug, Clone, PartialEq)]
pub struct PortSpec {
    pub name: &'static str,
    pub ty: ValueType,
    /// Inputs only: whether the node can run without it.
    pub optional: bool,
    pub doc: &'static str,
}

impl PortSpec {
    pub const fn required(name: &'static str, ty: ValueType, doc: &'static str) -> Self {
        Self {
            name,
            ty,
            optional: false,
            doc,
        }
    }
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
    pub inputs: Vec<PortSpec>,
    pub outputs: Vec<PortSpec>,
    pub params: Vec<ParamSpec>,
    /// Sinks write files: they run every time they are requested and are never cached.
    pub sink: bool,
}

impl NodeSchema {
    pub fn input(&self, name: &str) -> Option<&PortSpec> {
        self.inputs.iter().find(|p| p.name == name)
    }
    pub fn output(&self, name: &str) -> Option<&PortSpec> {
        self.outputs.iter().find(|p| p.name == name)
    }
    pub fn param(&self, name: &str) -> Option<&ParamSpec> {
        self.params.iter().find(|p| p.name == name)
    }
}

/// Errors a node reports. The scheduler adds the node's name and kind.
#[derive(Debug, thiserror::Error)]
pub enum NodeError {
    #[error("input `{port}`: {message}")]
    Input { port: String, message: String },
    #[error("parameter `{param}`: {message}")]
    Param { param: String, message: String },
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: cannot decode: {message}")]
    Decode { path: PathBuf, message: String },
    #[error("{path}: {message}")]
    Encode { path: PathBuf, message: String },
    #[error("{path}: refusing to write over a file this pipeline reads")]
    WouldOverwriteInput { path: PathBuf },
    #[error("{0}")]
    Invalid(String),
    #[error("cancelled")]
    Cancelled,
}

impl NodeError {
    pub fn input(port: &str, message: impl Into<String>) -> Self {
        NodeError::Input {
            port: port.to_string(),
            message: message.into(),
        }
    }
    pub fn param(param: &str, message: impl Into<String>) -> Self {
        NodeError::Param {
            param: param.to_string(),
            message: message.into(),
        }
    }
}

/// Shared flag that asks running nodes to stop.
#[derive(Debug, Clone, Default)]
pub struct CancelToken(Arc<AtomicBool>);

impl CancelToken {
    pub fn new() -> Self {
        Self::default()
    }
    pub fn cancel(&self) {
        self.0.store(true, Ordering::Relaxed);
    }
    pub fn is_cancelled(&self) -> bool {
        self.0.load(Ordering::Relaxed)
    }
}

/// Receives progress reports: `(node name, fraction in [0, 1])`.
pub type ProgressFn = Arc<dyn Fn(&str, f32) + Send + Sync>;

/// What a node sees of the run besides its inputs.
pub struct EvalCtx<'a> {
    /// The node's name in the pipeline.
    pub node: &'a str,
    pub cancel: &'a CancelToken,
    pub progress: Option<&'a ProgressFn>,
    /// Directory that relative output paths are resolved against.
    pub out_dir: &'a std::path::Path,
    /// Files the pipeline reads (sinks refuse to write over them).
    pub input_files: &'a [PathBuf],
}

impl EvalCtx<'_> {
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
        let p = PathBuf::from(path);
        let p = if p.is_absolute() {
            p
        } else {
            self.out_dir.join(p)
        };
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

/// Canonical path for comparisons, also for files that do not exist yet
/// (their parent directory is canonicalised).
pub fn canonical_for_compare(p: &std::path::Path) -> PathBuf {
    if let Ok(c) = p.canonicalize() {
        return c;
    }
    match (p.parent(), p.file_name()) {
        (Some(parent), Some(name)) => {
            let parent = if parent.as_os_str().is_empty() {
                std::path::Path::new(".")
            } else {
                parent
            };
            parent
                .canonicalize()
                .map(|c| c.join(name))
                .unwrap_or_else(|_| p.to_path_buf())
        }
        _ => p.to_path_buf(),
    }
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
    pub fn new() -> Self {
        Self::default()
    }
    pub fn insert(&mut self, port: impl Into<String>, v: Value) {
        self.values.insert(port.into(), v);
    }
    pub fn get(&self, port: &str) -> Option<&Value> {
        self.values.get(port)
    }
    typed_getter!(
        (color, color_opt, Color, ColorImage),
        (depth, depth_opt, Depth, DepthMap),
        (normals, normals_opt, Normals, NormalMap),
        (labels, labels_opt, Labels, LabelImage),
        (point_cloud, point_cloud_opt, PointCloud, PointCloud),
        (mesh, mesh_opt, Mesh, Mesh),
        (exposures, exposures_opt, ExposureStack, ExposureStack),
    );
    /// A Mask or Confidence input (they share a representation).
    pub fn mask(&self, port: &str) -> Result<&Arc<Mask>, NodeError> {
        match self.values.get(port) {
            Some(Value::Mask(v)) | Some(Value::Confidence(v)) => Ok(v),
            Some(other) => Err(NodeError::input(
                port,
                format!("expected Mask, found {}", other.value_type()),
            )),
            None => Err(NodeError::input(port, "not connected")),
        }
    }
    pub fn mask_opt(&self, port: &str) -> Result<Option<&Arc<Confidence>>, NodeError> {
        match self.values.get(port) {
            None => Ok(None),
            Some(_) => self.mask(port).map(Some),
        }
    }
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
    pub fn intrinsics_opt(&self, port: &str) -> Result<Option<Intrinsics>, NodeError> {
        match self.values.get(port) {
            None => Ok(None),
            Some(_) => self.intrinsics(port).map(Some),
        }
    }
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
}

/// What an evaluation returns.
#[derive(Debug, Clone, Default)]
pub struct Outputs {
    pub values: BTreeMap<String, Value>,
    /// Set when the node passed its input through unchanged, with the reason
    /// (e.g. "no holes to fill"); `explain` shows it.
    pub passthrough: Option<String>,
}

impl Outputs {
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

impl From<DepthMap> for Value {
    fn from(v: DepthMap) -> Value {
        Value::Depth(Arc::new(v))
    }
}
impl From<Intrinsics> for Value {
    fn from(v: Intrinsics) -> Value {
        Value::Intrinsics(v)
    }
}
impl From<f64> for Value {
    fn from(v: f64) -> Value {
        Value::Scalar(v)
    }
}
impl From<PathBuf> for Value {
    fn from(v: PathBuf) -> Value {
        Value::File(v)
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
    /// Name of the backend ("cpu", "wgpu"), shown by `explain`.
    fn backend(&self) -> &'static str {
        "cpu"
    }
}

/// Helper to build a typed parameter struct from a checked map.
pub fn typed_params<P: NodeParams>(params: &ParamMap) -> Result<P, NodeError> {
    P::from_values(params).map_err(NodeError::Invalid)
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
        match (self.files, P::from_values(params)) {
            (Some(f), Ok(p)) => f(&p),
            _ => Vec::new(),
        }
    }
    fn backend(&self) -> &'static str {
        self.backend
    }
}
