//! `scatterfarm bench engine`: throughput of an engine on the standard medium, as JSON.
//!
//! The standard medium is the default geometry (16 mm, 16×16 pixels, 128 positions, 9
//! directions) with every pixel `moderate`, 512 photons per source, seed 1.

use crate::engines::{self, EngineArgs, EngineChoice};
use anyhow::{Context, Result};
use clap::{Args, Subcommand, ValueEnum};
use cpu_time::ProcessTime;
use scatterfarm_model::material::builtin_material;
use scatterfarm_model::{Engine, Geometry, PhotonRange, RenderBatch, RenderItem};
use serde::Serialize;
use std::path::PathBuf;
use std::time::Instant;

#[path = "bench_farm/mod.rs"]
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
    /// Every parser of untrusted input under generated and mutated inputs: panics, accepted
    /// and refused inputs and peak memory per parser.
    Fuzz(super::bench_fuzz::FuzzArgs),
    /// What a differential render costs beside a plain render of the same photons: per-pixel
    /// tallies alone, one change, and a whole sweep's single-pixel changes with their scoring.
    Tallies(super::bench_tallies::TalliesBenchArgs),
}

#[derive(Debug, Args)]
pub struct ReconstructBenchArgs {
    /// Also write the JSON here.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Keep each scene's outputs (report, maps) under this folder (SEED/SCENE).
    #[arg(long)]
    pub keep: Option<PathBuf>,
    /// Scenes to run (default: fig7a … fig7l and phantom16).
    #[arg(long, value_delimiter = ',')]
    pub scenes: Option<Vec<String>>,
    /// The search grid (default: each scene's own, the truth's resolution).
    #[arg(long)]
    pub grid: Option<u32>,
    /// Boundary positions and directions of target and search (the default, 32 × 5, carries
    /// the objects' information at 200 000 target photons).
    #[arg(long, default_value_t = 32)]
    pub positions: u32,
    #[arg(long, default_value_t = 5)]
    pub directions: u32,
    #[arg(long, default_value_t = 1)]
    pub permutations: u32,
    #[arg(long, default_value_t = 8)]
    pub iterations: u32,
    #[arg(long, default_value_t = 512)]
    pub photons_per_iteration: u32,
    /// The metric (default: the search mode's).
    #[arg(long, value_name = "METRIC", value_parser = crate::args::choice::choice::<scatterfarm_search::similarity::Metric>())]
    pub metric: Option<scatterfarm_search::similarity::Metric>,
    /// Job seeds, comma-separated: every scene runs once per seed (pixel accuracy moves in
    /// whole pixels, so compare searches over several).
    #[arg(
        long = "seeds",
        alias = "seed",
        value_delimiter = ',',
        default_value = "1"
    )]
    pub seeds: Vec<u64>,
    /// Photons per source of the synthesized targets; keep it when comparing searches, so
    /// every search sees the same targets.
    #[arg(long, default_value_t = 200_000)]
    pub target_photons: u32,
    /// The search: the likelihood search (the reconstructions' default), the fast one, or the
    /// paper's.
    #[arg(
        long,
        default_value_t = scatterfarm_job::options::SearchMode::Likelihood,
        value_parser = crate::args::choice::choice::<scatterfarm_job::options::SearchMode>()
    )]
    pub search: scatterfarm_job::options::SearchMode,
    /// Photons per source of the truth check after each run (the truth and the map found on
    /// common fresh photons: information or search?); 0 skips it.
    #[arg(long, default_value_t = 102_400)]
    pub check_photons: u32,
    /// Any other job-file key, as KEY=VALUE in TOML (e.g. race_share=0.5,
    /// common_random_numbers=false, level_photons=[400,200]); repeatable.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub set: Vec<String>,
    #[command(flatten)]
    pub engine: EngineArgs,
}

