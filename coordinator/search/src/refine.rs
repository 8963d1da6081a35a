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

use crate::likelihood::paired;
use crate::machine::ChangeScore;
use crate::seeds::{self, Stream};
pub use scatterfarm_model::Change;
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
    /// How a sweep scores its changes: a direct render of each, or one differential render of
    /// the current map that estimates them all from its photons (changes it cannot reweight
    /// are rendered directly).
    #[serde(default)]
    pub screen: Screen,
    /// The most changes one differential render estimates (its memory is this many count
    /// matrices).
    #[serde(default = "default_changes_per_render")]
    pub changes_per_render: u32,
    /// How many times the stage may double its sweep and confirmation photons where it would
    /// otherwise end (a sweep with no candidate, or two stalls): more photons where the signal
    /// of the changes left is small.
    #[serde(default)]
    pub escalations: u32,
    /// Whether sweeps also try each connected region of two pixels or more (objects and the
    /// background alike) set wholly to each other candidate material: a region found in the
    /// right place with the wrong material is then one change, not one per pixel.
    #[serde(default)]
    pub recolour_regions: bool,
    /// The pixel's side in mm, for how noisy reweighting is ([`Refinement::with_spread`]).
    #[serde(default = "default_pixel_mm")]
    pub pixel_mm: f64,
    /// Photons per source of a differential sweep's direct renders (the changes it cannot
    /// reweight, such as a scattering pixel in a non-scattering background) and of the plain
    /// render of `M` they are paired with; `None`: the sweep's photons. Their signal is
    /// usually large (a pixel that starts or stops scattering), so fewer photons find them,
    /// and a sweep over a transmissive background no longer costs a full render per pixel.
    /// Escalations double it with the others.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub direct_photons: Option<u32>,
    /// A sweep of a map swept before (after a stall, or escalated) renders directly only the
    /// changes whose paired z on that map's last sweep was above this; `None`: every change.
    /// A change that does not come close at `N` photons is expected to lose by √2 more
    /// standard errors at `2N` (the difference stays, its error shrinks), so re-rendering it
    /// is where an escalation's photons went. Changes a differential render estimates cost
    /// no photons of their own and are always tried.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub retest_z: Option<f64>,
    /// Whether sweeps also swap each pair of neighbouring pixels (8-connected) of different
    /// materials: one object pixel moved to a neighbouring place, which keeps the object's size
    /// and so changes the counts far less than either pixel alone.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub swap_pixels: bool,
    /// Whether sweeps also set each 2 × 2 block, and each pair of neighbouring pixels side by
    /// side or one above the other, wholly to each candidate material (where two pixels or
    /// more change): an object's edge grown, shrunk or shifted two pixels at a time. Such a
    /// change moves the counts about twice as far as one pixel against about √2 times the
    /// noise, so it clears `z` where each of its pixels alone does not, and it leaves the
    /// local optima where one pixel alone cannot improve (an object found one pixel too thin
    /// and one pixel off). With them, each object's bounding box grown or shrunk by one row
    /// or column on each side.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub blocks: bool,
    /// Where the stage would end, a **simplification** round first: a sweep of every
    /// non-background pixel and region set to the background, in which a change is a
    /// candidate, and a confirmation's option wins, unless it loses to the current map by
    /// more than this many paired standard errors. What the target cannot tell from the
    /// background becomes the background (an opaque pixel deep inside a tunnel that no photon
    /// reaches); what it can stays. Rounds come after the last escalation, at its photons.
    /// After a round that changes the map, sweeps go on; after one that
    /// changes nothing, the stage goes on as without it; [`MAX_SIMPLIFICATIONS`] rounds at
    /// most.
    /// `None`: no simplification.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub simplify_z: Option<f64>,
    /// Where the stage would end (before it escalates), a **growth** round first: each small
    /// object (a connected region of at most [`GROWTH_MAX_PIXELS`] pixels, not of the
    /// background) grown by its 8-connected neighbours and set wholly to each candidate
    /// material other than the background, and (an object of two pixels or more) its bounding
    /// box grown by one row or column on each side in turn and filled with its material (an
    /// object found with a corner or a side missing), each grown map rendered on its own at a
    /// [`GROWTH_FRACTION`]th of the sweep's photons. A small object of a strong material can
    /// stand in for a larger one of a weaker material (one opaque pixel for a 3 × 2 block of
    /// `uniform` on fig7f): no single pixel then improves the map, and the recolour of the
    /// grown object is too noisy for a differential render to estimate. A round that changes
    /// the map lets the sweeps go on from it (they trim what it grew too far). In a round that
    /// changes nothing, its best grown map is **tried** ([`Trial`]): the sweeps go on from it
    /// as from a confirmed map, and where they would end, the map they reached is rendered
    /// beside the round's start on a fresh seed at the confirmation photons; it stays if it
    /// beats the start by `z` paired standard errors, else the start comes back and the stage
    /// goes on as without the round. A grown map that fits worse than the stand-in (it grew
    /// into pixels the object lacks) can so still lead to the object. [`MAX_GROWTHS`] rounds
    /// at most, and none twice on one map.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub grow_objects: bool,
    /// A growth round's best grown map is tried ([`Trial`]) only where its paired z against
    /// the current map is above this; below it, the round ends as one without a trial. `None`:
    /// every round whose grown maps all lose runs a trial.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub grow_trial_z: Option<f64>,
}

/// The most simplification rounds one refinement runs ([`RefineConfig::simplify_z`]).
pub const MAX_SIMPLIFICATIONS: u32 = 3;

/// The most growth rounds one refinement runs ([`RefineConfig::grow_objects`]).
pub const MAX_GROWTHS: u32 = 4;

/// A growth round grows the objects of at most this many pixels.
pub const GROWTH_MAX_PIXELS: usize = 4;

/// A growth round's renders take this fraction of the sweep's photons (escalated): each is a
/// render of its own, and the changes it looks for move the counts as a whole object does.
pub const GROWTH_FRACTION: u32 = 4;

fn is_zero(n: &u32) -> bool {
    *n == 0
}

fn default_pixel_mm() -> f64 {
    1.0
}

/// A differential sweep leaves out a recolour whose photon weights are noisier than this
/// ([`Refinement::spread_of`]): its estimate would rest on a few photons and could never beat
/// `z`, and a direct render of each would cost a full render apiece.
pub const MAX_SPREAD: f64 = 10.0;

fn default_changes_per_render() -> u32 {
    1024
}

/// How a refinement sweep scores its changes.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Screen {
    /// A render of every changed map.
    #[default]
    Direct,
    /// One differential render of the current map (`docs/model.md`, "Differential renders").
    Differential,
}

impl Screen {
    pub const ALL: [Screen; 2] = [Screen::Direct, Screen::Differential];

    pub fn name(self) -> &'static str {
        match self {
            Screen::Direct => "direct",
            Screen::Differential => "differential",
        }
    }
}

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

