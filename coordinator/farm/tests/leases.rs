//! Lease sizing in process: a lease that expires doubles its worker's transfer allowance (at
//! least to the shortest lease), so a worker whose results crawl up a slow link gets leases it
//! can meet; results that come back promptly bring the allowance down again.

mod common;

use scatterfarm_coordinator::scheduler::{Scheduler, Settings, TaskOut};
use scatterfarm_coordinator::store::MemoryStore;
use scatterfarm_engines::cpu::CpuEngine;
use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

fn unix_ms() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

/// Seconds from now to the task's lease deadline.
fn lease_seconds(task: &TaskOut) -> f64 {
    (task.deadline_unix_ms as f64 - unix_ms() as f64) / 1e3
}

#[test]
fn expired_leases_lengthen_the_next_and_prompt_results_shorten_them_again() {
    let settings = Settings {
        task_seconds: 0.01,
        min_lease: Duration::from_secs(1),
        ..Settings::default()
    };
    let mut s = Scheduler::open(Arc::new(MemoryStore::new()), settings).unwrap();
    let (spec, inputs) = common::job();
    let id = s.submit(spec, inputs).unwrap();
    let engine = CpuEngine::new();
    let worker = common::register(&mut s, "slow-link", &engine, true);
    let first = s.lease(&worker).unwrap().unwrap();
    assert_eq!(first.job, id);
    let shortest = lease_seconds(&first);
    assert!((0.8..=1.05).contains(&shortest), "first lease {shortest} s");

    // Two leases expire unanswered: the allowance goes to 1 s, then 2 s, added twice.
    let mut expected = 1.0;
    for round in 0..2 {
        // Heard from (its heartbeats pass) when the lease is found expired.
        let later = Instant::now() + Duration::from_secs(30 * (round + 1));
        assert!(s.liveness.touch(&worker, later));
        s.sweep(later);
        let again = s.lease(&worker).unwrap().unwrap();
        assert_eq!(
            again.piece.attempt,
            round as u32 + 2,
            "the expired piece again"
        );
        let secs = lease_seconds(&again);
        let want = 1.0 + 2.0 * expected;
        assert!(
            (want - 0.2..=want + 0.05).contains(&secs),
            "lease after {} expiries: {secs} s, expected {want}",
            round + 1
        );
        expected *= 2.0;
        if round == 1 {
            // Prompt results: the allowance halves with each (a moving average of about 0).
            let mut task = again;
            let mut last = secs;
            for _ in 0..6 {
                let rendered = common::render(&engine, &task);
                s.complete(
                    &worker,
                    &task.job,
                    task.piece.task_id,
                    task.piece.attempt,
                    rendered,
                )
                .unwrap();
                let Ok(next) = s.lease(&worker).unwrap() else {
                    break;
                };
                last = lease_seconds(&next);
                task = next;
            }
            assert!(
                last < 1.0 + 2.0 * 4.0 / 8.0,
                "after prompt results the lease is still {last} s"
            );
        }
    }
}
