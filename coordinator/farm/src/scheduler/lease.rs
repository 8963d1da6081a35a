//! The scheduler proper: the next piece of work for a worker, taken from the jobs in
//! round-robin, with the job pinned to the worker's engine on its first lease.

use super::sizing::{lease_duration, max_photons, photons_per_launch, piece_photons_per_launch};
use super::{unix_ms_after, Refusal, Scheduler, STRIKES};
use crate::work::Piece;
use scatterfarm_proto::differential::DifferentialPart;
use scatterfarm_search::driver::Scoring;
use std::sync::Arc;
use std::time::Instant;

/// A leased piece.
#[derive(Debug, Clone)]
pub struct Lease {
    pub job: String,
    pub group: u64,
    pub piece: Piece,
    pub worker: String,
    /// When it was leased: a result's arrival less its render time is the worker's transfer
    /// time.
    pub leased_at: Instant,
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
    /// A differential render's changes and chunk size.
    pub differential: Option<DifferentialPart>,
    /// The job's scoring, for a differential or scored render: its target goes to workers
    /// without it.
    pub scoring: Option<Arc<Scoring>>,
    /// Whether the worker scores the renders and returns their scores, not their counts.
    pub scored: bool,
}

impl Scheduler {
    /// The next piece for `worker`, or why there is none.
    pub fn lease(&mut self, worker_id: &str) -> Result<Result<TaskOut, String>, Refusal> {
        let worker = match self.workers.get_mut(worker_id) {
            Some(w) => {
                self.liveness.touch(worker_id, Instant::now());
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
            if self.strikes.blocked(id, &worker.name) {
                reason = format!("blocked for job {id} after {STRIKES} bad results");
                continue;
            }
            let next_group = &mut self.next_group;
            let Some(job) = self.jobs.get_mut(id) else {
                continue;
            };
            if !job.is_active() || job.is_paused() {
                continue;
            }
            if job.needs_differential() && !worker.renders_differentially {
                reason = format!(
                    "job {id} screens by differential renders, which engine {} does not render",
                    worker.fingerprint_key
                );
                continue;
            }
            if !job.accepts(&worker.fingerprint_key) {
                reason = format!(
                    "no job for engine {} (job {id} is pinned to {})",
                    worker.fingerprint_key,
                    job.checkpoint.pinned.clone().unwrap_or_default()
                );
                continue;
            }
            let budget = self.settings.max_job_photons;
            if job.checkpoint.photons_simulated > budget {
                let message = format!(
                    "the job simulated {} photons, more than this coordinator's budget of {budget} \
                     per job (--max-job-photons)",
                    job.checkpoint.photons_simulated
                );
                if let Err(e) = job.fail(message, store.as_ref()) {
                    job.pause(&e);
                }
                continue;
            }
            if job.checkpoint.pinned.is_none() {
                tracing::info!("job {id} pinned to {}", worker.fingerprint_key);
                if let Err(e) = job.pin(&worker.fingerprint_key, store.as_ref()) {
                    job.on_error(e, store.as_ref());
                    continue;
                }
            }
            let mut new_group = super::ids(next_group);
            if let Err(e) = job.plan_work(&mut new_group, store.as_ref()) {
                job.on_error(e, store.as_ref());
                continue;
            }
            let scoring = job.scoring().cloned();
            let scores = worker.scores_renders;
            let Some(group) = job
                .groups
                .iter_mut()
                .find_map(|g| (g.has_work() && (scores || g.serves_counts())).then_some(g))
            else {
                if job.groups.iter().any(|g| g.has_work()) {
                    reason = format!(
                        "job {id}'s renders under way are scored on workers, which worker {} \
                         does not do (a release before protocol 1.3)",
                        worker.name
                    );
                }
                continue;
            };
            let per_photon = photons_per_launch(group);
            let max_photons = max_photons(&self.settings, worker.photons_per_second, per_photon);
            // Drawn before it is known to be needed (a requeued piece keeps its id): ids
            // skipped that way are never seen.
            let task_id = store.new_task_id().map_err(anyhow::Error::from)?;
            let Some(piece) = group.take(max_photons, &mut || task_id) else {
                continue;
            };
            let lease_for = lease_duration(
                &self.settings,
                piece.count,
                worker.photons_per_second,
                piece_photons_per_launch(group, &piece),
                worker.transfer_seconds,
            );
            let task = TaskOut {
                job: id.clone(),
                piece,
                deadline_unix_ms: unix_ms_after(lease_for),
                geometry: group.geometry,
                job_geometry: group.geometry == job.plan.search_geometry,
                table: group.table.clone(),
                items: group.items[piece.items()]
                    .iter()
                    .map(|i| i.item.clone())
                    .collect(),
                differential: group.is_differential().then(|| DifferentialPart {
                    changes: group.changes.clone(),
                    chunk: scatterfarm_model::differential::CHUNK_PHOTONS,
                }),
                scoring: scoring.filter(|_| group.is_differential() || group.is_scored()),
                scored: group.is_scored(),
            };
            self.leases.insert(
                piece.task_id,
                Lease {
                    job: id.clone(),
                    group: group.id,
                    piece,
                    worker: worker.id.clone(),
                    leased_at: Instant::now(),
                    deadline: Instant::now() + lease_for,
                    deadline_unix_ms: task.deadline_unix_ms,
                },
            );
            self.last_served = Some(id.clone());
            return Ok(Ok(task));
        }
        Ok(Err(reason))
    }
}
