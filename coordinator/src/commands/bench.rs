//! `scatterfarm bench engine`: throughput of an engine on the standard medium, as JSON.
//!
//! The standard medium is the default geometry (16 mm, 16×16 pixels, 128 positions, 9
//! directions) with every pixel `moderate`, 512 photons per source, seed 1.

use crate::engines::{self, EngineChoice};
use anyhow::{Context, Result};
use clap::{Args, Subcommand, ValueEnum};
use cpu_time::ProcessTime;
use scatterfarm_worker::material::builtin_material;
use scatterfarm_worker::{Engine, Geometry, PhotonRange, RenderBatch, RenderItem};
use serde::Serialize;
use std::path::PathBuf;
use std::time::Instant;

#[derive(Debug, Args)]
pub struct BenchArgs {
    #[command(subcommand)]
    pub what: BenchWhat,
}

#[derive(Debug, Subcommand)]
pub enum BenchWhat {
    /// Photons and scattering events per second (and per CPU-second) on the standard medium.
    Engine(EngineBenchArgs),
}

/// Engines `bench engine` can measure.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum BenchEngine {
    Cpu,
    Gpu,
    Auto,
    /// CPU and GPU in one run, with their ratio.
    All,
}

#[derive(Debug, Args)]
pub struct EngineBenchArgs {
    #[arg(long, value_enum, default_value_t = BenchEngine::Cpu)]
    pub engine: BenchEngine,
    /// Also write the JSON here.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Photons per source.
    #[arg(long, default_value_t = 512)]
    pub photons: u32,
}

/// One engine's figures.
#[derive(Debug, Clone, Serialize)]
pub struct EngineBench {
    pub engine: String,
    pub adapter: String,
    pub photons: u64,
    pub wall_seconds: f64,
    pub cpu_seconds: f64,
    pub photons_per_second: f64,
    pub scatter_events_per_second: f64,
    pub scatter_events_per_cpu_second: f64,
}

/// Renders the standard medium once (after a small warm-up) and measures it.
pub fn measure(engine: &dyn Engine, photons: u32) -> Result<EngineBench> {
    let geometry = Geometry::default();
    let moderate =
        builtin_material("moderate").context("the built-in dictionary lacks moderate")?;
    let items = [RenderItem {
        assignment: vec![0; geometry.pixels()],
        seed: 1,
    }];
    let table = [moderate];
    let batch = |first, count| RenderBatch {
        geometry,
        table: &table,
        items: &items,
        photons: PhotonRange { first, count },
    };
    // Warm-up: thread pools, shader compilation.
    engine.render(&batch(0, 4))?;
    let cpu0 = ProcessTime::now();
    let wall0 = Instant::now();
    let out = engine.render(&batch(0, photons))?;
    let wall = wall0.elapsed().as_secs_f64();
    let cpu = cpu0.elapsed().as_secs_f64();
    let events: u64 = out.iter().map(|o| o.scatter_events).sum();
    let launched = u64::from(photons) * geometry.sources() as u64;
    let fp = engine.fingerprint();
    Ok(EngineBench {
        engine: fp.engine,
        adapter: fp.adapter,
        photons: launched,
        wall_seconds: wall,
        cpu_seconds: cpu,
        photons_per_second: launched as f64 / wall,
        scatter_events_per_second: events as f64 / wall,
        scatter_events_per_cpu_second: events as f64 / cpu.max(1e-9),
    })
}

pub fn run(args: BenchArgs) -> Result<()> {
    match args.what {
        BenchWhat::Engine(a) => run_engine(a),
    }
}

fn run_engine(args: EngineBenchArgs) -> Result<()> {
    anyhow::ensure!(args.photons > 0, "--photons must be at least 1");
    let measure_choice = |choice| -> Result<EngineBench> {
        let engine = engines::open(choice)?;
        let result = measure(engine.as_ref(), args.photons)?;
        eprintln!(
            "{} ({}): {:.2} M photons/s, {:.2} M scattering events per CPU-second",
            result.engine,
            result.adapter,
            result.photons_per_second / 1e6,
            result.scatter_events_per_cpu_second / 1e6
        );
        Ok(result)
    };
    let json = match args.engine {
        BenchEngine::Cpu => serde_json::to_value(measure_choice(EngineChoice::Cpu)?)?,
        BenchEngine::Gpu => serde_json::to_value(measure_choice(EngineChoice::Gpu)?)?,
        BenchEngine::Auto => serde_json::to_value(measure_choice(EngineChoice::Auto)?)?,
        BenchEngine::All => {
            let cpu = measure_choice(EngineChoice::Cpu)?;
            let gpu = measure_choice(EngineChoice::Gpu)?;
            serde_json::json!({
                "engines": [cpu, gpu],
                "gpu_over_cpu_photons_per_second": gpu.photons_per_second / cpu.photons_per_second,
                "gpu_over_cpu_scatter_events_per_cpu_second":
                    gpu.scatter_events_per_cpu_second / cpu.scatter_events_per_cpu_second,
            })
        }
    };
    let text = serde_json::to_string_pretty(&json)?;
    println!("{text}");
    if let Some(out) = &args.out {
        crate::observation::write_atomically(out, |w| Ok(w.write_all(text.as_bytes())?))?;
        eprintln!("wrote {}", out.display());
    }
    Ok(())
}
