//! `report.json` of a reconstruction: the measures, what it consumed, and its configuration.

use crate::search::Bounds;
use crate::similarity::Metric;
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
    pub grid: u32,
    pub size_mm: f64,
    pub positions: u32,
    pub directions: u32,
    pub seed: u64,
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
    pub epsilon: f64,
    /// Search renders and the photons they launched (all sources).
    pub renders: u64,
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
}
