//! A farm: a coordinator (killed and restarted at will on the same data folder and port), its
//! `scatterfarm worker`s with their logs, and the client commands, all real processes on
//! loopback, in a temporary folder with the job files.

use super::process::{run, scatterfarm, scatterfarm_in_netns, Proc, Ran};
use super::reference::reference_of;
use super::scenes::{job_toml, job_toml_of, Search, THREE};
use serde_json::Value;
use std::path::PathBuf;
use std::process::{Command, ExitStatus};
use std::time::{Duration, Instant};

/// The files `scatterfarm result` writes.
const RESULT_FILES: [&str; 6] = [
    "report.json",
    "convergence.png",
    "materials.npy",
    "materials.json",
    "reconstruction.png",
    "maps.png",
];

/// A coordinator (killed and restarted at will on the same data folder and port), its workers
/// and a temporary folder with the job file (`job/job.toml`, naming `three.toml` beside it).
/// Processes are declared first: they are killed before the folder goes.
pub struct Farm {
    pub coordinator: Option<Proc>,
    pub workers: Vec<Proc>,
    /// The URL the coordinator wrote to its address file.
    pub address: String,
    /// The URL clients and workers use (the address, unless a test changes it).
    pub url: String,
    /// Port 0 at first, then the port the coordinator chose: restarts keep it. The address is
    /// loopback's unless a test sets another one before the first start.
    pub listen: String,
    pub coordinator_args: Vec<String>,
    /// `--token-file` / `--tls-ca` of clients and workers.
    pub connect: Vec<String>,
    pub starts: usize,
    pub root: tempfile::TempDir,
}

pub const STATUS_POLL: Duration = Duration::from_millis(50);
/// Long enough for any job here on a loaded 2-core machine.
pub const JOB_LIMIT: Duration = Duration::from_secs(300);

