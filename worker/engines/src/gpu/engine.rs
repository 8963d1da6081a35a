//! [`GpuEngine`]: the device, the compute pipeline, and one render batch's trip through them.
//!
//! A render, step by step (the style of wgpu's `hello_compute`):
//! 1. check the batch and lay it out for the shader on the host: per source its ray (computed in
//!    f64, uploaded as f32) and start pixel (grid-line rule applied in f64); per item and pixel
//!    the record (σt or −1 for opaque, uniform-block level, σa/σt, HG c); per item its seed;
//! 2. cut it into chunks that fit the device's buffer limits ([`plan::chunks`]) — usually one,
//!    so the whole batch is one submission;
//! 3. per chunk: upload, record one compute pass of several bounded dispatches (each reads its own
//!    parameter record through a dynamic uniform offset), copy the tallies to staging buffers,
//!    submit, wait, read back into each item's [`CountMatrix`].
//!
//! Device errors are caught by wgpu's uncaptured-error handler and returned as
//! [`EngineError::Device`]; nothing the device or the batch does can panic here.

use super::adapters::{choose, enumerate, new_instance, AdapterInfo, AdapterSelector};
use super::plan::{self, Chunk, Shape};
use super::{block_on, shader_source, SHADER_HASH};
use crate::rules::{start_pixel, uniform_block_levels, CORNER_TOLERANCE_F32};
use scatterfarm_model::engine::{
    validate_batch, CountMatrix, Engine, EngineError, EngineFingerprint, RenderBatch, RenderItem,
    RenderOutput,
};
use scatterfarm_model::geometry::Geometry;
use scatterfarm_model::material::Material;
use std::fmt;
use std::sync::{mpsc, Arc, Mutex};
use wgpu::util::DeviceExt;

/// Bumped whenever a change outside the shader changes this engine's counts (a shader change
/// changes [`SHADER_HASH`], which the fingerprint carries too).
pub const GPU_ENGINE_VERSION: &str = "gpu-1";

/// The largest HG `c = (1−g)/(1+g)` the shader gets: beyond it (g within 2e-18 of −1) the turn
/// is a full reversal to f32 precision, and c² must not overflow f32.
const MAX_HG_C: f64 = 1e18;

/// Invocations per workgroup (the shader's `WORKGROUP_SIZE` override).
const WORKGROUP_SIZE: u32 = 64;

/// Bytes of one dispatch's parameter record (`Params` in `transport.wgsl`).
const PARAMS_BYTES: u64 = 80;

/// Bytes of one source record (`Source` in `transport.wgsl`).
const SOURCE_BYTES: usize = 24;

/// How the engine cuts work; fixed per device type, changed only by tests and benchmarks.
#[derive(Debug, Clone)]
pub(crate) struct Tuning {
    /// Largest buffer a chunk may use, below the device's own limits.
    pub(crate) max_buffer_bytes: u64,
    /// Photons in flight the device wants (sets photons per invocation).
    pub(crate) target_invocations: u64,
    /// Photons per invocation, when fixed.
    pub(crate) per_invocation: Option<u32>,
    /// At most this many photons per dispatch (a dispatch stays well under a second).
    pub(crate) photons_per_dispatch: u64,
}

impl Tuning {
    fn for_device(cpu: bool) -> Tuning {
        // A CPU device (lavapipe) runs one workgroup per core at a time: a few workgroups of 64
        // per core are enough, and longer runs per invocation keep its SIMD lanes busy. A GPU
        // wants tens of thousands of invocations in flight.
        let cores = std::thread::available_parallelism().map_or(4, |n| n.get()) as u64;
        Tuning {
            max_buffer_bytes: 1 << 30,
            target_invocations: if cpu { cores * 1024 } else { 1 << 18 },
            per_invocation: None,
            photons_per_dispatch: if cpu { 1 << 22 } else { 1 << 23 },
        }
    }
}

