//! Picking a render engine from `--engine cpu|gpu|auto` and `--adapter`.

use anyhow::{ensure, Context, Result};
use clap::ValueEnum;
use scatterfarm_engines::gpu::{AdapterSelector, GpuEngine};
use scatterfarm_engines::CpuEngine;
use scatterfarm_job::plan::Plan;
use scatterfarm_model::Engine;
use scatterfarm_search::refine::Screen;

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

    /// The chosen engine for renders of `plan`: where its search renders differentially and
    /// the chosen engine cannot (an engine without per-pixel tallies), the CPU engine, said in a warning,
    /// so the job does not fail when its refinement starts.
    pub fn open_for(&self, plan: &Plan) -> Result<Box<dyn Engine>> {
        let engine = self.open()?;
        if renders_differentially(plan) && !engine.renders_differentially() {
            tracing::warn!(
                "engine {} does not render differentially (refine_screen = \"differential\"); \
                 the CPU engine renders this job",
                engine.fingerprint().key()
            );
            return Ok(Box::new(CpuEngine::new()));
        }
        Ok(engine)
    }
}

/// Whether `plan`'s search makes differential renders.
pub fn renders_differentially(plan: &Plan) -> bool {
    plan.search
        .config()
        .refine
        .as_ref()
        .is_some_and(|r| r.screen == Screen::Differential)
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