impl ReconstructBenchArgs {
    /// The job parameters of `scene` under `seed`: the bench's flags, then every `--set`.
    fn params(&self, scene: &str, seed: u64) -> Result<scatterfarm_job::spec::JobSpec> {
        let mut keys = toml::Table::new();
        let mut put = |k: &str, v: toml::Value| {
            keys.insert(k.to_string(), v);
        };
        put("scene", scene.into());
        // The paper searched 7i with all six materials.
        if scene == "fig7i" {
            let all: Vec<toml::Value> = scatterfarm_model::material::BUILTIN_MATERIALS
                .iter()
                .map(|(n, _)| toml::Value::from(*n))
                .collect();
            put("dictionary", toml::Value::Array(all));
        }
        put("permutations", i64::from(self.permutations).into());
        put("iterations", i64::from(self.iterations).into());
        put(
            "photons_per_iteration",
            i64::from(self.photons_per_iteration).into(),
        );
        if let Some(grid) = self.grid {
            put("grid", i64::from(grid).into());
        }
        put("positions", i64::from(self.positions).into());
        put("directions", i64::from(self.directions).into());
        put(
            "seed",
            i64::try_from(seed).context("--seeds: too large")?.into(),
        );
        put("search", toml::Value::try_from(self.search)?);
        if let Some(m) = self.metric {
            put("metric", toml::Value::try_from(m)?);
        }
        put("target_photons", i64::from(self.target_photons).into());
        for pair in &self.set {
            let (k, v) = pair
                .split_once('=')
                .with_context(|| format!("--set {pair}: expected KEY=VALUE"))?;
            let (k, v) = (k.trim(), v.trim());
            // A bare word is a string (`search=fast`).
            let value = toml::from_str::<toml::Table>(&format!("v = {v}"))
                .ok()
                .and_then(|mut t| t.remove("v"))
                .unwrap_or_else(|| toml::Value::from(v));
            put(k, value);
        }
        let text = toml::to_string(&keys)?;
        scatterfarm_job::spec::JobSpec::from_toml(&text, std::path::Path::new("--set"))
    }
}

/// The folder of a scene's run: a built-in name as it is, a scene file by its file stem (a
/// scene named by an absolute path must not replace the whole output path).
fn run_folder(scene: &str) -> String {
    let stem = std::path::Path::new(scene)
        .file_stem()
        .and_then(|s| s.to_str())
        .unwrap_or("scene");
    stem.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' {
                c
            } else {
                '_'
            }
        })
        .collect()
}

/// One scene's row of the quality table.
#[derive(Debug, Clone, Serialize)]
pub struct QualityRow {
    pub scene: String,
    pub seed: u64,
    pub pixel_accuracy: Option<f64>,
    /// The pixel accuracy of the search's level-0 map (one material everywhere): where a
    /// search that changed nothing after level 0 would end. On scenes that are mostly
    /// background a noisy search can end below it.
    pub level0_pixel_accuracy: Option<f64>,
    pub material_sse: Option<f64>,
    pub similarity: f64,
    pub requests: u64,
    pub renders: u64,
    /// Batches that needed renders: renders / batches run at once on average.
    pub batches: u64,
    /// Photons the search consumed (all sources).
    pub photons: u64,
    /// Photons engines ran: search, target and calibration renders.
    pub photons_simulated: u64,
    pub wall_seconds: f64,
    /// The truth's likelihood score minus the map's, rendered on common fresh photons
    /// (`--check-photons`), and that margin in paired standard errors: a clearly positive
    /// margin on a map that misses pixels means the search stopped short of what the target
    /// tells; a margin near 0 means the target cannot tell the two apart.
    pub truth_margin: Option<f64>,
    pub truth_margin_z: Option<f64>,
    /// The truth's one-pixel neighbours on the check's photons (where the engine renders
    /// differentially): how many were estimated, and how many of those the truth does not
    /// beat by 2 paired standard errors (the target cannot tell them from the truth).
    pub neighbours_estimated: Option<usize>,
    pub neighbours_unresolved: Option<usize>,
    /// The map's wrong pixels, split by their one-pixel neighbour of the truth: `told`, the
    /// truth beats it by 2 standard errors or more (the search missed it); `untold`, it does
    /// not (the information is not there at these photons); the rest were not estimated.
    pub wrong_pixels: Option<usize>,
    pub wrong_told: Option<usize>,
    pub wrong_untold: Option<usize>,
    /// The map found's one-pixel changes on the check's photons: how many beat it by 2 paired
    /// standard errors (0: a local optimum of single-pixel changes, only larger moves leave
    /// it), how many of those set a pixel to the truth's material, and the best one's z.
    pub escapes: Option<usize>,
    pub escapes_toward_truth: Option<usize>,
    pub escape_best_z: Option<f64>,
    /// The refinement's sweeps, the changes they tried, and of those the ones a differential
    /// render estimated (each would be a render of its own with direct screening).
    pub sweeps: usize,
    pub changes_tried: u64,
    pub changes_reweighted: u64,
    /// The refinement's growth rounds (`refine_grow`), in order.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub growth: Vec<GrowthRound>,
}

