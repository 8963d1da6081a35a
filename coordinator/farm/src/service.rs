//! The two gRPC services over a shared [`Core`]: `WorkerService` (register, heartbeat, lease,
//! complete, release) and `ClientService` (submit, status, watch, result, cancel, delete,
//! listings). They translate between protocol messages and the core's types and map refusals
//! to status codes; all decisions live in the core.

use super::core::{Core, Refusal, TaskOut};
use super::job::{Job, Phase};
use scatterfarm_job::inputs::Inputs;
use scatterfarm_job::spec::JobSpec;
use scatterfarm_model::{CountMatrix, EngineFingerprint, Material};
use scatterfarm_proto::v1 as pb;
use scatterfarm_proto::v1::client_service_server::ClientService;
use scatterfarm_proto::v1::worker_service_server::WorkerService;
use std::path::Path;
use std::pin::Pin;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};
use tokio::sync::Notify;
use tokio_stream::Stream;
use tonic::{Request, Response, Status};

/// The coordinator shared by both services and the background sweeper.
pub struct Farm {
    core: Mutex<Core>,
    /// Woken when work may have appeared (a submission, a piece given back, a group done).
    pub work: Notify,
}

impl Farm {
    pub fn new(core: Core) -> Arc<Farm> {
        Arc::new(Farm {
            core: Mutex::new(core),
            work: Notify::new(),
        })
    }

    /// The core, even if a panic poisoned the lock (the state stays consistent per call).
    pub fn core(&self) -> MutexGuard<'_, Core> {
        self.core.lock().unwrap_or_else(|e| e.into_inner())
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

/// The `WorkerService` implementation.
pub struct WorkerApi(pub Arc<Farm>);

fn material_to_pb(m: &Material) -> pb::Material {
    pb::Material {
        sigma_s: m.sigma_s,
        sigma_a: if m.is_opaque() { 0.0 } else { m.sigma_a },
        g: m.g,
        opaque: m.is_opaque(),
    }
}

fn task_to_pb(t: TaskOut, cached: &[String]) -> pb::Task {
    let send_geometry = !(t.job_geometry && cached.contains(&t.job));
    pb::Task {
        job_id: t.job,
        task_id: t.piece.task_id,
        attempt: t.piece.attempt,
        lease_deadline_unix_ms: t.deadline_unix_ms,
        geometry: send_geometry.then_some(pb::Geometry {
            size_mm: t.geometry.size_mm,
            grid: t.geometry.grid,
            positions: t.geometry.positions,
            directions: t.geometry.directions,
        }),
        geometry_is_job_geometry: t.job_geometry,
        table: t.table.iter().map(material_to_pb).collect(),
        assignments: t
            .items
            .iter()
            .map(|i| pb::Assignment {
                indices_le_u16: i
                    .assignment
                    .iter()
                    .flat_map(|v| v.to_le_bytes())
                    .collect::<Vec<u8>>()
                    .into(),
                seed: i.seed,
            })
            .collect(),
        photon_first: t.piece.first,
        photon_count: t.piece.count,
    }
}

/// Decodes result matrices; an error says what is malformed.
fn decode_counts(counts: &[pb::CountMatrix]) -> Result<Vec<CountMatrix>, String> {
    counts
        .iter()
        .enumerate()
        .map(|(i, c)| {
            let (s, b) = (c.sources as usize, c.bins as usize);
            let expected = s.checked_mul(b).and_then(|n| n.checked_mul(4));
            if expected != Some(c.counts_le_u32.len()) {
                return Err(format!(
                    "matrix {i}: {} bytes for {s}×{b} u32 counts",
                    c.counts_le_u32.len()
                ));
            }
            Ok(CountMatrix {
                sources: s,
                bins: b,
                counts: c
                    .counts_le_u32
                    .chunks_exact(4)
                    .map(|w| u32::from_le_bytes([w[0], w[1], w[2], w[3]]))
                    .collect(),
            })
        })
        .collect()
}

#[tonic::async_trait]
impl WorkerService for WorkerApi {
    async fn register(
        &self,
        request: Request<pb::RegisterRequest>,
    ) -> Result<Response<pb::RegisterResponse>, Status> {
        let r = request.into_inner();
        let theirs = r.protocol.unwrap_or_default();
        if theirs.major != pb::PROTOCOL.major {
            return Err(Status::failed_precondition(format!(
                "protocol version mismatch: the worker speaks {}.{}, this coordinator {}.{}; \
                 run the same scatterfarm release on both",
                theirs.major,
                theirs.minor,
                pb::PROTOCOL.major,
                pb::PROTOCOL.minor
            )));
        }
        let f = r.fingerprint.ok_or_else(|| {
            Status::invalid_argument("registration without an engine fingerprint")
        })?;
        let mut core = self.0.core();
        if core.draining {
            return Err(Status::unavailable("the coordinator is draining"));
        }
        let id = core.register(
            r.name,
            EngineFingerprint {
                engine: f.engine,
                adapter: f.adapter,
                driver: f.driver,
                version: f.version,
            },
            r.photons_per_second,
        );
        let heartbeat = core.settings.heartbeat.as_millis() as u32;
        Ok(Response::new(pb::RegisterResponse {
            worker_id: id,
            heartbeat_interval_ms: heartbeat,
        }))
    }

