//! The search's convergence: at the end of every level and every refinement sweep, the map it
//! stood on, its score, and what the search had consumed by then (the paper's Fig. 6 kind of
//! curve: score against renders and photons).
//!
//! The search state machine does not count what its requests cost (the cache answers some);
//! the step driver ([`crate::steps::Steps`]) does, and notes it here when a step ends a stage
//! ([`Search::note_spent`]). The notes live in the search's state, so a checkpointed search
//! resumes with its curve, and a search replayed from stored scores notes the same figures.

use crate::driver::Consumption;
use crate::machine::Search;
use serde::{Deserialize, Serialize};

/// What the search had consumed when a stage ended (`Consumption`'s counters).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Spent {
    pub requests: u64,
    pub renders: u64,
    /// Photons over all sources.
    pub photons: u64,
}

impl From<&Consumption> for Spent {
    fn from(c: &Consumption) -> Spent {
        Spent {
            requests: c.requests,
            renders: c.renders,
            photons: c.photons,
        }
    }
}

/// Which stage a point ends.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "stage", content = "index")]
pub enum Stage {
    /// The quad-tree level (0: the one-material map).
    Level(u32),
    /// The refinement sweep (from 0).
    Sweep(u32),
}

/// One point of the curve.
#[derive(Debug, Clone, PartialEq)]
pub struct Point {
    pub stage: Stage,
    /// What the search had consumed at the stage's end (`None` only for a stage the driver
    /// has not noted yet).
    pub spent: Option<Spent>,
    /// The stage's score (a level's best, a sweep's confirmed map on its confirmation seed).
    pub score: f64,
    /// The map the stage ended on (at the level's grid for levels).
    pub map: Vec<u16>,
}

/// How many stages `search` has ended: its finished levels, then its sweeps (a sweep ends
/// with its confirmation).
pub fn stages_ended(search: &Search) -> usize {
    search.levels().len() + search.refinement().map_or(0, |r| r.sweeps_done())
}

/// The curve of `search` so far, in order: every level, then every sweep that has ended.
pub fn curve(search: &Search) -> Vec<Point> {
    let spent = search.spent();
    let levels = search
        .levels()
        .iter()
        .map(|l| (Stage::Level(l.level), l.score, &l.assignment));
    let sweeps = search
        .refinement()
        .map(|r| &r.history()[..r.sweeps_done()])
        .unwrap_or_default()
        .iter()
        .map(|s| (Stage::Sweep(s.sweep), s.score, &s.map));
    levels
        .chain(sweeps)
        .enumerate()
        .map(|(i, (stage, score, map))| Point {
            stage,
            spent: spent.get(i).copied(),
            score,
            map: map.clone(),
        })
        .collect()
}