/// A growth round of a bench run's refinement.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct GrowthRound {
    pub sweep: u32,
    /// Where no grown map won: the best one's paired z against the map it grew from.
    pub grown_z: Option<f64>,
    /// How the trial the round started ended: its map kept or given back (`None`: no trial
    /// ran, or the run stopped first).
    pub trial_kept: Option<bool>,
}

/// The growth rounds of a refinement's sweeps, each with the end of the trial it started: a
/// trial's end belongs to the last round before it.
fn growth_rounds(sweeps: &[scatterfarm_job::report::SweepReport]) -> Vec<GrowthRound> {
    let mut rounds: Vec<GrowthRound> = Vec::new();
    for s in sweeps.iter().filter(|s| s.growth) {
        match s.trial_kept {
            None => rounds.push(GrowthRound {
                sweep: s.sweep,
                grown_z: s.grown_z,
                trial_kept: None,
            }),
            Some(kept) => {
                if let Some(round) = rounds.last_mut() {
                    round.trial_kept = Some(kept);
                }
            }
        }
    }
    rounds
}

/// A scene's rows averaged over the seeds.
#[derive(Debug, Clone, Serialize)]
pub struct SceneSummary {
    pub scene: String,
    pub seeds: usize,
    pub mean_pixel_accuracy: Option<f64>,
    pub min_pixel_accuracy: Option<f64>,
    pub mean_level0_pixel_accuracy: Option<f64>,
    pub mean_material_sse: Option<f64>,
    pub photons: u64,
    pub photons_simulated: u64,
    pub renders: u64,
    pub wall_seconds: f64,
}

fn summarize(scene: &str, rows: &[&QualityRow]) -> SceneSummary {
    let acc: Vec<f64> = rows.iter().filter_map(|r| r.pixel_accuracy).collect();
    let level0: Vec<f64> = rows
        .iter()
        .filter_map(|r| r.level0_pixel_accuracy)
        .collect();
    let sse: Vec<f64> = rows.iter().filter_map(|r| r.material_sse).collect();
    let mean = |v: &[f64]| (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64);
    SceneSummary {
        scene: scene.to_string(),
        seeds: rows.len(),
        mean_pixel_accuracy: mean(&acc),
        min_pixel_accuracy: acc.iter().copied().reduce(f64::min),
        mean_level0_pixel_accuracy: mean(&level0),
        mean_material_sse: mean(&sse),
        photons: rows.iter().map(|r| r.photons).sum(),
        photons_simulated: rows.iter().map(|r| r.photons_simulated).sum(),
        renders: rows.iter().map(|r| r.renders).sum(),
        wall_seconds: rows.iter().map(|r| r.wall_seconds).sum(),
    }
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
        BenchWhat::Fuzz(a) => super::bench_fuzz::run(a),
        BenchWhat::Tallies(a) => super::bench_tallies::run(a),
    }
}

