//! The lease loop: lease a task, render it on a blocking thread, return its counts (or give it
//! back), until shutdown or `max_tasks`. A differential task is rendered in its chunks and its
//! changes are scored here against the job's target, so one score per change goes back; a
//! scored task's renders are scored here too, and their scores go back instead of the counts.

use super::cache::{GeometryCache, TargetCache};
use super::retry::{describe, is_auth_failure, is_transient, within, Backoff, Stop};
use super::session::{Connector, Session};
use super::{AgentError, AgentSummary};
use scatterfarm_model::differential::{render_in_chunks, PhotonChunks};
use scatterfarm_model::engine::{Engine, RenderOutput};
use scatterfarm_model::likelihood::{change_deviances, deviance, Target};
use scatterfarm_proto::convert::{decode_task, outputs_to_proto, ConvertError, RenderTask};
use scatterfarm_proto::differential::change_scores_to_proto;
use scatterfarm_proto::scored::render_scores_to_proto;
use scatterfarm_proto::v1::{self, CompleteRequest, LeaseRequest, ReleaseRequest, Task};
use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};
use tonic::Code;

/// How long a Lease or Release may take.
const CALL_TIMEOUT: Duration = Duration::from_secs(60);
/// How long a Complete (megabytes of counts) may take.
const COMPLETE_TIMEOUT: Duration = Duration::from_secs(600);
/// The pause when the coordinator has no task and names no `retry_after_ms`.
const DEFAULT_RETRY_AFTER: Duration = Duration::from_secs(1);
/// Returning a result is retried at least this long, even past the lease deadline.
const MIN_COMPLETE_PATIENCE: Duration = Duration::from_secs(30);
/// …and this long when the lease names no deadline.
const NO_DEADLINE_PATIENCE: Duration = Duration::from_secs(600);
/// After shutdown is asked for, a result is retried at most this long.
const SHUTDOWN_PATIENCE: Duration = Duration::from_secs(30);

/// A task's identity, for its Complete, its Release and the log.
#[derive(Debug, Clone)]
struct TaskRef {
    job_id: String,
    task_id: u64,
    attempt: u32,
    deadline_unix_ms: u64,
}

impl std::fmt::Display for TaskRef {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "job {} task {} attempt {}",
            self.job_id, self.task_id, self.attempt
        )
    }
}

/// A rendered task, encoded for its Complete.
struct Encoded {
    counts: Vec<v1::CountMatrix>,
    scatter_events: u64,
    change_scores: Vec<v1::ChangeScore>,
    render_scores: Vec<v1::RenderScore>,
}

/// What became of a leased task.
enum Outcome {
    Completed {
        photons: u64,
    },
    /// Given back, or refused: nothing to count.
    NotCompleted,
    /// The engine or the task was at fault: pause before leasing again.
    Failed,
}

pub(crate) struct Worker {
    pub engine: Arc<dyn Engine>,
    pub connector: Connector,
    pub stop: Stop,
    pub max_tasks: Option<u64>,
}

