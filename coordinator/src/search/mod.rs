//! The paper's hierarchical quad-tree permutation search (`model.md`, "Search") as a pure state
//! machine: it emits the render requests it needs next and consumes their scores. It does no
//! I/O and calls no engine; its whole state, the random generator's included, serializes, so a
//! search restored from any step boundary ends exactly as one left alone.
//!
//! Assignments are always at the search grid's resolution (`grid²` material indices, row-major,
//! top row first); a region of level `ℓ` is a square block of `grid / 2^ℓ` pixels.

mod random;

use crate::seeds::{self, Stream};
use rand_chacha::rand_core::SeedableRng;
use rand_chacha::ChaCha8Rng;
use scatterfarm_worker::{Material, MaterialTable};
use serde::{Deserialize, Serialize};
use thiserror::Error;

pub use random::Bounds;

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
    #[serde(default)]
    pub seeding: Seeding,
}

/// Why a search cannot start or go on.
#[derive(Debug, Error, PartialEq)]
pub enum SearchError {
    #[error("the search grid must be a power of two, got {0}")]
    Grid(u32),
    #[error("at least one permutation per level is needed")]
    Permutations,
    #[error("the dictionary is empty")]
    EmptyDictionary,
    #[error("dictionary index {0} is not in the material table")]
    DictionaryIndex(u16),
    #[error("unknown-materials mode needs at least one material per level")]
    NoRandomMaterials,
    #[error("the material table is full")]
    TableFull,
    #[error("expected {expected} scores, got {got}")]
    ScoreCount { expected: usize, got: usize },
    #[error("score {0} is not a number")]
    ScoreNaN(f64),
    #[error("the search has finished")]
    Finished,
}

/// One render the search needs: the assignment and the seed to render it with.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct RenderRequest {
    /// The request's index in the search's deterministic order.
    pub index: u64,
    pub seed: u64,
    /// `grid²` indices into the search's table.
    pub assignment: Vec<u16>,
}

