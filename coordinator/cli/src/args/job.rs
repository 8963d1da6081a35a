//! `reconstruct`'s job flags and how they map onto the job spec: the flags are the command
//! line's business, the [`JobSpec`] is what a job file, the coordinator and its store read.

use super::choice::choice;
use clap::Args;
use scatterfarm_job::options::{SearchMode, TiebreakMetric};
use scatterfarm_job::spec::{
    JobSpec, DEFAULT_ITERATIONS, DEFAULT_PERCENTILE, DEFAULT_PERMUTATIONS,
    DEFAULT_PHOTONS_PER_ITERATION, DEFAULT_SEED,
};
use scatterfarm_search::similarity::Metric;
use std::path::PathBuf;

/// `reconstruct`'s job flags, as given: each maps onto the [`JobSpec`] key of the same name
/// (dashes as underscores), which a job file gives instead.
#[derive(Debug, Clone, Args)]
pub struct JobArgs {
    /// Synthesize the target from this scene (a file or a built-in name); its map is the truth.
    #[arg(long, conflicts_with = "target", required_unless_present = "target")]
    pub scene: Option<String>,
    /// A captured observation set (NPY with its JSON sidecar) to reconstruct instead.
    #[arg(long, requires = "calibration")]
    pub target: Option<PathBuf>,
    /// A capture of a known homogeneous material (NPY with sidecar), to calibrate ε for --target.
    #[arg(long, requires = "target")]
    pub calibration: Option<PathBuf>,
    /// The calibration material's name (default: the first dictionary material that scatters).
    #[arg(long)]
    pub calibration_material: Option<String>,
    /// Candidate materials, comma-separated names (default: the scene's own materials).
    #[arg(long, value_delimiter = ',', conflicts_with = "random_materials")]
    pub dictionary: Option<Vec<String>>,
    /// Unknown materials: draw this many random materials per level instead of a dictionary.
    #[arg(long)]
    pub random_materials: Option<u32>,
    /// Bounds of random materials, e.g. sigma_s=0:1,sigma_a=0:0.03,g=0:1.
    #[arg(long, requires = "random_materials")]
    pub bounds: Option<String>,
    /// Random permutations per level (the paper's T).
    #[arg(long, default_value_t = DEFAULT_PERMUTATIONS)]
    pub permutations: u32,
    /// Simulation iterations per render.
    #[arg(long, default_value_t = DEFAULT_ITERATIONS)]
    pub iterations: u32,
    /// Photons per source per iteration.
    #[arg(long, default_value_t = DEFAULT_PHOTONS_PER_ITERATION)]
    pub photons_per_iteration: u32,
    /// Photons per source of a synthesized target (default: iterations × photons per iteration).
    #[arg(long)]
    pub target_photons: Option<u32>,
    /// ε is this percentile of the calibration differences.
    #[arg(long, default_value_t = DEFAULT_PERCENTILE)]
    pub percentile: f64,
    /// The similarity metric (paper, fast: within-epsilon; likelihood: deviance).
    #[arg(long, value_name = "METRIC", value_parser = choice::<Metric>())]
    pub metric: Option<Metric>,
    /// Search at this grid (a power of two, at most the scene's); default: the scene's grid,
    /// or 16 for a captured target.
    #[arg(long)]
    pub grid: Option<u32>,
    /// Override the boundary positions (target and search alike).
    #[arg(long)]
    pub positions: Option<u32>,
    /// Override the directions per position (target and search alike).
    #[arg(long)]
    pub directions: Option<u32>,
    /// The job seed: every random stream derives from it.
    #[arg(long, default_value_t = DEFAULT_SEED)]
    pub seed: u64,
    /// The search: `likelihood` (the quad-tree levels by the likelihood on common random
    /// numbers, then pixel-level refinement: the most accurate on the quality bench), `fast`
    /// (the quad-tree levels only, with racing and re-scoring) or `paper` (the paper's
    /// algorithm exactly). The options below switch one improvement on or off in any mode;
    /// `fast` and `likelihood` change their defaults (given after each as "fast: …",
    /// "likelihood: …").
    #[arg(long, default_value_t = SearchMode::Likelihood, value_parser = choice::<SearchMode>())]
    pub search: SearchMode,
    /// Common random numbers: every render of a level on one seed (fast, likelihood: true).
    #[arg(long, value_name = "BOOL")]
    pub common_random_numbers: Option<bool>,
    /// Request all M⁰-variants of a permutation (its step-2 renders) at once when it starts,
    /// so they render in parallel (fast, likelihood: true).
    #[arg(long, value_name = "BOOL")]
    pub early_step2: Option<bool>,
    /// Quad-tree levels the coarse stage runs, from level 0 (unless set all of them, that is
    /// log2 grid + 1; likelihood: auto); the refinement then starts from the last one's map (1: from the
    /// one-material map; auto: from level 0's where that material scatters and the sweeps
    /// screen differentially, else after every level).
    #[arg(long, value_name = "N|auto")]
    pub coarse_levels: Option<scatterfarm_search::CoarseLevels>,
    /// Photons per source of each level's renders, from level 0, comma-separated; the last
    /// holds for finer levels (paper: iterations × photons per iteration; fast: a tenth of it;
    /// likelihood: a quarter).
    #[arg(long, value_delimiter = ',', value_name = "N,N,...")]
    pub level_photons: Option<Vec<u32>>,
    /// Racing: render every candidate first with this share of the level's photons and
    /// spend the rest on the contenders; 1 turns it off (paper, likelihood: 1; fast: 0.25).
    #[arg(long, value_name = "SHARE")]
    pub race_share: Option<f64>,
    /// Racing drops a candidate whose first-stage score is this many standard errors behind
    /// the leader's (fast: 3).
    #[arg(long, value_name = "Z")]
    pub race_z: Option<f64>,
    /// Re-score a level's distinct finalists (each permutation's result, and the level's
    /// starting map) on one fresh seed with this many photons per source and keep the best;
    /// 0 turns it off (paper: 0; fast, likelihood: iterations × photons per iteration).
    #[arg(long, value_name = "N")]
    pub rescore_photons: Option<u32>,
    /// Scores closer than this many standard errors of their difference tie: a tie inside a
    /// step goes to the earlier candidate, between the steps to step 2, as in the paper's
    /// exact ties (paper, likelihood: 0; fast: 1).
    #[arg(long, value_name = "Z")]
    pub tie_z: Option<f64>,
    /// Where within-ε is saturated (see --tiebreak-saturation), this metric decides between
    /// candidates tied on it; `off` keeps the paper's tie rule alone (paper: off; fast:
    /// l2-stabilized).
    #[arg(long, value_name = "METRIC", value_parser = choice::<TiebreakMetric>())]
    pub tiebreak: Option<TiebreakMetric>,
    /// The tiebreak must win by more than this many standard errors of the difference
    /// (fast: 1).
    #[arg(long, value_name = "Z")]
    pub tiebreak_z: Option<f64>,
    /// Within-ε counts as saturated for a map that misses at most this many times the share
    /// of observations a perfect map misses (1 − percentile/100): the tiebreak decides only
    /// there (fast: 3, a score of 0.997 at the 99.9th percentile).
    #[arg(long, value_name = "FACTOR")]
    pub tiebreak_saturation: Option<f64>,
    /// After the quad-tree levels, refine single pixels and object positions by the
    /// likelihood, accepting a change only when it beats the current map by more than
    /// --refine-z paired standard errors on a fresh seed (needs --metric deviance;
    /// likelihood: true).
    #[arg(long, value_name = "BOOL")]
    pub refine: Option<bool>,
    /// Photons per source of a refinement sweep's renders (likelihood: 25 × iterations ×
    /// photons per iteration for a differential sweep, 102 400 at 8 × 512; an eighth of that
    /// for a direct one).
    #[arg(long, value_name = "N")]
    pub refine_photons: Option<u32>,
    /// Photons per source of a refinement's confirmation renders (likelihood: 50 ×
    /// iterations × photons per iteration).
    #[arg(long, value_name = "N")]
    pub refine_confirm_photons: Option<u32>,
    /// Photons per source of a differential sweep's direct renders (the changes it cannot
    /// reweight, e.g. a scattering pixel in a transmissive background) and of the render of
    /// the current map they are paired with (default: an eighth of the sweep's photons).
    #[arg(long, value_name = "N")]
    pub refine_direct_photons: Option<u32>,
    /// A refinement change must beat the current map by more than this many paired standard
    /// errors (likelihood: 3).
    #[arg(long, value_name = "Z")]
    pub refine_z: Option<f64>,
    /// The most refinement sweeps (likelihood: 24).
    #[arg(long, value_name = "N")]
    pub refine_sweeps: Option<u32>,
    /// Whether refinement sweeps also move whole objects by one pixel (likelihood: true).
    #[arg(long, value_name = "BOOL")]
    pub refine_moves: Option<bool>,
    /// How a refinement sweep scores its changes: `direct` renders each changed map;
    /// `differential` estimates them all from one render of the current map (either engine;
    /// on the farm the workers render and score them), rendering directly only the changes it
    /// cannot reweight (likelihood: differential).
    #[arg(long, value_name = "HOW", value_parser = choice::<scatterfarm_search::refine::Screen>())]
    pub refine_screen: Option<scatterfarm_search::refine::Screen>,
    /// How many times refinement may double its sweep and confirmation photons where it would
    /// otherwise end (likelihood: 2).
    #[arg(long, value_name = "N")]
    pub refine_escalations: Option<u32>,
    /// Whether refinement sweeps also set each connected region of two pixels or more
    /// (objects and background) wholly to each other candidate material (likelihood: true).
    #[arg(long, value_name = "BOOL")]
    pub refine_recolour: Option<bool>,
    /// Whether refinement sweeps also swap each pair of neighbouring pixels (8-connected) of
    /// different materials: one object pixel moved at a time, keeping the object's size
    /// (likelihood: false).
    #[arg(long, value_name = "BOOL")]
    pub refine_swaps: Option<bool>,
    /// Whether refinement sweeps also set each 2 × 2 block and each pair of neighbouring
    /// pixels (side by side or one above the other) wholly to each candidate material, and
    /// each object's bounding box grown or shrunk by one row or column on each side: an
    /// object's edge grown, shrunk or shifted several pixels at once, with their signal
    /// together (likelihood: false).
    #[arg(long, value_name = "BOOL")]
    pub refine_blocks: Option<bool>,
    /// Where refinement would end, a simplification round first: every pixel and region not
    /// of the background set to it unless that loses to the current map by more than Z paired
    /// standard errors, so what the target cannot tell from the background (an opaque pixel
    /// no photon reaches) becomes the background; sweeps then go on (likelihood: off).
    #[arg(long, value_name = "Z")]
    pub refine_simplify_z: Option<f64>,
    /// Where refinement would end (before it escalates), a growth round first: each object
    /// of at most four pixels, not of the background, grown by its 8-connected neighbours and
    /// set wholly to each other candidate material, and its bounding box grown by one row or
    /// column on each side in turn and filled with its material, each grown map rendered on
    /// its own at a quarter of the sweep's photons: a small object of a strong material standing in for a
    /// larger one of a weaker material is then one change; sweeps go on from what it
    /// changes. auto: only where the refinement starts from a one-material map (level 0's,
    /// where --coarse-levels auto stops there), not where the quad-tree levels built the
    /// objects (likelihood: auto).
    #[arg(long, value_name = "true|false|auto")]
    pub refine_grow: Option<scatterfarm_search::refine::Growth>,
    /// A growth round in which no grown map wins tries the best of them (the sweeps go on
    /// from it, and the map they reach is kept only if it beats the round's start) only where
    /// that map's paired z against the current map is above Z (likelihood: every such round
    /// tries it; -inf: the same).
    #[arg(long, value_name = "Z", allow_hyphen_values = true)]
    pub refine_grow_trial_z: Option<f64>,
    /// A refinement sweep of a map swept before (after a stall, or escalated) renders
    /// directly only the changes whose paired z on its last sweep was above this; changes a
    /// differential render estimates are always tried (likelihood: -1; -inf: every change).
    #[arg(long, value_name = "Z", allow_hyphen_values = true)]
    pub refine_retest_z: Option<f64>,
}

