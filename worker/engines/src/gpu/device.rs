//! Device setup, apart from the work: the wgpu device and queue on one adapter, the handler
//! that collects its errors, and the transport pipelines (plain and differential) with their bind
//! group layouts.
//!
//! Built once per engine ([`GpuDevice::open`]); each render then only makes buffers and bind
//! groups and records dispatches ([`super::submission`]).

use super::adapters::AdapterInfo;
use super::records::{DIFFERENTIAL_BYTES, PARAMS_BYTES, PHYSICS_BYTES, SEED_BYTES, SOURCE_BYTES};
use super::{block_on, dispatch_plan, shader_source};
use scatterfarm_model::engine::EngineError;
use std::sync::{Arc, Mutex};

/// Invocations per workgroup (the shader's `WORKGROUP_SIZE` override).
pub(crate) const WORKGROUP_SIZE: u32 = 64;

/// An open device with the transport pipeline built on it.
pub(crate) struct GpuDevice {
    pub(crate) device: wgpu::Device,
    pub(crate) queue: wgpu::Queue,
    pub(crate) pipeline: wgpu::ComputePipeline,
    pub(crate) layout: wgpu::BindGroupLayout,
    /// The differential render's pipeline (entry point `differential`) and its bindings.
    pub(crate) differential: wgpu::ComputePipeline,
    pub(crate) differential_layout: wgpu::BindGroupLayout,
    pub(crate) limits: wgpu::Limits,
    /// The adapter's name, for error messages.
    name: String,
    /// Errors wgpu reported outside any error scope, since the last check.
    errors: Arc<Mutex<Vec<String>>>,
}

impl GpuDevice {
    /// Opens a device on `adapter` (with 64-bit integers when `int64`) and builds the pipeline.
    pub(crate) fn open(
        adapter: &wgpu::Adapter,
        info: &AdapterInfo,
        int64: bool,
    ) -> Result<GpuDevice, EngineError> {
        let limits = adapter.limits();
        let (device, queue) = request_device(adapter, info, &limits, int64)?;
        let errors = collect_uncaptured_errors(&device);
        let (pipeline, layout, differential, differential_layout) =
            build_pipelines(&device, info, int64)?;
        Ok(GpuDevice {
            device,
            queue,
            pipeline,
            layout,
            differential,
            differential_layout,
            limits,
            name: info.name.clone(),
            errors,
        })
    }

    /// The largest buffer a chunk may use, at most `tuned`.
    pub(crate) fn buffer_limit(&self, tuned: u64) -> u64 {
        self.limits
            .max_storage_buffer_binding_size
            .min(self.limits.max_buffer_size)
            .min(tuned)
    }

    /// Errors the device reported since the last call, as one `EngineError`.
    pub(crate) fn take_errors(&self, during: &str) -> Result<(), EngineError> {
        let mut errors = match self.errors.lock() {
            Ok(e) => e,
            Err(poisoned) => poisoned.into_inner(),
        };
        if errors.is_empty() {
            return Ok(());
        }
        let all = errors.drain(..).collect::<Vec<_>>().join("; ");
        Err(EngineError::Device(format!(
            "{} failed {during}: {all}",
            self.name
        )))
    }

    /// A device error mentioning this device.
    pub(crate) fn error(&self, what: impl std::fmt::Display) -> EngineError {
        EngineError::Device(format!("{} failed {what}", self.name))
    }
}

/// The device, with the adapter's best limits (count matrices are megabytes) and 64-bit integers
/// when asked for (a cheaper Philox multiply).
fn request_device(
    adapter: &wgpu::Adapter,
    info: &AdapterInfo,
    limits: &wgpu::Limits,
    int64: bool,
) -> Result<(wgpu::Device, wgpu::Queue), EngineError> {
    let features = if int64 {
        wgpu::Features::SHADER_INT64
    } else {
        wgpu::Features::empty()
    };
    block_on(adapter.request_device(&wgpu::DeviceDescriptor {
        label: Some("scatterfarm"),
        required_features: features,
        required_limits: limits.clone(),
        ..Default::default()
    }))
    .map_err(|e| EngineError::Unavailable(format!("cannot open a device on {}: {e}", info.name)))
}

