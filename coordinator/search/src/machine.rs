//! The paper's hierarchical quad-tree permutation search (`docs/model.md`, "Search") as a pure state
//! machine: it emits the render requests it needs next and consumes their scores. It does no
//! I/O and calls no engine; its whole state, the random generator's included, serializes, so a
//! search restored from any step boundary ends exactly as one left alone.
//!
//! Beside the paper's algorithm (the default configuration) it runs the faster search's
//! options, each on its own:
//! - [`Seeding::PerLevel`]: common random numbers, one seed for every render of a level;
//! - [`Photons`]: a photon budget per level, racing (a first stage with a share of the photons,
//!   the rest spent on the contenders) and the re-scoring of a level's finalists on a fresh seed;
//! - `early_step2`: every `M⁰`-variant (a permutation's step-2 renders, and its first step) is
//!   requested at once when a permutation starts, so they render in parallel up front;
//! - `tie_z` and [`Tiebreak`]: wider ties, and a secondary score where the primary one is
//!   saturated (the decision rule is `ties`).
//!
//! Requests that repeat a render's identity (assignment, seed, photons) are the driver's to
//! answer from its cache: the search asks for what it needs and does not track what was
//! rendered.
//!
//! Assignments are always at the search grid's resolution (`grid²` material indices, row-major,
//! top row first); a region of level `ℓ` is a square block of `grid / 2^ℓ` pixels.
//!
//! This file holds the [`Search`] state and its public face (construction, submission,
//! progress); the rest is one concern per module: `config` (what fixes a search, its errors),
//! `request` (render requests and their scores), `progress` (level results, progress),
//! `level` (the coarse stage's levels, permutations and steps), `stages` (what follows a level:
//! the next one, the refinement stage, the end), `coarse` (how many levels run), `photons`
//! (photon budgets, racing, re-scoring), `ties` (the decision rule), `random` (unknown
//! materials' bounds and draws).

mod coarse;
mod config;
mod level;
mod photons;
mod progress;
mod random;
mod request;
mod stages;
mod ties;

use crate::refine::{BlockScore, RefineRequest, Refinement};
use crate::seeds::{self, Stream};
use rand_chacha::rand_core::SeedableRng;
use rand_chacha::ChaCha8Rng;
use scatterfarm_model::{Material, MaterialTable};
use serde::{Deserialize, Serialize};

pub use coarse::{CoarseLevels, ParseCoarseLevelsError};
pub use config::{Candidates, SearchConfig, SearchError, Seeding};
use level::{LevelState, Step};
pub use photons::{Photons, Race};
pub use progress::{LevelResult, Progress};
pub use random::Bounds;
pub use request::{ChangeScore, RenderRequest, Score};
use ties::Rule;
pub use ties::{Secondary, Tiebreak};

/// What the pending requests are for.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
enum Waiting {
    /// Early step 2: a permutation's `M⁰`-variants. Their scores are not used here: the steps
    /// that need them request them again and the driver answers from its cache.
    Prefetch,
    Step(Step),
    /// A level's distinct finalists on the re-scoring seed.
    Rescore(Vec<LevelResult>),
    /// The refinement stage's requests ([`Search::refinement`]).
    Refine,
}

/// The search state machine.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Search {
    config: SearchConfig,
    table: MaterialTable,
    rng: ChaCha8Rng,
    /// Index of the next render request.
    next_request: u64,
    /// Finished levels.
    levels: Vec<LevelResult>,
    /// `None` after the end.
    state: Option<LevelState>,
    pending: Vec<RenderRequest>,
    /// What `pending` is for (`None` once finished).
    waiting: Option<Waiting>,
    /// The refinement stage, once the last level has finished (with `config.refine`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    refinement: Option<Refinement>,
    /// The refinement's final map and its score on its last confirmation seed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    refined: Option<LevelResult>,
    finished: bool,
    /// What the search had consumed at the end of each stage, noted by the step driver
    /// ([`crate::convergence`]).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    spent: Vec<crate::convergence::Spent>,
    /// The index of the current stage's first request ([`Search::stage_start`]).
    #[serde(default)]
    stage_start: u64,
    /// The refinement sweep the current stage is (`None` before refinement).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    stage_sweep: Option<u32>,
}

