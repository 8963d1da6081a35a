//! The files `reconstruct` writes, made from a job's result (or its current best), and read
//! back from the store once it finished.
//!
//! Drawing them (PNG encoding, a convergence plot) takes tens of milliseconds, so it never runs
//! under the scheduler's lock: [`Job::output_source`] copies what they are made from, under
//! the lock, and [`OutputSource::render`] draws them after it. A job that finishes is marked
//! [`Job::outputs_due`]; the farm stores its outputs once the call that finished it has
//! released the lock (`Farm::store_due_outputs`). A coordinator killed before they were stored
//! draws them again from the checkpoint when they are asked for: the same files.

use super::Job;
use crate::store::Store;
use anyhow::{Context, Result};
use scatterfarm_job::outcome::{self, Summary};
use std::collections::BTreeMap;

/// The output file every result has, stored last: the stored outputs of a job count only when
/// it is there (a coordinator killed while storing them leaves no partial set).
const LAST_OUTPUT: &str = "report.json";

/// The output files a finished job stores, as blobs `output/NAME`.
const OUTPUT_FILES: [&str; 6] = [
    "convergence.png",
    "materials.npy",
    "materials.json",
    "reconstruction.png",
    "maps.png",
    LAST_OUTPUT,
];

/// The blob key of the output file `name`.
pub(super) fn output_key(name: &str) -> String {
    format!("output/{name}")
}

/// What a job's output files are made from, copied out of the job.
#[derive(Debug, Clone)]
pub struct OutputSource {
    job: String,
    config: scatterfarm_job::report::Configuration,
    truth: Option<scatterfarm_model::Scene>,
    search: scatterfarm_search::Search,
    assignment: Vec<u16>,
    similarity: f64,
    epsilons: BTreeMap<u32, f64>,
    used: scatterfarm_search::driver::Consumption,
    photons_simulated: u64,
    wall_seconds: f64,
    engine: String,
    reproducible: bool,
}

impl OutputSource {
    /// The job these outputs are of.
    pub fn job(&self) -> &str {
        &self.job
    }

    /// The output files, as file name → bytes.
    pub fn render(&self) -> Result<BTreeMap<String, Vec<u8>>> {
        let dir = tempfile::tempdir().context("cannot create a scratch folder")?;
        outcome::write_outputs(
            dir.path(),
            &Summary {
                config: &self.config,
                truth: self.truth.as_ref(),
                search: &self.search,
                assignment: &self.assignment,
                similarity: self.similarity,
                epsilons: &self.epsilons,
                used: self.used,
                photons_simulated: self.photons_simulated,
                wall_seconds: self.wall_seconds,
                engine: self.engine.clone(),
                reproducible: self.reproducible,
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

    /// Draws the outputs and stores them, [`LAST_OUTPUT`] last.
    pub fn store(&self, store: &dyn Store) -> Result<()> {
        let files = self.render()?;
        let last = files.get(LAST_OUTPUT);
        for (name, bytes) in files.iter().filter(|(name, _)| *name != LAST_OUTPUT) {
            store.put_blob(&self.job, &output_key(name), bytes)?;
        }
        if let Some(bytes) = last {
            store.put_blob(&self.job, &output_key(LAST_OUTPUT), bytes)?;
        }
        Ok(())
    }
}

/// The stored outputs of job `job`, if a complete set was stored.
pub fn stored_outputs(store: &dyn Store, job: &str) -> Result<Option<BTreeMap<String, Vec<u8>>>> {
    if store.blob(job, &output_key(LAST_OUTPUT))?.is_none() {
        return Ok(None);
    }
    let mut files = BTreeMap::new();
    for name in OUTPUT_FILES {
        if let Some(b) = store.blob(job, &output_key(name))? {
            files.insert(name.to_string(), b);
        }
    }
    Ok(Some(files))
}

impl Job {
    /// What the outputs `reconstruct` writes are made from: the final result, or the current
    /// best of a running job; an error before anything has been scored.
    pub fn output_source(&self) -> Result<OutputSource> {
        let search = &self.checkpoint.search;
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
        Ok(OutputSource {
            job: self.id.clone(),
            config: self.plan.config.clone(),
            truth: self.plan.truth.clone(),
            search: search.clone(),
            assignment,
            similarity,
            epsilons: self.checkpoint.epsilons.clone(),
            used: self.checkpoint.used,
            photons_simulated: self.checkpoint.photons_simulated,
            wall_seconds: self.checkpoint.active_seconds,
            engine: self.engine_label(),
            reproducible: self.reproducible(),
        })
    }

    /// The outputs of the job as it is now (drawn on the calling thread).
    pub fn outputs(&self) -> Result<BTreeMap<String, Vec<u8>>> {
        self.output_source()?.render()
    }
}
