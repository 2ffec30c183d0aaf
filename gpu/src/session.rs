//! One node's evaluation on the device: uploads (or finds already resident)
//! its inputs, runs its kernels, downloads its outputs, and counts every
//! byte and millisecond of it for the trace.

use std::any::Any;
use std::sync::Arc;
use std::time::Instant;

use depthgraph_graph::node::Transfers;
use depthgraph_graph::prelude::*;

use crate::context::{GpuContext, GpuError, Layout, PooledBuffer};

/// Storage buffers a kernel reads and writes, and that can be copied.
pub const STORAGE: wgpu::BufferUsages = wgpu::BufferUsages::STORAGE
    .union(wgpu::BufferUsages::COPY_DST)
    .union(wgpu::BufferUsages::COPY_SRC);

/// Uniform buffers.
pub const UNIFORM: wgpu::BufferUsages =
    wgpu::BufferUsages::UNIFORM.union(wgpu::BufferUsages::COPY_DST);

/// Host-readable staging buffers.
const READBACK: wgpu::BufferUsages =
    wgpu::BufferUsages::MAP_READ.union(wgpu::BufferUsages::COPY_DST);

/// The work of one device node evaluation.
pub struct Session<'a> {
    ctx: &'a GpuContext,
    /// What moved, for the trace.
    pub stats: Transfers,
    /// Output buffers to remember as resident once the output values exist.
    kept: Vec<(String, Arc<PooledBuffer>, u64)>,
    /// Set when the device cannot run the node (a buffer larger than it
    /// binds, out of device memory, a driver failure, the device lost):
    /// the node then runs on the CPU instead.
    pub(crate) cpu_fallback: bool,
    /// The error scopes (out of memory, internal, then validation) that
    /// capture everything this session does on its thread between two
    /// submissions, so a device error is this node's and no other's.
    scopes: Vec<(wgpu::ErrorFilter, wgpu::ErrorScopeGuard)>,
}

/// The shared pointer behind an image value, for residency.
pub(crate) fn value_arc(v: &Value) -> Option<Arc<dyn Any + Send + Sync>> {
    Some(match v {
        Value::Color(a) => a.clone(),
        Value::Depth(a) => a.clone(),
        Value::Mask(a) => a.clone(),
        Value::Confidence(a) => a.clone(),
        _ => return None,
    })
}

impl<'a> Session<'a> {
    /// A session on `ctx`.
    pub fn new(ctx: &'a GpuContext) -> Self {
        let mut s = Self {
            ctx,
            stats: Transfers::default(),
            kept: Vec::new(),
            cpu_fallback: false,
            scopes: Vec::new(),
        };
        s.open_scopes();
        s
    }

    fn open_scopes(&mut self) {
        let d = self.ctx.device();
        // (called with no scope open: at creation and after close_scopes)
        for f in [
            wgpu::ErrorFilter::OutOfMemory,
            wgpu::ErrorFilter::Internal,
            wgpu::ErrorFilter::Validation,
        ] {
            self.scopes.push((f, d.push_error_scope(f)));
        }
    }

    /// Pops the scopes (innermost first) and reopens them: the first error
    /// they caught since they were opened, if any. Running out of device
    /// memory and a driver's internal error send the node to the CPU
    /// ([`Session::cpu_fallback`]: the CPU computes what the device could
    /// not); a validation error is this program's and is reported.
    fn close_scopes(&mut self) -> Option<NodeError> {
        let mut first = None;
        while let Some((filter, scope)) = self.scopes.pop() {
            if let Some(e) = pollster::block_on(scope.pop()) {
                let msg = match filter {
                    wgpu::ErrorFilter::OutOfMemory => format!("out of device memory: {e}"),
                    wgpu::ErrorFilter::Internal => format!("the driver failed: {e}"),
                    wgpu::ErrorFilter::Validation => e.to_string(),
                };
                self.cpu_fallback |= filter != wgpu::ErrorFilter::Validation;
                first.get_or_insert_with(|| self.fail(self.ctx.error(msg)));
            }
        }
        self.open_scopes();
        first
    }

