//! Data folders written by earlier releases (`tests/fixtures/data/`, one folder per release):
//! this build must still open each, restore its jobs and read their results.

use scatterfarm_coordinator::job::{Job, JobState};
use scatterfarm_coordinator::store::{SledStore, Store};
use std::path::{Path, PathBuf};

/// The fixture folders, one per release.
fn fixtures() -> Vec<PathBuf> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/fixtures/data");
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(&root)
        .unwrap_or_else(|e| panic!("cannot list {}: {e}", root.display()))
        .map(|e| e.unwrap().path())
        .filter(|p| p.is_dir())
        .collect();
    dirs.sort();
    dirs
}

/// Copies `from` into `to` (opening a sled folder writes to it; the fixture stays untouched).
fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for entry in std::fs::read_dir(from).unwrap() {
        let entry = entry.unwrap();
        let target = to.join(entry.file_name());
        if entry.file_type().unwrap().is_dir() {
            copy_dir(&entry.path(), &target);
        } else {
            std::fs::copy(entry.path(), target).unwrap();
        }
    }
}

#[test]
fn every_release_data_folder_opens_with_its_finished_job_and_result() {
    let dirs = fixtures();
    assert!(!dirs.is_empty(), "no fixture data folders");
    for dir in dirs {
        let scratch = tempfile::tempdir().unwrap();
        copy_dir(&dir, scratch.path());
        let store =
            SledStore::open(scratch.path()).unwrap_or_else(|e| panic!("{}: {e}", dir.display()));
        let records = store.records().unwrap();
        assert!(!records.is_empty(), "{}: no jobs", dir.display());
        for (id, record) in records {
            let job = Job::restore(id.clone(), &record, &store)
                .unwrap_or_else(|e| panic!("{} job {id}: {e:#}", dir.display()));
            assert_eq!(
                job.checkpoint.state,
                JobState::Finished,
                "{} job {id}",
                dir.display()
            );
            let result = job
                .checkpoint
                .search
                .result()
                .unwrap_or_else(|| panic!("{} job {id}: no result", dir.display()));
            assert!(!result.assignment.is_empty());
            let outputs = job.outputs().unwrap();
            assert!(
                outputs.contains_key("materials.npy") && outputs.contains_key("report.json"),
                "{} job {id}: {:?}",
                dir.display(),
                outputs.keys().collect::<Vec<_>>()
            );
        }
    }
}
