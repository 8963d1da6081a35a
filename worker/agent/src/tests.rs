//! The agent against an in-process fake coordinator: registration, leasing with the geometry
//! cache, results, failures, forgetting coordinators, refusals and shutdown.

use super::*;
use scatterfarm_engines::cpu::CpuEngine;
use scatterfarm_model::engine::{
    EngineFingerprint, PhotonRange, RenderBatch, RenderItem, RenderOutput,
};
use scatterfarm_model::geometry::Geometry;
use scatterfarm_model::likelihood::Target;
use scatterfarm_model::material::Material;
use scatterfarm_proto::auth::RequireToken;
use scatterfarm_proto::convert::{
    assignment_to_proto, counts_from_proto, geometry_to_proto, material_to_proto,
};
use scatterfarm_proto::v1::worker_service_server::{WorkerService, WorkerServiceServer};
use scatterfarm_proto::v1::*;
use std::collections::{HashSet, VecDeque};
use std::sync::Mutex;
use std::time::{Duration, Instant};
use tonic::codec::CompressionEncoding;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::server::TcpIncoming;
use tonic::transport::Server;
use tonic::{Request, Response, Status};

/// What the fake coordinator saw and what it is told to do.
#[derive(Default)]
struct State {
    tasks: VecDeque<Task>,
    register_error: Option<Status>,
    /// Errors returned by the next Complete calls, in order.
    complete_errors: VecDeque<Status>,
    /// Forget every worker when this many Completes have been accepted.
    forget_after_completes: Option<usize>,
    /// Answer `known = false` to this many heartbeats (without forgetting).
    unknown_heartbeats: usize,
    heartbeat_interval_ms: u32,
    known: HashSet<String>,
    registrations: Vec<RegisterRequest>,
    heartbeats: usize,
    leases: Vec<LeaseRequest>,
    leased: Vec<u64>,
    complete_calls: Vec<CompleteRequest>,
    completed: Vec<CompleteRequest>,
    releases: Vec<ReleaseRequest>,
}

#[derive(Default)]
struct Fake(Mutex<State>);

impl Fake {
    fn with(f: impl FnOnce(&mut State)) -> Arc<Fake> {
        let fake = Fake::default();
        f(&mut fake.state());
        Arc::new(fake)
    }

    fn state(&self) -> std::sync::MutexGuard<'_, State> {
        self.0.lock().unwrap_or_else(|p| p.into_inner())
    }
}

#[tonic::async_trait]
impl WorkerService for Fake {
    async fn register(
        &self,
        request: Request<RegisterRequest>,
    ) -> Result<Response<RegisterResponse>, Status> {
        let mut s = self.state();
        if let Some(e) = s.register_error.clone() {
            return Err(e);
        }
        s.registrations.push(request.into_inner());
        let worker_id = format!("w{}", s.registrations.len());
        s.known.insert(worker_id.clone());
        Ok(Response::new(RegisterResponse {
            worker_id,
            heartbeat_interval_ms: s.heartbeat_interval_ms,
        }))
    }

    async fn heartbeat(
        &self,
        request: Request<HeartbeatRequest>,
    ) -> Result<Response<HeartbeatResponse>, Status> {
        let mut s = self.state();
        s.heartbeats += 1;
        let mut known = s.known.contains(&request.get_ref().worker_id);
        if s.unknown_heartbeats > 0 {
            s.unknown_heartbeats -= 1;
            known = false;
        }
        Ok(Response::new(HeartbeatResponse { known }))
    }

    async fn lease(
        &self,
        request: Request<LeaseRequest>,
    ) -> Result<Response<LeaseResponse>, Status> {
        let mut s = self.state();
        let request = request.into_inner();
        if !s.known.contains(&request.worker_id) {
            return Err(Status::not_found(format!(
                "no worker {}",
                request.worker_id
            )));
        }
        s.leases.push(request);
        let task = s.tasks.pop_front();
        if let Some(t) = &task {
            s.leased.push(t.task_id);
        }
        Ok(Response::new(LeaseResponse {
            task,
            retry_after_ms: 20,
            reason: "nothing to do".into(),
        }))
    }

