//! Cutting a job's work into render groups, through the search's step driver
//! ([`scatterfarm_search::steps::Steps`]), and taking the groups back as they complete.

use super::scoring::ScoreWork;
use super::{Job, JobState};
use crate::store::Store;
use crate::work::{Purpose, RenderGroup};
use anyhow::{Context, Result};
use scatterfarm_search::identity::identity;
use scatterfarm_search::steps::{GroupItem, Next};

impl Job {
    /// Makes sure the job has groups to render if it needs any: the missing setup renders, or
    /// the current step's unscored renders. Steps whose renders are all scored are submitted
    /// on the way. Needs the job pinned.
    pub fn plan_work(
        &mut self,
        new_group_id: &mut dyn FnMut() -> u64,
        store: &dyn Store,
    ) -> Result<()> {
        if !self.groups.is_empty() || !self.is_active() || self.is_scoring() {
            return Ok(());
        }
        let fingerprint = self
            .checkpoint
            .pinned
            .clone()
            .context("a job is planned before it is pinned")?;
        if self.checkpoint.state == JobState::Preparing {
            for r in self.plan.setup_renders()? {
                if self.setup.has(r.kind) {
                    continue;
                }
                let id = identity(
                    &r.item.assignment,
                    &r.table,
                    r.geometry,
                    r.item.seed,
                    r.photons,
                    &fingerprint,
                );
                self.groups.push(RenderGroup::new(
                    new_group_id(),
                    Purpose::Setup(r.kind),
                    r.geometry,
                    r.table,
                    vec![GroupItem {
                        identity: id,
                        item: r.item,
                    }],
                    r.photons,
                ));
            }
            if self.groups.is_empty() {
                self.finish_setup(store)?;
            } else {
                return Ok(());
            }
        }
        let geometry = self.plan.search_geometry;
        // Steps answered from the cache can follow one another by the hundred: the checkpoint
        // is written once, when the loop stops (a search state can be large, and this runs
        // under the scheduler's lock), not after each.
        let mut submitted = false;
        loop {
            let steps = self
                .steps
                .as_mut()
                .context("a job is planned before it is pinned")?;
            match steps.next(&mut self.checkpoint.search, &mut self.checkpoint.used)? {
                Next::Finished => return self.finish(store),
                Next::Submitted => submitted = true,
                Next::Render(groups) => {
                    if submitted {
                        self.persist(store)?;
                    }
                    let table = self.checkpoint.search.materials();
                    // A likelihood job's renders that nothing extends are scored where they
                    // are rendered: only their scores come back.
                    let likelihood = self.scoring.as_ref().is_some_and(|s| s.is_likelihood());
                    for g in groups {
                        let scored =
                            likelihood && !g.keeps_counts && g.changes.is_empty() && g.start == 0;
                        let group = RenderGroup::new(
                            new_group_id(),
                            Purpose::Search,
                            geometry,
                            table.clone(),
                            g.items,
                            g.photons,
                        )
                        .with_changes(g.changes);
                        let group = group.starting_from(g.start, g.prefixes);
                        self.groups.push(if scored {
                            group.scored_on_workers()
                        } else {
                            group
                        });
                    }
                    return Ok(());
                }
            }
        }
    }

    /// Takes a complete group's counts. Setup counts are kept until the setup is complete, and
    /// the next work is planned; a search group comes back as [`ScoreWork`], to be scored off
    /// the lock and handed to [`Job::take_scored`].
    pub fn group_complete(
        &mut self,
        group: RenderGroup,
        new_group_id: &mut dyn FnMut() -> u64,
        store: &dyn Store,
    ) -> Result<Option<ScoreWork>> {
        let sources = group.geometry.sources() as u64;
        self.checkpoint.photons_simulated +=
            sources * u64::from(group.photons - group.start) * group.items.len() as u64;
        self.checkpoint.used.scatter_events += group.scatter_events;
        let (id, purpose, photons) = (group.id, group.purpose, group.photons);
        let items = group.items.clone();
        let parts = group.into_parts();
        match purpose {
            Purpose::Setup(kind) => {
                if let Some(c) = parts.counts.into_iter().next() {
                    self.setup.set(kind, c);
                }
                if self.groups.is_empty() {
                    self.plan_work(new_group_id, store)?;
                }
                Ok(None)
            }
            Purpose::Search => self.score_later(id, photons, items, parts).map(Some),
        }
    }
}