fn run_reconstruct(args: ReconstructBenchArgs) -> Result<()> {
    use crate::commands::reconstruct;
    let scenes = args.scenes.clone().unwrap_or_else(|| {
        (b'a'..=b'l')
            .map(|c| format!("fig7{}", c as char))
            .chain(["phantom16".to_string()])
            .collect()
    });
    anyhow::ensure!(!args.seeds.is_empty(), "--seeds: give at least one seed");
    // Every parameter set is checked before the first (long) run.
    let mut plans = Vec::new();
    for scene in &scenes {
        let params = args.params(scene, args.seeds[0])?;
        let inputs = scatterfarm_job::inputs::Inputs::gather(&params, std::path::Path::new("."))?;
        plans.push(
            scatterfarm_job::plan::Plan::resolve(&params, &inputs)
                .with_context(|| format!("scene {scene}"))?,
        );
    }
    let engine = match plans.iter().find(|p| engines::renders_differentially(p)) {
        Some(plan) => args.engine.open_for(plan)?,
        None => args.engine.open()?,
    };
    let scratch = tempfile::tempdir().context("cannot create a scratch folder")?;
    let mut rows = Vec::new();
    eprintln!(
        "{:<10} {:>5} {:>9} {:>8} {:>9} {:>10} {:>8} {:>14} {:>9} {:>8} {:>12} {:>8}",
        "scene",
        "seed",
        "accuracy",
        "level 0",
        "SSE",
        "similarity",
        "renders",
        "photons",
        "seconds",
        "truth z",
        "wrong (told)",
        "escapes"
    );
    let mut config = None;
    for &seed in &args.seeds {
        for scene in &scenes {
            let out = args
                .keep
                .as_deref()
                .unwrap_or(scratch.path())
                .join(seed.to_string())
                .join(run_folder(scene));
            let params = args.params(scene, seed)?;
            let (report, check) = reconstruct::run_checked(
                &params,
                engine.as_ref(),
                &out,
                true,
                (args.check_photons > 0).then_some(args.check_photons),
            )
            .with_context(|| format!("{scene}, seed {seed}"))?;
            let neighbours = check.as_ref().and_then(|c| c.neighbours.as_ref());
            let escapes = check.as_ref().and_then(|c| c.escapes.as_ref());
            let row = QualityRow {
                scene: scene.clone(),
                seed,
                pixel_accuracy: report.pixel_accuracy,
                level0_pixel_accuracy: report.levels.first().and_then(|l| l.pixel_accuracy),
                material_sse: report.material_sse,
                similarity: report.similarity,
                requests: report.requests,
                renders: report.renders,
                batches: report.batches,
                photons: report.photons,
                photons_simulated: report.photons_simulated,
                wall_seconds: report.wall_seconds,
                truth_margin: check.as_ref().map(|c| c.margin),
                truth_margin_z: check.as_ref().map(|c| c.z()),
                neighbours_estimated: neighbours.map(|n| n.estimated),
                neighbours_unresolved: neighbours.map(|n| n.unresolved),
                wrong_pixels: neighbours.map(|n| n.wrong.len()),
                wrong_told: neighbours.map(|n| n.wrong_resolved()),
                wrong_untold: neighbours.map(|n| n.wrong_unresolved()),
                escapes: escapes.map(|e| e.beating),
                escapes_toward_truth: escapes.map(|e| e.toward_truth),
                escape_best_z: escapes.and_then(|e| e.best_z),
                sweeps: report.refinement.len(),
                changes_tried: report.refinement.iter().map(|s| u64::from(s.tried)).sum(),
                changes_reweighted: report
                    .refinement
                    .iter()
                    .map(|s| u64::from(s.reweighted))
                    .sum(),
                growth: growth_rounds(&report.refinement),
            };
            eprintln!(
                "{:<10} {:>5} {:>8.1}% {:>7.1}% {:>9.3} {:>10.4} {:>8} {:>14} {:>9.1} {:>8.1} {:>12} {:>8}",
                row.scene,
                seed,
                row.pixel_accuracy.unwrap_or(f64::NAN) * 100.0,
                row.level0_pixel_accuracy.unwrap_or(f64::NAN) * 100.0,
                row.material_sse.unwrap_or(f64::NAN),
                row.similarity,
                row.renders,
                row.photons,
                row.wall_seconds,
                row.truth_margin_z.unwrap_or(f64::NAN),
                match (row.wrong_pixels, row.wrong_told) {
                    (Some(w), Some(t)) => format!("{w} ({t})"),
                    _ => "-".to_string(),
                },
                match (row.escapes, row.escapes_toward_truth) {
                    (Some(e), Some(t)) => format!("{e} ({t})"),
                    _ => "-".to_string(),
                }
            );
            config.get_or_insert(report.configuration);
            rows.push(row);
        }
    }
    let summaries: Vec<SceneSummary> = scenes
        .iter()
        .map(|scene| {
            let of: Vec<&QualityRow> = rows.iter().filter(|r| &r.scene == scene).collect();
            summarize(scene, &of)
        })
        .collect();
    let all: Vec<&QualityRow> = rows.iter().collect();
    let total = summarize("total", &all);
    eprintln!(
        "mean pixel accuracy {:.1} % over {} runs (level 0: {:.1} %); {} photons consumed, {} simulated",
        total.mean_pixel_accuracy.unwrap_or(f64::NAN) * 100.0,
        rows.len(),
        total.mean_level0_pixel_accuracy.unwrap_or(f64::NAN) * 100.0,
        total.photons,
        total.photons_simulated
    );
    let json = serde_json::json!({
        "engine": engine.fingerprint().key(),
        "geometry": { "grid": args.grid, "positions": args.positions, "directions": args.directions },
        "permutations": args.permutations,
        "iterations": args.iterations,
        "photons_per_iteration": args.photons_per_iteration,
        "search": args.search,
        "set": args.set,
        "seeds": args.seeds,
        "configuration": config,
        "runs": rows,
        "scenes": summaries,
        "total": total,
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
pub(super) fn emit(json: &serde_json::Value, out: Option<&std::path::Path>) -> Result<()> {
    let text = serde_json::to_string_pretty(json)?;
    println!("{text}");
    if let Some(out) = out {
        scatterfarm_job::observation::write_atomically(out, |w| Ok(w.write_all(text.as_bytes())?))?;
        eprintln!("wrote {}", out.display());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use scatterfarm_job::report::SweepReport;

    fn sweep(
        sweep: u32,
        growth: bool,
        trial_kept: Option<bool>,
        grown_z: Option<f64>,
    ) -> SweepReport {
        SweepReport {
            sweep,
            tried: 1,
            reweighted: 0,
            candidates: 0,
            changed: 0,
            similarity: 0.0,
            pixel_accuracy: None,
            growth,
            trial_kept,
            grown_z,
        }
    }

    #[test]
    fn a_trial_end_belongs_to_the_round_before_it() {
        let sweeps = [
            sweep(3, false, None, None),
            // A round with no trial (below the floor), then one whose trial is kept.
            sweep(4, true, None, Some(-12.0)),
            sweep(5, true, None, Some(-4.0)),
            sweep(6, false, None, None),
            sweep(7, true, Some(true), None),
            // A round whose trial the run's end cut short.
            sweep(8, true, None, Some(-6.0)),
        ];
        let round = |sweep, grown_z, trial_kept| GrowthRound {
            sweep,
            grown_z: Some(grown_z),
            trial_kept,
        };
        assert_eq!(
            growth_rounds(&sweeps),
            vec![
                round(4, -12.0, None),
                round(5, -4.0, Some(true)),
                round(8, -6.0, None)
            ]
        );
        assert!(growth_rounds(&sweeps[..1]).is_empty());
    }
}
