//! A render group: renders that share geometry, material table and photon range (the
//! candidates of one search step that need the same photons, or one setup render), cut into
//! photon-range pieces for workers, with their partial counts summed in memory. A group may
//! start from counts already in hand (racing's first stage), rendering only the photons after
//! them.
//!
//! A differential group (a refinement's screen) is one render with the changes it also
//! estimates; it goes to one worker whole, which renders it in the job's chunks and returns its
//! counts with one score per change (the deltas behind them never cross the wire).
//!
//! A scored group (a likelihood job's renders that nothing extends) is cut by renders, not by
//! photons: each piece is some of its renders over all their photons, and the worker returns
//! one deviance per render instead of its counts ([`scatterfarm_proto::scored`]), so the
//! coordinator never ingests those lightfields.
//!
//! A plain group whose counts would not fit one result (more than [`MAX_RESULT_BYTES`] of
//! matrices) is cut by renders too, with counts: each piece is at most that many bytes of its
//! renders, over all the group's photons.
//!
//! Counts are additive over photon ranges (`[0, a) + [a, n) = [0, n)` per item, bit-exactly), so
//! a group's sums do not depend on how it was cut, in what order pieces came back, or how often a
//! piece was leased again.

use scatterfarm_job::plan::SetupKind;
use scatterfarm_model::differential::{change_is_reweightable, Change};
use scatterfarm_model::likelihood::{blocks, Deviance};
use scatterfarm_model::{CountMatrix, Geometry, Material};
pub use scatterfarm_search::steps::GroupItem;
use std::collections::VecDeque;

/// The most count-matrix bytes one piece's result may carry, a quarter of a message
/// (`scatterfarm_proto::v1::MAX_MESSAGE_BYTES`): a group whose renders' counts are more is cut
/// by renders.
pub const MAX_RESULT_BYTES: usize = 256 << 20;

/// What a group's counts are for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Purpose {
    Setup(SetupKind),
    /// The renders of the search's current step that have no score yet.
    Search,
}

/// A photon range of a group handed to a worker.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Piece {
    pub task_id: u64,
    /// 1 for the first lease; each new lease of the same range adds one.
    pub attempt: u32,
    pub first: u32,
    pub count: u32,
    /// The group's renders the piece holds, from `items_first`: all of them for a group cut
    /// by photons, some for one cut by renders.
    pub items_first: u32,
    pub items_count: u32,
}

impl Piece {
    /// The indices of the group's renders the piece holds.
    pub fn items(&self) -> std::ops::Range<usize> {
        let first = self.items_first as usize;
        first..first + self.items_count as usize
    }
}

/// Renders rendered together.
#[derive(Debug)]
pub struct RenderGroup {
    /// Unique within a coordinator's run; a result for a group that is gone is refused.
    pub id: u64,
    pub purpose: Purpose,
    pub geometry: Geometry,
    pub table: Vec<Material>,
    pub items: Vec<GroupItem>,
    /// Photons per source of every render of the group, when complete.
    pub photons: u32,
    /// The first photon the group renders: the photons before it came summed in.
    pub start: u32,
    /// The next photon never handed out.
    next: u32,
    /// Pieces handed back (expired, released or refused), handed out again first.
    requeue: VecDeque<Piece>,
    /// Photons per source summed so far.
    done: u64,
    /// Empty until the first piece arrives, whose matrices become the sums (no zero-filled
    /// 5 MB buffers, no first addition).
    sums: Vec<CountMatrix>,
    /// Scattering events reported with the summed pieces.
    pub scatter_events: u64,
    /// The changes a differential group's one render also estimates; empty for plain groups.
    pub changes: Vec<Change>,
    /// A differential group's change scores, once its piece is in.
    change_scores: Option<Vec<Option<Deviance>>>,
    /// Whether its workers score its renders (cut by renders, every piece from photon 0).
    scored: bool,
    /// Whether it is cut by renders (a scored group, or one whose counts would not fit one
    /// result): then at most this many renders per piece.
    by_renders: Option<u32>,
    /// A group cut by renders: its next render never handed out.
    item_next: usize,
    /// A scored group's render scores as their pieces come in, one slot per render.
    render_scores: Vec<Option<Deviance>>,
    /// A group cut by renders with counts: each render's counts (with the photons before
    /// `start` summed in) as its piece comes in, one slot per render.
    render_counts: Vec<Option<CountMatrix>>,
    /// A group cut by renders: its renders come in so far.
    items_done: usize,
    /// The most count-matrix bytes one piece's result may carry ([`MAX_RESULT_BYTES`]).
    result_bytes: usize,
}

