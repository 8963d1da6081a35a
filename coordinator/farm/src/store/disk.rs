//! The sled store of a data folder: one tree per kind of record, job-prefixed keys, a schema
//! version checked on open. Records, blobs and deletions are flushed before they return;
//! progress and scores, written under the coordinator's lock after every step, become durable
//! at the next [`Store::flush`], which the coordinator calls once the lock is released.

use super::score_codec::{decode_score, encode_score};
use super::{Store, StoreError, SCHEMA_VERSION};
use scatterfarm_search::Score;
use std::collections::BTreeMap;
use std::path::Path;

/// The sled store of a data folder.
pub struct SledStore {
    db: sled::Db,
    records: sled::Tree,
    progress: sled::Tree,
    blobs: sled::Tree,
    scores: sled::Tree,
}

const SCHEMA_KEY: &[u8] = b"schema_version";

fn prefixed(job: &str, rest: &[u8]) -> Vec<u8> {
    let mut k = Vec::with_capacity(job.len() + 1 + rest.len());
    k.extend_from_slice(job.as_bytes());
    k.push(0);
    k.extend_from_slice(rest);
    k
}

fn prefix(job: &str) -> Vec<u8> {
    prefixed(job, &[])
}

impl SledStore {
    /// Opens (or creates) the store in `dir`, checking its schema version.
    pub fn open(dir: &Path) -> Result<SledStore, StoreError> {
        let path = dir.display().to_string();
        let db = sled::open(dir.join("store")).map_err(|source| StoreError::Open {
            path: path.clone(),
            source,
        })?;
        match db.get(SCHEMA_KEY)? {
            None => {
                db.insert(SCHEMA_KEY, &SCHEMA_VERSION.to_le_bytes())?;
                db.flush()?;
            }
            Some(v) => {
                let found = <[u8; 4]>::try_from(v.as_ref())
                    .map(u32::from_le_bytes)
                    .map_err(|_| StoreError::Damaged {
                        what: "schema version",
                        detail: format!("{} bytes", v.len()),
                    })?;
                if found != SCHEMA_VERSION {
                    return Err(StoreError::Schema {
                        path,
                        found,
                        expected: SCHEMA_VERSION,
                    });
                }
            }
        }
        Ok(SledStore {
            records: db.open_tree("records")?,
            progress: db.open_tree("progress")?,
            blobs: db.open_tree("blobs")?,
            scores: db.open_tree("scores")?,
            db,
        })
    }
}

impl Store for SledStore {
    fn new_job_id(&self) -> Result<String, StoreError> {
        // sled ids are unique across restarts; a short random tail keeps ids of different data
        // folders apart.
        let n = self.db.generate_id()?;
        let tail = crate::nonce() as u16;
        Ok(format!("j{n}-{tail:04x}"))
    }

    fn new_task_id(&self) -> Result<u64, StoreError> {
        // sled's ids are monotonic across restarts: recovery skips past every id it may have
        // handed out before a crash.
        Ok(self.db.generate_id()?)
    }

    fn put_record(&self, job: &str, record: &[u8]) -> Result<(), StoreError> {
        self.records.insert(job.as_bytes(), record)?;
        self.db.flush()?;
        Ok(())
    }

    fn records(&self) -> Result<Vec<(String, Vec<u8>)>, StoreError> {
        self.records
            .iter()
            .map(|kv| {
                let (k, v) = kv?;
                Ok((String::from_utf8_lossy(&k).into_owned(), v.to_vec()))
            })
            .collect()
    }

    fn put_progress(&self, job: &str, progress: &[u8]) -> Result<(), StoreError> {
        // Not flushed here: the caller flushes outside the scheduler's lock.
        self.progress.insert(job.as_bytes(), progress)?;
        Ok(())
    }

    fn progress(&self, job: &str) -> Result<Option<Vec<u8>>, StoreError> {
        Ok(self.progress.get(job.as_bytes())?.map(|v| v.to_vec()))
    }

    fn put_blob(&self, job: &str, name: &str, bytes: &[u8]) -> Result<(), StoreError> {
        self.blobs.insert(prefixed(job, name.as_bytes()), bytes)?;
        self.db.flush()?;
        Ok(())
    }

    fn blob(&self, job: &str, name: &str) -> Result<Option<Vec<u8>>, StoreError> {
        Ok(self
            .blobs
            .get(prefixed(job, name.as_bytes()))?
            .map(|v| v.to_vec()))
    }

    fn put_score(
        &self,
        job: &str,
        identity: &[u8; 32],
        score: Score,
        step: u64,
    ) -> Result<(), StoreError> {
        // Not flushed here: the next flush makes it durable, and a lost score is re-rendered.
        self.scores
            .insert(prefixed(job, identity), encode_score(&score, step))?;
        Ok(())
    }

    fn scores(&self, job: &str) -> Result<BTreeMap<[u8; 32], (Score, u64)>, StoreError> {
        let p = prefix(job);
        let mut out = BTreeMap::new();
        for kv in self.scores.scan_prefix(&p) {
            let (k, v) = kv?;
            let id = <[u8; 32]>::try_from(&k[p.len()..]).map_err(|_| StoreError::Damaged {
                what: "score key",
                detail: format!("{} bytes", k.len()),
            })?;
            let (score, step) = decode_score(&v)?;
            out.insert(id, (score, step));
        }
        Ok(out)
    }