impl Search {
    /// A search over `table` (which it extends in unknown-materials mode), with level 0's
    /// requests pending.
    pub fn new(config: SearchConfig, table: MaterialTable) -> Result<Search, SearchError> {
        if !config.grid.is_power_of_two() {
            return Err(SearchError::Grid(config.grid));
        }
        if config.permutations == 0 {
            return Err(SearchError::Permutations);
        }
        let most = config.grid.trailing_zeros() + 1;
        if let Some(CoarseLevels::Count(got)) = config
            .coarse_levels
            .filter(|&c| matches!(c, CoarseLevels::Count(n) if n == 0 || n > most))
        {
            return Err(SearchError::CoarseLevels {
                got,
                most,
                grid: config.grid,
            });
        }
        if let Some(problem) = config.photons.problem() {
            return Err(SearchError::Photons(problem));
        }
        if let Some(problem) = config.refine.as_ref().and_then(|r| r.problem()) {
            return Err(SearchError::Refine(problem));
        }
        match &config.candidates {
            Candidates::Dictionary(d) if d.is_empty() => return Err(SearchError::EmptyDictionary),
            Candidates::Dictionary(d) => {
                if let Some(&i) = d.iter().find(|&&i| usize::from(i) >= table.len()) {
                    return Err(SearchError::DictionaryIndex(i));
                }
            }
            Candidates::Random { per_level: 0, .. } => return Err(SearchError::NoRandomMaterials),
            Candidates::Random { .. } => {}
        }
        let rng = ChaCha8Rng::seed_from_u64(seeds::derive(config.seed, Stream::Search));
        let mut search = Search {
            config,
            table,
            rng,
            next_request: 0,
            levels: Vec::new(),
            state: None,
            pending: Vec::new(),
            waiting: None,
            refinement: None,
            refined: None,
            finished: false,
            spent: Vec::new(),
            stage_start: 0,
            stage_sweep: None,
        };
        let candidates = search.level_candidates(0, &[])?;
        // Level 0 is one step over one region (the whole medium) from a map that every
        // candidate replaces entirely.
        let m0 = vec![candidates[0]; search.pixels()];
        search.state = Some(LevelState::start(0, candidates, m0, vec![0]));
        search.emit_steps();
        Ok(search)
    }

    pub fn config(&self) -> &SearchConfig {
        &self.config
    }

    /// The material table requests index into (it grows per level in unknown-materials mode).
    pub fn table(&self) -> &MaterialTable {
        &self.table
    }

    /// The requests whose scores [`Search::submit`] expects, in order.
    pub fn pending(&self) -> &[RenderRequest] {
        &self.pending
    }

    pub fn is_finished(&self) -> bool {
        self.finished
    }

    /// Every finished level's best.
    pub fn levels(&self) -> &[LevelResult] {
        &self.levels
    }

    /// The final answer, once finished: the refined map when the search refines, else the
    /// last level's best.
    pub fn result(&self) -> Option<&LevelResult> {
        if self.finished {
            self.refined.as_ref().or(self.levels.last())
        } else {
            None
        }
    }

    /// The index of the first request of the current stage: a level, or a refinement sweep
    /// with its confirmation. Every render seed of a stage is its own (a level's seed, a
    /// sweep's, or a request's index), so no later request has the identity of one made
    /// before this index: their scores may be forgotten ([`crate::steps`] does).
    pub fn stage_start(&self) -> u64 {
        self.stage_start
    }

    /// The refinement stage, once it has started.
    pub fn refinement(&self) -> Option<&Refinement> {
        self.refinement.as_ref()
    }

    /// What the search had consumed at the end of each stage so far (levels, then sweeps).
    pub fn spent(&self) -> &[crate::convergence::Spent] {
        &self.spent
    }

    /// Notes what the search has consumed, `used`, for every stage ended since the last note
    /// (the step driver calls it after each step; a search checkpointed before the curve was
    /// recorded notes its earlier stages at the first note after it resumes).
    pub fn note_spent(&mut self, used: &crate::driver::Consumption) {
        let ended = crate::convergence::stages_ended(self);
        if self.spent.len() < ended {
            self.spent.resize(ended, used.into());
        }
    }