impl JobArgs {
    /// The job spec these flags give (the spec checks its values when a plan resolves it).
    pub fn into_spec(self) -> JobSpec {
        JobSpec {
            scene: self.scene,
            target: self.target,
            calibration: self.calibration,
            calibration_material: self.calibration_material,
            dictionary: self.dictionary,
            random_materials: self.random_materials,
            bounds: self.bounds,
            permutations: self.permutations,
            iterations: self.iterations,
            photons_per_iteration: self.photons_per_iteration,
            target_photons: self.target_photons,
            percentile: self.percentile,
            metric: self.metric,
            grid: self.grid,
            positions: self.positions,
            directions: self.directions,
            seed: self.seed,
            search: self.search,
            common_random_numbers: self.common_random_numbers,
            early_step2: self.early_step2,
            coarse_levels: self.coarse_levels,
            level_photons: self.level_photons,
            race_share: self.race_share,
            race_z: self.race_z,
            rescore_photons: self.rescore_photons,
            tie_z: self.tie_z,
            tiebreak: self.tiebreak,
            tiebreak_z: self.tiebreak_z,
            tiebreak_saturation: self.tiebreak_saturation,
            refine: self.refine,
            refine_photons: self.refine_photons,
            refine_confirm_photons: self.refine_confirm_photons,
            refine_direct_photons: self.refine_direct_photons,
            refine_z: self.refine_z,
            refine_sweeps: self.refine_sweeps,
            refine_moves: self.refine_moves,
            refine_screen: self.refine_screen,
            refine_escalations: self.refine_escalations,
            refine_recolour: self.refine_recolour,
            refine_swaps: self.refine_swaps,
            refine_blocks: self.refine_blocks,
            refine_simplify_z: self.refine_simplify_z,
            refine_grow: self.refine_grow,
            refine_grow_trial_z: self.refine_grow_trial_z,
            refine_retest_z: self.refine_retest_z,
            ..JobSpec::default()
        }
    }
}
