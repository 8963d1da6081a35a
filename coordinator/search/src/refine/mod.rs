//! The pixel-level refinement stage (`docs/model.md`, "Refinement"): the fine-tuning the paper
//! names as the purpose of its coarse stochastic search. A pure state machine like the search:
//! it emits render requests and consumes their scores, with its whole state serializable.
//!
//! A **sweep** renders the current map `M` and every change of it on one fresh seed (common
//! random numbers): each pixel turned to each other candidate material, and each object (a
//! connected region of a material other than the map's most common one) moved by one pixel in
//! each of the four directions; with `recolour_regions`, each connected region of two pixels or
//! more set wholly to each other candidate material. A change is a candidate when its
//! likelihood beats `M`'s by more than `z` paired standard errors
//! ([`crate::likelihood::paired`]). The candidates are taken best
//! first, skipping any that touches a pixel next to one already taken (single pixels set to
//! the same material excepted), and applied together.
//!
//! A **confirmation** then renders `M`, the combined map, the better half of the taken changes
//! and the single best change on another fresh seed: the first of them that beats `M` by `z`
//! standard errors there replaces it. With differential screening ([`Screen::Differential`])
//! a sweep scores the changes it can reweight from differential renders of `M` and renders only
//! the others. A sweep with no candidate ends the stage; so do two
//! confirmations in a row that confirm nothing, and the sweep limit. Fresh seeds between sweeps
//! keep the map from fitting one set of photons, and the final map is the last confirmed one.
//!
//! The stage's parts: `config` (what fixes a refinement and checks it), `moves` (the
//! changes a sweep tries: pixels, objects, regions, growths and simplifications), `scored`
//! (what a sweep's and a confirmation's scores decide), `reweight` (what a differential render of
//! the current map can estimate) and `trial` (growth trials).

mod config;
mod moves;
mod reweight;
mod scored;
#[cfg(test)]
mod tests;
mod trial;

use crate::likelihood::paired;
use crate::machine::ChangeScore;
use crate::seeds::{self, Stream};
pub use scatterfarm_model::Change;
use serde::{Deserialize, Serialize};
use std::collections::BTreeSet;

use config::is_zero;
pub use config::{
    Growth, ParseGrowthError, RefineConfig, Screen, GROWTH_FRACTION, GROWTH_MAX_PIXELS,
    MAX_GROWTHS, MAX_SIMPLIFICATIONS, MAX_SPREAD,
};
use reweight::Base;
use trial::Trial;

/// One render a refinement step needs: the assignment, seed and photons per source, and for a
/// differential render the changes it also estimates.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RefineRequest {
    pub assignment: Vec<u16>,
    pub seed: u64,
    pub photons: u32,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub changes: Vec<Change>,
}

/// A score as refinement reads it: the value and its per-block split (see
/// [`crate::likelihood`]).
#[derive(Debug, Clone, Copy)]
pub struct BlockScore<'a> {
    pub value: f64,
    pub blocks: &'a [f64],
    /// A differential render's estimates of its changes.
    pub changes: &'a [Option<ChangeScore>],
}

impl<'a> BlockScore<'a> {
    /// The estimated score of change `j` of this differential render, if it was reweighted.
    fn estimate(&self, j: usize) -> Option<BlockScore<'a>> {
        self.changes
            .get(j)
            .and_then(Option::as_ref)
            .map(|c| BlockScore {
                value: c.value,
                blocks: &c.blocks,
                changes: &[],
            })
    }
}

