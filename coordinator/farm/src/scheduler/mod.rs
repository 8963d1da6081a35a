//! The coordinator's scheduler: jobs, registered workers and leases, and the rules between them.
//!
//! Everything here is synchronous and driven by the gRPC services (one mutex around a
//! [`Scheduler`]; a result that completes a search group is scored without it, see
//! [`results`]): workers register and lease pieces of render groups; jobs are served
//! round-robin so many reconstructions progress together; a piece not returned by its deadline,
//! or whose worker stops sending heartbeats, is leased again with the next attempt number, up to
//! a cap; results are checked before they are summed, and a worker that sends three bad results
//! is blocked for that job, across registrations and restarts. Task ids come from the store, so
//! they are unique across coordinator runs.
//!
//! - [`jobs`]: what clients ask of jobs (submit, look up, cancel, delete, why one waits).
//! - [`registry`]: registered workers ([`WorkerEntry`]).
//! - [`liveness`]: when each worker was last heard from, behind its own lock, so heartbeats
//!   never wait on the scheduler's.
//! - [`lease`]: handing the next piece to a worker, jobs in round-robin.
//! - [`sizing`]: how many photons a piece holds and how long its lease lasts.
//! - [`results`]: checking a returned result against its lease and summing it; give-backs.
//! - [`expiry`]: leases past their deadline and silent workers.
//! - [`giveback`]: pieces that come back without a result, and the attempt cap.
//! - [`strikes`]: bad results per job and worker identity, stored with the job.
//! - [`restore`]: paused jobs restored from the store, and damaged ones.

mod expiry;
mod giveback;
mod jobs;
mod lease;
mod liveness;
mod registry;
mod restore;
mod results;
mod sizing;
mod strikes;

pub use jobs::stored_job;
pub use lease::{Lease, TaskOut};
pub use liveness::Liveness;
pub use registry::{Abilities, WorkerEntry};
pub use results::Rendered;
use strikes::Strikes;
pub use strikes::STRIKES;

use super::job::Job;
use super::store::Store;
use anyhow::Result;
use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;
use std::time::Duration;

/// Tunables of a coordinator.
#[derive(Debug, Clone, Copy)]
pub struct Settings {
    /// Pieces are sized so the leasing worker renders one in about this long.
    pub task_seconds: f64,
    /// How often workers send heartbeats.
    pub heartbeat: Duration,
    /// Heartbeats a worker may miss before its leases are handed out again.
    pub missed_heartbeats: u32,
    /// The shortest lease; a lease lasts the longer of this and 5 × the expected render time,
    /// plus twice the worker's transfer time ([`sizing`]).
    pub min_lease: Duration,
    /// Leases of one piece before its job fails (a piece that expires, is given back or whose
    /// result is refused is leased again, up to this many times in all).
    pub max_attempts: u32,
    /// Photons (all sources) a job may simulate; past it, the job fails saying so.
    pub max_job_photons: u64,
}

impl Default for Settings {
    fn default() -> Self {
        Settings {
            task_seconds: 2.0,
            heartbeat: Duration::from_secs(2),
            missed_heartbeats: 3,
            min_lease: Duration::from_secs(30),
            max_attempts: 8,
            max_job_photons: 1_000_000_000_000,
        }
    }
}

/// Why a request is refused; the service maps these to gRPC status codes.
#[derive(Debug, thiserror::Error)]
pub enum Refusal {
    #[error("{0}")]
    NotFound(String),
    #[error("{0}")]
    Stale(String),
    #[error("{0}")]
    Invalid(String),
    #[error("{0}")]
    Internal(String),
}

impl From<anyhow::Error> for Refusal {
    fn from(e: anyhow::Error) -> Self {
        Refusal::Internal(format!("{e:#}"))
    }
}

/// Counters for listings and metrics.
#[derive(Debug, Clone, Copy, Default)]
pub struct Counters {
    pub leases_expired: u64,
    pub results_refused: u64,
    pub results_accepted: u64,
    /// Renders whose counts were complete (setup and search renders).
    pub renders_completed: u64,
    /// Of those, renders scored by the workers that rendered them (their counts never sent).
    pub renders_scored_on_workers: u64,
    /// Photons (all sources) of accepted results.
    pub photons: u64,
}

/// The coordinator's state.
pub struct Scheduler {
    store: Arc<dyn Store>,
    pub settings: Settings,
    pub jobs: BTreeMap<String, Job>,
    /// Stored jobs that cannot be read, with why: listed, and deletable, nothing else.
    pub damaged: BTreeMap<String, String>,
    pub workers: HashMap<String, WorkerEntry>,
    /// Last contact per worker, shared with the services (heartbeats skip the scheduler lock).
    pub liveness: Arc<Liveness>,
    /// By task id.
    pub leases: HashMap<u64, Lease>,
    /// Bad results per job and worker identity.
    strikes: Strikes,
    /// The job served last, for round-robin.
    last_served: Option<String>,
    next_group: u64,
    next_worker: u64,
    /// Makes worker ids of different coordinator runs differ.
    boot: u32,
    pub draining: bool,
    pub counters: Counters,
}

fn unix_ms_after(d: Duration) -> u64 {
    (std::time::SystemTime::now() + d)
        .duration_since(std::time::UNIX_EPOCH)
        .map(|t| t.as_millis() as u64)
        .unwrap_or(0)
}

impl Scheduler {
    /// Loads every stored job; unfinished ones resume.
    pub fn open(store: Arc<dyn Store>, settings: Settings) -> Result<Scheduler> {
        let mut jobs = BTreeMap::new();
        let mut damaged = BTreeMap::new();
        for (id, record) in store.records()? {
            match Job::restore(id.clone(), &record, store.as_ref()) {
                Ok(job) => {
                    if job.is_active() {
                        tracing::info!(
                            "resuming job {id} at {} of {} renders",
                            job.checkpoint.search.progress().renders_done,
                            job.checkpoint.search.progress().renders_total
                        );
                    }
                    jobs.insert(id, job);
                }
                Err(e) => {
                    tracing::error!("cannot load job {id}: {e:#}; listed as damaged");
                    damaged.insert(id, format!("{e:#}"));
                }
            }
        }
        let strikes = Strikes::load(store.as_ref(), jobs.keys());
        Ok(Scheduler {
            store,
            settings,
            jobs,
            damaged,
            workers: HashMap::new(),
            liveness: Arc::default(),
            leases: HashMap::new(),
            strikes,
            last_served: None,
            next_group: 1,
            next_worker: 1,
            boot: super::nonce(),
            draining: false,
            counters: Counters::default(),
        })
    }

    pub fn store(&self) -> &dyn Store {
        self.store.as_ref()
    }

    pub fn store_arc(&self) -> Arc<dyn Store> {
        self.store.clone()
    }
}

/// Ids drawn from `next` (group ids), each one more than the last.
fn ids(next: &mut u64) -> impl FnMut() -> u64 + '_ {
    move || {
        let id = *next;
        *next += 1;
        id
    }
}
