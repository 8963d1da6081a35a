//! Store faults, in process: a [`MemoryStore`] fails every write from the Nth on, the job
//! pauses, and once the store is healed it is restored and ends with exactly the map of a run
//! without faults. Stored jobs that cannot be read are listed as damaged and can be deleted.

mod common;

use scatterfarm_coordinator::job::outputs::stored_outputs;
use scatterfarm_coordinator::job::JobState;
use scatterfarm_coordinator::scheduler::{Scheduler, Settings};
use scatterfarm_coordinator::status::{all_statuses, state_name, status_of};
use scatterfarm_coordinator::store::{MemoryStore, Store};
use scatterfarm_engines::cpu::CpuEngine;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Runs the job to its end with one in-process CPU worker; its `materials.npy` and the writes
/// made after its submission. `fault` is the write after the submission to fail from (1 for
/// the first), and how many retries fail before the store is healed.
fn reconstruct(store: &Arc<MemoryStore>, fault: Option<(u64, usize)>) -> (Vec<u8>, u64) {
    let settings = Settings {
        task_seconds: 0.02,
        ..Settings::default()
    };
    let mut s = Scheduler::open(store.clone(), settings).unwrap();
    let (spec, inputs) = common::job();
    let id = s.submit(spec, inputs).unwrap();
    let submitted = store.writes();
    let engine = CpuEngine::new();
    let mut worker = common::register(&mut s, "w", &engine, true);
    let mut failing_rounds = 0;
    let mut paused_seen = false;
    for round in 0.. {
        assert!(round < 100_000, "the job did not end");
        if let Some((from, _)) = fault {
            if round == 0 {
                store.fail_writes_from(submitted + from);
            }
        }
        match s.lease(&worker).unwrap() {
            Ok(task) => {
                let rendered = common::render(&engine, &task);
                // A result may be refused as no longer needed once its job paused.
                let _ = s.complete_and_score(
                    &worker,
                    &task.job,
                    task.piece.task_id,
                    task.piece.attempt,
                    rendered,
                );
            }
            Err(reason) => {
                let status = status_of(&s, &id).unwrap();
                match state_name(status.state) {
                    "finished" => break,
                    "paused" => {
                        paused_seen = true;
                        assert!(
                            status.message.contains("data store failed")
                                && status.message.contains("retried"),
                            "{status:?}"
                        );
                        failing_rounds += 1;
                        if failing_rounds > fault.map_or(0, |f| f.1) {
                            store.heal();
                        }
                        // Time passes: the pause is over. The worker, silent meanwhile, was
                        // forgotten and registers again.
                        s.sweep(Instant::now() + Duration::from_secs(60));
                        worker = common::register(&mut s, "w", &engine, true);
                    }
                    other => {
                        panic!("the job is {other} with nothing to lease ({reason}): {status:?}")
                    }
                }
            }
        }
    }
    assert_eq!(paused_seen, fault.is_some(), "paused or not");
    assert_eq!(s.jobs[&id].checkpoint.state, JobState::Finished);
    let writes = store.writes() - submitted;
    // The outputs are drawn and stored as the farm does it, off the lock, once.
    let due = s.take_due_outputs();
    assert_eq!(due.len(), 1, "the finished job's outputs are due");
    assert!(s.take_due_outputs().is_empty(), "and due once");
    due[0].store(store.as_ref()).unwrap();
    let outputs = stored_outputs(store.as_ref(), &id)
        .unwrap()
        .expect("stored outputs");
    (outputs["materials.npy"].clone(), writes)
}

#[test]
fn a_job_whose_store_fails_pauses_and_resumes_to_the_reference_map() {
    let clean = Arc::new(MemoryStore::new());
    let (reference, writes) = reconstruct(&clean, None);
    assert!(writes > 10, "{writes} writes");
    // The first write (the pin), one in the middle (a score or progress), the last (the
    // finished checkpoint); healed at once, or after a retry that failed too.
    for (from, failing) in [(1, 0), (writes / 2, 1), (writes, 0)] {
        let store = Arc::new(MemoryStore::new());
        let (npy, _) = reconstruct(&store, Some((from, failing)));
        assert!(
            npy == reference,
            "writes failing from {from} (of {writes}): another map"
        );
    }
}

#[test]
fn damaged_jobs_are_listed_as_damaged_and_can_be_deleted() {
    let store = Arc::new(MemoryStore::new());
    store.put_raw_record("j9", b"{\"not a job record\": ");
    store.put_blob("j9", "input/three.toml", b"x").unwrap();
    let mut s = Scheduler::open(store.clone(), Settings::default()).unwrap();
    let all = all_statuses(&s);
    assert_eq!(all.len(), 1);
    assert_eq!(state_name(all[0].state), "damaged");
    assert!(
        all[0].message.contains("damaged") && all[0].message.contains("delete j9"),
        "{:?}",
        all[0]
    );
    let err = s.cancel("j9").unwrap_err().to_string();
    assert!(err.contains("only be deleted"), "{err}");
    s.delete("j9").unwrap();
    assert!(all_statuses(&s).is_empty());
    assert!(store.records().unwrap().is_empty());
    assert_eq!(store.blob("j9", "input/three.toml").unwrap(), None);
    // It stays gone.
    let s = Scheduler::open(store, Settings::default()).unwrap();
    assert!(all_statuses(&s).is_empty());
}
