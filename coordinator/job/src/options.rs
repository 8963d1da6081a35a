//! A job's search options: the search mode (the paper's, the fast one or the likelihood
//! search), its defaults, and the options a [`JobSpec`] resolves to, checked.

use crate::spec::JobSpec;
use anyhow::Result;
use scatterfarm_search::refine::{RefineConfig, Screen};
use scatterfarm_search::similarity::Metric;
use scatterfarm_search::{CoarseLevels, Photons, Race, Seeding, Tiebreak};
use serde::{Deserialize, Serialize};

/// Which search runs. The likelihood search is the default: on the quality bench at the
/// truth's resolution it is more accurate than the paper's and the fast search on every scene
/// measured (README, "Reconstruction quality").
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SearchMode {
    /// The paper's algorithm exactly: every render request its own seed, every render with
    /// iterations × photons per iteration photons, the within-ε metric.
    Paper,
    /// The faster search: its options' defaults switch to common random numbers per level,
    /// early step 2, racing, per-level budgets, re-scoring, ties within one standard error
    /// and the stabilized-L2 tiebreak where within-ε is saturated.
    Fast,
    /// The likelihood search: the quad-tree levels pick block materials by the likelihood
    /// (the two-sample deviance) on common random numbers, then a pixel-level refinement stage
    /// changes single pixels and moves objects while a change beats the current map by more
    /// than `refine_z` paired standard errors on fresh seeds (`docs/model.md`, "Refinement").
    #[default]
    Likelihood,
}

/// The tiebreak's metric (`--tiebreak`): a metric of the L2 family, or none.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
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

impl SearchMode {
    /// Every mode, in the order a command line lists them.
    pub const ALL: [SearchMode; 3] = [SearchMode::Paper, SearchMode::Fast, SearchMode::Likelihood];

    /// Its name in a job spec and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            SearchMode::Paper => "paper",
            SearchMode::Fast => "fast",
            SearchMode::Likelihood => "likelihood",
        }
    }
}

impl std::fmt::Display for SearchMode {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl TiebreakMetric {
    /// Every choice, in the order a command line lists them.
    pub const ALL: [TiebreakMetric; 5] = [
        TiebreakMetric::Off,
        TiebreakMetric::L2,
        TiebreakMetric::L2InverseIntensity,
        TiebreakMetric::L2Pooled,
        TiebreakMetric::L2Stabilized,
    ];

    /// Its name in a job spec and on the command line.
    pub fn name(self) -> &'static str {
        self.metric().map_or("off", Metric::name)
    }

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

/// The likelihood search's defaults (`--search likelihood`), each overridable by its own
/// option. Budgets are shares of the nominal budget (iterations × photons per iteration).
pub mod likelihood {
    use scatterfarm_search::refine::Growth;