/// What a complete group yields.
#[derive(Debug)]
pub struct GroupParts {
    /// The summed counts, one per item (empty for a scored group).
    pub counts: Vec<CountMatrix>,
    /// A differential group's change scores.
    pub change_scores: Option<Vec<Option<Deviance>>>,
    /// A scored group's render scores, one per item.
    pub render_scores: Option<Vec<Deviance>>,
}

impl RenderGroup {
    pub fn new(
        id: u64,
        purpose: Purpose,
        geometry: Geometry,
        table: Vec<Material>,
        items: Vec<GroupItem>,
        photons: u32,
    ) -> RenderGroup {
        let sums = Vec::new();
        let mut group = RenderGroup {
            id,
            purpose,
            geometry,
            table,
            items,
            photons,
            start: 0,
            next: 0,
            requeue: VecDeque::new(),
            done: 0,
            sums,
            scatter_events: 0,
            changes: Vec::new(),
            change_scores: None,
            scored: false,
            by_renders: None,
            item_next: 0,
            render_scores: Vec::new(),
            render_counts: Vec::new(),
            items_done: 0,
            result_bytes: MAX_RESULT_BYTES,
        };
        group.cut_to_fit();
        group
    }

    /// The group with results of at most `bytes` of count matrices (not [`MAX_RESULT_BYTES`]),
    /// cut by renders if its counts are more.
    pub fn with_result_bytes(mut self, bytes: usize) -> RenderGroup {
        self.result_bytes = bytes;
        if self.by_renders.is_some() && !self.scored {
            self.by_renders = None;
        }
        self.cut_to_fit();
        self
    }

    /// Cuts a plain group by renders if its counts would not fit one result
    /// (`result_bytes`); leaves it as it is otherwise. Only before anything is taken from it.
    fn cut_to_fit(&mut self) {
        let matrix = 4 * self.geometry.sources() * self.geometry.bins();
        let fit = (self.result_bytes / matrix.max(1)).max(1);
        if self.scored || self.is_differential() || self.items.len() <= fit {
            self.by_renders = None;
            self.render_counts = Vec::new();
            return;
        }
        self.by_renders = Some(u32::try_from(fit).unwrap_or(u32::MAX));
        self.render_counts = if self.start > 0 && self.sums.len() == self.items.len() {
            std::mem::take(&mut self.sums)
                .into_iter()
                .map(Some)
                .collect()
        } else {
            vec![None; self.items.len()]
        };
    }

    /// The group as one whose workers score its renders (a plain group from photon 0): it is
    /// cut by renders, and its renders' scores come back instead of their counts.
    pub fn scored_on_workers(mut self) -> RenderGroup {
        if self.is_differential() || self.start != 0 {
            return self;
        }
        self.scored = true;
        self.by_renders = Some(u32::MAX);
        self.render_counts = Vec::new();
        self.render_scores = vec![None; self.items.len()];
        self
    }

    /// Whether its workers score its renders.
    pub fn is_scored(&self) -> bool {
        self.scored
    }

    /// Whether it is cut by renders (each piece some renders over all the group's photons).
    pub fn is_cut_by_renders(&self) -> bool {
        self.by_renders.is_some()
    }

    /// Whether a worker that does not score renders can be served from the group: a plain
    /// group, or a scored one nothing has been taken from yet, which then goes back to counts
    /// (the coordinator scores them, to the same scores).
    pub fn serves_counts(&mut self) -> bool {
        if !self.scored {
            return true;
        }
        if self.item_next > 0 || self.items_done > 0 || !self.requeue.is_empty() {
            return false;
        }
        self.scored = false;
        self.render_scores = Vec::new();
        self.by_renders = None;
        self.cut_to_fit();
        true
    }

