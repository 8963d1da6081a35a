//! Resolving a reconstruction's parameters and inputs into a [`Plan`]: geometries, candidates,
//! the fresh search, and the renders that must come before it (target and ε calibration).
//!
//! Nothing here renders. The in-process path ([`crate::setup`] and `scatterfarm_search::driver`) and the farm
//! (`scatterfarm_coordinator`) both render a plan's [`SetupRender`]s and hand the counts back to
//! [`Plan::finish_setup`], so the two reach the same target and ε from the same seeds.

use crate::inputs::Inputs;
use crate::params::JobParams;
use crate::report::Configuration;
use anyhow::{bail, ensure, Context, Result};
use scatterfarm_model::material::builtin_material;
use scatterfarm_model::{CountMatrix, Geometry, Material, MaterialTable, RenderItem, Scene};
use scatterfarm_search::driver::{Budget, Scoring};
use scatterfarm_search::seeds::{self, Stream};
use scatterfarm_search::similarity::{self, Metric, Target};
use scatterfarm_search::{Bounds, Candidates, Search, SearchConfig};
use std::collections::BTreeMap;

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

/// Which setup render this is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
pub enum SetupKind {
    /// The synthesized target (stream `target`).
    Target,
    /// The calibration material as the target is made (stream `calibration-target`).
    CalibrationTarget,
    /// The calibration material as the search renders (stream `calibration-search`), with
    /// one of the photon budgets the search renders with.
    CalibrationSearch { photons: u32 },
}

/// One render that must be done before the search starts.
#[derive(Debug, Clone)]
pub struct SetupRender {
    pub kind: SetupKind,
    pub geometry: Geometry,
    pub table: Vec<Material>,
    pub item: RenderItem,
    /// Photons per source.
    pub photons: u32,
}

/// The counts of a plan's setup renders.
#[derive(Debug, Clone, Default)]
pub struct SetupCounts {
    pub target: Option<CountMatrix>,
    pub calibration_target: Option<CountMatrix>,
    /// By photons per source.
    pub calibration_search: BTreeMap<u32, CountMatrix>,
}

impl SetupCounts {
    /// Stores the counts of `kind`.
    pub fn set(&mut self, kind: SetupKind, counts: CountMatrix) {
        match kind {
            SetupKind::Target => self.target = Some(counts),
            SetupKind::CalibrationTarget => self.calibration_target = Some(counts),
            SetupKind::CalibrationSearch { photons } => {
                self.calibration_search.insert(photons, counts);
            }
        }
    }

    /// Whether the counts of `kind` are here.
    pub fn has(&self, kind: SetupKind) -> bool {
        match kind {
            SetupKind::Target => self.target.is_some(),
            SetupKind::CalibrationTarget => self.calibration_target.is_some(),
            SetupKind::CalibrationSearch { photons } => {
                self.calibration_search.contains_key(&photons)
            }
        }
    }
}

/// Where the target comes from.
#[derive(Debug, Clone)]
pub enum TargetSource {
    /// Rendered from the truth scene with this many photons per source.
    Synthesized { photons: u32 },
    /// A capture.
    Captured(Target),
}

/// A reconstruction resolved from its parameters and inputs, before anything is rendered.
#[derive(Debug, Clone)]
pub struct Plan {
    pub config: Configuration,
    /// The truth, when the target is synthesized from a scene (at the target's boundary sampling).
    pub truth: Option<Scene>,
    /// The fresh search.
    pub search: Search,
    /// The target's boundary sampling (at the truth's grid, or 1 for captures).
    pub geometry: Geometry,
    /// The search's geometry: the target's boundary sampling at the search grid.
    pub search_geometry: Geometry,
    pub target: TargetSource,
    pub calibration_material: Material,
    /// A capture of the calibration material, for captured targets.
    pub calibration_reference: Option<Vec<f32>>,
    pub target_photons: u32,
    /// The nominal budget: iterations × photons per iteration (the paper's every render).
    pub budget: Budget,
    pub metric: Metric,
    /// The tiebreak's metric, scored beside `metric` (`Scoring::secondary`).
    pub secondary: Option<Metric>,
    pub percentile: f64,
    pub seed: u64,
}

