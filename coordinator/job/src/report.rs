//! `report.json` of a reconstruction: the measures, what it consumed, and its configuration.

use crate::options::SearchMode;
use scatterfarm_search::refine::RefineConfig;
use scatterfarm_search::similarity::Metric;
use scatterfarm_search::{Bounds, CoarseLevels, Race};
use serde::{Deserialize, Serialize};

/// The configuration, as recorded in `report.json`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Configuration {
    pub scene: Option<String>,
    pub target: Option<String>,
    pub calibration: Option<String>,
    pub calibration_material: String,
    pub dictionary: Option<Vec<String>>,
    pub random_materials: Option<u32>,
    pub bounds: Option<Bounds>,
    pub permutations: u32,
    pub iterations: u32,
    pub photons_per_iteration: u32,
    pub target_photons: u32,
    pub percentile: f64,
    pub metric: Metric,
    /// The search mode and the options it resolved to.
    pub search: SearchMode,
    pub common_random_numbers: bool,
    pub early_step2: bool,
    /// Quad-tree levels the coarse stage ran (absent: all).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub coarse_levels: Option<CoarseLevels>,
    pub tie_z: f64,
    /// The tiebreak's metric, its margin in standard errors, and the within-ε score from
    /// which it decides (absent: no tiebreak).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tiebreak: Option<Metric>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tiebreak_z: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tiebreak_from: Option<f64>,
    pub level_photons: Vec<u32>,
    pub race: Option<Race>,
    pub rescore_photons: Option<u32>,
    pub grid: u32,
    pub size_mm: f64,
    pub positions: u32,
    pub directions: u32,
    pub seed: u64,
    /// The refinement stage as it ran (absent: none); its photons are per source.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub refine: Option<RefineConfig>,
}

/// One level in `report.json`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct LevelReport {
    pub level: u32,
    pub similarity: f64,
    pub pixel_accuracy: Option<f64>,
    pub material_sse: Option<f64>,
}

/// `report.json`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Report {
    pub pixel_accuracy: Option<f64>,
    pub material_sse: Option<f64>,
    pub similarity: f64,
    /// ε of the finest level's budget (none for the likelihood, which needs no ε).
    pub epsilon: Option<f64>,
    /// ε of every photons-per-source budget the search scored renders of.
    pub epsilons: std::collections::BTreeMap<u32, f64>,
    /// Render requests of the search (answered by a render or by the cache).
    pub requests: u64,
    /// Search renders and the photons they launched (all sources).
    pub renders: u64,
    /// Batches of the search's requests that needed renders (`renders / batches` renders can
    /// run at once, on average).
    pub batches: u64,
    pub photons: u64,
    /// Photons the engine actually ran: search, target and calibration renders.
    pub photons_simulated: u64,
    pub wall_seconds: f64,
    pub engine: String,
    pub seed: u64,
    /// Whether the same seed and engine reproduce this result (always, in one process).
    pub reproducible: bool,
    pub configuration: Configuration,
    pub levels: Vec<LevelReport>,
    /// The refinement stage's sweeps, when the search refines.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub refinement: Vec<SweepReport>,
    /// The score (and accuracy) at the end of every level and sweep against what the search
    /// had consumed by then: the curve `convergence.png` draws.
    #[serde(default)]
    pub convergence: Vec<ConvergenceReport>,
}

/// One point of the convergence curve in `report.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ConvergenceReport {
    /// `level` or `sweep`.
    pub stage: String,
    /// The level (from 0) or the sweep (from 0).
    pub index: u32,
    /// What the search had consumed when the stage ended (as the report's totals).
    pub requests: u64,
    pub renders: u64,
    pub photons: u64,
    pub score: f64,
    /// The stage's map's pixel accuracy, when the truth is known.
    pub pixel_accuracy: Option<f64>,
}

/// One refinement sweep in `report.json`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SweepReport {
    pub sweep: u32,
    /// Changes tried, those scored by a differential render, and those that beat the current
    /// map by `refine_z` paired standard errors.
    pub tried: u32,
    pub reweighted: u32,
    pub candidates: u32,
    /// Pixels the confirmation changed (0: none confirmed).
    pub changed: u32,
    pub similarity: f64,
    /// The map's pixel accuracy after the sweep, when the truth is known.
    pub pixel_accuracy: Option<f64>,
    /// A growth round's (`refine_grow`).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub growth: bool,
    /// The end of a growth trial: whether the map the trial reached was kept (else the map
    /// its round started from came back).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub trial_kept: Option<bool>,
    /// A growth round in which no grown map won: the best grown map's paired z against the
    /// current map (it is tried where above `refine_grow_trial_z`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub grown_z: Option<f64>,
}
