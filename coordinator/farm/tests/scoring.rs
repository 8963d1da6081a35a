//! Scoring off the scheduler's lock, in process: a result that completes a search group hands
//! the group out as [`ScoreWork`]; while it is out, its job leases nothing and the scheduler
//! answers heartbeats; its scores, kept afterwards, give exactly the map of scores made at
//! once. Scores that come back for a cancelled job are dropped. A likelihood job's renders
//! are scored by the workers that render them (their scores come back, not their counts), and
//! end with exactly the map the coordinator's own scores give.

mod common;

use scatterfarm_coordinator::job::scoring::ScoreWork;
use scatterfarm_coordinator::job::JobState;
use scatterfarm_coordinator::scheduler::{Abilities, Scheduler, Settings};
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
    let worker = common::register(&mut s, "w", &engine, true);
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

/// A likelihood job (its refinement screened by direct renders) run by one in-process worker
/// that scores renders or not: the materials, and how many tasks came back as scores.
fn likelihood_job(scores_renders: bool) -> (Vec<u8>, usize) {
    const JOB: &str = "scene = \"three.toml\"\npermutations = 1\niterations = 4\n\
        photons_per_iteration = 256\nseed = 7\nsearch = \"likelihood\"\nrefine_sweeps = 2\n";
    let settings = Settings {
        task_seconds: 0.02,
        ..Settings::default()
    };
    let mut s = Scheduler::open(Arc::new(MemoryStore::new()), settings).unwrap();
    let (_, inputs) = common::job();
    let spec =
        scatterfarm_job::spec::JobSpec::from_toml(JOB, std::path::Path::new("job.toml")).unwrap();
    let id = s.submit(spec, inputs).unwrap();
    let engine = CpuEngine::new();
    let abilities = Abilities {
        renders_differentially: true,
        scores_renders,
    };
    let worker = s.register("w".into(), engine.fingerprint(), 2e6, abilities);
    let mut scored = 0;
    for round in 0.. {
        assert!(round < 100_000, "the job did not end");
        let task = match s.lease(&worker).unwrap() {
            Ok(task) => task,
            Err(why) => {
                eprintln!("no task: {why}");
                break;
            }
        };
        assert!(
            scores_renders || !task.scored,
            "a worker that does not score renders was leased a scored task"
        );
        if task.scored {
            scored += 1;
            assert_eq!(task.piece.first, 0, "a scored task renders all its photons");
            assert!(
                task.scoring.is_some(),
                "a scored task without the job's target"
            );
            let rendered = common::render(&engine, &task);
            assert!(rendered.counts.as_ref().unwrap().is_empty());
            if scored > 1 {
                let (j, t, a) = (task.job.clone(), task.piece.task_id, task.piece.attempt);
                s.complete_and_score(&worker, &j, t, a, rendered).unwrap();
                continue;
            }
            // Counts where scores are due are refused (the piece is leased again).
            let mut wrong = common::render(&engine, &task);
            wrong.render_scores = Ok(Vec::new());
            wrong.counts = Ok(vec![
                scatterfarm_model::CountMatrix::zeros(
                    task.geometry.sources(),
                    task.geometry.bins()
                );
                task.items.len()
            ]);
            let (j, t, a) = (task.job.clone(), task.piece.task_id, task.piece.attempt);
            assert!(s.complete_and_score(&worker, &j, t, a, wrong).is_err());
            continue;
        }
        let rendered = common::render(&engine, &task);
        let (j, t, a) = (task.job.clone(), task.piece.task_id, task.piece.attempt);
        s.complete_and_score(&worker, &j, t, a, rendered).unwrap();
    }
    assert_eq!(s.counters.renders_scored_on_workers > 0, scores_renders);
    (materials(&s, &id), scored)
}

#[test]
fn renders_scored_on_workers_give_the_map_of_scores_made_by_the_coordinator() {
    let (on_workers, scored) = likelihood_job(true);
    let (here, none) = likelihood_job(false);
    assert!(scored > 3, "{scored} scored tasks");
    assert_eq!(none, 0);
    assert!(on_workers == here, "another map");
}
