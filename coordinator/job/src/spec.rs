//! The job spec: what to reconstruct and how, as one versioned serde type. A job file, the
//! text a submission sends to the coordinator and the coordinator's stored record are all this
//! type, so renaming a command-line flag (the binary maps its flags onto it) never changes what
//! is stored. Resolving its search options is [`crate::options`]'s job.

use crate::options::{SearchMode, TiebreakMetric};
use anyhow::{Context, Result};
use scatterfarm_search::refine::Growth;
use scatterfarm_search::similarity::Metric;
use scatterfarm_search::CoarseLevels;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// The layout of [`JobSpec`] this build reads and writes.
pub const SPEC_VERSION: u32 = 1;
/// The paper's T.
pub const DEFAULT_PERMUTATIONS: u32 = 10;
/// The paper's iterations per render.
pub const DEFAULT_ITERATIONS: u32 = 100;
/// The paper's photons per source per iteration.
pub const DEFAULT_PHOTONS_PER_ITERATION: u32 = 512;
/// The paper's k.
pub const DEFAULT_PERCENTILE: f64 = 99.9;
/// The default job seed.
pub const DEFAULT_SEED: u64 = 1;

/// What to reconstruct and how: a job file's keys, the wire text and the stored record. See
/// `scatterfarm reconstruct --help` for each key (its flag is the key with dashes).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct JobSpec {
    /// The spec's layout ([`SPEC_VERSION`]); a job file may leave it out.
    pub version: u32,
    /// Synthesize the target from this scene (a file or a built-in name); its map is the truth.
    pub scene: Option<String>,
    /// A captured observation set (NPY with its JSON sidecar) to reconstruct instead.
    pub target: Option<PathBuf>,
    /// A capture of a known homogeneous material (NPY with sidecar), to calibrate ε for --target.
    pub calibration: Option<PathBuf>,
    /// The calibration material's name (default: the first dictionary material that scatters).
    pub calibration_material: Option<String>,
    /// Candidate materials, comma-separated names (default: the scene's own materials).
    pub dictionary: Option<Vec<String>>,
    /// Unknown materials: draw this many random materials per level instead of a dictionary.
    pub random_materials: Option<u32>,
    /// Bounds of random materials, e.g. sigma_s=0:1,sigma_a=0:0.03,g=0:1.
    pub bounds: Option<String>,
    /// Random permutations per level (the paper's T).
    pub permutations: u32,
    /// Simulation iterations per render.
    pub iterations: u32,
    /// Photons per source per iteration.
    pub photons_per_iteration: u32,
    /// Photons per source of a synthesized target (default: iterations × photons per iteration).
    pub target_photons: Option<u32>,
    /// ε is this percentile of the calibration differences.
    pub percentile: f64,
    /// The similarity metric.
    pub metric: Option<Metric>,
    /// Search at this grid (a power of two, at most the scene's); default: the scene's grid,
    /// or 16 for a captured target.
    pub grid: Option<u32>,
    /// Override the boundary positions (target and search alike).
    pub positions: Option<u32>,
    /// Override the directions per position (target and search alike).
    pub directions: Option<u32>,
    /// The job seed: every random stream derives from it.
    pub seed: u64,
    /// The search: `likelihood` (the default: the quad-tree levels, then pixel-level
    /// refinement by the likelihood), `fast` (the quad-tree levels only) or `paper` (the
    /// paper's algorithm exactly). The options below switch one improvement on or off in any
    /// mode; `fast` and `likelihood` change their defaults.
    pub search: SearchMode,
    /// Common random numbers: every render of a level on one seed (fast: true).
    pub common_random_numbers: Option<bool>,
    /// Request all M⁰-variants of a permutation (its step-2 renders) at once when it starts,
    /// so they render in parallel (fast: true).
    pub early_step2: Option<bool>,
    /// Photons per source of each level's renders, from level 0, comma-separated; the last
    /// holds for finer levels (paper: iterations × photons per iteration; fast: a tenth of it).
    pub level_photons: Option<Vec<u32>>,
    /// Racing: render every candidate first with this share of the level's photons and
    /// spend the rest on the contenders; 1 turns it off (paper: 1; fast: 0.25).
    pub race_share: Option<f64>,
    /// Racing drops a candidate whose first-stage score is this many standard errors behind
    /// the leader's (fast: 3).
    pub race_z: Option<f64>,
    /// Re-score a level's distinct finalists (each permutation's result, and the level's
    /// starting map) on one fresh seed with this many photons per source and keep the best;
    /// 0 turns it off (paper: 0; fast: iterations × photons per iteration).
    pub rescore_photons: Option<u32>,
    /// Scores closer than this many standard errors of their difference tie: a tie inside a
    /// step goes to the earlier candidate, between the steps to step 2, as in the paper's
    /// exact ties (paper: 0; fast: 1).
    pub tie_z: Option<f64>,
    /// Where within-ε is saturated (see --tiebreak-saturation), this metric decides between
    /// candidates tied on it; `off` keeps the paper's tie rule alone (paper: off; fast:
    /// l2-stabilized).
    pub tiebreak: Option<TiebreakMetric>,
    /// The tiebreak must win by more than this many standard errors of the difference
    /// (fast: 1).
    pub tiebreak_z: Option<f64>,
    /// Within-ε counts as saturated for a map that misses at most this many times the share
    /// of observations a perfect map misses (1 − percentile/100): the tiebreak decides only
    /// there (fast: 3, a score of 0.997 at the 99.9th percentile).
    pub tiebreak_saturation: Option<f64>,
    /// Quad-tree levels the coarse stage runs, from level 0 (unless set all of them, that is
    /// log2 grid + 1; likelihood: auto); the refinement then starts from the last one's map (1: from the
    /// one-material map; `auto`: from level 0's where that material scatters and the sweeps
    /// screen differentially, else after every level).
    pub coarse_levels: Option<CoarseLevels>,
    /// After the quad-tree levels, refine single pixels and object positions by the likelihood
    /// (needs the deviance metric; likelihood: true).
    pub refine: Option<bool>,
    /// Photons per source of a refinement sweep's renders (likelihood: 25 × iterations ×
    /// photons per iteration for a differential sweep, 102 400 at 8 × 512; an eighth of that
    /// for a direct one).
    pub refine_photons: Option<u32>,
    /// Photons per source of a refinement's confirmation renders, on a fresh seed
    /// (likelihood: 50 × iterations × photons per iteration).
    pub refine_confirm_photons: Option<u32>,
    /// Photons per source of a differential sweep's direct renders (the changes it cannot
    /// reweight) and of the render of the current map they are paired with (default: an
    /// eighth of the sweep's photons).
    pub refine_direct_photons: Option<u32>,
    /// A refinement change must beat the current map by more than this many paired standard
    /// errors (likelihood: 3).
    pub refine_z: Option<f64>,
    /// The most refinement sweeps (likelihood: 24).
    pub refine_sweeps: Option<u32>,
    /// Whether refinement sweeps also move whole objects by one pixel (likelihood: true).
    pub refine_moves: Option<bool>,
    /// How a refinement sweep scores its changes: `direct` (a render of each) or
    /// `differential` (one differential render of the current map; either engine, in process
    /// and on the farm; likelihood: differential).
    pub refine_screen: Option<scatterfarm_search::refine::Screen>,
    /// How many times refinement may double its photons where it would otherwise end
    /// (likelihood: 2).
    pub refine_escalations: Option<u32>,
    /// Whether refinement sweeps also set each connected region (of two pixels or more)
    /// wholly to each other candidate material (likelihood: true).
    pub refine_recolour: Option<bool>,
    /// Whether refinement sweeps also swap each pair of neighbouring pixels (8-connected) of
    /// different materials, moving one object pixel at a time (likelihood: false).
    pub refine_swaps: Option<bool>,
    /// Whether refinement sweeps also set each 2 × 2 block and each pair of neighbouring
    /// pixels wholly to each candidate material, and grow or shrink each object's sides by one
    /// row or column (likelihood: false).
    pub refine_blocks: Option<bool>,
    /// Where refinement would end, a simplification round first: every non-background
    /// pixel and region set to the background unless that loses by more than this many paired
    /// standard errors (likelihood: off).
    pub refine_simplify_z: Option<f64>,
    /// Where refinement would end, a growth round first: each object of at most four pixels
    /// grown by its neighbours and set wholly to each other material, and its bounding box
    /// grown by each side in turn and filled, each rendered on its own: `true`, `false`, or
    /// `"auto"`, only where the refinement starts from a one-material map (likelihood: auto).
    pub refine_grow: Option<Growth>,
    /// A growth round whose grown maps all lose tries its best only where that map's paired z
    /// against the current map is above this (likelihood: every such round tries it).
    pub refine_grow_trial_z: Option<f64>,
    /// A refinement sweep of a map swept before renders directly only the changes whose
    /// paired z there was above this (likelihood: -1; `-inf`: every change).
    pub refine_retest_z: Option<f64>,
    /// A label for job listings (job files only, no flag).
    pub name: Option<String>,
    /// Pin the job to this engine fingerprint instead of the first worker's (job files only, no flag).
    pub engine_fingerprint: Option<String>,
    /// Let any engine render the job: faster, but not reproducible (job files only, no flag).
    pub any_engine: bool,
}

