//! [`Plan::resolve`] in named steps: the spec's numbers, the inputs it names, the geometries,
//! the candidates, the calibration material, the target, and the search and its report
//! configuration. The steps run in this order, so the first problem found is the one reported.

use super::{limits, Plan, TargetSource};
use crate::inputs::Inputs;
use crate::observation::Sidecar;
use crate::options::SearchOptions;
use crate::report::Configuration;
use crate::spec::JobSpec;
use anyhow::{bail, ensure, Context, Result};
use ndarray::Array2;
use scatterfarm_model::material::builtin_material;
use scatterfarm_model::{Geometry, Material, MaterialTable, Scene};
use scatterfarm_search::driver::Budget;
use scatterfarm_search::similarity::Target;
use scatterfarm_search::{Bounds, Candidates, CoarseLevels, Search, SearchConfig};

fn parse_range(text: &str, key: &str) -> Result<(f64, f64)> {
    let (lo, hi) = text
        .split_once(':')
        .with_context(|| format!("bounds {key}: expected LOW:HIGH, got {text:?}"))?;
    let lo: f64 = lo
        .trim()
        .parse()
        .with_context(|| format!("bounds {key}: {lo:?} is not a number"))?;
    let hi: f64 = hi
        .trim()
        .parse()
        .with_context(|| format!("bounds {key}: {hi:?} is not a number"))?;
    ensure!(
        lo.is_finite() && hi.is_finite() && lo <= hi,
        "bounds {key}: need LOW <= HIGH, got {lo}:{hi}"
    );
    Ok((lo, hi))
}

