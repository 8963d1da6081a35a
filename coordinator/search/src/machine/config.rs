//! What fixes a search ([`SearchConfig`]): where candidate materials come from, how requests
//! are seeded, and what goes wrong ([`SearchError`]).

use super::{Bounds, CoarseLevels, Photons, Tiebreak};
use crate::refine::RefineConfig;
use serde::{Deserialize, Serialize};
use thiserror::Error;

/// Where a level's candidate materials come from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum Candidates {
    /// Known materials: these indices into the search's table, in dictionary order.
    Dictionary(Vec<u16>),
    /// Unknown materials: `per_level` new random materials per level, drawn within `bounds`.
    Random { per_level: u32, bounds: Bounds },
}

/// How render requests get their seeds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Seeding {
    /// The paper's: every request its own seed, `hash(S, "render", n)`.
    #[default]
    PerRequest,
    /// Common random numbers: every request of a level shares `hash(S, "render-level", ℓ)`,
    /// so scores inside a level differ by the material change, not by noise, and an assignment
    /// asked for twice in a level is the same render (cached by identity).
    PerLevel,
}

/// What fixes a search.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SearchConfig {
    /// The search grid `N` (a power of two): levels run `0 ..= log2 N`.
    pub grid: u32,
    /// Random permutations per level (the paper's `T`).
    pub permutations: u32,
    /// The job seed: permutations, random materials and render seeds derive from it.
    pub seed: u64,
    pub candidates: Candidates,
    pub seeding: Seeding,
    /// Photons per source of every request.
    pub photons: Photons,
    /// Request all of a permutation's `M⁰`-variants up front.
    pub early_step2: bool,
    /// Scores closer than this many standard errors of their difference tie (0: only equal
    /// scores tie, the paper's). A tie inside a step goes to the earlier candidate, and
    /// between the steps to step 2, as in the paper.
    pub tie_z: f64,
    /// Where the primary score is saturated, a secondary score decides between tied
    /// candidates (scores then carry [`Score::secondary`](super::Score::secondary)).
    pub tiebreak: Option<Tiebreak>,
    /// The pixel-level refinement stage after the last level (`crate::refine`), when set.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub refine: Option<RefineConfig>,
    /// Quad-tree levels the coarse stage runs, from level 0 (`None`: all of them,
    /// `log2 N + 1`). With fewer, the search's result (or the refinement's start) is the last
    /// one's map, each of its blocks a square of the grid's pixels; with
    /// [`CoarseLevels::Auto`] the search decides after level 0.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub coarse_levels: Option<CoarseLevels>,
}

/// Why a search cannot start or go on.
#[derive(Debug, Error, PartialEq)]
pub enum SearchError {
    #[error("the search grid must be a power of two, got {0}")]
    Grid(u32),
    #[error("at least one permutation per level is needed")]
    Permutations,
    #[error("the coarse stage runs 1 to {most} levels on a grid of {grid}, got {got}")]
    CoarseLevels { got: u32, most: u32, grid: u32 },
    #[error("the dictionary is empty")]
    EmptyDictionary,
    #[error("dictionary index {0} is not in the material table")]
    DictionaryIndex(u16),
    #[error("unknown-materials mode needs at least one material per level")]
    NoRandomMaterials,
    #[error("the material table is full")]
    TableFull,
    #[error("refinement: {0}")]
    Refine(String),
    #[error("photons: {0}")]
    Photons(String),
    #[error("expected {expected} scores, got {got}")]
    ScoreCount { expected: usize, got: usize },
    #[error("score {0} is not a number")]
    ScoreNaN(f64),
    #[error("the search has finished")]
    Finished,
    #[error("the stored search state is inconsistent: {0}")]
    Inconsistent(String),
}
