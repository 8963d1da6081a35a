//! A job that screens by differential renders, in process: its differential renders go only to
//! workers that render them (a GPU worker today does not, and is told why it gets nothing of
//! that job), whole, with the job's target; their change scores are checked before use, and
//! the job ends with the scene found.

mod common;

use scatterfarm_coordinator::job::JobState;
use scatterfarm_coordinator::scheduler::{Rendered, Scheduler, Settings};
use scatterfarm_coordinator::store::{MemoryStore, Store};
use scatterfarm_engines::cpu::CpuEngine;
use scatterfarm_job::spec::JobSpec;
use std::path::Path;
use std::sync::Arc;

const JOB: &str = "scene = \"three.toml\"\npermutations = 1\niterations = 4\n\
    photons_per_iteration = 256\nseed = 7\nsearch = \"likelihood\"\nrefine_sweeps = 2\n\
    refine_screen = \"differential\"\n";

#[test]
fn differential_renders_go_whole_to_workers_that_render_them_and_their_scores_are_checked() {
    let settings = Settings {
        task_seconds: 0.02,
        ..Settings::default()
    };
    let store = Arc::new(MemoryStore::new());
    let mut s = Scheduler::open(store.clone(), settings).unwrap();
    let (_, inputs) = common::job();
    let spec = JobSpec::from_toml(JOB, Path::new("job.toml")).unwrap();
    let id = s.submit(spec, inputs).unwrap();
    let engine = CpuEngine::new();
    // Same engine fingerprint, but it says it does not render differentially (as a worker whose
    // engine has no per-pixel tallies would).
    let plain = common::register(&mut s, "gpu", &engine, false);
    let cpu = common::register(&mut s, "cpu", &engine, true);
    let (mut differential, mut waited, mut refused) = (0, 0, 0);
    for round in 0.. {
        assert!(round < 100_000, "the job did not end");
        match s.lease(&plain).unwrap() {
            Ok(task) => {
                assert!(
                    task.differential.is_none(),
                    "a plain worker got a differential render"
                );
                let rendered = common::render(&engine, &task);
                let (job, t, a) = (task.job.clone(), task.piece.task_id, task.piece.attempt);
                s.complete_and_score(&plain, &job, t, a, rendered).unwrap();
                continue;
            }
            Err(reason) if reason.contains("differential") => waited += 1,
            Err(_) => {}
        }
        let task = match s.lease(&cpu).unwrap() {
            Ok(task) => task,
            Err(_) => break,
        };
        let (job, t, a) = (task.job.clone(), task.piece.task_id, task.piece.attempt);
        let rendered = common::render(&engine, &task);
        if let Some(part) = &task.differential {
            differential += 1;
            let target = &task.scoring.as_ref().expect("the job's target").target;
            assert_eq!(
                target.values.len(),
                task.geometry.sources() * task.geometry.bins()
            );
            assert_eq!(task.piece.first, 0, "a differential render is cut");
            assert_eq!(part.chunk, scatterfarm_model::differential::CHUNK_PHOTONS);
            // The first result of each differential render has one change score too many
            // taken away, then one altered: both are refused, the worker struck once each.
            if differential <= 2 {
                let mut bad: Rendered = common::render(&engine, &task);
                let scores = bad.change_scores.as_mut().unwrap();
                if differential == 1 {
                    scores.pop();
                } else if let Some(d) = scores.iter_mut().flatten().next() {
                    d.value += 1.0;
                } else {
                    scores.clear();
                }
                assert!(s.complete_and_score(&cpu, &job, t, a, bad).is_err());
                refused += 1;
                // The piece comes back after the strike; it is leased again below.
                continue;
            }
        }
        let _ = s.complete_and_score(&cpu, &job, t, a, rendered);
    }
    assert!(
        differential > 2,
        "{differential} differential renders leased"
    );
    assert!(waited > 0, "the plain worker was never told why it waits");
    assert_eq!(refused, 2);
    let job = &s.jobs[&id];
    assert_eq!(
        job.checkpoint.state,
        JobState::Finished,
        "{:?}",
        job.checkpoint
    );
    let report: serde_json::Value =
        serde_json::from_slice(&job.outputs().unwrap()["report.json"]).unwrap();
    assert_eq!(report["pixel_accuracy"], 1.0, "{report:#}");
    // The store kept the scores of the last stages only: level 0's (step 0) are gone.
    let stored = store.scores(&id).unwrap();
    let renders = report["renders"].as_u64().unwrap();
    assert!(
        (stored.len() as u64) < renders && stored.values().all(|(_, step)| *step > 0),
        "{} scores stored for {renders} renders",
        stored.len()
    );
}
