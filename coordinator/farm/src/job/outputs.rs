//! The files `reconstruct` writes, made from a job's result (or its current best), and read
//! back from the store once it finished.

use super::Job;
use crate::store::Store;
use anyhow::{Context, Result};
use scatterfarm_job::outcome::{self, Summary};
use std::collections::BTreeMap;

/// The output files a finished job stores, as blobs `output/NAME`.
const OUTPUT_FILES: [&str; 6] = [
    "report.json",
    "convergence.png",
    "materials.npy",
    "materials.json",
    "reconstruction.png",
    "maps.png",
];

/// The blob key of the output file `name`.
pub(super) fn output_key(name: &str) -> String {
    format!("output/{name}")
}

impl Job {
    /// The outputs `reconstruct` writes, as file name → bytes: the final result, or the current
    /// best of a running job; an error before anything has been scored.
    pub fn outputs(&self) -> Result<BTreeMap<String, Vec<u8>>> {
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
        let dir = tempfile::tempdir().context("cannot create a scratch folder")?;
        outcome::write_outputs(
            dir.path(),
            &Summary {
                config: &self.plan.config,
                truth: self.plan.truth.as_ref(),
                search,
                assignment: &assignment,
                similarity,
                epsilons: &self.checkpoint.epsilons,
                used: self.checkpoint.used,
                photons_simulated: self.checkpoint.photons_simulated,
                wall_seconds: self.checkpoint.active_seconds,
                engine: self.engine_label(),
                reproducible: self.reproducible(),
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

    /// Stores the outputs of the job as it is now.
    pub(super) fn store_outputs(&self, store: &dyn Store) -> Result<()> {
        for (name, bytes) in &self.outputs()? {
            store.put_blob(&self.id, &output_key(name), bytes)?;
        }
        Ok(())
    }

    /// The stored outputs of a finished job.
    pub fn stored_outputs(&self, store: &dyn Store) -> Result<BTreeMap<String, Vec<u8>>> {
        let mut files = BTreeMap::new();
        for name in OUTPUT_FILES {
            if let Some(b) = store.blob(&self.id, &output_key(name))? {
                files.insert(name.to_string(), b);
            }
        }
        if files.is_empty() {
            return self.outputs();
        }
        Ok(files)
    }
}
