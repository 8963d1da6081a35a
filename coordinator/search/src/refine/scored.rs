//! What the scores of a sweep, a confirmation and a trial's end decide: the candidates taken,
//! the map confirmed, the escalations and the stage's end.

use super::*;

impl Refinement {
    /// How far `a` beats `b` in paired standard errors (`+∞` for a win without noise; `None`
    /// without blocks to pair).
    pub(super) fn z_of(&self, a: BlockScore, b: BlockScore) -> Option<f64> {
        let (diff, se) = paired(a.blocks, b.blocks)?;
        Some(if se > 0.0 {
            diff / se
        } else if diff > 0.0 {
            f64::INFINITY
        } else {
            f64::NEG_INFINITY
        })
    }

    /// Hands in the scores of every pending request, in order.
    pub fn submit(&mut self, scores: &[BlockScore]) -> Result<(), String> {
        if scores.len() != self.pending.len() {
            return Err(format!(
                "refinement expected {} scores, got {}",
                self.pending.len(),
                scores.len()
            ));
        }
        let Some(waiting) = self.waiting.take() else {
            return Err("the refinement has finished".into());
        };
        self.pending.clear();
        match waiting {
            Waiting::Sweep {
                changes,
                reweighted,
                filled,
                separate,
            } => self.sweep_scored(changes, reweighted, filled || separate, filled, scores),
            Waiting::Confirm {
                options,
                reweighted,
                filled,
            } => self.confirm_scored(options, reweighted, filled, scores),
            Waiting::Trial => self.trial_scored(scores),
        }
        Ok(())
    }