impl Default for JobSpec {
    fn default() -> Self {
        JobSpec {
            version: SPEC_VERSION,
            scene: None,
            target: None,
            calibration: None,
            calibration_material: None,
            dictionary: None,
            random_materials: None,
            bounds: None,
            permutations: DEFAULT_PERMUTATIONS,
            iterations: DEFAULT_ITERATIONS,
            photons_per_iteration: DEFAULT_PHOTONS_PER_ITERATION,
            target_photons: None,
            percentile: DEFAULT_PERCENTILE,
            metric: None,
            grid: None,
            positions: None,
            directions: None,
            seed: DEFAULT_SEED,
            search: SearchMode::default(),
            common_random_numbers: None,
            early_step2: None,
            coarse_levels: None,
            level_photons: None,
            race_share: None,
            race_z: None,
            rescore_photons: None,
            tie_z: None,
            tiebreak: None,
            tiebreak_z: None,
            tiebreak_saturation: None,
            refine: None,
            refine_photons: None,
            refine_confirm_photons: None,
            refine_direct_photons: None,
            refine_z: None,
            refine_sweeps: None,
            refine_moves: None,
            refine_screen: None,
            refine_escalations: None,
            refine_recolour: None,
            refine_swaps: None,
            refine_blocks: None,
            refine_simplify_z: None,
            refine_grow: None,
            refine_grow_trial_z: None,
            refine_retest_z: None,
            name: None,
            engine_fingerprint: None,
            any_engine: false,
        }
    }
}

