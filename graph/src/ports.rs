//! Ports declared once: a struct of inputs (or of outputs) whose fields are
//! the ports. [`ports!`](macro@crate::ports) generates the schema's port list
//! from the fields (name, type from the field's Rust type, optional when
//! the field is an `Option`, doc from the doc comment), the typed reading
//! of the inputs and the building of the outputs, so a node's adapter is
//! the call of its algorithm:
//!
//! ```
//! use std::sync::Arc;
//! use depthgraph_graph::prelude::*;
//! use depthgraph_graph::{node_params, ports};
//! use depthgraph_graph::ports::Produced;
//!
//! node_params! {
//!     /// Parameters of `Scale`.
//!     pub struct ScaleParams {
//!         /// Factor.
//!         pub factor: f64 = 2.0, ParamKind::Float { min: 0.0, max: 10.0 };
//!     }
//! }
//! ports! {
//!     /// Inputs of `Scale`.
//!     inputs struct ScaleIn {
//!         /// Metres.
//!         depth: Arc<DepthMap>,
//!         /// Where to scale (everywhere when absent).
//!         mask: Option<Arc<Mask>>,
//!     }
//! }
//! ports! {
//!     /// Outputs of `Scale`.
//!     outputs struct ScaleOut {
//!         /// Scaled depth.
//!         depth: DepthMap,
//!     }
//! }
//! fn scale(_: &EvalCtx, i: ScaleIn, p: &ScaleParams) -> Result<Produced<ScaleOut>, NodeError> {
//!     Ok(ScaleOut { depth: i.depth.map_same(|z| z * p.factor as f32) }.into())
//! }
//! let node = PortedNode::new("Scale", 1, "Scales depth.", scale);
//! assert_eq!(node.schema().inputs[0].ty, ValueType::Depth);
//! assert!(node.schema().inputs[1].optional);
//! assert_eq!(node.schema().outputs[0].doc, "Scaled depth.");
//! ```

use std::marker::PhantomData;
use std::path::PathBuf;
use std::sync::Arc;

use crate::error::NodeError;
use crate::node::{EvalCtx, Inputs, Node, NodeSchema, Outputs, PortSpec, files_read, typed_params};
use crate::params::{NodeParams, ParamMap};
use crate::value::{
    ColorImage, Confidence, DepthMap, ExposureStack, Intrinsics, LabelImage, Mask, Mesh, NormalMap,
    PointCloud, Value, ValueType, VplSet,
};

/// A Rust type that a port carries, and its [`ValueType`].
pub trait PortType {
    /// The port's type.
    const TYPE: ValueType;
}

/// A type an input port can be read as.
pub trait InPort: Sized {
    /// The port's type.
    const TYPE: ValueType;
    /// Whether the node runs without it.
    const OPTIONAL: bool;
    /// Reads input `port`.
    fn take(inputs: &Inputs, port: &str) -> Result<Self, NodeError>;
}

/// A type an output port can be built from.
pub trait OutPort {
    /// The port's type.
    const TYPE: ValueType;
    /// The value on the wire.
    fn into_value(self) -> Value;
}

/// A struct of input ports ([`ports!`](macro@crate::ports) with `inputs`).
pub trait InputPorts: Sized {
    /// The ports, in declaration order.
    fn specs() -> Vec<PortSpec>;
    /// Reads every port from `inputs`.
    fn take(inputs: &Inputs) -> Result<Self, NodeError>;
}

/// A struct of output ports ([`ports!`](macro@crate::ports) with `outputs`).
pub trait OutputPorts {
    /// The ports, in declaration order.
    fn specs() -> Vec<PortSpec>;
    /// The values by port name.
    fn into_outputs(self) -> Outputs;
}

/// The inputs of a node without input ports (a source).
#[derive(Debug, Clone, Copy)]
pub struct NoInputs;

impl InputPorts for NoInputs {
    fn specs() -> Vec<PortSpec> {
        Vec::new()
    }
    fn take(_: &Inputs) -> Result<Self, NodeError> {
        Ok(NoInputs)
    }
}