    /// The group as a differential render of its one item, estimating `changes` too.
    pub fn with_changes(mut self, changes: Vec<Change>) -> RenderGroup {
        self.changes = changes;
        self
    }

    /// Whether the group is a differential render.
    pub fn is_differential(&self) -> bool {
        !self.changes.is_empty()
    }

    /// The group with photons `[0, start)` of every item already summed in `sums` (one
    /// matrix per item, in order): only `[start, photons)` is handed out.
    pub fn starting_from(mut self, start: u32, sums: Vec<CountMatrix>) -> RenderGroup {
        if start == 0 || start >= self.photons || sums.len() != self.items.len() || self.scored {
            return self;
        }
        self.start = start;
        self.next = start;
        self.done = u64::from(start);
        self.sums = sums;
        self.cut_to_fit();
        self
    }

    /// Whether a piece can be handed out now.
    pub fn has_work(&self) -> bool {
        if self.by_renders.is_some() {
            return !self.requeue.is_empty() || self.item_next < self.items.len();
        }
        !self.requeue.is_empty() || self.next < self.photons
    }

    /// The next piece: a handed-back one (next attempt), else up to `max_photons` new photons
    /// per source of every render (a scored group: whole renders, as many as `max_photons`
    /// photons per source of one render make, at least one). `new_task_id` gives ids to new
    /// pieces.
    pub fn take(
        &mut self,
        max_photons: u32,
        new_task_id: &mut dyn FnMut() -> u64,
    ) -> Option<Piece> {
        if let Some(mut p) = self.requeue.pop_front() {
            p.attempt += 1;
            return Some(p);
        }
        if let Some(most) = self.by_renders {
            let left = self.items.len() - self.item_next;
            if left == 0 {
                return None;
            }
            let count = self.photons - self.start;
            let renders = (max_photons / count.max(1)).clamp(1, (left as u32).min(most));
            let piece = Piece {
                task_id: new_task_id(),
                attempt: 1,
                first: self.start,
                count,
                items_first: self.item_next as u32,
                items_count: renders,
            };
            self.item_next += renders as usize;
            return Some(piece);
        }
        if self.next >= self.photons {
            return None;
        }
        // A differential render goes whole: its worker scores the changes of all its photons.
        let count = if self.is_differential() {
            self.photons - self.next
        } else {
            max_photons.clamp(1, self.photons - self.next)
        };
        let piece = Piece {
            task_id: new_task_id(),
            attempt: 1,
            first: self.next,
            count,
            items_first: 0,
            items_count: self.items.len() as u32,
        };
        self.next += count;
        Some(piece)
    }

    /// Hands a leased piece back to be leased again.
    pub fn give_back(&mut self, piece: Piece) {
        self.requeue.push_back(piece);
    }

    /// Checks a piece's result: one count matrix per item, each of the group's shape, and no
    /// source with more exits than photons launched; a differential group's change scores; a
    /// scored group's render scores, and no counts.
    pub fn check(
        &self,
        piece: &Piece,
        counts: &[CountMatrix],
        change_scores: &[Option<Deviance>],
        render_scores: &[Deviance],
    ) -> Result<(), String> {
        self.check_change_scores(change_scores)?;
        if self.scored {
            if !counts.is_empty() {
                return Err(format!(
                    "{} count matrices for renders scored on the worker",
                    counts.len()
                ));
            }
            return self.check_render_scores(piece, render_scores);
        }
        if !render_scores.is_empty() {
            return Err(format!(
                "{} render scores for renders scored by the coordinator",
                render_scores.len()
            ));
        }
        if counts.len() != piece.items_count as usize {
            return Err(format!(
                "{} count matrices for {} assignments",
                counts.len(),
                piece.items_count
            ));
        }
        let (sources, bins) = (self.geometry.sources(), self.geometry.bins());
        for (i, c) in counts.iter().enumerate() {
            if c.sources != sources || c.bins != bins || c.counts.len() != sources * bins {
                return Err(format!(
                    "assignment {i}: a {}×{} matrix with {} counts, expected {sources}×{bins}",
                    c.sources,
                    c.bins,
                    c.counts.len()
                ));
            }
            for s in 0..sources {
                let total: u64 = c.row(s).iter().map(|&v| u64::from(v)).sum();
                if total > u64::from(piece.count) {
                    return Err(format!(
                        "assignment {i}, source {s}: {total} photons exited, {} were launched",
                        piece.count
                    ));
                }
            }
        }
        Ok(())
    }