    async fn heartbeat(
        &self,
        request: Request<pb::HeartbeatRequest>,
    ) -> Result<Response<pb::HeartbeatResponse>, Status> {
        let known = self.0.core().heartbeat(&request.into_inner().worker_id);
        Ok(Response::new(pb::HeartbeatResponse { known }))
    }

    async fn lease(
        &self,
        request: Request<pb::LeaseRequest>,
    ) -> Result<Response<pb::LeaseResponse>, Status> {
        let r = request.into_inner();
        // Wait up to a second for work before answering "none", so idle workers do not poll
        // hard and new work starts at once.
        let until = Instant::now() + Duration::from_secs(1);
        loop {
            let notified = self.0.work.notified();
            let outcome = self.0.core().lease(&r.worker_id)?;
            match outcome {
                Ok(task) => {
                    return Ok(Response::new(pb::LeaseResponse {
                        task: Some(task_to_pb(task, &r.cached_jobs)),
                        retry_after_ms: 0,
                        reason: String::new(),
                    }))
                }
                Err(reason) => {
                    let left = until.saturating_duration_since(Instant::now());
                    if left.is_zero() || tokio::time::timeout(left, notified).await.is_err() {
                        return Ok(Response::new(pb::LeaseResponse {
                            task: None,
                            retry_after_ms: 500,
                            reason,
                        }));
                    }
                }
            }
        }
    }

    async fn complete(
        &self,
        request: Request<pb::CompleteRequest>,
    ) -> Result<Response<pb::CompleteResponse>, Status> {
        let r = request.into_inner();
        let counts = decode_counts(&r.counts);
        let farm = self.0.clone();
        // Scoring a completed group takes milliseconds: keep it off the async threads.
        tokio::task::spawn_blocking(move || {
            farm.core().complete(
                &r.worker_id,
                &r.job_id,
                r.task_id,
                r.attempt,
                counts,
                r.scatter_events,
            )
        })
        .await
        .map_err(|e| Status::internal(format!("the result handler failed: {e}")))??;
        self.0.work.notify_waiters();
        Ok(Response::new(pb::CompleteResponse {}))
    }

