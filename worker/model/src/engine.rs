//! The `Engine` trait every renderer implements, and the types a render speaks in.
//!
//! A render is a batch of material assignments over one geometry and one material table, each
//! with its own seed, for the photon range `[first, first + count)` of every source. It returns
//! integer counts per (source, bin) for each assignment. Engines know nothing of the network.

use crate::geometry::Geometry;
use crate::material::Material;
use serde::{Deserialize, Serialize};
use std::fmt;
use thiserror::Error;

/// What makes counts bit-exact: engine kind, adapter, driver and engine version (`docs/model.md`).
#[derive(Debug, Clone, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct EngineFingerprint {
    /// `cpu` or `gpu`.
    pub engine: String,
    /// The device the engine runs on.
    pub adapter: String,
    /// The driver (GPU) or the target triple (CPU).
    pub driver: String,
    /// The engine or shader version: bumped whenever its counts change.
    pub version: String,
}

impl EngineFingerprint {
    /// The canonical key of the fingerprint, `engine/adapter/driver/version`: what jobs are
    /// pinned to and renders are identified with. [`fmt::Display`] writes the same text.
    pub fn key(&self) -> String {
        self.to_string()
    }

    /// The fingerprint of counts that replay this engine's under another name: the version
    /// becomes `version+tag`, so such counts never mix with the engine's own.
    pub fn tagged(self, tag: &str) -> Self {
        EngineFingerprint {
            version: format!("{}+{tag}", self.version),
            ..self
        }
    }
}

/// Writes the canonical key (see [`EngineFingerprint::key`]).
impl fmt::Display for EngineFingerprint {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{}/{}/{}/{}",
            self.engine, self.adapter, self.driver, self.version
        )
    }
}

/// Photons `[first, first + count)` of every source.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct PhotonRange {
    pub first: u32,
    pub count: u32,
}

impl PhotonRange {
    /// Photons `[0, count)`.
    pub fn first_n(count: u32) -> Self {
        PhotonRange { first: 0, count }
    }

    /// `count` more photons after `self`.
    pub fn end(&self) -> u64 {
        u64::from(self.first) + u64::from(self.count)
    }
}

/// One material assignment to render, with its own seed.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RenderItem {
    /// `N²` indices into the batch's material table, row-major, row 0 at the top.
    pub assignment: Vec<u16>,
    pub seed: u64,
}

/// Everything an engine needs for one submission.
#[derive(Debug, Clone)]
pub struct RenderBatch<'a> {
    pub geometry: Geometry,
    pub table: &'a [Material],
    pub items: &'a [RenderItem],
    pub photons: PhotonRange,
}

/// Integer photon counts per (source, bin), row-major `sources × bins`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CountMatrix {
    pub sources: usize,
    pub bins: usize,
    pub counts: Vec<u32>,
}

impl CountMatrix {
    pub fn zeros(sources: usize, bins: usize) -> Self {
        CountMatrix {
            sources,
            bins,
            counts: vec![0; sources * bins],
        }
    }

    /// Row `source`.
    pub fn row(&self, source: usize) -> &[u32] {
        &self.counts[source * self.bins..(source + 1) * self.bins]
    }

    /// Adds another partial render of the same identity (a later photon range).
    pub fn add(&mut self, other: &CountMatrix) -> Result<(), EngineError> {
        if other.sources != self.sources || other.bins != self.bins {
            return Err(EngineError::ShapeMismatch {
                expected: (self.sources, self.bins),
                got: (other.sources, other.bins),
            });
        }
        for (a, b) in self.counts.iter_mut().zip(&other.counts) {
            *a += *b;
        }
        Ok(())
    }

    /// Photons counted in some bin.
    pub fn total(&self) -> u64 {
        self.counts.iter().map(|&c| u64::from(c)).sum()
    }
}

/// One assignment's result: its counts and what the transport did.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RenderOutput {
    pub counts: CountMatrix,
    /// Scattering events along all paths (for throughput figures).
    pub scatter_events: u64,
}

/// Why a render failed.
#[derive(Debug, Error)]
pub enum EngineError {
    #[error("assignment {item} has {got} pixels, the geometry needs {expected}")]
    AssignmentSize {
        item: usize,
        expected: usize,
        got: usize,
    },
    #[error("assignment {item} uses material index {index}, the table has {table} materials")]
    MaterialIndex {
        item: usize,
        index: u16,
        table: usize,
    },
    #[error("photon range {first}..{end} does not fit in 32-bit photon indices")]
    PhotonRange { first: u32, end: u64 },
    #[error("count matrices differ in shape: expected {expected:?}, got {got:?}")]
    ShapeMismatch {
        expected: (usize, usize),
        got: (usize, usize),
    },
    #[error("invalid material {index}: {source}")]
    Material {
        index: usize,
        source: crate::material::MaterialError,
    },
    #[error("invalid geometry: {0}")]
    Geometry(#[from] crate::geometry::GeometryError),
    #[error("engine unavailable: {0}")]
    Unavailable(String),
    #[error("device error: {0}")]
    Device(String),
    #[error("not supported: {0}")]
    Unsupported(String),
}

/// A renderer of binned lightfields.
pub trait Engine: Send + Sync {
    /// Identifies the counts this engine produces (`docs/model.md`, "Engine fingerprint").
    fn fingerprint(&self) -> EngineFingerprint;

    /// Renders every item of the batch; outputs are in item order.
    fn render(&self, batch: &RenderBatch<'_>) -> Result<Vec<RenderOutput>, EngineError>;

    /// Whether [`Engine::render_differential`] is implemented (a worker tells the coordinator,
    /// which leases differential renders only to such engines).
    fn renders_differentially(&self) -> bool {
        false
    }

    /// Renders `item` over photons `photons` of every source and, from the same photons,
    /// estimates every change of it (`docs/model.md`, "Differential renders"). Engines that do
    /// not tally per-pixel paths say so with [`EngineError::Unsupported`].
    fn render_differential(
        &self,
        geometry: Geometry,
        table: &[Material],
        item: &RenderItem,
        photons: PhotonRange,
        changes: &[crate::differential::Change],
    ) -> Result<crate::differential::DifferentialOutput, EngineError> {
        let _ = (geometry, table, item, photons, changes);
        Err(EngineError::Unsupported(format!(
            "the {} engine does not render differentially",
            self.fingerprint().engine
        )))
    }
}

/// Checks what every engine must check before it renders.
pub fn validate_batch(batch: &RenderBatch<'_>) -> Result<(), EngineError> {
    batch.geometry.validate()?;
    for (index, m) in batch.table.iter().enumerate() {
        m.validate()
            .map_err(|source| EngineError::Material { index, source })?;
    }
    let pixels = batch.geometry.pixels();
    for (item, it) in batch.items.iter().enumerate() {
        if it.assignment.len() != pixels {
            return Err(EngineError::AssignmentSize {
                item,
                expected: pixels,
                got: it.assignment.len(),
            });
        }
        if let Some(&index) = it
            .assignment
            .iter()
            .find(|&&i| usize::from(i) >= batch.table.len())
        {
            return Err(EngineError::MaterialIndex {
                item,
                index,
                table: batch.table.len(),
            });
        }
    }
    if batch.photons.end() > u64::from(u32::MAX) + 1 {
        return Err(EngineError::PhotonRange {
            first: batch.photons.first,
            end: batch.photons.end(),
        });
    }
    Ok(())
}