impl RefineConfig {
    /// What is wrong with the configuration, if anything.
    pub fn problem(&self) -> Option<String> {
        if self.photons == 0 || self.confirm_photons == 0 || self.direct_photons == Some(0) {
            return Some("refinement renders need at least one photon per source".into());
        }
        if !(self.z.is_finite() && self.z >= 0.0) {
            return Some(format!("refinement z must be a number ≥ 0, got {}", self.z));
        }
        if self.max_sweeps == 0 {
            return Some("refinement needs at least one sweep".into());
        }
        if self.changes_per_render == 0 {
            return Some("a differential render needs room for at least one change".into());
        }
        if self
            .simplify_z
            .is_some_and(|z| !(z.is_finite() && z >= 0.0))
        {
            return Some(format!(
                "the refinement's simplification z must be a number ≥ 0, got {}",
                self.simplify_z.unwrap_or_default()
            ));
        }
        if self.grow_trial_z.is_some_and(f64::is_nan) {
            return Some(
                "the refinement's growth trial z must be a number (or -inf: every trial)".into(),
            );
        }
        if self.retest_z.is_some_and(f64::is_nan) {
            return Some(
                "the refinement's retest z must be a number (or -inf: every change)".into(),
            );
        }
        if !(self.pixel_mm.is_finite() && self.pixel_mm > 0.0) {
            return Some(format!(
                "the pixel size must be > 0 mm, got {}",
                self.pixel_mm
            ));
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

/// A growth round's best grown map, tried although it did not win: the sweeps go on from it,
/// and where they would end, the map they reach is compared with `from` on a fresh seed
/// ([`Stream::RefineTrial`]); the better of the two stays.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct Trial {
    /// The map the growth round started from.
    from: Vec<u16>,
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

/// The rows and columns `pixels` (indices of an `n × n` grid) span: first row, last row,
/// first column, last column; `None` for no pixels.
fn bounding_box(pixels: &[usize], n: usize) -> Option<(usize, usize, usize, usize)> {
    let rows = pixels.iter().map(|p| p / n);
    let columns = pixels.iter().map(|p| p % n);
    Some((
        rows.clone().min()?,
        rows.max()?,
        columns.clone().min()?,
        columns.max()?,
    ))
}

/// The bounding box of `pixels` (indices of an `n × n` grid) grown by one row or column on
/// each side in turn, where the grid has room: up, down, left, right, each as its pixels in
/// order.
fn grown_boxes(pixels: &[usize], n: usize) -> Vec<Vec<usize>> {
    let Some((y0, y1, x0, x1)) = bounding_box(pixels, n) else {
        return Vec::new();
    };
    let boxes = [
        (y0 > 0).then(|| (y0 - 1, y1, x0, x1)),
        (y1 + 1 < n).then(|| (y0, y1 + 1, x0, x1)),
        (x0 > 0).then(|| (y0, y1, x0 - 1, x1)),
        (x1 + 1 < n).then(|| (y0, y1, x0, x1 + 1)),
    ];
    boxes
        .into_iter()
        .flatten()
        .map(|(ya, yb, xa, xb)| {
            (ya..=yb)
                .flat_map(|y| (xa..=xb).map(move |x| y * n + x))
                .collect()
        })
        .collect()
}

/// The filled base of a map ([`Refinement::filled_base`]): the map rendered, and the change
/// of it that gives back the map it was filled from.
#[derive(Debug, Clone)]
struct Base {
    map: Vec<u16>,
    current: Change,
}

impl Base {
    /// The change of the base that gives `target`: its pixels that differ, in order.
    fn change_to(&self, target: &[u16]) -> Change {
        Change {
            pixels: self
                .map
                .iter()
                .zip(target)
                .enumerate()
                .filter(|(_, (b, t))| b != t)
                .map(|(p, (_, &t))| (p as u32, t))
                .collect(),
        }
    }
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
    /// the recolours noisier than [`MAX_SPREAD`].
    #[allow(clippy::too_many_arguments)]
    pub fn with_spread(
        config: RefineConfig,
        grid: u32,
        materials: Vec<u16>,
        job_seed: u64,
        start: Vec<u16>,
        reweightable: Vec<Vec<bool>>,
        opaque: Vec<bool>,
        spread: Vec<Vec<f64>>,
    ) -> Refinement {
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

    /// The filled base of the current map `M`: `M` with every opaque pixel (and every pixel
    /// nothing reweights out of) set to the background (`docs/model.md`, "The filled base").
    /// Nothing reweights out of an opaque pixel, so a differential render of `M` cannot
    /// estimate clearing one; a render of the base can estimate `M` (its opaque pixels back:
    /// weight 0 for every photon that entered them, exact) and every change of `M`, clearing
    /// included, on the same photons. `None` when `M` has no pixel to fill, or its background
    /// is opaque.
    fn filled_base(&self) -> Option<Base> {
        let opaque = |m: u16| self.opaque.get(usize::from(m)).copied().unwrap_or(false);
        let reweights = |from: u16, to: u16| {
            self.reweightable
                .get(usize::from(from))
                .and_then(|row| row.get(usize::from(to)))
                .copied()
                .unwrap_or(false)
        };
        let background = self.background();
        if opaque(background) {
            return None;
        }
        // Opaque pixels, and any other whose material nothing reweights out of to the
        // background while the background reweights into it (a non-scattering pixel in a
        // scattering background: its crossings are reweighted, unbiased, noisier).
        let filled = |m: u16| {
            m != background
                && (opaque(m) || (!reweights(m, background) && reweights(background, m)))
        };
        let mut map = self.current.clone();
        let mut pixels = Vec::new();
        for (p, m) in map.iter_mut().enumerate() {
            if filled(*m) {
                pixels.push((p as u32, *m));
                *m = background;
            }
        }
        (!pixels.is_empty()).then_some(Base {
            map,
            current: Change { pixels },
        })
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
        let may_grow = self.config.grow_objects
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

    /// Tries `map`, a growth round's best grown map that did not win ([`Trial`]): the next
    /// sweep is of it.
    fn start_trial(&mut self, map: Vec<u16>) {
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
    fn emit_trial_end(&mut self) {
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
    fn trial_scored(&mut self, scores: &[BlockScore]) {
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

    /// Whether every pixel of `change` can be reweighted from the current map.
    fn can_reweight(&self, change: &Change) -> bool {
        self.can_reweight_on(&self.current, change)
    }

    /// Whether every pixel of `change` can be reweighted from `map`.
    fn can_reweight_on(&self, map: &[u16], change: &Change) -> bool {
        change.pixels.iter().all(|&(p, d)| {
            let from = map[p as usize];
            self.reweightable
                .get(usize::from(from))
                .and_then(|row| row.get(usize::from(d)))
                .copied()
                .unwrap_or(false)
        })
    }

    /// Whether a differential sweep rendering `map` leaves `change` (of the current map `M`,
    /// written as `relative`, the same change of `map`) out: a recolour (several pixels set to
    /// one material) whose photon weights are too noisy to estimate
    /// ([`Refinement::spread_of`] above [`MAX_SPREAD`]), or that `map` cannot reweight. A
    /// direct render of each would cost a full render apiece; direct screening tries them all.
    fn left_out(&self, change: &Change, map: &[u16], relative: &Change) -> bool {
        let recolour =
            change.pixels.len() >= 2 && change.pixels.iter().all(|&(_, d)| d == change.pixels[0].1);
        recolour
            && (!self.can_reweight_on(map, relative) || self.spread_of(map, relative) > MAX_SPREAD)
    }

    /// How noisy the photon weights of `change` of `map` are: 1 for a change of at most one
    /// inexact pixel (single pixels are always reweighted: rendering each directly is what
    /// differential screening saves), else the noisiest pixel's spread to the power √k for
    /// its `k` inexact pixels (a photon crossing a region of `k` pixels crosses about √k).
    pub fn spread_of(&self, map: &[u16], change: &Change) -> f64 {
        let spreads: Vec<f64> = change
            .pixels
            .iter()
            .map(|&(p, d)| {
                let from = map[p as usize];
                self.spread
                    .get(usize::from(from))
                    .and_then(|row| row.get(usize::from(d)))
                    .copied()
                    .unwrap_or(1.0)
            })
            .filter(|&s| s > 1.0)
            .collect();
        if spreads.len() <= 1 {
            return 1.0;
        }
        let worst = spreads.iter().copied().fold(1.0, f64::max);
        worst.powf((spreads.len() as f64).sqrt())
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
        if self.simplifying {
            return self.simplifications();
        }
        if self.growing {
            return self.growths_of_current();
        }
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
        // Moves, recolours and swaps, in that order, each once and never a single already
        // listed (nor an empty move).
        let mut seen: BTreeSet<Vec<(u32, u16)>> = out.iter().map(|c| c.pixels.clone()).collect();
        let more = [
            (
                self.config.move_objects,
                Self::object_moves as fn(&Self) -> Vec<Change>,
            ),
            (self.config.recolour_regions, Self::recolours),
            (self.config.swap_pixels, Self::swaps),
            (self.config.blocks, Self::blocks),
            (self.config.blocks, Self::object_sides),
        ];
        for (on, changes) in more {
            if !on {
                continue;
            }
            for c in changes(self) {
                if !c.pixels.is_empty() && seen.insert(c.pixels.clone()) {
                    out.push(c);
                }
            }
        }
        out
    }

    /// A simplification round's changes: each pixel not of the background set to it, then
    /// each region of two pixels or more not of the background set wholly to it.
    fn simplifications(&self) -> Vec<Change> {
        let background = self.background();
        let mut out: Vec<Change> = self
            .current
            .iter()
            .enumerate()
            .filter(|(_, &m)| m != background)
            .map(|(p, _)| Change {
                pixels: vec![(p as u32, background)],
            })
            .collect();
        for (m, pixels) in self.regions() {
            if m != background && pixels.len() >= 2 {
                out.push(Change {
                    pixels: pixels.iter().map(|&p| (p as u32, background)).collect(),
                });
            }
        }
        out
    }

    /// A growth round's changes: each object of at most [`GROWTH_MAX_PIXELS`] pixels not of
    /// the background, with its 8-connected neighbours, set wholly to each candidate material
    /// other than the background, then (an object of two pixels or more) its bounding box
    /// grown by each side in turn ([`grown_boxes`]) filled with its material; where two pixels
    /// or more change, objects in the order of their first pixel.
    fn growths_of_current(&self) -> Vec<Change> {
        let n = self.grid as i64;
        let background = self.background();
        let mut out = Vec::new();
        let mut seen = BTreeSet::new();
        for (m, pixels) in self.regions() {
            if m == background || pixels.len() > GROWTH_MAX_PIXELS {
                continue;
            }
            let mut grown: BTreeSet<usize> = BTreeSet::new();
            for &p in &pixels {
                let (y, x) = (p as i64 / n, p as i64 % n);
                for dy in -1..=1 {
                    for dx in -1..=1 {
                        let (yy, xx) = (y + dy, x + dx);
                        if (0..n).contains(&yy) && (0..n).contains(&xx) {
                            grown.insert((yy * n + xx) as usize);
                        }
                    }
                }
            }
            for &d in &self.materials {
                if d == background {
                    continue;
                }
                let pixels: Vec<(u32, u16)> = grown
                    .iter()
                    .filter(|&&p| self.current[p] != d)
                    .map(|&p| (p as u32, d))
                    .collect();
                if pixels.len() >= 2 && seen.insert(pixels.clone()) {
                    out.push(Change { pixels });
                }
            }
            if pixels.len() >= 2 {
                // An object found with a corner or a side missing (an L of three pixels where
                // a 3 × 2 block is): its bounding box grown by one row or column on each side
                // in turn, filled with its material.
                for rectangle in grown_boxes(&pixels, self.grid as usize) {
                    let pixels: Vec<(u32, u16)> = rectangle
                        .into_iter()
                        .filter(|&p| self.current[p] != m)
                        .map(|p| (p as u32, m))
                        .collect();
                    if pixels.len() >= 2 && seen.insert(pixels.clone()) {
                        out.push(Change { pixels });
                    }
                }
            }
        }
        out
    }

    /// Each 2 × 2 block, then each horizontal and each vertical pair of neighbouring pixels,
    /// set wholly to each candidate material where at least two of its pixels change; blocks
    /// and pairs in the order of their top-left pixel.
    fn blocks(&self) -> Vec<Change> {
        let n = self.grid as usize;
        let shapes: [&[(usize, usize)]; 3] = [
            &[(0, 0), (0, 1), (1, 0), (1, 1)],
            &[(0, 0), (0, 1)],
            &[(0, 0), (1, 0)],
        ];
        let mut out = Vec::new();
        for shape in shapes {
            for y in 0..n {
                for x in 0..n {
                    if shape.iter().any(|&(dy, dx)| y + dy >= n || x + dx >= n) {
                        continue;
                    }
                    let pixels: Vec<usize> = shape
                        .iter()
                        .map(|&(dy, dx)| (y + dy) * n + x + dx)
                        .collect();
                    for &d in &self.materials {
                        let changed: Vec<(u32, u16)> = pixels
                            .iter()
                            .filter(|&&p| self.current[p] != d)
                            .map(|&p| (p as u32, d))
                            .collect();
                        if changed.len() >= 2 {
                            out.push(Change { pixels: changed });
                        }
                    }
                }
            }
        }
        out
    }

    /// Each object (as [`Self::object_moves`] finds them) grown by the row or column just
    /// outside each side of its bounding box, over the box's span, and shrunk by its outermost
    /// row or column on each side (its pixels there set to the background): a rectangle found
    /// one row too thin or too wide is then one change, with the signal of the whole row.
    fn object_sides(&self) -> Vec<Change> {
        let n = self.grid as usize;
        let background = self.background();
        let mut out = Vec::new();
        for (m, pixels) in self.regions() {
            if m == background || pixels.len() * 2 > self.current.len() {
                continue;
            }
            let Some((y0, y1, x0, x1)) = bounding_box(&pixels, n) else {
                continue;
            };
            let row = |y: usize| (x0..=x1).map(move |x| y * n + x).collect::<Vec<_>>();
            let column = |x: usize| (y0..=y1).map(move |y| y * n + x).collect::<Vec<_>>();
            let mut grow = Vec::new();
            if y0 > 0 {
                grow.push(row(y0 - 1));
            }
            if y1 + 1 < n {
                grow.push(row(y1 + 1));
            }
            if x0 > 0 {
                grow.push(column(x0 - 1));
            }
            if x1 + 1 < n {
                grow.push(column(x1 + 1));
            }
            let shrink = [row(y0), row(y1), column(x0), column(x1)];
            for line in grow {
                let change: Vec<(u32, u16)> = line
                    .into_iter()
                    .filter(|&p| self.current[p] != m)
                    .map(|p| (p as u32, m))
                    .collect();
                out.push(Change { pixels: change });
            }
            for line in shrink {
                let change: Vec<(u32, u16)> = line
                    .into_iter()
                    .filter(|p| pixels.binary_search(p).is_ok())
                    .map(|p| (p as u32, background))
                    .collect();
                // Shrinking a line of the box away entirely is the object cleared or split.
                if change.len() < pixels.len() {
                    out.push(Change { pixels: change });
                }
            }
        }
        out
    }

    /// Each pair of 8-connected neighbouring pixels of different materials, their materials
    /// exchanged; pairs in the order of their first pixel, then right, down-left, down,
    /// down-right.
    fn swaps(&self) -> Vec<Change> {
        let n = self.grid as i64;
        let mut out = Vec::new();
        for p in 0..self.current.len() {
            let (y, x) = (p as i64 / n, p as i64 % n);
            for (dy, dx) in [(0i64, 1i64), (1, -1), (1, 0), (1, 1)] {
                let (yy, xx) = (y + dy, x + dx);
                if yy >= n || xx < 0 || xx >= n {
                    continue;
                }
                let q = (yy * n + xx) as usize;
                let (a, b) = (self.current[p], self.current[q]);
                if a != b {
                    out.push(Change {
                        pixels: vec![(p as u32, b), (q as u32, a)],
                    });
                }
            }
        }
        out
    }

    /// Each connected region of two pixels or more, background included, set wholly to each
    /// other candidate material.
    fn recolours(&self) -> Vec<Change> {
        let mut out = Vec::new();
        for (m, pixels) in self.regions() {
            if pixels.len() < 2 {
                continue;
            }
            for &d in &self.materials {
                if d != m {
                    out.push(Change {
                        pixels: pixels.iter().map(|&p| (p as u32, d)).collect(),
                    });
                }
            }
        }
        out
    }

    /// The map's 4-connected regions of one material, each with its pixels in order, the
    /// regions in the order of their first pixel.
    fn regions(&self) -> Vec<(u16, Vec<usize>)> {
        let n = self.grid as i64;
        let mut label = vec![usize::MAX; self.current.len()];
        let mut regions: Vec<(u16, Vec<usize>)> = Vec::new();
        for start in 0..self.current.len() {
            if label[start] != usize::MAX {
                continue;
            }
            let m = self.current[start];
            let id = regions.len();
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
            regions.push((m, pixels));
        }
        regions
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
        let objects: Vec<(u16, Vec<usize>)> = self
            .regions()
            .into_iter()
            .filter(|(m, _)| *m != background)
            .collect();
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

    /// Whether two changes may not be taken together: they touch pixels within one pixel of
    /// each other, unless both set one pixel each, to the same material, and different pixels
    /// (neighbours growing or shrinking one object together).
    fn near(&self, a: &Change, b: &Change) -> bool {
        if let ([(p, m)], [(q, d)]) = (&a.pixels[..], &b.pixels[..]) {
            if m == d && p != q {
                return false;
            }
        }
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
    fn sweep_scored(
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

    fn confirm_scored(
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

#[cfg(test)]
mod tests {
    use super::*;

    /// A refinement over materials 0 and 1 (job seed 1), knowing nothing of reweighting.
    fn two_materials(config: RefineConfig, grid: u32, start: Vec<u16>) -> Refinement {
        Refinement::new(config, grid, vec![0, 1], 1, start, Vec::new(), Vec::new())
    }

    fn config() -> RefineConfig {
        RefineConfig {
            photons: 100,
            confirm_photons: 200,
            z: 2.0,
            max_sweeps: 5,
            move_objects: true,
            screen: Screen::Direct,
            changes_per_render: 1024,
            escalations: 0,
            recolour_regions: false,
            pixel_mm: 1.0,
            direct_photons: None,
            retest_z: None,
            swap_pixels: false,
            blocks: false,
            simplify_z: None,
            grow_objects: false,
            grow_trial_z: None,
        }
    }

    /// Scores from a known truth: each block is minus the number of wrong pixels, plus noise
    /// that pairs cancel (the same per seed and photons for every map; fewer photons score
    /// higher, as a deviance does, so a render paired with one of other photons misleads).
    fn score_of(truth: &[u16], map: &[u16], seed: u64, photons: u32) -> (f64, Vec<f64>) {
        let wrong = truth.iter().zip(map).filter(|(a, b)| a != b).count() as f64;
        let blocks: Vec<f64> = (0..8)
            .map(|b| {
                -wrong / 8.0 + ((seed % 97) as f64) * 0.01 + f64::from(b) * 0.001
                    - f64::from(photons) * 0.01
            })
            .collect();
        (blocks.iter().sum(), blocks)
    }

    fn run(truth: &[u16], start: Vec<u16>, materials: Vec<u16>) -> Refinement {
        run_with(config(), truth, start, materials, Vec::new(), Vec::new())
    }

    /// A score's value and blocks.
    type Scored = (f64, Vec<f64>);

    /// Runs a refinement against [`score_of`]; a differential request's changes are scored as
    /// a direct render of each would be.
    fn run_with(
        config: RefineConfig,
        truth: &[u16],
        start: Vec<u16>,
        materials: Vec<u16>,
        reweightable: Vec<Vec<bool>>,
        opaque: Vec<bool>,
    ) -> Refinement {
        let score = |a: &[u16], seed: u64, photons: u32| score_of(truth, a, seed, photons);
        run_scored(config, start, materials, reweightable, opaque, &score)
    }

    /// [`run_with`] against any scores of a 4 × 4 map (its assignment, seed and photons).
    fn run_scored(
        config: RefineConfig,
        start: Vec<u16>,
        materials: Vec<u16>,
        reweightable: Vec<Vec<bool>>,
        opaque: Vec<bool>,
        score_of: &dyn Fn(&[u16], u64, u32) -> Scored,
    ) -> Refinement {
        run_traced(
            config,
            start,
            materials,
            reweightable,
            opaque,
            score_of,
            &mut |_| {},
        )
    }

    /// [`run_scored`], handing each step's state to `on_step` before its scores.
    fn run_traced(
        config: RefineConfig,
        start: Vec<u16>,
        materials: Vec<u16>,
        reweightable: Vec<Vec<bool>>,
        opaque: Vec<bool>,
        score_of: &dyn Fn(&[u16], u64, u32) -> Scored,
        on_step: &mut dyn FnMut(&Refinement),
    ) -> Refinement {
        let r = Refinement::new(config, 4, materials, 1, start, reweightable, opaque);
        drive(r, score_of, on_step)
    }

    /// Runs `r` to its end against `score_of`, handing each step's state to `on_step`.
    fn drive(
        mut r: Refinement,
        score_of: &dyn Fn(&[u16], u64, u32) -> Scored,
        on_step: &mut dyn FnMut(&Refinement),
    ) -> Refinement {
        let mut steps = 0;
        while !r.is_finished() {
            on_step(&r);
            let scored: Vec<(Scored, Vec<Option<ChangeScore>>)> = r
                .pending()
                .iter()
                .map(|q| {
                    let changes = q
                        .changes
                        .iter()
                        .map(|c| {
                            let mut a = q.assignment.clone();
                            for &(p, m) in &c.pixels {
                                a[p as usize] = m;
                            }
                            let (value, blocks) = score_of(&a, q.seed, q.photons);
                            Some(ChangeScore { value, blocks })
                        })
                        .collect();
                    (score_of(&q.assignment, q.seed, q.photons), changes)
                })
                .collect();
            let scores: Vec<BlockScore> = scored
                .iter()
                .map(|((v, b), c)| BlockScore {
                    value: *v,
                    blocks: b,
                    changes: c,
                })
                .collect();
            r.submit(&scores).unwrap();
            steps += 1;
            assert!(steps < 50, "the refinement ends");
        }
        r
    }

    #[test]
    fn growth_rounds_replace_a_strong_pixel_standing_in_for_a_weak_block() {
        // Each pixel grown outside the block costs less than the strong pixel: the grown map
        // wins outright.
        let start = stand_in_start();
        let run = |grow_objects| run_stand_in(0.2, grow_objects, 12, &mut |_| {});
        // Without growth rounds the start is where the stage ends.
        let kept = run(false);
        assert_eq!(kept.current().0, &start[..]);
        assert!(kept.history().iter().all(|h| !h.growth));
        // With them, the strong pixel's neighbourhood becomes the weak material, and the
        // sweeps after it trim what grew outside the block: the truth.
        let grown = run(true);
        assert_eq!(
            grown.current().0,
            &stand_in_truth()[..],
            "{:?}",
            grown.history()
        );
        let rounds: Vec<&SweepRecord> = grown.history().iter().filter(|h| h.growth).collect();
        assert!(rounds.first().is_some_and(|h| h.changed == 9), "{rounds:?}");
        // It won outright: no trial (a later round on the truth tries, and loses, one).
        assert!(rounds[0].trial_kept.is_none(), "{rounds:?}");
        // A round that changes nothing is not run again on its map.
        assert!(rounds.len() <= MAX_GROWTHS as usize);
        assert!(grown.is_finished());
        // The rounds' state survives a checkpoint (the scores only to JSON's float precision).
        let json = serde_json::to_string(&grown).unwrap();
        let back: Refinement = serde_json::from_str(&json).unwrap();
        assert_eq!((back.growths, &back.grown), (grown.growths, &grown.grown));
        assert_eq!(back.history().len(), grown.history().len());
        assert!(back
            .history()
            .iter()
            .zip(grown.history())
            .all(|(a, b)| a.growth == b.growth));
    }

    /// A 4 × 4 map whose truth is a 2 × 2 block (pixels 5, 6, 9, 10) of the weak material 1 in
    /// background 0, scored without noise: one pixel of the strong material 2 (worth four weak
    /// ones) at 5 fits the counts almost as well, and no single pixel, move or recolour
    /// improves it. Each non-background pixel outside the block costs `outside`.
    fn stand_in_scores(outside: f64) -> impl Fn(&[u16], u64, u32) -> Scored {
        const BLOCK: [usize; 4] = [5, 6, 9, 10];
        move |a: &[u16], seed: u64, _photons: u32| -> Scored {
            let weight = |m: u16| [0.0, 1.0, 4.0][usize::from(m)];
            let signal: f64 = BLOCK.iter().map(|&p| weight(a[p])).sum();
            let grown = (0..16).filter(|p| !BLOCK.contains(p) && a[*p] != 0).count() as f64;
            let strong = a.iter().filter(|&&m| m == 2).count() as f64;
            let badness = 2.0 * (signal - 4.0).powi(2) + outside * grown + 1.5 * strong;
            let objects = a.iter().filter(|&&m| m != 0).count() as f64;
            let blocks: Vec<f64> = (0..8)
                .map(|b| {
                    let sign = if b % 2 == 0 { 1.0 } else { -1.0 };
                    -badness / 8.0 + sign * 0.001 * objects + ((seed % 97) as f64) * 0.01
                })
                .collect();
            (blocks.iter().sum(), blocks)
        }
    }

    /// A refinement of [`stand_in_start`] against [`stand_in_scores`] of `outside`, over the
    /// three materials, handing each step's state to `on_step`.
    fn run_stand_in(
        outside: f64,
        grow_objects: bool,
        max_sweeps: u32,
        on_step: &mut dyn FnMut(&Refinement),
    ) -> Refinement {
        let config = RefineConfig {
            grow_objects,
            max_sweeps,
            ..config()
        };
        let score = stand_in_scores(outside);
        run_traced(
            config,
            stand_in_start(),
            vec![0, 1, 2],
            Vec::new(),
            Vec::new(),
            &score,
            on_step,
        )
    }

    /// The stand-in of [`stand_in_scores`]: the strong pixel at 5.
    fn stand_in_start() -> Vec<u16> {
        let mut start = vec![0u16; 16];
        start[5] = 2;
        start
    }

    fn stand_in_truth() -> Vec<u16> {
        let mut truth = vec![0u16; 16];
        for p in [5, 6, 9, 10] {
            truth[p] = 1;
        }
        truth
    }

    #[test]
    fn a_grown_map_that_loses_is_tried_and_kept_only_if_its_sweeps_beat_the_start() {
        // Grown too far, the map loses to the strong pixel (5 pixels outside the block cost
        // more than the strong pixel), but the sweeps from it trim it to the truth.
        let start = stand_in_start();
        let run = |max_sweeps| run_stand_in(0.4, true, max_sweeps, &mut |_| {});
        let tried = run(16);
        assert_eq!(
            tried.current().0,
            &stand_in_truth()[..],
            "{:?}",
            tried.history()
        );
        let ends: Vec<&SweepRecord> = tried
            .history()
            .iter()
            .filter(|h| h.trial_kept.is_some())
            .collect();
        assert!(
            ends.first().is_some_and(|h| h.trial_kept == Some(true)),
            "{ends:?}"
        );
        assert_eq!(ends[0].map, stand_in_truth(), "{ends:?}");
        assert!(tried.is_finished());
        // The trial survives a checkpoint: resumed midway, the run ends the same.
        let mut steps = 0;
        let mut midway = None;
        run_stand_in(0.4, true, 16, &mut |r: &Refinement| {
            steps += 1;
            if r.trial.is_some() && midway.is_none() {
                midway = Some(serde_json::to_string(r).unwrap());
            }
        });
        let midway: Refinement = serde_json::from_str(&midway.expect("a trial ran")).unwrap();
        assert!(steps > 0 && midway.trial.is_some());
        let resumed = drive(midway, &stand_in_scores(0.4), &mut |_| {});
        assert_eq!(resumed.current(), tried.current());
        assert_eq!(resumed.history().len(), tried.history().len());
        // Cut short by the sweep limit right after the round, the trial has not trimmed
        // anything: its map loses, and the strong pixel comes back.
        let round = tried.history().iter().position(|h| h.growth).unwrap() as u32;
        let cut = run(round + 1);
        assert_eq!(cut.current().0, &start[..], "{:?}", cut.history());
        let last = cut.history().last().unwrap();
        assert_eq!(last.trial_kept, Some(false), "{:?}", cut.history());
        assert_eq!(last.map, start);
        assert!(cut.is_finished());
        // The round records its best grown map's z. With a floor above it no trial runs, and
        // the stand-in stays; with a floor below every round's, the trials run as without one.
        let grown_z = tried.history().iter().find_map(|h| h.grown_z);
        let grown_z = grown_z.expect("the round records its best grown map's z");
        assert!(grown_z.is_finite() && grown_z < config().z, "{grown_z}");
        let floored = |floor: f64| {
            let config = RefineConfig {
                grow_objects: true,
                max_sweeps: 16,
                grow_trial_z: Some(floor),
                ..config()
            };
            let score = stand_in_scores(0.4);
            run_traced(
                config,
                start.clone(),
                vec![0, 1, 2],
                Vec::new(),
                Vec::new(),
                &score,
                &mut |_| {},
            )
        };
        let above = floored(grown_z + 0.5);
        assert!(above.history().iter().all(|h| h.trial_kept.is_none()));
        assert_eq!(above.current().0, &start[..], "{:?}", above.history());
        assert!(above.is_finished());
        let lowest = tried
            .history()
            .iter()
            .filter_map(|h| h.grown_z)
            .fold(grown_z, f64::min);
        let below = floored(lowest - 0.5);
        assert_eq!(below.current(), tried.current());
        assert_eq!(below.history(), tried.history());
    }

    #[test]
    fn simplification_clears_what_the_scores_cannot_see() {
        // Pixels 12, 13, 14 and 15 (the bottom row) are hidden: no score sees them. The truth
        // is background but pixel 5 and the hidden pixel 12; the start has the truth and two
        // spurious hidden pixels, 14 and 15.
        let hidden = |p: usize| p >= 12;
        let mut truth = vec![0u16; 16];
        truth[5] = 1;
        truth[12] = 1;
        let score = |a: &[u16], seed: u64, photons: u32| -> Scored {
            let wrong = (0..16).filter(|&p| !hidden(p) && a[p] != truth[p]).count() as f64;
            // Noise that the hidden pixels move but that sums to nothing.
            let objects = (12..16).filter(|&p| a[p] != 0).count() as f64;
            let blocks: Vec<f64> = (0..8)
                .map(|b| {
                    let sign = if b % 2 == 0 { 1.0 } else { -1.0 };
                    -wrong / 8.0 + sign * 0.001 * objects + ((seed % 97) as f64) * 0.01
                        - f64::from(photons) * 0.01
                })
                .collect();
            (blocks.iter().sum(), blocks)
        };
        let mut start = truth.clone();
        start[14] = 1;
        start[15] = 1;
        let run = |simplify_z| {
            let config = RefineConfig {
                simplify_z,
                ..config()
            };
            run_scored(
                config,
                start.clone(),
                vec![0, 1],
                Vec::new(),
                Vec::new(),
                &score,
            )
        };
        // Without simplification nothing beats the start: it stays.
        let kept = run(None);
        assert_eq!(kept.current().0, &start[..]);
        assert!(kept.history().iter().all(|h| !h.simplification));
        // With it, every hidden pixel becomes the background (the hidden object too: the
        // scores cannot tell it), and the seen one stays.
        let simplified = run(Some(1.0));
        let mut expected = truth.clone();
        expected[12] = 0;
        assert_eq!(simplified.current().0, &expected[..]);
        let rounds: Vec<&SweepRecord> = simplified
            .history()
            .iter()
            .filter(|h| h.simplification)
            .collect();
        assert!(!rounds.is_empty());
        assert_eq!(rounds[0].changed, 3);
        // A second round, on the simplified map, changes nothing and ends the stage.
        assert_eq!(rounds.last().map(|h| h.changed), Some(0));
        assert!(rounds.len() <= MAX_SIMPLIFICATIONS as usize);
        // With an escalation, rounds come after it, at its doubled photons.
        let mut rounds = Vec::new();
        run_traced(
            RefineConfig {
                simplify_z: Some(1.0),
                escalations: 1,
                ..config()
            },
            start.clone(),
            vec![0, 1],
            Vec::new(),
            Vec::new(),
            &score,
            &mut |r| {
                if r.simplifying && matches!(r.waiting, Some(Waiting::Sweep { .. })) {
                    rounds.push(r.pending()[0].photons);
                }
            },
        );
        assert!(
            !rounds.is_empty() && rounds.iter().all(|&p| p == 200),
            "{rounds:?}"
        );
        // A negative z would clear what loses: refused.
        assert!(RefineConfig {
            simplify_z: Some(-1.0),
            ..config()
        }
        .problem()
        .is_some());
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
    fn recolours_set_a_whole_region_to_each_other_material() {
        let mut start = vec![0u16; 16];
        for p in [5, 6, 9, 10] {
            start[p] = 1;
        }
        start[15] = 2;
        let cfg = RefineConfig {
            recolour_regions: true,
            ..config()
        };
        let r = Refinement::new(cfg, 4, vec![0, 1, 2], 1, start.clone(), vec![], vec![]);
        let recolours = r.recolours();
        // The background (11 pixels) to 1 and 2, the block to 0 and 2; the single pixel 15 is
        // left to the pixel changes.
        assert_eq!(recolours.len(), 4, "{recolours:?}");
        let block_to_2: Vec<(u32, u16)> = [5, 6, 9, 10].map(|p| (p, 2)).to_vec();
        assert!(recolours.iter().any(|c| c.pixels == block_to_2));
        assert!(recolours
            .iter()
            .any(|c| c.pixels.len() == 11 && c.pixels.iter().all(|&(_, d)| d == 1)));
        // A block found with the wrong material is one change away from the truth.
        let mut truth = start.clone();
        for p in [5, 6, 9, 10] {
            truth[p] = 2;
        }
        let cfg = RefineConfig {
            recolour_regions: true,
            move_objects: false,
            ..config()
        };
        let found = run_with(cfg, &truth, start, vec![0, 1, 2], Vec::new(), Vec::new());
        assert_eq!(found.current().0, &truth[..]);
    }

    #[test]
    fn noisy_recolours_are_left_out_of_differential_sweeps() {
        let mut start = vec![0u16; 16];
        for p in [5, 6, 9, 10] {
            start[p] = 1;
        }
        // 0 ↔ 1 is nearly exact, anything to or from 2 very noisy (a forward to a backward
        // phase function).
        let spread = vec![vec![1.0, 1.1, 300.0], vec![1.1, 1.0, 300.0], vec![300.0; 3]];
        let reweightable = vec![vec![true; 3]; 3];
        let cfg = |screen| RefineConfig {
            screen,
            recolour_regions: true,
            move_objects: false,
            ..config()
        };
        let r = Refinement::with_spread(
            cfg(Screen::Differential),
            4,
            vec![0, 1, 2],
            1,
            start.clone(),
            reweightable.clone(),
            vec![],
            spread.clone(),
        );
        let single = Change {
            pixels: vec![(3, 2)],
        };
        let block_to_0 = Change {
            pixels: [5, 6, 9, 10].map(|p| (p, 0)).to_vec(),
        };
        let block_to_2 = Change {
            pixels: [5, 6, 9, 10].map(|p| (p, 2)).to_vec(),
        };
        assert_eq!(r.spread_of(&start, &single), 1.0);
        assert!(r.spread_of(&start, &block_to_2) > MAX_SPREAD);
        assert!(
            !r.left_out(&single, &start, &single),
            "single pixels are always tried"
        );
        assert!(!r.left_out(&block_to_0, &start, &block_to_0));
        assert!(r.left_out(&block_to_2, &start, &block_to_2));
        // The sweep estimates 16 × 2 single pixels and 2 of the 4 recolours (the background
        // to 1 and the block to 0) in its one differential render.
        let estimated: usize = r.pending().iter().map(|q| q.changes.len()).sum();
        assert_eq!(r.pending().len(), 1);
        assert_eq!(estimated, 32 + 2);
        // Direct screening renders all four.
        let direct = Refinement::with_spread(
            cfg(Screen::Direct),
            4,
            vec![0, 1, 2],
            1,
            start,
            reweightable,
            vec![],
            spread,
        );
        assert_eq!(direct.pending().len(), 1 + 32 + 4);
    }

    #[test]
    fn object_moves_shift_a_block_by_one_pixel() {
        let mut start = vec![0u16; 16];
        for p in [5, 6, 9, 10] {
            start[p] = 1;
        }
        let r = two_materials(config(), 4, start.clone());
        let right = r
            .object_moves()
            .into_iter()
            .find(|c| c.pixels.contains(&(7, 1)))
            .expect("a move to the right");
        assert_eq!(right.pixels, vec![(5, 0), (7, 1), (9, 0), (11, 1)]);
    }

    #[test]
    fn swaps_exchange_neighbouring_pixels_of_different_materials() {
        // One object pixel (5) in a 4 × 4 map: its 8 neighbours each swap with it once.
        let mut start = vec![0u16; 16];
        start[5] = 1;
        let swapping = RefineConfig {
            swap_pixels: true,
            move_objects: false,
            ..config()
        };
        let r = two_materials(swapping.clone(), 4, start.clone());
        let swaps = r.swaps();
        assert_eq!(swaps.len(), 8);
        for c in &swaps {
            let [(p, a), (q, b)] = c.pixels[..] else {
                panic!("a swap of two pixels: {c:?}");
            };
            assert_eq!((a, b), (start[q as usize], start[p as usize]));
            assert!(p == 5 || q == 5);
        }
        assert!(swaps.iter().any(|c| c.pixels == vec![(5, 0), (10, 1)]));
        // A sweep tries them after the single pixels; without the option it does not.
        let tried = |config: RefineConfig| two_materials(config, 4, start.clone()).changes().len();
        let plain = RefineConfig {
            move_objects: false,
            ..config()
        };
        assert_eq!(tried(swapping), tried(plain) + 8);
    }

    #[test]
    fn object_sides_grow_and_shrink_each_side_of_an_object() {
        // A 1 × 2 object (pixels 5 and 6) in a 4 × 4 map.
        let mut start = vec![0u16; 16];
        start[5] = 1;
        start[6] = 1;
        let r = two_materials(
            RefineConfig {
                blocks: true,
                ..config()
            },
            4,
            start,
        );
        let sides: Vec<Vec<(u32, u16)>> = r.object_sides().into_iter().map(|c| c.pixels).collect();
        // Grown up, down, left and right; shrunk from the left and the right (shrinking its
        // only row would clear it).
        assert_eq!(
            sides,
            vec![
                vec![(1, 1), (2, 1)],
                vec![(9, 1), (10, 1)],
                vec![(4, 1)],
                vec![(7, 1)],
                vec![(5, 0)],
                vec![(6, 0)],
            ]
        );
    }

    #[test]
    fn a_growth_round_fills_an_objects_box_grown_by_each_side() {
        // An L of three pixels (5, 10, 11) in a 5 × 5 map: a 2 × 2 block (rows 1–2, columns
        // 0–1) with its top-right corner missing.
        let mut start = vec![0u16; 25];
        for p in [5, 10, 11] {
            start[p] = 1;
        }
        let r = two_materials(
            RefineConfig {
                grow_objects: true,
                ..config()
            },
            5,
            start,
        );
        let grown: Vec<Vec<(u32, u16)>> = r
            .growths_of_current()
            .into_iter()
            .map(|c| c.pixels)
            .collect();
        let set = |pixels: &[u32]| pixels.iter().map(|&p| (p, 1)).collect::<Vec<_>>();
        // The L with its 8-connected neighbours, then its box grown up, down and right,
        // filled (the missing corner, 6, with each); nothing lies left of column 0.
        assert_eq!(
            grown,
            vec![
                set(&[0, 1, 6, 7, 12, 15, 16, 17]),
                set(&[0, 1, 6]),
                set(&[6, 15, 16]),
                set(&[6, 7, 12]),
            ]
        );
        // A corner pixel's box grows only down and right.
        assert_eq!(grown_boxes(&[0], 5), vec![vec![0, 5], vec![0, 1]]);
    }

    #[test]
    fn blocks_set_two_by_two_blocks_and_pairs_wholly_to_each_material() {
        // A 3 × 3 map, all background but pixel 4 (the centre): 4 blocks and 12 pairs.
        let mut start = vec![0u16; 9];
        start[4] = 1;
        let blocking = RefineConfig {
            blocks: true,
            move_objects: false,
            ..config()
        };
        let r = two_materials(blocking.clone(), 3, start.clone());
        let blocks = r.blocks();
        // To material 1 every block and pair changes, except the pairs through the centre
        // (one pixel each); to material 0 none changes two pixels.
        assert_eq!(blocks.len(), 4 + 12 - 4);
        for c in &blocks {
            assert!(c.pixels.len() >= 2, "{c:?}");
            assert!(c
                .pixels
                .iter()
                .all(|&(p, d)| d == 1 && start[p as usize] == 0));
            assert!(c.pixels.windows(2).all(|w| w[0].0 < w[1].0));
        }
        // The top-left block: pixels 0, 1 and 3 (4 already is material 1).
        assert_eq!(blocks[0].pixels, vec![(0, 1), (1, 1), (3, 1)]);
        assert!(blocks.iter().any(|c| c.pixels == vec![(6, 1), (7, 1)]));
        assert!(blocks.iter().any(|c| c.pixels == vec![(2, 1), (5, 1)]));
        // A sweep tries them all after the single pixels (the one-pixel object's sides add
        // nothing: grown, each is a single pixel already listed; shrunk, it would be cleared);
        // without the option it does not.
        let tried = |config: RefineConfig| two_materials(config, 3, start.clone()).changes().len();
        let plain = RefineConfig {
            move_objects: false,
            ..config()
        };
        assert_eq!(tried(blocking), tried(plain) + blocks.len());
    }

    #[test]
    fn requests_share_a_seed_within_a_sweep_and_sweeps_differ() {
        let r = two_materials(config(), 4, vec![0; 16]);
        let seeds: BTreeSet<u64> = r.pending().iter().map(|p| p.seed).collect();
        assert_eq!(seeds.len(), 1);
        assert_eq!(r.pending().len(), 17);
        assert!(r.pending().iter().all(|p| p.photons == 100));
        assert!(config().problem().is_none());
        assert!(RefineConfig {
            z: f64::NAN,
            ..config()
        }
        .problem()
        .is_some());
        let trial_z = |z| {
            RefineConfig {
                grow_trial_z: Some(z),
                ..config()
            }
            .problem()
        };
        assert!(trial_z(f64::NAN).is_some_and(|p| p.contains("growth trial z")));
        assert!(trial_z(f64::NEG_INFINITY).is_none() && trial_z(-5.0).is_none());
    }

    /// Differential screening: the changes the reweighting covers ride on renders of the
    /// current map (in chunks), the others are rendered directly, and the result is the one
    /// direct screening finds.
    #[test]
    fn differential_screening_finds_what_direct_screening_does() {
        let mut truth = vec![0u16; 16];
        truth[5] = 1;
        truth[10] = 2;
        // 0 → anything and 1 → 0 reweight; 2 is like an opaque material: nothing leaves it.
        let reweightable = vec![
            vec![true, true, true],
            vec![true, true, false],
            vec![false, false, true],
        ];
        let cfg = RefineConfig {
            screen: Screen::Differential,
            changes_per_render: 10,
            ..config()
        };
        let first = Refinement::new(
            cfg.clone(),
            4,
            vec![0, 1, 2],
            1,
            vec![0; 16],
            reweightable.clone(),
            Vec::new(),
        );
        // 32 single-pixel changes, all from material 0: four differential renders of M.
        assert_eq!(first.pending().len(), 4);
        assert!(first.pending().iter().all(|q| q.assignment == vec![0; 16]));
        assert_eq!(
            first
                .pending()
                .iter()
                .map(|q| q.changes.len())
                .sum::<usize>(),
            32
        );
        let r = run_with(
            cfg,
            &truth,
            vec![0; 16],
            vec![0, 1, 2],
            reweightable,
            Vec::new(),
        );
        assert_eq!(r.current().0, &truth[..]);
        let direct = run(&truth, vec![0; 16], vec![0, 1, 2]);
        assert_eq!(r.current().0, direct.current().0);
    }

    /// The changes a differential sweep cannot reweight (here 0 → 2, like a scattering pixel
    /// in a transmissive background) are rendered with `direct_photons`, paired with a render
    /// of `M` at those photons (scores at other photons differ: a wrong pairing would take
    /// every one of them), and the refinement still ends at the truth.
    #[test]
    fn direct_renders_of_a_differential_sweep_have_their_own_photons() {
        let mut truth = vec![0u16; 16];
        truth[5] = 1;
        truth[10] = 2;
        let reweightable = vec![
            vec![true, true, false],
            vec![true, true, false],
            vec![true, true, true],
        ];
        let cfg = RefineConfig {
            screen: Screen::Differential,
            changes_per_render: 10,
            direct_photons: Some(25),
            ..config()
        };
        let first = Refinement::new(
            cfg.clone(),
            4,
            vec![0, 1, 2],
            1,
            vec![0; 16],
            reweightable.clone(),
            Vec::new(),
        );
        let pending = first.pending();
        // 16 reweighted changes (0 → 1) in two differential renders, then M and the 16
        // direct changes (0 → 2) at 25 photons.
        assert_eq!(pending.len(), 2 + 1 + 16);
        assert!(pending[..2].iter().all(|q| q.photons == 100));
        assert!(pending[2..].iter().all(|q| q.photons == 25));
        assert_eq!(pending[2].assignment, vec![0; 16]);
        assert!(pending[2].changes.is_empty());
        let r = run_with(
            cfg,
            &truth,
            vec![0; 16],
            vec![0, 1, 2],
            reweightable,
            Vec::new(),
        );
        assert_eq!(r.current().0, &truth[..]);
    }

    /// Scores `request` (a direct render) for [`an_escalated_sweep_retests_only_what_came_close`]:
    /// minus the wrong pixels per block, and for a map whose pixel 3 is 1, noise around a
    /// slightly worse mean (z about −0.4 against the truth), so only that change comes close.
    fn close_call_score(truth: &[u16], request: &RefineRequest) -> (f64, Vec<f64>) {
        let wrong = truth
            .iter()
            .zip(&request.assignment)
            .filter(|(a, b)| a != b)
            .count() as f64;
        let close = request.assignment[3] == 1 && wrong == 1.0;
        let blocks: Vec<f64> = (0..8)
            .map(|b| {
                if close {
                    if b % 2 == 0 {
                        0.3
                    } else {
                        -0.4
                    }
                } else {
                    -wrong / 8.0
                }
            })
            .collect();
        (blocks.iter().sum(), blocks)
    }

    /// After a sweep of the right map finds nothing, the escalated sweep renders only the
    /// change that came within `retest_z` (and `M`); without `retest_z`, every change again.
    #[test]
    fn an_escalated_sweep_retests_only_what_came_close() {
        let truth = vec![0u16; 16];
        let second_sweep = |retest_z: Option<f64>| {
            let cfg = RefineConfig {
                escalations: 1,
                move_objects: false,
                retest_z,
                ..config()
            };
            let mut r =
                Refinement::new(cfg, 4, vec![0, 1], 1, truth.clone(), Vec::new(), Vec::new());
            assert_eq!(r.pending().len(), 1 + 16, "M and every pixel turned to 1");
            let scored: Vec<(f64, Vec<f64>)> = r
                .pending()
                .iter()
                .map(|q| close_call_score(&truth, q))
                .collect();
            let scores: Vec<BlockScore> = scored
                .iter()
                .map(|(v, b)| BlockScore {
                    value: *v,
                    blocks: b,
                    changes: &[],
                })
                .collect();
            r.submit(&scores).unwrap();
            assert!(!r.is_finished(), "the sweep found nothing, so it escalates");
            assert!(r.pending().iter().all(|q| q.photons == 200));
            r.pending()
                .iter()
                .map(|q| q.assignment.clone())
                .collect::<Vec<_>>()
        };
        let mut close = truth.clone();
        close[3] = 1;
        assert_eq!(second_sweep(Some(-1.0)), vec![truth.clone(), close]);
        assert_eq!(second_sweep(Some(0.0)), vec![truth.clone()]);
        assert_eq!(second_sweep(None).len(), 1 + 16);
    }

    /// A pixel whose material nothing reweights out of to the background (3, like a
    /// non-scattering one in a scattering background) is filled too, opaque or not.
    #[test]
    fn non_scattering_pixels_are_filled_too() {
        let mut start = vec![0u16; 16];
        start[3] = 3;
        start[9] = 1;
        let reweightable = vec![
            vec![true, true, true, true],
            vec![true, true, true, true],
            vec![false, false, true, false],
            vec![false, false, true, true],
        ];
        let cfg = RefineConfig {
            screen: Screen::Differential,
            ..config()
        };
        let r = Refinement::new(
            cfg,
            4,
            vec![0, 1, 3],
            1,
            start.clone(),
            reweightable,
            vec![false, false, true, false],
        );
        let mut base = start;
        base[3] = 0;
        assert_eq!(r.pending().len(), 1, "nothing rendered directly");
        assert_eq!(r.pending()[0].assignment, base);
        assert_eq!(r.pending()[0].changes[0].pixels, vec![(3, 3)]);
    }

    /// With an opaque material (2: nothing reweights out of it), a differential sweep renders
    /// the filled base (the map with its opaque pixels set to the background): `M` is its
    /// first change, clearing an opaque pixel is a change of it like any other, so nothing is
    /// rendered directly, and the refinement ends where direct screening does.
    #[test]
    fn opaque_pixels_are_cleared_from_the_filled_base() {
        let mut truth = vec![0u16; 16];
        truth[5] = 2;
        truth[6] = 2;
        truth[10] = 1;
        // Start with an opaque pixel too many and one missing.
        let mut start = truth.clone();
        start[6] = 0;
        start[12] = 2;
        let reweightable = vec![
            vec![true, true, true],
            vec![true, true, true],
            vec![false, false, true],
        ];
        let opaque = vec![false, false, true];
        let cfg = RefineConfig {
            screen: Screen::Differential,
            ..config()
        };
        let first = Refinement::new(
            cfg.clone(),
            4,
            vec![0, 1, 2],
            1,
            start.clone(),
            reweightable.clone(),
            opaque.clone(),
        );
        let pending = first.pending();
        assert_eq!(pending.len(), 1, "one differential render, nothing direct");
        let mut base = start.clone();
        base[5] = 0;
        base[12] = 0;
        assert_eq!(pending[0].assignment, base);
        assert_eq!(
            pending[0].changes[0].pixels,
            vec![(5, 2), (12, 2)],
            "M is the base's first change"
        );
        // Clearing pixel 12 keeps pixel 5 opaque: the change of the base is (5, 2) alone.
        assert!(pending[0].changes[1..]
            .iter()
            .any(|c| c.pixels == vec![(5, 2)]));
        let r = run_with(
            cfg,
            &truth,
            start.clone(),
            vec![0, 1, 2],
            reweightable,
            opaque,
        );
        assert_eq!(r.current().0, &truth[..]);
        let direct = run(&truth, start, vec![0, 1, 2]);
        assert_eq!(r.current().0, direct.current().0);
    }
}
