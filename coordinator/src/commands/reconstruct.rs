//! `scatterfarm reconstruct`: find the material map whose simulation matches a target, in one
//! process, and write the report, material map and pictures.

use crate::engines::EngineArgs;
use crate::outcome;
use crate::reconstruction::{self, Budget, Consumption, Scoring};
use crate::report::{Configuration, LevelReport, Report};
use crate::search::{Bounds, Candidates, Search, SearchConfig};
use crate::similarity::{Metric, Target};
use crate::{observation, scene_source};
use anyhow::{bail, ensure, Context, Result};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use scatterfarm_worker::material::builtin_material;
use scatterfarm_worker::{Engine, Geometry, Material, MaterialTable, Scene};
use std::path::{Path, PathBuf};
use std::time::Instant;

#[derive(Debug, Clone, Args)]
pub struct ReconstructArgs {
    /// Synthesize the target from this scene (a file or a built-in name); its map is the truth.
    #[arg(long, conflicts_with = "target", required_unless_present = "target")]
    pub scene: Option<String>,
    /// A captured observation set (NPY with its JSON sidecar) to reconstruct instead.
    #[arg(long, requires = "calibration")]
    pub target: Option<PathBuf>,
    /// A capture of a known homogeneous material (NPY with sidecar), to calibrate ε for --target.
    #[arg(long, requires = "target")]
    pub calibration: Option<PathBuf>,
    /// The calibration material's name (default: the first dictionary material that scatters).
    #[arg(long)]
    pub calibration_material: Option<String>,
    /// Candidate materials, comma-separated names (default: the scene's own materials).
    #[arg(long, value_delimiter = ',', conflicts_with = "random_materials")]
    pub dictionary: Option<Vec<String>>,
    /// Unknown materials: draw this many random materials per level instead of a dictionary.
    #[arg(long)]
    pub random_materials: Option<u32>,
    /// Bounds of random materials, e.g. sigma_s=0:1,sigma_a=0:0.03,g=0:1.
    #[arg(long, requires = "random_materials")]
    pub bounds: Option<String>,
    /// Random permutations per level (the paper's T).
    #[arg(long, default_value_t = 10)]
    pub permutations: u32,
    /// Simulation iterations per render.
    #[arg(long, default_value_t = 100)]
    pub iterations: u32,
    /// Photons per source per iteration.
    #[arg(long, default_value_t = 512)]
    pub photons_per_iteration: u32,
    /// Photons per source of a synthesized target (default: iterations × photons per iteration).
    #[arg(long)]
    pub target_photons: Option<u32>,
    /// ε is this percentile of the calibration differences.
    #[arg(long, default_value_t = 99.9)]
    pub percentile: f64,
    /// The similarity metric.
    #[arg(long, value_enum, default_value_t = Metric::WithinEpsilon)]
    pub metric: Metric,
    /// Search at this grid (a power of two, at most the scene's); default: the scene's grid,
    /// or 16 for a captured target.
    #[arg(long)]
    pub grid: Option<u32>,
    /// Override the boundary positions (target and search alike).
    #[arg(long)]
    pub positions: Option<u32>,
    /// Override the directions per position (target and search alike).
    #[arg(long)]
    pub directions: Option<u32>,
    /// The job seed: every random stream derives from it.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    #[command(flatten)]
    pub engine: EngineArgs,
    /// The output folder.
    #[arg(long)]
    pub out: PathBuf,
    /// No progress bar (for scripts and benchmarks).
    #[arg(long, hide = true)]
    pub quiet: bool,
}

fn parse_range(text: &str, key: &str) -> Result<(f64, f64)> {
    let (lo, hi) = text
        .split_once(':')
        .with_context(|| format!("--bounds {key}: expected LOW:HIGH, got {text:?}"))?;
    let lo: f64 = lo
        .trim()
        .parse()
        .with_context(|| format!("--bounds {key}: {lo:?} is not a number"))?;
    let hi: f64 = hi
        .trim()
        .parse()
        .with_context(|| format!("--bounds {key}: {hi:?} is not a number"))?;
    ensure!(
        lo.is_finite() && hi.is_finite() && lo <= hi,
        "--bounds {key}: need LOW <= HIGH, got {lo}:{hi}"
    );
    Ok((lo, hi))
}

