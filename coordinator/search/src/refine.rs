//! The pixel-level refinement stage (`docs/model.md`, "Refinement"): the fine-tuning the paper
//! names as the purpose of its coarse stochastic search. A pure state machine like the search:
//! it emits render requests and consumes their scores, with its whole state serializable.
//!
//! A **sweep** renders the current map `M` and every change of it on one fresh seed (common
//! random numbers): each pixel turned to each other candidate material, and each object (a
//! connected region of a material other than the map's most common one) moved by one pixel in
//! each of the four directions. A change is a candidate when its likelihood beats `M`'s by more
//! than `z` paired standard errors ([`crate::likelihood::paired`]). The candidates are taken best
//! first, skipping any that touches a pixel next to one already taken, and applied together.
//!
//! A **confirmation** then renders `M`, the combined map and the single best change on another
//! fresh seed: the combined map replaces `M` if it beats it by `z` standard errors there, else
//! the best change alone if it does. A sweep with no candidate ends the stage; so do two
//! confirmations in a row that confirm nothing, and the sweep limit. Fresh seeds between sweeps
//! keep the map from fitting one set of photons, and the final map is the last confirmed one.

use crate::likelihood::paired;
use crate::seeds::{self, Stream};
use serde::{Deserialize, Serialize};
use std::collections::BTreeSet;

/// What fixes a refinement.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RefineConfig {
    /// Photons per source of a sweep's renders.
    pub photons: u32,
    /// Photons per source of the confirmation renders.
    pub confirm_photons: u32,
    /// A change must beat the current map by more than this many paired standard errors.
    pub z: f64,
    /// The most sweeps.
    pub max_sweeps: u32,
    /// Whether sweeps also move whole objects by one pixel.
    pub move_objects: bool,
}

impl RefineConfig {
    /// What is wrong with the configuration, if anything.
    pub fn problem(&self) -> Option<String> {
        if self.photons == 0 || self.confirm_photons == 0 {
            return Some("refinement renders need at least one photon per source".into());
        }
        if !(self.z.is_finite() && self.z >= 0.0) {
            return Some(format!("refinement z must be a number ≥ 0, got {}", self.z));
        }
        if self.max_sweeps == 0 {
            return Some("refinement needs at least one sweep".into());
        }
        None
    }
}

/// A score as refinement reads it: the value and its per-block split (see
/// [`crate::likelihood`]).
#[derive(Debug, Clone, Copy)]
pub struct BlockScore<'a> {
    pub value: f64,
    pub blocks: &'a [f64],
}

/// One change of the current map: the pixels it sets and their new materials.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Change {
    pub pixels: Vec<(u32, u16)>,
}

/// What the pending requests are for.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
enum Waiting {
    /// `M` (first) and then one render per change, in order.
    Sweep { changes: Vec<Change> },
    /// `M` (first) and the options in order: the combined map, then the best change alone
    /// (when it differs).
    Confirm { options: Vec<Vec<u16>> },
}

/// One finished sweep, for reports.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SweepRecord {
    pub sweep: u32,
    /// Changes tried, and those that beat the current map by `z` standard errors.
    pub tried: u32,
    pub candidates: u32,
    /// Pixels of the map that changed after the confirmation (0: none confirmed).
    pub changed: u32,
    /// The confirmed map's score on the confirmation seed.
    pub score: f64,
}

/// The refinement state machine.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Refinement {
    config: RefineConfig,
    grid: u32,
    /// Candidate materials, in tie-breaking order.
    materials: Vec<u16>,
    job_seed: u64,
    current: Vec<u16>,
    /// The score of the current map on the last seed it was rendered on.
    current_score: Option<f64>,
    sweep: u32,
    stalls: u32,
    waiting: Option<Waiting>,
    /// The pending requests: assignment, seed, photons per source.
    pending: Vec<(Vec<u16>, u64, u32)>,
    history: Vec<SweepRecord>,
}

