//! Results and give-backs: a returned result is checked against its lease (worker, job,
//! attempt) and its group, counted against the worker if malformed, and otherwise summed; a
//! complete search group is handed out to be scored off the lock ([`ScoreWork`]), and its
//! scores ([`Scheduler::scored`]) advance its job.

use super::giveback::Returned;
use super::sizing::piece_photons_per_launch;
use super::{Lease, Refusal, Scheduler, STRIKES};
use crate::job::scoring::{ScoreWork, Scored};
use crate::work::RenderGroup;
use scatterfarm_model::likelihood::Deviance;
use scatterfarm_model::CountMatrix;

/// What a worker returns for a piece.
#[derive(Debug)]
pub struct Rendered {
    /// One matrix per assignment, or why the result could not be decoded.
    pub counts: Result<Vec<CountMatrix>, String>,
    pub scatter_events: u64,
    /// The worker's own time for the render, which feeds its measured speed.
    pub render_seconds: f64,
    /// A differential render's change scores (one per change; none for a plain render), or why
    /// they could not be decoded.
    pub change_scores: Result<Vec<Option<Deviance>>, String>,
    /// A scored task's render scores (one per assignment, and no counts; none for other
    /// tasks), or why they could not be decoded.
    pub render_scores: Result<Vec<Deviance>, String>,
}

impl Scheduler {
    /// The lease a result claims to answer, checked for worker, job and attempt.
    pub(super) fn check_lease(
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

    /// Takes a result: checks it and sums it. When that completes a search group, the group
    /// comes back to be scored off the lock: run it and hand it to [`Scheduler::scored`].
    pub fn complete(
        &mut self,
        worker: &str,
        job_id: &str,
        task: u64,
        attempt: u32,
        rendered: Rendered,
    ) -> Result<Option<ScoreWork>, Refusal> {
        let Rendered {
            counts,
            scatter_events,
            render_seconds,
            change_scores,
            render_scores,
        } = rendered;
        let refused = |scheduler: &mut Scheduler, r: Refusal| {
            scheduler.counters.results_refused += 1;
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
                Some(group) => match (&counts, &change_scores, &render_scores) {
                    (Err(e), _, _) | (_, Err(e), _) | (_, _, Err(e)) => {
                        Err(Refusal::Invalid(e.clone()))
                    }
                    (Ok(c), Ok(s), Ok(r)) => {
                        group.check(&lease.piece, c, s, r).map_err(Refusal::Invalid)
                    }
                },
            }
        };
        if let Err(r) = check {
            self.leases.remove(&task);
            if let Refusal::Invalid(why) = &r {
                let identity = self
                    .workers
                    .get(worker)
                    .map(|w| w.name.clone())
                    .unwrap_or_else(|| worker.to_string());
                let n = self.strikes.add(job_id, &identity, store.as_ref());
                if n >= STRIKES {
                    tracing::warn!(
                        "worker {worker} ({identity}) sent {STRIKES} bad results for job \
                         {job_id}: blocked for it"
                    );
                }
                let detail = format!("worker {worker} ({identity}) sent: {why}");
                self.piece_returned(lease, Returned::Refused, &detail);
            }
            return refused(self, r);
        }
        let counts = counts.map_err(Refusal::Invalid)?;
        let change_scores = change_scores.map_err(Refusal::Invalid)?;
        let render_scores = render_scores.map_err(Refusal::Invalid)?;
        self.leases.remove(&task);
        self.counters.results_accepted += 1;
        let per_launch = job_photons_per_launch(self, job_id, &lease);
        if let Some(w) = self.workers.get_mut(worker) {
            w.tasks_completed += 1;
            w.measured(
                u64::from(lease.piece.count) as f64 * per_launch,
                render_seconds,
            );
            w.measured_transfer(lease.leased_at.elapsed().as_secs_f64(), render_seconds);
        }
        let next_group = &mut self.next_group;
        let mut new_group = super::ids(next_group);
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
        group.accumulate(
            &lease.piece,
            counts,
            scatter_events,
            change_scores,
            render_scores,
        );
        let photons = u64::from(lease.piece.count)
            * (group.geometry.sources() * lease.piece.items_count as usize) as u64;
        job.session_photons += photons;
        self.counters.photons += photons;
        let leased_elsewhere = self.leases.values().any(|l| l.group == lease.group);
        let mut work = None;
        if job.groups[pos].is_complete() && !leased_elsewhere {
            let group: RenderGroup = job.groups.remove(pos);
            self.counters.renders_completed += group.items.len() as u64;
            if group.is_scored() {
                self.counters.renders_scored_on_workers += group.items.len() as u64;
            }
            match job.group_complete(group, &mut new_group, store.as_ref()) {
                Ok(w) => work = w,
                Err(e) => {
                    job.on_error(e, store.as_ref());
                    if !job.is_active() || job.is_paused() {
                        self.leases.retain(|_, l| l.job != job_id);
                    }
                }
            }
        }
        Ok(work)
    }

    /// Takes a group's scores, made off the lock from the [`ScoreWork`] that
    /// [`Scheduler::complete`] handed out: its job keeps them and plans its next work. Scores
    /// of a job deleted meanwhile are dropped.
    pub fn scored(&mut self, scored: Scored) {
        let store = self.store.clone();
        let next_group = &mut self.next_group;
        let mut new_group = super::ids(next_group);
        let Some(job) = self.jobs.get_mut(&scored.job) else {
            return;
        };
        if let Err(e) = job.take_scored(scored, &mut new_group, store.as_ref()) {
            job.on_error(e, store.as_ref());
            if !job.is_active() || job.is_paused() {
                let id = job.id.clone();
                self.leases.retain(|_, l| l.job != id);
            }
        }
    }

    /// [`Scheduler::complete`] with its scoring done at once, under the lock: for tests and
    /// tools that drive a scheduler on one thread.
    pub fn complete_and_score(
        &mut self,
        worker: &str,
        job_id: &str,
        task: u64,
        attempt: u32,
        rendered: Rendered,
    ) -> Result<(), Refusal> {
        if let Some(work) = self.complete(worker, job_id, task, attempt, rendered)? {
            self.scored(work.run());
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
        let detail = format!("worker {worker}: {reason}");
        self.piece_returned(lease, Returned::GivenBack, &detail);
        Ok(())
    }
}

/// Photons one photon index of `lease`'s piece of `job` launches; 0 when its group is gone.
fn job_photons_per_launch(s: &Scheduler, job: &str, lease: &Lease) -> f64 {
    s.jobs
        .get(job)
        .and_then(|j| j.groups.iter().find(|g| g.id == lease.group))
        .map_or(0.0, |g| piece_photons_per_launch(g, &lease.piece))
}
