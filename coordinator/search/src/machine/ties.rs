//! How the search decides between scored candidates: the paper's rule (the highest score wins;
//! a tie inside a step goes to the earlier candidate, between a permutation's steps to step 2),
//! with two widenings of "tie" for the faster search:
//! - `tie_z`: scores closer than `tie_z` standard errors of their difference tie;
//! - a [`Tiebreak`]: among candidates tied on the primary (within-ε) score, a secondary score
//!   decides, but only where the primary score is saturated.
//!
//! Why the tiebreak: the within-ε fraction counts observations beyond the calibrated noise
//! threshold, so a map that already fits every observation to within the noise (it scores about
//! what the truth would, `k/100`) cannot be improved on by it: in a low-contrast medium the
//! one-material map and the truth score alike, and the search stays at level 0. A χ²-type
//! score (the stabilized L2) still sees the difference there. Where within-ε is not saturated
//! it keeps the decision alone: there the L2 family follows the coarse grid's misfit and moves
//! pixels the truth does not have (measured: `bench reconstruct`, README).

use super::Score;
use serde::{Deserialize, Serialize};

/// The secondary score and where it may decide.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Tiebreak {
    /// The secondary score decides only against a candidate whose primary score is at least
    /// this: a map missing at most a few times the observations a perfect map misses
    /// (`1 − F·(1 − k/100)`, see `params`).
    pub from: f64,
    /// The secondary score must beat by more than this many standard errors of the
    /// difference (the two renders' errors combined as if independent).
    pub z: f64,
}

/// A second opinion on a render, from another metric (`Score::secondary`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Secondary {
    pub value: f64,
    pub std_error: f64,
}

/// A candidate: its index among the step's (or re-scoring's) requests and its score.
pub type Scored = (usize, Score);

/// The decision rule of a search (`SearchConfig::tie_z`, `SearchConfig::tiebreak`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Rule {
    pub tie_z: f64,
    pub tiebreak: Option<Tiebreak>,
}

impl Rule {
    /// Whether `a` beats `b` on the primary score by more than `tie_z` standard errors: of
    /// their paired difference when both carry likelihood blocks (renders on common photons),
    /// else of the two renders' errors combined as if independent.
    pub fn beats(&self, a: &Score, b: &Score) -> bool {
        let se = match crate::likelihood::paired(&a.blocks, &b.blocks) {
            Some((_, se)) => se,
            None => combined(a.std_error, b.std_error),
        };
        a.value > b.value + self.tie_z * se
    }

    /// Whether the tiebreak prefers `a` to `b`: `b`'s primary score is saturated and `a`'s
    /// secondary score beats `b`'s by more than the tiebreak's margin.
    fn breaks(&self, a: &Score, b: &Score) -> bool {
        match (self.tiebreak, a.secondary, b.secondary) {
            (Some(t), Some(x), Some(y)) => {
                b.value >= t.from && x.value > y.value + t.z * combined(x.std_error, y.std_error)
            }
            _ => false,
        }
    }

    /// The winner of candidates in request order: the earliest of those the highest does not
    /// beat, unless the tiebreak prefers the best of them (by secondary score) to it.
    pub fn best(&self, scored: &[Scored]) -> Option<Scored> {
        let top = scored
            .iter()
            .reduce(|b, v| if b.1.value >= v.1.value { b } else { v })?;
        let tied: Vec<&Scored> = scored
            .iter()
            .filter(|(_, v)| !self.beats(&top.1, v))
            .collect();
        let first = (*tied.first()?).clone();
        if self.tiebreak.is_none() {
            return Some(first);
        }
        let second = tied
            .iter()
            .copied()
            .reduce(|b, v| match (b.1.secondary, v.1.secondary) {
                (Some(x), Some(y)) if y.value > x.value => v,
                _ => b,
            })?;
        Some(if self.breaks(&second.1, &first.1) {
            second.clone()
        } else {
            first
        })
    }

    /// Between a permutation's steps: step 1's winner only if it beats step 2's, on the
    /// primary score or (tied on it) by the tiebreak; otherwise step 2's.
    pub fn between(&self, one: Option<Scored>, two: Option<Scored>) -> Option<Scored> {
        match (one, two) {
            (Some(a), Some(b)) if self.beats(&a.1, &b.1) => Some(a),
            (Some(a), Some(b)) if !self.beats(&b.1, &a.1) && self.breaks(&a.1, &b.1) => Some(a),
            (_, Some(b)) => Some(b),
            (a, None) => a,
        }
    }

    /// The re-scored finalists' winner; the last finalist is the level's starting map `M⁰`.
    /// With a tiebreak, decided as a step is, `M⁰` first: the level keeps its parent's map
    /// unless the fresh render confirms a change (on within-ε, or saturated and by the
    /// tiebreak); then the earlier permutation's. Without one, the highest re-score (ties:
    /// the earlier).
    pub fn rescored(&self, scores: &[Score]) -> Option<usize> {
        if self.tiebreak.is_some() {
            let mut scored: Vec<Scored> = scores.iter().cloned().enumerate().collect();
            if !scored.is_empty() {
                scored.rotate_right(1);
            }
            return self.best(&scored).map(|(i, _)| i);
        }
        super::best_of(scores, 0..scores.len())
    }
}

