//! The job-status view: a job as clients, the CLI and the status page see it (the protocol's
//! `JobStatus`), and the one name of each job state.

use crate::job::{Job, JobState};
use crate::scheduler::{Refusal, Scheduler};
use scatterfarm_proto::v1 as pb;
use scatterfarm_search::Progress;

/// The protocol's state of a job.
fn state_of(job: &Job) -> pb::JobState {
    if job.is_paused() {
        return pb::JobState::Paused;
    }
    match job.checkpoint.state {
        JobState::Preparing => pb::JobState::Preparing,
        JobState::Searching => pb::JobState::Searching,
        JobState::Finished => pb::JobState::Finished,
        JobState::Cancelled => pb::JobState::Cancelled,
        JobState::Failed { .. } => pb::JobState::Failed,
    }
}

/// A job's status as clients see it.
pub fn job_status(scheduler: &Scheduler, job: &Job) -> pb::JobStatus {
    let p = job.checkpoint.search.progress();
    let (rate, eta) = job.pace();
    let message = match &job.checkpoint.state {
        _ if job.is_paused() => job
            .paused
            .as_ref()
            .map(|p| p.reason.clone())
            .unwrap_or_default(),
        JobState::Failed { message } => message.clone(),
        JobState::Preparing => scheduler
            .waiting_reason(job)
            .unwrap_or_else(|| "rendering the target and calibrating ε".into()),
        JobState::Searching => scheduler.waiting_reason(job).unwrap_or_default(),
        JobState::Finished => "finished".into(),
        JobState::Cancelled => "cancelled".into(),
    };
    pb::JobStatus {
        job_id: job.id.clone(),
        name: job.name(),
        state: state_of(job) as i32,
        message,
        engine: job.checkpoint.pinned.clone().unwrap_or_default(),
        level: p.level,
        levels: p.levels,
        permutation: p.permutation,
        permutations: p.permutations,
        region: p.region,
        regions: p.regions,
        renders_done: p.renders_done,
        renders_total: p.renders_total,
        best_similarity: p.best_score.unwrap_or(f64::NAN),
        photons: job.checkpoint.photons_simulated,
        photons_per_second: rate,
        eta_seconds: eta.unwrap_or(-1.0),
        workers_busy: scheduler.workers_busy(&job.id),
        submitted_unix_seconds: job.record.submitted_unix,
        refining: p.refining,
        sweep: p.sweep,
        sweeps: p.sweeps,
    }
}

/// The search's progress as a status carries it, for displays ([`Progress::stage`]).
pub fn progress_of(s: &pb::JobStatus) -> Progress {
    Progress {
        level: s.level,
        levels: s.levels,
        permutation: s.permutation,
        permutations: s.permutations,
        region: s.region,
        regions: s.regions,
        renders_done: s.renders_done,
        renders_total: s.renders_total,
        best_score: s.best_similarity.is_finite().then_some(s.best_similarity),
        refining: s.refining,
        sweep: s.sweep,
        sweeps: s.sweeps,
    }
}

/// The status of job `id`, damaged or not.
pub fn status_of(scheduler: &Scheduler, id: &str) -> Result<pb::JobStatus, Refusal> {
    if let Some(why) = scheduler.damaged.get(id) {
        return Ok(damaged_status(id, why));
    }
    Ok(job_status(scheduler, scheduler.job(id)?))
}

/// Every job's status, damaged ones included, by id.
pub fn all_statuses(scheduler: &Scheduler) -> Vec<pb::JobStatus> {
    let mut all: Vec<pb::JobStatus> = scheduler
        .jobs
        .values()
        .map(|j| job_status(scheduler, j))
        .chain(
            scheduler
                .damaged
                .iter()
                .map(|(id, why)| damaged_status(id, why)),
        )
        .collect();
    all.sort_by(|a, b| a.job_id.cmp(&b.job_id));
    all
}

/// A stored job that cannot be read.
fn damaged_status(id: &str, why: &str) -> pb::JobStatus {
    pb::JobStatus {
        job_id: id.to_string(),
        name: id.to_string(),
        state: pb::JobState::Damaged as i32,
        message: format!("damaged: {why}; `scatterfarm delete {id}` removes it"),
        best_similarity: f64::NAN,
        eta_seconds: -1.0,
        ..Default::default()
    }
}

/// A job state's name in listings and pages.
pub fn state_name(state: i32) -> &'static str {
    match pb::JobState::try_from(state) {
        Ok(pb::JobState::Preparing) => "preparing",
        Ok(pb::JobState::Searching) => "searching",
        Ok(pb::JobState::Finished) => "finished",
        Ok(pb::JobState::Cancelled) => "cancelled",
        Ok(pb::JobState::Failed) => "failed",
        Ok(pb::JobState::Paused) => "paused",
        Ok(pb::JobState::Damaged) => "damaged",
        _ => "unknown",
    }
}

/// Seconds as H:MM:SS, or "?" when unknown (negative or not finite).
pub fn duration_text(seconds: f64) -> String {
    if seconds < 0.0 || !seconds.is_finite() {
        return "?".into();
    }
    let t = seconds.round() as u64;
    format!("{}:{:02}:{:02}", t / 3600, t / 60 % 60, t % 60)
}

/// Whether a status is final (finished, cancelled, failed or damaged).
pub fn is_terminal(s: &pb::JobStatus) -> bool {
    matches!(
        pb::JobState::try_from(s.state),
        Ok(pb::JobState::Finished
            | pb::JobState::Cancelled
            | pb::JobState::Failed
            | pb::JobState::Damaged)
    )
}
