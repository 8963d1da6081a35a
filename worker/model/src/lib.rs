//! The scatterfarm model: what a medium, its materials, a scene and an observation are, and the
//! contract every render engine fulfils (`docs/model.md`). Nothing here renders, talks to a
//! network or touches a GPU; every other crate builds on these types.
//!
//! - [`geometry`]: the square medium, boundary arc length, sources and bins.
//! - [`material`]: materials, the paper's dictionary and material tables.
//! - [`scene`]: scene files, parsed and validated; [`builtin`]: the built-in scenes.
//! - [`engine`]: the [`Engine`] trait, render batches, count matrices and engine fingerprints.
//! - [`differential`]: differential renders: the changes one render also estimates, and which
//!   material changes a photon weight covers, and the chunked render both ends run.
//! - [`likelihood`]: the deviance of a render against a target, split into blocks for paired
//!   comparisons; both the coordinator and a worker score with it.

pub mod builtin;
pub mod differential;
pub mod engine;
pub mod geometry;
pub mod likelihood;
pub mod material;
pub mod scene;

pub use differential::{Change, DifferentialOutput};
pub use engine::{
    CountMatrix, Engine, EngineError, EngineFingerprint, PhotonRange, RenderBatch, RenderItem,
    RenderOutput,
};
pub use geometry::Geometry;
pub use likelihood::Target;
pub use material::{Material, MaterialTable};
pub use scene::{Scene, SceneError};