    /// The context.
    pub fn ctx(&self) -> &'a GpuContext {
        self.ctx
    }

    /// The compiled pipeline of `k` (compiled on first use, then cached by
    /// the context).
    pub fn kernel(
        &mut self,
        k: &crate::shaders::Kernel,
    ) -> Result<Arc<wgpu::ComputePipeline>, NodeError> {
        self.ctx
            .pipeline(k.name, &k.source(), k.entry)
            .map_err(|e| self.compile_failed(e))
    }

    /// A device error as a node error.
    pub fn fail(&self, e: GpuError) -> NodeError {
        let (adapter, message) = match e {
            GpuError::Device { adapter, message } | GpuError::Unavailable { adapter, message } => {
                (adapter, message)
            }
            GpuError::TooLarge {
                adapter,
                needed_mib,
                allowed_mib,
            } => (
                adapter,
                format!(
                    "needs a {needed_mib:.1} MiB buffer, the device binds at most {allowed_mib:.1} MiB"
                ),
            ),
            other => (self.ctx.adapter().label(), other.to_string()),
        };
        NodeError::Device { adapter, message }
    }

    /// The pixels of an image input on the device: the buffer a device node
    /// upstream left (no upload), else a fresh upload of `bytes`.
    pub fn image<T: Send + Sync + 'static>(
        &mut self,
        value: &Arc<T>,
        bytes: &[u8],
    ) -> Result<Arc<PooledBuffer>, NodeError> {
        let any: Arc<dyn Any + Send + Sync> = value.clone();
        if let Some(b) = self.ctx.resident(&any) {
            self.stats.resident_hits += 1;
            return Ok(b);
        }
        // Kept too: the next device node that reads the same value (the
        // guide image of a chain, say) finds it there. Kernels never write
        // their inputs, so the copy stays equal to the value.
        let b = Arc::new(self.upload(bytes)?);
        self.ctx.keep_resident(&any, b.clone(), bytes.len() as u64);
        Ok(b)
    }

    /// Checks that a `w` x `h` grid of `tile` x `tile` workgroups fits the
    /// device's dispatch limit; a larger one marks the session too large
    /// (the node then runs on the CPU).
    pub fn check_grid(&mut self, w: usize, h: usize, tile: usize) -> Result<(), NodeError> {
        let max = self.ctx.limits().max_compute_workgroups_per_dimension as usize;
        if w.div_ceil(tile) > max || h.div_ceil(tile) > max {
            self.cpu_fallback = true;
            return Err(self.fail(self.ctx.error(format!(
                "a {w}x{h} image needs more than {max} workgroups along one side"
            ))));
        }
        Ok(())
    }

    /// Marks the problem as one the device should not run (the node then
    /// runs on the CPU), with the reason.
    pub fn too_large(&mut self, why: &str) -> NodeError {
        self.cpu_fallback = true;
        self.fail(self.ctx.error(why))
    }

    /// A buffer from the context; a too large one marks the session.
    fn alloc(&mut self, size: u64, usage: wgpu::BufferUsages) -> Result<PooledBuffer, NodeError> {
        match self.ctx.buffer(size, usage) {
            Ok(b) => Ok(b),
            Err(e) => {
                self.cpu_fallback |= matches!(e, GpuError::TooLarge { .. });
                Err(self.fail(e))
            }
        }
    }

    /// Copies `bytes` into a new storage buffer.
    pub fn upload(&mut self, bytes: &[u8]) -> Result<PooledBuffer, NodeError> {
        let t = Instant::now();
        let b = self.alloc(bytes.len().max(4) as u64, STORAGE)?;
        if !bytes.is_empty() {
            self.write(&b, bytes);
        }
        self.stats.uploads += 1;
        self.stats.upload_bytes += bytes.len();
        self.stats.upload_ms += t.elapsed().as_secs_f64() * 1e3;
        Ok(b)
    }

    /// A uniform buffer holding `bytes` (parameter blocks; not counted as
    /// image traffic).
    pub fn uniform(&mut self, bytes: &[u8]) -> Result<PooledBuffer, NodeError> {
        let b = self.alloc(bytes.len().max(16) as u64, UNIFORM)?;
        self.write(&b, bytes);
        Ok(b)
    }

    /// The pipeline of `k` in the explicit layout `binds` (cached per
    /// kernel file under `layout_name`).
    pub fn kernel_in(
        &mut self,
        layout_name: &'static str,
        binds: &[Bind],
        k: &crate::shaders::Kernel,
    ) -> Result<(Arc<wgpu::ComputePipeline>, Arc<Layout>), NodeError> {
        let layout = self.ctx.layout(layout_name, &layout_entries(binds));
        let p = self
            .ctx
            .pipeline_in(k.name, &k.source(), k.entry, Some(&layout.1))
            .map_err(|e| self.compile_failed(e))?;
        Ok((p, layout))
    }

    /// A pipeline that did not compile as a node error; out of memory or a
    /// driver failure sends the node to the CPU.
    fn compile_failed(&mut self, e: GpuError) -> NodeError {
        self.cpu_fallback |= matches!(e, GpuError::Unavailable { .. });
        self.fail(e)
    }

    /// An uninitialised storage buffer of `size` bytes.
    pub fn scratch(&mut self, size: u64) -> Result<PooledBuffer, NodeError> {
        self.alloc(size.max(4), STORAGE)
    }

    fn write(&self, b: &wgpu::Buffer, bytes: &[u8]) {
        // write_buffer needs a multiple of 4 bytes
        if bytes.len().is_multiple_of(4) {
            self.ctx.queue().write_buffer(b, 0, bytes);
        } else {
            let mut padded = bytes.to_vec();
            padded.resize(bytes.len().next_multiple_of(4), 0);
            self.ctx.queue().write_buffer(b, 0, &padded);
        }
    }

    /// A bind group of `pipeline`'s group 0 with `buffers` at bindings 0, 1, ...
    pub fn bind(
        &self,
        pipeline: &wgpu::ComputePipeline,
        buffers: &[&wgpu::Buffer],
    ) -> wgpu::BindGroup {
        let at: Vec<(u32, &wgpu::Buffer)> = buffers
            .iter()
            .enumerate()
            .map(|(i, b)| (i as u32, *b))
            .collect();
        self.bind_at(pipeline, &at)
    }

    /// A bind group of `pipeline`'s group 0 with each buffer at its binding
    /// (an entry point's derived layout holds only the bindings it uses).
    pub fn bind_at(
        &self,
        pipeline: &wgpu::ComputePipeline,
        buffers: &[(u32, &wgpu::Buffer)],
    ) -> wgpu::BindGroup {
        let layout = pipeline.get_bind_group_layout(0);
        let entries: Vec<wgpu::BindGroupEntry> = buffers
            .iter()
            .map(|(i, b)| wgpu::BindGroupEntry {
                binding: *i,
                resource: b.as_entire_binding(),
            })
            .collect();
        self.ctx
            .device()
            .create_bind_group(&wgpu::BindGroupDescriptor {
                label: None,
                layout: &layout,
                entries: &entries,
            })
    }

    /// A command encoder holding one compute pass that runs `steps` in
    /// order, each kernel over a `w` x `h` grid of 8 x 8 workgroups.
    pub fn image_passes(
        &self,
        steps: &[(&wgpu::ComputePipeline, &wgpu::BindGroup)],
        (w, h): (usize, usize),
    ) -> wgpu::CommandEncoder {
        let mut encoder = self.encoder();
        {
            let mut pass = encoder.begin_compute_pass(&Default::default());
            let groups = ((w as u32).div_ceil(8), (h as u32).div_ceil(8));
            for (pipeline, bind_group) in steps {
                pass.set_pipeline(pipeline);
                pass.set_bind_group(0, *bind_group, &[]);
                pass.dispatch_workgroups(groups.0, groups.1, 1);
            }
        }
        encoder
    }

    /// A new command encoder.
    pub fn encoder(&self) -> wgpu::CommandEncoder {
        self.ctx
            .device()
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None })
    }

    /// Submits `encoder`, waits for it, and reads back `reads` (buffer and
    /// byte count each). Kernel time and download bytes go to the stats.
    pub fn finish(
        &mut self,
        mut encoder: wgpu::CommandEncoder,
        reads: &[(&wgpu::Buffer, u64)],
    ) -> Result<Vec<Vec<u8>>, NodeError> {
        let ctx = self.ctx;
        let staging: Vec<PooledBuffer> = reads
            .iter()
            .map(|(src, n)| {
                let n4 = n.next_multiple_of(4).max(4);
                let s = ctx.buffer(n4, READBACK)?;
                encoder.copy_buffer_to_buffer(src, 0, &s, 0, n4);
                Ok(s)
            })
            .collect::<Result<_, GpuError>>()
            .map_err(|e| self.fail(e))?;
        let t = Instant::now();
        let index = ctx.queue().submit([encoder.finish()]);
        // Everything since the last submission (buffers, bind groups,
        // writes, this submission) is checked here.
        if let Some(e) = self.close_scopes() {
            return Err(e);
        }
        self.wait(Some(index))?;
        self.stats.kernel_ms += t.elapsed().as_secs_f64() * 1e3;
        let t = Instant::now();
        let mut out = Vec::with_capacity(reads.len());
        for (s, (_, n)) in staging.iter().zip(reads) {
            let slice = s.slice(..n.next_multiple_of(4).max(4));
            let (tx, rx) = std::sync::mpsc::channel();
            slice.map_async(wgpu::MapMode::Read, move |r| {
                let _ = tx.send(r);
            });
            self.wait(None)?;
            match rx.recv() {
                Ok(Ok(())) => {}
                Ok(Err(e)) => return Err(self.fail(ctx.error(format!("reading back: {e}")))),
                Err(_) => {
                    return Err(self.fail(ctx.error("reading back: no answer from the device")));
                }
            }
            let view = match slice.get_mapped_range() {
                Ok(v) => v,
                Err(e) => {
                    s.unmap();
                    return Err(self.fail(ctx.error(format!("reading back: {e}"))));
                }
            };
            out.push(view[..*n as usize].to_vec());
            drop(view);
            s.unmap();
            self.stats.downloads += 1;
            self.stats.download_bytes += *n as usize;
        }
        self.stats.download_ms += t.elapsed().as_secs_f64() * 1e3;
        if let Some(e) = self.close_scopes() {
            return Err(e);
        }
        Ok(out)
    }

    /// Submits `encoder` and waits, reading nothing back.
    pub fn submit(&mut self, encoder: wgpu::CommandEncoder) -> Result<(), NodeError> {
        self.finish(encoder, &[]).map(|_| ())
    }

    /// Waits for the device. A lost device (a driver reset, a hang, a
    /// destroyed device) makes wgpu panic inside `poll`, or refuse to wait
    /// for a submission that never reached it: either way the context is
    /// marked lost and the node sent to the CPU.
    fn wait(&mut self, index: Option<wgpu::SubmissionIndex>) -> Result<(), NodeError> {
        let device = self.ctx.device();
        let polled = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            device.poll(wgpu::PollType::Wait {
                submission_index: index,
                timeout: None,
            })
        }));
        match polled {
            Ok(Ok(_)) => Ok(()),
            // the submission did not reach the device though no scope
            // caught an error (checked before the wait): the device is gone
            Ok(Err(e)) => {
                let why = format!("the device was lost (waiting for it: {e})");
                self.ctx.mark_lost(why.clone());
                self.cpu_fallback = true;
                Err(self.fail(self.ctx.error(why)))
            }
            Err(panic) => {
                let why = panic
                    .downcast_ref::<String>()
                    .cloned()
                    .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
                    .unwrap_or_else(|| "wgpu panicked while waiting".into());
                self.ctx.mark_lost(why.clone());
                self.cpu_fallback = true;
                Err(self.fail(self.ctx.error(format!("the device was lost: {why}"))))
            }
        }
    }

    /// Marks `buffer` (holding `bytes` bytes) as the device copy of output
    /// `port`, so a device node downstream finds it resident.
    pub fn keep(&mut self, port: &str, buffer: Arc<PooledBuffer>, bytes: u64) {
        self.kept.push((port.to_string(), buffer, bytes));
    }

    /// Registers the kept buffers against the output values.
    pub(crate) fn register_outputs(mut self, out: &Outputs) -> Transfers {
        for (port, buffer, bytes) in std::mem::take(&mut self.kept) {
            if let Some(arc) = out.values.get(&port).and_then(value_arc) {
                self.ctx.keep_resident(&arc, buffer, bytes);
            }
        }
        self.stats
    }
}