impl Refinement {
    /// A refinement of `start` (`grid²` indices) over `materials`, with its first sweep pending.
    pub fn new(
        config: RefineConfig,
        grid: u32,
        materials: Vec<u16>,
        job_seed: u64,
        start: Vec<u16>,
    ) -> Refinement {
        let mut r = Refinement {
            config,
            grid,
            materials,
            job_seed,
            current: start,
            current_score: None,
            sweep: 0,
            stalls: 0,
            waiting: None,
            pending: Vec::new(),
            history: Vec::new(),
        };
        r.emit_sweep();
        r
    }

    /// The requests whose scores [`Refinement::submit`] expects, in order.
    pub fn pending(&self) -> &[(Vec<u16>, u64, u32)] {
        &self.pending
    }

    pub fn is_finished(&self) -> bool {
        self.waiting.is_none()
    }

    /// The current map and the score of its last render.
    pub fn current(&self) -> (&[u16], Option<f64>) {
        (&self.current, self.current_score)
    }

    /// The finished sweeps.
    pub fn history(&self) -> &[SweepRecord] {
        &self.history
    }

    pub fn config(&self) -> &RefineConfig {
        &self.config
    }

    /// Requests a sweep makes on `pixels` pixels with `d` materials (for progress totals: one
    /// per pixel and other material, plus the current map, plus the confirmation).
    pub fn requests_per_sweep(pixels: u64, d: u64) -> u64 {
        pixels * d.saturating_sub(1) + 1 + 3
    }

    /// Requests still to come, on a guess of one more sweep and its confirmation.
    pub fn requests_left_estimate(&self) -> u64 {
        if self.is_finished() {
            return 0;
        }
        let pixels = self.current.len() as u64;
        let d = self.materials.len() as u64;
        self.pending.len() as u64 + Self::requests_per_sweep(pixels, d)
    }

    fn emit_sweep(&mut self) {
        if self.sweep >= self.config.max_sweeps {
            self.waiting = None;
            self.pending.clear();
            return;
        }
        let changes = self.changes();
        if changes.is_empty() {
            self.waiting = None;
            self.pending.clear();
            return;
        }
        let seed = seeds::derive(self.job_seed, Stream::RefineSweep(self.sweep));
        let photons = self.config.photons;
        let mut pending = vec![(self.current.clone(), seed, photons)];
        pending.extend(changes.iter().map(|c| (self.apply(c), seed, photons)));
        self.pending = pending;
        self.waiting = Some(Waiting::Sweep { changes });
    }

    /// `M` with `change` applied.
    fn apply(&self, change: &Change) -> Vec<u16> {
        let mut a = self.current.clone();
        for &(p, m) in &change.pixels {
            a[p as usize] = m;
        }
        a
    }

    /// Every change a sweep tries, in a fixed order, without repeats or no-ops.
    fn changes(&self) -> Vec<Change> {
        let mut out: Vec<Change> = Vec::new();
        for (p, &m) in self.current.iter().enumerate() {
            for &d in &self.materials {
                if d != m {
                    out.push(Change {
                        pixels: vec![(p as u32, d)],
                    });
                }
            }
        }
        if self.config.move_objects {
            let mut seen: BTreeSet<Vec<(u32, u16)>> =
                out.iter().map(|c| c.pixels.clone()).collect();
            for c in self.object_moves() {
                if !c.pixels.is_empty() && seen.insert(c.pixels.clone()) {
                    out.push(c);
                }
            }
        }
        out
    }

    /// The map's most common material (ties: the lowest index).
    fn background(&self) -> u16 {
        let mut counts = std::collections::BTreeMap::<u16, usize>::new();
        for &m in &self.current {
            *counts.entry(m).or_default() += 1;
        }
        counts
            .iter()
            .max_by(|a, b| a.1.cmp(b.1).then(b.0.cmp(a.0)))
            .map(|(&m, _)| m)
            .unwrap_or(0)
    }

