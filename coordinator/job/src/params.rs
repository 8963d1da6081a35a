//! The parameters of a reconstruction: `scatterfarm reconstruct`'s flags and a job file's keys
//! (the same names, dashes as underscores) are one struct, so the two cannot drift apart.

use anyhow::{Context, Result};
use clap::Args;
use scatterfarm_search::similarity::Metric;
use scatterfarm_search::{Photons, Race, Seeding, Tiebreak};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

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

/// Which search runs. The fast one is the default: on the quality bench it is at least as
/// accurate as the paper's on every scene with a small part of the photons (README).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SearchMode {
    /// The paper's algorithm exactly: every render request its own seed, every render with
    /// iterations × photons per iteration photons, the within-ε metric.
    Paper,
    /// The faster search: its options' defaults switch to common random numbers per level,
    /// early step 2, racing, per-level budgets, re-scoring, ties within one standard error
    /// and the stabilized-L2 tiebreak where within-ε is saturated.
    #[default]
    Fast,
}

/// The tiebreak's metric (`--tiebreak`): a metric of the L2 family, or none.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum TiebreakMetric {
    /// No tiebreak: the paper's tie rule alone.
    Off,
    /// `--metric l2`'s score.
    L2,
    /// `--metric l2-inverse-intensity`'s score.
    L2InverseIntensity,
    /// `--metric l2-pooled`'s score.
    L2Pooled,
    /// `--metric l2-stabilized`'s score: weights from a noise model, whatever the intensity.
    L2Stabilized,
}

impl TiebreakMetric {
    /// The metric, or none when off.
    pub fn metric(self) -> Option<Metric> {
        match self {
            TiebreakMetric::Off => None,
            TiebreakMetric::L2 => Some(Metric::L2),
            TiebreakMetric::L2InverseIntensity => Some(Metric::L2InverseIntensity),
            TiebreakMetric::L2Pooled => Some(Metric::L2Pooled),
            TiebreakMetric::L2Stabilized => Some(Metric::L2Stabilized),
        }
    }
}

/// The faster search's defaults (`--search fast`), each overridable by its own option; the
/// choices are measured in `scatterfarm bench reconstruct` (see the README).
pub mod fast {
    /// The paper's within-ε: the L2 metrics follow render noise at small budgets and move
    /// pixels the truth does not have.
    pub const METRIC: scatterfarm_search::similarity::Metric =
        scatterfarm_search::similarity::Metric::WithinEpsilon;
    /// Photons per source of each level, as a share of the nominal budget (iterations ×
    /// photons per iteration), from level 0; the last share holds for finer levels.
    pub const LEVEL_SHARES: [f64; 1] = [0.1];
    /// Racing's first stage: this share of the level's photons.
    pub const RACE_SHARE: f64 = 0.25;
    /// Racing drops a candidate this many standard errors behind the leader.
    pub const RACE_Z: f64 = 3.0;
    /// Re-scoring photons, as a share of the nominal budget.
    pub const RESCORE_SHARE: f64 = 1.0;
    /// Scores within one standard error of each other tie (then the paper's rule decides):
    /// under common random numbers exact ties are rare, and changes the noise of one seed
    /// supports are kept out.
    pub const TIE_Z: f64 = 1.0;
    /// The tiebreak where within-ε is saturated: the stabilized L2 weighs every observation
    /// by a noise model, so it sees a low-contrast object the within-ε fraction cannot.
    pub const TIEBREAK: super::TiebreakMetric = super::TiebreakMetric::L2Stabilized;
    /// The tiebreak's margin in standard errors (over six bench seeds 0.5 made wrong changes
    /// on fig7a, 2 never left phantom16's one-material map).
    pub const TIEBREAK_Z: f64 = 1.0;
    /// Within-ε is saturated for a map missing at most this many times the observations a
    /// perfect map misses (`1 − k/100` of them): 3 at k = 99.9 is a score of 0.997. Over six
    /// bench seeds 2 leaves phantom16 nearer its level 0 and 5 makes wrong changes on fig7a.
    pub const TIEBREAK_SATURATION: f64 = 3.0;
}

/// The search options resolved from a mode and its overrides.
#[derive(Debug, Clone, PartialEq)]
pub struct SearchOptions {
    pub metric: Metric,
    pub seeding: Seeding,
    pub photons: Photons,
    pub early_step2: bool,
    pub tie_z: f64,
    /// The tiebreak's metric and where it decides.
    pub tiebreak: Option<(Metric, Tiebreak)>,
}

