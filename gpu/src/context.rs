//! The device: one wgpu instance, adapter, device and queue, with the
//! compiled pipelines and a pool of buffers.
//!
//! A [`GpuContext`] is made once by the program (the CLI or the editor) and
//! shared by every device node through an `Arc`; nothing here is static or
//! process-wide. Choosing the adapter never panics: no adapter, or none
//! matching `WGPU_ADAPTER_NAME`, is a [`GpuError`] that names what was found.

use std::collections::HashMap;
use std::sync::{Arc, Mutex, MutexGuard, Weak};
use std::time::Instant;

/// Why no device could be had, or a device operation failed.
#[derive(Debug, Clone, thiserror::Error)]
pub enum GpuError {
    /// No adapter of the allowed backends exists (no driver installed).
    #[error(
        "no {backends} adapter found (install a Vulkan driver, e.g. Mesa's lavapipe: apt install mesa-vulkan-drivers)"
    )]
    NoAdapter {
        /// The backends searched, e.g. "Vulkan".
        backends: String,
    },
    /// `WGPU_ADAPTER_NAME` (or `DEPTHGRAPH_ADAPTER`) matches no adapter.
    #[error("no adapter name contains `{wanted}` (from {var}); found: {found}")]
    NoMatchingAdapter {
        /// The requested name fragment.
        wanted: String,
        /// The variable it came from.
        var: &'static str,
        /// The adapters that exist.
        found: String,
    },
    /// The adapter refused to open a device.
    #[error("{adapter}: could not open a device: {message}")]
    RequestDevice {
        /// The adapter.
        adapter: String,
        /// The driver's reason.
        message: String,
    },
    /// A problem needs a buffer larger than the device binds (or than the
    /// `DEPTHGRAPH_GPU_MAX_BUFFER_MB` cap); device nodes then run on the CPU.
    #[error(
        "{adapter}: needs a {needed_mib:.1} MiB buffer, the device binds at most {allowed_mib:.1} MiB"
    )]
    TooLarge {
        /// The adapter.
        adapter: String,
        /// The buffer asked for, MiB.
        needed_mib: f64,
        /// The largest the device binds, MiB.
        allowed_mib: f64,
    },
    /// The device could not do what was asked though nothing was wrong
    /// with the request (out of its memory, a driver's internal failure):
    /// device nodes then run on the CPU.
    #[error("{adapter}: {message}")]
    Unavailable {
        /// The adapter.
        adapter: String,
        /// What failed.
        message: String,
    },
    /// A device operation failed (validation, out of memory, device lost).
    #[error("{adapter}: {message}")]
    Device {
        /// The adapter.
        adapter: String,
        /// What failed.
        message: String,
    },
}

/// What the program knows of the adapter in use.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct AdapterSummary {
    /// The adapter's name, e.g. "llvmpipe (LLVM 15.0.6, 256 bits)".
    pub name: String,
    /// Driver name and version.
    pub driver: String,
    /// The graphics API ("Vulkan").
    pub api: String,
    /// Discrete, integrated, virtual or CPU (a software rasteriser such as lavapipe).
    pub device_type: String,
}

impl AdapterSummary {
    fn of(info: &wgpu::AdapterInfo) -> Self {
        let driver = [info.driver.as_str(), info.driver_info.as_str()]
            .iter()
            .filter(|s| !s.is_empty())
            .copied()
            .collect::<Vec<_>>()
            .join(" ");
        Self {
            name: info.name.clone(),
            driver,
            api: format!("{:?}", info.backend),
            device_type: format!("{:?}", info.device_type),
        }
    }
    /// True for a software implementation (lavapipe, SwiftShader): its
    /// timings are for correctness only.
    pub fn is_software(&self) -> bool {
        self.device_type == "Cpu"
    }
    /// `name (API, driver)`, the form `explain` prints.
    pub fn label(&self) -> String {
        format!("{} ({}, {})", self.name, self.api, self.driver)
    }
}

