//! The parameters of a reconstruction: `scatterfarm reconstruct`'s flags and a job file's keys
//! (the same names, dashes as underscores) are one struct, so the two cannot drift apart.

use crate::similarity::Metric;
use anyhow::{Context, Result};
use clap::Args;
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

/// Which search runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SearchMode {
    /// The paper's algorithm exactly: every render request its own seed.
    #[default]
    Paper,
    /// Common random numbers per level and a render cache: the same search, with every render
    /// of a level on one seed, so repeated assignments are rendered once.
    Fast,
}

impl SearchMode {
    /// How the search seeds its renders.
    pub fn seeding(self) -> crate::search::Seeding {
        match self {
            SearchMode::Paper => crate::search::Seeding::PerRequest,
            SearchMode::Fast => crate::search::Seeding::PerLevel,
        }
    }
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
    #[arg(long, value_enum, default_value_t = Metric::WithinEpsilon)]
    pub metric: Metric,
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
    /// The search: the paper's exactly, or the faster one (common random numbers per level,
    /// render cache).
    #[arg(long, value_enum, default_value_t = SearchMode::Paper)]
    pub search: SearchMode,
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
            metric: Metric::default(),
            grid: None,
            positions: None,
            directions: None,
            seed: DEFAULT_SEED,
            search: SearchMode::Paper,
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
            table.retain(|k, v| d.get(k) != Some(v));
        }
        toml::to_string(&table).context("cannot write the job parameters as TOML")
    }

    /// The input files these parameters name: a scene file (when `scene` is not a built-in
    /// name), the target and calibration NPYs and their JSON sidecars.
    pub fn input_paths(&self) -> Vec<PathBuf> {
        let mut paths = Vec::new();
        if let Some(s) = &self.scene {
            if scatterfarm_worker::builtin::toml(s).is_none() {
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
        assert_eq!(p.metric, Metric::L2);
        let text = p.to_toml().unwrap();
        assert!(
            !text.contains("iterations ="),
            "defaults are left out: {text}"
        );
        let back = JobParams::from_toml(&text, Path::new("k.toml")).unwrap();
        assert_eq!(back, p);
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