    /// A sweep's scores. With `own_reference`, the direct renders are paired with the plain
    /// render of `M` just before them (on the filled base, or at their own photons).
    pub(super) fn sweep_scored(
        &mut self,
        changes: Vec<Change>,
        reweighted: Vec<Vec<usize>>,
        own_reference: bool,
        filled: bool,
        scores: &[BlockScore],
    ) {
        // On the filled base, `M` is the first render's first change.
        let n_differential = reweighted.len().max(1);
        let reference = if filled {
            scores[0].estimate(0).unwrap_or(scores[0])
        } else {
            scores[0]
        };
        let direct_reference = if own_reference {
            scores.get(n_differential).copied().unwrap_or(reference)
        } else {
            reference
        };
        self.current_score = Some(reference.value);
        // Each change's score: from its differential render, or its own direct render, and
        // the score of `M` it is paired with.
        let mut of_change: Vec<Option<(BlockScore, BlockScore)>> = vec![None; changes.len()];
        for (r, ks) in reweighted.iter().enumerate() {
            let offset = usize::from(filled && r == 0);
            for (j, &k) in ks.iter().enumerate() {
                of_change[k] = scores[r].estimate(j + offset).map(|s| (s, reference));
            }
        }
        let first_direct = n_differential + usize::from(own_reference);
        let mut listed = vec![false; changes.len()];
        for ks in &reweighted {
            for &k in ks {
                listed[k] = true;
            }
        }
        let direct = (0..changes.len()).filter(|&k| !listed[k]);
        for (i, k) in direct.enumerate() {
            of_change[k] = scores
                .get(first_direct + i)
                .copied()
                .map(|s| (s, direct_reference));
        }
        let z_of_change: Vec<Option<f64>> = of_change
            .iter()
            .map(|s| {
                let (s, against) = (*s)?;
                self.z_of(s, against)
            })
            .collect();
        let threshold = self.threshold();
        if let (Some(retest_z), false) = (self.config.retest_z, self.simplifying || self.growing) {
            // A change without a z (no blocks to pair) stays in reach.
            let changes = changes
                .iter()
                .zip(&z_of_change)
                .filter(|(_, z)| z.is_none_or(|z| z > retest_z))
                .map(|(c, _)| c.pixels.clone())
                .collect();
            self.reach = Some(Reach {
                map: self.current.clone(),
                changes,
            });
        }
        let mut ranked: Vec<(f64, usize)> = z_of_change
            .iter()
            .enumerate()
            .filter_map(|(k, z)| {
                let z = (*z)?;
                (z > threshold).then_some((z, k))
            })
            .collect();
        // Best first; ties keep the fixed order.
        ranked.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
        let candidates = ranked.len() as u32;
        let mut taken: Vec<&Change> = Vec::new();
        for &(_, k) in &ranked {
            let c = &changes[k];
            if taken.iter().all(|t| !self.near(t, c)) {
                taken.push(c);
            }
        }
        if taken.is_empty() {
            self.history.push(SweepRecord {
                sweep: self.sweep,
                tried: changes.len() as u32,
                candidates,
                changed: 0,
                score: reference.value,
                reweighted: reweighted.iter().map(|k| k.len() as u32).sum(),
                map: self.current.clone(),
                simplification: self.simplifying,
                growth: self.growing,
                trial_kept: None,
                grown_z: None,
            });
            if self.simplifying {
                self.simplifying = false;
                self.simplified = Some(self.current.clone());
            }
            if self.growing {
                // No grown map won: the best of them is tried (ties: the first).
                let best = z_of_change
                    .iter()
                    .enumerate()
                    .filter_map(|(k, z)| z.filter(|z| *z > f64::NEG_INFINITY).map(|z| (z, k)))
                    .fold(None::<(f64, usize)>, |best, (z, k)| match best {
                        Some((bz, _)) if bz >= z => best,
                        _ => Some((z, k)),
                    });
                if let Some(h) = self.history.last_mut() {
                    h.grown_z = best.map(|(z, _)| z);
                }
                let floor = self.config.grow_trial_z.unwrap_or(f64::NEG_INFINITY);
                if let Some((_, k)) = best.filter(|&(z, _)| z > floor) {
                    let map = self.apply(&changes[k]);
                    self.start_trial(map);
                    return;
                }
                self.growing = false;
                self.grown = Some(self.current.clone());
            }
            self.escalate_or_end();
            return;
        }
        let mut combined = self.current.clone();
        for c in &taken {
            for &(p, m) in &c.pixels {
                combined[p as usize] = m;
            }
        }
        let seed = seeds::derive(self.job_seed, Stream::RefineConfirm(self.sweep));
        let photons = self.escalated(self.config.confirm_photons);
        let request = |assignment: Vec<u16>, changes: Vec<Change>| RefineRequest {
            assignment,
            seed,
            photons,
            changes,
        };
        // Differential confirmation: the best 1, 2, 4, … of the taken changes together, each
        // estimated on the confirmation seed; the best of them beating `M` wins.
        let prefixes: Vec<Change> = {
            let mut sizes: Vec<usize> = std::iter::successors(Some(1usize), |k| Some(k * 2))
                .take_while(|&k| k < taken.len())
                .collect();
            sizes.push(taken.len());
            sizes
                .into_iter()
                .map(|k| {
                    let mut pixels: Vec<(u32, u16)> = taken[..k]
                        .iter()
                        .flat_map(|c| c.pixels.iter().copied())
                        .collect();
                    pixels.sort_unstable();
                    pixels.dedup_by_key(|p| p.0);
                    Change { pixels }
                })
                .collect()
        };
        // Estimated from a differential render of `M`, or of its filled base when `M` has
        // opaque pixels (then `M` is the render's first change).
        let base = match self.config.screen {
            Screen::Direct => None,
            Screen::Differential => self.filled_base(),
        };
        // A growth's recolours are too noisy to estimate: they are confirmed by renders.
        let differential = self.config.screen == Screen::Differential
            && !self.growing
            && match &base {
                Some(b) => prefixes
                    .iter()
                    .all(|c| self.can_reweight_on(&b.map, &b.change_to(&self.apply(c)))),
                None => prefixes.iter().all(|c| self.can_reweight(c)),
            };
        let filled = differential && base.is_some();
        let options: Vec<Vec<u16>> = if differential {
            prefixes.iter().map(|c| self.apply(c)).collect()
        } else {
            // The confirmation tries all of them, the better half, then the best alone: the
            // first that beats the current map wins.
            let mut options = vec![combined];
            if taken.len() >= 4 {
                let mut half = self.current.clone();
                for c in &taken[..taken.len() / 2] {
                    for &(p, m) in &c.pixels {
                        half[p as usize] = m;
                    }
                }
                options.push(half);
            }
            let best = self.apply(taken[0]);
            if !options.contains(&best) {
                options.push(best);
            }
            options
        };
        self.pending = if let (true, Some(b)) = (differential, &base) {
            let chosen = std::iter::once(b.current.clone())
                .chain(options.iter().map(|o| b.change_to(o)))
                .collect();
            vec![request(b.map.clone(), chosen)]
        } else if differential {
            vec![request(self.current.clone(), prefixes)]
        } else {
            let mut pending = vec![request(self.current.clone(), Vec::new())];
            pending.extend(options.iter().map(|o| request(o.clone(), Vec::new())));
            pending
        };
        self.history.push(SweepRecord {
            sweep: self.sweep,
            tried: changes.len() as u32,
            candidates,
            changed: 0,
            score: reference.value,
            reweighted: reweighted.iter().map(|k| k.len() as u32).sum(),
            map: self.current.clone(),
            simplification: self.simplifying,
            growth: self.growing,
            trial_kept: None,
            grown_z: None,
        });
        self.waiting = Some(Waiting::Confirm {
            options,
            reweighted: differential,
            filled,
        });
    }