/// The wgpu engine on one adapter.
pub struct GpuEngine {
    info: AdapterInfo,
    device: wgpu::Device,
    queue: wgpu::Queue,
    pipeline: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
    limits: wgpu::Limits,
    /// The shader multiplies with 64-bit integers.
    int64: bool,
    /// Errors wgpu reported outside any error scope, since the last check.
    errors: Arc<Mutex<Vec<String>>>,
    /// One render at a time on the device, so errors belong to the render that caused them.
    busy: Mutex<()>,
    pub(crate) tuning: Tuning,
}

impl fmt::Debug for GpuEngine {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("GpuEngine")
            .field("adapter", &self.info)
            .field("tuning", &self.tuning)
            .finish()
    }
}

impl GpuEngine {
    /// Opens the adapter `selector` picks and builds the transport pipeline on it. Logs which
    /// adapter and why. [`EngineError::Unavailable`] when there is no such adapter (the caller
    /// may fall back to the CPU engine), [`EngineError::Device`] when the device fails.
    pub fn new(selector: &AdapterSelector) -> Result<GpuEngine, EngineError> {
        Self::select(selector, true)
    }

    /// The engine on the adapter `selector` picks, with 64-bit integer multiplies in the shader
    /// only when `int64` is set and the device has them (tests compare both shader variants).
    #[cfg(test)]
    pub(crate) fn with_int64(
        selector: &AdapterSelector,
        int64: bool,
    ) -> Result<GpuEngine, EngineError> {
        Self::select(selector, int64)
    }

    fn select(selector: &AdapterSelector, int64: bool) -> Result<GpuEngine, EngineError> {
        let instance = new_instance();
        let adapters = enumerate(&instance);
        let infos: Vec<AdapterInfo> = adapters
            .iter()
            .enumerate()
            .map(|(i, a)| AdapterInfo::from_wgpu(i, a))
            .collect();
        let pci: Vec<String> = adapters
            .iter()
            .map(|a| a.get_info().device_pci_bus_id)
            .collect();
        let (index, why) = choose(&infos, &pci, selector)?;
        let info = infos[index].clone();
        tracing::info!("GPU engine on adapter {info}: {why}");
        Self::open(&adapters[index], info, int64)
    }

    /// True when the shader multiplies with 64-bit integers (the device has `SHADER_INT64`);
    /// otherwise it builds the products from 16-bit pieces. Both give the same counts.
    pub fn uses_int64(&self) -> bool {
        self.int64
    }

    /// The adapter this engine renders on.
    pub fn adapter(&self) -> &AdapterInfo {
        &self.info
    }