impl JobSpec {
    /// That this build reads the spec's layout.
    pub fn check_version(&self) -> Result<()> {
        anyhow::ensure!(
            self.version == SPEC_VERSION,
            "`version` is {}, this build reads job specs of version {SPEC_VERSION}",
            self.version
        );
        Ok(())
    }

    /// Parses a job file's text; `path` names it in errors (TOML errors carry line and column).
    pub fn from_toml(text: &str, path: &Path) -> Result<JobSpec> {
        let params: JobSpec =
            toml::from_str(text).with_context(|| format!("job file {}", path.display()))?;
        params
            .check_version()
            .with_context(|| format!("job file {}", path.display()))?;
        anyhow::ensure!(
            params.scene.is_some() != params.target.is_some(),
            "job file {}: give exactly one of `scene` and `target`",
            path.display()
        );
        anyhow::ensure!(
            params.target.is_none() || params.calibration.is_some(),
            "job file {}: `target` needs `calibration` (a capture of a known homogeneous material)",
            path.display()
        );
        anyhow::ensure!(
            !(params.dictionary.is_some() && params.random_materials.is_some()),
            "job file {}: give `dictionary` or `random_materials`, not both",
            path.display()
        );
        Ok(params)
    }

    /// The job file text of this spec (also its wire form): `version`, `search` and the keys
    /// that differ from the defaults, so a coordinator of an older release (which refuses keys
    /// it does not know) still reads it unless the job uses something new.
    pub fn to_toml(&self) -> Result<String> {
        let full = toml::Value::try_from(self).context("cannot write the job spec as TOML")?;
        let defaults = toml::Value::try_from(JobSpec::default())
            .context("cannot write the default job spec as TOML")?;
        let mut table = match full {
            toml::Value::Table(t) => t,
            _ => anyhow::bail!("the job spec is not a TOML table"),
        };
        if let toml::Value::Table(d) = defaults {
            // `version` and `search` always: a reader of a later layout, or with another
            // default search, still reads this job as it was meant.
            table.retain(|k, v| k == "version" || k == "search" || d.get(k) != Some(v));
        }
        toml::to_string(&table).context("cannot write the job spec as TOML")
    }

