//! Durable coordinator state behind a small trait: job records (parameters and input files),
//! job progress (search state after each step, pinned engine, ε), scores of completed renders
//! keyed by render identity, setup products and final outputs.
//!
//! Count matrices are never stored: a `kill -9` loses at most the renders in progress.
//!
//! - [`disk`]: the [`SledStore`] of a data folder, which checks a schema version when it opens.
//! - [`memory`]: the [`MemoryStore`], which keeps everything in memory and can be told to fail
//!   writes (the store-fault tests, and the fuzz bench's restores).
//! - [`score_codec`]: how a render's score is written as bytes, and read back.

pub mod disk;
pub mod memory;
pub mod score_codec;

pub use disk::SledStore;
pub use memory::MemoryStore;
pub use score_codec::{decode_score, encode_score};

use scatterfarm_search::Score;
use std::collections::BTreeMap;
use thiserror::Error;

/// The layout of the data this build writes. A data folder of another version is refused.
pub const SCHEMA_VERSION: u32 = 2;

#[derive(Debug, Error)]
pub enum StoreError {
    #[error("cannot open the data folder {path}: {source}")]
    Open { path: String, source: sled::Error },
    #[error(
        "the data folder {path} has schema version {found}, this build reads version {expected}: \
         use a scatterfarm of the version that wrote it, or a new data folder"
    )]
    Schema {
        path: String,
        found: u32,
        expected: u32,
    },
    #[error("the data store failed: {0}")]
    Sled(#[from] sled::Error),
    #[error("a stored {what} is damaged: {detail}")]
    Damaged { what: &'static str, detail: String },
    /// A write the [`MemoryStore`] was told to fail.
    #[error("write {0} failed: the store was told to fail it (a test of store faults)")]
    Injected(u64),
}

/// What the coordinator keeps across restarts. Keys are job ids; values are opaque bytes the
/// coordinator encodes.
pub trait Store: Send + Sync {
    /// A new, never reused job id.
    fn new_job_id(&self) -> Result<String, StoreError>;
    /// A new task id, never handed out before by any coordinator run on this store.
    fn new_task_id(&self) -> Result<u64, StoreError>;
    /// Stores a job's immutable record (parameters and input files).
    fn put_record(&self, job: &str, record: &[u8]) -> Result<(), StoreError>;
    /// Every stored job's record.
    fn records(&self) -> Result<Vec<(String, Vec<u8>)>, StoreError>;
    /// Replaces a job's progress (state after a step). Reads see it at once; it is durable
    /// after the next [`Store::flush`] (the coordinator writes it under its lock and flushes
    /// after releasing it, before answering the request that caused it).
    fn put_progress(&self, job: &str, progress: &[u8]) -> Result<(), StoreError>;
    fn progress(&self, job: &str) -> Result<Option<Vec<u8>>, StoreError>;
    /// A named blob of a job (setup products such as the target, final outputs).
    fn put_blob(&self, job: &str, name: &str, bytes: &[u8]) -> Result<(), StoreError>;
    fn blob(&self, job: &str, name: &str) -> Result<Option<Vec<u8>>, StoreError>;
    /// The score of a completed render, keyed by its identity, with the first request index
    /// of the search step it was rendered for.
    fn put_score(
        &self,
        job: &str,
        identity: &[u8; 32],
        score: Score,
        step: u64,
    ) -> Result<(), StoreError>;
    fn scores(&self, job: &str) -> Result<BTreeMap<[u8; 32], (Score, u64)>, StoreError>;
    /// Removes a job's scores rendered for steps before `step` (a stage its search has left,
    /// [`scatterfarm_search::Search::stage_start`]); returns how many. A score that cannot be
    /// read is left for [`Store::scores`] to report.
    fn forget_scores_before(&self, job: &str, step: u64) -> Result<usize, StoreError>;
    /// Removes everything of a job.
    fn delete_job(&self, job: &str) -> Result<(), StoreError>;
    /// Makes every write so far durable.
    fn flush(&self) -> Result<(), StoreError>;
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Scores of steps before the given one go, of that job only; damaged ones stay for
    /// [`Store::scores`] to report.
    fn forgets_only_earlier_steps_of_one_job(s: &dyn Store) {
        let (a, b) = (s.new_job_id().unwrap(), s.new_job_id().unwrap());
        for (i, step) in [0u64, 3, 7, 7, 12].into_iter().enumerate() {
            s.put_score(&a, &[i as u8; 32], Score::exact(i as f64), step)
                .unwrap();
            s.put_score(&b, &[i as u8; 32], Score::exact(i as f64), step)
                .unwrap();
        }
        assert_eq!(s.forget_scores_before(&a, 7).unwrap(), 2);
        assert_eq!(s.forget_scores_before(&a, 7).unwrap(), 0);
        let kept: Vec<u64> = s.scores(&a).unwrap().values().map(|(_, st)| *st).collect();
        assert_eq!(kept, vec![7, 7, 12]);
        assert_eq!(s.scores(&b).unwrap().len(), 5, "another job's scores stay");
        assert_eq!(s.forget_scores_before(&a, 100).unwrap(), 3);
        assert!(s.scores(&a).unwrap().is_empty());
    }

    #[test]
    fn the_memory_store_forgets_only_earlier_steps_of_one_job() {
        let s = MemoryStore::new();
        forgets_only_earlier_steps_of_one_job(&s);
        s.put_raw_score("job-x", &[1; 32], b"short");
        assert_eq!(s.forget_scores_before("job-x", 100).unwrap(), 0);
        assert!(
            s.scores("job-x").is_err(),
            "the damaged score is still reported"
        );
    }

    #[test]
    fn the_sled_store_forgets_only_earlier_steps_of_one_job() {
        let dir = tempfile::tempdir().unwrap();
        let s = SledStore::open(dir.path()).unwrap();
        forgets_only_earlier_steps_of_one_job(&s);
    }
}
