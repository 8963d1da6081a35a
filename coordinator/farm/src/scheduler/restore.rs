//! Jobs restored from the store: paused jobs (a store write failed, see
//! [`crate::job::faults`]) once their wait is over, and the stored jobs that cannot be read,
//! which stay listed as damaged until they are deleted.

use super::{Refusal, Scheduler};
use crate::job::faults::PAUSE_RETRY;
use crate::job::Job;
use std::time::Instant;

impl Scheduler {
    /// Restores from the store every paused job that has waited [`PAUSE_RETRY`] by `now`; one
    /// that cannot be read yet waits again.
    pub(super) fn restore_paused(&mut self, now: Instant) {
        let due: Vec<String> = self
            .jobs
            .values()
            .filter(|j| {
                j.paused
                    .as_ref()
                    .is_some_and(|p| now.saturating_duration_since(p.since) >= PAUSE_RETRY)
            })
            .map(|j| j.id.clone())
            .collect();
        for id in due {
            let Some(job) = self.jobs.get_mut(&id) else {
                continue;
            };
            let restored = serde_json::to_vec(&job.record)
                .map_err(anyhow::Error::from)
                .and_then(|record| Job::restore(id.clone(), &record, self.store.as_ref()));
            match restored {
                Ok(restored) => {
                    tracing::info!(
                        "job {id} restored from the store at {} of {} renders",
                        restored.checkpoint.search.progress().renders_done,
                        restored.checkpoint.search.progress().renders_total
                    );
                    *job = restored;
                    self.leases.retain(|_, l| l.job != id);
                }
                Err(e) => job.pause(&e),
            }
        }
    }

    /// Deletes a damaged job: everything stored under its id.
    pub(super) fn delete_damaged(&mut self, id: &str) -> Result<(), Refusal> {
        self.store.delete_job(id).map_err(anyhow::Error::from)?;
        self.damaged.remove(id);
        tracing::info!("damaged job {id} deleted");
        Ok(())
    }
}