impl Plan {
    /// Resolves `params` against `inputs`: every check that needs no rendering happens here.
    pub fn resolve(params: &JobParams, inputs: &Inputs) -> Result<Plan> {
        let budget = Budget {
            iterations: params.iterations,
            photons_per_iteration: params.photons_per_iteration,
        };
        let search_photons = budget.photons_per_source()?;
        let options = params.search_options(search_photons)?;
        ensure!(params.permutations > 0, "permutations must be at least 1");
        ensure!(
            (0.0..=100.0).contains(&params.percentile),
            "percentile must lie in [0, 100]"
        );

        let truth = params
            .scene
            .as_deref()
            .map(|s| inputs.scene(s))
            .transpose()?;
        let mut truth_scene = truth.as_ref().map(|t| t.scene.clone());
        let target_file = params
            .target
            .as_ref()
            .map(|t| inputs.observation(t))
            .transpose()?;

        // The boundary geometry of target and search.
        let mut geometry = match (&truth_scene, &target_file) {
            (Some(s), _) => s.geometry,
            (None, Some((_, side))) => Geometry {
                size_mm: side.size_mm,
                grid: params.grid.unwrap_or(16),
                positions: side.positions,
                directions: side.directions,
            },
            (None, None) => bail!("give a scene or a target"),
        };
        if let Some(p) = params.positions {
            geometry.positions = p;
        }
        if let Some(k) = params.directions {
            geometry.directions = k;
        }
        if let Some(s) = truth_scene.as_mut() {
            s.geometry.positions = geometry.positions;
            s.geometry.directions = geometry.directions;
        }
        let grid = params.grid.unwrap_or(geometry.grid);
        ensure!(
            grid.is_power_of_two(),
            "grid must be a power of two, got {grid}"
        );
        if let Some(s) = &truth_scene {
            ensure!(
                grid <= s.geometry.grid,
                "grid {grid} is finer than the scene's grid {}",
                s.geometry.grid
            );
        }
        let search_geometry = Geometry { grid, ..geometry };
        search_geometry.validate().context("search geometry")?;
        geometry.validate().context("target geometry")?;

        // Candidates and the search's table.
        let mut table = MaterialTable::default();
        let dictionary_names: Option<Vec<String>> =
            match (&params.dictionary, params.random_materials, &truth_scene) {
                (Some(d), _, _) => Some(d.iter().map(|n| n.trim().to_string()).collect()),
                (None, Some(_), _) => None,
                (None, None, Some(s)) => {
                    Some(s.table.materials.iter().map(|m| m.name.clone()).collect())
                }
                (None, None, None) => {
                    bail!("a captured target needs a dictionary or random materials")
                }
            };
        let candidates = match (&dictionary_names, params.random_materials) {
            (Some(names), _) => {
                ensure!(!names.is_empty(), "the dictionary is empty");
                let mut indices = Vec::new();
                for name in names {
                    ensure!(
                        table.index_of(name).is_none(),
                        "the dictionary names {name:?} twice"
                    );
                    indices.push(table.push(name.clone(), lookup(name, truth_scene.as_ref())?));
                }
                Candidates::Dictionary(indices)
            }
            (None, Some(n)) => {
                ensure!(n > 0, "random materials must be at least 1");
                let bounds = params
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

        // The calibration material: named, else the first (dictionary or scene) material that
        // scatters.
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
        let (calibration_name, calibration_material) = match &params.calibration_material {
            Some(name) => (name.clone(), lookup(name, truth_scene.as_ref())?),
            None => pool
                .iter()
                .find(|(_, m)| m.sigma_s > 0.0 && !m.is_opaque())
                .or(pool.first())
                .cloned()
                .context("name the calibration material (calibration_material)")?,
        };

        let (target, target_photons, calibration_reference) = match (&truth_scene, target_file) {
            (Some(_), _) => {
                let photons = params.target_photons.unwrap_or(search_photons);
                ensure!(photons > 0, "target photons must be at least 1");
                (TargetSource::Synthesized { photons }, photons, None)
            }
            (None, Some((data, side))) => {
                let cal_path = params
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
                    params.positions.is_none() && params.directions.is_none(),
                    "positions and directions apply to synthesized targets only"
                );
                let photons = u32::try_from(side.photons_per_source).unwrap_or(u32::MAX);
                let target = Target {
                    values: data.iter().cloned().collect(),
                    photons_per_source: side.photons_per_source,
                };
                (
                    TargetSource::Captured(target),
                    photons,
                    Some(cal.iter().cloned().collect::<Vec<f32>>()),
                )
            }
            (None, None) => bail!("give a scene or a target"),
        };

        let search = Search::new(
            SearchConfig {
                grid,
                permutations: params.permutations,
                seed: params.seed,
                candidates: candidates.clone(),
                seeding: options.seeding,
                photons: options.photons.clone(),
                early_step2: options.early_step2,
                tie_z: options.tie_z,
                tiebreak: options.tiebreak.map(|(_, t)| t),
            },
            table,
        )?;
        let config = Configuration {
            scene: params.scene.clone(),
            target: params.target.as_ref().map(|p| p.display().to_string()),
            calibration: params.calibration.as_ref().map(|p| p.display().to_string()),
            calibration_material: calibration_name,
            dictionary: dictionary_names,
            random_materials: params.random_materials,
            bounds: match candidates {
                Candidates::Random { bounds, .. } => Some(bounds),
                Candidates::Dictionary(_) => None,
            },
            permutations: params.permutations,
            iterations: params.iterations,
            photons_per_iteration: params.photons_per_iteration,
            target_photons,
            percentile: params.percentile,
            metric: options.metric,
            search: params.search,
            common_random_numbers: options.seeding == scatterfarm_search::Seeding::PerLevel,
            early_step2: options.early_step2,
            tie_z: options.tie_z,
            tiebreak: options.tiebreak.map(|(m, _)| m),
            tiebreak_z: options.tiebreak.map(|(_, t)| t.z),
            tiebreak_from: options.tiebreak.map(|(_, t)| t.from),
            level_photons: options.photons.per_level.clone(),
            race: options.photons.race,
            rescore_photons: options.photons.rescore,
            grid,
            size_mm: geometry.size_mm,
            positions: geometry.positions,
            directions: geometry.directions,
            seed: params.seed,
        };
        Ok(Plan {
            config,
            truth: truth_scene,
            search,
            geometry,
            search_geometry,
            target,
            calibration_material,
            calibration_reference,
            target_photons,
            budget,
            metric: options.metric,
            secondary: options.tiebreak.map(|(m, _)| m),
            percentile: params.percentile,
            seed: params.seed,
        })
    }

    /// The renders the search needs first: the synthesized target (if any) and the calibration
    /// pair (one of them, for a captured target).
    pub fn setup_renders(&self) -> Result<Vec<SetupRender>> {
        let mut renders = Vec::new();
        if let (TargetSource::Synthesized { photons }, Some(scene)) = (&self.target, &self.truth) {
            renders.push(SetupRender {
                kind: SetupKind::Target,
                geometry: scene.geometry,
                table: scene.table.physics(),
                item: RenderItem {
                    assignment: scene.assignment.clone(),
                    seed: seeds::derive(self.seed, Stream::Target),
                },
                photons: *photons,
            });
        }
        let homogeneous = Geometry {
            grid: 1,
            ..self.geometry
        };
        if self.calibration_reference.is_none() {
            renders.push(SetupRender {
                kind: SetupKind::CalibrationTarget,
                geometry: homogeneous,
                table: vec![self.calibration_material],
                item: RenderItem {
                    assignment: vec![0],
                    seed: seeds::derive(self.seed, Stream::CalibrationTarget),
                },
                photons: self.target_photons,
            });
        }
        // One per budget the search renders with, all on the one stream (a smaller budget's
        // render is the first photons of a larger one's).
        for photons in self.search.budgets() {
            renders.push(SetupRender {
                kind: SetupKind::CalibrationSearch { photons },
                geometry: homogeneous,
                table: vec![self.calibration_material],
                item: RenderItem {
                    assignment: vec![0],
                    seed: seeds::derive(self.seed, Stream::CalibrationSearch),
                },
                photons,
            });
        }
        Ok(renders)
    }

    /// The target and ε from the setup renders' counts.
    pub fn finish_setup(&self, counts: &SetupCounts) -> Result<Scoring> {
        let target = match &self.target {
            TargetSource::Captured(t) => t.clone(),
            TargetSource::Synthesized { photons } => {
                let c = counts
                    .target
                    .as_ref()
                    .context("the target render is missing")?;
                Target {
                    values: similarity::fractions(c, u64::from(*photons)),
                    photons_per_source: u64::from(*photons),
                }
            }
        };
        let rendered_reference;
        let reference: &[f32] = match &self.calibration_reference {
            Some(r) => r,
            None => {
                let c = counts
                    .calibration_target
                    .as_ref()
                    .context("the calibration-target render is missing")?;
                rendered_reference = similarity::fractions(c, u64::from(self.target_photons));
                &rendered_reference
            }
        };
        let mut epsilons = BTreeMap::new();
        for photons in self.search.budgets() {
            let c = counts.calibration_search.get(&photons).with_context(|| {
                format!("the calibration-search render at {photons} photons is missing")
            })?;
            let search = similarity::fractions(c, u64::from(photons));
            epsilons.insert(
                photons,
                similarity::epsilon(reference, &search, self.percentile)?,
            );
        }
        Ok(self.scoring(target, epsilons))
    }

    /// What the search scores against, from the target and the ε of every budget.
    pub fn scoring(&self, target: Target, epsilons: BTreeMap<u32, f64>) -> Scoring {
        Scoring {
            geometry: self.search_geometry,
            target,
            metric: self.metric,
            secondary: self.secondary,
            epsilons,
            with_errors: self.search.config().photons.race.is_some()
                || self.search.config().tie_z > 0.0
                || self.secondary.is_some(),
            chunk: self.budget.photons_per_iteration.max(1),
        }
    }

    /// Photons (all sources) the setup renders launch.
    pub fn setup_photons(&self) -> Result<u64> {
        Ok(self
            .setup_renders()?
            .iter()
            .map(|r| r.geometry.sources() as u64 * u64::from(r.photons))
            .sum())
    }
}