/// The standard error of a difference of two independent estimates.
fn combined(a: f64, b: f64) -> f64 {
    (a * a + b * b).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn s(value: f64, std_error: f64, secondary: Option<(f64, f64)>) -> Score {
        Score {
            value,
            std_error,
            secondary: secondary.map(|(value, std_error)| Secondary { value, std_error }),
            blocks: Vec::new(),
            changes: Vec::new(),
        }
    }

    const RULE: Rule = Rule {
        tie_z: 1.0,
        tiebreak: Some(Tiebreak { from: 0.99, z: 1.0 }),
    };

    #[test]
    fn the_tiebreak_decides_only_among_saturated_ties() {
        // Tied on within-ε (0.001 apart, errors 0.001): the secondary decides, by > 1 SE.
        let tied = [
            (0, s(0.995, 0.001, Some((-100.0, 2.0)))),
            (1, s(0.996, 0.001, Some((-90.0, 2.0)))),
        ];
        assert_eq!(RULE.best(&tied).map(|b| b.0), Some(1));
        // Without a tiebreak, the paper's rule: the earlier tied candidate.
        let plain = Rule {
            tie_z: 1.0,
            tiebreak: None,
        };
        assert_eq!(plain.best(&tied).map(|b| b.0), Some(0));
        // A secondary difference inside its margin leaves the earlier.
        let close = [
            (0, s(0.995, 0.001, Some((-100.0, 2.0)))),
            (1, s(0.996, 0.001, Some((-98.0, 2.0)))),
        ];
        assert_eq!(RULE.best(&close).map(|b| b.0), Some(0));
        // Not saturated (below `from`): within-ε's tie rule alone.
        let unsaturated = [
            (0, s(0.95, 0.001, Some((-100.0, 2.0)))),
            (1, s(0.951, 0.001, Some((-50.0, 2.0)))),
        ];
        assert_eq!(RULE.best(&unsaturated).map(|b| b.0), Some(0));
        // A clear primary winner is never overruled.
        let clear = [
            (0, s(0.999, 0.0001, Some((-100.0, 2.0)))),
            (1, s(0.995, 0.0001, Some((-10.0, 2.0)))),
        ];
        assert_eq!(RULE.best(&clear).map(|b| b.0), Some(0));
    }

    #[test]
    fn between_steps_step_two_keeps_ties_unless_the_tiebreak_prefers_step_one() {
        let one = (0, s(0.995, 0.001, Some((-90.0, 2.0))));
        let two = (3, s(0.996, 0.001, Some((-100.0, 2.0))));
        assert_eq!(
            RULE.between(Some(one.clone()), Some(two.clone()))
                .map(|b| b.0),
            Some(0)
        );
        let plain = Rule {
            tie_z: 1.0,
            tiebreak: None,
        };
        assert_eq!(
            plain
                .between(Some(one.clone()), Some(two.clone()))
                .map(|b| b.0),
            Some(3)
        );
        // Step 2 clearly ahead on within-ε: step 2, whatever the secondary says.
        let ahead = (3, s(0.9999, 0.0001, Some((-100.0, 2.0))));
        let behind = (0, s(0.995, 0.0001, Some((-10.0, 2.0))));
        assert_eq!(
            RULE.between(Some(behind.clone()), Some(ahead.clone()))
                .map(|b| b.0),
            Some(3)
        );
        assert_eq!(RULE.between(Some(one.clone()), None).map(|b| b.0), Some(0));
        assert_eq!(RULE.between(None, None), None);
    }

    #[test]
    fn rescoring_keeps_the_highest_without_a_tiebreak_and_the_start_unless_a_change_is_confirmed() {
        // Two permutations' results, then the level's starting map M⁰ (last).
        let scores = [
            s(0.995, 0.001, Some((-80.0, 2.0))),
            s(0.996, 0.001, Some((-95.0, 2.0))),
            s(0.9955, 0.001, Some((-100.0, 2.0))),
        ];
        let plain = Rule {
            tie_z: 1.0,
            tiebreak: None,
        };
        assert_eq!(plain.rescored(&scores), Some(1));
        // All tied on within-ε; the tiebreak confirms the first permutation's change over M⁰.
        assert_eq!(RULE.rescored(&scores), Some(0));
        // Not confirmed (inside the tiebreak's margin): M⁰ stays.
        let unconfirmed = [
            s(0.995, 0.001, Some((-99.0, 2.0))),
            s(0.996, 0.001, Some((-98.0, 2.0))),
            s(0.9955, 0.001, Some((-100.0, 2.0))),
        ];
        assert_eq!(RULE.rescored(&unconfirmed), Some(2));
        // Confirmed on within-ε alone.
        let clear = [
            s(0.999, 0.0001, Some((-200.0, 2.0))),
            s(0.99, 0.0001, Some((-95.0, 2.0))),
            s(0.995, 0.0001, Some((-100.0, 2.0))),
        ];
        assert_eq!(RULE.rescored(&clear), Some(0));
        assert_eq!(RULE.rescored(&[]), None);
    }
}