/// Parses `sigma_s=0:1,sigma_a=0:0.03,g=0:1` (missing keys keep their defaults).
pub fn parse_bounds(text: &str) -> Result<Bounds> {
    let mut b = Bounds::default();
    for part in text.split(',').filter(|p| !p.trim().is_empty()) {
        let (key, range) = part
            .split_once('=')
            .with_context(|| format!("--bounds: expected KEY=LOW:HIGH, got {part:?}"))?;
        let range = parse_range(range, key.trim())?;
        match key.trim() {
            "sigma_s" => b.sigma_s = range,
            "sigma_a" => b.sigma_a = range,
            "g" => b.g = range,
            other => bail!("--bounds: unknown key {other:?} (expected sigma_s, sigma_a or g)"),
        }
    }
    ensure!(
        b.sigma_s.0 >= 0.0 && b.sigma_a.0 >= 0.0,
        "--bounds: coefficients must be >= 0"
    );
    ensure!(
        b.g.0 >= -1.0 && b.g.1 <= 1.0,
        "--bounds: g must lie in [-1, 1]"
    );
    Ok(b)
}

/// A material by name: the scene's own, else a built-in one.
fn lookup(name: &str, scene: Option<&Scene>) -> Result<Material> {
    if let Some(m) = scene
        .and_then(|s| s.table.index_of(name))
        .and_then(|i| scene.map(|s| s.table.materials[i as usize].material))
    {
        return Ok(m);
    }
    builtin_material(name).with_context(|| {
        let mut known: Vec<String> = scatterfarm_worker::material::BUILTIN_MATERIALS
            .iter()
            .map(|(n, _)| n.to_string())
            .collect();
        if let Some(s) = scene {
            known.extend(s.table.materials.iter().map(|m| m.name.clone()));
        }
        known.dedup();
        format!("unknown material {name:?} (known: {})", known.join(", "))
    })
}

/// Everything resolved and rendered before the search starts.
pub struct Prepared {
    pub config: Configuration,
    pub truth: Option<Scene>,
    pub search: Search,
    pub scoring: Scoring,
    /// Photons rendered for the target and calibration (all sources).
    pub setup_photons: u64,
}

