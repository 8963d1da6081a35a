//! The coordinator's state: jobs, registered workers and leases, and the rules between them.
//!
//! Everything here is synchronous and driven by the gRPC services (one mutex around a
//! [`Core`]): workers register and lease pieces of render groups; jobs are served round-robin
//! so many reconstructions progress together; a piece not returned by its deadline, or whose
//! worker stops sending heartbeats, is leased again with the next attempt number; results are
//! checked before they are summed, and a worker that sends three bad results is blocked for
//! that job.

use super::job::{Job, Phase};
use super::store::Store;
use super::work::{Piece, RenderGroup};
use anyhow::Result;
use scatterfarm_job::inputs::Inputs;
use scatterfarm_job::spec::JobSpec;
use scatterfarm_model::{CountMatrix, EngineFingerprint};
use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Tunables of a coordinator.
#[derive(Debug, Clone, Copy)]
pub struct Settings {
    /// Pieces are sized so the leasing worker renders one in about this long.
    pub task_seconds: f64,
    /// How often workers send heartbeats.
    pub heartbeat: Duration,
    /// Heartbeats a worker may miss before its leases are handed out again.
    pub missed_heartbeats: u32,
    /// The shortest lease; a lease lasts the longer of this and 5 × the expected render time.
    pub min_lease: Duration,
}

impl Default for Settings {
    fn default() -> Self {
        Settings {
            task_seconds: 2.0,
            heartbeat: Duration::from_secs(2),
            missed_heartbeats: 3,
            min_lease: Duration::from_secs(30),
        }
    }
}

/// Bad results a worker may send for one job before it is blocked for it.
pub const STRIKES: u32 = 3;

/// A registered worker.
#[derive(Debug, Clone)]
pub struct Worker {
    pub id: String,
    pub name: String,
    pub fingerprint: EngineFingerprint,
    /// The fingerprint as jobs are pinned to it.
    pub fingerprint_key: String,
    pub photons_per_second: f64,
    pub last_seen: Instant,
    pub tasks_completed: u64,
}

/// A leased piece.
#[derive(Debug, Clone)]
pub struct Lease {
    pub job: String,
    pub group: u64,
    pub piece: Piece,
    pub worker: String,
    pub deadline: Instant,
    pub deadline_unix_ms: u64,
}

/// A task as handed to a worker (the service turns it into the protocol's message).
#[derive(Debug, Clone)]
pub struct TaskOut {
    pub job: String,
    pub piece: Piece,
    pub deadline_unix_ms: u64,
    /// The group's geometry, and whether it is the job's (cacheable) geometry.
    pub geometry: scatterfarm_model::Geometry,
    pub job_geometry: bool,
    pub table: Vec<scatterfarm_model::Material>,
    pub items: Vec<scatterfarm_model::RenderItem>,
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
    /// Photons (all sources) of accepted results.
    pub photons: u64,
}

