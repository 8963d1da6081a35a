//! The one driver of a search's steps, shared by every place a search runs: in this process
//! ([`crate::driver::drive`]) and on the farm (the coordinator's jobs, which add leases and
//! persistence around it).
//!
//! [`Steps::next`] looks at the search's pending requests: every request whose render identity
//! ([`crate::identity`]) already has a score is answered from the score cache; when all are,
//! the step is submitted and its consumption counted; otherwise the missing renders come back as
//! [`StepGroup`]s, grouped by the photon range they still need (a racing contender's full render
//! starts after its first stage, whose counts [`Prefixes`] holds). A caller renders each group
//! however it likes and hands the counts to [`Steps::complete`], which scores them.
//!
//! What the search consumed is derived from the score cache alone (which step each score was
//! rendered for), so a driver restored from stored scores counts exactly what one left alone
//! does.
//!
//! The cache holds one stage's scores: when the search moves to a new stage (a level, or a
//! refinement sweep, [`Search::stage_start`]) the scores of steps before it are forgotten, since
//! no later request can have their identities (a differential render's scores are about 1 MB,
//! so a long refinement would otherwise grow without end). What is kept is a function of the
//! stage alone, so a driver restored mid-stage from every stored score keeps what one left
//! alone does, and counts the same.

use crate::driver::{Consumption, Scoring};
use crate::identity::{identity, Identity};
use crate::machine::{Score, Search};
use crate::prefixes::{Prefixes, DEFAULT_BYTES};
use anyhow::{Context, Result};
use scatterfarm_model::{Change, CountMatrix, DifferentialOutput, Geometry, RenderItem};
use std::collections::{BTreeMap, HashMap};

/// One render of a group: its identity and what the engine renders.
#[derive(Debug, Clone)]
pub struct GroupItem {
    /// The render's identity: its score is cached under it.
    pub identity: Identity,
    pub item: RenderItem,
}

/// Renders of the current step that need the same photon range.
#[derive(Debug, Clone)]
pub struct StepGroup {
    pub items: Vec<GroupItem>,
    /// The first photon per source still to render: photons `[0, start)` of every item are in
    /// `prefixes`.
    pub start: u32,
    /// Photons per source of every render of the group, when complete.
    pub photons: u32,
    /// The counts of photons `[0, start)` of every item, in order (empty when `start` is 0).
    pub prefixes: Vec<CountMatrix>,
    /// A differential render (one item, from photon 0): the changes it also estimates
    /// ([`Steps::complete_differential`] scores it). Empty for plain renders.
    pub changes: Vec<Change>,
    /// Whether [`Steps::keep`] keeps the group's counts (racing's first stage, extended by a
    /// later full render): a group that does not may be scored where it is rendered, its
    /// counts never handed over.
    pub keeps_counts: bool,
}

/// What [`Steps::next`] did.
#[derive(Debug)]
pub enum Next {
    /// A step was answered from the cache and submitted; the search moved on.
    Submitted,
    /// The current step needs these renders first.
    Render(Vec<StepGroup>),
    /// The search has finished.
    Finished,
}

/// A new score for the caller to keep (the farm stores it): identity, score, and the index of
/// the first request of the step it was rendered for.
pub type NewScore = (Identity, Score, u64);

/// The score cache and racing prefixes of one search.
#[derive(Debug)]
pub struct Steps {
    geometry: Geometry,
    fingerprint: String,
    /// Scores by render identity, with the first request index of the step each was rendered
    /// for.
    scores: HashMap<Identity, (Score, u64)>,
    /// Racing's first-stage counts of the current level (memory only: without them a
    /// contender renders from photon 0, to the same counts).
    prefixes: Prefixes,
    prefix_level: u32,
    /// The stage start the cache was last pruned to.
    pruned_to: u64,
    /// Whether earlier stages' scores are forgotten (off only in tests that measure that
    /// forgetting them changes nothing).
    forget: bool,
}

impl Steps {
    /// A driver for searches rendered on `geometry` by an engine of `fingerprint`, knowing
    /// `scores` (stored ones, when a job resumes).
    pub fn new(
        geometry: Geometry,
        fingerprint: &str,
        scores: impl IntoIterator<Item = (Identity, (Score, u64))>,
    ) -> Steps {
        Steps {
            geometry,
            fingerprint: fingerprint.to_string(),
            scores: scores.into_iter().collect(),
            prefixes: Prefixes::new(DEFAULT_BYTES),
            prefix_level: 0,
            pruned_to: 0,
            forget: true,
        }
    }

    /// Scores held now.
    pub fn cached(&self) -> usize {
        self.scores.len()
    }

    /// Keeps every score, of every stage (for tests comparing against the bounded cache).
    #[cfg(test)]
    pub(crate) fn keep_every_stage(&mut self) {
        self.forget = false;
    }

    /// Forgets the scores of steps before the search's current stage.
    fn prune(&mut self, search: &Search) {
        let start = search.stage_start();
        if self.forget && start > self.pruned_to {
            self.scores.retain(|_, (_, step)| *step >= start);
            self.pruned_to = start;
        }
    }

