//! One reconstruction job inside the coordinator: its immutable record, its durable progress,
//! and the render groups of its current step.
//!
//! A job moves Preparing (target and ε calibration renders) → Searching (one group per search
//! step, holding the step's renders that have no cached score) → Finished. Every transition is
//! written to the [`Store`] before the next group is cut, so a coordinator killed at any moment
//! resumes from its last step and, renders being seeded per request, ends with exactly the
//! result of an uninterrupted run.

use super::store::{Store, StoreError};
use super::work::{Purpose, RenderGroup};
use anyhow::{Context, Result};
use scatterfarm_job::inputs::Inputs;
use scatterfarm_job::outcome::{self, Summary};
use scatterfarm_job::plan::{Plan, SetupCounts, TargetSource};
use scatterfarm_job::spec::JobSpec;
use scatterfarm_search::driver::{Consumption, Scoring};
use scatterfarm_search::identity::{identity, Identity};
use scatterfarm_search::similarity::Target;
use scatterfarm_search::steps::{GroupItem, Next, Steps};
use scatterfarm_search::{Score, Search};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::time::Instant;

/// The pinned fingerprint of a job that opted out of pinning.
pub const ANY_ENGINE: &str = "any";

/// What never changes after submission.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct JobRecord {
    pub params: JobSpec,
    /// The names of the input files, stored as blobs `input/NAME`.
    pub files: Vec<String>,
    pub submitted_unix: f64,
}

/// A stored job record, its spec of a layout this build reads.
fn record_from_json(bytes: &[u8]) -> Result<JobRecord, String> {
    let record: JobRecord = serde_json::from_slice(bytes).map_err(|e| e.to_string())?;
    record.params.check_version().map_err(|e| e.to_string())?;
    Ok(record)
}

/// Where a job stands.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "state", rename_all = "kebab-case")]
pub enum Phase {
    Preparing,
    Searching,
    Finished,
    Cancelled,
    Failed { message: String },
}

/// What is written after every step.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Progress {
    pub phase: Phase,
    /// The engine fingerprint the job is pinned to ([`ANY_ENGINE`] when it opted out).
    pub pinned: Option<String>,
    /// ε of the finest level's budget (for listings; `epsilons` holds every budget's).
    pub epsilon: Option<f64>,
    /// ε by photons per source.
    pub epsilons: BTreeMap<u32, f64>,
    pub search: Search,
    /// What the search consumed (the same for interrupted and uninterrupted runs).
    pub used: Consumption,
    /// Photons engines actually ran for this job (all sources), recomputation included.
    pub photons_simulated: u64,
    /// Seconds the job was worked on, over all of the coordinator's runs.
    pub active_seconds: f64,
}

/// A job in memory.
pub struct Job {
    pub id: String,
    pub record: JobRecord,
    pub plan: Plan,
    pub progress: Progress,
    scoring: Option<Scoring>,
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
}

fn input_key(name: &str) -> String {
    format!("input/{name}")
}

fn now_unix() -> f64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs_f64())
        .unwrap_or(0.0)
}

fn encode_f32(values: &[f32]) -> Vec<u8> {
    values.iter().flat_map(|v| v.to_le_bytes()).collect()
}