impl Drop for Session<'_> {
    fn drop(&mut self) {
        // wgpu requires scopes to be popped innermost first (a Vec drops
        // its elements first to last).
        while let Some((_, scope)) = self.scopes.pop() {
            drop(scope);
        }
    }
}

/// `f32` bytes of a slice of `f32`s or `[f32; N]`s.
pub fn bytes_of<T: bytemuck::Pod>(v: &[T]) -> &[u8] {
    bytemuck::cast_slice(v)
}

/// `f32`s from bytes read back (a copy; the length is a multiple of 4 by
/// construction of [`Session::finish`], a trailing partial value would be
/// dropped). The device's bytes are the host's order, as [`bytes_of`]
/// uploads them: one copy of the whole buffer, whatever its alignment.
pub fn f32s(bytes: &[u8]) -> Vec<f32> {
    bytemuck::pod_collect_to_vec(&bytes[..bytes.len() / 4 * 4])
}

/// `u32`s from bytes read back (as [`f32s`]).
pub fn u32s(bytes: &[u8]) -> Vec<u32> {
    bytemuck::pod_collect_to_vec(&bytes[..bytes.len() / 4 * 4])
}

/// How a kernel binds one buffer (for an explicit layout).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Bind {
    /// A uniform block.
    Uniform,
    /// A uniform block at a per-dispatch offset (one block per level or view).
    DynamicUniform,
    /// A read-only storage buffer.
    Read,
    /// A read-write storage buffer.
    ReadWrite,
}