    /// Every photons-per-source value the search renders with (each needs its own ε).
    pub fn budgets(&self) -> Vec<u32> {
        let mut budgets = self.config.photons.budgets(self.planned_max_level() + 1);
        if let Some(r) = &self.config.refine {
            budgets.extend(Refinement::photon_levels(r));
            budgets.sort_unstable();
            budgets.dedup();
        }
        budgets
    }

    /// The best assignment known now: during refinement its current map; else the current
    /// permutation's `M^{i−1}` if it beats the last finished level, else that level's best.
    /// (Scores of different seeds and stages are not comparable to the refinement's, so its
    /// map is shown as soon as it has a score.)
    pub fn current_best(&self) -> Option<(Vec<u16>, f64)> {
        if let Some(r) = self.refined.as_ref() {
            return Some((r.assignment.clone(), r.score));
        }
        if let Some((map, Some(score))) = self.refinement.as_ref().map(|r| r.current()) {
            return Some((map.to_vec(), score));
        }
        let finished = self.levels.last().map(|l| (l.assignment.clone(), l.score));
        let in_level = self.state.as_ref().and_then(|s| {
            let best = s.best.as_ref().map(|b| (b.assignment.clone(), b.score));
            let current = s.current_score.map(|sc| (s.current.clone(), sc));
            match (best, current) {
                (Some(b), Some(c)) => Some(if c.1 > b.1 { c } else { b }),
                (b, c) => b.or(c),
            }
        });
        match (finished, in_level) {
            (Some(f), Some(l)) => Some(if l.1 > f.1 { l } else { f }),
            (f, l) => f.or(l),
        }
    }

    pub(super) fn pixels(&self) -> usize {
        (self.config.grid as usize).pow(2)
    }

    /// Checks a search state read back from a store against the invariants every state this
    /// module makes keeps: levels within the grid's, maps of the grid's pixels over the table.
    /// A state that fails is damaged, and would otherwise make progress loop over a level
    /// count of billions or index past a map.
    pub fn check_consistent(&self) -> Result<(), SearchError> {
        let bad = |what: String| Err(SearchError::Inconsistent(what));
        let grid = self.config.grid;
        if grid == 0 || !grid.is_power_of_two() || grid > 4096 {
            return bad(format!("grid {grid}"));
        }
        if let Some(problem) = self.config.photons.problem() {
            return bad(format!("photons: {problem}"));
        }
        if let Some(problem) = self.config.refine.as_ref().and_then(|r| r.problem()) {
            return bad(format!("refinement: {problem}"));
        }
        let (levels, pixels, materials) = (
            self.planned_max_level() + 1,
            self.pixels(),
            self.table.len(),
        );
        let map_ok = |a: &[u16]| a.len() == pixels && a.iter().all(|&m| usize::from(m) < materials);
        if self.levels.len() > levels as usize {
            return bad(format!("{} levels done of {levels}", self.levels.len()));
        }
        if let Some(l) = self
            .levels
            .iter()
            .find(|l| l.level >= levels || !map_ok(&l.assignment))
        {
            return bad(format!("the result of level {}", l.level));
        }
        if let Some(st) = &self.state {
            if st.level >= levels {
                return bad(format!("level {} of {levels}", st.level));
            }
            if !map_ok(&st.m0) || !map_ok(&st.current) {
                return bad(format!("the maps of level {}", st.level));
            }
            if st.candidates.iter().any(|&m| usize::from(m) >= materials) {
                return bad(format!("the candidates of level {}", st.level));
            }
            let regions = 1u64 << (2 * st.level);
            if st.order.iter().any(|&r| u64::from(r) >= regions) || st.done > st.order.len() {
                return bad(format!("the region order of level {}", st.level));
            }
        }
        if let Some(r) = self.pending.iter().find(|r| !map_ok(&r.assignment)) {
            return bad(format!("pending request {}", r.index));
        }
        Ok(())
    }