    /// The engine fingerprint renders are identified with.
    pub fn fingerprint(&self) -> &str {
        &self.fingerprint
    }

    /// The identity of a render of `search`'s table on this driver's geometry and engine.
    fn identity_of(
        &self,
        search: &Search,
        assignment: &[u16],
        seed: u64,
        photons: u32,
    ) -> Identity {
        identity(
            assignment,
            &search.materials(),
            self.geometry,
            seed,
            photons,
            &self.fingerprint,
        )
    }

    /// Answers the current step from the cache and submits it, or says which renders it needs.
    pub fn next(&mut self, search: &mut Search, used: &mut Consumption) -> Result<Next> {
        if search.is_finished() {
            return Ok(Next::Finished);
        }
        self.prune(search);
        let level = search.progress().level;
        if level != self.prefix_level {
            self.prefixes.clear();
            self.prefix_level = level;
        }
        let table = search.materials();
        let pending: Vec<(GroupItem, u32)> = search
            .pending()
            .iter()
            .map(|r| {
                let plain = identity(
                    &r.assignment,
                    &table,
                    self.geometry,
                    r.seed,
                    r.photons,
                    &self.fingerprint,
                );
                let item = GroupItem {
                    identity: if r.changes.is_empty() {
                        plain
                    } else {
                        differential_identity(&plain, &r.changes)
                    },
                    item: RenderItem {
                        assignment: r.assignment.clone(),
                        seed: r.seed,
                    },
                };
                (item, r.photons)
            })
            .collect();
        // The unscored renders, grouped by the photon range they need; each differential
        // render a group of its own.
        let mut missing: BTreeMap<(u32, u32), Vec<GroupItem>> = BTreeMap::new();
        let mut differential: Vec<StepGroup> = Vec::new();
        for ((p, photons), request) in pending.iter().zip(search.pending()) {
            if self.scores.contains_key(&p.identity) {
                continue;
            }
            if !request.changes.is_empty() {
                if !differential
                    .iter()
                    .any(|g| g.items[0].identity == p.identity)
                {
                    differential.push(StepGroup {
                        items: vec![p.clone()],
                        start: 0,
                        photons: *photons,
                        prefixes: Vec::new(),
                        changes: request.changes.clone(),
                        keeps_counts: false,
                    });
                }
                continue;
            }
            let key = (p.item.assignment.clone(), p.item.seed);
            let start = self.prefixes.get(&key, *photons).map_or(0, |(s, _)| s);
            let items = missing.entry((start, *photons)).or_default();
            if !items.iter().any(|m| m.identity == p.identity) {
                items.push(p.clone());
            }
        }
        if !missing.is_empty() || !differential.is_empty() {
            let full = search.config().photons.level(level);
            let mut groups: Vec<StepGroup> = missing
                .into_iter()
                .map(|((start, photons), items)| {
                    let prefixes = if start == 0 {
                        Vec::new()
                    } else {
                        items
                            .iter()
                            .filter_map(|i| {
                                let key = (i.item.assignment.clone(), i.item.seed);
                                self.prefixes.get(&key, photons).map(|(_, c)| c.clone())
                            })
                            .collect()
                    };
                    // Every item of a group starting after 0 has its prefix (they were grouped
                    // by it); should one be gone, the group renders from photon 0.
                    let (start, prefixes) = if prefixes.len() == items.len() {
                        (start, prefixes)
                    } else {
                        (0, Vec::new())
                    };
                    StepGroup {
                        items,
                        start,
                        photons,
                        prefixes,
                        changes: Vec::new(),
                        keeps_counts: photons < full,
                    }
                })
                .collect();
            groups.extend(differential);
            return Ok(Next::Render(groups));
        }
        let scores: Vec<Score> = pending
            .iter()
            .map(|(p, _)| self.scores[&p.identity].0.clone())
            .collect();
        self.count(search, &pending, used);
        search.submit_scores(&scores)?;
        used.requests += pending.len() as u64;
        search.note_spent(used);
        self.prune(search);
        Ok(Next::Submitted)
    }

    /// Counts the renders made for the current step (not cache hits), once each. A render whose
    /// stream (same assignment and seed) was rendered with fewer photons for an earlier step
    /// counts only the photons beyond those.
    fn count(&self, search: &Search, pending: &[(GroupItem, u32)], used: &mut Consumption) {
        let sources = self.geometry.sources() as u64;
        let step = search.pending().first().map(|r| r.index);
        let budgets = search.budgets();
        let mut rendered: Vec<&(GroupItem, u32)> = pending
            .iter()
            .filter(|(p, _)| self.scores.get(&p.identity).map(|s| s.1) == step)
            .collect();
        rendered.sort_unstable_by_key(|(p, _)| p.identity);
        rendered.dedup_by_key(|(p, _)| p.identity);
        if !rendered.is_empty() {
            used.batches += 1;
        }
        for (p, photons) in rendered {
            let before = budgets
                .iter()
                .filter(|&&b| b != *photons)
                .filter(|&&b| {
                    let id = self.identity_of(search, &p.item.assignment, p.item.seed, b);
                    self.scores
                        .get(&id)
                        .is_some_and(|(_, s)| step.is_some_and(|step| *s < step))
                })
                .max()
                .copied()
                .unwrap_or(0);
            used.renders += 1;
            used.photons += u64::from(photons - before.min(*photons)) * sources;
        }
    }