/// What a ported node's function returns: its outputs and, when it passed
/// its input through, the reason (`explain` shows it).
#[derive(Debug, Clone)]
pub struct Produced<O> {
    /// The outputs.
    pub out: O,
    /// Why the node passed its input through, if it did.
    pub passthrough: Option<String>,
    /// What the node found, in one line (`explain` shows it).
    pub report: Option<String>,
}

impl<O> Produced<O> {
    /// Outputs that are a pass-through of the input, with the reason.
    pub fn passthrough(out: O, reason: impl Into<String>) -> Self {
        Self {
            out,
            passthrough: Some(reason.into()),
            report: None,
        }
    }
    /// Outputs with a report of what the node found.
    pub fn reported(out: O, report: impl Into<String>) -> Self {
        Self {
            out,
            passthrough: None,
            report: Some(report.into()),
        }
    }
}

impl<O> From<O> for Produced<O> {
    fn from(out: O) -> Self {
        Self {
            out,
            passthrough: None,
            report: None,
        }
    }
}

macro_rules! port_types {
    ($($t:ty => $vt:ident, $get:ident;)*) => {$(
        impl PortType for $t {
            const TYPE: ValueType = ValueType::$vt;
        }
        impl InPort for Arc<$t> {
            const TYPE: ValueType = ValueType::$vt;
            const OPTIONAL: bool = false;
            fn take(inputs: &Inputs, port: &str) -> Result<Self, NodeError> {
                inputs.$get(port).cloned()
            }
        }
        impl OutPort for $t {
            const TYPE: ValueType = ValueType::$vt;
            fn into_value(self) -> Value {
                Value::from(self)
            }
        }
        impl OutPort for Arc<$t> {
            const TYPE: ValueType = ValueType::$vt;
            fn into_value(self) -> Value {
                Value::from(self)
            }
        }
        impl InPort for Option<Arc<$t>> {
            const TYPE: ValueType = ValueType::$vt;
            const OPTIONAL: bool = true;
            fn take(inputs: &Inputs, port: &str) -> Result<Self, NodeError> {
                match inputs.get(port) {
                    None => Ok(None),
                    Some(_) => <Arc<$t> as InPort>::take(inputs, port).map(Some),
                }
            }
        }
    )*};
}

port_types! {
    ColorImage => Color, color;
    DepthMap => Depth, depth;
    Mask => Mask, mask;
    Confidence => Confidence, confidence;
    NormalMap => Normals, normals;
    LabelImage => Labels, labels;
    PointCloud => PointCloud, point_cloud;
    Mesh => Mesh, mesh;
    ExposureStack => ExposureStack, exposures;
    VplSet => Vpls, vpls;
}

impl InPort for Intrinsics {
    const TYPE: ValueType = ValueType::Intrinsics;
    const OPTIONAL: bool = false;
    fn take(inputs: &Inputs, port: &str) -> Result<Self, NodeError> {
        inputs.intrinsics(port)
    }
}
impl InPort for Option<Intrinsics> {
    const TYPE: ValueType = ValueType::Intrinsics;
    const OPTIONAL: bool = true;
    fn take(inputs: &Inputs, port: &str) -> Result<Self, NodeError> {
        inputs.intrinsics_opt(port)
    }
}
impl OutPort for Intrinsics {
    const TYPE: ValueType = ValueType::Intrinsics;
    fn into_value(self) -> Value {
        Value::Intrinsics(self)
    }
}
impl InPort for f64 {
    const TYPE: ValueType = ValueType::Scalar;
    const OPTIONAL: bool = false;
    fn take(inputs: &Inputs, port: &str) -> Result<Self, NodeError> {
        inputs.scalar(port)
    }
}
impl OutPort for f64 {
    const TYPE: ValueType = ValueType::Scalar;
    fn into_value(self) -> Value {
        Value::Scalar(self)
    }
}
impl OutPort for PathBuf {
    const TYPE: ValueType = ValueType::File;
    fn into_value(self) -> Value {
        Value::File(self)
    }
}

