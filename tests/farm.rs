//! The farm across processes: `scatterfarm coordinator`, `scatterfarm worker`s and the client
//! commands as real processes on loopback, and fake workers that speak the protocol from here
//! (late, malformed and impossible results, another protocol version).
//!
//! Every job is the same small reconstruction (grid 4, 16 positions × 3 directions, three
//! materials), and whatever happens to the farm on the way it must end with exactly what
//! `scatterfarm reconstruct` finds in one process with the same seed: a byte-identical
//! `materials.npy` and the same report.
//!
//! Every process a test starts is killed when the test ends, passing or panicking ([`Proc`]).
//! Their logs are kept in the test's temporary folder and shown when an assertion fails.

use scatterfarm_proto::channel::{Authed, Target};
use scatterfarm_proto::v1 as pb;
use scatterfarm_proto::v1::client_service_client::ClientServiceClient;
use scatterfarm_proto::v1::worker_service_client::WorkerServiceClient;
use serde_json::Value;
use std::fs::File;
use std::future::Future;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::OnceLock;
use std::time::{Duration, Instant};
use tonic::Code;

// ---- the job ------------------------------------------------------------------------------

const SCENE: &str = r##"
[geometry]
grid = 4
positions = 16
directions = 3
[map]
legend = { "." = "moderate", "o" = "opaque", "b" = "back" }
rows = ["oo..", "oo..", "...b", "..bb"]
"##;

/// The job's keys besides its scene: a job file writes them as they are, `reconstruct` as flags.
const JOB_KEYS: [(&str, &str); 4] = [
    ("permutations", "2"),
    ("iterations", "4"),
    ("photons_per_iteration", "256"),
    ("seed", "7"),
];

/// The job file with the paper's search: `scene` on line 1, then [`JOB_KEYS`] on lines 2 to 5,
/// then `search` on line 6.
fn job_toml() -> String {
    job_toml_of("paper")
}

/// The same job with the faster search (the default), whose every option is on by default
/// (racing, re-scoring, early step 2, common random numbers, the tiebreak): `job/fast.toml`.
fn fast_job_toml() -> String {
    job_toml_of("fast")
}

fn job_toml_of(search: &str) -> String {
    let mut text = "scene = \"three.toml\"\n".to_string();
    for (key, value) in JOB_KEYS {
        text.push_str(&format!("{key} = {value}\n"));
    }
    text.push_str(&format!("search = \"{search}\"\n"));
    text
}

/// Which of the two jobs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Search {
    Paper,
    Fast,
}

/// The files `scatterfarm result` writes.
const RESULT_FILES: [&str; 5] = [
    "report.json",
    "materials.npy",
    "materials.json",
    "reconstruction.png",
    "maps.png",
];

/// The job reconstructed by `scatterfarm reconstruct --engine cpu`, in one process.
struct Reference {
    report: Value,
    npy: Vec<u8>,
}

/// Computed once per search, by the first test that needs it.
fn reference_of(search: Search) -> &'static Reference {
    static PAPER: OnceLock<Reference> = OnceLock::new();
    static FAST: OnceLock<Reference> = OnceLock::new();
    let cell = match search {
        Search::Paper => &PAPER,
        Search::Fast => &FAST,
    };
    cell.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("three.toml"), SCENE).unwrap();
        let mut cmd = scatterfarm();
        cmd.args(["reconstruct", "--scene", "three.toml"]);
        for (key, value) in JOB_KEYS {
            cmd.arg(format!("--{}", key.replace('_', "-"))).arg(value);
        }
        cmd.args([
            "--search",
            match search {
                Search::Paper => "paper",
                Search::Fast => "fast",
            },
        ]);
        cmd.args(["--engine", "cpu", "--quiet", "--out", "out"])
            .current_dir(dir.path());
        let ran = run(cmd, dir.path(), Duration::from_secs(300));
        ran.ok();
        let out = dir.path().join("out");
        Reference {
            report: serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap())
                .unwrap(),
            npy: std::fs::read(out.join("materials.npy")).unwrap(),
        }
    })
}

/// The paper's job's reference.
fn reference() -> &'static Reference {
    reference_of(Search::Paper)
}

// ---- processes ----------------------------------------------------------------------------

/// `scatterfarm` with a clean environment: no token, coordinator URL or backtrace setting
/// leaks in from the caller; logs at info, without colours.
fn scatterfarm() -> Command {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_scatterfarm"));
    for var in [
        "SCATTERFARM_TOKEN",
        "SCATTERFARM_TOKEN_FILE",
        "SCATTERFARM_COORDINATOR",
        "RUST_BACKTRACE",
        "RUST_LIB_BACKTRACE",
    ] {
        cmd.env_remove(var);
    }
    cmd.env("RUST_LOG", "info")
        .env("NO_COLOR", "1")
        .stdin(Stdio::null());
    cmd
}

/// `scatterfarm ARGS…`, for messages.
fn describe(cmd: &Command) -> String {
    let args: Vec<String> = cmd
        .get_args()
        .map(|a| a.to_string_lossy().into_owned())
        .collect();
    format!("scatterfarm {}", args.join(" "))
}

/// A child process that is killed (SIGKILL) and reaped when dropped, so no test leaves one
/// behind, even when it panics.
struct Proc {
    child: Child,
    what: String,
    /// Where its stderr goes.
    log: Option<PathBuf>,
}

impl Proc {
    fn spawn(mut cmd: Command) -> Proc {
        let what = describe(&cmd);
        let child = cmd
            .spawn()
            .unwrap_or_else(|e| panic!("cannot start `{what}`: {e}"));
        Proc {
            child,
            what,
            log: None,
        }
    }

    /// Started with stdout discarded and stderr (the log) in `log`.
    fn logged(mut cmd: Command, log: &Path) -> Proc {
        cmd.stdout(Stdio::null()).stderr(File::create(log).unwrap());
        let mut proc = Proc::spawn(cmd);
        proc.log = Some(log.to_path_buf());
        proc
    }

    fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    fn running(&mut self) -> bool {
        matches!(self.child.try_wait(), Ok(None))
    }

    fn log_text(&self) -> String {
        self.log
            .as_ref()
            .and_then(|l| std::fs::read_to_string(l).ok())
            .unwrap_or_default()
    }

    /// Waits for the process to end by itself.
    fn wait_exit(&mut self, limit: Duration) -> ExitStatus {
        let deadline = Instant::now() + limit;
        loop {
            if let Some(status) = self.child.try_wait().unwrap() {
                return status;
            }
            assert!(
                Instant::now() < deadline,
                "`{}` did not end within {limit:?}:\n{}",
                self.what,
                self.log_text()
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        self.kill();
    }
}

/// A finished short-lived command.
struct Ran {
    what: String,
    status: ExitStatus,
    stdout: String,
    stderr: String,
}

impl Ran {
    fn ok(&self) -> &str {
        assert!(
            self.status.success(),
            "`{}` failed ({}):\n{}\n{}",
            self.what,
            self.status,
            self.stdout,
            self.stderr
        );
        &self.stdout
    }

    fn fails(&self) -> &str {
        assert!(
            !self.status.success(),
            "`{}` succeeded where it should fail:\n{}\n{}",
            self.what,
            self.stdout,
            self.stderr
        );
        &self.stderr
    }
}

/// Runs `cmd` to its end (killed, and the test failed, after `limit`); its output goes
/// through files in `scratch`.
fn run(mut cmd: Command, scratch: &Path, limit: Duration) -> Ran {
    static RUNS: AtomicUsize = AtomicUsize::new(0);
    let n = RUNS.fetch_add(1, Ordering::Relaxed);
    let out = scratch.join(format!("run-{n}.stdout"));
    let err = scratch.join(format!("run-{n}.stderr"));
    cmd.stdout(File::create(&out).unwrap())
        .stderr(File::create(&err).unwrap());
    let mut proc = Proc::spawn(cmd);
    proc.log = Some(err.clone());
    let status = proc.wait_exit(limit);
    Ran {
        what: proc.what.clone(),
        status,
        stdout: std::fs::read_to_string(&out).unwrap(),
        stderr: std::fs::read_to_string(&err).unwrap(),
    }
}

// ---- a farm -------------------------------------------------------------------------------

/// A coordinator (killed and restarted at will on the same data folder and port), its workers
/// and a temporary folder with the job file (`job/job.toml`, naming `three.toml` beside it).
/// Processes are declared first: they are killed before the folder goes.
struct Farm {
    coordinator: Option<Proc>,
    workers: Vec<Proc>,
    /// The URL the coordinator wrote to its address file.
    address: String,
    /// The URL clients and workers use (the address, unless a test changes it).
    url: String,
    /// Port 0 at first, then the port the coordinator chose: restarts keep it.
    listen: String,
    coordinator_args: Vec<String>,
    /// `--token-file` / `--tls-ca` of clients and workers.
    connect: Vec<String>,
    starts: usize,
    root: tempfile::TempDir,
}

const STATUS_POLL: Duration = Duration::from_millis(50);
/// Long enough for any job here on a loaded 2-core machine.
const JOB_LIMIT: Duration = Duration::from_secs(300);

impl Farm {
    /// The folder and job file, no processes yet.
    fn unstarted() -> Farm {
        let root = tempfile::tempdir().unwrap();
        std::fs::create_dir(root.path().join("job")).unwrap();
        std::fs::write(root.path().join("job/three.toml"), SCENE).unwrap();
        std::fs::write(root.path().join("job/job.toml"), job_toml()).unwrap();
        std::fs::write(root.path().join("job/fast.toml"), fast_job_toml()).unwrap();
        Farm {
            coordinator: None,
            workers: Vec::new(),
            address: String::new(),
            url: String::new(),
            listen: "127.0.0.1:0".into(),
            coordinator_args: Vec::new(),
            connect: Vec::new(),
            starts: 0,
            root,
        }
    }

    /// A farm whose coordinator runs with `args` (paths relative to the farm's folder).
    fn start(args: &[&str]) -> Farm {
        let mut farm = Farm::unstarted();
        farm.start_with(args);
        farm
    }

    fn start_with(&mut self, args: &[&str]) {
        self.coordinator_args = args.iter().map(|a| a.to_string()).collect();
        self.start_coordinator();
    }

    fn path(&self, name: &str) -> PathBuf {
        self.root.path().join(name)
    }

    fn port(&self) -> &str {
        self.address.rsplit(':').next().unwrap()
    }

    /// Starts the coordinator (again) and waits until it has written its address.
    fn start_coordinator(&mut self) {
        assert!(self.coordinator.is_none(), "the coordinator runs already");
        self.starts += 1;
        let address = self.path(&format!("address-{}", self.starts));
        let mut cmd = scatterfarm();
        cmd.args(["coordinator", "--listen", &self.listen, "--data"])
            .arg(self.path("data"))
            .arg("--address-file")
            .arg(&address)
            .args(&self.coordinator_args)
            .current_dir(self.root.path());
        let mut proc = Proc::logged(cmd, &self.path(&format!("coordinator-{}.log", self.starts)));
        let deadline = Instant::now() + Duration::from_secs(60);
        let url = loop {
            // Written atomically: once it is there, it is whole.
            if let Ok(text) = std::fs::read_to_string(&address) {
                break text.trim().to_string();
            }
            if let Ok(Some(status)) = proc.child.try_wait() {
                panic!(
                    "the coordinator exited ({status}) before listening:\n{}",
                    proc.log_text()
                );
            }
            assert!(
                Instant::now() < deadline,
                "the coordinator wrote no address within 60 s:\n{}",
                proc.log_text()
            );
            std::thread::sleep(Duration::from_millis(20));
        };
        assert!(
            url.starts_with("http://127.0.0.1:") || url.starts_with("https://127.0.0.1:"),
            "address file: {url:?}"
        );
        if self.starts > 1 {
            assert_eq!(url, self.address, "the restarted coordinator moved");
        }
        self.address = url.clone();
        if self.url.is_empty() {
            self.url = url;
        }
        self.listen = format!("127.0.0.1:{}", self.port());
        self.coordinator = Some(proc);
    }

    /// `kill -9` of the coordinator.
    fn kill_coordinator(&mut self) {
        let mut proc = self.coordinator.take().expect("no coordinator runs");
        assert!(
            proc.running(),
            "the coordinator had died:\n{}",
            proc.log_text()
        );
        proc.kill();
    }

    /// Starts `scatterfarm worker --engine cpu --name NAME` with the farm's connection flags and
    /// `extra`; returns its index in `workers`.
    fn start_worker(&mut self, name: &str, extra: &[&str]) -> usize {
        let mut cmd = scatterfarm();
        cmd.args([
            "worker",
            "--coordinator",
            &self.url,
            "--engine",
            "cpu",
            "--name",
            name,
        ])
        .args(&self.connect)
        .args(extra)
        .current_dir(self.root.path());
        self.workers
            .push(Proc::logged(cmd, &self.path(&format!("worker-{name}.log"))));
        self.workers.len() - 1
    }

    /// A client command at `url` with the connection flags `connect`, environment `env` and
    /// `args` (the subcommand first).
    fn client_at(
        &self,
        url: &str,
        connect: &[&str],
        env: &[(&str, &str)],
        args: &[&str],
        limit: Duration,
    ) -> Ran {
        let mut cmd = scatterfarm();
        cmd.env("RUST_LOG", "warn")
            .arg(args[0])
            .args(["--coordinator", url])
            .args(connect)
            .args(&args[1..])
            .current_dir(self.root.path());
        for (k, v) in env {
            cmd.env(k, v);
        }
        run(cmd, self.root.path(), limit)
    }

    /// A client command with the farm's URL and connection flags.
    fn cli(&self, args: &[&str]) -> Ran {
        let connect: Vec<&str> = self.connect.iter().map(String::as_str).collect();
        self.client_at(&self.url, &connect, &[], args, Duration::from_secs(120))
    }

    /// A client command that must succeed; its stdout.
    fn ok(&self, args: &[&str]) -> String {
        let ran = self.cli(args);
        assert!(
            ran.status.success(),
            "`{}` failed ({}):\n{}\n{}\n{}",
            ran.what,
            ran.status,
            ran.stdout,
            ran.stderr,
            self.logs()
        );
        ran.stdout
    }

    fn json(&self, args: &[&str]) -> Value {
        let text = self.ok(args);
        serde_json::from_str(&text).unwrap_or_else(|e| panic!("{args:?}: {e}: {text}"))
    }

    /// Submits `job/job.toml`; the job id `submit` printed, alone on stdout.
    fn submit(&self) -> String {
        self.submit_file("job/job.toml")
    }

    /// Submits a job file of the farm's folder; the job id.
    fn submit_file(&self, file: &str) -> String {
        let out = self.ok(&["submit", file]);
        let id = out.trim().to_string();
        assert!(
            !id.is_empty() && !id.contains(char::is_whitespace) && out == format!("{id}\n"),
            "submit printed {out:?}"
        );
        id
    }

    fn status(&self, id: &str) -> Value {
        self.json(&["status", id, "--json"])
    }

    /// Polls `status --json` until `reached` holds; fails if the job ends first.
    fn wait_for(&self, id: &str, what: &str, reached: impl Fn(&Value) -> bool) -> Value {
        let deadline = Instant::now() + JOB_LIMIT;
        loop {
            let s = self.status(id);
            if reached(&s) {
                return s;
            }
            assert!(
                !matches!(
                    s["state"].as_str(),
                    Some("finished" | "cancelled" | "failed")
                ),
                "job {id} ended before {what}: {s:#}\n{}",
                self.logs()
            );
            assert!(
                Instant::now() < deadline,
                "job {id}: no {what} within {JOB_LIMIT:?}: {s:#}\n{}",
                self.logs()
            );
            std::thread::sleep(STATUS_POLL);
        }
    }

    /// Polls `status --json` until the job ends; it must have finished.
    fn wait_finished(&self, id: &str) -> Value {
        let deadline = Instant::now() + JOB_LIMIT;
        loop {
            let s = self.status(id);
            match s["state"].as_str() {
                Some("finished") => return s,
                Some("preparing" | "searching") => {}
                _ => panic!("job {id} did not finish: {s:#}\n{}", self.logs()),
            }
            assert!(
                Instant::now() < deadline,
                "job {id} did not finish within {JOB_LIMIT:?}: {s:#}\n{}",
                self.logs()
            );
            std::thread::sleep(STATUS_POLL);
        }
    }

    /// `workers --json`.
    fn worker_list(&self) -> Vec<Value> {
        self.json(&["workers", "--json"])
            .as_array()
            .expect("workers --json is an array")
            .clone()
    }

    fn worker_named(&self, name: &str) -> Option<Value> {
        self.worker_list().into_iter().find(|w| w["name"] == name)
    }

    /// Waits until workers of every name in `names` are registered.
    fn wait_workers(&self, names: &[&str]) {
        let deadline = Instant::now() + Duration::from_secs(120);
        loop {
            let list = self.worker_list();
            if names.iter().all(|n| list.iter().any(|w| w["name"] == *n)) {
                return;
            }
            assert!(
                Instant::now() < deadline,
                "workers {names:?} did not register: {list:?}\n{}",
                self.logs()
            );
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    /// `result ID --out DIR`: every output file is written; the report and `materials.npy`.
    fn result(&self, id: &str) -> (Value, Vec<u8>) {
        let out = format!("result-{id}");
        self.ok(&["result", id, "--out", &out]);
        let dir = self.path(&out);
        for f in RESULT_FILES {
            assert!(dir.join(f).is_file(), "result wrote no {f}");
        }
        let report = serde_json::from_slice(&std::fs::read(dir.join("report.json")).unwrap())
            .expect("report.json is JSON");
        (report, std::fs::read(dir.join("materials.npy")).unwrap())
    }

    /// The job's result is `reconstruct`'s: the same `materials.npy` bytes, the same report
    /// (but for the wall time, and the photons simulated, which grow when renders are redone
    /// after a coordinator restart).
    fn assert_reference_result(&self, id: &str, redone: bool) {
        self.assert_result_of(Search::Paper, id, redone);
    }

    fn assert_result_of(&self, search: Search, id: &str, redone: bool) {
        let (report, npy) = self.result(id);
        let r = reference_of(search);
        assert!(
            npy == r.npy,
            "materials.npy of job {id} differs from `scatterfarm reconstruct`'s\nfarm: {report:#}\n{}",
            self.logs()
        );
        assert_eq!(report["similarity"], r.report["similarity"]);
        let strip = |v: &Value| {
            let mut v = v.clone();
            let o = v.as_object_mut().unwrap();
            o.remove("wall_seconds");
            o.remove("photons_simulated");
            v
        };
        assert_eq!(strip(&report), strip(&r.report), "reports differ");
        let simulated = report["photons_simulated"].as_u64().unwrap();
        let reference = r.report["photons_simulated"].as_u64().unwrap();
        if redone {
            assert!(simulated >= reference, "{simulated} < {reference}");
        } else {
            assert_eq!(simulated, reference);
        }
    }

    /// The tails of every log of the farm, for failure messages.
    fn logs(&self) -> String {
        let mut names: Vec<String> = std::fs::read_dir(self.root.path())
            .unwrap()
            .filter_map(|e| e.ok())
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .filter(|n| n.ends_with(".log"))
            .collect();
        names.sort();
        let mut text = String::new();
        for name in names {
            let body = std::fs::read_to_string(self.path(&name)).unwrap_or_default();
            let lines: Vec<&str> = body.lines().collect();
            let keep = if name.starts_with("coordinator") {
                60
            } else {
                15
            };
            text.push_str(&format!("---- {name} (last {keep} lines)\n"));
            for line in &lines[lines.len().saturating_sub(keep)..] {
                text.push_str(line);
                text.push('\n');
            }
        }
        text
    }
}

/// The share of the job's renders done.
fn fraction(s: &Value) -> f64 {
    let done = s["renders_done"].as_f64().unwrap();
    let total = s["renders_total"].as_f64().unwrap();
    if total > 0.0 {
        done / total
    } else {
        0.0
    }
}

// ---- a fake worker (and client) speaking the protocol from the test -----------------------

/// gRPC clients of a plaintext, token-less coordinator, on a runtime of their own.
struct Rpc {
    worker: WorkerServiceClient<Authed>,
    client: ClientServiceClient<Authed>,
    rt: tokio::runtime::Runtime,
}

/// The CPU engine's fingerprint: jobs are pinned to the first worker's, so a fake worker
/// announces the same one as the real workers it shares jobs with.
fn cpu_fingerprint() -> pb::EngineFingerprint {
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
    fn connect(url: &str) -> Rpc {
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .enable_all()
            .build()
            .unwrap();
        let target = Target {
            url: url.to_string(),
            ca_pem: None,
            token: None,
        };
        let channel = rt
            .block_on(target.connect())
            .unwrap_or_else(|e| panic!("cannot connect to {url}: {e}"));
        Rpc {
            worker: Target::worker_client(channel.clone()),
            client: Target::client_client(channel),
            rt,
        }
    }

    fn worker_call<T, F>(
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

    fn client_call<T, F>(&self, call: impl FnOnce(ClientServiceClient<Authed>) -> F) -> T
    where
        F: Future<Output = Result<tonic::Response<T>, tonic::Status>>,
    {
        self.rt
            .block_on(call(self.client.clone()))
            .map(tonic::Response::into_inner)
            .unwrap_or_else(|s| panic!("client call failed: {s:?}"))
    }

    /// Registers a fake CPU worker speaking `protocol`.
    fn register(
        &self,
        protocol: pb::ProtocolVersion,
        name: &str,
    ) -> Result<pb::RegisterResponse, tonic::Status> {
        let request = pb::RegisterRequest {
            protocol: Some(protocol),
            fingerprint: Some(cpu_fingerprint()),
            photons_per_second: 1e6,
            name: name.to_string(),
        };
        self.worker_call(|mut w| async move { w.register(request).await })
    }

    /// Registers a fake worker of this protocol version; its id.
    fn register_fake(&self, name: &str) -> String {
        self.register(pb::PROTOCOL, name)
            .unwrap_or_else(|s| panic!("registration refused: {s:?}"))
            .worker_id
    }

    fn heartbeat(&self, worker: &str) -> bool {
        let request = pb::HeartbeatRequest {
            worker_id: worker.to_string(),
        };
        self.worker_call(|mut w| async move { w.heartbeat(request).await })
            .expect("heartbeat")
            .known
    }

    /// One lease request (the coordinator waits up to a second for work).
    fn try_lease(&self, worker: &str) -> pb::LeaseResponse {
        let request = pb::LeaseRequest {
            worker_id: worker.to_string(),
            cached_jobs: Vec::new(),
        };
        self.worker_call(|mut w| async move { w.lease(request).await })
            .unwrap_or_else(|s| panic!("lease refused: {s:?}"))
    }

    /// Leases until a task comes.
    fn lease(&self, worker: &str) -> pb::Task {
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

    fn complete(
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
        };
        self.worker_call(|mut w| async move { w.complete(request).await })
    }

    fn workers(&self) -> Vec<pb::WorkerStatus> {
        self.client_call(|mut c| async move { c.list_workers(pb::ListWorkersRequest {}).await })
            .workers
    }

    fn status(&self, id: &str) -> pb::JobStatus {
        let request = pb::JobRef {
            job_id: id.to_string(),
        };
        self.client_call(|mut c| async move { c.status(request).await })
    }

    fn jobs(&self) -> Vec<pb::JobStatus> {
        self.client_call(|mut c| async move { c.list_jobs(pb::ListJobsRequest {}).await })
            .jobs
    }

    fn submit(
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
fn task_sources(task: &pb::Task) -> u32 {
    let g = task
        .geometry
        .as_ref()
        .expect("the task has its geometry (no cached jobs were named)");
    g.positions * g.directions
}

fn matrix(sources: u32, bins: u32, counts: &[u32]) -> pb::CountMatrix {
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
fn dark_counts(task: &pb::Task) -> Vec<pb::CountMatrix> {
    let n = task_sources(task);
    let zeros = vec![0; (n * n) as usize];
    task.assignments
        .iter()
        .map(|_| matrix(n, n, &zeros))
        .collect()
}

fn assert_code(result: Result<impl std::fmt::Debug, tonic::Status>, code: Code) -> String {
    match result {
        Ok(v) => panic!("accepted where {code:?} was expected: {v:?}"),
        Err(s) => {
            assert_eq!(s.code(), code, "{s:?}");
            s.message().to_string()
        }
    }
}

// ---- the tests ----------------------------------------------------------------------------

#[test]
fn two_workers_reconstruct_exactly_what_reconstruct_does() {
    let mut farm = Farm::start(&["--task-seconds", "0.05"]);
    farm.start_worker("a", &[]);
    farm.start_worker("b", &[]);
    farm.wait_workers(&["a", "b"]);
    let id = farm.submit();
    let jobs = farm.json(&["jobs", "--json"]);
    assert_eq!(jobs.as_array().unwrap().len(), 1, "{jobs:#}");
    assert_eq!(jobs[0]["job_id"], id.as_str());

    // `watch` returns when the job ends.
    let connect: Vec<&str> = farm.connect.iter().map(String::as_str).collect();
    farm.client_at(&farm.url, &connect, &[], &["watch", &id], JOB_LIMIT)
        .ok();
    let status = farm.status(&id);
    assert_eq!(status["state"], "finished", "{status:#}\n{}", farm.logs());
    assert_eq!(status["renders_done"], status["renders_total"]);
    assert_eq!(
        status["best_similarity"],
        reference().report["similarity"],
        "{status:#}"
    );
    farm.assert_reference_result(&id, false);

    // Both workers rendered pieces of it, and are still running.
    for name in ["a", "b"] {
        let w = farm.worker_named(name).expect("still registered");
        assert!(w["tasks_completed"].as_u64().unwrap() > 0, "{w:#}");
        assert_eq!(w["engine"], status["engine"]);
    }
    for w in &mut farm.workers {
        assert!(w.running(), "{} died:\n{}", w.what, w.log_text());
    }

    // Deleted, the job is gone.
    farm.ok(&["delete", &id]);
    assert_eq!(farm.json(&["jobs", "--json"]), serde_json::json!([]));
    let err = farm.cli(&["status", &id]).fails().to_string();
    assert!(err.contains(&id), "{err}");
}

#[test]
fn a_coordinator_killed_three_times_resumes_to_the_same_result() {
    let mut farm = Farm::start(&["--task-seconds", "0.05"]);
    farm.start_worker("a", &[]);
    farm.start_worker("b", &[]);
    farm.wait_workers(&["a", "b"]);
    let id = farm.submit();

    // 1: while preparing, with a render leased (polled over gRPC: preparing is short).
    let rpc = Rpc::connect(&farm.address);
    let deadline = Instant::now() + JOB_LIMIT;
    let before = loop {
        let s = rpc.status(&id);
        if s.workers_busy > 0 {
            assert_eq!(
                s.state,
                pb::JobState::Preparing as i32,
                "the job left preparing before a lease was seen: {s:?}"
            );
            break s;
        }
        assert!(
            Instant::now() < deadline,
            "no lease: {s:?}\n{}",
            farm.logs()
        );
        std::thread::sleep(Duration::from_millis(1));
    };
    drop(rpc);
    farm.kill_coordinator();
    farm.start_coordinator();
    let after = farm.status(&id);
    assert!(
        after["state"] == "preparing" || after["state"] == "searching",
        "{after:#}"
    );
    assert!(after["renders_done"].as_u64().unwrap() >= before.renders_done);

    // 2 and 3: past 20 % and 70 % of the renders.
    for share in [0.2, 0.7] {
        let before = farm.wait_for(&id, &format!("{share} of the renders"), |s| {
            s["state"] == "searching" && fraction(s) > share
        });
        farm.kill_coordinator();
        farm.start_coordinator();
        let after = farm.status(&id);
        assert!(
            after["state"] == "searching" || after["state"] == "finished",
            "after a restart past {share}: {after:#}\n{}",
            farm.logs()
        );
        // It resumes where it stood: every step reported before the kill was stored.
        assert!(
            after["renders_done"].as_u64() >= before["renders_done"].as_u64(),
            "before the kill: {before:#}\nafter the restart: {after:#}"
        );
    }

    farm.wait_finished(&id);
    farm.assert_reference_result(&id, true);
    // The workers lived through it and registered again by themselves.
    for w in &mut farm.workers {
        assert!(w.running(), "{} died:\n{}", w.what, w.log_text());
    }
    farm.wait_workers(&["a", "b"]);
}

#[test]
fn a_fast_job_through_a_restart_ends_as_the_fast_search_in_one_process() {
    // Racing (first stages extended by their contenders' groups), re-scoring, early step 2
    // and common random numbers, across processes and a coordinator killed mid-search, which
    // loses the first-stage counts it held.
    let mut farm = Farm::start(&["--task-seconds", "0.05"]);
    farm.start_worker("a", &[]);
    farm.start_worker("b", &[]);
    farm.wait_workers(&["a", "b"]);
    let id = farm.submit_file("job/fast.toml");
    let before = farm.wait_for(&id, "half of the requests", |s| {
        s["state"] == "searching" && fraction(s) > 0.5
    });
    farm.kill_coordinator();
    farm.start_coordinator();
    let after = farm.status(&id);
    assert!(
        after["renders_done"].as_u64() >= before["renders_done"].as_u64(),
        "before the kill: {before:#}\nafter the restart: {after:#}"
    );
    farm.wait_finished(&id);
    farm.assert_result_of(Search::Fast, &id, true);
    let (report, _) = farm.result(&id);
    let config = &report["configuration"];
    assert_eq!(config["search"], "fast", "{config:#}");
    assert!(
        config["race"].is_object() && config["rescore_photons"].is_u64(),
        "{config:#}"
    );
    // One ε per budget: the level's, racing's first stage, re-scoring's.
    assert!(
        report["epsilons"].as_object().unwrap().len() >= 3,
        "{report:#}"
    );
    // Fewer photons than the paper's search of the same job, from the same request logic.
    let paper = reference().report["photons"].as_u64().unwrap();
    let fast = report["photons"].as_u64().unwrap();
    assert!(fast * 4 < paper, "fast {fast} photons, paper {paper}");
}

#[test]
fn a_task_of_a_worker_killed_mid_task_is_rendered_by_another() {
    let mut farm = Farm::start(&["--task-seconds", "0.05", "--heartbeat-ms", "300"]);
    let rpc = Rpc::connect(&farm.address);
    farm.start_worker("survivor", &[]);
    let mut victim = farm.start_worker("victim-1", &[]);
    farm.wait_workers(&["survivor", "victim-1"]);
    let id = farm.submit();

    // Kill a worker the coordinator says holds a task. If it returned its task in the instant
    // before the kill, try again with another one.
    let mut lost = None;
    for round in 1..=5 {
        let name = format!("victim-{round}");
        if round > 1 {
            victim = farm.start_worker(&name, &[]);
            farm.wait_workers(&[&name]);
        }
        let deadline = Instant::now() + JOB_LIMIT;
        while !rpc
            .workers()
            .iter()
            .any(|w| w.name == name && w.tasks_leased > 0)
        {
            let s = rpc.status(&id);
            assert!(
                s.state == pb::JobState::Preparing as i32
                    || s.state == pb::JobState::Searching as i32,
                "the job ended before {name} was seen holding a task: {s:?}"
            );
            assert!(Instant::now() < deadline, "{name} never held a task");
            std::thread::sleep(Duration::from_millis(1));
        }
        farm.workers[victim].kill();
        // Let a result already on its way land.
        std::thread::sleep(Duration::from_millis(100));
        // (A worker the coordinator already forgot, say on a loaded machine, does not count.)
        let held = rpc
            .workers()
            .into_iter()
            .find(|w| w.name == name && w.tasks_leased > 0);
        if let Some(w) = held {
            lost = Some(w.worker_id);
            break;
        }
    }
    let lost = lost.expect("no worker was killed holding a task in 5 tries");

    // Its heartbeats stop: it is forgotten and its task leased again.
    let deadline = Instant::now() + Duration::from_secs(30);
    while rpc.workers().iter().any(|w| w.worker_id == lost) {
        assert!(
            Instant::now() < deadline,
            "the killed worker {lost} is still registered 30 s later\n{}",
            farm.logs()
        );
        std::thread::sleep(Duration::from_millis(100));
    }

    farm.wait_finished(&id);
    farm.assert_reference_result(&id, false);
    // Only the survivor was left to render the lost task; it is still running.
    let survivor = &mut farm.workers[0];
    assert!(
        survivor.running(),
        "the survivor died:\n{}",
        survivor.log_text()
    );
}

#[test]
fn late_results_of_lost_leases_are_refused() {
    // Fake workers answer between lease calls of a second: a heartbeat of a second (3 s of
    // silence before a worker is forgotten) keeps them registered on a loaded machine.
    let mut farm = Farm::start(&["--task-seconds", "0.05", "--heartbeat-ms", "1000"]);
    let rpc = Rpc::connect(&farm.address);
    let first = rpc.register(pb::PROTOCOL, "late-1").unwrap();
    assert_eq!(first.heartbeat_interval_ms, 1000);
    let id = farm.submit();
    let task = rpc.lease(&first.worker_id);
    assert_eq!((task.job_id.as_str(), task.attempt), (id.as_str(), 1));

    // The first fake falls silent. A second one leases everything it can, holding it, until
    // the coordinator has forgotten the first and hands its task out again.
    let second = rpc.register_fake("late-2");
    let deadline = Instant::now() + Duration::from_secs(60);
    let again = loop {
        assert!(rpc.heartbeat(&second), "the second fake was forgotten");
        let response = rpc.try_lease(&second);
        if let Some(t) = response.task {
            if t.task_id == task.task_id {
                break t;
            }
        }
        assert!(
            Instant::now() < deadline,
            "task {} was not leased again\n{}",
            task.task_id,
            farm.logs()
        );
    };
    assert_eq!(again.attempt, 2);
    assert_eq!(
        (again.photon_first, again.photon_count),
        (task.photon_first, task.photon_count)
    );

    // Like a real worker, the first fake learns it was forgotten, registers again and sends its
    // result: attempt 1 is stale while attempt 2 holds the lease.
    assert!(!rpc.heartbeat(&first.worker_id));
    assert_code(
        rpc.complete(&first.worker_id, &task, dark_counts(&task)),
        Code::NotFound,
    );
    let first_again = rpc.register_fake("late-1");
    let message = assert_code(
        rpc.complete(&first_again, &task, dark_counts(&task)),
        Code::FailedPrecondition,
    );
    assert!(message.contains(&task.task_id.to_string()), "{message}");

    // Now the second fake falls silent holding the task, and a real worker joins: it gets the
    // task once the second fake is forgotten, and the job can only get past preparing (the
    // task is a setup render) once the real worker has rendered it.
    farm.start_worker("real", &[]);
    farm.wait_for(&id, "the end of preparing", |s| s["state"] != "preparing");
    let real = farm
        .worker_named("real")
        .expect("the real worker is registered");
    assert!(real["tasks_completed"].as_u64().unwrap() > 0, "{real:#}");
    assert!(
        farm.worker_named("late-2").is_none(),
        "late-2 was not forgotten"
    );

    // The second fake's result for attempt 2 comes too late as well.
    assert!(!rpc.heartbeat(&second));
    let second_again = rpc.register_fake("late-2");
    let message = assert_code(
        rpc.complete(&second_again, &again, dark_counts(&again)),
        Code::FailedPrecondition,
    );
    assert!(message.contains(&task.task_id.to_string()), "{message}");

    farm.wait_finished(&id);
    farm.assert_reference_result(&id, false);
}

#[test]
fn tokens_are_required_and_checked() {
    let mut farm = Farm::unstarted();
    std::fs::write(farm.path("token"), "s3cret\n").unwrap();
    std::fs::write(farm.path("wrong-token"), "nope\n").unwrap();
    farm.start_with(&["--token-file", "token"]);
    let wrong = ["--token-file", "wrong-token"];

    // Clients without a token and with a wrong one are refused, saying why.
    for args in [&["jobs", "--json"][..], &["submit", "job/job.toml"][..]] {
        let limit = Duration::from_secs(60);
        let none = farm.client_at(&farm.url, &[], &[], args, limit);
        let err = none.fails();
        assert!(err.contains("token"), "{args:?} without a token: {err}");
        let bad = farm.client_at(&farm.url, &wrong, &[], args, limit);
        let err = bad.fails();
        assert!(
            err.contains("wrong token"),
            "{args:?} with a wrong token: {err}"
        );
    }
    // So are workers: they exit with an error.
    let no_token = farm.start_worker("no-token", &[]);
    let wrong_token = farm.start_worker("wrong-token", &wrong);
    for (i, expected) in [(no_token, "token"), (wrong_token, "wrong token")] {
        let w = &mut farm.workers[i];
        let status = w.wait_exit(Duration::from_secs(120));
        assert!(!status.success(), "{} exited {status}", w.what);
        let log = w.log_text();
        assert!(log.contains(expected), "{}:\n{log}", w.what);
    }

    // The right token, from a file or from SCATTERFARM_TOKEN, works; nothing was stored.
    farm.connect = vec!["--token-file".into(), "token".into()];
    assert_eq!(farm.json(&["jobs", "--json"]), serde_json::json!([]));
    let from_env = farm.client_at(
        &farm.url,
        &[],
        &[("SCATTERFARM_TOKEN", "s3cret")],
        &["jobs", "--json"],
        Duration::from_secs(60),
    );
    assert_eq!(from_env.ok().trim(), "[]");
    farm.start_worker("right-token", &[]);
    let id = farm.submit();
    farm.wait_finished(&id);
    farm.assert_reference_result(&id, false);
    let names: Vec<Value> = farm
        .worker_list()
        .iter()
        .map(|w| w["name"].clone())
        .collect();
    assert_eq!(names, vec![Value::from("right-token")]);
}

/// A CA, and a certificate it signed for `localhost` and 127.0.0.1: (CA PEM, certificate PEM,
/// key PEM).
fn certificates() -> (String, String, String) {
    use rcgen::{
        BasicConstraints, CertificateParams, DnType, ExtendedKeyUsagePurpose, IsCa, Issuer,
        KeyPair, KeyUsagePurpose,
    };
    let ca_key = KeyPair::generate().unwrap();
    let mut ca = CertificateParams::new(Vec::<String>::new()).unwrap();
    ca.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    ca.distinguished_name
        .push(DnType::CommonName, "scatterfarm test CA");
    ca.key_usages = vec![
        KeyUsagePurpose::KeyCertSign,
        KeyUsagePurpose::CrlSign,
        KeyUsagePurpose::DigitalSignature,
    ];
    let ca_pem = ca.self_signed(&ca_key).unwrap().pem();
    let issuer = Issuer::new(ca, ca_key);
    let key = KeyPair::generate().unwrap();
    let mut server =
        CertificateParams::new(vec!["localhost".to_string(), "127.0.0.1".to_string()]).unwrap();
    server
        .distinguished_name
        .push(DnType::CommonName, "localhost");
    server.extended_key_usages = vec![ExtendedKeyUsagePurpose::ServerAuth];
    server.use_authority_key_identifier_extension = true;
    let cert_pem = server.signed_by(&key, &issuer).unwrap().pem();
    (ca_pem, cert_pem, key.serialize_pem())
}

#[test]
fn tls_carries_a_job_end_to_end_and_plaintext_is_refused() {
    let mut farm = Farm::unstarted();
    let (ca, cert, key) = certificates();
    std::fs::write(farm.path("ca.pem"), ca).unwrap();
    std::fs::write(farm.path("server.pem"), cert).unwrap();
    std::fs::write(farm.path("server.key"), key).unwrap();
    farm.start_with(&["--tls-cert", "server.pem", "--tls-key", "server.key"]);
    assert!(farm.address.starts_with("https://"), "{}", farm.address);
    let port = farm.port().to_string();
    farm.url = format!("https://localhost:{port}");
    let limit = Duration::from_secs(60);
    let jobs = ["jobs", "--json"];

    // A plaintext client is refused; so is a TLS client that does not trust the CA.
    let plain = farm.client_at(&format!("http://127.0.0.1:{port}"), &[], &[], &jobs, limit);
    assert!(!plain.fails().trim().is_empty());
    let untrusting = farm.client_at(&farm.url, &[], &[], &jobs, limit);
    assert!(!untrusting.fails().trim().is_empty());
    // --tls-ca needs an https:// URL.
    let mixed = farm.client_at(
        &format!("http://127.0.0.1:{port}"),
        &["--tls-ca", "ca.pem"],
        &[],
        &jobs,
        limit,
    );
    assert!(mixed.fails().contains("https://"), "{}", mixed.stderr);

    // With the CA, clients and a worker reach it by name and by address.
    farm.connect = vec!["--tls-ca".into(), "ca.pem".into()];
    assert_eq!(farm.json(&jobs), serde_json::json!([]));
    let by_ip = farm.client_at(&farm.address, &["--tls-ca", "ca.pem"], &[], &jobs, limit);
    assert_eq!(by_ip.ok().trim(), "[]");
    farm.start_worker("tls", &[]);
    let id = farm.submit();
    farm.wait_finished(&id);
    farm.assert_reference_result(&id, false);
}

#[test]
fn malformed_results_are_refused_with_a_reason() {
    let mut farm = Farm::start(&["--task-seconds", "0.05"]);
    let rpc = Rpc::connect(&farm.address);
    let fake = rpc.register_fake("bad-results");
    let id = farm.submit();

    // Matrices of the wrong shape.
    let task = rpc.lease(&fake);
    assert_eq!(task.job_id, id);
    let n = task_sources(&task);
    let small = task
        .assignments
        .iter()
        .map(|_| matrix(3, 3, &[0; 9]))
        .collect();
    let message = assert_code(rpc.complete(&fake, &task, small), Code::InvalidArgument);
    assert!(
        message.contains("expected") && message.contains(&n.to_string()),
        "{message}"
    );

    // More photons leaving through one source than were launched.
    let task = rpc.lease(&fake);
    let mut counts = dark_counts(&task);
    let mut first_row = vec![0u32; (n * n) as usize];
    first_row[0] = task.photon_count + 1;
    counts[0] = matrix(n, n, &first_row);
    let message = assert_code(rpc.complete(&fake, &task, counts), Code::InvalidArgument);
    assert!(
        message.contains(&(task.photon_count + 1).to_string())
            && message.contains(&task.photon_count.to_string()),
        "{message}"
    );

    // Fewer bytes than the matrix's own shape needs.
    let task = rpc.lease(&fake);
    let mut counts = dark_counts(&task);
    counts[0].counts_le_u32 = vec![0u8; (4 * n * n - 4) as usize].into();
    let message = assert_code(rpc.complete(&fake, &task, counts), Code::InvalidArgument);
    assert!(message.contains("bytes"), "{message}");

    // Three bad results: the fake is blocked for this job, which still has work.
    let response = rpc.try_lease(&fake);
    assert!(
        response.task.is_none(),
        "a worker that sent 3 bad results got {:?}",
        response.task
    );

    // A real worker renders the job, refused pieces included.
    farm.start_worker("real", &[]);
    farm.wait_finished(&id);
    farm.assert_reference_result(&id, false);
}

#[test]
fn malformed_job_files_are_refused_and_nothing_is_stored() {
    let farm = Farm::start(&[]);
    let good = job_toml();
    std::fs::write(
        farm.path("job/bad-scene.toml"),
        SCENE.replace("\"...b\"", "\"..xb\""),
    )
    .unwrap();
    let cases: [(&str, String, &[&str]); 5] = [
        (
            "unknown-key.toml",
            format!("{good}permutation = 3\n"),
            &["unknown-key.toml", "permutation", "line 7"],
        ),
        (
            "wrong-type.toml",
            good.replace("iterations = 4", "iterations = \"four\""),
            &["wrong-type.toml", "line 3", "four"],
        ),
        (
            "no-scene.toml",
            good.replace("scene = \"three.toml\"\n", ""),
            &["no-scene.toml", "scene"],
        ),
        (
            "bad-row.toml",
            good.replace("three.toml", "bad-scene.toml"),
            &["bad-row.toml", "bad-scene.toml", "row 3", "'x'"],
        ),
        (
            "no-scene-file.toml",
            good.replace("three.toml", "nowhere.toml"),
            &["no-scene-file.toml", "nowhere.toml"],
        ),
    ];
    for (name, text, expected) in &cases {
        std::fs::write(farm.path(&format!("job/{name}")), text).unwrap();
        let ran = farm.cli(&["submit", &format!("job/{name}")]);
        let err = ran.fails();
        for e in *expected {
            assert!(err.contains(e), "{name}: {e:?} missing from:\n{err}");
        }
        assert!(ran.stdout.trim().is_empty(), "{name}: {}", ran.stdout);
    }

    // The coordinator checks what reaches it without the command's checks too.
    let rpc = Rpc::connect(&farm.address);
    let message = assert_code(
        rpc.submit(
            &format!("{good}permutation = 3\n"),
            &[("three.toml", SCENE)],
        ),
        Code::InvalidArgument,
    );
    assert!(message.contains("permutation"), "{message}");
    let bad_scene = SCENE.replace("\"...b\"", "\"..xb\"");
    let message = assert_code(
        rpc.submit(&good, &[("three.toml", &bad_scene)]),
        Code::InvalidArgument,
    );
    assert!(message.contains("'x'"), "{message}");
    let message = assert_code(rpc.submit(&good, &[]), Code::InvalidArgument);
    assert!(message.contains("three.toml"), "{message}");

    assert!(rpc.jobs().is_empty());
    assert_eq!(farm.json(&["jobs", "--json"]), serde_json::json!([]));
}

#[test]
fn workers_of_another_protocol_version_are_refused() {
    let farm = Farm::start(&[]);
    let rpc = Rpc::connect(&farm.address);
    let ours = format!("{}.{}", pb::PROTOCOL.major, pb::PROTOCOL.minor);
    let message = assert_code(
        rpc.register(pb::ProtocolVersion { major: 2, minor: 0 }, "future"),
        Code::FailedPrecondition,
    );
    assert!(
        message.contains("2.0") && message.contains(&ours),
        "{message}"
    );
    // Another minor version of the same major one is welcome.
    rpc.register(
        pb::ProtocolVersion {
            major: pb::PROTOCOL.major,
            minor: pb::PROTOCOL.minor + 1,
        },
        "newer-minor",
    )
    .unwrap_or_else(|s| panic!("a newer minor version was refused: {s:?}"));
    let names: Vec<String> = rpc.workers().into_iter().map(|w| w.name).collect();
    assert_eq!(names, ["newer-minor"]);
}
