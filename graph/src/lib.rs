//! # depthgraph-graph
//!
//! The dataflow core of depthgraph, with no image algorithm in it:
//!
//! - [`value`]: the typed values on wires (color, depth, masks, intrinsics,
//!   point clouds, meshes, exposure stacks) and their conventions;
//! - [`params`]: parameter schemas and the [`node_params!`] macro;
//! - [`node`]: the [`Node`](node::Node) trait, ports, evaluation context;
//! - [`registry`]: node kinds by name, with backends;
//! - [`document`] and [`ron_text`]: the RON pipeline format with positions;
//! - [`pipeline`]: checking a document into a runnable [`Pipeline`](pipeline::Pipeline);
//! - [`ports`](mod@crate::ports): input and output ports declared once, as struct fields ([`ports!`]);
//! - [`bytes`]: the checked little-endian byte writer and reader of the caches;
//! - [`key`], [`cache`], [`codec`], [`scheduler`], [`trace`]: Merkle keys,
//!   memory and disk caches, the demand-driven parallel scheduler and its
//!   record of what ran.
//!
//! ```
//! use depthgraph_graph::prelude::*;
//! use depthgraph_graph::node_params;
//!
//! node_params! {
//!     /// Parameters of `Constant`.
//!     pub struct ConstParams {
//!         /// The value.
//!         pub value: f64 = 1.0, ParamKind::Float { min: -10.0, max: 10.0 };
//!     }
//! }
//! fn constant(_: &EvalCtx, _: &Inputs, p: &ConstParams) -> Result<Outputs, NodeError> {
//!     Ok(Outputs::new().with("out", p.value))
//! }
//! let mut reg = Registry::new();
//! reg.register(TypedNode::new("Constant", 1, "A number.", vec![],
//!     vec![PortSpec::output("out", ValueType::Scalar, "the value")], constant)).unwrap();
//! let doc = Document::parse(r#"(version: 1, nodes: {"c": (kind: "Constant", params: (value: 2.5))}, outputs: ["c.out"])"#, "inline").unwrap();
//! let pipeline = Pipeline::check(&doc, &reg).unwrap();
//! let engine = Engine::new(EngineOptions::default()).unwrap();
//! let result = engine.run(&pipeline, &RunOptions::default()).unwrap();
//! assert_eq!(result.outputs["c.out"], Value::Scalar(2.5));
//! ```

// Check errors carry their location and suggestions by value: they are built
// on the cold path, reported in bulk, and boxing them would only add noise.
#![allow(clippy::result_large_err)]
#![warn(missing_docs)]

pub mod bytes;
pub mod cache;
pub mod codec;
pub mod document;
pub mod error;
pub mod frames;
pub mod key;
pub mod node;
pub mod params;
pub mod pipeline;
pub mod ports;
pub mod registry;
pub mod ron_text;
pub mod scheduler;
pub mod trace;
pub mod value;

/// The names most users need.
pub mod prelude {
    pub use crate::cache::{DiskCache, MemoryCache};
    pub use crate::document::Document;
    pub use crate::error::{CheckError, CheckErrors, FailureKind, NodeError, RunError};
    pub use crate::node::{
        CancelToken, EvalCtx, Inputs, Node, NodeSchema, Outputs, PortSpec, TypedNode,
    };
    pub use crate::params::{NodeParams, ParamKind, ParamMap, ParamValue};
    pub use crate::pipeline::Pipeline;
    pub use crate::ports::{NoInputs, PortedNode, Produced};
    pub use crate::registry::Registry;
    pub use crate::scheduler::{Engine, EngineOptions, RunOptions, RunResult};
    pub use crate::trace::{Status, Trace};
    pub use crate::value::{
        ColorImage, Confidence, DepthMap, ExposureStack, Image, Intrinsics, LabelImage, Mask, Mesh,
        NormalMap, PointCloud, Value, ValueType, Vpl, VplSet,
    };
}