    pub(super) fn confirm_scored(
        &mut self,
        options: Vec<Vec<u16>>,
        reweighted: bool,
        filled: bool,
        scores: &[BlockScore],
    ) {
        let offset = usize::from(filled);
        let reference = if filled {
            scores[0].estimate(0).unwrap_or(scores[0])
        } else {
            scores[0]
        };
        let of_option: Vec<Option<BlockScore>> = if reweighted {
            (0..options.len())
                .map(|k| scores[0].estimate(k + offset))
                .collect()
        } else {
            (0..options.len())
                .map(|k| scores.get(k + 1).copied())
                .collect()
        };
        let threshold = self.threshold();
        let beating = |k: usize| -> Option<f64> {
            let s = of_option[k]?;
            let z = self.z_of(s, reference)?;
            (z > threshold).then_some(s.value)
        };
        let winner = if reweighted && self.simplifying {
            // The largest simplification that passes (the options grow).
            (0..options.len()).rev().find(|&k| beating(k).is_some())
        } else if reweighted {
            // The best estimate among those beating `M` (ties: the smaller option).
            (0..options.len())
                .filter_map(|k| beating(k).map(|v| (v, k)))
                .fold(None::<(f64, usize)>, |best, (v, k)| match best {
                    Some((bv, _)) if bv >= v => best,
                    _ => Some((v, k)),
                })
                .map(|(_, k)| k)
        } else {
            (0..options.len()).find(|&k| beating(k).is_some())
        };
        match winner {
            Some(k) => {
                let changed = self
                    .current
                    .iter()
                    .zip(&options[k])
                    .filter(|(a, b)| a != b)
                    .count() as u32;
                let value = of_option[k].map_or(reference.value, |s| s.value);
                self.current = options[k].clone();
                self.current_score = Some(value);
                self.stalls = 0;
                if let Some(h) = self.history.last_mut() {
                    h.changed = changed;
                    h.score = value;
                    h.map = self.current.clone();
                }
            }
            None => {
                self.current_score = Some(reference.value);
                self.stalls += 1;
                if let Some(h) = self.history.last_mut() {
                    h.score = reference.value;
                }
            }
        }
        if self.simplifying || self.growing {
            // A round that changed the map: sweeps go on from it; one that did not: as where
            // the stage would have ended without it (escalate, or end).
            let unchanged = self.stalls > 0;
            if unchanged && self.growing {
                // The grown map did not hold: the best of them alone is tried.
                if let Some(best) = options.last().cloned() {
                    self.start_trial(best);
                    return;
                }
            }
            if unchanged {
                self.stalls = 0;
                if self.simplifying {
                    self.simplified = Some(self.current.clone());
                } else {
                    self.grown = Some(self.current.clone());
                }
            }
            self.simplifying = false;
            self.growing = false;
            if unchanged {
                self.escalate_or_end();
                return;
            }
        } else if self.stalls >= 2 {
            self.escalate_or_end();
            return;
        }
        self.sweep += 1;
        self.emit_sweep();
    }
}
