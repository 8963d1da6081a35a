//! [`GpuEngine`]: the engine on one adapter, and a render batch's trip through it.
//!
//! A render, step by step (the style of wgpu's `hello_compute`):
//! 1. check the batch and lay it out for the shader on the host ([`HostLayout`]): per source its
//!    ray (computed in f64, uploaded as f32) and start pixel (the grid-line rule of
//!    [`crate::rules`], in f64); per item and pixel the record (σt or −1 for opaque,
//!    uniform-block level, σa/σt, HG c); per item its seed;
//! 2. cut it into chunks that fit the device's buffer limits ([`dispatch_plan::chunks`]) —
//!    usually one, so the whole batch is one submission;
//! 3. per chunk, one submission ([`submission::render_chunk`]): upload, record one compute pass of
//!    several bounded dispatches (each reads its own parameter record through a dynamic uniform
//!    offset), copy the tallies to staging buffers, submit, wait, read back into each item's
//!    [`CountMatrix`].
//!
//! A differential render (per-pixel tallies and every change's weights) takes the same device
//! through the shader's `differential` entry point ([`super::differential`]).
//!
//! The device and pipeline are set up once, apart from the work ([`GpuDevice`]). Device errors
//! are caught by wgpu's uncaptured-error handler and returned as [`EngineError::Device`]; nothing
//! the device or the batch does can panic here.

use super::adapters::{choose, enumerate, new_instance, AdapterInfo, AdapterSelector};
use super::device::{GpuDevice, WORKGROUP_SIZE};
use super::dispatch_plan::{self, Shape};
use super::records::HostLayout;
use super::submission::Rendered;
use super::{differential, submission, SHADER_HASH};
use scatterfarm_model::engine::{
    validate_batch, CountMatrix, Engine, EngineError, EngineFingerprint, RenderBatch, RenderOutput,
};
use scatterfarm_model::{Change, DifferentialOutput, Geometry, Material, PhotonRange, RenderItem};
use std::fmt;
use std::sync::Mutex;

/// Bumped whenever a change outside the shader changes this engine's counts (a shader change
/// changes [`SHADER_HASH`], which the fingerprint carries too).
pub const GPU_ENGINE_VERSION: &str = "gpu-2";

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
    gpu: GpuDevice,
    /// The shader multiplies with 64-bit integers.
    int64: bool,
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

    /// The engine on `adapter`: checks the workgroup size fits, then opens the device and
    /// builds the pipeline ([`GpuDevice::open`]).
    fn open(
        adapter: &wgpu::Adapter,
        info: AdapterInfo,
        allow_int64: bool,
    ) -> Result<GpuEngine, EngineError> {
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
        let gpu = GpuDevice::open(adapter, &info, int64)?;
        let tuning = Tuning::for_device(info.is_cpu());
        Ok(GpuEngine {
            info,
            gpu,
            int64,
            busy: Mutex::new(()),
            tuning,
        })
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
        let limit = self.gpu.buffer_limit(self.tuning.max_buffer_bytes);
        let chunks = dispatch_plan::chunks(shape, limit).map_err(|why| {
            EngineError::Device(format!("render too large for {}: {why}", self.info.name))
        })?;
        let per_invocation = dispatch_plan::photons_per_invocation(
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
        self.gpu.take_errors("before this render")?;
        for chunk in &chunks {
            let mut per = per_invocation;
            while let Rendered::CutShort(cut) = submission::render_chunk(
                &self.gpu,
                self.tuning.photons_per_dispatch,
                batch,
                &host,
                chunk,
                per,
                &mut outputs,
            )? {
                per = submission::fewer_per_invocation(&self.gpu, per, cut)?;
            }
        }
        Ok(outputs)
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
        let _busy = self.lock();
        self.render_batch(batch)
    }

    /// On a GPU. A CPU device (lavapipe) renders differentially too, but does not offer it: there
    /// a sweep's differential render of fig7a cost 29 plain renders, the CPU engine's 2
    /// (`tests/bench/tallies/`), so such jobs go to the CPU engine (in process) or to CPU-engine
    /// workers. [`Engine::render_differential`] runs on either.
    fn renders_differentially(&self) -> bool {
        !self.info.is_cpu()
    }

    fn render_differential(
        &self,
        geometry: Geometry,
        table: &[Material],
        item: &RenderItem,
        photons: PhotonRange,
        changes: &[Change],
    ) -> Result<DifferentialOutput, EngineError> {
        let _busy = self.lock();
        differential::render(
            &self.gpu,
            &self.tuning,
            geometry,
            table,
            item,
            photons,
            changes,
        )
    }
}

impl GpuEngine {
    /// The device, one render at a time.
    fn lock(&self) -> std::sync::MutexGuard<'_, ()> {
        match self.busy.lock() {
            Ok(guard) => guard,
            Err(poisoned) => poisoned.into_inner(),
        }
    }
}
