//! The farm across processes: `scatterfarm coordinator`, `scatterfarm worker`s and the client
//! commands as real processes on loopback, and fake workers that speak the protocol from here
//! (late, malformed and impossible results, another protocol version).
//!
//! Every job is the same small reconstruction (grid 4, 16 positions × 3 directions, three
//! materials), and whatever happens to the farm on the way it must end with exactly what
//! `scatterfarm reconstruct` finds in one process with the same seed: a byte-identical
//! `materials.npy` and the same report.
//!
//! Every process a test starts is killed when the test ends, passing or panicking. Their logs
//! are kept in the test's temporary folder and shown when an assertion fails. The harness is
//! [`crate::harness::farm`], [`crate::harness::rpc`] and [`crate::harness::reference`].

use crate::harness::farm::{fraction, Farm, JOB_LIMIT};
use crate::harness::reference::reference;
use crate::harness::rpc::{assert_code, dark_counts, matrix, task_sources, Rpc};
use crate::harness::scenes::{job_toml, Search, THREE};
use crate::harness::tls::certificates;
use scatterfarm_proto::v1 as pb;
use serde_json::Value;
use std::time::{Duration, Instant};
use tonic::Code;

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
fn a_coordinator_killed_four_times_resumes_to_the_same_result() {
    let mut farm = Farm::start(&["--task-seconds", "0.05"]);
    let id = farm.submit();

    // 1: while preparing. No worker runs yet, so the job cannot have left it.
    assert_eq!(farm.status(&id)["state"], "preparing");
    farm.kill_coordinator();
    farm.start_coordinator();
    let after = farm.status(&id);
    assert_eq!(after["state"], "preparing", "{after:#}");

    // 2: with a render leased (polled over gRPC; preparing may be over by then under load).
    farm.start_worker("a", &[]);
    farm.start_worker("b", &[]);
    farm.wait_workers(&["a", "b"]);
    let rpc = Rpc::connect(&farm.address);
    let deadline = Instant::now() + JOB_LIMIT;
    let before = loop {
        let s = rpc.status(&id);
        if s.workers_busy > 0 {
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

    // 3 and 4: past 20 % and 70 % of the renders.
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

/// How long the workers of [`finished_through_a_restart`] run between two status reads.
const STEP: std::time::Duration = std::time::Duration::from_millis(20);

/// Submits `job_file` to a farm of two workers, kills the coordinator once the job has answered
/// more than `mark` of its requests, starts it again on the same data and waits for the job to
/// finish: the farm and the job's id.
fn finished_through_a_restart(job_file: &str, mark: f64) -> (Farm, String) {
    let mut farm = Farm::start(&["--task-seconds", "0.05"]);
    farm.start_worker("a", &[]);
    farm.start_worker("b", &[]);
    farm.wait_workers(&["a", "b"]);
    let id = farm.submit_file(job_file);
    // The workers run in short steps and are stopped (SIGSTOP) while the status is read, so a
    // short job cannot pass the mark, or end, between two polls on a loaded machine.
    let what = format!("{mark} of the requests");
    let deadline = std::time::Instant::now() + JOB_LIMIT;
    let before = loop {
        for w in &farm.workers {
            w.signal("STOP");
        }
        let s = farm.status(&id);
        assert!(
            s["state"] != "finished" && s["state"] != "failed",
            "job {id} ended before {what}: {s:#}\n{}",
            farm.logs()
        );
        if s["state"] == "searching" && fraction(&s) > mark {
            break s;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "job {id}: no {what} within {JOB_LIMIT:?}: {s:#}\n{}",
            farm.logs()
        );
        for w in &farm.workers {
            w.signal("CONT");
        }
        std::thread::sleep(STEP);
    };
    farm.kill_coordinator();
    for w in &farm.workers {
        w.signal("CONT");
    }
    farm.start_coordinator();
    let after = farm.status(&id);
    assert!(
        after["renders_done"].as_u64() >= before["renders_done"].as_u64(),
        "before the kill: {before:#}\nafter the restart: {after:#}"
    );
    farm.wait_finished(&id);
    (farm, id)
}

#[test]
fn a_fast_job_through_a_restart_ends_as_the_fast_search_in_one_process() {
    // Racing (first stages extended by their contenders' groups), re-scoring, early step 2
    // and common random numbers, across processes and a coordinator killed mid-search, which
    // loses the first-stage counts it held.
    let (farm, id) = finished_through_a_restart("job/fast.toml", 0.2);
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

/// Issue 19: a job whose refinement screens by differential renders, across processes: the
/// coordinator sends each differential render whole with the job's target (once per worker),
/// the workers score its changes where the counts are, and a coordinator killed during the
/// search resumes from the stored change scores; the job ends exactly as in one process.
#[test]
fn a_differential_job_through_a_restart_ends_as_in_one_process() {
    let (farm, id) = finished_through_a_restart("job/differential.toml", 0.5);
    farm.assert_result_of(Search::Differential, &id, true);
    let (report, _) = farm.result(&id);
    assert_eq!(report["pixel_accuracy"], 1.0, "{report:#}");
    let reweighted: u64 = report["refinement"]
        .as_array()
        .expect("the sweeps are reported")
        .iter()
        .map(|s| s["reweighted"].as_u64().unwrap())
        .sum();
    assert!(reweighted > 0, "{report:#}");
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
fn lease_requests_that_list_too_many_cached_jobs_are_refused_and_the_worker_still_leases() {
    let farm = Farm::start(&[]);
    let rpc = Rpc::connect(&farm.address);
    let fake = rpc.register_fake("many-cached");
    let id = farm.submit();
    let lease = |cached_jobs: Vec<String>, cached_targets: Vec<String>| {
        let request = pb::LeaseRequest {
            worker_id: fake.clone(),
            cached_jobs,
            cached_targets,
        };
        rpc.worker_call(|mut w| async move { w.lease(request).await })
    };
    let many: Vec<String> = (0..=scatterfarm_proto::convert::MAX_CACHED_LISTED)
        .map(|i| format!("j{i}"))
        .collect();
    let message = assert_code(lease(many.clone(), Vec::new()), Code::InvalidArgument);
    assert!(
        message.contains("cached_jobs") && message.contains(&many.len().to_string()),
        "{message}"
    );
    let message = assert_code(lease(Vec::new(), many), Code::InvalidArgument);
    assert!(message.contains("cached_targets"), "{message}");
    let long = "j".repeat(scatterfarm_proto::convert::MAX_JOB_ID_BYTES + 1);
    let message = assert_code(
        lease(vec![id.clone(), long], Vec::new()),
        Code::InvalidArgument,
    );
    assert!(
        message.contains("entry 1") && message.contains("bytes"),
        "{message}"
    );
    // Nothing was leased by the refused requests: the first lease that lists within the limits
    // gets the job's first task.
    let task = rpc.lease(&fake);
    assert_eq!(task.job_id, id);
    assert_eq!(task.attempt, 1);
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

    // Three bad results: the fake is blocked for this job, which still has work; registering
    // again under the same name does not clear that, nor does a coordinator restart.
    let blocked = |rpc: &Rpc, fake: &str, when: &str| {
        let response = rpc.try_lease(fake);
        assert!(
            response.task.is_none() && response.reason.contains("blocked"),
            "{when}: a worker that sent 3 bad results got {:?} ({})",
            response.task,
            response.reason
        );
    };
    blocked(&rpc, &fake, "at once");
    let fake = rpc.register_fake("bad-results");
    blocked(&rpc, &fake, "registered again");
    drop(rpc);
    farm.kill_coordinator();
    farm.start_coordinator();
    let rpc = Rpc::connect(&farm.address);
    let fake = rpc.register_fake("bad-results");
    blocked(&rpc, &fake, "after a restart");

    // A real worker renders the job, refused pieces included.
    farm.start_worker("real", &[]);
    farm.wait_finished(&id);
    farm.assert_reference_result(&id, false);
}

#[test]
fn a_task_that_never_comes_back_fails_its_job_naming_it_and_task_ids_are_never_reused() {
    let mut farm = Farm::start(&["--task-seconds", "0.05", "--max-attempts", "3"]);
    let rpc = Rpc::connect(&farm.address);
    let fake = rpc.register_fake("gives-back");
    let id = farm.submit();

    // Task ids of a restarted coordinator are new.
    let before = rpc.lease(&fake);
    drop(rpc);
    farm.kill_coordinator();
    farm.start_coordinator();
    let rpc = Rpc::connect(&farm.address);
    let fake = rpc.register_fake("gives-back");
    let first = rpc.lease(&fake);
    assert!(
        first.task_id > before.task_id,
        "task {} after a restart, {} before it",
        first.task_id,
        before.task_id
    );

    // The same piece, given back three times: the job fails, naming it.
    let mut task = first.clone();
    for attempt in 1..=3 {
        assert_eq!(task.attempt, attempt, "{task:?}");
        rpc.release(&fake, &task, "the engine crashed on it");
        if attempt < 3 {
            task = rpc.lease(&fake);
            assert_eq!(task.task_id, first.task_id);
        }
    }
    let status = farm.status(&id);
    assert_eq!(status["state"], "failed", "{status:#}");
    let message = status["message"].as_str().unwrap_or_default();
    assert!(
        message.contains(&format!("task {}", first.task_id))
            && message.contains("3 times")
            && message.contains("the engine crashed on it")
            && message.contains("--max-attempts"),
        "{status:#}"
    );
    // Nothing of it is leased any more.
    assert!(rpc.try_lease(&fake).task.is_none());
}

#[test]
fn a_job_past_the_coordinators_photon_budget_fails_saying_so() {
    let mut farm = Farm::start(&["--task-seconds", "0.05", "--max-job-photons", "100000"]);
    farm.start_worker("a", &[]);
    let id = farm.submit();
    let s = farm.wait_for(&id, "its end", |s| {
        s["state"] != "preparing" && s["state"] != "searching"
    });
    assert_eq!(s["state"], "failed", "{s:#}");
    let message = s["message"].as_str().unwrap_or_default();
    assert!(
        message.contains("--max-job-photons") && message.contains("100000"),
        "{s:#}"
    );
}

#[test]
fn malformed_job_files_are_refused_and_nothing_is_stored() {
    let farm = Farm::start(&[]);
    let good = job_toml();
    std::fs::write(
        farm.path("job/bad-scene.toml"),
        THREE.replace("\"...b\"", "\"..xb\""),
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
            &[("three.toml", THREE)],
        ),
        Code::InvalidArgument,
    );
    assert!(message.contains("permutation"), "{message}");
    let bad_scene = THREE.replace("\"...b\"", "\"..xb\"");
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
