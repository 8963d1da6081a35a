//! Picking a render engine from `--engine cpu|gpu|auto`.

use anyhow::Result;
use clap::ValueEnum;
use scatterfarm_worker::{CpuEngine, Engine};

/// The `--engine` choices.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum EngineChoice {
    /// The CPU engine (rayon, every core).
    Cpu,
    /// The wgpu engine on a GPU, or lavapipe.
    Gpu,
    /// A GPU if one is found, else the CPU engine.
    Auto,
}

/// The engine for `choice`.
pub fn open(choice: EngineChoice) -> Result<Box<dyn Engine>> {
    match choice {
        EngineChoice::Cpu => Ok(Box::new(CpuEngine::new())),
        EngineChoice::Gpu => {
            anyhow::bail!("the GPU engine is not built into this version yet; use --engine cpu")
        }
        EngineChoice::Auto => {
            tracing::info!("engine auto: no GPU engine in this build, using the CPU engine");
            Ok(Box::new(CpuEngine::new()))
        }
    }
}
