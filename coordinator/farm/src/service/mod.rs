//! The two gRPC services over a shared [`Farm`] (one [`Scheduler`] behind a mutex): they
//! translate between protocol messages and the scheduler's types (every conversion is
//! `scatterfarm_proto::convert`'s) and map refusals to status codes; all decisions live in the
//! scheduler.
//!
//! - [`worker`]: `WorkerService` (register, heartbeat, lease, complete, release).
//! - [`client`]: `ClientService` (submit, status, watch, result, cancel, delete, listings).

mod client;
mod worker;

pub use client::ClientApi;
pub use worker::WorkerApi;

use crate::scheduler::{Liveness, Refusal, Scheduler};
use crate::store::Store;
use std::sync::{Arc, Mutex, MutexGuard};
use tokio::sync::Notify;
use tonic::Status;

/// The coordinator shared by both services and the background sweeper.
pub struct Farm {
    scheduler: Mutex<Scheduler>,
    /// The scheduler's store, for work done outside its lock (a submission's parsing and
    /// writes).
    pub store: Arc<dyn Store>,
    /// Woken when work may have appeared (a submission, a piece given back, a group done).
    pub work: Notify,
    /// The scheduler's record of when workers were last heard from, touched without its lock.
    pub liveness: Arc<Liveness>,
}

impl Farm {
    pub fn new(scheduler: Scheduler) -> Arc<Farm> {
        let farm = Arc::new(Farm {
            store: scheduler.store_arc(),
            liveness: scheduler.liveness.clone(),
            scheduler: Mutex::new(scheduler),
            work: Notify::new(),
        });
        // Jobs that finished while they were restored.
        farm.store_due_outputs();
        farm
    }

    /// The scheduler, even if a panic poisoned the lock (the state stays consistent per call).
    /// Async code uses [`Self::locked`] instead, so no runtime thread waits on the lock.
    pub fn scheduler(&self) -> MutexGuard<'_, Scheduler> {
        self.scheduler.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Runs `f` on the scheduler from a blocking thread. An async thread that waited on the
    /// lock while results were being scored could not answer its connections' HTTP/2 pings,
    /// and under load clients then dropped the connection ("keep-alive timed out").
    pub async fn locked<T: Send + 'static>(
        self: &Arc<Self>,
        f: impl FnOnce(&mut Scheduler) -> T + Send + 'static,
    ) -> Result<T, Status> {
        self.blocking(move |farm| f(&mut farm.scheduler())).await
    }

    /// [`Self::locked`] for a call that may write checkpoints: `f` runs under the lock, then,
    /// with the lock released, the store is synced ([`Farm::sync`]) before the answer goes out.
    pub async fn locked_durable<T: Send + 'static>(
        self: &Arc<Self>,
        f: impl FnOnce(&mut Scheduler) -> T + Send + 'static,
    ) -> Result<T, Status> {
        self.blocking(move |farm| {
            let out = f(&mut farm.scheduler());
            farm.store_due_outputs();
            farm.sync();
            out
        })
        .await
    }

    /// Draws and stores the outputs of the jobs that finished (`Job::outputs_due`), with the
    /// scheduler's lock held only to copy what they are made from. A failure is logged: the
    /// outputs are drawn again from the checkpoint when they are asked for.
    pub fn store_due_outputs(&self) {
        let due = self.scheduler().take_due_outputs();
        for source in due {
            if let Err(e) = source.store(self.store.as_ref()) {
                tracing::error!(
                    "job {}: cannot store its outputs: {e:#}; they are drawn again when asked for",
                    source.job()
                );
            }
        }
    }

    /// Runs `f` on a blocking thread.
    async fn blocking<T: Send + 'static>(
        self: &Arc<Self>,
        f: impl FnOnce(&Farm) -> T + Send + 'static,
    ) -> Result<T, Status> {
        let farm = self.clone();
        tokio::task::spawn_blocking(move || f(&farm))
            .await
            .map_err(|e| Status::internal(format!("a request handler failed: {e}")))
    }

    /// Makes the checkpoints written under the lock durable, outside it (a disk sync can take
    /// tens of milliseconds; heartbeats and leases must not wait behind it). Concurrent syncs
    /// share one write to disk. A failed sync is logged: the jobs keep their state in memory,
    /// the next sync writes it, and a coordinator killed meanwhile resumes from the last
    /// durable checkpoint, which replays to the same result.
    pub fn sync(&self) {
        if let Err(e) = self.store.flush() {
            tracing::error!(
                "cannot sync the data store: {e}; the latest checkpoints are not yet durable"
            );
        }
    }
}

impl From<Refusal> for Status {
    fn from(r: Refusal) -> Status {
        match r {
            Refusal::NotFound(m) => Status::not_found(m),
            Refusal::Stale(m) => Status::failed_precondition(m),
            Refusal::Invalid(m) => Status::invalid_argument(m),
            Refusal::Internal(m) => Status::internal(m),
        }
    }
}