    async fn complete(
        &self,
        request: Request<CompleteRequest>,
    ) -> Result<Response<CompleteResponse>, Status> {
        let mut s = self.state();
        let request = request.into_inner();
        s.complete_calls.push(request.clone());
        if let Some(e) = s.complete_errors.pop_front() {
            return Err(e);
        }
        if !s.known.contains(&request.worker_id) {
            return Err(Status::not_found(format!(
                "no worker {}",
                request.worker_id
            )));
        }
        s.completed.push(request);
        if s.forget_after_completes == Some(s.completed.len()) {
            s.known.clear();
        }
        Ok(Response::new(CompleteResponse {}))
    }

    async fn release(
        &self,
        request: Request<ReleaseRequest>,
    ) -> Result<Response<ReleaseResponse>, Status> {
        self.state().releases.push(request.into_inner());
        Ok(Response::new(ReleaseResponse {}))
    }
}

fn service(fake: Arc<Fake>) -> WorkerServiceServer<Fake> {
    WorkerServiceServer::from_arc(fake)
        .accept_compressed(CompressionEncoding::Zstd)
        .send_compressed(CompressionEncoding::Zstd)
        .max_decoding_message_size(v1::MAX_MESSAGE_BYTES)
}

/// Serves `fake` on `addr` (port 0: any); returns its URL.
async fn serve_on(fake: Arc<Fake>, addr: &str, token: Option<&str>) -> String {
    let incoming = TcpIncoming::bind(addr.parse().expect("address")).expect("bind");
    let url = format!("http://{}", incoming.local_addr().expect("local address"));
    let router = match token {
        None => Server::builder().add_service(service(fake)),
        Some(t) => Server::builder().add_service(InterceptedService::new(
            service(fake),
            RequireToken::new(Some(t)),
        )),
    };
    tokio::spawn(router.serve_with_incoming(incoming));
    url
}

async fn serve(fake: Arc<Fake>) -> String {
    serve_on(fake, "127.0.0.1:0", None).await
}

fn config(url: &str, max_tasks: Option<u64>) -> AgentConfig {
    AgentConfig {
        endpoint: Endpoint {
            url: url.into(),
            ca_pem: None,
            token: None,
        },
        name: Some("test-worker".into()),
        photons_per_second: Some(1e6),
        max_tasks,
    }
}

fn geometry() -> Geometry {
    Geometry::new(4.0, 4, 4, 2).unwrap()
}

const MODERATE: Material = Material {
    sigma_s: 0.6,
    sigma_a: 0.01,
    g: 0.75,
};

fn items() -> Vec<RenderItem> {
    let mut opaque_middle = vec![0u16; 16];
    opaque_middle[5] = 1;
    vec![
        RenderItem {
            assignment: vec![0; 16],
            seed: 11,
        },
        RenderItem {
            assignment: opaque_middle,
            seed: 12,
        },
    ]
}

/// A task of `job`, carrying the job's geometry when `with_geometry`.
fn task(job: &str, task_id: u64, with_geometry: bool) -> Task {
    Task {
        job_id: job.into(),
        task_id,
        attempt: 1,
        lease_deadline_unix_ms: 0,
        geometry: with_geometry.then(|| geometry_to_proto(&geometry())),
        geometry_is_job_geometry: with_geometry,
        table: vec![
            material_to_proto(&MODERATE),
            material_to_proto(&Material::OPAQUE),
        ],
        assignments: items().iter().map(assignment_to_proto).collect(),
        photon_first: 100,
        photon_count: 50,
        differential: None,
        scored: None,
    }
}

