//! Scoring off the scheduler's lock, in process: a result that completes a search group hands
//! the group out as [`ScoreWork`]; while it is out, its job leases nothing and the scheduler
//! answers heartbeats; its scores, kept afterwards, give exactly the map of scores made at
//! once. Scores that come back for a cancelled job are dropped.

mod common;

use scatterfarm_coordinator::job::scoring::ScoreWork;
use scatterfarm_coordinator::job::JobState;
use scatterfarm_coordinator::scheduler::{Scheduler, Settings};
use scatterfarm_coordinator::store::MemoryStore;
use scatterfarm_engines::cpu::CpuEngine;
use scatterfarm_model::Engine;
use std::sync::Arc;

/// How a run treats the groups handed out for scoring.
#[derive(Clone, Copy, PartialEq)]
enum Scoring {
    /// Scored and kept at once.
    AtOnce,
    /// Held while the scheduler is asked for work and heartbeats, then kept.
    Held,
    /// The job is cancelled while the first group is out.
    CancelledMeanwhile,
}

/// Runs the job with one in-process CPU worker; the scheduler and the job's id.
fn run(scoring: Scoring) -> (Scheduler, String) {
    let settings = Settings {
        task_seconds: 0.02,
        ..Settings::default()
    };
    let store = Arc::new(MemoryStore::new());
    let mut s = Scheduler::open(store, settings).unwrap();
    let (spec, inputs) = common::job();
    let id = s.submit(spec, inputs).unwrap();
    let engine = CpuEngine::new();
    let worker = s.register("w".into(), engine.fingerprint(), 2e6, true);
    let mut handed_out = 0;
    for round in 0.. {
        assert!(round < 100_000, "the job did not end");
        let task = match s.lease(&worker).unwrap() {
            Ok(task) => task,
            Err(_) => break,
        };
        let rendered = common::render(&engine, &task);
        let work: Option<ScoreWork> = s
            .complete(
                &worker,
                &task.job,
                task.piece.task_id,
                task.piece.attempt,
                rendered,
            )
            .unwrap();
        let Some(work) = work else { continue };
        handed_out += 1;
        assert_eq!(work.job, id);
        match scoring {
            Scoring::AtOnce => {}
            Scoring::Held => {
                assert!(s.jobs[&id].is_scoring());
                assert!(
                    s.liveness.touch(&worker, std::time::Instant::now()),
                    "the worker is known while scores are out"
                );
                let nothing = s.lease(&worker).unwrap();
                assert!(
                    nothing.is_err(),
                    "a job waiting for its scores leased more work"
                );
            }
            Scoring::CancelledMeanwhile => {
                s.cancel(&id).unwrap();
                s.scored(work.run());
                assert_eq!(s.jobs[&id].checkpoint.state, JobState::Cancelled);
                assert!(!s.jobs[&id].is_scoring());
                assert!(s.lease(&worker).unwrap().is_err(), "a cancelled job leased");
                return (s, id);
            }
        }
        s.scored(work.run());
    }
    assert!(handed_out > 3, "{handed_out} groups scored");
    (s, id)
}

fn materials(s: &Scheduler, id: &str) -> Vec<u8> {
    let job = &s.jobs[id];
    assert_eq!(job.checkpoint.state, JobState::Finished);
    job.outputs().unwrap()["materials.npy"].clone()
}

#[test]
fn scores_made_off_the_lock_give_the_map_of_scores_made_at_once() {
    let (at_once, a) = run(Scoring::AtOnce);
    let (held, b) = run(Scoring::Held);
    assert!(
        materials(&at_once, &a) == materials(&held, &b),
        "another map"
    );
}

#[test]
fn scores_that_come_back_for_a_cancelled_job_are_dropped() {
    run(Scoring::CancelledMeanwhile);
}
