//! The setup's end: ε calibrated and the synthesized target stored, and the scoring they make
//! rebuilt when a job is restored.

use super::{Checkpoint, Job, JobState};
use crate::store::Store;
use anyhow::{Context, Result};
use scatterfarm_job::plan::{Plan, SetupCounts, TargetSource};
use scatterfarm_search::driver::Scoring;
use scatterfarm_search::similarity::Target;

/// The blob key of a synthesized target.
const TARGET_KEY: &str = "target";

fn encode_f32(values: &[f32]) -> Vec<u8> {
    values.iter().flat_map(|v| v.to_le_bytes()).collect()
}

fn decode_f32(bytes: &[u8]) -> Vec<f32> {
    bytes
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
}

/// The scoring of stored job `id`, once its setup is complete (`None` before).
pub(super) fn restored_scoring(
    id: &str,
    plan: &Plan,
    checkpoint: &Checkpoint,
    store: &dyn Store,
) -> Result<Option<Scoring>> {
    // Past preparation the target (and ε, for the metrics that need it) are known.
    Ok(match &checkpoint.state {
        JobState::Preparing => None,
        _ => {
            let target = match &plan.target {
                TargetSource::Captured(t) => t.clone(),
                TargetSource::Synthesized { photons } => Target {
                    values: decode_f32(
                        &store
                            .blob(id, TARGET_KEY)?
                            .with_context(|| format!("job {id}: its target is missing"))?,
                    ),
                    photons_per_source: u64::from(*photons),
                },
            };
            Some(plan.scoring(target, checkpoint.epsilons.clone()))
        }
    })
}

impl Job {
    /// Completes the setup from its counts: ε and the target become the job's scoring, and the
    /// job starts searching.
    pub(super) fn finish_setup(&mut self, store: &dyn Store) -> Result<()> {
        let scoring = self.plan.finish_setup(&self.setup)?;
        if matches!(self.plan.target, TargetSource::Synthesized { .. }) {
            store.put_blob(&self.id, TARGET_KEY, &encode_f32(&scoring.target.values))?;
        }
        let finest = self.checkpoint.search.config().photons.level(u32::MAX);
        for (photons, e) in &scoring.epsilons {
            tracing::info!(
                "job {}: ε = {e:.6} at {photons} photons per source",
                self.id
            );
        }
        self.checkpoint.epsilon = scoring.epsilons.get(&finest).copied();
        self.checkpoint.epsilons = scoring.epsilons.clone();
        self.checkpoint.state = JobState::Searching;
        self.scoring = Some(std::sync::Arc::new(scoring));
        self.setup = SetupCounts::default();
        self.persist(store)
    }
}