    /// The two-sample deviance: it sees objects whose signal is spread thinly over many
    /// observations, which a threshold count cannot.
    pub const METRIC: scatterfarm_search::similarity::Metric =
        scatterfarm_search::similarity::Metric::Deviance;
    /// Photons per source of each level, as a share of the nominal budget.
    pub const LEVEL_SHARES: [f64; 1] = [0.25];
    /// Re-scoring photons, as a share of the nominal budget.
    pub const RESCORE_SHARE: f64 = 1.0;
    /// A differential sweep's photons per source, as a share of the nominal budget: 102 400 at
    /// the bench's 8 × 512, the photons at which one render of the current map resolves its
    /// single-pixel changes on the Fig. 7 scenes (`README.md`, "The likelihood search").
    pub const REFINE_SHARE: f64 = 25.0;
    /// A sweep's direct renders (every change of a direct sweep; the changes a differential
    /// one cannot reweight, and the render of the current map they pair with) take one
    /// `DIRECT_FRACTION`th of a differential sweep's photons: their signal is usually large (a
    /// pixel that starts or stops scattering), and there is one render per change.
    pub const DIRECT_FRACTION: u32 = 8;
    /// The confirmation's photons per source, as a share of the nominal budget.
    pub const CONFIRM_SHARE: f64 = 50.0;
    /// A change must beat the current map by more than this many paired standard errors.
    pub const REFINE_Z: f64 = 3.0;
    /// The most refinement sweeps: the refinement from the one-material map builds the
    /// objects in 10–20 sweeps on the Fig. 7 scenes.
    pub const REFINE_SWEEPS: u32 = 24;
    /// Doublings of the refinement's photons where it would otherwise end.
    pub const REFINE_ESCALATIONS: u32 = 2;
    /// A sweep of a map swept before renders directly only the changes whose paired z there
    /// was above this: on transmissive backgrounds, where every change to a scattering pixel
    /// is a render of its own, escalations otherwise re-render hundreds of clear losers.
    pub const REFINE_RETEST_Z: f64 = -1.0;
    /// How sweeps score their changes: one differential render of the current map estimates
    /// them all (7–11× fewer photons than a render of each on the bench's scenes).
    pub const REFINE_SCREEN: scatterfarm_search::refine::Screen =
        scatterfarm_search::refine::Screen::Differential;
    /// The coarse stage stops after level 0 where its one-material map scatters and the sweeps
    /// screen differentially (`docs/model.md`, "Where it starts"), else runs every level: on
    /// the bench's moderate backgrounds the refinement from that map ends 2–3 points higher
    /// (fig7a, fig7f over 3 seeds; fig7e 95.3 %), where the full coarse stage leaves local
    /// optima (`README.md`, "Refinement from the one-material map").
    pub const COARSE_LEVELS: scatterfarm_search::CoarseLevels =
        scatterfarm_search::CoarseLevels::Auto;
    /// Growth rounds where the refinement starts from a one-material map, as `COARSE_LEVELS`
    /// leaves it on moderate backgrounds: there they end 1–2 points higher on fig7d, fig7e
    /// and fig7f over 3 seeds, where the sweeps otherwise leave a small strong object standing
    /// in for a larger weak one (`README.md`, "Growth rounds").
    pub const REFINE_GROW: Growth = Growth::Auto;
    /// The most changes one differential render estimates, before the plan fits it to the
    /// geometry (`plan::resolve`: at most 256 MiB of estimates per render).
    pub const CHANGES_PER_RENDER: u32 = 1024;
}

/// The search options resolved from a mode and its overrides.
#[derive(Debug, Clone, PartialEq)]
pub struct SearchOptions {
    pub metric: Metric,
    pub seeding: Seeding,
    pub photons: Photons,
    pub early_step2: bool,
    /// Quad-tree levels the coarse stage runs (`None`: all).
    pub coarse_levels: Option<CoarseLevels>,
    pub tie_z: f64,
    /// The tiebreak's metric and where it decides.
    pub tiebreak: Option<(Metric, Tiebreak)>,
    /// The pixel-level refinement stage, when on.
    pub refine: Option<RefineConfig>,
}

impl JobSpec {
    /// The search options: the mode's defaults with every explicit option over them. `nominal`
    /// is iterations × photons per iteration.
    pub fn search_options(&self, nominal: u32) -> Result<SearchOptions> {
        let mode = self.search;
        // The likelihood search shares the fast one's machinery defaults (common random
        // numbers, early step 2, re-scoring); its own are below.
        let fast = matches!(mode, SearchMode::Fast | SearchMode::Likelihood);
        let like = mode == SearchMode::Likelihood;
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
            None if like => likelihood::LEVEL_SHARES.iter().map(|&s| share(s)).collect(),
            None if fast => fast::LEVEL_SHARES.iter().map(|&s| share(s)).collect(),
            None => vec![nominal],
        };
        let race_share =
            self.race_share
                .unwrap_or(if fast && !like { fast::RACE_SHARE } else { 1.0 });
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
            None if like => Some(share(likelihood::RESCORE_SHARE)),
            None if fast => Some(share(fast::RESCORE_SHARE)),
            None => None,
        };
        let crn = self.common_random_numbers.unwrap_or(fast);
        let tie_z = self
            .tie_z
            .unwrap_or(if fast && !like { fast::TIE_Z } else { 0.0 });
        anyhow::ensure!(
            tie_z.is_finite() && tie_z >= 0.0,
            "tie_z (--tie-z) must be a number ≥ 0, got {tie_z}"
        );
        let metric = self.metric.unwrap_or(if like {
            likelihood::METRIC
        } else if fast {
            fast::METRIC
        } else {
            Metric::WithinEpsilon
        });
        let tiebreak = self.tiebreak(fast, metric)?;
        let refine = match self.refine.unwrap_or(like) {
            false => None,
            true => {
                anyhow::ensure!(
                    metric == Metric::Deviance,
                    "refine (--refine) compares maps by the likelihood: it needs --metric deviance, and the metric is {}{}",
                    metric.name(),
                    if like && self.refine.is_none() {
                        " (the likelihood search, the default, refines: for another metric choose --search fast or paper, or turn the refinement off with --refine false)"
                    } else {
                        ""
                    }
                );
                let screen = self.refine_screen.unwrap_or(likelihood::REFINE_SCREEN);
                let differential_photons = share(likelihood::REFINE_SHARE);
                let direct_default = |sweep: u32| (sweep / likelihood::DIRECT_FRACTION).max(1);
                let photons = self.refine_photons.unwrap_or(match screen {
                    Screen::Differential => differential_photons,
                    Screen::Direct => direct_default(differential_photons),
                });
                let direct_photons = match screen {
                    Screen::Differential => Some(
                        self.refine_direct_photons
                            .unwrap_or(direct_default(photons)),
                    ),
                    Screen::Direct => self.refine_direct_photons,
                };
                let config = RefineConfig {
                    photons,
                    confirm_photons: self
                        .refine_confirm_photons
                        .unwrap_or_else(|| share(likelihood::CONFIRM_SHARE)),
                    z: self.refine_z.unwrap_or(likelihood::REFINE_Z),
                    max_sweeps: self.refine_sweeps.unwrap_or(likelihood::REFINE_SWEEPS),
                    move_objects: self.refine_moves.unwrap_or(true),
                    screen,
                    changes_per_render: likelihood::CHANGES_PER_RENDER,
                    escalations: self
                        .refine_escalations
                        .unwrap_or(likelihood::REFINE_ESCALATIONS),
                    recolour_regions: self.refine_recolour.unwrap_or(true),
                    // Set from the geometry when the plan resolves.
                    pixel_mm: 1.0,
                    direct_photons,
                    retest_z: Some(self.refine_retest_z.unwrap_or(likelihood::REFINE_RETEST_Z)),
                    swap_pixels: self.refine_swaps.unwrap_or(false),
                    blocks: self.refine_blocks.unwrap_or(false),
                    simplify_z: self.refine_simplify_z,
                    grow_objects: self.refine_grow.unwrap_or(likelihood::REFINE_GROW),
                    grow_trial_z: self.refine_grow_trial_z,
                };
                if let Some(problem) = config.problem() {
                    anyhow::bail!("refine_* (--refine-*): {problem}");
                }
                Some(config)
            }
        };
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
            coarse_levels: self
                .coarse_levels
                .or(like.then_some(likelihood::COARSE_LEVELS)),
            tie_z,
            tiebreak,
            refine,
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
            metric.name()
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
}

