//! The scatterfarm worker library: everything about rendering binned lightfields.
//!
//! - [`geometry`]: the square medium, boundary arc length, sources and bins (`model.md`).
//! - [`material`]: materials, the paper's dictionary and material tables.
//! - [`scene`]: scene files, parsed and validated; [`builtin`]: the built-in scenes.
//! - [`rng`]: Philox4x32-10, the counter-based generator keyed by (seed, source, photon).
//! - [`phase`]: flatland Henyey–Greenstein sampling.
//! - [`transport`]: one photon's path through the pixel grid.
//! - [`engine`]: the `Engine` trait and render types; [`cpu`]: the rayon CPU engine.
//! - [`gpu`]: the wgpu engine (WGSL compute shader in `shaders/`), adapters and their choice.
//! - [`agent`]: the worker process's gRPC side: register, lease, render, return the counts (the
//!   only module that speaks the protocol).

pub mod agent;
pub mod builtin;
pub mod cpu;
pub mod engine;
pub mod geometry;
pub mod gpu;
pub mod material;
pub mod phase;
pub mod rng;
pub mod scene;
pub mod transport;

pub use cpu::CpuEngine;
pub use engine::{
    CountMatrix, Engine, EngineError, EngineFingerprint, PhotonRange, RenderBatch, RenderItem,
    RenderOutput,
};
pub use geometry::Geometry;
pub use material::{Material, MaterialTable};
pub use scene::{Scene, SceneError};
