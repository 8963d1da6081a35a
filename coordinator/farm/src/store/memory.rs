//! A store in memory. It loses everything when dropped, so it serves tests and the fuzz bench,
//! not a coordinator: [`MemoryStore::fail_writes_from`] makes every write from the Nth on fail
//! (a disk that filled up) until [`MemoryStore::heal`], and [`MemoryStore::put_raw_record`] and
//! [`MemoryStore::put_raw_score`] plant damaged records.

use super::score_codec::{decode_score, encode_score};
use super::{Store, StoreError};
use scatterfarm_search::Score;
use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Mutex, MutexGuard};

/// Records of one kind, by job id and name.
type Tree = BTreeMap<(String, Vec<u8>), Vec<u8>>;

/// Everything a [`MemoryStore`] holds.
#[derive(Debug, Default)]
struct Trees {
    records: BTreeMap<String, Vec<u8>>,
    progress: BTreeMap<String, Vec<u8>>,
    blobs: Tree,
    scores: Tree,
}

/// A [`Store`] in memory, with injected write faults.
#[derive(Debug, Default)]
pub struct MemoryStore {
    trees: Mutex<Trees>,
    ids: AtomicU64,
    /// Writes so far (failed ones included).
    writes: AtomicU64,
    /// The first write (counted from 1) that fails; 0 for none.
    fail_from: AtomicU64,
}

impl MemoryStore {
    pub fn new() -> MemoryStore {
        MemoryStore::default()
    }

    /// Every write from the `n`th (counted from 1 over the store's life) on fails, until
    /// [`Self::heal`].
    pub fn fail_writes_from(&self, n: u64) {
        self.fail_from.store(n.max(1), Ordering::SeqCst);
    }

    /// Writes succeed again.
    pub fn heal(&self) {
        self.fail_from.store(0, Ordering::SeqCst);
    }

    /// Writes so far, failed ones included.
    pub fn writes(&self) -> u64 {
        self.writes.load(Ordering::SeqCst)
    }

    /// Stores `bytes` as `job`'s record as they are (a damaged record, for tests).
    pub fn put_raw_record(&self, job: &str, bytes: &[u8]) {
        self.trees().records.insert(job.into(), bytes.to_vec());
    }

    /// Stores `bytes` as a score of `job` as they are (a damaged score, for tests).
    pub fn put_raw_score(&self, job: &str, identity: &[u8; 32], bytes: &[u8]) {
        self.trees()
            .scores
            .insert(key(job, identity), bytes.to_vec());
    }

    fn trees(&self) -> MutexGuard<'_, Trees> {
        self.trees.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Counts a write; the injected fault when it is one to fail.
    fn write(&self) -> Result<MutexGuard<'_, Trees>, StoreError> {
        let n = self.writes.fetch_add(1, Ordering::SeqCst) + 1;
        let from = self.fail_from.load(Ordering::SeqCst);
        if from != 0 && n >= from {
            return Err(StoreError::Injected(n));
        }
        Ok(self.trees())
    }
}

fn key(job: &str, name: &[u8]) -> (String, Vec<u8>) {
    (job.to_string(), name.to_vec())
}

impl Store for MemoryStore {
    fn new_job_id(&self) -> Result<String, StoreError> {
        Ok(format!("j{}", self.ids.fetch_add(1, Ordering::SeqCst) + 1))
    }

    fn new_task_id(&self) -> Result<u64, StoreError> {
        Ok(self.ids.fetch_add(1, Ordering::SeqCst) + 1)
    }

    fn put_record(&self, job: &str, record: &[u8]) -> Result<(), StoreError> {
        self.write()?.records.insert(job.into(), record.to_vec());
        Ok(())
    }

    fn records(&self) -> Result<Vec<(String, Vec<u8>)>, StoreError> {
        Ok(self.trees().records.clone().into_iter().collect())
    }

    fn put_progress(&self, job: &str, progress: &[u8]) -> Result<(), StoreError> {
        self.write()?.progress.insert(job.into(), progress.to_vec());
        Ok(())
    }

    fn progress(&self, job: &str) -> Result<Option<Vec<u8>>, StoreError> {
        Ok(self.trees().progress.get(job).cloned())
    }

    fn put_blob(&self, job: &str, name: &str, bytes: &[u8]) -> Result<(), StoreError> {
        self.write()?
            .blobs
            .insert(key(job, name.as_bytes()), bytes.to_vec());
        Ok(())
    }

    fn blob(&self, job: &str, name: &str) -> Result<Option<Vec<u8>>, StoreError> {
        Ok(self.trees().blobs.get(&key(job, name.as_bytes())).cloned())
    }

    fn put_score(
        &self,
        job: &str,
        identity: &[u8; 32],
        score: Score,
        step: u64,
    ) -> Result<(), StoreError> {
        self.write()?
            .scores
            .insert(key(job, identity), encode_score(&score, step));
        Ok(())
    }

    fn scores(&self, job: &str) -> Result<BTreeMap<[u8; 32], (Score, u64)>, StoreError> {
        let trees = self.trees();
        let mut out = BTreeMap::new();
        for ((j, id), v) in &trees.scores {
            if j != job {
                continue;
            }
            let id = <[u8; 32]>::try_from(id.as_slice()).map_err(|_| StoreError::Damaged {
                what: "score key",
                detail: format!("{} bytes", id.len()),
            })?;
            out.insert(id, decode_score(v)?);
        }
        Ok(out)
    }

    fn forget_scores_before(&self, job: &str, step: u64) -> Result<usize, StoreError> {
        let mut t = self.write()?;
        let before = t.scores.len();
        t.scores
            .retain(|(j, _), v| j != job || decode_score(v).map_or(true, |(_, s)| s >= step));
        Ok(before - t.scores.len())
    }

    fn delete_job(&self, job: &str) -> Result<(), StoreError> {
        let mut t = self.write()?;
        t.records.remove(job);
        t.progress.remove(job);
        t.blobs.retain(|(j, _), _| j != job);
        t.scores.retain(|(j, _), _| j != job);
        Ok(())
    }

    fn flush(&self) -> Result<(), StoreError> {
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn writes_fail_from_the_nth_until_healed_and_reads_go_on() {
        let s = MemoryStore::new();
        s.put_blob("j", "a", b"1").unwrap();
        s.fail_writes_from(3);
        s.put_blob("j", "b", b"2").unwrap();
        let err = s.put_blob("j", "c", b"3").unwrap_err();
        assert!(matches!(err, StoreError::Injected(3)), "{err}");
        assert!(s.put_progress("j", b"p").is_err());
        assert_eq!(s.blob("j", "b").unwrap().as_deref(), Some(&b"2"[..]));
        assert_eq!(s.blob("j", "c").unwrap(), None);
        s.heal();
        s.put_blob("j", "c", b"3").unwrap();
        assert_eq!(s.writes(), 5);
        s.delete_job("j").unwrap();
        assert_eq!(s.blob("j", "a").unwrap(), None);
    }
}