/// Where adapters are looked for and which one is taken.
#[derive(Debug, Clone, Default)]
pub struct AdapterRequest {
    /// A fragment of the adapter's name (case-insensitive); `None` reads
    /// `DEPTHGRAPH_ADAPTER`, then `WGPU_ADAPTER_NAME`.
    pub name: Option<String>,
    /// The largest buffer a device node may use, MiB (to leave room on a
    /// shared device); `None` reads `DEPTHGRAPH_GPU_MAX_BUFFER_MB`, else the
    /// device's own limit. A node whose problem needs more runs on the CPU.
    pub max_buffer_mb: Option<u64>,
    /// Aperture views `Refocus` renders per dispatch (`None`:
    /// [`DEFAULT_VIEWS_PER_DISPATCH`]; fewer where the buffers of that many
    /// views would exceed the largest buffer). 1 is one view per dispatch,
    /// the path before batching, kept to compare against.
    pub views_per_dispatch: Option<usize>,
    /// The most workgroups a flat (1-D) kernel's dispatch uses along one
    /// dimension before it wraps into rows; `None` (or more than the
    /// device allows) is the device's limit. Smaller values only split a
    /// dispatch into more rows, the same results: a test can reach the
    /// wrapped path without millions of pixels.
    pub max_groups_per_row: Option<u32>,
    /// The most surfaces one dispatch of Relight's decision kernels (the
    /// object's light, the fill) takes: at most (and with `None`)
    /// [`DEFAULT_SURFACES_PER_DISPATCH`], larger values clamped to it, and
    /// fewer where their decisions would exceed the largest buffer.
    /// Smaller values only split a call into more dispatches, the same
    /// sums: a test can reach the split path without 65 536 surfaces.
    pub max_surfaces_per_dispatch: Option<usize>,
}

/// Surfaces per dispatch of Relight's decision kernels unless the request
/// says fewer: a dispatch's run time stays short (a driver's watchdog ends
/// long ones).
pub const DEFAULT_SURFACES_PER_DISPATCH: usize = 1 << 16;

/// Views `Refocus` renders per dispatch unless the request says otherwise:
/// one dispatch has a fixed cost on the device and on the host (its
/// recording), which a view at 640x480 does not amortise (measured on an
/// H200: 0.12 ms a view at 640x480, 0.33 ms at 1600x1200, 7.5x the pixels).
pub const DEFAULT_VIEWS_PER_DISPATCH: usize = 16;

/// One device, its queue, the compiled pipelines and the buffer pool.
pub struct GpuContext {
    // kept alive for the device's lifetime
    _instance: wgpu::Instance,
    adapter: wgpu::Adapter,
    device: wgpu::Device,
    queue: wgpu::Queue,
    summary: AdapterSummary,
    /// Largest storage buffer a kernel may bind, bytes.
    max_storage: u64,
    /// Refocus's views per dispatch (at least 1).
    views_per_dispatch: usize,
    /// A flat dispatch's workgroups per row (at least 1, at most the
    /// device's limit per dimension).
    groups_per_row: u32,
    /// Surfaces per dispatch of the decision kernels (at least 1).
    surfaces_per_dispatch: usize,
    pipelines: Mutex<HashMap<&'static str, Arc<wgpu::ComputePipeline>>>,
    layouts: Mutex<HashMap<&'static str, Arc<Layout>>>,
    compile_ms: Mutex<f64>,
    pool: Arc<Mutex<Pool>>,
    resident: Mutex<Vec<Resident>>,
    /// Errors nobody captured (reported by the next operation that checks).
    uncaptured: Arc<Mutex<Option<String>>>,
    /// Why the device was lost (a driver reset, a hang, a removed GPU), once
    /// it was: every device node then runs on the CPU ([`crate::node`]).
    lost: Arc<Mutex<Option<String>>>,
}

impl std::fmt::Debug for GpuContext {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuContext")
            .field("adapter", &self.summary)
            .finish_non_exhaustive()
    }
}

/// The backends searched: `WGPU_BACKEND` when set (e.g. `vulkan`), else
/// Vulkan, Metal and DX12 (the GL backend has no compute on many drivers).
fn backends() -> wgpu::Backends {
    wgpu::Backends::from_env().unwrap_or(wgpu::Backends::PRIMARY)
}

