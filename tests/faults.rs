//! Faults beyond a killed process: several jobs at once, jobs cancelled and deleted with their
//! tasks in flight, SIGTERM to a coordinator and to a worker, a second coordinator on a running
//! one's data folder, and a result that comes back after its lease expired although its worker
//! kept sending heartbeats: from a fake worker, and from a real one in a network namespace whose
//! link `tc` slows down, whose leases then grow until its results fit them (as root with
//! iproute2; skipped loudly otherwise, a failure under `CI=true`).
//!
//! Each ends with the reference result (the job's `materials.npy` byte for byte what
//! `scatterfarm reconstruct` writes in one process, and the same report) or with a refusal whose
//! message says why. The harness is [`crate::farm`]'s: real processes on loopback, fake workers
//! speaking the protocol from the test, every process killed when the test ends.

use crate::harness::farm::{Farm, JOB_LIMIT, STATUS_POLL};
use crate::harness::gating::{effective_uid, has_ip, has_tc, skip_or_fail};
use crate::harness::process::{run, scatterfarm};
use crate::harness::rpc::{assert_code, dark_counts, Rpc};
use crate::harness::scenes::{job_toml, Search};
use scatterfarm_proto::v1 as pb;
use std::collections::BTreeMap;
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};
use tonic::Code;

fn active(s: &pb::JobStatus) -> bool {
    s.state == pb::JobState::Preparing as i32 || s.state == pb::JobState::Searching as i32
}

/// Polls the job's status over gRPC (faster than the command) until `reached` holds; fails if
/// the job ends first or after [`JOB_LIMIT`].
fn poll(
    farm: &Farm,
    rpc: &Rpc,
    id: &str,
    what: &str,
    reached: impl Fn(&pb::JobStatus) -> bool,
) -> pb::JobStatus {
    let deadline = Instant::now() + JOB_LIMIT;
    loop {
        let s = rpc.status(id);
        if reached(&s) {
            return s;
        }
        assert!(
            active(&s),
            "job {id} ended before {what}: {s:?}\n{}",
            farm.logs()
        );
        assert!(
            Instant::now() < deadline,
            "job {id}: no {what} within {JOB_LIMIT:?}: {s:?}\n{}",
            farm.logs()
        );
        std::thread::sleep(Duration::from_millis(1));
    }
}

