//! A job's durable checkpoint: where it stands and everything its search has consumed, written to
//! the store after every step.

use super::Job;
use crate::store::{Store, StoreError};
use anyhow::Result;
use scatterfarm_search::driver::Consumption;
use scatterfarm_search::Search;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::time::Instant;

/// Where a job stands.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "state", rename_all = "kebab-case")]
pub enum JobState {
    Preparing,
    Searching,
    Finished,
    Cancelled,
    Failed { message: String },
}

/// What is written after every step.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Checkpoint {
    #[serde(rename = "phase")]
    pub state: JobState,
    /// The engine fingerprint the job is pinned to ([`super::ANY_ENGINE`] when it opted out).
    pub pinned: Option<String>,
    /// ε of the finest level's budget (for listings; `epsilons` holds every budget's).
    pub epsilon: Option<f64>,
    /// ε by photons per source.
    pub epsilons: BTreeMap<u32, f64>,
    pub search: Search,
    /// What the search consumed (the same for interrupted and uninterrupted runs).
    pub used: Consumption,
    /// Photons engines actually ran for this job (all sources), recomputation included.
    pub photons_simulated: u64,
    /// Seconds the job was worked on, over all of the coordinator's runs.
    pub active_seconds: f64,
}

impl Checkpoint {
    /// A new job's: preparing, nothing consumed.
    pub(super) fn start(pinned: Option<String>, search: Search) -> Checkpoint {
        Checkpoint {
            state: JobState::Preparing,
            pinned,
            epsilon: None,
            epsilons: BTreeMap::new(),
            search,
            used: Consumption::default(),
            photons_simulated: 0,
            active_seconds: 0.0,
        }
    }

    /// Writes it as job `id`'s.
    pub(super) fn save(&self, id: &str, store: &dyn Store) -> Result<()> {
        store.put_progress(id, &serde_json::to_vec(self)?)?;
        Ok(())
    }

    /// Reads job `id`'s back.
    pub(super) fn load(id: &str, store: &dyn Store) -> Result<Checkpoint> {
        match store.progress(id)? {
            Some(bytes) => Ok(
                serde_json::from_slice(&bytes).map_err(|e| StoreError::Damaged {
                    what: "job progress",
                    detail: e.to_string(),
                })?,
            ),
            None => anyhow::bail!("job {id}: its progress is missing"),
        }
    }
}

impl Job {
    /// Adds the time worked since the last write and stores the checkpoint, then forgets the
    /// stored scores of stages it left behind.
    pub(super) fn persist(&mut self, store: &dyn Store) -> Result<()> {
        self.account_time();
        self.checkpoint.save(&self.id, store)?;
        let stage_start = self.checkpoint.search.stage_start();
        let gone = self.stored_stages.written(&self.id, stage_start, store)?;
        if gone > 0 {
            tracing::debug!("job {}: {gone} scores of earlier stages forgotten", self.id);
        }
        Ok(())
    }

    /// Adds the time since the last account to the job's active seconds.
    pub(super) fn account_time(&mut self) {
        let now = Instant::now();
        self.checkpoint.active_seconds += now.duration_since(self.last_active).as_secs_f64();
        self.last_active = now;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_state_keeps_its_stored_names() {
        let failed = JobState::Failed {
            message: "m".into(),
        };
        assert_eq!(
            serde_json::to_value(&failed).unwrap(),
            serde_json::json!({"state": "failed", "message": "m"})
        );
        assert_eq!(
            serde_json::to_value(JobState::Preparing).unwrap(),
            serde_json::json!({"state": "preparing"})
        );
    }
}