/// What the pending requests are for.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
enum Waiting {
    /// `M` first, then one render per change, in order; with differential screening `M`'s
    /// first renders are differential ones, each estimating the changes listed for it in
    /// `reweighted`, and the direct renders are of the other changes, in order.
    ///
    /// With `filled`, the differential renders are of the filled base
    /// ([`Refinement::filled_base`]): the first one's first change is `M` itself, and when
    /// some changes are rendered directly, a plain render of `M` comes before them.
    Sweep {
        changes: Vec<Change>,
        #[serde(default, skip_serializing_if = "Vec::is_empty")]
        reweighted: Vec<Vec<usize>>,
        #[serde(default, skip_serializing_if = "std::ops::Not::not")]
        filled: bool,
        /// The direct renders have their own photons ([`RefineConfig::direct_photons`]): a
        /// plain render of `M` at those photons comes before them, their reference.
        #[serde(default, skip_serializing_if = "std::ops::Not::not")]
        separate: bool,
    },
    /// `M` (first) and the options in order: the combined map, then the best change alone
    /// (when it differs).
    /// With `reweighted`, the options are estimated by one differential render of `M` (the
    /// only request) and the best of those beating `M` wins, not the first.
    /// With `filled`, that render is of the filled base and its first change is `M`.
    Confirm {
        options: Vec<Vec<u16>>,
        #[serde(default, skip_serializing_if = "std::ops::Not::not")]
        reweighted: bool,
        #[serde(default, skip_serializing_if = "std::ops::Not::not")]
        filled: bool,
    },
    /// A growth trial's end ([`Trial`]): the map the trial's sweeps reached, then the map its
    /// round started from, rendered on a fresh seed.
    Trial,
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
    /// Changes scored by a differential render rather than a render of their own.
    #[serde(default)]
    pub reweighted: u32,
    /// The current map after the sweep.
    #[serde(default)]
    pub map: Vec<u16>,
    /// A simplification round ([`RefineConfig::simplify_z`]).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub simplification: bool,
    /// A growth round ([`RefineConfig::grow_objects`]).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub growth: bool,
    /// After a growth trial ended: whether the map the trial reached replaced the map its
    /// round started from (this record's `map` is the one kept).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub trial_kept: Option<bool>,
    /// A growth round in which no grown map won: the paired z of the best of them against the
    /// current map (on the round's renders), whether or not it was tried.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub grown_z: Option<f64>,
}

/// The changes of a map that came within reach on its last sweep ([`RefineConfig::retest_z`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct Reach {
    map: Vec<u16>,
    changes: BTreeSet<Vec<(u32, u16)>>,
}