impl Worker {
    /// Registers, then leases and renders until shutdown or `max_tasks` completed tasks.
    pub async fn run(mut self) -> Result<AgentSummary, AgentError> {
        let mut summary = AgentSummary::default();
        let Some(mut session) = self.connector.session().await? else {
            return Ok(summary);
        };
        let mut cache = GeometryCache::new(GeometryCache::CAPACITY);
        let mut targets = TargetCache::new(TargetCache::CAPACITY, TargetCache::BYTES);
        let mut backoff = Backoff::new();
        let mut failures = Backoff::new();
        loop {
            if self.stop.requested() || self.max_tasks.is_some_and(|m| summary.tasks_completed >= m)
            {
                return Ok(summary);
            }
            if session.is_forgotten() {
                match self.connector.session().await? {
                    Some(s) => session = s,
                    None => return Ok(summary),
                }
                continue;
            }
            let request = LeaseRequest {
                worker_id: session.worker_id.clone(),
                cached_jobs: cache.jobs(),
                cached_targets: targets.jobs(),
            };
            let task = match within(CALL_TIMEOUT, session.client.lease(request)).await {
                Ok(response) => {
                    backoff.reset();
                    match response.task {
                        Some(task) => task,
                        None => {
                            tracing::debug!(
                                "no task ({}); asking again in {} ms",
                                if response.reason.is_empty() {
                                    "no reason given"
                                } else {
                                    &response.reason
                                },
                                response.retry_after_ms
                            );
                            let delay = match response.retry_after_ms {
                                0 => DEFAULT_RETRY_AFTER,
                                ms => Duration::from_millis(u64::from(ms)),
                            };
                            self.stop.sleep(delay).await;
                            continue;
                        }
                    }
                }
                Err(status) if status.code() == Code::NotFound => {
                    tracing::info!(
                        "the coordinator at {} no longer knows worker {} ({}); registering again",
                        self.connector.url(),
                        session.worker_id,
                        status.message()
                    );
                    match self.connector.session().await? {
                        Some(s) => session = s,
                        None => return Ok(summary),
                    }
                    continue;
                }
                Err(status) if is_auth_failure(&status) => {
                    return Err(self.unauthenticated(&status));
                }
                Err(status) => {
                    let delay = backoff.next_delay();
                    tracing::warn!(
                        "cannot lease from the coordinator at {}: {}; retrying in {:.1} s",
                        self.connector.url(),
                        describe(&status),
                        delay.as_secs_f64()
                    );
                    self.stop.sleep(delay).await;
                    continue;
                }
            };
            match self
                .handle(&mut session, &mut cache, &mut targets, task)
                .await?
            {
                Outcome::Completed { photons } => {
                    summary.tasks_completed += 1;
                    summary.photons += photons;
                    failures.reset();
                }
                Outcome::NotCompleted => {}
                Outcome::Failed => {
                    self.stop.sleep(failures.next_delay()).await;
                }
            }
        }
    }

    fn unauthenticated(&self, status: &tonic::Status) -> AgentError {
        AgentError::Unauthenticated {
            url: self.connector.url().to_string(),
            message: status.message().to_string(),
        }
    }

    /// Renders one leased task and returns its counts, or gives it back.
    async fn handle(
        &mut self,
        session: &mut Session,
        cache: &mut GeometryCache,
        targets: &mut TargetCache,
        task: Task,
    ) -> Result<Outcome, AgentError> {
        let task_ref = TaskRef {
            job_id: task.job_id.clone(),
            task_id: task.task_id,
            attempt: task.attempt,
            deadline_unix_ms: task.lease_deadline_unix_ms,
        };
        let decoded = cache
            .resolve(&task)
            .and_then(|geometry| decode_task(&task, geometry))
            .and_then(|render| {
                if render.differential.is_none() && !render.scored {
                    return Ok((render, None));
                }
                targets
                    .resolve(&task, &render.geometry)
                    .map(|t| (render, Some(t)))
            });
        let (render, target) = match decoded {
            Ok(decoded) => decoded,
            Err(e) => {
                tracing::warn!("cannot render {task_ref}: {e}; giving it back");
                self.release(session, &task_ref, format!("protocol error: {e}"))
                    .await?;
                return Ok(Outcome::Failed);
            }
        };
        drop(task);
        tracing::debug!(
            "leased {task_ref}: {} assignments, photons {}..{}, grid {}, {} sources",
            render.items.len(),
            render.photons.first,
            render.photons.end(),
            render.geometry.grid,
            render.geometry.sources()
        );
        let photons = render.photons_launched();
        let (encoded, seconds) = self.render(render, target).await;
        let Encoded {
            counts,
            scatter_events,
            change_scores,
            render_scores,
        } = match encoded {
            Ok(encoded) => encoded,
            Err(e) => {
                tracing::warn!("the engine failed on {task_ref}: {e}; giving it back");
                self.release(session, &task_ref, format!("engine failed: {e}"))
                    .await?;
                return Ok(Outcome::Failed);
            }
        };
        tracing::debug!(
            "rendered {task_ref} in {seconds:.3} s ({:.3e} photons/s)",
            photons as f64 / seconds.max(1e-9)
        );
        let request = CompleteRequest {
            worker_id: session.worker_id.clone(),
            job_id: task_ref.job_id.clone(),
            task_id: task_ref.task_id,
            attempt: task_ref.attempt,
            counts,
            scatter_events,
            render_seconds: seconds,
            change_scores,
            render_scores,
        };
        Ok(if self.complete(session, &task_ref, request).await? {
            Outcome::Completed { photons }
        } else {
            Outcome::NotCompleted
        })
    }