/// Errors outside error scopes are recorded, not panicked on: a render reports them.
fn collect_uncaptured_errors(device: &wgpu::Device) -> Arc<Mutex<Vec<String>>> {
    let errors = Arc::new(Mutex::new(Vec::new()));
    let sink = Arc::clone(&errors);
    device.on_uncaptured_error(Arc::new(move |e: wgpu::Error| {
        if let Ok(mut v) = sink.lock() {
            v.push(e.to_string());
        }
    }));
    errors
}

/// The pipelines' parts: the transport pipeline and its layout, then the differential ones.
type Pipelines = (
    wgpu::ComputePipeline,
    wgpu::BindGroupLayout,
    wgpu::ComputePipeline,
    wgpu::BindGroupLayout,
);

/// The shader module and its two compute pipelines (entry points `main` and `differential`); a
/// failure here means the shader does not build on this device.
fn build_pipelines(
    device: &wgpu::Device,
    info: &AdapterInfo,
    int64: bool,
) -> Result<Pipelines, EngineError> {
    let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
    let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some("transport.wgsl"),
        source: wgpu::ShaderSource::Wgsl(shader_source(int64).into()),
    });
    let layout = bind_group_layout(device, false);
    let differential_layout = bind_group_layout(device, true);
    let pipeline = build_pipeline(device, &module, &layout, "main");
    let differential = build_pipeline(device, &module, &differential_layout, "differential");
    if let Some(e) = block_on(scope.pop()) {
        return Err(EngineError::Device(format!(
            "the transport shader does not build on {}: {e}",
            info.name
        )));
    }
    tracing::debug!(int64, "transport pipelines built on {}", info.name);
    Ok((pipeline, layout, differential, differential_layout))
}

fn build_pipeline(
    device: &wgpu::Device,
    module: &wgpu::ShaderModule,
    layout: &wgpu::BindGroupLayout,
    entry_point: &str,
) -> wgpu::ComputePipeline {
    let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
        label: Some(entry_point),
        bind_group_layouts: &[Some(layout)],
        immediate_size: 0,
    });
    let workgroup = f64::from(WORKGROUP_SIZE);
    device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
        label: Some(entry_point),
        layout: Some(&pipeline_layout),
        module,
        entry_point: Some(entry_point),
        compilation_options: wgpu::PipelineCompilationOptions {
            constants: &[("WORKGROUP_SIZE", workgroup)],
            zero_initialize_workgroup_memory: false,
        },
        cache: None,
    })
}

/// Bindings: the dispatch's parameters (dynamic offset), then sources, medium, seeds (read), and
/// the tallies: counts and scattering events (read-write). The differential render adds its
/// sizes (uniform), the factors and materials (read), and its scratch and deltas (read-write).
fn bind_group_layout(device: &wgpu::Device, differential: bool) -> wgpu::BindGroupLayout {
    let storage = |binding: u32, read_only: bool, min: u64| {
        let ty = wgpu::BufferBindingType::Storage { read_only };
        layout_entry(binding, ty, false, min)
    };
    let mut entries = vec![
        layout_entry(0, wgpu::BufferBindingType::Uniform, true, PARAMS_BYTES),
        storage(1, true, SOURCE_BYTES),
        storage(2, true, dispatch_plan::PIXEL_BYTES),
        storage(3, true, SEED_BYTES),
        storage(4, false, 4),
        storage(5, false, 8),
    ];
    if differential {
        entries.extend([
            layout_entry(
                6,
                wgpu::BufferBindingType::Uniform,
                false,
                DIFFERENTIAL_BYTES,
            ),
            storage(7, true, 4),
            storage(8, true, PHYSICS_BYTES),
            storage(9, false, 4),
            storage(10, false, 8),
        ]);
    }
    device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
        label: Some(if differential {
            "differential bindings"
        } else {
            "transport bindings"
        }),
        entries: &entries,
    })
}

fn layout_entry(
    binding: u32,
    ty: wgpu::BufferBindingType,
    dynamic: bool,
    min: u64,
) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::COMPUTE,
        ty: wgpu::BindingType::Buffer {
            ty,
            has_dynamic_offset: dynamic,
            min_binding_size: wgpu::BufferSize::new(min),
        },
        count: None,
    }
}