/// What to reconstruct and how; see `scatterfarm reconstruct --help` for each key.
#[derive(Debug, Clone, PartialEq, Args, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct JobParams {
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
    /// The similarity metric.
    #[arg(long, value_enum, value_name = "METRIC")]
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
    /// The search: the faster one, or the paper's exactly. The options below switch one
    /// improvement on or off in either mode; `fast` changes their defaults (given after each
    /// as "fast: …").
    #[arg(long, value_enum, default_value_t = SearchMode::Fast)]
    pub search: SearchMode,
    /// Common random numbers: every render of a level on one seed (fast: true).
    #[arg(long, value_name = "BOOL")]
    pub common_random_numbers: Option<bool>,
    /// Request all M⁰-variants of a permutation (its step-2 renders) at once when it starts,
    /// so they render in parallel (fast: true).
    #[arg(long, value_name = "BOOL")]
    pub early_step2: Option<bool>,
    /// Photons per source of each level's renders, from level 0, comma-separated; the last
    /// holds for finer levels (paper: iterations × photons per iteration; fast: a tenth of it).
    #[arg(long, value_delimiter = ',', value_name = "N,N,...")]
    pub level_photons: Option<Vec<u32>>,
    /// Racing: render every candidate first with this share of the level's photons and
    /// spend the rest on the contenders; 1 turns it off (paper: 1; fast: 0.25).
    #[arg(long, value_name = "SHARE")]
    pub race_share: Option<f64>,
    /// Racing drops a candidate whose first-stage score is this many standard errors behind
    /// the leader's (fast: 3).
    #[arg(long, value_name = "Z")]
    pub race_z: Option<f64>,
    /// Re-score a level's distinct finalists (each permutation's result, and the level's
    /// starting map) on one fresh seed with this many photons per source and keep the best;
    /// 0 turns it off (paper: 0; fast: iterations × photons per iteration).
    #[arg(long, value_name = "N")]
    pub rescore_photons: Option<u32>,
    /// Scores closer than this many standard errors of their difference tie: a tie inside a
    /// step goes to the earlier candidate, between the steps to step 2, as in the paper's
    /// exact ties (paper: 0; fast: 1).
    #[arg(long, value_name = "Z")]
    pub tie_z: Option<f64>,
    /// Where within-ε is saturated (see --tiebreak-saturation), this metric decides between
    /// candidates tied on it; `off` keeps the paper's tie rule alone (paper: off; fast:
    /// l2-stabilized).
    #[arg(long, value_enum, value_name = "METRIC")]
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
    /// A label for job listings (job files only).
    #[arg(skip)]
    pub name: Option<String>,
    /// Pin the job to this engine fingerprint instead of the first worker's (job files only).
    #[arg(skip)]
    pub engine_fingerprint: Option<String>,
    /// Let any engine render the job: faster, but not reproducible (job files only).
    #[arg(skip)]
    pub any_engine: bool,
}

impl Default for JobParams {
    fn default() -> Self {
        JobParams {
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
            search: SearchMode::Fast,
            common_random_numbers: None,
            early_step2: None,
            level_photons: None,
            race_share: None,
            race_z: None,
            rescore_photons: None,
            tie_z: None,
            tiebreak: None,
            tiebreak_z: None,
            tiebreak_saturation: None,
            name: None,
            engine_fingerprint: None,
            any_engine: false,
        }
    }
}

