//! Durable coordinator state behind a small trait: job records (parameters and input files),
//! job progress (search state after each step, pinned engine, ε), scores of completed renders
//! keyed by render identity, setup products and final outputs.
//!
//! Count matrices are never stored: a `kill -9` loses at most the renders in progress. The sled
//! implementation checks a schema version when it opens a data folder.

use scatterfarm_search::{Score, Secondary};
use std::collections::BTreeMap;
use std::path::Path;
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
}

/// What the coordinator keeps across restarts. Keys are job ids; values are opaque bytes the
/// coordinator encodes.
pub trait Store: Send + Sync {
    /// A new, never reused job id.
    fn new_job_id(&self) -> Result<String, StoreError>;
    /// Stores a job's immutable record (parameters and input files).
    fn put_record(&self, job: &str, record: &[u8]) -> Result<(), StoreError>;
    /// Every stored job's record.
    fn records(&self) -> Result<Vec<(String, Vec<u8>)>, StoreError>;
    /// Replaces a job's progress (state after a step) and makes it durable.
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
    /// Removes everything of a job.
    fn delete_job(&self, job: &str) -> Result<(), StoreError>;
    /// Makes every write so far durable.
    fn flush(&self) -> Result<(), StoreError>;
}

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
        let tail = super::nonce() as u16;
        Ok(format!("j{n}-{tail:04x}"))
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
        self.progress.insert(job.as_bytes(), progress)?;
        self.db.flush()?;
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
        // Not flushed here: the next progress write flushes, and a lost score is re-rendered.
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

/// A stored score: value, step and standard error (little-endian f64, u64, f64); then, when
/// there is a secondary score, its value and error; then, when there are likelihood blocks,
/// their count (u64) and values. The secondary is present when the remainder after the first
/// three words is 16 bytes, or 16 bytes plus a block list; a block list alone starts right
/// after the first three words. The two cases are told apart by the block count.
fn encode_score(score: &Score, step: u64) -> Vec<u8> {
    let mut value = Vec::with_capacity(40 + 8 * (score.blocks.len() + 1));
    value.extend_from_slice(&score.value.to_le_bytes());
    value.extend_from_slice(&step.to_le_bytes());
    value.extend_from_slice(&score.std_error.to_le_bytes());
    if let Some(s) = score.secondary {
        value.extend_from_slice(&s.value.to_le_bytes());
        value.extend_from_slice(&s.std_error.to_le_bytes());
    }
    if !score.blocks.is_empty() {
        value.extend_from_slice(&(score.blocks.len() as u64).to_le_bytes());
        for b in &score.blocks {
            value.extend_from_slice(&b.to_le_bytes());
        }
    }
    value
}

/// The inverse of [`encode_score`]; a record of any other shape is damaged.
pub fn decode_score(v: &[u8]) -> Result<(Score, u64), StoreError> {
    let damaged = || StoreError::Damaged {
        what: "score",
        detail: format!("{} bytes", v.len()),
    };
    if v.len() < 24 || !v.len().is_multiple_of(8) {
        return Err(damaged());
    }
    let words: Vec<[u8; 8]> = v
        .chunks_exact(8)
        .map(|c| {
            let mut b = [0u8; 8];
            b.copy_from_slice(c);
            b
        })
        .collect();
    let f = |i: usize| f64::from_le_bytes(words[i]);
    let rest = words.len() - 3;
    // A block list at word `at`: its count fills the rest exactly.
    let blocks_at = |at: usize| -> Option<Vec<f64>> {
        let n = u64::from_le_bytes(*words.get(at)?);
        (n > 0 && usize::try_from(n).ok()? == words.len() - at - 1)
            .then(|| (at + 1..words.len()).map(f).collect())
    };
    let (secondary, blocks) = match rest {
        0 => (None, Vec::new()),
        2 if blocks_at(3).is_none() => (
            Some(Secondary {
                value: f(3),
                std_error: f(4),
            }),
            Vec::new(),
        ),
        _ => match blocks_at(3) {
            Some(b) => (None, b),
            None => match blocks_at(5) {
                Some(b) => (
                    Some(Secondary {
                        value: f(3),
                        std_error: f(4),
                    }),
                    b,
                ),
                None => return Err(damaged()),
            },
        },
    };
    Ok((
        Score {
            value: f(0),
            std_error: f(2),
            secondary,
            blocks,
            changes: Vec::new(),
        },
        u64::from_le_bytes(words[1]),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

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
        let s = SledStore::open(dir.path()).unwrap();
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
    fn scores_round_trip_in_every_shape_and_damage_is_named() {
        let shapes = [
            Score::exact(0.25),
            Score {
                secondary: Some(Secondary {
                    value: -1.0,
                    std_error: 0.5,
                }),
                ..Score::exact(0.5)
            },
            Score {
                blocks: vec![-1.5, -2.0, -0.25],
                changes: Vec::new(),
                ..Score::exact(-3.75)
            },
            Score {
                secondary: Some(Secondary {
                    value: 3.0,
                    std_error: 1.0,
                }),
                blocks: vec![-4.0, -5.0],
                changes: Vec::new(),
                ..Score::exact(-9.0)
            },
        ];
        for (step, score) in shapes.into_iter().enumerate() {
            let bytes = encode_score(&score, step as u64);
            assert_eq!(decode_score(&bytes).unwrap(), (score, step as u64));
        }
        assert!(decode_score(&[0; 23]).is_err());
        assert!(decode_score(&[0; 25]).is_err());
        // A block count that does not fill the record.
        let mut bad = encode_score(
            &Score {
                blocks: vec![1.0, 2.0],
                changes: Vec::new(),
                ..Score::exact(0.0)
            },
            0,
        );
        bad.truncate(bad.len() - 8);
        bad.extend_from_slice(&[0; 16]);
        assert!(decode_score(&bad).is_err());
    }

    #[test]
    fn refuses_another_schema_version() {
        let dir = tempfile::tempdir().unwrap();
        {
            let db = sled::open(dir.path().join("store")).unwrap();
            db.insert(SCHEMA_KEY, &99u32.to_le_bytes()).unwrap();
            db.flush().unwrap();
        }
        let err = SledStore::open(dir.path()).err().unwrap();
        assert!(err.to_string().contains("schema version 99"), "{err}");
    }
}
