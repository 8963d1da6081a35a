//! `scatterfarm bench engine`: throughput of an engine on the standard medium, as JSON.
//!
//! The standard medium is the default geometry (16 mm, 16×16 pixels, 128 positions, 9
//! directions) with every pixel `moderate`, 512 photons per source, seed 1.

use crate::engines::{self, EngineArgs, EngineChoice};
use anyhow::{Context, Result};
use clap::{Args, Subcommand, ValueEnum};
use cpu_time::ProcessTime;
use scatterfarm_worker::material::builtin_material;
use scatterfarm_worker::{Engine, Geometry, PhotonRange, RenderBatch, RenderItem};
use serde::Serialize;
use std::path::PathBuf;
use std::time::Instant;

#[path = "bench_farm.rs"]
mod farm;

#[derive(Debug, Args)]
pub struct BenchArgs {
    #[command(subcommand)]
    pub what: BenchWhat,
}

#[derive(Debug, Subcommand)]
pub enum BenchWhat {
    /// Photons and scattering events per second (and per CPU-second) on the standard medium.
    Engine(EngineBenchArgs),
    /// The quality table: reconstruct the twelve Fig. 7 scenes (and any others named) and report
    /// accuracy and cost, with the paper's search or the fast one.
    Reconstruct(ReconstructBenchArgs),
    /// What one coordinator can feed: full-size renders per second ingested and scored, and
    /// its CPU per render, with replay workers (recorded counts) on loopback.
    Farm(farm::FarmBenchArgs),
}

#[derive(Debug, Args)]
pub struct ReconstructBenchArgs {
    /// Also write the JSON here.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Keep each scene's outputs (report, maps) under this folder.
    #[arg(long)]
    pub keep: Option<PathBuf>,
    /// Scenes to run (default: fig7a … fig7l).
    #[arg(long, value_delimiter = ',')]
    pub scenes: Option<Vec<String>>,
    #[arg(long, default_value_t = 16)]
    pub grid: u32,
    #[arg(long, default_value_t = 16)]
    pub positions: u32,
    #[arg(long, default_value_t = 3)]
    pub directions: u32,
    #[arg(long, default_value_t = 1)]
    pub permutations: u32,
    #[arg(long, default_value_t = 8)]
    pub iterations: u32,
    #[arg(long, default_value_t = 512)]
    pub photons_per_iteration: u32,
    #[arg(long, value_enum, default_value_t = crate::similarity::Metric::WithinEpsilon)]
    pub metric: crate::similarity::Metric,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Photons per source of the synthesized targets (default: the search's); give the same
    /// value when comparing budgets, so every search sees the same targets.
    #[arg(long)]
    pub target_photons: Option<u32>,
    /// The search: the paper's, or the fast one.
    #[arg(long, value_enum, default_value_t = crate::params::SearchMode::Paper)]
    pub search: crate::params::SearchMode,
    #[command(flatten)]
    pub engine: EngineArgs,
}

/// One scene's row of the quality table.
#[derive(Debug, Clone, Serialize)]
pub struct QualityRow {
    pub scene: String,
    pub pixel_accuracy: Option<f64>,
    pub material_sse: Option<f64>,
    pub similarity: f64,
    pub renders: u64,
    pub photons: u64,
    pub wall_seconds: f64,
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
    /// The GPU adapter: an index or part of a name (see `scatterfarm adapters`).
    #[arg(long)]
    pub adapter: Option<String>,
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
        BenchWhat::Reconstruct(a) => run_reconstruct(a),
        BenchWhat::Farm(a) => farm::run(a),
    }
}

fn run_reconstruct(args: ReconstructBenchArgs) -> Result<()> {
    use crate::commands::reconstruct;
    let scenes = args.scenes.clone().unwrap_or_else(|| {
        (b'a'..=b'l')
            .map(|c| format!("fig7{}", c as char))
            .collect()
    });
    let engine = args.engine.open()?;
    let scratch = tempfile::tempdir().context("cannot create a scratch folder")?;
    let mut rows = Vec::new();
    eprintln!(
        "{:<8} {:>9} {:>9} {:>10} {:>8} {:>14} {:>9}",
        "scene", "accuracy", "SSE", "similarity", "renders", "photons", "seconds"
    );
    for scene in &scenes {
        let out = match &args.keep {
            Some(dir) => dir.join(scene),
            None => scratch.path().join(scene),
        };
        // The paper searched 7i with all six materials.
        let dictionary = (scene == "fig7i").then(|| {
            scatterfarm_worker::material::BUILTIN_MATERIALS
                .iter()
                .map(|(n, _)| n.to_string())
                .collect()
        });
        let params = crate::params::JobParams {
            scene: Some(scene.clone()),
            dictionary,
            permutations: args.permutations,
            iterations: args.iterations,
            photons_per_iteration: args.photons_per_iteration,
            metric: args.metric,
            grid: Some(args.grid),
            positions: Some(args.positions),
            directions: Some(args.directions),
            seed: args.seed,
            search: args.search,
            target_photons: args.target_photons,
            ..Default::default()
        };
        let report = reconstruct::run_in_process(&params, engine.as_ref(), &out, true)?;
        let row = QualityRow {
            scene: scene.clone(),
            pixel_accuracy: report.pixel_accuracy,
            material_sse: report.material_sse,
            similarity: report.similarity,
            renders: report.renders,
            photons: report.photons,
            wall_seconds: report.wall_seconds,
        };
        eprintln!(
            "{:<8} {:>8.1}% {:>9.3} {:>10.4} {:>8} {:>14} {:>9.1}",
            row.scene,
            row.pixel_accuracy.unwrap_or(f64::NAN) * 100.0,
            row.material_sse.unwrap_or(f64::NAN),
            row.similarity,
            row.renders,
            row.photons,
            row.wall_seconds
        );
        rows.push(row);
    }
    let json = serde_json::json!({
        "engine": engine.fingerprint().to_string(),
        "geometry": { "grid": args.grid, "positions": args.positions, "directions": args.directions },
        "permutations": args.permutations,
        "iterations": args.iterations,
        "photons_per_iteration": args.photons_per_iteration,
        "metric": args.metric,
        "search": args.search,
        "seed": args.seed,
        "scenes": rows,
        "total_photons": rows.iter().map(|r| r.photons).sum::<u64>(),
        "total_wall_seconds": rows.iter().map(|r| r.wall_seconds).sum::<f64>(),
        "mean_pixel_accuracy": rows.iter().filter_map(|r| r.pixel_accuracy).sum::<f64>() / rows.len().max(1) as f64,
    });
    emit(&json, args.out.as_deref())
}

fn run_engine(args: EngineBenchArgs) -> Result<()> {
    anyhow::ensure!(args.photons > 0, "--photons must be at least 1");
    let measure_choice = |choice| -> Result<EngineBench> {
        let adapter = if choice == EngineChoice::Cpu {
            None
        } else {
            args.adapter.as_deref()
        };
        let engine = engines::open(choice, adapter)?;
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
    emit(&json, args.out.as_deref())
}

/// Prints the JSON on stdout and, when asked, writes it to `out` as well.
fn emit(json: &serde_json::Value, out: Option<&std::path::Path>) -> Result<()> {
    let text = serde_json::to_string_pretty(json)?;
    println!("{text}");
    if let Some(out) = out {
        crate::observation::write_atomically(out, |w| Ok(w.write_all(text.as_bytes())?))?;
        eprintln!("wrote {}", out.display());
    }
    Ok(())
}