    /// Runs the engine on a blocking thread (to the end, shutdown or not) and encodes what it
    /// rendered, or the error text; with the wall seconds. A differential task (with the
    /// job's `target`) is rendered in its chunks and its changes scored there too; a scored task's
    /// renders are scored against it and only their scores kept.
    async fn render(
        &self,
        render: RenderTask,
        target: Option<Arc<Target>>,
    ) -> (Result<Encoded, String>, f64) {
        let engine = self.engine.clone();
        let start = Instant::now();
        let joined = tokio::task::spawn_blocking(move || match (&render.differential, target) {
            (Some(part), Some(target)) => render_and_score(engine.as_ref(), &render, part, &target),
            (Some(_), None) => Err("a differential task without the job's target".to_string()),
            (None, target) => {
                let outputs = engine.render(&render.batch()).map_err(|e| e.to_string())?;
                if !render.scored {
                    let (counts, scatter_events) = outputs_to_proto(&render, &outputs)
                        .map_err(|e: ConvertError| e.to_string())?;
                    return Ok(Encoded {
                        counts,
                        scatter_events,
                        change_scores: Vec::new(),
                        render_scores: Vec::new(),
                    });
                }
                let target = target.ok_or("a scored task without the job's target")?;
                score_renders(&render, &outputs, &target)
            }
        })
        .await;
        let seconds = start.elapsed().as_secs_f64();
        let result = joined.unwrap_or_else(|e| Err(format!("the engine panicked: {e}")));
        (result, seconds)
    }

    /// Returns a result: true when the coordinator took it. Transient failures are retried with
    /// backoff (for a while); a refusal (a stale attempt, say) is logged and dropped.
    async fn complete(
        &mut self,
        session: &mut Session,
        task: &TaskRef,
        mut request: CompleteRequest,
    ) -> Result<bool, AgentError> {
        let started = Instant::now();
        let patience = complete_patience(task.deadline_unix_ms);
        let mut backoff = Backoff::new();
        let mut registered_again = false;
        loop {
            request.worker_id = session.worker_id.clone();
            let status =
                match within(COMPLETE_TIMEOUT, session.client.complete(request.clone())).await {
                    Ok(_) => {
                        tracing::debug!("returned {task}");
                        return Ok(true);
                    }
                    Err(status) => status,
                };
            if is_auth_failure(&status) {
                return Err(self.unauthenticated(&status));
            }
            if status.code() == Code::NotFound && !registered_again {
                tracing::info!(
                    "the coordinator at {} does not know worker {} ({}); registering again to return {task}",
                    self.connector.url(),
                    session.worker_id,
                    status.message()
                );
                registered_again = true;
                match self.connector.session().await? {
                    Some(s) => *session = s,
                    None => return Ok(false),
                }
                continue;
            }
            let limit = if self.stop.requested() {
                patience.min(SHUTDOWN_PATIENCE)
            } else {
                patience
            };
            if !is_transient(&status) || started.elapsed() >= limit {
                tracing::warn!(
                    "the coordinator at {} did not take the result of {task}: {}",
                    self.connector.url(),
                    describe(&status)
                );
                return Ok(false);
            }
            let delay = backoff.next_delay();
            tracing::warn!(
                "cannot return {task} to the coordinator at {}: {}; retrying in {:.1} s",
                self.connector.url(),
                describe(&status),
                delay.as_secs_f64()
            );
            tokio::time::sleep(delay).await;
        }
    }