    fn forget_scores_before(&self, job: &str, step: u64) -> Result<usize, StoreError> {
        // Not flushed here: a score that comes back after a crash is forgotten again.
        let mut old = Vec::new();
        for kv in self.scores.scan_prefix(prefix(job)) {
            let (k, v) = kv?;
            if decode_score(&v).is_ok_and(|(_, s)| s < step) {
                old.push(k);
            }
        }
        for k in &old {
            self.scores.remove(k)?;
        }
        Ok(old.len())
    }

    fn delete_job(&self, job: &str) -> Result<(), StoreError> {
        self.records.remove(job.as_bytes())?;
        self.progress.remove(job.as_bytes())?;
        let p = prefix(job);
        for tree in [&self.blobs, &self.scores] {
            let keys: Vec<sled::IVec> = tree
                .scan_prefix(&p)
                .keys()
                .collect::<Result<_, sled::Error>>()?;
            for k in keys {
                tree.remove(k)?;
            }
        }
        self.db.flush()?;
        Ok(())
    }

    fn flush(&self) -> Result<(), StoreError> {
        self.db.flush()?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use scatterfarm_search::Secondary;

    /// Opens `dir` again in this process. sled's flusher thread of the store just dropped may
    /// still hold the folder's lock for a moment on a loaded machine (a new process never
    /// meets that), so this retries for up to five seconds.
    fn reopen(dir: &Path) -> SledStore {
        let until = std::time::Instant::now() + std::time::Duration::from_secs(5);
        loop {
            match SledStore::open(dir) {
                Ok(s) => return s,
                Err(e) if std::time::Instant::now() < until => {
                    eprintln!("reopening: {e}; again");
                    std::thread::sleep(std::time::Duration::from_millis(50));
                }
                Err(e) => panic!("{e}"),
            }
        }
    }

    #[test]
    fn survives_reopen_and_keeps_jobs_apart() {
        let dir = tempfile::tempdir().unwrap();
        let (a, b);
        {
            let s = SledStore::open(dir.path()).unwrap();
            a = s.new_job_id().unwrap();
            b = s.new_job_id().unwrap();
            assert_ne!(a, b);
            s.put_record(&a, b"rec-a").unwrap();
            s.put_record(&b, b"rec-b").unwrap();
            s.put_progress(&a, b"p1").unwrap();
            s.put_progress(&a, b"p2").unwrap();
            s.put_score(&a, &[7; 32], Score::exact(0.25), 3).unwrap();
            s.put_score(
                &b,
                &[7; 32],
                Score {
                    value: 0.5,
                    std_error: 0.125,
                    // A tiebreak's score (40-byte records).
                    secondary: Some(Secondary {
                        value: -12.5,
                        std_error: 0.75,
                    }),
                    blocks: Vec::new(),
                    changes: Vec::new(),
                },
                4,
            )
            .unwrap();
            s.put_blob(&a, "target", b"xyz").unwrap();
            s.flush().unwrap();
        }
        let s = reopen(dir.path());
        assert_eq!(s.records().unwrap().len(), 2);
        assert_eq!(s.progress(&a).unwrap().as_deref(), Some(&b"p2"[..]));
        assert_eq!(
            s.scores(&a).unwrap().get(&[7; 32]),
            Some(&(Score::exact(0.25), 3))
        );
        assert_eq!(
            s.scores(&b).unwrap().get(&[7; 32]),
            Some(&(
                Score {
                    value: 0.5,
                    std_error: 0.125,
                    // A tiebreak's score (40-byte records).
                    secondary: Some(Secondary {
                        value: -12.5,
                        std_error: 0.75,
                    }),
                    blocks: Vec::new(),
                    changes: Vec::new(),
                },
                4
            ))
        );
        assert_eq!(s.blob(&a, "target").unwrap().as_deref(), Some(&b"xyz"[..]));
        s.delete_job(&a).unwrap();
        assert_eq!(s.records().unwrap().len(), 1);
        assert!(s.scores(&a).unwrap().is_empty());
        assert!(s.blob(&a, "target").unwrap().is_none());
        assert_eq!(s.scores(&b).unwrap().len(), 1);
    }

    #[test]
    fn refuses_another_schema_version() {
        let dir = tempfile::tempdir().unwrap();
        {
            let db = sled::open(dir.path().join("store")).unwrap();
            db.insert(SCHEMA_KEY, &99u32.to_le_bytes()).unwrap();
            db.flush().unwrap();
        }
        // sled's background flusher may hold the folder's lock a moment after the drop.
        let mut err = SledStore::open(dir.path()).err().unwrap();
        for _ in 0..50 {
            if !err.to_string().contains("could not acquire lock") {
                break;
            }
            std::thread::sleep(std::time::Duration::from_millis(100));
            err = SledStore::open(dir.path()).err().unwrap();
        }
        assert!(err.to_string().contains("schema version 99"), "{err}");
    }
}
