//! One reconstruction job inside the coordinator: [`Job`] and its lifecycle (submission,
//! restoring, failing, cancelling, finishing), with one file per concern:
//!
//! - [`record`]: the immutable [`JobRecord`].
//! - [`checkpoint`]: the durable [`Checkpoint`] written after every step, and the [`JobState`].
//! - [`pinning`]: pinning the job to one engine fingerprint ([`ANY_ENGINE`] for none).
//! - `planning`: its work cut into render groups through the search's step driver, and the
//!   groups taken back as they complete.
//! - `setup`: the setup's end (ε and the target), and its scoring rebuilt on restore.
//! - [`outputs`]: the files `reconstruct` writes, copied out under the lock, drawn and stored
//!   after it.
//! - `pace`: photons per second and the time left.
//! - [`scoring`]: a complete search group scored away from the scheduler's lock.
//! - [`faults`]: a job paused when the store fails, and restored from it.
//! - `forgetting`: stored scores of stages the search has left, removed.
//!
//! A job moves Preparing (target and ε calibration renders) → Searching (one group per search
//! step, holding the step's renders that have no cached score) → Finished. Every transition is
//! written to the [`Store`] before the next group is cut, so a coordinator killed at any moment
//! resumes from its last step and, renders being seeded per request, ends with exactly the
//! result of an uninterrupted run.

pub mod checkpoint;
pub mod faults;
mod forgetting;
pub mod outputs;
mod pace;
pub mod pinning;
mod planning;
pub mod record;
pub mod scoring;
mod setup;

pub use checkpoint::{Checkpoint, JobState};
pub use outputs::OutputSource;
pub use pinning::ANY_ENGINE;
pub use record::JobRecord;

use crate::store::{Store, StoreError};
use crate::work::RenderGroup;
use anyhow::{Context, Result};
use record::{input_key, now_unix, record_from_json};
use scatterfarm_job::inputs::Inputs;
use scatterfarm_job::plan::{Plan, SetupCounts};
use scatterfarm_job::spec::JobSpec;
use scatterfarm_search::driver::Scoring;
use scatterfarm_search::identity::Identity;
use scatterfarm_search::steps::Steps;
use scatterfarm_search::Score;
use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Instant;

/// A job in memory.
pub struct Job {
    pub id: String,
    pub record: JobRecord,
    pub plan: Plan,
    pub checkpoint: Checkpoint,
    scoring: Option<Arc<Scoring>>,
    /// The group being scored off the lock ([`scoring`]), while the job waits for its scores.
    scoring_group: Option<u64>,
    /// The search's step driver (score cache and racing prefixes), once the job is pinned to
    /// an engine; its scores are also in the store.
    steps: Option<Steps>,
    setup: SetupCounts,
    /// The groups being rendered now.
    pub groups: Vec<RenderGroup>,
    /// Since this coordinator run started working on the job.
    session_started: Instant,
    session_renders_start: u64,
    /// Photons (all sources) summed in this run.
    pub session_photons: u64,
    last_active: Instant,
    /// Set while the job waits to be restored after a store fault.
    pub paused: Option<faults::Pause>,
    /// The job finished and its outputs are still to be stored (off the lock:
    /// [`outputs`]).
    pub outputs_due: bool,
    /// Where its stored scores were forgotten to.
    stored_stages: forgetting::StoredStages,
}

impl Job {
    /// Validates a submission and stores it. Nothing is stored when it is invalid.
    pub fn submit(id: String, params: JobSpec, inputs: Inputs, store: &dyn Store) -> Result<Job> {
        let plan = Plan::resolve(&params, &inputs)?;
        let record = JobRecord {
            files: inputs.files.keys().cloned().collect(),
            params,
            submitted_unix: now_unix(),
        };
        let checkpoint =
            Checkpoint::start(pinning::initial_pin(&record.params), plan.search.clone());
        for (name, bytes) in &inputs.files {
            store.put_blob(&id, &input_key(name), bytes)?;
        }
        checkpoint.save(&id, store)?;
        // The record goes last: a job without one is not loaded, so a crash mid-submission
        // leaves nothing visible.
        store.put_record(&id, &serde_json::to_vec(&record)?)?;
        Ok(Job::assemble(
            id,
            record,
            plan,
            checkpoint,
            BTreeMap::new(),
            None,
        ))
    }

