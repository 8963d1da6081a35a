//! The `ClientService`: submitting jobs, following them, fetching results, cancelling and
//! deleting them, and listing jobs and workers.

use super::Farm;
use crate::job::outputs::stored_outputs;
use crate::job::JobState;
use crate::scheduler::stored_job;
use crate::status::{all_statuses, is_terminal, job_status, status_of};
use scatterfarm_job::inputs::Inputs;
use scatterfarm_job::spec::JobSpec;
use scatterfarm_proto::convert::fingerprint_to_proto;
use scatterfarm_proto::v1 as pb;
use scatterfarm_proto::v1::client_service_server::ClientService;
use std::path::Path;
use std::pin::Pin;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio_stream::Stream;
use tonic::{Request, Response, Status};

/// The `ClientService` implementation.
pub struct ClientApi(pub Arc<Farm>);

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
        // Parsing and storing happen outside the scheduler's lock; only the insert takes it.
        let id = tokio::task::spawn_blocking(move || {
            stored_job(farm.store.as_ref(), params, inputs).map(|job| farm.scheduler().add_job(job))
        })
        .await
        .map_err(|e| Status::internal(format!("the submission handler failed: {e}")))??;
        self.0.work.notify_waiters();
        Ok(Response::new(pb::SubmitResponse { job_id: id }))
    }

    async fn status(
        &self,
        request: Request<pb::JobRef>,
    ) -> Result<Response<pb::JobStatus>, Status> {
        let id = request.into_inner().job_id;
        let status = self.0.locked(move |s| status_of(s, &id)).await??;
        Ok(Response::new(status))
    }

    type WatchStream = StatusStream;

    async fn watch(&self, request: Request<pb::JobRef>) -> Result<Response<StatusStream>, Status> {
        let id = request.into_inner().job_id;
        let farm = self.0.clone();
        // Fail now if the job does not exist.
        {
            let scheduler = farm.scheduler();
            status_of(&scheduler, &id)?;
        }
        let (tx, rx) = tokio::sync::mpsc::channel(4);
        tokio::spawn(async move {
            let mut last: Option<pb::JobStatus> = None;
            loop {
                let id = id.clone();
                let status = match farm.locked(move |s| status_of(s, &id)).await {
                    Ok(s) => s.map_err(Status::from),
                    Err(e) => Err(e),
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
            // The files are read from the store, or drawn, without the lock: under it only
            // what they are made from is copied.
            let (finished, status) = {
                let scheduler = farm.scheduler();
                let job = scheduler.job(&id)?;
                let finished = job.checkpoint.state == JobState::Finished;
                (finished, job_status(&scheduler, job))
            };
            let failed = |e: anyhow::Error| Status::failed_precondition(format!("job {id}: {e:#}"));
            let stored = if finished {
                stored_outputs(farm.store.as_ref(), &id).map_err(failed)?
            } else {
                None
            };
            let files = match stored {
                Some(files) => files,
                None => {
                    let source = farm.scheduler().job(&id)?.output_source();
                    source.and_then(|s| s.render()).map_err(failed)?
                }
            };
            Ok(pb::JobResult {
                partial: !finished,
                status: Some(status),
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
        let id = request.into_inner().job_id;
        self.0.locked_durable(move |s| s.cancel(&id)).await??;
        Ok(Response::new(pb::CancelResponse {}))
    }

    async fn delete(
        &self,
        request: Request<pb::JobRef>,
    ) -> Result<Response<pb::DeleteResponse>, Status> {
        let id = request.into_inner().job_id;
        self.0.locked_durable(move |s| s.delete(&id)).await??;
        Ok(Response::new(pb::DeleteResponse {}))
    }

    async fn list_jobs(
        &self,
        _request: Request<pb::ListJobsRequest>,
    ) -> Result<Response<pb::ListJobsResponse>, Status> {
        let jobs = self.0.locked(|s| all_statuses(s)).await?;
        Ok(Response::new(pb::ListJobsResponse { jobs }))
    }

    async fn list_workers(
        &self,
        _request: Request<pb::ListWorkersRequest>,
    ) -> Result<Response<pb::ListWorkersResponse>, Status> {
        let scheduler = self.0.scheduler();
        let now = Instant::now();
        let mut workers: Vec<pb::WorkerStatus> = scheduler
            .workers
            .values()
            .map(|w| pb::WorkerStatus {
                worker_id: w.id.clone(),
                name: w.name.clone(),
                fingerprint: Some(fingerprint_to_proto(&w.fingerprint)),
                photons_per_second: w.photons_per_second,
                tasks_leased: scheduler
                    .leases
                    .values()
                    .filter(|l| l.worker == w.id)
                    .count() as u32,
                last_heartbeat_seconds_ago: scheduler
                    .liveness
                    .last_seen(&w.id)
                    .map_or(f64::INFINITY, |t| {
                        now.saturating_duration_since(t).as_secs_f64()
                    }),
                tasks_completed: w.tasks_completed,
            })
            .collect();
        workers.sort_by(|a, b| a.worker_id.cmp(&b.worker_id));
        Ok(Response::new(pb::ListWorkersResponse { workers }))
    }
}