/// Resolves the arguments, synthesizes or loads the target and calibrates ε.
pub fn prepare(args: &ReconstructArgs, engine: &dyn Engine) -> Result<Prepared> {
    let budget = Budget {
        iterations: args.iterations,
        photons_per_iteration: args.photons_per_iteration,
    };
    let search_photons = budget.photons_per_source()?;
    ensure!(args.permutations > 0, "--permutations must be at least 1");
    ensure!(
        (0.0..=100.0).contains(&args.percentile),
        "--percentile must lie in [0, 100]"
    );

    let truth = args.scene.as_deref().map(scene_source::load).transpose()?;
    let mut truth_scene = truth.as_ref().map(|t| t.scene.clone());
    let mut setup_photons = 0u64;

    // The boundary geometry of target and search.
    let mut geometry = match (&truth_scene, &args.target) {
        (Some(s), _) => s.geometry,
        (None, Some(t)) => {
            let (_, side) = observation::read(t)?;
            Geometry {
                size_mm: side.size_mm,
                grid: args.grid.unwrap_or(16),
                positions: side.positions,
                directions: side.directions,
            }
        }
        (None, None) => bail!("give --scene or --target"),
    };
    if let Some(p) = args.positions {
        geometry.positions = p;
    }
    if let Some(k) = args.directions {
        geometry.directions = k;
    }
    if let Some(s) = truth_scene.as_mut() {
        s.geometry.positions = geometry.positions;
        s.geometry.directions = geometry.directions;
    }
    let grid = args.grid.unwrap_or(geometry.grid);
    ensure!(
        grid.is_power_of_two(),
        "--grid must be a power of two, got {grid}"
    );
    if let Some(s) = &truth_scene {
        ensure!(
            grid <= s.geometry.grid,
            "--grid {grid} is finer than the scene's grid {}",
            s.geometry.grid
        );
    }
    let search_geometry = Geometry { grid, ..geometry };
    search_geometry.validate().context("search geometry")?;

    // Candidates and the search's table.
    let mut table = MaterialTable::default();
    let dictionary_names: Option<Vec<String>> =
        match (&args.dictionary, args.random_materials, &truth_scene) {
            (Some(d), _, _) => Some(d.iter().map(|n| n.trim().to_string()).collect()),
            (None, Some(_), _) => None,
            (None, None, Some(s)) => {
                Some(s.table.materials.iter().map(|m| m.name.clone()).collect())
            }
            (None, None, None) => {
                bail!("a captured target needs --dictionary or --random-materials")
            }
        };
    let candidates = match (&dictionary_names, args.random_materials) {
        (Some(names), _) => {
            ensure!(!names.is_empty(), "--dictionary is empty");
            let mut indices = Vec::new();
            for name in names {
                ensure!(
                    table.index_of(name).is_none(),
                    "--dictionary names {name:?} twice"
                );
                indices.push(table.push(name.clone(), lookup(name, truth_scene.as_ref())?));
            }
            Candidates::Dictionary(indices)
        }
        (None, Some(n)) => {
            ensure!(n > 0, "--random-materials must be at least 1");
            let bounds = args
                .bounds
                .as_deref()
                .map(parse_bounds)
                .transpose()?
                .unwrap_or_default();
            Candidates::Random {
                per_level: n,
                bounds,
            }
        }
        (None, None) => bail!("no candidate materials"),
    };

    // The calibration material: named, else the first (dictionary or scene) material that scatters.
    let pool: Vec<(String, Material)> = match (&dictionary_names, &truth_scene) {
        (Some(_), _) => table
            .materials
            .iter()
            .map(|m| (m.name.clone(), m.material))
            .collect(),
        (None, Some(s)) => s
            .table
            .materials
            .iter()
            .map(|m| (m.name.clone(), m.material))
            .collect(),
        (None, None) => Vec::new(),
    };
    let (calibration_name, calibration_material) = match &args.calibration_material {
        Some(name) => (name.clone(), lookup(name, truth_scene.as_ref())?),
        None => pool
            .iter()
            .find(|(_, m)| m.sigma_s > 0.0 && !m.is_opaque())
            .or(pool.first())
            .cloned()
            .context("name the calibration material with --calibration-material")?,
    };

    let sources = geometry.sources() as u64;
    let (target, target_photons, reference) = match (&truth_scene, &args.target) {
        (Some(scene), _) => {
            let photons = args.target_photons.unwrap_or(search_photons);
            ensure!(photons > 0, "--target-photons must be at least 1");
            tracing::info!(
                "synthesizing the target: {} sources × {photons} photons",
                geometry.sources()
            );
            let target = reconstruction::synthesize_target(engine, scene, photons, args.seed)?;
            setup_photons += sources * u64::from(photons);
            (target, photons, None)
        }
        (None, Some(path)) => {
            let (data, side) = observation::read(path)?;
            let cal_path = args
                .calibration
                .as_ref()
                .context("--target needs --calibration")?;
            let (cal, cal_side) = observation::read(cal_path)?;
            ensure!(
                (cal_side.size_mm, cal_side.positions, cal_side.directions)
                    == (side.size_mm, side.positions, side.directions),
                "{} and {} have different geometries",
                cal_path.display(),
                path.display()
            );
            ensure!(
                args.positions.is_none() && args.directions.is_none(),
                "--positions and --directions apply to synthesized targets only"
            );
            let photons = u32::try_from(side.photons_per_source).unwrap_or(u32::MAX);
            let target = Target {
                values: data.iter().cloned().collect(),
                photons_per_source: side.photons_per_source,
            };
            (
                target,
                photons,
                Some(cal.iter().cloned().collect::<Vec<f32>>()),
            )
        }
        (None, None) => bail!("give --scene or --target"),
    };

    tracing::info!("calibrating ε on {calibration_name}");
    let calibration = reconstruction::Calibration {
        material: calibration_material,
        reference: reference.as_deref(),
        target_photons,
        search_photons,
        percentile: args.percentile,
    };
    let epsilon = reconstruction::calibrate(
        engine,
        Geometry {
            grid: 1,
            ..geometry
        },
        &calibration,
        args.seed,
    )?;
    setup_photons += sources * u64::from(search_photons)
        + if reference.is_none() {
            sources * u64::from(target_photons)
        } else {
            0
        };
    tracing::info!("ε = {epsilon:.6} ({}th percentile)", args.percentile);

    let search = Search::new(
        SearchConfig {
            grid,
            permutations: args.permutations,
            seed: args.seed,
            candidates: candidates.clone(),
        },
        table,
    )?;
    let config = Configuration {
        scene: args.scene.clone(),
        target: args.target.as_ref().map(|p| p.display().to_string()),
        calibration: args.calibration.as_ref().map(|p| p.display().to_string()),
        calibration_material: calibration_name,
        dictionary: dictionary_names,
        random_materials: args.random_materials,
        bounds: match candidates {
            Candidates::Random { bounds, .. } => Some(bounds),
            Candidates::Dictionary(_) => None,
        },
        permutations: args.permutations,
        iterations: args.iterations,
        photons_per_iteration: args.photons_per_iteration,
        target_photons,
        percentile: args.percentile,
        metric: args.metric,
        grid,
        size_mm: geometry.size_mm,
        positions: geometry.positions,
        directions: geometry.directions,
        seed: args.seed,
    };
    Ok(Prepared {
        config,
        truth: truth_scene,
        search,
        scoring: Scoring {
            geometry: search_geometry,
            target,
            metric: args.metric,
            epsilon,
            budget,
        },
        setup_photons,
    })
}

