//! The `WorkerService`: workers register, send heartbeats, lease tasks, and return results or
//! give tasks back.

use super::Farm;
use crate::scheduler::{Abilities, Refusal, Rendered, TaskOut};
use scatterfarm_model::PhotonRange;
use scatterfarm_proto::convert::{
    check_lease_request, fingerprint_from_proto, results_from_proto, task_to_proto, RenderTask,
    TaskLease,
};
use scatterfarm_proto::differential::change_scores_from_proto;
use scatterfarm_proto::scored::render_scores_from_proto;
use scatterfarm_proto::v1 as pb;
use scatterfarm_proto::v1::worker_service_server::WorkerService;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tonic::{Request, Response, Status};

/// The `WorkerService` implementation.
pub struct WorkerApi(pub Arc<Farm>);

/// The wire task for `t`; the geometry is left out when it is the job's and the worker holds
/// it (`cached` lists the jobs whose geometry it holds), and a differential or scored task's
/// target when the worker holds that (`cached_targets`).
fn task_to_pb(t: TaskOut, cached: &[String], cached_targets: &[String]) -> pb::Task {
    let send_geometry = !(t.job_geometry && cached.contains(&t.job));
    let scoring = t.scoring.clone();
    let target = scoring
        .as_deref()
        .filter(|_| !cached_targets.contains(&t.job))
        .map(|s| &s.target);
    let lease = TaskLease {
        job_id: t.job,
        task_id: t.piece.task_id,
        attempt: t.piece.attempt,
        lease_deadline_unix_ms: t.deadline_unix_ms,
    };
    let task = RenderTask {
        geometry: t.geometry,
        table: t.table,
        items: t.items,
        photons: PhotonRange {
            first: t.piece.first,
            count: t.piece.count,
        },
        differential: t.differential,
        scored: t.scored,
    };
    task_to_proto(lease, &task, t.job_geometry, send_geometry, target)
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
        let (id, heartbeat) = self
            .0
            .locked(move |scheduler| {
                if scheduler.draining {
                    return Err(Status::unavailable("the coordinator is draining"));
                }
                let id = scheduler.register(
                    r.name,
                    fingerprint_from_proto(f),
                    r.photons_per_second,
                    Abilities {
                        renders_differentially: r.renders_differentially,
                        scores_renders: r.scores_renders,
                    },
                );
                Ok((id, scheduler.settings.heartbeat.as_millis() as u32))
            })
            .await??;
        Ok(Response::new(pb::RegisterResponse {
            worker_id: id,
            heartbeat_interval_ms: heartbeat,
        }))
    }

    async fn heartbeat(
        &self,
        request: Request<pb::HeartbeatRequest>,
    ) -> Result<Response<pb::HeartbeatResponse>, Status> {
        let worker = request.into_inner().worker_id;
        // Not the scheduler's lock: a heartbeat never waits behind results or checkpoints.
        let known = self.0.liveness.touch(&worker, Instant::now());
        Ok(Response::new(pb::HeartbeatResponse { known }))
    }

    async fn lease(
        &self,
        request: Request<pb::LeaseRequest>,
    ) -> Result<Response<pb::LeaseResponse>, Status> {
        let r = request.into_inner();
        check_lease_request(&r).map_err(|e| Status::invalid_argument(e.to_string()))?;
        // Wait up to a second for work before answering "none", so idle workers do not poll
        // hard and new work starts at once.
        let until = Instant::now() + Duration::from_secs(1);
        loop {
            let notified = self.0.work.notified();
            let worker = r.worker_id.clone();
            // A first lease pins its job, and a lease can fail a job: both write checkpoints.
            let outcome = self.0.locked_durable(move |s| s.lease(&worker)).await??;
            match outcome {
                Ok(task) => {
                    return Ok(Response::new(pb::LeaseResponse {
                        task: Some(task_to_pb(task, &r.cached_jobs, &r.cached_targets)),
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
        // A result is contact too: its worker is alive, however long the upload took.
        self.0.liveness.touch(&r.worker_id, Instant::now());
        let counts = results_from_proto(&r.counts).map_err(|e| e.to_string());
        let change_scores = change_scores_from_proto(&r.change_scores).map_err(|e| e.to_string());
        let render_scores = render_scores_from_proto(&r.render_scores).map_err(|e| e.to_string());
        let farm = self.0.clone();
        // Off the async threads: the lock to sum the result, then, without it, the scoring of
        // a group it completed, then the lock again to keep the scores. Heartbeats and leases
        // never wait behind scoring.
        tokio::task::spawn_blocking(move || {
            let work = farm.scheduler().complete(
                &r.worker_id,
                &r.job_id,
                r.task_id,
                r.attempt,
                Rendered {
                    counts,
                    scatter_events: r.scatter_events,
                    render_seconds: r.render_seconds,
                    change_scores,
                    render_scores,
                },
            )?;
            if let Some(work) = work {
                let scored = work.run();
                farm.scheduler().scored(scored);
            }
            farm.sync();
            Ok::<(), Refusal>(())
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
            .locked_durable(move |s| {
                s.release(&r.worker_id, &r.job_id, r.task_id, r.attempt, &r.reason)
            })
            .await??;
        self.0.work.notify_waiters();
        Ok(Response::new(pb::ReleaseResponse {}))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scheduler::{Scheduler, Settings};
    use crate::store::MemoryStore;
    use scatterfarm_model::EngineFingerprint;

    fn fingerprint() -> pb::EngineFingerprint {
        scatterfarm_proto::convert::fingerprint_to_proto(&EngineFingerprint {
            engine: "cpu".into(),
            adapter: "test".into(),
            driver: "x86_64".into(),
            version: "1".into(),
        })
    }

    /// The scheduler's lock held (as by a long checkpoint or scoring) must not hold up a
    /// heartbeat: the sweep would forget a worker that is alive.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_heartbeat_is_answered_while_the_scheduler_is_locked() {
        let store: Arc<dyn crate::store::Store> = Arc::new(MemoryStore::new());
        let farm = Farm::new(Scheduler::open(store, Settings::default()).unwrap());
        let api = WorkerApi(farm.clone());
        let id = api
            .register(Request::new(pb::RegisterRequest {
                protocol: Some(pb::PROTOCOL),
                fingerprint: Some(fingerprint()),
                photons_per_second: 1e6,
                name: "w".into(),
                renders_differentially: false,
                scores_renders: true,
            }))
            .await
            .unwrap()
            .into_inner()
            .worker_id;
        let before = farm.liveness.last_seen(&id).unwrap();
        // Another thread holds the scheduler's lock until told to let go.
        let (locked, is_locked) = std::sync::mpsc::channel();
        let (release, released) = std::sync::mpsc::channel::<()>();
        let holder = {
            let farm = farm.clone();
            std::thread::spawn(move || {
                let _guard = farm.scheduler();
                locked.send(()).unwrap();
                let _ = released.recv();
            })
        };
        is_locked.recv().unwrap();
        let heartbeat = api.heartbeat(Request::new(pb::HeartbeatRequest {
            worker_id: id.clone(),
        }));
        // Without the lock-free path this waits for the lock, released only after: the
        // timeout turns that deadlock into a failure.
        let answer = tokio::time::timeout(Duration::from_secs(30), heartbeat)
            .await
            .expect("the heartbeat waited on the scheduler's lock")
            .unwrap()
            .into_inner();
        release.send(()).unwrap();
        holder.join().unwrap();
        assert!(answer.known);
        assert!(farm.liveness.last_seen(&id).unwrap() >= before);
        let unknown = api
            .heartbeat(Request::new(pb::HeartbeatRequest {
                worker_id: "w-nobody".into(),
            }))
            .await
            .unwrap()
            .into_inner();
        assert!(
            !unknown.known,
            "an unknown worker is told to register again"
        );
    }
}
