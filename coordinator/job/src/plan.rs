//! Resolving a reconstruction's parameters and inputs into a [`Plan`]: geometries, candidates,
//! the fresh search, and the renders that must come before it (target and ε calibration).
//!
//! Nothing here renders. The in-process path ([`crate::setup`] and `scatterfarm_search::driver`) and the farm
//! (`scatterfarm_coordinator`) both render a plan's [`SetupRender`]s and hand the counts back to
//! [`Plan::finish_setup`], so the two reach the same target and ε from the same seeds.

use crate::inputs::Inputs;
use crate::report::Configuration;
use crate::spec::JobSpec;
use anyhow::{Context, Result};
use scatterfarm_model::{CountMatrix, Geometry, Material, RenderItem, Scene};
use scatterfarm_search::driver::{Budget, Scoring};
use scatterfarm_search::seeds::{self, Stream};
use scatterfarm_search::similarity::{self, Metric, Target};
use scatterfarm_search::Search;
use std::collections::BTreeMap;

pub mod limits;
mod resolve;

pub use resolve::parse_bounds;

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
    /// Resolves `spec` against `inputs`: every check that needs no rendering happens here,
    /// in the order of the steps in `plan::resolve`.
    pub fn resolve(spec: &JobSpec, inputs: &Inputs) -> Result<Plan> {
        resolve::resolve(spec, inputs)
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
        if !self.needs_epsilon() {
            return Ok(renders);
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

    /// Whether the search's scores need ε: every metric but the likelihood does, and so does
    /// a tiebreak.
    pub fn needs_epsilon(&self) -> bool {
        self.metric != Metric::Deviance || self.secondary.is_some()
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
        if !self.needs_epsilon() {
            return Ok(self.scoring(target, BTreeMap::new()));
        }
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
