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

mod coarse;
mod photons;
mod random;
mod ties;

use crate::refine::{BlockScore, RefineConfig, RefineRequest, Refinement};
use crate::seeds::{self, Stream};
use rand_chacha::rand_core::SeedableRng;
use rand_chacha::ChaCha8Rng;
use scatterfarm_model::Change;
use scatterfarm_model::{Material, MaterialTable};
use serde::{Deserialize, Serialize};
use thiserror::Error;

pub use coarse::{CoarseLevels, ParseCoarseLevelsError};
pub use photons::{Photons, Race};
pub use random::Bounds;
use ties::Rule;
pub use ties::{Secondary, Tiebreak};

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
    /// candidates (scores then carry [`Score::secondary`]).
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

/// One render the search needs: the assignment, the seed and the photons to render it with.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct RenderRequest {
    /// The request's index in the search's deterministic order.
    pub index: u64,
    pub seed: u64,
    /// Photons per source.
    pub photons: u32,
    /// `grid²` indices into the search's table.
    pub assignment: Vec<u16>,
    /// A differential render (`docs/model.md`, "Differential renders"): the changes of
    /// `assignment` whose scores the same photons also estimate. Empty for a plain render.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub changes: Vec<Change>,
}

/// A render's score and its standard error from the render's own Monte Carlo noise
/// (`similarity::score`); racing compares candidates with it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Score {
    pub value: f64,
    pub std_error: f64,
    /// The tiebreak's score of the same render, when the search has a [`Tiebreak`].
    pub secondary: Option<Secondary>,
    /// The likelihood score split into interleaved blocks of observations
    /// ([`crate::likelihood`]): two renders on one seed are compared by their blocks' paired
    /// differences. Empty for the other metrics.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub blocks: Vec<f64>,
    /// A differential render's estimated scores of its request's changes, in order (`None`:
    /// the change could not be reweighted). Empty for a plain render.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub changes: Vec<Option<ChangeScore>>,
}

/// The likelihood score of one change estimated by a differential render: its value and its
/// blocks, paired with the rendered map's.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ChangeScore {
    pub value: f64,
    pub blocks: Vec<f64>,
}

impl Score {
    /// A score known without error.
    pub fn exact(value: f64) -> Score {
        Score {
            value,
            std_error: 0.0,
            secondary: None,
            blocks: Vec::new(),
            changes: Vec::new(),
        }
    }

    /// The likelihood score of a render from its deviance, wherever that was computed (here,
    /// or by the worker that rendered it): the value and blocks as they are, the standard
    /// error the blocks' spread.
    pub fn of_deviance(d: scatterfarm_model::likelihood::Deviance) -> Score {
        Score {
            value: d.value,
            std_error: crate::likelihood::spread(&d.blocks),
            secondary: None,
            blocks: d.blocks,
            changes: Vec::new(),
        }
    }
}

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

/// A racing step's stage.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
enum Stage {
    /// Every candidate with the level's photons (no racing).
    Full,
    /// Every candidate with the first stage's photons.
    First,
    /// These candidates (indices into the step's) with the level's photons.
    Second { survivors: Vec<usize> },
}

/// One step's candidates: step 1's, then step 2's from `step2_from`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct Step {
    assignments: Vec<Vec<u16>>,
    /// Each candidate's seed: both racing stages render a candidate on it.
    seeds: Vec<u64>,
    step2_from: usize,
    stage: Stage,
}

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

