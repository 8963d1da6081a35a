//! A scatterfarm reconstruction job, whichever driver runs it: its spec and input files,
//! the plan they resolve to (geometries, candidates, the fresh search, its setup renders), and
//! its outputs (the map, pictures, `report.json`, measures against a known truth).
//!
//! - [`spec`]: the versioned job spec (a job file, the wire text, the stored record).
//! - [`options`]: the search mode and the search options a spec resolves to.
//! - [`scene_source`]: turns a command-line `SCENE` (a file or a built-in name) into a scene.
//! - [`observation`]: observation files (float32 NPY plus JSON sidecar), written atomically.
//! - [`inputs`]: the input files a reconstruction names, held in memory.
//! - [`plan`]: parameters and inputs resolved; the renders needed before the search.
//! - [`setup`]: rendering a plan's setup renders in one process.
//! - [`report`]: the contents of `report.json`.
//! - [`picture`]: PNG drawings of material maps and observation matrices.
//! - [`convergence_plot`]: the convergence curve as a PNG and as SVG.
//! - [`outcome`]: a reconstruction's outputs and its measures against a known truth.

pub mod convergence_plot;
pub mod inputs;
pub mod observation;
pub mod options;
pub mod outcome;
pub mod picture;
pub mod plan;
pub mod report;
pub mod scene_source;
pub mod setup;
pub mod spec;
pub mod truth_check;