    /// Checks a differential group's change scores: one per change, a score exactly where the
    /// change can be reweighted, each with the geometry's blocks, every block a deviance's
    /// (not above 0) and the value their sum. A plain group takes none.
    fn check_change_scores(&self, scores: &[Option<Deviance>]) -> Result<(), String> {
        if scores.len() != self.changes.len() {
            return Err(format!(
                "{} change scores for {} changes",
                scores.len(),
                self.changes.len()
            ));
        }
        let Some(item) = self.items.first().filter(|_| self.is_differential()) else {
            return Ok(());
        };
        let expected = blocks(self.geometry.sources() * self.geometry.bins());
        for (k, (change, score)) in self.changes.iter().zip(scores).enumerate() {
            let reweightable = change_is_reweightable(&self.table, &item.item.assignment, change);
            match score {
                None if reweightable => {
                    return Err(format!("change {k} can be reweighted, yet it has no score"))
                }
                Some(_) if !reweightable => {
                    return Err(format!(
                        "change {k} cannot be reweighted, yet it has a score"
                    ))
                }
                None => {}
                Some(d) => {
                    check_deviance(d, expected).map_err(|why| format!("change {k}: {why}"))?
                }
            }
        }
        Ok(())
    }

    /// Checks a scored piece's render scores: one per render it holds, each with the
    /// geometry's blocks, every block a deviance's (not above 0) and the value their sum.
    fn check_render_scores(&self, piece: &Piece, scores: &[Deviance]) -> Result<(), String> {
        if scores.len() != piece.items_count as usize {
            return Err(format!(
                "{} render scores for {} renders",
                scores.len(),
                piece.items_count
            ));
        }
        let expected = blocks(self.geometry.sources() * self.geometry.bins());
        for (k, d) in scores.iter().enumerate() {
            check_deviance(d, expected).map_err(|why| format!("render {k}: {why}"))?;
        }
        Ok(())
    }

    /// Adds a checked piece's counts (and a differential group's change scores, or a scored
    /// group's render scores).
    pub fn accumulate(
        &mut self,
        piece: &Piece,
        counts: Vec<CountMatrix>,
        scatter_events: u64,
        change_scores: Vec<Option<Deviance>>,
        render_scores: Vec<Deviance>,
    ) {
        if self.scored {
            for (slot, score) in self.render_scores[piece.items()]
                .iter_mut()
                .zip(render_scores)
            {
                if slot.replace(score).is_none() {
                    self.items_done += 1;
                }
            }
            self.scatter_events += scatter_events;
            return;
        }
        if self.is_differential() {
            self.change_scores = Some(change_scores);
        }
        if self.by_renders.is_some() {
            for (slot, c) in self.render_counts[piece.items()].iter_mut().zip(counts) {
                match slot {
                    // The photons before `start`, summed in.
                    Some(sum) if self.start > 0 => {
                        for (a, b) in sum.counts.iter_mut().zip(&c.counts) {
                            *a += *b;
                        }
                    }
                    _ => *slot = Some(c),
                }
            }
            self.items_done += piece.items_count as usize;
            self.scatter_events += scatter_events;
            return;
        }
        if self.sums.is_empty() {
            self.sums = counts;
        } else {
            for (sum, c) in self.sums.iter_mut().zip(&counts) {
                for (a, b) in sum.counts.iter_mut().zip(&c.counts) {
                    *a += *b;
                }
            }
        }
        self.done += u64::from(piece.count);
        self.scatter_events += scatter_events;
    }

