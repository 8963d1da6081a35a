//! The scatterfarm coordinator library: what the `scatterfarm` binary is built from.
//!
//! - [`scene_source`]: turns a command-line `SCENE` (a file or a built-in name) into a scene.
//! - [`observation`]: observation files (float32 NPY plus JSON sidecar), written atomically.
//! - [`picture`]: PNG drawings of material maps and observation matrices.
//! - [`engines`]: picking a render engine from `--engine`.
//! - [`seeds`]: the seed streams every random use derives from the job seed.
//! - [`similarity`]: similarity metrics and the calibration of ε.
//! - [`search`]: the paper's quad-tree permutation search as a pure state machine.
//! - [`params`]: a reconstruction's parameters (`reconstruct`'s flags, a job file's keys).
//! - [`inputs`]: the input files a reconstruction names, held in memory.
//! - [`plan`]: parameters and inputs resolved; the renders needed before the search.
//! - [`reconstruction`]: rendering a plan's setup and driving the search in one process.
//! - [`prefixes`]: racing's first-stage counts, which a contender's full render extends.
//! - [`farm`]: the coordinator service: jobs, leases, the store, gRPC.
//! - [`report`]: the contents of `report.json`.
//! - [`outcome`]: a reconstruction's outputs and its measures against a known truth.
//! - [`commands`]: one module per subcommand.

pub mod commands;
pub mod engines;
pub mod farm;
pub mod inputs;
pub mod observation;
pub mod outcome;
pub mod params;
pub mod picture;
pub mod plan;
pub mod prefixes;
pub mod reconstruction;
pub mod report;
pub mod scene_source;
pub mod search;
pub mod seeds;
pub mod similarity;
