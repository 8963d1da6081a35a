//! Scoring a complete search group away from the scheduler's lock. The job hands out a
//! [`ScoreWork`] (the group's counts and a shared handle on its scoring, or the scores its
//! workers made) and plans nothing
//! until it comes back; [`ScoreWork::run`] scores it on any thread; [`Job::take_scored`] keeps
//! the [`Scored`] under the lock, unless the job was cancelled, deleted or restored from the
//! store meanwhile (a restored job plans the step again, and its renders are seeded per
//! request, so it ends with the same result).

use super::Job;
use crate::store::Store;
use crate::work::GroupParts;
use anyhow::{Context, Result};
use scatterfarm_model::likelihood::Deviance;
use scatterfarm_model::CountMatrix;
use scatterfarm_search::driver::Scoring;
use scatterfarm_search::steps::{score_group, GroupItem};
use scatterfarm_search::{ChangeScore, Score};
use std::sync::Arc;

/// A complete search group, to be scored off the lock.
pub struct ScoreWork {
    /// The job it belongs to.
    pub job: String,
    group: u64,
    scoring: Arc<Scoring>,
    photons: u32,
    items: Vec<GroupItem>,
    counts: Vec<CountMatrix>,
    /// A differential group's change scores, as its worker returned them.
    changes: Option<Vec<Option<Deviance>>>,
    /// A scored group's render scores, as its workers returned them (`counts` is empty).
    renders: Option<Vec<Deviance>>,
}

/// A group's scores, to be kept by its job.
pub struct Scored {
    /// The job it belongs to.
    pub job: String,
    group: u64,
    photons: u32,
    items: Vec<GroupItem>,
    counts: Vec<CountMatrix>,
    scores: Result<Vec<Score>>,
    differential: bool,
}

impl ScoreWork {
    /// Scores the group: the one heavy step of taking a result, run without the lock.
    pub fn run(mut self) -> Scored {
        let differential = self.changes.is_some();
        let scores = match (self.changes.take(), self.renders.take()) {
            (Some(changes), _) => self.score_differential(changes),
            // The same score the coordinator makes of the counts ([`Scoring::score`]).
            (None, Some(renders)) => Ok(renders.into_iter().map(Score::of_deviance).collect()),
            (None, None) => score_group(&self.scoring, self.photons, &self.counts),
        };
        Scored {
            job: self.job,
            group: self.group,
            photons: self.photons,
            items: self.items,
            counts: self.counts,
            scores,
            differential,
        }
    }

    /// A differential group's score: its render's counts scored here, with the changes'
    /// scores its worker made from the same photons.
    fn score_differential(&self, changes: Vec<Option<Deviance>>) -> Result<Vec<Score>> {
        let counts = self
            .counts
            .first()
            .context("a differential group without its render")?;
        let changes = changes
            .into_iter()
            .map(|c| {
                c.map(|d| ChangeScore {
                    value: d.value,
                    blocks: d.blocks,
                })
            })
            .collect();
        let score = self
            .scoring
            .score_with_changes(counts, self.photons, changes)
            .with_context(|| {
                format!(
                    "scoring a differential render of {} photons per source",
                    self.photons
                )
            })?;
        Ok(vec![score])
    }
}

impl Job {
    /// Hands group `group`'s complete counts (or its workers' scores) out to be scored; the
    /// job plans no work until [`Job::take_scored`] has them back.
    pub(super) fn score_later(
        &mut self,
        group: u64,
        photons: u32,
        items: Vec<GroupItem>,
        parts: GroupParts,
    ) -> Result<ScoreWork> {
        let scoring = self
            .scoring
            .clone()
            .context("a search render completed before ε was calibrated")?;
        self.scoring_group = Some(group);
        Ok(ScoreWork {
            job: self.id.clone(),
            group,
            scoring,
            photons,
            items,
            counts: parts.counts,
            changes: parts.change_scores,
            renders: parts.render_scores,
        })
    }

    /// Whether a group of this job is being scored off the lock.
    pub fn is_scoring(&self) -> bool {
        self.scoring_group.is_some()
    }

    /// Keeps a group's scores (stored, then the next work planned). Scores of a group this
    /// job no longer waits for (it was cancelled, or restored from the store) are dropped.
    pub fn take_scored(
        &mut self,
        scored: Scored,
        new_group_id: &mut dyn FnMut() -> u64,
        store: &dyn Store,
    ) -> Result<()> {
        if self.scoring_group != Some(scored.group) || !self.is_active() {
            tracing::debug!(
                "job {}: scores of group {} are no longer needed",
                self.id,
                scored.group
            );
            return Ok(());
        }
        self.scoring_group = None;
        let scores = scored.scores?;
        let steps = self
            .steps
            .as_mut()
            .context("a search render completed for a job that is not pinned")?;
        let new = if scored.differential {
            let item = scored
                .items
                .first()
                .context("a differential group without its render")?;
            let score = scores
                .into_iter()
                .next()
                .context("a differential group without its score")?;
            steps.keep_differential(&self.checkpoint.search, scored.photons, item, score)
        } else {
            steps.keep(
                &self.checkpoint.search,
                scored.photons,
                &scored.items,
                scored.counts,
                scores,
            )?
        };
        for (id, score, step) in new {
            store.put_score(&self.id, &id, score, step)?;
        }
        if self.groups.is_empty() {
            self.plan_work(new_group_id, store)?;
        }
        Ok(())
    }
}
