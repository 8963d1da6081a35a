//! A job's stored scores of stages its search has left, forgotten
//! ([`scatterfarm_search::Search::stage_start`]: no later request has their identities; the
//! step driver forgets them in memory, [`scatterfarm_search::steps`]).
//!
//! The store keeps the scores of the stage two before the current one: a coordinator that
//! stops restores from its last durable checkpoint, which can be behind the one last written
//! (the store flushes after the lock is released), and that checkpoint's stage must still find
//! its scores, or the restored job would render them again and count what an uninterrupted one
//! does not. A restored checkpoint is durable, so what is before its stage goes at once.

use crate::store::{Store, StoreError};

/// Stage starts seen by a job's checkpoints, and where its stored scores were forgotten to.
#[derive(Debug, Default)]
pub struct StoredStages {
    /// The last distinct stage starts written, oldest first (at most three).
    written: Vec<u64>,
    /// A stage start known durable (the restored checkpoint's).
    durable: u64,
    /// Stored scores of steps before this are gone.
    forgotten_before: u64,
}

impl StoredStages {
    /// For a job restored from a checkpoint whose stage starts at `stage_start`.
    pub fn restored(stage_start: u64) -> StoredStages {
        StoredStages {
            durable: stage_start,
            ..StoredStages::default()
        }
    }

    /// Notes a checkpoint of stage `stage_start` written, and forgets `job`'s stored scores of
    /// the stages it made safe to forget; returns how many went.
    pub fn written(
        &mut self,
        job: &str,
        stage_start: u64,
        store: &dyn Store,
    ) -> Result<usize, StoreError> {
        if self.written.last() != Some(&stage_start) {
            self.written.push(stage_start);
            if self.written.len() > 3 {
                self.written.remove(0);
            }
        }
        let safe = if self.written.len() == 3 {
            self.written[0]
        } else {
            0
        };
        let before = safe.max(self.durable);
        if before <= self.forgotten_before {
            return Ok(0);
        }
        let gone = store.forget_scores_before(job, before)?;
        self.forgotten_before = before;
        Ok(gone)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::MemoryStore;
    use scatterfarm_search::Score;

    #[test]
    fn scores_go_two_stages_behind_and_at_once_before_a_restored_stage() {
        let store = MemoryStore::new();
        for step in 0..40u64 {
            store
                .put_score("j", &[step as u8; 32], Score::exact(0.0), step)
                .unwrap();
        }
        let steps = |s: &MemoryStore| -> Vec<u64> {
            s.scores("j").unwrap().values().map(|(_, st)| *st).collect()
        };
        let mut stages = StoredStages::default();
        assert_eq!(stages.written("j", 0, &store).unwrap(), 0);
        assert_eq!(stages.written("j", 0, &store).unwrap(), 0);
        assert_eq!(stages.written("j", 10, &store).unwrap(), 0);
        assert_eq!(
            stages.written("j", 20, &store).unwrap(),
            0,
            "stage 0 is two behind"
        );
        assert_eq!(stages.written("j", 30, &store).unwrap(), 10, "stage 0 goes");
        assert_eq!(steps(&store).first(), Some(&10));
        let mut restored = StoredStages::restored(30);
        assert_eq!(restored.written("j", 30, &store).unwrap(), 20);
        assert_eq!(steps(&store).first(), Some(&30));
    }
}