    /// Scores a group's complete counts (photons `[0, photons)` of every item, in order,
    /// prefixes included) and keeps them; returns the new scores.
    pub fn complete(
        &mut self,
        search: &Search,
        scoring: &Scoring,
        photons: u32,
        items: &[GroupItem],
        counts: Vec<CountMatrix>,
    ) -> Result<Vec<NewScore>> {
        let scores = score_group(scoring, photons, &counts)?;
        self.keep(search, photons, items, counts, scores)
    }

    /// Keeps a group's scores, made by [`score_group`] from its complete `counts` (the farm
    /// scores away from its scheduler's lock, or its workers score and `counts` is empty: the
    /// group's [`StepGroup::keeps_counts`] was false); returns the new scores.
    pub fn keep(
        &mut self,
        search: &Search,
        photons: u32,
        items: &[GroupItem],
        counts: Vec<CountMatrix>,
        scores: Vec<Score>,
    ) -> Result<Vec<NewScore>> {
        anyhow::ensure!(
            (counts.is_empty() || items.len() == counts.len()) && items.len() == scores.len(),
            "{} count matrices and {} scores for {} renders",
            counts.len(),
            scores.len(),
            items.len()
        );
        let step = search.pending().first().map(|r| r.index).unwrap_or(0);
        let level = search.progress().level;
        let full = search.config().photons.level(level);
        let mut new = Vec::with_capacity(items.len());
        for (item, score) in items.iter().zip(scores) {
            self.scores.insert(item.identity, (score.clone(), step));
            new.push((item.identity, score, step));
        }
        if photons < full && level == self.prefix_level {
            for (item, counts) in items.iter().zip(counts) {
                let key = (item.item.assignment.clone(), item.item.seed);
                self.prefixes.keep(key, photons, counts);
            }
        }
        Ok(new)
    }

    /// Scores a differential group's render (photons `[0, photons)` of its one item) and
    /// keeps the score ([`Steps::keep_differential`]).
    pub fn complete_differential(
        &mut self,
        search: &Search,
        scoring: &Scoring,
        photons: u32,
        item: &GroupItem,
        output: &DifferentialOutput,
    ) -> Result<Vec<NewScore>> {
        let score = scoring
            .score_differential(output, photons)
            .with_context(|| {
                format!("scoring a differential render of {photons} photons per source")
            })?;
        Ok(self.keep_differential(search, photons, item, score))
    }

    /// Keeps a differential render's score (its changes' scores in it) under the group's
    /// identity and returns what is new. The rendered map's counts are those of a plain render
    /// of it, so its score without the changes is kept under the plain identity too.
    pub fn keep_differential(
        &mut self,
        search: &Search,
        photons: u32,
        item: &GroupItem,
        score: Score,
    ) -> Vec<NewScore> {
        let step = search.pending().first().map(|r| r.index).unwrap_or(0);
        let plain = self.identity_of(search, &item.item.assignment, item.item.seed, photons);
        let mut base = score.clone();
        base.changes.clear();
        let mut new = Vec::with_capacity(2);
        if let std::collections::hash_map::Entry::Vacant(e) = self.scores.entry(plain) {
            e.insert((base.clone(), step));
            new.push((plain, base, step));
        }
        self.scores.insert(item.identity, (score.clone(), step));
        new.push((item.identity, score, step));
        new
    }
}

/// The scores of a group's complete counts (photons `[0, photons)` of every item, in order):
/// pure, so it may run anywhere; [`Steps::keep`] takes them.
pub fn score_group(scoring: &Scoring, photons: u32, counts: &[CountMatrix]) -> Result<Vec<Score>> {
    counts
        .iter()
        .map(|c| {
            scoring
                .score(c, photons)
                .with_context(|| format!("scoring a render of {photons} photons per source"))
        })
        .collect()
}

/// The identity of a differential render: the plain render's and the changes it estimates.
pub fn differential_identity(plain: &Identity, changes: &[Change]) -> Identity {
    use sha2::{Digest, Sha256};
    let mut h = Sha256::new();
    h.update(b"scatterfarm-differential/1\0");
    h.update(plain);
    h.update((changes.len() as u64).to_le_bytes());
    for c in changes {
        h.update((c.pixels.len() as u64).to_le_bytes());
        for &(p, m) in &c.pixels {
            h.update(p.to_le_bytes());
            h.update(m.to_le_bytes());
        }
    }
    h.finalize().into()
}

#[cfg(test)]
mod tests;