    fn open(
        adapter: &wgpu::Adapter,
        info: AdapterInfo,
        allow_int64: bool,
    ) -> Result<GpuEngine, EngineError> {
        // The device, with the adapter's best limits (count matrices are megabytes) and 64-bit
        // integers when it has them (a cheaper Philox multiply).
        let limits = adapter.limits();
        let fits = WORKGROUP_SIZE <= limits.max_compute_invocations_per_workgroup
            && WORKGROUP_SIZE <= limits.max_compute_workgroup_size_x;
        if !fits {
            return Err(EngineError::Unavailable(format!(
                "{} runs fewer than {WORKGROUP_SIZE} invocations per workgroup",
                info.name
            )));
        }
        let int64 = allow_int64 && adapter.features().contains(wgpu::Features::SHADER_INT64);
        let features = if int64 {
            wgpu::Features::SHADER_INT64
        } else {
            wgpu::Features::empty()
        };
        let (device, queue) = block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("scatterfarm"),
            required_features: features,
            required_limits: limits.clone(),
            ..Default::default()
        }))
        .map_err(|e| {
            EngineError::Unavailable(format!("cannot open a device on {}: {e}", info.name))
        })?;

        // Errors outside error scopes are recorded, not panicked on: render() reports them.
        let errors = Arc::new(Mutex::new(Vec::new()));
        let sink = Arc::clone(&errors);
        device.on_uncaptured_error(Arc::new(move |e: wgpu::Error| {
            if let Ok(mut v) = sink.lock() {
                v.push(e.to_string());
            }
        }));

        // The shader and the pipeline; a failure here means the shader does not build here.
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("transport.wgsl"),
            source: wgpu::ShaderSource::Wgsl(shader_source(int64).into()),
        });
        // Bindings: the dispatch's parameters, then sources, medium, seeds (read), and the
        // tallies: counts and scattering events (read-write).
        let storage = |binding: u32, read_only: bool, min: u64| {
            let ty = wgpu::BufferBindingType::Storage { read_only };
            layout_entry(binding, ty, false, min)
        };
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("transport bindings"),
            entries: &[
                layout_entry(0, wgpu::BufferBindingType::Uniform, true, PARAMS_BYTES),
                storage(1, true, SOURCE_BYTES as u64),
                storage(2, true, plan::PIXEL_BYTES),
                storage(3, true, 8),
                storage(4, false, 4),
                storage(5, false, 8),
            ],
        });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("transport layout"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let workgroup = f64::from(WORKGROUP_SIZE);
        let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some("transport"),
            layout: Some(&pipeline_layout),
            module: &module,
            entry_point: Some("main"),
            compilation_options: wgpu::PipelineCompilationOptions {
                constants: &[("WORKGROUP_SIZE", workgroup)],
                zero_initialize_workgroup_memory: false,
            },
            cache: None,
        });
        if let Some(e) = block_on(scope.pop()) {
            return Err(EngineError::Device(format!(
                "the transport shader does not build on {}: {e}",
                info.name
            )));
        }
        tracing::debug!(int64, "transport pipeline built on {}", info.name);
        let tuning = Tuning::for_device(info.is_cpu());
        Ok(GpuEngine {
            info,
            device,
            queue,
            pipeline,
            layout,
            limits,
            int64,
            errors,
            busy: Mutex::new(()),
            tuning,
        })
    }

    /// The largest buffer a chunk may use.
    fn buffer_limit(&self) -> u64 {
        self.limits
            .max_storage_buffer_binding_size
            .min(self.limits.max_buffer_size)
            .min(self.tuning.max_buffer_bytes)
    }

    /// Errors the device reported since the last call, as one `EngineError`.
    fn take_errors(&self, during: &str) -> Result<(), EngineError> {
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
            self.info.name
        )))
    }

    fn render_batch(&self, batch: &RenderBatch<'_>) -> Result<Vec<RenderOutput>, EngineError> {
        let geo = batch.geometry;
        let (sources, bins) = (geo.sources(), geo.bins());
        let mut outputs: Vec<RenderOutput> = batch
            .items
            .iter()
            .map(|_| RenderOutput {
                counts: CountMatrix::zeros(sources, bins),
                scatter_events: 0,
            })
            .collect();
        if batch.items.is_empty() || batch.photons.count == 0 {
            return Ok(outputs);
        }
        let host = HostLayout::new(batch);
        let shape = Shape {
            items: batch.items.len(),
            sources,
            bins,
            pixels: geo.pixels(),
        };
        let limit = self.buffer_limit();
        let chunks = plan::chunks(shape, limit).map_err(|why| {
            EngineError::Device(format!("render too large for {}: {why}", self.info.name))
        })?;
        let per_invocation = plan::photons_per_invocation(
            batch.items.len() * sources,
            batch.photons.count,
            self.tuning.target_invocations,
            self.tuning.per_invocation,
        );
        tracing::debug!(
            chunks = chunks.len(),
            per_invocation,
            "GPU render: {} items, {} photons per source",
            batch.items.len(),
            batch.photons.count
        );
        self.take_errors("before this render")?;
        for chunk in &chunks {
            self.render_chunk(batch, &host, chunk, per_invocation, &mut outputs)?;
        }
        Ok(outputs)
    }

    /// One submission: the rows of `chunk`, all their photons.
    fn render_chunk(
        &self,
        batch: &RenderBatch<'_>,
        host: &HostLayout,
        chunk: &Chunk,
        per_invocation: u32,
        outputs: &mut [RenderOutput],
    ) -> Result<(), EngineError> {
        let geo = batch.geometry;
        let bins = geo.bins();
        let rows = chunk.rows();
        let photons = batch.photons;
        let splits = photons.count.div_ceil(per_invocation);
        let tasks = rows as u64 * u64::from(splits);
        let max_tasks =
            u64::from(self.limits.max_compute_workgroups_per_dimension) * u64::from(WORKGROUP_SIZE);
        let dispatches = plan::dispatches(
            tasks,
            per_invocation,
            self.tuning.photons_per_dispatch,
            max_tasks,
        );

        // 1. Parameter records, one per dispatch, at the device's uniform offset alignment.
        let stride = PARAMS_BYTES.next_multiple_of(u64::from(
            self.limits.min_uniform_buffer_offset_alignment.max(1),
        ));
        let mut params = vec![0u8; dispatches.len() * stride as usize];
        for (k, d) in dispatches.iter().enumerate() {
            let record = Params {
                geometry: &geo,
                photon_first: photons.first,
                photon_count: photons.count,
                per_invocation,
                splits,
                task_first: d.first,
                task_count: d.count,
                source_first: chunk.source_first as u32,
                source_count: chunk.source_count as u32,
            }
            .bytes();
            params[k * stride as usize..][..record.len()].copy_from_slice(&record);
        }

        // 2. Buffers: inputs initialised from the host, tallies zeroed by wgpu.
        let items = chunk.item_first..chunk.item_first + chunk.item_count;
        let storage = wgpu::BufferUsages::STORAGE;
        let init = |label: &str, contents: &[u8], usage: wgpu::BufferUsages| {
            self.device
                .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some(label),
                    contents,
                    usage,
                })
        };
        let params_buf = init("params", &params, wgpu::BufferUsages::UNIFORM);
        let sources_buf = init("sources", &host.sources, storage);
        let medium_buf = init("medium", &concat(&host.medium[items.clone()]), storage);
        let seeds_buf = init("seeds", &concat(&host.seeds[items.clone()]), storage);
        let counts_bytes = (rows * bins * 4) as u64;
        let scatter_bytes = (chunk.item_count * 8) as u64;
        let zeroed = |label: &str, size: u64, usage: wgpu::BufferUsages| {
            self.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size,
                usage,
                mapped_at_creation: false,
            })
        };
        let counts_buf = zeroed(
            "counts",
            counts_bytes,
            storage | wgpu::BufferUsages::COPY_SRC,
        );
        let scatters_buf = zeroed(
            "scatters",
            scatter_bytes,
            storage | wgpu::BufferUsages::COPY_SRC,
        );
        let readback = wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST;
        let counts_read = zeroed("counts readback", counts_bytes, readback);
        let scatters_read = zeroed("scatters readback", scatter_bytes, readback);

        let bind_group = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("transport bind group"),
            layout: &self.layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                        buffer: &params_buf,
                        offset: 0,
                        size: wgpu::BufferSize::new(PARAMS_BYTES),
                    }),
                },
                whole(1, &sources_buf),
                whole(2, &medium_buf),
                whole(3, &seeds_buf),
                whole(4, &counts_buf),
                whole(5, &scatters_buf),
            ],
        });

        // 3. One compute pass of bounded dispatches, then copies to the readback buffers.
        let mut encoder = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("render"),
            });
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("transport"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&self.pipeline);
            for (k, d) in dispatches.iter().enumerate() {
                pass.set_bind_group(0, &bind_group, &[(k as u64 * stride) as u32]);
                pass.dispatch_workgroups(d.count.div_ceil(WORKGROUP_SIZE), 1, 1);
            }
        }
        encoder.copy_buffer_to_buffer(&counts_buf, 0, &counts_read, 0, counts_bytes);
        encoder.copy_buffer_to_buffer(&scatters_buf, 0, &scatters_read, 0, scatter_bytes);
        self.queue.submit(Some(encoder.finish()));

        // 4. Wait, and read the tallies back.
        let (tx, rx) = mpsc::channel();
        for (which, buffer) in [(0usize, &counts_read), (1, &scatters_read)] {
            let tx = tx.clone();
            buffer.slice(..).map_async(wgpu::MapMode::Read, move |r| {
                let _ = tx.send((which, r));
            });
        }
        drop(tx);
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| {
                EngineError::Device(format!("{} failed while rendering: {e}", self.info.name))
            })?;
        self.take_errors("while rendering")?;
        for _ in 0..2 {
            match rx.recv() {
                Ok((_, Ok(()))) => {}
                Ok((which, Err(e))) => {
                    return Err(EngineError::Device(format!(
                        "reading back buffer {which} failed: {e}"
                    )));
                }
                Err(_) => {
                    return Err(EngineError::Device(
                        "the device dropped a readback".to_string(),
                    ))
                }
            }
        }
        let counts = read_words(&counts_read)?;
        let scatters = read_words(&scatters_read)?;

        for (r, row) in counts.chunks_exact(bins).enumerate() {
            let item = chunk.item_first + r / chunk.source_count;
            let source = chunk.source_first + r % chunk.source_count;
            outputs[item].counts.counts[source * bins..(source + 1) * bins].copy_from_slice(row);
        }
        for (i, pair) in scatters.chunks_exact(2).enumerate() {
            outputs[chunk.item_first + i].scatter_events +=
                u64::from(pair[0]) | (u64::from(pair[1]) << 32);
        }
        Ok(())
    }
}