/// Runs a prepared reconstruction and writes its outputs into `out`.
pub fn run_prepared(
    mut p: Prepared,
    engine: &dyn Engine,
    out: &Path,
    quiet: bool,
) -> Result<Report> {
    let started = Instant::now();
    let bar = if quiet {
        ProgressBar::hidden()
    } else {
        ProgressBar::new(p.search.progress().renders_total)
    };
    bar.set_style(
        ProgressStyle::with_template("{spinner} [{bar:30}] {pos}/{len} renders, ETA {eta} · {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    let mut on_step = |s: &Search, used: &Consumption| {
        let pr = s.progress();
        bar.set_length(pr.renders_total);
        bar.set_position(pr.renders_done);
        let rate = used.photons as f64 / started.elapsed().as_secs_f64().max(1e-9);
        bar.set_message(format!(
            "level {}/{} · permutation {}/{} · region {}/{} · best {:.4} · {:.2} M photons/s",
            pr.level,
            pr.levels - 1,
            (pr.permutation + 1).min(pr.permutations),
            pr.permutations,
            pr.region,
            pr.regions,
            pr.best_score.unwrap_or(f64::NAN),
            rate / 1e6
        ));
    };
    let used = reconstruction::drive(&mut p.search, engine, &p.scoring, &mut on_step, &mut |_| {})?;
    bar.finish_and_clear();
    let result = p
        .search
        .result()
        .context("the search ended without a result")?
        .clone();
    let grid = p.scoring.geometry.grid as usize;
    let table = p.search.table().clone();
    let truth = p.truth.as_ref();
    let measures = |a: &[u16], level: u32| {
        truth.map(|t| {
            // A level's map lives at 2^level; the search keeps it at the search grid already.
            let _ = level;
            (
                outcome::pixel_accuracy(a, grid, &table, t),
                outcome::material_sse(a, grid, &table, t),
            )
        })
    };
    let levels = p
        .search
        .levels()
        .iter()
        .map(|l| {
            let m = measures(&l.assignment, l.level);
            LevelReport {
                level: l.level,
                similarity: l.score,
                pixel_accuracy: m.map(|m| m.0),
                material_sse: m.map(|m| m.1),
            }
        })
        .collect();
    let final_measures = measures(&result.assignment, result.level);
    let report = Report {
        pixel_accuracy: final_measures.map(|m| m.0),
        material_sse: final_measures.map(|m| m.1),
        similarity: result.score,
        epsilon: p.scoring.epsilon,
        renders: used.renders,
        photons: used.photons,
        photons_simulated: used.photons + p.setup_photons,
        wall_seconds: started.elapsed().as_secs_f64(),
        engine: engine.fingerprint().to_string(),
        seed: p.config.seed,
        reproducible: true,
        configuration: p.config.clone(),
        levels,
    };
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    outcome::write_materials(out, &result.assignment, grid, &table)?;
    outcome::write_reconstruction_png(
        &out.join("reconstruction.png"),
        &result.assignment,
        grid,
        &table,
        truth,
    )?;
    outcome::write_maps_png(&out.join("maps.png"), &result.assignment, grid, &table)?;
    outcome::write_json(&out.join("report.json"), &report)?;
    Ok(report)
}

pub fn run(args: ReconstructArgs) -> Result<()> {
    let engine = args.engine.open()?;
    let prepared = prepare(&args, engine.as_ref())?;
    let report = run_prepared(prepared, engine.as_ref(), &args.out, args.quiet)?;
    let accuracy = report
        .pixel_accuracy
        .map(|a| format!(", pixel accuracy {:.1} %", a * 100.0))
        .unwrap_or_default();
    eprintln!(
        "similarity {:.4}{accuracy}; {} renders in {:.1} s; wrote report.json, materials.npy, materials.json, reconstruction.png and maps.png to {}",
        report.similarity,
        report.renders,
        report.wall_seconds,
        args.out.display()
    );
    Ok(())
}
