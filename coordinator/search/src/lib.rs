//! The scatterfarm search: the quad-tree permutation search as a pure state machine, how its
//! renders are scored, and the one driver that runs it against an engine. The farm runs the same
//! machine and scoring; nothing here does I/O beyond calling an `Engine`.
//!
//! - [`machine`]: the search state machine (`docs/model.md`, "Search"): requests out, scores in.
//! - [`seeds`]: the seed streams every random use derives from the job seed.
//! - [`similarity`]: similarity metrics and the calibration of ε.
//! - [`likelihood`]: the deviance score and paired comparisons on common random numbers.
//! - [`refine`]: the pixel-level refinement stage after the quad-tree search.
//! - [`convergence`]: the score and consumption at the end of every level and sweep.
//! - [`prefixes`]: racing's first-stage counts, which a contender's full render extends.
//! - [`identity`]: a render's identity, under which its score is cached.
//! - [`steps`]: the one step driver: cached scores, missing renders grouped, consumption.
//! - [`chunks`]: rendering in photon chunks with any engine.
//! - [`driver`]: what a search scores against and consumes; running it in one process.

pub mod chunks;
pub mod convergence;
pub mod driver;
pub mod identity;
pub mod likelihood;
pub mod machine;
pub mod prefixes;
pub mod refine;
pub mod seeds;
pub mod similarity;
pub mod steps;

pub use driver::{Budget, Consumption, Scoring};
pub use machine::{
    Bounds, Candidates, ChangeScore, CoarseLevels, LevelResult, Photons, Progress, Race,
    RenderRequest, Score, Search, SearchConfig, SearchError, Secondary, Seeding, Tiebreak,
};