    /// Whether every photon of every render has been summed (a scored group: every render
    /// scored).
    pub fn is_complete(&self) -> bool {
        if self.by_renders.is_some() {
            return self.items_done == self.items.len();
        }
        self.done == u64::from(self.photons)
    }

    /// What the complete group yields: its summed counts (one per item; none for a scored
    /// group), a differential group's change scores, a scored group's render scores.
    pub fn into_parts(self) -> GroupParts {
        if self.scored {
            return GroupParts {
                counts: Vec::new(),
                change_scores: None,
                render_scores: self.render_scores.into_iter().collect(),
            };
        }
        let zeros = || CountMatrix::zeros(self.geometry.sources(), self.geometry.bins());
        if self.by_renders.is_some() {
            let counts = self
                .render_counts
                .into_iter()
                .map(|c| c.unwrap_or_else(zeros))
                .collect();
            return GroupParts {
                counts,
                change_scores: None,
                render_scores: None,
            };
        }
        let counts = if self.sums.is_empty() {
            let zeros = CountMatrix::zeros(self.geometry.sources(), self.geometry.bins());
            vec![zeros; self.items.len()]
        } else {
            self.sums
        };
        GroupParts {
            counts,
            change_scores: self.change_scores,
            render_scores: None,
        }
    }

    /// The summed counts, one per item.
    pub fn into_sums(self) -> Vec<CountMatrix> {
        self.into_parts().counts
    }
}

/// How far above 0 a block may round: a term is never below 0 but its floating-point sum can
/// be, by a few ulps, where the render matches the target exactly.
const BLOCK_ROUNDING: f64 = 1e-9;