/// The best assignment of a level.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LevelResult {
    pub level: u32,
    pub assignment: Vec<u16>,
    /// The score of the render that produced it.
    pub score: f64,
    /// Which permutation produced it.
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
    pub renders_done: u64,
    /// Renders the whole search needs (an estimate in unknown-materials mode).
    pub renders_total: u64,
    pub best_score: Option<f64>,
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
    /// `None` before level 1 starts (level 0 runs from `pending` alone) and after the end.
    state: Option<LevelState>,
    pending: Vec<RenderRequest>,
    /// Whether `pending` holds step-2 requests after the step-1 ones.
    pending_step2: bool,
    finished: bool,
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
            pending_step2: false,
            finished: false,
        };
        let candidates = search.level_candidates(0, &[])?;
        let pixels = search.pixels();
        let assignments: Vec<Vec<u16>> = candidates.iter().map(|&c| vec![c; pixels]).collect();
        search.state = Some(LevelState {
            level: 0,
            candidates,
            m0: Vec::new(),
            permutation: 0,
            order: vec![0],
            done: 0,
            current: Vec::new(),
            current_score: None,
            best: None,
        });
        search.emit(assignments, false);
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

    /// The final answer, once finished.
    pub fn result(&self) -> Option<&LevelResult> {
        if self.finished {
            self.levels.last()
        } else {
            None
        }
    }

    /// The best assignment known now: the current permutation's `M^{i−1}` if it beats the
    /// last finished level, else that level's best.
    pub fn current_best(&self) -> Option<(Vec<u16>, f64)> {
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

    fn max_level(&self) -> u32 {
        self.config.grid.trailing_zeros()
    }

    /// Where the search stands.
    pub fn progress(&self) -> Progress {
        let levels = self.max_level() + 1;
        let per_level = |level: u32, d: u64| -> u64 {
            if level == 0 {
                d
            } else {
                let regions = 4u64.pow(level);
                u64::from(self.config.permutations) * (d + (regions - 1) * 2 * d)
            }
        };
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
            // Renders of finished work plus this level's and later levels' counts at today's
            // candidate count (exact for dictionary searches).
            let before: u64 = (0..level).map(|l| per_level(l, self.level_d(l))).sum();
            before + (level..levels).map(|l| per_level(l, d)).sum::<u64>()
        };
        Progress {
            level,
            levels,
            permutation,
            permutations: if level == 0 {
                1
            } else {
                self.config.permutations
            },
            region,
            regions,
            renders_done: self.next_request - self.pending.len() as u64,
            renders_total: renders_total.max(self.next_request),
            best_score: self.current_best().map(|(_, s)| s),
        }
    }

    /// Candidates used at a finished level (for render totals).
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

    fn emit(&mut self, assignments: Vec<Vec<u16>>, step2: bool) {
        let level = self.state.as_ref().map(|s| s.level).unwrap_or(0);
        let (seed, seeding) = (self.config.seed, self.config.seeding);
        self.pending = assignments
            .into_iter()
            .map(|assignment| {
                let index = self.next_request;
                self.next_request += 1;
                RenderRequest {
                    index,
                    seed: match seeding {
                        Seeding::PerRequest => seeds::derive(seed, Stream::Render(index)),
                        Seeding::PerLevel => seeds::derive(seed, Stream::LevelRender(level)),
                    },
                    assignment,
                }
            })
            .collect();
        self.pending_step2 = step2;
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

    /// Emits step 1 (and step 2 when `i > 1`) for the next region of the current permutation.
    fn emit_steps(&mut self) {
        let Some(s) = self.state.as_ref() else { return };
        let r = s.order[s.done];
        let mut assignments: Vec<Vec<u16>> = s
            .candidates
            .iter()
            .map(|&c| self.with_region(&s.current, s.level, r, c))
            .collect();
        let step2 = s.done > 0;
        if step2 {
            assignments.extend(
                s.candidates
                    .iter()
                    .map(|&c| self.with_region(&s.m0, s.level, r, c)),
            );
        }
        self.emit(assignments, step2);
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
        self.emit_steps();
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
        });
        self.start_permutation();
        Ok(())
    }

    /// Hands in the scores of every pending request, in order, and advances the search.
    pub fn submit(&mut self, scores: &[f64]) -> Result<(), SearchError> {
        if self.finished {
            return Err(SearchError::Finished);
        }
        if scores.len() != self.pending.len() {
            return Err(SearchError::ScoreCount {
                expected: self.pending.len(),
                got: scores.len(),
            });
        }
        if let Some(&nan) = scores.iter().find(|s| s.is_nan()) {
            return Err(SearchError::ScoreNaN(nan));
        }
        let pending = std::mem::take(&mut self.pending);
        let Some(mut s) = self.state.take() else {
            return Err(SearchError::Finished);
        };
        let d = s.candidates.len();
        // Ties inside a step go to the earlier candidate.
        let best_of = |range: std::ops::Range<usize>| {
            range.fold(None::<usize>, |best, i| match best {
                Some(b) if scores[b] >= scores[i] => Some(b),
                _ => Some(i),
            })
        };
        let Some(b1) = best_of(0..d) else {
            return Err(SearchError::ScoreCount {
                expected: d,
                got: 0,
            });
        };

        if s.level == 0 {
            self.levels.push(LevelResult {
                level: 0,
                assignment: pending[b1].assignment.clone(),
                score: scores[b1],
                permutation: 0,
            });
            return self.after_level();
        }

        // Step 1 against step 2: a tie goes to step 2 (the paper's "otherwise").
        let winner = match self.pending_step2.then(|| best_of(d..2 * d)).flatten() {
            Some(b2) if scores[b2] >= scores[b1] => b2,
            _ => b1,
        };
        s.current = pending[winner].assignment.clone();
        s.current_score = Some(scores[winner]);
        s.done += 1;
        if s.done < s.order.len() {
            self.state = Some(s);
            self.emit_steps();
            return Ok(());
        }
        // The permutation is finished: keep it if it beats the earlier ones (ties: earlier).
        let score = scores[winner];
        if s.best.as_ref().is_none_or(|b| score > b.score) {
            s.best = Some(LevelResult {
                level: s.level,
                assignment: s.current.clone(),
                score,
                permutation: s.permutation,
            });
        }
        s.permutation += 1;
        if s.permutation < self.config.permutations {
            self.state = Some(s);
            self.start_permutation();
            return Ok(());
        }
        if let Some(best) = s.best.take() {
            self.levels.push(best);
        }
        self.after_level()
    }

    fn after_level(&mut self) -> Result<(), SearchError> {
        let next = self.levels.len() as u32;
        if next > self.max_level() {
            self.finished = true;
            self.state = None;
            self.pending.clear();
            Ok(())
        } else {
            self.start_level(next)
        }
    }

    /// The materials of the table, without names.
    pub fn materials(&self) -> Vec<Material> {
        self.table.physics()
    }
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
