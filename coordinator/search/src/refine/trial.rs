//! Growth trials: a growth round's best grown map that did not win, swept on its own, and kept
//! only if the map its sweeps reach beats the map the round started from on a fresh seed.

use super::*;

/// A growth round's best grown map, tried although it did not win: the sweeps go on from it,
/// and where they would end, the map they reach is compared with `from` on a fresh seed
/// ([`Stream::RefineTrial`]); the better of the two stays.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(super) struct Trial {
    /// The map the growth round started from.
    pub(super) from: Vec<u16>,
}

impl Refinement {
    /// Tries `map`, a growth round's best grown map that did not win ([`Trial`]): the next
    /// sweep is of it.
    pub(super) fn start_trial(&mut self, map: Vec<u16>) {
        self.growing = false;
        self.trial = Some(Trial {
            from: std::mem::replace(&mut self.current, map),
        });
        self.current_score = None;
        self.stalls = 0;
        self.sweep += 1;
        self.emit_sweep();
    }

    /// Renders the map a trial reached and the map its round started from on a fresh seed.
    pub(super) fn emit_trial_end(&mut self) {
        let Some(trial) = &self.trial else {
            return;
        };
        let seed = seeds::derive(self.job_seed, Stream::RefineTrial(self.sweep));
        let photons = self.escalated(self.config.confirm_photons);
        self.pending = plain_renders([self.current.clone(), trial.from.clone()], seed, photons);
        self.waiting = Some(Waiting::Trial);
    }

    /// A trial's end: the map it reached stays if it beats the map its round started from by
    /// `z` paired standard errors; else that map comes back, and no growth round runs on it
    /// again. The stage then goes on as where it would have ended.
    pub(super) fn trial_scored(&mut self, scores: &[BlockScore]) {
        let Some(trial) = self.trial.take() else {
            return;
        };
        let (reached, from) = (scores[0], scores[1]);
        let kept = self.z_of(reached, from).is_some_and(|z| z > self.config.z);
        let changed = self
            .current
            .iter()
            .zip(&trial.from)
            .filter(|(a, b)| a != b)
            .count() as u32;
        if kept {
            self.current_score = Some(reached.value);
        } else {
            self.current = trial.from;
            self.current_score = Some(from.value);
            self.grown = Some(self.current.clone());
        }
        self.stalls = 0;
        self.history.push(SweepRecord {
            sweep: self.sweep,
            tried: 1,
            candidates: u32::from(kept),
            changed: if kept { changed } else { 0 },
            score: self.current_score.unwrap_or(from.value),
            reweighted: 0,
            map: self.current.clone(),
            simplification: false,
            growth: true,
            trial_kept: Some(kept),
            grown_z: None,
        });
        self.escalate_or_end();
    }
}