    async fn release(
        &self,
        request: Request<pb::ReleaseRequest>,
    ) -> Result<Response<pb::ReleaseResponse>, Status> {
        let r = request.into_inner();
        self.0
            .core()
            .release(&r.worker_id, &r.job_id, r.task_id, r.attempt, &r.reason)?;
        self.0.work.notify_waiters();
        Ok(Response::new(pb::ReleaseResponse {}))
    }
}

/// The `ClientService` implementation.
pub struct ClientApi(pub Arc<Farm>);

fn state_of(job: &Job) -> pb::JobState {
    match job.progress.phase {
        Phase::Preparing => pb::JobState::Preparing,
        Phase::Searching => pb::JobState::Searching,
        Phase::Finished => pb::JobState::Finished,
        Phase::Cancelled => pb::JobState::Cancelled,
        Phase::Failed { .. } => pb::JobState::Failed,
    }
}

/// A job's status as clients see it.
pub fn job_status(core: &Core, job: &Job) -> pb::JobStatus {
    let p = job.progress.search.progress();
    let (rate, eta) = job.pace();
    let message = match &job.progress.phase {
        Phase::Failed { message } => message.clone(),
        Phase::Preparing => core
            .waiting_reason(job)
            .unwrap_or_else(|| "rendering the target and calibrating ε".into()),
        Phase::Searching => core.waiting_reason(job).unwrap_or_default(),
        Phase::Finished => "finished".into(),
        Phase::Cancelled => "cancelled".into(),
    };
    pb::JobStatus {
        job_id: job.id.clone(),
        name: job.name(),
        state: state_of(job) as i32,
        message,
        engine: job.progress.pinned.clone().unwrap_or_default(),
        level: p.level,
        levels: p.levels,
        permutation: p.permutation,
        permutations: p.permutations,
        region: p.region,
        regions: p.regions,
        renders_done: p.renders_done,
        renders_total: p.renders_total,
        best_similarity: p.best_score.unwrap_or(f64::NAN),
        photons: job.progress.photons_simulated,
        photons_per_second: rate,
        eta_seconds: eta.unwrap_or(-1.0),
        workers_busy: core.workers_busy(&job.id),
        submitted_unix_seconds: job.record.submitted_unix,
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

fn is_terminal(s: &pb::JobStatus) -> bool {
    matches!(
        pb::JobState::try_from(s.state),
        Ok(pb::JobState::Finished | pb::JobState::Cancelled | pb::JobState::Failed)
    )
}

type StatusStream = Pin<Box<dyn Stream<Item = Result<pb::JobStatus, Status>> + Send>>;

#[tonic::async_trait]
impl ClientService for ClientApi {
    async fn submit(
        &self,
        request: Request<pb::SubmitRequest>,
    ) -> Result<Response<pb::SubmitResponse>, Status> {
        let r = request.into_inner();
        let params = JobSpec::from_toml(&r.job_toml, Path::new("the submitted job"))
            .map_err(|e| Status::invalid_argument(format!("{e:#}")))?;
        let inputs = Inputs {
            files: r.files.into_iter().map(|(k, v)| (k, v.to_vec())).collect(),
        };
        let farm = self.0.clone();
        let id = tokio::task::spawn_blocking(move || farm.core().submit(params, inputs))
            .await
            .map_err(|e| Status::internal(format!("the submission handler failed: {e}")))??;
        self.0.work.notify_waiters();
        Ok(Response::new(pb::SubmitResponse { job_id: id }))
    }

    async fn status(
        &self,
        request: Request<pb::JobRef>,
    ) -> Result<Response<pb::JobStatus>, Status> {
        let core = self.0.core();
        let job = core.job(&request.into_inner().job_id)?;
        Ok(Response::new(job_status(&core, job)))
    }

    type WatchStream = StatusStream;

    async fn watch(&self, request: Request<pb::JobRef>) -> Result<Response<StatusStream>, Status> {
        let id = request.into_inner().job_id;
        let farm = self.0.clone();
        // Fail now if the job does not exist.
        {
            let core = farm.core();
            core.job(&id)?;
        }
        let (tx, rx) = tokio::sync::mpsc::channel(4);
        tokio::spawn(async move {
            let mut last: Option<pb::JobStatus> = None;
            loop {
                let status = {
                    let core = farm.core();
                    match core.job(&id) {
                        Ok(job) => Ok(job_status(&core, job)),
                        Err(r) => Err(Status::from(r)),
                    }
                };
                let end = match &status {
                    Ok(s) => is_terminal(s),
                    Err(_) => true,
                };
                if last.as_ref() != status.as_ref().ok() {
                    last = status.as_ref().ok().cloned();
                    if tx.send(status).await.is_err() {
                        return;
                    }
                }
                if end {
                    return;
                }
                tokio::time::sleep(Duration::from_millis(250)).await;
            }
        });
        Ok(Response::new(Box::pin(
            tokio_stream::wrappers::ReceiverStream::new(rx),
        )))
    }

    async fn result(
        &self,
        request: Request<pb::JobRef>,
    ) -> Result<Response<pb::JobResult>, Status> {
        let id = request.into_inner().job_id;
        let farm = self.0.clone();
        let result = tokio::task::spawn_blocking(move || -> Result<pb::JobResult, Status> {
            let core = farm.core();
            let job = core.job(&id)?;
            let finished = job.progress.phase == Phase::Finished;
            let files = if finished {
                job.stored_outputs(core.store())
            } else {
                job.outputs()
            }
            .map_err(|e| Status::failed_precondition(format!("job {id}: {e:#}")))?;
            Ok(pb::JobResult {
                partial: !finished,
                status: Some(job_status(&core, job)),
                files: files.into_iter().map(|(k, v)| (k, v.into())).collect(),
            })
        })
        .await
        .map_err(|e| Status::internal(format!("the result handler failed: {e}")))??;
        Ok(Response::new(result))
    }

    async fn cancel(
        &self,
        request: Request<pb::JobRef>,
    ) -> Result<Response<pb::CancelResponse>, Status> {
        self.0.core().cancel(&request.into_inner().job_id)?;
        Ok(Response::new(pb::CancelResponse {}))
    }

    async fn delete(
        &self,
        request: Request<pb::JobRef>,
    ) -> Result<Response<pb::DeleteResponse>, Status> {
        self.0.core().delete(&request.into_inner().job_id)?;
        Ok(Response::new(pb::DeleteResponse {}))
    }

    async fn list_jobs(
        &self,
        _request: Request<pb::ListJobsRequest>,
    ) -> Result<Response<pb::ListJobsResponse>, Status> {
        let core = self.0.core();
        let jobs = core.jobs.values().map(|j| job_status(&core, j)).collect();
        Ok(Response::new(pb::ListJobsResponse { jobs }))
    }

    async fn list_workers(
        &self,
        _request: Request<pb::ListWorkersRequest>,
    ) -> Result<Response<pb::ListWorkersResponse>, Status> {
        let core = self.0.core();
        let now = Instant::now();
        let mut workers: Vec<pb::WorkerStatus> = core
            .workers
            .values()
            .map(|w| pb::WorkerStatus {
                worker_id: w.id.clone(),
                name: w.name.clone(),
                fingerprint: Some(pb::EngineFingerprint {
                    engine: w.fingerprint.engine.clone(),
                    adapter: w.fingerprint.adapter.clone(),
                    driver: w.fingerprint.driver.clone(),
                    version: w.fingerprint.version.clone(),
                }),
                photons_per_second: w.photons_per_second,
                tasks_leased: core.leases.values().filter(|l| l.worker == w.id).count() as u32,
                last_heartbeat_seconds_ago: now.duration_since(w.last_seen).as_secs_f64(),
                tasks_completed: w.tasks_completed,
            })
            .collect();
        workers.sort_by(|a, b| a.worker_id.cmp(&b.worker_id));
        Ok(Response::new(pb::ListWorkersResponse { workers }))
    }
}