impl Engine for GpuEngine {
    fn fingerprint(&self) -> EngineFingerprint {
        EngineFingerprint {
            engine: "gpu".into(),
            adapter: self.info.name.clone(),
            driver: self.info.driver.clone(),
            version: format!("{GPU_ENGINE_VERSION}+shader.{SHADER_HASH:016x}"),
        }
    }

    fn render(&self, batch: &RenderBatch<'_>) -> Result<Vec<RenderOutput>, EngineError> {
        validate_batch(batch)?;
        let _busy = match self.busy.lock() {
            Ok(guard) => guard,
            Err(poisoned) => poisoned.into_inner(),
        };
        self.render_batch(batch)
    }
}

fn whole(binding: u32, buffer: &wgpu::Buffer) -> wgpu::BindGroupEntry<'_> {
    wgpu::BindGroupEntry {
        binding,
        resource: buffer.as_entire_binding(),
    }
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

/// A mapped readback buffer's contents as 32-bit words (then unmapped).
fn read_words(buffer: &wgpu::Buffer) -> Result<Vec<u32>, EngineError> {
    let words = {
        let view = buffer
            .slice(..)
            .get_mapped_range()
            .map_err(|e| EngineError::Device(format!("cannot read back the tallies: {e}")))?;
        view.chunks_exact(4)
            .map(|b| u32::from_ne_bytes([b[0], b[1], b[2], b[3]]))
            .collect()
    };
    buffer.unmap();
    Ok(words)
}