    /// The input files these parameters name: a scene file (when `scene` is not a built-in
    /// name), the target and calibration NPYs and their JSON sidecars.
    pub fn input_paths(&self) -> Vec<PathBuf> {
        let mut paths = Vec::new();
        if let Some(s) = &self.scene {
            if scatterfarm_model::builtin::toml(s).is_none() {
                paths.push(PathBuf::from(s));
            }
        }
        for p in [&self.target, &self.calibration].into_iter().flatten() {
            paths.push(p.clone());
            paths.push(crate::observation::sidecar_path(p));
        }
        paths
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn job_files_take_the_flags_keys_and_defaults() {
        let p = JobSpec::from_toml(
            "scene = \"fig7a\"\npermutations = 3\nphotons_per_iteration = 64\nmetric = \"l2\"\n",
            Path::new("j.toml"),
        )
        .unwrap();
        assert_eq!(p.scene.as_deref(), Some("fig7a"));
        assert_eq!(p.permutations, 3);
        assert_eq!(p.iterations, DEFAULT_ITERATIONS);
        assert_eq!(p.metric, Some(Metric::L2));
        let text = p.to_toml().unwrap();
        assert!(
            !text.contains("iterations ="),
            "defaults are left out: {text}"
        );
        // But always the version and the search.
        assert!(text.contains("search = \"likelihood\""), "{text}");
        assert!(text.contains("version = 1"), "{text}");
        let back = JobSpec::from_toml(&text, Path::new("k.toml")).unwrap();
        assert_eq!(back, p);
    }

    #[test]
    fn the_coarse_stage_is_a_level_count_or_auto_in_job_files() {
        for (text, want) in [
            ("2", CoarseLevels::Count(2)),
            ("\"auto\"", CoarseLevels::Auto),
        ] {
            let p = JobSpec::from_toml(
                &format!("scene = \"fig7a\"\ncoarse_levels = {text}\n"),
                Path::new("j.toml"),
            )
            .unwrap();
            assert_eq!(p.coarse_levels, Some(want));
            let back = JobSpec::from_toml(&p.to_toml().unwrap(), Path::new("k.toml")).unwrap();
            assert_eq!(back, p);
        }
        let err = JobSpec::from_toml(
            "scene = \"fig7a\"\ncoarse_levels = \"most\"\n",
            Path::new("j.toml"),
        )
        .unwrap_err();
        let text = format!("{err:#}");
        assert!(
            text.contains("j.toml") && text.contains("coarse_levels") && text.contains("\"auto\""),
            "{text}"
        );
        // A value of the wrong type says what was expected too.
        for wrong in ["true", "-1", "1.5"] {
            let err = JobSpec::from_toml(
                &format!("scene = \"fig7a\"\ncoarse_levels = {wrong}\n"),
                Path::new("j.toml"),
            )
            .unwrap_err();
            let text = format!("{err:#}");
            assert!(text.contains("a level count"), "{wrong}: {text}");
        }
    }

    #[test]
    fn growth_is_a_boolean_or_auto_in_job_files() {
        // A job file written when growth was a boolean reads as before.
        for (text, want) in [
            ("true", Growth::On),
            ("false", Growth::Off),
            ("\"auto\"", Growth::Auto),
        ] {
            let p = JobSpec::from_toml(
                &format!("scene = \"fig7a\"\nrefine_grow = {text}\n"),
                Path::new("j.toml"),
            )
            .unwrap();
            assert_eq!(p.refine_grow, Some(want));
            let back = JobSpec::from_toml(&p.to_toml().unwrap(), Path::new("k.toml")).unwrap();
            assert_eq!(back, p);
        }
        let err = JobSpec::from_toml("scene = \"fig7a\"\nrefine_grow = 2\n", Path::new("j.toml"))
            .unwrap_err();
        let text = format!("{err:#}");
        assert!(
            text.contains("j.toml")
                && text.contains("refine_grow")
                && text.contains("expected true, false or \"auto\""),
            "{text}"
        );
    }

    #[test]
    fn bad_job_files_say_where() {
        let err = JobSpec::from_toml("scene = \"a\"\npermutation = 3\n", Path::new("j.toml"))
            .unwrap_err();
        let text = format!("{err:#}");
        assert!(
            text.contains("j.toml") && text.contains("permutation"),
            "{text}"
        );
        assert!(text.contains("line 2"), "{text}");
        let err = JobSpec::from_toml("permutations = 3\n", Path::new("j.toml")).unwrap_err();
        assert!(format!("{err:#}").contains("exactly one of"));
        let err = JobSpec::from_toml("scene = \"a\"\niterations = \"x\"\n", Path::new("j.toml"))
            .unwrap_err();
        assert!(format!("{err:#}").contains("iterations"));
        let err =
            JobSpec::from_toml("version = 7\nscene = \"a\"\n", Path::new("j.toml")).unwrap_err();
        let text = format!("{err:#}");
        assert!(
            text.contains("j.toml") && text.contains("`version` is 7"),
            "{text}"
        );
    }
}