#[cfg(test)]
mod tests {
    use super::*;
    use scatterfarm_search::refine::Growth;

    #[test]
    fn names_are_the_serde_names() {
        for m in SearchMode::ALL {
            assert_eq!(serde_json::to_value(m).unwrap(), m.name());
        }
        for t in TiebreakMetric::ALL {
            assert_eq!(serde_json::to_value(t).unwrap(), t.name());
        }
    }

    #[test]
    fn the_mode_sets_the_defaults_and_options_override_them() {
        assert_eq!(JobSpec::default().search, SearchMode::Likelihood);
        let paper = JobSpec {
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
                coarse_levels: None,
                tie_z: 0.0,
                tiebreak: None,
                refine: None,
            }
        );
        let like = JobSpec {
            search: SearchMode::Likelihood,
            ..Default::default()
        };
        let o = like.search_options(4096).unwrap();
        assert_eq!(o.metric, Metric::Deviance);
        assert_eq!(o.seeding, Seeding::PerLevel);
        assert!(o.photons.race.is_none() && o.tiebreak.is_none());
        let r = o.refine.expect("the likelihood search refines");
        // At the bench's nominal 8 × 512: its `likelihood-differential-direct8` recipe.
        assert_eq!(r.screen, Screen::Differential);
        assert_eq!(
            (r.photons, r.confirm_photons, r.direct_photons, r.max_sweeps),
            (102_400, 204_800, Some(12_800), 24)
        );
        assert_eq!(o.coarse_levels, Some(CoarseLevels::Auto));
        // A direct sweep renders every change at the direct renders' photons; a sweep's
        // photons set explicitly carry its direct renders with them.
        let direct = JobSpec {
            refine_screen: Some(Screen::Direct),
            ..like.clone()
        };
        let r = direct.search_options(4096).unwrap().refine.unwrap();
        assert_eq!((r.photons, r.direct_photons), (12_800, None));
        let small = JobSpec {
            refine_photons: Some(800),
            ..like.clone()
        };
        let r = small.search_options(4096).unwrap().refine.unwrap();
        assert_eq!((r.photons, r.direct_photons), (800, Some(100)));
        let pinned = JobSpec {
            refine_photons: Some(800),
            refine_direct_photons: Some(800),
            ..like.clone()
        };
        let r = pinned.search_options(4096).unwrap().refine.unwrap();
        assert_eq!(r.direct_photons, Some(800));
        let all = JobSpec {
            coarse_levels: Some(CoarseLevels::Count(5)),
            ..like.clone()
        };
        let o = all.search_options(4096).unwrap();
        assert_eq!(o.coarse_levels, Some(CoarseLevels::Count(5)));
        let off = JobSpec {
            refine: Some(false),
            ..like.clone()
        };
        assert!(off.search_options(4096).unwrap().refine.is_none());
        let wrong = JobSpec {
            metric: Some(Metric::WithinEpsilon),
            ..like
        };
        let err = wrong.search_options(4096).unwrap_err().to_string();
        assert!(err.contains("--metric deviance"), "{err}");
        // Growth rounds are `auto` unless set: on from a one-material start.
        let grow = |refine_grow| {
            JobSpec {
                refine_grow,
                ..Default::default()
            }
            .search_options(4096)
            .unwrap()
            .refine
            .unwrap()
            .grow_objects
        };
        assert_eq!(grow(None), Growth::Auto);
        assert_eq!(grow(Some(Growth::On)), Growth::On);
        assert_eq!(grow(Some(Growth::Off)), Growth::Off);
        // The default search refines: the refusal says how to use another metric.
        assert!(err.contains("--search fast"), "{err}");
        let asked = JobSpec {
            refine: Some(true),
            metric: Some(Metric::WithinEpsilon),
            search: SearchMode::Fast,
            ..Default::default()
        };
        let err = asked.search_options(4096).unwrap_err().to_string();
        assert!(
            err.contains("--metric deviance") && !err.contains("--search fast"),
            "{err}"
        );
        let fast = JobSpec {
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
        let crn_only = JobSpec {
            search: SearchMode::Paper,
            common_random_numbers: Some(true),
            ..Default::default()
        };
        let o = crn_only.search_options(4096).unwrap();
        assert_eq!(
            (o.seeding, o.photons.clone()),
            (Seeding::PerLevel, Photons::uniform(4096))
        );
        let off = JobSpec {
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
        let k99 = JobSpec {
            search: SearchMode::Fast,
            percentile: 99.0,
            tiebreak_saturation: Some(2.0),
            ..Default::default()
        };
        let t = k99.search_options(4096).unwrap().tiebreak.unwrap().1;
        assert!((t.from - 0.98).abs() < 1e-12, "{}", t.from);
        let off = JobSpec {
            search: SearchMode::Fast,
            tiebreak: Some(TiebreakMetric::Off),
            ..Default::default()
        };
        assert_eq!(off.search_options(4096).unwrap().tiebreak, None);
        let l2 = JobSpec {
            search: SearchMode::Fast,
            metric: Some(Metric::L2Stabilized),
            ..Default::default()
        };
        assert_eq!(l2.search_options(4096).unwrap().tiebreak, None);
        let paper_with = JobSpec {
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
        let err = JobSpec {
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
            JobSpec {
                tiebreak: Some(TiebreakMetric::L2Stabilized),
                tiebreak_z: Some(f64::NAN),
                ..Default::default()
            },
            JobSpec {
                tiebreak: Some(TiebreakMetric::L2Stabilized),
                tiebreak_saturation: Some(-1.0),
                ..Default::default()
            },
            JobSpec {
                race_share: Some(0.0),
                ..Default::default()
            },
            JobSpec {
                level_photons: Some(vec![10, 0]),
                ..Default::default()
            },
            JobSpec {
                race_z: Some(-1.0),
                race_share: Some(0.5),
                ..Default::default()
            },
        ] {
            assert!(bad.search_options(4096).is_err(), "{bad:?}");
        }
    }
}
