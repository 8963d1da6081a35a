//! How many photons each render of the search gets: a budget per level, racing (a first stage
//! with a share of the level's photons, the rest spent on the contenders) and the re-scoring
//! of a level's finalists.

use serde::{Deserialize, Serialize};

/// Racing: every candidate of a step is rendered first with a share of the level's photons;
/// those clearly behind the leader are dropped, and only the contenders are rendered with the
/// level's full budget (extending their first-stage render: the first stage's photons are the
/// first photons of the full render, on the same seed).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Race {
    /// Photons per source of the first stage, as a share of the level's (0 < share ≤ 1).
    pub share: f64,
    /// A candidate is dropped when the leader's first-stage score exceeds its own by more than
    /// `z` standard errors of the difference (see [`Race::survives`]).
    pub z: f64,
}

impl Race {
    /// Whether a first-stage score `(value, std_error)` is still in the race against the
    /// leader's. The two renders' noises are treated as independent, so the difference has
    /// variance `se² + se_leader²`; under common random numbers the noises are positively
    /// correlated and the true variance of the difference is smaller, so the bound only ever
    /// keeps too many candidates, never drops too many.
    pub fn survives(&self, value: f64, std_error: f64, leader: f64, leader_error: f64) -> bool {
        let spread = (std_error.powi(2) + leader_error.powi(2)).sqrt();
        value + self.z * spread >= leader
    }
}

/// The photon plan of a search.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct Photons {
    /// Photons per source of level ℓ's renders, from level 0; the last entry holds for every
    /// finer level. Never empty in a running search.
    pub per_level: Vec<u32>,
    /// Racing, when on.
    pub race: Option<Race>,
    /// Re-scoring, when on: photons per source with which a level's distinct finalists (the
    /// final assignment of each permutation, and the level's starting map) are rendered again
    /// on one fresh seed, the level's result being the best of those renders.
    pub rescore: Option<u32>,
}

impl Photons {
    /// Every render with `photons` per source, no racing, no re-scoring: the paper's.
    pub fn uniform(photons: u32) -> Photons {
        Photons {
            per_level: vec![photons],
            race: None,
            rescore: None,
        }
    }

    /// Photons per source of level `level`'s (final-stage) renders.
    pub fn level(&self, level: u32) -> u32 {
        let i = (level as usize).min(self.per_level.len().saturating_sub(1));
        self.per_level.get(i).copied().unwrap_or(1)
    }

    /// Photons per source of level `level`'s first racing stage, when it races: `None` when
    /// racing is off or its share leaves the level's whole budget.
    pub fn first_stage(&self, level: u32) -> Option<u32> {
        let race = self.race?;
        let full = self.level(level);
        let first = ((f64::from(full) * race.share).round() as u32).clamp(1, full.max(1));
        (first < full).then_some(first)
    }

    /// Every photons-per-source value a search of `levels` levels renders with, ascending:
    /// each gets its own calibrated ε.
    pub fn budgets(&self, levels: u32) -> Vec<u32> {
        let mut all: Vec<u32> = (0..levels)
            .flat_map(|l| [Some(self.level(l)), self.first_stage(l)])
            .flatten()
            .chain(self.rescore)
            .collect();
        all.sort_unstable();
        all.dedup();
        all
    }

    /// Why this plan cannot run, if it cannot.
    pub fn problem(&self) -> Option<String> {
        if self.per_level.is_empty() {
            return Some("no photon budget is given".into());
        }
        if self.per_level.contains(&0) {
            return Some("every level needs at least one photon per source".into());
        }
        if let Some(r) = self.race {
            if !(r.share > 0.0 && r.share <= 1.0) {
                return Some(format!(
                    "the racing share must lie in (0, 1], got {}",
                    r.share
                ));
            }
            if !(r.z.is_finite() && r.z >= 0.0) {
                return Some(format!("the racing z must be ≥ 0, got {}", r.z));
            }
        }
        if self.rescore == Some(0) {
            return Some("re-scoring needs at least one photon per source".into());
        }
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn levels_take_the_last_budget_and_racing_a_share() {
        let p = Photons {
            per_level: vec![100, 200],
            race: Some(Race {
                share: 0.25,
                z: 2.0,
            }),
            rescore: Some(800),
        };
        assert_eq!((p.level(0), p.level(1), p.level(5)), (100, 200, 200));
        assert_eq!(p.first_stage(0), Some(25));
        assert_eq!(p.first_stage(3), Some(50));
        assert_eq!(p.budgets(4), vec![25, 50, 100, 200, 800]);
        let whole = Photons {
            race: Some(Race { share: 1.0, z: 2.0 }),
            ..Photons::uniform(64)
        };
        assert_eq!(whole.first_stage(0), None, "a share of 1 does not race");
        assert_eq!(whole.budgets(3), vec![64]);
        assert!(Photons::default().problem().is_some());
        assert!(Photons::uniform(0).problem().is_some());
        let bad_share = Photons {
            race: Some(Race { share: 0.0, z: 2.0 }),
            ..Photons::uniform(64)
        };
        assert!(bad_share.problem().unwrap().contains("share"));
    }

    #[test]
    fn a_candidate_survives_unless_clearly_behind() {
        let race = Race { share: 0.5, z: 2.0 };
        // Leader 10 ± 1, candidate 8 ± 1: spread √2, 8 + 2·1.41 = 10.8 ≥ 10.
        assert!(race.survives(8.0, 1.0, 10.0, 1.0));
        // 6 + 2.83 < 10: dropped.
        assert!(!race.survives(6.0, 1.0, 10.0, 1.0));
        // Exact scores: only ties with the leader survive.
        assert!(race.survives(10.0, 0.0, 10.0, 0.0));
        assert!(!race.survives(9.999, 0.0, 10.0, 0.0));
    }
}
