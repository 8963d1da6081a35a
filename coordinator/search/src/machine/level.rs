//! The coarse stage: one quad-tree level after another, each a number of permutations of its
//! regions, each region a step of candidate renders (`docs/model.md`, "Search"), and the
//! levels the stage runs.

use super::*;

/// A racing step's stage.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(super) enum Stage {
    /// Every candidate with the level's photons (no racing).
    Full,
    /// Every candidate with the first stage's photons.
    First,
    /// These candidates (indices into the step's) with the level's photons.
    Second { survivors: Vec<usize> },
}

/// One step's candidates: step 1's, then step 2's from `step2_from`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(super) struct Step {
    pub(super) assignments: Vec<Vec<u16>>,
    /// Each candidate's seed: both racing stages render a candidate on it.
    pub(super) seeds: Vec<u64>,
    pub(super) step2_from: usize,
    pub(super) stage: Stage,
}

/// The search's position inside a level.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(super) struct LevelState {
    pub(super) level: u32,
    /// Candidate materials of this level, in tie-breaking order.
    pub(super) candidates: Vec<u16>,
    /// `M⁰`: every region with its parent's material.
    pub(super) m0: Vec<u16>,
    pub(super) permutation: u32,
    /// The regions in this permutation's order.
    pub(super) order: Vec<u32>,
    /// Regions done in this permutation (`i − 1`).
    pub(super) done: usize,
    /// `M^{i−1}` and the score of the render that produced it.
    pub(super) current: Vec<u16>,
    pub(super) current_score: Option<f64>,
    /// The best final `M^R` of the permutations so far.
    pub(super) best: Option<LevelResult>,
    /// The distinct final maps `M^R` of the finished permutations, each as it first came (for
    /// re-scoring).
    pub(super) finals: Vec<LevelResult>,
    /// With early step 2 and per-request seeds: the index of this permutation's first
    /// `M⁰`-variant request, whose seeds the steps reuse.
    pub(super) early_base: Option<u64>,
}

impl LevelState {
    /// The start of `level` from `m0`, before its first permutation (`order`: that
    /// permutation's regions where already known).
    pub(super) fn start(level: u32, candidates: Vec<u16>, m0: Vec<u16>, order: Vec<u32>) -> Self {
        LevelState {
            level,
            candidates,
            m0: m0.clone(),
            permutation: 0,
            order,
            done: 0,
            current: m0,
            current_score: None,
            best: None,
            finals: Vec::new(),
            early_base: None,
        }
    }
}

impl Search {
    /// The last level the coarse stage runs ([`SearchConfig::coarse_levels`]); under
    /// [`CoarseLevels::Auto`], decided once level 0 has ended (the finest until then).
    pub(super) fn max_level(&self) -> u32 {
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
    pub(super) fn planned_max_level(&self) -> u32 {
        match self.config.coarse_levels {
            Some(CoarseLevels::Auto) => self.config.grid.trailing_zeros(),
            _ => self.max_level(),
        }
    }

    /// [`coarse::refines_from_level_zero`] for this search's refinement and candidates.
    pub(super) fn refines_from_level_zero(&self, level_zero: &[u16]) -> bool {
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
    pub(super) fn permutations_of(&self, level: u32) -> u32 {
        if level == 0 {
            1
        } else {
            self.config.permutations
        }
    }

    /// Requests a level with `d` candidates makes.
    pub(super) fn level_requests(&self, level: u32, d: u64) -> u64 {
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

    /// Candidates used at a finished level (for request totals).
    pub(super) fn level_d(&self, level: u32) -> u64 {
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
    pub(super) fn level_candidates(
        &mut self,
        level: u32,
        m0: &[u16],
    ) -> Result<Vec<u16>, SearchError> {
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
    pub(super) fn seed_for(&self, level: u32, index: u64) -> u64 {
        match self.config.seeding {
            Seeding::PerRequest => seeds::derive(self.config.seed, Stream::Render(index)),
            Seeding::PerLevel => seeds::derive(self.config.seed, Stream::LevelRender(level)),
        }
    }

    /// Makes `(assignment, seed, photons)` the pending requests, numbered in order.
    pub(super) fn emit(&mut self, requests: Vec<(Vec<u16>, u64, u32)>, waiting: Waiting) {
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

    /// The pixels of region `r` at `level`.
    pub(super) fn region_pixels(&self, level: u32, r: u32) -> impl Iterator<Item = usize> {
        let n = self.config.grid as usize;
        let side = 1usize << level;
        let block = n / side;
        let (ry, rx) = (r as usize / side, r as usize % side);
        (0..block).flat_map(move |y| (0..block).map(move |x| (ry * block + y) * n + rx * block + x))
    }

    pub(super) fn with_region(&self, base: &[u16], level: u32, r: u32, material: u16) -> Vec<u16> {
        let mut a = base.to_vec();
        for p in self.region_pixels(level, r) {
            a[p] = material;
        }
        a
    }

    /// Photons per source of a step's first requests at `level`, and their stage.
    pub(super) fn opening_stage(&self, level: u32) -> (u32, Stage) {
        match self.config.photons.first_stage(level) {
            Some(first) => (first, Stage::First),
            None => (self.config.photons.level(level), Stage::Full),
        }
    }

    /// Emits the steps (1, and 2 when `i > 1`) for the next region of the current permutation.
    pub(super) fn emit_steps(&mut self) {
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
    pub(super) fn start_permutation(&mut self) {
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
    pub(super) fn start_level(&mut self, level: u32) -> Result<(), SearchError> {
        let m0 = self
            .levels
            .last()
            .map(|l| l.assignment.clone())
            .unwrap_or_default();
        let candidates = self.level_candidates(level, &m0)?;
        self.state = Some(LevelState::start(level, candidates, m0, Vec::new()));
        self.stage_start = self.next_request;
        self.start_permutation();
        Ok(())
    }

    /// A step's stage came back: race on, or decide the step.
    pub(super) fn step_scored(&mut self, step: Step, scores: &[Score]) -> Result<(), SearchError> {
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
    pub(super) fn rule(&self) -> Rule {
        Rule {
            tie_z: self.config.tie_z,
            tiebreak: self.config.tiebreak,
        }
    }
}
