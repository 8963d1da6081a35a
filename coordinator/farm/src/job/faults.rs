//! Store faults: a job whose progress cannot be written (a full or failing disk) pauses instead
//! of failing. Its in-memory state after the failed write is not what the store holds, so it is
//! thrown away; [`Scheduler`](crate::scheduler::Scheduler) later restores the job from the store,
//! exactly as a restarted coordinator would, and the job redoes the lost step. Renders being
//! seeded per request, it then ends with the result of an uninterrupted run.

use super::Job;
use crate::store::{Store, StoreError};
use std::time::{Duration, Instant};

/// How long a paused job waits before it is restored from the store and tried again.
pub const PAUSE_RETRY: Duration = Duration::from_secs(5);

/// Why a job is paused, and since when.
#[derive(Debug, Clone)]
pub struct Pause {
    pub reason: String,
    pub since: Instant,
}

/// Whether `e` came from the store.
pub fn is_store_fault(e: &anyhow::Error) -> bool {
    e.chain().any(|c| c.is::<StoreError>())
}

impl Job {
    /// Pauses the job after the store failed (`e`): its groups are dropped, so results of its
    /// leases are refused, and it gets no renders until it is restored.
    pub fn pause(&mut self, e: &anyhow::Error) {
        tracing::error!(
            "job {}: the store failed ({e:#}); paused, retried every {} s",
            self.id,
            PAUSE_RETRY.as_secs()
        );
        self.groups.clear();
        self.paused = Some(Pause {
            reason: format!(
                "paused: the data store failed ({e:#}); retried every {} s",
                PAUSE_RETRY.as_secs()
            ),
            since: Instant::now(),
        });
    }

    /// Handles an error of the job's own work: a store fault pauses the job, anything else
    /// fails it (and if that failure cannot be stored, the job pauses and fails again on its
    /// retry).
    pub fn on_error(&mut self, e: anyhow::Error, store: &dyn Store) {
        if is_store_fault(&e) {
            self.pause(&e);
        } else if let Err(stored) = self.fail(format!("{e:#}"), store) {
            self.pause(&stored);
        }
    }

    /// Whether the job waits to be restored.
    pub fn is_paused(&self) -> bool {
        self.paused.is_some()
    }
}