/// Checks a deviance from a worker: `expected` blocks, none above 0 (beyond rounding), the
/// value their sum (bit for bit, as the likelihood sums them).
fn check_deviance(d: &Deviance, expected: usize) -> Result<(), String> {
    if d.blocks.len() != expected {
        return Err(format!("{} blocks, expected {expected}", d.blocks.len()));
    }
    let sum: f64 = d.blocks.iter().sum();
    if d.blocks.iter().any(|b| *b > BLOCK_ROUNDING) || sum.to_bits() != d.value.to_bits() {
        return Err(format!(
            "a score of {} that is not the sum of its blocks, or a block above 0",
            d.value
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use scatterfarm_engines::CpuEngine;
    use scatterfarm_model::{Engine, PhotonRange, RenderBatch, RenderItem};

    fn geometry() -> Geometry {
        Geometry {
            size_mm: 16.0,
            grid: 2,
            positions: 8,
            directions: 3,
        }
    }

    fn group(photons: u32) -> RenderGroup {
        let items = (0..2)
            .map(|i| GroupItem {
                identity: [i; 32],
                item: RenderItem {
                    assignment: vec![0, i as u16, 1, 0],
                    seed: 5 + u64::from(i),
                },
            })
            .collect();
        let table = vec![
            Material {
                sigma_s: 0.5,
                sigma_a: 0.01,
                g: 0.3,
            },
            Material {
                sigma_s: 0.1,
                sigma_a: 0.2,
                g: 0.0,
            },
        ];
        RenderGroup::new(1, Purpose::Search, geometry(), table, items, photons)
    }

    fn render(g: &RenderGroup, p: &Piece) -> Vec<CountMatrix> {
        let items: Vec<RenderItem> = g.items.iter().map(|i| i.item.clone()).collect();
        CpuEngine::new()
            .render(&RenderBatch {
                geometry: g.geometry,
                table: &g.table,
                items: &items,
                photons: PhotonRange {
                    first: p.first,
                    count: p.count,
                },
            })
            .unwrap()
            .into_iter()
            .map(|o| o.counts)
            .collect()
    }

    #[test]
    fn pieces_out_of_order_and_retried_sum_to_one_render() {
        let mut whole = group(100);
        let mut ids = 0u64;
        let mut next = || {
            ids += 1;
            ids
        };
        let all = whole.take(1000, &mut next).unwrap();
        assert_eq!((all.first, all.count), (0, 100));
        let c = render(&whole, &all);
        whole.accumulate(&all, c, 0, Vec::new(), Vec::new());
        assert!(whole.is_complete());

        let mut cut = group(100);
        let a = cut.take(30, &mut next).unwrap();
        let b = cut.take(30, &mut next).unwrap();
        let c2 = cut.take(30, &mut next).unwrap();
        let d = cut.take(30, &mut next).unwrap();
        assert_eq!((d.first, d.count), (90, 10));
        assert!(cut.take(30, &mut next).is_none());
        // b expires and comes back as attempt 2 with the same range and id.
        cut.give_back(b);
        let b2 = cut.take(30, &mut next).unwrap();
        assert_eq!((b2.task_id, b2.attempt, b2.first), (b.task_id, 2, b.first));
        for p in [d, a, b2, c2] {
            let counts = render(&cut, &p);
            cut.check(&p, &counts, &[], &[]).unwrap();
            cut.accumulate(&p, counts, 0, Vec::new(), Vec::new());
        }
        assert!(cut.is_complete());
        assert_eq!(cut.into_sums(), whole.into_sums());
    }

    #[test]
    fn a_group_started_from_a_prefix_sums_to_the_whole_render() {
        let mut ids = 0u64;
        let mut next = || {
            ids += 1;
            ids
        };
        let mut whole = group(100);
        let all = whole.take(1000, &mut next).unwrap();
        let c = render(&whole, &all);
        whole.accumulate(&all, c, 0, Vec::new(), Vec::new());

        let mut first = group(40);
        let p = first.take(1000, &mut next).unwrap();
        let c = render(&first, &p);
        first.accumulate(&p, c, 0, Vec::new(), Vec::new());
        let mut rest = group(100).starting_from(40, first.into_sums());
        assert_eq!(rest.start, 40);
        let p = rest.take(1000, &mut next).unwrap();
        assert_eq!(
            (p.first, p.count),
            (40, 60),
            "only the photons after the prefix"
        );
        let c = render(&rest, &p);
        rest.accumulate(&p, c, 0, Vec::new(), Vec::new());
        assert!(rest.is_complete());
        assert_eq!(rest.into_sums(), whole.into_sums());
    }

    #[test]
    fn a_group_too_big_for_one_result_is_cut_by_renders_to_the_same_sums() {
        let mut whole = group(100);
        let all = whole.take(100, &mut || 0).unwrap();
        let c = render(&whole, &all);
        whole.accumulate(&all, c, 0, Vec::new(), Vec::new());
        let whole = whole.into_sums();
        let one = 4 * geometry().sources() * geometry().bins();
        let mut ids = 0u64;
        let mut next = || {
            ids += 1;
            ids
        };
        // From photon 0, and from counts in hand for [0, 40).
        let mut prefix = group(40);
        let p = prefix.take(40, &mut next).unwrap();
        let c = render(&prefix, &p);
        prefix.accumulate(&p, c, 0, Vec::new(), Vec::new());
        let cuts = [
            group(100).with_result_bytes(one),
            group(100)
                .with_result_bytes(one)
                .starting_from(40, prefix.into_sums()),
        ];
        for (k, mut g) in cuts.into_iter().enumerate() {
            assert!(g.is_cut_by_renders());
            let a = g.take(1, &mut next).unwrap();
            let b = g.take(1000, &mut next).unwrap();
            assert!(g.take(1000, &mut next).is_none());
            let start = if k == 0 { 0 } else { 40 };
            assert_eq!(
                (a.first, a.count, a.items(), b.items()),
                (start, 100 - start, 0..1, 1..2)
            );
            let counts = |p: &Piece| render(&g, p)[p.items()].to_vec();
            let (ca, cb) = (counts(&a), counts(&b));
            assert!(g.check(&a, &cb, &[], &[]).is_ok());
            assert!(g
                .check(&a, &[ca[0].clone(), cb[0].clone()], &[], &[])
                .is_err());
            g.accumulate(&b, cb, 0, Vec::new(), Vec::new());
            assert!(!g.is_complete());
            g.accumulate(&a, ca, 0, Vec::new(), Vec::new());
            assert!(g.is_complete());
            assert_eq!(g.into_sums(), whole, "cut {k}");
        }
        // Where the counts fit, the group is cut by photons.
        assert!(!group(100).with_result_bytes(2 * one).is_cut_by_renders());
    }

    #[test]
    fn bad_counts_are_refused_with_a_reason() {
        let mut g = group(10);
        let p = g.take(10, &mut || 1).unwrap();
        let mut c = render(&g, &p);
        assert!(g
            .check(&p, &c[..1], &[], &[])
            .unwrap_err()
            .contains("1 count matrices"));
        c[1].counts[0] += 11;
        assert!(g.check(&p, &c, &[], &[]).unwrap_err().contains("exited"));
        let wrong = vec![CountMatrix::zeros(3, 3); 2];
        assert!(g
            .check(&p, &wrong, &[], &[])
            .unwrap_err()
            .contains("expected"));
    }

    #[test]
    fn a_scored_group_is_cut_by_renders_and_takes_scores_not_counts() {
        let mut t = group(50);
        let all = t.take(50, &mut || 0).unwrap();
        let tc = &render(&t, &all)[1];
        let target = scatterfarm_model::likelihood::Target {
            values: tc.counts.iter().map(|&v| v as f32 / 50.0).collect(),
            photons_per_source: 50,
        };
        let mut g = group(50).scored_on_workers();
        assert!(g.is_scored());
        let mut ids = 0u64;
        let mut next = || {
            ids += 1;
            ids
        };
        // 60 photons per source make one render of 50: one render per piece, all photons.
        let a = g.take(60, &mut next).unwrap();
        let b = g.take(60, &mut next).unwrap();
        assert!(g.take(60, &mut next).is_none());
        assert_eq!(
            (a.first, a.count, a.items(), b.items()),
            (0, 50, 0..1, 1..2)
        );
        let score = |g: &RenderGroup, p: &Piece| -> Vec<Deviance> {
            let counts = render(
                g,
                &Piece {
                    items_first: 0,
                    items_count: 2,
                    ..*p
                },
            );
            counts[p.items()]
                .iter()
                .map(|c| scatterfarm_model::likelihood::deviance(&target, c, 50).unwrap())
                .collect()
        };
        let (sa, sb) = (score(&g, &a), score(&g, &b));
        assert!(g
            .check(&a, &render(&g, &a), &[], &sa)
            .unwrap_err()
            .contains("count matrices"));
        assert!(g
            .check(&a, &[], &[], &[])
            .unwrap_err()
            .contains("0 render scores"));
        let mut bent = sa.clone();
        bent[0].value += 1.0;
        assert!(g
            .check(&a, &[], &[], &bent)
            .unwrap_err()
            .contains("render 0"));
        for (p, s) in [(b, sb.clone()), (a, sa.clone())] {
            g.check(&p, &[], &[], &s).unwrap();
            assert!(!g.is_complete());
            g.accumulate(&p, Vec::new(), 0, Vec::new(), s);
        }
        assert!(g.is_complete());
        let parts = g.into_parts();
        assert!(parts.counts.is_empty());
        assert_eq!(
            parts.render_scores.unwrap(),
            vec![sa[0].clone(), sb[0].clone()]
        );
        // A scored group nothing was taken from goes back to counts for a worker that does
        // not score; once taken from, it stays scored.
        let mut fresh = group(50).scored_on_workers();
        assert!(fresh.serves_counts() && !fresh.is_scored());
        assert_eq!(fresh.take(60, &mut next).unwrap().items(), 0..2);
        let mut taken = group(50).scored_on_workers();
        taken.take(60, &mut next).unwrap();
        assert!(!taken.serves_counts() && taken.is_scored());
        // A plain group takes no render scores.
        let mut plain = group(10);
        let p = plain.take(10, &mut || 1).unwrap();
        assert_eq!(p.items(), 0..2);
        let c = render(&plain, &p);
        assert!(plain
            .check(&p, &c, &[], &sa)
            .unwrap_err()
            .contains("render scores"));
    }
}