    /// Gives a task back with `reason`; a few tries, then the lease deadline does it for us.
    async fn release(
        &mut self,
        session: &mut Session,
        task: &TaskRef,
        reason: String,
    ) -> Result<(), AgentError> {
        let request = ReleaseRequest {
            worker_id: session.worker_id.clone(),
            job_id: task.job_id.clone(),
            task_id: task.task_id,
            attempt: task.attempt,
            reason,
        };
        let mut backoff = Backoff::new();
        for attempt in 1..=3 {
            match within(CALL_TIMEOUT, session.client.release(request.clone())).await {
                Ok(v1::ReleaseResponse {}) => return Ok(()),
                Err(status) if is_auth_failure(&status) => {
                    return Err(self.unauthenticated(&status))
                }
                Err(status) if is_transient(&status) && attempt < 3 => {
                    tokio::time::sleep(backoff.next_delay()).await;
                }
                Err(status) => {
                    tracing::warn!(
                        "cannot give {task} back to the coordinator at {}: {}",
                        self.connector.url(),
                        describe(&status)
                    );
                    return Ok(());
                }
            }
        }
        Ok(())
    }
}

/// Renders a differential task in its chunks and scores every change it estimated against
/// `target`: the rendered map's counts and one score per change.
fn render_and_score(
    engine: &dyn Engine,
    render: &RenderTask,
    part: &scatterfarm_proto::differential::DifferentialPart,
    target: &Target,
) -> Result<Encoded, String> {
    let item = render
        .items
        .first()
        .ok_or("a differential task without its assignment")?;
    let output = render_in_chunks(
        engine,
        render.geometry,
        &render.table,
        item,
        PhotonChunks {
            photons: render.photons.count,
            chunk: part.chunk,
        },
        &part.changes,
        &mut |_| {},
    )
    .map_err(|e| e.to_string())?;
    let scores = change_deviances(target, &output, u64::from(render.photons.count))
        .map_err(|e| format!("scoring the changes: {e}"))?;
    let outputs = [RenderOutput {
        counts: output.counts,
        scatter_events: output.scatter_events,
    }];
    let (counts, scatter_events) = outputs_to_proto(render, &outputs).map_err(|e| e.to_string())?;
    Ok(Encoded {
        counts,
        scatter_events,
        change_scores: change_scores_to_proto(&scores),
        render_scores: Vec::new(),
    })
}

/// A scored task's renders scored against `target` (the deviance, as the coordinator scores in
/// process): one score per assignment, and no counts.
fn score_renders(
    render: &RenderTask,
    outputs: &[RenderOutput],
    target: &Target,
) -> Result<Encoded, String> {
    if outputs.len() != render.items.len() {
        return Err(ConvertError::OutputCount {
            expected: render.items.len(),
            got: outputs.len(),
        }
        .to_string());
    }
    let photons = u64::from(render.photons.count);
    let scores = outputs
        .iter()
        .enumerate()
        .map(|(k, o)| {
            deviance(target, &o.counts, photons).map_err(|e| format!("scoring render {k}: {e}"))
        })
        .collect::<Result<Vec<_>, _>>()?;
    Ok(Encoded {
        counts: Vec::new(),
        scatter_events: outputs
            .iter()
            .fold(0u64, |n, o| n.saturating_add(o.scatter_events)),
        change_scores: Vec::new(),
        render_scores: render_scores_to_proto(&scores),
    })
}

/// How long to keep retrying a result: until the lease deadline, and at least a little while.
fn complete_patience(deadline_unix_ms: u64) -> Duration {
    if deadline_unix_ms == 0 {
        return NO_DEADLINE_PATIENCE;
    }
    let now_ms = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_millis() as u64)
        .unwrap_or(0);
    Duration::from_millis(deadline_unix_ms.saturating_sub(now_ms)).max(MIN_COMPLETE_PATIENCE)
}