/// The search's position inside a level.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct LevelState {
    level: u32,
    /// Candidate materials of this level, in tie-breaking order.
    candidates: Vec<u16>,
    /// `M⁰`: every region with its parent's material.
    m0: Vec<u16>,
    permutation: u32,
    /// The regions in this permutation's order.
    order: Vec<u32>,
    /// Regions done in this permutation (`i − 1`).
    done: usize,
    /// `M^{i−1}` and the score of the render that produced it.
    current: Vec<u16>,
    current_score: Option<f64>,
    /// The best final `M^R` of the permutations so far.
    best: Option<LevelResult>,
    /// The distinct final maps `M^R` of the finished permutations, each as it first came (for
    /// re-scoring).
    finals: Vec<LevelResult>,
    /// With early step 2 and per-request seeds: the index of this permutation's first
    /// `M⁰`-variant request, whose seeds the steps reuse.
    early_base: Option<u64>,
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
        search.state = Some(LevelState {
            level: 0,
            candidates,
            m0: m0.clone(),
            permutation: 0,
            order: vec![0],
            done: 0,
            current: m0,
            current_score: None,
            best: None,
            finals: Vec::new(),
            early_base: None,
        });
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

    fn pixels(&self) -> usize {
        (self.config.grid as usize).pow(2)
    }

    /// The last level the coarse stage runs ([`SearchConfig::coarse_levels`]); under
    /// [`CoarseLevels::Auto`], decided once level 0 has ended (the finest until then).
    fn max_level(&self) -> u32 {
        let finest = self.config.grid.trailing_zeros();
        match self.config.coarse_levels {
            None => finest,
            Some(CoarseLevels::Count(n)) => n.saturating_sub(1).min(finest),
            Some(CoarseLevels::Auto) => match self.levels.first() {
                Some(zero) if self.refines_from_level_zero(&zero.assignment) => 0,
                _ => finest,
            },
        }
    }

    /// The last level the coarse stage may run: [`Search::max_level`] where it is fixed, the
    /// finest under [`CoarseLevels::Auto`] (what is planned before level 0 ends, such as ε's
    /// photon budgets, covers every level it might run).
    fn planned_max_level(&self) -> u32 {
        match self.config.coarse_levels {
            Some(CoarseLevels::Auto) => self.config.grid.trailing_zeros(),
            _ => self.max_level(),
        }
    }

    /// [`coarse::refines_from_level_zero`] for this search's refinement and candidates.
    fn refines_from_level_zero(&self, level_zero: &[u16]) -> bool {
        match &self.config.candidates {
            Candidates::Dictionary(d) => coarse::refines_from_level_zero(
                self.config.refine.as_ref(),
                level_zero,
                &self.table.physics(),
                d,
            ),
            // Unknown-materials mode: the levels draw the materials the refinement then
            // tries (level 0's map holds one), so every level runs.
            Candidates::Random { .. } => false,
        }
    }

    /// Permutations of `level` (level 0 has one step and no permutations).
    fn permutations_of(&self, level: u32) -> u32 {
        if level == 0 {
            1
        } else {
            self.config.permutations
        }
    }

    /// Requests a level with `d` candidates makes.
    fn level_requests(&self, level: u32, d: u64) -> u64 {
        let racing = self.config.photons.first_stage(level).is_some();
        // With racing, every candidate runs the first stage and, on a guess, half the second.
        let staged = |n: u64| if racing { n + n.div_ceil(2) } else { n };
        if level == 0 {
            return staged(d);
        }
        let regions = 4u64.pow(level);
        let t = u64::from(self.config.permutations);
        let steps = t * (staged(d) + (regions - 1) * staged(2 * d));
        let prefetch = match (self.config.early_step2, self.config.seeding) {
            (false, _) => 0,
            (true, Seeding::PerLevel) => regions * d,
            (true, Seeding::PerRequest) => t * regions * d,
        };
        let rescore = if self.config.photons.rescore.is_some() {
            t + 1
        } else {
            0
        };
        steps + prefetch + rescore
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

    /// Candidates used at a finished level (for request totals).
    fn level_d(&self, level: u32) -> u64 {
        match &self.config.candidates {
            Candidates::Dictionary(d) => d.len() as u64,
            Candidates::Random { per_level, .. } => {
                let parent = if level == 0 {
                    None
                } else {
                    self.levels.get(level as usize - 1)
                };
                let inherited = parent
                    .map(|p| distinct(&p.assignment).len() as u64)
                    .unwrap_or(0);
                u64::from(*per_level) + inherited
            }
        }
    }

    /// The candidates of `level` given `M⁰`; draws new materials in unknown-materials mode.
    fn level_candidates(&mut self, level: u32, m0: &[u16]) -> Result<Vec<u16>, SearchError> {
        match self.config.candidates.clone() {
            Candidates::Dictionary(d) => Ok(d),
            Candidates::Random { per_level, bounds } => {
                let mut candidates = distinct(m0);
                for j in 0..per_level {
                    let m = bounds.draw(&mut self.rng);
                    if self.table.len() >= usize::from(u16::MAX) {
                        return Err(SearchError::TableFull);
                    }
                    candidates.push(self.table.push(format!("random-l{level}-{j}"), m));
                }
                Ok(candidates)
            }
        }
    }

    /// The seed of request `index` of `level` under the configured seeding.
    fn seed_for(&self, level: u32, index: u64) -> u64 {
        match self.config.seeding {
            Seeding::PerRequest => seeds::derive(self.config.seed, Stream::Render(index)),
            Seeding::PerLevel => seeds::derive(self.config.seed, Stream::LevelRender(level)),
        }
    }

    /// Makes `(assignment, seed, photons)` the pending requests, numbered in order.
    fn emit(&mut self, requests: Vec<(Vec<u16>, u64, u32)>, waiting: Waiting) {
        let requests = requests
            .into_iter()
            .map(|(assignment, seed, photons)| RefineRequest {
                assignment,
                seed,
                photons,
                changes: Vec::new(),
            })
            .collect();
        self.emit_requests(requests, waiting);
    }

    /// Makes `requests` pending, numbered in order.
    fn emit_requests(&mut self, requests: Vec<RefineRequest>, waiting: Waiting) {
        self.pending = requests
            .into_iter()
            .map(|r| {
                let index = self.next_request;
                self.next_request += 1;
                RenderRequest {
                    index,
                    seed: r.seed,
                    photons: r.photons,
                    assignment: r.assignment,
                    changes: r.changes,
                }
            })
            .collect();
        self.waiting = Some(waiting);
    }

    /// The pixels of region `r` at `level`.
    fn region_pixels(&self, level: u32, r: u32) -> impl Iterator<Item = usize> {
        let n = self.config.grid as usize;
        let side = 1usize << level;
        let block = n / side;
        let (ry, rx) = (r as usize / side, r as usize % side);
        (0..block).flat_map(move |y| (0..block).map(move |x| (ry * block + y) * n + rx * block + x))
    }

    fn with_region(&self, base: &[u16], level: u32, r: u32, material: u16) -> Vec<u16> {
        let mut a = base.to_vec();
        for p in self.region_pixels(level, r) {
            a[p] = material;
        }
        a
    }

    /// Photons per source of a step's first requests at `level`, and their stage.
    fn opening_stage(&self, level: u32) -> (u32, Stage) {
        match self.config.photons.first_stage(level) {
            Some(first) => (first, Stage::First),
            None => (self.config.photons.level(level), Stage::Full),
        }
    }

    /// Emits the steps (1, and 2 when `i > 1`) for the next region of the current permutation.
    fn emit_steps(&mut self) {
        let Some(s) = self.state.as_ref() else { return };
        let (level, r, d) = (s.level, s.order[s.done], s.candidates.len());
        let mut assignments: Vec<Vec<u16>> = s
            .candidates
            .iter()
            .map(|&c| self.with_region(&s.current, level, r, c))
            .collect();
        if s.done > 0 {
            assignments.extend(
                s.candidates
                    .iter()
                    .map(|&c| self.with_region(&s.m0, level, r, c)),
            );
        }
        // An `M⁰`-variant requested up front (step 2's candidates, and step 1's at i = 1)
        // keeps that request's seed; everything else is seeded by its own request index.
        let early_seed = |j: usize| {
            s.early_base
                .map(|base| self.seed_for(level, base + (s.done * d + j) as u64))
        };
        let first = self.next_request;
        let seeds: Vec<u64> = (0..assignments.len())
            .map(|j| {
                let variant = if s.done == 0 {
                    Some(j)
                } else {
                    j.checked_sub(d)
                };
                variant
                    .and_then(early_seed)
                    .unwrap_or_else(|| self.seed_for(level, first + j as u64))
            })
            .collect();
        let (photons, stage) = self.opening_stage(level);
        let requests = assignments
            .iter()
            .zip(&seeds)
            .map(|(a, &seed)| (a.clone(), seed, photons))
            .collect();
        let step = Step {
            step2_from: if s.done > 0 { d } else { assignments.len() },
            assignments,
            seeds,
            stage,
        };
        self.emit(requests, Waiting::Step(step));
    }

    /// Starts permutation `permutation` of `level` from `M⁰`.
    fn start_permutation(&mut self) {
        let Some(s) = self.state.as_mut() else { return };
        let regions = 4u32.pow(s.level);
        let mut order: Vec<u32> = (0..regions).collect();
        random::shuffle(&mut self.rng, &mut order);
        s.order = order;
        s.done = 0;
        s.current = s.m0.clone();
        s.current_score = None;
        s.early_base = None;
        let prefetch = self.config.early_step2
            && !(self.config.seeding == Seeding::PerLevel && s.permutation > 0);
        if !prefetch {
            self.emit_steps();
            return;
        }
        // Every M⁰-variant, in the permutation's region order; under common random numbers
        // they are the same for every permutation of the level, so only the first asks.
        let Some(s) = self.state.as_ref() else { return };
        let level = s.level;
        let (photons, _) = self.opening_stage(level);
        let first = self.next_request;
        let mut requests = Vec::new();
        for &r in &s.order {
            for &c in &s.candidates {
                let seed = self.seed_for(level, first + requests.len() as u64);
                requests.push((self.with_region(&s.m0, level, r, c), seed, photons));
            }
        }
        if self.config.seeding == Seeding::PerRequest {
            if let Some(s) = self.state.as_mut() {
                s.early_base = Some(first);
            }
        }
        self.emit(requests, Waiting::Prefetch);
    }

    /// Starts `level` (≥ 1) from the previous level's best.
    fn start_level(&mut self, level: u32) -> Result<(), SearchError> {
        let m0 = self
            .levels
            .last()
            .map(|l| l.assignment.clone())
            .unwrap_or_default();
        let candidates = self.level_candidates(level, &m0)?;
        self.state = Some(LevelState {
            level,
            candidates,
            m0: m0.clone(),
            permutation: 0,
            order: Vec::new(),
            done: 0,
            current: m0,
            current_score: None,
            best: None,
            finals: Vec::new(),
            early_base: None,
        });
        self.stage_start = self.next_request;
        self.start_permutation();
        Ok(())
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

    /// A step's stage came back: race on, or decide the step.
    fn step_scored(&mut self, step: Step, scores: &[Score]) -> Result<(), SearchError> {
        let evaluated: Vec<usize> = match &step.stage {
            Stage::Full => (0..step.assignments.len()).collect(),
            Stage::Second { survivors } => survivors.clone(),
            Stage::First => {
                let race = self
                    .config
                    .photons
                    .race
                    .unwrap_or(Race { share: 1.0, z: 0.0 });
                let leader = best_of(scores, 0..scores.len()).unwrap_or(0);
                let (lv, le) = (scores[leader].value, scores[leader].std_error);
                let survivors: Vec<usize> = (0..scores.len())
                    .filter(|&c| {
                        c == leader || race.survives(scores[c].value, scores[c].std_error, lv, le)
                    })
                    .collect();
                let level = self.state.as_ref().map(|s| s.level).unwrap_or(0);
                let photons = self.config.photons.level(level);
                let requests = survivors
                    .iter()
                    .map(|&c| (step.assignments[c].clone(), step.seeds[c], photons))
                    .collect();
                self.emit(
                    requests,
                    Waiting::Step(Step {
                        stage: Stage::Second { survivors },
                        ..step
                    }),
                );
                return Ok(());
            }
        };
        // Ties (the paper's rule, `ties`): inside a step the earliest candidate tied with the
        // best, between the steps step 2 unless step 1 beats it (its "otherwise").
        let rule = self.rule();
        let score_of = |c: usize| {
            evaluated
                .iter()
                .position(|&e| e == c)
                .map(|k| scores[k].clone())
        };
        let best_in = |range: std::ops::Range<usize>| {
            let scored: Vec<(usize, Score)> =
                range.filter_map(|c| score_of(c).map(|s| (c, s))).collect();
            rule.best(&scored)
        };
        let b1 = best_in(0..step.step2_from);
        let b2 = best_in(step.step2_from..step.assignments.len());
        let Some((winner, Score { value: score, .. })) = rule.between(b1, b2) else {
            return Err(SearchError::ScoreCount {
                expected: step.assignments.len(),
                got: 0,
            });
        };
        let Some(mut s) = self.state.take() else {
            return Err(SearchError::Finished);
        };
        s.current = step.assignments[winner].clone();
        s.current_score = Some(score);
        s.done += 1;
        if s.done < s.order.len() {
            self.state = Some(s);
            self.emit_steps();
            return Ok(());
        }
        // The permutation is finished: keep it if it beats the earlier ones (ties: earlier).
        let last = LevelResult {
            level: s.level,
            assignment: s.current.clone(),
            score,
            permutation: s.permutation,
        };
        if s.best.as_ref().is_none_or(|b| score > b.score) {
            s.best = Some(last.clone());
        }
        // Only the first of equal maps: re-scoring takes the distinct finalists, first
        // occurrence first, so the result is the same, and the checkpoint written after every
        // step no longer grows with every permutation finished.
        if !s.finals.iter().any(|f| f.assignment == last.assignment) {
            s.finals.push(last);
        }
        s.permutation += 1;
        if s.permutation < self.permutations_of(s.level) {
            self.state = Some(s);
            self.start_permutation();
            return Ok(());
        }
        // Re-scoring: the distinct finalists on one fresh seed, when there is a choice. The
        // level's starting map `M⁰` is the last finalist (numbered as permutation T), so a
        // level whose changes a fresh render does not confirm keeps its parent's map.
        let mut finalists: Vec<LevelResult> = Vec::new();
        let start = LevelResult {
            level: s.level,
            assignment: s.m0.clone(),
            // Replaced by its re-scoring; the parent's score until then (a finite number, as
            // checkpoints need).
            score: self.levels.last().map_or(0.0, |l| l.score),
            permutation: self.config.permutations,
        };
        for f in s.finals.iter().chain([&start]) {
            if !finalists.iter().any(|g| g.assignment == f.assignment) {
                finalists.push(f.clone());
            }
        }
        let level = s.level;
        match self.config.photons.rescore {
            Some(photons) if level > 0 && finalists.len() > 1 => {
                let seed = seeds::derive(self.config.seed, Stream::Rescore(level));
                let requests = finalists
                    .iter()
                    .map(|f| (f.assignment.clone(), seed, photons))
                    .collect();
                self.state = Some(s);
                self.emit(requests, Waiting::Rescore(finalists));
                Ok(())
            }
            _ => {
                if let Some(best) = s.best.take() {
                    self.levels.push(best);
                }
                self.after_level()
            }
        }
    }

    /// The decision rule of this search's configuration.
    fn rule(&self) -> Rule {
        Rule {
            tie_z: self.config.tie_z,
            tiebreak: self.config.tiebreak,
        }
    }

    fn after_level(&mut self) -> Result<(), SearchError> {
        let next = self.levels.len() as u32;
        if next <= self.max_level() {
            return self.start_level(next);
        }
        self.state = None;
        match (self.config.refine.clone(), self.levels.last().cloned()) {
            (Some(config), Some(last)) => {
                let materials = match &self.config.candidates {
                    Candidates::Dictionary(d) => d.clone(),
                    Candidates::Random { .. } => distinct(&last.assignment),
                };
                let physics = self.table.physics();
                let reweightable = physics
                    .iter()
                    .map(|from| {
                        physics
                            .iter()
                            .map(|to| scatterfarm_model::differential::reweightable(from, to))
                            .collect()
                    })
                    .collect();
                let opaque = physics.iter().map(|m| m.is_opaque()).collect();
                let spread = physics
                    .iter()
                    .map(|from| {
                        physics
                            .iter()
                            .map(|to| {
                                // Finite, for the checkpoint's JSON: an unsupported
                                // change is refused by `reweightable` anyway.
                                scatterfarm_model::differential::weight_spread(
                                    from,
                                    to,
                                    config.pixel_mm,
                                )
                                .min(f64::MAX)
                            })
                            .collect()
                    })
                    .collect();
                self.refinement = Some(Refinement::with_spread(
                    config,
                    self.config.grid,
                    materials,
                    self.config.seed,
                    last.assignment,
                    reweightable,
                    opaque,
                    spread,
                ));
                self.emit_refinement();
                Ok(())
            }
            _ => {
                self.finish();
                Ok(())
            }
        }
    }

    fn finish(&mut self) {
        self.finished = true;
        self.state = None;
        self.pending.clear();
        self.waiting = None;
    }

    /// Makes the refinement's requests pending, or ends the search when it has finished.
    fn emit_refinement(&mut self) {
        let Some(r) = self.refinement.as_ref() else {
            self.finish();
            return;
        };
        if r.is_finished() {
            // The refined map is of the grid's pixels, whatever level the coarse stage ended.
            let level = self.config.grid.trailing_zeros();
            let (map, score) = r.current();
            let last = self.levels.last();
            self.refined = Some(LevelResult {
                level,
                assignment: map.to_vec(),
                score: score.or(last.map(|l| l.score)).unwrap_or(0.0),
                permutation: last.map_or(0, |l| l.permutation),
            });
            self.finish();
            return;
        }
        if self.stage_sweep != Some(r.sweep()) {
            self.stage_sweep = Some(r.sweep());
            self.stage_start = self.next_request;
        }
        let requests = r.pending().to_vec();
        self.emit_requests(requests, Waiting::Refine);
    }

    /// The refinement's requests came back.
    fn refine_scored(&mut self, scores: &[Score]) -> Result<(), SearchError> {
        let Some(r) = self.refinement.as_mut() else {
            return Err(SearchError::Finished);
        };
        let blocks: Vec<BlockScore> = scores
            .iter()
            .map(|s| BlockScore {
                value: s.value,
                blocks: &s.blocks,
                changes: &s.changes,
            })
            .collect();
        r.submit(&blocks).map_err(SearchError::Refine)?;
        self.emit_refinement();
        Ok(())
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
