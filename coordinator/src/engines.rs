//! Picking a render engine from `--engine cpu|gpu|auto` and `--adapter`, and rendering in
//! photon chunks (for progress) with any engine.

use anyhow::{ensure, Context, Result};
use clap::ValueEnum;
use scatterfarm_worker::gpu::{AdapterSelector, GpuEngine};
use scatterfarm_worker::{
    CountMatrix, CpuEngine, Engine, Geometry, Material, PhotonRange, RenderBatch, RenderItem,
};

/// The `--engine` choices.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum EngineChoice {
    /// The CPU engine (rayon, every core).
    Cpu,
    /// The wgpu engine on a GPU, or on lavapipe where there is no GPU.
    Gpu,
    /// The first discrete or integrated GPU, else lavapipe, else the CPU engine.
    Auto,
}

/// `--engine` and `--adapter`, for every command that renders.
#[derive(Debug, Clone, clap::Args)]
pub struct EngineArgs {
    /// Which engine renders.
    #[arg(long, value_enum, default_value_t = EngineChoice::Auto)]
    pub engine: EngineChoice,
    /// The GPU adapter: an index or part of a name (see `scatterfarm adapters`).
    #[arg(long)]
    pub adapter: Option<String>,
}

impl EngineArgs {
    /// The chosen engine.
    pub fn open(&self) -> Result<Box<dyn Engine>> {
        open(self.engine, self.adapter.as_deref())
    }
}

/// The engine for `choice`; `adapter` (an index or part of a name, see `scatterfarm adapters`)
/// picks the GPU adapter.
pub fn open(choice: EngineChoice, adapter: Option<&str>) -> Result<Box<dyn Engine>> {
    let selector = match adapter {
        Some(a) => a
            .parse::<AdapterSelector>()
            .with_context(|| format!("--adapter {a}"))?,
        None => AdapterSelector::Auto,
    };
    match choice {
        EngineChoice::Cpu => {
            ensure!(
                adapter.is_none(),
                "--adapter applies to the GPU engine; drop it or use --engine gpu"
            );
            Ok(Box::new(CpuEngine::new()))
        }
        EngineChoice::Gpu => {
            let engine = GpuEngine::new(&selector).context(
                "cannot start the GPU engine (on a machine without a GPU, install Mesa's Vulkan \
                 drivers, e.g. Debian's mesa-vulkan-drivers, or use --engine cpu)",
            )?;
            tracing::info!("engine gpu: {}", engine.adapter().name);
            Ok(Box::new(engine))
        }
        EngineChoice::Auto => match GpuEngine::new(&selector) {
            Ok(engine) => {
                tracing::info!(
                    "engine auto: GPU engine on {} ({})",
                    engine.adapter().name,
                    engine.adapter().device_type
                );
                Ok(Box::new(engine))
            }
            Err(e) => {
                tracing::info!("engine auto: no usable GPU adapter ({e}); using the CPU engine");
                Ok(Box::new(CpuEngine::new()))
            }
        },
    }
}

/// What a chunked render produced: one count matrix per item, and the scattering events.
#[derive(Debug, Clone)]
pub struct Rendered {
    pub counts: Vec<CountMatrix>,
    pub scatter_events: u64,
}

/// Renders `items` over photons `[0, photons)` in chunks of `chunk` photons per source, calling
/// `on_chunk` with each chunk's size. By batch additivity the sum equals one single render.
pub fn render_in_chunks(
    engine: &dyn Engine,
    geometry: Geometry,
    table: &[Material],
    items: &[RenderItem],
    photons: u32,
    chunk: u32,
    on_chunk: &mut dyn FnMut(u32),
) -> Result<Rendered> {
    render_range(engine, geometry, table, items, 0..photons, chunk, on_chunk)
}

/// Renders `items` over the photons `range` of every source, in chunks of `chunk` photons.
pub fn render_range(
    engine: &dyn Engine,
    geometry: Geometry,
    table: &[Material],
    items: &[RenderItem],
    range: std::ops::Range<u32>,
    chunk: u32,
    on_chunk: &mut dyn FnMut(u32),
) -> Result<Rendered> {
    ensure!(chunk > 0, "a render chunk needs at least one photon");
    let mut counts = vec![CountMatrix::zeros(geometry.sources(), geometry.bins()); items.len()];
    let mut scatter_events = 0;
    let mut first = range.start;
    while first < range.end {
        let count = chunk.min(range.end - first);
        let batch = RenderBatch {
            geometry,
            table,
            items,
            photons: PhotonRange { first, count },
        };
        let outputs = engine.render(&batch)?;
        ensure!(
            outputs.len() == items.len(),
            "the engine returned {} results for {} items",
            outputs.len(),
            items.len()
        );
        for (total, out) in counts.iter_mut().zip(&outputs) {
            total.add(&out.counts)?;
            scatter_events += out.scatter_events;
        }
        first += count;
        on_chunk(count);
    }
    Ok(Rendered {
        counts,
        scatter_events,
    })
}