/// Waits (up to 20 s) until `done` holds of the fake's state.
async fn until(fake: &Fake, what: &str, done: impl Fn(&State) -> bool) {
    let start = Instant::now();
    while !done(&fake.state()) {
        assert!(
            start.elapsed() < Duration::from_secs(20),
            "timed out waiting for {what}"
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

/// Runs the agent in the background; `stop` asks it to shut down.
struct Running {
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    handle: tokio::task::JoinHandle<Result<AgentSummary, AgentError>>,
}

impl Running {
    fn start(config: AgentConfig, engine: Arc<dyn Engine>) -> Running {
        let (tx, rx) = tokio::sync::oneshot::channel::<()>();
        let handle = tokio::spawn(run(config, engine, async {
            let _ = rx.await;
        }));
        Running {
            stop: Some(tx),
            handle,
        }
    }

    async fn finish(mut self, stop: bool) -> Result<AgentSummary, AgentError> {
        if stop {
            if let Some(tx) = self.stop.take() {
                let _ = tx.send(());
            }
        }
        tokio::time::timeout(Duration::from_secs(30), self.handle)
            .await
            .expect("the agent did not return")
            .expect("the agent panicked")
    }
}

fn cpu() -> Arc<dyn Engine> {
    Arc::new(CpuEngine::new())
}

/// Counts that the engine renders for [`items`] over photons 100..150.
fn expected_counts() -> Vec<scatterfarm_model::engine::CountMatrix> {
    let table = [MODERATE, Material::OPAQUE];
    let items = items();
    CpuEngine::new()
        .render(&RenderBatch {
            geometry: geometry(),
            table: &table,
            items: &items,
            photons: PhotonRange {
                first: 100,
                count: 50,
            },
        })
        .unwrap()
        .into_iter()
        .map(|o| o.counts)
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn renders_tasks_with_cached_geometry_and_returns_the_counts() {
    let fake = Fake::with(|s| {
        s.tasks = [task("a", 0, false), task("a", 1, true), task("a", 2, false)].into();
    });
    let url = serve(fake.clone()).await;
    let summary = Running::start(config(&url, Some(2)), cpu())
        .finish(false)
        .await
        .unwrap();
    assert_eq!(summary.tasks_completed, 2);
    assert_eq!(summary.photons, 2 * 8 * 50 * 2);
    let s = fake.state();
    let r = &s.registrations[0];
    assert_eq!(r.protocol, Some(v1::PROTOCOL));
    assert_eq!(r.name, "test-worker");
    assert_eq!(r.photons_per_second, 1e6);
    assert_eq!(r.fingerprint.as_ref().unwrap().engine, "cpu");
    // The task without a geometry of an uncached job is given back, and says why.
    assert_eq!(s.releases.len(), 1);
    assert_eq!(s.releases[0].task_id, 0);
    assert!(
        s.releases[0].reason.contains("geometry"),
        "{}",
        s.releases[0].reason
    );
    // After the job's geometry came, leases name the job.
    assert!(s.leases[0].cached_jobs.is_empty());
    assert_eq!(s.leases.last().unwrap().cached_jobs, ["a"]);
    let expected = expected_counts();
    for (c, id) in s.completed.iter().zip([1, 2]) {
        assert_eq!(c.task_id, id);
        assert_eq!(
            (c.worker_id.as_str(), c.job_id.as_str(), c.attempt),
            ("w1", "a", 1)
        );
        assert!(c.scatter_events > 0 && c.render_seconds > 0.0);
        let counts: Vec<_> = c
            .counts
            .iter()
            .map(|m| counts_from_proto(m).unwrap())
            .collect();
        assert_eq!(counts, expected);
    }
}

/// A differential task of `job` (the item with an opaque pixel 5, photons `[0, 64)` in chunks
/// of 16) with two changes: pixel 0 made opaque, and pixel 5 cleared (not reweightable).
fn differential_task(job: &str, task_id: u64, target: Option<&Target>) -> Task {
    let mut t = task(job, task_id, true);
    t.assignments.remove(0);
    t.photon_first = 0;
    t.photon_count = 64;
    let part = scatterfarm_proto::differential::DifferentialPart {
        changes: vec![
            scatterfarm_model::Change {
                pixels: vec![(0, 1)],
            },
            scatterfarm_model::Change {
                pixels: vec![(5, 0)],
            },
        ],
        chunk: 16,
    };
    t.differential = Some(scatterfarm_proto::differential::differential_to_proto(
        &part, target,
    ));
    t
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn differential_tasks_are_scored_against_the_target_it_was_sent_once() {
    let g = geometry();
    let target = Target {
        values: vec![0.01; g.sources() * g.bins()],
        photons_per_source: 1000,
    };
    let fake = Fake::with(|s| {
        s.tasks = [
            differential_task("e", 3, None),
            differential_task("d", 1, Some(&target)),
            differential_task("d", 2, None),
        ]
        .into();
    });
    let url = serve(fake.clone()).await;
    let summary = Running::start(config(&url, Some(2)), cpu())
        .finish(false)
        .await
        .unwrap();
    assert_eq!(summary.tasks_completed, 2);
    let s = fake.state();
    assert!(s.registrations[0].renders_differentially);
    assert!(s.leases[1].cached_targets.is_empty());
    assert_eq!(s.leases[2].cached_targets, ["d"]);
    // A task of a job whose target it never got is given back, saying so.
    assert_eq!(s.releases.len(), 1);
    assert_eq!(s.releases[0].task_id, 3);
    assert!(
        s.releases[0].reason.contains("target"),
        "{}",
        s.releases[0].reason
    );
    // The same render twice: the same counts and change scores, the second from the cache.
    assert_eq!(s.completed.len(), 2);
    assert_eq!(s.completed[0].counts, s.completed[1].counts);
    assert_eq!(s.completed[0].change_scores, s.completed[1].change_scores);
    let scores =
        scatterfarm_proto::differential::change_scores_from_proto(&s.completed[0].change_scores)
            .unwrap();
    assert_eq!(scores.len(), 2);
    assert!(
        scores[1].is_none(),
        "clearing an opaque pixel was estimated"
    );
    let opaque = scores[0]
        .as_ref()
        .expect("an opaque candidate is estimated");
    assert!(opaque.value.is_finite() && opaque.value < 0.0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_coordinator_that_forgets_the_worker_gets_a_new_registration() {
    let fake = Fake::with(|s| {
        s.tasks = [task("a", 1, true), task("a", 2, true)].into();
        s.forget_after_completes = Some(1);
    });
    let url = serve(fake.clone()).await;
    let summary = Running::start(config(&url, Some(2)), cpu())
        .finish(false)
        .await
        .unwrap();
    assert_eq!(summary.tasks_completed, 2);
    let s = fake.state();
    assert_eq!(s.registrations.len(), 2);
    assert_eq!(s.completed[1].worker_id, "w2");
    assert_eq!(s.registrations[1].photons_per_second, 1e6);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_heartbeat_answered_unknown_registers_again() {
    let fake = Fake::with(|s| {
        s.heartbeat_interval_ms = 50;
        s.unknown_heartbeats = 1;
    });
    let url = serve(fake.clone()).await;
    let running = Running::start(config(&url, None), cpu());
    until(&fake, "a second registration", |s| {
        s.registrations.len() >= 2
    })
    .await;
    until(&fake, "a lease as w2", |s| {
        s.leases.last().is_some_and(|l| l.worker_id == "w2")
    })
    .await;
    // The new session beats too.
    until(&fake, "a second heartbeat", |s| s.heartbeats >= 2).await;
    let summary = running.finish(true).await.unwrap();
    assert_eq!(summary, AgentSummary::default());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn results_are_retried_through_transient_failures_and_dropped_when_refused() {
    let fake = Fake::with(|s| {
        s.tasks = [task("a", 1, true), task("a", 2, true)].into();
        s.complete_errors = [
            Status::unavailable("restarting"),
            Status::failed_precondition("attempt 1 is stale"),
        ]
        .into();
    });
    let url = serve(fake.clone()).await;
    let summary = Running::start(config(&url, Some(1)), cpu())
        .finish(false)
        .await
        .unwrap();
    assert_eq!(summary.tasks_completed, 1);
    let s = fake.state();
    let calls: Vec<u64> = s.complete_calls.iter().map(|c| c.task_id).collect();
    assert_eq!(calls, [1, 1, 2]);
    assert_eq!(s.completed.len(), 1);
    assert_eq!(s.completed[0].task_id, 2);
}

/// An engine that always fails.
struct Broken;

impl Engine for Broken {
    fn fingerprint(&self) -> EngineFingerprint {
        EngineFingerprint {
            engine: "broken".into(),
            adapter: "none".into(),
            driver: "none".into(),
            version: "0".into(),
        }
    }

    fn render(&self, _: &RenderBatch<'_>) -> Result<Vec<RenderOutput>, EngineError> {
        Err(EngineError::Device("the device is lost".into()))
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn engine_failures_give_the_task_back_and_the_agent_goes_on() {
    let fake = Fake::with(|s| s.tasks = [task("a", 1, true), task("a", 2, true)].into());
    let url = serve(fake.clone()).await;
    let running = Running::start(config(&url, None), Arc::new(Broken));
    until(&fake, "two releases", |s| s.releases.len() >= 2).await;
    let summary = running.finish(true).await.unwrap();
    assert_eq!(summary.tasks_completed, 0);
    let s = fake.state();
    assert!(
        s.releases[0].reason.contains("the device is lost"),
        "{}",
        s.releases[0].reason
    );
    assert_eq!((s.releases[1].task_id, s.releases[1].attempt), (2, 1));
    assert!(s.completed.is_empty());
}

/// The CPU engine, slowly.
struct Slow(Duration);

impl Engine for Slow {
    fn fingerprint(&self) -> EngineFingerprint {
        CpuEngine::new().fingerprint()
    }

    fn render(&self, batch: &RenderBatch<'_>) -> Result<Vec<RenderOutput>, EngineError> {
        std::thread::sleep(self.0);
        CpuEngine::new().render(batch)
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_finishes_and_returns_the_task_in_hand() {
    let fake = Fake::with(|s| s.tasks = [task("a", 1, true), task("a", 2, true)].into());
    let url = serve(fake.clone()).await;
    let running = Running::start(
        config(&url, None),
        Arc::new(Slow(Duration::from_millis(700))),
    );
    until(&fake, "a lease", |s| !s.leased.is_empty()).await;
    let summary = running.finish(true).await.unwrap();
    assert_eq!(summary.tasks_completed, 1);
    let s = fake.state();
    assert_eq!(s.leased, [1], "no lease after shutdown");
    assert_eq!(s.completed.len(), 1);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn connects_once_the_coordinator_comes_up() {
    // Find a free port, and leave it unserved for a while.
    let addr = TcpIncoming::bind("127.0.0.1:0".parse().unwrap())
        .unwrap()
        .local_addr()
        .unwrap();
    let fake = Fake::with(|s| s.tasks = [task("a", 1, true)].into());
    let running = Running::start(config(&format!("http://{addr}"), Some(1)), cpu());
    tokio::time::sleep(Duration::from_millis(1200)).await;
    assert!(!running.handle.is_finished());
    serve_on(fake.clone(), &addr.to_string(), None).await;
    let summary = running.finish(false).await.unwrap();
    assert_eq!(summary.tasks_completed, 1);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn another_protocol_version_is_fatal() {
    let fake = Fake::with(|s| {
        s.register_error = Some(Status::failed_precondition(
            "this coordinator speaks protocol 2, the worker 1.0",
        ))
    });
    let url = serve(fake).await;
    let err = Running::start(config(&url, None), cpu())
        .finish(false)
        .await
        .unwrap_err();
    assert!(matches!(err, AgentError::Refused { .. }), "{err}");
    assert!(err.to_string().contains("speaks protocol 2"), "{err}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_wrong_token_is_fatal() {
    let fake = Fake::default();
    let url = serve_on(Arc::new(fake), "127.0.0.1:0", Some("right")).await;
    let mut config = config(&url, None);
    config.endpoint.token = Some("wrong".into());
    let err = Running::start(config, cpu())
        .finish(false)
        .await
        .unwrap_err();
    assert!(matches!(err, AgentError::Unauthenticated { .. }), "{err}");
    assert!(err.to_string().contains("wrong token"), "{err}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_malformed_url_is_fatal_and_a_bad_rate_is_refused() {
    let err = Running::start(config("not a url", None), cpu())
        .finish(false)
        .await
        .unwrap_err();
    assert!(matches!(err, AgentError::Connect(_)), "{err}");
    let mut bad = config("http://127.0.0.1:1", None);
    bad.photons_per_second = Some(f64::NAN);
    let err = Running::start(bad, cpu()).finish(false).await.unwrap_err();
    assert!(matches!(err, AgentError::PhotonsPerSecond(_)), "{err}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_while_unreachable_returns_at_once() {
    let running = Running::start(config("http://127.0.0.1:1", None), cpu());
    tokio::time::sleep(Duration::from_millis(300)).await;
    let start = Instant::now();
    let summary = running.finish(true).await.unwrap();
    assert_eq!(summary, AgentSummary::default());
    assert!(start.elapsed() < Duration::from_secs(5));
}

#[test]
fn the_default_name_is_host_and_engine() {
    let name = default_name(&CpuEngine::new().fingerprint());
    assert!(name.ends_with("/cpu") && name.len() > 4, "{name}");
    let gpu = EngineFingerprint {
        engine: "gpu".into(),
        adapter: "llvmpipe".into(),
        driver: "mesa".into(),
        version: "1".into(),
    };
    assert!(default_name(&gpu).ends_with("/gpu-llvmpipe"));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn without_a_given_rate_the_engine_is_measured() {
    let fake = Fake::with(|s| s.tasks = [task("a", 1, true)].into());
    let url = serve(fake.clone()).await;
    let mut config = config(&url, Some(1));
    config.photons_per_second = None;
    config.name = None;
    let start = Instant::now();
    Running::start(config, cpu()).finish(false).await.unwrap();
    let s = fake.state();
    let rate = s.registrations[0].photons_per_second;
    assert!(rate.is_finite() && rate > 0.0 && rate != 1e6, "{rate}");
    assert!(s.registrations[0].name.ends_with("/cpu"));
    eprintln!(
        "measured {rate:.3e} photons/s; the run took {:.2} s",
        start.elapsed().as_secs_f64()
    );
}

/// A scored task of `job`: both items, photons `[0, 50)`, scored against `target` if it is
/// sent.
fn scored_task(job: &str, task_id: u64, target: Option<&Target>) -> Task {
    let mut t = task(job, task_id, true);
    t.photon_first = 0;
    t.photon_count = 50;
    t.scored = Some(scatterfarm_proto::scored::scored_to_proto(target));
    t
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn scored_tasks_return_the_deviance_of_each_render_and_no_counts() {
    let g = geometry();
    let target = Target {
        values: vec![0.01; g.sources() * g.bins()],
        photons_per_source: 1000,
    };
    let fake = Fake::with(|s| {
        s.tasks = [
            scored_task("t", 3, None),
            scored_task("s", 1, Some(&target)),
            scored_task("s", 2, None),
        ]
        .into();
    });
    let url = serve(fake.clone()).await;
    let summary = Running::start(config(&url, Some(2)), cpu())
        .finish(false)
        .await
        .unwrap();
    assert_eq!(summary.tasks_completed, 2);
    let s = fake.state();
    assert!(s.registrations[0].scores_renders);
    // A scored task of a job whose target it never got is given back, saying so.
    assert_eq!(s.releases.len(), 1);
    assert!(
        s.releases[0].reason.contains("target"),
        "{}",
        s.releases[0].reason
    );
    // The scores are the deviances of the renders the coordinator would have scored.
    let render = scatterfarm_proto::convert::decode_task(&scored_task("s", 1, None), g).unwrap();
    let outputs = cpu().render(&render.batch()).unwrap();
    let expected: Vec<_> = outputs
        .iter()
        .map(|o| scatterfarm_model::likelihood::deviance(&target, &o.counts, 50).unwrap())
        .collect();
    assert_eq!(s.completed.len(), 2);
    for c in &s.completed {
        assert!(c.counts.is_empty(), "counts came back with the scores");
        assert!(c.scatter_events > 0);
        let scores = scatterfarm_proto::scored::render_scores_from_proto(&c.render_scores).unwrap();
        assert_eq!(scores, expected);
    }
}