fn decode_f32(bytes: &[u8]) -> Vec<f32> {
    bytes
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
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
        let pinned = if record.params.any_engine {
            Some(ANY_ENGINE.to_string())
        } else {
            record.params.engine_fingerprint.clone()
        };
        let progress = Progress {
            phase: Phase::Preparing,
            pinned,
            epsilon: None,
            epsilons: BTreeMap::new(),
            search: plan.search.clone(),
            used: Consumption::default(),
            photons_simulated: 0,
            active_seconds: 0.0,
        };
        for (name, bytes) in &inputs.files {
            store.put_blob(&id, &input_key(name), bytes)?;
        }
        store.put_progress(&id, &serde_json::to_vec(&progress)?)?;
        // The record goes last: a job without one is not loaded, so a crash mid-submission
        // leaves nothing visible.
        store.put_record(&id, &serde_json::to_vec(&record)?)?;
        Ok(Job::assemble(
            id,
            record,
            plan,
            progress,
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
        let progress: Progress = match store.progress(&id)? {
            Some(bytes) => serde_json::from_slice(&bytes).map_err(|e| StoreError::Damaged {
                what: "job progress",
                detail: e.to_string(),
            })?,
            None => anyhow::bail!("job {id}: its progress is missing"),
        };
        // Past preparation the target (and ε, for the metrics that need it) are known.
        let scoring = match &progress.phase {
            Phase::Preparing => None,
            _ => {
                let target = match &plan.target {
                    TargetSource::Captured(t) => t.clone(),
                    TargetSource::Synthesized { photons } => Target {
                        values: decode_f32(
                            &store
                                .blob(&id, "target")?
                                .with_context(|| format!("job {id}: its target is missing"))?,
                        ),
                        photons_per_source: u64::from(*photons),
                    },
                };
                Some(plan.scoring(target, progress.epsilons.clone()))
            }
        };
        let scores = store.scores(&id)?;
        Ok(Job::assemble(id, record, plan, progress, scores, scoring))
    }

    fn assemble(
        id: String,
        record: JobRecord,
        plan: Plan,
        progress: Progress,
        scores: BTreeMap<Identity, (Score, u64)>,
        scoring: Option<Scoring>,
    ) -> Job {
        let renders = progress.search.progress().renders_done;
        let steps = progress
            .pinned
            .as_deref()
            .map(|fingerprint| Steps::new(plan.search_geometry, fingerprint, scores));
        Job {
            id,
            record,
            plan,
            progress,
            scoring,
            steps,
            setup: SetupCounts::default(),
            groups: Vec::new(),
            session_started: Instant::now(),
            session_renders_start: renders,
            session_photons: 0,
            last_active: Instant::now(),
        }
    }

    /// Whether the job still needs renders.
    pub fn is_active(&self) -> bool {
        matches!(self.progress.phase, Phase::Preparing | Phase::Searching)
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

    /// Pins the job to `fingerprint` (the first worker to lease its tasks) and stores it.
    pub fn pin(&mut self, fingerprint: &str, store: &dyn Store) -> Result<()> {
        self.progress.pinned = Some(fingerprint.to_string());
        self.steps = Some(Steps::new(self.plan.search_geometry, fingerprint, []));
        self.persist(store)
    }

    /// Whether a worker of `fingerprint` may render this job (pinning it if not yet pinned).
    pub fn accepts(&self, fingerprint: &str) -> bool {
        match self.progress.pinned.as_deref() {
            None | Some(ANY_ENGINE) => true,
            Some(p) => p == fingerprint,
        }
    }

    fn persist(&mut self, store: &dyn Store) -> Result<()> {
        let now = Instant::now();
        self.progress.active_seconds += now.duration_since(self.last_active).as_secs_f64();
        self.last_active = now;
        store.put_progress(&self.id, &serde_json::to_vec(&self.progress)?)?;
        Ok(())
    }

    /// Marks the job failed with `message` (and stores that).
    pub fn fail(&mut self, message: String, store: &dyn Store) -> Result<()> {
        tracing::error!("job {} failed: {message}", self.id);
        self.groups.clear();
        self.progress.phase = Phase::Failed { message };
        self.persist(store)
    }

    /// Cancels the job: its groups are dropped, so results of its leases are refused.
    pub fn cancel(&mut self, store: &dyn Store) -> Result<()> {
        if self.is_active() {
            self.groups.clear();
            self.progress.phase = Phase::Cancelled;
            self.persist(store)?;
        }
        Ok(())
    }

    /// Makes sure the job has groups to render if it needs any: the missing setup renders, or
    /// the current step's unscored renders. Steps whose renders are all scored are submitted
    /// on the way. Needs the job pinned.
    pub fn plan_work(
        &mut self,
        new_group_id: &mut dyn FnMut() -> u64,
        store: &dyn Store,
    ) -> Result<()> {
        if !self.groups.is_empty() || !self.is_active() {
            return Ok(());
        }
        let fingerprint = self
            .progress
            .pinned
            .clone()
            .context("a job is planned before it is pinned")?;
        if self.progress.phase == Phase::Preparing {
            for r in self.plan.setup_renders()? {
                if self.setup.has(r.kind) {
                    continue;
                }
                let id = identity(
                    &r.item.assignment,
                    &r.table,
                    r.geometry,
                    r.item.seed,
                    r.photons,
                    &fingerprint,
                );
                self.groups.push(RenderGroup::new(
                    new_group_id(),
                    Purpose::Setup(r.kind),
                    r.geometry,
                    r.table,
                    vec![GroupItem {
                        identity: id,
                        item: r.item,
                    }],
                    r.photons,
                ));
            }
            if self.groups.is_empty() {
                self.finish_setup(store)?;
            } else {
                return Ok(());
            }
        }
        let geometry = self.plan.search_geometry;
        loop {
            let steps = self
                .steps
                .as_mut()
                .context("a job is planned before it is pinned")?;
            match steps.next(&mut self.progress.search, &mut self.progress.used)? {
                Next::Finished => return self.finish(store),
                Next::Submitted => self.persist(store)?,
                Next::Render(groups) => {
                    let table = self.progress.search.materials();
                    for g in groups {
                        let group = RenderGroup::new(
                            new_group_id(),
                            Purpose::Search,
                            geometry,
                            table.clone(),
                            g.items,
                            g.photons,
                        );
                        self.groups.push(group.starting_from(g.start, g.prefixes));
                    }
                    return Ok(());
                }
            }
        }
    }

    fn finish_setup(&mut self, store: &dyn Store) -> Result<()> {
        let scoring = self.plan.finish_setup(&self.setup)?;
        if matches!(self.plan.target, TargetSource::Synthesized { .. }) {
            store.put_blob(&self.id, "target", &encode_f32(&scoring.target.values))?;
        }
        let finest = self.progress.search.config().photons.level(u32::MAX);
        for (photons, e) in &scoring.epsilons {
            tracing::info!(
                "job {}: ε = {e:.6} at {photons} photons per source",
                self.id
            );
        }
        self.progress.epsilon = scoring.epsilons.get(&finest).copied();
        self.progress.epsilons = scoring.epsilons.clone();
        self.progress.phase = Phase::Searching;
        self.scoring = Some(scoring);
        self.setup = SetupCounts::default();
        self.persist(store)
    }

    fn finish(&mut self, store: &dyn Store) -> Result<()> {
        self.progress.phase = Phase::Finished;
        self.persist(store)?;
        let outputs = self.outputs()?;
        for (name, bytes) in &outputs {
            store.put_blob(&self.id, &format!("output/{name}"), bytes)?;
        }
        tracing::info!(
            "job {} finished: similarity {:.4}",
            self.id,
            self.progress
                .search
                .result()
                .map(|r| r.score)
                .unwrap_or(f64::NAN)
        );
        Ok(())
    }

    /// Takes a complete group's counts: setup counts are kept until the setup is complete;
    /// search renders are scored and their scores stored. Then plans the next work.
    pub fn group_complete(
        &mut self,
        group: RenderGroup,
        new_group_id: &mut dyn FnMut() -> u64,
        store: &dyn Store,
    ) -> Result<()> {
        let sources = group.geometry.sources() as u64;
        self.progress.photons_simulated +=
            sources * u64::from(group.photons - group.start) * group.items.len() as u64;
        self.progress.used.scatter_events += group.scatter_events;
        let purpose = group.purpose;
        let photons = group.photons;
        let items = group.items.clone();
        let sums = group.into_sums();
        match purpose {
            Purpose::Setup(kind) => {
                if let Some(c) = sums.into_iter().next() {
                    self.setup.set(kind, c);
                }
            }
            Purpose::Search => {
                let scoring = self
                    .scoring
                    .as_ref()
                    .context("a search render completed before ε was calibrated")?;
                let steps = self
                    .steps
                    .as_mut()
                    .context("a search render completed for a job that is not pinned")?;
                for (id, score, step) in
                    steps.complete(&self.progress.search, scoring, photons, &items, sums)?
                {
                    store.put_score(&self.id, &id, score, step)?;
                }
            }
        }
        if self.groups.is_empty() {
            self.plan_work(new_group_id, store)?;
        }
        Ok(())
    }

    /// The engine named in reports.
    fn engine_label(&self) -> String {
        self.progress
            .pinned
            .clone()
            .unwrap_or_else(|| "not pinned yet".into())
    }

    /// The outputs `reconstruct` writes, as file name → bytes: the final result, or the current
    /// best of a running job. `None` before anything has been scored.
    pub fn outputs(&self) -> Result<BTreeMap<String, Vec<u8>>> {
        let search = &self.progress.search;
        let (assignment, similarity) = match search.result() {
            Some(r) => (r.assignment.clone(), r.score),
            None => search
                .current_best()
                .context("nothing has been scored yet: no result to show")?,
        };
        let grid = self.plan.config.grid as usize;
        let assignment = if assignment.len() == grid * grid {
            assignment
        } else {
            let from = (assignment.len() as f64).sqrt().round() as usize;
            outcome::upsample(&assignment, from.max(1), grid)
        };
        let dir = tempfile::tempdir().context("cannot create a scratch folder")?;
        outcome::write_outputs(
            dir.path(),
            &Summary {
                config: &self.plan.config,
                truth: self.plan.truth.as_ref(),
                search,
                assignment: &assignment,
                similarity,
                epsilons: &self.progress.epsilons,
                used: self.progress.used,
                photons_simulated: self.progress.photons_simulated,
                wall_seconds: self.progress.active_seconds,
                engine: self.engine_label(),
                reproducible: self.progress.pinned.as_deref() != Some(ANY_ENGINE),
            },
        )?;
        let mut files = BTreeMap::new();
        for entry in std::fs::read_dir(dir.path())? {
            let entry = entry?;
            let name = entry.file_name().to_string_lossy().into_owned();
            files.insert(name, std::fs::read(entry.path())?);
        }
        Ok(files)
    }

    /// The stored outputs of a finished job.
    pub fn stored_outputs(&self, store: &dyn Store) -> Result<BTreeMap<String, Vec<u8>>> {
        let mut files = BTreeMap::new();
        for name in [
            "report.json",
            "materials.npy",
            "materials.json",
            "reconstruction.png",
            "maps.png",
        ] {
            if let Some(b) = store.blob(&self.id, &format!("output/{name}"))? {
                files.insert(name.to_string(), b);
            }
        }
        if files.is_empty() {
            return self.outputs();
        }
        Ok(files)
    }

    /// Renders per second and the estimated seconds left, from this run's pace.
    pub fn pace(&self) -> (f64, Option<f64>) {
        let elapsed = self.session_started.elapsed().as_secs_f64().max(1e-6);
        let photons_per_second = self.session_photons as f64 / elapsed;
        let p = self.progress.search.progress();
        let done_here = p.renders_done.saturating_sub(self.session_renders_start);
        let eta = if !self.is_active() {
            Some(0.0)
        } else if done_here > 0 {
            Some(elapsed / done_here as f64 * p.renders_total.saturating_sub(p.renders_done) as f64)
        } else {
            None
        };
        (photons_per_second, eta)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use scatterfarm_job::spec::JobSpec;

    #[test]
    fn records_read_back_and_another_spec_version_is_refused() {
        let record = JobRecord {
            params: JobSpec {
                scene: Some("demo8".into()),
                permutations: 2,
                ..Default::default()
            },
            files: vec![],
            submitted_unix: 2.0,
        };
        let bytes = serde_json::to_vec(&record).unwrap();
        assert_eq!(record_from_json(&bytes).unwrap().params, record.params);
        let mut later = record.clone();
        later.params.version += 1;
        let err = record_from_json(&serde_json::to_vec(&later).unwrap()).unwrap_err();
        assert!(err.contains("`version`"), "{err}");
        assert!(record_from_json(b"{").is_err());
    }
}
