//! The CPU engine: the reference implementation of `docs/model.md`, parallel over sources with rayon;
//! its differential render (per-pixel tallies and photon weights) is in [`differential`].
//!
//! Each (assignment, source) pair is traced independently into its own row, so the counts do not
//! depend on the number of threads or on how the photon range is split.

use crate::rng::PhotonStream;
use crate::transport::{trace_photon, Fate, Medium};
use rayon::prelude::*;
use scatterfarm_model::engine::{
    validate_batch, CountMatrix, Engine, EngineError, EngineFingerprint, RenderBatch, RenderOutput,
};
use scatterfarm_model::{Change, DifferentialOutput, Geometry, Material, PhotonRange, RenderItem};

mod differential;
pub use differential::MAX_CHANGES;

/// Bumped whenever a change to the CPU transport changes its counts.
pub const CPU_ENGINE_VERSION: &str = "cpu-2";

/// The rayon-parallel CPU engine.
#[derive(Debug, Clone, Default)]
pub struct CpuEngine {
    /// Runs in this pool when set (tests pin thread counts); the global pool otherwise.
    pool: Option<std::sync::Arc<rayon::ThreadPool>>,
}

impl CpuEngine {
    pub fn new() -> Self {
        CpuEngine { pool: None }
    }

    /// An engine that renders on exactly `threads` threads.
    pub fn with_threads(threads: usize) -> Result<Self, EngineError> {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .map_err(|e| {
                EngineError::Unavailable(format!("cannot start {threads} threads: {e}"))
            })?;
        Ok(CpuEngine {
            pool: Some(std::sync::Arc::new(pool)),
        })
    }

    fn render_all(&self, batch: &RenderBatch<'_>) -> Vec<RenderOutput> {
        let geo = batch.geometry;
        let sources = geo.sources();
        let bins = geo.bins();
        let media: Vec<Medium> = batch
            .items
            .iter()
            .map(|it| Medium::new(geo, batch.table, &it.assignment))
            .collect();
        let rays: Vec<_> = (0..sources).map(|i| geo.source_ray(i)).collect();
        let photons = batch.photons;
        // One task per (item, source): a row of counts and its scatter events.
        let rows: Vec<(Vec<u32>, u64)> = (0..batch.items.len() * sources)
            .into_par_iter()
            .map(|task| {
                let item = task / sources;
                let source = task % sources;
                let seed = batch.items[item].seed;
                let mut row = vec![0u32; bins];
                let mut scatters = 0u64;
                for photon in u64::from(photons.first)..photons.end() {
                    // validate_batch keeps the range within 32-bit photon indices.
                    let mut rng = PhotonStream::new(seed, source as u32, photon as u32);
                    let trace = trace_photon(&media[item], &rays[source], &mut rng);
                    scatters += u64::from(trace.scatters);
                    if let Fate::Exited(bin) = trace.fate {
                        row[bin] += 1;
                    }
                }
                (row, scatters)
            })
            .collect();
        rows.chunks(sources)
            .map(|item_rows| {
                let mut counts = CountMatrix::zeros(sources, bins);
                let mut scatter_events = 0;
                for (source, (row, s)) in item_rows.iter().enumerate() {
                    counts.counts[source * bins..(source + 1) * bins].copy_from_slice(row);
                    scatter_events += s;
                }
                RenderOutput {
                    counts,
                    scatter_events,
                }
            })
            .collect()
    }
}

impl Engine for CpuEngine {
    fn fingerprint(&self) -> EngineFingerprint {
        EngineFingerprint {
            engine: "cpu".into(),
            adapter: "cpu".into(),
            driver: format!("{}-{}", std::env::consts::ARCH, std::env::consts::OS),
            version: CPU_ENGINE_VERSION.into(),
        }
    }

    fn render(&self, batch: &RenderBatch<'_>) -> Result<Vec<RenderOutput>, EngineError> {
        validate_batch(batch)?;
        Ok(match &self.pool {
            Some(pool) => pool.install(|| self.render_all(batch)),
            None => self.render_all(batch),
        })
    }

    fn renders_differentially(&self) -> bool {
        true
    }

    fn render_differential(
        &self,
        geometry: Geometry,
        table: &[Material],
        item: &RenderItem,
        photons: PhotonRange,
        changes: &[Change],
    ) -> Result<DifferentialOutput, EngineError> {
        let run = || differential::render_differential(geometry, table, item, photons, changes);
        match &self.pool {
            Some(pool) => pool.install(run),
            None => run(),
        }
    }
}

#[cfg(test)]
mod tests;
