//! What the search reports: each level's best map ([`LevelResult`]) and where it stands
//! ([`Progress`]).

use serde::{Deserialize, Serialize};

/// The best assignment of a level.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LevelResult {
    pub level: u32,
    pub assignment: Vec<u16>,
    /// The score of the render that produced it (with re-scoring: of its re-scoring render).
    pub score: f64,
    /// Which permutation produced it (with re-scoring, T when the level kept its starting map).
    pub permutation: u32,
}

/// Where the search stands, for progress displays.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Progress {
    pub level: u32,
    pub levels: u32,
    pub permutation: u32,
    pub permutations: u32,
    /// Regions finished in this permutation, and the level's region count.
    pub region: u32,
    pub regions: u32,
    /// Requests answered so far (renders or cache hits).
    pub renders_done: u64,
    /// Requests the whole search makes (exact for the paper's search on a dictionary; an
    /// estimate with racing, early step 2, re-scoring or unknown materials).
    pub renders_total: u64,
    pub best_score: Option<f64>,
    /// Whether the refinement stage has begun, its sweeps ended so far, and the most it may
    /// run (0 for a search without refinement).
    #[serde(default)]
    pub refining: bool,
    #[serde(default)]
    pub sweep: u32,
    #[serde(default)]
    pub sweeps: u32,
}

impl Progress {
    /// Where the search stands, in words: its level, permutation and region, or its
    /// refinement sweep.
    pub fn stage(&self) -> String {
        if self.refining {
            return format!(
                "refinement · sweep {}/{}",
                (self.sweep + 1).min(self.sweeps),
                self.sweeps
            );
        }
        format!(
            "level {}/{} · permutation {}/{} · region {}/{}",
            self.level,
            self.levels.saturating_sub(1),
            (self.permutation + 1).min(self.permutations),
            self.permutations,
            self.region,
            self.regions
        )
    }
}