/// Declares a struct of input or output ports (see the [module](mod@crate::ports)).
#[macro_export]
macro_rules! ports {
    (
        $(#[$meta:meta])*
        inputs struct $name:ident {
            $( $(#[doc = $doc:literal])+ $field:ident : $ty:ty ),* $(,)?
        }
    ) => {
        $(#[$meta])*
        #[derive(Debug, Clone)]
        pub struct $name {
            $( $(#[doc = $doc])+ pub $field: $ty, )*
        }
        impl $crate::ports::InputPorts for $name {
            fn specs() -> ::std::vec::Vec<$crate::node::PortSpec> {
                ::std::vec![ $(
                    $crate::node::PortSpec {
                        name: stringify!($field),
                        ty: <$ty as $crate::ports::InPort>::TYPE,
                        optional: <$ty as $crate::ports::InPort>::OPTIONAL,
                        doc: concat!($($doc, "\n"),+).trim_ascii(),
                    },
                )* ]
            }
            fn take(inputs: &$crate::node::Inputs) -> ::core::result::Result<Self, $crate::error::NodeError> {
                let _ = inputs;
                Ok(Self { $( $field: <$ty as $crate::ports::InPort>::take(inputs, stringify!($field))?, )* })
            }
        }
    };
    (
        $(#[$meta:meta])*
        outputs struct $name:ident {
            $( $(#[doc = $doc:literal])+ $field:ident : $ty:ty ),* $(,)?
        }
    ) => {
        $(#[$meta])*
        #[derive(Debug, Clone)]
        pub struct $name {
            $( $(#[doc = $doc])+ pub $field: $ty, )*
        }
        impl $crate::ports::OutputPorts for $name {
            fn specs() -> ::std::vec::Vec<$crate::node::PortSpec> {
                ::std::vec![ $(
                    $crate::node::PortSpec {
                        name: stringify!($field),
                        ty: <$ty as $crate::ports::OutPort>::TYPE,
                        optional: false,
                        doc: concat!($($doc, "\n"),+).trim_ascii(),
                    },
                )* ]
            }
            fn into_outputs(self) -> $crate::node::Outputs {
                let mut out = $crate::node::Outputs::new();
                $( out.values.insert(stringify!($field).to_string(), $crate::ports::OutPort::into_value(self.$field)); )*
                out
            }
        }
    };
}

/// The function of a [`PortedNode`]: typed inputs and parameters in, typed
/// outputs out.
pub type PortedEval<I, O, P> = fn(&EvalCtx, I, &P) -> Result<Produced<O>, NodeError>;

/// A node whose schema comes from its parameter struct and its input and
/// output port structs: nothing is spelled twice.
pub struct PortedNode<I, O, P: NodeParams> {
    schema: NodeSchema,
    eval: PortedEval<I, O, P>,
    files: Option<fn(&P) -> Vec<PathBuf>>,
    guards: Option<fn(&P) -> Vec<PathBuf>>,
    ports: PhantomData<fn() -> (I, O)>,
}

impl<I: InputPorts, O: OutputPorts, P: NodeParams> PortedNode<I, O, P> {
    /// `doc`'s first line is the summary `depthgraph nodes` prints.
    pub fn new(
        kind: &'static str,
        version: u32,
        doc: &'static str,
        eval: PortedEval<I, O, P>,
    ) -> Self {
        Self {
            schema: NodeSchema {
                kind,
                version,
                doc,
                inputs: I::specs(),
                outputs: O::specs(),
                params: P::specs(),
                sink: false,
            },
            eval,
            files: None,
            guards: None,
            ports: PhantomData,
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
    /// Declares files that say what the node reads (a sequence's index):
    /// no sink may write over them ([`Node::guarded_files`]), and they stay
    /// out of the cache key.
    pub fn guards(mut self, files: fn(&P) -> Vec<PathBuf>) -> Self {
        self.guards = Some(files);
        self
    }
}

impl<I: InputPorts, O: OutputPorts, P: NodeParams> Node for PortedNode<I, O, P> {
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
        let i = I::take(inputs)?;
        let r = (self.eval)(ctx, i, &p)?;
        let mut out = r.out.into_outputs();
        out.passthrough = r.passthrough;
        out.report = r.report;
        Ok(out)
    }
    fn input_files(&self, params: &ParamMap) -> Vec<PathBuf> {
        files_read(self.files, params)
    }
    fn guarded_files(&self, params: &ParamMap) -> Vec<PathBuf> {
        let mut all = files_read(self.files, params);
        all.extend(files_read(self.guards, params));
        all
    }
}
