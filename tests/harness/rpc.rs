//! The protocol spoken from the test: gRPC clients of a plaintext, token-less coordinator, and
//! what fake workers answer (well-formed dark counts, matrices of any shape).

use scatterfarm_proto::channel::{Authed, Endpoint};
use scatterfarm_proto::v1 as pb;
use scatterfarm_proto::v1::client_service_client::ClientServiceClient;
use scatterfarm_proto::v1::worker_service_client::WorkerServiceClient;
use std::future::Future;
use std::time::{Duration, Instant};
use tonic::Code;

/// gRPC clients of a plaintext, token-less coordinator, on a runtime of their own.
pub struct Rpc {
    worker: WorkerServiceClient<Authed>,
    client: ClientServiceClient<Authed>,
    rt: tokio::runtime::Runtime,
}

/// The CPU engine's fingerprint: jobs are pinned to the first worker's, so a fake worker
/// announces the same one as the real workers it shares jobs with.
pub fn cpu_fingerprint() -> pb::EngineFingerprint {
    use scatterfarm_model::Engine;
    let f = scatterfarm_engines::CpuEngine::new().fingerprint();
    pb::EngineFingerprint {
        engine: f.engine,
        adapter: f.adapter,
        driver: f.driver,
        version: f.version,
    }
}

impl Rpc {
    pub fn connect(url: &str) -> Rpc {
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .enable_all()
            .build()
            .unwrap();
        let endpoint = Endpoint {
            url: url.to_string(),
            ca_pem: None,
            token: None,
        };
        let channel = rt
            .block_on(endpoint.connect())
            .unwrap_or_else(|e| panic!("cannot connect to {url}: {e}"));
        Rpc {
            worker: Endpoint::worker_client(channel.clone()),
            client: Endpoint::client_client(channel),
            rt,
        }
    }

    pub fn worker_call<T, F>(
        &self,
        call: impl FnOnce(WorkerServiceClient<Authed>) -> F,
    ) -> Result<T, tonic::Status>
    where
        F: Future<Output = Result<tonic::Response<T>, tonic::Status>>,
    {
        self.rt
            .block_on(call(self.worker.clone()))
            .map(tonic::Response::into_inner)
    }

    pub fn client_call<T, F>(&self, call: impl FnOnce(ClientServiceClient<Authed>) -> F) -> T
    where
        F: Future<Output = Result<tonic::Response<T>, tonic::Status>>,
    {
        self.rt
            .block_on(call(self.client.clone()))
            .map(tonic::Response::into_inner)
            .unwrap_or_else(|s| panic!("client call failed: {s:?}"))
    }

    /// Registers a fake CPU worker speaking `protocol`.
    pub fn register(
        &self,
        protocol: pb::ProtocolVersion,
        name: &str,
    ) -> Result<pb::RegisterResponse, tonic::Status> {
        let request = pb::RegisterRequest {
            protocol: Some(protocol),
            fingerprint: Some(cpu_fingerprint()),
            photons_per_second: 1e6,
            name: name.to_string(),
            renders_differentially: true,
            // Its tasks come back as counts (`render_task`); the real agent scores renders.
            scores_renders: false,
        };
        self.worker_call(|mut w| async move { w.register(request).await })
    }

    /// Registers a fake worker of this protocol version; its id.
    pub fn register_fake(&self, name: &str) -> String {
        self.register_fake_at(name, 1e6)
    }

    /// Registers a fake worker announcing `photons_per_second` (a slow one gets small tasks);
    /// its id.
    pub fn register_fake_at(&self, name: &str, photons_per_second: f64) -> String {
        let request = pb::RegisterRequest {
            protocol: Some(pb::PROTOCOL),
            fingerprint: Some(cpu_fingerprint()),
            photons_per_second,
            name: name.to_string(),
            renders_differentially: true,
            // Its tasks come back as counts (`render_task`); the real agent scores renders.
            scores_renders: false,
        };
        self.worker_call(|mut w| async move { w.register(request).await })
            .unwrap_or_else(|s| panic!("registration refused: {s:?}"))
            .worker_id
    }

    pub fn heartbeat(&self, worker: &str) -> bool {
        let request = pb::HeartbeatRequest {
            worker_id: worker.to_string(),
        };
        self.worker_call(|mut w| async move { w.heartbeat(request).await })
            .expect("heartbeat")
            .known
    }