/// Layout entries for bindings 0, 1, ... of group 0, compute stage.
pub fn layout_entries(binds: &[Bind]) -> Vec<wgpu::BindGroupLayoutEntry> {
    binds
        .iter()
        .enumerate()
        .map(|(i, b)| {
            let (ty, dynamic) = match b {
                Bind::Uniform => (wgpu::BufferBindingType::Uniform, false),
                Bind::DynamicUniform => (wgpu::BufferBindingType::Uniform, true),
                Bind::Read => (wgpu::BufferBindingType::Storage { read_only: true }, false),
                Bind::ReadWrite => (wgpu::BufferBindingType::Storage { read_only: false }, false),
            };
            wgpu::BindGroupLayoutEntry {
                binding: i as u32,
                visibility: wgpu::ShaderStages::COMPUTE,
                ty: wgpu::BindingType::Buffer {
                    ty,
                    has_dynamic_offset: dynamic,
                    min_binding_size: None,
                },
                count: None,
            }
        })
        .collect()
}

/// A bind group entry for `buf` (its first `size` bytes, or all of it).
pub fn entry(binding: u32, buf: &wgpu::Buffer, size: Option<u64>) -> wgpu::BindGroupEntry<'_> {
    wgpu::BindGroupEntry {
        binding,
        resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
            buffer: buf,
            offset: 0,
            size: size.and_then(std::num::NonZeroU64::new),
        }),
    }
}

