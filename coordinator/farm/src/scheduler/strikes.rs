//! Strikes: bad results a worker sent for a job. A worker with [`STRIKES`] of them is blocked
//! for that job. Strikes are keyed by the worker's identity (the name it registers with), not
//! by the id a registration hands out, so registering again does not clear them, and they are
//! stored with the job, so a coordinator restart does not either. Deleting the job deletes them.

use crate::store::Store;
use std::collections::{BTreeMap, HashMap};

/// Bad results a worker may send for one job before it is blocked for it.
pub const STRIKES: u32 = 3;

/// The job blob that holds a job's strikes (JSON: identity → count).
const BLOB: &str = "strikes";

/// Every job's strikes, by job id, then worker identity.
#[derive(Debug, Default)]
pub struct Strikes {
    by_job: HashMap<String, BTreeMap<String, u32>>,
}

impl Strikes {
    /// The stored strikes of `jobs`. A damaged record is logged and read as no strikes.
    pub fn load<'a>(store: &dyn Store, jobs: impl Iterator<Item = &'a String>) -> Strikes {
        let mut by_job = HashMap::new();
        for id in jobs {
            match store.blob(id, BLOB) {
                Ok(None) => {}
                Ok(Some(bytes)) => match serde_json::from_slice::<BTreeMap<String, u32>>(&bytes) {
                    Ok(m) => {
                        by_job.insert(id.clone(), m);
                    }
                    Err(e) => tracing::error!("job {id}: its stored strikes are damaged: {e}"),
                },
                Err(e) => tracing::error!("job {id}: cannot read its strikes: {e}"),
            }
        }
        Strikes { by_job }
    }

    /// Whether `identity` is blocked for `job`.
    pub fn blocked(&self, job: &str, identity: &str) -> bool {
        self.count(job, identity) >= STRIKES
    }

    pub fn count(&self, job: &str, identity: &str) -> u32 {
        self.by_job
            .get(job)
            .and_then(|m| m.get(identity))
            .copied()
            .unwrap_or(0)
    }

    /// Counts one more bad result of `identity` for `job` and stores the job's strikes; the
    /// new count.
    pub fn add(&mut self, job: &str, identity: &str, store: &dyn Store) -> u32 {
        let m = self.by_job.entry(job.to_string()).or_default();
        let n = m.entry(identity.to_string()).or_insert(0);
        *n += 1;
        let n = *n;
        match serde_json::to_vec(m) {
            Ok(bytes) => {
                if let Err(e) = store.put_blob(job, BLOB, &bytes) {
                    tracing::error!("job {job}: cannot store its strikes: {e}");
                }
            }
            Err(e) => tracing::error!("job {job}: cannot encode its strikes: {e}"),
        }
        n
    }

    /// Forgets a deleted job's strikes (the store deletes its blobs with it).
    pub fn forget(&mut self, job: &str) {
        self.by_job.remove(job);
    }
}