fn concat(parts: &[Vec<u8>]) -> Vec<u8> {
    parts.concat()
}

/// A dispatch's `Params` record.
struct Params<'a> {
    geometry: &'a Geometry,
    photon_first: u32,
    photon_count: u32,
    per_invocation: u32,
    splits: u32,
    task_first: u32,
    task_count: u32,
    source_first: u32,
    source_count: u32,
}

impl Params<'_> {
    fn bytes(&self) -> Vec<u8> {
        let g = self.geometry;
        let floats = [
            g.size_mm as f32,
            g.pixel_size() as f32,
            (1.0 / g.pixel_size()) as f32,
            (1.0 / g.extent()) as f32,
            (CORNER_TOLERANCE_F32 * g.size_mm) as f32,
        ];
        let words = [
            g.grid,
            g.positions,
            g.directions,
            g.sources() as u32,
            self.photon_first,
            self.photon_count,
            self.per_invocation,
            self.splits,
            self.task_first,
            self.task_count,
            self.source_first,
            self.source_count,
            0,
            0,
            0,
        ];
        let mut out = Vec::with_capacity(PARAMS_BYTES as usize);
        floats
            .iter()
            .for_each(|f| out.extend_from_slice(&f.to_ne_bytes()));
        words
            .iter()
            .for_each(|w| out.extend_from_slice(&w.to_ne_bytes()));
        out
    }
}