    /// Where the search stands.
    pub fn progress(&self) -> Progress {
        let levels = self.max_level() + 1;
        let d = self
            .state
            .as_ref()
            .map(|s| s.candidates.len() as u64)
            .unwrap_or(0);
        let (level, permutation, region, regions) = match &self.state {
            Some(s) => (s.level, s.permutation, s.done as u32, s.order.len() as u32),
            None => (self.max_level(), self.config.permutations, 0, 0),
        };
        let renders_total = if self.finished {
            self.next_request
        } else {
            // Requests of finished work plus this level's and later levels' counts at today's
            // candidate count (exact for the paper's search on a dictionary).
            let before: u64 = (0..level)
                .map(|l| self.level_requests(l, self.level_d(l)))
                .sum();
            let refine = match (&self.config.refine, &self.refinement) {
                (Some(r), None) => {
                    u64::from(r.max_sweeps.min(2))
                        * Refinement::requests_per_sweep(self.pixels() as u64, d.max(2))
                }
                (_, Some(r)) => r.requests_left_estimate(),
                (None, None) => 0,
            };
            let levels_left: u64 = if self.state.is_some() {
                (level..levels).map(|l| self.level_requests(l, d)).sum()
            } else {
                0
            };
            before + levels_left + refine
        };
        Progress {
            level,
            levels,
            permutation,
            permutations: self.permutations_of(level),
            region,
            regions,
            renders_done: self.next_request - self.pending.len() as u64,
            renders_total: renders_total.max(self.next_request),
            best_score: self.current_best().map(|(_, s)| s),
            refining: self.refinement.is_some(),
            sweep: self
                .refinement
                .as_ref()
                .map_or(0, |r| r.sweeps_done() as u32),
            sweeps: self.config.refine.as_ref().map_or(0, |r| r.max_sweeps),
        }
    }

    /// Hands in the scores of every pending request, in order, as exact values.
    pub fn submit(&mut self, scores: &[f64]) -> Result<(), SearchError> {
        let scores: Vec<Score> = scores.iter().map(|&v| Score::exact(v)).collect();
        self.submit_scores(&scores)
    }

    /// Hands in the scores of every pending request, in order, and advances the search.
    pub fn submit_scores(&mut self, scores: &[Score]) -> Result<(), SearchError> {
        if self.finished {
            return Err(SearchError::Finished);
        }
        if scores.len() != self.pending.len() {
            return Err(SearchError::ScoreCount {
                expected: self.pending.len(),
                got: scores.len(),
            });
        }
        if let Some(nan) = scores
            .iter()
            .find(|s| s.value.is_nan() || s.std_error.is_nan())
        {
            return Err(SearchError::ScoreNaN(nan.value));
        }
        let Some(waiting) = self.waiting.take() else {
            return Err(SearchError::Finished);
        };
        self.pending.clear();
        match waiting {
            Waiting::Prefetch => {
                self.emit_steps();
                Ok(())
            }
            Waiting::Step(step) => self.step_scored(step, scores),
            Waiting::Refine => self.refine_scored(scores),
            Waiting::Rescore(finalists) => {
                // The best re-scored finalist (ties: the earlier permutation).
                let best = self.rule().rescored(scores).unwrap_or(0);
                if let Some(f) = finalists.get(best) {
                    self.levels.push(LevelResult {
                        score: scores[best].value,
                        ..f.clone()
                    });
                }
                self.after_level()
            }
        }
    }

    /// The materials of the table, without names.
    pub fn materials(&self) -> Vec<Material> {
        self.table.physics()
    }
}

/// The index in `range` of the highest score (ties: the earliest).
fn best_of(scores: &[Score], range: std::ops::Range<usize>) -> Option<usize> {
    range.fold(None::<usize>, |best, i| match best {
        Some(b) if scores[b].value >= scores[i].value => Some(b),
        _ => Some(i),
    })
}

/// The distinct values of `a`, ascending.
fn distinct(a: &[u16]) -> Vec<u16> {
    let mut v = a.to_vec();
    v.sort_unstable();
    v.dedup();
    v
}

#[cfg(test)]
mod tests;
