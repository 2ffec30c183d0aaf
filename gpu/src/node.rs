//! The adapter between a device function and the graph: a [`DeviceNode`]
//! has the CPU node's schema (so the cache key is the same whichever
//! backend runs), the backend name "wgpu", and names its adapter.

use std::marker::PhantomData;
use std::path::PathBuf;
use std::sync::Arc;

use depthgraph_graph::node::{Origin, typed_params};
use depthgraph_graph::ports::{InputPorts, OutputPorts, Produced};
use depthgraph_graph::prelude::*;
use depthgraph_graph::registry::RegistryError;

use crate::context::GpuContext;
use crate::session::Session;

/// A device node's function: the session, the typed inputs and parameters.
pub type DeviceEval<I, O, P> = fn(&mut Session, &EvalCtx, I, &P) -> Result<Produced<O>, NodeError>;

/// A node kind's implementation on the device.
pub struct DeviceNode<I, O, P: NodeParams> {
    schema: NodeSchema,
    ctx: Arc<GpuContext>,
    cpu: Arc<dyn Node>,
    eval: DeviceEval<I, O, P>,
    ports: Marker<I, O, P>,
}

/// The port and parameter types of a [`DeviceNode`] (no data).
type Marker<I, O, P> = PhantomData<fn() -> (I, O, P)>;

impl<I: InputPorts, O: OutputPorts, P: NodeParams> Node for DeviceNode<I, O, P> {
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
        // The same kind on the CPU (same schema, result within the stated
        // tolerance); the trace then names the CPU as its producer.
        let on_cpu = |why: String| -> Result<Outputs, NodeError> {
            let mut out = self.cpu.eval(ctx, inputs, params)?;
            out.origin = Some(Origin {
                backend: "cpu".to_string(),
                adapter: None,
                note: Some(format!("ran on the CPU: {why}")),
            });
            Ok(out)
        };
        // a lost device runs nothing more (wgpu panics on its next wait)
        if let Some(why) = self.ctx.lost() {
            return on_cpu(format!("the device was lost earlier ({why})"));
        }
        let i = I::take(inputs)?;
        let mut session = Session::new(&self.ctx);
        let r = match (self.eval)(&mut session, ctx, i, &p) {
            Ok(r) => r,
            // a problem the device cannot run (larger than it binds, out of
            // its memory, a driver failure, the device lost)
            Err(NodeError::Device { message, .. })
                if session.cpu_fallback || self.ctx.lost().is_some() =>
            {
                drop(session);
                return on_cpu(message);
            }
            Err(e) => return Err(e),
        };
        let mut out = r.out.into_outputs();
        out.passthrough = r.passthrough;
        out.report = r.report;
        out.transfers = session.register_outputs(&out);
        out.origin = Some(Origin {
            backend: "wgpu".to_string(),
            adapter: Some(self.ctx.adapter().label()),
            note: None,
        });
        Ok(out)
    }
    fn input_files(&self, params: &ParamMap) -> Vec<PathBuf> {
        self.cpu.input_files(params)
    }
    fn guarded_files(&self, params: &ParamMap) -> Vec<PathBuf> {
        self.cpu.guarded_files(params)
    }
    fn backend(&self) -> &'static str {
        "wgpu"
    }
    fn adapter(&self) -> Option<String> {
        Some(self.ctx.adapter().label())
    }
}

/// Adds the device implementation `eval` of `kind`, whose CPU node must
/// already be in `reg` (its schema is taken, so the two cannot differ).
pub fn register_device<I, O, P>(
    reg: &mut Registry,
    ctx: &Arc<GpuContext>,
    kind: &'static str,
    eval: DeviceEval<I, O, P>,
) -> Result<(), RegistryError>
where
    I: InputPorts + 'static,
    O: OutputPorts + 'static,
    P: NodeParams + 'static,
{
    let Some(cpu) = reg.get(kind) else {
        return Err(RegistryError::Missing(kind));
    };
    let schema = cpu.schema().clone();
    reg.register_backend(DeviceNode {
        schema,
        ctx: ctx.clone(),
        cpu,
        eval,
        ports: PhantomData,
    })
}
