//! The scatterfarm render engines: Monte Carlo photon transport through a pixel grid, on the CPU
//! and on a GPU, both implementing `scatterfarm_model::Engine` (`docs/model.md`, "Transport").
//! The engines know nothing of the farm or its protocol.
//!
//! - [`rng`]: Philox4x32-10, the counter-based generator keyed by (seed, source, photon).
//! - [`phase`]: flatland Henyey–Greenstein sampling.
//! - [`rules`]: the transport rules both engines apply on the host (tolerances, the grid-line
//!   start rule, uniform blocks), defined once.
//! - [`transport`]: one photon's path through the pixel grid (the CPU engine's, mirrored by the
//!   shader).
//! - [`cpu`]: the rayon CPU engine.
//! - [`gpu`]: the wgpu engine (WGSL compute shader in `shaders/`), adapters and their choice.
//! - `reweighting_check` (tests only): the scene both engines' differential tests render, and
//!   the check they pass: reweighted counts against direct renders of the changed map.

pub mod cpu;
pub mod gpu;
pub mod phase;
#[cfg(test)]
mod reweighting_check;
pub mod rng;
pub mod rules;
pub mod transport;

pub use cpu::CpuEngine;
pub use gpu::GpuEngine;