impl JobParams {
    /// Parses a job file's text; `path` names it in errors (TOML errors carry line and column).
    pub fn from_toml(text: &str, path: &Path) -> Result<JobParams> {
        let params: JobParams =
            toml::from_str(text).with_context(|| format!("job file {}", path.display()))?;
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

    /// The search options: the mode's defaults with every explicit option over them. `nominal`
    /// is iterations × photons per iteration.
    pub fn search_options(&self, nominal: u32) -> Result<SearchOptions> {
        let fast = self.search == SearchMode::Fast;
        let share = |s: f64| ((f64::from(nominal) * s).round() as u32).max(1);
        let per_level = match &self.level_photons {
            Some(v) => {
                anyhow::ensure!(
                    !v.is_empty(),
                    "level_photons (--level-photons): give at least one value"
                );
                anyhow::ensure!(
                    v.iter().all(|&p| p > 0),
                    "level_photons (--level-photons): every level needs at least one photon per source"
                );
                v.clone()
            }
            None if fast => fast::LEVEL_SHARES.iter().map(|&s| share(s)).collect(),
            None => vec![nominal],
        };
        let race_share = self
            .race_share
            .unwrap_or(if fast { fast::RACE_SHARE } else { 1.0 });
        anyhow::ensure!(
            race_share > 0.0 && race_share <= 1.0,
            "race_share (--race-share) must lie in (0, 1], got {race_share}"
        );
        let race_z = self.race_z.unwrap_or(fast::RACE_Z);
        anyhow::ensure!(
            race_z.is_finite() && race_z >= 0.0,
            "race_z (--race-z) must be a number ≥ 0, got {race_z}"
        );
        let rescore = match self.rescore_photons {
            Some(0) => None,
            Some(n) => Some(n),
            None if fast => Some(share(fast::RESCORE_SHARE)),
            None => None,
        };
        let crn = self.common_random_numbers.unwrap_or(fast);
        let tie_z = self.tie_z.unwrap_or(if fast { fast::TIE_Z } else { 0.0 });
        anyhow::ensure!(
            tie_z.is_finite() && tie_z >= 0.0,
            "tie_z (--tie-z) must be a number ≥ 0, got {tie_z}"
        );
        let metric = self.metric.unwrap_or(if fast {
            fast::METRIC
        } else {
            Metric::WithinEpsilon
        });
        let tiebreak = self.tiebreak(fast, metric)?;
        Ok(SearchOptions {
            metric,
            seeding: if crn {
                Seeding::PerLevel
            } else {
                Seeding::PerRequest
            },
            photons: Photons {
                per_level,
                race: (race_share < 1.0).then_some(Race {
                    share: race_share,
                    z: race_z,
                }),
                rescore,
            },
            early_step2: self.early_step2.unwrap_or(fast),
            tie_z,
            tiebreak,
        })
    }

    /// The tiebreak: its metric, and from which within-ε score it decides. Fast's default is
    /// on with the within-ε metric only (saturation is within-ε's).
    fn tiebreak(&self, fast: bool, metric: Metric) -> Result<Option<(Metric, Tiebreak)>> {
        let within = metric == Metric::WithinEpsilon;
        let chosen = match self.tiebreak {
            Some(t) => t.metric(),
            None if fast && within => fast::TIEBREAK.metric(),
            None => None,
        };
        let Some(secondary) = chosen else {
            return Ok(None);
        };
        anyhow::ensure!(
            within,
            "tiebreak (--tiebreak) needs the within-epsilon metric: it decides where within-ε is saturated, and the metric is {}",
            clap::ValueEnum::to_possible_value(&metric)
                .map_or_else(|| format!("{metric:?}"), |v| v.get_name().to_string())
        );
        let z = self.tiebreak_z.unwrap_or(fast::TIEBREAK_Z);
        anyhow::ensure!(
            z.is_finite() && z >= 0.0,
            "tiebreak_z (--tiebreak-z) must be a number ≥ 0, got {z}"
        );
        let factor = self
            .tiebreak_saturation
            .unwrap_or(fast::TIEBREAK_SATURATION);
        anyhow::ensure!(
            factor.is_finite() && factor >= 0.0,
            "tiebreak_saturation (--tiebreak-saturation) must be a number ≥ 0, got {factor}"
        );
        let from = 1.0 - factor * (1.0 - self.percentile / 100.0);
        Ok(Some((secondary, Tiebreak { from, z })))
    }

    /// The job file text of these parameters: only the keys that differ from the defaults, so
    /// a coordinator of an older release (which refuses keys it does not know) still reads it
    /// unless the job uses something new.
    pub fn to_toml(&self) -> Result<String> {
        let full =
            toml::Value::try_from(self).context("cannot write the job parameters as TOML")?;
        let defaults = toml::Value::try_from(JobParams::default())
            .context("cannot write the default job parameters as TOML")?;
        let mut table = match full {
            toml::Value::Table(t) => t,
            _ => anyhow::bail!("job parameters are not a TOML table"),
        };
        if let toml::Value::Table(d) = defaults {
            // `search` always: releases before the fast search was the default read its
            // absence as `paper`.
            table.retain(|k, v| k == "search" || d.get(k) != Some(v));
        }
        toml::to_string(&table).context("cannot write the job parameters as TOML")
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
        let p = JobParams::from_toml(
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
        // But not the search: older releases read its absence as the paper's.
        assert!(text.contains("search = \"fast\""), "{text}");
        let back = JobParams::from_toml(&text, Path::new("k.toml")).unwrap();
        assert_eq!(back, p);
    }

    #[test]
    fn the_mode_sets_the_defaults_and_options_override_them() {
        assert_eq!(JobParams::default().search, SearchMode::Fast);
        let paper = JobParams {
            search: SearchMode::Paper,
            ..Default::default()
        }
        .search_options(4096)
        .unwrap();
        assert_eq!(
            paper,
            SearchOptions {
                metric: Metric::WithinEpsilon,
                seeding: Seeding::PerRequest,
                photons: Photons::uniform(4096),
                early_step2: false,
                tie_z: 0.0,
                tiebreak: None,
            }
        );
        let fast = JobParams {
            search: SearchMode::Fast,
            ..Default::default()
        };
        let o = fast.search_options(4096).unwrap();
        assert_eq!(o.metric, fast::METRIC);
        assert_eq!(o.seeding, Seeding::PerLevel);
        assert!(o.early_step2);
        assert!(o.photons.race.is_some());
        let (metric, t) = o.tiebreak.unwrap();
        assert_eq!(metric, Metric::L2Stabilized);
        assert_eq!(t.z, fast::TIEBREAK_Z);
        // 3 × the 0.1 % a perfect map misses at the 99.9th percentile.
        assert!((t.from - 0.997).abs() < 1e-12, "{}", t.from);
        // Each improvement alone, in the paper's search.
        let crn_only = JobParams {
            search: SearchMode::Paper,
            common_random_numbers: Some(true),
            ..Default::default()
        };
        let o = crn_only.search_options(4096).unwrap();
        assert_eq!(
            (o.seeding, o.photons.clone()),
            (Seeding::PerLevel, Photons::uniform(4096))
        );
        let off = JobParams {
            search: SearchMode::Fast,
            race_share: Some(1.0),
            rescore_photons: Some(0),
            level_photons: Some(vec![100, 50]),
            ..Default::default()
        };
        let o = off.search_options(4096).unwrap();
        assert_eq!(o.photons.race, None);
        assert_eq!(o.photons.rescore, None);
        assert_eq!(o.photons.per_level, vec![100, 50]);
        // The tiebreak follows the percentile, turns off, and is fast's only with within-ε.
        let k99 = JobParams {
            search: SearchMode::Fast,
            percentile: 99.0,
            tiebreak_saturation: Some(2.0),
            ..Default::default()
        };
        let t = k99.search_options(4096).unwrap().tiebreak.unwrap().1;
        assert!((t.from - 0.98).abs() < 1e-12, "{}", t.from);
        let off = JobParams {
            search: SearchMode::Fast,
            tiebreak: Some(TiebreakMetric::Off),
            ..Default::default()
        };
        assert_eq!(off.search_options(4096).unwrap().tiebreak, None);
        let l2 = JobParams {
            search: SearchMode::Fast,
            metric: Some(Metric::L2Stabilized),
            ..Default::default()
        };
        assert_eq!(l2.search_options(4096).unwrap().tiebreak, None);
        let paper_with = JobParams {
            search: SearchMode::Paper,
            tiebreak: Some(TiebreakMetric::L2Pooled),
            ..Default::default()
        };
        assert_eq!(
            paper_with
                .search_options(4096)
                .unwrap()
                .tiebreak
                .map(|t| t.0),
            Some(Metric::L2Pooled)
        );
        let err = JobParams {
            metric: Some(Metric::L2),
            tiebreak: Some(TiebreakMetric::L2Stabilized),
            ..Default::default()
        }
        .search_options(4096)
        .unwrap_err();
        assert!(
            format!("{err:#}").contains("--tiebreak") && format!("{err:#}").contains("l2"),
            "{err:#}"
        );
        for bad in [
            JobParams {
                tiebreak: Some(TiebreakMetric::L2Stabilized),
                tiebreak_z: Some(f64::NAN),
                ..Default::default()
            },
            JobParams {
                tiebreak: Some(TiebreakMetric::L2Stabilized),
                tiebreak_saturation: Some(-1.0),
                ..Default::default()
            },
            JobParams {
                race_share: Some(0.0),
                ..Default::default()
            },
            JobParams {
                level_photons: Some(vec![10, 0]),
                ..Default::default()
            },
            JobParams {
                race_z: Some(-1.0),
                race_share: Some(0.5),
                ..Default::default()
            },
        ] {
            assert!(bad.search_options(4096).is_err(), "{bad:?}");
        }
    }

    #[test]
    fn bad_job_files_say_where() {
        let err = JobParams::from_toml("scene = \"a\"\npermutation = 3\n", Path::new("j.toml"))
            .unwrap_err();
        let text = format!("{err:#}");
        assert!(
            text.contains("j.toml") && text.contains("permutation"),
            "{text}"
        );
        assert!(text.contains("line 2"), "{text}");
        let err = JobParams::from_toml("permutations = 3\n", Path::new("j.toml")).unwrap_err();
        assert!(format!("{err:#}").contains("exactly one of"));
        let err = JobParams::from_toml("scene = \"a\"\niterations = \"x\"\n", Path::new("j.toml"))
            .unwrap_err();
        assert!(format!("{err:#}").contains("iterations"));
    }
}