/// The batch laid out for the shader, as bytes: per source, per item.
struct HostLayout {
    /// `Source` records: origin, direction (f32 of the f64 ray), start pixel.
    sources: Vec<u8>,
    /// Per item: per pixel `iy · N + ix` (`iy` from the bottom) the record (σt or −1 for opaque,
    /// uniform block level, σa/σt, HG c or −1 for g = −1).
    medium: Vec<Vec<u8>>,
    /// Per item: the seed as (low, high) words.
    seeds: Vec<Vec<u8>>,
}

impl HostLayout {
    fn new(batch: &RenderBatch<'_>) -> HostLayout {
        let geo = batch.geometry;
        let mut sources = Vec::with_capacity(geo.sources() * SOURCE_BYTES);
        for i in 0..geo.sources() {
            let ray = geo.source_ray(i);
            let (ix, iy) = start_pixel(&geo, ray.origin, ray.direction);
            let (ix, iy) = (ix as u32, iy as u32);
            for v in [
                ray.origin[0],
                ray.origin[1],
                ray.direction[0],
                ray.direction[1],
            ] {
                sources.extend_from_slice(&(v as f32).to_ne_bytes());
            }
            sources.extend_from_slice(&ix.to_ne_bytes());
            sources.extend_from_slice(&iy.to_ne_bytes());
        }
        let cells: Vec<CellMaterial> = batch.table.iter().map(CellMaterial::new).collect();
        let n = geo.grid as usize;
        let mut medium = Vec::with_capacity(batch.items.len());
        let mut seeds = Vec::with_capacity(batch.items.len());
        for RenderItem { assignment, seed } in batch.items {
            // Bottom-up pixel order, as the shader indexes pixels.
            let pixels: Vec<u16> = (0..n)
                .flat_map(|iy| assignment[(n - 1 - iy) * n..(n - iy) * n].iter().copied())
                .collect();
            let levels = uniform_block_levels(&pixels, n);
            let mut bytes = Vec::with_capacity(n * n * plan::PIXEL_BYTES as usize);
            for (&m, &level) in pixels.iter().zip(&levels) {
                // validate_batch checked every index against the table.
                let c = cells[usize::from(m)];
                for v in [c.sigma_t, f32::from(level), c.absorb, c.hg_c] {
                    bytes.extend_from_slice(&v.to_ne_bytes());
                }
            }
            medium.push(bytes);
            let mut s = Vec::with_capacity(8);
            s.extend_from_slice(&(*seed as u32).to_ne_bytes());
            s.extend_from_slice(&((*seed >> 32) as u32).to_ne_bytes());
            seeds.push(s);
        }
        HostLayout {
            sources,
            medium,
            seeds,
        }
    }
}

/// One material as the shader reads it.
#[derive(Debug, Clone, Copy)]
struct CellMaterial {
    /// σt, or −1 for opaque.
    sigma_t: f32,
    /// σa/σt (0 for transmissive and opaque).
    absorb: f32,
    /// HG c = (1−g)/(1+g), at most [`MAX_HG_C`], or −1 for g = −1 (full reversal).
    hg_c: f32,
}

impl CellMaterial {
    fn new(m: &Material) -> CellMaterial {
        let sigma_t = m.sigma_t();
        let opaque = m.is_opaque();
        CellMaterial {
            sigma_t: if opaque { -1.0 } else { sigma_t as f32 },
            absorb: if sigma_t > 0.0 && !opaque {
                (m.sigma_a / sigma_t) as f32
            } else {
                0.0
            },
            hg_c: if m.g <= -1.0 {
                -1.0
            } else {
                ((1.0 - m.g) / (1.0 + m.g)).min(MAX_HG_C) as f32
            },
        }
    }
}
