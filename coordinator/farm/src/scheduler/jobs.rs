//! What clients ask of jobs: submit, look up, cancel, delete, and why an active job waits.

use super::{Refusal, Scheduler};
use crate::job::{Job, OutputSource};
use crate::store::Store;
use scatterfarm_job::inputs::Inputs;
use scatterfarm_job::spec::JobSpec;

/// Validates a submission and stores it under a new id (no lock needed: the store is shared).
pub fn stored_job(store: &dyn Store, params: JobSpec, inputs: Inputs) -> Result<Job, Refusal> {
    let id = store.new_job_id().map_err(anyhow::Error::from)?;
    Job::submit(id, params, inputs, store).map_err(|e| Refusal::Invalid(format!("{e:#}")))
}

impl Scheduler {
    /// Validates and stores a job; returns its id. The gRPC service does the two halves apart
    /// ([`stored_job`], then [`Self::add_job`] under the lock), so that parsing a submission and
    /// writing its files never holds the scheduler's lock.
    pub fn submit(&mut self, params: JobSpec, inputs: Inputs) -> Result<String, Refusal> {
        let job = stored_job(self.store.as_ref(), params, inputs)?;
        Ok(self.add_job(job))
    }

    /// Adds a job [`stored_job`] made; its id.
    pub fn add_job(&mut self, job: Job) -> String {
        let id = job.id.clone();
        tracing::info!("job {id} submitted ({})", job.name());
        self.jobs.insert(id.clone(), job);
        id
    }

    /// What the outputs of the jobs that finished since the last call are made from (their
    /// flags cleared): the farm draws and stores them off the lock.
    pub fn take_due_outputs(&mut self) -> Vec<OutputSource> {
        let mut due = Vec::new();
        for job in self.jobs.values_mut().filter(|j| j.outputs_due) {
            job.outputs_due = false;
            match job.output_source() {
                Ok(source) => due.push(source),
                Err(e) => tracing::error!("job {}: no outputs to store: {e:#}", job.id),
            }
        }
        due
    }

    pub fn job(&self, id: &str) -> Result<&Job, Refusal> {
        self.jobs
            .get(id)
            .ok_or_else(|| Refusal::NotFound(format!("no job {id:?} (see `scatterfarm jobs`)")))
    }

    pub(super) fn job_mut(&mut self, id: &str) -> Result<&mut Job, Refusal> {
        self.jobs
            .get_mut(id)
            .ok_or_else(|| Refusal::NotFound(format!("no job {id:?} (see `scatterfarm jobs`)")))
    }

    /// Stops a job; leases of it are refused when they come back.
    pub fn cancel(&mut self, id: &str) -> Result<(), Refusal> {
        if let Some(why) = self.damaged.get(id) {
            return Err(Refusal::Invalid(format!(
                "job {id} is damaged ({why}): it can only be deleted"
            )));
        }
        let store = self.store.clone();
        self.job_mut(id)?.cancel(store.as_ref())?;
        self.leases.retain(|_, l| l.job != id);
        tracing::info!("job {id} cancelled");
        Ok(())
    }

    /// Removes a job and everything stored of it (cancelling it first if it runs).
    pub fn delete(&mut self, id: &str) -> Result<(), Refusal> {
        if self.damaged.contains_key(id) {
            return self.delete_damaged(id);
        }
        self.cancel(id)?;
        self.jobs.remove(id);
        self.store.delete_job(id).map_err(anyhow::Error::from)?;
        self.strikes.forget(id);
        tracing::info!("job {id} deleted");
        Ok(())
    }

    /// Why an active job gets no renders, if it does not.
    pub fn waiting_reason(&self, job: &Job) -> Option<String> {
        if !job.is_active() {
            return None;
        }
        if let Some(p) = &job.paused {
            return Some(p.reason.clone());
        }
        if self.leases.values().any(|l| l.job == job.id) {
            return None;
        }
        let matching = self
            .workers
            .values()
            .filter(|w| job.accepts(&w.fingerprint_key))
            .filter(|w| w.renders_differentially || !job.needs_differential())
            .filter(|w| !self.strikes.blocked(&job.id, &w.name))
            .count();
        if matching == 0 {
            return Some(match job.checkpoint.pinned.as_deref() {
                _ if job.needs_differential() => format!(
                    "waiting for a worker whose engine renders differentially (the CPU engine){}",
                    match job.checkpoint.pinned.as_deref() {
                        Some(p) if p != crate::job::ANY_ENGINE => format!(", with engine {p}"),
                        _ => String::new(),
                    }
                ),
                Some(p) if p != crate::job::ANY_ENGINE => {
                    format!("waiting for a worker with engine {p}")
                }
                _ => "waiting for a worker".to_string(),
            });
        }
        None
    }

    /// Workers holding a lease of `job`.
    pub fn workers_busy(&self, job: &str) -> u32 {
        let mut w: Vec<&str> = self
            .leases
            .values()
            .filter(|l| l.job == job)
            .map(|l| l.worker.as_str())
            .collect();
        w.sort_unstable();
        w.dedup();
        w.len() as u32
    }
}