    /// Loads a stored job.
    pub fn restore(id: String, record: &[u8], store: &dyn Store) -> Result<Job> {
        let record = record_from_json(record)
            .map_err(|e| StoreError::Damaged {
                what: "job record",
                detail: e,
            })
            .with_context(|| format!("job {id}"))?;
        let mut inputs = Inputs::default();
        for name in &record.files {
            let bytes = store
                .blob(&id, &input_key(name))?
                .with_context(|| format!("job {id}: the input file {name} is missing"))?;
            inputs.files.insert(name.clone(), bytes);
        }
        let plan = Plan::resolve(&record.params, &inputs).with_context(|| format!("job {id}"))?;
        let checkpoint = Checkpoint::load(&id, store)?;
        checkpoint
            .search
            .check_consistent()
            .map_err(|e| StoreError::Damaged {
                what: "job progress",
                detail: e.to_string(),
            })
            .with_context(|| format!("job {id}"))?;
        let scoring = setup::restored_scoring(&id, &plan, &checkpoint, store)?.map(Arc::new);
        let stage_start = checkpoint.search.stage_start();
        let mut scores = store.scores(&id)?;
        scores.retain(|_, (_, step)| *step >= stage_start);
        let mut job = Job::assemble(id, record, plan, checkpoint, scores, scoring);
        job.stored_stages = forgetting::StoredStages::restored(stage_start);
        Ok(job)
    }

    fn assemble(
        id: String,
        record: JobRecord,
        plan: Plan,
        checkpoint: Checkpoint,
        scores: BTreeMap<Identity, (Score, u64)>,
        scoring: Option<Arc<Scoring>>,
    ) -> Job {
        let renders = checkpoint.search.progress().renders_done;
        let steps = checkpoint
            .pinned
            .as_deref()
            .map(|fingerprint| Steps::new(plan.search_geometry, fingerprint, scores));
        Job {
            id,
            record,
            plan,
            checkpoint,
            scoring,
            scoring_group: None,
            steps,
            setup: SetupCounts::default(),
            groups: Vec::new(),
            session_started: Instant::now(),
            session_renders_start: renders,
            session_photons: 0,
            last_active: Instant::now(),
            paused: None,
            outputs_due: false,
            stored_stages: forgetting::StoredStages::default(),
        }
    }

    /// What the job's search renders are scored against, once its setup is done.
    pub fn scoring(&self) -> Option<&Arc<Scoring>> {
        self.scoring.as_ref()
    }

    /// Whether the job still needs renders.
    pub fn is_active(&self) -> bool {
        matches!(
            self.checkpoint.state,
            JobState::Preparing | JobState::Searching
        )
    }

    /// A label for listings.
    pub fn name(&self) -> String {
        self.record.params.name.clone().unwrap_or_else(|| {
            self.record
                .params
                .scene
                .clone()
                .or_else(|| {
                    self.record
                        .params
                        .target
                        .as_ref()
                        .map(|t| t.display().to_string())
                })
                .unwrap_or_default()
        })
    }

    /// Marks the job failed with `message` (and stores that).
    pub fn fail(&mut self, message: String, store: &dyn Store) -> Result<()> {
        tracing::error!("job {} failed: {message}", self.id);
        self.groups.clear();
        self.scoring_group = None;
        self.checkpoint.state = JobState::Failed { message };
        self.persist(store)
    }

    /// Cancels the job: its groups are dropped, so results of its leases are refused.
    pub fn cancel(&mut self, store: &dyn Store) -> Result<()> {
        if self.is_active() {
            self.groups.clear();
            self.scoring_group = None;
            self.checkpoint.state = JobState::Cancelled;
            self.persist(store)?;
        }
        Ok(())
    }

    /// Marks the job finished and stores that; its outputs are drawn and stored after the
    /// lock is released ([`outputs`]).
    fn finish(&mut self, store: &dyn Store) -> Result<()> {
        self.checkpoint.state = JobState::Finished;
        self.persist(store)?;
        self.outputs_due = true;
        tracing::info!(
            "job {} finished: similarity {:.4}",
            self.id,
            self.checkpoint
                .search
                .result()
                .map(|r| r.score)
                .unwrap_or(f64::NAN)
        );
        Ok(())
    }
}