/// A fake worker's heartbeats, sent every 100 ms from a thread (and a connection) of their own
/// until dropped, so that the test can wait on other things meanwhile.
struct Heartbeats {
    stop: Arc<AtomicBool>,
    forgotten: Arc<AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Heartbeats {
    fn start(address: &str, worker: &str) -> Heartbeats {
        let rpc = Rpc::connect(address);
        let worker = worker.to_string();
        let stop = Arc::new(AtomicBool::new(false));
        let forgotten = Arc::new(AtomicBool::new(false));
        let thread = {
            let (stop, forgotten) = (stop.clone(), forgotten.clone());
            std::thread::spawn(move || {
                while !stop.load(Ordering::Relaxed) {
                    if !rpc.heartbeat(&worker) {
                        forgotten.store(true, Ordering::Relaxed);
                    }
                    std::thread::sleep(Duration::from_millis(100));
                }
            })
        };
        Heartbeats {
            stop,
            forgotten,
            thread: Some(thread),
        }
    }

    /// Every heartbeat so far was answered, and the coordinator knew the worker.
    fn assert_known(&self, farm: &Farm) {
        let thread = self.thread.as_ref().unwrap();
        assert!(
            !thread.is_finished() && !self.forgotten.load(Ordering::Relaxed),
            "the fake worker was forgotten, or a heartbeat failed\n{}",
            farm.logs()
        );
    }
}

impl Drop for Heartbeats {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

fn unix_ms() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap()
        .as_millis() as u64
}

#[test]
fn three_jobs_at_once_on_two_workers_each_end_with_their_reference() {
    let mut farm = Farm::start(&["--task-seconds", "0.05"]);
    farm.start_worker("a", &[]);
    farm.start_worker("b", &[]);
    farm.wait_workers(&["a", "b"]);
    // Two of the paper's search and one of the fast one, so that counts of one job summed into
    // another could not go unnoticed.
    let jobs = [
        (Search::Paper, farm.submit()),
        (Search::Fast, farm.submit_file("job/fast.toml")),
        (Search::Paper, farm.submit()),
    ];

    // They run side by side (round-robin): when the first one ends, each of the others has
    // completed renders of its own.
    let rpc = Rpc::connect(&farm.address);
    let deadline = Instant::now() + JOB_LIMIT;
    let at_first_end = loop {
        let list = rpc.jobs();
        assert_eq!(list.len(), 3, "{list:?}");
        if list.iter().any(|j| !active(j)) {
            break list;
        }
        assert!(
            Instant::now() < deadline,
            "no job ended within {JOB_LIMIT:?}: {list:?}\n{}",
            farm.logs()
        );
        std::thread::sleep(STATUS_POLL);
    };
    for j in &at_first_end {
        assert!(
            j.state == pb::JobState::Finished as i32 || (active(j) && j.photons > 0),
            "when the first job ended: {at_first_end:#?}\n{}",
            farm.logs()
        );
    }

    for (search, id) in &jobs {
        farm.wait_finished(id);
        farm.assert_result_of(*search, id, false);
    }
    for w in &mut farm.workers {
        assert!(w.running(), "{} died:\n{}", w.what, w.log_text());
    }
}

#[test]
fn jobs_cancelled_and_deleted_with_tasks_in_flight_leave_the_farm_working() {
    // The two jobs that go have 256 times the photons of the farm's job, and tasks last a
    // second: the real workers are still rendering theirs when the jobs go.
    let mut farm = Farm::start(&["--task-seconds", "1"]);
    let big = job_toml().replace(
        "photons_per_iteration = 256",
        "photons_per_iteration = 65536",
    );
    assert_ne!(big, job_toml());
    std::fs::write(farm.path("job/big.toml"), big).unwrap();
    let rpc = Rpc::connect(&farm.address);
    // A slow fake (small tasks, so both jobs keep work for the real workers) takes a task of
    // each job and holds it: their answers are certain to come back after the cancel and the
    // delete.
    let holder = rpc.register_fake_at("holder", 1e4);
    let beats = Heartbeats::start(&farm.address, &holder);
    let cancelled = farm.submit_file("job/big.toml");
    let deleted = farm.submit_file("job/big.toml");
    let mut held: BTreeMap<String, pb::Task> = BTreeMap::new();
    let mut leased = 0;
    let deadline = Instant::now() + Duration::from_secs(60);
    while !(held.contains_key(&cancelled) && held.contains_key(&deleted)) {
        let response = rpc.try_lease(&holder);
        if let Some(t) = response.task {
            leased += 1;
            held.entry(t.job_id.clone()).or_insert(t);
        }
        assert!(
            Instant::now() < deadline,
            "the fake got no task of each job: {:?} ({})\n{}",
            held.keys(),
            response.reason,
            farm.logs()
        );
    }

    // Real workers render the rest. Once one of them holds a task (of one job or the other),
    // with the fake's leases outstanding, one job is cancelled and the other deleted.
    farm.start_worker("a", &[]);
    farm.start_worker("b", &[]);
    let deadline = Instant::now() + JOB_LIMIT;
    let rendering = loop {
        let workers = rpc.workers();
        if let Some(real) = workers
            .iter()
            .find(|w| w.name != "holder" && w.tasks_leased > 0)
        {
            let fake = workers.iter().find(|w| w.worker_id == holder);
            assert_eq!(
                fake.map(|w| w.tasks_leased),
                Some(leased),
                "the fake's leases: {workers:?}"
            );
            break real.worker_id.clone();
        }
        assert!(
            Instant::now() < deadline,
            "no real worker leased a task: {workers:?}\n{}",
            farm.logs()
        );
        std::thread::sleep(Duration::from_millis(1));
    };
    for id in [&cancelled, &deleted] {
        let s = rpc.status(id);
        assert!(active(&s) && s.workers_busy > 0, "{s:?}");
    }
    farm.ok(&["cancel", &cancelled]);
    farm.ok(&["delete", &deleted]);

    let status = farm.status(&cancelled);
    assert_eq!(status["state"], "cancelled", "{status:#}");
    let err = farm.cli(&["status", &deleted]).fails();
    assert!(err.contains(&deleted), "{err}");
    let listed: Vec<String> = rpc.jobs().into_iter().map(|j| j.job_id).collect();
    assert_eq!(listed, std::slice::from_ref(&cancelled));

    // The fake's late answers are refused, naming the task: a result of the cancelled job and
    // a give-back of the deleted one.
    beats.assert_known(&farm);
    let task = &held[&cancelled];
    let message = assert_code(
        rpc.complete(&holder, task, dark_counts(task)),
        Code::FailedPrecondition,
    );
    assert!(
        message.contains(&format!("task {}", task.task_id)) && message.contains("not leased"),
        "{message}"
    );
    let task = &held[&deleted];
    let message = assert_code(
        rpc.try_release(&holder, task, "leaving"),
        Code::FailedPrecondition,
    );
    assert!(
        message.contains(&format!("task {}", task.task_id)) && message.contains("not leased"),
        "{message}"
    );
    // Nothing of either job is leased any more.
    assert!(rpc.try_lease(&holder).task.is_none());
    assert_eq!(rpc.status(&cancelled).workers_busy, 0);
    beats.assert_known(&farm);
    drop(beats);

    // The real worker's result comes back late too, and is refused.
    let log = farm.path("coordinator-1.log");
    let deadline = Instant::now() + Duration::from_secs(120);
    while !std::fs::read_to_string(&log)
        .unwrap()
        .lines()
        .any(|l| l.contains(&format!("from {rendering} refused")) && l.contains("not leased"))
    {
        assert!(
            Instant::now() < deadline,
            "no result of {rendering} was refused\n{}",
            farm.logs()
        );
        std::thread::sleep(STATUS_POLL);
    }

    // The real workers keep going: a new job ends with the reference result.
    let id = farm.submit();
    farm.wait_finished(&id);
    farm.assert_reference_result(&id, false);
    for w in &mut farm.workers {
        assert!(w.running(), "{} died:\n{}", w.what, w.log_text());
    }
    assert_eq!(farm.status(&cancelled)["state"], "cancelled");
}

#[test]
fn a_coordinator_sent_sigterm_drains_exits_and_resumes_to_the_same_result() {
    // A drain that had to give up on a lease would take 120 s: the bound below is shorter.
    let mut farm = Farm::start(&["--task-seconds", "0.05", "--drain-seconds", "120"]);
    farm.start_worker("a", &[]);
    farm.start_worker("b", &[]);
    farm.wait_workers(&["a", "b"]);
    let id = farm.submit();
    let rpc = Rpc::connect(&farm.address);
    let before = poll(
        &farm,
        &rpc,
        &id,
        "a lease past a fifth of the renders",
        |s| {
            s.workers_busy > 0
                && s.state == pb::JobState::Searching as i32
                && s.renders_done * 5 > s.renders_total
        },
    );
    drop(rpc);

    let log = farm.path(&format!("coordinator-{}.log", farm.starts));
    let status = farm.terminate_coordinator(Duration::from_secs(60));
    let text = std::fs::read_to_string(&log).unwrap();
    assert!(status.success(), "the coordinator exited {status}:\n{text}");
    assert!(
        text.contains("draining") && text.contains("coordinator stopped"),
        "{text}"
    );
    assert!(!text.contains("did not come back"), "{text}");
    // The workers outlive it, retrying.
    for w in &mut farm.workers {
        assert!(w.running(), "{} died:\n{}", w.what, w.log_text());
    }

    farm.start_coordinator();
    let after = farm.status(&id);
    assert!(
        after["renders_done"].as_u64().unwrap() >= before.renders_done,
        "before SIGTERM: {before:?}\nafter the restart: {after:#}"
    );
    farm.wait_finished(&id);
    farm.assert_reference_result(&id, true);
    farm.wait_workers(&["a", "b"]);
}

#[test]
fn a_worker_sent_sigterm_returns_its_task_and_exits_cleanly() {
    // Heartbeats of 5 s: the worker that left stays listed for 15 s, long enough to read what
    // it left behind.
    let mut farm = Farm::start(&["--task-seconds", "0.05", "--heartbeat-ms", "5000"]);
    let rpc = Rpc::connect(&farm.address);
    farm.start_worker("stays", &[]);
    let leaves = farm.start_worker("leaves", &[]);
    farm.wait_workers(&["stays", "leaves"]);
    let id = farm.submit();

    let deadline = Instant::now() + JOB_LIMIT;
    while !rpc
        .workers()
        .iter()
        .any(|w| w.name == "leaves" && w.tasks_leased > 0)
    {
        let s = rpc.status(&id);
        assert!(active(&s), "the job ended first: {s:?}");
        assert!(Instant::now() < deadline, "`leaves` never held a task");
        std::thread::sleep(Duration::from_millis(1));
    }
    farm.workers[leaves].signal("TERM");
    let w = &mut farm.workers[leaves];
    let status = w.wait_exit(Duration::from_secs(60));
    let log = w.log_text();
    assert!(status.success(), "the worker exited {status}:\n{log}");
    assert!(
        log.contains("shutting down") && log.contains("worker stopped after"),
        "{log}"
    );
    assert!(!log.contains("did not take the result"), "{log}");

    // It returned what it held: the coordinator, which still lists it, has no lease of it.
    let left = rpc
        .workers()
        .into_iter()
        .find(|w| w.name == "leaves")
        .expect("the worker that left is still listed");
    assert_eq!(left.tasks_leased, 0, "{left:?}");
    assert!(left.tasks_completed > 0, "{left:?}");

    farm.wait_finished(&id);
    farm.assert_reference_result(&id, false);
    let stays = &mut farm.workers[0];
    assert!(
        stays.running(),
        "{} died:\n{}",
        stays.what,
        stays.log_text()
    );
}

#[test]
fn a_second_coordinator_on_the_same_data_folder_is_refused_and_the_first_works_on() {
    let mut farm = Farm::start(&["--task-seconds", "0.05"]);
    farm.start_worker("a", &[]);
    let id = farm.submit();

    let data = farm.path("data");
    let address = farm.path("address-second");
    let mut cmd = scatterfarm();
    cmd.args(["coordinator", "--listen", "127.0.0.1:0", "--data"])
        .arg(&data)
        .arg("--address-file")
        .arg(&address)
        .current_dir(farm.root.path());
    let second = run(cmd, farm.root.path(), Duration::from_secs(60));
    let err = second.fails();
    assert!(
        err.contains(&data.display().to_string()) && err.contains("in use"),
        "{err}"
    );
    assert!(!err.contains("panicked"), "{err}");
    assert!(
        !address.exists(),
        "the second coordinator wrote its address"
    );

    farm.wait_finished(&id);
    farm.assert_reference_result(&id, false);
    assert!(farm.coordinator.as_mut().unwrap().running());
}

#[test]
fn a_result_past_its_lease_is_refused_although_its_worker_sent_heartbeats() {
    // Leases of 3 s, heartbeats every second (the fake sends them every 100 ms).
    let mut farm = Farm::start(&[
        "--task-seconds",
        "0.05",
        "--lease-seconds",
        "3",
        "--heartbeat-ms",
        "1000",
    ]);
    let rpc = Rpc::connect(&farm.address);
    let slow = rpc.register_fake("slow");
    let beats = Heartbeats::start(&farm.address, &slow);
    let id = farm.submit();
    let task = rpc.lease(&slow);
    assert_eq!((task.job_id.as_str(), task.attempt), (id.as_str(), 1));
    let deadline_ms = task.lease_deadline_unix_ms;
    assert!(deadline_ms > unix_ms(), "{task:?}");

    // It renders slowly, alive all along: the lease expires and is taken from it.
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        beats.assert_known(&farm);
        let me = rpc
            .workers()
            .into_iter()
            .find(|w| w.worker_id == slow)
            .expect("the slow fake is listed");
        if me.tasks_leased == 0 {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "the lease never expired\n{}",
            farm.logs()
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    assert!(
        unix_ms() >= deadline_ms,
        "the lease was taken before its deadline"
    );

    // Its result comes too late, named as such; it is not counted (the result below would
    // differ if its dark counts were).
    let message = assert_code(
        rpc.complete(&slow, &task, dark_counts(&task)),
        Code::FailedPrecondition,
    );
    assert!(
        message.contains(&format!("task {}", task.task_id)) && message.contains("not leased"),
        "{message}"
    );
    std::thread::sleep(Duration::from_millis(200));
    beats.assert_known(&farm);
    drop(beats);

    // A real worker renders the task again, and the rest of the job.
    farm.start_worker("real", &[]);
    farm.wait_finished(&id);
    farm.assert_reference_result(&id, false);
    let log = std::fs::read_to_string(farm.path("coordinator-1.log")).unwrap();
    let expired = format!(
        "task {} attempt 1 of job {id} (worker {slow}) expired",
        task.task_id
    );
    assert!(
        log.contains(&expired),
        "{expired:?} is not in the log:\n{log}"
    );
}

/// Runs `args` to its end; why not, when it fails.
fn sh(args: &[&str]) -> Result<(), String> {
    let out = Command::new(args[0])
        .args(&args[1..])
        .stdin(Stdio::null())
        .output()
        .map_err(|e| format!("cannot run `{}`: {e}", args.join(" ")))?;
    if out.status.success() {
        Ok(())
    } else {
        Err(format!(
            "`{}` failed ({}): {}",
            args.join(" "),
            out.status,
            String::from_utf8_lossy(&out.stderr).trim()
        ))
    }
}

/// A network namespace cabled to the host by a veth pair (the host's end `host_ip`/30, the
/// namespace's `eth0` the other address of the /30); deleted, with whatever still runs in it,
/// when dropped.
struct Netns {
    name: String,
    host_if: String,
    host_ip: String,
}

impl Netns {
    fn create() -> Result<Netns, String> {
        let pid = std::process::id();
        let k = pid % 250 + 1;
        let ns = Netns {
            name: format!("sf-faults-{pid}"),
            host_if: format!("sfh{pid}"),
            host_ip: format!("10.253.{k}.1"),
        };
        sh(&["ip", "netns", "add", &ns.name])?;
        let ns_ip = format!("10.253.{k}.2/30");
        let host_ip = format!("{}/30", ns.host_ip);
        let (name, host_if) = (ns.name.as_str(), ns.host_if.as_str());
        for args in [
            &[
                "ip", "link", "add", host_if, "type", "veth", "peer", "name", "eth0", "netns", name,
            ][..],
            &["ip", "addr", "add", &host_ip, "dev", host_if],
            &["ip", "link", "set", host_if, "up"],
            &["ip", "-n", name, "addr", "add", &ns_ip, "dev", "eth0"],
            &["ip", "-n", name, "link", "set", "eth0", "up"],
            &["ip", "-n", name, "link", "set", "lo", "up"],
        ] {
            sh(args)?;
        }
        Ok(ns)
    }

    /// Shapes what leaves the namespace: `tc qdisc add dev eth0 root QDISC…` in it.
    fn shape(&self, qdisc: &[&str]) -> Result<(), String> {
        let mut args = vec!["ip", "netns", "exec", &self.name, "tc", "qdisc", "add"];
        args.extend(["dev", "eth0", "root"]);
        args.extend(qdisc);
        sh(&args)
    }
}

impl Drop for Netns {
    fn drop(&mut self) {
        if let Ok(out) = Command::new("ip")
            .args(["netns", "pids", &self.name])
            .output()
        {
            for pid in String::from_utf8_lossy(&out.stdout).split_whitespace() {
                let _ = sh(&["kill", "-9", pid]);
            }
        }
        // Deleting the namespace deletes its end of the pair, and with it the host's.
        let _ = sh(&["ip", "netns", "del", &self.name]);
        let _ = sh(&["ip", "link", "del", &self.host_if]);
    }
}

fn skip_partition(why: &str) {
    skip_or_fail(
        "faults::a_worker_on_a_slow_link_loses_results_past_their_lease_until_its_leases_fit",
        why,
        "run the tests as root with iproute2 (ip, tc) and the kernel's tbf qdisc",
    );
}

#[test]
fn a_worker_on_a_slow_link_loses_results_past_their_lease_until_its_leases_fit() {
    match effective_uid() {
        Some(0) => {}
        Some(uid) => return skip_partition(&format!("not root (uid {uid})")),
        None => return skip_partition("cannot tell whether this runs as root"),
    }
    if !has_ip() || !has_tc() {
        return skip_partition("iproute2's `ip` or `tc` is not on PATH");
    }
    let ns = match Netns::create() {
        Ok(ns) => ns,
        Err(why) => return skip_partition(&format!("cannot build a network namespace: {why}")),
    };
    // What the far worker sends crawls at 250 bytes/s: a result (a kilobyte or more of
    // compressed counts) takes seconds, past its lease of 1 s, yet far less than the 30 s of
    // silence (3 heartbeats of 10 s) after which a worker is forgotten. Heartbeats share the
    // result's connection (one HTTP/2 channel), so they wait behind it: no link can pass them
    // and stop results for longer than that.
    if let Err(why) = ns.shape(&["tbf", "rate", "2kbit", "burst", "1600", "limit", "200000"]) {
        return skip_partition(&format!("cannot shape the link: {why}"));
    }

    let mut farm = Farm::unstarted();
    farm.listen = format!("{}:0", ns.host_ip);
    farm.start_with(&[
        "--task-seconds",
        "0.05",
        "--lease-seconds",
        "1",
        "--heartbeat-ms",
        "10000",
    ]);
    let rpc = Rpc::connect(&farm.address);
    farm.start_worker_in(&ns.name, "far", &[]);
    farm.wait_workers(&["far"]);
    let far = rpc
        .workers()
        .into_iter()
        .find(|w| w.name == "far")
        .unwrap()
        .worker_id;
    let id = farm.submit();
    let far_worker = |what: &str, limit: Duration, reached: &dyn Fn(&pb::WorkerStatus) -> bool| {
        let deadline = Instant::now() + limit;
        while !rpc
            .workers()
            .iter()
            .any(|w| w.worker_id == far && reached(w))
        {
            assert!(Instant::now() < deadline, "{what}\n{}", farm.logs());
            std::thread::sleep(Duration::from_millis(1));
        }
    };
    far_worker("the far worker leased nothing", JOB_LIMIT, &|w| {
        w.tasks_leased > 0
    });

    // The far worker's lease expires while it uploads; its result is refused when it lands,
    // as stale, not from an unknown worker: it was still registered.
    let log = farm.path("coordinator-1.log");
    let refused = format!("from {far} refused");
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        let text = std::fs::read_to_string(&log).unwrap();
        if text.contains(&format!("(worker {far}) expired"))
            && text
                .lines()
                .any(|l| l.contains(&refused) && (l.contains("stale") || l.contains("not leased")))
        {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "no result of {far} was refused for its expired lease\n{}",
            farm.logs()
        );
        std::thread::sleep(STATUS_POLL);
    }

    // Each expired lease doubles the time the far worker is allowed for its uploads, and a
    // result that lands measures it: its leases grow until a result fits, and is accepted.
    far_worker(
        "the far worker's leases never grew to fit its uploads",
        Duration::from_secs(180),
        &|w| w.tasks_completed > 0,
    );

    farm.start_worker("near", &[]);
    farm.wait_finished(&id);
    farm.assert_reference_result(&id, false);
    for w in &mut farm.workers {
        assert!(w.running(), "{} died:\n{}", w.what, w.log_text());
    }
}