/// The coordinator's state.
pub struct Core {
    store: Arc<dyn Store>,
    pub settings: Settings,
    pub jobs: BTreeMap<String, Job>,
    pub workers: HashMap<String, Worker>,
    /// By task id.
    pub leases: HashMap<u64, Lease>,
    /// (job, worker) → bad results.
    strikes: HashMap<(String, String), u32>,
    /// The job served last, for round-robin.
    last_served: Option<String>,
    next_task: u64,
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

impl Core {
    /// Loads every stored job; unfinished ones resume.
    pub fn open(store: Arc<dyn Store>, settings: Settings) -> Result<Core> {
        let mut jobs = BTreeMap::new();
        for (id, record) in store.records()? {
            match Job::restore(id.clone(), &record, store.as_ref()) {
                Ok(job) => {
                    if job.is_active() {
                        tracing::info!(
                            "resuming job {id} at {} of {} renders",
                            job.progress.search.progress().renders_done,
                            job.progress.search.progress().renders_total
                        );
                    }
                    jobs.insert(id, job);
                }
                Err(e) => tracing::error!("cannot load job {id}: {e:#}"),
            }
        }
        Ok(Core {
            store,
            settings,
            jobs,
            workers: HashMap::new(),
            leases: HashMap::new(),
            strikes: HashMap::new(),
            last_served: None,
            next_task: 1,
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

    // ---- clients -----------------------------------------------------------------------------

    /// Validates and stores a job; returns its id.
    pub fn submit(&mut self, params: JobSpec, inputs: Inputs) -> Result<String, Refusal> {
        let id = self.store.new_job_id().map_err(anyhow::Error::from)?;
        let job = Job::submit(id.clone(), params, inputs, self.store.as_ref())
            .map_err(|e| Refusal::Invalid(format!("{e:#}")))?;
        tracing::info!("job {id} submitted ({})", job.name());
        self.jobs.insert(id.clone(), job);
        Ok(id)
    }

    pub fn job(&self, id: &str) -> Result<&Job, Refusal> {
        self.jobs
            .get(id)
            .ok_or_else(|| Refusal::NotFound(format!("no job {id:?} (see `scatterfarm jobs`)")))
    }

    fn job_mut(&mut self, id: &str) -> Result<&mut Job, Refusal> {
        self.jobs
            .get_mut(id)
            .ok_or_else(|| Refusal::NotFound(format!("no job {id:?} (see `scatterfarm jobs`)")))
    }

    /// Stops a job; leases of it are refused when they come back.
    pub fn cancel(&mut self, id: &str) -> Result<(), Refusal> {
        let store = self.store.clone();
        self.job_mut(id)?.cancel(store.as_ref())?;
        self.leases.retain(|_, l| l.job != id);
        tracing::info!("job {id} cancelled");
        Ok(())
    }

    /// Removes a job and everything stored of it (cancelling it first if it runs).
    pub fn delete(&mut self, id: &str) -> Result<(), Refusal> {
        self.cancel(id)?;
        self.jobs.remove(id);
        self.store.delete_job(id).map_err(anyhow::Error::from)?;
        self.strikes.retain(|(j, _), _| j != id);
        tracing::info!("job {id} deleted");
        Ok(())
    }

    /// Why an active job gets no renders, if it does not.
    pub fn waiting_reason(&self, job: &Job) -> Option<String> {
        if !job.is_active() {
            return None;
        }
        if self.leases.values().any(|l| l.job == job.id) {
            return None;
        }
        let matching = self
            .workers
            .values()
            .filter(|w| job.accepts(&w.fingerprint_key))
            .filter(|w| {
                self.strikes
                    .get(&(job.id.clone(), w.id.clone()))
                    .is_none_or(|&s| s < STRIKES)
            })
            .count();
        if matching == 0 {
            return Some(match job.progress.pinned.as_deref() {
                Some(p) if p != super::job::ANY_ENGINE => {
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

    // ---- workers -----------------------------------------------------------------------------

    /// Registers a worker; returns its id.
    pub fn register(
        &mut self,
        name: String,
        fingerprint: EngineFingerprint,
        photons_per_second: f64,
    ) -> String {
        let id = format!("w{:08x}-{}", self.boot, self.next_worker);
        self.next_worker += 1;
        let key = fingerprint.to_string();
        tracing::info!(
            "worker {id} ({name}) registered: {key}, {:.2} M photons/s",
            photons_per_second / 1e6
        );
        self.workers.insert(
            id.clone(),
            Worker {
                id: id.clone(),
                name,
                fingerprint,
                fingerprint_key: key,
                photons_per_second: if photons_per_second.is_finite() && photons_per_second > 0.0 {
                    photons_per_second
                } else {
                    1e5
                },
                last_seen: Instant::now(),
                tasks_completed: 0,
            },
        );
        id
    }

    /// Records a heartbeat; false if the worker is not known (it must register again).
    pub fn heartbeat(&mut self, worker: &str) -> bool {
        match self.workers.get_mut(worker) {
            Some(w) => {
                w.last_seen = Instant::now();
                true
            }
            None => false,
        }
    }

    /// The next piece for `worker`, or why there is none.
    pub fn lease(&mut self, worker_id: &str) -> Result<Result<TaskOut, String>, Refusal> {
        let worker = match self.workers.get_mut(worker_id) {
            Some(w) => {
                w.last_seen = Instant::now();
                w.clone()
            }
            None => {
                return Err(Refusal::NotFound(format!(
                    "unknown worker {worker_id}: register again"
                )))
            }
        };
        if self.draining {
            return Ok(Err("the coordinator is draining".into()));
        }
        // Round-robin: start after the job served last.
        let ids: Vec<String> = self.jobs.keys().cloned().collect();
        let start = self
            .last_served
            .as_ref()
            .and_then(|l| ids.iter().position(|i| i > l))
            .unwrap_or(0);
        let store = self.store.clone();
        let mut reason = "no job needs renders".to_string();
        for k in 0..ids.len() {
            let id = &ids[(start + k) % ids.len()];
            if self
                .strikes
                .get(&(id.clone(), worker.id.clone()))
                .is_some_and(|&s| s >= STRIKES)
            {
                reason = format!("blocked for job {id} after {STRIKES} bad results");
                continue;
            }
            let (next_group, next_task) = (&mut self.next_group, &mut self.next_task);
            let Some(job) = self.jobs.get_mut(id) else {
                continue;
            };
            if !job.is_active() {
                continue;
            }
            if !job.accepts(&worker.fingerprint_key) {
                reason = format!(
                    "no job for engine {} (job {id} is pinned to {})",
                    worker.fingerprint_key,
                    job.progress.pinned.clone().unwrap_or_default()
                );
                continue;
            }
            if job.progress.pinned.is_none() {
                tracing::info!("job {id} pinned to {}", worker.fingerprint_key);
                job.pin(&worker.fingerprint_key, store.as_ref())?;
            }
            let mut new_group = || {
                let g = *next_group;
                *next_group += 1;
                g
            };
            if let Err(e) = job.plan_work(&mut new_group, store.as_ref()) {
                let msg = format!("{e:#}");
                job.fail(msg, store.as_ref())?;
                continue;
            }
            let Some(group) = job.groups.iter_mut().find(|g| g.has_work()) else {
                continue;
            };
            let per_photon = (group.geometry.sources() * group.items.len()).max(1) as f64;
            let max_photons = (self.settings.task_seconds * worker.photons_per_second / per_photon)
                .clamp(1.0, f64::from(u32::MAX)) as u32;
            let mut new_task = || {
                let t = *next_task;
                *next_task += 1;
                t
            };
            let Some(piece) = group.take(max_photons, &mut new_task) else {
                continue;
            };
            let expected = piece.count as f64 * per_photon / worker.photons_per_second;
            let lease_for = self
                .settings
                .min_lease
                .max(Duration::from_secs_f64((expected * 5.0).min(86_400.0)));
            let task = TaskOut {
                job: id.clone(),
                piece,
                deadline_unix_ms: unix_ms_after(lease_for),
                geometry: group.geometry,
                job_geometry: group.geometry == job.plan.search_geometry,
                table: group.table.clone(),
                items: group.items.iter().map(|i| i.item.clone()).collect(),
            };
            self.leases.insert(
                piece.task_id,
                Lease {
                    job: id.clone(),
                    group: group.id,
                    piece,
                    worker: worker.id.clone(),
                    deadline: Instant::now() + lease_for,
                    deadline_unix_ms: task.deadline_unix_ms,
                },
            );
            self.last_served = Some(id.clone());
            return Ok(Ok(task));
        }
        Ok(Err(reason))
    }

    /// The lease a result claims to answer, checked for worker, job and attempt.
    fn check_lease(
        &self,
        worker: &str,
        job: &str,
        task: u64,
        attempt: u32,
    ) -> Result<&Lease, Refusal> {
        if !self.workers.contains_key(worker) {
            return Err(Refusal::NotFound(format!(
                "unknown worker {worker}: register again"
            )));
        }
        let lease = self.leases.get(&task).ok_or_else(|| {
            Refusal::Stale(format!(
                "task {task} is not leased (its lease expired and it was done elsewhere, or its job \
                 was cancelled)"
            ))
        })?;
        if lease.piece.attempt != attempt {
            return Err(Refusal::Stale(format!(
                "attempt {attempt} of task {task} is stale: attempt {} holds the lease",
                lease.piece.attempt
            )));
        }
        if lease.worker != worker {
            return Err(Refusal::Stale(format!(
                "task {task} attempt {attempt} is leased to another worker"
            )));
        }
        if lease.job != job {
            return Err(Refusal::Invalid(format!(
                "task {task} belongs to job {}, not {job}",
                lease.job
            )));
        }
        Ok(lease)
    }

    /// Takes a result: checks it, sums it, and when its group is complete scores it and
    /// advances the job.
    pub fn complete(
        &mut self,
        worker: &str,
        job_id: &str,
        task: u64,
        attempt: u32,
        counts: Result<Vec<CountMatrix>, String>,
        scatter_events: u64,
    ) -> Result<(), Refusal> {
        let refused = |core: &mut Core, r: Refusal| {
            core.counters.results_refused += 1;
            tracing::warn!("result of task {task} attempt {attempt} from {worker} refused: {r}");
            Err(r)
        };
        let lease = match self.check_lease(worker, job_id, task, attempt) {
            Ok(l) => l.clone(),
            Err(r) => return refused(self, r),
        };
        let store = self.store.clone();
        let check = {
            let job = self.job(job_id)?;
            match job.groups.iter().find(|g| g.id == lease.group) {
                None => Err(Refusal::Stale(format!(
                    "task {task}'s renders are no longer needed"
                ))),
                Some(group) => match &counts {
                    Err(e) => Err(Refusal::Invalid(e.clone())),
                    Ok(c) => group.check(&lease.piece, c).map_err(Refusal::Invalid),
                },
            }
        };
        if let Err(r) = check {
            self.leases.remove(&task);
            if let Refusal::Invalid(_) = r {
                let strikes = self
                    .strikes
                    .entry((job_id.to_string(), worker.to_string()))
                    .or_insert(0);
                *strikes += 1;
                if *strikes >= STRIKES {
                    tracing::warn!(
                        "worker {worker} sent {STRIKES} bad results for job {job_id}: blocked for it"
                    );
                }
                if let Ok(job) = self.job_mut(job_id) {
                    if let Some(g) = job.groups.iter_mut().find(|g| g.id == lease.group) {
                        g.give_back(lease.piece);
                    }
                }
            }
            return refused(self, r);
        }
        let counts = counts.map_err(Refusal::Invalid)?;
        self.leases.remove(&task);
        self.counters.results_accepted += 1;
        if let Some(w) = self.workers.get_mut(worker) {
            w.tasks_completed += 1;
        }
        let next_group = &mut self.next_group;
        let mut new_group = || {
            let g = *next_group;
            *next_group += 1;
            g
        };
        let job = self
            .jobs
            .get_mut(job_id)
            .ok_or_else(|| Refusal::NotFound(format!("no job {job_id}")))?;
        let Some(pos) = job.groups.iter().position(|g| g.id == lease.group) else {
            return Err(Refusal::Stale(format!(
                "task {task}'s renders are no longer needed"
            )));
        };
        let group = &mut job.groups[pos];
        group.accumulate(&lease.piece, counts, scatter_events);
        let photons =
            u64::from(lease.piece.count) * (group.geometry.sources() * group.items.len()) as u64;
        job.session_photons += photons;
        self.counters.photons += photons;
        let leased_elsewhere = self.leases.values().any(|l| l.group == lease.group);
        if job.groups[pos].is_complete() && !leased_elsewhere {
            let group: RenderGroup = job.groups.remove(pos);
            self.counters.renders_completed += group.items.len() as u64;
            if let Err(e) = job.group_complete(group, &mut new_group, store.as_ref()) {
                job.fail(format!("{e:#}"), store.as_ref())?;
            }
        }
        Ok(())
    }

    /// A worker gives a task back.
    pub fn release(
        &mut self,
        worker: &str,
        job: &str,
        task: u64,
        attempt: u32,
        reason: &str,
    ) -> Result<(), Refusal> {
        let lease = self.check_lease(worker, job, task, attempt)?.clone();
        tracing::warn!("worker {worker} gave back task {task}: {reason}");
        self.leases.remove(&task);
        if let Some(j) = self.jobs.get_mut(job) {
            if let Some(g) = j.groups.iter_mut().find(|g| g.id == lease.group) {
                g.give_back(lease.piece);
            }
        }
        Ok(())
    }

    /// Hands out again the leases past their deadline or of workers that stopped sending
    /// heartbeats, and forgets those workers.
    pub fn sweep(&mut self, now: Instant) {
        let silent_after = self.settings.heartbeat * self.settings.missed_heartbeats;
        let gone: Vec<String> = self
            .workers
            .values()
            .filter(|w| now.duration_since(w.last_seen) > silent_after)
            .map(|w| w.id.clone())
            .collect();
        for id in &gone {
            tracing::warn!(
                "worker {id} missed {} heartbeats: forgotten",
                self.settings.missed_heartbeats
            );
            self.workers.remove(id);
        }
        let expired: Vec<u64> = self
            .leases
            .iter()
            .filter(|(_, l)| now > l.deadline || !self.workers.contains_key(&l.worker))
            .map(|(&t, _)| t)
            .collect();
        for t in expired {
            if let Some(l) = self.leases.remove(&t) {
                tracing::warn!(
                    "task {t} attempt {} of job {} (worker {}) expired: leasing it again",
                    l.piece.attempt,
                    l.job,
                    l.worker
                );
                self.counters.leases_expired += 1;
                if let Some(j) = self.jobs.get_mut(&l.job) {
                    if let Some(g) = j.groups.iter_mut().find(|g| g.id == l.group) {
                        g.give_back(l.piece);
                    }
                }
            }
        }
    }

    /// The phase name of a job, for listings.
    pub fn phase_name(job: &Job) -> &'static str {
        match job.progress.phase {
            Phase::Preparing => "preparing",
            Phase::Searching => "searching",
            Phase::Finished => "finished",
            Phase::Cancelled => "cancelled",
            Phase::Failed { .. } => "failed",
        }
    }
}