impl Farm {
    /// The folder and job file, no processes yet.
    pub fn unstarted() -> Farm {
        let root = tempfile::tempdir().unwrap();
        std::fs::create_dir(root.path().join("job")).unwrap();
        std::fs::write(root.path().join("job/three.toml"), THREE).unwrap();
        std::fs::write(root.path().join("job/job.toml"), job_toml()).unwrap();
        std::fs::write(root.path().join("job/fast.toml"), job_toml_of(Search::Fast)).unwrap();
        std::fs::write(
            root.path().join("job/differential.toml"),
            job_toml_of(Search::Differential),
        )
        .unwrap();
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
    pub fn start(args: &[&str]) -> Farm {
        let mut farm = Farm::unstarted();
        farm.start_with(args);
        farm
    }

    pub fn start_with(&mut self, args: &[&str]) {
        self.coordinator_args = args.iter().map(|a| a.to_string()).collect();
        self.start_coordinator();
    }

    pub fn path(&self, name: &str) -> PathBuf {
        self.root.path().join(name)
    }

    pub fn port(&self) -> &str {
        self.address.rsplit(':').next().unwrap()
    }

    /// Starts the coordinator (again) and waits until it has written its address.
    pub fn start_coordinator(&mut self) {
        assert!(self.coordinator.is_none(), "the coordinator runs already");
        self.starts += 1;
        let address = self.path(&format!("address-{}", self.starts));
        let mut cmd = scatterfarm();
        cmd.env("RUST_LOG", "info")
            .args(["coordinator", "--listen", &self.listen, "--data"])
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
        let host = self.listen.rsplit_once(':').unwrap().0.to_string();
        assert!(
            url.starts_with(&format!("http://{host}:"))
                || url.starts_with(&format!("https://{host}:")),
            "address file: {url:?} (listening on {})",
            self.listen
        );
        if self.starts > 1 {
            assert_eq!(url, self.address, "the restarted coordinator moved");
        }
        self.address = url.clone();
        if self.url.is_empty() {
            self.url = url;
        }
        self.listen = format!("{host}:{}", self.port());
        self.coordinator = Some(proc);
    }

    /// `kill -9` of the coordinator.
    pub fn kill_coordinator(&mut self) {
        let mut proc = self.coordinator.take().expect("no coordinator runs");
        assert!(
            proc.running(),
            "the coordinator had died:\n{}",
            proc.log_text()
        );
        proc.kill();
    }

    /// SIGTERM to the coordinator, which must then exit by itself within `limit` (its drain);
    /// its exit status. It can be started again on the same folder and port.
    pub fn terminate_coordinator(&mut self, limit: Duration) -> ExitStatus {
        let mut proc = self.coordinator.take().expect("no coordinator runs");
        assert!(
            proc.running(),
            "the coordinator had died:\n{}",
            proc.log_text()
        );
        proc.signal("TERM");
        proc.wait_exit(limit)
    }

    /// Starts `scatterfarm worker --engine cpu --name NAME` with the farm's connection flags and
    /// `extra`; returns its index in `workers`.
    pub fn start_worker(&mut self, name: &str, extra: &[&str]) -> usize {
        self.start_worker_with(scatterfarm(), name, extra)
    }

    /// [`Self::start_worker`] in the network namespace `netns` (`ip netns exec`).
    pub fn start_worker_in(&mut self, netns: &str, name: &str, extra: &[&str]) -> usize {
        self.start_worker_with(scatterfarm_in_netns(netns), name, extra)
    }

    fn start_worker_with(&mut self, mut cmd: Command, name: &str, extra: &[&str]) -> usize {
        cmd.env("RUST_LOG", "info")
            .args([
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
    pub fn client_at(
        &self,
        url: &str,
        connect: &[&str],
        env: &[(&str, &str)],
        args: &[&str],
        limit: Duration,
    ) -> Ran {
        let mut cmd = scatterfarm();
        cmd.arg(args[0])
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
    pub fn cli(&self, args: &[&str]) -> Ran {
        let connect: Vec<&str> = self.connect.iter().map(String::as_str).collect();
        self.client_at(&self.url, &connect, &[], args, Duration::from_secs(120))
    }

    /// A client command that must succeed; its stdout.
    pub fn ok(&self, args: &[&str]) -> String {
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

    pub fn json(&self, args: &[&str]) -> Value {
        let text = self.ok(args);
        serde_json::from_str(&text).unwrap_or_else(|e| panic!("{args:?}: {e}: {text}"))
    }

    /// Submits `job/job.toml`; the job id `submit` printed, alone on stdout.
    pub fn submit(&self) -> String {
        self.submit_file("job/job.toml")
    }

    /// Submits a job file of the farm's folder; the job id.
    pub fn submit_file(&self, file: &str) -> String {
        let out = self.ok(&["submit", file]);
        let id = out.trim().to_string();
        assert!(
            !id.is_empty() && !id.contains(char::is_whitespace) && out == format!("{id}\n"),
            "submit printed {out:?}"
        );
        id
    }

    pub fn status(&self, id: &str) -> Value {
        self.json(&["status", id, "--json"])
    }

    /// Polls `status --json` until `reached` holds; fails if the job ends first.
    pub fn wait_for(&self, id: &str, what: &str, reached: impl Fn(&Value) -> bool) -> Value {
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
    pub fn wait_finished(&self, id: &str) -> Value {
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
    pub fn worker_list(&self) -> Vec<Value> {
        self.json(&["workers", "--json"])
            .as_array()
            .expect("workers --json is an array")
            .clone()
    }

    pub fn worker_named(&self, name: &str) -> Option<Value> {
        self.worker_list().into_iter().find(|w| w["name"] == name)
    }

    /// Waits until workers of every name in `names` are registered.
    pub fn wait_workers(&self, names: &[&str]) {
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
    pub fn result(&self, id: &str) -> (Value, Vec<u8>) {
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
    pub fn assert_reference_result(&self, id: &str, redone: bool) {
        self.assert_result_of(Search::Paper, id, redone);
    }

    pub fn assert_result_of(&self, search: Search, id: &str, redone: bool) {
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
    pub fn logs(&self) -> String {
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
pub fn fraction(s: &Value) -> f64 {
    let done = s["renders_done"].as_f64().unwrap();
    let total = s["renders_total"].as_f64().unwrap();
    if total > 0.0 {
        done / total
    } else {
        0.0
    }
}