/// Blocks of `T` at the device's uniform offset alignment, for a
/// [`Bind::DynamicUniform`]: the bytes and the stride.
pub fn uniform_blocks<T: bytemuck::Pod>(blocks: &[T], align: u32) -> (Vec<u8>, usize) {
    let size = std::mem::size_of::<T>();
    let stride = size.next_multiple_of((align as usize).max(1));
    let mut bytes = vec![0u8; stride * blocks.len().max(1)];
    for (k, b) in blocks.iter().enumerate() {
        bytes[k * stride..k * stride + size].copy_from_slice(bytemuck::bytes_of(b));
    }
    (bytes, stride)
}

#[cfg(test)]
mod tests {
    use super::{bytes_of, f32s, u32s};

    #[test]
    fn read_back_values_round_trip_at_any_alignment() {
        let v: Vec<f32> = (0..37).map(|i| i as f32 * 0.37 - 3.0).collect();
        let mut padded = vec![0u8; 1];
        padded.extend_from_slice(bytes_of(&v));
        padded.push(0xff); // a partial value at the end is dropped
        // one byte in: the values start unaligned
        let back = f32s(&padded[1..]);
        assert_eq!(back.len(), v.len());
        assert!(back.iter().zip(&v).all(|(a, b)| a.to_bits() == b.to_bits()));
        let bits = u32s(&padded[1..padded.len() - 1]);
        assert_eq!(bits, v.iter().map(|x| x.to_bits()).collect::<Vec<_>>());
    }
}