/// A plain render (no changes estimated) of each of `maps`, in order, on `seed`.
fn plain_renders(
    maps: impl IntoIterator<Item = Vec<u16>>,
    seed: u64,
    photons: u32,
) -> Vec<RefineRequest> {
    maps.into_iter()
        .map(|assignment| RefineRequest {
            assignment,
            seed,
            photons,
            changes: Vec::new(),
        })
        .collect()
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
    /// Whether a pixel can go from material `i` to `j` by reweighting (indexed by table
    /// index; empty: by no change).
    #[serde(default)]
    reweightable: Vec<Vec<bool>>,
    /// Which table materials are opaque (indexed by table index; empty: none known). Their
    /// pixels are filled for differential renders ([`Refinement::filled_base`]).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    opaque: Vec<bool>,
    /// How noisy a pixel's photon weights are going from material `i` to `j`
    /// (`model::differential::weight_spread`; empty: not known, taken as exact).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    spread: Vec<Vec<f64>>,
    /// The score of the current map on the last seed it was rendered on.
    current_score: Option<f64>,
    sweep: u32,
    stalls: u32,
    /// Doublings of the photons so far.
    #[serde(default)]
    escalation: u32,
    /// What the last sweep found within reach of `z`, on the map it swept.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    reach: Option<Reach>,
    /// Whether the pending sweep or confirmation is a simplification round.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    simplifying: bool,
    /// Simplification rounds so far.
    #[serde(default, skip_serializing_if = "is_zero")]
    simplifications: u32,
    /// The map of the last simplification round that changed nothing (none is run on it
    /// again).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    simplified: Option<Vec<u16>>,
    /// Whether the pending sweep or confirmation is a growth round.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    growing: bool,
    /// Growth rounds so far.
    #[serde(default, skip_serializing_if = "is_zero")]
    growths: u32,
    /// The map of the last growth round that changed nothing (none is run on it again).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    grown: Option<Vec<u16>>,
    /// The growth trial under way, if any.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    trial: Option<Trial>,
    waiting: Option<Waiting>,
    /// The pending requests.
    pending: Vec<RefineRequest>,
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
        reweightable: Vec<Vec<bool>>,
        opaque: Vec<bool>,
    ) -> Refinement {
        Self::with_spread(
            config,
            grid,
            materials,
            job_seed,
            start,
            reweightable,
            opaque,
            Vec::new(),
        )
    }

    /// [`Refinement::new`], knowing how noisy each material change's photon weights are
    /// (`spread[i][j]`, `model::differential::weight_spread`): a differential sweep leaves out
    /// the recolours noisier than [`MAX_SPREAD`]. A [`Growth::Auto`] setting is resolved here,
    /// from `start`.
    #[allow(clippy::too_many_arguments)]
    pub fn with_spread(
        mut config: RefineConfig,
        grid: u32,
        materials: Vec<u16>,
        job_seed: u64,
        start: Vec<u16>,
        reweightable: Vec<Vec<bool>>,
        opaque: Vec<bool>,
        spread: Vec<Vec<f64>>,
    ) -> Refinement {
        config.grow_objects = config.grow_objects.resolve(&start);
        let mut r = Refinement {
            config,
            grid,
            materials,
            job_seed,
            current: start,
            reweightable,
            opaque,
            spread,
            current_score: None,
            sweep: 0,
            stalls: 0,
            escalation: 0,
            reach: None,
            simplifying: false,
            simplifications: 0,
            simplified: None,
            growing: false,
            growths: 0,
            grown: None,
            trial: None,
            waiting: None,
            pending: Vec::new(),
            history: Vec::new(),
        };
        r.emit_sweep();
        r
    }

    /// The requests whose scores [`Refinement::submit`] expects, in order.
    pub fn pending(&self) -> &[RefineRequest] {
        &self.pending
    }

    pub fn is_finished(&self) -> bool {
        self.waiting.is_none()
    }

    /// The current map and the score of its last render.
    pub fn current(&self) -> (&[u16], Option<f64>) {
        (&self.current, self.current_score)
    }

    /// The sweeps so far (the last one's confirmation may still be pending).
    pub fn history(&self) -> &[SweepRecord] {
        &self.history
    }

    /// The number of the current sweep: its renders' seeds derive from it.
    pub fn sweep(&self) -> u32 {
        self.sweep
    }

    /// How many sweeps have ended: confirmed (or found nothing to confirm).
    pub fn sweeps_done(&self) -> usize {
        let confirming = matches!(self.waiting, Some(Waiting::Confirm { .. }));
        self.history.len() - usize::from(confirming && !self.history.is_empty())
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
            self.end();
            return;
        }
        let changes = self.changes();
        if changes.is_empty() {
            self.end();
            return;
        }
        let seed = seeds::derive(self.job_seed, Stream::RefineSweep(self.sweep));
        let photons = self.escalated(self.config.photons);
        if self.growing {
            // Every grown map rendered on its own, paired with a render of `M` on its seed.
            let photons = (photons / GROWTH_FRACTION).max(1);
            let maps: Vec<Vec<u16>> = changes.iter().map(|c| self.apply(c)).collect();
            self.pending = plain_renders(
                std::iter::once(self.current.clone()).chain(maps),
                seed,
                photons,
            );
            self.waiting = Some(Waiting::Sweep {
                changes,
                reweighted: Vec::new(),
                filled: false,
                separate: false,
            });
            return;
        }
        let request = |assignment: Vec<u16>, changes: Vec<Change>| RefineRequest {
            assignment,
            seed,
            photons,
            changes,
        };
        let base = match self.config.screen {
            Screen::Direct => None,
            Screen::Differential => self.filled_base(),
        };
        if let Some(base) = base {
            self.emit_filled_sweep(changes, base, seed, photons);
            return;
        }
        let changes: Vec<Change> = match self.config.screen {
            Screen::Direct => changes.into_iter().filter(|c| self.retested(c)).collect(),
            Screen::Differential => changes
                .into_iter()
                .filter(|c| !self.left_out(c, &self.current, c))
                .filter(|c| self.can_reweight(c) || self.retested(c))
                .collect(),
        };
        let (reweighted, direct): (Vec<usize>, Vec<usize>) = match self.config.screen {
            Screen::Direct => (Vec::new(), (0..changes.len()).collect()),
            Screen::Differential => {
                (0..changes.len()).partition(|&k| self.can_reweight(&changes[k]))
            }
        };
        let reweighted: Vec<Vec<usize>> = reweighted
            .chunks(self.config.changes_per_render.max(1) as usize)
            .map(<[usize]>::to_vec)
            .collect();
        let mut pending: Vec<RefineRequest> = reweighted
            .iter()
            .map(|ks| {
                let chosen = ks.iter().map(|&k| changes[k].clone()).collect();
                request(self.current.clone(), chosen)
            })
            .collect();
        if pending.is_empty() {
            pending.push(request(self.current.clone(), Vec::new()));
        }
        let separate = self.config.screen == Screen::Differential
            && !direct.is_empty()
            && self.direct_photons(photons) != photons;
        let maps = direct.iter().map(|&k| self.apply(&changes[k])).collect();
        pending.extend(self.direct_renders(seed, photons, separate, maps));
        self.pending = pending;
        self.waiting = Some(Waiting::Sweep {
            changes,
            reweighted,
            filled: false,
            separate,
        });
    }

    /// A differential sweep on the filled base `base`: every change of `M` becomes the change
    /// of the base to the changed map, `M` itself the first change of the first render.
    fn emit_filled_sweep(&mut self, changes: Vec<Change>, base: Base, seed: u64, photons: u32) {
        let request = |assignment: Vec<u16>, changes: Vec<Change>| RefineRequest {
            assignment,
            seed,
            photons,
            changes,
        };
        let (changes, relative): (Vec<Change>, Vec<Change>) = changes
            .into_iter()
            .map(|c| {
                let relative = base.change_to(&self.apply(&c));
                (c, relative)
            })
            .filter(|(c, relative)| !self.left_out(c, &base.map, relative))
            .filter(|(c, relative)| self.can_reweight_on(&base.map, relative) || self.retested(c))
            .unzip();
        let (reweighted, direct): (Vec<usize>, Vec<usize>) =
            (0..changes.len()).partition(|&k| self.can_reweight_on(&base.map, &relative[k]));
        let reweighted: Vec<Vec<usize>> = reweighted
            .chunks(self.config.changes_per_render.max(1) as usize)
            .map(<[usize]>::to_vec)
            .collect();
        let mut pending: Vec<RefineRequest> = reweighted
            .iter()
            .enumerate()
            .map(|(r, ks)| {
                let first = (r == 0).then(|| base.current.clone());
                let chosen = first
                    .into_iter()
                    .chain(ks.iter().map(|&k| relative[k].clone()))
                    .collect();
                request(base.map.clone(), chosen)
            })
            .collect();
        if pending.is_empty() {
            pending.push(request(base.map.clone(), vec![base.current.clone()]));
        }
        if !direct.is_empty() {
            let maps = direct.iter().map(|&k| self.apply(&changes[k])).collect();
            pending.extend(self.direct_renders(seed, photons, true, maps));
        }
        self.pending = pending;
        self.waiting = Some(Waiting::Sweep {
            changes,
            reweighted,
            filled: true,
            separate: false,
        });
    }

    /// A sweep's plain renders of `maps` at its direct photons ([`Self::direct_photons`]),
    /// after a render of `M` at those photons when `with_reference`.
    fn direct_renders(
        &self,
        seed: u64,
        photons: u32,
        with_reference: bool,
        maps: Vec<Vec<u16>>,
    ) -> Vec<RefineRequest> {
        let photons = self.direct_photons(photons);
        let reference = with_reference.then(|| self.current.clone());
        plain_renders(reference.into_iter().chain(maps), seed, photons)
    }

    /// Photons per source of a differential sweep's direct renders, for a sweep of `photons`
    /// (already escalated).
    fn direct_photons(&self, photons: u32) -> u32 {
        match self.config.direct_photons {
            Some(d) => self.escalated(d).min(photons),
            None => photons,
        }
    }

    /// `photons` doubled for every escalation so far (at most 2³¹).
    fn escalated(&self, photons: u32) -> u32 {
        let p = u64::from(photons) << self.escalation.min(31);
        p.min(1 << 31) as u32
    }

    /// Every photon count the stage may render with (for budgets).
    pub fn photon_levels(config: &RefineConfig) -> Vec<u32> {
        (0..=config.escalations.min(31))
            .flat_map(|e| {
                [config.photons, config.confirm_photons]
                    .map(|p| (u64::from(p) << e).min(1 << 31) as u32)
            })
            .collect()
    }

    /// Where the stage would end: doubles the photons and starts the next sweep, else (after
    /// the last escalation, where the photons tell most) a simplification round, else the end.
    /// (A first round before any escalation, where sweeps are cheapest, ended fig7k lower in
    /// the one run measured, `docs/model.md`.)
    fn escalate_or_end(&mut self) {
        if self.trial.is_some() {
            self.emit_trial_end();
            return;
        }
        let may_simplify = self.config.simplify_z.is_some()
            && self.simplifications < MAX_SIMPLIFICATIONS
            && self.sweep + 1 < self.config.max_sweeps
            && self.simplified.as_ref() != Some(&self.current);
        let may_grow = self.config.grow_objects.is_on()
            && self.growths < MAX_GROWTHS
            && self.sweep + 1 < self.config.max_sweeps
            && self.grown.as_ref() != Some(&self.current)
            && !self.growths_of_current().is_empty();
        if may_simplify && self.escalation >= self.config.escalations {
            self.simplifications += 1;
            self.simplifying = true;
            self.stalls = 0;
            self.sweep += 1;
            self.emit_sweep();
        } else if may_grow {
            self.growths += 1;
            self.growing = true;
            self.stalls = 0;
            self.sweep += 1;
            self.emit_sweep();
        } else if self.escalation < self.config.escalations {
            self.escalation += 1;
            self.stalls = 0;
            self.sweep += 1;
            self.emit_sweep();
        } else {
            self.end();
        }
    }

    fn end(&mut self) {
        if self.trial.is_some() {
            // A trial never ends the stage on its own map: it is compared first.
            self.emit_trial_end();
            return;
        }
        self.waiting = None;
        self.pending.clear();
        self.simplifying = false;
        self.growing = false;
    }

    /// The z a change must beat the current map by to be a candidate, and a confirmation's
    /// option to win: `z`, or in a simplification round minus its z.
    fn threshold(&self) -> f64 {
        match (self.simplifying, self.config.simplify_z) {
            (true, Some(z)) => -z,
            _ => self.config.z,
        }
    }

    /// Whether a sweep of the current map renders `change` (directly): always, unless the
    /// map was swept before and `change` did not come within [`RefineConfig::retest_z`] of
    /// beating it there.
    fn retested(&self, change: &Change) -> bool {
        if self.simplifying || self.growing {
            return true;
        }
        match &self.reach {
            Some(reach) if self.config.retest_z.is_some() && reach.map == self.current => {
                reach.changes.contains(&change.pixels)
            }
            _ => true,
        }
    }

    /// `M` with `change` applied.
    fn apply(&self, change: &Change) -> Vec<u16> {
        let mut a = self.current.clone();
        for &(p, m) in &change.pixels {
            a[p as usize] = m;
        }
        a
    }
}