/// Parses `sigma_s=0:1,sigma_a=0:0.03,g=0:1` (missing keys keep their defaults).
pub fn parse_bounds(text: &str) -> Result<Bounds> {
    let mut b = Bounds::default();
    for part in text.split(',').filter(|p| !p.trim().is_empty()) {
        let (key, range) = part
            .split_once('=')
            .with_context(|| format!("bounds: expected KEY=LOW:HIGH, got {part:?}"))?;
        let range = parse_range(range, key.trim())?;
        match key.trim() {
            "sigma_s" => b.sigma_s = range,
            "sigma_a" => b.sigma_a = range,
            "g" => b.g = range,
            other => bail!("bounds: unknown key {other:?} (expected sigma_s, sigma_a or g)"),
        }
    }
    ensure!(
        b.sigma_s.0 >= 0.0 && b.sigma_a.0 >= 0.0,
        "bounds: coefficients must be >= 0"
    );
    ensure!(
        b.g.0 >= -1.0 && b.g.1 <= 1.0,
        "bounds: g must lie in [-1, 1]"
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
        let mut known: Vec<String> = scatterfarm_model::material::BUILTIN_MATERIALS
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

/// A captured target file: its values and sidecar.
type Capture = (Array2<f32>, Sidecar);

/// The steps of [`Plan::resolve`], in order.
pub(super) fn resolve(spec: &JobSpec, inputs: &Inputs) -> Result<Plan> {
    let (budget, options) = numbers(spec)?;
    let search_photons = budget.photons_per_source()?;
    let (mut truth, target_file) = named_inputs(spec, inputs)?;
    let geometries = geometries(spec, truth.as_mut(), target_file.as_ref())?;
    limits::check_sources("geometry", &geometries.target)?;
    let (table, dictionary, candidates) = candidates(spec, truth.as_ref())?;
    let size_mm = geometries.target.size_mm;
    limits::check_thickness("the search's materials", &table, size_mm)?;
    if let Some(t) = &truth {
        limits::check_thickness("the scene", &t.table, size_mm)?;
    }
    let (calibration_name, calibration_material) =
        calibration_material(spec, dictionary.is_some(), &table, truth.as_ref())?;
    let target = target(spec, inputs, truth.is_some(), target_file, search_photons)?;
    if let Some(CoarseLevels::Count(n)) = options.coarse_levels {
        let most = geometries.grid.trailing_zeros() + 1;
        anyhow::ensure!(
            (1..=most).contains(&n),
            "coarse_levels (--coarse-levels) must be auto or lie in 1 ..= {most} on a grid of {}, got {n}",
            geometries.grid
        );
    }
    let refine = options.refine.clone().map(|mut r| {
        // A differential render holds one f64 matrix of estimates per change.
        let per_change = geometries.search.sources() * geometries.search.bins() * 8;
        let fit = (256usize << 20) / per_change.max(1);
        r.changes_per_render = r
            .changes_per_render
            .min(fit.clamp(1, u32::MAX as usize) as u32);
        r.pixel_mm = size_mm / f64::from(geometries.grid.max(1));
        r
    });
    let search_config = SearchConfig {
        grid: geometries.grid,
        permutations: spec.permutations,
        seed: spec.seed,
        candidates,
        seeding: options.seeding,
        photons: options.photons.clone(),
        early_step2: options.early_step2,
        tie_z: options.tie_z,
        tiebreak: options.tiebreak.map(|(_, t)| t),
        coarse_levels: options.coarse_levels,
        refine,
    };
    let config = configuration(
        spec,
        &options,
        &geometries,
        &target,
        calibration_name,
        dictionary,
        &search_config,
    );
    let search = Search::new(search_config, table)?;
    Ok(Plan {
        config,
        truth,
        search,
        geometry: geometries.target,
        search_geometry: geometries.search,
        target: target.source,
        calibration_material,
        calibration_reference: target.calibration_reference,
        target_photons: target.photons,
        budget,
        metric: options.metric,
        secondary: options.tiebreak.map(|(m, _)| m),
        percentile: spec.percentile,
        seed: spec.seed,
    })
}

/// The budget and search options, and the counts that need no inputs to check.
fn numbers(spec: &JobSpec) -> Result<(Budget, SearchOptions)> {
    let budget = Budget {
        iterations: spec.iterations,
        photons_per_iteration: spec.photons_per_iteration,
    };
    let options = spec.search_options(budget.photons_per_source()?)?;
    ensure!(spec.permutations > 0, "permutations must be at least 1");
    ensure!(
        (0.0..=100.0).contains(&spec.percentile),
        "percentile must lie in [0, 100]"
    );
    Ok((budget, options))
}

/// The truth scene and the captured target the spec names, read from `inputs`.
fn named_inputs(spec: &JobSpec, inputs: &Inputs) -> Result<(Option<Scene>, Option<Capture>)> {
    let truth = spec
        .scene
        .as_deref()
        .map(|s| inputs.scene(s))
        .transpose()?
        .map(|t| t.scene);
    let target_file = spec
        .target
        .as_ref()
        .map(|t| inputs.observation(t))
        .transpose()?;
    Ok((truth, target_file))
}

/// The target's boundary sampling and the search's.
struct Geometries {
    target: Geometry,
    search: Geometry,
    grid: u32,
}

/// The boundary geometry of target and search (the truth takes the target's sampling).
fn geometries(
    spec: &JobSpec,
    truth: Option<&mut Scene>,
    target_file: Option<&Capture>,
) -> Result<Geometries> {
    let mut geometry = match (&truth, target_file) {
        (Some(s), _) => s.geometry,
        (None, Some((_, side))) => Geometry {
            size_mm: side.size_mm,
            grid: spec.grid.unwrap_or(16),
            positions: side.positions,
            directions: side.directions,
        },
        (None, None) => bail!("give a scene or a target"),
    };
    if let Some(p) = spec.positions {
        geometry.positions = p;
    }
    if let Some(k) = spec.directions {
        geometry.directions = k;
    }
    let truth_grid = truth.map(|s| {
        s.geometry.positions = geometry.positions;
        s.geometry.directions = geometry.directions;
        s.geometry.grid
    });
    let grid = spec.grid.unwrap_or(geometry.grid);
    ensure!(
        grid.is_power_of_two(),
        "grid must be a power of two, got {grid}"
    );
    if let Some(scene_grid) = truth_grid {
        ensure!(
            grid <= scene_grid,
            "grid {grid} is finer than the scene's grid {scene_grid}"
        );
    }
    let search = Geometry { grid, ..geometry };
    search.validate().context("search geometry")?;
    geometry.validate().context("target geometry")?;
    Ok(Geometries {
        target: geometry,
        search,
        grid,
    })
}

/// The search's table, the dictionary's names (none for random materials) and the candidates.
fn candidates(
    spec: &JobSpec,
    truth: Option<&Scene>,
) -> Result<(MaterialTable, Option<Vec<String>>, Candidates)> {
    let mut table = MaterialTable::default();
    let dictionary: Option<Vec<String>> = match (&spec.dictionary, spec.random_materials, truth) {
        (Some(d), _, _) => Some(d.iter().map(|n| n.trim().to_string()).collect()),
        (None, Some(_), _) => None,
        (None, None, Some(s)) => Some(s.table.materials.iter().map(|m| m.name.clone()).collect()),
        (None, None, None) => {
            bail!("a captured target needs a dictionary or random materials")
        }
    };
    let candidates = match (&dictionary, spec.random_materials) {
        (Some(names), _) => {
            ensure!(!names.is_empty(), "the dictionary is empty");
            let mut indices = Vec::new();
            for name in names {
                ensure!(
                    table.index_of(name).is_none(),
                    "the dictionary names {name:?} twice"
                );
                indices.push(table.push(name.clone(), lookup(name, truth)?));
            }
            Candidates::Dictionary(indices)
        }
        (None, Some(n)) => {
            ensure!(n > 0, "random materials must be at least 1");
            let bounds = spec
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
    Ok((table, dictionary, candidates))
}

/// The calibration material: named, else the first (dictionary or scene) material that
/// scatters.
fn calibration_material(
    spec: &JobSpec,
    has_dictionary: bool,
    table: &MaterialTable,
    truth: Option<&Scene>,
) -> Result<(String, Material)> {
    let pool: Vec<(String, Material)> = match (has_dictionary, truth) {
        (true, _) => table
            .materials
            .iter()
            .map(|m| (m.name.clone(), m.material))
            .collect(),
        (false, Some(s)) => s
            .table
            .materials
            .iter()
            .map(|m| (m.name.clone(), m.material))
            .collect(),
        (false, None) => Vec::new(),
    };
    match &spec.calibration_material {
        Some(name) => Ok((name.clone(), lookup(name, truth)?)),
        None => pool
            .iter()
            .find(|(_, m)| m.sigma_s > 0.0 && !m.is_opaque())
            .or(pool.first())
            .cloned()
            .context("name the calibration material (calibration_material)"),
    }
}

/// Where the target comes from, its photons per source, and a captured target's calibration.
struct TargetPlan {
    source: TargetSource,
    photons: u32,
    calibration_reference: Option<Vec<f32>>,
}

/// The target: synthesized from the truth, or a capture checked against its calibration.
fn target(
    spec: &JobSpec,
    inputs: &Inputs,
    synthesized: bool,
    target_file: Option<Capture>,
    search_photons: u32,
) -> Result<TargetPlan> {
    match (synthesized, target_file) {
        (true, _) => {
            let photons = spec.target_photons.unwrap_or(search_photons);
            ensure!(photons > 0, "target photons must be at least 1");
            Ok(TargetPlan {
                source: TargetSource::Synthesized { photons },
                photons,
                calibration_reference: None,
            })
        }
        (false, Some((data, side))) => {
            let cal_path = spec
                .calibration
                .as_ref()
                .context("a captured target needs a calibration capture")?;
            let (cal, cal_side) = inputs.observation(cal_path)?;
            ensure!(
                (cal_side.size_mm, cal_side.positions, cal_side.directions)
                    == (side.size_mm, side.positions, side.directions),
                "{} and the target have different geometries",
                cal_path.display(),
            );
            ensure!(
                spec.positions.is_none() && spec.directions.is_none(),
                "positions and directions apply to synthesized targets only"
            );
            Ok(TargetPlan {
                source: TargetSource::Captured(Target {
                    values: data.iter().cloned().collect(),
                    photons_per_source: side.photons_per_source,
                }),
                photons: u32::try_from(side.photons_per_source).unwrap_or(u32::MAX),
                calibration_reference: Some(cal.iter().cloned().collect()),
            })
        }
        (false, None) => bail!("give a scene or a target"),
    }
}

/// What `report.json` says the reconstruction was.
fn configuration(
    spec: &JobSpec,
    options: &SearchOptions,
    geometries: &Geometries,
    target: &TargetPlan,
    calibration_material: String,
    dictionary: Option<Vec<String>>,
    search: &SearchConfig,
) -> Configuration {
    let geometry = &geometries.target;
    Configuration {
        scene: spec.scene.clone(),
        target: spec.target.as_ref().map(|p| p.display().to_string()),
        calibration: spec.calibration.as_ref().map(|p| p.display().to_string()),
        calibration_material,
        dictionary,
        random_materials: spec.random_materials,
        bounds: match &search.candidates {
            Candidates::Random { bounds, .. } => Some(*bounds),
            Candidates::Dictionary(_) => None,
        },
        permutations: spec.permutations,
        iterations: spec.iterations,
        photons_per_iteration: spec.photons_per_iteration,
        target_photons: target.photons,
        percentile: spec.percentile,
        metric: options.metric,
        search: spec.search,
        common_random_numbers: options.seeding == scatterfarm_search::Seeding::PerLevel,
        early_step2: options.early_step2,
        coarse_levels: options.coarse_levels,
        tie_z: options.tie_z,
        tiebreak: options.tiebreak.map(|(m, _)| m),
        tiebreak_z: options.tiebreak.map(|(_, t)| t.z),
        tiebreak_from: options.tiebreak.map(|(_, t)| t.from),
        level_photons: options.photons.per_level.clone(),
        race: options.photons.race,
        rescore_photons: options.photons.rescore,
        grid: geometries.grid,
        size_mm: geometry.size_mm,
        positions: geometry.positions,
        directions: geometry.directions,
        seed: spec.seed,
        refine: search.refine.clone(),
    }
}