fn backend_names(b: wgpu::Backends) -> String {
    let mut names = Vec::new();
    if b.contains(wgpu::Backends::VULKAN) {
        names.push("Vulkan");
    }
    if b.contains(wgpu::Backends::METAL) {
        names.push("Metal");
    }
    if b.contains(wgpu::Backends::DX12) {
        names.push("DX12");
    }
    if b.contains(wgpu::Backends::GL) {
        names.push("GL");
    }
    if names.is_empty() {
        "wgpu".to_string()
    } else {
        names.join("/")
    }
}

/// Preference among adapter kinds: real GPUs first, a software one last.
fn rank(t: wgpu::DeviceType) -> u8 {
    match t {
        wgpu::DeviceType::DiscreteGpu => 0,
        wgpu::DeviceType::IntegratedGpu => 1,
        wgpu::DeviceType::VirtualGpu => 2,
        wgpu::DeviceType::Other => 3,
        wgpu::DeviceType::Cpu => 4,
    }
}

impl GpuContext {
    /// Opens the preferred adapter (see [`AdapterRequest`]). Never panics.
    pub fn new(req: &AdapterRequest) -> Result<Arc<Self>, GpuError> {
        let backends = backends();
        let instance = wgpu::Instance::new(wgpu::InstanceDescriptor {
            backends,
            ..wgpu::InstanceDescriptor::new_without_display_handle()
        });
        let adapters = pollster::block_on(instance.enumerate_adapters(backends));
        if adapters.is_empty() {
            return Err(GpuError::NoAdapter {
                backends: backend_names(backends),
            });
        }
        let wanted = match &req.name {
            Some(n) => Some((n.clone(), "the request")),
            None => std::env::var("DEPTHGRAPH_ADAPTER")
                .ok()
                .map(|n| (n, "DEPTHGRAPH_ADAPTER"))
                .or_else(|| {
                    std::env::var("WGPU_ADAPTER_NAME")
                        .ok()
                        .map(|n| (n, "WGPU_ADAPTER_NAME"))
                }),
        };
        let mut candidates: Vec<wgpu::Adapter> = adapters;
        if let Some((name, var)) = &wanted {
            let lower = name.to_lowercase();
            let found = candidates
                .iter()
                .map(|a| a.get_info().name)
                .collect::<Vec<_>>()
                .join(", ");
            candidates.retain(|a| a.get_info().name.to_lowercase().contains(&lower));
            if candidates.is_empty() {
                return Err(GpuError::NoMatchingAdapter {
                    wanted: name.clone(),
                    var,
                    found,
                });
            }
        }
        candidates.sort_by_key(|a| rank(a.get_info().device_type));
        let adapter = candidates.remove(0);
        let summary = AdapterSummary::of(&adapter.get_info());
        let limits = adapter.limits();
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("depthgraph"),
            required_features: wgpu::Features::empty(),
            required_limits: limits.clone(),
            ..Default::default()
        }))
        .map_err(|e| GpuError::RequestDevice {
            adapter: summary.label(),
            message: e.to_string(),
        })?;
        let cap_mb = req.max_buffer_mb.or_else(|| {
            std::env::var("DEPTHGRAPH_GPU_MAX_BUFFER_MB")
                .ok()
                .and_then(|v| v.trim().parse().ok())
        });
        let device_max =
            (limits.max_storage_buffer_binding_size as u64).min(limits.max_buffer_size);
        let max_storage = match cap_mb {
            Some(mb) => device_max.min(mb.saturating_mul(1 << 20)),
            None => device_max,
        };
        let uncaptured = Arc::new(Mutex::new(None));
        {
            let slot = uncaptured.clone();
            device.on_uncaptured_error(Arc::new(move |e: wgpu::Error| {
                let mut s = slot.lock().unwrap_or_else(|p| p.into_inner());
                if s.is_none() {
                    *s = Some(e.to_string());
                }
            }));
        }
        let lost = Arc::new(Mutex::new(None));
        {
            let slot = lost.clone();
            device.set_device_lost_callback(move |reason, message| {
                let mut s = slot.lock().unwrap_or_else(|p| p.into_inner());
                if s.is_none() {
                    *s = Some(format!("{reason:?}: {message}"));
                }
            });
        }
        Ok(Arc::new(Self {
            _instance: instance,
            adapter,
            device,
            queue,
            summary,
            max_storage,
            views_per_dispatch: req
                .views_per_dispatch
                .unwrap_or(DEFAULT_VIEWS_PER_DISPATCH)
                .max(1),
            groups_per_row: req
                .max_groups_per_row
                .unwrap_or(u32::MAX)
                .min(limits.max_compute_workgroups_per_dimension)
                .max(1),
            surfaces_per_dispatch: req
                .max_surfaces_per_dispatch
                .unwrap_or(DEFAULT_SURFACES_PER_DISPATCH)
                .clamp(1, DEFAULT_SURFACES_PER_DISPATCH),
            pipelines: Mutex::new(HashMap::new()),
            layouts: Mutex::new(HashMap::new()),
            compile_ms: Mutex::new(0.0),
            pool: Arc::new(Mutex::new(Pool::default())),
            resident: Mutex::new(Vec::new()),
            uncaptured,
            lost,
        }))
    }

    /// Why the device was lost, if it was (its callback said so, or a wait
    /// on it failed): nothing more can run on it.
    pub fn lost(&self) -> Option<String> {
        lock(&self.lost).clone()
    }

    /// Records that the device is lost (the first reason is kept).
    pub fn mark_lost(&self, why: impl Into<String>) {
        let mut s = lock(&self.lost);
        if s.is_none() {
            *s = Some(why.into());
        }
    }

    /// The adapter in use.
    pub fn adapter(&self) -> &AdapterSummary {
        &self.summary
    }

    /// The adapter's limits (the device was opened with all of them).
    pub fn limits(&self) -> wgpu::Limits {
        self.adapter.limits()
    }

    /// The wgpu device.
    pub fn device(&self) -> &wgpu::Device {
        &self.device
    }

    /// The wgpu queue.
    pub fn queue(&self) -> &wgpu::Queue {
        &self.queue
    }

    /// A device error in the adapter's name.
    pub fn error(&self, message: impl Into<String>) -> GpuError {
        GpuError::Device {
            adapter: self.summary.label(),
            message: message.into(),
        }
    }

    /// The error an earlier operation raised and nobody captured, if any
    /// (taken: it is reported once).
    pub fn take_uncaptured(&self) -> Option<GpuError> {
        let msg = lock(&self.uncaptured).take()?;
        Some(self.error(msg))
    }

    /// The compute pipeline of entry point `entry` in WGSL `source`, compiled
    /// once per context and kept under `name`. Compile errors are returned.
    pub fn pipeline(
        &self,
        name: &'static str,
        source: &str,
        entry: &str,
    ) -> Result<Arc<wgpu::ComputePipeline>, GpuError> {
        self.pipeline_in(name, source, entry, None)
    }

    /// [`GpuContext::pipeline`] with an explicit layout (one of
    /// [`GpuContext::layout`]'s, so it is the same object on every call).
    pub fn pipeline_in(
        &self,
        name: &'static str,
        source: &str,
        entry: &str,
        layout: Option<&wgpu::PipelineLayout>,
    ) -> Result<Arc<wgpu::ComputePipeline>, GpuError> {
        if let Some(p) = lock(&self.pipelines).get(name) {
            return Ok(p.clone());
        }
        let t = Instant::now();
        // every kind of error (a driver's internal one, memory, validation):
        // an invalid pipeline is never cached
        let scopes = [
            wgpu::ErrorFilter::OutOfMemory,
            wgpu::ErrorFilter::Internal,
            wgpu::ErrorFilter::Validation,
        ]
        .map(|f| self.device.push_error_scope(f));
        let module = self
            .device
            .create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some(name),
                source: wgpu::ShaderSource::Wgsl(source.into()),
            });
        let pipeline = self
            .device
            .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(name),
                layout,
                module: &module,
                entry_point: Some(entry),
                compilation_options: Default::default(),
                cache: None,
            });
        // (popped innermost first, each one; validation is the last pushed)
        let mut first: Option<(bool, wgpu::Error)> = None;
        for (k, scope) in scopes.into_iter().enumerate().rev() {
            if let Some(e) = pollster::block_on(scope.pop()) {
                first.get_or_insert((k < 2, e));
            }
        }
        if let Some((unavailable, e)) = first {
            let message = format!("compiling `{name}`: {e}");
            return Err(if unavailable {
                GpuError::Unavailable {
                    adapter: self.summary.label(),
                    message,
                }
            } else {
                self.error(message)
            });
        }
        *lock(&self.compile_ms) += t.elapsed().as_secs_f64() * 1e3;
        let p = Arc::new(pipeline);
        lock(&self.pipelines).insert(name, p.clone());
        Ok(p)
    }

    /// The bind group layout `entries` and a pipeline layout of it alone,
    /// made once per context under `name`.
    pub fn layout(
        &self,
        name: &'static str,
        entries: &[wgpu::BindGroupLayoutEntry],
    ) -> Arc<Layout> {
        let mut map = lock(&self.layouts);
        if let Some(l) = map.get(name) {
            return l.clone();
        }
        let bgl = self
            .device
            .create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
                label: Some(name),
                entries,
            });
        let pl = self
            .device
            .create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some(name),
                bind_group_layouts: &[Some(&bgl)],
                immediate_size: 0,
            });
        let l = Arc::new((bgl, pl));
        map.insert(name, l.clone());
        l
    }

    /// Milliseconds spent compiling pipelines so far (the cold cost).
    pub fn compile_ms(&self) -> f64 {
        *lock(&self.compile_ms)
    }

    /// The largest buffer a kernel may bind, bytes.
    pub fn max_buffer(&self) -> u64 {
        self.max_storage
    }

    /// How many surfaces one dispatch of a decision kernel takes, at most
    /// (see [`AdapterRequest::max_surfaces_per_dispatch`]).
    pub fn surfaces_per_dispatch(&self) -> usize {
        self.surfaces_per_dispatch
    }

    /// How many aperture views `Refocus` renders per dispatch, at most
    /// (see [`AdapterRequest::views_per_dispatch`]).
    pub fn views_per_dispatch(&self) -> usize {
        self.views_per_dispatch
    }

    /// How a flat kernel of `n` invocations in workgroups of `size` is
    /// dispatched: `(x, y)` workgroups, rows of at most
    /// [`AdapterRequest::max_groups_per_row`]; invocation `k` is
    /// `(k % (x size), k / (x size))`. `None` when even the rows exceed the
    /// device's limit.
    pub fn flat_grid(&self, n: usize, size: u32) -> Option<(u32, u32)> {
        let total = u32::try_from(n.div_ceil(size.max(1) as usize).max(1)).ok()?;
        let x = total.min(self.groups_per_row);
        let y = total.div_ceil(x);
        (y <= self.limits().max_compute_workgroups_per_dimension).then_some((x, y))
    }

    /// A buffer of at least `size` bytes with `usage`, from the pool when
    /// one is free; it returns to the pool when dropped. Larger than
    /// [`GpuContext::max_buffer`] is [`GpuError::TooLarge`].
    pub fn buffer(&self, size: u64, usage: wgpu::BufferUsages) -> Result<PooledBuffer, GpuError> {
        if size > self.max_storage {
            return Err(GpuError::TooLarge {
                adapter: self.summary.label(),
                needed_mib: size as f64 / (1u64 << 20) as f64,
                allowed_mib: self.max_storage as f64 / (1u64 << 20) as f64,
            });
        }
        // Sizes are rounded up to a power of two (at least 256 B) so that
        // buffers of similar images are reused; near the limit, to 256 B.
        let pow2 = size.max(256).next_power_of_two();
        let class = [pow2, size.next_multiple_of(256), size.next_multiple_of(4)]
            .into_iter()
            .find(|&c| c <= self.max_storage)
            .ok_or_else(|| GpuError::TooLarge {
                adapter: self.summary.label(),
                needed_mib: size as f64 / (1u64 << 20) as f64,
                allowed_mib: self.max_storage as f64 / (1u64 << 20) as f64,
            })?;
        if let Some(b) = lock(&self.pool).take(class, usage) {
            return Ok(PooledBuffer {
                buffer: Some(b),
                class,
                usage,
                pool: Arc::downgrade(&self.pool),
            });
        }
        let b = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: None,
            size: class,
            usage,
            mapped_at_creation: false,
        });
        Ok(PooledBuffer {
            buffer: Some(b),
            class,
            usage,
            pool: Arc::downgrade(&self.pool),
        })
    }

    /// The device copy of `value`, if a device node left one (see
    /// [`GpuContext::keep_resident`]).
    pub(crate) fn resident(
        &self,
        value: &Arc<dyn std::any::Any + Send + Sync>,
    ) -> Option<Arc<PooledBuffer>> {
        let mut list = lock(&self.resident);
        list.retain(|r| r.value.strong_count() > 0);
        let ptr = Arc::as_ptr(value) as *const () as usize;
        list.iter()
            .find(|r| r.ptr == ptr && r.value.upgrade().is_some_and(|v| Arc::ptr_eq(&v, value)))
            .map(|r| r.buffer.clone())
    }

    /// Remembers that `buffer` holds `value`'s pixels for as long as the
    /// value lives, so a device node downstream reads it without an upload.
    /// At most [`RESIDENT_BUDGET`] bytes are kept (oldest dropped first).
    pub(crate) fn keep_resident(
        &self,
        value: &Arc<dyn std::any::Any + Send + Sync>,
        buffer: Arc<PooledBuffer>,
        bytes: u64,
    ) {
        let mut list = lock(&self.resident);
        list.retain(|r| r.value.strong_count() > 0);
        list.push(Resident {
            value: Arc::downgrade(value),
            ptr: Arc::as_ptr(value) as *const () as usize,
            buffer,
            bytes,
        });
        let mut total: u64 = list.iter().map(|r| r.bytes).sum();
        while total > RESIDENT_BUDGET && !list.is_empty() {
            total -= list.remove(0).bytes;
        }
    }
}