    /// One lease request (the coordinator waits up to a second for work).
    pub fn try_lease(&self, worker: &str) -> pb::LeaseResponse {
        let request = pb::LeaseRequest {
            worker_id: worker.to_string(),
            cached_jobs: Vec::new(),
            cached_targets: Vec::new(),
        };
        self.worker_call(|mut w| async move { w.lease(request).await })
            .unwrap_or_else(|s| panic!("lease refused: {s:?}"))
    }

    /// Leases until a task comes.
    pub fn lease(&self, worker: &str) -> pb::Task {
        let deadline = Instant::now() + Duration::from_secs(60);
        loop {
            let response = self.try_lease(worker);
            if let Some(task) = response.task {
                return task;
            }
            assert!(
                Instant::now() < deadline,
                "no task within 60 s: {}",
                response.reason
            );
        }
    }

    pub fn complete(
        &self,
        worker: &str,
        task: &pb::Task,
        counts: Vec<pb::CountMatrix>,
    ) -> Result<pb::CompleteResponse, tonic::Status> {
        let request = pb::CompleteRequest {
            worker_id: worker.to_string(),
            job_id: task.job_id.clone(),
            task_id: task.task_id,
            attempt: task.attempt,
            counts,
            scatter_events: 0,
            render_seconds: 0.01,
            change_scores: Vec::new(),
            render_scores: Vec::new(),
        };
        self.worker_call(|mut w| async move { w.complete(request).await })
    }

    /// Gives `task` back, as a worker that leaves or whose engine failed does.
    pub fn release(&self, worker: &str, task: &pb::Task, reason: &str) {
        self.try_release(worker, task, reason)
            .unwrap_or_else(|s| panic!("release refused: {s:?}"));
    }

    /// Gives `task` back; the coordinator's answer.
    pub fn try_release(
        &self,
        worker: &str,
        task: &pb::Task,
        reason: &str,
    ) -> Result<pb::ReleaseResponse, tonic::Status> {
        let request = pb::ReleaseRequest {
            worker_id: worker.to_string(),
            job_id: task.job_id.clone(),
            task_id: task.task_id,
            attempt: task.attempt,
            reason: reason.to_string(),
        };
        self.worker_call(|mut w| async move { w.release(request).await })
    }

    pub fn workers(&self) -> Vec<pb::WorkerStatus> {
        self.client_call(|mut c| async move { c.list_workers(pb::ListWorkersRequest {}).await })
            .workers
    }

    pub fn status(&self, id: &str) -> pb::JobStatus {
        let request = pb::JobRef {
            job_id: id.to_string(),
        };
        self.client_call(|mut c| async move { c.status(request).await })
    }

    pub fn jobs(&self) -> Vec<pb::JobStatus> {
        self.client_call(|mut c| async move { c.list_jobs(pb::ListJobsRequest {}).await })
            .jobs
    }

    pub fn submit(
        &self,
        job_toml: &str,
        files: &[(&str, &str)],
    ) -> Result<pb::SubmitResponse, tonic::Status> {
        let request = pb::SubmitRequest {
            job_toml: job_toml.to_string(),
            files: files
                .iter()
                .map(|(k, v)| (k.to_string(), v.as_bytes().to_vec().into()))
                .collect(),
        };
        self.rt
            .block_on(self.client.clone().submit(request))
            .map(tonic::Response::into_inner)
    }
}

/// Sources (= bins) of a task's geometry.
pub fn task_sources(task: &pb::Task) -> u32 {
    let g = task
        .geometry
        .as_ref()
        .expect("the task has its geometry (no cached jobs were named)");
    g.positions * g.directions
}

pub fn matrix(sources: u32, bins: u32, counts: &[u32]) -> pb::CountMatrix {
    pb::CountMatrix {
        sources,
        bins,
        counts_le_u32: counts
            .iter()
            .flat_map(|c| c.to_le_bytes())
            .collect::<Vec<u8>>()
            .into(),
    }
}

/// A well-formed answer to `task` in which no photon left the medium.
pub fn dark_counts(task: &pb::Task) -> Vec<pb::CountMatrix> {
    let n = task_sources(task);
    let zeros = vec![0; (n * n) as usize];
    task.assignments
        .iter()
        .map(|_| matrix(n, n, &zeros))
        .collect()
}

pub fn assert_code(result: Result<impl std::fmt::Debug, tonic::Status>, code: Code) -> String {
    match result {
        Ok(v) => panic!("accepted where {code:?} was expected: {v:?}"),
        Err(s) => {
            assert_eq!(s.code(), code, "{s:?}");
            s.message().to_string()
        }
    }
}