    /// Each object (4-connected region of one non-background material, at most half the map)
    /// moved by one pixel up, down, left and right: pixels it leaves take the background, pixels
    /// it enters take its material; moves that would leave the map are skipped.
    fn object_moves(&self) -> Vec<Change> {
        let n = self.grid as i64;
        let background = self.background();
        let mut label = vec![usize::MAX; self.current.len()];
        let mut objects: Vec<(u16, Vec<usize>)> = Vec::new();
        for start in 0..self.current.len() {
            let m = self.current[start];
            if m == background || label[start] != usize::MAX {
                continue;
            }
            let id = objects.len();
            let mut stack = vec![start];
            let mut pixels = Vec::new();
            label[start] = id;
            while let Some(p) = stack.pop() {
                pixels.push(p);
                let (y, x) = (p as i64 / n, p as i64 % n);
                for (dy, dx) in [(-1, 0), (1, 0), (0, -1), (0, 1)] {
                    let (yy, xx) = (y + dy, x + dx);
                    if yy < 0 || yy >= n || xx < 0 || xx >= n {
                        continue;
                    }
                    let q = (yy * n + xx) as usize;
                    if label[q] == usize::MAX && self.current[q] == m {
                        label[q] = id;
                        stack.push(q);
                    }
                }
            }
            pixels.sort_unstable();
            objects.push((m, pixels));
        }
        let mut moves = Vec::new();
        for (m, pixels) in objects {
            if pixels.len() * 2 > self.current.len() {
                continue;
            }
            let inside: BTreeSet<usize> = pixels.iter().copied().collect();
            'dir: for (dy, dx) in [(-1i64, 0i64), (1, 0), (0, -1), (0, 1)] {
                let mut moved = BTreeSet::new();
                for &p in &pixels {
                    let (y, x) = (p as i64 / n + dy, p as i64 % n + dx);
                    if y < 0 || y >= n || x < 0 || x >= n {
                        continue 'dir;
                    }
                    moved.insert((y * n + x) as usize);
                }
                let mut change = Vec::new();
                for &p in inside.difference(&moved) {
                    change.push((p as u32, background));
                }
                for &p in moved.difference(&inside) {
                    if self.current[p] != m {
                        change.push((p as u32, m));
                    }
                }
                change.sort_unstable();
                moves.push(Change { pixels: change });
            }
        }
        moves
    }

    /// Whether two changes touch pixels within one pixel of each other.
    fn near(&self, a: &Change, b: &Change) -> bool {
        let n = self.grid as i64;
        a.pixels.iter().any(|&(p, _)| {
            b.pixels.iter().any(|&(q, _)| {
                let (py, px) = (i64::from(p) / n, i64::from(p) % n);
                let (qy, qx) = (i64::from(q) / n, i64::from(q) % n);
                (py - qy).abs() <= 1 && (px - qx).abs() <= 1
            })
        })
    }

    /// How far `a` beats `b` in paired standard errors (`+∞` for a win without noise; `None`
    /// without blocks to pair).
    fn z_of(&self, a: BlockScore, b: BlockScore) -> Option<f64> {
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
            Waiting::Sweep { changes } => self.sweep_scored(changes, scores),
            Waiting::Confirm { options } => self.confirm_scored(options, scores),
        }
        Ok(())
    }

    fn sweep_scored(&mut self, changes: Vec<Change>, scores: &[BlockScore]) {
        let reference = scores[0];
        self.current_score = Some(reference.value);
        let mut ranked: Vec<(f64, usize)> = changes
            .iter()
            .enumerate()
            .filter_map(|(k, _)| {
                let z = self.z_of(scores[k + 1], reference)?;
                (z > self.config.z).then_some((z, k))
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
            });
            self.waiting = None;
            return;
        }
        let mut combined = self.current.clone();
        for c in &taken {
            for &(p, m) in &c.pixels {
                combined[p as usize] = m;
            }
        }
        let best = self.apply(taken[0]);
        let mut options = vec![combined];
        if best != options[0] {
            options.push(best);
        }
        let seed = seeds::derive(self.job_seed, Stream::RefineConfirm(self.sweep));
        let photons = self.config.confirm_photons;
        let mut pending = vec![(self.current.clone(), seed, photons)];
        pending.extend(options.iter().map(|o| (o.clone(), seed, photons)));
        self.pending = pending;
        self.history.push(SweepRecord {
            sweep: self.sweep,
            tried: changes.len() as u32,
            candidates,
            changed: 0,
            score: reference.value,
        });
        self.waiting = Some(Waiting::Confirm { options });
    }

    fn confirm_scored(&mut self, options: Vec<Vec<u16>>, scores: &[BlockScore]) {
        let reference = scores[0];
        let winner = options.iter().enumerate().find_map(|(k, _)| {
            let z = self.z_of(scores[k + 1], reference)?;
            (z > self.config.z).then_some(k)
        });
        match winner {
            Some(k) => {
                let changed = self
                    .current
                    .iter()
                    .zip(&options[k])
                    .filter(|(a, b)| a != b)
                    .count() as u32;
                self.current = options[k].clone();
                self.current_score = Some(scores[k + 1].value);
                self.stalls = 0;
                if let Some(h) = self.history.last_mut() {
                    h.changed = changed;
                    h.score = scores[k + 1].value;
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
        self.sweep += 1;
        if self.stalls >= 2 {
            self.waiting = None;
            return;
        }
        self.emit_sweep();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config() -> RefineConfig {
        RefineConfig {
            photons: 100,
            confirm_photons: 200,
            z: 2.0,
            max_sweeps: 5,
            move_objects: true,
        }
    }

    /// Scores from a known truth: each block is minus the number of wrong pixels, plus noise
    /// that pairs cancel (the same per seed for every map).
    fn score_of(truth: &[u16], map: &[u16], seed: u64) -> (f64, Vec<f64>) {
        let wrong = truth.iter().zip(map).filter(|(a, b)| a != b).count() as f64;
        let blocks: Vec<f64> = (0..8)
            .map(|b| -wrong / 8.0 + ((seed % 97) as f64) * 0.01 + f64::from(b) * 0.001)
            .collect();
        (blocks.iter().sum(), blocks)
    }

    fn run(truth: &[u16], start: Vec<u16>, materials: Vec<u16>) -> Refinement {
        let mut r = Refinement::new(config(), 4, materials, 1, start);
        let mut steps = 0;
        while !r.is_finished() {
            let scored: Vec<(f64, Vec<f64>)> = r
                .pending()
                .iter()
                .map(|(a, s, _)| score_of(truth, a, *s))
                .collect();
            let scores: Vec<BlockScore> = scored
                .iter()
                .map(|(v, b)| BlockScore {
                    value: *v,
                    blocks: b,
                })
                .collect();
            r.submit(&scores).unwrap();
            steps += 1;
            assert!(steps < 50, "the refinement ends");
        }
        r
    }

    #[test]
    fn noiseless_scores_lead_to_the_truth() {
        let mut truth = vec![0u16; 16];
        truth[5] = 1;
        truth[10] = 2;
        let r = run(&truth, vec![0; 16], vec![0, 1, 2]);
        assert_eq!(r.current().0, &truth[..]);
        // The last sweep found nothing more.
        assert_eq!(r.history().last().map(|h| h.candidates), Some(0));
    }

    #[test]
    fn a_map_that_is_right_stays() {
        let truth = vec![1u16; 16];
        let r = run(&truth, truth.clone(), vec![0, 1]);
        assert_eq!(r.current().0, &truth[..]);
        assert_eq!(r.history().len(), 1);
    }

    #[test]
    fn object_moves_shift_a_block_by_one_pixel() {
        let mut start = vec![0u16; 16];
        for p in [5, 6, 9, 10] {
            start[p] = 1;
        }
        let r = Refinement::new(config(), 4, vec![0, 1], 1, start.clone());
        let right = r
            .object_moves()
            .into_iter()
            .find(|c| c.pixels.contains(&(7, 1)))
            .expect("a move to the right");
        assert_eq!(right.pixels, vec![(5, 0), (7, 1), (9, 0), (11, 1)]);
    }

    #[test]
    fn requests_share_a_seed_within_a_sweep_and_sweeps_differ() {
        let r = Refinement::new(config(), 4, vec![0, 1], 1, vec![0; 16]);
        let seeds: BTreeSet<u64> = r.pending().iter().map(|p| p.1).collect();
        assert_eq!(seeds.len(), 1);
        assert_eq!(r.pending().len(), 17);
        assert!(r.pending().iter().all(|p| p.2 == 100));
        assert!(config().problem().is_none());
        assert!(RefineConfig {
            z: f64::NAN,
            ..config()
        }
        .problem()
        .is_some());
    }
}