/// A bind group layout and the pipeline layout made of it alone.
pub type Layout = (wgpu::BindGroupLayout, wgpu::PipelineLayout);

/// Device bytes kept for values that device nodes hand each other.
pub const RESIDENT_BUDGET: u64 = 1 << 30;

/// Largest number of bytes the pool keeps idle.
const POOL_BUDGET: u64 = 512 << 20;

struct Resident {
    value: Weak<dyn std::any::Any + Send + Sync>,
    ptr: usize,
    buffer: Arc<PooledBuffer>,
    bytes: u64,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

#[derive(Default)]
struct Pool {
    free: HashMap<(u64, u32), Vec<wgpu::Buffer>>,
    bytes: u64,
}

impl Pool {
    fn take(&mut self, class: u64, usage: wgpu::BufferUsages) -> Option<wgpu::Buffer> {
        let b = self.free.get_mut(&(class, usage.bits()))?.pop()?;
        self.bytes -= class;
        Some(b)
    }
    fn give(&mut self, class: u64, usage: wgpu::BufferUsages, b: wgpu::Buffer) {
        if self.bytes + class > POOL_BUDGET {
            return; // dropped: freed by wgpu
        }
        self.bytes += class;
        self.free.entry((class, usage.bits())).or_default().push(b);
    }
}

/// A buffer borrowed from the context's pool.
pub struct PooledBuffer {
    buffer: Option<wgpu::Buffer>,
    class: u64,
    usage: wgpu::BufferUsages,
    pool: Weak<Mutex<Pool>>,
}

impl PooledBuffer {
    /// The wgpu buffer.
    pub fn get(&self) -> &wgpu::Buffer {
        // Invariant: `buffer` is Some until drop.
        self.buffer.as_ref().unwrap_or_else(|| unreachable!())
    }
}

impl std::ops::Deref for PooledBuffer {
    type Target = wgpu::Buffer;
    fn deref(&self) -> &wgpu::Buffer {
        self.get()
    }
}

impl Drop for PooledBuffer {
    fn drop(&mut self) {
        if let (Some(b), Some(pool)) = (self.buffer.take(), self.pool.upgrade()) {
            lock(&pool).give(self.class, self.usage, b);
        }
    }
}
